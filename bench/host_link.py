"""Latency of the daemon's two interfaces, each against a bare peer measured in the same run.

1. The board link: an acknowledged SET_SETPOINTS and a PING/PONG through the real firmware in simavr (paced to
   the wall clock, 115200 baud), against the same session talking to a minimal Python responder on a pty
   (the peer: what the host side alone costs).
2. The local API: a request through ApiServer (JSON parse, dispatch, per-client queue and writer task)
   against a bare asyncio echo over the same kind of Unix socket; then the API again while a subscriber that
   never reads is being flooded with telemetry (the slow-client rule: it must not slow the others).

    .venv/bin/python bench/host_link.py [--n 200]

Prints a table (median and 99th percentile, ms, and the ratio to the peer).
"""

from __future__ import annotations

import argparse
import asyncio
import os
import socket
import tempfile
import time
import tty
from pathlib import Path

import numpy as np

from phantom.host.api import ApiServer
from phantom.host.session import LinkSession, LinkTiming
from phantom.host.transports import SerialTransport
from phantom.protocol.link import BoardPeer


async def responder(master: int, stop: asyncio.Event) -> None:
    """The peer board (the link core's board end): answers HELLO, ACKs every acknowledged command, PONGs pings,
    streams telemetry."""
    loop = asyncio.get_running_loop()
    board = BoardPeer(board="NATIVE")
    queue: asyncio.Queue = asyncio.Queue()
    loop.add_reader(master, lambda: queue.put_nowait(os.read(master, 4096)))

    async def stream():
        while not stop.is_set():
            os.write(master, board.telemetry(0, [0, 0, 0], [0, 0, 0]))
            await asyncio.sleep(0.02)

    streamer = asyncio.create_task(stream())
    try:
        while not stop.is_set():
            try:
                data = await asyncio.wait_for(queue.get(), 0.1)
            except TimeoutError:
                continue
            for message in board.receive(data):
                answer = board.answer(message, 0)
                if answer is not None:
                    os.write(master, answer)
    finally:
        streamer.cancel()
        loop.remove_reader(master)


async def link_latencies(port: str, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Seconds per acknowledged SET_SETPOINTS, and PONG round trips (s), over ``n`` samples each."""
    rtts = []
    session = LinkSession(SerialTransport(port), LinkTiming(keepalive_s=0.05))
    task = asyncio.create_task(session.run())
    await asyncio.wait_for(session.online_event.wait(), 30)
    acks = []
    for index in range(n):
        started = time.perf_counter()
        await session.command("SET_SETPOINTS", {"setpoint_pa": [index % 500, 0, 0]})
        acks.append(time.perf_counter() - started)
    last = None
    while len(rtts) < n:
        await asyncio.sleep(0.01)
        if session.stats.pings != last and session.stats.rtt_ms is not None:
            last = session.stats.pings
            rtts.append(session.stats.rtt_ms / 1e3)
    await session.command("VENT")
    session.stop()
    await task
    return np.asarray(acks), np.asarray(rtts)


async def peer_link(n: int):
    master, slave = os.openpty()
    tty.setraw(slave)
    stop = asyncio.Event()
    peer = asyncio.create_task(responder(master, stop))
    try:
        return await link_latencies(os.ttyname(slave), n)
    finally:
        stop.set()
        await peer
        os.close(slave)
        os.close(master)


def api_round_trips(path: Path, n: int, request: bytes) -> np.ndarray:
    client = socket.socket(socket.AF_UNIX)
    client.connect(str(path))
    stream = client.makefile("rb")
    times = []
    for _ in range(n):
        started = time.perf_counter()
        client.sendall(request)
        stream.readline()
        times.append(time.perf_counter() - started)
    client.close()
    return np.asarray(times)


async def api_bench(n: int) -> dict[str, np.ndarray]:
    directory = Path(tempfile.mkdtemp(prefix="phantom-bench-"))
    loop = asyncio.get_running_loop()

    async def echo_handler(params):
        return params

    server = ApiServer(directory / "api.sock", {"echo": echo_handler})
    await server.start()

    async def bare(reader, writer):
        while line := await reader.readline():
            writer.write(line)
            await writer.drain()

    bare_server = await asyncio.start_unix_server(bare, path=str(directory / "bare.sock"))
    request = b'{"id": 1, "method": "echo", "params": {"volume_ml": 32}}\n'
    results = {"bare": await loop.run_in_executor(None, api_round_trips, directory / "bare.sock", n, request),
               "api": await loop.run_in_executor(None, api_round_trips, directory / "api.sock", n, request)}
    stalled = socket.socket(socket.AF_UNIX)
    stalled.connect(str(directory / "api.sock"))
    stalled.sendall(b'{"id": 1, "method": "subscribe", "params": {"topics": ["telemetry"]}}\n')
    flooding = True

    async def flood():
        sample = {"pressures_kpa": [1.0, 2.0, 3.0], "setpoints_kpa": [1.0, 2.0, 3.0], "drive_levels": [0.1, 0.2, 0.3]}
        while flooding:
            for _ in range(10):
                server.publish("telemetry", sample)
            await asyncio.sleep(0.002)

    flooder = asyncio.create_task(flood())
    await asyncio.sleep(2.0)
    results["api, stalled subscriber"] = await loop.run_in_executor(None, api_round_trips, directory / "api.sock", n,
                                                                   request)
    flooding = False
    await flooder
    results["dropped lines"] = server.stats()["dropped_lines"]
    stalled.close()
    bare_server.close()
    await server.close()
    return results


def row(name: str, seconds: np.ndarray, peer: np.ndarray) -> str:
    median_ms, p99_ms = 1e3 * np.median(seconds), 1e3 * np.percentile(seconds, 99)
    return f"| {name} | {median_ms:.3f} | {p99_ms:.3f} | {np.median(seconds) / np.median(peer):.2f} |"


def main() -> None:
    from phantom.hil.sim import SimulatedBoard

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, default=200)
    args = parser.parse_args()
    peer_ack, peer_rtt = asyncio.run(peer_link(args.n))
    with SimulatedBoard(speed=1.0) as board:
        sim_ack, sim_rtt = asyncio.run(link_latencies(board.port, args.n))
    api = asyncio.run(api_bench(args.n * 10))
    print("| measurement | median (ms) | p99 (ms) | ratio to peer (median) |")
    print("| --- | --- | --- | --- |")
    print(row("peer: SET_SETPOINTS ack, Python responder on a pty", peer_ack, peer_ack))
    print(row("SET_SETPOINTS ack, firmware in simavr (real time)", sim_ack, peer_ack))
    print(row("peer: PING/PONG, Python responder on a pty", peer_rtt, peer_rtt))
    print(row("PING/PONG, firmware in simavr (real time)", sim_rtt, peer_rtt))
    print(row("peer: bare asyncio echo on a Unix socket", api["bare"], api["bare"]))
    print(row("API request (ApiServer)", api["api"], api["bare"]))
    print(row("API request, a stalled subscriber flooded with 5000 lines/s", api["api, stalled subscriber"],
              api["bare"]))
    print(f"\nlines dropped for the stalled subscriber: {api['dropped lines']}")


if __name__ == "__main__":
    main()
