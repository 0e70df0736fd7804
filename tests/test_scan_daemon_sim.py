"""The daemon's ``scan`` API method (host/motion.py, the capture given by ``phantom daemon``: scan/daemon_scan.py)
on the simulated board: the firmware's steppers turn the orbit in simavr, the virtual camera renders the truth
phantom at the rig's counted angles, and the pictures land in a capture folder; bad requests are refused."""

import json
import sys
from pathlib import Path

import pytest
from daemon_rig import daemon_process

from phantom.host.client import DaemonClient, DaemonError

PHANTOM = Path(sys.executable).with_name("phantom")

pytestmark = [pytest.mark.sim, pytest.mark.slow]


@pytest.mark.timeout(600)
def test_the_daemon_scans_through_its_api(tmp_path, default_model_cached):
    pytest.importorskip("cv2")
    with daemon_process(tmp_path, "--sim", "--sim-speed", "2", ready_s=120) as daemon:
        with DaemonClient(daemon.socket, timeout_s=300) as client:
            with pytest.raises(DaemonError, match=r"scan takes out .*not colour"):
                client.call("scan", {"out": str(tmp_path / "x"), "colour": "red"})
            with pytest.raises(DaemonError, match="views must be at least 1"):
                client.call("scan", {"out": str(tmp_path / "y"), "views": 0})
            out = tmp_path / "capture"
            answer = client.call("scan", {"out": str(out), "views": 4, "elevations_deg": [0, 30], "scale": 0.2,
                                          "settle_s": 0.05})
            assert answer == {"folder": str(out), "status": "complete", "pictures": 8}
            status = client.call("motion_status")
            with pytest.raises(DaemonError, match="look must be one of ideal, real"):
                client.call("scan", {"out": str(tmp_path / "z"), "look": "sepia"})
            # the virtual camera's real look: the phantom hung by its tubes out of the picture's top edge
            real = client.call("scan", {"out": str(tmp_path / "real"), "views": 1, "elevations_deg": [0],
                                        "scale": 0.2, "settle_s": 0.05, "look": "real"})
            assert real["status"] == "complete" and real["pictures"] == 1
        described = json.loads((tmp_path / "real" / "capture.json").read_text())["camera"]
        assert described["tubes"] and described["cloth"] == 1.0 and described["gloss"] > 0
        from phantom.scan.capture import CaptureFolder
        from phantom.scan.silhouette import silhouette

        hung = CaptureFolder.open(tmp_path / "real")
        assert silhouette(hung.image(hung.frames[0])).touches_top
        data = json.loads((out / "capture.json").read_text())
        stops = [angle for f in data["frames"] for angle in (f["orbit_deg"], f["elevation_deg"])]
        wanted = [-180.0, 0.0, -90.0, 0.0, 0.0, 0.0, 90.0, 0.0, 90.0, 30.0, 0.0, 30.0, -90.0, 30.0, -180.0, 30.0]
        assert stops == pytest.approx(wanted, abs=0.01)
        assert all(len(f["pressures_kpa"]) == 3 for f in data["frames"])
        assert data["camera"]["kind"] == "virtual" and (out / "images" / "0007.png").is_file()
        # the simulated rig's true angle (the pulses counted by simavr) is where the board says the orbit is
        assert status["simulated"]["rig_deg"] == pytest.approx([-180.0, 30.0], abs=0.01)
