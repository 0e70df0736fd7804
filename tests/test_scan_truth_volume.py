"""The verify scan reads the shipped simulated phantom's true volume: its virtual camera as the daemon makes it,
the capture loop and the verify scan's reconstruction, at the controller's pressures for 40 ml (the most deformed
state a verified target of the BPH scene holds), within 0.2 % of the plant's gland volume (measured +0.12 %;
the verified target's tolerance is 0.3 %). Another phantom's truth: tests/test_sim_truth_verify.py (``long``: its
plant is built first)."""

import numpy as np
import pytest
from truth_scan import SCANNER_TOLERANCE, verify_scan, verify_scan_ml


@pytest.mark.slow
def test_the_verify_scan_reads_the_shipped_truths_volume(tmp_path):
    pytest.importorskip("cv2")
    from phantom.hil.simulated_truth import SimulatedTruth

    truth = SimulatedTruth().shape()
    pressures_kpa = [0.794, 2.584, 2.584]
    scanned_ml = verify_scan_ml(truth, pressures_kpa, tmp_path / "scan")
    true_ml = truth.plant.truth_gland_volume_ml(1e3 * np.array(pressures_kpa))
    assert scanned_ml == pytest.approx(true_ml, rel=SCANNER_TOLERANCE), (scanned_ml, true_ml)


@pytest.mark.slow
def test_the_hulls_error_on_the_models_shape_taken_off_leaves_a_third_of_it(tmp_path):
    """At the controller's pressures for 45 ml, the hull reads the shipped truth +0.17 % high (its folds); the
    same error read on the model's shape there (phantom.scan.hull_bias) and taken off leaves at most 0.06 %."""
    pytest.importorskip("cv2")
    from phantom.hil.plant import CALIBRATED_SCENE_PATH
    from phantom.hil.simulated_truth import SimulatedTruth
    from phantom.hil.truth_shape import TruthShape

    truth = SimulatedTruth().shape()
    pressures_kpa = [2.157, 2.945, 2.945]
    model = TruthShape(CALIBRATED_SCENE_PATH, 1.0, plant_path=None).surface(pressures_kpa)  # the model's own shape
    answer = verify_scan(truth, pressures_kpa, tmp_path / "scan", (model.vertices_mm, model.triangles))
    true_ml = truth.plant.truth_gland_volume_ml(1e3 * np.array(pressures_kpa))
    raw_pct, corrected_pct = (100 * (answer[key] / true_ml - 1) for key in ("scanned_raw_ml", "volume_ml"))
    assert raw_pct > 0.12, raw_pct
    assert abs(corrected_pct) < 0.06 and abs(corrected_pct) < raw_pct / 3, (raw_pct, corrected_pct)
