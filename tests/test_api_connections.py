"""The API server's connections under abuse (issue 51, item 4): a client that stops half way through a line, or
connects and says nothing, is closed with why after a timeout of its own, and what it held is freed; the other
clients are answered meanwhile. On main 3000 such clients (half of a 60 kB line each) held 200 MB for as long as
they stayed; here 300 on the Unix socket, with the timeouts shortened for the test."""

import asyncio
import gc
import time
import tracemalloc

from phantom.host.api import ApiServer

HALF_LINE = b'{"id": 1, "method": "status", "params": {"padding": "' + b"a" * 30_000


async def _status(params):
    return {"ok": True}


def test_half_lines_are_closed_after_their_timeout_and_what_they_held_is_freed(tmp_path, monkeypatch):
    """...and the heap's free pages go back to the system once after the burst (glibc keeps them otherwise: 3000
    such clients on the daemon's loop left 107 MB of RSS, 20-26 MB with the give-back; measured by hand)."""
    import phantom.model.fem.heap

    given_back = []
    monkeypatch.setattr(phantom.model.fem.heap, "give_back", lambda: given_back.append(time.monotonic()))

    async def run():
        server = ApiServer(tmp_path / "d.sock", {"status": _status}, partial_line_timeout_s=1.0)
        await server.start()
        gc.collect()
        tracemalloc.start()
        try:
            baseline = tracemalloc.get_traced_memory()[0]
            stalled = []
            for _ in range(300):
                reader, writer = await asyncio.open_unix_connection(str(tmp_path / "d.sock"))
                writer.write(HALF_LINE)
                await writer.drain()
                stalled.append((reader, writer))
            await asyncio.sleep(0.3)
            held_mb = (tracemalloc.get_traced_memory()[0] - baseline) / 2**20
            # another client is answered while they hang
            reader, writer = await asyncio.open_unix_connection(str(tmp_path / "d.sock"))
            started = time.monotonic()
            writer.write(b'{"id": 2, "method": "status"}\n')
            assert b'"ok":true' in await asyncio.wait_for(reader.readline(), 5)
            answered_s = time.monotonic() - started
            # each half-line client is told why and closed once its line has taken longer than the timeout
            deadline = time.monotonic() + 10
            while len(server.clients) > 1 and time.monotonic() < deadline:
                await asyncio.sleep(0.05)
            assert len(server.clients) == 1, f"{len(server.clients) - 1} half-line clients still served"
            said = await asyncio.wait_for(stalled[0][0].read(), 5)
            assert b"did not end within 1 s" in said and b'"invalid_request"' in said
            for _, stalled_writer in stalled:
                stalled_writer.close()
            stalled.clear()
            await asyncio.sleep(0.2)
            gc.collect()
            left_mb = (tracemalloc.get_traced_memory()[0] - baseline) / 2**20
            print(f"300 half lines held {held_mb:.1f} MB, {left_mb:.2f} MB after they were closed; another client "
                  f"answered in {answered_s * 1e3:.0f} ms")
            assert held_mb > 5, "the half lines were not held at all: the measure measures nothing"
            assert left_mb < 1.0
            await asyncio.sleep(1.5)
            assert 1 <= len(given_back) <= 3, given_back  # once a second of the burst, not once a client
            writer.close()
        finally:
            tracemalloc.stop()
            await server.close()
    asyncio.run(run())


def test_a_connection_that_says_nothing_is_closed_and_one_that_asked_is_kept(tmp_path):
    async def run():
        server = ApiServer(tmp_path / "d.sock", {"status": _status}, silent_timeout_s=0.5)
        await server.start()
        try:
            silent_reader, _ = await asyncio.open_unix_connection(str(tmp_path / "d.sock"))
            reader, writer = await asyncio.open_unix_connection(str(tmp_path / "d.sock"))
            writer.write(b'{"id": 1, "method": "status"}\n')
            await reader.readline()
            said = await asyncio.wait_for(silent_reader.read(), 5)
            assert b"sent no request within 0.5 s" in said
            await asyncio.sleep(1.0)
            writer.write(b'{"id": 2, "method": "status"}\n')   # a client that asked before idles as long as it likes
            assert b'"ok":true' in await asyncio.wait_for(reader.readline(), 5)
            writer.close()
        finally:
            await server.close()
    asyncio.run(run())


def test_a_request_that_gives_a_key_twice_is_refused_not_the_last_taken(tmp_path):
    asked = []

    async def record(params):
        asked.append(params)
        return {"ok": True}

    async def run():
        server = ApiServer(tmp_path / "d.sock", {"status": record})
        await server.start()
        try:
            reader, writer = await asyncio.open_unix_connection(str(tmp_path / "d.sock"))
            writer.write(b'{"id": 1, "method": "status", "params": {"volume_ml": 30, "volume_ml": 45}}\n')
            answer = await asyncio.wait_for(reader.readline(), 5)
            assert b'"parse_error"' in answer and b"duplicate key 'volume_ml'" in answer and asked == []
            writer.close()
        finally:
            await server.close()
    asyncio.run(run())
