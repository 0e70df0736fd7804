"""Calibration of the scanner from pictures of a ChArUco target: the camera's intrinsics and distortion, the orbit's
axis and radius, and the camera's pose at each elevation.

The target (:class:`~phantom.scan.render.CharucoTarget`, printed flat) stands where the phantom hangs, and the
capture loop takes pictures of it as the orbit turns (``phantom scan capture --target``), at every elevation the
rig will scan at; each capture folder is one placement of the target. A second placement (the target turned to
face the other side, or tilted) constrains the lens better. Then:

1. The target's corners are found in each picture (OpenCV's ``CharucoDetector``); a picture with fewer than
   :data:`MIN_CORNERS` is left out.
2. OpenCV's ``calibrateCamera`` gives the intrinsics, the distortion (k1, k2, p1, p2, k3) and each picture's
   pose of the target.
3. The orbit, from those poses: the camera's centres in a placement's target frame lie on a circle about the
   axis; a plane and a circle fitted to them give the axis's direction and a point on it, the orbit angles
   the direction's sign. The world frame is the orbit's: z along the axis (a positive orbit angle turns the
   camera right-handed about it), x towards the camera of the first elevation at orbit 0, the origin on the axis
   at that camera's height.
4. One least-squares fit of everything (a bundle adjustment: intrinsics, the camera's pose at orbit 0 at each
   elevation, each placement's pose of the target) to the corners' pixel positions, with every picture's pose
   bound to the rig's model (``Rig.pose``: the orbit angle the board reported, turned about the axis). Its RMS
   reprojection error, and each picture's, say how well the rig follows the model.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from phantom import PhantomError, require_extra
from phantom.model.arrays import FloatArray
from phantom.scan.camera import Camera, Elevation, Pose, Rig, axis_rotation
from phantom.scan.render import CharucoTarget

#: A picture with fewer target corners found is left out.
MIN_CORNERS = 12
#: Pictures of one placement at one elevation needed to fit the orbit's circle.
MIN_ORBIT_VIEWS = 3


class CalibrationError(PhantomError):
    """The pictures do not allow a calibration (too few corners or views, an orbit that does not turn)."""


@dataclass(frozen=True)
class TargetView:
    """One picture of the target: its placement, the axes' angles (deg) and the corners found (target frame mm,
    pixels)."""

    placement: int
    orbit_deg: float
    elevation_deg: float
    object_mm: FloatArray
    pixels: FloatArray
    name: str = ""


def detect(image: np.ndarray, target: CharucoTarget) -> tuple[FloatArray, FloatArray]:
    """The target's inner corners found in an 8-bit RGB picture: their positions on the target (n, 3) mm and in
    the picture (n, 2) px (refined to a fraction of a pixel by OpenCV); empty arrays when none."""
    with require_extra("scan"):
        import cv2

    board = target.board()
    grey = cv2.cvtColor(np.ascontiguousarray(image), cv2.COLOR_RGB2GRAY)
    corners, ids, _, _ = cv2.aruco.CharucoDetector(board).detectBoard(grey)
    if ids is None or len(ids) == 0:
        return np.zeros((0, 3)), np.zeros((0, 2))
    object_mm = np.asarray(board.getChessboardCorners(), float)[np.asarray(ids).ravel()]
    return object_mm, np.asarray(corners, float).reshape(-1, 2)


# --- geometry helpers ---------------------------------------------------------------------------------------------


def rotation_vector(rotation: FloatArray) -> FloatArray:
    """The axis-angle vector of a rotation matrix (rad)."""
    angle = math.acos(min(1.0, max(-1.0, (np.trace(rotation) - 1.0) / 2.0)))
    if angle < 1e-12:
        return np.zeros(3)
    if angle > math.pi - 1e-6:
        # near a half turn: the axis from the symmetric part
        values, vectors = np.linalg.eigh((rotation + rotation.T) / 2.0)
        axis = vectors[:, np.argmax(values)]
        return np.asarray(axis * angle, float)
    axis = np.array([rotation[2, 1] - rotation[1, 2], rotation[0, 2] - rotation[2, 0],
                     rotation[1, 0] - rotation[0, 1]]) / (2.0 * math.sin(angle))
    return np.asarray(axis * angle, float)


def rotation_matrix(vector: FloatArray) -> FloatArray:
    """The rotation matrix of an axis-angle vector (rad)."""
    angle = float(np.linalg.norm(vector))
    if angle < 1e-15:
        return np.eye(3)
    return axis_rotation(np.asarray(vector) / angle, math.degrees(angle))


def mean_rotation(rotations: Sequence[FloatArray]) -> FloatArray:
    """The rotation nearest to the mean of rotation matrices (SVD projection)."""
    u, _, vt = np.linalg.svd(np.sum(rotations, axis=0))
    nearest: FloatArray = u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt
    return nearest


def fit_orbit(centres: FloatArray, angles_deg: FloatArray) -> tuple[FloatArray, FloatArray, float]:
    """The axis (a point, the unit direction) and radius of a circle through camera centres (n, 3) taken at orbit
    angles (deg): a plane through them (its normal the direction, signed so that increasing angles turn
    right-handed about it), a circle in that plane (algebraic fit)."""
    mean = centres.mean(axis=0)
    _, _, vt = np.linalg.svd(centres - mean)
    normal, in_u, in_v = vt[2], vt[0], vt[1]
    u, v = (centres - mean) @ in_u, (centres - mean) @ in_v
    system = np.column_stack([u, v, np.ones_like(u)])
    a, b, c = np.linalg.lstsq(system, u * u + v * v, rcond=None)[0]
    cu, cv = a / 2.0, b / 2.0
    radius = math.sqrt(c + cu * cu + cv * cv)
    point = mean + cu * in_u + cv * in_v
    # the sense: the turn from the first to the last centre, against the angles' change
    first, last = np.argmin(angles_deg), np.argmax(angles_deg)
    turn = np.cross(centres[first] - point, centres[last] - point) @ normal
    if turn * (angles_deg[last] - angles_deg[first]) < 0:
        normal = -normal
    return point, normal, radius


def _compose(outer: Pose, inner: Pose) -> Pose:
    """The map ``outer(inner(x))``."""
    return Pose(outer.rotation @ inner.rotation, outer.rotation @ inner.translation_mm + outer.translation_mm)


def _inverse(pose: Pose) -> Pose:
    return Pose(pose.rotation.T, -pose.rotation.T @ pose.translation_mm)


# --- the fit ------------------------------------------------------------------------------------------------------


@dataclass
class _Layout:
    """Where each unknown sits in the parameter vector of the bundle adjustment."""

    elevations: list[float]
    placements: int

    @property
    def size(self) -> int:
        return 9 + 4 + 6 * (len(self.elevations) - 1) + 6 * self.placements

    def unpack(self, x: FloatArray, width: int, height: int) -> tuple[Camera, list[Pose], list[Pose]]:
        fx, fy, cx, cy, k1, k2, p1, p2, k3 = x[:9]
        camera = Camera(width, height, fx, fy, cx, cy, (k1, k2, p1, p2, k3))
        rotation = rotation_matrix(x[9:12])
        bases = [Pose(rotation, -rotation @ np.array([x[12], 0.0, 0.0]))]
        at = 13
        for _ in self.elevations[1:]:
            rotation = rotation_matrix(x[at:at + 3])
            bases.append(Pose(rotation, -rotation @ x[at + 3:at + 6]))
            at += 6
        targets = []
        for _ in range(self.placements):
            targets.append(Pose(rotation_matrix(x[at:at + 3]), x[at + 3:at + 6].copy()))
            at += 6
        return camera, bases, targets


def _project(camera: Camera, pose: Pose, points_mm: FloatArray) -> FloatArray:
    return camera.project(pose.apply(points_mm))


def calibrate_rig(views: Sequence[TargetView], width: int, height: int, fit_k3: bool = False) -> Rig:
    """The rig (see the module docstring) from the target's pictures; CalibrationError when they do not allow it.

    ``k3`` (the sixth-order radial term) stays 0 unless ``fit_k3``: a webcam's lens needs two terms, and the third
    trades off against k2 where the target does not reach the picture's corners."""
    with require_extra("scan"):
        import cv2
        from scipy.optimize import least_squares

    used = [view for view in views if len(view.object_mm) >= MIN_CORNERS]
    if len(used) < 6:
        raise CalibrationError(f"the target was found in {len(used)} of {len(views)} pictures (at least "
                               f"{MIN_CORNERS} corners each); at least 6 are needed: light it evenly, keep it whole "
                               f"and sharp in the pictures, and turn the orbit less far from it")
    elevations = sorted({round(view.elevation_deg, 3) for view in used})
    placements = sorted({view.placement for view in used})
    if placements != list(range(len(placements))):
        raise CalibrationError(f"placements must be numbered 0, 1, ... (got {placements})")
    # 1. OpenCV's calibration: the lens, and each picture's pose of the target
    rms, matrix, distortion, rvecs, tvecs = cv2.calibrateCamera(
        [view.object_mm.astype(np.float32) for view in used], [view.pixels.astype(np.float32) for view in used],
        (width, height), None, None, flags=0 if fit_k3 else cv2.CALIB_FIX_K3)
    k1, k2, p1, p2, k3 = (float(value) for value in (list(np.ravel(distortion)) + [0.0] * 5)[:5])
    camera = Camera(width, height, matrix[0, 0], matrix[1, 1], matrix[0, 2], matrix[1, 2], (k1, k2, p1, p2, k3))
    seen = [Pose(rotation_matrix(np.ravel(r)), np.ravel(t).astype(float)) for r, t in zip(rvecs, tvecs, strict=True)]
    # 2. the orbit in the first placement's target frame, from its first elevation's pictures
    first = [k for k, view in enumerate(used) if view.placement == 0 and _same(view.elevation_deg, elevations[0])]
    if len(first) < MIN_ORBIT_VIEWS:
        raise CalibrationError(f"the first placement has {len(first)} usable pictures at elevation "
                               f"{elevations[0]:g} deg; the orbit's axis needs at least {MIN_ORBIT_VIEWS} at "
                               f"different orbit angles")
    angles = np.array([used[k].orbit_deg for k in first])
    if np.ptp(angles) < 10.0:
        raise CalibrationError(f"the pictures of the first placement span {np.ptp(angles):.1f} deg of the orbit: "
                               f"turn it at least 10 deg (30 or more is better) to find its axis")
    centres = np.array([_inverse(seen[k]).translation_mm for k in first])
    point, direction, _ = fit_orbit(centres, angles)
    # the world: z the axis, x towards the first elevation's camera at orbit 0, origin at that camera's height
    at_zero = np.mean([axis_rotation(direction, -used[k].orbit_deg) @ (centres[n] - point)
                       for n, k in enumerate(first)], axis=0)
    height_on_axis = float(at_zero @ direction)
    origin = point + height_on_axis * direction
    x_axis = at_zero - height_on_axis * direction
    x_axis /= np.linalg.norm(x_axis)
    world_from_target = Pose(np.vstack([x_axis, np.cross(direction, x_axis), direction]),
                             -np.vstack([x_axis, np.cross(direction, x_axis), direction]) @ origin)
    # target poses in the world per placement, base poses per elevation (each from the pictures that give it)
    target_in_world: dict[int, Pose] = {0: world_from_target}
    bases: dict[float, Pose] = {}
    for _ in range(len(placements) + len(elevations)):
        for k, view in enumerate(used):
            key = _key(elevations, view.elevation_deg)
            turn = axis_rotation(np.array([0.0, 0.0, 1.0]), view.orbit_deg)
            if view.placement in target_in_world and key not in bases:
                camera_from_world = _compose(seen[k], _inverse(target_in_world[view.placement]))
                bases[key] = Pose(camera_from_world.rotation @ turn, camera_from_world.translation_mm)
            elif key in bases and view.placement not in target_in_world:
                base = bases[key]
                camera_from_world = Pose(base.rotation @ turn.T, base.translation_mm)
                target_in_world[view.placement] = _compose(_inverse(camera_from_world), seen[k])
    missing = [e for e in elevations if e not in bases] + [p for p in placements if p not in target_in_world]
    if missing:
        raise CalibrationError("every placement must share an elevation with another, through the first: "
                               f"{missing} cannot be placed")
    # 3. the bundle adjustment
    layout = _Layout(elevations, len(placements))
    x0 = np.zeros(layout.size)
    x0[:9] = [camera.fx, camera.fy, camera.cx, camera.cy, k1, k2, p1, p2, k3]
    base0 = bases[elevations[0]]
    x0[9:12] = rotation_vector(base0.rotation)
    x0[12] = float(np.linalg.norm(base0.centre_mm[:2]))
    at = 13
    for elevation in elevations[1:]:
        x0[at:at + 3] = rotation_vector(bases[elevation].rotation)
        x0[at + 3:at + 6] = bases[elevation].centre_mm
        at += 6
    for placement in placements:
        x0[at:at + 3] = rotation_vector(target_in_world[placement].rotation)
        x0[at + 3:at + 6] = target_in_world[placement].translation_mm
        at += 6
    index = [(_key(elevations, view.elevation_deg), view.placement) for view in used]

    free = np.ones(layout.size, bool)
    free[8] = fit_k3

    def residuals(free_x: FloatArray) -> FloatArray:
        x = x0.copy()
        x[free] = free_x
        lens, base_poses, targets = layout.unpack(x, width, height)
        parts = []
        for view, (elevation, placement) in zip(used, index, strict=True):
            rig = Rig(lens, np.zeros(3), np.array([0.0, 0.0, 1.0]),
                      (Elevation(elevation, base_poses[elevations.index(elevation)]),))
            pose = _compose(rig.pose(view.orbit_deg, elevation), targets[placement])
            parts.append((_project(lens, pose, view.object_mm) - view.pixels).ravel())
        return np.concatenate(parts)

    solution = least_squares(residuals, x0[free], method="lm", x_scale="jac")
    x = x0.copy()
    x[free] = solution.x
    lens, base_poses, _ = layout.unpack(x, width, height)
    errors = solution.fun.reshape(-1, 2)
    per_view, at = [], 0
    for view in used:
        count = len(view.object_mm)
        per_view.append(float(np.sqrt(np.mean(np.sum(errors[at:at + count] ** 2, axis=1)))))
        at += count
    report: dict[str, Any] = {
        "pictures": len(views), "pictures_used": len(used), "placements": len(placements),
        "corners": int(sum(len(view.object_mm) for view in used)),
        "opencv_rms_px": float(rms),
        "rms_px": float(np.sqrt(np.mean(np.sum(errors ** 2, axis=1)))),
        "worst_picture_rms_px": max(per_view),
        "worst_picture": used[int(np.argmax(per_view))].name,
        "left_out": [view.name for view in views if len(view.object_mm) < MIN_CORNERS],
    }
    return Rig(lens, np.zeros(3), np.array([0.0, 0.0, 1.0]),
               tuple(Elevation(e, pose) for e, pose in zip(elevations, base_poses, strict=True)), report)


def _same(a: float, b: float) -> bool:
    return abs(a - b) <= 0.05


def _key(elevations: Sequence[float], elevation_deg: float) -> float:
    return next(e for e in elevations if _same(e, elevation_deg))


def target_views(folders: Sequence[Any], target: CharucoTarget | None = None) -> list[TargetView]:
    """The target's corners in every picture of capture folders (:class:`~phantom.scan.capture.CaptureFolder`),
    folder n being placement n; the target is the one the first folder's conditions name, else the default."""
    if not folders:
        raise CalibrationError("no capture folders of the target given")
    if target is None:
        described = folders[0].conditions.get("target")
        target = CharucoTarget.from_json(described) if isinstance(described, dict) else CharucoTarget()
    views = []
    for placement, folder in enumerate(folders):
        for frame in folder.frames:
            object_mm, pixels = detect(folder.image(frame), target)
            views.append(TargetView(placement, frame.orbit_deg, frame.elevation_deg, object_mm, pixels,
                                    f"{folder.path.name}/{frame.image}"))
    return views
