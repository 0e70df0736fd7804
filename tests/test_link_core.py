"""The link rules of protocol/PROTOCOL.md, checked on the sans-I/O core with a fake clock.

``HostLink`` gets bytes and a time and gives frames and events; the peer is ``BoardPeer``, the board's end of
the same framing. No port, no thread, no sleep: each test says what time it is. The drivers over a real pty,
CAN bus and simavr are tested in test_link_session.py, test_link_board.py and test_link_sim.py.
"""

import pytest

from phantom.protocol.codec import FrameReader, Message, encode
from phantom.protocol.errors import ProtocolError
from phantom.protocol.link import (
    Acked,
    BoardPeer,
    BoardRestarted,
    CommandFailed,
    FaultIn,
    FrameIn,
    HandshakeDone,
    HandshakeRefused,
    HandshakeTimedOut,
    HostLink,
    LinkBooting,
    LinkTiming,
    Nacked,
    Pong,
    Silence,
    TelemetryIn,
    fault_names,
)
from phantom.protocol.messages import PROTOCOL_VERSION, SPEC_HASH, Fault, MsgId, Status


def sent(link: HostLink) -> list[Message]:
    """Decode what the host would write now."""
    reader = FrameReader()
    return [m for frame in link.take_output() for m in reader.feed(frame)]


def kinds(events) -> list[str]:
    return [type(e).__name__ for e in events if not isinstance(e, FrameIn)]


def open_session(link: HostLink, peer: BoardPeer, now: float = 0.0) -> float:
    """Open, answer the HELLO, return the time."""
    link.open(now)
    (hello,) = sent(link)
    assert hello.msg_id == MsgId.HELLO
    events = link.receive(peer.answer(hello, 10), now + 0.01)
    assert kinds(events) == ["HandshakeDone"]
    return now + 0.01


def test_handshake_sends_hello_with_this_spec_and_reports_the_board():
    link, peer = HostLink(), BoardPeer(reset_cause="WATCHDOG", board="MEGA2560")
    link.open(0.0)
    (hello,) = sent(link)
    assert hello.fields == {"protocol_version": PROTOCOL_VERSION, "spec_hash": SPEC_HASH}
    events = link.receive(peer.answer(hello, 1234), 0.02)
    done = [e for e in events if isinstance(e, HandshakeDone)]
    assert len(done) == 1 and isinstance(events[0], FrameIn)
    assert done[0].board.board == "MEGA2560" and done[0].board.reset_cause == "WATCHDOG"
    assert link.session_open


def test_hello_is_repeated_every_interval_then_gives_up():
    timing = LinkTiming(hello_timeout_s=0.25, hello_attempts=4)
    link = HostLink(timing)
    link.open(0.0)
    assert len(sent(link)) == 1
    assert link.next_deadline() == pytest.approx(0.25)
    assert link.poll(0.2499) == [] and sent(link) == []
    times = [0.25, 0.5, 0.75]
    for t in times:
        assert link.poll(t) == []
        (hello,) = sent(link)
        assert hello.msg_id == MsgId.HELLO
    events = link.poll(1.0)
    assert events == [HandshakeTimedOut(4)]
    assert sent(link) == []


def test_a_board_from_another_spec_is_refused_with_both_hashes():
    link, peer = HostLink(), BoardPeer(spec_hash=SPEC_HASH ^ 0x1234)
    link.open(0.0)
    (hello,) = sent(link)
    reply = peer.answer(hello, 0)
    assert reply is not None
    (refused,) = [e for e in link.receive(reply, 0.01) if not isinstance(e, FrameIn)]
    assert isinstance(refused, HandshakeRefused)
    assert f"0x{SPEC_HASH ^ 0x1234:08X}" in refused.error and f"0x{SPEC_HASH:08X}" in refused.error
    assert not link.session_open


def test_boot_delay_sends_nothing_and_drops_what_arrives():
    link, peer = HostLink(LinkTiming(boot_delay_s=1.5)), BoardPeer()
    link.open(10.0)
    assert sent(link) == [] and link.next_deadline() == pytest.approx(11.5)
    # the bootloader's chatter, and even a valid frame, are dropped while it may still be listening
    assert link.receive(b"\x14\x10garbage" + peer.frame("PONG", {"host_time_ms": 1, "board_time_ms": 2}), 10.5) == []
    assert link.counters.boot_bytes_dropped > 0 and link.counters.frames_rx == 0
    with pytest.raises(LinkBooting, match="bootloader"):
        link.command("VENT", None, 11.0)
    assert link.poll(11.49) == [] and sent(link) == []
    link.poll(11.5)
    (hello,) = sent(link)
    assert hello.msg_id == MsgId.HELLO
    # the silence clock starts after the boot delay, not at the port's opening
    assert link.poll(12.4) == []


def test_a_lost_answer_is_retransmitted_with_the_same_seq_and_doubling_waits():
    link, peer = HostLink(LinkTiming(silence_s=10.0)), BoardPeer()
    now = open_session(link, peer)
    seq = link.command("VENT", None, now)
    copies = sent(link)
    t = now
    # the documented waits: 100, 200, 400, 800 ms, the fifth copy also waits 800 ms (the cap)
    for wait_s in (0.1, 0.2, 0.4, 0.8):
        assert link.next_deadline() == pytest.approx(t + wait_s)
        assert link.poll(t + wait_s - 1e-6) == [] and sent(link) == []
        t += wait_s
        link.poll(t)
        copies += sent(link)
    assert [m.seq for m in copies] == [seq] * 5 and {m.msg_id for m in copies} == {MsgId.VENT}
    assert link.counters.retries == 4
    # the fifth copy is answered: one Acked, and a late answer to an earlier copy changes nothing
    ack = peer.ack(copies[-1])
    assert kinds(link.receive(ack, t + 0.05)) == ["Acked"]
    assert kinds(link.receive(peer.ack(copies[0]), t + 0.06)) == []


def test_a_command_never_answered_fails_after_five_sends():
    link, peer = HostLink(LinkTiming(silence_s=10.0)), BoardPeer()
    now = open_session(link, peer)
    seq = link.command("SET_SETPOINTS", {"setpoint_pa": [1, 2, 3]}, now)
    events = []
    t = now
    while not events:
        t = link.next_deadline()
        events = [e for e in link.poll(t) if isinstance(e, CommandFailed)]
        if t > now + 10:
            break
    assert events == [CommandFailed("SET_SETPOINTS", seq, 5)]
    assert t == pytest.approx(now + 0.1 + 0.2 + 0.4 + 0.8 + 0.8)
    assert link.counters.commands_failed == 1 and link.pending() == []


def test_zero_sensors_waits_longer_for_its_answer():
    assert LinkTiming().ack_waits_s("ZERO_SENSORS") == pytest.approx([0.3, 0.6, 0.8, 0.8, 0.8])
    assert LinkTiming().ack_waits_s("VENT", first_s=2.0, attempts=2) == pytest.approx([2.0, 2.0])
    link, peer = HostLink(), BoardPeer()
    now = open_session(link, peer)
    link.command("ZERO_SENSORS", None, now)
    assert link.next_deadline() == pytest.approx(now + 0.3)


def test_nack_carries_the_status_name_and_other_commands_stay_pending():
    link, peer = HostLink(), BoardPeer()
    now = open_session(link, peer)
    clear = link.command("CLEAR_FAULT", None, now)
    vent = link.command("VENT", None, now)
    clear_frame, vent_frame = sent(link)
    (nacked,) = [e for e in link.receive(peer.nack(clear_frame, "FAULT_ACTIVE"), now) if not isinstance(e, FrameIn)]
    assert isinstance(nacked, Nacked) and nacked.status == "FAULT_ACTIVE" and nacked.seq == clear
    assert link.pending() == [("VENT", vent)]
    (acked,) = [e for e in link.receive(peer.ack(vent_frame, "CLAMPED"), now) if not isinstance(e, FrameIn)]
    assert isinstance(acked, Acked) and acked.status == "CLAMPED" and acked.seq == vent
    assert link.counters.nacks == 1


def test_an_answer_matches_msg_id_and_seq_both():
    link, peer = HostLink(), BoardPeer()
    now = open_session(link, peer)
    seq = link.command("VENT", None, now)
    wrong_id = encode("ACK", 1, {"ref_msg_id": MsgId.CLEAR_FAULT, "ref_seq": seq, "status": Status.OK})
    wrong_seq = encode("ACK", 2, {"ref_msg_id": MsgId.VENT, "ref_seq": (seq + 1) & 0xFF, "status": Status.OK})
    assert kinds(link.receive(wrong_id + wrong_seq, now)) == []
    assert link.pending() == [("VENT", seq)]


def test_keepalive_pings_every_period_and_pong_gives_the_round_trip():
    link, peer = HostLink(LinkTiming(keepalive_s=0.1)), BoardPeer()
    now = open_session(link, peer)
    link.keepalive = True
    link.poll(now)
    (ping,) = sent(link)
    assert ping.msg_id == MsgId.PING
    assert link.next_deadline() == pytest.approx(now + 0.1)
    assert link.poll(now + 0.05) == [] and sent(link) == []
    pong = peer.pong(ping, 500)
    events = [e for e in link.receive(pong, now + 0.0123) if isinstance(e, Pong)]
    assert events[0].rtt_s == pytest.approx(0.0123) and events[0].board_time_ms == 500
    assert link.counters.rtt_ms == pytest.approx(12.3)
    link.poll(now + 0.1)
    assert [m.msg_id for m in sent(link)] == [MsgId.PING]
    # a PONG for a ping we never sent (or forgot) is ignored
    assert kinds(link.receive(peer.frame("PONG", {"host_time_ms": 7, "board_time_ms": 1}), now + 0.11)) == []
    link.keepalive = False
    assert link.poll(now + 0.3) == [] and sent(link) == []


def test_a_silent_board_is_reported_once():
    link, peer = HostLink(LinkTiming(silence_s=0.5)), BoardPeer()
    now = open_session(link, peer)
    assert link.poll(now + 0.49) == []
    assert link.poll(now + 0.5) == [Silence("no frame from the board for 0.5 s")]
    assert link.poll(now + 2.0) == []
    # anything arriving ends the silence; the next one is reported again
    link.receive(peer.telemetry(100, [0, 0, 0], [0, 0, 0]), now + 3.0)
    assert link.poll(now + 3.5) == [Silence("no frame from the board for 0.5 s")]


def test_no_telemetry_after_set_config_means_the_board_lost_its_session():
    link, peer = HostLink(LinkTiming(silence_s=0.5, keepalive_s=0.1)), BoardPeer()
    now = open_session(link, peer)
    link.command("SET_CONFIG", {"telemetry_period_ms": 20, "host_deadline_ms": 500}, now)
    (config,) = sent(link)
    link.receive(peer.ack(config), now)
    link.keepalive = True
    t, events = now, []
    # PONGs keep coming (a board without a session answers PING) but telemetry stopped
    while not events and t < now + 2:
        t += 0.1
        events = [e for e in link.poll(t) if isinstance(e, Silence)]
        for ping in sent(link):
            link.receive(peer.pong(ping, int(t * 1000)), t)
    assert events == [Silence("no telemetry from the board for 0.5 s (it lost its session)")]
    assert t == pytest.approx(now + 0.5)


def test_a_board_clock_that_goes_back_is_a_restart():
    link, peer = HostLink(), BoardPeer()
    now = open_session(link, peer)
    assert kinds(link.receive(peer.telemetry(5000, [0, 0, 0], [0, 0, 0]), now)) == ["TelemetryIn"]
    # a telemetry sample may be a little older than a PONG sent just before it: not a restart
    assert kinds(link.receive(peer.telemetry(4950, [0, 0, 0], [0, 0, 0]), now)) == ["TelemetryIn"]
    fault = peer.frame("FAULT", {"time_ms": 3, "fault_bit": 7, "fault_flags": Fault.WATCHDOG_RESET,
                                 "pressure_pa": [0, 0, 0]})
    events = [e for e in link.receive(fault, now) if not isinstance(e, FrameIn)]
    assert isinstance(events[0], FaultIn) and events[0].bit_name == "WATCHDOG_RESET"
    assert events[1] == BoardRestarted(4950, 3)
    assert not link.session_open


def test_garbage_and_a_partial_frame_are_counted_and_a_reopen_starts_clean():
    link, peer = HostLink(), BoardPeer()
    now = open_session(link, peer)
    pong = encode("PONG", 1, {"host_time_ms": 1, "board_time_ms": 2})
    link.receive(b"\x13\x37garbage\x00" + pong[:-3] + b"\x55\x00", now)
    assert sum(link.rx_dropped().values()) >= 2
    dropped = link.rx_dropped()
    # the cable is pulled in the middle of a frame; after the reopen, the first reply must not be swallowed
    link.receive(peer.telemetry(1, [0, 0, 0], [0, 0, 0])[:20], now)
    link.open(now + 1)
    (hello,) = sent(link)
    assert kinds(link.receive(peer.answer(hello, 5), now + 1.01)) == ["HandshakeDone"]
    assert link.rx_dropped() == dropped  # counters carry over the reopen


def test_telemetry_and_fault_events():
    link, peer = HostLink(), BoardPeer()
    now = open_session(link, peer)
    (telemetry,) = [e for e in link.receive(peer.telemetry(100, [1, 2, 3], [4, 5, 6]), now)
                    if isinstance(e, TelemetryIn)]
    assert telemetry.message.fields["pressure_pa"] == [1, 2, 3]


def test_commands_and_sends_are_checked():
    link = HostLink()
    link.open(0.0)
    with pytest.raises(ProtocolError, match="not an acknowledged command"):
        link.command("PING", {"host_time_ms": 1}, 0.0)
    with pytest.raises(ProtocolError, match="unknown message 'VENTS'"):
        link.command("VENTS", None, 0.0)
    with pytest.raises(ProtocolError, match="attempts must be at least 1"):
        link.command("VENT", None, 0.0, attempts=0)
    sent(link)
    link.send_raw(b"\x01\x02\x00", 0.0)
    assert link.take_output() == [b"\x01\x02\x00"]


def test_sequence_numbers_wrap_after_255():
    link = HostLink()
    link.open(0.0)
    seqs = [link.send("PING", {"host_time_ms": i}, 0.0) for i in range(300)]
    assert seqs[:2] == [2, 3] and max(seqs) == 255 and 0 in seqs  # 1 went to the HELLO


def test_fault_names_follow_the_spec_bits():
    assert fault_names(Fault.DEAD_HOST | Fault.OVERPRESSURE_1) == ["OVERPRESSURE_1", "DEAD_HOST"]
    assert fault_names(0) == []
    assert fault_names(1 << 15) == ["BIT15"]
