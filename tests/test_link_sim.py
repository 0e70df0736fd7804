"""The link session against the real firmware in simavr: a board that resets behind an open port, and a noisy line.

These are the cases where the port stays open and only the protocol tells the host what happened: the
firmware's watchdog reset (provoked with the bench-only TEST_HANG) and bytes flipped or dropped on the wire.
"""

import asyncio

import pytest
from daemon_rig import wait_for

from phantom.host.session import LinkSession, LinkState, LinkTiming
from phantom.host.transports import SerialTransport
from phantom.protocol.messages import CONSTANTS

pytestmark = [pytest.mark.sim]

SPEED = 2.0
TIMING = LinkTiming(keepalive_s=0.05, hello_timeout_s=0.1)


@pytest.fixture
def board():
    from phantom.hil.sim import SimulatedBoard

    with SimulatedBoard(speed=SPEED) as simulated:
        yield simulated



def test_a_watchdog_reset_behind_an_open_port_is_seen_and_its_cause_reported(board):
    events = []

    async def main():
        session = LinkSession(SerialTransport(board.port), TIMING, on_event=lambda *event: events.append(event))
        task = asyncio.create_task(session.run())
        try:
            await asyncio.wait_for(session.online_event.wait(), 20)
            assert session.board.reset_cause == "POWER_ON"
            await asyncio.sleep(0.5)  # a second of board time: its clock then visibly goes back at the reset
            assert await session.command("TEST_HANG", {"magic": CONSTANTS["TEST_HANG_MAGIC"]}) == "OK"
            await wait_for(lambda: session.stats.reconnects == 1 and session.state is LinkState.ONLINE, 15)
            return session.board, session.stats
        finally:
            session.stop()
            await task

    board_info, stats = asyncio.run(main())
    assert board_info.reset_cause == "WATCHDOG"
    kinds = [event[0] for event in events]
    assert kinds[0] == "connected" and kinds.index("link_lost") < kinds.index("reconnected")
    lost = events[kinds.index("link_lost")][1]
    # the board's FAULT frame at start-up carries a clock that went back: the reset is seen at once
    assert "the board restarted (its clock went back" in lost
    assert "reset cause WATCHDOG" in events[kinds.index("reconnected")][1]
    assert any(kind == "fault" and "WATCHDOG_RESET" in text for kind, text, _ in events)
    assert board.plant_state()["resets"] >= 1
    assert stats.links_lost == 1


def test_line_noise_costs_retries_not_wrong_setpoints(board):
    async def main():
        session = LinkSession(SerialTransport(board.port), TIMING)
        task = asyncio.create_task(session.run())
        try:
            await asyncio.wait_for(session.online_event.wait(), 20)
            board.inject("line_noise", flip_probability=0.002, drop_probability=0.002)
            sent = []
            for index in range(40):
                setpoints = [500 + 10 * index, 800, 300 + 5 * index]
                try:
                    await session.command("SET_SETPOINTS", {"setpoint_pa": setpoints})
                    sent.append(setpoints)
                except Exception:  # a command may fail after all its retries on a very noisy line; counted below
                    pass
            board.inject("clear")
            await asyncio.sleep(0.5)
            final = [1000, 1000, 1000]
            await session.command("SET_SETPOINTS", {"setpoint_pa": final})
            telemetry = []
            session.on_telemetry = telemetry.append
            await wait_for(lambda: len(telemetry) > 5, 10)
            return sent, telemetry[-1], session.status()["stats"]
        finally:
            session.stop()
            await task

    sent, last, stats = asyncio.run(main())
    assert len(sent) >= 30
    # noise was seen and survived: frames the host dropped, or retransmissions, and the board holds the last
    # setpoints exactly (a corrupted frame is never applied: CRC)
    assert stats["bad_frames"] + stats["retries"] + sum(stats["board_counters"].values()) > 0
    assert last.setpoints_pa.tolist() == [1000, 1000, 1000]
