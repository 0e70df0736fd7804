"""A capture folder to a mesh: the silhouettes, the poses from the rig's calibration, carving, the surface.

:func:`reconstruct` reads each picture, finds the phantom's silhouette (:mod:`phantom.scan.silhouette`), takes
the camera's pose at the frame's orbit angle and elevation from the rig (:class:`phantom.scan.camera.Rig`),
carves the visual hull coarse to fine and returns its smooth, closed surface in mm in the rig's frame (the orbit
axis along z through the origin, for a calibrated rig). The pictures are read and keyed on two threads (OpenCV
and the kernels release the interpreter's lock), and so is the carving.

The visual hull is the largest shape consistent with the silhouettes: it holds the phantom and touches it wherever
a camera sees its outline. A dent that no line of sight grazes (a concavity: the surface curving inwards in every
direction) is filled in; :mod:`bench/scan_accuracy.py` shows how much on a shape with one.

A capture whose pictures do not line up is refused (CarveError) rather than carved: a picture taken after the
camera or the turntable was bumped cuts a slab off the hull (one shifted 30 px of the verify scan's 640x480 read
its volume 14 % low). Each silhouette must be covered by the hull's projection
(:func:`phantom.scan.carve.view_agreement`, scan/README.md for the figures); where one is not, the picture whose
silhouette bounds the most of the hull is carved without, and named when the others then all agree.
"""

from __future__ import annotations

import concurrent.futures
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import meshio
import numpy as np

from phantom import memory_budget_bytes
from phantom.model.arrays import FloatArray
from phantom.model.mesh.surface import TriangleMesh, enclosed_volume_ml
from phantom.scan.camera import Camera, Pose, Rig
from phantom.scan.capture import CaptureError, CaptureFolder, Frame, png_size
from phantom.scan.carve import CarveError, Carver, View, ViewAgreement, carve, surface, view_agreement
from phantom.scan.compare import SCAN_SUFFIXES, ScanError
from phantom.scan.hanging import HANGING_SHARE, Hanging, cut_column
from phantom.scan.silhouette import Silhouette, SilhouetteError, silhouette

#: The voxel size (mm) of the finest grid by default.
VOXEL_MM = 0.3
#: The carving starts from a cube of this fraction of the camera's distance from the orbit's centre (half side).
START_FRACTION = 0.35
#: Threads that read and key the pictures, and carve.
THREADS = 2
#: The finest voxel (mm) carving goes to: the virtual camera's pixel is 0.14 mm at the phantom, so a finer grid
#: only resolves the carving's own noise.
MIN_VOXEL_MM = 0.05
#: The coarsest: a voxel of the phantom's wall thickness.
MAX_VOXEL_MM = 5.0
#: The most of a silhouette's area the hull may leave uncovered (a share) in a capture whose pictures line up:
#: steady captures of the virtual rig read 0.00 % (ideal and hung by its tubes, 320x240 to 1280x960), one picture
#: moved 5 px at 640x480 0.64 %, 10 px 2.5 % or more (scan/README.md, "Pictures that do not line up").
MAX_UNCOVERED = 0.005
#: Bytes the carving keeps per pixel of a picture (a silhouette's signed distance, float32, at most the whole
#: picture), and holds per picture being read and keyed (the picture, its linear copy, the key, the backdrop's
#: level smoothed, its alpha).
SILHOUETTE_BYTES_PER_PX = 4
KEYING_BYTES_PER_PX = 64


@dataclass
class Reconstruction:
    """The surface (mm, the rig's frame), its volume, and what it took."""

    mesh: TriangleMesh
    volume_ml: float
    voxel_mm: float
    views: int
    centre_mm: FloatArray
    stage_s: dict[str, float] = field(default_factory=dict)
    projections: int = 0
    #: Pictures whose edge the reconstructed phantom reaches (what is past it is missing).
    touching_edge: int = 0
    #: The hanging column taken off (None: nothing hung in view).
    hanging: Hanging | None = None
    #: The largest share of a picture's silhouette the hull leaves uncovered (%): near 0 when the pictures line up;
    #: None when not checked (``reconstruct(check_lined_up=False)``).
    worst_uncovered_pct: float | None = None


def views_cutting(mesh: TriangleMesh, camera: Camera, poses: Sequence[Pose], margin_px: float = 1.0) -> int:
    """How many of the pictures the surface reaches the edge of (within ``margin_px``) or passes behind."""
    count = 0
    for pose in poses:
        points = pose.apply(mesh.vertices_mm)
        if np.any(points[:, 2] <= 1e-6):
            count += 1
            continue
        pixels = camera.project(points)
        if (np.any(pixels < margin_px - 0.5) or np.any(pixels[:, 0] > camera.width - 0.5 - margin_px)
                or np.any(pixels[:, 1] > camera.height - 0.5 - margin_px)):
            count += 1
    return count


def rig_centre(poses: Sequence[FloatArray], forwards: Sequence[FloatArray]) -> FloatArray:
    """The point nearest to every camera's optical axis (least squares): what the orbit looks at."""
    system, right = np.zeros((3, 3)), np.zeros(3)
    for centre, forward in zip(poses, forwards, strict=True):
        across = np.eye(3) - np.outer(forward, forward)
        system += across
        right += across @ centre
    point: FloatArray = np.asarray(np.linalg.solve(system, right), dtype=np.float64)
    return point


def check_voxel_mm(voxel_mm: float) -> None:
    """Refuse a voxel size outside :data:`MIN_VOXEL_MM`-:data:`MAX_VOXEL_MM` (CaptureError), saying which way it
    is out: too fine resolves less than a pixel and only takes memory, too coarse loses the phantom's shape."""
    if MIN_VOXEL_MM <= voxel_mm <= MAX_VOXEL_MM:
        return
    why = ("a grid finer than that resolves less than a pixel and only takes memory" if voxel_mm < MIN_VOXEL_MM else
           "a coarser grid loses the phantom's shape" if voxel_mm > MAX_VOXEL_MM else "not a finite number of mm")
    raise CaptureError(f"the voxel size must be from {MIN_VOXEL_MM:g} to {MAX_VOXEL_MM:g} mm, got {voxel_mm!r} mm: "
                       f"{why} (give --voxel-mm within the range; default {VOXEL_MM:g})")


def reconstruct(folder: CaptureFolder, rig: Rig | None = None, voxel_mm: float = VOXEL_MM,
                frames: Sequence[Frame] | None = None, progress: Callable[[str], None] | None = None,
                keyed: Mapping[str, Silhouette] | None = None, check_lined_up: bool = True) -> Reconstruction:
    """The carved surface of a capture folder's pictures (all, or ``frames``), posed by ``rig`` (default: the rig
    kept in the folder). ``keyed``: silhouettes found already, by picture (``Frame.image``), each of the very
    picture in the folder (``phantom.scan.keying``: keyed as the capture wrote them); the others are read and
    keyed here. CaptureError for a folder without pictures or a rig, or pictures of another size than the rig's
    camera; SilhouetteError for a picture without a silhouette; CarveError if nothing is left, or if the pictures
    do not line up (:func:`out_of_line`; not checked with ``check_lined_up`` False: silhouettes rendered from one
    surface at the capture's poses line up by construction)."""
    rig = rig if rig is not None else folder.rig()
    if rig is None:
        raise CaptureError(f"{folder.path} keeps no rig calibration (rig.json): give the rig's (--rig RIG.json, "
                           f"from phantom scan calibrate)")
    frames = list(folder.frames if frames is None else frames)
    if len(frames) < 2:
        raise CaptureError(f"{folder.path} has {len(frames)} picture(s): carving needs pictures from several sides")
    check_voxel_mm(voxel_mm)
    pixels = rig.camera.width * rig.camera.height
    needed = pixels * (len(frames) * SILHOUETTE_BYTES_PER_PX + THREADS * KEYING_BYTES_PER_PX)
    budget = memory_budget_bytes()
    if needed > budget:
        raise CaptureError(f"{len(frames)} pictures of {rig.camera.width}x{rig.camera.height} need about "
                           f"{needed / 2**30:.1f} GiB to carve, more than the {budget / 2**30:.1f} GiB this machine "
                           f"has to spare: reconstruct from fewer frames or smaller pictures")
    stage_s: dict[str, float] = {}
    started = time.perf_counter()
    poses = [rig.pose(frame.orbit_deg, frame.elevation_deg) for frame in frames]

    keyed = {} if keyed is None else keyed

    def key(frame: Frame) -> tuple[Frame, object]:
        found, image = keyed.get(frame.image), None
        if found is None:
            image = folder.image(frame)
            height, width = image.shape[:2]
        else:  # keyed as it was written: its size from its header
            width, height = png_size(folder.path / frame.image)
        if (height, width) != (rig.camera.height, rig.camera.width):
            raise CaptureError(f"{frame.image} is {width}x{height}, the rig's camera "
                               f"{rig.camera.width}x{rig.camera.height}: calibrate the rig at this picture size")
        if image is None:
            return frame, found
        try:
            return frame, silhouette(image)
        except SilhouetteError as error:
            raise SilhouetteError(f"{frame.image}: {error}") from None

    with concurrent.futures.ThreadPoolExecutor(THREADS) as pool:
        silhouettes = list(pool.map(key, frames))
    views = [View(pose, found) for pose, (_, found) in zip(poses, silhouettes, strict=True)]  # type: ignore[arg-type]
    stage_s["silhouettes"] = time.perf_counter() - started
    if progress is not None:
        ahead = sum(frame.image in keyed for frame in frames)
        progress(f"{len(views)} silhouettes in {stage_s['silhouettes']:.1f} s"
                 + (f" ({ahead} keyed as they were taken)" if ahead else ""))
    centre = rig_centre([pose.centre_mm for pose in poses], [pose.forward for pose in poses])
    distance = float(np.median([np.linalg.norm(pose.centre_mm - centre) for pose in poses]))
    carver = Carver(rig.camera, views, threads=THREADS)
    started = time.perf_counter()
    grid = carve(carver, centre, START_FRACTION * distance, voxel_mm, progress)
    stage_s["carve"] = time.perf_counter() - started
    started = time.perf_counter()
    agreement = view_agreement(grid, carver, rig.axis_point_mm, rig.axis_direction) if check_lined_up else None
    stage_s["agreement"] = time.perf_counter() - started
    started = time.perf_counter()
    hanging = None
    if sum(view.silhouette.touches_top for view in views) >= HANGING_SHARE * len(views):
        grid, hanging = cut_column(grid, rig)
        if progress is not None and hanging is not None:
            progress(f"the hanging tubes taken off at {hanging.cut_mm:.2f} mm up the axis ({hanging.removed_ml:.3f} "
                     f"ml of column, {hanging.column_area_mm2:.0f} mm^2 across)")
    mesh = surface(grid)
    stage_s["surface"] = time.perf_counter() - started
    touching = views_cutting(mesh, rig.camera, poses)
    # a phantom cut by a picture's edge leaves the other pictures' silhouettes uncovered where it is cut off: it is
    # said as such (touching_edge), not as pictures that moved
    if agreement is not None and touching == 0 and np.max(agreement.uncovered) > MAX_UNCOVERED:
        raise out_of_line(frames, views, carver, agreement, rig, centre, START_FRACTION * distance, voxel_mm)
    return Reconstruction(mesh, enclosed_volume_ml(mesh), voxel_mm, len(views), centre, stage_s, carver.projections,
                          touching, hanging, None if agreement is None else 100.0 * float(np.max(agreement.uncovered)))


def out_of_line(frames: Sequence[Frame], views: Sequence[View], carver: Carver, agreement: ViewAgreement, rig: Rig,
                centre_mm: FloatArray, half_size_mm: float, voxel_mm: float) -> CarveError:
    """The refusal of a capture whose pictures do not line up (``agreement`` of its ``views``, carved by
    ``carver``: some silhouette's uncovered share over :data:`MAX_UNCOVERED`): the picture whose silhouette bounds
    the most of the hull carved without it, named when the others then all line up; else the pictures the hull
    covers least."""
    suspect = int(np.argmax(agreement.bounding))
    others = [view for number, view in enumerate(views) if number != suspect]
    without = carve(Carver(rig.camera, others, threads=THREADS), centre_mm, half_size_mm, voxel_mm)
    # every view against the hull the others carve: the suspect's own share is how far it sticks out
    against = view_agreement(without, carver, rig.axis_point_mm, rig.axis_direction).uncovered
    rest = np.delete(against, suspect)
    if np.max(rest) <= MAX_UNCOVERED:
        frame = frames[suspect]
        return CarveError(f"{frame.image} (frame {frame.index}) is out of line with the other {len(rest)} pictures: "
                          f"{against[suspect]:.1%} of its silhouette lies outside the hull they carve (theirs: at most "
                          f"{np.max(rest):.2%}, a steady capture's under {MAX_UNCOVERED:.1%}); the camera or the "
                          f"turntable moved while it was taken: take the capture again")
    worst = np.argsort(agreement.uncovered)[::-1][:3]
    named = ", ".join(f"{frames[number].image} {agreement.uncovered[number]:.1%}" for number in worst)
    return CarveError(f"the pictures do not line up: the hull carved from all {len(views)} leaves up to "
                      f"{np.max(agreement.uncovered):.1%} of a silhouette uncovered ({named}; a steady capture: under "
                      f"{MAX_UNCOVERED:.1%}), and no one picture left out mends it; the camera or the turntable moved "
                      f"during the capture, or the rig's calibration does not pose these pictures: take the capture "
                      f"again (or calibrate the rig again)")


def check_mesh_path(path: str | Path) -> Path:
    """``path`` as a mesh :func:`write_mesh` can write (by its suffix), checked before any carve; ScanError if not."""
    path = Path(path)
    if path.suffix.lower() not in SCAN_SUFFIXES:
        raise ScanError(f"{path}: write the mesh as .ply, .stl or .obj")
    return path


def write_mesh(mesh: TriangleMesh, path: str | Path) -> Path:
    """Write a surface (mm) as PLY, STL or OBJ (by the suffix)."""
    path = check_mesh_path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        meshio.write_points_cells(path, mesh.vertices_mm, [("triangle", mesh.triangles.astype(np.int32))])
    except (OSError, meshio.WriteError) as error:
        raise ScanError(f"cannot write {path}: {error}") from None
    return path

