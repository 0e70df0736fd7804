"""The daemon's API methods (host/README.md, "The local API"): each checks its params, acts on the daemon and
answers JSON-ready data, or raises ``ApiError`` with one of the API's error codes."""

from __future__ import annotations

import asyncio
import contextlib
import json
import time
from collections.abc import AsyncIterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from phantom import PhantomError, read_text
from phantom.host.api import ApiError, Handler, RawJson
from phantom.host.control import MAX_TOLERANCE_PCT
from phantom.host.scene_runner import PreparedRun, prepare_run
from phantom.host.scenes import (
    check_step_count,
    effective_model,
    load_timeline_scene,
    model_differences,
    parse_target,
    shape_steps,
    time_scale_of,
    with_shape_pressures,
)
from phantom.host.session import fault_names
from phantom.host.verify import MAX_VERIFY_ROUNDS, VERIFY_TOLERANCE_PCT, Verify
from phantom.model.errors import SceneError
from phantom.model.scene import MAX_SCENE_BYTES, pressure_limit_error

if TYPE_CHECKING:
    from phantom.host.daemon import Daemon
    from phantom.model.scene import Scene

PA_PER_KPA = 1e3
#: How long clear_fault waits, once the board acknowledged it, for telemetry without the fault (s) ...
CLEARED_IN_TELEMETRY_S = 1.0
#: ... then for the target's setpoints to be acknowledged again (s; held again is the control core's later word,
#: ``target_after_interruption``): a solve on full solves takes seconds.
RESTORED_S = 10.0


class ApiHandlers:
    """The methods of the local API, bound to one daemon."""

    def __init__(self, daemon: Daemon):
        self.daemon = daemon
        self.heavy = HeavyRequests()

    def table(self) -> dict[str, Handler]:
        """Method name -> handler, for :class:`phantom.host.api.ApiServer`."""
        return {"status": self.status, "set_target": self.set_target, "vent": self.vent,
                "clear_fault": self.clear_fault, "run_scene": self.run_scene, "zero": self.zero,
                "surface": self.surface}

    async def status(self, params: dict[str, Any]) -> dict[str, Any]:
        return self.daemon.status()

    async def set_target(self, params: dict[str, Any]) -> dict[str, Any]:
        daemon = self.daemon
        params = dict(params)
        tolerance_pct = params.pop("tolerance_pct", None)
        if tolerance_pct is not None and (isinstance(tolerance_pct, bool) or not isinstance(tolerance_pct, (int, float))
                                          or not 0 < tolerance_pct <= MAX_TOLERANCE_PCT):
            raise ApiError("invalid_params", f"set_target: tolerance_pct (how close the estimate must come for the "
                           f"target to be reached, %) must be a number in (0, {MAX_TOLERANCE_PCT:g}], got "
                           f"{tolerance_pct!r}")
        if "shape" in params:
            shape, labels, refine_solves = shape_of(params)
            return await daemon.set_shape_target(shape, labels, refine_solves,
                                                 None if tolerance_pct is None else float(tolerance_pct))
        verify = verify_of(params)
        try:
            target = parse_target(params, daemon.chamber_names, "set_target", daemon.chamber_labels)
        except SceneError as error:
            raise ApiError("invalid_params", str(error)) from error
        return await daemon.set_target(target, None if tolerance_pct is None else float(tolerance_pct), verify)

    async def vent(self, params: dict[str, Any]) -> dict[str, Any]:
        await self.daemon.vent("on request: every setpoint is 0")
        return {"vented": True}

    async def clear_fault(self, params: dict[str, Any]) -> dict[str, Any]:
        """CLEAR_FAULT; once the telemetry shows it cleared, the control core applies the target in force again
        (the board set its setpoints to 0 when the fault latched), a scene's step that came meanwhile included."""
        daemon, core = self.daemon, self.daemon.core
        before = fault_names(daemon.fault_flags)
        await daemon.board_command("CLEAR_FAULT")
        # the answer waits for the board's telemetry to say so too, so that the status read next is not the
        # latched one (a client that set a target at once saw the fault in a frame sent before the clear)
        deadline_s = time.monotonic() + CLEARED_IN_TELEMETRY_S
        while daemon.fault_flags and time.monotonic() < deadline_s:
            await asyncio.sleep(0.01)
        daemon.event("fault", f"faults cleared on request (were: {', '.join(before) or 'none'})")
        deadline_s = time.monotonic() + RESTORED_S
        while (core.busy or core.solving) and not core.target_applied and time.monotonic() < deadline_s:
            await asyncio.sleep(0.01)
        target = core.target
        return {"cleared": before, "setpoints_restored": core.target_applied,
                "target": target.to_json() if target is not None else None}

    async def zero(self, params: dict[str, Any]) -> dict[str, Any]:
        """ZERO_SENSORS on request: the board measures each sensor's zero (it must be vented and settled)."""
        acknowledged = await self.daemon.zero.sensors()
        self.daemon.event("zero", "sensors zeroed on request")
        return {"zeroed": True, "acknowledged": acknowledged}

    async def surface(self, params: dict[str, Any]) -> RawJson:
        """The deformed outer surface (positions mm, triangles): at ``pressures_kpa`` if given (within the model's
        pressure range), else at the latest measured pressures (at rest when there are none). The model worker
        writes the JSON: thousands of numbers are not the event loop's work."""
        daemon = self.daemon
        pressures = params.get("pressures_kpa")
        if pressures is not None:
            try:
                target = parse_target({"pressures_kpa": pressures}, daemon.chamber_names, "surface",
                                      daemon.chamber_labels)
            except SceneError as error:
                raise ApiError("invalid_params", str(error)) from error
            pressures_pa: np.ndarray | None = np.asarray(target.values, dtype=float)
            refused = pressure_limit_error(pressures, daemon.chamber_labels,
                                           daemon.model.info.pressure_max_pa / PA_PER_KPA)
            if refused:
                raise ApiError("invalid_params", f"surface: {refused}")
        elif daemon.schedule.window:
            pressures_pa = np.mean([frame for _, frame in daemon.schedule.window], axis=0)
        else:
            pressures_pa = None
        async with self.heavy.slot("surface"):
            surface_json = await daemon.model.surface_json(pressures_pa)
        measured = "null" if pressures_pa is None else json.dumps((pressures_pa / PA_PER_KPA).tolist())
        return RawJson(f'{{"pressures_kpa":{measured},{surface_json[1:]}')

    async def run_scene(self, params: dict[str, Any]) -> dict[str, Any]:
        daemon = self.daemon
        path = params.get("path")
        time_scale: Any = params.get("time_scale", 1.0)
        if not isinstance(path, str) or not path:
            raise ApiError("invalid_params", "run_scene needs params.path: the scene TOML file (absolute path)")
        if "\0" in path:  # no file can be named so: opening it raised ValueError, answered as a bug
            raise ApiError("invalid_params", f"run_scene: params.path {path!r:.200} is not a valid path: it holds a "
                                             "null character; give the scene TOML file's path")
        try:
            time_scale = time_scale_of(time_scale)
        except SceneError as error:
            raise ApiError("invalid_params", str(error)) from error
        try:
            async with self.heavy.slot("run_scene"):
                shapes = await asyncio.to_thread(scene_shapes, path)
                pressures_kpa = {}
                for index, keys in shapes:  # solved before the scene starts: seconds each, in the model worker
                    shape, labels, solves = shape_of(keys, f"{path}: steps[{index}]")
                    try:
                        answer = await daemon.model.shape_answer(shape, labels, solves)
                    except PhantomError as error:
                        raise ApiError("invalid_params", f"{path}: steps[{index}]: shape: {error}; the scene was not "
                                                         "started") from error
                    pressures_kpa[index] = answer["pressures_kpa"]
                prepared = await asyncio.to_thread(prepare_scene, path, time_scale, daemon.chamber_names,
                                                   daemon.model.info.effective_model, daemon.model.info.scene_path,
                                                   pressures_kpa)
                # a gland volume beyond the reachable range is refused before anything moves (ApiError unreachable)
                try:
                    await daemon.check_scene_reachable(prepared)
                except ApiError as error:
                    raise ApiError(error.code, f"{error}; the scene was not started", error.data) from error
        except SceneError as error:
            raise ApiError("invalid_params", str(error)) from error
        verified = [index for index, step in enumerate(prepared.timeline.steps) if step.verify is not None]
        why = daemon.verify_refusal() if verified else None
        if why is not None:
            raise ApiError("invalid_params", f"{path}: steps {', '.join(map(str, verified))} scan (verify or scan): "
                                             f"{why}; the scene was not started")
        return daemon.start_scene(prepared)


#: Full solves that refine a shape target's answer by default (``set_target``'s ``refine_solves``): one, so that
#: its distance is the full model's; each costs seconds of the model worker.
SHAPE_REFINE_SOLVES = 1
#: The most full solves a shape target may ask for.
MAX_SHAPE_REFINE_SOLVES = 5


def shape_of(params: dict[str, Any], where: str = "set_target") -> tuple[str | dict[str, Any], list[int] | None, int]:
    """``set_target``'s (or a scene step's) ``shape`` (a file path on the daemon's machine, or a mesh object),
    ``labels`` and ``refine_solves``, checked; ApiError ``invalid_params`` naming what is wrong."""
    unknown = set(params) - {"shape", "labels", "refine_solves", "at_s", "ramp_s"}
    if unknown:
        raise ApiError("invalid_params", f"{where}: shape goes alone (with labels and refine_solves), not with "
                                         f"{', '.join(sorted(unknown))}")
    shape, labels, solves = params["shape"], params.get("labels"), params.get("refine_solves", SHAPE_REFINE_SOLVES)
    if not (isinstance(shape, str) and shape) and not isinstance(shape, dict):
        raise ApiError("invalid_params", f"{where}: shape is the path of a mask or mesh file on the daemon's machine, "
                                         "or a mesh {vertices_mm, triangles}")
    if labels is not None and (not isinstance(labels, list) or not labels or not all(
            isinstance(label, int) and not isinstance(label, bool) and label > 0 for label in labels)):
        raise ApiError("invalid_params", f"{where}: labels are the gland's labels in a label map, a list of positive "
                                         f"whole numbers, got {labels!r}")
    if isinstance(solves, bool) or not isinstance(solves, int) or not 0 <= solves <= MAX_SHAPE_REFINE_SOLVES:
        raise ApiError("invalid_params", f"{where}: refine_solves (full solves after the table's answer) must be a "
                                         f"whole number from 0 to {MAX_SHAPE_REFINE_SOLVES}, got {solves!r}")
    return shape, labels, solves


def scene_shapes(path: str) -> list[tuple[int, dict[str, Any]]]:
    """A scene file's steps that give a ``shape`` (:func:`phantom.host.scenes.shape_steps`), read off the event
    loop, its size checked first as :func:`prepare_scene` does."""
    check_step_count(read_text(path, MAX_SCENE_BYTES, "the scene file", SceneError), path)
    return shape_steps(load_timeline_scene(path).raw.get("steps"), Path(path).parent)


def prepare_scene_run(scene: Scene, name: str, chamber_names: list[str], time_scale: float,
                      shape_pressures_kpa: dict[int, list[float]] | None = None) -> PreparedRun:
    """A read scene's run (:func:`prepare_run`: its timeline checked against ``chamber_names``, named ``name``),
    its shape steps played as the pressures ``shape_pressures_kpa`` their shape inverse answered (step index ->
    kPa): what the daemon's :func:`prepare_scene` plays and ``phantom scene check`` checks."""
    raw = with_shape_pressures(scene.raw, shape_pressures_kpa) if shape_pressures_kpa else scene.raw
    return prepare_run(raw, name, chamber_names, time_scale, bool(scene.outputs.shape))


def prepare_scene(path: str, time_scale: float, chamber_names: list[str], running_model: dict[str, Any],
                  running_scene: str, shape_pressures_kpa: dict[int, list[float]] | None = None) -> PreparedRun:
    """Read a scene file and check its timeline against the running model (off the event loop: reading and
    checking a scene takes time in proportion to its size, which the scene reader and the timeline bound; a
    scene of too many steps is refused before it is parsed); its shape steps played as the pressures
    ``shape_pressures_kpa`` their shape inverse answered (step index -> kPa)."""
    check_step_count(read_text(path, MAX_SCENE_BYTES, "the scene file", SceneError), path)
    scene = load_timeline_scene(path)
    # the timeline runs on the loaded model: a scene for another phantom, material or model setting needs its own
    # model, so the daemon must be restarted with it
    differing = model_differences(running_model, effective_model(scene))
    if differing:
        raise SceneError(f"{path} describes another phantom than the running one (its [{'], ['.join(differing)}] "
                         f"differ from {running_scene}): restart the daemon with --scene {path}")
    return prepare_scene_run(scene, path, chamber_names, time_scale, shape_pressures_kpa)


class HeavyRequests:
    """Bounds the requests that cost the daemon real work (a surface, a scene to read): ``in_flight`` of a kind
    at once, ``waiting`` more queued behind them; beyond that the API answers ``busy``."""

    def __init__(self, in_flight: int = 2, waiting: int = 16):
        self.in_flight = in_flight
        self.waiting = waiting
        self._slots: dict[str, asyncio.Semaphore] = {}
        self._queued: dict[str, int] = {}

    @contextlib.asynccontextmanager
    async def slot(self, kind: str) -> AsyncIterator[None]:
        semaphore = self._slots.setdefault(kind, asyncio.Semaphore(self.in_flight))
        if semaphore.locked() and self._queued.get(kind, 0) >= self.waiting:
            raise ApiError("busy", f"{self.in_flight + self.waiting} {kind} requests are already in progress: "
                           "try again when they are answered")
        self._queued[kind] = self._queued.get(kind, 0) + 1
        try:
            await semaphore.acquire()
        finally:
            self._queued[kind] -= 1
        try:
            yield
        finally:
            semaphore.release()


def verify_of(params: dict[str, Any]) -> Verify | None:
    """``set_target``'s ``verify`` (``"scan"`` or ``"auto"``), ``verify_tolerance_pct`` and ``verify_rounds``,
    taken out of ``params``: a Verify, or None without ``verify``; ApiError invalid_params for a bad one."""
    verify = params.pop("verify", None)
    tolerance_pct = params.pop("verify_tolerance_pct", None)
    rounds = params.pop("verify_rounds", None)
    if verify is None:
        if tolerance_pct is not None or rounds is not None:
            raise ApiError("invalid_params", "set_target: verify_tolerance_pct and verify_rounds go with verify: "
                                             "\"scan\"")
        return None
    if verify not in ("scan", "auto"):
        raise ApiError("invalid_params", f"set_target: verify must be \"scan\" (the scanner measures the gland's "
                                         f"volume) or \"auto\" (a scan only when the correction's 95 % band at the "
                                         f"target is wider than the tolerance), got {verify!r:.60}")
    defaults = Verify()
    if tolerance_pct is None:
        tolerance_pct = defaults.tolerance_pct
    if (isinstance(tolerance_pct, bool) or not isinstance(tolerance_pct, int | float)
            or not VERIFY_TOLERANCE_PCT[0] <= tolerance_pct <= VERIFY_TOLERANCE_PCT[1]):
        raise ApiError("invalid_params", f"set_target: verify_tolerance_pct (how close the scanned volume must come, "
                                         f"%) must be a number from {VERIFY_TOLERANCE_PCT[0]:g} to "
                                         f"{VERIFY_TOLERANCE_PCT[1]:g} (the scanner's own error is about 0.15 %), got "
                                         f"{tolerance_pct!r:.60}")
    if rounds is None:
        rounds = defaults.rounds
    if isinstance(rounds, bool) or not isinstance(rounds, int) or not 1 <= rounds <= MAX_VERIFY_ROUNDS:
        raise ApiError("invalid_params", f"set_target: verify_rounds (scans at most) must be a whole number from 1 "
                                         f"to {MAX_VERIFY_ROUNDS}, got {rounds!r:.60}")
    return Verify(float(tolerance_pct), int(rounds), auto=verify == "auto")
