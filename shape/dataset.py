"""Shape data: the pelvic MRI dataset's layout, folders of masks or meshes, read into one set of shape grids.

The Cross-institution Male Pelvic Structures dataset (Li et al. 2023; Zenodo record 7013610, ``data.zip`` and
``institution.txt``) unpacks to::

    DATASET/
        institution.txt          one line per case: "<case id> <institution number 1-7>"
        data/
            <case id>_img.nii    the T2-weighted image
            <case id>_mask.nii   its label map: 0 background, 1 bladder, 2 bone, 3 obturator internus,
                                 4 transition zone (TZ), 5 central gland (CG), 6 rectum, 7 seminal vesicles,
                                 8 neurovascular bundles

The labels are exclusive (one per voxel), so the prostate is the union of labels 4 and 5
(:data:`PROSTATE_LABELS`); ``labels`` chooses others. Besides that layout, a folder may hold binary masks
(``*.nii``, ``*.nii.gz``: voxels above 0 are the shape; a file with values above 1 is a label map and ``labels``
selects from it) or closed meshes (``.obj``, ``.ply``, ``.stl``, in mm in the phantom's frame: x to the
patient's left, y anterior, z toward the base).

Every shape is resampled onto a grid of ``grid_size^3`` cubic voxels in the world's axes (RAS, from each file's
affine, so spacing and orientation are the file's own), centred on its centroid, with one voxel size for the
whole set (:attr:`ShapeSet.voxel_mm`, recorded with a trained run so that volumes come back in ml).
"""

from __future__ import annotations

import multiprocessing
import os
from collections.abc import Iterator, Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from itertools import repeat
from pathlib import Path

import numpy as np

from phantom import require_extra
from phantom.model.mesh.surface import TriangleMesh
from phantom.model.mesh.tetmesh import open_edge_count
from phantom.model.mesh.winding import WindingError, outward_surface
from phantom.model.shape_file import ShapeFileError, read_nifti
from phantom.shape.errors import ShapeError
from phantom.shape.voxels import SUPERSAMPLE, ClosedSurface, LabelMask

#: The dataset's label numbers and names (as its loaders name them).
LABEL_NAMES: dict[int, str] = {1: "BladderMask", 2: "BoneMask", 3: "ObdInternMask", 4: "TZ", 5: "CG",
                               6: "RectumMask", 7: "SV", 8: "NVB"}
#: The prostate in the dataset's label maps: transition zone and central gland.
PROSTATE_LABELS: tuple[int, ...] = (4, 5)
MASK_SUFFIX = "_mask"
IMAGE_SUFFIX = "_img"
NIFTI_EXTENSIONS = (".nii", ".nii.gz")
MESH_EXTENSIONS = (".obj", ".ply", ".stl")
#: Empty voxels kept between a set's largest shape and the grid's faces.
MARGIN_VOXELS = 2
#: Fewer cases than this are put on the grid in this process: a worker process takes about a second to start,
#: the time of four cases' grids (0.26 s each on this project's machine; 589 cases took 150 s on one core).
PARALLEL_FROM_CASES = 16


def nifti_stem(path: Path) -> str | None:
    """The file name without .nii or .nii.gz; None for any other file."""
    for extension in (".nii.gz", ".nii"):
        if path.name.endswith(extension):
            return path.name[: -len(extension)]
    return None


@dataclass(frozen=True)
class Case:
    """One shape to read: its name, file, and whether the file is a label map, a binary mask or a mesh."""

    name: str
    path: Path
    kind: str  # "labels", "mask" or "mesh"


def find_cases(path: str | Path) -> list[Case]:
    """The shapes a path holds: the dataset's layout, a folder of masks or meshes, or one such file."""
    path = Path(path)
    if not path.exists():
        raise ShapeError(f"{path}: no such file or folder")
    if path.is_file():
        return [_file_case(path)]
    data = path / "data" if (path / "data").is_dir() else path
    label_maps = sorted(p for p in data.iterdir() if (nifti_stem(p) or "").endswith(MASK_SUFFIX))
    if label_maps:
        return [Case(nifti_stem(p)[: -len(MASK_SUFFIX)], p, "labels") for p in label_maps]  # type: ignore[index]
    images = [p for p in data.iterdir() if (nifti_stem(p) or "").endswith(IMAGE_SUFFIX)]
    masks = sorted(p for p in data.iterdir() if nifti_stem(p) is not None and p not in images)
    meshes = sorted(p for p in data.iterdir() if p.suffix.lower() in MESH_EXTENSIONS)
    if images and not masks:
        raise ShapeError(f"{data} holds images (*{IMAGE_SUFFIX}.nii) but no label maps (*{MASK_SUFFIX}.nii): "
                         f"the shapes come from the label maps")
    if masks and meshes:
        raise ShapeError(f"{data} mixes NIfTI masks and meshes: keep one kind of shape in a folder")
    cases = [_file_case(p) for p in masks + meshes]
    if not cases:
        raise ShapeError(f"{path} holds no shapes: expected the dataset's data/*{MASK_SUFFIX}.nii, NIfTI masks "
                         f"(*.nii, *.nii.gz) or closed meshes ({', '.join(MESH_EXTENSIONS)})")
    return cases


def _file_case(path: Path) -> Case:
    stem = nifti_stem(path)
    if stem is not None:
        if stem.endswith(MASK_SUFFIX):
            return Case(stem[: -len(MASK_SUFFIX)], path, "labels")
        return Case(stem, path, "mask")
    if path.suffix.lower() in MESH_EXTENSIONS:
        return Case(path.stem, path, "mesh")
    raise ShapeError(f"{path}: not a shape file: use a NIfTI mask (.nii, .nii.gz) or a closed mesh "
                     f"({', '.join(MESH_EXTENSIONS)})")


def read_institutions(path: str | Path) -> dict[str, str]:
    """The dataset's ``institution.txt`` (case id -> institution), or {} where there is none."""
    path = Path(path)
    listing = path / "institution.txt" if path.is_dir() else path.parent.parent / "institution.txt"
    if not listing.is_file():
        return {}
    institutions = {}
    for number, line in enumerate(listing.read_text().splitlines(), 1):
        fields = line.split()
        if not fields:
            continue
        if len(fields) != 2:
            raise ShapeError(f"{listing}:{number}: expected '<case id> <institution>', got {line!r}")
        institutions[fields[0]] = fields[1]
    return institutions


def _label_text(labels: Sequence[int]) -> str:
    return " or ".join(f"{label} ({LABEL_NAMES.get(label, 'unnamed')})" for label in labels)


def read_label_mask(case: Case, labels: Sequence[int] = PROSTATE_LABELS) -> LabelMask:
    """The shape's mask in a NIfTI file: ``labels`` of a label map, or the voxels above 0 of a binary mask."""
    try:
        values, affine = read_nifti(case.path)   # the checks of the shape inverse's targets
    except ShapeFileError as error:
        raise ShapeError(str(error)) from None
    is_label_map = case.kind == "labels" or values.max(initial=0) > 1
    if is_label_map:
        mask = np.isin(values, np.asarray(labels))
        if not mask.any():
            present = sorted(int(v) for v in np.unique(values) if v != 0)
            raise ShapeError(f"{case.path}: no voxel is labelled {_label_text(labels)} (labels present: "
                             f"{present or 'none'}): choose the shape's labels with --labels")
    else:
        mask = values > 0
        if not mask.any():
            raise ShapeError(f"{case.path}: the mask is empty (no voxel above 0)")
    return LabelMask(mask.astype(bool, copy=False), affine)


def read_closed_mesh(path: str | Path) -> ClosedSurface:
    """A closed triangle mesh (mm, the phantom's frame) as a surface in RAS mm, wound one way and outward
    (:func:`phantom.model.mesh.winding.outward_surface`).

    Raises ShapeError when the file cannot be read, a vertex is not finite, the surface is not closed, or its
    triangles cannot be wound one way.
    """
    # trimesh (0.3 s to import) only where a mesh is read
    with require_extra("shape"):
        import trimesh

    path = Path(path)
    try:
        loaded = trimesh.load(str(path), force="mesh", process=False)
    except Exception as error:  # trimesh raises several kinds for a damaged or foreign file
        raise ShapeError(f"{path}: not a readable mesh ({error})") from None
    if not isinstance(loaded, trimesh.Trimesh) or len(loaded.faces) == 0:
        raise ShapeError(f"{path}: the mesh has no triangles")
    finite = np.isfinite(np.asarray(loaded.vertices, np.float64)).all(axis=1)
    if not finite.all():  # the merge below drops them, and what was left failed far later without a word
        raise ShapeError(f"{path} has {np.count_nonzero(~finite)} vertices with non-finite coordinates (nan or "
                         f"inf), first at index {int(np.flatnonzero(~finite)[0])}: re-export the mesh")
    merged = trimesh.Trimesh(np.asarray(loaded.vertices, np.float64), np.asarray(loaded.faces, np.int64), process=True)
    vertices, triangles = np.asarray(merged.vertices, float), np.asarray(merged.faces, np.int64)
    open_edges = open_edge_count(triangles)
    if open_edges:
        raise ShapeError(f"{path}: the mesh is not closed ({open_edges} open edges): close its holes first "
                         f"(compare-scan cleans and closes scans)")
    try:
        outward, _ = outward_surface(TriangleMesh(vertices, triangles))
    except WindingError as error:
        raise ShapeError(f"{path}: {error}") from None
    return ClosedSurface(outward.vertices_mm, outward.triangles).mirrored_x()


def read_shape(case: Case, labels: Sequence[int] = PROSTATE_LABELS) -> LabelMask | ClosedSurface:
    """A case's shape: a mask on its image grid, or a closed surface, both in RAS mm."""
    if case.kind == "mesh":
        return read_closed_mesh(case.path)
    return read_label_mask(case, labels)


@dataclass
class ShapeSet:
    """Shapes on one grid: ``occupancy (N, G, G, G)`` in [0, 1], RAS axes, each centred on its centroid.

    Attributes
    ----------
    names : list of str
        Case names, in the order of ``occupancy``.
    occupancy : ndarray
        The grids, float32.
    voxel_mm : float
        Side of a grid voxel (mm), the same for every shape (the set's one scale factor).
    volumes_ml : ndarray
        Each shape's volume as read (mask voxels or mesh), ml.
    labels : tuple of int
        The labels that made the shapes from label maps.
    """

    names: list[str]
    occupancy: np.ndarray
    voxel_mm: float
    volumes_ml: np.ndarray
    labels: tuple[int, ...]

    @property
    def grid_size(self) -> int:
        return int(self.occupancy.shape[1])


def set_voxel_mm(half_extents_mm: Sequence[float], grid_size: int, margin_voxels: int = MARGIN_VOXELS) -> float:
    """The voxel size (mm) that fits the largest shape in the grid with ``margin_voxels`` to spare each side."""
    usable = grid_size - 2 * margin_voxels
    if usable < 2:
        raise ShapeError(f"grid_size {grid_size} leaves no room inside a margin of {margin_voxels} voxels")
    return 2.0 * max(half_extents_mm) / usable


def shape_grid(shape: LabelMask | ClosedSurface, voxel_mm: float, grid_size: int, name: str,
               supersample: int = SUPERSAMPLE) -> np.ndarray:
    """One shape on a grid centred on its centroid; ShapeError when it does not fit the grid."""
    centre = shape.centroid_mm()
    half_extent = shape.half_extent_mm(centre)
    room = grid_size / 2.0 * voxel_mm
    if not half_extent <= room:
        raise ShapeError(f"{name} reaches {half_extent:.1f} mm from its centroid, beyond the grid's "
                         f"{room:.1f} mm ({grid_size} voxels of {voxel_mm:.3f} mm): it is larger than the shapes "
                         f"the run was trained on")
    grid = shape.occupancy(centre, voxel_mm, grid_size, supersample)
    if not grid.any():
        raise ShapeError(f"{name} comes out empty on the grid ({grid_size} voxels of {voxel_mm:.3f} mm): it is "
                         f"smaller than a voxel; check its units")
    return grid


def _grids(shapes: list[LabelMask | ClosedSurface], names: list[str], voxel_mm: float, grid_size: int,
           workers: int | None, progress: bool) -> list[np.ndarray]:
    """Each shape on the grid (:func:`shape_grid`), by ``workers`` processes (None: one per core) where there are
    enough shapes to pay for starting them; a line of progress every 50 shapes."""
    if workers is None:
        workers = len(os.sched_getaffinity(0))
    if workers <= 1 or len(shapes) < PARALLEL_FROM_CASES:
        return _told(map(shape_grid, shapes, repeat(voxel_mm), repeat(grid_size), names), len(shapes), progress)
    # spawned, not forked: the caller may have started JAX's threads, which a fork would copy mid-flight
    with ProcessPoolExecutor(max_workers=min(workers, len(shapes)),
                             mp_context=multiprocessing.get_context("spawn")) as pool:
        return _told(pool.map(shape_grid, shapes, repeat(voxel_mm), repeat(grid_size), names,
                              chunksize=max(1, len(shapes) // (4 * workers))), len(shapes), progress)


def _told(grids: Iterator[np.ndarray], count: int, progress: bool) -> list[np.ndarray]:
    """The grids as they come, with a line of progress every 50."""
    made = []
    for number, grid in enumerate(grids, 1):
        made.append(grid)
        if progress and (number % 50 == 0 or number == count):
            print(f"shape: put {number}/{count} shapes on the grid", flush=True)
    return made


def load_shapes(path: str | Path, grid_size: int = 32, labels: Sequence[int] = PROSTATE_LABELS,
                voxel_mm: float | None = None, margin_voxels: int = MARGIN_VOXELS,
                progress: bool = False, workers: int | None = None) -> ShapeSet:
    """Read every shape under ``path`` (see the module docstring) onto one grid.

    ``voxel_mm`` None fits the set's largest shape in the grid with ``margin_voxels`` to spare; a trained run
    passes its own, so that a new shape lands on the grid it was trained on. The grids are made by ``workers``
    processes (None: one per core; 1: in this process), the same grids either way.
    """
    cases = find_cases(path)
    shapes = []
    for number, case in enumerate(cases, 1):
        shapes.append(read_shape(case, labels))
        if progress and (number % 50 == 0 or number == len(cases)):
            print(f"shape: read {number}/{len(cases)} shapes", flush=True)
    centres = [shape.centroid_mm() for shape in shapes]
    if voxel_mm is None:
        voxel_mm = set_voxel_mm([s.half_extent_mm(c) for s, c in zip(shapes, centres, strict=True)], grid_size,
                                margin_voxels)
    grids = np.stack(_grids(shapes, [str(case.path) for case in cases], voxel_mm, grid_size, workers, progress))
    volumes = np.array([shape.volume_ml() for shape in shapes])
    return ShapeSet([case.name for case in cases], grids, float(voxel_mm), volumes, tuple(labels))
