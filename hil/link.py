"""The bench's serial link to a board (real or simulated): handshake, acknowledged commands, telemetry.

It speaks the wire protocol through ``phantom.protocol.codec`` and keeps the session alive with PINGs. All its
intervals are divided by ``time_scale`` so that a simulated board running faster than real time sees the same
timing, in its own time, as a real board does.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass

from phantom import PhantomError

#: The TEST_HANG message's magic number ("HANG").
TEST_HANG_MAGIC = 0x48414E47


class LinkError(PhantomError):
    """The board did not answer, refused a command, or the port went away."""


@dataclass
class Received:
    """A message from the board and the host's monotonic clock when it arrived (s)."""

    host_time_s: float
    message: object


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
    """

    def __init__(self, port: str, baudrate: int = 115200, time_scale: float = 1.0, keepalive_s: float = 0.1):
        import serial

        from phantom.protocol.codec import FrameReader

        self.time_scale = time_scale
        self.keepalive_s = keepalive_s
        self.port_path = port
        try:
            self._serial = serial.Serial(port, baudrate, timeout=0.01, write_timeout=1.0)
        except (serial.SerialException, OSError) as error:
            raise LinkError(f"cannot open the serial port {port}: {error}; check the path and the cable") from None
        self.reader = FrameReader()
        self.received: list[Received] = []
        self.retransmissions = 0
        self.disconnected = False
        self._seq = 0
        self._changed = threading.Condition()
        self._write_lock = threading.Lock()
        self._stop = threading.Event()
        self._keepalive = threading.Event()
        self._threads = [
            threading.Thread(target=self._read_loop, daemon=True),
            threading.Thread(target=self._keepalive_loop, daemon=True),
        ]
        for thread in self._threads:
            thread.start()

    def close(self) -> None:
        """Stop the threads and close the port."""
        self._stop.set()
        for thread in self._threads:
            thread.join(timeout=2)
        self._serial.close()

    def __enter__(self) -> BoardLink:
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()

    def _read_loop(self) -> None:
        import serial

        while not self._stop.is_set():
            try:
                data = self._serial.read(512)
            except (serial.SerialException, OSError, TypeError):
                with self._changed:
                    self.disconnected = True
                    self._changed.notify_all()
                return
            if not data:
                continue
            messages = self.reader.feed(data)
            if messages:
                now = time.monotonic()
                with self._changed:
                    self.received.extend(Received(now, message) for message in messages)
                    self._changed.notify_all()

    def _keepalive_loop(self) -> None:
        while not self._stop.wait(self.keepalive_s / self.time_scale):
            if self._keepalive.is_set() and not self.disconnected:
                try:
                    self.send("PING", {"host_time_ms": int(time.monotonic() * 1000) & 0xFFFFFFFF})
                except LinkError:
                    pass

    def keepalive(self, on: bool) -> None:
        """Start or stop the PINGs that keep the session alive (stop them to play a silent host)."""
        if on:
            self._keepalive.set()
        else:
            self._keepalive.clear()

    def send(self, name: str, fields: dict | None = None) -> int:
        """Send one message without waiting; returns its seq."""
        import serial

        from phantom.protocol.codec import encode

        with self._write_lock:
            self._seq = (self._seq + 1) & 0xFF
            frame = encode(name, self._seq, fields or {})
            try:
                self._serial.write(frame)
            except (serial.SerialException, OSError) as error:
                raise LinkError(f"writing to {self.port_path} failed: {error}") from None
            return self._seq

    def _resend(self, name: str, seq: int, fields: dict) -> None:
        import serial

        from phantom.protocol.codec import encode

        with self._write_lock:
            try:
                self._serial.write(encode(name, seq, fields))
            except (serial.SerialException, OSError) as error:
                raise LinkError(f"writing to {self.port_path} failed: {error}") from None

    def wait_for(self, predicate, timeout_s: float, start: int = 0):
        """The first received message (index >= start) satisfying predicate, within timeout_s board seconds;
        None on timeout."""
        deadline = time.monotonic() + timeout_s / self.time_scale
        index = start
        with self._changed:
            while True:
                while index < len(self.received):
                    if predicate(self.received[index].message):
                        return self.received[index]
                    index += 1
                remaining = deadline - time.monotonic()
                if remaining <= 0 or self.disconnected:
                    return None
                self._changed.wait(remaining)

    def mark(self) -> int:
        """An index into ``received``: pass it as ``start`` to wait only for what arrives after now."""
        with self._changed:
            return len(self.received)

    def hello(self, attempts: int = 10, timeout_s: float = 0.3):
        """Open a session: send HELLO until HELLO_REPLY arrives; returns the reply after checking the spec."""
        from phantom.protocol.codec import check_hello_reply
        from phantom.protocol.messages import PROTOCOL_VERSION, SPEC_HASH

        for _ in range(attempts):
            start = self.mark()
            self.send("HELLO", {"protocol_version": PROTOCOL_VERSION, "spec_hash": SPEC_HASH})
            got = self.wait_for(lambda m: m.name == "HELLO_REPLY", timeout_s, start)
            if got is not None:
                check_hello_reply(got.message)
                return got.message
        raise LinkError(
            f"no HELLO_REPLY from {self.port_path} after {attempts} tries: is the phantom firmware running "
            "at 115200 baud on this port?"
        )

    def command(
        self,
        name: str,
        fields: dict | None = None,
        timeout_s: float = 0.1,
        attempts: int = 8,
        accept_nack: bool = False,
    ):
        """Send an acknowledged command, retransmitting with doubling timeouts; returns the ACK (or NACK).

        Raises LinkError when no answer comes, or on a NACK unless accept_nack.
        """
        from phantom.protocol.messages import ENUMS, MESSAGES

        fields = fields or {}
        seq = self.send(name, fields)
        msg_id = MESSAGES[name].msg_id
        wait_s = timeout_s
        start = 0
        for attempt in range(attempts):
            got = self.wait_for(
                lambda m: m.name in ("ACK", "NACK") and m.fields["ref_seq"] == seq and m.fields["ref_msg_id"] == msg_id,
                wait_s,
                start,
            )
            if got is not None:
                if got.message.name == "NACK" and not accept_nack:
                    status = {v: k for k, v in ENUMS["status"].items()}.get(got.message.fields["status"])
                    raise LinkError(f"the board refused {name}: NACK {status}")
                return got.message
            if attempt + 1 < attempts:
                start = self.mark()
                self.retransmissions += 1
                self._resend(name, seq, fields)
                wait_s = min(2 * wait_s, 1.0)
        raise LinkError(f"no ACK for {name} from {self.port_path} after {attempts} tries")

    def telemetry(self, start: int = 0) -> list[Received]:
        """TELEMETRY messages received since index start."""
        with self._changed:
            return [r for r in self.received[start:] if r.message.name == "TELEMETRY"]
