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
import json
import logging
import os
import stat
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from phantom import PhantomError

logger = logging.getLogger(__name__)

#: Error codes a request can get back, with what they mean.
ERROR_CODES: dict[str, str] = {
    "parse_error": "the line is not a JSON object",
    "invalid_request": "the object lacks a string method, or params is not an object",
    "unknown_method": "no such method",
    "invalid_params": "the params are missing, of the wrong type or out of range",
    "unreachable": "the target cannot be reached within the pressure limits",
    "link_down": "no board is connected",
    "starting": "the daemon is still starting (loading its model): try again in a few seconds",
    "rejected": "the board refused the command (e.g. a fault is latched and its cause persists)",
    "internal": "a bug in the daemon: please report it",
}

#: Subscription topics.
TOPICS: tuple[str, ...] = ("telemetry", "status", "events")

#: Outgoing lines a client may have waiting before further ones are dropped.
CLIENT_QUEUE_LINES = 256

#: Longest request line accepted (bytes).
MAX_REQUEST_BYTES = 64 * 1024


class ApiError(PhantomError):
    """An error answered to one request, with one of :data:`ERROR_CODES`."""

    def __init__(self, code: str, message: str):
        if code not in ERROR_CODES:
            raise ValueError(f"unknown API error code {code!r}")
        super().__init__(message)
        self.code = code


Handler = Callable[[dict[str, Any]], Awaitable[object]]


@dataclass
class Client:
    """One connected client: its outgoing queue, subscriptions and counters."""

    number: int
    queue: asyncio.Queue[bytes | None]
    topics: set[str] = field(default_factory=set)
    dropped_lines: int = 0

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
    """

    def __init__(self, socket_path: str | Path, handlers: dict[str, Handler], mode: int = 0o660,
                 queue_lines: int = CLIENT_QUEUE_LINES):
        self.socket_path = Path(socket_path)
        self.handlers = dict(handlers)
        self.mode = mode
        self.queue_lines = queue_lines
        self.clients: dict[int, Client] = {}
        self.dropped_lines_total = 0
        self.requests_total = 0
        self.errors_total = 0
        self._server: asyncio.AbstractServer | None = None
        self._next_client = 1
        self._tasks: set[asyncio.Task[None]] = set()

    async def start(self) -> None:
        """Bind and listen; raises PhantomError if another daemon already serves this socket."""
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
        try:
            self._server = await asyncio.start_unix_server(self._serve_client, path=str(self.socket_path),
                                                           limit=MAX_REQUEST_BYTES)
        except OSError as error:
            raise PhantomError(f"cannot listen on {self.socket_path}: {error.strerror}; pass another "
                               "--socket") from None
        os.chmod(self.socket_path, self.mode)

    async def close(self) -> None:
        """Stop listening, drop every client and remove the socket file."""
        if self._server is not None:
            self._server.close()
        for task in list(self._tasks):
            task.cancel()
        for task in list(self._tasks):
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await task
        if self._server is None:
            return  # never listened: the path, if any, is another daemon's
        with contextlib.suppress(Exception):
            await asyncio.wait_for(self._server.wait_closed(), 1.0)
        with contextlib.suppress(FileNotFoundError):
            self.socket_path.unlink()
        self._server = None

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
        return {"clients": len(self.clients), "requests": self.requests_total, "errors": self.errors_total,
                "dropped_lines": self.dropped_lines_total}

    async def _serve_client(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        """Read requests from one client until it goes; answers go through its queue and writer task."""
        client = Client(self._next_client, asyncio.Queue(maxsize=self.queue_lines))
        self._next_client += 1
        self.clients[client.number] = client
        writer_task = asyncio.create_task(self._drain_client(client, writer))
        self._tasks.add(writer_task)
        this_task = asyncio.current_task()
        assert this_task is not None  # a client is served in a task of its own
        self._tasks.add(this_task)
        try:
            while True:
                try:
                    line = await reader.readline()
                except (ValueError, asyncio.LimitOverrunError):
                    client.offer(_error_line(None, "invalid_request",
                                             f"request longer than {MAX_REQUEST_BYTES} bytes: connection closed"))
                    break
                except (ConnectionError, asyncio.CancelledError):
                    # closing the server cancels this task; ending normally keeps asyncio's stream callback quiet
                    break
                if not line:
                    break
                if not line.strip():
                    continue
                try:
                    reply = await self._answer(line, client)
                except Exception as error:  # a bug here must not end the connection; it is reported and logged
                    logger.exception("API request from client %d failed", client.number)
                    self.errors_total += 1
                    reply = _error_line(None, "internal", f"{type(error).__name__}: {error}")
                if reply is not None and not client.offer(reply):
                    self.dropped_lines_total += 1
        finally:
            self.clients.pop(client.number, None)
            with contextlib.suppress(asyncio.QueueFull):
                client.queue.put_nowait(None)
            with contextlib.suppress(asyncio.TimeoutError, asyncio.CancelledError, Exception):
                await asyncio.wait_for(asyncio.shield(writer_task), 0.5)
            writer_task.cancel()
            writer.close()
            self._tasks.discard(writer_task)
            self._tasks.discard(this_task)

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
            request = json.loads(line.decode("utf-8"))
        except UnicodeDecodeError as error:
            self.errors_total += 1
            return _error_line(None, "parse_error", f"the request is not UTF-8 (byte {error.start}: "
                               f"{error.reason}): send one JSON object per line, in UTF-8")
        except (ValueError, RecursionError) as error:
            # JSONDecodeError, an integer of too many digits (ValueError), nesting deeper than the parser's stack
            self.errors_total += 1
            reason = error.msg if isinstance(error, json.JSONDecodeError) else (
                "nested too deeply" if isinstance(error, RecursionError) else str(error).split(";")[0])
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
        result: object
        try:
            if method == "subscribe":
                result = self._subscribe(client, params)
            elif method in self.handlers:
                result = await self.handlers[method](params)
            elif not self.handlers:
                raise ApiError("starting", "the daemon is still starting (loading its model): try again in a few "
                               "seconds")
            else:
                known = ", ".join(sorted([*self.handlers, "subscribe"]))
                raise ApiError("unknown_method", f"unknown method {method!r}; methods: {known}")
        except ApiError as error:
            self.errors_total += 1
            return _error_line(request_id, error.code, str(error))
        except PhantomError as error:
            self.errors_total += 1
            return _error_line(request_id, "invalid_params", str(error))
        except Exception as error:  # a handler bug must not take the daemon down; the client learns of it
            logger.exception("API method %s failed", method)
            self.errors_total += 1
            return _error_line(request_id, "internal", f"{type(error).__name__}: {error}")
        return _encode({"id": request_id, "result": result})

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


def _encode(message: dict[str, Any]) -> bytes:
    """One JSON line; NaN (no value yet) is written as null."""
    return (json.dumps(_finite(message), separators=(",", ":")) + "\n").encode()


def _finite(value: Any) -> Any:
    """``value`` with every non-finite float replaced by None (JSON has no NaN)."""
    if isinstance(value, float):
        return value if value == value and value not in (float("inf"), float("-inf")) else None
    if isinstance(value, dict):
        return {key: _finite(item) for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return [_finite(item) for item in value]
    return value


def _error_line(request_id: object, code: str, message: str) -> bytes:
    return _encode({"id": request_id, "error": {"code": code, "message": message}})


async def _socket_is_live(path: Path) -> bool:
    """Whether something accepts connections on the Unix socket at ``path``."""
    try:
        _, writer = await asyncio.wait_for(asyncio.open_unix_connection(str(path)), 1.0)
    except (TimeoutError, OSError):
        return False
    writer.close()
    return True


def default_socket_path() -> Path:
    """The socket the daemon listens on and clients call by default.

    ``$PHANTOM_SOCKET`` if set; else ``/run/phantom/phantomd.sock`` when that folder exists (the systemd
    service's RuntimeDirectory); else ``$XDG_RUNTIME_DIR/phantomd.sock``; else ``/tmp/phantomd-<uid>.sock``.
    """
    if os.environ.get("PHANTOM_SOCKET"):
        return Path(os.environ["PHANTOM_SOCKET"])
    if Path("/run/phantom").is_dir():
        return Path("/run/phantom/phantomd.sock")
    if os.environ.get("XDG_RUNTIME_DIR"):
        return Path(os.environ["XDG_RUNTIME_DIR"]) / "phantomd.sock"
    return Path(f"/tmp/phantomd-{os.getuid()}.sock")
