"""The scanner driven through a running daemon: the daemon's own ``scan`` method (:class:`DaemonScanner`), its
real camera checked at its start (:func:`camera_plan`), and the capture through the daemon's API that
``phantom scan capture`` and ``phantom scan validate --sim`` (phantom/cli/scan.py, scan_validate.py) use.

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
    daemon``): the capture loop, run by ``phantom daemon`` in the scan worker's process
    (``phantom.cli.scan_worker``), with the daemon's axes and state through its rig (``ThreadRig``'s calls).

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
        try:
            kept = load_rig(params["rig"]) if params.get("rig") else None
            folder = CaptureFolder.create(params["out"], camera.describe(), plan.to_json(), {"by": "daemon"}, kept)
            rig.configure(SCANNER_AXES)
            answer: dict[str, Any] = {"folder": str(folder.path)}
            try:
                capture(rig, camera, rig, plan, folder, stop=rig)
            except CaptureError as error:  # stopped or aborted: the folder says which, the error why
                answer["reason"] = str(error)
        finally:  # a webcam is let go: the process it was opened in outlives the scan, the next opens it again
            close = getattr(camera, "close", None)
            if close is not None:
                close()
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
        from phantom.scan.camera import virtual_pose_at, virtual_rig
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
                                 pose_at=virtual_pose_at(scale))
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
