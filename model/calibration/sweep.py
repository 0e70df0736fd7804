"""Parameter sweeps of the forward model as independent Dask tasks, cached on disk.

A task (:class:`RayTask`) is one scene (its parsed TOML, so material and geometry are whatever it says) and one
pressure ray ``t p`` traced by continuation over load factors ``t = 0, dt, 2 dt, ...``: each solve starts from
the last three equilibria extrapolated to its load factor (:func:`trace_ray`; the small-strain model, whose load
is taken on its start, solves each from rest). At each
``t`` it records the gland and chamber volumes and what physical validity needs: the smallest det F (an
inverted element has det F <= 0), the extreme principal stretches and the largest ``I1 - 3`` over the elements
(the Gent law holds only below ``Jm``). The trace stops at the last ``t``, at the first failed solve (a limit
point), once the gland has grown by ``stop_growth_m3``, or once ``I1 - 3`` passes ``stop_i1_minus_3`` (where
the law stops holding: nothing beyond can be a valid calibration).

For a hyperelastic law at fixed Poisson ratio the state at (pressures p, modulus E) is the one at
(p E0 / E, E0), so one trace of a ray gives the response at every modulus: E is the load factor.

:func:`run_sweep` runs the tasks that are not cached on a ``dask.distributed`` cluster (a LocalCluster on the
machine's cores, or ``scheduler="tcp://host:port"`` for an existing one), shows progress, stores each result
under ``phantom.cache_dir("sweeps")`` by a hash of the task, and returns them in task order: a second sweep
over the same tasks (a leave-one-out refit) re-solves nothing.
"""

from __future__ import annotations

import contextlib
import functools
import hashlib
import json
import os
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

import phantom
from phantom import require_extra
from phantom.model.arrays import FloatArray
from phantom.model.cluster import Progress, dask_client
from phantom.model.errors import SolveError
from phantom.model.fem.model import PhantomModel
from phantom.model.scene import scene_from_dict

if TYPE_CHECKING:
    from dask.distributed import Client

#: Bump when what a trace computes changes, so cached traces are recomputed.
SWEEP_VERSION = 2
#: Equilibria a trace's predictor extrapolates (a polynomial of one degree less in the load factor; 1: start each
#: solve from the last equilibrium). On the 7 mm prostate at (3, 1, 2) kPa a quadratic took 5 iterations a step
#: where a secant took 5-7 and the last equilibrium 11-26.
PREDICTOR_POINTS = 3


@dataclass(frozen=True)
class RayTask:
    """One pressure ray of one scene: solve at ``load_factors[k] * pressures_pa`` in order.

    scene_raw : the scene's parsed TOML (material and geometry as the scene says); a built-in mesh only, or an
        absolute mesh path. mesh_size_mm : element size of the built-in mesh (None: the scene's).
    body_force_n_per_m3 : the weight per volume (N/m^3) in the medium the ray was measured in; it is scaled by
        the load factor with the pressures, because the load factor stands for the modulus (E0 / t).
    """

    scene_raw: dict[str, Any]
    pressures_pa: tuple[float, ...]
    load_factors: tuple[float, ...]
    stop_growth_m3: float = float("inf")
    mesh_size_mm: float | None = None
    stop_i1_minus_3: float = float("inf")
    body_force_n_per_m3: tuple[float, float, float] = (0.0, 0.0, 0.0)

    @property
    def key(self) -> str:
        """A hash of everything the trace depends on: the name it is stored under."""
        parts = [SWEEP_VERSION, self.scene_raw, list(self.pressures_pa), list(self.load_factors),
                 repr(self.stop_growth_m3), self.mesh_size_mm, repr(self.stop_i1_minus_3)]
        if any(self.body_force_n_per_m3):  # weightless rays keep the names their traces were stored under
            parts.append([repr(value) for value in self.body_force_n_per_m3])
        text = json.dumps(parts, sort_keys=True, default=repr)
        return hashlib.sha256(text.encode()).hexdigest()[:32]


@dataclass
class RayTrace:
    """What a ray gave at each solved load factor (arrays of length ``solved``, NaN-free).

    gland_m3 (k,), chamber_m3 (k, n_chambers), min_det (k,), min_stretch (k,), max_stretch (k,),
    max_i1_minus_3 (k,); ``stopped`` says why the trace ended ("end", "growth", or the solver's message).
    """

    load_factors: np.ndarray
    gland_m3: np.ndarray
    chamber_m3: np.ndarray
    min_det: np.ndarray
    min_stretch: np.ndarray
    max_stretch: np.ndarray
    max_i1_minus_3: np.ndarray
    stopped: str
    solve_time_s: float

    def arrays(self) -> dict[str, Any]:
        """The trace's arrays by name (for storing)."""
        return {name: getattr(self, name) for name in ("load_factors", "gland_m3", "chamber_m3", "min_det",
                                                       "min_stretch", "max_stretch", "max_i1_minus_3")}


def element_stretch_measures(deformation: np.ndarray) -> tuple[float, float, float, float]:
    """Smallest det F, smallest and largest principal stretch and largest ``I1 - 3 = tr(F^T F) - 3`` over
    deformation gradients ``(..., 3, 3)`` (:meth:`~phantom.model.fem.body.Body.deformation_gradients`: every
    point where the law is evaluated)."""
    deformation = deformation.reshape(-1, 3, 3)
    right_cauchy_green = np.einsum("eki,ekj->eij", deformation, deformation)
    squared_stretches = np.linalg.eigvalsh(right_cauchy_green)
    stretches = np.sqrt(np.clip(squared_stretches, 0.0, None))
    return (float(np.linalg.det(deformation).min()), float(stretches[:, 0].min()), float(stretches[:, -1].max()),
            float((squared_stretches.sum(axis=1) - 3.0).max()))


@functools.lru_cache(maxsize=4)
def _model_of(scene_text: str, mesh_size_mm: float | None) -> PhantomModel:
    """The model of a scene (kept per worker process: the tasks of one grid point share it)."""
    return PhantomModel.from_scene(scene_from_dict(json.loads(scene_text)), mesh_size_mm=mesh_size_mm)


def trace_ray(task: RayTask) -> RayTrace:
    """Trace one ray (see the module docstring); runs on a Dask worker or in the calling process.

    Each solve after the second starts Newton from the last PREDICTOR_POINTS equilibria (rest at t = 0 among
    them) extrapolated to its load factor, positions and element pressures alike, rather than from the last
    one: on the 7 mm prostate at (3, 1, 2) kPa the trace took 9+5+5+5+6 Newton iterations where solves from the
    last equilibrium took 9+11+15+26+15 (23 against 62 s of CPU; bench/calibration_traces.py). The same
    equilibria: only where Newton starts changes, and where it does not converge from the prediction the
    solve starts from the last equilibrium (:meth:`PhantomModel.equilibrium`'s path following) as before.
    """
    started = time.perf_counter()
    model = _model_of(json.dumps(task.scene_raw, sort_keys=True), task.mesh_size_mm)
    pressures = np.asarray(task.pressures_pa, dtype=float)
    body_force = np.asarray(task.body_force_n_per_m3, dtype=float)
    warm_start = model.formulation != "linear"
    rows, stopped = [], "end"
    # the last equilibria on the ray (load factors, node positions), from rest at t = 0,
    # which is one whether or not the ray's load factors start there (the full solves that verify a fit do not)
    solved_t: list[float] = [0.0]
    solved_m: list[FloatArray] = [model.nodes_m]
    for load_factor in task.load_factors:
        if load_factor == 0 or not (np.any(pressures) or np.any(body_force)):
            positions_m_here, chambers, gland = model.nodes_m, model.rest_chamber_volumes_m3, model.rest_gland_volume_m3
        else:
            last = solved_m[-1] if solved_t[-1] > 0 else None  # the first solve starts from rest
            predicted_m = predicted_pa = None
            if last is not None:  # (PREDICTOR_POINTS = 1: from the last equilibrium)
                predicted_m, predicted_pa = model.extrapolated_start(solved_m[::-1], solved_t[::-1], load_factor)
            try:
                state = model.equilibrium(load_factor * pressures, initial_positions_m=last,
                                          body_force_n_per_m3=load_factor * body_force,
                                          predicted_positions_m=predicted_m,
                                          predicted_element_pressures_pa=predicted_pa)
            except SolveError as error:
                stopped = str(error)
                break
            positions_m_here, chambers, gland = state.positions_m, state.chamber_volumes_m3, state.gland_volume_m3
        if warm_start and load_factor > 0:
            solved_t = [*solved_t, load_factor][-PREDICTOR_POINTS:]
            solved_m = [*solved_m, positions_m_here][-PREDICTOR_POINTS:]
        measures = element_stretch_measures(model.body.deformation_gradients(positions_m_here))
        if model.order == 2:  # the least of det F at the quadrature points and each element's volume ratio (Jbar)
            measures = (float(model.body.deformation_determinants(positions_m_here).min()), *measures[1:])
        rows.append((load_factor, gland, np.asarray(chambers, float), *measures))
        if gland - model.rest_gland_volume_m3 > task.stop_growth_m3:
            stopped = "growth"
            break
        if measures[3] > task.stop_i1_minus_3:
            stopped = "law limit"
            break
    columns = list(zip(*rows, strict=True))
    return RayTrace(np.array(columns[0]), np.array(columns[1]), np.array(columns[2]), np.array(columns[3]),
                    np.array(columns[4]), np.array(columns[5]), np.array(columns[6]), stopped,
                    time.perf_counter() - started)


# ------------------------------------------------------------------------------------------ cache
def _cache_path(task: RayTask) -> Path:
    return phantom.cache_dir("sweeps") / f"{task.key}.npz"


def cached_trace(task: RayTask) -> RayTrace | None:
    """The stored trace of a task, or None."""
    path = _cache_path(task)
    if not path.is_file():
        return None
    try:
        with np.load(path) as stored:
            return RayTrace(**{name: stored[name] for name in stored.files if name not in ("stopped", "time")},
                            stopped=str(stored["stopped"]), solve_time_s=float(stored["time"]))
    except (OSError, ValueError, KeyError, TypeError):
        path.unlink(missing_ok=True)
        return None


def store_trace(task: RayTask, trace: RayTrace) -> None:
    path = _cache_path(task)
    handle, temporary = tempfile.mkstemp(dir=path.parent, suffix=".npz")
    os.close(handle)
    np.savez(temporary, stopped=np.array(trace.stopped), time=np.array(trace.solve_time_s), **trace.arrays())
    os.replace(temporary, path)


# ------------------------------------------------------------------------------------------ running
def run_sweep(tasks: list[RayTask], scheduler: str | None = None, n_workers: int | None = None,
              progress: Progress | None = None, client: Client | None = None) -> list[RayTrace]:
    """Every task's trace, in order: cached ones read from disk, the others computed on Dask and stored.

    ``client`` (a ``dask.distributed.Client``) is used as given; else ``scheduler`` is the address of a
    running scheduler; else a LocalCluster of ``n_workers`` processes (default: the cores) is started for the
    sweep and closed after it.
    """
    results: list[RayTrace | None] = [cached_trace(task) for task in tasks]
    missing = [index for index, trace in enumerate(results) if trace is None]
    total = len(tasks)
    if progress is not None:
        progress(total - len(missing), total)
    if not missing:
        return [trace for trace in results if trace is not None]
    # dask.distributed (1 s to import, an optional extra) only where a sweep has traces to solve
    with require_extra("calibrate"):
        from dask.distributed import as_completed

    with contextlib.ExitStack() as stack:
        if client is None:
            client = stack.enter_context(dask_client(scheduler, n_workers))
        futures = {client.submit(trace_ray, tasks[index], key=f"trace-{tasks[index].key}", pure=False): index
                   for index in missing}
        done = total - len(missing)
        for future in as_completed(futures):
            index = futures[future]
            trace = future.result()
            store_trace(tasks[index], trace)
            results[index] = trace
            done += 1
            if progress is not None:
                progress(done, total)
    return [trace for trace in results if trace is not None]  # every task has its trace by now
