"""How fast a capture of 120 pictures (two elevations, 1280x960) is reconstructed, by stage, against a plain numpy
carve of the same silhouettes measured in the same run.

The pictures are the virtual rig's of the simulated phantom at the BPH scene's top target (rendered once into a
temporary capture folder). ``phantom.scan.reconstruct`` is timed ``--repeats`` times (the first run also loads
the numba kernels from their cache); wall and CPU seconds per stage (reading and keying the pictures, carving,
marching cubes). The peer evaluates the same field (each silhouette's signed distance, bilinear, at the point's
projection, in mm at its depth, the maximum over views) with numpy at every point of the final grid's box, view
by view, without the coarse-to-fine band or the early exit: what carving costs done plainly.

Run: ``.venv/bin/python bench/scan_speed.py [--repeats 3] [--voxel-mm 0.3]``
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from phantom.hil.truth_shape import TruthShape
from phantom.scan.camera import virtual_rig
from phantom.scan.capture import CaptureFolder, Plan
from phantom.scan.carve import Carver, View
from phantom.scan.reconstruct import VOXEL_MM, reconstruct
from phantom.scan.silhouette import silhouette
from phantom.scan.virtual import render_capture

#: The inverse's pressures (kPa) for the BPH scene's 43 ml target on the calibrated model.
TOP_PRESSURES_KPA = (3.0, 3.0, 3.0)


def numpy_field(carver: Carver, points: np.ndarray) -> np.ndarray:
    """The carving field at every point, numpy only, view by view."""
    camera = carver.camera
    field = np.full(len(points), -np.inf, np.float32)
    focal = 0.5 * (camera.fx + camera.fy)
    for view in carver.views:
        local = view.pose.apply(points)
        normalized = local[:, :2] / local[:, 2:3]
        pixels = camera.project(local)
        x0, y0, width, height = view.silhouette.crop
        u, v = pixels[:, 0] - x0, pixels[:, 1] - y0
        inside = (u >= 0) & (v >= 0) & (u <= width - 1) & (v <= height - 1) & (
            np.sum(normalized ** 2, axis=1) <= carver.max_radius2)
        iu = np.clip(u.astype(np.int64), 0, width - 2)
        iv = np.clip(v.astype(np.int64), 0, height - 2)
        fu, fv = u - iu, v - iv
        grid = view.silhouette.signed_distance_px
        d = ((1 - fu) * (1 - fv) * grid[iv, iu] + fu * (1 - fv) * grid[iv, iu + 1] + (1 - fu) * fv * grid[iv + 1, iu]
             + fu * fv * grid[iv + 1, iu + 1])
        d = np.where(inside, d, view.silhouette.truncation_px)
        field = np.maximum(field, (d * local[:, 2] / focal).astype(np.float32))
    return field


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--voxel-mm", type=float, default=VOXEL_MM)
    args = parser.parse_args()
    rig = virtual_rig()
    with tempfile.TemporaryDirectory(prefix="scan-speed-") as scratch:
        started = time.perf_counter()
        folder = render_capture(TruthShape().surface(list(TOP_PRESSURES_KPA)), rig, Plan(60), Path(scratch) / "c")
        print(f"rendered {len(folder.frames)} pictures of {rig.camera.width}x{rig.camera.height} in "
              f"{time.perf_counter() - started:.1f} s")
        folder = CaptureFolder.open(folder.path)
        runs = []
        for _ in range(args.repeats):
            wall, cpu = time.perf_counter(), time.process_time()
            result = reconstruct(folder, rig, args.voxel_mm)
            runs.append((time.perf_counter() - wall, time.process_time() - cpu, result))
        best = min(runs, key=lambda run: run[0])
        print("\n| run | wall s | CPU s | silhouettes s | carve s | surface s | projections |")
        print("|---|---|---|---|---|---|---|")
        for number, (wall_s, cpu_s, result) in enumerate(runs, start=1):
            stages = result.stage_s
            print(f"| {number} | {wall_s:.1f} | {cpu_s:.1f} | {stages['silhouettes']:.1f} | {stages['carve']:.1f} | "
                  f"{stages['surface']:.2f} | {result.projections / 1e6:.1f} M |")
        # the peer: the same field on the final grid's whole box, in numpy
        views = [View(rig.pose(frame.orbit_deg, frame.elevation_deg), silhouette(folder.image(frame)))
                 for frame in folder.frames]
        carver = Carver(rig.camera, views)
        mesh = best[2].mesh
        low, high = mesh.vertices_mm.min(axis=0) - 1.0, mesh.vertices_mm.max(axis=0) + 1.0
        axes = [np.arange(low[k], high[k], args.voxel_mm) for k in range(3)]
        points = np.stack([a.ravel() for a in np.meshgrid(*axes, indexing="ij")], axis=1)
        wall, cpu = time.perf_counter(), time.process_time()
        for start in range(0, len(points), 500_000):
            numpy_field(carver, points[start:start + 500_000])
        numpy_wall, numpy_cpu = time.perf_counter() - wall, time.process_time() - cpu
        carve_s = best[2].stage_s["carve"]
        print(f"\npeer: numpy, every point of the final box ({len(points) / 1e6:.1f} M points x {len(views)} views): "
              f"{numpy_wall:.1f} s wall, {numpy_cpu:.1f} s CPU; the coarse-to-fine numba carve {carve_s:.1f} s "
              f"({numpy_wall / carve_s:.0f}x faster); the whole reconstruction {best[0]:.1f} s wall "
              f"(goal: under 30 s)")


if __name__ == "__main__":
    main()
