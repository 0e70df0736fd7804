"""The host daemon: one asyncio process that owns the board link, the scenes, Rerun and the API, and drives the
control core (host/control.py), which decides; the daemon performs its actions and feeds it what happens.

The parts, each built before the daemon runs (:meth:`Daemon.start` builds them in this order): the API's socket
(claimed first: a daemon that cannot start never touches another daemon's files), the recording, the model in
its worker process, the simulated board if any, the link session; then the handlers.

Tasks: the link (``LinkSession.run``), the control loop (every control period: the scene's target, the core's
tick, a volume estimate when due, status to subscribers, link statistics to Rerun), the simulated board's watch.

A verified target's scans (the core's :class:`~phantom.host.verify.Scan`) go through the daemon's own ``scan``
API method (host/motion.py) with the :class:`VerifyScanner`'s plan; the capture is reconstructed by the
:class:`VerifyScanner` in a worker thread (the host imports nothing of the scanner's code: ``phantom daemon``
gives it); every scan is recorded as a measurement through the model worker when it can take one
(``record_measurement``, :meth:`Daemon._record_scan`): a miss's before the next round is solved
(:meth:`Daemon._correct_for_core`), the scan that ends the verification on its own (the core's ``Record``).
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import logging
import time
from collections import deque
from collections.abc import Coroutine
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from phantom import PhantomError
from phantom.host import control, verify
from phantom.host.api import ApiError, ApiServer
from phantom.host.board_watch import BoardSettings, Stillness
from phantom.host.config import DaemonConfig
from phantom.host.control import ControlCore, ReachRule, predicted_volume_ml
from phantom.host.estimation import EstimateSchedule, VolumeEstimates
from phantom.host.model_worker import Estimate
from phantom.host.motion import SCAN_TRIES, Orbit, simulated_truth
from phantom.host.parts import BoardSession, Clock, ControlState, Model, Recording
from phantom.host.scene_runner import PreparedRun, SceneRunner
from phantom.host.scenes import ML_PER_M3, gland_volume_ml
from phantom.host.session import (
    BoardInfo,
    CommandRejected,
    LinkDown,
    Telemetry,
    fault_names,
)
from phantom.host.sim_board import SimulatedBoardKeeper
from phantom.host.stalls import LoopStalls, said_stalls
from phantom.host.startup import BackgroundTable, StartupProgress, notify_systemd
from phantom.host.status import daemon_status
from phantom.host.web import WebServer
from phantom.host.zeroing import ZEROING_WHY, SensorZero
from phantom.model.measurements import data_dir
from phantom.model.target import InverseResult, Target, UnreachableTargetError
from phantom.protocol.link import board_clock_went_back
from phantom.protocol.motion import ELEVATION

logger = logging.getLogger(__name__)

PA_PER_KPA = 1e3
LEVELS = {"INFO": logging.INFO, "WARN": logging.WARNING, "ERROR": logging.ERROR}
#: The control loop's rate (Hz): the scene's target, volume estimates and status to subscribers.
CONTROL_HZ = 10.0


class VerifyScanner(Protocol):
    """What a verified target's scan needs besides the ``scan`` API method (``phantom.cli.scan_verify``):
    ``plan``, the ``scan`` params of a verify scan (without ``out``), :meth:`plan_for` and :meth:`volume`."""

    plan: dict[str, Any]

    def plan_for(self, tolerance_pct: float) -> dict[str, Any]:
        """The ``scan`` params of a verified target's scan at ``tolerance_pct`` (%): the plan sized to it."""
        ...

    def expect_surface(self, model_surface_mm: tuple[Any, Any] | None) -> None:
        """The model's outer surface at the next verify scan's pressures (None: none), given before its capture
        (blocking: run in a worker thread), so that the capture renders its silhouettes while the rig moves for
        :meth:`volume`'s hull error."""
        ...

    def volume(self, folder: str, model_surface_mm: tuple[Any, Any] | None = None) -> dict[str, Any]:
        """The capture folder reconstructed (blocking: run in a worker thread): ``volume_ml`` (the visual hull's
        error on ``model_surface_mm``, the model's outer surface at the scan's pressures, taken off),
        ``scanned_raw_ml`` and ``hull_error_pct`` (None, ``hull_note`` says why), ``mesh`` (the surface's file),
        ``surface_mm`` (its vertices and triangles in the model's frame, for the recording; None when the scan's
        frame is not the model's), ``stage_s``, ``keyed_while_taken`` and ``hull_rendered_while_taken``;
        PhantomError when it cannot be (a picture without the phantom, a hull not closed)."""
        ...


#: A verify scan that fails within this long after the board's link was lost fails for the rig's sake (s): a board
#: that reset holds its axes busy (BUSY) while they stop, and the scan retaken at once was refused for it.
LINK_LOSS_GRACE_S = 30.0
#: How long a verify scan waits for the rig's axes to come to rest before it starts (s).
RIG_REST_WAIT_S = 30.0
#: How long a verification's outcome waits for its last scan to be stored before it is told anyway (s): a store
#: is a fit of the correction, under a second for 200 measurements (bench/correction_fit.py).
STORED_WAIT_S = 30.0
#: How far back the link loop's stalls are told when DEAD_HOST latches (s): the deadline (500 ms) and the
#: telemetry that brings the fault to the daemon, with room; told this long after the fault (s), once the link's
#: process has measured a stall it was in and sent its status (every 0.2 s).
DEAD_HOST_LOOKBACK_S = 3.0
DEAD_HOST_TOLD_AFTER_S = 1.0
#: How long a reconnection waits for the board's first frame before it sends a reached target's setpoints again
#: (s): the frame says whether the board kept them (a link briefly lost) or lost them (it restarted), which the
#: setpoints sent again would hide. Telemetry streams every 20 ms from the handshake on.
FIRST_FRAME_WAIT_S = 0.5


def verify_folder(round_: int) -> Path:
    """Where a verified target's scan goes: the user's data directory (the scans are measurements kept)."""
    return data_dir() / "scans" / f"{time.strftime('%Y%m%dT%H%M%S')}_{time.time_ns() % 10**9:09d}_round{round_}"


class Daemon:
    """The parts built by :meth:`start`, the control core, and the tasks; :meth:`serve` until asked to stop."""

    def __init__(self, config: DaemonConfig, api: ApiServer, model: Model, recorder: Recording, session: BoardSession,
                 sim_board: SimulatedBoardKeeper | None, clock: Clock = time.monotonic,
                 startup: StartupProgress | None = None):
        self.config, self.api, self.model, self.recorder, self.session = config, api, model, recorder, session
        self.sim_board, self.clock = sim_board, clock
        self.started_s = clock()
        self.recording = bool(config.rerun_save or config.rerun_connect)
        self.chamber_names = list(model.info.chamber_names)
        self.chamber_labels = list(model.info.chamber_labels)
        self.core = ControlCore(len(self.chamber_names), ReachRule(config.settled_kpa, config.settled_for_s))
        self.telemetry: Telemetry | None = None
        #: set by every telemetry frame (a reconnection waits on it: :data:`FIRST_FRAME_WAIT_S`)
        self._frame_came = asyncio.Event()
        self.events: deque[dict[str, Any]] = deque(maxlen=100)
        self.fault_flags = 0
        self.scenes = SceneRunner(clock, self.event)
        self.schedule = EstimateSchedule(config.mesh_hz)
        self.estimates = VolumeEstimates(self.schedule, model, recorder, self.event, self._estimated,
                                         lambda: (self.target_volume_ml(), self.plant_volume_ml()))
        self.board_settings = BoardSettings(config.kp_per_kpa, config.ki_per_kpa_s, config.kd_s_per_kpa,
                                            config.pressure_limit_kpa * PA_PER_KPA)
        self.board_settings_source = "not set yet: no board has been connected"
        self.loop_stalls = LoopStalls()
        self.stillness = Stillness()
        self.zero = SensorZero(self.session.command, lambda: self.telemetry, lambda: self.stillness,
                               lambda why: self._feed(self.core.zeroing, why), self.event)
        self._board_configured = False
        self._requests: dict[int, asyncio.Future[InverseResult | None]] = {}
        self._request_ids = itertools.count()
        self.stopping = asyncio.Event()
        self.exit_code = 0
        self._link_log_due_s = 0.0
        self.tasks: list[asyncio.Task[Any]] = []
        self.background: set[asyncio.Task[Any]] = set()
        #: scans being stored as measurements: the shutdown waits for them (a scan is a measurement kept)
        self.storing: set[asyncio.Future[Any]] = set()
        #: when the board's link was last lost (s, :meth:`now_s`; None: never)
        self.link_lost_s: float | None = None
        #: start-up: what it is doing until ready (the model answers and the board was first online and zeroed)
        self.startup = startup or StartupProgress(clock)
        self.ready = False
        #: the scene's response table being built in the background (the model answers on full solves meanwhile)
        self.table = BackgroundTable(config.scene, model, self.event, lambda: self.ready, self.startup,
                                     lambda: self._feed(self.core.model_changed))
        #: the scanner's axes (host/motion.py)
        self.motion = Orbit(self.board_command, self.event, simulated_truth(sim_board) if sim_board else None)
        #: the browser panel's server (host/web.py), when the daemon serves one (--http)
        self.web: WebServer | None = None
        #: what reconstructs a verified target's scans (None: this daemon cannot verify targets)
        self.verify_scanner: VerifyScanner | None = None
        #: the verify scan running or last run (a newer one stops it: :meth:`_scan_for_core`)
        self.verify_scan: asyncio.Task[Any] | None = None

    # --- life cycle -------------------------------------------------------------------------------------

    def now_s(self) -> float:
        """Seconds since the daemon started (the recording's time line)."""
        return float(self.clock() - self.started_s)

    def spawn(self, coroutine: Coroutine[Any, Any, Any]) -> asyncio.Task[Any]:
        """A background task, referenced until it ends (the event loop keeps only weak references)."""
        task = asyncio.create_task(coroutine)
        self.background.add(task)
        task.add_done_callback(self.background.discard)
        return task

    def request_stop(self) -> None:
        """Ask :func:`phantom.host.service.serve` to shut down (SIGTERM and SIGINT do this)."""
        self.stopping.set()

    # --- the control core: what it is fed, and its actions performed -----------------------------------

    def _feed(self, method: Any, *args: Any, at: float | None = None) -> None:
        """Feed the core one input, at the clock's time unless ``at``, then perform the actions it took."""
        method(self.clock() if at is None else at, *args)
        for action in self.core.take_actions():
            self._perform(action)

    def _perform(self, action: control.Action) -> None:
        if isinstance(action, control.Tell):
            if action.after_stored and self.storing:
                self.spawn(self._tell_once_stored(action))
            else:
                self.event(action.kind, action.text, action.level, action.data)
        elif isinstance(action, control.Solve):
            self.spawn(self._solve_for_core(action))
        elif isinstance(action, control.SendSetpoints):
            self.spawn(self._send_setpoints(action))
        elif isinstance(action, control.SendVent):
            self.spawn(self._send_vent(action))
        elif isinstance(action, control.ConfigureBoard):
            self.spawn(self.send_board_settings(action.when))
        elif isinstance(action, control.StepApplied):
            self.scenes.applied(action.index)
        elif isinstance(action, control.StepReached):
            self.scenes.reached(action.index)
        elif isinstance(action, control.StepUnreachable):
            self.scenes.unreachable(action.index, action.text)
        elif isinstance(action, control.StopScene):
            self.scenes.stop(action.why)
        elif isinstance(action, verify.Scan):
            self.spawn(self._scan_for_core(action))
        elif isinstance(action, verify.StopScan):
            self.spawn(self._stop_verify_scan(action.why))
        elif isinstance(action, verify.Correct):
            self.spawn(self._correct_for_core(action))
        elif isinstance(action, verify.Record):
            recording = self.spawn(self._record_scan(action.pressures_kpa, action.scanned_ml, action.scan_folder))
            self.storing.add(recording)  # from now: the outcome told with it waits for it
            recording.add_done_callback(self.storing.discard)
        elif isinstance(action, control.Answer):
            waiting = self._requests.pop(action.request, None)
            if waiting is not None and not waiting.done():
                if action.error is not None:
                    waiting.set_exception(ApiError(*action.error))
                else:
                    waiting.set_result(action.result)

    async def _solve_for_core(self, action: control.Solve) -> None:
        try:
            answer = await self.solve(action.target, action.ramp)
        except ApiError as error:
            edge = (error.data or {}).get("gland_range_ml")
            self._feed(self.core.solve_failed, action.target, error.code == "unreachable", str(error),
                       None if edge is None else (float(edge[0]), float(edge[1])))
        except Exception as error:  # the model worker failed: said, and tried again
            self._feed(self.core.solve_failed, action.target, False, f"the model failed: {error}")
        else:
            self._feed(self.core.solved, action.target, answer)

    def verify_refusal(self) -> str | None:
        """Why this daemon cannot verify a target by scanning (None: it can)."""
        if self.verify_scanner is None or "scan" not in self.api.handlers:
            return ("this daemon has no scanner to verify a target with (`phantom daemon` gives its `scan` method; "
                    "a daemon started without one cannot): set the target without verify")
        if self.sim_board is None and self.verify_scanner.plan.get("camera", "virtual") == "virtual":
            return ("this daemon drives a real board, and its verify scan's camera is the virtual one, which "
                    "photographs only the simulated phantom: start it with the rig's camera and calibration "
                    "(phantom daemon --camera DEVICE|URL --rig rig.json; README.md, \"A verified volume on a real "
                    "rig\"), or set the target without verify")
        return None

    async def _stop_verify_scan(self, why: str) -> None:
        """Stop the verify scan while it runs (its verification ended: ``why``); a scan a client took itself is
        not the verification's, and is left alone."""
        task = self.verify_scan
        if task is not None and not task.done():
            await self.motion.stop_scan(why)

    async def _scan_for_core(self, action: verify.Scan) -> None:
        """A verified target's scan: the ``scan`` API method's capture, reconstructed in a worker thread. A scan
        still running for a verification that is no more (a second client's verified target replaced it) is
        stopped first, and its answer is not fed to the core: the core asks one scan at a time."""
        superseded, self.verify_scan = self.verify_scan, asyncio.current_task()
        if superseded is not None and not superseded.done():
            await self.motion.stop_scan("its verified target was replaced by another")
            with contextlib.suppress(Exception):
                await superseded
        folder: str | None = None
        started_s = self.now_s()
        try:
            scanner = self.verify_scanner
            why = self.verify_refusal()
            if scanner is None or why is not None:
                raise ApiError("invalid_params", why or "no scanner")
            # the model's surface at the round's pressures before the capture: its silhouettes are rendered while
            # the rig moves, for the hull's error measured after it
            surface_mm = await self._model_surface_mm(action)
            await asyncio.to_thread(scanner.expect_surface, surface_mm)
            answer = await self.perform_scan(action.round, scanner.plan_for(action.tolerance_pct))
            folder = str(answer["folder"])
            if answer.get("status") != "complete":
                raise ApiError("rejected", f"the capture ended {answer.get('status')!r}")
            result = await asyncio.to_thread(scanner.volume, folder, surface_mm)
            volume_ml = float(result["volume_ml"])
        except Exception as error:  # any failure of the scan is the round's, told to the core: no correction
            if self.verify_scan is not asyncio.current_task():
                return  # superseded: stopped for a newer verification, whose round this is not
            # lost during the scan (or just before it), or not online now: a silence the scan found before any
            # event of it was told
            link_lost = ((self.link_lost_s is not None and self.link_lost_s >= started_s - LINK_LOSS_GRACE_S)
                         or not self.session.online)
            self._feed(self.core.scanned, action.round, None, str(error), folder, None, link_lost)
            return
        if self.verify_scan is not asyncio.current_task():
            return
        if result.get("hull_error_pct") is not None:
            # with how the reconstruction went: its stages' seconds, and how many pictures' silhouettes (the scan's
            # own, the model's) were ready when the capture ended
            self.event("scan", f"round {action.round}: the visual hull reads the model's shape at these pressures "
                               f"{result['hull_error_pct']:+.3f} % off; taken off the scan's "
                               f"{result['scanned_raw_ml']:.3f} ml: {volume_ml:.3f} ml",
                       data={"round": action.round, "stage_s": result.get("stage_s"),
                             "keyed_while_taken": result.get("keyed_while_taken"),
                             "hull_rendered_while_taken": result.get("hull_rendered_while_taken")})
        elif result.get("hull_note"):
            self.event("scan", f"round {action.round}: {result['hull_note']}", "WARN")
        self.recorder.log_scanned_volume(self.now_s(), volume_ml, action.round, action.tolerance_pct)
        if result.get("surface_mm") is not None:
            self.recorder.log_scan_surface(self.now_s(), *result["surface_mm"])
        self._feed(self.core.scanned, action.round, volume_ml, None, folder, self.plant_volume_ml(), False,
                   result.get("hull_error_pct"))

    async def _model_surface_mm(self, action: verify.Scan) -> tuple[Any, Any] | None:
        """The model's outer surface (positions mm, triangles) at the round's settled pressures, on which the scan's
        reconstruction measures the visual hull's own error; None when the model cannot give it (said)."""
        try:
            estimate = await self.model.estimate(PA_PER_KPA * np.asarray(action.pressures_kpa), with_surface=True)
        except Exception as error:  # the scan is still a measurement, only with the hull's error left in it
            self.event("scan", f"round {action.round}: no model surface to measure the hull's error on ({error})",
                       "WARN")
            return None
        return estimate.surface_mm

    async def perform_scan(self, round_: int, plan: dict[str, Any]) -> dict[str, Any]:
        """One verified round's capture with the ``scan`` method's ``plan``, into a new folder of its own; a capture
        that failed for a late reply of the board (a frame lost on the link) is taken again, :data:`SCAN_TRIES` in
        all. The scan method's answer; ApiError when the last try failed."""
        for attempt in range(1, SCAN_TRIES + 1):
            await self._rig_at_rest()
            late_before = self.motion.late_replies
            status = self.motion.latest
            # from the elevation the last scan ended at, not tilted back first
            passes = verify.passes_from(plan, None if status is None else status.axes[ELEVATION].position_deg)
            try:
                # the pictures' silhouettes keyed while the rig moves, in the process its reconstruction runs in
                answer = await self.api.handlers["scan"]({"out": str(verify_folder(round_)), **passes,
                                                          "key_silhouettes": True})
            except ApiError as error:
                if attempt == SCAN_TRIES or self.motion.late_replies == late_before:
                    raise
                self.event("scan", f"the scan of round {round_} failed ({error}): scanned again", "WARN")
                continue
            assert isinstance(answer, dict)  # the scan method answers JSON-ready data
            return answer
        raise AssertionError("unreachable")

    async def _rig_at_rest(self) -> None:
        """Wait (at most :data:`RIG_REST_WAIT_S`) until no axis of the rig moves, homes or stops: the board refuses
        a move (BUSY) meanwhile, as after a reset while a scan moved it."""
        deadline_s = self.now_s() + RIG_REST_WAIT_S
        while self.now_s() < deadline_s:
            status = self.motion.latest
            if status is None or all(axis.state not in ("MOVING", "HOMING", "STOPPING") for axis in status.axes):
                return
            await asyncio.sleep(0.2)

    async def _correct_for_core(self, action: verify.Correct) -> None:
        """A verified target's miss: the next round's pressures, decided by :class:`phantom.host.verify.NextRound`;
        the daemon only performs its actions (records the scan, solves what it asks) and feeds it the answers."""
        policy = verify.NextRound(action)
        policy.start(self.now_s())
        while steps := policy.take_actions():
            for step in steps:
                if isinstance(step, verify.Record):
                    stored = await self._record_scan(step.pressures_kpa, step.scanned_ml, step.scan_folder)
                    corrected: tuple[float, float] | None = None
                    if stored:
                        with contextlib.suppress(Exception):  # the model failed: the shifted volume instead
                            corrected = await self.model.gland_band(np.asarray(step.pressures_kpa) * PA_PER_KPA)
                    policy.recorded(self.now_s(), stored, *(corrected or (None, None)))
                elif isinstance(step, verify.Solve):
                    try:
                        answer = await self.solve(step.target)
                    except ApiError as error:
                        if error.code == "unreachable":
                            data = error.data or {}
                            edge = data.get("gland_range_ml")
                            policy.unreachable(self.now_s(), None if edge is None else (float(edge[0]), float(edge[1])),
                                               bool(data.get("corrected")), str(error))
                        else:
                            policy.failed(self.now_s(), str(error))
                    except Exception as error:  # the model worker failed
                        policy.failed(self.now_s(), f"the model failed: {error}")
                    else:
                        policy.solved(self.now_s(), answer)
                elif isinstance(step, verify.Apply):
                    self._feed(self.core.corrected, step.round, step.answer, step.how)
                elif isinstance(step, verify.Confirm):
                    self._feed(self.core.confirmed, step.round, step.corrected_ml, step.band_ml)
                elif isinstance(step, verify.Hold):
                    self._feed(self.core.held, step.round, step.next_kpa)
                else:
                    self._feed(self.core.correct_failed, step.round, step.unreachable, step.text)
        if not policy.done:  # every event takes an action until the last: none is the policy's fault
            self._feed(self.core.correct_failed, action.round, False, "the verify policy stopped without an answer")

    async def _tell_once_stored(self, tell: control.Tell) -> None:
        """A verification's outcome, told once the scans being stored are (at most :data:`STORED_WAIT_S`): a
        client that reads the phantom's measurements on it finds its last scan there."""
        await asyncio.wait(set(self.storing), timeout=STORED_WAIT_S)
        self.event(tell.kind, tell.text, tell.level, tell.data)

    async def _record_scan(self, pressures_kpa: tuple[float, ...], scanned_ml: float, folder: str | None) -> bool:
        """A scan stored as a measurement of the phantom (the model's correction fitted again), when the model can
        take one: whether it was (one that could not be is said; the scan is still the round's)."""
        record = getattr(self.model, "record_measurement", None)
        if record is None:
            return False
        try:
            recorded = record(list(pressures_kpa), scanned_ml, "scan", folder)
            if asyncio.iscoroutine(recorded):
                storing = asyncio.ensure_future(recorded)
                self.storing.add(storing)
                storing.add_done_callback(self.storing.discard)
                await asyncio.shield(storing)  # a round cancelled (a shutdown) does not cancel its store
        except Exception as error:
            self.event("verify", f"the scan as a measurement of the phantom: {error}", "WARN")
            return False
        return True

    async def _send_setpoints(self, action: control.SendSetpoints) -> None:
        try:
            await self.board_command("SET_SETPOINTS", {"setpoint_pa": [int(p) for p in action.setpoints_pa]})
        except ApiError as error:
            self._feed(self.core.send_failed, action.target, error.code == "rejected", str(error))
        else:
            self._feed(self.core.sent, action.target)

    async def _send_vent(self, action: control.SendVent) -> None:
        """The one place that sends VENT."""
        try:
            await self.board_command("VENT")
        except ApiError as error:
            self._feed(self.core.vent_done, str(error), error.code == "link_down")
        else:
            self._feed(self.core.vent_done, None)

    def _request(self) -> tuple[int, asyncio.Future[InverseResult | None]]:
        request = next(self._request_ids)
        waiting = self._requests[request] = asyncio.get_running_loop().create_future()
        return request, waiting

    async def solve(self, target: Target, ramp: tuple[Target, Target] | None = None) -> InverseResult:
        """The inverse's answer for ``target`` (on its ramp, when it is a point of one); ApiError ``unreachable``.
        Solved after any scan being stored: its refit changes the correction the estimate then uses, and a target
        solved on the one before never came within its verify tolerance of the estimate (make demo's 35 ml, solved
        3 s before 30 ml's last scan refitted the correction, waited for ever)."""
        if self.storing:
            await asyncio.wait(set(self.storing))
        try:
            if ramp is not None:
                answer = await self.model.pressures_on_ramp(ramp[0], ramp[1], target)
            else:
                answer = await self.model.pressures_for(target)
        except UnreachableTargetError as error:
            # the gland's reachable range (with a correction in force, the corrected model's) as data too
            data = None if error.gland_range_ml is None else {"gland_range_ml": list(error.gland_range_ml),
                                                              "corrected": error.corrected}
            raise ApiError("unreachable", str(error), data) from error
        self.recorder.log_solver(self.now_s(), answer.qp_solve_time_s, answer.solve_time_s)
        return answer

    async def set_target(self, target: Target, tolerance_pct: float | None = None,
                         verify: verify.Verify | None = None) -> dict[str, Any]:
        """A target from the API: solved first, so that an unreachable one changes nothing (a playing scene goes
        on); then sent, and only once the board has acknowledged it does it replace the scene; with ``verify``,
        verified by scans once reached on pressure (host/control.py). Returns the inverse's answer as JSON;
        raises ApiError (``unreachable``, ``link_down``, ``rejected``, ``invalid_params``: verify without a
        scanner or not of a gland volume)."""
        if verify is not None:
            why = self.verify_refusal()
            if why is None and target.gland_volume_m3 is None:
                why = "verify compares the scanned gland volume with the target: give volume_ml"
            if why is not None:
                raise ApiError("invalid_params", f"set_target: {why}; the target was not set")
        if not self.session.online:
            raise ApiError("link_down", f"no board: the link is {self.session.state.value}; the target was not set")
        await self.zero.over()
        answer = await self.solve(target)
        request, waiting = self._request()
        self._feed(self.core.offer, request, answer, tolerance_pct, verify)
        await waiting
        return {**answer.to_json(), **(verify.to_json() if verify is not None else {})}

    async def set_shape_target(self, shape: str | dict[str, Any], labels: list[int] | None, refine_solves: int,
                               tolerance_pct: float | None = None) -> dict[str, Any]:
        """A target gland from the API (``set_target`` with ``shape``): the shape inverse's pressures, solved in the
        model worker, set as a pressure target; its answer under ``shape`` (distance, per-region error, ...).
        ApiError ``invalid_params`` for a shape that cannot be used, else as :meth:`set_target`."""
        if not self.session.online:
            raise ApiError("link_down", f"no board: the link is {self.session.state.value}; the target was not set")
        try:
            answer = await self.model.shape_answer(shape, labels, refine_solves)
        except PhantomError as error:
            raise ApiError("invalid_params", f"set_target: shape: {error}; the target was not set") from error
        target = Target(pressures_pa=[value * PA_PER_KPA for value in answer["pressures_kpa"]])
        return {**await self.set_target(target, tolerance_pct), "shape": answer}

    async def vent(self, why: str) -> None:
        """VENT (acknowledged): every setpoint 0, the target and any scene dropped; ``why`` goes to the status's
        ``vented_why`` and the events. Raises ApiError ``link_down`` when the board cannot be told."""
        request, waiting = self._request()
        self._feed(self.core.vent, why, "INFO", request)
        await waiting

    async def board_command(self, name: str, fields: dict[str, Any] | None = None) -> str:
        """One acknowledged command to the board; link errors become API errors."""
        try:
            return str(await self.session.command(name, fields))
        except LinkDown as error:
            raise ApiError("link_down", str(error)) from error
        except CommandRejected as error:
            raise ApiError("rejected", str(error)) from error

    async def send_board_settings(self, when: str) -> bool:
        """SET_PID to every chamber with the daemon's gains and limit; the answer goes to ``board_settings`` in the
        status. A refusal because a chamber holds a setpoint above the new limit vents first."""
        for chamber in range(len(self.chamber_names)):
            fields = self.board_settings.set_pid_fields(chamber)
            try:
                try:
                    await self.board_command("SET_PID", fields)
                except ApiError as error:
                    if "BAD_VALUE" not in str(error):
                        raise
                    await self.vent(f"the board refused its limits with a setpoint above "
                                    f"{self.board_settings.pressure_limit_pa / PA_PER_KPA:g} kPa: vented first")
                    await self.board_command("SET_PID", fields)
            except ApiError as error:
                self.board_settings_source = f"unknown: SET_PID failed ({error})"
                self.event("board", f"the board's gains and limits could not be set {when}: {error}", "ERROR")
                return False
        self.board_settings_source = f"set by the daemon {when} (SET_PID acknowledged, {time.strftime('%H:%M:%S')})"
        return True

    # --- events, telemetry, the link ----------------------------------------------------------------------

    def event(self, kind: str, text: str, level: str = "INFO", data: dict[str, Any] | None = None) -> None:
        """Record an event: the status's recent events, Rerun's text log, subscribers, the log. ``data`` (a
        target's outcome, a verify scan's reconstruction) goes with it to subscribers and the status."""
        if kind == "link_lost":  # the session's event: a verify scan failing after it is retaken
            self.link_lost_s = self.now_s()
        entry = {"time_s": round(self.now_s(), 3), "kind": kind, "level": level, "text": text, **(data or {})}
        self.events.append(entry)
        self.recorder.log_event(self.now_s(), text, level)
        self.api.publish("events", entry)
        logger.log(LEVELS.get(level, logging.INFO), "%s", text)
        if kind == "fault" and text.startswith("fault latched: DEAD_HOST"):  # the board's FAULT frame (session)
            self.spawn(self._say_what_came_before_dead_host())

    async def _say_what_came_before_dead_host(self) -> None:
        """DEAD_HOST latched: say what the link's loop did in the seconds before (its notable stalls) and, on a
        simulated board, what the board heard of it. A hung daemon says so itself (the link process withholds the
        keepalive); this tells a link loop that stalled from a line or a machine that did."""
        # the link's status a moment later: the loop that was stalled has measured its stall by then, and has sent it
        await asyncio.sleep(DEAD_HOST_TOLD_AFTER_S)
        loop = self.session.status().get("event_loop")
        if loop is not None:
            stalls = said_stalls(loop["notable_stalls"], DEAD_HOST_LOOKBACK_S + DEAD_HOST_TOLD_AFTER_S)
            self.event("link", f"before DEAD_HOST, the link's loop: {stalls}", "WARN")
        if self.sim_board is not None:
            said = await asyncio.get_running_loop().run_in_executor(None, self.sim_board.gaps_said)
            if said is not None:
                self.event("sim", f"before DEAD_HOST, {said}", "WARN")

    def on_telemetry(self, telemetry: Telemetry) -> None:
        """Keep the latest frame and the estimation window; the core sees a restart (the board's clock went back
        since the last frame, across a reconnection too), its faults and setpoints."""
        last, self.telemetry = self.telemetry, telemetry
        self._frame_came.set()
        if last is not None and board_clock_went_back(last.board_time_ms, telemetry.board_time_ms):
            self._feed(self.core.board_restarted, f"its clock went back from {last.board_time_ms / 1e3:.1f} s to "
                       f"{telemetry.board_time_ms / 1e3:.1f} s")
        self.schedule.add(telemetry.board_time_ms / 1e3, telemetry.pressures_pa)
        self.stillness.frame(telemetry.board_time_ms / 1e3, telemetry.pressures_pa)
        self.fault_flags = telemetry.fault_flags
        self._feed(self.core.faults, tuple(fault_names(telemetry.fault_flags)))
        self._feed(self.core.board_setpoints, telemetry.setpoints_pa)
        now_s = self.now_s()
        self.recorder.log_telemetry(now_s, telemetry.pressures_pa / PA_PER_KPA, telemetry.setpoints_pa / PA_PER_KPA,
                                    telemetry.drive_levels)
        self.api.publish("telemetry", {
            "time_s": now_s, "board_time_ms": telemetry.board_time_ms,
            "pressures_kpa": (telemetry.pressures_pa / PA_PER_KPA).tolist(),
            "setpoints_kpa": (telemetry.setpoints_pa / PA_PER_KPA).tolist(),
            "drive_levels": telemetry.drive_levels.tolist(), "states": telemetry.states,
            "fault_flags": telemetry.fault_flags})

    async def on_online(self, board: BoardInfo, reconnected: bool) -> None:
        """The link came up: set the board's gains and limits, then the core applies the current target (a board
        that reset holds no setpoints; for a reached target, once the board's first frame said whether it kept
        them), or the sensors are zeroed if the phantom is vented."""
        self.schedule.clear()
        self.stillness = Stillness()
        self._board_configured = False
        self._feed(self.core.board, False, "the board's gains and limits are being set")
        self.spawn(self.motion.restore())
        if board.chamber_count != len(self.chamber_names):
            why = f"the board has {board.chamber_count} chambers, the scene {len(self.chamber_names)}"
            self.event("link", f"{why}: setpoints not sent", "ERROR")
            self._feed(self.core.board, False, why)
            return
        await self.send_board_settings("at connection")
        if self.core.awaits_board_frame:
            # a reached target's board is back: its first frame says whether it kept the setpoints before they go
            # again (a lost link, its session re-opened) or lost them (a restart), and so whether it was interrupted
            self._frame_came.clear()
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self._frame_came.wait(), FIRST_FRAME_WAIT_S)
        self._board_configured = True
        self._feed(self.core.board, True)
        idle = self.core.target is None or self.core.state is ControlState.VENTED
        if idle and self.config.zero_on_connect:
            if not self.ready:
                self.startup.enter("zeroing the pressure sensors (the phantom is vented)")
            # targets wait for the zero from now on
            self._feed(self.core.zeroing, ZEROING_WHY)
            self.spawn(self.zero.after_connecting()).add_done_callback(lambda _: self._became_ready())
            return
        self._became_ready()

    def _became_ready(self) -> None:
        """The model answers and the board is online (and zeroed): tell systemd and the clients, once."""
        if self.ready or self.stopping.is_set():
            return
        self.ready = True
        fidelity, pending = self.model.info.fidelity, self.model.info.pending_fidelity
        building = f" (the {pending} level is being built)" if pending else ""
        since_start_s = self.startup.clock() - self.startup.started_s
        self.event("startup", f"ready {since_start_s:.1f} s after start: the model answers on {fidelity}{building}, "
                   "the board is online")
        notify_systemd("READY=1", f"STATUS=ready: fidelity {fidelity}{building}")

    # --- the control loop -------------------------------------------------------------------------------

    async def _control_loop(self) -> None:
        period_s = 1.0 / CONTROL_HZ
        while True:
            started = time.monotonic()
            try:
                self.control_tick()
            except Exception as error:  # one bad tick must not end control; it is shown to people and logged
                logger.exception("control tick failed")
                self.event("internal", f"control tick failed: {type(error).__name__}: {error}", "ERROR")
            # the next period, or sooner when the core has something due (a retry)
            deadline_s = self.core.next_deadline()
            wait_s = period_s - (time.monotonic() - started)
            if deadline_s is not None:
                wait_s = min(wait_s, deadline_s - self.clock())
            await asyncio.sleep(max(0.0, wait_s))

    def control_tick(self) -> None:
        """One control period: the recording's health, the board's state and the scene's target to the core, its
        tick, the table's build, an estimate when due, the status."""
        self.recorder.check()
        self.recorder.set_scene_time(self.scenes.scene_time_s())
        if not self.session.online:
            self._board_configured = False
            link = self.session.status()
            self._feed(self.core.board, False, f"the link is {link['state']}"
                       + (f" ({link['last_error']})" if link.get("last_error") else ""))
        elif self.schedule.window:
            self._feed(self.core.measured, np.mean([frame for _, frame in self.schedule.window], axis=0))
        was_active = self.scenes.active
        target, run = self.scenes.tick(), self.scenes.run
        if was_active and not self.scenes.active:
            self._feed(self.core.scene_ended, "finished")
        if target is not None and run is not None and self.core.state is ControlState.SCENE:
            self._feed(self.core.want, target, f"scene:{run.name}", self.scenes.step_index(), self.scenes.ramp(),
                       self.scenes.verify())
        self._feed(self.core.tick)
        self.scenes.hold(self.core.verifying)
        self.table.report_tick(self.now_s())
        self.estimates.tick(self.now_s(), self.clock(), self.wants_shape(), self.spawn)
        self._publish_status_tick()

    async def check_scene_reachable(self, prepared: PreparedRun) -> None:
        """Refuse a scene with a gland volume step beyond the reachable range when it is loaded, before anything
        moves: ApiError ``unreachable``, as ``set_target``'s, naming the step (index, time) and the range, which
        goes as data too (``gland_range_ml``, ``corrected``, and ``step``, ``at_s``, ``steps``: every volume step
        beyond it).

        The model worker is asked for the scene's highest and lowest volume step only, whatever the number of
        steps: a gland volume is continuous over the pressure box, so that the steps between two reachable ones
        are reachable; an end beyond the range is answered with the worker's own range (the response table's,
        without a solve, where it is at hand; with a correction in force, the corrected model's), and every volume
        step is checked against that range. Steps of the other kinds (pressures, chamber volumes), a volume step
        that only its growth ratio puts out of reach, and answers other than unreachable (the limit point) are
        solved as they come, as before. The caller says what was not started."""
        steps = [(index, step.at_s, volume_ml) for index, step in enumerate(prepared.timeline.steps)
                 if (volume_ml := gland_volume_ml(step.target)) is not None]
        if not steps:
            return
        highest, lowest = max(steps, key=lambda step: step[2]), min(steps, key=lambda step: step[2])
        for index, at_s, volume_ml in dict.fromkeys((highest, lowest)):
            try:
                await self.model.pressures_for(Target(gland_volume_m3=volume_ml / ML_PER_M3))
            except UnreachableTargetError as error:
                where = f"{prepared.name}: steps[{index}] at {at_s:g} s"
                if error.gland_range_ml is None:
                    raise ApiError("unreachable", f"{where}: {error}", {"step": index, "at_s": at_s}) from error
                low_ml, high_ml = (float(value) for value in error.gland_range_ml)
                beyond = sorted({step for step in steps if not low_ml <= step[2] <= high_ml} | {(index, at_s,
                                                                                                 volume_ml)})
                first, corrected = beyond[0], " with the correction in force" if error.corrected else ""
                also = (f" (so are steps {', '.join(str(step[0]) for step in beyond[1:])})" if len(beyond) > 1
                        else "")
                raise ApiError(
                    "unreachable", f"{prepared.name}: steps[{first[0]}] at {first[1]:g} s asks {first[2]:.2f} ml of "
                    f"gland volume, beyond the reachable range {low_ml:.3f} to {high_ml:.3f} ml{corrected}{also}; "
                    "ask for volumes in that range or raise the scene's pressure_max_kpa",
                    {"gland_range_ml": [low_ml, high_ml], "corrected": error.corrected, "step": first[0],
                     "at_s": first[1], "steps": [step[0] for step in beyond]}) from error
            except PhantomError:
                continue  # not a matter of range (the limit point): the step is solved when it comes, as before

    def start_scene(self, prepared: PreparedRun) -> dict[str, Any]:
        """Start playing a checked scene (:func:`phantom.host.scene_runner.prepare_run`)."""
        started = self.scenes.begin(prepared)
        self._feed(self.core.scene_started)
        return started

    def wants_shape(self) -> bool:
        """Whether the deformed shape is worth computing: a recording, and a scene that asks for it."""
        run = self.scenes.run
        scene_asks = self.model.info.wants_shape or (run is not None and not run.finished and run.wants_shape)
        return self.recording and scene_asks

    def _estimated(self, asked_s: float, estimate: Estimate) -> None:
        self._feed(self.core.estimated, estimate.gland_volume_ml, tuple(estimate.chamber_volumes_ml), at=asked_s)
        answer = self.core.answer
        self.scenes.observe(estimate.gland_volume_ml, None if answer is None else predicted_volume_ml(answer),
                            None if answer is None else answer.target, self.plant_volume_ml())

    def plant_volume_ml(self) -> float | None:
        """The simulated plant's true gland volume (ml); None on a real board or before the truth model."""
        return self.sim_board.plant_volume_ml if self.sim_board is not None else None

    def target_volume_ml(self) -> float | None:
        """The gland volume aimed at (ml): the target's for a volume target, else the inverse's prediction."""
        target, answer = self.core.target, self.core.answer
        if target is None or self.core.state is ControlState.VENTED:
            return None
        if target.kind == "volume":
            return gland_volume_ml(target)
        return predicted_volume_ml(answer) if answer is not None else None

    def status(self) -> dict[str, Any]:
        """Everything ``phantom status --json`` shows (host/status.py)."""
        return daemon_status(self)

    def _publish_status_tick(self) -> None:
        """Status to subscribers each control period; link statistics to Rerun twice a second."""
        now_s = self.now_s()
        if self.api.clients:
            self.api.publish("status", self.status())
        if now_s >= self._link_log_due_s:
            self._link_log_due_s = now_s + 0.5
            stats = self.session.status()["stats"]
            self.recorder.log_link(now_s, stats["rtt_ms"], stats["retries"], stats["bad_frames"],
                                   stats["tx_dropped"] + stats["commands_failed"])
