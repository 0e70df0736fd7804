"""A socket anyone can squat (issue 23, defect 7): without $XDG_RUNTIME_DIR or /run/phantom (sudo, cron) the
default socket was /tmp/phantomd-UID.sock, and a fake daemon another user left there answered `vent` with
"vented". Clients now check who serves the socket (SO_PEERCRED) and the fallback is a private folder."""

from __future__ import annotations

import os
import shutil
import socket
import stat
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest

from phantom import PhantomError
from phantom.host import peer
from phantom.host.api import default_socket_path
from phantom.host.client import DaemonClient

FAKE_DAEMON = """
import json, os, socket, sys
server = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
server.bind(sys.argv[1])
os.chmod(sys.argv[1], 0o777)
server.listen(4)
print("ready", flush=True)
while True:
    connection, _ = server.accept()
    for line in connection.makefile("rb"):
        request = json.loads(line)
        connection.sendall((json.dumps({"id": request["id"], "result": {"vented": True}}) + "\\n").encode())
"""


def start_fake(path, user_id: int | None = None, python: str = sys.executable) -> subprocess.Popen:
    # the user and group set by Popen itself, not by a preexec_fn: Python code between fork and exec in a worker
    # whose threads (JAX's) may hold locks can hang, and JAX warns of every such fork
    fake = subprocess.Popen([python, "-c", FAKE_DAEMON, str(path)], stdout=subprocess.PIPE, text=True,
                            user=user_id, group=user_id)
    assert fake.stdout is not None and fake.stdout.readline().strip() == "ready"
    return fake


def test_a_daemon_of_an_untrusted_user_is_refused_before_anything_is_sent(tmp_path, monkeypatch):
    path = tmp_path / "phantomd.sock"
    fake = start_fake(path)
    try:
        with DaemonClient(path, timeout_s=5) as client:      # this user's daemon is trusted
            assert client.call("vent") == {"vented": True}
        monkeypatch.setattr(peer, "trusted_daemon_uids", lambda: {os.getuid() + 12345})
        with pytest.raises(PhantomError, match="may be a fake daemon"):
            DaemonClient(path, timeout_s=5)
    finally:
        fake.kill()
        fake.wait(10)


@pytest.mark.skipif(os.geteuid() != 0 or not shutil.which("python3", path="/usr/bin:/bin"),
                    reason="starting a process as another user needs root (and a Python that user may run)")
def test_a_fake_daemon_another_user_left_in_tmp_cannot_answer_vent():
    folder = Path(tempfile.mkdtemp(prefix="phantom-squat-"))   # like /tmp: anyone may write, sticky
    folder.chmod(0o1777)
    path = folder / "phantomd.sock"
    nobody = 65534
    fake = start_fake(path, nobody, shutil.which("python3", path="/usr/bin:/bin") or "")
    try:
        assert os.lstat(path).st_uid == nobody
        with pytest.raises(PhantomError, match="user nobody .* may be a fake daemon"):
            DaemonClient(path, timeout_s=5).call("vent")
    finally:
        fake.kill()
        fake.wait(10)
        shutil.rmtree(folder)


def test_the_fallback_socket_is_in_a_folder_only_this_user_may_write(monkeypatch):
    monkeypatch.delenv("PHANTOM_SOCKET", raising=False)
    monkeypatch.delenv("XDG_RUNTIME_DIR", raising=False)
    if os.path.isdir("/run/phantom"):
        pytest.skip("/run/phantom exists here: the service's folder is the default")
    path = default_socket_path()
    folder = os.lstat(path.parent)
    assert path.parent != "/tmp" and folder.st_uid == os.getuid()
    assert stat.S_IMODE(folder.st_mode) & 0o077 == 0


def test_a_socket_folder_someone_else_could_write_is_refused(tmp_path):
    made = peer.private_folder(tmp_path / "mine")
    assert stat.S_IMODE(os.lstat(made).st_mode) == 0o700
    open_to_all = tmp_path / "open"
    open_to_all.mkdir()
    open_to_all.chmod(0o777)
    with pytest.raises(PhantomError, match="not a private folder of yours"):
        peer.private_folder(open_to_all)
    not_a_folder = tmp_path / "file"
    not_a_folder.write_text("")
    with pytest.raises(PhantomError, match="not a private folder"):
        peer.private_folder(not_a_folder)


def test_peer_uid_reads_the_kernels_credentials():
    left, right = socket.socketpair(socket.AF_UNIX, socket.SOCK_STREAM)
    with left, right:
        assert peer.peer_uid(left) == (os.getpid(), os.getuid())
