"""The wire protocol's Python side: framing against independent references, golden vectors, the streaming
reader, the handshake check, and the generated files' freshness."""

import json
import re
from pathlib import Path

import pytest

from phantom import PhantomError
from phantom.protocol import ProtocolError, generate
from phantom.protocol.codec import (
    MAX_FRAME_BYTES,
    FrameReader,
    Message,
    check_hello_reply,
    decode,
    decode_body,
    encode,
    encode_body,
)
from phantom.protocol.framing import cobs_decode, cobs_encode, crc16_mcrf4xx
from phantom.protocol.messages import MAX_BODY_BYTES, MESSAGES, PROTOCOL_VERSION, SPEC_HASH

VECTOR_DIR = Path(generate.PROTOCOL_DIR) / "vectors"
VECTORS = json.loads((VECTOR_DIR / "messages.json").read_text())
INVALID = json.loads((VECTOR_DIR / "invalid" / "frames.json").read_text())


def test_crc_matches_the_catalogue_check_value():
    # CRC-16/MCRF4XX's catalogued check value (reveng CRC catalogue): "123456789" -> 0x6F91.
    assert crc16_mcrf4xx(b"123456789") == 0x6F91


@pytest.mark.parametrize(
    ("raw", "encoded"),
    [  # the worked examples of the COBS paper (Cheshire & Baker 1999) as listed on Wikipedia
        (b"\x00", b"\x01\x01"),
        (b"\x00\x00", b"\x01\x01\x01"),
        (b"\x00\x11\x00", b"\x01\x02\x11\x01"),
        (b"\x11\x22\x00\x33", b"\x03\x11\x22\x02\x33"),
        (b"\x11\x22\x33\x44", b"\x05\x11\x22\x33\x44"),
        (b"\x11\x00\x00\x00", b"\x02\x11\x01\x01\x01"),
        (bytes(range(1, 255)), b"\xff" + bytes(range(1, 255)) + b"\x01"),
    ],
)
def test_cobs_matches_published_examples(raw, encoded):
    assert cobs_encode(raw) == encoded
    assert cobs_decode(encoded) == raw


def test_every_message_has_golden_vectors():
    assert {v["message"] for v in VECTORS} == set(MESSAGES)


@pytest.mark.parametrize("vector", VECTORS, ids=[v["name"] for v in VECTORS])
def test_golden_vector_decodes_and_reencodes(vector):
    frame = bytes.fromhex(vector["frame_hex"])
    message = decode(frame)
    assert message == Message(vector["message"], MESSAGES[vector["message"]].msg_id, vector["seq"], vector["fields"])
    assert encode(vector["message"], vector["seq"], vector["fields"]) == frame
    assert frame.count(0) == 1 and frame.endswith(b"\x00")


def test_worked_example_of_protocol_md_is_built_by_hand():
    # SET_SETPOINTS seq 7, setpoints 2000, 0, 1500 Pa, laid out byte by byte as PROTOCOL.md does it.
    body_head = bytes([0x10, 0x07, 0xD0, 0x07, 0x00, 0x00, 0xDC, 0x05])
    crc = crc16_mcrf4xx(body_head)
    body = body_head + bytes([crc & 0xFF, crc >> 8])
    assert encode_body("SET_SETPOINTS", 7, {"setpoint_pa": [2000, 0, 1500]}) == body
    assert encode("SET_SETPOINTS", 7, {"setpoint_pa": [2000, 0, 1500]}).hex() == "051007d0070105dc05c53400"


@pytest.mark.parametrize("vector", INVALID, ids=[v["name"] for v in INVALID])
def test_invalid_frames_are_refused_and_counted(vector):
    frame = bytes.fromhex(vector["frame_hex"])
    with pytest.raises(ProtocolError):
        decode(frame)
    reader = FrameReader()
    assert reader.feed(frame) == []
    assert getattr(reader, vector["error"]) == 1
    assert reader.frames_ok == 0


def test_protocol_error_is_a_user_facing_error():
    assert issubclass(ProtocolError, PhantomError)


@pytest.mark.parametrize(
    ("name", "seq", "fields", "complaint"),
    [
        ("NOPE", 0, {}, "unknown message"),
        ("VENT", 256, {}, "seq"),
        ("VENT", -1, {}, "seq"),
        ("VENT", 0, {"extra": 1}, "unknown"),
        ("PING", 0, {}, "missing"),
        ("PING", 0, {"host_time_ms": -1}, "outside u32"),
        ("PING", 0, {"host_time_ms": 2**32}, "outside u32"),
        ("PING", 0, {"host_time_ms": 1.5}, "integer"),
        ("PING", 0, {"host_time_ms": True}, "integer"),
        ("SET_SETPOINTS", 0, {"setpoint_pa": [1, 2]}, "list of 3"),
        ("SET_SETPOINTS", 0, {"setpoint_pa": 5}, "list of 3"),
        ("SET_SETPOINTS", 0, {"setpoint_pa": [0, 0, 40000]}, "outside i16"),
        ("SET_PID", 0, {"chamber": 0, "kp_per_kpa": "1", "ki_per_kpa_s": 0.0, "kd_s_per_kpa": 0.0,
                        "max_pressure_pa": 1, "max_drive": 1}, "number"),
        ("SET_PID", 0, {"chamber": 0, "kp_per_kpa": 1e39, "ki_per_kpa_s": 0.0, "kd_s_per_kpa": 0.0,
                        "max_pressure_pa": 1, "max_drive": 1}, "32-bit float"),
    ],
)
def test_encode_refuses_bad_input_with_a_clear_message(name, seq, fields, complaint):
    with pytest.raises(ProtocolError, match=complaint):
        encode(name, seq, fields)


def test_decode_refuses_empty_and_embedded_delimiters():
    with pytest.raises(ProtocolError, match="empty"):
        decode(b"\x00")
    frame = encode("VENT", 1, {})
    with pytest.raises(ProtocolError, match="0x00 inside"):
        decode(frame[:2] + b"\x00" + frame[2:])


def test_decode_body_checks_crc_before_id_and_length():
    with pytest.raises(ProtocolError, match="bad CRC"):
        decode_body(bytes([0x7F, 0, 0, 0]))
    with pytest.raises(ProtocolError, match="shorter"):
        decode_body(b"\x01\x02\x03")
    with pytest.raises(ProtocolError, match="exceeds"):
        decode_body(bytes(MAX_BODY_BYTES + 1))


def test_reader_handles_frames_split_at_every_byte_and_garbage_between():
    frames = [bytes.fromhex(v["frame_hex"]) for v in VECTORS]
    garbage = b"\x13\x37\xff\xfe garbage \x00\x00\x01\x00"
    stream = garbage + garbage.join(frames) + garbage
    reader = FrameReader()
    got = []
    for byte in stream:
        got += reader.feed(bytes([byte]))
    assert [m.name for m in got] == [v["message"] for v in VECTORS]
    assert [m.fields for m in got] == [v["fields"] for v in VECTORS]
    assert reader.frames_ok == len(VECTORS)


def test_reader_drops_an_overlong_frame_and_resynchronises():
    reader = FrameReader()
    good = encode("PING", 3, {"host_time_ms": 77})
    assert reader.feed(b"\x01" * (MAX_FRAME_BYTES + 10)) == []
    assert reader.overflow == 1
    # the bytes after the overflow up to the next delimiter belong to the lost frame
    assert reader.feed(good) == []
    assert [m.fields for m in reader.feed(good)] == [{"host_time_ms": 77}]
    assert reader.overflow == 1 and reader.frames_ok == 1


def test_reader_accepts_the_longest_legal_frame():
    # TELEMETRY is the largest message; a body of exactly MAX_BODY_BYTES must pass through the reader.
    largest = max(MESSAGES.values(), key=lambda m: m.payload_size)
    assert largest.payload_size + 4 <= MAX_BODY_BYTES
    vector = next(v for v in VECTORS if v["message"] == largest.name)
    assert len(FrameReader().feed(bytes.fromhex(vector["frame_hex"]))) == 1


def _hello_reply(spec_hash, status=0, version=PROTOCOL_VERSION):
    return Message("HELLO_REPLY", 2, 0, {
        "protocol_version": version, "spec_hash": spec_hash, "status": status, "firmware_major": 0,
        "firmware_minor": 1, "firmware_patch": 0, "board": 1, "chamber_count": 3, "reset_cause": 1,
        "fault_flags": 0, "time_ms": 0})


def test_handshake_accepts_the_same_spec_and_names_both_sides_on_a_mismatch():
    check_hello_reply(_hello_reply(SPEC_HASH))
    with pytest.raises(ProtocolError) as info:
        check_hello_reply(_hello_reply(0x12345678, status=7, version=9))
    text = str(info.value)
    assert "v9" in text and "0x12345678" in text
    assert f"v{PROTOCOL_VERSION}" in text and f"0x{SPEC_HASH:08X}" in text


def test_generated_files_are_fresh():
    assert generate.main(["--check"]) == 0, "run `python -m phantom.protocol.generate`"


def test_stale_generated_file_is_detected(tmp_path, monkeypatch, capsys):
    spec = generate.load_spec()
    stale = tmp_path / "messages.py"
    stale.write_text(generate.render_python(spec).replace("PROTOCOL_VERSION = ", "PROTOCOL_VERSION = 1 + "))
    fresh = tmp_path / "protocol_generated.h"
    fresh.write_text(generate.render_header(spec))
    monkeypatch.setattr(generate, "PYTHON_OUT", stale)
    monkeypatch.setattr(generate, "HEADER_OUT", fresh)
    assert generate.main(["--check"]) == 1
    assert "messages.py" in capsys.readouterr().err


def test_stale_message_reference_in_protocol_md_is_detected(tmp_path, monkeypatch, capsys):
    doc = tmp_path / "PROTOCOL.md"
    doc.write_text(generate.DOC_PATH.read_text().replace("| `0x10` | [SET_SETPOINTS]", "| `0x11` | [SET_SETPOINTS]"))
    monkeypatch.setattr(generate, "DOC_PATH", doc)
    assert generate.main(["--check"]) == 1
    assert "PROTOCOL.md" in capsys.readouterr().err
    doc.write_text("no markers here")
    with pytest.raises(ProtocolError, match="markers"):
        generate.main(["--check"])


def test_spec_hash_ignores_docs_but_follows_layout():
    spec = generate.load_spec()
    assert generate.spec_hash(spec) == SPEC_HASH
    spec["message"][0]["doc"] = "changed words"
    assert generate.spec_hash(spec) == SPEC_HASH
    spec["message"][0]["fields"][0]["type"] = "u32"
    assert generate.spec_hash(spec) != SPEC_HASH


def test_spec_validation_names_the_problem():
    spec = generate.load_spec()
    spec["message"][1]["id"] = spec["message"][0]["id"]
    with pytest.raises(ProtocolError, match="repeats"):
        generate._validate(spec)
    spec = generate.load_spec()
    spec["message"][0]["fields"].append({"name": "big", "type": "u32", "count": 20})
    with pytest.raises(ProtocolError, match="exceeds 64"):
        generate._validate(spec)


def test_constants_reach_both_sides_and_the_spec_hash():
    """The [constants] table is one source: the Python table and the C++ header carry the same values, a changed
    constant changes the spec hash, and a constant that does not fit its type is refused."""
    from phantom.protocol.messages import CONSTANTS

    spec = generate.load_spec()
    assert CONSTANTS == {name: entry["value"] for name, entry in spec["constants"].items()}
    header = generate.HEADER_OUT.read_text()
    for name, value in CONSTANTS.items():
        assert re.search(rf"const \w+ {name} = (0x{value:08X}UL|{value});", header), name
    spec["constants"]["PRESSURE_CEILING_PA"]["value"] = 6001
    assert generate.spec_hash(spec) != SPEC_HASH
    spec["constants"]["PRESSURE_CEILING_PA"]["value"] = 40000
    with pytest.raises(ProtocolError, match="PRESSURE_CEILING_PA = 40000 does not fit i16"):
        generate.constants(spec)
    spec = generate.load_spec()
    spec["constants"]["TICK_HZ"]["type"] = "f32"
    with pytest.raises(ProtocolError, match="TICK_HZ type"):
        generate.constants(spec)


def test_one_count_of_the_pressure_reading_is_the_datasheets():
    """The host's ADC count, from the spec's sensor constants, against the MPXV7025G's datasheet (Vout / Vs = 0.018
    P[kPa] + 0.5) over a 10-bit ADC of Vs (the firmware's own conversion is tested against it in firmware/test)."""
    from phantom.protocol.sensor import ADC_COUNT_KPA

    assert ADC_COUNT_KPA == pytest.approx(5.0 / 1024 / (5.0 * 0.018), rel=1e-12)
