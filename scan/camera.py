"""The scanner's camera model and the orbit's geometry, in millimetres (numpy only).

A pinhole camera with Brown-Conrady lens distortion, as OpenCV models it (``k1, k2, p1, p2, k3``): a point
``(x, y, z)`` in the camera's frame (x right, y down, z forward) goes to ``x' = x / z``, ``y' = y / z``, then
``r^2 = x'^2 + y'^2`` and

    x'' = x' (1 + k1 r^2 + k2 r^4 + k3 r^6) + 2 p1 x' y' + p2 (r^2 + 2 x'^2)
    y'' = y' (1 + k1 r^2 + k2 r^4 + k3 r^6) + p1 (r^2 + 2 y'^2) + 2 p2 x' y'
    u = fx x'' + cx,   v = fy y'' + cy

in pixels, pixel (0, 0)'s centre at (0, 0). A pose maps the world into the camera: ``x_cam = R x_world + t``.

The orbit (:class:`Rig`) turns the camera about one axis (the orbit axis, through ``axis_point_mm`` along
``axis_direction``): the camera's pose at orbit angle theta is its pose at angle 0 turned by theta about the
axis. The camera's pose at angle 0 is known for each elevation the rig was calibrated at (the elevation axis
tilts the camera between passes). A rig's calibration (``phantom scan calibrate``) writes one as ``rig.json``.
"""

from __future__ import annotations

import contextlib
import json
import math
import stat
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from phantom import PhantomError
from phantom.model.arrays import FloatArray

#: The version of rig.json's layout.
RIG_FORMAT = "phantom-rig/1"
#: Two elevations closer than this (deg) are the same pass.
ELEVATION_MATCH_DEG = 0.05


#: The largest picture side (px) a rig's camera may have: an 8K sensor. A picture of 8192x8192 RGB is 200 MB.
MAX_PICTURE_SIDE_PX = 8192
#: The smallest: a silhouette needs pixels to be a shape.
MIN_PICTURE_SIDE_PX = 16
#: A rotation read from a file is a rotation when ``R^T R`` is within this of the identity and ``det R > 0``.
ROTATION_TOLERANCE = 1e-6
#: The largest distance (mm) a rig's camera or axis may be from the world's origin: 10 m.
MAX_RIG_DISTANCE_MM = 1e4


#: The largest rig file read (a rig calibration is a few kB).
MAX_RIG_FILE_BYTES = 16 * 2**20


class RigError(PhantomError):
    """A rig file that cannot be read, or an angle the rig was not calibrated for."""


def checked_array(value: Any, shape: tuple[int, ...], name: str, error: type[PhantomError] = PhantomError,
                  limit: float = math.inf) -> FloatArray:
    """``value`` (from a JSON file) as a float array of ``shape``, every element a finite number (not a bool, not
    a string) of magnitude at most ``limit``; ``error`` naming ``name``, the value and the shape otherwise."""
    try:
        array = np.asarray(value) if isinstance(value, list | tuple | int | float) else None
    except (ValueError, OverflowError):  # ragged nesting, an integer beyond any dtype
        array = None
    if array is None or array.dtype.kind not in "iuf" or array.shape != shape:
        raise error(f"{name} must be {'a number' if not shape else f'numbers of shape {shape}'}, got {value!r:.80}")
    numbers: FloatArray = array.astype(float)
    if not np.all(np.isfinite(numbers)) or np.any(np.abs(numbers) > limit):
        raise error(f"{name} must be finite{f' and within +-{limit:g}' if limit < math.inf else ''}, got "
                    f"{value!r:.80}")
    return numbers


@dataclass(frozen=True)
class Camera:
    """Intrinsics: image size (px), focal lengths and principal point (px), distortion ``(k1, k2, p1, p2, k3)``."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    distortion: tuple[float, float, float, float, float] = (0.0, 0.0, 0.0, 0.0, 0.0)

    @property
    def matrix(self) -> FloatArray:
        """The 3x3 camera matrix K (OpenCV's cameraMatrix)."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def scaled(self, factor: float) -> Camera:
        """The same lens on a sensor read out at ``factor`` times the resolution (a 1280x960 camera at 0.5 is
        640x480): focal lengths and principal point scale (pixel centres stay pixel centres)."""
        width, height = round(self.width * factor), round(self.height * factor)
        sx, sy = width / self.width, height / self.height
        return Camera(width, height, self.fx * sx, self.fy * sy, (self.cx + 0.5) * sx - 0.5,
                      (self.cy + 0.5) * sy - 0.5, self.distortion)

    def distort(self, normalized: FloatArray) -> FloatArray:
        """Ideal normalized coordinates (..., 2) (x/z, y/z) to distorted normalized coordinates (..., 2)."""
        k1, k2, p1, p2, k3 = self.distortion
        x, y = normalized[..., 0], normalized[..., 1]
        r2 = x * x + y * y
        radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
        yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
        distorted: FloatArray = np.stack([xd, yd], axis=-1)
        return distorted

    def undistort(self, distorted: FloatArray, iterations: int = 20) -> FloatArray:
        """Distorted normalized coordinates (..., 2) to ideal ones: Newton's method on :meth:`distort` (its
        Jacobian by central differences), started from the distorted point; converges to 1e-12 within the
        image for a lens whose distortion is monotonic there."""
        target = np.asarray(distorted, dtype=float)
        guess = target.copy()
        step = 1e-7
        for _ in range(iterations):
            residual = self.distort(guess) - target
            if np.max(np.abs(residual), initial=0.0) < 1e-13:
                break
            dx = (self.distort(guess + [step, 0.0]) - self.distort(guess - [step, 0.0])) / (2 * step)
            dy = (self.distort(guess + [0.0, step]) - self.distort(guess - [0.0, step])) / (2 * step)
            a, b, c, d = dx[..., 0], dy[..., 0], dx[..., 1], dy[..., 1]
            determinant = a * d - b * c
            guess = guess - np.stack([(d * residual[..., 0] - b * residual[..., 1]) / determinant,
                                      (a * residual[..., 1] - c * residual[..., 0]) / determinant], axis=-1)
        return guess

    def project(self, points_camera_mm: FloatArray) -> FloatArray:
        """Points in the camera's frame (n, 3) to pixels (n, 2), distortion included."""
        normalized = points_camera_mm[:, :2] / points_camera_mm[:, 2:3]
        distorted = self.distort(normalized)
        pixels: FloatArray = np.column_stack([self.fx * distorted[:, 0] + self.cx,
                                              self.fy * distorted[:, 1] + self.cy])
        return pixels

    def normalized_rays(self, pixels: FloatArray) -> FloatArray:
        """Pixels (..., 2) to the ideal normalized coordinates (..., 2) of the rays through them."""
        distorted = np.stack([(pixels[..., 0] - self.cx) / self.fx, (pixels[..., 1] - self.cy) / self.fy], axis=-1)
        return self.undistort(distorted)

    def to_json(self) -> dict[str, Any]:
        return {"width": self.width, "height": self.height, "fx": self.fx, "fy": self.fy, "cx": self.cx,
                "cy": self.cy, "distortion_k1_k2_p1_p2_k3": list(self.distortion)}

    @classmethod
    def from_json(cls, data: Any) -> Camera:
        """The camera of a rig file, checked: RigError naming the field, its value and what it must be (a zero
        focal length carved a sphere of 24 ml into 55 ml; a NaN one crashed the carving)."""
        if not isinstance(data, dict):
            raise RigError(f"the rig's camera must be an object of width, height, fx, fy, cx, cy, got {data!r:.80}")
        sides = []
        for key in ("width", "height"):
            side = data.get(key)
            if isinstance(side, bool) or not isinstance(side, int) or not (
                    MIN_PICTURE_SIDE_PX <= side <= MAX_PICTURE_SIDE_PX):
                raise RigError(f"the rig's camera {key} must be a whole number of pixels from {MIN_PICTURE_SIDE_PX} "
                               f"to {MAX_PICTURE_SIDE_PX}, got {side!r}: calibrate the rig again")
            sides.append(side)
        width, height = sides
        focal = [float(checked_array(data.get(key), (), f"the rig's camera {key}", RigError)) for key in ("fx", "fy")]
        if min(focal) <= 0 or max(focal) > 100 * max(width, height):
            raise RigError(f"the rig's camera focal lengths (fx, fy) = {focal} px must be positive and under 100 "
                           f"times the picture's size: calibrate the rig again")
        cx, cy = (float(checked_array(data.get(key), (), f"the rig's camera {key}", RigError, 2.0 * side))
                  for key, side in (("cx", width), ("cy", height)))
        k1, k2, p1, p2, k3 = checked_array(data.get("distortion_k1_k2_p1_p2_k3"), (5,),
                                           "the rig's camera distortion_k1_k2_p1_p2_k3", RigError, 1e3).tolist()
        return cls(width, height, focal[0], focal[1], cx, cy, (k1, k2, p1, p2, k3))


@dataclass(frozen=True)
class Pose:
    """A rigid map from the world into the camera's frame: ``x_cam = rotation @ x_world + translation_mm``."""

    rotation: FloatArray
    translation_mm: FloatArray

    @property
    def centre_mm(self) -> FloatArray:
        """The camera's centre in the world (mm)."""
        centre: FloatArray = -self.rotation.T @ self.translation_mm
        return centre

    @property
    def forward(self) -> FloatArray:
        """The optical axis (the camera's +z) in the world."""
        forward: FloatArray = self.rotation[2].copy()
        return forward

    def apply(self, points_world_mm: FloatArray) -> FloatArray:
        """World points (n, 3) into the camera's frame."""
        points: FloatArray = points_world_mm @ self.rotation.T + self.translation_mm
        return points

    def matrix(self) -> FloatArray:
        """The 4x4 homogeneous matrix of the map."""
        matrix = np.eye(4)
        matrix[:3, :3], matrix[:3, 3] = self.rotation, self.translation_mm
        return matrix

    @classmethod
    def from_matrix(cls, matrix: FloatArray) -> Pose:
        return cls(np.array(matrix[:3, :3], dtype=float), np.array(matrix[:3, 3], dtype=float))

    @classmethod
    def look_at(cls, centre_mm: FloatArray, target_mm: FloatArray, up: FloatArray) -> Pose:
        """The pose of a camera at ``centre_mm`` looking at ``target_mm`` with the world's ``up`` towards the
        top of its pictures."""
        forward = np.asarray(target_mm, float) - np.asarray(centre_mm, float)
        forward /= np.linalg.norm(forward)
        right = np.cross(forward, up)
        right /= np.linalg.norm(right)
        down = np.cross(forward, right)
        rotation = np.vstack([right, down, forward])
        return cls(rotation, -rotation @ np.asarray(centre_mm, float))


def axis_rotation(direction: FloatArray, angle_deg: float) -> FloatArray:
    """The rotation by ``angle_deg`` about a unit ``direction`` (right hand), 3x3."""
    axis = np.asarray(direction, float) / np.linalg.norm(direction)
    angle = math.radians(angle_deg)
    cross = np.array([[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]], [-axis[1], axis[0], 0.0]])
    rotation: FloatArray = np.eye(3) + math.sin(angle) * cross + (1.0 - math.cos(angle)) * cross @ cross
    return rotation


@dataclass(frozen=True)
class Elevation:
    """One pass of the orbit: the elevation axis's angle (deg, as the board reports it) and the camera's pose at
    orbit angle 0 there."""

    elevation_deg: float
    pose: Pose


@dataclass(frozen=True)
class Rig:
    """The scanner: its camera, the orbit axis (a point on it and its unit direction, in the world, mm) and the
    camera's pose at orbit angle 0 at each calibrated elevation. ``calibration`` holds how it was found
    (reprojection errors, views); empty for a rig given by hand (the virtual rig's truth)."""

    camera: Camera
    axis_point_mm: FloatArray
    axis_direction: FloatArray
    elevations: tuple[Elevation, ...]
    calibration: dict[str, Any] = field(default_factory=dict)

    def elevation(self, elevation_deg: float) -> Elevation:
        """The calibrated pass at this elevation; RigError naming the calibrated ones if there is none."""
        for entry in self.elevations:
            if abs(entry.elevation_deg - elevation_deg) <= ELEVATION_MATCH_DEG:
                return entry
        known = ", ".join(f"{entry.elevation_deg:g}" for entry in self.elevations)
        raise RigError(f"the rig is calibrated at elevation(s) {known} deg, not {elevation_deg:g} deg: calibrate "
                       f"it there too (phantom scan calibrate) or capture at a calibrated elevation")

    def pose(self, orbit_deg: float, elevation_deg: float) -> Pose:
        """The camera's pose at an orbit angle and an elevation (deg): the pose at orbit 0 turned about the axis.
        A point x of the camera at orbit 0 goes to ``p + Q (x - p)`` (Q the turn, p on the axis), so the map
        ``R x + t`` becomes ``R Q^T x + t + R p - R Q^T p``."""
        base = self.elevation(elevation_deg).pose
        turn = axis_rotation(self.axis_direction, orbit_deg)
        rotation = base.rotation @ turn.T
        translation = base.translation_mm + base.rotation @ self.axis_point_mm - rotation @ self.axis_point_mm
        return Pose(rotation, translation)

    def radius_mm(self, elevation_deg: float) -> float:
        """The camera centre's distance from the orbit axis at an elevation (mm)."""
        offset = self.elevation(elevation_deg).pose.centre_mm - self.axis_point_mm
        along = float(offset @ self.axis_direction)
        return float(np.linalg.norm(offset - along * self.axis_direction))

    def to_json(self) -> dict[str, Any]:
        return {
            "format": RIG_FORMAT,
            "units": "mm, deg, px",
            "camera": self.camera.to_json(),
            "axis": {"point_mm": self.axis_point_mm.tolist(), "direction": self.axis_direction.tolist()},
            "elevations": [{"elevation_deg": entry.elevation_deg, "rotation": entry.pose.rotation.tolist(),
                            "translation_mm": entry.pose.translation_mm.tolist(),
                            "orbit_radius_mm": self.radius_mm(entry.elevation_deg)} for entry in self.elevations],
            "calibration": self.calibration,
        }

    @classmethod
    def from_json(cls, data: dict[str, Any]) -> Rig:
        if data.get("format") != RIG_FORMAT:
            raise RigError(f"not a rig file of this version (format {data.get('format')!r}, expected "
                           f"{RIG_FORMAT!r}): calibrate the rig again with phantom scan calibrate")
        entries, axis, calibration = data.get("elevations"), data.get("axis"), data.get("calibration", {})
        if not isinstance(entries, list) or not entries or not all(isinstance(entry, dict) for entry in entries):
            raise RigError(f"the rig file is damaged: elevations must be a non-empty list of passes, got "
                           f"{entries!r:.80}: calibrate again")
        if not isinstance(axis, dict) or not isinstance(calibration, dict):
            raise RigError("the rig file is damaged: axis (point_mm, direction) and calibration must be objects: "
                           "calibrate again")
        elevations = tuple(Elevation(float(checked_array(entry.get("elevation_deg"), (), "a pass's elevation_deg",
                                                         RigError, 180.0)),
                                     _checked_pose(entry.get("rotation"), entry.get("translation_mm")))
                           for entry in entries)
        direction = checked_array(axis.get("direction"), (3,), "the rig's axis direction", RigError)
        length = float(np.linalg.norm(direction))
        if not length > 1e-9:
            raise RigError(f"the rig's axis direction {direction.tolist()} has no length: calibrate again")
        point = checked_array(axis.get("point_mm"), (3,), "the rig's axis point_mm", RigError, MAX_RIG_DISTANCE_MM)
        return cls(Camera.from_json(data.get("camera")), point, direction / length, elevations, dict(calibration))

    def save(self, path: str | Path) -> Path:
        path = Path(path)
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_text(json.dumps(self.to_json(), indent=1) + "\n")
        except OSError as error:
            raise RigError(f"cannot write the rig file {path}: {error.strerror or error}") from None
        return path

    @classmethod
    def load(cls, path: str | Path) -> Rig:
        """A rig file, refused (RigError) before it is read when it is not a regular file of at most
        :data:`MAX_RIG_FILE_BYTES` (a path a client names: /dev/zero is endless)."""
        path = Path(path)
        with contextlib.suppress(OSError):  # a missing file: the read below says what to do
            info = path.stat()
            if not stat.S_ISREG(info.st_mode):
                raise RigError(f"the rig file {path} is not a regular file: give the rig.json phantom scan "
                               "calibrate wrote")
            if info.st_size > MAX_RIG_FILE_BYTES:
                raise RigError(f"the rig file {path} holds {info.st_size / 2**20:.0f} MiB, more than the "
                               f"{MAX_RIG_FILE_BYTES // 2**20} MiB a rig calibration can be: give the rig.json "
                               "phantom scan calibrate wrote")
        try:
            data = json.loads(path.read_text())
        except FileNotFoundError:
            raise RigError(f"the rig file {path} does not exist: calibrate the rig first (phantom scan calibrate) "
                           f"or give --rig") from None
        except (OSError, json.JSONDecodeError) as error:
            raise RigError(f"cannot read the rig file {path}: {error}") from None
        if not isinstance(data, dict):
            raise RigError(f"the rig file {path} is not a JSON object: calibrate again")
        return cls.from_json(data)


def _checked_pose(rotation: Any, translation_mm: Any) -> Pose:
    """A pass's pose from a rig file: a proper rotation (orthonormal, det +1) and a finite translation."""
    matrix = checked_array(rotation, (3, 3), "a pass's rotation", RigError)
    if not (np.max(np.abs(matrix.T @ matrix - np.eye(3))) <= ROTATION_TOLERANCE and np.linalg.det(matrix) > 0):
        raise RigError(f"a pass's rotation {matrix.tolist()} is not a rotation (orthonormal, determinant +1): "
                       f"calibrate again")
    return Pose(matrix, checked_array(translation_mm, (3,), "a pass's translation_mm", RigError, MAX_RIG_DISTANCE_MM))


# --- the virtual rig ---------------------------------------------------------------------------------------------

#: The virtual camera: a 1280x960 sensor behind a lens of about 49 degrees across, with a webcam's barrel
#: distortion and a principal point off the centre.
VIRTUAL_CAMERA = Camera(1280, 960, 1400.0, 1400.0, 647.3, 474.1, (-0.12, 0.09, 6e-4, -4e-4, 0.0))
#: The virtual orbit: the camera 200 mm from the axis, looking at a point 4 mm below the origin (the middle of
#: the hanging phantom); the axis is neither through the phantom's origin nor quite vertical, as a real one.
VIRTUAL_RADIUS_MM = 200.0
VIRTUAL_CENTRE_MM = np.array([0.0, 0.0, -4.0])
VIRTUAL_AXIS_POINT_MM = np.array([0.9, -0.6, 0.0])
VIRTUAL_AXIS_TILT_DEG = 0.3
#: The elevations of the virtual rig's two passes (deg): level with the phantom and 30 deg above it.
VIRTUAL_ELEVATIONS_DEG = (0.0, 30.0)


def virtual_pose(orbit_deg: float, elevation_deg: float, scale: float = 1.0) -> Pose:
    """The virtual rig's true camera pose at any orbit angle and elevation (deg)."""
    return virtual_rig(scale, (elevation_deg,)).pose(orbit_deg, elevation_deg)


def virtual_pose_at(scale: float) -> Callable[[float, float], Pose]:
    """The virtual rig's true pose at any (orbit_deg, elevation_deg), for pictures of ``scale`` times 1280x960: a
    virtual camera's ``pose_at`` where the rig is at elevations its calibration does not list."""
    return lambda orbit_deg, elevation_deg: virtual_pose(orbit_deg, elevation_deg, scale)


#: The virtual camera's picture sizes (fractions of 1280x960): below, the phantom is a few pixels; above, one
#: picture's buffers take gigabytes (scale 6 grew the daemon to 5 GB) where scale 1 already measures the volume
#: to 0.14 % (bench/README.md, "Scanner").
VIRTUAL_SCALE_RANGE = (0.05, 2.0)


def virtual_rig(scale: float = 1.0, elevations_deg: tuple[float, ...] = VIRTUAL_ELEVATIONS_DEG) -> Rig:
    """The simulated scanner's true geometry (the phantom's frame: z up, the phantom hanging from z = 20 mm):
    :data:`VIRTUAL_CAMERA` read out at ``scale`` times 1280x960, orbiting :data:`VIRTUAL_RADIUS_MM` from a
    slightly tilted axis, at each elevation of ``elevations_deg`` (the camera swung up on an arc about the
    phantom's middle). RigError for a scale outside :data:`VIRTUAL_SCALE_RANGE`."""
    low, high = VIRTUAL_SCALE_RANGE
    if isinstance(scale, bool) or not isinstance(scale, (int, float)) or not low <= scale <= high:
        raise RigError(f"the virtual camera's scale must be a number from {low:g} to {high:g} (a fraction of "
                       f"1280x960 pixels), got {scale!r}")
    tilt = math.radians(VIRTUAL_AXIS_TILT_DEG)
    direction = np.array([math.sin(tilt), 0.0, math.cos(tilt)])
    elevations = []
    for elevation_deg in elevations_deg:
        e = math.radians(elevation_deg)
        centre = VIRTUAL_CENTRE_MM + VIRTUAL_RADIUS_MM * np.array([math.cos(e), 0.0, math.sin(e)])
        elevations.append(Elevation(float(elevation_deg), Pose.look_at(centre, VIRTUAL_CENTRE_MM, direction)))
    camera = VIRTUAL_CAMERA if scale == 1.0 else VIRTUAL_CAMERA.scaled(scale)
    return Rig(camera, VIRTUAL_AXIS_POINT_MM.copy(), direction, tuple(elevations))
