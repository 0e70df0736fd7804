"""How late the daemon's loops run while a verified target scans, learns and applies again, idle and with one
busy process per core beside it (issue 48, "the link holds while the phantom learns"), against the same target
held without verify for as long (the peer: what the machine and the daemon's link cost without a scan).

Per row, a fresh ``phantom daemon --sim --sim-speed 2`` (the firmware in simavr, the shipped simulated phantom)
with an empty measurement store is asked one volume, with ``verify="scan"`` (each round: the capture, the
reconstruction, the correction's fit) or, for the peer row, without verify and then held for ``--hold-s``; this
script polls the daemon's status twice a second meanwhile. From the status's lists of probes later than 10 ms it
takes, over the verify or the hold only (not the start-up), the longest lateness of a 20 ms timer on the daemon's
event loop (``event_loop``), on the board link's loop (its own process: ``link_detail.event_loop``, the one
whose silence past 500 ms makes the board latch DEAD_HOST) and how many probes of the link's loop were later than
100 ms, the longest three of each loop with what they were made of (waiting for a core, the garbage collector);
and the longest lateness of the same timer in a bare process that does nothing else (what the machine's
scheduling alone costs). With busy processes, ``--busy N`` pure-Python loops run at normal priority beside the
daemon from before the target is set until it is answered (or the hold ends). A hold ends early on a fault.

    .venv/bin/python bench/verify_loop_stalls.py [--target 35] [--busy 0,2] [--hold-s 90] [--logs DIR]
                                                 [--link-rt-priority N]   (0: the link at the daemon's priority)

About 2-3 minutes a verify row and two a hold row. Prints a Markdown table (bench/README.md, "A verified
target's scan beside busy cores").
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import phantom
from phantom.cli.demo import stop_daemon, wait_until_ready
from phantom.host.client import DaemonClient, DaemonError

#: A bare process's 20 ms timer: prints its longest lateness (ms) when its stdin closes.
BARE_PEER = """
import sys, threading, time
longest = 0.0
done = threading.Event()
threading.Thread(target=lambda: (sys.stdin.read(), done.set()), daemon=True).start()
while not done.is_set():
    due = time.monotonic() + 0.02
    time.sleep(0.02)
    longest = max(longest, (time.monotonic() - due) * 1e3)
print(longest)
"""


class StallWatch:
    """The daemon's status polled from a thread: each loop's probes later than 10 ms, on the monotonic clock of
    this process (the status says how long ago each was), kept between :meth:`start` and :meth:`stop`."""

    def __init__(self, socket: Path):
        self.socket = socket
        self.stalls: dict[str, dict[float, float]] = {"daemon": {}, "link": {}}
        #: each stall's parts: ms its thread waited for a core, ms the garbage collector ran
        self.causes: dict[str, dict[float, list[Any]]] = {"daemon": {}, "link": {}}
        self.gc: dict[str, Any] = {}
        self.scheduling = "a thread of the daemon"
        self.faults: set[str] = set()
        self._from_s = float("inf")
        self._to_s = float("inf")
        self._done = threading.Event()
        self._thread = threading.Thread(target=self._poll, daemon=True)

    def start(self) -> None:
        self._from_s = time.monotonic()
        self._thread.start()

    def stop(self) -> None:
        """Stop polling, after one last status (the stalls and a fault up to the verify's answer)."""
        self._to_s = time.monotonic()
        self._done.set()
        self._thread.join(10)
        with DaemonClient(self.socket) as client:
            self._take(client)

    def _poll(self) -> None:
        with DaemonClient(self.socket) as client:
            while not self._done.wait(0.5):
                self._take(client)

    def _take(self, client: DaemonClient) -> None:
        try:
            status = client.call("status")
        except (DaemonError, OSError):
            return
        now_s = time.monotonic()
        self.faults.update(status.get("faults") or ())
        self.gc = (status.get("event_loop") or {}).get("gc") or self.gc
        self.scheduling = ((status.get("link_detail") or {}).get("process") or {}).get("scheduling",
                                                                                      self.scheduling)
        for name, figures in (("daemon", status.get("event_loop")),
                              ("link", (status.get("link_detail") or {}).get("event_loop"))):
            for ago_s, late_ms, *causes in (figures or {}).get("notable_stalls", []):
                self.stalls[name][round(now_s - ago_s, 2)] = late_ms
                self.causes[name][round(now_s - ago_s, 2)] = causes

    def during(self, name: str) -> list[float]:
        """The loop's stalls (ms) from :meth:`start` to :meth:`stop`."""
        return [late for at_s, late in self.stalls[name].items() if self._from_s <= at_s <= self._to_s]

    def worst(self, name: str, count: int = 3) -> list[str]:
        """The loop's longest stalls from :meth:`start` to :meth:`stop`, each with what it was made of."""
        stalls: list[tuple[float, float]] = []
        for late, at_s in sorted(((late, at_s) for at_s, late in self.stalls[name].items()
                                  if self._from_s <= at_s <= self._to_s), reverse=True):
            # one stall seen in several polls (its age rounded differently each time) is listed once
            if not any(late == seen and abs(at_s - seen_at_s) < 0.5 for seen, seen_at_s in stalls):
                stalls.append((late, at_s))
        described = []
        for late, at_s in stalls[:count]:
            causes = list(self.causes[name].get(at_s) or [])
            queued_ms, gc_ms, ran_ms, faults, stolen_ms, blocked = (causes + [None] * 6)[:6]
            said = [f"{'?' if value is None else f'{value:.0f}'}{unit}" for value, unit in
                    ((queued_ms, " ms waiting for a core"), (gc_ms, " ms in the garbage collector"),
                     (ran_ms, " ms on a core"), (faults, " major page faults"),
                     (stolen_ms, " ms stolen by the hypervisor"))]
            if blocked:
                said.append(f"seen in {blocked}")
            described.append(f"{late:.0f} ms at +{at_s - self._from_s:.0f} s ({', '.join(said)})")
        return described


def one_row(target_ml: float, busy: int, hold_s: float | None, logs: Path | None,
            daemon_flags: tuple[str, ...] = ()) -> dict[str, Any]:
    """One daemon asked ``target_ml`` with verify (``hold_s`` None), or without and held ``hold_s``."""
    with tempfile.TemporaryDirectory() as scratch:
        folder = Path(scratch)
        log_path, sock = folder / "daemon.log", folder / "d.sock"
        with open(log_path, "w") as log:
            process = subprocess.Popen([str(Path(sys.executable).with_name("phantom")), "daemon", "--sim",
                                        "--sim-speed", "2", "--socket", str(sock), *daemon_flags], stdout=log,
                                       stderr=subprocess.STDOUT, env={**os.environ,
                                                                      "PHANTOM_DATA_DIR": str(folder / "data")})
            load: list[subprocess.Popen[bytes]] = []
            peer = subprocess.Popen([sys.executable, "-c", BARE_PEER], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                    text=True)
            try:
                wait_until_ready(sock, process, log_path)
                load = [subprocess.Popen([sys.executable, "-c", "while True:\n    pass\n"]) for _ in range(busy)]
                watch = StallWatch(sock)
                load_before = os.getloadavg()[0]
                started = time.monotonic()
                watch.start()
                error = ""
                rounds: list[dict[str, Any]] = []
                verified = False
                with phantom.connect(sock) as ph:
                    try:
                        if hold_s is None:
                            result = ph.set_volume(target_ml, verify="scan", timeout_s=1700)
                            rounds, verified = list(result.rounds), bool(result.verified)
                        else:
                            ph.set_volume(target_ml, timeout_s=300)
                            while time.monotonic() < started + hold_s and not ph.status().faults:
                                time.sleep(1.0)
                    except DaemonError as failed:
                        error = str(failed)
                        rounds = list(getattr(failed, "rounds", []) or [])
                watch.stop()
                seconds = time.monotonic() - started
                load_after = os.getloadavg()[0]
            finally:
                for busy_process in load:
                    busy_process.kill()
                    busy_process.wait()
                peer_out, _ = peer.communicate("", timeout=30)
                stop_daemon(process)
                if logs is not None:
                    logs.mkdir(parents=True, exist_ok=True)
                    shutil.copy(log_path, logs / f"daemon_busy{busy}_{'verify' if hold_s is None else 'hold'}_"
                                            f"{time.strftime('%H%M%S')}.log")
        daemon_ms, link_ms = watch.during("daemon"), watch.during("link")
        true_ml = rounds[-1].get("true_volume_ml") if rounds else None
        return {"busy": busy, "what": "verify" if hold_s is None else f"hold {hold_s:g} s",
                "load": f"{load_before:.1f}-{load_after:.1f}", "seconds": seconds, "rounds": len(rounds),
                "verified": verified, "true_pct": None if true_ml is None else (true_ml - target_ml) / target_ml * 100,
                "daemon_ms": max(daemon_ms, default=0.0), "link_ms": max(link_ms, default=0.0),
                "link_over_100": sum(late > 100 for late in link_ms), "peer_ms": float(peer_out.strip() or "nan"),
                "faults": ", ".join(sorted(watch.faults)) or "none", "error": error,
                "link_worst": watch.worst("link"), "daemon_worst": watch.worst("daemon"), "gc": watch.gc,
                "scheduling": watch.scheduling}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--target", type=float, default=35.0, help="the verified volume (ml)")
    parser.add_argument("--busy", default=f"0,{os.cpu_count() or 2}",
                        help="busy processes beside the daemon, one row each (comma-separated)")
    parser.add_argument("--logs", type=Path, help="keep each row's daemon log in this folder")
    parser.add_argument("--hold-s", type=float, default=90.0, help="how long the peer row holds the target (s)")
    parser.add_argument("--link-rt-priority", type=int,
                        help="the daemon's link_rt_priority (default: its own; 0: the link's process at the daemon's "
                             "priority)")
    args = parser.parse_args()
    flags = () if args.link_rt_priority is None else ("--link-rt-priority", str(args.link_rt_priority))
    rows = [one_row(args.target, int(busy), hold_s, args.logs, flags) for busy in args.busy.split(",")
            for hold_s in (args.hold_s, None)]
    print(f"`{Path(sys.argv[0]).name} --target {args.target:g} --busy {args.busy} --hold-s {args.hold_s:g}"
          f"{'' if not flags else ' ' + ' '.join(flags)}`, "
          f"{time.strftime('%Y-%m-%d %H:%M')} UTC, {os.cpu_count()} cores\n")
    print("| busy processes | asked | load (1 min) | seconds | rounds | verified | true error % | daemon's loop: "
          "longest stall (ms) | link's loop (ms) | link's probes > 100 ms | bare peer process (ms) | faults |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for row in rows:
        true_pct = "-" if row["true_pct"] is None else f"{row['true_pct']:+.2f}"
        print(f"| {row['busy']} | {row['what']} | {row['load']} | {row['seconds']:.0f} | {row['rounds']} | "
              f"{row['verified'] if row['what'] == 'verify' else '-'} | {true_pct} | {row['daemon_ms']:.0f} | "
              f"{row['link_ms']:.0f} | {row['link_over_100']} | {row['peer_ms']:.0f} | {row['faults']} |")
        if row["error"]:
            print(f"\n(busy {row['busy']}, {row['what']}: {row['error']})\n")
    print()
    for row in rows:
        print(f"- busy {row['busy']}, {row['what']}, the link's process {row['scheduling']}: its loop's longest "
              f"stalls: "
              f"{'; '.join(row['link_worst']) or 'none'}; the daemon's: {'; '.join(row['daemon_worst']) or 'none'}; "
              f"the garbage collector: {row['gc']}")


if __name__ == "__main__":
    main()
