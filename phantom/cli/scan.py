"""Subcommand of ``phantom``: ``compare-scan`` (a 3D scan of the phantom against the model).

Only argparse is imported at module load; the handler imports what it needs when it runs.
"""

import argparse


def register(subparsers: argparse._SubParsersAction) -> None:
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
    compare.set_defaults(run=run_compare_scan)


def run_compare_scan(args: argparse.Namespace) -> int:
    """Handler of ``phantom compare-scan``."""
    import json
    from pathlib import Path

    import numpy as np

    from phantom.cli.common import parse_numbers
    from phantom.model.errors import SolveError
    from phantom.model.fem.model import PhantomModel
    from phantom.model.scene import load_scene
    from phantom.scan.compare import StageClock, compare, model_surface, read_scan, rotation_axis
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
        state = model.solve([p * 1e3 for p in pressures_kpa])
    result = compare(scan, model_surface(state.positions_m, model.outer_triangles), state.gland_volume_m3 * 1e6,
                     args.units, clock=clock)
    from phantom.cli.common import chamber_labels

    labels = chamber_labels(scene.raw, list(model.chamber_names))
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
                        "heatmap": str(heatmap), "recording": None if recording is None else str(recording)})
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
    print(f"heatmap    {heatmap}")
    if recording is not None:
        print(f"recording  {recording}")
    return 0
