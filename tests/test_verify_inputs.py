"""Bad verify inputs (issue 36): ``set_target``'s verify, verify_tolerance_pct and verify_rounds, and a scene
step's verify / scan, refused with what was wrong before anything changes; a scene's clock waits while a step
scans."""

import pytest

from phantom.host.api import ApiError
from phantom.host.handlers import verify_of
from phantom.host.scene_runner import SceneRunner, prepare_run
from phantom.host.scenes import parse_timeline
from phantom.host.verify import Verify
from phantom.model.errors import SceneError

CHAMBERS = ["chamber0", "chamber1", "chamber2"]


def test_verify_defaults_and_its_params_are_taken_out_of_the_target():
    params = {"volume_ml": 40.0, "verify": "scan"}
    assert verify_of(params) == Verify(0.3, 4) and params == {"volume_ml": 40.0}
    params = {"volume_ml": 40.0, "verify": "scan", "verify_tolerance_pct": 0.5, "verify_rounds": 2}
    assert verify_of(params) == Verify(0.5, 2) and params == {"volume_ml": 40.0}
    assert verify_of({"volume_ml": 40.0}) is None


@pytest.mark.parametrize("params, words", [
    ({"verify": "water"}, 'verify must be "scan"'),
    ({"verify": True}, 'verify must be "scan"'),
    ({"verify": "scan", "verify_tolerance_pct": 0.0}, "verify_tolerance_pct .* from 0.05 to 20"),
    ({"verify": "scan", "verify_tolerance_pct": float("nan")}, "verify_tolerance_pct"),
    ({"verify": "scan", "verify_tolerance_pct": -1}, "verify_tolerance_pct"),
    ({"verify": "scan", "verify_tolerance_pct": "0.3"}, "verify_tolerance_pct"),
    ({"verify": "scan", "verify_tolerance_pct": 1e9}, "verify_tolerance_pct"),
    ({"verify": "scan", "verify_rounds": 0}, "verify_rounds .* from 1 to 10"),
    ({"verify": "scan", "verify_rounds": 2.5}, "verify_rounds"),
    ({"verify": "scan", "verify_rounds": True}, "verify_rounds"),
    ({"verify": "scan", "verify_rounds": 10**9}, "verify_rounds"),
    ({"verify_rounds": 2}, "go with verify"),
    ({"verify_tolerance_pct": 0.3}, "go with verify"),
])
def test_bad_verify_params_are_refused_with_what_was_wrong(params, words):
    with pytest.raises(ApiError, match=words) as raised:
        verify_of({"volume_ml": 40.0, **params})
    assert raised.value.code == "invalid_params"


def steps(**extra):
    return [{"at_s": 0, "volume_ml": 30.0}, {"at_s": 10, "volume_ml": 35.0, **extra}]


def test_a_steps_verify_and_scan_are_read():
    timeline = parse_timeline(steps(verify="scan", verify_tolerance_pct=0.5), CHAMBERS)
    assert timeline.steps[0].verify is None and timeline.steps[1].verify == Verify(0.5, 4)
    assert parse_timeline(steps(scan=True), CHAMBERS).steps[1].verify == Verify(rounds=1, correct=False)
    assert parse_timeline(steps(scan=False), CHAMBERS).steps[1].verify is None


@pytest.mark.parametrize("extra, words", [
    ({"verfy": "scan"}, "unknown key.*verfy"),                  # a misspelt key is still refused
    ({"verify": "yes"}, 'verify must be "scan"'),
    ({"scan": "true"}, "scan must be true or false"),
    ({"verify": "scan", "scan": True}, "not both"),
    ({"verify_rounds": 3}, "go with verify"),
    ({"verify": "scan", "verify_rounds": 0}, "verify_rounds must be a whole number from 1 to 10"),
    ({"verify": "scan", "verify_tolerance_pct": 50}, "verify_tolerance_pct must be a number from 0.05 to 20"),
])
def test_bad_step_verify_keys_are_refused(extra, words):
    with pytest.raises(SceneError, match=words):
        parse_timeline(steps(**extra), CHAMBERS)


def test_only_a_volume_step_is_verified():
    with pytest.raises(SceneError, match="give volume_ml"):
        parse_timeline([{"at_s": 0, "pressures_kpa": [1, 1, 1], "verify": "scan"}], CHAMBERS)


def test_the_scene_clock_waits_while_a_step_scans():
    now = [0.0]
    runner = SceneRunner(lambda: now[0], lambda *told: None)
    runner.begin(prepare_run({"steps": steps(verify="scan"), "timeline": {"end_s": 20}}, "s", CHAMBERS, 1.0))
    now[0] = 11.0
    runner.tick()
    assert runner.step_index() == 1 and runner.verify() == Verify()
    runner.hold(True)
    now[0] = 41.0                                             # a 30 s scan
    assert runner.scene_time_s() == pytest.approx(11.0) and runner.tick() is not None
    runner.hold(False)
    now[0] = 45.0
    assert runner.scene_time_s() == pytest.approx(15.0)
    now[0] = 50.0
    assert runner.tick() is None and runner.run.finished      # 20 s of scene time, 30 s held beside it


@pytest.mark.parametrize("line, words", [
    (["set", "--pressures-kpa", "1,1,1", "--verify", "scan"], "give --volume-ml"),
    (["set", "--volume-ml", "40", "--verify-rounds", "2"], "go with --verify scan"),
])
def test_the_command_line_refuses_verify_where_it_cannot_be_before_connecting(line, words):
    from phantom import PhantomError
    from phantom.cli.main import build_parser

    args = build_parser().parse_args([*line, "--socket", "/nonexistent/d.sock"])
    with pytest.raises(PhantomError, match=words):
        args.run(args)
