"""The paper's validation by scanning, reproduced on the simulated rig (``phantom scan validate --sim``), short:
two BPH targets, 12 pictures each of 320x240 px. The daemon holds the inverse's pressures with the firmware in
simavr, the firmware's steppers turn the orbit, the virtual camera renders the truth phantom at the rig's counted
angles, the rig is calibrated from rendered pictures of the ChArUco target, and the scans are compared with the
target, the model and the truth. The full run (120 pictures of 1280x960 per target) is the documented command in
scan/README.md."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from phantom.cli import main as cli

PHANTOM = Path(sys.executable).with_name("phantom")
TARGETS_ML = (27.0, 35.0)
VIEWS = 6  # per pass, two passes


def test_validate_needs_the_simulated_rig(capsys):
    assert cli.main(["scan", "validate", "--out", "unused"]) == 2
    assert "give --sim" in capsys.readouterr().err


def surface_centroid_mm(entity: dict) -> np.ndarray:
    """The area-weighted centroid of a recorded mesh's last surface (mm)."""
    vertices = np.asarray(entity["Mesh3D:vertex_positions"][-1], dtype=float)
    corners = vertices[np.asarray(entity["Mesh3D:triangle_indices"][-1], dtype=int).reshape(-1, 3)]
    areas = 0.5 * np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=1)
    return np.asarray((areas[:, None] * corners.mean(axis=1)).sum(axis=0) / areas.sum())


@pytest.mark.sim
@pytest.mark.slow
@pytest.mark.timeout(900)  # the first user of the calibrated model's response table may build it
def test_the_simulated_scan_of_two_bph_targets(tmp_path, default_model_cached):
    pytest.importorskip("cv2")
    pytest.importorskip("skimage")
    try:
        import rerun  # noqa: F401
        recording = True
    except ImportError:
        recording = False
    out = tmp_path / "validation"
    command = [str(PHANTOM), "scan", "validate", "--sim", "--out", str(out), "--targets",
               ",".join(f"{t:g}" for t in TARGETS_ML), "--views", str(VIEWS), "--scale", "0.25", "--voxel-mm", "0.6",
               "--settle-s", "0.05", "--target-views", "7", "--sim-speed", "2", "--json"]
    if not recording:
        command.append("--no-rerun")
    done = subprocess.run(command, capture_output=True, text=True, timeout=840)
    assert done.returncode == 0, done.stderr[-3000:]
    answer = json.loads(done.stdout)
    results = answer["targets"]
    assert [r["target_ml"] for r in results] == list(TARGETS_ML)
    for r in results:
        assert r["views"] == 2 * VIEWS and r["image_size"] == [320, 240]
        # the inverse reaches the target on the model, and the board holds its pressures
        assert r["model_ml"] == pytest.approx(r["target_ml"], rel=0.01)
        assert np.allclose(r["measured_pressures_kpa"], r["inverse_pressures_kpa"], atol=0.1)
        # the scanner's own error at this size: the visual hull of 12 small pictures, against the known truth
        assert abs(r["scan_vs_truth_pct"]) < 4.0
        assert r["truth_distance_mm"]["mean"] < 0.4
        assert r["model_distance_mm"]["mean"] < 1.0
        assert Path(r["heatmap"]).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
        assert len(json.loads((Path(r["capture"]) / "capture.json").read_text())["frames"]) == 2 * VIEWS
    small, large = results
    assert sum(large["inverse_pressures_kpa"]) > sum(small["inverse_pressures_kpa"]) + 1.0
    # the simulated phantom is the measured one: at the larger target it holds less than the controller's model
    # (the paper's Fig. 9: its scans below the simulation at the larger targets); this small scan's own error (its
    # visual hull over-reads by up to 4 %, above) is as large as that gap, so the scan is held to the truth instead
    assert large["true_ml"] < large["model_ml"] * 0.99
    report = Path(answer["report"]).read_text()
    assert "| 27 |" in report and "| 35 |" in report and "![Fig. 9](fig9.png)" in report
    assert (out / "fig9.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert json.loads((out / "results.json").read_text())["targets"] == results
    if recording:
        from phantom.host.recording import read_rrd

        entities = read_rrd(answer["recording"])
        assert len(entities["/scan/reconstruction"]["Mesh3D:vertex_positions"]) == len(TARGETS_ML)
        cameras = [name for name in entities if name.startswith("/scan/cameras/") and name.endswith("/picture")]
        assert len(cameras) == 2 * VIEWS
        # the model, aligned into the rig's frame, lies on the reconstruction: their surfaces' centroids (area
        # weighted: the model's graded mesh has its vertices densest near the chambers, which moved the mean of
        # its vertices 2 mm from the surface's centroid)
        model, scan = (surface_centroid_mm(entities[name]) for name in ("/scan/model", "/scan/reconstruction"))
        assert np.linalg.norm(model - scan) < 1.0, (model, scan)
