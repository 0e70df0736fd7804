"""The phantom's reach over a population: for each case, the pressures that make the phantom look most like it and
how close that is (:mod:`phantom.model.shape_inverse`), as a table, a histogram and a picture of the latent space.

A population is a shape dataset (the pelvic MRI layout, a folder of masks or closed meshes: each case), or a
trained run's cluster centres (``phantom shape clusters``: each centre decoded). A case is *covered* when the
phantom comes within ``within_mm`` of it (the symmetric mean closest-point distance at the best pressures):
whether one phantom can serve a training curriculum is the share of its cases it covers. The latent picture puts
the cases (encoded by a run's encoder) on the plane of the latent vectors' two leading principal components,
coloured by whether they are covered; without a run there is no latent space, and no picture of it.
"""

from __future__ import annotations

import csv
import json
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from phantom import require_extra
from phantom.model.mesh.surface import TriangleMesh
from phantom.model.shape_file import read_target_surface
from phantom.model.shape_inverse import ShapeInverse
from phantom.shape.dataset import PROSTATE_LABELS, find_cases
from phantom.shape.errors import ShapeError

#: A case is covered when the phantom comes this close to it (mm, symmetric mean distance), by default: about a
#: 3D scanner's accuracy and a tenth of the population's spread of sizes on a 26 ml gland.
WITHIN_MM = 1.0


@dataclass
class ReachCase:
    """One case: its name, volume (ml), the best pressures (kPa), the distance at rest and at them (mm), whether it
    is covered, the chambers at the box's limit, and its latent vector (None without a run)."""

    name: str
    volume_ml: float
    pressures_kpa: list[float]
    rest_distance_mm: float
    distance_mm: float
    covered: bool
    at_limit: list[str]
    time_s: float
    latent: np.ndarray | None = field(default=None, repr=False)


def population(source: str | Path, labels: tuple[int, ...] | None = None) -> list[tuple[str, TriangleMesh]]:
    """The cases of a dataset folder (or one file), each read as a target gland (mm, the phantom's frame): a label
    map's ``labels`` (default the prostate's, 4 and 5), a binary mask's voxels, or a closed mesh."""
    cases = find_cases(source)
    surfaces = []
    for case in cases:
        chosen = (labels or PROSTATE_LABELS) if case.kind == "labels" else labels
        surfaces.append((case.name, read_target_surface(case.path, list(chosen) if chosen else None)))
    return surfaces


def reach(inverse: ShapeInverse, cases: list[tuple[str, TriangleMesh]], within_mm: float = WITHIN_MM,
          refine_solves: int = 0, scale: bool = False,
          progress: Callable[[str], None] | None = None) -> list[ReachCase]:
    """Each case's best pressures and distances (see the module)."""
    if not within_mm > 0:
        raise ShapeError(f"--within-mm must be a positive distance, got {within_mm}")
    say = progress or (lambda message: None)
    results = []
    for index, (name, surface) in enumerate(cases):
        started = time.perf_counter()
        answer = inverse.solve(surface, refine_solves, scale=scale)
        results.append(ReachCase(name, answer.target_volume_ml, (answer.pressures_pa / 1e3).tolist(),
                                 answer.rest_distance_mm, answer.distance_mm, answer.distance_mm <= within_mm,
                                 answer.at_limit, time.perf_counter() - started))
        say(f"shape reach: {index + 1}/{len(cases)} {name}: {answer.target_volume_ml:.1f} ml, "
            f"{answer.rest_distance_mm:.2f} -> {answer.distance_mm:.2f} mm at "
            f"{', '.join(f'{value / 1e3:.2f}' for value in answer.pressures_pa)} kPa")
    return results


def summary(cases: list[ReachCase], within_mm: float) -> dict[str, Any]:
    """The population's figures: how many cases are covered, the distances' quartiles before and after."""
    before = np.array([case.rest_distance_mm for case in cases])
    after = np.array([case.distance_mm for case in cases])
    return {"cases": len(cases), "within_mm": within_mm, "covered": int(sum(case.covered for case in cases)),
            "covered_at_rest": int(np.sum(before <= within_mm)),
            "rest_distance_mm": {"median": float(np.median(before)), "max": float(before.max())},
            "distance_mm": {"median": float(np.median(after)), "max": float(after.max())},
            "time_s": float(sum(case.time_s for case in cases))}


def write_reach(cases: list[ReachCase], out: Path, within_mm: float, title: str,
                background_latents: np.ndarray | None = None) -> dict[str, str]:
    """``reach.csv`` (one row a case), ``reach.json`` (the same and :func:`summary`), the histogram of the distances
    before and after (``reach_histogram.png``) and, when the cases have latent vectors, their picture
    (``reach_latent.png``; ``background_latents``: a run's cases, drawn grey behind cluster centres)."""
    with require_extra("shape"):
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

    out.mkdir(parents=True, exist_ok=True)
    files = {"table": str(out / "reach.csv"), "json": str(out / "reach.json"),
             "histogram": str(out / "reach_histogram.png")}
    with open(files["table"], "w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(["case", "volume_ml", "pressure0_kpa", "pressure1_kpa", "pressure2_kpa", "rest_distance_mm",
                         "distance_mm", f"covered_within_{within_mm:g}_mm", "at_limit"])
        for case in cases:
            writer.writerow([case.name, f"{case.volume_ml:.3f}", *(f"{value:.3f}" for value in case.pressures_kpa),
                             f"{case.rest_distance_mm:.4f}", f"{case.distance_mm:.4f}", case.covered,
                             "; ".join(case.at_limit)])
    figure, axis = plt.subplots(figsize=(6.4, 4.0), layout="constrained")
    before = [case.rest_distance_mm for case in cases]
    after = [case.distance_mm for case in cases]
    bins = np.linspace(0.0, max(max(before), max(after), within_mm) * 1.05, 25).tolist()
    axis.hist(before, bins, alpha=0.55, label="at rest", color="tab:grey")
    axis.hist(after, bins, alpha=0.75, label="at the best pressures", color="tab:blue")
    axis.axvline(within_mm, color="tab:red", linestyle="--", label=f"covered: within {within_mm:g} mm")
    axis.set_xlabel("symmetric mean closest-point distance to the case (mm)")
    axis.set_ylabel("cases")
    axis.set_title(title, fontsize=9)
    axis.legend(fontsize=8)
    figure.savefig(files["histogram"], dpi=110)
    plt.close(figure)
    latents = [case.latent for case in cases]
    if all(latent is not None for latent in latents) and cases:
        files["latent"] = str(out / "reach_latent.png")
        _latent_picture(np.array(latents), cases, within_mm, files["latent"], title, background_latents, plt)
    with open(files["json"], "w") as handle:
        json.dump({"summary": summary(cases, within_mm), "files": files,
                   "cases": [{"case": case.name, "volume_ml": case.volume_ml, "pressures_kpa": case.pressures_kpa,
                              "rest_distance_mm": case.rest_distance_mm, "distance_mm": case.distance_mm,
                              "covered": case.covered, "at_limit": case.at_limit} for case in cases]}, handle,
                  indent=1)
    return files


def _latent_picture(latents: np.ndarray, cases: list[ReachCase], within_mm: float, path: str, title: str,
                    background: np.ndarray | None, plt: Any) -> None:
    """The cases on the plane of the latent vectors' two leading principal components, covered or not."""
    every = latents if background is None else np.vstack([background, latents])
    centre = every.mean(axis=0)
    _, _, axes = np.linalg.svd(every - centre, full_matrices=False)
    plane = axes[:2].T if len(axes) >= 2 else np.eye(latents.shape[1])[:, :2]
    figure, axis = plt.subplots(figsize=(6.0, 5.0), layout="constrained")
    if background is not None:
        points = (background - centre) @ plane
        axis.scatter(points[:, 0], points[:, 1], s=8, color="lightgrey", label="the run's cases")
    points = (latents - centre) @ plane
    covered = np.array([case.covered for case in cases])
    distance = np.array([case.distance_mm for case in cases])
    marker = 40 if background is None else 120
    axis.scatter(points[covered, 0], points[covered, 1], s=marker, color="tab:green", edgecolor="black",
                 label=f"covered (within {within_mm:g} mm)")
    axis.scatter(points[~covered, 0], points[~covered, 1], s=marker, color="tab:red", edgecolor="black",
                 label="not covered")
    for point, value in zip(points, distance, strict=True):
        axis.annotate(f"{value:.1f}", point, fontsize=6, xytext=(3, 3), textcoords="offset points")
    axis.set_xlabel("latent principal component 1")
    axis.set_ylabel("latent principal component 2")
    axis.set_title(f"{title}\n(numbers: distance at the best pressures, mm)", fontsize=9)
    axis.legend(fontsize=8)
    figure.savefig(path, dpi=110)
    plt.close(figure)
