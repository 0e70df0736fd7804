"""The daemon's model side: targets -> inverse QP -> pressure setpoints; measured pressures -> volumes (-> shape).

:class:`LoadedModel` loads the scene and its model once, precomputes the compliance (or loads it from the disk
cache), warms the inverse and times each stage. :class:`ModelWorker` runs it in a process of its own, which
dies with the daemon, so that the link never waits on the model.
"""

from __future__ import annotations

import asyncio
import contextlib
import io
import json
import logging
import multiprocessing
import os
import signal
import sys
import threading
import time
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, replace
from typing import Any, TextIO, TypeVar

import numpy as np

import phantom
from phantom.host.logs import configure_logging
from phantom.host.processes import descendants
from phantom.host.scenes import effective_model
from phantom.model.cluster import exit_with_parent
from phantom.model.corrections import CorrectedModel, Correction, judged, pressures_in_box
from phantom.model.measurements import CorrectionError, CorrectionStore, Measurement
from phantom.model.target import InverseResult, Target, UnreachableTargetError

logger = logging.getLogger(__name__)

#: What a function run in the worker answers.
Answer = TypeVar("Answer")

ML_PER_M3 = 1e6
PA_PER_KPA = 1e3
MM_PER_M = 1e3
#: On the full solve, measured pressures are rounded to this (Pa) before they are solved: a held target's noisy
#: mean then meets the state solved last instead of costing a new solve (most of a second) each time, which
#: would also take the CPU from the response table's build. 10 Pa moves a volume by about 0.1 %.
FULL_SOLVE_QUANTUM_PA = 10.0


class LoadedModel:
    """The scene's model, its inverse solver and its volume estimator, built once and warmed up.

    Parameters
    ----------
    scene_source : str
        ``builtin:converged`` (the daemon's default), another built-in name, or a scene TOML path, a timeline
        scene naming its model included (:func:`phantom.host.scenes.read_timeline_scene`).
    report : callable(str), optional
        Where start-up progress goes (the log by default): each stage and how long it took.
    defer_table : bool
        When the scene names the ``table`` fidelity and its table is not stored yet, answer on the full solve
        (what the table approximates, most of a second an answer) and leave the build to the caller
        (``pending_level`` is then ``"table"``; :meth:`use_level` switches once it is stored). False: build the
        table here first (minutes, with progress).
    """

    def __init__(self, scene_source: str, report: Callable[[str], None] = logger.info, defer_table: bool = False):
        # the model's stack (scipy, numba) is loaded where the model is built: in the worker process, not in the
        # daemon that imports this module
        from phantom.host.scenes import load_timeline_scene
        from phantom.model import PhantomModel

        self.report = report
        self.timings_s: dict[str, float] = {}
        started = time.perf_counter()
        report(f"loading scene {scene_source} ...")
        self.scene = load_timeline_scene(scene_source)
        self.wants_shape = bool(self.scene.outputs.shape)
        self.model = PhantomModel.from_scene(self.scene)
        self.timings_s["model_s"] = time.perf_counter() - started
        report(f"model ready in {self.timings_s['model_s']:.2f} s ({len(self.model.nodes_m)} nodes, "
               f"{len(self.model.tets)} tets); compliance ...")
        stage = time.perf_counter()
        self.rest_compliance = self.model.compliance()
        self.timings_s["compliance_s"] = time.perf_counter() - stage
        report(f"compliance ready in {self.timings_s['compliance_s']:.2f} s (computed, or loaded from "
               f"{phantom.cache_dir('compliance')}); inverse solver ...")
        #: the level the scene asks for, once it can be had (None: the one in use is it)
        self.pending_level: str | None = None
        level = self.scene.model_settings.fidelity
        if level == "table" and defer_table and not self.table_stored():
            level, self.pending_level = "full", "table"
        self._set_up(level)
        self.timings_s["total_s"] = time.perf_counter() - started
        report(f"start-up took {self.timings_s['total_s']:.2f} s")
        self.chamber_names = list(self.model.chamber_names)
        self.rest_volume_ml = float(self.model.rest_gland_volume_m3) * ML_PER_M3
        #: the outer surface as its own mesh (model node indices, triangles into them), for shapes and the rest ghost
        self._outer_surface = self.model.outer_surface()
        #: the inverse's answers for the ends of the ramps played lately (:meth:`pressures_on_ramp`)
        self._ramp_ends: dict[str, InverseResult] = {}
        #: the correction by the phantom's measured volumes in force (:meth:`set_correction`; None: none), and
        #: its size (ml)
        self.corrected: CorrectedModel | None = None
        self.correction_size_ml: float | None = None
        #: the shape inverse, made at its first target (``set_target`` with ``shape``)
        self._shape_inverse: Any = None
        #: whether the last measured pressures lay beyond what the table answers (:meth:`measured` says so once)
        self._beyond_table = False

    def table_stored(self) -> bool:
        """Whether the scene's response table is in the disk cache (or shipped), so the table level costs no build."""
        from phantom.model.fidelity.response_table import stored_response_table

        settings = self.model.model_settings
        return stored_response_table(self.model, settings.pressure_max_pa, settings.table_points) is not None

    def _set_up(self, level: str | None) -> None:
        """The estimator and the inverse at ``level`` (None: the scene's choice), warmed up where a warm-up is
        cheap (not on the full solve, where one answer costs more than what warming saves)."""
        from phantom.model.fidelity.levels import VolumeEstimator
        from phantom.model.inverse import InverseSolver

        stage = time.perf_counter()
        # The model keeps its scene: the estimator reads the [model] table (pressure_max_kpa, fidelity) from it,
        # and without a fidelity probes for the cheapest level within the scene's accuracy_pct (one solve per
        # level at the pressure limit); the table level is built here if it is not stored (minutes, with progress).
        estimator = VolumeEstimator(self.model, level=level, progress=build_progress(self.report))
        self.solver = InverseSolver(self.model, estimator=estimator)
        self.pressure_max_pa = float(self.solver.pressure_max_pa.max())
        self.estimator = self.solver.estimator
        self.timings_s["inverse_setup_s"] = time.perf_counter() - stage
        stage = time.perf_counter()
        if self.estimator.level != "full":
            self.warm_up()
        self.timings_s["warm_up_s"] = time.perf_counter() - stage
        probe = ""
        if self.estimator.probe_errors_pct:
            probe = ", chosen for accuracy_pct {:g} from errors {}".format(self.estimator.accuracy_pct, ", ".join(
                f"{level} {error:.3g} %" for level, error in self.estimator.probe_errors_pct.items()))
            discretisation = self.estimator.discretisation_error_pct
            probe += (" against the full solve on its own mesh (a mesh file is not refined here)" if discretisation
                      is None else f" against the converged answer (the mesh's own error {discretisation:.2g} %)")
        if self.estimator.table is not None:
            probe = (f", a {self.estimator.table.points_per_axis}^{self.estimator.table.n_chambers} response table "
                     f"within {self.estimator.table.check_errors_pct:.2g} % of full solves")
            if self.estimator.table.position_values is None:
                probe += ", its volumes shipped with the scene"
                if self.wants_shape and self.estimator.shapes is not None:
                    shapes = self.estimator.shapes
                    probe += (f", its outer surface's shapes too ({shapes.table.points_per_axis}^"
                              f"{shapes.table.n_chambers} points, within {shapes.check_error_m * MM_PER_M:.2g} mm "
                              "of full solves at their checks)")
                elif self.wants_shape:
                    probe += " (no shapes: each is a full solve, seconds from a near one, tens of seconds from rest)"

        if self.pending_level is not None:
            probe = f" until the {self.pending_level} level is built"
        self.report(f"inverse ready in {self.timings_s['inverse_setup_s']:.2f} s (fidelity {self.estimator.level}"
                    f"{probe}), warmed up in {self.timings_s['warm_up_s']:.2f} s")

    def use_level(self, level: str) -> None:
        """Answer on ``level`` from now on (the pending table, once stored); the correction is dropped (it was
        fitted to the level before: the daemon fits it again)."""
        self._set_up(level)
        if level == self.pending_level:
            self.pending_level = None
        self.set_correction(None)

    def set_correction(self, correction: Correction | None) -> None:
        """Correct the gland volumes of the answers from now on (None: answer with the model's own)."""
        from phantom.model.corrections import model_grid

        self.corrected = self.correction_size_ml = None
        if correction is not None:
            self.corrected = CorrectedModel(model_grid(self.estimator), correction)
            self.correction_size_ml = correction.size_ml(self.corrected.grid)
        self._ramp_ends.clear()  # the ends were solved with the correction before

    def gland_ml(self, pressures_pa: np.ndarray, model_gland_m3: float) -> float:
        """The gland volume (ml) at pressures (Pa) where the model's own is ``model_gland_m3``: corrected when a
        correction is in force."""
        model_ml = float(model_gland_m3) * ML_PER_M3
        if self.corrected is None:
            return model_ml
        return self.corrected.corrected_ml(np.asarray(pressures_pa, dtype=float) / PA_PER_KPA, model_ml)

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
        """What a scene must match to run on this model (see :func:`phantom.host.scenes.effective_model`): the
        level it will answer on (the pending table, not the full solve it serves on meanwhile)."""
        return effective_model(self.scene, fidelity=self.pending_level or self.estimator.level,
                               pressure_max_kpa=self.pressure_max_pa / PA_PER_KPA)

    def pressures_for(self, target: Target) -> InverseResult:
        """The setpoints (Pa) for ``target``; raises UnreachableTargetError (a PhantomError) with the range.

        With a correction in force, a gland volume target is met by the corrected volume: the inverse is asked
        for the model's volumes that the correction takes to the target (:meth:`CorrectedModel.pressures_for_ml`,
        a few inverses), and the answer's predicted gland volume is the corrected one. Chamber volume and
        pressure targets are the model's own pressures (the measurements are of the gland), their predicted gland
        volume the corrected one too: the daemon's estimates are, and a pressure target is reached once the
        estimate meets its prediction (before: never, once a correction moved the gland by over 1 % there)."""
        if self.corrected is None:
            return self.solver.pressures_for(target)
        if target.kind != "volume":
            answer = self.solver.pressures_for(target)
            gland_ml = self.gland_ml(np.asarray(answer.pressures_pa), answer.predicted_gland_volume_m3)
            return self._with_band(replace(answer, predicted_gland_volume_m3=gland_ml / ML_PER_M3))
        assert target.gland_volume_m3 is not None  # the kind says so
        target_ml = target.gland_volume_m3 * ML_PER_M3
        corrected = self.corrected
        answers: list[InverseResult] = []

        def inverse_kpa(volume_ml: float) -> np.ndarray:
            try:
                answers.append(self.solver.pressures_for(replace(target, gland_volume_m3=volume_ml / ML_PER_M3)))
            except UnreachableTargetError as error:
                # the model's range, moved by what the correction adds here, is the corrected model's
                moved_ml = target_ml - volume_ml
                raise UnreachableTargetError(
                    f"{target_ml:.2f} ml with the correction in force ({corrected.describe()}) is the model's "
                    f"{volume_ml:.2f} ml: {error}",
                    None if error.gland_range_ml is None else
                    (error.gland_range_ml[0] + moved_ml, error.gland_range_ml[1] + moved_ml), corrected=True) from None
            return np.asarray(answers[-1].pressures_pa, dtype=float) / PA_PER_KPA

        _, corrected_ml, _ = corrected.pressures_for_ml(target_ml, inverse_kpa)
        last = answers[-1]
        return self._with_band(InverseResult(target, last.pressures_pa, corrected_ml / ML_PER_M3,
                                             last.predicted_chamber_volumes_m3,
                                             sum(answer.iterations for answer in answers),
                                             sum(answer.solve_time_s for answer in answers),
                                             sum(answer.qp_solve_time_s for answer in answers),
                                             [entry for answer in answers for entry in answer.history]))

    def _with_band(self, answer: InverseResult) -> InverseResult:
        """The answer with the correction's 95 % band (ml) at its pressures and its number of measurements."""
        if self.corrected is None:
            return answer
        _, band_ml = self.corrected.gland_band_ml(np.asarray(answer.pressures_pa, dtype=float) / PA_PER_KPA)
        return replace(answer, band_ml=band_ml, measurements=self.corrected.correction.count)

    def measured(self, pressures_pa: np.ndarray) -> np.ndarray:
        """Measured pressures (Pa) as the estimator takes them: negative ones 0; on the table no further over its
        box than it answers (a sensor a count or two over the box is in its linear extension; one far over it, a
        fault, is estimated at the extension's edge, and the log says so once per excursion: the table refuses
        it, and a refusal would leave the daemon without an estimate); and on the full solve rounded to
        FULL_SOLVE_QUANTUM_PA."""
        pressures = np.clip(np.asarray(pressures_pa, dtype=float), 0.0, None)
        table = self.estimator.table
        if table is not None:
            edge_pa = table.pressure_max_pa + table.extension_pa
            beyond = bool(np.any(pressures > edge_pa))
            if beyond and not self._beyond_table:
                logger.warning("measured pressures %s kPa lie outside the model's box, 0-%g kPa, further than its "
                               "table answers (%g kPa): the volumes are estimated at the table's edge, %g kPa, "
                               "until they are back", ", ".join(f"{p:g}" for p in pressures / PA_PER_KPA),
                               table.pressure_max_pa / PA_PER_KPA, table.extension_pa / PA_PER_KPA,
                               edge_pa / PA_PER_KPA)
            self._beyond_table = beyond
            pressures = np.minimum(pressures, edge_pa)
        if self.estimator.level == "full":
            pressures = np.round(pressures / FULL_SOLVE_QUANTUM_PA) * FULL_SOLVE_QUANTUM_PA
        return np.asarray(pressures, dtype=float)
    def pressures_on_ramp(self, start: Target, end: Target, target: Target) -> InverseResult:
        """The setpoints for ``target``, a point of a ramp from ``start`` to ``end`` (targets of one kind): on the
        straight line between the inverse's answers for the two ends, where the line meets the target's volume.

        Solving each point of a ramp on its own gave setpoints that jumped by 0.1-0.2 kPa from one control tick
        to the next, down then up (the QP's answer is not unique: a volume can be shared between chambers in many
        ways, and the answer moved between them). On the line every setpoint moves monotonically from its
        start to its end value as the target moves, and the ramp ends on the inverse's own answer.
        A pressure ramp is its own line.
        """
        if target.kind == "pressures":
            return self.pressures_for(target)
        from scipy.optimize import brentq

        started = time.perf_counter()
        first, last = self._ramp_end(start), self._ramp_end(end)
        step_pa = np.asarray(last.pressures_pa, dtype=float) - np.asarray(first.pressures_pa, dtype=float)
        evaluations = [0]

        def volume_m3(fraction: float) -> tuple[np.ndarray, float, float]:
            """Chamber volumes, gland volume and the target's own measure of volume at a point of the line."""
            evaluations[0] += 1
            pressures_pa = np.asarray(first.pressures_pa, dtype=float) + fraction * step_pa
            chambers, model_gland = self.estimator.volumes(pressures_pa)
            gland = self.gland_ml(pressures_pa, float(model_gland)) / ML_PER_M3
            measure = float(gland) if target.kind == "volume" else float(sum(
                chambers[index] for index, value in enumerate(target.values) if value is not None))
            return np.asarray(chambers, dtype=float), float(gland), measure

        goal_m3 = float(sum(value for value in target.values if value is not None))
        low_m3, high_m3 = volume_m3(0.0)[2], volume_m3(1.0)[2]
        if (goal_m3 - low_m3) * (goal_m3 - high_m3) >= 0:  # at (or past) an end: that end
            fraction = 0.0 if abs(goal_m3 - low_m3) <= abs(goal_m3 - high_m3) else 1.0
        else:
            fraction = float(brentq(lambda f: volume_m3(f)[2] - goal_m3, 0.0, 1.0, xtol=1e-9))
        chambers, gland, _ = volume_m3(fraction)
        return InverseResult(target, np.asarray(first.pressures_pa, dtype=float) + fraction * step_pa, gland,
                             chambers, evaluations[0], time.perf_counter() - started, 0.0)

    def _ramp_end(self, target: Target) -> InverseResult:
        """The inverse's answer for a ramp's end, solved once per ramp (the last few are kept)."""
        key = repr(target)
        if key not in self._ramp_ends:
            if len(self._ramp_ends) >= 8:
                self._ramp_ends.pop(next(iter(self._ramp_ends)))
            self._ramp_ends[key] = self.pressures_for(target)
        return self._ramp_ends[key]

    def estimate(self, pressures_pa: np.ndarray) -> tuple[list[float], float, float]:
        """Estimated chamber volumes (ml), gland volume (ml, corrected when a correction is in force) and the
        model's own gland volume (ml) at measured pressures (Pa, negative -> 0).

        The chambers' air volumes are the model's: a scan measures the gland's outer surface, which says how much
        the gland grew but not how the air inside it is shared between the chambers (the correction's split per
        chamber is its smoothness, not a measurement)."""
        measured = self.measured(pressures_pa)
        chamber_m3, gland_m3 = self.estimator.volumes(measured)
        return ((np.asarray(chamber_m3) * ML_PER_M3).tolist(), self.gland_ml(measured, float(gland_m3)),
                float(gland_m3) * ML_PER_M3)

    def gland_band(self, pressures_pa: np.ndarray) -> tuple[float, float] | None:
        """The corrected gland volume (ml) at measured pressures (Pa) and the half-width of the correction's 95 %
        band there (ml); None without a correction in force."""
        if self.corrected is None:
            return None
        return self.corrected.gland_band_ml(self.measured(pressures_pa) / PA_PER_KPA)

    def rest_surface_mm(self) -> tuple[np.ndarray, np.ndarray]:
        """The outer surface at rest: positions (mm, (n, 3)) and triangles ((k, 3) indices into them)."""
        used, triangles = self._outer_surface
        return np.asarray(self.model.nodes_m)[used] * MM_PER_M, triangles

    def outer_surface_mm(self, pressures_pa: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The deformed outer surface at pressures (Pa): positions (mm) and triangles; a shape is formed only here."""
        used, triangles = self._outer_surface
        return np.asarray(self.estimator.shape(self.measured(pressures_pa), nodes=used)) * MM_PER_M, triangles


    def shape_answer(self, shape: str | dict[str, Any], labels: list[int] | None, refine_solves: int) -> dict[str, Any]:
        """The shape inverse (:mod:`phantom.model.shape_inverse`) for a target gland: ``shape`` a file on this
        machine or a mesh given in the request (:func:`~phantom.model.shape_file.surface_from_json`). Its answer
        as JSON (kPa, mm, ml), without the surfaces. PhantomError for a bad shape or a scene without a table of
        shapes (its build is minutes: not in the daemon)."""
        from phantom.model.shape_file import read_target_surface, surface_from_json
        from phantom.model.shape_inverse import ShapeInverse, surface_shapes

        if self._shape_inverse is None:
            self._shape_inverse = ShapeInverse(self.model, surface_shapes(self.model, build=False),
                                               self.pressure_max_pa)
        target = read_target_surface(shape, labels) if isinstance(shape, str) else surface_from_json(shape)
        result = self._shape_inverse.solve(target, refine_solves, progress=self.report)
        answer: dict[str, Any] = result.to_json(list(self.scene.chamber_labels))
        answer["source"] = shape if isinstance(shape, str) else f"a mesh of {len(target.vertices_mm)} vertices"
        if self.corrected is not None:
            answer["notes"].append("the model's own shapes: the correction by measured volumes is of the gland's "
                                   "volume, not its shape")
        return answer


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
    #: the level the scene asks for while the worker answers on ``fidelity`` until it is built (None: it is)
    pending_fidelity: str | None = None


@dataclass(frozen=True)
class Estimate:
    """Volumes at measured pressures, the surface when asked, and the estimator's work counters."""

    chamber_volumes_ml: list[float]
    gland_volume_ml: float
    surface_mm: tuple[np.ndarray, np.ndarray] | None
    counts: dict[str, int]
    rest_surface_mm: tuple[np.ndarray, np.ndarray] | None = None
    #: the model's own gland volume (ml), before the correction in force (None without one)
    model_gland_volume_ml: float | None = None
    #: the correction in force: its size (largest magnitude over the pressure box, ml) and from how many
    #: measurements (None and 0 without one)
    correction_size_ml: float | None = None
    correction_count: int = 0


# --- the model in its own process -------------------------------------------------------------------------
#
# The inverse and the estimator are numpy/scipy/numba work that holds the GIL for long stretches (seconds for
# an inverse at the "updated" or "full" fidelity). In a thread of the daemon they delayed the event loop enough
# to miss the board's 500 ms dead-host deadline; in a process of their own they cannot.

_worker_model: LoadedModel | None = None


def _worker_init(parent_pid: int, log_level: str, messages: Any = None) -> None:
    """In the worker, first: die with the daemon, leave Ctrl-C to it, log like it; and, given a queue, send what
    it says (its log lines, and the model's notices on stderr: compiling kernels, meshing) there too."""
    exit_with_parent(parent_pid)
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the daemon's to handle; it stops the worker
    configure_logging(log_level)
    if messages is not None:
        logging.getLogger("phantom").addHandler(_MessageHandler(messages))
        sys.stderr = _NoticeTee(sys.stderr, messages)


class _MessageHandler(logging.Handler):
    """Log records of INFO and above, as their text, onto a queue (never blocking the worker)."""

    def __init__(self, messages: Any):
        super().__init__(logging.INFO)
        self.messages = messages

    def emit(self, record: logging.LogRecord) -> None:
        with contextlib.suppress(Exception):
            self.messages.put_nowait(record.getMessage())


class _NoticeTee(io.TextIOBase):
    """stderr that also puts each line the model prints as a notice (``phantom: meshing ...``) onto a queue."""

    def __init__(self, stream: TextIO, messages: Any):
        self.stream, self.messages, self._line = stream, messages, ""

    def write(self, text: str) -> int:
        self._line += text
        *lines, self._line = self._line.split("\n")
        for line in lines:
            if line.startswith("phantom: "):
                with contextlib.suppress(Exception):
                    self.messages.put_nowait(line.removeprefix("phantom: "))
        return self.stream.write(text)

    def flush(self) -> None:
        self.stream.flush()

    def fileno(self) -> int:
        return self.stream.fileno()


class WorkerMessages:
    """What the model worker says while it works, relayed to ``on_message(text)`` by a thread of the daemon (the
    start-up's progress: which stage of a cold start it is in)."""

    def __init__(self, on_message: Callable[[str], None]):
        self.queue: Any = multiprocessing.get_context("spawn").Queue()
        self._thread = threading.Thread(target=self._relay, args=(on_message,), name="model worker messages",
                                        daemon=True)
        self._thread.start()

    def _relay(self, on_message: Callable[[str], None]) -> None:
        while True:
            try:
                text = self.queue.get()
            except (EOFError, OSError):
                return
            if text is None:
                return
            on_message(str(text))

    def close(self) -> None:
        with contextlib.suppress(Exception):
            self.queue.put(None)
        self._thread.join(2.0)
        self.queue.close()
        self.queue.cancel_join_thread()


def _worker_model_or_fail() -> LoadedModel:
    if _worker_model is None:
        raise RuntimeError("the model worker has no model: start() was not called")
    return _worker_model


def _worker_start(scene_source: str, defer_table: bool = False) -> ModelInfo:
    """In the worker: build the model; return what the daemon needs to know about it."""
    global _worker_model
    _worker_model = LoadedModel(scene_source, defer_table=defer_table)
    return _worker_info()


def _worker_info() -> ModelInfo:
    model = _worker_model_or_fail()
    return ModelInfo(model.chamber_names, list(model.scene.chamber_labels), model.rest_volume_ml,
                     dict(model.timings_s), model.estimator.level, model.scene.raw, str(model.scene.path),
                     model.pressure_max_pa, model.wants_shape, model.effective_model(), model.pending_level)


def _worker_use_level(level: str) -> ModelInfo:
    _worker_model_or_fail().use_level(level)
    return _worker_info()


def _worker_pressures_for(target: Target) -> InverseResult:
    return _worker_model_or_fail().pressures_for(target)


def _worker_pressures_on_ramp(start: Target, end: Target, target: Target) -> InverseResult:
    return _worker_model_or_fail().pressures_on_ramp(start, end, target)


def _worker_estimate(pressures_pa: np.ndarray, with_surface: bool, with_rest_surface: bool) -> Estimate:
    model = _worker_model_or_fail()
    chamber_ml, gland_ml, model_gland_ml = model.estimate(pressures_pa)
    surface = model.outer_surface_mm(pressures_pa) if with_surface else None
    rest = model.rest_surface_mm() if with_surface and with_rest_surface else None
    corrected = model.corrected
    if corrected is None:
        return Estimate(chamber_ml, gland_ml, surface, dict(model.estimator.counts), rest)
    return Estimate(chamber_ml, gland_ml, surface, dict(model.estimator.counts), rest, model_gland_ml,
                    model.correction_size_ml, corrected.correction.count)


def _worker_gland_band(pressures_pa: np.ndarray) -> tuple[float, float] | None:
    return _worker_model_or_fail().gland_band(pressures_pa)


def _worker_shape_answer(shape: str | dict[str, Any], labels: list[int] | None, refine_solves: int) -> dict[str, Any]:
    return _worker_model_or_fail().shape_answer(shape, labels, refine_solves)


def _worker_set_correction(correction: Correction | None) -> None:
    _worker_model_or_fail().set_correction(correction)


def _worker_surface_json(pressures_pa: np.ndarray | None) -> str:
    model = _worker_model_or_fail()
    positions_mm, triangles = model.rest_surface_mm() if pressures_pa is None else model.outer_surface_mm(pressures_pa)
    return json.dumps({"positions_mm": np.round(positions_mm, 4).tolist(),
                       "triangles": np.asarray(triangles).tolist()}, separators=(",", ":"))


# --- the correction's fit, in a process of its own ------------------------------------------------------------
#
# A fit takes seconds (4.5 s for 8 measurements, 17 s for 27 on the converged model on this two-core machine:
# every candidate's leave-one-out is a quadratic programme per measurement left out). In the model worker it
# would hold every inverse and estimate for that long; in a process of its own the worker answers with the
# correction in force until the new one is set.

_fitter_grids: dict[tuple[str, str], Any] = {}


@dataclass(frozen=True)
class FitAnswer:
    """A fit of the store's measurements: the correction (None: no measurements, or ``error`` says why none),
    what the status shows of it (``summary``: :meth:`Correction.summary`), the store's signature when it was
    read, how many measurements it held, and how long the fit took."""

    correction: Correction | None
    summary: dict[str, Any] | None
    error: str | None
    signature: tuple[int, int, int] | None
    stored: int
    fit_s: float


def _fitter_grid(scene_source: str, level: str) -> Any:
    """The scene's model on ``level`` as the correction sees it (:func:`phantom.model.corrections.model_grid`),
    made once per process. CorrectionError while the model's response table is not stored (the grid is its):
    it is not built here."""
    key = (scene_source, level)
    if key not in _fitter_grids:
        from phantom.host.scenes import load_timeline_scene
        from phantom.model import PhantomModel
        from phantom.model.corrections import model_grid
        from phantom.model.fidelity.levels import VolumeEstimator
        from phantom.model.fidelity.response_table import stored_response_table

        model = PhantomModel.from_scene(load_timeline_scene(scene_source))
        settings = model.model_settings
        if stored_response_table(model, settings.pressure_max_pa, settings.table_points) is None:
            raise CorrectionError("the model's response table is not built yet: the correction is fitted on its "
                                  "grid once it is")
        _fitter_grids[key] = model_grid(VolumeEstimator(model, level=level), scene_source)
    return _fitter_grids[key]


def _fitter_fit(scene_source: str, level: str, store_path: str) -> FitAnswer:
    """In the fitter: the correction of the model by the store's measurements, or why there is none."""
    from phantom.model.corrections import cached_fit

    started = time.perf_counter()
    store = CorrectionStore(store_path)
    signature = store.signature()
    stored = 0
    try:
        entries = store.entries()
        stored = len(entries)
        if not entries:
            return FitAnswer(None, None, None, signature, 0, 0.0)
        # the unconfirmed wait for a person, the refused (a volume no gland has) for one to remove them
        confirmed = [entry for entry in entries if entry.status == "confirmed"]
        if not confirmed:
            refused = "".join(f"; measurement {number} refused: {entry.reason} (`phantom corrections remove "
                              f"{number}`)" for number, entry in enumerate(entries, start=1)
                              if entry.status == "refused")
            return FitAnswer(None, None, f"none of the {stored} stored measurement(s) is confirmed (`phantom "
                             f"corrections list`){refused}", signature, stored, 0.0)
        grid = _fitter_grid(scene_source, level)
        correction = cached_fit(confirmed, grid)
        return FitAnswer(correction, correction.summary(grid), None, signature, stored,
                         time.perf_counter() - started)
    except Exception as error:  # anything a store or a fit raises leaves the model's answers
        why = str(error) if isinstance(error, CorrectionError) else f"{type(error).__name__}: {error}"
        return FitAnswer(None, None, why, signature, stored, time.perf_counter() - started)


def _fitter_record(scene_source: str, level: str, store_path: str, measurement: Measurement) -> FitAnswer:
    """In the fitter: store ``measurement`` (with the model's own volume there) and fit again. CorrectionError,
    and nothing stored, for a measurement this model cannot take (another chamber count, a pressure beyond its
    grid)."""
    grid = _fitter_grid(scene_source, level)
    pressures = np.asarray(measurement.pressures_kpa, dtype=float)
    chambers = grid.chamber_ml.shape[-1]
    if len(pressures) != chambers:
        raise CorrectionError(f"a measurement of this phantom has {chambers} pressures (one per chamber), got "
                              f"{len(pressures)}: is it of another phantom?")
    on_box = pressures_in_box(pressures, float(grid.points_kpa[-1]), "a measurement's pressures")
    store = CorrectionStore(store_path)
    stored = replace(measurement, model=scene_source, model_volume_ml=grid.gland_ml(on_box))
    # a call retried after the fitter died (SIGTERM to the daemon's process group mid-fit) finds its measurement
    # stored already, judged then: it is not stored (nor judged) twice (compared as stored with the entry's status:
    # a refused entry, a volume no gland has, cannot be made confirmed to compare)
    kept = next((entry for entry in store.entries()
                 if replace(stored, status=entry.status, reason=entry.reason) == entry), None)
    if kept is None:
        kept = judged(stored, grid, store.confirmed(), scene_source)
        store.add(kept)
    answer = _fitter_fit(scene_source, level, store_path)
    if kept.status != "confirmed":
        return replace(answer, error=f"the scan was stored UNCONFIRMED, left out of the fit: {kept.reason} "
                       f"(`phantom corrections confirm N` if it is right)")
    return answer


def worker_pool(log_level: str = "info", messages: WorkerMessages | None = None) -> ProcessPoolExecutor:
    """A one-process pool (spawned, not forked: no copy of the daemon's event loop or threads) whose process
    dies with this one; what it says goes to ``messages`` too."""
    return ProcessPoolExecutor(max_workers=1, mp_context=multiprocessing.get_context("spawn"),
                               initializer=_worker_init,
                               initargs=(os.getpid(), log_level, None if messages is None else messages.queue))


def end_pool(pool: ProcessPoolExecutor) -> None:
    """Stop a worker pool now, whatever its worker is doing, with every process the worker started: a worker
    building a response table has a pool of its own, whose processes are not told when their parent dies (left
    running under PID 1, one spinning, one hung on a pipe, when the daemon stopped during the build)."""
    workers = list(getattr(pool, "_processes", None) or {})  # the executor keeps its processes by pid
    for pid in [*(child for worker in workers for child in descendants(worker)), *workers]:
        with contextlib.suppress(ProcessLookupError, PermissionError):
            os.kill(pid, signal.SIGKILL)
    pool.shutdown(wait=False, cancel_futures=True)


async def _started_pool(scene_source: str, log_level: str, defer_table: bool,
                        messages: WorkerMessages | None) -> tuple[ProcessPoolExecutor, ModelInfo]:
    """A worker pool whose process has built the model (:func:`_worker_start`), and the model's info; a pool
    whose start failed is ended with every process it started."""
    pool = worker_pool(log_level, messages)
    try:
        info = await asyncio.get_running_loop().run_in_executor(pool, _worker_start, scene_source, defer_table)
    except BaseException:
        end_pool(pool)
        raise
    return pool, info


class ModelWorker:
    """The :class:`LoadedModel` in a worker process that dies with the daemon, called without blocking the loop.

    Build it with :meth:`start`, which returns a worker whose model is ready (``info``).
    """

    def __init__(self, pool: ProcessPoolExecutor, info: ModelInfo, scene_source: str = "", log_level: str = "info",
                 phantom: str = "default"):
        self._pool = pool
        self.info = info
        self._messages: WorkerMessages | None = None
        self._scene_source = scene_source
        self._log_level = log_level
        self._replacing = asyncio.Lock()
        #: workers started again after one died (the OOM killer's SIGKILL): each rebuilt its model from the cache
        self.restarts = 0
        #: the phantom whose measured volumes correct the model's answers, and their store
        self.phantom = phantom
        self.store = CorrectionStore.for_phantom(phantom)
        #: the last fit of the store (what is in force), the process fits run in, and the fit running now
        self.fit: FitAnswer | None = None
        self._fitter: ProcessPoolExecutor | None = None
        self._fitting: asyncio.Task[FitAnswer] | None = None

    @classmethod
    async def start(cls, scene_source: str, log_level: str = "info", defer_table: bool = False,
                    on_message: Callable[[str], None] | None = None, phantom: str = "default") -> ModelWorker:
        """Start the worker process and build the model in it (its progress is logged from there, and told to
        ``on_message`` as it comes). ``defer_table``: answer on the full solve while a table that is not stored
        yet is built elsewhere (``info.pending_fidelity``; :meth:`use_level` once it is stored). The answers are
        corrected by the measured volumes of ``phantom`` (its :class:`CorrectionStore`): the first fit is made
        before this returns (seconds with many measurements), so that the first answer is corrected already.
        CorrectionError for a name no store can have."""
        CorrectionStore.for_phantom(phantom)  # a bad name fails before anything is started
        messages = WorkerMessages(on_message) if on_message is not None else None
        try:
            pool, info = await _started_pool(scene_source, log_level, defer_table, messages)
        except BaseException:
            if messages is not None:
                messages.close()
            raise
        worker = cls(pool, info, scene_source, log_level, phantom)
        worker._messages = messages
        try:
            if on_message is not None and worker.store.signature() is not None:
                on_message(f"fitting the correction to phantom {phantom!r}'s measurements ({worker.store.path})")
            await worker.refit()
        except BaseException:
            worker.close()
            raise
        return worker

    # --- the correction in force --------------------------------------------------------------------------
    async def refit(self) -> FitAnswer:
        """Fit the correction to the store now (in the fitter process) and put it in force; the fit. A fit
        already running is waited for instead when the store has not changed since it started."""
        if self._fitting is None or self._fitting.done():
            self._fitting = asyncio.ensure_future(self._fit_and_apply())
        return await asyncio.shield(self._fitting)

    def check_store(self) -> None:
        """Start a fit when the store changed since the last one (one stat: cheap enough before every answer);
        the answers keep the correction in force until the new one is set."""
        if self._fitting is not None and not self._fitting.done():
            return
        if self.fit is not None and self.store.signature() == self.fit.signature:
            return
        self._fitting = asyncio.ensure_future(self._fit_and_apply())
        self._fitting.add_done_callback(_log_failed_fit)

    async def _fit_and_apply(self) -> FitAnswer:
        if self.store.signature() is None:  # nothing measured: no fitter process, no second model in memory
            answer = FitAnswer(None, None, None, None, 0, 0.0)
        elif self.info.pending_fidelity is not None:
            answer = FitAnswer(None, None, f"the model answers on the {self.info.fidelity} level until the "
                               f"{self.info.pending_fidelity} level is built: the correction is fitted then",
                               self.store.signature(), 0, 0.0)
        else:
            try:
                answer = await self._in_fitter(_fitter_fit, self._scene_source, self.info.fidelity,
                                               str(self.store.path))
            except BrokenProcessPool as error:  # died twice: the model's own answers, and why (never a failed start)
                answer = FitAnswer(None, None, f"the fit's process died ({error}): the model's own answers until the "
                                   f"store changes", self.store.signature(), 0, 0.0)
        await self._call(_worker_set_correction, answer.correction)
        self._put_in_force(answer)
        return answer

    async def _in_fitter(self, function: Callable[..., Answer], *arguments: Any) -> Answer:
        """``function(*arguments)`` in the fitter process (started on first use; started again when it died)."""
        if self._fitter is None:
            self._fitter = worker_pool(self._log_level)
        try:
            return await asyncio.get_running_loop().run_in_executor(self._fitter, function, *arguments)
        except BrokenProcessPool:
            end_pool(self._fitter)
            self._fitter = worker_pool(self._log_level)
        return await asyncio.get_running_loop().run_in_executor(self._fitter, function, *arguments)

    def _put_in_force(self, answer: FitAnswer) -> None:
        self.fit = answer
        _, text, level = self.correction_event()
        logger.log(logging.WARNING if level == "WARN" else logging.INFO, "%s", text)

    async def record_measurement(self, pressures_kpa: list[float], volume_ml: float, method: str = "scan",
                                 scan_file: str | None = None) -> dict[str, Any]:
        """Store a measured gland volume of the phantom at these pressures (kPa) and fit the correction again;
        the correction now in force (:meth:`Correction.summary`: its kind, ``count``, ``size_ml``, the
        leave-one-out). CorrectionError for a bad measurement (nothing stored), or when the measurements give no
        correction (the measurement is stored; the error says why)."""
        if self.info.pending_fidelity is not None:
            raise CorrectionError(f"the model answers on the {self.info.fidelity} level until the "
                                  f"{self.info.pending_fidelity} level is built: measurements are taken after")
        measurement = Measurement.now(pressures_kpa, volume_ml, method, scan_file)
        while self._fitting is not None and not self._fitting.done():  # one fit at a time, the latest last
            await asyncio.shield(self._fitting)
        self._fitting = asyncio.ensure_future(self._record_and_apply(measurement))
        answer = await asyncio.shield(self._fitting)
        if answer.summary is None or answer.error is not None:
            raise CorrectionError(f"the measurement was stored in {self.store.path}, but "
                                  f"{'no correction is in force: ' if answer.summary is None else ''}{answer.error}")
        return answer.summary

    async def _record_and_apply(self, measurement: Measurement) -> FitAnswer:
        answer = await self._in_fitter(_fitter_record, self._scene_source, self.info.fidelity, str(self.store.path),
                                       measurement)
        await self._call(_worker_set_correction, answer.correction)
        self._put_in_force(answer)
        return answer

    def correction_event(self) -> tuple[str, str, str]:
        """The correction in force, or why there is none, as an event (kind, text, level) for the daemon's log."""
        fit, name = self.fit, f"phantom {self.phantom!r}"
        if fit is None or (fit.summary is None and fit.error is None):
            return "correction", f"no measured volumes of {name} in {self.store.path}: the model's answers are its " \
                "own", "INFO"
        if fit.summary is None:
            return "correction", f"no correction of {name} in force: {fit.error}", "WARN"
        summary = fit.summary
        # the unconfirmed and the refused stored beside them: the listing says which and why
        left_out = (f" ({fit.stored - summary['count']} of the {fit.stored} stored left out of it: `phantom "
                    f"corrections list`)" if fit.stored > summary["count"] else "")
        return "correction", (f"correction of {name} in force: {summary['kind']} from {summary['count']} "
                              f"measurement(s){left_out}, up to {summary['size_ml']:.3f} ml over the pressure box, "
                              f"leave-one-out {_leave_one_out_words(summary)} (fitted in {fit.fit_s:.1f} s)"), "INFO"

    def correction_status(self) -> dict[str, Any]:
        """What the status shows of the correction: the phantom, its store, whether one is in force (then its
        :meth:`Correction.summary`), why none is, and whether a fit is running."""
        fit = self.fit
        return {"phantom": self.phantom, "store": str(self.store.path),
                "in_force": fit is not None and fit.summary is not None,
                "correction": None if fit is None else fit.summary,
                "error": None if fit is None else fit.error, "stored": 0 if fit is None else fit.stored,
                "fit_s": None if fit is None else round(fit.fit_s, 3),
                "fitting": self._fitting is not None and not self._fitting.done()}

    async def _call(self, function: Callable[..., Answer], *arguments: Any) -> Answer:
        """``function(*arguments)`` in the worker; a worker found dead is replaced and the call made once more."""
        pool = self._pool
        try:
            return await asyncio.get_running_loop().run_in_executor(pool, function, *arguments)
        except BrokenProcessPool:
            await self._replace(pool)
        return await asyncio.get_running_loop().run_in_executor(self._pool, function, *arguments)

    async def shape_answer(self, shape: str | dict[str, Any], labels: list[int] | None,
                           refine_solves: int) -> dict[str, Any]:
        """The shape inverse's answer for a target gland (:meth:`LoadedModel.shape_answer`), in the worker: seconds
        with full solves, which the event loop does not wait on."""
        return await self._call(_worker_shape_answer, shape, labels, refine_solves)

    async def use_level(self, level: str) -> ModelInfo:
        """Answer on ``level`` from now on (the pending table, once the build stored it); the new ``info``. The
        correction is fitted again on it."""
        self.info = await self._call(_worker_use_level, level)
        await self.refit()
        return self.info

    async def _replace(self, broken: ProcessPoolExecutor) -> None:
        """Start a new worker in place of ``broken`` (once, whoever found it dead first); its model is rebuilt
        from the cached response table. A worker that cannot be started again raises, and the caller fails."""
        async with self._replacing:
            if self._pool is not broken:
                return
            logger.warning("the model worker died (killed, out of memory?): starting a new one")
            broken.shutdown(wait=False, cancel_futures=True)
            # a table that is not stored yet is not built here (minutes): the new worker answers on the full
            # solve, as the first did, until the daemon's background build switches it
            pool, info = await _started_pool(self._scene_source, self._log_level, True, self._messages)
            # the new worker answers with the correction in force, and the store is read again at the next answer
            if self.fit is not None and self.fit.correction is not None and info.pending_fidelity is None:
                await asyncio.get_running_loop().run_in_executor(pool, _worker_set_correction, self.fit.correction)
            self.fit = None if self.fit is None else replace(self.fit, signature=None)
            self._pool = pool
            self.info = info
            self.restarts += 1
            logger.warning("the model worker was replaced (%d since the daemon started)", self.restarts)

    async def _store_in_force(self) -> None:
        """Before a target is solved: a store changed since the last fit is fitted, and the fit waited for (under
        a second), so that the target is solved on the correction its estimates will be made with (before: solved
        on the one before, it never came to its estimate, or was said reached 5.8 % off). A fit that fails leaves
        the one before in force (logged)."""
        self.check_store()
        fitting = self._fitting
        if fitting is not None and not fitting.done():
            with contextlib.suppress(Exception):
                await asyncio.shield(fitting)

    async def pressures_for(self, target: Target) -> InverseResult:
        """Setpoints for ``target`` (a gland volume with the correction in force, the store's latest); raises the
        inverse's UnreachableTargetError with its reachable range."""
        await self._store_in_force()
        return await self._call(_worker_pressures_for, target)

    async def pressures_on_ramp(self, start: Target, end: Target, target: Target) -> InverseResult:
        """Setpoints for ``target`` on the ramp from ``start`` to ``end`` (:meth:`LoadedModel.pressures_on_ramp`)."""
        await self._store_in_force()
        return await self._call(_worker_pressures_on_ramp, start, end, target)

    async def estimate(self, pressures_pa: np.ndarray, with_surface: bool = False,
                       with_rest_surface: bool = False) -> Estimate:
        """Volumes at ``pressures_pa`` (Pa; the gland's corrected, the model's own beside it); the deformed
        surface (mm) only when asked, and with it the rest surface when asked too (the recording's reference,
        logged once before the first mesh)."""
        self.check_store()
        return await self._call(_worker_estimate, np.asarray(pressures_pa, dtype=float), with_surface,
                                with_rest_surface)

    async def gland_band(self, pressures_pa: np.ndarray) -> tuple[float, float] | None:
        """The corrected gland volume (ml) at ``pressures_pa`` (Pa) and the correction's 95 % band there (ml), on
        the store's latest measurements (a store changed since the last fit is fitted first); None without a
        correction."""
        await self._store_in_force()
        return await self._call(_worker_gland_band, np.asarray(pressures_pa, dtype=float))

    async def surface_json(self, pressures_pa: np.ndarray | None) -> str:
        """The outer surface at ``pressures_pa`` (Pa), or at rest for None, as the JSON text of an object
        ``{"positions_mm": [[x, y, z], ...], "triangles": [[i, j, k], ...]}`` (mm; indices into the positions),
        written in the worker."""
        pressures = None if pressures_pa is None else np.asarray(pressures_pa, dtype=float)
        return await self._call(_worker_surface_json, pressures)

    def close(self) -> None:
        """Stop the worker process and wait for it (a pool left running is woken by the interpreter's exit
        hook through a pipe already closed, which prints an error)."""
        if self._fitting is not None:
            self._fitting.cancel()
        if self._fitter is not None:
            end_pool(self._fitter)  # a fit is seconds of OSQP: not waited for
        self._pool.shutdown(wait=True, cancel_futures=True)
        if self._messages is not None:
            self._messages.close()


def _leave_one_out_words(summary: dict[str, Any]) -> str:
    errors = summary.get("leave_one_out_pct") or {}
    return ", ".join(f"{kind} {error:.2f} %" for kind, error in errors.items()) or "none (one measurement)"


def _log_failed_fit(task: asyncio.Task[FitAnswer]) -> None:
    """A fit started in the background that failed (its process died twice, the worker could not take it):
    logged; the correction before stays in force and the next answer tries again."""
    if not task.cancelled() and task.exception() is not None:
        logger.warning("fitting the correction failed (%s: %s): the one before stays in force",
                       type(task.exception()).__name__, task.exception())
