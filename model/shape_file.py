"""A target gland read from a file for the shape inverse: a NIfTI mask or label map, or a closed mesh in mm.

Both come out as one closed, outward :class:`~phantom.model.mesh.surface.TriangleMesh` in millimetres in the
phantom's frame (x to the patient's left, y anterior, z from apex to base), as ``phantom design`` and ``phantom
shape`` take them:

- a mask is a NIfTI volume whose voxels above 0 (a binary mask) or whose ``labels`` (a label map) are the gland;
  it is blurred by a Gaussian of one voxel (half a marching step where the step spans more) and surfaced by
  marching cubes on its own grid, sampled about :data:`MARCHING_STEP_MM` apart along each voxel axis (the blur
  takes the staircase away: a surface on the voxels' corners is a quarter voxel from the smooth gland on average,
  more than the distance the inverse is to resolve), at the level whose surface encloses the mask's own volume
  (its voxels' count times a voxel's volume: the half level of the blur reads a convex gland 0.4-4.5 % small),
  carried through the affine into scanner RAS and from there into the phantom's frame (``x -> -x``: RAS's +x is
  the patient's right). Ellipsoids voxelised at 0.1 x 0.1 x 1.4 to 0.5 x 0.5 x 3.6 mm come back within 0.8 % of
  their volume, 0.24 mm of their surface on average (``tests/test_shape_mask_volume.py``);
- a mesh (STL, PLY, OBJ, VTK, ... through meshio) is read in mm and already in the phantom's frame; it must be
  closed (every edge shared by two triangles), since its volume and its inside are reported.

What is refused, with why: a file that cannot be read, an empty mask or one without the labels asked for, a mask
of no gland's volume (:data:`GLAND_VOLUME_RANGE_ML`: a speck) or of scattered voxels, an affine that is not finite
or not invertible, voxels outside :data:`VOXEL_RANGE_MM`, a mesh that is not closed, and a surface whose volume is
no gland's in mm (:data:`GLAND_VOLUME_RANGE_ML`: a mesh in metres or centimetres).
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from phantom import PhantomError, require_extra
from phantom.model.mesh.surface import TriangleMesh, enclosed_volume_ml
from phantom.model.mesh.tetmesh import open_edge_count, surface_components
from phantom.model.mesh.winding import WindingError, outward_surface

#: What a gland's volume (ml) may be: a surface outside is in other units than mm (metres, centimetres).
GLAND_VOLUME_RANGE_ML = (2.0, 400.0)
#: The voxel sizes (mm) a mask's affine may give: MRI and CT voxels are 0.1 to 10 mm; a micrometre voxel (a header
#: in metres, or a missing scale) would put the prostate in a speck.
VOXEL_RANGE_MM = (0.05, 20.0)
#: The most voxels a mask may have (a 512 x 512 x 512 volume), checked from its header before it is read.
MAX_MASK_VOXELS = 512**3
#: The most triangles a target mesh may hold (a finely sampled scan of a gland has some 10^5).
MAX_TRIANGLES = 2_000_000
#: The least spacing (mm) of the marching cubes' samples of a mask (whole voxels: finer voxels are stepped over).
MARCHING_STEP_MM = 1.0
#: The mask's blur (voxels) before marching cubes.
MASK_BLUR_VOXELS = 1.0
#: The levels of the blurred mask (0 to 1) its surface may be drawn at: the one that keeps the mask's volume is near
#: one half (0.45 to 0.49 on ellipsoids of 7 to 28 ml); a quarter off it, the surface follows the blur, not the mask.
SURFACE_LEVELS = (0.25, 0.75)
#: The mask's surface encloses the mask's volume within this fraction, found in at most this many steps.
VOLUME_TOLERANCE = 1e-4
LEVEL_ITERATIONS = 8
#: The file endings read as a NIfTI volume; every other file is read as a mesh.
NIFTI_SUFFIXES = (".nii", ".nii.gz")
#: Flip from RAS to the phantom's frame (and back): x to the patient's left.
PHANTOM_FROM_RAS = np.array([-1.0, 1.0, 1.0])


class ShapeFileError(PhantomError):
    """A target shape file that cannot be used: the message says what is wrong and what to do."""


def is_nifti(path: str | Path) -> bool:
    """Whether ``path`` names a NIfTI volume (by its ending)."""
    return str(path).lower().endswith(NIFTI_SUFFIXES)


def read_target_surface(path: str | Path, labels: Sequence[int] | None = None) -> TriangleMesh:
    """The gland in ``path`` as a closed outward surface (mm, the phantom's frame); see the module.

    ``labels``: the gland's labels in a label map (a mask with one label needs none). Raises ShapeFileError.
    """
    path = Path(path)
    if not path.is_file():
        raise ShapeFileError(f"{path}: no such file: give a NIfTI mask (.nii, .nii.gz) or a closed mesh in mm")
    surface = _mask_surface(path, labels) if is_nifti(path) else _mesh_surface(path)
    return checked_gland(surface, str(path))


#: The most vertices of a mesh given in a request (the daemon's ``set_target`` with ``shape``): the API's request
#: size bounds it anyway; a larger target is a file on the daemon's machine.
MAX_REQUEST_VERTICES = 5000


def surface_from_json(data: object, where: str = "shape") -> TriangleMesh:
    """A target mesh given as ``{"vertices_mm": [[x, y, z], ...], "triangles": [[i, j, k], ...]}`` (mm, the
    phantom's frame), checked as a gland (:func:`checked_gland`); at most :data:`MAX_REQUEST_VERTICES` vertices.
    Raises ShapeFileError naming ``where``."""
    if not isinstance(data, dict) or set(data) != {"vertices_mm", "triangles"}:
        raise ShapeFileError(f"{where}: a mesh is an object with vertices_mm ([[x, y, z], ...] in mm) and triangles "
                             "([[i, j, k], ...]), or the path of a file on the daemon's machine")
    vertices, triangles = data["vertices_mm"], data["triangles"]
    if not isinstance(vertices, list) or not isinstance(triangles, list):
        raise ShapeFileError(f"{where}: vertices_mm and triangles are lists")
    if len(vertices) > MAX_REQUEST_VERTICES or len(triangles) > 2 * MAX_REQUEST_VERTICES:
        raise ShapeFileError(f"{where}: {len(vertices)} vertices, more than the {MAX_REQUEST_VERTICES} a request may "
                             "carry: give the path of a file on the daemon's machine")
    try:
        vertices_mm = np.array(vertices, dtype=float).reshape(-1, 3)
        indices = np.array(triangles, dtype=np.int64).reshape(-1, 3)
    except (TypeError, ValueError):
        raise ShapeFileError(f"{where}: vertices_mm are three numbers each, triangles three vertex indices each") \
            from None
    if len(vertices_mm) != len(vertices) or len(indices) != len(triangles):
        raise ShapeFileError(f"{where}: vertices_mm are three numbers each, triangles three vertex indices each")
    return checked_gland(TriangleMesh(vertices_mm, indices), where)


def checked_gland(surface: TriangleMesh, where: str) -> TriangleMesh:
    """``surface`` checked as a target gland: closed, finite, of one body, outward, and of a gland's volume in mm
    (turned outward when it faces in). Raises ShapeFileError naming ``where``."""
    vertices = np.asarray(surface.vertices_mm, dtype=float)
    triangles = np.asarray(surface.triangles, dtype=np.int64)
    if vertices.ndim != 2 or vertices.shape[1:] != (3,) or triangles.ndim != 2 or triangles.shape[1:] != (3,):
        raise ShapeFileError(f"{where}: a surface is vertices (n, 3) and triangles (k, 3), got {vertices.shape} and "
                             f"{triangles.shape}")
    if len(triangles) < 4:
        raise ShapeFileError(f"{where}: the surface has {len(triangles)} triangles: a closed surface has at least 4")
    if len(triangles) > MAX_TRIANGLES:
        raise ShapeFileError(f"{where}: the surface has {len(triangles)} triangles, more than {MAX_TRIANGLES}: "
                             "decimate it first")
    if not np.all(np.isfinite(vertices)):
        raise ShapeFileError(f"{where}: the surface has vertices that are not finite numbers")
    if triangles.min() < 0 or triangles.max() >= len(vertices):
        raise ShapeFileError(f"{where}: the triangles name vertices the surface does not have")
    open_edges = open_edge_count(triangles)
    if open_edges:
        raise ShapeFileError(f"{where}: the mesh is not closed ({open_edges} open edges): a target gland is a closed "
                             "surface; close its holes first (phantom compare-scan cleans and closes scans)")
    components = surface_components(triangles)
    if components.max() > 0:
        raise ShapeFileError(f"{where}: the mesh holds {components.max() + 1} separate bodies: keep the gland's")
    try:  # wound one way and outward: faces of mixed winding summed to a speck's volume, read as metres
        mesh, _ = outward_surface(TriangleMesh(vertices, triangles))
    except WindingError as error:
        raise ShapeFileError(f"{where}: {error}") from None
    volume_ml = enclosed_volume_ml(mesh)
    low, high = GLAND_VOLUME_RANGE_ML
    if not low <= volume_ml <= high:
        size_mm = float(np.max(np.ptp(vertices, axis=0)))
        raise ShapeFileError(
            f"{where}: the surface encloses {volume_ml:.3g} ml (if its numbers are mm) and is {size_mm:.3g} long: no "
            f"gland's size ({low:g}-{high:g} ml); a target is in millimetres: convert a mesh in metres (x 1000) or "
            "centimetres (x 10) first")
    return mesh


def read_nifti(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """A NIfTI volume's voxel values (3D) and its voxel-to-RAS affine (4 x 4, mm), checked: a readable 3D volume
    of at most :data:`MAX_MASK_VOXELS`, an affine that is finite and invertible with voxel sides within
    :data:`VOXEL_RANGE_MM` (a NaN affine or micrometre voxels encoded as the empty grid, exit 0), finite numbers.
    ShapeFileError naming the file otherwise. The shape analysis reads its masks through it too."""
    with require_extra("design"):
        import nibabel

    try:
        image: Any = nibabel.load(str(path))
        shape = tuple(int(side) for side in image.shape)
    except Exception as error:  # nibabel raises several kinds for a damaged or foreign file
        raise ShapeFileError(f"{path}: not a readable NIfTI file ({' '.join(str(error).split())})") from None
    if len(shape) == 4 and shape[3] == 1:
        shape = shape[:3]
    if len(shape) != 3:
        raise ShapeFileError(f"{path}: expected a 3D volume, got shape {shape}")
    if math.prod(shape) > MAX_MASK_VOXELS:
        raise ShapeFileError(f"{path}: the header declares {' x '.join(map(str, shape))} voxels, more than the "
                             f"{MAX_MASK_VOXELS} of a 512^3 mask: crop or resample it to the prostate's region first")
    affine = checked_affine(image.affine, path)
    try:
        values = np.asanyarray(image.dataobj).reshape(shape)
    except Exception as error:  # a file shorter than its header says, or damaged compression
        raise ShapeFileError(f"{path}: not a readable NIfTI file ({' '.join(str(error).split())})") from None
    if values.dtype.kind == "f" and not np.all(np.isfinite(values)):
        raise ShapeFileError(f"{path}: the mask holds NaN or infinite values: a mask is labels or 0/1")
    if values.dtype.kind not in "iufb":
        raise ShapeFileError(f"{path}: the mask's voxels are {values.dtype}, not numbers: a mask is labels or 0/1")
    return values, affine


def checked_affine(affine: Any, path: str | Path) -> np.ndarray:
    """A NIfTI file's voxel-to-RAS affine (mm), checked (see :func:`read_nifti`); ShapeFileError otherwise."""
    matrix = np.asarray(affine, dtype=float)
    if matrix.shape != (4, 4) or not np.all(np.isfinite(matrix)):
        raise ShapeFileError(f"{path}: the affine (voxel to RAS mm) is not finite: fix the header's qform/sform")
    sides_mm = np.linalg.norm(matrix[:3, :3], axis=0)
    low, high = VOXEL_RANGE_MM
    if not np.all((sides_mm >= low) & (sides_mm <= high)):
        raise ShapeFileError(f"{path}: the voxel sides are {', '.join(f'{side:.3g}' for side in sides_mm)} mm, "
                             f"outside [{low:g}, {high:g}] mm: the header's units or spacing are wrong (fix its "
                             "pixdim, qform or sform)")
    if abs(np.linalg.det(matrix[:3, :3])) < 1e-6 * float(np.prod(sides_mm)):
        raise ShapeFileError(f"{path}: the affine (voxel to RAS mm) is singular (its axes are not independent): fix "
                             "the header's qform/sform")
    return matrix


def _mask_surface(path: Path, labels: Sequence[int] | None) -> TriangleMesh:
    """A NIfTI mask's gland surfaced (see the module), in the phantom's frame."""
    with require_extra("design"):
        from scipy import ndimage
        from skimage import measure

    values, affine = read_nifti(path)
    sides_mm = np.linalg.norm(affine[:3, :3], axis=0)
    present = [int(value) for value in np.unique(values) if value != 0]
    if not present:
        raise ShapeFileError(f"{path}: the mask is empty (no voxel above 0): give the gland's segmentation")
    if labels:
        mask = np.isin(values, np.asarray(list(labels)))
        if not mask.any():
            raise ShapeFileError(f"{path}: no voxel is labelled {', '.join(map(str, labels))} (labels present: "
                                 f"{', '.join(map(str, present))}): choose the gland's labels")
    elif len(present) > 1:
        raise ShapeFileError(f"{path}: the mask holds several labels ({', '.join(map(str, present))}): say which are "
                             "the gland (--labels; the pelvic MRI dataset's prostate is 4,5)")
    else:
        mask = values != 0
    mask_ml = float(np.count_nonzero(mask)) * abs(float(np.linalg.det(affine[:3, :3]))) / 1e3
    low, high = GLAND_VOLUME_RANGE_ML
    if not low <= mask_ml <= high:
        raise ShapeFileError(f"{path}: the gland is {np.count_nonzero(mask)} voxels of "
                             f"{' x '.join(f'{side:.3g}' for side in sides_mm)} mm, {mask_ml:.3g} ml: no gland's "
                             f"size ({low:g}-{high:g} ml); give the gland's segmentation, with its voxel sizes in the "
                             "header")
    # samples about MARCHING_STEP_MM apart along each voxel axis, not a voxel's (0.7 mm voxels made 25,000
    # triangles on a gland): the blurred surface's curvature puts a 1.4 mm chord within 0.02 mm of it, and the
    # inverse's closest-point queries cost in proportion to the triangles near each point. Each axis has its own
    # step: one step for all, from the shortest side, sampled 0.1 x 0.1 x 1.4 mm voxels 14 mm apart along the long
    # side (a gland's volume +2 to +6 %, or a surface left open at the mask's end)
    steps = np.maximum(1, np.ceil(MARCHING_STEP_MM / sides_mm - 1e-9)).astype(int)
    # the blur no narrower than half a step: samples farther apart than two blur widths see the staircase again
    blur_voxels = np.maximum(MASK_BLUR_VOXELS, steps / 2.0)
    # three samples' margin (three voxels, as before the steps were per axis) keep the outermost samples outside
    # the gland, so the surface closes
    pad = 3 * steps
    padded = np.pad(mask.astype(np.float32), [(int(side), int(side)) for side in pad])
    sampled = ndimage.gaussian_filter(padded, blur_voxels)[::steps[0], ::steps[1], ::steps[2]]

    def surface_at(level: float) -> TriangleMesh:
        vertices, triangles, _, _ = measure.marching_cubes(sampled, level=level)
        ras_mm = (vertices * steps - pad) @ affine[:3, :3].T + affine[:3, 3]
        return TriangleMesh(np.asarray(ras_mm * PHANTOM_FROM_RAS, float), np.asarray(triangles, np.int64))

    if sampled.max() <= SURFACE_LEVELS[0]:
        raise ShapeFileError(f"{path}: the mask's voxels are scattered or thinner than a voxel everywhere: no "
                             "surface; is it the gland's segmentation?")
    surface = _volume_keeping_surface(surface_at, mask_ml, float(sampled.max()))
    return largest_body(surface, str(path))


def _volume_keeping_surface(surface_at: Callable[[float], TriangleMesh], volume_ml: float,
                             highest: float) -> TriangleMesh:
    """The surface ``surface_at(level)`` of the blurred mask at the level whose surface encloses the mask's volume
    (``volume_ml``: its voxels' count times a voxel's volume); ``highest``: the blurred mask's largest value.

    The blur keeps the mask's volume but its half level does not: on a convex gland the half level lies inside by
    about the blur's width squared times the mean curvature, which read ellipsoids 0.4 to 4.5 % small (more on
    thick slices and small glands). The level is found by the secant method on the volume (which falls as the level
    rises), within :data:`SURFACE_LEVELS`.
    """
    low, high = SURFACE_LEVELS[0], min(SURFACE_LEVELS[1], 0.999 * highest)
    before = min(0.5, high)
    before_ml = abs(enclosed_volume_ml(surface_at(before)))
    level = max(before - 0.02, low)
    surface = surface_at(level)
    for _ in range(LEVEL_ITERATIONS):
        level_ml = abs(enclosed_volume_ml(surface))
        if abs(level_ml - volume_ml) <= VOLUME_TOLERANCE * volume_ml or level_ml == before_ml:
            break
        following = float(np.clip(level + (volume_ml - level_ml) * (level - before) / (level_ml - before_ml), low,
                                  high))
        before, before_ml, level = level, level_ml, following
        surface = surface_at(level)
    return surface


def _mesh_surface(path: Path) -> TriangleMesh:
    """A mesh file's triangles (meshio), with coincident vertices merged (an STL repeats them per triangle)."""
    import meshio

    try:
        with warnings.catch_warnings():
            # meshio's binary-STL size check overflows a 32-bit count on an ASCII file (harmless: it reads it)
            warnings.simplefilter("ignore", RuntimeWarning)
            mesh = meshio.read(str(path))
    except Exception as error:  # meshio raises several kinds for a damaged or foreign file
        raise ShapeFileError(f"{path}: not a readable mesh ({' '.join(str(error).split())}): give a closed triangle "
                             "mesh (STL, PLY, OBJ, VTK) in mm, or a NIfTI mask") from None
    blocks = [np.asarray(block.data, np.int64) for block in mesh.cells if block.type == "triangle"]
    if not blocks:
        raise ShapeFileError(f"{path}: the mesh has no triangles: give a closed triangle surface in mm")
    points = np.asarray(mesh.points, dtype=float)[:, :3]
    if not np.all(np.isfinite(points)):
        raise ShapeFileError(f"{path}: the mesh has vertices that are not finite numbers")
    scale = max(float(np.max(np.abs(points))), 1e-300)
    _, first, merged = np.unique(np.round(points / scale, 9), axis=0, return_index=True, return_inverse=True)
    triangles = merged.reshape(-1)[np.concatenate(blocks)]
    return TriangleMesh(points[first], triangles.astype(np.int64))


def largest_body(surface: TriangleMesh, where: str) -> TriangleMesh:
    """The largest closed body of a surface (a stray island of a segmentation or of a decoded shape dropped),
    vertices compacted."""
    components = surface_components(surface.triangles)
    keep = surface.triangles
    if components.max() > 0:
        volumes = [abs(enclosed_volume_ml(TriangleMesh(surface.vertices_mm, surface.triangles[components == k])))
                   for k in range(components.max() + 1)]
        keep = surface.triangles[components == int(np.argmax(volumes))]
    used, renumbered = np.unique(keep, return_inverse=True)
    if len(used) == 0:
        raise ShapeFileError(f"{where}: the mask's gland has no surface")
    return TriangleMesh(surface.vertices_mm[used], renumbered.reshape(-1, 3).astype(np.int64))
