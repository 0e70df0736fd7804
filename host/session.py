"""The daemon's link to its board: an asyncio driver of :class:`phantom.protocol.link.HostLink`.

State machine (``LinkSession.state``)::

    disconnected --port opens--> handshake --HELLO_REPLY ok, SET_CONFIG acked--> online
         ^                           |  \\--spec hash differs--> incompatible (retried slowly)
         |                           v
         +-- port lost, read error, silence, board restarted, no HELLO_REPLY --+

The rules (boot delay, handshake, retransmission, keepalive, silence, restart) are the link core's, from
protocol/PROTOCOL.md; this module only opens and reopens the transport, passes bytes and the time to the core,
writes what it gives back, and turns its events into futures, callbacks and log lines. A link problem (port
missing, permission denied, board silent) is logged once when it starts and once when it ends.
"""

from __future__ import annotations

import asyncio
import contextlib
import enum
import logging
import time
from collections.abc import Awaitable, Callable
from dataclasses import asdict, dataclass, field, fields
from typing import Any, Protocol

import numpy as np

from phantom import PhantomError
from phantom.host.transports import TransportLost, TransportUnavailable
from phantom.protocol import ProtocolError
from phantom.protocol.codec import Message
from phantom.protocol.link import (
    Acked,
    BoardInfo,
    BoardRestarted,
    CommandFailed,
    Event,
    FaultIn,
    FrameIn,
    HandshakeDone,
    HandshakeRefused,
    HandshakeTimedOut,
    HostLink,
    LinkCounters,
    LinkTiming,
    Nacked,
    Silence,
    TelemetryIn,
    enum_name,
    fault_names,
)
from phantom.protocol.messages import MESSAGES, PROTOCOL_VERSION, ChamberState, ConfigSource, Status, ZeroSource

__all__ = ["BoardInfo", "CommandRejected", "LinkDown", "LinkSession", "LinkState", "LinkStats",
           "LinkTiming", "Telemetry", "fault_names"]

logger = logging.getLogger(__name__)

_DRIVE_SCALE = {f.name: f.scale for f in MESSAGES["TELEMETRY"].fields}["drive"]

#: The spec hash of the HELLO that ends a session: no firmware has it, so the board answers SPEC_MISMATCH, which
#: closes its session and switches every blower off as VENT does (PROTOCOL.md section 4, step 3). A board without
#: a session has no host deadline, so a daemon that leaves this way does not leave a DEAD_HOST fault behind.
GOODBYE_SPEC_HASH = 0
#: How long (s) :meth:`LinkSession.end_session` waits for the board's answer to that HELLO.
GOODBYE_WAIT_S = 0.5


class LinkState(enum.StrEnum):
    """Where the session is; the value is what ``status`` shows."""

    DISCONNECTED = "disconnected"
    HANDSHAKE = "handshake"
    ONLINE = "online"
    INCOMPATIBLE = "incompatible"
    STOPPED = "stopped"
    #: the daemon's view of a link whose process has not reported for longer than its deadline (host/link_process.py):
    #: what the board does is unknown, and what the process last said is not current
    SILENT = "silent"


class LinkDown(PhantomError):
    """A command could not be delivered: no board is connected, or it never acknowledged."""


class CommandRejected(PhantomError):
    """The board answered NACK; ``status`` is the protocol's status name (e.g. ``FAULT_ACTIVE``)."""

    def __init__(self, command: str, status: str):
        hints = {
            "FAULT_LATCHED": "a fault is latched: clear it first (phantom clear-fault)",
            "FAULT_ACTIVE": "the fault's cause is still present (see faults in phantom status)",
            "BAD_VALUE": "a value is outside its documented range",
            "NO_SESSION": "the board has no session (it reset): the daemon is reconnecting",
        }
        super().__init__(f"the board refused {command}: {status}" + (f" ({hints[status]})" if status in hints else ""))
        self.command = command
        self.status = status


class Transport(Protocol):
    """What the session needs of a transport (``SerialTransport``, ``CanTransport``)."""

    description: str

    async def open(self) -> None: ...

    async def read(self) -> bytes: ...

    def write(self, frame: bytes) -> None: ...

    def close(self) -> None: ...


@dataclass
class Telemetry:
    """One TELEMETRY frame in the daemon's units (Pa, 0..1), with the host time it arrived."""

    host_time_s: float
    board_time_ms: int
    pressures_pa: np.ndarray
    setpoints_pa: np.ndarray
    drive_levels: np.ndarray
    states: list[str]
    fault_flags: int
    board_counters: dict[str, int]


@dataclass
class LinkStats(LinkCounters):
    """Counters of the link since the daemon started: the link core's (frames, retries, round trip), the
    session's connections and losses, and the board's last reported counters. :meth:`as_dict` adds the
    transport's: frames it dropped, and how often it read the port (``port_reads``: each a wake-up of the link's
    thread; None for a transport that does not count them)."""

    connects: int = 0
    reconnects: int = 0
    links_lost: int = 0
    board_counters: dict[str, int] = field(default_factory=dict)

    def as_dict(self, rx_dropped: dict[str, int], tx_dropped: int, port_reads: int | None) -> dict[str, Any]:
        result = asdict(self)
        result["rx_dropped"] = dict(rx_dropped)
        result["bad_frames"] = sum(result["rx_dropped"].values())
        result["tx_dropped"] = tx_dropped
        result["port_reads"] = port_reads
        return result


class _ConnectionEnded(Exception):
    """Raised inside the serving loop to end one connection; ``reason`` is said to people."""


class LinkSession:
    """One board behind one transport, kept connected for as long as the session runs.

    Parameters
    ----------
    transport : SerialTransport or CanTransport
        Opened, read and closed by the session (reopened after a loss).
    timing : LinkTiming
        Timeouts and periods (the link core's).
    on_telemetry : callable(Telemetry), optional
        Called for every telemetry frame.
    on_event : callable(kind: str, text: str, level: str), optional
        Link events for people: connected, lost, reset cause, faults, incompatible firmware.
    on_online : coroutine function(BoardInfo, reconnected: bool), optional
        Awaited each time the link comes up (the daemon restores its setpoints); ``online_event`` is set after.
    clock : callable() -> float, optional
        The monotonic clock in seconds (``time.monotonic``).
    on_motion : callable(Message), optional
        Called for every MOTION_STATUS and MOTION_INFO frame (the scanner's axes).
    """

    def __init__(self, transport: Transport, timing: LinkTiming | None = None,
                 on_telemetry: Callable[[Telemetry], None] | None = None,
                 on_event: Callable[[str, str, str], None] | None = None,
                 on_online: Callable[[BoardInfo, bool], Awaitable[None]] | None = None,
                 clock: Callable[[], float] = time.monotonic,
                 on_motion: Callable[[Message], None] | None = None):
        self.transport = transport
        self.timing = timing or LinkTiming()
        self.on_telemetry: Callable[[Telemetry], None] = on_telemetry or (lambda telemetry: None)
        self.on_event: Callable[[str, str, str], None] = on_event or (lambda kind, text, level: None)
        self.on_online = on_online
        self.on_motion: Callable[[Message], None] = on_motion or (lambda message: None)
        self.clock = clock
        self.state = LinkState.DISCONNECTED
        self.board: BoardInfo | None = None
        #: what the board's BOARD_INFO said after the handshake: where its settings and zeros came from
        self.board_details: dict[str, Any] | None = None
        self.last_error: str | None = None
        self._host_stats = LinkStats()
        self.link = HostLink(self.timing)
        self.online_event = asyncio.Event()
        self._futures: dict[int, asyncio.Future[str]] = {}
        self._config_seq: int | None = None
        self._stopping = False
        #: the keepalive held back while the daemon is silent (host/link_child.py): the board then vents
        self._keepalive_withheld = False
        self._lost_at: float | None = None
        #: when the board's bytes last arrived (the outage after a loss is counted from then)
        self._heard_at: float | None = None
        self._serving: asyncio.Task[None] | None = None
        self._wake = asyncio.Event()
        #: the link core's deadline :meth:`_serve` sleeps until (None: none)
        self._sleeping_until: float | None = None
        self._bringing_online: asyncio.Task[None] | None = None
        self._problem: tuple[str, float] | None = None
        self._goodbye: asyncio.Future[str] | None = None

    # --- public -----------------------------------------------------------------------------------------

    async def run(self) -> None:
        """Connect, serve, and reconnect after every loss, until :meth:`stop`."""
        while not self._stopping:
            try:
                await self.transport.open()
            except TransportUnavailable as error:
                self._set_state(LinkState.DISCONNECTED, str(error))
                self._problem_started(str(error))
                await asyncio.sleep(self.timing.reconnect_s)
                continue
            wait_s = self.timing.reconnect_s
            self._serving = asyncio.create_task(self._serve())
            try:
                await self._serving
            except asyncio.CancelledError:
                if not self._stopping:
                    raise
            except (TransportLost, LinkDown, _ConnectionEnded) as error:
                self._lose(str(error))
            except ProtocolError as error:
                if self.last_error != str(error):  # said once; the state stays until the board changes
                    self.on_event("incompatible", str(error), "ERROR")
                self._set_state(LinkState.INCOMPATIBLE, str(error))
                self._problem_started(str(error))
                wait_s = self.timing.incompatible_retry_s
            finally:
                self.transport.close()
                self._end_connection(LinkDown(f"the link to the board is {self.state.value}"))
            if not self._stopping:
                await asyncio.sleep(wait_s)
        self._set_state(LinkState.STOPPED, None)

    def stop(self) -> None:
        """Make :meth:`run` return after closing the port."""
        self._stopping = True
        if self._serving is not None:
            self._serving.cancel()

    @property
    def online(self) -> bool:
        return self.state is LinkState.ONLINE

    @property
    def keepalive_withheld(self) -> bool:
        """Whether :meth:`withhold_keepalive` holds the keepalive back."""
        return self._keepalive_withheld

    def withhold_keepalive(self, withheld: bool) -> None:
        """Hold back the keepalive (the board latches DEAD_HOST at its deadline and vents), or give it back."""
        self._keepalive_withheld = withheld
        self.link.keepalive = self.online and not withheld
        self._wake.set()  # the core's deadlines changed

    async def end_session(self) -> bool:
        """End the board's session before the daemon leaves: a HELLO with :data:`GOODBYE_SPEC_HASH`, which the
        board refuses (closing its session and venting), so that it does not latch DEAD_HOST once the daemon is
        gone. True when the board answered within :data:`GOODBYE_WAIT_S`."""
        if not self.online:
            return False
        self._goodbye = asyncio.get_running_loop().create_future()
        try:
            self.link.send("HELLO", {"protocol_version": PROTOCOL_VERSION, "spec_hash": GOODBYE_SPEC_HASH},
                           self.clock())
            self._flush()
            await asyncio.wait_for(asyncio.shield(self._goodbye), GOODBYE_WAIT_S)
        except (TimeoutError, TransportLost, ProtocolError):
            return False
        finally:
            self._goodbye = None
        self.link.keepalive = False  # the board has no session left to keep
        return True

    async def command(self, name: str, fields: dict[str, Any] | None = None) -> str:
        """Send an acknowledged command and wait for its ACK; return the ACK's status name (OK, CLAMPED).

        Raises
        ------
        LinkDown
            Not online, or no ACK after every retransmission.
        CommandRejected
            The board answered NACK.
        """
        if not self.online:
            raise LinkDown(f"no board: the link is {self.state.value}" + (f" ({self.last_error})"
                                                                          if self.last_error else ""))
        return await self._command(name, fields or {})

    def status(self) -> dict[str, Any]:
        """The link's state, board and counters, JSON-ready."""
        return {
            "state": self.state.value,
            "transport": self.transport.description,
            "board": asdict(self.board) if self.board else None,
            "board_info": self.board_details,
            "last_error": self.last_error,
            "stats": self.stats.as_dict(self.rx_dropped(), getattr(self.transport, "tx_dropped", 0),
                                        getattr(self.transport, "reads", None)),
        }

    def rx_dropped(self) -> dict[str, int]:
        """Frames from the board dropped since the daemon started, by reason (bad CRC, length, id, COBS,
        overflow)."""
        return self.link.rx_dropped()

    @property
    def stats(self) -> LinkStats:
        """The session's counters (connects, losses) with the link core's (frames, retries, round trip)."""
        for counter in fields(LinkCounters):
            setattr(self._host_stats, counter.name, getattr(self.link.counters, counter.name))
        return self._host_stats

    # --- the connection ---------------------------------------------------------------------------------

    async def _serve(self) -> None:
        """One connection: boot delay, handshake, configure, then pass bytes and time until it ends.

        The board's bytes are handled as they arrive, by :meth:`_receive`; this loop wakes for the link core's
        deadlines (keepalive, retransmission, silence) and new commands only. (A task and an ``asyncio.wait`` per
        read cost about five turns of the loop for every frame.)"""
        self._set_state(LinkState.HANDSHAKE, None)
        self.link.open(self.clock())
        receiving = asyncio.create_task(self._receive())
        waking: asyncio.Task[bool] | None = None
        try:
            while True:
                self._flush()
                if waking is None:
                    self._wake.clear()
                    waking = asyncio.create_task(self._wake.wait())
                self._sleeping_until = self.link.next_deadline()
                timeout_s = None if self._sleeping_until is None else max(0.0, self._sleeping_until - self.clock())
                done, _ = await asyncio.wait({receiving, waking}, timeout=timeout_s,
                                             return_when=asyncio.FIRST_COMPLETED)
                if receiving in done:
                    receiving.result()  # raises what ended the connection (TransportLost when the port went away)
                if waking in done:
                    waking = None
                for event in self.link.poll(self.clock()):
                    self._handle(event)
        finally:
            for task in (receiving, waking, self._bringing_online):
                if task is not None and not task.done():
                    task.cancel()
                    with contextlib.suppress(asyncio.CancelledError, Exception):
                        await task

    async def _receive(self) -> None:
        """Hand the board's bytes to the link core as they arrive, act on its events and send its answers; wake
        :meth:`_serve` when the core's next deadline came earlier than the one it sleeps until (a command to
        acknowledge after the handshake, the keepalive once online). Runs until the connection ends: it raises
        what ended it."""
        while True:
            data = await self.transport.read()
            self._heard_at = self.clock()
            for event in self.link.receive(data, self._heard_at):
                self._handle(event)
            self._flush()
            deadline = self.link.next_deadline()
            if deadline is not None and (self._sleeping_until is None or deadline < self._sleeping_until):
                self._wake.set()

    def _flush(self) -> None:
        for frame in self.link.take_output():
            self.transport.write(frame)

    def _handle(self, event: Event) -> None:
        """Act on one event of the link core."""
        if isinstance(event, FrameIn) and event.message.name in ("MOTION_STATUS", "MOTION_INFO"):
            self.on_motion(event.message)
        elif isinstance(event, TelemetryIn):
            self._on_telemetry_frame(event)
        elif isinstance(event, FrameIn):
            self._on_frame(event)
        elif isinstance(event, HandshakeDone):
            self.board = event.board
            self._config_seq = self.link.command("SET_CONFIG", {
                "telemetry_period_ms": self.timing.telemetry_period_ms,
                "host_deadline_ms": self.timing.host_deadline_ms}, self.clock())
        elif isinstance(event, HandshakeRefused):
            raise ProtocolError(event.error)
        elif isinstance(event, HandshakeTimedOut):
            raise LinkDown(f"no HELLO_REPLY from {self.transport.description} after {event.attempts} HELLOs: is it "
                           "the phantom's board, running its firmware?")
        elif isinstance(event, (Acked, Nacked, CommandFailed)):
            self._answer(event)
        elif isinstance(event, FaultIn):
            fields = event.message.fields
            pressures_kpa = ", ".join(f"{p / 1000:.2f}" for p in fields["pressure_pa"])
            self.on_event("fault", f"fault latched: {event.bit_name} (all: {', '.join(fault_names(event.fault_flags))};"
                          f" pressures {pressures_kpa} kPa); blowers stopped until cleared", "ERROR")
        elif isinstance(event, BoardRestarted):
            raise _ConnectionEnded(f"the board restarted (its clock went back from {event.earlier_ms} to "
                                   f"{event.now_ms} ms)")
        elif isinstance(event, Silence):
            raise _ConnectionEnded(event.reason)

    def _on_frame(self, event: FrameIn) -> None:
        """The frames the link core hands on without an event of their own: BOARD_INFO, and the board's answer to
        the goodbye HELLO."""
        message = event.message
        if message.name == "BOARD_INFO":
            fields = message.fields
            self.board_details = {
                "config_source": _wire_name(ConfigSource, fields["config_source"]),
                "zero_source": [_wire_name(ZeroSource, value) for value in fields["zero_source"]],
                "zero_offset_kpa": [value / 1e3 for value in fields["zero_offset_pa"]],
                "supply_mv": fields["supply_mv"]}
        elif (message.name == "HELLO_REPLY" and self._goodbye is not None and not self._goodbye.done()
              and message.fields["status"] == Status.SPEC_MISMATCH):
            self._goodbye.set_result("closed")

    def _answer(self, event: Acked | Nacked | CommandFailed) -> None:
        """An acknowledged command is answered (or given up): resolve its future, or go online after
        SET_CONFIG."""
        if event.seq == self._config_seq:
            self._config_seq = None
            if not isinstance(event, Acked):
                reason = "refused" if isinstance(event, Nacked) else "not acknowledged"
                raise LinkDown(f"SET_CONFIG was {reason} by the board")
            self._go_online()
            return
        future = self._futures.pop(event.seq, None)
        if future is None or future.done():
            return
        if isinstance(event, Acked):
            future.set_result(event.status)
        elif isinstance(event, Nacked):
            future.set_exception(CommandRejected(event.name, event.status))
        else:
            future.set_exception(LinkDown(f"{event.name} was not acknowledged after {event.attempts} attempts"))

    def _go_online(self) -> None:
        reconnected = self.stats.connects > 0
        self.stats.connects += 1
        if reconnected:
            self.stats.reconnects += 1
        self._set_state(LinkState.ONLINE, None)
        self._problem_ended()
        self._announce(reconnected)
        self.link.keepalive = not self._keepalive_withheld
        self._bringing_online = asyncio.create_task(self._bring_online(reconnected))

    async def _bring_online(self, reconnected: bool) -> None:
        """Let the daemon restore its state, then tell waiters the link is up."""
        if self.on_online is not None and self.board is not None:
            try:
                await self.on_online(self.board, reconnected)
            except (PhantomError, TimeoutError) as error:
                logger.warning("restoring the board's state after connecting failed: %s", error)
            except Exception:
                logger.exception("restoring the board's state after connecting failed")
        self.online_event.set()

    def _on_telemetry_frame(self, event: TelemetryIn) -> None:
        fields = event.message.fields
        counters = {key: fields[key] for key in ("rx_bad_crc", "rx_overflow", "rx_bad_frame", "tx_dropped",
                                                 "tick_overruns")}
        self.stats.board_counters = counters
        self.on_telemetry(Telemetry(
            host_time_s=self.clock(), board_time_ms=fields["time_ms"],
            pressures_pa=np.asarray(fields["pressure_pa"], dtype=float),
            setpoints_pa=np.asarray(fields["setpoint_pa"], dtype=float),
            drive_levels=np.asarray(fields["drive"], dtype=float) * _DRIVE_SCALE,
            states=[enum_name(ChamberState, state) for state in fields["state"]],
            fault_flags=fields["fault_flags"], board_counters=counters))

    def _announce(self, reconnected: bool) -> None:
        """Tell people the link is up: board, firmware, reset cause, latched faults."""
        board = self.board
        assert board is not None
        text = (f"board {board.board} firmware {board.firmware_version} on {self.transport.description}, "
                f"reset cause {board.reset_cause}")
        if reconnected and self._lost_at is not None:
            text = f"link restored after {self.clock() - self._lost_at:.1f} s: {text}"
        else:
            text = f"link up: {text}"
        self.on_event("reconnected" if reconnected else "connected", text, "WARN" if reconnected else "INFO")
        if board.fault_flags:
            self.on_event("fault", f"faults latched on the board: {', '.join(fault_names(board.fault_flags))}",
                          "ERROR")

    def _lose(self, reason: str) -> None:
        """The link went away: count it, remember when, tell people once."""
        was_online = self.state is LinkState.ONLINE
        self._set_state(LinkState.DISCONNECTED, reason)
        self._problem_started(reason)
        if was_online:
            self.stats.links_lost += 1
            # from the board's last word: a loss found late (the board silent for 1 s, the link's process stopped
            # for seconds and its silence seen once it ran again) lasted from then, not from its finding
            self._lost_at = self._heard_at if self._heard_at is not None else self.clock()
            self.on_event("link_lost", f"link lost: {reason}", "WARN")

    def _problem_started(self, text: str) -> None:
        """Log a link problem once when it starts (not at every retry); a different problem is logged too."""
        kind = _problem_kind(text)
        if self._problem is not None and self._problem[0] == kind:
            return
        self._problem = (kind, self.clock())
        logger.warning("board link problem: %s", text)

    def _problem_ended(self) -> None:
        if self._problem is None:
            return
        kind, since = self._problem
        self._problem = None
        logger.info("board link problem over after %.1f s (was: %s): online", self.clock() - since, kind)

    def _set_state(self, state: LinkState, error: str | None) -> None:
        self.state = state
        if error is not None or state is LinkState.ONLINE:
            self.last_error = error

    def _end_connection(self, error: Exception) -> None:
        self.online_event.clear()
        self.link.keepalive = False
        self._config_seq = None
        for future in self._futures.values():
            if not future.done():
                future.set_exception(error)
        self._futures.clear()

    # --- commands ---------------------------------------------------------------------------------------

    async def _command(self, name: str, fields: dict[str, Any]) -> str:
        """Hand the command to the link core and wait for its answer; see :meth:`command`."""
        future: asyncio.Future[str] = asyncio.get_running_loop().create_future()
        try:
            seq = self.link.command(name, fields, self.clock())
            self._flush()
        except TransportLost as error:
            raise LinkDown(f"{name} not sent: {error}") from error
        self._futures[seq] = future
        self._wake.set()  # the core has a new deadline
        return await future


def _wire_name(table: type[ConfigSource] | type[ZeroSource], value: int) -> str:
    """The name of a wire value in one of BOARD_INFO's enums, or the number as text if the spec has none."""
    try:
        return table(value).name
    except ValueError:
        return str(value)


def _problem_kind(text: str) -> str:
    """A short name for a link problem, so that a retry that fails the same way is not logged again."""
    lowered = text.lower()
    for kind, words in (("port missing", ("does not exist",)), ("permission denied", ("permission denied",)),
                        ("board silent", ("no frame", "no hello_reply", "no telemetry", "not acknowledged")),
                        ("incompatible firmware", ("protocol mismatch",)), ("board restarted", ("restarted",))):
        if any(word in lowered for word in words):
            return kind
    return lowered.split(":")[0]
