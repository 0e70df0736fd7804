"""The daemon's scans in a process of their own: the capture (the virtual camera's rendering or a webcam's
frames, the pictures written) and the verify scan's reconstruction, out of the daemon's process.

Why: in a thread of the daemon, the rendering and the reconstruction hold Python's GIL for long stretches; when
the kernel gives that thread's core to another process while it holds the GIL (a lab PC is rarely idle), the
daemon's event loop and its board link's loop wait with it. At load 10-13 on two cores the loops were late by up
to 350 ms during a verify scan and the board latched DEAD_HOST (its 500 ms dead-host deadline passed) in three
verified targets of three (bench/README.md, "A verified target's scan beside busy cores").

How: :class:`ScanWorker` is both what ``phantom daemon`` gives the daemon as its ``Scanner`` (the ``scan`` API
method's capture, ``phantom.host.motion``) and as its ``VerifyScanner`` (the verify scan's plan and
reconstruction, ``phantom.host.daemon``). It runs them in one spawned process, kept while the
daemon runs, so that the imports (OpenCV, SciPy, the scanner's numba kernels, made on the first job) and the
simulated phantom's truth shape are paid once; ``phantom daemon`` starts it before the daemon and closes it when
the daemon has stopped, and it dies with the daemon however the daemon dies (PR_SET_PDEATHSIG). One job at a
time: a scan asked during a reconstruction waits for it.

In the process, the capture loop runs unchanged (the scanner ``phantom daemon`` gives:
``phantom.scan.daemon_scan.DaemonScanner``, the camera the scan's params say, a webcam through the same ``Webcam``
code as ever). Each of its calls on the rig (a move, the
rig's angles, the pressures, a stop request, the release, the simulated truth) is sent back over a pipe and
performed by the daemon's ``ThreadRig`` in the daemon's worker thread, which runs it on the daemon's loop: the
board link keeps one owner, and the daemon's thread does nothing heavy. What crosses the pipe is small: the
params, the capture folder's path, the rig's answers, the result's JSON and the reconstructed surface's arrays.
"""

from __future__ import annotations

import atexit
import multiprocessing
import os
import signal
import threading
import traceback
from typing import TYPE_CHECKING, Any

from phantom import PhantomError

if TYPE_CHECKING:
    from multiprocessing.connection import Connection
    from multiprocessing.process import BaseProcess

    from phantom.host.daemon import VerifyScanner
    from phantom.host.motion import Scanner

#: The rig's calls a capture makes (``phantom.host.motion.ThreadRig``'s methods): the only ones relayed.
RIG_CALLS = frozenset({"configure", "move_to", "position_deg", "release", "stop_requested", "pressures_kpa",
                       "simulated"})
#: How long :meth:`ScanWorker.close` waits for the process to end once told to (s), before it is killed.
CLOSE_WAIT_S = 10.0


class ScanWorker:
    """The daemon's scanner and verify scanner, run in a process of their own (see the module docstring).

    Parameters
    ----------
    scanner : Scanner
        The capture, run in the process for each ``scan`` request (picklable: sent to the process once).
    verify : VerifyScanner
        The verify scan's plan (:attr:`plan`, :meth:`plan_for`, read in the daemon) and its reconstruction (run
        in the process).
    log_level : str
        The process logs as the daemon does, at this level and above, to the daemon's stderr.
    """

    def __init__(self, scanner: Scanner, verify: VerifyScanner, log_level: str = "info"):
        self.scanner, self.verify, self.log_level = scanner, verify, log_level
        self.plan = verify.plan
        self._lock = threading.Lock()
        self._process: BaseProcess | None = None
        self._connection: Connection | None = None
        self._closed = False
        atexit.register(self.close)  # before multiprocessing's exit hook, which would wait for the process

    @property
    def pid(self) -> int | None:
        """The process's id while it runs (None before the first job, and once closed)."""
        process = self._process
        return process.pid if process is not None and process.is_alive() else None

    def __call__(self, params: dict[str, Any], rig: Any) -> dict[str, Any]:
        """A ``scan`` request's capture (``phantom.host.motion.Scanner``): blocking, called in the daemon's worker
        thread with its ``ThreadRig``, whose methods the capture calls through this thread."""
        return self._job("scan", params, rig)

    def plan_for(self, tolerance_pct: float) -> dict[str, Any]:
        """The verify scan's plan at ``tolerance_pct`` (%): the :class:`VerifyScan`'s, decided in the daemon."""
        return self.verify.plan_for(tolerance_pct)

    def expect_surface(self, model_surface_mm: tuple[Any, Any] | None) -> None:
        """The model's surface at the next verify scan's pressures, given to the process before its capture
        (``phantom.host.daemon.VerifyScanner``): blocking, run in a worker thread of the daemon."""
        self._job("surface", model_surface_mm, None)

    def volume(self, folder: str, model_surface_mm: tuple[Any, Any] | None = None) -> dict[str, Any]:
        """The capture folder reconstructed (``phantom.host.daemon.VerifyScanner``): blocking, run in a worker
        thread of the daemon, which waits without holding the GIL."""
        return self._job("volume", (folder, model_surface_mm), None)

    def close(self) -> None:
        """Tell the process to end and wait for it (killed after :data:`CLOSE_WAIT_S`); a job still running is
        left to fail. Idempotent."""
        self._closed = True
        process, connection = self._process, self._connection
        self._process = self._connection = None
        if connection is not None:
            try:
                connection.send(None)
            except (OSError, ValueError):  # it has ended, or a job's thread holds the pipe broken
                pass
            connection.close()
        if process is not None:
            process.join(CLOSE_WAIT_S)
            if process.is_alive():
                process.kill()
                process.join()
            process.close()

    def _job(self, kind: str, argument: Any, rig: Any) -> dict[str, Any]:
        from phantom.host.api import ApiError

        with self._lock:
            connection = self._started()
            try:
                connection.send((kind, argument))
                while True:
                    message = connection.recv()
                    if message[0] != "call":
                        break
                    connection.send(_performed(rig, message[1], message[2]))
            except (EOFError, OSError) as error:
                raise PhantomError(f"the scan's worker process ended during the {kind} ({self._ended(error)}): "
                                   "see the daemon's log; the next scan starts it again") from None
        if message[0] == "done":
            answer: dict[str, Any] = message[1]
            return answer
        if message[0] == "api_error":
            raise ApiError(message[1], message[2])
        if message[0] == "phantom_error":
            raise PhantomError(message[1])
        raise PhantomError(f"the {kind} failed in the scan's worker process: {message[1]} (its traceback is in the "
                           "daemon's log)")

    def start(self) -> None:
        """Start the process now, if it is not running. Call it from the thread that lives as long as the daemon
        (its main thread): Linux kills the process when the thread that started it ends (PR_SET_PDEATHSIG), and a
        job started from a worker thread of the daemon's loop would have it killed when that loop's executor ends,
        before :meth:`close` tells it to end (a process that died is started again by the next job, from its
        thread)."""
        with self._lock:
            self._started()

    def _started(self) -> Connection:
        """The process's end of the pipe, the process started first when it is not running."""
        if self._closed:
            raise PhantomError("the daemon's scan worker is closed: the daemon is stopping")
        if self._process is not None and self._process.is_alive() and self._connection is not None:
            return self._connection
        context = multiprocessing.get_context("spawn")  # not forked: no copy of the daemon's threads and loops
        ours, theirs = context.Pipe()
        # not daemonic: the capture's truth shape starts a process of its own
        process = context.Process(target=_serve, args=(theirs, os.getpid(), self.scanner, self.verify,
                                                       self.log_level), name="phantom scan worker")
        process.start()
        theirs.close()
        self._process, self._connection = process, ours
        return ours

    def _ended(self, error: BaseException) -> str:
        """Why the process is gone (its exit status), forgotten so that the next job starts another."""
        process, connection = self._process, self._connection
        self._process = self._connection = None
        if connection is not None:
            connection.close()
        if process is None:
            return str(error) or type(error).__name__
        process.join(CLOSE_WAIT_S)
        code = process.exitcode
        if code is None:
            process.kill()
            process.join()
            return "it stopped answering and was killed"
        return f"killed by signal {-code}" if code < 0 else f"exit status {code}"


def _performed(rig: Any, name: str, args: tuple[Any, ...]) -> tuple[str, Any]:
    """A rig call from the process performed here: ("value", its answer) or ("raised", why it failed)."""
    if rig is None or name not in RIG_CALLS:
        return "raised", f"the scan's worker asked {name!r}, which is not one of the rig's calls"
    try:
        return "value", getattr(rig, name)(*args)
    except PhantomError as error:
        return "raised", str(error)
    except Exception as error:  # the board's or the loop's failure, told to the capture (which aborts cleanly)
        return "raised", f"{type(error).__name__}: {error}"


# --- in the process ------------------------------------------------------------------------------------------


class _DaemonGone(Exception):
    """The daemon's end of the pipe closed: the process ends (not a PhantomError: no capture catches it)."""


class _PipeRig:
    """The daemon's rig as the capture in the process sees it: each call sent to the daemon's ``ThreadRig``."""

    def __init__(self, connection: Connection):
        self._connection = connection

    def _call(self, name: str, *args: Any) -> Any:
        try:
            self._connection.send(("call", name, args))
            kind, value = self._connection.recv()
        except (EOFError, OSError) as error:
            raise _DaemonGone(str(error)) from None
        if kind == "raised":
            raise PhantomError(value)
        return value

    def configure(self, configs: Any) -> None:
        self._call("configure", configs)

    def move_to(self, orbit_deg: float, elevation_deg: float) -> tuple[float, float]:
        orbit, elevation = self._call("move_to", orbit_deg, elevation_deg)
        return orbit, elevation

    def position_deg(self) -> tuple[float, float]:
        orbit, elevation = self._call("position_deg")
        return orbit, elevation

    def release(self) -> None:
        self._call("release")

    def stop_requested(self, wait_s: float = 0.0) -> str | None:
        reason: str | None = self._call("stop_requested", wait_s)
        return reason

    def pressures_kpa(self) -> list[float] | None:
        pressures: list[float] | None = self._call("pressures_kpa")
        return pressures

    def simulated(self) -> dict[str, Any] | None:
        truth: dict[str, Any] | None = self._call("simulated")
        return truth


def _serve(connection: Connection, parent_pid: int, scanner: Scanner, verify: VerifyScanner,
           log_level: str) -> None:
    """The process's loop: one job at a time until told to end (None) or the daemon's end closes."""
    from phantom.host.api import ApiError
    from phantom.host.logs import configure_logging
    from phantom.model.cluster import exit_with_parent

    exit_with_parent(parent_pid)
    configure_logging(log_level)
    # Ctrl-C and a SIGTERM to the daemon's process group are the daemon's to handle: it stops the scan (the
    # capture releases the motors and marks its folder stopped), then closes this process
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    # at the daemon's priority, not below it: the reconstruction is a round's wait, the board holding its pressures
    # meanwhile, and the link that must not wait is in a process of its own (real-time where allowed). Niced +5,
    # beside a busy process per core, a round took 73 s against 46 s (bench/README.md, "A round's last seconds")
    rig: Any = _PipeRig(connection)  # the ThreadRig's calls, relayed to it
    while True:
        try:
            request = connection.recv()
        except (EOFError, OSError):
            return
        if request is None:
            return
        kind, argument = request
        reply: tuple[Any, ...]
        try:
            if kind == "scan":
                answer = scanner(argument, rig)
            elif kind == "surface":
                verify.expect_surface(argument)
                answer = {}
            else:
                answer = verify.volume(*argument)
        except _DaemonGone:
            return
        except ApiError as error:
            reply = ("api_error", error.code, str(error))
        except PhantomError as error:  # a scanner's refusal of its params says so by its code (invalid_params)
            code = getattr(error, "code", None)
            reply = ("api_error", code, str(error)) if code == "invalid_params" else ("phantom_error", str(error))
        except Exception as error:  # a bug: its traceback to the daemon's log (this process's stderr is its)
            traceback.print_exc()
            reply = ("failed", f"{type(error).__name__}: {error}")
        else:
            reply = ("done", answer)
        try:
            connection.send(reply)
        except (OSError, ValueError):
            return
