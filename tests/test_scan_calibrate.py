"""Rig calibration (phantom.scan.calibrate): the virtual rig calibrated from rendered pictures of the ChArUco
target recovers its true lens and orbit; the exports give each picture that pose in the tools' conventions."""

import json
import math

import numpy as np
import pytest

from phantom.scan.calibrate import CalibrationError, TargetView, calibrate_rig, fit_orbit, target_views
from phantom.scan.camera import axis_rotation, virtual_rig

cv2 = pytest.importorskip("cv2")

from phantom.cli.scan import rig_against_truth  # noqa: E402
from phantom.scan.export import export_colmap, export_meshroom, quaternion  # noqa: E402
from phantom.scan.virtual import render_target_captures  # noqa: E402


@pytest.fixture(scope="module")
def calibrated(tmp_path_factory):
    truth = virtual_rig(0.5)
    folders = render_target_captures(truth, tmp_path_factory.mktemp("target"), views=9)
    views = target_views(folders)
    return truth, calibrate_rig(views, truth.camera.width, truth.camera.height), folders, views


@pytest.mark.slow
def test_the_virtual_rig_calibrates_to_its_truth(calibrated):
    truth, rig, _, views = calibrated
    assert rig.calibration["pictures_used"] == len(views) == 36
    assert rig.calibration["rms_px"] < 0.25
    error = rig_against_truth(rig, truth)
    assert abs(error["fx_pct"]) < 0.1 and abs(error["fy_pct"]) < 0.1
    assert abs(error["cx_px"]) < 1.0 and abs(error["cy_px"]) < 1.0
    assert abs(error["k1"]) < 0.005
    assert error["axis_angle_deg"] < 0.05
    assert error["axis_offset_mm"] < 0.3
    assert abs(error["radius_0_mm"]) < 0.2 and abs(error["radius_30_mm"]) < 0.2
    # the calibrated rig's own frame: z along the axis, the first elevation's camera at orbit 0 on +x
    centre = rig.pose(0.0, 0.0).centre_mm
    assert abs(centre[1]) < 1e-9 and abs(centre[2]) < 1e-9 and centre[0] > 0


@pytest.mark.slow
def test_colmap_export_projects_as_the_rig(calibrated, tmp_path):
    _, rig, folders, _ = calibrated
    folder = folders[0]
    export_colmap(folder, tmp_path / "colmap", rig)
    camera_line = (tmp_path / "colmap" / "cameras.txt").read_text().splitlines()[-1].split()
    assert camera_line[1] == "OPENCV" and camera_line[2:4] == [str(rig.camera.width), str(rig.camera.height)]
    fx, fy, cx, cy, k1, k2, p1, p2 = map(float, camera_line[4:])
    image_lines = [line for line in (tmp_path / "colmap" / "images.txt").read_text().splitlines()
                   if line and not line.startswith("#")]
    assert len(image_lines) == len(folder.frames)
    point = np.array([3.0, -2.0, 5.0])
    for line, frame in zip(image_lines, folder.frames, strict=True):
        fields = line.split()
        qw, qx, qy, qz, tx, ty, tz = map(float, fields[1:8])
        assert fields[9] == frame.image.split("/")[-1]
        # COLMAP's OPENCV model, written out here from its documentation, with its pixel centres at +0.5
        rotation = np.array([[1 - 2 * (qy * qy + qz * qz), 2 * (qx * qy - qz * qw), 2 * (qx * qz + qy * qw)],
                             [2 * (qx * qy + qz * qw), 1 - 2 * (qx * qx + qz * qz), 2 * (qy * qz - qx * qw)],
                             [2 * (qx * qz - qy * qw), 2 * (qy * qz + qx * qw), 1 - 2 * (qx * qx + qy * qy)]])
        x, y, z = rotation @ point + [tx, ty, tz]
        u, v = x / z, y / z
        r2 = u * u + v * v
        radial = 1 + k1 * r2 + k2 * r2 * r2
        du = u * radial + 2 * p1 * u * v + p2 * (r2 + 2 * u * u)
        dv = v * radial + 2 * p2 * u * v + p1 * (r2 + 2 * v * v)
        colmap_pixel = np.array([fx * du + cx, fy * dv + cy])
        ours = rig.camera.project(rig.pose(frame.orbit_deg, frame.elevation_deg).apply(point[None]))[0]
        assert np.allclose(colmap_pixel - 0.5, ours, atol=1e-6)
    sfm = json.loads(export_meshroom(folder, tmp_path / "cameras.sfm", rig).read_text())
    pose = rig.pose(folder.frames[3].orbit_deg, folder.frames[3].elevation_deg)
    stored = np.array(sfm["poses"][3]["pose"]["transform"]["rotation"], float).reshape(3, 3, order="F")
    assert np.allclose(stored, pose.rotation)
    assert np.allclose(np.array(sfm["poses"][3]["pose"]["transform"]["center"], float), pose.centre_mm)
    assert len(sfm["views"]) == len(folder.frames) and sfm["intrinsics"][0]["locked"] == "true"


def test_quaternion_against_the_rotation_it_came_from():
    rng = np.random.default_rng(1)
    for _ in range(50):
        axis = rng.normal(size=3)
        rotation = axis_rotation(axis, rng.uniform(-180, 180))
        w, x, y, z = quaternion(rotation)
        angle = 2 * math.degrees(math.acos(min(1.0, w)))
        assert np.allclose(axis_rotation(np.array([x, y, z]) if angle > 1e-6 else np.array([0, 0, 1.0]), angle),
                           rotation, atol=1e-9)


def test_orbit_fit_finds_a_known_circle():
    direction = np.array([0.1, -0.2, 1.0]) / np.linalg.norm([0.1, -0.2, 1.0])
    point, start = np.array([5.0, -3.0, 40.0]), np.cross(direction, [1.0, 0, 0])
    start = 180.0 * start / np.linalg.norm(start)
    angles = np.array([-40.0, -20.0, 0.0, 15.0, 45.0])
    centres = np.array([point + axis_rotation(direction, a) @ start for a in angles])
    fitted_point, fitted_direction, radius = fit_orbit(centres, angles)
    assert np.allclose(fitted_direction, direction) and radius == pytest.approx(180.0)
    offset = fitted_point - point
    assert np.linalg.norm(offset - (offset @ direction) * direction) < 1e-9


def test_calibration_refuses_too_few_views():
    empty = [TargetView(0, 0.0, 0.0, np.zeros((0, 3)), np.zeros((0, 2)), f"{k}.png") for k in range(8)]
    with pytest.raises(CalibrationError, match="found in 0 of 8 pictures"):
        calibrate_rig(empty, 640, 480)
