"""Where a verified round's time goes on the simulated board: per picture of the verify scan (the move, the settle
wait, the pressures, the rig's angles, the picture rendered, written), per round (the capture, its
reconstruction, the rest: the correction's fit, the solve, the pressures' settle), against the board's own time
for the moves (the axes' trapezoidal profile, ``phantom.protocol.motion.SCANNER_AXES``) measured in the same run.

Starts ``phantom daemon --sim`` (the firmware in simavr, real time) with a data directory of its own, holds a
target on pressure, then takes the verify plan's scan (``VerifyScan().plan_for(0.3)``) through the daemon's
``scan`` method twice (the first also starts the scan worker and the truth shape: reported apart), reads each
picture's ``stage_s`` from capture.json, reconstructs the second in this process (the worker's code, not its
process) from the folder (``phantom scan reconstruct``'s way, every picture read back and keyed) and as the
worker does after a verify scan (each picture keyed as it was written, timed apart: the capture's pictures thread
does it while the rig moves; then only the carving and the surface), each twice in turn (the faster kept),
checks that the two volumes are one, and sets one verified target (``verify="scan"``) for the round's whole
time, each round's capture time read from its folder.

Run: ``.venv/bin/python bench/scan_round.py [--target 35] [--no-verify]``
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import phantom
from phantom.cli.demo import sim_daemon
from phantom.cli.scan_verify import VerifyScan
from phantom.host.client import Phantom, VerifyError
from phantom.protocol.motion import SCANNER_AXES
from phantom.scan.capture import STAGES, CaptureFolder
from phantom.scan.keying import KeyedPictures
from phantom.scan.reconstruct import Reconstruction, reconstruct


def board_moves_s(folder: CaptureFolder, start_deg: tuple[float, float]) -> list[float]:
    """Each picture's move on the board's profile (s), the elevation's then the orbit's, from where the rig was
    before it (the first from ``start_deg``, the orbit's and the elevation's angles before the scan)."""
    orbit, elevation = SCANNER_AXES
    where = start_deg
    times = []
    for frame in folder.frames:
        times.append(elevation.move_s(frame.elevation_deg - where[1]) + orbit.move_s(frame.orbit_deg - where[0]))
        where = (frame.orbit_deg, frame.elevation_deg)
    return times


def scan(ph: Phantom, out: Path, plan: dict[str, object]) -> tuple[float, CaptureFolder, tuple[float, float]]:
    """The scan's wall time (s), its folder and where the rig was before it (deg)."""
    axes = ph.call("motion_status")["axes"]
    start_deg = (float(axes[0].get("position_deg", 0.0)), float(axes[1].get("position_deg", 0.0)))
    started = time.monotonic()
    ph.call("scan", {"out": str(out), **plan})
    return time.monotonic() - started, CaptureFolder.open(out), start_deg


def picture_table(wall_s: float, folder: CaptureFolder, start_deg: tuple[float, float]) -> None:
    frames = folder.frames
    stages = {name: [(frame.stage_s or {}).get(name, 0.0) for frame in frames] for name in STAGES}
    board = board_moves_s(folder, start_deg)
    count = len(frames)
    print(f"{count} pictures in {wall_s:.1f} s ({wall_s / count:.2f} s a picture)")
    print(f"{'stage':>16} {'mean s':>7} {'max s':>7} {'total s':>8} {'share':>6}")
    for name, values in (("move (board)", board), *stages.items()):
        total = sum(values)
        print(f"{name:>16} {total / count:>7.3f} {max(values):>7.3f} {total:>8.1f} {total / wall_s:>6.0%}")
    moves = stages["move"]
    print(f"{'move - board':>16} {(sum(moves) - sum(board)) / count:>7.3f} "
          f"{max(m - b for m, b in zip(moves, board, strict=True)):>7.3f} {sum(moves) - sum(board):>8.1f} "
          f"{(sum(moves) - sum(board)) / wall_s:>6.0%}")
    # the pictures are rendered and written while the rig moves on: their time is then not the scan's
    overlapped = sum(sum(values) for values in stages.values()) - wall_s
    print(f"{'overlapped':>16} {'':>7} {'':>7} {overlapped:>8.1f} {overlapped / wall_s:>6.0%}  (the stages' sum less "
          f"the scan's time)")


def reconstruction_table(capture: CaptureFolder, verify: VerifyScan) -> float:
    """The folder's reconstruction against the worker's after a verify scan (its pictures keyed as they were
    written): their stages, and the time after the capture's last picture (s), returned. Exits when the two
    volumes differ."""
    rig = verify.rig_for(capture)
    keyed = KeyedPictures()
    keep = keyed.start(capture)
    started = time.monotonic()
    for frame in capture.frames:  # what the capture's pictures thread does after writing each
        keep(frame, capture.image(frame))
    keying_s = time.monotonic() - started
    taken = keyed.take(capture)
    # each twice, in turn, the faster kept: the first pays the imports and the kernels' loading
    timed: dict[str, tuple[float, Reconstruction]] = {}
    for _ in range(2):
        for name, given in (("from the folder", None), ("after the capture", taken)):
            started = time.monotonic()
            result = reconstruct(capture, rig, keyed=given)
            took_s = time.monotonic() - started
            if name not in timed or took_s < timed[name][0]:
                timed[name] = took_s, result
    print(f"\nreconstruction ({len(capture.frames)} pictures; {len(taken)} keyed ahead, {keying_s:.1f} s of keying "
          f"that the capture's pictures thread does while the rig moves, the PNG read back included):")
    for name, (total_s, result) in timed.items():
        stages = ", ".join(f"{stage} {seconds:.2f}" for stage, seconds in result.stage_s.items())
        print(f"{name:>18}: {total_s:5.1f} s ({stages}); {result.volume_ml!r} ml")
    (_, whole), (after_s, ahead) = timed["from the folder"], timed["after the capture"]
    if ahead.volume_ml != whole.volume_ml:
        sys.exit(f"the volumes differ: {ahead.volume_ml!r} ml after the capture, {whole.volume_ml!r} ml from the "
                 "folder")
    return after_s


def round_scans_s(scans: Path) -> list[tuple[float, float]]:
    """Each verified round's capture time (s, its last picture's time_s) and its pictures' keying (s, the ``key``
    stage's sum: done in the capture's pictures thread) from its folder under ``scans``."""
    folders = [CaptureFolder.open(path) for path in sorted(scans.glob("*_round*")) if (path / "capture.json").is_file()]
    return [(folder.frames[-1].time_s, sum((frame.stage_s or {}).get("key", 0.0) for frame in folder.frames))
            for folder in folders if folder.frames]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--target", type=float, default=35.0, help="the volume held while scanning (ml)")
    parser.add_argument("--no-verify", action="store_true", help="skip the verified target (the round's whole time)")
    args = parser.parse_args()
    plan = VerifyScan().plan_for(0.3)
    print(f"verify plan at 0.3 %: {json.dumps(plan)}; load {os.getloadavg()[0]:.1f}")
    with tempfile.TemporaryDirectory() as scratch:
        folder = Path(scratch)
        with sim_daemon(folder) as socket:
            with phantom.connect(socket, request_timeout_s=900) as ph:
                started = time.monotonic()
                ph.set_volume(args.target, timeout_s=300)
                print(f"{args.target:g} ml held on pressure in {time.monotonic() - started:.1f} s")
                cold_s, _, _ = scan(ph, folder / "cold", plan)
                print(f"first scan (starts the scan worker and the truth shape): {cold_s:.1f} s")
                wall_s, capture, start_deg = scan(ph, folder / "warm", plan)
                print("\nthe second scan, per picture:")
                picture_table(wall_s, capture, start_deg)
                reconstruct_s = reconstruction_table(capture, VerifyScan(plan))
                if not args.no_verify:
                    started = time.monotonic()
                    try:
                        rounds = ph.set_volume(args.target, verify="scan", timeout_s=1800).rounds
                    except VerifyError as error:
                        rounds = tuple(error.rounds)
                    verified_s = time.monotonic() - started
                    per_round_s = verified_s / max(len(rounds), 1)
                    scans = round_scans_s(folder / "data" / "scans")
                    scan_s = sum(took_s for took_s, _ in scans) / max(len(scans), 1)
                    each = ", ".join(f"{took_s:.1f} keying {key_s:.1f}" for took_s, key_s in scans)
                    print(f"verified target: {len(rounds)} round(s) in {verified_s:.1f} s, {per_round_s:.1f} s a round"
                          f": its scan {scan_s:.1f} s (capture.json; {each}), "
                          f"the reconstruction after it (as here) {reconstruct_s:.1f} s, the rest (fit, solve, "
                          f"pressures) {per_round_s - scan_s - reconstruct_s:.1f} s")


if __name__ == "__main__":
    main()
