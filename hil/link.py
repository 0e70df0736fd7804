"""The bench's serial link to a board (real or simulated): a blocking driver of the link core.

The rules (boot delay, handshake, sequence numbers, retransmission, keepalive) are
:class:`phantom.protocol.link.HostLink`'s; one thread here reads the port, passes bytes and the time to it,
writes what it gives back, and keeps every message received, so that a check can wait for what it expects.
The core runs on the board's clock: host seconds times ``time_scale``, so that a simulated board running faster
than real time sees the same timing, in its own time, as a real board does.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from phantom import PhantomError
from phantom.protocol.codec import FrameReader, Message
from phantom.protocol.errors import ProtocolError
from phantom.protocol.link import (
    Acked,
    CommandFailed,
    Event,
    FrameIn,
    HandshakeDone,
    HandshakeRefused,
    HandshakeTimedOut,
    HostLink,
    LinkTiming,
    Nacked,
)
from phantom.protocol.messages import MsgId

#: How long one read of the port blocks (s): the longest a deadline of the core can be late.
_READ_SLICE_S = 0.005


class LinkError(PhantomError):
    """The board did not answer, refused a command, or the port went away."""


@dataclass
class Received:
    """A message from the board and the host's monotonic clock when it arrived (s)."""

    host_time_s: float
    message: Message


class BoardLink:
    """A session with a board over a serial port.

    Parameters
    ----------
    port
        Serial port path (``/dev/ttyACM0``, or ``SimulatedBoard.port``).
    time_scale
        How much faster than real time the board runs (1 for a real board).
    keepalive_s
        PING period in board time while the keepalive runs (the firmware's host deadline is 500 ms).
    boot_delay_s
        Board seconds after opening the port during which nothing is sent and what arrives is dropped: opening
        the port resets an Uno or a Mega, whose bootloader listens meanwhile (about 1 s after an Optiboot
        reset; 2 s or more for the Mega's stk500v2). The constructor returns once it is over.
    """

    def __init__(self, port: str, baudrate: int = 115200, time_scale: float = 1.0, keepalive_s: float = 0.1,
                 boot_delay_s: float = 0.0):
        import serial

        self.time_scale = time_scale
        self.keepalive_s = keepalive_s
        self.port_path = port
        try:
            self._serial = serial.Serial(port, baudrate, timeout=_READ_SLICE_S, write_timeout=1.0)
        except (serial.SerialException, OSError) as error:
            raise LinkError(f"cannot open the serial port {port}: {error}; check the path and the cable") from None
        self.link = HostLink(LinkTiming(keepalive_s=keepalive_s, boot_delay_s=boot_delay_s))
        self.received: list[Received] = []
        self.disconnected = False
        self._answers: dict[int, Event] = {}
        self._handshake: Event | None = None
        self._changed = threading.Condition()
        self._stop = threading.Event()
        with self._changed:
            self.link.open(self._now(), handshake=False)
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()
        while self.link.booting(self._now()) and not self.disconnected:
            time.sleep(min(0.05, boot_delay_s / time_scale))

    @property
    def reader(self) -> FrameReader:
        """The frame reader, with its counters of frames dropped on receipt."""
        return self.link.reader

    @property
    def retransmissions(self) -> int:
        return self.link.counters.retries

    def close(self) -> None:
        """Stop the thread and close the port."""
        self._stop.set()
        self._thread.join(timeout=2)
        self._serial.close()

    def __enter__(self) -> BoardLink:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()

    def _now(self) -> float:
        """The core's clock: board seconds."""
        return time.monotonic() * self.time_scale

    def _run(self) -> None:
        """Read, feed the core, act on its deadlines, write its frames; until closed or the port goes away."""
        import serial

        while not self._stop.is_set():
            try:
                data = self._serial.read(512)
            except (serial.SerialException, OSError, TypeError):
                with self._changed:
                    self.disconnected = True
                    self._changed.notify_all()
                return
            arrived_s = time.monotonic()
            with self._changed:
                events = self.link.receive(data, self._now()) if data else []
                events += self.link.poll(self._now())
                for event in events:
                    self._record(event, arrived_s)
                try:
                    self._flush()
                except LinkError:
                    self.disconnected = True
                if events:
                    self._changed.notify_all()

    def _record(self, event: Event, arrived_s: float) -> None:
        if isinstance(event, FrameIn):
            self.received.append(Received(arrived_s, event.message))
        elif isinstance(event, (Acked, Nacked, CommandFailed)):
            self._answers[event.seq] = event
        elif isinstance(event, (HandshakeDone, HandshakeRefused, HandshakeTimedOut)):
            self._handshake = event

    def _flush(self) -> None:
        """Write the core's frames (the caller holds the lock)."""
        import serial

        for frame in self.link.take_output():
            try:
                self._serial.write(frame)
            except (serial.SerialException, OSError) as error:
                raise LinkError(f"writing to {self.port_path} failed: {error}") from None

    def _wait(self, done: Callable[[], Any], timeout_s: float) -> Any:
        """Wait (holding the lock between checks) until ``done()`` gives something, or timeout_s host seconds."""
        deadline = time.monotonic() + timeout_s
        with self._changed:
            while True:
                result = done()
                if result is not None:
                    return result
                remaining = deadline - time.monotonic()
                if remaining <= 0 or self.disconnected:
                    return None
                self._changed.wait(remaining)

    def keepalive(self, on: bool) -> None:
        """Start or stop the PINGs that keep the session alive (stop them to play a silent host)."""
        with self._changed:
            self.link.keepalive = on

    def send(self, name: str, fields: dict[str, Any] | None = None) -> int:
        """Send one message without waiting or retransmitting; returns its seq."""
        with self._changed:
            seq = self.link.send(name, fields, self._now())
            self._flush()
            return seq

    def send_raw(self, frame: bytes) -> None:
        """Send bytes as they are (a corrupted or hand-made frame for a fault test)."""
        with self._changed:
            self.link.send_raw(frame, self._now())
            self._flush()

    def wait_for(self, predicate: Callable[[Message], bool], timeout_s: float, start: int = 0) -> Received | None:
        """The first received message (index >= start) satisfying predicate, within timeout_s board seconds;
        None on timeout."""
        index = start

        def found() -> Received | None:
            nonlocal index
            while index < len(self.received):
                if predicate(self.received[index].message):
                    return self.received[index]
                index += 1
            return None

        result: Received | None = self._wait(found, timeout_s / self.time_scale)
        return result

    def mark(self) -> int:
        """An index into ``received``: pass it as ``start`` to wait only for what arrives after now."""
        with self._changed:
            return len(self.received)

    def hello(self, attempts: int = 10, timeout_s: float = 0.3) -> Message:
        """Open a session: send HELLO every timeout_s board seconds until HELLO_REPLY arrives; returns the reply
        after checking the spec (ProtocolError when the board was built from another one)."""
        with self._changed:
            self._handshake = None
            self.link.start_handshake(self._now(), attempts=attempts, interval_s=timeout_s)
            self._flush()
        outcome = self._wait(lambda: self._handshake, 2 * attempts * timeout_s / self.time_scale + 1.0)
        if isinstance(outcome, HandshakeDone):
            return outcome.message
        if isinstance(outcome, HandshakeRefused):
            raise ProtocolError(outcome.error)
        raise LinkError(
            f"no HELLO_REPLY from {self.port_path} after {attempts} tries: is the phantom firmware running "
            "at 115200 baud on this port?"
        )

    def command(
        self,
        name: str,
        fields: dict[str, Any] | None = None,
        timeout_s: float | None = None,
        attempts: int | None = None,
        accept_nack: bool = False,
    ) -> Message:
        """Send an acknowledged command, retransmitted by the link's rule (PROTOCOL.md section 5; ``timeout_s``
        and ``attempts`` override its first wait and number of sends); returns the ACK (or NACK).

        Raises LinkError when no answer comes, or on a NACK unless accept_nack.
        """
        with self._changed:
            seq = self.link.command(name, fields, self._now(), first_wait_s=timeout_s, attempts=attempts)
            waits_s = self.link.timing.ack_waits_s(name, timeout_s, attempts)
            self._flush()
        answer = self._wait(lambda: self._answers.pop(seq, None), 2 * sum(waits_s) / self.time_scale + 1.0)
        if isinstance(answer, Nacked):
            if not accept_nack:
                raise LinkError(f"the board refused {name}: NACK {answer.status}")
            return answer.message
        if isinstance(answer, Acked):
            return answer.message
        raise LinkError(f"no ACK for {name} from {self.port_path} after {len(waits_s)} tries")

    def telemetry(self, start: int = 0) -> list[Received]:
        """TELEMETRY messages received since index start."""
        with self._changed:
            return [r for r in self.received[start:] if r.message.msg_id == MsgId.TELEMETRY]
