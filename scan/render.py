"""The virtual camera: pictures of a triangle mesh, or of the calibration target, as the scanner's webcam would
take them (headless, on the CPU: numpy and numba, no GPU).

Each pixel is ``supersample`` x ``supersample`` samples. Every sample's ray goes through the lens model
(:class:`~phantom.scan.camera.Camera`, Brown-Conrady distortion) once per camera (:func:`sample_rays`); the mesh is
drawn into a z-buffer in the ideal image plane (:func:`~phantom.scan.kernels.rasterize`), so its edges
come out bent by the lens as in a real picture. A drawn sample is shaded by Lambert's law with the mesh's
normals interpolated across each triangle, under a lamp fixed to the camera's arm (up and to the left of the
lens) and an ambient light, in the phantom's colour; the rest is a plain backdrop of one colour (a green
cloth). The samples of a pixel are averaged (the edge's antialiasing a lens and sensor give). What a real rig
has in view is a :class:`Look`'s: the tubes the phantom hangs by and their holder (:func:`hung_scene`), a white
highlight on the glossy silicone (Blinn-Phong), a cloth whose brightness varies across the frame and in folds,
the lens's vignetting. Then sensor noise is added (read noise and shot noise, in linear light) and the result is
encoded as 8-bit sRGB, as a webcam delivers it.

The calibration target (:class:`CharucoTarget`, a ChArUco board printed on a flat plate) is drawn the same way
by casting each sample's ray onto its plane and reading its printed pattern.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Any

import numpy as np

from phantom import require_extra
from phantom.model.arrays import FloatArray, IntArray
from phantom.model.mesh.surface import TriangleMesh, vertex_normals
from phantom.scan import kernels
from phantom.scan.camera import Camera, Pose

#: Samples per pixel along each axis.
SUPERSAMPLE = 3


@dataclass(frozen=True)
class Look:
    """Colours (linear RGB, 0..1), light and noise of the virtual pictures, and what a real rig has in view: the
    tubes the phantom hangs by (``tubes``, up to a holder out of view), its silicone's gloss (the white
    highlight's strength, ``gloss``), the cloth's unevenness (``cloth``: 1 the real rig's folds and fall-off
    across the frame, 0 an even backdrop), the lens's vignetting (the corners' darkening) and the sensor's noise.
    :data:`IDEAL_LOOK` (the default: an even backdrop, a matt phantom floating in view) and :data:`REAL_LOOK`."""

    backdrop_rgb: tuple[float, float, float] = (0.05, 0.32, 0.09)
    phantom_rgb: tuple[float, float, float] = (0.78, 0.46, 0.40)
    ambient: float = 0.22
    lamp: float = 0.85
    #: Direction from the scene towards the lamp, in the camera's frame (x right, y down, z forward).
    lamp_direction: tuple[float, float, float] = (-0.35, -0.45, -1.0)
    read_noise: float = 0.004
    shot_noise_gain: float = 0.0004
    tubes: bool = False
    gloss: float = 0.0
    cloth: float = 0.0
    vignetting: float = 0.0
    tube_rgb: tuple[float, float, float] = (0.82, 0.82, 0.80)
    holder_rgb: tuple[float, float, float] = (0.04, 0.04, 0.05)
    #: The highlight's exponent (Blinn-Phong): a small sharp highlight, as wet-looking silicone has.
    shininess: float = 60.0

    @property
    def noise(self) -> bool:
        return self.read_noise > 0 or self.shot_noise_gain > 0


IDEAL_LOOK = Look()
REAL_LOOK = Look(tubes=True, gloss=0.6, cloth=1.0, vignetting=0.3)
DEFAULT_LOOK = IDEAL_LOOK
LOOKS = {"ideal": IDEAL_LOOK, "real": REAL_LOOK}

#: The tubes (three of 4.4 mm, the chambers' lines) where they leave the gland's base (mm, x and y from the base's
#: middle), and the holder's underside above the base (mm), out of every picture.
TUBE_RADIUS_MM = 2.2
TUBES_XY_MM = ((-3.4, -1.3), (3.4, -1.3), (0.0, 1.7))
HOLDER_ABOVE_MM = 100.0


def _cylinder(centre_xy: tuple[float, float], radius_mm: float, bottom_mm: float, top_mm: float,
              segments: int = 32) -> TriangleMesh:
    """An open vertical cylinder (no ends), outward."""
    angles = np.linspace(0.0, 2 * np.pi, segments, endpoint=False)
    ring = np.column_stack([centre_xy[0] + radius_mm * np.cos(angles), centre_xy[1] + radius_mm * np.sin(angles)])
    vertices = np.vstack([np.column_stack([ring, np.full(segments, bottom_mm)]),
                          np.column_stack([ring, np.full(segments, top_mm)])])
    k = np.arange(segments)
    k1 = (k + 1) % segments
    triangles = np.vstack([np.column_stack([k, k1, segments + k1]), np.column_stack([k, segments + k1, segments + k])])
    return TriangleMesh(vertices, triangles.astype(np.int64))


def _slab(centre_mm: FloatArray, half_mm: tuple[float, float, float]) -> TriangleMesh:
    """A box, outward."""
    corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], float)
    faces = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1], [2, 3, 7], [2, 7, 6],
                      [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]], np.int64)
    return TriangleMesh(centre_mm + corners * np.array(half_mm), faces)


def hung_scene(gland: TriangleMesh) -> tuple[TriangleMesh, FloatArray, IntArray]:
    """The gland with what hangs it (mm, the phantom's frame, z up): three tubes from just inside its base (its
    top) up to a holder :data:`HOLDER_ABOVE_MM` above; the whole as one mesh, its vertex normals (each part's
    own) and each triangle's material (0 gland, 1 tube, 2 holder)."""
    top = float(gland.vertices_mm[:, 2].max())
    base = gland.vertices_mm[gland.vertices_mm[:, 2] > top - 0.5]
    middle = 0.5 * (base.min(axis=0) + base.max(axis=0))
    parts = [(gland, 0)] + [(_cylinder((middle[0] + x, middle[1] + y), TUBE_RADIUS_MM, top - 1.0,
                                       top + HOLDER_ABOVE_MM + 1.0), 1) for x, y in TUBES_XY_MM]
    parts.append((_slab(np.array([middle[0], middle[1], top + HOLDER_ABOVE_MM + 5.0]), (40.0, 40.0, 5.0)), 2))
    vertices, triangles, normals, material, offset = [], [], [], [], 0
    for part, kind in parts:
        vertices.append(part.vertices_mm)
        triangles.append(part.triangles + offset)
        normals.append(vertex_normals(part.vertices_mm, part.triangles))
        material.append(np.full(len(part.triangles), kind, np.int64))
        offset += len(part.vertices_mm)
    return (TriangleMesh(np.vstack(vertices), np.vstack(triangles)), np.vstack(normals),
            np.concatenate(material))


@functools.lru_cache(maxsize=2)
def sample_rays(camera: Camera, supersample: int = SUPERSAMPLE) -> np.ndarray:
    """The ideal normalized coordinates of every sample's ray (height * s, width * s, 2), float32; computed
    once per camera and process."""
    rays = np.empty((camera.height * supersample, camera.width * supersample, 2), np.float64)
    worst = kernels.sample_rays(camera.fx, camera.fy, camera.cx, camera.cy,
                                       np.array(camera.distortion, float), supersample, rays)
    if not worst < 1e-9:
        raise ValueError(f"the lens's distortion cannot be inverted over the image (residual {worst:.2g}): its "
                         f"coefficients fold the image")
    return rays.astype(np.float32)


class Renderer:
    """Pictures through one camera (its sample rays are made once)."""

    def __init__(self, camera: Camera, supersample: int = SUPERSAMPLE, look: Look = DEFAULT_LOOK):
        self.camera = camera
        self.supersample = supersample
        self.look = look
        self.rays = sample_rays(camera, supersample)

    def mesh_samples(self, mesh: TriangleMesh, pose: Pose) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Rasterize a mesh (mm, world): per sample the depth (mm, +inf on the backdrop), the triangle (-1 on the
        backdrop) and the barycentric weights of its vertices 1 and 2."""
        depth = np.full(self.rays.shape[:2], np.inf, np.float32)
        face = np.full(self.rays.shape[:2], -1, np.int32)
        weights = np.zeros(self.rays.shape[:2] + (2,), np.float32)
        camera = self.camera
        vertices = np.ascontiguousarray(pose.apply(mesh.vertices_mm))
        kernels.rasterize(vertices, np.ascontiguousarray(mesh.triangles, dtype=np.int64), camera.fx, camera.fy,
                          camera.cx, camera.cy, np.array(camera.distortion, float), self.supersample, self.rays,
                          depth, face, weights)
        return depth, face, weights

    def render_mesh(self, mesh: TriangleMesh, pose: Pose, normals: FloatArray | None = None,
                    material: IntArray | None = None) -> np.ndarray:
        """A picture of a mesh (mm, world) in linear RGB (height, width, 3), float32, without noise; ``material``
        each triangle's (0 phantom, 1 tube, 2 holder; default all phantom)."""
        _, face, weights = self.mesh_samples(mesh, pose)
        normals = vertex_normals(mesh.vertices_mm, mesh.triangles) if normals is None else normals
        material = np.zeros(len(mesh.triangles), np.int64) if material is None else material
        look = self.look
        image = np.empty((self.camera.height, self.camera.width, 3), np.float32)
        albedo = np.array([look.phantom_rgb, look.tube_rgb, look.holder_rgb])
        gloss = np.array([look.gloss, look.gloss, 0.0])
        kernels.shade_pixels(face, weights, np.ascontiguousarray(mesh.triangles, dtype=np.int64),
                             np.ascontiguousarray(normals @ pose.rotation.T), self._lamp(), look.ambient, look.lamp,
                             albedo, np.ascontiguousarray(material, dtype=np.int64), gloss, look.shininess, self.rays,
                             np.array(look.backdrop_rgb), self._backdrop_level, self.supersample, image)
        if look.vignetting > 0:
            image *= self._vignette[:, :, None]
        return image

    @functools.cached_property
    def _backdrop_level(self) -> np.ndarray:
        """The cloth's brightness at each pixel (1 on average): the cloth hangs on the orbit's arm behind the
        phantom, so its pattern is fixed in the camera's frame; lit from one side it falls off across the frame
        and darkens up it, and it hangs in folds."""
        camera = self.camera
        x = (np.arange(camera.width, dtype=np.float32)[None, :] - camera.cx) / camera.fx
        y = (np.arange(camera.height, dtype=np.float32)[:, None] - camera.cy) / camera.fy
        pattern = (0.15 * np.tanh(2.5 * x) - 0.1 * 2.5 * y + 0.08 * np.sin(2 * np.pi * x / 0.11 + np.sin(7.0 * y))
                   + 0.04 * np.sin(2 * np.pi * (x + 0.3 * y) / 0.04))
        level: np.ndarray = (1.0 + self.look.cloth * pattern).astype(np.float32)
        return level

    @functools.cached_property
    def _vignette(self) -> np.ndarray:
        """The lens's fall-off: 1 in the middle, 1 - vignetting in the corners (quadratic in the radius)."""
        camera = self.camera
        x = np.arange(camera.width, dtype=np.float32)[None, :] - camera.cx
        y = np.arange(camera.height, dtype=np.float32)[:, None] - camera.cy
        corner = float(np.hypot(max(camera.cx, camera.width - camera.cx), max(camera.cy, camera.height - camera.cy)))
        vignette: np.ndarray = (1.0 - self.look.vignetting * (x * x + y * y) / corner ** 2).astype(np.float32)
        return vignette

    def _lamp(self) -> FloatArray:
        lamp: FloatArray = np.array(self.look.lamp_direction) / np.linalg.norm(self.look.lamp_direction)
        return lamp

    def render_target(self, target: CharucoTarget, target_pose: Pose, pose: Pose) -> np.ndarray:
        """A picture of the calibration target placed at ``target_pose`` (the map from the target's frame, mm,
        into the world) in linear RGB, float32, without noise."""
        depth = np.full(self.rays.shape[:2], np.inf, np.float32)
        value = np.zeros(depth.shape, np.float32)
        rotation = pose.rotation @ target_pose.rotation
        origin = pose.apply(target_pose.translation_mm[None, :])[0]
        kernels.cast_plane(self.rays, np.ascontiguousarray(origin), np.ascontiguousarray(rotation[:, 0]),
                           np.ascontiguousarray(rotation[:, 1]), target.texture, target.pixels_per_mm, depth, value)
        # a matt print lit by the same lamp: its brightness follows the plate's tilt to the lamp
        normal = -rotation[:, 2] if rotation[2, 2] > 0 else rotation[:, 2]
        light = self.look.ambient + self.look.lamp * max(float(normal @ self._lamp()), 0.0)
        image = np.empty((self.camera.height, self.camera.width, 3), np.float32)
        kernels.plane_pixels(depth, value, light, np.array(self.look.backdrop_rgb), self.supersample, image)
        return image


#: Linear light in ENCODE_LEVELS steps to 8-bit sRGB codes (a table: the power law once, not per pixel).
ENCODE_LEVELS = 1 << 16
_levels = np.linspace(0.0, 1.0, ENCODE_LEVELS)
ENCODE_TABLE = np.round(255.0 * np.where(_levels <= 0.0031308, 12.92 * _levels,
                                         1.055 * np.power(_levels, 1 / 2.4) - 0.055)).astype(np.uint8)


def to_8bit(linear: np.ndarray, rng: np.random.Generator | None, look: Look = DEFAULT_LOOK) -> np.ndarray:
    """A linear picture with sensor noise (Gaussian read noise and shot noise; none without ``rng``), encoded as
    8-bit sRGB (height, width, 3), RGB order."""
    values = np.asarray(linear, np.float32)
    if rng is not None:
        sigma = np.sqrt(look.read_noise ** 2 + look.shot_noise_gain * np.clip(values, 0.0, None))
        values = values + sigma * rng.standard_normal(values.shape, dtype=np.float32)
    return ENCODE_TABLE[np.asarray(np.clip(values, 0.0, 1.0) * (ENCODE_LEVELS - 1) + 0.5, np.int32)]


# --- the calibration target --------------------------------------------------------------------------------------

#: The default target: a ChArUco board of 9 x 6 squares of 15 mm (markers of 11 mm, dictionary 4x4_50) on a
#: 135 x 90 mm plate, which the virtual camera sees whole from 200 mm.
CHARUCO_SQUARES = (9, 6)
CHARUCO_SQUARE_MM = 15.0
CHARUCO_MARKER_MM = 11.0
CHARUCO_DICTIONARY = "DICT_4X4_50"


@dataclass(frozen=True)
class CharucoTarget:
    """A ChArUco board (OpenCV's layout): ``squares`` (columns, rows), the square's and the marker's side (mm), the
    ArUco dictionary's name. Its frame: origin at the board's top-left corner, x along a row, y down the columns,
    z into the board (OpenCV's board frame)."""

    squares: tuple[int, int] = CHARUCO_SQUARES
    square_mm: float = CHARUCO_SQUARE_MM
    marker_mm: float = CHARUCO_MARKER_MM
    dictionary: str = CHARUCO_DICTIONARY
    pixels_per_mm: float = 12.0

    @property
    def size_mm(self) -> tuple[float, float]:
        return self.squares[0] * self.square_mm, self.squares[1] * self.square_mm

    def board(self) -> Any:
        """OpenCV's CharucoBoard."""
        with require_extra("scan"):
            import cv2
        dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary))
        return cv2.aruco.CharucoBoard(self.squares, self.square_mm, self.marker_mm, dictionary)

    @functools.cached_property
    def texture(self) -> np.ndarray:
        """The printed pattern (rows along y, columns along x) as reflectance 0.04..0.85 (ink, paper), float64,
        ``pixels_per_mm`` across each millimetre."""
        width_mm, height_mm = self.size_mm
        size = (round(width_mm * self.pixels_per_mm), round(height_mm * self.pixels_per_mm))
        printed = self.board().generateImage(size, marginSize=0, borderBits=1)
        return np.ascontiguousarray(0.04 + 0.81 * (printed.astype(np.float64) / 255.0))

    def to_json(self) -> dict[str, Any]:
        return {"kind": "charuco", "squares": list(self.squares), "square_mm": self.square_mm,
                "marker_mm": self.marker_mm, "dictionary": self.dictionary}

    @classmethod
    def from_json(cls, data: dict[str, Any]) -> CharucoTarget:
        columns, rows = (int(value) for value in data["squares"])
        return cls((columns, rows), float(data["square_mm"]), float(data["marker_mm"]), str(data["dictionary"]))
