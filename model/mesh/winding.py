"""Triangle surfaces wound one way: inconsistent winding made consistent, a closed surface turned outward.

A surface read from a file (a scan, a target gland, a shape) may have some triangles listed clockwise and some
counter-clockwise (an exporter that mixes them, a hand-edited STL). Its enclosed volume by the divergence
theorem is then wrong without a warning: every flipped triangle subtracts what it should add. Every reader
whose volume counts passes the surface through here before using it:

- :func:`consistent_winding`: each edge-connected piece wound one way, the way most of its triangles already
  run (an open surface too: a scan before its holes are closed); a surface that is already consistent comes back
  as the same array.
- :func:`outward_surface`: a closed surface consistently wound and facing outward (positive volume).

The winding is found on the double cover of the triangles' adjacency: each triangle as it is and turned, two
triangles that share an edge joined as-is to as-is when they run the edge opposite ways (they agree) and as-is to
turned when they run it the same way. A one-sided piece (a Moebius strip) joins a triangle to its own turned
self; an orientable piece falls into two mirror components, and the one that keeps most triangles as they are is
taken. One graph search (scipy) for the whole surface, 5120 triangles in milliseconds (trimesh's
``repair.fix_winding``, a networkx traversal and an optional extra, took 0.26 s and refuses nothing).

A surface that cannot be wound one way raises :class:`WindingError`: an edge shared by more than two triangles
(non-manifold: which two of them should agree is undefined) while the winding disagrees somewhere, or a
one-sided piece.
"""

from __future__ import annotations

import numpy as np

from phantom import PhantomError
from phantom.model.arrays import FloatArray, IntArray
from phantom.model.mesh.surface import TriangleMesh, enclosed_volume_ml
from phantom.model.mesh.tetmesh import surface_components

#: What the message suggests for a non-manifold surface whose winding disagrees.
REPAIR_HINT = ("repair it (MeshLab: Filters > Cleaning and Repairing > Repair non Manifold Edges, then Normals > "
               "Re-Orient all faces coherently) and export again")
#: What the message suggests for a one-sided surface.
REBUILD_HINT = "it is no solid's surface: rebuild it (e.g. screened Poisson in MeshLab) and export again"


class WindingError(PhantomError):
    """A triangle surface whose triangles cannot all be wound one way (non-manifold edges, or one-sided)."""


def consistent_winding(triangles: IntArray) -> tuple[IntArray, int]:
    """The triangles with each edge-connected piece wound one way, and how many were turned.

    Each piece keeps the winding of most of its triangles (a tie: either, always the same). A surface
    that is already consistent (every edge of two triangles run opposite ways by them) is returned as the same
    array, with 0. Open edges (one triangle) are allowed. Raises WindingError (see the module).
    """
    triangles = np.asarray(triangles, dtype=np.int64)
    if len(triangles) == 0:
        return triangles, 0
    directed = triangles[:, [[0, 1], [1, 2], [2, 0]]].reshape(-1, 2)
    n_vertices = int(triangles.max()) + 1
    key = directed.min(axis=1) * n_vertices + directed.max(axis=1)
    order = np.argsort(key, kind="stable")
    sorted_key = key[order]
    starts = np.flatnonzero(np.concatenate([[True], sorted_key[1:] != sorted_key[:-1]]))
    counts = np.diff(np.append(starts, len(key)))
    pairs = starts[counts == 2]
    first, second = order[pairs], order[pairs + 1]
    # two triangles that run their shared edge the same way disagree: one of them faces the other side
    disagree = directed[first, 0] == directed[second, 0]
    if not disagree.any():
        return triangles, 0
    shared_by_more = int(np.count_nonzero(counts > 2))
    if shared_by_more:
        raise WindingError(f"the triangles do not all face one way ({np.count_nonzero(disagree)} edges run the same "
                           f"way by both their triangles) and {shared_by_more} edges are shared by more than two "
                           f"triangles (non-manifold), so no one way can be chosen: {REPAIR_HINT}")
    flip = _flips(len(triangles), first // 3, second // 3, disagree)
    wound = triangles.copy()
    wound[flip] = wound[flip][:, ::-1]
    return wound, int(np.count_nonzero(flip))


def _flips(n_triangles: int, first: IntArray, second: IntArray, disagree: np.ndarray) -> np.ndarray:
    """Which triangles to turn, from the pairs that share an edge and whether they disagree (the double cover)."""
    # scipy.sparse (0.15 s to import) only where a winding is repaired
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    turned = n_triangles
    rows = np.concatenate([first, first + turned])
    columns = np.concatenate([np.where(disagree, second + turned, second), np.where(disagree, second, second + turned)])
    graph = coo_matrix((np.ones(len(rows), np.int8), (rows, columns)), shape=(2 * n_triangles, 2 * n_triangles))
    labels = connected_components(graph, directed=False)[1]
    as_is, flipped = labels[:n_triangles], labels[n_triangles:]
    one_sided = as_is == flipped
    if one_sided.any():
        raise WindingError(f"the surface is one-sided (like a Moebius strip or a Klein bottle: "
                           f"{np.count_nonzero(one_sided)} triangles cannot all face one way), so it encloses no "
                           f"volume: {REBUILD_HINT}")
    # each piece is the pair of mirror components {as_is, flipped}; keep the side most triangles are on as they are
    piece = np.unique(np.minimum(as_is, flipped), return_inverse=True)[1].ravel()
    on_lower = as_is < flipped
    keep_lower = 2 * np.bincount(piece, on_lower.astype(float)) >= np.bincount(piece)
    flip: np.ndarray = on_lower != keep_lower[piece]
    return flip


def signed_volumes_ml(vertices_mm: FloatArray, triangles: IntArray) -> FloatArray:
    """Each triangle's signed share (ml) of the volume a closed surface in mm encloses (the divergence theorem,
    about the origin)."""
    a, b, c = (vertices_mm[triangles[:, k]] for k in range(3))
    shares: FloatArray = np.einsum("ij,ij->i", a, np.cross(b, c)) / 6.0 / 1e3
    return shares


def outward_surface(mesh: TriangleMesh) -> tuple[TriangleMesh, int]:
    """A closed surface wound one way and facing outward, and how many triangles were turned to agree.

    A consistent surface is turned as a whole when its volume is negative (nothing else changes). When the
    winding had to be repaired, each connected piece is turned outward on its own (a piece whose triangles were
    half one way has no majority to trust), so a piece inside another counts as a body, not a cavity. Raises
    WindingError (see the module).
    """
    wound, rewound = consistent_winding(mesh.triangles)
    if rewound:
        shares = signed_volumes_ml(mesh.vertices_mm, wound)
        pieces = surface_components(wound)
        inward = np.bincount(pieces, shares) < 0
        turn = inward[pieces]
        wound[turn] = wound[turn][:, ::-1]
    surface = TriangleMesh(mesh.vertices_mm, wound)
    if enclosed_volume_ml(surface) < 0:
        surface = TriangleMesh(mesh.vertices_mm, wound[:, ::-1].copy())
    return surface, rewound
