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
