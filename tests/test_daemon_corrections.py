"""The daemon's model answers with the correction by the phantom's measured volumes (issue 36, item 3).

The model worker's own functions in this process (:class:`LoadedModel`), the worker and its fitter in processes of
their own (:class:`ModelWorker`), and one daemon on the simulated board end to end. The "scans" here are the
simulated phantom's true volumes at the pressures (hil/plant.py's truth, what a scan measures to 0.03-0.14 %):
stand-ins for scans, said so where they are used.
"""

from __future__ import annotations

import asyncio
import json
import os
import signal

import numpy as np
import pytest
from test_corrections import offset_correction

from phantom.model.measurements import CorrectionError, CorrectionStore, Measurement
from phantom.model.target import Target

ML = 1e-6


@pytest.fixture
def data_dir(tmp_path, monkeypatch):
    monkeypatch.setenv("PHANTOM_DATA_DIR", str(tmp_path / "data"))
    return tmp_path / "data"


@pytest.fixture(scope="module")
def loaded():
    from phantom.host.model_worker import LoadedModel

    return LoadedModel("builtin:converged", report=lambda text: None)


def true_ml(pressures_kpa):
    """The simulated phantom's gland volume (ml) at these pressures: what a scan there measures."""
    from phantom.hil.plant import load_plant

    return load_plant().truth_gland_volume_ml(np.asarray(pressures_kpa, dtype=float) * 1e3)


def test_a_correction_moves_the_inverse_and_corrects_the_estimates_gland_not_its_chambers(loaded):
    target = Target(gland_volume_m3=35 * ML)
    pressures = np.full(3, 1500.0)
    plain = loaded.pressures_for(target)
    chambers, gland, model_gland = loaded.estimate(pressures)
    assert gland == model_gland and loaded.gland_band(pressures) is None   # no correction: no band
    try:
        loaded.set_correction(offset_correction(1.5))
        corrected = loaded.pressures_for(target)
        assert np.max(np.abs(corrected.pressures_pa - plain.pressures_pa)) > 50  # Pa: another answer
        assert corrected.predicted_gland_volume_m3 / ML == pytest.approx(35, abs=2e-3)
        # the model's own volume there is 1.5 ml less: the correction says the phantom holds 1.5 ml more
        assert loaded.estimate(corrected.pressures_pa)[2] == pytest.approx(33.5, abs=2e-3)
        chambers_after, gland_after, model_after = loaded.estimate(pressures)
        assert (gland_after, model_after, chambers_after) == (pytest.approx(model_gland + 1.5), model_gland,
                                                              chambers)
        # what the verify policy asks after a round's scan is stored: the corrected volume there and its band
        band_gland, band_ml = loaded.gland_band(pressures)
        assert band_gland == gland_after and 0.0 < band_ml < 10.0
        ramp = loaded.pressures_on_ramp(Target(gland_volume_m3=30 * ML), target, Target(gland_volume_m3=33 * ML))
        assert ramp.predicted_gland_volume_m3 / ML == pytest.approx(33, abs=1e-3)
        with pytest.raises(Exception, match="with the correction in force .gp.offset from 1 measurement"):
            loaded.pressures_for(Target(gland_volume_m3=80 * ML))
        pressure_target = Target(pressures_pa=[1000.0, 1000.0, 1000.0])
        assert list(loaded.pressures_for(pressure_target).pressures_pa) == [1000.0, 1000.0, 1000.0]
    finally:
        loaded.set_correction(None)
    assert np.allclose(loaded.pressures_for(target).pressures_pa, plain.pressures_pa)


@pytest.mark.slow
def test_after_a_few_scans_of_verified_targets_unverified_targets_between_them_land_within_half_a_percent(loaded):
    """Item 3's "after a few scans a target is hit on the first round", on the shipped simulated phantom (the
    measured phantom's truth, Table I shaped). The scans are stand-ins: the truth's volume at the pressures the
    daemon applied. Verified targets of 30, 35, 40 and 44 ml (scan, correct, re-apply until within 0.3 %) store
    their scans; then targets between them, never scanned, are applied once: each lands nearer the truth than the
    uncorrected model (up to 4 % off), and two of three within 0.5 %. Figures (2026-11-28, the Gaussian process):
    6 scans; 32.5 ml +1.44 % (uncorrected +1.75 %; the old field's +0.5 %: the truth plant's residual has kinks
    between the scanned states that five scans do not show, and the process's band there, 0.27 %, is too narrow),
    37.5 ml +0.45 %, 42.5 ml +0.15 %."""
    from phantom.model.corrections import fit_correction, model_grid

    grid = model_grid(loaded.estimator)
    unverified = (32.5, 37.5, 42.5)

    def error_pct(volume_ml):
        pressures_kpa = loaded.pressures_for(Target(gland_volume_m3=volume_ml * ML)).pressures_pa / 1e3
        return pressures_kpa, (true_ml(pressures_kpa) / volume_ml - 1) * 100

    before = [error_pct(volume)[1] for volume in unverified]
    scans = []
    try:
        for volume in (30.0, 35.0, 40.0, 44.0):
            for _ in range(4):
                pressures_kpa, error = error_pct(volume)
                if abs(error) <= 0.3:
                    break
                scans.append(Measurement(tuple(pressures_kpa), true_ml(pressures_kpa)))
                loaded.set_correction(fit_correction(scans, grid))
            assert abs(error) <= 0.3, f"{volume} ml verified: {error:+.2f} %"
        after = [error_pct(volume)[1] for volume in unverified]
    finally:
        loaded.set_correction(None)
    print(f"{len(scans)} scans; unverified {unverified} ml: before {np.round(before, 2)} %, after "
          f"{np.round(after, 2)} %")
    assert max(abs(error) for error in before) > 1.5
    assert all(abs(error) < abs(uncorrected) for error, uncorrected in zip(after, before, strict=True))
    assert sum(abs(error) <= 0.5 for error in after) >= 2


def run(coroutine):
    return asyncio.run(coroutine)


def test_a_pressure_target_with_a_correction_in_force_is_reached_at_its_pressures(loaded):
    """The real `phantom characterise --path 13` on the simulated rig: from its third scan the field put the
    corrected gland 4.5 % over the model's at the next point's pressures, the daemon's reach rule compared that
    estimate with the pressure target's predicted volume (the model's own) and never called it reached: every
    later point was skipped after 120 s. The prediction of a pressure (and chamber) target is the corrected gland
    now, as the estimate is; its pressures and chambers are the model's own."""
    from phantom.host.control import estimate_within

    pressures = [591.0, 1131.0, 1131.0]
    plain = loaded.pressures_for(Target(pressures_pa=pressures))
    try:
        loaded.set_correction(offset_correction(1.5))
        for target in (Target(pressures_pa=pressures), Target(chamber_volumes_m3=[3.0 * ML, None, None])):
            answer = loaded.pressures_for(target)
            chambers, gland, model_gland = loaded.estimate(answer.pressures_pa)
            assert answer.predicted_gland_volume_m3 / ML == pytest.approx(gland, abs=1e-6)
            assert gland == pytest.approx(model_gland + 1.5)
            assert estimate_within(target, answer, gland, tuple(chambers), 1.0), "reached at its own pressures"
        answer = loaded.pressures_for(Target(pressures_pa=pressures))
        assert list(answer.pressures_pa) == pressures
        assert np.allclose(answer.predicted_chamber_volumes_m3, plain.predicted_chamber_volumes_m3)
    finally:
        loaded.set_correction(None)


@pytest.mark.slow
def test_the_worker_fits_the_store_at_start_follows_it_refuses_another_phantoms_and_survives_a_kill(data_dir):
    """A worker started with measurements stored answers a volume target with other pressures than one started
    without; a measurement added by another writer is picked up before an answer; record_measurement stores and
    refits; a measurement of another phantom (four pressures) is refused and nothing stored; a worker killed is
    replaced with the correction in force."""
    from phantom.host.model_worker import ModelWorker

    target = Target(gland_volume_m3=35 * ML)

    async def scenario():
        plain = await ModelWorker.start("builtin:converged", phantom="plain")
        try:
            assert plain.correction_status()["in_force"] is False and plain.fit.error is None
            plain_answer = await plain.pressures_for(target)
        finally:
            plain.close()
        store = CorrectionStore.for_phantom("scanned")
        for pressures in ((0, 0, 0), (2, 0, 0), (0, 2, 0)):
            store.add(Measurement(tuple(map(float, pressures)), true_ml(pressures)))
        worker = await ModelWorker.start("builtin:converged", phantom="scanned")
        try:
            status = worker.correction_status()
            assert status["in_force"] and status["correction"]["count"] == 3, status
            answer = await worker.pressures_for(target)
            assert np.max(np.abs(answer.pressures_pa - plain_answer.pressures_pa)) > 50
            estimate = await worker.estimate(answer.pressures_pa)
            assert estimate.gland_volume_ml == pytest.approx(35, abs=0.01)
            assert estimate.model_gland_volume_ml != pytest.approx(35, abs=0.1)
            # another writer (`phantom corrections add`) changes the store under the running worker
            fit_before = worker._fitting
            store.add(Measurement((1.0, 1.0, 1.0), true_ml((1, 1, 1))))
            await worker.estimate(answer.pressures_pa)          # the check before an answer starts a fit
            assert worker._fitting is not fit_before
            await worker._fitting
            assert worker.correction_status()["correction"]["count"] == 4
            recorded = await worker.record_measurement([1.5, 0.5, 0.0], true_ml((1.5, 0.5, 0)), scan_file="s.ply")
            assert recorded["count"] == 5 and recorded["size_ml"] > 0 and "leave_one_out_pct" in recorded
            assert store.entries()[-1].model == "builtin:converged" and store.entries()[-1].scan_file == "s.ply"
            scanned_gland, scanned_band = await worker.gland_band(np.array([1500.0, 500.0, 0.0]))
            assert scanned_gland == pytest.approx(true_ml((1.5, 0.5, 0)), rel=0.005) and 0.0 < scanned_band < 0.5
            with pytest.raises(CorrectionError, match="has 3 pressures.*got 4: is it of another phantom"):
                await worker.record_measurement([1.0, 1.0, 1.0, 1.0], 30.0)
            with pytest.raises(CorrectionError, match="must lie on the grid, 0-3 kPa, the model's pressure box"):
                await worker.record_measurement([1.0, 1.0, 5.0], 30.0)
            assert len(store.entries()) == 5
            # make demo's last 45 ml scan: chambers held at the box's top read 3.0003 and 3.0005 kPa (refused before)
            edge = await worker.record_measurement([2.306, 3.0003, 3.0005], true_ml((2.306, 3.0, 3.0)))
            assert edge["count"] == 6 and store.entries()[-1].pressures_kpa[2] == pytest.approx(3.0005)
            corrected = await worker.pressures_for(target)
            os.kill(next(iter(worker._pool._processes)), signal.SIGKILL)  # the OOM killer
            again = await worker.pressures_for(target)
            assert worker.restarts == 1 and np.allclose(again.pressures_pa, corrected.pressures_pa, atol=1.0)
            await worker.refit()  # the replaced worker reads the store again
            assert worker.correction_status()["correction"]["count"] == 6
        finally:
            worker.close()

    run(scenario())


@pytest.mark.slow
def test_many_stored_measurements_a_store_changed_before_a_target_and_a_fitter_killed_mid_store(data_dir):
    """Three defects of the red team's (issue 48), on a worker whose store holds 150 scans (stand-ins: the
    truth's volumes with the scanner's noise): its start fits them (128 took the old field 130 s, and the daemon
    was not ready after 90 s; the bound here is loose on purpose, the fit's time is bench/correction_fit.py's);
    a measurement stored by another writer just before a target is in force for that target (before: it was
    solved on the correction before and never came to its estimate); the fitter killed (SIGTERM, as the
    daemon's process group gets it) after it stored a scan and while it fits is started again, and the scan is
    stored once (before: the retry stored it twice)."""
    from phantom.host.model_worker import ModelWorker

    rng = np.random.default_rng(11)
    store = CorrectionStore.for_phantom("many")
    states = rng.uniform(0, 3, (150, 3))
    stored = [Measurement(tuple(p), true_ml(p) * (1 + 0.0012 * rng.standard_normal())) for p in states]
    store._write(stored)  # one write of all 150 (add() writes the whole file per measurement)
    target = Target(gland_volume_m3=35 * ML)

    async def scenario():
        worker = await ModelWorker.start("builtin:converged", phantom="many")
        try:
            assert worker.fit.stored == 150 and worker.correction_status()["correction"]["count"] == 150
            assert worker.fit.fit_s < 30
            before = await worker.pressures_for(target)
            # another writer stores a scan at the target's state that reads 1 ml over, just before a target
            store.add(Measurement(tuple(before.pressures_pa / 1e3), 36.0))
            answer = await worker.pressures_for(target)
            if worker._fitting is not None:
                await worker._fitting
            assert worker.correction_status()["correction"]["count"] == 151
            estimate = await worker.estimate(answer.pressures_pa)
            assert estimate.gland_volume_ml == pytest.approx(35, abs=0.01)
            # the fitter killed between its store and its fit's end
            recording = asyncio.ensure_future(worker.record_measurement([1.0, 2.0, 0.5], true_ml((1.0, 2.0, 0.5))))
            while len(store.entries()) < 152:
                await asyncio.sleep(0.002)
            for pid in list(worker._fitter._processes):
                os.kill(pid, signal.SIGTERM)
            summary = await recording
            assert len(store.entries()) == 152 and summary["count"] == 152
        finally:
            worker.close()

    run(scenario())


@pytest.mark.slow
@pytest.mark.parametrize("content, why", [
    ("{not json", "is damaged"),
    (json.dumps({"format": "phantom-corrections/1", "measurements": [
        {"pressures_kpa": [1, 1, 1, 1], "volume_ml": 30.0}, {"pressures_kpa": [2, 2, 2, 2], "volume_ml": 33.0}]}),
     "4 pressures, the model 3 chambers: they are of another phantom"),
])
def test_a_damaged_store_or_another_phantoms_starts_the_worker_without_a_correction_and_says_why(data_dir, content,
                                                                                               why):
    """The daemon starts (it must still hold and vent the phantom) with the model's own answers, and its status,
    log and events say why no correction is in force; recording a measurement is refused."""
    from phantom.host.model_worker import ModelWorker

    store = CorrectionStore.for_phantom("bad")
    store.path.parent.mkdir(parents=True)
    store.path.write_text(content)

    async def scenario():
        worker = await ModelWorker.start("builtin:converged", phantom="bad")
        try:
            status = worker.correction_status()
            assert not status["in_force"] and why in status["error"]
            kind, text, level = worker.correction_event()
            assert level == "WARN" and why in text and "'bad'" in text
            with pytest.raises(CorrectionError):
                await worker.record_measurement([1.0, 1.0, 1.0], 30.0)
        finally:
            worker.close()

    run(scenario())


def test_a_phantom_name_no_store_can_have_is_refused_before_anything_starts():
    from phantom.host.model_worker import ModelWorker

    with pytest.raises(CorrectionError, match="a phantom's name is 1-64 letters"):
        run(ModelWorker.start("builtin:converged", phantom="../etc"))


@pytest.mark.sim
def test_a_daemon_on_the_simulated_board_answers_with_the_stored_scans_follows_the_store_and_keeps_it_over_a_restart(
        tmp_path, data_dir, loaded, default_model_cached):
    """End to end: `phantom daemon --phantom scanned` on the simulated board with three stored scans (stand-ins:
    the simulated phantom's true volumes) sets a 35 ml target on other pressures than the model alone would, its
    status and `phantom status` show the correction, a scan added by another writer is in force at the next
    estimate, the recording holds the correction's series and the model's own estimate beside the corrected one,
    and a daemon started again on the same board answers with all four."""
    from daemon_rig import DaemonRig

    from phantom.host.recording import read_rrd

    store = CorrectionStore.for_phantom("scanned")
    for pressures in ((0, 0, 0), (2, 0, 0), (0, 2, 0)):
        store.add(Measurement(tuple(map(float, pressures)), true_ml(pressures)))
    plain_kpa = loaded.pressures_for(Target(gland_volume_m3=35 * ML)).pressures_pa / 1e3
    first = tmp_path / "first"
    first.mkdir()
    rig = DaemonRig(first, "--phantom", "scanned", "--rerun-save", str(first / "run.rrd"))
    board = rig.board
    rig.own_board = False
    try:
        rig.wait_online()
        status = rig.status()
        assert status["correction"]["in_force"] and status["correction"]["correction"]["count"] == 3
        assert status["correction"]["phantom"] == "scanned"
        answer = rig.call("set_target", {"volume_ml": 35.0})
        solution = rig.wait_status(lambda s: s["solution"] is not None, 10, "a solution")["solution"]
        assert solution["predicted_volume_ml"] == pytest.approx(35, abs=0.01), answer
        assert np.max(np.abs(np.array(solution["pressures_kpa"]) - plain_kpa)) > 0.05
        shown = rig.cli("status")
        assert "corrected yes: " in shown.stdout and "from 3 measurement(s) of phantom 'scanned'" in shown.stdout
        store.add(Measurement((1.0, 1.0, 1.0), true_ml((1, 1, 1))))
        rig.wait_status(lambda s: (s["correction"]["correction"] or {}).get("count") == 4, 60, "the 4th scan")
        rig.wait_status(lambda s: s["estimated_volume_ml"] is not None, 10, "an estimate")
        rig.process.send_signal(signal.SIGTERM)
        rig.process.wait(30)
    finally:
        rig.close()
    recording = read_rrd(first / "run.rrd")
    assert recording["/correction/measurements"] and recording["/volume/uncorrected_ml"], sorted(recording)
    second = tmp_path / "second"
    second.mkdir()
    rig = DaemonRig(second, "--phantom", "scanned", board=board)
    try:
        rig.wait_online()
        assert rig.status()["correction"]["correction"]["count"] == 4
    finally:
        rig.close()
        board.stop()


def test_phantom_daemon_with_a_bad_phantom_name_stops_its_start_with_one_line(tmp_path):
    import subprocess
    import sys
    from pathlib import Path

    result = subprocess.run([str(Path(sys.executable).with_name("phantom")), "daemon", "--port",
                             str(tmp_path / "no-board"), "--socket", str(tmp_path / "d.sock"), "--phantom", "../x"],
                            capture_output=True, text=True, timeout=120)
    assert result.returncode == 2
    assert "phantom daemon: error: a phantom's name is 1-64 letters" in result.stderr and "'../x'" in result.stderr
