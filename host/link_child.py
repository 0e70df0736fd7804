"""The board link's process itself (started by :mod:`phantom.host.link_entry` for
:class:`phantom.host.link_process.LinkProcess`): the :class:`~phantom.host.session.LinkSession` on an event loop of
its own, at the real-time priority it may have, talking to the daemon over a pipe."""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import logging
import os
import queue
import signal
import threading
import time
from collections.abc import Awaitable
from multiprocessing.connection import Connection
from typing import Any

from phantom.host.session import BoardInfo, CommandRejected, LinkSession, LinkTiming, Transport
from phantom.host.stalls import GC_PAUSES, LoopStalls
from phantom.protocol import ProtocolError

logger = logging.getLogger(__name__)

#: How often (s) the link process sends its status (the daemon's ``status`` shows the latest).
STATUS_PERIOD_S = 0.2
#: Telemetry frames the link process keeps for a daemon that does not read them (a stalled daemon): beyond, the
#: oldest are dropped (counted as ``telemetry_dropped``), never the keepalive's time. 4 s at the default 50
#: frames/s, 2 s at the fastest (10 ms).
TELEMETRY_BACKLOG = 200
#: How long (s) the writer to the daemon is given to finish when the process ends.
STOP_WAIT_S = 5.0


def scheduling_of_this_process(rt_priority: int | None) -> str:
    """Ask for SCHED_FIFO at ``rt_priority``; what the process runs at, for the status."""
    if rt_priority is not None:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(rt_priority))
        except OSError as error:
            return (f"normal, nice {os.getpriority(os.PRIO_PROCESS, 0)} (SCHED_FIFO {rt_priority} refused: "
                    f"{error.strerror}; allow it with the unit's LimitRTPRIO= or limits.conf's rtprio)")
        return f"SCHED_FIFO {rt_priority}"
    return f"normal, nice {os.getpriority(os.PRIO_PROCESS, 0)}"


class _Sender:
    """The process's messages to the daemon, written by a thread of their own so that a daemon that does not
    read (a stalled loop, a full pipe) never holds up the link's loop; telemetry beyond
    :data:`TELEMETRY_BACKLOG` frames waiting is dropped and counted, nothing else is."""

    def __init__(self, connection: Connection):
        self.connection = connection
        self.telemetry_dropped = 0
        self._queue: queue.SimpleQueue[tuple[Any, ...] | None] = queue.SimpleQueue()
        self._telemetry_waiting = 0
        self._lock = threading.Lock()
        self._thread = threading.Thread(target=self._write, name="to the daemon", daemon=True)
        self._thread.start()

    def send(self, message: tuple[Any, ...]) -> None:
        if message[0] == "telemetry":
            with self._lock:
                if self._telemetry_waiting >= TELEMETRY_BACKLOG:
                    self.telemetry_dropped += 1
                    return
                self._telemetry_waiting += 1
        self._queue.put(message)

    def close(self) -> None:
        self._queue.put(None)
        self._thread.join(STOP_WAIT_S)

    def _write(self) -> None:
        while (message := self._queue.get()) is not None:
            if message[0] == "telemetry":
                with self._lock:
                    self._telemetry_waiting -= 1
            try:
                self.connection.send(message)
            except (OSError, ValueError):
                return


def serve_link(connection: Connection, transport: Transport, timing: LinkTiming, rt_priority: int | None,
               log_level: str, daemon_silent_s: float) -> None:
    """The link's process (started by :mod:`phantom.host.link_entry`, which has made it die with the daemon): its
    session on its own loop until the daemon says stop or is gone."""
    from phantom.host.logs import configure_logging

    with contextlib.suppress(ValueError):
        configure_logging(log_level)
    # SIGTERM and Ctrl-C to the daemon's process group are the daemon's: it vents through this process and ends
    # the board's session, then stops it
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    scheduling = scheduling_of_this_process(rt_priority)
    sender = _Sender(connection)
    try:
        asyncio.run(_run_session(connection, sender, transport, timing, scheduling, daemon_silent_s))
    finally:
        sender.close()
        connection.close()


async def _run_session(connection: Connection, sender: _Sender, transport: Transport, timing: LinkTiming,
                       scheduling: str, daemon_silent_s: float) -> None:
    loop = asyncio.get_running_loop()
    #: when the daemon last said anything (its loop says it is alive every LinkProcess.ALIVE_PERIOD_S)
    heard_at_s = time.monotonic()
    #: each connection's wait for the daemon to restore its state, by the connection's number
    restored: dict[int, asyncio.Future[None]] = {}
    connections = itertools.count()
    stalls = LoopStalls()
    GC_PAUSES.install()

    def send_status() -> None:
        status = session.status()
        status["event_loop"] = stalls.to_json()
        status["sent_s"] = time.monotonic()
        status["process"] = {"pid": os.getpid(), "scheduling": scheduling,
                             "telemetry_dropped": sender.telemetry_dropped}
        sender.send(("status", status))

    async def on_online(board: BoardInfo, reconnected: bool) -> None:
        number = next(connections)
        restored[number] = loop.create_future()
        send_status()
        sender.send(("online", board, reconnected, number))
        try:
            await restored[number]
        finally:
            del restored[number]

    def on_event(kind: str, text: str, level: str) -> None:
        send_status()
        sender.send(("event", kind, text, level))

    session = LinkSession(transport, timing, on_telemetry=lambda telemetry: sender.send(("telemetry", telemetry)),
                          on_event=on_event, on_online=on_online,
                          on_motion=lambda message: sender.send(("motion", message)))
    tasks: set[asyncio.Task[None]] = set()

    async def answer(request: int, work: Awaitable[Any]) -> None:
        try:
            sender.send(("answer", request, "ok", await work))
        except CommandRejected as error:
            sender.send(("answer", request, "rejected", (error.command, error.status)))
        except ProtocolError as error:  # a field the protocol cannot carry: the caller's mistake, said as such
            sender.send(("answer", request, "invalid", str(error)))
        except Exception as error:  # LinkDown, or what it did not foresee: the daemon's command fails with it
            sender.send(("answer", request, "down", str(error) or type(error).__name__))

    def readable() -> None:
        nonlocal heard_at_s
        try:
            while connection.poll():
                message = connection.recv()
                heard_at_s = time.monotonic()
                kind = message[0]
                if kind == "alive":
                    continue
                if kind == "command":
                    task = loop.create_task(answer(message[1], session.command(message[2], message[3])))
                elif kind == "end_session":
                    task = loop.create_task(answer(message[1], session.end_session()))
                elif kind == "online_done":
                    waiting = restored.get(message[1])
                    if waiting is not None and not waiting.done():
                        waiting.set_result(None)
                    continue
                else:  # stop
                    session.stop()
                    continue
                tasks.add(task)
                task.add_done_callback(tasks.discard)
        except (EOFError, OSError):  # the daemon is gone: stop, so that the board's deadline vents it
            loop.remove_reader(connection.fileno())
            session.stop()

    def watch_the_daemon() -> None:
        """A daemon silent for ``daemon_silent_s`` is hung: withhold the keepalive, so that the board latches
        DEAD_HOST and vents as it would for a daemon gone; give it back once the daemon speaks again."""
        silent_s = time.monotonic() - heard_at_s
        if not session.keepalive_withheld and silent_s > daemon_silent_s and session.online:
            session.withhold_keepalive(True)
            text = (f"the daemon's loop has said nothing for {silent_s:.1f} s (hung): the board's keepalive "
                    "withheld, so that it latches DEAD_HOST and vents; restart the daemon if it does not come back")
            logger.error(text)
            on_event("daemon_silent", text, "ERROR")  # the daemon reads it when its loop runs again
        elif session.keepalive_withheld and silent_s <= daemon_silent_s:
            session.withhold_keepalive(False)
            text = ("the daemon answered again: the board's keepalive resumed (a fault it latched meanwhile stays "
                    "until cleared: phantom clear-fault)")
            logger.warning(text)
            on_event("daemon_silent", text, "WARNING")

    async def report() -> None:
        while True:
            watch_the_daemon()
            send_status()
            await asyncio.sleep(STATUS_PERIOD_S)

    loop.add_reader(connection.fileno(), readable)
    helpers = [loop.create_task(stalls.probe()), loop.create_task(report())]
    try:
        await session.run()
    finally:
        for helper in helpers:
            helper.cancel()
        send_status()
        session.transport.close()
