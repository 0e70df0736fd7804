"""A verify scan's reconstruction right after an idle wait, as the daemon's scan worker does it (idle while the rig
moves, then carving), with numpy's huge-page advice on and off.

numpy asks the kernel for transparent huge pages on its large arrays (``madvise(MADV_HUGEPAGE)``; the environment
variable ``NUMPY_MADVISE_HUGEPAGE``, read when numpy is imported, turns it off). Where the kernel's
``transparent_hugepage/defrag`` is ``madvise`` (Debian's and Ubuntu's default), a fault on such an array compacts
memory for a huge page on the spot. Each setting runs in a process of its own: the verify plan's capture of the
shipped simulated phantom at 40 ml (the virtual camera, 20 stops at 15 and 45 deg of 640x480), its silhouettes
keyed once, then the reconstruction (``phantom.scan.reconstruct``, as the worker's after a verify capture) timed
back to back and after ``--idle-s`` of sleep, in turn. Prints a table: the carve's and the whole reconstruction's
median seconds and the system CPU seconds, each way, and the kernel's settings.

    .venv/bin/python bench/carve_after_idle.py [--idle-s 8] [--repeats 4]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

#: The pressures (kPa) the controller holds for 40 ml (make demo's daemon log).
STATE_KPA = (0.798, 2.588, 2.588)


def measure(folder: Path, idle_s: float, repeats: int) -> dict[str, list[float]]:
    """In this process: the capture in ``folder`` reconstructed after each pause (0, then ``idle_s``, in turn),
    ``repeats`` times each; by pause, the carve's seconds, the whole reconstruction's and its system CPU seconds."""
    import resource
    import time

    from phantom.scan.capture import CaptureFolder
    from phantom.scan.reconstruct import reconstruct
    from phantom.scan.silhouette import silhouette

    capture = CaptureFolder.open(folder)
    rig = capture.rig()
    assert rig is not None
    keyed = {frame.image: silhouette(capture.image(frame)) for frame in capture.frames}
    reconstruct(capture, rig, keyed=keyed)  # the kernels loaded
    found: dict[str, list[float]] = {}
    for _ in range(repeats):
        for pause_s in (0.0, idle_s):
            time.sleep(pause_s)
            before, started = resource.getrusage(resource.RUSAGE_SELF), time.perf_counter()
            result = reconstruct(capture, rig, keyed=keyed)
            took_s = time.perf_counter() - started
            system_s = resource.getrusage(resource.RUSAGE_SELF).ru_stime - before.ru_stime
            for name, value in (("carve", result.stage_s["carve"]), ("all", took_s), ("system", system_s)):
                found.setdefault(f"{name} {pause_s:g}", []).append(value)
    return found


def kernel_setting(name: str) -> str:
    try:
        return Path(f"/sys/kernel/mm/transparent_hugepage/{name}").read_text().strip()
    except OSError:
        return "(not readable)"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--idle-s", type=float, default=8.0, help="the pause before every other reconstruction")
    parser.add_argument("--repeats", type=int, default=4)
    parser.add_argument("--measure", default=None, help=argparse.SUPPRESS)  # a child's folder
    args = parser.parse_args()
    if args.measure:
        print(json.dumps(measure(Path(args.measure), args.idle_s, args.repeats)))
        return

    import numpy as np

    from phantom.cli.scan_verify import VERIFY_PLAN
    from phantom.hil.simulated_truth import SimulatedTruth
    from phantom.scan.camera import virtual_rig
    from phantom.scan.capture import Plan
    from phantom.scan.virtual import render_capture

    print(f"transparent huge pages: enabled {kernel_setting('enabled')}, defrag {kernel_setting('defrag')}")
    elevations = tuple(float(e) for e in VERIFY_PLAN["elevations_deg"])
    rig = virtual_rig(VERIFY_PLAN["scale"], elevations)
    with tempfile.TemporaryDirectory() as scratch:
        folder = Path(scratch) / "scan"
        render_capture(SimulatedTruth().shape().surface(STATE_KPA), rig, Plan(VERIFY_PLAN["views"], elevations),
                       folder)
        print(f"the verify plan's capture at {', '.join(map(str, STATE_KPA))} kPa: "
              f"{VERIFY_PLAN['views'] * len(elevations)} pictures\n")
        print(f"| numpy's huge-page advice | carve, back to back (s) | carve after {args.idle_s:g} s idle (s) | "
              "reconstruction, back to back / after idle (s) | system CPU, back to back / after idle (s) |")
        print("|---|---|---|---|---|")
        for advice in ("1", "0"):
            child = subprocess.run([sys.executable, __file__, "--measure", str(folder), "--idle-s",
                                    str(args.idle_s), "--repeats", str(args.repeats)],
                                   env={**os.environ, "NUMPY_MADVISE_HUGEPAGE": advice}, capture_output=True,
                                   text=True, check=True)
            found = json.loads(child.stdout.splitlines()[-1])
            busy, idle = "0", f"{args.idle_s:g}"

            def median(name: str, pause: str, found: dict[str, list[float]] = found) -> float:
                return float(np.median(found[f"{name} {pause}"]))

            print(f"| {'on' if advice == '1' else 'off'} | {median('carve', busy):.2f} | "
                  f"{median('carve', idle):.2f} | {median('all', busy):.2f} / {median('all', idle):.2f} | "
                  f"{median('system', busy):.2f} / {median('system', idle):.2f} |", flush=True)
        print(f"\nmedians of {args.repeats} each")


if __name__ == "__main__":
    main()
