"""The virtual camera and the reconstruction against closed forms: a sphere's picture and hull, a dent the hull
cannot see, the capture folder's pictures back to a mesh (phantom.scan.render, silhouette, carve, reconstruct)."""

import math
import time

import numpy as np
import pytest

from phantom.model.mesh.surface import SurfaceIndex, enclosed_volume_ml
from phantom.scan.camera import VIRTUAL_CENTRE_MM, Camera, Pose, virtual_rig
from phantom.scan.capture import CaptureFolder, Plan
from phantom.scan.silhouette import SilhouetteError, alpha_matte, silhouette
from phantom.scan.synthetic import sphere

pytest.importorskip("cv2")
pytest.importorskip("skimage")

from phantom.scan.reconstruct import reconstruct  # noqa: E402
from phantom.scan.render import Renderer, to_8bit  # noqa: E402
from phantom.scan.virtual import render_capture  # noqa: E402


def test_a_spheres_picture_is_the_closed_form_disc():
    # a sphere of radius r at distance d on the optical axis of a lens without distortion projects to a disc of
    # radius f r / sqrt(d^2 - r^2)
    camera = Camera(400, 300, 500.0, 500.0, 199.5, 149.5)
    distance, radius = 150.0, 12.0
    pose = Pose(np.eye(3), np.array([0.0, 0.0, distance]))
    image = to_8bit(Renderer(camera).render_mesh(sphere(radius, np.zeros(3), levels=6), pose), None)
    area = float(alpha_matte(image).sum())
    expected = math.pi * (500.0 * radius / math.sqrt(distance ** 2 - radius ** 2)) ** 2
    assert area == pytest.approx(expected, rel=0.004)


def test_the_rasteriser_depth_is_the_ray_sphere_intersection():
    camera = Camera(200, 150, 300.0, 300.0, 99.5, 74.5, (-0.1, 0.05, 0.0, 0.0, 0.0))
    renderer = Renderer(camera, supersample=1)
    distance, radius = 100.0, 10.0
    depth, face, _ = renderer.mesh_samples(sphere(radius, np.array([0, 0, distance]), levels=6),
                                           Pose(np.eye(3), np.zeros(3)))
    hit = face >= 0
    rays = renderer.rays[hit].astype(float)
    directions = np.column_stack([rays, np.ones(len(rays))])
    # |t d - c|^2 = r^2, nearest root; the mesh's facets sit inside the sphere by at most its sagitta
    a = np.sum(directions ** 2, axis=1)
    b = -2 * directions[:, 2] * distance
    c = distance ** 2 - radius ** 2
    inside = b * b - 4 * a * c > 0
    t = (-b[inside] - np.sqrt(b[inside] ** 2 - 4 * a[inside] * c)) / (2 * a[inside])
    assert np.median(np.abs(depth[hit][inside] - t)) < 0.01
    assert np.count_nonzero(inside) > 0.97 * np.count_nonzero(hit)


def test_silhouette_refuses_pictures_without_a_phantom():
    backdrop = np.zeros((120, 160, 3), np.uint8)
    backdrop[:] = (40, 150, 60)
    with pytest.raises(SilhouetteError, match="is the phantom in view"):
        silhouette(backdrop)
    with pytest.raises(SilhouetteError, match="black"):
        silhouette(np.zeros((120, 160, 3), np.uint8))
    with pytest.raises(SilhouetteError, match="8-bit colour"):
        silhouette(np.zeros((120, 160), np.uint8))


@pytest.mark.slow  # seconds of numerics: make test, not make check
def test_sphere_from_a_rendered_capture(tmp_path):
    truth = sphere(15.0, VIRTUAL_CENTRE_MM, levels=5)
    folder = render_capture(truth, virtual_rig(0.5), Plan(12), tmp_path / "capture")
    again = CaptureFolder.open(folder.path)
    assert again.status == "complete" and len(again.frames) == 24
    result = reconstruct(again, voxel_mm=0.4)
    assert result.volume_ml == pytest.approx(enclosed_volume_ml(truth), rel=0.01)
    distance, _, _ = SurfaceIndex(truth.vertices_mm, truth.triangles).closest(result.mesh.vertices_mm)
    assert distance.mean() < 0.1
    # closed: every edge between exactly two triangles
    edges = np.sort(result.mesh.triangles[:, [[0, 1], [1, 2], [2, 0]]].reshape(-1, 2), axis=1)
    _, counts = np.unique(edges, axis=0, return_counts=True)
    assert np.all(counts == 2)


@pytest.mark.slow
def test_the_hull_fills_a_dent_no_camera_grazes(tmp_path):
    dented = sphere(15.0, VIRTUAL_CENTRE_MM, levels=5, dent_mm=6.0)
    plain = sphere(15.0, VIRTUAL_CENTRE_MM, levels=5)
    folder = render_capture(dented, virtual_rig(0.5), Plan(12), tmp_path / "capture")
    result = reconstruct(folder, voxel_mm=0.4)
    dent_ml = enclosed_volume_ml(plain) - enclosed_volume_ml(dented)
    # the bowl's bottom, which curves inwards every way, stays filled; its flanks are seen and carved
    assert result.volume_ml - enclosed_volume_ml(dented) > 0.4 * dent_ml
    bottom = VIRTUAL_CENTRE_MM + np.array([0.0, 9.0, 0.0])
    index = SurfaceIndex(result.mesh.vertices_mm, result.mesh.triangles)
    assert index.closest(bottom[None])[0][0] > 3.5
    # away from the dent the hull is the sphere
    far = dented.vertices_mm[dented.vertices_mm[:, 1] - VIRTUAL_CENTRE_MM[1] < 5.0]
    assert index.closest(far)[0].mean() < 0.1


def test_a_zero_level_through_grid_points_gives_a_closed_surface_without_repeated_vertices():
    """A field that is exactly 0 at grid points (here a box's faces on grid planes) makes marching cubes put
    several vertices on one point; the surface merges them: no zero-length edge (it broke closest-point
    queries in bench/scan_accuracy.py), every edge between two triangles, the box's volume."""
    from phantom.scan.carve import Grid, surface

    spacing = 0.5
    points = np.indices((21, 21, 21)).transpose(1, 2, 3, 0) * spacing - 5.0
    values = (np.abs(points).max(axis=3) - 3.0).astype(np.float32)  # 0 exactly on the faces of a 6 mm cube
    assert np.count_nonzero(values == 0.0) > 0
    mesh = surface(Grid(np.array([-5.0, -5.0, -5.0]), spacing, values))
    assert len(np.unique(mesh.vertices_mm, axis=0)) == len(mesh.vertices_mm)
    edges = np.sort(mesh.triangles[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    _, counts = np.unique(edges, axis=0, return_counts=True)
    assert np.all(counts == 2)
    assert enclosed_volume_ml(mesh) == pytest.approx(0.216, rel=1e-6)
    distance, _, _ = SurfaceIndex(mesh.vertices_mm, mesh.triangles).closest(np.array([[0.0, 0.0, 9.0]]))
    assert distance[0] == pytest.approx(6.0)


@pytest.fixture(scope="module")
def sphere_capture(tmp_path_factory):
    truth = sphere(15.0, VIRTUAL_CENTRE_MM, levels=4)
    return render_capture(truth, virtual_rig(0.25), Plan(6), tmp_path_factory.mktemp("sphere") / "capture")


@pytest.mark.parametrize("voxel_mm", [0.02, 0.0, float("nan"), float("inf"), 50.0])
def test_a_voxel_outside_the_carving_range_is_refused_before_anything_is_read(sphere_capture, voxel_mm):
    """--voxel-mm 0.02 took over 5 GB before it was stopped."""
    from phantom.scan.capture import CaptureError

    with pytest.raises(CaptureError, match=r"the voxel size must be from 0.05 to 5 mm, got"):
        reconstruct(sphere_capture, voxel_mm=voxel_mm)


def test_carving_refuses_a_grid_over_the_memory_budget_with_its_estimate(sphere_capture):
    from phantom.scan.carve import CarveError, Carver, View, carve

    rig = virtual_rig(0.25)
    views = [View(rig.pose(frame.orbit_deg, frame.elevation_deg), silhouette(sphere_capture.image(frame)))
             for frame in sphere_capture.frames]
    with pytest.raises(CarveError, match=r"at 0.05 mm needs about [0-9.]+ GiB, more than the 0.0 GiB this machine "
                                         r"has to spare: give a coarser voxel \(--voxel-mm\)"):
        carve(Carver(rig.camera, views), VIRTUAL_CENTRE_MM, 70.0, 0.05, max_bytes=2**20)


def test_reconstruct_refuses_more_pictures_than_memory_allows_with_its_estimate(sphere_capture, monkeypatch):
    from phantom.scan import reconstruct as module
    from phantom.scan.capture import CaptureError

    monkeypatch.setattr(module, "memory_budget_bytes", lambda: 2**20)
    with pytest.raises(CaptureError, match=r"12 pictures of 320x240 need about 0.0 GiB to carve, more than the 0.0 "
                                           r"GiB this machine has to spare"):
        reconstruct(sphere_capture, voxel_mm=0.4)


def test_a_camera_whose_projection_is_nan_is_refused_and_the_kernel_reads_nothing_out_of_bounds(sphere_capture):
    """fx = NaN (now refused when a rig file is read) passed the kernel's bounds check and indexed out of bounds:
    SIGSEGV. The carver refuses such a camera; the kernel treats a NaN projection as outside the picture."""
    from phantom.scan import kernels
    from phantom.scan.carve import CarveError, Carver, View

    rig = virtual_rig(0.25)
    camera = Camera(rig.camera.width, rig.camera.height, float("nan"), rig.camera.fy, rig.camera.cx, rig.camera.cy,
                    rig.camera.distortion)
    views = [View(rig.pose(frame.orbit_deg, frame.elevation_deg), silhouette(sphere_capture.image(frame)))
             for frame in sphere_capture.frames[:2]]
    with pytest.raises(CarveError, match="are not finite with positive focal lengths: calibrate the rig again"):
        Carver(camera, views)
    good = Carver(rig.camera, views)
    points = np.array([VIRTUAL_CENTRE_MM, VIRTUAL_CENTRE_MM + 1.0])
    out = np.empty(2, np.float32)
    kernels.hull_distance(points, good.rotations, good.translations, float("nan"), camera.fy, camera.cx, camera.cy,
                          np.array(camera.distortion), good.max_radius2, good.distances, good.offsets, good.crops,
                          good.truncation_px, 10.0, out)
    assert out.shape == (2,)  # reached: no read outside the silhouettes


def test_reconstruct_refuses_a_capture_that_did_not_complete_unless_told_partial(sphere_capture, tmp_path, capsys):
    """An aborted capture with 5 of its plan's 16 pictures carved +3.5 % (3 of them +16.6 %) without a word: part
    of the views carve a hull too large. It is refused, saying how many of the plan's pictures it holds, unless
    --partial asks for it, which then says what it carved. A mesh suffix it cannot write is refused before the
    carve, not after."""
    import json
    import shutil

    from phantom.cli.main import main

    folder = tmp_path / "aborted"
    shutil.copytree(sphere_capture.path, folder)
    record = json.loads((folder / "capture.json").read_text())
    record["status"], record["reason"] = "aborted", "the orbit stalled"
    record["frames"] = record["frames"][:4]
    (folder / "capture.json").write_text(json.dumps(record))
    assert main(["scan", "reconstruct", str(folder), "--out", str(tmp_path / "a.ply")]) == 2
    said = capsys.readouterr().err
    assert "was aborted (the orbit stalled) with 4 of its plan's 12 pictures" in said and "--partial" in said, said
    assert not (tmp_path / "a.ply").exists()
    assert main(["scan", "reconstruct", str(folder), "--out", str(tmp_path / "a.ply"), "--partial"]) == 0
    assert "carved from 4 of the plan's 12 pictures (the capture was aborted)" in capsys.readouterr().out
    started = time.monotonic()
    assert main(["scan", "reconstruct", str(sphere_capture.path), "--out", str(tmp_path / "a.xyz")]) == 2
    assert "write the mesh as .ply, .stl or .obj" in capsys.readouterr().err and time.monotonic() - started < 1.0
