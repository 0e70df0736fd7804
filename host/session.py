"""The link session with a board: handshake, acknowledged commands, keepalive, telemetry, reconnection.

State machine (``LinkSession.state``)::

    disconnected --port opens--> handshake --HELLO_REPLY ok, SET_CONFIG acked--> online
         ^                           |  \\--spec hash differs--> incompatible (retried slowly)
         |                           v
         +------ port lost, read error, silence, no HELLO_REPLY ------+

Rules (protocol/PROTOCOL.md): a command with ``acked = true`` is retransmitted with the same seq after
``ack_timeout_s``, doubling each time, ``command_attempts`` times in all; setpoints are absolute, so a
repeat is harmless. A PING goes out every ``keepalive_s`` while online, well inside the board's dead-host
deadline, and its PONG gives the round-trip time. No frame at all for ``silence_s`` (telemetry streams at
50 Hz) means the board is gone: the session closes the port and reconnects by itself, and reports the
reset cause the board gives in its next HELLO_REPLY.
"""

from __future__ import annotations

import asyncio
import contextlib
import enum
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field

import numpy as np

from phantom import PhantomError
from phantom.host.transports import TransportLost, TransportUnavailable
from phantom.protocol import ProtocolError
from phantom.protocol.codec import FrameReader, Message, check_hello_reply, encode
from phantom.protocol.messages import BITS, ENUMS, MESSAGES, PROTOCOL_VERSION, SPEC_HASH


class LinkState(enum.StrEnum):
    """Where the session is; the value is what ``status`` shows."""

    DISCONNECTED = "disconnected"
    HANDSHAKE = "handshake"
    ONLINE = "online"
    INCOMPATIBLE = "incompatible"
    STOPPED = "stopped"


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


def _names(table: dict[str, int]) -> dict[int, str]:
    return {value: name for name, value in table.items()}


STATUS_NAMES = _names(ENUMS["status"])
RESET_CAUSE_NAMES = _names(ENUMS["reset_cause"])
BOARD_NAMES = _names(ENUMS["board"])
CHAMBER_STATE_NAMES = _names(ENUMS["chamber_state"])
FAULT_BIT_NAMES = _names(BITS["fault"])
_DRIVE_SCALE = {f.name: f.scale for f in MESSAGES["TELEMETRY"].fields}["drive"]


#: How far the board's clock may seem to go back between frames (ms): a telemetry frame carries the time its
#: control tick was sampled, which can precede a PONG sent just before the frame.
BOARD_CLOCK_JITTER_MS = 100
#: FrameReader counters of frames dropped on receipt.
RX_DROP_COUNTERS = ("bad_crc", "bad_length", "unknown_id", "bad_cobs", "overflow")


def fault_names(fault_flags: int) -> list[str]:
    """The names of the set bits of a fault bit set (``bits.fault`` in the spec), low bit first."""
    return [FAULT_BIT_NAMES.get(bit, f"BIT{bit}") for bit in range(16) if fault_flags >> bit & 1]


@dataclass(frozen=True)
class LinkTiming:
    """Timeouts and periods of the session, in wall-clock seconds (board-side periods in ms).

    With a simulated board running faster than real time, the board's deadlines pass faster: the
    daemon divides the keepalive period by the speed-up.
    """

    ack_timeout_s: float = 0.1
    command_attempts: int = 4
    keepalive_s: float = 0.1
    silence_s: float = 1.0
    hello_timeout_s: float = 0.2
    hello_attempts: int = 10
    reconnect_s: float = 0.2
    incompatible_retry_s: float = 5.0
    telemetry_period_ms: int = 20
    host_deadline_ms: int = 500


@dataclass
class BoardInfo:
    """What the board said in its HELLO_REPLY."""

    protocol_version: int
    spec_hash: int
    firmware_version: str
    board: str
    chamber_count: int
    reset_cause: str
    fault_flags: int


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
    board_counters: dict


@dataclass
class LinkStats:
    """Counters of the link since the daemon started (host side) and the board's last reported ones."""

    frames_rx: int = 0
    frames_tx: int = 0
    retries: int = 0
    commands_failed: int = 0
    nacks: int = 0
    pings: int = 0
    rtt_ms: float | None = None
    rtt_ms_mean: float | None = None
    connects: int = 0
    reconnects: int = 0
    links_lost: int = 0
    board_counters: dict = field(default_factory=dict)

    def as_dict(self, rx_dropped: dict, tx_dropped: int) -> dict:
        result = asdict(self)
        result["rx_dropped"] = dict(rx_dropped)
        result["bad_frames"] = sum(result["rx_dropped"].values())
        result["tx_dropped"] = tx_dropped
        return result


def _host_time_ms() -> int:
    return int(time.monotonic() * 1000) & 0xFFFFFFFF


class LinkSession:
    """One board behind one transport, kept connected for as long as the session runs.

    Parameters
    ----------
    transport : SerialTransport or CanTransport
        Opened, read and closed by the session (reopened after a loss).
    timing : LinkTiming
        Timeouts and periods.
    on_telemetry : callable(Telemetry), optional
        Called for every telemetry frame.
    on_event : callable(kind: str, text: str, level: str), optional
        Link events for people: connected, lost, reset cause, faults, incompatible firmware.
    on_online : coroutine function(BoardInfo, reconnected: bool), optional
        Awaited each time the link comes up, before keepalive starts (the daemon restores its setpoints).
    """

    def __init__(self, transport, timing: LinkTiming = LinkTiming(), on_telemetry: Callable | None = None,
                 on_event: Callable | None = None, on_online: Callable | None = None):
        self.transport = transport
        self.timing = timing
        self.on_telemetry = on_telemetry or (lambda telemetry: None)
        self.on_event = on_event or (lambda kind, text, level: None)
        self.on_online = on_online
        self.state = LinkState.DISCONNECTED
        self.board: BoardInfo | None = None
        self.last_error: str | None = None
        self.stats = LinkStats()
        self.reader = FrameReader()
        self.online_event = asyncio.Event()
        self._seq = 0
        self._pending: dict[tuple[int, int], asyncio.Future] = {}
        self._hello_reply: asyncio.Future | None = None
        self._stopping = False
        self._lost_at: float | None = None
        self._serving: asyncio.Task | None = None
        self._pings_sent: dict[int, float] = {}
        self._rx_dropped_before = dict.fromkeys(RX_DROP_COUNTERS, 0)
        self._board_time_ms: int | None = None
        self._board_clock_went_back: tuple[int, int] | None = None
        self._last_telemetry_s = 0.0

    # --- public -----------------------------------------------------------------------------------------

    async def run(self) -> None:
        """Connect, serve, and reconnect after every loss, until :meth:`stop`."""
        while not self._stopping:
            try:
                await self.transport.open()
            except TransportUnavailable as error:
                self._set_state(LinkState.DISCONNECTED, str(error))
                await asyncio.sleep(self.timing.reconnect_s)
                continue
            wait_s = self.timing.reconnect_s
            self._serving = asyncio.create_task(self._serve())
            try:
                await self._serving
            except asyncio.CancelledError:
                if not self._stopping:
                    raise
            except (TransportLost, LinkDown) as error:
                self._lose(str(error))
            except ProtocolError as error:
                if self.last_error != str(error):  # said once; the state stays until the board changes
                    self.on_event("incompatible", str(error), "ERROR")
                self._set_state(LinkState.INCOMPATIBLE, str(error))
                wait_s = self.timing.incompatible_retry_s
            finally:
                self.transport.close()
                self._fail_pending(LinkDown(f"the link to the board is {self.state.value}"))
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

    async def command(self, name: str, fields: dict | None = None) -> str:
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

    def status(self) -> dict:
        """The link's state, board and counters, JSON-ready."""
        return {
            "state": self.state.value,
            "transport": self.transport.description,
            "board": asdict(self.board) if self.board else None,
            "last_error": self.last_error,
            "stats": self.stats.as_dict(self.rx_dropped(), getattr(self.transport, "tx_dropped", 0)),
        }

    def rx_dropped(self) -> dict:
        """Frames from the board dropped since the daemon started, by reason (bad CRC, length, id, COBS,
        overflow)."""
        return {name: self._rx_dropped_before[name] + getattr(self.reader, name) for name in RX_DROP_COUNTERS}

    # --- the connection ---------------------------------------------------------------------------------

    async def _serve(self) -> None:
        """One connection: handshake, configure, then keepalive until the reader loop ends."""
        # a fresh reader: a partial frame left by the last connection must not swallow the first reply
        for name in RX_DROP_COUNTERS:
            self._rx_dropped_before[name] += getattr(self.reader, name)
        self.reader = FrameReader()
        self._board_time_ms, self._board_clock_went_back = None, None
        self._set_state(LinkState.HANDSHAKE, None)
        reading = asyncio.create_task(self._read_loop())
        keepalive = None
        try:
            self.board = await self._handshake(reading)
            await self._command("SET_CONFIG", {"telemetry_period_ms": self.timing.telemetry_period_ms,
                                               "host_deadline_ms": self.timing.host_deadline_ms})
            reconnected = self.stats.connects > 0
            self.stats.connects += 1
            if reconnected:
                self.stats.reconnects += 1
            self._last_telemetry_s = time.monotonic()
            self._set_state(LinkState.ONLINE, None)
            self._announce(reconnected)
            keepalive = asyncio.create_task(self._keepalive())
            if self.on_online is not None:
                await self.on_online(self.board, reconnected)
            self.online_event.set()
            await reading
        finally:
            self.online_event.clear()
            for task in (reading, keepalive):
                if task is not None and not task.done():
                    task.cancel()
                    with contextlib.suppress(asyncio.CancelledError, Exception):
                        await task

    async def _handshake(self, reading: asyncio.Task) -> BoardInfo:
        """Send HELLO until HELLO_REPLY comes; check the spec hash; return the board's description."""
        loop = asyncio.get_running_loop()
        for _ in range(self.timing.hello_attempts):
            self._hello_reply = loop.create_future()
            self._send("HELLO", {"protocol_version": PROTOCOL_VERSION, "spec_hash": SPEC_HASH})
            done, _ = await asyncio.wait({self._hello_reply, reading}, timeout=self.timing.hello_timeout_s,
                                         return_when=asyncio.FIRST_COMPLETED)
            if reading in done:
                reading.result()
                raise TransportLost("the port closed during the handshake")
            if self._hello_reply in done:
                reply = self._hello_reply.result()
                check_hello_reply(reply)
                fields = reply.fields
                return BoardInfo(
                    protocol_version=fields["protocol_version"], spec_hash=fields["spec_hash"],
                    firmware_version=f"{fields['firmware_major']}.{fields['firmware_minor']}."
                                     f"{fields['firmware_patch']}",
                    board=BOARD_NAMES.get(fields["board"], str(fields["board"])),
                    chamber_count=fields["chamber_count"],
                    reset_cause=RESET_CAUSE_NAMES.get(fields["reset_cause"], str(fields["reset_cause"])),
                    fault_flags=fields["fault_flags"])
        raise LinkDown(f"no HELLO_REPLY from {self.transport.description} after {self.timing.hello_attempts} "
                       "HELLOs: is it the phantom's board, running its firmware?")

    def _announce(self, reconnected: bool) -> None:
        """Tell people the link is up: board, firmware, reset cause, latched faults."""
        board = self.board
        text = (f"board {board.board} firmware {board.firmware_version} on {self.transport.description}, "
                f"reset cause {board.reset_cause}")
        if reconnected and self._lost_at is not None:
            text = f"link restored after {time.monotonic() - self._lost_at:.1f} s: {text}"
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
        if was_online:
            self.stats.links_lost += 1
            self._lost_at = time.monotonic()
            self.on_event("link_lost", f"link lost: {reason}", "WARN")

    def _set_state(self, state: LinkState, error: str | None) -> None:
        self.state = state
        if error is not None or state is LinkState.ONLINE:
            self.last_error = error

    async def _keepalive(self) -> None:
        """PING every keepalive period: keeps the board's dead-host deadline away and measures latency."""
        while True:
            host_time_ms = _host_time_ms()
            if not self.online:
                return
            # the wire carries whole milliseconds; the send time is kept here for a sub-millisecond round trip
            self._pings_sent[host_time_ms] = time.perf_counter()
            while len(self._pings_sent) > 64:
                self._pings_sent.pop(next(iter(self._pings_sent)))
            try:
                self._send("PING", {"host_time_ms": host_time_ms})
            except TransportLost:
                return  # the read loop sees the loss too and ends the connection
            self.stats.pings += 1
            await asyncio.sleep(self.timing.keepalive_s)

    async def _read_loop(self) -> None:
        """Read frames and dispatch them; raise TransportLost on a loss or a silent board."""
        while True:
            # asyncio.timeout, not wait_for: in Python 3.11 wait_for can swallow a cancellation that arrives as
            # the read completes, and then closing the session would wait forever
            try:
                async with asyncio.timeout(self.timing.silence_s):
                    data = await self.transport.read()
            except TimeoutError:
                raise TransportLost(f"no frame from the board for {self.timing.silence_s:g} s") from None
            for message in self.reader.feed(data):
                self.stats.frames_rx += 1
                self._dispatch(message)
            self._check_board_alive()

    def _check_board_alive(self) -> None:
        """A board that restarted without its port closing (watchdog, reset button) has no session: it still
        answers PING, but its clock went back and its telemetry stopped. Either ends the connection, so the
        session handshakes again and learns the reset cause."""
        if self._board_clock_went_back is not None:
            earlier_ms, now_ms = self._board_clock_went_back
            self._board_clock_went_back = None
            raise TransportLost(f"the board restarted (its clock went back from {earlier_ms} to {now_ms} ms)")
        if (self.state is LinkState.ONLINE and self.timing.telemetry_period_ms > 0
                and time.monotonic() - self._last_telemetry_s > self.timing.silence_s):
            raise TransportLost(f"no telemetry from the board for {self.timing.silence_s:g} s (it lost its session)")

    def _board_clock(self, board_time_ms: int) -> None:
        """Track the board's clock (ms since it started); note when it goes back by more than the jitter
        between a telemetry frame's sample time and a PONG sent just before it."""
        if self._board_time_ms is not None and board_time_ms + BOARD_CLOCK_JITTER_MS < self._board_time_ms:
            self._board_clock_went_back = (self._board_time_ms, board_time_ms)
        self._board_time_ms = board_time_ms

    def _dispatch(self, message: Message) -> None:
        """Route one message from the board."""
        name, fields = message.name, message.fields
        if name == "HELLO_REPLY":
            if self._hello_reply is not None and not self._hello_reply.done():
                self._hello_reply.set_result(message)
        elif name in ("ACK", "NACK"):
            future = self._pending.get((fields["ref_msg_id"], fields["ref_seq"]))
            if future is not None and not future.done():
                future.set_result(message)
        elif name == "PONG":
            sent = self._pings_sent.pop(fields["host_time_ms"], None)
            if sent is None:
                return
            rtt_ms = 1e3 * (time.perf_counter() - sent)
            self.stats.rtt_ms = rtt_ms
            self._board_clock(fields["board_time_ms"])
            mean = self.stats.rtt_ms_mean
            self.stats.rtt_ms_mean = rtt_ms if mean is None else 0.9 * mean + 0.1 * rtt_ms
        elif name == "TELEMETRY":
            self._last_telemetry_s = time.monotonic()
            self._board_clock(fields["time_ms"])
            counters = {key: fields[key] for key in ("rx_bad_crc", "rx_overflow", "rx_bad_frame", "tx_dropped",
                                                     "tick_overruns")}
            self.stats.board_counters = counters
            self.on_telemetry(Telemetry(
                host_time_s=time.monotonic(), board_time_ms=fields["time_ms"],
                pressures_pa=np.asarray(fields["pressure_pa"], dtype=float),
                setpoints_pa=np.asarray(fields["setpoint_pa"], dtype=float),
                drive_levels=np.asarray(fields["drive"], dtype=float) * _DRIVE_SCALE,
                states=[CHAMBER_STATE_NAMES.get(state, str(state)) for state in fields["state"]],
                fault_flags=fields["fault_flags"], board_counters=counters))
        elif name == "FAULT":
            self._board_clock(fields["time_ms"])
            bit = fields["fault_bit"]
            pressures_kpa = ", ".join(f"{p / 1000:.2f}" for p in fields["pressure_pa"])
            self.on_event("fault", f"fault latched: {FAULT_BIT_NAMES.get(bit, bit)} (all: "
                          f"{', '.join(fault_names(fields['fault_flags']))}; pressures {pressures_kpa} kPa); blowers "
                          "stopped until cleared", "ERROR")

    # --- frames -----------------------------------------------------------------------------------------

    def _next_seq(self) -> int:
        self._seq = (self._seq + 1) & 0xFF
        return self._seq

    def _send(self, name: str, fields: dict, seq: int | None = None) -> int:
        seq = self._next_seq() if seq is None else seq
        self.transport.write(encode(name, seq, fields))
        self.stats.frames_tx += 1
        return seq

    async def _command(self, name: str, fields: dict) -> str:
        """Send with retransmission and backoff until ACK or NACK; see :meth:`command`."""
        msg_id = MESSAGES[name].msg_id
        seq = self._next_seq()
        future = asyncio.get_running_loop().create_future()
        key = (msg_id, seq)
        self._pending[key] = future
        timeout_s = self.timing.ack_timeout_s
        try:
            for attempt in range(self.timing.command_attempts):
                if attempt:
                    self.stats.retries += 1
                self._send(name, fields, seq)
                try:
                    async with asyncio.timeout(timeout_s):
                        reply = await asyncio.shield(future)
                    break
                except TimeoutError:
                    timeout_s *= 2
            else:
                self.stats.commands_failed += 1
                raise LinkDown(f"{name} was not acknowledged after {self.timing.command_attempts} attempts")
        finally:
            self._pending.pop(key, None)
        status = STATUS_NAMES.get(reply.fields["status"], str(reply.fields["status"]))
        if reply.name == "NACK":
            self.stats.nacks += 1
            raise CommandRejected(name, status)
        return status

    def _fail_pending(self, error: Exception) -> None:
        for future in self._pending.values():
            if not future.done():
                future.set_exception(error)
        self._pending.clear()
        if self._hello_reply is not None and not self._hello_reply.done():
            self._hello_reply.cancel()
