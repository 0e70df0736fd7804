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
import math
import os
import signal
import time
from collections import deque
from collections.abc import Awaitable, Callable, Coroutine
from typing import Any

import numpy as np

from phantom import PhantomError
from phantom.host.api import ApiError, ApiServer, Handler, default_socket_path
from phantom.host.board_watch import BoardSettings, SetpointWatch, Stillness
from phantom.host.config import DaemonConfig
from phantom.host.estimation import EstimateRequest, EstimateSchedule
from phantom.host.handlers import ApiHandlers
from phantom.host.logs import configured_level
from phantom.host.model_worker import Estimate, ModelWorker
from phantom.host.motion import Orbit, Scanner, scan_method, simulated_truth
from phantom.host.parts import BoardSession, Clock, ControlState, Model, Recording
from phantom.host.recording import Recorder
from phantom.host.scene_runner import PreparedRun, SceneRunner, prepare_run
from phantom.host.scenes import gland_volume_ml
from phantom.host.session import (
    BoardInfo,
    CommandRejected,
    LinkDown,
    LinkSession,
    LinkThread,
    LinkTiming,
    Telemetry,
    Transport,
    fault_names,
)
from phantom.host.sim_board import SimulatedBoardFactory, SimulatedBoardKeeper
from phantom.host.stalls import LoopStalls
from phantom.host.startup import StartupProgress, TableBuild, notify_systemd
from phantom.host.transports import CanTransport, SerialTransport
from phantom.model import load_scene
from phantom.model.errors import SceneError
from phantom.model.target import InverseResult, Target, UnreachableTargetError
from phantom.protocol.codec import Message
from phantom.protocol.link import BOOT_DELAY_S

logger = logging.getLogger(__name__)

PA_PER_KPA = 1e3
ML_PER_M3 = 1e6

#: After connecting, how long the daemon keeps asking a board that answers NOT_SETTLED (s): the board zeroes only
#: once every reading has been still for 2 s, which a phantom still deflating after a vent or a reset takes a
#: while to be; the daemon asks again each time the readings have been still that long (its status says how far
#: they are), and says the zero is missing if they never are. Targets wait meanwhile, so that their setpoints do
#: not cancel the zero.
ZERO_SETTLE_LIMIT_S = 60.0
#: How often the wait looks at the readings (s); the board is asked again at least every four of these.
ZERO_RETRY_S = 0.5
#: How long clear_fault waits, once the board acknowledged it, for a telemetry frame without the fault (s).
CLEARED_IN_TELEMETRY_S = 1.0
#: After a target could not be sent (refused, not acknowledged), how long the control loop waits before it tries
#: again (s).
RETRY_S = 0.5
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
#: The methods that need the board: before the daemon is first ready they answer ``starting`` (with its progress).
BOARD_METHODS = ("set_target", "run_scene", "zero", "clear_fault")
#: How often (s) the background table build's progress goes to the log and to systemd's status line.
BUILD_REPORT_S = 10.0



class Daemon:
    """The daemon's state and tasks, from parts built by :meth:`start`; :meth:`serve` until asked to stop."""

    def __init__(self, config: DaemonConfig, api: ApiServer, model: Model, recorder: Recording, session: BoardSession,
                 sim_board: SimulatedBoardKeeper | None, clock: Clock = time.monotonic,
                 startup: StartupProgress | None = None):
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
        self._model_restarts_seen = 0
        self.meshes_logged = 0
        self.scenes = SceneRunner(clock, self.event)
        self.schedule = EstimateSchedule(config.mesh_hz)
        #: the target the board holds (its setpoints acknowledged and not lost since), and why the current one waits
        self.applied_target: Target | None = None
        self.target_pending: str | None = None
        self.vented_why: str | None = None
        self.board_settings = BoardSettings(config.kp_per_kpa, config.ki_per_kpa_s, config.kd_s_per_kpa,
                                            config.pressure_limit_kpa * PA_PER_KPA)
        self.board_settings_source = "not set yet: no board has been connected"
        self.setpoint_watch = SetpointWatch()
        self.loop_stalls = LoopStalls()
        self.stillness = Stillness()
        self.zero_state: dict[str, Any] = {"state": "not asked", "text": "no zero asked since the daemon started"}
        self._stop = asyncio.Event()
        self._exit_code = 0
        self._link_log_due_s = 0.0
        self._rest_surface_logged = False
        self._setpoint_lock = asyncio.Lock()
        self._zeroing = False
        self._zero_done = asyncio.Event()
        self._applying = False
        self._was_online = False
        self._pending_since_s: float | None = None
        self._retry_after_s = 0.0
        self._unreachable: Target | None = None
        self._target_step: int | None = None
        self._target_ramp: tuple[Target, Target] | None = None
        self._tasks: list[asyncio.Task[Any]] = []
        self._background: set[asyncio.Task[Any]] = set()
        #: start-up: what it is doing until ready (the model answers and the board was first online and zeroed)
        self.startup = startup or StartupProgress(clock)
        self.ready = False
        #: the scene's response table being built in the background (the model answers on full solves meanwhile)
        self.table_build: TableBuild | None = None
        #: when the build's progress was last logged: never, so the first control tick of a build logs it (a
        #: session shorter than BUILD_REPORT_S still says the build ran)
        self._build_reported_s = -math.inf
        #: the scanner's axes (host/motion.py)
        self.motion = Orbit(self.board_command, self.event, simulated_truth(sim_board) if sim_board else None)

    # --- building the parts -----------------------------------------------------------------------------

    @classmethod
    async def start(cls, config: DaemonConfig, simulated_board: SimulatedBoardFactory | None = None) -> Daemon:
        """Build every part, in an order that never harms another daemon; raises PhantomError (one line).

        ``simulated_board`` builds the board of ``config.sim`` (the command line passes the HIL package's).
        """
        if config.sim and simulated_board is None:
            raise PhantomError("this program cannot simulate a board: start the daemon with `phantom daemon --sim`")
        startup = StartupProgress()
        api = ApiServer(config.socket or default_socket_path(), {}, mode=SOCKET_MODE)
        api.starting = lambda: ApiError("starting", f"the daemon is still starting: {startup.text()}",
                                        startup.to_json())
        await api.start()  # first: a second daemon stops here, before it opens anything of the first's
        closers: list[Callable[[], None]] = []  # of the parts built so far, for a start that fails
        try:
            # the recording opens before the model is built: a path another daemon records to, or one that
            # cannot be written, is refused before anything slow
            wired: dict[str, Daemon] = {}  # the callbacks find the daemon here once it is built
            startup.enter("opening the recording")
            recorder = Recorder(load_scene(config.scene).chamber_labels, config.rerun_save, config.rerun_connect,
                                on_problem=lambda text, level: wired["daemon"].event("recording", text, level))
            recorder.open()
            closers.append(recorder.close)
            # a response table that is not stored yet is built in the background (serve() starts it) while the
            # worker answers on full solves
            startup.enter(f"loading the model of {config.scene}")
            model = await ModelWorker.start(config.scene, configured_level(), defer_table=True,
                                            on_message=startup.tell)
            closers.append(model.close)
            sim_board = None
            if simulated_board is not None and config.sim:
                sim_board = SimulatedBoardKeeper(config.sim_speed, lambda kind, text, level: None, simulated_board)
                closers.append(sim_board.close)
                startup.enter(f"starting the simulated board (firmware in simavr, speed {config.sim_speed:g})")
                await asyncio.get_running_loop().run_in_executor(None, sim_board.start)
            session = _link_session(config, sim_board, on_telemetry=lambda frame: wired["daemon"].on_telemetry(frame),
                                    on_event=lambda kind, text, level: wired["daemon"].event(kind, text, level),
                                    on_online=lambda board, again: wired["daemon"].on_online(board, again),
                                    on_motion=lambda message: wired["daemon"].motion.on_message(message))
        except BaseException:
            for close in reversed(closers):
                with contextlib.suppress(Exception):
                    close()
            await api.close()
            raise
        daemon = wired["daemon"] = cls(config, api, model, recorder, session, sim_board, startup=startup)
        if sim_board is not None:
            sim_board.on_event = daemon.event
        handlers = ApiHandlers(daemon).table()
        for name in BOARD_METHODS:
            handlers[name] = daemon.when_ready(handlers[name])
        api.handlers.update(handlers)
        api.handlers.update(daemon.motion.api_methods())
        startup.enter("waiting for the board: the first connection")
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
                           asyncio.create_task(self._control_loop(), name="control"),
                           asyncio.create_task(self.loop_stalls.probe(), name="event loop probe")]
            if info.pending_fidelity is not None:
                self._start_table_build()
            if self.sim_board is not None:
                self._tasks.append(asyncio.create_task(self.sim_board.watch(), name="simulated board"))
            for task in self._tasks:
                task.add_done_callback(self._task_ended)
            logger.info("serving: API on %s, board on %s", self.api.socket_path, self.session.transport.description)
            if self.config.run_scene:
                try:
                    self.start_scene(prepare_run(info.scene_raw, info.scene_path, self.chamber_names, 1.0,
                                                 info.wants_shape))
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
            # and the board's session ends, so that it does not latch DEAD_HOST once the daemon is gone
            if await self.session.end_session():
                self.event("link", "session ended: the board is vented and expects no host")
            else:
                self.event("link", "the board did not answer the end of its session: it will latch DEAD_HOST",
                           "WARN")
        notify_systemd("STOPPING=1")
        self.session.stop()
        if self.table_build is not None:
            asyncio.get_running_loop().remove_reader(self.table_build.fileno())
            self.table_build.stop()
        for task in [*self._tasks, *self._background]:
            task.cancel()
        for task in [*self._tasks, *self._background]:
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await task
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
        """Keep the latest frame and the estimation window; check the board's setpoints; log and publish it."""
        self.telemetry = telemetry
        self.schedule.add(telemetry.board_time_ms / 1e3, telemetry.pressures_pa)
        self.stillness.frame(telemetry.board_time_ms / 1e3, telemetry.pressures_pa)
        if telemetry.fault_flags != self.fault_flags:
            if telemetry.fault_flags and not self.fault_flags:
                self.event("fault", f"faults latched: {', '.join(fault_names(telemetry.fault_flags))}", "ERROR")
                # the board set every setpoint to 0 and will refuse setpoints until the fault is cleared
                self._board_dropped_setpoints(np.zeros(len(self.chamber_names)))
            elif not telemetry.fault_flags:
                self.event("fault", "faults cleared")
            self.fault_flags = telemetry.fault_flags
        if not telemetry.fault_flags and self.setpoint_watch.frame(telemetry.setpoints_pa, self.clock()):
            self._mismatch(telemetry.setpoints_pa)
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
        """The link came up: set the board's gains and limits, then apply the current target (a board that reset
        holds no setpoints), or zero the sensors if the phantom is vented."""
        self.schedule.clear()
        self.stillness = Stillness()
        self._board_dropped_setpoints(None)
        self.spawn(self.motion.restore())
        if board.chamber_count != len(self.chamber_names):
            self.event("link", f"the board has {board.chamber_count} chambers, the scene "
                       f"{len(self.chamber_names)}: setpoints not sent", "ERROR")
            return
        await self.send_board_settings("at connection")
        if self.target is None or self.control_state is ControlState.VENTED:
            # the daemon drives nothing: setpoints on the board are someone else's
            self.setpoints_pa = np.zeros(len(self.chamber_names))
            self.setpoint_watch.expect(self.setpoints_pa, self.clock())
            if self.config.zero_on_connect:
                self._zeroing = True  # targets wait for the zero from now on
                if not self.ready:
                    self.startup.enter("zeroing the pressure sensors (the phantom is vented)")
                self.spawn(self.zero_quietly()).add_done_callback(lambda _: self._became_ready())
                return
        self._became_ready()

    # --- readiness and the background table -------------------------------------------------------------

    def _became_ready(self) -> None:
        """The model answers and the board is online (and zeroed): tell systemd and the clients, once."""
        if self.ready or self._stop.is_set():
            return
        self.ready = True
        fidelity = self.model.info.fidelity
        building = f" (the {self.model.info.pending_fidelity} level is being built)" if (
            self.model.info.pending_fidelity) else ""
        since_start_s = self.startup.clock() - self.startup.started_s
        self.event("startup", f"ready {since_start_s:.1f} s after start: the model answers on {fidelity}{building}, "
                   "the board is online")
        notify_systemd("READY=1", f"STATUS=ready: fidelity {fidelity}{building}")

    def when_ready(self, handler: Handler) -> Handler:
        """``handler``, answering ``starting`` with the start-up's progress until the daemon is first ready."""
        async def guarded(params: dict[str, Any]) -> object:
            if not self.ready:
                link = self.session.state.value
                raise ApiError("starting", f"the daemon is still starting: {self.startup.text()}; the link is {link}",
                               {**self.startup.to_json(), "link": link})
            return await handler(params)
        return guarded

    def _start_table_build(self) -> None:
        """Build the scene's response table in the background (a process group of its own, at a lower priority);
        its progress goes to status, the log and systemd, and the model switches to it when it is stored."""
        self.table_build = TableBuild(self.config.scene)
        self.event("model", f"the model answers on full solves (most of a second each) while its response table "
                   f"is built in the background (process {self.table_build.pid}, once per model and machine)")
        asyncio.get_running_loop().add_reader(self.table_build.fileno(), self._table_build_readable)

    def _table_build_readable(self) -> None:
        build = self.table_build
        assert build is not None  # the reader exists only while a build does
        if not build.read():
            return
        asyncio.get_running_loop().remove_reader(build.fileno())
        if build.error is not None:
            self.event("model", f"the response table could not be built ({build.error}): the model keeps "
                       "answering on full solves", "ERROR")
            return
        self.spawn(self._switch_to_table(build))

    def _report_build_tick(self) -> None:
        """Every BUILD_REPORT_S while the table builds: how far it is, in the log and systemd's status line."""
        build = self.table_build
        if build is None or build.finished or self.now_s() - self._build_reported_s < BUILD_REPORT_S:
            return
        self._build_reported_s = self.now_s()
        text = build.text()
        logger.info("%s (the model answers on full solves until then)", text)
        notify_systemd(f"STATUS={'ready' if self.ready else self.startup.stage}; {text}")

    async def _switch_to_table(self, build: TableBuild) -> None:
        """The table is stored: the worker answers from it; a target held from the API is solved again on it."""
        pending = self.model.info.pending_fidelity or "table"
        info = await self.model.use_level(pending)
        self.event("model", f"switched to the {info.fidelity} level: the response table was built in "
                   f"{build.progress.elapsed_s:.0f} s, within {build.check_errors_pct or 0.0:.2g} % of full solves")
        notify_systemd(f"STATUS={'ready' if self.ready else self.startup.stage}: fidelity {info.fidelity}")
        if self.target is not None and self.control_state is not ControlState.VENTED:
            # the target's setpoints came from a full solve: the control loop solves it again on the new level and
            # sends them (or says why it cannot)
            async with self._setpoint_lock:
                self.inverse_result, self.applied_target = None, None

    async def send_board_settings(self, when: str) -> bool:
        """SET_PID to every chamber with the daemon's gains and limit; the answer goes to ``board_settings`` in the
        status. A refusal because a chamber holds a setpoint above the new limit vents first."""
        for chamber in range(len(self.chamber_names)):
            fields = self.board_settings.set_pid_fields(chamber)
            try:
                try:
                    await self.session.command("SET_PID", fields)
                except CommandRejected as error:
                    if error.status != "BAD_VALUE":
                        raise
                    self.event("board", f"the board refused its limits with a setpoint above "
                               f"{self.board_settings.pressure_limit_pa / PA_PER_KPA:g} kPa: venting first", "WARN")
                    await self.session.command("VENT")
                    await self.session.command("SET_PID", fields)
            except (LinkDown, CommandRejected) as error:
                self.board_settings_source = f"unknown: SET_PID failed ({error})"
                self.event("board", f"the board's gains and limits could not be set {when}: {error}", "ERROR")
                return False
        self.board_settings_source = f"set by the daemon {when} (SET_PID acknowledged, {time.strftime('%H:%M:%S')})"
        return True

    async def zero_quietly(self) -> None:
        """ZERO_SENSORS after connecting to a vented phantom, waiting for still readings; a refusal is an event
        and the status's ``zero`` says the zero is missing."""
        try:
            acknowledged = await self.zero_sensors(settle_limit_s=ZERO_SETTLE_LIMIT_S)
            self.event("zero", "sensors zeroed after connecting (the phantom was vented)"
                       + ("" if acknowledged else "; the board's ACK was not seen (a retransmission found it busy)"))
        except ApiError as error:
            self.zero_state = {"state": "missing", "text": f"the sensors were not zeroed after connecting: {error}"}
            self.event("zero", f"sensors not zeroed after connecting: {error}", "WARN")

    async def zero_sensors(self, settle_limit_s: float = 0.0) -> bool:
        """ZERO_SENSORS; True when acknowledged, False when the board was found zeroing already (its ACK comes
        after the zeroing, about 128 ms, so a retransmission can meet BUSY while our own request runs: the
        daemon then waits for the telemetry to leave ZEROING). A board that answers NOT_SETTLED is asked again,
        for up to ``settle_limit_s`` seconds, each time the readings have been still for as long as the board
        needs (its own rule, followed on the telemetry; the progress is in the status's ``zero``). Targets wait
        meanwhile, so that their setpoints do not cancel the zero. Raises ApiError ``rejected`` saying why the
        board refused."""
        self._zeroing = True
        self._zero_done.clear()
        give_up_s = time.monotonic() + settle_limit_s
        try:
            while True:
                async with self._setpoint_lock:
                    try:
                        await self.session.command("ZERO_SENSORS")
                        self.zero_state = {"state": "zeroed", "text": f"zeroed at {time.strftime('%H:%M:%S')}"}
                        return True
                    except LinkDown as error:
                        raise ApiError("link_down", str(error)) from error
                    except CommandRejected as error:
                        if error.status == "BUSY":
                            return await self._wait_zeroing_over()
                        if error.status != "NOT_SETTLED" or time.monotonic() + ZERO_RETRY_S > give_up_s:
                            why = ZERO_REFUSALS.get(error.status, f"the board answered {error.status}")
                            raise ApiError("rejected", f"the board refused to zero its sensors: {error.status} "
                                           f"({why})") from error
                await self._wait_still(give_up_s)
        finally:
            self._zeroing = False
            self._zero_done.set()

    async def _wait_still(self, give_up_s: float) -> None:
        """Until the readings have been still for the board's settle time (or the next try is due anyway: the
        board is the judge), with the progress in the status's ``zero``."""
        asked_s = time.monotonic()
        while time.monotonic() < give_up_s:
            self.zero_state = {"state": "waiting", "text": "waiting for the chambers to be still before zeroing "
                               f"(still for {self.stillness.still_for_s:.1f} of {self.stillness.needed_s:g} s; "
                               f"moved {self.stillness.moved_pa:.0f} Pa)",
                               "still_for_s": self.stillness.still_for_s, "needed_s": self.stillness.needed_s}
            if self.stillness.still or time.monotonic() - asked_s >= ZERO_RETRY_S * 4:
                return
            await asyncio.sleep(ZERO_RETRY_S)

    async def _wait_zeroing_over(self) -> bool:
        for _ in range(40):
            await asyncio.sleep(0.05)
            if self.telemetry is not None and "ZEROING" not in self.telemetry.states:
                self.zero_state = {"state": "zeroed", "text": f"zeroed at {time.strftime('%H:%M:%S')}"}
                return False
        raise ApiError("rejected", "the board stayed busy zeroing its sensors for 2 s: try again")

    async def wait_for_zero(self) -> None:
        """Wait until a zero in progress is over (a target would cancel it)."""
        if self._zeroing:
            await asyncio.wait_for(self._zero_done.wait(), ZERO_SETTLE_LIMIT_S + 5.0)

    # --- control ----------------------------------------------------------------------------------------

    async def _control_loop(self) -> None:
        """Every control period: scene target, what the board holds, volume estimate, status, Rerun."""
        period_s = 1.0 / CONTROL_HZ
        while True:
            started = time.monotonic()
            try:
                self.control_tick()
            except Exception as error:  # one bad tick must not end control; it is shown to people and logged
                logger.exception("control tick failed")
                self.event("internal", f"control tick failed: {type(error).__name__}: {error}", "ERROR")
            await asyncio.sleep(max(0.0, period_s - (time.monotonic() - started)))

    def control_tick(self) -> None:
        """One control period: the recording's health, the scene's target, what the board holds, the table's build,
        an estimate when due, the status."""
        self.recorder.check()
        self.recorder.set_scene_time(self.scenes.scene_time_s())
        self._scene_tick()
        self._reconcile_tick()
        self._report_build_tick()
        self._estimate_tick()
        self._publish_status_tick()

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
            # the last estimate is of pressures no longer measured: status shows none rather than a stale one
            self.estimated_chamber_ml = self.estimated_volume_ml = None
            self.event("estimate", f"volume estimate failed ({type(error).__name__}: {error}): no estimate until "
                       "the next one succeeds", "WARN")
            return
        self._note_model_restarts()
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

    def _note_model_restarts(self) -> None:
        """An event when the model worker was replaced since the last look (it died: the OOM killer?)."""
        if self.model.restarts != self._model_restarts_seen:
            self._model_restarts_seen = self.model.restarts
            self.event("model", f"the model worker died and was replaced ({self.model.restarts} since the daemon "
                       "started): its model was rebuilt from the cache", "WARN")

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

    @property
    def target_applied(self) -> bool:
        """Whether the board holds the setpoints of the current target (acknowledged, and not lost since)."""
        return self.target is not None and self.applied_target == self.target and self.session.online

    # What the board holds. ``target`` is what the daemon aims at (a request's, or the scene's step); the board
    # holds it once it acknowledged the target's setpoints (``applied_target``). A lost link, a latched fault or a
    # board that reset drops them: the daemon then says why the target waits (``target_pending``) and applies it
    # again as soon as it can (``_reconcile_tick``), whatever came in between (a scene's next step included).

    def want(self, target: Target, source: str, step_index: int | None = None,
             ramp: tuple[Target, Target] | None = None) -> None:
        """Aim at ``target``: the control loop applies it as soon as the board can take it."""
        if target == self.target and source == self.target_source:
            return
        if self._pending_since_s is None:
            self._pending_since_s = self.clock()
        self.target, self.target_source = target, source
        self._target_step, self._target_ramp = step_index, ramp
        if self.inverse_result is not None and self.inverse_result.target != target:
            self.inverse_result = None

    def _board_dropped_setpoints(self, setpoints_pa: np.ndarray | None) -> None:
        """The board no longer holds the daemon's setpoints (a fault set them to 0, a new connection)."""
        self.applied_target = None
        self.setpoints_pa = setpoints_pa
        self.setpoint_watch.expect(setpoints_pa, self.clock())
        if self.target is not None and self._pending_since_s is None:
            self._pending_since_s = self.clock()

    def _why_not_now(self) -> str | None:
        """Why the board cannot take setpoints now, or None."""
        if not self.session.online:
            link = self.session.status()
            return f"the link is {link['state']}" + (f" ({link['last_error']})" if link.get("last_error") else "")
        if self.fault_flags:
            return (f"faults latched on the board ({', '.join(fault_names(self.fault_flags))}): clear them "
                    "(phantom clear-fault)")
        if self._zeroing:
            return "the sensors are being zeroed: " + str(self.zero_state.get("text", "waiting for the board"))
        return None

    def _reconcile_tick(self) -> None:
        """Make the board hold the current target: apply it when it is not applied and the board can take it, or
        say why it waits."""
        online = self.session.online
        if self._was_online and not online:
            self._board_dropped_setpoints(None)
        self._was_online = online
        target = self.target
        if target is None or self.control_state is ControlState.VENTED or self._applying:
            return
        if self.applied_target == target:
            return
        why = self._why_not_now()
        if why is not None:
            self._pending(target, why)
            return
        if self.clock() < self._retry_after_s or target == self._unreachable:
            return
        self._applying = True
        task = self.spawn(self._apply_quietly(target))
        task.add_done_callback(lambda _: setattr(self, "_applying", False))

    def _pending(self, target: Target, why: str) -> None:
        """The target waits: say why, once per reason."""
        if why != self.target_pending:
            self.event("target", f"target {target.describe()} not applied: {why}"
                       + ("" if why.startswith("unreachable") else "; it will be applied as soon as the board can "
                          "take it"), "WARN")
        self.target_pending = why

    async def _apply_quietly(self, target: Target) -> None:
        """Apply a target from the control loop; what goes wrong is said (events, ``target_pending``)."""
        try:
            await self.apply(target)
        except ApiError as error:
            if error.code == "unreachable":
                self._unreachable = target
                self._pending(target, f"unreachable: {error}")
            else:
                self._retry_after_s = self.clock() + RETRY_S
                self._pending(target, f"{error}")

    async def solve(self, target: Target, ramp: tuple[Target, Target] | None = None) -> InverseResult:
        """The inverse's answer for ``target`` (on its ramp, when it is a point of one); ApiError ``unreachable``."""
        try:
            if ramp is not None:
                return await self.model.pressures_on_ramp(ramp[0], ramp[1], target)
            return await self.model.pressures_for(target)
        except UnreachableTargetError as error:
            raise ApiError("unreachable", str(error)) from error

    async def apply(self, target: Target) -> None:
        """Solve ``target`` (unless its answer is known) and send its setpoints, if it is still the current
        target once the board is free; raises ApiError (``unreachable``, ``link_down``, ``rejected``)."""
        ramp = self._target_ramp if target == self.target else None
        answer = self.inverse_result if self.inverse_result is not None and self.inverse_result.target == target \
            else await self.solve(target, ramp)
        self.recorder.log_solver(self.now_s(), answer.qp_solve_time_s, answer.solve_time_s)
        async with self._setpoint_lock:
            if target != self.target or self.applied_target == target or self.control_state is ControlState.VENTED:
                return  # replaced (a new target, a vent) or applied meanwhile
            await self._send_setpoints(answer.pressures_pa)
            self.inverse_result = answer
            self._applied(target)

    def _applied(self, target: Target) -> None:
        """The board acknowledged ``target``'s setpoints."""
        waited = self.target_pending
        self.applied_target, self.target_pending, self._unreachable = target, None, None
        if self._target_step is not None:
            self.scenes.applied(self._target_step)
        if waited is not None and self._pending_since_s is not None:
            self.event("target", f"target {target.describe()} applied after {self.clock() - self._pending_since_s:.1f}"
                       f" s (it waited: {waited})")
        self._pending_since_s = None

    async def set_target(self, target: Target) -> dict[str, Any]:
        """A target from the API: solved first, so that an unreachable one changes nothing (a playing scene goes
        on); then sent, and only once the board has acknowledged it does it replace the scene. Returns the
        inverse's answer as JSON; raises ApiError (``unreachable``, ``link_down``, ``rejected``)."""
        if not self.session.online:
            raise ApiError("link_down", f"no board: the link is {self.session.state.value}; the target was not set")
        await self.wait_for_zero()
        answer = await self.solve(target)
        self.recorder.log_solver(self.now_s(), answer.qp_solve_time_s, answer.solve_time_s)
        async with self._setpoint_lock:
            await self._send_setpoints(answer.pressures_pa)
            changed = self.target != target
            self.scenes.stop("a set_target request")
            self.control_state = ControlState.HOLDING
            self.want(target, "api")
            self.inverse_result = answer
            self._applied(target)
        if changed:
            self.event("target", f"target {target.describe()} -> setpoints "
                       f"{', '.join(f'{p / PA_PER_KPA:.3f}' for p in answer.pressures_pa)} kPa "
                       f"(predicted {_predicted_volume_ml(answer):.2f} ml, "
                       f"inverse {answer.solve_time_s * 1e3:.1f} ms)")
        return answer.to_json()

    async def vent(self, why: str, level: str = "INFO") -> None:
        """VENT (acknowledged): every setpoint 0, the target and any scene dropped; ``why`` goes to the status's
        ``vented_why`` and the events. Raises ApiError ``link_down`` when the board cannot be told."""
        self.scenes.stop("vented")
        async with self._setpoint_lock:
            self.setpoint_watch.expect(None, self.clock())
            await self.board_command("VENT")
            self.control_state = ControlState.VENTED
            self.target, self.inverse_result, self.target_source = None, None, None
            self.applied_target, self.target_pending, self._pending_since_s = None, None, None
            self.setpoints_pa = np.zeros(len(self.chamber_names))
            self.setpoint_watch.expect(self.setpoints_pa, self.clock())
            self.vented_why = why
        self.event("vent", f"vented: {why}", level)

    async def clear_fault(self) -> dict[str, Any]:
        """CLEAR_FAULT, then the current target's setpoints again (the board set them to 0 when the fault
        latched): the target in force now, a scene's step that came while the fault was latched included."""
        before = fault_names(self.fault_flags)
        await self.board_command("CLEAR_FAULT")
        # acknowledged: the board cleared its latch (it refuses while a cause lasts); the answer waits for the board's
        # telemetry to say so too, so that the status read next is not the latched one (a client that set a target
        # at once saw the fault in a frame sent before the clear, and gave up)
        loop = asyncio.get_running_loop()
        deadline_s = loop.time() + CLEARED_IN_TELEMETRY_S
        while self.fault_flags and loop.time() < deadline_s:
            await asyncio.sleep(0.01)
        self.event("fault", f"faults cleared on request (were: {', '.join(before) or 'none'})")
        target = self.target
        restored = False
        if target is not None and self.control_state is not ControlState.VENTED:
            await self.apply(target)
            restored = self.applied_target == target
        return {"cleared": before, "setpoints_restored": restored,
                "target": target.to_json() if target is not None else None}

    async def board_command(self, name: str, fields: dict[str, Any] | None = None) -> str:
        """One acknowledged command to the board for an API request; link errors become API errors."""
        try:
            return str(await self.session.command(name, fields))
        except LinkDown as error:
            raise ApiError("link_down", str(error)) from error
        except CommandRejected as error:
            raise ApiError("rejected", str(error)) from error

    async def _send_setpoints(self, pressures_pa: np.ndarray) -> None:
        """SET_SETPOINTS (acknowledged), with the setpoint lock held; link errors become API errors."""
        setpoints = np.asarray([int(round(min(max(p, 0.0), 32767.0))) for p in pressures_pa], dtype=float)
        self.setpoint_watch.expect(None, self.clock())  # in flight: the board may show either
        try:
            await self.board_command("SET_SETPOINTS", {"setpoint_pa": [int(p) for p in setpoints]})
        except ApiError as error:
            # refused: nothing changed on the board; not delivered: it is unknown what the board holds
            self.setpoint_watch.expect(self.setpoints_pa if error.code == "rejected" else None, self.clock())
            raise
        self.setpoints_pa = setpoints
        self.setpoint_watch.expect(setpoints, self.clock())
        if self.control_state is ControlState.VENTED or self.control_state is ControlState.IDLE:
            self.control_state = ControlState.HOLDING

    def _mismatch(self, board_setpoints_pa: np.ndarray) -> None:
        """The board holds setpoints the daemon did not send: vent, and set the gains and limits again."""
        expected = self.setpoint_watch.expected_pa
        self.setpoint_watch.expect(None, self.clock())  # once: the vent sets what is expected next
        text = (f"the board holds setpoints {_kpa(board_setpoints_pa)} kPa that the daemon did not send (it sent "
                f"{_kpa(expected)} kPa): another program is driving the board (a process on its port?) or the "
                "board lost its state; the phantom is vented and the target dropped: find what drove it, then "
                "set a target again")
        self.event("board", text, "ERROR")
        self.spawn(self._vent_after_mismatch(text))

    async def _vent_after_mismatch(self, text: str) -> None:
        try:
            await self.vent(text, "ERROR")
        except ApiError as error:
            self.event("vent", f"could not vent after the board's setpoints changed: {error}", "ERROR")
        await self.send_board_settings("after the mismatch")

    # --- scenes -----------------------------------------------------------------------------------------

    def start_scene(self, prepared: PreparedRun) -> dict[str, Any]:
        """Start playing a checked scene (:func:`phantom.host.scene_runner.prepare_run`)."""
        started = self.scenes.begin(prepared)
        self.control_state = ControlState.SCENE
        return started

    def _scene_tick(self) -> None:
        """Move the scene's target along its timeline; hold the last one when it ends."""
        was_active = self.scenes.active
        target = self.scenes.tick()
        if was_active and not self.scenes.active and self.control_state is ControlState.SCENE:
            self.control_state = ControlState.HOLDING
        run = self.scenes.run
        if target is not None and run is not None and self.control_state is ControlState.SCENE:
            self.want(target, f"scene:{run.name}", self.scenes.step_index(), self.scenes.ramp())

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
            # the measured pressures averaged over the estimate's window (sensor noise averages out): what a client
            # compares with the setpoints to see them settled
            "pressures_mean_kpa": (np.mean([frame for _, frame in self.schedule.window], axis=0) / PA_PER_KPA).tolist()
            if fresh and self.schedule.window else None,
            "drive_levels": telemetry.drive_levels.tolist() if telemetry is not None else None,
            "chamber_states": telemetry.states if telemetry is not None else None,
            "estimated_volume_ml": self.estimated_volume_ml if fresh else None,
            "estimated_chamber_volumes_ml": self.estimated_chamber_ml if fresh else None,
            "rest_volume_ml": info.rest_volume_ml,
            "target_volume_ml": self.target_volume_ml(),
            "target": self.target.to_json() if self.target is not None else None,
            "target_source": self.target_source,
            "target_applied": self.target_applied,
            "target_pending": self.target_pending if self.target is not None and not self.target_applied else None,
            "solution": self.inverse_result.to_json() if self.inverse_result is not None else None,
            "faults": fault_names(self.fault_flags),
            "vented_why": self.vented_why if self.control_state is ControlState.VENTED else None,
            "board_settings": {**self.board_settings.to_json(), "source": self.board_settings_source,
                               "board_config_source": (link.get("board_info") or {}).get("config_source")},
            "zero": {**self.zero_state, "sources": (link.get("board_info") or {}).get("zero_source")},
            "scene": self.scenes.to_json(),
            "startup_s": info.timings_s,
            "fidelity": info.fidelity,
            "fidelity_pending": info.pending_fidelity,
            "model_build": self.table_build.to_json() if self.table_build is not None else None,
            "ready": self.ready,
            "starting": None if self.ready else {**self.startup.to_json(), "text": self.startup.text()},
            "pid": os.getpid(),
            "model_counts": self.model_counts,
            "model_worker_restarts": self.model.restarts,
            "meshes_logged": self.meshes_logged,
            "api": self.api.stats(),
            "event_loop": self.loop_stalls.to_json(),
            "recording": self.recorder.status(),
            "uptime_s": self.now_s(),
            "events": list(self.events)[-10:],
            "motion": self.motion.status(),
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


def _kpa(pressures_pa: np.ndarray | None) -> str:
    """Pressures (Pa) as people read them: ``1.000, 0.500, 0.000`` (kPa)."""
    return "none" if pressures_pa is None else ", ".join(f"{p / PA_PER_KPA:.3f}" for p in pressures_pa)


def _predicted_volume_ml(answer: InverseResult) -> float:
    """The gland volume (ml) the inverse predicts for its pressures."""
    return float(answer.predicted_gland_volume_m3) * ML_PER_M3


def _log_loop_exception(loop: asyncio.AbstractEventLoop, context: dict[str, Any]) -> None:
    """Errors the event loop catches (a background task's exception nobody awaited) go to the log with their
    traceback."""
    logger.error("unexpected error: %s", context.get("message", "in the event loop"), exc_info=context.get("exception"))


def _link_session(config: DaemonConfig, sim_board: SimulatedBoardKeeper | None,
                  on_telemetry: Callable[[Telemetry], None], on_event: Callable[[str, str, str], None],
                  on_online: Callable[[BoardInfo, bool], Awaitable[None]],
                  on_motion: Callable[[Message], None]) -> LinkThread:
    """The link session over the configured transport, in a thread of its own."""
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
    return LinkThread(LinkSession(transport, timing, on_telemetry=on_telemetry, on_event=on_event,
                                  on_online=on_online, on_motion=on_motion), LoopStalls())


async def _run(config: DaemonConfig, simulated_board: SimulatedBoardFactory | None,
               scanner: Scanner | None = None) -> int:
    # SIGTERM or SIGINT while the parts are built (a first start builds the response table for minutes) cancels
    # the build: the parts built so far are closed and the model worker is ended with the processes it started,
    # which the default action (the process killed at once) left running
    loop = asyncio.get_running_loop()
    starting = asyncio.current_task()
    assert starting is not None
    for signum in (signal.SIGTERM, signal.SIGINT):
        loop.add_signal_handler(signum, starting.cancel)
    try:
        daemon = await Daemon.start(config, simulated_board)
    except asyncio.CancelledError:
        logger.info("stopped while starting")
        return 0
    if scanner is not None:
        daemon.api.handlers.update(scan_method(daemon.motion, scanner, daemon.status))
    return await daemon.serve()


def run_daemon(config: DaemonConfig, simulated_board: SimulatedBoardFactory | None = None,
               scanner: Scanner | None = None) -> int:
    """Run the daemon in this process until SIGTERM/SIGINT; returns the exit status. ``simulated_board`` builds
    the board of ``config.sim``; ``scanner`` takes the ``scan`` API method's captures (host/motion.py)."""
    return asyncio.run(_run(config, simulated_board, scanner))
