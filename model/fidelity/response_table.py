"""The model's response over its whole operating box, solved once and interpolated: the ``table`` fidelity.

A hyperelastic model answers "what volumes do these pressures give" with a full solve (0.4-1 s on the
calibrated 4 mm mesh) and its inverse with several; a daemon that re-solves at every control tick of a ramp
cannot wait that long. The box of pressures the daemon may ask for is small (0 to ``pressure_max`` in each of
three chambers) and the response in it is smooth (no limit point below the pressure limit), so it is solved
once on a grid and interpolated by a tensor-product cubic spline:

- grid: ``n`` evenly spaced pressures from 0 to ``p_max`` on each axis (``n^3`` points);
- values: chamber and gland volumes (m^3) and every node's position (m), from full solves, each started from
  the quadratic through the (up to three) solved points before it down a grid line (3-6 Newton iterations on
  ``builtin:converged``, 4-11 from the neighbour itself), each point a Dask task (:mod:`phantom.model.cluster`)
  that starts when those are solved;
- answers: the not-a-knot cubic spline through the grid along each axis, as a contraction of the grid values
  with each axis's cardinal-spline weights, and its exact gradient (the tangent compliance at the operating
  point), in a fraction of a millisecond; outside the box, the value at the nearest point of the box plus the
  gradient there times the distance (an overshoot of a few pascal must not meet a cubic's extrapolation), up to
  :data:`EXTENSION_OF_BOX` of the box beyond it: further out the table does not know the model, and is refused
  (1e6 Pa answered 12973 ml).

Along chamber 0's axis of the calibrated model (its cavity grows 4.5-fold, with an inflection) a spline through
0.5 kPa steps misses a dense set of full solves by 0.007 ml, a polynomial through 7 Chebyshev nodes by 0.03 ml.

Built tables are stored under ``phantom.cache_dir("response")`` by a hash of the model (mesh, material,
solver) and the grid, so a daemon pays the build (n^3 solves: 2-3 min for n = 7 on one core for the 4-node
calibration, divided by the workers down to the longest chain of solves, ``3 (n - 1)``) once per model and
machine; a build that is killed resumes from the points it solved (kept on disk until the table is whole). Each
build is checked against full solves at :data:`CHECK_FRACTIONS`, points between the grid's.

A scene whose build costs most of an hour (the 10-node ``builtin:converged``) ships its table's volumes beside
it (``[model] table_volumes``, :func:`write_table_volumes`: 9 kB compressed, where the nodes' positions take
67 MB). Such a table answers volumes and compliances at once on a fresh machine; it has no shapes. The scene
may ship its outer surface's shapes too (``[model] table_shapes``, :func:`write_table_shapes`): the surface
nodes' displacements on a coarser grid (:data:`SHIPPED_SHAPE_POINTS` per axis, as their leading singular modes),
interpolated the same way; without them ``VolumeEstimator.shape`` solves each shape. A shipped file is used only
for the model it was made for: it states the model (material, mesh size, geometry, load, solver, grid) and its
rest volumes, and a model that differs is refused with what differs. The rest volumes (within
:data:`SHIPPED_REST_TOLERANCE_PCT`) stand for the nodes' coordinates, so that a mesh another gmsh release makes
from the same settings is accepted for its volumes when they agree; shapes, which name nodes, need the same
surface nodes at the same places (within :data:`SHIPPED_NODE_TOLERANCE_M`), else they are solved.
"""

from __future__ import annotations

import dataclasses
import functools
import importlib.util
import json
import logging
import os
import shutil
import tempfile
import time
import uuid
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike

import phantom
from phantom import PhantomError, require_extra
from phantom.model.arrays import FloatArray
from phantom.model.cluster import LocalWorkersError, dask_client
from phantom.model.errors import SceneError, SolveError
from phantom.model.fem.body import SOLVER_VERSION
from phantom.model.fem.model import PhantomModel
from phantom.model.fidelity.table_files import check_shape_nodes, read_members, read_provenance, table_members
from phantom.model.scene import DEFAULT_TABLE_POINTS

if TYPE_CHECKING:
    from scipy.interpolate import CubicSpline

#: Bump when what a table holds or how it is built changes, so stored tables are rebuilt (and write the tables
#: the built-in scenes ship again: model/scenes/*.toml say how).
TABLE_VERSION = 1
#: Where each build is checked against full solves (fractions of the pressure limit per chamber): points far
#: from every node, one near each corner region and one inside.
CHECK_FRACTIONS = ((0.2, 0.6, 0.9), (0.9, 0.2, 0.6), (0.6, 0.9, 0.2), (0.7, 0.7, 0.7))
#: How far (% of a rest volume) the model's rest volumes may be from those a shipped table was made on.
SHIPPED_REST_TOLERANCE_PCT = 0.05
#: Grid points per axis of the shapes a scene ships (1 kPa steps on a 3 kPa box: 64 solves).
SHIPPED_SHAPE_POINTS = 4
#: How far (m) a surface node of the model may be from where a shipped shape table has it at rest.
SHIPPED_NODE_TOLERANCE_M = 1e-9
#: How far (m) the singular modes a shape table ships may put a node from its solved position at a grid point.
SHIPPED_MODES_TOLERANCE_M = 2e-5
#: How far outside its box (a fraction of the box's top, on each side) a table extends linearly: a chamber held at
#: the top reads an ADC count or two (54 Pa each) over it, a step's overshoot more, and 200 Pa over a 3 kPa box
#: the extension is within 1 % of the full solve's growth (tests/test_response.py); its error grows as the
#: distance squared, and far beyond it is no answer of the model's (1e6 Pa gave 12973 ml).
EXTENSION_OF_BOX = 0.1

Progress = Callable[[int, int], None]
#: One axis's cardinal-spline weights at a pressure, and their slope per Pa.
Basis = tuple[FloatArray, FloatArray]

logger = logging.getLogger(__name__)


class ResponseTableError(PhantomError):
    """A table that cannot be built (a grid point without equilibrium) or that misses the model."""


def grid_pa(pressure_max_pa: float, points_per_axis: int) -> np.ndarray:
    """The grid's pressures on each axis: ``points_per_axis`` evenly spaced from 0 to ``pressure_max_pa`` (Pa)."""
    return np.linspace(0.0, pressure_max_pa, points_per_axis)


@functools.lru_cache(maxsize=8)
def _cardinal_splines(points_per_axis: int) -> CubicSpline:
    """The cubic splines (not-a-knot) through the unit vectors on the grid 0, 1, ..., n - 1: row i of their value
    at x is the weight of grid value i in the spline through any values, so a tensor spline is a contraction."""
    # scipy.interpolate (0.2 s to import) only where a table is evaluated
    from scipy.interpolate import CubicSpline

    return CubicSpline(np.arange(points_per_axis, dtype=float), np.eye(points_per_axis))


@dataclass(frozen=True)
class ResponseTable:
    """A model's volumes and shape over ``[0, pressure_max_pa]^n_chambers``, interpolated (see the module).

    The value arrays (grid values) have one leading axis of length ``points_per_axis`` per chamber, indexed like
    :func:`grid_pa`, then the quantity's own axes; ``check_errors_pct``
    is the largest volume error (% of the volume) of the build's check against full solves;
    ``build_time_s`` what the build took. ``position_values`` is None for a table of volumes only (shipped with
    its scene, :func:`shipped_table_volumes`).
    """

    pressure_max_pa: float
    chamber_values: np.ndarray
    gland_values: np.ndarray
    position_values: np.ndarray | None
    check_errors_pct: float
    build_time_s: float

    @property
    def n_chambers(self) -> int:
        return self.gland_values.ndim

    @property
    def points_per_axis(self) -> int:
        return int(self.gland_values.shape[0])

    @property
    def extension_pa(self) -> float:
        """How far outside its box (Pa) the table answers, by its linear extension (:data:`EXTENSION_OF_BOX`)."""
        return EXTENSION_OF_BOX * self.pressure_max_pa

    def _bases(self, pressures_pa: np.ndarray) -> tuple[list[Basis], np.ndarray]:
        """Per chamber: the basis and its slope (per Pa) at the pressure clipped into the box; and the excess
        of each pressure over the box (Pa), for the linear extension outside.

        Raises
        ------
        ResponseTableError
            A pressure further outside the box than :attr:`extension_pa`, or not finite.
        """
        top_pa, extension_pa = self.pressure_max_pa, self.extension_pa
        if not np.all(np.isfinite(pressures_pa)) or np.any(pressures_pa < -extension_pa) \
                or np.any(pressures_pa > top_pa + extension_pa):
            raise ResponseTableError(
                f"the response table answers within its box, 0-{top_pa:g} Pa (0-{top_pa / 1e3:g} kPa) per chamber, "
                f"and up to {extension_pa:g} Pa outside it; got {np.asarray(pressures_pa).tolist()} Pa: give "
                f"pressures in Pa within the box (the model beyond it: fidelity full)")
        inside_pa = np.clip(pressures_pa, 0.0, top_pa)
        # One piece of the splines' coefficients per chamber gives both the weights and their slopes (scipy's
        # CubicSpline evaluates the two separately, and a lookup needed them for every chamber and quantity).
        coefficients = _cardinal_splines(self.points_per_axis).c        # (4, n - 1, n), highest power first
        per_pa = (self.points_per_axis - 1) / self.pressure_max_pa
        bases = []
        for pressure in inside_pa:
            x = pressure * per_pa
            piece = min(int(x), self.points_per_axis - 2)
            dx = x - piece
            a, b, c, d = coefficients[:, piece]
            bases.append((((a * dx + b) * dx + c) * dx + d, ((3.0 * a * dx + 2.0 * b) * dx + c) * per_pa))
        return bases, pressures_pa - inside_pa

    def _contract(self, values: np.ndarray, vectors: list[np.ndarray]) -> np.ndarray:
        result = values
        for vector in vectors:
            result = np.tensordot(vector, result, axes=(0, 0))
        return result

    def _gradient(self, grid_values: np.ndarray, bases: list[Basis]) -> np.ndarray:
        """d(value)/dp_chamber (per Pa) for each chamber, stacked on a leading axis."""
        return np.stack([self._contract(grid_values, [slopes if axis == chamber else values
                                                      for axis, (values, slopes) in enumerate(bases)])
                         for chamber in range(self.n_chambers)])

    def _value(self, grid_values: np.ndarray, pressures_pa: np.ndarray,
               bases: tuple[list[Basis], np.ndarray] | None = None) -> np.ndarray:
        """The interpolant at ``pressures_pa`` (``bases``: theirs, when already formed); outside the box, its
        linear extension from the box's edge (the gradient is formed only then: inside, a value is one
        contraction per axis)."""
        bases_here, excess_pa = bases or self._bases(pressures_pa)
        value = self._contract(grid_values, [values for values, _ in bases_here])
        if np.any(excess_pa):
            value = value + np.tensordot(excess_pa, self._gradient(grid_values, bases_here), axes=(0, 0))
        return value

    def volumes(self, pressures_pa: ArrayLike) -> tuple[np.ndarray, float]:
        """Chamber volumes (m^3) and the gland volume (m^3) at ``pressures_pa`` (Pa, one per chamber; within
        :attr:`extension_pa` of the box, else ResponseTableError)."""
        pressures = np.asarray(pressures_pa, dtype=float)
        bases = self._bases(pressures)
        return (self._value(self.chamber_values, pressures, bases),
                float(self._value(self.gland_values, pressures, bases)))

    def compliance(self, pressures_pa: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
        """The tangent compliance at ``pressures_pa``: ``dV_chamber_i/dp_j`` (n, n) and ``dV_gland/dp_j`` (n,),
        m^3/Pa (the interpolant's exact gradient; at the box's edge beyond it)."""
        bases, _ = self._bases(np.asarray(pressures_pa, dtype=float))
        return self._gradient(self.chamber_values, bases).T, self._gradient(self.gland_values, bases)

    def positions_m(self, pressures_pa: ArrayLike) -> np.ndarray:
        """Every node's position (m, (nodes, 3)) at ``pressures_pa``; ResponseTableError for a table of volumes
        only."""
        if self.position_values is None:
            raise ResponseTableError("this response table holds volumes only (shipped with its scene): solve the "
                                     "shape (VolumeEstimator.shape does)")
        return self._value(self.position_values, np.asarray(pressures_pa, dtype=float))


def _predecessor(index: tuple[int, ...]) -> tuple[int, ...] | None:
    """The grid point a point's solve starts from: one step down the last raised axis (None at the origin), so
    that the grid is walked along its lines, (i, 0, 0) from (i - 1, 0, 0), (i, j, 0) from (i, j - 1, 0) and
    (i, j, k) from (i, j, k - 1): a tree whose longest branch is ``n_chambers (n - 1)`` solves."""
    raised = [axis for axis, position in enumerate(index) if position > 0]
    if not raised:
        return None
    return tuple(position - (axis == raised[-1]) for axis, position in enumerate(index))


def _line_before(index: tuple[int, ...], count: int, origin_solved: bool) -> list[tuple[int, ...]]:
    """Up to ``count`` grid points down the grid line a point is solved along (its :func:`_predecessor`'s axis),
    nearest first: the equilibria its solve's start is extrapolated from (:func:`_solve_point`). None where the
    predecessor is the origin (that solve starts from rest); the origin itself only when ``origin_solved`` (the
    rest shape is the equilibrium at zero pressure only without a body force)."""
    before = _predecessor(index)
    if before is None or not any(before):
        return []
    axis = next(axis for axis, (a, b) in enumerate(zip(index, before, strict=True)) if a != b)
    line = [tuple(position - step * (other == axis) for other, position in enumerate(index))
            for step in range(1, min(count, index[axis]) + 1)]
    return [point for point in line if origin_solved or any(point)]


#: Equilibria down a grid line that a point's start is extrapolated from (1: the neighbour itself; 2: a secant;
#: 3: a quadratic), measured by bench/table_points.py (bench/README.md, "The table's cost per point").
LINE_PREDICTOR_POINTS = 3


#: Newton's tolerance at a grid point (relative to the load): the table is a spline through its points, checked
#: against full solves to a tenth of a percent (:data:`CHECK_FRACTIONS`), and a residual of 1e-7 of the load moves
#: a volume by about that fraction of its growth, so the last Newton iteration to the solver's 1e-9 bought nothing
#: (bench/README.md, "The table's cost per point").
POINT_TOLERANCE = 1e-7


#: One grid point's answer: chamber volumes (m^3), gland volume (m^3), every node's position (m), and the CPU
#: time its solve took (s; NaN for a point stored by a build that did not record it).
PointResult = tuple[FloatArray, float, FloatArray, float]


def _solve_point(model: PhantomModel, pressures_pa: FloatArray, *line: PointResult) -> PointResult:
    """The equilibrium at ``pressures_pa``, started from the answers ``line`` at the points before it down its
    grid line, nearest first (:func:`_line_before`): extrapolated through them
    (:meth:`~phantom.model.fem.model.PhantomModel.extrapolated_start`); none: from rest (a small-strain solve takes
    its load on its start, so it always starts from rest). Runs on a Dask worker or in the calling process."""
    started_cpu_s = time.process_time()
    nearest_m = predicted_m = predicted_pa = None
    if line and model.formulation != "linear":
        nearest_m = line[0][2]
        predicted_m, predicted_pa = model.extrapolated_start([point[2] for point in line])
    try:
        state = model.equilibrium(pressures_pa, initial_positions_m=nearest_m, tolerance=POINT_TOLERANCE,
                                  predicted_positions_m=predicted_m, predicted_element_pressures_pa=predicted_pa)
    except SolveError as error:
        raise ResponseTableError(
            f"the model has no equilibrium at {np.round(pressures_pa / 1e3, 3).tolist()} kPa, inside the pressure "
            f"limit ({error}): lower [model] pressure_max_kpa or stiffen the material") from None
    return (np.asarray(state.chamber_volumes_m3, float), float(state.gland_volume_m3), state.positions_m,
            time.process_time() - started_cpu_s)


def _points_folder(model: PhantomModel, pressure_max_pa: float, points_per_axis: int) -> Path:
    """Where a build keeps each solved grid point until the table is whole (what a killed build resumes from)."""
    return _cache_path(model, pressure_max_pa, points_per_axis).with_suffix(".points")


def _point_path(folder: Path, index: tuple[int, ...]) -> Path:
    return folder / f"point-{'-'.join(str(position) for position in index)}.npz"


def _store_point(folder: Path, index: tuple[int, ...], result: PointResult) -> None:
    """One grid point's answer, written whole or not at all (a kill mid-write leaves no half file)."""
    folder.mkdir(parents=True, exist_ok=True)
    handle, temporary = tempfile.mkstemp(dir=folder, suffix=".npz")
    os.close(handle)
    np.savez(temporary, chambers=result[0], gland=result[1], positions=result[2], cpu_s=result[3])
    os.replace(temporary, _point_path(folder, index))


def _stored_points(folder: Path, grid: tuple[int, ...], n_nodes: int) -> dict[tuple[int, ...], PointResult]:
    """The grid points an earlier build of the same table solved (a damaged file is removed and solved again)."""
    stored: dict[tuple[int, ...], PointResult] = {}
    for index in np.ndindex(*grid):
        path = _point_path(folder, index)
        if not path.is_file():
            continue
        try:
            with np.load(path) as point:
                result = (np.asarray(point["chambers"], float), float(point["gland"]),
                          np.asarray(point["positions"], float),
                          float(point["cpu_s"]) if "cpu_s" in point.files else float("nan"))
        except (OSError, ValueError, KeyError):
            path.unlink(missing_ok=True)
            continue
        if result[2].shape == (n_nodes, 3):
            stored[index] = result
    return stored


def _solve_grid(model: PhantomModel, nodes_pa: FloatArray, known: dict[tuple[int, ...], PointResult],
                folder: Path, progress: Callable[[], None], workers: int, scheduler: str | None) -> None:
    """Solve every grid point not in ``known`` (which holds the origin), each started from the points before it
    down the grid line to its :func:`_predecessor` (:func:`_line_before`),
    storing each in ``folder`` and adding it to ``known`` as it comes; in this process for one worker and no
    scheduler, else as one Dask task per point (:func:`phantom.model.cluster.dask_client`)."""
    grid = (len(nodes_pa),) * int(model.n_chambers)
    origin_solved = not np.any(model.body_force_n_per_m3)  # rest is then the equilibrium at zero pressure
    missing = [index for index in np.ndindex(*grid) if index not in known]  # C order: predecessors first
    if not missing:
        return
    if workers == 1 and scheduler is None:
        for index in missing:
            line = _line_before(index, LINE_PREDICTOR_POINTS, origin_solved)
            known[index] = _solve_point(model, nodes_pa[list(index)], *(known[point] for point in line))
            _store_point(folder, index, known[index])
            progress()
        return
    try:
        _solve_on_dask(model, nodes_pa, known, missing, folder, progress, workers, scheduler)
    except LocalWorkersError as error:
        logger.warning("%s; building the rest of the response table in this process", error)
        _solve_grid(model, nodes_pa, known, folder, progress, 1, None)


def _solve_on_dask(model: PhantomModel, nodes_pa: FloatArray, known: dict[tuple[int, ...], PointResult],
                   missing: list[tuple[int, ...]], folder: Path, progress: Callable[[], None], workers: int,
                   scheduler: str | None) -> None:
    """:func:`_solve_grid`'s points as Dask tasks, each depending on the tasks of the points it starts from (or
    given their stored answers), stored as they come in whatever order they finish."""
    # dask.distributed (1 s to import, an optional extra) only where a build is spread
    with require_extra("calibrate"):
        from dask.distributed import as_completed

    origin_solved = not np.any(model.body_force_n_per_m3)  # rest is then the equilibrium at zero pressure
    with dask_client(scheduler, workers) as client:
        # the model (17 MB pickled, with its factorisations) goes to each worker once, not with every task
        [model_on_workers] = client.scatter([model], broadcast=True, hash=False)
        futures: dict[tuple[int, ...], Any] = {}
        build = uuid.uuid4().hex[:12]  # keys of this build's tasks only, on a cluster that may run others
        for index in missing:
            line = [futures.get(point, known.get(point))
                    for point in _line_before(index, LINE_PREDICTOR_POINTS, origin_solved)]
            futures[index] = client.submit(_solve_point, model_on_workers, nodes_pa[list(index)], *line,
                                           key=f"table-point-{build}-{'-'.join(map(str, index))}")
        points = {future.key: index for index, future in futures.items()}
        for future in as_completed(list(futures.values())):
            index = points[future.key]
            known[index] = future.result()
            _store_point(folder, index, known[index])
            progress()


def _cost_of_grid(cpu_s: dict[tuple[int, ...], float]) -> str:
    """What the grid's solves cost, in words: their CPU time in all, and along the longest chain of solves that
    start from each other (:func:`_predecessor`), which no number of workers shortens. Points stored by an
    earlier build without a recorded time count at the mean of the others."""
    measured = [value for index, value in cpu_s.items() if any(index) and np.isfinite(value)]
    if not measured:
        return "the grid's points were all stored by an earlier build"
    mean_s = float(np.mean(measured))
    chain_s: dict[tuple[int, ...], float] = {}
    for index in sorted(cpu_s):  # lexicographic: a predecessor before its successors
        before = _predecessor(index)
        own_s = cpu_s[index] if np.isfinite(cpu_s[index]) else mean_s
        chain_s[index] = own_s + (0.0 if before is None else chain_s[before])
    total_s = float(np.sum(measured)) + mean_s * (len(cpu_s) - 1 - len(measured))
    return (f"the grid's {len(cpu_s) - 1} solves: {total_s:.0f} s of CPU ({mean_s:.1f} s a point, measured on "
            f"{len(measured)}), the longest chain of solves {max(chain_s.values()):.0f} s; on W idle workers the "
            f"grid takes at least the larger of {total_s:.0f} s / W and the chain")


def build_response_table(model: PhantomModel, pressure_max_pa: float, points_per_axis: int = DEFAULT_TABLE_POINTS,
                         progress: Progress | None = None, workers: int | None = None,
                         scheduler: str | None = None) -> ResponseTable:
    """Solve ``model`` at every point of the grid, each from a solved neighbour (:func:`_predecessor`), then check
    the interpolant against full solves at :data:`CHECK_FRACTIONS`. The points are Dask tasks on the cluster at
    ``scheduler``, else on a LocalCluster of ``workers`` processes (default: the cores; without the ``calibrate``
    extra, in this process); ``workers=1``: in this process. Each solved point is kept on disk until the table
    is whole, so a build that was killed resumes where it stopped. Raises ResponseTableError when a grid point
    has no equilibrium. A point's solve does not depend on where it runs, so neither does the table."""
    if points_per_axis < 2:
        raise ResponseTableError(f"a response table needs at least 2 points per axis, got {points_per_axis}")
    if not np.isfinite(pressure_max_pa) or pressure_max_pa <= 0:
        raise ResponseTableError(f"the pressure limit must be a positive number of Pa, got {pressure_max_pa}")
    if workers is not None and workers < 1:
        raise ResponseTableError(f"a build needs at least one worker, got {workers}")
    started = time.perf_counter()
    n, n_chambers = points_per_axis, int(model.n_chambers)
    nodes_pa = grid_pa(pressure_max_pa, n)
    grid = (n,) * n_chambers
    folder = _points_folder(model, pressure_max_pa, n)
    known = _stored_points(folder, grid, len(model.nodes_m))
    known[(0,) * n_chambers] = (np.asarray(model.rest_chamber_volumes_m3, float), float(model.rest_gland_volume_m3),
                                np.asarray(model.nodes_m, float), 0.0)
    total = int(np.prod(grid)) + len(CHECK_FRACTIONS)
    done = [len(known)]

    def tell() -> None:
        if progress is not None:
            progress(done[0], total)

    def one_more() -> None:
        done[0] += 1
        tell()

    tell()  # the size of the work (and what an earlier build did), before the first solve is done
    if workers is None and scheduler is None and importlib.util.find_spec("distributed") is None:
        logger.info("dask.distributed is not installed (the 'calibrate' extra): the response table is built in "
                    "this process")
        workers = 1
    workers = workers or os.cpu_count() or 1
    _solve_grid(model, nodes_pa, known, folder, one_more, workers, scheduler)
    logger.info("%s", _cost_of_grid({index: result[3] for index, result in known.items()}))
    chambers = np.stack([known[index][0] for index in np.ndindex(*grid)]).reshape(*grid, n_chambers)
    gland = np.array([known[index][1] for index in np.ndindex(*grid)]).reshape(grid)
    positions = np.stack([known[index][2] for index in np.ndindex(*grid)]).reshape(*grid, *np.shape(model.nodes_m))
    table = ResponseTable(float(pressure_max_pa), chambers, gland, positions, 0.0, 0.0)
    worst_pct, _ = check_errors(model, table, after_each=one_more)
    shutil.rmtree(folder, ignore_errors=True)
    return dataclasses.replace(table, check_errors_pct=worst_pct, build_time_s=time.perf_counter() - started)


def check_errors(model: PhantomModel, table: ResponseTable, nodes: np.ndarray | None = None,
                 after_each: Callable[[], None] | None = None) -> tuple[float, float]:
    """How far ``table`` (which holds every node's position) is from full solves at :data:`CHECK_FRACTIONS`: the
    largest volume error (% of the volume) and the largest distance (m) of one of ``nodes`` (0 without them).
    Each solve starts from the nearest grid point's state (an interpolated shape is no equilibrium: started
    there, a nearly incompressible body's Newton took minutes); ``after_each()`` is called after each."""
    assert table.position_values is not None
    nodes_pa = grid_pa(table.pressure_max_pa, table.points_per_axis)
    warm_start = model.formulation != "linear"
    worst_pct, worst_m = 0.0, 0.0
    for fractions in CHECK_FRACTIONS:
        pressures = table.pressure_max_pa * np.asarray(fractions[:model.n_chambers], dtype=float)
        nearest = tuple(int(np.argmin(np.abs(nodes_pa - p))) for p in pressures)
        state = model.equilibrium(pressures,
                                  initial_positions_m=table.position_values[nearest] if warm_start else None)
        table_chambers, table_gland = table.volumes(pressures)
        exact = np.append(state.chamber_volumes_m3, state.gland_volume_m3)
        worst_pct = max(worst_pct, float(np.max(np.abs(np.append(table_chambers, table_gland) - exact) / exact)) * 100)
        if nodes is not None:
            off_m = np.linalg.norm(table.positions_m(pressures)[nodes] - state.positions_m[nodes], axis=1)
            worst_m = max(worst_m, float(off_m.max()))
        if after_each is not None:
            after_each()
    return worst_pct, worst_m


def _cache_path(model: PhantomModel, pressure_max_pa: float, points_per_axis: int) -> Path:
    extra = repr(("response", TABLE_VERSION, model.formulation, float(pressure_max_pa), int(points_per_axis)))
    return phantom.cache_dir("response") / f"{model.cache_key(extra.encode())}.npz"


def table_provenance(model: PhantomModel, pressure_max_pa: float, points_per_axis: int) -> dict[str, Any]:
    """What a table's volumes depend on besides the mesh's node coordinates, as JSON values: the model a shipped
    table was made for (:func:`write_table_volumes`). The nodes are stood for by the rest volumes (checked
    within a tolerance), so that a mesh from another gmsh release with the same settings still matches."""
    scene = model.scene
    geometry = None if scene is None or scene.geometry is None else dataclasses.asdict(scene.geometry)
    if geometry is not None:
        geometry["mesh_size_mm"] = model.mesh_size_mm
    provenance = {
        "table_version": TABLE_VERSION, "solver_version": SOLVER_VERSION, "formulation": model.formulation,
        "material": dataclasses.asdict(model.material), "mesh": Path(model.source).name, "geometry": geometry,
        "chambers": list(model.chamber_names), "fixed": None if scene is None else scene.fixed,
        "fixed_penalty": float(model.body.fixed_penalty),
        "body_force_n_per_m3": [float(value) for value in model.body_force_n_per_m3],
        "pressure_max_pa": float(pressure_max_pa), "points_per_axis": int(points_per_axis)}
    return dict(json.loads(json.dumps(provenance)))  # tuples as lists, as they read back


def _flat(values: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    """Nested tables as one level of dotted keys (``geometry.mesh_size_mm``), to name what differs."""
    flat: dict[str, Any] = {}
    for key, value in values.items():
        if isinstance(value, dict):
            flat.update(_flat(value, f"{prefix}{key}."))
        else:
            flat[f"{prefix}{key}"] = value
    return flat


@dataclass(frozen=True)
class SurfaceShapes:
    """Some nodes' positions over the box, interpolated: the outer surface's shapes a scene ships
    (``[model] table_shapes``, :func:`shipped_table_shapes`).

    ``table`` holds the positions of ``nodes`` only (model node indices, sorted); ``check_error_m`` is the
    largest distance (m) of one of them from a full solve's, at the build's checks (:data:`CHECK_FRACTIONS`).
    """

    table: ResponseTable
    nodes: np.ndarray
    check_error_m: float

    def positions_m(self, pressures_pa: ArrayLike, nodes: ArrayLike) -> np.ndarray | None:
        """The positions (m, (len(nodes), 3)) of ``nodes`` at ``pressures_pa``; None when the table does not
        hold every one of them."""
        wanted = np.asarray(nodes)
        where = np.minimum(np.searchsorted(self.nodes, wanted), len(self.nodes) - 1)
        if not np.array_equal(self.nodes[where], wanted):
            return None
        return self.table.positions_m(pressures_pa)[where]


def build_table_shapes(model: PhantomModel, pressure_max_pa: float, points_per_axis: int = SHIPPED_SHAPE_POINTS,
                       progress: Progress | None = None, workers: int | None = None, scheduler: str | None = None,
                       table: ResponseTable | None = None) -> SurfaceShapes:
    """The outer surface's shapes on a ``points_per_axis`` grid, checked against full solves at
    :data:`CHECK_FRACTIONS` (volumes and shapes from the same solves): what :func:`write_table_shapes` ships.
    Taken from ``table``'s positions where its grid holds every point of this one (7 points per axis hold the 4
    shipped: a table and its shapes in one pass), else built (:func:`build_response_table`)."""
    if points_per_axis < 2:
        raise ResponseTableError(f"a shape table needs at least 2 points per axis, got {points_per_axis}")
    stride = 0
    if (table is not None and table.position_values is not None and table.pressure_max_pa == pressure_max_pa
            and (table.points_per_axis - 1) % (points_per_axis - 1) == 0):
        stride = (table.points_per_axis - 1) // (points_per_axis - 1)
    if table is not None and table.position_values is not None and stride:
        every = (slice(None, None, stride),) * table.n_chambers
        assert table.position_values is not None
        grid_table = ResponseTable(table.pressure_max_pa, table.chamber_values[every], table.gland_values[every],
                                   table.position_values[every], 0.0, table.build_time_s)
    else:
        grid_table = build_response_table(model, pressure_max_pa, points_per_axis, progress, workers, scheduler)
    assert grid_table.position_values is not None  # a build solves every shape
    nodes, _ = model.outer_surface()
    volumes_pct, shapes_m = check_errors(model, grid_table, np.asarray(nodes))
    return SurfaceShapes(dataclasses.replace(grid_table, position_values=grid_table.position_values[..., nodes, :],
                                             check_errors_pct=volumes_pct), np.asarray(nodes), shapes_m)


def write_table_shapes(shapes: SurfaceShapes, model: PhantomModel, path: str | Path) -> None:
    """Write ``shapes`` for shipping with ``model``'s scene (``[model] table_shapes``): the nodes' displacements
    from rest as the fewest singular modes that keep every grid point within :data:`SHIPPED_MODES_TOLERANCE_M` (19
    modes, 0.3 MB, for builtin:converged's 1718 surface nodes on 4^3 points, where the displacements themselves
    take 1.3 MB), as float32; the model they belong to (:func:`table_provenance`), its rest volumes and the nodes'
    rest positions. The check error written is the build's plus the modes' own (a bound on their sum)."""
    table = shapes.table
    assert table.position_values is not None
    rest_m = np.asarray(model.nodes_m, dtype=float)[shapes.nodes]
    grid = table.position_values.shape[:-2]
    displacement = (table.position_values - rest_m).reshape(int(np.prod(grid)), -1)
    left, singular, right = np.linalg.svd(displacement, full_matrices=False)
    for count in range(1, len(singular) + 1):
        coefficients = (left[:, :count] * singular[:count]).astype(np.float32)
        modes = right[:count].astype(np.float32)
        off_m = np.linalg.norm((coefficients.astype(float) @ modes.astype(float) - displacement).reshape(
            len(displacement), -1, 3), axis=2).max()
        if off_m <= SHIPPED_MODES_TOLERANCE_M:
            break
    np.savez_compressed(
        path, coefficients=coefficients.reshape(*grid, -1), modes_m=modes.reshape(-1, len(shapes.nodes), 3),
        nodes=shapes.nodes.astype(np.int32), rest_positions_m=rest_m, chamber=table.chamber_values,
        gland=table.gland_values, check_error_m=shapes.check_error_m + off_m,
        check_errors_pct=table.check_errors_pct, build_time_s=table.build_time_s,
        provenance=json.dumps(table_provenance(model, table.pressure_max_pa, table.points_per_axis)),
        rest_volumes_m3=np.append(model.rest_chamber_volumes_m3, model.rest_gland_volume_m3))


def write_table_volumes(table: ResponseTable, model: PhantomModel, path: str | Path) -> None:
    """Write ``table``'s volumes (not its positions) for shipping with ``model``'s scene, with the model they
    belong to (:func:`table_provenance`) and its rest volumes; ``[model] table_volumes`` names the file."""
    np.savez_compressed(
        path, chamber=table.chamber_values, gland=table.gland_values, check_errors_pct=table.check_errors_pct,
        build_time_s=table.build_time_s,
        provenance=json.dumps(table_provenance(model, table.pressure_max_pa, table.points_per_axis)),
        rest_volumes_m3=np.append(model.rest_chamber_volumes_m3, model.rest_gland_volume_m3))


def _read_shipped(model: PhantomModel, key: str, path: Path, pressure_max_pa: float, points_per_axis: int | None,
                  remedy: str) -> dict[str, np.ndarray]:
    """The arrays of the file a scene ships under ``[model] key``, once it is shown to belong to ``model`` and
    the grid (its provenance, and its rest volumes within :data:`SHIPPED_REST_TOLERANCE_PCT`; None
    ``points_per_axis``: the file's own); ResponseTableError, saying what differs and ``remedy``, otherwise, and
    a SceneError for a file that is not such a table (:mod:`phantom.model.fidelity.table_files`)."""
    where = f"the table {key.removeprefix('table_')} {path} ([model] {key})"
    provenance = read_provenance(path, where, remedy)
    if points_per_axis is None:
        points_per_axis = provenance.get("points_per_axis")
        if isinstance(points_per_axis, bool) or not isinstance(points_per_axis, int) or not (
                2 <= points_per_axis <= 64):
            raise SceneError(f"{where} is damaged (its points_per_axis is {points_per_axis!r}): {remedy}")
    wanted, made = _flat(table_provenance(model, pressure_max_pa, points_per_axis)), _flat(provenance)
    differing = sorted(key for key in set(wanted) | set(made) if wanted.get(key) != made.get(key))
    if differing:
        shown = "; ".join(f"{key}: made for {made.get(key)!r}, this model has {wanted.get(key)!r}"
                          for key in differing)
        raise ResponseTableError(f"{where} belong to another model ({shown}): {remedy}")
    arrays = read_members(path, table_members(model.n_chambers, points_per_axis, key == "table_shapes"), where, remedy)
    rest_m3 = arrays["rest_volumes_m3"]
    model_rest_m3 = np.append(model.rest_chamber_volumes_m3, model.rest_gland_volume_m3)
    with np.errstate(divide="ignore", invalid="ignore"):
        off_pct = float(np.max(np.abs(model_rest_m3 - rest_m3) / rest_m3)) * 100
    if not off_pct <= SHIPPED_REST_TOLERANCE_PCT:
        raise ResponseTableError(
            f"{where} were made on a mesh whose rest volumes are up to {off_pct:.2g} % from this one's (more than "
            f"{SHIPPED_REST_TOLERANCE_PCT:g} %: the mesher made another mesh from the same settings): {remedy}")
    return arrays


def shipped_table_volumes(model: PhantomModel, pressure_max_pa: float,
                          points_per_axis: int = DEFAULT_TABLE_POINTS) -> ResponseTable | None:
    """The volumes shipped with the model's scene (``[model] table_volumes``) as a table without positions, or
    None when the scene ships none. Raises ResponseTableError, saying what differs, when the file was made for
    another model or grid, or cannot be read."""
    path = model.model_settings.table_volumes
    if path is None:
        return None
    remedy = ("use a copy of the scene without [model] table_volumes (the table is then built once per machine: "
              "53 min on one core for builtin:converged), another level ([model] fidelity; phantom inverse "
              "--fidelity), or write the file again for this model (phantom model table SCENE --out FILE)")
    stored = _read_shipped(model, "table_volumes", path, pressure_max_pa, points_per_axis, remedy)
    return ResponseTable(float(pressure_max_pa), np.asarray(stored["chamber"], float),
                         np.asarray(stored["gland"], float), None, float(stored["check_errors_pct"]),
                         float(stored["build_time_s"]))


def shipped_table_shapes(model: PhantomModel, pressure_max_pa: float,
                         path: Path | None = None) -> SurfaceShapes | None:
    """The outer surface's shapes shipped with the model's scene (``[model] table_shapes``; or the file at
    ``path``, written by :func:`write_table_shapes`), on the file's own grid, or None when it ships none, or
    (with a warning) when this mesh's nodes are not where the file has them. Raises ResponseTableError, saying
    what differs, when the file was made for another model or pressure box, or cannot be read."""
    path = model.model_settings.table_shapes if path is None else path
    if path is None:
        return None
    remedy = ("use a copy of the scene without [model] table_shapes (each shape is then a full solve), or write "
              "the file again for this model (phantom model table SCENE --shapes-out FILE)")
    stored = _read_shipped(model, "table_shapes", path, pressure_max_pa, None, remedy)
    check_shape_nodes(stored, f"the table shapes {path} ([model] table_shapes)", remedy)
    nodes = np.asarray(stored["nodes"], dtype=np.int64)
    rest_m = np.asarray(stored["rest_positions_m"], dtype=float)
    coefficients = np.asarray(stored["coefficients"], dtype=float)
    modes_m = np.asarray(stored["modes_m"], dtype=float)
    check_error_m = float(stored["check_error_m"])
    model_nodes_m = np.asarray(model.nodes_m, dtype=float)
    if (nodes.size == 0 or nodes.max() >= len(model_nodes_m)
            or np.abs(model_nodes_m[nodes] - rest_m).max() > SHIPPED_NODE_TOLERANCE_M):
        # Not the user's doing (a gmsh release that numbers or places the same mesh's nodes otherwise, where the
        # volumes still agree): the model is the same, only its shapes must be solved.
        logger.warning("the table shapes %s ([model] table_shapes) name nodes this mesh does not have where they "
                       "were (the mesher numbered or placed them otherwise): each shape is a full solve; write the "
                       "file again for this mesh (phantom model table SCENE --shapes-out FILE)", path)
        return None
    displacement_m = np.tensordot(coefficients, modes_m, axes=(-1, 0))
    table = ResponseTable(float(pressure_max_pa), np.asarray(stored["chamber"], float),
                          np.asarray(stored["gland"], float), rest_m + displacement_m,
                          float(stored["check_errors_pct"]), float(stored["build_time_s"]))
    return SurfaceShapes(table, nodes, check_error_m)


def stored_response_table(model: PhantomModel, pressure_max_pa: float,
                          points_per_axis: int = DEFAULT_TABLE_POINTS) -> ResponseTable | None:
    """The model's table from the disk cache, else the volumes shipped with its scene, or None when neither is
    there (a damaged cache entry is removed): whether :func:`response_table` would answer at once or build
    first (the daemon serves on another level meanwhile)."""
    path = _cache_path(model, pressure_max_pa, points_per_axis)
    if path.is_file():
        try:
            with np.load(path) as stored:
                return ResponseTable(float(stored["pressure_max_pa"]), stored["chamber"], stored["gland"],
                                     stored["positions"], float(stored["check_errors_pct"]),
                                     float(stored["build_time_s"]))
        except (OSError, ValueError, KeyError):
            path.unlink(missing_ok=True)
    return shipped_table_volumes(model, pressure_max_pa, points_per_axis)


def response_table(model: PhantomModel, pressure_max_pa: float, points_per_axis: int = DEFAULT_TABLE_POINTS,
                   progress: Progress | None = None, workers: int | None = None,
                   scheduler: str | None = None) -> ResponseTable:
    """The model's table: read from the disk cache or shipped with its scene (:func:`stored_response_table`),
    else built (:func:`build_response_table`) and stored. ``progress(done, total)`` is told how a build goes
    (nothing is told for a stored table)."""
    stored = stored_response_table(model, pressure_max_pa, points_per_axis)
    if stored is not None:
        return stored
    path = _cache_path(model, pressure_max_pa, points_per_axis)
    table = build_response_table(model, pressure_max_pa, points_per_axis, progress, workers, scheduler)
    assert table.position_values is not None  # a build solves every shape
    handle, temporary = tempfile.mkstemp(dir=path.parent, suffix=".npz")
    os.close(handle)
    np.savez(temporary, pressure_max_pa=table.pressure_max_pa, chamber=table.chamber_values,
             gland=table.gland_values, positions=table.position_values,
             check_errors_pct=table.check_errors_pct, build_time_s=table.build_time_s)
    os.replace(temporary, path)
    return table
