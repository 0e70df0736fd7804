"""A measured volume is checked before it is believed, and the store of them never stops anything (issue 51,
items 1 and 2): the plausibility rule, `phantom corrections add/confirm/remove`, and a store damaged in every way
the red team found (a FIFO, 1e300 ml, wrong types, duplicate keys, a link to another phantom's store) refused with
the field named, quickly."""

from __future__ import annotations

import asyncio
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from phantom.cli.main import main
from phantom.model.calibration.calibrate import load_measurements
from phantom.model.measurements import (
    MODEL_ERROR_95_PCT,
    PLAUSIBLE_SIGMAS,
    CorrectionError,
    CorrectionStore,
    Measurement,
    plausibility,
)

PHANTOM = Path(sys.executable).with_name("phantom")


@pytest.fixture
def data_dir(tmp_path, monkeypatch):
    monkeypatch.setenv("PHANTOM_DATA_DIR", str(tmp_path / "data"))
    return tmp_path / "data"


def _store_file(data_dir, name, document):
    path = data_dir / "corrections" / f"{name}.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(document if isinstance(document, str) else json.dumps(document))
    return path


def _entry(**changes):
    return {"pressures_kpa": [1, 1, 1], "volume_ml": 30.0, "method": "scan", "time_utc": "2026-01-01T00:00:00+00:00"
            } | changes


# ----------------------------------------------------------------------------------------------- the rule
def test_the_rule_believes_a_volume_within_k_sigma_of_what_is_expected_and_says_why_it_does_not_beyond():
    sigma = 2.0 / 1.96
    inside = plausibility(30.0 + (PLAUSIBLE_SIGMAS - 0.1) * sigma, 30.0, 2.0, "the model")
    assert inside.plausible and inside.reason == ""
    beyond = plausibility(30.0 + (PLAUSIBLE_SIGMAS + 0.1) * sigma, 30.0, 2.0, "the model")
    assert not beyond.plausible
    assert "expected 30.000 ml" in beyond.reason and "the model" in beyond.reason and "+" in beyond.reason
    with pytest.raises(CorrectionError, match="half-width"):
        plausibility(30.0, 30.0, 0.0, "the model")


def test_the_models_known_error_covers_table_one_and_not_a_typo():
    """builtin:converged misses Table I's measurements by up to 10.03 % (2,0,0 kPa): every one of them passes the
    rule against the model alone; 39.96 for 29.96 at 1,1,1 (+37 %) does not."""
    from phantom.model import PhantomModel, load_scene
    from phantom.model.corrections import model_grid
    from phantom.model.fidelity.levels import VolumeEstimator

    grid = model_grid(VolumeEstimator(PhantomModel.from_scene(load_scene("builtin:converged"))))
    rows = np.loadtxt(Path(__file__).parents[1] / "model" / "data" / "forward_measurements.csv", delimiter=",",
                      comments="#", skiprows=4)
    for row in rows:
        model_ml = grid.gland_ml(row[:3])
        assert plausibility(row[3], model_ml, model_ml * MODEL_ERROR_95_PCT / 100, "m").plausible, row
    model_ml = grid.gland_ml(np.ones(3))
    assert not plausibility(39.96, model_ml, model_ml * MODEL_ERROR_95_PCT / 100, "m").plausible


def test_a_scan_far_from_the_corrections_measurements_is_judged_by_the_models_own_error_and_one_near_them_not():
    """`bench/verify_daemon.py --sim-truth` (2026-11-29): after three scans at 26.5 and 30 ml the correction in force
    (fitted amplitude 0.3 ml) expected 34.98 +- 0.70 ml at the pressures for 35 ml, 1 kPa from its nearest scan,
    and the phantom's scan there, 33.13 ml (-5.3 %, within the model's known error), was stored unconfirmed (5.2
    standard deviations) and left out of the fit, and so was the next round's: the correction never learned where
    it had no measurement. Away from its measurements a correction knows no more than the model, so a volume there
    is judged by the model's known error; at a measured state its band still holds out a typo."""
    from phantom.model import PhantomModel, load_scene
    from phantom.model.corrections import CorrectedModel, fit_correction, judged, model_grid
    from phantom.model.fidelity.levels import VolumeEstimator

    grid = model_grid(VolumeEstimator(PhantomModel.from_scene(load_scene("builtin:converged"))))
    confirmed = [Measurement((0.098, 0.093, 0.095), 26.545), Measurement((0.886, 1.255, 1.255), 29.670),
                 Measurement((0.919, 1.323, 1.325), 29.960)]
    far = judged(Measurement((0.850, 2.078, 2.078), 33.132), grid, confirmed)
    assert far.status == "confirmed", far.reason
    corrected = CorrectedModel(grid, fit_correction(confirmed, grid))
    at_scan = np.array(confirmed[2].pressures_kpa)
    typo = judged(Measurement(tuple(at_scan), 0.94 * corrected.gland_ml(at_scan)), grid, confirmed)
    assert typo.status == "unconfirmed" and "the correction in force" in (typo.reason or ""), typo


# ----------------------------------------------------------------------------------------------- the command line
def test_a_typo_is_stored_unconfirmed_out_of_the_fit_until_confirmed_and_one_entry_can_be_removed(data_dir, capsys):
    assert main(["corrections", "add", "--phantom", "p", "--pressures-kpa", "1,1,1", "--volume-ml", "29.96"]) == 0
    assert "stored" in capsys.readouterr().out
    assert main(["corrections", "add", "--phantom", "p", "--pressures-kpa", "1,1,1", "--volume-ml", "39.96"]) == 0
    out = capsys.readouterr().out
    assert "UNCONFIRMED" in out and "phantom corrections confirm 2" in out and "remove 2" in out
    store = CorrectionStore.for_phantom("p")
    entries = store.entries()
    assert [e.status for e in entries] == ["confirmed", "unconfirmed"]
    assert "expected" in (entries[1].reason or "")
    assert [e.volume_ml for e in store.confirmed()] == [29.96]
    assert main(["corrections", "list", "--phantom", "p"]) == 0
    listed = capsys.readouterr().out
    assert "UNCONFIRMED" in listed and "expected" in listed
    assert main(["corrections", "confirm", "--phantom", "p", "2"]) == 0
    assert [e.status for e in store.entries()] == ["confirmed", "confirmed"]
    assert store.entries()[1].reason is None
    assert main(["corrections", "remove", "--phantom", "p", "1"]) == 0
    assert [e.volume_ml for e in store.entries()] == [39.96]
    assert main(["corrections", "remove", "--phantom", "p", "5"]) == 2
    assert "no measurement 5: phantom 'p' has 1 (`phantom corrections list`)" in capsys.readouterr().err
    assert main(["corrections", "confirm", "--phantom", "p", "0"]) == 2


def test_an_unconfirmed_typo_is_exported_as_a_comment_that_calibrate_does_not_fit(data_dir, tmp_path, capsys):
    """``corrections export`` wrote every measurement as a row, an unconfirmed typo with the rest, so ``phantom
    calibrate --measurements`` fitted the material to it: the store leaves it out of every fit, and so does the CSV
    now (a comment line saying why, kept in the copy)."""
    for volume_ml in ("29.96", "39.96", "32.36"):
        pressures = "2,0,0" if volume_ml == "32.36" else "1,1,1"
        assert main(["corrections", "add", "--phantom", "p", "--pressures-kpa", pressures, "--volume-ml",
                     volume_ml]) == 0
    assert [e.status for e in CorrectionStore.for_phantom("p").entries()] == ["confirmed", "unconfirmed", "confirmed"]
    capsys.readouterr()
    out = tmp_path / "measured.csv"
    assert main(["corrections", "export", "--phantom", "p", "--out", str(out)]) == 0
    said = capsys.readouterr().out
    assert "wrote 2 measurement(s)" in said and "the unconfirmed measurement(s) 2 as comment" in said
    assert "phantom corrections confirm" in said
    lines = out.read_text().splitlines()
    assert [line.split(",")[3] for line in lines[1:] if not line.startswith("#")] == ["29.96", "32.36"]
    (comment,) = [line for line in lines if line.startswith("#")]
    assert "unconfirmed" in comment and "39.96" in comment and "expected" in comment
    with open(out, "a") as csv_file:
        csv_file.write("0,0,0,26.43,air,scan,,,\n")   # calibrate needs three rows
    measured = load_measurements(out, 3)
    assert sorted(np.round(measured.volumes_m3 * 1e6, 2)) == [26.43, 29.96, 32.36]


def test_a_measurement_outside_the_pressure_box_is_refused_at_the_door(data_dir, capsys):
    assert main(["corrections", "add", "--phantom", "p", "--pressures-kpa", "50,1,1", "--volume-ml", "30"]) == 2
    assert "0-3 kPa, the model's pressure box" in capsys.readouterr().err
    assert main(["corrections", "add", "--phantom", "p", "--pressures-kpa", "1,1", "--volume-ml", "30"]) == 2
    assert "3 pressures" in capsys.readouterr().err
    assert not CorrectionStore.for_phantom("p").path.exists()


def test_a_typo_stored_by_hand_does_not_move_the_daemons_model(data_dir):
    """The red team's case: 39.96 ml at 1,1,1 kPa (for 29.96) stored; the worker (the daemon's model) then answers a
    40 ml target with the pressures the model alone gives (before: a correction of +10.7 ml, and 40 ml "reached"
    where the simulated phantom held 30.3 ml); confirmed, it is in force."""
    from phantom.host.model_worker import ModelWorker
    from phantom.model.target import Target

    assert main(["corrections", "add", "--phantom", "typo", "--pressures-kpa", "1,1,1", "--volume-ml", "39.96"]) == 0
    target = Target(gland_volume_m3=40e-6)

    async def scenario():
        worker = await ModelWorker.start("builtin:converged", phantom="typo")
        try:
            status = worker.correction_status()
            assert not status["in_force"] and status["stored"] == 1, status
            held = await worker.pressures_for(target)
            plain = await ModelWorker.start("builtin:converged", phantom="nobody")
            try:
                alone = await plain.pressures_for(target)
            finally:
                plain.close()
            np.testing.assert_allclose(held.pressures_pa, alone.pressures_pa, atol=1.0)
            assert main(["corrections", "confirm", "--phantom", "typo", "1"]) == 0
            await worker.refit()
            assert worker.correction_status()["in_force"]
            # the daemon's own record of a scan is checked the same way: stored unconfirmed, said so
            with pytest.raises(CorrectionError, match="UNCONFIRMED"):
                await worker.record_measurement([2.0, 0.0, 0.0], 80.0)
            assert CorrectionStore.for_phantom("typo").entries()[-1].status == "unconfirmed"
            assert worker.correction_status()["correction"]["count"] == 1
        finally:
            worker.close()

    asyncio.run(scenario())


# ----------------------------------------------------------------------------------------------- damaged stores
#: (1e300 ml, which made the daemon exit 1 at start, is a volume no gland has: that entry alone is left out, below)
HUGE_VOLUME = json.dumps({"format": "phantom-corrections/1", "measurements": [_entry(volume_ml=1e300)]})
DAMAGED = {
    "huge pressure": (json.dumps({"format": "phantom-corrections/1",
                                  "measurements": [_entry(pressures_kpa=[1e300, 1, 1])]}), "pressures_kpa"),
    "time a number": (json.dumps({"format": "phantom-corrections/1", "measurements": [_entry(time_utc=5)]}),
                      "time_utc"),
    "time an object": (json.dumps({"format": "phantom-corrections/1", "measurements": [_entry(time_utc={"a": 1})]}),
                       "time_utc"),
    "scan file a list": (json.dumps({"format": "phantom-corrections/1", "measurements": [_entry(scan_file=[1])]}),
                         "scan_file"),
    "status unknown": (json.dumps({"format": "phantom-corrections/1", "measurements": [_entry(status="maybe")]}),
                       "status"),
    "duplicate keys": ('{"format": "phantom-corrections/1", "measurements": [{"pressures_kpa": [1, 1, 1], '
                       '"volume_ml": 30.0, "volume_ml": 40.0}]}', "duplicate key 'volume_ml'"),
    "entries not a list": ('{"format": "phantom-corrections/1", "measurements": {"a": 1}}', "measurements"),
    # an integer of 401 digits: no float holds it (was an OverflowError traceback from every command)
    "volume an integer too large": (json.dumps({"format": "phantom-corrections/1",
                                                "measurements": [_entry(volume_ml=10**400)]}), "volume_ml"),
    "pressure an integer too large": (json.dumps({"format": "phantom-corrections/1",
                                                  "measurements": [_entry(pressures_kpa=[1, 10**400, 1])]}),
                                      "pressures_kpa"),
    # entries of two phantoms (was listed, exported as misaligned rows, and a ValueError traceback from fit)
    "chamber counts differ": (json.dumps({"format": "phantom-corrections/1",
                                          "measurements": [_entry(), _entry(pressures_kpa=[1, 1])]}),
                              "measurement 2: it has 2 pressures, measurement 1 has 3"),
}


@pytest.mark.parametrize("kind", sorted(DAMAGED))
def test_a_damaged_store_is_refused_with_the_field_named(data_dir, kind):
    content, field = DAMAGED[kind]
    _store_file(data_dir, "bad", content)
    with pytest.raises(CorrectionError, match="is damaged") as refused:
        CorrectionStore.for_phantom("bad").entries()
    assert field in str(refused.value)


@pytest.mark.parametrize("kind", ["volume an integer too large", "chamber counts differ"])
@pytest.mark.parametrize("action", ["list", "export", "fit"])
def test_every_corrections_command_reports_a_damaged_entry_with_what_to_do(data_dir, capsys, kind, action):
    content, field = DAMAGED[kind]
    _store_file(data_dir, "bad", content)
    assert main(["corrections", action, "--phantom", "bad"]) == 2
    captured = capsys.readouterr()
    assert "is damaged" in captured.err and field in captured.err and "move it aside" in captured.err
    assert "Traceback" not in captured.err and captured.out == ""


@pytest.mark.parametrize("kind", ["volume an integer too large", "chamber counts differ"])
def test_the_daemons_fit_says_a_store_with_a_damaged_entry_is_damaged(data_dir, kind):
    """The daemon's status showed ``OverflowError: int too large to convert to float``, not that the store is
    damaged and what to do."""
    from phantom.host.model_worker import _fitter_fit

    content, field = DAMAGED[kind]
    path = _store_file(data_dir, "bad", content)
    answer = _fitter_fit("builtin:converged", "table", str(path))
    assert answer.correction is None and answer.error is not None
    assert answer.error.startswith(f"the correction store {path} is damaged") and field in answer.error


def test_a_fifo_or_a_device_in_place_of_the_store_is_refused_without_being_opened(data_dir, tmp_path):
    path = data_dir / "corrections" / "fifo.json"
    path.parent.mkdir(parents=True)
    os.mkfifo(path)
    started = time.monotonic()
    result = subprocess.run([str(PHANTOM), "corrections", "list", "--phantom", "fifo"], capture_output=True,
                            text=True, timeout=60, env=os.environ | {"PHANTOM_DATA_DIR": str(data_dir)})
    assert result.returncode == 2, result
    assert "not a regular file" in result.stderr and time.monotonic() - started < 30
    os.symlink("/dev/zero", data_dir / "corrections" / "zero.json")
    with pytest.raises(CorrectionError, match="not a regular file|a link"):
        CorrectionStore.for_phantom("zero").entries()


def test_a_store_linked_to_another_phantoms_is_refused_not_merged(data_dir):
    other = CorrectionStore.for_phantom("other")
    other.add(Measurement.now([1, 1, 1], 30.0))
    os.symlink(other.path, other.path.with_name("mine.json"))
    mine = CorrectionStore.for_phantom("mine")
    with pytest.raises(CorrectionError, match="is a link"):
        mine.entries()
    with pytest.raises(CorrectionError, match="is a link"):
        mine.add(Measurement.now([1, 1, 1], 30.5))
    assert len(other.entries()) == 1 and other.path.is_file() and not other.path.is_symlink()


# ----------------------------------------------------------------------------------------------- a volume no gland has
#: A store an older version (or a hand edit) left with one volume outside a whole gland's 2-400 ml among good ones:
#: 40 ml written in m^3 (4e-05), then another measurement.
NO_GLANDS = {"format": "phantom-corrections/1", "measurements": [
    _entry(), _entry(volume_ml=4e-05, pressures_kpa=[2, 0, 0]), _entry(volume_ml=31.0, pressures_kpa=[1, 1, 1.5])]}


def test_a_volume_no_gland_has_is_kept_in_the_store_left_out_of_the_fit_and_says_why_not_the_store_refused(data_dir):
    """Before: the whole store read as damaged ("move it aside"), so every measurement in it was refused for one
    entry an older version let in. Now that entry is ``refused``: listed with why, out of every fit, kept in the
    file through later writes; it cannot be confirmed as it is (remove it and add the volume again in ml)."""
    path = _store_file(data_dir, "old", NO_GLANDS)
    store = CorrectionStore.for_phantom("old")
    entries = store.entries()
    assert [e.status for e in entries] == ["confirmed", "refused", "confirmed"]
    reason = entries[1].reason or ""
    assert "4e-05" in reason and "2-400 ml" in reason and "40 ml in m^3" in reason, reason
    assert [e.volume_ml for e in store.confirmed()] == [30.0, 31.0]
    store.add(Measurement((2.0, 2.0, 2.0), 33.0))
    kept = json.loads(path.read_text())["measurements"]
    assert [m["volume_ml"] for m in kept] == [30.0, 4e-05, 31.0, 33.0] and kept[1]["status"] == "refused"
    assert [e.status for e in CorrectionStore.for_phantom("old").entries()] == ["confirmed", "refused", "confirmed",
                                                                               "confirmed"]
    with pytest.raises(CorrectionError, match=r"measurement 2 cannot be confirmed: .*4e-05.*phantom corrections "
                                              r"remove 2"):
        store.confirm(2)
    assert store.remove(2).volume_ml == 4e-05
    assert [e.status for e in store.entries()] == ["confirmed"] * 3


def test_every_corrections_command_reads_a_store_with_a_volume_no_gland_has_and_shows_it_left_out(data_dir, capsys,
                                                                                                tmp_path):
    _store_file(data_dir, "old", NO_GLANDS)
    assert main(["corrections", "list", "--phantom", "old"]) == 0
    listed = capsys.readouterr().out
    assert "REFUSED, left out of the fit" in listed and "4e-05" in listed and "remove 2" in listed
    out = tmp_path / "measured.csv"
    assert main(["corrections", "export", "--phantom", "old", "--out", str(out)]) == 0
    said = capsys.readouterr().out
    assert "wrote 2 measurement(s)" in said and "refused measurement(s) 2" in said and "unconfirmed" not in said
    (comment,) = [line for line in out.read_text().splitlines() if line.startswith("#")]
    assert "measurement 2 refused" in comment and "2-400 ml" in comment
    assert main(["corrections", "fit", "--phantom", "old", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["count"] == 2


def test_the_daemons_fit_leaves_a_volume_no_gland_has_out_and_says_so_and_records_beside_it(data_dir):
    """The daemon's fitter fits the store's good measurements (before: the store was damaged, no correction);
    with nothing else stored it says which is refused and why; and a scan recorded beside it is stored (the
    check for a retried record compared each stored entry confirmed, which a refused volume cannot be)."""
    from types import SimpleNamespace

    from phantom.host.model_worker import ModelWorker, _fitter_fit, _fitter_record

    path = _store_file(data_dir, "old", NO_GLANDS)
    answer = _fitter_fit("builtin:converged", "table", str(path))
    assert answer.error is None and answer.correction is not None and answer.correction.count == 2
    assert answer.stored == 3
    _, said, level = ModelWorker.correction_event(SimpleNamespace(fit=answer, phantom="old"))  # the daemon's log
    assert level == "INFO" and "from 2 measurement(s) (1 of the 3 stored left out of it: `phantom corrections " \
        "list`)" in said
    alone = _store_file(data_dir, "alone", HUGE_VOLUME)
    answer = _fitter_fit("builtin:converged", "table", str(alone))
    assert answer.correction is None and "measurement 1 refused" in (answer.error or "")
    assert "volume_ml" in (answer.error or "") and "phantom corrections remove 1" in (answer.error or "")
    recorded = _fitter_record("builtin:converged", "table", str(path),
                              Measurement((1.5, 1.5, 1.5), 33.0, time_utc="2026-01-02T00:00:00+00:00"))
    assert recorded.correction is not None and recorded.correction.count == 3
    assert [e.status for e in CorrectionStore(path).entries()] == ["confirmed", "refused", "confirmed", "confirmed"]


@pytest.mark.parametrize(("make", "message"), [
    (lambda: Measurement((1.0, 1.0, 1.0), 1e300), "volume_ml"),
    (lambda: Measurement((1.0, 1.0, 1.0), 30.0, time_utc=5), "time_utc"),          # type: ignore[arg-type]
    (lambda: Measurement((1.0, 1.0, 1.0), 30.0, model_volume_ml=1e300), "model_volume_ml"),
    (lambda: Measurement((1.0, 1.0, 1.0), 30.0, status="maybe"), "status"),
])
def test_absurd_numbers_and_wrong_types_are_refused_with_the_field_named(make, message):
    with pytest.raises(CorrectionError, match=message):
        make()


@pytest.mark.sim
def test_a_daemon_on_the_simulated_board_starts_uncorrected_saying_why_whatever_its_store_holds(
        tmp_path, data_dir, default_model_cached):
    """Each damaged store the red team found (before: 1e300 ml made the daemon exit 1 at start, a FIFO kept it from
    ever being ready) leaves a daemon on the simulated board ready within its usual start (wait_online's 60 s),
    uncorrected, its status and log saying why; the typo stored unconfirmed too, and 1e300 ml (no gland's volume)
    read refused, left out, with why."""
    from daemon_rig import DaemonRig

    from phantom.hil.sim import SimulatedBoard

    corrections = data_dir / "corrections"
    corrections.mkdir(parents=True)
    cases = {"huge": HUGE_VOLUME, "clock": DAMAGED["time an object"][0], "twice": DAMAGED["duplicate keys"][0]}
    for name, content in cases.items():
        (corrections / f"{name}.json").write_text(content)
    os.mkfifo(corrections / "fifo.json")
    CorrectionStore.for_phantom("other").add(Measurement.now([1, 1, 1], 30.0))
    os.symlink(corrections / "other.json", corrections / "linked.json")
    typo = CorrectionStore.for_phantom("typo")
    typo.add(Measurement((1.0, 1.0, 1.0), 39.96, status="unconfirmed", reason="a typo"))
    # the typo first: each daemon after it finds the board latched DEAD_HOST by the one killed before it
    whys = {"typo": "none of the 1 stored measurement(s) is confirmed", "huge": "measurement 1 refused: read as "
            "1e+300 ml", "clock": "time_utc",
            "twice": "duplicate key", "fifo": "not a regular file", "linked": "is a link"}
    board = SimulatedBoard(speed=2.0).start()
    try:
        for name, why in whys.items():
            folder = tmp_path / name
            folder.mkdir()
            rig = DaemonRig(folder, "--phantom", name, board=board)
            try:
                started = time.monotonic()
                rig.wait_online()
                correction = rig.status()["correction"]
                assert not correction["in_force"] and why in (correction["error"] or ""), (name, correction)
                assert why in rig.daemon_log(), name
                print(f"{name}: ready in {time.monotonic() - started:.1f} s, uncorrected: {correction['error']}")
                if name == "typo":
                    # the done-when: 40 ml set with the typo stored is the model's own 40 ml, which the simulated
                    # phantom holds within the model's known error (with the typo believed: 30.3 ml)
                    done = rig.cli("set", "--volume-ml", "40", "--wait")
                    assert done.returncode == 0, done.stderr
                    from phantom.hil.plant import load_plant

                    held_kpa = np.asarray(rig.status()["solution"]["pressures_kpa"], dtype=float)
                    true_ml = load_plant().truth_gland_volume_ml(held_kpa * 1e3)  # what a scan there measures
                    print(f"typo: 40 ml set, the simulated phantom holds {true_ml:.2f} ml")
                    assert abs(true_ml - 40.0) < 40.0 * MODEL_ERROR_95_PCT / 100, true_ml
            finally:
                rig.close()
    finally:
        board.stop()



def test_a_fitter_that_dies_twice_leaves_the_worker_started_uncorrected_saying_why(data_dir, monkeypatch):
    """The fit's own process killed (OSQP crashing in C, the OOM killer) on its first try and its retry: the
    daemon's model still starts, on its own answers, and says why (it raised out of the start, exit 1)."""
    from concurrent.futures.process import BrokenProcessPool

    from phantom.host.model_worker import ModelWorker

    CorrectionStore.for_phantom("crashing").add(Measurement.now([1, 1, 1], 30.0))

    async def dies(self, function, *arguments):
        raise BrokenProcessPool("A process in the process pool was terminated abruptly")

    monkeypatch.setattr(ModelWorker, "_in_fitter", dies)

    async def scenario():
        worker = await ModelWorker.start("builtin:converged", phantom="crashing")
        try:
            status = worker.correction_status()
            assert not status["in_force"] and "the fit's process died" in status["error"], status
        finally:
            worker.close()

    asyncio.run(scenario())
