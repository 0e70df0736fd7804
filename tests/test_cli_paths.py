"""Paths and numbers given to `phantom inverse`, `compare-scan`, `scan import` and `corrections add` refused at once,
in the command line's terms: a folder where a file goes said to be a folder (not "no such file"), a scan file that
is not there, a volume that is not one blamed on --volume-ml, and --refine-solves without --shape. No test here
builds a model: the model's builders are replaced by ones that fail the test if they are reached."""

from __future__ import annotations

import pytest

from phantom.cli.main import main


class ModelReached(BaseException):
    """Raised where a model would be built: a BaseException, so that ``main`` does not report it as a bug."""


def _unreached(*args, **kwargs):
    raise ModelReached("the model was reached")


@pytest.fixture
def no_model(monkeypatch):
    """Building a model (or the corrections' grid of model volumes) fails the test."""
    from phantom.model import PhantomModel
    from phantom.model import corrections as model_corrections

    monkeypatch.setattr(PhantomModel, "from_scene", classmethod(lambda cls, *a, **k: _unreached()))
    monkeypatch.setattr(model_corrections, "model_grid", _unreached)


def _refused(argv: list[str], capsys: pytest.CaptureFixture[str]) -> str:
    assert main(argv) == 2
    lines = [line for line in capsys.readouterr().err.splitlines()
             if not line.startswith("phantom: compiling the model's kernels")]  # numba's notice, once a process
    assert len(lines) == 1, lines
    return lines[0]


# ------------------------------------------------------------------------------- a folder where a file goes
@pytest.mark.parametrize(("argv", "said"), [
    (["inverse", "--shape", "adir", "--scene", "builtin"],
     "--shape adir is a folder: give a NIfTI mask (.nii, .nii.gz) or a closed mesh file"),
    (["compare-scan", "adir", "--scene", "builtin:calibrated", "--pressures-kpa", "1,2,0.5", "--out", "cmpout"],
     "the scan file adir is a folder: give the scan's mesh file (.obj, .ply or .stl)"),
    (["scan", "import", "adir", "--out", "x.ply"],
     "the mesh adir is a folder: give the tool's mesh file (.obj, .ply or .stl)"),
])
def test_a_folder_given_for_a_file_is_said_to_be_a_folder(data_dir, tmp_path, capsys, no_model, argv, said):
    (tmp_path / "adir").mkdir()
    err = _refused(argv, capsys)
    assert said in err, err
    assert "no such file" not in err and "does not exist" not in err
    assert not (tmp_path / "x.ply").exists()


@pytest.mark.parametrize("argv", [
    ["inverse", "--shape", "missing.stl", "--scene", "builtin"],
    ["compare-scan", "missing.ply", "--scene", "builtin:calibrated", "--pressures-kpa", "1,2,0.5"],
    ["scan", "import", "missing.ply", "--out", "x.ply"],
])
def test_a_missing_file_is_still_said_to_be_missing(data_dir, capsys, no_model, argv):
    err = _refused(argv, capsys)
    assert "missing" in err and ("no such file" in err or "does not exist" in err), err


# ---------------------------------------------------------------------------------- corrections add --scan-file
ADD = ["corrections", "add", "--pressures-kpa", "1,1,1", "--method", "scan"]


@pytest.mark.parametrize(("scan_file", "said"), [
    ("/nonexist.ply", "--scan-file /nonexist.ply does not exist: check the path"),
    ("adir", "--scan-file adir is a folder: give the scan's mesh file"),
])
def test_corrections_add_refuses_a_scan_file_that_is_not_there(data_dir, tmp_path, capsys, no_model, scan_file,
                                                               said):
    (tmp_path / "adir").mkdir()
    err = _refused([*ADD, "--volume-ml", "30", "--scan-file", scan_file], capsys)
    assert said in err, err
    assert not (data_dir / "corrections" / "default.json").exists()


# ---------------------------------------------------------------------------------- corrections add --volume-ml
@pytest.mark.parametrize("volume", ["nan", "inf", "-5", "0", "1e6"])
def test_corrections_add_blames_a_bad_volume_on_the_flag(data_dir, capsys, no_model, volume):
    err = _refused([*ADD, "--volume-ml", volume], capsys)
    assert "--volume-ml" in err and "(volume_ml)" not in err, err
    assert not (data_dir / "corrections" / "default.json").exists()


def test_corrections_add_names_a_volume_in_another_unit(data_dir, capsys, no_model):
    err = _refused([*ADD, "--volume-ml", "3e-5"], capsys)  # 30 ml in m^3
    assert "--volume-ml" in err and "in ml?" in err and "convert it" in err, err


@pytest.mark.parametrize("pressures", ["-1,1,1", "1,2000,1"])
def test_corrections_add_blames_bad_pressures_on_the_flag(data_dir, capsys, no_model, pressures):
    err = _refused(["corrections", "add", "--pressures-kpa", pressures, "--volume-ml", "30"], capsys)
    assert "--pressures-kpa" in err and "(pressures_kpa)" not in err, err


def test_corrections_add_keeps_an_existing_scan_file(data_dir, tmp_path, no_model):
    """A scan file that is there passes the check: the command goes on to the model."""
    (tmp_path / "good.ply").write_text("ply\n")
    with pytest.raises(ModelReached):
        main([*ADD, "--volume-ml", "30", "--scan-file", "good.ply"])


# ------------------------------------------------------------------------------- inverse options of --shape only
@pytest.mark.parametrize("extra", [["--refine-solves", "3"], ["--refine-solves", "0"], ["--labels", "4"],
                                   ["--scale"], ["--out", "answer"]])
def test_inverse_refuses_shape_options_without_shape(data_dir, capsys, no_model, extra):
    err = _refused(["inverse", "--volume-ml", "32", *extra], capsys)
    assert "--labels, --scale, --out and --refine-solves go with --shape" in err, err


def test_inverse_shape_refine_solves_defaults_to_the_models():
    """Without --refine-solves, --shape refines with the model's default number of full solves."""
    from phantom.cli import inverse_shape
    from phantom.cli.main import build_parser
    from phantom.model.shape_inverse import REFINE_SOLVES

    args = build_parser().parse_args(["inverse", "--shape", "gland.stl"])
    assert args.refine_solves is None
    assert inverse_shape.refine_solves(args) == REFINE_SOLVES
    args = build_parser().parse_args(["inverse", "--shape", "gland.stl", "--refine-solves", "0"])
    assert inverse_shape.refine_solves(args) == 0
