"""Another phantom as the simulated board's truth, end to end (issue 36's done-when line): ``phantom daemon --sim
--sim-truth SCENE --sim-truth-modulus-factor 0.9`` with the lobes' chambers scaled 1.1 instead of the controller's
1.2 and E x 0.9 reaches a verified 40 ml within 0.3 % of its TRUE volume through the Python API; and the truth's
shapes, built with its plant, are what the virtual camera photographs, without an FE solve per pressure state, and
the verify scan reads them within 0.2 % of the plant's gland volume.

The truth is a coarser mesh (10 mm, 10-node) than the controller's model (builtin:converged, 7 mm): its plant's
64 solves and 8 checks take minutes, once per machine (cached by the scene's content, the factor and the shipped
plant; the fixture builds it for the session when it is not cached)."""

import os
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from daemon_rig import daemon_process
from rounds_bench import verify_rounds
from truth_scan import SCANNER_TOLERANCE, verify_scan_ml

import phantom
import phantom.hil

PHANTOM = Path(sys.executable).with_name("phantom")

#: builtin:converged's material and mesh kind with the lobes' chambers scaled 1.1 (the controller's: 1.2), on a
#: 10 mm mesh (the file says why)
LOBES_1_1_SCENE = Path(phantom.hil.__file__).with_name("truths") / "lobes_1_1.toml"
MODULUS_FACTOR = 0.9
#: The daemon's verify scan as it reads this truth, the visual hull's error taken off (bench/scan_hull_bias.py: within
#: 0.027 % of it at make demo's states, ideal look; +0.04 to +0.24 % as scanned): no bias, 0.03 % of repeatability
THIS_SCANNER = ("--bias-pct", "0.0", "--noise-pct", "0.03")

# long: its truth's plant and shapes take 5-10 min to build on a cold cache and the verified target 10-25 min:
# `make test-long` runs it, `make test` does not (its 20-minute budget)
pytestmark = [pytest.mark.slow, pytest.mark.long]


@pytest.fixture(scope="module")
def lobes_truth():
    """The scene file and its truth plant (built with progress on stderr unless cached) and shapes."""
    from phantom.hil.plant import truth_plant_path, truth_shapes_path
    from phantom.model.cluster import stderr_progress

    scene = LOBES_1_1_SCENE
    plant = truth_plant_path(scene, MODULUS_FACTOR, progress=stderr_progress("the lobes-1.1 truth"))
    return scene, plant, truth_shapes_path(plant)


@pytest.mark.timeout(1800)
def test_the_truths_own_shapes_are_its_surface_without_a_solve(lobes_truth, caplog):
    """Read from the shapes built with the plant, off the grid and at an ADC count past the box's edge: no FE
    solve, the plant's gland volume, and the shape of the truth model's own full solve (in the worker)."""
    from phantom.hil.plant import load_plant
    from phantom.hil.truth_shape import TruthShape
    from phantom.model.mesh.surface import enclosed_volume_ml

    scene, plant_path, shapes_path = lobes_truth
    truth = TruthShape(scene, MODULUS_FACTOR, plant_path=plant_path, shapes_path=shapes_path)
    pressures_kpa = np.array([1.3, 0.4, 2.2])
    read = truth.surface(pressures_kpa)
    truth.surface([3.05, 3.05, 0.0])                       # the box's edge rippled past: still read
    assert truth.solves == 0
    assert enclosed_volume_ml(read) == pytest.approx(
        load_plant(plant_path).truth_gland_volume_ml(1e3 * pressures_kpa), rel=1e-9)
    solved = TruthShape(scene, MODULUS_FACTOR, plant_path=plant_path, tabulated=False).surface(pressures_kpa)
    # both scaled to the plant's volume: the shapes apart by less than the scanner's own mean error at 640x480
    # (0.08 mm), as the shipped truth's shapes are (test_truth_shape_reuse.py)
    off_mm = np.linalg.norm(read.vertices_mm - solved.vertices_mm, axis=1)
    assert off_mm.mean() < 0.08 and off_mm.max() < 0.3, (off_mm.mean(), off_mm.max())
    # another truth's shapes (the controller's scene's, another mesh and modulus) are refused, with why
    from phantom.model.scene import load_scene

    converged = load_scene("builtin:converged").model_settings.table_shapes
    other = TruthShape(scene, MODULUS_FACTOR, plant_path=plant_path, shapes_path=converged)
    assert other._shapes is None and "are not this truth's" in caplog.text


@pytest.mark.timeout(900)
@pytest.mark.parametrize("pressures_kpa", [[0.0, 0.0, 0.0], [0.794, 2.584, 2.584]], ids=["rest", "40ml"])
def test_the_verify_scan_reads_this_truths_volume(lobes_truth, tmp_path, pressures_kpa):
    """The daemon's verify scan of this truth, without the board: its virtual camera as ``phantom daemon
    --sim-truth`` makes it (the truth's shapes scaled to its plant's gland volume, the verify plan's poses), the
    capture loop, and the verify scan's reconstruction (tests/truth_scan.py); the volume read within 0.2 % of the
    plant's at rest and at the controller's pressures for 40 ml (measured: -0.10 % and +0.02 %). A run on an
    earlier build read this truth 1.2-1.5 % high in all four rounds (bench/README.md): a scanner that far off fails
    here, in a minute, not after 20 minutes of rounds."""
    pytest.importorskip("cv2")
    from phantom.hil.simulated_truth import SimulatedTruth

    scene, plant_path, shapes_path = lobes_truth
    truth = SimulatedTruth(scene, MODULUS_FACTOR, plant_path, shapes_path).shape()
    scanned_ml = verify_scan_ml(truth, pressures_kpa, tmp_path / "scan")
    true_ml = truth.plant.truth_gland_volume_ml(1e3 * np.array(pressures_kpa))
    assert scanned_ml == pytest.approx(true_ml, rel=SCANNER_TOLERANCE), (scanned_ml, true_ml)


@pytest.mark.sim
@pytest.mark.timeout(2700)
def test_another_phantom_reaches_a_verified_40_ml_in_true_volume(lobes_truth, tmp_path):
    """10-25 minutes on the loaded two-core machine (four to six rounds of 60 pictures at half speed; 24 minutes
    at load 12-14): not the 2 minutes asked for; the verify scan's plan is the daemon's
    (phantom/cli/scan_verify.py). Its last scan is stored (a correction's fit) before the daemon exits: the
    shutdown waits for it up to STORE_WAIT_S."""
    from phantom.host.service import STORE_WAIT_S

    pytest.importorskip("cv2")
    scene, _, _ = lobes_truth
    # half speed: the board's dead-host deadline and simavr's pace tolerate twice the stalls of a loaded machine (at
    # speed 1 and load 22-28 a scan aborted on a lost link in round 1 or 2 of three tries)
    with daemon_process(tmp_path, "--sim", "--sim-truth", str(scene), "--sim-truth-modulus-factor",
                        f"{MODULUS_FACTOR:g}", "--sim-speed", "0.5", ready_s=180, stop_s=STORE_WAIT_S + 60,
                        env={**os.environ, "PHANTOM_DATA_DIR": str(tmp_path / "data")}) as daemon:
        sock = daemon.socket
        started = time.monotonic()
        with phantom.connect(sock) as ph:
            # six rounds: the loop's corrections near 40 ml went 39.56, 40.21, 39.87, 40.09, then 39.95 ml scanned
            # in the sixth (2026-11-27), the default four would have ended at -0.32 %
            result = ph.set_volume(40.0, verify="scan", verify_rounds=6, timeout_s=2100)
        took_s = time.monotonic() - started
        rounds = result.rounds
        assert result.verified and abs(result.scanned_volume_ml - 40.0) <= 0.003 * 40.0, rounds
        # the phantom's true volume, which nothing in the loop sees, within 0.3 %
        assert abs(result.true_volume_ml - 40.0) <= 0.003 * 40.0, rounds
        # the controller's model alone misses this phantom by more than the tolerance: the rounds corrected it
        assert len(rounds) >= 2 and abs(rounds[0]["true_volume_ml"] - 40.0) > 0.003 * 40.0, rounds
        text = daemon.log()
        assert "the simulated phantom's plant:" in text and "simulated phantom's truth [" not in text  # cached
        print(f"verified 40 ml against the lobes-1.1, E x 0.9 truth in {took_s:.0f} s, {len(rounds)} rounds: "
              + "; ".join(f"{entry['scanned_volume_ml']:.3f} / {entry['true_volume_ml']:.3f} ml" for entry in rounds))


@pytest.mark.timeout(900)
def test_five_verified_then_five_auto_targets_on_this_truth_offline(lobes_truth, tmp_path):
    """Issue 48's --sim-truth line, offline (bench/verify_rounds.py: the daemon's corrected inverse, correction fit
    and verify policy, the truth's plant as the phantom, pressures held exactly, no simavr): from an empty store
    make demo's five volumes verified, then five others with verify="auto", the scanner as it reads this truth
    (the hull's error taken off: no bias, 0.03 % repeatability; bench/scan_hull_bias.py), four seeds. Every
    verified target within 0.3 % scanned and in true volume, in at most 3 rounds; every auto target within 0.5 %
    true (scanned when the correction's band is wider than the tolerance: after five targets it always is).
    Measured (2026-11-29, eight seeds): 2.05 rounds a verified target (the issue asks at most 2: not asserted,
    not met), auto targets 1.90, true errors at most 0.12 / 0.16 % (with the hull's error left in, +0.09 % of
    bias: 2.10 rounds, 0.19 / 0.25 %). About 20 s with the truth cached."""
    _, plant_path, _ = lobes_truth
    verified, auto, _ = verify_rounds(tmp_path, "--truth", str(plant_path), *THIS_SCANNER)
    assert len(verified) == 20 and len(auto) == 20
    for row in verified:
        assert abs(row["scanned_error_pct"]) <= 0.3 and abs(row["true_error_pct"]) <= 0.3, row
        assert 1 <= row["rounds"] <= 3, row
    assert all(abs(row["true_error_pct"]) <= 0.5 for row in auto), auto
    largest = [max(abs(row["true_error_pct"]) for row in rows) for rows in (verified, auto)]
    print(f"mean rounds {np.mean([row['rounds'] for row in verified]):.2f} verified, "
          f"{np.mean([row['rounds'] for row in auto]):.2f} auto; largest true error {largest[0]:.2f} / "
          f"{largest[1]:.2f} %")


@pytest.mark.timeout(900)
def test_after_a_36_point_characterisation_this_truths_targets_land_in_one_round_and_auto_needs_no_scan(
        lobes_truth, tmp_path):
    """tests/test_verify_rounds.py's line after `phantom characterise --path 36`, on this truth (its scanner with
    the hull's error taken off, four seeds): every verified target in one round within 0.3 % true, every
    verify="auto" target without a scan within 0.5 % true (measured, eight seeds: within 0.09 and 0.23 %; with the
    hull's error left in, 0.17 and 0.30 %)."""
    _, plant_path, _ = lobes_truth
    verified, auto, _ = verify_rounds(tmp_path, "--truth", str(plant_path), *THIS_SCANNER, "--path", "36")
    assert len(verified) == 20 and len(auto) == 20
    for row in verified:
        assert row["rounds"] == 1 and abs(row["true_error_pct"]) <= 0.3, row
    for row in auto:
        assert row["rounds"] == 0 and abs(row["true_error_pct"]) <= 0.5, row
