"""The Python API of the running daemon: ``phantom.connect()`` gives a :class:`Phantom`.

    import phantom

    with phantom.connect() as ph:                      # the daemon's default socket, or connect("/path.sock")
        print(ph.status().estimated_volume_ml)
        result = ph.set_volume(32.0)                   # returns once the estimate is within 1 % and settled
        print(result.pressures_kpa, result.estimated_volume_ml)
        surface = ph.surface()                         # the deformed outer surface, mm
        surface.save_stl("phantom.stl")

Every method returns a typed result (dataclasses, units in the names) or raises a :class:`DaemonError` subclass
that says what was wrong and what to do: :class:`UnreachableError` (with the reachable range),
:class:`FaultError` (with the faults' names), :class:`StartingError` (with the daemon's start-up progress),
:class:`WaitTimeoutError`, :class:`TargetReplacedError`, :class:`DaemonRestartedError`. :class:`AsyncPhantom`
(``await phantom.connect_async()``) is the asyncio twin with the same methods as coroutines.

A :class:`Phantom` runs its :class:`AsyncPhantom` on an event loop of its own, in a background thread, so it
works in scripts, in Jupyter (whose own loop is busy) and in threads. The connection speaks the daemon's
JSON-lines API (host/README.md, "The local API"); :class:`DaemonClient` is that protocol without types, for
tools and tests.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import itertools
import json
import numbers
import os
import struct
import threading
import time
from collections.abc import AsyncIterator, Awaitable, Callable, Coroutine, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar

from phantom import PhantomError, is_finite_number
from phantom.host.api import check_socket_path, default_socket_path
from phantom.host.peer import check_daemon_peer

if TYPE_CHECKING:
    import numpy as np

#: How long one request may take before the client gives up (s): an inverse on the full solve takes seconds.
REQUEST_TIMEOUT_S = 60.0
#: How long :func:`connect` waits for a daemon that is still starting (its model, the first connection to the
#: board) before it raises StartingError (s).
READY_TIMEOUT_S = 300.0

Result = TypeVar("Result")


# --- errors -------------------------------------------------------------------------------------------------

class DaemonError(PhantomError):
    """The daemon answered a request with an error; ``code`` is one of the API's error codes and ``data`` what
    it said besides its message (a ``starting`` answer's progress)."""

    def __init__(self, code: str, message: str, data: dict[str, Any] | None = None):
        super().__init__(f"{message} [{code}]")
        self.code = code
        self.message = message
        self.data = data or {}


class UnreachableError(DaemonError):
    """No pressures within the limits reach the target; ``range_ml`` is the gland's reachable range (low, high)
    when the daemon gave it (as data: ``gland_range_ml``, never read out of the message's words)."""

    @property
    def range_ml(self) -> tuple[float, float] | None:
        found = self.data.get("gland_range_ml")
        if not isinstance(found, list | tuple) or len(found) != 2:
            return None
        return float(found[0]), float(found[1])


class StartingError(DaemonError):
    """The daemon is still starting (loading its model, or waiting for the board); ``data`` has its progress."""


class FaultError(DaemonError):
    """The board latched a fault while the client waited; ``faults`` names them."""

    def __init__(self, faults: Sequence[str], while_doing: str):
        names = ", ".join(faults)
        super().__init__("fault", f"the board latched {names} while {while_doing}: the blowers are off; remove the "
                         "cause, then call clear_fault() and set the target again", {"faults": list(faults)})
        self.faults = tuple(faults)


class WaitTimeoutError(DaemonError):
    """A wait ran out of time before the target was reached and settled; ``status`` is the last status seen."""

    def __init__(self, message: str, status: Status):
        super().__init__("timeout", message)
        self.status = status


class TargetReplacedError(DaemonError):
    """Another client (or a vent) replaced the target, or a scene, the client was waiting for."""


class DaemonRestartedError(DaemonError):
    """The daemon restarted while the client waited: the target it was given is gone."""


class ConnectionLostError(DaemonError):
    """The daemon closed the connection, or none answers on the socket."""


class VerifyError(DaemonError):
    """A verified target was not verified: a scan failed (``code`` ``scan_failed``: no correction was made from
    it) or the scanned volume stayed outside the tolerance after the last round (``not_verified``); the pressures
    are held. ``rounds`` are the rounds taken (each one's pressures and scanned volume)."""

    @property
    def rounds(self) -> list[dict[str, Any]]:
        return list(self.data.get("rounds") or [])


#: How long a set target is waited for by default (s), and how much longer each verify round (a scan and its
#: reconstruction, a correction, the pressures settling again; about 30 s on the simulated rig, bench/README.md).
SET_TIMEOUT_S = 60.0
VERIFY_ROUND_S = 120.0
#: The kinds of the daemon's events a wait for a target passes to its ``on_progress``: a verified target's rounds.
PROGRESS_EVENTS = ("verify", "scan")

_ERRORS: dict[str, type[DaemonError]] = {"unreachable": UnreachableError, "starting": StartingError}


def _error(code: str, message: str, data: dict[str, Any] | None = None) -> DaemonError:
    return _ERRORS.get(code, DaemonError)(code, message, data)


# --- results ------------------------------------------------------------------------------------------------

def _floats(values: Sequence[float | None] | None) -> tuple[float, ...] | None:
    return None if values is None else tuple(float("nan") if value is None else float(value) for value in values)


@dataclass(frozen=True)
class Progress:
    """Long work the daemon is doing: ``done`` of ``total``, seconds spent and left (None: not known yet)."""

    what: str
    done: int
    total: int
    elapsed_s: float
    left_s: float | None

    @classmethod
    def from_json(cls, data: dict[str, Any]) -> Progress:
        return cls(str(data.get("what", "")), int(data.get("done", 0)), int(data.get("total", 0)),
                   float(data.get("elapsed_s", 0.0)), data.get("left_s"))

    def __str__(self) -> str:
        if self.total <= 0:
            return f"{self.what}: {self.elapsed_s:.0f} s so far"
        left = "" if self.left_s is None else f", about {self.left_s:.0f} s left"
        return f"{self.what}: {self.done}/{self.total}, {self.elapsed_s:.0f} s so far{left}"


@dataclass(frozen=True)
class SceneStep:
    """One step of a scene as played: its target, the volume reached at the end of its hold, the error, the
    time to come within 1 % (from the step's start, after its ramp) and the simulated plant's true volume."""

    index: int
    at_s: float
    target: str
    target_volume_ml: float | None
    reached_volume_ml: float | None
    error_pct: float | None
    reached_after_s: float | None
    true_volume_ml: float | None
    #: why its target (or a point of its ramp) was beyond the phantom's range; None: it was not
    unreachable: str | None = None

    @classmethod
    def from_json(cls, data: dict[str, Any]) -> SceneStep:
        return cls(int(data["index"]), float(data["at_s"]), str(data["target"]), data.get("target_volume_ml"),
                   data.get("reached_volume_ml"), data.get("error_pct"), data.get("reached_after_s"),
                   data.get("true_volume_ml"), data.get("unreachable"))


@dataclass(frozen=True)
class SceneState:
    """The scene the daemon plays (or played last): its name, scene time, end, speed and steps so far."""

    name: str
    time_s: float
    end_s: float
    time_scale: float
    #: it played to its end, or was stopped before it (``stopped``)
    finished: bool
    steps: tuple[SceneStep, ...]
    #: why it was stopped before its end (another target, vent); None: it was not
    stopped: str | None = None

    @classmethod
    def from_json(cls, data: dict[str, Any]) -> SceneState:
        return cls(str(data["name"]), float(data["time_s"]), float(data["end_s"]), float(data["time_scale"]),
                   bool(data["finished"]), tuple(SceneStep.from_json(step) for step in data.get("steps", [])),
                   data.get("stopped"))


@dataclass(frozen=True)
class Status:
    """What the daemon is doing (``phantom status``). Chamber quantities are in chamber order, named by
    ``chamber_labels``; ``None`` where there is nothing yet (no telemetry, no estimate, no target).

    ``pressures_mean_kpa`` are the measured pressures averaged over the last half second (what the estimate
    uses). ``link`` is ``online`` when the board answers; ``control`` is ``idle``, ``holding``, ``scene`` or
    ``vented``; ``fidelity`` is the level the model answers on, ``fidelity_pending`` the level being built
    meanwhile (with ``model_build``'s progress); ``true_volume_ml`` is the simulated plant's own volume (only
    with a simulated board). ``verify`` is where a verified target's rounds are while they run (the round under
    way, what it is doing, the scans so far: ``phantom.host.verify.Rounds.progress``), ``scan`` the pictures of
    the scan being taken (``stops_reached`` of ``stops``), None when none runs; each has its ``text``, the
    daemon's words for it (what ``phantom status`` prints). ``raw`` is the whole answer, for what this class does
    not name.
    """

    ready: bool
    link: str
    control: str
    chamber_labels: tuple[str, ...]
    pressures_kpa: tuple[float, ...] | None
    pressures_mean_kpa: tuple[float, ...] | None
    setpoints_kpa: tuple[float, ...] | None
    estimated_volume_ml: float | None
    estimated_chamber_volumes_ml: tuple[float, ...] | None
    target_volume_ml: float | None
    target: dict[str, Any] | None
    rest_volume_ml: float
    faults: tuple[str, ...]
    fidelity: str
    fidelity_pending: str | None
    model_build: Progress | None
    scene: SceneState | None
    true_volume_ml: float | None
    recording: dict[str, Any] | None
    pid: int | None
    uptime_s: float
    verify: dict[str, Any] | None
    scan: dict[str, Any] | None
    raw: dict[str, Any] = field(repr=False, compare=False)

    @classmethod
    def from_json(cls, data: dict[str, Any]) -> Status:
        build = data.get("model_build")
        return cls(
            ready=bool(data.get("ready", True)), link=str(data["link"]), control=str(data["control"]),
            chamber_labels=tuple(data.get("chamber_labels") or data.get("chambers") or ()),
            pressures_kpa=_floats(data.get("pressures_kpa")),
            pressures_mean_kpa=_floats(data.get("pressures_mean_kpa")),
            setpoints_kpa=_floats(data.get("setpoints_kpa")),
            estimated_volume_ml=data.get("estimated_volume_ml"),
            estimated_chamber_volumes_ml=_floats(data.get("estimated_chamber_volumes_ml")),
            target_volume_ml=data.get("target_volume_ml"), target=data.get("target"),
            rest_volume_ml=float(data["rest_volume_ml"]), faults=tuple(data.get("faults", ())),
            fidelity=str(data.get("fidelity", "")), fidelity_pending=data.get("fidelity_pending"),
            model_build=Progress.from_json(build) if build and not build.get("finished") else None,
            scene=SceneState.from_json(data["scene"]) if data.get("scene") else None,
            true_volume_ml=data.get("plant_volume_ml"), recording=data.get("recording"), pid=data.get("pid"),
            uptime_s=float(data.get("uptime_s", 0.0)), verify=data.get("verify"),
            scan=(data.get("motion") or {}).get("scan"), raw=data)


@dataclass(frozen=True)
class TargetResult:
    """A target set: the setpoints the inverse chose (kPa) and the volumes it predicts (ml); with ``wait=True``
    also what was measured once reached: the estimated volumes at the settled pressures, the simulated plant's
    true volume (when known) and how long it took (s; None without a wait)."""

    target: dict[str, Any]
    pressures_kpa: tuple[float, ...]
    predicted_volume_ml: float
    predicted_chamber_volumes_ml: tuple[float, ...]
    iterations: int
    solve_time_s: float
    estimated_volume_ml: float | None = None
    estimated_chamber_volumes_ml: tuple[float, ...] | None = None
    measured_pressures_kpa: tuple[float, ...] | None = None
    true_volume_ml: float | None = None
    waited_s: float | None = None
    #: a verified target: the gland volume the last scan measured (ml), whether it is within the tolerance, and
    #: each round (``round``, ``asked_ml``, ``setpoints_kpa``, ``pressures_kpa``, ``estimated_volume_ml``,
    #: ``scanned_volume_ml``, ``scanned_error_pct``, ``hull_error_pct``: the visual hull's error on the model's
    #: shape taken off it, ``scan`` folder, ``next``: what the next round asked)
    scanned_volume_ml: float | None = None
    verified: bool | None = None
    rounds: tuple[dict[str, Any], ...] = ()
    #: with a correction by measured volumes in force: its 95 % half-width (ml) at the answer's pressures and from
    #: how many measurements; ``scanned`` False: ``verify="auto"`` found the band within the tolerance, no scan
    band_ml: float | None = None
    measurements: int = 0
    scanned: bool | None = None
    #: a shape target (:meth:`DaemonClient.set_shape`): the shape inverse's answer (``distance_mm``,
    #: ``rest_distance_mm``, ``regions``, volumes, ...: ``phantom inverse --shape --json``'s), else None
    shape: dict[str, Any] | None = None

    @property
    def volume_source(self) -> str:
        """Where :attr:`volume_ml` comes from: ``scan (measured)`` for a verified target, else ``model
        (estimated)``."""
        return "scan (measured)" if self.scanned_volume_ml is not None else "model (estimated)"

    @property
    def volume_ml(self) -> float | None:
        """The volume reached: the scanned one (measured) when the target was verified, else the estimate."""
        return self.scanned_volume_ml if self.scanned_volume_ml is not None else self.estimated_volume_ml

    @classmethod
    def from_json(cls, data: dict[str, Any]) -> TargetResult:
        return cls(dict(data["target"]), tuple(data["pressures_kpa"]), float(data["predicted_volume_ml"]),
                   tuple(data["predicted_chamber_volumes_ml"]), int(data["iterations"]), float(data["solve_time_s"]),
                   band_ml=None if data.get("band_ml") is None else float(data["band_ml"]),
                   measurements=int(data.get("measurements", 0)),
                   shape=dict(data["shape"]) if isinstance(data.get("shape"), dict) else None)


@dataclass(frozen=True)
class SceneRun:
    """A scene started: its name, steps, timeline length (s) and about how long it takes at its time scale."""

    name: str
    steps: int
    end_s: float
    wall_duration_s: float


@dataclass(frozen=True)
class Cleared:
    """The faults ``clear_fault`` cleared, whether the target's setpoints were sent again, and that target as the
    daemon states it (``{"volume_ml": 32.0}``; None when none is in force)."""

    faults: tuple[str, ...]
    setpoints_restored: bool
    target: dict[str, Any] | None = None


@dataclass(frozen=True)
class Surface:
    """The phantom's outer surface: ``vertices_mm`` (n, 3), ``faces`` (k, 3) indices into them, counter-clockwise
    seen from outside; at ``pressures_kpa`` (None: at rest)."""

    vertices_mm: np.ndarray
    faces: np.ndarray
    pressures_kpa: tuple[float, ...] | None

    def save_stl(self, path: str | Path) -> Path:
        """Write the surface as a binary STL file (millimetres), for a robot planner or a slicer; the path."""
        import numpy as np  # only here and in surface(): the command-line clients start without it

        path = Path(path)
        corners = self.vertices_mm[self.faces].astype(np.float64)
        normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
        length = np.linalg.norm(normals, axis=1, keepdims=True)
        normals = normals / np.where(length > 0, length, 1.0)
        records = np.zeros(len(self.faces), dtype=[("normal", "<f4", 3), ("corners", "<f4", (3, 3)),
                                                   ("attribute", "<u2")])
        records["normal"], records["corners"] = normals, corners
        with open(path, "wb") as file:
            file.write(b"active prostate phantom, outer surface, mm".ljust(80, b" "))
            file.write(struct.pack("<I", len(self.faces)))
            file.write(records.tobytes())
        return path


@dataclass(frozen=True)
class Event:
    """Something the daemon did or saw (``kind``: link, fault, target, scene, recording, model ...)."""

    time_s: float
    kind: str
    level: str
    text: str


@dataclass(frozen=True)
class TelemetryFrame:
    """One telemetry frame from the board (50 Hz): pressures and setpoints (kPa), drive levels (0..1), each
    chamber's state, the latched fault bits; ``time_s`` on the daemon's clock, ``board_time_ms`` on the board's."""

    time_s: float
    board_time_ms: int
    pressures_kpa: tuple[float, ...]
    setpoints_kpa: tuple[float, ...]
    drive_levels: tuple[float, ...]
    states: tuple[str, ...]
    fault_flags: int


# --- the connection -----------------------------------------------------------------------------------------

class Connection:
    """One connection to the daemon's socket: requests answered in turn, and the events of a subscription.

    Raises ConnectionLostError (a PhantomError saying what to do) when nothing listens or the daemon goes.
    """

    def __init__(self, socket_path: Path, reader: asyncio.StreamReader, writer: asyncio.StreamWriter):
        self.socket_path = socket_path
        self._reader, self._writer = reader, writer
        self._ids = itertools.count(1)
        self._lock = asyncio.Lock()
        self._events: list[dict[str, Any]] = []

    @classmethod
    async def open(cls, socket_path: str | Path) -> Connection:
        path = Path(socket_path)
        check_socket_path(path)
        try:
            reader, writer = await asyncio.open_unix_connection(str(path), limit=2**26)
        except (FileNotFoundError, ConnectionRefusedError) as error:
            raise ConnectionLostError("no_daemon", f"no daemon is listening on {path}: start one with `phantom "
                                      "daemon` (or pass the right socket)") from error
        except PermissionError as error:
            raise ConnectionLostError("no_daemon", f"no permission to use {path}: join the daemon's group") from error
        try:
            check_daemon_peer(writer.get_extra_info("socket"), path)
        except PhantomError:
            writer.close()
            raise
        return cls(path, reader, writer)

    async def close(self) -> None:
        self._writer.close()
        with contextlib.suppress(Exception):
            await self._writer.wait_closed()

    async def send_line(self, line: bytes) -> None:
        """Send raw bytes (tests send malformed requests with it)."""
        try:
            self._writer.write(line)
            await self._writer.drain()
        except (ConnectionError, RuntimeError) as error:
            raise self._lost() from error

    def _lost(self) -> ConnectionLostError:
        return ConnectionLostError("connection_lost", f"the daemon on {self.socket_path} closed the connection "
                                   "(it stopped or restarted)")

    async def read_message(self) -> dict[str, Any]:
        """The next JSON line from the daemon (a reply or an event)."""
        try:
            line = await self._reader.readline()
        except (ConnectionError, ValueError) as error:
            raise self._lost() from error
        if not line:
            raise self._lost()
        try:
            message = json.loads(line)
        except ValueError:
            message = None
        if not isinstance(message, dict) or not ("event" in message or "id" in message):
            raise self.not_a_daemon(line)
        return message

    def not_a_daemon(self, answer: object) -> DaemonError:
        """The error of a socket that answered what no phantom daemon sends (another program's socket)."""
        said = answer.decode(errors="replace") if isinstance(answer, bytes) else json.dumps(answer)
        return DaemonError("not_a_daemon", f"{self.socket_path} answered {said.strip()[:80]!r}, not a phantom "
                           "daemon's answer: is it another program's socket? Give the daemon's (--socket, "
                           "$PHANTOM_SOCKET)")

    async def call(self, method: str, params: dict[str, Any] | None = None) -> Any:
        """Send one request and return its result; raises the DaemonError subclass of its error code. Events that
        arrive meanwhile are kept for :meth:`next_event`."""
        async with self._lock:
            request_id = next(self._ids)
            await self.send_line((_request_json(request_id, method, params or {}) + "\n").encode())
            while True:
                message = await self.read_message()
                if "event" in message:
                    self._events.append(message)
                elif message.get("id") == request_id:
                    break
        if "error" in message:
            error = message["error"]
            if not (isinstance(error, dict) and isinstance(error.get("code"), str)
                    and isinstance(error.get("message"), str)):
                raise self.not_a_daemon(message)
            raise _error(error["code"], error["message"], error.get("data"))
        if "result" not in message:
            raise self.not_a_daemon(message)
        return message["result"]

    async def next_event(self) -> dict[str, Any]:
        """The next ``{"event", "data"}`` message of this connection's subscription."""
        if self._events:
            return self._events.pop(0)
        while True:
            message = await self.read_message()
            if "event" in message:
                return message


def _request_json(request_id: int, method: str, params: dict[str, Any]) -> str:
    """A request as a JSON line; PhantomError for a param JSON has no form for (the daemon checks the rest)."""
    try:
        return json.dumps({"id": request_id, "method": method, "params": params}, default=_json_value)
    except (TypeError, ValueError) as error:
        raise PhantomError(f"{method}: {error}: give numbers, text, lists and dicts (numpy's numbers and arrays "
                           "too)") from None


def _json_value(value: object) -> object:
    """JSON's form of what ``json`` cannot write: numpy's numbers and arrays, what a notebook passes (numpy is
    not imported for it: the command-line clients start without it)."""
    if type(value).__module__ == "numpy" and hasattr(value, "tolist"):
        return value.tolist()
    raise TypeError(f"{type(value).__name__} {value!r} cannot be sent")


# --- the asyncio API ----------------------------------------------------------------------------------------

def resolve_scene(path: str | Path) -> str:
    """A scene file's absolute path; a bare name (``bph_growth``) is a shipped example scene (PhantomError naming
    the shipped ones when there is none of that name)."""
    from phantom.host.scenes import example_scene_path

    text = str(path)
    candidate = Path(text)
    if not candidate.exists() and "/" not in text and not text.endswith(".toml"):
        candidate = example_scene_path(text)
    return str(candidate.resolve())


class AsyncPhantom:
    """The daemon's API as coroutines (see :class:`Phantom` for what each method does); build it with
    ``await phantom.connect_async()``."""

    def __init__(self, connection: Connection, request_timeout_s: float = REQUEST_TIMEOUT_S,
                 ready_timeout_s: float = READY_TIMEOUT_S):
        self.connection = connection
        self.socket_path = connection.socket_path
        self.request_timeout_s = request_timeout_s
        self.ready_timeout_s = ready_timeout_s
        #: the daemon's process id when connected: a wait that finds another one knows it restarted
        self.daemon_pid: int | None = None

    @classmethod
    async def connect(cls, socket: str | Path | None = None, *, request_timeout_s: float = REQUEST_TIMEOUT_S,
                      ready_timeout_s: float = READY_TIMEOUT_S,
                      on_wait: Callable[[str], None] | None = None) -> AsyncPhantom:
        """Connect and wait until the daemon is ready (its model answers and the board is online), for at most
        ``ready_timeout_s`` (0: do not wait); ``on_wait`` is told what it is waiting for, now and then."""
        # the client's own settings: refused here, before they make a wait's arithmetic fail or never end
        if not (is_finite_number(request_timeout_s) and request_timeout_s > 0):
            raise PhantomError(f"request_timeout_s must be a positive number of seconds, got {request_timeout_s!r}")
        if not (is_finite_number(ready_timeout_s) and ready_timeout_s >= 0):
            raise PhantomError(f"ready_timeout_s must be a number of seconds, 0 or more (0: do not wait), got "
                               f"{ready_timeout_s!r}")
        path = Path(socket) if socket is not None else default_socket_path()
        phantom = cls(await Connection.open(path), request_timeout_s, ready_timeout_s)
        try:
            status = await phantom.wait_ready(ready_timeout_s, on_wait) if ready_timeout_s > 0 else (
                await phantom.status())
        except BaseException:
            await phantom.close()
            raise
        phantom.daemon_pid = status.pid
        return phantom

    async def close(self) -> None:
        """Close the connection (the daemon keeps its target)."""
        await self.connection.close()

    async def __aenter__(self) -> AsyncPhantom:
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    async def call(self, method: str, params: dict[str, Any] | None = None) -> Any:
        """One request of the JSON API, untyped (host/README.md lists the methods)."""
        try:
            return await asyncio.wait_for(self.connection.call(method, params), self.request_timeout_s)
        except TimeoutError:
            # a connection whose answer is still due cannot be used for the next request
            await self.connection.close()
            self.connection = await Connection.open(self.socket_path)
            raise DaemonError("timeout", f"the daemon on {self.socket_path} did not answer {method} within "
                              f"{self.request_timeout_s:g} s (request_timeout_s)") from None

    async def status(self) -> Status:
        answer = await self.call("status")
        try:
            return Status.from_json(answer)
        except (KeyError, TypeError, AttributeError, ValueError):  # a status no phantom daemon sends
            raise self.connection.not_a_daemon(answer) from None

    async def wait_ready(self, timeout_s: float = READY_TIMEOUT_S,
                         on_wait: Callable[[str], None] | None = None) -> Status:
        """Wait until the daemon is ready; its status. Raises StartingError with its progress after ``timeout_s``
        of waiting, or at once when the daemon's start-up ended in an error."""
        deadline_s = time.monotonic() + timeout_s
        told_s = 0.0
        while True:
            try:
                status = await self.status()
                if status.ready:
                    return status
                starting = status.raw.get("starting") or {}
                what = str(starting.get("text", "waiting for the board"))
            except StartingError as error:
                what = error.message.removeprefix("the daemon is still starting: ")
            if time.monotonic() >= deadline_s:
                raise StartingError("starting", f"the daemon on {self.socket_path} was not ready after "
                                    f"{timeout_s:g} s: {what}; wait longer (ready_timeout_s), or see its log")
            if on_wait is not None and time.monotonic() - told_s >= 2.0:
                told_s = time.monotonic()
                on_wait(what)
            await asyncio.sleep(0.5)

    # --- targets ---

    async def set_volume(self, volume_ml: float, *, wait: bool = True, tolerance_pct: float = 1.0,
                         timeout_s: float | None = None, growth_ratio: dict[str, float] | None = None,
                         verify: str | None = None, verify_tolerance_pct: float | None = None,
                         verify_rounds: int | None = None,
                         on_progress: Callable[[str], None] | None = None) -> TargetResult:
        params: dict[str, Any] = {"volume_ml": volume_ml}
        if growth_ratio:
            params["growth_ratio"] = growth_ratio
        if verify is not None:
            params["verify"] = verify
            if verify_tolerance_pct is not None:
                params["verify_tolerance_pct"] = verify_tolerance_pct
            if verify_rounds is not None:
                params["verify_rounds"] = verify_rounds
        elif verify_tolerance_pct is not None or verify_rounds is not None:
            raise PhantomError('verify_tolerance_pct and verify_rounds go with verify="scan"')
        if timeout_s is None:
            # rounds the daemon refuses (0, -1, 2.5) wait as the default's: its refusal says what was wrong
            rounds = verify_rounds if isinstance(verify_rounds, numbers.Integral) and 0 < verify_rounds <= 100 else 4
            timeout_s = SET_TIMEOUT_S if verify is None else SET_TIMEOUT_S + VERIFY_ROUND_S * rounds
        return await self._set(params, wait, tolerance_pct, timeout_s, on_progress)

    async def set_chamber_volumes(self, volumes_ml: Sequence[float | None], *, wait: bool = True,
                                  tolerance_pct: float = 1.0, timeout_s: float = 60.0) -> TargetResult:
        return await self._set({"chamber_volumes_ml": volumes_ml}, wait, tolerance_pct, timeout_s)

    async def set_pressures(self, pressures_kpa: Sequence[float], *, wait: bool = True, tolerance_pct: float = 1.0,
                            timeout_s: float = 60.0) -> TargetResult:
        return await self._set({"pressures_kpa": pressures_kpa}, wait, tolerance_pct, timeout_s)

    async def set_shape(self, shape: str | os.PathLike[str] | dict[str, Any], *, wait: bool = True,
                        labels: Sequence[int] | None = None, refine_solves: int | None = None,
                        tolerance_pct: float = 1.0, timeout_s: float = SET_TIMEOUT_S + 60.0) -> TargetResult:
        # a path as the daemon (on this machine, with another working folder) finds it
        params: dict[str, Any] = {"shape": os.path.abspath(shape) if isinstance(shape, str | os.PathLike) else shape}
        if labels is not None:
            params["labels"] = labels
        if refine_solves is not None:
            params["refine_solves"] = refine_solves
        return await self._set(params, wait, tolerance_pct, timeout_s)

    async def _set(self, params: dict[str, Any], wait: bool, tolerance_pct: float, timeout_s: float,
                   on_progress: Callable[[str], None] | None = None) -> TargetResult:
        # the wait is the client's own, so is its check; the daemon checks the target and tolerance_pct
        if not (is_finite_number(timeout_s) and timeout_s > 0):
            raise PhantomError(f"timeout_s must be a positive number of seconds, got {timeout_s!r}")
        if not wait:
            return TargetResult.from_json(await self.call("set_target", {**params, "tolerance_pct": tolerance_pct}))
        # subscribed before the target is set: its outcome cannot come before the client listens
        outcomes = await self._subscribed("events")
        try:
            result = TargetResult.from_json(await self.call("set_target", {**params, "tolerance_pct": tolerance_pct}))
        except BaseException:
            await outcomes.close()
            raise
        return await self._wait_reached(result, outcomes, timeout_s, on_progress)

    async def _subscribed(self, topic: str) -> Connection:
        """A connection of its own subscribed to ``topic``'s events."""
        connection = await Connection.open(self.socket_path)
        try:
            await connection.call("subscribe", {"topics": [topic]})
        except BaseException:
            await connection.close()
            raise
        return connection

    async def _wait_reached(self, result: TargetResult, outcomes: Connection, timeout_s: float,
                            on_progress: Callable[[str], None] | None = None) -> TargetResult:
        """Wait for the daemon's word on the target (an event with its ``outcome``: the daemon's one rule of
        reached, host/control.py): return once reached; raise on a fault, a replaced target, a restarted daemon
        or the timeout; ``on_progress`` is given the text of each verify and scan event meanwhile (a verified
        target's rounds). Closes ``outcomes``, the events subscription."""
        try:
            return await self._outcome(result, outcomes, timeout_s, on_progress)
        finally:
            await outcomes.close()

    async def _outcome(self, result: TargetResult, outcomes: Connection, timeout_s: float,
                       on_progress: Callable[[str], None] | None) -> TargetResult:
        started_s = time.monotonic()
        wanted = describe_target(result.target)
        while True:
            left_s = started_s + timeout_s - time.monotonic()
            try:
                message = await asyncio.wait_for(outcomes.next_event(), max(left_s, 0.0))
            except TimeoutError:
                status = await self._status_across_restarts(result, wanted, started_s + timeout_s)
                raise WaitTimeoutError(
                    f"{wanted} was not reached within {timeout_s:g} s: estimate "
                    f"{_ml(status.estimated_volume_ml)}, pressures {_kpa(status.pressures_kpa)} against setpoints "
                    f"{_kpa(status.setpoints_kpa)} kPa, link {status.link}; wait longer (timeout_s), or check the "
                    "tubes and the blowers", status) from None
            except ConnectionLostError:
                # raises unless the same daemon answers again; its outcome may have come meanwhile: the status says
                # whether the target is still held, and the wait goes on until its outcome or the timeout
                await self._status_across_restarts(result, wanted, started_s + timeout_s)
                await outcomes.close()
                outcomes = await self._subscribed("events")
                continue
            data = message.get("data") or {}
            if on_progress is not None and data.get("kind") in PROGRESS_EVENTS and "outcome" not in data:
                on_progress(str(data.get("text", "")))
            if data.get("source") != "api" or data.get("target") != result.target or "outcome" not in data:
                continue
            outcome = data["outcome"]
            if outcome == "reached":
                status = await self.status()
                scanned = data.get("scanned_volume_ml")
                return dataclasses.replace(
                    result, estimated_volume_ml=data.get("estimated_volume_ml"),
                    estimated_chamber_volumes_ml=_floats(data.get("estimated_chamber_volumes_ml")),
                    measured_pressures_kpa=_floats(data.get("measured_pressures_kpa")),
                    true_volume_ml=status.true_volume_ml, waited_s=time.monotonic() - started_s,
                    scanned_volume_ml=None if scanned is None else float(scanned),
                    verified=data.get("verified") if "rounds" in data else None,
                    rounds=tuple(data.get("rounds") or ()), scanned=data.get("scanned"))
            if outcome in ("scan_failed", "not_verified"):
                raise VerifyError(outcome, str(data.get("text", f"{wanted} was not verified")),
                                  {"rounds": data.get("rounds") or []})
            if outcome == "faulted":
                status = await self.status()
                # mid-verify, the outcome says which round it was in and what to do
                during = f" ({data['text']})" if "rounds" in data and data.get("text") else ""
                raise FaultError(status.faults or ("a fault",), f"waiting for {wanted}{during}")
            if outcome == "unreachable":
                raise UnreachableError("unreachable", str(data.get("text", f"{wanted} is unreachable")),
                                       {"gland_range_ml": data["gland_range_ml"]} if "gland_range_ml" in data else None)
            raise TargetReplacedError("replaced", f"the target {wanted} was replaced while waiting for it: "
                                      f"{message['data'].get('text', outcome)}")

    async def _status_across_restarts(self, result: TargetResult, wanted: str, deadline_s: float) -> Status:
        """The status; when the connection is lost, connect again (the daemon may be restarting) until the
        deadline, and raise DaemonRestartedError when another daemon answers."""
        try:
            return await self.status()
        except ConnectionLostError:
            pass
        while True:
            try:
                await self.connection.close()
                self.connection = await Connection.open(self.socket_path)
                status = await self.status()
            except (ConnectionLostError, StartingError):
                if time.monotonic() >= deadline_s:
                    raise
                await asyncio.sleep(0.5)
                continue
            if status.pid != self.daemon_pid:
                self.daemon_pid = status.pid
                raise DaemonRestartedError("restarted", f"the daemon restarted while waiting for {wanted} (it "
                                           f"now holds {describe_target(status.target)}, control {status.control}): "
                                           "set the target again")
            return status

    async def vent(self) -> None:
        await self.call("vent")

    async def clear_fault(self) -> Cleared:
        answer = await self.call("clear_fault")
        return Cleared(tuple(answer.get("cleared", ())), bool(answer.get("setpoints_restored")), answer.get("target"))

    async def zero(self) -> None:
        await self.call("zero")

    async def run_scene(self, path: str | Path, *, wait: bool = False, time_scale: float = 1.0,
                        timeout_s: float | None = None,
                        on_progress: Callable[[Status], None] | None = None) -> SceneRun | SceneState:
        started = await self.call("run_scene", {"path": resolve_scene(path), "time_scale": time_scale})
        run = SceneRun(str(started["name"]), int(started["steps"]), float(started["end_s"]),
                       float(started["wall_duration_s"]))
        if not wait:
            return run
        return await self.follow_scene(run, timeout_s=timeout_s, on_progress=on_progress)

    async def follow_scene(self, run: SceneRun, *, timeout_s: float | None = None,
                           on_progress: Callable[[Status], None] | None = None) -> SceneState:
        limit_s = timeout_s if timeout_s is not None else 2.0 * run.wall_duration_s + 60.0
        deadline_s = time.monotonic() + limit_s
        while True:
            status = await self.status()
            if status.faults:
                raise FaultError(status.faults, f"playing the scene {run.name}")
            if status.scene is None or status.scene.name != run.name:
                raise TargetReplacedError("replaced", f"the scene {run.name} was replaced by another request before "
                                          "it finished")
            if on_progress is not None:
                on_progress(status)
            if status.scene.stopped is not None:
                raise TargetReplacedError("replaced", f"the scene {run.name} was stopped at {status.scene.time_s:.1f} "
                                          f"of {status.scene.end_s:g} s: {status.scene.stopped}")
            if status.scene.finished:
                return status.scene
            if time.monotonic() >= deadline_s:
                raise WaitTimeoutError(f"the scene {run.name} did not finish within {limit_s:g} s (at "
                                       f"{status.scene.time_s:.1f} of {status.scene.end_s:g} s)", status)
            await asyncio.sleep(0.5)

    async def surface(self, pressures_kpa: Sequence[float] | None = None) -> Surface:
        import numpy as np  # only here and in save_stl(): the command-line clients start without it

        params = {} if pressures_kpa is None else {"pressures_kpa": pressures_kpa}
        answer = await self.call("surface", params)
        return Surface(np.asarray(answer["positions_mm"], dtype=float), np.asarray(answer["triangles"], dtype=np.int64),
                       _floats(answer.get("pressures_kpa")))

    async def events(self) -> AsyncIterator[Event]:
        async for data in self._subscription("events"):
            yield Event(float(data["time_s"]), str(data["kind"]), str(data["level"]), str(data["text"]))

    async def telemetry(self) -> AsyncIterator[TelemetryFrame]:
        async for data in self._subscription("telemetry"):
            yield TelemetryFrame(float(data["time_s"]), int(data["board_time_ms"]), tuple(data["pressures_kpa"]),
                                 tuple(data["setpoints_kpa"]), tuple(data["drive_levels"]), tuple(data["states"]),
                                 int(data["fault_flags"]))

    async def _subscription(self, topic: str) -> AsyncIterator[dict[str, Any]]:
        """The data of one topic's events, on a connection of their own (requests are not held up by them)."""
        connection = await self._subscribed(topic)
        try:
            while True:
                message = await connection.next_event()
                if message["event"] == topic:
                    yield message["data"]
        finally:
            await connection.close()


def describe_target(target: dict[str, Any] | None) -> str:
    """A target as the daemon states it (``Status.target``, ``TargetResult.target``) in words: ``40 ml``,
    ``chamber volumes 2, -, - ml``, ``pressures 1, 1, 1 kPa``; ``none``."""
    if not target:
        return "none"
    if "volume_ml" in target:
        return f"{target['volume_ml']:g} ml"
    if "chamber_volumes_ml" in target:
        return "chamber volumes " + ", ".join("-" if v is None else f"{v:g}" for v in target["chamber_volumes_ml"]) \
            + " ml"
    return "pressures " + ", ".join(f"{v:g}" for v in target.get("pressures_kpa", [])) + " kPa"


def _ml(value: float | None) -> str:
    return "-" if value is None else f"{value:.2f} ml"


def _kpa(values: Sequence[float] | None) -> str:
    return "-" if values is None else ", ".join(f"{value:.3f}" for value in values)


# --- the blocking API ---------------------------------------------------------------------------------------

class _LoopThread:
    """An event loop in a daemon thread of its own, shared by every blocking client of this process."""

    _instance: _LoopThread | None = None
    _guard = threading.Lock()

    def __init__(self) -> None:
        self.loop = asyncio.new_event_loop()
        self.thread = threading.Thread(target=self.loop.run_forever, name="phantom client", daemon=True)
        self.thread.start()

    @classmethod
    def shared(cls) -> _LoopThread:
        with cls._guard:
            if cls._instance is None or not cls._instance.thread.is_alive():
                cls._instance = cls()
            return cls._instance

    def run(self, coroutine: Coroutine[Any, Any, Result]) -> Result:
        """Run ``coroutine`` on the loop and wait for it here; Ctrl-C cancels it."""
        future = asyncio.run_coroutine_threadsafe(coroutine, self.loop)
        try:
            return future.result()
        except BaseException:
            future.cancel()
            raise

    def iterate(self, iterator: AsyncIterator[Result]) -> Iterator[Result]:
        """An async iterator's items, one by one, here."""
        try:
            while True:
                try:
                    yield self.run(_anext(iterator))
                except StopAsyncIteration:
                    return
        finally:
            with contextlib.suppress(Exception):
                self.run(_aclose(iterator))


async def _anext(iterator: AsyncIterator[Result]) -> Result:
    return await iterator.__anext__()


async def _aclose(iterator: AsyncIterator[Any]) -> None:
    close: Callable[[], Awaitable[None]] | None = getattr(iterator, "aclose", None)
    if close is not None:
        await close()


class Phantom:
    """The running daemon, from a script or a notebook: ``phantom.connect()`` builds one.

    Every method blocks until the daemon answers (or, with ``wait=True``, until the target is reached) and raises
    a :class:`DaemonError` subclass saying what to do when it cannot. Use it as a context manager, or call
    :meth:`close`. It is the blocking face of :class:`AsyncPhantom` (``.aio``), which runs on an event loop in a
    background thread. Numbers and lists of numbers may be numpy's (scalars, arrays); the daemon checks them.
    """

    def __init__(self, aio: AsyncPhantom, loop: _LoopThread):
        self.aio = aio
        self._loop = loop

    @property
    def socket_path(self) -> Path:
        return self.aio.socket_path

    def close(self) -> None:
        """Close the connection; the daemon keeps the target."""
        self._loop.run(self.aio.close())

    def __enter__(self) -> Phantom:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def call(self, method: str, params: dict[str, Any] | None = None) -> Any:
        """One request of the daemon's JSON API, untyped (host/README.md, "The local API")."""
        return self._loop.run(self.aio.call(method, params))

    def status(self) -> Status:
        """What the daemon is doing: link, control, pressures, volumes, faults, fidelity, scene, recording."""
        return self._loop.run(self.aio.status())

    def wait_ready(self, timeout_s: float = READY_TIMEOUT_S) -> Status:
        """Wait until the daemon's model answers and its board is online; StartingError with its progress after
        ``timeout_s``."""
        return self._loop.run(self.aio.wait_ready(timeout_s))

    def set_volume(self, volume_ml: float, *, wait: bool = True, tolerance_pct: float = 1.0,
                   timeout_s: float | None = None, growth_ratio: dict[str, float] | None = None,
                   verify: str | None = None, verify_tolerance_pct: float | None = None,
                   verify_rounds: int | None = None, on_progress: Callable[[str], None] | None = None
                   ) -> TargetResult:
        """Make the gland ``volume_ml`` (ml): the inverse finds the chamber pressures and the board holds them.

        Parameters
        ----------
        volume_ml : float
            The whole gland's volume (ml).
        wait : bool
            Return only once the estimated volume (the model at the measured pressures) is within
            ``tolerance_pct`` of the target and every pressure has stayed within 0.1 kPa of its setpoint for a
            second; False: return as soon as the setpoints are sent.
        tolerance_pct : float
            How close the estimate must come (% of the target).
        timeout_s : float, optional
            How long to wait (s) before WaitTimeoutError: 60 s by default, and 120 s more per round with verify.
        growth_ratio : dict, optional
            How the growth is shared: chamber name or index -> weight (``{"chamber1": 2, "chamber2": 1}``: the
            left lobe grows twice as much as the right).
        verify : str, optional
            ``"scan"``: once reached on pressure, scan the phantom and compare the scanned gland volume with the
            target; outside 0.6 of ``verify_tolerance_pct`` (a third for a scan whose visual hull's error could
            not be taken off; the last round: outside it) the scan corrects
            the model (or the volume asked) and the pressures are applied again, for at most ``verify_rounds``
            scans; every scan is stored as a measurement of the phantom. The result's ``volume_ml`` is then
            the scanned (measured) volume, ``rounds`` each round's pressures and scanned volume. ``"auto"``:
            the same, unless the correction by the stored measurements is sure of the target (its 95 % band
            there within ``verify_tolerance_pct``): then no scan, and the result says reached within +-``band_pct``
            (95 %) from ``measurements`` stored measurements (``scanned`` False).
        verify_tolerance_pct : float, optional
            How close the scanned volume must come (% of the target; default 0.3, from 0.05 to 20); the rounds
            aim at 0.6 of it, a third without the hull's error taken off (the scanner's own error adds to the
            scanned one in the true volume).
        verify_rounds : int, optional
            The most scans (default 4, at most 10).
        on_progress : callable, optional
            Given the text of each of the daemon's verify and scan events while waiting: a verified target's
            rounds as they go (settled and scanning, scanned and correcting), a minute or two each.

        Raises
        ------
        UnreachableError
            No pressures within the limits give ``volume_ml``; ``range_ml`` is the reachable range.
        FaultError
            The board latched a fault while waiting (``faults`` names them).
        WaitTimeoutError, TargetReplacedError, DaemonRestartedError
            Not reached in time; another client replaced the target; the daemon restarted meanwhile.
        VerifyError
            With verify: a scan failed (no correction made from it), or the scanned volume stayed outside the
            tolerance after the last round; the pressures are held. DaemonError ``invalid_params`` when the
            daemon has no scanner.
        """
        return self._loop.run(self.aio.set_volume(volume_ml, wait=wait, tolerance_pct=tolerance_pct,
                                                  timeout_s=timeout_s, growth_ratio=growth_ratio, verify=verify,
                                                  verify_tolerance_pct=verify_tolerance_pct,
                                                  verify_rounds=verify_rounds, on_progress=on_progress))

    def set_chamber_volumes(self, volumes_ml: Sequence[float | None], *, wait: bool = True, tolerance_pct: float = 1.0,
                            timeout_s: float = 60.0) -> TargetResult:
        """Make each chamber hold a volume (ml, chamber order; None leaves one free); ``wait`` etc. as in
        :meth:`set_volume`, the tolerance applying to each given chamber."""
        return self._loop.run(self.aio.set_chamber_volumes(volumes_ml, wait=wait, tolerance_pct=tolerance_pct,
                                                           timeout_s=timeout_s))

    def set_pressures(self, pressures_kpa: Sequence[float], *, wait: bool = True, tolerance_pct: float = 1.0,
                      timeout_s: float = 60.0) -> TargetResult:
        """Hold raw chamber pressures (kPa, chamber order); with ``wait``, until they have settled and the
        estimate is within ``tolerance_pct`` of the volume the model predicts at them."""
        return self._loop.run(self.aio.set_pressures(pressures_kpa, wait=wait, tolerance_pct=tolerance_pct,
                                                     timeout_s=timeout_s))

    def set_shape(self, shape: str | os.PathLike[str] | dict[str, Any], *, wait: bool = True,
                  labels: Sequence[int] | None = None, refine_solves: int | None = None, tolerance_pct: float = 1.0,
                  timeout_s: float = SET_TIMEOUT_S + 60.0) -> TargetResult:
        """Make the phantom look most like a gland: ``shape`` a NIfTI mask or closed mesh (mm) on the daemon's
        machine (a path), or a small mesh ``{"vertices_mm": [...], "triangles": [...]}``; ``labels`` the gland's
        labels in a label map; ``refine_solves`` full solves after the table's answer (default 1). The daemon
        answers the pressures of the shape inverse (``phantom inverse --shape``) and holds them; the result's
        ``shape`` has the distance to the target at rest and at the answer, the per-region error and the
        volumes. ``wait`` etc. as in :meth:`set_pressures`."""
        return self._loop.run(self.aio.set_shape(shape, wait=wait, labels=labels, refine_solves=refine_solves,
                                                 tolerance_pct=tolerance_pct, timeout_s=timeout_s))

    def vent(self) -> None:
        """All blowers off now: every setpoint 0; the target and any scene are dropped."""
        self._loop.run(self.aio.vent())

    def clear_fault(self) -> Cleared:
        """Clear the board's latched faults (refused while a cause persists); the target's setpoints are sent
        again."""
        return self._loop.run(self.aio.clear_fault())

    def zero(self) -> None:
        """Zero the pressure sensors (the phantom must be vented and still; a refusal says why)."""
        self._loop.run(self.aio.zero())

    def run_scene(self, path: str | Path, *, wait: bool = False, time_scale: float = 1.0,
                  timeout_s: float | None = None) -> SceneRun | SceneState:
        """Play a scene's ``[[steps]]`` timeline (a TOML path, or a shipped example's name: ``bph_growth``,
        ``lopsided``), ``time_scale`` times faster than written. Returns at once (a SceneRun), or with ``wait``
        when it has finished (a SceneState with each step's target, reached volume and time), raising FaultError,
        TargetReplacedError or WaitTimeoutError (default: twice the scene's duration and a minute)."""
        return self._loop.run(self.aio.run_scene(path, wait=wait, time_scale=time_scale, timeout_s=timeout_s))

    def follow_scene(self, run: SceneRun, *, timeout_s: float | None = None,
                     on_progress: Callable[[Status], None] | None = None) -> SceneState:
        """Wait for a scene started with ``run_scene`` to finish (``on_progress`` is shown each status on the
        way); its steps. Raises as ``run_scene(..., wait=True)`` does."""
        return self._loop.run(self.aio.follow_scene(run, timeout_s=timeout_s, on_progress=on_progress))

    def surface(self, pressures_kpa: Sequence[float] | None = None) -> Surface:
        """The deformed outer surface (vertices in mm, triangles) at ``pressures_kpa``, or at the latest measured
        pressures; ``save_stl`` writes it for a robot planner."""
        return self._loop.run(self.aio.surface(pressures_kpa))

    def events(self) -> Iterator[Event]:
        """The daemon's events as they happen (link, faults, targets, scenes, recording), until the loop stops."""
        return self._loop.iterate(self.aio.events())

    def telemetry(self) -> Iterator[TelemetryFrame]:
        """The board's telemetry frames (50 Hz) as they arrive."""
        return self._loop.iterate(self.aio.telemetry())


def connect(socket: str | Path | None = None, *, request_timeout_s: float = REQUEST_TIMEOUT_S,
            ready_timeout_s: float = READY_TIMEOUT_S, on_wait: Callable[[str], None] | None = None) -> Phantom:
    """Connect to the running daemon and wait until it is ready.

    Parameters
    ----------
    socket : path, optional
        The daemon's socket; default ``$PHANTOM_SOCKET``, ``/run/phantom/phantomd.sock``,
        ``$XDG_RUNTIME_DIR/phantomd.sock`` or ``/tmp/phantomd-UID.sock``, as the daemon chooses.
    request_timeout_s : float
        How long one request may take (s).
    ready_timeout_s : float
        How long to wait for a daemon that is still starting (s; 0: not at all).
    on_wait : callable(str), optional
        Told what the daemon is doing while it starts (every few seconds).

    Raises
    ------
    ConnectionLostError
        No daemon listens on the socket.
    StartingError
        Not ready within ``ready_timeout_s``; the message has its progress.
    """
    loop = _LoopThread.shared()
    return Phantom(loop.run(AsyncPhantom.connect(socket, request_timeout_s=request_timeout_s,
                                                 ready_timeout_s=ready_timeout_s, on_wait=on_wait)), loop)


async def connect_async(socket: str | Path | None = None, *, request_timeout_s: float = REQUEST_TIMEOUT_S,
                        ready_timeout_s: float = READY_TIMEOUT_S,
                        on_wait: Callable[[str], None] | None = None) -> AsyncPhantom:
    """:func:`connect`'s asyncio twin: ``async with await phantom.connect_async() as ph: await ph.set_volume(32)``."""
    return await AsyncPhantom.connect(socket, request_timeout_s=request_timeout_s, ready_timeout_s=ready_timeout_s,
                                      on_wait=on_wait)


class DaemonClient:
    """One connection speaking the daemon's JSON protocol without types (tools and tests): ``call`` a method,
    ``events`` of a subscription, raw lines. It does not wait for readiness."""

    def __init__(self, socket_path: str | Path, timeout_s: float = REQUEST_TIMEOUT_S):
        self.socket_path = Path(socket_path)
        self.timeout_s = timeout_s
        self._loop = _LoopThread.shared()
        self._connection = self._loop.run(Connection.open(self.socket_path))

    def __enter__(self) -> DaemonClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        self._loop.run(self._connection.close())

    def _run(self, coroutine: Coroutine[Any, Any, Result], what: str) -> Result:
        try:
            return self._loop.run(asyncio.wait_for(coroutine, self.timeout_s))
        except TimeoutError:
            raise PhantomError(f"the daemon on {self.socket_path} did not answer {what} in time "
                               f"({self.timeout_s:g} s)") from None

    def send_line(self, line: bytes) -> None:
        """Send raw bytes (tests send malformed requests with it)."""
        self._run(self._connection.send_line(line), "a line")

    def read_message(self) -> dict[str, Any]:
        """The next JSON line from the daemon (a reply or an event)."""
        return self._run(self._connection.read_message(), "with a message")

    def call(self, method: str, params: dict[str, Any] | None = None) -> Any:
        """Send one request and return its result; raises DaemonError (its subclass by code) on an error."""
        return self._run(self._connection.call(method, params), method)

    def events(self, topics: list[str] | None = None) -> Iterator[dict[str, Any]]:
        """Subscribe and yield ``{"event", "data"}`` messages as they come."""
        self.call("subscribe", {"topics": topics} if topics else {})
        while True:
            yield self._loop.run(self._connection.next_event())
