"""Synthetic scans made from a surface with known damage: used by the tests, bench/scan_*.py and
``phantom scan synthetic``.

A synthetic scan is the surface subdivided (midpoints: the same surface, more vertices), its vertices moved
along their normals by Gaussian noise (and optionally a constant offset), with holes cut out, a stray fragment
added beside it, and the whole moved by a known rigid transform: ``x_scan = R x + t``.
"""

from dataclasses import dataclass

import numpy as np

from phantom.model.mesh.surface import TriangleMesh, compact, subdivide, vertex_normals


@dataclass
class SyntheticScan:
    """The scan (mm) and the transform that made it from the surface: ``x_scan = rotation @ x + translation``."""

    mesh: TriangleMesh
    rotation: np.ndarray
    translation_mm: np.ndarray


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    """A rotation drawn uniformly (a random unit quaternion)."""
    q = rng.normal(size=4)
    w, x, y, z = q / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def make_scan(surface: TriangleMesh, rng: np.random.Generator, levels: int = 2, noise_mm: float = 0.0,
              offset_mm: float = 0.0, holes: int = 0, hole_radius_mm: float = 2.5, fragment: bool = False,
              rotation: np.ndarray | None = None, translation_mm: np.ndarray | None = None) -> SyntheticScan:
    """A damaged, moved copy of ``surface`` (mm); see the module docstring."""
    vertices, triangles = surface.vertices_mm, surface.triangles
    for _ in range(levels):
        vertices, triangles = subdivide(vertices, triangles)
    normals = vertex_normals(vertices, triangles)
    vertices = vertices + normals * (offset_mm + noise_mm * rng.normal(size=(len(vertices), 1)))
    if holes:
        if holes > len(vertices):
            raise ValueError(f"{holes} holes need as many vertices to centre them on; the surface has "
                             f"{len(vertices)}")
        centres = vertices[rng.choice(len(vertices), holes, replace=False)]
        centroid = vertices[triangles].mean(axis=1)
        near = np.zeros(len(triangles), dtype=bool)
        for centre in centres:  # one at a time: all at once is triangles x holes x 3 (GBs at millions of triangles)
            near |= np.linalg.norm(centroid - centre, axis=1) < hole_radius_mm
        triangles = triangles[~near]
    mesh = compact(vertices, triangles)
    if fragment:
        mesh = _with_fragment(mesh)
    rotation = np.eye(3) if rotation is None else rotation
    translation_mm = np.zeros(3) if translation_mm is None else np.asarray(translation_mm, float)
    return SyntheticScan(TriangleMesh(mesh.vertices_mm @ rotation.T + translation_mm, mesh.triangles), rotation,
                         translation_mm)


def _with_fragment(mesh: TriangleMesh) -> TriangleMesh:
    """Add a small closed tetrahedron (a stray reconstruction blob) 8 mm outside the surface's extent."""
    corner = mesh.vertices_mm.max(axis=0) + 8.0
    blob = corner + 3.0 * np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    faces = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]]) + len(mesh.vertices_mm)
    return TriangleMesh(np.vstack([mesh.vertices_mm, blob]), np.vstack([mesh.triangles, faces]))


def sphere(radius_mm: float, centre_mm: np.ndarray, levels: int = 4, dent_mm: float = 0.0) -> TriangleMesh:
    """A closed sphere (mm): an octahedron subdivided ``levels`` times and pushed out, optionally with a round
    dent of depth ``dent_mm`` facing +y (a bowl no line of sight grazes: what a visual hull cannot see)."""
    vertices = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], float)
    triangles = np.array([[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4], [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]])
    for _ in range(levels):
        vertices, triangles = subdivide(vertices, triangles)
        vertices /= np.linalg.norm(vertices, axis=1, keepdims=True)
    angle = np.arccos(np.clip(vertices[:, 1], -1, 1))
    radius = radius_mm - dent_mm * np.exp(-(angle / 0.25) ** 2)
    return TriangleMesh(vertices * radius[:, None] + np.asarray(centre_mm, float), triangles.astype(np.int64))

