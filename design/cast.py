"""The lost-wax cast: the outer mould in two halves and a wax core per chamber, as printable STLs.

Booleans by manifold3d (exact, always closed output). The mould is a block around the gland with the gland cut out,
split on the plane with the least undercut (:func:`choose_split_plane`: the gland's surface area facing against the
pull of the half it lies in, searched over planes within 30 degrees of vertical that cut every chamber near its
centre, so each core's stem lies in the plane and neither half locks a stem); the undercut of the chosen plane and
of the coronal plane through the chambers' centres are reported. One half carries hemispherical registration keys,
the other the matching sockets (with a clearance). The mould is poured apex up: a pour spout at the apex and a vent
at the top of each lobe, and the cores' stems leave through the base, each through a seat (a hole of the stem's size
in the mould) that holds the core where the design puts it. A core is its chamber's ellipsoid and a stem from the
chamber to the outside (the tube channel, ``stem_diameter_mm``), in the split plane: from the chamber's centre's
foot on the plane, straight up the plane from the base chamber, and from each lobe's chamber tilted outward in the
plane just enough to pass the other chambers at the minimum wall. The spout runs down the plane from the gland's
centre out through the apex.

Every file is checked: one body, closed (watertight), consistent normals, positive volume.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from phantom import require_extra, written_atomically
from phantom.design.chambers import BASE, Chamber, least_ellipsoid_distance_mm
from phantom.design.errors import DesignError
from phantom.design.surface import Surface
from phantom.model.arrays import FloatArray

#: The mould block's wall around the gland's bounding box (mm).
MOULD_WALL_MM = 8.0
#: Registration keys: radius, and the socket's extra radius (mm).
KEY_RADIUS_MM = 3.0
KEY_CLEARANCE_MM = 0.2
#: The pour spout's and the vents' diameters (mm).
SPOUT_DIAMETER_MM = 8.0
VENT_DIAMETER_MM = 2.0
#: Segments of a printed circle.
CIRCLE_SEGMENTS = 48
#: A face whose normal points against its half's pull by more than this (the normal's component) is an undercut.
UNDERCUT_TOLERANCE = 0.05
#: The split planes searched: normals within this angle of horizontal (the stems leave upward, through the base),
#: about SPLIT_NORMALS of them over the half sphere, and SPLIT_OFFSETS offsets each across the band where the plane
#: cuts every chamber within SPLIT_CHAMBER_BAND of its half-width along the normal from its centre.
SPLIT_TILT_DEGREES = 30.0
SPLIT_NORMALS = 600
SPLIT_OFFSETS = 9
SPLIT_CHAMBER_BAND = 0.5
#: An undercut above this (mm^2) is said: the silicone must flex out of it.
UNDERCUT_WARNING_MM2 = 1.0


@dataclass
class CastPart:
    """One printed part: its file, volume and checks."""

    name: str
    path: Path
    volume_ml: float
    bodies: int
    watertight: bool
    winding_consistent: bool

    @property
    def printable(self) -> bool:
        return self.bodies == 1 and self.watertight and self.winding_consistent and self.volume_ml > 0


@dataclass(frozen=True)
class SplitPlane:
    """The mould's split plane ``normal . x = offset_mm`` (``normal`` unit; the front half on its + side) and the
    gland's undercut across it (mm^2)."""

    normal: tuple[float, float, float]
    offset_mm: float
    undercut_mm2: float

    def foot_mm(self, point_mm: FloatArray) -> FloatArray:
        """The point's orthogonal projection onto the plane."""
        normal = np.asarray(self.normal)
        foot: FloatArray = point_mm - (normal @ point_mm - self.offset_mm) * normal
        return foot

    def up(self) -> FloatArray:
        """The plane's steepest upward direction (unit, +z projected onto it)."""
        normal = np.asarray(self.normal)
        up = np.array([0.0, 0.0, 1.0]) - normal[2] * normal
        direction: FloatArray = up / np.linalg.norm(up)
        return direction

    def across(self) -> FloatArray:
        """The plane's horizontal direction toward +x (unit)."""
        across = np.cross(self.up(), np.asarray(self.normal))
        direction: FloatArray = across * math.copysign(1.0, across[0])
        return direction

    def tilt_degrees(self) -> float:
        """The plane's angle from the coronal plane (degrees)."""
        return math.degrees(math.acos(min(1.0, abs(self.normal[1]))))


@dataclass
class Cast:
    """The cast's parts, the silicone to mix, the split plane (with its undercut), the coronal plane's undercut
    through the chambers' centres (what the search is compared with, mm^2) and each stem's clearance (mm)."""

    parts: list[CastPart]
    silicone_ml: float
    split: SplitPlane
    coronal_undercut_mm2: float
    stem_clearances_mm: dict[str, float] = field(default_factory=dict)


def _manifold(surface: Surface) -> Any:
    with require_extra("design"):
        import manifold3d

    mesh = manifold3d.Mesh(vert_properties=np.ascontiguousarray(surface.vertices_mm, np.float32),
                           tri_verts=np.ascontiguousarray(surface.triangles, np.uint32))
    solid = manifold3d.Manifold(mesh)
    if solid.is_empty():
        raise DesignError(f"the gland's surface is not a closed manifold for the cast's booleans "
                          f"({solid.status()})")
    return solid


def _rod(start_mm: FloatArray, end_mm: FloatArray, diameter_mm: float) -> Any:
    """A cylinder from ``start_mm`` to ``end_mm``."""
    with require_extra("design"):
        import manifold3d

    axis = end_mm - start_mm
    length = float(np.linalg.norm(axis))
    direction = axis / length
    # a rotation taking z to the direction (Rodrigues), then the translation
    z = np.array([0.0, 0.0, 1.0])
    cross = np.cross(z, direction)
    sine, cosine = float(np.linalg.norm(cross)), float(direction @ z)
    if sine < 1e-12:
        rotation = np.diag([1.0, 1.0 if cosine > 0 else -1.0, 1.0 if cosine > 0 else -1.0])
    else:
        k = cross / sine
        skew = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
        rotation = np.eye(3) + sine * skew + (1 - cosine) * skew @ skew
    cylinder = manifold3d.Manifold.cylinder(length, diameter_mm / 2, -1.0, CIRCLE_SEGMENTS)
    return cylinder.transform(np.hstack([rotation, start_mm[:, None]]))


def _ellipsoid(chamber: Chamber) -> Any:
    with require_extra("design"):
        import manifold3d

    return manifold3d.Manifold.sphere(1.0, 96).scale(chamber.semi_axes_mm).translate(chamber.centre_mm)


def stem_directions(chambers: list[Chamber], split: SplitPlane, min_wall_mm: float, stem_diameter_mm: float,
                    length_mm: float) -> tuple[list[FloatArray], dict[str, float]]:
    """Each chamber's stem direction (unit, in the split plane, from the foot of its centre on it) and its
    clearance to the other chambers (mm, the stem's surface to theirs): the base chamber's straight up the plane, a
    lobe's tilted outward from the plane's upward by the least angle (in 1 degree steps, to 75) that clears the
    others by ``min_wall_mm``."""
    directions = []
    clearances = {}
    along = np.linspace(0.0, length_mm, 400)[:, None]
    up, across = split.up(), split.across()
    for index, chamber in enumerate(chambers):
        others = [other for k, other in enumerate(chambers) if k != index]
        if not others:
            directions.append(up)
            continue
        tilted = chamber.kind != BASE
        outward = math.copysign(1.0, chamber.centre_mm[0]) if tilted else 0.0
        best: tuple[float, FloatArray] | None = None
        start = split.foot_mm(np.asarray(chamber.centre_mm))
        for degrees in range(0, 76) if tilted else [0]:
            angle = math.radians(degrees)
            direction = outward * math.sin(angle) * across + math.cos(angle) * up
            points = start + along * direction
            clearance = min(least_ellipsoid_distance_mm(points, other) for other in others)
            clearance -= stem_diameter_mm / 2
            if best is None or clearance > best[0]:
                best = (clearance, direction)
            if clearance >= min_wall_mm:
                break
        assert best is not None
        directions.append(best[1])
        clearances[f"{chamber.label} stem"] = best[0]
    return directions, clearances


def make_cast(surface: Surface, chambers: list[Chamber], min_wall_mm: float, stem_diameter_mm: float,
              out: Path) -> Cast:
    """Write the mould halves and the cores as STLs into ``out`` and check each (see the module docstring)."""
    with require_extra("design"):
        import manifold3d as m3d
        import trimesh

    gland = _manifold(surface)
    low, high = surface.vertices_mm.min(axis=0), surface.vertices_mm.max(axis=0)
    block_low, block_high = low - MOULD_WALL_MM, high + MOULD_WALL_MM
    reach = float(np.linalg.norm(block_high - block_low))
    split = choose_split_plane(surface, chambers)
    directions, clearances = stem_directions(chambers, split, min_wall_mm, stem_diameter_mm, reach)
    stems = []
    for chamber, direction in zip(chambers, directions, strict=True):
        start = split.foot_mm(np.asarray(chamber.centre_mm))
        # out of the block by 5 mm: the part of the stem the seat holds, and a handle
        length = _length_to_leave_box(start, direction, block_low, block_high) + 5.0
        stems.append(_rod(start, start + length * direction, stem_diameter_mm))
    cores = [_ellipsoid(chamber) + stem for chamber, stem in zip(chambers, stems, strict=True)]
    block = m3d.Manifold.cube(block_high - block_low).translate(block_low)
    spout = split.foot_mm(surface.centroid_mm())
    down = -split.up()
    channels = [_rod(spout, spout + (_length_to_leave_box(spout, down, block_low, block_high) + 1.0) * down,
                     SPOUT_DIAMETER_MM)]
    for side in (1.0, -1.0):
        top = _lowest_point(surface, side, spout)
        # nudged off the vertex: a marching-cubes surface has flats on its grid's planes, which a rod through the
        # vertex's own coordinates touches along a line (a non-manifold edge in the STL)
        start = top + np.array([0.113, 0.171, 0.5])
        channels.append(_rod(start, np.array([start[0], start[1], block_low[2] - 1.0]), VENT_DIAMETER_MM))
    mould = block - gland
    for solid in stems + channels:
        mould = mould - solid
    front, back = mould.split_by_plane(split.normal, split.offset_mm)
    keys = _key_centres(surface, split)
    for centre in keys:
        front = front + m3d.Manifold.sphere(KEY_RADIUS_MM, CIRCLE_SEGMENTS).translate(centre)
        back = back - m3d.Manifold.sphere(KEY_RADIUS_MM + KEY_CLEARANCE_MM, CIRCLE_SEGMENTS).translate(centre)
    parts = [("mould_front", front), ("mould_back", back)]
    parts += [(f"core_{chamber.label.replace(' ', '_')}", core) for chamber, core in zip(chambers, cores, strict=True)]
    written = [_write_part(name, solid, out / f"{name}.stl", trimesh) for name, solid in parts]
    silicone = gland
    for core in cores:
        silicone = silicone - core
    return Cast(written, float(silicone.volume()) / 1e3, split, coronal_plane(surface, chambers).undercut_mm2,
                clearances)


def _length_to_leave_box(start: FloatArray, direction: FloatArray, low: FloatArray, high: FloatArray) -> float:
    """How far from ``start`` (inside the box) along ``direction`` the box ends."""
    with np.errstate(divide="ignore"):
        limits = np.where(direction > 0, (high - start) / direction,
                          np.where(direction < 0, (low - start) / direction, np.inf))
    return float(limits.min())


def _lowest_point(surface: Surface, side: float, spout_mm: FloatArray) -> FloatArray:
    """The surface's lowest vertex (the apex end, the top when the mould is poured apex up) on one side of the
    mid-sagittal plane (``side`` +1: left, x > 0), far enough from the spout (through ``spout_mm``) that the vent
    does not touch it."""
    vertices = surface.vertices_mm
    clear = (np.hypot(vertices[:, 0] - spout_mm[0], vertices[:, 1] - spout_mm[1])
             > SPOUT_DIAMETER_MM / 2 + VENT_DIAMETER_MM / 2 + 2.0)
    half = vertices[(side * vertices[:, 0] > 0.25 * np.abs(vertices[:, 0]).max()) & clear]
    if len(half) == 0:
        raise DesignError("the gland is too narrow for a vent beside the pour spout: design it larger")
    lowest: FloatArray = half[np.argmin(half[:, 2])]
    return lowest


def _key_centres(surface: Surface, split: SplitPlane) -> list[FloatArray]:
    """Four keys on the split plane, in the mould's wall half way out from the gland on either side, at a quarter
    and three quarters of its height along the plane."""
    up, across = split.up(), split.across()
    origin = split.foot_mm(surface.centroid_mm())
    relative = surface.vertices_mm - origin
    sideways = relative @ across
    beside = [float(sideways.max()) + MOULD_WALL_MM / 2, float(sideways.min()) - MOULD_WALL_MM / 2]
    heights = relative @ up
    along = [float(np.quantile(heights, 0.25)), float(np.quantile(heights, 0.75))]
    return [origin + side * across + height * up for side in beside for height in along]


def plane_undercuts_mm2(surface: Surface, normals: FloatArray, offsets_mm: FloatArray) -> FloatArray:
    """The gland's undercut (mm^2) across each plane ``normals[i] . x = offsets_mm[i, j]``: the area on the + side
    whose outward normal points against +normal (by more than UNDERCUT_TOLERANCE), and on the - side against
    -normal. ``normals (N, 3)`` unit, ``offsets_mm (N, K)``; returns ``(N, K)``."""
    a, b, c = (surface.vertices_mm[surface.triangles[:, i]] for i in range(3))
    cross = np.cross(b - a, c - a)
    area = 0.5 * np.linalg.norm(cross, axis=1)
    unit = cross / np.maximum(2.0 * area, 1e-300)[:, None]
    centres = (a + b + c) / 3.0
    undercuts = np.empty(offsets_mm.shape)
    for index, normal in enumerate(normals):
        facing = unit @ normal
        height = centres @ normal
        order = np.argsort(height)
        # faces above the plane facing down, and below it facing up: cumulative areas in order along the normal
        down = np.concatenate([[0.0], np.cumsum(np.where(facing[order] < -UNDERCUT_TOLERANCE, area[order], 0.0))])
        up = np.concatenate([[0.0], np.cumsum(np.where(facing[order] > UNDERCUT_TOLERANCE, area[order], 0.0))])
        cut = np.searchsorted(height[order], offsets_mm[index])
        undercuts[index] = (down[-1] - down[cut]) + up[cut]
    return undercuts


def coronal_plane(surface: Surface, chambers: list[Chamber]) -> SplitPlane:
    """The coronal plane through the chambers' mean centre, and its undercut."""
    offset = float(np.mean([chamber.centre_mm[1] for chamber in chambers]))
    undercut = float(plane_undercuts_mm2(surface, np.array([[0.0, 1.0, 0.0]]), np.array([[offset]]))[0, 0])
    return SplitPlane((0.0, 1.0, 0.0), offset, undercut)


def candidate_normals(count: int = SPLIT_NORMALS, tilt_degrees: float = SPLIT_TILT_DEGREES) -> FloatArray:
    """About ``count`` unit normals spread evenly (a Fibonacci lattice) over the half sphere y >= 0, those within
    ``tilt_degrees`` of horizontal (|z| <= sin tilt), the coronal normal (0, 1, 0) first."""
    index = np.arange(count) + 0.5
    y = index / count
    radius = np.sqrt(1.0 - y**2)
    angle = np.pi * (1.0 + np.sqrt(5.0)) * index
    normals = np.stack([radius * np.cos(angle), y, radius * np.sin(angle)], axis=1)
    normals = normals[np.abs(normals[:, 2]) <= math.sin(math.radians(tilt_degrees))]
    result: FloatArray = np.vstack([[0.0, 1.0, 0.0], normals])
    return result


def choose_split_plane(surface: Surface, chambers: list[Chamber]) -> SplitPlane:
    """The plane of least undercut among :func:`candidate_normals` times SPLIT_OFFSETS offsets across the band
    where it cuts every chamber near its centre (within SPLIT_CHAMBER_BAND of the chamber's half-width along the
    normal), so each stem can lie in it; the coronal plane through the chambers' centres is always a candidate and
    wins ties."""
    normals = candidate_normals()
    centres = np.array([chamber.centre_mm for chamber in chambers])
    axes = np.array([chamber.semi_axes_mm for chamber in chambers])
    along = normals @ centres.T
    half_widths = SPLIT_CHAMBER_BAND * np.sqrt((normals[:, None, :] ** 2 * axes[None, :, :] ** 2).sum(axis=2))
    low, high = (along - half_widths).max(axis=1), (along + half_widths).min(axis=1)
    feasible = low <= high
    normals, low, high = normals[feasible], low[feasible], high[feasible]
    offsets = low[:, None] + (high - low)[:, None] * np.linspace(0.0, 1.0, SPLIT_OFFSETS)[None, :]
    undercuts = plane_undercuts_mm2(surface, normals, offsets)
    coronal = coronal_plane(surface, chambers)
    best = np.unravel_index(int(np.argmin(undercuts)), undercuts.shape)
    if undercuts[best] >= coronal.undercut_mm2:
        return coronal
    normal = normals[best[0]]
    return SplitPlane((float(normal[0]), float(normal[1]), float(normal[2])), float(offsets[best]),
                      float(undercuts[best]))


def undercut_warnings(split: SplitPlane, coronal_undercut_mm2: float) -> list[str]:
    """What to say when the chosen plane still leaves an undercut above UNDERCUT_WARNING_MM2."""
    if split.undercut_mm2 <= UNDERCUT_WARNING_MM2:
        return []
    return [f"no split plane of the mould is free of undercut: the least, {split.tilt_degrees():.0f} degrees from "
            f"coronal, leaves {split.undercut_mm2:.0f} mm^2 of the gland facing against its half's pull (the coronal "
            f"plane {coronal_undercut_mm2:.0f} mm^2); the cured silicone must flex out of it, or print the mould in "
            f"more parts"]


def _write_part(name: str, solid: Any, path: Path, trimesh: Any) -> CastPart:
    mesh_data = solid.to_mesh()
    mesh = trimesh.Trimesh(np.asarray(mesh_data.vert_properties)[:, :3], np.asarray(mesh_data.tri_verts),
                           process=True)
    with written_atomically(path, DesignError) as temporary:
        mesh.export(str(temporary), file_type="stl")
    bodies = len(solid.decompose())
    part = CastPart(name, path, float(mesh.volume) / 1e3, bodies, bool(mesh.is_watertight),
                    bool(mesh.is_winding_consistent))
    if not part.printable:
        raise DesignError(f"the cast's {name} is not printable ({bodies} bodies, watertight {part.watertight}, "
                          f"consistent normals {part.winding_consistent}, {part.volume_ml:.2f} ml): report this")
    return part
