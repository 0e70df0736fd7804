"""The board link in a process of its own (:class:`LinkProcess`), at a real-time priority where it may have one.

Why a process, and why a priority (issue 48, "the link holds while the phantom learns"): a verified target's
scan beside one busy process per core latched DEAD_HOST, the link's loop 500-620 ms late. Its probe's thread
waited for a core for most of each long stall (``/proc/thread-self/schedstat``: 123 of 171 ms in the worst of a
verify at load 2.5-8, the garbage collector 0 ms; bench/README.md), and a thread of the daemon's process also
waits for the GIL, which the daemon's loop holds when the kernel takes its core away. Here the link's loop is
alone in a small process (its own GIL), which asks the kernel for ``SCHED_FIFO`` (the board's keepalive is the
one thing on the machine that must keep time; it needs a few milliseconds of CPU a second): granted to root,
to a user with ``RLIMIT_RTPRIO`` (``LimitRTPRIO=`` of a systemd unit, ``rtprio`` in limits.conf) or
``CAP_SYS_NICE``; otherwise it keeps the daemon's priority and says so (status ``link_detail.process``).

The daemon talks to it over a pipe: commands and the end of the session out; the session's telemetry, events,
motion frames, answers and its status back. The process dies with the daemon (``PR_SET_PDEATHSIG``; the pipe's
end too): its keepalive stops, and the board vents at its dead-host deadline, as with a daemon of one process.
A daemon alive but hung (its loop blocked: a deadlock, a call that never returns) would otherwise keep the
phantom inflated with nobody to answer a stop: its loop says it is alive every :data:`ALIVE_PERIOD_S`, and a
process that hears nothing from it for ``daemon_silent_s`` withholds the keepalive until it does, so that the
board vents then too.

The other way round, a link's process that stops reporting (stopped, hung, starved of every core) leaves the
daemon with its last status: from :data:`LINK_SILENT_S` without one, the link is ``silent`` (not online: no
measured pressure or estimate is shown as current, commands are refused), the daemon is told so at once and, when
the process reports again, for how long it was silent.
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import logging
import multiprocessing
import os
import pickle
import time
from collections import deque
from collections.abc import Awaitable, Callable
from multiprocessing.connection import Connection
from typing import Any

from phantom.host import link_entry
from phantom.host.link_child import STATUS_PERIOD_S
from phantom.host.session import (
    BoardInfo,
    CommandRejected,
    LinkDown,
    LinkState,
    LinkStats,
    LinkTiming,
    Telemetry,
    Transport,
)
from phantom.protocol import ProtocolError
from phantom.protocol.codec import Message

__all__ = ["LINK_RT_PRIORITY", "LINK_SILENT_S", "LinkProcess"]

logger = logging.getLogger(__name__)

#: The link process's SCHED_FIFO priority by default (1-99; low: above every normal process, below the kernel's
#: threads); the daemon's setting ``link_rt_priority``.
LINK_RT_PRIORITY = 10
#: How long (s) :meth:`LinkProcess.run` waits for the process to end after asking it to stop.
STOP_WAIT_S = 5.0
#: How often (s) the daemon's loop tells the link's process that it runs.
ALIVE_PERIOD_S = 0.5
#: How long (s) the daemon's loop may say nothing before the link's process lets the board vent: hung, not busy.
#: Its longest stalls measured were 0.4-0.6 s beside busy cores and a 1.5 s GIL hold (bench/README.md, "A
#: verified target's scan beside busy cores"; tests/test_link_process.py); the board's own deadline is 0.5 s.
DAEMON_SILENT_S = 10.0
#: How long (s) the link's process may send no status (it sends one every STATUS_PERIOD_S, 0.2 s) before its link is
#: shown as ``silent``: five missed, and twice the board's 500 ms dead-host deadline, which a process that did not
#: run for that long has let pass (its keepalive stopped with it).
LINK_SILENT_S = 5 * STATUS_PERIOD_S
#: How long (s) a link found online again after a silence must stay online, on its connection of before, before the
#: daemon restores the board's state on it: the process's first status after a stop may be the one it had before,
#: its loss of the board found only a moment later (then the reconnection restores it).
SILENCE_SETTLE_S = 2 * STATUS_PERIOD_S
#: A link's process that ends by itself (the OOM killer, a crash) is started again, as the simulated board and the
#: model worker are, unless it has ended more than this many times within :data:`LINK_RESTART_WINDOW_S`: then the
#: daemon stops (exit status 1; systemd starts it again), a process that dies at once being a fault, not bad luck.
LINK_RESTARTS = 3
LINK_RESTART_WINDOW_S = 60.0


class LinkProcess:
    """A :class:`LinkSession` on ``transport`` in a spawned process of its own; the daemon sees the session's
    interface (:class:`phantom.host.parts.BoardSession`).

    Parameters
    ----------
    transport : SerialTransport or CanTransport
        Not opened: the process opens it (a CAN bus of python-can's ``virtual`` interface is per process).
    timing : LinkTiming
        The link core's periods and deadlines.
    rt_priority : int or None
        The SCHED_FIFO priority the process asks for (None: none; it keeps the daemon's).
    daemon_silent_s : float
        How long the daemon's loop may be silent before the process withholds the board's keepalive (at least
        twice :data:`ALIVE_PERIOD_S`).
    clock : callable() -> float, optional
        The daemon's monotonic clock in seconds (``time.monotonic``; a counter in tests): when each status arrived,
        and how long the process has been silent.
    """

    def __init__(self, transport: Transport, timing: LinkTiming, rt_priority: int | None = LINK_RT_PRIORITY,
                 daemon_silent_s: float = DAEMON_SILENT_S, clock: Callable[[], float] = time.monotonic):
        if not daemon_silent_s >= 2 * ALIVE_PERIOD_S:
            raise ValueError(f"daemon_silent_s must be at least {2 * ALIVE_PERIOD_S:g} s (twice the daemon's "
                             f"{ALIVE_PERIOD_S:g} s between words to the link's process), not {daemon_silent_s!r}")
        self.transport = transport
        self.timing = timing
        self.rt_priority = rt_priority
        self.daemon_silent_s = daemon_silent_s
        self.clock = clock
        self._status: dict[str, Any] = {"state": LinkState.DISCONNECTED.value,
                                        "transport": transport.description, "board": None, "board_info": None,
                                        "last_error": "the link's process is starting",
                                        "stats": LinkStats().as_dict({}, 0, None)}  # all its keys, zero
        self._on_telemetry: Callable[[Telemetry], None] = lambda telemetry: None
        self._on_event: Callable[[str, str, str], None] = lambda kind, text, level: None
        self._on_online: Callable[[BoardInfo, bool], Awaitable[None]] | None = None
        self._on_motion: Callable[[Message], None] = lambda message: None
        self._connection: Connection | None = None
        self._process: multiprocessing.process.BaseProcess | None = None
        self._answers: dict[int, asyncio.Future[Any]] = {}
        self._ids = itertools.count()
        self._stopping = False
        self._ended: asyncio.Future[None] | None = None
        self._onlines: set[asyncio.Task[None]] = set()
        #: when the last status arrived (the clock's s; None: none yet, the process is starting)
        self._reported_at: float | None = None
        #: since when (the clock's s) the process has been told to be silent (None: it is not)
        self._silent_since: float | None = None
        #: the board of the latest connection the process said was online, and that connection's count
        self._board: BoardInfo | None = None
        #: after a silence with the link still online on its connection of before: since when it has been (None:
        #: nothing to restore), and that connection's count
        self._online_again: tuple[float, int] | None = None
        #: how often the process ended by itself and was started again
        self.restarts = 0

    def attach(self, on_telemetry: Callable[[Telemetry], None], on_event: Callable[[str, str, str], None],
               on_online: Callable[[BoardInfo, bool], Awaitable[None]] | None,
               on_motion: Callable[[Message], None]) -> None:
        """The session's callbacks, run on the loop that awaits :meth:`run`."""
        self._on_telemetry, self._on_event, self._on_online, self._on_motion = (on_telemetry, on_event, on_online,
                                                                               on_motion)

    @property
    def state(self) -> LinkState:
        """The session's state as its process last said it, or ``silent`` when it has not reported for
        :data:`LINK_SILENT_S`: what it said then is no longer known to hold."""
        if self.silent_for_s() is not None:
            return LinkState.SILENT
        return LinkState(self._status["state"])

    def silent_for_s(self) -> float | None:
        """How long (s) the process has sent no status, once beyond :data:`LINK_SILENT_S` (None: it reports)."""
        if self._reported_at is None or self._status["state"] == LinkState.STOPPED.value:
            return None
        silent_s = self.clock() - self._reported_at
        if silent_s <= LINK_SILENT_S or self._messages_waiting():
            return None
        return silent_s

    def _messages_waiting(self) -> bool:
        """Whether the process has sent what the daemon has not read yet: then the daemon's loop was late (a stall
        of its own, up to 1.5 s measured), not the process silent."""
        try:
            return self._connection is not None and self._connection.poll()
        except (EOFError, OSError):
            return False

    @property
    def online(self) -> bool:
        return self.state is LinkState.ONLINE

    def status(self) -> dict[str, Any]:
        """The session's status as the process last sent it (at most :data:`STATUS_PERIOD_S` old), with its
        loop's stalls (``event_loop``, its stalls' ages as of now) and the process (``process``: pid, scheduling)."""
        status = dict(self._status)
        if (silent_s := self.silent_for_s()) is not None:
            status["state"], status["last_error"] = LinkState.SILENT.value, self._silence_text(silent_s)
        sent_s = status.pop("sent_s", None)
        loop = status.get("event_loop")
        if sent_s is not None and loop is not None:  # one monotonic clock for the machine's processes
            age_s = time.monotonic() - sent_s
            status["event_loop"] = {**loop, "notable_stalls": [[round(ago_s + age_s, 3), *rest]
                                                               for ago_s, *rest in loop["notable_stalls"]]}
        status["process"] = {**status.get("process", {}), "restarts": self.restarts}
        return status

    async def run(self) -> None:
        """Start the process and serve it until :meth:`stop`. One that ends by itself is started again and the
        daemon told (the board, without its keepalive meanwhile, vents at its dead-host deadline: a fault to clear);
        :class:`LinkDown` once it has ended more than :data:`LINK_RESTARTS` times within
        :data:`LINK_RESTART_WINDOW_S`."""
        ended_s: deque[float] = deque()
        while True:
            try:
                await self._serve_one_process()
                return
            except LinkDown as error:
                now_s = self.clock()
                ended_s.append(now_s)
                while now_s - ended_s[0] > LINK_RESTART_WINDOW_S:
                    ended_s.popleft()
                if len(ended_s) > LINK_RESTARTS:
                    raise LinkDown(f"{error}, {len(ended_s)} times within {LINK_RESTART_WINDOW_S:g} s: not started "
                                   "again") from None
                self.restarts += 1
                self._silent_since = self._online_again = None
                text = (f"{error}: started again (restart {self.restarts}); the board, without its keepalive "
                        "meanwhile, vents at its dead-host deadline")
                logger.error("%s", text)
                self._on_event("link_process", text, "ERROR")

    async def _serve_one_process(self) -> None:
        """Start the process and serve it until :meth:`stop`; raises :class:`LinkDown` if it ended by itself."""
        loop = asyncio.get_running_loop()
        context = multiprocessing.get_context("spawn")  # not forked: no copy of the daemon's threads and loops
        ours, theirs = context.Pipe()
        level = logging.getLevelName(logging.getLogger("phantom").getEffectiveLevel()).lower()
        settings = pickle.dumps((self.transport, self.timing, self.rt_priority, level, self.daemon_silent_s))
        process = context.Process(target=link_entry.main, args=(theirs, os.getpid(), settings),
                                  name="phantom board link", daemon=True)
        process.start()
        theirs.close()
        self._process, self._connection = process, ours
        self._ended = loop.create_future()
        loop.add_reader(ours.fileno(), self._readable)
        alive = loop.create_task(self._say_alive())
        watch = loop.create_task(self._watch_the_process())
        try:
            await asyncio.shield(self._ended)
        except asyncio.CancelledError:
            self.stop()
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(asyncio.shield(self._ended), STOP_WAIT_S)
            raise
        finally:
            alive.cancel()
            watch.cancel()
            with contextlib.suppress(ValueError, OSError):
                loop.remove_reader(ours.fileno())
            ours.close()
            await loop.run_in_executor(None, process.join, STOP_WAIT_S)
            if process.is_alive():
                process.kill()
            self._fail_answers(LinkDown("no board: the link's process ended"))
            self._status = {**self._status, "state": LinkState.STOPPED.value}
        if not self._stopping:
            raise LinkDown(f"the board link's process ended by itself (exit status {process.exitcode})")

    def stop(self) -> None:
        """Make :meth:`run` return after the process closed the port."""
        self._stopping = True
        self._send(("stop",))

    async def command(self, name: str, fields: dict[str, Any] | None = None) -> str:
        """:meth:`LinkSession.command`, run in the link's process."""
        if not self.online:
            # a silence found here before the watch (every STATUS_PERIOD_S) is told first: a verified target's scan
            # failing on it must find the link lost (retaken, then the fault named), not a failed scan
            self.check_reports()
            last = self._status.get("last_error")
            raise LinkDown(f"no board: the link is {self.state.value}" + (f" ({last})" if last else ""))
        answer: str = await self._ask("command", name, fields or {})
        return answer

    async def end_session(self) -> bool:
        """:meth:`LinkSession.end_session`, run in the link's process."""
        try:
            ended: bool = await self._ask("end_session")
        except LinkDown:
            return False
        return ended

    def check_reports(self) -> None:
        """Tell the daemon (an event) when the process has just gone silent; restore the board's state once a
        link that stayed online through a silence is seen to hold (:data:`SILENCE_SETTLE_S`)."""
        silent_s = self.silent_for_s()
        if silent_s is not None and self._silent_since is None:
            assert self._reported_at is not None
            self._silent_since = self._reported_at
            text = self._silence_text(silent_s)
            logger.error(text)
            # a link lost for the daemon: a verified target's scan failing now is retaken
            self._on_event("link_lost", f"link lost: {text}", "ERROR")
        self._restore_if_online_again()

    def _silence_text(self, silent_s: float) -> str:
        pid = self._status.get("process", {}).get("pid")
        return (f"the link's process{f' (pid {pid})' if pid else ''} has not reported for {silent_s:.1f} s (it "
                f"reports every {STATUS_PERIOD_S:g} s): stopped or hung; the board's state is unknown, and what the "
                "process last said is not shown as current")

    def _reported(self, status: dict[str, Any]) -> None:
        """A status from the process: the link is what it says; a silence before it is over, and told."""
        self._status, self._reported_at = status, self.clock()
        if self._silent_since is None:
            return
        silent_s, self._silent_since = self._reported_at - self._silent_since, None
        text = f"the link's process reported again after {silent_s:.1f} s silent"
        logger.warning(text)
        self._on_event("link_process", text, "WARN")
        if status["state"] == LinkState.ONLINE.value and self._board is not None:
            self._online_again = (self._reported_at, status["stats"]["connects"])

    def _restore_if_online_again(self) -> None:
        if self._online_again is None:
            return
        since, connects = self._online_again
        if self._status["state"] != LinkState.ONLINE.value or self._status["stats"]["connects"] != connects:
            self._online_again = None  # lost, or reconnected: the reconnection restores the board's state
        elif self.clock() - since >= SILENCE_SETTLE_S and self._board is not None:
            # no loss the process found: the board may still have let go meanwhile (DEAD_HOST, vented), and the
            # daemon took it for gone; its state is restored as after a reconnection
            self._online_again = None
            self._on_event("link_process", "the link stayed online through its process's silence: the board's "
                           "state is restored as after a reconnection", "WARN")
            self._start_bringing_online(self._board, True, None)

    async def _watch_the_process(self) -> None:
        while True:
            self.check_reports()
            await asyncio.sleep(STATUS_PERIOD_S)

    # --- the pipe -----------------------------------------------------------------------------------------

    async def _say_alive(self) -> None:
        """Tell the process, from the daemon's own loop, that it runs (a hung loop says nothing)."""
        while self._send(("alive",)):
            await asyncio.sleep(ALIVE_PERIOD_S)

    async def _ask(self, kind: str, *arguments: Any) -> Any:
        request = next(self._ids)
        future: asyncio.Future[Any] = asyncio.get_running_loop().create_future()
        self._answers[request] = future
        if not self._send((kind, request, *arguments)):
            self._answers.pop(request, None)
            raise LinkDown("no board: the link's process is not running")
        return await future

    def _send(self, message: tuple[Any, ...]) -> bool:
        connection = self._connection
        if connection is None or connection.closed:
            return False
        try:
            connection.send(message)
        except (OSError, ValueError):
            return False
        return True

    def _readable(self) -> None:
        """What the process sent: every whole message there is (the pipe is read on the daemon's loop)."""
        connection = self._connection
        assert connection is not None
        try:
            while connection.poll():
                self._handle(connection.recv())
        except (EOFError, OSError):
            asyncio.get_running_loop().remove_reader(connection.fileno())
            if self._ended is not None and not self._ended.done():
                self._ended.set_result(None)

    def _handle(self, message: tuple[Any, ...]) -> None:
        kind = message[0]
        if kind == "telemetry":
            self._on_telemetry(message[1])
        elif kind == "motion":
            self._on_motion(message[1])
        elif kind == "status":
            self._reported(message[1])
        elif kind == "event":
            self._on_event(*message[1:])
        elif kind == "online":
            self._board, self._online_again = message[1], None
            self._start_bringing_online(*message[1:])
        elif kind == "answer":
            _, request, outcome, value = message
            future = self._answers.pop(request, None)
            if future is None or future.done():
                return
            if outcome == "ok":
                future.set_result(value)
            elif outcome == "rejected":
                future.set_exception(CommandRejected(*value))
            elif outcome == "invalid":
                future.set_exception(ProtocolError(value))
            else:
                future.set_exception(LinkDown(value))

    def _start_bringing_online(self, board: BoardInfo, reconnected: bool, connection: int | None) -> None:
        task = asyncio.create_task(self._bring_online(board, reconnected, connection))
        self._onlines.add(task)
        task.add_done_callback(self._onlines.discard)

    async def _bring_online(self, board: BoardInfo, reconnected: bool, connection: int | None) -> None:
        """The daemon restores its state on the new connection; the process is told when it is done (None: a
        connection it did not announce, kept through a silence: nothing of it waits)."""
        try:
            if self._on_online is not None:
                await self._on_online(board, reconnected)
        finally:
            if connection is not None:
                self._send(("online_done", connection))

    def _fail_answers(self, error: Exception) -> None:
        for future in self._answers.values():
            if not future.done():
                future.set_exception(error)
        self._answers.clear()
