"""Subcommands of ``phantom``: ``compare-scan`` (a 3D scan of the phantom against the model) and ``scan ...``:
the scanner (``render``, ``capture``, ``calibrate``, ``reconstruct``, ``export``, ``import``, ``validate``) and
``synthetic`` (a scan of the model with known damage, to try compare-scan on).

Only argparse is imported at module load; the handlers import what they need when they run.
"""

from __future__ import annotations

import argparse
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from phantom.scan.capture import CaptureFolder
    from phantom.scan.render import Look

#: ``scan synthetic``'s largest ``--noise-mm`` (mm, sigma): a scanner's noise is tenths of a mm; 5 mm is a wall's
#: thickness, and the scan is still the phantom's shape.
MAX_NOISE_MM = 5.0
#: ``scan synthetic``'s most ``--levels``: each multiplies the vertices by 4 (the built-in phantom's surface at 6:
#: 2.1 million vertices, 1.2 GB and 40 s to write; 12 would be 8 billion).
MAX_LEVELS = 6
#: ``scan synthetic``'s most ``--holes``: a hole is 2.5 mm across (20 mm^2) of the phantom's 4,400 mm^2 surface;
#: 50 take a fifth of it, more leave too little to align (and the coarsest surface has 500 vertices to centre
#: them on).
MAX_HOLES = 50
#: The file a Rerun recording is written to ends with this.
RECORDING_SUFFIX = ".rrd"


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

    scan = subparsers.add_parser(
        "scan", help="the scanner: render, capture, calibrate, reconstruct, export, import, validate; synthetic",
        description="The phantom's scanner (scan/README.md): a camera orbiting the hanging phantom, its calibration, "
                    "the reconstruction of a capture folder, the validation in simulation; and synthetic scans.")
    actions = scan.add_subparsers(dest="scan_action", metavar="ACTION", required=True)
    register_scanner(actions)
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
    synthetic.add_argument("--noise-mm", type=float, default=0.05,
                           help=f"noise along the normals (mm, sigma; 0 to {MAX_NOISE_MM:g})")
    synthetic.add_argument("--holes", type=int, default=3, help=f"holes cut out of the surface (0 to {MAX_HOLES})")
    synthetic.add_argument("--levels", type=int, default=2,
                           help=f"midpoint subdivisions, each 4 times the vertices (0 to {MAX_LEVELS}; the built-in "
                                f"phantom: 2 about 8k, 4 about 130k, 6 about 2 million)")
    synthetic.add_argument("--seed", type=int, default=0, help="seed of the noise, holes and motion (0 or more)")
    synthetic.set_defaults(run=run_synthetic_scan)


def register_scanner(actions: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """The scanner's actions of ``phantom scan``."""
    render = actions.add_parser(
        "render", help="render the virtual rig's pictures of a closed mesh (mm) into a capture folder",
        description="Render what the simulated scanner's webcam sees of a closed mesh (OBJ, PLY, STL, in mm, in the "
                    "phantom's frame: z up, hanging from z = 20 mm) as the orbit turns, into a capture folder with "
                    "the virtual rig's true geometry beside it (or --rig's), for phantom scan reconstruct.")
    render.add_argument("mesh", metavar="MESH", help="the mesh: .obj, .ply or .stl")
    render.add_argument("--out", required=True, help="the capture folder to make")
    _add_plan_options(render)
    render.add_argument("--scale", type=float, default=1.0, help="picture size as a fraction of 1280x960 (default 1)")
    render.add_argument("--units", choices=("mm", "cm", "m"), default="mm", help="the mesh's unit (default mm)")
    render.add_argument("--rig", help="keep this rig calibration (rig.json) beside the pictures instead of the true "
                                      "rig, e.g. one from phantom scan calibrate --sim")
    render.add_argument("--seed", type=int, default=0, help="seed of the sensor noise")
    render.add_argument("--look", choices=("ideal", "real"), default="ideal",
                        help="ideal: an even backdrop, a matt phantom floating in view (default); real: what a real "
                             "rig sees, the phantom hung by three 4.4 mm tubes from a holder above, glossy, an "
                             "uneven cloth in folds, vignetting")
    for part in ("tubes", "gloss", "cloth", "vignetting", "noise"):
        render.add_argument(f"--no-{part}", action="store_true", help=f"--look real without the {part}")
    render.set_defaults(run=run_render)

    reconstruct = actions.add_parser(
        "reconstruct", help="carve a capture folder's silhouettes into a closed mesh (mm)",
        description="Find the phantom's silhouette against the backdrop in each picture, carve the visual hull on a "
                    "voxel grid with the rig's poses (coarse to fine) and write its smooth closed surface in mm, in "
                    "the rig's frame; phantom compare-scan reads it like any scan.")
    reconstruct.add_argument("capture", metavar="DIR", help="a capture folder (capture.json, images/)")
    reconstruct.add_argument("--out", required=True, help="the mesh to write: .ply, .stl or .obj")
    reconstruct.add_argument("--replace", action="store_true", help="write over a mesh already at --out")
    reconstruct.add_argument("--rig", help="the rig calibration (rig.json; default the one in the folder)")
    reconstruct.add_argument("--voxel-mm", type=float, default=None, help="the finest voxel (mm, default 0.3)")
    reconstruct.add_argument("--partial", action="store_true",
                             help="carve a capture that did not complete (aborted, stopped) from the pictures it "
                             "has: fewer sides carve a hull too large")
    reconstruct.add_argument("--json", action="store_true", help="print one JSON object")
    reconstruct.set_defaults(run=run_reconstruct)

    calibrate = actions.add_parser(
        "calibrate", help="calibrate the rig (lens, orbit axis and radius) from pictures of the ChArUco target",
        description="Find the ChArUco target's corners in capture folders of it (one folder per placement of the "
                    "target, from phantom scan capture --target) and fit the camera's intrinsics and distortion, "
                    "the orbit's axis and radius and the camera's pose at each elevation; write rig.json. --sim "
                    "renders the virtual rig's target pictures first and compares the result with its truth.")
    calibrate.add_argument("captures", metavar="DIR", nargs="*", help="capture folders of the target")
    calibrate.add_argument("--sim", action="store_true", help="calibrate the virtual rig from rendered pictures")
    calibrate.add_argument("--out", required=True, help="the rig file to write (rig.json)")
    calibrate.add_argument("--views", type=int, default=11, help="with --sim: pictures per placement and elevation")
    calibrate.add_argument("--scale", type=float, default=1.0, help="with --sim: picture size, a fraction of 1280x960")
    calibrate.add_argument("--keep", help="with --sim: keep the target's capture folders here")
    calibrate.add_argument("--fit-k3", action="store_true", help="fit the sixth-order distortion term too")
    calibrate.add_argument("--json", action="store_true", help="print one JSON object")
    calibrate.set_defaults(run=run_calibrate)

    export = actions.add_parser(
        "export", help="a capture folder with its known camera poses for COLMAP or Meshroom",
        description="Write the capture's camera model and every picture's pose from the rig's calibration as a "
                    "COLMAP text model (cameras.txt, images.txt, points3D.txt) and/or Meshroom's cameras.sfm.")
    export.add_argument("capture", metavar="DIR", help="a capture folder")
    export.add_argument("--colmap", metavar="FOLDER", help="write the COLMAP text model into this folder")
    export.add_argument("--meshroom", metavar="FILE", help="write Meshroom's SfMData (cameras.sfm) here")
    export.add_argument("--rig", help="the rig calibration (default the one in the folder)")
    export.set_defaults(run=run_export)

    imported = actions.add_parser(
        "import", help="a photogrammetry tool's mesh, cleaned and closed, as a scan in mm",
        description="Read the mesh COLMAP or Meshroom made from an export (in the rig's frame), keep its largest "
                    "piece, close its holes and write it in mm.")
    imported.add_argument("mesh", metavar="MESH", help="the tool's mesh: .obj, .ply or .stl")
    imported.add_argument("--out", required=True, help="the mesh to write: .ply, .stl or .obj")
    imported.add_argument("--units", choices=("mm", "cm", "m"), default="mm", help="the mesh's unit (default mm)")
    imported.add_argument("--replace", action="store_true", help="write over a mesh already at --out")
    imported.set_defaults(run=run_import)

    capture = actions.add_parser(
        "capture", help="turn the orbit through a running daemon and take a picture at each stop",
        description="With the daemon holding the pressures, configure the scanner's axes, then at each stop of "
                    "the plan move there, settle and take a picture (a webcam, or on the simulated board the "
                    "virtual camera), and save it with its angles, pressures and time in a capture folder. A "
                    "fault, a lost camera or Ctrl-C stops it with the motors released and the pictures kept.")
    capture.add_argument("--out", required=True, help="the capture folder to make")
    _add_plan_options(capture)
    capture.add_argument("--start-deg", type=float, default=-180.0,
                         help="the first orbit angle (deg, default -180: a turn within the +-190 deg soft limits)")
    capture.add_argument("--span-deg", type=float, default=360.0,
                         help="the orbit's span: 360 (default) a whole turn, less from --start-deg to its end")
    capture.add_argument("--settle-s", type=float, default=0.3, help="wait after each move (s, default 0.3)")
    capture.add_argument("--camera", default="virtual",
                         help="'virtual' (the simulated board's virtual camera, default), a device number (0 for "
                              "/dev/video0), a network camera's stream URL (http://HOST:PORT/phantom.mjpg, "
                              "rtsp://...), or a video file or image sequence (frames/%%04d.png)")
    capture.add_argument("--width", type=int, help="webcam: picture width (px)")
    capture.add_argument("--height", type=int, help="webcam: picture height (px)")
    capture.add_argument("--exposure", type=float, help="webcam: fixed exposure (the driver's units)")
    capture.add_argument("--focus", type=float, help="webcam: fixed focus (the driver's units)")
    capture.add_argument("--rig", help="keep this rig calibration (rig.json) beside the pictures")
    capture.add_argument("--target", action="store_true",
                         help="pictures of the calibration target (the virtual camera renders it)")
    capture.add_argument("--placement", type=int, default=0, help="virtual --target: the target's placement")
    capture.add_argument("--scale", type=float, default=1.0, help="virtual camera: picture size, of 1280x960")
    capture.add_argument("--seed", type=int, default=0, help="virtual camera: seed of the sensor noise")
    capture.add_argument("--socket", help="the daemon's API socket (default: as phantom status)")
    capture.set_defaults(run=run_capture)

    validate = actions.add_parser(
        "validate", help="the paper's validation by scanning, on the simulated rig (--sim)",
        description="Start the daemon on the simulated board with the BPH scene and, at each of its target "
                    "volumes: set the target (the inverse's pressures), scan it with the orbit and the virtual "
                    "camera, reconstruct, and compare with the target, the model and the simulated phantom's truth; "
                    "write a report (markdown, the paper's Figs. 9 and 10 as PNGs) and a Rerun recording.")
    validate.add_argument("--sim", action="store_true", help="on the simulated board (required)")
    validate.add_argument("--out", default="out/scan-validation", help="folder for everything (default "
                                                                        "out/scan-validation)")
    validate.add_argument("--scene", help="the scene (default the BPH growth example)")
    validate.add_argument("--targets", help="target volumes (ml; default the scene's steps)")
    validate.add_argument("--views", type=int, default=60, help="pictures per turn (default 60: 120 in two passes)")
    validate.add_argument("--elevations", default="0,30", help="the passes' elevations (deg, default 0,30)")
    validate.add_argument("--scale", type=float, default=1.0, help="picture size, of 1280x960 (default 1)")
    validate.add_argument("--voxel-mm", type=float, help="the finest voxel (mm, default 0.3)")
    validate.add_argument("--settle-s", type=float, default=0.3, help="wait after each move (s)")
    validate.add_argument("--target-views", type=int, default=11, help="calibration pictures per placement and pass")
    validate.add_argument("--rig", help="a rig calibration to use instead of calibrating first")
    validate.add_argument("--sim-speed", type=float, default=1.0, help="the simulated board's speed-up")
    validate.add_argument("--daemon-timeout-s", type=float, default=600.0,
                          help="how long one stage of the daemon's start may go without moving on (s)")
    validate.add_argument("--no-rerun", dest="rerun", action="store_false", help="no Rerun recording")
    validate.add_argument("--seed", type=int, default=0, help="seed of the sensor noise")
    validate.add_argument("--json", action="store_true", help="print one JSON object")
    validate.set_defaults(run=run_validate)


def run_capture(args: argparse.Namespace) -> int:
    """Handler of ``phantom scan capture``: the plan's pictures through the running daemon (its axes and state),
    from a webcam or, on the simulated board, the virtual camera (of the phantom, or with --target of the
    ChArUco target in a virtual placement)."""
    import dataclasses
    import sys

    from phantom.cli.common import capture_through_daemon, frame_progress, plan_of
    from phantom.host.api import default_socket_path
    from phantom.host.client import DaemonClient
    from phantom.host.scan_client import DaemonOrbit
    from phantom.scan.camera import Rig, virtual_pose_at, virtual_rig
    from phantom.scan.capture import CaptureFolder, FrameSource, Webcam
    from phantom.scan.render import CharucoTarget

    plan = dataclasses.replace(plan_of(args, args.settle_s), start_deg=args.start_deg, span_deg=args.span_deg)
    rig = Rig.load(args.rig) if args.rig else None
    camera: FrameSource
    with DaemonClient(args.socket or default_socket_path()) as client:
        if args.camera == "virtual":
            from phantom.hil.truth_shape import TruthShape
            from phantom.scan.virtual import AnglesRead, TargetCamera, VirtualCamera, truth_scene, virtual_placement

            true_rig = virtual_rig(args.scale, plan.elevations_deg)
            if args.target:
                camera = TargetCamera(true_rig, CharucoTarget(), virtual_placement(args.placement),
                                      AnglesRead(lambda: _simulated_angles(client)), args.seed,
                                      virtual_pose_at(args.scale))
            else:
                camera = VirtualCamera(true_rig, truth_scene(DaemonOrbit(client).simulated, TruthShape()), args.seed,
                                       pose_at=virtual_pose_at(args.scale))
        else:
            source: int | str = int(args.camera) if args.camera.isdigit() else args.camera
            camera = Webcam(source, args.width, args.height, args.exposure, args.focus)
        conditions: dict[str, Any] = {"socket": str(args.socket or default_socket_path())}
        if args.target:
            conditions["target"] = CharucoTarget().to_json()
        try:
            folder = CaptureFolder.create(args.out, camera.describe(), plan.to_json(), conditions, rig)
            capture_through_daemon(client, camera, plan, folder, frame_progress("captured"))
        finally:
            camera.close()  # a webcam's, its stream's reader with it
    print(f"captured {len(folder.frames)} pictures into {folder.path}", file=sys.stderr)
    return 0


def _simulated_angles(client: Any) -> tuple[float, float]:
    """The simulated rig's true angles (deg) through the daemon (``motion_status``'s ``simulated``)."""
    from phantom import PhantomError

    simulated = client.call("motion_status").get("simulated") or {}
    angles = simulated.get("rig_deg")
    if angles is None or None in angles:
        raise PhantomError("the daemon does not report a simulated rig: the virtual camera needs `phantom daemon "
                           "--sim`")
    return float(angles[0]), float(angles[1])


def run_validate(args: argparse.Namespace) -> int:
    """Handler of ``phantom scan validate`` (phantom/cli/scan_validate.py)."""
    import sys

    from phantom.cli.scan_validate import run_validate as handler

    args.argv = sys.argv[1:]
    return handler(args)


def _add_plan_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--views", type=int, default=60, help="pictures per turn of the orbit (default 60)")
    parser.add_argument("--elevations", default="0,30", help="the elevations (deg) of the passes (default 0,30)")


def _checked_mesh(path: str, what: str = "the mesh", give: str | None = None) -> str:
    """A mesh file's path, refused (ScanError) before a reader holds it whole when it is over the size read; with
    ``give`` (what to give instead), a folder named in its place too."""
    from phantom.cli.common import MAX_MESH_BYTES, MESH_TOO_LARGE, check_input_size
    from phantom.scan.compare import ScanError

    check_input_size(path, MAX_MESH_BYTES, what, ScanError, MESH_TOO_LARGE, give=give)
    return path


def _read_mesh(path: str, units: str, give: str | None = None) -> Any:
    """A scan or mesh file (OBJ, PLY, STL) as a TriangleMesh in mm, its size checked before it is read."""
    from phantom.scan.compare import read_scan

    return read_scan(_checked_mesh(path, give=give), units)


def _open_capture(path: str) -> Any:
    """A capture folder, the sizes of its capture.json, rig file and pictures checked before any is read."""
    from pathlib import Path

    from phantom.cli.common import MAX_JSON_BYTES, MAX_PICTURE_BYTES, check_input_size
    from phantom.scan.capture import CAPTURE_FILE, CaptureError, CaptureFolder

    check_input_size(Path(path) / CAPTURE_FILE, MAX_JSON_BYTES, "the capture file", CaptureError)
    folder = CaptureFolder.open(path)
    if folder.rig_file:
        check_input_size(folder.path / folder.rig_file, MAX_JSON_BYTES, "the capture's rig file", CaptureError)
    for frame in folder.frames:
        check_input_size(folder.path / frame.image, MAX_PICTURE_BYTES, "the picture", CaptureError,
                         "a capture's pictures are camera frames of a few MB")
    return folder


def look_of(args: argparse.Namespace) -> Look:
    """The virtual pictures' look from ``--look`` and its ``--no-PART`` flags."""
    from dataclasses import replace

    from phantom.scan.render import LOOKS

    look = LOOKS[args.look]
    look = replace(look, tubes=look.tubes and not args.no_tubes, gloss=0.0 if args.no_gloss else look.gloss,
                   cloth=0.0 if args.no_cloth else look.cloth,
                   vignetting=0.0 if args.no_vignetting else look.vignetting)
    return replace(look, read_noise=0.0, shot_noise_gain=0.0) if args.no_noise else look


def run_render(args: argparse.Namespace) -> int:
    """Handler of ``phantom scan render``."""
    from phantom.cli.common import frame_progress, plan_of
    from phantom.scan.camera import Rig, virtual_rig
    from phantom.scan.virtual import render_capture

    plan = plan_of(args)
    true_rig = virtual_rig(args.scale, plan.elevations_deg)
    kept = Rig.load(args.rig) if args.rig else true_rig
    mesh = _read_mesh(args.mesh, args.units, give="the mesh file to render (.obj, .ply or .stl)")
    conditions = {"mesh": str(args.mesh), "units": args.units, "rig": "given" if args.rig else "virtual, true",
                  "look": args.look}
    folder = render_capture(mesh, true_rig, plan, args.out, args.seed, conditions, frame_progress("rendered"),
                            look=look_of(args))
    if kept is not true_rig:
        kept.save(folder.path / "rig.json")
    print(f"wrote {len(folder.frames)} pictures of {args.mesh} ({true_rig.camera.width}x{true_rig.camera.height}) "
          f"into {folder.path}; reconstruct it with `phantom scan reconstruct {folder.path} --out scan.ply`")
    return 0


def _planned(folder: CaptureFolder) -> int:
    """How many pictures the capture's plan takes (its views at each of its elevations; 0: no plan is kept)."""
    views = folder.plan.get("views_per_elevation", 0)
    return int(views) * len(folder.plan.get("elevations_deg") or [0]) if isinstance(views, int) else 0


def _partial_capture(folder: CaptureFolder) -> str | None:
    """What is missing from a capture that did not complete (its status, its pictures of its plan's), or None."""
    if folder.status == "complete" and len(folder.frames) >= _planned(folder):
        return None
    reason = f" ({folder.reason})" if folder.reason else ""
    return f"was {folder.status}{reason} with {len(folder.frames)} of its plan's {_planned(folder)} pictures"


def run_reconstruct(args: argparse.Namespace) -> int:
    """Handler of ``phantom scan reconstruct``."""
    import json
    import sys

    from phantom.scan.camera import Rig
    from phantom.scan.capture import CaptureError
    from phantom.scan.reconstruct import VOXEL_MM, check_mesh_path, check_voxel_mm, reconstruct, write_mesh

    check_mesh_path(args.out)
    if args.voxel_mm is not None:
        check_voxel_mm(args.voxel_mm)
    _check_out_is_free(args)
    folder = _open_capture(args.capture)
    partial = _partial_capture(folder)
    if partial is not None and not args.partial:
        raise CaptureError(f"{folder.path} {partial}: fewer sides carve a hull too large; take the capture again, or "
                           "give --partial to carve what it has")
    rig = Rig.load(args.rig) if args.rig else None
    voxel_mm = VOXEL_MM if args.voxel_mm is None else args.voxel_mm
    result = reconstruct(folder, rig, voxel_mm, progress=None if args.json else lambda text: print(
        text, file=sys.stderr))
    path = write_mesh(result.mesh, args.out)
    summary = {"capture": str(folder.path), "mesh": str(path), "views": result.views, "voxel_mm": result.voxel_mm,
               "volume_ml": result.volume_ml, "vertices": len(result.mesh.vertices_mm),
               "triangles": len(result.mesh.triangles), "stage_s": result.stage_s,
               "silhouettes_touching_edge": result.touching_edge, "worst_uncovered_pct": result.worst_uncovered_pct,
               "hanging": None if result.hanging is None else result.hanging.to_json(), "partial": partial}
    if args.json:
        print(json.dumps(summary))
        return 0
    carved = (f"{result.views} pictures" if partial is None else
              f"{result.views} of the plan's {_planned(folder)} pictures (the capture was "
              f"{folder.status})")
    print(f"wrote {path}: {result.volume_ml:.3f} ml, {len(result.mesh.triangles)} triangles, closed; carved from "
          f"{carved} at {result.voxel_mm:g} mm in "
          + ", ".join(f"{stage} {seconds:.1f} s" for stage, seconds in result.stage_s.items()))
    if result.hanging is not None:
        print(f"the tubes it hangs by taken off at the gland's base, {result.hanging.cut_mm:.2f} mm up the orbit's "
              f"axis ({result.hanging.removed_ml:.2f} ml of them in view)")
    if result.touching_edge:
        print(f"warning: the phantom reaches the picture's edge in {result.touching_edge} picture(s): it was not "
              f"whole in view there, and what was cut off is missing", file=sys.stderr)
    return 0


def run_calibrate(args: argparse.Namespace) -> int:
    """Handler of ``phantom scan calibrate``."""
    import json
    import tempfile

    from phantom.cli.common import frame_progress
    from phantom.scan.calibrate import CalibrationError, calibrate_rig, target_views
    from phantom.scan.camera import virtual_rig
    from phantom.scan.virtual import render_target_captures

    if args.sim == bool(args.captures):
        raise CalibrationError("give the target's capture folders, or --sim for the virtual rig (not both)")
    truth = None
    with tempfile.TemporaryDirectory(prefix="phantom-target-") as scratch:
        if args.sim:
            truth = virtual_rig(args.scale)
            folders = render_target_captures(truth, args.keep or scratch, args.views,
                                             progress=frame_progress("target pictures"))
        else:
            folders = [_open_capture(path) for path in args.captures]
        first = folders[0].image(folders[0].frames[0]) if folders[0].frames else None
        if first is None:
            raise CalibrationError(f"{folders[0].path} holds no pictures")
        height, width = first.shape[:2]
        rig = calibrate_rig(target_views(folders), width, height, args.fit_k3)
    path = rig.save(args.out)
    summary = {"rig": str(path), **rig.to_json()}
    if truth is not None:
        summary["against_truth"] = rig_against_truth(rig, truth)
    if args.json:
        print(json.dumps(summary))
        return 0
    report, camera = rig.calibration, rig.camera
    print(f"wrote {path}: {report['pictures_used']} of {report['pictures']} pictures, {report['corners']} corners, "
          f"reprojection RMS {report['rms_px']:.3f} px (worst picture {report['worst_picture_rms_px']:.3f} px)")
    print(f"camera     {camera.width}x{camera.height}, f {camera.fx:.2f}, {camera.fy:.2f} px, centre {camera.cx:.2f}, "
          f"{camera.cy:.2f} px, k1 {camera.distortion[0]:.4f}, k2 {camera.distortion[1]:.4f}, "
          f"p1 {camera.distortion[2]:.5f}, p2 {camera.distortion[3]:.5f}, k3 {camera.distortion[4]:.4f}")
    for entry in rig.elevations:
        print(f"orbit      elevation {entry.elevation_deg:g} deg: radius {rig.radius_mm(entry.elevation_deg):.2f} mm")
    if truth is not None:
        print("truth      " + ", ".join(f"{key} {value:.4g}" for key, value in summary["against_truth"].items()))
    return 0


def rig_against_truth(rig: Any, truth: Any) -> dict[str, float]:
    """How far a calibrated rig is from the true one, in quantities that do not depend on the world frame each
    chose: the intrinsics, the axis in the camera's frame at orbit 0 and the first elevation (its direction's
    angle, its distance at the camera's point of view), each elevation's radius."""
    import math

    import numpy as np

    first = rig.elevations[0].elevation_deg

    def axis_in_camera(of: Any) -> tuple[Any, Any]:
        pose = of.pose(0.0, first)
        return pose.apply(of.axis_point_mm[None])[0], pose.rotation @ of.axis_direction

    point, direction = axis_in_camera(rig)
    true_point, true_direction = axis_in_camera(truth)
    offset = point - true_point
    result = {
        "fx_pct": 100 * (rig.camera.fx / truth.camera.fx - 1), "fy_pct": 100 * (rig.camera.fy / truth.camera.fy - 1),
        "cx_px": rig.camera.cx - truth.camera.cx, "cy_px": rig.camera.cy - truth.camera.cy,
        "k1": rig.camera.distortion[0] - truth.camera.distortion[0],
        "axis_angle_deg": math.degrees(math.acos(min(1.0, abs(float(direction @ true_direction))))),
        "axis_offset_mm": float(np.linalg.norm(offset - (offset @ true_direction) * true_direction)),
    }
    for entry in rig.elevations:
        result[f"radius_{entry.elevation_deg:g}_mm"] = (rig.radius_mm(entry.elevation_deg)
                                                       - truth.radius_mm(entry.elevation_deg))
    return result


def run_export(args: argparse.Namespace) -> int:
    """Handler of ``phantom scan export``."""
    from phantom.scan.camera import Rig
    from phantom.scan.capture import CaptureError
    from phantom.scan.export import export_colmap, export_meshroom

    if not (args.colmap or args.meshroom):
        raise CaptureError("say what to write: --colmap FOLDER and/or --meshroom FILE")
    folder = _open_capture(args.capture)
    rig = Rig.load(args.rig) if args.rig else None
    if args.colmap:
        print(f"wrote the COLMAP model of {len(folder.frames)} pictures into {export_colmap(folder, args.colmap, rig)} "
              f"(images: {folder.path / 'images'})")
    if args.meshroom:
        print(f"wrote {export_meshroom(folder, args.meshroom, rig)} ({len(folder.frames)} views)")
    return 0


def _check_out_is_free(args: argparse.Namespace) -> None:
    """A mesh already at ``--out`` (another scan's) is not written over by a slip of the option: ScanError unless
    ``--replace``."""
    from pathlib import Path

    from phantom.scan.compare import ScanError

    if Path(args.out).exists() and not args.replace:
        raise ScanError(f"--out {args.out} exists already: give another --out, or --replace to write over it")


def run_import(args: argparse.Namespace) -> int:
    """Handler of ``phantom scan import``."""
    from phantom.model.mesh.surface import Frame, enclosed_volume_ml
    from phantom.scan.compare import PHANTOM_RMS_RADIUS_MM, check_scale
    from phantom.scan.export import import_mesh
    from phantom.scan.reconstruct import check_mesh_path, write_mesh

    check_mesh_path(args.out)
    _check_out_is_free(args)
    mesh = import_mesh(_checked_mesh(args.mesh, give="the tool's mesh file (.obj, .ply or .stl)"), args.units)
    # compare-scan's check of the size, against the built-in phantom's: a mesh in mm read as cm was 32 litres
    check_scale(Frame.of(mesh).rms_radius_mm, PHANTOM_RMS_RADIUS_MM, args.units, "import", "pass --units {unit}",
                "scale it to mm (or give its unit with --units) before importing it")
    path = write_mesh(mesh, args.out)
    print(f"wrote {path}: {enclosed_volume_ml(mesh):.3f} ml, {len(mesh.triangles)} triangles, closed")
    return 0


def run_compare_scan(args: argparse.Namespace) -> int:
    """Handler of ``phantom compare-scan``."""
    import json
    from pathlib import Path

    import numpy as np

    from phantom import require_extra

    # its size, or a folder in its place, said at once, before the scene is read (read below as it is)
    _checked_mesh(args.scan, "the scan file", "the scan's mesh file (.obj, .ply or .stl)")
    if args.rerun_save:
        check_recording_path(args.rerun_save)
    with require_extra("scan"):  # said at once, not after the model's kernels are compiled (10 s on a new cache)
        import trimesh  # noqa: F401

    from phantom.cli.common import scene_pressures_kpa
    from phantom.model.fem.model import PhantomModel
    from phantom.model.mesh.surface import model_surface, rotation_axis
    from phantom.model.scene import load_scene
    from phantom.scan.compare import StageClock, compare, read_scan
    from phantom.scan.heatmap import write_heatmap, write_recording

    scene = load_scene(args.scene)
    pressures_kpa = scene_pressures_kpa(args.pressures_kpa, scene)
    clock = StageClock()
    with clock.stage("read"):
        scan = read_scan(args.scan, args.units)
    with clock.stage("model"):
        _checked_mesh(scene.mesh)
        model = PhantomModel.from_scene(scene, mesh_size_mm=args.size_mm)
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


def check_recording_path(path: str, option: str = "--rerun-save") -> None:
    """A Rerun recording's file, refused in one line (ScanError) before the comparison when it cannot be written:
    another suffix than .rrd, a folder (the SDK's "Failed to create file: Is a directory" came as a traceback
    after it), or a place it cannot be made (:func:`~phantom.cli.common.check_output_file`)."""
    from pathlib import Path

    from phantom.cli.common import check_output_file
    from phantom.scan.compare import ScanError

    if Path(path).suffix.lower() != RECORDING_SUFFIX and not Path(path).is_dir():
        raise ScanError(f"{option} {path}: a Rerun recording is a {RECORDING_SUFFIX} file: give a file name ending "
                        f"in {RECORDING_SUFFIX}")
    check_output_file(path, option, f"compare{RECORDING_SUFFIX}", ScanError)


def run_synthetic_scan(args: argparse.Namespace) -> int:
    """Handler of ``phantom scan synthetic``."""
    import meshio
    import numpy as np

    from phantom import PhantomError
    from phantom.cli.common import output_file, scene_pressures_kpa
    from phantom.model.fem.model import PhantomModel
    from phantom.model.mesh.surface import model_surface
    from phantom.model.scene import load_scene
    from phantom.scan.synthetic import make_scan, random_rotation

    check_synthetic_arguments(args)
    scene = load_scene(args.scene)
    pressures_kpa = scene_pressures_kpa(args.pressures_kpa, scene)
    model = PhantomModel.from_scene(scene)
    if args.modulus_factor != 1.0:
        model = model.with_material(youngs_modulus_pa=args.modulus_factor * model.material.youngs_modulus_pa)
    state = model.equilibrium([p * 1e3 for p in pressures_kpa])
    rng = np.random.default_rng(args.seed)
    scan = make_scan(model_surface(state.positions_m, model.outer_triangles), rng, levels=args.levels,
                     noise_mm=args.noise_mm, holes=args.holes, fragment=True, rotation=random_rotation(rng),
                     translation_mm=rng.uniform(-50.0, 50.0, 3))
    path = output_file(args.out)  # checked before the solve; its folder is made now
    try:
        meshio.write_points_cells(path, scan.mesh.vertices_mm, [("triangle", scan.mesh.triangles.astype(np.int32))])
    except (OSError, KeyError, meshio.WriteError) as error:
        raise PhantomError(f"cannot write {path}: {error}; give a .ply, .stl or .obj --out") from None
    print(f"wrote {path}: {len(scan.mesh.vertices_mm)} vertices, gland {state.gland_volume_m3 * 1e6:.3f} ml")
    return 0


def check_synthetic_arguments(args: argparse.Namespace) -> None:
    """``scan synthetic``'s numbers and ``--out``, refused in one line (PhantomError) before the model is solved:
    NaN noise wrote a scan of NaN vertices, ``--levels 12`` ran for minutes, a ``.txt`` --out, a negative seed
    and more holes than vertices were tracebacks after the solve."""
    import math
    from pathlib import Path

    from phantom import PhantomError
    from phantom.scan.compare import SCAN_SUFFIXES

    if not (math.isfinite(args.modulus_factor) and args.modulus_factor > 0):
        raise PhantomError(f"--modulus-factor {args.modulus_factor:g} must be a finite number above 0 (E times it; "
                           f"e.g. 0.85)")
    if not 0 <= args.noise_mm <= MAX_NOISE_MM:  # NaN fails it too
        raise PhantomError(f"--noise-mm {args.noise_mm:g} is out of range: give a noise from 0 to {MAX_NOISE_MM:g} mm "
                           f"(sigma, along the normals; a scanner's is tenths of a mm)")
    if args.levels < 0:
        raise PhantomError(f"--levels {args.levels}: give 0 to {MAX_LEVELS} subdivisions, not negative")
    if args.holes < 0:
        raise PhantomError(f"--holes {args.holes}: give 0 to {MAX_HOLES} holes, not negative")
    if args.levels > MAX_LEVELS:
        raise PhantomError(f"--levels {args.levels} is too many: each level multiplies the vertices by 4 "
                           f"({MAX_LEVELS} makes about 2 million of the built-in phantom's, 1.2 GB of memory); give "
                           f"0 to {MAX_LEVELS}")
    if args.holes > MAX_HOLES:
        raise PhantomError(f"--holes {args.holes} is too many: each cuts 20 mm^2 of the phantom's 4,400 mm^2 surface, "
                           f"and more than {MAX_HOLES} leave too little to align; give 0 to {MAX_HOLES}")
    if args.seed < 0:
        raise PhantomError(f"--seed {args.seed} is negative: give a whole number, 0 or more")
    out = Path(args.out)
    if out.suffix.lower() not in SCAN_SUFFIXES:
        raise PhantomError(f"--out {out}: a scan is written as .ply, .stl or .obj (not "
                           f"{out.suffix or 'no extension'}): give a file name ending in one of them")
    if out.is_dir():
        raise PhantomError(f"--out {out} is a folder: give a file name (.ply, .stl or .obj)")
