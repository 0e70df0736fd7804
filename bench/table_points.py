"""The response table's cost per point on ``builtin:converged``: grid points solved along a few grid lines as the
table build solves them (each started from the equilibria before it down its grid line), with 1 (the neighbour
itself), 2 (a secant) or 3 (a quadratic) of them in the predictor and Newton's tolerance at a point (relative to
the load: the solver's 1e-9, or the build's ``POINT_TOLERANCE``), each configuration in the same run.

The sample is the points the build needs to reach the lines (i, 0, 0), (6, 0, k) and (3, 3, k) of the 7-point
grid (21 points, 0.5 kPa apart). Per point: CPU time, Newton iterations, and the chamber and gland volumes against
the shipped table (``model/scenes/prostate_converged.volumes.npz``), relative to the gland volume. The whole
build is extrapolated from the mean CPU time a point and the critical path (the longest chain of solves, 18
points on a 7^3 grid): on W idle workers it takes at least the larger of 342 t / W and 18 t.

Run: ``nice .venv/bin/python bench/table_points.py [--configs 1:1e-9 3:1e-9 3:1e-7]`` (predictor points:tolerance)
"""

import argparse
import os
import time

import numpy as np

from phantom.model import PhantomModel, load_scene
from phantom.model.fidelity.response_table import POINT_TOLERANCE, _line_before, _predecessor, grid_pa

TARGETS = [(6, 0, 0), (6, 0, 6), (3, 3, 6)]
SHIPPED = "model/scenes/prostate_converged.volumes.npz"


def sample(targets: list[tuple[int, ...]], line_points: int) -> list[tuple[int, ...]]:
    """The targets and every point their solves need (predecessors and their line points), in build order."""
    needed: set[tuple[int, ...]] = set()
    pending = list(targets)
    while pending:
        index = pending.pop()
        if index in needed or not any(index):
            continue
        needed.add(index)
        before = _predecessor(index)
        pending.extend(([before] if before is not None else []) + _line_before(index, line_points, True))
    return sorted(needed)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--configs", nargs="*", default=["1:1e-9", "3:1e-9", f"3:{POINT_TOLERANCE:g}"],
                        help="predictor points:Newton tolerance, each measured in turn")
    args = parser.parse_args()
    configs = [(int(points), float(tolerance)) for points, tolerance in (c.split(":") for c in args.configs)]
    model = PhantomModel.from_scene(load_scene("builtin:converged"))
    model.rest_factorization()
    model.equilibrium([1.0, 0.0, 0.0])  # compile and warm every kernel once
    nodes_pa = grid_pa(3000.0, 7)
    with np.load(SHIPPED) as shipped:
        shipped_chambers, shipped_gland = shipped["chamber"], shipped["gland"]
    points = sample(TARGETS, max(points for points, _ in configs))
    print(f"{len(points)} points; load average at start {os.getloadavg()[0]:.1f} (2 cores)")
    summary = []
    for line_points, tolerance in configs:
        known = {(0, 0, 0): model.nodes_m}
        cpu, iterations, off = {}, {}, []
        print(f"\npredictor through {line_points} point(s), tolerance {tolerance:g}")
        print("| point | CPU | iterations | steps | off shipped / gland |")
        print("|---|---|---|---|---|")
        for index in points:
            line = _line_before(index, line_points, True)
            started = time.process_time()
            nearest_m, start_m, start_pa = ((known[line[0]], *model.extrapolated_start([known[p] for p in line]))
                                            if line else (None, None, None))
            state = model.equilibrium(nodes_pa[list(index)], initial_positions_m=nearest_m, tolerance=tolerance,
                                      predicted_positions_m=start_m, predicted_element_pressures_pa=start_pa)
            cpu[index], iterations[index] = time.process_time() - started, state.iterations
            known[index] = state.positions_m
            volumes = np.append(state.chamber_volumes_m3, state.gland_volume_m3)
            expected = np.append(shipped_chambers[index], shipped_gland[index])
            off.append(float(np.max(np.abs(volumes - expected)) / shipped_gland[index]))
            print(f"| {index} | {cpu[index]:.1f} s | {iterations[index]} | {state.load_steps} | {off[-1]:.1e} |",
                  flush=True)
        warm = [index for index in points if _predecessor(index) != (0, 0, 0)]
        mean_s = float(np.mean([cpu[index] for index in warm]))
        mean_iterations = float(np.mean([iterations[index] for index in warm]))
        summary.append((line_points, tolerance, mean_s, mean_iterations, max(off)))
    print(f"\nload average at end {os.getloadavg()[0]:.1f}")
    print("\n| predictor points | tolerance | CPU a warm point | iterations a warm point | "
          "build on 2 workers (342 t / 2) | critical path (18 t) | most off shipped / gland |")
    print("|---|---|---|---|---|---|---|")
    for line_points, tolerance, mean_s, mean_iterations, worst in summary:
        print(f"| {line_points} | {tolerance:g} | {mean_s:.2f} s | {mean_iterations:.1f} | "
              f"{342 * mean_s / 2 / 60:.1f} min | {18 * mean_s:.0f} s | {worst:.1e} |")


if __name__ == "__main__":
    main()
