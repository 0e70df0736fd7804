"""``phantom inverse`` refuses what a command-line user got wrong in the user's words: the flag, its unit (ml, kPa)
and the command line's syntax, never the library's argument names and SI units, and before any model is built."""

import json
import os

import pytest

from phantom.cli import inverse
from phantom.cli import main as cli
from phantom.model import PhantomModel

LIBRARY_WORDS = ("_m3", "_pa", "None", "{1: 2.0")


@pytest.fixture
def no_model(monkeypatch):
    """A refusal comes before the finite-element model is built (fast, and nothing of it in the message)."""
    def built(*args, **kwargs):
        pytest.fail("the model was built before the arguments were checked")
    monkeypatch.setattr(PhantomModel, "from_scene", built)


def refusal(capsys, *arguments: str) -> str:
    assert cli.main(["inverse", *arguments]) == 2
    captured = capsys.readouterr()
    assert captured.out == ""
    message = captured.err
    assert message.startswith("phantom inverse: error: ") and message.count("\n") == 1
    for word in LIBRARY_WORDS:
        assert word not in message
    return message


@pytest.mark.parametrize("value", ["nan", "inf", "-inf", "0", "-5"])
def test_volume_must_be_a_positive_finite_number_of_ml(capsys, no_model, value):
    message = refusal(capsys, f"--volume-ml={value}")
    assert "--volume-ml" in message and "ml" in message and "32" in message


def test_chamber_volumes_need_one_entry_per_chamber(capsys, no_model):
    message = refusal(capsys, "--chamber-volumes-ml", "1,2")
    assert "--chamber-volumes-ml has 2 entries; the scene has 3 chambers (0 base, 1 left lobe, 2 right lobe)" in message
    assert "'-' for a free chamber" in message


@pytest.mark.parametrize("text", [",,", "-,-,-", "-, ,-"])
def test_chamber_volumes_that_leave_every_chamber_free_are_refused(capsys, no_model, text):
    message = refusal(capsys, "--chamber-volumes-ml", text)
    assert "--chamber-volumes-ml leaves every chamber free" in message
    assert "at least one chamber's volume (ml)" in message and "4,-,-" in message


def test_raw_pressures_need_one_per_chamber(capsys, no_model):
    message = refusal(capsys, "--pressures-kpa", "1,1")
    assert "--pressures-kpa has 2 values; the scene has 3 chambers" in message


def test_raw_pressures_are_checked_against_the_bound_given(capsys, no_model):
    message = refusal(capsys, "--pressures-kpa", "1,1,2.5", "--pressure-max-kpa", "2")
    assert "right lobe (chamber 2) at 2.5 kPa is above the 2 kPa limit" in message


@pytest.mark.parametrize("value", ["-1", "0", "nan", "inf"])
def test_pressure_bound_must_be_a_positive_number_of_kpa(capsys, no_model, value):
    message = refusal(capsys, "--volume-ml", "32", "--pressure-max-kpa", value)
    assert "--pressure-max-kpa" in message and "kPa" in message
    assert "-1000" not in message


@pytest.mark.parametrize("ratio, words", [
    ("chamber1=-1", "--growth-ratio weights must be positive"),
    ("chamber1=2", "--growth-ratio relates at least two chambers"),
    ("chamber1=2,chamber2=-1", "--growth-ratio weights must be positive"),
    ("chamber1=2,chamber2=0", "--growth-ratio weights must be positive"),
    ("chamber1=2,1=1", "--growth-ratio names chamber 1 twice"),
])
def test_growth_ratio_is_refused_in_the_command_line_syntax(capsys, no_model, ratio, words):
    message = refusal(capsys, "--volume-ml", "32", "--growth-ratio", ratio)
    assert words in message
    assert "chamber1=2,chamber2=1" in message


def test_growth_limits_need_one_per_chamber_and_none_negative(capsys, no_model):
    assert "--max-growth-ml has 2 values; the scene has 3 chambers" in refusal(
        capsys, "--volume-ml", "32", "--max-growth-ml", "1,2")
    assert "--max-growth-ml" in refusal(capsys, "--volume-ml", "32", "--max-growth-ml", "-1,-,-")


def test_a_bound_above_the_shipped_table_is_refused_in_kpa_with_what_to_do(capsys, no_model):
    message = refusal(capsys, "--volume-ml", "32", "--pressure-max-kpa", "4")
    assert "--pressure-max-kpa 4 is above the 3 kPa" in message
    assert "give at most 3" in message and "--fidelity" in message
    assert "3000" not in message and "4000" not in message


def test_a_bound_below_the_shipped_table_is_honoured_with_the_table(capsys):
    assert cli.main(["inverse", "--volume-ml", "32", "--pressure-max-kpa", "2", "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["fidelity"] == "table"
    assert max(report["pressures_kpa"]) <= 2 + 1e-9
    assert report["predicted_volume_ml"] == pytest.approx(32, rel=1e-3)


def test_what_the_solver_library_prints_to_stdout_stays_off_it(capfd):
    with inverse._solver_output_silenced():
        os.write(1, b"Polishing not needed - no active set detected at optimal point\n")
    print("after")
    assert capfd.readouterr().out == "after\n"


def test_a_volume_beyond_the_bound_asked_says_to_raise_that_bound_not_the_scenes(capsys):
    """A target out of reach under --pressure-max-kpa below the scene's bound: raising the scene's pressure_max_kpa
    (what the message said) changes nothing; the bound asked is what to raise, as far as the scene's."""
    message = refusal(capsys, "--volume-ml", "45", "--pressure-max-kpa", "1")
    assert "between 0 and [1, 1, 1] kPa give 26.296 to 29.239 ml" in message, message
    assert message.rstrip().endswith("raise the pressure bound asked, up to the scene's pressure_max_kpa (3 kPa)")
    message = refusal(capsys, "--volume-ml", "60")
    assert message.rstrip().endswith("between 0 and [3, 3, 3] kPa give 26.296 to 51.581 ml; ask for a volume in "
                                     "that range or raise the scene's pressure_max_kpa"), message
