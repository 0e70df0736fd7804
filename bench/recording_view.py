"""A recording as the daemon makes it, from the model, and screenshots of it in Rerun's web viewer.

Drives :class:`phantom.host.recording.Recorder` at the daemon's rates (telemetry 50 Hz, volumes 10 Hz, link
2 Hz, mesh 1 Hz) through a scene of gland-volume steps: setpoints from the calibrated model's inverse, pressures
following them as first-order lags with sensor noise, volumes and shapes from the model's estimator at the
measured pressures, and a "true" volume 3 % above the estimate standing in for the simulated plant's. Then,
with ``--screenshot``, serves the file with ``rerun --serve-web`` on loopback and takes a screenshot with
headless Chromium (Debian's ``chromium``; SwiftShader renders the WebGL), driven over its DevTools pipe.

    .venv/bin/python bench/recording_view.py [--out out/recording_view.rrd] [--screenshot docs/img/rerun_view.png]
"""

from __future__ import annotations

import argparse
import base64
import fcntl
import functools
import http.server
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
import urllib.parse
from pathlib import Path

import numpy as np

TELEMETRY_HZ, VOLUME_HZ, LINK_HZ, MESH_HZ = 50, 10, 2, 1
#: The scene: (start s on its timeline, gland volume ml; None: vent).
SCENE_STEPS = ((0.0, 30.0), (15.0, 34.0), (30.0, 38.0), (45.0, 31.0), (55.0, None), (62.0, 38.0))
SCENE_START_S, DURATION_S = 8.0, 90.0
#: Pressure lag of each chamber (s): the base is three times as compliant as a lobe.
LAG_S = (0.45, 0.15, 0.15)


def record(path: Path, names: list[str]) -> None:
    from phantom.host.recording import Recorder
    from phantom.model import PhantomModel, load_scene
    from phantom.model.inverse import InverseSolver, Target

    model = PhantomModel.from_scene(load_scene("builtin:calibrated"))
    solver = InverseSolver(model)
    used, triangles = model.outer_surface()
    recorder = Recorder(names, save_path=path)
    recorder.open()
    recorder.log_rest_surface(model.nodes_m[used] * 1e3, triangles)
    rng = np.random.default_rng(1)
    pressure_kpa, setpoint_kpa, target_ml = np.zeros(3), np.zeros(3), None
    step_index = -1
    dt = 1.0 / TELEMETRY_HZ
    recorder.log_event(0.0, "daemon started: model ready, link up")
    for k in range(int(DURATION_S * TELEMETRY_HZ)):
        time_s = k * dt
        scene_s = time_s - SCENE_START_S
        recorder.set_scene_time(scene_s if scene_s >= 0 else None)
        if scene_s >= 0 and step_index + 1 < len(SCENE_STEPS) and scene_s >= SCENE_STEPS[step_index + 1][0]:
            step_index += 1
            target_ml = SCENE_STEPS[step_index][1]
            if target_ml is None:
                setpoint_kpa = np.zeros(3)
                recorder.log_event(time_s, f"scene step {step_index}: vent", "WARN")
            else:
                started = time.perf_counter()
                result = solver.pressures_for(Target(gland_volume_m3=target_ml * 1e-6))
                setpoint_kpa = np.asarray(result.pressures_pa) / 1e3
                recorder.log_solver(time_s, result.qp_solve_time_s, time.perf_counter() - started)
                recorder.log_event(time_s, f"scene step {step_index}: {target_ml:.1f} ml -> setpoints "
                                   + ", ".join(f"{p:.2f}" for p in setpoint_kpa) + " kPa")
        drive = np.clip(0.12 * setpoint_kpa + 1.5 * (setpoint_kpa - pressure_kpa), 0.0, 1.0)
        pressure_kpa = pressure_kpa + (setpoint_kpa - pressure_kpa) * dt / np.asarray(LAG_S)
        measured_kpa = pressure_kpa + rng.normal(0.0, 0.01, 3)
        recorder.log_telemetry(time_s, measured_kpa, setpoint_kpa, drive)
        if k % (TELEMETRY_HZ // VOLUME_HZ) == 0:
            chamber_m3, gland_m3 = solver.estimator.volumes(np.clip(pressure_kpa, 0, None) * 1e3)
            recorder.log_volumes(time_s, target_ml, gland_m3 * 1e6, np.asarray(chamber_m3) * 1e6,
                                 true_ml=gland_m3 * 1e6 * 1.03)
        if k % (TELEMETRY_HZ // LINK_HZ) == 0:
            recorder.log_link(time_s, 4.0 + rng.gamma(2.0, 0.5), 0, 0, 0)
        if k % (TELEMETRY_HZ // MESH_HZ) == 0:
            shape_m = solver.estimator.shape(np.clip(pressure_kpa, 0, None) * 1e3)
            recorder.log_mesh(time_s, np.asarray(shape_m)[used] * 1e3, triangles)
    recorder.set_scene_time(None)
    recorder.log_event(DURATION_S, "daemon stopped")
    recorder.close()


class _CorsFiles(http.server.SimpleHTTPRequestHandler):
    """Static files with the CORS header the web viewer (another origin) needs to fetch an .rrd."""

    def end_headers(self):
        self.send_header("Access-Control-Allow-Origin", "*")
        super().end_headers()

    def log_message(self, *args):
        pass


class _Chromium:
    """Headless Chromium driven over its DevTools pipe (fds 3 and 4, NUL-separated JSON): no extra package."""

    def __init__(self, size: tuple[int, int], profile: str):
        chromium = shutil.which("chromium") or shutil.which("chromium-browser")
        if chromium is None:
            sys.exit("no chromium: apt-get install -y chromium")
        commands_read, self._commands = os.pipe()
        self._replies, replies_write = os.pipe()

        def onto_fds_3_and_4():
            low = [fcntl.fcntl(fd, fcntl.F_DUPFD, 10) for fd in (commands_read, replies_write)]
            os.dup2(low[0], 3)
            os.dup2(low[1], 4)

        self.process = subprocess.Popen(
            [chromium, "--headless=new", "--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
             "--ignore-gpu-blocklist", f"--user-data-dir={profile}", f"--window-size={size[0]},{size[1]}",
             "--remote-debugging-pipe", "about:blank"],
            pass_fds=(3, 4), preexec_fn=onto_fds_3_and_4, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
            start_new_session=True)
        os.close(commands_read)
        os.close(replies_write)
        self._buffer, self._id, self.size = b"", 0, size

    def call(self, method: str, params: dict | None = None, session: str | None = None) -> dict:
        self._id += 1
        message = {"id": self._id, "method": method, "params": params or {}}
        if session:
            message["sessionId"] = session
        os.write(self._commands, json.dumps(message).encode() + b"\0")
        while True:
            while b"\0" not in self._buffer:
                chunk = os.read(self._replies, 1 << 20)
                if not chunk:
                    raise RuntimeError("chromium closed its DevTools pipe")
                self._buffer += chunk
            raw, self._buffer = self._buffer.split(b"\0", 1)
            reply = json.loads(raw)
            if reply.get("id") == self._id:
                if "error" in reply:
                    raise RuntimeError(f"{method}: {reply['error']}")
                return reply["result"]

    def screenshot(self, url: str, png: Path, wait_s: float) -> None:
        """Open ``url``, wait ``wait_s`` of real time (the viewer compiles its wasm and loads the file), shoot."""
        target = self.call("Target.createTarget", {"url": url})["targetId"]
        session = self.call("Target.attachToTarget", {"targetId": target, "flatten": True})["sessionId"]
        self.call("Emulation.setDeviceMetricsOverride", {"width": self.size[0], "height": self.size[1],
                                                          "deviceScaleFactor": 1, "mobile": False}, session)
        time.sleep(wait_s)
        data = self.call("Page.captureScreenshot", {"format": "png"}, session)["data"]
        png.write_bytes(base64.b64decode(data))

    def close(self) -> None:
        os.killpg(self.process.pid, signal.SIGTERM)  # the browser and its renderer and GPU processes
        self.process.wait(10)
        os.close(self._commands)
        os.close(self._replies)


def screenshot(rrd: Path, png: Path, size: tuple[int, int] = (1600, 1000), wait_s: float = 60.0) -> Path:
    """Open ``rrd`` in Rerun's web viewer (served on loopback, the file fetched over HTTP so that the viewer
    loads it whole rather than replaying it as a live stream) and screenshot it with headless Chromium."""
    files = http.server.ThreadingHTTPServer(("127.0.0.1", 0),
                                            functools.partial(_CorsFiles, directory=str(rrd.resolve().parent)))
    threading.Thread(target=files.serve_forever, daemon=True).start()
    file_url = f"http://127.0.0.1:{files.server_port}/{rrd.name}"
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        web_port = probe.getsockname()[1]
    viewer = subprocess.Popen([str(Path(sys.executable).with_name("rerun")), "--serve-web", "--bind", "127.0.0.1",
                               "--web-viewer-port", str(web_port), file_url],
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    png.parent.mkdir(parents=True, exist_ok=True)
    try:
        for _ in range(150):
            try:
                socket.create_connection(("127.0.0.1", web_port), 0.2).close()
                break
            except OSError:
                time.sleep(0.2)
        with tempfile.TemporaryDirectory() as profile:
            browser = _Chromium(size, profile)
            try:
                browser.screenshot(f"http://127.0.0.1:{web_port}/?url={urllib.parse.quote(file_url, safe='')}",
                                   png, wait_s)
            finally:
                browser.close()
    finally:
        # the `rerun` script runs the viewer binary as its child: end the whole process group
        os.killpg(viewer.pid, signal.SIGTERM)
        viewer.wait(10)
        files.shutdown()
    return png


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="out/recording_view.rrd", help="the recording to write")
    parser.add_argument("--names", default="base,left lobe,right lobe", help="chamber names, comma-separated")
    parser.add_argument("--rrd", help="screenshot this existing recording instead of making one")
    parser.add_argument("--screenshot", help="PNG to write (needs chromium)")
    parser.add_argument("--size", default="1600,1000", help="browser window width,height (px)")
    parser.add_argument("--wait-s", type=float, default=60.0,
                        help="seconds the viewer gets to load before the screenshot (SwiftShader is slow)")
    args = parser.parse_args()
    rrd = Path(args.rrd) if args.rrd else Path(args.out)
    if not args.rrd:
        rrd.parent.mkdir(parents=True, exist_ok=True)
        started = time.perf_counter()
        record(rrd, args.names.split(","))
        print(f"{rrd}: {rrd.stat().st_size / 1e6:.1f} MB, {DURATION_S:g} s recorded in "
              f"{time.perf_counter() - started:.1f} s")
    if args.screenshot:
        size = tuple(int(value) for value in args.size.split(","))
        print(f"screenshot: {screenshot(rrd, Path(args.screenshot), size, args.wait_s)}")


if __name__ == "__main__":
    main()
