"""Tagged tetrahedral meshes: reading, checking, writing, and the surfaces the solver needs.

A mesh is a set of nodes (m), positively oriented tetrahedra (4-node, or 10-node quadratic ones in meshio's node
order, :mod:`phantom.model.mesh.elements`), and named surface groups (faces of 3 or 6 nodes): chamber walls, the
fixation patch, anything else a file carries. :func:`prepare_surfaces` turns a scene's group names into oriented
chamber walls, the outer boundary and the fixed nodes, checking each on the way. Volumes enclosed by 6-node
faces are those of the curved (quadratic) surface, exactly.
"""

import contextlib
import signal
import threading
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from phantom import written_atomically
from phantom.model.errors import MeshError
from phantom.model.mesh.elements import (
    GMSH_TET10_ORDER,
    TET10_FACES,
    TET10_REFLECTED,
    TET_DEGREE2_POINTS,
    TET_DEGREE3_POINTS,
    TET_FACES,
    TRIANGLE_DEGREE4_POINTS,
    TRIANGLE_DEGREE4_WEIGHTS,
    face_vertices,
    split_triangles,
    tet10_shape,
    triangle6_shape,
)

#: A 6-node face with its orientation reversed (vertices 2, 1, 0 and their mid-edge nodes).
REVERSED_TRIANGLE6 = np.array([2, 1, 0, 4, 3, 5])


@dataclass
class TetMesh:
    """Nodes in metres, tetrahedra (positive volume) and named surface groups (triangles, node indices)."""

    nodes_m: np.ndarray
    tets: np.ndarray
    surface_groups: dict[str, np.ndarray] = field(default_factory=dict)

    @property
    def n_nodes(self) -> int:
        return len(self.nodes_m)

    @property
    def order(self) -> int:
        """1 for 4-node tetrahedra, 2 for 10-node (quadratic) ones."""
        return 1 if self.tets.shape[1] == 4 else 2


@dataclass
class Surfaces:
    """The surfaces a scene uses, oriented and checked: faces of the mesh's order (3 or 6 nodes).

    chamber_faces : list of (k_i, 3 or 6) int arrays, each wall oriented with normals out of its cavity, so
        the volume it encloses is positive.
    outer_faces : (k, 3 or 6) int array, the outer boundary with outward normals (encloses the gland).
    fixed_faces : (k, 3 or 6) int array or None, the fixation patch.

    The ``*_triangles`` properties give the same surfaces as 3-node triangles (a 6-node face split in four at its
    mid-edge nodes), for drawing and for whatever wants flat facets.
    """

    chamber_faces: list[np.ndarray]
    outer_faces: np.ndarray
    fixed_faces: np.ndarray | None

    @property
    def chamber_triangles(self) -> list[np.ndarray]:
        return [split_triangles(faces) for faces in self.chamber_faces]

    @property
    def outer_triangles(self) -> np.ndarray:
        return split_triangles(self.outer_faces)

    @property
    def fixed_triangles(self) -> np.ndarray | None:
        return None if self.fixed_faces is None else split_triangles(self.fixed_faces)


def tet_signed_volumes_m3(nodes_m: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """Signed volume of each tetrahedron's vertices, ``det[x1-x0, x2-x0, x3-x0] / 6`` (m^3); positive when
    right-handed (for a 10-node tetrahedron, the straight one through its vertices)."""
    x0 = nodes_m[tets[:, 0]]
    edges = nodes_m[tets[:, 1:4]] - x0[:, None, :]
    volumes: np.ndarray = np.linalg.det(edges) / 6.0
    return volumes


#: The 6-node triangle's shape functions and derivatives at the degree-4 points (the quadratic faces' rule).
_FACE_SHAPE, _FACE_DERIVATIVES = triangle6_shape(TRIANGLE_DEGREE4_POINTS)
_FACE_ALONG_XI, _FACE_ALONG_ETA = (np.ascontiguousarray(_FACE_DERIVATIVES[:, :, axis]) for axis in (0, 1))


def quadratic_face_frames(positions_m: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray,
                                                                                 np.ndarray]:
    """At each degree-4 point of each 6-node face: its position ``x`` (k, q, 3) and the tangents ``x_xi``,
    ``x_eta`` (k, q, 3) (their cross product is the normal scaled by the area per unit reference area)."""
    corners = positions_m[faces]                       # (k, 6, 3)
    # (q, 6) @ (k, 6, 3): matmul, a quarter of einsum's time on the chambers' few hundred faces
    return _FACE_SHAPE @ corners, _FACE_ALONG_XI @ corners, _FACE_ALONG_ETA @ corners


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a x b`` over the last axis (3) by components: np.cross's checks and copies took most of its time on the
    chambers' face arrays, which the path's every Newton iteration measures."""
    product = np.empty(np.broadcast_shapes(a.shape, b.shape))
    product[..., 0] = a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1]
    product[..., 1] = a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2]
    product[..., 2] = a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]
    return product


def enclosed_volume_m3(positions_m: np.ndarray, triangles: np.ndarray) -> float:
    """Volume enclosed by a closed, consistently oriented surface of 3- or 6-node faces (m^3).

    By the divergence theorem, ``V = 1/3 integral x . n dA``: ``sum_t x0 . (x1 x x2) / 6`` over flat triangles
    (normals outward); over 6-node faces the integrand ``x . (x_xi x x_eta)`` is a polynomial of degree 4,
    integrated exactly by the degree-4 rule, so the volume is that of the curved surface.
    """
    if triangles.shape[1] == 6:
        points, along_xi, along_eta = quadratic_face_frames(positions_m, triangles)
        integrand = np.einsum("kqi,kqi->kq", points, _cross(along_xi, along_eta))
        return float(np.einsum("kq,q->", integrand, TRIANGLE_DEGREE4_WEIGHTS) / 3.0)
    x0, x1, x2 = (positions_m[triangles[:, k]] for k in range(3))
    return float(np.einsum("ij,ij->", x0, _cross(x1, x2)) / 6.0)


def volume_gradient_m2(positions_m: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Gradient of the enclosed volume with respect to each node position, (n, 3) in m^2.

    Flat triangles: each gives ``a_t n_t / 3`` to each of its vertices. 6-node faces: node a gets
    ``integral N_a n dA`` (degree 4, exact). On a closed surface either is the exact derivative of
    :func:`enclosed_volume_m3`, and ``p`` times it is the nodal pressure force.
    """
    if triangles.shape[1] == 6:
        _, along_xi, along_eta = quadratic_face_frames(positions_m, triangles)
        normals = _cross(along_xi, along_eta) * TRIANGLE_DEGREE4_WEIGHTS[:, None]
        shares = _FACE_SHAPE.T @ normals                # (k, 6, 3): each face node's share
    else:
        x0, x1, x2 = (positions_m[triangles[:, k]] for k in range(3))
        shares = np.repeat((_cross(x1 - x0, x2 - x0) / 6.0)[:, None, :], 3, axis=1)
    # every (node, axis) summed in one bincount over the flattened dofs
    dofs = (3 * triangles[:, :, None] + np.arange(3)).ravel()
    gradient: np.ndarray = np.bincount(dofs, shares.ravel(), 3 * len(positions_m)).reshape(-1, 3)
    return gradient


def curved_jacobian_determinants(nodes_m: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """det(dX/dxi) of each 10-node tetrahedron at its quadrature points (m, 9): the degree-2 points, then the
    degree-3 ones (a curved element folds over itself where one is not positive)."""
    _, derivatives = tet10_shape(np.vstack([TET_DEGREE2_POINTS, TET_DEGREE3_POINTS]))
    jacobians = np.einsum("eai,qaj->eqij", nodes_m[tets], derivatives)
    determinants: np.ndarray = np.linalg.det(jacobians)
    return determinants


def check_tets(nodes_m: np.ndarray, tets: np.ndarray, source: str) -> np.ndarray:
    """Check tetrahedra (4- or 10-node) and return them positively oriented.

    Raises MeshError when there are none, when an index is out of range, when a node belongs to no
    tetrahedron, when some are degenerate (volume below 1e-9 of a cube of the mean edge length), when
    orientations are mixed (some inverted), or when a curved 10-node element folds over itself (its Jacobian
    is not positive at a quadrature point). A mesh whose tetrahedra are all negatively oriented follows the
    other convention and is flipped.
    """
    if len(tets) == 0:
        raise MeshError(f"{source}: the mesh has no tetrahedra: export the volume (a 3D physical group in gmsh)")
    if tets.min() < 0 or tets.max() >= len(nodes_m):
        raise MeshError(f"{source}: tetrahedra refer to nodes that do not exist (index {tets.max()})")
    unused = np.setdiff1d(np.arange(len(nodes_m)), tets)
    if len(unused):
        raise MeshError(
            f"{source}: {len(unused)} node(s) lie outside every tetrahedron (first: node {unused[0]} at "
            f"{nodes_m[unused[0]].tolist()}): remove unused nodes (gmsh: do not set Mesh.SaveAll)"
        )
    volumes = tet_signed_volumes_m3(nodes_m, tets)
    edge_m = np.mean(np.linalg.norm(nodes_m[tets[:, 1:4]] - nodes_m[tets[:, :1]], axis=2))
    degenerate = np.flatnonzero(np.abs(volumes) < 1e-9 * edge_m**3)
    if len(degenerate):
        raise MeshError(
            f"{source}: {len(degenerate)} degenerate (flat) tetrahedra, first: tet {degenerate[0]} with nodes "
            f"{tets[degenerate[0]].tolist()}: remesh"
        )
    inverted = np.flatnonzero(volumes < 0)
    if len(inverted) == len(tets):
        tets = tets[:, [0, 2, 1, 3]] if tets.shape[1] == 4 else tets[:, TET10_REFLECTED]
    elif len(inverted):
        raise MeshError(
            f"{source}: {len(inverted)} of {len(tets)} tetrahedra are inverted (negative volume), first: tet "
            f"{inverted[0]} with nodes {tets[inverted[0]].tolist()}: remesh or fix their node order"
        )
    if tets.shape[1] == 10:
        folded = np.flatnonzero(curved_jacobian_determinants(nodes_m, tets).min(axis=1) <= 0)
        if len(folded):
            raise MeshError(
                f"{source}: {len(folded)} curved 10-node tetrahedra fold over themselves (Jacobian <= 0 inside), "
                f"first: tet {folded[0]} with nodes {tets[folded[0]].tolist()}: remesh (gmsh: "
                f"Mesh.HighOrderOptimize) or straighten their mid-edge nodes"
            )
    return tets


def boundary_faces(tets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Faces that belong to one tetrahedron only, with outward normals (3-node faces of 4-node tetrahedra, 6-node
    faces of 10-node ones), and the tetrahedron of each."""
    local = TET_FACES if tets.shape[1] == 4 else TET10_FACES
    faces = tets[:, local].reshape(-1, local.shape[1])
    _, first, counts = np.unique(_face_keys(faces, tets.max() + 1), return_index=True, return_counts=True)
    single = first[counts == 1]
    return faces[single], single // 4


def _face_keys(faces: np.ndarray, n_nodes: int) -> np.ndarray:
    """One integer per face, equal for the same three vertices in any order (a fast key for np.unique)."""
    ordered = np.sort(face_vertices(faces), axis=1).astype(np.int64)
    return (ordered[:, 0] * n_nodes + ordered[:, 1]) * n_nodes + ordered[:, 2]


def _edge_keys(triangles: np.ndarray) -> np.ndarray:
    """One integer per triangle edge (3 per triangle, in order), equal for both directions of an edge."""
    edges = np.sort(triangles[:, [[0, 1], [1, 2], [2, 0]]].reshape(-1, 2), axis=1).astype(np.int64)
    return edges[:, 0] * (int(triangles.max()) + 1) + edges[:, 1]


def _face_lookup(faces: np.ndarray) -> dict[tuple[int, int, int], int]:
    return {tuple(key): row for row, key in enumerate(np.sort(face_vertices(faces), axis=1).tolist())}


def open_edge_count(triangles: np.ndarray) -> int:
    """Number of edges of a triangle surface (3- or 6-node faces) not shared by exactly two faces (0 for a closed
    surface)."""
    _, counts = np.unique(_edge_keys(face_vertices(triangles)), return_counts=True)
    return int(np.count_nonzero(counts != 2))


def surface_components(triangles: np.ndarray) -> np.ndarray:
    """Label of the edge-connected component of each triangle (3- or 6-node faces; 0, 1, ... in the order of
    their first triangle).

    Union-find over the triangles that share an edge, vectorised: each round hooks every pair's larger root under
    the smaller one and then compresses the paths, so components merge in a logarithmic number of rounds.
    """
    triangles = face_vertices(triangles)
    edge_ids = np.unique(_edge_keys(triangles), return_inverse=True)[1].ravel()
    triangle_of_edge = np.repeat(np.arange(len(triangles)), 3)
    order = np.argsort(edge_ids, kind="stable")
    same_edge = edge_ids[order[1:]] == edge_ids[order[:-1]]
    first, second = order[:-1][same_edge], order[1:][same_edge]
    first, second = triangle_of_edge[first], triangle_of_edge[second]
    parent = np.arange(len(triangles))
    while True:
        root_first, root_second = parent[first], parent[second]
        differ = root_first != root_second
        if not differ.any():
            break
        np.minimum.at(parent, np.maximum(root_first, root_second)[differ],
                      np.minimum(root_first, root_second)[differ])
        while True:
            grandparent = parent[parent]
            if np.array_equal(grandparent, parent):
                break
            parent = grandparent
    return np.unique(parent, return_inverse=True)[1].ravel()


def prepare_surfaces(mesh: TetMesh, chambers: list[str], fixed: str | None, source: str) -> Surfaces:
    """Orient and check the chamber walls, find the outer boundary and the fixation patch.

    Each chamber wall must be a closed surface made of boundary faces of the tetrahedra; it is oriented by its
    tetrahedra (normals into the solid, i.e. out of the cavity) and made of their faces (6-node faces for
    10-node tetrahedra, whatever the group's triangles list). The outer boundary is the component of the
    boundary that encloses a positive volume with outward normals. Raises MeshError naming what is wrong.
    """
    faces, _ = boundary_faces(mesh.tets)
    lookup = _face_lookup(faces)
    available = ", ".join(sorted(mesh.surface_groups)) or "none"
    chamber_faces = []
    for name in chambers:
        if name not in mesh.surface_groups:
            raise MeshError(f"{source}: the chamber group {name!r} is missing; the mesh has: {available}")
        triangles = mesh.surface_groups[name]
        rows = [lookup.get(tuple(key)) for key in np.sort(face_vertices(triangles), axis=1).tolist()]
        off_boundary = [i for i, row in enumerate(rows) if row is None]
        if off_boundary:
            raise MeshError(
                f"{source}: {len(off_boundary)} triangle(s) of chamber {name!r} are not on the boundary of the "
                f"tetrahedra (first: nodes {triangles[off_boundary[0]].tolist()}): the wall must bound a cavity"
            )
        reverse = np.array([2, 1, 0]) if faces.shape[1] == 3 else REVERSED_TRIANGLE6
        oriented = faces[np.array(rows)][:, reverse]
        open_edges = open_edge_count(oriented)
        if open_edges:
            raise MeshError(
                f"{source}: the wall of chamber {name!r} is not closed ({open_edges} open edges): a chamber "
                f"must be a closed cavity"
            )
        chamber_faces.append(oriented)
    labels = surface_components(faces)
    enclosed = np.array([enclosed_volume_m3(mesh.nodes_m, faces[labels == k]) for k in range(labels.max() + 1)])
    if np.count_nonzero(enclosed > 0) != 1:
        raise MeshError(f"{source}: the mesh is not one body ({np.count_nonzero(enclosed > 0)} outer boundaries)")
    outer_faces = faces[labels == int(np.argmax(enclosed))]
    fixed_faces = None
    if fixed is not None:
        if fixed not in mesh.surface_groups:
            raise MeshError(f"{source}: the fixed group {fixed!r} is missing; the mesh has: {available}")
        fixed_faces = mesh.surface_groups[fixed]
        if fixed_faces.shape[1] != faces.shape[1]:
            # a 10-node mesh whose file lists the patch by its vertices: take the faces of the tetrahedra
            rows = [lookup.get(tuple(key)) for key in np.sort(face_vertices(fixed_faces), axis=1).tolist()]
            if any(row is None for row in rows):
                raise MeshError(f"{source}: the fixed group {fixed!r} has triangles that are not faces of the "
                                "boundary: the patch must lie on the surface")
            fixed_faces = faces[np.array(rows)]
    return Surfaces(chamber_faces, outer_faces, fixed_faces)


def read_mesh(path: str | Path, length_scale_m: float) -> TetMesh:
    """Read a tagged tetrahedral mesh with meshio and check it; coordinates are multiplied by ``length_scale_m``.

    Groups come from named cell sets (MSH 4.1), from ``gmsh:physical`` tags and their names (MSH 2.2), or
    from integer cell data that meshio wrote for cell sets (VTU).
    """
    # meshio (0.1 s to import) only where a mesh file is read or written
    import meshio

    path = Path(path)
    if not path.is_file():
        raise MeshError(f"the mesh file {path} does not exist: check the scene's [phantom] mesh path")
    try:
        raw = meshio.read(path)
    except Exception as error:  # meshio raises many types for unreadable files
        raise MeshError(f"meshio cannot read {path}: {error}") from error
    source = str(path)
    kinds = {block.type for block in raw.cells} & {"tetra", "tetra10"}
    if len(kinds) > 1:
        raise MeshError(f"{source}: the mesh mixes 4-node and 10-node tetrahedra: use one element order")
    tet_blocks = [block.data for block in raw.cells if block.type in kinds]
    tets = np.concatenate(tet_blocks).astype(np.int64) if tet_blocks else np.zeros((0, 4), np.int64)
    nodes_m = np.asarray(raw.points, dtype=np.float64)[:, :3] * length_scale_m
    tets = check_tets(nodes_m, tets, source)
    return TetMesh(nodes_m, tets, _surface_groups(raw))


def _surface_groups(raw: Any) -> dict[str, np.ndarray]:
    """Named triangle groups of a meshio mesh (``raw``, a ``meshio.Mesh``), whichever way the file stored them."""
    cell_sets = {name: sets for name, sets in raw.cell_sets.items() if not name.startswith("gmsh:")}
    if not cell_sets and "gmsh:physical" in raw.cell_data:
        cell_sets = {}
        for name, (tag, dim) in raw.field_data.items():
            if dim == 2:
                cell_sets[name] = [np.flatnonzero(tags == tag) for tags in raw.cell_data["gmsh:physical"]]
    if not cell_sets:
        for key in list(raw.cell_data):
            # cell sets come back as integer cell data; float data (a written volume ratio) is no group
            integer = all(np.issubdtype(np.asarray(block).dtype, np.integer) for block in raw.cell_data[key])
            if integer and not key.startswith("gmsh:"):
                try:
                    raw.cell_data_to_sets(key)
                except (ValueError, KeyError, TypeError):
                    continue
        cell_sets = dict(raw.cell_sets)
    groups = {}
    for name, per_block in cell_sets.items():
        triangles = [block.data[np.asarray(ids, dtype=np.int64)]
                     for block, ids in zip(raw.cells, per_block, strict=False)
                     if block.type in ("triangle", "triangle6") and ids is not None and len(ids)]
        if triangles:
            groups[name] = np.concatenate(triangles).astype(np.int64)
    return groups


def write_mesh(mesh: TetMesh, path: str | Path, length_scale_m: float = 1e-3,
               element_data: dict[str, np.ndarray] | None = None) -> None:
    """Write a mesh with its groups; coordinates are divided by ``length_scale_m`` (default: millimetres).

    ``.msh`` is written by gmsh as MSH 4.1 with named physical groups (a volume group ``solid`` and one
    surface group per name); any other extension goes through meshio with cell sets, and with
    ``element_data`` (name: one value per tetrahedron) as cell data (the surface cells get NaN).
    """
    path = Path(path)
    coordinates = mesh.nodes_m / length_scale_m
    if not np.isfinite(coordinates).all():
        bad = int(np.flatnonzero(~np.isfinite(coordinates).all(axis=1))[0])
        raise MeshError(f"cannot write {path}: node {bad} has a coordinate that is not finite "
                        f"({coordinates[bad].tolist()}): the mesh or its deformation is broken")
    if path.suffix == ".msh":
        with written_atomically(path, MeshError, ends_with=b"$EndElements\n") as temporary:
            _write_msh41(mesh, coordinates, temporary)
        return
    # meshio (0.1 s to import) only where a mesh file is read or written
    import meshio

    names = list(mesh.surface_groups)
    width = 3 if mesh.order == 1 else 6
    triangles = (np.concatenate([mesh.surface_groups[n] for n in names]) if names
                 else np.zeros((0, width), np.int64))
    offsets = np.cumsum([0] + [len(mesh.surface_groups[n]) for n in names])
    cell_sets = {"solid": [np.arange(len(mesh.tets)), np.zeros(0, np.int64)]}
    for k, name in enumerate(names):
        cell_sets[name] = [np.zeros(0, np.int64), np.arange(offsets[k], offsets[k + 1])]
    kinds = ("tetra", "triangle") if mesh.order == 1 else ("tetra10", "triangle6")
    cell_data = {name: [np.asarray(values, float), np.full(len(triangles), np.nan)]
                 for name, values in (element_data or {}).items()}
    out = meshio.Mesh(coordinates, [(kinds[0], mesh.tets), (kinds[1], triangles)], cell_sets=cell_sets,
                      cell_data=cell_data)
    with written_atomically(path, MeshError) as temporary:
        try:
            out.write(temporary)
        except OSError:
            raise
        except Exception as error:  # meshio raises many types for unknown formats
            raise MeshError(f"cannot write {path}: {error}; use .msh or .vtu") from error


#: The signals whose disposition gmsh's initialize sets back to the default action (read off /proc/self/status
#: before and after it, gmsh 4; it also resets SIGSEGV and SIGFPE, which Python leaves at their default).
GMSH_RESET_SIGNALS = (signal.SIGPIPE, signal.SIGTERM, signal.SIGHUP, signal.SIGQUIT)


@contextlib.contextmanager
def gmsh_session() -> Iterator[Any]:
    """gmsh initialised quietly (no terminal output, one thread) for one model, finalised on exit.

    gmsh's initialize sets SIGPIPE, SIGTERM, SIGHUP and SIGQUIT back to the default action (terminate) behind
    Python's back, whose handlers then stay in place on paper only: a later write to a closed pipe (a dead worker
    process, ``phantom forward ... | head``) killed the whole process instead of raising BrokenPipeError (Python
    ignores SIGPIPE), and a response-table build that meshed its model died of the daemon's SIGTERM instead of
    ending its solver processes (host/startup.py). The dispositions Python had are set again (from the main
    thread, the only one that may).
    """
    # gmsh (0.2 s to import, and a native library) only where a mesh is generated or an .msh written
    import gmsh

    previous = {signum: signal.getsignal(signum) for signum in GMSH_RESET_SIGNALS}
    gmsh.initialize(interruptible=False)
    if threading.current_thread() is threading.main_thread():
        for signum, handler in previous.items():
            if handler is not None:
                signal.signal(signum, handler)
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.option.setNumber("General.NumThreads", 1)
        yield gmsh
    finally:
        gmsh.finalize()


def _write_msh41(mesh: TetMesh, coordinates: np.ndarray, path: Path) -> None:
    with gmsh_session() as gmsh:
        gmsh.model.add("phantom")
        node_tags = np.arange(1, mesh.n_nodes + 1)
        volume = gmsh.model.addDiscreteEntity(3)
        gmsh.model.mesh.addNodes(3, volume, node_tags, coordinates.ravel())
        # gmsh's element types: 4-node tetrahedron 4, 10-node 11 (its own node order), 3-node triangle 2, 6-node 9
        tets = mesh.tets if mesh.order == 1 else mesh.tets[:, GMSH_TET10_ORDER]
        gmsh.model.mesh.addElementsByType(volume, 4 if mesh.order == 1 else 11, [], (tets + 1).ravel())
        gmsh.model.addPhysicalGroup(3, [volume], name="solid")
        for name, triangles in mesh.surface_groups.items():
            surface = gmsh.model.addDiscreteEntity(2)
            gmsh.model.mesh.addElementsByType(surface, 2 if triangles.shape[1] == 3 else 9, [],
                                              (triangles + 1).ravel())
            gmsh.model.addPhysicalGroup(2, [surface], name=name)
        gmsh.option.setNumber("Mesh.MshFileVersion", 4.1)
        gmsh.write(str(path))
