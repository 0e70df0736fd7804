"""The shape inverse (phantom.model.shape_inverse) on builtin:converged: the distance against the number of full
solves that refine the table's answer, and the time from the table against one full solve's, measured in the same
run.

Each target is the model's own deformed outer surface at hidden pressures (a full solve from rest), turned by 14
degrees, shifted by 9 mm and moved by Gaussian noise of 0.1 mm RMS; the inverse answers from the shipped table of
shapes, then refines by up to three full solves. A row per target: the table's answer (its pressure error, its
distance, its wall and CPU time), then after each full solve the pressure error and the full model's distance. The
distance cannot go below the noise's floor (about 0.046 mm: the mean of |the normal component| of 0.1 mm RMS).

    .venv/bin/python bench/shape_inverse.py            # three targets, about 2 minutes on an idle machine
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np

from phantom.model import PhantomModel, load_scene
from phantom.model.mesh.surface import TriangleMesh, rotation_from_vector
from phantom.model.shape_inverse import ShapeInverse, surface_shapes

TARGETS_KPA = ((0.9, 2.3, 1.6), (2.6, 0.4, 0.7), (1.7, 1.2, 2.8))


def noised(vertices_mm: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    axis = np.array([0.4, 0.8, 0.45]) / np.linalg.norm([0.4, 0.8, 0.45])
    rotation = rotation_from_vector(np.radians(14.0) * axis)
    return (vertices_mm @ rotation.T + np.array([7.0, -4.0, 5.0])
            + rng.normal(0.0, 0.1 / np.sqrt(3.0), vertices_mm.shape))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--solves", type=int, default=3, help="full solves of the refinement at most (default 3)")
    args = parser.parse_args()
    model = PhantomModel.from_scene(load_scene("builtin:converged"))
    inverse = ShapeInverse(model, surface_shapes(model))
    rng = np.random.default_rng(52)
    print(f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores; builtin:converged, "
          f"{len(inverse.nodes)} surface nodes\n")
    header = (f"{'target kPa':<16} {'rest mm':>8} | {'table: err kPa':>14} {'mm':>6} {'wall s':>7} {'CPU s':>6} | "
              + " | ".join(f"solve {k}: err kPa    mm" for k in range(1, args.solves + 1)))
    print(header)
    solve_times = []
    for truth_kpa in TARGETS_KPA:
        truth_pa = np.array(truth_kpa) * 1e3
        started = time.perf_counter()
        state = model.equilibrium(truth_pa)
        solve_times.append(time.perf_counter() - started)
        target = TriangleMesh(noised(np.asarray(state.positions_m)[inverse.nodes] * 1e3, rng), inverse.triangles)
        result = inverse.solve(target, args.solves)
        cells = [f"{np.max(np.abs(pressures - truth_pa)) / 1e3:15.4f} {distance:6.3f}"
                 for pressures, distance in result.refinement]
        print(f"{','.join(f'{v:g}' for v in truth_kpa):<16} {result.rest_distance_mm:8.3f} | "
              f"{np.max(np.abs(result.table_pressures_pa - truth_pa)) / 1e3:14.4f} {result.table_distance_mm:6.3f} "
              f"{result.table_time_s:7.2f} {result.table_cpu_s:6.2f} | " + " | ".join(cells)
              + f"   (refinement {result.refine_time_s:.1f} s)")
    print(f"\none full solve from rest (the targets'): {np.mean(solve_times):.1f} s on average; the table's answer "
          "takes the wall time above")


if __name__ == "__main__":
    main()
