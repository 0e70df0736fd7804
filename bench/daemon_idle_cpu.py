"""The daemon's CPU when it does nothing (issue 23, defect 11), against a bare asyncio reader of the same pty.

A daemon (``phantom daemon --port``) is connected to the simulated board (the firmware in simavr, real time),
vented, with the board streaming 50 Hz telemetry; its CPU time (all its threads, not the model worker) is read
from /proc over ``--seconds``. Then the daemon is killed and, as the peer, a bare asyncio process reads the same
pty (an ``add_reader`` callback and ``os.read``, nothing else) while the board, whose session is still open,
keeps streaming: what reading those bytes costs at the least. The daemon's reads of the port are its status's
``port_reads``; the peer reads every piece the pty delivers (a byte at a time from the simulated UART). Before
the serial transport waited out a frame's bytes, the daemon read the port as often as the peer (about 1300 times
a second) and spent 5-9 % of a core idle.

    .venv/bin/python bench/daemon_idle_cpu.py [--seconds 20] [--record]

``--record``: the daemon records to an ``.rrd`` (``--rerun-save``), as ``make demo``'s does, and a second daemon
that does not is measured in the same run: what recording the telemetry costs.

Prints a Markdown table (bench/README.md, "The daemon's idle CPU").
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.append(str(Path(__file__).resolve().parent.parent / "tests"))  # daemon_rig: a daemon on a simulated board
TICKS_PER_S = os.sysconf("SC_CLK_TCK")

PEER = """
import asyncio, os, resource, sys, time
async def main(path, seconds):
    fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_NOCTTY)
    counts = {"bytes": 0, "wakeups": 0}
    def readable():
        counts["wakeups"] += 1
        try:
            counts["bytes"] += len(os.read(fd, 4096))
        except BlockingIOError:
            pass
    asyncio.get_running_loop().add_reader(fd, readable)
    await asyncio.sleep(1.0)
    start = time.monotonic(); cpu = time.process_time(); before = dict(counts)
    await asyncio.sleep(seconds)
    elapsed = time.monotonic() - start
    print(100 * (time.process_time() - cpu) / elapsed, (counts["bytes"] - before["bytes"]) / elapsed,
          (counts["wakeups"] - before["wakeups"]) / elapsed)
asyncio.run(main(sys.argv[1], float(sys.argv[2])))
"""


def cpu_s(pid: int) -> float:
    """User and system CPU time (s) of a process, all its threads."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / TICKS_PER_S


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seconds", type=float, default=20.0)
    parser.add_argument("--record", action="store_true", help="also a daemon that records to an .rrd")
    args = parser.parse_args()
    from daemon_rig import DaemonRig

    recorded_cpu = None
    if args.record:
        with tempfile.TemporaryDirectory(prefix="phantom-idle-") as folder:
            rig = DaemonRig(Path(folder), "--rerun-save", str(Path(folder) / "idle.rrd"), speed=1.0)
            try:
                rig.wait_online(120)
                time.sleep(3.0)
                started, cpu_before = time.monotonic(), cpu_s(rig.process.pid)
                time.sleep(args.seconds)
                recorded_cpu = 100 * (cpu_s(rig.process.pid) - cpu_before) / (time.monotonic() - started)
            finally:
                rig.close()
    with tempfile.TemporaryDirectory(prefix="phantom-idle-") as folder:
        rig = DaemonRig(Path(folder), speed=1.0)
        try:
            rig.wait_online(120)
            time.sleep(3.0)
            before = rig.status()["link_detail"]["stats"]
            started, cpu_before = time.monotonic(), cpu_s(rig.process.pid)
            time.sleep(args.seconds)
            elapsed = time.monotonic() - started
            daemon_cpu = 100 * (cpu_s(rig.process.pid) - cpu_before) / elapsed
            after = rig.status()["link_detail"]["stats"]
            frames_per_s = (after["frames_rx"] - before["frames_rx"]) / elapsed
            reads_per_s = (after["port_reads"] - before["port_reads"]) / elapsed
            rig.process.send_signal(signal.SIGKILL)      # the board's session stays open: it keeps streaming
            rig.process.wait(10)
            peer = subprocess.run([sys.executable, "-c", PEER, rig.board.port, str(args.seconds)],
                                  capture_output=True, text=True, timeout=args.seconds + 30, check=True)
        finally:
            rig.close()
        peer_cpu, peer_bytes_per_s, peer_wakeups_per_s = map(float, peer.stdout.split())
    print("| process | CPU (% of a core) | ratio to peer | traffic |")
    print("|---|---|---|---|")
    print(f"| peer: bare asyncio reader of the pty | {peer_cpu:.2f} | 1.0 | {peer_bytes_per_s:.0f} bytes/s in "
          f"{peer_wakeups_per_s:.0f} reads/s |")
    print(f"| daemon, idle (vented, 50 Hz telemetry) | {daemon_cpu:.2f} | {daemon_cpu / max(peer_cpu, 1e-9):.1f} | "
          f"{frames_per_s:.0f} frames received/s in {reads_per_s:.0f} reads/s |")
    if recorded_cpu is not None:
        print(f"| daemon, idle, recording to an .rrd | {recorded_cpu:.2f} | {recorded_cpu / max(peer_cpu, 1e-9):.1f} | "
              "the same board |")
    print(json.dumps({"daemon_cpu_percent": daemon_cpu, "peer_cpu_percent": peer_cpu, "daemon_reads_per_s": reads_per_s,
                      "peer_reads_per_s": peer_wakeups_per_s, "recording_daemon_cpu_percent": recorded_cpu}))


if __name__ == "__main__":
    main()
