"""Parameters of the built-in prostate's geometry: a scene's ``[geometry]`` table, checked, and its walls.

The body (a tapered chestnut of 26.3 ml, see :mod:`phantom.model.mesh.prostate`) is fixed; what a scene may change is
where the three ellipsoidal chambers sit and how large they are, and the fixation patch:

    [geometry]
    base_chamber_centre_mm = [0.0, 0.0, 11.0]       # chamber 0, on the mid-sagittal plane x = 0
    base_chamber_semi_axes_mm = [12.5, 8.5, 4.5]
    lobe_chamber_centre_mm = [8.7, 0.0, -2.5]       # chamber 1 (left lobe, x > 0); chamber 2 is its mirror
    lobe_chamber_semi_axes_mm = [5.7, 7.5, 6.5]
    base_chamber_scale = 1.0                        # multiplies the base chamber's semi-axes
    lobe_chamber_scale = 1.0                        # multiplies both lobe chambers' semi-axes
    fixation_radius_mm = 6.0                        # the fixed patch around the base pole
    min_wall_mm = 2.0                               # the thinnest wall allowed (manufacturable: >= 2 mm)
    mesh_size_mm = 2.5                              # element size (a calibration holds at its mesh size)

Every wall (chamber to outer surface, chamber to chamber) must be at least ``min_wall_mm`` thick, itself at
least :data:`MANUFACTURABLE_WALL_MM`: a cast silicone wall thinner than that tears on demoulding. Walls are
measured on samples of the surfaces (to about 0.05 mm) before meshing, so bad parameters give a one-line
``MeshError`` instead of a broken mesh. Only the standard library is imported at module load.
"""

from __future__ import annotations

import dataclasses
import hashlib
import math
from dataclasses import dataclass

from phantom.model.errors import MeshError, SceneError

#: The thinnest silicone wall that can be cast and demoulded (mm).
MANUFACTURABLE_WALL_MM = 2.0
#: Bounds of each scalar parameter (mm or dimensionless), beyond which the body cannot hold the chamber.
SCALE_RANGE = (0.3, 2.5)
FIXATION_RADIUS_RANGE_MM = (1.0, 15.0)


@dataclass(frozen=True)
class ProstateGeometry:
    """Chamber placement and size of the built-in prostate (mm); see the module docstring."""

    base_chamber_centre_mm: tuple[float, float, float] = (0.0, 0.0, 11.0)
    base_chamber_semi_axes_mm: tuple[float, float, float] = (12.5, 8.5, 4.5)
    lobe_chamber_centre_mm: tuple[float, float, float] = (8.7, 0.0, -2.5)
    lobe_chamber_semi_axes_mm: tuple[float, float, float] = (5.7, 7.5, 6.5)
    base_chamber_scale: float = 1.0
    lobe_chamber_scale: float = 1.0
    fixation_radius_mm: float = 6.0
    min_wall_mm: float = MANUFACTURABLE_WALL_MM
    mesh_size_mm: float = 2.5

    def ellipsoids_mm(self) -> tuple[tuple[tuple, tuple], ...]:
        """(centre, semi-axes) of chambers 0, 1 (left, x > 0) and 2 (right, the mirror of 1), scales applied."""
        base_axes = tuple(self.base_chamber_scale * a for a in self.base_chamber_semi_axes_mm)
        lobe_axes = tuple(self.lobe_chamber_scale * a for a in self.lobe_chamber_semi_axes_mm)
        x, y, z = self.lobe_chamber_centre_mm
        return ((tuple(self.base_chamber_centre_mm), base_axes), ((x, y, z), lobe_axes), ((-x, y, z), lobe_axes))

    def with_values(self, **values) -> ProstateGeometry:
        """A copy with some parameters changed (checked like a scene's table)."""
        return geometry_from_table({**self.as_table(), **values}, "geometry")

    def as_table(self) -> dict:
        """The scene's ``[geometry]`` table for this geometry (lists for the vectors)."""
        return {key: list(value) if isinstance(value, tuple) else value
                for key, value in dataclasses.asdict(self).items()}

    @property
    def key(self) -> str:
        """A short hash of the shape's parameters (not the element size): the mesh cache's name for it."""
        shape = {key: value for key, value in dataclasses.asdict(self).items() if key != "mesh_size_mm"}
        text = repr(sorted((key, repr(value)) for key, value in shape.items()))
        return hashlib.sha256(text.encode()).hexdigest()[:16]


def geometry_from_table(table: dict, where: str) -> ProstateGeometry:
    """Check a ``[geometry]`` table (types and ranges; the walls are checked by :func:`check_walls`)."""
    if not isinstance(table, dict):
        raise SceneError(f"{where}: [geometry] must be a table of the built-in prostate's parameters")
    fields = {f.name: f for f in dataclasses.fields(ProstateGeometry)}
    unknown = sorted(set(table) - set(fields))
    if unknown:
        raise SceneError(f"{where}: [geometry] has unknown keys {unknown}: use {', '.join(fields)}")
    values = {}
    for name, value in table.items():
        if name.endswith("_mm") and isinstance(fields[name].default, tuple):
            if (not isinstance(value, list | tuple) or len(value) != 3
                    or not all(_finite_number(item) for item in value)):
                raise SceneError(f"{where}: [geometry] {name} must be three numbers (x, y, z in mm), got {value!r}")
            if "semi_axes" in name and min(value) <= 0:
                raise SceneError(f"{where}: [geometry] {name} must be positive, got {value!r}")
            values[name] = tuple(float(item) for item in value)
            continue
        if not _finite_number(value):
            raise SceneError(f"{where}: [geometry] {name} must be a number, got {value!r}")
        low, high = {"base_chamber_scale": SCALE_RANGE, "lobe_chamber_scale": SCALE_RANGE,
                     "fixation_radius_mm": FIXATION_RADIUS_RANGE_MM,
                     "min_wall_mm": (MANUFACTURABLE_WALL_MM, 10.0), "mesh_size_mm": (0.3, 10.0)}[name]
        if not low <= value <= high:
            why = " (thinner walls cannot be cast)" if name == "min_wall_mm" else ""
            raise SceneError(f"{where}: [geometry] {name} = {value} is outside [{low:g}, {high:g}]{why}")
        values[name] = float(value)
    geometry = ProstateGeometry(**values)
    if geometry.lobe_chamber_centre_mm[0] <= 0:
        raise SceneError(f"{where}: [geometry] lobe_chamber_centre_mm must have x > 0 (the left lobe; the right "
                         f"one is its mirror image), got {list(geometry.lobe_chamber_centre_mm)}")
    return geometry


def _finite_number(value) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)


def wall_thicknesses_mm(geometry: ProstateGeometry) -> dict[str, float]:
    """The thinnest wall between each chamber and the outer surface, and between chambers (mm).

    Negative when a chamber breaks through the surface or two chambers overlap. Measured between samples of the
    surfaces 0.5 mm apart: the nearest sample lies within 0.35 mm of the nearest point along the surface, which
    overestimates a wall of 2 mm or more by under 0.05 mm.
    """
    import numpy as np
    from scipy.spatial import cKDTree

    from phantom.model.mesh.prostate import body_surface_points_mm, inside_body

    outer = cKDTree(body_surface_points_mm())
    samples = [_ellipsoid_points_mm(centre, axes) for centre, axes in geometry.ellipsoids_mm()]
    walls = {}
    for index, points in enumerate(samples):
        distance = float(outer.query(points)[0].min())
        walls[f"chamber{index}-outer"] = distance if np.all(inside_body(points)) else -distance
    ellipsoids = geometry.ellipsoids_mm()
    for first in range(len(samples)):
        for second in range(first + 1, len(samples)):
            distance = float(cKDTree(samples[second]).query(samples[first])[0].min())
            centre, axes = (np.asarray(value) for value in ellipsoids[first])
            overlapping = np.any(np.sum(((samples[second] - centre) / axes) ** 2, axis=1) < 1)
            walls[f"chamber{first}-chamber{second}"] = -distance if overlapping else distance
    return walls


def _ellipsoid_points_mm(centre, axes, spacing_mm: float = 0.5):
    import numpy as np

    largest = max(axes)
    n_polar = max(int(math.pi * largest / spacing_mm), 16)
    n_azimuth = 2 * n_polar
    polar = np.linspace(0.0, math.pi, n_polar)
    azimuth = np.linspace(0.0, 2 * math.pi, n_azimuth, endpoint=False)
    polar, azimuth = np.meshgrid(polar, azimuth, indexing="ij")
    unit = np.stack([np.sin(polar) * np.cos(azimuth), np.sin(polar) * np.sin(azimuth), np.cos(polar)], axis=-1)
    return (unit * np.asarray(axes) + np.asarray(centre)).reshape(-1, 3)


def check_walls(geometry: ProstateGeometry) -> dict[str, float]:
    """The walls (see :func:`wall_thicknesses_mm`), or MeshError naming the thinnest one below ``min_wall_mm``."""
    walls = wall_thicknesses_mm(geometry)
    name = min(walls, key=walls.get)
    if walls[name] < geometry.min_wall_mm:
        what = "breaks through" if walls[name] < 0 and "outer" in name else "overlaps" if walls[name] < 0 else ""
        detail = f"{what} ({walls[name]:.2f} mm)" if what else f"is {walls[name]:.2f} mm thick"
        raise MeshError(f"geometry: the wall {name} {detail}, below min_wall_mm = {geometry.min_wall_mm:g} mm: "
                        f"shrink or move the chambers")
    return walls
