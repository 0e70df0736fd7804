"""Voxel geometry: masks and closed meshes resampled onto a shape grid, and grids surfaced back into meshes.

A *shape grid* is ``G^3`` cubic voxels of side ``voxel_mm``, centred on a shape's volume centroid, its axes those
of the world frame. The world frame is NIfTI's RAS+ (x to the patient's right, y anterior, z superior), in mm.
The phantom's own frame (its model and meshes) has x to the patient's *left*, y anterior and z from apex to base
(superior): a mesh in the phantom's frame maps to RAS by ``x -> -x`` (:data:`RAS_FROM_PHANTOM`).

Occupancy is the fraction of a voxel inside the shape, estimated on ``supersample^3`` points per voxel; the
shape's surface within a label map is the 0.5 level of the mask's trilinear interpolation, so resampling a
coarse, anisotropic segmentation gives a smooth surface rather than its staircase.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from phantom import require_extra
from phantom.shape.errors import ShapeError

#: A point (mm) in the phantom's frame times this diagonal is the same point in RAS, and back.
RAS_FROM_PHANTOM = np.array([-1.0, 1.0, 1.0])
#: Sub-samples per voxel side when estimating occupancy.
SUPERSAMPLE = 3


def sample_offsets_mm(grid_size: int, voxel_mm: float, supersample: int) -> np.ndarray:
    """Positions (mm) of the sub-samples along one axis of a grid centred on 0: ``grid_size * supersample``."""
    count = grid_size * supersample
    return ((np.arange(count) + 0.5) / supersample - grid_size / 2.0) * voxel_mm


def _average_blocks(samples: np.ndarray, grid_size: int, supersample: int) -> np.ndarray:
    s = supersample
    blocks = samples.reshape(grid_size, s, grid_size, s, grid_size, s)
    averaged: np.ndarray = blocks.mean(axis=(1, 3, 5)).astype(np.float32)
    return averaged


@dataclass(frozen=True)
class LabelMask:
    """A binary mask on an image's voxel grid, with the image's affine (voxel index -> RAS mm)."""

    mask: np.ndarray
    affine: np.ndarray

    @property
    def voxel_volume_mm3(self) -> float:
        """Volume of one image voxel (mm^3)."""
        return float(abs(np.linalg.det(self.affine[:3, :3])))

    def points_mm(self) -> np.ndarray:
        """RAS positions (mm) of the centres of the mask's voxels, ``(N, 3)``."""
        index = np.argwhere(self.mask).astype(float)
        points: np.ndarray = index @ self.affine[:3, :3].T + self.affine[:3, 3]
        return points

    def volume_ml(self) -> float:
        """The mask's volume: its voxel count times the voxel volume (ml)."""
        return float(np.count_nonzero(self.mask)) * self.voxel_volume_mm3 / 1e3

    def centroid_mm(self) -> np.ndarray:
        """The centroid (RAS, mm) of the mask's voxels."""
        centroid: np.ndarray = self.points_mm().mean(axis=0)
        return centroid

    def half_extent_mm(self, centre_mm: np.ndarray) -> float:
        """The largest distance along a world axis from ``centre_mm`` to the mask's edge (mm)."""
        half_voxel = 0.5 * np.abs(self.affine[:3, :3]).sum(axis=1)
        return float((np.abs(self.points_mm() - centre_mm) + half_voxel).max())

    def occupancy(self, centre_mm: np.ndarray, voxel_mm: float, grid_size: int,
                  supersample: int = SUPERSAMPLE) -> np.ndarray:
        """The shape grid ``(G, G, G)`` (RAS axes) centred at ``centre_mm``: occupancy in [0, 1]."""
        axis = sample_offsets_mm(grid_size, voxel_mm, supersample)
        x, y, z = np.meshgrid(axis + centre_mm[0], axis + centre_mm[1], axis + centre_mm[2], indexing="ij")
        world = np.stack([x.ravel(), y.ravel(), z.ravel()])
        index = np.linalg.solve(self.affine[:3, :3], world - self.affine[:3, 3:4])
        # the mask as bytes (a float copy of a 512^3 mask took 512 MB): order-1 interpolation needs no prefilter
        mask = np.ascontiguousarray(self.mask, dtype=bool).view(np.uint8)
        values = ndimage.map_coordinates(mask, index, output=np.float32, order=1, mode="constant", cval=0.0)
        inside = (values >= 0.5).reshape(x.shape)
        return _average_blocks(inside, grid_size, supersample)


@dataclass(frozen=True)
class ClosedSurface:
    """A closed triangle mesh in RAS mm: ``vertices_mm (V, 3)``, ``triangles (T, 3)``."""

    vertices_mm: np.ndarray
    triangles: np.ndarray

    def volume_ml(self) -> float:
        """Enclosed volume (ml), by the divergence theorem, whichever way the triangles face."""
        return abs(self.signed_volume_ml())

    def signed_volume_ml(self) -> float:
        """Enclosed volume (ml), positive when the triangles face outward."""
        a, b, c = (self.vertices_mm[self.triangles[:, i]] for i in range(3))
        return float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0 / 1e3)

    def outward(self) -> ClosedSurface:
        """The same surface with its triangles facing outward."""
        if self.signed_volume_ml() < 0:
            return ClosedSurface(self.vertices_mm, self.triangles[:, ::-1])
        return self

    def mirrored_x(self) -> ClosedSurface:
        """The surface reflected through x = 0 (phantom frame <-> RAS), its triangles still facing the same side."""
        return ClosedSurface(self.vertices_mm * RAS_FROM_PHANTOM, self.triangles[:, ::-1])

    def centroid_mm(self) -> np.ndarray:
        """The centroid (RAS, mm) of the enclosed solid."""
        a, b, c = (self.vertices_mm[self.triangles[:, i]] for i in range(3))
        signed = np.einsum("ij,ij->i", a, np.cross(b, c))
        centroid: np.ndarray = (signed[:, None] * (a + b + c)).sum(axis=0) / (4.0 * signed.sum())
        return centroid

    def half_extent_mm(self, centre_mm: np.ndarray) -> float:
        """The largest distance along a world axis from ``centre_mm`` to a vertex (mm)."""
        return float(np.abs(self.vertices_mm - centre_mm).max())

    def occupancy(self, centre_mm: np.ndarray, voxel_mm: float, grid_size: int,
                  supersample: int = SUPERSAMPLE) -> np.ndarray:
        """The shape grid ``(G, G, G)`` centred at ``centre_mm``: occupancy in [0, 1], by ray parity along z."""
        axis = sample_offsets_mm(grid_size, voxel_mm, supersample)
        # Columns nudged off the sample lattice so that a ray cannot run exactly through an edge or a vertex.
        nudge = np.array([3.1e-6, 4.7e-6]) * voxel_mm
        inside = column_parity(self.vertices_mm - centre_mm, self.triangles, axis + nudge[0], axis + nudge[1], axis)
        return _average_blocks(inside, grid_size, supersample)


def column_parity(vertices: np.ndarray, triangles: np.ndarray, xs: np.ndarray, ys: np.ndarray,
                  zs: np.ndarray) -> np.ndarray:
    """Inside test of the points ``(xs[i], ys[j], zs[k])`` against a closed mesh: ``(X, Y, Z)`` booleans.

    Each column (x, y) is a ray along +z; a point is inside when an odd number of triangles cross its column
    below it. Every triangle visits only the columns in its bounding box.
    """
    tri = vertices[triangles]
    step_x, step_y = xs[1] - xs[0], ys[1] - ys[0]
    low_i = np.clip(np.ceil((tri[:, :, 0].min(axis=1) - xs[0]) / step_x), 0, len(xs)).astype(int)
    high_i = np.clip(np.floor((tri[:, :, 0].max(axis=1) - xs[0]) / step_x) + 1, 0, len(xs)).astype(int)
    low_j = np.clip(np.ceil((tri[:, :, 1].min(axis=1) - ys[0]) / step_y), 0, len(ys)).astype(int)
    high_j = np.clip(np.floor((tri[:, :, 1].max(axis=1) - ys[0]) / step_y) + 1, 0, len(ys)).astype(int)
    width_i = np.maximum(high_i - low_i, 0)
    width_j = np.maximum(high_j - low_j, 0)
    counts = width_i * width_j
    owner = np.repeat(np.arange(len(tri)), counts)
    local = np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts)
    column_i = low_i[owner] + local // np.maximum(width_j[owner], 1)
    column_j = low_j[owner] + local % np.maximum(width_j[owner], 1)
    px, py = xs[column_i], ys[column_j]
    a, b, c = tri[owner, 0], tri[owner, 1], tri[owner, 2]
    # Barycentric coordinates of the column in the triangle's xy projection.
    det = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (c[:, 0] - a[:, 0]) * (b[:, 1] - a[:, 1])
    safe = np.where(det == 0, 1.0, det)
    u = ((px - a[:, 0]) * (c[:, 1] - a[:, 1]) - (c[:, 0] - a[:, 0]) * (py - a[:, 1])) / safe
    v = ((b[:, 0] - a[:, 0]) * (py - a[:, 1]) - (px - a[:, 0]) * (b[:, 1] - a[:, 1])) / safe
    hit = (det != 0) & (u >= 0) & (v >= 0) & (u + v <= 1)
    z_hit = a[hit, 2] + u[hit] * (b[hit, 2] - a[hit, 2]) + v[hit] * (c[hit, 2] - a[hit, 2])
    first_above = np.searchsorted(zs, z_hit)
    crossings = np.zeros((len(xs), len(ys), len(zs) + 1), np.int32)
    np.add.at(crossings, (column_i[hit], column_j[hit], first_above), 1)
    return (np.cumsum(crossings, axis=2)[:, :, :-1] % 2).astype(bool)


def surface_of(occupancy: np.ndarray, voxel_mm: float, level: float = 0.5) -> ClosedSurface:
    """The ``level`` surface of a shape grid by marching cubes: a closed mesh in mm about the grid's centre.

    Raises ShapeError when no voxel reaches ``level`` (an empty shape).
    """
    # scikit-image (0.5 s to import) only where a surface is made
    with require_extra("shape"):
        from skimage import measure

    if occupancy.max() < level:
        raise ShapeError(f"the grid holds no shape: no voxel reaches occupancy {level:g}")
    padded = np.pad(occupancy.astype(np.float32), 1)
    vertices, triangles, _, _ = measure.marching_cubes(padded, level=level, spacing=(voxel_mm,) * 3)
    vertices = vertices - (occupancy.shape[0] + 1) / 2.0 * voxel_mm
    return ClosedSurface(vertices, triangles.astype(np.int64)).outward()
