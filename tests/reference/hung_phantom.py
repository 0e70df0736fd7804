"""Pictures of a phantom hung by its tubes, made by a ray caster that shares no code with the scanner's renderer.

The scanner's virtual camera (``phantom.scan.render`` and its numba kernels) rasterises triangle meshes; were the
reconstruction tested only on its pictures, a fault common to the two (the lens model's inverse, the pixel's
centre, the edge's antialiasing) would pass unseen. This oracle casts one ray per sample through the lens with
OpenCV's own undistortion (``cv2.undistortPoints``, iterated to 1e-12), reads the poses from rig.json's numbers
with its own algebra, and intersects analytic shapes whose volume is a closed form:

- the gland: an ellipsoid cut flat at its top (the base the tubes enter), glossy pink silicone (Lambert plus a
  Blinn-Phong highlight of the lamp, white);
- the tubes: vertical cylinders from the gland's base up to a holder far above the picture, glossy white;
- the holder: a dark plate (80 x 80 mm) above, out of the pictures;
- the backdrop: a green cloth on the orbit's arm behind the phantom, its brightness varying across the frame and
  in vertical folds;
- the lens's vignetting, then read and shot noise, and 8-bit sRGB.

Each of gloss, cloth, vignetting, noise and tubes can be turned off (the ideal case). Numpy and OpenCV only.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np


@dataclass(frozen=True)
class HungPhantom:
    """The scene, in the rig's world (mm): the gland an ellipsoid of ``semi_axes_mm`` about ``centre_mm`` cut at
    ``centre z + top_mm``; ``tubes_xy_mm`` the tubes' axes (offsets from the centre, vertical), ``tube_radius_mm``
    their radius; the holder's underside at ``holder_z_mm``."""

    semi_axes_mm: tuple[float, float, float] = (21.0, 15.0, 20.0)
    centre_mm: tuple[float, float, float] = (0.4, -0.3, -1.0)
    top_mm: float = 18.5
    tubes_xy_mm: tuple[tuple[float, float], ...] = ((-3.6, -1.6), (3.6, -1.6), (0.0, 2.6))
    tube_radius_mm: float = 2.2
    holder_z_mm: float = 120.0
    gland_rgb: tuple[float, float, float] = (0.70, 0.40, 0.35)
    tube_rgb: tuple[float, float, float] = (0.80, 0.80, 0.77)
    holder_rgb: tuple[float, float, float] = (0.05, 0.05, 0.06)
    cloth_rgb: tuple[float, float, float] = (0.06, 0.30, 0.10)
    tubes: bool = True
    gloss: bool = True
    cloth: bool = True
    vignetting: bool = True
    noise: bool = True

    def gland_volume_ml(self) -> float:
        """The cut ellipsoid's volume (closed form): pi a b (h + c - (h^3 + c^3) / (3 c^2)), h the cut's height."""
        a, b, c = self.semi_axes_mm
        h = self.top_mm
        return math.pi * a * b * ((h + c) - (h ** 3 + c ** 3) / (3 * c * c)) / 1e3


@dataclass
class RigGeometry:
    """rig.json's numbers: the camera matrix and distortion, the axis, each pass's pose at orbit 0."""

    width: int
    height: int
    matrix: np.ndarray
    distortion: np.ndarray
    axis_point: np.ndarray
    axis_direction: np.ndarray
    passes: dict[float, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)

    @classmethod
    def read(cls, data: dict[str, Any]) -> RigGeometry:
        camera = data["camera"]
        matrix = np.array([[camera["fx"], 0.0, camera["cx"]], [0.0, camera["fy"], camera["cy"]], [0.0, 0.0, 1.0]])
        direction = np.array(data["axis"]["direction"], float)
        passes = {float(entry["elevation_deg"]): (np.array(entry["rotation"], float),
                                                  np.array(entry["translation_mm"], float))
                  for entry in data["elevations"]}
        distortion = np.array(camera["distortion_k1_k2_p1_p2_k3"], float)
        return cls(int(camera["width"]), int(camera["height"]), matrix, distortion,
                   np.array(data["axis"]["point_mm"], float), direction / np.linalg.norm(direction), passes)

    def pose(self, orbit_deg: float, elevation_deg: float) -> tuple[np.ndarray, np.ndarray]:
        """World to camera (R, t) at an orbit angle: the camera at orbit 0 carried about the axis by the angle
        (OpenCV's Rodrigues for the turn)."""
        rotation0, translation0 = self.passes[float(elevation_deg)]
        turn, _ = cv2.Rodrigues(math.radians(orbit_deg) * self.axis_direction)
        centre0 = -rotation0.T @ translation0
        centre = self.axis_point + turn @ (centre0 - self.axis_point)
        rotation = rotation0 @ turn.T
        return rotation, -rotation @ centre


#: Rays along each side of a pixel an edge crosses.
EDGE_SAMPLES = 8


class HungPhantomCamera:
    """Pictures of a :class:`HungPhantom` through a rig (its rig.json as a dict), ``supersample`` squared rays a
    pixel, :data:`EDGE_SAMPLES` squared where they do not all meet the same thing."""

    def __init__(self, rig_json: dict[str, Any], scene: HungPhantom, supersample: int = 2, seed: int = 0):
        self.rig = RigGeometry.read(rig_json)
        self.scene = scene
        self.supersample = supersample
        self.rng = np.random.default_rng(seed)
        s, w, h = supersample, self.rig.width, self.rig.height
        offsets = (np.arange(s) + 0.5) / s - 0.5
        u = (np.arange(w)[None, :, None, None] + offsets[None, None, None, :]).repeat(h, 0).repeat(s, 2)
        v = (np.arange(h)[:, None, None, None] + offsets[None, None, :, None]).repeat(w, 1).repeat(s, 3)
        pixels = np.stack([u.ravel(), v.ravel()], axis=1).astype(np.float64)
        self.criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)
        normalized = cv2.undistortPoints(pixels[:, None, :], self.rig.matrix, self.rig.distortion, None, None, None,
                                         self.criteria)[:, 0, :]
        self.rays_camera = np.column_stack([normalized, np.ones(len(normalized))])  # (h, w, s, s) order
        corner = np.hypot(w / 2, h / 2)
        self.vignette = 1.0 - 0.3 * ((np.hypot(np.arange(w)[None, :] - w / 2, np.arange(h)[:, None] - h / 2)
                                      / corner) ** 2)

    def picture(self, orbit_deg: float, elevation_deg: float) -> np.ndarray:
        """An 8-bit sRGB picture (height, width, 3), RGB."""
        rotation, translation = self.rig.pose(orbit_deg, elevation_deg)
        origin = -rotation.T @ translation
        s, w, h = self.supersample, self.rig.width, self.rig.height
        colour = self._cloth(self.rays_camera).reshape(h, w, s, s, 3)
        # only the rays within the scene's projected box can meet it (the rest see the cloth)
        x0, y0, x1, y1 = self._box_px(rotation, translation)
        if x1 > x0 and y1 > y0:
            rays = self.rays_camera.reshape(h, w, s, s, 3)[y0:y1, x0:x1].reshape(-1, 3)
            directions = rays @ rotation
            directions /= np.linalg.norm(directions, axis=1, keepdims=True)
            shaded, material = self._shade(origin, directions, rotation, rays)
            colour[y0:y1, x0:x1] = shaded.reshape(y1 - y0, x1 - x0, s, s, 3)
            material = material.reshape(y1 - y0, x1 - x0, s * s)
            mixed = np.argwhere(np.any(material != material[:, :, :1], axis=2)) + (y0, x0)
        else:
            mixed = np.zeros((0, 2), int)
        linear = colour.mean(axis=(2, 3))
        if len(mixed):
            linear[mixed[:, 0], mixed[:, 1]] = self._edge_pixels(mixed, origin, rotation)
        if self.scene.vignetting:
            linear = linear * self.vignette[:, :, None]
        if self.scene.noise:
            sigma = np.sqrt(0.005 ** 2 + 0.0005 * np.clip(linear, 0.0, None))
            linear = linear + sigma * self.rng.standard_normal(linear.shape)
        linear = np.clip(linear, 0.0, 1.0)
        encoded = np.where(linear <= 0.0031308, 12.92 * linear, 1.055 * linear ** (1 / 2.4) - 0.055)
        return np.round(255.0 * encoded).astype(np.uint8)

    def _edge_pixels(self, pixels_yx: np.ndarray, origin: np.ndarray, rotation: np.ndarray) -> np.ndarray:
        """The pixels an edge crosses, again with EDGE_SAMPLES squared rays each: a sensor's pixel integrates the
        light over its area, and a coarse sampling's steps of coverage (a quarter pixel with 2 x 2 rays) carved
        from many views trim the hull by their worst."""
        n = EDGE_SAMPLES
        offsets = (np.arange(n) + 0.5) / n - 0.5
        du, dv = np.meshgrid(offsets, offsets)
        points = np.stack([pixels_yx[:, None, 1] + du.ravel()[None, :], pixels_yx[:, None, 0] + dv.ravel()[None, :]],
                          axis=2).reshape(-1, 2)
        normalized = cv2.undistortPoints(points[:, None, :].astype(np.float64), self.rig.matrix, self.rig.distortion,
                                         None, None, None, self.criteria)[:, 0, :]
        rays = np.column_stack([normalized, np.ones(len(normalized))])
        directions = rays @ rotation
        directions /= np.linalg.norm(directions, axis=1, keepdims=True)
        colour, _ = self._shade(origin, directions, rotation, rays)
        averaged: np.ndarray = colour.reshape(len(pixels_yx), n * n, 3).mean(axis=1)
        return averaged

    def _box_px(self, rotation: np.ndarray, translation: np.ndarray) -> tuple[int, int, int, int]:
        """The pixel box (x0, y0, x1, y1) holding the projection of the scene's bounding box (the gland, the tubes
        up to the holder, cut where it would pass behind the camera), a few pixels wide of it."""
        scene = self.scene
        centre, axes = np.array(scene.centre_mm), np.array(scene.semi_axes_mm)
        top = scene.holder_z_mm + 10.0 if scene.tubes else centre[2] + scene.top_mm
        corners = np.array([[x, y, z] for x in (centre[0] - axes[0], centre[0] + axes[0])
                            for y in (centre[1] - axes[1], centre[1] + axes[1])
                            for z in np.linspace(centre[2] - axes[2], top, 40)])
        camera = corners @ rotation.T + translation
        camera = camera[camera[:, 2] > 1.0]
        pixels, _ = cv2.projectPoints(camera, np.zeros(3), np.zeros(3), self.rig.matrix, self.rig.distortion)
        pixels = pixels[:, 0, :]
        # far outside the picture the lens model folds: clamp those to the picture's side they lie on
        x0 = int(np.clip(np.floor(pixels[:, 0].min()) - 4, 0, self.rig.width))
        x1 = int(np.clip(np.ceil(pixels[:, 0].max()) + 5, 0, self.rig.width))
        y0 = int(np.clip(np.floor(pixels[:, 1].min()) - 4, 0, self.rig.height))
        y1 = int(np.clip(np.ceil(pixels[:, 1].max()) + 5, 0, self.rig.height))
        if scene.tubes:
            y0 = 0
        return x0, y0, x1, y1

    def _cloth(self, rays_camera: np.ndarray) -> np.ndarray:
        """The cloth on the arm behind the phantom, 180 mm past the axis, its pattern fixed in the camera's frame:
        brighter to one side, darker up the frame, in folds."""
        depth = 380.0
        x = rays_camera[:, 0] / rays_camera[:, 2] * depth
        y = rays_camera[:, 1] / rays_camera[:, 2] * depth
        brightness = np.ones(len(x))
        if self.scene.cloth:
            brightness = (1.0 + 0.18 * np.tanh(x / 150.0) - 0.12 * (y / 150.0)
                          + 0.10 * np.sin(2 * math.pi * x / 37.0 + 0.9 * np.sin(2 * math.pi * y / 97.0))
                          + 0.05 * np.sin(2 * math.pi * (x + 0.4 * y) / 13.0))
        cloth: np.ndarray = brightness[:, None] * np.array(self.scene.cloth_rgb)
        return cloth

    def _shade(self, origin: np.ndarray, directions: np.ndarray, rotation: np.ndarray,
               rays_camera: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        scene = self.scene
        count = len(directions)
        nearest = np.full(count, np.inf)
        normal = np.zeros((count, 3))
        material = np.zeros(count, np.int8)  # 0 cloth, 1 gland, 2 tube, 3 holder
        # the gland: an ellipsoid cut by the plane z = top
        centre = np.array(scene.centre_mm)
        axes = np.array(scene.semi_axes_mm)
        top = centre[2] + scene.top_mm
        o = (origin - centre) / axes
        d = directions / axes
        a = np.sum(d * d, axis=1)
        b = 2.0 * d @ o
        c = float(o @ o) - 1.0
        disc = b * b - 4 * a * c
        hit = disc > 0
        root = np.sqrt(np.where(hit, disc, 0.0))
        t0, t1 = (-b - root) / (2 * a), (-b + root) / (2 * a)
        z0 = origin[2] + t0 * directions[:, 2]
        side = hit & (t0 > 0) & (z0 <= top)
        with np.errstate(divide="ignore", invalid="ignore"):
            tp = (top - origin[2]) / directions[:, 2]
        cap = hit & ~side & (z0 > top) & (tp >= t0) & (tp <= t1) & (tp > 0)
        for mask, t in ((side, t0), (cap, tp)):
            closer = mask & (t < nearest)
            nearest[closer] = t[closer]
            material[closer] = 1
        points = origin + nearest[side, None] * directions[side]
        gradient = (points - centre) / axes ** 2
        normal[side] = gradient / np.linalg.norm(gradient, axis=1, keepdims=True)
        normal[cap & (tp <= nearest)] = (0.0, 0.0, 1.0)
        # the tubes: vertical cylinders from the gland's base to the holder
        if scene.tubes:
            dxy = directions[:, :2]
            a2 = np.sum(dxy * dxy, axis=1)
            for tube in scene.tubes_xy_mm:
                q = origin[:2] - (centre[:2] + np.array(tube))
                b2 = 2.0 * dxy @ q
                c2 = float(q @ q) - scene.tube_radius_mm ** 2
                disc2 = b2 * b2 - 4 * a2 * c2
                ok = disc2 > 0
                t = (-b2 - np.sqrt(np.where(ok, disc2, 0.0))) / (2 * np.maximum(a2, 1e-12))
                z = origin[2] + t * directions[:, 2]
                closer = ok & (t > 0) & (z >= top) & (z <= scene.holder_z_mm) & (t < nearest)
                nearest[closer] = t[closer]
                material[closer] = 2
                radial = (origin[:2] + t[closer, None] * dxy[closer]) - (centre[:2] + np.array(tube))
                normal[closer] = np.column_stack([radial / scene.tube_radius_mm, np.zeros(len(radial))])
        # the holder: a slab above, facing down
        with np.errstate(divide="ignore", invalid="ignore"):
            th = (scene.holder_z_mm - origin[2]) / directions[:, 2]
        plate = origin[:2] + np.where(np.isfinite(th), th, 0.0)[:, None] * directions[:, :2] - centre[:2]
        under = (th > 0) & (th < nearest) & (directions[:, 2] > 0) & np.all(np.abs(plate) <= 40.0, axis=1)
        nearest[under] = th[under]
        material[under] = 3
        normal[under] = (0.0, 0.0, -1.0)
        # light: a lamp on the camera's arm (up and left of the lens), ambient light
        lamp = rotation.T @ np.array([-0.35, -0.45, -1.0])
        lamp /= np.linalg.norm(lamp)
        diffuse = 0.22 + 0.85 * np.clip(normal @ lamp, 0.0, None)
        colour = np.zeros((count, 3))
        for index, rgb in ((1, scene.gland_rgb), (2, scene.tube_rgb), (3, scene.holder_rgb)):
            mask = material == index
            colour[mask] = diffuse[mask, None] * np.array(rgb)
        if scene.gloss:
            halfway = lamp - directions
            halfway /= np.linalg.norm(halfway, axis=1, keepdims=True)
            glossy = (material == 1) | (material == 2)
            highlight = 0.9 * np.clip(np.sum(normal[glossy] * halfway[glossy], axis=1), 0.0, None) ** 80
            colour[glossy] += highlight[:, None]
        cloth = material == 0
        colour[cloth] = self._cloth(rays_camera[cloth])
        return colour, material


def write_capture(out: Path, rig_json: dict[str, Any], scene: HungPhantom, views: int, elevations_deg: list[float],
                  supersample: int = 2, seed: int = 0) -> Path:
    """A capture folder (capture.json, rig.json, images/NNNN.png) of ``views`` stops a turn at each elevation,
    written with OpenCV and json alone."""
    images = out / "images"
    images.mkdir(parents=True, exist_ok=True)
    camera = HungPhantomCamera(rig_json, scene, supersample, seed)
    frames = []
    for elevation in elevations_deg:
        for stop in range(views):
            orbit = -180.0 + 360.0 * stop / views
            name = f"images/{len(frames):04d}.png"
            cv2.imwrite(str(out / name), cv2.cvtColor(camera.picture(orbit, elevation), cv2.COLOR_RGB2BGR))
            frames.append({"index": len(frames), "image": name, "orbit_deg": orbit, "elevation_deg": elevation,
                           "pressures_kpa": None, "time_utc": "2026-01-01T00:00:00Z", "time_s": 0.0})
    (out / "rig.json").write_text(json.dumps(rig_json, indent=1))
    capture = {"format": "phantom-capture/1", "status": "complete", "reason": None,
               "started_utc": "2026-01-01T00:00:00Z", "finished_utc": "2026-01-01T00:00:00Z",
               "camera": {"kind": "reference ray caster"}, "plan": {"views": views, "elevations_deg": elevations_deg},
               "conditions": {}, "rig": "rig.json", "frames": frames}
    (out / "capture.json").write_text(json.dumps(capture, indent=1))
    return out
