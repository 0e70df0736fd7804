"""The built-in prostate's shape: its body of revolution, and the walls its chambers leave (millimetres).

Geometry (x to the patient's left, y anterior, z from apex to base): a chestnut-like body of revolution about z,
profile ``r(z) = R sqrt(1 - t^2) (1 + k t)`` with ``t = z / c``, widest toward the base (+z), squeezed
front-to-back by ``ANTERIOR_POSTERIOR_RATIO``; ``R`` is set so the body encloses ``REST_VOLUME_ML``. The chambers
are the ellipsoids of a :class:`~phantom.model.mesh.geometry.ProstateGeometry`; every wall between them and the
surface is measured here before :mod:`phantom.model.mesh.prostate` meshes the body with gmsh.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np

from phantom.model.arrays import BoolArray, FloatArray, IntArray
from phantom.model.errors import MeshError
from phantom.model.mesh.geometry import ProstateGeometry, Vector3

#: The body's volume (ml), half its length along z (mm), its taper toward the apex and its front-to-back squeeze.
REST_VOLUME_ML = 26.3
HALF_LENGTH_MM = 20.0
TAPER = 0.3
ANTERIOR_POSTERIOR_RATIO = 0.66


def profile_radius_mm(t: FloatArray, equator_radius_mm: float) -> FloatArray:
    """Radius of the body of revolution at ``z = t * HALF_LENGTH_MM`` (mm)."""
    return equator_radius_mm * np.sqrt(np.clip(1.0 - t * t, 0.0, None)) * (1.0 + TAPER * t)


def equator_radius_mm() -> float:
    """``R`` such that the body's volume is REST_VOLUME_ML: ``V = pi R^2 c q (4/3 + 4 k^2 / 15)``."""
    shape_integral = 4.0 / 3.0 + 4.0 * TAPER**2 / 15.0
    volume_mm3 = REST_VOLUME_ML * 1e3
    return math.sqrt(volume_mm3 / (math.pi * HALF_LENGTH_MM * ANTERIOR_POSTERIOR_RATIO * shape_integral))


def body_surface_points_mm(spacing_mm: float = 0.5) -> FloatArray:
    """Dense samples of the body's outer surface (mm), for measuring walls."""
    radius_mm = equator_radius_mm()
    n_axial = int(2 * HALF_LENGTH_MM / spacing_mm)
    n_around = int(2 * math.pi * radius_mm * 1.3 / spacing_mm)
    t = np.linspace(-1.0, 1.0, n_axial)
    angle = np.linspace(0.0, 2 * math.pi, n_around, endpoint=False)
    t, angle = np.meshgrid(t, angle, indexing="ij")
    r = profile_radius_mm(t, radius_mm)
    points = np.stack([r * np.cos(angle), ANTERIOR_POSTERIOR_RATIO * r * np.sin(angle), HALF_LENGTH_MM * t], -1)
    return points.reshape(-1, 3)


def body_surface_mesh_mm(spacing_mm: float = 0.5) -> tuple[FloatArray, IntArray]:
    """The body's outer surface as a closed triangle mesh (mm): vertices (V, 3) and outward triangles (T, 3), rings
    about ``spacing_mm`` apart (the polar angle ``t = -cos(theta)`` keeps them even near the poles)."""
    radius_mm = equator_radius_mm()
    n_rings = max(int(math.pi * HALF_LENGTH_MM / spacing_mm), 8)
    n_around = max(int(2 * math.pi * radius_mm * 1.3 / spacing_mm), 12)
    t = -np.cos(np.linspace(0.0, math.pi, n_rings + 1)[1:-1])
    angle = np.linspace(0.0, 2 * math.pi, n_around, endpoint=False)
    t_grid, angle_grid = np.meshgrid(t, angle, indexing="ij")
    r = profile_radius_mm(t_grid, radius_mm)
    rings = np.stack([r * np.cos(angle_grid), ANTERIOR_POSTERIOR_RATIO * r * np.sin(angle_grid),
                      HALF_LENGTH_MM * t_grid], -1).reshape(-1, 3)
    vertices = np.vstack([rings, [[0.0, 0.0, -HALF_LENGTH_MM], [0.0, 0.0, HALF_LENGTH_MM]]])
    apex, base = len(rings), len(rings) + 1
    ring, step = np.meshgrid(np.arange(len(t) - 1), np.arange(n_around), indexing="ij")
    a = ring * n_around + step
    b = ring * n_around + (step + 1) % n_around
    c, d = a + n_around, b + n_around
    quads = np.concatenate([np.stack([a, b, d], -1).reshape(-1, 3), np.stack([a, d, c], -1).reshape(-1, 3)])
    around = np.arange(n_around)
    last = (len(t) - 1) * n_around
    caps = np.concatenate([np.stack([np.full(n_around, apex), (around + 1) % n_around, around], -1),
                           np.stack([np.full(n_around, base), last + around, last + (around + 1) % n_around], -1)])
    return vertices, np.concatenate([quads, caps]).astype(np.int64)


def inside_body(points_mm: FloatArray) -> BoolArray:
    """Whether each point (mm) lies inside the body."""
    t = points_mm[:, 2] / HALF_LENGTH_MM
    radial = np.hypot(points_mm[:, 0], points_mm[:, 1] / ANTERIOR_POSTERIOR_RATIO)
    return (np.abs(t) < 1.0) & (radial < profile_radius_mm(t, equator_radius_mm()))


def wall_thicknesses_mm(geometry: ProstateGeometry) -> dict[str, float]:
    """The thinnest wall between each chamber and the outer surface, and between chambers (mm).

    Negative when a chamber breaks through the surface or two chambers overlap. Measured between samples of the
    surfaces 0.5 mm apart: the nearest sample lies within 0.35 mm of the nearest point along the surface, which
    overestimates a wall of 2 mm or more by under 0.05 mm.
    """
    # scipy.spatial (0.1 s to import) only where walls are measured
    from scipy.spatial import cKDTree

    outer = cKDTree(body_surface_points_mm())
    samples = [ellipsoid_points_mm(centre, axes) for centre, axes in geometry.ellipsoids_mm()]
    walls: dict[str, float] = {}
    for index, points in enumerate(samples):
        distance = float(np.min(outer.query(points)[0]))
        walls[f"chamber{index}-outer"] = distance if np.all(inside_body(points)) else -distance
    ellipsoids = geometry.ellipsoids_mm()
    for first in range(len(samples)):
        for second in range(first + 1, len(samples)):
            distance = float(np.min(cKDTree(samples[second]).query(samples[first])[0]))
            centre, axes = (np.asarray(value) for value in ellipsoids[first])
            overlapping = np.any(np.sum(((samples[second] - centre) / axes) ** 2, axis=1) < 1)
            walls[f"chamber{first}-chamber{second}"] = -distance if overlapping else distance
    return walls


def ellipsoid_points_mm(centre: Vector3, axes: Vector3, spacing_mm: float = 0.5) -> FloatArray:
    """Samples (k, 3) of an ellipsoid's surface, about ``spacing_mm`` apart along its largest axis."""
    largest = max(axes)
    n_polar = max(int(math.pi * largest / spacing_mm), 16)
    n_azimuth = 2 * n_polar
    polar = np.linspace(0.0, math.pi, n_polar)
    azimuth = np.linspace(0.0, 2 * math.pi, n_azimuth, endpoint=False)
    polar, azimuth = np.meshgrid(polar, azimuth, indexing="ij")
    unit = np.stack([np.sin(polar) * np.cos(azimuth), np.sin(polar) * np.sin(azimuth), np.cos(polar)], axis=-1)
    points: FloatArray = (unit * np.asarray(axes) + np.asarray(centre)).reshape(-1, 3)
    return points


@dataclass(frozen=True)
class WallField:
    """The local wall thickness on a regular grid (mm): at a point of the solid, the thickness of the wall it lies
    in, ``min over pairs of surfaces (d_a + d_b)`` with ``d`` the distance to each surface (the outer one and every
    chamber's); deep in the body it is large, inside a thin wall it is that wall's thickness. ``origin_mm`` is the
    grid's first point, ``spacing_mm`` its step, ``thickness_mm`` (nx, ny, nz) the values."""

    origin_mm: FloatArray
    spacing_mm: float
    thickness_mm: FloatArray

    def at(self, x: float, y: float, z: float) -> float:
        """The thickness (mm) at a point, trilinear between the grid's points (the nearest edge value outside).

        gmsh asks this once per point while meshing (hundreds of thousands of times), so it is scalar arithmetic
        on the grid's values, in the order a 2x2x2 block's numpy interpolation takes: the same floats."""
        nx, ny, nz = (int(n) for n in self.thickness_mm.shape)
        ox, oy, oz = self._origin
        px, py, pz = (x - ox) / self.spacing_mm, (y - oy) / self.spacing_mm, (z - oz) / self.spacing_mm
        i = min(max(int(math.floor(px)), 0), nx - 2)
        j = min(max(int(math.floor(py)), 0), ny - 2)
        k = min(max(int(math.floor(pz)), 0), nz - 2)
        u, v, w = min(max(px - i, 0.0), 1.0), min(max(py - j, 0.0), 1.0), min(max(pz - k, 0.0), 1.0)
        values = self._values
        c = (i * ny + j) * nz + k           # the corner (i, j, k) in C order; +1 along z, +nz along y, +ny nz along x
        dy, dx = nz, ny * nz
        # along x, at the four (y, z) corners; then along y; then along z
        x00 = values[c] * (1.0 - u) + values[c + dx] * u
        x01 = values[c + 1] * (1.0 - u) + values[c + dx + 1] * u
        x10 = values[c + dy] * (1.0 - u) + values[c + dx + dy] * u
        x11 = values[c + dy + 1] * (1.0 - u) + values[c + dx + dy + 1] * u
        y0 = x00 * (1.0 - v) + x10 * v
        y1 = x01 * (1.0 - v) + x11 * v
        return y0 * (1.0 - w) + y1 * w

    @functools.cached_property
    def _values(self) -> list[float]:
        values: list[float] = np.ascontiguousarray(self.thickness_mm, dtype=float).ravel().tolist()
        return values

    @functools.cached_property
    def _origin(self) -> tuple[float, float, float]:
        x, y, z = (float(value) for value in self.origin_mm)
        return x, y, z


def wall_field(geometry: ProstateGeometry, spacing_mm: float = 1.0) -> WallField:
    """The local wall thickness (:class:`WallField`) of the built-in body with ``geometry``'s chambers, on a grid
    of ``spacing_mm`` over the body's bounding box; distances to surface samples 0.5 mm apart."""
    surfaces = [body_surface_points_mm()] + [ellipsoid_points_mm(centre, axes)
                                            for centre, axes in geometry.ellipsoids_mm()]
    radius_mm = equator_radius_mm() * (1.0 + TAPER) + spacing_mm
    low = np.array([-radius_mm, -ANTERIOR_POSTERIOR_RATIO * radius_mm, -HALF_LENGTH_MM - spacing_mm])
    return wall_field_of(surfaces, low, -low, spacing_mm)


def wall_field_of(surfaces: list[FloatArray], low_mm: FloatArray, high_mm: FloatArray, spacing_mm: float = 1.0,
                  within_mm: float = math.inf) -> WallField:
    """The local wall thickness (:class:`WallField`) between surfaces given by dense samples (each (k, 3), mm; the
    outer one and every chamber's), on a grid of ``spacing_mm`` from ``low_mm`` to ``high_mm``; walls thicker than
    ``within_mm`` read as infinite (a nearest-sample search deep inside a hollow set of samples visits most of
    them: the bound keeps it to the walls that matter)."""
    # scipy.spatial (0.1 s to import) only where walls are measured
    from scipy.spatial import cKDTree

    axes = [np.arange(start, stop + 0.5 * spacing_mm, spacing_mm) for start, stop in zip(low_mm, high_mm,
                                                                                         strict=True)]
    points = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    distances = [cKDTree(samples).query(points, distance_upper_bound=within_mm)[0] for samples in surfaces]
    thickness = np.full(len(points), np.inf)
    for first in range(len(distances)):
        for second in range(first + 1, len(distances)):
            thickness = np.minimum(thickness, distances[first] + distances[second])
    # finite, so that interpolating next to an unbounded wall gives a large number, not inf * 0
    thickness = np.minimum(thickness, 1e6)
    return WallField(np.asarray(low_mm, float), spacing_mm, thickness.reshape([len(axis) for axis in axes]))


def check_walls(geometry: ProstateGeometry) -> dict[str, float]:
    """The walls (see :func:`wall_thicknesses_mm`), or MeshError naming the thinnest one below ``min_wall_mm``."""
    walls = wall_thicknesses_mm(geometry)
    name = min(walls, key=lambda wall: walls[wall])
    if walls[name] < geometry.min_wall_mm:
        what = "breaks through" if walls[name] < 0 and "outer" in name else "overlaps" if walls[name] < 0 else ""
        detail = f"{what} ({walls[name]:.2f} mm)" if what else f"is {walls[name]:.2f} mm thick"
        raise MeshError(f"geometry: the wall {name} {detail}, below min_wall_mm = {geometry.min_wall_mm:g} mm: "
                        f"shrink or move the chambers")
    return walls
