"""The host daemon: one asyncio process that owns the board link, the control state, scenes, Rerun and the API.

The parts, each built before the daemon runs (:meth:`Daemon.start` builds them in this order):

    api        the Unix-socket JSON-lines server (host/api.py): the socket is claimed first, so that a daemon
               that cannot start never touches another daemon's files (its recording included)
    model      the scene's model, inverse and estimator in a worker process (host/model_worker.py)
    recorder   Rerun logging (host/recording.py), opened once the socket is ours
    board      the link session (host/session.py) over a serial port, CAN, or the daemon's own simulated board
               (host/sim_board.py)
    scene      the scene runner (host/scene_runner.py) and the estimate schedule (host/estimation.py)
    handlers   the API's methods (host/handlers.py)

Tasks: the link (``LinkSession.run``), the control loop (every control period: the scene's target, a volume
estimate when due, status to subscribers, link statistics to Rerun), the simulated board's watch.

Control state (``ControlState``): ``idle`` (no target), ``holding`` (a target from the API), ``scene`` (a
scene's timeline drives the target), ``vented`` (blowers off on request). A latched firmware fault is shown
in ``faults`` whatever the state, and only ``clear_fault`` clears it; the daemon then restores the
setpoints of the current target.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import signal
import time
from collections import deque
from collections.abc import Awaitable, Callable, Coroutine
from typing import Any

import numpy as np

from phantom import PhantomError
from phantom.host.api import ApiError, ApiServer, default_socket_path
from phantom.host.config import DaemonConfig
from phantom.host.estimation import EstimateRequest, EstimateSchedule
from phantom.host.handlers import ApiHandlers
from phantom.host.logs import configured_level
from phantom.host.model_worker import Estimate, ModelWorker
from phantom.host.parts import BoardSession, Clock, ControlState, Model, Recording
from phantom.host.recording import Recorder
from phantom.host.scene_runner import SceneRunner
from phantom.host.scenes import gland_volume_ml
from phantom.host.session import (
    BoardInfo,
    CommandRejected,
    LinkDown,
    LinkSession,
    LinkTiming,
    Telemetry,
    Transport,
    fault_names,
)
from phantom.host.sim_board import SimulatedBoardFactory, SimulatedBoardKeeper
from phantom.host.transports import CanTransport, SerialTransport
from phantom.model import load_scene
from phantom.model.errors import SceneError
from phantom.model.target import InverseResult, Target, UnreachableTargetError
from phantom.protocol.link import BOOT_DELAY_S

logger = logging.getLogger(__name__)

PA_PER_KPA = 1e3
ML_PER_M3 = 1e6

#: After connecting, how long the daemon keeps asking a board that answers NOT_SETTLED (s): a board that just
#: started (or a phantom still deflating) needs its readings steady for about 2 s before it accepts a zero;
#: targets wait meanwhile, so that their setpoints do not cancel the zero.
ZERO_SETTLE_WAIT_S = 5.0
#: How often it asks again (s).
ZERO_RETRY_S = 0.5
#: Why the board refuses ZERO_SENSORS, by NACK status (protocol/spec.toml); other statuses are named as such.
ZERO_REFUSALS: dict[str, str] = {
    "NOT_VENTED": "a setpoint or a blower is on: vent first (phantom vent) and wait for the chambers to empty",
    "NOT_SETTLED": "the readings are not steady yet: wait a few seconds after venting and try again",
    "ZERO_OUT_OF_RANGE": "a measured zero is too far from the sensor's nominal zero (a chamber still "
                         "pressurised, or a sensor fault); the old zero is kept",
}

LEVELS = {"INFO": logging.INFO, "WARN": logging.WARNING, "ERROR": logging.ERROR}

#: The control loop's rate (Hz): the scene's target, volume estimates and status to subscribers.
CONTROL_HZ = 10.0
#: File mode of the API's socket: the owner and the group may drive the phantom.
SOCKET_MODE = 0o660


class Daemon:
    """The daemon's state and tasks, from parts built by :meth:`start`; :meth:`serve` until asked to stop."""

    def __init__(self, config: DaemonConfig, api: ApiServer, model: Model, recorder: Recording, session: BoardSession,
                 sim_board: SimulatedBoardKeeper | None, clock: Clock = time.monotonic):
        self.config = config
        self.api = api
        self.model = model
        self.recorder = recorder
        self.session = session
        self.sim_board = sim_board
        self.clock = clock
        self.started_s = clock()
        self.recording = bool(config.rerun_save or config.rerun_connect)
        self.chamber_names = list(model.info.chamber_names)
        self.chamber_labels = list(model.info.chamber_labels)
        self.control_state = ControlState.IDLE
        self.target: Target | None = None
        self.target_source: str | None = None
        #: the inverse's answer to the current target
        self.inverse_result: InverseResult | None = None
        self.setpoints_pa: np.ndarray | None = None
        self.telemetry: Telemetry | None = None
        self.estimated_chamber_ml: list[float] | None = None
        self.estimated_volume_ml: float | None = None
        self.events: deque[dict[str, Any]] = deque(maxlen=100)
        self.fault_flags = 0
        self.model_counts: dict[str, int] = {"full_solves": 0, "tangent_solves": 0, "shapes": 0}
        self.meshes_logged = 0
        self.scenes = SceneRunner(clock, self.event)
        self.schedule = EstimateSchedule(config.mesh_hz)
        self._stop = asyncio.Event()
        self._exit_code = 0
        self._link_log_due_s = 0.0
        self._rest_surface_logged = False
        self._setpoint_lock = asyncio.Lock()
        self._scene_target_pending = False
        self._tasks: list[asyncio.Task[Any]] = []
        self._background: set[asyncio.Task[Any]] = set()

    # --- building the parts -----------------------------------------------------------------------------

    @classmethod
    async def start(cls, config: DaemonConfig, simulated_board: SimulatedBoardFactory | None = None) -> Daemon:
        """Build every part, in an order that never harms another daemon; raises PhantomError (one line).

        ``simulated_board`` builds the board of ``config.sim`` (the command line passes the HIL package's).
        """
        if config.sim and simulated_board is None:
            raise PhantomError("this program cannot simulate a board: start the daemon with `phantom daemon --sim`")
        api = ApiServer(config.socket or default_socket_path(), {}, mode=SOCKET_MODE)
        await api.start()  # first: a second daemon stops here, before it opens anything of the first's
        closers: list[Callable[[], None]] = []  # of the parts built so far, for a start that fails
        try:
            # the recording opens before the model is built: a first start may build the model's response table
            # for minutes, and an unwritable path must not wait for that to be reported
            recorder = Recorder(list(load_scene(config.scene).chambers), config.rerun_save, config.rerun_connect)
            recorder.open()
            closers.append(recorder.close)
            model = await ModelWorker.start(config.scene, configured_level())
            closers.append(model.close)
            sim_board = None
            if simulated_board is not None and config.sim:
                sim_board = SimulatedBoardKeeper(config.sim_speed, lambda kind, text, level: None, simulated_board)
                closers.append(sim_board.close)
                logger.info("starting the simulated board (firmware in simavr, speed %g) ...", config.sim_speed)
                await asyncio.get_running_loop().run_in_executor(None, sim_board.start)
            # the session calls the daemon, which is built after it: the callbacks find it here
            wired: dict[str, Daemon] = {}
            session = _link_session(config, sim_board, on_telemetry=lambda frame: wired["daemon"].on_telemetry(frame),
                                    on_event=lambda kind, text, level: wired["daemon"].event(kind, text, level),
                                    on_online=lambda board, again: wired["daemon"].on_online(board, again))
        except BaseException:
            for close in reversed(closers):
                with contextlib.suppress(Exception):
                    close()
            await api.close()
            raise
        daemon = wired["daemon"] = cls(config, api, model, recorder, session, sim_board)
        if sim_board is not None:
            sim_board.on_event = daemon.event
        api.handlers.update(ApiHandlers(daemon).table())
        return daemon

    # --- life cycle -------------------------------------------------------------------------------------

    def now_s(self) -> float:
        """Seconds since the daemon started (the recording's time line)."""
        return float(self.clock() - self.started_s)

    async def serve(self) -> int:
        """Run the tasks until SIGTERM/SIGINT or :meth:`request_stop`, then vent and close; the exit code."""
        loop = asyncio.get_running_loop()
        for signum in (signal.SIGTERM, signal.SIGINT):
            loop.add_signal_handler(signum, self.request_stop)
        loop.set_exception_handler(_log_loop_exception)
        try:
            info = self.model.info
            self.event("startup", "model ready: " + ", ".join(f"{key} {value:.2f} s"
                                                             for key, value in info.timings_s.items()))
            self._tasks = [asyncio.create_task(self.session.run(), name="link"),
                           asyncio.create_task(self._control_loop(), name="control")]
            if self.sim_board is not None:
                self._tasks.append(asyncio.create_task(self.sim_board.watch(), name="simulated board"))
            for task in self._tasks:
                task.add_done_callback(self._task_ended)
            logger.info("ready: API on %s, board on %s", self.api.socket_path, self.session.transport.description)
            if self.config.run_scene:
                try:
                    self.start_scene(info.scene_raw, info.scene_path, 1.0, info.wants_shape)
                except SceneError as error:
                    self.event("scene", f"the scene's [[steps]] were not started: {error}", "ERROR")
            await self._stop.wait()
        finally:
            await self._shutdown()
        return self._exit_code

    def _task_ended(self, task: asyncio.Task[Any]) -> None:
        """A main task must run until shutdown: one that failed is a bug, logged with its traceback, and the
        daemon stops (exit status 1; under systemd it is restarted)."""
        if task.cancelled() or self._stop.is_set():
            return
        error = task.exception()
        logger.error("the %s task ended unexpectedly", task.get_name(), exc_info=error)
        self.event("internal", f"the {task.get_name()} task ended: {type(error).__name__}: {error}", "ERROR")
        self._exit_code = 1
        self.request_stop()

    def spawn(self, coroutine: Coroutine[Any, Any, Any]) -> asyncio.Task[Any]:
        """A background task, referenced until it ends (the event loop keeps only weak references)."""
        task = asyncio.create_task(coroutine)
        self._background.add(task)
        task.add_done_callback(self._background.discard)
        return task

    def request_stop(self) -> None:
        """Ask :meth:`serve` to shut down (SIGTERM and SIGINT do this)."""
        self._stop.set()

    async def _shutdown(self) -> None:
        """Vent the phantom (if the board is there), close the recording, the API, the link and the model."""
        logger.info("stopping: venting and closing")
        if self.config.vent_on_exit and self.session.online:
            try:
                await asyncio.wait_for(self.session.command("VENT"), 2.0)
                self.event("vent", "vented on shutdown")
            except (TimeoutError, PhantomError) as error:
                self.event("vent", f"could not vent on shutdown: {error}", "ERROR")
        self.session.stop()
        for task in [*self._tasks, *self._background]:
            task.cancel()
        for task in [*self._tasks, *self._background]:
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await task
        self.session.transport.close()
        await self.api.close()
        self.recorder.log_event(self.now_s(), "daemon stopped")
        self.recorder.close()
        if self.sim_board is not None:
            await asyncio.get_running_loop().run_in_executor(None, self.sim_board.close)
        self.model.close()

    # --- events and telemetry ---------------------------------------------------------------------------

    def event(self, kind: str, text: str, level: str = "INFO") -> None:
        """Record an event: the status's recent events, Rerun's text log, subscribers, the log."""
        entry = {"time_s": round(self.now_s(), 3), "kind": kind, "level": level, "text": text}
        self.events.append(entry)
        self.recorder.log_event(self.now_s(), text, level)
        self.api.publish("events", entry)
        logger.log(LEVELS.get(level, logging.INFO), "%s", text)

    def on_telemetry(self, telemetry: Telemetry) -> None:
        """Keep the latest frame and the estimation window; log and publish it."""
        self.telemetry = telemetry
        self.schedule.add(telemetry.board_time_ms / 1e3, telemetry.pressures_pa)
        if telemetry.fault_flags != self.fault_flags:
            if telemetry.fault_flags and not self.fault_flags:
                self.event("fault", f"faults latched: {', '.join(fault_names(telemetry.fault_flags))}", "ERROR")
            elif not telemetry.fault_flags:
                self.event("fault", "faults cleared")
            self.fault_flags = telemetry.fault_flags
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
        """The link came up: zero the sensors if the phantom is vented, else restore the current setpoints
        (a board that reset starts with none)."""
        self.schedule.clear()
        if board.chamber_count != len(self.chamber_names):
            self.event("link", f"the board has {board.chamber_count} chambers, the scene "
                       f"{len(self.chamber_names)}: setpoints not sent", "ERROR")
            return
        if self.setpoints_pa is not None and self.control_state is not ControlState.VENTED and np.any(
                self.setpoints_pa > 0):
            self.spawn(self.send_setpoints_quietly(self.setpoints_pa, "restored after (re)connection"))
        elif self.config.zero_on_connect:
            self.spawn(self.zero_quietly())

    async def zero_quietly(self) -> None:
        """ZERO_SENSORS after connecting to a vented phantom; a refusal is an event, not an error."""
        try:
            acknowledged = await self.zero_sensors(settle_wait_s=ZERO_SETTLE_WAIT_S)
            self.event("zero", "sensors zeroed after connecting (the phantom was vented)"
                       + ("" if acknowledged else "; the board's ACK was not seen (a retransmission found it busy)"))
        except ApiError as error:
            self.event("zero", f"sensors not zeroed after connecting: {error}", "WARN")

    async def zero_sensors(self, settle_wait_s: float = 0.0) -> bool:
        """ZERO_SENSORS; True when acknowledged, False when the board was found zeroing already (its ACK comes
        after the zeroing, about 128 ms, so a retransmission can meet BUSY while our own request runs: the
        daemon then waits for the telemetry to leave ZEROING). A board that answers NOT_SETTLED is asked again
        every ``ZERO_RETRY_S`` for up to ``settle_wait_s`` seconds. Raises ApiError ``rejected`` saying why the
        board refused."""
        # the board answers BUSY to setpoints while it zeroes: a target waits for the zeroing instead
        async with self._setpoint_lock:
            give_up_s = time.monotonic() + settle_wait_s
            while True:
                try:
                    await self.session.command("ZERO_SENSORS")
                    return True
                except LinkDown as error:
                    raise ApiError("link_down", str(error)) from error
                except CommandRejected as error:
                    if error.status == "BUSY":
                        break
                    if error.status == "NOT_SETTLED" and time.monotonic() + ZERO_RETRY_S <= give_up_s:
                        await asyncio.sleep(ZERO_RETRY_S)
                        continue
                    why = ZERO_REFUSALS.get(error.status, f"the board answered {error.status}")
                    raise ApiError("rejected", f"the board refused to zero its sensors: {error.status} "
                                   f"({why})") from error
            for _ in range(40):
                await asyncio.sleep(0.05)
                if self.telemetry is not None and "ZEROING" not in self.telemetry.states:
                    return False
            raise ApiError("rejected", "the board stayed busy zeroing its sensors for 2 s: try again")

    # --- control ----------------------------------------------------------------------------------------

    async def _control_loop(self) -> None:
        """Every control period: scene target, volume estimate, status, Rerun."""
        period_s = 1.0 / CONTROL_HZ
        while True:
            started = time.monotonic()
            try:
                self.recorder.set_scene_time(self.scenes.scene_time_s())
                self._scene_tick()
                self._estimate_tick()
                self._publish_status_tick()
            except Exception as error:  # one bad tick must not end control; it is shown to people and logged
                logger.exception("control tick failed")
                self.event("internal", f"control tick failed: {type(error).__name__}: {error}", "ERROR")
            await asyncio.sleep(max(0.0, period_s - (time.monotonic() - started)))

    def wants_shape(self) -> bool:
        """Whether the deformed shape is worth computing: a recording, and a scene that asks for it."""
        run = self.scenes.run
        scene_asks = self.model.info.wants_shape or (run is not None and not run.finished and run.wants_shape)
        return self.recording and scene_asks

    def _estimate_tick(self) -> None:
        request = self.schedule.due(self.now_s(), self.wants_shape())
        if request is None:
            return
        task = self.spawn(self.model.estimate(request.pressures_pa, request.with_shape,
                                              not self._rest_surface_logged))
        task.add_done_callback(lambda done: self._estimate_done(done, request))

    def _estimate_done(self, done: asyncio.Task[Estimate], request: EstimateRequest) -> None:
        self.schedule.finished()
        if done.cancelled():
            return
        try:
            estimate = done.result()
        except Exception as error:  # shown, not fatal: the next tick tries again
            self.event("estimate", f"volume estimate failed: {error}", "WARN")
            return
        self.model_counts = estimate.counts
        self.estimated_chamber_ml, self.estimated_volume_ml = estimate.chamber_volumes_ml, estimate.gland_volume_ml
        self.recorder.log_volumes(request.time_s, self.target_volume_ml(), estimate.gland_volume_ml,
                                  estimate.chamber_volumes_ml, true_ml=self.plant_volume_ml())
        if estimate.surface_mm is not None:
            if estimate.rest_surface_mm is not None and not self._rest_surface_logged:
                self._rest_surface_logged = True
                self.recorder.log_rest_surface(*estimate.rest_surface_mm)
            self.recorder.log_mesh(request.time_s, *estimate.surface_mm)
            self.meshes_logged += 1
        answer = self.inverse_result
        self.scenes.observe(estimate.gland_volume_ml, None if answer is None else _predicted_volume_ml(answer),
                            None if answer is None else answer.target, self.plant_volume_ml())

    def plant_volume_ml(self) -> float | None:
        """The simulated plant's true gland volume (ml); None on a real board or before the truth model."""
        return self.sim_board.plant_volume_ml if self.sim_board is not None else None

    def target_volume_ml(self) -> float | None:
        """The gland volume aimed at (ml): the target's for a volume target, else the inverse's prediction."""
        if self.target is None or self.control_state is ControlState.VENTED:
            return None
        if self.target.kind == "volume":
            return gland_volume_ml(self.target)
        return _predicted_volume_ml(self.inverse_result) if self.inverse_result is not None else None

    async def apply_target(self, target: Target, source: str) -> dict[str, Any]:
        """Find the pressures for ``target`` (the inverse, in the model worker) and send them as setpoints;
        returns the inverse's answer as JSON.

        Raises ApiError ``unreachable`` (with the reachable range), ``link_down`` or ``rejected``.
        """
        try:
            answer = await self.model.pressures_for(target)
        except UnreachableTargetError as error:
            raise ApiError("unreachable", str(error)) from error
        self.recorder.log_solver(self.now_s(), answer.qp_solve_time_s, answer.solve_time_s)
        if source != "api" and self.control_state is not ControlState.SCENE:
            # the scene was stopped (vent, a new target) while the inverse ran: its answer is stale
            return answer.to_json()
        await self.send_setpoints(answer.pressures_pa)
        changed = self.target != target
        self.target, self.target_source, self.inverse_result = target, source, answer
        if changed and source == "api":
            self.event("target", f"target {target.describe()} -> setpoints "
                       f"{', '.join(f'{p / PA_PER_KPA:.3f}' for p in answer.pressures_pa)} kPa "
                       f"(predicted {_predicted_volume_ml(answer):.2f} ml, "
                       f"inverse {answer.solve_time_s * 1e3:.1f} ms)")
        return answer.to_json()

    async def board_command(self, name: str, fields: dict[str, Any] | None = None) -> str:
        """One acknowledged command to the board for an API request; link errors become API errors."""
        try:
            return str(await self.session.command(name, fields))
        except LinkDown as error:
            raise ApiError("link_down", str(error)) from error
        except CommandRejected as error:
            raise ApiError("rejected", str(error)) from error

    async def send_setpoints(self, pressures_pa: np.ndarray) -> str:
        """SET_SETPOINTS (acknowledged); translates link errors into API errors."""
        setpoints = [int(round(min(max(p, 0.0), 32767.0))) for p in pressures_pa]
        async with self._setpoint_lock:
            status = await self.board_command("SET_SETPOINTS", {"setpoint_pa": setpoints})
        self.setpoints_pa = np.asarray(setpoints, dtype=float)
        if self.control_state is ControlState.VENTED or self.control_state is ControlState.IDLE:
            self.control_state = ControlState.HOLDING
        if status == "CLAMPED":
            self.event("setpoints", "the board clamped a setpoint to its pressure limit", "WARN")
        return status

    async def send_setpoints_quietly(self, pressures_pa: np.ndarray, why: str) -> None:
        """Send setpoints from a background path (reconnection, scene); failures become events, once."""
        try:
            await self.send_setpoints(pressures_pa)
            self.event("setpoints", f"setpoints {why}")
        except ApiError as error:
            self.event("setpoints", f"setpoints not sent ({why}): {error}", "WARN")

    # --- scenes -----------------------------------------------------------------------------------------

    def start_scene(self, raw: dict[str, Any], name: str, time_scale: float, wants_shape: bool) -> dict[str, Any]:
        """Check a scene's timeline against the loaded phantom and start playing it (SceneError if bad)."""
        started = self.scenes.start(raw, name, self.chamber_names, time_scale, wants_shape)
        self.control_state = ControlState.SCENE
        return started

    def _scene_tick(self) -> None:
        """Move the scene's target along its timeline; hold the last one when it ends."""
        was_active = self.scenes.active
        target = self.scenes.tick()
        if was_active and not self.scenes.active and self.control_state is ControlState.SCENE:
            self.control_state = ControlState.HOLDING
        run = self.scenes.run
        if target is not None and run is not None and target != self.target and not self._scene_target_pending:
            self._scene_target_pending = True
            task = self.spawn(self._apply_scene_target(target, run.name))
            task.add_done_callback(lambda _: setattr(self, "_scene_target_pending", False))

    async def _apply_scene_target(self, target: Target, name: str) -> None:
        try:
            await self.apply_target(target, f"scene:{name}")
        except ApiError as error:
            if self.target != target:
                self.event("scene", f"scene target {target.describe()} not applied: {error}", "WARN")
                self.target = target

    # --- status -----------------------------------------------------------------------------------------

    def status(self) -> dict[str, Any]:
        """Everything ``phantom status --json`` shows."""
        telemetry = self.telemetry if self.session.online else None  # a stale frame is not shown
        fresh = telemetry is not None
        link = self.session.status()
        info = self.model.info
        status = {
            "link": link["state"],
            "link_detail": link,
            "control": self.control_state.value,
            "chambers": self.chamber_names,
            "chamber_labels": self.chamber_labels,
            "pressures_kpa": (telemetry.pressures_pa / PA_PER_KPA).tolist() if telemetry is not None else None,
            "setpoints_kpa": (self.setpoints_pa / PA_PER_KPA).tolist() if self.setpoints_pa is not None else None,
            "board_setpoints_kpa": (telemetry.setpoints_pa / PA_PER_KPA).tolist() if telemetry is not None else None,
            "drive_levels": telemetry.drive_levels.tolist() if telemetry is not None else None,
            "chamber_states": telemetry.states if telemetry is not None else None,
            "estimated_volume_ml": self.estimated_volume_ml if fresh else None,
            "estimated_chamber_volumes_ml": self.estimated_chamber_ml if fresh else None,
            "rest_volume_ml": info.rest_volume_ml,
            "target_volume_ml": self.target_volume_ml(),
            "target": self.target.to_json() if self.target is not None else None,
            "target_source": self.target_source,
            "solution": self.inverse_result.to_json() if self.inverse_result is not None else None,
            "faults": fault_names(self.fault_flags),
            "scene": self.scenes.to_json(),
            "startup_s": info.timings_s,
            "fidelity": info.fidelity,
            "model_counts": self.model_counts,
            "meshes_logged": self.meshes_logged,
            "api": self.api.stats(),
            "recording": str(self.config.rerun_save) if self.config.rerun_save else self.config.rerun_connect,
            "uptime_s": self.now_s(),
            "events": list(self.events)[-10:],
        }
        if self.sim_board is not None:
            status["simulated_board"] = self.sim_board.status()
            if self.sim_board.plant_volume_ml is not None:
                status["plant_volume_ml"] = self.sim_board.plant_volume_ml
        return status

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


def _predicted_volume_ml(answer: InverseResult) -> float:
    """The gland volume (ml) the inverse predicts for its pressures."""
    return float(answer.predicted_gland_volume_m3) * ML_PER_M3


def _log_loop_exception(loop: asyncio.AbstractEventLoop, context: dict[str, Any]) -> None:
    """Errors the event loop catches (a background task's exception nobody awaited) go to the log with their
    traceback."""
    logger.error("unexpected error: %s", context.get("message", "in the event loop"), exc_info=context.get("exception"))


def _link_session(config: DaemonConfig, sim_board: SimulatedBoardKeeper | None,
                  on_telemetry: Callable[[Telemetry], None], on_event: Callable[[str, str, str], None],
                  on_online: Callable[[BoardInfo, bool], Awaitable[None]]) -> LinkSession:
    """The link session over the configured transport."""
    transport: Transport
    boot_delay_s = 0.0
    if config.can_channel:
        transport = CanTransport(config.can_channel, config.can_interface)
    elif sim_board is not None:
        transport = SerialTransport(sim_board.port, config.baud)
        boot_delay_s = BOOT_DELAY_S["sim"]
    else:
        assert config.port is not None  # a DaemonConfig has exactly one board
        transport = SerialTransport(config.port, config.baud)
        boot_delay_s = max(BOOT_DELAY_S.values()) if config.boot_delay_s is None else config.boot_delay_s
    # a simulated board faster than real time passes its dead-host deadline sooner (speed 0: as fast as it can,
    # about 5x here)
    speed = (config.sim_speed or 10.0) if config.sim else 1.0
    # a HELLO that opened a session on the board but whose reply was lost must be repeated before the board's
    # dead-host deadline passes: HELLOs go out at twice the keepalive period
    timing = LinkTiming(keepalive_s=min(0.1, 0.1 / speed), hello_timeout_s=min(0.2, 0.2 / speed),
                        telemetry_period_ms=config.telemetry_period_ms, host_deadline_ms=config.host_deadline_ms,
                        boot_delay_s=boot_delay_s)
    return LinkSession(transport, timing, on_telemetry=on_telemetry, on_event=on_event, on_online=on_online)


async def _run(config: DaemonConfig, simulated_board: SimulatedBoardFactory | None) -> int:
    daemon = await Daemon.start(config, simulated_board)
    return await daemon.serve()


def run_daemon(config: DaemonConfig, simulated_board: SimulatedBoardFactory | None = None) -> int:
    """Run the daemon in this process until SIGTERM/SIGINT; returns the exit status. ``simulated_board`` builds
    the board of ``config.sim``."""
    return asyncio.run(_run(config, simulated_board))
