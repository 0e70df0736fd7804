"""The daemon's command line, its config file and the systemd unit, without a board."""

import argparse
import configparser
import subprocess
import sys
from pathlib import Path

import pytest

from phantom import PhantomError
from phantom.cli.client import format_steps
from phantom.host.config import ConfigError, DaemonConfig, load_config, merged_config, settings

PHANTOM = Path(sys.executable).with_name("phantom")
HOST = Path(__file__).resolve().parent.parent / "host"


def run_phantom(*arguments, env=None):
    return subprocess.run([str(PHANTOM), *arguments], capture_output=True, text=True, timeout=120, env=env)


def test_the_shipped_config_file_is_valid_and_names_every_setting():
    path = HOST / "systemd" / "phantomd.toml"
    table = load_config(path)
    assert table["socket"] == Path("/run/phantom/phantomd.sock") and table["port"].startswith("/dev/serial/by-id/")
    # every key is there, set or in a comment, so that the file a lab edits shows what it may set
    text = path.read_text()
    missing = [item.name for item in settings() if f"{item.name} = " not in text]
    assert missing == []


@pytest.mark.parametrize(("text", "message"), [
    ("[daemon]\nprot = '/dev/ttyACM0'\n", "unknown key.*prot"),
    ("[daemon]\nsim = 'yes'\n", "\\[daemon\\] sim must be true or false, got 'yes'"),
    ("[daemon]\nbaud = true\n", "\\[daemon\\] baud must be an integer, got True"),
    ("[daemon]\nbaud = 9600.5\n", "baud must be an integer"),
    ("[daemon]\nmesh_hz = nan\n", "mesh_hz must be between 0 and 10, got nan"),
    ("[daemon]\nhost_deadline_ms = 5\n", "host_deadline_ms must be between 50 and 10000, got 5"),
    ("[daemon]\ntelemetry_period_ms = 0\n", "telemetry_period_ms must be between 10 and 1000, got 0"),
    ("[daemon]\nboot_delay_s = -1\n", "boot_delay_s must be between 0 and 60"),
    ("[daemon]\nscene = 3\n", "scene must be a string"),
    ("daemon = 3\n", "daemon must be a table"),
    ("[daemon\n", "not valid TOML"),
])
def test_bad_config_files_are_refused_with_the_key(tmp_path, text, message):
    path = tmp_path / "phantomd.toml"
    path.write_text(text)
    with pytest.raises(ConfigError, match=message) as refused:
        load_config(path)
    assert "\n" not in str(refused.value) and str(path) in str(refused.value)
    with pytest.raises(PhantomError, match="does not exist"):
        load_config(tmp_path / "missing.toml")


def test_a_config_takes_the_file_then_the_flags_and_a_flagged_group_replaces_the_files():
    from_file = {"port": "/dev/ttyACM0", "mesh_hz": 2.0, "rerun_save": Path("a.rrd"), "vent_on_exit": False}
    config = merged_config(from_file, {"mesh_hz": 3.0, "vent_on_exit": None, "port": None})
    assert (config.port, config.mesh_hz, config.rerun_save, config.vent_on_exit) == ("/dev/ttyACM0", 3.0,
                                                                                      Path("a.rrd"), False)
    # --sim on the command line replaces the file's board; --rerun-connect its recording
    config = merged_config(from_file, {"sim": True, "rerun_connect": "rerun+http://127.0.0.1:9876/proxy"})
    assert config.sim and config.port is None and config.rerun_save is None and config.rerun_connect
    assert config.socket is None and config.baud == 115200 and config.zero_on_connect


def test_a_config_needs_one_board_and_values_in_range():
    with pytest.raises(ConfigError, match="^give exactly one board: --port DEV, --sim, or --can-channel CH$"):
        DaemonConfig()
    with pytest.raises(ConfigError, match="give exactly one board"):
        DaemonConfig(sim=True, port="/dev/ttyACM0")
    with pytest.raises(ConfigError, match="give at most one recording: --rerun-save FILE, or --rerun-connect ADDR"):
        merged_config({"sim": True, "rerun_save": "a.rrd", "rerun_connect": "rerun+http://x/proxy"}, {})
    with pytest.raises(ConfigError, match="sim_speed must be between 0 and 100, got -1"):
        DaemonConfig(sim=True, sim_speed=-1)
    assert DaemonConfig(sim=True, rerun_save="x.rrd").rerun_save == Path("x.rrd")


@pytest.mark.parametrize(("config", "keepalive_s", "board_deadline_ms"), [
    (DaemonConfig(port="/dev/ttyACM0"), 0.1, 500),
    (DaemonConfig(sim=True, sim_speed=2.0), 0.05, 1000),        # 500 ms of wall clock at twice real time
    (DaemonConfig(sim=True, sim_speed=0.5), 0.1, 250),
    (DaemonConfig(sim=True, sim_speed=0.0), 0.01, 5000),       # as fast as it can: about 5x, taken as 10x
    (DaemonConfig(sim=True, sim_speed=4.0, host_deadline_ms=5000), 0.025, 10000),     # the board's longest
])
def test_the_dead_host_deadline_is_the_configured_wall_clock_time_at_a_simulated_boards_speed(
        config, keepalive_s, board_deadline_ms):
    """At --sim-speed 2 the board's 500 ms were 250 ms of wall clock, half a real board's: a scan reconstructed in
    the daemon's process on a loaded machine held the link's thread past it (DEAD_HOST in make test)."""
    from phantom.host.service import link_timing

    timing = link_timing(config, 0.0)
    assert (timing.keepalive_s, timing.host_deadline_ms) == (pytest.approx(keepalive_s), board_deadline_ms)


def test_every_setting_is_a_daemon_flag_with_its_help_and_range():
    from phantom.cli import daemon as commands

    parser = argparse.ArgumentParser()
    commands.register(parser.add_subparsers())
    daemon_help = run_phantom("daemon", "--help").stdout
    for item in settings():
        assert item.flag in daemon_help and item.setting.help[:30] in " ".join(daemon_help.split()), item.name
    args = parser.parse_args(["daemon", "--sim", "--mesh-hz", "2.5", "--no-vent-on-exit", "--host-deadline-ms",
                              "800", "--rerun-save", "out/x.rrd"])
    assert (args.sim, args.mesh_hz, args.vent_on_exit, args.host_deadline_ms, args.rerun_save) == (
        True, 2.5, False, 800, Path("out/x.rrd"))
    assert args.port is None and args.zero_on_connect is None     # not given: the config file's value stands


@pytest.mark.parametrize(("flags", "message"), [
    (["--mesh-hz", "nan"], "argument --mesh-hz: the value must be between 0 and 10, got nan"),
    (["--host-deadline-ms", "5"], "argument --host-deadline-ms: the value must be between 50 and 10000, got 5"),
    (["--baud", "fast"], "argument --baud: 'fast' is not an integer"),
])
def test_daemon_flags_out_of_range_are_usage_errors(tmp_path, flags, message):
    result = run_phantom("daemon", "--sim", "--socket", str(tmp_path / "d.sock"), *flags)
    assert result.returncode == 2 and result.stderr.strip().splitlines()[-1] == f"phantom daemon: error: {message}"


def test_a_pressure_limit_below_the_scenes_pressure_max_is_refused_before_anything_slow(tmp_path):
    """It was taken, and every target the model reached above it was then refused by the board (SET_SETPOINTS:
    BAD_VALUE), 45 ml among them, inside the range the daemon said it reached."""
    result = run_phantom("daemon", "--sim", "--socket", str(tmp_path / "d.sock"), "--pressure-limit-kpa", "2")
    assert result.returncode == 2 and result.stderr.strip().splitlines()[-1] == (
        "phantom daemon: error: the pressure limit (2 kPa) is below the scene builtin:converged's pressure_max_kpa "
        "(3 kPa), up to which the model sets pressures: give --pressure-limit-kpa (or pressure_limit_kpa in the "
        "config file) of at least 3, or a scene with a lower [model] pressure_max_kpa")
    assert not (tmp_path / "d.sock").exists()


def test_a_config_file_out_of_range_is_one_line_and_exit_2(tmp_path):
    path = tmp_path / "phantomd.toml"
    path.write_text("[daemon]\nsim = true\ntelemetry_period_ms = 0\n")
    result = run_phantom("daemon", "--config", str(path), "--socket", str(tmp_path / "d.sock"))
    assert result.returncode == 2
    assert result.stderr.strip() == (f"phantom daemon: error: {path}: [daemon] telemetry_period_ms must be between "
                                     "10 and 1000, got 0")


def test_systemd_unit_restarts_on_failure_and_vents_on_sigterm():
    unit = configparser.ConfigParser(strict=False, interpolation=None)
    unit.optionxform = str
    unit.read(HOST / "systemd" / "phantomd.service")
    service = unit["Service"]
    assert service["Restart"] == "on-failure"
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
    assert table[1].split() == ["0", "0.0", "30.00", "ml", "29.98", "1.2"]
    assert table[2].split()[2:] == ["pressures", "1.00,1.00,1.00", "kPa", "31.00", "-"]


@pytest.mark.parametrize("command", ["set", "inverse"])
def test_a_list_starting_with_a_free_chamber_is_a_value_not_an_option(command):
    from phantom.cli.main import build_parser, join_list_values

    args = build_parser().parse_args(join_list_values([command, "--chamber-volumes-ml", "-,3.5,3.5"]))
    assert args.chamber_volumes_ml == "-,3.5,3.5"
    assert join_list_values(["set", "--volume-ml", "32", "--json"]) == ["set", "--volume-ml", "32", "--json"]


def test_every_host_subcommand_has_a_description_and_json():
    from phantom.cli import client, daemon

    parser = argparse.ArgumentParser()
    subparsers = parser.add_subparsers()
    daemon.register(subparsers)
    client.register(subparsers)
    for name, subparser in subparsers.choices.items():
        assert subparser.description, name
        if name != "daemon":
            assert "--json" in subparser.format_help(), name


def test_the_text_answers_of_vent_clear_fault_and_zero():
    from phantom.cli.client import format_simple, watch_header

    assert format_simple("vent", {"vented": True}).startswith("vented")
    assert format_simple("clear_fault", {"cleared": ["SENSOR_1"], "setpoints_restored": True}) == (
        "faults cleared: SENSOR_1; the target's setpoints restored")
    assert format_simple("zero", {"zeroed": True}) == "sensors zeroed"
    assert "left l" in watch_header(["base", "left lobe", "right lobe"])


def test_format_steps_adds_the_true_volume_only_when_known():
    step = {"index": 0, "at_s": 0.0, "target": "30.00 ml", "target_volume_ml": 30.0, "reached_volume_ml": 30.1,
            "error_pct": 0.33, "reached_after_s": 1.0, "true_volume_ml": None}
    assert "true" not in format_steps([step])
    table = format_steps([{**step, "true_volume_ml": 29.8}])
    assert "true ml" in table.splitlines()[0] and "29.80" in table.splitlines()[1]


def test_the_step_table_shows_the_true_error_and_its_mean_not_the_estimates():
    """The estimate is what the controller drives to the target (within hundredths of a percent); the true
    volume's error against the target is the figure that tells how accurate the phantom was."""
    steps = [{"index": k, "at_s": 10.0 * k, "target": f"{target:.2f} ml", "target_volume_ml": target,
              "reached_volume_ml": target + 0.01, "error_pct": 0.03, "reached_after_s": 2.0, "true_volume_ml": true}
             for k, (target, true) in enumerate([(30.0, 30.3), (40.0, 38.8), (45.0, None)])]
    table = format_steps(steps).splitlines()
    assert table[0].split()[:6] == ["step", "at", "(s)", "target", "estimate", "ml"]
    assert "true error %" in table[0] and "error %" not in table[0].replace("true error %", "")
    assert table[1].split()[:7] == ["0", "0.0", "30.00", "ml", "30.01", "30.30", "+1.00"]
    assert table[2].split()[5:7] == ["38.80", "-3.00"]
    assert table[3].split()[5:7] == ["-", "-"]
    assert table[4].startswith("mean |true error| 2.00 % (largest 3.00 %)")


def test_a_verified_targets_rounds_and_a_scans_pictures_read_as_words():
    """The daemon words a verification's progress and a scan's (``text`` in the status): phantom status and the panel
    show the same words."""
    from phantom.host.motion import ScanRun
    from phantom.host.verify import progress_text

    verify = {"target_ml": 35.0, "round": 2, "doing": "scanning", "verify": "scan", "verify_tolerance_pct": 0.3,
              "verify_rounds": 4, "scans": [{"round": 1, "scanned_volume_ml": 34.0312, "scanned_error_pct": -2.768}]}
    run = ScanRun(40)
    run.stops_reached = 14
    scan = run.to_json()
    assert progress_text(verify, scan) == ("35 ml (scan, within 0.3 %): round 2 of at most 4, scanning (picture 14 "
                                           "of 40); round 1 scanned 34.03 ml (-2.77 %)")
    assert progress_text({**verify, "round": 1, "doing": "correcting"}) == (
        "35 ml (scan, within 0.3 %): round 1 of at most 4, solving the next round's pressures; round 1 scanned "
        "34.03 ml (-2.77 %)")
    assert progress_text({**verify, "round": 1, "doing": "settling", "scans": []}, None).endswith(
        "round 1 of at most 4, settling")
    unplanned = ScanRun()
    unplanned.stops_reached = 14
    assert unplanned.to_json()["text"] == "picture 14"


@pytest.mark.parametrize("count", ["0", "-3"])
def test_a_watch_count_below_one_is_a_usage_error(tmp_path, count):
    """``--count 0`` watched forever and ``--count -3`` printed one line."""
    result = run_phantom("watch", "--count", count, "--socket", str(tmp_path / "none.sock"))
    assert result.returncode == 2
    assert result.stderr.splitlines()[-1] == (f"phantom watch: error: argument --count: {count} is below 1: give how "
                                              "many status lines to print, or leave --count out to watch until "
                                              "interrupted")


@pytest.mark.parametrize("options", [["--tolerance-pct", "2"], ["--timeout-s", "5"],
                                     ["--tolerance-pct", "2", "--timeout-s", "5"]])
def test_a_waits_options_without_wait_are_refused_before_connecting(options):
    """They were ignored without a word: ``set`` returns as soon as the setpoints are sent."""
    from phantom.cli.main import build_parser

    args = build_parser().parse_args(["set", "--volume-ml", "32", *options, "--socket", "/nonexistent/d.sock"])
    with pytest.raises(PhantomError) as caught:
        args.run(args)
    assert str(caught.value) == ("--tolerance-pct and --timeout-s go with --wait: add --wait (without it, set "
                                 "returns as soon as the setpoints are sent)")


@pytest.mark.parametrize("waits", [["--wait"], ["--verify", "scan"]])
def test_a_waits_options_go_with_wait_and_with_verify_which_waits(waits):
    from phantom.cli.main import build_parser

    args = build_parser().parse_args(["set", "--volume-ml", "32", *waits, "--tolerance-pct", "2", "--timeout-s",
                                      "500", "--socket", "/nonexistent/d.sock"])
    with pytest.raises(PhantomError, match="no daemon is listening on /nonexistent/d.sock"):
        args.run(args)
