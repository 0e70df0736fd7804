"""The correction of the model by the measured volumes (:mod:`phantom.model.measurements` keeps them).

:func:`fit_correction` turns them into a residual over the pressures that the model's answers are corrected
with, everywhere in the pressure box, not only at the points measured. The candidates, each fitted by least
squares to the measured minus the model's volumes:

- ``offset``: one constant (the rest volume's error: silicone, not air);
- ``growth``: a constant plus a multiple of the model's own growth above rest, what a refit of the modulus does
  to first order (the growth goes as 1/E);
- ``field``: the smoothest residual on a grid over the pressures (:func:`smoothest_residual`) that meets every
  measurement, each chamber's part zero while the chamber is not inflated, every growth kept above a floor that
  is soft (each ml short costs ``GROWTH_PENALTY``: scans a little noisy between close states bend the field
  instead of leaving none);
- ``growth+field``: the growth's fit, and the field through what it leaves.

The one with the least mean leave-one-out error over the stored measurements is used (with fewer than two,
the offset: there is nothing to leave out), and the leave-one-out errors of all are kept to be reported; a field's
kind that no field passes through (two measurements at one state that disagree) is left out, and why is kept.
:class:`CorrectedModel` applies it to a model's estimate and inverse. The module reads no scans (a scan's volume
comes from ``phantom.scan``, passed in by the command line or the daemon).
"""

from __future__ import annotations

import contextlib
import json
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from phantom import written_atomically
from phantom.model.measurements import CorrectionError, Measurement
from phantom.model.target import UnreachableTargetError

#: The field keeps each chamber's and the gland's growth per kPa at least this fraction of the model's (a phantom
#: that swells with every pressure; a pneumatic plant needs positive compliances).
MIN_GROWTH_FRACTION = 0.3
#: What a correction's field pays for each ml its growth falls short of that floor (the floor is soft there: scans
#: a little noisy between close states must not leave no field at all).
GROWTH_PENALTY: float | None = 10.0
#: A measured pressure this close outside the grid's box (kPa: two counts of the board's ADC, its settled band)
#: is on the box's edge: a chamber held at 3 kPa reads 3.01 on average, and its scan is a measurement at 3 kPa.
EDGE_SLACK_KPA = 0.1
#: A volume target this close outside the corrected model's range (ml: the corrected inverse's own tolerance) is
#: still searched for: the search meets it at the edge.
RANGE_SLACK_ML = 1e-3
#: The weight (kPa) of the field's slope beside its curvature in its roughness: a little, so that where no
#: measurement holds it the field levels off rather than sweeping on.
FIRST_DIFFERENCE_WEIGHT = 0.3
#: The candidate corrections, from the fewest parameters.
KINDS = ("offset", "growth", "field", "growth+field")


class NoFieldError(CorrectionError):
    """No residual field passes through the measurements (two that contradict each other: different volumes at
    the same pressures, or a growth the floor forbids where it is hard): the field's kinds are not fitted."""


# ----------------------------------------------------------------------------- the residual field on a grid
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


def pressures_in_box(pressures_kpa: ArrayLike, top_kpa: float, what: str = "a measurement") -> np.ndarray:
    """Measured pressures (kPa) as a state of the box 0-``top_kpa``: those within EDGE_SLACK_KPA outside it are on
    its edge (clipped to it: a chamber held at the top reads a little over it, one vented a little under 0).

    Raises
    ------
    CorrectionError
        A pressure further outside, or not finite.
    """
    pressures = np.asarray(pressures_kpa, dtype=float)
    if not np.all(np.isfinite(pressures)) or np.any(pressures < -EDGE_SLACK_KPA) \
            or np.any(pressures > top_kpa + EDGE_SLACK_KPA):
        raise CorrectionError(f"{what} must lie on the grid, 0-{top_kpa:g} kPa, the model's pressure box "
                              f"({EDGE_SLACK_KPA:g} kPa outside it is on its edge), got "
                              f"{np.round(pressures, 4).tolist()}")
    clipped: np.ndarray = np.clip(pressures, 0.0, top_kpa)
    return clipped


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


# ----------------------------------------------------------------------------- the correction
@dataclass(frozen=True)
class ModelGrid:
    """A model's volumes (ml) on a grid of pressures (kPa, the same on every axis), where a field lives, and its
    gland volume anywhere (``gland_ml(pressures_kpa)``: the model's own estimate, e.g. its VolumeEstimator)."""

    points_kpa: np.ndarray
    chamber_ml: np.ndarray     # (n, n, n, 3)
    gland_grid_ml: np.ndarray  # (n, n, n)
    gland_ml: Callable[[np.ndarray], float]
    description: str = ""


@dataclass(frozen=True)
class Correction:
    """A residual over the pressures (see the module docstring): ``kind``, fitted to ``count`` measurements,
    ``offset_ml`` + ``growth_factor`` x the model's growth above rest + ``residual_field`` (a field kind's);
    ``leave_one_out_pct``: the mean leave-one-out error (% of the volume) of each candidate that had enough
    measurements for it; ``uncorrected_pct``: the model's own mean error on them (%)."""

    kind: str
    count: int
    offset_ml: float = 0.0
    growth_factor: float = 0.0
    residual_field: ResidualField | None = None
    leave_one_out_pct: dict[str, float] = field(default_factory=dict)
    uncorrected_pct: float = 0.0
    #: the kinds asked for that no field could be fitted for, and why (:class:`NoFieldError`)
    unfitted: dict[str, str] = field(default_factory=dict)

    def residual_ml(self, pressures_kpa: ArrayLike, model_growth_ml: float) -> float:
        """What to add to the model's gland volume at these pressures, where the model grew ``model_growth_ml``
        above its rest."""
        value = self.offset_ml + self.growth_factor * model_growth_ml
        if self.residual_field is not None:
            value += self.residual_field.gland_at_ml(pressures_kpa)
        return float(value)

    def size_ml(self, grid: ModelGrid) -> float:
        """The correction's largest magnitude over the grid's box (ml): how far the model was from the
        measurements anywhere."""
        rest = float(grid.gland_grid_ml[0, 0, 0])
        n = len(grid.points_kpa)
        return max(abs(self.residual_ml(grid.points_kpa[list(index)], float(grid.gland_grid_ml[index]) - rest))
                   for index in np.ndindex(n, n, n))

    def to_json(self) -> dict[str, Any]:
        """For the daemon's status and the report: the kind, from how many measurements, the leave-one-out."""
        return {"kind": self.kind, "measurements": self.count, "offset_ml": self.offset_ml,
                "growth_factor": self.growth_factor, "field": self.residual_field is not None,
                "leave_one_out_pct": dict(self.leave_one_out_pct), "uncorrected_pct": self.uncorrected_pct,
                "unfitted": dict(self.unfitted)}

    def to_document(self) -> dict[str, Any]:
        """Everything the correction is, its field's values included, as JSON (:meth:`from_document` reads it)."""
        residual = self.residual_field
        return {**asdict(self), "residual_field": None if residual is None else {
            "points_kpa": residual.points_kpa.tolist(), "chamber_ml": residual.chamber_ml.tolist(),
            "constant_ml": residual.constant_ml}}

    @classmethod
    def from_document(cls, document: dict[str, Any]) -> Correction:
        """The correction :meth:`to_document` wrote."""
        residual = document["residual_field"]
        return cls(**{**document, "residual_field": None if residual is None else ResidualField(
            np.asarray(residual["points_kpa"], dtype=float), np.asarray(residual["chamber_ml"], dtype=float),
            float(residual["constant_ml"]))})

    def summary(self, grid: ModelGrid) -> dict[str, Any]:
        """:meth:`to_json` with the correction's size over the grid's box (``size_ml``, :meth:`size_ml`) and the
        number of measurements (``count``): what the daemon reports of the correction in force."""
        return self.to_json() | {"size_ml": self.size_ml(grid), "count": self.count}


#: The fewest measurements each kind is fitted to (its leave-one-out needs one more).
MIN_MEASUREMENTS = {"offset": 1, "growth": 2, "field": 1, "growth+field": 2}


def _fit_kind(kind: str, pressures_kpa: np.ndarray, volumes_ml: np.ndarray, model_ml: np.ndarray, rest_ml: float,
              grid: ModelGrid, what: str) -> Correction:
    gaps = volumes_ml - model_ml
    growth = model_ml - rest_ml
    offset, factor = float(np.mean(gaps)), 0.0
    if kind in ("growth", "growth+field"):
        (offset, factor), *_ = np.linalg.lstsq(np.column_stack([np.ones_like(growth), growth]), gaps, rcond=None)
    if kind == "field":
        offset = 0.0
    residual_field = None
    if kind in ("field", "growth+field"):
        left = gaps - offset - factor * growth
        residual_field = smoothest_residual(grid.points_kpa, grid.chamber_ml, grid.gland_grid_ml, pressures_kpa, left,
                                            what, MIN_GROWTH_FRACTION, GROWTH_PENALTY)
    return Correction(kind, len(volumes_ml), float(offset), float(factor), residual_field)


def fit_correction(measurements: Sequence[Measurement], grid: ModelGrid,
                   kinds: Sequence[str] = KINDS) -> Correction:
    """The correction of the model (``grid``) by the measurements: of ``kinds``, the one with the least mean
    leave-one-out error (see the module docstring); a field's kind no field passes through is left out
    (``unfitted`` says why). CorrectionError when there are no measurements, or none of ``kinds`` fits."""
    if not measurements:
        raise CorrectionError("no measurements to correct the model with: scan the phantom first")
    unknown = sorted(set(kinds) - set(KINDS))
    if unknown:
        raise CorrectionError(f"unknown correction kinds {unknown}: choose from {', '.join(KINDS)}")
    pressures = np.array([m.pressures_kpa for m in measurements], dtype=float)
    if pressures.shape[1] != grid.chamber_ml.shape[-1]:
        raise CorrectionError(f"the measurements have {pressures.shape[1]} pressures, the model "
                              f"{grid.chamber_ml.shape[-1]} chambers: they are of another phantom")
    volumes = np.array([m.volume_ml for m in measurements], dtype=float)
    model_ml = np.array([grid.gland_ml(p) for p in pressures])
    rest_ml = grid.gland_ml(np.zeros(pressures.shape[1]))
    what = f"{len(volumes)} measurements"
    leave_one_out: dict[str, float] = {}
    unfitted: dict[str, str] = {}
    fits: dict[str, Correction] = {}
    count = len(volumes)
    for kind in kinds:
        if count < MIN_MEASUREMENTS[kind]:
            continue
        try:
            fits[kind] = _fit_kind(kind, pressures, volumes, model_ml, rest_ml, grid, what)
            if count < MIN_MEASUREMENTS[kind] + 1:
                continue
            errors = []
            for left_out in range(count):
                keep = np.arange(count) != left_out
                fitted = _fit_kind(kind, pressures[keep], volumes[keep], model_ml[keep], rest_ml, grid, what)
                predicted = model_ml[left_out] + fitted.residual_ml(pressures[left_out], model_ml[left_out] - rest_ml)
                errors.append(abs(predicted - volumes[left_out]) / volumes[left_out] * 100)
            leave_one_out[kind] = float(np.mean(errors))
        except NoFieldError as error:  # only a field's kinds raise it: the others are still chosen among
            fits.pop(kind, None)
            unfitted[kind] = str(error)
    if not fits:
        raise CorrectionError(f"{count} measurement(s) fit none of {', '.join(kinds)}: "
                              + ("; ".join(unfitted.values()) if unfitted else "store more"))
    best = (min(leave_one_out, key=lambda kind: leave_one_out[kind]) if leave_one_out else next(iter(fits)))
    correction = fits[best]
    uncorrected = float(np.mean(np.abs(volumes - model_ml) / volumes * 100))
    return Correction(correction.kind, count, correction.offset_ml, correction.growth_factor,
                      correction.residual_field, leave_one_out, uncorrected, unfitted)


#: Bumped when what a cached fit holds, or how a fit is made, changes.
FIT_CACHE_VERSION = 2


def cached_fit(measurements: Sequence[Measurement], grid: ModelGrid) -> Correction:
    """:func:`fit_correction`, kept in the cache folder ``corrections`` keyed by the measurements and the model's
    grid (its volumes), so that a daemon started again with many stored measurements does not fit them again
    (17-28 s for 27 on this machine, a few ms read back). A cached file that cannot be read is fitted again."""
    import hashlib

    from phantom import cache_dir

    digest = hashlib.sha256(json.dumps({"version": FIT_CACHE_VERSION, "kinds": KINDS,
                                        "min_growth_fraction": MIN_GROWTH_FRACTION,
                                        "growth_penalty": GROWTH_PENALTY,
                                        "first_difference_weight": FIRST_DIFFERENCE_WEIGHT,
                                        "measurements": [asdict(m) for m in measurements]},
                                       sort_keys=True).encode())
    for array in (grid.points_kpa, grid.chamber_ml, grid.gland_grid_ml):
        digest.update(np.ascontiguousarray(array, dtype=float).tobytes())
    path = cache_dir("corrections") / f"{digest.hexdigest()[:24]}.json"
    with contextlib.suppress(OSError, ValueError, KeyError, TypeError):
        return Correction.from_document(json.loads(path.read_text()))
    correction = fit_correction(measurements, grid)
    with contextlib.suppress(CorrectionError, OSError), written_atomically(path, CorrectionError) as temporary:
        temporary.write_text(json.dumps(correction.to_document()))
    return correction


#: Asked volumes this close (ml) on either side of a target the corrected volume does not meet between them: a
#: jump along the inverse's path (:meth:`CorrectedModel.pressures_for_ml`).
JUMP_ML = 1e-4


class CorrectedModel:
    """A model's gland volume and inverse with a correction applied (the daemon's model can wrap its own).

    ``grid.gland_ml`` is the model's estimate; ``pressures_for_ml`` wraps any inverse (``inverse(volume_ml)`` ->
    pressures in kPa) by asking it for another volume, moved by secant steps, until the corrected volume at its
    answer meets the target: the correction is smooth and small beside the growth, so this converges in a few
    rounds."""

    def __init__(self, grid: ModelGrid, correction: Correction):
        self.grid = grid
        self.correction = correction
        chambers = grid.chamber_ml.shape[-1]
        self.rest_ml = grid.gland_ml(np.zeros(chambers))
        #: the model's largest volume in the box: with the rest, the range the inverse is asked within
        self.top_ml = grid.gland_ml(np.full(chambers, float(grid.points_kpa[-1])))
        #: the corrected volumes at rest and at the box's top: the range of volume targets with the correction
        self.range_ml = (self.corrected_ml(np.zeros(chambers), self.rest_ml),
                         self.corrected_ml(np.full(chambers, float(grid.points_kpa[-1])), self.top_ml))

    def describe(self) -> str:
        """The correction in words, for messages: its kind and from how many measurements."""
        return f"{self.correction.kind} from {self.correction.count} measurement(s)"

    def gland_ml(self, pressures_kpa: ArrayLike) -> float:
        """The corrected gland volume (ml) at these pressures (kPa)."""
        pressures = np.asarray(pressures_kpa, dtype=float)
        return self.corrected_ml(pressures, self.grid.gland_ml(pressures))

    def corrected_ml(self, pressures_kpa: ArrayLike, model_ml: float) -> float:
        """The corrected gland volume (ml) at these pressures (kPa), where the model's own is ``model_ml`` (a caller
        that has it already spares the model a second evaluation)."""
        return float(model_ml) + self.correction.residual_ml(pressures_kpa, float(model_ml) - self.rest_ml)

    def pressures_for_ml(self, volume_ml: float, inverse: Callable[[float], np.ndarray],
                         tolerance_ml: float = 1e-3, max_rounds: int = 30) -> tuple[np.ndarray, float, int]:
        """Pressures (kPa) whose corrected gland volume is ``volume_ml``, that volume, and the inverse's rounds.

        Raises
        ------
        UnreachableTargetError
            ``volume_ml`` beyond the corrected range (:attr:`range_ml`, stated as "give LOW to HIGH ml" and held as
            its ``gland_range_ml``, whose edge the daemon's verify loop asks), though perhaps inside the model's
            own: one scan near rest corrects by an offset the phantom at rest does not hold, and searched for, such
            a target met nothing.
        CorrectionError
            The search did not converge (the target at the edge of the reachable range).
        """
        low_ml, high_ml = self.range_ml
        if not low_ml - RANGE_SLACK_ML <= volume_ml <= high_ml + RANGE_SLACK_ML:
            raise UnreachableTargetError(f"{volume_ml:.2f} ml is beyond the model's range with the correction in force "
                                         f"({self.describe()}): give {low_ml:.3f} to {high_ml:.3f} ml",
                                         gland_range_ml=(low_ml, high_ml), corrected=True)
        # within the model's range from the first ask: the corrected range may reach past the model's
        asked = float(np.clip(volume_ml, self.rest_ml, self.top_ml))
        previous: tuple[float, float] | None = None
        # once the target is bracketed, the asked volumes below and above it with their misses (ml), and which end
        # was replaced last: regula falsi, Illinois (an end kept twice counts its miss half), since the inverse's
        # path has kinks (one chamber's pressure turning) where secant steps from one side crawl
        ends: dict[str, tuple[float, float, np.ndarray]] = {}
        replaced, halved = "", {"below": 1.0, "above": 1.0}
        for rounds in range(1, max_rounds + 1):
            pressures = np.asarray(inverse(asked), dtype=float)
            corrected = self.gland_ml(pressures)
            miss = corrected - volume_ml
            if abs(miss) <= tolerance_ml:
                return pressures, corrected, rounds
            side = "below" if miss < 0 else "above"
            ends[side] = (asked, miss, pressures)
            halved[side] = 1.0
            if len(ends) == 2:
                other = "above" if side == "below" else "below"
                if side == replaced:
                    halved[other] /= 2
                replaced = side
                (low, low_miss, _), (high, high_miss, _) = ends["below"], ends["above"]
                if abs(high - low) <= JUMP_ML:
                    # the target lies in a jump of the corrected volume along the inverse's path (the inverse
                    # turns to another branch there, and the correction differs between the two): the nearer end
                    _, miss, pressures = min(ends.values(), key=lambda end: abs(end[1]))
                    return pressures, volume_ml + miss, rounds
                low_miss, high_miss = low_miss * halved["below"], high_miss * halved["above"]
                asked = low - low_miss * (high - low) / (high_miss - low_miss)
                continue
            # secant steps: the corrected volume's slope in the asked one (1 at first: a constant correction)
            slope = 1.0
            if previous is not None and previous[0] != asked:
                slope = float(np.clip((corrected - previous[1]) / (asked - previous[0]), 0.2, 5.0))
            previous = (asked, corrected)
            # within the model's range: near rest or the top a step may overshoot it (a phantom that grows faster
            # than the model at first asked the model for less than its rest)
            asked = float(np.clip(asked - miss / slope, self.rest_ml, self.top_ml))
        raise CorrectionError(f"the corrected inverse did not meet {volume_ml:g} ml in {max_rounds} rounds (last "
                              f"{corrected:.3f} ml): the target is at the edge of what the phantom reaches")


def model_grid(estimator: Any, description: str = "") -> ModelGrid:
    """A model's grid from its estimator (``phantom.model.fidelity.levels.VolumeEstimator``): the grid of its
    response table (the table level's own, else the model's table, built and cached on first use), and the
    estimator's gland volume anywhere."""
    from phantom.model.fidelity.response_table import grid_pa, response_table

    table = estimator.table if estimator.table is not None else response_table(estimator.model,
                                                                               estimator.pressure_max_pa)
    points_kpa = grid_pa(table.pressure_max_pa, table.gland_values.shape[0]) / 1e3

    def gland_ml(pressures_kpa: np.ndarray) -> float:
        return float(estimator.volumes(np.asarray(pressures_kpa, dtype=float) * 1e3)[1] * 1e6)

    return ModelGrid(points_kpa, 1e6 * np.asarray(table.chamber_values), 1e6 * np.asarray(table.gland_values),
                     gland_ml, description)
