"""``make demo``: the daemon on the simulated board runs a BPH growth scene end to end.

Starts ``phantom daemon --sim`` (the real firmware image in simavr, paced to the wall clock) with a
recording, plays the scene's timeline through the local API, prints a table of each step's target and
reached volume with the time it took, stops the daemon with SIGTERM (it vents) and reads the recording back.

    python -m phantom.cli.demo [--scene host/scenes/bph_growth.toml] [--time-scale 3] [--out out/]
"""

from __future__ import annotations

import argparse
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

from phantom import PhantomError

if TYPE_CHECKING:
    from phantom.host.client import DaemonClient


def _wait_online(client_factory: Callable[[], DaemonClient], process: subprocess.Popen[bytes],
                 timeout_s: float) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if process.poll() is not None:
            raise PhantomError(f"the daemon exited with status {process.returncode} (see the log above)")
        try:
            with client_factory() as client:
                if client.call("status")["link"] == "online":
                    return
        except PhantomError:
            pass
        time.sleep(0.2)
    raise PhantomError(f"the daemon did not reach the board within {timeout_s:g} s")


def main(argv: list[str] | None = None) -> int:
    from phantom.cli.daemon import follow_scene, format_steps
    from phantom.host.client import DaemonClient
    from phantom.host.recording import read_rrd
    from phantom.host.scenes import example_scene_path

    parser = argparse.ArgumentParser(prog="python -m phantom.cli.demo", description=__doc__.splitlines()[0])
    parser.add_argument("--scene", default=str(example_scene_path("bph_growth")))
    parser.add_argument("--time-scale", type=float, default=3.0, help="play the timeline this much faster")
    parser.add_argument("--out", default="out", help="folder for the recording, socket and log")
    args = parser.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    sock, recording = out / "demo.sock", out / "demo.rrd"
    phantom = Path(sys.executable).with_name("phantom")
    command = [str(phantom), "daemon", "--sim", "--scene", args.scene, "--socket", str(sock),
               "--rerun-save", str(recording)]
    print("$ " + " ".join(command), file=sys.stderr)
    started = time.monotonic()
    log_path = out / "daemon.log"
    log = open(log_path, "w")
    process = subprocess.Popen(command, stdout=log, stderr=subprocess.STDOUT)
    try:
        _wait_online(lambda: DaemonClient(sock), process, 120)
        print(f"daemon ready and online in {time.monotonic() - started:.1f} s", file=sys.stderr)
        with DaemonClient(sock) as client:
            run = client.call("run_scene", {"path": str(Path(args.scene).resolve()), "time_scale": args.time_scale})
            print(f"running {run['name']}: {run['steps']} steps, {run['end_s']:g} s of timeline in about "
                  f"{run['wall_duration_s']:.0f} s", file=sys.stderr)
            status = follow_scene(client, run["name"], args.time_scale)
        steps = status["scene"]["steps"]
        faults = status["faults"]
    finally:
        if process.poll() is None:
            process.send_signal(signal.SIGTERM)
            process.wait(30)
        log.close()
        print(f"\ndaemon log ({log_path}):", file=sys.stderr)
        print(log_path.read_text(), file=sys.stderr)
    print(f"BPH growth on the simulated board (firmware in simavr), timeline x{args.time_scale:g}; "
          "'time to 1 %' counts from the step's start (ramp included), in wall seconds:")
    print(format_steps(steps))
    entities = read_rrd(recording)
    logged = sum(len(columns.get("time", [])) for columns in entities.values())
    print(f"\nrecording {recording}: {len(entities)} entities, {logged} logged rows "
          f"(open it with `rerun {recording}`); faults: {', '.join(faults) or 'none'}; "
          f"daemon exit status {process.returncode}")
    missed = [step for step in steps if step["error_pct"] is None or abs(step["error_pct"]) > 1.0]
    return 1 if missed or process.returncode != 0 else 0


if __name__ == "__main__":
    try:
        sys.exit(main())
    except PhantomError as error:
        print(f"make demo: error: {error}", file=sys.stderr)
        sys.exit(2)
