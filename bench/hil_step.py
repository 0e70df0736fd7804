"""Step responses 0 -> 2 kPa of the real firmware in simavr on the default plant, per chamber and per gain set.

Prints rise time, overshoot, 2 % settling time and steady-state error for the firmware's default gains and
for other gain sets sent with SET_PID (default: 2, 3, 0, the firmware's first defaults), against the targets
(settle < 1 s, overshoot < 5 %, error < one ADC count = 0.054 kPa), and writes out/hil_step.png (defaults) and
out/hil_step_other.png (the other sets).

    .venv/bin/python bench/hil_step.py [--gains KP,KI,KD ...] [--plant PLANT.toml] [--chambers 0 1 2]
"""

import argparse
from pathlib import Path

from phantom.hil import bench
from phantom.hil.link import BoardLink
from phantom.hil.sim import SimulatedBoard


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--gains", nargs="*", default=["2,3,0"], help="KP,KI,KD sets to try besides the defaults")
    parser.add_argument("--out", default="out/hil_step.png", help="plot path")
    parser.add_argument("--plant", help="plant parameter file (default hil/plant.toml)")
    parser.add_argument("--chambers", nargs="*", type=int, default=[0, 1, 2], help="chambers to step")
    args = parser.parse_args()
    gain_sets = [None] + [tuple(float(v) for v in g.split(",")) for g in args.gains]
    steps = []
    with SimulatedBoard(plant=args.plant, speed=1.0) as board, BoardLink(board.port) as link:
        for gains in gain_sets:
            for chamber in args.chambers:
                bench.progress(f"gains {gains or 'default'}, chamber {chamber}")
                steps.append(bench.check_step(link, chamber, 2.0, duration_s=2.5, gains=gains))
    print("| gains kp, ki, kd | chamber | rise s | overshoot % | settling 2 % s | error kPa | meets targets |")
    print("|---|---|---|---|---|---|---|")
    for s in steps:
        meets = bench.step_within_thresholds(s)
        gains = "firmware default" if s["gains"] is None else ", ".join(f"{g:g}" for g in s["gains"])
        settling = "n/a" if s["settling_time_s"] is None else f"{s['settling_time_s']:.2f}"
        print(f"| {gains} | {s['chamber']} | {s['rise_time_s']:.3f} | {s['overshoot_pct']:.2f} | {settling} | "
              f"{s['steady_state_error_kpa']:+.4f} | {'yes' if meets else 'no'} |")
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    bench.plot_steps([s for s in steps if s["gains"] is None], out, board="simulated (simavr)")
    plots = [out]
    if len(gain_sets) > 1:
        plots.append(out.with_name(out.stem + "_other.png"))
        bench.plot_steps([s for s in steps if s["gains"] is not None], plots[-1], board="simulated (simavr)")
    print(f"\nplots: {', '.join(map(str, plots))}")


if __name__ == "__main__":
    main()
