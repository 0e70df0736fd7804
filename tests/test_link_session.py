"""The link session over real transports (a pseudo-terminal, python-can's virtual bus) against a scripted peer.

The peer speaks through the link core's board end (phantom.protocol.link.BoardPeer) and is the one fake here: it
stands in for the firmware so that the asyncio driver (handshake over a port, spec-hash refusal, retransmission,
NACK, keepalive, loss and reconnection with the reset cause, boot delay, logging of link problems) can be
checked over a real pty, including the cases a real board makes hard to provoke on demand. The link rules
themselves, with their exact times, are checked on a fake clock in test_link_core.py. The end-to-end proof
against the real firmware in simavr is tests/test_daemon_e2e.py.
"""

import asyncio
import logging
import os
import re
import threading
import time
import tty

import pytest
from daemon_rig import wait_for

from phantom.host.session import CommandRejected, LinkDown, LinkSession, LinkState, LinkTiming
from phantom.host.transports import (
    CanReassembler,
    CanTransport,
    SerialTransport,
    TransportLost,
    TransportUnavailable,
    can_frames,
    frame_bytes,
)
from phantom.protocol.codec import MAX_FRAME_BYTES, FrameReader, encode
from phantom.protocol.link import BoardPeer
from phantom.protocol.messages import MESSAGES, SPEC_HASH, ChamberState, Fault

FAST = LinkTiming(ack_timeout_s=0.05, command_attempts=4, keepalive_s=0.05, silence_s=0.5, hello_timeout_s=0.2,
                  hello_attempts=3, reconnect_s=0.05, incompatible_retry_s=0.3)


class ScriptedBoard:
    """A stand-in board on a pty: answers HELLO, ACKs commands, PONGs pings, streams telemetry.

    It speaks through ``BoardPeer`` (the board's end of the link core). ``drop_first`` acked frames are ignored
    (to force retransmission); ``nack`` maps a command name to a status name to refuse it with; ``spec_hash``
    and ``reset_cause`` are what HELLO_REPLY says.
    """

    def __init__(self, link_path, spec_hash=SPEC_HASH, reset_cause="POWER_ON", drop_first=0, nack=None):
        self.link_path = str(link_path)
        self.peer = BoardPeer(spec_hash=spec_hash, reset_cause=reset_cause)
        self.drop_first = drop_first
        self.nack = nack or {}
        self.received = []
        self.received_at = []
        self.setpoints_pa = [0, 0, 0]
        self.time0 = time.monotonic()
        self._master = None
        self._stop = threading.Event()
        self._threads = []
        self.plug()

    def plug(self):
        master, slave = os.openpty()
        tty.setraw(slave)
        self._slave_name = os.ttyname(slave)
        os.close(slave)
        self._master = master
        self.plugged_at = time.monotonic()
        self.peer.reader = FrameReader()
        os.symlink(self._slave_name, self.link_path)
        self._stop.clear()
        self._threads = [threading.Thread(target=self._serve, daemon=True),
                         threading.Thread(target=self._stream, daemon=True)]
        for thread in self._threads:
            thread.start()

    def unplug(self):
        self._stop.set()
        for thread in self._threads:
            thread.join(2)
        os.unlink(self.link_path)
        os.close(self._master)
        self._master = None

    def _time_ms(self):
        return int((time.monotonic() - self.time0) * 1000)

    def _write(self, frame):
        if self._master is not None and frame is not None:
            try:
                os.write(self._master, frame)
            except OSError:
                pass

    def _stream(self):
        while not self._stop.wait(0.02):
            self._write(self.peer.telemetry(self._time_ms(), self.setpoints_pa, self.setpoints_pa,
                                            drive=[1000, 2000, 3000], states=[ChamberState.REGULATING] * 3))

    def _serve(self):
        import select

        while not self._stop.is_set():
            ready, _, _ = select.select([self._master], [], [], 0.02)
            if not ready:
                continue
            try:
                data = os.read(self._master, 4096)
            except OSError:
                continue
            for message in self.peer.receive(data):
                self.received.append(message)
                self.received_at.append(time.monotonic())
                self._answer(message)

    def _answer(self, message):
        if MESSAGES[message.name].acked:
            if self.drop_first > 0:
                self.drop_first -= 1
                return
            if message.name in self.nack:
                self._write(self.peer.nack(message, self.nack[message.name]))
                return
            if message.name == "SET_SETPOINTS":
                self.setpoints_pa = list(message.fields["setpoint_pa"])
        self._write(self.peer.answer(message, self._time_ms()))


def run_session(transport, script, timing=FAST, **callbacks):
    """Run a LinkSession on ``transport`` while ``script(session)`` (a coroutine) runs; return its result."""

    async def main():
        session = LinkSession(transport, timing, **callbacks)
        task = asyncio.create_task(session.run())
        try:
            return await asyncio.wait_for(script(session), 20)
        finally:
            session.stop()
            await asyncio.wait_for(task, 5)

    return asyncio.run(main())



def test_handshake_config_setpoints_and_telemetry_over_a_pty(tmp_path):
    board = ScriptedBoard(tmp_path / "board")
    telemetry = []

    async def script(session):
        await asyncio.wait_for(session.online_event.wait(), 5)
        assert session.board.board == "UNO" and session.board.reset_cause == "POWER_ON"
        assert await session.command("SET_SETPOINTS", {"setpoint_pa": [1000, 1500, 0]}) == "OK"
        await wait_for(lambda: telemetry and telemetry[-1].setpoints_pa.tolist() == [1000, 1500, 0])
        await wait_for(lambda: session.stats.rtt_ms is not None)
        return session.status()

    try:
        status = run_session(SerialTransport(tmp_path / "board"), script, on_telemetry=telemetry.append)
    finally:
        board.unplug()
    names = [message.name for message in board.received]
    assert names[0] == "HELLO" and names[1] == "SET_CONFIG"
    config = board.received[1].fields
    assert config == {"telemetry_period_ms": 20, "host_deadline_ms": 500}
    assert "PING" in names
    assert status["state"] == "online"
    assert 0 <= status["stats"]["rtt_ms"] < 200
    last = telemetry[-1]
    assert last.drive_levels == pytest.approx([1000 / 65535, 2000 / 65535, 3000 / 65535])
    assert last.states == ["REGULATING"] * 3


def test_lost_acks_are_retransmitted_with_the_same_seq(tmp_path):
    board = ScriptedBoard(tmp_path / "board")

    async def script(session):
        await asyncio.wait_for(session.online_event.wait(), 5)
        board.drop_first = 2
        started = time.monotonic()
        assert await session.command("VENT") == "OK"
        return time.monotonic() - started, session.stats.retries

    try:
        elapsed_s, retries = run_session(SerialTransport(tmp_path / "board"), script)
    finally:
        board.unplug()
    vents = [message for message in board.received if message.name == "VENT"]
    assert len(vents) == 3 and len({message.seq for message in vents}) == 1
    assert retries == 2
    # the waits themselves are checked on a fake clock (test_link_core.py); here only their lower bound
    assert elapsed_s >= 0.05 + 0.1


def test_a_command_never_acknowledged_fails_after_every_attempt(tmp_path):
    board = ScriptedBoard(tmp_path / "board")

    async def script(session):
        await asyncio.wait_for(session.online_event.wait(), 5)
        board.drop_first = 100
        with pytest.raises(LinkDown, match="not acknowledged after 4 attempts"):
            await session.command("VENT")
        return session.stats.commands_failed

    try:
        assert run_session(SerialTransport(tmp_path / "board"), script) == 1
    finally:
        board.unplug()


def test_a_nack_names_the_status_and_what_to_do(tmp_path):
    board = ScriptedBoard(tmp_path / "board", nack={"CLEAR_FAULT": "FAULT_ACTIVE"})

    async def script(session):
        await asyncio.wait_for(session.online_event.wait(), 5)
        with pytest.raises(CommandRejected, match="FAULT_ACTIVE .*cause is still present") as error:
            await session.command("CLEAR_FAULT")
        return error.value.status

    try:
        assert run_session(SerialTransport(tmp_path / "board"), script) == "FAULT_ACTIVE"
    finally:
        board.unplug()


def test_a_board_built_from_another_spec_is_refused_with_both_hashes(tmp_path):
    board = ScriptedBoard(tmp_path / "board", spec_hash=SPEC_HASH ^ 0x1234)
    events = []

    async def script(session):
        await wait_for(lambda: session.state is LinkState.INCOMPATIBLE)
        with pytest.raises(LinkDown, match="incompatible"):
            await session.command("VENT")
        return session.last_error

    try:
        error = run_session(SerialTransport(tmp_path / "board"), script, on_event=lambda *e: events.append(e))
    finally:
        board.unplug()
    assert f"0x{SPEC_HASH ^ 0x1234:08X}" in error and f"0x{SPEC_HASH:08X}" in error
    assert events[0][0] == "incompatible"
    assert not any(message.name == "SET_CONFIG" for message in board.received)


def test_unplug_and_replug_reconnects_reports_the_reset_cause_and_restores(tmp_path):
    board = ScriptedBoard(tmp_path / "board")
    events = []
    onlines = []

    async def on_online(info, reconnected):
        onlines.append((info.reset_cause, reconnected))

    async def script(session):
        await asyncio.wait_for(session.online_event.wait(), 5)
        board._stop.set()
        # the cable is pulled in the middle of a frame: its first half must not spoil the next connection
        os.write(board._master, encode("TELEMETRY", 0, {
            "time_ms": 1, "pressure_pa": [1, 2, 3], "setpoint_pa": [0, 0, 0], "drive": [0, 0, 0], "state": [0, 0, 0],
            "fault_flags": 0, "rx_bad_crc": 0, "rx_overflow": 0, "rx_bad_frame": 0, "tx_dropped": 0,
            "tick_overruns": 0})[:20])
        await asyncio.sleep(0.1)
        board.unplug()
        await wait_for(lambda: session.state is LinkState.DISCONNECTED)
        with pytest.raises(LinkDown, match="disconnected"):
            await session.command("VENT")
        board.peer.reset_cause = "WATCHDOG"
        board.peer.fault_flags = Fault.WATCHDOG_RESET
        board.plug()
        await wait_for(lambda: session.state is LinkState.ONLINE and session.stats.reconnects == 1)
        return session.stats

    try:
        stats = run_session(SerialTransport(tmp_path / "board"), script, on_online=on_online,
                            on_event=lambda *e: events.append(e))
    finally:
        board.unplug()
    assert onlines == [("POWER_ON", False), ("WATCHDOG", True)]
    kinds = [event[0] for event in events]
    assert kinds == ["connected", "link_lost", "reconnected", "fault"]
    assert "reset cause WATCHDOG" in events[2][1] and "link restored after" in events[2][1]
    assert "WATCHDOG_RESET" in events[3][1]
    assert stats.links_lost == 1 and stats.connects == 2
    # one HELLO per connection: the reply after the replug was not lost to the half frame
    assert [message.name for message in board.received].count("HELLO") == 2


def test_a_silent_board_is_declared_lost(tmp_path):
    board = ScriptedBoard(tmp_path / "board")

    async def script(session):
        await asyncio.wait_for(session.online_event.wait(), 5)
        board._stop.set()  # the board hangs: the port stays, nothing comes
        await wait_for(lambda: session.state is not LinkState.ONLINE, 3)
        return session.last_error

    try:
        error = run_session(SerialTransport(tmp_path / "board"), script)
    finally:
        board.unplug()
    # telemetry and PONGs stop together: whichever stream was last heard of decides which of the two silences
    # (no frame at all, or no telemetry while PONGs still came) is seen first
    assert re.search(r"no (frame|telemetry) from the board for 0\.5 s", error), error


def test_garbage_on_the_line_is_counted_and_the_link_survives(tmp_path):
    board = ScriptedBoard(tmp_path / "board")

    async def script(session):
        await asyncio.wait_for(session.online_event.wait(), 5)
        os.write(board._master, b"\x13\x37garbage\x00" + encode("PONG", 1, {"host_time_ms": 1, "board_time_ms": 2})[
            :-3] + b"\x55\x00")
        assert await session.command("VENT") == "OK"
        return session.status()["stats"]

    try:
        stats = run_session(SerialTransport(tmp_path / "board"), script)
    finally:
        board.unplug()
    assert stats["bad_frames"] >= 2


def test_missing_port_is_unavailable_not_a_crash(tmp_path):
    async def main():
        with pytest.raises(TransportUnavailable, match="does not exist"):
            await SerialTransport(tmp_path / "nothing").open()

    asyncio.run(main())


def test_a_port_this_user_may_not_open_names_the_ports_group(tmp_path, monkeypatch):
    import grp

    # the tests run as root, for whom every file is accessible: the permission check is made to fail
    port = tmp_path / "ttyACM0"
    port.touch()
    group = grp.getgrgid(os.stat(port).st_gid).gr_name
    monkeypatch.setattr(os, "access", lambda path, mode: False)

    async def main():
        with pytest.raises(TransportUnavailable, match=f"permission denied on .*ttyACM0: add your user to the {group} "
                           f"group, which owns the port \\(sudo usermod -aG {group} "):
            await SerialTransport(port).open()

    asyncio.run(main())


def test_a_link_problem_is_logged_once_when_it_starts_and_once_when_it_ends(tmp_path, caplog):
    caplog.set_level(logging.INFO, logger="phantom.host.session")

    async def script(session):
        await wait_for(lambda: session.state is LinkState.DISCONNECTED and session.last_error)
        await asyncio.sleep(0.3)  # several reconnect attempts (every 0.05 s) fail the same way
        board = ScriptedBoard(tmp_path / "board")
        try:
            await asyncio.wait_for(session.online_event.wait(), 5)
        finally:
            board.unplug()
        return session.state

    run_session(SerialTransport(tmp_path / "board"), script)
    lines = [record for record in caplog.records if "link problem" in record.getMessage()]
    assert [record.levelname for record in lines[:2]] == ["WARNING", "INFO"]
    assert "does not exist" in lines[0].getMessage() and "over after" in lines[1].getMessage()


def test_the_boot_delay_holds_the_first_hello_back(tmp_path):
    board = ScriptedBoard(tmp_path / "board")
    timing = LinkTiming(**{**FAST.__dict__, "boot_delay_s": 0.4})

    async def script(session):
        await asyncio.wait_for(session.online_event.wait(), 5)
        return session.link.counters.boot_bytes_dropped

    try:
        dropped = run_session(SerialTransport(tmp_path / "board"), script, timing=timing)
    finally:
        board.unplug()
    first_hello = board.received_at[[m.name for m in board.received].index("HELLO")]
    assert first_hello - board.plugged_at >= 0.4
    # the board streamed telemetry meanwhile: a bootloader's bytes would be dropped the same way
    assert dropped > 0


# --- CAN ----------------------------------------------------------------------------------------------------


def test_can_mapping_splits_and_rebuilds_every_message_body():
    from phantom.protocol.codec import encode_body

    reassembler = CanReassembler(from_board=True)
    body = encode_body("TELEMETRY", 7, {
        "time_ms": 123456, "pressure_pa": [1, -2, 3], "setpoint_pa": [4, 5, 6], "drive": [7, 8, 65535],
        "state": [0, 1, 3], "fault_flags": 0x81, "rx_bad_crc": 1, "rx_overflow": 2, "rx_bad_frame": 3,
        "tx_dropped": 4, "tick_overruns": 5})
    frames = can_frames(body, to_board=False)
    assert all(arbitration_id == 0x200 + MESSAGES["TELEMETRY"].msg_id for arbitration_id, _ in frames)
    assert all(len(data) <= 8 for _, data in frames)
    assert len(frames) == -(-(len(body) - 1) // 7)
    results = [reassembler.feed(arbitration_id, data) for arbitration_id, data in frames]
    assert results[:-1] == [None] * (len(frames) - 1) and results[-1] == body
    # a lost middle segment drops the message rather than splicing a wrong one
    assert [reassembler.feed(i, d) for i, d in frames[:1] + frames[2:]] == [None] * (len(frames) - 1)
    assert reassembler.dropped_segments == len(frames) - 2  # every segment after the gap
    # the other direction's ids are not ours
    assert reassembler.feed(0x100 + 5, bytes([0, 1, 2])) is None


def test_session_over_python_can_virtual_bus():
    channel = f"phantom-test-{os.getpid()}"

    async def peer(bus_transport, stop):
        board = BoardPeer()
        while not stop.is_set():
            try:
                data = await asyncio.wait_for(bus_transport.read(), 0.1)
            except TimeoutError:
                continue
            for message in board.receive(data):
                answer = board.answer(message, 5)
                if answer is not None:
                    bus_transport.write(answer)

    async def main():
        board_side = CanTransport(channel, "virtual", role="board")
        await board_side.open()
        stop = asyncio.Event()
        peer_task = asyncio.create_task(peer(board_side, stop))
        timing = LinkTiming(ack_timeout_s=0.05, keepalive_s=0.05, silence_s=5.0, hello_timeout_s=0.2)
        session = LinkSession(CanTransport(channel, "virtual"), timing)
        task = asyncio.create_task(session.run())
        try:
            await asyncio.wait_for(session.online_event.wait(), 5)
            status = await session.command("SET_SETPOINTS", {"setpoint_pa": [1200, 0, 800]})
            await wait_for(lambda: session.stats.rtt_ms is not None)
            return status, session.board
        finally:
            session.stop()
            stop.set()
            await asyncio.wait_for(task, 5)
            await peer_task
            board_side.close()

    status, board = asyncio.run(main())
    assert status == "OK" and board.board == "UNO"


def test_can_transport_that_cannot_open_says_so():
    async def main():
        with pytest.raises(TransportUnavailable, match="cannot open CAN"):
            await CanTransport("no-such-can0", "socketcan").open()

    asyncio.run(main())


def test_reading_a_closed_transport_is_a_loss(tmp_path):
    async def main():
        transport = CanTransport("x", "virtual")
        with pytest.raises(TransportLost):
            await transport.read()

    asyncio.run(main())


# --- the bench's blocking driver (phantom.hil.link.BoardLink) -----------------------------------------------


def test_board_link_handshake_commands_nack_retransmission_and_keepalive(tmp_path):
    from phantom.hil.link import BoardLink, LinkError

    board = ScriptedBoard(tmp_path / "board", nack={"CLEAR_FAULT": "FAULT_ACTIVE"})
    try:
        with BoardLink(str(tmp_path / "board")) as link:
            reply = link.hello()
            assert reply.name == "HELLO_REPLY" and reply.fields["reset_cause"] == 1
            answer = link.command("SET_SETPOINTS", {"setpoint_pa": [700, 0, 0]})
            assert answer.name == "ACK" and board.setpoints_pa == [700, 0, 0]
            with pytest.raises(LinkError, match="refused CLEAR_FAULT: NACK FAULT_ACTIVE"):
                link.command("CLEAR_FAULT")
            assert link.command("CLEAR_FAULT", accept_nack=True).name == "NACK"
            board.drop_first = 2
            assert link.command("VENT").name == "ACK" and link.retransmissions == 2
            vents = [m for m in board.received if m.name == "VENT"]
            assert len(vents) == 3 and len({m.seq for m in vents}) == 1
            board.drop_first = 100
            with pytest.raises(LinkError, match="no ACK for VENT .* after 2 tries"):
                link.command("VENT", timeout_s=0.05, attempts=2)
            start = link.mark()
            link.keepalive(True)
            assert link.wait_for(lambda m: m.name == "PONG", 2.0, start) is not None
            got = link.wait_for(lambda m: m.name == "TELEMETRY", 2.0, start)
            assert got is not None and link.telemetry(start)[0] is got
    finally:
        board.unplug()


def test_board_link_refuses_another_spec_and_waits_out_the_boot_delay(tmp_path):
    from phantom.hil.link import BoardLink
    from phantom.protocol.errors import ProtocolError

    board = ScriptedBoard(tmp_path / "board", spec_hash=SPEC_HASH ^ 1)
    try:
        opened = time.monotonic()
        with BoardLink(str(tmp_path / "board"), boot_delay_s=0.3) as link:
            assert time.monotonic() - opened >= 0.3
            # what the board sent during the boot delay was dropped; a frame may arrive the moment it ends
            assert all(received.host_time_s >= opened + 0.3 for received in link.received)
            assert link.link.counters.boot_bytes_dropped > 0
            with pytest.raises(ProtocolError, match="protocol mismatch"):
                link.hello()
    finally:
        board.unplug()


def test_a_frame_that_arrives_a_byte_at_a_time_wakes_the_session_once(tmp_path):
    """Issue 23, defect 11: a pty delivers the simulated UART's bytes a few at a time, and each piece woke the link
    session (about 900 times a second, 5-14 % of a core, at 50 Hz telemetry). The transport hands on whole frames."""
    master, slave = os.openpty()
    tty.setraw(slave)
    link = tmp_path / "board"
    os.symlink(os.ttyname(slave), link)
    frames = [bytes([3, 1, 2, 4, 7, 8, 9, 0]), bytes([2, 5, 1, 6, 0])]
    noise = bytes(range(1, 256)) * 6                          # 1530 bytes without a delimiter

    def trickle(data):
        for byte in data:
            os.write(master, bytes([byte]))
            time.sleep(0.0005)

    async def script():
        transport = SerialTransport(link)
        await transport.open()
        reads = []
        try:
            writer = asyncio.get_running_loop().run_in_executor(None, trickle, b"".join(frames))
            while sum(map(len, reads)) < sum(map(len, frames)):
                reads.append(await asyncio.wait_for(transport.read(), 5))
            await writer
            os.write(master, noise)
            handed = b""
            while len(handed) < len(noise):
                handed += await asyncio.wait_for(transport.read(), 5)
        finally:
            transport.close()
        return reads, handed

    try:
        reads, handed = asyncio.run(script())
    finally:
        os.close(master)
        os.close(slave)
    assert b"".join(reads) == b"".join(frames)
    assert len(reads) <= len(frames)                          # before: a read per byte or few
    assert handed == noise                                    # bytes without a delimiter are not held for ever


def test_a_frame_that_arrives_at_the_ports_baud_rate_costs_a_few_reads_not_one_per_byte(tmp_path):
    """Issue 23, defect 11: handing on whole frames left the link's thread waking for every byte the pty
    delivered (strace of the idle daemon: 1300 one-byte reads a second, 7 % of a core in that thread). A frame
    begun is read again once its rest could have arrived at the port's baud rate."""
    master, slave = os.openpty()
    tty.setraw(slave)
    link = tmp_path / "board"
    os.symlink(os.ttyname(slave), link)
    baudrate = 9600
    byte_s = 10 / baudrate                                    # 8N1: 1.04 ms a byte
    frames = [bytes([30, *range(1, 30), 0])] * 3              # 31 bytes each, 32 ms at 9600 baud

    def uart():
        started = time.monotonic()
        for index, byte in enumerate(b"".join(frames)):
            gap_s = 0.1 * (index // len(frames[0]))           # the frames 100 ms apart, as telemetry is
            time.sleep(max(0.0, started + gap_s + index * byte_s - time.monotonic()))
            os.write(master, bytes([byte]))

    async def script():
        transport = SerialTransport(link, baudrate)
        await transport.open()
        handed = b""
        try:
            writer = asyncio.get_running_loop().run_in_executor(None, uart)
            while len(handed) < sum(map(len, frames)):
                handed += await asyncio.wait_for(transport.read(), 5)
            await writer
        finally:
            transport.close()
        return handed, transport.reads

    try:
        handed, reads = asyncio.run(script())
    finally:
        os.close(master)
        os.close(slave)
    assert handed == b"".join(frames)
    assert reads <= 3 * len(frames), reads                    # before: about one per byte, 93


def test_the_transport_knows_a_board_frames_length_from_its_first_two_bytes():
    """The wait for the rest of a frame is its own message's length once the id is there, so that an ACK is not
    held as long as the longest frame (the ACK's round trip through simavr grew from 5.7 to 7.9 ms)."""
    frames = [encode("ACK", 7, {"ref_msg_id": 6, "ref_seq": 7, "status": 0}),
              encode("PONG", 1, {"host_time_ms": 1, "board_time_ms": 2}),
              encode("TELEMETRY", 3, {"time_ms": 1, "pressure_pa": [1, 2, 3], "setpoint_pa": [0, 0, 0],
                                      "drive": [0, 0, 0], "state": [0, 0, 0], "fault_flags": 0, "rx_bad_crc": 0,
                                      "rx_overflow": 0, "rx_bad_frame": 0, "tx_dropped": 0, "tick_overruns": 0})]
    for frame in frames:
        assert frame_bytes(frame[:2]) == frame_bytes(frame[:-1]) == len(frame)
        assert frame_bytes(frame[:1]) <= len(frame)                # before the id: the shortest a board sends
    hello = encode("HELLO", 1, {"protocol_version": 1, "spec_hash": 5})   # the host's: not a board's frame
    assert frame_bytes(hello[:2]) == MAX_FRAME_BYTES


def test_the_keepalive_keeps_time_while_the_daemons_loop_is_stalled(tmp_path):
    """Issue 23, defect 3: work inside the daemon's event loop (a 30 MB scene parsed, 100 surfaces encoded) held
    the link's timers too, past the board's 500 ms dead-host deadline. The link runs on its own loop in a thread
    (now a process of its own, host/link_process.py): a 1.5 s stall of the daemon's loop leaves no gap in the
    board's PINGs, commands still reach the board, and the telemetry that arrived meanwhile is delivered to the
    daemon afterwards."""
    from phantom.host.link_process import LinkProcess

    board = ScriptedBoard(tmp_path / "board")
    telemetry = []

    async def main():
        link = LinkProcess(SerialTransport(tmp_path / "board"), FAST)
        link.attach(on_telemetry=telemetry.append, on_event=lambda *event: None, on_online=None,
                    on_motion=lambda message: None)
        task = asyncio.create_task(link.run())
        try:
            await wait_for(lambda: link.online)
            assert await link.command("SET_SETPOINTS", {"setpoint_pa": [800, 0, 0]}) == "OK"
            stalled_from = time.monotonic()
            time.sleep(1.5)                                   # the daemon's loop does nothing else meanwhile
            stalled_until = time.monotonic()
            frames_before = len(telemetry)
            await asyncio.sleep(0.1)
            assert await link.command("SET_SETPOINTS", {"setpoint_pa": [900, 0, 0]}) == "OK"
            return stalled_from, stalled_until, len(telemetry) - frames_before
        finally:
            link.stop()
            await asyncio.wait_for(task, 5)

    try:
        stalled_from, stalled_until, delivered_after = asyncio.run(main())
    finally:
        board.unplug()
    pings = [at for message, at in zip(board.received, board.received_at, strict=True) if message.name == "PING"
             and stalled_from <= at <= stalled_until]
    gaps = [later - earlier for earlier, later in zip([stalled_from, *pings], [*pings, stalled_until], strict=True)]
    assert len(pings) >= 10 and max(gaps) < 0.25, gaps      # FAST's keepalive: a PING every 50 ms
    assert delivered_after > 20                               # the frames of the stall, handed over after it
    assert board.setpoints_pa == [900, 0, 0]
