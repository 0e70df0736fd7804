"""A verified target end to end on the simulated board (issue 36): ``phantom daemon --sim`` (the firmware in
simavr, the simulated phantom the measured one, which the controller's model misses by about 3 %) reaches 40 ml
on pressure, scans it with its own scanner (the virtual camera at the rig's counted angles), corrects and applies
again until the scanned volume is within 0.3 %; the simulated phantom's TRUE volume then ends within 0.3 %, and the
wait's progress and the status told which round was under way meanwhile. And a
daemon on a real board's port, whose verify scan would photograph nothing real, refuses verify."""

import json
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from daemon_rig import AS_AT_A_TERMINAL, daemon_process

import phantom
from phantom.host.client import DaemonError, TargetResult

PHANTOM = Path(sys.executable).with_name("phantom")

pytestmark = [pytest.mark.sim, pytest.mark.slow]


def watch_progress(sock, seen, hull_events, done):
    """The status's verify progress and scan pictures, twice a second until ``done``, into ``seen``; its recent
    events of the hull's error taken off a round's scan into ``hull_events`` (by round)."""
    with phantom.connect(sock) as watcher:
        while True:
            stopping = done.wait(0.5)
            status = watcher.status()
            if status.verify is not None:
                seen.append((status.verify, status.scan))
            hull_events.update({event["round"]: event for event in status.raw["events"]
                                if "the visual hull reads" in event["text"]})
            if stopping:  # once more after the command ended: its last round's events too
                return


@pytest.mark.timeout(1800)
def test_a_verified_target_ends_within_0_3_pct_of_the_true_volume(tmp_path):
    pytest.importorskip("cv2")
    from phantom.host.recording import read_rrd
    from phantom.model.measurements import CorrectionStore

    data, rrd = tmp_path / "data", tmp_path / "verify.rrd"
    # the board at twice the wall clock: the orbit's moves take half the time
    with daemon_process(tmp_path, "--sim", "--sim-speed", "2", "--rerun-save", str(rrd), ready_s=180, stop_s=120,
                        env={**os.environ, "PHANTOM_DATA_DIR": str(data)}) as daemon:
        sock = daemon.socket
        with phantom.connect(sock) as ph:
            with pytest.raises(DaemonError, match="verify_tolerance_pct .* from 0.05 to 20") as bad:
                ph.set_volume(40.0, verify="scan", verify_tolerance_pct=0.0)
            assert bad.value.code == "invalid_params" and ph.status().target is None   # nothing was set
        seen, hull_events, done = [], {}, threading.Event()
        watcher = threading.Thread(target=watch_progress, args=(sock, seen, hull_events, done))
        watcher.start()
        try:  # the command line a lab engineer types: its result as JSON, the rounds as they go on stderr
            typed = subprocess.Popen([str(PHANTOM), "set", "--socket", str(sock), "--volume-ml", "40", "--verify",
                                      "scan", "--timeout-s", "1700", "--json"], stdout=subprocess.PIPE,
                                     stderr=subprocess.PIPE, text=True)
            told_at = []                                   # (when, line) of what it printed on stderr
            teller = threading.Thread(target=lambda: told_at.extend((time.monotonic(), line.rstrip())
                                                                    for line in typed.stderr))
            teller.start()
            answer = typed.stdout.read()
            typed.wait(1750)
            ended_s = time.monotonic()
            teller.join(30)
        finally:
            done.set()
            watcher.join(30)
        told = [line for _, line in told_at]
        assert typed.returncode == 0, told[-30:]
        result = TargetResult(**json.loads(answer))                   # phantom set --json's is the API's
        rounds = result.rounds
        # the rounds as they went: the wait's progress (the daemon's events, printed as they came, the first
        # round's scan a round or more before the command ended), and the status meanwhile (the round under way,
        # what it does, the scans so far, the scan's pictures of its plan's 40), as the panel shows it
        assert any("round 1 settled" in text and text.endswith("scanning") for text in told), told
        first_scanned = [when for when, text in told_at
                         if f"round 1 scanned {rounds[0]['scanned_volume_ml']:.2f} ml" in text]
        assert first_scanned and first_scanned[0] < ended_s - 20, told_at
        scanning = [(verify, scan) for verify, scan in seen if verify["doing"] == "scanning" and scan]
        assert {verify["round"] for verify, _ in scanning} >= {1, 2}, seen
        assert [scan for _, scan in scanning if scan["stops"] != 40 or not 0 <= scan["stops_reached"] <= 40] == []
        assert len({scan["stops_reached"] for _, scan in scanning}) > 5, scanning   # it counts up as it goes
        # in the daemon's words, which phantom status and the panel print
        assert all(verify["text"].startswith(f"40 ml (scan, within 0.3 %): round {verify['round']} of at most 4, ")
                   for verify, _ in seen), seen
        assert all(f"scanning (picture {scan['stops_reached']} of 40)" in verify["text"] for verify, scan in scanning)
        later = [verify for verify, _ in seen if verify["round"] == 2]
        assert later and later[-1]["scans"][0]["scanned_volume_ml"] == pytest.approx(rounds[0]["scanned_volume_ml"])
        assert result.verified and result.volume_source == "scan (measured)"
        assert result.volume_ml == result.scanned_volume_ml == rounds[-1]["scanned_volume_ml"]
        assert abs(result.scanned_volume_ml - 40.0) <= 0.003 * 40.0
        # the phantom's true volume, which nothing in the loop sees, within 0.3 % after the rounds
        assert abs(rounds[-1]["true_volume_ml"] - 40.0) <= 0.003 * 40.0, rounds
        assert abs(result.true_volume_ml - 40.0) <= 0.003 * 40.0, rounds
        # the model alone misses the truth by more than the tolerance: the first round is corrected
        assert len(rounds) >= 2 and abs(rounds[0]["true_volume_ml"] - 40.0) > 0.003 * 40.0, rounds
        assert all(Path(entry["scan"], "scan.ply").is_file() and Path(entry["scan"]).parent.parent == data
                   for entry in rounds)
        assert rounds[0]["pressures_kpa"] != rounds[-1]["pressures_kpa"] and "next" in rounds[0]
        # each round's scan had every picture's silhouette keyed, and the model's silhouette for the hull's error
        # rendered, while the rig moved (the scan worker's capture): after it only the carving is left
        assert sorted(hull_events) == list(range(1, len(rounds) + 1)), hull_events
        assert all(event["keyed_while_taken"] == event["hull_rendered_while_taken"] == 40
                   and event["stage_s"]["hull_bias"] > 0 for event in hull_events.values()), hull_events
        # each round's scan starts at the elevation the one before ended at: its passes the other way round
        frames = [json.loads(Path(entry["scan"], "capture.json").read_text())["frames"] for entry in rounds]
        assert [scan[0]["elevation_deg"] for scan in frames[1:]] == pytest.approx(
            [scan[-1]["elevation_deg"] for scan in frames[:-1]], abs=0.5), frames
    # every scan is a measurement kept, the last (within the tolerance) too: stored before the daemon stopped
    stored = CorrectionStore.for_phantom("default", data).entries()
    assert [(entry.method, entry.volume_ml, entry.scan_file) for entry in stored] == [
        ("scan", pytest.approx(entry["scanned_volume_ml"]), entry["scan"]) for entry in rounds]
    # the recording read back (a run past 20 minutes is written in segments, the earlier ones set aside beside it
    # as verify.<time>.rrd): each scan's volume on the volume plot and its surface (phantom/scan, in the view of
    # the model's surface) enclosing that volume
    scanned, rounds_logged, tolerances, enclosed_ml = [], [], [], []
    for path in sorted(tmp_path.glob("verify*.rrd")):
        entities = read_rrd(path)
        scanned += [values[0] for values in entities.get("/volume/scanned_ml", {}).get("Scalars:scalars", [])]
        rounds_logged += [values[0] for values in entities.get("/verify/round", {}).get("Scalars:scalars", [])]
        tolerances += [values[0] for values in entities.get("/verify/tolerance_pct", {}).get("Scalars:scalars", [])]
        surfaces = entities.get("/phantom/scan", {})
        for positions, triangles in zip(surfaces.get("Mesh3D:vertex_positions", []),
                                        surfaces.get("Mesh3D:triangle_indices", []), strict=True):
            corners = np.asarray(positions, float)[np.asarray(triangles, int)]
            enclosed_ml.append(np.einsum("ij,ij->i", corners[:, 0], np.cross(corners[:, 1], corners[:, 2])).sum()
                               / 6e3)
    assert sorted(scanned) == pytest.approx(sorted(entry["scanned_volume_ml"] for entry in rounds))
    # with each scan its round and the tolerance asked, which `phantom report` groups and judges the scans by
    assert sorted(rounds_logged) == list(range(1, len(rounds) + 1)) and tolerances == [0.3] * len(rounds)
    # (the surface is the hull's: the hull's error on the model's shape, taken off the scanned volume, is in it)
    hull_ml = [entry["scanned_volume_ml"] * (1 + entry["hull_error_pct"] / 100) for entry in rounds]
    assert all(entry["hull_error_pct"] is not None for entry in rounds)
    assert sorted(enclosed_ml) == pytest.approx(sorted(hull_ml), rel=1e-3)


@pytest.mark.busy_cores
@pytest.mark.long
@pytest.mark.timeout(1800)
@pytest.mark.parametrize("link_priority", ["real-time", "normal"])
def test_a_verified_target_holds_the_link_with_one_busy_process_per_core(tmp_path, link_priority):
    """Issue 48: `make demo`'s verify latched DEAD_HOST during round 2's scan on a loaded machine (a
    reconstruction and a fit running while the board waited), the blowers stopped and the rest was refused.
    With one busy process per core beside the daemon (at the test's own priority), a verified target scans,
    learns and ends with no fault latched, within 0.3 % of its true volume.

    With the link a thread of the daemon's process it passed 4 times in 8 (2026-11-29, load 1-7): in the others
    the link's loop was 500-620 ms late, its thread waiting for a core and for the GIL the daemon's loop held
    (bench/README.md, "A verified target's scan beside busy cores"). The link now runs in a process of its own at
    SCHED_FIFO (host/link_process.py; granted to root, or with an RLIMIT_RTPRIO as the systemd unit's): it passed
    6 times in 6 (2026-11-29 03:15-04:00, load 3-11, 2.3-5.4 minutes; the daemon's loop up to 541 ms late, the
    link's 10-347 ms). ``normal``: the link's process at the daemon's priority (``--link-rt-priority 0``, as for
    a user without the right): it passed 6 times in 6 (2026-12-02, load 4.5-6.1, 2 rounds each; the daemon's
    loop up to 195 ms late, the link's 25-181 ms). Under a heavier load (2026-11-29, others' work beside, load
    5-8.5) such a link's process once waited 429 ms for a core, near the board's 500: the priority is what makes
    it sure. Minutes each, so in `make test-long`. A failure says how late the daemon's loops were, what the
    link's process ran at, and the load; a pass prints the same."""
    pytest.importorskip("cv2")
    from phantom.host.client import FaultError

    data = tmp_path / "data"
    load = [subprocess.Popen([sys.executable, "-c", "while True:\n    pass\n"]) for _ in range(os.cpu_count() or 2)]
    try:
        priority = ["--link-rt-priority", "0"] if link_priority == "normal" else []
        with (daemon_process(tmp_path, "--sim", "--sim-speed", "2", *priority, ready_s=600, stop_s=120,
                             env={**os.environ, "PHANTOM_DATA_DIR": str(data)}) as daemon,
              phantom.connect(daemon.socket) as ph):
            try:
                result = ph.set_volume(35.0, verify="scan", timeout_s=1700)
            except FaultError as error:
                status = ph.call("status")
                pytest.fail(f"a fault latched during the verify: {error}; load {os.getloadavg()}, the daemon's loop "
                            f"{status['event_loop']}, the link's {status['link_detail'].get('event_loop')} "
                            f"({status['link_detail'].get('process')})")
            assert ph.status().faults == ()
            status = ph.call("status")
        link = status["link_detail"]
        print(f"verified in {len(result.rounds)} round(s); load {os.getloadavg()}; the daemon's loop's longest stall "
              f"{status['event_loop']['longest_stall_ms']} ms, the link's {link['event_loop']['longest_stall_ms']} ms "
              f"({link['process']['scheduling']})")
        assert result.verified and len(result.rounds) >= 1
        assert abs(result.rounds[-1]["true_volume_ml"] - 35.0) <= 0.003 * 35.0, result.rounds
        if link_priority == "normal":
            assert link["process"]["scheduling"].startswith("normal"), link["process"]
    finally:
        for busy in load:
            busy.kill()
            busy.wait()


@pytest.mark.timeout(300)
def test_a_daemon_on_a_real_boards_port_refuses_verify_and_changes_nothing(tmp_path):
    from phantom.hil.sim import SimulatedBoard

    with (SimulatedBoard(speed=1.0) as board,
          daemon_process(tmp_path, "--port", board.port, ready_s=180, stop_s=60) as daemon,
          phantom.connect(daemon.socket) as ph):
        with pytest.raises(DaemonError, match="real board.*virtual one.*without verify") as refused:
            ph.set_volume(35.0, verify="scan")
        assert refused.value.code == "invalid_params" and ph.status().target is None
        assert ph.set_volume(35.0, wait=False).target == {"volume_ml": 35.0}   # without verify it goes


def wait_scanning(daemon, timeout_s=120):
    """Until the daemon's verified target is scanning; if it never does, what it did instead (its verify status,
    its faults, its log: once in a clean clone's make test, with nothing said)."""
    with phantom.connect(daemon.socket) as watcher:
        deadline = time.monotonic() + timeout_s
        while ((status := watcher.call("status")).get("verify") or {}).get("doing") != "scanning":
            assert time.monotonic() < deadline, (
                f"the verified target never scanned in {timeout_s} s: verify {status.get('verify')}, target "
                f"{status.get('target')}, faults {status.get('faults')}, link {status.get('link')}; the daemon's "
                f"log:\n{daemon.log()[-4000:]}")
            time.sleep(0.2)


@pytest.mark.timeout(300)
def test_a_client_that_leaves_a_verified_target_and_a_daemon_that_stops_during_one_say_what_goes_on(tmp_path):
    """``phantom set --verify`` interrupted (Ctrl-C) said "interrupted" while the daemon went on verifying (and
    inflating): it now says the daemon goes on with the target, and how to stop it. SIGTERM while a verified
    target's round is scanning: the daemon stops the scan and vents. It told the waiting client "the scan of round
    1 failed ... the pressures are held", and then vented them; the client is now told the target was not reached
    because the daemon vented on its way out, and the daemon ends within seconds."""
    pytest.importorskip("cv2")
    import signal

    with daemon_process(tmp_path, "--sim", "--sim-speed", "2", ready_s=180, stop_s=60,
                        env={**os.environ, "PHANTOM_DATA_DIR": str(tmp_path / "data")}) as daemon:
        sock, process = daemon.socket, daemon.process
        # Ctrl-C as a person's: not ignored
        typed = subprocess.Popen([*AS_AT_A_TERMINAL, str(PHANTOM), "set", "--socket", str(sock), "--volume-ml", "35",
                                  "--verify", "scan"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        try:
            wait_scanning(daemon)
        except AssertionError as error:
            typed.kill()
            raise AssertionError(f"{error}\nphantom set said: {typed.communicate()[1]!r}") from None
        typed.send_signal(signal.SIGINT)
        try:
            _, said = typed.communicate(timeout=60)
        except subprocess.TimeoutExpired as late:   # once in CI (30 s then): what each side was doing
            typed.kill()
            raise AssertionError(f"phantom set still ran 60 s after Ctrl-C; it said {late.stderr!r}; the daemon's "
                                 f"log:\n{daemon.log()[-4000:]}") from None
        assert typed.returncode == 130, said
        assert ("phantom set: the daemon goes on with the target (35.00 ml; verify: 35 ml (scan, within 0.3 %): "
                "round 1 of at most 4, scanning") in said and "`phantom vent` stops it" in said, said
        with phantom.connect(sock) as ph:
            assert ph.status().verify["target_ml"] == 35.0                # and it does
        told = []

        def verify():
            try:
                with phantom.connect(sock) as ph:
                    ph.set_volume(35.0, verify="scan", timeout_s=250)
            except DaemonError as error:
                told.append(error)

        waiting = threading.Thread(target=verify)                       # the same target, set again
        waiting.start()
        time.sleep(1.0)
        wait_scanning(daemon)
        time.sleep(2.0)                                                    # a few pictures in
        process.send_signal(signal.SIGTERM)
        assert process.wait(30) == 0, daemon.log()[-3000:]
        waiting.join(30)
        (error,) = told
        assert "not reached: vented: on shutdown" in str(error) and "held" not in str(error), str(error)
