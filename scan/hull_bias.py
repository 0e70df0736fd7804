"""The visual hull's own error on a scan, measured on the model's shape, and the scanned volume without it.

A visual hull holds the phantom and touches it only where some line of sight grazes it: it reads high where the
surface folds away from every view and a little low where the silhouettes' edges trim it. Both depend on the
shape and the cameras' poses, not on the phantom's exact size, so a shape close to the phantom's measures them:
the model's outer surface at the scan's pressures, its silhouettes rasterised at each picture's pose through the
scan's camera (coverage, no picture and no key), carved as the scan was (the same frames, grid and hanging
column). Its carved volume over its enclosed volume is the hull's ratio; the scanned volume over that ratio is
the phantom's, the hull's error taken off (:func:`hull_bias`).

The model's surface is in the model's frame. A scan posed by the virtual rig's own geometry is in it too; one
posed by a calibrated rig is in the rig's frame, so the model's surface is first placed on the scanned one by a
rigid alignment (``phantom.model.mesh.surface.align``), the tubes it hangs by (when the scan cut a hanging
column) drawn from its base before it is moved.

What it leaves (``bench/scan_hull_bias.py``, the verify plan of 20 stops at 15 and 45 deg, 640x480, six states
from rest to 44 ml): on the shipped simulated phantom the scanned error went from -0.01..+0.17 % to within
0.054 % (hung by its tubes: 0.135 to 0.080 %); on another phantom (``--sim-truth``'s lobes 1.1, E x 0.9, whose
shape the model does not share) from +0.04..+0.24 % to within 0.027 % (tubes: 0.219 to 0.083 %). What it cannot
see: a real camera's keying errors (a picture's own, not the hull's), and a phantom whose shape differs from the
model's more than these do.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from phantom import PhantomError
from phantom.model.mesh.surface import AlignmentError, TriangleMesh, enclosed_volume_ml
from phantom.scan.camera import Pose, Rig
from phantom.scan.capture import CaptureFolder, Frame
from phantom.scan.reconstruct import Reconstruction, reconstruct
from phantom.scan.render import Renderer, hung_scene
from phantom.scan.silhouette import Silhouette, silhouette_of_alpha


@dataclass(frozen=True)
class HullBias:
    """The model's surface carved as a scan was (ml), its own enclosed volume (ml), whether it was placed on the
    scan by alignment (a calibrated rig's frame), the seconds it took, and of how many pictures the model's
    silhouette had been rendered while the capture ran (:class:`ModelSilhouettes`; the others rendered here)."""

    carved_ml: float
    enclosed_ml: float
    aligned: bool
    seconds: float
    rendered_while_taken: int = 0

    @property
    def ratio(self) -> float:
        """The hull's volume over the shape's: above 1 where the hull reads high."""
        return self.carved_ml / self.enclosed_ml

    @property
    def error_pct(self) -> float:
        """The hull's error on the model's shape (%)."""
        return 100.0 * (self.ratio - 1.0)

    def corrected_ml(self, scanned_ml: float) -> float:
        """A scanned volume (ml) with the hull's error taken off."""
        return scanned_ml / self.ratio


def coverage_silhouette(renderer: Renderer, mesh: TriangleMesh, pose: Pose) -> Silhouette:
    """The silhouette of a surface (mm, world) seen from ``pose``: each pixel's share of samples that hit it."""
    _, face, _ = renderer.mesh_samples(mesh, pose)
    s = renderer.supersample
    camera = renderer.camera
    # each pixel's hits counted in two passes of small integers: a third of the time of one float mean over both
    # axes (15 ms a 640x480 picture of 3x3 samples, 40 of them in each verify scan's hull)
    hits = (face >= 0).view(np.uint8).reshape(camera.height, s, camera.width * s).sum(axis=1, dtype=np.uint16)
    alpha = hits.reshape(camera.height, camera.width, s).sum(axis=2, dtype=np.uint16) / np.float32(s * s)
    return silhouette_of_alpha(alpha)


def placed_on_scan(surface: TriangleMesh, scanned: TriangleMesh, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """The rigid motion (rotation (3, 3), translation (3,) mm) that takes the model's ``surface`` onto the scanned
    one: the scan aligned onto the model (``align``), inverted. AlignmentError when no motion fits them."""
    from phantom.model.mesh.surface import Frame, SurfaceIndex, align

    alignment = align(Frame.of(scanned), scanned.vertices_mm, surface, Frame.of(surface),
                      SurfaceIndex(surface.vertices_mm, surface.triangles), np.random.default_rng(seed))
    # x_model = R x_scan + t, so x_scan = R^T (x_model - t)
    rotation = alignment.rotation.T
    return rotation, -rotation @ alignment.translation_mm


def check_fit(surface: TriangleMesh, scanned: TriangleMesh) -> None:
    """AlignmentError when the scanned hull does not lie on the model's surface where it is (its vertices' RMS
    distance from it above ``FIT_RMS_LIMIT`` of the surface's size, as an alignment that fits nothing)."""
    from phantom.model.mesh.surface import FIT_RMS_LIMIT, Frame, SurfaceIndex

    distance_mm, _, _ = SurfaceIndex(surface.vertices_mm, surface.triangles).closest(scanned.vertices_mm)
    rms_mm, size_mm = float(np.sqrt(np.mean(distance_mm ** 2))), Frame.of(surface).rms_radius_mm
    if rms_mm > FIT_RMS_LIMIT * size_mm:
        raise AlignmentError(rms_mm, size_mm)


def hull_bias(capture: CaptureFolder, rig: Rig, scanned: Reconstruction, surface: TriangleMesh,
              in_model_frame: bool, rendered: Mapping[str, Rendered] | None = None) -> HullBias:
    """The hull's error on the model's ``surface`` (mm, the model's frame) at the scan's pressures, for the scan
    ``scanned`` of ``capture`` posed by ``rig``: its frames carved at the scan's voxel, from silhouettes of the
    surface (and of the tubes it hangs by, when the scan cut a hanging column). ``in_model_frame``: the rig's frame
    is the model's (the virtual rig's own geometry: the scan must lie on the surface, :func:`check_fit`); else the
    surface is placed on the scan first (:func:`placed_on_scan`). ``rendered``: the surface's silhouettes rendered
    while the capture ran (:class:`ModelSilhouettes`), by picture, each used where it was rendered at the very pose
    and the scene is the surface itself. AlignmentError when it fits no motion onto it."""
    started = time.perf_counter()
    scene = hung_scene(surface)[0] if scanned.hanging is not None else surface
    aligned = not in_model_frame
    if aligned:
        rotation, translation = placed_on_scan(surface, scanned.mesh)
        scene = TriangleMesh(scene.vertices_mm @ rotation.T + translation, scene.triangles)
    else:
        check_fit(surface, scanned.mesh)
    rendered = rendered if rendered is not None and scene is surface else {}
    renderer = Renderer(rig.camera)
    keyed, taken = {}, 0
    for frame in capture.frames:
        pose = rig.pose(frame.orbit_deg, frame.elevation_deg)
        kept = rendered.get(frame.image)
        if kept is not None and kept.at(pose):
            keyed[frame.image], taken = kept.silhouette, taken + 1
        else:
            keyed[frame.image] = coverage_silhouette(renderer, scene, pose)
    carved = reconstruct(capture, rig, scanned.voxel_mm, keyed=keyed, check_lined_up=False)
    return HullBias(carved.volume_ml, enclosed_volume_ml(surface), aligned, time.perf_counter() - started, taken)


@dataclass(frozen=True)
class Rendered:
    """The model's silhouette in one picture of a capture, and the pose it was rendered at."""

    pose: Pose
    silhouette: Silhouette

    def at(self, pose: Pose) -> bool:
        """Whether it was rendered at ``pose``, exactly."""
        return bool(np.array_equal(self.pose.rotation, pose.rotation)
                    and np.array_equal(self.pose.translation_mm, pose.translation_mm))


class ModelSilhouettes:
    """The model's silhouettes at a verify capture's stops, rendered in the capture's pictures thread as each
    picture is written, while the rig moves to the next stop, for the hull's error measured after the capture
    (:func:`hull_bias`): the verify plan's 40 renders of 640x480 were 1.4 s of the 3.3 s the hull's error took
    after each verify scan. Kept in this process (the daemon's scan worker, where its verify captures and their
    reconstructions run), as the pictures' own silhouettes are (``phantom.scan.keying``): the surface the next
    capture is measured on (:meth:`expect`), one capture's silhouettes at a time (:meth:`start`), handed out
    once (:meth:`take`) and only for that very surface, which goes with them (a later capture renders only a
    surface expected for it); a capture that stopped drops its silhouettes (:meth:`drop`) and keeps the surface
    for the round's capture taken again; :func:`hull_bias` uses each only at the pose it was rendered at. Only a
    capture posed in the model's frame (the virtual rig's own geometry) renders them: a calibrated rig's needs the
    scan to place the surface first."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._surface: TriangleMesh | None = None
        self._folder: Path | None = None
        self._rendered: dict[str, Rendered] = {}

    def expect(self, surface_mm: tuple[Any, Any] | None) -> None:
        """The model's outer surface (positions mm, triangles; the model's frame) at the next capture's pressures;
        None: none (the capture renders nothing)."""
        surface = None if surface_mm is None else _mesh(surface_mm)
        with self._lock:
            self._surface, self._folder, self._rendered = surface, None, {}

    def start(self, folder: CaptureFolder, rig: Rig) -> Callable[[Frame], None] | None:
        """Render the expected surface's silhouette at each of ``folder``'s pictures, posed by ``rig``, from now on
        (another capture's are dropped): the call to make with each frame once its picture is written; None when
        no surface is expected."""
        path = folder.path.resolve()
        with self._lock:
            surface = self._surface
            self._folder, self._rendered = path, {}
        if surface is None:
            return None
        renderer = Renderer(rig.camera)

        def render(frame: Frame) -> None:
            pose = rig.pose(frame.orbit_deg, frame.elevation_deg)
            try:
                found = coverage_silhouette(renderer, surface, pose)
            except PhantomError:
                return  # the hull's error renders it again, and says what is wrong
            with self._lock:
                if self._folder == path:
                    self._rendered[frame.image] = Rendered(pose, found)

        return render

    def take(self, folder: CaptureFolder, surface_mm: tuple[Any, Any]) -> dict[str, Rendered]:
        """The silhouettes rendered of ``folder``'s pictures, by picture (``Frame.image``), if they are of the
        surface ``surface_mm`` ({} otherwise); forgotten here, with the surface."""
        with self._lock:
            if self._folder != folder.path.resolve() or self._surface is None:
                return {}
            rendered, surface = self._rendered, self._surface
            self._surface, self._folder, self._rendered = None, None, {}
        given = _mesh(surface_mm)
        same = (np.array_equal(given.vertices_mm, surface.vertices_mm)
                and np.array_equal(given.triangles, surface.triangles))
        return rendered if same else {}

    def drop(self, folder: CaptureFolder) -> None:
        """Forget ``folder``'s silhouettes (its capture stopped or aborted); the surface stays expected: the
        daemon takes a round's capture again, at the same pressures, when the board's reply came late."""
        with self._lock:
            if self._folder == folder.path.resolve():
                self._folder, self._rendered = None, {}


def _mesh(surface_mm: tuple[Any, Any]) -> TriangleMesh:
    positions_mm, triangles = surface_mm
    return TriangleMesh(np.asarray(positions_mm, dtype=float), np.asarray(triangles, dtype=np.int64))


#: This process's: the daemon's scan worker renders its verify captures' model silhouettes here.
MODEL_SILHOUETTES = ModelSilhouettes()


def measured_hull_bias(capture: CaptureFolder, rig: Rig, scanned: Reconstruction,
                       model_surface_mm: tuple[Any, Any], rendered: Mapping[str, Rendered] | None = None
                       ) -> HullBias | str:
    """:func:`hull_bias` for a scan of ``capture`` and the model's surface at its pressures (positions mm,
    triangles; the model's frame), in the model's frame when the capture keeps no rig of its own (the virtual
    rig's geometry); or why there is none, to be said beside the scan's own volume: the surface does not lie on
    the scan, where it is or after any rigid motion (not this phantom, or not at these pressures). ``rendered``:
    the surface's silhouettes rendered while the capture ran (:class:`ModelSilhouettes`)."""
    from phantom.scan.carve import CarveError
    from phantom.scan.silhouette import SilhouetteError

    try:
        return hull_bias(capture, rig, scanned, _mesh(model_surface_mm), not capture.rig_file, rendered)
    except (AlignmentError, SilhouetteError, CarveError) as error:
        return f"the hull's error not taken off: the model's surface does not fit the scan ({error})"
