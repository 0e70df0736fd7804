"""Property-based fuzzing of the Python codec: random streams never crash the reader, round trips are exact,
and no frame with a wrong CRC is ever accepted."""

import math
import struct

from hypothesis import given, settings
from hypothesis import strategies as st

from phantom.protocol import ProtocolError
from phantom.protocol.codec import FrameReader, decode, encode, encode_body
from phantom.protocol.framing import cobs_decode, cobs_encode, crc16_mcrf4xx
from phantom.protocol.messages import MESSAGES

_INTEGER_RANGES = {
    "u8": (0, 0xFF), "i8": (-0x80, 0x7F), "u16": (0, 0xFFFF), "i16": (-0x8000, 0x7FFF),
    "u32": (0, 0xFFFFFFFF), "i32": (-0x80000000, 0x7FFFFFFF),
}


def _value(wire_type):
    if wire_type == "f32":
        return st.floats(width=32, allow_nan=False)
    low, high = _INTEGER_RANGES[wire_type]
    return st.integers(low, high)


@st.composite
def messages(draw):
    """A random message of the spec with random in-range field values."""
    spec = draw(st.sampled_from(list(MESSAGES.values())))
    fields = {}
    for f in spec.fields:
        element = _value(f.type)
        fields[f.name] = draw(st.lists(element, min_size=f.count, max_size=f.count)) if f.count > 1 else draw(element)
    return spec.name, draw(st.integers(0, 255)), fields


def _crc_ok(body: bytes) -> bool:
    return crc16_mcrf4xx(body[:-2]) == struct.unpack("<H", body[-2:])[0]


@settings(max_examples=400, deadline=None)
@given(messages())
def test_every_message_round_trips(case):
    name, seq, fields = case
    message = decode(encode(name, seq, fields))
    assert (message.name, message.seq) == (name, seq)
    assert message.fields == fields


@settings(max_examples=400, deadline=None)
@given(st.binary(max_size=300))
def test_cobs_round_trips_and_never_emits_a_delimiter(raw):
    encoded = cobs_encode(raw)
    assert 0 not in encoded
    assert len(encoded) <= len(raw) + len(raw) // 254 + 1
    assert cobs_decode(encoded) == raw


@settings(max_examples=600, deadline=None)
@given(st.binary(max_size=400))
def test_random_bytes_never_crash_and_only_crc_valid_frames_pass(stream):
    reader = FrameReader()
    for message in reader.feed(stream):
        body = encode_body(message.name, message.seq, message.fields)
        assert _crc_ok(body)
    try:
        decode(stream)
    except ProtocolError:
        pass


@settings(max_examples=400, deadline=None)
@given(messages(), st.data())
def test_any_corruption_of_a_frame_is_never_accepted_as_a_different_frame(case, data):
    name, seq, fields = case
    body = bytearray(encode_body(name, seq, fields))
    # a burst of up to 16 flipped bits: CRC-16 detects every such error, so the frame must be dropped
    start = data.draw(st.integers(0, len(body) * 8 - 1))
    length = data.draw(st.integers(1, min(16, len(body) * 8 - start)))
    pattern = data.draw(st.integers(1, (1 << length) - 1).filter(lambda p: p & 1 and p >> (length - 1)))
    for bit in range(length):
        if pattern >> bit & 1:
            position = start + bit
            body[position // 8] ^= 1 << (position % 8)
    reader = FrameReader()
    assert reader.feed(cobs_encode(bytes(body)) + b"\x00") == []
    assert reader.bad_crc == 1


@settings(max_examples=300, deadline=None)
@given(st.lists(messages(), min_size=1, max_size=6), st.lists(st.binary(max_size=40), min_size=7, max_size=7),
       st.data())
def test_reader_resynchronises_after_garbage_and_any_split(cases, garbage, data):
    frames = [encode(*case) for case in cases]
    # garbage ends with a delimiter, so it can never glue itself onto the next real frame
    stream = b"".join(g + b"\x00" + f for g, f in zip(garbage, frames, strict=False)) + garbage[-1]
    cuts = sorted(data.draw(st.lists(st.integers(0, len(stream)), max_size=10)))
    reader = FrameReader()
    got = []
    for a, b in zip([0, *cuts], [*cuts, len(stream)], strict=True):
        got += reader.feed(stream[a:b])
    wanted = [(name, seq, fields) for name, seq, fields in cases]
    # garbage may itself hold a CRC-valid frame by chance (p ~ 2^-16 each): keep only the real ones, in order
    real = [(m.name, m.seq, m.fields) for m in got]
    index = 0
    for item in real:
        if index < len(wanted) and _same(item, wanted[index]):
            index += 1
    assert index == len(wanted)


def _same(a, b):
    if a[:2] != b[:2]:
        return False
    for key, value in a[2].items():
        other = b[2][key]
        if isinstance(value, float) and math.isnan(value) and math.isnan(other):
            continue
        if value != other:
            return False
    return True
