"""The host's side of the link, without I/O: bytes and the time go in, events and frames to send come out.

One :class:`HostLink` holds every rule of PROTOCOL.md that the host keeps: the boot delay after a port opens,
the handshake (HELLO repeated until HELLO_REPLY, the spec-hash check), sequence numbers, matching ACK and
NACK to their command, retransmission with backoff, the keepalive PING and its round trip, and what tells the
host that the board is gone (silence) or restarted (its clock went back). It never reads a clock, sleeps or
touches a port: a driver (``phantom.host.session`` with asyncio, ``phantom.hil.link`` with a thread, a test
with a number) calls :meth:`HostLink.receive` with the bytes it read, :meth:`HostLink.poll` at
:meth:`HostLink.next_deadline`, and writes what :meth:`HostLink.take_output` returns, one wire frame each.

:class:`BoardPeer` is the other end, for the tests and benches that stand in for a board: it decodes the
host's frames, keeps the board's seq counter, and builds the board's answers.

Times are seconds on whatever monotonic clock the driver uses (a simulated board running faster than real
time can be driven on its own clock: the driver scales the time it passes in).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from phantom.protocol.codec import FrameReader, Message, check_hello_reply, encode
from phantom.protocol.errors import ProtocolError
from phantom.protocol.messages import (
    CONSTANTS,
    MESSAGES,
    PROTOCOL_VERSION,
    SPEC_HASH,
    Board,
    ChamberState,
    Fault,
    MsgId,
    ResetCause,
    Status,
)

#: How far the board's clock may seem to go back between frames (ms): a telemetry frame carries the time its
#: control tick was sampled, which can precede a PONG sent just before the frame.
BOARD_CLOCK_JITTER_MS = 100
#: FrameReader counters of frames dropped on receipt.
RX_DROP_COUNTERS = ("bad_crc", "bad_length", "unknown_id", "bad_cobs", "overflow")
#: Boot delay by board (s): after an Optiboot reset (Uno) the firmware starts about 1.0 s later (measured in
#: simavr with Debian's Optiboot 4.4), so 1.5 s leaves a margin; the Mega's stk500v2 bootloader starts it after
#: about 0.8 s but stays in its loop while bytes arrive; the simulated board does not reset when its port opens.
BOOT_DELAY_S = {"uno": 1.5, "mega": 2.0, "sim": 0.0}
#: Pings remembered for their round trip; older ones are forgotten (their PONG was lost).
_PINGS_REMEMBERED = 64


def board_clock_went_back(earlier_ms: int, later_ms: int) -> bool:
    """Whether the board's clock went back from ``earlier_ms`` to ``later_ms`` by more than its jitter between
    frames (:data:`BOARD_CLOCK_JITTER_MS`): the board restarted in between."""
    return later_ms + BOARD_CLOCK_JITTER_MS < earlier_ms


def enum_name(table: type[Status] | type[ResetCause] | type[Board] | type[ChamberState], value: int) -> str:
    """The name of a wire value in one of the spec's enums, or the number as text if the spec has none."""
    try:
        return table(value).name
    except ValueError:
        return str(value)


def fault_names(fault_flags: int) -> list[str]:
    """The names of the set bits of a fault bit set (``bits.fault`` in the spec), low bit first."""
    known = {flag.value: flag.name for flag in Fault}
    return [known.get(1 << bit) or f"BIT{bit}" for bit in range(16) if fault_flags >> bit & 1]


def board_host_deadline_ms(wall_ms: float, speed: float) -> int:
    """The dead-host deadline (ms of the board's clock, for SET_CONFIG) that leaves a host ``wall_ms`` of wall clock
    on a board running ``speed`` times real time (1: a real board), within what the board accepts. A host's stalls
    are wall-clock ones, whatever the board's speed: at twice real time the firmware's 500 ms were 250 ms of wall
    clock, which a test's link thread beside busy cores missed (DEAD_HOST)."""
    return max(CONSTANTS["MIN_HOST_DEADLINE_MS"], min(CONSTANTS["MAX_HOST_DEADLINE_MS"], round(wall_ms * speed)))


@dataclass(frozen=True)
class LinkTiming:
    """The link's timeouts and periods, in seconds of the driver's clock (board-side periods in ms).

    The defaults are PROTOCOL.md's: a command waits ``ack_timeout_s`` (``zero_ack_timeout_s`` for
    ZERO_SENSORS) for its answer, then is sent again with the same seq, the wait doubling up to
    ``max_ack_timeout_s``, ``command_attempts`` sends in all; HELLO goes out every ``hello_timeout_s`` until a
    HELLO_REPLY comes, ``hello_attempts`` times (5 s). ``boot_delay_s``: after the port opens nothing is sent
    and what arrives is dropped (the board resets when its port opens and its bootloader listens meanwhile).
    ``reconnect_s`` and ``incompatible_retry_s`` are for a driver that reopens its port.
    """

    ack_timeout_s: float = 0.1
    zero_ack_timeout_s: float = 0.3
    max_ack_timeout_s: float = 0.8
    command_attempts: int = 5
    keepalive_s: float = 0.1
    silence_s: float = 1.0
    hello_timeout_s: float = 0.25
    hello_attempts: int = 20
    boot_delay_s: float = 0.0
    reconnect_s: float = 0.2
    incompatible_retry_s: float = 5.0
    telemetry_period_ms: int = 20
    host_deadline_ms: int = 500

    def ack_waits_s(self, name: str, first_s: float | None = None, attempts: int | None = None) -> list[float]:
        """How long each send of command ``name`` waits for its answer, in order (one entry per send)."""
        wait_s = first_s if first_s is not None else (
            self.zero_ack_timeout_s if name == "ZERO_SENSORS" else self.ack_timeout_s)
        cap_s = max(self.max_ack_timeout_s, wait_s)
        waits = []
        for _ in range(self.command_attempts if attempts is None else attempts):
            waits.append(wait_s)
            wait_s = min(2 * wait_s, cap_s)
        return waits


# --- events -------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class BoardInfo:
    """What the board said in its HELLO_REPLY."""

    protocol_version: int
    spec_hash: int
    firmware_version: str
    board: str
    chamber_count: int
    reset_cause: str
    fault_flags: int

    @classmethod
    def from_reply(cls, reply: Message) -> BoardInfo:
        f = reply.fields
        return cls(protocol_version=f["protocol_version"], spec_hash=f["spec_hash"],
                   firmware_version=f"{f['firmware_major']}.{f['firmware_minor']}.{f['firmware_patch']}",
                   board=enum_name(Board, f["board"]), chamber_count=f["chamber_count"],
                   reset_cause=enum_name(ResetCause, f["reset_cause"]), fault_flags=f["fault_flags"])


@dataclass(frozen=True)
class FrameIn:
    """Any valid frame from the board (sent before the events it causes)."""

    message: Message


@dataclass(frozen=True)
class HandshakeDone:
    """The board answered HELLO with this host's spec: the session is open."""

    board: BoardInfo
    message: Message


@dataclass(frozen=True)
class HandshakeRefused:
    """The board was built from another spec; ``error`` names both sides' versions and hashes."""

    error: str
    message: Message


@dataclass(frozen=True)
class HandshakeTimedOut:
    """No HELLO_REPLY after every HELLO."""

    attempts: int


@dataclass(frozen=True)
class Acked:
    """The board carried out command ``name`` sent with ``seq``; ``status`` is OK or CLAMPED."""

    name: str
    seq: int
    status: str
    fields: dict[str, Any]
    message: Message


@dataclass(frozen=True)
class Nacked:
    """The board refused command ``name`` (nothing changed); ``status`` says why."""

    name: str
    seq: int
    status: str
    fields: dict[str, Any]
    message: Message


@dataclass(frozen=True)
class CommandFailed:
    """No answer to command ``name`` after ``attempts`` sends."""

    name: str
    seq: int
    attempts: int


@dataclass(frozen=True)
class TelemetryIn:
    """One TELEMETRY frame."""

    message: Message


@dataclass(frozen=True)
class MotionIn:
    """One MOTION_STATUS frame: where the scanner's stepper axes are."""

    message: Message


@dataclass(frozen=True)
class FaultIn:
    """The board latched a fault (a FAULT frame)."""

    bit_name: str
    fault_flags: int
    message: Message


@dataclass(frozen=True)
class Pong:
    """The answer to one of our PINGs: round trip in seconds of the driver's clock, and the board's time."""

    rtt_s: float
    board_time_ms: int


@dataclass(frozen=True)
class BoardRestarted:
    """The board's clock went back: it restarted behind an open port (watchdog, reset button) and lost its
    session; a new handshake tells why."""

    earlier_ms: int
    now_ms: int


@dataclass(frozen=True)
class Silence:
    """Nothing (or no telemetry while it should stream) came for the silence period: the board is gone."""

    reason: str


Event = (FrameIn | HandshakeDone | HandshakeRefused | HandshakeTimedOut | Acked | Nacked | CommandFailed
         | TelemetryIn | MotionIn | FaultIn | Pong | BoardRestarted | Silence)


@dataclass
class LinkCounters:
    """Counters of one HostLink, for status displays."""

    frames_rx: int = 0
    frames_tx: int = 0
    retries: int = 0
    commands_failed: int = 0
    nacks: int = 0
    pings: int = 0
    rtt_ms: float | None = None
    rtt_ms_mean: float | None = None
    boot_bytes_dropped: int = 0


@dataclass
class _Pending:
    """An acknowledged command waiting for its ACK or NACK."""

    name: str
    seq: int
    frame: bytes
    fields: dict[str, Any]
    waits_s: list[float]
    deadline: float
    sent: int = 1


class LinkBooting(ProtocolError):
    """Something was to be sent during the boot delay, while the board's bootloader still listens."""


class HostLink:
    """The host's end of one connection to a board (see the module's description).

    Call :meth:`open` each time the port opens; then feed :meth:`receive` and :meth:`poll`, and send what
    :meth:`take_output` gives. With ``handshake=True`` (the default) the handshake starts by itself once the
    boot delay is over; else call :meth:`start_handshake`.
    """

    def __init__(self, timing: LinkTiming | None = None):
        self.timing = timing or LinkTiming()
        self.counters = LinkCounters()
        self.reader = FrameReader()
        self.keepalive = False
        self.board: BoardInfo | None = None
        self.session_open = False
        self._seq = 0
        self._out: list[bytes] = []
        self._pending: dict[tuple[int, int], _Pending] = {}
        self._booting_until: float | None = None
        self._handshake_after_boot = False
        self._hello_deadline: float | None = None
        self._hellos_left = 0
        self._hellos_sent = 0
        self._hello_interval_s = self.timing.hello_timeout_s
        self._next_ping: float | None = None
        self._pings: dict[int, float] = {}
        self._last_rx: float | None = None
        self._last_telemetry: float | None = None
        self._silent = False
        self._telemetry_period_ms = 0
        self._board_time_ms: int | None = None

    # --- driver side --------------------------------------------------------------------------------------

    def open(self, now: float, handshake: bool = True) -> None:
        """The port has just opened: forget the last connection, wait out the boot delay, then handshake."""
        self.reader = _carry_counters(self.reader)
        self._out.clear()
        self._pending.clear()
        self._pings.clear()
        self.board, self.session_open, self.keepalive = None, False, False
        self._hello_deadline = None
        self._next_ping = None
        self._last_rx = self._last_telemetry = now
        self._silent = False
        self._telemetry_period_ms = 0
        self._board_time_ms = None
        self._handshake_after_boot = handshake
        self._booting_until = now + self.timing.boot_delay_s if self.timing.boot_delay_s > 0 else None
        if self._booting_until is None and handshake:
            self.start_handshake(now)

    def booting(self, now: float) -> bool:
        """Whether the boot delay still runs (nothing may be sent, what arrives is dropped)."""
        return self._booting_until is not None and now < self._booting_until

    def receive(self, data: bytes, now: float) -> list[Event]:
        """Take bytes read from the port; return what they mean, in order."""
        if self.booting(now):
            self.counters.boot_bytes_dropped += len(data)
            return []
        events: list[Event] = []
        for message in self.reader.feed(data):
            self.counters.frames_rx += 1
            self._last_rx = now
            self._silent = False
            events.append(FrameIn(message))
            events += self._dispatch(message, now)
        return events

    def poll(self, now: float) -> list[Event]:
        """Act on every deadline that has passed: end of boot delay, HELLO and command retransmissions,
        keepalive, silence."""
        events: list[Event] = []
        if self._booting_until is not None and now >= self._booting_until:
            self._booting_until = None
            self._last_rx = self._last_telemetry = now
            if self._handshake_after_boot:
                self.start_handshake(now)
        if self._booting_until is not None:
            return events
        if self._hello_deadline is not None and now >= self._hello_deadline:
            if self._hellos_left > 0:
                self._send_hello(now)
            else:
                self._hello_deadline = None
                events.append(HandshakeTimedOut(self._hellos_sent))
        for key, pending in list(self._pending.items()):
            if now < pending.deadline:
                continue
            if pending.sent >= len(pending.waits_s):
                del self._pending[key]
                self.counters.commands_failed += 1
                events.append(CommandFailed(pending.name, pending.seq, pending.sent))
                continue
            self._out.append(pending.frame)
            self.counters.frames_tx += 1
            self.counters.retries += 1
            pending.deadline = now + pending.waits_s[pending.sent]
            pending.sent += 1
        if self.keepalive and self.session_open:
            if self._next_ping is None or now >= self._next_ping:
                self._send_ping(now)
        events += self._check_silence(now)
        return events

    def next_deadline(self) -> float | None:
        """The earliest time :meth:`poll` has something to do, or None if nothing is scheduled."""
        times = [p.deadline for p in self._pending.values()]
        if self._booting_until is not None:
            return self._booting_until
        if self._hello_deadline is not None:
            times.append(self._hello_deadline)
        if self.keepalive and self.session_open:
            times.append(self._next_ping if self._next_ping is not None else 0.0)
        if self.session_open and not self._silent and self._last_rx is not None:
            times.append(self._last_rx + self.timing.silence_s)
            if self._telemetry_expected() and self._last_telemetry is not None:
                times.append(self._last_telemetry + self.timing.silence_s)
        return min(times) if times else None

    def take_output(self) -> list[bytes]:
        """The wire frames to write now, in order (each a whole ``COBS(body) 0x00``)."""
        out, self._out = self._out, []
        return out

    # --- what the host does -------------------------------------------------------------------------------

    def start_handshake(self, now: float, attempts: int | None = None, interval_s: float | None = None) -> None:
        """Send HELLO now and again every ``interval_s`` until HELLO_REPLY, ``attempts`` times in all."""
        self._check_not_booting(now, "HELLO")
        self._hellos_left = self.timing.hello_attempts if attempts is None else attempts
        self._hellos_sent = 0
        self._hello_interval_s = self.timing.hello_timeout_s if interval_s is None else interval_s
        self._send_hello(now)

    def command(self, name: str, fields: dict[str, Any] | None, now: float, first_wait_s: float | None = None,
                attempts: int | None = None) -> int:
        """Send acknowledged command ``name``; its Acked, Nacked or CommandFailed event will name the seq
        returned. ``first_wait_s`` and ``attempts`` override the timing's for this command."""
        spec = MESSAGES.get(name)
        if spec is None:
            raise ProtocolError(f"unknown message {name!r}; known: {', '.join(MESSAGES)}")
        if not spec.acked:
            raise ProtocolError(f"{name} is not an acknowledged command; use send()")
        self._check_not_booting(now, name)
        fields = dict(fields or {})
        seq = self._next_seq()
        frame = encode(name, seq, fields)
        waits = self.timing.ack_waits_s(name, first_wait_s, attempts)
        if not waits:
            raise ProtocolError(f"{name}: attempts must be at least 1")
        self._pending[(spec.msg_id, seq)] = _Pending(name, seq, frame, fields, waits, now + waits[0])
        self._out.append(frame)
        self.counters.frames_tx += 1
        return seq

    def send(self, name: str, fields: dict[str, Any] | None, now: float) -> int:
        """Send one message with the next seq, unacknowledged and not retransmitted; returns its seq."""
        self._check_not_booting(now, name)
        seq = self._next_seq()
        self._out.append(encode(name, seq, dict(fields or {})))
        self.counters.frames_tx += 1
        return seq

    def send_raw(self, frame: bytes, now: float) -> None:
        """Send bytes as they are (a bench's corrupted or hand-made frame); the link's rules do not see it."""
        self._check_not_booting(now, "a raw frame")
        self._out.append(bytes(frame))

    def pending(self) -> list[tuple[str, int]]:
        """The commands still waiting for an answer: (name, seq)."""
        return [(p.name, p.seq) for p in self._pending.values()]

    def rx_dropped(self) -> dict[str, int]:
        """Frames dropped on receipt since this HostLink was made, by reason."""
        return {name: getattr(self.reader, name) for name in RX_DROP_COUNTERS}

    # --- inside -------------------------------------------------------------------------------------------

    def _check_not_booting(self, now: float, what: str) -> None:
        if self.booting(now):
            raise LinkBooting(f"{what} not sent: the port opened less than {self.timing.boot_delay_s:g} s ago "
                              "and the board's bootloader may still be listening")

    def _next_seq(self) -> int:
        self._seq = (self._seq + 1) & 0xFF
        return self._seq

    def _send_hello(self, now: float) -> None:
        self.send("HELLO", {"protocol_version": PROTOCOL_VERSION, "spec_hash": SPEC_HASH}, now)
        self._hellos_left -= 1
        self._hellos_sent += 1
        self._hello_deadline = now + self._hello_interval_s

    def _send_ping(self, now: float) -> None:
        host_time_ms = int(now * 1000) & 0xFFFFFFFF
        # the wire carries whole milliseconds; the send time is kept here for a finer round trip
        self._pings[host_time_ms] = now
        while len(self._pings) > _PINGS_REMEMBERED:
            self._pings.pop(next(iter(self._pings)))
        self.send("PING", {"host_time_ms": host_time_ms}, now)
        self.counters.pings += 1
        self._next_ping = now + self.timing.keepalive_s

    def _telemetry_expected(self) -> bool:
        return self.session_open and self._telemetry_period_ms > 0

    def _check_silence(self, now: float) -> list[Event]:
        if self._silent or self._last_rx is None or not self.session_open:
            return []  # before the session opens, the handshake's own attempts decide
        silence_s = self.timing.silence_s
        if now - self._last_rx >= silence_s:
            self._silent = True
            return [Silence(f"no frame from the board for {silence_s:g} s")]
        if self._telemetry_expected() and self._last_telemetry is not None and now - self._last_telemetry >= silence_s:
            self._silent = True
            return [Silence(f"no telemetry from the board for {silence_s:g} s (it lost its session)")]
        return []

    def _board_clock(self, board_time_ms: int) -> list[Event]:
        earlier = self._board_time_ms
        self._board_time_ms = board_time_ms
        if earlier is not None and board_clock_went_back(earlier, board_time_ms):
            self.session_open = False
            return [BoardRestarted(earlier, board_time_ms)]
        return []

    def _dispatch(self, message: Message, now: float) -> list[Event]:
        name, fields = message.name, message.fields
        if name == "HELLO_REPLY":
            if self._hello_deadline is None:
                return []  # an answer to a HELLO sent with send(), or a late duplicate
            self._hello_deadline = None
            try:
                check_hello_reply(message)
            except ProtocolError as error:
                self.session_open = False
                return [HandshakeRefused(str(error), message)]
            self.board = BoardInfo.from_reply(message)
            self.session_open = True
            self._board_time_ms = fields["time_ms"]
            self._last_telemetry = now
            self._next_ping = None
            return [HandshakeDone(self.board, message)]
        if name in ("ACK", "NACK"):
            pending = self._pending.pop((fields["ref_msg_id"], fields["ref_seq"]), None)
            if pending is None:
                return []  # the answer to a copy already answered
            status = enum_name(Status, fields["status"])
            if name == "NACK":
                self.counters.nacks += 1
                return [Nacked(pending.name, pending.seq, status, pending.fields, message)]
            if pending.name == "SET_CONFIG":
                self._telemetry_period_ms = pending.fields["telemetry_period_ms"]
                self._last_telemetry = now
            return [Acked(pending.name, pending.seq, status, pending.fields, message)]
        if name == "PONG":
            sent = self._pings.pop(fields["host_time_ms"], None)
            if sent is None:
                return []
            rtt_s = now - sent
            rtt_ms = 1e3 * rtt_s
            mean = self.counters.rtt_ms_mean
            self.counters.rtt_ms = rtt_ms
            self.counters.rtt_ms_mean = rtt_ms if mean is None else 0.9 * mean + 0.1 * rtt_ms
            return [Pong(rtt_s, fields["board_time_ms"]), *self._board_clock(fields["board_time_ms"])]
        if name == "TELEMETRY":
            self._last_telemetry = now
            return [TelemetryIn(message), *self._board_clock(fields["time_ms"])]
        if name == "MOTION_STATUS":
            return [MotionIn(message), *self._board_clock(fields["time_ms"])]
        if name == "FAULT":
            bit = fields["fault_bit"]
            bit_name = fault_names(1 << bit)[0] if 0 <= bit < 16 else str(bit)
            return [FaultIn(bit_name, fields["fault_flags"], message), *self._board_clock(fields["time_ms"])]
        return []


def _carry_counters(reader: FrameReader) -> FrameReader:
    """A fresh reader (a partial frame left by the last connection must not swallow the first reply) that
    keeps the drop counters."""
    fresh = FrameReader()
    for name in ("frames_ok", *RX_DROP_COUNTERS):
        setattr(fresh, name, getattr(reader, name))
    return fresh


# --- the board's side, for peers that stand in for one ------------------------------------------------------


@dataclass
class BoardPeer:
    """The board's end of the framing, for test and bench peers: decode the host's frames, answer them.

    :meth:`answer` gives the default answer a healthy board gives (HELLO_REPLY, PONG, ACK OK); a peer that
    should misbehave builds its own with :meth:`frame`, :meth:`hello_reply`, :meth:`ack` and :meth:`nack`.
    """

    spec_hash: int = SPEC_HASH
    reset_cause: str = "POWER_ON"
    board: str = "UNO"
    fault_flags: int = 0
    seq: int = 0
    reader: FrameReader = field(default_factory=FrameReader)

    def receive(self, data: bytes) -> list[Message]:
        """The host's messages completed by ``data``."""
        return self.reader.feed(data)

    def frame(self, name: str, fields: dict[str, Any]) -> bytes:
        """One board frame with the board's next seq."""
        self.seq = (self.seq + 1) & 0xFF
        return encode(name, self.seq, fields)

    def hello_reply(self, hello: Message, time_ms: int) -> bytes:
        accepted = hello.fields["spec_hash"] == self.spec_hash
        return self.frame("HELLO_REPLY", {
            "protocol_version": PROTOCOL_VERSION, "spec_hash": self.spec_hash,
            "status": Status.OK if accepted else Status.SPEC_MISMATCH, "firmware_major": 0, "firmware_minor": 1,
            "firmware_patch": 0, "board": Board[self.board], "chamber_count": 3,
            "reset_cause": ResetCause[self.reset_cause], "fault_flags": self.fault_flags, "time_ms": time_ms})

    def ack(self, command: Message, status: str = "OK") -> bytes:
        return self.frame("ACK", {"ref_msg_id": command.msg_id, "ref_seq": command.seq, "status": Status[status]})

    def nack(self, command: Message, status: str) -> bytes:
        return self.frame("NACK", {"ref_msg_id": command.msg_id, "ref_seq": command.seq, "status": Status[status]})

    def pong(self, ping: Message, time_ms: int) -> bytes:
        return self.frame("PONG", {"host_time_ms": ping.fields["host_time_ms"], "board_time_ms": time_ms})

    def telemetry(self, time_ms: int, pressures_pa: list[int], setpoints_pa: list[int],
                  drive: list[int] | None = None, states: list[int] | None = None) -> bytes:
        return self.frame("TELEMETRY", {
            "time_ms": time_ms, "pressure_pa": list(pressures_pa), "setpoint_pa": list(setpoints_pa),
            "drive": list(drive or [0, 0, 0]), "state": list(states or [ChamberState.OFF] * 3),
            "fault_flags": self.fault_flags, "rx_bad_crc": self.reader.bad_crc, "rx_overflow": self.reader.overflow,
            "rx_bad_frame": self.reader.bad_cobs + self.reader.bad_length + self.reader.unknown_id,
            "tx_dropped": 0, "tick_overruns": 0})

    def answer(self, message: Message, time_ms: int) -> bytes | None:
        """What a healthy board answers to ``message``: HELLO_REPLY, PONG, ACK OK, or nothing."""
        if message.msg_id == MsgId.HELLO:
            return self.hello_reply(message, time_ms)
        if message.msg_id == MsgId.PING:
            return self.pong(message, time_ms)
        if MESSAGES[message.name].acked:
            return self.ack(message)
        return None
