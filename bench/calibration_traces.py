"""The calibration's traces with and without their predictor, in the same run: CPU, Newton iterations, answers.

Usage: .venv/bin/python bench/calibration_traces.py [--scene bench/calibration_ecoflex.toml]
       [--measurements model/data/forward_measurements.csv] [--size-mm 7] [--set gent_jm=5 ...] [--rows 1,2,...]

The pressure rays ``phantom calibrate`` traces at one grid point (default: the one of the command that wrote
``builtin:converged``: gent_jm=5, base_chamber_scale=1, lobe_chamber_scale=1.2, 7 mm), each traced in this
process on one core twice: with each solve started from the last equilibrium (``PREDICTOR_POINTS = 1``, what
the traces did before) and from the last equilibria extrapolated to its load factor (the shipped predictor).
Nothing is read from or written to the trace cache. Printed, as markdown: per ray, the solves, the Newton
iterations and the CPU seconds of each, and the largest difference of the traced gland volumes (ml); the load
average before and after (the machine is shared: CPU time is what compares).
"""

import argparse
import json
import os
import time

import numpy as np

SHIPPED_GRID_POINT = ("gent_jm=5", "base_chamber_scale=1", "lobe_chamber_scale=1.2")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", default="bench/calibration_ecoflex.toml")
    parser.add_argument("--measurements", default="model/data/forward_measurements.csv")
    parser.add_argument("--size-mm", type=float, default=7.0)
    parser.add_argument("--set", action="append", metavar="NAME=VALUE",
                        help=f"the grid point's parameters (default: {' '.join(SHIPPED_GRID_POINT)})")
    parser.add_argument("--rows", help="measurement rows to trace (default: every loaded one)")
    parser.add_argument("--json", help="write the figures to this file")
    args = parser.parse_args()

    from phantom.model.calibration import sweep
    from phantom.model.calibration.calibrate import (
        GENT_LIMIT_FRACTION,
        MAX_LINEAR_MULTIPLE,
        OVERSHOOT,
        STEPS_PER_LINEAR_LOAD_FACTOR,
        linear_load_factor,
        load_measurements,
        ray_task,
        scene_with,
    )
    from phantom.model.fem.model import PhantomModel
    from phantom.model.scene import load_scene, scene_from_dict

    base = load_scene(args.scene)
    values = {name: float(value) for name, _, value in (item.partition("=") for item in args.set or SHIPPED_GRID_POINT)}
    document = scene_with(base.raw, {**values, "mesh_size_mm": args.size_mm})
    scene = scene_from_dict(document, base.path)
    measurements = load_measurements(args.measurements, n_chambers=len(scene.chambers))
    model = PhantomModel.from_scene(scene)
    # the load factors and stops calibrate() gives this grid point's traces (no modulus band)
    t_linear = linear_load_factor(model, measurements)
    step = t_linear / STEPS_PER_LINEAR_LOAD_FACTOR
    load_factors = tuple(np.arange(0.0, MAX_LINEAR_MULTIPLE * t_linear + 0.5 * step, step).tolist())
    measured = measurements.volumes_m3
    stop_growth = OVERSHOOT * np.maximum(measured - model.rest_gland_volume_m3, 0.2 * measured.max() / 10)
    jm = scene.material.gent_jm
    law_limit = GENT_LIMIT_FRACTION * jm if scene.material.model == "gent" and jm is not None else np.inf
    rows = ([int(row) for row in args.rows.split(",")] if args.rows
            else [row for row in range(len(measured)) if np.any(measurements.pressures_pa[row])])

    iterations: list[int] = []
    solve = PhantomModel.equilibrium

    def counted(self, *positional, **named):  # type: ignore[no-untyped-def]
        state = solve(self, *positional, **named)
        iterations.append(state.iterations)
        return state

    PhantomModel.equilibrium = counted  # type: ignore[method-assign]
    shipped_points = sweep.PREDICTOR_POINTS
    load_before = os.getloadavg()[0]
    figures = []
    print(f"{len(model.nodes_m)} nodes, {args.size_mm:g} mm, {values}; load factor step {step:.4g} "
          f"(E0 / E; the traces' {len(load_factors)} at most)\n")
    print("| pressures (kPa) | solves | iterations before | iterations after | CPU before (s) | CPU after (s) "
          "| CPU ratio | largest gland difference (ml) |")
    print("|---|---|---|---|---|---|---|---|")
    for row in rows:
        task = ray_task(scene, document, measurements, row, load_factors, float(stop_growth[row]), law_limit)
        runs = {}
        for label, points in (("before", 1), ("after", shipped_points)):
            sweep.PREDICTOR_POINTS = points
            iterations.clear()
            started = time.process_time()
            trace = sweep.trace_ray(task)
            runs[label] = (trace, time.process_time() - started, list(iterations))
        sweep.PREDICTOR_POINTS = shipped_points
        (before, cpu_before, its_before), (after, cpu_after, its_after) = runs["before"], runs["after"]
        common = min(len(before.gland_m3), len(after.gland_m3))
        difference_ml = float(np.max(np.abs(before.gland_m3[:common] - after.gland_m3[:common]))) * 1e6
        pressures = ", ".join(f"{p / 1e3:g}" for p in measurements.pressures_pa[row])
        print(f"| {pressures} | {len(its_after)} | {sum(its_before)} ({'+'.join(map(str, its_before))}) | "
              f"{sum(its_after)} ({'+'.join(map(str, its_after))}) | {cpu_before:.1f} | {cpu_after:.1f} | "
              f"{cpu_before / cpu_after:.2f} | {difference_ml:.2e} |", flush=True)
        figures.append({"row": row, "iterations_before": its_before, "iterations_after": its_after,
                        "cpu_before_s": cpu_before, "cpu_after_s": cpu_after, "stopped_before": before.stopped,
                        "stopped_after": after.stopped, "max_gland_difference_ml": difference_ml})
    total_before = sum(f["cpu_before_s"] for f in figures)
    total_after = sum(f["cpu_after_s"] for f in figures)
    print(f"\nall rays: CPU {total_before:.0f} s before, {total_after:.0f} s after "
          f"({total_before / total_after:.2f}x); "
          f"load average {load_before:.1f} at the start, {os.getloadavg()[0]:.1f} at the end")
    if args.json:
        with open(args.json, "w") as handle:
            json.dump({"size_mm": args.size_mm, "grid_point": values, "rays": figures}, handle, indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
