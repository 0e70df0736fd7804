"""Calibration of material and geometry to measured gland volumes, with leave-one-out cross-validation.

Parameters: Young's modulus E and a grid of others (``NAME=v1,v2,...``): material parameters (``gent_jm``) and
geometry parameters of the built-in prostate (``base_chamber_scale``, ``lobe_chamber_scale``, any key of
:class:`phantom.model.mesh.geometry.ProstateGeometry`).

E is a load factor. For every law the model has, at fixed Poisson ratio (the fixation springs are a multiple of
E too), the state at pressures p and modulus E is the one at ``t p`` and the scene's modulus E0, ``t = E0 / E``.
So each measured pressure ray is traced once per grid point over ``t``
(:mod:`phantom.model.calibration.sweep`: Dask tasks, cached on disk), and the volume of every ray is then known
at every (grid point, t). The fit is

    minimise  sum_j ((G_j(theta, t) - m_j) / m_j)^2   over theta in the grid's box and t > 0,

with G interpolated: monotone cubic in t along each trace, multilinear in theta between grid points (a search
over every grid point and t, then a bounded refinement). Leave-one-out refits everything (theta and E) without
each point and predicts it from the same traces: it solves nothing more.

A calibration anchored on the material gives E a band (``modulus_band_pa``: the silicone's published modulus
and its spread, e.g. Ecoflex 00-10's 50 kPa +/- 40 %): t is then bounded to ``[E0 / E_high, E0 / E_low]`` in the
fit and in every leave-one-out refit, the geometry takes up what the band cannot, and a fit held at an edge of
the band says so (``binding``): the data ask for a material outside it.

Physical validity is a constraint, not a hope: only measurements at pressures within PRESSURE_LIMIT_PA are
used, and a (theta, t) is admissible only where, on every fitted ray, no element is inverted (det F > 0), the
principal stretches stay inside the law's stated range (:data:`LAW_STRETCH_RANGE`) and, for the Gent law,
``I1 - 3`` stays below GENT_LIMIT_FRACTION of ``Jm``. The fit is then checked by full solves at the fitted
parameters (a new mesh for a new geometry): the fit errors reported are those solves', and a fit whose solves
break a constraint is refused with the reason.
"""

from __future__ import annotations

import copy
import csv
import dataclasses
import itertools
import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from phantom import PhantomError, read_text
from phantom.model.arrays import BoolArray, FloatArray
from phantom.model.calibration.sweep import RayTask, RayTrace, cached_trace, run_sweep
from phantom.model.errors import MeshError
from phantom.model.fem.model import PhantomModel
from phantom.model.measurements import gland_volume_problem
from phantom.model.mesh.geometry import ProstateGeometry, geometry_from_table
from phantom.model.mesh.shape import check_walls
from phantom.model.scene import (
    HYPERELASTIC_MODELS,
    MEDIA,
    PRESSURE_LIMIT_PA,
    Scene,
    scene_from_dict,
    without_shipped_tables,
)

#: The largest measurement file read (bytes): a table of thousands of rows is far smaller.
MAX_MEASUREMENT_BYTES = 2**20

#: A ray's trace stops once its gland growth exceeds this multiple of the measured growth.
OVERSHOOT = 1.8
#: Load-factor steps per rest-compliance estimate of t, and the largest t traced, in those estimates. The
#: hyperelastic fits land near a third of that estimate (inflation softens), so a quarter of it left one or two
#: traced steps below the fit and the traces' interpolation there up to 1.3 ml (3 %) off the full solves.
STEPS_PER_LINEAR_LOAD_FACTOR = 12
MAX_LINEAR_MULTIPLE = 4.0
#: Points of the fine load-factor grid the traces are interpolated onto.
FINE_LOAD_FACTOR_POINTS = 300
#: Principal stretches inside which each law is stated to hold: 10 % strain for the small-strain laws; the
#: Neo-Hookean law follows silicone rubber to about twice its length; the Gent law's limit is its Jm; a Yeoh
#: law holds over the stretches its coefficients were fitted to, taken here as Neo-Hookean's.
LAW_STRETCH_RANGE = {"linear": (0.9, 1.1), "corotational": (0.9, 1.1), "neo_hookean": (0.5, 2.0),
                     "gent": (0.0, float("inf")), "yeoh": (0.5, 2.0)}
#: The Gent law's energy diverges at I1 - 3 = Jm; an admissible state keeps this margin from it.
GENT_LIMIT_FRACTION = 0.95
#: Parameters that are material keys (everything else named in a grid is a [geometry] key).
MATERIAL_PARAMETERS = ("gent_jm", "poisson_ratio")
#: The refinement's cost of a state that is inadmissible or beyond the traces: finite (an infinite cost derails
#: the Powell line searches, which span the whole box) and above any fit's (8 points 100 % off cost 8).
INADMISSIBLE_COST = 1e6


class CalibrationError(PhantomError):
    """Bad measurement file, or a calibration the data cannot support."""


@dataclass(frozen=True)
class Measurements:
    """Measured gland volumes (m^3) at chamber pressures (Pa), one row per experiment, and where each was
    measured (``media``: one of :data:`~phantom.model.scene.MEDIA` per row; empty means every row in air)."""

    pressures_pa: np.ndarray       # (k, n_chambers)
    volumes_m3: np.ndarray         # (k,)
    path: str = ""
    media: tuple[str, ...] = ()

    def medium(self, row: int) -> str:
        """Where row ``row`` was measured: hanging in air from the tube junction (the default) or in water."""
        return self.media[row] if self.media else "air"


#: The files a ``measured_ml`` entry may name instead of a number: scans of the phantom.
SCAN_SUFFIXES = (".obj", ".ply", ".stl")

#: The volume (ml) of a scan file (mm): ``phantom.scan.compare.scan_volume_ml``, which the command line passes.
ScanVolume = Callable[[Path], float]
#: ``progress(done, total)``: how a sweep goes.
Progress = Callable[[int, int], None]


def load_measurements(path: str | Path, n_chambers: int | None = None,
                      scan_volume_ml: ScanVolume | None = None) -> Measurements:
    """Read a CSV with columns ``p0_kpa, p1_kpa, ..., measured_ml`` (``#`` lines are comments), and optionally
    ``medium``: where the phantom hung when it was measured, ``air`` (the default, also for a blank entry) or
    ``water`` (which leaves only the silicone's density excess over water's as its weight).

    A ``measured_ml`` entry may instead name a scan file (.obj, .ply or .stl, in mm, relative to the CSV's
    folder): ``scan_volume_ml(file)`` measures it (``phantom calibrate`` passes the scan comparison's cleaned,
    watertight volume; the model itself reads no scans).

    Raises
    ------
    CalibrationError
        Missing file or columns, non-numeric, non-finite or negative values, a volume no whole gland has (one in
        ul or litres: the row and the unit are named), a chamber count that does not match the model, fewer than
        three rows, or a scan file with no ``scan_volume_ml`` to measure it.
    """
    path = Path(path)
    text = read_text(path, MAX_MEASUREMENT_BYTES, "the measurement file", CalibrationError)
    lines = [line for line in text.splitlines() if line.strip() and not line.lstrip().startswith("#")]
    if not lines:
        raise CalibrationError(f"{path} holds no data: expected a header p0_kpa,p1_kpa,...,measured_ml and rows")
    reader = csv.DictReader(lines)
    header = [name.strip() for name in reader.fieldnames or []]
    pressure_columns = sorted((name for name in header if name.startswith("p") and name.endswith("_kpa")),
                              key=lambda name: int(name[1:-4]) if name[1:-4].isdigit() else 10**6)
    if "measured_ml" not in header or not pressure_columns:
        raise CalibrationError(f"{path} needs columns p0_kpa, p1_kpa, ... and measured_ml; it has {header}")
    expected = [f"p{index}_kpa" for index in range(len(pressure_columns))]
    if pressure_columns != expected:
        raise CalibrationError(f"{path}: pressure columns must be {expected}, got {pressure_columns}")
    if n_chambers is not None and len(pressure_columns) != n_chambers:
        raise CalibrationError(f"{path} has {len(pressure_columns)} pressure columns but the model has "
                               f"{n_chambers} chambers")
    rows_kpa: list[list[float]] = []
    rows_ml: list[float] = []
    media: list[str] = []
    for line_number, row in enumerate(reader, start=2):
        row = {key.strip(): value for key, value in row.items() if key is not None}
        medium = (row.get("medium") or "").strip().lower() or "air"
        if medium not in MEDIA:
            raise CalibrationError(f"{path}, data row {line_number - 1}: medium {medium!r} is not one of "
                                   f"{', '.join(MEDIA)} (where the phantom hung when it was measured; blank: air)")
        media.append(medium)
        try:
            rows_kpa.append([float(row[name]) for name in pressure_columns])
            rows_ml.append(_measured_volume_ml(row["measured_ml"], path.parent, scan_volume_ml,
                                               f"{path}, data row {line_number - 1}"))
        except (TypeError, ValueError) as error:
            raise CalibrationError(f"{path}, data row {line_number - 1}: not a number ({error})") from None
    pressures_kpa, volumes_ml = np.array(rows_kpa), np.array(rows_ml)
    if not (np.all(np.isfinite(pressures_kpa)) and np.all(np.isfinite(volumes_ml))):
        raise CalibrationError(f"{path} holds non-finite values (nan or inf): fix the measurements")
    if np.any(pressures_kpa < 0):
        raise CalibrationError(f"{path} holds negative pressures: the blowers only push, gauge pressures are >= 0")
    if np.any(volumes_ml <= 0):
        raise CalibrationError(f"{path} holds volumes <= 0 ml: fix the measurements")
    if len(volumes_ml) < 3:
        raise CalibrationError(f"{path} has {len(volumes_ml)} rows: a fit with leave-one-out needs at least 3")
    return Measurements(pressures_kpa * 1e3, volumes_ml * 1e-6, str(path), tuple(media))


def _measured_volume_ml(entry: str | None, folder: Path, scan_volume_ml: ScanVolume | None, where: str) -> float:
    """A ``measured_ml`` entry: a number, or a scan file whose volume ``scan_volume_ml`` measures. A number outside a
    whole gland's volumes (:data:`~phantom.model.shape_file.GLAND_VOLUME_RANGE_ML`, the corrections store's range)
    is refused, naming the unit that makes it one (30000: mm^3), before any fit."""
    text = (entry or "").strip()
    if Path(text).suffix.lower() not in SCAN_SUFFIXES:
        volume_ml = float(text)
        # the store's check of a measured volume (phantom corrections add); <= 0, nan: the file's own check
        if np.isfinite(volume_ml) and volume_ml > 0 and (problem := gland_volume_problem(volume_ml, "measured_ml")):
            raise CalibrationError(f"{where}: {problem}")
        return volume_ml
    if scan_volume_ml is None:
        raise CalibrationError(f"{where}: {text} is a scan file, and nothing here measures scans: pass "
                               "load_measurements a scan_volume_ml (phantom calibrate uses the scan comparison's)")
    return scan_volume_ml(folder / text)


def relative_abs_errors_pct(predicted_m3: ArrayLike, measured_m3: ArrayLike) -> FloatArray:
    """``|measured - predicted| / measured`` in percent, per point."""
    measured = np.asarray(measured_m3, dtype=float)
    errors: FloatArray = np.abs(measured - np.asarray(predicted_m3, dtype=float)) / measured * 100
    return errors


# --------------------------------------------------------------------- the parameter grid
@dataclass(frozen=True)
class Grid:
    """Values of each swept parameter (ascending); the calibration's box is their range."""

    names: tuple[str, ...]
    values: tuple[np.ndarray, ...]

    @property
    def shape(self) -> tuple[int, ...]:
        return tuple(len(v) for v in self.values)

    def points(self) -> list[dict[str, float]]:
        """Every grid point as {name: value}, in C order of ``shape``."""
        return [dict(zip(self.names, combination, strict=True))
                for combination in itertools.product(*(v.tolist() for v in self.values))]


def parse_grid(items: list[str]) -> Grid:
    """``["gent_jm=3,6,12", "lobe_chamber_scale=1,1.1,1.2"]`` as a Grid; CalibrationError on a bad item."""
    known = set(MATERIAL_PARAMETERS) | {f.name for f in dataclasses.fields(ProstateGeometry)
                                        if not isinstance(f.default, tuple)}
    names, values = [], []
    for item in items:
        name, _, text = item.partition("=")
        name = name.strip()
        if name not in known:
            raise CalibrationError(f"--grid {item!r}: unknown parameter {name!r}; use one of "
                                   f"{', '.join(sorted(known))}")
        if name in names:
            raise CalibrationError(f"--grid names {name} twice")
        try:
            numbers = np.array([float(value) for value in text.split(",")])
        except ValueError:
            raise CalibrationError(f"--grid {item!r}: expected NAME=v1,v2,... with numbers") from None
        if not np.all(np.isfinite(numbers)) or np.any(np.diff(numbers) <= 0):
            raise CalibrationError(f"--grid {item!r}: values must be finite and strictly increasing")
        names.append(name)
        values.append(numbers)
    return Grid(tuple(names), tuple(values))


def scene_with(raw: dict[str, Any], values: dict[str, float]) -> dict[str, Any]:
    """A copy of a scene's TOML dict with parameters set: material keys in [material], others in [geometry];
    without the table files the scene ships (:func:`phantom.model.scene.without_shipped_tables`)."""
    document = without_shipped_tables(raw)
    for name, value in values.items():
        table = "material" if name in MATERIAL_PARAMETERS else "geometry"
        document.setdefault(table, {})[name] = float(value)
    return document


# --------------------------------------------------------------------- validity
def violations(material_model: str, gent_jm: float | FloatArray | None, min_det: FloatArray,
               min_stretch: FloatArray, max_stretch: FloatArray, max_i1_minus_3: FloatArray) -> BoolArray:
    """Boolean array: where a state breaks a validity constraint (NaN, i.e. not solved, counts as broken);
    ``gent_jm`` (one, or one per state) for the Gent law."""
    low, high = LAW_STRETCH_RANGE[material_model]
    with np.errstate(invalid="ignore"):
        broken: BoolArray = ~(min_det > 0) | ~(min_stretch >= low) | ~(max_stretch <= high)
        if material_model == "gent":
            assert gent_jm is not None  # the Gent law has its Jm
            broken |= ~(max_i1_minus_3 < GENT_LIMIT_FRACTION * gent_jm)
    return broken


def violation_reason(material_model: str, gent_jm: float | None, where: str, min_det: float, min_stretch: float,
                     max_stretch: float, max_i1_minus_3: float) -> str | None:
    """The first broken constraint of one state, in words, or None."""
    low, high = LAW_STRETCH_RANGE[material_model]
    if not min_det > 0:
        return f"{where}: an element is inverted (det F = {min_det:.3g})"
    if not low <= min_stretch or not max_stretch <= high:
        hint = (" (a finite-strain law holds there: --material gent --grid gent_jm=2,3)"
                if material_model in ("linear", "corotational") else "")
        return (f"{where}: principal stretches {min_stretch:.3g}-{max_stretch:.3g} leave the {material_model} "
                f"law's range {low:g}-{high:g}{hint}")
    if material_model == "gent" and gent_jm is not None and not max_i1_minus_3 < GENT_LIMIT_FRACTION * gent_jm:
        return (f"{where}: I1 - 3 = {max_i1_minus_3:.3g} reaches {GENT_LIMIT_FRACTION:g} Jm "
                f"(Jm = {gent_jm:.3g}), where the Gent law locks")
    return None


# --------------------------------------------------------------------- traced responses
@dataclass
class Responses:
    """The traces of every (grid point, ray) on a fine load-factor grid, NaN where not traced.

    gland_m3 : (*grid.shape, n_fine, n_rays); admissible : same shape, bool (validity of that state);
    and the validity measures themselves, for reporting.
    """

    grid: Grid
    load_factors: np.ndarray
    gland_m3: np.ndarray
    admissible: np.ndarray
    measures: dict[str, FloatArray]
    gent_jm: np.ndarray  # (*grid.shape,) the Jm at each grid point (NaN for other laws)
    material_model: str = "gent"

    @property
    def varying(self) -> list[int]:
        """Axes of the grid with more than one value (the others are fixed)."""
        return [axis for axis, values in enumerate(self.grid.values) if len(values) > 1]

    def interpolate(self, name: str, theta: np.ndarray, load_factor: float) -> np.ndarray:
        """Per-ray value of ``name`` ("gland_m3", "admissible" as 0/1, or a measure) at parameters ``theta``:
        multilinear over the varying grid axes and t, NaN outside the grid or where a corner that carries
        weight is NaN (a corner of zero weight does not count: the value on a cell's face is the face's)."""
        values = {"gland_m3": self.gland_m3, "admissible": self.admissible}.get(name)
        values = self.measures[name] if values is None else values
        axes = [self.grid.values[axis] if axis in self.varying else None for axis in range(len(self.grid.names))]
        axes.append(self.load_factors)
        point = [*theta, load_factor]
        cells, fractions = [], []
        for axis, coordinate in zip(axes, point, strict=True):
            if axis is None:
                cells.append(0)
                fractions.append(0.0)
                continue
            if not axis[0] <= coordinate <= axis[-1]:
                return np.full(values.shape[-1], np.nan)
            cell = int(np.clip(np.searchsorted(axis, coordinate, side="right") - 1, 0, len(axis) - 2))
            cells.append(cell)
            fractions.append((coordinate - axis[cell]) / (axis[cell + 1] - axis[cell]))
        result = np.zeros(values.shape[-1])
        for corner in np.ndindex(*(2,) * len(cells)):
            weight = float(np.prod([f if c else 1.0 - f for c, f in zip(corner, fractions, strict=True)]))
            if weight == 0.0:
                continue
            result = result + weight * values[tuple(cell + c for cell, c in zip(cells, corner, strict=True))]
        return result


def _fine(trace: RayTrace, load_factors: FloatArray, values: FloatArray, monotone: bool) -> FloatArray:
    """A trace's values on the fine grid: monotone cubic (volumes) or linear (measures), NaN beyond it."""
    # scipy.interpolate (0.5 s to import) only where traces are put on the fine grid
    from scipy.interpolate import PchipInterpolator

    out = np.full(len(load_factors), np.nan)
    inside = load_factors <= trace.load_factors[-1] + 1e-12
    if len(trace.load_factors) < 2:
        out[inside] = values[0]
        return out
    if monotone:
        out[inside] = PchipInterpolator(trace.load_factors, values)(load_factors[inside])
    else:
        out[inside] = np.interp(load_factors[inside], trace.load_factors, values)
    return out


def assemble_responses(grid: Grid, traces: list[RayTrace | None], feasible: list[bool], material_model: str,
                       gent_jms: list[float | None], n_rays: int, max_load_factor: float) -> Responses:
    """Put the traces of ``grid.points()`` x rays (row-major, None for infeasible points) on the fine grid."""
    load_factors = np.linspace(0.0, max_load_factor, FINE_LOAD_FACTOR_POINTS)
    shape = (*grid.shape, FINE_LOAD_FACTOR_POINTS, n_rays)
    gland = np.full(shape, np.nan)
    names = ("min_det", "min_stretch", "max_stretch", "max_i1_minus_3")
    measures = {name: np.full(shape, np.nan) for name in names}
    for flat, index in enumerate(np.ndindex(*grid.shape)):
        if not feasible[flat]:
            continue
        for ray in range(n_rays):
            trace = traces[flat * n_rays + ray]
            assert trace is not None  # a feasible grid point has its traces
            gland[index][:, ray] = _fine(trace, load_factors, trace.gland_m3, True)
            for name in names:
                measures[name][index][:, ray] = _fine(trace, load_factors, getattr(trace, name), False)
    jm = np.array([np.nan if value is None else value for value in gent_jms]).reshape(grid.shape)
    jm_full = np.broadcast_to(jm.reshape(*grid.shape, 1, 1), shape)
    broken = violations(material_model, jm_full, *(measures[name] for name in names))
    return Responses(grid, load_factors, gland, ~broken, measures, jm, material_model)


# --------------------------------------------------------------------- fitting
@dataclass
class Fit:
    """One least-squares fit: parameters (grid names), load factor, and per-ray interpolated volumes (m^3)."""

    theta: np.ndarray
    load_factor: float
    predicted_m3: np.ndarray
    cost: float
    #: The constraint the unconstrained optimum (on the grid) breaks, when it fits better: the fit sits on it.
    binding: str | None = None


def fit(responses: Responses, measured_m3: np.ndarray, rays: list[int],
        load_factor_range: tuple[float, float] | None = None) -> Fit:
    """The admissible (theta, t) of least relative squared residual on ``rays``: grid search, then refinement.

    ``load_factor_range``: the t (E0/E) the fit may take, from a modulus band; None: any traced t.
    Raises CalibrationError when no traced state fits every ray while keeping to the constraints.
    """
    # scipy.optimize (0.5 s to import) only where a fit is refined
    from scipy.optimize import minimize

    rays = list(rays)
    measured = measured_m3[rays]
    residual = (responses.gland_m3[..., rays] - measured) / measured
    with np.errstate(invalid="ignore"):
        cost = np.sum(residual**2, axis=-1)
    usable = np.all(responses.admissible[..., rays], axis=-1) & np.isfinite(cost)
    t_low, t_high = load_factor_range or (responses.load_factors[1], responses.load_factors[-1])
    t_low, t_high = max(t_low, responses.load_factors[1]), min(t_high, responses.load_factors[-1])
    in_band = (responses.load_factors >= t_low - 1e-12) & (responses.load_factors <= t_high + 1e-12)
    usable &= in_band
    if not usable.any():
        raise CalibrationError(_no_admissible_state(responses, rays))
    best = np.unravel_index(np.argmin(np.where(usable, cost, np.inf)), cost.shape)
    theta0 = np.array([responses.grid.values[axis][best[axis]] for axis in range(len(best) - 1)])
    t0 = float(responses.load_factors[best[-1]])
    # The refinement moves the varying axes and t only: a single-valued axis stays at its value.
    varying = responses.varying
    low = np.array([responses.grid.values[axis][0] for axis in varying] + [t_low])
    high = np.array([responses.grid.values[axis][-1] for axis in varying] + [t_high])
    span = high - low

    def state(scaled: np.ndarray) -> tuple[np.ndarray, float]:
        free = low + np.clip(scaled, 0, 1) * span
        theta = theta0.copy()
        theta[varying] = free[:-1]
        return theta, float(free[-1])

    def objective(scaled: np.ndarray) -> float:
        theta, load_factor = state(scaled)
        if not _admissible_here(responses, theta, load_factor, rays):
            return INADMISSIBLE_COST
        volumes = responses.interpolate("gland_m3", theta, load_factor)[rays]
        value = float(np.sum(((volumes - measured) / measured) ** 2))
        return value if np.isfinite(value) else INADMISSIBLE_COST

    start = (np.append(theta0[varying], t0) - low) / span
    # Nelder-Mead from a simplex of a fifth of a grid cell and two load-factor steps around the grid's best:
    # it starts where the grid search ended and shrinks away from inadmissible states. (Powell's bounded line
    # searches start at the golden section of the whole box, beyond the traces' ends, and never came back.)
    cell_steps = [np.diff(responses.grid.values[axis]).min() / 5 for axis in varying]
    steps = np.array(cell_steps + [2 * (responses.load_factors[1] - responses.load_factors[0])]) / span
    simplex = np.vstack([start, start + np.diag(np.where(start + steps <= 1, steps, -steps))])
    refined = minimize(objective, start, method="Nelder-Mead", bounds=[(0, 1)] * len(start),
                       options={"initial_simplex": simplex, "xatol": 1e-6, "fatol": 1e-12, "maxfev": 3000})
    scaled = refined.x if refined.fun <= objective(start) else start
    theta, load_factor = state(scaled)
    predicted = responses.interpolate("gland_m3", theta, load_factor)
    binding = _binding(responses, cost, usable, rays)
    if load_factor_range is not None and binding is None:
        binding = _band_edge(load_factor, (t_low, t_high))
    return Fit(theta, load_factor, predicted, float(objective(scaled)), binding)


def _band_edge(load_factor: float, band: tuple[float, float]) -> str | None:
    """Which edge of the modulus band the fit sits on (t = E0/E: the band's high t is its low E), if any."""
    tolerance = 1e-3 * (band[1] - band[0])
    if load_factor >= band[1] - tolerance:
        return "the modulus band's lower edge: the measurements ask for a softer material than the band allows"
    if load_factor <= band[0] + tolerance:
        return "the modulus band's upper edge: the measurements ask for a stiffer material than the band allows"
    return None


def _binding(responses: Responses, cost: np.ndarray, usable: np.ndarray, rays: list[int]) -> str | None:
    """The constraint the fit sits on: broken at a traced state that fits better than every admissible one, or
    reached (the trace ends or turns inadmissible) at the next load factor above the best admissible state
    while the cost still falls there."""
    finite = np.where(np.isfinite(cost), cost, np.inf)
    best_usable = np.unravel_index(np.argmin(np.where(usable, cost, np.inf)), cost.shape)
    best = np.unravel_index(np.argmin(finite), cost.shape)
    if usable[best] or not finite[best] < cost[best_usable]:
        following = (*best_usable[:-1], best_usable[-1] + 1)
        if following[-1] >= cost.shape[-1] or usable[following]:
            return None
        falling = np.nan_to_num(np.diff(cost[best_usable[:-1]])[best_usable[-1] - 1], nan=-1.0) < 0
        if not falling:
            return None
        best = following
    jm = responses.gent_jm[best[:-1]]
    where_t = f"E0/E = {responses.load_factors[best[-1]]:.3g}"
    for ray in rays:
        values = [float(responses.measures[name][best][ray]) for name in
                  ("min_det", "min_stretch", "max_stretch", "max_i1_minus_3")]
        if not np.all(np.isfinite(values)):
            return (f"ray {ray} ends at {where_t}, where its trace stopped (the law's limit or a failed solve): "
                    f"the fit stops below it")
        reason = violation_reason(responses.material_model, None if np.isnan(jm) else float(jm),
                                  f"ray {ray} at {where_t}", *values)
        if reason:
            return reason
    return None


def _admissible_here(responses: Responses, theta: np.ndarray, load_factor: float, rays: list[int]) -> bool:
    """(theta, t) lies in a cell whose traced states are all admissible on ``rays``, and the interpolated
    validity measures there keep every constraint."""
    if not np.all(responses.interpolate("admissible", theta, load_factor)[rays] > 1 - 1e-9):
        return False
    names = ("min_det", "min_stretch", "max_stretch", "max_i1_minus_3")
    values = [responses.interpolate(name, theta, load_factor)[rays] for name in names]
    jm = _gent_jm_at(responses, theta)
    return not np.any(violations(responses.material_model, jm, *values))


def _gent_jm_at(responses: Responses, theta: np.ndarray) -> float | None:
    if "gent_jm" in responses.grid.names:
        return float(theta[responses.grid.names.index("gent_jm")])
    jm = responses.gent_jm.ravel()[0]
    return None if np.isnan(jm) else float(jm)


def _no_admissible_state(responses: Responses, rays: list[int]) -> str:
    """Why no grid state serves: the constraint broken most often at the states that fit best."""
    traced = np.all(np.isfinite(responses.gland_m3[..., rays]), axis=-1)
    if not traced.any():
        return ("no grid point traced every ray: the solves failed (see the sweep) or the load-factor range is "
                "too short; widen the grid or change the scene's modulus")
    return (f"refused: no state on the grid fits the measurements within the constraints (law "
            f"{responses.material_model}: det F > 0, stretches in {LAW_STRETCH_RANGE[responses.material_model]}"
            + (f", I1 - 3 < {GENT_LIMIT_FRACTION:g} Jm" if responses.material_model == "gent" else "")
            + "): every state that reaches the measured volumes breaks one; try a stiffening law (gent) or "
              "larger chambers")


@dataclass
class CalibrationResult:
    """The calibration: fitted parameters and modulus, checked by full solves, and leave-one-out."""

    material_model: str
    grid: Grid
    parameters: dict[str, float]
    youngs_modulus_pa: float
    measured_m3: np.ndarray
    pressures_pa: np.ndarray
    fit_predicted_m3: np.ndarray          # full solves at the fitted parameters
    fit_interpolated_m3: np.ndarray       # the traces' interpolation at the same parameters
    loo_predicted_m3: np.ndarray
    loo_parameters: list[dict[str, float]]
    loo_youngs_modulus_pa: np.ndarray
    validity: dict[str, Any]
    tasks: int
    traces_solved: int
    binding: str | None = None
    modulus_band_pa: tuple[float, float] | None = None
    #: the traces the fit was made on: the model's response at any modulus (E0 / load factor) and grid point
    responses: Responses | None = None

    @property
    def fit_mean_abs_pct_error(self) -> float:
        return float(relative_abs_errors_pct(self.fit_predicted_m3, self.measured_m3).mean())

    @property
    def loo_mean_abs_pct_error(self) -> float:
        return float(relative_abs_errors_pct(self.loo_predicted_m3, self.measured_m3).mean())

    def uncertainty(self) -> dict[str, float]:
        """Jackknife standard error of each parameter and of E (kPa) from the leave-one-out fits."""
        n = len(self.loo_parameters)
        spread = {}
        for name in self.parameters:
            values = np.array([fit[name] for fit in self.loo_parameters])
            spread[name] = float(np.sqrt((n - 1) / n * np.sum((values - values.mean()) ** 2)))
        moduli = self.loo_youngs_modulus_pa / 1e3
        spread["youngs_modulus_kpa"] = float(np.sqrt((n - 1) / n * np.sum((moduli - moduli.mean()) ** 2)))
        return spread

    def as_json(self) -> dict[str, Any]:
        """kPa, ml, %."""
        return {
            "material_model": self.material_model,
            "youngs_modulus_kpa": self.youngs_modulus_pa / 1e3,
            "parameters": self.parameters,
            "fit_mean_abs_pct_error": self.fit_mean_abs_pct_error,
            "loo_mean_abs_pct_error": self.loo_mean_abs_pct_error,
            "pressures_kpa": (self.pressures_pa / 1e3).tolist(),
            "measured_ml": (self.measured_m3 * 1e6).tolist(),
            "fit_predicted_ml": (self.fit_predicted_m3 * 1e6).tolist(),
            "fit_interpolated_ml": (self.fit_interpolated_m3 * 1e6).tolist(),
            "fit_abs_pct_error": relative_abs_errors_pct(self.fit_predicted_m3, self.measured_m3).tolist(),
            "loo_predicted_ml": (self.loo_predicted_m3 * 1e6).tolist(),
            "loo_abs_pct_error": relative_abs_errors_pct(self.loo_predicted_m3, self.measured_m3).tolist(),
            "loo_parameters": self.loo_parameters,
            "loo_youngs_modulus_kpa": (self.loo_youngs_modulus_pa / 1e3).tolist(),
            "loo_jackknife_std": self.uncertainty(),
            "validity": self.validity,
            "grid": {name: values.tolist() for name, values in zip(self.grid.names, self.grid.values, strict=True)},
            "traces": self.tasks,
            "traces_solved_now": self.traces_solved,
            "binding_constraint": self.binding,
            "youngs_modulus_band_kpa": (None if self.modulus_band_pa is None
                                        else [value / 1e3 for value in self.modulus_band_pa]),
        }


def linear_load_factor(model: PhantomModel, measurements: Measurements) -> float:
    """Relative least squares of ``g = g_0 + t h . p`` for t, with the rest gland compliance h (first estimate)."""
    slope = (measurements.pressures_pa @ np.asarray(model.compliance().gland_m3_per_pa)) / measurements.volumes_m3
    residual = (measurements.volumes_m3 - model.rest_gland_volume_m3) / measurements.volumes_m3
    denominator = float(slope @ slope)
    factor = float(slope @ residual / denominator) if denominator > 0 else 0.0
    if factor <= 0:
        raise CalibrationError("the measurements do not grow with pressure: no positive modulus fits them")
    return factor


def ray_task(parsed: Scene, document: dict[str, Any], measurements: Measurements, row: int,
             load_factors: tuple[float, ...], stop_growth_m3: float = float("inf"),
             stop_i1_minus_3: float = float("inf")) -> RayTask:
    """The sweep task of measurement ``row`` in the scene ``document`` (``parsed`` is it parsed): its pressure
    ray, with the weight of the medium it was measured in (the scene's ``[load]``; none without one), both
    scaled by the load factor."""
    body_force = parsed.load.body_force_n_per_m3(measurements.medium(row))
    return RayTask(document, tuple(measurements.pressures_pa[row].tolist()), load_factors, stop_growth_m3,
                   stop_i1_minus_3=stop_i1_minus_3, body_force_n_per_m3=body_force)


def calibrate(scene: Scene, measurements: Measurements, grid: Grid, scheduler: str | None = None,
              n_workers: int | None = None, progress: Progress | None = None, max_load_factor: float | None = None,
              load_factor_step: float | None = None,
              modulus_band_pa: tuple[float, float] | None = None) -> CalibrationResult:
    """Fit E and the grid's parameters to ``measurements`` (see the module docstring); refuse an invalid fit.

    ``scene`` gives everything else (material law, Poisson ratio, geometry, mesh size); its modulus is E0.
    ``modulus_band_pa``: (lowest, highest) E the fit and every leave-one-out refit may take (the material's
    published modulus and its uncertainty); None lets E go wherever the traces reach.
    """
    e0 = scene.material.youngs_modulus_pa
    band_t: tuple[float, float] | None = None
    if modulus_band_pa is not None:
        low_pa, high_pa = modulus_band_pa
        if not 0 < low_pa <= e0 <= high_pa:
            raise CalibrationError(f"the modulus band {low_pa / 1e3:g}-{high_pa / 1e3:g} kPa must hold the "
                                   f"scene's modulus ({e0 / 1e3:g} kPa) and be positive")
        band_t = (e0 / high_pa, e0 / low_pa)
    over = measurements.pressures_pa.max()
    if over > PRESSURE_LIMIT_PA:
        raise CalibrationError(f"{measurements.path}: a measurement at {over / 1e3:g} kPa is above the "
                               f"{PRESSURE_LIMIT_PA / 1e3:g} kPa the phantom is driven to: remove it")
    law = scene.material.model
    if "gent_jm" in grid.names and law != "gent":
        raise CalibrationError(f"--grid gent_jm needs a scene with [material] model = 'gent', not {law!r}")
    raw = scene.raw
    if scene.path is not None and not scene.mesh.startswith("builtin:"):
        raw = copy.deepcopy(raw)
        raw["phantom"]["mesh"] = scene.mesh  # absolute, so a worker finds it
    geometry_names = [name for name in grid.names if name not in MATERIAL_PARAMETERS]
    if geometry_names and scene.geometry is None:
        raise CalibrationError(f"--grid {', '.join(geometry_names)}: geometry parameters need the built-in mesh")
    base_model = PhantomModel.from_scene(scene)
    t_linear = linear_load_factor(base_model, measurements)
    if band_t is not None:
        # The traces need to reach the band's softest E only; the steps are as fine as they are over 4 t_linear.
        max_load_factor = max_load_factor or band_t[1]
        step = load_factor_step or max_load_factor / (STEPS_PER_LINEAR_LOAD_FACTOR * MAX_LINEAR_MULTIPLE)
    else:
        max_load_factor = max_load_factor or MAX_LINEAR_MULTIPLE * t_linear
        step = load_factor_step or t_linear / STEPS_PER_LINEAR_LOAD_FACTOR
    load_factors = tuple(np.arange(0.0, max_load_factor + 0.5 * step, step).tolist())
    measured = measurements.volumes_m3
    stop_growth = OVERSHOOT * np.maximum(measured - base_model.rest_gland_volume_m3, 0.2 * measured.max() / 10)
    points = grid.points()
    feasible, tasks, gent_jms = [], [], []
    for values in points:
        document = scene_with(raw, values)
        parsed = scene_from_dict(document, scene.path)
        gent_jms.append(parsed.material.gent_jm)
        ok = True
        if parsed.geometry is not None:
            try:
                check_walls(geometry_from_table(document.get("geometry", {}), "grid"))
            except MeshError:
                ok = False
        feasible.append(ok)
        if ok:
            jm = parsed.material.gent_jm
            law_limit = GENT_LIMIT_FRACTION * jm if law == "gent" and jm is not None else np.inf
            tasks += [ray_task(parsed, document, measurements, j, load_factors, float(stop_growth[j]), law_limit)
                      for j in range(len(measured))]
    if not any(feasible):
        raise CalibrationError("every grid point breaks the wall-thickness limit: shrink the geometry grid")
    solved_now = sum(cached_trace(task) is None for task in tasks)
    results = iter(run_sweep(tasks, scheduler=scheduler, n_workers=n_workers, progress=progress))
    n_rays = len(measured)
    traces: list[RayTrace | None] = []
    for ok in feasible:
        traces += [next(results) for _ in range(n_rays)] if ok else [None] * n_rays
    responses = assemble_responses(grid, traces, feasible, law, gent_jms, n_rays, float(load_factors[-1]))
    everyone = list(range(n_rays))
    full = fit(responses, measured, everyone, band_t)
    loo_fits = [fit(responses, measured, [j for j in everyone if j != left_out], band_t) for left_out in everyone]
    loo_predicted = np.array([refit.predicted_m3[left_out] for left_out, refit in enumerate(loo_fits)])
    beyond = [left_out for left_out in everyone if not np.isfinite(loo_predicted[left_out])]
    if beyond:  # the left-out ray's trace stopped (OVERSHOOT) below the refit's load: solve it there
        loo_predicted[beyond] = _solve_left_out(raw, grid, [loo_fits[j] for j in beyond], beyond, measurements,
                                                scheduler, n_workers, progress)
    parameters = {name: float(full.theta[k]) for k, name in enumerate(grid.names)}
    verified, validity = _verify(raw, parameters, full.load_factor, measurements, law, scheduler, n_workers,
                                 progress)
    return CalibrationResult(
        law, grid, parameters, e0 / full.load_factor, measured, measurements.pressures_pa, verified,
        full.predicted_m3, np.array(loo_predicted),
        [{name: float(f.theta[k]) for k, name in enumerate(grid.names)} for f in loo_fits],
        np.array([e0 / f.load_factor for f in loo_fits]), validity, len(tasks), solved_now, full.binding,
        modulus_band_pa, responses)


def _solve_left_out(raw: dict[str, Any], grid: Grid, refits: list[Fit], left_outs: list[int],
                    measurements: Measurements, scheduler: str | None, n_workers: int | None,
                    progress: Progress | None) -> FloatArray:
    """Gland volumes (m^3) of left-out measurements at their refits' parameters, by full solves (continuation in
    four steps); where the model has no state there (a limit point), the last solved volume, a lower bound."""
    tasks = []
    for refit, left_out in zip(refits, left_outs, strict=True):
        document = scene_with(raw, {name: float(refit.theta[k]) for k, name in enumerate(grid.names)})
        load_factors = tuple((refit.load_factor * np.array([0.25, 0.5, 0.75, 1.0])).tolist())
        tasks.append(ray_task(scene_from_dict(document), document, measurements, left_out, load_factors))
    return np.array([trace.gland_m3[-1] for trace in run_sweep(tasks, scheduler=scheduler, n_workers=n_workers,
                                                               progress=progress)])


def _verify(raw: dict[str, Any], parameters: dict[str, float], load_factor: float, measurements: Measurements,
            law: str, scheduler: str | None, n_workers: int | None,
            progress: Progress | None) -> tuple[FloatArray, dict[str, Any]]:
    """Full solves of every measurement at the fitted parameters (continuation in four steps to ``t``);
    returns the gland volumes (m^3) and the validity figures, or raises CalibrationError with the reason."""
    document = scene_with(raw, parameters)
    jm = document.get("material", {}).get("gent_jm")
    load_factors = tuple((load_factor * np.array([0.25, 0.5, 0.75, 1.0])).tolist())
    parsed = scene_from_dict(document)
    tasks = [ray_task(parsed, document, measurements, row, load_factors) for row in range(len(measurements.volumes_m3))]
    traces = run_sweep(tasks, scheduler=scheduler, n_workers=n_workers, progress=progress)
    volumes, reasons = [], []
    for trace, pressures in zip(traces, measurements.pressures_pa, strict=True):
        where = f"at ({', '.join(f'{p / 1e3:g}' for p in pressures)}) kPa"
        if len(trace.load_factors) < len(load_factors) and np.any(pressures):
            raise CalibrationError(f"refused: the fitted calibration does not solve {where}: {trace.stopped}")
        volumes.append(trace.gland_m3[-1])
        reason = violation_reason(law, jm, where, trace.min_det[-1], trace.min_stretch[-1], trace.max_stretch[-1],
                                  trace.max_i1_minus_3[-1])
        if reason:
            reasons.append(reason)
    if reasons:
        raise CalibrationError(f"refused: the fitted calibration breaks a constraint {reasons[0]}")
    validity = {
        "min_det": float(min(t.min_det.min() for t in traces)),
        "min_stretch": float(min(t.min_stretch.min() for t in traces)),
        "max_stretch": float(max(t.max_stretch.max() for t in traces)),
        "max_i1_minus_3": float(max(t.max_i1_minus_3.max() for t in traces)),
        "stretch_range": list(LAW_STRETCH_RANGE[law]),
        "max_pressure_kpa": float(measurements.pressures_pa.max() / 1e3),
    }
    if jm is not None:
        validity["max_i1_minus_3_over_jm"] = validity["max_i1_minus_3"] / jm
    return np.array(volumes), validity



# --------------------------------------------------------------------- writing the calibrated scene
def _toml_value(value: object) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (int, np.integer)):
        return str(int(value))
    if isinstance(value, (float, np.floating)):
        if not np.isfinite(value):
            raise CalibrationError(f"cannot write the non-finite value {value} to a scene")
        return repr(float(value))
    if isinstance(value, str):
        return '"' + value.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_toml_value(item) for item in value) + "]"
    if isinstance(value, dict):
        return "{ " + ", ".join(f"{key} = {_toml_value(item)}" for key, item in value.items()) + " }"
    raise CalibrationError(f"cannot write a {type(value).__name__} to a scene")


def dump_toml(document: dict[str, Any], header_comment: str = "") -> str:
    """TOML text for a scene dictionary: top-level tables of scalars, lists and inline tables, and arrays of
    tables (``[[steps]]``)."""
    lines = [f"# {line}" if line else "#" for line in header_comment.splitlines()]
    scalars = {key: value for key, value in document.items() if not isinstance(value, (dict, list))
               or (isinstance(value, list) and not all(isinstance(item, dict) for item in value))}
    for key, value in scalars.items():
        lines.append(f"{key} = {_toml_value(value)}")
    for key, value in document.items():
        if isinstance(value, dict):
            lines.append("")
            lines.append(f"[{key}]")
            lines.extend(f"{name} = {_toml_value(item)}" for name, item in value.items())
        elif isinstance(value, list) and value and all(isinstance(item, dict) for item in value):
            for item in value:
                lines.append("")
                lines.append(f"[[{key}]]")
                lines.extend(f"{name} = {_toml_value(entry)}" for name, entry in item.items())
    return "\n".join(lines) + "\n"



def write_calibrated_scene(scene: Scene, result: CalibrationResult, output_path: str | Path,
                           header_comment: str = "") -> Path:
    """Write ``scene`` with the calibration's material (law, E, parameters) and geometry, its mesh path made
    relative to the new file; returns the path written."""
    output_path = Path(output_path)
    document = scene_with(scene.raw, result.parameters)
    phantom_table = document.setdefault("phantom", {})
    mesh = phantom_table.get("mesh", "builtin:prostate")
    if not str(mesh).startswith("builtin"):
        source = (Path(scene.path).parent / mesh).resolve() if scene.path else Path(mesh).resolve()
        phantom_table["mesh"] = os.path.relpath(source, output_path.resolve().parent)
    material = document.setdefault("material", {})
    material["model"] = result.material_model
    material["youngs_modulus_kpa"] = round(result.youngs_modulus_pa / 1e3, 5)
    for name in result.parameters:
        table = "material" if name in MATERIAL_PARAMETERS else "geometry"
        document[table][name] = round(result.parameters[name], 5)
    if result.material_model in HYPERELASTIC_MODELS:
        # A daemon on a finite-strain law answers from the response table (a full solve takes most of a second)
        document.setdefault("model", {}).setdefault("fidelity", "table")
    try:
        output_path.parent.mkdir(parents=True, exist_ok=True)
        output_path.write_text(dump_toml(document, header_comment))
    except OSError as error:
        raise CalibrationError(f"cannot write {output_path}: {error.strerror}") from None
    return output_path
