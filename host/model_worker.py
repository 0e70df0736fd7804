"""The daemon's model side: targets -> inverse QP -> pressure setpoints; measured pressures -> volumes (-> shape).

:class:`LoadedModel` loads the scene and its model once, precomputes the compliance (or loads it from the disk
cache), warms the inverse and times each stage. :class:`ModelWorker` runs it in a process of its own, which
dies with the daemon, so that the link never waits on the model.
"""

from __future__ import annotations

import asyncio
import logging
import multiprocessing
import os
import signal
import time
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from typing import Any, TypeVar

import numpy as np

import phantom
from phantom.host.logs import configure_logging
from phantom.host.scenes import effective_model
from phantom.model.target import InverseResult, Target, UnreachableTargetError

logger = logging.getLogger(__name__)

#: What a function run in the worker answers.
Answer = TypeVar("Answer")

ML_PER_M3 = 1e6
PA_PER_KPA = 1e3
MM_PER_M = 1e3


class LoadedModel:
    """The scene's model, its inverse solver and its volume estimator, built once and warmed up.

    Parameters
    ----------
    scene_source : str
        ``builtin:calibrated`` (the daemon's default), another built-in name, or a scene TOML path
        (``phantom.model.load_scene``).
    report : callable(str), optional
        Where start-up progress goes (the log by default): each stage and how long it took.
    """

    def __init__(self, scene_source: str, report: Callable[[str], None] = logger.info):
        # the model's stack (scipy, numba) is loaded where the model is built: in the worker process, not in the
        # daemon that imports this module
        from phantom.model import PhantomModel, load_scene
        from phantom.model.fidelity.levels import VolumeEstimator
        from phantom.model.inverse import InverseSolver

        self.timings_s: dict[str, float] = {}
        started = time.perf_counter()
        report(f"loading scene {scene_source} ...")
        self.scene = load_scene(scene_source)
        self.model = PhantomModel.from_scene(self.scene)
        self.timings_s["model_s"] = time.perf_counter() - started
        report(f"model ready in {self.timings_s['model_s']:.2f} s ({len(self.model.nodes_m)} nodes, "
               f"{len(self.model.tets)} tets); compliance ...")
        stage = time.perf_counter()
        self.rest_compliance = self.model.compliance()
        self.timings_s["compliance_s"] = time.perf_counter() - stage
        report(f"compliance ready in {self.timings_s['compliance_s']:.2f} s (computed, or loaded from "
               f"{phantom.cache_dir('compliance')}); inverse solver ...")
        stage = time.perf_counter()
        # The model keeps its scene: the estimator reads the [model] table (pressure_max_kpa, fidelity) from it,
        # and without a fidelity probes for the cheapest level within the scene's accuracy_pct (one solve per
        # level at the pressure limit); the table level is built here the first time (minutes, with progress).
        estimator = VolumeEstimator(self.model, progress=build_progress(report))
        self.solver = InverseSolver(self.model, estimator=estimator)
        self.pressure_max_pa = float(self.solver.pressure_max_pa.max())
        self.estimator = self.solver.estimator
        self.timings_s["inverse_setup_s"] = time.perf_counter() - stage
        stage = time.perf_counter()
        self.warm_up()
        self.timings_s["warm_up_s"] = time.perf_counter() - stage
        self.timings_s["total_s"] = time.perf_counter() - started
        probe = ""
        if self.estimator.probe_errors_pct:
            probe = ", chosen for accuracy_pct {:g} from errors {}".format(self.estimator.accuracy_pct, ", ".join(
                f"{level} {error:.3g} %" for level, error in self.estimator.probe_errors_pct.items()))
        if self.estimator.table is not None:
            probe = (f", a {self.estimator.table.points_per_axis}^{self.estimator.table.n_chambers} response table "
                     f"within {self.estimator.table.check_errors_pct:.2g} % of full solves")
        report(f"inverse ready in {self.timings_s['inverse_setup_s']:.2f} s (fidelity {self.estimator.level}{probe}), "
               f"warmed up in {self.timings_s['warm_up_s']:.2f} s; start-up took {self.timings_s['total_s']:.2f} s")
        self.chamber_names = list(self.model.chamber_names)
        self.rest_volume_ml = float(self.model.rest_gland_volume_m3) * ML_PER_M3
        self.wants_shape = bool(self.scene.outputs.shape)
        #: the outer surface as its own mesh (model node indices, triangles into them), for shapes and the rest ghost
        self._outer_surface = self.model.outer_surface()

    def warm_up(self) -> None:
        """Solve one reachable and one unreachable gland target, so that the first request finds the QPs set
        up and the solvers' modules loaded (the first ``set`` took 0.2-0.6 s, later ones 10-30 ms); the
        estimator's counters start again from zero."""
        rest_m3 = float(self.model.rest_gland_volume_m3)
        _, highest_m3, _ = self.estimator.evaluate(self.solver.pressure_max_pa)
        self.solver.pressures_for(Target(gland_volume_m3=rest_m3 + 0.5 * (float(highest_m3) - rest_m3)))
        try:
            self.solver.pressures_for(Target(gland_volume_m3=float(highest_m3) + 0.1 * (float(highest_m3) - rest_m3)))
        except UnreachableTargetError:
            pass
        for key in self.estimator.counts:
            self.estimator.counts[key] = 0

    def effective_model(self) -> dict[str, Any]:
        """What a scene must match to run on this model (see :func:`phantom.host.scenes.effective_model`)."""
        return effective_model(self.scene, fidelity=self.estimator.level, pressure_max_kpa=self.pressure_max_pa
                               / PA_PER_KPA)

    def pressures_for(self, target: Target) -> InverseResult:
        """The setpoints (Pa) for ``target``; raises UnreachableTargetError (a PhantomError) with the range."""
        return self.solver.pressures_for(target)

    def estimate(self, pressures_pa: np.ndarray) -> tuple[list[float], float]:
        """Estimated chamber volumes (ml) and gland volume (ml) at measured pressures (Pa, negative -> 0)."""
        chamber_m3, gland_m3 = self.estimator.volumes(np.clip(np.asarray(pressures_pa, dtype=float), 0.0, None))
        return (np.asarray(chamber_m3) * ML_PER_M3).tolist(), float(gland_m3) * ML_PER_M3

    def rest_surface_mm(self) -> tuple[np.ndarray, np.ndarray]:
        """The outer surface at rest: positions (mm, (n, 3)) and triangles ((k, 3) indices into them)."""
        used, triangles = self._outer_surface
        return np.asarray(self.model.nodes_m)[used] * MM_PER_M, triangles

    def outer_surface_mm(self, pressures_pa: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The deformed outer surface at pressures (Pa): positions (mm) and triangles; a shape is formed only here."""
        used, triangles = self._outer_surface
        positions_m = self.estimator.shape(np.clip(np.asarray(pressures_pa, dtype=float), 0.0, None))
        return np.asarray(positions_m)[used] * MM_PER_M, triangles


def build_progress(report: Callable[[str], None], every_s: float = 10.0) -> Callable[[int, int], None]:
    """A ``progress(done, total)`` for a long model build that reports at most every ``every_s`` seconds, and
    at the end."""
    started = time.perf_counter()
    last_s = [started]

    def progress(done: int, total: int) -> None:
        now = time.perf_counter()
        if done < total and now - last_s[0] < every_s:
            return
        last_s[0] = now
        elapsed_s = now - started
        left = f", about {elapsed_s / done * (total - done):.0f} s left" if 0 < done < total else ""
        report(f"response table: {done}/{total} solves in {elapsed_s:.0f} s{left} (once per model and machine; "
               "stored in the cache)")
    return progress


@dataclass(frozen=True)
class ModelInfo:
    """What the daemon knows about the model in the worker (``scene_raw``: the scene's TOML, whose ``[[steps]]``
    and ``[timeline]`` the daemon plays)."""

    chamber_names: list[str]
    chamber_labels: list[str]
    rest_volume_ml: float
    timings_s: dict[str, float]
    fidelity: str
    scene_raw: dict[str, Any]
    scene_path: str
    pressure_max_pa: float
    wants_shape: bool
    effective_model: dict[str, Any]


@dataclass(frozen=True)
class Estimate:
    """Volumes at measured pressures, the surface when asked, and the estimator's work counters."""

    chamber_volumes_ml: list[float]
    gland_volume_ml: float
    surface_mm: tuple[np.ndarray, np.ndarray] | None
    counts: dict[str, int]
    rest_surface_mm: tuple[np.ndarray, np.ndarray] | None = None


# --- the model in its own process -------------------------------------------------------------------------
#
# The inverse and the estimator are numpy/scipy/numba work that holds the GIL for long stretches (seconds for
# an inverse at the "updated" or "full" fidelity). In a thread of the daemon they delayed the event loop enough
# to miss the board's 500 ms dead-host deadline; in a process of their own they cannot.

#: Linux prctl option: the signal a process gets when its parent dies (prctl(2)).
PR_SET_PDEATHSIG = 1

_worker_model: LoadedModel | None = None


def exit_with_parent(parent_pid: int) -> None:
    """In a child process: be killed (SIGKILL) when the parent dies, however it dies (SIGKILL included).

    Linux's PR_SET_PDEATHSIG through libc; if the parent died before this ran, exit now.
    """
    import ctypes
    import ctypes.util

    libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
    if libc.prctl(PR_SET_PDEATHSIG, int(signal.SIGKILL), 0, 0, 0) != 0:
        logger.warning("prctl(PR_SET_PDEATHSIG) failed (errno %d): the model worker may outlive a killed daemon",
                       ctypes.get_errno())
    if os.getppid() != parent_pid:
        os._exit(0)


def _worker_init(parent_pid: int, log_level: str) -> None:
    """In the worker, first: die with the daemon, leave Ctrl-C to it, log like it."""
    exit_with_parent(parent_pid)
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the daemon's to handle; it stops the worker
    configure_logging(log_level)


def _worker_model_or_fail() -> LoadedModel:
    if _worker_model is None:
        raise RuntimeError("the model worker has no model: start() was not called")
    return _worker_model


def _worker_start(scene_source: str) -> ModelInfo:
    """In the worker: build the model; return what the daemon needs to know about it."""
    global _worker_model
    _worker_model = model = LoadedModel(scene_source)
    return ModelInfo(model.chamber_names, list(model.scene.chamber_labels), model.rest_volume_ml, model.timings_s,
                     model.estimator.level, model.scene.raw, str(model.scene.path), model.pressure_max_pa,
                     model.wants_shape, model.effective_model())


def _worker_pressures_for(target: Target) -> InverseResult:
    return _worker_model_or_fail().pressures_for(target)


def _worker_estimate(pressures_pa: np.ndarray, with_surface: bool, with_rest_surface: bool) -> Estimate:
    model = _worker_model_or_fail()
    chamber_ml, gland_ml = model.estimate(pressures_pa)
    surface = model.outer_surface_mm(pressures_pa) if with_surface else None
    rest = model.rest_surface_mm() if with_surface and with_rest_surface else None
    return Estimate(chamber_ml, gland_ml, surface, dict(model.estimator.counts), rest)


def _worker_surface(pressures_pa: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    model = _worker_model_or_fail()
    return model.rest_surface_mm() if pressures_pa is None else model.outer_surface_mm(pressures_pa)


def worker_pool(log_level: str = "info") -> ProcessPoolExecutor:
    """A one-process pool (spawned, not forked: no copy of the daemon's event loop or threads) whose process
    dies with this one."""
    return ProcessPoolExecutor(max_workers=1, mp_context=multiprocessing.get_context("spawn"),
                               initializer=_worker_init, initargs=(os.getpid(), log_level))


class ModelWorker:
    """The :class:`LoadedModel` in a worker process that dies with the daemon, called without blocking the loop.

    Build it with :meth:`start`, which returns a worker whose model is ready (``info``).
    """

    def __init__(self, pool: ProcessPoolExecutor, info: ModelInfo):
        self._pool = pool
        self.info = info

    @classmethod
    async def start(cls, scene_source: str, log_level: str = "info") -> ModelWorker:
        """Start the worker process and build the model in it (its progress is logged from there)."""
        pool = worker_pool(log_level)
        try:
            info = await asyncio.get_running_loop().run_in_executor(pool, _worker_start, scene_source)
        except BaseException:
            pool.shutdown(wait=False, cancel_futures=True)
            raise
        return cls(pool, info)

    async def _call(self, function: Callable[..., Answer], *arguments: Any) -> Answer:
        return await asyncio.get_running_loop().run_in_executor(self._pool, function, *arguments)

    async def pressures_for(self, target: Target) -> InverseResult:
        """Setpoints for ``target``; raises the inverse's UnreachableTargetError with its reachable range."""
        return await self._call(_worker_pressures_for, target)

    async def estimate(self, pressures_pa: np.ndarray, with_surface: bool = False,
                       with_rest_surface: bool = False) -> Estimate:
        """Volumes at ``pressures_pa`` (Pa); the deformed surface (mm) only when asked, and with it the rest
        surface when asked too (the recording's reference, logged once before the first mesh)."""
        return await self._call(_worker_estimate, np.asarray(pressures_pa, dtype=float), with_surface,
                                with_rest_surface)

    async def surface(self, pressures_pa: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
        """The outer surface (positions mm, triangles) at ``pressures_pa`` (Pa), or at rest for None."""
        pressures = None if pressures_pa is None else np.asarray(pressures_pa, dtype=float)
        return await self._call(_worker_surface, pressures)

    def close(self) -> None:
        """Stop the worker process and wait for it (a pool left running is woken by the interpreter's exit
        hook through a pipe already closed, which prints an error)."""
        self._pool.shutdown(wait=True, cancel_futures=True)
