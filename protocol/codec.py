"""Encode and decode whole wire frames, and read a byte stream into messages.

A wire frame is ``COBS(body) 0x00`` with ``body = msg_id | seq | payload | crc16`` (PROTOCOL.md). Field
values are plain Python numbers: ints for integer types (enums and bit sets as their numbers), floats for
f32, and a list of ``count`` values for an array field.
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass, field
from typing import Any

from phantom.protocol.errors import ProtocolError
from phantom.protocol.framing import cobs_decode, cobs_encode, crc16_mcrf4xx
from phantom.protocol.messages import MAX_BODY_BYTES, MESSAGES, MESSAGES_BY_ID, SPEC_HASH, MessageSpec

#: struct format and inclusive integer range of each wire type.
_FORMATS = {"u8": "B", "i8": "b", "u16": "H", "i16": "h", "u32": "I", "i32": "i", "f32": "f"}
_RANGES = {
    "u8": (0, 0xFF),
    "i8": (-0x80, 0x7F),
    "u16": (0, 0xFFFF),
    "i16": (-0x8000, 0x7FFF),
    "u32": (0, 0xFFFFFFFF),
    "i32": (-0x80000000, 0x7FFFFFFF),
}
#: Longest wire frame: a body of MAX_BODY_BYTES, one COBS code byte per 254 bytes plus one, the delimiter.
MAX_FRAME_BYTES = MAX_BODY_BYTES + MAX_BODY_BYTES // 254 + 2


@dataclass
class Message:
    """One decoded message: its name and id, the frame's seq, and the field values by name."""

    name: str
    msg_id: int
    seq: int
    fields: dict[str, Any]


def _struct_format(spec: MessageSpec) -> struct.Struct:
    """The little-endian struct of a message's payload, one item per array element."""
    return struct.Struct("<" + "".join(_FORMATS[f.type] * f.count for f in spec.fields))


_STRUCTS = {name: _struct_format(spec) for name, spec in MESSAGES.items()}


def _check_value(message: str, field_name: str, wire_type: str, value: object) -> None:
    """Raise ProtocolError if ``value`` does not fit ``wire_type``."""
    if wire_type == "f32":
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ProtocolError(f"{message}.{field_name}: expected a number, got {value!r}")
        if math.isfinite(value) and abs(value) > 3.4028234663852886e38:
            raise ProtocolError(f"{message}.{field_name}: {value} does not fit a 32-bit float")
        return
    if isinstance(value, bool) or not isinstance(value, int):
        raise ProtocolError(f"{message}.{field_name}: expected an integer, got {value!r}")
    low, high = _RANGES[wire_type]
    if not low <= value <= high:
        raise ProtocolError(f"{message}.{field_name}: {value} is outside {wire_type} range {low}..{high}")


def _flatten(spec: MessageSpec, fields: dict[str, Any]) -> list[int | float]:
    """The payload's values in wire order, checked against the spec."""
    names = {f.name for f in spec.fields}
    unknown = sorted(set(fields) - names)
    missing = [f.name for f in spec.fields if f.name not in fields]
    if unknown or missing:
        raise ProtocolError(
            f"{spec.name}: fields do not match the spec (missing {missing}, unknown {unknown}); "
            f"expected {[f.name for f in spec.fields]}"
        )
    values: list[int | float] = []
    for f in spec.fields:
        value = fields[f.name]
        items = value if f.count > 1 else [value]
        if f.count > 1 and (not isinstance(value, (list, tuple)) or len(value) != f.count):
            raise ProtocolError(f"{spec.name}.{f.name}: expected a list of {f.count} values, got {value!r}")
        for item in items:
            _check_value(spec.name, f.name, f.type, item)
        values.extend(items)
    return values


def encode_body(name: str, seq: int, fields: dict[str, Any]) -> bytes:
    """The frame body before COBS: ``msg_id | seq | payload | crc16 (LE)``."""
    spec = MESSAGES.get(name)
    if spec is None:
        raise ProtocolError(f"unknown message {name!r}; known: {', '.join(MESSAGES)}")
    if isinstance(seq, bool) or not isinstance(seq, int) or not 0 <= seq <= 255:
        raise ProtocolError(f"{name}: seq must be an integer 0..255, got {seq!r}")
    head = bytes((spec.msg_id, seq)) + _STRUCTS[name].pack(*_flatten(spec, fields))
    return head + struct.pack("<H", crc16_mcrf4xx(head))


def encode(name: str, seq: int, fields: dict[str, Any]) -> bytes:
    """The whole wire frame of one message: ``COBS(body) + b"\\x00"``.

    Raises
    ------
    ProtocolError
        For an unknown message name, a seq outside 0..255, missing or unknown fields, or a value that does
        not fit its wire type.
    """
    return cobs_encode(encode_body(name, seq, fields)) + b"\x00"


def decode_body(body: bytes) -> Message:
    """Decode a frame body (after COBS); checks CRC, then id, then length, in that order."""
    if len(body) < 4:
        raise ProtocolError(f"frame body of {len(body)} bytes is shorter than the 4-byte minimum")
    if len(body) > MAX_BODY_BYTES:
        raise ProtocolError(f"frame body of {len(body)} bytes exceeds the {MAX_BODY_BYTES}-byte maximum")
    received = body[-2] | body[-1] << 8
    computed = crc16_mcrf4xx(body[:-2])
    if received != computed:
        raise ProtocolError(f"bad CRC: frame says 0x{received:04X}, body gives 0x{computed:04X}")
    msg_id, seq = body[0], body[1]
    spec = MESSAGES_BY_ID.get(msg_id)
    if spec is None:
        raise ProtocolError(f"unknown message id 0x{msg_id:02X}")
    payload = body[2:-2]
    if len(payload) != spec.payload_size:
        raise ProtocolError(f"{spec.name}: payload of {len(payload)} bytes, the spec says {spec.payload_size}")
    flat = list(_STRUCTS[spec.name].unpack(payload))
    fields = {}
    for f in spec.fields:
        fields[f.name] = flat[: f.count] if f.count > 1 else flat[0]
        del flat[: f.count]
    return Message(spec.name, msg_id, seq, fields)


def decode(frame: bytes) -> Message:
    """Decode one wire frame (COBS bytes, with or without the trailing 0x00).

    Raises
    ------
    ProtocolError
        For bad COBS, a body shorter than 4 or longer than 64 bytes, a bad CRC, an unknown id, or a
        payload length that differs from the spec.
    """
    frame = bytes(frame)
    if frame.endswith(b"\x00"):
        frame = frame[:-1]
    if not frame:
        raise ProtocolError("empty frame")
    return decode_body(cobs_decode(frame))


@dataclass
class FrameReader:
    """Splits a byte stream at 0x00 delimiters and decodes each frame, counting and dropping bad ones.

    A frame is dropped (never returned) on bad COBS, bad length, bad CRC or unknown id; bytes past
    MAX_FRAME_BYTES without a delimiter are dropped up to the next 0x00 (``overflow``). Empty frames
    (two delimiters in a row) are ignored silently: a sender may use a lone 0x00 to flush a receiver.
    """

    frames_ok: int = 0
    bad_crc: int = 0
    bad_length: int = 0
    unknown_id: int = 0
    bad_cobs: int = 0
    overflow: int = 0
    _buffer: bytearray = field(default_factory=bytearray, repr=False)
    _discarding: bool = field(default=False, repr=False)

    def feed(self, data: bytes) -> list[Message]:
        """Consume ``data`` (any split of the stream) and return the messages completed by it, in order."""
        messages = []
        for byte in bytes(data):
            if byte != 0:
                if self._discarding:
                    continue
                self._buffer.append(byte)
                if len(self._buffer) > MAX_FRAME_BYTES - 1:
                    self.overflow += 1
                    self._buffer.clear()
                    self._discarding = True
                continue
            if self._discarding:
                self._discarding = False
                continue
            if self._buffer:
                message = self._decode(bytes(self._buffer))
                self._buffer.clear()
                if message is not None:
                    messages.append(message)
        return messages

    def _decode(self, encoded: bytes) -> Message | None:
        """Decode one delimited frame, or count why not and return None."""
        try:
            body = cobs_decode(encoded)
        except ProtocolError:
            self.bad_cobs += 1
            return None
        if len(body) < 4 or len(body) > MAX_BODY_BYTES:
            self.bad_length += 1
            return None
        if crc16_mcrf4xx(body[:-2]) != (body[-2] | body[-1] << 8):
            self.bad_crc += 1
            return None
        spec = MESSAGES_BY_ID.get(body[0])
        if spec is None:
            self.unknown_id += 1
            return None
        if len(body) - 4 != spec.payload_size:
            self.bad_length += 1
            return None
        self.frames_ok += 1
        return decode_body(body)


def check_hello_reply(message: Message) -> None:
    """Raise ProtocolError unless a HELLO_REPLY shows a board built from this host's spec.

    The error names both sides' protocol versions and spec hashes, so that a user sees which side to rebuild.
    """
    from phantom.protocol.messages import PROTOCOL_VERSION, Status

    if message.name != "HELLO_REPLY":
        raise ProtocolError(f"expected HELLO_REPLY, got {message.name}")
    board_version = message.fields["protocol_version"]
    board_hash = message.fields["spec_hash"]
    if board_hash != SPEC_HASH or message.fields["status"] == Status.SPEC_MISMATCH:
        raise ProtocolError(
            f"protocol mismatch: the board speaks protocol v{board_version} (spec hash 0x{board_hash:08X}), "
            f"this host speaks v{PROTOCOL_VERSION} (spec hash 0x{SPEC_HASH:08X}); "
            "flash firmware built from the same protocol/spec.toml as this host (make -C firmware upload)"
        )
