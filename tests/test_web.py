"""The daemon's API over a WebSocket (host/web.py): JSON-RPC framing through the Unix socket's dispatch, and each
refusal (another Origin, a rebinding Host, no token, a wrong one, a read-only token setting a target, a public
address without a token, an unsafe tokens' file), with a plain aiohttp client against a real server."""

from __future__ import annotations

import asyncio
import json
import logging
import os
import stat
import time
from collections.abc import AsyncIterator, Awaitable, Callable
from contextlib import asynccontextmanager
from pathlib import Path
from typing import Any

import aiohttp
import pytest

from phantom.host.api import ApiError, ApiServer
from phantom.host.web import (
    JSONRPC_CODES,
    PanelTokens,
    WebError,
    WebServer,
    host_allowed,
    jsonrpc_frame,
    origin_allowed,
    panel_tokens,
    parse_address,
)


async def _status(params: dict[str, Any]) -> dict[str, Any]:
    return {"link": "online", "estimated_volume_ml": float("nan")}


async def _set_target(params: dict[str, Any]) -> dict[str, Any]:
    if "volume_ml" not in params:
        raise ApiError("invalid_params", "set_target needs volume_ml")
    return {"volume_ml": params["volume_ml"]}


@asynccontextmanager
async def served(tmp_path: Path, tokens: PanelTokens | None, hosts: tuple[str, ...] = ()) -> AsyncIterator[
        tuple[ApiServer, WebServer]]:
    api = ApiServer(tmp_path / "api.sock", {"status": _status, "set_target": _set_target})
    await api.start()
    web = WebServer(api, "127.0.0.1:0", tokens, hosts)
    await web.start()
    try:
        yield api, web
    finally:
        await web.close()
        await api.close()


def run(test: Callable[[], Awaitable[None]]) -> None:
    asyncio.run(test())


async def call(socket: aiohttp.ClientWebSocketResponse, method: str, params: dict[str, Any] | None = None,
               request_id: int = 1) -> dict[str, Any]:
    await socket.send_str(json.dumps({"jsonrpc": "2.0", "method": method, "params": params or {}, "id": request_id}))
    while True:
        message = json.loads((await socket.receive(timeout=5)).data)
        if message.get("id") == request_id:
            return dict(message)


@pytest.fixture
def tokens(tmp_path: Path) -> PanelTokens:
    return panel_tokens(tmp_path / "data" / "panel-tokens.json")


def test_the_tokens_file_is_made_private_once_and_refused_when_others_may_read_it(tmp_path):
    path = tmp_path / "data" / "panel-tokens.json"
    first = panel_tokens(path)
    assert stat.S_IMODE(path.stat().st_mode) == 0o600
    assert len(first.control) >= 40 and first.control != first.read
    assert panel_tokens(path) == first                      # kept across restarts
    assert first.access(first.control) == "control" and first.access(first.read) == "read"
    assert first.access(first.control + "x") is None and first.access(None) is None
    os.chmod(path, 0o644)
    with pytest.raises(WebError, match="may be read by others.*chmod 600"):
        panel_tokens(path)
    os.chmod(path, 0o600)
    path.write_text("{not json")
    with pytest.raises(WebError, match="damaged"):
        panel_tokens(path)


def test_addresses_hosts_and_origins():
    assert parse_address("127.0.0.1:8080") == ("127.0.0.1", 8080)
    assert parse_address("[::1]:8080") == ("::1", 8080)
    assert parse_address("8080") == ("127.0.0.1", 8080)           # a port alone: this machine only
    for bad in ("127.0.0.1", "127.0.0.1:http", "127.0.0.1:70000", ":8080", "http"):
        with pytest.raises(WebError, match="HOST:PORT"):
            parse_address(bad)
    names = frozenset({"labpc.example.org"})
    for good in ("127.0.0.1:8080", "localhost:9000", "[::1]:8080", "192.168.1.20:8080", "labpc.example.org:8080"):
        assert host_allowed(good, names), good
    for rebound in ("evil.example:8080", "127.0.0.1.evil.example:8080", "", None):
        assert not host_allowed(rebound, names), rebound
    assert origin_allowed(None, "127.0.0.1:8080")
    assert origin_allowed("http://127.0.0.1:8080", "127.0.0.1:8080")
    assert not origin_allowed("http://127.0.0.1:8081", "127.0.0.1:8080")
    assert not origin_allowed("http://evil.example", "127.0.0.1:8080")
    assert not origin_allowed("null", "127.0.0.1:8080")


def test_a_public_address_without_a_token_is_refused(tmp_path, tokens):
    api = ApiServer(tmp_path / "api.sock", {})
    with pytest.raises(WebError, match="reachable from other machines: it needs the token"):
        WebServer(api, "0.0.0.0:8080", None)
    with pytest.raises(WebError, match="reachable from other machines"):
        WebServer(api, "192.168.1.20:8080", None)
    WebServer(api, "0.0.0.0:8080", tokens)                  # with the token: allowed
    WebServer(api, "127.0.0.1:8080", None)                  # loopback without: allowed


def test_json_rpc_through_the_api_dispatch_with_notifications(tmp_path, tokens):
    async def test() -> None:
        async with served(tmp_path, tokens) as (api, web), aiohttp.ClientSession() as session:
            url = f"http://127.0.0.1:{web.port}/websocket"
            async with session.ws_connect(url, headers={"Authorization": f"Bearer {tokens.control}"}) as socket:
                answer = await call(socket, "status")
                assert answer == {"jsonrpc": "2.0", "id": 1, "result": {"link": "online",
                                                                          "estimated_volume_ml": None}}
                answer = await call(socket, "set_target", {"volume_ml": 44}, 2)
                assert answer["result"] == {"volume_ml": 44}
                answer = await call(socket, "set_target", {}, 3)
                assert answer["error"]["code"] == JSONRPC_CODES["invalid_params"] == -32602
                assert answer["error"]["data"]["error"] == "invalid_params"
                assert "volume_ml" in answer["error"]["message"]
                answer = await call(socket, "nonsense", {}, 4)
                assert answer["error"]["code"] == -32601 and "methods:" in answer["error"]["message"]
                answer = await call(socket, "identify", {}, 5)
                assert answer["result"]["access"] == "control" and "set_target" in answer["result"]["methods"]
                await socket.send_str('{"method": "status", "id": 6}')        # not JSON-RPC 2.0
                assert json.loads((await socket.receive(timeout=5)).data)["error"]["code"] == -32600
                await socket.send_str("{not json")
                assert json.loads((await socket.receive(timeout=5)).data)["error"]["code"] == -32700
                assert (await call(socket, "subscribe", {"topics": ["events"]}, 7))["result"] == {"topics": ["events"]}
                api.publish("events", {"kind": "target", "text": "reached", "outcome": "reached"})
                message = json.loads((await socket.receive(timeout=5)).data)
                assert message == {"jsonrpc": "2.0", "method": "notify_events",
                                   "params": [{"kind": "target", "text": "reached", "outcome": "reached"}]}
                assert api.stats()["clients"] == 1            # counted among the API's clients
            assert api.stats()["requests"] >= 7
    run(test)


def test_another_origin_a_rebinding_host_and_a_missing_or_wrong_token_are_refused(tmp_path, tokens):
    async def test() -> None:
        async with served(tmp_path, tokens) as (_, web), aiohttp.ClientSession() as session:
            url = f"http://127.0.0.1:{web.port}/websocket"
            good = {"Authorization": f"Bearer {tokens.control}"}
            refusals = [
                ({**good, "Origin": "http://evil.example"}, 403, "may not use this panel's API"),
                ({**good, "Origin": f"http://localhost:{web.port + 1}"}, 403, "may not use"),
                ({**good, "Host": f"evil.example:{web.port}"}, 403, "is not served here"),
                ({}, 401, "needs its token"),
                ({"Authorization": "Bearer wrong"}, 401, "needs its token"),
                ({"Authorization": f"Bearer {tokens.control[:-1]}"}, 401, "needs its token"),
            ]
            for headers, code, words in refusals:
                with pytest.raises(aiohttp.WSServerHandshakeError) as refused:
                    await session.ws_connect(url, headers=headers)
                assert refused.value.status == code, headers
                async with session.get(url, headers=headers) as response:   # the words, for people
                    assert response.status == code and words in await response.text()
            assert web.status()["refused"] == {"host": 2, "origin": 4, "token": 6, "forbidden": 0}
            # the page's own origin with the token is served
            async with session.ws_connect(url, headers={**good, "Origin": f"http://127.0.0.1:{web.port}"}) as socket:
                assert (await call(socket, "status"))["result"]["link"] == "online"
            # a rebound name is refused for the page too, not only the WebSocket
            async with session.get(f"http://127.0.0.1:{web.port}/",
                                   headers={"Host": f"evil.example:{web.port}"}) as response:
                assert response.status == 403
    run(test)


def test_a_name_given_in_http_hosts_is_served(tmp_path, tokens):
    async def test() -> None:
        async with served(tmp_path, tokens, ("labpc.example.org",)) as (_, web), aiohttp.ClientSession() as session:
            host = f"labpc.example.org:{web.port}"
            async with session.ws_connect(f"http://127.0.0.1:{web.port}/websocket", headers={
                    "Host": host, "Origin": f"http://{host}", "Authorization": f"Bearer {tokens.read}"}) as socket:
                assert (await call(socket, "status"))["result"]["link"] == "online"
    run(test)


def test_a_read_only_token_watches_and_cannot_set(tmp_path, tokens):
    async def test() -> None:
        async with served(tmp_path, tokens) as (_, web), aiohttp.ClientSession() as session:
            async with session.ws_connect(f"http://127.0.0.1:{web.port}/websocket",
                                          headers={"Authorization": f"Bearer {tokens.read}"}) as socket:
                assert (await call(socket, "identify"))["result"] == {"access": "read",
                                                                      "methods": ["identify", "status", "subscribe"]}
                assert (await call(socket, "status", {}, 2))["result"]["link"] == "online"
                answer = await call(socket, "set_target", {"volume_ml": 44}, 3)
                assert answer["error"]["data"]["error"] == "forbidden"
                assert "read-only" in answer["error"]["message"]
            assert web.status()["refused"]["forbidden"] == 1
    run(test)


def test_the_token_in_the_address_becomes_a_cookie_and_never_reaches_the_log(tmp_path, tokens, caplog):
    caplog.set_level(logging.DEBUG)

    async def test() -> None:
        # a browser keeps a cookie of an IP address; aiohttp's jar only when told
        async with served(tmp_path, tokens) as (_, web), aiohttp.ClientSession(
                cookie_jar=aiohttp.CookieJar(unsafe=True)) as session:
            base = f"http://127.0.0.1:{web.port}"
            async with session.get(f"{base}/?token={tokens.read}", allow_redirects=False) as response:
                assert response.status == 303 and response.headers["Location"] == "/"
                cookie = response.headers["Set-Cookie"]
                assert "HttpOnly" in cookie and "SameSite=Strict" in cookie
            async with session.get(f"{base}/access") as response:            # the cookie now says who this is
                assert await response.json() == {"access": "read", "token_needed": True}
            async with session.ws_connect(f"{base}/websocket") as socket:
                assert (await call(socket, "identify"))["result"]["access"] == "read"
            async with session.get(f"{base}/") as response:
                assert response.status == 200 and "<title>Prostate phantom</title>" in await response.text()
                assert response.headers["X-Frame-Options"] == "DENY"
                assert "frame-ancestors 'none'" in response.headers["Content-Security-Policy"]
            async with session.get(f"{base}/?token=wrong", allow_redirects=False) as response:
                assert response.status == 401
            async with session.get(f"{base}/static/vendor/three/LICENSE") as response:
                assert response.status == 200 and "MIT" in await response.text()
    run(test)
    assert tokens.control not in caplog.text and tokens.read not in caplog.text


def test_the_apis_lines_become_json_rpc():
    assert jsonrpc_frame(b'{"event":"status","data":{"a":1}}\n') == (
        '{"jsonrpc":"2.0","method":"notify_status","params":[{"a":1}]}')
    shed = json.loads(jsonrpc_frame(b'{"id":null,"error":{"code":"busy","message":"closed for a new one"}}\n'))
    assert shed["error"]["code"] == JSONRPC_CODES["busy"] and shed["error"]["data"] == {"error": "busy"}
    assert len(set(JSONRPC_CODES.values())) == len(JSONRPC_CODES)


def test_a_port_in_use_is_refused_with_what_to_do(tmp_path, tokens):
    async def test() -> None:
        async with served(tmp_path, tokens) as (api, web):
            second = WebServer(api, f"127.0.0.1:{web.port}", tokens)
            with pytest.raises(WebError, match=f"cannot serve the panel on 127.0.0.1:{web.port}: .*another --http"):
                await second.start()
    run(test)


def test_the_printed_one_time_code_opens_the_panel_once(tmp_path, tokens):
    async def test() -> None:
        async with served(tmp_path, tokens) as (_, web), aiohttp.ClientSession(
                cookie_jar=aiohttp.CookieJar(unsafe=True)) as session:
            base = f"http://127.0.0.1:{web.port}"
            code = web.one_time_code
            assert code is not None and code not in (tokens.control, tokens.read)
            async with session.get(f"{base}/?code=wrong", allow_redirects=False) as response:
                assert response.status == 401
            async with session.get(f"{base}/?code={code}", allow_redirects=False) as response:
                assert response.status == 303 and response.headers["Location"] == "/"
            async with session.get(f"{base}/access") as response:
                assert (await response.json())["access"] == "control"
            session.cookie_jar.clear()
            async with session.get(f"{base}/?code={code}", allow_redirects=False) as response:
                assert response.status == 401 and "used already" in await response.text()
    run(test)


def test_closing_ends_the_open_websockets_at_once(tmp_path, tokens):
    # a panel left open must not hold the daemon's stop (aiohttp waits up to a minute for its handlers otherwise)
    async def test() -> None:
        api = ApiServer(tmp_path / "api.sock", {"status": _status})
        await api.start()
        web = WebServer(api, "127.0.0.1:0", tokens)
        await web.start()
        async with aiohttp.ClientSession() as session:
            async with session.ws_connect(f"http://127.0.0.1:{web.port}/websocket",
                                          headers={"Authorization": f"Bearer {tokens.control}"}) as socket:
                assert (await call(socket, "status"))["result"]["link"] == "online"
                started = time.monotonic()
                await asyncio.wait_for(web.close(), 10)
                assert time.monotonic() - started < 3.0
                message = await socket.receive(timeout=5)
                assert message.type in (aiohttp.WSMsgType.CLOSE, aiohttp.WSMsgType.CLOSED)
        await api.close()
    run(test)
