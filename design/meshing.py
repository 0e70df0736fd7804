"""The designed model's tetrahedral mesh (gmsh) and its scene.

The gland's surface and the chambers' ellipsoids go to gmsh as discrete surfaces; gmsh classifies and reparametrises
them (``classifySurfaces``, ``createGeometry``), so it remeshes them at the element size, and meshes the solid
between them with :func:`phantom.model.mesh.prostate.mesh_solid`, the built-in prostate's own mesher. The size at a
point is the least of the scene's ``size_mm``, half the local wall (so two elements span every wall:
:func:`phantom.model.mesh.shape.wall_field_of`) and, on a chamber, ``2 pi rho / CURVATURE_ELEMENTS`` with ``rho``
its ellipsoid's mean radius of curvature there (the built-in mesh gets the same from OpenCASCADE's exact surfaces;
gmsh's estimate on a reparametrised triangulation refines a cavity ten times too much). The surface groups are the
built-in's: ``chamber0, chamber1, ...`` (one per designed chamber) and ``fixed``, the outer faces within the
fixation radius of the base pole (where the ray up the gland's axis leaves it). The tube channels are the cast's,
not the model's: like the built-in model, the designed one has closed chambers.
"""

from __future__ import annotations

import math
import textwrap
from pathlib import Path
from typing import Any

import numpy as np

from phantom import PhantomError, require_extra
from phantom.design.chambers import BASE, Chamber, chamber_name
from phantom.design.errors import DesignError
from phantom.design.material import InheritedMaterial
from phantom.design.surface import Surface
from phantom.model.arrays import FloatArray
from phantom.model.mesh.geometry import MESH_SIZE_RANGE_MM, Vector3
from phantom.model.mesh.prostate import CURVATURE_ELEMENTS, QUADRATIC_CURVATURE_SIZE_MM, mesh_solid, tag_surfaces
from phantom.model.mesh.shape import ellipsoid_points_mm, wall_field_of
from phantom.model.mesh.tetmesh import TetMesh, gmsh_session
from phantom.model.scene import builtin_scene_path, read_scene_toml

#: Subdivisions of the icosphere a chamber's ellipsoid starts from (2562 vertices; gmsh remeshes it).
ELLIPSOID_SUBDIVISIONS = 4
#: Elements through the thinnest wall.
ELEMENTS_PER_WALL = 2


def base_pole_mm(surface: Surface, chambers: list[Chamber]) -> Vector3:
    """Where the gland's axis (the vertical through the base chamber's centre; without a base chamber, through the
    mid-sagittal plane at the chambers' mean depth) leaves it at the base: the tube junction, the centre of the
    fixed patch."""
    base = [chamber for chamber in chambers if chamber.kind == BASE]
    centres = np.array([chamber.centre_mm for chamber in chambers])
    start = np.array(base[0].centre_mm) if base else np.array([0.0, centres[:, 1].mean(), centres[:, 2].mean()])
    x, y, _ = start
    crossings = surface.crossings_above_mm(start)
    if len(crossings) == 0:
        raise DesignError("the gland's axis does not leave the gland at the base: the mask is not a gland")
    return (x, y, float(crossings[-1]))


def _ellipsoid_surface(chamber: Chamber) -> Surface:
    with require_extra("design"):
        from trimesh import creation

    sphere = creation.icosphere(ELLIPSOID_SUBDIVISIONS)
    vertices = np.asarray(sphere.vertices) * np.asarray(chamber.semi_axes_mm) + np.asarray(chamber.centre_mm)
    return Surface(vertices, np.asarray(sphere.faces, np.int64))


def _curvature_size_mm(point: tuple[float, float, float], chamber: Chamber, elements: float) -> float:
    """``2 pi rho / elements`` near the chamber's surface, ``rho`` the least principal radius of curvature at the
    radial projection of ``point`` onto the ellipsoid (as gmsh sizes an exact surface), else inf.

    gmsh asks this once per point and chamber (hundreds of thousands of times a mesh), so it is scalar arithmetic,
    not small numpy arrays (those took half of ``phantom design``'s time). The principal curvatures of
    ``F = sum x_i^2 / a_i^2`` are the non-zero eigenvalues of ``P D P / |grad F|`` (``D = diag(2 / a_i^2)``, ``P`` the
    projection onto the tangent plane, unit normal ``n``): their sum is ``(tr D - n^T D n) / |grad F|`` and their
    product ``n^T adj(D) n / |grad F|^2`` (the determinant of ``D`` on the plane normal to ``n``), so the larger is
    a quadratic's root."""
    ax, ay, az = chamber.semi_axes_mm
    cx, cy, cz = chamber.centre_mm
    rx, ry, rz = (point[0] - cx) / ax, (point[1] - cy) / ay, (point[2] - cz) / az
    level = math.sqrt(rx * rx + ry * ry + rz * rz)
    if not 0.5 < level < 1.5:
        return math.inf
    dx, dy, dz = 2.0 / (ax * ax), 2.0 / (ay * ay), 2.0 / (az * az)
    # the gradient at the surface point (r / level * a): 2 s_i / a_i^2 = d_i a_i r_i / level
    gx, gy, gz = dx * ax * rx / level, dy * ay * ry / level, dz * az * rz / level
    gradient = math.sqrt(gx * gx + gy * gy + gz * gz)
    nx2, ny2, nz2 = (gx / gradient) ** 2, (gy / gradient) ** 2, (gz / gradient) ** 2
    total = (dx + dy + dz - (dx * nx2 + dy * ny2 + dz * nz2)) / gradient
    product = (nx2 * dy * dz + ny2 * dx * dz + nz2 * dx * dy) / (gradient * gradient)
    largest = 0.5 * (total + math.sqrt(max(total * total - 4.0 * product, 0.0)))
    return 2.0 * math.pi / largest / elements


def check_mesh_options(size_mm: float, element_order: int | None) -> None:
    """DesignError for an element size outside MESH_SIZE_RANGE_MM or an element order not 1 or 2 (None: the
    inherited material's, not checked here)."""
    if not MESH_SIZE_RANGE_MM[0] <= size_mm <= MESH_SIZE_RANGE_MM[1]:
        raise DesignError(f"--size-mm {size_mm:g} is out of range: use {MESH_SIZE_RANGE_MM[0]:g} to "
                          f"{MESH_SIZE_RANGE_MM[1]:g} mm")
    if element_order not in (1, 2, None):
        raise DesignError(f"--element-order {element_order} is not 1 (4-node) or 2 (10-node)")


def mesh_design(surface: Surface, chambers: list[Chamber], size_mm: float, element_order: int,
                fixation_radius_mm: float, outer_samples_mm: FloatArray,
                elements_per_wall: int = ELEMENTS_PER_WALL) -> TetMesh:
    """The tagged tetrahedral mesh (nodes in metres) of the gland with the chambers cut out; see the module
    docstring (``elements_per_wall``: fewer for a coarse mesh)."""
    check_mesh_options(size_mm, element_order)
    shells = [surface] + [_ellipsoid_surface(chamber) for chamber in chambers]
    low = surface.vertices_mm.min(axis=0) - 1.0
    high = surface.vertices_mm.max(axis=0) + 1.0
    walls = wall_field_of([outer_samples_mm] + [ellipsoid_points_mm(c.centre_mm, c.semi_axes_mm) for c in chambers],
                          low, high, spacing_mm=min(1.0, size_mm / 2), within_mm=2.0 * size_mm)
    elements = CURVATURE_ELEMENTS
    if element_order == 2:
        elements = max(4, round(CURVATURE_ELEMENTS * QUADRATIC_CURVATURE_SIZE_MM / size_mm))

    def size_at(x: float, y: float, z: float) -> float:
        point = (x, y, z)
        size = walls.at(x, y, z) / elements_per_wall
        for chamber in chambers:
            size = min(size, _curvature_size_mm(point, chamber, elements))
        return size

    try:
        with gmsh_session() as gmsh:
            gmsh.model.add("design")
            volume = _solid_from_shells(gmsh, shells, chambers)
            nodes_mm, tets = mesh_solid(gmsh, [(3, volume)], size_mm, 0, element_order, size_at=size_at)
    except PhantomError:
        raise
    except Exception as error:  # gmsh raises plain Exceptions (an overlapping or self-crossing surface)
        raise DesignError(f"gmsh could not mesh the design ({' '.join(str(error).split())[:300]}): the gland's surface "
                          f"or a chamber's is too rough or too thin for a {size_mm:g} mm mesh: smooth it more "
                          f"(--smooth-iterations, 20 for a mask by default: try 60), or give a finer mask") from None
    ellipsoids = tuple((chamber.centre_mm, chamber.semi_axes_mm) for chamber in chambers)
    groups = tag_surfaces(nodes_mm, tets, ellipsoids, base_pole_mm(surface, chambers), fixation_radius_mm,
                          patch_edge_meshed=False)
    for index, chamber in enumerate(chambers):
        if len(groups[chamber_name(index)]) == 0:
            raise DesignError(f"the {chamber.label} chamber's wall is missing from the mesh: gmsh merged it; "
                              f"report this")
    if len(groups["fixed"]) == 0:
        raise DesignError(f"no outer face lies within --fixation-radius-mm {fixation_radius_mm:g} of the base "
                          f"pole: give a larger radius")
    return TetMesh(nodes_mm * 1e-3, tets, groups)


def _solid_from_shells(gmsh: Any, shells: list[Surface], chambers: list[Chamber]) -> int:
    """Add the closed shells (the outer surface first) as discrete surfaces, let gmsh reparametrise them, and make
    the volume between them; return its tag."""
    offset = 1
    for shell in shells:
        entity = gmsh.model.addDiscreteEntity(2)
        tags = np.arange(offset, offset + len(shell.vertices_mm))
        gmsh.model.mesh.addNodes(2, entity, tags, shell.vertices_mm.ravel())
        gmsh.model.mesh.addElementsByType(entity, 2, [], (shell.triangles + offset).ravel())
        offset += len(shell.vertices_mm)
    # patches split at 40 degrees, each reparametrised; curves split wherever they turn (pi)
    gmsh.model.mesh.classifySurfaces(math.radians(40), True, True, math.pi)
    gmsh.model.mesh.createGeometry()
    members: dict[int, list[int]] = {}
    for _, tag in gmsh.model.getEntities(2):
        _, coordinates, _ = gmsh.model.mesh.getNodes(2, tag, True)
        points = coordinates.reshape(-1, 3)
        # a patch of a chamber's surface has its nodes on the ellipsoid: level 1 in the ellipsoid's own axes
        levels = [float(np.median(np.abs(np.linalg.norm((points - np.asarray(c.centre_mm)) /
                                                         np.asarray(c.semi_axes_mm), axis=1) - 1.0)))
                  for c in chambers]
        owner = 1 + int(np.argmin(levels)) if min(levels) < 0.05 else 0
        members.setdefault(owner, []).append(tag)
    if sorted(members) != list(range(len(shells))):
        raise DesignError(f"gmsh could not separate the gland's surface from the chambers' ({sorted(members)})")
    loops = [gmsh.model.geo.addSurfaceLoop(members[owner]) for owner in range(len(shells))]
    volume: int = gmsh.model.geo.addVolume(loops)
    gmsh.model.geo.synchronize()
    return volume


def write_scene(mesh_path: Path, scene_path: Path, material: InheritedMaterial, chambers: list[Chamber]) -> None:
    """A scene naming the designed mesh (beside it) and its ``chambers``, with the inherited calibrated
    ``material`` (:mod:`phantom.design.material`) and the built-in prostate's model settings, so that ``phantom
    forward``, ``inverse``, ``calibrate`` and the daemon take it as they take the built-in one; its header says
    which calibration it inherits and that the cast must be measured and calibrated."""
    from phantom import written_atomically
    from phantom.model.calibration.calibrate import dump_toml

    document = read_scene_toml(builtin_scene_path("builtin:prostate"))
    document["phantom"] = {"mesh": mesh_path.name, "units": "mm",
                           "chambers": [chamber_name(index) for index in range(len(chambers))],
                           "chamber_labels": [chamber.label for chamber in chambers], "fixed": "fixed"}
    document["material"] = dict(material.table)
    if material.element_order == 2:
        document.get("model", {}).pop("accuracy_pct", None)
    header = textwrap.fill(f"A phantom designed by phantom design: the gland's mesh beside this file; "
                           f"{material.caveat}.", 110)
    with written_atomically(scene_path, DesignError) as temporary:
        temporary.write_text(dump_toml(document, header))
