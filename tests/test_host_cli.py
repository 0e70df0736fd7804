"""The daemon's command line, its config file and the systemd unit, without a board."""

import configparser
import subprocess
import sys
from pathlib import Path

import pytest

from phantom import PhantomError
from phantom.cli.daemon import CONFIG_KEYS, format_steps, load_config

PHANTOM = Path(sys.executable).with_name("phantom")
HOST = Path(__file__).resolve().parent.parent / "host"


def run_phantom(*arguments, env=None):
    return subprocess.run([str(PHANTOM), *arguments], capture_output=True, text=True, timeout=120, env=env)


def test_the_shipped_config_file_is_valid_and_uses_known_keys():
    table = load_config(HOST / "systemd" / "phantomd.toml")
    assert set(table) <= set(CONFIG_KEYS)
    assert table["socket"] == "/run/phantom/phantomd.sock" and table["port"].startswith("/dev/serial/by-id/")


@pytest.mark.parametrize(("text", "message"), [
    ("[daemon]\nprot = '/dev/ttyACM0'\n", "unknown key.*prot"),
    ("[daemon]\nsim = 'yes'\n", "sim must be a bool"),
    ("[daemon]\nbaud = true\n", "baud must be a int"),
    ("[daemon\n", "not valid TOML"),
])
def test_bad_config_files_are_refused_with_the_key(tmp_path, text, message):
    path = tmp_path / "phantomd.toml"
    path.write_text(text)
    with pytest.raises(PhantomError, match=message):
        load_config(path)
    with pytest.raises(PhantomError, match="does not exist"):
        load_config(tmp_path / "missing.toml")


def test_systemd_unit_restarts_on_failure_vents_on_sigterm_and_uses_the_serial_group():
    unit = configparser.ConfigParser(strict=False, interpolation=None)
    unit.optionxform = str
    unit.read(HOST / "systemd" / "phantomd.service")
    service = unit["Service"]
    assert service["Restart"] == "on-failure"
    assert "dialout" in service["SupplementaryGroups"]
    assert service["KillSignal"] == "SIGTERM" and service["KillMode"] == "mixed"
    assert service["ExecStart"].endswith("phantom daemon --config /etc/phantom/phantomd.toml")
    assert service["RuntimeDirectory"] == "phantom"
    assert unit["Install"]["WantedBy"] == "multi-user.target"


def test_daemon_needs_exactly_one_board(tmp_path):
    both = run_phantom("daemon", "--port", "/dev/null", "--sim")
    assert both.returncode == 2 and "not allowed with argument" in both.stderr
    none = run_phantom("daemon", "--socket", str(tmp_path / "d.sock"))
    assert none.returncode == 2
    assert none.stderr.strip() == ("phantom daemon: error: give exactly one board: --port DEV, --sim, or "
                                   "--can-channel CH")


def test_client_usage_errors_are_one_line(tmp_path):
    ratio = run_phantom("set", "--pressures-kpa", "1,1,1", "--growth-ratio", "chamber1=2", "--socket",
                        str(tmp_path / "none.sock"))
    assert ratio.returncode == 2 and "--growth-ratio goes with --volume-ml" in ratio.stderr
    scene = run_phantom("run-scene", "no_such_scene", "--socket", str(tmp_path / "none.sock"))
    assert scene.returncode == 2 and "no example scene 'no_such_scene'; shipped: bph_growth, lopsided" in scene.stderr
    target = run_phantom("set", "--socket", str(tmp_path / "none.sock"))
    assert target.returncode == 2 and "one of the arguments" in target.stderr


def test_the_step_table_has_a_row_per_step_with_blanks_for_unknowns():
    table = format_steps([
        {"index": 0, "at_s": 0.0, "target": "30.00 ml", "target_volume_ml": 30.0, "reached_volume_ml": 29.98,
         "error_pct": -0.0667, "reached_after_s": 1.25},
        {"index": 1, "at_s": 30.0, "target": "pressures 1.00,1.00,1.00 kPa", "target_volume_ml": None,
         "reached_volume_ml": 31.0, "error_pct": None, "reached_after_s": None},
    ]).splitlines()
    assert len(table) == 3 and "time to 1 %" in table[0]
    assert table[1].split() == ["0", "0.0", "30.00", "ml", "30.00", "29.98", "-0.07", "1.2"]
    assert table[2].split()[-3:] == ["31.00", "-", "-"]


@pytest.mark.parametrize("command", ["set", "inverse"])
def test_a_list_starting_with_a_free_chamber_is_a_value_not_an_option(command):
    from phantom.cli.main import build_parser, join_list_values

    args = build_parser().parse_args(join_list_values([command, "--chamber-volumes-ml", "-,3.5,3.5"]))
    assert args.chamber_volumes_ml == "-,3.5,3.5"
    assert join_list_values(["set", "--volume-ml", "32", "--json"]) == ["set", "--volume-ml", "32", "--json"]


def test_every_host_subcommand_has_a_description_and_json():
    import argparse

    from phantom.cli import daemon as commands

    parser = argparse.ArgumentParser()
    subparsers = parser.add_subparsers()
    commands.register(subparsers)
    for name, subparser in subparsers.choices.items():
        assert subparser.description, name
        if name != "daemon":
            assert "--json" in subparser.format_help(), name


def test_the_text_answers_of_vent_clear_fault_and_zero():
    from phantom.cli.daemon import format_simple, watch_header

    assert format_simple("vent", {"vented": True}).startswith("vented")
    assert format_simple("clear_fault", {"cleared": ["SENSOR_1"], "setpoints_restored": True}) == (
        "faults cleared: SENSOR_1; the target's setpoints restored")
    assert format_simple("zero", {"zeroed": True}) == "sensors zeroed"
    assert "left l" in watch_header(["base", "left lobe", "right lobe"])


def test_format_steps_adds_the_true_volume_only_when_known():
    step = {"index": 0, "at_s": 0.0, "target": "30.00 ml", "target_volume_ml": 30.0, "reached_volume_ml": 30.1,
            "error_pct": 0.33, "reached_after_s": 1.0, "true_volume_ml": None}
    assert "true ml" not in format_steps([step])
    table = format_steps([{**step, "true_volume_ml": 29.8}])
    assert "true ml" in table.splitlines()[0] and "29.80" in table.splitlines()[1]
