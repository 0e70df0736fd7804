"""The daemon's longest event-loop stall under the red-team load (issue 23, defect 3): goal under 50 ms.

A daemon (``phantom daemon --port``, the calibrated model from its cached response table) drives the simulated
board (the real firmware in simavr, real time) holding 32 ml, while this script plays the load of the red-team
report one phase at a time, each bounded in count and time, all on the daemon's Unix socket:

    idle             nothing (the baseline)
    connections      300 idle connections opened and held
    subscribers      20 clients subscribed to every topic, reading, for 5 s
    surface x100     100 concurrent `surface` requests, three rounds
    run_scene 30 MB  a scene file of 30 MB (refused by size now; parsed in the loop before: 0.56 s)
    run_scene 20k    a valid scene of 20,000 steps (refused by count now; parsed in the loop before: 0.57 s)
    status flood     50 clients sending 200 `status` requests each, as fast as answered

Per phase: the longest lateness of the daemon's event-loop probe (a 20 ms timer: ``event_loop`` in the status),
of the board link's own loop (``link_detail.event_loop``: its keepalive's timers, in the link's thread), and,
as the peer measured in the same run, of the same probe in a bare process that does nothing else (what the
machine's scheduler alone costs: on a shared two-core machine it is not zero); and whether the link was lost
or a fault latched (the board stops its blowers when the daemon is silent for 500 ms).

    .venv/bin/python bench/daemon_stall.py [--rounds 3]   # about 1 minute a round

With ``--rounds``, each phase is played that many times and the worst of each column is shown.

Prints a Markdown table (bench/README.md, "The daemon under load").
"""

from __future__ import annotations

import argparse
import asyncio
import json
import subprocess
import sys
import tempfile
import time
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parent.parent
sys.path.append(str(REPO / "tests"))  # daemon_rig: a daemon process on a simulated board


async def call(socket_path: Path, method: str, params: dict[str, Any] | None = None,
               timeout_s: float = 60.0) -> dict[str, Any]:
    """One request on a connection of its own; the whole answer line (result or error)."""
    reader, writer = await asyncio.open_unix_connection(str(socket_path), limit=64 * 2**20)
    try:
        writer.write((json.dumps({"id": 1, "method": method, "params": params or {}}) + "\n").encode())
        await writer.drain()
        answer: dict[str, Any] = json.loads(await asyncio.wait_for(reader.readline(), timeout_s))
        return answer
    finally:
        writer.close()


async def idle_connections(socket_path: Path, count: int = 300, hold_s: float = 5.0) -> None:
    writers = []
    for _ in range(count):
        _, writer = await asyncio.open_unix_connection(str(socket_path))
        writers.append(writer)
    await asyncio.sleep(hold_s)
    for writer in writers:
        writer.close()


async def subscribers(socket_path: Path, count: int = 20, seconds: float = 5.0) -> None:
    async def one() -> None:
        reader, writer = await asyncio.open_unix_connection(str(socket_path), limit=2**20)
        writer.write(b'{"id": 1, "method": "subscribe", "params": {}}\n')
        await writer.drain()
        ends = time.monotonic() + seconds
        while time.monotonic() < ends:
            await asyncio.wait_for(reader.readline(), 5.0)
        writer.close()
    await asyncio.gather(*(one() for _ in range(count)))


async def surfaces(socket_path: Path, count: int = 100, rounds: int = 3) -> None:
    for _ in range(rounds):
        await asyncio.gather(*(call(socket_path, "surface") for _ in range(count)))


def scene_header() -> str:
    return (REPO / "host" / "scenes" / "bph_growth.toml").read_text().split("[[steps]]")[0].split("[timeline]")[0]


async def big_scene_file(socket_path: Path, directory: Path) -> None:
    path = directory / "big.toml"
    with open(path, "w") as handle:
        handle.write(scene_header())
        line = "# " + "x" * 98 + "\n"
        handle.write(line * (30 * 2**20 // len(line)))
        handle.write("[[steps]]\nat_s = 0\nvolume_ml = 32.0\n")
    await call(socket_path, "run_scene", {"path": str(path)})


async def many_steps(socket_path: Path, directory: Path) -> None:
    path = directory / "steps.toml"
    steps = "".join(f"[[steps]]\nat_s = {index}\nvolume_ml = {30 + (index % 5)}.0\n" for index in range(20000))
    path.write_text(scene_header() + "[timeline]\nend_s = 20010\n" + steps)
    await call(socket_path, "run_scene", {"path": str(path)})
    await call(socket_path, "set_target", {"volume_ml": 32.0})   # back to holding


async def status_flood(socket_path: Path, clients: int = 50, requests: int = 200) -> None:
    async def one() -> None:
        reader, writer = await asyncio.open_unix_connection(str(socket_path), limit=2**20)
        for index in range(requests):
            writer.write((json.dumps({"id": index, "method": "status"}) + "\n").encode())
            await writer.drain()
            await asyncio.wait_for(reader.readline(), 30.0)
        writer.close()
    await asyncio.gather(*(one() for _ in range(clients)))


PEER = """
import asyncio, sys, time
async def main():
    longest = 0.0
    while True:
        due = time.monotonic() + 0.02
        await asyncio.sleep(0.02)
        longest = max(longest, (time.monotonic() - due) * 1e3)
        if sys.stdin in __import__("select").select([sys.stdin], [], [], 0)[0]:
            sys.stdin.readline()
            print(f"{longest:.1f}", flush=True)
            longest = 0.0
asyncio.run(main())
"""


class PeerProbe:
    """A bare process that runs the daemon's 20 ms probe and nothing else; :meth:`longest` reads and resets it."""

    def __init__(self) -> None:
        self.process = subprocess.Popen([sys.executable, "-c", PEER], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                        text=True)

    def longest(self) -> float:
        assert self.process.stdin is not None and self.process.stdout is not None
        self.process.stdin.write("\n")
        self.process.stdin.flush()
        return float(self.process.stdout.readline())

    def close(self) -> None:
        self.process.kill()
        self.process.wait(10)


def longest(stalls: list[list[float]], since_ago_s: float) -> float:
    """The longest listed stall (ms) of those less than ``since_ago_s`` ago."""
    return max((late for ago_s, late, *_ in stalls if ago_s <= since_ago_s), default=0.0)


async def measure(socket_path: Path, name: str, load: Callable[[], Awaitable[None]], peer: PeerProbe) -> dict[str, Any]:
    before = (await call(socket_path, "status"))["result"]
    peer.longest()
    started = time.monotonic()
    await load()
    await asyncio.sleep(0.5)
    after = (await call(socket_path, "status"))["result"]
    window_s = time.monotonic() - started + 0.1
    link_loop = after["link_detail"].get("event_loop", {})
    stats_before, stats_after = before["link_detail"]["stats"], after["link_detail"]["stats"]
    return {"phase": name, "seconds": window_s, "peer_ms": peer.longest(),
            "loop_ms": longest(after["event_loop"]["notable_stalls"], window_s),
            "link_ms": longest(link_loop.get("notable_stalls", []), window_s) if link_loop else None,
            "links_lost": stats_after["links_lost"] - stats_before["links_lost"],
            "faults": after["faults"], "held": after["target_applied"] if "target_applied" in after else None}


def worst(rounds: list[list[dict[str, Any]]]) -> list[dict[str, Any]]:
    """Per phase, the worst of several rounds: the longest stalls of each loop and of the peer, the links lost
    added up, every fault, and whether the target was held in all of them."""
    rows = []
    for runs in zip(*rounds, strict=True):
        row = dict(runs[0])
        for key in ("seconds", "peer_ms", "loop_ms", "link_ms"):
            values = [run[key] for run in runs if run[key] is not None]
            row[key] = max(values) if values else None
        row["links_lost"] = sum(run["links_lost"] for run in runs)
        row["faults"] = sorted({fault for run in runs for fault in run["faults"]})
        row["held"] = all(run["held"] for run in runs)
        rows.append(row)
    return rows


async def main_async(socket_path: Path, directory: Path, chosen: str | None,
                     rounds: int = 1) -> list[dict[str, Any]]:
    answer = await call(socket_path, "set_target", {"volume_ml": 32.0})
    assert "result" in answer, answer
    await asyncio.sleep(3.0)
    phases: list[tuple[str, Callable[[], Awaitable[None]]]] = [
        ("idle", lambda: asyncio.sleep(5.0)),
        ("connections: 300 idle", lambda: idle_connections(socket_path)),
        ("subscribers: 20 on every topic", lambda: subscribers(socket_path)),
        ("surface: 100 at once, 3 rounds", lambda: surfaces(socket_path)),
        ("run_scene: a 30 MB file", lambda: big_scene_file(socket_path, directory)),
        ("run_scene: 20,000 steps", lambda: many_steps(socket_path, directory)),
        ("status: 50 clients x 200", lambda: status_flood(socket_path)),
    ]
    if chosen:
        phases = [phases[int(number)] for number in chosen.split(",")]
    peer = PeerProbe()
    try:
        return worst([[await measure(socket_path, name, load, peer) for name, load in phases]
                      for _ in range(rounds)])
    finally:
        peer.close()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--log", type=Path, help="keep the daemon's log in this file")
    parser.add_argument("--phases", help="comma-separated phase numbers to run (default: all)")
    parser.add_argument("--rounds", type=int, default=1, help="play the phases this many times; the worst is shown")
    args = parser.parse_args()
    from daemon_rig import DaemonRig

    with tempfile.TemporaryDirectory(prefix="phantom-stall-") as folder:
        directory = Path(folder)
        rig = DaemonRig(directory, speed=1.0)
        try:
            rig.wait_online(120)
            rows = asyncio.run(main_async(rig.socket, directory, args.phases, args.rounds))
        finally:
            rig.close()
            if args.log:
                args.log.write_text((directory / "daemon.log").read_text())
    print("| load | seconds | daemon's loop: longest stall (ms) | link's loop (ms) | bare peer process (ms) | "
          "links lost | faults | target held |")
    print("|---|---|---|---|---|---|---|---|")
    for row in rows:
        link = "-" if row["link_ms"] is None else f"{row['link_ms']:.0f}"
        print(f"| {row['phase']} | {row['seconds']:.1f} | {row['loop_ms']:.0f} | {link} | {row['peer_ms']:.0f} | "
              f"{row['links_lost']} | {', '.join(row['faults']) or 'none'} | {row['held']} |")


if __name__ == "__main__":
    main()
