"""The host daemon: one asyncio process that owns the board link, the control state, scenes, Rerun and the API.

Tasks (all in one event loop; model work runs in a worker process so it never stalls the link):

    link      LinkSession.run: connect, handshake, keepalive, telemetry in, reconnect
    control   every control period: the scene timeline's target, volume estimation from measured pressures,
              scene step bookkeeping, status to subscribers, link statistics and mesh to Rerun
    api       the Unix-socket JSON-lines server

Control state (``ControlState``): ``idle`` (no target), ``holding`` (a target from the API), ``scene`` (a
scene's timeline drives the target), ``vented`` (blowers off on request). A latched firmware fault is shown
in ``faults`` whatever the state, and only ``clear_fault`` clears it; the daemon then restores the
setpoints of the current target.
"""

from __future__ import annotations

import asyncio
import contextlib
import enum
import signal
import sys
import time
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from phantom import PhantomError
from phantom.host.api import ApiError, ApiServer, default_socket_path
from phantom.host.scenes import SceneError, Timeline, parse_target, parse_timeline
from phantom.model.scene import read_scene_toml

PA_PER_KPA = 1e3
#: Estimated volumes average the measured pressures over this window (s of board time): sensor noise and
#: ADC quantisation average out while a settled chamber does not move.
ESTIMATE_WINDOW_S = 0.5
#: A new estimate is computed when the mean pressures moved by this much (Pa, a tenth of an ADC count; about
#: 0.05 % of the volume change) or once a second: a held target costs almost nothing with a full-solve fidelity.
ESTIMATE_CHANGE_PA = 5.0
#: A step counts as reached when the estimated volume is within this fraction of its target volume.
REACHED_TOLERANCE = 0.01


class ControlState(enum.StrEnum):
    IDLE = "idle"
    HOLDING = "holding"
    SCENE = "scene"
    VENTED = "vented"


@dataclass
class DaemonConfig:
    """Everything ``phantom daemon`` is told (CLI flags, or the config file of the systemd service)."""

    port: str | None = None
    sim: bool = False
    sim_speed: float = 1.0
    can_channel: str | None = None
    can_interface: str = "socketcan"
    baudrate: int = 115200
    scene: str = "builtin:calibrated"
    socket: Path = field(default_factory=default_socket_path)
    socket_mode: int = 0o660
    rerun_save: Path | None = None
    rerun_connect: str | None = None
    mesh_hz: float = 1.0
    control_hz: float = 10.0
    host_deadline_ms: int = 500
    telemetry_period_ms: int = 20
    vent_on_exit: bool = True
    run_scene: bool = False


@dataclass
class StepRecord:
    """How one scene step went: when it started, its target volume, when the estimate reached it."""

    index: int
    at_s: float
    target: str
    target_volume_ml: float | None
    started_wall_s: float
    reached_after_s: float | None = None
    final_volume_ml: float | None = None

    def to_json(self) -> dict:
        error_pct = None
        if self.target_volume_ml and self.final_volume_ml is not None:
            error_pct = 100.0 * (self.final_volume_ml - self.target_volume_ml) / self.target_volume_ml
        return {"index": self.index, "at_s": self.at_s, "target": self.target,
                "target_volume_ml": self.target_volume_ml, "reached_volume_ml": self.final_volume_ml,
                "error_pct": error_pct, "reached_after_s": self.reached_after_s}


@dataclass
class SceneRun:
    """A scene timeline being played: its clock and the record of its steps."""

    name: str
    timeline: Timeline
    end_s: float
    time_scale: float
    started_wall_s: float
    steps: list[StepRecord] = field(default_factory=list)
    finished: bool = False

    def scene_time_s(self, now_s: float) -> float:
        return (now_s - self.started_wall_s) * self.time_scale

    def to_json(self, now_s: float) -> dict:
        return {"name": self.name, "time_s": min(self.scene_time_s(now_s), self.end_s), "end_s": self.end_s,
                "time_scale": self.time_scale, "finished": self.finished,
                "steps": [step.to_json() for step in self.steps]}


class Daemon:
    """The daemon process's state and tasks; :meth:`run` until SIGTERM/SIGINT or :meth:`request_stop`."""

    def __init__(self, config: DaemonConfig, report=None):
        self.config = config
        self.report = report or (lambda text: print(f"phantom daemon: {text}", file=sys.stderr, flush=True))
        self.started_s = time.monotonic()
        self.control_state = ControlState.IDLE
        self.target = None
        self.target_source: str | None = None
        self.solution = None
        self.setpoints_pa: np.ndarray | None = None
        self.telemetry = None
        self.pressure_window: deque = deque()
        self.estimated_chamber_ml: list[float] | None = None
        self.estimated_volume_ml: float | None = None
        self.scene_run: SceneRun | None = None
        self.events: deque = deque(maxlen=100)
        self.fault_flags = 0
        self.controller = None
        self.session = None
        self.recorder = None
        self.api: ApiServer | None = None
        self.board_sim = None
        self._stop = asyncio.Event()
        self._estimating = False
        self.model_counts: dict = {}
        self._estimated_pa: np.ndarray | None = None
        self._estimated_s = 0.0
        self._mesh_due_s = 0.0
        self._link_log_due_s = 0.0
        self._setpoint_lock = asyncio.Lock()
        self._scene_solving = False
        self._tasks: list[asyncio.Task] = []
        self._background: set[asyncio.Task] = set()

    # --- life cycle -------------------------------------------------------------------------------------

    def now_s(self) -> float:
        """Seconds since the daemon started (the recording's time line)."""
        return time.monotonic() - self.started_s

    async def run(self) -> int:
        """Start everything, serve until asked to stop, then vent and close cleanly; returns the exit code."""
        from phantom.host.control import ModelWorker
        from phantom.host.recording import Recorder
        from phantom.host.session import LinkSession, LinkTiming

        loop = asyncio.get_running_loop()
        for signum in (signal.SIGTERM, signal.SIGINT):
            loop.add_signal_handler(signum, self.request_stop)
        chosen = [bool(self.config.port), self.config.sim, bool(self.config.can_channel)]
        if sum(chosen) != 1:
            raise PhantomError("give exactly one board: --port DEV, --sim, or --can-channel CH")
        try:
            self.controller = ModelWorker(self.config.scene)
            await self.controller.start()
            names = self.controller.chamber_names
            self.recorder = Recorder(names, self.config.rerun_save, self.config.rerun_connect)
            self._event("startup", "model ready: " + ", ".join(f"{key} {value:.2f} s"
                                                               for key, value in self.controller.timings_s.items()))
            transport = await self._make_transport()
            # a simulated board faster than real time passes its dead-host deadline sooner (speed 0: as fast as
            # it can, about 5x here)
            speed = (self.config.sim_speed or 10.0) if self.config.sim else 1.0
            # a HELLO that opened a session on the board but whose reply was lost must be repeated before the
            # board's dead-host deadline passes: HELLOs go out at twice the keepalive period
            timing = LinkTiming(keepalive_s=min(0.1, 0.1 / speed), hello_timeout_s=min(0.2, 0.2 / speed),
                                telemetry_period_ms=self.config.telemetry_period_ms,
                                host_deadline_ms=self.config.host_deadline_ms)
            self.session = LinkSession(transport, timing, on_telemetry=self._on_telemetry,
                                       on_event=self._event, on_online=self._on_online)
            self.api = ApiServer(self.config.socket, self._handlers(), mode=self.config.socket_mode)
            await self.api.start()
            self._tasks = [asyncio.create_task(self.session.run(), name="link"),
                           asyncio.create_task(self._control_loop(), name="control")]
            self.report(f"ready: API on {self.config.socket}, board on {transport.description}")
            if self.config.run_scene:
                self._start_scene(self.controller.scene_raw, self.controller.scene_path, 1.0)
            await self._stop.wait()
        finally:
            await self._shutdown()
        return 0

    def _spawn(self, coroutine) -> asyncio.Task:
        """A background task, referenced until it ends (the event loop keeps only weak references)."""
        task = asyncio.create_task(coroutine)
        self._background.add(task)
        task.add_done_callback(self._background.discard)
        return task

    def request_stop(self) -> None:
        """Ask :meth:`run` to shut down (SIGTERM and SIGINT do this)."""
        self._stop.set()

    async def _make_transport(self):
        """The board's transport from the configuration: a serial port, the simulated board, or CAN."""
        from phantom.host.transports import CanTransport, SerialTransport

        if self.config.can_channel:
            return CanTransport(self.config.can_channel, self.config.can_interface)
        if self.config.sim:
            from phantom.hil.sim import SimulatedBoard

            self.report(f"starting the simulated board (firmware in simavr, speed {self.config.sim_speed:g}) ...")
            self.board_sim = SimulatedBoard(speed=self.config.sim_speed)
            await asyncio.get_running_loop().run_in_executor(None, self.board_sim.start)
            return SerialTransport(self.board_sim.port, self.config.baudrate)
        return SerialTransport(self.config.port, self.config.baudrate)

    async def _shutdown(self) -> None:
        """Vent the phantom (if the board is there), close the recording, the API and the link."""
        self.report("stopping: venting and closing")
        if self.config.vent_on_exit and self.session is not None and self.session.online:
            try:
                await asyncio.wait_for(self.session.command("VENT"), 2.0)
                self._event("vent", "vented on shutdown")
            except (TimeoutError, PhantomError) as error:
                self._event("vent", f"could not vent on shutdown: {error}", "ERROR")
        if self.session is not None:
            self.session.stop()
        for task in [*self._tasks, *self._background]:
            task.cancel()
        for task in [*self._tasks, *self._background]:
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await task
        if self.session is not None:
            self.session.transport.close()
        if self.api is not None and self.api._server is not None:
            await self.api.close()
        if self.recorder is not None:
            self.recorder.log_event(self.now_s(), "daemon stopped")
            self.recorder.close()
        if self.board_sim is not None:
            await asyncio.get_running_loop().run_in_executor(None, self.board_sim.stop)
        if self.controller is not None:
            self.controller.close()

    # --- events and telemetry ---------------------------------------------------------------------------

    def _event(self, kind: str, text: str, level: str = "INFO") -> None:
        """Record an event: the status's recent events, Rerun's text log, subscribers, stderr."""
        entry = {"time_s": round(self.now_s(), 3), "kind": kind, "level": level, "text": text}
        self.events.append(entry)
        if self.recorder is not None:
            self.recorder.log_event(self.now_s(), text, level)
        if self.api is not None:
            self.api.publish("events", entry)
        self.report(f"[{level}] {text}")

    def _on_telemetry(self, telemetry) -> None:
        """Keep the latest frame and the estimation window; log and publish it."""
        self.telemetry = telemetry
        board_time_s = telemetry.board_time_ms / 1e3
        self.pressure_window.append((board_time_s, telemetry.pressures_pa))
        while self.pressure_window and (board_time_s - self.pressure_window[0][0] > ESTIMATE_WINDOW_S
                                        or board_time_s < self.pressure_window[0][0]):
            self.pressure_window.popleft()
        if telemetry.fault_flags != self.fault_flags:
            from phantom.host.session import fault_names

            if telemetry.fault_flags and not self.fault_flags:
                self._event("fault", f"faults latched: {', '.join(fault_names(telemetry.fault_flags))}", "ERROR")
            elif not telemetry.fault_flags:
                self._event("fault", "faults cleared")
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

    async def _on_online(self, board, reconnected: bool) -> None:
        """The link came up: restore the current setpoints (a board that reset starts with none)."""
        self.pressure_window.clear()
        if board.chamber_count != len(self.controller.chamber_names):
            self._event("link", f"the board has {board.chamber_count} chambers, the scene "
                        f"{len(self.controller.chamber_names)}: setpoints not sent", "ERROR")
            return
        if self.setpoints_pa is not None and self.control_state is not ControlState.VENTED:
            self._spawn(self._send_setpoints_quietly(self.setpoints_pa, "restored after (re)connection"))

    # --- control ----------------------------------------------------------------------------------------

    async def _control_loop(self) -> None:
        """Every control period: scene target, volume estimate, step bookkeeping, status, Rerun."""
        period_s = 1.0 / self.config.control_hz
        while True:
            started = time.monotonic()
            try:
                self._scene_tick()
                self._estimate_tick()
                self._publish_status_tick()
            except Exception as error:  # one bad tick must not end control; it is shown to people
                self._event("internal", f"control tick failed: {type(error).__name__}: {error}", "ERROR")
            await asyncio.sleep(max(0.0, period_s - (time.monotonic() - started)))

    def _estimate_tick(self) -> None:
        """Start a volume estimate from the window's mean pressure (one at a time, in the model's process)."""
        if self._estimating or not self.pressure_window:
            return
        mean_pa = np.mean([pressures for _, pressures in self.pressure_window], axis=0)
        now_s = self.now_s()
        want_mesh = self.recorder.wants_mesh and self.config.mesh_hz > 0 and now_s >= self._mesh_due_s
        unchanged = self._estimated_pa is not None and np.max(np.abs(mean_pa - self._estimated_pa)) < (
            ESTIMATE_CHANGE_PA)
        if unchanged and not want_mesh and now_s - self._estimated_s < 1.0:
            return
        self._estimated_pa, self._estimated_s = mean_pa, now_s
        if want_mesh:
            self._mesh_due_s = now_s + 1.0 / self.config.mesh_hz
        self._estimating = True
        task = self._spawn(self.controller.estimate(mean_pa, want_mesh))
        task.add_done_callback(lambda done: self._estimate_done(done, now_s))

    def _estimate_done(self, future, time_s: float) -> None:
        self._estimating = False
        if future.cancelled():
            return
        try:
            chamber_ml, gland_ml, surface, self.model_counts = future.result()
        except Exception as error:  # shown, not fatal: the next tick tries again
            self._event("estimate", f"volume estimate failed: {error}", "WARN")
            return
        self.estimated_chamber_ml, self.estimated_volume_ml = chamber_ml, gland_ml
        self.recorder.log_volumes(time_s, self.target_volume_ml(), gland_ml, chamber_ml)
        if surface is not None:
            self.recorder.log_mesh(time_s, *surface)
        self._step_bookkeeping()

    def target_volume_ml(self) -> float | None:
        """The gland volume aimed at (ml): the target's for a volume target, else the inverse's prediction."""
        if self.target is None or self.control_state is ControlState.VENTED:
            return None
        if self.target.kind == "volume_ml":
            return float(self.target.values[0])
        return self.solution.predicted_volume_ml if self.solution is not None else None

    async def apply_target(self, target, source: str) -> dict:
        """Solve the inverse for ``target`` and send the setpoints; returns the solution as JSON.

        Raises ApiError ``unreachable`` (with the reachable range), ``link_down`` or ``rejected``.
        """
        from phantom.model.inverse import UnreachableTargetError

        try:
            solution = await self.controller.solve(target)
        except UnreachableTargetError as error:
            raise ApiError("unreachable", str(error)) from error
        self.recorder.log_solver(self.now_s(), solution.qp_time_s, solution.solve_time_s)
        if source != "api" and self.control_state is not ControlState.SCENE:
            # the scene was stopped (vent, a new target) while this solve ran: its answer is stale
            return solution.to_json()
        await self._send_setpoints(solution.pressures_pa)
        changed = self.target != target
        self.target, self.target_source, self.solution = target, source, solution
        if changed and source == "api":
            self._event("target", f"target {target.describe()} -> setpoints "
                        f"{', '.join(f'{p / PA_PER_KPA:.3f}' for p in solution.pressures_pa)} kPa "
                        f"(predicted {solution.predicted_volume_ml:.2f} ml, "
                        f"solve {solution.solve_time_s * 1e3:.1f} ms)")
        return solution.to_json()

    async def _board_command(self, name: str, fields: dict | None = None) -> str:
        """One acknowledged command to the board for an API request; link errors become API errors."""
        from phantom.host.session import CommandRejected, LinkDown

        try:
            return await self.session.command(name, fields)
        except LinkDown as error:
            raise ApiError("link_down", str(error)) from error
        except CommandRejected as error:
            raise ApiError("rejected", str(error)) from error

    async def _send_setpoints(self, pressures_pa: np.ndarray) -> str:
        """SET_SETPOINTS (acknowledged); translates link errors into API errors."""
        setpoints = [int(round(min(max(p, 0.0), 32767.0))) for p in pressures_pa]
        async with self._setpoint_lock:
            status = await self._board_command("SET_SETPOINTS", {"setpoint_pa": setpoints})
        self.setpoints_pa = np.asarray(setpoints, dtype=float)
        if self.control_state is ControlState.VENTED or self.control_state is ControlState.IDLE:
            self.control_state = ControlState.HOLDING
        if status == "CLAMPED":
            self._event("setpoints", "the board clamped a setpoint to its pressure limit", "WARN")
        return status

    async def _send_setpoints_quietly(self, pressures_pa: np.ndarray, why: str) -> None:
        """Send setpoints from a background path (reconnection, scene); failures become events, once."""
        try:
            await self._send_setpoints(pressures_pa)
            self._event("setpoints", f"setpoints {why}")
        except ApiError as error:
            self._event("setpoints", f"setpoints not sent ({why}): {error}", "WARN")

    # --- scenes -----------------------------------------------------------------------------------------

    def _start_scene(self, raw: dict, name: str, time_scale: float) -> dict:
        """Check a scene's timeline against the loaded phantom and start playing it."""
        timeline = parse_timeline(raw.get("steps"), self.controller.chamber_names, name)
        if not timeline.steps:
            raise SceneError(f"{name} has no [[steps]]: nothing to run")
        settings = raw.get("timeline", {})
        end_s = settings.get("end_s", timeline.duration_s + 10.0) if isinstance(settings, dict) else None
        if not isinstance(end_s, (int, float)) or end_s < timeline.duration_s:
            raise SceneError(f"{name}: [timeline] end_s must be a number >= {timeline.duration_s:g} s "
                             "(the end of the last step's ramp)")
        if not np.isfinite(time_scale) or time_scale <= 0:
            raise SceneError(f"time_scale must be a positive number, got {time_scale!r}")
        self.scene_run = SceneRun(name, timeline, float(end_s), float(time_scale), time.monotonic())
        self.control_state = ControlState.SCENE
        self._event("scene", f"scene {name} started: {len(timeline.steps)} steps over {end_s:g} s "
                    f"(time scale {time_scale:g})")
        return {"name": name, "steps": len(timeline.steps), "end_s": float(end_s), "time_scale": time_scale,
                "wall_duration_s": float(end_s) / time_scale}

    def _scene_tick(self) -> None:
        """Move the scene's target along its timeline; finish the scene at its end."""
        run = self.scene_run
        if run is None or run.finished:
            return
        now_wall = time.monotonic()
        scene_time_s = run.scene_time_s(now_wall)
        index = run.timeline.step_index_at(scene_time_s)
        if index is not None and len(run.steps) <= index:
            for new_index in range(len(run.steps), index + 1):
                step = run.timeline.steps[new_index]
                run.steps.append(StepRecord(new_index, step.at_s, step.target.describe(),
                                            self._step_target_volume(step.target), now_wall))
                self._event("scene", f"step {new_index} at {step.at_s:g} s: {step.target.describe()}"
                            + (f" over {step.ramp_s:g} s" if step.ramp_s else ""))
        if scene_time_s >= run.end_s:
            run.finished = True
            self.control_state = ControlState.HOLDING
            self._step_bookkeeping(final=True)
            self._event("scene", f"scene {run.name} finished; holding its last target")
            return
        target = run.timeline.target_at(scene_time_s)
        if target is not None and target != self.target and not self._scene_solving:
            self._scene_solving = True
            task = self._spawn(self._apply_scene_target(target, run.name))
            task.add_done_callback(lambda _: setattr(self, "_scene_solving", False))

    def _step_target_volume(self, target) -> float | None:
        return float(target.values[0]) if target.kind == "volume_ml" else None

    async def _apply_scene_target(self, target, name: str) -> None:
        try:
            await self.apply_target(target, f"scene:{name}")
        except ApiError as error:
            if self.target != target:
                self._event("scene", f"scene target {target.describe()} not applied: {error}", "WARN")
                self.target = target

    def _step_bookkeeping(self, final: bool = False) -> None:
        """For the current scene step: its latest estimated volume, and when it first came within 1 % of the
        step's target volume after the ramp (the last estimate before the next step is the volume reached)."""
        run = self.scene_run
        if run is None or not run.steps or self.estimated_volume_ml is None:
            return
        if run.finished and not final:
            return
        record = run.steps[-1]
        record.final_volume_ml = self.estimated_volume_ml
        goal_ml = record.target_volume_ml
        if goal_ml is None and self.solution is not None and self.target is not None and self.solution.target == \
                run.timeline.steps[record.index].target:
            goal_ml = record.target_volume_ml = self.solution.predicted_volume_ml
        if goal_ml is None:
            return
        ramp_end_wall = record.started_wall_s + run.timeline.steps[record.index].ramp_s / run.time_scale
        within = abs(self.estimated_volume_ml - goal_ml) <= REACHED_TOLERANCE * goal_ml
        if within and record.reached_after_s is None and time.monotonic() >= ramp_end_wall:
            record.reached_after_s = time.monotonic() - record.started_wall_s

    # --- status -----------------------------------------------------------------------------------------

    def status(self) -> dict:
        """Everything ``phantom status --json`` shows."""
        from phantom.host.session import fault_names

        telemetry = self.telemetry
        fresh = telemetry is not None and self.session.online
        link = self.session.status()
        return {
            "link": link["state"],
            "link_detail": link,
            "control": self.control_state.value,
            "chambers": self.controller.chamber_names,
            "pressures_kpa": (telemetry.pressures_pa / PA_PER_KPA).tolist() if fresh else None,
            "setpoints_kpa": (self.setpoints_pa / PA_PER_KPA).tolist() if self.setpoints_pa is not None else None,
            "board_setpoints_kpa": (telemetry.setpoints_pa / PA_PER_KPA).tolist() if fresh else None,
            "drive_levels": telemetry.drive_levels.tolist() if fresh else None,
            "chamber_states": telemetry.states if fresh else None,
            "estimated_volume_ml": self.estimated_volume_ml if fresh else None,
            "estimated_chamber_volumes_ml": self.estimated_chamber_ml if fresh else None,
            "rest_volume_ml": self.controller.rest_volume_ml,
            "target_volume_ml": self.target_volume_ml(),
            "target": self.target.to_json() if self.target is not None else None,
            "target_source": self.target_source,
            "solution": self.solution.to_json() if self.solution is not None else None,
            "faults": fault_names(self.fault_flags),
            "scene": self.scene_run.to_json(time.monotonic()) if self.scene_run is not None else None,
            "startup_s": self.controller.timings_s,
            "fidelity": self.controller.fidelity,
            "model_counts": self.model_counts,
            "api": self.api.stats(),
            "recording": str(self.config.rerun_save) if self.config.rerun_save else self.config.rerun_connect,
            "uptime_s": self.now_s(),
            "events": list(self.events)[-10:],
        }

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

    # --- API handlers -----------------------------------------------------------------------------------

    def _handlers(self) -> dict:
        return {"status": self._api_status, "set_target": self._api_set_target, "vent": self._api_vent,
                "clear_fault": self._api_clear_fault, "run_scene": self._api_run_scene}

    async def _api_status(self, params: dict) -> dict:
        return self.status()

    async def _api_set_target(self, params: dict) -> dict:
        try:
            target = parse_target(params, self.controller.chamber_names, "set_target")
        except SceneError as error:
            raise ApiError("invalid_params", str(error)) from error
        if not self.session.online:
            raise ApiError("link_down", f"no board: the link is {self.session.state.value}; the target was not set")
        if self.scene_run is not None and not self.scene_run.finished:
            self.scene_run.finished = True
            self._event("scene", f"scene {self.scene_run.name} stopped by a set_target request")
        result = await self.apply_target(target, "api")
        self.control_state = ControlState.HOLDING
        return result

    async def _api_vent(self, params: dict) -> dict:
        if self.scene_run is not None and not self.scene_run.finished:
            self.scene_run.finished = True
        await self._board_command("VENT")
        self.control_state = ControlState.VENTED
        self.setpoints_pa = np.zeros(len(self.controller.chamber_names))
        self.target, self.solution, self.target_source = None, None, None
        self._event("vent", "vented on request: every setpoint is 0")
        return {"vented": True}

    async def _api_clear_fault(self, params: dict) -> dict:
        from phantom.host.session import fault_names

        before = fault_names(self.fault_flags)
        await self._board_command("CLEAR_FAULT")
        self._event("fault", f"faults cleared on request (were: {', '.join(before) or 'none'})")
        restored = False
        if self.setpoints_pa is not None and self.control_state is not ControlState.VENTED and np.any(
                self.setpoints_pa > 0):
            await self._send_setpoints(self.setpoints_pa)
            restored = True
        return {"cleared": before, "setpoints_restored": restored}

    async def _api_run_scene(self, params: dict) -> dict:
        path = params.get("path")
        time_scale = params.get("time_scale", 1.0)
        if not isinstance(path, str) or not path:
            raise ApiError("invalid_params", "run_scene needs params.path: the scene TOML file (absolute path)")
        if isinstance(time_scale, bool) or not isinstance(time_scale, (int, float)):
            raise ApiError("invalid_params", f"time_scale must be a number, got {time_scale!r}")
        try:
            raw = read_scene_toml(path)
            # the timeline runs on the loaded model: a scene for another phantom, material or model setting needs
            # its own model, so the daemon must be restarted with it
            differing = [table for table in ("phantom", "material", "model")
                         if raw.get(table) != self.controller.scene_raw.get(table)]
            if differing:
                raise SceneError(f"{path} describes another phantom than the running one (its "
                                 f"[{'], ['.join(differing)}] differ from {self.controller.scene_path}): restart "
                                 f"the daemon with --scene {path}")
            return self._start_scene(raw, str(path), float(time_scale))
        except SceneError as error:
            raise ApiError("invalid_params", str(error)) from error


def run_daemon(config: DaemonConfig) -> int:
    """Run the daemon in this process until SIGTERM/SIGINT; returns the exit status."""
    return asyncio.run(Daemon(config).run())
