"""A verified volume on a real rig, rehearsed end to end on the simulated board presented as a real one (the
README's "A verified volume on a real rig", step by step): ``phantom sim-board --camera-stream`` (the firmware in
simavr, its camera an MJPEG stream), ``phantom daemon --port`` on its serial port (no ``--sim``: no simulated
privileges), the rig calibrated from the target's stream (``phantom scan capture --target``, ``phantom scan
calibrate``), then the daemon again with ``--camera URL --rig rig.json`` and a 40 ml target with
``verify="scan"`` through the Python API, judged against the simulated phantom's truth (the stream's
``/truth.json``, which the daemon never reads); and ``phantom characterise`` through the same
daemon, camera and rig on a path of two points, whose scans correct the next target's answer."""

from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
import time
import urllib.request
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest

import phantom
from phantom.model.measurements import CorrectionStore
from tests.daemon_rig import wait_ready

pytest.importorskip("cv2")

PHANTOM = Path(sys.executable).with_name("phantom")
#: The simulated board runs at twice real time (the orbit's moves and the pressures' settling take half the wall
#: time), so its dead-host deadline, counted on the board's clock, is given as 1000 ms: a real board's 500 ms.
SIM_SPEED = 2
HOST_DEADLINE_MS = 1000


def _run(*arguments: str, env: dict[str, str], timeout_s: float = 300) -> str:
    done = subprocess.run([str(PHANTOM), *arguments], capture_output=True, text=True, timeout=timeout_s, env=env)
    assert done.returncode == 0, f"phantom {' '.join(arguments)}:\n{done.stderr[-4000:]}"
    return done.stdout + done.stderr


class _Daemon:
    """``phantom daemon --port PORT`` as a lab PC runs it against a board, its log in ``folder``."""

    def __init__(self, folder: Path, port: str, env: dict[str, str], *arguments: str):
        self.socket = folder / "phantomd.sock"
        self.log_path = folder / f"daemon{len(list(folder.glob('daemon*.log')))}.log"
        self.log = open(self.log_path, "w")
        self.process = subprocess.Popen([str(PHANTOM), "daemon", "--port", port, "--socket", str(self.socket),
                                         "--host-deadline-ms", str(HOST_DEADLINE_MS), *arguments],
                                        stdout=self.log, stderr=subprocess.STDOUT, env=env)
        wait_ready(self.socket, self.process, self.log_path, timeout_s=120)

    def stop(self) -> None:
        """SIGTERM, as Ctrl-C or systemd stops it: it vents the phantom and exits."""
        if self.process.poll() is None:
            self.process.send_signal(signal.SIGTERM)
            try:
                self.process.wait(30)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait(10)
        self.log.close()


@dataclass
class RealRig:
    """The simulated board served as a real one, its rig calibrated, and the daemon given its camera and rig."""

    daemon: _Daemon
    streams: dict[str, str]
    env: dict[str, str]
    folder: Path


def _link_account(streams: dict[str, str] | None, socket: Path | None) -> str:
    """What explains a lost link, both sides of it: the simulated board's timing (the stream's ``/board.json``: how
    far the harness fell behind the wall clock, the gaps in the host's bytes to its UART, the line's counters) and
    the daemon's link (its ``link_detail``: the link process's scheduling and its loop's stalls, the counters)."""
    lines = []
    if streams is not None:
        try:
            with urllib.request.urlopen(streams["board"], timeout=10) as answer:
                lines.append(f"the simulated board: {json.dumps(json.load(answer))}")
        except Exception as error:  # an account, not a check: the board may be gone
            lines.append(f"the simulated board: not read ({error})")
    if socket is not None and socket.exists():
        try:
            with phantom.connect(socket) as lab:
                detail = lab.status().raw.get("link_detail") or {}
            keys = ("state", "last_error", "process", "event_loop", "stats")
            lines.append(f"the daemon's link: {json.dumps({key: detail.get(key) for key in keys})}")
        except Exception as error:
            lines.append(f"the daemon's link: not read ({error})")
    return "\n".join(lines)


@contextlib.contextmanager
def real_rig(tmp_path: Path) -> Iterator[RealRig]:
    """The README's "A verified volume on a real rig" up to the daemon that scans for itself: ``phantom sim-board
    --camera-stream``, a daemon on its port, the target's pictures through the stream (facing the camera at orbit
    0, then turned round), ``phantom scan calibrate``, and the daemon again with ``--camera URL --rig rig.json``.
    Its logs are printed at the end (shown with a failure)."""
    env = {**os.environ, "PHANTOM_DATA_DIR": str(tmp_path / "data")}
    board_log = open(tmp_path / "board.log", "w")  # a file, not a pipe no one reads on: it would fill and block
    board = subprocess.Popen([str(PHANTOM), "sim-board", "--camera-stream", "127.0.0.1:0", "--sim-speed",
                              str(SIM_SPEED), "--json"], stdout=subprocess.PIPE, stderr=board_log, text=True, env=env)
    daemon, streams = None, None
    try:
        line = board.stdout.readline()
        assert line, (tmp_path / "board.log").read_text()
        said = json.loads(line)
        port, streams = said["port"], said["streams"]

        # once per rig: the target's pictures through the stream, facing the camera at orbit 0 and turned round
        daemon = _Daemon(tmp_path, port, env)
        sock = str(daemon.socket)
        _run("scan", "capture", "--target", "--camera", streams["target0"], "--out", str(tmp_path / "target0"),
             "--views", "7", "--start-deg", "-45", "--span-deg", "90", "--settle-s", "0.1", "--socket", sock, env=env)
        _run("scan", "capture", "--target", "--camera", streams["target1"], "--out", str(tmp_path / "target1"),
             "--views", "7", "--start-deg", "130", "--span-deg", "60", "--settle-s", "0.1", "--socket", sock, env=env)
        said_calibrate = _run("scan", "calibrate", str(tmp_path / "target0"), str(tmp_path / "target1"), "--out",
                              str(tmp_path / "rig.json"), env=env)
        assert "28 of 28 pictures" in said_calibrate
        daemon.stop()

        # the daemon given the camera and the rig: it scans for itself
        daemon = _Daemon(tmp_path, port, env, "--camera", streams["phantom"], "--rig", str(tmp_path / "rig.json"))
        yield RealRig(daemon, streams, env, tmp_path)
    finally:
        # shown with a failure (a DEAD_HOST latched, the link lost), and with -rP
        print("--- the link, both sides\n" + _link_account(streams, None if daemon is None else daemon.socket))
        if daemon is not None:
            daemon.stop()
        board.terminate()
        try:
            board.wait(30)
        finally:
            if board.poll() is None:  # still there: its log has its threads' stacks (sim-board dumps them at 20 s)
                board.kill()
                board.wait(10)
            board_log.close()
            for log in [*sorted(tmp_path.glob("daemon*.log")), tmp_path / "board.log"]:  # shown with a failure
                print(f"--- {log.name} (the last lines)\n" + "\n".join(log.read_text().splitlines()[-60:]))


@pytest.mark.sim  # the simulated board (simavr) and two daemons on its port
@pytest.mark.slow  # the calibration's 28 pictures, then a verified target's rounds of 40: 5-6 minutes at load 6-8
# make test-long, not make test: beside make test's other runs it latched DEAD_HOST in 3 of 6 clean-clone runs
# (2026-11-30). Once the simulated board's harness starved for a second (fixed: its real-time priority); once,
# after that fix, the daemon's link process (SCHED_FIFO 10) sent nothing for 0.87 s while its loop's thread was
# neither running nor waiting for a core (7.8 ms run, 0 ms queued, no collection, no page fault: blocked in
# something not yet found; the test prints the board's host gaps and the link's stalls, which showed it). Alone, or
# beside busy processes, it passes (4 of 4 at load 6-12)
@pytest.mark.long
@pytest.mark.timeout(1200)  # three rounds of 80-120 s each at load 6-10
def test_a_verified_40_ml_target_through_a_camera_stream_on_a_board_driven_as_a_real_one(tmp_path):
    with real_rig(tmp_path) as rig:
        with phantom.connect(rig.daemon.socket) as lab:
            reached = lab.set_volume(40, verify="scan")
        with urllib.request.urlopen(rig.streams["truth"], timeout=10) as answer:
            truth = json.load(answer)
        log = rig.daemon.log_path.read_text()
        print(f"verified {reached.verified} in {len(reached.rounds)} rounds, scanned {reached.scanned_volume_ml} ml, "
              f"the truth {truth['gland_volume_ml']} ml")  # shown with -rP
        assert reached.verified, log[-4000:]
        assert reached.true_volume_ml is None  # a real board's daemon knows no truth
        assert abs(reached.scanned_volume_ml - 40) <= 0.003 * 40
        assert abs(truth["gland_volume_ml"] - 40) <= 0.003 * 40, (truth, reached.rounds)
        # every round's scan went through the stream, posed by the calibrated rig kept beside its pictures
        for entry in reached.rounds:
            capture = json.loads((Path(entry["scan"]) / "capture.json").read_text())
            assert capture["camera"]["kind"] == "webcam" and capture["camera"]["source"] == rig.streams["phantom"]
            assert (Path(entry["scan"]) / "rig.json").exists()


@pytest.mark.sim
@pytest.mark.long  # make test-long: the rig's calibration, then a characterisation's 2 scans of 30 (2.1-2.2
# minutes at load 6-8); make test runs characterise through the simulated daemon (test_characterise_sim.py), and
# the camera stream a real rig's daemon reads (test_daemon_camera.py, test_sim_stream.py, test_webcam_stream.py)
@pytest.mark.timeout(1200)
def test_characterise_through_a_camera_stream_on_a_board_driven_as_a_real_one(tmp_path):
    """The same daemon characterises the phantom on a small path (rest and the top of the model's inverse) through
    the same camera and rig; its scans join the phantom's measurements, and the next target's answer is corrected
    by them. 15 views a turn (30 pictures, half the default's): about 60 s a point; the rest point read 26.51 ml
    against 26.39 ml with 30 views (fewer silhouettes carve less), not judged here."""
    with real_rig(tmp_path) as rig:
        with phantom.connect(rig.daemon.socket) as lab:
            store = CorrectionStore(lab.status().raw["correction"]["store"])
        confirmed_before = sum(entry.status == "confirmed" for entry in store.entries())
        started = time.monotonic()
        said = _run("characterise", "--path", "2", "--views", "15", "--rig", str(tmp_path / "rig.json"), "--out",
                    str(tmp_path / "characterised"), "--socket", str(rig.daemon.socket), "--json", env=rig.env,
                    timeout_s=600)
        print(f"characterise: {time.monotonic() - started:.0f} s")  # shown with -rP
        summary = json.loads([line for line in said.splitlines() if line.startswith("{")][-1])
        assert (summary["points"], summary["skipped"]) == (2, 0), said[-3000:]
        entries = store.entries()
        run = [entry for entry in entries
               if entry.scan_file and Path(entry.scan_file).is_relative_to(tmp_path / "characterised")]
        assert len(run) == 2
        # the rest point at least agrees with the scans before; a point the correction so far finds implausible
        # is stored unconfirmed and left out (phantom.model.corrections.judged), as the report says
        confirmed = [entry for entry in run if entry.status == "confirmed"]
        rest = [entry for entry in run if max(entry.pressures_kpa) < 0.1]  # the measured pressures, near 0
        assert len(rest) == 1 and rest[0].status == "confirmed", said[-3000:]
        with phantom.connect(rig.daemon.socket) as lab:
            lab.set_volume(35, wait=False)  # an answer after the store changed starts a fit (if none ran since)
            deadline = time.monotonic() + 120
            while True:
                correction = lab.status().raw["correction"]
                if correction["stored"] == len(entries) and not correction["fitting"]:
                    break
                assert time.monotonic() < deadline, correction
                time.sleep(0.5)
            answer = lab.set_volume(35, wait=False)
        assert correction["in_force"], correction
        assert answer.measurements == correction["correction"]["count"] == confirmed_before + len(confirmed), (
            answer, correction)
        assert answer.band_ml is not None
