"""The capture loop and folder (phantom.scan.capture): a webcam's path fed with recorded frames through OpenCV's
VideoCapture, the folder another tool reads, and clean aborts (motors released, pictures kept)."""

import json

import numpy as np
import pytest

from phantom import PhantomError
from phantom.model.mesh.surface import enclosed_volume_ml
from phantom.scan.camera import VIRTUAL_CENTRE_MM, virtual_rig
from phantom.scan.capture import STAGES, CameraLost, CaptureError, CaptureFolder, Plan, Webcam, capture
from phantom.scan.synthetic import sphere

cv2 = pytest.importorskip("cv2")
pytest.importorskip("skimage")

from phantom.scan.reconstruct import reconstruct  # noqa: E402
from phantom.scan.render import Renderer, to_8bit  # noqa: E402


class RecordingOrbit:
    """An orbit for one layer's test: it is where it is told and logs what it was told (a real one is
    tested through the daemon and simavr)."""

    def __init__(self, interrupt_at: int | None = None):
        self.moves: list[tuple[float, float]] = []
        self.released = 0
        self.interrupt_at = interrupt_at

    def move_to(self, orbit_deg, elevation_deg):
        if self.interrupt_at is not None and len(self.moves) == self.interrupt_at:
            raise KeyboardInterrupt
        self.moves.append((orbit_deg, elevation_deg))
        return self.position_deg()

    def position_deg(self):
        orbit_deg, elevation_deg = self.moves[-1]
        return orbit_deg + 0.004, elevation_deg  # the board reports the step it stopped on

    def release(self):
        self.released += 1


class Phantom:
    def __init__(self, fault_at: int | None = None):
        self.calls = 0
        self.fault_at = fault_at

    def pressures_kpa(self):
        self.calls += 1
        if self.fault_at is not None and self.calls > self.fault_at:
            raise PhantomError("faults latched: OVERPRESSURE")
        return [1.0, 1.5, 0.5]


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    """A webcam's recording of a sphere on the virtual rig: one picture per stop of a 2 x 10 plan, as an image
    sequence (what VideoCapture reads like a device)."""
    folder = tmp_path_factory.mktemp("recording")
    rig, plan = virtual_rig(0.4), Plan(10, settle_s=0.0)
    renderer, rng = Renderer(rig.camera), np.random.default_rng(3)
    mesh = sphere(15.0, VIRTUAL_CENTRE_MM, levels=5)
    for number, (orbit, elevation) in enumerate(plan.stops()):
        picture = to_8bit(renderer.render_mesh(mesh, rig.pose(orbit, elevation)), rng)
        assert cv2.imwrite(str(folder / f"{number:04d}.png"), picture[:, :, ::-1])
    return folder, rig, plan, mesh


@pytest.mark.slow  # seconds of numerics: make test, not make check
def test_recorded_frames_through_the_webcam_path_make_the_sphere(recording, tmp_path):
    frames, rig, plan, mesh = recording
    camera = Webcam(str(frames / "%04d.png"))
    orbit = RecordingOrbit()
    folder = CaptureFolder.create(tmp_path / "capture", camera.describe(), plan.to_json(), {"test": 1}, rig)
    shown = []
    capture(orbit, camera, Phantom(), plan, folder, lambda done, total, frame: shown.append((done, total)))
    camera.close()
    assert orbit.moves == plan.stops() and shown[-1] == (20, 20)
    data = json.loads((tmp_path / "capture" / "capture.json").read_text())
    assert data["format"] == "phantom-capture/1" and data["status"] == "complete" and data["rig"] == "rig.json"
    first = data["frames"][0]
    assert first["image"] == "images/0000.png" and first["pressures_kpa"] == [1.0, 1.5, 0.5]
    assert first["orbit_deg"] == pytest.approx(-180.0 + 0.004) and "time_utc" in first and first["time_s"] >= 0
    assert (tmp_path / "capture" / "images" / "0019.png").is_file()
    # where each picture's time went, read back: every stage of the loop, none negative
    stages = [frame.stage_s for frame in CaptureFolder.open(tmp_path / "capture").frames]
    assert all(set(stage) == set(STAGES) - {"key"} and min(stage.values()) >= 0 for stage in stages), stages[0]
    result = reconstruct(CaptureFolder.open(tmp_path / "capture"), voxel_mm=0.4)
    assert result.volume_ml == pytest.approx(enclosed_volume_ml(mesh), rel=0.015)


def test_a_lost_camera_aborts_with_the_motors_released_and_the_pictures_kept(recording, tmp_path):
    frames, rig, _, _ = recording
    plan = Plan(15, settle_s=0.0)  # 30 stops, the recording has 20
    orbit = RecordingOrbit()
    folder = CaptureFolder.create(tmp_path / "capture", {"kind": "webcam"}, plan.to_json())
    with pytest.raises(CaptureError, match=r"aborted after 20 of 30 pictures: .*gave no picture.*motors are "
                                           r"released.*kept in"):
        capture(orbit, Webcam(str(frames / "%04d.png")), Phantom(), plan, folder)
    assert orbit.released == 1
    again = CaptureFolder.open(tmp_path / "capture")
    assert again.status == "aborted" and "gave no picture" in again.reason and len(again.frames) == 20


def test_a_fault_aborts_the_capture(recording, tmp_path):
    frames, _, plan, _ = recording
    orbit = RecordingOrbit()
    folder = CaptureFolder.create(tmp_path / "capture", {"kind": "webcam"}, plan.to_json())
    with pytest.raises(CaptureError, match="aborted after 3 of 20 pictures: faults latched: OVERPRESSURE"):
        capture(orbit, Webcam(str(frames / "%04d.png")), Phantom(fault_at=3), plan, folder)
    assert orbit.released == 1 and CaptureFolder.open(folder.path).status == "aborted"


def test_ctrl_c_aborts_the_capture(recording, tmp_path):
    frames, _, plan, _ = recording
    orbit = RecordingOrbit(interrupt_at=2)
    folder = CaptureFolder.create(tmp_path / "capture", {"kind": "webcam"}, plan.to_json())
    with pytest.raises(KeyboardInterrupt):
        capture(orbit, Webcam(str(frames / "%04d.png")), Phantom(), plan, folder)
    again = CaptureFolder.open(folder.path)
    assert orbit.released == 1 and again.status == "aborted" and again.reason.startswith("interrupted")
    assert len(again.frames) == 2


def test_capture_folder_errors(tmp_path):
    CaptureFolder.create(tmp_path / "one", {}, {})
    with pytest.raises(CaptureError, match="already holds a capture"):
        CaptureFolder.create(tmp_path / "one", {}, {})
    with pytest.raises(CaptureError, match="not a capture folder"):
        CaptureFolder.open(tmp_path)
    (tmp_path / "two").mkdir()
    (tmp_path / "two" / "capture.json").write_text("{\"format\": \"phantom-capture/1\", \"frames\": [{}]}")
    with pytest.raises(CaptureError, match="frame 0: image must be a picture's path inside the folder"):
        CaptureFolder.open(tmp_path / "two")
    with pytest.raises(CameraLost, match="cannot open the camera .*nothing.*: is the path right\\?"):
        Webcam(str(tmp_path / "nothing" / "%04d.png"))
    with pytest.raises(CaptureError, match="at least one view"):
        Plan(0).stops()


def _frames(count, **change):
    return [{"index": k, "image": f"images/{k:04d}.png", "orbit_deg": 6.0 * k, "elevation_deg": 0.0,
             "pressures_kpa": [1.0, 1.0, 1.0], "time_s": 0.1 * k, **change} for k in range(count)]


@pytest.mark.parametrize(("frames", "message"), [
    (_frames(2, orbit_deg=float("nan")), "frame 0: orbit_deg must be finite and within"),
    (_frames(2, orbit_deg=float("inf")), "frame 0: orbit_deg must be finite and within"),
    (_frames(2, elevation_deg="30"), "frame 0: elevation_deg must be a number, got '30'"),
    (_frames(2, elevation_deg=1e9), r"frame 0: elevation_deg must be finite and within \+-360"),
    (_frames(2, pressures_kpa=[1.0, None]), "frame 0: pressures_kpa must be"),
    (_frames(2, time_s=float("nan")), "frame 0: time_s must be finite"),
    (_frames(2, index=True), "frame 0: index must be a whole number"),
    (_frames(2, stage_s={"move": "slow"}), "frame 0: stage_s move must be a number"),
    (_frames(2, stage_s={"nap": 1.0}), "frame 0: stage_s must map some of move, settle"),
    (_frames(2, stage_s=[1.0]), "frame 0: stage_s must map some of move, settle"),
    (_frames(2, image="../../etc/passwd"), "frame 0: image must be a picture's path inside the folder"),
    (_frames(2, image="/etc/passwd"), "frame 0: image must be a picture's path inside the folder"),
    (_frames(5000, image="images/0000.png"), "frames must be a list of at most 2000 pictures, got 5000"),
    (_frames(3, image="images/0000.png"), "names the picture images/0000.png for more than one frame"),
    ({"0": {}}, "frames must be a list of at most 2000 pictures"),
    ([3], "frame 0 must be an object, got 3"),
])
def test_a_capture_file_with_an_impossible_frame_is_refused_naming_it(tmp_path, frames, message):
    """orbit_deg NaN or Infinity was a traceback; 5000 frames naming one picture took 1.4 GB and over 120 s."""
    (tmp_path / "capture.json").write_text(json.dumps({"format": "phantom-capture/1", "frames": frames}))
    with pytest.raises(CaptureError, match=message) as raised:
        CaptureFolder.open(tmp_path)
    assert "\n" not in str(raised.value)


@pytest.mark.parametrize(("views", "elevations", "message"), [
    ("100000000", "0", "views must be at most 720"),
    ("600", "0,10,20,30", "is 2400 pictures: give from 1 to 2000 in all"),
    ("0", "0", "views must be at least 1"),
])
def test_render_refuses_more_pictures_than_a_capture_holds_before_rendering(tmp_path, capsys, views, elevations,
                                                                             message):
    """phantom scan render --views 1e8 took over 3.4 GB and was still running."""
    from phantom.cli.main import main

    truth = sphere(15.0, VIRTUAL_CENTRE_MM, levels=2)
    import meshio

    meshio.write_points_cells(tmp_path / "sphere.ply", truth.vertices_mm, [("triangle", truth.triangles)])
    assert main(["scan", "render", str(tmp_path / "sphere.ply"), "--out", str(tmp_path / "capture"), "--views", views,
                 "--elevations", elevations]) == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "capture").exists()


def test_plan_runs_every_other_pass_backwards():
    stops = Plan(4, (0.0, 30.0), start_deg=0.0).stops()
    assert stops == [(0.0, 0.0), (90.0, 0.0), (180.0, 0.0), (270.0, 0.0),
                     (270.0, 30.0), (180.0, 30.0), (90.0, 30.0), (0.0, 30.0)]
    assert Plan(3, (0.0,), start_deg=-50.0, span_deg=100.0).stops() == [(-50.0, 0.0), (0.0, 0.0), (50.0, 0.0)]



def test_a_plans_moves_take_the_axes_trapezoid_and_the_turn_back_after_an_odd_number_of_passes():
    """The board's time of a verify plan's moves (the plan's sizing, phantom/cli/scan_verify.py): a 12 deg stop
    ramps up and down at 240 deg/s^2 and cruises at 30 deg/s (0.125 + 0.4 s), a 2 deg one never reaches it (a
    triangle, 2 sqrt(2/240) s); the 30 deg tilt 1.0 s, once between two passes (the next scan starts at the
    elevation this one ended at, not tilted back); a third pass ends a turn away from the first stop."""
    from phantom.protocol.motion import SCANNER_AXES

    orbit, elevation = SCANNER_AXES
    assert orbit.move_s(-12.0) == pytest.approx(0.525) and orbit.move_s(0.0) == 0.0
    assert orbit.move_s(2.0) == pytest.approx(2 * (2.0 / 240.0) ** 0.5) and elevation.move_s(30.0) == pytest.approx(1.0)
    assert Plan(30, (0.0, 30.0)).moves_s(SCANNER_AXES) == pytest.approx(58 * 0.525 + 1.0)
    assert Plan(30, (30.0, 0.0)).moves_s(SCANNER_AXES) == pytest.approx(58 * 0.525 + 1.0)
    assert Plan(30, (0.0, 15.0, 30.0)).moves_s(SCANNER_AXES) == pytest.approx(
        87 * 0.525 + 2 * elevation.move_s(15.0) + orbit.move_s(348.0))
    assert Plan(30, (0.0,)).moves_s(SCANNER_AXES) == pytest.approx(29 * 0.525 + orbit.move_s(348.0))

@pytest.mark.parametrize(("plan", "message"), [
    (dict(views=0), "views must be at least 1"),
    (dict(views=100_000_000), "views must be at most 720"),
    (dict(views=1e8), "views must be a whole number"),
    (dict(views=12, settle_s=float("nan")), "settle_s must be a finite number"),
    (dict(views=12, settle_s=-1.0), r"settle_s must be between 0 and 10 s .*got -1"),
    (dict(views=12, settle_s=1e6), r"settle_s must be between 0 and 10 s"),
    (dict(views=12, elevations_deg=()), "one to 8 elevations"),
    (dict(views=12, elevations_deg=(0.0, float("inf"))), "an elevation must be a finite number"),
    (dict(views=12, start_deg=float("nan")), "start_deg must be a finite number"),
    (dict(views=12, span_deg=0.0), "span_deg must be above 0"),
    (dict(views=12, span_deg=720.0), "span_deg must be between 0 and 360"),
])
def test_a_plan_out_of_bounds_is_refused_before_any_move(plan, message):
    with pytest.raises(CaptureError, match=message):
        Plan(**plan)


@pytest.mark.parametrize("scale", [6.0, 0.0, float("nan"), -1.0, True])
def test_a_virtual_camera_scale_out_of_bounds_is_refused(scale):
    from phantom.scan.camera import RigError

    with pytest.raises(RigError, match="scale must be a number from 0.05 to 2"):
        virtual_rig(scale)


@pytest.mark.parametrize(("params", "message"), [
    ({"settle_s": float("nan")}, "settle_s must be a finite number"),
    ({"settle_s": -0.5}, "settle_s must be between 0 and 10 s"),
    ({"settle_s": 1e6}, "settle_s must be between 0 and 10 s"),
    ({"views": 1e8}, "views must be a whole number"),
    ({"views": 100_000_000}, "views must be at most 720"),
    ({"views": "60"}, "views must be a whole number"),
    ({"scale": 6}, "scale must be a number from 0.05 to 2"),
    ({"elevations_deg": 30}, "elevations_deg must be a list"),
    ({"elevations_deg": ["up"]}, "an elevation must be a finite number"),
    ({"seed": -1}, "seed must be a whole number"),
    ({"key_silhouettes": "yes"}, "key_silhouettes must be true or false"),
])
def test_the_daemons_scan_refuses_bad_parameters_before_it_makes_a_folder_or_moves(tmp_path, params, message):
    """The red team's cases (settle_s NaN, negative or 1e6, views 1e8, scale 6): refused with why by the daemon's
    scan handler before the capture folder exists and before the rig is touched (rig=None would fail on use)."""
    from phantom.scan.daemon_scan import DaemonScanner

    out = tmp_path / "capture"
    with pytest.raises(PhantomError, match=f"scan: .*{message}"):
        DaemonScanner()({"out": str(out), **params}, None)
    assert not out.exists()


def test_a_picture_larger_than_any_camera_is_refused_from_its_header(tmp_path):
    """A 16000^2 PNG took 1.6 GB before the size error: its header says how large it is."""
    import zlib

    def chunk(kind, data):
        return len(data).to_bytes(4, "big") + kind + data + zlib.crc32(kind + data).to_bytes(4, "big")

    header = (16000).to_bytes(4, "big") * 2 + bytes([8, 2, 0, 0, 0])
    (tmp_path / "images").mkdir()
    (tmp_path / "images" / "0000.png").write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header))
    (tmp_path / "capture.json").write_text(json.dumps({"format": "phantom-capture/1", "frames": _frames(1)}))
    folder = CaptureFolder.open(tmp_path)
    with pytest.raises(CaptureError, match="0000.png is 16000x16000, larger than any camera's"):
        folder.image(folder.frames[0])


def test_capture_refuses_more_pictures_than_a_capture_holds_before_it_calls_the_daemon(tmp_path, capsys):
    from phantom.cli.main import main

    assert main(["scan", "capture", "--out", str(tmp_path / "capture"), "--views", "600", "--elevations",
                 "0,10,20,30", "--socket", str(tmp_path / "no-daemon.sock")]) == 2
    assert "give from 1 to 2000 in all" in capsys.readouterr().err and not (tmp_path / "capture").exists()


def test_validate_refuses_more_pictures_than_a_capture_holds_before_writing(tmp_path, capsys):
    from phantom.cli.main import main

    assert main(["scan", "validate", "--sim", "--out", str(tmp_path / "out"), "--views", "700",
                 "--elevations", "0,10,20"]) == 2
    assert "give from 1 to 2000 in all" in capsys.readouterr().err and not (tmp_path / "out").exists()


def test_the_daemons_virtual_camera_without_a_simulated_phantom_is_refused_before_a_folder(tmp_path):
    """A daemon on a real board gives its scanner no simulated truth: a scan asking the virtual camera is refused
    with what to give instead, before the capture folder exists (rig=None would fail on use)."""
    from phantom.scan.daemon_scan import DaemonScanner

    out = tmp_path / "capture"
    with pytest.raises(PhantomError, match="this daemon has none: give the scan a real camera"):
        DaemonScanner(None)({"out": str(out), "views": 2}, None)
    assert not out.exists()


def test_a_rig_file_that_is_no_file_is_refused_before_it_is_read(tmp_path):
    """The scan's ``rig`` param names any path: /dev/zero (endless) and a folder are refused from their stat."""
    from phantom.scan.camera import Rig, RigError

    for path in ("/dev/zero", tmp_path):
        with pytest.raises(RigError, match="is not a regular file: give the rig.json"):
            Rig.load(path)
    with pytest.raises(RigError, match="does not exist: calibrate the rig first"):
        Rig.load(tmp_path / "missing.json")
