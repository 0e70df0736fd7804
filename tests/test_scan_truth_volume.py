"""The verify scan reads the shipped simulated phantom's true volume: its virtual camera as the daemon makes it,
the capture loop and the verify scan's reconstruction, at the controller's pressures for 40 ml (the most deformed
state a verified target of the BPH scene holds), within 0.2 % of the plant's gland volume (measured +0.12 %;
the verified target's tolerance is 0.3 %). Another phantom's truth: tests/test_sim_truth_verify.py (``long``: its
plant is built first)."""

import numpy as np
import pytest
from truth_scan import SCANNER_TOLERANCE, verify_scan_ml


@pytest.mark.slow
def test_the_verify_scan_reads_the_shipped_truths_volume(tmp_path):
    pytest.importorskip("cv2")
    from phantom.hil.simulated_truth import SimulatedTruth

    truth = SimulatedTruth().shape()
    pressures_kpa = [0.794, 2.584, 2.584]
    scanned_ml = verify_scan_ml(truth, pressures_kpa, tmp_path / "scan")
    true_ml = truth.plant.truth_gland_volume_ml(1e3 * np.array(pressures_kpa))
    assert scanned_ml == pytest.approx(true_ml, rel=SCANNER_TOLERANCE), (scanned_ml, true_ml)
