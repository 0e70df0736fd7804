"""The daemon's API over a WebSocket, and the browser panel's page (``phantom daemon --http 127.0.0.1:8080``).

The WebSocket at ``/websocket`` speaks JSON-RPC 2.0 as Moonraker (Klipper's API server) frames it: a request
``{"jsonrpc": "2.0", "method": "set_target", "params": {...}, "id": 7}`` gets ``{"jsonrpc": "2.0", "result": ...,
"id": 7}`` or ``{"jsonrpc": "2.0", "error": {"code": -32602, "message": "...", "data": {"error":
"invalid_params"}}, "id": 7}``; the events a connection subscribes to come as notifications ``{"jsonrpc": "2.0",
"method": "notify_telemetry", "params": [{...}]}``. The methods are the Unix socket's, through the same dispatch
(:meth:`phantom.host.api.ApiServer.call`): this module only frames them, and adds ``identify`` (what this
connection may do).

It is safe from other web pages and other users:

* every request's ``Host`` must be an IP address, ``localhost`` or a name given in ``--http-hosts``: a page of
  another site whose name was rebound to this address (DNS rebinding) is refused;
* the WebSocket's ``Origin``, when a browser sends one, must be this page's own (``http://`` + ``Host``): another
  page open in the same browser cannot drive the phantom;
* every connection presents a token (:class:`PanelTokens`: a control and a read-only one, kept in the user's data
  directory with mode 0600): opening ``/?token=...``, or once the ``/?code=...`` printed at start, keeps it in an
  HttpOnly cookie and takes it out of the address bar; scripts send ``Authorization: Bearer ...``. A read-only
  token watches (status, the surface, subscriptions) and is answered ``forbidden`` for everything else;
* ``--no-http-token`` is refused unless the address is loopback; tokens never reach the log (no access log: the
  first address carries the token).
"""

from __future__ import annotations

import asyncio
import contextlib
import hmac
import ipaddress
import json
import logging
import math
import os
import secrets
import stat
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TextIO

from phantom import PhantomError, read_text, require_extra, written_atomically
from phantom.host.api import ERROR_CODES, MAX_REQUEST_BYTES, ApiError, ApiServer, Client, RawJson, _encode
from phantom.model.measurements import data_dir

logger = logging.getLogger(__name__)

#: The page's files (index.html, its modules, the vendored libraries).
PANEL_FILES = Path(__file__).resolve().parent / "panel"

#: Methods a read-only token may call: they show, they do not act.
READ_METHODS = frozenset({"status", "surface", "subscribe", "presets", "motion_status", "identify"})

#: JSON-RPC error codes of the API's errors (the JSON-RPC spec's where it has one, else server errors
#: -32001...); ``data.error`` keeps the API's own name.
JSONRPC_CODES: dict[str, int] = {"parse_error": -32700, "invalid_request": -32600, "unknown_method": -32601,
                                 "invalid_params": -32602, "internal": -32603}
for _number, _name in enumerate(name for name in ERROR_CODES if name not in JSONRPC_CODES):
    JSONRPC_CODES[_name] = -32001 - _number

#: Requests one connection may have in progress at once (each runs in its own task: a vent is answered while a
#: set_target waits for its solve); beyond it the connection is answered ``busy``.
REQUESTS_IN_FLIGHT = 16

#: How long closing waits for each WebSocket's goodbye, and for the requests in progress (s).
CLOSE_WAIT_S = 2.0

#: The tokens' file in the user's data directory.
TOKENS_FILE = "panel-tokens.json"

#: Names that always mean this machine (an SSH tunnel's end): allowed as Host whatever the bound address.
LOOPBACK_NAMES = frozenset({"localhost", "localhost.localdomain"})

#: Headers on every answer: the page must not be framed by another (a click on its buttons would come from a
#: page the user did not mean to use), and loads nothing but its own files.
SECURITY_HEADERS = {
    "Content-Security-Policy": "default-src 'self'; img-src 'self' data:; connect-src 'self'; "
                               "frame-ancestors 'none'; base-uri 'none'; form-action 'self'",
    "X-Frame-Options": "DENY", "X-Content-Type-Options": "nosniff", "Referrer-Policy": "no-referrer",
    "Cache-Control": "no-store",
}


class WebError(PhantomError):
    """The panel cannot be served as configured (a bad address, a public one without a token, the port taken,
    the tokens' file unsafe)."""


@dataclass(frozen=True)
class PanelTokens:
    """The panel's two tokens: ``control`` drives the phantom, ``read`` only watches."""

    control: str
    read: str
    path: Path

    def access(self, presented: str | None) -> str | None:
        """``"control"``, ``"read"`` or None (no token, or a wrong one), compared in constant time."""
        if not presented:
            return None
        given = presented.encode()
        if hmac.compare_digest(given, self.control.encode()):
            return "control"
        if hmac.compare_digest(given, self.read.encode()):
            return "read"
        return None


def panel_tokens(path: Path | None = None) -> PanelTokens:
    """The panel's tokens from ``path`` (default: ``panel-tokens.json`` in the user's data directory), made on
    first use (random, 256 bits each) with mode 0600. A file that others may read is refused: its tokens are no
    longer secret."""
    path = path if path is not None else data_dir() / TOKENS_FILE
    if path.exists():
        mode = stat.S_IMODE(path.stat().st_mode)
        if mode & 0o077:
            raise WebError(f"the panel's tokens in {path} may be read by others (mode {mode:04o}): remove the file "
                           "(new tokens are made) or `chmod 600` it")
        try:
            stored = json.loads(read_text(path, 4096, "the panel's tokens", WebError))
            return PanelTokens(str(stored["control"]), str(stored["read"]), path)
        except (ValueError, KeyError, TypeError):
            raise WebError(f"the panel's tokens in {path} are damaged: remove the file (new tokens are made)") from None
    path.parent.mkdir(parents=True, exist_ok=True)
    tokens = PanelTokens(secrets.token_urlsafe(32), secrets.token_urlsafe(32), path)
    with written_atomically(path, WebError) as temporary:
        os.chmod(temporary, 0o600)
        temporary.write_text(json.dumps({"control": tokens.control, "read": tokens.read}, indent=1) + "\n")
    os.chmod(path, 0o600)
    return tokens


def parse_address(text: str) -> tuple[str, int]:
    """``HOST:PORT`` (``127.0.0.1:8080``, ``[::1]:8080``, ``0.0.0.0:8080``, ``localhost:8080``) or a port alone
    (``8080``: loopback, this machine only) as (host, port); port 0: one the system picks, which the status and the
    printed address say. WebError for anything else."""
    host, colon, port_text = text.rpartition(":") if ":" in text else ("127.0.0.1", ":", text)
    host = host[1:-1] if host.startswith("[") and host.endswith("]") else host
    if not colon or not host or not port_text.isdigit() or not 0 <= int(port_text) < 65536:
        raise WebError(f"--http {text!r}: give HOST:PORT, e.g. 127.0.0.1:8080 (this machine only) or "
                       "0.0.0.0:8080 (every address, with the token)")
    return host, int(port_text)


def is_loopback(host: str) -> bool:
    """Whether ``host`` (an address or a name) is this machine only."""
    if host in LOOPBACK_NAMES:
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def split_host(host_header: str) -> tuple[str, str]:
    """A Host header's name (brackets of an IPv6 address taken off) and port ("" without one)."""
    if host_header.startswith("["):
        name, _, rest = host_header[1:].partition("]")
        return name, rest[1:] if rest.startswith(":") else ""
    name, _, port = host_header.partition(":")
    return name, port


def host_allowed(host_header: str | None, names: frozenset[str]) -> bool:
    """Whether a request's Host is this daemon's: an IP address (a rebound name is not one), a loopback name or
    one of ``names`` (``--http-hosts``)."""
    if not host_header:
        return False
    name = split_host(host_header)[0].lower().rstrip(".")
    if name in LOOPBACK_NAMES or name in names:
        return True
    try:
        ipaddress.ip_address(name)
    except ValueError:
        return False
    return True


def origin_allowed(origin: str | None, host_header: str | None) -> bool:
    """Whether a WebSocket's Origin is the page's own: none (not a browser: the token still counts), or
    ``http(s)://`` followed by exactly the Host it connects to."""
    if origin is None:
        return True
    if not host_header:
        return False
    return origin.lower() in (f"http://{host_header.lower()}", f"https://{host_header.lower()}")


def _aiohttp() -> Any:
    """aiohttp's server (the ``panel`` extra), imported when the panel is served."""
    with require_extra("panel"):
        import aiohttp.web
    return aiohttp.web


def jsonrpc_error(request_id: object, code: str, message: str, data: dict[str, Any] | None = None) -> str:
    """A JSON-RPC error answer for one of the API's error codes."""
    return json.dumps({"jsonrpc": "2.0", "id": request_id, "error": {
        "code": JSONRPC_CODES[code], "message": message, "data": {"error": code, **(data or {})}}})


def jsonrpc_frame(line: bytes) -> str:
    """What the API queued for a client (an event line, or an error line it sent unasked) as JSON-RPC: events
    become ``notify_<topic>`` notifications (the data is not parsed again: the API wrote the line), answers
    framed here pass as they are."""
    if line.startswith(b'{"jsonrpc"'):
        return line.decode()
    if line.startswith(b'{"event":"'):
        topic, separator, data = line[10:].partition(b'","data":')
        if separator and data.endswith(b"}\n"):
            return f'{{"jsonrpc":"2.0","method":"notify_{topic.decode()}","params":[{data[:-2].decode()}]}}'
    message = json.loads(line)
    if "event" in message:
        return json.dumps({"jsonrpc": "2.0", "method": f"notify_{message['event']}", "params": [message["data"]]})
    error = message.get("error") or {}
    return jsonrpc_error(message.get("id"), error.get("code", "internal"), error.get("message", ""),
                         error.get("data"))


class WebServer:
    """The panel's HTTP server: the page's files and the API's WebSocket (aiohttp, on the daemon's loop).

    Parameters
    ----------
    api : ApiServer
        The daemon's API: its dispatch answers every request, its clients' queues carry the events.
    address : str
        ``HOST:PORT`` to listen on (``--http``).
    tokens : PanelTokens or None
        The tokens every connection must present; None (``--no-http-token``) only on a loopback address.
    host_names : iterable of str
        Names the page may be reached by besides IP addresses and localhost (``--http-hosts``).
    """

    def __init__(self, api: ApiServer, address: str, tokens: PanelTokens | None, host_names: tuple[str, ...] = ()):
        self.api = api
        self.host, self.port = parse_address(address)
        if tokens is None and not is_loopback(self.host):
            raise WebError(f"--http {address} is reachable from other machines: it needs the token (drop "
                           "--no-http-token), or bind 127.0.0.1 and reach it through an SSH tunnel")
        self.tokens = tokens
        self.host_names = frozenset(name.strip().lower().rstrip(".") for name in host_names if name.strip())
        self.cookie = f"phantom_panel_{self.port}"
        self.refused: dict[str, int] = {"host": 0, "origin": 0, "token": 0, "forbidden": 0}
        #: what the address printed at start carries instead of the token (Jupyter's way): it opens the panel with
        #: the control token once, and is spent (a terminal's scrollback or a shell's history holds nothing usable)
        self.one_time_code: str | None = secrets.token_urlsafe(16) if tokens is not None else None
        self._runner: Any = None
        self._sockets: set[Any] = set()

    async def start(self) -> None:
        """Listen; WebError if the address cannot be bound (the port taken, an address not this machine's)."""
        web = _aiohttp()
        app = web.Application(middlewares=[self._checked], client_max_size=MAX_REQUEST_BYTES)
        app.router.add_get("/", self._index)
        app.router.add_get("/access", self._access_answer)
        app.router.add_get("/websocket", self._websocket)
        app.router.add_static("/static/", PANEL_FILES, follow_symlinks=False)
        # no access log: the first request's address carries the token
        runner = web.AppRunner(app, access_log=None, handle_signals=False, shutdown_timeout=CLOSE_WAIT_S)
        await runner.setup()
        site = web.TCPSite(runner, self.host, self.port, reuse_address=True)
        try:
            await site.start()
        except OSError as error:
            await runner.cleanup()
            raise WebError(f"cannot serve the panel on {self.host}:{self.port}: {error.strerror or error}; pass "
                           "another --http HOST:PORT") from None
        self._runner = runner
        if self.port == 0:  # the port the system chose (tests)
            server = getattr(site, "_server", None)
            if server is not None and server.sockets:
                self.port = server.sockets[0].getsockname()[1]

    async def close(self) -> None:
        """Close every WebSocket (telling the pages the daemon is going away) and stop listening. aiohttp alone
        would wait up to a minute for the open WebSockets' handlers: a panel left open held the daemon's stop."""
        for socket in list(self._sockets):
            with contextlib.suppress(Exception):
                await asyncio.wait_for(socket.close(code=1001, message=b"the daemon is stopping"), CLOSE_WAIT_S)
        if self._runner is not None:
            await self._runner.cleanup()
            self._runner = None

    def url(self) -> str:
        """The page's address, without its token."""
        host = f"[{self.host}]" if ":" in self.host else self.host
        host = "127.0.0.1" if host in ("0.0.0.0", "[::]") else host
        return f"http://{host}:{self.port}/"

    def status(self) -> dict[str, Any]:
        """For the daemon's status: where the panel is, whether it asks for a token, and what it refused."""
        return {"url": self.url(), "token": self.tokens is not None,
                "tokens_file": str(self.tokens.path) if self.tokens is not None else None,
                "refused": dict(self.refused)}

    # --- checks ------------------------------------------------------------------------------------------

    @property
    def _checked(self) -> Any:
        web = _aiohttp()

        async def checked(request: Any, handler: Any) -> Any:
            if not host_allowed(request.headers.get("Host"), self.host_names):
                self.refused["host"] += 1
                raise web.HTTPForbidden(text=f"Host {request.headers.get('Host', '(none)')!r} is not served here: "
                                        "reach the panel by its IP address or localhost, or add the name to "
                                        "--http-hosts\n")
            response = await handler(request)
            if not response.prepared:
                response.headers.update(SECURITY_HEADERS)
            return response
        return web.middleware(checked)

    def _access(self, request: Any) -> str | None:
        """What the request's token allows: ``"control"``, ``"read"`` or None. The token comes from the cookie
        the page got, an ``Authorization: Bearer`` header or a ``token`` query parameter."""
        if self.tokens is None:
            return "control"
        presented = request.cookies.get(self.cookie)
        authorization = request.headers.get("Authorization", "")
        if authorization.startswith("Bearer "):
            presented = authorization[7:].strip()
        presented = request.query.get("token", presented)
        return self.tokens.access(presented)

    # --- routes ----------------------------------------------------------------------------------------------

    async def _index(self, request: Any) -> Any:
        """The page. ``/?code=...`` (the one-time code the daemon printed at start) or ``/?token=...`` keeps the
        token in a cookie and takes it out of the address bar; the code is spent by its first use."""
        web = _aiohttp()
        token = request.query.get("token")
        if "code" in request.query and self.tokens is not None:
            code, self.one_time_code = self.one_time_code, None
            if code is not None and hmac.compare_digest(request.query["code"].encode(), code.encode()):
                token = self.tokens.control
            else:
                self.one_time_code = code  # a wrong code does not spend the right one
                self.refused["token"] += 1
                raise web.HTTPUnauthorized(text="this address's one-time code was used already (or is not this "
                                           "daemon's): open the panel with a token from its panel-tokens.json\n")
        elif token is not None and (self.tokens is None or self.tokens.access(token) is None):
            self.refused["token"] += 1
            raise web.HTTPUnauthorized(text="this token is not the panel's: open the address the daemon "
                                       "printed, or take a token from its panel-tokens.json\n")
        if token is None:
            return web.FileResponse(PANEL_FILES / "index.html")
        response = web.Response(status=303, headers={"Location": "/"})
        response.set_cookie(self.cookie, token, httponly=True, samesite="Strict", path="/", max_age=30 * 24 * 3600)
        return response

    async def _access_answer(self, request: Any) -> Any:
        """``{"access": "control" | "read" | null}``: what this browser's token allows (the page asks first)."""
        web = _aiohttp()
        return web.json_response({"access": self._access(request), "token_needed": self.tokens is not None})

    async def _websocket(self, request: Any) -> Any:
        web = _aiohttp()
        if not origin_allowed(request.headers.get("Origin"), request.headers.get("Host")):
            self.refused["origin"] += 1
            raise web.HTTPForbidden(text=f"a page from {request.headers.get('Origin')} may not use this panel's "
                                    "API: open the panel's own page\n")
        access = self._access(request)
        if access is None:
            self.refused["token"] += 1
            raise web.HTTPUnauthorized(text="the panel's API needs its token: open the address the daemon printed "
                                       "(?token=...), or send Authorization: Bearer TOKEN\n")
        socket = web.WebSocketResponse(heartbeat=20.0, max_msg_size=MAX_REQUEST_BYTES)
        await socket.prepare(request)
        self._sockets.add(socket)
        this_task = asyncio.current_task()
        assert this_task is not None  # aiohttp serves each request in a task
        client = self.api.connect(this_task)
        writer = asyncio.create_task(self._drain(client, socket))
        requests: set[asyncio.Task[None]] = set()
        try:
            async for message in socket:
                if message.type is not web.WSMsgType.TEXT:
                    if message.type is web.WSMsgType.BINARY:
                        client.offer(jsonrpc_error(None, "invalid_request", "send JSON-RPC as text").encode())
                    continue
                client.active_s = time.monotonic()
                if len(requests) >= REQUESTS_IN_FLIGHT:
                    client.offer(jsonrpc_error(None, "busy", f"{REQUESTS_IN_FLIGHT} requests of this connection "
                                               "are in progress: wait for their answers").encode())
                    continue
                task = asyncio.create_task(self._request(message.data, client, access))
                requests.add(task)
                task.add_done_callback(requests.discard)
        except asyncio.CancelledError:
            pass  # the API closed it (the longest idle of too many connections), or the daemon stops
        finally:
            self.api.disconnect(client)
            for task in list(requests):
                task.cancel()
            with contextlib.suppress(asyncio.TimeoutError, asyncio.CancelledError, Exception):
                await asyncio.wait_for(asyncio.shield(writer), 0.5)
            writer.cancel()
            self._sockets.discard(socket)
            with contextlib.suppress(Exception):
                await socket.close()
        return socket

    async def _drain(self, client: Client, socket: Any) -> None:
        """Send the client's queued answers and events; a slow browser blocks only this task (its queue fills
        and what does not fit is dropped and counted, as for the Unix socket's clients)."""
        with contextlib.suppress(ConnectionError, asyncio.CancelledError, RuntimeError):
            while True:
                line = await client.queue.get()
                if line is None:
                    return
                await socket.send_str(jsonrpc_frame(line))

    async def _request(self, text: str, client: Client, access: str) -> None:
        """Answer one JSON-RPC request through the API's dispatch (a notification, without an id, gets none)."""
        self.api.requests_total += 1
        try:
            request = json.loads(text)
        except (ValueError, RecursionError):
            self.api.errors_total += 1
            client.offer(jsonrpc_error(None, "parse_error", "the message is not valid JSON: send one JSON-RPC "
                                       "request per message").encode())
            return
        request_id = request.get("id") if isinstance(request, dict) else None
        if not _valid_id(request_id):  # refused before anything runs; its id cannot be echoed: answered with null
            self.api.errors_total += 1
            client.offer(jsonrpc_error(None, "invalid_request", "a request's id must be a string, a number or null, "
                                       f"got {_json_kind(request_id)}: give one of those").encode())
            return
        method = request.get("method") if isinstance(request, dict) else None
        params = request.get("params", {}) if isinstance(request, dict) else None
        if (not isinstance(request, dict) or request.get("jsonrpc") != "2.0" or not isinstance(method, str)
                or not isinstance(params, dict | None)):
            self.api.errors_total += 1
            client.offer(jsonrpc_error(request_id, "invalid_request", 'a request is {"jsonrpc": "2.0", "method": '
                                       '"...", "params": {...}, "id": ...} (params an object)').encode())
            return
        try:
            if access != "control" and method not in READ_METHODS:
                self.refused["forbidden"] += 1
                raise ApiError("forbidden", f"{method}: this panel's token is read-only (it shows the phantom, "
                                            "it may not drive it): open the panel with the control token")
            if method == "identify":
                result: object = {"access": access, "methods": sorted(
                    name for name in [*self.api.handlers, "subscribe", "identify"]
                    if access == "control" or name in READ_METHODS)}
            else:
                result = await self.api.call(client, method, params or {})
        except ApiError as error:
            reply = jsonrpc_error(request_id, error.code, str(error), error.data)
        else:
            if isinstance(result, RawJson):
                reply = f'{{"jsonrpc":"2.0","id":{json.dumps(request_id)},"result":{result}}}'
            else:
                reply = _encode({"jsonrpc": "2.0", "id": request_id, "result": result}).decode().rstrip("\n")
        if "id" in request and not client.offer(reply.encode()):
            self.api.dropped_lines_total += 1



def _valid_id(request_id: object) -> bool:
    """A JSON-RPC 2.0 id: a string, a number (finite: NaN or Infinity is not JSON) or null."""
    if request_id is None or isinstance(request_id, str | int) and not isinstance(request_id, bool):
        return True
    return isinstance(request_id, float) and math.isfinite(request_id)


def _json_kind(value: object) -> str:
    """What a JSON value is, in JSON's words."""
    if isinstance(value, bool):
        return "a boolean"
    if isinstance(value, float):
        return f"{value} (not a JSON number)"
    return "an object" if isinstance(value, dict) else "an array" if isinstance(value, list) else type(value).__name__


def tell_panel_address(web: WebServer, stream: TextIO | None = None) -> None:
    """Say where the panel is, on stderr and not through the log (which must never hold a token): at a terminal
    the address with a one-time code for the control token, as Jupyter prints its own; otherwise (a service's
    journal) the address and the file that holds the tokens."""
    stream = stream if stream is not None else sys.stderr
    if web.tokens is None:
        print(f"the panel: {web.url()} (no token asked: this machine only)", file=stream, flush=True)
    elif stream.isatty() and web.one_time_code is not None:
        print(f"the panel: open {web.url()}?code={web.one_time_code} in a browser (once: it is then kept as a "
              f"cookie; the tokens, control and read-only for a second screen, are in {web.tokens.path})",
              file=stream, flush=True)
    else:
        print(f"the panel: {web.url()}, with a token from {web.tokens.path} (open {web.url()}?token=TOKEN once)",
              file=stream, flush=True)
