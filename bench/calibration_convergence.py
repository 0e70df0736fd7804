"""Does the calibration converge under mesh refinement? The same calibration on three meshes.

Usage: .venv/bin/python bench/calibration_convergence.py [--scene bench/calibration_ecoflex.toml]
       [--measurements model/data/forward_measurements.csv] [--sizes-mm 10,7,5]
       [--grid gent_jm=5 --grid base_chamber_scale=1 --grid lobe_chamber_scale=1.2] [--workers 2]
       [--json bench-out.json]

For each mesh size (the scene's ``mesh_size_mm`` overridden; 10-node, graded where walls are thin), what
``phantom calibrate`` does with that scene: the pressure rays of the measurements traced by continuation (Dask,
cached under the phantom cache, so a second run re-solves nothing), E and the grid fitted, leave-one-out, and the
fit verified by full solves. Printed, as markdown:

- per mesh: nodes, the fitted E, the fit's and leave-one-out's mean error against the measurements;
- per measured point: the gland's growth (ml) each mesh gives at one common modulus, the finest mesh's fitted
  E (for a hyperelastic law the state at (p, E) is the one at (p E0 / E, E0): the traces give every E), and
  each mesh's change to the finest: the model's own convergence at the calibrated material, with E held;
- per measured point: each mesh's calibrated prediction (its own E) and its change to the finest: what a user of
  the calibration sees change when the mesh is refined and the calibration re-run.

The tracing costs minutes per mesh on two cores (12 min at 7 mm, 80 min at 5 mm beside other solves, for the eight
measured points) the first time; progress goes to stderr.
"""

import argparse
import json
import sys
import time

import numpy as np


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", default="bench/calibration_ecoflex.toml")
    parser.add_argument("--measurements", default="model/data/forward_measurements.csv")
    parser.add_argument("--sizes-mm", default="10,7,5", help="mesh sizes, coarsest first (mm)")
    parser.add_argument("--grid", action="append",
                        help="as phantom calibrate's (default: gent_jm=5, base_chamber_scale=1, "
                             "lobe_chamber_scale=1.2)")
    parser.add_argument("--workers", type=int, default=None)
    parser.add_argument("--json", help="write the figures to this file")
    args = parser.parse_args()

    from phantom.model.calibration.calibrate import calibrate, load_measurements, parse_grid, scene_with
    from phantom.model.cluster import stderr_progress
    from phantom.model.fem.model import PhantomModel
    from phantom.model.scene import load_scene, scene_from_dict

    sizes_mm = [float(size) for size in args.sizes_mm.split(",")]
    grid = parse_grid(args.grid or ["gent_jm=5", "base_chamber_scale=1", "lobe_chamber_scale=1.2"])
    base = load_scene(args.scene)
    measurements = load_measurements(args.measurements, n_chambers=len(base.chambers))
    results, nodes, took_s = [], [], []
    for size_mm in sizes_mm:
        scene = scene_from_dict(scene_with(base.raw, {"mesh_size_mm": size_mm}), base.path)
        nodes.append(len(PhantomModel.from_scene(scene).nodes_m))
        started = time.perf_counter()
        results.append(calibrate(scene, measurements, grid, n_workers=args.workers,
                                 progress=stderr_progress(f"{size_mm:g} mm: tracing the pressure rays")))
        took_s.append(time.perf_counter() - started)
        print(file=sys.stderr)

    finest = results[-1]
    common_pa = finest.youngs_modulus_pa
    theta = np.array([finest.parameters[name] for name in grid.names])  # every mesh at the finest fit's
    e0 = base.material.youngs_modulus_pa
    growth_ml = []  # per mesh, per point: at the common modulus
    for result in results:
        assert result.responses is not None  # calibrate keeps the traces it fitted on
        rest = result.responses.interpolate("gland_m3", theta, 0.0)
        at_common = result.responses.interpolate("gland_m3", theta, e0 / common_pa)
        growth_ml.append((at_common - rest) * 1e6)
    growth = np.array(growth_ml)
    predicted = np.array([result.fit_predicted_m3 * 1e6 for result in results])
    rest_ml = predicted[:, 0] if not measurements.pressures_pa[0].any() else None

    labels = [", ".join(f"{p / 1e3:g}" for p in row) for row in measurements.pressures_pa]
    print(f"Calibration on {len(sizes_mm)} meshes ({base.material.model}, grid "
          f"{', '.join(f'{n}={v.tolist()}' for n, v in zip(grid.names, grid.values, strict=True))}):\n")
    print("| mesh (mm) | nodes | E (kPa) | fit (%) | leave-one-out (%) | traces solved in this run | this run (s) |")
    print("|---|---|---|---|---|---|---|")
    for size_mm, count, result, seconds in zip(sizes_mm, nodes, results, took_s, strict=True):
        print(f"| {size_mm:g} | {count} | {result.youngs_modulus_pa / 1e3:.3f} | {result.fit_mean_abs_pct_error:.2f} "
              f"| {result.loo_mean_abs_pct_error:.2f} | {result.traces_solved} of {result.tasks} | {seconds:.0f} |")
    header = " | ".join(f"{size:g} mm" for size in sizes_mm)
    changes = " | ".join(f"{size:g} mm to {sizes_mm[-1]:g}" for size in sizes_mm[:-1])
    print(f"\nGland growth (ml) at E = {common_pa / 1e3:.3f} kPa (the {sizes_mm[-1]:g} mm fit's) on every mesh, and "
          "each mesh's change to the finest (% of the growth):\n")
    print(f"| pressures (kPa) | {header} | {changes} |")
    print("|---|" + "---|" * (2 * len(sizes_mm) - 1))
    for point, label in enumerate(labels):
        if not measurements.pressures_pa[point].any():
            continue
        values = growth[:, point]
        cells = " | ".join(f"{value:.4f}" for value in values)
        deltas = " | ".join(f"{100 * (value - values[-1]) / values[-1]:+.2f}" for value in values[:-1])
        print(f"| {label} | {cells} | {deltas} |")
    print("\nEach mesh's calibrated prediction (ml, its own E, full solves) and its growth's change to the finest "
          "(% of the growth):\n")
    print(f"| pressures (kPa) | measured | {header} | {changes} |")
    print("|---|---|" + "---|" * (2 * len(sizes_mm) - 1))
    for point, label in enumerate(labels):
        values = predicted[:, point]
        cells = " | ".join(f"{value:.3f}" for value in values)
        if rest_ml is None or not measurements.pressures_pa[point].any():
            deltas = " | ".join("" for _ in values[:-1])
        else:
            grown = values - rest_ml
            deltas = " | ".join(f"{100 * (value - grown[-1]) / grown[-1]:+.2f}" for value in grown[:-1])
        print(f"| {label} | {measurements.volumes_m3[point] * 1e6:.2f} | {cells} | {deltas} |")
    if args.json:
        with open(args.json, "w") as handle:
            json.dump({"sizes_mm": sizes_mm, "nodes": nodes, "took_s": took_s, "common_youngs_modulus_kpa":
                       common_pa / 1e3, "pressures_kpa": (measurements.pressures_pa / 1e3).tolist(),
                       "growth_at_common_modulus_ml": growth.tolist(), "predicted_ml": predicted.tolist(),
                       "calibrations": [result.as_json() for result in results]}, handle, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
