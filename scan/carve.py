"""Space carving: the visual hull of the silhouettes on a voxel grid, coarse to fine, and its smooth surface.

The field at a point x is ``F(x) = max over views of d_v(pi_v(x)) z_v(x) / f``: the silhouette's signed
distance (px, + outside) at the point's projection in each picture, turned into millimetres at the point's depth
(``z / f``). F is negative exactly inside every silhouette's cone, i.e. inside the visual hull; near the hull's
surface it is close to the distance from it (never more), so its zero level, found by marching cubes between
grid points (scikit-image), lies a fraction of a voxel from the hull. A point that projects outside a picture, or
behind the camera, is outside: the phantom must be whole in every picture.

Coarse to fine: a coarse grid over a cube around the orbit's centre first; each finer level (half the spacing)
covers the box of the previous level's inside and band, and computes F only where the previous level found
the surface near (|F| < 2 h); elsewhere the coarse value stands, whose sign is right. Each point stops at the
first view that puts it further outside than the band, so most of the empty space costs one or two views.
"""

from __future__ import annotations

import concurrent.futures
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, cast

import numpy as np

from phantom import PhantomError, memory_budget_bytes, require_extra
from phantom.model.arrays import FloatArray, IntArray
from phantom.model.mesh.surface import TriangleMesh, compact, enclosed_volume_ml, triangle_areas_mm2
from phantom.scan import kernels
from phantom.scan.camera import Camera, Pose
from phantom.scan.compare import drop_degenerate, largest_component, merge_coincident_vertices
from phantom.scan.silhouette import Silhouette

#: Points across the coarsest grid's cube (at least).
COARSE_POINTS = 32
#: A finer level computes F where the coarser one had |F| below this many of its spacings.
BAND_SPACINGS = 2.0
#: Bytes a level holds per point of its box while it is carved (each point's index and its parent's, int64 x 3
#: each, the parent's value, the mask, the value and the points computed): the estimate checked before a level
#: is allocated.
BYTES_PER_GRID_POINT = 72


class CarveError(PhantomError):
    """Nothing left after carving: the silhouettes do not agree (wrong poses, or the phantom not in view)."""


@dataclass(frozen=True)
class View:
    """One picture for carving: where the camera was and the phantom's silhouette in it."""

    pose: Pose
    silhouette: Silhouette


@dataclass
class Grid:
    """F on a regular grid: the corner point (mm), the spacing (mm) and the values (nx, ny, nz), float32."""

    origin_mm: FloatArray
    spacing_mm: float
    values: np.ndarray

    def points(self, index: IntArray) -> FloatArray:
        """Positions (mm) of grid indices (n, 3)."""
        points: FloatArray = self.origin_mm + index * self.spacing_mm
        return points


def spread_order(count: int) -> IntArray:
    """An order of views in which each next one is far from those before (bit-reversed indices), so that a point
    outside the hull meets a view that rejects it early."""
    bits = max(1, math.ceil(math.log2(max(count, 2))))
    keys = [int(f"{index:0{bits}b}"[::-1], 2) for index in range(count)]
    return np.argsort(keys).astype(np.int64)


class Carver:
    """F for a set of views through one camera."""

    def __init__(self, camera: Camera, views: Sequence[View], threads: int = 1):
        if not views:
            raise CarveError("no pictures to carve with")
        intrinsics = np.array([camera.fx, camera.fy, camera.cx, camera.cy, *camera.distortion])
        if not (np.all(np.isfinite(intrinsics)) and camera.fx > 0 and camera.fy > 0):
            raise CarveError(f"the camera's intrinsics (fx, fy, cx, cy, distortion) {intrinsics.tolist()} are not "
                             f"finite with positive focal lengths: calibrate the rig again")
        order = spread_order(len(views))
        self.views = [views[index] for index in order]
        self.camera = camera
        self.rotations = np.ascontiguousarray([view.pose.rotation for view in self.views], dtype=np.float64)
        self.translations = np.ascontiguousarray([view.pose.translation_mm for view in self.views], dtype=np.float64)
        sizes = [view.silhouette.signed_distance_px.size for view in self.views]
        self.offsets = np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(np.int64)
        self.distances = np.concatenate([view.silhouette.signed_distance_px.ravel() for view in self.views])
        self.crops = np.array([view.silhouette.crop for view in self.views], dtype=np.int64)
        self.truncation_px = float(min(view.silhouette.truncation_px for view in self.views))
        corners = np.array([[0.0, 0.0], [camera.width - 1.0, 0.0], [0.0, camera.height - 1.0],
                            [camera.width - 1.0, camera.height - 1.0]])
        self.max_radius2 = 1.1 * float(np.max(np.sum(camera.normalized_rays(corners) ** 2, axis=1)))
        self.projections = 0
        self.threads = max(1, threads)

    def field(self, points_mm: FloatArray, stop_mm: float) -> np.ndarray:
        """F (mm) at points (n, 3), exact up to ``stop_mm`` (a point further outside gets some value above)."""
        points = np.ascontiguousarray(points_mm, dtype=np.float64)
        out = np.empty(len(points), np.float32)
        camera = self.camera
        distortion = np.array(camera.distortion, float)

        def run(part: slice) -> int:
            return int(kernels.hull_distance(points[part], self.rotations, self.translations, camera.fx, camera.fy,
                                             camera.cx, camera.cy, distortion, self.max_radius2, self.distances,
                                             self.offsets, self.crops, self.truncation_px, float(stop_mm), out[part]))

        # interleaved slices share the work evenly (the hull's points cost more than the empty space's)
        parts = [slice(k, None, self.threads) for k in range(self.threads)] if len(points) > 10000 else [slice(None)]
        if len(parts) == 1:
            self.projections += run(parts[0])
        else:
            with concurrent.futures.ThreadPoolExecutor(len(parts)) as pool:
                self.projections += sum(pool.map(run, parts))
        return out


def _grid_points(origin: FloatArray, spacing: float, shape: tuple[int, int, int]) -> FloatArray:
    axes = [origin[k] + spacing * np.arange(shape[k]) for k in range(3)]
    mesh = np.meshgrid(*axes, indexing="ij")
    points: FloatArray = np.stack([axis.ravel() for axis in mesh], axis=1)
    return points


def carve(carver: Carver, centre_mm: FloatArray, half_size_mm: float, voxel_mm: float,
          progress: Callable[[str], None] | None = None, max_bytes: int | None = None) -> Grid:
    """F on a grid of spacing ``voxel_mm`` around the hull, carved coarse to fine from a cube of half side
    ``half_size_mm`` about ``centre_mm`` (see the module docstring). CarveError, before the finer levels are
    allocated, when the finest one's box would need more than ``max_bytes`` (default: what the machine has to
    spare, :func:`phantom.memory_budget_bytes`)."""
    budget = memory_budget_bytes() if max_bytes is None else max_bytes
    levels = max(0, math.ceil(math.log2(2.0 * half_size_mm / (COARSE_POINTS * voxel_mm))))
    spacing = voxel_mm * 2 ** levels
    count = int(math.ceil(2.0 * half_size_mm / spacing)) + 1
    origin = np.asarray(centre_mm, float) - 0.5 * spacing * (count - 1)
    shape = (count, count, count)
    values = carver.field(_grid_points(origin, spacing, shape), BAND_SPACINGS * spacing).reshape(shape)
    for level in range(levels, -1, -1):
        if progress is not None:
            progress(f"carving at {spacing:.3g} mm: {np.count_nonzero(values < 0)} of {values.size} points inside")
        if level == 0:
            break
        near = values < BAND_SPACINGS * spacing
        if not np.any(values < 0):
            raise CarveError("no point is inside every silhouette: the poses do not match the pictures (wrong "
                             "rig calibration, or the phantom moved), or the phantom is not in view")
        index = np.argwhere(near)
        low, high = index.min(axis=0) - 1, index.max(axis=0) + 1
        low, high = np.maximum(low, 0), np.minimum(high, np.array(values.shape) - 1)
        finest = np.prod((high - low) * spacing / voxel_mm + 1.0)
        if finest * BYTES_PER_GRID_POINT > budget:
            box_mm = " x ".join(f"{side:.0f}" for side in (high - low) * spacing)
            needed_gib = finest * BYTES_PER_GRID_POINT / 2**30
            raise CarveError(f"carving the hull's box ({box_mm} mm) at {voxel_mm:g} mm needs about {needed_gib:.1f} "
                             f"GiB, more than the {budget / 2**30:.1f} GiB this machine has to spare: give a "
                             f"coarser voxel (--voxel-mm)")
        fine_origin = origin + low * spacing
        fine_shape = tuple(int(2 * (h - lo) + 1) for lo, h in zip(low, high, strict=True))
        fine_spacing = spacing / 2.0
        # each fine point's nearest coarse point (ties to the lower one) gives its value and whether to compute it
        fine_index = np.indices(fine_shape).reshape(3, -1).T
        parent = low + fine_index // 2
        parent_values = values[parent[:, 0], parent[:, 1], parent[:, 2]]
        compute = np.abs(parent_values) < BAND_SPACINGS * spacing
        fine = parent_values.astype(np.float32)
        fine[compute] = carver.field(fine_origin + fine_index[compute] * fine_spacing, BAND_SPACINGS * fine_spacing)
        origin, spacing, values = fine_origin, fine_spacing, fine.reshape(fine_shape)
    return Grid(origin, spacing, values)


def surface(grid: Grid) -> TriangleMesh:
    """The zero level of F as a closed triangle surface (mm), outward: marching cubes (scikit-image) on the grid
    padded with outside values, the largest connected piece kept."""
    with require_extra("scan"):
        from skimage.measure import marching_cubes

    pad = float(max(np.max(grid.values), grid.spacing_mm))
    padded = np.pad(grid.values, 1, constant_values=pad)
    if not np.any(padded < 0):
        raise CarveError("nothing is inside every silhouette: the poses do not match the pictures")
    # scikit-image's function is not annotated
    vertices, faces, _, _ = cast(Any, marching_cubes)(padded, level=0.0, spacing=(grid.spacing_mm,) * 3)
    vertices = vertices + grid.origin_mm - grid.spacing_mm
    # where the zero level passes through a grid point, marching cubes puts several vertices on it: merged, the
    # triangles between them collapse and are dropped (a zero-length edge breaks closest-point queries)
    vertices, faces = merge_coincident_vertices(np.asarray(vertices, np.float64), np.asarray(faces, np.int64))
    faces = faces[drop_degenerate(faces, triangle_areas_mm2(vertices, faces))]
    mesh = largest_piece(TriangleMesh(vertices, faces))
    if enclosed_volume_ml(mesh) < 0:
        mesh = TriangleMesh(mesh.vertices_mm, mesh.triangles[:, ::-1].copy())
    return mesh


def largest_piece(mesh: TriangleMesh) -> TriangleMesh:
    """The connected piece with the largest area (a speck carved apart from the phantom is dropped)."""
    keep, _ = largest_component(mesh.triangles, triangle_areas_mm2(mesh.vertices_mm, mesh.triangles))
    return compact(mesh.vertices_mm, mesh.triangles[keep])
