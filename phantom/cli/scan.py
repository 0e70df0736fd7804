"""Subcommands of ``phantom``: ``compare-scan`` (a 3D scan of the phantom against the model) and ``scan
synthetic`` (a scan of the model with known damage, to try compare-scan on).

Only argparse is imported at module load; the handlers import what they need when they run.
"""

from __future__ import annotations

import argparse


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """Add ``compare-scan`` to the ``phantom`` parser."""
    compare = subparsers.add_parser(
        "compare-scan", help="compare a 3D scan (OBJ, PLY, STL) with the model's shape at given pressures",
        description="Read a scan of the phantom, clean it (largest piece, stray fragments removed, holes closed), "
                    "align it rigidly to the model's deformed outer surface at the given pressures, and report "
                    "the transform, the volumes and the closest-point distances; write the signed distance on the "
                    "model as a heatmap PNG (and, with --rerun-save, a Rerun recording).")
    compare.add_argument("scan", metavar="SCAN", help="the scan file: .obj, .ply or .stl")
    compare.add_argument("--scene", required=True, help="a scene TOML path, 'builtin' or 'builtin:calibrated'")
    compare.add_argument("--pressures-kpa", required=True,
                         help="the chamber pressures (kPa, chamber order) the scan was taken at, e.g. 1,1,1")
    compare.add_argument("--units", choices=("mm", "cm", "m"), default="mm",
                         help="unit of the scan's coordinates (default mm)")
    compare.add_argument("--out", default="out", help="folder for the heatmap PNG (created if missing; default out)")
    compare.add_argument("--rerun-save", metavar="FILE", help="also write a Rerun recording (.rrd) of the result")
    compare.add_argument("--size-mm", type=float, default=None, help="element size of the built-in mesh (mm)")
    compare.add_argument("--json", action="store_true", help="print one JSON object instead of text")
    compare.add_argument("--shape-run", metavar="RUN",
                         help="a trained shape analysis run (phantom shape train): also report the latent distance "
                              "between the scan and the model's shape (the paper's Fig. 9)")
    compare.set_defaults(run=run_compare_scan)

    scan = subparsers.add_parser("scan", help="scans of the phantom: 'synthetic' writes one made from the model",
                                 description="Scans of the phantom. 'phantom scan synthetic' writes a scan made "
                                             "from the model's deformed surface, with known damage.")
    actions = scan.add_subparsers(dest="scan_action", metavar="synthetic", required=True)
    synthetic = actions.add_parser(
        "synthetic", help="write a synthetic scan (mm) of the model's deformed surface, e.g. for compare-scan",
        description="Solve the scene's model at the given pressures and write its deformed outer surface as a scan "
                    "(mm): subdivided, with noise along the normals, holes, a stray fragment and a random rigid "
                    "motion, as a photogrammetry scan would have them.")
    synthetic.add_argument("--out", required=True, help="file to write: .ply, .stl or .obj")
    synthetic.add_argument("--scene", default="builtin:calibrated",
                           help="a scene TOML path, 'builtin' or 'builtin:calibrated' (default)")
    synthetic.add_argument("--pressures-kpa", default="1,2,0.5",
                           help="the chamber pressures (kPa, chamber order; default 1,2,0.5)")
    synthetic.add_argument("--modulus-factor", type=float, default=1.0,
                           help="make the scan from the model with E times this (another material)")
    synthetic.add_argument("--noise-mm", type=float, default=0.05, help="noise along the normals (mm, sigma)")
    synthetic.add_argument("--holes", type=int, default=3, help="holes cut out of the surface")
    synthetic.add_argument("--levels", type=int, default=2, help="midpoint subdivisions (4: about 250k vertices)")
    synthetic.add_argument("--seed", type=int, default=0, help="seed of the noise, holes and motion")
    synthetic.set_defaults(run=run_synthetic_scan)


def run_compare_scan(args: argparse.Namespace) -> int:
    """Handler of ``phantom compare-scan``."""
    import json
    from pathlib import Path

    import numpy as np

    from phantom.cli.common import parse_numbers
    from phantom.model.errors import SolveError
    from phantom.model.fem.model import PhantomModel
    from phantom.model.mesh.surface import model_surface, rotation_axis
    from phantom.model.scene import load_scene
    from phantom.scan.compare import StageClock, compare, read_scan
    from phantom.scan.heatmap import write_heatmap, write_recording

    pressures_kpa = parse_numbers(args.pressures_kpa, "--pressures-kpa")
    clock = StageClock()
    with clock.stage("read"):
        scan = read_scan(args.scan, args.units)
    with clock.stage("model"):
        scene = load_scene(args.scene)
        model = PhantomModel.from_scene(scene, mesh_size_mm=args.size_mm)
        if len(pressures_kpa) != model.n_chambers:
            raise SolveError(f"--pressures-kpa has {len(pressures_kpa)} values; the scene has {model.n_chambers} "
                             f"chambers ({', '.join(model.chamber_names)})")
        state = model.equilibrium([p * 1e3 for p in pressures_kpa])
    model_mesh = model_surface(state.positions_m, model.outer_triangles)
    result = compare(scan, model_mesh, state.gland_volume_m3 * 1e6, args.units, clock=clock)
    shape_latent_distance = None
    if args.shape_run:
        from phantom.shape.compare import latent_distance

        with clock.stage("shape"):
            shape_latent_distance = latent_distance(args.shape_run, model_mesh, result.scan_aligned)
    labels = scene.chamber_labels
    at = ", ".join(f"{label} {p:g}" for label, p in zip(labels, pressures_kpa, strict=True))
    distance = result.symmetric_mm
    title = (f"{Path(args.scan).name} against the model at {at} kPa\nmean {distance['mean']:.3f}, "
             f"p95 {distance['p95']:.3f}, max {distance['max']:.3f} mm; volume {result.scan_volume_ml:.2f} ml "
             f"(model {result.model_volume_ml:.2f} ml)")
    with clock.stage("heatmap"):
        heatmap = write_heatmap(result, Path(args.out) / f"{Path(args.scan).stem}_vs_model.png", title)
    recording = None
    if args.rerun_save:
        with clock.stage("rerun"):
            recording = write_recording(result, args.rerun_save)
    alignment = result.alignment
    if args.json:
        summary = result.to_json()
        summary.update({"scan": str(args.scan), "units": args.units, "scene": args.scene,
                        "chamber_names": model.chamber_names, "pressures_kpa": [float(p) for p in pressures_kpa],
                        "heatmap": str(heatmap), "recording": None if recording is None else str(recording),
                        "latent_distance": shape_latent_distance, "shape_run": args.shape_run})
        summary["transform"]["rotation_axis"] = rotation_axis(alignment.rotation).tolist()
        print(json.dumps(summary))
        return 0
    axis = np.array2string(rotation_axis(alignment.rotation), precision=3, separator=", ")
    shift = np.array2string(alignment.translation_mm, precision=2, separator=", ")
    scan_to_model, model_to_scan = result.scan_to_model_mm, result.model_to_scan_mm
    print(f"scan       {args.scan} ({args.units}): {result.clean.summary()}")
    print(f"model      {args.scene} ({model.formulation}) at {at} kPa")
    print(f"transform  rotation {alignment.rotation_angle_deg:.2f} deg about {axis}, translation {shift} mm "
          f"(scan to model); fit RMS {alignment.rms_mm:.3f} mm after {alignment.iterations} ICP iterations")
    if alignment.ambiguous:
        print(f"           ambiguous: a rotation by {alignment.alternative_angle_deg:.0f} deg from this one fits "
              f"almost as well (RMS {alignment.alternative_rms_mm:.3f} mm): the shape is nearly symmetric")
    change = 100 * (result.scan_volume_ml - result.model_volume_ml) / result.model_volume_ml
    print(f"volume     scan {result.scan_volume_ml:.3f} ml, model gland {result.model_volume_ml:.3f} ml "
          f"({change:+.2f} %)")
    print(f"distance   mean {distance['mean']:.3f}, median {distance['median']:.3f}, p95 {distance['p95']:.3f}, "
          f"max {distance['max']:.3f} mm (both ways; scan to model mean {scan_to_model['mean']:.3f}, "
          f"model to scan mean {model_to_scan['mean']:.3f})")
    if shape_latent_distance is not None:
        print(f"shape      latent distance {shape_latent_distance:.3f} (run {args.shape_run})")
    print(f"heatmap    {heatmap}")
    if recording is not None:
        print(f"recording  {recording}")
    return 0


def run_synthetic_scan(args: argparse.Namespace) -> int:
    """Handler of ``phantom scan synthetic``."""
    import meshio
    import numpy as np

    from phantom import PhantomError
    from phantom.cli.common import output_file, parse_numbers
    from phantom.model.fem.model import PhantomModel
    from phantom.model.mesh.surface import model_surface
    from phantom.model.scene import load_scene
    from phantom.scan.synthetic import make_scan, random_rotation

    if not args.modulus_factor > 0 or args.noise_mm < 0 or args.holes < 0 or args.levels < 0:
        raise PhantomError("--modulus-factor must be positive, and --noise-mm, --holes and --levels not negative")
    pressures_kpa = parse_numbers(args.pressures_kpa, "--pressures-kpa")
    model = PhantomModel.from_scene(load_scene(args.scene))
    if args.modulus_factor != 1.0:
        model = model.with_material(youngs_modulus_pa=args.modulus_factor * model.material.youngs_modulus_pa)
    state = model.equilibrium([p * 1e3 for p in pressures_kpa])
    rng = np.random.default_rng(args.seed)
    scan = make_scan(model_surface(state.positions_m, model.outer_triangles), rng, levels=args.levels,
                     noise_mm=args.noise_mm, holes=args.holes, fragment=True, rotation=random_rotation(rng),
                     translation_mm=rng.uniform(-50.0, 50.0, 3))
    path = output_file(args.out)
    try:
        meshio.write_points_cells(path, scan.mesh.vertices_mm, [("triangle", scan.mesh.triangles.astype(np.int32))])
    except (OSError, KeyError, meshio.WriteError) as error:
        raise PhantomError(f"cannot write {path}: {error}; give a .ply, .stl or .obj --out") from None
    print(f"wrote {path}: {len(scan.mesh.vertices_mm)} vertices, gland {state.gland_volume_m3 * 1e6:.3f} ml")
    return 0
