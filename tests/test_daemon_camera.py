"""``phantom daemon --camera DEVICE|URL --rig rig.json``: the verify scan's real camera, checked before the daemon
starts (the rig read, one picture of the rig's size), and a picture of another size refused during a capture.
OpenCV's VideoCapture reads an image sequence through the API a device or a stream uses, so the camera here is
a folder of pictures."""

from __future__ import annotations

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


def test_a_picture_of_another_size_during_a_capture_is_refused_saying_both_sizes(tmp_path):
    camera = _pictures(tmp_path / "camera", 320, 240)
    webcam = Webcam(camera, size=(640, 480))
    with pytest.raises(CameraLost, match="gave a 320x240 picture, the rig was calibrated at 640x480"):
        webcam.grab()
    assert Webcam(camera, size=(320, 240)).grab().shape == (240, 320, 3)
