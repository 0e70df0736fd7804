"""Parameters of the built-in prostate's geometry: a scene's ``[geometry]`` table, checked, and its walls.

The body (a tapered chestnut of 26.3 ml, see :mod:`phantom.model.mesh.shape`) is fixed; what a scene may change is
where the three ellipsoidal chambers sit and how large they are, and the fixation patch:

    [geometry]
    base_chamber_centre_mm = [0.0, 0.0, 11.0]       # chamber 0, on the mid-sagittal plane x = 0
    base_chamber_semi_axes_mm = [12.5, 8.5, 4.5]
    lobe_chamber_centre_mm = [8.7, 0.0, -2.5]       # chamber 1 (left lobe, x > 0); chamber 2 is its mirror
    lobe_chamber_semi_axes_mm = [5.7, 7.5, 6.5]
    base_chamber_scale = 1.0                        # multiplies the base chamber's semi-axes
    lobe_chamber_scale = 1.0                        # multiplies both lobe chambers' semi-axes
    fixation_radius_mm = 6.0                        # the fixed patch around the base pole
    min_wall_mm = 2.0                               # the thinnest wall allowed (a lost-wax cast makes 1 mm)
    mesh_size_mm = 2.5                              # element size, the one knob that refines the whole mesh
    element_order = 1                               # 1: 4-node tetrahedra; 2: 10-node (quadratic) ones

Every wall (chamber to outer surface, chamber to chamber) must be at least ``min_wall_mm`` thick, itself at
least :data:`MANUFACTURABLE_WALL_MM`: the thinnest wall a lost-wax cast makes (the wax core melts out, so
nothing is pulled through the wall); the design default of 2 mm leaves margin for a cast that is off by a
millimetre. Walls are
measured on samples of the surfaces (to about 0.05 mm) before meshing (:func:`phantom.model.mesh.shape.check_walls`),
so bad parameters give a one-line ``MeshError`` instead of a broken mesh. Only the standard library is imported at
module load: a scene is parsed without numpy.
"""

from __future__ import annotations

import dataclasses
import hashlib
from dataclasses import dataclass
from typing import Any

from phantom import is_finite_number
from phantom.model.errors import SceneError, check_known_keys, setting_refused

#: The thinnest silicone wall a lost-wax cast makes (mm).
MANUFACTURABLE_WALL_MM = 1.0
#: The element orders of the built-in mesh: 4-node and 10-node tetrahedra.
ELEMENT_ORDERS = (1, 2)
#: A point or the semi-axes of an ellipsoid (x, y, z), mm.
Vector3 = tuple[float, float, float]
#: Bounds of each scalar parameter (mm or dimensionless), beyond which the body cannot hold the chamber.
SCALE_RANGE = (0.3, 2.5)
FIXATION_RADIUS_RANGE_MM = (1.0, 15.0)
#: The element sizes (mm) the built-in mesh is made at.
MESH_SIZE_RANGE_MM = (0.3, 10.0)


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
    min_wall_mm: float = 2.0
    mesh_size_mm: float = 2.5
    element_order: int = 1

    def ellipsoids_mm(self) -> tuple[tuple[Vector3, Vector3], ...]:
        """(centre, semi-axes) of chambers 0, 1 (left, x > 0) and 2 (right, the mirror of 1), scales applied."""
        a, b, c = self.base_chamber_semi_axes_mm
        base_axes = (self.base_chamber_scale * a, self.base_chamber_scale * b, self.base_chamber_scale * c)
        a, b, c = self.lobe_chamber_semi_axes_mm
        lobe_axes = (self.lobe_chamber_scale * a, self.lobe_chamber_scale * b, self.lobe_chamber_scale * c)
        x, y, z = self.lobe_chamber_centre_mm
        return ((self.base_chamber_centre_mm, base_axes), ((x, y, z), lobe_axes), ((-x, y, z), lobe_axes))

    def with_values(self, **values: Any) -> ProstateGeometry:
        """A copy with some parameters changed (checked like a scene's table)."""
        return geometry_from_table({**self.as_table(), **values}, "geometry")

    def as_table(self) -> dict[str, Any]:
        """The scene's ``[geometry]`` table for this geometry (lists for the vectors)."""
        return {key: list(value) if isinstance(value, tuple) else value
                for key, value in dataclasses.asdict(self).items()}

    @property
    def key(self) -> str:
        """A short hash of the shape's parameters (not the element size or order): the mesh cache's name for it."""
        shape = {key: value for key, value in dataclasses.asdict(self).items()
                 if key not in ("mesh_size_mm", "element_order")}
        text = repr(sorted((key, repr(value)) for key, value in shape.items()))
        return hashlib.sha256(text.encode()).hexdigest()[:16]


def geometry_from_table(table: dict[str, Any], where: str) -> ProstateGeometry:
    """Check a ``[geometry]`` table (types and ranges; the walls are checked by
    :func:`phantom.model.mesh.shape.check_walls`)."""
    if not isinstance(table, dict):
        raise SceneError(f"{where}: [geometry] must be a table of the built-in prostate's parameters")
    fields = {f.name: f for f in dataclasses.fields(ProstateGeometry)}
    check_known_keys(table, fields, "[geometry]", where)
    values: dict[str, Any] = {}
    for name, value in table.items():
        if name.endswith("_mm") and isinstance(fields[name].default, tuple):
            if (not isinstance(value, list | tuple) or len(value) != 3
                    or not all(is_finite_number(item) for item in value)):
                raise setting_refused(where, "geometry", name, "must be three numbers (x, y, z in mm)", value)
            if "semi_axes" in name and min(value) <= 0:
                raise setting_refused(where, "geometry", name, "must be positive", value)
            values[name] = tuple(float(item) for item in value)
            continue
        if name == "element_order":
            if value not in ELEMENT_ORDERS or isinstance(value, bool) or not float(value).is_integer():
                raise setting_refused(where, "geometry", name, "must be 1 (4-node tetrahedra) or 2 (10-node, "
                                      "quadratic)", value)
            values[name] = int(value)
            continue
        if not is_finite_number(value):
            raise setting_refused(where, "geometry", name, "must be a number", value)
        low, high = {"base_chamber_scale": SCALE_RANGE, "lobe_chamber_scale": SCALE_RANGE,
                     "fixation_radius_mm": FIXATION_RADIUS_RANGE_MM,
                     "min_wall_mm": (MANUFACTURABLE_WALL_MM, 10.0), "mesh_size_mm": MESH_SIZE_RANGE_MM}[name]
        if not low <= value <= high:
            why = " (thinner walls cannot be cast)" if name == "min_wall_mm" else ""
            raise setting_refused(where, "geometry", name, f"must lie in [{low:g}, {high:g}]{why}", value)
        values[name] = float(value)
    geometry = ProstateGeometry(**values)
    if geometry.lobe_chamber_centre_mm[0] <= 0:
        raise setting_refused(where, "geometry", "lobe_chamber_centre_mm", "must have x > 0 (the left lobe; the right "
                              "one is its mirror image)", list(geometry.lobe_chamber_centre_mm))
    return geometry
