"""Verified and ``verify="auto"`` targets through the daemon on the simulated board, each judged by the simulated
phantom's TRUE volume: issue 48's ``--sim-truth`` line, and its line after ``phantom characterise``.

Starts ``phantom daemon --sim`` (the firmware in simavr) with a data directory of its own, so the measurement store
starts empty; ``--sim-truth`` makes its phantom another one (hil/truths/lobes_1_1.toml at 0.9 x its modulus: the
lobes' chambers 1.1 x instead of the controller's 1.2; its plant built on first use and cached), else the shipped
one. ``--characterise N`` first calibrates the virtual rig (``phantom scan calibrate --sim``) and runs ``phantom
characterise --path N`` through the daemon. Then sets ``--verified``'s volumes with ``verify="scan"`` and
``--auto``'s with ``verify="auto"``, and prints per target: whether it was scanned, the rounds, the last scanned
volume, the true volume and its error, the correction's 95 % band at the answer and from how many measurements,
and the wall time; ``--json`` writes the rows. ``bench/verify_rounds.py`` is its offline form (seconds, no
simavr; ``--truth PLANT`` another phantom, ``--path N`` a characterisation's stand-in scans).

    .venv/bin/python bench/verify_daemon.py [--sim-truth] [--characterise N] [--verified 26.5,30,35,40,45]
        [--auto 28,32.5,37.5,42.5,47] [--sim-speed 1] [--json rows.json]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import phantom
import phantom.hil
from phantom.cli.demo import VERIFY_TIMEOUT_S, sim_daemon, wait_for_link
from phantom.host.client import DaemonError

SCENE = Path(phantom.hil.__file__).with_name("truths") / "lobes_1_1.toml"
MODULUS_FACTOR = 0.9


def volumes(text: str) -> list[float]:
    return [float(value) for value in text.split(",") if value]


def characterise(folder: Path, socket: Path, points: int) -> str:
    """``phantom characterise --path POINTS`` through the daemon at ``socket`` (its data directory in ``folder``,
    as :func:`sim_daemon` makes it), the virtual rig calibrated first; what it did, in words."""
    phantom_cli = str(Path(sys.executable).with_name("phantom"))
    env = {**os.environ, "PHANTOM_DATA_DIR": str(folder / "data")}
    started_s = time.monotonic()
    subprocess.run([phantom_cli, "scan", "calibrate", "--sim", "--scale", "0.5", "--out", str(folder / "rig.json")],
                   check=True, env=env, stdout=subprocess.DEVNULL)
    subprocess.run([phantom_cli, "characterise", "--path", str(points), "--rig", str(folder / "rig.json"),
                    "--out", str(folder / "characterised"), "--socket", str(socket)], check=True, env=env,
                   stdout=sys.stderr)
    return f", then `phantom characterise --path {points}` ({(time.monotonic() - started_s) / 60:.1f} min)"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--verified", type=volumes, default=[26.5, 30.0, 35.0, 40.0, 45.0],
                        help="volumes (ml) set with verify=\"scan\", first (default make demo's five)")
    parser.add_argument("--auto", type=volumes, default=[28.0, 32.5, 37.5, 42.5, 47.0],
                        help="volumes (ml) set with verify=\"auto\" after them")
    parser.add_argument("--sim-truth", action="store_true",
                        help=f"another phantom as the simulated board's truth: {SCENE.name} at {MODULUS_FACTOR:g} x "
                        "its modulus")
    parser.add_argument("--characterise", type=int, default=0, metavar="N",
                        help="first `phantom characterise --path N` through the daemon (the virtual rig calibrated "
                        "for it)")
    parser.add_argument("--sim-speed", default="1", help="the simulated board's pace (phantom daemon --sim-speed)")
    parser.add_argument("--json", type=Path, default=None, help="also write the rows there")
    args = parser.parse_args()
    rows: list[dict[str, Any]] = []
    started_s = time.monotonic()
    truth = ["--sim-truth", str(SCENE), "--sim-truth-modulus-factor", f"{MODULUS_FACTOR:g}"] if args.sim_truth else []
    characterised = ""
    with tempfile.TemporaryDirectory() as scratch, \
            sim_daemon(Path(scratch), [*truth, "--sim-speed", args.sim_speed]) as socket, \
            phantom.connect(socket) as ph:
        if args.characterise:
            characterised = characterise(Path(scratch), socket, args.characterise)
        for verify, targets in (("scan", args.verified), ("auto", args.auto)):
            for target_ml in targets:
                print(f"{target_ml:g} ml, verify={verify} ...", file=sys.stderr, flush=True)
                wait_for_link(ph)
                target_started_s = time.monotonic()
                row: dict[str, Any] = {"target_ml": target_ml, "verify": verify}
                try:
                    result = ph.set_volume(target_ml, verify=verify, timeout_s=VERIFY_TIMEOUT_S)
                except DaemonError as error:
                    row.update(error=str(error), rounds=len(getattr(error, "rounds", [])))
                else:
                    last = result.rounds[-1] if result.rounds else {}
                    true_ml = last.get("true_volume_ml", result.true_volume_ml)
                    row.update(scanned=bool(result.rounds), rounds=len(result.rounds), verified=result.verified,
                               scanned_ml=result.scanned_volume_ml, true_ml=true_ml,
                               true_error_pct=None if true_ml is None else 100.0 * (true_ml / target_ml - 1.0),
                               band_ml=result.band_ml, measurements=result.measurements,
                               per_round=[(entry.get("scanned_volume_ml"), entry.get("true_volume_ml"))
                                          for entry in result.rounds])
                row["took_s"] = time.monotonic() - target_started_s
                rows.append(row)
                print(f"  {row}", file=sys.stderr, flush=True)
    print(f"\nphantom daemon --sim {' '.join(truth)} --sim-speed {args.sim_speed}, from an empty store"
          f"{characterised}, {(time.monotonic() - started_s) / 60:.1f} min in all:\n")
    print("| target ml | verify | scanned | rounds | last scanned ml | true ml | true error % | band +- ml "
          "(measurements) | s |")
    print("|---|---|---|---|---|---|---|---|---|")
    for row in rows:
        if "error" in row:
            print(f"| {row['target_ml']:g} | {row['verify']} | - | {row['rounds']} | NOT REACHED: {row['error']} "
                  f"| | | | {row['took_s']:.0f} |")
            continue
        scanned = "-" if row["scanned_ml"] is None else f"{row['scanned_ml']:.3f}"
        band = "-" if row["band_ml"] is None else f"{row['band_ml']:.3f} ({row['measurements']})"
        true = "-" if row["true_ml"] is None else f"{row['true_ml']:.3f}"
        off = "-" if row["true_error_pct"] is None else f"{row['true_error_pct']:+.3f}"
        print(f"| {row['target_ml']:g} | {row['verify']} | {'yes' if row['scanned'] else 'no'} | {row['rounds']} | "
              f"{scanned} | {true} | {off} | {band} | {row['took_s']:.0f} |")
    for verify in ("scan", "auto"):
        done = [row for row in rows if row["verify"] == verify and "error" not in row]
        if done:
            errors = [abs(row["true_error_pct"]) for row in done if row["true_error_pct"] is not None]
            print(f"verify={verify}: {len(done)} of {sum(row['verify'] == verify for row in rows)} reached, "
                  f"{sum(row['rounds'] for row in done) / len(done):.2f} rounds on average, "
                  f"{sum(not row['scanned'] for row in done)} not scanned, largest true error "
                  f"{max(errors, default=float('nan')):.3f} %")
    if args.json is not None:
        args.json.write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
