"""``phantom daemon --camera DEVICE|URL --rig rig.json``: the verify scan's real camera, checked before the daemon
starts (the rig read, one picture of the rig's size), and a picture of another size refused during a capture.
OpenCV's VideoCapture reads an image sequence through the API a device or a stream uses, so the camera here is
a folder of pictures."""

from __future__ import annotations

import contextlib
import json
import subprocess
import sys

import numpy as np
import pytest

cv2 = pytest.importorskip("cv2")

from phantom.scan.camera import virtual_rig  # noqa: E402
from phantom.scan.capture import CameraLost, Webcam  # noqa: E402


def _pictures(folder, width, height, count=2):
    folder.mkdir(parents=True, exist_ok=True)
    for index in range(count):
        cv2.imwrite(str(folder / f"{index:04d}.png"), np.full((height, width, 3), 90, np.uint8))
    return str(folder / "%04d.png")


@contextlib.contextmanager
def _streaming_board():
    """``phantom sim-board --camera-stream`` on a free port: its streams' URLs (what its ``--json`` line says)."""
    board = subprocess.Popen([sys.executable, "-m", "phantom", "sim-board", "--camera-stream", "127.0.0.1:0",
                              "--json"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        line = board.stdout.readline()
        assert line, board.stderr.read()
        yield json.loads(line)["streams"]
    finally:
        board.terminate()
        board.wait(30)


def _daemon(*arguments):
    return subprocess.run([sys.executable, "-m", "phantom", "daemon", "--port", "/dev/null", *arguments],
                          capture_output=True, text=True, timeout=120)


def test_a_rig_calibrated_for_another_picture_size_is_refused_before_the_daemon_starts(tmp_path):
    rig = virtual_rig(0.5).save(tmp_path / "rig.json")  # 640x480
    camera = _pictures(tmp_path / "camera", 320, 240)
    done = _daemon("--camera", camera, "--rig", str(rig))
    assert done.returncode != 0
    assert "gives 320x240 pictures and the rig" in done.stderr and "calibrated at 640x480" in done.stderr


def test_a_camera_without_a_rig_or_one_that_cannot_be_opened_is_refused(tmp_path):
    rig = virtual_rig(0.5).save(tmp_path / "rig.json")
    assert "--camera and --rig go together" in _daemon("--camera", "0").stderr
    done = _daemon("--camera", str(tmp_path / "none" / "%04d.png"), "--rig", str(rig))
    assert done.returncode != 0 and "cannot open the camera" in done.stderr


def test_a_camera_stream_address_that_is_not_host_and_port_is_refused():
    done = subprocess.run([sys.executable, "-m", "phantom", "sim-board", "--camera-stream", "8080"],
                          capture_output=True, text=True, timeout=60)
    assert done.returncode != 0 and "--camera-stream must be HOST:PORT" in done.stderr


def test_a_picture_of_another_size_during_a_capture_is_refused_saying_both_sizes(tmp_path):
    camera = _pictures(tmp_path / "camera", 320, 240)
    webcam = Webcam(camera, size=(640, 480))
    with pytest.raises(CameraLost, match="gave a 320x240 picture, the rig was calibrated at 640x480"):
        webcam.grab()
    assert Webcam(camera, size=(320, 240)).grab().shape == (240, 320, 3)


@pytest.mark.sim  # starts the simulated board (simavr)
def test_the_simulated_board_serves_its_camera_as_an_mjpeg_stream_opencv_reads(tmp_path):
    from phantom.scan.silhouette import silhouette

    with _streaming_board() as streams:
        assert set(streams) == {"phantom", "target0", "target1", "truth", "board"}
        truth_url, board_url = streams.pop("truth"), streams.pop("board")
        pictures = {}
        for name, url in streams.items():
            capture = cv2.VideoCapture(url)  # as a daemon's --camera URL opens it
            ok, picture = capture.read()
            capture.release()
            assert ok and picture.shape == (480, 640, 3), name
            pictures[name] = picture[:, :, ::-1].copy()
        found = silhouette(pictures["phantom"])
        assert not found.touches_edge and 4000 < found.area_px < 40000  # the gland, whole in view
        board_of = cv2.aruco.CharucoBoard((9, 6), 15.0, 11.0, cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50))
        corners, _, _, _ = cv2.aruco.CharucoDetector(board_of).detectBoard(cv2.cvtColor(pictures["target0"],
                                                                                        cv2.COLOR_RGB2GRAY))
        assert corners is not None and len(corners) >= 30  # the target facing the camera at orbit 0
        import urllib.error
        import urllib.request

        with pytest.raises(urllib.error.HTTPError, match="404"):
            urllib.request.urlopen(streams["phantom"].replace("phantom.mjpg", "nothing.mjpg"), timeout=10)
        with urllib.request.urlopen(truth_url, timeout=10) as answer:  # for a test to judge a scan by
            truth = json.load(answer)
        assert 26.0 < truth["gland_volume_ml"] < 27.0 and len(truth["pressures_kpa"]) == 3  # vented, at rest
        assert truth["rig_deg"] is not None
        with urllib.request.urlopen(board_url, timeout=10) as answer:  # for a test to explain a lost link by
            board = json.load(answer)
        assert board["time_s"] > 0 and board["lost_s"] >= 0 and isinstance(board["host_gaps"], list)
        assert {"bytes_to_mcu", "bytes_from_mcu", "bytes_overflowed"} <= set(board["serial"]) and board["scheduling"]


class _CountedReads:
    """A VideoCapture whose frames read are counted."""

    def __init__(self, capture):
        self.capture, self.frames = capture, 0

    def grab(self):
        self.frames += 1
        return self.capture.grab()

    def __getattr__(self, name):
        return getattr(self.capture, name)


@pytest.mark.sim  # starts the simulated board (simavr)
def test_a_picture_through_the_simulated_stream_comes_in_a_few_frames_of_a_paced_stream(monkeypatch):
    """The simulated stream rendered its pictures as fast as the machine allowed (30 ms each, idle), and each
    picture of a scan read 61 frames (1.3-1.9 s of the board's CPU). At a webcam's frame rate its reader, which
    reads the frames as they come, takes a picture from the second frame after it was asked for."""
    import time

    from phantom.cli.sim_stream import FRAMES_PER_S
    from phantom.scan import capture as capture_module
    from phantom.scan.capture import STREAM_FRESH_FRAME

    opened, counted = capture_module._open_video, []

    def open_counted(source):
        counted.append(_CountedReads(opened(source)))
        return counted[-1]

    monkeypatch.setattr(capture_module, "_open_video", open_counted)
    with _streaming_board() as streams:
        camera = Webcam(streams["phantom"])
        taken_s = []
        for _ in range(3):
            time.sleep(1.0)  # the orbit moves and settles
            started = time.monotonic()
            assert camera.grab().shape == (480, 640, 3)
            taken_s.append(time.monotonic() - started)
        # the frames asked for, one on its way, and a busy machine's pause
        assert max(taken_s) < (STREAM_FRESH_FRAME + 1) / FRAMES_PER_S + 0.5, taken_s
        counted[0].frames = 0
        time.sleep(2.0)
        assert counted[0].frames <= 1.25 * FRAMES_PER_S * 2.0 + 4, counted[0].frames  # paced (a frame on its way)
        camera.close()


def test_a_look_that_is_not_one_is_refused_saying_the_looks_there_are(tmp_path):
    done = _daemon("--look", "nonsense")
    assert done.returncode == 2 and "--look: the value must be one of ideal, real, got 'nonsense'" in done.stderr
    config = tmp_path / "phantomd.toml"
    config.write_text('[daemon]\nsim = true\nlook = "sepia"\n')
    done = subprocess.run([sys.executable, "-m", "phantom", "daemon", "--config", str(config)], capture_output=True,
                          text=True, timeout=120)
    assert done.returncode == 2 and "[daemon] look must be one of ideal, real, got 'sepia'" in done.stderr


def test_the_daemons_scan_takes_the_daemons_camera_when_its_params_name_none(tmp_path):
    """``phantom daemon --camera`` is the scan method's camera unless the params give another (characterise's
    scans on a real rig then need no --camera of their own); the rig's picture size is checked either way."""
    from phantom.scan.daemon_scan import DaemonScanner

    rig = virtual_rig(0.5).save(tmp_path / "rig.json")  # 640x480
    own = _pictures(tmp_path / "own", 640, 480)
    other = _pictures(tmp_path / "other", 320, 240)
    camera = DaemonScanner(camera=own)._camera({"rig": str(rig)}, None, (0.0, 30.0), 1.0, 0)
    try:
        assert camera.describe()["source"] == own and camera.grab().shape == (480, 640, 3)
    finally:
        camera.close()
    camera = DaemonScanner(camera=own)._camera({"camera": other, "rig": str(rig)}, None, (0.0,), 1.0, 0)
    try:
        assert camera.describe()["source"] == other
        with pytest.raises(CameraLost, match="gave a 320x240 picture, the rig was calibrated at 640x480"):
            camera.grab()
    finally:
        camera.close()
