"""CPU cost of the scanner's motion on the phantom's own board, counted exactly by simavr's cycle counter.

The real bench image in simavr against the plant: all three chambers regulating at 2 kPa with telemetry at
50 Hz, and the orbit cruising at each step rate (0: no axis configured, the phantom's own load). For each row:
the CPU use (cycles inside the control tick, the frame receiver and every interrupt handler, counted once where
they nest, over all cycles), the control tick's worst case against its 2 ms (32000 cycles), the step
interrupt's cycles per step, and ticks missed. The peer of the ratio columns is the budget: 25 % of the CPU and
32000 cycles a tick. No GPU is involved.

    .venv/bin/python bench/motion_cycles.py [--duration-s 4] [--rates 0,500,1000,1500,2000,2500]
"""

import argparse
import time

from phantom.hil import bench, motion
from phantom.hil.link import BoardLink
from phantom.hil.sim import SimulatedBoard

CPU_TARGET = 0.25


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--duration-s", type=float, default=4.0, help="board time measured per row")
    parser.add_argument("--rates", default=f"0,500,1000,1500,2000,{motion.MAX_STEP_RATE}",
                        help="orbit step rates to measure (steps/s, comma-separated)")
    args = parser.parse_args()
    rates = [float(r) for r in args.rates.split(",")]
    rows = []
    with SimulatedBoard(speed=1.0) as board, BoardLink(board.port) as link:
        for rate in rates:
            bench.progress(f"measuring with the orbit at {rate:g} steps/s")
            wall = time.monotonic()
            result = motion.measure_cycles(link, board, rate, args.duration_s)
            result["simulated_per_wall"] = (args.duration_s + 2.0) / (time.monotonic() - wall)
            rows.append(result)
    print("| orbit steps/s | steps made | CPU use | CPU / target | tick cycles mean | tick cycles max | "
          "max / budget | step interrupt cycles | ticks missed | stack bytes | sim speed |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        isr = "-" if r["step_isr_cycles_mean"] is None else f"{r['step_isr_cycles_mean']:.0f}"
        print(
            f"| {r['step_rate']:g} | {r['steps']} | {100 * r['cpu_use_fraction']:.1f} % | "
            f"{r['cpu_use_fraction'] / CPU_TARGET:.2f} | {r['control_tick_cycles_mean']:.0f} | "
            f"{r['control_tick_cycles_max']} | {r['control_tick_cycles_max'] / r['control_tick_budget_cycles']:.3f} | "
            f"{isr} | {r['tick_overruns']} | {r['stack_bytes_max']} | {r['simulated_per_wall']:.2f}x |"
        )


if __name__ == "__main__":
    main()
