"""``make demo`` (phantom/cli/demo.py) when it fails, and the viewer command it prints: a failed demo keeps the
last good recording and blames the stage that failed; the rerun command is one that works from here."""

import os
import sys
from pathlib import Path

import pytest

from phantom import PhantomError
from phantom.cli import demo

VIEWER = Path(sys.executable).with_name("rerun")


@pytest.mark.slow  # a real daemon process starts and fails (a few seconds)
def test_a_demo_whose_daemon_fails_keeps_the_last_good_recording_and_says_why(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    good = out / "demo.rrd"
    good.write_bytes(b"the last good recording")
    with pytest.raises(PhantomError, match=r"the daemon exited with status 2 while .*its log .* ends:"
                                           r"(.|\n)*no_such_scene\.toml"):
        demo.main(["--scene", str(tmp_path / "no_such_scene.toml"), "--out", str(out)])
    assert good.read_bytes() == b"the last good recording"


def test_the_viewer_command_names_the_environments_rerun_when_it_is_not_on_path(tmp_path, monkeypatch):
    monkeypatch.setenv("PATH", "/usr/bin:/bin")
    monkeypatch.chdir(tmp_path)
    assert demo.rerun_command(Path("out/demo.rrd")) == f"{VIEWER} out/demo.rrd"
    monkeypatch.chdir(VIEWER.parents[2])  # the checkout holding .venv/: the short relative path
    assert demo.rerun_command(Path("out/demo.rrd")) == f"{VIEWER.relative_to(VIEWER.parents[2])} out/demo.rrd"


def test_the_viewer_command_is_plain_rerun_when_path_finds_this_environments(monkeypatch):
    monkeypatch.setenv("PATH", f"{VIEWER.parent}{os.pathsep}/usr/bin:/bin")
    assert demo.rerun_command(Path("out/demo.rrd")) == "rerun out/demo.rrd"


@pytest.mark.sim
@pytest.mark.slow  # the daemon on the simulated board plays make demo's BPH scene, at x6 (make demo: x4), 45 s
def test_the_demo_prints_the_true_error_and_writes_its_report(tmp_path, capsys):
    """What `make demo` promises: the table's true volume and its error against each target with their mean, read
    from what the simulated plant reported (not hard-coded), and the recording's HTML report beside it."""
    import re

    from phantom.host.scenes import example_scene_path

    out = tmp_path / "out"
    # the uncorrected table (the verified rounds are test_verify_sim's: minutes a volume)
    assert demo.main(["--scene", str(example_scene_path("bph_growth")), "--time-scale", "6", "--out", str(out),
                      "--no-verify"]) == 0
    printed = capsys.readouterr().out
    header = next(line for line in printed.splitlines() if line.startswith("step"))
    assert "true ml" in header and "true error %" in header and "reached" not in header
    rows = [line.split() for line in printed.splitlines() if re.match(r"\s+\d+\s+\d", line)]
    assert len(rows) == 5
    errors = []
    for row in rows:  # step, at, target, "ml", estimate, true, true error %, time
        target, true, error = float(row[2]), float(row[5]), float(row[6])
        assert error == pytest.approx((true - target) / target * 100, abs=0.05)  # true ml printed to 0.01 ml
        errors.append(abs(error))
    mean = re.search(r"mean \|true error\| ([\d.]+) %", printed)
    assert mean and float(mean.group(1)) == pytest.approx(sum(errors) / len(errors), abs=0.02)
    report = (out / "demo.html").read_text()
    reported = re.search(r"Mean \|true error\| ([\d.]+) %", report)  # from the recording, read back
    assert (out / "demo.rrd").is_file() and reported
    assert float(reported.group(1)) == pytest.approx(float(mean.group(1)), abs=0.1)
    assert "out/demo.html" in printed or str(out / "demo.html") in printed


def test_the_verified_table_shows_before_and_after_the_correction_in_true_volume():
    rows = [{"target_ml": 40.0, "error": None, "took_s": 95.0,
             "rounds": [{"estimated_volume_ml": 39.9, "scanned_volume_ml": 38.85, "true_volume_ml": 38.8},
                        {"estimated_volume_ml": 41.1, "band_ml": 0.061, "scanned_volume_ml": 40.03,
                         "true_volume_ml": 39.98}]},
            {"target_ml": 45.0, "error": "a scan failed", "took_s": 40.0, "rounds": [{"estimated_volume_ml": 45.0}]}]
    table = demo.format_verified(rows).splitlines()
    assert table[1].split() == ["40.00", "|", "39.90", "38.850", "38.800", "-3.000", "|", "41.10", "0.061",
                                "40.030", "39.980", "-0.050", "|", "2", "95"]
    assert "NOT VERIFIED: a scan failed" in table[2]
    assert table[3].startswith("after the scans: mean |true error| 0.050 % (largest 0.050 %), 1.5 rounds on "
                               "average")   # the error of the verified only


def test_a_verified_volume_waits_for_the_boards_link_before_it_is_set(monkeypatch):
    """The loaded machine's simulated board lost its link for a second as one verified volume ended, and the next
    four were refused at once (link_down): each waits for the link first, then is set."""
    import types

    links = iter(["disconnected", "handshake", "online"])
    calls = []

    class Daemon:
        def status(self):
            calls.append("status")
            return types.SimpleNamespace(link=next(links, "online"))

        def set_volume(self, target_ml, **_):
            calls.append(("set", target_ml))
            return types.SimpleNamespace(rounds=[{"true_volume_ml": 30.01}], scanned_volume_ml=30.02)

    monkeypatch.setattr(demo.time, "sleep", lambda _: None)
    (row,) = demo.verified_steps(Daemon(), [30.0])
    assert calls == ["status", "status", "status", ("set", 30.0)] and row["error"] is None


def test_a_fault_during_a_verified_volume_leaves_the_rest_untried_and_says_where_it_came():
    """make demo on a loaded machine: DEAD_HOST during 26.5 ml's fourth round, then each later volume refused at
    once (FAULT_LATCHED), four lines of the same cause. The fault's row says the round and what to do; the rest
    are not tried."""
    import types

    from phantom.host.client import FaultError

    tried = []

    class Daemon:
        def status(self):
            return types.SimpleNamespace(link="online")

        def set_volume(self, target_ml, **_):
            tried.append(target_ml)
            raise FaultError(("DEAD_HOST",), f"waiting for {target_ml:g} ml (target {target_ml:.2f} ml not reached: "
                             "faults latched (DEAD_HOST) during verify round 4 of 4 (scanning); ...)")

    rows = demo.verified_steps(Daemon(), [26.5, 30.0, 35.0])
    assert tried == [26.5] and [row["target_ml"] for row in rows] == [26.5, 30.0, 35.0]
    assert "during verify round 4 of 4 (scanning)" in rows[0]["error"]
    assert rows[1]["error"] == rows[2]["error"] == "not tried: DEAD_HOST latched while verifying 26.5 ml"
