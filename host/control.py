"""The daemon's model side: targets -> inverse QP -> pressure setpoints; measured pressures -> volumes (-> shape).

:class:`Controller` loads the scene and its model once, precomputes the compliance (or loads it from the disk
cache) and times each stage; the daemon runs its calls in a worker thread so the link never waits on them.
"""

from __future__ import annotations

import sys
import time
from dataclasses import dataclass

import numpy as np

import phantom
from phantom import PhantomError
from phantom.host.scenes import TargetSpec

ML_PER_M3 = 1e6
PA_PER_KPA = 1e3


@dataclass
class Solution:
    """The inverse's answer to one target, in the units people see, with its cost."""

    target: TargetSpec
    pressures_pa: np.ndarray
    predicted_volume_ml: float
    predicted_chamber_volumes_ml: list[float]
    iterations: int
    solve_time_s: float
    qp_time_s: float

    def to_json(self) -> dict:
        return {"target": self.target.to_json(), "pressures_kpa": (self.pressures_pa / PA_PER_KPA).tolist(),
                "predicted_volume_ml": self.predicted_volume_ml,
                "predicted_chamber_volumes_ml": self.predicted_chamber_volumes_ml, "iterations": self.iterations,
                "solve_time_s": self.solve_time_s, "qp_time_s": self.qp_time_s}


def _progress(message: str) -> None:
    print(f"phantom daemon: {message}", file=sys.stderr, flush=True)


class Controller:
    """The scene's model, its inverse solver and its volume estimator.

    Parameters
    ----------
    scene_source : str
        ``builtin:calibrated`` (the daemon's default), another built-in name, or a scene TOML path
        (``phantom.model.load_scene``).
    report : callable(str), optional
        Where start-up progress goes (stderr by default): each stage and how long it took.
    """

    def __init__(self, scene_source: str, report=_progress):
        from phantom.model import PhantomModel, load_scene
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
        # The model keeps its scene: the inverse reads the [model] table (pressure_max_kpa, fidelity) from it, and
        # without a fidelity probes for the cheapest level within the scene's accuracy_pct (one solve per level
        # at the pressure limit).
        self.solver = InverseSolver(self.model)
        self.pressure_max_pa = float(self.solver.pressure_max_pa.max())
        self.estimator = self.solver.estimator
        self.timings_s["inverse_setup_s"] = time.perf_counter() - stage
        self.timings_s["total_s"] = time.perf_counter() - started
        probe = ""
        if self.estimator.probe_errors_pct:
            probe = ", chosen for accuracy_pct {:g} from errors {}".format(self.estimator.accuracy_pct, ", ".join(
                f"{level} {error:.3g} %" for level, error in self.estimator.probe_errors_pct.items()))
        report(f"inverse ready in {self.timings_s['inverse_setup_s']:.2f} s (fidelity {self.estimator.level}{probe}); "
               f"start-up took {self.timings_s['total_s']:.2f} s")
        self.chamber_names = list(self.model.chamber_names)
        self.rest_volume_ml = float(self.model.rest_gland_volume_m3) * ML_PER_M3
        self.wants_shape = bool(getattr(self.scene.outputs, "shape", False)) if not isinstance(
            self.scene.outputs, dict) else bool(self.scene.outputs.get("shape", False))

    def solve(self, target: TargetSpec) -> Solution:
        """The setpoints (Pa) for ``target``; raises UnreachableTargetError (a PhantomError) with the range."""
        from phantom.model.inverse import Target

        if target.kind == "volume_ml":
            inverse_target = Target(gland_volume_m3=target.values[0] / ML_PER_M3,
                                    growth_ratio=dict(target.growth_ratio) or None)
        elif target.kind == "chamber_volumes_ml":
            inverse_target = Target(chamber_volumes_m3=[None if v is None else v / ML_PER_M3 for v in target.values])
        elif target.kind == "pressures_kpa":
            inverse_target = Target(pressures_pa=[v * PA_PER_KPA for v in target.values])
        else:
            raise PhantomError(f"unknown target kind {target.kind!r}")
        result = self.solver.solve(inverse_target)
        return Solution(target, np.asarray(result.pressures_pa, dtype=float),
                        float(result.predicted_gland_volume_m3) * ML_PER_M3,
                        (np.asarray(result.predicted_chamber_volumes_m3) * ML_PER_M3).tolist(),
                        int(result.iterations), float(result.solve_time_s), float(result.qp_solve_time_s))

    def estimate(self, pressures_pa: np.ndarray) -> tuple[list[float], float]:
        """Estimated chamber volumes (ml) and gland volume (ml) at measured pressures (Pa, negative -> 0)."""
        chamber_m3, gland_m3 = self.estimator.volumes(np.clip(np.asarray(pressures_pa, dtype=float), 0.0, None))
        return (np.asarray(chamber_m3) * ML_PER_M3).tolist(), float(gland_m3) * ML_PER_M3

    def outer_surface_mm(self, pressures_pa: np.ndarray, used_nodes: np.ndarray) -> np.ndarray:
        """The deformed outer-surface nodes (mm) at measured pressures (Pa); a shape is computed only here."""
        positions_m = self.estimator.shape(np.clip(np.asarray(pressures_pa, dtype=float), 0.0, None))
        return np.asarray(positions_m)[used_nodes] * 1e3


# --- the model in its own process -------------------------------------------------------------------------
#
# The inverse and the estimator are numpy/scipy/numba work that holds the GIL for long stretches (seconds for
# an inverse at the "updated" or "full" fidelity). In a thread of the daemon they delayed the event loop enough
# to miss the board's 500 ms dead-host deadline; in a process of their own they cannot.

_worker_controller: Controller | None = None


def _worker_start(scene_source: str) -> dict:
    """In the worker: build the Controller; return what the daemon needs to know about it."""
    import signal

    global _worker_controller
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the daemon's to handle; it stops the worker
    _worker_controller = Controller(scene_source)
    controller = _worker_controller
    return {"chamber_names": controller.chamber_names, "rest_volume_ml": controller.rest_volume_ml,
            "timings_s": controller.timings_s, "fidelity": controller.estimator.level,
            "scene_raw": controller.scene.raw, "scene_path": str(controller.scene.path),
            "pressure_max_pa": controller.pressure_max_pa}


def _worker_solve(target: TargetSpec) -> Solution:
    return _worker_controller.solve(target)


def _worker_estimate(pressures_pa: np.ndarray, with_surface: bool):
    """Estimated volumes (ml), the deformed outer surface (mm) with its triangles only when asked, and the
    estimator's work counters (full solves, tangent solves, shapes formed)."""
    from phantom.host.recording import surface_mesh

    chamber_ml, gland_ml = _worker_controller.estimate(pressures_pa)
    surface = None
    if with_surface:
        model = _worker_controller.model
        used, triangles = surface_mesh(model.nodes_m, model.outer_triangles)
        surface = (_worker_controller.outer_surface_mm(pressures_pa, used), triangles)
    return chamber_ml, gland_ml, surface, dict(_worker_controller.estimator.counts)


class ModelWorker:
    """The :class:`Controller` in a worker process, called from the event loop without blocking it.

    Attributes (after :meth:`start`): ``chamber_names``, ``rest_volume_ml``, ``timings_s``, ``fidelity``,
    ``scene_raw``, ``scene_path``, ``pressure_max_pa``.
    """

    def __init__(self, scene_source: str):
        import multiprocessing
        from concurrent.futures import ProcessPoolExecutor

        self.scene_source = scene_source
        self._pool = ProcessPoolExecutor(max_workers=1, mp_context=multiprocessing.get_context("spawn"))

    async def _call(self, function, *arguments):
        import asyncio

        return await asyncio.get_running_loop().run_in_executor(self._pool, function, *arguments)

    async def start(self) -> None:
        """Build the model in the worker (progress lines go to stderr from there)."""
        for key, value in (await self._call(_worker_start, self.scene_source)).items():
            setattr(self, key, value)

    async def solve(self, target: TargetSpec) -> Solution:
        """Setpoints for ``target``; raises the inverse's UnreachableTargetError with its reachable range."""
        return await self._call(_worker_solve, target)

    async def estimate(self, pressures_pa: np.ndarray, with_surface: bool = False):
        """(chamber volumes ml, gland volume ml, surface (positions mm, triangles) or None, work counters)."""
        return await self._call(_worker_estimate, np.asarray(pressures_pa, dtype=float), with_surface)

    def close(self) -> None:
        """Stop the worker process."""
        self._pool.shutdown(wait=False, cancel_futures=True)
