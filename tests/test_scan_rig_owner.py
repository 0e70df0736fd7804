"""The daemon's hold on the rig while it scans (host/motion.py's Orbit and scan method), one layer with a stand-in
board command and a stand-in scanner: the other motion methods refused with why, a second scan refused,
motion_stop ending the scan and answering once it has ended, the daemon stopping a scan when it stops. The same
against the firmware in simavr with the real capture: tests/test_scan_rig_sim.py."""

import asyncio
import time

import pytest

from phantom.host.api import ApiError
from phantom.host.motion import Orbit, scan_method
from phantom.protocol.codec import decode, encode


def _status(enabled: bool) -> object:
    flags = 0b0001 if enabled else 0
    return decode(encode("MOTION_STATUS", 0, {
        "time_ms": int(time.monotonic() * 1e3) % 2 ** 32, "state": [1, 1], "flags": [flags, flags], "result": [2, 2],
        "position_steps": [0, 0], "position_mdeg": [0, 0], "target_mdeg": [0, 0], "velocity_mdeg_s": [0, 0]}))


class Board:
    """A board for this layer: ACKs every command and answers MOTION_STOP with a status at rest (released if
    asked), as the firmware's next MOTION_STATUS does."""

    def __init__(self):
        self.commands = []
        self.orbit = None

    async def command(self, name, fields):
        self.commands.append((name, fields))
        if name == "MOTION_STOP":
            asyncio.get_running_loop().call_later(0.05, self.orbit.on_message, _status(not fields["release"]))
        return "OK"


class Scanner:
    """A capture that waits for its stop request (at most ``wait_s``, 30 s), as the capture loop's settle wait
    does."""

    def __call__(self, params, rig):
        asked = rig.stop_requested(params.get("wait_s", 30.0))
        status = "complete" if asked is None else "stopped"
        return {"folder": params["out"], "status": status, "pictures": 0, "reason": asked}


def _rig(scanner):
    board = Board()
    orbit = Orbit(board.command, lambda kind, text, level: None)
    board.orbit = orbit
    state = {"faults": [], "link": "online", "pressures_kpa": [0.0, 0.0, 0.0]}
    return board, orbit, orbit.api_methods(), scan_method(orbit, scanner, lambda: state)["scan"]


async def _until_scanning(orbit):
    while orbit.scan is None:
        await asyncio.sleep(0.01)


def test_a_scan_owns_the_rig_and_motion_stop_ends_it():
    async def run():
        board, orbit, api, scan = _rig(Scanner())
        scanning = asyncio.ensure_future(scan({"out": "capture"}))
        await _until_scanning(orbit)
        for method, params in (("motion_move", {"orbit_deg": 10.0}), ("motion_home", {"axis": 0}),
                               ("motion_config", {"axis": 0, "max_speed_deg_s": 5.0})):
            with pytest.raises(ApiError, match=rf"{method} refused: a scan is running \(started 20.*\) and owns the "
                                               r"rig: wait for it, or stop it with motion_stop") as refused:
                await api[method](params)
            assert refused.value.code == "rejected"
        with pytest.raises(ApiError, match=r"a scan is running \(started .*\): wait for it, or stop it"):
            await scan({"out": "second"})
        assert board.commands == []  # nothing of those reached the board
        assert (await api["motion_status"]({}))["axes"][0]["name"] == "orbit"  # the status answers as ever
        started = time.monotonic()
        answer = await api["motion_stop"]({"release": False})
        assert answer["scan_stopped"] is True and time.monotonic() - started < 5.0 and orbit.scan is None
        assert board.commands == [("MOTION_STOP", {"release": 1})]  # released: the capture's own release races it
        with pytest.raises(ApiError, match="the scan was stopped: stopped by motion_stop") as stopped:
            await scanning
        assert stopped.value.data == {"folder": "capture", "status": "stopped", "pictures": 0,
                                      "reason": "stopped by motion_stop"}
        # the rig is free again: the next scan runs, and a motion_stop without a scan is the board's stop only
        assert await scan({"out": "again", "wait_s": 0.0}) == {"folder": "again", "status": "complete",
                                                                "pictures": 0, "reason": None}
        assert "scan_stopped" not in await api["motion_stop"]({})
        assert await orbit.stop_scan("nothing to stop") is False
    asyncio.run(run())


class MovingScanner(Scanner):
    """A capture that moves to three stops (refused here: the axes are not configured; counted all the same), then
    waits for its stop request."""

    def __call__(self, params, rig):
        from phantom import PhantomError

        for orbit_deg in (0.0, 18.0, 36.0):
            with pytest.raises(PhantomError, match="not configured"):
                rig.move_to(orbit_deg, 15.0)
        return super().__call__(params, rig)


@pytest.mark.parametrize("plan, stops", [({"views": 20, "elevations_deg": [15.0, 45.0]}, 40), ({}, None),
                                         ({"views": True, "elevations_deg": [0.0]}, None)])
def test_the_motion_status_says_how_far_the_scan_is(plan, stops):
    """The status's ``motion.scan`` (the panel and ``phantom status`` show it): the stops moved to of those its
    plan takes (None: the request left the plan to the scanner), none once the scan has ended."""
    async def run():
        _, orbit, api, scan = _rig(MovingScanner())
        assert (await api["motion_status"]({}))["scan"] is None
        scanning = asyncio.ensure_future(scan({"out": "capture", **plan}))
        await _until_scanning(orbit)
        while orbit.scan.stops_reached < 3:
            await asyncio.sleep(0.01)
        progress = (await api["motion_status"]({}))["scan"]
        assert progress == {"started_utc": orbit.scan.started_utc, "stops_reached": 3, "stops": stops,
                            "text": "picture 3" + ("" if stops is None else f" of {stops}")}
        await api["motion_stop"]({})
        with pytest.raises(ApiError, match="stopped by motion_stop"):
            await scanning
        assert orbit.status()["scan"] is None
    asyncio.run(run())


def test_the_daemon_stopping_stops_the_scan_first():
    async def run():
        _, orbit, _, scan = _rig(Scanner())
        scanning = asyncio.ensure_future(scan({"out": "capture"}))
        await _until_scanning(orbit)
        started = time.monotonic()
        assert await orbit.stop_scan("the daemon is stopping") is True
        assert time.monotonic() - started < 5.0 and orbit.scan is None
        with pytest.raises(ApiError, match="the scan was stopped: the daemon is stopping"):
            await scanning
    asyncio.run(run())


def test_a_cancelled_scan_request_asks_its_capture_to_stop_and_frees_the_rig_when_it_has():
    async def run():
        _, orbit, _, scan = _rig(Scanner())
        scanning = asyncio.ensure_future(scan({"out": "capture"}))
        await _until_scanning(orbit)
        run_ = orbit.scan
        scanning.cancel()
        with pytest.raises(asyncio.CancelledError):
            await scanning
        await asyncio.wait_for(run_.ended.wait(), 5.0)
        assert run_.stop_requested() == "the daemon is stopping" and orbit.scan is None
    asyncio.run(run())


def test_a_verified_rounds_scan_failed_for_a_late_reply_is_taken_again_once_and_only_for_that():
    """The daemon's one entry point for a round's scan (Daemon.perform_scan), with a stand-in scan method: a capture
    that failed because the board's reply was late is taken again into a new folder; any other failure, and a
    second late reply, end the round."""
    from types import SimpleNamespace

    from phantom.host.daemon import Daemon
    from phantom.host.motion import SCAN_TRIES

    late = ("the scan stopped: the orbit's configuration did not end within 2 s (is the axis configured and the link "
            "up?)")

    def stand_in(failures):
        calls, events = [], []
        motion = SimpleNamespace(late_replies=0, latest=None)  # no status from the board yet, as at a start

        async def scan(params):
            calls.append(params["out"])
            if len(calls) <= len(failures):
                text, counted = failures[len(calls) - 1]
                motion.late_replies += counted  # the orbit counted a late reply: what the daemon goes by
                raise ApiError("rejected", text)
            return {"folder": params["out"], "status": "complete", "pictures": 60}

        async def at_rest():
            return None

        daemon = SimpleNamespace(api=SimpleNamespace(handlers={"scan": scan}), _rig_at_rest=at_rest, motion=motion,
                                 event=lambda *event: events.append(event))
        return daemon, calls, events

    daemon, calls, events = stand_in([(late, 1)])
    answer = asyncio.run(Daemon.perform_scan(daemon, 4, {"views": 30}))
    assert answer["status"] == "complete" and len(calls) == 2 and calls[0] != calls[1]
    assert events[0][0] == "scan" and "the scan of round 4 failed" in events[0][1] and events[0][2] == "WARN"
    daemon, calls, _ = stand_in([(late, 1)] * SCAN_TRIES)
    with pytest.raises(ApiError, match="did not end within"):
        asyncio.run(Daemon.perform_scan(daemon, 4, {}))
    assert len(calls) == SCAN_TRIES
    # the same words without a late reply counted: not taken again (the daemon goes by the count, not the text)
    daemon, calls, _ = stand_in([(late, 0)])
    with pytest.raises(ApiError, match="did not end within"):
        asyncio.run(Daemon.perform_scan(daemon, 4, {}))
    assert len(calls) == 1
    daemon, calls, _ = stand_in([("the scan was aborted: the camera stopped delivering", 0)])
    with pytest.raises(ApiError, match="camera stopped"):
        asyncio.run(Daemon.perform_scan(daemon, 4, {}))
    assert len(calls) == 1
