"""Build and drive the simavr harness process (``hil/harness``, C against Debian's libsimavr).

The harness takes line commands on stdin and answers each with one JSON line on stdout; see hil/README.md.
"""

from __future__ import annotations

import fcntl
import hashlib
import json
import os
import select
import shutil
import subprocess
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import phantom
from phantom import PhantomError

#: Sources of the harness (shipped as package data, so a wheel install can build it too).
HARNESS_SOURCE_DIR = Path(__file__).resolve().parent / "harness"


class HarnessError(PhantomError):
    """The harness cannot be built, did not start, or refused a command."""


def harness_sources_digest() -> str:
    """The first 16 hex digits of sha256 over the harness's sources (every file of :data:`HARNESS_SOURCE_DIR`)."""
    digest = hashlib.sha256()
    for source in sorted(path for path in HARNESS_SOURCE_DIR.iterdir() if path.is_file()):
        digest.update(source.name.encode() + b"\0" + source.read_bytes())
    return digest.hexdigest()[:16]


def build_harness() -> Path:
    """Build the harness if its sources changed (``make``) and return the executable's path.

    The build goes to ``phantom.cache_dir("hil")/harness-<digest of the sources>``: checkouts share the cache, and
    make's check of times alone handed one checkout's harness to another whose sources were older than it.
    """
    missing = [tool for tool in ("make", "cc") if shutil.which(tool) is None]
    if missing:
        raise HarnessError(f"cannot build the simavr harness: {', '.join(missing)} not found; run scripts/bootstrap.sh")
    if not Path("/usr/include/simavr/sim_avr.h").exists():
        raise HarnessError("cannot build the simavr harness: libsimavr-dev is not installed; run scripts/bootstrap.sh")
    build_dir = phantom.cache_dir("hil") / f"harness-{harness_sources_digest()}"
    # one build at a time on this machine: two pytest workers that found the sources changed ran make at once, and
    # one started the executable while the other was still linking it (OSError in 14 tests)
    with open(phantom.cache_dir("hil") / "harness.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        result = subprocess.run(
            ["make", "-s", "-C", str(HARNESS_SOURCE_DIR), f"BUILD={build_dir}"], capture_output=True, text=True
        )
    if result.returncode != 0:
        raise HarnessError(f"building the simavr harness failed:\n{result.stdout}{result.stderr}")
    return build_dir / "phantom-hil"


class HarnessProcess:
    """One running harness: send a command, get its JSON reply.

    Parameters
    ----------
    arguments
        Command-line arguments after the executable (``--elf``, ``--param`` ...).
    start_timeout_s
        How long to wait for the harness's ``ready`` line.
    """

    def __init__(self, arguments: list[str], start_timeout_s: float = 20.0):
        executable = build_harness()
        self._stderr = tempfile.TemporaryFile()
        # Its own session: a Ctrl-C or SIGTERM meant for the host must not kill the simulated board before the
        # host has vented it; the board is stopped through stop() instead.
        self._process = subprocess.Popen(
            [str(executable), *arguments],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=self._stderr,
            start_new_session=True,
        )
        # both pipes exist: they were asked for above
        assert self._process.stdin is not None and self._process.stdout is not None
        self._stdin, self._stdout = self._process.stdin, self._process.stdout
        self._buffer = b""
        self._lock = threading.Lock()
        self.ready = self._read_reply(start_timeout_s, "start")

    def _stderr_text(self) -> str:
        self._stderr.seek(0)
        return self._stderr.read().decode(errors="replace").strip()

    def _read_reply(self, timeout_s: float, what: str) -> dict[str, Any]:
        deadline = time.monotonic() + timeout_s
        while b"\n" not in self._buffer:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise HarnessError(f"the simavr harness did not answer '{what}' within {timeout_s:g} s")
            readable, _, _ = select.select([self._stdout], [], [], remaining)
            if readable:
                chunk = os.read(self._stdout.fileno(), 65536)
                if not chunk:
                    self._process.wait(timeout=5)
                    raise HarnessError(
                        f"the simavr harness exited (status {self._process.returncode}) during '{what}': "
                        f"{self._stderr_text() or 'no message'}"
                    )
                self._buffer += chunk
        line, self._buffer = self._buffer.split(b"\n", 1)
        reply: dict[str, Any] = json.loads(line)
        if "error" in reply:
            raise HarnessError(f"the simavr harness refused '{what}': {reply['error']}")
        return reply

    def command(self, line: str, timeout_s: float = 30.0) -> dict[str, Any]:
        """Send one command line and return its JSON reply; HarnessError if it failed."""
        with self._lock:
            if self._process.poll() is not None:
                raise HarnessError(f"the simavr harness is not running (exit status {self._process.returncode})")
            try:
                self._stdin.write(line.encode() + b"\n")
                self._stdin.flush()
            except BrokenPipeError:
                raise HarnessError(f"the simavr harness exited: {self._stderr_text() or 'no message'}") from None
            return self._read_reply(timeout_s, line)

    @property
    def running(self) -> bool:
        return self._process.poll() is None

    def close(self) -> None:
        """Ask the harness to quit; kill it if it does not."""
        if self._process.poll() is None:
            try:
                self.command("quit", timeout_s=5)
            except (HarnessError, OSError):
                pass
            try:
                self._process.wait(timeout=5)
            except subprocess.TimeoutExpired:
                self._process.kill()
                self._process.wait()
        for stream in (self._process.stdin, self._process.stdout):
            if stream:
                stream.close()
        self._stderr.close()
