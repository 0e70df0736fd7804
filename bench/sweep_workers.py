"""Time of a calibration sweep against the number of Dask workers (LocalCluster), with the same traces run
one after another in this process as the peer.

    .venv/bin/python bench/sweep_workers.py [--workers 1,2] [--size-mm 6] [--rays 8]

Each row traces the same rays (Neo-Hookean built-in prostate, E0 = 20 kPa, load factors 0, 0.25, ..., 1 of
pressures up to 3 kPa) from an empty sweep cache; the mesh is cached beforehand so every row solves the same
work. Cluster start-up is included (it is what a calibration pays) and also printed apart.
"""

import argparse
import os
import shutil
import tempfile
import time

import numpy as np


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--workers", default="1,2", help="worker counts, comma-separated")
    parser.add_argument("--size-mm", type=float, default=6.0)
    parser.add_argument("--rays", type=int, default=8)
    args = parser.parse_args()
    os.environ["PHANTOM_CACHE_DIR"] = tempfile.mkdtemp(prefix="sweep-bench-")
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    import phantom
    from phantom.model import PhantomModel
    from phantom.model.calibration.sweep import RayTask, run_sweep, trace_ray
    from phantom.model.cluster import local_cluster
    from phantom.model.scene import scene_from_dict

    raw = {"phantom": {"mesh": "builtin:prostate", "units": "mm", "chambers": ["chamber0", "chamber1", "chamber2"],
                       "fixed": "fixed"},
           "material": {"model": "neo_hookean", "youngs_modulus_kpa": 20.0, "poisson_ratio": 0.45},
           "geometry": {"mesh_size_mm": args.size_mm}}
    PhantomModel.from_scene(scene_from_dict(raw))  # mesh and kernels cached before timing
    rng = np.random.default_rng(1)
    tasks = [RayTask(raw, tuple(rng.uniform(0, 3000, 3).tolist()), (0.0, 0.25, 0.5, 0.75, 1.0))
             for _ in range(args.rays)]
    started = time.perf_counter()
    for task in tasks:
        trace_ray(task)
    peer_s = time.perf_counter() - started
    print(f"{len(tasks)} rays, {args.size_mm:g} mm mesh, {os.cpu_count()} cores")
    print("| run | workers | cluster start (s) | sweep (s) | total (s) | peer / total |")
    print("|---|---|---|---|---|---|")
    print(f"| in-process, one after another (peer) | - | - | {peer_s:.1f} | {peer_s:.1f} | 1.00 |")
    for workers in (int(value) for value in args.workers.split(",")):
        shutil.rmtree(phantom.cache_dir("sweeps"))
        started = time.perf_counter()
        cluster = local_cluster(workers)
        start_s = time.perf_counter() - started
        try:
            run_sweep(tasks, scheduler=cluster.scheduler_address)
        finally:
            cluster.close()
        total_s = time.perf_counter() - started
        print(f"| LocalCluster | {workers} | {start_s:.1f} | {total_s - start_s:.1f} | {total_s:.1f} | "
              f"{peer_s / total_s:.2f} |")
    shutil.rmtree(os.environ["PHANTOM_CACHE_DIR"], ignore_errors=True)


if __name__ == "__main__":
    main()
