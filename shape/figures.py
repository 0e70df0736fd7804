"""Implicit-distance heatmaps between shapes (the paper's Figs. 5 and 6) and the cluster figures of a run.

The implicit distance at a point of surface A is its signed distance to surface B: positive outside B (A
reaches beyond B there), negative inside, measured to B's closest point (the sign from that triangle's outward
normal), as PyVista's ``compute_implicit_distance`` does. Each heatmap shows A from the front (anterior) and
from the side (the patient's left), in the phantom's frame, with a colour bar in mm.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from phantom import require_extra
from phantom.model.mesh.surface import SurfaceIndex
from phantom.shape.analysis import DecodedShape, ShapeModel
from phantom.shape.errors import ShapeError

#: The views: title, matplotlib's elevation and azimuth (degrees) in the phantom's frame (y anterior, x left).
VIEWS = (("front (anterior)", 0.0, 90.0), ("side (patient's left)", 0.0, 0.0))
COLOUR_MAP = "RdBu_r"


def implicit_distance_mm(points_mm: np.ndarray, vertices_mm: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Signed distance (mm) of points to a closed, outward-oriented surface: positive outside it."""
    index = SurfaceIndex(vertices_mm, triangles)
    distances, closest, triangle = index.closest(points_mm)
    side = np.einsum("ij,ij->i", points_mm - closest, index.face_normals[triangle])
    return np.where(side < 0, -distances, distances)


def write_heatmap(vertices_mm: np.ndarray, triangles: np.ndarray, distance_mm: np.ndarray, path: str | Path,
                  title: str, colour_bar_label: str) -> Path:
    """Surface A (phantom frame, mm) coloured by a value per vertex (mm), front and side, with a colour bar."""
    # matplotlib (0.5 s to import) only where a figure is drawn
    with require_extra("shape"):
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
        from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    limit = max(float(np.abs(distance_mm).max()), 0.1)
    norm = matplotlib.colors.Normalize(-limit, limit)
    colour_map = matplotlib.colormaps[COLOUR_MAP]
    face_colours = colour_map(norm(distance_mm[triangles].mean(axis=1)))
    centre = 0.5 * (vertices_mm.min(axis=0) + vertices_mm.max(axis=0))
    half = 0.5 * float((vertices_mm.max(axis=0) - vertices_mm.min(axis=0)).max())
    figure = plt.figure(figsize=(10, 5))
    for column, (name, elevation, azimuth) in enumerate(VIEWS):
        axis = figure.add_subplot(1, 2, column + 1, projection="3d")
        axis.add_collection3d(Poly3DCollection(vertices_mm[triangles], facecolors=face_colours, linewidths=0,
                                               shade=True, lightsource=matplotlib.colors.LightSource(315, 45)))
        for set_limits, c in zip((axis.set_xlim, axis.set_ylim, axis.set_zlim), centre, strict=True):
            set_limits(c - half, c + half)
        axis.set_box_aspect((1, 1, 1))
        axis.view_init(elev=elevation, azim=azimuth)
        axis.set_proj_type("ortho")
        axis.set_title(name)
        axis.set_axis_off()
    mappable = matplotlib.cm.ScalarMappable(norm=norm, cmap=colour_map)
    figure.colorbar(mappable, ax=figure.axes, shrink=0.7, label=colour_bar_label)
    figure.suptitle(title, fontsize=10)
    figure.savefig(path, dpi=110)
    plt.close(figure)
    return path


def pair_heatmap(a: DecodedShape, b: DecodedShape, path: str | Path, title: str, name_b: str) -> dict[str, Any]:
    """The implicit distance of A's surface to B's, drawn on A; the distance's range and mean magnitude."""
    distance = implicit_distance_mm(a.vertices_mm, b.vertices_mm, b.triangles)
    written = write_heatmap(a.vertices_mm, a.triangles, distance, path, title,
                            f"implicit distance to {name_b} (mm, + outside it)")
    return {"heatmap": str(written), "min_mm": round(float(distance.min()), 4),
            "max_mm": round(float(distance.max()), 4), "mean_abs_mm": round(float(np.abs(distance).mean()), 4)}


def cluster_figures(model: ShapeModel, k: int, out: str | Path, seed: int = 0) -> dict[str, Any]:
    """k-means clusters of a run: each decoded centre as ``cluster_<i>.ply`` and a heatmap for every pair of
    centres (``cluster_<i>_vs_<j>.png``, on centre i); returns a summary (sizes, volumes, distances)."""
    if k < 2:
        raise ShapeError(f"--k must be at least 2 to compare clusters, got {k}")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    centres, assignment, shapes = model.clusters(k, seed)
    clusters = []
    for number, shape in enumerate(shapes, 1):
        mesh = shape.write(out / f"cluster_{number}.ply")
        clusters.append({"cluster": number, "cases": int(np.count_nonzero(assignment == number - 1)),
                         "volume_ml": round(shape.volume_ml, 4), "mesh": str(mesh)})
    pairs = []
    for first in range(k):
        for second in range(first + 1, k):
            title = (f"cluster {first + 1} ({shapes[first].volume_ml:.1f} ml) vs cluster {second + 1} "
                     f"({shapes[second].volume_ml:.1f} ml); latent distance "
                     f"{np.linalg.norm(centres[first] - centres[second]):.2f}")
            summary = pair_heatmap(shapes[first], shapes[second], out / f"cluster_{first + 1}_vs_{second + 1}.png",
                                   title, f"cluster {second + 1}")
            pairs.append({"a": first + 1, "b": second + 1,
                          "latent_distance": round(float(np.linalg.norm(centres[first] - centres[second])), 4),
                          **summary})
    return {"run": str(model.run), "k": k, "clusters": clusters, "pairs": pairs}
