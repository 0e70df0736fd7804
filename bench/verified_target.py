"""How long one verified target takes on the simulated board (scan, reconstruct, correct, apply again), with
its rounds, against the same target reached on pressure alone, measured in the same run.

Starts ``phantom daemon --sim`` (the firmware in simavr, the simulated phantom the measured one) with a data
directory of its own, sets each target first without verify (the peer: reached on pressure, the model's volume)
and then with ``verify="scan"``, and prints per target: the time to reach on pressure, the verified target's
wall time and rounds, and per round the scanned and true volume. The first scan of a daemon also builds the
truth shape's worker and solves it from rest (the simulated phantom's cost, not the loop's): it is the first row.

Run: ``.venv/bin/python bench/verified_target.py [--targets 40,35]``
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import tempfile
import time
from pathlib import Path

import phantom
from phantom.cli.demo import sim_daemon
from phantom.host.client import VerifyError


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--targets", default="40,35", help="target volumes (ml), comma-separated")
    args = parser.parse_args()
    targets = [float(value) for value in args.targets.split(",")]
    with tempfile.TemporaryDirectory() as scratch:
        with sim_daemon(Path(scratch)) as socket:
            rows = []
            with phantom.connect(socket) as ph:
                for target_ml in targets:
                    started = time.monotonic()
                    plain = ph.set_volume(target_ml, timeout_s=300)
                    plain_s = time.monotonic() - started
                    started = time.monotonic()
                    try:
                        verified = ph.set_volume(target_ml, verify="scan", timeout_s=1800)
                    except VerifyError as error:  # the round limit: its rounds still say how it went
                        print(f"{target_ml:g} ml not verified: {error}", file=sys.stderr)
                        verified = dataclasses.replace(plain, rounds=tuple(error.rounds))
                    rows.append((target_ml, plain_s, plain.true_volume_ml, time.monotonic() - started, verified))
    print(f"{'target ml':>9} {'on pressure s':>13} {'true ml':>8} | {'verified s':>10} {'rounds':>6} "
          f"{'x pressure':>10} | per round: scanned / true ml")
    for target_ml, plain_s, plain_true_ml, verified_s, result in rows:
        per_round = "; ".join(f"{entry.get('scanned_volume_ml', float('nan')):.3f} / "
                              f"{entry.get('true_volume_ml', float('nan')):.3f}" for entry in result.rounds)
        print(f"{target_ml:>9.2f} {plain_s:>13.1f} {plain_true_ml or float('nan'):>8.3f} | {verified_s:>10.1f} "
              f"{len(result.rounds):>6} {verified_s / plain_s:>10.1f} | {per_round}")


if __name__ == "__main__":
    main()
