"""Full solves from rest on ``builtin:converged`` through the chambers' limit points: time, iterations, steps and the
equilibrium against the answers of the path following before issue 40 (main at d0626fb), kept below.

Every Table I point (model/data/forward_measurements.csv) and (3,3,3) kPa, one process, warm caches (the mesh and
the rest factor loaded, the kernels compiled, before the first timing), each solve from rest as
``phantom forward --scene builtin:converged`` does. Columns: wall time and the process's CPU time (on the shared
two-core machine the wall time of a single-threaded solve is its CPU time plus the waiting; both are printed,
with the load average), Newton iterations (pressure- and volume-controlled), accepted steps, the gland volume
and its difference from the kept answer relative to the gland volume (the issue: within 1e-6).

Run: ``nice .venv/bin/python bench/fem_limit_points.py [--points 2,2,2 3,1,2 3,3,3]``
"""

import argparse
import os
import time

# one BLAS thread, as `phantom forward` runs (phantom/cli/model.py): numpy's threaded OpenBLAS only loses time to
# thread wake-ups on two busy cores
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

from phantom.model import PhantomModel, load_scene  # noqa: E402

#: The gland volume (ml) and (iterations, accepted steps) at each point from rest with the path following before
#: issue 40 (main at d0626fb: a first pressure step, then volume control from rest where it failed; secant
#: predictors; the crossing of lam = 1 bracketed under volume control). Its times, on the idle machine:
#: (3,1,2) 34 s, (2,2,2) 57 s, (3,3,3) 71 s (bench/README.md); under this run's load they were 5-12 times that.
BEFORE = {
    (2, 2, 2): (37.42015804273464, 75, 8),
    (3, 1, 2): (39.00314458409227, 42, 3),
    (3, 3, 3): (51.58146575256908, 100, 12),
    (1, 1, 1): (29.238918699812714, 14, 1),
    (2, 0, 0): (29.41107710151244, 18, 2),
    (0, 2, 0): (29.75595369215748, 15, 2),
    (0, 0, 2): (29.75595369215752, 15, 2),
    (1, 2, 3): (39.58599726457779, 64, 8),
}
TABLE_I = [(1, 1, 1), (2, 2, 2), (2, 0, 0), (0, 2, 0), (0, 0, 2), (1, 2, 3), (3, 1, 2)]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--points", nargs="*", default=None, help="pressure triples in kPa, e.g. 2,2,2 3,1,2")
    args = parser.parse_args()
    points = ([tuple(float(x) for x in point.split(",")) for point in args.points] if args.points
              else [*TABLE_I, (3, 3, 3)])
    model = PhantomModel.from_scene(load_scene("builtin:converged"))
    model.rest_factorization()
    model.equilibrium([1.0, 0.0, 0.0])  # compile and warm every kernel once
    print(f"load average at start {os.getloadavg()[0]:.1f} (2 cores)")
    print("| kPa | wall | CPU | iterations | steps | gland (ml) | before: iterations, steps | gland change / gland |")
    print("|---|---|---|---|---|---|---|---|")
    for point in points:
        wall, cpu = time.perf_counter(), time.process_time()
        state = model.equilibrium([p * 1e3 for p in point])
        wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
        gland_ml = state.gland_volume_m3 * 1e6
        before = BEFORE.get(tuple(int(p) for p in point) if all(float(p).is_integer() for p in point) else None)
        compared = ("not kept", "") if before is None else (f"{before[1]}, {before[2]}",
                                                              f"{abs(gland_ml - before[0]) / before[0]:.1e}")
        print(f"| {','.join(f'{p:g}' for p in point)} | {wall:.1f} s | {cpu:.1f} s | {state.iterations} | "
              f"{state.load_steps} | {gland_ml:.6f} | {compared[0]} | {compared[1]} |", flush=True)
    print(f"load average at end {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
