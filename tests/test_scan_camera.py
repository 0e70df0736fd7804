"""The scanner's camera model and rig against OpenCV's projection and closed forms (phantom.scan.camera)."""

import json
import math

import numpy as np
import pytest

from phantom.scan.camera import VIRTUAL_CAMERA, Camera, Pose, Rig, RigError, axis_rotation, virtual_rig

cv2 = pytest.importorskip("cv2")


def test_projection_matches_opencv():
    rng = np.random.default_rng(0)
    points = rng.uniform([-40, -30, 150], [40, 30, 260], (200, 3))
    camera = VIRTUAL_CAMERA
    ours = camera.project(points)
    theirs, _ = cv2.projectPoints(points, np.zeros(3), np.zeros(3), camera.matrix, np.array(camera.distortion))
    assert np.max(np.abs(ours - theirs.reshape(-1, 2))) < 1e-9


def test_undistort_inverts_distort_over_the_picture():
    camera = VIRTUAL_CAMERA
    pixels = np.stack(np.meshgrid(np.linspace(0, camera.width - 1, 17), np.linspace(0, camera.height - 1, 13)),
                      axis=-1).reshape(-1, 2)
    rays = camera.normalized_rays(pixels)
    back = camera.project(np.column_stack([rays, np.ones(len(rays))]))
    assert np.max(np.abs(back - pixels)) < 1e-8
    theirs = cv2.undistortPoints(pixels.reshape(-1, 1, 2), camera.matrix, np.array(camera.distortion),
                                 criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-14))
    assert np.max(np.abs(theirs.reshape(-1, 2) - rays)) < 1e-6


def test_scaled_camera_keeps_the_lens():
    half = VIRTUAL_CAMERA.scaled(0.5)
    assert (half.width, half.height) == (640, 480)
    point = np.array([[10.0, -7.0, 200.0]])
    # a pixel of the half-size sensor covers two of the full one: same place on the sensor
    full, small = VIRTUAL_CAMERA.project(point)[0], half.project(point)[0]
    assert np.allclose((small + 0.5) * 2 - 0.5, full, atol=1e-9)


def test_look_at_points_the_camera_at_the_target():
    pose = Pose.look_at(np.array([200.0, 0, 50]), np.array([0.0, 0, 0]), np.array([0.0, 0, 1]))
    assert np.allclose(pose.apply(np.zeros((1, 3)))[0][:2], 0.0, atol=1e-12)
    assert np.allclose(pose.rotation @ pose.rotation.T, np.eye(3))
    # the world's up is up in the picture (image y grows downwards)
    above = pose.apply(np.array([[0.0, 0.0, 10.0]]))[0]
    assert above[1] < 0


def test_the_orbit_turns_the_camera_about_its_axis():
    rig = virtual_rig()
    for elevation in (0.0, 30.0):
        centres = np.array([rig.pose(angle, elevation).centre_mm for angle in np.arange(0, 360, 15)])
        offsets = centres - rig.axis_point_mm
        along = offsets @ rig.axis_direction
        radial = np.linalg.norm(offsets - np.outer(along, rig.axis_direction), axis=1)
        assert np.ptp(along) < 1e-9 and np.ptp(radial) < 1e-9
        assert radial[0] == pytest.approx(rig.radius_mm(elevation))
        assert np.allclose(rig.pose(360.0, elevation).matrix(), rig.pose(0.0, elevation).matrix(), atol=1e-9)
    # a positive angle turns the camera right-handed about the axis direction
    a, b = rig.pose(0.0, 0.0).centre_mm - rig.axis_point_mm, rig.pose(10.0, 0.0).centre_mm - rig.axis_point_mm
    assert np.cross(a, b) @ rig.axis_direction > 0
    turn = axis_rotation(rig.axis_direction, 10.0)
    assert np.allclose(turn @ a, b, atol=1e-9)


def test_rig_file_round_trip_and_errors(tmp_path):
    rig = virtual_rig(0.5)
    path = rig.save(tmp_path / "rig.json")
    again = Rig.load(path)
    assert again.camera == rig.camera
    assert np.allclose(again.pose(33.0, 30.0).matrix(), rig.pose(33.0, 30.0).matrix())
    with pytest.raises(RigError, match="calibrated at elevation"):
        rig.pose(0.0, 45.0)
    with pytest.raises(RigError, match="does not exist"):
        Rig.load(tmp_path / "missing.json")
    (tmp_path / "bad.json").write_text(json.dumps({"format": "phantom-rig/1", "camera": {}}))
    with pytest.raises(RigError, match="damaged"):
        Rig.load(tmp_path / "bad.json")
    (tmp_path / "old.json").write_text(json.dumps({"format": "something else"}))
    with pytest.raises(RigError, match="not a rig file"):
        Rig.load(tmp_path / "old.json")


def test_camera_json_round_trip():
    camera = Camera(320, 240, 300.0, 301.0, 160.2, 119.7, (-0.1, 0.02, 0.001, -0.002, 0.0))
    assert Camera.from_json(json.loads(json.dumps(camera.to_json()))) == camera
    assert math.isclose(camera.matrix[0, 0], 300.0)


def _tampered(tmp_path, change):
    """The virtual rig's file with one field changed by ``change(data)``."""
    data = virtual_rig(0.25).to_json()
    change(data)
    path = tmp_path / "rig.json"
    path.write_text(json.dumps(data))
    return path


def _set(path, value):
    def change(data):
        *parents, last = path
        for key in parents:
            data = data[key]
        data[last] = value
    return change


@pytest.mark.parametrize(("path", "value", "message"), [
    (("camera", "fx"), 0.0, r"focal lengths \(fx, fy\) = \[0.0, .*\] px must be positive"),
    (("camera", "fx"), float("nan"), "the rig's camera fx must be finite, got nan"),
    (("camera", "fy"), -350.0, "must be positive"),
    (("camera", "fx"), True, "the rig's camera fx must be a number, got True"),
    (("camera", "cx"), float("inf"), "the rig's camera cx must be finite"),
    (("camera", "width"), 0, "width must be a whole number of pixels from 16 to 8192, got 0"),
    (("camera", "height"), 120.5, "height must be a whole number of pixels"),
    (("camera", "distortion_k1_k2_p1_p2_k3"), [0.1, 0.0], r"distortion_k1_k2_p1_p2_k3 must be numbers of shape \(5,\)"),
    (("camera", "distortion_k1_k2_p1_p2_k3"), [[], 0.1, 0.0, 0.0, 0.0], "distortion_k1_k2_p1_p2_k3 must be numbers"),
    (("axis", "direction"), [0.0, 0.0, 0.0], "the rig's axis direction .* has no length"),
    (("axis", "direction"), [float("nan"), 0.0, 1.0], "the rig's axis direction must be finite"),
    (("axis", "point_mm"), ["0", 0, 0], r"the rig's axis point_mm must be numbers of shape \(3,\)"),
    (("elevations", 0, "translation_mm"), [float("nan"), 0.0, 200.0], "a pass's translation_mm must be finite"),
    (("elevations", 0, "rotation"), [[1.0, 0.0], [0.0, 1.0]], r"a pass's rotation must be numbers of shape \(3, 3\)"),
    (("elevations", 0, "rotation"), [[2.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0]], "is not a rotation"),
    (("elevations", 0, "rotation"), [[-1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0]], "is not a rotation"),
    (("elevations", 0, "elevation_deg"), float("inf"), "a pass's elevation_deg must be finite"),
    (("elevations",), [], "elevations must be a non-empty list"),
    (("camera",), [], "the rig's camera must be an object"),
])
def test_a_rig_file_with_an_impossible_value_is_refused_naming_the_field(tmp_path, path, value, message):
    """fx = 0 carved a 24.2 ml sphere into 54.9 ml, exit 0; fx = NaN crashed the carving (SIGSEGV); the rest were
    tracebacks."""
    with pytest.raises(RigError, match=message) as raised:
        Rig.load(_tampered(tmp_path, _set(path, value)))
    assert "\n" not in str(raised.value)


def test_a_rig_file_refusal_is_exit_2_from_reconstruct(tmp_path, capsys):
    from phantom.cli.main import main

    path = _tampered(tmp_path, _set(("camera", "fx"), 0.0))
    (tmp_path / "capture").mkdir()
    frames = [{"index": k, "image": f"images/{k:04d}.png", "orbit_deg": 90.0 * k, "elevation_deg": 0.0}
              for k in range(4)]
    (tmp_path / "capture" / "capture.json").write_text(json.dumps({"format": "phantom-capture/1", "frames": frames}))
    assert main(["scan", "reconstruct", str(tmp_path / "capture"), "--rig", str(path), "--out",
                 str(tmp_path / "out.ply")]) == 2
    assert "fx, fy" in capsys.readouterr().err and not (tmp_path / "out.ply").exists()
