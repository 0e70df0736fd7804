"""Meshes generated with gmsh: the built-in prostate phantom and the thick hollow sphere used for verification.

The built-in prostate (millimetres, x to the patient's left, y anterior, z from apex to base) is the body of
revolution of :mod:`phantom.model.mesh.shape` with three ellipsoidal cavities cut from it: chamber 0 at the base,
chambers 1 (+x, left lobe) and 2 (-x, right lobe) mirror images about the mid-sagittal plane x = 0. The ``fixed``
patch is the base surface within a fixation radius of the base pole, where the three air tubes enter. Chamber
sizes and positions and the fixation radius are parameters (:class:`phantom.model.mesh.geometry.ProstateGeometry`,
a scene's ``[geometry]`` table); the defaults leave every wall at least 3.5 mm thick, and no wall may be under
2 mm.

The 10-node mesh is graded where walls are thin: the element size at a point is ``min(h, h w / WALL_SPAN_MM)``
with ``h`` the scene's ``mesh_size_mm`` and ``w`` the local wall thickness
(:func:`phantom.model.mesh.shape.wall_field`), so ``WALL_SPAN_MM / h`` elements span every wall thinner than
WALL_SPAN_MM (two at 4 mm), and ``mesh_size_mm`` stays the one knob: halving it halves every size, the
curvature sizing's included (``CURVATURE_ELEMENTS * QUADRATIC_CURVATURE_SIZE_MM / h`` elements per 2 pi of
curvature; the curved faces keep a cavity's volume with few). Order 2 adds
gmsh's mid-edge nodes, placed on the curved surfaces (10-node tetrahedra), to the same elements. The 10-node
mesh's fixed patch ends exactly on the fixation radius (the solid is split by that sphere before meshing), so a
finer mesh does not move the clamped edge. The 4-node mesh is neither graded nor split (the shipped calibration
holds on it as it is).
"""

import math
import os
import sys
import tempfile
from collections.abc import Callable
from typing import Any

import numpy as np

import phantom
from phantom.model.errors import MeshError
from phantom.model.mesh.elements import GMSH_TET10_ORDER, TET10_EDGES, TET10_REFLECTED, face_vertices
from phantom.model.mesh.geometry import MESH_SIZE_RANGE_MM, ProstateGeometry, Vector3
from phantom.model.mesh.shape import (
    ANTERIOR_POSTERIOR_RATIO,
    HALF_LENGTH_MM,
    WallField,
    check_walls,
    equator_radius_mm,
    profile_radius_mm,
    wall_field,
)
from phantom.model.mesh.tetmesh import (
    TetMesh,
    boundary_faces,
    check_tets,
    curved_jacobian_determinants,
    gmsh_session,
    surface_components,
    tet_signed_volumes_m3,
)

#: Bump when the generated geometry changes, so cached meshes are regenerated.
PROSTATE_GEOMETRY_VERSION = 2
#: Walls thinner than this (mm) are graded: ``WALL_SPAN_MM / mesh_size_mm`` elements through each (module
#: docstring); 8 mm puts two through every wall at a 4 mm mesh size.
WALL_SPAN_MM = 8.0
#: The default chamber ellipsoids: centre (x, y, z) and semi-axes (a, b, c), millimetres.
CHAMBER_ELLIPSOIDS_MM = ProstateGeometry().ellipsoids_mm()
#: Default element size of the built-in mesh (mm): about 3k nodes.
DEFAULT_SIZE_MM = ProstateGeometry.mesh_size_mm
#: Elements per 2 pi of curvature, so small cavities keep their volume on coarse meshes.
CURVATURE_ELEMENTS = 16
#: The 10-node mesh size (mm) at which it has CURVATURE_ELEMENTS per 2 pi; the number scales as 1 / size, so that
#: ``mesh_size_mm`` refines the whole 10-node mesh (with a fixed number, 10 -> 8 mm was 10983 -> 11218 nodes).
QUADRATIC_CURVATURE_SIZE_MM = 4.0


def _ellipsoid(occ: Any, centre_mm: Vector3, semi_axes_mm: Vector3) -> tuple[int, int]:
    """An ellipsoid added to gmsh's OpenCASCADE kernel ``occ``: its (dimension, tag)."""
    sphere = occ.addSphere(0.0, 0.0, 0.0, 1.0)
    occ.dilate([(3, sphere)], 0.0, 0.0, 0.0, *semi_axes_mm)
    occ.translate([(3, sphere)], *centre_mm)
    return (3, sphere)


def mesh_solid(gmsh: Any, volumes: list[tuple[int, int]], size_mm: float, curvature_elements: int,
               element_order: int, walls: WallField | None = None,
               size_at: Callable[[float, float, float], float] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Mesh one solid, made of ``volumes`` that share their faces, (graded by ``walls`` when given, see the module
    docstring, and no larger than ``size_at(x, y, z)`` mm when given) at ``element_order``; return its nodes (mm)
    and positively oriented tets (4 or 10 nodes, meshio's order), numbered from 0 without gaps."""
    graded = walls is not None or size_at is not None
    gmsh.option.setNumber("Mesh.MeshSizeMax", size_mm)
    gmsh.option.setNumber("Mesh.MeshSizeMin", size_mm / (16.0 if graded else 4.0))
    gmsh.option.setNumber("Mesh.MeshSizeFromCurvature", curvature_elements)
    gmsh.option.setNumber("Mesh.Optimize", 1)
    if graded:
        def graded_size(dim: int, tag: int, x: float, y: float, z: float, size: float) -> float:
            if walls is not None:
                size = min(size, size_mm * walls.at(x, y, z) / WALL_SPAN_MM)
            return size if size_at is None else min(size, size_at(x, y, z))
        gmsh.model.mesh.setSizeCallback(graded_size)
    gmsh.model.addPhysicalGroup(3, [tag for _, tag in volumes], name="solid")
    gmsh.model.mesh.generate(3)
    if element_order == 2:
        gmsh.model.mesh.setOrder(2)
    node_tags, coordinates, _ = gmsh.model.mesh.getNodes()
    order = np.argsort(node_tags)
    node_tags, coordinates = node_tags[order], coordinates.reshape(-1, 3)[order]
    if element_order == 2:
        _, tet_nodes = gmsh.model.mesh.getElementsByType(11)
        tets = np.searchsorted(node_tags, tet_nodes.reshape(-1, 10)[:, GMSH_TET10_ORDER])
    else:
        _, tet_nodes = gmsh.model.mesh.getElementsByType(4)
        tets = np.searchsorted(node_tags, tet_nodes.reshape(-1, 4))
    used = np.unique(tets)
    renumber = np.full(len(node_tags), -1)
    renumber[used] = np.arange(len(used))
    nodes_mm, tets = coordinates[used], renumber[tets]
    if element_order == 2:
        nodes_mm = _straighten_folded(nodes_mm, tets)
    return nodes_mm, check_tets(nodes_mm, tets, "gmsh")


def _straighten_folded(nodes_mm: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """Move the mid-edge nodes of every curved 10-node tetrahedron that folds over itself (gmsh places them on
    the curved surfaces, which can fold a thin element in a thin wall) to their edges' midpoints, which makes
    it straight and valid; repeated, since a moved node changes its neighbours. The nodes so moved leave the
    exact surface by a fraction of the element size."""
    nodes_mm = nodes_mm.copy()
    straight = np.sign(tet_signed_volumes_m3(nodes_mm, tets[:, :4]))
    for _ in range(4):
        folded = np.flatnonzero((curved_jacobian_determinants(nodes_mm, tets) * straight[:, None]).min(axis=1) <= 0)
        if len(folded) == 0:
            break
        for local, (first, second) in enumerate(TET10_EDGES.tolist()):
            middle = tets[folded, 4 + local]
            nodes_mm[middle] = 0.5 * (nodes_mm[tets[folded, first]] + nodes_mm[tets[folded, second]])
    return nodes_mm


def _imprint_fixation(occ: Any, solid: list[tuple[int, int]], radius_mm: float) -> list[tuple[int, int]]:
    """Split ``solid`` by the sphere of ``radius_mm`` about the base pole, so that the fixation patch's edge (where
    that sphere meets the outer surface) is a line the mesh follows: a patch made of whichever faces fall inside
    the radius changes its area by several % from one mesh to the next (80, 88 and 82 mm^2 at 10, 7 and 5 mm),
    and a clamped edge, where the stress is singular, would move with it. Returns the solid's pieces, which
    share their faces."""
    sphere = occ.addSphere(0.0, 0.0, HALF_LENGTH_MM, radius_mm)
    _, children = occ.fragment(solid, [(3, sphere)])
    pieces = [piece for parent in children[:len(solid)] for piece in parent]
    occ.remove([piece for piece in children[len(solid)] if piece not in pieces], recursive=True)
    occ.synchronize()
    return pieces


def _mirror_about_x(nodes_mm: np.ndarray, tets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Join a mesh of the half x >= 0 with its mirror image; nodes on the plane x = 0 are shared."""
    on_plane = np.abs(nodes_mm[:, 0]) < 1e-9 * np.abs(nodes_mm).max()
    mirrored = np.flatnonzero(~on_plane)
    image = np.arange(len(nodes_mm))
    image[mirrored] = len(nodes_mm) + np.arange(len(mirrored))
    nodes_mm = nodes_mm.copy()
    nodes_mm[on_plane, 0] = 0.0
    reflected = nodes_mm[mirrored] * np.array([-1.0, 1.0, 1.0])
    # A reflection reverses orientation: swap two vertices (and their mid-edge nodes) to keep volumes positive.
    mirror_tets = image[tets][:, [0, 2, 1, 3] if tets.shape[1] == 4 else TET10_REFLECTED]
    return np.vstack([nodes_mm, reflected]), np.vstack([tets, mirror_tets])


def generate_prostate(size_mm: float = DEFAULT_SIZE_MM, geometry: ProstateGeometry | None = None,
                      element_order: int | None = None) -> TetMesh:
    """Mesh the built-in prostate phantom with gmsh (element size ``size_mm``, graded where walls are thin,
    ``element_order`` 1 or 2, default the geometry's); nodes in metres.

    Raises MeshError, before meshing, when a wall of ``geometry`` (default: the shipped one) is thinner than
    its ``min_wall_mm``.
    """
    if not MESH_SIZE_RANGE_MM[0] <= size_mm <= MESH_SIZE_RANGE_MM[1]:
        raise MeshError(f"mesh size {size_mm} mm is out of range: use {MESH_SIZE_RANGE_MM[0]:g} to "
                        f"{MESH_SIZE_RANGE_MM[1]:g} mm (default {DEFAULT_SIZE_MM})")
    geometry = geometry or ProstateGeometry()
    element_order = geometry.element_order if element_order is None else element_order
    check_walls(geometry)
    # the 4-node mesh stays ungraded: the shipped calibration holds on it as it is
    walls = wall_field(geometry) if element_order == 2 else None
    ellipsoids = geometry.ellipsoids_mm()
    radius_mm = equator_radius_mm()
    with gmsh_session() as gmsh:
        occ = gmsh.model.occ
        t_values = np.linspace(-1.0, 1.0, 33)
        radii = profile_radius_mm(t_values, radius_mm)
        points = [occ.addPoint(r, 0.0, HALF_LENGTH_MM * t) for r, t in zip(radii, t_values, strict=True)]
        profile = occ.addSpline(points)
        axis = occ.addLine(points[-1], points[0])
        section = occ.addPlaneSurface([occ.addCurveLoop([profile, axis])])
        body = [d for d in occ.revolve([(2, section)], 0, 0, 0, 0, 0, 1, 2 * math.pi) if d[0] == 3]
        occ.dilate(body, 0.0, 0.0, 0.0, 1.0, ANTERIOR_POSTERIOR_RATIO, 1.0)
        cavities = [_ellipsoid(occ, centre, axes) for centre, axes in ellipsoids]
        solid, _ = occ.cut(body, cavities)
        # Mesh the left half and mirror it, so that chambers 1 and 2 are exact mirror images.
        extent_mm = 4.0 * HALF_LENGTH_MM
        half_space = occ.addBox(0.0, -extent_mm, -extent_mm, extent_mm, 2 * extent_mm, 2 * extent_mm)
        half, _ = occ.intersect(solid, [(3, half_space)])
        occ.synchronize()
        if len(half) != 1:
            raise MeshError(f"gmsh produced {len(half)} volumes for the prostate instead of one")
        if element_order == 2:
            half = _imprint_fixation(occ, half, geometry.fixation_radius_mm)
        curvature_elements = CURVATURE_ELEMENTS
        if element_order == 2:
            curvature_elements = max(4, round(CURVATURE_ELEMENTS * QUADRATIC_CURVATURE_SIZE_MM / size_mm))
        nodes_mm, tets = _mirror_about_x(*mesh_solid(gmsh, half, size_mm, curvature_elements, element_order,
                                                     walls))
    tets = check_tets(nodes_mm, tets, "mirrored prostate mesh")
    groups = tag_surfaces(nodes_mm, tets, ellipsoids, (0.0, 0.0, HALF_LENGTH_MM), geometry.fixation_radius_mm,
                          patch_edge_meshed=element_order == 2)
    return TetMesh(nodes_mm * 1e-3, tets, groups)


def tag_surfaces(nodes_mm: np.ndarray, tets: np.ndarray, ellipsoids: tuple[tuple[Vector3, Vector3], ...],
                 base_pole_mm: Vector3, fixation_radius_mm: float, patch_edge_meshed: bool) -> dict[str, np.ndarray]:
    """The surface groups of a meshed body with ellipsoidal cavities: ``chamber<i>`` (the boundary component of
    the cavity nearest ``ellipsoids[i]``'s centre, in its own semi-axes) and ``fixed`` (the outer faces within
    ``fixation_radius_mm`` of ``base_pole_mm``: those whose centroid lies within it when the patch's edge is a
    line of the mesh, ``patch_edge_meshed``, so that a face is in it or out of it whole; else those whose corners
    all do)."""
    faces, _ = boundary_faces(tets)
    centroids = nodes_mm[face_vertices(faces)].mean(axis=1)
    labels = surface_components(faces)
    groups = {}
    on_cavity = np.zeros(len(faces), bool)
    for index, (centre, axes) in enumerate(ellipsoids):
        scaled = np.linalg.norm((centroids - np.asarray(centre)) / np.asarray(axes), axis=1)
        component = labels[np.argmin(scaled)]
        groups[f"chamber{index}"] = faces[labels == component]
        on_cavity |= labels == component
    pole = np.asarray(base_pole_mm)
    if patch_edge_meshed:
        inside = np.linalg.norm(centroids - pole, axis=1) < fixation_radius_mm
    else:
        # the built-in 4-node mesh's calibration was fitted with this rule
        inside = np.linalg.norm(nodes_mm[face_vertices(faces)] - pole, axis=2).max(axis=1) < fixation_radius_mm
    groups["fixed"] = faces[~on_cavity & inside]
    return groups


def generate_hollow_sphere(inner_radius_mm: float, outer_radius_mm: float, size_mm: float,
                           element_order: int = 1) -> TetMesh:
    """Mesh a thick hollow sphere (centre at the origin) with 4- or 10-node tetrahedra (``element_order``);
    groups ``cavity`` and ``outer``; nodes in metres.

    Nodes of both spherical surfaces (mid-edge ones included) lie on the exact spheres (gmsh places them on the
    geometry).
    """
    with gmsh_session() as gmsh:
        occ = gmsh.model.occ
        outer = occ.addSphere(0.0, 0.0, 0.0, outer_radius_mm)
        inner = occ.addSphere(0.0, 0.0, 0.0, inner_radius_mm)
        solid, _ = occ.cut([(3, outer)], [(3, inner)])
        occ.synchronize()
        nodes_mm, tets = mesh_solid(gmsh, solid, size_mm, 0, element_order)
    faces, _ = boundary_faces(tets)
    radius = np.linalg.norm(nodes_mm[face_vertices(faces)].mean(axis=1), axis=1)
    cavity = radius < 0.5 * (inner_radius_mm + outer_radius_mm)
    return TetMesh(nodes_mm * 1e-3, tets, {"cavity": faces[cavity], "outer": faces[~cavity]})


def builtin_prostate(size_mm: float | None = None, geometry: ProstateGeometry | None = None,
                     element_order: int | None = None) -> TetMesh:
    """The built-in prostate mesh, from the on-disk cache (``phantom.cache_dir("meshes")``) or generated.

    The cache key is the geometry version, the parameter set (:attr:`ProstateGeometry.key`), the element size
    (``size_mm``, else the geometry's ``mesh_size_mm``) and the element order (``element_order``, else the
    geometry's).
    """
    geometry = geometry or ProstateGeometry()
    size_mm = geometry.mesh_size_mm if size_mm is None else float(size_mm)
    element_order = geometry.element_order if element_order is None else int(element_order)
    # the 4-node mesh keeps the name it had before 10-node ones existed, so existing caches stay valid
    # (the 10-node mesh's curvature sizing scales with its size since "c", its fixation patch's edge is a mesh
    # line since "d": older 10-node caches are not read)
    order_tag = "" if element_order == 1 else f"-p{element_order}d"
    name = f"prostate-v{PROSTATE_GEOMETRY_VERSION}-{geometry.key}-h{size_mm:.6g}mm{order_tag}.npz"
    cache_path = phantom.cache_dir("meshes") / name
    if cache_path.is_file():
        try:
            with np.load(cache_path) as stored:
                groups = {key[len("group_"):]: stored[key] for key in stored.files if key.startswith("group_")}
                return TetMesh(stored["nodes_m"], stored["tets"], groups)
        except (OSError, ValueError, KeyError):
            cache_path.unlink(missing_ok=True)
    print(f"phantom: meshing the built-in prostate at {size_mm:g} mm, order {element_order} (cached "
          "afterwards)...", file=sys.stderr)
    mesh = generate_prostate(size_mm, geometry, element_order)
    arrays: dict[str, Any] = {"nodes_m": mesh.nodes_m, "tets": mesh.tets}
    arrays.update({f"group_{name}": triangles for name, triangles in mesh.surface_groups.items()})
    handle, temporary = tempfile.mkstemp(dir=cache_path.parent, suffix=".npz")
    os.close(handle)
    np.savez(temporary, **arrays)
    os.replace(temporary, cache_path)
    return mesh
