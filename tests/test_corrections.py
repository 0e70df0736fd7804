"""The measured volumes that correct a phantom's model (phantom.model.corrections, ``phantom corrections``): the
store survives restarts and kills, refuses bad input with why, exports what ``phantom calibrate`` reads; the
correction, a Gaussian process whose trend is chosen by leave-one-out, corrects the model away from the points
measured, knows where it does not know (its band), stays within its bound, and fits 200 measurements quickly."""

import json
import os
import re
import signal
import subprocess
import sys

import numpy as np
import pytest

from phantom.cli.main import main
from phantom.model.calibration.calibrate import load_measurements
from phantom.model.corrections import TRENDS, CorrectedModel, Correction, ModelGrid, fit_correction
from phantom.model.measurements import CorrectionError, CorrectionStore, Measurement


@pytest.fixture
def store(tmp_path, monkeypatch):
    monkeypatch.setenv("PHANTOM_DATA_DIR", str(tmp_path / "data"))
    return CorrectionStore.for_phantom("bench-phantom")


def test_the_store_keeps_measurements_across_a_restart_and_exports_what_calibrate_reads(store, tmp_path):
    assert store.entries() == []
    store.add(Measurement.now([1, 1, 1], 29.96, "scan", "scan_1.ply", "builtin:converged", 29.24))
    store.add(Measurement.now([2, 0, 0], 32.36, "water_displacement"))
    assert store.path == tmp_path / "data" / "corrections" / "bench-phantom.json"
    again = CorrectionStore.for_phantom("bench-phantom")          # a new process would see this
    entries = again.entries()
    assert [(e.pressures_kpa, e.volume_ml, e.method) for e in entries] == [
        ((1.0, 1.0, 1.0), 29.96, "scan"), ((2.0, 0.0, 0.0), 32.36, "water_displacement")]
    assert entries[0].scan_file == "scan_1.ply" and entries[0].model_volume_ml == 29.24 and entries[0].time_utc
    csv_path = tmp_path / "measured.csv"
    csv_path.write_text(again.to_csv() + "0,0,0,26.43,air,scan,,,\n")   # calibrate needs three rows
    measured = load_measurements(csv_path, 3)
    np.testing.assert_allclose(measured.pressures_pa[:2], [[1000, 1000, 1000], [2000, 0, 0]])
    np.testing.assert_allclose(measured.volumes_m3[:2] * 1e6, [29.96, 32.36])
    assert measured.media[:2] == ("air", "water")
    assert "method" in csv_path.read_text().splitlines()[0]
    assert again.clear() == 2 and again.entries() == []


@pytest.mark.parametrize(("make", "message"), [
    (lambda: Measurement((1.0, -0.5, 0.0), 30.0), "pressures must be finite numbers >= 0"),
    (lambda: Measurement((1.0, float("nan"), 0.0), 30.0), "pressures must be finite numbers >= 0"),
    (lambda: Measurement((1.0, 1.0, 1.0), float("inf")), "a measured volume (volume_ml) must be a whole gland's"),
    (lambda: Measurement((1.0, 1.0, 1.0), 0.0), "a measured volume (volume_ml) must be a whole gland's volume, a "
                                                "finite number of ml within 2-400 ml, got 0"),
    (lambda: Measurement((1.0, 1.0, 1.0), 30.0, "guess"), "method is one of scan, water_displacement"),
    (lambda: CorrectionStore.for_phantom("../etc/passwd"), "a phantom's name is 1-64 letters"),
])
def test_bad_measurements_and_names_are_refused(make, message):
    with pytest.raises(CorrectionError, match=re.escape(message)):
        make()


def test_a_damaged_store_is_refused_with_what_to_do_and_another_phantoms_point_is_not_mixed_in(store):
    store.add(Measurement.now([1, 1, 1], 30.0))
    with pytest.raises(CorrectionError, match="3 pressures, this one 4: is it another phantom"):
        store.add(Measurement.now([1, 1, 1, 1], 30.0))
    store.path.write_text('{"format": "phantom-corrections/1", "measurements": [{"pressures_kpa": [1, 1')
    with pytest.raises(CorrectionError, match="is damaged .*move it aside"):
        store.entries()
    with pytest.raises(CorrectionError, match="nothing to export"):
        CorrectionStore.for_phantom("empty").to_csv()


KILLER = """
import sys
from phantom.model.measurements import CorrectionStore, Measurement
store = CorrectionStore(sys.argv[1])
start = len(store.entries())
for number in range(start, 100000):
    store.add(Measurement.now([1, 1, 1], 30.0 + number * 1e-3))
    print(number + 1, flush=True)
"""


def test_the_store_survives_a_kill_in_the_middle_of_writing(tmp_path):
    """SIGKILL a writer many times mid-stream: the file is always whole, with every measurement it said it
    stored (atomic writes: a temporary file renamed over the store)."""
    path = tmp_path / "store.json"
    stored = 0
    for attempt in range(3):
        writer = subprocess.Popen([sys.executable, "-c", KILLER, str(path)], stdout=subprocess.PIPE, text=True)
        assert writer.stdout is not None
        said = 0
        while said < stored + 5 + 3 * attempt:
            said = int(writer.stdout.readline())
        os.kill(writer.pid, signal.SIGKILL)
        writer.wait()
        entries = CorrectionStore(path).entries()
        assert len(entries) >= said
        stored = len(entries)
        np.testing.assert_allclose([e.volume_ml for e in entries], 30.0 + np.arange(stored) * 1e-3)
    # a kill between the temporary file's creation and its rename leaves it; the next writer removes it
    CorrectionStore(path).add(Measurement.now([1, 1, 1], 30.0 + stored * 1e-3))
    assert len(CorrectionStore(path).entries()) == stored + 1
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".store")], "no temporary file left behind"


def _linear_grid(growth_ml_per_kpa=2.0, rest_ml=20.0):
    """A model whose chambers grow 2 ml/kPa each, on a 0.5 kPa grid over 0-3 kPa."""
    points = np.linspace(0, 3, 7)
    pressures = np.stack(np.meshgrid(points, points, points, indexing="ij"), -1)
    chamber = 2.0 + growth_ml_per_kpa * pressures
    gland = rest_ml + growth_ml_per_kpa * pressures.sum(axis=-1)
    return ModelGrid(points, chamber, gland, lambda p: float(rest_ml + growth_ml_per_kpa * np.sum(p)), "linear")


def offset_correction(offset_ml, chambers=3):
    """A correction that adds ``offset_ml`` everywhere (to about 1e-7 ml): one exact measurement at rest under a
    broad offset trend and a residual of no spread."""
    return Correction("gp+offset", 1, ((0.0,) * chambers,), (0.0,), (float(offset_ml),), (1e-4,), 1e-3,
                      (1.5,) * chambers, 0.0, 1e6, 1.0, float(offset_ml))


def test_a_stiffer_phantom_is_corrected_by_its_growth_and_the_inverse_then_hits_the_truth():
    """The truth grows 10 % less than the model and sits 0.3 ml higher, scanned with the scanner's noise: the
    growth trend wins the leave-one-out, the factor is found, and the corrected inverse meets the truth within the
    noise."""
    grid = _linear_grid()

    def truth(p):
        return 20.3 + 1.8 * float(np.sum(p))

    rng = np.random.default_rng(4)
    scanned = rng.uniform(0, 3, (12, 3))
    noise = 1 + 0.0012 * rng.standard_normal(len(scanned))
    correction = fit_correction([Measurement(tuple(p), truth(p) * n) for p, n in zip(scanned, noise, strict=True)],
                                grid)
    assert correction.kind == "gp+growth" and set(correction.leave_one_out_pct) == set(TRENDS)
    assert correction.leave_one_out_pct["gp+growth"] == min(correction.leave_one_out_pct.values()) < 0.2
    assert correction.growth_factor == pytest.approx(-0.1, abs=0.01)
    corrected = CorrectedModel(grid, correction)
    for p in rng.uniform(0, 3, (5, 3)):
        assert corrected.gland_ml(p) == pytest.approx(truth(p), rel=0.002)

    def inverse(volume_ml):  # the model's own inverse: equal pressures
        return np.full(3, (volume_ml - 20.0) / 6.0)

    pressures, volume, rounds = corrected.pressures_for_ml(35.0, inverse)
    assert truth(pressures) == pytest.approx(35.0, rel=0.002) and volume == pytest.approx(35.0, abs=1e-3)
    assert rounds <= 4
    with pytest.raises(CorrectionError, match="no measurements"):
        fit_correction([], grid)
    with pytest.raises(CorrectionError, match="unknown correction kinds"):
        fit_correction([Measurement((1.0, 1.0, 1.0), 26.5)], grid, ["field"])


def test_one_scan_corrects_near_it_returns_to_the_model_far_away_and_says_where_it_does_not_know():
    """One scan at 1 kPa each that reads 0.5 ml over the model: there the corrected volume is the scan's within
    its noise and the band is narrow; at the far corner of the box the correction is smaller and the band wide."""
    grid = _linear_grid()
    one = fit_correction([Measurement((1.0, 1.0, 1.0), 26.5)], grid)
    assert one.leave_one_out_pct == {} and one.count == 1
    corrected = CorrectedModel(grid, one)
    near, near_band = corrected.gland_band_ml((1.0, 1.0, 1.0))
    assert near == pytest.approx(26.5, abs=2 * 0.0012 * 26.5)
    far, far_band = corrected.gland_band_ml((3.0, 0.0, 3.0))
    assert abs(far - grid.gland_ml(np.array([3.0, 0.0, 3.0]))) < 0.5 and far_band > 2 * near_band
    assert one.bound_pct == pytest.approx((0.5 + 2 * 0.0012 * 26.5) / 26.0 * 100)
    assert one.size_ml(grid) <= one.bound_pct / 100 * 38.0


def test_the_correction_is_nowhere_larger_than_its_bound_even_from_scans_only_near_rest():
    """The old field, fitted to scans near rest, was "up to 23.9 ml over the pressure box" (make demo, issue
    48): the growth trend fitted to a steep miss near rest would extrapolate so. The bound: the largest measured
    miss plus twice its noise as a share of the model's volume there, nowhere exceeded (checked at 2000 random
    states and the grid's)."""
    grid = _linear_grid()
    scans = [Measurement((p, q, 0.0), 20.0 + 2.0 * (p + q) + 3.0 * (p + q)) for p in (0.0, 0.1, 0.2)
             for q in (0.0, 0.15)]
    correction = fit_correction(scans, grid)
    largest_pct = max((abs(s.volume_ml - grid.gland_ml(np.array(s.pressures_kpa))) + 2 * 0.0012 * s.volume_ml)
                      / grid.gland_ml(np.array(s.pressures_kpa)) * 100 for s in scans)
    assert correction.bound_pct == pytest.approx(largest_pct)
    states = np.random.default_rng(3).uniform(0, 3, (2000, 3))
    model = np.array([grid.gland_ml(p) for p in states])
    mean, deviation = correction.band_ml(states, model - 20.0)
    assert np.all(np.abs(mean) <= correction.bound_pct / 100 * model + 1e-12)
    assert np.max(np.abs(mean) / model) > 0.9 * correction.bound_pct / 100  # the trend reaches it: the clip holds
    assert correction.size_ml(grid) <= correction.bound_pct / 100 * 38.0 + 1e-12
    assert np.all(deviation >= 0)


@pytest.mark.slow
def test_a_bump_the_growth_cannot_follow_is_met_and_leave_one_out_chooses():
    grid = _linear_grid()

    def truth(p):  # chamber 0 softer past 1.5 kPa than any scale of the model's growth says
        return 20.0 + 2.0 * float(np.sum(p)) + 1.5 * max(p[0] - 1.5, 0.0) ** 2

    points = np.array(list(np.ndindex(3, 3, 3)), dtype=float) * 1.5
    correction = fit_correction([Measurement(tuple(p), truth(p)) for p in points], grid)
    assert correction.leave_one_out_pct[correction.kind] == min(correction.leave_one_out_pct.values())
    corrected = CorrectedModel(grid, correction)
    for p in points:  # within the scanner's noise of each measurement
        assert corrected.gland_ml(p) == pytest.approx(truth(p), rel=2 * 0.0012)
    rng = np.random.default_rng(5)
    held_out = rng.uniform(0, 3, (20, 3))
    errors = [abs(corrected.gland_ml(p) - truth(p)) / truth(p) * 100 for p in held_out]
    model_errors = [abs(grid.gland_ml(p) - truth(p)) / truth(p) * 100 for p in held_out]
    # 0.76 % against the model's 2.02 % (the old field's: 1.06 %); the bump between the scanned 1.5 and 3 kPa
    # is smoothed over
    assert np.mean(errors) < 0.5 * np.mean(model_errors)


def test_two_hundred_measurements_are_fitted_and_the_fit_is_read_back_the_same():
    """The issue's 128 stored measurements took the old field 130 s and kept the daemon from being ready; the
    process's fit of 200 is a fraction of a second (bench/correction_fit.py measures it; no timing asserted
    here): it is fitted, its leave-one-out is about the scanner's noise, and its document reads back the same."""
    grid = _linear_grid()
    rng = np.random.default_rng(8)
    states = rng.uniform(0, 3, (200, 3))
    scans = [Measurement(tuple(p), (20.3 + 1.8 * float(np.sum(p))) * (1 + 0.0012 * rng.standard_normal()))
             for p in states]
    correction = fit_correction(scans, grid)
    assert correction.count == 200 and correction.leave_one_out_pct[correction.kind] < 0.15
    again = Correction.from_document(json.loads(json.dumps(correction.to_document())))
    assert again == correction
    assert again.band_ml(states[:5], np.zeros(5))[0] == pytest.approx(correction.band_ml(states[:5], np.zeros(5))[0])


@pytest.mark.slow
def test_table_one_scanned_corrects_the_model_towards_the_simulated_phantom():
    """The eight Table I points stored as scans of the shipped simulated phantom (its truth passes through
    them): the trends' leave-one-out is reported, the chosen the least, and the error at held-out points measured
    against the truth. Figures (2026-11-28): 2.69 % uncorrected; leave-one-out (8 irregular points leave each other
    out badly) picks gp+offset (4.1 %; gp 4.1, gp+growth 4.9), 1.97 % held out; gp+growth 1.12 % (the old field:
    1.24 %)."""
    from phantom.hil.plant import MEASURED_VOLUMES_PATH, load_plant
    from phantom.hil.truth_residual import trilinear
    from phantom.model import PhantomModel, load_scene
    from phantom.model.corrections import model_grid
    from phantom.model.fidelity.levels import VolumeEstimator

    plant = load_plant()
    rows = np.loadtxt(MEASURED_VOLUMES_PATH, delimiter=",", comments="#", skiprows=4)
    grid = model_grid(VolumeEstimator(PhantomModel.from_scene(load_scene("builtin:converged")), level="table"))
    scans = [Measurement(tuple(row[:3]), row[3]) for row in rows]
    chosen = fit_correction(scans, grid)
    assert set(chosen.leave_one_out_pct) == set(TRENDS)
    assert chosen.leave_one_out_pct[chosen.kind] == min(chosen.leave_one_out_pct.values())
    held_out = np.random.default_rng(1).uniform(0, 3, (30, 3))
    truth = np.array([plant.truth_gland_volume_ml(1e3 * p) for p in held_out])

    def mean_error_pct(model):
        return float(np.mean([abs(model(p) - t) / t * 100 for p, t in zip(held_out, truth, strict=True)]))

    uncorrected = mean_error_pct(grid.gland_ml)
    corrected = CorrectedModel(grid, chosen)
    assert mean_error_pct(corrected.gland_ml) < uncorrected
    assert mean_error_pct(CorrectedModel(grid, fit_correction(scans, grid, ["gp+growth"])).gland_ml) < 0.5 * uncorrected
    for row in rows:  # through the eight points themselves, within the noise
        assert corrected.gland_ml(row[:3]) == pytest.approx(row[3], rel=3 * 0.0012)
    assert float(trilinear(plant.truth_gland_volume_m3 * 1e6, np.arange(4.0), rows[2, :3])) == pytest.approx(34.80,
                                                                                                        abs=0.005)


def test_the_command_line_lists_adds_exports_and_clears(store, tmp_path, capsys):
    assert main(["corrections", "add", "--phantom", "bench-phantom", "--pressures-kpa", "1,1,1",
                 "--volume-ml", "29.96"]) == 0
    assert main(["corrections", "list", "--phantom", "bench-phantom"]) == 0
    assert "1.000, 1.000, 1.000 kPa  29.960 ml (water_displacement)" in capsys.readouterr().out
    out = tmp_path / "exported.csv"
    assert main(["corrections", "export", "--phantom", "bench-phantom", "--out", str(out)]) == 0
    assert out.read_text().startswith("p0_kpa,p1_kpa,p2_kpa,measured_ml,medium,method")
    assert main(["corrections", "clear", "--phantom", "bench-phantom"]) == 0
    assert "1 measurement(s) of phantom 'bench-phantom' would be removed: add --yes" in capsys.readouterr().out
    assert len(store.entries()) == 1
    assert main(["corrections", "clear", "--phantom", "bench-phantom", "--yes"]) == 0
    assert store.entries() == []
    assert main(["corrections", "add", "--pressures-kpa", "1,1", "--volume-ml", "-3"]) == 2
    assert "--volume-ml (the measured gland volume) must be a whole gland's volume, a finite number of ml within " \
           "2-400 ml, got " \
           "-3.0" in capsys.readouterr().err


@pytest.mark.slow
def test_corrections_fit_reports_each_trends_leave_one_out_the_hyperparameters_and_the_band(store, capsys):
    for pressures, volume in (((1, 1, 1), 29.96), ((2, 0, 0), 32.36), ((0, 0, 2), 31.20)):
        store.add(Measurement.now(pressures, volume))
    assert main(["corrections", "fit", "--phantom", "bench-phantom"]) == 0
    out = capsys.readouterr().out
    assert "3 measurement(s) of phantom 'bench-phantom'; the model builtin:converged misses them by" in out
    assert "leave-one-out (mean abs error of the volume left out): gp " in out and "gp+growth " in out
    assert "a Gaussian process: amplitude" in out and "length scales" in out and "bound" in out
    assert "at the measured pressures (kPa): measured, model, corrected +- its 95 % band (ml)" in out
    assert "  1.000, 1.000, 1.000: 29.960, " in out and out.count(" +- ") == 4
    assert main(["corrections", "fit", "--phantom", "nobody"]) == 2
    assert "no measurements to correct the model with: scan the phantom first" in capsys.readouterr().err
    store.add(Measurement.now((1, 1, 1), 30.5))  # the same state read 0.54 ml more: the white noise takes it
    assert main(["corrections", "fit", "--phantom", "bench-phantom", "--json"]) == 0
    fitted = json.loads(capsys.readouterr().out)
    assert fitted["white_noise_ml"] > 0.1 and len(fitted["band_at_measured"]) == 4


def test_a_fit_is_kept_in_the_cache_and_read_back_the_same_and_a_damaged_one_is_fitted_again(tmp_path, monkeypatch):
    """A daemon started again with many stored scans reads its fit back instead of fitting again."""
    from phantom.model.corrections import cached_fit

    monkeypatch.setenv("PHANTOM_CACHE_DIR", str(tmp_path / "cache"))
    points = np.array([0.0, 1.5, 3.0])
    chamber = np.stack(np.meshgrid(points, points, points, indexing="ij"), -1) + 2.0
    gland = 26.0 + 2.0 * chamber.sum(-1)
    grid = ModelGrid(points, chamber, gland, lambda p: 26.0 + 2.0 * float(np.sum(np.asarray(p) + 2.0)))
    scans = [Measurement((0.0, 0.0, 0.0), 38.2), Measurement((1.0, 0.0, 0.0), 40.6),
             Measurement((0.0, 2.0, 1.0), 45.5)]
    fitted = cached_fit(scans, grid)
    [stored] = (tmp_path / "cache" / "corrections").iterdir()
    again = cached_fit(scans, grid)
    assert again.to_document() == fitted.to_document() and again.kind == fitted.kind
    assert again.residual_ml((0.5, 1.0, 2.0), 3.0) == fitted.residual_ml((0.5, 1.0, 2.0), 3.0)
    stored.write_text("{damaged")
    assert cached_fit(scans, grid).to_document() == fitted.to_document()
    assert json.loads(stored.read_text())["kind"] == fitted.kind
    assert cached_fit(scans[:2], grid).count == 2  # other measurements: another entry


def test_a_scan_held_a_count_above_the_box_is_a_measurement_on_its_edge_and_one_beyond_is_refused():
    """A chamber held at 3 kPa reads 3.01 on average: its measurement fits the truth plant's field as one at 3 kPa,
    and the correction's process as one at 3 kPa too; 3.5 kPa is refused by both."""
    from phantom.hil.truth_residual import smoothest_residual

    grid = _linear_grid()
    edge = smoothest_residual(grid.points_kpa, grid.chamber_ml, grid.gland_grid_ml, [[3.01, 0.0, 1.5]], [0.4])
    at_three = smoothest_residual(grid.points_kpa, grid.chamber_ml, grid.gland_grid_ml, [[3.0, 0.0, 1.5]], [0.4])
    assert edge.gland_at_ml([3.0, 0.0, 1.5]) == pytest.approx(0.4, abs=1e-3)
    assert np.allclose(edge.gland_ml, at_three.gland_ml)
    with pytest.raises(CorrectionError, match="must lie on the grid"):
        smoothest_residual(grid.points_kpa, grid.chamber_ml, grid.gland_grid_ml, [[3.5, 0.0, 1.5]], [0.4])
    edge_fit = fit_correction([Measurement((3.01, 0.0, 1.5), 29.4)], grid)
    assert edge_fit.pressures_kpa == ((3.0, 0.0, 1.5),)
    with pytest.raises(CorrectionError, match="must lie on the grid"):
        fit_correction([Measurement((3.5, 0.0, 1.5), 29.4)], grid)


def test_a_target_inside_the_models_range_but_beyond_the_corrected_one_is_unreachable_with_the_corrected_range():
    """make demo's 26.5 ml: one scan near rest read 0.5 ml over the model, the offset it fitted put the corrected
    rest above 26.5 ml, and the corrected inverse searched the model's range for 30 rounds and failed as the model's
    fault. Refused by the corrected model itself (every caller, the daemon, the CLI and the bench, gets it) as
    unreachable with the corrected range, in the words the daemon's verify loop reads to ask the range's edge; the
    edge itself is met; beyond the model's own top too. Both are asked of no inverse."""
    import pickle
    import re

    from phantom.model.target import UnreachableTargetError

    grid = _linear_grid()
    corrected = CorrectedModel(grid, offset_correction(1.5))
    assert corrected.range_ml == pytest.approx((21.5, 39.5))
    asked = []

    def inverse(volume_ml):
        asked.append(volume_ml)
        return np.full(3, (volume_ml - 20.0) / 6.0)

    for target_ml in (20.5, 39.6):  # inside the model's 20-38 ml, beyond the corrected 21.5-39.5; beyond both
        with pytest.raises(UnreachableTargetError, match=r"beyond the model's range with the correction in force "
                           r"\(gp\+offset from 1 measurement\(s\)\): give 21.500 to 39.500 ml") as raised:
            corrected.pressures_for_ml(target_ml, inverse)
        # the range as data, which crosses from the model worker's process with the error
        crossed = pickle.loads(pickle.dumps(raised.value))
        assert crossed.gland_range_ml == pytest.approx((21.5, 39.5)) and crossed.corrected
        assert str(crossed) == str(raised.value)
        assert not re.search("is the model's", str(raised.value))  # the range given is the corrected one
    assert asked == []
    pressures, volume, _ = corrected.pressures_for_ml(21.55, inverse)
    assert volume == pytest.approx(21.55, abs=1e-3) and np.sum(pressures) * 2.0 == pytest.approx(0.05, abs=1e-3)
    # the corrected top (39.5 ml) is past the model's (38 ml): the inverse is asked only within the model's range
    pressures, volume, _ = corrected.pressures_for_ml(39.5, inverse)
    assert volume == pytest.approx(39.5, abs=1e-3) and max(asked) <= 38.0


def test_the_pressure_box_takes_a_reading_a_count_outside_as_its_edge_and_refuses_one_further_or_not_finite():
    """One check of a measurement's pressures against the model's box, for the field's fit and the daemon's store:
    0.1 kPa outside the box is on its edge (clipped to it), further or NaN is refused with the values."""
    from phantom.model.corrections import pressures_in_box

    assert pressures_in_box([-0.004, 3.0005, 1.2], 3.0).tolist() == [0.0, 3.0, 1.2]
    for bad in ([-0.3, 1.0, 1.0], [1.0, 3.2, 1.0], [float("nan"), 1.0, 1.0]):
        with pytest.raises(CorrectionError, match=r"a scan's pressures must lie on the grid, 0-3 kPa, the model's "
                           r"pressure box \(0.1 kPa outside it is on its edge\), got \["):
            pressures_in_box(bad, 3.0, "a scan's pressures")


def test_scans_that_disagree_between_close_states_take_the_white_noise_not_a_wiggle():
    """Two scans 0.05 kPa apart whose volumes disagree by 0.1 ml (a chamber that shrinks as it is inflated): the
    field needed a soft growth floor to pass through them at all. The process takes the disagreement as noise:
    its mean between them is neither, and a state further away is not bent by it."""
    grid = _linear_grid()
    rng = np.random.default_rng(7)
    points = [*rng.uniform(0, 3, (6, 3)), (1.0, 1.0, 1.0), (1.05, 1.0, 1.0)]
    volumes = [20.3 + 1.8 * float(np.sum(p)) for p in points]
    volumes[-1] = volumes[-2] - 0.1
    correction = fit_correction([Measurement(tuple(p), v) for p, v in zip(points, volumes, strict=True)], grid)
    corrected = CorrectedModel(grid, correction)
    assert volumes[-1] - 0.01 < corrected.gland_ml(np.array([1.025, 1.0, 1.0])) < volumes[-2] + 0.01
    assert corrected.gland_ml(np.array([2.0, 2.0, 2.0])) == pytest.approx(20.3 + 1.8 * 6, abs=0.1)


def test_the_corrected_inverse_asks_the_model_only_for_volumes_it_reaches():
    """A phantom growing three times as fast as the model: the first secant step from a target just above rest
    asked the model's inverse for less than its rest (which it refuses); it is kept at the rest and goes on."""
    grid = _linear_grid()
    correction = fit_correction([Measurement((p, p, p), 20.0 + 18.0 * p) for p in (0.0, 1.0, 2.0)], grid,
                                ["gp+growth"])
    assert correction.growth_factor == pytest.approx(2.0, abs=0.05)

    def inverse(volume_ml):
        if not 20.0 <= volume_ml <= 38.0:
            raise CorrectionError(f"{volume_ml} ml is unreachable")
        return np.full(3, (volume_ml - 20.0) / 6.0)

    pressures, volume, _ = CorrectedModel(grid, correction).pressures_for_ml(21.0, inverse)
    assert volume == pytest.approx(21.0, abs=1e-3) and np.sum(pressures) * 6.0 == pytest.approx(1.0, abs=0.05)


@pytest.mark.slow
def test_scans_along_the_inverses_path_put_unscanned_targets_within_half_a_percent_of_the_truth():
    """The issue's "after `phantom characterise`, targets across the reachable range, not scanned before, land
    within 0.5 % of the true volume on the first round", offline: the shipped simulated phantom's true volumes at
    the states of `--path 19`, read 0.1 % low with 0.05 % of noise (about the scanner's own, bench/README.md
    "Scanner"), the correction the daemon fits to them, and seven targets each halfway between two scans' true
    volumes, set by the corrected inverse: their true volumes. Before: no field passed through these scans (the
    field's hard growth floor: the truth grows a quarter of the model's in places), and the 27 states of the grid 0,
    1.5, 3 kPa missed by up to 2.8 % (bench/README.md, "Characterisation"). Measured 2026-11-27: worst 0.22 %."""
    from phantom.hil.plant import load_plant
    from phantom.model import PhantomModel, load_scene
    from phantom.model.corrections import model_grid
    from phantom.model.inverse import InverseSolver
    from phantom.model.target import Target
    from phantom.scan.characterise import path_design

    plant = load_plant()
    solver = InverseSolver(PhantomModel.from_scene(load_scene("builtin:converged")))
    grid = model_grid(solver.estimator)

    def inverse(volume_ml):
        return np.asarray(solver.pressures_for(Target(gland_volume_m3=volume_ml * 1e-6)).pressures_pa) / 1e3

    def true_ml(pressures_kpa):
        return plant.truth_gland_volume_ml(np.asarray(pressures_kpa) * 1e3)

    design = path_design(19, inverse, grid.gland_ml(np.zeros(3)), grid.gland_ml(np.full(3, 3.0)))
    truths = np.array([true_ml(p) for p in design])
    scanned = truths * (0.999 + 0.0005 * np.random.default_rng(0).standard_normal(len(design)))
    correction = fit_correction([Measurement(tuple(p), v) for p, v in zip(design, scanned, strict=True)], grid)
    corrected = CorrectedModel(grid, correction)
    for first in (0, 3, 6, 9, 12, 15, 17):  # rest to the top
        target = float(truths[first:first + 2].mean())
        pressures, _, _ = corrected.pressures_for_ml(target, inverse)
        assert np.min(np.abs(design - pressures).max(axis=1)) > 0.03, "the target is not a scanned state"
        assert true_ml(pressures) == pytest.approx(target, rel=0.005)


def _a_jump_at_30_ml():
    """A corrected model and an inverse whose path turns to another branch at 30 ml (only the lobes, then all
    three chambers) where the correction (0.5 ml per kPa of chamber 0, measured by water displacement on a grid)
    differs between the two: the corrected volume along the path jumps by about 0.8 ml there."""
    grid = _linear_grid()
    states = np.array(list(np.ndindex(4, 4, 4)), dtype=float)
    correction = fit_correction([Measurement(tuple(p), grid.gland_ml(p) + 0.5 * p[0], "water_displacement")
                                 for p in states], grid, ["gp"])

    def inverse(volume_ml):
        if volume_ml < 30.0:
            return np.array([0.0, *[(volume_ml - 20.0) / 4.0] * 2])
        return np.full(3, (volume_ml - 20.0) / 6.0)

    return CorrectedModel(grid, correction), inverse


def test_a_target_in_a_jump_of_the_corrected_volume_along_the_inverses_path_gets_the_nearer_side_and_says_so():
    """The model's inverse turns to another branch at 30 ml (only the lobes, then all three chambers), and the
    correction (0.5 ml per kPa of chamber 0, measured by water displacement on a grid) differs between them: the
    corrected volume jumps by about 0.8 ml there, and no pressures give 30.5 ml. The answer is the nearer side,
    with its own corrected volume (before: the secant crawled at the jump and the target was refused as
    unreachable)."""
    corrected, inverse = _a_jump_at_30_ml()
    pressures, volume, _ = corrected.pressures_for_ml(30.5, inverse)
    assert volume == pytest.approx(corrected.gland_ml(pressures), abs=1e-9)
    assert abs(volume - 30.5) > 0.2 and pressures[0] in (0.0, pytest.approx(10 / 6, abs=0.05))
    assert corrected.pressures_for_ml(29.5, inverse)[1] == pytest.approx(29.5, abs=1e-3)


def test_a_target_a_hair_above_the_low_side_of_a_jump_is_not_refused_as_the_edge_of_the_range():
    """As above, but 30 ml asked of the corrected model after make demo's scans at 26.5 ml (bench/verify_rounds.py,
    the correction of no trend): the target was 1.4 ul above the low side of a 0.3 ml jump, so each false-position
    step moved a few thousandths of the bracket, and after 30 rounds a verify round was refused as "the target is
    at the edge of what the phantom reaches" in the middle of the range. The bracket is now halved while its
    slope is steeper than a correction can make it (a jump inside): the nearer side, in a few rounds."""
    corrected, inverse = _a_jump_at_30_ml()
    low_side_ml = corrected.gland_ml(inverse(30.0 - 1e-12))
    assert corrected.gland_ml(inverse(30.0)) - low_side_ml > 0.3       # the jump
    pressures, volume, rounds = corrected.pressures_for_ml(low_side_ml + 0.0015, inverse)
    assert volume == pytest.approx(low_side_ml, abs=1e-3) and pressures[0] == 0.0
    assert rounds <= 20


def test_two_scans_that_agree_on_a_residual_are_met_by_the_process_alone():
    """Two scans of one target's rounds, 0.1 kPa apart, both 0.6 ml over the model and within 0.01 ml of each
    other: the process without a trend (fitted on its starting hyperparameters below three measurements) passes
    within the scanner's noise of both. Its amplitude started at the residuals' spread (0.005 ml) left them
    unrepresented: the corrected model stayed near the model's own, and the verify loop's next round near rest
    moved by the whole residual (bench/verify_rounds.py)."""
    grid = _linear_grid()
    scans = [Measurement((0.1, 0.1, 0.1), grid.gland_ml(np.full(3, 0.1)) + 0.60),
             Measurement((0.2, 0.1, 0.1), grid.gland_ml(np.array([0.2, 0.1, 0.1])) + 0.61)]
    corrected = CorrectedModel(grid, fit_correction(scans, grid, kinds=("gp",)))
    for scan in scans:
        assert corrected.gland_ml(scan.pressures_kpa) == pytest.approx(scan.volume_ml, rel=2 * 0.0012)


def test_the_band_between_two_clusters_of_scans_assumes_no_smoother_a_residual_than_a_kpa():
    """Five verified targets' rounds are five clusters of scans; the marginal likelihood then takes the residual
    as smooth over 1.6-2.6 kPa, and verify="auto" was sure (band within 0.3 %) between clusters where the shipped
    truth kinks, 0.65-1.51 % off (bench/verify_rounds.py --auto). The band's length scales are at most
    BAND_LENGTH_SCALE_MAX_KPA; the mean keeps the fitted ones, and at a scan the band is the scan's noise."""
    from dataclasses import replace

    from phantom.model.corrections import BAND_LENGTH_SCALE_MAX_KPA

    grid = _linear_grid()
    clusters = [((0.5, 1.0, 1.0), 0.4), ((0.6, 1.05, 1.05), 0.41), ((1.0, 2.2, 2.2), -0.3), ((1.05, 2.25, 2.25), -0.29)]
    correction = fit_correction([Measurement(p, grid.gland_ml(np.asarray(p)) + r) for p, r in clusters], grid)
    smooth = replace(correction, length_scales_kpa=(2.6, 2.6, 2.6))     # what the likelihood took after the demo
    assert BAND_LENGTH_SCALE_MAX_KPA == 1.0
    between = np.array([0.8, 1.6, 1.6])
    _, band_smooth = CorrectedModel(grid, smooth).gland_band_ml(between)
    trusting = replace(smooth, length_scales_kpa=(2.6, 2.6, 2.6))
    object.__setattr__(trusting, "_for_band", trusting._fitted)          # the band on the fitted scales, as before
    _, band_before = CorrectedModel(grid, trusting).gland_band_ml(between)
    assert band_smooth > 3 * band_before
    mean_now, _ = smooth.band_ml(between[None], [grid.gland_ml(between) - 20.0])
    mean_before, _ = trusting.band_ml(between[None], [grid.gland_ml(between) - 20.0])
    assert mean_now == pytest.approx(mean_before)                         # the mean is the fitted process's
    _, at_scan = CorrectedModel(grid, smooth).gland_band_ml(np.array(clusters[0][0]))
    assert at_scan < 2.5 * 0.0012 * grid.gland_ml(np.array(clusters[0][0]))


def test_two_scans_at_the_same_pressures_that_disagree_widen_the_band_there_by_their_disagreement():
    """35 and 39 ml measured at the same pressures, passed straight to fit_correction (the command line and the
    daemon hold the second unconfirmed; a library user need not): below three measurements the white noise was not
    fitted, and the band there was +-0.06 ml, as if the scanner alone erred. Their disagreement is now the white
    noise's floor: the band is at least half their difference. Scans that agree, and scans at different
    pressures, keep the fit they had (the verify loop's numbers come from it)."""
    grid = _linear_grid()
    at = (1.0, 1.0, 1.0)
    correction = fit_correction([Measurement(at, 35.0), Measurement(at, 39.0)], grid)
    _, band_ml = CorrectedModel(grid, correction).gland_band_ml(np.array(at))
    assert band_ml >= 0.5 * (39.0 - 35.0), band_ml
    assert correction.white_noise_ml == pytest.approx(np.sqrt(0.5 * 4.0 ** 2), rel=0.01)
    # replicates the scanner's own noise explains leave the white noise at its bound: no floor
    agreeing = fit_correction([Measurement(at, 30.00), Measurement(at, 30.02)], grid)
    assert agreeing.white_noise_ml == pytest.approx(1e-4)
    # a third scan elsewhere: the fitted white noise is no less than the replicates' disagreement either
    three = fit_correction([Measurement(at, 35.0), Measurement(at, 39.0), Measurement((2.0, 0.0, 0.0), 25.0)], grid)
    assert CorrectedModel(grid, three).gland_band_ml(np.array(at))[1] >= 0.5 * (39.0 - 35.0)
