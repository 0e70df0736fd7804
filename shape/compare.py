"""Two shapes compared the paper's two ways: the mean closest-point distance after ICP, and the latent distance.

B is aligned rigidly onto A (the model's :func:`phantom.model.mesh.surface.align`: principal-axes starts, then
ICP on exact closest points); the mean closest-point distance is the area-weighted mean of the distances from
each surface's vertices to the other surface, averaged over the two directions; the latent distance is the
Euclidean distance between the encoder's means of A and of the aligned B, both put on the run's grid centred
on their centroids. A shape and itself moved rigidly are at distance 0 both ways.

Shapes are handled in RAS mm (see :mod:`phantom.shape.voxels`); meshes given in the phantom's frame are turned
into RAS first, so a mesh of the phantom model and a mask from an MRI land in the same anatomical frame.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from phantom.model.mesh.surface import (
    Frame,
    SurfaceIndex,
    TriangleMesh,
    align,
    vertex_areas_mm2,
)
from phantom.model.mesh.tetmesh import open_edge_count
from phantom.shape.analysis import ShapeModel
from phantom.shape.errors import ShapeError
from phantom.shape.voxels import ClosedSurface, LabelMask, surface_of

#: Two different shapes align when ICP leaves an RMS distance below this fraction of A's RMS radius (a scan of
#: the same object is held to 0.1, phantom.model.mesh.surface.FIT_RMS_LIMIT).
SHAPE_FIT_RMS_LIMIT = 0.5
#: A mask is surfaced for the distances on a grid this many times finer than the run's.
MASK_SURFACE_REFINEMENT = 2


@dataclass
class ShapeComparison:
    """The two distances between shapes A and B, what the alignment did, and the surfaces (RAS mm: A, and B
    aligned onto it)."""

    latent_distance: float
    mean_distance_mm: float
    a_to_b_mm: float
    b_to_a_mm: float
    rotation_deg: float
    icp_rms_mm: float
    volume_a_ml: float
    volume_b_ml: float
    latent_a: np.ndarray
    latent_b: np.ndarray
    surface_a: ClosedSurface
    aligned_b: ClosedSurface

    def to_json(self) -> dict[str, Any]:
        """The comparison as JSON-ready values."""
        return {"latent_distance": round(self.latent_distance, 6),
                "mean_distance_mm": round(self.mean_distance_mm, 4), "a_to_b_mm": round(self.a_to_b_mm, 4),
                "b_to_a_mm": round(self.b_to_a_mm, 4), "rotation_deg": round(self.rotation_deg, 3),
                "icp_rms_mm": round(self.icp_rms_mm, 4), "volume_a_ml": round(self.volume_a_ml, 4),
                "volume_b_ml": round(self.volume_b_ml, 4)}


def phantom_mesh(mesh: TriangleMesh) -> ClosedSurface:
    """A closed mesh in the phantom's frame (mm) as a surface in RAS, checked closed."""
    open_edges = open_edge_count(np.asarray(mesh.triangles))
    if open_edges:
        raise ShapeError(f"the mesh is not closed ({open_edges} open edges): close its holes first")
    return ClosedSurface(np.asarray(mesh.vertices_mm, float), np.asarray(mesh.triangles)).outward().mirrored_x()


def closed_surface(model: ShapeModel, shape: LabelMask | ClosedSurface) -> ClosedSurface:
    """A shape's closed surface in RAS mm: a mesh as it is, a mask surfaced on a grid finer than the run's."""
    if isinstance(shape, ClosedSurface):
        return shape
    centre = shape.centroid_mm()
    voxel_mm = model.voxel_mm / MASK_SURFACE_REFINEMENT
    size = model.grid_size * MASK_SURFACE_REFINEMENT
    surface = surface_of(shape.occupancy(centre, voxel_mm, size), voxel_mm)
    return ClosedSurface(surface.vertices_mm + centre, surface.triangles)


def mean_closest_distances_mm(a: ClosedSurface, b: ClosedSurface) -> tuple[float, float]:
    """Area-weighted mean distance (mm) from A's vertices to B's surface, and from B's to A's."""
    def one_way(source: ClosedSurface, target: ClosedSurface) -> float:
        distances, _, _ = SurfaceIndex(target.vertices_mm, target.triangles).closest(source.vertices_mm)
        weights = vertex_areas_mm2(source.vertices_mm, source.triangles)
        return float(np.sum(distances * weights) / np.sum(weights))

    return one_way(a, b), one_way(b, a)


def compare_shapes(model: ShapeModel, a: LabelMask | ClosedSurface, b: LabelMask | ClosedSurface,
                   names: tuple[str, str] = ("A", "B"), seed: int = 0) -> ShapeComparison:
    """Align B onto A, then both distances (see the module docstring)."""
    surface_a, surface_b = closed_surface(model, a), closed_surface(model, b)
    mesh_a = TriangleMesh(surface_a.vertices_mm, surface_a.triangles)
    mesh_b = TriangleMesh(surface_b.vertices_mm, surface_b.triangles)
    alignment = align(Frame.of(mesh_b), surface_b.vertices_mm, mesh_a, Frame.of(mesh_a),
                      SurfaceIndex(surface_a.vertices_mm, surface_a.triangles), np.random.default_rng(seed),
                      SHAPE_FIT_RMS_LIMIT)
    moved_b = ClosedSurface(alignment.apply(surface_b.vertices_mm), surface_b.triangles)
    a_to_b, b_to_a = mean_closest_distances_mm(surface_a, moved_b)
    latents = model.encode_grids(np.stack([model.grid_of(surface_a, names[0]), model.grid_of(moved_b, names[1])]))
    return ShapeComparison(float(np.linalg.norm(latents[0] - latents[1])), 0.5 * (a_to_b + b_to_a), a_to_b,
                           b_to_a, alignment.rotation_angle_deg, alignment.rms_mm, surface_a.volume_ml(),
                           moved_b.volume_ml(), latents[0], latents[1], surface_a, moved_b)


def compare_files(model: ShapeModel, a: str | Path, b: str | Path) -> ShapeComparison:
    """:func:`compare_shapes` of two shape files (masks, label maps with the run's labels, closed meshes)."""
    return compare_shapes(model, model.read(a), model.read(b), (str(a), str(b)))


def latent_distance(run: str | Path | ShapeModel, mesh_a: TriangleMesh, mesh_b: TriangleMesh) -> float:
    """The latent distance between two closed meshes (mm, the phantom's frame) after aligning B onto A.

    ``run`` is a trained run folder or a loaded :class:`~phantom.shape.analysis.ShapeModel`.
    """
    model = run if isinstance(run, ShapeModel) else ShapeModel.load(run)
    return compare_shapes(model, phantom_mesh(mesh_a), phantom_mesh(mesh_b)).latent_distance
