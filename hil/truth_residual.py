"""The smoothest residual field through measured volumes, on a grid of pressures: what the simulated phantom's
truth plant adds to a truth table so that its gland volume passes through the measurements of a physical
phantom (``phantom hil plant --truth-from-scene SCENE --truth-through CSV``,
:func:`phantom.hil.plant.truth_through_measurements`). The model's own correction by measurements is a Gaussian
process (:mod:`phantom.model.corrections`); this field is the truth's, a plant that must stay a grid.

Per chamber a residual on the grid, zero while that chamber is not inflated, the gland's their sum plus one
constant; among those that meet every measurement and keep each chamber's and the gland's growth above a floor,
the smoothest (least squared second and, lightly, first differences): a quadratic programme (OSQP). The plant
interpolates its tables trilinearly (plant.c), as :func:`trilinear` does here.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from phantom.model.corrections import pressures_in_box
from phantom.model.measurements import CorrectionError

#: The field keeps each chamber's and the gland's growth per kPa at least this fraction of the table's (a phantom
#: that swells with every pressure; a pneumatic plant needs positive compliances).
MIN_GROWTH_FRACTION = 0.3
#: The weight (kPa) of the field's slope beside its curvature in its roughness: a little, so that where no
#: measurement holds it the field levels off rather than sweeping on.
FIRST_DIFFERENCE_WEIGHT = 0.3


class NoFieldError(CorrectionError):
    """No residual field passes through the measurements (two that contradict each other: different volumes at
    the same pressures, or a growth the floor forbids)."""


def trilinear(table: np.ndarray, points_kpa: ArrayLike, pressures_kpa: Sequence[float] | np.ndarray) -> np.ndarray:
    """The table (n, n, n, ...) at pressures (kPa, one per chamber), trilinear inside, the edge cell's linear
    extension outside (as the simulated board's plant.c does)."""
    n = table.shape[0]
    weights = _trilinear_weights(np.asarray(points_kpa, dtype=float), np.asarray(pressures_kpa, dtype=float))
    return np.asarray(np.tensordot(weights, table.reshape(n ** 3, *table.shape[3:]), axes=1))


def _axis_differences(n: int, axis: int, order: int) -> Any:
    """The sparse operator of forward differences (``order`` 1 or 2) along ``axis`` of an (n, n, n) grid in C
    order."""
    import scipy.sparse as sparse

    index = np.arange(n ** 3).reshape(n, n, n)
    coefficients = (-1.0, 1.0) if order == 1 else (1.0, -2.0, 1.0)
    rows, columns, values = [], [], []
    row = 0
    for cell in np.ndindex(n, n, n):
        if cell[axis] + order >= n:
            continue
        for step, value in enumerate(coefficients):
            shifted = list(cell)
            shifted[axis] += step
            rows.append(row)
            columns.append(index[tuple(shifted)])
            values.append(value)
        row += 1
    return sparse.csr_matrix((values, (rows, columns)), shape=(row, n ** 3))


def _trilinear_weights(points_kpa: np.ndarray, pressures_kpa: np.ndarray) -> np.ndarray:
    """The weights of the (n, n, n) grid's values (C order) whose sum is :func:`trilinear` at the pressures."""
    n = len(points_kpa)
    index = np.arange(n ** 3).reshape(n, n, n)
    weights = np.zeros(n ** 3)
    # the eight corners of the pressures' cell (the edge cell beyond the grid), each weighted by the product of
    # its fractions along the axes
    cells, fractions = [], []
    for pressure in pressures_kpa:
        cell = int(np.clip(np.searchsorted(points_kpa, pressure, side="right") - 1, 0, n - 2))
        cells.append(cell)
        fractions.append((pressure - points_kpa[cell]) / (points_kpa[cell + 1] - points_kpa[cell]))
    for corner in np.ndindex(2, 2, 2):
        weight = np.prod([f if c else 1.0 - f for c, f in zip(corner, fractions, strict=True)])
        weights[index[tuple(cell + c for cell, c in zip(cells, corner, strict=True))]] += weight
    return weights


@dataclass(frozen=True)
class ResidualField:
    """Per chamber a residual on the grid ``points_kpa``^3 (ml, (n, n, n, 3)) and one constant (ml): the gland's
    residual is their sum plus the constant, interpolated trilinearly."""

    points_kpa: np.ndarray
    chamber_ml: np.ndarray
    constant_ml: float

    @property
    def gland_ml(self) -> np.ndarray:
        return np.asarray(self.chamber_ml.sum(axis=-1) + self.constant_ml)

    def gland_at_ml(self, pressures_kpa: ArrayLike) -> float:
        return float(trilinear(self.gland_ml, self.points_kpa, np.asarray(pressures_kpa, dtype=float)))


def smoothest_residual(points_kpa: ArrayLike, chamber_ml: np.ndarray, gland_ml: np.ndarray, pressures_kpa: ArrayLike,
                       gaps_ml: ArrayLike, what: str = "the measurements",
                       min_growth_fraction: float = MIN_GROWTH_FRACTION,
                       growth_penalty: float | None = None) -> ResidualField:
    """The smoothest residual field over the grid that adds ``gaps_ml`` to the tabled volumes at the pressures.

    ``chamber_ml`` (n, n, n, 3) and ``gland_ml`` (n, n, n) are a model's volumes on the grid ``points_kpa`` in
    every axis. Each chamber gets its own residual, zero while that chamber is not inflated (the excess of a
    chamber's growth is that chamber's), and the gland's is their sum plus one constant. Among the residuals whose
    gland part, interpolated trilinearly, is ``gaps_ml`` at the pressures and that keep each chamber's own growth
    and the gland's growth along every pressure at least ``min_growth_fraction`` of the tabled ones, the one with
    the least squared second (and, lightly, first) differences along every axis: a quadratic programme (OSQP).
    With ``growth_penalty`` (per ml) that floor is soft: the growth may fall short of it, each ml short costing
    that much beside the roughness.

    Raises
    ------
    CorrectionError
        A pressure outside the grid or not finite.
    NoFieldError
        Measurements no field passes through (with a hard floor: no growing phantom).
    """
    import osqp
    import scipy.sparse as sparse

    points = np.asarray(points_kpa, dtype=float)
    pressures = np.atleast_2d(np.asarray(pressures_kpa, dtype=float))
    gaps = np.asarray(gaps_ml, dtype=float).ravel()
    chambers = chamber_ml.shape[-1]
    if pressures.shape != (len(gaps), chambers) or not np.all(np.isfinite(pressures)):
        raise CorrectionError(f"{what}: {chambers} finite pressures per volume are needed, got {pressures.shape[0]} "
                              f"rows of {pressures.shape[1]} for {len(gaps)} volumes")
    pressures = pressures_in_box(pressures, float(points[-1]), what)
    n = len(points)
    cells = n ** 3
    size = chambers * cells + 1            # each chamber's residual, then the constant

    def on_chamber(chamber: int, operator: Any) -> Any:
        blocks = [sparse.csr_matrix((operator.shape[0], cells)) for _ in range(chambers)]
        blocks[chamber] = operator
        return sparse.hstack([*blocks, sparse.csr_matrix((operator.shape[0], 1))])

    # the same functional on any grid: second differences / h^2 and first / h, squared, times the cell h^3
    # (h in kPa), so a finer grid refines the field instead of changing it
    spacing = float(points[1] - points[0])
    weights = ((2, spacing ** -0.5), (1, FIRST_DIFFERENCE_WEIGHT * spacing ** 0.5))
    roughness = sparse.vstack([on_chamber(chamber, weight * _axis_differences(n, axis, order))
                               for chamber in range(chambers) for axis in range(chambers) for order, weight in weights])
    rows, lower, upper = [], [], []
    grid = np.stack(np.meshgrid(*[np.arange(n)] * chambers, indexing="ij"), -1).reshape(-1, chambers)
    for chamber in range(chambers):
        uninflated = np.flatnonzero(grid[:, chamber] == 0)
        rows.append(on_chamber(chamber, sparse.identity(cells, format="csr")[uninflated]))
        lower += [0.0] * len(uninflated)
        upper += [0.0] * len(uninflated)
    for pressure, gap in zip(pressures, gaps, strict=True):
        rows.append(sparse.csr_matrix(np.concatenate([np.tile(_trilinear_weights(points, pressure), chambers), [1.0]])))
        lower.append(gap)
        upper.append(gap)
    growth_rows, growth_floor = [], []
    for axis in range(chambers):
        difference = _axis_differences(n, axis, 1)
        growth_rows.append(on_chamber(axis, difference))
        growth_floor.append(-(1 - min_growth_fraction) * (difference @ chamber_ml[..., axis].ravel()))
        growth_rows.append(sparse.hstack([difference] * chambers + [sparse.csr_matrix((difference.shape[0], 1))]))
        growth_floor.append(-(1 - min_growth_fraction) * (difference @ gland_ml.ravel()))
    growth = sparse.vstack(growth_rows)
    floor = np.concatenate(growth_floor)
    objective = roughness.T @ roughness + 1e-9 * sparse.identity(size)
    linear = np.zeros(size)
    if growth_penalty is None:
        rows.append(growth)
        lower += list(floor)
        upper += [np.inf] * len(floor)
    else:
        # a soft floor: each growth row has a slack (ml) it may fall short by, each ml costing growth_penalty (and
        # a little squared, which keeps OSQP's problem strictly convex); measurements a little noisy then bend
        # the field where they must instead of leaving none
        slacks = len(floor)
        rows = [sparse.hstack([row, sparse.csr_matrix((row.shape[0], slacks))]) for row in rows]
        rows.append(sparse.hstack([growth, sparse.identity(slacks)]))
        lower += list(floor)
        upper += [np.inf] * slacks
        rows.append(sparse.hstack([sparse.csr_matrix((slacks, size)), sparse.identity(slacks)]))
        lower += [0.0] * slacks
        upper += [np.inf] * slacks
        objective = sparse.block_diag([objective, 1e-3 * growth_penalty * sparse.identity(slacks)])
        linear = np.concatenate([linear, np.full(slacks, float(growth_penalty))])
    solver = osqp.OSQP()
    # 1e-6 (ml) is far below a scan's error (0.01 ml); at 1e-8 the scans of one verified target's rounds, at
    # nearly the same pressures, kept OSQP iterating: a fit of 9 such scans took 219 s, at 1e-6 33 s, with the
    # same leave-one-out errors to 0.001 %
    solver.setup(objective.tocsc(), linear, sparse.vstack(rows).tocsc(), np.array(lower), np.array(upper),
                 verbose=False, eps_abs=1e-6, eps_rel=1e-6, max_iter=100000, polishing=True)
    result = solver.solve(raise_error=False)
    if result.info.status not in ("solved", "solved inaccurate") or result.x is None:
        raise NoFieldError(f"no residual field passes through the volumes of {what} while every chamber and the "
                              f"gland keep growing with their pressures ({result.info.status}): check the "
                              f"measurements")
    residual = np.stack([result.x[c * cells:(c + 1) * cells].reshape(n, n, n) for c in range(chambers)], -1)
    return ResidualField(points, residual, float(result.x[size - 1]))
