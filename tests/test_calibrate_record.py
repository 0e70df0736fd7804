"""`phantom calibrate record` on the simulated board (the real firmware in simavr, a real pty), with the
volumes answered on standard input; its CSV is read back by the calibration's own loader."""

import io
import sys
from pathlib import Path

import numpy as np
import pytest

from phantom import PhantomError
from phantom.model.calibration.calibrate import load_measurements

PHANTOM = Path(sys.executable).with_name("phantom")


def _parse(argv):
    import argparse

    from phantom.cli import calibrate as calibrate_cli

    parser = argparse.ArgumentParser(prog="phantom")
    calibrate_cli.register(parser.add_subparsers(dest="command", required=True))
    return parser.parse_args(argv)


@pytest.mark.sim
def test_record_holds_each_combination_and_writes_the_csv_calibrate_reads(tmp_path, monkeypatch, capsys):
    out = tmp_path / "new" / "measured.csv"
    monkeypatch.setattr(sys, "stdin", io.StringIO("26.4\n31.25\n33.0\n"))
    args = _parse(["calibrate", "record", "--sim", "--points-kpa", "0,0,0;2,0,0;1,1.5,0.5", "--settle-s", "0.3",
                   "--out", str(out)])
    assert args.run(args) == 0
    captured = capsys.readouterr()
    assert captured.err.count("measured gland volume (ml) or scan file?") == 3
    measurements = load_measurements(out, n_chambers=3)
    np.testing.assert_allclose(measurements.pressures_pa, [[0, 0, 0], [2000, 0, 0], [1000, 1500, 500]])
    np.testing.assert_allclose(measurements.volumes_m3 * 1e6, [26.4, 31.25, 33.0])
    # The pressures the board held while each volume was measured are within the settled band.
    held_kpa = np.loadtxt(out, delimiter=",", comments="#", skiprows=3)[:, 4:]
    np.testing.assert_allclose(held_kpa, measurements.pressures_pa / 1e3, atol=0.1)


@pytest.mark.parametrize("argv, answers, message", [
    (["--points-kpa", "0,0,0;4,0,0;1,1,1"], "", r"base \(chamber 0\) at 4 kPa is above the 3 kPa limit"),
    (["--points-kpa", "0,0,0;0,-1,0;1,1,1"], "", r"left lobe \(chamber 1\) at -1 kPa is below 0 kPa: the blowers"),
    (["--points-kpa", "0,0,0;1,1;1,1,1"], "", r"one pressure per chamber \(0 base, 1 left lobe, 2 right lobe\)"),
    (["--points-kpa", "0,0,0;1,1,1"], "", "at least 3"),
])
def test_bad_points_are_refused_before_the_board_starts(tmp_path, monkeypatch, argv, answers, message):
    monkeypatch.setattr(sys, "stdin", io.StringIO(answers))
    args = _parse(["calibrate", "record", "--sim", "--out", str(tmp_path / "m.csv"), *argv])
    with pytest.raises(PhantomError, match=message):
        args.run(args)


def test_a_bad_answer_is_a_one_line_error(monkeypatch):
    from phantom.cli.calibrate import _ask_volume_ml

    for answer, message in (("", "no answer"), ("lots\n", "neither a volume"), ("-3\n", "positive number")):
        monkeypatch.setattr(sys, "stdin", io.StringIO(answer))
        with pytest.raises(PhantomError, match=message):
            _ask_volume_ml("? ")
