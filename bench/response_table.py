"""The daemon's model on the calibrated scene: the response table against full solves, accuracy and speed.

On ``builtin:calibrated`` (Gent, 4 mm mesh) it compares, at random pressures in the 0-3 kPa box and for a few
gland targets, the ``table`` level (the daemon's) with the ``full`` level (a full Gent solve per answer, each
started from the nearest earlier state): volume errors, and times per estimate and per inverse with their ratio
(both measured in this run). ``--build-workers 1,2`` also times building a table from scratch (no cache) on a
coarser grid and mesh with one and two worker processes. The plot shows chamber 0's and the gland's volume
along two pressure paths: full solves, the shipped 7-point table and a 5-point one.

    .venv/bin/python bench/response_table.py [--points 12] [--build-workers 1,2] [--plot bench/response_table.png]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

TARGETS_ML = [26.0, 30.0, 35.0, 40.0, 43.0]


def timed(function, *arguments):
    started = time.perf_counter()
    result = function(*arguments)
    return result, time.perf_counter() - started


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--points", type=int, default=12, help="random pressure sets compared (default 12)")
    parser.add_argument("--build-workers", default="", help="e.g. 1,2: time a fresh build with these worker counts")
    parser.add_argument("--build-mm", type=float, default=8.0, help="mesh of the build timing (default 8 mm)")
    parser.add_argument("--build-points", type=int, default=5, help="grid of the build timing (default 5)")
    parser.add_argument("--plot", default="bench/response_table.png", help="where the plot goes ('' for none)")
    args = parser.parse_args()

    from phantom.model import PhantomModel, load_scene
    from phantom.model.fidelity.levels import VolumeEstimator
    from phantom.model.inverse import InverseSolver
    from phantom.model.target import Target

    model = PhantomModel.from_scene(load_scene("builtin:calibrated"))
    table_estimator, load_s = timed(VolumeEstimator, model)
    full_estimator = VolumeEstimator(model, level="full")
    rest = np.append(model.rest_chamber_volumes_m3, model.rest_gland_volume_m3)
    rng = np.random.default_rng(7)
    volume_errors, growth_errors, table_s, full_s = [], [], [], []
    for pressures_pa in rng.uniform(0.0, 3000.0, size=(args.points, 3)):
        (table_chambers, table_gland, _), seconds = timed(table_estimator.evaluate, pressures_pa)
        table_s.append(seconds)
        (full_chambers, full_gland, _), seconds = timed(full_estimator.evaluate, pressures_pa)
        full_s.append(seconds)
        table = np.append(table_chambers, table_gland)
        full = np.append(full_chambers, full_gland)
        volume_errors.append(np.abs(table - full) / full * 100)
        growth_errors.append(np.abs(table - full) / np.abs(full - rest) * 100)
    volume_errors, growth_errors = np.array(volume_errors), np.array(growth_errors)
    print(f"builtin:calibrated, {len(model.nodes_m)} nodes; table loaded (or built) in {load_s:.2f} s, "
          f"checked at build against full solves: {table_estimator.table.check_errors_pct:.3f} %")
    print(f"\n{args.points} random pressure sets in 0-3 kPa, table against full solves:\n")
    print("| quantity | chamber 0 | chamber 1 | chamber 2 | gland |")
    print("|---|---|---|---|---|")
    print("| max error, % of the volume | " + " | ".join(f"{v:.3f}" for v in volume_errors.max(axis=0)) + " |")
    print("| max error, % of the growth | " + " | ".join(f"{v:.3f}" for v in growth_errors.max(axis=0)) + " |")

    table_solver = InverseSolver(model, estimator=table_estimator)
    full_solver = InverseSolver(model, estimator=full_estimator)
    print("\n| target (ml) | table: pressures (kPa) | table inverse (ms) | full inverse (s) | full / table | "
          "full solve at the table's answer (ml) |")
    print("|---|---|---|---|---|---|")
    for volume_ml in TARGETS_ML:
        target = Target(gland_volume_m3=volume_ml * 1e-6)
        table_result, table_inverse_s = timed(table_solver.pressures_for, target)
        _, full_inverse_s = timed(full_solver.pressures_for, target)
        check = model.equilibrium(table_result.pressures_pa)
        print(f"| {volume_ml:g} | {', '.join(f'{p / 1e3:.3f}' for p in table_result.pressures_pa)} | "
              f"{table_inverse_s * 1e3:.1f} | {full_inverse_s:.2f} | {full_inverse_s / table_inverse_s:.0f} | "
              f"{check.gland_volume_m3 * 1e6:.3f} |")
    print(f"\nper estimate: table {np.median(table_s) * 1e3:.2f} ms, full {np.median(full_s) * 1e3:.0f} ms "
          f"(median; full / table = {np.median(full_s) / np.median(table_s):.0f})")

    if args.build_workers:
        from phantom.model.fidelity.response_table import build_response_table

        coarse = PhantomModel.from_scene(load_scene("builtin:calibrated"), mesh_size_mm=args.build_mm)
        print(f"\nbuilding a {args.build_points}^3 table from scratch on a {args.build_mm:g} mm mesh "
              f"({len(coarse.nodes_m)} nodes):\n")
        print("| workers | build (s) | one worker / this |")
        print("|---|---|---|")
        first_s = None
        for workers in (int(w) for w in args.build_workers.split(",")):
            _, seconds = timed(build_response_table, coarse, 3000.0, args.build_points, None, workers)
            first_s = first_s or seconds
            print(f"| {workers} | {seconds:.1f} | {first_s / seconds:.2f} |")

    if args.plot:
        plot(model, table_estimator, args.plot)


def plot(model, table_estimator, path: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from phantom.model.fidelity.response_table import build_response_table

    five = build_response_table(model, 3000.0, 5)
    pressures_kpa = np.linspace(0.0, 3.0, 25)
    figure, axes = plt.subplots(2, 2, figsize=(10, 7), sharex=True)
    for column_axes, (label, direction) in zip(axes.T, [("chamber 0 alone, (p, 0, 0)", (1.0, 0.0, 0.0)),
                                                        ("every chamber, (p, p, p)", (1.0, 1.0, 1.0))], strict=True):
        full, seven, coarse = [], [], []
        start_m = None
        for pressure_kpa in pressures_kpa:
            pressures_pa = 1e3 * pressure_kpa * np.asarray(direction)
            state = model.equilibrium(pressures_pa, initial_positions_m=start_m)
            start_m = state.positions_m
            full.append((state.chamber_volumes_m3[0] * 1e6, state.gland_volume_m3 * 1e6))
            chambers, gland = table_estimator.table.volumes(pressures_pa)
            seven.append((chambers[0] * 1e6, gland * 1e6))
            chambers, gland = five.volumes(pressures_pa)
            coarse.append((chambers[0] * 1e6, gland * 1e6))
        full, seven, coarse = np.array(full), np.array(seven), np.array(coarse)
        volumes, errors = column_axes
        for column, colour, name in ((0, "tab:blue", "chamber 0"), (1, "tab:green", "gland")):
            volumes.plot(pressures_kpa, full[:, column], "o", color=colour, markersize=4, label=f"{name}: full solves")
            volumes.plot(pressures_kpa, seven[:, column], "-", color=colour, label=f"{name}: table, 7 points")
            errors.plot(pressures_kpa, seven[:, column] - full[:, column], "-", color=colour,
                        label=f"{name}: table, 7 points (shipped)")
            errors.plot(pressures_kpa, coarse[:, column] - full[:, column], "--", color=colour, alpha=0.6,
                        label=f"{name}: table, 5 points")
        volumes.set_title(label)
        volumes.set_ylabel("volume (ml)")
        errors.set_ylabel("table - full solve (ml)")
        errors.set_xlabel("pressure (kPa)")
        for axis in column_axes:
            axis.grid(alpha=0.3)
    axes[0, 0].legend(fontsize=7)
    axes[1, 0].legend(fontsize=7)
    figure.suptitle("builtin:calibrated (Gent): the response table against full solves")
    figure.tight_layout()
    figure.savefig(path, dpi=110)
    print(f"\nplot: {path}")


if __name__ == "__main__":
    main()
