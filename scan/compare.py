"""Compare a 3D scan of the phantom with the model: read, clean, align, measure (millimetres throughout).

A scan (OBJ, PLY or STL from photogrammetry or a structured-light scanner) is read in the unit it was exported
in, cleaned (largest connected piece kept, stray fragments dropped, its triangles wound one way, holes closed by
MeshFix so that its volume is defined), and aligned rigidly to the model's deformed outer surface
(:func:`phantom.model.mesh.surface.align`: principal axes, the 24 axis-to-axis candidates, point-to-plane ICP on
exact closest points). The result says how far the surfaces are apart (closest-point distances both ways,
area-weighted) and, per model vertex, the signed distance to the scan (positive where the scan lies outside the model).

The surface geometry itself (areas, normals, volumes, closest points, ICP) is the model's
(:mod:`phantom.model.mesh.surface`); what is here is about scans: reading their files, cleaning them, closing
their holes, and the comparison's report.
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from phantom import PhantomError, require_extra
from phantom.model.mesh.surface import (
    Alignment,
    AlignmentError,
    Frame,
    SurfaceIndex,
    TriangleMesh,
    align,
    compact,
    enclosed_volume_ml,
    triangle_areas_mm2,
    vertex_areas_mm2,
    vertex_normals,
)
from phantom.model.mesh.winding import WindingError, consistent_winding

#: Millimetres per unit of a scan file.
UNITS_MM = {"mm": 1.0, "cm": 10.0, "m": 1000.0}
SCAN_SUFFIXES = (".obj", ".ply", ".stl")
#: A scan whose size (area-weighted RMS radius) differs from the model's by more than this factor is not
#: aligned: its unit is wrong, or it is not this phantom.
SCALE_TOLERANCE = 1.5
#: The built-in phantom's size (builtin:calibrated's outer surface at rest, area-weighted RMS radius): what a scan
#: measured without a model is checked against, so that measuring a volume needs no model built.
PHANTOM_RMS_RADIUS_MM = 18.8


class ScanError(PhantomError):
    """A scan file that cannot be read or used, or a scan that does not fit the model."""


class StageClock:
    """Wall and CPU seconds per named stage. CPU time (all threads of this process) shows the work itself when
    other processes share the cores and stretch the wall time."""

    def __init__(self) -> None:
        self.wall_s: dict[str, float] = {}
        self.cpu_s: dict[str, float] = {}

    @contextlib.contextmanager
    def stage(self, name: str) -> Iterator[None]:
        """Time the ``with`` block as stage ``name`` (added to what the stage took before)."""
        wall, cpu = time.perf_counter(), time.process_time()
        try:
            yield
        finally:
            self.wall_s[name] = self.wall_s.get(name, 0.0) + time.perf_counter() - wall
            self.cpu_s[name] = self.cpu_s.get(name, 0.0) + time.process_time() - cpu


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
    rewound_triangles: int
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
        if self.rewound_triangles:
            parts.append(f"{self.rewound_triangles} triangles turned to face the same way as their neighbours")
        if self.reoriented:
            parts.append("faces turned outward")
        return "; ".join(parts)


@dataclass
class Comparison:
    """Everything ``compare-scan`` reports; distances in mm, volumes in ml."""

    clean: CleanReport
    alignment: Alignment
    scan_volume_ml: float
    model_volume_ml: float
    scan_to_model_mm: dict[str, float]
    model_to_scan_mm: dict[str, float]
    symmetric_mm: dict[str, float]
    model_vertices_mm: np.ndarray
    model_triangles: np.ndarray
    model_signed_distance_mm: np.ndarray
    scan_aligned: TriangleMesh
    clock: StageClock = field(default_factory=StageClock)

    def to_json(self) -> dict[str, Any]:
        """The report as one JSON object (mm, ml, %, s)."""
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
    # trimesh (1 s to import, an optional extra) only where a scan file is read
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
        vertices = np.asarray(getattr(loaded, "vertices", np.zeros((0, 3))), dtype=np.float64)
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
    kept: np.ndarray = keep & distinct
    return kept


def vertex_components(triangles: np.ndarray, n_vertices: int) -> np.ndarray:
    """Label of the connected piece of each vertex (vertices joined by triangle edges); scipy's graph search is
    about ten times faster than the model's edge-based union-find on a scan's half a million triangles."""
    # scipy.sparse (0.15 s to import) only where a scan is cleaned
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    rows, columns = triangles[:, [0, 1, 2]].ravel(), triangles[:, [1, 2, 0]].ravel()
    graph = coo_matrix((np.ones(len(rows), np.int8), (rows, columns)), shape=(n_vertices, n_vertices))
    labels: np.ndarray = connected_components(graph, directed=False)[1]
    return labels


def largest_component(triangles: np.ndarray, areas_mm2: np.ndarray) -> tuple[np.ndarray, int]:
    """Mask of the triangles of the connected piece with the largest area, and the number of pieces."""
    labels = vertex_components(triangles, int(triangles.max()) + 1)[triangles[:, 0]]
    _, labels = np.unique(labels, return_inverse=True)
    piece_area = np.bincount(labels, areas_mm2)
    return labels == int(np.argmax(piece_area)), len(piece_area)


def boundary_edges(triangles: np.ndarray) -> np.ndarray:
    """Directed edges (k, 2) that belong to one triangle only, as that triangle runs them."""
    directed = triangles[:, [[0, 1], [1, 2], [2, 0]]].reshape(-1, 2)
    n = int(triangles.max()) + 1
    ordered = np.sort(directed, axis=1).astype(np.int64)
    _, inverse, counts = np.unique(ordered[:, 0] * n + ordered[:, 1], return_inverse=True, return_counts=True)
    edges: np.ndarray = directed[counts[inverse.ravel()] == 1]
    return edges


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
    # pymeshfix (a native library, an optional extra) only where holes are closed
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


def _triangle_mesh(mesh: TriangleMesh, what: str) -> TriangleMesh:
    """``mesh``, or TypeError naming its type and the conversion (another library's mesh, trimesh's say, has
    ``vertices`` and ``faces``, not ``vertices_mm`` and ``triangles``)."""
    if not isinstance(mesh, TriangleMesh):
        raise TypeError(f"{what} must be a phantom.model.mesh.surface.TriangleMesh in mm, got "
                        f"{type(mesh).__module__}.{type(mesh).__qualname__}: convert it with "
                        f"TriangleMesh(mesh.vertices, mesh.faces) (scaled to mm), or read a file with read_scan")
    return mesh


def clean_scan(mesh: TriangleMesh) -> tuple[TriangleMesh, TriangleMesh, CleanReport]:
    """The watertight, outward-oriented largest piece of a scan, that piece before its holes were closed (the
    measured surface, for distances), and what was changed.

    Exactly coincident vertices are merged first (a triangle soup made in memory, as an STL file's is when read).
    The piece is wound one way (:func:`phantom.model.mesh.winding.consistent_winding`) before its holes are
    closed (each fill runs its hole's edges against the scan's) and turned outward after. Raises TypeError for
    anything but a TriangleMesh, ScanError for a scan whose triangles cannot be wound one way (non-manifold edges,
    one-sided).
    """
    mesh = _triangle_mesh(mesh, "a scan")
    vertices, triangles = merge_coincident_vertices(mesh.vertices_mm, mesh.triangles)
    areas = triangle_areas_mm2(vertices, triangles)
    keep = drop_degenerate(triangles, areas)
    triangles, areas = triangles[keep], areas[keep]
    if len(triangles) == 0:
        raise ScanError("the scan has no triangle of non-zero area")
    in_largest, pieces = largest_component(triangles, areas)
    measured = compact(vertices, triangles[in_largest])
    try:
        measured.triangles, rewound = consistent_winding(measured.triangles)
    except WindingError as error:
        raise ScanError(f"the scan's largest piece cannot be measured: {error}") from None
    closed, holes = close_holes(measured)
    reoriented = enclosed_volume_ml(closed) < 0
    if reoriented:
        # New meshes, not turned in place: a scan without holes comes back from close_holes as the same object,
        # which turning both in place would turn twice.
        closed = TriangleMesh(closed.vertices_mm, closed.triangles[:, ::-1].copy())
        measured = TriangleMesh(measured.vertices_mm, measured.triangles[:, ::-1].copy())
    report = CleanReport(
        input_vertices=len(mesh.vertices_mm), input_triangles=len(mesh.triangles),
        removed_degenerate_triangles=int(np.count_nonzero(~keep)), removed_components=pieces - 1,
        removed_component_triangles=int(np.count_nonzero(~in_largest)), holes_filled=holes,
        added_triangles=len(closed.triangles) - len(measured.triangles), rewound_triangles=rewound,
        reoriented=bool(reoriented),
        output_vertices=len(closed.vertices_mm), output_triangles=len(closed.triangles))
    return closed, measured, report


def scan_volume_ml(path: str | Path, units: str = "mm", model: TriangleMesh | None = None,
                   remedy: str = "export it in mm (or pass units={unit!r})", otherwise: str | None = None) -> float:
    """The volume (ml) of a scan file after cleaning: its largest piece, holes closed.

    Its size is checked as :func:`compare` checks it, against ``model``'s (a surface in mm) or, without one, the
    built-in phantom's (:data:`PHANTOM_RMS_RADIUS_MM`): a file in another unit is refused naming it, and saying
    what to do in the caller's terms (:func:`check_scale`'s ``remedy`` and ``otherwise``; by default this
    function's arguments).
    """
    closed, _, _ = clean_scan(read_scan(path, units))
    if model is None:
        reference_mm = PHANTOM_RMS_RADIUS_MM
        said = "scale it to mm, or pass model= (the phantom's surface in mm) if it is another phantom"
    else:
        reference_mm = Frame.of(_triangle_mesh(model, "the model surface")).rms_radius_mm
        said = "scale it to mm before measuring it"
    check_scale(Frame.of(closed).rms_radius_mm, reference_mm, units, "measure", remedy,
                said if otherwise is None else otherwise)
    return enclosed_volume_ml(closed)


def check_scale(scan_size_mm: float, model_size_mm: float, units: str, purpose: str = "align",
                remedy: str = "pass --units {unit}", otherwise: str = "scale it to millimetres before comparing"
                ) -> None:
    """Raise ScanError when the scan's size (RMS radius, mm) is far from the model's, suggesting the unit that
    would fit: ``remedy`` (``{unit}`` is filled in) says how to give that unit; ``otherwise`` what to do when
    none fits. The scan is about to be ``purpose``d (align, measure)."""
    ratio = scan_size_mm / model_size_mm
    if 1.0 / SCALE_TOLERANCE <= ratio <= SCALE_TOLERANCE:
        return
    hint = otherwise
    for unit, mm in UNITS_MM.items():
        if unit != units and 1.0 / SCALE_TOLERANCE <= ratio * mm / UNITS_MM[units] <= SCALE_TOLERANCE:
            hint = f"it looks like the file is in {unit}: {remedy.format(unit=unit)}"
    raise ScanError(f"the scan is {ratio:.3g} times the model's size (read in {units}), too far off to {purpose}: "
                    f"{hint}")


# --- distances -------------------------------------------------------------------------------------------------


def weighted_statistics(values: np.ndarray, weights: np.ndarray) -> dict[str, float]:
    """Mean, median, 95th percentile and max of ``values`` with ``weights`` (area shares)."""
    order = np.argsort(values)
    sorted_values = values[order]
    cumulative = np.cumsum(weights[order])
    cumulative /= cumulative[-1]

    def quantile(q: float) -> float:
        return float(sorted_values[min(int(np.searchsorted(cumulative, q)), len(values) - 1)])

    return {"mean": float(np.average(values, weights=weights)), "median": quantile(0.5), "p95": quantile(0.95),
            "max": float(sorted_values[-1])}


def compare(scan: TriangleMesh, model: TriangleMesh, model_volume_ml: float, units: str = "mm", seed: int = 0,
            clock: StageClock | None = None) -> Comparison:
    """Clean the scan, align it to the model surface (mm) and measure distances and volumes.

    Both are :class:`~phantom.model.mesh.surface.TriangleMesh` (another library's mesh raises TypeError)."""
    clock = clock or StageClock()
    model = _triangle_mesh(model, "the model surface")
    with clock.stage("clean"):
        closed, measured, report = clean_scan(scan)
    with clock.stage("align"):
        scan_frame, model_frame = Frame.of(closed), Frame.of(model)
        check_scale(scan_frame.rms_radius_mm, model_frame.rms_radius_mm, units)
        model_index = SurfaceIndex(model.vertices_mm, model.triangles)
        try:
            alignment = align(scan_frame, measured.vertices_mm, model, model_frame, model_index,
                              np.random.default_rng(seed))
        except AlignmentError as error:
            raise ScanError(f"no rigid alignment fits the scan to the model: the best leaves an RMS distance of "
                            f"{error.rms_mm:.2f} mm ({100 * error.rms_mm / error.size_mm:.0f} % of the model's "
                            f"size): is it this phantom, at these pressures?") from None
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
    return Comparison(report, alignment, enclosed_volume_ml(closed), model_volume_ml,
                      weighted_statistics(scan_distance, scan_weights),
                      weighted_statistics(model_distance, model_weights), symmetric, model.vertices_mm,
                      model.triangles, signed, aligned, clock)
