"""The simulated phantom's true shape, and the simulated board with the scanner's mechanism.

The simulated plant's chambers follow a truth the controller does not share (hil/plant.py: the calibrated
scene with its modulus times ``TRUTH_MODULUS_FACTOR`` plus the residual that takes it through the measured
phantom's volumes, tabulated in hil/plant.toml). :class:`TruthShape` solves that same model for its deformed outer
surface at the pressures the plant holds and scales it about its centre to the plant's gland volume there (the
residual has a volume, not a shape: the model's shape is the best guess of where it goes), which the virtual
camera photographs; so a simulated scan sees the phantom as it is, not as the controller's model predicts it.
Where the scene ships its outer surface's shapes (``[model] table_shapes``, as the shipped converged scene does),
the truth's shape at p is read from them at p / the modulus factor, with no solve: a hyperelastic body's shape
depends on the pressure over the modulus only (0.02 mm mean from the truth's own solve at (2, 1, 3) kPa; 1 s
against 72 s for the solve on the loaded machine). A ``--sim-truth`` scene's truth reads its own shapes, built
from the same solves as its plant (``phantom.hil.plant.truth_shapes_path``), at p. Elsewhere (a scene without
either, pressures beyond the shapes' box), the FE solves run in a process of their own (:class:`_SolverProcess`):
a CHOLMOD factorisation holds the interpreter's lock for 1.4-3.6 s (measured on the loaded two-core machine),
which in the daemon's process (its ``scan`` renders the truth) starved the board's link into DEAD_HOST.

:class:`ScannerBoard` is the simulated board (:class:`phantom.hil.sim.SimulatedBoard`) whose stepper drivers
turn the scanner of ``phantom.protocol.motion.SCANNER_AXES`` (its steps per turn set in the harness at start),
and whose ``plant_state`` also says where the rig truly is (``rig_deg``: orbit and elevation from the pulses the
drivers took).
"""

from __future__ import annotations

import logging
import weakref
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from phantom.hil.motion import SimulatedRig
from phantom.hil.plant import (
    CALIBRATED_SCENE_PATH,
    DEFAULT_PLANT_PATH,
    TRUTH_MODULUS_FACTOR,
    TRUTH_POINTS_KPA,
    load_plant,
)
from phantom.hil.sim import SimulatedBoard
from phantom.model.mesh.surface import TriangleMesh
from phantom.protocol.motion import AXES, SCANNER_AXES

if TYPE_CHECKING:
    from phantom.model.fidelity.response_table import SurfaceShapes

logger = logging.getLogger(__name__)

#: The pressure box (Pa) of a truth plant's shapes: its truth table's.
TRUTH_MAX_PA = 1e3 * TRUTH_POINTS_KPA[-1]
#: Pressures closer than this (kPa, every chamber) to the last solved ones reuse its shape.
REUSE_KPA = 0.01
#: ... and this, when the shape is scaled to the plant's gland volume (computed at the pressures asked, so the
#: volume is exact): a shape solved 0.1 kPa away differs from the true one by far less than the scanner resolves,
#: and a settled phantom's ripple (an ADC count, 0.054 kPa) no longer costs an FE solve per picture (each one
#: seconds to minutes of a loaded machine, with the daemon's scan waiting on it).
REUSE_SCALED_KPA = 0.1


class _SolverProcess:
    """The truth model's equilibria solved in one worker process (spawned: the daemon has threads), which builds
    its own copy of the model once; the caller waits without holding the interpreter's lock. The worker is
    killed when the process that made it dies, however it dies (a SIGKILLed daemon left it solving for nobody);
    Linux ties that to the thread that started it (a scan's thread of the daemon's executor, which lives as long
    as the daemon)."""

    def __init__(self, scene: str, modulus_factor: float, mesh_size_mm: float | None):
        import multiprocessing
        import os

        self.pool = ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn"),
                                        initializer=_build_worker_model,
                                        initargs=(os.getpid(), scene, modulus_factor, mesh_size_mm))
        self._end = weakref.finalize(self, _end_pool, self.pool)

    def positions_m(self, pressures_pa: np.ndarray, start: np.ndarray | None) -> np.ndarray:
        positions: np.ndarray = self.pool.submit(_worker_positions_m, pressures_pa, start).result()
        return positions

    def close(self) -> None:
        """End the worker now, a solve in it or not (:func:`_end_pool`, which also runs when this object is
        collected; once either way)."""
        self._end()


def _end_pool(pool: ProcessPoolExecutor) -> None:
    """Kill the pool's worker, a solve in it or not (a caller waiting on that solve gets BrokenProcessPool), and
    shut the pool down. Not waiting matters: at the interpreter's exit, concurrent.futures joins the pool's manager
    thread, which waits for the running solve (a sim-board asked to stop mid-solve ended only when it did, 25 s
    later on this machine idle, and past a test's 30 s wait under make test's load)."""
    for process in list(pool._processes.values()):  # the executor has no kill of its own
        process.kill()
    pool.shutdown(wait=False, cancel_futures=True)


#: The worker process's truth model (built by its initializer).
_WORKER_MODEL: Any = None


def _build_worker_model(parent_pid: int, scene: str, modulus_factor: float, mesh_size_mm: float | None) -> None:
    global _WORKER_MODEL
    from phantom.model import PhantomModel, load_scene
    from phantom.model.cluster import exit_with_parent

    exit_with_parent(parent_pid)

    model = PhantomModel.from_scene(load_scene(scene), mesh_size_mm=mesh_size_mm)
    _WORKER_MODEL = model.with_material(youngs_modulus_pa=model.material.youngs_modulus_pa * modulus_factor)


def _worker_positions_m(pressures_pa: np.ndarray, start: np.ndarray | None) -> np.ndarray:
    positions: np.ndarray = _WORKER_MODEL.equilibrium(pressures_pa, initial_positions_m=start).positions_m
    return positions


def _shipped_shapes(model: Any, path: Path | None = None) -> SurfaceShapes | None:
    """The outer surface's shapes the scene ships (``[model] table_shapes``; or those at ``path``, a truth
    plant's), or None: none shipped, or made for another mesh or box (then each shape is a solve, as without
    them)."""
    from phantom.model.fidelity.response_table import ResponseTableError, shipped_table_shapes

    try:
        return shipped_table_shapes(model, model.model_settings.pressure_max_pa if path is None else TRUTH_MAX_PA,
                                    path)
    except ResponseTableError as error:
        if path is not None:
            logger.warning("the truth shapes %s are not this truth's (%s): each shape is a solve", path, error)
        return None


class TruthShape:
    """The truth model's outer surface (mm, the phantom's frame) at chamber pressures."""

    def __init__(self, scene: str | Path = CALIBRATED_SCENE_PATH, modulus_factor: float = TRUTH_MODULUS_FACTOR,
                 mesh_size_mm: float | None = None, plant_path: str | Path | None = DEFAULT_PLANT_PATH,
                 tabulated: bool = True, shapes_path: str | Path | None = None):
        """``plant_path``: the plant file whose truth table's gland volume the surface is scaled to (None: the
        FEM's own volume, unscaled); ``tabulated``: take the shapes the scene ships where they hold the pressures
        (False: solve every shape); ``shapes_path``: the truth's own shapes (a truth plant's,
        ``phantom.hil.plant.truth_shapes_path``) instead of the scene's."""
        # the FEM's stack loads only when a truth shape is wanted
        from phantom.model import PhantomModel, load_scene

        model = PhantomModel.from_scene(load_scene(scene), mesh_size_mm=mesh_size_mm)
        self.model = model.with_material(youngs_modulus_pa=model.material.youngs_modulus_pa * modulus_factor)
        self.plant = None if plant_path is None else load_plant(plant_path)
        self.description = f"{scene} with E x {modulus_factor:g}" + (
            "" if self.plant is None else f", scaled to the gland volume of {self.plant.path}")
        self.surface_nodes, self.triangles = self.model.outer_surface()
        self.modulus_factor = float(modulus_factor)
        # the scene's shapes are its own modulus's: the truth's at p are theirs at p / factor
        self._shapes_pa_per_truth_pa = 1.0 if shapes_path is not None else 1.0 / self.modulus_factor
        self._shapes = None if not tabulated else (
            _shipped_shapes(self.model, Path(shapes_path)) if shapes_path is not None else _shipped_shapes(model))
        self._solver_args = (str(scene), self.modulus_factor, mesh_size_mm)
        self._solver: _SolverProcess | None = None
        self._last: tuple[np.ndarray, np.ndarray, TriangleMesh] | None = None
        self.solves = 0
        #: whether a shape is being solved in the solver's process now (its model built first: seconds)
        self.solving = False

    def surface(self, pressures_kpa: list[float] | np.ndarray) -> TriangleMesh:
        """The surface at these pressures (kPa, chamber order); warm-started from the last solve, whose shape is
        reused when every pressure is within REUSE_KPA of it (REUSE_SCALED_KPA when scaled to the plant's gland
        volume at these pressures)."""
        pressures = np.asarray(pressures_kpa, dtype=float)
        wanted_ml = None if self.plant is None else self.plant.truth_gland_volume_ml(pressures * 1e3)
        reuse_kpa = REUSE_KPA if wanted_ml is None else REUSE_SCALED_KPA
        if self._last is not None and np.all(np.abs(self._last[0] - pressures) <= reuse_kpa):
            shape = self._last[2]
        elif (tabulated_m := self._tabulated_m(pressures, 0.0 if wanted_ml is None else REUSE_SCALED_KPA)) is not None:
            shape = TriangleMesh(tabulated_m * 1e3, self.triangles.astype(np.int64))
        else:
            start = None if self._last is None else self._last[1]
            if self._solver is None:
                self._solver = _SolverProcess(*self._solver_args)
            self.solving = True
            try:
                positions_m = self._solver.positions_m(pressures * 1e3, start)
            finally:
                self.solving = False
            self.solves += 1
            shape = TriangleMesh(positions_m[self.surface_nodes] * 1e3, self.triangles.astype(np.int64))
            self._last = (pressures, positions_m, shape)
        return shape if wanted_ml is None else scaled_to_volume(shape, wanted_ml)

    def _tabulated_m(self, pressures_kpa: np.ndarray, margin_kpa: float) -> np.ndarray | None:
        """The outer surface's nodes (m) from the tabulated shapes, or None where they cannot say (none, or the
        pressures more than ``margin_kpa`` outside their box: a phantom held at the box's edge reads an ADC
        count or two past it, whose shape is the edge's). The truth differs from the scene's model by its modulus
        alone, and a hyperelastic body's shape depends on the pressure over the modulus only, so the truth at p
        holds the model's shape at p / factor: no solve (the truth's own shapes: at p)."""
        if self._shapes is None:
            return None
        shapes_pa = pressures_kpa * 1e3 * self._shapes_pa_per_truth_pa
        box_pa = self._shapes.table.pressure_max_pa
        if np.any(shapes_pa < -margin_kpa * 1e3) or np.any(shapes_pa > box_pa + margin_kpa * 1e3):
            return None
        return self._shapes.positions_m(np.clip(shapes_pa, 0.0, box_pa), self.surface_nodes)

    def close(self) -> None:
        """End the solver's process, if any, without waiting for a solve in it."""
        if self._solver is not None:
            self._solver.close()

    def gland_volume_ml(self, pressures_kpa: list[float] | np.ndarray) -> float:
        """The gland volume (ml) of the surface at these pressures."""
        from phantom.model.mesh.surface import enclosed_volume_ml

        return enclosed_volume_ml(self.surface(pressures_kpa))


def scaled_to_volume(mesh: TriangleMesh, volume_ml: float) -> TriangleMesh:
    """The closed surface scaled about its area-weighted centre so that it encloses ``volume_ml``."""
    from phantom.model.mesh.surface import enclosed_volume_ml, vertex_areas_mm2

    areas = vertex_areas_mm2(mesh.vertices_mm, mesh.triangles)
    centre = areas @ mesh.vertices_mm / areas.sum()
    factor = (volume_ml / enclosed_volume_ml(mesh)) ** (1.0 / 3.0)
    return TriangleMesh(centre + factor * (mesh.vertices_mm - centre), mesh.triangles)


class ScannerBoard(SimulatedBoard):
    """The simulated board driving the scanner's simulated mechanism (see the module docstring)."""

    def start(self) -> ScannerBoard:
        super().start()
        rig = SimulatedRig(self)
        for axis in range(AXES):
            rig.set_axis(axis, SCANNER_AXES[axis].steps_per_rev)
        return self

    def plant_state(self) -> dict[str, Any]:
        state = super().plant_state()
        state["rig_deg"] = [entry["angle_deg"] for entry in SimulatedRig(self).axes()]
        return state
