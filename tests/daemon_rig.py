"""A daemon process on a simulated board, for the end-to-end tests of the daemon's promises (test code only).

:class:`DaemonRig` starts ``phantom daemon --port PORT`` as its own process against a
:class:`phantom.hil.sim.SimulatedBoard` (the real firmware in simavr), and gives the tests its status, the
``phantom`` CLI, the raw API and its log; :func:`daemon_process` runs ``phantom daemon`` (``--sim`` or a port) for
the length of a ``with`` block. :func:`calibrated_scene` writes a scene on the daemon's default model
(the calibrated Gent phantom, answered from its cached response table) with the given ``[[steps]]``.
:func:`wait_for` awaits a condition in the link's tests' event loops.
"""

from __future__ import annotations

import asyncio
import subprocess
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from phantom import PhantomError
from phantom.host.client import DaemonClient

PHANTOM = Path(sys.executable).with_name("phantom")
REPO = Path(__file__).resolve().parent.parent


async def wait_for(predicate: Any, timeout_s: float = 5.0) -> None:
    """Await ``predicate()`` true, polling every 20 ms; AssertionError after ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    while not predicate():
        assert time.monotonic() < deadline, "condition not met in time"
        await asyncio.sleep(0.02)


def calibrated_scene(steps: list[dict[str, Any]], end_s: float) -> str:
    """A scene file's text: the shipped BPH scene's phantom, material and model (the daemon's default model),
    with these ``[[steps]]`` and ``[timeline] end_s``."""
    header = (REPO / "host" / "scenes" / "bph_growth.toml").read_text().split("[timeline]")[0].split("[[steps]]")[0]
    lines = [header, "[timeline]", f"end_s = {end_s}", ""]
    for step in steps:
        lines.append("[[steps]]")
        lines += [f"{key} = {value!r}".replace("'", '"') for key, value in step.items()]
        lines.append("")
    return "\n".join(lines)


def wait_ready(socket: Path, process: subprocess.Popen[Any], log_path: Path, timeout_s: float) -> None:
    """Wait until the daemon ``process`` on ``socket`` has its link online and is ready (model answering, sensors
    zeroed; before that requests are answered ``starting``); fail with its log if it exits or takes too long."""
    deadline = time.monotonic() + timeout_s
    while True:
        assert process.poll() is None, log_path.read_text()
        try:
            with DaemonClient(socket, timeout_s=10) as client:
                if (answer := client.call("status"))["link"] == "online" and answer["ready"]:
                    return
        except PhantomError:
            pass
        assert time.monotonic() < deadline, log_path.read_text()
        time.sleep(0.2)


@dataclass(frozen=True)
class DaemonProcess:
    """A ``phantom daemon`` process, its API's socket and the file its output goes to."""

    process: subprocess.Popen[Any]
    socket: Path
    log_path: Path

    def log(self) -> str:
        """What it printed so far."""
        return self.log_path.read_text()


#: A child's command prefix: Ctrl-C (SIGINT) as a terminal's foreground command has it (coreutils' env resets it
#: to the default action before it executes the command). A background job of a non-interactive shell, such as make
#: test's [sim] run (scripts/pytest-all.sh), passes SIGINT on ignored to everything it starts, and a Python started
#: so never raises KeyboardInterrupt: a test that sends a command SIGINT, as a person's Ctrl-C, then waited in vain
#: (test_verify_sim's ``phantom set`` interrupted). A prefix, not a ``preexec_fn``: that would run Python between
#: fork and exec in a worker that may hold JAX's threads from another test.
AS_AT_A_TERMINAL = ("env", "--default-signal=INT")


@contextmanager
def daemon_process(directory: Path, *arguments: str, ready_s: float, stop_s: float = 30.0,
                   env: dict[str, str] | None = None, socket_name: str = "d.sock") -> Iterator[DaemonProcess]:
    """``phantom daemon ARGUMENTS --socket DIRECTORY/SOCKET_NAME`` as its own process, its output in
    DIRECTORY/daemon.log, ready (:func:`wait_ready` within ``ready_s``) when the block starts; on the way out, unless
    it has ended already, SIGTERM (it vents and stores, as systemd stops it) and a wait of up to ``stop_s``."""
    socket, log_path = directory / socket_name, directory / "daemon.log"
    with open(log_path, "w") as log:
        process = subprocess.Popen([str(PHANTOM), "daemon", *arguments, "--socket", str(socket)], stdout=log,
                                   stderr=subprocess.STDOUT, env=env)
        try:
            wait_ready(socket, process, log_path, ready_s)
            yield DaemonProcess(process, socket, log_path)
        finally:
            if process.poll() is None:
                process.terminate()
                process.wait(stop_s)


class DaemonRig:
    """A simulated board and a daemon process driving it; :meth:`close` stops both."""

    def __init__(self, directory: Path, *daemon_arguments: str, speed: float = 2.0,
                 board: Any | None = None):
        from phantom.hil.sim import SimulatedBoard

        self.directory = directory
        self.socket = directory / "phantomd.sock"
        self.own_board = board is None
        self.board = board if board is not None else SimulatedBoard(speed=speed).start()
        self.log = open(directory / "daemon.log", "a+")
        self.process = subprocess.Popen([str(PHANTOM), "daemon", "--port", self.board.port, "--socket",
                                         str(self.socket), *daemon_arguments],
                                        stdout=self.log, stderr=subprocess.STDOUT)

    def close(self) -> None:
        if self.process.poll() is None:
            self.process.kill()
            self.process.wait(10)
        if self.own_board:
            self.board.stop()
        self.log.close()

    def daemon_log(self) -> str:
        self.log.flush()
        return Path(self.log.name).read_text()

    def call(self, method: str, params: dict[str, Any] | None = None, timeout_s: float = 10.0) -> Any:
        with DaemonClient(self.socket, timeout_s=timeout_s) as client:
            return client.call(method, params)

    def status(self) -> dict[str, Any]:
        answer: dict[str, Any] = self.call("status")
        return answer

    def cli(self, *arguments: str) -> subprocess.CompletedProcess[str]:
        return subprocess.run([str(PHANTOM), *arguments, "--socket", str(self.socket)], capture_output=True,
                              text=True, timeout=60)

    def wait_until(self, predicate: Any, timeout_s: float, what: str = "condition") -> Any:
        """Poll ``predicate()`` until it gives something true (returned); fail with the daemon's log."""
        deadline = time.monotonic() + timeout_s
        while True:
            if self.process.poll() is not None:
                raise AssertionError(f"the daemon exited with {self.process.returncode}:\n{self.daemon_log()}")
            try:
                value = predicate()
                if value:
                    return value
            except (OSError, PhantomError, KeyError, TypeError, IndexError):
                pass
            if time.monotonic() > deadline:
                raise AssertionError(f"{what}: not met in {timeout_s} s; daemon log:\n{self.daemon_log()[-6000:]}")
            time.sleep(0.1)

    def wait_status(self, predicate: Any, timeout_s: float, what: str = "condition") -> dict[str, Any]:
        """Poll the status until ``predicate(status)`` holds; that status."""
        def holds() -> dict[str, Any] | None:
            answer = self.status()
            return answer if predicate(answer) else None
        return self.wait_until(holds, timeout_s, what)  # type: ignore[no-any-return]

    def wait_online(self, timeout_s: float = 60.0) -> None:
        """Wait until the link is online and the daemon ready (model answering, sensors zeroed): before that
        requests are answered ``starting``."""
        wait_ready(self.socket, self.process, Path(self.log.name), timeout_s)

    def wait_scene_time(self, scene_time_s: float, timeout_s: float = 60.0) -> dict[str, Any]:
        """Wait until the running scene's time has passed ``scene_time_s``; the status then."""
        return self.wait_status(lambda answer: answer["scene"]["time_s"] >= scene_time_s, timeout_s,
                                f"scene time {scene_time_s} s")


def board_holds_solution(status: dict[str, Any], volume_ml: float) -> bool:
    """Whether the board's setpoints are those of the daemon's answer to a ``volume_ml`` target (to the pascal)."""
    solution = status.get("solution")
    board = status.get("board_setpoints_kpa")
    if solution is None or board is None or solution["target"].get("volume_ml") != volume_ml:
        return False
    return all(abs(b - round(s * 1e3) / 1e3) <= 0.0015 for b, s in zip(board, solution["pressures_kpa"], strict=True))


def telemetry_mean_kpa(socket_path: Path, seconds: float) -> tuple[Any, Any]:
    """Mean measured pressures and the board's last setpoints (kPa) over ``seconds`` of the board's time of
    subscribed telemetry. Board time, not the wall clock's: a loaded machine runs the simulated board slower than
    asked (at a load of 14 one wall second held 20 frames, fewer than the 50 Hz check wanted of two board seconds)."""
    import numpy as np

    measured, setpoints, board_ms = [], [], []
    with DaemonClient(socket_path, timeout_s=10) as client:
        for message in client.events(["telemetry"]):
            measured.append(message["data"]["pressures_kpa"])
            setpoints.append(message["data"]["setpoints_kpa"])
            board_ms.append(message["data"]["board_time_ms"])
            if board_ms[-1] - board_ms[0] >= seconds * 1e3:
                break
    # one frame each 20 ms of board time (the default period), a few lost to the link at most
    assert len(measured) >= 0.8 * 50 * seconds, f"telemetry should stream at 50 Hz of board time: {len(measured)}"
    return np.mean(measured, axis=0), np.asarray(setpoints[-1])
