"""The daemon's start-up: what it is doing while it cannot serve yet, readiness for systemd, and the response
table it builds in the background.

A first start on a machine used to build the calibrated model's response table (about 200 CPU-seconds of full
solves) before it answered anything, and clients got "still starting" for minutes. Now:

* the model worker serves at once on the full solve (the answers the table approximates, each taking most of a
  second) when the scene's table is not stored yet (:class:`StartupProgress` says which fidelity it is on);
* :class:`TableBuild` builds the table in a process of its own, at a lower CPU priority, reporting how far it
  is and how long is left; the daemon then switches the worker to the table;
* readiness (:func:`notify_systemd`, ``READY=1`` for a ``Type=notify`` unit) once the model answers and the
  board is online; until then the API answers ``starting`` with this progress, and clients wait for it.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import multiprocessing
import os
import signal
import socket
import time
from dataclasses import dataclass
from multiprocessing import util as multiprocessing_util
from multiprocessing.connection import Connection
from typing import TYPE_CHECKING, Any

from phantom.host.processes import child_pids

if TYPE_CHECKING:
    from collections.abc import Callable

    from phantom.host.parts import Model

logger = logging.getLogger(__name__)

#: How much lower (nice increment) the table build runs than the daemon, the model worker and the simulated board.
BUILD_NICENESS = 10
#: How long (s) a build asked to stop may take before its process group is killed.
STOP_WAIT_S = 5.0
#: How often (s) the background table build's progress goes to the log and to systemd's status line.
BUILD_REPORT_S = 10.0


def notify_systemd(*lines: str) -> bool:
    """Tell systemd about the service (``READY=1``, ``STATUS=...``, ``STOPPING=1``; sd_notify(3)) when it started
    the daemon with ``$NOTIFY_SOCKET``; True if sent. Outside systemd it does nothing."""
    address = os.environ.get("NOTIFY_SOCKET")
    if not address:
        return False
    if address.startswith("@"):  # an abstract socket
        address = "\0" + address[1:]
    try:
        with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC) as notify:
            notify.connect(address)
            notify.sendall("\n".join(lines).encode())
    except OSError as error:
        logger.warning("could not notify systemd on %s: %s", os.environ["NOTIFY_SOCKET"], error)
        return False
    return True


@dataclass
class Progress:
    """How far one long piece of work is: ``done`` of ``total`` units, and the seconds spent and left."""

    what: str
    done: int = 0
    total: int = 0
    started_s: float = 0.0
    now_s: float = 0.0

    @property
    def elapsed_s(self) -> float:
        return max(0.0, self.now_s - self.started_s)

    @property
    def left_s(self) -> float | None:
        """Seconds left at the rate so far; None before the first unit is done."""
        if self.done <= 0 or self.total <= 0:
            return None
        return self.elapsed_s / self.done * max(0, self.total - self.done)

    def text(self) -> str:
        """``response table: 120/347 solves, 61 s so far, about 115 s left``."""
        if self.total <= 0:
            return f"{self.what}: {self.elapsed_s:.0f} s so far"
        left = f", about {self.left_s:.0f} s left" if self.left_s is not None else ""
        return f"{self.what}: {self.done}/{self.total}, {self.elapsed_s:.0f} s so far{left}"

    def to_json(self) -> dict[str, Any]:
        return {"what": self.what, "done": self.done, "total": self.total, "elapsed_s": round(self.elapsed_s, 1),
                "left_s": None if self.left_s is None else round(self.left_s, 1)}


class StartupProgress:
    """What the daemon is doing before it is ready, for the API's ``starting`` answers and systemd's status line.

    ``stage`` is one line (``loading the model of builtin:converged``); ``work`` the progress of a long stage.
    """

    def __init__(self, clock: Any = time.monotonic):
        self.clock = clock
        self.started_s = clock()
        self.stage = "starting"
        self.stage_started_s = self.started_s
        #: the latest thing the stage's worker said (``meshing the built-in prostate at 4 mm``), if any
        self.detail: str | None = None

    def enter(self, stage: str) -> None:
        """A new stage begins (logged, and sent to systemd as the unit's status)."""
        self.stage, self.stage_started_s, self.detail = stage, self.clock(), None
        logger.info("start-up: %s", stage)
        notify_systemd(f"STATUS={stage}")

    def tell(self, detail: str) -> None:
        """What the current stage is doing now (from any thread)."""
        self.detail = detail.strip()

    def text(self) -> str:
        """The stage, what it is doing now and how long it has taken, for a ``starting`` answer."""
        now_s = self.clock()
        detail = f": {self.detail}" if self.detail else ""
        return (f"{self.stage}{detail} ({now_s - self.stage_started_s:.0f} s so far, {now_s - self.started_s:.0f} s "
                "since the daemon started)")

    def to_json(self) -> dict[str, Any]:
        return {"stage": self.stage, "detail": self.detail, "stage_s": round(self.clock() - self.stage_started_s, 1),
                "since_start_s": round(self.clock() - self.started_s, 1)}


# --- the response table, built in the background ------------------------------------------------------------

def _build_in_child(scene_source: str, results: Connection, parent_pid: int) -> None:
    """In the build process: its own process group (so that the daemon can end it and the solver processes it
    starts in one call), a lower priority, death with the daemon; then the table, with progress on ``results``.

    The daemon's death sends it SIGTERM, which ends its solver processes too (:func:`_stop_build`). With SIGKILL,
    a daemon killed during the build (the OOM killer, systemd's last resort) left the solver processes running
    under PID 1 and the semaphores of their pool in /dev/shm: the resource tracker that removes them waits until
    every process holding its pipe has ended."""
    from phantom.model.cluster import exit_with_parent

    os.setpgid(0, 0)
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the daemon's; it ends this process group
    signal.signal(signal.SIGTERM, _stop_build)
    exit_with_parent(parent_pid, signal.SIGTERM)
    os.nice(BUILD_NICENESS)
    started_s = time.monotonic()
    try:
        from phantom.host.scenes import load_timeline_scene
        from phantom.model import PhantomModel
        from phantom.model.fidelity.response_table import response_table

        model = PhantomModel.from_scene(load_timeline_scene(scene_source))
        settings = model.model_settings
        table = response_table(model, settings.pressure_max_pa, settings.table_points,
                               progress=lambda done, total: results.send(("progress", done, total)))
        results.send(("done", time.monotonic() - started_s, table.check_errors_pct))
    except Exception as error:  # the daemon reports it and keeps serving on the full solve
        logger.exception("the response table's build failed")
        results.send(("failed", f"{type(error).__name__}: {error}"))
    finally:
        results.close()


def _stop_build(signum: int, frame: object) -> None:
    """SIGTERM in the build process: kill the solver processes it started (mid-solve: their work is lost anyway),
    run multiprocessing's finalizers, which release the pool's semaphores (what Python's exit runs first), and
    exit at once. A SIGKILL of the whole group leaves the semaphores to the daemon's resource tracker, which warns
    of leaked semaphores at its exit; and an exit through Python, unwinding the Dask cluster's shutdown, took
    3.4-4.5 s of the STOP_WAIT_S at nice 10 beside busy processes (0.2-0.3 s this way), and was killed past it in
    a clean clone's make test."""
    # a failure here leaves the build to Python's exit: child_pids reads past a process that ends meanwhile (a
    # thread's children read without care failed in a clean clone's make test, and the build took 3.8 s to end)
    for child in child_pids():
        with contextlib.suppress(ProcessLookupError):
            os.kill(child, signal.SIGKILL)
    multiprocessing_util._exit_function()  # type: ignore[attr-defined]  # private, as Python's exit calls it
    os._exit(0)


class TableBuild:
    """The response table of a scene, built in a process of its own while the daemon serves on the full solve.

    The process and the solver processes it starts form one process group at a lower CPU priority
    (:data:`BUILD_NICENESS`): the daemon, its model worker and a simulated board keep the CPU they need. The table
    lands in the model's disk cache, where the model worker then reads it.
    """

    def __init__(self, scene_source: str, clock: Any = time.monotonic):
        self.scene_source = scene_source
        self.clock = clock
        self.progress = Progress("response table solves", started_s=clock(), now_s=clock())
        self.finished = False
        self.error: str | None = None
        self.check_errors_pct: float | None = None
        context = multiprocessing.get_context("spawn")
        self._results, child_end = context.Pipe(duplex=False)
        self._process = context.Process(target=_build_in_child, args=(scene_source, child_end, os.getpid()),
                                         name="phantom response table", daemon=False)
        self._process.start()
        child_end.close()

    @property
    def pid(self) -> int | None:
        return self._process.pid

    def fileno(self) -> int:
        """The results pipe, for the event loop's reader."""
        return self._results.fileno()

    def read(self) -> bool:
        """Take what the build reported since the last call (without blocking); True once it has ended (see
        ``error`` and ``check_errors_pct``)."""
        while not self.finished and self._results.poll():
            try:
                message = self._results.recv()
            except (EOFError, OSError):
                self._ended(f"the build process ended without a table (exit status {self._process.exitcode})")
                break
            self.progress.now_s = self.clock()
            if message[0] == "progress":
                self.progress.done, self.progress.total = int(message[1]), int(message[2])
            elif message[0] == "done":
                self.check_errors_pct = float(message[2])
                self._ended(None)
            else:
                self._ended(str(message[1]))
        self.progress.now_s = self.clock()
        return self.finished

    def _ended(self, error: str | None) -> None:
        self.finished, self.error = True, error
        self._process.join(5.0)
        self._results.close()

    def _now(self) -> Progress:
        if not self.finished:
            self.progress.now_s = self.clock()
        return self.progress

    def text(self) -> str:
        """``response table solves: 120/347, 61 s so far, about 115 s left``."""
        return self._now().text()

    def to_json(self) -> dict[str, Any]:
        return {**self._now().to_json(), "finished": self.finished, "error": self.error}

    def stop(self) -> None:
        """End the build if it still runs: SIGTERM (it kills its solver processes and exits cleanly), then SIGKILL
        to its whole process group if it has not ended within STOP_WAIT_S; and reap it."""
        if self._process.is_alive():
            self._process.terminate()
            self._process.join(STOP_WAIT_S)
        if self._process.is_alive() and self._process.pid is not None:
            with contextlib.suppress(ProcessLookupError, PermissionError):
                os.killpg(self._process.pid, signal.SIGKILL)
            self._process.kill()  # before its setpgid, the group is not there yet
        self._process.join(5.0)
        if not self._results.closed:
            self._results.close()


class BackgroundTable:
    """The daemon's side of a :class:`TableBuild`: started when the scene's table is not stored, read on the
    event loop, its progress told every BUILD_REPORT_S, and the model switched to the table once it is stored
    (``on_switched``: the held target is solved again on it)."""

    def __init__(self, scene_source: str, model: Model, event: Callable[[str, str, str], None],
                 ready: Callable[[], bool], startup: StartupProgress, on_switched: Callable[[], None]):
        self.scene_source, self.model, self.event, self.ready = scene_source, model, event, ready
        self.startup, self.on_switched = startup, on_switched
        self.build: TableBuild | None = None
        #: when the progress was last logged: never, so that the first tick of a build logs it
        self._reported_s = -math.inf
        self._switching: asyncio.Task[None] | None = None

    def start(self) -> None:
        self.build = TableBuild(self.scene_source)
        self.event("model", f"the model answers on full solves (most of a second each) while its response table "
                   f"is built in the background (process {self.build.pid}, once per model and machine)", "INFO")
        asyncio.get_running_loop().add_reader(self.build.fileno(), self._readable)

    def _readable(self) -> None:
        build = self.build
        assert build is not None  # the reader exists only while a build does
        if not build.read():
            return
        asyncio.get_running_loop().remove_reader(build.fileno())
        if build.error is not None:
            self.event("model", f"the response table could not be built ({build.error}): the model keeps "
                       "answering on full solves", "ERROR")
            return
        self._switching = asyncio.get_running_loop().create_task(self._switch(build))

    async def _switch(self, build: TableBuild) -> None:
        info = await self.model.use_level(self.model.info.pending_fidelity or "table")
        self.event("model", f"switched to the {info.fidelity} level: the response table was built in "
                   f"{build.progress.elapsed_s:.0f} s, within {build.check_errors_pct or 0.0:.2g} % of full solves",
                   "INFO")
        notify_systemd(f"STATUS={'ready' if self.ready() else self.startup.stage}: fidelity {info.fidelity}")
        self.on_switched()

    def report_tick(self, now_s: float) -> None:
        """Every BUILD_REPORT_S while the table builds: how far it is, in the log and systemd's status line."""
        build = self.build
        if build is None or build.finished or now_s - self._reported_s < BUILD_REPORT_S:
            return
        self._reported_s = now_s
        text = build.text()
        logger.info("%s (the model answers on full solves until then)", text)
        notify_systemd(f"STATUS={'ready' if self.ready() else self.startup.stage}; {text}")

    def to_json(self) -> dict[str, Any] | None:
        return self.build.to_json() if self.build is not None else None

    def stop(self) -> None:
        if self.build is not None:
            with contextlib.suppress(ValueError, OSError):
                asyncio.get_running_loop().remove_reader(self.build.fileno())
            self.build.stop()
        if self._switching is not None:
            self._switching.cancel()
