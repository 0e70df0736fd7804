"""The scan owns the rig while it scans (host/motion.py's scan method and Orbit, on the simulated board: the
firmware's steppers in simavr over a real pty): another client's motion_move, motion_home and motion_config during
the scan's settle are refused with why and the pictures stay where they were planned; motion_stop during the
settle stops the scan at once (folder "stopped", drivers released, the next scan runs); SIGTERM during a scan ends
the daemon within seconds. The red team found each of these broken on main (the orbit turned mid-scan and the
capture completed at the planned angles; motion_stop did not stop a settling scan). Short plans, small pictures."""

import json
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
from daemon_rig import daemon_process

from phantom.host.client import DaemonClient, DaemonError

PHANTOM = Path(sys.executable).with_name("phantom")

pytestmark = [pytest.mark.sim, pytest.mark.slow]

#: two stops at elevation 0, -20 and 20 deg (the rig powers up at 0: short moves), pictures a tenth of 1280x960
PLAN = {"views": 2, "elevations_deg": [0], "start_deg": -20.0, "span_deg": 40.0, "scale": 0.1}


@pytest.fixture(scope="module")
def daemon(tmp_path_factory, default_model_cached):
    pytest.importorskip("cv2")
    with daemon_process(tmp_path_factory.mktemp("rig"), "--sim", "--sim-speed", "2", ready_s=120) as daemon:
        yield daemon.process, daemon.socket, daemon.log_path


class ScanInThread:
    """One client's scan request, answered in a thread of its own while the test acts as another client."""

    def __init__(self, sock, params):
        self.answer, self.error = None, None
        self.thread = threading.Thread(target=self._call, args=(sock, params))
        self.thread.start()

    def _call(self, sock, params):
        try:
            with DaemonClient(sock, timeout_s=300) as client:
                self.answer = client.call("scan", params)
        except DaemonError as error:
            self.error = error

    def join(self, timeout_s):
        self.thread.join(timeout_s)
        assert not self.thread.is_alive(), f"the scan request was not answered within {timeout_s} s"


def wait_settling(client, out, timeout_s=120):
    """Until the scan's first stop: the orbit at rest at -20 deg with no picture taken yet (the settle wait)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        orbit = client.call("motion_status")["axes"][0]
        if (out / "capture.json").is_file() and orbit.get("state") == "IDLE" and orbit.get("result") == "REACHED" \
                and abs(orbit["position_deg"] + 20.0) < 0.05:
            assert json.loads((out / "capture.json").read_text())["frames"] == []
            return
        time.sleep(0.1)
    raise AssertionError("the scan did not reach its first stop")


@pytest.mark.timeout(600)
def test_another_clients_motion_during_the_settle_is_refused_and_the_frames_stay_where_planned(daemon, tmp_path):
    _, sock, _ = daemon
    out = tmp_path / "capture"
    scan = ScanInThread(sock, {**PLAN, "out": str(out), "settle_s": 6.0})
    with DaemonClient(sock, timeout_s=60) as other:
        wait_settling(other, out)
        for method, params in (("motion_move", {"orbit_deg": 14.6}), ("motion_home", {"axis": 0}),
                               ("motion_config", {"axis": 0, "max_speed_deg_s": 5.0})):
            with pytest.raises(DaemonError, match=rf"{method} refused: a scan is running \(started .*\) and owns the "
                                                  r"rig: wait for it, or stop it with motion_stop"):
                other.call(method, params)
        with pytest.raises(DaemonError, match=r"a scan is running \(started .*\): wait for it, or stop it with "
                                              r"motion_stop"):
            other.call("scan", {**PLAN, "out": str(tmp_path / "second")})
        assert other.call("motion_status")["axes"][0]["position_deg"] == pytest.approx(-20.0, abs=0.05)
    scan.join(120)
    assert scan.error is None and scan.answer == {"folder": str(out), "status": "complete", "pictures": 2}
    record = json.loads((out / "capture.json").read_text())
    # the angles the simulated rig had at each picture (its drivers' pulses counted by simavr)
    assert [(f["orbit_deg"], f["elevation_deg"]) for f in record["frames"]] == [
        pytest.approx((-20.0, 0.0), abs=0.02), pytest.approx((20.0, 0.0), abs=0.02)]


@pytest.mark.timeout(600)
def test_motion_stop_during_the_settle_stops_the_scan_and_the_next_one_runs(daemon, tmp_path):
    _, sock, _ = daemon
    out = tmp_path / "capture"
    scan = ScanInThread(sock, {**PLAN, "out": str(out), "settle_s": 10.0})
    with DaemonClient(sock, timeout_s=60) as other:
        wait_settling(other, out)
        started = time.monotonic()
        answer = other.call("motion_stop")
        took_s = time.monotonic() - started
        assert answer["scan_stopped"] is True and took_s < 5.0  # not the rest of the 10 s settle
        assert [axis["enabled"] for axis in answer["axes"]] == [False, False]  # the drivers released
        scan.join(10)
        assert scan.answer is None and "the scan was stopped: capture stopped after 0 of 2 pictures: stopped by " \
                                      "motion_stop" in str(scan.error)
        record = json.loads((out / "capture.json").read_text())
        assert record["status"] == "stopped" and record["reason"] == "stopped by motion_stop"
        assert record["frames"] == []
        # the orbit stayed where the stop found it
        assert other.call("motion_status")["axes"][0]["position_deg"] == pytest.approx(-20.0, abs=0.05)
        # and the next scan starts at once and completes
        again = other.call("scan", {**PLAN, "out": str(tmp_path / "again"), "views": 1, "start_deg": 20.0,
                                    "settle_s": 0.0})
        assert again["status"] == "complete" and again["pictures"] == 1


@pytest.mark.timeout(600)
def test_sigterm_during_a_scan_ends_the_daemon_within_seconds(daemon, tmp_path):
    process, sock, log = daemon
    out = tmp_path / "capture"
    scan = ScanInThread(sock, {**PLAN, "out": str(out), "settle_s": 10.0})
    with DaemonClient(sock, timeout_s=60) as other:
        wait_settling(other, out)
    started = time.monotonic()
    process.send_signal(signal.SIGTERM)
    try:
        code = process.wait(15)
    except subprocess.TimeoutExpired:
        raise AssertionError(f"the daemon was still running 15 s after SIGTERM:\n{log.read_text()[-3000:]}") from None
    took_s = time.monotonic() - started
    assert code == 0 and took_s < 8.0, log.read_text()[-3000:]
    scan.join(10)
    record = json.loads((out / "capture.json").read_text())
    assert record["status"] == "stopped" and record["reason"].startswith("the daemon is stopping")
