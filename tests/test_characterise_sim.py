"""``phantom characterise`` end to end through a real ``phantom daemon --sim`` (the firmware in simavr, the orbit's
steppers, the virtual camera photographing the simulated phantom's truth): two pressure states set, reached,
scanned with a small plan, reconstructed and stored; the report written; a resumed finished run scans nothing."""

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from daemon_rig import daemon_process

PHANTOM = Path(sys.executable).with_name("phantom")

pytestmark = [pytest.mark.sim, pytest.mark.slow]


@pytest.mark.timeout(1500)
def test_characterise_scans_stores_and_reports_through_a_simulated_daemon(tmp_path, default_model_cached):
    pytest.importorskip("cv2")
    from phantom.model.measurements import CorrectionStore
    from phantom.scan.camera import virtual_rig

    environment = {**os.environ, "PHANTOM_DATA_DIR": str(tmp_path / "data")}
    virtual_rig(0.25, (0.0, 30.0)).save(tmp_path / "rig.json")  # the virtual camera's own geometry
    out = tmp_path / "run"
    with daemon_process(tmp_path, "--sim", "--sim-speed", "2", ready_s=120, env=environment) as daemon:
        sock = daemon.socket
        command = [str(PHANTOM), "characterise", "--out", str(out), "--socket", str(sock), "--json"]
        done = subprocess.run([*command, "--points", "2", "--rig", str(tmp_path / "rig.json"), "--views", "8",
                               "--scale", "0.25", "--settle-s", "0", "--voxel-mm", "0.5", "--phantom", "bench"],
                              capture_output=True, text=True, env=environment, timeout=1400)
        assert done.returncode == 0, done.stderr + daemon.log()
        again = subprocess.run([*command, "--resume"], capture_output=True, text=True, env=environment, timeout=300)
        assert again.returncode == 0, again.stderr
        status = json.loads(subprocess.run([str(PHANTOM), "status", "--json", "--socket", str(sock)],
                                           capture_output=True, text=True, timeout=60).stdout)
    record = json.loads((out / "characterisation.json").read_text())
    assert len(record["results"]) == 2 and not record["skipped"]
    for result in record["results"]:
        asked, measured = result["asked_kpa"], result["pressures_kpa"]
        assert max(abs(a - m) for a, m in zip(asked, measured, strict=True)) < 0.1, "scanned where it was set"
        assert result["stored"] and Path(result["scan_folder"], "capture.json").is_file()
        # 16 small pictures: the hull is coarse, but it is this phantom's (the truth), not a stand-in
        assert result["volume_ml"] == pytest.approx(result["true_ml"], rel=0.08)
    stored = CorrectionStore(tmp_path / "data" / "corrections" / "bench.json").entries()
    assert sorted(m.scan_file for m in stored) == sorted(r["scan_folder"] for r in record["results"])
    assert all(m.method == "scan" and m.model == "builtin:converged" for m in stored)
    assert "2 of 2 points done; 0 to scan" in again.stderr, "the finished points are not scanned again"
    summary = json.loads(done.stdout)
    assert summary["points"] == 2 and Path(summary["report"]).is_file() and Path(summary["plot"]).is_file()
    assert "elapsed, about" in done.stderr and "left" in done.stderr, "progress with the time left"
    assert status["setpoints_kpa"] == [0.0, 0.0, 0.0], "vented at the end"
