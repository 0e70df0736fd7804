"""The virtual scanner: a camera that renders what the rig's webcam would see, and an orbit for rendering offline.

:class:`VirtualCamera` is a :class:`~phantom.scan.capture.FrameSource`: each picture renders the mesh that its
``scene`` callable returns, from the rig's pose at the orbit angle and elevation it returns, with the sensor's
noise. On the simulated board the command line passes a scene that reads the simulated rig's true angles (from
the pulses its drivers took) and the truth model's shape at the plant's pressures; offline
(:func:`render_capture`, ``phantom scan render``) the scene is a fixed mesh and the angles the
:class:`VirtualOrbit`'s. Either way the pictures go through :func:`phantom.scan.capture.capture`, the loop a
webcam uses.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from phantom import PhantomError
from phantom.model.arrays import FloatArray
from phantom.model.mesh.surface import TriangleMesh, vertex_normals
from phantom.scan.camera import VIRTUAL_CENTRE_MM, Pose, Rig, axis_rotation
from phantom.scan.capture import CaptureFolder, Plan, Progress, capture
from phantom.scan.render import DEFAULT_LOOK, SUPERSAMPLE, CharucoTarget, Look, Renderer, hung_scene, to_8bit

#: What the virtual camera sees at one moment: the phantom's surface (mm, the rig's world) and the true orbit
#: angle and elevation (deg).
SceneNow = Callable[[], tuple[TriangleMesh, float, float]]


#: The camera's true pose at an orbit angle and elevation (deg).
PoseAt = Callable[[float, float], Pose]


class PhantomShapes(Protocol):
    """The simulated phantom's surface at any chamber pressures (``phantom.hil.truth_shape.TruthShape``)."""

    def surface(self, pressures_kpa: list[float] | np.ndarray) -> TriangleMesh: ...


def truth_scene(read: Callable[[], dict[str, Any] | None], truth: PhantomShapes) -> SceneNow:
    """The virtual camera's scene on the simulated board: the truth's surface at the plant's true pressures and
    the rig's true angles, as ``read`` returns them (``motion_status``'s ``simulated`` part: ``rig_deg``,
    ``pressures_kpa``); PhantomError when it returns none (not the simulated board)."""
    def now() -> tuple[TriangleMesh, float, float]:
        simulated = read()
        if not simulated or simulated.get("rig_deg") is None or None in simulated["rig_deg"]:
            raise PhantomError("the daemon does not report a simulated rig: the virtual camera needs `phantom "
                               "daemon --sim`; with a real board give --camera N (a webcam)")
        orbit_deg, elevation_deg = simulated["rig_deg"]
        return truth.surface(simulated["pressures_kpa"]), float(orbit_deg), float(elevation_deg)
    return now


class VirtualCamera:
    """A webcam on the rig, rendered (see the module docstring); ``seed`` makes the noise repeatable. The rig gives
    the camera; ``pose_at`` the true pose at any angles (default the rig's own poses)."""

    def __init__(self, rig: Rig, scene: SceneNow, seed: int = 0, supersample: int = SUPERSAMPLE,
                 look: Look = DEFAULT_LOOK, pose_at: PoseAt | None = None):
        self.rig = rig
        self.pose_at: PoseAt = pose_at or rig.pose
        self.scene = scene
        self.renderer = Renderer(rig.camera, supersample, look)
        self.rng = np.random.default_rng(seed)
        self.seed = seed
        self._drawn: tuple[TriangleMesh, TriangleMesh, np.ndarray, np.ndarray | None] | None = None

    def grab(self) -> np.ndarray:
        return self.take()()

    def close(self) -> None:
        """Nothing to let go: a rendered camera holds no device."""

    def take(self) -> Callable[[], np.ndarray]:
        """The picture of this moment: the scene and the rig's angles read now; the returned call renders it (the
        capture loop renders it while the rig moves on). Rendered in the order taken, one at a time."""
        mesh, orbit_deg, elevation_deg = self.scene()
        pose = self.pose_at(orbit_deg, elevation_deg)

        def develop() -> np.ndarray:
            if self._drawn is None or self._drawn[0] is not mesh:
                if self.renderer.look.tubes and len(mesh.triangles):
                    self._drawn = (mesh, *hung_scene(mesh))
                else:
                    self._drawn = (mesh, mesh, vertex_normals(mesh.vertices_mm, mesh.triangles), None)
            linear = self.renderer.render_mesh(self._drawn[1], pose, self._drawn[2], self._drawn[3])
            return to_8bit(linear, self.rng, self.renderer.look)
        return develop

    def describe(self) -> dict[str, Any]:
        camera = self.rig.camera
        look = self.renderer.look
        return {"kind": "virtual", "width": camera.width, "height": camera.height, "seed": self.seed,
                "supersample": self.renderer.supersample, "tubes": look.tubes, "gloss": look.gloss,
                "cloth": look.cloth, "vignetting": look.vignetting, "noise": look.noise}


class VirtualOrbit:
    """An orbit that is where it is told at once (for rendering offline); it never fails."""

    def __init__(self) -> None:
        self.orbit_deg = 0.0
        self.elevation_deg = 0.0
        self.released = False

    def move_to(self, orbit_deg: float, elevation_deg: float) -> tuple[float, float]:
        self.orbit_deg, self.elevation_deg, self.released = orbit_deg, elevation_deg, False
        return orbit_deg, elevation_deg

    def position_deg(self) -> tuple[float, float]:
        return self.orbit_deg, self.elevation_deg

    def release(self) -> None:
        self.released = True


class FixedPhantom:
    """A phantom state with no pressures to report (a mesh rendered offline)."""

    def pressures_kpa(self) -> list[float] | None:
        return None


def render_capture(mesh: TriangleMesh, rig: Rig, plan: Plan, out: str | Path, seed: int = 0,
                   conditions: dict[str, Any] | None = None, progress: Progress | None = None,
                   supersample: int = SUPERSAMPLE, look: Look = DEFAULT_LOOK) -> CaptureFolder:
    """The virtual rig's pictures of ``mesh`` (mm, the rig's world) into a new capture folder, with ``rig``
    kept beside them."""
    orbit = VirtualOrbit()
    camera = VirtualCamera(rig, lambda: (mesh, orbit.orbit_deg, orbit.elevation_deg), seed, supersample, look)
    folder = CaptureFolder.create(out, camera.describe(), plan.to_json(), conditions, rig)
    return capture(orbit, camera, FixedPhantom(), replace(plan, settle_s=0.0), folder, progress)


class Angles(Protocol):
    """Where the rig is (deg): a VirtualOrbit's angles, or the simulated rig's true ones."""

    @property
    def orbit_deg(self) -> float: ...

    @property
    def elevation_deg(self) -> float: ...


class TargetCamera(VirtualCamera):
    """The virtual camera's pictures of the calibration target where ``target_pose`` (target to world) puts it,
    from where ``orbit`` says the rig is."""

    def __init__(self, rig: Rig, target: CharucoTarget, target_pose: Pose, orbit: Angles, seed: int = 0,
                 pose_at: PoseAt | None = None):
        super().__init__(rig, lambda: (TriangleMesh(np.zeros((0, 3)), np.zeros((0, 3), np.int64)), 0.0, 0.0), seed,
                         pose_at=pose_at)
        self.target, self.target_pose, self.orbit = target, target_pose, orbit

    def take(self) -> Callable[[], np.ndarray]:
        orbit = self.orbit
        pose = self.pose_at(orbit.orbit_deg, orbit.elevation_deg)
        return lambda: to_8bit(self.renderer.render_target(self.target, self.target_pose, pose), self.rng,
                               self.renderer.look)

    def describe(self) -> dict[str, Any]:
        return {**super().describe(), "target": self.target.to_json()}


def target_pose_facing(orbit_deg: float, tilt_deg: float, spin_deg: float, target: CharucoTarget,
                       centre_mm: FloatArray = VIRTUAL_CENTRE_MM) -> Pose:
    """The target's placement (target to world) in the virtual rig: centred on ``centre_mm``, upright, its printed
    face towards the camera at ``orbit_deg`` (elevation 0), then tilted back by ``tilt_deg`` and turned in its
    own plane by ``spin_deg``."""
    facing = np.array([math.cos(math.radians(orbit_deg)), math.sin(math.radians(orbit_deg)), 0.0])
    across = np.cross(np.array([0.0, 0.0, 1.0]), facing)        # the target's x: to the camera's right
    down = np.array([0.0, 0.0, -1.0])
    rotation = np.column_stack([across, down, -facing])          # the printed side (-z) faces the camera
    rotation = axis_rotation(across, -tilt_deg) @ rotation @ axis_rotation(np.array([0.0, 0.0, 1.0]), spin_deg)
    width, height = target.size_mm
    translation = np.asarray(centre_mm, float) - rotation @ np.array([width / 2, height / 2, 0.0])
    return Pose(rotation, translation)


#: The virtual rig's calibration: two placements of the target, each seen over +-50 deg of the orbit at both
#: elevations: upright towards orbit 0, and towards orbit 180 tilted back 25 deg and turned 10 deg in its plane.
VIRTUAL_PLACEMENTS = ((0.0, 0.0, 0.0), (180.0, 25.0, 10.0))
VIRTUAL_TARGET_SPAN_DEG = 100.0


def virtual_placement(number: int, target: CharucoTarget | None = None) -> Pose:
    """The target's pose (target to world) in the virtual rig's calibration placement ``number``
    (:data:`VIRTUAL_PLACEMENTS`); PhantomError for a placement there is not."""
    if not 0 <= number < len(VIRTUAL_PLACEMENTS):
        raise PhantomError(f"--placement is 0..{len(VIRTUAL_PLACEMENTS) - 1} on the virtual rig, got {number}")
    return target_pose_facing(*VIRTUAL_PLACEMENTS[number], target or CharucoTarget())


class AnglesRead:
    """The rig's angles (an :class:`Angles`) read from ``read`` (orbit_deg, elevation_deg) each time a camera
    renders: the simulated rig's true angles through the daemon, for the target's virtual pictures."""

    def __init__(self, read: Callable[[], tuple[float, float]]):
        self.read = read

    @property
    def orbit_deg(self) -> float:
        return float(self.read()[0])

    @property
    def elevation_deg(self) -> float:
        return float(self.read()[1])


def render_target_captures(rig: Rig, out: str | Path, views: int = 11, seed: int = 0,
                           target: CharucoTarget | None = None,
                           progress: Progress | None = None) -> list[CaptureFolder]:
    """The virtual rig's pictures of the calibration target, one capture folder per placement
    (``out/placement0``, ...), each over VIRTUAL_TARGET_SPAN_DEG of the orbit at every elevation of the rig."""
    target = target or CharucoTarget()
    folders = []
    for number, (facing_deg, tilt_deg, spin_deg) in enumerate(VIRTUAL_PLACEMENTS):
        orbit = VirtualOrbit()
        camera = TargetCamera(rig, target, target_pose_facing(facing_deg, tilt_deg, spin_deg, target), orbit,
                              seed + number)
        plan = Plan(views, tuple(entry.elevation_deg for entry in rig.elevations),
                    facing_deg - VIRTUAL_TARGET_SPAN_DEG / 2, 0.0, VIRTUAL_TARGET_SPAN_DEG)
        folder = CaptureFolder.create(Path(out) / f"placement{number}", camera.describe(), plan.to_json(),
                                      {"target": target.to_json(), "placement": number})
        folders.append(capture(orbit, camera, FixedPhantom(), plan, folder, progress))
    return folders
