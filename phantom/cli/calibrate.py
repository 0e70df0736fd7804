"""``phantom calibrate``: fit material and geometry to measured volumes (offline, Dask sweep), and
``phantom calibrate record``: measure those volumes on a board.

Only the standard library is imported at module load; handlers import what they need when they run.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    import numpy as np
    from dask.distributed import LocalCluster

    from phantom.hil.link import BoardLink
    from phantom.model.scene import Scene

#: The grid swept when none is given, per material law: stiffening (Jm) and the chambers' size.
#: The pressure combinations of the paper's Table I (kPa), the default list to record.
TABLE_I_POINTS_KPA = ((0, 0, 0), (1, 1, 1), (2, 2, 2), (2, 0, 0), (0, 2, 0), (0, 0, 2), (1, 2, 3), (3, 1, 2))
#: Longest a combination may take to settle (board time, s) before the recording gives up.
SETTLE_TIMEOUT_S = 30.0
DEFAULT_GRIDS = {
    "gent": ["gent_jm=2.5,5,10", "base_chamber_scale=0.85,1", "lobe_chamber_scale=1,1.1,1.2"],
    "neo_hookean": ["base_chamber_scale=0.85,1", "lobe_chamber_scale=1,1.1,1.2"],
    "corotational": ["lobe_chamber_scale=1,1.2"],
    "linear": ["lobe_chamber_scale=1,1.2"],
}


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """Add ``calibrate`` (and its ``record`` subcommand) to the ``phantom`` parser."""
    calibrate = subparsers.add_parser(
        "calibrate", help="fit material and geometry to measured volumes (offline); 'record' measures them",
        description="Fit the scene's Young's modulus and a grid of material and geometry parameters to measured "
                    "gland volumes by least squares, with leave-one-out cross-validation and physical validity "
                    "as a constraint; the forward solves run as Dask tasks (cached). Writes a scene with the fit. "
                    "'phantom calibrate record' holds pressures on a board and asks for the volume at each.")
    calibrate.add_argument("--scene", default="builtin", help="scene TOML path or 'builtin' (default)")
    calibrate.add_argument("--measurements",
                           help="CSV with columns p0_kpa,p1_kpa,...,measured_ml and optionally medium (air or water: "
                                "where each point hung, for a scene with [load]; default air)")
    calibrate.add_argument("--material", choices=("gent", "neo_hookean", "corotational", "linear"),
                           help="material law to fit (default: the scene's)")
    calibrate.add_argument("--gent-jm", type=float, help="Gent Jm when --material gent and Jm is not swept")
    calibrate.add_argument("--youngs-modulus-kpa", type=float,
                           help="the material's published modulus E0 (kPa; default: the scene's)")
    calibrate.add_argument("--modulus-band-pct", type=float,
                           help="E may move at most this many %% from E0 (e.g. 40: the silicone's spread); "
                                "default: E is free")
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

    actions = calibrate.add_subparsers(dest="calibrate_action", metavar="record")
    record = actions.add_parser(
        "record", help="hold pressure combinations on the board and ask for the measured volume at each",
        description="Hold each pressure combination on the board until it has settled, ask for the gland volume "
                    "measured there (ml, or a scan file, typed on standard input), vent, and write the "
                    "measurements CSV that 'phantom calibrate --measurements' reads.")
    target = record.add_mutually_exclusive_group(required=True)
    target.add_argument("--port", help="serial port of the board, e.g. /dev/ttyACM0")
    target.add_argument("--sim", action="store_true", help="the firmware in simavr against the plant")
    record.add_argument("--baud", type=int, default=115200, help="serial baud rate (default 115200)")
    record.add_argument("--sim-speed", type=float, default=1.0, help="--sim: simulated time per wall time")
    record.add_argument("--points-kpa", default=";".join(",".join(map(str, p)) for p in TABLE_I_POINTS_KPA),
                        help="pressure combinations 'a,b,c;a,b,c;...' in kPa, each within 0-3 (default: the "
                             "paper's eight)")
    # unset: the daemon's rule of settled pressures (host/control.py, ReachRule), here on the board's clock
    record.add_argument("--settle-s", type=float,
                        help="board time every chamber must stay within --tolerance-kpa (default: the daemon's, 1 s)")
    record.add_argument("--tolerance-kpa", type=float, help="settled band (default: the daemon's, 0.1 kPa)")
    record.add_argument("--out", required=True, help="measurements CSV to write")
    record.add_argument("--json", action="store_true", help="print one JSON object")
    record.set_defaults(run=run_record)


def _scene_for(args: argparse.Namespace) -> Scene:
    """The scene, with --material, --gent-jm, --youngs-modulus-kpa and --size-mm applied to its table."""
    import math

    from phantom import PhantomError
    from phantom.model.calibration.calibrate import scene_with
    from phantom.model.scene import load_scene, scene_from_dict

    scene = load_scene(args.scene)
    _check_flags(args, scene)
    document = scene.raw
    if args.material:
        document = scene_with(document, {})
        document.setdefault("material", {})["model"] = args.material
        if args.material != "gent":
            document["material"].pop("gent_jm", None)
    if args.gent_jm is not None:
        document = scene_with(document, {"gent_jm": args.gent_jm})
    if args.youngs_modulus_kpa is not None:
        if not (math.isfinite(args.youngs_modulus_kpa) and args.youngs_modulus_kpa > 0):
            raise PhantomError(f"--youngs-modulus-kpa must be a positive number, got {args.youngs_modulus_kpa}")
        document = scene_with(document, {})
        document.setdefault("material", {})["youngs_modulus_kpa"] = args.youngs_modulus_kpa
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


def _check_flags(args: argparse.Namespace, scene: Scene) -> None:
    """Refuse a --gent-jm, --size-mm or --grid value the scene's own checks refuse, naming the flag, before it is
    merged into the scene (whose checks would blame the scene file for it)."""
    from phantom import PhantomError
    from phantom.model.calibration.calibrate import parse_grid

    law = args.material or scene.material.model
    if args.gent_jm is not None:
        if law != "gent":
            given = f"--material {law}" if args.material else f"the scene's law is {law!r}"
            raise PhantomError(f"--gent-jm applies to the Gent law only ({given}): add --material gent")
        _check_value(scene, "--gent-jm", "gent_jm", args.gent_jm)
    if args.size_mm is not None and scene.geometry is not None:
        _check_value(scene, "--size-mm", "mesh_size_mm", args.size_mm)
    if args.grid:
        grid = parse_grid(args.grid)
        for name, values in zip(grid.names, grid.values, strict=True):
            if name == "poisson_ratio" or name == "gent_jm" or scene.geometry is not None:  # else: calibrate says
                for value in values:
                    _check_value(scene, f"--grid {name}", name, float(value))


def _check_value(scene: Scene, flag: str, key: str, value: float) -> None:
    """Check ``value`` of the [material] or [geometry] ``key`` by the scene's own checks (and bounds), on the scene
    with it alone set; PhantomError naming ``flag`` for one they refuse. ``gent_jm`` is checked under the Gent law
    (whether the law is Gent is the caller's check)."""
    from phantom import PhantomError
    from phantom.model.calibration.calibrate import scene_with
    from phantom.model.errors import SceneError
    from phantom.model.scene import YEOH_KEYS, scene_from_dict

    document = scene_with(scene.raw, {key: value})
    if key == "gent_jm":
        document["material"]["model"] = "gent"
        for other in YEOH_KEYS:
            document["material"].pop(other, None)
    try:
        scene_from_dict(document, scene.path)
    except SceneError as error:
        if error.key == key and error.requirement is not None:
            raise PhantomError(f"{flag} {error.requirement}, got {value:g}") from None
        where = f"scene {scene.path}" if scene.path else "scene"  # scene_from_dict's prefix: the file is not at fault
        raise PhantomError(f"{flag} {value:g}: {str(error).removeprefix(f'{where}: ')}") from None


def run_calibrate(args: argparse.Namespace) -> int:
    """Handler of ``phantom calibrate``."""
    import json

    from phantom import PhantomError
    from phantom.cli.common import check_output_file
    from phantom.model.calibration.calibrate import calibrate, load_measurements, parse_grid, write_calibrated_scene

    if not args.measurements:
        raise PhantomError("phantom calibrate needs --measurements CSV (or use 'phantom calibrate record' to "
                           "make one)")
    if args.workers is not None and args.workers < 1:
        raise PhantomError(f"--workers must be at least 1, got {args.workers}")
    scene = _scene_for(args)
    stem = Path(scene.path).stem if scene.path else "scene"
    output = Path(args.output) if args.output else Path.cwd() / f"{stem}_calibrated.toml"
    check_output_file(args.output or output, "--output" if args.output else "the default --output",
                      f"{stem}_calibrated.toml")
    band = None
    if args.modulus_band_pct is not None:
        if not 0 < args.modulus_band_pct < 100:
            raise PhantomError(f"--modulus-band-pct must be within (0, 100), got {args.modulus_band_pct}")
        e0 = scene.material.youngs_modulus_pa
        band = (e0 * (1 - args.modulus_band_pct / 100), e0 * (1 + args.modulus_band_pct / 100))
    measurements = load_measurements(args.measurements, n_chambers=len(scene.chambers),
                                     scan_volume_ml=_scan_volume_of(scene))
    grid = parse_grid(args.grid or DEFAULT_GRIDS[scene.material.model])
    cluster = None if args.scheduler else local_cluster_deaf_to_ctrl_c(args.workers)
    scheduler = args.scheduler if cluster is None else cluster.scheduler_address
    try:
        result = calibrate(scene, measurements, grid, scheduler=scheduler,
                           n_workers=args.workers, progress=fit_progress(len(measurements.volumes_m3)),
                           modulus_band_pa=band)
    finally:
        if cluster is not None:
            cluster.close()
    parameters = ", ".join(f"{name} = {value:.4g}" for name, value in result.parameters.items())
    grid_text = " ".join(f"--grid {name}={','.join(f'{v:g}' for v in values)}"
                         for name, values in zip(grid.names, grid.values, strict=True))
    comment = (f"Calibrated by `phantom calibrate --scene {args.scene} --measurements {args.measurements}"
               f"{' --material ' + args.material if args.material else ''}"
               f"{f' --size-mm {args.size_mm:g}' if args.size_mm else ''}"
               f"{f' --youngs-modulus-kpa {args.youngs_modulus_kpa:g}' if args.youngs_modulus_kpa else ''}"
               f"{f' --modulus-band-pct {args.modulus_band_pct:g}' if args.modulus_band_pct else ''} {grid_text}`\n"
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


def local_cluster_deaf_to_ctrl_c(n_workers: int | None) -> LocalCluster:
    """The fit's Dask cluster on this machine (one for all its sweeps), whose worker processes ignore SIGINT: a
    Ctrl-C in the terminal reaches every process of its group, and workers it killed mid-solve left "12 leaked
    semaphore objects" warnings; now only this process gets it and closes the cluster in order. The workers
    inherit the ignored signal (Python keeps SIGINT ignored when it starts with it ignored)."""
    import signal

    from phantom.model.cluster import local_cluster

    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        return local_cluster(n_workers)
    finally:
        signal.signal(signal.SIGINT, previous)


def fit_progress(n_measurements: int) -> Callable[[int, int], None]:
    """The fit's progress on stderr by stage, each with its time left. The calibration runs up to three sweeps
    of forward solves, each reporting ``(done, total)`` from its own start: the grid's pressure rays (most of the
    time), the left-out points at their refits (only where a refit reaches past its ray), and the fit verified
    by full solves, one per measurement. A new sweep is one whose count starts again or changes its total."""
    from phantom.cli.common import progress_reporter

    stage: list[Any] = [0, None, None]  # number, the last (done, total), the stage's reporter

    def report(done: int, total: int) -> None:
        last = stage[1]
        if last is None or done < last[0] or total != last[1] or last[0] >= last[1]:
            stage[0] += 1
            if stage[0] == 1:
                name = "tracing the pressure rays of every grid point (the long part)"
            elif total == n_measurements:
                name = "verifying the fit by full solves at each measurement"
            else:
                name = "solving left-out points at their refits"
            stage[2] = progress_reporter(f"calibrate: stage {stage[0]}, {name}:")
        stage[1] = (done, total)
        stage[2](done, total)
    return report


def recommended_fit(measurements: str | Path, output: str = "my_phantom.toml") -> str:
    """The fit command the README recommends, for a measurements CSV: the shipped model's kind (builtin:converged:
    Gent on 10-node elements), not the co-rotational default, whose leave-one-out error is about 20 %."""
    return (f"phantom calibrate --scene bench/calibration_ecoflex.toml --measurements {measurements} --size-mm 7 "
            f"--grid gent_jm=5 --grid base_chamber_scale=1 --grid lobe_chamber_scale=1.2 --output {output}")


def _scan_volume_ml(path: Path, rest_surface: Any = None) -> float:
    """The cleaned, watertight volume (ml) of a scan file in mm: the scan comparison's, for a measurements CSV
    or an answer that names a scan (the model reads no scans itself). Its size is checked against
    ``rest_surface`` (the phantom's at rest, mm), else the built-in phantom's: a file in another unit is refused."""
    from phantom import PhantomError

    try:
        from phantom.scan.compare import scan_volume_ml
    except ImportError:
        raise PhantomError("scan files need phantom.scan.compare, which this install lacks: give the volume "
                           "in ml") from None
    # a measurements CSV or a typed answer names a file, with no unit beside it: the remedies are the file's
    phantom = "the --scene" if rest_surface is not None else "the built-in one"
    return scan_volume_ml(path, units="mm", model=rest_surface,
                          remedy="export it in mm (phantom calibrate reads scan files in mm)",
                          otherwise=f"is it a scan of this phantom ({phantom})? Export it in mm, or give the "
                                    f"volume in ml")


def _scan_volume_of(scene: Any) -> Callable[[Path], float]:
    """:func:`_scan_volume_ml` checked against ``scene``'s phantom at rest (one designed larger or smaller than
    the built-in one), its surface built at the first scan file (a CSV of numbers needs none)."""
    rest: list[Any] = []

    def measured_ml(path: Path) -> float:
        if not rest:
            from phantom.model.fem.model import PhantomModel
            from phantom.model.mesh.surface import model_surface

            model = PhantomModel.from_scene(scene)
            rest.append(model_surface(model.nodes_m, model.outer_triangles))
        return _scan_volume_ml(path, rest[0])

    return measured_ml


def _parse_points(text: str) -> list[list[float]]:
    from phantom import PhantomError
    from phantom.cli.common import parse_numbers
    from phantom.model.scene import DEFAULT_CHAMBER_LABELS, PRESSURE_LIMIT_PA, describe_chambers, pressure_limit_error

    points = [parse_numbers(item, "--points-kpa") for item in text.split(";") if item.strip()]
    for point in points:
        if len(point) != len(DEFAULT_CHAMBER_LABELS):
            raise PhantomError(f"--points-kpa: each combination is one pressure per chamber "
                               f"({describe_chambers(DEFAULT_CHAMBER_LABELS)}), got {point}")
        refused = pressure_limit_error(point, DEFAULT_CHAMBER_LABELS, PRESSURE_LIMIT_PA / 1e3)
        if refused:
            raise PhantomError(f"--points-kpa {','.join(f'{p:g}' for p in point)}: {refused}")
    if len(points) < 3:
        raise PhantomError(f"--points-kpa: a calibration with leave-one-out needs at least 3, got {len(points)}")
    return points


def _ask_volume_ml(prompt: str) -> float:
    """A volume typed on stdin (ml), or the path of a scan file whose volume phantom.scan.compare measures."""
    import math
    import sys

    from phantom import PhantomError

    sys.stderr.write(prompt)
    sys.stderr.flush()
    answer = sys.stdin.readline()
    if not answer:
        raise PhantomError("no answer on standard input: type the measured volume in ml (or a scan file path)")
    answer = answer.strip()
    try:
        volume_ml = float(answer)
    except ValueError:
        if not Path(answer).is_file():
            raise PhantomError(f"{answer!r} is neither a volume in ml nor a scan file") from None
        volume_ml = _scan_volume_ml(Path(answer))
    if not (math.isfinite(volume_ml) and volume_ml > 0):
        raise PhantomError(f"the volume must be a positive number of ml, got {answer!r}")
    return volume_ml


def _hold_until_settled(link: BoardLink, point_kpa: list[float], tolerance_kpa: float | None,
                        settle_s: float | None) -> np.ndarray:
    """Set the pressures and wait (board clock) until every chamber has stayed within the band for
    ``settle_s`` (the daemon's settled rule where None); return the mean pressures (kPa) of five telemetry
    frames then."""
    import numpy as np

    from phantom import PhantomError
    from phantom.hil import bench
    from phantom.host.control import SETTLED, ReachRule, Settling

    rule = ReachRule(settled_kpa=SETTLED.settled_kpa if tolerance_kpa is None else tolerance_kpa,
                     settled_for_s=SETTLED.settled_for_s if settle_s is None else settle_s)
    setpoints_pa = [int(round(value * 1e3)) for value in point_kpa]
    bench.set_setpoints(link, setpoints_pa)
    settling = Settling(rule)

    def settled(fields: dict[str, Any]) -> bool:
        return settling.settled(fields["time_ms"] / 1e3, np.asarray(fields["pressure_pa"], dtype=float),
                                np.asarray(setpoints_pa, dtype=float))

    if bench.wait_board_time(link, SETTLE_TIMEOUT_S, settled) is None:
        raise PhantomError(f"the pressures ({', '.join(f'{p:g}' for p in point_kpa)}) kPa did not settle within "
                           f"{rule.settled_kpa:g} kPa in {SETTLE_TIMEOUT_S:g} s of board time: check for leaks")
    held_pa: np.ndarray = np.mean([bench.latest_telemetry(link)["pressure_pa"] for _ in range(5)], axis=0)
    return held_pa / 1e3


def run_record(args: argparse.Namespace) -> int:
    """Handler of ``phantom calibrate record``."""
    import json

    from phantom import PhantomError
    from phantom.hil import bench
    from phantom.hil.link import BoardLink

    points = _parse_points(args.points_kpa)
    out = Path(args.out)
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        raise PhantomError(f"cannot create the folder of {out}: {error.strerror}") from None
    board = None
    port, scale = args.port, 1.0
    if args.sim:
        from phantom.hil.sim import SimulatedBoard

        board = SimulatedBoard(speed=args.sim_speed).start()
        port, scale = board.port, args.sim_speed or 1.0
    rows = []
    try:
        with BoardLink(port, baudrate=args.baud, time_scale=scale) as link:
            bench.start_session(link)
            bench.zero_sensors(link)  # vented now: the sensors' offsets are measured before any point
            for point in points:
                held = _hold_until_settled(link, point, args.tolerance_kpa, args.settle_s)
                volume_ml = _ask_volume_ml(f"holding {', '.join(f'{p:.2f}' for p in held)} kPa: measured gland "
                                           f"volume (ml) or scan file? ")
                rows.append((*point, volume_ml, *held))
            bench.vent_and_wait(link)
    finally:
        if board is not None:
            board.stop()
    lines = ["# Measured by `phantom calibrate record`: setpoints (kPa), the gland volume measured at each (ml),",
             "# and the pressures the board held meanwhile (held_p*_kpa: mean of five telemetry frames).",
             "p0_kpa,p1_kpa,p2_kpa,measured_ml,held_p0_kpa,held_p1_kpa,held_p2_kpa"]
    lines += [",".join(f"{value:.4g}" for value in row) for row in rows]
    out.write_text("\n".join(lines) + "\n")
    if args.json:
        print(json.dumps({"out": str(out), "points": len(rows)}))
    else:
        print(f"wrote {out}: {len(rows)} points. Fit them as the shipped model was fitted (Gent law, 10-node "
              f"elements; about 15 minutes on two cores), from the clone:\n  {recommended_fit(out)}")
    return 0
