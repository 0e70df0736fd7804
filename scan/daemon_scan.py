"""The daemon's ``scan`` API method's capture (:class:`DaemonScanner`, a ``phantom.host.motion.Scanner`` that
``phantom daemon`` gives the daemon, run in its scan worker's process, ``phantom.host.scan_worker``), and the
verify scan's plan with a real camera checked at the daemon's start (:func:`camera_plan`).

The capture loop (``phantom.scan.capture``) drives the daemon's rig as the scan worker hands it over: its calls
(``configure``, ``move_to``, ``position_deg``, ``release``, ``stop_requested``, ``pressures_kpa``, ``simulated``)
are ``phantom.host.motion.ThreadRig``'s, met here by duck typing (:class:`DaemonRig`): this part imports nothing
of the host. The virtual camera photographs the simulated phantom's truth, which the command line passes in as a
:class:`PhantomShapes` factory (``phantom.hil.simulated_truth.SimulatedTruth.shape``): nor of the HIL.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Any, Protocol

from phantom import PhantomError
from phantom.protocol.motion import SCANNER_AXES, AxisConfig
from phantom.scan.camera import Rig, virtual_pose_at, virtual_rig
from phantom.scan.capture import CaptureError, CaptureFolder, FrameSource, Plan, Webcam, capture
from phantom.scan.keying import KEYED

if TYPE_CHECKING:
    import numpy as np

    from phantom.scan.capture import Frame
    from phantom.scan.virtual import PhantomShapes


class ScanParamsError(PhantomError):
    """A ``scan`` request's params that are not ones (the caller's to fix: the API's ``invalid_params``)."""

    code = "invalid_params"


class DaemonRig(Protocol):
    """The daemon's axes and state as the capture sees them (``phantom.host.motion.ThreadRig``'s methods)."""

    def configure(self, configs: tuple[AxisConfig, ...]) -> None: ...

    def move_to(self, orbit_deg: float, elevation_deg: float) -> tuple[float, float]: ...

    def position_deg(self) -> tuple[float, float]: ...

    def release(self) -> None: ...

    def stop_requested(self, wait_s: float = 0.0) -> str | None: ...

    def pressures_kpa(self) -> list[float] | None: ...

    def simulated(self) -> dict[str, Any] | None: ...


#: The params a ``scan`` request takes.
SCAN_PARAMS = frozenset({"out", "views", "elevations_deg", "start_deg", "span_deg", "settle_s", "camera", "scale",
                         "seed", "width", "height", "exposure", "focus", "rig", "look", "key_silhouettes"})


class DaemonScanner:
    """The daemon's ``scan`` API method (a ``phantom.host.motion.Scanner``, given to the daemon by ``phantom
    daemon``): the capture loop, run by ``phantom daemon`` in the scan worker's process
    (``phantom.host.scan_worker``), with the daemon's axes and state through its rig (:class:`DaemonRig`).

    Params: ``out`` (the capture folder to make, required), ``views`` (per turn, default 60), ``elevations_deg``
    (default [0, 30]), ``start_deg`` (-180), ``span_deg`` (360), ``settle_s`` (0.3), ``camera`` ("virtual", the
    default, on the simulated board; a device number or a video path for a webcam), ``scale`` (the virtual
    picture's size of 1280x960), ``look`` (the virtual pictures: "ideal", the default, or "real": the phantom hung
    by its tubes, glossy, an uneven cloth, vignetting), ``seed``, ``width``, ``height``, ``exposure``, ``focus``,
    ``rig`` (a rig.json to keep beside the pictures), ``key_silhouettes`` (false; the daemon's verify scan sets it:
    each picture's silhouette keyed as it is taken and kept in this process for the reconstruction that follows,
    ``phantom.scan.keying``). Answers the folder, its status (``complete``, ``stopped``
    by a stop request, ``aborted``) and the number of pictures, and for a capture that did not complete the
    ``reason``. The virtual camera photographs what ``truth`` makes (the simulated phantom ``phantom daemon``
    gives: the shipped one unless ``--sim-truth`` said another; None: no virtual camera).

    Picklable (sent once to the scan worker's process): ``truth`` is called there, on the first virtual picture.
    """

    def __init__(self, truth: Callable[[], PhantomShapes] | None = None, look: str = "ideal",
                 camera: str | None = None):
        self.truth = truth
        # what the params do not say: the virtual camera's pictures (phantom daemon --look), the camera (--camera)
        self.look = look
        self.camera = camera
        self._shape: PhantomShapes | None = None

    def __call__(self, params: dict[str, Any], rig: DaemonRig) -> dict[str, Any]:
        plan, seed = self._checked(params)
        camera = self._camera(params, rig, plan.elevations_deg, params.get("scale", 1.0), seed)
        try:
            kept = Rig.load(params["rig"]) if params.get("rig") else None
            folder = CaptureFolder.create(params["out"], camera.describe(), plan.to_json(), {"by": "daemon"}, kept)
            answer: dict[str, Any] = {"folder": str(folder.path)}
            keep = self._keeper(folder, camera) if params.get("key_silhouettes") else None
            try:
                rig.configure(SCANNER_AXES)
                capture(rig, camera, rig, plan, folder, stop=rig, keep=keep)
            except CaptureError as error:  # stopped or aborted: the folder says which, the error why
                answer["reason"] = str(error)
            finally:  # a capture that did not complete leaves no silhouettes to read
                if keep is not None and folder.status != "complete":
                    self._drop(folder)
        finally:  # a webcam is let go: the process it was opened in outlives the scan, the next opens it again
            camera.close()
        return {**answer, "status": folder.status, "pictures": len(folder.frames)}

    @staticmethod
    def _keeper(folder: CaptureFolder, camera: FrameSource) -> Callable[[Frame, np.ndarray], None]:
        """What the capture gives each picture once written: its silhouette keyed (``phantom.scan.keying``) and,
        for a virtual camera's (posed in the model's frame), the model's silhouette at its pose rendered
        (``phantom.scan.hull_bias.ModelSilhouettes``, when the daemon gave the model's surface at the scan's
        pressures), both kept for the reconstruction that follows."""
        from phantom.scan.hull_bias import MODEL_SILHOUETTES  # the renderer's kernels: in the scan worker only
        from phantom.scan.virtual import VirtualCamera

        key = KEYED.start(folder)
        render = MODEL_SILHOUETTES.start(folder, camera.rig) if isinstance(camera, VirtualCamera) else None
        if render is None:
            return key

        def keep(frame: Frame, picture: np.ndarray) -> None:
            key(frame, picture)
            render(frame)

        return keep

    @staticmethod
    def _drop(folder: CaptureFolder) -> None:
        """Forget what :meth:`_keeper` kept of a capture that stopped or aborted: its keyed silhouettes and the
        model's rendered ones."""
        from phantom.scan.hull_bias import MODEL_SILHOUETTES

        KEYED.drop(folder)
        MODEL_SILHOUETTES.drop(folder)

    @staticmethod
    def _checked(params: dict[str, Any]) -> tuple[Plan, int]:
        """The scan's plan and seed from its params; ScanParamsError for a param that is not one or is out of
        range."""
        from phantom.scan.render import LOOKS  # the renderer's kernels: in the scan worker's process only

        unknown = sorted(set(params) - SCAN_PARAMS)
        if unknown or not isinstance(params.get("out"), str):
            raise ScanParamsError(f"scan takes out (a folder, required) and {', '.join(sorted(SCAN_PARAMS - {'out'}))}"
                                  + (f"; not {', '.join(unknown)}" if unknown else ""))
        elevations = params.get("elevations_deg", [0.0, 30.0])
        if not isinstance(elevations, list):
            raise ScanParamsError(f"scan: elevations_deg must be a list of angles (deg), got {elevations!r}")
        look = params.get("look", "ideal")  # checked here: the default is the daemon's, checked by its config
        if not isinstance(look, str) or look not in LOOKS:
            raise ScanParamsError(f"scan: look must be one of {', '.join(sorted(LOOKS))} (the virtual camera's "
                                  f"pictures: ideal, or as a real rig sees the phantom hung by its tubes), got "
                                  f"{look!r}")
        if not isinstance(params.get("key_silhouettes", False), bool):
            raise ScanParamsError(f"scan: key_silhouettes must be true or false, got {params['key_silhouettes']!r:.60}")
        seed = params.get("seed", 0)
        if isinstance(seed, bool) or not isinstance(seed, int) or not 0 <= seed < 2 ** 32:
            raise ScanParamsError(f"scan: seed must be a whole number from 0 to 2^32 - 1, got {seed!r}")
        # the plan and the virtual rig check their own numbers (NaN, negative, too many, too big) before any move
        try:
            plan = Plan(params.get("views", 60), tuple(elevations), params.get("start_deg", -180.0),
                        params.get("settle_s", 0.3), params.get("span_deg", 360.0))
        except PhantomError as error:
            raise ScanParamsError(f"scan: {error}") from None
        return plan, seed

    def _camera(self, params: dict[str, Any], rig: DaemonRig, elevations: tuple[float, ...], scale: Any,
                seed: int) -> FrameSource:
        camera = params.get("camera", self.camera or "virtual")
        if camera == "virtual":
            from phantom.scan.render import LOOKS
            from phantom.scan.virtual import VirtualCamera, truth_scene

            try:
                true_rig = virtual_rig(scale, elevations)
            except PhantomError as error:
                raise ScanParamsError(f"scan: {error}") from None
            if self._shape is None:
                if self.truth is None:
                    raise PhantomError("the virtual camera photographs the simulated phantom, and this daemon has "
                                       "none: give the scan a real camera (camera: a device number or a URL)")
                self._shape = self.truth()
            return VirtualCamera(true_rig, truth_scene(rig.simulated, self._shape), seed,
                                 look=LOOKS[params.get("look", self.look)], pose_at=virtual_pose_at(scale))
        source = int(camera) if isinstance(camera, int) or str(camera).isdigit() else str(camera)
        size = None
        if params.get("rig"):
            kept = Rig.load(params["rig"]).camera
            size = (kept.width, kept.height)
        return Webcam(source, params.get("width"), params.get("height"), params.get("exposure"), params.get("focus"),
                      size=size)


def camera_plan(camera: str | None, rig_path: Any, views: int) -> dict[str, Any]:
    """The verify scan's plan with a real camera (``phantom daemon --camera DEVICE|URL --rig rig.json``), checked
    before the daemon starts: the rig read, the camera opened and one picture taken, of the size the rig was
    calibrated at (PhantomError saying why otherwise); ``views`` stops a turn at each of the rig's elevations."""
    if camera is None or rig_path is None:
        raise PhantomError("--camera and --rig go together: the camera's pictures are posed by the rig's calibration "
                           "(phantom scan calibrate), give both")
    rig = Rig.load(str(rig_path))
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
    return {"views": views, "elevations_deg": [entry.elevation_deg for entry in rig.elevations],
            "settle_s": 0.3, "camera": camera, "width": rig.camera.width, "height": rig.camera.height,
            "rig": str(rig_path)}

