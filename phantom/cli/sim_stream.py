"""The simulated board's camera as a network camera: ``phantom sim-board --camera-stream HOST:PORT``.

A daemon started with ``--port`` on the simulated board drives it as a real board, with no simulated privileges:
its pictures must come through a camera, as on a real rig. This serves the virtual camera's pictures as MJPEG
over HTTP (what an IP camera or a phone as a webcam serves, which OpenCV's ``VideoCapture`` reads by URL), at a
webcam's frame rate (:data:`FRAMES_PER_S`), each rendered when it is sent, at the simulated rig's true angles (the
pulses its drivers took, counted by simavr). While the rig moves (its angles changed since the frame before), the
stream sends its last picture again instead of rendering one: a scan's reader takes a picture from frames that
arrive after its grab, which starts after the move and its settle (``phantom.scan.capture.Webcam``), and rendering
the move was most of the simulated rig's CPU (a real camera's frames in motion are blurred, and dropped the same way):

- ``/phantom.mjpg``: the simulated phantom (the truth model at the plant's true pressures);
- ``/target0.mjpg``, ``/target1.mjpg``: the ChArUco target, in the virtual rig's two calibration placements
  (facing the camera at orbit 0, then turned round), for ``phantom scan capture --target`` and
  ``phantom scan calibrate``;
- ``/truth.json``: the simulated phantom's truth now, for a test or a bench to judge a scan by (the plant's true
  pressures in kPa, the truth model's gland volume in ml, the rig's true angles in deg). A daemon driving the
  board reads nothing of it: it has no simulated privileges, as on a real rig.
- ``/board.json``: the simulated board's own account of its timing, for a test to explain a lost link by: its
  time, how far it fell behind the wall clock (``max_lag_s``, ``lost_s``, the last notable ``lags``), the last
  notable gaps in the host's bytes to its UART (``host_gaps``) and the serial line's counters (``serial``); see
  :meth:`CameraStream.board_timing`.

Pictures of ``scale`` times 1280x960 in the ``look`` (scan/render.py: ideal, or real), JPEG quality 95 with the
colour at full resolution (4:4:4): with the usual 4:2:0, the colour key's edges blur over two pixels and a scan of
the gland at rest read -2.1 % (a real camera's MJPEG has the same: prefer its 4:4:4 or raw mode). The socket's
send buffer is kept small, so that a reader gets a picture rendered a frame ago, not several.
"""

from __future__ import annotations

import threading
import time
from concurrent.futures.process import BrokenProcessPool
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import Any

import numpy as np

from phantom import require_extra

#: The stream's paths: the phantom, and the target in each virtual calibration placement.
PATHS = ("/phantom.mjpg", "/target0.mjpg", "/target1.mjpg")
#: The simulated phantom's truth (JSON), for a test or a bench, never for the daemon.
TRUTH_PATH = "/truth.json"
#: The simulated board's timing and serial counters (JSON), for a test or a bench, never for the daemon.
BOARD_PATH = "/board.json"
JPEG_QUALITY = 95
SEND_BUFFER_BYTES = 64 * 1024
#: The stream's frame rate at most, a webcam's. Rendered as fast as the machine allowed (30 ms idle), a scan's picture
#: cost 1.3-1.9 s of this process's CPU; a reader reads every frame as it comes (phantom.scan.capture.Webcam), so
#: the rate is what it decodes, 15 a second here.
FRAMES_PER_S = 15.0


class CameraStream:
    """The simulated rig's camera served as MJPEG (see the module docstring) from ``board`` (a ScannerBoard)."""

    def __init__(self, board: Any, host: str, port: int, scale: float = 0.5, look: str = "ideal"):
        from phantom.hil.truth_shape import TruthShape
        from phantom.scan.camera import virtual_pose_at, virtual_rig
        from phantom.scan.render import LOOKS, CharucoTarget
        from phantom.scan.virtual import VIRTUAL_PLACEMENTS, TargetCamera, VirtualCamera, target_pose_facing

        self.board = board
        self.closing = False
        #: pictures rendered so far; the stream's other frames repeat one while the rig moved
        self.rendered = 0
        self._lock = threading.Lock()
        self._angles = _Angles()
        rig = virtual_rig(scale)
        pose_at = virtual_pose_at(scale)
        self._truth_shape = truth = TruthShape()
        target = CharucoTarget()
        self.cameras: dict[str, Any] = {
            "/phantom.mjpg": VirtualCamera(rig, lambda: (truth.surface(self._angles.pressures_kpa),
                                                         self._angles.orbit_deg, self._angles.elevation_deg),
                                           look=LOOKS[look], pose_at=pose_at)}
        for number, (facing_deg, tilt_deg, spin_deg) in enumerate(VIRTUAL_PLACEMENTS):
            self.cameras[f"/target{number}.mjpg"] = TargetCamera(
                rig, target, target_pose_facing(facing_deg, tilt_deg, spin_deg, target), self._angles, number,
                pose_at=pose_at)
        self.server = ThreadingHTTPServer((host, port), self._handler())
        self.server.daemon_threads = True
        self.address = self.server.server_address
        self._thread = threading.Thread(target=self.server.serve_forever, name="camera-stream", daemon=True)

    def start(self) -> CameraStream:
        self._thread.start()
        return self

    def close(self) -> None:
        self.closing = True
        self.server.shutdown()
        self._truth_shape.close()  # a picture being solved is not waited for: the stream is closing
        self.server.server_close()

    def urls(self) -> dict[str, str]:
        """The streams' URLs by name (phantom, target0, target1), ``truth``: the truth's, and ``board``: the
        board's timing (neither a stream)."""
        host, port = str(self.address[0]), int(self.address[1])
        return {**{path.strip("/").removesuffix(".mjpg"): f"http://{host}:{port}{path}" for path in PATHS},
                "truth": f"http://{host}:{port}{TRUTH_PATH}", "board": f"http://{host}:{port}{BOARD_PATH}"}

    def plant_state(self) -> dict[str, Any]:
        """The board's plant now (``pressures_pa``, ``gland_volume_ml``, ``rig_deg``: ``ScannerBoard.plant_state``)."""
        with self._lock:  # the board's harness is not for two threads at once
            state: dict[str, Any] = self.board.plant_state()
        return state

    def truth(self) -> dict[str, Any]:
        """The simulated phantom now: ``pressures_kpa`` (the plant's true pressures), ``gland_volume_ml`` (the
        truth model's, at them) and ``rig_deg`` (the rig's true orbit and elevation angles)."""
        state = self.plant_state()
        return {"pressures_kpa": [p / 1e3 for p in state["pressures_pa"]],
                "gland_volume_ml": state.get("gland_volume_ml"), "rig_deg": state.get("rig_deg")}

    def board_timing(self) -> dict[str, Any]:
        """The harness's account of the board's time (``phantom.hil.sim.SimulatedBoard.plant_state``): ``time_s``
        (board time), ``last_host_byte_s`` (when its UART last took a byte from the host), ``max_lag_s`` and
        ``lost_s`` (the harness behind the wall clock: its longest stall, and all the time it gave up), ``lags`` (the
        last notable stalls, each ``[time of day s, board time s, stall s]``), ``host_gaps`` (the last gaps of over
        0.25 s of board time between the host's bytes to the UART, each ``[time of day s, board time s at its end,
        gap s of board time, wall time s the harness gave up meanwhile, bytes queued for the UART at its end]``),
        ``resets``, ``scheduling`` (what the harness runs at: ``phantom.hil.sim.HARNESS_RT_PRIORITY``), ``cpu_s``
        (the harness's CPU time) and ``serial`` (the line's byte counters: to and from the MCU, dropped,
        overflowed)."""
        with self._lock:
            state = self.board.plant_state()
            serial = self.board.cycle_stats()["serial"]
        keys = ("time_s", "last_host_byte_s", "max_lag_s", "lost_s", "lags", "host_gaps", "resets", "powered",
                "scheduling", "cpu_s")
        return {**{key: state.get(key) for key in keys}, "serial": serial}

    def picture(self, path: str, state: dict[str, Any] | None = None) -> np.ndarray:
        """One JPEG of the camera at ``path``, rendered now at the rig's true angles (those of ``state``, the
        plant's as :meth:`plant_state` read it, when given; else read now)."""
        with require_extra("scan"):
            import cv2

        state = self.plant_state() if state is None else state
        rig_deg = state.get("rig_deg") or [0.0, 0.0]
        with self._lock:  # the cameras' noise is not for two threads at once
            self._angles.orbit_deg, self._angles.elevation_deg = (float(angle or 0.0) for angle in rig_deg)
            self._angles.pressures_kpa = [p / 1e3 for p in state["pressures_pa"]]
            rgb = self.cameras[path].grab()
            self.rendered += 1
        ok, encoded = cv2.imencode(".jpg", np.ascontiguousarray(rgb[:, :, ::-1]),
                                   [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY,
                                    cv2.IMWRITE_JPEG_SAMPLING_FACTOR, cv2.IMWRITE_JPEG_SAMPLING_FACTOR_444])
        if not ok:
            raise RuntimeError("JPEG encoding failed")
        return np.asarray(encoded)

    def _handler(self) -> type[BaseHTTPRequestHandler]:
        stream = self

        class Handler(BaseHTTPRequestHandler):
            def setup(self) -> None:
                import socket

                self.request.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, SEND_BUFFER_BYTES)
                super().setup()

            def do_GET(self) -> None:  # noqa: N802 (http.server's name)
                if self.path in (TRUTH_PATH, BOARD_PATH):
                    import json

                    body = json.dumps(stream.truth() if self.path == TRUTH_PATH else stream.board_timing()).encode()
                    self.send_response(200)
                    self.send_header("Content-Type", "application/json")
                    self.send_header("Content-Length", str(len(body)))
                    self.end_headers()
                    self.wfile.write(body)
                    return
                if self.path not in stream.cameras:
                    self.send_error(404, f"the streams are {', '.join(PATHS)}; the truth is {TRUTH_PATH}, the board's "
                                         f"timing {BOARD_PATH}")
                    return
                self.send_response(200)
                self.send_header("Content-Type", "multipart/x-mixed-replace; boundary=frame")
                self.send_header("Cache-Control", "no-cache")
                self.end_headers()
                due_s = time.monotonic()
                sent, before_deg = False, None
                try:
                    while True:
                        time.sleep(max(0.0, due_s - time.monotonic()))
                        due_s = max(due_s + 1.0 / FRAMES_PER_S, time.monotonic())
                        state = stream.plant_state()
                        still = state.get("rig_deg") == before_deg  # since the frame before
                        before_deg = state.get("rig_deg")
                        if sent and not still:
                            # no frame while the rig moves, nor at the first tick after it stopped (not yet known
                            # still): the last picture sent again was of where the rig had been, and a reader a
                            # frame behind took it for where the rig stopped
                            continue
                        jpeg = stream.picture(self.path, state).tobytes()
                        sent = True
                        self.wfile.write(b"--frame\r\nContent-Type: image/jpeg\r\nContent-Length: "
                                         + str(len(jpeg)).encode() + b"\r\n\r\n" + jpeg + b"\r\n")
                        self.wfile.flush()
                except (BrokenPipeError, ConnectionResetError):
                    return
                except BrokenProcessPool:
                    # the truth's solver ended under this picture, or before it (the pool is then broken): the
                    # stream is closing
                    if stream.closing:
                        return
                    raise

            def log_message(self, format: str, *args: Any) -> None:  # noqa: A002 (http.server's name)
                return

        return Handler


class _Angles:
    """Where the rig truly is (deg) and the plant's pressures (kPa) at the picture being rendered."""

    def __init__(self) -> None:
        self.orbit_deg = 0.0
        self.elevation_deg = 0.0
        self.pressures_kpa: list[float] = [0.0, 0.0, 0.0]
