"""A SIGKILLed ``--sim`` daemon left two folders in /tmp each time (issue 23, defect 10): the simulated board's
(``phantom-sim-``) and the daemon's port link (``phantomd-sim-``). A SIGKILL runs no cleanup, so the next one
sweeps them: the folders are named after their process, and those of processes that no longer run are removed."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest

from phantom import process_temporary_folder

HOLDER = """
import sys, time
from phantom import process_temporary_folder
folder = process_temporary_folder(sys.argv[1])
print(folder.name, flush=True)
time.sleep(60)
"""


def hold_folder(prefix: str, tmp_path: Path) -> tuple[subprocess.Popen[str], Path]:
    holder = subprocess.Popen([sys.executable, "-c", HOLDER, prefix], stdout=subprocess.PIPE, text=True,
                              env={**os.environ, "TMPDIR": str(tmp_path)})
    assert holder.stdout is not None
    return holder, Path(holder.stdout.readline().strip())


def test_folders_of_killed_processes_are_swept_and_those_of_live_ones_kept(tmp_path, monkeypatch):
    killed, killed_folder = hold_folder("phantom-sim-", tmp_path)
    live, live_folder = hold_folder("phantom-sim-", tmp_path)
    try:
        killed.send_signal(signal.SIGKILL)
        killed.wait(10)
        assert killed_folder.is_dir()                       # a SIGKILL runs no cleanup
        monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
        mine = process_temporary_folder("phantom-sim-")
        assert not killed_folder.exists() and live_folder.is_dir() and Path(mine.name).is_dir()
        assert Path(mine.name).name.startswith(f"phantom-sim-{os.getpid()}-")
        mine.cleanup()
    finally:
        live.kill()
        live.wait(10)


@pytest.mark.sim
@pytest.mark.slow
def test_a_sigkilled_sim_daemon_leaves_no_folder_behind_its_successor(tmp_path, default_model_cached):
    phantom = Path(sys.executable).with_name("phantom")
    temporary = tmp_path / "tmp"
    temporary.mkdir()
    environment = {**os.environ, "TMPDIR": str(temporary)}

    def start(number: int) -> subprocess.Popen[bytes]:
        daemon = subprocess.Popen([str(phantom), "daemon", "--sim", "--socket", str(tmp_path / f"{number}.sock")],
                                  env=environment, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        deadline = time.monotonic() + 90
        while len(list(temporary.glob(f"*-{daemon.pid}-*"))) < 2:
            assert daemon.poll() is None and time.monotonic() < deadline, "the daemon made no folders"
            time.sleep(0.2)
        return daemon

    first = start(1)
    first.send_signal(signal.SIGKILL)
    first.wait(10)
    left = sorted(path.name.split("-")[0] + "-" + path.name.split("-")[1] for path in temporary.iterdir())
    assert left == ["phantom-sim", "phantomd-sim"]           # what the issue saw leak
    second = start(2)
    try:
        assert not list(temporary.glob(f"*-{first.pid}-*"))
    finally:
        second.terminate()
        second.wait(30)
    assert list(temporary.iterdir()) == []
