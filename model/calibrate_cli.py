"""``phantom calibrate``: fit material and geometry to measured volumes (offline, Dask sweep), and
``phantom calibrate record``: measure those volumes on a board.

Only argparse is imported at module load; handlers import what they need when they run.
"""

import argparse

#: The grid swept when none is given, per material law: stiffening (Jm) and the chambers' size.
DEFAULT_GRIDS = {
    "gent": ["gent_jm=2.5,5,10", "base_chamber_scale=0.85,1", "lobe_chamber_scale=1,1.1,1.2"],
    "neo_hookean": ["base_chamber_scale=0.85,1", "lobe_chamber_scale=1,1.1,1.2"],
    "corotational": ["lobe_chamber_scale=1,1.2"],
    "linear": ["lobe_chamber_scale=1,1.2"],
}


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add ``calibrate`` (and its ``record`` subcommand) to the ``phantom`` parser."""
    calibrate = subparsers.add_parser(
        "calibrate", help="fit material and geometry to measured volumes (offline); 'record' measures them",
        description="Fit the scene's Young's modulus and a grid of material and geometry parameters to measured "
                    "gland volumes by least squares, with leave-one-out cross-validation and physical validity "
                    "as a constraint; the forward solves run as Dask tasks (cached). Writes a scene with the fit. "
                    "'phantom calibrate record' holds pressures on a board and asks for the volume at each.")
    calibrate.add_argument("--scene", default="builtin", help="scene TOML path or 'builtin' (default)")
    calibrate.add_argument("--measurements", help="CSV with columns p0_kpa,p1_kpa,...,measured_ml")
    calibrate.add_argument("--material", choices=("gent", "neo_hookean", "corotational", "linear"),
                           help="material law to fit (default: the scene's)")
    calibrate.add_argument("--gent-jm", type=float, help="Gent Jm when --material gent and Jm is not swept")
    calibrate.add_argument("--grid", action="append", metavar="NAME=V1,V2,...",
                           help="a swept parameter and its values (repeat; default: a grid per law, see "
                                "README); names: gent_jm, poisson_ratio, or any [geometry] key")
    calibrate.add_argument("--size-mm", type=float, help="element size of the built-in mesh (mm; default: the "
                                                         "scene's [geometry] mesh_size_mm, 2.5)")
    calibrate.add_argument("--scheduler", help="address of a running Dask scheduler (default: a LocalCluster "
                                               "on this machine's cores)")
    calibrate.add_argument("--workers", type=int, help="workers of the LocalCluster (default: the cores)")
    calibrate.add_argument("--output", help="scene file to write (default: <scene>_calibrated.toml here)")
    calibrate.add_argument("--json", action="store_true", help="print one JSON object")
    calibrate.set_defaults(run=run_calibrate)


def _scene_for(args):
    """The scene, with --material, --gent-jm and --size-mm applied to its table."""
    from phantom import PhantomError
    from phantom.model.calibrate import scene_with
    from phantom.model.scene import load_scene, scene_from_dict

    scene = load_scene(args.scene)
    document = scene.raw
    if args.material:
        document = scene_with(document, {})
        document.setdefault("material", {})["model"] = args.material
        if args.material != "gent":
            document["material"].pop("gent_jm", None)
    if args.gent_jm is not None:
        document = scene_with(document, {"gent_jm": args.gent_jm})
    if args.size_mm is not None:
        if scene.geometry is None:
            raise PhantomError(f"--size-mm applies to the built-in mesh only; {scene.mesh} is read as it is")
        document = scene_with(document, {"mesh_size_mm": args.size_mm})
    if document is not scene.raw:
        material = document.setdefault("material", {})
        if material.get("model") == "gent" and "gent_jm" not in material:
            grid_names = [item.partition("=")[0].strip() for item in args.grid or DEFAULT_GRIDS["gent"]]
            if "gent_jm" not in grid_names:
                raise PhantomError("--material gent needs --gent-jm VALUE or a --grid gent_jm=V1,V2,...")
            material["gent_jm"] = 10.0  # a placeholder: the grid sets Jm at every point
        scene = scene_from_dict(document, scene.path)
    return scene


def run_calibrate(args) -> int:
    """Handler of ``phantom calibrate``."""
    import json
    from pathlib import Path

    from phantom import PhantomError
    from phantom.model.calibrate import calibrate, load_measurements, parse_grid, write_calibrated_scene
    from phantom.model.sweep import stderr_progress

    if not args.measurements:
        raise PhantomError("phantom calibrate needs --measurements CSV (or use 'phantom calibrate record' to "
                           "make one)")
    if args.workers is not None and args.workers < 1:
        raise PhantomError(f"--workers must be at least 1, got {args.workers}")
    scene = _scene_for(args)
    measurements = load_measurements(args.measurements, n_chambers=len(scene.chambers))
    grid = parse_grid(args.grid or DEFAULT_GRIDS[scene.material.model])
    result = calibrate(scene, measurements, grid, scheduler=args.scheduler, n_workers=args.workers,
                       progress=stderr_progress("calibrate: tracing the pressure rays"))
    stem = Path(scene.path).stem if scene.path else "scene"
    output = Path(args.output) if args.output else Path.cwd() / f"{stem}_calibrated.toml"
    parameters = ", ".join(f"{name} = {value:.4g}" for name, value in result.parameters.items())
    grid_text = " ".join(f"--grid {name}={','.join(f'{v:g}' for v in values)}"
                         for name, values in zip(grid.names, grid.values, strict=True))
    comment = (f"Calibrated by `phantom calibrate --scene {args.scene} --measurements {args.measurements}"
               f"{' --material ' + args.material if args.material else ''}"
               f"{f' --size-mm {args.size_mm:g}' if args.size_mm else ''} {grid_text}`\n"
               f"({len(measurements.volumes_m3)} points): {result.material_model}, E = "
               f"{result.youngs_modulus_pa / 1e3:.4g} kPa, {parameters};\n"
               f"fit mean |error| {result.fit_mean_abs_pct_error:.2f} % (full solves), leave-one-out "
               f"{result.loo_mean_abs_pct_error:.2f} %; largest stretch {result.validity['max_stretch']:.3g}, "
               f"smallest det F {result.validity['min_det']:.3g}. See bench/README.md (calibration).")
    written = write_calibrated_scene(scene, result, output, comment)
    report = result.as_json()
    report["scene_written"] = str(written)
    if args.json:
        print(json.dumps(report))
        return 0
    print(f"{result.material_model}: E = {result.youngs_modulus_pa / 1e3:.4g} kPa, {parameters}")
    print(f"{'pressures kPa':>16} {'measured ml':>12} {'fit ml':>8} {'fit %':>7} {'LOO ml':>8} {'LOO %':>7}")
    for k in range(len(measurements.volumes_m3)):
        pressures = ",".join(f"{p:g}" for p in report["pressures_kpa"][k])
        print(f"{pressures:>16} {report['measured_ml'][k]:12.2f} {report['fit_predicted_ml'][k]:8.2f} "
              f"{report['fit_abs_pct_error'][k]:7.2f} {report['loo_predicted_ml'][k]:8.2f} "
              f"{report['loo_abs_pct_error'][k]:7.2f}")
    print(f"fit mean |error| {result.fit_mean_abs_pct_error:.3f} %, leave-one-out "
          f"{result.loo_mean_abs_pct_error:.3f} %")
    validity = result.validity
    print(f"valid: smallest det F {validity['min_det']:.3g} (> 0), stretches {validity['min_stretch']:.3g}-"
          f"{validity['max_stretch']:.3g} (law's range {validity['stretch_range'][0]:g}-"
          f"{validity['stretch_range'][1]:g})"
          + (f", I1 - 3 at {validity['max_i1_minus_3_over_jm']:.2f} Jm" if "max_i1_minus_3_over_jm" in validity
             else "") + f", pressures <= {validity['max_pressure_kpa']:g} kPa")
    if result.binding:
        print(f"the fit sits on a constraint: the better fit outside it breaks it ({result.binding})")
    print(f"wrote {written}")
    return 0
