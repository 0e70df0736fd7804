"""The measured volumes that correct a phantom's model (phantom.model.corrections, ``phantom corrections``): the
store survives restarts and kills, refuses bad input with why, exports what ``phantom calibrate`` reads; the
correction is chosen by leave-one-out and corrects the model away from the points measured."""

import json
import os
import signal
import subprocess
import sys

import numpy as np
import pytest

from phantom.cli.main import main
from phantom.model.calibration.calibrate import load_measurements
from phantom.model.corrections import CorrectedModel, Correction, ModelGrid, fit_correction, trilinear
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
    (lambda: Measurement((1.0, 1.0, 1.0), float("inf")), "measured volume must be a finite number"),
    (lambda: Measurement((1.0, 1.0, 1.0), 0.0), "measured volume must be a finite number of ml above 0"),
    (lambda: Measurement((1.0, 1.0, 1.0), 30.0, "guess"), "method is one of scan, water_displacement"),
    (lambda: CorrectionStore.for_phantom("../etc/passwd"), "a phantom's name is 1-64 letters"),
])
def test_bad_measurements_and_names_are_refused(make, message):
    with pytest.raises(CorrectionError, match=message):
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


@pytest.mark.slow
def test_a_stiffer_phantom_is_corrected_by_its_growth_and_the_inverse_then_hits_the_truth():
    """The truth grows 10 % less than the model and sits 0.3 ml higher: the growth correction wins the
    leave-one-out and is exact everywhere; the corrected inverse meets the truth."""
    grid = _linear_grid()

    def truth(p):
        return 20.3 + 1.8 * float(np.sum(p))

    rng = np.random.default_rng(4)
    scanned = rng.uniform(0, 3, (6, 3))
    correction = fit_correction([Measurement(tuple(p), truth(p)) for p in scanned], grid)
    assert correction.kind == "growth"
    assert correction.leave_one_out_pct["growth"] < 1e-6 < correction.leave_one_out_pct["offset"]
    assert correction.growth_factor == pytest.approx(-0.1) and correction.offset_ml == pytest.approx(0.3)
    corrected = CorrectedModel(grid, correction)
    for p in rng.uniform(0, 3, (5, 3)):
        assert corrected.gland_ml(p) == pytest.approx(truth(p), rel=1e-9)

    def inverse(volume_ml):  # the model's own inverse: equal pressures
        return np.full(3, (volume_ml - 20.0) / 6.0)

    pressures, volume, rounds = corrected.pressures_for_ml(35.0, inverse)
    assert truth(pressures) == pytest.approx(35.0, abs=1e-3) and volume == pytest.approx(35.0, abs=1e-3)
    assert rounds <= 3
    with pytest.raises(CorrectionError, match="no measurements"):
        fit_correction([], grid)


@pytest.mark.slow
def test_one_scan_gives_an_offset_and_a_field_meets_a_bump_the_growth_cannot():
    grid = _linear_grid()
    one = fit_correction([Measurement((1.0, 1.0, 1.0), 26.5)], grid)
    assert one.kind == "offset" and one.offset_ml == pytest.approx(0.5) and one.leave_one_out_pct == {}

    def truth(p):  # chamber 0 softer past 1.5 kPa than any scale of the model's growth says
        return 20.0 + 2.0 * float(np.sum(p)) + 1.5 * max(p[0] - 1.5, 0.0) ** 2

    points = np.array(list(np.ndindex(3, 3, 3)), dtype=float) * 1.5
    correction = fit_correction([Measurement(tuple(p), truth(p)) for p in points], grid)
    assert correction.kind in ("field", "growth+field")
    assert correction.leave_one_out_pct[correction.kind] < correction.leave_one_out_pct["growth"]
    corrected = CorrectedModel(grid, correction)
    for p in points:
        assert corrected.gland_ml(p) == pytest.approx(truth(p), abs=1e-3)
    rng = np.random.default_rng(5)
    held_out = rng.uniform(0, 3, (20, 3))
    errors = [abs(corrected.gland_ml(p) - truth(p)) / truth(p) * 100 for p in held_out]
    model_errors = [abs(grid.gland_ml(p) - truth(p)) / truth(p) * 100 for p in held_out]
    # 1.06 % against the model's 2.02 % (2026-11-27): a kink between the scanned points is smoothed over
    assert np.mean(errors) < 0.6 * np.mean(model_errors)


@pytest.mark.slow
def test_table_one_scanned_corrects_the_model_towards_the_simulated_phantom():
    """The eight Table I points stored as scans of the shipped simulated phantom (its truth passes through
    them): the corrections' leave-one-out is reported, and each kind's error at held-out points measured against
    the truth. Figures (2026-11-27): leave-one-out picks the offset (4.6 %; growth 5.1, field 5.5,
    growth+field 6.7: eight irregular points leave each other out badly); at 30 random held-out points the mean
    error is 2.69 % uncorrected and 1.24 % with the field: better, and short of the issue's 0.5 %."""
    from phantom.hil.plant import MEASURED_VOLUMES_PATH, load_plant
    from phantom.model import PhantomModel, load_scene
    from phantom.model.corrections import model_grid
    from phantom.model.fidelity.levels import VolumeEstimator

    plant = load_plant()
    rows = np.loadtxt(MEASURED_VOLUMES_PATH, delimiter=",", comments="#", skiprows=4)
    grid = model_grid(VolumeEstimator(PhantomModel.from_scene(load_scene("builtin:converged")), level="table"))
    scans = [Measurement(tuple(row[:3]), row[3]) for row in rows]
    chosen = fit_correction(scans, grid)
    assert set(chosen.leave_one_out_pct) == {"offset", "growth", "field", "growth+field"}
    assert chosen.leave_one_out_pct[chosen.kind] == min(chosen.leave_one_out_pct.values())
    held_out = np.random.default_rng(1).uniform(0, 3, (30, 3))
    truth = np.array([plant.truth_gland_volume_ml(1e3 * p) for p in held_out])

    def mean_error_pct(model):
        return float(np.mean([abs(model(p) - t) / t * 100 for p, t in zip(held_out, truth, strict=True)]))

    uncorrected = mean_error_pct(grid.gland_ml)
    field = CorrectedModel(grid, fit_correction(scans, grid, ["field"]))
    assert mean_error_pct(CorrectedModel(grid, chosen).gland_ml) < uncorrected
    assert mean_error_pct(field.gland_ml) < 0.5 * uncorrected
    # through the eight points themselves the field is exact (to the file's 5 digits)
    for row in rows:
        assert field.gland_ml(row[:3]) == pytest.approx(row[3], abs=0.01)
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
    assert "measured volume must be a finite number of ml above 0" in capsys.readouterr().err


@pytest.mark.slow
def test_corrections_fit_reports_each_candidates_leave_one_out(store, capsys):
    for pressures, volume in (((1, 1, 1), 29.96), ((2, 0, 0), 32.36), ((0, 0, 2), 31.20)):
        store.add(Measurement.now(pressures, volume))
    assert main(["corrections", "fit", "--phantom", "bench-phantom"]) == 0
    out = capsys.readouterr().out
    assert "3 measurement(s) of phantom 'bench-phantom'; the model builtin:converged misses them by" in out
    assert "leave-one-out (mean abs error of the volume left out): offset" in out
    assert "correction in force: offset" in out   # three points: the offset leaves the others out best
    assert main(["corrections", "fit", "--phantom", "nobody"]) == 2
    assert "no measurements to correct the model with: scan the phantom first" in capsys.readouterr().err
    store.add(Measurement.now((1, 1, 1), 30.5))  # the same state read 0.54 ml more: no field passes through both
    assert main(["corrections", "fit", "--phantom", "bench-phantom"]) == 0
    assert "not fitted: field (no residual field passes through" in capsys.readouterr().out


def test_a_fit_is_kept_in_the_cache_and_read_back_the_same_and_a_damaged_one_is_fitted_again(tmp_path, monkeypatch):
    """A daemon started again with many stored scans (27: 17-28 s to fit here) reads its fit back instead."""
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
    field_only = fit_correction(scans, grid, ("field",))
    read_back = Correction.from_document(json.loads(json.dumps(field_only.to_document())))
    assert read_back.residual_field is not None and np.array_equal(read_back.residual_field.chamber_ml,
                                                                   field_only.residual_field.chamber_ml)
    assert read_back.residual_ml((0.5, 1.0, 2.0), 3.0) == field_only.residual_ml((0.5, 1.0, 2.0), 3.0)


def test_a_scan_held_a_count_above_the_box_is_a_measurement_on_its_edge_and_one_beyond_is_refused():
    """A chamber held at 3 kPa reads 3.01 on average: its scan fits the field as a measurement at 3 kPa (the
    27-point characterisation's field was refused for it and fell back to a weaker kind); 3.5 kPa is refused."""
    from phantom.model.corrections import smoothest_residual

    grid = _linear_grid()
    edge = smoothest_residual(grid.points_kpa, grid.chamber_ml, grid.gland_grid_ml, [[3.01, 0.0, 1.5]], [0.4])
    at_three = smoothest_residual(grid.points_kpa, grid.chamber_ml, grid.gland_grid_ml, [[3.0, 0.0, 1.5]], [0.4])
    assert edge.gland_at_ml([3.0, 0.0, 1.5]) == pytest.approx(0.4, abs=1e-3)
    assert np.allclose(edge.gland_ml, at_three.gland_ml)
    with pytest.raises(CorrectionError, match="must lie on the grid"):
        smoothest_residual(grid.points_kpa, grid.chamber_ml, grid.gland_grid_ml, [[3.5, 0.0, 1.5]], [0.4])


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
    corrected = CorrectedModel(grid, Correction("offset", 1, offset_ml=1.5))
    assert corrected.range_ml == pytest.approx((21.5, 39.5))
    asked = []

    def inverse(volume_ml):
        asked.append(volume_ml)
        return np.full(3, (volume_ml - 20.0) / 6.0)

    for target_ml in (20.5, 39.6):  # inside the model's 20-38 ml, beyond the corrected 21.5-39.5; beyond both
        with pytest.raises(UnreachableTargetError, match=r"beyond the model's range with the correction in force "
                           r"\(offset from 1 measurement\(s\)\): give 21.500 to 39.500 ml") as raised:
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


@pytest.mark.slow
def test_scans_a_little_noisy_between_close_states_still_give_a_field():
    """A scan's noise (0.1 ml here) between two states 0.05 kPa apart asks for a chamber that shrinks as it is
    inflated: the field's growth floor is soft (each ml short costs), so a field is fitted through them instead
    of none (before: the QP was infeasible and the fit failed)."""
    grid = _linear_grid()
    rng = np.random.default_rng(7)
    points = [*rng.uniform(0, 3, (6, 3)), (1.0, 1.0, 1.0), (1.05, 1.0, 1.0)]
    volumes = [20.3 + 1.8 * float(np.sum(p)) for p in points]
    volumes[-1] = volumes[-2] - 0.1
    correction = fit_correction([Measurement(tuple(p), v) for p, v in zip(points, volumes, strict=True)], grid)
    assert {"field", "growth+field"} <= set(correction.leave_one_out_pct) and not correction.unfitted
    field = fit_correction([Measurement(tuple(p), v) for p, v in zip(points, volumes, strict=True)], grid, ["field"])
    for p, v in zip(points, volumes, strict=True):
        assert field.residual_ml(p, 0.0) + grid.gland_ml(np.asarray(p)) == pytest.approx(v, abs=1e-3)


def test_the_corrected_inverse_asks_the_model_only_for_volumes_it_reaches():
    """A phantom growing three times as fast as the model: the first secant step from a target just above rest
    asked the model's inverse for less than its rest (which it refuses); it is kept at the rest and goes on."""
    grid = _linear_grid()
    correction = fit_correction([Measurement((p, p, p), 20.0 + 18.0 * p) for p in (0.0, 1.0, 2.0)], grid,
                                ["growth"])
    assert correction.growth_factor == pytest.approx(2.0)

    def inverse(volume_ml):
        if not 20.0 <= volume_ml <= 38.0:
            raise CorrectionError(f"{volume_ml} ml is unreachable")
        return np.full(3, (volume_ml - 20.0) / 6.0)

    pressures, volume, _ = CorrectedModel(grid, correction).pressures_for_ml(21.0, inverse)
    assert volume == pytest.approx(21.0, abs=1e-3) and np.sum(pressures) * 6.0 == pytest.approx(1.0, abs=1e-3)


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
    assert correction.kind in ("field", "growth+field") and not correction.unfitted
    corrected = CorrectedModel(grid, correction)
    for first in (0, 3, 6, 9, 12, 15, 17):  # rest to the top
        target = float(truths[first:first + 2].mean())
        pressures, _, _ = corrected.pressures_for_ml(target, inverse)
        assert np.min(np.abs(design - pressures).max(axis=1)) > 0.03, "the target is not a scanned state"
        assert true_ml(pressures) == pytest.approx(target, rel=0.005)


def test_a_target_in_a_jump_of_the_corrected_volume_along_the_inverses_path_gets_the_nearer_side_and_says_so():
    """The model's inverse turns to another branch at 30 ml (only the lobes, then all three chambers), and the
    correction (0.5 ml per kPa of chamber 0) differs between them: the corrected volume jumps from 30.00 to 30.83
    ml there, and no pressures give 30.5 ml. The answer is the nearer side, with its own corrected volume (before:
    the secant crawled at the jump and the target was refused as unreachable)."""
    from phantom.model.corrections import ResidualField

    grid = _linear_grid()
    residual = np.zeros((7, 7, 7, 3))
    residual[..., 0] = 0.5 * grid.points_kpa[:, None, None]
    correction = Correction("field", 3, residual_field=ResidualField(grid.points_kpa, residual, 0.0))

    def inverse(volume_ml):
        if volume_ml < 30.0:
            return np.array([0.0, *[(volume_ml - 20.0) / 4.0] * 2])
        return np.full(3, (volume_ml - 20.0) / 6.0)

    pressures, volume, _ = CorrectedModel(grid, correction).pressures_for_ml(30.5, inverse)
    assert volume == pytest.approx(30.0 + 0.5 * 10 / 6, abs=1e-3) and pressures[0] == pytest.approx(10 / 6, abs=1e-3)
    assert CorrectedModel(grid, correction).pressures_for_ml(29.5, inverse)[1] == pytest.approx(29.5, abs=1e-3)
