"""The daemon's local API: a Unix stream socket, one JSON object per line.

A request ``{"id": ..., "method": "...", "params": {...}}`` gets ``{"id": ..., "result": ...}`` or
``{"id": ..., "error": {"code": "...", "message": "..."}}``. ``subscribe`` makes the connection also
receive ``{"event": "<topic>", "data": {...}}`` lines.

Every client has a bounded outgoing queue drained by its own writer task: a client that reads slowly or
not at all fills only its own queue; what does not fit is dropped and counted, and the control loop never
waits on a socket.
"""

from __future__ import annotations

import asyncio
import contextlib
import errno
import json
import logging
import os
import resource
import socket
import stat
import time
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from phantom import PhantomError, unique_keys
from phantom.host.peer import private_folder

logger = logging.getLogger(__name__)

#: Error codes a request can get back, with what they mean.
ERROR_CODES: dict[str, str] = {
    "parse_error": "the line is not a JSON object",
    "invalid_request": "the object lacks a string method, or params is not an object",
    "unknown_method": "no such method",
    "invalid_params": "the params are missing, of the wrong type or out of range",
    "unreachable": "the target cannot be reached within the pressure limits",
    "link_down": "no board is connected",
    "starting": "the daemon is still starting (its model, or the first connection to the board): data says how "
                "far it is; try again shortly",
    "rejected": "the board refused the command (e.g. a fault is latched and its cause persists)",
    "busy": "too many requests of this kind are in progress: try again when they are answered",
    "forbidden": "this connection's token is read-only (host/web.py): it may watch the phantom, not drive it",
    "internal": "a bug in the daemon: please report it",
}

#: Subscription topics.
TOPICS: tuple[str, ...] = ("telemetry", "status", "events")

#: Outgoing lines a client may have waiting before further ones are dropped.
CLIENT_QUEUE_LINES = 256

#: Longest request line accepted (bytes).
MAX_REQUEST_BYTES = 64 * 1024

#: File descriptors kept out of the API's reach (the board's port, the model worker's pipes, the recording, the
#: log): clients are capped this far below the process's file limit.
RESERVED_FILES = 64

#: Requests started in one turn of the event loop; the rest wait for the next turn. The loop runs every callback
#: that is ready in a turn before it looks at its timers again: 50 clients' `status` in one turn delayed the
#: control loop's timers by their sum.
REQUESTS_PER_TURN = 8

#: How long a request line, once begun, may take to end (s): a client that stops half way through one is closed
#: then, with why (3000 clients each holding half of a 60 kB line held 200 MB for as long as they stayed).
PARTIAL_LINE_TIMEOUT_S = 10.0
#: How long a new connection may stay silent before its first request (s): one that says nothing holds a file
#: and its buffers for nothing. A client that has asked once may idle as long as it likes (a notebook's
#: connection); at the connection cap the longest idle is shed.
SILENT_TIMEOUT_S = 60.0

#: How long after a client that held a long line is closed the heap's free pages are given back to the system (s):
#: once for a burst of them (Python frees their buffers, glibc keeps the pages: 3000 such clients left 107 MB).
GIVE_BACK_DELAY_S = 1.0

#: Connections the kernel queues until the daemon accepts them (one at a time): a burst of clients must fit, for
#: a client of a full queue (asyncio's, at least) believes it is connected and then finds the connection reset.
LISTEN_BACKLOG = 1024

#: How long a cancelled client task is given to end before it is cancelled again (s).
CANCEL_AGAIN_S = 0.1

#: The longest path a Unix socket may have (bytes): Linux's ``sun_path`` holds 108 with the closing NUL.
MAX_SOCKET_PATH_BYTES = 107


class PartialLineTimeout(TimeoutError):
    """A client began a request line and did not end it within the partial-line timeout."""


class ApiError(PhantomError):
    """An error answered to one request, with one of :data:`ERROR_CODES`; ``data`` (optional, JSON) says more
    for programs (a ``starting`` answer's progress)."""

    def __init__(self, code: str, message: str, data: dict[str, Any] | None = None):
        if code not in ERROR_CODES:
            raise ValueError(f"unknown API error code {code!r}")
        super().__init__(message)
        self.code = code
        self.data = data


Handler = Callable[[dict[str, Any]], Awaitable[object]]


class RawJson(str):
    """A result already written as JSON text (a large one, made off the event loop): sent as it is."""


@dataclass
class Client:
    """One connected client: its outgoing queue, subscriptions and counters."""

    number: int
    queue: asyncio.Queue[bytes | None]
    topics: set[str] = field(default_factory=set)
    dropped_lines: int = 0
    #: when it last sent a request, or connected (monotonic s)
    active_s: float = field(default_factory=time.monotonic)
    #: the task that reads its requests (cancelled to close it)
    task: asyncio.Task[None] | None = None

    def offer(self, line: bytes) -> bool:
        """Queue ``line`` if there is room; otherwise drop it and count. Never blocks."""
        try:
            self.queue.put_nowait(line)
            return True
        except asyncio.QueueFull:
            self.dropped_lines += 1
            return False


class ApiServer:
    """The JSON-lines server over a Unix socket.

    Parameters
    ----------
    socket_path : path
        Where to listen; a stale socket file left by a dead daemon is replaced, a live one is an error.
    handlers : dict
        Method name -> ``async def handler(params: dict) -> result``; raising :class:`ApiError` answers
        with its code. ``subscribe`` is handled here.
    mode : int
        File mode of the socket (0o660: the owner and the group may drive the phantom).
    max_clients : int, optional
        Connections served at once; default: the process's file limit less :data:`RESERVED_FILES`. A connection
        beyond it closes the longest idle one (told why in an error line), so that the client that needs the
        daemon (to vent) is answered and the port can be reopened: at the file limit itself, accepting fails
        and asyncio stops listening for a second at a time.
    partial_line_timeout_s, silent_timeout_s : float
        A client whose request line has not ended this long after it began, or that has sent no request this long
        after it connected, is told why and closed (:data:`PARTIAL_LINE_TIMEOUT_S`, :data:`SILENT_TIMEOUT_S`).
    """

    def __init__(self, socket_path: str | Path, handlers: dict[str, Handler], mode: int = 0o660,
                 queue_lines: int = CLIENT_QUEUE_LINES, max_clients: int | None = None,
                 partial_line_timeout_s: float = PARTIAL_LINE_TIMEOUT_S, silent_timeout_s: float = SILENT_TIMEOUT_S):
        self.partial_line_timeout_s = partial_line_timeout_s
        self.silent_timeout_s = silent_timeout_s
        self.socket_path = Path(socket_path)
        self.handlers = dict(handlers)
        self.mode = mode
        self.queue_lines = queue_lines
        self.max_clients = max_clients if max_clients is not None else _client_cap()
        self.clients: dict[int, Client] = {}
        self.dropped_lines_total = 0
        self.requests_total = 0
        self.errors_total = 0
        self.clients_shed_total = 0
        self._listener: socket.socket | None = None
        self._accepting: asyncio.Task[None] | None = None
        self._files_short = False
        self._started_this_turn = 0
        self._next_client = 1
        #: the answer to a request that comes before the handlers are installed (what the daemon is doing)
        self.starting: Callable[[], ApiError] = lambda: ApiError(
            "starting", "the daemon is still starting (loading its model): try again in a few seconds")
        self._tasks: set[asyncio.Task[None]] = set()
        self._give_back: asyncio.TimerHandle | None = None

    async def start(self) -> None:
        """Bind and listen; raises PhantomError if another daemon already serves this socket."""
        check_socket_path(self.socket_path)
        try:
            self.socket_path.parent.mkdir(parents=True, exist_ok=True)
            existing = os.lstat(self.socket_path)
        except FileNotFoundError:
            existing = None
        except OSError as error:
            raise PhantomError(f"cannot use the socket path {self.socket_path}: {error.strerror}; pass another "
                               "--socket") from None
        if existing is not None:
            if not stat.S_ISSOCK(existing.st_mode):
                kind = "a folder" if stat.S_ISDIR(existing.st_mode) else "a file that is not a socket"
                raise PhantomError(f"{self.socket_path} is {kind}: the daemon replaces only a stale socket; "
                                   "remove it yourself or pass another --socket")
            if await _socket_is_live(self.socket_path):
                raise PhantomError(f"a daemon already listens on {self.socket_path}: stop it, or pass another "
                                   "--socket")
            self.socket_path.unlink()  # a stale socket left by a daemon that died
        listener = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        try:
            listener.bind(str(self.socket_path))
            listener.listen(LISTEN_BACKLOG)
        except OSError as error:
            listener.close()
            raise PhantomError(f"cannot listen on {self.socket_path}: {error.strerror}; pass another "
                               "--socket") from None
        listener.setblocking(False)
        os.chmod(self.socket_path, self.mode)
        self._listener = listener
        self._accepting = asyncio.create_task(self._accept(listener), name="API accept")

    async def close(self) -> None:
        """Stop listening, drop every client and remove the socket file."""
        if self._give_back is not None:
            self._give_back.cancel()
        if self._accepting is not None:
            self._accepting.cancel()
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await self._accepting
        await _cancelled(set(self._tasks))
        if self._listener is None:
            return  # never listened: the path, if any, is another daemon's
        self._listener.close()
        with contextlib.suppress(FileNotFoundError):
            self.socket_path.unlink()
        self._listener = None

    async def _accept(self, listener: socket.socket) -> None:
        """Accept connections one at a time, each only once there is room for it (the longest idle client is
        closed to make it); a file limit reached anyway (by other files) is logged once and waited out."""
        loop = asyncio.get_running_loop()
        while True:
            while self.clients and len(self.clients) >= self.max_clients:
                await self._shed_longest_idle()
            try:
                connection, _ = await loop.sock_accept(listener)
            except OSError as error:
                if error.errno not in (errno.EMFILE, errno.ENFILE, errno.ENOBUFS, errno.ENOMEM):
                    raise
                if not self._files_short:
                    logger.warning("API connections: no file descriptor left to accept one (%s), with %d "
                                   "clients: waiting for files to be freed", error.strerror, len(self.clients))
                self._files_short = True
                await asyncio.sleep(0.1)
                continue
            reader, writer = await asyncio.open_unix_connection(sock=connection, limit=MAX_REQUEST_BYTES)
            task = asyncio.create_task(self._serve_client(reader, writer))
            self._tasks.add(task)
            task.add_done_callback(self._tasks.discard)

    def publish(self, topic: str, data: dict[str, Any]) -> None:
        """Offer an event to every client subscribed to ``topic``; never blocks, drops where full."""
        if topic not in TOPICS:
            raise ValueError(f"unknown topic {topic!r}")
        subscribers = [client for client in self.clients.values() if topic in client.topics]
        if not subscribers:
            return
        line = _encode({"event": topic, "data": data})
        for client in subscribers:
            if not client.offer(line):
                self.dropped_lines_total += 1

    def stats(self) -> dict[str, Any]:
        """Counters for ``status``: clients, requests, errors, lines dropped for slow clients."""
        return {"clients": len(self.clients), "max_clients": self.max_clients,
                "clients_shed": self.clients_shed_total, "requests": self.requests_total, "errors": self.errors_total,
                "dropped_lines": self.dropped_lines_total}

    async def _shed_longest_idle(self) -> None:
        """Close the client idle the longest, with an error line saying why; the first time, log a warning."""
        idle = min(self.clients.values(), key=lambda client: client.active_s)
        if self.clients_shed_total == 0:
            logger.warning("%d API connections, the most served at once (the file limit less %d): the longest "
                           "idle is closed for each new one from now on (counted in status api.clients_shed)",
                           self.max_clients, RESERVED_FILES)
        self.clients_shed_total += 1
        idle.offer(_error_line(None, "busy", f"the daemon serves at most {self.max_clients} connections: this one, "
                               "the longest idle, was closed for a new one; reconnect when needed"))
        self.clients.pop(idle.number, None)
        if idle.task is not None:
            await _cancelled({idle.task})

    async def _serve_client(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        """Read requests from one client until it goes; answers go through its queue and writer task."""
        this_task = asyncio.current_task()
        assert this_task is not None  # a client is served in a task of its own
        client = self.connect(this_task)
        writer_task = asyncio.create_task(self._drain_client(client, writer))
        self._tasks.add(writer_task)
        self._tasks.add(this_task)
        asked = held_long_line = False
        try:
            while True:
                try:
                    line = await self._read_line(reader, None if asked else self.silent_timeout_s)
                except (ValueError, asyncio.LimitOverrunError):
                    client.offer(_error_line(None, "invalid_request",
                                             f"request longer than {MAX_REQUEST_BYTES} bytes: connection closed"))
                    held_long_line = True
                    break
                except TimeoutError as why:
                    client.offer(_error_line(None, "invalid_request", f"{why}: connection closed"))
                    held_long_line = isinstance(why, PartialLineTimeout)
                    break
                except (ConnectionError, asyncio.CancelledError):
                    # closing the server cancels this task; ending normally keeps asyncio's stream callback quiet
                    break
                if not line:
                    break
                if not line.strip():
                    continue
                asked = True
                client.active_s = time.monotonic()
                try:
                    reply = await self._answer(line, client)
                except Exception as error:  # a bug here must not end the connection; it is reported and logged
                    logger.exception("API request from client %d failed", client.number)
                    self.errors_total += 1
                    reply = _error_line(None, "internal", f"{type(error).__name__}: {error}")
                if reply is not None and not client.offer(reply):
                    self.dropped_lines_total += 1
        finally:
            self.disconnect(client)
            with contextlib.suppress(asyncio.TimeoutError, asyncio.CancelledError, Exception):
                await asyncio.wait_for(asyncio.shield(writer_task), 0.5)
            writer_task.cancel()
            writer.close()
            self._tasks.discard(writer_task)
            self._tasks.discard(this_task)
            if held_long_line and self._give_back is None:
                self._give_back = asyncio.get_running_loop().call_later(GIVE_BACK_DELAY_S, self._given_back)

    def _given_back(self) -> None:
        """The heap's free pages back to the system, once after a burst of clients that held long lines closed."""
        from phantom.model.fem.heap import give_back

        self._give_back = None
        give_back()

    async def _read_line(self, reader: asyncio.StreamReader, silent_timeout_s: float | None) -> bytes:
        """The next line (b"" at the end of the stream): its first byte waited for at most ``silent_timeout_s``
        (None: for ever), the rest for at most the partial-line timeout. TimeoutError saying which was exceeded;
        ValueError for a line over the limit."""
        try:
            first = await asyncio.wait_for(reader.readexactly(1), silent_timeout_s)
        except asyncio.IncompleteReadError:
            return b""
        except TimeoutError:
            raise TimeoutError(f"the connection sent no request within {silent_timeout_s:g} s") from None
        if first == b"\n":
            return first
        try:
            rest = await asyncio.wait_for(reader.readline(), self.partial_line_timeout_s)
        except TimeoutError:
            raise PartialLineTimeout(f"a request line did not end within {self.partial_line_timeout_s:g} s") from None
        return first + rest

    async def _drain_client(self, client: Client, writer: asyncio.StreamWriter) -> None:
        """Write the client's queued lines; a stuck client blocks only this task."""
        try:
            while True:
                line = await client.queue.get()
                if line is None:
                    return
                writer.write(line)
                await writer.drain()
        except (ConnectionError, asyncio.CancelledError):
            return

    async def _answer(self, line: bytes, client: Client) -> bytes | None:
        """The reply line to one request line."""
        self.requests_total += 1
        try:
            request = json.loads(line.decode("utf-8"), object_pairs_hook=unique_keys)
        except UnicodeDecodeError as error:
            self.errors_total += 1
            return _error_line(None, "parse_error", f"the request is not UTF-8 (byte {error.start}: "
                               f"{error.reason}): send one JSON object per line, in UTF-8")
        except (ValueError, RecursionError) as error:
            # JSONDecodeError, an integer of too many digits (ValueError), nesting deeper than the parser's stack
            self.errors_total += 1
            reason = error.msg if isinstance(error, json.JSONDecodeError) else (
                "nested too deeply" if isinstance(error, RecursionError) else str(error).split(";")[0][:200])
            return _error_line(None, "parse_error", f"the request is not valid JSON ({reason}): send one JSON "
                               "object per line")
        if not isinstance(request, dict):
            self.errors_total += 1
            return _error_line(None, "parse_error", 'the request must be a JSON object {"id", "method", "params"}')
        request_id = request.get("id")
        if not (request_id is None or isinstance(request_id, (str, int, float))) or isinstance(request_id, bool):
            self.errors_total += 1
            return _error_line(None, "invalid_request", "\"id\" must be a string, a number or null")
        method = request.get("method")
        params = request.get("params", {})
        if not isinstance(method, str):
            self.errors_total += 1
            return _error_line(request_id, "invalid_request", "the request needs a string \"method\"")
        if params is None:
            params = {}
        if not isinstance(params, dict):
            self.errors_total += 1
            return _error_line(request_id, "invalid_request", "\"params\" must be a JSON object")
        try:
            result = await self.call(client, method, params)
        except ApiError as error:
            return _error_line(request_id, error.code, str(error), error.data)
        if isinstance(result, RawJson):
            return f'{{"id":{json.dumps(request_id)},"result":{result}}}\n'.encode()
        return _encode({"id": request_id, "result": result})

    async def call(self, client: Client, method: str, params: dict[str, Any]) -> object:
        """Run one request of ``client`` (paced; ``subscribe`` handled here): the method's result, or ApiError
        (a PhantomError answers ``invalid_params``, a handler's bug ``internal``, logged). The one dispatch of
        every transport: the Unix socket's lines and the WebSocket's JSON-RPC (host/web.py)."""
        await self._pace()
        try:
            if method == "subscribe":
                return self._subscribe(client, params)
            if method in self.handlers:
                return await self.handlers[method](params)
            if not self.handlers:
                raise self.starting()
            known = ", ".join(sorted([*self.handlers, "subscribe"]))
            raise ApiError("unknown_method", f"unknown method {method!r}; methods: {known}")
        except ApiError:
            self.errors_total += 1
            raise
        except PhantomError as error:
            self.errors_total += 1
            raise ApiError("invalid_params", str(error)) from None
        except Exception as error:  # a handler bug must not take the daemon down; the client learns of it
            logger.exception("API method %s failed", method)
            self.errors_total += 1
            raise ApiError("internal", f"{type(error).__name__}: {error}") from error

    def connect(self, task: asyncio.Task[Any]) -> Client:
        """A new client served by ``task`` (cancelled to close it), counted among the clients until
        :meth:`disconnect`: it receives what it subscribes to in its queue."""
        client = Client(self._next_client, asyncio.Queue(maxsize=self.queue_lines), task=task)
        self._next_client += 1
        self.clients[client.number] = client
        return client

    def disconnect(self, client: Client) -> None:
        """The client is gone: nothing more is queued for it, and its writer is told to end."""
        self.clients.pop(client.number, None)
        with contextlib.suppress(asyncio.QueueFull):
            client.queue.put_nowait(None)

    async def _pace(self) -> None:
        """Wait for a turn of the event loop in which fewer than :data:`REQUESTS_PER_TURN` requests started."""
        while self._started_this_turn >= REQUESTS_PER_TURN:
            await asyncio.sleep(0)
        if self._started_this_turn == 0:
            asyncio.get_running_loop().call_soon(self._new_turn)
        self._started_this_turn += 1

    def _new_turn(self) -> None:
        self._started_this_turn = 0

    def _subscribe(self, client: Client, params: dict[str, Any]) -> dict[str, Any]:
        """Add topics to a client's subscriptions (default: all)."""
        topics = params.get("topics", list(TOPICS))
        if not isinstance(topics, list) or not all(isinstance(topic, str) for topic in topics):
            raise ApiError("invalid_params", f"topics must be a list of strings out of {', '.join(TOPICS)}")
        unknown = sorted(set(topics) - set(TOPICS))
        if unknown:
            raise ApiError("invalid_params", f"unknown topic(s) {', '.join(unknown)}; topics: {', '.join(TOPICS)}")
        client.topics.update(topics)
        return {"topics": sorted(client.topics)}


def _client_cap() -> int:
    """The most API connections at once: the process's file limit less :data:`RESERVED_FILES` (at least 16)."""
    soft, _ = resource.getrlimit(resource.RLIMIT_NOFILE)
    if soft == resource.RLIM_INFINITY:
        soft = 2**16
    return max(16, soft - RESERVED_FILES)


def _encode(message: dict[str, Any]) -> bytes:
    """One JSON line; NaN (no value yet) is written as null. The C encoder alone does the common case, a message
    without NaN (the Python walk that replaces NaN took three times as long)."""
    try:
        text = json.dumps(message, separators=(",", ":"), allow_nan=False)
    except ValueError:
        text = json.dumps(_finite(message), separators=(",", ":"))
    return (text + "\n").encode()


def _finite(value: Any) -> Any:
    """``value`` with every non-finite float replaced by None (JSON has no NaN)."""
    if isinstance(value, float):
        return value if value == value and value not in (float("inf"), float("-inf")) else None
    if isinstance(value, dict):
        return {key: _finite(item) for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return [_finite(item) for item in value]
    return value


def _error_line(request_id: object, code: str, message: str, data: dict[str, Any] | None = None) -> bytes:
    error: dict[str, Any] = {"code": code, "message": message}
    if data is not None:
        error["data"] = data
    return _encode({"id": request_id, "error": error})


async def _socket_is_live(path: Path) -> bool:
    """Whether something accepts connections on the Unix socket at ``path``."""
    try:
        _, writer = await asyncio.wait_for(asyncio.open_unix_connection(str(path)), 1.0)
    except (TimeoutError, OSError):
        return False
    writer.close()
    return True


async def _cancelled(tasks: set[asyncio.Task[None]]) -> None:
    """Cancel ``tasks`` and wait until each has ended, cancelling again those that go on. On Python 3.11 a
    cancellation that meets the end of an ``asyncio.wait_for`` in one turn is lost (wait_for returns the read's
    result): a client's task then went on to wait for the next line, and closing the server waited for it until
    the client left."""
    pending = {task for task in tasks if not task.done()}
    while pending:
        for task in pending:
            task.cancel()
        _, pending = await asyncio.wait(pending, timeout=CANCEL_AGAIN_S)
    for task in tasks:
        if task.done() and not task.cancelled():
            task.exception()  # retrieved: a task that failed was logged where it failed


def check_socket_path(path: Path) -> None:
    """Refuse (PhantomError) a path too long to be a Unix socket's, before the daemon binds or a client connects:
    the socket module says only ``AF_UNIX path too long``, without an errno."""
    length = len(os.fsencode(path))
    if length > MAX_SOCKET_PATH_BYTES:
        raise PhantomError(f"the socket path {path} is {length} bytes long: a Unix socket's path may be at most "
                           f"{MAX_SOCKET_PATH_BYTES} bytes (on Linux); pass a shorter socket path")


def default_socket_path() -> Path:
    """The socket the daemon listens on and clients call by default.

    ``$PHANTOM_SOCKET`` if set; else ``/run/phantom/phantomd.sock`` when that folder exists (the systemd
    service's RuntimeDirectory); else ``$XDG_RUNTIME_DIR/phantomd.sock``; else ``/tmp/phantomd-<uid>/phantomd.sock``
    in a folder only this user may write (a socket straight in /tmp could be squatted by another user's fake
    daemon: sudo and cron have no ``$XDG_RUNTIME_DIR``).
    """
    if os.environ.get("PHANTOM_SOCKET"):
        return Path(os.environ["PHANTOM_SOCKET"])
    if Path("/run/phantom").is_dir():
        return Path("/run/phantom/phantomd.sock")
    if os.environ.get("XDG_RUNTIME_DIR"):
        return Path(os.environ["XDG_RUNTIME_DIR"]) / "phantomd.sock"
    return private_folder(Path(f"/tmp/phantomd-{os.getuid()}")) / "phantomd.sock"
