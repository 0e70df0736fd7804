"""The chambers, placed in the gland's own anatomy and sized as the walls allow (mm, the phantom's frame).

The built-in prostate's chambers are the template: a flat base chamber on the mid-sagittal plane toward the base and
one chamber in each lateral lobe; a design takes any non-empty subset of them (``--chambers``), named ``chamber0,
chamber1, ...`` in the order given. Each template ellipsoid's centre and semi-axes are taken as fractions of the
built-in body's half-extents and laid into the gland's: along each axis, the extent on the side the centre lies (the
left lobe's chamber takes the gland's extent to the left of the mid-sagittal plane, the right one the extent to the
right, the base chamber the extent toward the base), so an asymmetric gland gets asymmetric chambers and the
built-in body gets its own chambers back. ``chamber_scale`` multiplies every semi-axis; then every chamber whose wall
(to the outer surface, or to another chamber) is below ``min_wall_mm`` shrinks about its centre until none is, and
each grows back in turn (bisection of its scale, up to ``chamber_scale``) to the largest its own walls allow: the
shrinking alone overshoots, shrinking both chambers of a thin wall between them, and left the bilobed test gland's lobe
chambers with 2.9 and 3.2 mm walls at a 2 mm minimum (4.45 ml of chambers where 5.79 ml fit). A chamber that must
shrink below :data:`SMALLEST_SCALE` of its template leaves no room: the gland is too small for its chambers at that
wall.

Walls are measured between dense samples of the surfaces (0.5 mm apart, as the built-in geometry's check does).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from phantom import require_extra
from phantom.design.errors import DesignError
from phantom.design.surface import Surface
from phantom.model.arrays import FloatArray
from phantom.model.mesh.geometry import ProstateGeometry, Vector3
from phantom.model.mesh.shape import (
    ANTERIOR_POSTERIOR_RATIO,
    HALF_LENGTH_MM,
    ellipsoid_points_mm,
    equator_radius_mm,
    profile_radius_mm,
)

#: The template's chambers: the names ``--chambers`` takes, and the names people see, in the template's order.
CHAMBER_KINDS = ("base", "left", "right")
CHAMBER_LABELS = ("base", "left lobe", "right lobe")
#: The template's index of the base chamber (its stem goes straight up; the others' tilt outward).
BASE = 0
#: A chamber may shrink to this fraction of its template's semi-axes (an eighth of its volume) before the gland is
#: said too small for its chambers.
SMALLEST_SCALE = 0.5
#: The range of ``--chamber-scale`` (times the template's semi-axes); the sizing searches it.
CHAMBER_SCALE_RANGE = (0.3, 2.5)
#: Each step of the shrinking multiplies a chamber's semi-axes by this.
SHRINK_STEP = 0.98
#: After the shrinking, each chamber grows back to its walls in turn: sweeps over the chambers, and the bisection's
#: relative tolerance of a chamber's scale (a semi-axis of 10 mm to 0.02 mm).
REGROW_SWEEPS = 2
REGROW_TOLERANCE = 0.002
#: Spacing of the surface samples walls are measured on (mm).
SAMPLE_SPACING_MM = 0.5


@dataclass(frozen=True)
class Chamber:
    """An ellipsoidal chamber: centre and semi-axes (mm, the phantom's frame, axis-aligned), and which of the
    template's chambers it is (``kind``: an index into CHAMBER_KINDS)."""

    centre_mm: Vector3
    semi_axes_mm: Vector3
    kind: int = BASE

    @property
    def label(self) -> str:
        return CHAMBER_LABELS[self.kind]

    @property
    def volume_ml(self) -> float:
        a, b, c = self.semi_axes_mm
        return float(4.0 / 3.0 * np.pi * a * b * c / 1e3)

    def scaled(self, factor: float) -> Chamber:
        a, b, c = self.semi_axes_mm
        return Chamber(self.centre_mm, (a * factor, b * factor, c * factor), self.kind)


def chamber_name(index: int) -> str:
    """The mesh's and the scene's name of a design's ``index``-th chamber."""
    return f"chamber{index}"


def parse_chamber_kinds(text: str) -> tuple[int, ...]:
    """``--chambers``: comma-separated names of CHAMBER_KINDS, each at most once, at least one; their indices."""
    names = [name.strip().lower() for name in text.split(",")]
    unknown = [name for name in names if name not in CHAMBER_KINDS]
    if not text.strip() or unknown:
        raise DesignError(f"--chambers takes one or more of {','.join(CHAMBER_KINDS)} (comma-separated); got "
                          f"{text!r}" + (f": {', '.join(repr(name) for name in unknown)} is not one" if text.strip()
                                         else ""))
    if len(set(names)) != len(names):
        raise DesignError(f"--chambers names a chamber twice: {text!r}; give each once")
    return tuple(CHAMBER_KINDS.index(name) for name in names)


def builtin_half_extents_mm() -> FloatArray:
    """The built-in body's half-extents along x, y, z (mm): it is symmetric about its bounding box's centre, 0."""
    t = np.linspace(-1.0, 1.0, 4001)
    widest = float(profile_radius_mm(t, equator_radius_mm()).max())
    return np.array([widest, ANTERIOR_POSTERIOR_RATIO * widest, HALF_LENGTH_MM])


def template_chambers(surface: Surface, chamber_scale: float = 1.0,
                      kinds: tuple[int, ...] = (0, 1, 2)) -> list[Chamber]:
    """The built-in chambers ``kinds`` laid into ``surface``'s extents (see the module docstring), semi-axes times
    ``chamber_scale``. ``surface`` is centred as :func:`~phantom.design.surface.read_gland` leaves it (its
    mid-sagittal plane x = 0)."""
    reference = builtin_half_extents_mm()
    plus = surface.vertices_mm.max(axis=0)
    minus = -surface.vertices_mm.min(axis=0)
    chambers = []
    template = ProstateGeometry().ellipsoids_mm()
    for kind in kinds:
        centre, axes = template[kind]
        fraction = np.asarray(centre) / reference
        side = np.where(fraction > 1e-9, plus, np.where(fraction < -1e-9, minus, 0.5 * (plus + minus)))
        placed = fraction * side
        semi_axes = np.asarray(axes) / reference * side * chamber_scale
        chambers.append(Chamber(_vector(placed), _vector(semi_axes), kind))
    return chambers


def _mm(point: Vector3) -> str:
    return ", ".join(f"{value:.1f}" for value in point) + " mm"


def _vector(values: FloatArray) -> Vector3:
    return (float(values[0]), float(values[1]), float(values[2]))


def surface_samples_mm(surface: Surface) -> FloatArray:
    """Points of ``surface`` no more than SAMPLE_SPACING_MM apart (its vertices, subdivided), mm."""
    with require_extra("design"):
        from trimesh import remesh

    vertices, _ = remesh.subdivide_to_size(surface.vertices_mm, surface.triangles, max_edge=SAMPLE_SPACING_MM,
                                           max_iter=20)
    return np.asarray(vertices, float)


def ellipsoid_distance_mm(points_mm: FloatArray, chamber: Chamber) -> FloatArray:
    """Each point's distance to the chamber's ellipsoidal surface (mm), negative inside it.

    The closest point ``x_i = a_i^2 y_i / (t + a_i^2)`` (``y`` the point about the centre) has the root ``t`` of
    ``sum (a_i y_i / (t + a_i^2))^2 = 1``, found by bisection (the sum falls monotonically in ``t`` above
    ``-min a_i^2``; Eberly's method): exact, where nearest samples would need a dense cloud and a slow search.
    """
    axes = np.asarray(chamber.semi_axes_mm)
    offset = np.abs(points_mm - np.asarray(chamber.centre_mm))
    squared = axes**2
    low = np.full(len(points_mm), -squared.min())
    high = axes.max() * np.linalg.norm(offset, axis=1) + 1e-9
    for _ in range(48):
        middle = 0.5 * (low + high)
        level = np.sum((axes * offset / (middle[:, None] + squared)) ** 2, axis=1)
        above = level > 1.0
        low = np.where(above, middle, low)
        high = np.where(above, high, middle)
    t = 0.5 * (low + high)
    closest = squared * offset / (t[:, None] + squared)
    distance = np.linalg.norm(closest - offset, axis=1)
    inside = np.sum((offset / axes) ** 2, axis=1) < 1.0
    result: FloatArray = np.where(inside, -distance, distance)
    return result


def least_ellipsoid_distance_mm(points_mm: FloatArray, chamber: Chamber) -> float:
    """The least of :func:`ellipsoid_distance_mm` over the points (mm; negative when one lies inside), solved only
    for the points that can hold it.

    A point at normalised radius ``r = |y / a|`` lies on the ellipsoid scaled by ``r``; a ball of radius ``rho``
    fits in the ellipsoid scaled by ``rho / a_min``, and ellipsoids of one shape add as their scales do, so the
    point is at least ``|r - 1| a_min`` from the surface, and at most as far as the surface along its ray from the
    centre, ``|y| |1 - 1/r|``. The least upper bound leaves the few points whose lower bound is below it (bisecting
    every sample of an outer surface was a third of ``phantom design``'s time)."""
    offset = np.asarray(points_mm, float) - np.asarray(chamber.centre_mm)
    axes = np.asarray(chamber.semi_axes_mm)
    radius = np.sqrt(np.sum((offset / axes) ** 2, axis=1))
    along_ray = np.linalg.norm(offset, axis=1) * np.abs(1.0 - 1.0 / np.maximum(radius, 1e-12))
    scaled = np.abs(radius - 1.0) * axes.min()
    outside = radius >= 1.0
    lower = np.where(outside, scaled, -along_ray)
    upper = np.where(outside, along_ray, -scaled)
    # (a micrometre of slack for the bounds' rounding: where both are equal, a sphere's, it may order them wrongly)
    candidates = lower <= upper.min() + 1e-3
    return float(ellipsoid_distance_mm(np.asarray(points_mm, float)[candidates], chamber).min())


def measure_walls(outer_samples_mm: FloatArray, chambers: list[Chamber]) -> dict[str, float]:
    """The thinnest wall between each chamber and the outer surface (``outer_samples_mm``: dense samples of it),
    and between chambers (mm); negative where a chamber breaks through the surface or two chambers overlap."""
    walls: dict[str, float] = {}
    for index, chamber in enumerate(chambers):
        walls[f"{chamber_name(index)}-outer"] = least_ellipsoid_distance_mm(outer_samples_mm, chamber)
    for first in range(len(chambers)):
        points = ellipsoid_points_mm(chambers[first].centre_mm, chambers[first].semi_axes_mm, SAMPLE_SPACING_MM)
        for second in range(first + 1, len(chambers)):
            distance = least_ellipsoid_distance_mm(points, chambers[second])
            walls[f"{chamber_name(first)}-{chamber_name(second)}"] = distance
    return walls


@dataclass(frozen=True)
class ChamberDesign:
    """The placed chambers, their walls (mm, see :func:`measure_walls`) and each one's scale of its template."""

    chambers: list[Chamber]
    walls_mm: dict[str, float]
    scales: list[float]


def place_chambers(surface: Surface, min_wall_mm: float, chamber_scale: float = 1.0,
                   samples_mm: FloatArray | None = None, kinds: tuple[int, ...] = (0, 1, 2)) -> ChamberDesign:
    """The template's chambers ``kinds`` in ``surface`` (see the module docstring), each shrunk until every wall
    is at least ``min_wall_mm``; DesignError when one must shrink below SMALLEST_SCALE of its template."""
    if not CHAMBER_SCALE_RANGE[0] <= chamber_scale <= CHAMBER_SCALE_RANGE[1]:
        raise DesignError(f"--chamber-scale {chamber_scale:g} is out of range: use 0.3 to 2.5 (1: the built-in "
                          f"prostate's proportions)")
    samples_mm = surface_samples_mm(surface) if samples_mm is None else samples_mm
    template = template_chambers(surface, chamber_scale, kinds)
    for chamber in template:
        if not surface.contains(np.asarray(chamber.centre_mm)):
            raise DesignError(f"the {chamber.label} chamber's place ({_mm(chamber.centre_mm)}) lies outside "
                              f"the gland: its shape is too far from a prostate's for the built-in chambers' layout")
    scales = [chamber_scale] * len(template)
    chambers = list(template)
    while True:
        walls = measure_walls(samples_mm, chambers)
        thin = [name for name, value in walls.items() if value < min_wall_mm]
        if not thin:
            break
        for index in range(len(chambers)):
            deficits = [min_wall_mm - walls[name] for name in thin if chamber_name(index) in name.split("-")]
            if deficits:
                # shrink by about the missing thickness over the longest semi-axis, at least by SHRINK_STEP
                factor = 1.0 - (max(deficits) + 0.02) / max(chambers[index].semi_axes_mm)
                scales[index] *= min(SHRINK_STEP, max(factor, 0.8))
                chambers[index] = template[index].scaled(scales[index] / chamber_scale)
        if min(scales) < SMALLEST_SCALE:
            index = int(np.argmin(scales))
            raise DesignError(
                f"the gland leaves no room for {_count(len(chambers))} with walls of {min_wall_mm:g} mm: the "
                f"{chambers[index].label} chamber would shrink to {scales[index]:.2f} of the built-in's proportions "
                f"(thinnest wall {', '.join(thin)}); design at a larger --volume-ml or a smaller --min-wall-mm")
    # the shrinking overshoots (a thin wall between two chambers shrinks both; a step takes the whole deficit):
    # each chamber grows back, in turn, to the largest scale up to the one asked that its own walls allow
    for _ in range(REGROW_SWEEPS):
        for index in range(len(chambers)):
            scales[index] = _largest_scale(index, chambers, template, scales[index], chamber_scale, samples_mm,
                                           min_wall_mm)
            chambers[index] = template[index].scaled(scales[index] / chamber_scale)
    return ChamberDesign(chambers, measure_walls(samples_mm, chambers), scales)


def _own_wall_mm(index: int, chambers: list[Chamber], outer_samples_mm: FloatArray) -> float:
    """The thinnest of chamber ``index``'s walls, to the outer surface and to each other chamber (mm)."""
    chamber = chambers[index]
    walls = [least_ellipsoid_distance_mm(outer_samples_mm, chamber)]
    points = ellipsoid_points_mm(chamber.centre_mm, chamber.semi_axes_mm, SAMPLE_SPACING_MM)
    walls += [least_ellipsoid_distance_mm(points, other) for other_index, other in enumerate(chambers)
              if other_index != index]
    return min(walls)


def _largest_scale(index: int, chambers: list[Chamber], template: list[Chamber], scale: float, most: float,
                   outer_samples_mm: FloatArray, min_wall_mm: float) -> float:
    """The largest scale of chamber ``index`` between ``scale`` (whose walls hold) and ``most`` whose walls are at
    least ``min_wall_mm``, the others as they are: bisection to REGROW_TOLERANCE of the scale."""

    def holds(trial: float) -> bool:
        others = list(chambers)
        others[index] = template[index].scaled(trial / most)
        return _own_wall_mm(index, others, outer_samples_mm) >= min_wall_mm

    if holds(most):
        return most
    low, high = scale, most
    while high - low > REGROW_TOLERANCE * low:
        middle = 0.5 * (low + high)
        low, high = (middle, high) if holds(middle) else (low, middle)
    return low


def _count(chambers: int) -> str:
    return {1: "one chamber", 2: "two chambers", 3: "three chambers"}[chambers]
