"""Subcommands of ``phantom``: offline model commands: mesh, forward, model table (inverse and calibrate have
their own modules).

Only argparse is imported at module load; handlers import what they need when they run.
"""

from __future__ import annotations

import argparse
import contextlib
import os
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

from phantom import written_atomically

if TYPE_CHECKING:
    from phantom.model.fem.model import PhantomModel, State
    from phantom.model.scene import Scene


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """Add this part's subcommands to the ``phantom`` parser."""
    mesh = subparsers.add_parser(
        "mesh", help="write a scene's tetrahedral mesh (with its groups) to a file",
        description="Write the scene's mesh with its physical groups: .msh (MSH 4.1, named groups) or any "
                    "format meshio writes (.vtu keeps groups as cell data). Coordinates in the scene's unit.")
    mesh.add_argument("--scene", default="builtin:converged",
                      help="a scene TOML path, or 'builtin', 'builtin:calibrated', 'builtin:converged' (the default, "
                           "as for the other offline commands)")
    mesh.add_argument("--out", required=True, help="output file: .msh or .vtu, or another of the formats a refused "
                                                    "name lists")
    mesh.add_argument("--size-mm", type=float, default=None, help="element size of the built-in mesh (mm)")
    mesh.add_argument("--json", action="store_true", help="print one JSON object instead of a line")
    mesh.set_defaults(run=run_mesh)

    forward = subparsers.add_parser(
        "forward", help="solve the model at given chamber pressures: volumes, iterations, time",
        description="Solve the scene's model at gauge pressures (kPa, chamber order) and print the chamber "
                    "volumes, the gland volume and its change, the iterations and the solve time.")
    forward.add_argument("--scene", default="builtin:converged",
                         help="a scene TOML path, or 'builtin', 'builtin:calibrated', 'builtin:converged' (the "
                              "default: 10-node, converged, the deformed mesh to take into planning)")
    forward.add_argument("--pressures-kpa", required=True,
                         help="comma-separated gauge pressures in kPa, one per chamber, e.g. 1,1,1")
    # phantom.model.scene.MATERIAL_MODELS spelled out: importing the model for the parser would cost every CLI call
    forward.add_argument("--formulation", choices=("corotational", "linear", "neo_hookean", "gent", "yeoh"),
                         default=None,
                         help="override the scene's material model (gent needs the scene's gent_jm, yeoh its "
                              "yeoh_c20_over_c10 and yeoh_c30_over_c10)")
    forward.add_argument("--size-mm", type=float, default=None, help="element size of the built-in mesh (mm)")
    forward.add_argument("--out", default=None,
                         help="also write the deformed tetrahedral mesh (same nodes and groups as `phantom mesh`, "
                              "in the scene's unit) to this file; the format follows the extension (.msh, .vtu, "
                              "any meshio format, which also carries each element's volume ratio as cell data "
                              "'volume_ratio'); a surface format (.stl, .obj, .ply, .off) gets the deformed "
                              "outer surface of the gland, which compare-scan and robot planners read")
    forward.add_argument("--json", action="store_true", help="print one JSON object instead of a table")
    forward.set_defaults(run=run_forward)

    scene = subparsers.add_parser("scene", help="check a scene file", description="Work with scene files.")
    scene_actions = scene.add_subparsers(dest="action", metavar="ACTION", required=True)
    check = scene_actions.add_parser(
        "check", help="check a scene and print every value it resolves to, and where each came from",
        description="Read a scene as the model does (an unknown or misspelt key, a value out of range: one line, "
                    "exit status 2) and print each value of its tables as the model uses it, marked 'file' where "
                    "the file gives it and 'default' where it does not. A timeline scene (model = \"...\" and "
                    "[[steps]]) is checked as the daemon reads it: its model, what it overrides, its steps.")
    check.add_argument("scene", metavar="FILE", help="a scene TOML path, or 'builtin', 'builtin:calibrated', "
                                                     "'builtin:converged'")
    check.add_argument("--json", action="store_true", help="print one JSON object")
    check.set_defaults(run=run_scene_check)

    model = subparsers.add_parser("model", help="build what a scene ships with its model: model table",
                                  description="Offline builds of a scene's model.")
    actions = model.add_subparsers(dest="model_action", metavar="ACTION", required=True)
    table = actions.add_parser(
        "table", help="build a scene's response table and its shapes, and write what the scene ships of them",
        description="Solve the scene's model on its response table's grid ([model] table_points per axis over "
                    "0 to pressure_max_kpa), each point started from a solved neighbour, and write its volumes "
                    "(the scene's [model] table_volumes) and its outer surface's shapes on the coarser shipped "
                    "grid, taken from the same solves (its [model] table_shapes). The solves run as Dask tasks "
                    "on this machine's cores or an existing cluster; each solved point is kept on disk, so the "
                    "same command after a kill resumes where it stopped. A table already in the cache is read.")
    table.add_argument("scene", metavar="SCENE", help="a scene TOML path, or 'builtin', 'builtin:calibrated', "
                                                      "'builtin:converged'")
    table.add_argument("--out", help="the volumes' .npz to write (the scene's [model] table_volumes)")
    table.add_argument("--shapes-out", help="the outer surface's shapes' .npz to write ([model] table_shapes)")
    where = table.add_mutually_exclusive_group()
    where.add_argument("--workers", type=int, metavar="N",
                       help="worker processes of the LocalCluster (default: the cores; 1: in this process)")
    where.add_argument("--scheduler", metavar="ADDRESS",
                       help="address of a running Dask scheduler (tcp://HOST:8786) to run the solves on")
    table.set_defaults(run=run_table)


def _single_threaded_blas() -> None:
    """One BLAS thread: the solver's small dense kernels only lose time to OpenBLAS threads on 2 busy cores."""
    for variable in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS"):
        os.environ.setdefault(variable, "1")


def run_mesh(args: argparse.Namespace) -> int:
    """Write the scene's mesh to ``--out``."""
    from phantom.cli.common import MAX_MESH_BYTES, MESH_TOO_LARGE, check_input_size
    from phantom.model.errors import MeshError
    from phantom.model.mesh.prostate import builtin_prostate
    from phantom.model.mesh.tetmesh import read_mesh, write_mesh
    from phantom.model.scene import load_scene

    out = _checked_out(args.out, MESH_FORMATS)
    scene = load_scene(args.scene)
    if scene.mesh == "builtin:prostate":
        mesh = builtin_prostate(args.size_mm, scene.geometry)
    elif args.size_mm is not None:
        raise MeshError(f"--size-mm applies to the built-in mesh only; {scene.mesh} is read as it is")
    else:
        check_input_size(scene.mesh, MAX_MESH_BYTES, "the scene's mesh file", MeshError, MESH_TOO_LARGE)
        mesh = read_mesh(scene.mesh, scene.length_scale_m)
    with _folders_made_for(out) as made:
        write_mesh(mesh, out, scene.length_scale_m)
    if args.json:
        import json

        print(json.dumps({"out": args.out, "nodes": mesh.n_nodes, "tetrahedra": len(mesh.tets),
                          "groups": list(mesh.surface_groups)}))
    else:
        print(f"wrote {args.out}: {mesh.n_nodes} nodes, {len(mesh.tets)} tetrahedra, groups "
              f"{', '.join(mesh.surface_groups)}{_made_note(made)}")
    return 0


def run_forward(args: argparse.Namespace) -> int:
    """Solve at the given pressures and print the state as a table or JSON."""
    _single_threaded_blas()
    import json
    import time

    from phantom.cli.common import MAX_MESH_BYTES, MESH_TOO_LARGE, check_input_size, scene_pressures_kpa
    from phantom.model.errors import MeshError
    from phantom.model.fem.model import PhantomModel
    from phantom.model.scene import load_scene

    started = time.perf_counter()
    out = _checked_out(args.out, VOLUME_FORMATS + SURFACE_FORMATS) if args.out else None
    scene = load_scene(args.scene)
    args.pressures_kpa = scene_pressures_kpa(args.pressures_kpa, scene)
    check_input_size(scene.mesh, MAX_MESH_BYTES, "the scene's mesh file", MeshError, MESH_TOO_LARGE)
    model = PhantomModel.from_scene(scene, mesh_size_mm=args.size_mm)
    state = model.equilibrium([p * 1e3 for p in args.pressures_kpa], formulation=args.formulation)
    total_s = time.perf_counter() - started
    made = None
    if out:
        with _folders_made_for(out) as made:
            _write_deformed(model, state, out, scene.length_scale_m)
    rest_ml = model.rest_gland_volume_m3 * 1e6
    # how far the material compressed or swelled: det F per 4-node element, the dilatation per 10-node one
    volume_ratios = model.body.element_volume_ratios(state.positions_m)
    if args.json:
        print(json.dumps({
            "chamber_names": model.chamber_names,
            "pressures_kpa": [float(p) for p in args.pressures_kpa],
            "chamber_volumes_ml": [float(v) * 1e6 for v in state.chamber_volumes_m3],
            "rest_chamber_volumes_ml": [float(v) * 1e6 for v in model.rest_chamber_volumes_m3],
            "total_volume_ml": float(state.gland_volume_m3) * 1e6,
            "rest_total_volume_ml": rest_ml,
            "volume_change_ml": float(state.gland_volume_m3) * 1e6 - rest_ml,
            "iterations": int(state.iterations),
            "solve_time_s": float(state.solve_time_s),
            "model_time_s": total_s,
            "formulation": state.formulation,
            "element_order": model.order,
            "element_volume_ratio_range": [float(volume_ratios.min()), float(volume_ratios.max())],
            "out": args.out,
        }))
        return 0
    labels = scene.chamber_labels
    print(f"{'chamber':<12} {'pressure kPa':>12} {'rest ml':>9} {'volume ml':>10} {'change ml':>10}")
    for label, pressure, rest, volume in zip(labels, args.pressures_kpa, model.rest_chamber_volumes_m3,
                                             state.chamber_volumes_m3, strict=True):
        print(f"{label:<12} {pressure:>12.3f} {rest * 1e6:>9.3f} {volume * 1e6:>10.3f} {(volume - rest) * 1e6:>10.3f}")
    gland_ml = state.gland_volume_m3 * 1e6
    print(f"{'gland':<12} {'':>12} {rest_ml:>9.3f} {gland_ml:>10.3f} {gland_ml - rest_ml:>10.3f}")
    print(f"{state.formulation} model, {model.nodes_m.shape[0]} nodes, {len(model.tets)} tetrahedra, "
          f"E = {model.material.youngs_modulus_pa / 1e3:g} kPa, nu = {model.material.poisson_ratio:g}: "
          f"{state.iterations} Newton iterations, solve {state.solve_time_s:.3f} s, model total {total_s:.3f} s; "
          f"element volume ratios {volume_ratios.min():.4f} to {volume_ratios.max():.4f}")
    if args.out:
        print(f"wrote the deformed mesh to {args.out}{_made_note(made)}")
    return 0


def run_table(args: argparse.Namespace) -> int:
    """Build (or read from the cache) the scene's response table and write its volumes and shapes."""
    _single_threaded_blas()
    from phantom import PhantomError
    from phantom.cli.common import output_file
    from phantom.model.cluster import stderr_progress
    from phantom.model.fem.model import PhantomModel
    from phantom.model.fidelity.response_table import (
        build_table_shapes,
        response_table,
        write_table_shapes,
        write_table_volumes,
    )
    from phantom.model.scene import load_scene, scene_from_dict, without_shipped_tables

    if not args.out and not args.shapes_out:
        raise PhantomError("phantom model table needs --out, --shapes-out or both: the files to write")
    if args.workers is not None and args.workers < 1:
        raise PhantomError(f"--workers must be at least 1, got {args.workers}")
    # the files' folders before the build (which may take an hour), not after
    out = output_file(args.out) if args.out else None
    shapes_out = output_file(args.shapes_out, "--shapes-out") if args.shapes_out else None
    loaded = load_scene(args.scene)
    # the full table, not what the scene may ship already (or names before it is written)
    model = PhantomModel.from_scene(scene_from_dict(without_shipped_tables(loaded.raw), loaded.path))
    settings = model.model_settings
    table = None
    if out:
        table = response_table(model, settings.pressure_max_pa, settings.table_points,
                               stderr_progress("table: full solves"), args.workers, args.scheduler)
        write_table_volumes(table, model, out)
        print(f"wrote {args.out}: {table.points_per_axis}^{table.n_chambers} points, within "
              f"{table.check_errors_pct:.2g} % of full solves at its checks (built in {table.build_time_s:.0f} s)")
    if shapes_out:
        shapes = build_table_shapes(model, settings.pressure_max_pa, progress=stderr_progress("shapes: full solves"),
                                    workers=args.workers, scheduler=args.scheduler, table=table)
        write_table_shapes(shapes, model, shapes_out)
        print(f"wrote {args.shapes_out}: {len(shapes.nodes)} outer-surface nodes on "
              f"{shapes.table.points_per_axis}^{shapes.table.n_chambers} points, within "
              f"{shapes.check_error_m * 1e3:.3g} mm of full solves at its checks")
    return 0


#: Formats that hold triangles only: ``forward --out`` writes the deformed outer surface to them (a tetrahedral
#: mesh's surface groups alone, the chamber walls and the fixation, would not describe the gland).
SURFACE_FORMATS = (".stl", ".obj", ".ply", ".off")
#: The formats ``--out`` writes a tetrahedral mesh to, 4- or 10-node, with its nodes: .msh by gmsh (MSH 4.1, named
#: groups), the others by meshio (tests/test_model_cli_inputs.py writes and reads back each). The rest of meshio's
#: drop 10-node elements (.mesh, .ugrid, .tec, .avs, .xml, .ele), need a library the package does not install
#: (h5py, netCDF4: .xdmf, .med, .exo, .cgns, ...), hold no tetrahedra (.wkt, .svg) or fail (.su2, .f3grid, .gz).
VOLUME_FORMATS = (".msh", ".vtu", ".vtk", ".inp", ".bdf", ".nas", ".fem", ".mdpa", ".vol", ".post", ".dato")
#: What ``phantom mesh --out`` writes: the tetrahedral formats, and the triangle formats meshio writes a mesh's
#: surface groups to (its tetrahedra dropped; .obj refuses a mesh with tetrahedra).
MESH_FORMATS = (*VOLUME_FORMATS, ".stl", ".ply", ".off")


def _checked_out(out: str, formats: tuple[str, ...], option: str = "--out") -> Path:
    """``--out``, refused in one line before any work when its extension is not one of ``formats`` or it cannot be
    written (a folder, a path under a file, a folder this user cannot write); its missing folders are made only
    when it is written (:func:`_folders_made_for`)."""
    from phantom.cli.common import check_output_file
    from phantom.model.errors import MeshError

    path = Path(out)
    suffix = path.suffix.lower()
    if suffix not in formats:
        said = f"its extension {suffix!r} is not a format it writes" if suffix else "it has no extension"
        surfaces = [suffix for suffix in formats if suffix not in VOLUME_FORMATS]
        surface_words = ("its surface groups' triangles" if formats == MESH_FORMATS
                         else "the deformed gland's outer surface")
        raise MeshError(f"{option} {out}: {said}: end it with one of {', '.join(VOLUME_FORMATS)} (the tetrahedral "
                        f"mesh with its groups) or {', '.join(surfaces)} ({surface_words})")
    return check_output_file(path, option, f"deformed{formats[0]}", MeshError)


@contextlib.contextmanager
def _folders_made_for(path: Path) -> Iterator[Path | None]:
    """The missing folders of ``path`` made for the ``with`` body that writes it (as model/README.md documents),
    and removed again when it fails, so that a refused or failed write leaves no folder behind; yields the
    topmost folder made (None when none was)."""
    from phantom.cli.common import output_file

    missing = []
    for folder in path.absolute().parents:
        if folder.exists():
            break
        missing.append(folder)
    try:
        output_file(path)
        yield missing[-1] if missing else None
    except BaseException:
        for folder in missing:  # the deepest first; a folder something else wrote into stays
            try:
                folder.rmdir()
            except OSError:
                break
        raise


def _made_note(made: Path | None) -> str:
    return f" (made the folder {made})" if made else ""


def _write_deformed(model: PhantomModel, state: State, path: Path, length_scale_m: float) -> None:
    """The deformed mesh to ``path`` (its folder there), coordinates in the scene's unit; the outer surface only
    for a surface format."""
    from phantom.model.errors import MeshError
    from phantom.model.mesh.tetmesh import write_mesh

    if path.suffix.lower() in SURFACE_FORMATS:
        import meshio

        surface_nodes, triangles = model.outer_surface()
        surface = meshio.Mesh(state.positions_m[surface_nodes] / length_scale_m, [("triangle", triangles)])
        with written_atomically(path, MeshError) as temporary:
            surface.write(temporary, file_format=meshio.extension_to_filetypes[path.suffix.lower()][0])
        return
    # each element's volume ratio (det F; a 10-node element's dilatation) travels with a meshio format
    write_mesh(model.deformed_mesh(state), path, length_scale_m,
               {"volume_ratio": model.body.element_volume_ratios(state.positions_m)})


#: How a .npz file (a zip archive of .npy arrays, numpy.savez's) starts.
NPZ_START = b"PK\x03\x04"


def _check_named_files(scene: Scene) -> None:
    """What ``scene check`` adds to the reader's checks before it says valid: the table files the scene names are
    .npz files (the reader leaves their contents to the model that reads them, which refuses a bad one in its own
    words), and its mesh file is there: a warning on stderr only, as a scene may be written before its mesh is
    (tests/test_scene.py checks such a scene; every command that meshes refuses it)."""
    import sys

    from phantom.model.errors import SceneError

    where = f"scene {scene.path}"
    if scene.mesh != "builtin:prostate" and not Path(scene.mesh).is_file():
        print(f"phantom scene: warning: {where}: [phantom] mesh names {scene.mesh}, which is not a file: every "
              f"command that meshes the scene will refuse it; give a mesh file's path (taken from the scene's "
              f"folder) or 'builtin:prostate'", file=sys.stderr)
    settings = scene.model_settings
    for key, file in (("table_volumes", settings.table_volumes), ("table_shapes", settings.table_shapes)):
        if file is None:
            continue
        try:
            with open(file, "rb") as opened:
                start = opened.read(len(NPZ_START))
        except OSError as error:
            raise SceneError(f"{where}: [model] {key} names {file}, which cannot be read ({error.strerror}): make "
                             f"it readable, or remove the key") from None
        if start != NPZ_START:
            raise SceneError(f"{where}: [model] {key} names {file}, which is not a .npz: name the one phantom model "
                             f"table wrote (--out for table_volumes, --shapes-out for table_shapes), or remove the key")


def _check_timeline_scene(args: argparse.Namespace, raw: dict[str, Any]) -> int:
    """A timeline scene (``raw``: its file's TOML) checked as ``run_scene`` reads it, without a daemon: its model
    (and what the file overrides of it), its steps against the model's chambers, its timeline; a shape step's file
    is solved when it runs, so here it must only be there. Prints what it found (``--json``: as one object)."""
    import json

    from phantom.host.handlers import prepare_scene_run
    from phantom.host.scenes import read_timeline_scene, shape_steps
    from phantom.model.errors import SceneError

    path = Path(args.scene)
    # (the daemon counts a file's steps before it parses it; here it is parsed: its timeline's check counts them)
    timeline = read_timeline_scene(path, raw)
    scene = timeline.scene
    shaped = shape_steps(scene.raw.get("steps"), path.parent)
    for index, keys in shaped:
        if not Path(str(keys["shape"])).is_file():
            raise SceneError(f"{path}: steps[{index}]'s shape {keys['shape']} is not a file: give the path of a "
                             "NIfTI mask or closed mesh (relative to the scene's folder)")
    # a shape step is played as the pressures its shape inverse answers when the scene is run: any will do here
    prepared = prepare_scene_run(scene, str(path), list(scene.chambers), 1.0,
                                 {index: [0.0] * len(scene.chambers) for index, _ in shaped})
    steps, end_s = len(prepared.timeline.steps), prepared.end_s
    if args.json:
        print(json.dumps({"scene": str(path), "timeline": True, "model": timeline.model,
                          "overrides": timeline.overrides, "steps": steps, "shape_steps": len(shaped),
                          "end_s": end_s}))
        return 0
    print(f"scene {path}: valid, a timeline scene: {steps} step(s) over {end_s:g} s on its model {timeline.model}"
          + (f", {len(shaped)} of them shapes solved when it is run" if shaped else ""))
    print(f"  it overrides {', '.join(timeline.overrides)}" if timeline.overrides else "  it overrides nothing")
    print("  play it with phantom run-scene (a daemon on its model) or phantom daemon --scene; a target beyond "
          "the phantom's range is refused when it is run")
    return 0


def run_scene_check(args: argparse.Namespace) -> int:
    """Print the scene's resolved values and their sources; a timeline scene (one that names its model) is checked
    as the daemon reads it (:func:`_check_timeline_scene`)."""
    import json

    from phantom.model.scene import BUILTIN_SCENES, load_scene, read_scene_toml, resolved_scene, scene_from_dict

    if args.scene in BUILTIN_SCENES:
        scene = load_scene(args.scene)
    else:
        raw = read_scene_toml(args.scene)
        if isinstance(raw.get("model"), str):
            return _check_timeline_scene(args, raw)
        scene = scene_from_dict(raw, Path(args.scene))
    _check_named_files(scene)
    rows = resolved_scene(scene)
    if args.json:
        resolved: dict[str, dict[str, dict[str, object]]] = {}
        for section, key, value, from_file in rows:
            resolved.setdefault(section, {})[key] = {"value": value, "from": "file" if from_file else "default"}
        print(json.dumps({"scene": str(scene.path), "resolved": resolved}))
        return 0
    print(f"scene {scene.path}: valid")
    section_now = ""
    for section, key, value, from_file in rows:
        if section != section_now:
            print(f"[{section}]")
            section_now = section
        line = f"  {key} = {json.dumps(value)}"
        print(f"{line:<64} # {'file' if from_file else 'default'}")
    return 0
