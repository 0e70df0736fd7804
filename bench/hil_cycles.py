"""CPU cost of the firmware, counted exactly by simavr's cycle counter (no timing, no sampling).

Runs the real image (firmware/build/uno/phantom.elf) against the plant with all three chambers regulating at
2 kPa, for each telemetry rate, and prints cycles per control tick and per telemetry frame, and the CPU use:
the cycles spent inside the control tick, the frame receiver and every interrupt handler (counted once where
they nest), over all cycles. The peer of the ratio column is the budget: 16 MHz / 500 Hz = 32000 cycles per
tick, and the 25 % CPU target.

    .venv/bin/python bench/hil_cycles.py [--duration-s 5]
"""

import argparse
import time

from phantom.hil import bench
from phantom.hil.link import BoardLink
from phantom.hil.sim import SimulatedBoard
from phantom.protocol.messages import CONSTANTS

TICK_BUDGET_CYCLES = 16_000_000 // CONSTANTS["TICK_HZ"]
CPU_TARGET = 0.25


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--duration-s", type=float, default=5.0, help="board time measured per row")
    args = parser.parse_args()
    rows = []
    with SimulatedBoard(speed=1.0) as board, BoardLink(board.port) as link:
        for period_ms in (20, 10):
            bench.progress(f"measuring with telemetry every {period_ms} ms")
            wall = time.monotonic()
            result = bench.measure_cycles(link, board, args.duration_s, period_ms, 2.0)
            result["simulated_per_wall"] = (args.duration_s + 2.0) / (time.monotonic() - wall)
            rows.append(result)
    print("| telemetry | ticks/s | tick cycles mean | tick cycles max | max / budget | frame cycles mean | "
          "frame cycles max | CPU use | CPU / target | sim speed |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(
            f"| {r['telemetry_hz']:.1f} Hz | {r['control_tick_hz']:.1f} | {r['control_tick_cycles_mean']:.0f} | "
            f"{r['control_tick_cycles_max']} | {r['control_tick_cycles_max'] / TICK_BUDGET_CYCLES:.3f} | "
            f"{r['telemetry_frame_cycles_mean']:.0f} | {r['telemetry_frame_cycles_max']} | "
            f"{100 * r['cpu_use_fraction']:.1f} % | {r['cpu_use_fraction'] / CPU_TARGET:.2f} | "
            f"{r['simulated_per_wall']:.2f}x |"
        )
    print()
    print("cycles per call of each timed function (first row):")
    print("| function | calls | mean | max |")
    print("|---|---|---|---|")
    for name, region in rows[0]["regions"].items():
        mean = region["total_cycles"] / region["calls"] if region["calls"] else 0
        print(f"| {name} | {region['calls']} | {mean:.0f} | {region['max_cycles']} |")


if __name__ == "__main__":
    main()
