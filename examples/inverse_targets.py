"""Step through the paper's inverse targets on a running daemon and print, for each one, the target, the volume
the controller estimates once it is reached, and the true volume of the simulated plant.

The targets are those of Tian, Adagolodjo and Dequidt's inverse experiment (Fig. 8: 26, 30, 35, 40 and 45 ml).
Each is set through the Python API with ``wait=True``: the call returns once the estimate (the model at the
measured pressures) is within the tolerance and the pressures have settled. A target the model cannot reach
within the pressure limit is reported with the reachable range, and the script goes on.

    phantom daemon --sim &                       # the simulated board (or --port /dev/... for a real one)
    python examples/inverse_targets.py           # [--socket PATH] [--tolerance-pct 1] [--targets-ml 26,30]

"true" is the simulated plant's own gland volume (its chambers follow the calibrated model with a stiffer
modulus the controller does not know): the model's error, which pressure control alone cannot see. On a real
board there is none, and the column shows "-".
"""

from __future__ import annotations

import argparse
import sys

import phantom
from phantom.host.client import UnreachableError

#: The paper's inverse targets (ml).
PAPER_TARGETS_ML = (26.0, 30.0, 35.0, 40.0, 45.0)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--socket", help="the daemon's socket (default: where `phantom daemon` listens)")
    parser.add_argument("--targets-ml", default=",".join(f"{v:g}" for v in PAPER_TARGETS_ML),
                        help="comma-separated gland volumes (ml); default the paper's")
    parser.add_argument("--tolerance-pct", type=float, default=1.0, help="how close the estimate must come (%%)")
    parser.add_argument("--timeout-s", type=float, default=120.0, help="how long to wait for each target (s)")
    args = parser.parse_args(argv)
    targets_ml = [float(text) for text in args.targets_ml.split(",")]

    with phantom.connect(args.socket, on_wait=lambda what: print(f"waiting for the daemon: {what}",
                                                                   file=sys.stderr)) as ph:
        status = ph.status()
        print(f"daemon: model on {status.fidelity}, rest volume {status.rest_volume_ml:.2f} ml, link {status.link}")
        print(f"{'target ml':>9} {'estimate ml':>11} {'error %':>8} {'true ml':>8} {'true error %':>12} "
              f"{'time s':>6}  pressures kPa")
        for target_ml in targets_ml:
            try:
                result = ph.set_volume(target_ml, tolerance_pct=args.tolerance_pct, timeout_s=args.timeout_s)
            except UnreachableError as error:
                low, high = error.range_ml or (float("nan"), float("nan"))
                print(f"{target_ml:9.2f}  unreachable: the model reaches {low:.2f}-{high:.2f} ml within the pressure "
                      "limit")
                continue
            assert result.estimated_volume_ml is not None  # waited: there is an estimate
            error_pct = 100 * (result.estimated_volume_ml - target_ml) / target_ml
            true = "-" if result.true_volume_ml is None else f"{result.true_volume_ml:.2f}"
            true_error = "-" if result.true_volume_ml is None else (
                f"{100 * (result.true_volume_ml - target_ml) / target_ml:+.2f}")
            pressures = ", ".join(f"{p:.2f}" for p in result.pressures_kpa)
            print(f"{target_ml:9.2f} {result.estimated_volume_ml:11.2f} {error_pct:+8.2f} {true:>8} {true_error:>12} "
                  f"{result.waited_s or 0.0:6.1f}  {pressures}")
        ph.vent()
    return 0


if __name__ == "__main__":
    try:
        sys.exit(main())
    except phantom.PhantomError as error:
        print(f"inverse_targets: error: {error}", file=sys.stderr)
        sys.exit(2)
