"""The ``phantom`` console script as a user meets it: installed, on PATH, with clear usage errors."""

import json
import re
import subprocess
import sys
from pathlib import Path

import pytest

import phantom
from phantom.cli import common
from phantom.cli import main as cli

PHANTOM = Path(sys.executable).with_name("phantom")


def run_phantom(*arguments: str) -> subprocess.CompletedProcess:
    return subprocess.run([str(PHANTOM), *arguments], capture_output=True, text=True, timeout=120)


def test_console_script_reports_the_package_version():
    result = run_phantom("--version")
    assert result.returncode == 0
    assert result.stdout.strip() == f"phantom {phantom.__version__}"


def test_missing_subcommand_is_a_usage_error():
    result = run_phantom()
    assert result.returncode == 2
    assert "usage: phantom" in result.stderr


def test_unknown_subcommand_names_the_choices():
    result = run_phantom("no-such-command")
    assert result.returncode == 2
    assert "invalid choice: 'no-such-command'" in result.stderr


def test_user_errors_print_one_line_and_exit_2(capsys, monkeypatch):
    def fails(args):
        raise phantom.PhantomError("the scene file x.toml does not exist: check the path")

    parser = cli.build_parser()
    parser.parse_args = lambda argv=None: type("Args", (), {"command": "demo", "run": staticmethod(fails)})()
    monkeypatch.setattr(cli, "build_parser", lambda: parser)
    assert cli.main([]) == 2
    assert capsys.readouterr().err == "phantom demo: error: the scene file x.toml does not exist: check the path\n"


def test_cache_dir_honours_the_override(tmp_path, monkeypatch):
    monkeypatch.setenv("PHANTOM_CACHE_DIR", str(tmp_path))
    assert phantom.cache_dir("meshes") == tmp_path / "meshes"
    assert (tmp_path / "meshes").is_dir()


def test_number_lists_parse_free_entries_and_refuse_bad_items():
    assert common.parse_numbers("1, 1.5,0", "--pressures-kpa") == [1.0, 1.5, 0.0]
    assert common.parse_numbers("-,3.5,", "--chamber-volumes-ml", allow_free=True) == [None, 3.5, None]
    with pytest.raises(phantom.PhantomError, match=r"--pressures-kpa takes comma-separated numbers .* 'x' is not"):
        common.parse_numbers("1,x,2", "--pressures-kpa")
    with pytest.raises(phantom.PhantomError, match="'-' is not a number"):
        common.parse_numbers("1,-,2", "--pressures-kpa")
    with pytest.raises(phantom.PhantomError, match="'nan' is not a finite number"):
        common.parse_numbers("1,nan,2", "--pressures-kpa")


def test_growth_ratios_are_name_weight_pairs():
    assert common.parse_growth_ratio("chamber1=2, chamber2=1") == {"chamber1": 2.0, "chamber2": 1.0}
    with pytest.raises(phantom.PhantomError, match="NAME=WEIGHT pairs"):
        common.parse_growth_ratio("1:2,2:1")
    with pytest.raises(phantom.PhantomError, match="not a number"):
        common.parse_growth_ratio("chamber1=big")


@pytest.mark.parametrize("pressures, words", [
    ("-1,0,0", r"base \(chamber 0\) at -1 kPa is below 0 kPa: the blowers only push"),
    ("1,3.5,0", r"left lobe \(chamber 1\) at 3.5 kPa is above the 3 kPa limit, which protects the phantom"),
])
def test_offline_commands_refuse_what_the_daemon_refuses_in_its_words(tmp_path, pressures, words):
    """phantom forward computed a suction result for -1 kPa, which the daemon refuses; every command now refuses
    pressures the daemon would, with the same message, before building the model."""
    from phantom.host.scenes import parse_target
    from phantom.model.errors import SceneError
    from phantom.model.fem.model import PhantomModel
    from phantom.model.inverse import InverseSolver
    from phantom.model.scene import load_scene
    from phantom.model.target import Target, UnreachableTargetError

    scene = load_scene("builtin:converged")
    values = [float(value) for value in pressures.split(",")]
    if min(values) < 0:  # the daemon's set_target refuses it when it parses the target
        with pytest.raises(SceneError) as refused:
            parse_target({"pressures_kpa": values}, scene.chambers, "set_target", scene.chamber_labels)
        daemon_words = str(refused.value).removeprefix("set_target: ")
    else:  # above the limit: its inverse refuses it against the model's limit
        solver = InverseSolver(PhantomModel.from_scene(scene), fidelity="rest")
        with pytest.raises(UnreachableTargetError) as refused:
            solver.pressures_for(Target(pressures_pa=[value * 1e3 for value in values]))
        daemon_words = str(refused.value)
    assert re.search(words, daemon_words)
    commands = [("forward", "--scene", "builtin:converged", "--pressures-kpa", pressures),
                ("scan", "synthetic", "--scene", "builtin:converged", "--out", str(tmp_path / "s.ply"),
                 "--pressures-kpa", pressures),
                ("compare-scan", str(tmp_path / "none.ply"), "--scene", "builtin:converged", "--pressures-kpa",
                 pressures)]
    for command in commands:
        result = run_phantom(*command)
        assert result.returncode == 2 and result.stderr.strip().endswith(f"--pressures-kpa: {daemon_words}"), (
            command, result.stderr)



@pytest.mark.slow  # two 10-node solves and a mesh
def test_the_offline_commands_run_on_the_shipped_model_without_a_scene(tmp_path):
    """The README says the offline commands run on ``builtin:converged``; ``forward`` and ``mesh`` asked for
    ``--scene`` (an argparse error), ``inverse`` did not."""
    result = run_phantom("forward", "--pressures-kpa", "1,1,1", "--json")
    assert result.returncode == 0, result.stderr
    named = run_phantom("forward", "--scene", "builtin:converged", "--pressures-kpa", "1,1,1", "--json")
    assert json.loads(result.stdout)["total_volume_ml"] == json.loads(named.stdout)["total_volume_ml"]
    result = run_phantom("mesh", "--out", str(tmp_path / "prostate.msh"), "--json")
    assert result.returncode == 0, result.stderr
    assert (tmp_path / "prostate.msh").stat().st_size > 0


def test_progress_in_a_log_is_lines_with_the_time_left_not_carriage_returns(capsys):
    """Progress written with carriage returns made a log file one line; off a terminal it is a line every so
    often and at the end, and its time left counts from the first report (not the set-up before it). (Its own
    clock: a process-wide time.monotonic patched here stopped the event loop of a Dask cluster another test had
    started in the same worker.)"""
    clock = iter([100.0, 110.0, 130.0, 150.0])
    report = common.progress_reporter("calibrate: stage 1:", every_s=15.0, clock_s=lambda: next(clock))
    for done in (2, 4, 6, 10):
        report(done, 10)
    lines = capsys.readouterr().err.split("\n")
    assert "\r" not in "".join(lines)
    assert lines[:3] == ["calibrate: stage 1: 2/10, 0 s", "calibrate: stage 1: 6/10, 30 s, about 30 s left",
                         "calibrate: stage 1: 10/10, 50 s"]


def test_a_verified_targets_rounds_are_printed_as_they_come_with_the_seconds_since_it_was_set(capsys):
    """``phantom set --verify`` and ``make demo`` print the daemon's texts with one printer: a round takes a
    minute, and the seconds say how the target is going."""
    clock = iter([1000.0, 1004.2, 1047.0, 1085.6])
    tell = common.progress_printer("    ", clock_s=lambda: next(clock))
    tell("target 40.00 ml: round 1 settled (estimate 40.00 ml): scanning")
    assert capsys.readouterr().err == "       4 s  target 40.00 ml: round 1 settled (estimate 40.00 ml): scanning\n"
    tell("round 1 scanned 38.94 ml")
    tell("round 2 settled")
    assert capsys.readouterr().err.splitlines() == ["      47 s  round 1 scanned 38.94 ml",
                                                    "      86 s  round 2 settled"]


def test_the_fit_names_its_stages():
    from phantom.cli.calibrate import fit_progress

    shown = []
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(common, "progress_reporter", lambda label: lambda done, total: shown.append((label, done)))
        report = fit_progress(n_measurements=8)
        for done, total in ((0, 48), (48, 48), (0, 2), (2, 2), (0, 8), (8, 8)):
            report(done, total)
    stages = list(dict.fromkeys(label for label, _ in shown))
    assert [label.split(",")[0] for label in stages] == ["calibrate: stage 1", "calibrate: stage 2",
                                                         "calibrate: stage 3"]
    assert "pressure rays" in stages[0] and "left-out" in stages[1] and "verifying the fit" in stages[2]


def test_calibrate_record_recommends_the_fit_the_readme_recommends():
    from phantom.cli.calibrate import recommended_fit

    readme = (Path(__file__).parents[1] / "README.md").read_text().replace("\\\n", " ")
    assert " ".join(recommended_fit("my_phantom.csv").split()) in " ".join(readme.split())


def test_phantom_status_says_what_became_of_a_reached_target_after_an_interruption_in_the_daemons_words():
    """The status's target_after_interruption, after its control line; the words for what interrupted it are the
    daemon's (its "held again after ..." event) and the panel's."""
    from phantom.cli.client import INTERRUPTION_WORDS, _after_interruption
    from phantom.host.control import AFTER_WORDS

    assert INTERRUPTION_WORDS == AFTER_WORDS
    panel = (Path(__file__).resolve().parent.parent / "host" / "panel" / "panel.js").read_text()
    for after, words in AFTER_WORDS.items():
        assert f'"{after}": "{words}"' in panel
    assert _after_interruption(None) == ""
    assert _after_interruption({"state": "not_held", "after": "fault"}) == (
        "; not held since the fault: its setpoints go again once it is cleared")
    assert _after_interruption({"state": "not_held", "after": "board restart"}) == (
        "; not held since the board restarted: its setpoints go to the board again")
    assert _after_interruption({"state": "settling", "after": "link loss"}) == (
        "; settling again after the link was lost")
    assert _after_interruption({"state": "held_again", "after": "board restart"}) == (
        "; held again after the board restarted")
