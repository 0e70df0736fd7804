"""The local API server on a real Unix socket: request/answer rules, error codes, subscriptions, slow clients.

These use toy handlers (the daemon's own are exercised end to end in tests/test_daemon_e2e.py), so that
each rule of the JSON-lines protocol is checked on its own.
"""

import asyncio
import json
import os
import socket
import stat

import pytest

from phantom import PhantomError
from phantom.host.api import ERROR_CODES, ApiError, ApiServer


async def echo(params):
    return {"echo": params}


async def refuse(params):
    raise ApiError("unreachable", "45 ml is out of reach: 26.3 to 41.0 ml with 3 kPa")


async def crash(params):
    raise ZeroDivisionError("boom")


HANDLERS = {"echo": echo, "refuse": refuse, "crash": crash}


async def exchange(path, *lines):
    reader, writer = await asyncio.open_unix_connection(str(path))
    answers = []
    for line in lines:
        writer.write(line if isinstance(line, bytes) else (json.dumps(line) + "\n").encode())
        await writer.drain()
        answers.append(json.loads(await asyncio.wait_for(reader.readline(), 5)))
    writer.close()
    return answers


def serve(tmp_path, script, **options):
    async def main():
        server = ApiServer(tmp_path / "api.sock", HANDLERS, **options)
        await server.start()
        try:
            return await script(server)
        finally:
            await server.close()

    return asyncio.run(main())


def test_answers_carry_the_request_id_and_errors_carry_a_code(tmp_path):
    async def script(server):
        return await exchange(
            server.socket_path,
            {"id": 1, "method": "echo", "params": {"x": 1}},
            {"id": "two", "method": "refuse"},
            {"id": 3, "method": "nope"},
            b"this is not json\n",
            b"[1, 2]\n",
            {"id": 6, "params": {}},
            {"id": 7, "method": "echo", "params": [1]},
            {"id": 8, "method": "crash"},
            {"id": 9, "method": "subscribe", "params": {"topics": ["gossip"]}},
        )

    answers = serve(tmp_path, script)
    assert answers[0] == {"id": 1, "result": {"echo": {"x": 1}}}
    codes = [answer.get("error", {}).get("code") for answer in answers[1:]]
    assert codes == ["unreachable", "unknown_method", "parse_error", "parse_error", "invalid_request",
                     "invalid_request", "internal", "invalid_params"]
    assert answers[1]["id"] == "two" and "26.3 to 41.0 ml" in answers[1]["error"]["message"]
    assert "methods: crash, echo, refuse, subscribe" in answers[2]["error"]["message"]
    assert answers[3]["id"] is None
    assert "ZeroDivisionError: boom" in answers[7]["error"]["message"]
    assert "topics: telemetry, status, events" in answers[8]["error"]["message"]
    assert all(code in ERROR_CODES for code in codes)


def test_unknown_error_codes_are_a_programming_error():
    with pytest.raises(ValueError):
        ApiError("whatever", "x")


def test_subscribers_get_only_their_topics(tmp_path):
    async def script(server):
        reader, writer = await asyncio.open_unix_connection(str(server.socket_path))
        writer.write(b'{"id": 1, "method": "subscribe", "params": {"topics": ["events"]}}\n')
        reply = json.loads(await reader.readline())
        server.publish("telemetry", {"n": 1})
        server.publish("events", {"text": "fault latched"})
        event = json.loads(await asyncio.wait_for(reader.readline(), 5))
        writer.close()
        return reply, event

    reply, event = serve(tmp_path, script)
    assert reply == {"id": 1, "result": {"topics": ["events"]}}
    assert event == {"event": "events", "data": {"text": "fault latched"}}


def test_a_client_that_never_reads_is_dropped_from_not_waited_for(tmp_path):
    async def script(server):
        stalled = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        stalled.connect(str(server.socket_path))
        stalled.sendall(b'{"id": 1, "method": "subscribe"}\n')
        while not server.clients or not next(iter(server.clients.values())).topics:
            await asyncio.sleep(0.01)
        payload = {"samples": list(range(200))}
        for _ in range(20000):  # far more than the queue and the socket buffers hold
            server.publish("telemetry", payload)
            await asyncio.sleep(0) if _ % 100 == 0 else None
        answers = await exchange(server.socket_path, {"id": 2, "method": "echo", "params": {"still": "alive"}})
        stats = server.stats()
        stalled.close()
        return answers, stats

    answers, stats = serve(tmp_path, script, queue_lines=64)
    assert answers == [{"id": 2, "result": {"echo": {"still": "alive"}}}]
    assert stats["dropped_lines"] > 10000


def test_socket_mode_stale_socket_and_a_second_daemon(tmp_path):
    path = tmp_path / "api.sock"
    stale = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    stale.bind(str(path))
    stale.close()  # a file left by a daemon that died

    async def script(server):
        mode = stat.S_IMODE(os.stat(server.socket_path).st_mode)
        second = ApiServer(server.socket_path, HANDLERS)
        with pytest.raises(PhantomError, match="already listens"):
            await second.start()
        return mode

    assert serve(tmp_path, script) == 0o660
    assert not path.exists()


def test_nan_values_become_null_in_answers(tmp_path):
    async def nan(params):
        return {"volume_ml": float("nan"), "list": [1.0, float("inf")]}

    async def main():
        server = ApiServer(tmp_path / "api.sock", {"nan": nan})
        await server.start()
        try:
            return await exchange(server.socket_path, {"id": 1, "method": "nan"})
        finally:
            await server.close()

    assert asyncio.run(main()) == [{"id": 1, "result": {"volume_ml": None, "list": [1.0, None]}}]


def test_an_overlong_request_is_refused(tmp_path):
    async def script(server):
        reader, writer = await asyncio.open_unix_connection(str(server.socket_path))
        writer.write(b'{"id": 1, "method": "echo", "params": {"x": "' + b"a" * 100_000 + b'"}}\n')
        await writer.drain()
        answer = json.loads(await asyncio.wait_for(reader.readline(), 5))
        writer.close()
        return answer

    answer = serve(tmp_path, script)
    assert answer["error"]["code"] == "invalid_request" and "longer than" in answer["error"]["message"]


@pytest.mark.parametrize(("line", "reason"), [
    (b'{"id": 1, "method": "echo", "params": {"x": "\xff\xfe"}}\n', "not UTF-8"),
    (b"[" * 3000 + b"]" * 3000 + b"\n", "nested too deeply"),
    (b'{"id": 1, "method": "echo", "params": {"n": ' + b"7" * 5000 + b"}}\n", "not valid JSON"),
    (b'{"id": ' + b"[" * 900 + b"]" * 900 + b', "method": "echo"}\n', "id"),
])
def test_input_that_used_to_kill_the_connection_is_answered_and_the_connection_kept(tmp_path, line, reason):
    async def script(server):
        return await exchange(server.socket_path, line, {"id": 2, "method": "echo", "params": {"still": "here"}})

    refused, answered = serve(tmp_path, script)
    assert refused["error"]["code"] in ("parse_error", "invalid_request") and reason in refused["error"]["message"]
    assert answered == {"id": 2, "result": {"echo": {"still": "here"}}}


@pytest.mark.parametrize("kind", ["file", "folder"])
def test_only_a_stale_socket_is_replaced_never_a_file_or_folder(tmp_path, kind):
    path = tmp_path / "api.sock"
    if kind == "file":
        path.write_text("someone's notes")
    else:
        (path / "inside").mkdir(parents=True)

    async def main():
        server = ApiServer(path, HANDLERS)
        with pytest.raises(PhantomError, match="replaces only a stale socket"):
            await server.start()
        await server.close()

    asyncio.run(main())
    assert (path.read_text() == "someone's notes") if kind == "file" else (path / "inside").is_dir()


def test_a_daemon_still_loading_its_model_answers_starting(tmp_path):
    async def main():
        server = ApiServer(tmp_path / "api.sock", {})
        await server.start()
        try:
            return await exchange(server.socket_path, {"id": 1, "method": "status"},
                                  {"id": 2, "method": "subscribe", "params": {"topics": ["events"]}})
        finally:
            await server.close()

    starting, subscribed = asyncio.run(main())
    assert starting["error"]["code"] == "starting" and "try again" in starting["error"]["message"]
    assert subscribed == {"id": 2, "result": {"topics": ["events"]}}


SERVER_WITH_FEW_FILES = """
import asyncio, logging, resource, sys
from phantom.host.api import ApiServer
from phantom.host.logs import configure_logging

_, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
resource.setrlimit(resource.RLIMIT_NOFILE, (160, hard))

async def status(params):
    return {"ok": True}

async def main():
    server = ApiServer(sys.argv[1], {"status": status})
    await server.start()
    print("ready", flush=True)
    await asyncio.sleep(60)

configure_logging("info")
asyncio.run(main())
"""


def test_connections_beyond_the_file_limit_close_the_longest_idle_and_say_so_once(tmp_path):
    """At the process's file limit an idle client per new one is closed, so that a client that needs the daemon
    (to vent) is answered; before, 1100 idle connections at systemd's limit of 1024 made status and vent time out
    and logged a traceback per refused accept."""
    import subprocess
    import sys
    import time

    path = tmp_path / "api.sock"
    server = subprocess.Popen([sys.executable, "-c", SERVER_WITH_FEW_FILES, str(path)], stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE, text=True)
    idle = []
    try:
        assert server.stdout.readline().strip() == "ready"
        for _ in range(300):                    # far more than 160 files
            connection = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
            connection.connect(str(path))
            idle.append(connection)
        time.sleep(0.5)
        needed = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        needed.settimeout(5.0)
        needed.connect(str(path))
        needed.sendall(b'{"id": 1, "method": "status"}\n')
        assert json.loads(needed.makefile("rb").readline()) == {"id": 1, "result": {"ok": True}}
        needed.close()
        # the first idle ones were closed, with a line that says why
        oldest = idle[0]
        oldest.settimeout(5.0)
        farewell = json.loads(oldest.makefile("rb").readline())
        assert farewell["error"]["code"] == "busy" and "longest idle" in farewell["error"]["message"]
    finally:
        for connection in idle:
            connection.close()
        server.kill()
        _, stderr = server.communicate(timeout=10)
    warnings = [line for line in stderr.splitlines() if "WARNING" in line]
    assert len(warnings) == 1 and "connections" in warnings[0], stderr[-3000:]
    assert "Traceback" not in stderr


def test_a_socket_path_too_long_for_a_unix_socket_says_the_limit(tmp_path):
    """`phantom daemon --socket <too long>` said `cannot listen on ...: None`: bind's error has no strerror."""
    path = tmp_path / ("x" * 120 + ".sock")

    async def main():
        server = ApiServer(path, HANDLERS)
        with pytest.raises(PhantomError) as caught:
            await server.start()
        await server.close()
        return str(caught.value)

    assert asyncio.run(main()) == (f"the socket path {path} is {len(str(path))} bytes long: a Unix socket's path may "
                                   "be at most 107 bytes (on Linux); pass a shorter socket path")
    assert not path.exists()


def test_closing_ends_within_a_second_while_clients_keep_asking(tmp_path):
    """A daemon told to stop (SIGTERM) waited for ever in close() while a client polled status: on Python 3.11 a
    cancellation that meets the end of a read under ``asyncio.wait_for`` in one turn is lost, and the client's task
    went on to wait for its next line, holding the socket (a new daemon was refused) until the client left."""

    async def poll(path, stop):
        reader, writer = await asyncio.open_unix_connection(str(path))
        try:
            while not stop.is_set():
                writer.write(b'{"id": 1, ')              # a line in two writes: its end read under wait_for
                await writer.drain()
                await asyncio.sleep(0)
                writer.write(b'"method": "echo"}\n')
                await writer.drain()
                if not await reader.readline():
                    return
        except ConnectionError:
            return
        finally:
            writer.close()

    async def close_took_s(path):
        server = ApiServer(path, HANDLERS)
        await server.start()
        stop = asyncio.Event()
        pollers = [asyncio.create_task(poll(path, stop)) for _ in range(4)]
        await asyncio.sleep(0.2)
        started = asyncio.get_running_loop().time()
        closing = asyncio.create_task(server.close())
        done, _ = await asyncio.wait({closing}, timeout=3.0)
        stop.set()
        await asyncio.wait(pollers, timeout=3.0)
        if not done:
            return None                                    # close() hung: its task is abandoned with the loop
        return asyncio.get_running_loop().time() - started

    async def main():
        return [await close_took_s(tmp_path / f"api{number}.sock") for number in range(5)]

    loop = asyncio.new_event_loop()
    try:
        took_s = loop.run_until_complete(main())
    finally:
        loop.close()
    assert all(took is not None and took < 1.5 for took in took_s), took_s
