"""The virtual camera: pictures of a triangle mesh, or of the calibration target, as the scanner's webcam would
take them (headless, on the CPU: numpy and numba, no GPU).

Each pixel is ``supersample`` x ``supersample`` samples. Every sample's ray goes through the lens model
(:class:`~phantom.scan.camera.Camera`, Brown-Conrady distortion) once per camera (:func:`sample_rays`); the mesh is
drawn into a z-buffer in the ideal image plane (:func:`~phantom.scan.kernels.rasterize`), so its edges
come out bent by the lens as in a real picture. A drawn sample is shaded by Lambert's law with the mesh's
normals interpolated across each triangle, under a lamp fixed to the camera's arm (up and to the left of the
lens) and an ambient light, in the phantom's colour; the rest is a plain backdrop of one colour (a green
cloth). The samples of a pixel are averaged (the edge's antialiasing a lens and sensor give), then sensor noise
is added (read noise and shot noise, in linear light) and the result is encoded as 8-bit sRGB, as a webcam
delivers it.

The calibration target (:class:`CharucoTarget`, a ChArUco board printed on a flat plate) is drawn the same way
by casting each sample's ray onto its plane and reading its printed pattern.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Any

import numpy as np

from phantom import require_extra
from phantom.model.arrays import FloatArray
from phantom.model.mesh.surface import TriangleMesh, vertex_normals
from phantom.scan import kernels
from phantom.scan.camera import Camera, Pose

#: Samples per pixel along each axis.
SUPERSAMPLE = 3


@dataclass(frozen=True)
class Look:
    """Colours (linear RGB, 0..1), light and noise of the virtual pictures."""

    backdrop_rgb: tuple[float, float, float] = (0.05, 0.32, 0.09)
    phantom_rgb: tuple[float, float, float] = (0.78, 0.46, 0.40)
    ambient: float = 0.22
    lamp: float = 0.85
    #: Direction from the scene towards the lamp, in the camera's frame (x right, y down, z forward).
    lamp_direction: tuple[float, float, float] = (-0.35, -0.45, -1.0)
    read_noise: float = 0.004
    shot_noise_gain: float = 0.0004


DEFAULT_LOOK = Look()


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

    def render_mesh(self, mesh: TriangleMesh, pose: Pose, normals: FloatArray | None = None) -> np.ndarray:
        """A picture of a mesh (mm, world) in linear RGB (height, width, 3), float32, without noise."""
        _, face, weights = self.mesh_samples(mesh, pose)
        normals = vertex_normals(mesh.vertices_mm, mesh.triangles) if normals is None else normals
        look = self.look
        image = np.empty((self.camera.height, self.camera.width, 3), np.float32)
        kernels.shade_pixels(face, weights, np.ascontiguousarray(mesh.triangles, dtype=np.int64),
                             np.ascontiguousarray(normals @ pose.rotation.T), self._lamp(), look.ambient, look.lamp,
                             np.array(look.phantom_rgb), np.array(look.backdrop_rgb), self.supersample, image)
        return image

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


def srgb_to_linear(image: np.ndarray) -> np.ndarray:
    """8-bit sRGB to linear light, float32 (a table of the 256 values)."""
    codes = np.arange(256) / 255.0
    table = np.where(codes <= 0.04045, codes / 12.92, ((codes + 0.055) / 1.055) ** 2.4).astype(np.float32)
    linear: np.ndarray = table[image]
    return linear


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
