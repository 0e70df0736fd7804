"""A verified target's rounds offline on the shipped simulated phantom (bench/verify_rounds.py: the daemon's
corrected inverse, correction fit, judging of each scan and verify policy; the phantom's truth table read with the
verify scan's bias by volume, the visual hull's error taken off as the daemon does (bench/scan_hull_bias.py), and
0.03 % of repeatability; pressures held exactly; no simavr). ``tests/test_sim_truth_verify.py`` runs the same on
another phantom."""

import numpy as np
import pytest
from rounds_bench import verify_rounds

pytestmark = pytest.mark.slow

#: the daemon's verify scan: its bias by volume and 0.03 % of repeatability
SCANNER = ("--bias-by-volume", "--noise-pct", "0.03")


def test_from_an_empty_store_every_verified_target_ends_within_the_tolerance_in_true_volume(tmp_path):
    """make demo's five volumes, four seeds: every one verified within 0.3 % scanned and in true volume, in at most
    4 rounds, and no scan held out as implausible. Measured (2026-11-29, eight seeds): 2.62 rounds a target, the
    issue's 2 not met (round 1 misses by the model's 1.3-2.6 %, round 2 lands within the 0.6 of the tolerance
    aimed at only where the phantom grows per ml as the corrected model says), largest true error 0.19 %."""
    verified, _, printed = verify_rounds(tmp_path, *SCANNER)
    assert len(verified) == 20
    for row in verified:
        assert abs(row["scanned_error_pct"]) <= 0.3 and abs(row["true_error_pct"]) <= 0.3, row
        assert 1 <= row["rounds"] <= 4, row
    assert "; 0 scans stored unconfirmed" in printed, printed
    print(f"mean rounds {np.mean([row['rounds'] for row in verified]):.2f}")


def test_after_a_36_point_characterisation_every_target_lands_in_one_round_and_auto_needs_no_scan(tmp_path):
    """Issue 48's line after `phantom characterise`: with the store of `phantom characterise --path 36` (its states
    scanned with the same scanner), every verified target verified on its first scan within 0.3 % true, and
    every verify="auto" target reached without a scan within 0.5 % true (measured: within 0.15 %, the verified
    within 0.23 %; before the hull's error was taken off, 30 points left 8 of 40 auto targets of eight seeds
    scanned, 19 points 1.40 rounds a verified target)."""
    verified, auto, printed = verify_rounds(tmp_path, *SCANNER, "--path", "36")
    assert len(verified) == 20 and len(auto) == 20
    for row in verified:
        assert row["rounds"] == 1 and abs(row["true_error_pct"]) <= 0.3, row
    for row in auto:
        assert row["rounds"] == 0 and abs(row["true_error_pct"]) <= 0.5, row
    assert "; 0 scans stored unconfirmed" in printed, printed
