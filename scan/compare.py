"""Compare a 3D scan of the phantom with the model: read, clean, align, measure (millimetres throughout).

A scan (OBJ, PLY or STL from photogrammetry or a structured-light scanner) is read in the unit it was exported
in, cleaned (largest connected piece kept, stray fragments dropped, holes closed by MeshFix so that its volume
is defined), and aligned rigidly to the model's deformed outer surface: a global start from the principal axes
of both surfaces, trying all 24 axis-to-axis candidates (a principal axis' sign, and the order of two axes of
similar extent, are not defined by the shape), then point-to-plane ICP on exact closest points. The result
says how far the surfaces are apart (closest-point distances both ways, area-weighted) and, per model vertex,
the signed distance to the scan (positive where the scan lies outside the model).

Distances use an exact closest-point query: candidate triangles come from a k-d tree of triangle centroids and
are examined nearest first until the centroid distance minus the largest triangle radius exceeds the best
distance found; the point-triangle kernel is numba (cached on disk).
"""

from __future__ import annotations

import contextlib
import os
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

import phantom
from phantom import PhantomError, require_extra
from phantom.model.mesh.tetmesh import enclosed_volume_m3

#: Millimetres per unit of a scan file.
UNITS_MM = {"mm": 1.0, "cm": 10.0, "m": 1000.0}
SCAN_SUFFIXES = (".obj", ".ply", ".stl")
#: A scan whose size (area-weighted RMS radius) differs from the model's by more than this factor is not
#: aligned: its unit is wrong, or it is not this phantom.
SCALE_TOLERANCE = 1.5
#: No alignment fits when the RMS scan-to-model distance exceeds this fraction of the model's RMS radius.
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
#: Scan points used by the global start (per candidate) and by the final ICP.
START_POINTS = 600
START_ITERATIONS = 8
ICP_POINTS = 5000
ICP_MAX_ITERATIONS = 50


class ScanError(PhantomError):
    """A scan file that cannot be read or used, or a scan that does not fit the model."""


class StageClock:
    """Wall and CPU seconds per named stage. CPU time (all threads of this process) shows the work itself when
    other processes share the cores and stretch the wall time."""

    def __init__(self):
        self.wall_s: dict[str, float] = {}
        self.cpu_s: dict[str, float] = {}

    @contextlib.contextmanager
    def stage(self, name: str):
        wall, cpu = time.perf_counter(), time.process_time()
        try:
            yield
        finally:
            self.wall_s[name] = self.wall_s.get(name, 0.0) + time.perf_counter() - wall
            self.cpu_s[name] = self.cpu_s.get(name, 0.0) + time.process_time() - cpu


@dataclass
class TriangleMesh:
    """A triangle surface: vertices (n, 3) in mm and triangles (k, 3) vertex indices."""

    vertices_mm: np.ndarray
    triangles: np.ndarray


@dataclass
class CleanReport:
    """What cleaning changed."""

    input_vertices: int
    input_triangles: int
    removed_degenerate_triangles: int
    removed_components: int
    removed_component_triangles: int
    holes_filled: int
    added_triangles: int
    reoriented: bool
    output_vertices: int
    output_triangles: int

    def summary(self) -> str:
        parts = [f"{self.input_vertices} vertices, {self.input_triangles} triangles read"]
        if self.removed_degenerate_triangles:
            parts.append(f"{self.removed_degenerate_triangles} degenerate or duplicate triangles dropped")
        parts.append(f"{self.removed_components} stray fragment(s) removed "
                     f"({self.removed_component_triangles} triangles)")
        parts.append(f"{self.holes_filled} hole(s) closed ({self.added_triangles} triangles added)")
        if self.reoriented:
            parts.append("faces turned outward")
        return "; ".join(parts)


@dataclass
class Alignment:
    """``x_model = rotation @ x_scan + translation_mm``, and how well it fits."""

    rotation: np.ndarray
    translation_mm: np.ndarray
    rms_mm: float
    iterations: int
    #: The best alignment that differs by more than AMBIGUOUS_ANGLE_DEG, its angle from this one and residual.
    alternative_angle_deg: float
    alternative_rms_mm: float

    @property
    def rotation_angle_deg(self) -> float:
        return rotation_angle_deg(self.rotation)

    @property
    def ambiguous(self) -> bool:
        excess_mm = self.alternative_rms_mm - self.rms_mm
        return excess_mm <= max((AMBIGUOUS_RESIDUAL_RATIO - 1.0) * self.rms_mm, AMBIGUOUS_EXCESS_MM)

    def apply(self, points_mm: np.ndarray) -> np.ndarray:
        return points_mm @ self.rotation.T + self.translation_mm


@dataclass
class Comparison:
    """Everything ``compare-scan`` reports; distances in mm, volumes in ml."""

    clean: CleanReport
    alignment: Alignment
    scan_volume_ml: float
    model_volume_ml: float
    scan_to_model_mm: dict
    model_to_scan_mm: dict
    symmetric_mm: dict
    model_vertices_mm: np.ndarray
    model_triangles: np.ndarray
    model_signed_distance_mm: np.ndarray
    scan_aligned: TriangleMesh
    clock: StageClock = field(default_factory=StageClock)

    def to_json(self) -> dict:
        alignment = self.alignment
        return {
            "clean": dict(vars(self.clean)),
            "transform": {
                "rotation": alignment.rotation.tolist(),
                "translation_mm": alignment.translation_mm.tolist(),
                "rotation_angle_deg": alignment.rotation_angle_deg,
                "fit_rms_mm": alignment.rms_mm,
                "iterations": alignment.iterations,
                "ambiguous": bool(alignment.ambiguous),
                # None when no start ended far from the best (JSON has no infinity).
                "alternative_angle_deg": (alignment.alternative_angle_deg
                                          if np.isfinite(alignment.alternative_rms_mm) else None),
                "alternative_rms_mm": (alignment.alternative_rms_mm
                                       if np.isfinite(alignment.alternative_rms_mm) else None),
            },
            "scan_volume_ml": self.scan_volume_ml,
            "model_volume_ml": self.model_volume_ml,
            "volume_difference_pct": 100.0 * (self.scan_volume_ml - self.model_volume_ml) / self.model_volume_ml,
            "distance_mm": self.symmetric_mm,
            "scan_to_model_mm": self.scan_to_model_mm,
            "model_to_scan_mm": self.model_to_scan_mm,
            "signed_distance_range_mm": [float(self.model_signed_distance_mm.min()),
                                         float(self.model_signed_distance_mm.max())],
            "stage_times_s": self.clock.wall_s,
            "stage_cpu_s": self.clock.cpu_s,
        }


# --- reading ---------------------------------------------------------------------------------------------------


def read_scan(path: str | Path, units: str = "mm") -> TriangleMesh:
    """Read an OBJ, PLY or STL triangle surface; coordinates in ``units`` (mm, cm or m) are returned in mm.

    Polygons are split into triangles by the reader; exactly coincident vertices (an STL's triangle soup) are
    merged. Raises ScanError for a missing or unreadable file, no faces (a point cloud), no vertices, indices out
    of range, or non-finite coordinates.
    """
    if units not in UNITS_MM:
        raise ScanError(f"unknown unit {units!r}: use one of {', '.join(UNITS_MM)}")
    path = Path(path)
    if not path.is_file():
        raise ScanError(f"the scan file {path} does not exist: check the path")
    if path.suffix.lower() not in SCAN_SUFFIXES:
        raise ScanError(f"{path}: a scan must be an OBJ, PLY or STL file (not {path.suffix or 'no extension'})")
    with require_extra("scan"):
        import trimesh

    try:
        loaded = trimesh.load(path, process=False)
        if isinstance(loaded, trimesh.PointCloud):
            raise ScanError(f"{path} is a point cloud ({len(loaded.vertices)} points, no faces): reconstruct a "
                            f"surface first (e.g. Meshroom's meshing step, or screened Poisson in MeshLab) and "
                            f"export that")
        if isinstance(loaded, trimesh.Scene):
            loaded = trimesh.load(path, force="mesh", process=False)
        vertices = np.asarray(loaded.vertices, dtype=np.float64)
        faces = np.asarray(getattr(loaded, "faces", np.zeros((0, 3))), dtype=np.int64)
    except ScanError:
        raise
    except Exception as error:  # trimesh raises many types for files that are not meshes
        raise ScanError(f"{path} is not a readable {path.suffix[1:].upper()} mesh ({type(error).__name__}: "
                        f"{str(error).splitlines()[0] if str(error) else 'no detail'})") from None
    if len(vertices) == 0:
        raise ScanError(f"{path} holds no vertices: export the reconstructed mesh, not an empty scene")
    if faces.size == 0:
        raise ScanError(f"{path} is a point cloud ({len(vertices)} points, no faces): reconstruct a surface first "
                        f"(e.g. Meshroom's meshing step, or screened Poisson in MeshLab) and export that")
    if faces.ndim != 2 or faces.shape[1] != 3 or faces.min() < 0 or faces.max() >= len(vertices):
        raise ScanError(f"{path}: faces refer to vertices that do not exist: the file is damaged")
    finite = np.isfinite(vertices).all(axis=1)
    if not finite.all():
        raise ScanError(f"{path} has {np.count_nonzero(~finite)} vertices with non-finite coordinates (nan or "
                        f"inf), first at index {int(np.flatnonzero(~finite)[0])}: re-export the scan")
    vertices, faces = merge_coincident_vertices(vertices, faces)
    return TriangleMesh(vertices * UNITS_MM[units], faces)


def merge_coincident_vertices(vertices: np.ndarray, triangles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Merge exactly equal vertices and drop unreferenced ones (an STL stores each triangle's corners; an OBJ
    with texture coordinates may repeat a position at a seam).

    Rows are grouped by a 64-bit hash of their bits (a hash table, much faster than sorting rows); a collision
    would join different rows, so the grouping is checked and, if that ever happens, redone by sorting rows.
    """
    rows = np.ascontiguousarray(vertices + 0.0)  # + 0.0 turns -0.0 into 0.0: equal values, equal bits
    bits = rows.view(np.uint64)
    key = (bits[:, 0] * np.uint64(0x9E3779B97F4A7C15)) ^ (bits[:, 1] * np.uint64(0xC2B2AE3D27D4EB4F)) \
        ^ (bits[:, 2] * np.uint64(0x165667B19E3779F9))
    _, first, inverse = np.unique(key, return_index=True, return_inverse=True)
    if not np.array_equal(rows[first][inverse.ravel()], rows):
        keys = rows.view(np.dtype((np.void, rows.dtype.itemsize * 3))).ravel()
        _, first, inverse = np.unique(keys, return_index=True, return_inverse=True)
    merged = compact(rows[first], inverse.ravel()[triangles])
    return merged.vertices_mm, merged.triangles


# --- cleaning --------------------------------------------------------------------------------------------------


def triangle_areas_mm2(vertices_mm: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    a, b, c = (vertices_mm[triangles[:, k]] for k in range(3))
    return 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)


def face_keys(triangles: np.ndarray, n_vertices: int) -> np.ndarray:
    """One integer per triangle, equal for the same three vertices in any order."""
    ordered = np.sort(triangles, axis=1).astype(np.int64)
    return (ordered[:, 0] * n_vertices + ordered[:, 1]) * n_vertices + ordered[:, 2]


def drop_degenerate(triangles: np.ndarray, areas_mm2: np.ndarray) -> np.ndarray:
    """Mask of triangles to keep: three distinct vertices, non-zero area, first copy of a repeated face."""
    distinct = ((triangles[:, 0] != triangles[:, 1]) & (triangles[:, 1] != triangles[:, 2])
                & (triangles[:, 0] != triangles[:, 2]) & (areas_mm2 > 0))
    keep = np.zeros(len(triangles), bool)
    _, first = np.unique(face_keys(triangles, int(triangles.max()) + 1), return_index=True)
    keep[first] = True
    return keep & distinct


def vertex_components(triangles: np.ndarray, n_vertices: int) -> np.ndarray:
    """Label of the connected piece of each vertex (vertices joined by triangle edges); scipy's graph search is
    about ten times faster than the model's edge-based union-find on a scan's half a million triangles."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    rows, columns = triangles[:, [0, 1, 2]].ravel(), triangles[:, [1, 2, 0]].ravel()
    graph = coo_matrix((np.ones(len(rows), np.int8), (rows, columns)), shape=(n_vertices, n_vertices))
    return connected_components(graph, directed=False)[1]


def largest_component(triangles: np.ndarray, areas_mm2: np.ndarray) -> tuple[np.ndarray, int]:
    """Mask of the triangles of the connected piece with the largest area, and the number of pieces."""
    labels = vertex_components(triangles, int(triangles.max()) + 1)[triangles[:, 0]]
    _, labels = np.unique(labels, return_inverse=True)
    piece_area = np.bincount(labels, areas_mm2)
    return labels == int(np.argmax(piece_area)), len(piece_area)


def compact(vertices_mm: np.ndarray, triangles: np.ndarray) -> TriangleMesh:
    """Drop the vertices no triangle uses and renumber."""
    used = np.bincount(triangles.ravel(), minlength=len(vertices_mm)) > 0
    renumber = np.cumsum(used) - 1
    return TriangleMesh(vertices_mm[used], renumber[triangles].astype(np.int64))


def boundary_edges(triangles: np.ndarray) -> np.ndarray:
    """Directed edges (k, 2) that belong to one triangle only, as that triangle runs them."""
    directed = triangles[:, [[0, 1], [1, 2], [2, 0]]].reshape(-1, 2)
    n = int(triangles.max()) + 1
    ordered = np.sort(directed, axis=1).astype(np.int64)
    _, inverse, counts = np.unique(ordered[:, 0] * n + ordered[:, 1], return_inverse=True, return_counts=True)
    return directed[counts[inverse.ravel()] == 1]


#: Rings of triangles around the holes handed to MeshFix with them.
HOLE_RINGS = 2


def close_holes(mesh: TriangleMesh) -> tuple[TriangleMesh, int]:
    """Close every hole with MeshFix's hole filling (triangulated, refined to the surrounding edge length,
    faired); return the closed surface and the number of holes. The choice is measured in bench/scan_repair.py.

    MeshFix's loading alone takes seconds per hundred thousand triangles, so it gets only the triangles within
    HOLE_RINGS rings of a hole. That patch also has its cut edge as boundary: everything MeshFix adds is split
    into connected fills and a fill is kept when it closes a loop of the scan's own boundary.
    """
    edges = boundary_edges(mesh.triangles)
    if len(edges) == 0:
        return mesh, 0
    n_vertices = len(mesh.vertices_mm)
    on_hole = np.zeros(n_vertices, bool)
    on_hole[edges.ravel()] = True
    near = on_hole.copy()
    for _ in range(HOLE_RINGS):
        touching = near[mesh.triangles].any(axis=1)
        near[mesh.triangles[touching].ravel()] = True
    patch_global = np.unique(mesh.triangles[touching])
    patch = compact(mesh.vertices_mm, mesh.triangles[touching])
    filled_vertices, filled_faces = _meshfix_fill(patch)
    # MeshFix keeps the patch's vertices (same coordinates, maybe renumbered) and appends new ones.
    patch_rows = np.ascontiguousarray(patch.vertices_mm)
    filled_rows = np.ascontiguousarray(filled_vertices)
    void = np.dtype((np.void, 24))
    known, where = np.unique(patch_rows.view(void).ravel(), return_index=True)
    position = np.searchsorted(known, filled_rows.view(void).ravel())
    position = np.minimum(position, len(known) - 1)
    is_old = known[position] == filled_rows.view(void).ravel()
    global_index = np.empty(len(filled_rows), np.int64)
    global_index[is_old] = patch_global[where[position[is_old]]]
    new_count = int(np.count_nonzero(~is_old))
    global_index[~is_old] = n_vertices + np.arange(new_count)
    faces = global_index[filled_faces]
    added = faces[~np.isin(face_keys(faces, n_vertices + new_count),
                           face_keys(mesh.triangles[touching], n_vertices + new_count))]
    labels = vertex_components(added, n_vertices + new_count)[added[:, 0]]
    touches_hole = np.zeros(n_vertices + new_count, bool)
    touches_hole[:n_vertices] = on_hole
    keep_label = np.zeros(labels.max() + 1 if len(labels) else 0, bool)
    keep_label[labels[touches_hole[added].any(axis=1)]] = True
    added, labels = added[keep_label[labels]], labels[keep_label[labels]]
    added = _orient_fills(added, labels, edges, n_vertices + new_count)
    holes = _count_loops(edges, n_vertices)
    # Closed when no hole edge and no edge of a fill is left on the patch's boundary (only its cut edge is).
    left = boundary_edges(np.vstack([mesh.triangles[touching], added]))
    unclosed = on_hole[left].all(axis=1) | (left >= n_vertices).any(axis=1)
    if unclosed.any():
        raise ScanError(f"the scan could not be closed ({np.count_nonzero(unclosed)} open edges remain after "
                        f"filling {holes} holes): repair it in MeshLab and export again")
    vertices = np.vstack([mesh.vertices_mm, filled_rows[~is_old]])
    return compact(vertices, np.vstack([mesh.triangles, added])), holes


def _meshfix_fill(patch: TriangleMesh) -> tuple[np.ndarray, np.ndarray]:
    with require_extra("scan"):
        import pymeshfix

    surface = pymeshfix.PyTMesh()
    surface.set_quiet(True)
    surface.load_array(patch.vertices_mm, patch.triangles.astype(np.int32))
    surface.fill_small_boundaries(nbe=0, refine=True)
    vertices, faces = surface.return_arrays()
    return np.asarray(vertices, np.float64), np.asarray(faces, np.int64)


def _orient_fills(added: np.ndarray, labels: np.ndarray, edges: np.ndarray, n_vertices: int) -> np.ndarray:
    """Turn each fill whose triangles run the hole's boundary edges the same way as the scan (they must run
    them the other way, for a consistently oriented closed surface)."""
    directed = added[:, [[0, 1], [1, 2], [2, 0]]].reshape(-1, 2).astype(np.int64)
    forward = np.isin(directed[:, 0] * n_vertices + directed[:, 1], edges[:, 0] * n_vertices + edges[:, 1])
    backward = np.isin(directed[:, 0] * n_vertices + directed[:, 1], edges[:, 1] * n_vertices + edges[:, 0])
    face_labels = np.repeat(labels, 3)
    votes = np.bincount(face_labels, forward.astype(float), labels.max() + 1 if len(labels) else 0)
    votes -= np.bincount(face_labels, backward.astype(float), len(votes))
    flip = votes[labels] > 0
    added = added.copy()
    added[flip] = added[flip][:, ::-1]
    return added


def _count_loops(edges: np.ndarray, n_vertices: int) -> int:
    """Number of boundary loops (connected sets of boundary edges)."""
    labels = vertex_components(edges[:, [0, 1, 1]], n_vertices)
    return len(np.unique(labels[np.unique(edges)]))


def clean_scan(mesh: TriangleMesh) -> tuple[TriangleMesh, TriangleMesh, CleanReport]:
    """The watertight, outward-oriented largest piece of a scan, that piece before its holes were closed (the
    measured surface, for distances), and what was changed."""
    areas = triangle_areas_mm2(mesh.vertices_mm, mesh.triangles)
    keep = drop_degenerate(mesh.triangles, areas)
    triangles, areas = mesh.triangles[keep], areas[keep]
    if len(triangles) == 0:
        raise ScanError("the scan has no triangle of non-zero area")
    in_largest, pieces = largest_component(triangles, areas)
    measured = compact(mesh.vertices_mm, triangles[in_largest])
    closed, holes = close_holes(measured)
    reoriented = enclosed_volume_m3(closed.vertices_mm, closed.triangles) < 0
    if reoriented:
        closed.triangles = closed.triangles[:, ::-1].copy()
        measured.triangles = measured.triangles[:, ::-1].copy()
    report = CleanReport(
        input_vertices=len(mesh.vertices_mm), input_triangles=len(mesh.triangles),
        removed_degenerate_triangles=int(np.count_nonzero(~keep)), removed_components=pieces - 1,
        removed_component_triangles=int(np.count_nonzero(~in_largest)), holes_filled=holes,
        added_triangles=len(closed.triangles) - len(measured.triangles), reoriented=bool(reoriented),
        output_vertices=len(closed.vertices_mm), output_triangles=len(closed.triangles))
    return closed, measured, report


def surface_volume_ml(mesh: TriangleMesh) -> float:
    """Volume enclosed by a closed, outward-oriented surface in mm (ml)."""
    return enclosed_volume_m3(mesh.vertices_mm, mesh.triangles) * 1e-3


def scan_volume_ml(path: str | Path, units: str = "mm") -> float:
    """The volume (ml) of a scan file after cleaning: its largest piece, holes closed."""
    closed, _, _ = clean_scan(read_scan(path, units))
    return surface_volume_ml(closed)


# --- geometry --------------------------------------------------------------------------------------------------


def vertex_areas_mm2(vertices_mm: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """A third of the area of each triangle around a vertex (the vertex's share of the surface)."""
    areas = triangle_areas_mm2(vertices_mm, triangles)
    return np.bincount(triangles.ravel(), np.repeat(areas / 3.0, 3), len(vertices_mm))


def vertex_normals(vertices_mm: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals (outward for an outward-oriented surface)."""
    a, b, c = (vertices_mm[triangles[:, k]] for k in range(3))
    face = np.cross(b - a, c - a)
    normals = np.zeros_like(vertices_mm)
    for k in range(3):
        np.add.at(normals, triangles[:, k], face)
    return normals / np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-300)


def principal_frame(points_mm: np.ndarray, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Weighted centroid, principal axes (columns, largest spread first, right-handed) and variances (mm^2)."""
    weights = weights / weights.sum()
    centroid = weights @ points_mm
    offsets = points_mm - centroid
    variances, axes = np.linalg.eigh((offsets * weights[:, None]).T @ offsets)
    variances, axes = variances[::-1], axes[:, ::-1]
    if np.linalg.det(axes) < 0:
        axes[:, 2] *= -1
    return centroid, axes, variances


def axis_candidates() -> np.ndarray:
    """The 24 proper rotations that map coordinate axes onto coordinate axes (signed permutations, det +1)."""
    candidates = []
    for order in ((0, 1, 2), (0, 2, 1), (1, 0, 2), (1, 2, 0), (2, 0, 1), (2, 1, 0)):
        for signs in np.array(np.meshgrid([1, -1], [1, -1], [1, -1])).T.reshape(-1, 3):
            matrix = np.zeros((3, 3))
            matrix[np.arange(3), order] = signs
            if np.linalg.det(matrix) > 0:
                candidates.append(matrix)
    return np.array(candidates)


def rotation_angle_deg(rotation: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(rotation) - 1.0) / 2.0, -1.0, 1.0))))


def rotation_axis(rotation: np.ndarray) -> np.ndarray:
    """Unit axis of a rotation (right-handed with :func:`rotation_angle_deg`); any unit vector for none."""
    values, vectors = np.linalg.eig(rotation)
    axis = np.real(vectors[:, np.argmin(np.abs(values - 1.0))])
    skew = np.array([rotation[2, 1] - rotation[1, 2], rotation[0, 2] - rotation[2, 0],
                     rotation[1, 0] - rotation[0, 1]])
    return -axis if axis @ skew < 0 else axis


def rotation_from_vector(omega: np.ndarray) -> np.ndarray:
    """Rodrigues: the rotation by ``|omega|`` radians about ``omega``."""
    angle = float(np.linalg.norm(omega))
    if angle < 1e-15:
        return np.eye(3)
    k = omega / angle
    cross = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(angle) * cross + (1 - np.cos(angle)) * cross @ cross


def subdivide(vertices: np.ndarray, triangles: np.ndarray, values: np.ndarray | None = None):
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


# --- closest points --------------------------------------------------------------------------------------------

_KERNEL = None


def _closest_kernel():
    """The numba closest-point kernel, compiled once per process (and cached on disk)."""
    global _KERNEL
    if _KERNEL is None:
        os.environ.setdefault("NUMBA_CACHE_DIR", str(phantom.cache_dir("numba")))
        from phantom.scan import kernels as scan_kernels

        _KERNEL = scan_kernels.closest_on_candidates
    return _KERNEL


#: Neighbour lists reach this many times the largest triangle radius (see SurfaceIndex.closest).
NEIGHBOUR_REACH_RADII = 2.5


class SurfaceIndex:
    """Exact closest points on a triangle surface (mm) for many query points."""

    def __init__(self, vertices_mm: np.ndarray, triangles: np.ndarray):
        from scipy.spatial import cKDTree

        self.vertices_mm = np.ascontiguousarray(vertices_mm, np.float64)
        self.triangles = np.ascontiguousarray(triangles, np.int64)
        corners = self.vertices_mm[self.triangles]
        centroids = corners.mean(axis=1)
        self.radius_mm = np.sqrt(np.max(np.sum((corners - centroids[:, None, :]) ** 2, axis=2), axis=1))
        self.radius_max_mm = float(self.radius_mm.max())
        self.tree = cKDTree(centroids, balanced_tree=False, compact_nodes=False)
        self._face_normals = None
        self._neighbours = None

    @property
    def face_normals(self) -> np.ndarray:
        """Unit normals of the triangles (made when first asked for: the model-to-scan query does not)."""
        if self._face_normals is None:
            a, b, c = (self.vertices_mm[self.triangles[:, k]] for k in range(3))
            normals = np.cross(b - a, c - a)
            self._face_normals = normals / np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-300)
        return self._face_normals

    def _neighbour_lists(self):
        """For each triangle, the triangles whose centroids lie within NEIGHBOUR_REACH_RADII * radius_max of its
        centroid (CSR: start offsets and indices); made once, for many queries on a small surface."""
        if self._neighbours is None:
            reach = NEIGHBOUR_REACH_RADII * self.radius_max_mm
            lists = self.tree.query_ball_point(self.tree.data, reach)
            start = np.zeros(len(lists) + 1, np.int64)
            start[1:] = np.cumsum([len(entries) for entries in lists])
            self._neighbours = (reach, start, np.concatenate(lists).astype(np.int64))
        return self._neighbours

    def closest(self, points_mm: np.ndarray, first_k: int = 16) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Distance (mm), closest point (mm) and triangle of each query point.

        Many points on a small surface (a scan against the model) first try the nearest centroid's neighbour
        list (one nearest-neighbour query each); the rest, and few points on a large surface, query the k
        nearest centroids, more until the answer is exact.
        """
        kernel = _closest_kernel()
        points_mm = np.ascontiguousarray(points_mm, np.float64)
        n = len(points_mm)
        distance = np.empty(n)
        closest = np.empty((n, 3))
        triangle = np.empty(n, np.int64)
        pending = np.arange(n)
        if n > 10 * len(self.triangles):
            from phantom.scan import kernels as scan_kernels

            reach, start, neighbours = self._neighbour_lists()
            nearest_distance, nearest = self.tree.query(points_mm)
            done = np.zeros(n, np.bool_)
            scan_kernels.closest_by_neighbours(points_mm, nearest.astype(np.int64), nearest_distance, start,
                                               neighbours, self.tree.data, self.radius_mm, self.radius_max_mm,
                                               reach, self.vertices_mm, self.triangles, distance, closest,
                                               triangle, done)
            pending = pending[~done]
        k = min(first_k, len(self.triangles))
        while len(pending):
            # Threads pay off only for large batches: starting them costs milliseconds on a busy machine.
            workers = -1 if len(pending) > 50000 else 1
            centroid_distance, candidates = self.tree.query(points_mm[pending], k=k, workers=workers)
            centroid_distance = np.ascontiguousarray(centroid_distance.reshape(len(pending), -1))
            candidates = np.ascontiguousarray(candidates.reshape(len(pending), -1), np.int64)
            done = np.zeros(len(pending), np.bool_)
            kernel(points_mm, pending, candidates, centroid_distance, self.vertices_mm, self.triangles,
                   self.radius_mm, self.radius_max_mm, k >= len(self.triangles), distance, closest, triangle, done)
            pending = pending[~done]
            k = min(4 * k, len(self.triangles))
        return distance, closest, triangle


# --- alignment -------------------------------------------------------------------------------------------------


def point_to_plane_step(points: np.ndarray, targets: np.ndarray, normals: np.ndarray,
                        weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The small rotation vector and translation that minimise ``sum w ((R p + t - q) . n)^2`` (linearised)."""
    jacobian = np.hstack([np.cross(points, normals), normals])
    residual = np.einsum("ij,ij->i", points - targets, normals)
    weighted = jacobian * weights[:, None]
    solution = np.linalg.lstsq(weighted.T @ jacobian, -weighted.T @ residual, rcond=None)[0]
    return solution[:3], solution[3:]


def icp(points_mm: np.ndarray, correspond, rotation: np.ndarray, translation_mm: np.ndarray,
        max_iterations: int, tolerance_mm: float = 1e-3) -> tuple[np.ndarray, np.ndarray, float, int]:
    """Point-to-plane ICP of ``points_mm`` from a start; ``correspond(points)`` gives each point's distance,
    target point and target normal. Pairs farther than three times the median distance are left out (stray
    points, unfilled parts). Each Gauss-Newton step is halved until the (trimmed) sum of squared distances
    decreases: where the distances do not go to zero (a scan that differs from the model) the linearisation
    leaves out the surface's curvature and a full step can overshoot along a weakly constrained rotation.
    Stops when a step moves no point by more than ``tolerance_mm``. Returns rotation, translation, RMS distance
    (mm, all points, at the result) and iterations."""
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


def exact_correspondence(index: SurfaceIndex):
    """Closest points on the surface, with the direction from there to the point (the distance's gradient);
    the face normal for points on the surface. A face normal alone would be wrong where the closest point is on
    an edge or a corner (an offset surface mostly is): ICP would then minimise another objective and drift."""
    def correspond(points_mm):
        distance, closest, triangle = index.closest(points_mm)
        normals = index.face_normals[triangle]
        away = distance > 1e-9
        normals[away] = (points_mm[away] - closest[away]) / distance[away, None]
        return distance, closest, normals
    return correspond


def vertex_correspondence(vertices_mm: np.ndarray, normals: np.ndarray):
    """Nearest surface vertex and its normal: cheap, for the global start's many candidates."""
    from scipy.spatial import cKDTree

    tree = cKDTree(vertices_mm)

    def correspond(points_mm):
        distance, nearest = tree.query(points_mm)
        return distance, vertices_mm[nearest], normals[nearest]
    return correspond


@dataclass
class Frame:
    """A surface's area-weighted centroid (mm), principal axes (columns) and variances along them (mm^2)."""

    centroid_mm: np.ndarray
    axes: np.ndarray
    variances_mm2: np.ndarray

    @classmethod
    def of(cls, mesh: TriangleMesh) -> Frame:
        return cls(*principal_frame(mesh.vertices_mm, vertex_areas_mm2(mesh.vertices_mm, mesh.triangles)))

    @property
    def rms_radius_mm(self) -> float:
        """RMS distance of the surface from its centroid: its size, whatever its pose."""
        return float(np.sqrt(self.variances_mm2.sum()))


def check_scale(scan: Frame, model: Frame, units: str) -> None:
    """Raise ScanError when the scan's size is far from the model's, suggesting the unit that would fit."""
    ratio = scan.rms_radius_mm / model.rms_radius_mm
    if 1.0 / SCALE_TOLERANCE <= ratio <= SCALE_TOLERANCE:
        return
    hint = "scale it to millimetres before comparing"
    for unit, mm in UNITS_MM.items():
        if unit != units and 1.0 / SCALE_TOLERANCE <= ratio * mm / UNITS_MM[units] <= SCALE_TOLERANCE:
            hint = f"it looks like the file is in {unit}: pass --units {unit}"
    raise ScanError(f"the scan is {ratio:.3g} times the model's size (read in {units}), too far off to align: "
                    f"{hint}")


def align(scan: Frame, measured_points_mm: np.ndarray, model: TriangleMesh, model_frame: Frame,
          model_index: SurfaceIndex, rng: np.random.Generator) -> Alignment:
    """Rigid alignment of the scan onto the model surface: principal-axes candidates, each refined briefly by
    ICP on a few hundred points against the model's vertices; the best, and the best that lies more than
    AMBIGUOUS_ANGLE_DEG from it, refined on up to ICP_POINTS points against the exact surface, the better kept.
    Raises ScanError when even that leaves an RMS distance above FIT_RMS_LIMIT of the model's size."""
    scan_centroid, scan_axes = scan.centroid_mm, scan.axes
    model_centroid, model_axes = model_frame.centroid_mm, model_frame.axes
    few = measured_points_mm[rng.choice(len(measured_points_mm), min(START_POINTS, len(measured_points_mm)),
                                        replace=False)]
    coarse = vertex_correspondence(model.vertices_mm, vertex_normals(model.vertices_mm, model.triangles))
    starts = []
    for swap in axis_candidates():
        rotation = model_axes @ swap @ scan_axes.T
        translation = model_centroid - rotation @ scan_centroid
        starts.append(icp(few, coarse, rotation, translation, START_ITERATIONS))
    order = np.argsort([rms for _, _, rms, _ in starts])
    many = measured_points_mm[rng.choice(len(measured_points_mm), min(ICP_POINTS, len(measured_points_mm)),
                                         replace=False)]
    exact = exact_correspondence(model_index)
    best = icp(many, exact, *starts[order[0]][:2], ICP_MAX_ITERATIONS)
    # The best start that lies far from that one is refined too: the better of the two is the answer, and the
    # other's residual says how well the shape pins the rotation (nearly symmetric shapes fit both ways). A start
    # that ICP brings back to the best alignment is the same answer, not another one (it was reported as an
    # "ambiguous" rotation by 0 deg): the next far start is tried, up to ALTERNATIVE_TRIES refinements.
    alternative = None
    tries = 0
    for index in order[1:]:
        if tries == ALTERNATIVE_TRIES:
            break
        if rotation_angle_deg(starts[index][0] @ best[0].T) > AMBIGUOUS_ANGLE_DEG:
            tries += 1
            refined = icp(many, exact, *starts[index][:2], ICP_MAX_ITERATIONS)
            if rotation_angle_deg(refined[0] @ best[0].T) > AMBIGUOUS_ANGLE_DEG:
                alternative = refined
                break
    if alternative is not None and alternative[2] < best[2]:
        best, alternative = alternative, best
    rotation, translation, rms, iterations = best
    alternative_angle, alternative_rms = 180.0, np.inf
    if alternative is not None:
        alternative_angle, alternative_rms = rotation_angle_deg(alternative[0] @ rotation.T), alternative[2]
    size_mm = model_frame.rms_radius_mm
    if rms > FIT_RMS_LIMIT * size_mm:
        raise ScanError(f"no rigid alignment fits the scan to the model: the best leaves an RMS distance of "
                        f"{rms:.2f} mm ({100 * rms / size_mm:.0f} % of the model's size): is it this phantom, "
                        f"at these pressures?")
    return Alignment(rotation, translation, rms, iterations, alternative_angle, float(alternative_rms))


# --- distances -------------------------------------------------------------------------------------------------


def weighted_statistics(values: np.ndarray, weights: np.ndarray) -> dict:
    """Mean, median, 95th percentile and max of ``values`` with ``weights`` (area shares)."""
    order = np.argsort(values)
    sorted_values = values[order]
    cumulative = np.cumsum(weights[order])
    cumulative /= cumulative[-1]

    def quantile(q: float) -> float:
        return float(sorted_values[min(np.searchsorted(cumulative, q), len(values) - 1)])

    return {"mean": float(np.average(values, weights=weights)), "median": quantile(0.5), "p95": quantile(0.95),
            "max": float(sorted_values[-1])}


def model_surface(positions_m: np.ndarray, outer_triangles: np.ndarray) -> TriangleMesh:
    """The model's outer surface as its own mesh in mm (only the nodes on it)."""
    return compact(np.asarray(positions_m) * 1e3, np.asarray(outer_triangles, np.int64))


def compare(scan: TriangleMesh, model: TriangleMesh, model_volume_ml: float, units: str = "mm", seed: int = 0,
            clock: StageClock | None = None) -> Comparison:
    """Clean the scan, align it to the model surface (mm) and measure distances and volumes."""
    clock = clock or StageClock()
    with clock.stage("clean"):
        closed, measured, report = clean_scan(scan)
    with clock.stage("align"):
        scan_frame, model_frame = Frame.of(closed), Frame.of(model)
        check_scale(scan_frame, model_frame, units)
        model_index = SurfaceIndex(model.vertices_mm, model.triangles)
        alignment = align(scan_frame, measured.vertices_mm, model, model_frame, model_index,
                          np.random.default_rng(seed))
    with clock.stage("distances"):
        aligned = TriangleMesh(alignment.apply(closed.vertices_mm), closed.triangles)
        scan_distance, _, _ = model_index.closest(alignment.apply(measured.vertices_mm))
        scan_weights = vertex_areas_mm2(measured.vertices_mm, measured.triangles)
        # The model's vertices against the scan in the scan's own frame (the inverse motion), then back.
        in_scan_frame = (model.vertices_mm - alignment.translation_mm) @ alignment.rotation
        model_distance, model_closest, _ = SurfaceIndex(closed.vertices_mm, closed.triangles).closest(in_scan_frame)
        model_weights = vertex_areas_mm2(model.vertices_mm, model.triangles)
        outward = np.einsum("ij,ij->i", alignment.apply(model_closest) - model.vertices_mm,
                            vertex_normals(model.vertices_mm, model.triangles))
        signed = np.where(outward >= 0, model_distance, -model_distance)
        symmetric = weighted_statistics(np.concatenate([scan_distance, model_distance]),
                                        np.concatenate([scan_weights / scan_weights.sum(),
                                                        model_weights / model_weights.sum()]))
    return Comparison(report, alignment, surface_volume_ml(closed), model_volume_ml,
                      weighted_statistics(scan_distance, scan_weights),
                      weighted_statistics(model_distance, model_weights), symmetric, model.vertices_mm,
                      model.triangles, signed, aligned, clock)
