"""Byte transports between the daemon and a board: a serial port (pyserial) and a CAN bus (python-can).

Every transport moves whole wire frames (``COBS(body) 0x00``, see protocol/PROTOCOL.md): ``write`` takes one
frame, ``read`` returns wire bytes to feed a :class:`phantom.protocol.codec.FrameReader`. A transport that
goes away (USB unplugged, bus closed) raises :class:`TransportLost`; the link session then reconnects.

CAN mapping (classic CAN, 11-bit ids, 8 data bytes)
---------------------------------------------------
One message travels as up to 16 CAN frames, all with the same arbitration id:

    arbitration id   0x100 + msg_id   host -> board
                     0x200 + msg_id   board -> host   (a lower id wins arbitration: commands before telemetry)
    data[0]          segment index (high nibble) | segment count - 1 (low nibble)
    data[1:]         up to 7 bytes of ``seq | payload | crc16`` (the frame body without msg_id, which the id
                     carries), in order

The receiver rebuilds the body ``msg_id | seq | payload | crc16`` and checks the protocol's own CRC as on a
serial link (CAN's CRC protects one CAN frame, ours the reassembled message). Segments out of order or a new
index 0 before the last segment drop the partial message (counted in ``dropped_segments``).
"""

from __future__ import annotations

import asyncio
import contextlib
import errno
import fcntl
import grp
import os
import termios
from pathlib import Path
from typing import Any

from phantom import PhantomError, require_extra
from phantom.protocol.codec import MAX_FRAME_BYTES
from phantom.protocol.framing import cobs_decode, cobs_encode
from phantom.protocol.messages import MESSAGES

#: Arbitration-id bases of the CAN mapping.
CAN_ID_HOST_TO_BOARD = 0x100
CAN_ID_BOARD_TO_HOST = 0x200
#: Body bytes per CAN frame after the segment header.
CAN_SEGMENT_BYTES = 7


class TransportUnavailable(PhantomError):
    """The board's port cannot be opened now (absent, busy or no permission); the session retries."""


class TransportLost(PhantomError):
    """An open transport went away (device unplugged, read error); the session reconnects."""


def permission_hint(path: str) -> str:
    """The message for a serial port this user may not open: join the port's group (phantom with the shipped udev
    rule, firmware/udev/99-phantom.rules; dialout for a port without it)."""
    try:
        group = grp.getgrgid(os.stat(path).st_gid).gr_name
    except (OSError, KeyError):
        group = "dialout"
    return (f"permission denied on {path}: add your user to the {group} group, which owns the port (sudo usermod "
            f"-aG {group} $USER), then log out and in again")


#: Bytes without a frame delimiter kept before they are handed on anyway (a frame is far shorter).
MAX_PARTIAL_BYTES = 1024
#: Bits on the wire per byte of a serial port (8N1: a start bit, 8 data bits, a stop bit).
BITS_PER_BYTE = 10


#: The wire length of each message the board sends, by id: payload, id, seq, CRC, COBS's code byte, delimiter.
BOARD_FRAME_BYTES = {spec.msg_id: spec.payload_size + 6 for spec in MESSAGES.values() if spec.direction == "board"}


def frame_bytes(partial: bytes) -> int:
    """How long the frame that ``partial`` begins is on the wire: its message's length once its id is there (the
    byte after COBS's first code byte, when that code is over 1), the shortest a board sends before that, and the
    longest frame for an id no board message has."""
    if len(partial) < 2:
        return min(BOARD_FRAME_BYTES.values())
    return BOARD_FRAME_BYTES.get(partial[1], MAX_FRAME_BYTES) if partial[0] > 1 else MAX_FRAME_BYTES


class SerialTransport:
    """A serial port (a USB CDC device, a ``/dev/serial/by-id/...`` path, or a pseudo-terminal).

    The port is configured by pyserial (raw, 8N1, ``baudrate``) and read through the event loop's reader
    callback on its file descriptor, so no thread is needed and an unplugged device is seen at once (EIO).
    """

    def __init__(self, path: str | Path, baudrate: int = 115200):
        self.path = str(path)
        self.baudrate = baudrate
        self.description = f"serial {self.path}"
        self._serial: Any = None  # serial.Serial once open
        self._queue: asyncio.Queue[bytes | TransportLost] = asyncio.Queue()
        self._partial = b""
        self._resume: asyncio.TimerHandle | None = None
        self.tx_dropped = 0
        #: reads of the port since it was first opened: the wake-ups reading it cost (status ``port_reads``)
        self.reads = 0

    async def open(self) -> None:
        """Open and configure the port; raises TransportUnavailable when it is not there."""
        import serial

        if not os.path.exists(self.path):
            raise TransportUnavailable(f"{self.path} does not exist (board unplugged?)")
        if not os.access(self.path, os.R_OK | os.W_OK):
            raise TransportUnavailable(permission_hint(self.path))
        try:
            self._serial = serial.Serial(self.path, self.baudrate, timeout=0, write_timeout=0, exclusive=True)
        except (serial.SerialException, OSError) as error:
            if getattr(error, "errno", None) == errno.EACCES or "Permission denied" in str(error):
                raise TransportUnavailable(permission_hint(self.path)) from error
            raise TransportUnavailable(f"cannot open {self.path}: {error}") from error
        # no other process may open the port while the daemon holds it (the kernel's exclusive mode; root is
        # exempt): a program of the port's group could otherwise drive the board behind the daemon's back
        with contextlib.suppress(OSError):
            fcntl.ioctl(self._serial.fileno(), termios.TIOCEXCL)
        self._serial.reset_input_buffer()
        self._queue = asyncio.Queue()
        self._partial = b""
        self._watch()

    def _on_readable(self) -> None:
        """Move the whole frames the port holds into the queue; an empty read or EIO means the device went away.

        A port delivers a frame in pieces (a pty fed by the simulated UART gives it a byte at a time, one every
        87 us at 115200 baud): reading each piece woke the link's thread about 1300 times a second at 50 Hz
        telemetry, 7 % of a core. Bytes are kept until a frame's delimiter (0x00) arrives, or until
        :data:`MAX_PARTIAL_BYTES` (noise without delimiters, which the frame reader discards), so the session
        wakes once per frame; and while a frame is partly there the port is not watched for as long as its rest
        takes to arrive at the port's baud rate (:meth:`_wait_for_rest`), so reading it costs two or three
        wake-ups, not one per byte."""
        self.reads += 1
        item: bytes | TransportLost
        try:
            item = os.read(self._serial.fileno(), 4096)
        except BlockingIOError:
            return
        except OSError as error:
            item = TransportLost(f"{self.path}: {error.strerror} (board unplugged or reset)")
        if not item:
            item = TransportLost(f"{self.path} closed (board unplugged or reset)")
        if isinstance(item, TransportLost):
            asyncio.get_running_loop().remove_reader(self._serial.fileno())
            if self._partial:
                self._queue.put_nowait(self._partial)
                self._partial = b""
            self._queue.put_nowait(item)
            return
        data = self._partial + item
        end = data.rfind(b"\x00") + 1
        if end == 0 and len(data) >= MAX_PARTIAL_BYTES:
            end = len(data)
        self._partial = data[end:]
        if end:
            self._queue.put_nowait(data[:end])
        if self._partial:
            self._wait_for_rest()

    def _wait_for_rest(self) -> None:
        """Stop watching the port until the rest of the frame begun in ``_partial`` should be there at the baud
        rate (10 bits a byte): :func:`frame_bytes` long. A telemetry frame is read in three reads, an ACK in two;
        waiting for the longest frame's bytes (5.7 ms at 115200) read every frame in two, but made an ACK's round
        trip 2.5 ms longer."""
        loop = asyncio.get_running_loop()
        loop.remove_reader(self._serial.fileno())
        expected = frame_bytes(self._partial)
        rest_bytes = max(1, (expected if expected > len(self._partial) else MAX_FRAME_BYTES) - len(self._partial))
        self._resume = loop.call_later(rest_bytes * BITS_PER_BYTE / self.baudrate, self._watch)

    def _watch(self) -> None:
        """Watch the port again: the event loop calls :meth:`_on_readable` when it holds bytes."""
        self._resume = None
        if self._serial is not None:
            asyncio.get_running_loop().add_reader(self._serial.fileno(), self._on_readable)

    async def read(self) -> bytes:
        """The next bytes from the port; raises TransportLost when the device went away."""
        data = await self._queue.get()
        if isinstance(data, Exception):
            raise data
        return data

    def write(self, frame: bytes) -> None:
        """Send one wire frame without blocking; a full output buffer drops it (counted)."""
        if self._serial is None:
            raise TransportLost(f"{self.path} is not open")
        try:
            written = os.write(self._serial.fileno(), frame)
        except BlockingIOError:
            self.tx_dropped += 1
            return
        except OSError as error:
            raise TransportLost(f"{self.path}: {error}") from error
        if written != len(frame):
            self.tx_dropped += 1

    def close(self) -> None:
        """Close the port (safe to call twice)."""
        if self._resume is not None:
            self._resume.cancel()
            self._resume = None
        if self._serial is None:
            return
        with contextlib.suppress(Exception):
            asyncio.get_running_loop().remove_reader(self._serial.fileno())
        with contextlib.suppress(Exception):
            fcntl.ioctl(self._serial.fileno(), termios.TIOCNXCL)
        with contextlib.suppress(Exception):
            self._serial.close()
        self._serial = None


def can_frames(body: bytes, to_board: bool) -> list[tuple[int, bytes]]:
    """Split one frame body into (arbitration id, data) CAN frames of the documented mapping.

    Parameters
    ----------
    body : bytes
        ``msg_id | seq | payload | crc16``, at most 64 bytes.
    to_board : bool
        Direction: host -> board (id base 0x100) or board -> host (0x200).
    """
    arbitration_id = (CAN_ID_HOST_TO_BOARD if to_board else CAN_ID_BOARD_TO_HOST) + body[0]
    rest = body[1:]
    count = max(1, -(-len(rest) // CAN_SEGMENT_BYTES))
    if count > 16:
        raise ValueError(f"a body of {len(body)} bytes needs {count} CAN segments; the mapping allows 16")
    return [(arbitration_id, bytes([index << 4 | (count - 1)]) + rest[index * CAN_SEGMENT_BYTES:
                                                                     (index + 1) * CAN_SEGMENT_BYTES])
            for index in range(count)]


class CanReassembler:
    """Rebuilds frame bodies from CAN frames of one direction (see the module's mapping)."""

    def __init__(self, from_board: bool):
        self.base = CAN_ID_BOARD_TO_HOST if from_board else CAN_ID_HOST_TO_BOARD
        self.dropped_segments = 0
        self._partial: dict[int, tuple[int, bytearray]] = {}

    def feed(self, arbitration_id: int, data: bytes) -> bytes | None:
        """Take one CAN frame; return a whole body once its last segment arrives, else None."""
        if not self.base <= arbitration_id < self.base + 0x100 or not data:
            return None
        msg_id = arbitration_id - self.base
        index, last = data[0] >> 4, data[0] & 0x0F
        if index == 0:
            if msg_id in self._partial:
                self.dropped_segments += 1
            self._partial[msg_id] = (0, bytearray(data[1:]))
        else:
            expected, collected = self._partial.get(msg_id, (-1, None))
            if collected is None or index != expected + 1:
                self.dropped_segments += 1
                self._partial.pop(msg_id, None)
                return None
            collected += data[1:]
            self._partial[msg_id] = (index, collected)
        if index == last:
            _, collected = self._partial.pop(msg_id)
            return bytes([msg_id]) + bytes(collected)
        return None


class CanTransport:
    """The protocol over a CAN bus through python-can (tested on its ``virtual`` interface).

    Parameters
    ----------
    channel : str
        The bus channel (``can0`` for SocketCAN, any name for ``virtual``).
    interface : str
        python-can interface name.
    role : str
        ``"host"`` (sends with the host -> board ids) or ``"board"`` (the other end; used by tests and
        bench peers).
    """

    def __init__(self, channel: str, interface: str = "socketcan", role: str = "host", **bus_options: Any):
        if role not in ("host", "board"):
            raise ValueError(f"role must be 'host' or 'board', got {role!r}")
        self.channel = channel
        self.interface = interface
        self.role = role
        self.bus_options = bus_options
        self.description = f"CAN {interface}:{channel}"
        self.reassembler = CanReassembler(from_board=(role == "host"))
        self.tx_dropped = 0
        self._bus: Any = None  # can.BusABC once open
        self._notifier: Any = None
        self._reader: Any = None

    async def open(self) -> None:
        """Connect to the bus; raises TransportUnavailable when the interface cannot be opened."""
        with require_extra("can"):
            import can

        try:
            self._bus = can.Bus(interface=self.interface, channel=self.channel, **self.bus_options)
        except (can.CanError, OSError, ValueError) as error:
            raise TransportUnavailable(f"cannot open CAN {self.interface}:{self.channel}: {error}") from error
        self._reader = can.AsyncBufferedReader()
        self._notifier = can.Notifier(self._bus, [self._reader], loop=asyncio.get_running_loop())

    async def read(self) -> bytes:
        """Wire bytes of the next complete message (COBS-encoded, delimited, for the FrameReader)."""
        while True:
            if self._reader is None:
                raise TransportLost(f"{self.description} is closed")
            message = await self._reader.get_message()
            if message.is_error_frame or message.is_remote_frame or message.is_extended_id:
                continue
            body = self.reassembler.feed(message.arbitration_id, bytes(message.data))
            if body is not None:
                return cobs_encode(body) + b"\x00"

    def write(self, frame: bytes) -> None:
        """Send one wire frame as its CAN segments."""
        with require_extra("can"):
            import can

        if self._bus is None:
            raise TransportLost(f"{self.description} is closed")
        body = cobs_decode(frame.rstrip(b"\x00"))
        for arbitration_id, data in can_frames(body, to_board=(self.role == "host")):
            try:
                self._bus.send(can.Message(arbitration_id=arbitration_id, data=data, is_extended_id=False),
                               timeout=0.05)
            except can.CanError:
                self.tx_dropped += 1
                return

    def close(self) -> None:
        """Stop the notifier and shut the bus down (safe to call twice)."""
        if self._notifier is not None:
            self._notifier.stop()
            self._notifier = None
        if self._bus is not None:
            self._bus.shutdown()
            self._bus = None
        self._reader = None
