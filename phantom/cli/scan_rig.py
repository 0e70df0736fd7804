"""The scanner driven through a running daemon: ``phantom scan capture`` and ``phantom scan validate --sim``.

This module joins the parts: the daemon's API client (host), the capture loop, the cameras and the
reconstruction (scan), and on the simulated board the truth shape (hil). The capture loop's Protocols are met
here by adapters over the API:

- :class:`DaemonOrbit` (``scan.capture.Orbit``): ``motion_move``, ``motion_status`` for where the rig is at a
  picture (the simulated rig's true angles on the simulated board), and ``motion_stop`` with the drivers released;
- :class:`DaemonPhantom` (``scan.capture.PhantomState``): the measured pressures from ``status``; a latched
  fault or a lost link stops the capture;
- :func:`simulated_scene`: for the virtual camera, the simulated rig's true angles and the truth model's surface
  at the plant's true pressures (``motion_status``'s ``simulated`` part).
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from phantom import PhantomError

if TYPE_CHECKING:
    from phantom.hil.truth_shape import TruthShape
    from phantom.host.client import DaemonClient
    from phantom.model.mesh.surface import TriangleMesh
    from phantom.scan.capture import CaptureFolder, FrameSource, Plan, Progress


class DaemonOrbit:
    """The scanner's axes through the daemon's API (a ``phantom.scan.capture.Orbit``)."""

    def __init__(self, client: DaemonClient):
        self.client = client

    def move_to(self, orbit_deg: float, elevation_deg: float) -> tuple[float, float]:
        status = _call(self.client, "motion_move", {"orbit_deg": orbit_deg, "elevation_deg": elevation_deg})
        axes = status["axes"]
        return float(axes[0]["position_deg"]), float(axes[1]["position_deg"])

    def position_deg(self) -> tuple[float, float]:
        """The simulated rig's true angles (``motion_status``'s ``simulated``), else those the board reports."""
        from phantom.host.motion import rig_position_deg

        return rig_position_deg(_call(self.client, "motion_status"))

    def release(self) -> None:
        _call(self.client, "motion_stop", {"release": True})

    def configure(self) -> None:
        """Send the scanner's axes (``phantom.protocol.motion.SCANNER_AXES``) to the board."""
        from dataclasses import asdict

        from phantom.protocol.motion import SCANNER_AXES

        for axis, config in enumerate(SCANNER_AXES):
            _call(self.client, "motion_config", {"axis": axis, **asdict(config)})


class DaemonPhantom:
    """The phantom's state through the daemon's API (a ``phantom.scan.capture.PhantomState``)."""

    def __init__(self, client: DaemonClient):
        self.client = client

    def pressures_kpa(self) -> list[float] | None:
        from phantom.host.motion import scannable_pressures_kpa

        return scannable_pressures_kpa(_call(self.client, "status"))


def _call(client: DaemonClient, method: str, params: dict[str, Any] | None = None) -> Any:
    from phantom.host.client import DaemonError

    try:
        return client.call(method, params)
    except DaemonError as error:
        raise PhantomError(f"the daemon refused {method}: {error}") from None


def simulated_scene(client: DaemonClient, truth: TruthShape) -> Callable[[], tuple[TriangleMesh, float, float]]:
    """What the virtual camera sees on the simulated board now: the truth model's surface at the plant's true
    pressures and the rig's true angles."""
    return truth_scene(lambda: _call(client, "motion_status").get("simulated"), truth)


def truth_scene(read: Callable[[], dict[str, Any] | None],
                truth: TruthShape) -> Callable[[], tuple[TriangleMesh, float, float]]:
    """The virtual camera's scene from the simulated board's truth as ``read`` returns it (``motion_status``'s
    ``simulated`` part)."""
    def now() -> tuple[TriangleMesh, float, float]:
        simulated = read()
        if not simulated or simulated.get("rig_deg") is None or None in simulated["rig_deg"]:
            raise PhantomError("the daemon does not report a simulated rig: the virtual camera needs `phantom "
                               "daemon --sim`; with a real board give --camera N (a webcam)")
        orbit_deg, elevation_deg = simulated["rig_deg"]
        return truth.surface(simulated["pressures_kpa"]), float(orbit_deg), float(elevation_deg)
    return now


def capture_through_daemon(client: DaemonClient, camera: FrameSource, plan: Plan, folder: CaptureFolder,
                           progress: Progress | None = None) -> CaptureFolder:
    """Configure the axes and take the plan's pictures through the daemon (the capture loop of
    ``phantom.scan.capture``)."""
    from phantom.scan.capture import capture

    orbit = DaemonOrbit(client)
    orbit.configure()
    return capture(orbit, camera, DaemonPhantom(client), plan, folder, progress)


@dataclass(frozen=True)
class SimulatedTruth:
    """The simulated phantom a virtual camera photographs: the scene, its modulus factor, the plant whose
    gland volume its shape is scaled to and the truth's own shapes built with it (the defaults: the shipped
    truth, hil/truth_shape.py, with the scene's shipped shapes)."""

    scene: str | Path | None = None
    modulus_factor: float | None = None
    plant_path: Path | None = None
    shapes_path: Path | None = None

    def shape(self) -> TruthShape:
        from phantom.hil.plant import CALIBRATED_SCENE_PATH, DEFAULT_PLANT_PATH, TRUTH_MODULUS_FACTOR
        from phantom.hil.truth_shape import TruthShape

        return TruthShape(self.scene or CALIBRATED_SCENE_PATH, self.modulus_factor or TRUTH_MODULUS_FACTOR,
                          plant_path=self.plant_path or DEFAULT_PLANT_PATH, shapes_path=self.shapes_path)


class DaemonScanner:
    """The daemon's ``scan`` API method (a ``phantom.host.motion.Scanner``, given to the daemon by ``phantom
    daemon``): the capture loop in the daemon's process, with its axes and state (``ThreadRig``).

    Params: ``out`` (the capture folder to make, required), ``views`` (per turn, default 60), ``elevations_deg``
    (default [0, 30]), ``start_deg`` (-180), ``span_deg`` (360), ``settle_s`` (0.3), ``camera`` ("virtual", the
    default, on the simulated board; a device number or a video path for a webcam), ``scale`` (the virtual
    picture's size of 1280x960), ``look`` (the virtual pictures: "ideal", the default, or "real": the phantom hung
    by its tubes, glossy, an uneven cloth, vignetting), ``seed``, ``width``, ``height``, ``exposure``, ``focus``,
    ``rig`` (a rig.json to keep beside the pictures). Answers the folder, its status (``complete``, ``stopped``
    by a stop request, ``aborted``) and the number of pictures, and for a capture that did not complete the
    ``reason``. The virtual camera photographs ``truth`` (the shipped simulated phantom unless ``phantom daemon
    --sim-truth`` said another)."""

    def __init__(self, truth: SimulatedTruth | None = None, look: str = "ideal", camera: str | None = None):
        self.truth = truth or SimulatedTruth()
        # what the params do not say: the virtual camera's pictures (phantom daemon --look), the camera (--camera)
        self.look = look
        self.camera = camera
        self._shape: TruthShape | None = None

    def __call__(self, params: dict[str, Any], rig: Any) -> dict[str, Any]:
        from phantom.cli.common import load_rig
        from phantom.host.api import ApiError
        from phantom.protocol.motion import SCANNER_AXES
        from phantom.scan.capture import CaptureError, CaptureFolder, capture

        try:
            plan, seed = self._checked(params)
        except PhantomError as error:  # bad params are the caller's to fix (invalid_params), not a state's refusal
            raise ApiError("invalid_params", str(error)) from None
        camera = self._camera(params, rig, plan.elevations_deg, params.get("scale", 1.0), seed)
        kept = load_rig(params["rig"]) if params.get("rig") else None
        folder = CaptureFolder.create(params["out"], camera.describe(), plan.to_json(), {"by": "daemon"}, kept)
        rig.configure(SCANNER_AXES)
        answer: dict[str, Any] = {"folder": str(folder.path)}
        try:
            capture(rig, camera, rig, plan, folder, stop=rig)
        except CaptureError as error:  # stopped or aborted: the folder says which, the error why
            answer["reason"] = str(error)
        return {**answer, "status": folder.status, "pictures": len(folder.frames)}

    @staticmethod
    def _checked(params: dict[str, Any]) -> tuple[Any, int]:
        """The scan's plan and seed from its params; PhantomError for a param that is not one or is out of range."""
        from phantom.scan.capture import Plan
        from phantom.scan.render import LOOKS

        known = {"out", "views", "elevations_deg", "start_deg", "span_deg", "settle_s", "camera", "scale", "seed",
                 "width", "height", "exposure", "focus", "rig", "look"}
        unknown = sorted(set(params) - known)
        if unknown or not isinstance(params.get("out"), str):
            raise PhantomError(f"scan takes out (a folder, required) and {', '.join(sorted(known - {'out'}))}"
                               + (f"; not {', '.join(unknown)}" if unknown else ""))
        elevations = params.get("elevations_deg", [0.0, 30.0])
        if not isinstance(elevations, list):
            raise PhantomError(f"scan: elevations_deg must be a list of angles (deg), got {elevations!r}")
        look = params.get("look", "ideal")  # checked here: the default is the daemon's, checked by its config
        if not isinstance(look, str) or look not in LOOKS:
            raise PhantomError(f"scan: look must be one of {', '.join(sorted(LOOKS))} (the virtual camera's "
                               f"pictures: ideal, or as a real rig sees the phantom hung by its tubes), got {look!r}")
        seed = params.get("seed", 0)
        if isinstance(seed, bool) or not isinstance(seed, int) or not 0 <= seed < 2 ** 32:
            raise PhantomError(f"scan: seed must be a whole number from 0 to 2^32 - 1, got {seed!r}")
        # the plan and the virtual rig check their own numbers (NaN, negative, too many, too big) before any move
        try:
            plan = Plan(params.get("views", 60), tuple(elevations), params.get("start_deg", -180.0),
                        params.get("settle_s", 0.3), params.get("span_deg", 360.0))
        except PhantomError as error:
            raise PhantomError(f"scan: {error}") from None
        return plan, seed

    def _camera(self, params: dict[str, Any], rig: Any, elevations: tuple[float, ...], scale: Any,
                seed: int) -> FrameSource:
        from phantom.scan.camera import virtual_rig
        from phantom.scan.capture import Webcam

        camera = params.get("camera", self.camera or "virtual")
        if camera == "virtual":
            from phantom.scan.virtual import VirtualCamera

            try:
                true_rig = virtual_rig(scale, elevations)
            except PhantomError as error:
                raise PhantomError(f"scan: {error}") from None
            from phantom.scan.render import LOOKS

            if self._shape is None:
                self._shape = self.truth.shape()
            return VirtualCamera(true_rig, truth_scene(rig.simulated, self._shape), seed,
                                 look=LOOKS[params.get("look", self.look)],
                                 pose_at=_scaled_pose(scale))
        source = int(camera) if isinstance(camera, int) or str(camera).isdigit() else str(camera)
        size = None
        if params.get("rig"):
            from phantom.cli.common import load_rig

            kept = load_rig(params["rig"]).camera
            size = (kept.width, kept.height)
        return Webcam(source, params.get("width"), params.get("height"), params.get("exposure"), params.get("focus"),
                      size=size)


def camera_plan(camera: str | None, rig_path: Any) -> dict[str, Any]:
    """The verify scan's plan with a real camera (``phantom daemon --camera DEVICE|URL --rig rig.json``), checked
    before the daemon starts: the rig read, the camera opened and one picture taken, of the size the rig was
    calibrated at (PhantomError saying why otherwise); 30 stops a turn at each of the rig's elevations."""
    from phantom.cli.common import load_rig
    from phantom.cli.scan_verify import VERIFY_PLAN
    from phantom.scan.capture import Webcam

    if camera is None or rig_path is None:
        raise PhantomError("--camera and --rig go together: the camera's pictures are posed by the rig's calibration "
                           "(phantom scan calibrate), give both")
    rig = load_rig(str(rig_path))
    source: int | str = int(camera) if camera.isdigit() else camera
    webcam = Webcam(source, rig.camera.width, rig.camera.height)
    try:
        picture = webcam.grab()
    finally:
        webcam.close()
    height, width = picture.shape[:2]
    if (width, height) != (rig.camera.width, rig.camera.height):
        raise PhantomError(f"the camera {camera} gives {width}x{height} pictures and the rig {rig_path} was calibrated "
                           f"at {rig.camera.width}x{rig.camera.height}: calibrate the rig at the camera's size "
                           f"(phantom scan capture --target, phantom scan calibrate), or give the camera that size")
    return {"views": VERIFY_PLAN["views"], "elevations_deg": [entry.elevation_deg for entry in rig.elevations],
            "settle_s": 0.3, "camera": camera, "width": rig.camera.width, "height": rig.camera.height,
            "rig": str(rig_path)}


def run_capture(args: Any) -> int:
    """Handler of ``phantom scan capture``."""
    import sys

    from phantom.cli.common import frame_progress, load_rig, plan_of
    from phantom.host.api import default_socket_path
    from phantom.host.client import DaemonClient
    from phantom.scan.camera import virtual_rig
    from phantom.scan.capture import CaptureFolder, Webcam
    from phantom.scan.render import CharucoTarget

    plan = dataclasses.replace(plan_of(args, args.settle_s), start_deg=args.start_deg, span_deg=args.span_deg)
    rig = load_rig(args.rig) if args.rig else None
    camera: FrameSource
    with DaemonClient(args.socket or default_socket_path()) as client:
        if args.camera == "virtual":
            from phantom.hil.truth_shape import TruthShape
            from phantom.scan.virtual import TargetCamera, VirtualCamera

            true_rig = virtual_rig(args.scale, plan.elevations_deg)
            pose_at = _scaled_pose(args.scale)
            if args.target:
                camera = TargetCamera(true_rig, CharucoTarget(), _placement(args.placement), _FollowingOrbit(client),
                                      args.seed, pose_at)
            else:
                camera = VirtualCamera(true_rig, simulated_scene(client, TruthShape()), args.seed, pose_at=pose_at)
        else:
            source: int | str = int(args.camera) if args.camera.isdigit() else args.camera
            camera = Webcam(source, args.width, args.height, args.exposure, args.focus)
        conditions: dict[str, Any] = {"socket": str(args.socket or default_socket_path())}
        if args.target:
            conditions["target"] = CharucoTarget().to_json()
        folder = CaptureFolder.create(args.out, camera.describe(), plan.to_json(), conditions, rig)
        progress = frame_progress("captured")
        capture_through_daemon(client, camera, plan, folder, progress)
    print(f"captured {len(folder.frames)} pictures into {folder.path}", file=sys.stderr)
    return 0


class _FollowingOrbit:
    """The simulated rig's true angles, read when the target camera renders (it has the attributes the
    TargetCamera reads)."""

    def __init__(self, client: DaemonClient):
        self.client = client

    @property
    def orbit_deg(self) -> float:
        return float(self._angles()[0])

    @property
    def elevation_deg(self) -> float:
        return float(self._angles()[1])

    def _angles(self) -> list[float]:
        simulated = _call(self.client, "motion_status").get("simulated") or {}
        angles = simulated.get("rig_deg")
        if angles is None or None in angles:
            raise PhantomError("the daemon does not report a simulated rig: the virtual camera needs `phantom "
                               "daemon --sim`")
        return [float(a) for a in angles]


def _scaled_pose(scale: float) -> Callable[[float, float], Any]:
    from phantom.scan.camera import virtual_pose

    return lambda orbit_deg, elevation_deg: virtual_pose(orbit_deg, elevation_deg, scale)


def _placement(number: int) -> Any:
    from phantom.scan.render import CharucoTarget
    from phantom.scan.virtual import VIRTUAL_PLACEMENTS, target_pose_facing

    if not 0 <= number < len(VIRTUAL_PLACEMENTS):
        raise PhantomError(f"--placement is 0..{len(VIRTUAL_PLACEMENTS) - 1} on the virtual rig, got {number}")
    return target_pose_facing(*VIRTUAL_PLACEMENTS[number], CharucoTarget())


def scene_targets_ml(scene_path: str) -> list[float]:
    """The gland volumes (ml) a scene's [[steps]] go through, in order, each once."""
    import tomllib

    from phantom import read_text
    from phantom.model.scene import MAX_SCENE_BYTES

    try:
        steps = tomllib.loads(read_text(scene_path, MAX_SCENE_BYTES, "the scene")).get("steps", [])
    except tomllib.TOMLDecodeError as error:
        raise PhantomError(f"cannot read the scene {scene_path}: {error}") from None
    volumes: list[float] = []
    for step in steps:
        volume = step.get("volume_ml")
        if isinstance(volume, (int, float)) and volume not in volumes:
            volumes.append(float(volume))
    if not volumes:
        raise PhantomError(f"the scene {scene_path} has no [[steps]] with volume_ml: give --targets")
    return volumes


def run_validate(args: Any) -> int:
    """Handler of ``phantom scan validate --sim``: the paper's validation on the simulated rig."""
    import json
    import shlex
    import signal
    import subprocess
    import sys
    from pathlib import Path

    import numpy as np

    import phantom
    from phantom.cli.common import frame_progress, load_rig, parse_numbers, plan_of
    from phantom.cli.demo import wait_until_ready
    from phantom.hil.truth_shape import TruthShape
    from phantom.host.client import DaemonClient
    from phantom.host.scenes import example_scene_path, load_timeline_scene
    from phantom.model import PhantomModel
    from phantom.model.mesh.surface import TriangleMesh, model_surface
    from phantom.scan.calibrate import calibrate_rig, target_views
    from phantom.scan.camera import virtual_rig
    from phantom.scan.capture import CaptureFolder
    from phantom.scan.compare import compare, read_scan
    from phantom.scan.heatmap import write_heatmap
    from phantom.scan.reconstruct import VOXEL_MM, reconstruct, write_mesh
    from phantom.scan.validation import TargetResult, frame_map, truth_distances, write_recording, write_report
    from phantom.scan.virtual import VirtualCamera, render_target_captures

    if not args.sim:
        raise PhantomError("validate runs on the simulated rig: give --sim (with a real board, scan with `phantom "
                           "scan capture`, `reconstruct` and `compare-scan`)")
    plan = plan_of(args, args.settle_s)
    elevations = plan.elevations_deg
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    scene = args.scene or str(example_scene_path("bph_growth"))
    targets = parse_numbers(args.targets, "--targets") if args.targets else scene_targets_ml(scene)
    true_rig = virtual_rig(args.scale, elevations)
    started = time.monotonic()

    def say(text: str) -> None:
        print(f"[{time.monotonic() - started:6.1f} s] {text}", file=sys.stderr, flush=True)

    # the rig's calibration, from rendered pictures of the target, as a real rig's from photographs of it
    if args.rig:
        rig = load_rig(args.rig)
    else:
        say("calibrating the virtual rig from pictures of the ChArUco target ...")
        folders = render_target_captures(true_rig, out / "target", args.target_views)
        rig = calibrate_rig(target_views(folders), true_rig.camera.width, true_rig.camera.height)
        rig.save(out / "rig.json")
        say(f"rig calibrated: reprojection RMS {rig.calibration['rms_px']:.3f} px")
    to_truth = frame_map(rig, true_rig, elevations[0])
    truth = TruthShape()
    controller = PhantomModel.from_scene(load_timeline_scene(scene))
    socket = out / "daemon.sock"
    command = [str(Path(sys.executable).with_name("phantom")), "daemon", "--sim", "--scene", scene, "--socket",
               str(socket), "--sim-speed", f"{args.sim_speed:g}"]
    say("$ " + shlex.join(command))
    log = open(out / "daemon.log", "w")
    process = subprocess.Popen(command, stdout=log, stderr=subprocess.STDOUT)
    results: list[TargetResult] = []
    captures: list[Path] = []
    models: list[tuple[TriangleMesh, np.ndarray]] = []
    try:
        wait_until_ready(socket, process, out / "daemon.log", stage_limit_s=args.daemon_timeout_s)
        say("daemon ready")
        with DaemonClient(socket) as client, phantom.connect(socket) as daemon:
            for target_ml in targets:
                # reached and settled by the control core's rule (the client's wait), as every client waits
                reached = daemon.set_volume(target_ml, wait=True)
                answer: dict[str, Any] = {"pressures_kpa": list(reached.pressures_kpa),
                                          "predicted_volume_ml": reached.predicted_volume_ml,
                                          "iterations": reached.iterations}
                measured = list(reached.measured_pressures_kpa or reached.pressures_kpa)
                say(f"{target_ml:g} ml: inverse {', '.join(f'{p:.3f}' for p in answer['pressures_kpa'])} kPa, "
                    f"held at {', '.join(f'{p:.3f}' for p in measured)} kPa; capturing {len(plan.stops())} pictures")
                folder = CaptureFolder.create(out / f"capture_{target_ml:g}ml", {}, plan.to_json(), {
                    "scene": scene, "target_ml": target_ml, "inverse": answer}, rig)
                camera = VirtualCamera(true_rig, simulated_scene(client, truth), args.seed,
                                       pose_at=_scaled_pose(args.scale))
                folder.camera = camera.describe()
                capture_through_daemon(client, camera, plan, folder, frame_progress(f"  {target_ml:g} ml"))
                frame_pressures = np.array([frame.pressures_kpa for frame in folder.frames], dtype=float)
                pressures = frame_pressures.mean(axis=0)
                result = reconstruct(folder, rig, args.voxel_mm or VOXEL_MM)
                mesh_path = write_mesh(result.mesh, out / f"scan_{target_ml:g}ml.ply")
                state = controller.equilibrium(pressures * 1e3)
                model = model_surface(state.positions_m, controller.outer_triangles)
                comparison = compare(read_scan(mesh_path), model, state.gland_volume_m3 * 1e6)
                heatmap = write_heatmap(comparison, out / f"heatmap_{target_ml:g}ml.png",
                                        f"scan against the model at the {target_ml:g} ml target\nmean "
                                        f"{comparison.symmetric_mm['mean']:.3f} mm, volume {result.volume_ml:.2f} ml "
                                        f"(model {state.gland_volume_m3 * 1e6:.2f} ml)")
                scanned = TriangleMesh(to_truth.apply(result.mesh.vertices_mm), result.mesh.triangles)
                true_surface = truth.surface(pressures)
                results.append(TargetResult(
                    target_ml, [float(p) for p in answer["pressures_kpa"]], pressures.tolist(),
                    float(answer["predicted_volume_ml"]), state.gland_volume_m3 * 1e6,
                    truth.gland_volume_ml(pressures), result.volume_ml, comparison.symmetric_mm,
                    truth_distances(scanned, true_surface), str(folder.path), str(mesh_path), str(heatmap),
                    len(folder.frames), [rig.camera.width, rig.camera.height], result.stage_s))
                captures.append(folder.path)
                # the model into the rig's frame, where the reconstruction and the cameras are (x_model = R x + t)
                alignment = comparison.alignment
                in_rig_mm = (comparison.model_vertices_mm - alignment.translation_mm) @ alignment.rotation
                models.append((TriangleMesh(in_rig_mm, comparison.model_triangles),
                               comparison.model_signed_distance_mm))
                last = results[-1]
                say(f"{target_ml:g} ml: scan {last.scan_ml:.2f} ml ({last.scan_vs_target_pct:+.2f} % of the target, "
                    f"{last.scan_vs_model_pct:+.2f} % of the model, {last.scan_vs_truth_pct:+.2f} % of the truth); "
                    f"mean distance to the model {last.model_distance_mm['mean']:.3f} mm, to the truth "
                    f"{last.truth_distance_mm['mean']:.3f} mm")
            _call(client, "vent")
    finally:
        if process.poll() is None:
            process.send_signal(signal.SIGTERM)
            process.wait(30)
        log.close()
    meta = {"command": shlex.join(["phantom", *args.argv]), "scene": scene,
            "truth": truth.description, "rig": rig.calibration, "elapsed_s": time.monotonic() - started}
    report = write_report(results, out, meta)
    recording = write_recording(results, rig, captures, models, out / "validation.rrd") if args.rerun else None
    if args.json:
        print(json.dumps({"report": str(report), "recording": None if recording is None else str(recording),
                          "targets": [r.to_json() for r in results]}))
    else:
        print(report.read_text())
        print(f"report {report}" + (f", recording {recording}" if recording else ""))
    return 0
