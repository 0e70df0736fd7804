"""Triangle surfaces in millimetres: areas, normals, enclosed volumes, exact closest points and rigid alignment.

What a scan comparison and a shape analysis both need from a surface, below either: a :class:`TriangleMesh`
(vertices ``(n, 3)`` in mm, triangles ``(k, 3)`` of vertex indices, outward when the surface is closed); its
areas, normals and volume; the exact closest point on it of many query points (:class:`SurfaceIndex`, a k-d
tree of triangle centroids and a numba point-triangle kernel); its principal frame; and the rigid motion that
brings another surface onto it (:func:`align`: a global start from the principal axes of both, trying all 24
axis-to-axis candidates, since a principal axis' sign and the order of two axes of similar extent are not
defined by the shape, then point-to-plane ICP on exact closest points).

Distances use an exact closest-point query: candidate triangles come from a k-d tree of triangle centroids and
are examined nearest first until the centroid distance minus the largest triangle radius exceeds the best
distance found.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, overload

import numpy as np

from phantom import PhantomError
from phantom.model.arrays import BoolArray, FloatArray, IntArray
from phantom.model.mesh.tetmesh import enclosed_volume_m3

if TYPE_CHECKING:
    from scipy.spatial import cKDTree

#: No alignment fits when the RMS distance left exceeds this fraction of the target surface's RMS radius.
FIT_RMS_LIMIT = 0.1
#: A second alignment (rotated by more than AMBIGUOUS_ANGLE_DEG from the best) whose RMS residual exceeds the
#: best's by less than 10 % of it, or by less than AMBIGUOUS_EXCESS_MM (a scanner's accuracy: a mesh's own
#: discretisation makes an exactly symmetric shape fit its mirror turn 0.06 mm worse), makes the alignment
#: ambiguous: the surface is close to symmetric under that rotation.
AMBIGUOUS_RESIDUAL_RATIO = 1.1
AMBIGUOUS_EXCESS_MM = 0.1
AMBIGUOUS_ANGLE_DEG = 10.0
#: Far starts refined in search of a second alignment before the best one is taken as the only one.
ALTERNATIVE_TRIES = 3
#: Moving points used by the global start (per candidate) and by the final ICP.
START_POINTS = 600
START_ITERATIONS = 8
ICP_POINTS = 5000
ICP_MAX_ITERATIONS = 50
#: Neighbour lists reach this many times the largest triangle radius (see SurfaceIndex.closest).
NEIGHBOUR_REACH_RADII = 2.5

#: ``correspond(points_mm (n, 3))`` -> distance (n,) mm, corresponding target point (n, 3) mm and the unit
#: direction along which the distance is measured (n, 3): what ICP minimises against.
Correspondence = Callable[[FloatArray], tuple[FloatArray, FloatArray, FloatArray]]
#: rotation (3, 3), translation (3,) mm, RMS distance (mm) and iterations of one ICP run.
IcpResult = tuple[FloatArray, FloatArray, float, int]


class AlignmentError(PhantomError):
    """No rigid motion brings one surface onto the other: the best leaves ``rms_mm`` of RMS distance, more than
    FIT_RMS_LIMIT of the target's size ``size_mm`` (its RMS radius)."""

    def __init__(self, rms_mm: float, size_mm: float):
        super().__init__(f"no rigid alignment fits the surfaces: the best leaves an RMS distance of {rms_mm:.2f} mm "
                         f"({100 * rms_mm / size_mm:.0f} % of the target's size)")
        self.rms_mm = rms_mm
        self.size_mm = size_mm


@dataclass
class TriangleMesh:
    """A triangle surface: ``vertices_mm`` (n, 3) in mm and ``triangles`` (k, 3) vertex indices (int64), each
    running counter-clockwise seen from outside when the surface is closed and oriented."""

    vertices_mm: FloatArray
    triangles: IntArray


# --- measures --------------------------------------------------------------------------------------------------


def triangle_areas_mm2(vertices_mm: FloatArray, triangles: IntArray) -> FloatArray:
    """The area (mm^2) of each triangle, (k,)."""
    a, b, c = (vertices_mm[triangles[:, k]] for k in range(3))
    areas: FloatArray = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
    return areas


def vertex_areas_mm2(vertices_mm: FloatArray, triangles: IntArray) -> FloatArray:
    """A third of the area of each triangle around a vertex (the vertex's share of the surface), (n,) mm^2."""
    areas = triangle_areas_mm2(vertices_mm, triangles)
    shares: FloatArray = np.asarray(np.bincount(triangles.ravel(), np.repeat(areas / 3.0, 3), len(vertices_mm)),
                                    dtype=np.float64)
    return shares


def vertex_normals(vertices_mm: FloatArray, triangles: IntArray) -> FloatArray:
    """Area-weighted unit vertex normals (n, 3) (outward for an outward-oriented surface)."""
    a, b, c = (vertices_mm[triangles[:, k]] for k in range(3))
    face = np.cross(b - a, c - a)
    normals = np.zeros_like(vertices_mm)
    for k in range(3):
        np.add.at(normals, triangles[:, k], face)
    unit: FloatArray = normals / np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-300)
    return unit


def enclosed_volume_ml(mesh: TriangleMesh) -> float:
    """The volume (ml) enclosed by a closed, outward-oriented surface in mm (negative when it faces inward)."""
    return enclosed_volume_m3(mesh.vertices_mm, mesh.triangles) * 1e-3


# --- building surfaces -----------------------------------------------------------------------------------------


def compact(vertices_mm: FloatArray, triangles: IntArray) -> TriangleMesh:
    """The surface of ``triangles`` alone: the vertices no triangle uses dropped, the others renumbered."""
    used = np.bincount(triangles.ravel(), minlength=len(vertices_mm)) > 0
    renumber = np.cumsum(used) - 1
    return TriangleMesh(vertices_mm[used], renumber[triangles].astype(np.int64))


def model_surface(positions_m: FloatArray, triangles: IntArray) -> TriangleMesh:
    """A surface of the model (its outer triangles, say) at node positions ``positions_m`` (n, 3) in m, as a mesh
    of its own in mm (only the nodes on it, in the order of their model indices)."""
    return compact(np.asarray(positions_m, dtype=float) * 1e3, np.asarray(triangles, np.int64))


@overload
def subdivide(vertices: FloatArray, triangles: IntArray, values: None = None) -> tuple[FloatArray, IntArray]: ...


@overload
def subdivide(vertices: FloatArray, triangles: IntArray,
              values: FloatArray) -> tuple[FloatArray, IntArray, FloatArray]: ...


def subdivide(vertices: FloatArray, triangles: IntArray, values: FloatArray | None = None
              ) -> tuple[FloatArray, IntArray] | tuple[FloatArray, IntArray, FloatArray]:
    """Split each triangle into four at its edge midpoints (the surface is unchanged); per-vertex ``values``
    are interpolated linearly. Returns (vertices, triangles) or (vertices, triangles, values)."""
    edges = np.sort(triangles[:, [[0, 1], [1, 2], [2, 0]]].reshape(-1, 2), axis=1)
    unique_edges, edge_of = np.unique(edges, axis=0, return_inverse=True)
    midpoint = len(vertices) + edge_of.reshape(-1, 3)
    new_vertices = np.vstack([vertices, 0.5 * (vertices[unique_edges[:, 0]] + vertices[unique_edges[:, 1]])])
    a, b, c = triangles.T
    ab, bc, ca = midpoint.T
    new_triangles = np.vstack([np.stack(t, axis=1) for t in ((a, ab, ca), (ab, b, bc), (ca, bc, c), (ab, bc, ca))])
    if values is None:
        return new_vertices, new_triangles
    new_values = np.concatenate([values, 0.5 * (values[unique_edges[:, 0]] + values[unique_edges[:, 1]])])
    return new_vertices, new_triangles, new_values


# --- frames and rotations --------------------------------------------------------------------------------------


def principal_frame(points_mm: FloatArray, weights: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Weighted centroid (3,) mm, principal axes (3, 3; columns, largest spread first, right-handed) and the
    variances along them (3,) mm^2 of points (n, 3) with weights (n,)."""
    weights = weights / weights.sum()
    centroid = weights @ points_mm
    offsets = points_mm - centroid
    variances, axes = np.linalg.eigh((offsets * weights[:, None]).T @ offsets)
    variances, axes = variances[::-1], axes[:, ::-1]
    if np.linalg.det(axes) < 0:
        axes[:, 2] *= -1
    return centroid, axes, variances


@dataclass
class Frame:
    """A surface's area-weighted centroid (3,) mm, principal axes (3, 3; columns) and variances along them
    (3,) mm^2."""

    centroid_mm: FloatArray
    axes: FloatArray
    variances_mm2: FloatArray

    @classmethod
    def of(cls, mesh: TriangleMesh) -> Frame:
        """The frame of a surface, its vertices weighted by their areas."""
        return cls(*principal_frame(mesh.vertices_mm, vertex_areas_mm2(mesh.vertices_mm, mesh.triangles)))

    @property
    def rms_radius_mm(self) -> float:
        """RMS distance of the surface from its centroid: its size, whatever its pose."""
        return float(np.sqrt(self.variances_mm2.sum()))


def axis_candidates() -> FloatArray:
    """The 24 proper rotations (24, 3, 3) that map coordinate axes onto coordinate axes (signed permutations,
    det +1)."""
    candidates = []
    for order in ((0, 1, 2), (0, 2, 1), (1, 0, 2), (1, 2, 0), (2, 0, 1), (2, 1, 0)):
        for signs in np.array(np.meshgrid([1, -1], [1, -1], [1, -1])).T.reshape(-1, 3):
            matrix = np.zeros((3, 3))
            matrix[np.arange(3), order] = signs
            if np.linalg.det(matrix) > 0:
                candidates.append(matrix)
    return np.array(candidates)


def rotation_angle_deg(rotation: FloatArray) -> float:
    """The angle (degrees, 0-180) of a rotation matrix."""
    return float(np.degrees(np.arccos(np.clip((np.trace(rotation) - 1.0) / 2.0, -1.0, 1.0))))


def rotation_axis(rotation: FloatArray) -> FloatArray:
    """Unit axis (3,) of a rotation (right-handed with :func:`rotation_angle_deg`); any unit vector for none."""
    values, vectors = np.linalg.eig(rotation)
    axis: FloatArray = np.real(vectors[:, np.argmin(np.abs(values - 1.0))])
    skew = np.array([rotation[2, 1] - rotation[1, 2], rotation[0, 2] - rotation[2, 0],
                     rotation[1, 0] - rotation[0, 1]])
    return -axis if axis @ skew < 0 else axis


def rotation_from_vector(omega: FloatArray) -> FloatArray:
    """Rodrigues: the rotation (3, 3) by ``|omega|`` radians about ``omega`` (3,)."""
    angle = float(np.linalg.norm(omega))
    if angle < 1e-15:
        return np.eye(3)
    k = omega / angle
    cross = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    rotation: FloatArray = np.eye(3) + np.sin(angle) * cross + (1 - np.cos(angle)) * cross @ cross
    return rotation


# --- closest points --------------------------------------------------------------------------------------------


class SurfaceIndex:
    """Exact closest points on a triangle surface (mm) for many query points.

    Parameters
    ----------
    vertices_mm : (n, 3) float array
    triangles : (k, 3) int array
    """

    def __init__(self, vertices_mm: FloatArray, triangles: IntArray):
        # scipy.spatial (0.1 s to import) only where a surface is indexed
        from scipy.spatial import cKDTree

        self.vertices_mm = np.ascontiguousarray(vertices_mm, np.float64)
        self.triangles = np.ascontiguousarray(triangles, np.int64)
        corners = self.vertices_mm[self.triangles]
        centroids = corners.mean(axis=1)
        self.radius_mm: FloatArray = np.sqrt(np.max(np.sum((corners - centroids[:, None, :]) ** 2, axis=2), axis=1))
        self.radius_max_mm = float(self.radius_mm.max())
        self.tree: cKDTree = cKDTree(centroids, balanced_tree=False, compact_nodes=False)
        self._face_normals: FloatArray | None = None
        self._neighbours: tuple[float, IntArray, IntArray] | None = None

    @property
    def face_normals(self) -> FloatArray:
        """Unit normals (k, 3) of the triangles (made when first asked for: a distance query does not)."""
        if self._face_normals is None:
            a, b, c = (self.vertices_mm[self.triangles[:, k]] for k in range(3))
            normals = np.cross(b - a, c - a)
            self._face_normals = normals / np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-300)
        return self._face_normals

    def _neighbour_lists(self) -> tuple[float, IntArray, IntArray]:
        """For each triangle, the triangles whose centroids lie within NEIGHBOUR_REACH_RADII * radius_max of its
        centroid (CSR: start offsets and indices); made once, for many queries on a small surface."""
        if self._neighbours is None:
            reach = NEIGHBOUR_REACH_RADII * self.radius_max_mm
            lists = self.tree.query_ball_point(self.tree.data, reach)
            assert isinstance(lists, np.ndarray)  # many query points: an object array of index lists
            start = np.zeros(len(lists) + 1, np.int64)
            start[1:] = np.cumsum([len(entries) for entries in lists])
            self._neighbours = (reach, start, np.concatenate(lists).astype(np.int64))
        return self._neighbours

    def closest(self, points_mm: FloatArray, first_k: int = 16) -> tuple[FloatArray, FloatArray, IntArray]:
        """Distance (n,) mm, closest point (n, 3) mm and triangle (n,) of each query point (n, 3).

        Many points on a small surface (a scan against the model) first try the nearest centroid's neighbour
        list (one nearest-neighbour query each); the rest, and few points on a large surface, query the k
        nearest centroids, more until the answer is exact.
        """
        # numba (0.2 s to import, and the kernels' first load) only when closest points are first asked for
        from phantom.model.mesh import surface_kernels as kernels

        points_mm = np.ascontiguousarray(points_mm, np.float64)
        n = len(points_mm)
        distance = np.empty(n)
        closest = np.empty((n, 3))
        triangle = np.empty(n, np.int64)
        pending = np.arange(n)
        if n > 10 * len(self.triangles):
            reach, start, neighbours = self._neighbour_lists()
            nearest_distance, nearest = self.tree.query(points_mm)
            done: BoolArray = np.zeros(n, np.bool_)
            kernels.closest_by_neighbours(points_mm, np.asarray(nearest, np.int64),
                                          np.asarray(nearest_distance, np.float64), start, neighbours,
                                          self.tree.data, self.radius_mm, self.radius_max_mm, reach, self.vertices_mm,
                                          self.triangles, distance, closest, triangle, done)
            pending = pending[~done]
        k = min(first_k, len(self.triangles))
        while len(pending):
            # Threads pay off only for large batches: starting them costs milliseconds on a busy machine.
            workers = -1 if len(pending) > 50000 else 1
            centroid_distance, candidates = self.tree.query(points_mm[pending], k=k, workers=workers)
            centroid_distance = np.ascontiguousarray(np.reshape(centroid_distance, (len(pending), -1)), np.float64)
            candidates = np.ascontiguousarray(np.reshape(candidates, (len(pending), -1)), np.int64)
            done = np.zeros(len(pending), np.bool_)
            kernels.closest_on_candidates(points_mm, pending, candidates, centroid_distance, self.vertices_mm,
                                          self.triangles, self.radius_mm, self.radius_max_mm,
                                          k >= len(self.triangles), distance, closest, triangle, done)
            pending = pending[~done]
            k = min(4 * k, len(self.triangles))
        return distance, closest, triangle


# --- rigid alignment -------------------------------------------------------------------------------------------


def point_to_plane_step(points: FloatArray, targets: FloatArray, normals: FloatArray,
                        weights: FloatArray) -> tuple[FloatArray, FloatArray]:
    """The small rotation vector (3,) and translation (3,) that minimise ``sum w ((R p + t - q) . n)^2``
    (linearised) over points p (n, 3), targets q (n, 3), normals n (n, 3) and weights w (n,)."""
    jacobian = np.hstack([np.cross(points, normals), normals])
    residual = np.einsum("ij,ij->i", points - targets, normals)
    weighted = jacobian * weights[:, None]
    solution: FloatArray = np.linalg.lstsq(weighted.T @ jacobian, -weighted.T @ residual, rcond=None)[0]
    return solution[:3], solution[3:]


def icp(points_mm: FloatArray, correspond: Correspondence, rotation: FloatArray, translation_mm: FloatArray,
        max_iterations: int, tolerance_mm: float = 1e-3) -> IcpResult:
    """Point-to-plane ICP of ``points_mm`` (n, 3) from a start; ``correspond(points)`` gives each point's
    distance, target point and target normal. Pairs farther than three times the median distance are left out
    (stray points, unfilled parts). Each Gauss-Newton step is halved until the (trimmed) sum of squared
    distances decreases: where the distances do not go to zero (a scan that differs from the model) the
    linearisation leaves out the surface's curvature and a full step can overshoot along a weakly constrained
    rotation. Stops when a step moves no point by more than ``tolerance_mm``. Returns rotation, translation, RMS
    distance (mm, all points, at the result) and iterations."""
    moved = points_mm @ rotation.T + translation_mm
    radius = float(np.max(np.linalg.norm(moved - moved.mean(axis=0), axis=1)))
    distance, targets, normals = correspond(moved)
    iterations = 0
    while iterations < max_iterations:
        iterations += 1
        limit = 3.0 * np.median(distance) + 1e-9
        inlier = distance <= limit
        cost = np.sum(np.minimum(distance, limit) ** 2)
        omega, shift = point_to_plane_step(moved[inlier], targets[inlier], normals[inlier],
                                           np.ones(np.count_nonzero(inlier)))
        for _ in range(8):
            step = rotation_from_vector(omega)
            trial = moved @ step.T + shift
            trial_correspondence = correspond(trial)
            if np.sum(np.minimum(trial_correspondence[0], limit) ** 2) <= cost:
                break
            omega, shift = 0.5 * omega, 0.5 * shift
        else:
            break
        rotation, translation_mm = step @ rotation, step @ translation_mm + shift
        moved = trial
        distance, targets, normals = trial_correspondence
        if np.linalg.norm(omega) * radius + np.linalg.norm(shift) < tolerance_mm:
            break
    return rotation, translation_mm, float(np.sqrt(np.mean(distance**2))), iterations


def exact_correspondence(index: SurfaceIndex) -> Correspondence:
    """Closest points on the surface, with the direction from there to the point (the distance's gradient);
    the face normal for points on the surface. A face normal alone would be wrong where the closest point is on
    an edge or a corner (an offset surface mostly is): ICP would then minimise another objective and drift."""
    def correspond(points_mm: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
        distance, closest, triangle = index.closest(points_mm)
        normals = index.face_normals[triangle]
        away = distance > 1e-9
        normals[away] = (points_mm[away] - closest[away]) / distance[away, None]
        return distance, closest, normals
    return correspond


def vertex_correspondence(vertices_mm: FloatArray, normals: FloatArray) -> Correspondence:
    """Nearest surface vertex and its normal: cheap, for the global start's many candidates."""
    # scipy.spatial (0.1 s to import) only where a surface is indexed
    from scipy.spatial import cKDTree

    tree = cKDTree(vertices_mm)

    def correspond(points_mm: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
        distance, nearest = tree.query(points_mm)
        return np.asarray(distance, np.float64), vertices_mm[nearest], normals[nearest]
    return correspond


@dataclass
class Alignment:
    """``x_target = rotation @ x_moving + translation_mm`` (rotation (3, 3), translation (3,) mm), and how well
    it fits: the RMS distance (mm) left and the ICP iterations, and the best alignment that differs by more than
    AMBIGUOUS_ANGLE_DEG, its angle from this one (degrees) and RMS distance (inf when there is none)."""

    rotation: FloatArray
    translation_mm: FloatArray
    rms_mm: float
    iterations: int
    alternative_angle_deg: float
    alternative_rms_mm: float

    @property
    def rotation_angle_deg(self) -> float:
        return rotation_angle_deg(self.rotation)

    @property
    def ambiguous(self) -> bool:
        """Another rotation fits almost as well: the surface is close to symmetric under it."""
        excess_mm = self.alternative_rms_mm - self.rms_mm
        return excess_mm <= max((AMBIGUOUS_RESIDUAL_RATIO - 1.0) * self.rms_mm, AMBIGUOUS_EXCESS_MM)

    def apply(self, points_mm: FloatArray) -> FloatArray:
        """Points (n, 3) mm of the moving surface in the target's frame."""
        moved: FloatArray = points_mm @ self.rotation.T + self.translation_mm
        return moved


def align(moving: Frame, moving_points_mm: FloatArray, target: TriangleMesh, target_frame: Frame,
          target_index: SurfaceIndex, rng: np.random.Generator, fit_rms_limit: float = FIT_RMS_LIMIT) -> Alignment:
    """Rigid alignment of a surface (its frame ``moving`` and points ``moving_points_mm`` (n, 3)) onto
    ``target``: principal-axes candidates, each refined briefly by ICP on a few hundred points against the
    target's vertices; the best, and the best that lies more than AMBIGUOUS_ANGLE_DEG from it, refined on up to
    ICP_POINTS points against the exact surface, the better kept. Raises AlignmentError when even that leaves an
    RMS distance above ``fit_rms_limit`` (default FIT_RMS_LIMIT) of the target's size: two different shapes (a
    shape analysis) may take a larger one."""
    few = moving_points_mm[rng.choice(len(moving_points_mm), min(START_POINTS, len(moving_points_mm)),
                                      replace=False)]
    coarse = vertex_correspondence(target.vertices_mm, vertex_normals(target.vertices_mm, target.triangles))
    starts = []
    for swap in axis_candidates():
        rotation = target_frame.axes @ swap @ moving.axes.T
        translation = target_frame.centroid_mm - rotation @ moving.centroid_mm
        starts.append(icp(few, coarse, rotation, translation, START_ITERATIONS))
    order = np.argsort([rms for _, _, rms, _ in starts])
    many = moving_points_mm[rng.choice(len(moving_points_mm), min(ICP_POINTS, len(moving_points_mm)),
                                       replace=False)]
    exact = exact_correspondence(target_index)

    def refine(start: IcpResult) -> IcpResult:
        return icp(many, exact, start[0], start[1], ICP_MAX_ITERATIONS)

    best = refine(starts[order[0]])
    # The best start that lies far from that one is refined too: the better of the two is the answer, and the
    # other's residual says how well the shape pins the rotation (nearly symmetric shapes fit both ways). A start
    # that ICP brings back to the best alignment is the same answer, not another one (it was reported as an
    # "ambiguous" rotation by 0 deg): the next far start is tried, up to ALTERNATIVE_TRIES refinements.
    alternative: IcpResult | None = None
    tries = 0
    for index in order[1:]:
        if tries == ALTERNATIVE_TRIES:
            break
        if rotation_angle_deg(starts[index][0] @ best[0].T) > AMBIGUOUS_ANGLE_DEG:
            tries += 1
            refined = refine(starts[index])
            if rotation_angle_deg(refined[0] @ best[0].T) > AMBIGUOUS_ANGLE_DEG:
                alternative = refined
                break
    if alternative is not None and alternative[2] < best[2]:
        best, alternative = alternative, best
    rotation, translation, rms, iterations = best
    alternative_angle, alternative_rms = 180.0, np.inf
    if alternative is not None:
        alternative_angle, alternative_rms = rotation_angle_deg(alternative[0] @ rotation.T), alternative[2]
    size_mm = target_frame.rms_radius_mm
    if rms > fit_rms_limit * size_mm:
        raise AlignmentError(rms, size_mm)
    return Alignment(rotation, translation, rms, iterations, alternative_angle, float(alternative_rms))
