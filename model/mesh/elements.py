"""Reference elements: the linear and quadratic tetrahedron and triangle, their node order and quadrature rules.

Node order is meshio's (VTK's): a 10-node tetrahedron lists its four vertices, then the mid-edge nodes of the
edges (0,1), (1,2), (0,2), (0,3), (1,3), (2,3); a 6-node triangle its three vertices, then the mid-edge nodes of
(0,1), (1,2), (2,0). gmsh numbers the tetrahedron's last two edges the other way round (:data:`GMSH_TET10_ORDER`).
Shape functions are written in barycentric coordinates ``L``: a vertex ``L_i (2 L_i - 1)``, an edge ``4 L_i L_j``.

Quadrature rules are on the reference simplex (weights sum to its volume, 1/6, or area, 1/2):

- ``TET_DEGREE2``: 4 points, all weights positive; the quadratic tetrahedron's deviatoric energy (as Abaqus'
  C3D10 and FElupe's ``RegionQuadraticTetra`` integrate it): exact for the small-strain stiffness of a
  straight-sided element.
- ``TET_DEGREE3``: 5 points, one negative weight; exact for ``det(dx/dxi)``, a cubic in the reference coordinates
  for any (curved) quadratic tetrahedron, so the element volumes it gives are exact.
- ``TRIANGLE_DEGREE4``: 6 points (Dunavant); exact for the integrands of a quadratic face's enclosed volume
  ``x . (x_xi x x_eta) / 3`` (degree 4), of its gradient and of its Hessian.
"""

from __future__ import annotations

import numpy as np

from phantom.model.arrays import FloatArray, IntArray

#: The tetrahedron's edges (local vertex pairs) in the order of its mid-edge nodes 4..9.
TET10_EDGES = np.array([[0, 1], [1, 2], [0, 2], [0, 3], [1, 3], [2, 3]])
#: gmsh's node order of a 10-node tetrahedron in meshio's: gmsh swaps the last two mid-edge nodes.
GMSH_TET10_ORDER = np.array([0, 1, 2, 3, 4, 5, 6, 7, 9, 8])
#: Faces of a 4-node tetrahedron (local vertices), each ordered so its normal points away from the fourth vertex.
TET_FACES = np.array([[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]])


def _edge_node(first: int, second: int) -> int:
    """The local number (4..9) of the mid-edge node between vertices ``first`` and ``second``."""
    for index, (a, b) in enumerate(TET10_EDGES.tolist()):
        if {a, b} == {first, second}:
            return 4 + index
    raise ValueError(f"no edge between vertices {first} and {second}")


#: Faces of a 10-node tetrahedron as 6-node triangles (vertices as TET_FACES, then the mid-edge nodes of their
#: edges (0,1), (1,2), (2,0)).
TET10_FACES = np.array([[*face, _edge_node(face[0], face[1]), _edge_node(face[1], face[2]),
                         _edge_node(face[2], face[0])] for face in TET_FACES.tolist()])
#: A 6-node triangle split at its mid-edge nodes into four 3-node triangles of the same orientation (drawing).
TRIANGLE6_SPLIT = np.array([[0, 3, 5], [3, 1, 4], [5, 4, 2], [3, 4, 5]])
#: A reflection swaps vertices 1 and 2 to keep the volume positive; the mid-edge nodes follow.
TET10_REFLECTED = np.array([0, 2, 1, 3, 6, 5, 4, 7, 9, 8])

_A2, _B2 = 0.5854101966249685, 0.1381966011250105
TET_DEGREE2_POINTS = np.array([[_B2, _B2, _B2], [_A2, _B2, _B2], [_B2, _A2, _B2], [_B2, _B2, _A2]])
TET_DEGREE2_WEIGHTS = np.full(4, 1.0 / 24.0)
TET_DEGREE3_POINTS = np.array([[0.25, 0.25, 0.25], [0.5, 1 / 6, 1 / 6], [1 / 6, 0.5, 1 / 6], [1 / 6, 1 / 6, 0.5],
                               [1 / 6, 1 / 6, 1 / 6]])
TET_DEGREE3_WEIGHTS = np.array([-4 / 5, 9 / 20, 9 / 20, 9 / 20, 9 / 20]) / 6.0
_A4, _B4 = 0.445948490915965, 0.091576213509771
_W4A, _W4B = 0.223381589678011 / 2, 0.109951743655322 / 2
TRIANGLE_DEGREE4_POINTS = np.array([[_A4, _A4], [1 - 2 * _A4, _A4], [_A4, 1 - 2 * _A4],
                                    [_B4, _B4], [1 - 2 * _B4, _B4], [_B4, 1 - 2 * _B4]])
TRIANGLE_DEGREE4_WEIGHTS = np.array([_W4A, _W4A, _W4A, _W4B, _W4B, _W4B])


def tet10_shape(points: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Shape functions (q, 10) and their derivatives by the reference coordinates (q, 10, 3) of the 10-node
    tetrahedron at reference points (q, 3) (``xi, eta, zeta``; barycentric ``L = (1 - xi - eta - zeta, xi, eta,
    zeta)``)."""
    points = np.atleast_2d(points)
    bary = np.column_stack([1.0 - points.sum(axis=1), points])
    # dL_i / dxi_k
    bary_gradient = np.array([[-1.0, -1.0, -1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    values = np.empty((len(points), 10))
    derivatives = np.empty((len(points), 10, 3))
    for i in range(4):
        values[:, i] = bary[:, i] * (2.0 * bary[:, i] - 1.0)
        derivatives[:, i] = (4.0 * bary[:, i] - 1.0)[:, None] * bary_gradient[i]
    for k, (i, j) in enumerate(TET10_EDGES.tolist()):
        values[:, 4 + k] = 4.0 * bary[:, i] * bary[:, j]
        derivatives[:, 4 + k] = 4.0 * (bary[:, j, None] * bary_gradient[i] + bary[:, i, None] * bary_gradient[j])
    return values, derivatives


def triangle6_shape(points: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Shape functions (q, 6) and their derivatives by ``xi, eta`` (q, 6, 2) of the 6-node triangle at reference
    points (q, 2)."""
    points = np.atleast_2d(points)
    bary = np.column_stack([1.0 - points.sum(axis=1), points])
    bary_gradient = np.array([[-1.0, -1.0], [1.0, 0.0], [0.0, 1.0]])
    values = np.empty((len(points), 6))
    derivatives = np.empty((len(points), 6, 2))
    for i in range(3):
        values[:, i] = bary[:, i] * (2.0 * bary[:, i] - 1.0)
        derivatives[:, i] = (4.0 * bary[:, i] - 1.0)[:, None] * bary_gradient[i]
    for k, (i, j) in enumerate(((0, 1), (1, 2), (2, 0))):
        values[:, 3 + k] = 4.0 * bary[:, i] * bary[:, j]
        derivatives[:, 3 + k] = 4.0 * (bary[:, j, None] * bary_gradient[i] + bary[:, i, None] * bary_gradient[j])
    return values, derivatives


def split_triangles(faces: IntArray) -> IntArray:
    """3-node triangles of a surface of 3- or 6-node faces: the faces themselves, or four per 6-node face (for
    drawing and for anything that wants flat facets; the nodes are the mesh's own)."""
    faces = np.asarray(faces, dtype=np.int64)
    if faces.shape[1] == 3:
        return faces
    return faces[:, TRIANGLE6_SPLIT].reshape(-1, 3)


def face_vertices(faces: IntArray) -> IntArray:
    """The three vertex nodes of each face (the first three columns, for 3- and 6-node faces alike)."""
    vertices: IntArray = np.asarray(faces, dtype=np.int64)[:, :3]
    return vertices
