"""Time of each stage of ``phantom design`` (surface, chambers with the sizing search, mesh and scene, cast, growth,
checks, report).

Two sources: the built-in body's outer surface as an STL (1 mm rings), and a NIfTI mask of the same body imaged
with 0.8 x 0.8 x 1.5 mm voxels on an oblique grid (marching cubes and smoothing included). The peer, measured in
the same run: gmsh meshing the built-in prostate from its exact OpenCASCADE geometry at the same size, and one
forward solve of the built-in scene at (1, 1, 1) kPa. The chambers are sized to the default target (the paper's
45 ml at 3 kPa: beyond the built-in material, so one coarse solve at the walls' limit; ``--target-ml`` gives one the
walls allow, and the search's steps). Growth is one solve at 1 kPa plus the target's confirmation at 3 kPa (the
command's default curve is six).

    .venv/bin/python bench/design_stages.py [--size-mm 2.5]
"""

from __future__ import annotations

import argparse
import math
import tempfile
import time
from pathlib import Path

import nibabel
import numpy as np
import trimesh

from phantom.design.pipeline import design
from phantom.design.result import DesignOptions
from phantom.model.fem.model import PhantomModel
from phantom.model.mesh.prostate import generate_prostate
from phantom.model.mesh.shape import body_surface_mesh_mm, inside_body
from phantom.model.scene import load_scene


def body_mask(path: Path) -> Path:
    """The built-in body (RAS: its x mirrored) on an oblique 0.8 x 0.8 x 1.5 mm grid."""
    axis = np.array([1.0, 0.5, 0.3]) / np.linalg.norm([1.0, 0.5, 0.3])
    angle = math.radians(20.0)
    skew = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    rotation = np.eye(3) + math.sin(angle) * skew + (1 - math.cos(angle)) * skew @ skew
    grid = np.array([80, 80, 40])
    affine = np.eye(4)
    affine[:3, :3] = rotation * np.array([0.8, 0.8, 1.5])
    affine[:3, 3] = -affine[:3, :3] @ ((grid - 1) / 2.0)
    index = np.stack(np.meshgrid(*[np.arange(n) for n in grid], indexing="ij"), -1).reshape(-1, 3).astype(float)
    world = index @ affine[:3, :3].T + affine[:3, 3]
    data = inside_body(world * np.array([-1.0, 1.0, 1.0])).reshape(tuple(grid)).astype(np.int16)
    nibabel.save(nibabel.Nifti1Image(data, affine), str(path))
    return path


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size-mm", type=float, default=2.5)
    parser.add_argument("--target-ml", type=float, default=None, help="the growth target (default the paper's)")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as folder:
        root = Path(folder)
        vertices, triangles = body_surface_mesh_mm(1.0)
        stl = root / "builtin.stl"
        trimesh.Trimesh(vertices, triangles, process=False).export(str(stl))
        sources = {"built-in body (STL)": stl, "built-in body (oblique NIfTI)": body_mask(root / "body.nii.gz")}
        # the built-in prostate's uncalibrated 4-node material, as the figures in bench/README.md were measured (the
        # default, builtin:converged's 10-node Gent, solves nonlinearly: README "Design", its own paragraph)
        options = DesignOptions(size_mm=args.size_mm, growth_pressures_kpa=(1.0,), growth_target_ml=args.target_ml,
                                material_from="builtin")
        rows = []
        for name, source in sources.items():
            result = design(source, root / name.split()[-1].strip("()"), options, progress=lambda line: None)
            rows.append((name, result))
        started = time.perf_counter()
        generate_prostate(args.size_mm)
        peer_mesh_s = time.perf_counter() - started
        started = time.perf_counter()
        model = PhantomModel.from_scene(load_scene("builtin:prostate"), mesh_size_mm=args.size_mm)
        model.equilibrium([1e3, 1e3, 1e3])
        peer_solve_s = time.perf_counter() - started
    stages = list(rows[0][1].stage_times_s)
    print(f"mesh size {args.size_mm:g} mm, 4-node; peers: the built-in mesh {peer_mesh_s:.1f} s, a built-in "
          f"forward solve (model and solve) {peer_solve_s:.1f} s\n")
    print("| source | " + " | ".join(f"{stage} s" for stage in stages) + " | total s | mesh / built-in mesh | "
          "growth / built-in solve | nodes | sizing solves | chambers' scale |")
    print("|---" * (len(stages) + 7) + "|")
    for name, result in rows:
        times = result.stage_times_s
        print(f"| {name} | " + " | ".join(f"{times[stage]:.1f}" for stage in stages)
              + f" | {sum(times.values()):.1f} | {times['mesh'] / peer_mesh_s:.1f} | "
              f"{times['growth'] / peer_solve_s:.1f} | {result.mesh_nodes} | "
              f"{len(result.sizing.steps) if result.sizing else 0} | "
              f"{result.sizing.scale if result.sizing else 1:.3f} |")


if __name__ == "__main__":
    main()
