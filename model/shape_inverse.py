"""The shape inverse: the chamber pressures that make the phantom look most like a given gland.

The volume inverse (:mod:`phantom.model.inverse`) asks for a volume; a trainer or a robot's validation asks for a
*gland*: this patient's lopsided enlargement. Given the target's closed surface (mm, the phantom's frame:
:mod:`phantom.model.shape_file` reads masks and meshes), the answer is the pressures in the box
``[0, pressure_max]^3`` and the target's pose that minimise the distance between the phantom's deformed outer
surface and the target.

**The distance** is the symmetric mean closest-point distance (mm): the area-weighted mean distance from the
phantom's surface to the target's and from the target's to the phantom's, averaged. Exact closest points on the
triangles (:class:`~phantom.model.mesh.surface.SurfaceIndex`) need no voxel grid whose resolution would floor the
answer, and the measure is what ``compare-scan`` and the shape analysis report, in mm. Both ways, because one way
alone is blind: a phantom inside a larger target is close to it everywhere seen from the phantom. It is minimised
as least squares of the same distances (Levenberg-Marquardt, smooth where the mean of absolute values is not);
the mean is what is reported.

**The registration** is rigid by default: the target keeps the orientation its file states (a mask's RAS axes, a
mesh in the phantom's frame) and is moved, from its centroid on the phantom's, by a rotation and translation fitted
together with the pressures. The orientation is taken from the file, not from the shape, because the phantom's
rest shape is nearly symmetric under a half turn about its long axis, which swaps the left and right lobes: a
shape-only start could grow the wrong lobe. A uniform scale is optional (``scale=True``) and reported apart: it is
off by default because the gland's size is what the pressures are to make, and a scale fitted with them would
explain a growth away.

**The speed** comes from the response table of the outer surface's shapes (the scene's ``[model] table_shapes``,
or :func:`~phantom.model.fidelity.response_table.build_table_shapes`): positions and their exact gradient in the
pressures in milliseconds, so each Levenberg-Marquardt step is one table lookup and two closest-point queries
(analytic Jacobian: point-to-plane residuals, the table's gradient carried through each closest point's barycentric
weights). The table's answer is then refined by full solves (``refine_solves``): at each solved point the table is
corrected by its own miss there (the solved surface minus the table's: a defect correction), and the least squares
are solved again on the corrected table; the answer is the last solved point, whose distance is the full model's.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from phantom import PhantomError
from phantom.model.arrays import FloatArray, IntArray
from phantom.model.fem.model import PhantomModel, State
from phantom.model.fidelity.response_table import (
    SurfaceShapes,
    build_table_shapes,
    shipped_table_shapes,
    stored_response_table,
)
from phantom.model.mesh.surface import (
    SurfaceIndex,
    TriangleMesh,
    enclosed_volume_ml,
    rotation_angle_deg,
    rotation_from_vector,
    vertex_areas_mm2,
)
from phantom.model.shape_file import checked_gland

#: Target points used (area-weighted draw) when its surface has more vertices.
MAX_TARGET_POINTS = 4000
#: Levenberg-Marquardt's iterations (each a table lookup and two closest-point queries), and its stop: a step that
#: changes the cost by less than this fraction.
MAX_ITERATIONS = 60
COST_TOLERANCE = 1e-7
#: Refinement stops when a full solve's pressures are this close (Pa) to the ones before.
REFINE_TOLERANCE_PA = 5.0
#: Full solves of the refinement by default.
REFINE_SOLVES = 3
#: The regions of the per-region error, on the phantom's rest surface: the base is the top third in z (toward the
#: base, where chamber 0 sits); the rest is split at the mid-sagittal plane into the left (+x) and right lobes.
REGIONS = ("base", "left", "right")
BASE_FRACTION = 1.0 / 3.0
#: Pressure axis scale (Pa) of the solver's variables, so that a kilopascal and a millimetre weigh alike.
PRESSURE_SCALE_PA = 1e3
#: Starting points per axis of the grid search over the box (the table's own grid on builtin:converged).
START_POINTS = 4


class ShapeInverseError(PhantomError):
    """A shape inverse that cannot be posed (a model without the surface's shapes, a bad target)."""


#: ``surface(pressures_pa) -> (positions_mm (n, 3), d positions / d p (3, n, 3) mm/Pa)`` of the phantom's surface.
SurfaceModel = Callable[[FloatArray], tuple[FloatArray, FloatArray]]


@dataclass
class Pose:
    """Where the target is put in the phantom's frame: ``x = scale * rotation @ (q - centroid) + translation_mm``
    for a target point ``q`` (mm), ``centroid`` the target's own."""

    rotation: FloatArray
    translation_mm: FloatArray
    scale: float = 1.0

    def moved(self, points_mm: FloatArray, centroid_mm: FloatArray) -> FloatArray:
        moved: FloatArray = self.scale * (points_mm - centroid_mm) @ self.rotation.T + self.translation_mm
        return moved

    def stepped(self, omega: FloatArray, shift_mm: FloatArray, log_scale: float) -> Pose:
        """The pose after a small rotation ``omega`` (rad) about the target's placed centroid, a shift (mm) and a
        scale change ``exp(log_scale)``."""
        return Pose(rotation_from_vector(omega) @ self.rotation, self.translation_mm + shift_mm,
                    self.scale * float(np.exp(log_scale)))


@dataclass
class Match:
    """The distances between the phantom's surface at some pressures and the placed target.

    ``phantom_signed_mm`` (n,): each phantom surface node's signed distance to the target (+: the phantom is
    outside it, too large there; -: inside, the target reaches beyond); ``target_mm`` (m,): each target point's
    distance to the phantom; the weights are area shares summing to 1 on each side.
    """

    phantom_signed_mm: FloatArray
    target_mm: FloatArray
    phantom_weights: FloatArray
    target_weights: FloatArray

    @property
    def distance_mm(self) -> float:
        """The symmetric mean closest-point distance (mm)."""
        return 0.5 * float(self.phantom_weights @ np.abs(self.phantom_signed_mm) + self.target_weights @ self.target_mm)

    @property
    def cost(self) -> float:
        """What the least squares minimise: half the sum of both sides' weighted mean squared distances (mm^2)."""
        return 0.5 * float(self.phantom_weights @ self.phantom_signed_mm**2 + self.target_weights @ self.target_mm**2)


@dataclass
class RegionError:
    """One region of the phantom's surface: its mean distance to the target (mm) and its mean signed distance (mm;
    -: the target reaches beyond the phantom there)."""

    mean_mm: float
    signed_mm: float


@dataclass
class ShapeInverseResult:
    """What the shape inverse answers (SI and mm; :meth:`to_json` in the units people read)."""

    pressures_pa: FloatArray
    distance_mm: float
    rest_distance_mm: float
    target_volume_ml: float
    rest_volume_ml: float
    volume_ml: float
    chamber_volumes_ml: FloatArray
    regions: dict[str, RegionError]
    rest_regions: dict[str, RegionError]
    pose: Pose
    at_limit: list[str]
    #: the phantom's surface at the answer (mm) and its triangles, with each node's signed distance (the residual)
    surface_mm: FloatArray
    triangles: IntArray
    residual_mm: FloatArray
    table_pressures_pa: FloatArray
    table_distance_mm: float
    table_time_s: float
    #: the table's part's CPU time (s): its wall time on a loaded machine includes the waits for a core
    table_cpu_s: float
    #: each full solve of the refinement: (pressures Pa, the full model's distance mm there)
    refinement: list[tuple[FloatArray, float]] = field(default_factory=list)
    refine_time_s: float = 0.0
    notes: list[str] = field(default_factory=list)

    @property
    def solves(self) -> int:
        return len(self.refinement)

    def to_json(self, chamber_names: list[str]) -> dict[str, Any]:
        """The answer as plain numbers in kPa, mm and ml."""
        def regions(values: dict[str, RegionError]) -> dict[str, dict[str, float]]:
            return {name: {"mean_mm": error.mean_mm, "signed_mm": error.signed_mm} for name, error in values.items()}

        return {
            "pressures_kpa": (self.pressures_pa / 1e3).tolist(),
            "chambers": list(chamber_names),
            "distance_mm": self.distance_mm,
            "rest_distance_mm": self.rest_distance_mm,
            "target_volume_ml": self.target_volume_ml,
            "rest_volume_ml": self.rest_volume_ml,
            "volume_ml": self.volume_ml,
            "chamber_volumes_ml": self.chamber_volumes_ml.tolist(),
            "regions": regions(self.regions),
            "rest_regions": regions(self.rest_regions),
            "registration": {"kind": "rigid+scale" if self.pose.scale != 1.0 else "rigid",
                             "rotation_deg": rotation_angle_deg(self.pose.rotation),
                             "rotation": self.pose.rotation.tolist(),
                             "translation_mm": self.pose.translation_mm.tolist(), "scale": self.pose.scale},
            "at_limit": self.at_limit,
            "table_pressures_kpa": (self.table_pressures_pa / 1e3).tolist(),
            "table_distance_mm": self.table_distance_mm,
            "table_time_s": self.table_time_s,
            "table_cpu_s": self.table_cpu_s,
            "refinement": [{"pressures_kpa": (pressures / 1e3).tolist(), "distance_mm": distance}
                           for pressures, distance in self.refinement],
            "refine_time_s": self.refine_time_s,
            "notes": self.notes,
        }


def _barycentric(points: FloatArray, corners: FloatArray) -> FloatArray:
    """Barycentric weights (n, 3) of points (n, 3) on (their closest points in) triangles with corners (n, 3, 3)."""
    a, b, c = corners[:, 0], corners[:, 1], corners[:, 2]
    v0, v1, v2 = b - a, c - a, points - a
    d00, d01, d11 = (np.einsum("ij,ij->i", x, y) for x, y in ((v0, v0), (v0, v1), (v1, v1)))
    d20, d21 = np.einsum("ij,ij->i", v2, v0), np.einsum("ij,ij->i", v2, v1)
    denominator = np.where(np.abs(d00 * d11 - d01**2) > 1e-300, d00 * d11 - d01**2, 1.0)
    v = (d11 * d20 - d01 * d21) / denominator
    w = (d00 * d21 - d01 * d20) / denominator
    weights: FloatArray = np.clip(np.stack([1.0 - v - w, v, w], axis=1), 0.0, 1.0)
    normalised: FloatArray = weights / weights.sum(axis=1, keepdims=True)
    return normalised


def surface_shapes(model: PhantomModel, pressure_max_pa: float | None = None,
                   progress: Callable[[int, int], None] | None = None, build: bool = True) -> SurfaceShapes:
    """The outer surface's shapes over the box for the shape inverse: those the scene ships (``[model]
    table_shapes``), else those of the model's response table in the disk cache, else built (64 full solves,
    ``progress(done, total)`` told; minutes on a fine mesh) or, without ``build``, ShapeInverseError."""
    pressure_max = float(model.model_settings.pressure_max_pa if pressure_max_pa is None else pressure_max_pa)
    shipped = shipped_table_shapes(model, pressure_max)
    if shipped is not None:
        return shipped
    stored = stored_response_table(model, pressure_max, model.model_settings.table_points)
    full = stored if stored is not None and stored.position_values is not None else None
    if full is None and not build:
        raise ShapeInverseError("the scene ships no table of its outer surface's shapes ([model] table_shapes) and "
                                "none is cached: write one first (phantom model table SCENE --shapes-out FILE), "
                                "or use phantom inverse --shape, which builds it")
    return build_table_shapes(model, pressure_max, progress=progress, table=full)


class ShapeInverse:
    """The shape inverse of one model (see the module).

    Parameters
    ----------
    model : PhantomModel
    shapes : SurfaceShapes
        The outer surface's shapes over the box (the scene's shipped ``table_shapes``, or built).
    pressure_max_pa : float, optional
        The box's upper bound per chamber (Pa; default: the shapes' table's).
    """

    def __init__(self, model: PhantomModel, shapes: SurfaceShapes, pressure_max_pa: float | None = None):
        self.model = model
        self.nodes, self.triangles = model.outer_surface()
        if shapes.positions_m(np.zeros(model.n_chambers), self.nodes) is None:
            raise ShapeInverseError("the table of shapes does not hold the model's outer surface: build it for this "
                                    "model (phantom model table SCENE --shapes-out FILE)")
        self.shapes = shapes
        table = shapes.table
        where = np.searchsorted(shapes.nodes, self.nodes)
        self._where = where
        self.pressure_max_pa = float(table.pressure_max_pa if pressure_max_pa is None else pressure_max_pa)
        if not 0.0 < self.pressure_max_pa <= table.pressure_max_pa * (1 + 1e-9):
            raise ShapeInverseError(f"the pressure limit {self.pressure_max_pa / 1e3:g} kPa is outside the table of "
                                    f"shapes' box (0-{table.pressure_max_pa / 1e3:g} kPa)")
        rest_mm = np.asarray(model.nodes_m, float)[self.nodes] * 1e3
        self.rest_mm = rest_mm
        areas = vertex_areas_mm2(rest_mm, self.triangles)
        self.phantom_weights = areas / areas.sum()
        low, high = rest_mm[:, 2].min(), rest_mm[:, 2].max()
        base = rest_mm[:, 2] >= high - BASE_FRACTION * (high - low)
        self.region_of = {"base": base, "left": ~base & (rest_mm[:, 0] >= 0.0), "right": ~base & (rest_mm[:, 0] < 0.0)}
        self.rest_volume_ml = float(model.rest_gland_volume_m3) * 1e6
        self._states: list[State] = []

    # ------------------------------------------------------------------ the surface
    def table_surface(self, pressures_pa: FloatArray) -> tuple[FloatArray, FloatArray]:
        """The table's surface positions (mm) at ``pressures_pa`` and their gradient (mm/Pa, (3, n, 3))."""
        table = self.shapes.table
        assert table.position_values is not None
        bases = table._bases(np.asarray(pressures_pa, float))
        values = table.position_values
        positions = table._value(values, np.asarray(pressures_pa, float), bases)[self._where] * 1e3
        gradient = table._gradient(values, bases[0])[:, self._where] * 1e3
        return positions, gradient

    def solved_state(self, pressures_pa: FloatArray) -> State:
        """The full model's equilibrium at ``pressures_pa``, started from the nearest one solved before."""
        nearest = min(self._states, default=None,
                      key=lambda state: float(np.max(np.abs(state.pressures_pa - pressures_pa))))
        state = self.model.equilibrium(pressures_pa, initial_positions_m=None if nearest is None
                                       else nearest.positions_m)
        self._states.append(state)
        return state

    # ------------------------------------------------------------------ the target
    def prepared(self, target: TriangleMesh, seed: int = 0) -> _Target:
        """The target's points, weights and index (a large surface drawn down to MAX_TARGET_POINTS by area)."""
        vertices = np.asarray(target.vertices_mm, float)
        areas = vertex_areas_mm2(vertices, target.triangles)
        if len(vertices) > MAX_TARGET_POINTS:
            rng = np.random.default_rng(seed)
            chosen = rng.choice(len(vertices), MAX_TARGET_POINTS, replace=False, p=areas / areas.sum())
            points, weights = vertices[chosen], np.full(MAX_TARGET_POINTS, 1.0 / MAX_TARGET_POINTS)
        else:
            points, weights = vertices, areas / areas.sum()
        centroid = (areas / areas.sum()) @ vertices
        return _Target(target, SurfaceIndex(vertices, target.triangles), points, weights, centroid,
                       abs(enclosed_volume_ml(target)))

    # ------------------------------------------------------------------ distances
    def match(self, phantom_mm: FloatArray, target: _Target, pose: Pose) -> tuple[Match, _Linear]:
        """The distances both ways, and what their linearisation needs."""
        # phantom -> target: the phantom's nodes taken into the target's own frame, where its index was built
        inverse = (phantom_mm - pose.translation_mm) @ pose.rotation / pose.scale + target.centroid_mm
        distance, closest, triangle = target.index.closest(inverse)
        distance = distance * pose.scale
        closest_placed = pose.moved(closest, target.centroid_mm)
        away = phantom_mm - closest_placed
        normals_here = target.index.face_normals[triangle] @ pose.rotation.T
        sign = np.where(np.einsum("ij,ij->i", away, normals_here) >= 0.0, 1.0, -1.0)
        direction = np.where(distance[:, None] > 1e-9, away / np.maximum(distance, 1e-300)[:, None], normals_here)
        signed = sign * distance
        # target -> phantom: closest points on the phantom's surface as it is at these pressures
        placed = pose.moved(target.points_mm, target.centroid_mm)
        phantom_index = SurfaceIndex(phantom_mm, self.triangles)
        back, on_phantom, phantom_triangle = phantom_index.closest(placed)
        corners = self.triangles[phantom_triangle]
        back_direction = np.where(back[:, None] > 1e-9, (placed - on_phantom) / np.maximum(back, 1e-300)[:, None],
                                  phantom_index.face_normals[phantom_triangle])
        weights = _barycentric(on_phantom, phantom_mm[corners])
        result = Match(signed, back, self.phantom_weights, target.weights)
        return result, _Linear(direction * sign[:, None], closest_placed, placed, back_direction, corners, weights)

    def rough_cost(self, phantom_mm: FloatArray, target: _Target, pose: Pose) -> float:
        """:attr:`Match.cost` with nearest vertices for closest points: the grid search's cheap stand-in (exact
        closest points far from a surface examine many triangles)."""
        # scipy.spatial (0.1 s to import) only where a target is matched
        from scipy.spatial import cKDTree

        placed = pose.moved(target.points_mm, target.centroid_mm)
        to_target, _ = cKDTree(placed).query(phantom_mm)
        to_phantom, _ = cKDTree(phantom_mm).query(placed)
        return 0.5 * float(self.phantom_weights @ np.square(to_target) + target.weights @ np.square(to_phantom))

    def _jacobian(self, gradient: FloatArray, linear: _Linear, pose: Pose,
                  scale: bool) -> tuple[FloatArray, FloatArray]:
        """d(residuals)/d(pressures in kPa, rotation rad, shift mm[, log scale]) of the signed residuals of both
        sides (rows: phantom nodes, then target points)."""
        pivot = pose.translation_mm
        n1, n2 = linear.phantom_direction, linear.target_direction
        # phantom side: d = n1 . (x - c); x moves with the pressures, c with the target's pose
        phantom_p = np.einsum("jnk,nk->nj", gradient, n1) * PRESSURE_SCALE_PA
        phantom_pose = [-np.cross(linear.closest_placed - pivot, n1), -n1]
        # target side: d = n2 . (q - b); q moves with the pose, b (on the phantom) with the pressures
        moved_b = np.einsum("nc,jnck->njk", linear.barycentric, gradient[:, linear.corners])
        target_p = -np.einsum("njk,nk->nj", moved_b, n2) * PRESSURE_SCALE_PA
        target_pose = [np.cross(linear.placed - pivot, n2), n2]
        if scale:
            phantom_pose.append(-np.einsum("ij,ij->i", linear.closest_placed - pivot, n1)[:, None])
            target_pose.append(np.einsum("ij,ij->i", linear.placed - pivot, n2)[:, None])
        return np.hstack([phantom_p, *phantom_pose]), np.hstack([target_p, *target_pose])

    # ------------------------------------------------------------------ least squares
    def fit(self, surface: SurfaceModel, target: _Target, pressures_pa: FloatArray, pose: Pose,
            free_pressures: bool = True, scale: bool = False) -> tuple[FloatArray, Pose, Match]:
        """Levenberg-Marquardt over the pressures (within the box; fixed when not ``free_pressures``) and the
        target's pose, from a start; the active bounds are held while a step pushes against them."""
        n = self.model.n_chambers
        pressures = np.clip(np.asarray(pressures_pa, float), 0.0, self.pressure_max_pa)
        positions, gradient = surface(pressures)
        current, linear = self.match(positions, target, pose)
        damping = 1e-3
        for _ in range(MAX_ITERATIONS):
            phantom_rows, target_rows = self._jacobian(gradient, linear, pose, scale)
            w1, w2 = np.sqrt(0.5 * current.phantom_weights), np.sqrt(0.5 * current.target_weights)
            jacobian = np.vstack([phantom_rows * w1[:, None], target_rows * w2[:, None]])
            residual = np.concatenate([current.phantom_signed_mm * w1, current.target_mm * w2])
            if not free_pressures:
                jacobian[:, :n] = 0.0
            normal, slope = jacobian.T @ jacobian, jacobian.T @ residual
            improved = False
            for _ in range(12):
                free = np.ones(len(slope), bool)
                if not free_pressures:
                    free[:n] = False
                step = np.zeros(len(slope))
                for _ in range(n + 1):  # hold the bounds a step would cross, solve again for the rest
                    system = normal[np.ix_(free, free)] + damping * np.diag(np.diag(normal)[free] + 1e-9)
                    step[:] = 0.0
                    step[free] = np.linalg.solve(system, -slope[free])
                    trial_p = pressures + step[:n] * PRESSURE_SCALE_PA
                    blocked = free[:n] & (((trial_p < 0.0) & (pressures <= 1e-9))
                                          | ((trial_p > self.pressure_max_pa)
                                             & (pressures >= self.pressure_max_pa - 1e-9)))
                    if not blocked.any():
                        break
                    free[:n] &= ~blocked
                trial_pressures = np.clip(pressures + step[:n] * PRESSURE_SCALE_PA, 0.0, self.pressure_max_pa)
                trial_pose = pose.stepped(step[n:n + 3], step[n + 3:n + 6], float(step[n + 6]) if scale else 0.0)
                trial_positions, trial_gradient = surface(trial_pressures)
                trial, trial_linear = self.match(trial_positions, target, trial_pose)
                if trial.cost <= current.cost:
                    change = (current.cost - trial.cost) / max(current.cost, 1e-300)
                    pressures, pose, current, linear, gradient = (trial_pressures, trial_pose, trial, trial_linear,
                                                                  trial_gradient)
                    damping = max(damping / 3.0, 1e-9)
                    improved = change > COST_TOLERANCE
                    break
                damping *= 10.0
            if not improved:
                break
        return pressures, pose, current

    def start_pose(self, target: _Target) -> Pose:
        """The target as its file orients it, its centroid on the phantom's rest surface's."""
        centroid = self.phantom_weights @ self.rest_mm
        return Pose(np.eye(3), centroid.copy())

    def regions(self, match: Match) -> dict[str, RegionError]:
        """Each region's mean and mean signed distance (mm) of the phantom's surface to the target."""
        errors = {}
        for name in REGIONS:
            inside = self.region_of[name]
            weights = match.phantom_weights[inside] / match.phantom_weights[inside].sum()
            errors[name] = RegionError(float(weights @ np.abs(match.phantom_signed_mm[inside])),
                                       float(weights @ match.phantom_signed_mm[inside]))
        return errors

    def solve(self, target_surface: TriangleMesh, refine_solves: int = REFINE_SOLVES, scale: bool = False,
              progress: Callable[[str], None] | None = None) -> ShapeInverseResult:
        """The pressures and pose that bring the phantom's surface closest to ``target_surface`` (see the module):
        from the table, then ``refine_solves`` full solves at most (0: the table's answer, without a full solve).
        ShapeFileError for a target that is not a gland's closed surface in mm (:func:`checked_gland`)."""
        if refine_solves < 0:
            raise ShapeInverseError(f"refine_solves must be 0 or more, got {refine_solves}")
        # checked here, whoever made the surface (a file, a request, a library user's mesh): a target in cm
        # (0.026 ml) came back as 0, 0, 0 kPa at 12.4 mm without a word
        target_surface = checked_gland(target_surface, "the target surface")
        say = progress or (lambda message: None)
        started, started_cpu = time.perf_counter(), time.process_time()
        target = self.prepared(target_surface)
        n = self.model.n_chambers
        rest = np.zeros(n)
        pose = self.start_pose(target)
        _, pose, rest_match = self.fit(self.table_surface, target, rest, pose, free_pressures=False, scale=scale)
        rest_pose = pose
        # the start: the best point of a coarse grid over the box with the target placed at rest, then the whole fit
        axis = np.linspace(0.0, self.pressure_max_pa, START_POINTS)
        grid = np.stack(np.meshgrid(*[axis] * n, indexing="ij"), axis=-1).reshape(-1, n)
        costs = [self.rough_cost(self.table_surface(point)[0], target, pose) for point in grid]
        start = grid[int(np.argmin(costs))]
        pressures, pose, table_match = self.fit(self.table_surface, target, start, pose, scale=scale)
        if table_match.distance_mm > rest_match.distance_mm:
            # the rest is a point of the box too: a whole fit that ends farther keeps the rest's fit (two fits that
            # both end at 0 kPa stop nanometres apart, and a reach table read the farther one as pressures that
            # made the case worse)
            pressures, pose, table_match = rest.copy(), rest_pose, rest_match
        table_time_s, table_cpu_s = time.perf_counter() - started, time.process_time() - started_cpu
        say(f"shape inverse: table answer {np.round(pressures / 1e3, 3).tolist()} kPa, distance "
            f"{table_match.distance_mm:.3f} mm (rest {rest_match.distance_mm:.3f} mm), {table_time_s:.2f} s "
            f"({table_cpu_s:.2f} s CPU)")
        table_pressures = pressures.copy()
        refinement: list[tuple[FloatArray, float]] = []
        solved_match, state = table_match, None
        refine_started = time.perf_counter()
        positions_mm = self.table_surface(pressures)[0]
        for solve in range(refine_solves):
            state = self.solved_state(pressures)
            solved_mm = np.asarray(state.positions_m, float)[self.nodes] * 1e3
            corrected = self._corrected(solved_mm - self.table_surface(pressures)[0])
            # the full model's distance here, the pose fitted to its surface
            _, pose, solved_match = self.fit(corrected, target, pressures, pose, free_pressures=False, scale=scale)
            positions_mm = solved_mm
            refinement.append((pressures.copy(), solved_match.distance_mm))
            say(f"shape inverse: full solve {solve + 1}/{refine_solves} at {np.round(pressures / 1e3, 3).tolist()} "
                f"kPa: distance {solved_match.distance_mm:.3f} mm")
            if solve == refine_solves - 1:
                break
            following, following_pose, _ = self.fit(corrected, target, pressures, pose, scale=scale)
            if np.max(np.abs(following - pressures)) < REFINE_TOLERANCE_PA:
                break
            pressures, pose = following, following_pose
        if state is not None:
            chamber_m3, gland_m3 = np.asarray(state.chamber_volumes_m3, float), float(state.gland_volume_m3)
        else:
            chamber_m3, gland_m3 = self._table_volumes(pressures)
        final = solved_match
        at_limit = [f"{self.model.chamber_names[index]} at {'0' if pressures[index] <= 1e-6 else 'its limit'}"
                    for index in range(n) if pressures[index] <= 1e-6
                    or pressures[index] >= self.pressure_max_pa - 1e-6]
        notes = []
        if any("limit" in entry for entry in at_limit):
            notes.append(f"the target lies beyond what the phantom can show: the closest it reaches within the box "
                         f"(0-{self.pressure_max_pa / 1e3:g} kPa) is {final.distance_mm:.2f} mm away "
                         f"({', '.join(entry for entry in at_limit if 'limit' in entry)})")
        return ShapeInverseResult(
            pressures, final.distance_mm, rest_match.distance_mm, target.volume_ml * pose.scale**3,
            self.rest_volume_ml, gland_m3 * 1e6, chamber_m3 * 1e6, self.regions(final), self.regions(rest_match),
            pose, at_limit, positions_mm, self.triangles, final.phantom_signed_mm, table_pressures,
            table_match.distance_mm, table_time_s, table_cpu_s, refinement, time.perf_counter() - refine_started,
            notes)

    def _corrected(self, miss_mm: FloatArray) -> SurfaceModel:
        """The table's surface moved by its miss ``miss_mm`` (n, 3) at a solved point: the defect correction."""
        def surface(pressures_pa: FloatArray) -> tuple[FloatArray, FloatArray]:
            positions, gradient = self.table_surface(pressures_pa)
            return positions + miss_mm, gradient
        return surface

    def _table_volumes(self, pressures_pa: FloatArray) -> tuple[FloatArray, float]:
        chambers, gland = self.shapes.table.volumes(pressures_pa)
        return np.asarray(chambers, float), float(gland)


@dataclass
class _Target:
    surface: TriangleMesh
    index: SurfaceIndex
    points_mm: FloatArray
    weights: FloatArray
    centroid_mm: FloatArray
    volume_ml: float


@dataclass
class _Linear:
    phantom_direction: FloatArray
    closest_placed: FloatArray
    placed: FloatArray
    target_direction: FloatArray
    corners: IntArray
    barycentric: FloatArray
