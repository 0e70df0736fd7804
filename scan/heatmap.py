"""Pictures of a scan comparison: the signed-distance heatmap on the model (PNG) and a Rerun recording."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from phantom import require_extra
from phantom.model.mesh.surface import subdivide
from phantom.scan.compare import Comparison, ScanError

if TYPE_CHECKING:
    from matplotlib.colors import Colormap, Normalize

#: Views: name, direction toward the viewer, and the coordinates shown right and up (a sign flips an axis so
#: that the picture is not mirrored). x is the patient's left, y anterior, z from apex to base.
VIEWS = (
    ("front (anterior)", np.array([0.0, 1.0, 0.0]), (0, 2), True),
    ("side (from the left, +x)", np.array([1.0, 0.0, 0.0]), (1, 2), False),
)
COLOUR_MAP = "RdBu_r"


def colour_limit_mm(signed_mm: np.ndarray) -> float:
    """Symmetric colour range: the largest |signed distance|, at least 0.05 mm (so noise is not saturated)."""
    return max(float(np.max(np.abs(signed_mm))), 0.05)


def shaded_faces(vertices: np.ndarray, triangles: np.ndarray, values: np.ndarray, toward_viewer: np.ndarray,
                 colour_map: Colormap, norm: Normalize) -> tuple[np.ndarray, np.ndarray]:
    """The faces that face the viewer, far to near (painter's order), with their colour times a Lambert
    shading (light from the viewer's upper left)."""
    a, b, c = (vertices[triangles[:, k]] for k in range(3))
    normals = np.cross(b - a, c - a)
    normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-300)
    facing = normals @ toward_viewer > 0
    light = toward_viewer + 0.4 * np.array([0.0, 0.0, 1.0]) + 0.3 * np.cross([0.0, 0.0, 1.0], toward_viewer)
    light /= np.linalg.norm(light)
    depth = ((a + b + c) / 3.0) @ toward_viewer
    order = np.flatnonzero(facing)[np.argsort(depth[facing])]
    colours = colour_map(norm(values[triangles[order]].mean(axis=1)))
    shade = 0.35 + 0.65 * np.clip(normals[order] @ light, 0.0, 1.0)
    colours[:, :3] *= shade[:, None]
    return order, colours


def write_heatmap(comparison: Comparison, path: str | Path, title: str) -> Path:
    """The model surface coloured by the signed distance to the scan (mm), front and side views, colour bar."""
    return write_surface_heatmap(comparison.model_vertices_mm, comparison.model_triangles,
                                 comparison.model_signed_distance_mm, path, title,
                                 "signed distance to the scan (mm): + scan outside the model")


def write_surface_heatmap(vertices_mm: np.ndarray, triangles: np.ndarray, signed_mm: np.ndarray, path: str | Path,
                          title: str, colour_label: str) -> Path:
    """A surface (mm) coloured by a signed distance per vertex (mm), front and side views, colour bar: a scan's
    comparison with the model, or the shape inverse's residual (``phantom inverse --shape``)."""
    # matplotlib (0.5 s to import, an optional extra) only where a picture is drawn
    with require_extra("scan"):
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
        from matplotlib.collections import PolyCollection

    path = Path(path)
    vertices, triangles, values = subdivide(vertices_mm, triangles, signed_mm)
    limit = colour_limit_mm(values)
    norm = matplotlib.colors.Normalize(-limit, limit)
    colour_map = matplotlib.colormaps[COLOUR_MAP]
    figure, axes = plt.subplots(1, 2, figsize=(9.5, 5.2), layout="constrained")
    for axis, (name, toward_viewer, (right, up), mirrored) in zip(axes, VIEWS, strict=True):
        order, colours = shaded_faces(vertices, triangles, values, toward_viewer, colour_map, norm)
        polygons = vertices[triangles[order]][:, :, [right, up]]
        axis.add_collection(PolyCollection(polygons, facecolors=colours, edgecolors=colours, linewidths=0.2))
        axis.autoscale_view()
        axis.set_aspect("equal")
        if mirrored:
            axis.invert_xaxis()
        axis.set_xlabel(f"{'xyz'[right]} (mm)")
        axis.set_ylabel(f"{'xyz'[up]} (mm)")
        axis.set_title(name, fontsize=10)
    bar = figure.colorbar(matplotlib.cm.ScalarMappable(norm, colour_map), ax=axes, shrink=0.8)
    bar.set_label(colour_label)
    figure.suptitle(title, fontsize=10)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        figure.savefig(path, dpi=110)
    except OSError as error:
        raise ScanError(f"cannot write the heatmap {path}: {error.strerror or error}") from None
    finally:
        plt.close(figure)
    return path


def write_recording(comparison: Comparison, path: str | Path, max_points: int = 200000) -> Path:
    """A Rerun recording: the model surface coloured per vertex (``model``, rr.Mesh3D) and the aligned scan's
    vertices (``scan``, rr.Points3D), in mm in the model's frame."""
    # matplotlib (0.5 s) and rerun-sdk (a second), optional extras, only where a recording is written
    with require_extra("scan"):
        import matplotlib
    with require_extra("record"):
        import rerun as rr

    path = Path(path)
    limit = colour_limit_mm(comparison.model_signed_distance_mm)
    rgba = matplotlib.colormaps[COLOUR_MAP](matplotlib.colors.Normalize(-limit, limit)(
        comparison.model_signed_distance_mm))
    points = comparison.scan_aligned.vertices_mm
    if len(points) > max_points:
        points = points[np.random.default_rng(0).choice(len(points), max_points, replace=False)]
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        stream = rr.RecordingStream("phantom_compare_scan")
        stream.save(str(path))
    except OSError as error:
        raise ScanError(f"cannot write the recording {path}: {error.strerror or error}") from None
    stream.log("model", rr.Mesh3D(vertex_positions=comparison.model_vertices_mm.astype(np.float32),
                                  triangle_indices=comparison.model_triangles.astype(np.uint32),
                                  vertex_colors=(255 * rgba).astype(np.uint8)))
    stream.log("model/signed_distance_mm", rr.AnyValues(signed_distance_mm=comparison.model_signed_distance_mm))
    stream.log("scan", rr.Points3D(points.astype(np.float32), radii=0.1, colors=[90, 90, 90]))
    stream.flush()
    stream.disconnect()
    return path
