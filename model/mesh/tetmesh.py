"""Tagged tetrahedral meshes: reading, checking, writing, and the surfaces the solver needs.

A mesh is a set of nodes (m), positively oriented linear tetrahedra, and named surface groups (triangles):
chamber walls, the fixation patch, anything else a file carries. :func:`prepare_surfaces` turns a scene's
group names into oriented chamber walls, the outer boundary and the fixed nodes, checking each on the way.
"""

import contextlib
import signal
import threading
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from phantom.model.errors import MeshError

#: Faces of a tetrahedron (local vertex numbers), each ordered so its normal points away from the fourth vertex.
TET_FACES = np.array([[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]])


@dataclass
class TetMesh:
    """Nodes in metres, tetrahedra (positive volume) and named surface groups (triangles, node indices)."""

    nodes_m: np.ndarray
    tets: np.ndarray
    surface_groups: dict[str, np.ndarray] = field(default_factory=dict)

    @property
    def n_nodes(self) -> int:
        return len(self.nodes_m)


@dataclass
class Surfaces:
    """The surfaces a scene uses, oriented and checked.

    chamber_triangles : list of (k_i, 3) int arrays, each wall oriented with normals out of its cavity, so
        the volume it encloses is positive.
    outer_triangles : (k, 3) int array, the outer boundary with outward normals (encloses the gland).
    fixed_triangles : (k, 3) int array or None, the fixation patch.
    """

    chamber_triangles: list[np.ndarray]
    outer_triangles: np.ndarray
    fixed_triangles: np.ndarray | None


def tet_signed_volumes_m3(nodes_m: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """Signed volume of each tetrahedron, ``det[x1-x0, x2-x0, x3-x0] / 6`` (m^3); positive when right-handed."""
    x0 = nodes_m[tets[:, 0]]
    edges = nodes_m[tets[:, 1:]] - x0[:, None, :]
    volumes: np.ndarray = np.linalg.det(edges) / 6.0
    return volumes


def enclosed_volume_m3(positions_m: np.ndarray, triangles: np.ndarray) -> float:
    """Volume enclosed by a closed, consistently oriented triangle surface (m^3).

    By the divergence theorem, ``V = sum_t x0 . (x1 x x2) / 6`` over the triangles (normals outward).
    """
    x0, x1, x2 = (positions_m[triangles[:, k]] for k in range(3))
    return float(np.einsum("ij,ij->", x0, np.cross(x1, x2)) / 6.0)


def volume_gradient_m2(positions_m: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Gradient of the enclosed volume with respect to each node position, (n, 3) in m^2.

    Each triangle gives ``a_t n_t / 3`` to each of its vertices; on a closed surface this sum is the exact
    derivative of :func:`enclosed_volume_m3`, and ``p`` times it is the nodal pressure force.
    """
    x0, x1, x2 = (positions_m[triangles[:, k]] for k in range(3))
    third_area_normal = np.cross(x1 - x0, x2 - x0) / 6.0
    gradient = np.zeros((len(positions_m), 3))
    for k in range(3):
        for axis in range(3):
            gradient[:, axis] += np.bincount(triangles[:, k], third_area_normal[:, axis], len(positions_m))
    return gradient


def check_tets(nodes_m: np.ndarray, tets: np.ndarray, source: str) -> np.ndarray:
    """Check tetrahedra and return them positively oriented.

    Raises MeshError when there are none, when an index is out of range, when a node belongs to no
    tetrahedron, when some are degenerate (volume below 1e-9 of a cube of the mean edge length), or when
    orientations are mixed (some inverted). A mesh whose tetrahedra are all negatively oriented follows the
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
    edge_m = np.mean(np.linalg.norm(nodes_m[tets[:, 1:]] - nodes_m[tets[:, :1]], axis=2))
    degenerate = np.flatnonzero(np.abs(volumes) < 1e-9 * edge_m**3)
    if len(degenerate):
        raise MeshError(
            f"{source}: {len(degenerate)} degenerate (flat) tetrahedra, first: tet {degenerate[0]} with nodes "
            f"{tets[degenerate[0]].tolist()}: remesh"
        )
    inverted = np.flatnonzero(volumes < 0)
    if len(inverted) == len(tets):
        return tets[:, [0, 2, 1, 3]]
    if len(inverted):
        raise MeshError(
            f"{source}: {len(inverted)} of {len(tets)} tetrahedra are inverted (negative volume), first: tet "
            f"{inverted[0]} with nodes {tets[inverted[0]].tolist()}: remesh or fix their node order"
        )
    return tets


def boundary_faces(tets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Faces that belong to one tetrahedron only, with outward normals, and the tetrahedron of each."""
    faces = tets[:, TET_FACES].reshape(-1, 3)
    _, first, counts = np.unique(_face_keys(faces, tets.max() + 1), return_index=True, return_counts=True)
    single = first[counts == 1]
    return faces[single], single // 4


def _face_keys(faces: np.ndarray, n_nodes: int) -> np.ndarray:
    """One integer per face, equal for the same three nodes in any order (a fast key for np.unique)."""
    ordered = np.sort(faces, axis=1).astype(np.int64)
    return (ordered[:, 0] * n_nodes + ordered[:, 1]) * n_nodes + ordered[:, 2]


def _edge_keys(triangles: np.ndarray) -> np.ndarray:
    """One integer per triangle edge (3 per triangle, in order), equal for both directions of an edge."""
    edges = np.sort(triangles[:, [[0, 1], [1, 2], [2, 0]]].reshape(-1, 2), axis=1).astype(np.int64)
    return edges[:, 0] * (int(triangles.max()) + 1) + edges[:, 1]


def _face_lookup(faces: np.ndarray) -> dict[tuple[int, int, int], int]:
    return {tuple(key): row for row, key in enumerate(np.sort(faces, axis=1).tolist())}


def open_edge_count(triangles: np.ndarray) -> int:
    """Number of edges of a triangle surface not shared by exactly two triangles (0 for a closed surface)."""
    _, counts = np.unique(_edge_keys(triangles), return_counts=True)
    return int(np.count_nonzero(counts != 2))


def surface_components(triangles: np.ndarray) -> np.ndarray:
    """Label of the edge-connected component of each triangle (0, 1, ... in the order of their first triangle).

    Union-find over the triangles that share an edge, vectorised: each round hooks every pair's larger root under
    the smaller one and then compresses the paths, so components merge in a logarithmic number of rounds.
    """
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
    tetrahedra (normals into the solid, i.e. out of the cavity). The outer boundary is the component of the
    boundary that encloses a positive volume with outward normals. Raises MeshError naming what is wrong.
    """
    faces, _ = boundary_faces(mesh.tets)
    lookup = _face_lookup(faces)
    available = ", ".join(sorted(mesh.surface_groups)) or "none"
    chamber_triangles = []
    for name in chambers:
        if name not in mesh.surface_groups:
            raise MeshError(f"{source}: the chamber group {name!r} is missing; the mesh has: {available}")
        triangles = mesh.surface_groups[name]
        rows = [lookup.get(tuple(key)) for key in np.sort(triangles, axis=1).tolist()]
        off_boundary = [i for i, row in enumerate(rows) if row is None]
        if off_boundary:
            raise MeshError(
                f"{source}: {len(off_boundary)} triangle(s) of chamber {name!r} are not on the boundary of the "
                f"tetrahedra (first: nodes {triangles[off_boundary[0]].tolist()}): the wall must bound a cavity"
            )
        oriented = faces[np.array(rows)][:, ::-1]
        open_edges = open_edge_count(oriented)
        if open_edges:
            raise MeshError(
                f"{source}: the wall of chamber {name!r} is not closed ({open_edges} open edges): a chamber "
                f"must be a closed cavity"
            )
        chamber_triangles.append(oriented)
    labels = surface_components(faces)
    enclosed = np.array([enclosed_volume_m3(mesh.nodes_m, faces[labels == k]) for k in range(labels.max() + 1)])
    if np.count_nonzero(enclosed > 0) != 1:
        raise MeshError(f"{source}: the mesh is not one body ({np.count_nonzero(enclosed > 0)} outer boundaries)")
    outer_triangles = faces[labels == int(np.argmax(enclosed))]
    fixed_triangles = None
    if fixed is not None:
        if fixed not in mesh.surface_groups:
            raise MeshError(f"{source}: the fixed group {fixed!r} is missing; the mesh has: {available}")
        fixed_triangles = mesh.surface_groups[fixed]
    return Surfaces(chamber_triangles, outer_triangles, fixed_triangles)


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
    tet_blocks = [block.data for block in raw.cells if block.type == "tetra"]
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
            if not key.startswith("gmsh:"):
                try:
                    raw.cell_data_to_sets(key)
                except (ValueError, KeyError, TypeError):
                    continue
        cell_sets = dict(raw.cell_sets)
    groups = {}
    for name, per_block in cell_sets.items():
        triangles = [block.data[np.asarray(ids, dtype=np.int64)]
                     for block, ids in zip(raw.cells, per_block, strict=False)
                     if block.type == "triangle" and ids is not None and len(ids)]
        if triangles:
            groups[name] = np.concatenate(triangles).astype(np.int64)
    return groups


def write_mesh(mesh: TetMesh, path: str | Path, length_scale_m: float = 1e-3) -> None:
    """Write a mesh with its groups; coordinates are divided by ``length_scale_m`` (default: millimetres).

    ``.msh`` is written by gmsh as MSH 4.1 with named physical groups (a volume group ``solid`` and one
    surface group per name); any other extension goes through meshio with cell sets.
    """
    path = Path(path)
    coordinates = mesh.nodes_m / length_scale_m
    if path.suffix == ".msh":
        _write_msh41(mesh, coordinates, path)
        return
    # meshio (0.1 s to import) only where a mesh file is read or written
    import meshio

    names = list(mesh.surface_groups)
    triangles = np.concatenate([mesh.surface_groups[n] for n in names]) if names else np.zeros((0, 3), np.int64)
    offsets = np.cumsum([0] + [len(mesh.surface_groups[n]) for n in names])
    cell_sets = {"solid": [np.arange(len(mesh.tets)), np.zeros(0, np.int64)]}
    for k, name in enumerate(names):
        cell_sets[name] = [np.zeros(0, np.int64), np.arange(offsets[k], offsets[k + 1])]
    out = meshio.Mesh(coordinates, [("tetra", mesh.tets), ("triangle", triangles)], cell_sets=cell_sets)
    try:
        out.write(path)
    except Exception as error:  # meshio raises many types for unknown formats
        raise MeshError(f"cannot write {path}: {error}; use .msh or .vtu") from error


@contextlib.contextmanager
def gmsh_session() -> Iterator[Any]:
    """gmsh initialised quietly (no terminal output, one thread) for one model, finalised on exit.

    gmsh's initialize sets SIGPIPE back to the default action (terminate) behind Python's back, which ignores it:
    a later write to a closed pipe (a dead worker process, ``phantom forward ... | head``) then killed the whole
    process instead of raising BrokenPipeError. The disposition Python had is set again (from the main thread,
    the only one that may).
    """
    # gmsh (0.2 s to import, and a native library) only where a mesh is generated or an .msh written
    import gmsh

    previous = signal.getsignal(signal.SIGPIPE)
    gmsh.initialize(interruptible=False)
    if previous is not None and threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGPIPE, previous)
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
        gmsh.model.mesh.addElementsByType(volume, 4, [], (mesh.tets + 1).ravel())
        gmsh.model.addPhysicalGroup(3, [volume], name="solid")
        for name, triangles in mesh.surface_groups.items():
            surface = gmsh.model.addDiscreteEntity(2)
            gmsh.model.mesh.addElementsByType(surface, 2, [], (triangles + 1).ravel())
            gmsh.model.addPhysicalGroup(2, [surface], name=name)
        gmsh.option.setNumber("Mesh.MshFileVersion", 4.1)
        gmsh.write(str(path))
