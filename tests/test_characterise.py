"""``phantom characterise``'s parts that need no daemon (phantom.scan.characterise, phantom/cli/characterise.py): the
design of the pressure states, the run's record and its resumption (a finished point never scanned twice, a
half-finished one never stored, a stop between the record and the store made good), the report, and the bad
inputs, each refused with what to do."""

import json

import numpy as np
import pytest
from test_corrections import _linear_grid

from phantom.cli import characterise as cli
from phantom.cli.main import main
from phantom.host.client import DaemonError, FaultError, UnreachableError
from phantom.model.corrections import fit_correction
from phantom.model.measurements import CorrectionError, CorrectionStore, Measurement
from phantom.scan.characterise import (
    CharacterisationError,
    CharacterisationRecord,
    PointResult,
    fit_run,
    grid_design,
    held_pressures_kpa,
    path_design,
    short_path,
    space_filling_design,
    write_report,
)


def test_the_grid_is_every_combination_from_rest_along_a_short_path():
    points = grid_design([0, 1.5, 3], 3.0)
    assert points.shape == (27, 3)
    assert {tuple(p) for p in points} == {(a, b, c) for a in (0, 1.5, 3) for b in (0, 1.5, 3) for c in (0, 1.5, 3)}
    assert points[0].tolist() == [0, 0, 0]
    steps = np.abs(np.diff(points, axis=0)).sum(axis=1)
    product_order = np.stack(np.meshgrid(*[[0, 1.5, 3]] * 3, indexing="ij"), -1).reshape(-1, 3)
    # the blowers travel less than in the plain product's order (which swings a chamber 0 -> 3 kPa at every third)
    assert steps.sum() < np.abs(np.diff(product_order, axis=0)).sum(axis=1).sum()
    assert np.count_nonzero(steps == 1.5) >= 20


@pytest.mark.parametrize("values, why", [
    ([0, 1.5, 3.5], "0 to 3 kPa"), ([-0.5, 1], "0 to 3 kPa"), ([0, float("nan")], "finite"),
    ([1, 1, 2], "must differ"), ([], "finite"), (list(np.linspace(0, 3, 11)), "1331 states"), ([1.0], "1 states")])
def test_a_bad_grid_is_refused_with_why(values, why):
    with pytest.raises(CharacterisationError, match=why):
        grid_design(values, 3.0)


def test_the_space_filling_design_is_a_latin_hypercube_in_the_box_the_same_for_a_seed():
    points = space_filling_design(12, 3.0, seed=4)
    assert points.shape == (12, 3) and points.min() >= 0 and points.max() <= 3.0
    for chamber in range(3):
        slices = np.floor(points[:, chamber] / 3.0 * 12 - 1e-6).clip(0, 11)
        assert sorted(slices) == list(range(12)), "one pressure in each twelfth of the range, per chamber"
    np.testing.assert_array_equal(points, space_filling_design(12, 3.0, seed=4))
    assert not np.array_equal(np.sort(points, axis=0), np.sort(space_filling_design(12, 3.0, seed=5), axis=0))


@pytest.mark.parametrize("count", [0, 1, 1001, True, 2.5])
def test_a_bad_number_of_points_is_refused(count):
    with pytest.raises(CharacterisationError, match="--points must be a whole number from 2 to 1000"):
        space_filling_design(count, 3.0)


def test_the_path_is_rest_then_the_inverses_states_at_volumes_evenly_to_the_top():
    asked = []

    def inverse(volume_ml):  # a model of equal chambers growing 2 ml/kPa each from 20 ml
        asked.append(volume_ml)
        return np.full(3, (volume_ml - 20.0) / 6.0)

    points = path_design(5, inverse, 20.0, 38.0, samples=10)
    np.testing.assert_allclose(asked[-4:], [24.5, 29.0, 33.5, 38.0])
    np.testing.assert_allclose(points, [[0, 0, 0], [0.75] * 3, [1.5] * 3, [2.25] * 3, [3.0] * 3])

    def bent(volume_ml):  # the same model inflating one chamber to its top first, then the other two
        return np.array([min(volume_ml - 20.0, 6.0) / 2.0, *[max(volume_ml - 26.0, 0.0) / 4.0] * 2])

    points = path_design(5, bent, 20.0, 38.0, samples=200)
    # evenly along the path, 3 + 18 ** 0.5 kPa long: 1.81 kPa a step (not 4.5 ml: 2.25 kPa, then 1.06)
    step = (3 + 18 ** 0.5) / 4
    np.testing.assert_allclose(points[1:], [[step, 0, 0], [3, *[(2 * step - 3) / 2 ** 0.5] * 2],
                                            [3, *[(3 * step - 3) / 2 ** 0.5] * 2], [3, 3, 3]], atol=0.01)


@pytest.mark.parametrize(("count", "rest", "top", "why"), [
    (1, 20.0, 38.0, "--path must be a whole number from 2"), (2.5, 20.0, 38.0, "--path must be a whole number"),
    (5, 38.0, 20.0, "must grow from rest"), (5, 20.0, float("nan"), "must grow from rest")])
def test_a_bad_path_is_refused(count, rest, top, why):
    with pytest.raises(CharacterisationError, match=why):
        path_design(count, lambda v: np.zeros(3), rest, top)


def test_the_fit_takes_two_scans_at_one_state_that_disagree_and_refuses_a_scan_off_the_box():
    """Two scans at one state that disagree: the old field could pass through neither and fell back; the process
    takes them as noise (no note). A scan outside the model's box is a bad measurement: an error, not a
    fall-back."""
    grid = _linear_grid()
    scans = [Measurement((p, p, p), 20.3 + 5.4 * p) for p in (0.0, 1.0, 2.0, 3.0)]
    correction, note = fit_run([*scans, Measurement((1.0, 1.0, 1.0), 26.0)], grid)
    assert note == "" and correction.count == 5 and correction.white_noise_ml > 0.05
    with pytest.raises(CorrectionError, match="must lie on the grid, 0-3 kPa"):
        fit_run([*scans, Measurement((4.0, 0.0, 0.0), 30.0)], grid)


def test_a_bad_pressure_box_is_refused():
    with pytest.raises(CharacterisationError, match="positive number of kPa"):
        space_filling_design(5, float("nan"))


def test_the_short_path_starts_nearest_rest_and_takes_the_nearest_next():
    points = short_path([[3, 3, 3], [0, 0, 1], [3, 3, 2], [0, 0, 0]])
    assert points.tolist() == [[0, 0, 0], [0, 0, 1], [3, 3, 2], [3, 3, 3]]


def _record(folder, points=((0, 0, 0), (1, 0, 0), (0, 1, 1))):
    record = CharacterisationRecord(folder, "bench-phantom", "linear", {"kind": "grid", "values_kpa": [0, 1]}, 3.0,
                                    [list(map(float, p)) for p in points],
                                    {"views": 60, "elevations_deg": [0, 30], "scale": 0.5, "voxel_mm": 0.3,
                                     "settle_s": 0.3, "seed": 0, "camera": "virtual"}, "rig.json")
    record.save()
    return record


def _result(index, pressures, volume_ml, true_ml=None):
    return PointResult(index, list(pressures), list(pressures), volume_ml, 20.0 + 2.0 * sum(pressures),
                       f"/scans/{index:03d}", "2026-11-27T11:00:00+00:00", 60.0, true_ml)


def test_the_record_survives_a_restart_and_never_takes_a_point_twice(tmp_path):
    record = _record(tmp_path)
    assert record.pending() == [0, 1, 2]
    record.finish(_result(1, [1, 0, 0], 22.3))
    record.skip(2, "not reached within 120 s")
    again = CharacterisationRecord.load(tmp_path)
    assert again.pending() == [0, 2], "a skipped point is tried again, a finished one is not"
    assert again.results[0].volume_ml == 22.3 and not again.results[0].stored
    assert again.skipped == {2: "not reached within 120 s"}
    with pytest.raises(CharacterisationError, match="finished already: it is not scanned twice"):
        again.finish(_result(1, [1, 0, 0], 22.4))
    again.mark_stored(1)
    assert CharacterisationRecord.load(tmp_path).results[0].stored


@pytest.mark.parametrize("damage", [
    lambda d: "{not json", lambda d: json.dumps({**d, "format": "other/1"}),
    lambda d: json.dumps({**d, "results": [{**d["results"][0], "index": 7}]}),
    lambda d: json.dumps({**d, "results": [{**d["results"][0], "volume_ml": -1}]}),
    lambda d: json.dumps({**d, "results": d["results"] * 2})])
def test_a_damaged_record_is_refused_with_what_to_do(tmp_path, damage):
    record = _record(tmp_path)
    record.finish(_result(1, [1, 0, 0], 22.3))
    record.path.write_text(damage(json.loads(record.path.read_text())))
    with pytest.raises(CharacterisationError, match="is damaged .*start the run again in another folder"):
        CharacterisationRecord.load(tmp_path)


def test_there_is_nothing_to_resume_in_an_empty_folder(tmp_path):
    with pytest.raises(CharacterisationError, match="holds no characterisation .* to resume: start one with --grid"):
        CharacterisationRecord.load(tmp_path)


@pytest.mark.slow
def test_the_report_has_every_point_the_leave_one_out_and_a_plot(tmp_path):
    grid = _linear_grid()
    record = _record(tmp_path, [(a, b, c) for a in (0, 1.5, 3) for b in (0, 1.5, 3) for c in (0, 3)])
    for index, pressures in enumerate(record.points_kpa):
        truth = 20.3 + 1.8 * sum(pressures)
        record.finish(_result(index, pressures, truth * 1.001, truth))
    record.sessions.append({"started_utc": "x", "points": 18, "elapsed_s": 1234.0})
    correction = fit_correction(record.measurements(), grid)
    markdown, plot = write_report(record, grid, correction, ["the calibration's lines"])
    text = markdown.read_text()
    rows = [line for line in text.splitlines() if line.startswith("| ") and line.split("|")[1].strip().isdigit()]
    assert len(rows) == 18
    assert "truth (ml)" in text and "scan vs truth" in text and "+0.10 %" in rows[0]
    for kind in correction.leave_one_out_pct:
        assert f"| {kind}" in text
    assert f"**{correction.kind}**" in text and "1234 s in all" in text and "the calibration's lines" in text
    assert plot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and plot.stat().st_size > 20_000


# --- the command line, without a daemon ------------------------------------------------------------------------
def test_the_command_needs_a_design(tmp_path, capsys):
    assert main(["characterise", "--out", str(tmp_path / "run"), "--rig", "rig.json"]) == 2
    assert "give the design: --path N, --grid KPA,KPA,... or --points N" in capsys.readouterr().err


def test_a_finished_folder_is_not_started_again_without_resume(tmp_path, capsys):
    _record(tmp_path)
    assert main(["characterise", "--grid", "0,1", "--out", str(tmp_path), "--rig", "rig.json"]) == 2
    assert "holds a characterisation already (0 point(s) done): give --resume" in capsys.readouterr().err


def test_resume_refuses_another_design(tmp_path, capsys):
    _record(tmp_path)
    assert main(["characterise", "--resume", "--points", "5", "--out", str(tmp_path)]) == 2
    assert "holds another design" in capsys.readouterr().err


def test_a_run_needs_the_rig(tmp_path, capsys):
    assert main(["characterise", "--grid", "0,1", "--out", str(tmp_path / "run")]) == 2
    assert "give the scanner's calibration: --rig RIG.json" in capsys.readouterr().err


def test_no_daemon_running_is_told_with_how_to_start_one(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(cli, "_grid", lambda scene: _linear_grid())
    assert main(["characterise", "--grid", "0,1", "--out", str(tmp_path / "run"), "--rig", "rig.json",
                 "--socket", str(tmp_path / "none.sock")]) == 2
    assert "no daemon is listening" in capsys.readouterr().err
    assert not (tmp_path / "run").exists(), "nothing written for a run that did not start"


class FakeDaemon:
    """The daemon's API as the command uses it, for the command's own logic (the real daemon: the sim test)."""

    def __init__(self, methods=("scan",), faults=(), rest_ml=20.0, on_set=None):
        self.methods, self.faults, self.rest_ml, self.on_set = methods, tuple(faults), rest_ml, on_set
        self.set = []

    def status(self):
        from types import SimpleNamespace

        return SimpleNamespace(faults=self.faults, raw={"rest_volume_ml": self.rest_ml}, true_volume_ml=None)

    def call(self, method, params=None):
        if method not in self.methods:
            raise DaemonError("unknown_method", f"unknown method {method!r}")
        raise DaemonError("rejected", "scan takes out (a folder, required)")

    def set_pressures(self, pressures, wait, timeout_s):
        self.set.append(list(pressures))
        if self.on_set:
            self.on_set(pressures)


def test_a_daemon_without_a_scanner_a_latched_fault_or_another_model_is_refused_before_anything_moves():
    grid = _linear_grid()
    with pytest.raises(CharacterisationError, match="has no scanner"):
        cli._check_daemon(FakeDaemon(methods=()), grid)
    with pytest.raises(CharacterisationError, match=r"faults latched \(OVERPRESSURE\).*clear-fault"):
        cli._check_daemon(FakeDaemon(faults=["OVERPRESSURE"]), grid)
    with pytest.raises(CharacterisationError, match="rests at 21.000 ml, linear at 20.000 ml: give --scene"):
        cli._check_daemon(FakeDaemon(rest_ml=21.0), grid)
    cli._check_daemon(FakeDaemon(), grid)


def _visit(record, store, daemon, monkeypatch, scanned):
    """Run the command's loop with the scan replaced (it is the daemon's; the sim test runs the real one)."""
    def scan_point(client, record, index, folder, rig, grid, started, label):
        folder.mkdir(parents=True)
        scanned.append(index)
        return _result(index, record.points_kpa[index], 25.0 + index)
    monkeypatch.setattr(cli, "_scan_point", scan_point)
    args = type("Args", (), {"reach_timeout_s": 10.0})()
    cli._visit(daemon, record, store, _linear_grid(), None, args, lambda text: None, {"points": 0}, 0.0)


def test_a_fault_during_a_point_stops_the_run_with_the_store_consistent_and_resume_goes_on(tmp_path, monkeypatch):
    record, store = _record(tmp_path / "run"), CorrectionStore(tmp_path / "store.json")

    def fault_at_third(pressures):
        if pressures == [0.0, 1.0, 1.0]:
            raise FaultError(["OVERPRESSURE"], "waiting for pressures 0,1,1 kPa")
    scanned = []
    with pytest.raises(CharacterisationError, match=r"point 2 \(0.00, 1.00, 1.00 kPa\).*OVERPRESSURE.*--resume"):
        _visit(record, store, FakeDaemon(on_set=fault_at_third), monkeypatch, scanned)
    assert scanned == [0, 1]
    assert [e.scan_file for e in store.entries()] == ["/scans/000", "/scans/001"]
    again = CharacterisationRecord.load(tmp_path / "run")
    assert again.pending() == [2] and all(r.stored for r in again.results)
    # a stopped scan left its folder: it is removed, the point scanned once, stored once
    again.scan_folder(2).mkdir(parents=True)
    (again.scan_folder(2) / "half.png").write_text("x")
    _visit(again, store, FakeDaemon(), monkeypatch, scanned)
    assert scanned == [0, 1, 2] and len(store.entries()) == 3
    assert not (again.scan_folder(2) / "half.png").exists()


def test_a_fault_latched_between_points_stops_the_run_with_how_to_go_on(tmp_path, monkeypatch):
    """The real run on the simulated rig (bench/README.md, "Characterisation"): the board latched DEAD_HOST while
    point 0's scan was reconstructed, and point 1's setpoints were refused by the board as a "rejected" error, not
    a FaultError: the command died with the board's words and no word of --resume. Now any refusal of a point's
    pressures stops the run with the point, why, and how to go on."""
    record, store = _record(tmp_path / "run"), CorrectionStore(tmp_path / "store.json")

    def latched(pressures):
        if pressures == [1.0, 0.0, 0.0]:
            raise DaemonError("rejected", "the board refused SET_SETPOINTS: FAULT_LATCHED (a fault is latched: clear "
                                          "it first (phantom clear-fault))")
    scanned = []
    with pytest.raises(CharacterisationError, match=r"point 1 \(1.00, 0.00, 0.00 kPa\): the board refused "
                       r"SET_SETPOINTS: FAULT_LATCHED .*clear-fault.*; then `phantom characterise --resume --out "):
        _visit(record, store, FakeDaemon(on_set=latched), monkeypatch, scanned)
    assert scanned == [0] and CharacterisationRecord.load(tmp_path / "run").pending() == [1, 2]


def test_sigterm_stops_the_points_as_ctrl_c_does_and_leaves_the_handler_as_it_was():
    """A run in the background ignores SIGINT; killed with SIGTERM, the session's time was not saved (the real
    run's report counted 2104 s of its 2317 s of points). SIGTERM now raises KeyboardInterrupt in the points'
    loop, whose handler saves the record and says --resume; outside it, SIGTERM is what it was."""
    import os
    import signal
    import time

    before = signal.getsignal(signal.SIGTERM)
    with pytest.raises(KeyboardInterrupt), cli._terminate_as_interrupt():
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(5)  # the handler interrupts it at once
    assert signal.getsignal(signal.SIGTERM) is before


def test_an_unreachable_point_is_skipped_and_tried_again_on_resume(tmp_path, monkeypatch):
    record, store = _record(tmp_path / "run"), CorrectionStore(tmp_path / "store.json")

    def unreachable(pressures):
        if pressures == [1.0, 0.0, 0.0]:
            raise UnreachableError("unreachable", "pressures above the limit")
    scanned = []
    _visit(record, store, FakeDaemon(on_set=unreachable), monkeypatch, scanned)
    assert scanned == [0, 2] and record.skipped == {1: "pressures above the limit"}
    assert CharacterisationRecord.load(tmp_path / "run").pending() == [1]


def test_a_stop_between_the_record_and_the_store_is_made_good_on_resume_once(tmp_path):
    from dataclasses import replace

    record, store = _record(tmp_path / "run"), CorrectionStore(tmp_path / "store.json")
    folders = [str(record.scan_folder(index).resolve()) for index in (0, 1)]
    for index in (0, 1):
        record.scan_folder(index).mkdir(parents=True)
    record.finish(replace(_result(0, [0, 0, 0], 20.1), scan_folder=folders[0]))  # recorded, killed before the store
    record.finish(replace(_result(1, [1, 0, 0], 22.3), scan_folder=folders[1]))
    store.add(record.results[1].measurement("linear"))  # killed after the store, before it was marked
    scanned = {"000": 20.1, "001": 22.3}  # what each scan reconstructs to (see tests/test_characterise_record.py)
    cli._store_unstored(CharacterisationRecord.load(tmp_path / "run"), store, lambda text: None, _linear_grid(),
                        lambda folder: scanned[folder.name])
    assert sorted(e.scan_file for e in store.entries()) == folders
    assert all(r.stored for r in CharacterisationRecord.load(tmp_path / "run").results)


def test_a_scan_at_rest_is_stored_at_zero_not_at_the_sensors_noise_below_it():
    """At rest the pictures' pressures average -0.001 kPa in a chamber (found on the simulated rig: the run stopped
    at its first point, the measurement refused)."""
    at_rest = [[0.001, -0.002, 0.0014], [-0.0003, -0.0007, 0.001]]
    pressures = held_pressures_kpa(at_rest)
    assert pressures == pytest.approx([0.00035, 0.0, 0.0012])
    assert _result(0, pressures, 26.3).measurement("linear").pressures_kpa[1] == 0.0
    with pytest.raises(CharacterisationError, match="finite measured pressures"):
        held_pressures_kpa([[0.1, float("nan"), 0.0]])
    with pytest.raises(CharacterisationError, match="finite measured pressures"):
        held_pressures_kpa([])


@pytest.mark.parametrize(("camera", "named", "scale"), [
    (None, None, 0.5),  # the daemon's own: its --camera on a real board, else the virtual one at the run's scale
    ("virtual", "virtual", 0.5),
    ("2", 2, None),  # a device number
    ("http://lab-camera:8080/video.mjpg", "http://lab-camera:8080/video.mjpg", None),  # a stream: the rig's size
])
def test_a_points_scan_names_the_runs_camera_or_leaves_it_to_the_daemon(tmp_path, camera, named, scale):
    from phantom.scan.characterise import scan_params

    record = _record(tmp_path)
    record.scan["camera"] = camera
    params = scan_params(record, 2, tmp_path / "scans" / "002")
    assert params.get("camera") == named and ("camera" in params) == (named is not None)
    assert params.get("scale") == scale
    assert params["seed"] == 2 and params["rig"] == str((tmp_path / "rig.json").resolve())
    assert params["out"] == str((tmp_path / "scans" / "002").resolve()) and params["views"] == 60
