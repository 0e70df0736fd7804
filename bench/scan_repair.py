"""Closing a scan's holes so that its volume is defined: the candidate libraries, measured (the choice in scan.py).

Each candidate gets the same damaged scan: the model's deformed outer surface (builtin:calibrated scene at
1, 2, 0.5 kPa) subdivided, with normal noise (0.05 mm), holes cut out, and already reduced to its largest piece
(scan.clean_scan does that itself, so every candidate starts from there). Reported: whether the result is
watertight (no open edge), is one piece, its volume's error against the undamaged surface's (the truth), the
time (best of ``--repeats``) and that time relative to scan.py's: MeshFix's hole filling given only the
triangles near the holes (its loading alone takes seconds per hundred thousand triangles). Screened Poisson is
run only on scans up to ``--poisson-max-triangles``.
A candidate whose package is not installed is listed as such (PyMeshLab and Open3D are not project
dependencies: ``pip install pymeshlab`` to include it).

Run: ``.venv/bin/python bench/scan_repair.py [--levels 2,4] [--holes 6] [--repeats 2]``
"""

import argparse
import importlib.util
import time

import numpy as np

from phantom.model.fem.model import PhantomModel
from phantom.model.mesh.surface import TriangleMesh, compact, model_surface, triangle_areas_mm2
from phantom.model.mesh.tetmesh import enclosed_volume_m3, open_edge_count, surface_components
from phantom.model.scene import load_scene
from phantom.scan.compare import close_holes, largest_component
from phantom.scan.synthetic import make_scan


def trimesh_fill(mesh):
    import trimesh

    surface = trimesh.Trimesh(mesh.vertices_mm, mesh.triangles, process=False)
    trimesh.repair.fill_holes(surface)
    return TriangleMesh(np.asarray(surface.vertices), np.asarray(surface.faces))


def meshfix_local(mesh):
    return close_holes(mesh)[0]


def meshfix_fill(mesh):
    import pymeshfix

    surface = pymeshfix.PyTMesh()
    surface.set_quiet(True)
    surface.load_array(mesh.vertices_mm, mesh.triangles.astype(np.int32))
    surface.fill_small_boundaries(nbe=0, refine=True)
    vertices, faces = surface.return_arrays()
    return TriangleMesh(np.asarray(vertices, np.float64), np.asarray(faces, np.int64))


def meshfix_full(mesh):
    import pymeshfix

    fixer = pymeshfix.MeshFix(mesh.vertices_mm, mesh.triangles.astype(np.int32))
    fixer.repair()
    return TriangleMesh(np.asarray(fixer.points), np.asarray(fixer.faces))


def meshlab_close_holes(mesh):
    import pymeshlab

    meshes = pymeshlab.MeshSet()
    meshes.add_mesh(pymeshlab.Mesh(mesh.vertices_mm, mesh.triangles.astype(np.int32)))
    meshes.meshing_close_holes(maxholesize=100000)
    out = meshes.current_mesh()
    return TriangleMesh(out.vertex_matrix(), out.face_matrix().astype(np.int64))


def meshlab_poisson(mesh):
    import pymeshlab

    meshes = pymeshlab.MeshSet()
    meshes.add_mesh(pymeshlab.Mesh(mesh.vertices_mm, mesh.triangles.astype(np.int32)))
    meshes.compute_normal_per_vertex()
    meshes.generate_surface_reconstruction_screened_poisson(depth=8, preclean=True)
    out = meshes.current_mesh()
    return TriangleMesh(out.vertex_matrix(), out.face_matrix().astype(np.int64))


CANDIDATES = (
    ("MeshFix fill_small_boundaries on the holes' neighbourhood (scan.py)", "pymeshfix", meshfix_local),
    ("MeshFix fill_small_boundaries on the whole scan", "pymeshfix", meshfix_fill),
    ("MeshFix full repair (pymeshfix)", "pymeshfix", meshfix_full),
    ("trimesh.repair.fill_holes (with networkx)", "networkx", trimesh_fill),
    ("PyMeshLab meshing_close_holes", "pymeshlab", meshlab_close_holes),
    ("PyMeshLab screened Poisson, depth 8", "pymeshlab", meshlab_poisson),
    ("Open3D", "open3d", None),
)


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--levels", default="2,4", help="midpoint subdivisions of the model surface (scan size)")
    parser.add_argument("--holes", type=int, default=6)
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--poisson-max-triangles", type=int, default=100000)
    args = parser.parse_args()
    model = PhantomModel.from_scene(load_scene("builtin:calibrated"))
    state = model.equilibrium([1e3, 2e3, 0.5e3])
    surface = model_surface(state.positions_m, model.outer_triangles)
    truth_ml = enclosed_volume_m3(surface.vertices_mm, surface.triangles) * 1e-3
    for levels in (int(level) for level in args.levels.split(",")):
        scan = make_scan(surface, np.random.default_rng(3), levels=levels, noise_mm=0.05, holes=args.holes,
                         hole_radius_mm=3.0).mesh
        keep, _ = largest_component(scan.triangles, triangle_areas_mm2(scan.vertices_mm, scan.triangles))
        scan = compact(scan.vertices_mm, scan.triangles[keep])
        print(f"\nscan: {len(scan.vertices_mm)} vertices, {len(scan.triangles)} triangles, "
              f"{open_edge_count(scan.triangles)} open edges; truth {truth_ml:.4f} ml\n")
        print("| method | watertight | pieces | volume error | time | time / scan.py |")
        print("|---|---|---|---|---|---|")
        reference_s = None
        for name, package, repair in CANDIDATES:
            if importlib.util.find_spec(package) is None or repair is None:
                print(f"| {name} | not measured: `{package}` is not installed | | | | |")
                continue
            if repair is meshlab_poisson and len(scan.triangles) > args.poisson_max_triangles:
                print(f"| {name} | not run above {args.poisson_max_triangles} triangles (slow) | | | | |")
                continue
            times = []
            for _ in range(args.repeats):
                started = time.perf_counter()
                result = repair(scan)
                times.append(time.perf_counter() - started)
            elapsed = min(times)
            reference_s = reference_s or elapsed
            open_edges = open_edge_count(result.triangles)
            pieces = surface_components(result.triangles).max() + 1
            volume_ml = abs(enclosed_volume_m3(result.vertices_mm, result.triangles)) * 1e-3
            error = f"{100 * (volume_ml - truth_ml) / truth_ml:+.3f} %" if open_edges == 0 else "undefined"
            print(f"| {name} | {'yes' if open_edges == 0 else f'no ({open_edges} open edges)'} | {pieces} | "
                  f"{error} | {elapsed:.3f} s | {elapsed / reference_s:.2f} |")


if __name__ == "__main__":
    main()
