"""The lost-wax cast: the outer mould in two halves and a wax core per chamber, as printable STLs.

Booleans by manifold3d (exact, always closed output). The mould is a block around the gland with the gland cut
out, split on the coronal plane through the chambers' centres (all three lie on it, so every core's tube stem lies
in it too and neither half locks a stem); the surface's undercut across that plane (area facing against the pull
of the half it is in) is measured and reported. One half carries hemispherical registration keys, the other the
matching sockets (with a clearance). The mould is poured apex up: a pour spout at the apex and a vent at the
top of each lobe, and the cores' stems leave through the base, each through a seat (a hole of the stem's size in
the mould) that holds the core where the design puts it. A core is its chamber's ellipsoid and a stem from the
chamber to the outside (the tube channel, ``stem_diameter_mm``): straight up from the base chamber, and from each
lobe's chamber tilted outward just enough to pass the base chamber at the minimum wall.

Every file is checked: one body, closed (watertight), consistent normals, positive volume.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from phantom import require_extra, written_atomically
from phantom.design.chambers import CHAMBER_LABELS, Chamber, ellipsoid_distance_mm
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


@dataclass
class Cast:
    """The cast's parts, the silicone to mix, the split plane's undercut and each stem's clearance (mm)."""

    parts: list[CastPart]
    silicone_ml: float
    split_y_mm: float
    undercut_mm2: float
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


def stem_directions(chambers: list[Chamber], min_wall_mm: float, stem_diameter_mm: float,
                    length_mm: float) -> tuple[list[FloatArray], dict[str, float]]:
    """Each chamber's stem direction (unit, in the plane y = its centre's) and its clearance to the other chambers
    (mm, the stem's surface to theirs): the base chamber's straight up, a lobe's tilted outward from vertical by
    the least angle (in 1 degree steps, to 75) that clears the others by ``min_wall_mm``."""
    directions = []
    clearances = {}
    along = np.linspace(0.0, length_mm, 400)[:, None]
    for index, chamber in enumerate(chambers):
        others = [other for k, other in enumerate(chambers) if k != index]
        outward = math.copysign(1.0, chamber.centre_mm[0]) if index else 0.0
        best: tuple[float, FloatArray] | None = None
        for degrees in range(0, 76) if index else [0]:
            angle = math.radians(degrees)
            direction = np.array([outward * math.sin(angle), 0.0, math.cos(angle)])
            points = np.asarray(chamber.centre_mm) + along * direction
            clearance = min(float(ellipsoid_distance_mm(points, other).min()) for other in others)
            clearance -= stem_diameter_mm / 2
            if best is None or clearance > best[0]:
                best = (clearance, direction)
            if clearance >= min_wall_mm:
                break
        assert best is not None
        directions.append(best[1])
        clearances[f"{CHAMBER_LABELS[index]} stem"] = best[0]
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
    directions, clearances = stem_directions(chambers, min_wall_mm, stem_diameter_mm, reach)
    stems = []
    for chamber, direction in zip(chambers, directions, strict=True):
        start = np.asarray(chamber.centre_mm)
        # out of the block by 5 mm: the part of the stem the seat holds, and a handle
        length = _length_to_leave_box(start, direction, block_low, block_high) + 5.0
        stems.append(_rod(start, start + length * direction, stem_diameter_mm))
    cores = [_ellipsoid(chamber) + stem for chamber, stem in zip(chambers, stems, strict=True)]
    split_y = float(np.mean([chamber.centre_mm[1] for chamber in chambers]))
    block = m3d.Manifold.cube(block_high - block_low).translate(block_low)
    channels = [_rod(np.array([0.0, split_y, low[2] + 1.0]), np.array([0.0, split_y, block_low[2] - 1.0]),
                     SPOUT_DIAMETER_MM)]
    for side in (1.0, -1.0):
        top = _lowest_point(surface, side, split_y)
        # nudged off the vertex: a marching-cubes surface has flats on its grid's planes, which a rod through the
        # vertex's own coordinates touches along a line (a non-manifold edge in the STL)
        start = top + np.array([0.113, 0.171, 0.5])
        channels.append(_rod(start, np.array([start[0], start[1], block_low[2] - 1.0]), VENT_DIAMETER_MM))
    mould = block - gland
    for solid in stems + channels:
        mould = mould - solid
    front, back = mould.split_by_plane((0.0, 1.0, 0.0), split_y)
    keys = _key_centres(block_low, block_high, low, high, split_y)
    for centre in keys:
        front = front + m3d.Manifold.sphere(KEY_RADIUS_MM, CIRCLE_SEGMENTS).translate(centre)
        back = back - m3d.Manifold.sphere(KEY_RADIUS_MM + KEY_CLEARANCE_MM, CIRCLE_SEGMENTS).translate(centre)
    parts = [("mould_front", front), ("mould_back", back)]
    parts += [(f"core_{label.replace(' ', '_')}", core) for label, core in zip(CHAMBER_LABELS, cores, strict=True)]
    written = [_write_part(name, solid, out / f"{name}.stl", trimesh) for name, solid in parts]
    silicone = gland
    for core in cores:
        silicone = silicone - core
    return Cast(written, float(silicone.volume()) / 1e3, split_y, undercut_area_mm2(surface, split_y), clearances)


def _length_to_leave_box(start: FloatArray, direction: FloatArray, low: FloatArray, high: FloatArray) -> float:
    """How far from ``start`` (inside the box) along ``direction`` the box ends."""
    with np.errstate(divide="ignore"):
        limits = np.where(direction > 0, (high - start) / direction,
                          np.where(direction < 0, (low - start) / direction, np.inf))
    return float(limits.min())


def _lowest_point(surface: Surface, side: float, split_y: float) -> FloatArray:
    """The surface's lowest vertex (the apex end, the top when the mould is poured apex up) on one side of the
    mid-sagittal plane (``side`` +1: left, x > 0), far enough from the spout that the vent does not touch it."""
    vertices = surface.vertices_mm
    clear = np.hypot(vertices[:, 0], vertices[:, 1] - split_y) > SPOUT_DIAMETER_MM / 2 + VENT_DIAMETER_MM / 2 + 2.0
    half = vertices[(side * vertices[:, 0] > 0.25 * np.abs(vertices[:, 0]).max()) & clear]
    if len(half) == 0:
        raise DesignError("the gland is too narrow for a vent beside the pour spout: design it larger")
    lowest: FloatArray = half[np.argmin(half[:, 2])]
    return lowest


def _key_centres(block_low: FloatArray, block_high: FloatArray, low: FloatArray, high: FloatArray,
                 split_y: float) -> list[FloatArray]:
    """Four keys on the split plane, in the mould's wall beside the gland's corners."""
    x = [0.5 * (block_low[0] + low[0]), 0.5 * (block_high[0] + high[0])]
    z = [0.5 * (low[2] + high[2]) - 0.25 * (high[2] - low[2]), 0.5 * (low[2] + high[2]) + 0.25 * (high[2] - low[2])]
    return [np.array([xi, split_y, zi]) for xi in x for zi in z]


def undercut_area_mm2(surface: Surface, split_y: float) -> float:
    """The gland's surface area that a mould half split at ``y = split_y`` cannot be pulled off (mm^2): on the +y
    side faces whose outward normal points toward -y, on the -y side toward +y."""
    a, b, c = (surface.vertices_mm[surface.triangles[:, i]] for i in range(3))
    cross = np.cross(b - a, c - a)
    area = 0.5 * np.linalg.norm(cross, axis=1)
    normal_y = cross[:, 1] / np.maximum(2.0 * area, 1e-300)
    side = np.sign((a[:, 1] + b[:, 1] + c[:, 1]) / 3.0 - split_y)
    return float(area[side * normal_y < -UNDERCUT_TOLERANCE].sum())


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
