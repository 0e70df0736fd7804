"""A network camera's faults through the scan's own stream reader (``phantom.scan.capture.Webcam`` on a URL): a
frame that cannot be decoded (an IP camera's frame cut short on a weak link) is passed over, not taken for a lost
camera; a stream that ends, or goes silent, is a lost camera (CameraLost, naming it), in seconds, not a scan that
waits forever. The stream is a real MJPEG stream over HTTP, read by OpenCV as a webcam's is; what it sends is
scripted by the test, frame by frame."""

from __future__ import annotations

import http.server
import queue
import socketserver
import threading
import time

import numpy as np
import pytest

cv2 = pytest.importorskip("cv2")

from phantom.scan import capture as capture_module  # noqa: E402
from phantom.scan.capture import CameraLost, Webcam  # noqa: E402

#: the frames a stream sends before the test's own: OpenCV reads a few to learn the stream's format when it opens
OPENING_FRAMES = 3
SIZE = (64, 48)


def _jpeg(value: int) -> bytes:
    """A flat grey picture of ``value``, as a camera's JPEG."""
    return cv2.imencode(".jpg", np.full((SIZE[1], SIZE[0], 3), value, np.uint8))[1].tobytes()


#: a frame whose JPEG cannot be decoded: its header, then zeros where its tables and data were
CUT_SHORT = _jpeg(100)[:20] + bytes(200)


class ScriptedStream:
    """An MJPEG stream over HTTP (``multipart/x-mixed-replace``, as IP cameras and ``phantom sim-board
    --camera-stream`` send) that sends what the test puts: a frame's bytes, or None to end the stream."""

    def __init__(self) -> None:
        self.frames: queue.Queue[bytes | None] = queue.Queue()
        frames = self.frames

        class Handler(http.server.BaseHTTPRequestHandler):
            def do_GET(self) -> None:  # noqa: N802 (http.server's name)
                self.send_response(200)
                self.send_header("Content-Type", "multipart/x-mixed-replace; boundary=frame")
                self.end_headers()
                try:
                    while (frame := frames.get()) is not None:
                        self.wfile.write(b"--frame\r\nContent-Type: image/jpeg\r\nContent-Length: "
                                         + str(len(frame)).encode() + b"\r\n\r\n" + frame + b"\r\n")
                        self.wfile.flush()
                except (BrokenPipeError, ConnectionResetError):
                    return

            def log_message(self, format, *args) -> None:  # noqa: A002 (http.server's name)
                return

        self.server = socketserver.ThreadingTCPServer(("127.0.0.1", 0), Handler)
        self.server.daemon_threads = True
        threading.Thread(target=self.server.serve_forever, args=(0.05,), daemon=True).start()
        self.url = f"http://127.0.0.1:{self.server.server_address[1]}/camera.mjpg"
        for _ in range(OPENING_FRAMES):
            self.frames.put(_jpeg(10))

    def close(self) -> None:
        self.frames.put(None)
        self.server.shutdown()
        self.server.server_close()


@pytest.fixture
def stream():
    scripted = ScriptedStream()
    yield scripted
    scripted.close()


def _opened(stream: ScriptedStream) -> Webcam:
    """A Webcam on ``stream``, its reader past the frames OpenCV buffered as it opened (they were sent before any
    picture is asked for)."""
    camera = Webcam(stream.url)
    time.sleep(0.3)
    return camera


def _when_asked(camera: Webcam, frames: list[bytes | None], stream: ScriptedStream) -> threading.Thread:
    """Sends ``frames`` (50 ms apart) once ``camera``'s reader has been asked for a picture."""
    def send() -> None:
        deadline = time.monotonic() + 30
        while camera._stream._asked_s is None and time.monotonic() < deadline:
            time.sleep(0.01)
        for frame in frames:
            stream.frames.put(frame)
            time.sleep(0.05)

    sender = threading.Thread(target=send, daemon=True)
    sender.start()
    return sender


def test_a_frame_that_cannot_be_decoded_is_passed_over_for_the_next(stream):
    """OpenCV's FFmpeg reader decodes as it grabs: a frame cut short fails its grab, and the stream goes on. The
    reader took that failure for a stream that had ended, and the scan lost its camera to one bad frame."""
    camera = _opened(stream)
    try:
        sender = _when_asked(camera, [CUT_SHORT, _jpeg(130), CUT_SHORT, CUT_SHORT, _jpeg(160), _jpeg(190)], stream)
        picture = camera.grab()
        sender.join(10)
        # the second frame that could be read after the ask (the first may have been sent before it)
        assert picture.shape == (SIZE[1], SIZE[0], 3)
        assert abs(float(picture.mean()) - 160) < 3, picture.mean()
        # and it reads on (the 190 may still be on its way at the next ask: then 220 is the second frame after it)
        _when_asked(camera, [_jpeg(220), _jpeg(240)], stream)
        again = float(camera.grab().mean())
        assert min(abs(again - value) for value in (220, 240)) < 3, again
    finally:
        stream.frames.put(_jpeg(0))                    # ends the reader's read under way, as a live camera's would
        camera.close()


def test_a_stream_that_ends_is_a_lost_camera_at_once(stream):
    camera = _opened(stream)
    try:
        _when_asked(camera, [_jpeg(130), None], stream)
        started = time.monotonic()
        with pytest.raises(CameraLost, match=r"the camera 'http://127\.0\.0\.1:\d+/camera\.mjpg' sent no picture"):
            camera.grab()
        assert time.monotonic() - started < 5.0
    finally:
        camera.close()


def test_a_stream_that_goes_silent_is_a_lost_camera_after_its_silence(stream, monkeypatch):
    """Silent from its opening frames on: lost once it has sent nothing for STREAM_SILENT_S, asked or not."""
    monkeypatch.setattr(capture_module, "STREAM_SILENT_S", 1.0)       # a real one waits 10 s
    started = time.monotonic()
    camera = Webcam(stream.url)
    try:
        time.sleep(0.2)                                                   # past the frames buffered as it opened
        with pytest.raises(CameraLost, match=r"the camera 'http://127\.0\.0\.1:\d+/camera\.mjpg' sent no picture"):
            camera.grab()
        assert 0.9 < time.monotonic() - started < 1.0 + 4.0
        with pytest.raises(CameraLost):                                   # and stays lost
            camera.grab()
    finally:
        started = time.monotonic()
        camera.close()
        assert time.monotonic() - started < 1.0 + 2.0                     # its reader ended with the stream


def test_a_stream_that_sends_nothing_readable_is_a_lost_camera_saying_so(stream):
    camera = _opened(stream)
    try:
        _when_asked(camera, [CUT_SHORT] * 12, stream)
        with pytest.raises(CameraLost, match="could not be read"):
            camera.grab()
    finally:
        camera.close()


def test_a_stream_that_cannot_be_opened_is_refused_with_a_hint_for_a_stream():
    """A URL nobody serves was refused with a device's hint ("is it plugged in (ls /dev/video*)")."""
    with pytest.raises(CameraLost, match=r"cannot open the camera 'http://127\.0\.0\.1:9/none\.mjpg': is the "
                                         r"stream up and its URL right\? \(open it in a browser\)"):
        Webcam("http://127.0.0.1:9/none.mjpg")
