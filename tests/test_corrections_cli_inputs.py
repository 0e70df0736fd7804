"""Bad input to `phantom corrections export` and `phantom calibrate`, refused at once, in the command line's terms:
an export over the store itself or over a file already there, a measurements CSV in ul (mm^3), an --output that is a
folder, and out-of-range --gent-jm, --grid and --size-mm values blamed on the flag, not on the scene file. No test
here runs a fit: `calibrate` and its cluster are replaced by ones that fail the test if they are reached."""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest

from phantom.cli.main import main
from phantom.model.calibration.calibrate import CalibrationError, load_measurements
from phantom.model.measurements import CorrectionStore

MEASUREMENTS = Path(__file__).resolve().parent.parent / "model" / "data" / "forward_measurements.csv"


def _stored(data_dir, name="default"):
    """A store of one measurement, written directly (no model is built)."""
    store = CorrectionStore.for_phantom(name)
    store.path.parent.mkdir(parents=True, exist_ok=True)
    store.path.write_text(json.dumps({"format": "phantom-corrections/1", "measurements": [
        {"pressures_kpa": [1, 1, 1], "volume_ml": 30.0, "method": "water_displacement",
         "time_utc": "2026-01-01T00:00:00+00:00"}]}))
    return store


# ------------------------------------------------------------------------------------- corrections export --out
@pytest.mark.parametrize("how", ["relative", "absolute", "symlink", "symlinked folder", "replace"])
def test_export_never_writes_over_the_store_itself(data_dir, tmp_path, capsys, how):
    store = _stored(data_dir)
    before = store.path.read_text()
    out = {"relative": "data/corrections/default.json", "absolute": str(store.path), "replace": str(store.path),
           "symlink": "link.json", "symlinked folder": "linked/default.json"}[how]
    if how == "symlink":
        os.symlink(store.path, tmp_path / "link.json")
    if how == "symlinked folder":
        os.symlink(store.path.parent, tmp_path / "linked")
    argv = ["corrections", "export", "--out", out] + (["--replace"] if how == "replace" else [])
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert f"--out {out} is the correction store of phantom 'default' ({store.path})" in err, err
    assert "give another --out" in err
    assert store.path.read_text() == before
    assert main(["corrections", "list"]) == 0
    assert "1 measurement(s)" in capsys.readouterr().out


def test_export_refuses_a_file_already_there_unless_replace(data_dir, tmp_path, capsys):
    _stored(data_dir)
    out = tmp_path / "copy.csv"
    out.write_text("keep me\n")
    assert main(["corrections", "export", "--out", str(out)]) == 2
    assert (f"phantom corrections: error: --out {out} exists already: give another --out, or --replace to write "
            f"over it") in capsys.readouterr().err
    assert out.read_text() == "keep me\n"
    assert main(["corrections", "export", "--out", str(out), "--replace"]) == 0
    assert out.read_text().startswith("p0_kpa,p1_kpa,p2_kpa,measured_ml")


def test_export_to_a_folder_says_it_is_a_folder(data_dir, tmp_path, capsys):
    _stored(data_dir)
    (tmp_path / "adir").mkdir()
    for argv in (["--out", "adir"], ["--out", "adir", "--replace"]):
        assert main(["corrections", "export", *argv]) == 2
        err = capsys.readouterr().err
        assert "--out adir is a folder: give the CSV file to write" in err, err
        assert "free space" not in err


# ------------------------------------------------------------------------------------- calibrate
@pytest.fixture
def no_fit(monkeypatch):
    """`calibrate` and its cluster fail the test if reached: a refusal comes before the slow work."""
    import phantom.cli.calibrate as calibrate_cli
    import phantom.model.calibration.calibrate as calibration

    def reached(*args, **kwargs):
        raise AssertionError("the fit was started")

    monkeypatch.setattr(calibration, "calibrate", reached)
    monkeypatch.setattr(calibrate_cli, "local_cluster_deaf_to_ctrl_c", reached)


def test_a_measurements_csv_in_ul_is_refused_naming_the_file_row_and_unit(tmp_path):
    path = tmp_path / "c_ul.csv"
    path.write_text("p0_kpa,p1_kpa,p2_kpa,measured_ml\n0,0,0,26400\n1,1,1,30000\n2,2,2,40000\n1,0,0,28000\n")
    with pytest.raises(CalibrationError, match=r"c_ul.csv, data row 1: measured_ml must be a whole gland's volume, "
                                               r"a finite number of ml within 2-400 ml: in ml\? got 26400, which is "
                                               r"26.4 ml in mm\^3: convert it"):
        load_measurements(path, n_chambers=3)
    path.write_text("p0_kpa,measured_ml\n0,26\n1,27\n2,1000\n")
    with pytest.raises(CalibrationError, match=r"data row 3: measured_ml must be a whole gland's volume, a finite "
                                               r"number of ml within 2-400 ml, got 1000"):
        load_measurements(path)
    path.write_text("p0_kpa,measured_ml\n0,26\n1,0.027\n2,28\n")   # litres
    with pytest.raises(CalibrationError, match=r"data row 2: .* which is 27 ml in litres"):
        load_measurements(path)


def test_calibrate_refuses_a_measurements_csv_in_ul_before_any_fit(data_dir, tmp_path, capsys, no_fit):
    path = tmp_path / "c_ul.csv"
    path.write_text("p0_kpa,p1_kpa,p2_kpa,measured_ml\n0,0,0,26400\n1,1,1,30000\n2,2,2,40000\n1,0,0,28000\n")
    assert main(["calibrate", "--measurements", str(path), "--output", "out.toml", "--workers", "1"]) == 2
    assert "data row 1: measured_ml must be a whole gland's volume" in capsys.readouterr().err
    assert not (tmp_path / "out.toml").exists()


@pytest.mark.parametrize("output, message", [
    ("adir", "--output adir is a folder: give the file to write, e.g. adir/prostate_calibrated.toml"),
    ("afile/out.toml", "--output afile/out.toml: afile is not a folder"),
    ("ro/out.toml", "--output ro/out.toml: the folder ro is not writable"),
])
def test_calibrate_checks_output_before_any_fit(data_dir, tmp_path, capsys, monkeypatch, no_fit, output, message):
    (tmp_path / "adir").mkdir()
    (tmp_path / "afile").write_text("")
    (tmp_path / "ro").mkdir(mode=0o555)
    access = os.access  # root writes any folder: "ro" is made unwritable for it too
    monkeypatch.setattr(os, "access", lambda path, mode: access(path, mode) and Path(path).name != "ro")
    assert main(["calibrate", "--measurements", str(MEASUREMENTS), "--output", output]) == 2
    assert message in capsys.readouterr().err


@pytest.mark.parametrize("argv, message", [
    (["--material", "gent", "--gent-jm", "-1"], "--gent-jm must be the locking value of I1 - 3 (a positive number, "
                                                "e.g. 20 for silicone), got -1"),
    (["--material", "gent", "--gent-jm", "nan"], "--gent-jm must be the locking value of I1 - 3"),
    (["--gent-jm", "5"], "--gent-jm applies to the Gent law only (the scene's law is 'corotational'): add "
                         "--material gent"),
    (["--grid", "poisson_ratio=0.6,0.7"], "--grid poisson_ratio must lie in (-1, 0.5), got 0.6"),
    (["--grid", "lobe_chamber_scale=1,5"], "--grid lobe_chamber_scale must lie in [0.3, 2.5], got 5"),
    (["--material", "gent", "--grid", "gent_jm=-2,5"], "--grid gent_jm must be the locking value of I1 - 3"),
    (["--size-mm", "0"], "--size-mm must lie in [0.3, 10], got 0"),
    (["--size-mm", "20"], "--size-mm must lie in [0.3, 10], got 20"),
])
def test_calibrate_blames_the_flag_not_the_scene_for_a_value_out_of_range(data_dir, capsys, no_fit, argv, message):
    assert main(["calibrate", "--measurements", str(MEASUREMENTS), "--output", "out.toml", *argv]) == 2
    err = capsys.readouterr().err
    assert message in err, err
    assert "prostate.toml" not in err and "scene " not in err
