"""How typical the designed gland is of a population: its latent distance to the population's average.

A trained shape run (``phantom shape train``) holds each case's latent vector; the population's average is their
mean (the latent :meth:`~phantom.shape.analysis.ShapeModel.average` decodes). The source is encoded by the run's
own encoder as ``phantom shape`` encodes a file (its labels, its grid), and its distance to the average is given
in latent units, in units of the population's spread (the root-mean-square distance of the run's cases to the
average) and as a percentile (the share of the run's cases that lie no farther from the average).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from phantom.design.errors import DesignError
from phantom.model.arrays import FloatArray


@dataclass(frozen=True)
class LatentDistance:
    """The source's latent distance to the population's average: in latent units, in spreads, and its percentile
    among the run's ``cases``."""

    run: str
    distance: float
    spread: float
    percentile: float
    cases: int

    @property
    def in_spreads(self) -> float:
        return self.distance / self.spread


def distance_to_average(latent: FloatArray, case_latents: FloatArray, run: str = "") -> LatentDistance:
    """``latent``'s distance to the mean of ``case_latents (N, L)``; see the module docstring."""
    if len(case_latents) < 2:
        raise DesignError(f"the shape run {run} has {len(case_latents)} case(s): a population's spread needs two or "
                          f"more; train it on the data set (phantom shape train)")
    average = case_latents.mean(axis=0)
    case_distances = np.linalg.norm(case_latents - average, axis=1)
    spread = float(np.sqrt(np.mean(case_distances**2)))
    if spread == 0.0:
        raise DesignError(f"the shape run {run}'s cases all have one latent vector: it has not learnt the shapes "
                          f"apart; train it longer")
    distance = float(np.linalg.norm(latent - average))
    return LatentDistance(run, distance, spread, float(100.0 * np.mean(case_distances <= distance)),
                          len(case_latents))


def latent_distance(source: str | Path, run: str | Path) -> LatentDistance:
    """The source file's latent distance to the average of the trained run ``run`` (its encoder, its cases)."""
    from phantom.shape.analysis import ShapeModel

    model = ShapeModel.load(run)
    _, case_latents = model.case_latents()
    return distance_to_average(model.encode_file(source), case_latents, str(run))
