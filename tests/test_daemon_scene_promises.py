"""A scene's steps are applied, or the status says plainly that they are not and why (issue 23, defect 1).

One daemon (``--run-scene`` with the default 2 s boot delay) plays a scene on the simulated board (the real
firmware in simavr, at twice real time) while the tests, in order, unplug the board across a step, latch a
fault across the next one, and ask for an unreachable target in the middle of the scene. Each step's target is
checked where it matters: the setpoints the board itself reports in its telemetry, to the pascal, against the
daemon's answer for that step's volume.
"""

import pytest
from daemon_rig import DaemonRig, board_holds_solution, calibrated_scene

from phantom.host.client import DaemonError

pytestmark = [pytest.mark.sim, pytest.mark.slow]

STEPS = [{"at_s": 0, "volume_ml": 30.0}, {"at_s": 12, "volume_ml": 38.0}, {"at_s": 24, "volume_ml": 33.0},
         {"at_s": 36, "volume_ml": 36.0}]


@pytest.fixture(scope="module")
def rig(tmp_path_factory, default_model_cached):
    directory = tmp_path_factory.mktemp("scene-promises")
    scene = directory / "steps.toml"
    scene.write_text(calibrated_scene(STEPS, end_s=44))
    rig = DaemonRig(directory, "--scene", str(scene), "--run-scene")
    try:
        rig.wait_online()
        yield rig
    finally:
        rig.close()


def test_the_first_step_is_applied_once_the_board_is_online_after_its_boot_delay(rig):
    # the scene started before the link was up (the port's 2 s boot delay): its first step waits for the link,
    # then goes to the board, which reports those setpoints
    status = rig.wait_status(lambda answer: board_holds_solution(answer, 30.0), 15,
                             "the board holding the first step's setpoints")
    assert status["control"] == "scene" and status["target_applied"] is True and status["target_pending"] is None
    first = status["scene"]["steps"][0]
    assert first["applied_after_s"] is not None and first["applied_after_s"] > 1.5   # after the boot delay
    texts = [event["text"] for event in status["events"]]
    assert any("not applied" in text and "link" in text for text in texts)


def test_a_step_due_while_the_board_is_unplugged_is_applied_when_it_is_back(rig):
    rig.wait_scene_time(8)
    rig.board.unplug()
    try:
        status = rig.wait_scene_time(13)                   # step 1 (38 ml) is due at 12 s
    finally:
        rig.board.replug()
    assert status["link"] == "disconnected" and status["target_volume_ml"] == 38.0
    # the daemon does not claim what the board does not hold
    assert status["target_applied"] is False and "link" in status["target_pending"]
    status = rig.wait_status(lambda answer: board_holds_solution(answer, 38.0), 15,
                             "the board holding step 1's setpoints after the replug")
    assert status["target_applied"] is True and status["scene"]["steps"][1]["applied_after_s"] > 1.0


def test_a_step_due_while_a_fault_is_latched_is_applied_when_the_fault_is_cleared(rig):
    rig.wait_scene_time(20)
    rig.board.inject("sensor_cut", chamber=1)
    rig.wait_until(lambda: "SENSOR_1" in rig.status()["faults"], 10, "the sensor fault latched")
    status = rig.wait_scene_time(25)                       # step 2 (33 ml) is due at 24 s
    assert status["target_volume_ml"] == 33.0 and status["target_applied"] is False
    assert "SENSOR_1" in status["target_pending"]
    rig.board.inject("clear")
    # the firmware refuses to clear while its filtered reading of the sensor is still out of range (FAULT_ACTIVE):
    # the reading the board reports comes back first
    rig.wait_until(lambda: rig.status()["pressures_kpa"][1] > -1.0, 10, "chamber 1's sensor reading again")
    cleared = rig.call("clear_fault")
    assert cleared["cleared"] == ["SENSOR_1"] and cleared["setpoints_restored"] is True
    assert cleared["target"] == {"volume_ml": 33.0}
    rig.wait_until(lambda: board_holds_solution(rig.status(), 33.0), 10, "step 2's setpoints after the clear")


def test_an_unreachable_target_during_a_scene_leaves_the_scene_playing(rig):
    rig.wait_scene_time(28)
    with pytest.raises(DaemonError, match="unreachable") as refused:
        rig.call("set_target", {"volume_ml": 80.0})
    assert refused.value.code == "unreachable"
    status = rig.status()
    assert status["control"] == "scene" and status["scene"]["finished"] is False
    rig.wait_scene_time(37)                                # step 3 (36 ml) is due at 36 s
    rig.wait_until(lambda: board_holds_solution(rig.status(), 36.0), 10, "step 3's setpoints")
