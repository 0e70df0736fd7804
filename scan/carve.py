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

The views' agreement (:func:`view_agreement`): the hull's surface projected into each picture must cover its
silhouette, each silhouette having carved the hull; a picture that moved against the others (the camera or the
turntable bumped while it was taken) has a silhouette that sticks out of the hull the others carve, and cuts off
a slab of it that the other pictures then miss, so every silhouette is left partly uncovered, and the moved one
bounds much more of the hull's surface than any other. What runs out of the pictures (the tubes the phantom hangs
by, out of the top edge) is cut where the first picture ends, and so not counted.
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
#: A silhouette's pixel is compared with the hull when it is more than this (px) inside the silhouette's edge: the
#: edge is placed to a fraction of a pixel, the hull a fraction of a voxel from it.
AGREEMENT_EDGE_PX = 1.0
#: The orbit's axis is sampled every this (mm) for the stretch of it every picture sees ...
AXIS_STEP_MM = 0.25
#: ... and a line of sight that passes it within this (mm) of that stretch's ends is not counted either: the tubes
#: stand a few mm off the axis, so a slanted line of sight through one passes the axis a little above or below it
#: (up to 3 mm measured at 30 deg).
AXIS_MARGIN_MM = 5.0
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
        #: each of :attr:`views`' place among the views given
        self.order = order
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

        self.projections += self._shared(len(points), run)
        return out

    def surface_in_views(self, points_mm: FloatArray) -> tuple[np.ndarray, IntArray]:
        """Points on the hull's surface (n, 3; mm) in the views: each view's pixels one of them projects to (uint8
        1, laid out as :attr:`distances`) and each point's bounding view (its index in :attr:`views`: the one whose
        silhouette's edge is nearest the point; -1 where none sees it)."""
        points = np.ascontiguousarray(points_mm, dtype=np.float64)
        covered = np.zeros(len(self.distances), np.uint8)
        bounding = np.empty(len(points), np.int64)
        camera = self.camera
        distortion = np.array(camera.distortion, float)

        def run(part: slice) -> int:
            # the threads' parts may mark the same pixel: each only ever sets it to 1
            kernels.hull_in_views(points[part], self.rotations, self.translations, camera.fx, camera.fy, camera.cx,
                                  camera.cy, distortion, self.max_radius2, self.distances, self.offsets, self.crops,
                                  self.truncation_px, covered, bounding[part])
            return 0

        self._shared(len(points), run)
        return covered, bounding

    def _shared(self, count: int, run: Callable[[slice], int]) -> int:
        """``run`` over ``count`` points shared by the carver's threads (the sum of what it returns)."""
        # interleaved slices share the work evenly (the hull's points cost more than the empty space's)
        parts = [slice(k, None, self.threads) for k in range(self.threads)] if count > 10000 else [slice(None)]
        if len(parts) == 1:
            return run(parts[0])
        with concurrent.futures.ThreadPoolExecutor(len(parts)) as pool:
            return sum(pool.map(run, parts))


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


@dataclass(frozen=True)
class ViewAgreement:
    """How each view's silhouette (in the order the views were given) agrees with a carved hull: ``uncovered``, the
    share of the silhouette (its pixels more than :data:`AGREEMENT_EDGE_PX` inside the edge) onto which no point of
    the hull projects, lines of sight that pass the orbit's axis beyond what every picture sees of it (less
    :data:`AXIS_MARGIN_MM`) not counted; ``bounding``, the share of the hull's surface where that view's
    silhouette is the one that bounds it."""

    uncovered: FloatArray
    bounding: FloatArray


def view_agreement(grid: Grid, carver: Carver, axis_point_mm: FloatArray, axis_direction: FloatArray
                   ) -> ViewAgreement:
    """The agreement of ``carver``'s views with the hull on ``grid`` (see the module docstring), the orbit's axis
    through ``axis_point_mm`` along ``axis_direction`` (unit): the grid points within half a voxel of the hull's
    surface projected into every picture (where the hull's surface is, to a fraction of a voxel), each
    silhouette's pixel counted covered within a voxel's image of one."""
    with require_extra("scan"):
        import cv2

    spacing = grid.spacing_mm
    points = np.ascontiguousarray(grid.origin_mm + np.argwhere(np.abs(grid.values) < 0.5 * spacing) * spacing)
    camera = carver.camera
    covered, bounding = carver.surface_in_views(points)
    middle = grid.origin_mm + 0.5 * spacing * (np.array(grid.values.shape) - 1)
    axis = np.asarray(axis_direction, float)
    low_mm, high_mm = axis_seen_mm(carver, np.asarray(axis_point_mm, float), axis, float(
        np.max([np.linalg.norm(view.pose.centre_mm - middle) for view in carver.views])))
    focal = 0.5 * (camera.fx + camera.fy)
    uncovered = np.zeros(len(carver.views))
    for number, view in enumerate(carver.views):
        x0, y0, width, height = view.silhouette.crop
        offset = int(carver.offsets[number])
        hit = covered[offset:offset + width * height].reshape(height, width)
        # the surface's points are a voxel apart: what lies within a voxel's image of one is covered
        reach_px = max(1.0, spacing * focal / float(view.pose.apply(middle[None])[0, 2])) + 0.5
        inner = view.silhouette.signed_distance_px < -AGREEMENT_EDGE_PX
        missed = inner & (cv2.distanceTransform(1 - hit, cv2.DIST_L2, 3) > reach_px)
        rows, columns = np.nonzero(missed)
        if len(rows):
            rays = camera.normalized_rays(np.column_stack([columns + x0, rows + y0]).astype(float))
            directions = np.column_stack([rays, np.ones(len(rays))]) @ view.pose.rotation
            along_mm = _passing_axis_mm(view.pose.centre_mm, directions, np.asarray(axis_point_mm, float), axis)
            rows = rows[(along_mm >= low_mm + AXIS_MARGIN_MM) & (along_mm <= high_mm - AXIS_MARGIN_MM)]
        uncovered[number] = len(rows) / max(int(np.count_nonzero(inner)), 1)
    by_view = np.bincount(bounding[bounding >= 0], minlength=len(carver.views)) / max(len(points), 1)
    # back to the order the views were given in
    given_uncovered, given_bounding = np.empty(len(carver.views)), np.empty(len(carver.views))
    given_uncovered[carver.order], given_bounding[carver.order] = uncovered, by_view
    return ViewAgreement(given_uncovered, given_bounding)


def axis_seen_mm(carver: Carver, axis_point_mm: FloatArray, axis_direction: FloatArray, reach_mm: float
                 ) -> tuple[float, float]:
    """The stretch of the orbit's axis (mm along ``axis_direction`` from ``axis_point_mm``, within ``reach_mm``)
    that every picture sees; all of it (-inf, inf) where no picture sees any (nothing is discounted)."""
    along = np.arange(-reach_mm, reach_mm + AXIS_STEP_MM, AXIS_STEP_MM)
    points = axis_point_mm + along[:, None] * axis_direction
    camera = carver.camera
    seen = np.ones(len(points), bool)
    for view in carver.views:
        local = view.pose.apply(points)
        ahead = local[:, 2] > kernels.NEAR_MM
        normalized = local[:, :2] / np.where(ahead, local[:, 2], 1.0)[:, None]
        ahead &= np.sum(normalized ** 2, axis=1) <= carver.max_radius2
        pixels = camera.project(np.where(ahead[:, None], local, [0.0, 0.0, 1.0]))
        seen &= ahead & np.all((pixels >= 0.0) & (pixels <= [camera.width - 1.0, camera.height - 1.0]), axis=1)
    if not np.any(seen):
        return -math.inf, math.inf
    return float(along[seen].min()), float(along[seen].max())


def _passing_axis_mm(origin_mm: FloatArray, directions: FloatArray, axis_point_mm: FloatArray,
                     axis_direction: FloatArray) -> FloatArray:
    """Where (mm along the axis) each line of sight from ``origin_mm`` along ``directions`` (n, 3) passes nearest
    the axis."""
    offset = origin_mm - axis_point_mm
    square = np.sum(directions ** 2, axis=1)
    slant = directions @ axis_direction
    across = directions @ offset
    height = float(axis_direction @ offset)
    along: FloatArray = (square * height - slant * across) / np.maximum(square - slant ** 2, 1e-12)
    return along


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
