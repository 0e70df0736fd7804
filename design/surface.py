"""The gland's outer surface (mm, the phantom's frame): from a NIfTI label mask or a closed mesh.

A mask is surfaced by marching cubes on its own voxel grid and carried through its affine into the world (RAS),
so an anisotropic or oblique acquisition gives the gland in millimetres as it is; only the largest connected
component is kept (a stray island of a segmentation is dropped and said). The surface is then smoothed by Taubin's
filter (a Laplacian step and a negative one in turn: the staircase goes, the volume stays; the change is
reported) and turned into the phantom's frame from the mask's RAS axes (x to the patient's left, y anterior, z
from apex to base: :data:`phantom.shape.voxels.RAS_FROM_PHANTOM`), centred and scaled to the target volume. The
mid-sagittal plane is taken through the gland's centroid (x = 0 after centring: a mask has no landmark of the
midline), the other axes are centred on the bounding box. A closed mesh is read as ``phantom shape`` reads one
(mm, already in the phantom's frame; wound one way and outward).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from phantom import require_extra
from phantom.design.errors import DesignError
from phantom.model.arrays import FloatArray, IntArray
from phantom.shape.dataset import PROSTATE_LABELS, Case, find_cases, read_closed_mesh, read_label_mask
from phantom.shape.voxels import RAS_FROM_PHANTOM

#: Taubin passes for a mask's marching-cubes surface (each a +0.5 and a -0.53 Laplacian step).
SMOOTHING_ITERATIONS = 20
#: A second component at least this fraction of the largest's size makes the mask ambiguous (two glands?).
AMBIGUOUS_COMPONENT_FRACTION = 0.5
#: The fewest voxels across the gland in every direction of its grid: marching cubes on fewer gives no gland's
#: surface (a one-voxel line ran 7 minutes at 1-3.5 GB before its mesh failed).
MIN_VOXELS_ACROSS = 3
#: The most a gland's longest principal extent may be times its shortest: a prostate is about 1.5 (4.5 x 3 x 3.5
#: cm), an enlarged one 2-3; a needle scaled to a gland's volume meshes into millions of elements.
MAX_ASPECT = 4.0


@dataclass(frozen=True)
class Surface:
    """A closed triangle mesh (mm): ``vertices_mm (V, 3)`` and outward ``triangles (T, 3)``."""

    vertices_mm: FloatArray
    triangles: IntArray

    def volume_ml(self) -> float:
        a, b, c = (self.vertices_mm[self.triangles[:, i]] for i in range(3))
        return float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0 / 1e3)

    def outward(self) -> Surface:
        return self if self.volume_ml() > 0 else Surface(self.vertices_mm, self.triangles[:, ::-1].copy())

    def centroid_mm(self) -> FloatArray:
        """The centroid of the enclosed solid (mm)."""
        a, b, c = (self.vertices_mm[self.triangles[:, i]] for i in range(3))
        signed = np.einsum("ij,ij->i", a, np.cross(b, c))
        centroid: FloatArray = (signed[:, None] * (a + b + c)).sum(axis=0) / (4.0 * signed.sum())
        return centroid

    def compacted(self) -> Surface:
        """The same surface without the vertices no triangle uses."""
        used, triangles = np.unique(self.triangles, return_inverse=True)
        return Surface(self.vertices_mm[used], triangles.reshape(-1, 3).astype(np.int64))

    def contains(self, point_mm: FloatArray) -> bool:
        """Whether a point lies inside: the parity of the triangles a ray along +z from it crosses."""
        return len(self.crossings_above_mm(point_mm)) % 2 == 1

    def crossings_above_mm(self, point_mm: FloatArray) -> FloatArray:
        """The heights (z, mm) at which the ray along +z from a point crosses the surface, sorted."""
        a, b, c = (self.vertices_mm[self.triangles[:, i]] - point_mm for i in range(3))
        det = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (c[:, 0] - a[:, 0]) * (b[:, 1] - a[:, 1])
        safe = np.where(det == 0, 1.0, det)
        # the ray is nudged off the lattice a marching-cubes surface's vertices lie on
        px, py = 3.1e-7, 4.7e-7
        u = ((px - a[:, 0]) * (c[:, 1] - a[:, 1]) - (c[:, 0] - a[:, 0]) * (py - a[:, 1])) / safe
        v = ((b[:, 0] - a[:, 0]) * (py - a[:, 1]) - (px - a[:, 0]) * (b[:, 1] - a[:, 1])) / safe
        hit = (det != 0) & (u >= 0) & (v >= 0) & (u + v <= 1)
        z = a[:, 2] + u * (b[:, 2] - a[:, 2]) + v * (c[:, 2] - a[:, 2])
        crossings: FloatArray = np.sort(z[hit & (z > 0)] + point_mm[2])
        return crossings

    def moved(self, offset_mm: FloatArray, scale: float = 1.0) -> Surface:
        """``(vertices + offset) * scale``."""
        return Surface((self.vertices_mm + offset_mm) * scale, self.triangles)


@dataclass(frozen=True)
class Gland:
    """The designed outer surface and what was done to get it.

    surface : the gland, smoothed, in the phantom's frame, centred (x on its centroid, y and z on its bounding
        box), scaled to the target.
    reference : the source's own surface (a mask's marching cubes before smoothing, or the mesh as read), moved
        and scaled the same way: what the design is compared with.
    source_volume_ml : the source's volume as read (a mask's voxel count times the voxel's volume, else the
        mesh's); smoothing_change_pct : the smoothing's volume change (% of the marching-cubes surface's);
        scale : the factor that made the target volume; notes : what a user should know (dropped components).
    """

    surface: Surface
    reference: Surface
    source_volume_ml: float
    smoothing_change_pct: float
    scale: float
    notes: list[str] = field(default_factory=list)


def read_gland(path: str | Path, volume_ml: float, labels: Sequence[int] | None = None,
               smoothing_iterations: int | None = None) -> Gland:
    """The gland of a NIfTI mask or a closed mesh (see the module docstring), scaled to ``volume_ml``.

    ``labels`` picks the gland's labels of a label map (the dataset's ``*_mask.nii`` default to its prostate,
    4 and 5); a plain mask with several labels needs them. ``smoothing_iterations`` defaults to
    SMOOTHING_ITERATIONS for a mask and 0 for a mesh.
    """
    if not 0 < volume_ml < 500:
        raise DesignError(f"--volume-ml {volume_ml:g} is not a gland's volume: give a positive number of ml "
                          f"(the paper's average prostate: 26.3)")
    cases = find_cases(path)
    if len(cases) != 1 or not Path(path).is_file():
        raise DesignError(f"{path} is a folder: give one mask or mesh file (phantom design designs one phantom)")
    case = cases[0]
    notes: list[str] = []
    if case.kind == "mesh":
        closed = read_closed_mesh(case.path).mirrored_x()  # shape reads meshes into RAS; back to the phantom's
        # read_closed_mesh winds it one way and outward; the mirror keeps it outward
        raw = _largest_body(Surface(closed.vertices_mm, closed.triangles), notes)
        source_volume_ml = raw.volume_ml()
        iterations = 0 if smoothing_iterations is None else smoothing_iterations
    else:
        raw, source_volume_ml = _mask_surface(case, labels, notes)
        iterations = SMOOTHING_ITERATIONS if smoothing_iterations is None else smoothing_iterations
    smooth = _taubin(raw, iterations)
    change_pct = 100.0 * (smooth.volume_ml() / raw.volume_ml() - 1.0)
    centre = -0.5 * (smooth.vertices_mm.min(axis=0) + smooth.vertices_mm.max(axis=0))
    # the mid-sagittal plane through the centroid: a mask has no landmark of the midline, and the bounding box's
    # middle would hand both lobes the same extent
    centre[0] = -smooth.centroid_mm()[0]
    scale = float((volume_ml / smooth.volume_ml()) ** (1.0 / 3.0))
    return Gland(smooth.moved(centre, scale), raw.moved(centre, scale), source_volume_ml, change_pct, scale, notes)


def _mask_surface(case: Case, labels: Sequence[int] | None, notes: list[str]) -> tuple[Surface, float]:
    """A mask's largest component surfaced by marching cubes in the phantom's frame, and the mask's volume (ml)."""
    with require_extra("design"):
        import nibabel
        from scipy import ndimage
        from skimage import measure

    try:
        image: Any = nibabel.load(str(case.path))
        values = np.unique(np.asarray(image.dataobj))
    except Exception:  # nibabel raises several kinds for a damaged file: read_label_mask says it plainly
        values = np.zeros(0)
    if values.dtype.kind == "f":
        finite = values[np.isfinite(values)]
        fractional = finite[finite != np.round(finite)]
        if fractional.size:
            shown = ", ".join(f"{value:.3g}" for value in fractional[:5]) + (", ..." if fractional.size > 5 else "")
            raise DesignError(f"{case.path}: the mask holds fractional values ({shown}; {fractional.size} in all): a "
                              f"mask is labels or 0/1, not a probability map: threshold it (e.g. > 0.5) and save it "
                              f"as integers")
    if labels is None:
        present = sorted(int(value) for value in values if value != 0)
        if present == [1]:
            # a binary mask, whatever its name says (a data set's *_mask.nii is a label map otherwise)
            case = Case(case.name, case.path, "mask")
        elif len(present) > 1 and case.kind == "mask":
            raise DesignError(f"{case.path} holds several labels ({', '.join(map(str, present))}): say which are "
                              f"the gland with --labels (the pelvic MRI dataset's prostate is 4,5)")
    mask = read_label_mask(case, PROSTATE_LABELS if labels is None else labels)
    components, count = ndimage.label(mask.mask, structure=np.ones((3, 3, 3)))
    sizes = np.bincount(components.ravel())[1:]
    largest = int(np.argmax(sizes)) + 1
    if count > 1:
        order = np.sort(sizes)[::-1]
        voxel_ml = mask.voxel_volume_mm3 / 1e3
        if order[1] >= AMBIGUOUS_COMPONENT_FRACTION * order[0]:
            raise DesignError(f"{case.path}: the gland is {count} separate pieces, the two largest "
                              f"{order[0] * voxel_ml:.2f} and {order[1] * voxel_ml:.2f} ml: which is the gland is "
                              f"not clear; crop the mask to one, or choose its labels with --labels")
        notes.append(f"the mask has {count} separate pieces: kept the largest ({order[0] * voxel_ml:.2f} ml), "
                     f"dropped {count - 1} of {order[1:].sum() * voxel_ml:.3f} ml in all")
    gland = components == largest
    where = np.nonzero(gland)
    low = np.array([axis.min() for axis in where])
    high = np.array([axis.max() for axis in where])
    across = high - low + 1
    if across.min() < MIN_VOXELS_ACROSS:
        raise DesignError(f"{case.path}: the gland is {' x '.join(map(str, across))} voxels: a gland's surface needs "
                          f"at least {MIN_VOXELS_ACROSS} voxels across in every direction of its grid; is it a "
                          f"gland's mask (a line or a sheet is not)?")
    if np.any(low == 0) or np.any(high == np.asarray(gland.shape) - 1):
        faces = [f"{'ijk'[axis]} = {0 if low[axis] == 0 else gland.shape[axis] - 1}" for axis in range(3)
                 for edge in (low[axis] == 0, high[axis] == gland.shape[axis] - 1) if edge]
        notes.append(f"the gland touches the edge of the mask's grid ({', '.join(faces)}): it may be cut off "
                     f"there (the design closes it flat); is the whole gland in the mask, and is it a gland's "
                     f"mask (an all-ones volume is a box)?")
    padded = np.pad(gland.astype(np.float32), 1)
    vertices, triangles, _, _ = measure.marching_cubes(padded, level=0.5)
    affine = mask.affine
    ras = (vertices - 1.0) @ affine[:3, :3].T + affine[:3, 3]
    surface = Surface(ras * RAS_FROM_PHANTOM, triangles.astype(np.int64)).outward()
    _check_aspect(surface, case.path)
    return surface, float(sizes[largest - 1]) * mask.voxel_volume_mm3 / 1e3


def _check_aspect(surface: Surface, path: Path) -> None:
    """Refuse a shape whose longest principal extent is more than MAX_ASPECT times its shortest (no gland's)."""
    centred = surface.vertices_mm - surface.vertices_mm.mean(axis=0)
    _, _, axes = np.linalg.svd(centred, full_matrices=False)
    projected = centred @ axes.T
    extents = np.sort(projected.max(axis=0) - projected.min(axis=0))[::-1]
    aspect = extents[0] / max(extents[-1], 1e-9)
    if aspect > MAX_ASPECT:
        sizes = " x ".join(f"{extent:.1f}" for extent in extents)
        raise DesignError(f"{path}: the shape is {aspect:.1f} times as long as it is thin ({sizes} mm along its "
                          f"principal axes); a gland is at most {MAX_ASPECT:g} (a prostate about 1.5): is it a "
                          f"gland's mask?")


def _largest_body(surface: Surface, notes: list[str]) -> Surface:
    """The largest closed body of a mesh that holds several (each a connected set of triangles)."""
    from phantom.model.mesh.tetmesh import surface_components

    labels = surface_components(surface.triangles)
    if labels.max() == 0:
        return surface
    bodies = [Surface(surface.vertices_mm, surface.triangles[labels == k]) for k in range(labels.max() + 1)]
    volumes = np.array([abs(body.volume_ml()) for body in bodies])
    order = np.argsort(volumes)[::-1]
    if volumes[order[1]] >= AMBIGUOUS_COMPONENT_FRACTION * volumes[order[0]]:
        raise DesignError(f"the mesh holds {len(bodies)} separate bodies, the two largest {volumes[order[0]]:.2f} "
                          f"and {volumes[order[1]]:.2f} ml: which is the gland is not clear; keep one")
    notes.append(f"the mesh holds {len(bodies)} separate bodies: kept the largest ({volumes[order[0]]:.2f} ml)")
    return bodies[int(order[0])].compacted()


def _taubin(surface: Surface, iterations: int) -> Surface:
    """Taubin's non-shrinking smoothing (trimesh's filter, lambda 0.5, mu -0.53)."""
    if iterations <= 0:
        return surface
    with require_extra("design"):
        import trimesh
        from trimesh import smoothing

    mesh = trimesh.Trimesh(surface.vertices_mm.copy(), surface.triangles, process=True)
    smoothing.filter_taubin(mesh, lamb=0.5, nu=0.53, iterations=iterations)
    return Surface(np.asarray(mesh.vertices, float), np.asarray(mesh.faces, np.int64)).outward()
