"""The daemon's side of the scanner's orbit: configure, move, home, stop and report its two stepper axes (0 the
orbit, 1 the elevation) through the board, fed by the board's MOTION_STATUS and MOTION_INFO frames.

The board moves one axis at a time, so a move of both goes the elevation first, then the orbit; each ends when
the first MOTION_STATUS received after the command's ACK shows the axis at rest (PROTOCOL.md, section 12): its
result must be REACHED (HOMED for a homing), else the request fails with what happened. The board does not keep
an axis's configuration across a reset: the daemon sends the last one again when the link comes back (the
position is then the board's power-up zero: home the axis before scanning).

API methods (host/README.md): ``motion_config``, ``motion_move``, ``motion_home``, ``motion_stop``,
``motion_status``. On the simulated board, ``motion_status`` also reports the simulation's truth (``simulated``:
the rig's true angles from the pulses its drivers took, the plant's pressures), for the virtual camera.

``scan`` (only when the command line gives the daemon a :class:`Scanner`, as ``phantom daemon`` does): a whole
capture at the pressures the daemon holds, run in a worker thread that drives the axes and reads the daemon's
state through the daemon's loop (:class:`ThreadRig`); the host imports nothing of the scanner's code.

While a scan runs it owns the rig (:attr:`Orbit.scan`): another client's ``motion_move``, ``motion_home`` and
``motion_config`` are refused with why, not queued (a queued move would turn the rig minutes later, when its
client may no longer expect it, and the client is better told now); ``motion_status`` answers as ever.
``motion_stop`` (and the daemon stopping) stops the scan: the capture sees the request before each move, during
its settle wait and after each picture, releases the drivers (whatever ``release`` says) and marks its folder
``stopped``; a move under way
is interrupted by the board's MOTION_STOP. ``motion_stop`` answers once the scan has ended, so the next scan can
start at once.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import contextlib
import datetime
import threading
from collections.abc import Awaitable, Callable
from dataclasses import asdict, fields
from typing import Any, Protocol, TypeVar

from phantom import PhantomError, is_finite_number
from phantom.host.api import ApiError, Handler
from phantom.host.session import CommandRejected
from phantom.host.sim_board import SimulatedBoardKeeper
from phantom.protocol.codec import Message
from phantom.protocol.motion import (
    ANGLE_LIMIT_DEG,
    AXES,
    ELEVATION,
    ORBIT,
    REFUSALS,
    AxisConfig,
    MotionError,
    MotionStatus,
)

#: Names of the axes in the API.
AXIS_NAMES = {ORBIT: "orbit", ELEVATION: "elevation"}
#: The slack (s) a move gets beyond its ideal duration before the daemon gives up on it.
MOVE_SLACK_S = 5.0
#: How long a configuration may take to be reported (MOTION_INFO).
INFO_WAIT_S = 2.0
#: How many times a configuration, and a move, is asked for when the board's reply is late (a frame lost or
#: delayed on the link: a configuration's MOTION_INFO is sent once).
REPLY_TRIES = 3
#: A wait ends after its time on the board's clock, or this many times it on the wall clock (a stalled simulator).
WALL_FACTOR = 10.0
#: How long a stop waits for a running scan to end (s): its capture sees the request within a picture's time.
SCAN_END_WAIT_S = 10.0

#: Sends one acknowledged command to the board: ``(name, fields) -> ACK status``; raises ApiError
#: (``link_down``, ``rejected``) as :meth:`phantom.host.daemon.Daemon.board_command` does.
BoardCommand = Callable[[str, dict[str, Any]], Awaitable[str]]
#: The simulated board's truth now (its rig's angles and its plant), None on a real board.
SimulatedTruth = Callable[[], Awaitable[dict[str, Any] | None]]
#: Where events go: ``(kind, text, level)``.
EventSink = Callable[[str, str, str], None]
#: The daemon's status (``Daemon.status``), called on the daemon's loop.
DaemonState = Callable[[], dict[str, Any]]

Result = TypeVar("Result")


#: A verified round's scan that failed for a late reply is taken this many times in all.
SCAN_TRIES = 2


class LateReply(ApiError):
    """The board's reply to a motion command did not come in time (the command may be asked again)."""

    def __init__(self, message: str):
        super().__init__("rejected", message)


class ScanRun:
    """A scan that owns the rig: when it started, how far it is (the orbit stops moved to, of how many: None
    when its request left the plan to the scanner), and the stop request its capture thread checks."""

    def __init__(self, stops: int | None = None) -> None:
        self.started_utc = datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds")
        self.ended = asyncio.Event()
        self.stops = stops
        #: the stops the capture has moved to (one picture each), counted by its thread (the one writer)
        self.stops_reached = 0
        self._stop = threading.Event()
        self._reason = ""

    def to_json(self) -> dict[str, Any]:
        """The scan for the status, with ``text``: how far it is in words (phantom status and the panel show it)."""
        of = "" if self.stops is None else f" of {self.stops}"
        return {"started_utc": self.started_utc, "stops_reached": self.stops_reached, "stops": self.stops,
                "text": f"picture {self.stops_reached}{of}"}

    def request_stop(self, reason: str) -> None:
        """Ask the capture to stop (from the daemon's loop); the first reason is kept."""
        if not self._stop.is_set():
            self._reason = reason
            self._stop.set()

    def stop_requested(self, wait_s: float = 0.0) -> str | None:
        """Why the capture must stop, or None; waits up to ``wait_s`` for a request (from the capture's thread)."""
        return self._reason if self._stop.wait(wait_s) else None


class Orbit:
    """The scanner's axes as the daemon drives them (see the module docstring)."""

    def __init__(self, command: BoardCommand, event: EventSink, simulated: SimulatedTruth | None = None):
        self._command = command
        self._event = event
        self._simulated = simulated
        self.configs: dict[int, AxisConfig] = {}
        self.reported: dict[int, AxisConfig] = {}
        self.latest: MotionStatus | None = None
        self._statuses = 0
        self._changed = asyncio.Condition()
        self._lock = asyncio.Lock()
        #: the scan that owns the rig, None when none runs
        self.scan: ScanRun | None = None
        #: how many waits for the board's reply ran out (a scan that failed meanwhile is worth taking again)
        self.late_replies = 0

    # --- frames from the board ------------------------------------------------------------------------------

    def on_message(self, message: Message) -> None:
        """A MOTION_STATUS or MOTION_INFO frame (the link session passes them)."""
        if message.name == "MOTION_STATUS":
            self.latest = MotionStatus.from_message(message)
            self._statuses += 1
        elif message.name == "MOTION_INFO":
            self.reported[int(message.fields["axis"])] = AxisConfig.from_fields(message.fields)
        else:
            return
        asyncio.get_running_loop().create_task(self._notify())

    async def _notify(self) -> None:
        async with self._changed:
            self._changed.notify_all()

    async def _wait(self, done: Callable[[], bool], timeout_s: float, what: str) -> None:
        """Until ``done()``, within ``timeout_s`` of the board's time (a simulated board slower than the wall
        clock still gets its time), and at most WALL_FACTOR times that on the wall clock."""
        started_board_s = self.latest.board_time_s if self.latest is not None else None
        deadline = asyncio.get_running_loop().time() + WALL_FACTOR * timeout_s + INFO_WAIT_S
        async with self._changed:
            while not done():
                left = deadline - asyncio.get_running_loop().time()
                board_s = self.latest.board_time_s if self.latest is not None else None
                if started_board_s is None:  # no status before (no axis configured yet): the board's time from now
                    started_board_s = board_s
                late = started_board_s is not None and board_s is not None and board_s - started_board_s > timeout_s
                if left <= 0 or late:
                    self.late_replies += 1
                    raise LateReply(f"{what} did not end within {timeout_s:.0f} s (is the axis configured and the "
                                    f"link up?)")
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(self._changed.wait(), min(left, 1.0))

    async def restore(self) -> None:
        """After the link came (back) up: send the axes' configurations again (the board forgets them)."""
        for axis, config in sorted(self.configs.items()):
            try:
                await self._command("MOTION_CONFIG", config.fields(axis))
            except ApiError as error:
                self._event("motion", f"the {AXIS_NAMES[axis]}'s configuration was not restored: {error}", "WARN")
                return
        if self.configs:
            self._event("motion", "the scanner's axes were configured again after the link came up: home them if "
                                  "the board restarted (its position is its power-up zero)", "INFO")

    # --- commands -------------------------------------------------------------------------------------------

    async def configure(self, axis: int, config: AxisConfig) -> AxisConfig:
        """MOTION_CONFIG; the configuration the board then reports."""
        try:
            fields_ = config.fields(axis)
        except MotionError as error:
            raise ApiError("invalid_params", str(error)) from None
        what = f"the {AXIS_NAMES[axis]}'s configuration"
        async with self._lock:
            for attempt in range(1, REPLY_TRIES + 1):
                self.reported.pop(axis, None)
                await self._checked("MOTION_CONFIG", fields_, axis)
                try:
                    await self._wait(lambda: axis in self.reported, INFO_WAIT_S, what)
                    break
                except LateReply as error:
                    if attempt == REPLY_TRIES:
                        raise LateReply(f"{error} ({REPLY_TRIES} times)") from None
                    self._event("motion", f"{error}: asked again ({attempt + 1} of {REPLY_TRIES})", "WARN")
            self.configs[axis] = config
            return self.reported[axis]

    async def move(self, targets: dict[int, float]) -> MotionStatus:
        """Move the axes to these angles (deg), the elevation first; the status once the last is at rest there."""
        status = self.latest
        async with self._lock:
            for axis in sorted(targets, reverse=True):  # the elevation (1) before the orbit (0)
                angle = float(targets[axis])
                config = self.configs.get(axis)
                if config is None:
                    raise ApiError("invalid_params", f"the {AXIS_NAMES[axis]} is not configured: send motion_config "
                                                     "first")
                start = self.latest.axes[axis].position_deg if self.latest is not None else angle
                duration_s = abs(angle - start) / config.max_speed_deg_s + config.max_speed_deg_s / max(
                    config.max_accel_deg_s2, 1e-9)
                what = f"the {AXIS_NAMES[axis]}'s move to {angle:g} deg"
                for attempt in range(1, REPLY_TRIES + 1):
                    try:
                        # asked again, a move ends at once where it already is (or is refused BUSY if it moves)
                        status = await self._until_rest("MOVE_TO", {"axis": axis, "angle_mdeg": round(angle * 1e3)},
                                                        axis, "REACHED", what, duration_s + MOVE_SLACK_S,
                                                        f"{angle:g} deg")
                        break
                    except LateReply as error:
                        if attempt == REPLY_TRIES:
                            raise LateReply(f"{error} ({REPLY_TRIES} times)") from None
                        self._event("motion", f"{error}: asked again ({attempt + 1} of {REPLY_TRIES})", "WARN")
        assert status is not None
        return status

    async def home(self, axis: int, method: str, angle_deg: float) -> MotionStatus:
        """HOME: ``here`` names the position now ``angle_deg``; ``switch`` searches the home switch."""
        methods = {"here": 0, "switch": 1}
        if method not in methods:
            raise ApiError("invalid_params", f"method must be 'here' or 'switch', got {method!r}")
        config = self.configs.get(axis)
        if config is None:
            raise ApiError("invalid_params", f"the {AXIS_NAMES[axis]} is not configured: send motion_config first")
        search_s = 1.1 * (config.max_angle_deg - config.min_angle_deg) / max(config.home_speed_deg_s, 1e-3)
        async with self._lock:
            return await self._until_rest("HOME", {"axis": axis, "method": methods[method],
                                                   "angle_mdeg": round(angle_deg * 1e3)}, axis, "HOMED",
                                          f"homing the {AXIS_NAMES[axis]} ({method})",
                                          (search_s if method == "switch" else 0.0) + MOVE_SLACK_S, f"{angle_deg:g}")

    async def stop(self, release: bool) -> dict[str, Any]:
        """MOTION_STOP: every axis to rest (its driver released if asked). Not behind a running move's lock: a
        stop interrupts it (the move then fails as STOPPED)."""
        await self._command("MOTION_STOP", {"release": int(release)})
        seen = self._statuses
        # the board releases a driver in its first planning window after the axis is at rest, which a status may
        # precede: a release is waited for until it is reported
        await self._wait(lambda: self._statuses > seen and self.latest is not None and all(
            axis.at_rest and not (release and axis.enabled) for axis in self.latest.axes), MOVE_SLACK_S, "the stop")
        return self.status()

    async def stop_scan(self, reason: str) -> bool:
        """Stop the running scan, if any: the capture is asked to stop, a move under way is interrupted
        (MOTION_STOP with the drivers released, as the capture's own release does: one holding them would race
        it), and this returns once the scan has ended (or after SCAN_END_WAIT_S); whether a scan was running."""
        run = self.scan
        if run is None:
            return False
        started = asyncio.get_running_loop().time()
        run.request_stop(reason)
        with contextlib.suppress(ApiError):  # the link is down: the capture's own release says so
            await self.stop(True)
        try:
            await asyncio.wait_for(run.ended.wait(), SCAN_END_WAIT_S)
        except TimeoutError:
            self._event("motion", f"the scan did not end within {SCAN_END_WAIT_S:g} s of the stop", "WARN")
        else:
            self._event("motion", f"the scan stopped ({reason}) in {asyncio.get_running_loop().time() - started:.1f} s",
                        "INFO")
        return True

    def _refuse_while_scanning(self, method: str) -> None:
        """ApiError when a scan owns the rig: its pictures must be taken where it moved the rig."""
        if self.scan is not None:
            raise ApiError("rejected", f"{method} refused: a scan is running (started {self.scan.started_utc}) and "
                                       f"owns the rig: wait for it, or stop it with motion_stop")

    async def _checked(self, name: str, fields_: dict[str, Any], axis: int, angle: str = "") -> None:
        """A motion command whose NACK becomes an API error saying what to do."""
        try:
            await self._command(name, fields_)
        except ApiError as error:
            status = error.__cause__.status if isinstance(error.__cause__, CommandRejected) else ""
            if status in REFUSALS:
                raise ApiError("rejected", REFUSALS[status].format(axis=axis, angle=angle, name=name, status=status,
                                                                   detail=f"{name} {fields_}")) from None
            raise

    async def _until_rest(self, name: str, fields_: dict[str, Any], axis: int, expected: str, what: str,
                          timeout_s: float, angle: str) -> MotionStatus:
        await self._checked(name, fields_, axis, angle)
        seen = self._statuses
        await self._wait(lambda: self._statuses > seen and self.latest is not None
                         and self.latest.axes[axis].at_rest, timeout_s, what)
        assert self.latest is not None
        result = self.latest.axes[axis].result
        if result != expected:
            raise ApiError("rejected", f"{what} ended {result} at {self.latest.axes[axis].position_deg:g} deg"
                           + (" (a fault halted it: clear it, and home the axis if its position was lost)"
                              if result == "FAULT" else ""))
        return self.latest

    # --- reporting ------------------------------------------------------------------------------------------

    def status(self) -> dict[str, Any]:
        """The axes as the board last reported them (JSON-ready), with the configurations sent."""
        axes = []
        for axis in range(AXES):
            entry: dict[str, Any] = {"axis": axis, "name": AXIS_NAMES[axis],
                                     "config": asdict(self.configs[axis]) if axis in self.configs else None}
            if self.latest is not None:
                entry.update(asdict(self.latest.axes[axis]))
            axes.append(entry)
        return {"board_time_s": None if self.latest is None else self.latest.board_time_s, "axes": axes,
                "scan": None if self.scan is None else self.scan.to_json()}

    async def full_status(self) -> dict[str, Any]:
        """:meth:`status`, and on the simulated board its truth (``simulated``)."""
        status = self.status()
        if self._simulated is not None:
            status["simulated"] = await self._simulated()
        return status

    # --- the API --------------------------------------------------------------------------------------------

    def api_methods(self) -> dict[str, Handler]:
        """The motion methods of the daemon's API."""
        return {"motion_config": self._api_config, "motion_move": self._api_move, "motion_home": self._api_home,
                "motion_stop": self._api_stop, "motion_status": self._api_status}

    async def _api_config(self, params: dict[str, Any]) -> dict[str, Any]:
        self._refuse_while_scanning("motion_config")
        axis = _axis(params)
        names = {field.name for field in fields(AxisConfig)}
        unknown = sorted(set(params) - names - {"axis"})
        if unknown:
            raise ApiError("invalid_params", f"motion_config takes axis and {', '.join(sorted(names))}; not "
                                             f"{', '.join(unknown)}")
        for field in fields(AxisConfig):
            if field.name not in params:
                continue
            value = params[field.name]
            if isinstance(field.default, bool):
                if not isinstance(value, bool):
                    raise ApiError("invalid_params", f"motion_config: {field.name} must be true or false, got "
                                                     f"{value!r:.60}")
            elif not is_finite_number(value):
                raise ApiError("invalid_params", f"motion_config: {field.name} must be a finite number, got "
                                                 f"{value!r:.60}")
        try:
            config = AxisConfig(**{key: value for key, value in params.items() if key != "axis"})
        except TypeError as error:
            raise ApiError("invalid_params", f"motion_config: {error}") from None
        return {"axis": axis, "config": asdict(await self.configure(axis, config))}

    async def _api_move(self, params: dict[str, Any]) -> dict[str, Any]:
        self._refuse_while_scanning("motion_move")
        targets = {}
        for axis, name in AXIS_NAMES.items():
            value = _angle_deg(params, f"{name}_deg")
            if value is not None:
                targets[axis] = value
        if not targets:
            raise ApiError("invalid_params", "motion_move needs orbit_deg and/or elevation_deg")
        await self.move(targets)
        return self.status()

    async def _api_home(self, params: dict[str, Any]) -> dict[str, Any]:
        self._refuse_while_scanning("motion_home")
        angle = _angle_deg(params, "angle_deg", 0.0)
        assert angle is not None  # it has a default
        method = params.get("method", "here")
        if not isinstance(method, str):
            raise ApiError("invalid_params", f"method must be 'here' or 'switch', got {method!r:.60}")
        await self.home(_axis(params), method, angle)
        return self.status()

    async def _api_stop(self, params: dict[str, Any]) -> dict[str, Any]:
        release = params.get("release", False)
        if not isinstance(release, bool):
            raise ApiError("invalid_params", f"release must be true or false, got {release!r:.60}")
        if await self.stop_scan("stopped by motion_stop"):  # the drivers released, whatever release says
            return {**self.status(), "scan_stopped": True}
        return await self.stop(release)

    async def _api_status(self, params: dict[str, Any]) -> dict[str, Any]:
        return await self.full_status()


def _angle_deg(params: dict[str, Any], key: str, default: float | None = None) -> float | None:
    """``params[key]`` (else ``default``): a finite number of degrees within the board's angle range; ApiError
    invalid_params otherwise (Python's json reads NaN and Infinity, which were internal errors)."""
    value = params.get(key, default)
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, int | float) or not abs(value) <= ANGLE_LIMIT_DEG:
        raise ApiError("invalid_params", f"{key} must be a finite number of degrees within +-{ANGLE_LIMIT_DEG:g}, "
                                         f"got {value!r:.60}")
    return float(value)


def _axis(params: dict[str, Any]) -> int:
    axis = params.get("axis")
    if axis not in AXIS_NAMES or isinstance(axis, bool):
        raise ApiError("invalid_params", f"axis must be {ORBIT} (orbit) or {ELEVATION} (elevation), got {axis!r}")
    return int(axis)


def rig_position_deg(status: dict[str, Any]) -> tuple[float, float]:
    """Where the orbit and the elevation are (deg) in a ``motion_status`` answer: the simulated rig's true angles
    when it has them, else the angles the board last reported; PhantomError when there are none."""
    angles = (status.get("simulated") or {}).get("rig_deg")
    if angles is not None and None not in angles:
        return float(angles[ORBIT]), float(angles[ELEVATION])
    axes = status["axes"]
    if any("position_deg" not in axis for axis in axes):
        raise PhantomError("the board has not reported the axes' positions (no MOTION_STATUS yet): is the link up?")
    return float(axes[ORBIT]["position_deg"]), float(axes[ELEVATION]["position_deg"])


def simulated_truth(keeper: SimulatedBoardKeeper) -> SimulatedTruth:
    """The simulated board's truth, read when asked: the rig's true angles (deg, from the pulses its drivers took;
    None for an axis whose mechanism is not set) and the plant's pressures (kPa) and gland volume (ml)."""
    async def read() -> dict[str, Any] | None:
        board = keeper.board
        if board is None:
            return None
        try:
            state = await asyncio.get_running_loop().run_in_executor(None, board.plant_state)
        except Exception:  # the simulator died: the keeper's watch restarts it
            return None
        return {"rig_deg": state.get("rig_deg"), "pressures_kpa": [p / 1e3 for p in state["pressures_pa"]],
                "gland_volume_ml": state.get("gland_volume_ml"), "time_s": state.get("time_s")}
    return read


class ThreadRig:
    """The daemon's axes and state for a capture running in a worker thread: a ``phantom.scan.capture`` Orbit
    (``move_to``, ``position_deg``, ``release``), PhantomState (``pressures_kpa``) and StopFlag
    (``stop_requested``: the scan's :class:`ScanRun`), and the simulated board's truth (``simulated``). Each call
    runs on the daemon's event loop and waits for its answer (a PhantomError once the loop has stopped)."""

    def __init__(self, orbit: Orbit, loop: asyncio.AbstractEventLoop, state: DaemonState, run: ScanRun):
        self._orbit = orbit
        self._loop = loop
        self._state = state
        self._scan = run

    def _run(self, coroutine: Awaitable[Result]) -> Result:
        async def wrapped() -> Result:
            return await coroutine
        try:
            future = asyncio.run_coroutine_threadsafe(wrapped(), self._loop)
        except RuntimeError:  # the loop is closed
            raise PhantomError("the daemon stopped") from None
        while True:
            try:
                return future.result(0.5)
            except ApiError as error:
                raise PhantomError(str(error)) from None
            except concurrent.futures.CancelledError:
                raise PhantomError("the daemon is stopping") from None
            except concurrent.futures.TimeoutError:
                if not self._loop.is_running():  # the daemon ended with the request not run: do not wait for ever
                    future.cancel()
                    raise PhantomError("the daemon stopped") from None

    def configure(self, configs: tuple[AxisConfig, ...]) -> None:
        """Send each axis its configuration (axis 0 the first)."""
        for axis, config in enumerate(configs):
            self._run(self._orbit.configure(axis, config))

    def move_to(self, orbit_deg: float, elevation_deg: float) -> tuple[float, float]:
        """Move to a stop of the capture (a picture is taken there): counted in the scan's progress."""
        self._scan.stops_reached += 1
        status = self._run(self._orbit.move({ELEVATION: elevation_deg, ORBIT: orbit_deg}))
        return status.axes[ORBIT].position_deg, status.axes[ELEVATION].position_deg

    def position_deg(self) -> tuple[float, float]:
        """The simulated rig's true angles, else the axes' positions in the board's last MOTION_STATUS."""
        return rig_position_deg(self._run(self._orbit.full_status()))

    def release(self) -> None:
        self._run(self._orbit.stop(True))

    def stop_requested(self, wait_s: float = 0.0) -> str | None:
        return self._scan.stop_requested(wait_s)

    def pressures_kpa(self) -> list[float] | None:
        async def read() -> dict[str, Any]:
            return self._state()
        return scannable_pressures_kpa(self._run(read()))

    def simulated(self) -> dict[str, Any] | None:
        """The simulated board's truth now (``motion_status``'s ``simulated``), None on a real board."""
        return self._run(self._orbit.full_status()).get("simulated")


def scannable_pressures_kpa(status: dict[str, Any]) -> list[float] | None:
    """The measured pressures (kPa) in a daemon status (``Daemon.status``, the API's ``status``), for a picture;
    PhantomError when the phantom cannot be scanned: a fault latched, or the link not online."""
    if status["faults"]:
        raise PhantomError(f"faults latched on the board: {', '.join(status['faults'])}")
    if status["link"] != "online":
        raise PhantomError(f"the board's link is {status['link']}")
    pressures = status["pressures_kpa"]
    return None if pressures is None else [float(p) for p in pressures]


class Scanner(Protocol):
    """A whole capture for the ``scan`` API method (``phantom.scan.daemon_scan.DaemonScanner``): blocking, run in a
    worker thread; ``params`` are the request's; returns the JSON answer (``folder``, ``status``, ``pictures``,
    and ``reason`` when the status is not ``complete``); a PhantomError is the request's error, the caller's to
    fix (``invalid_params``) when its ``code`` says so."""

    def __call__(self, params: dict[str, Any], rig: ThreadRig) -> dict[str, Any]: ...


def planned_stops(params: dict[str, Any]) -> int | None:
    """How many orbit stops (pictures) a ``scan`` request's plan takes: its ``views`` at each of its
    ``elevations_deg``; None when it leaves either to the scanner (or gives what the scanner will refuse)."""
    views, elevations = params.get("views"), params.get("elevations_deg")
    if isinstance(views, bool) or not isinstance(views, int) or not isinstance(elevations, list):
        return None
    return views * len(elevations)


def scan_method(orbit: Orbit, scanner: Scanner, state: DaemonState) -> dict[str, Handler]:
    """The ``scan`` API method: ``scanner`` run in a worker thread with the daemon's axes, which it owns until it
    ends (one scan at a time). A capture that did not complete (stopped, aborted) is an ApiError ``rejected``
    whose data is the scanner's answer."""
    async def scan(params: dict[str, Any]) -> dict[str, Any]:
        if orbit.scan is not None:
            raise ApiError("rejected", f"a scan is running (started {orbit.scan.started_utc}): wait for it, or stop "
                                       f"it with motion_stop")
        run = orbit.scan = ScanRun(planned_stops(params))

        def ended(_: object) -> None:  # when the thread has ended, not when this request was cancelled
            orbit.scan = None
            run.ended.set()
        work = asyncio.ensure_future(asyncio.to_thread(scanner, params, ThreadRig(orbit, asyncio.get_running_loop(),
                                                                                  state, run)))
        work.add_done_callback(ended)
        try:
            answer = await asyncio.shield(work)
        except asyncio.CancelledError:
            run.request_stop("the daemon is stopping")
            raise
        except ApiError:  # the scanner's refusal of its params (invalid_params), before anything moved
            raise
        except PhantomError as error:
            if getattr(error, "code", None) == "invalid_params":  # its params, refused before anything moved
                raise ApiError("invalid_params", str(error)) from None
            raise ApiError("rejected", f"the scan stopped: {error}") from None
        if answer.get("status") != "complete":
            raise ApiError("rejected", f"the scan was {answer.get('status')}: {answer.get('reason')}", answer)
        return answer
    return {"scan": scan}
