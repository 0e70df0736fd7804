"""The daemon's memory while it records: RSS of the daemon and of its model worker over time.

Runs ``phantom daemon --sim --rerun-save`` on a scene that asks for the shape (so the mesh is computed and logged
at --mesh-hz, the heaviest recording), moves the target between 30 and 40 ml every 30 s, and samples the
resident set size (/proc/PID/status VmRSS) of the daemon and of the worker every ``--every-s`` seconds. Prints a
table (minutes, daemon MB, worker MB, recording MB) and the daemon's growth per minute over the second half of
the run against the first half's (a bounded daemon grows at first, then levels off).

    .venv/bin/python bench/daemon_memory.py --minutes 10          # the run bench/README.md reports
"""

from __future__ import annotations

import argparse
import contextlib
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from phantom.host.client import DaemonClient, DaemonError
from phantom.model.scene import builtin_scene_path

PHANTOM = Path(sys.executable).with_name("phantom")


def rss_mb(pid: int) -> float | None:
    """Resident set size of a process (MB), None when it is gone."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    except OSError:
        return None
    return None


def children(pid: int) -> list[int]:
    found = []
    for task in Path(f"/proc/{pid}/task").iterdir():
        found += [int(child) for child in (task / "children").read_text().split()]
    return found


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--minutes", type=float, default=10.0, help="how long to record (default 10)")
    parser.add_argument("--every-s", type=float, default=30.0, help="sampling period (s, default 30)")
    parser.add_argument("--mesh-hz", type=float, default=1.0, help="mesh logging rate (default 1, the daemon's)")
    args = parser.parse_args()
    folder = Path(tempfile.mkdtemp(prefix="daemon-memory-"))
    scene = folder / "scene.toml"
    scene.write_text(builtin_scene_path("builtin:calibrated").read_text().replace("shape = false", "shape = true"))
    sock, recording = folder / "d.sock", folder / "run.rrd"
    log = open(folder / "daemon.log", "w")
    daemon = subprocess.Popen([str(PHANTOM), "daemon", "--sim", "--scene", str(scene), "--socket", str(sock),
                               "--rerun-save", str(recording), "--mesh-hz", str(args.mesh_hz)],
                              stdout=log, stderr=subprocess.STDOUT)
    rows: list[tuple] = []
    refusals = 0
    try:
        deadline = time.monotonic() + 120
        while True:
            try:
                with DaemonClient(sock, timeout_s=10) as client:
                    if client.call("status")["link"] == "online":
                        break
            except Exception:
                pass
            if time.monotonic() > deadline or daemon.poll() is not None:
                raise SystemExit(f"the daemon did not come online; see {log.name}")
            time.sleep(0.5)
        # the pool's worker, not multiprocessing's resource tracker: the one holding the model
        worker = max((pid for pid in children(daemon.pid) if b"multiprocessing" in Path(
            f"/proc/{pid}/cmdline").read_bytes()), key=lambda pid: rss_mb(pid) or 0.0)
        started = time.monotonic()
        next_target_s, target_ml = 0.0, 30.0
        while (elapsed := time.monotonic() - started) <= args.minutes * 60 + 1:
            if elapsed >= next_target_s:
                with DaemonClient(sock, timeout_s=10) as client:
                    try:
                        client.call("set_target", {"volume_ml": target_ml})
                    except DaemonError as error:
                        # a loaded machine can make the simulated board latch a fault: counted, cleared
                        refusals += 1
                        print(f"set_target refused ({error}); clearing faults", file=sys.stderr)
                        with contextlib.suppress(DaemonError):
                            client.call("clear_fault")
                target_ml = 70.0 - target_ml
                next_target_s += 30.0
            if not rows or elapsed >= len(rows) * args.every_s:
                with DaemonClient(sock, timeout_s=10) as client:
                    meshes = client.call("status").get("meshes_logged")
                rows.append((elapsed / 60, rss_mb(daemon.pid), rss_mb(worker),
                             recording.stat().st_size / 1e6 if recording.exists() else 0.0, meshes))
                print(f"{rows[-1][0]:7.2f} min  daemon {rows[-1][1]:7.1f} MB  worker {rows[-1][2]:7.1f} MB  "
                      f"recording {rows[-1][3]:7.1f} MB  meshes {meshes}", file=sys.stderr, flush=True)
            time.sleep(1.0)
    finally:
        daemon.send_signal(signal.SIGTERM)
        daemon.wait(30)
        log.close()
    print(f"daemon --sim --rerun-save, a scene with shape = true, --mesh-hz {args.mesh_hz:g}, target 30 <-> 40 ml "
          f"every 30 s, {args.minutes:g} min:")
    if refusals:
        print(f"({refusals} target(s) refused by a latched fault, cleared)")
    print(f"{'minutes':>7} {'daemon RSS MB':>13} {'worker RSS MB':>13} {'recording MB':>12} {'meshes':>7}")
    for minutes, daemon_mb, worker_mb, recording_mb, meshes in rows:
        print(f"{minutes:7.1f} {daemon_mb:13.1f} {worker_mb:13.1f} {recording_mb:12.1f} {meshes!s:>7}")
    half = len(rows) // 2
    if half >= 2:
        def slope(part):
            (t0, m0, *_), (t1, m1, *_) = part[0], part[-1]
            return (m1 - m0) / (t1 - t0) if t1 > t0 else float("nan")
        print(f"daemon growth: {slope(rows[:half + 1]):+.2f} MB/min over the first half, "
              f"{slope(rows[half:]):+.2f} MB/min over the second")
    return 0


if __name__ == "__main__":
    sys.exit(main())
