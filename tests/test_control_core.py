"""The daemon's control core (host/control.py) on a fake clock, as the link core is tested: every action it takes,
every transition, and the last red team's cases (issue 23: steps lost on unplug, fault and boot delay; a second
writer on the board) as unit tests. No board, no model, no event loop: times are plain numbers."""

import numpy as np
import pytest

from phantom.host import control
from phantom.host.board_watch import MISMATCH_FRAMES, MISMATCH_GRACE_S
from phantom.host.control import ControlCore, ReachRule, estimate_within
from phantom.host.parts import ControlState
from phantom.model.target import InverseResult, Target


def volume(ml):
    return Target(gland_volume_m3=ml * 1e-6)


def answer_for(target, kpa=(1.0, 0.5, 0.5), predicted_ml=None):
    predicted_ml = predicted_ml if predicted_ml is not None else (target.gland_volume_m3 or 30e-6) * 1e6
    return InverseResult(target, np.asarray(kpa) * 1e3, predicted_ml * 1e-6, np.full(3, predicted_ml / 3 * 1e-6),
                         3, 0.01, 0.001)


def of_kind(actions, kind):
    return [action for action in actions if isinstance(action, kind)]


def outcomes(actions):
    return [tell.data["outcome"] for tell in of_kind(actions, control.Tell) if tell.data and "outcome" in tell.data]


def held_again(actions):
    """The "held again after ..." events among the actions (data without an outcome)."""
    return [tell for tell in of_kind(actions, control.Tell) if tell.data and tell.data.get("held_again")]


def after_fault(state):
    """The core's ``target_after_interruption`` for a fault's interruption in ``state``."""
    return {"state": state, "after": "fault"}


@pytest.fixture
def core():
    core = ControlCore(3, ReachRule(settled_kpa=0.1, settled_for_s=1.0, tolerance_pct=1.0), retry_s=0.5)
    core.board(0.0, True)
    assert core.take_actions() == []
    return core


def hold(core, now, target, kpa=(1.0, 0.5, 0.5), request=1):
    """An API target offered and acknowledged; returns the actions."""
    core.offer(now, request, answer_for(target, kpa))
    actions = core.take_actions()
    send = of_kind(actions, control.SendSetpoints)
    assert len(send) == 1 and send[0].target == target
    core.sent(now, target)
    return actions + core.take_actions()


def settle(core, start, seconds, kpa=(1.0, 0.5, 0.5), estimate_ml=None, step_s=0.1):
    """Measured pressures at ``kpa`` every ``step_s`` from ``start`` and an estimate each time; the actions."""
    actions = []
    for now in np.arange(start, start + seconds + 1e-9, step_s):
        core.measured(float(now), np.asarray(kpa) * 1e3)
        if estimate_ml is not None:
            core.estimated(float(now), estimate_ml, None)
        core.tick(float(now))
        actions += core.take_actions()
    return actions


# --- an API target: sent, answered, reached ---------------------------------------------------------------------

def test_an_offered_target_is_sent_answered_on_its_ack_and_then_held(core):
    target = volume(32.0)
    core.offer(1.0, 7, answer_for(target))
    actions = core.take_actions()
    (send,) = of_kind(actions, control.SendSetpoints)
    np.testing.assert_array_equal(send.setpoints_pa, [1000.0, 500.0, 500.0])
    assert core.target is None and core.busy                 # nothing replaced before the board took it
    core.sent(1.1, target)
    actions = core.take_actions()
    (answer,) = of_kind(actions, control.Answer)
    assert answer.request == 7 and answer.error is None and answer.result.target == target
    assert core.state is ControlState.HOLDING and core.target == target and core.target_applied
    assert any("-> setpoints 1.000, 0.500, 0.500 kPa" in tell.text for tell in of_kind(actions, control.Tell))


def test_an_offer_without_a_board_or_refused_by_it_changes_nothing():
    core = ControlCore(3)
    core.offer(0.0, 1, answer_for(volume(32.0)))
    (answer,) = core.take_actions()
    assert answer.error[0] == "link_down" and "no board has been connected" in answer.error[1]
    core.board(0.0, True)
    hold(core, 1.0, volume(30.0))
    core.offer(2.0, 2, answer_for(volume(40.0)))
    core.take_actions()
    core.send_failed(2.1, volume(40.0), True, "the board refused: BAD_VALUE")
    (answer,) = of_kind(core.take_actions(), control.Answer)
    assert answer.request == 2 and answer.error == ("rejected", "the board refused: BAD_VALUE")
    assert core.target == volume(30.0) and core.target_applied  # refused: the board holds what it held


def test_reached_needs_the_pressures_settled_for_the_rule_and_the_estimate_within_the_tolerance(core):
    target = volume(32.0)
    hold(core, 0.0, target)
    early = settle(core, 0.0, 0.9, estimate_ml=32.1)            # 0.9 s settled: not yet
    assert outcomes(early) == []
    core.estimated(0.95, 33.0, None)
    off = settle(core, 1.0, 0.5, estimate_ml=33.0)              # settled long enough, estimate 3 % off
    assert outcomes(off) == []
    wobble = settle(core, 1.6, 0.2, kpa=(1.2, 0.5, 0.5), estimate_ml=32.1)  # 0.2 kPa off: the settle restarts
    assert outcomes(wobble) == []
    actions = settle(core, 1.9, 1.0, estimate_ml=32.1)
    (told,) = [tell for tell in of_kind(actions, control.Tell) if tell.data]
    assert told.data["outcome"] == "reached" and told.data["target"] == {"volume_ml": pytest.approx(32.0)}
    assert told.data["source"] == "api" and told.data["estimated_volume_ml"] == 32.1
    assert told.data["measured_pressures_kpa"] == [1.0, 0.5, 0.5]
    assert outcomes(settle(core, 3.0, 2.0, estimate_ml=32.1)) == []   # told once


def test_a_tolerance_asked_with_the_target_replaces_the_rules(core):
    core.offer(0.0, 1, answer_for(volume(32.0)), tolerance_pct=5.0)
    core.take_actions()
    core.sent(0.0, volume(32.0))
    core.take_actions()
    assert outcomes(settle(core, 0.0, 1.2, estimate_ml=33.0)) == ["reached"]   # 3.1 % off, within 5 %


def test_estimates_of_pressures_measured_before_the_ack_do_not_count(core):
    hold(core, 5.0, volume(32.0))
    core.estimated(4.9, 32.0, None)  # asked before the setpoints were held
    core.take_actions()
    actions = settle(core, 5.0, 1.5)
    assert outcomes(actions) == []


@pytest.mark.parametrize(("target", "chambers_ml", "gland_ml", "within"), [
    (Target(chamber_volumes_m3=[10e-6, None, 12e-6]), (10.05, 3.0, 11.95), 25.0, True),
    (Target(chamber_volumes_m3=[10e-6, None, 12e-6]), (10.2, 3.0, 12.0), 25.0, False),
    (Target(pressures_pa=[1000.0, 500.0, 500.0]), None, 30.2, True),      # against the inverse's 30 ml
    (Target(pressures_pa=[1000.0, 500.0, 500.0]), None, 30.5, False),
])
def test_what_the_estimate_is_held_against_for_each_kind_of_target(target, chambers_ml, gland_ml, within):
    assert estimate_within(target, answer_for(target, predicted_ml=30.0), gland_ml, chambers_ml, 1.0) is within


# --- outcomes other than reached --------------------------------------------------------------------------------

def test_a_target_replaced_before_it_was_reached_is_told_replaced(core):
    hold(core, 0.0, volume(32.0))
    actions = hold(core, 0.5, volume(35.0), request=2)
    (told,) = [tell for tell in of_kind(actions, control.Tell) if tell.data]
    assert told.data["outcome"] == "replaced" and told.data["target"]["volume_ml"] == pytest.approx(32.0)
    assert "replaced by 35.00 ml (api)" in told.text


def test_a_fault_before_reached_is_told_faulted_and_the_target_is_sent_again_once_cleared(core):
    target = volume(32.0)
    hold(core, 0.0, target)
    core.faults(0.5, ("OVERPRESSURE",))
    actions = core.take_actions()
    assert outcomes(actions) == ["faulted"] and not core.target_applied
    np.testing.assert_array_equal(core.setpoints_pa, np.zeros(3))   # the board zeroed them
    assert of_kind(actions, control.SendSetpoints) == []            # refused while latched
    assert "faults latched on the board (OVERPRESSURE)" in core.pending
    core.faults(3.0, ())
    (send,) = of_kind(core.take_actions(), control.SendSetpoints)  # the known answer, no new solve
    assert send.target == target


def fault_and_clear(core, at, target, names=("SENSOR_1",)):
    """A fault latched at ``at`` and cleared a second later: the target's setpoints sent again and acknowledged;
    the actions."""
    core.faults(at, names)
    actions = core.take_actions()
    core.faults(at + 1.0, ())
    actions += core.take_actions()
    (send,) = of_kind(actions, control.SendSetpoints)
    assert send.target == target
    core.sent(at + 1.1, target)
    return actions + core.take_actions()


def test_a_reached_target_held_again_after_a_fault_is_told_once_by_the_same_rule_and_is_no_second_outcome(core):
    """The panel judged "held again after the fault" itself (its own copy of the settled band): the core says it,
    by the reach rule, in an event without an outcome (a client waiting on a target is not woken by it) and in its
    state (the status's ``target_after_interruption``)."""
    target = volume(32.0)
    hold(core, 0.0, target)
    assert outcomes(settle(core, 0.0, 1.2, estimate_ml=32.0)) == ["reached"] and core.target_after_interruption is None
    core.faults(2.0, ("SENSOR_1",))
    actions = core.take_actions()
    assert outcomes(actions) == [] and held_again(actions) == []      # reached already: no "faulted" outcome
    assert core.target_after_interruption == after_fault("not_held")  # the board set every setpoint to 0
    core.faults(3.0, ())
    (send,) = of_kind(core.take_actions(), control.SendSetpoints)
    assert core.target_after_interruption == after_fault("not_held")  # not held until the board took them
    core.sent(3.1, target)
    core.take_actions()
    assert core.target_after_interruption == after_fault("settling")
    # the same rule as reached: the pressures within the band for settled_for_s ...
    assert held_again(settle(core, 3.1, 1.2, kpa=(0.0, 0.0, 0.0), estimate_ml=32.0)) == []   # still at 0
    assert held_again(settle(core, 4.4, 0.8, estimate_ml=32.0)) == []                         # 0.8 s: not yet
    assert held_again(settle(core, 5.3, 0.3, kpa=(1.2, 0.5, 0.5), estimate_ml=32.0)) == []    # off: restarts
    # ... and the estimate within the target's tolerance
    assert held_again(settle(core, 5.7, 1.5, estimate_ml=33.0)) == []                         # 3 % off
    assert core.target_after_interruption == after_fault("settling")
    actions = settle(core, 7.3, 1.2, estimate_ml=32.1)
    (told,) = held_again(actions)
    assert outcomes(actions) == [] and of_kind(actions, control.StepReached) == []
    assert told.kind == "target" and "outcome" not in told.data
    assert "held again after the fault" in told.text and told.text.startswith("target 32.00 ml")
    assert told.data["target"] == {"volume_ml": pytest.approx(32.0)} and told.data["source"] == "api"
    assert told.data["estimated_volume_ml"] == 32.1 and told.data["measured_pressures_kpa"] == [1.0, 0.5, 0.5]
    assert core.target_after_interruption == after_fault("held_again")
    assert held_again(settle(core, 8.6, 2.0, estimate_ml=32.1)) == []                         # told once


def test_a_fault_while_settling_again_is_no_outcome_and_a_new_target_forgets_the_fault(core):
    target = volume(32.0)
    hold(core, 0.0, target)
    settle(core, 0.0, 1.2, estimate_ml=32.0)
    fault_and_clear(core, 2.0, target)
    settle(core, 3.1, 0.5, estimate_ml=32.0)
    core.faults(3.7, ("OVERPRESSURE",))                                # again, before it was held again
    actions = core.take_actions()
    assert outcomes(actions) == [] and core.target_after_interruption == after_fault("not_held")
    core.faults(4.0, ())
    core.take_actions()
    core.sent(4.1, target)
    core.take_actions()
    (told,) = held_again(settle(core, 4.1, 1.2, estimate_ml=32.0))
    assert core.target_after_interruption == after_fault("held_again")
    # the same target asked again is judged again: a reached outcome, the fault forgotten
    hold(core, 6.0, target, request=2)
    assert core.target_after_interruption is None
    assert outcomes(settle(core, 6.0, 1.2, estimate_ml=32.0)) == ["reached"]
    # another target forgets it too; a vent as well
    fault_and_clear(core, 8.0, target)
    assert core.target_after_interruption == after_fault("settling")
    actions = hold(core, 9.5, volume(35.0), kpa=(1.5, 0.5, 0.5), request=3)
    assert outcomes(actions) == [] and core.target_after_interruption is None   # no "replaced": it was reached
    settle(core, 9.5, 1.2, kpa=(1.5, 0.5, 0.5), estimate_ml=35.0)
    core.faults(11.0, ("LEAK_0",))
    assert core.target_after_interruption == after_fault("not_held")
    core.vent(11.5, "on request")
    assert core.target_after_interruption is None


def test_a_target_faulted_before_it_was_reached_is_reached_once_cleared_not_held_again(core):
    target = volume(32.0)
    hold(core, 0.0, target)
    core.faults(0.5, ("OVERPRESSURE",))
    assert outcomes(core.take_actions()) == ["faulted"] and core.target_after_interruption is None
    core.faults(1.0, ())
    core.take_actions()
    core.sent(1.1, target)
    actions = settle(core, 1.1, 1.2, estimate_ml=32.0)
    assert outcomes(actions) == ["reached"] and held_again(actions) == [] and core.target_after_interruption is None


def test_a_scene_step_held_again_after_a_fault_is_told_and_not_reached_twice():
    core = ControlCore(3, ReachRule(settled_kpa=0.1, settled_for_s=1.0, tolerance_pct=1.0))
    core.board(0.0, True)
    core.scene_started(0.0)
    core.want(0.0, volume(30.0), "scene:bph", 0)
    core.solved(0.1, volume(30.0), answer_for(volume(30.0)))
    core.sent(0.2, volume(30.0))
    assert control.StepReached(0) in settle(core, 0.2, 1.2, estimate_ml=30.0)
    fault_and_clear(core, 2.0, volume(30.0))
    actions = settle(core, 3.1, 1.2, estimate_ml=30.0)
    (told,) = held_again(actions)
    assert told.data["source"] == "scene:bph" and of_kind(actions, control.StepReached) == []


# --- a reached target whose board lost its setpoints without a fault: a restart, a lost link ------------------

HELD_PA = np.asarray([1000.0, 500.0, 500.0])


def reached(core, target=None):
    """``target`` (32 ml) held and reached from 0 s; the core."""
    target = target or volume(32.0)
    hold(core, 0.0, target)
    assert outcomes(settle(core, 0.0, 1.2, estimate_ml=32.0)) == ["reached"]
    assert core.target_after_interruption is None
    return core


def tells(actions):
    return [tell.text for tell in of_kind(actions, control.Tell)]


def test_a_reached_target_on_a_board_that_restarted_is_not_held_then_settling_then_held_again(core):
    """The gap: a board that restarted (power-on reset, USB cable pulled and plugged back) comes back with no
    setpoints; the daemon sends the target's again, and while the phantom re-inflates the status said it reached.
    It is not held until the board acknowledged them, then settling, then held again by the reach rule."""
    target = volume(32.0)
    reached(core, target)
    core.board(2.0, False, "the link is disconnected")
    assert core.target_after_interruption is None                    # unknown while it is away: nothing said
    core.board_restarted(3.0, "its clock went back from 2000 to 1600 ms")
    actions = core.take_actions()
    assert core.target_after_interruption == {"state": "not_held", "after": "board restart"}
    (said,) = [tell for tell in of_kind(actions, control.Tell) if "not held" in tell.text]
    assert said.kind == "target" and said.level == "WARN" and not said.data      # no outcome, no held_again
    assert "not held: the board restarted" in said.text and "its clock went back" in said.text
    core.board_setpoints(3.02, np.zeros(3))                          # the restarted board holds nothing
    assert core.take_actions() == []                                 # said once
    core.board(3.1, True)
    (send,) = of_kind(core.take_actions(), control.SendSetpoints)
    assert send.target == target
    assert core.target_after_interruption == {"state": "not_held", "after": "board restart"}   # not taken yet
    core.sent(3.2, target)
    actions = core.take_actions()
    assert outcomes(actions) == [] and core.target_applied
    assert core.target_after_interruption == {"state": "settling", "after": "board restart"}
    assert held_again(settle(core, 3.2, 1.5, kpa=(0.3, 0.1, 0.1), estimate_ml=25.0)) == []   # re-inflating
    actions = settle(core, 4.8, 1.2, estimate_ml=32.1)
    (told,) = held_again(actions)
    assert outcomes(actions) == [] and told.kind == "target" and "outcome" not in told.data
    assert "held again after the board restarted" in told.text and told.data["after"] == "board restart"
    assert told.data["target"] == {"volume_ml": pytest.approx(32.0)} and told.data["source"] == "api"
    assert core.target_after_interruption == {"state": "held_again", "after": "board restart"}
    assert held_again(settle(core, 6.1, 2.0, estimate_ml=32.1)) == []                         # told once


def test_a_lost_link_after_which_the_board_reports_other_setpoints_is_an_interruption(core):
    """No restart seen (its clock did not go back), but the board reports setpoints that are not the target's
    once its link is back: it lost them, and the target is not held until they are taken again."""
    target = volume(32.0)
    reached(core, target)
    core.board(2.0, False, "the link is disconnected")
    assert core.awaits_board_frame                                   # a frame will say whether it kept them
    core.board_setpoints(2.9, np.zeros(3))
    actions = core.take_actions()
    assert core.target_after_interruption == {"state": "not_held", "after": "link loss"}
    assert any("not held: the board reports setpoints 0.000, 0.000, 0.000 kPa" in text for text in tells(actions))
    assert not core.awaits_board_frame
    core.board(3.0, True)
    core.take_actions()
    core.sent(3.1, target)
    core.take_actions()
    assert core.target_after_interruption == {"state": "settling", "after": "link loss"}
    (told,) = held_again(settle(core, 3.1, 1.2, estimate_ml=32.0))
    assert "held again after the link was lost" in told.text and told.data["after"] == "link loss"
    assert core.target_after_interruption == {"state": "held_again", "after": "link loss"}


def test_setpoints_lost_seen_while_they_are_sent_again_are_an_interruption(core):
    """The board back before a frame said anything: a frame sampled before the setpoints sent again landed, at
    0, says the board had lost them."""
    target = volume(32.0)
    reached(core, target)
    core.board(2.0, False, "the link is disconnected")
    core.board(2.5, True)
    (send,) = of_kind(core.take_actions(), control.SendSetpoints)
    core.board_setpoints(2.51, np.zeros(3))                          # before the ACK: what the board held
    assert core.target_after_interruption == {"state": "not_held", "after": "link loss"}
    core.sent(2.55, target)
    assert core.target_after_interruption == {"state": "settling", "after": "link loss"}


@pytest.mark.parametrize("in_flight", [False, True], ids=["before the send", "while it is in flight"])
def test_a_link_briefly_silent_while_the_board_kept_its_setpoints_is_no_interruption(core, in_flight):
    """A link silent for a moment (the link's process stalled, a silence that ended without a reset): the board
    reports the target's setpoints still, so nothing was interrupted: no words, no held again."""
    target = volume(32.0)
    reached(core, target)
    core.board(2.0, False, "the link's process has not reported for 1.2 s")
    if not in_flight:
        core.board_setpoints(2.4, HELD_PA)
        assert not core.awaits_board_frame
    core.board(2.5, True)
    actions = core.take_actions()
    if in_flight:
        core.board_setpoints(2.51, HELD_PA)                          # kept, or landed: it held them either way
    core.sent(2.55, target)
    actions += core.take_actions()
    actions += settle(core, 2.6, 2.0, estimate_ml=32.0)
    core.board_setpoints(4.7, HELD_PA)
    actions += core.take_actions()
    assert core.target_after_interruption is None and held_again(actions) == [] and outcomes(actions) == []
    assert not [text for text in tells(actions) if "not held" in text]


def back_and_taken_again(core, target):
    """``target`` reached, its board away at 2 s and back at 2.5 s, the setpoints sent again taken at 2.55 s before
    any frame came."""
    reached(core, target)
    core.board(2.0, False, "the link is disconnected")
    core.board(2.5, True)
    core.take_actions()
    core.sent(2.55, target)


def test_a_restart_seen_only_after_the_setpoints_were_taken_again_settles_from_their_ack(core):
    """No frame came between the board's return and the ACK of the setpoints sent again: the first frame after
    it tells the restart (its clock went back), and the target is settling from the ACK on, not stuck not held."""
    target = volume(32.0)
    back_and_taken_again(core, target)
    core.take_actions()
    assert core.target_after_interruption is None
    core.board_restarted(2.57, "its clock went back from 2000 to 1520 ms")
    core.board_setpoints(2.57, HELD_PA)                              # the setpoints sent again, taken
    assert core.target_after_interruption == {"state": "settling", "after": "board restart"}
    (told,) = held_again(settle(core, 2.6, 1.2, estimate_ml=32.0))
    assert "after the board restarted" in told.text


def test_the_first_frame_after_the_setpoints_were_taken_again_without_a_restart_is_no_interruption(core):
    target = volume(32.0)
    back_and_taken_again(core, target)
    core.board_setpoints(2.57, HELD_PA)
    core.board_restarted(5.0, "its clock went back")                 # a restart later is one of its own ...
    assert core.target_after_interruption == {"state": "not_held", "after": "board restart"}


def test_a_board_that_restarts_during_an_open_session_reads_not_held_until_its_link_is_back(core):
    """The frame whose clock went back comes while the link is still up (the session ends on it right after)."""
    target = volume(32.0)
    reached(core, target)
    core.board_restarted(2.0, "its clock went back from 2000 to 120 ms")
    assert core.target_after_interruption == {"state": "not_held", "after": "board restart"}
    core.board(2.01, False, "the link is disconnected: the board restarted")
    core.board_setpoints(3.0, np.zeros(3))
    core.board(3.1, True)
    core.take_actions()
    assert core.target_after_interruption == {"state": "not_held", "after": "board restart"}
    core.sent(3.2, target)
    assert core.target_after_interruption == {"state": "settling", "after": "board restart"}


def test_a_fault_latched_while_the_link_was_lost_is_the_faults_interruption(core):
    """DEAD_HOST: the board latched a fault while the daemon was away; it is the fault's (cleared on request)."""
    target = volume(32.0)
    reached(core, target)
    core.board(2.0, False, "the link's process has not reported for 1.2 s")
    core.faults(2.9, ("DEAD_HOST",))
    core.board_setpoints(2.9, np.zeros(3))
    actions = core.take_actions()
    assert core.target_after_interruption == after_fault("not_held")
    assert not [text for text in tells(actions) if "not held" in text]   # the fault says it
    core.board(3.0, True)
    core.faults(4.0, ())
    core.take_actions()
    core.sent(4.1, target)
    assert core.target_after_interruption == after_fault("settling")


def test_a_board_restart_before_reached_or_without_a_target_is_no_interruption(core):
    core.board_restarted(0.5, "its clock went back")
    assert core.target_after_interruption is None and core.take_actions() == []
    target = volume(32.0)
    hold(core, 1.0, target)
    settle(core, 1.0, 0.5, estimate_ml=32.0)                         # not reached yet
    core.board(1.6, False, "the link is disconnected")
    core.board_restarted(2.0, "its clock went back")
    core.board(2.1, True)
    core.take_actions()
    core.sent(2.2, target)
    actions = settle(core, 2.2, 1.2, estimate_ml=32.0)
    assert outcomes(actions) == ["reached"] and held_again(actions) == []
    assert core.target_after_interruption is None


def test_a_vent_or_another_target_forgets_an_interruption(core):
    target = volume(32.0)
    reached(core, target)
    core.board_restarted(2.0, "its clock went back")
    assert core.target_after_interruption["state"] == "not_held"
    hold(core, 2.5, volume(35.0), kpa=(1.5, 0.5, 0.5), request=2)
    assert core.target_after_interruption is None
    settle(core, 2.5, 1.2, kpa=(1.5, 0.5, 0.5), estimate_ml=35.0)
    core.board(4.0, False, "the link is disconnected")
    assert core.awaits_board_frame
    core.vent(4.5, "on request")
    assert core.target_after_interruption is None and not core.awaits_board_frame


def test_a_vent_drops_the_target_and_the_scene_and_answers_its_request_once_acknowledged(core):
    core.scene_started(0.0)
    core.want(0.0, volume(30.0), "scene:x", 0)
    core.take_actions()
    core.vent(1.0, "on request", request=9)
    actions = core.take_actions()
    assert of_kind(actions, control.StopScene) == [control.StopScene("vented")]
    assert of_kind(actions, control.SendVent) == [control.SendVent("on request", "INFO", 9)]
    assert core.state is ControlState.VENTED and core.target is None and core.vented_why == "on request"
    core.vent_done(1.1, None)
    actions = core.take_actions()
    assert of_kind(actions, control.Answer) == [control.Answer(9)]
    np.testing.assert_array_equal(core.setpoints_pa, np.zeros(3))
    core.vent(2.0, "again", request=10)
    core.take_actions()
    core.vent_done(2.1, "the link is down")
    (answer,) = of_kind(core.take_actions(), control.Answer)
    assert answer.error == ("link_down", "the link is down") and core.setpoints_pa is None


def test_a_vent_the_board_could_not_be_told_goes_when_the_board_is_back_and_says_so_at_once(core):
    """The red team's case: a vent asked while the link was down answered link_down ("nothing changed") while the
    target was dropped, and no VENT went when the link came back: the board still held the old setpoints, and the
    daemon took them for another program driving the board."""
    hold(core, 0.0, volume(36.0))
    core.board(1.0, False, "the link is disconnected")
    core.vent(1.5, "on request", request=7)
    assert of_kind(core.take_actions(), control.SendVent) == [control.SendVent("on request", "INFO", 7)]
    core.vent_done(1.6, "no board: the link is disconnected", link_down=True)
    (answer,) = of_kind(core.take_actions(), control.Answer)
    code, text = answer.error
    assert code == "link_down" and "the target is dropped and the VENT goes to the board when it is back" in text
    assert core.state is ControlState.VENTED and core.target is None
    core.tick(2.0)
    assert of_kind(core.take_actions(), control.SendVent) == []      # not again while the board is away
    core.board(5.0, True)
    assert of_kind(core.take_actions(), control.SendVent) == [control.SendVent("on request", "INFO", None)]
    core.vent_done(5.1, None)
    told = [action.text for action in of_kind(core.take_actions(), control.Tell)]
    assert told == ["vented: on request"] and core.take_actions() == []
    np.testing.assert_array_equal(core.setpoints_pa, np.zeros(3))


def test_a_vent_waits_for_the_setpoints_in_flight(core):
    core.offer(0.0, 1, answer_for(volume(32.0)))
    core.take_actions()
    core.vent(0.05, "on request", request=2)
    actions = core.take_actions()
    assert of_kind(actions, control.SendVent) == []                 # one command at a time
    assert of_kind(actions, control.Answer)[0].error[0] == "replaced"  # the set_target is not what holds
    core.sent(0.1, volume(32.0))
    actions = core.take_actions()
    assert of_kind(actions, control.SendVent) == [control.SendVent("on request", "INFO", 2)]
    assert core.state is ControlState.VENTED and core.target is None  # the vent came later: it wins


# --- a scene's targets: solves, retries, unreachable ----------------------------------------------------------

def test_a_scene_target_is_solved_then_sent_and_its_step_applied_and_reached(core):
    core.scene_started(0.0)
    target = volume(30.0)
    core.want(0.0, target, "scene:s", step=0)
    assert core.take_actions() == [control.Solve(target, None)]
    core.solved(0.2, target, answer_for(target))
    (send,) = core.take_actions()
    assert isinstance(send, control.SendSetpoints)
    core.sent(0.3, target)
    assert control.StepApplied(0) in core.take_actions()
    actions = []
    for now in np.arange(0.3, 1.45, 0.1):  # the driver gives the step in force at every control tick
        core.want(float(now), target, "scene:s", step=0)
        actions += settle(core, float(now), 0.0, estimate_ml=30.1)
    assert control.StepReached(0) in actions and outcomes(actions) == ["reached"]


def test_one_solve_at_a_time_along_a_ramp_and_reached_only_once_the_ramp_ends(core):
    core.scene_started(0.0)
    start, end = volume(30.0), volume(34.0)
    points = [volume(30.0 + 0.4 * k) for k in range(1, 11)]
    core.want(0.0, points[0], "scene:s", 1, (start, end))
    assert core.take_actions() == [control.Solve(points[0], (start, end))]
    core.want(0.1, points[1], "scene:s", 1, (start, end))            # the first solve still runs
    assert core.take_actions() == []
    core.solved(0.15, points[0], answer_for(points[0]))            # stale: the next point is solved
    assert core.take_actions() == [control.Solve(points[1], (start, end))]
    core.solved(0.2, points[1], answer_for(points[1]))
    core.sent(0.25, points[1])
    assert control.StepApplied(1) in core.take_actions()
    assert outcomes(settle(core, 0.3, 1.5, estimate_ml=30.8)) == []  # a ramp point is not waited on
    core.want(2.0, end, "scene:s", 1, None)                        # the ramp ends
    core.solved(2.1, end, answer_for(end))
    core.sent(2.2, end)
    core.take_actions()
    actions = settle(core, 2.2, 1.2, estimate_ml=34.0)
    assert control.StepReached(1) in actions and outcomes(actions) == ["reached"]


def test_an_unreachable_scene_target_is_told_once_and_not_solved_again(core):
    core.scene_started(0.0)
    target = volume(90.0)
    core.want(0.0, target, "scene:s", 0)
    core.take_actions()
    core.solve_failed(0.1, target, True, "above the reachable 26-45 ml")
    actions = core.take_actions()
    assert outcomes(actions) == ["unreachable"] and core.pending.startswith("unreachable")
    # the step's record says it (run-scene --wait exits 1 with it)
    assert of_kind(actions, control.StepUnreachable) == [
        control.StepUnreachable(0, f"target {target.describe()} is unreachable: above the reachable 26-45 ml")]
    for now in (1.0, 2.0, 3.0):
        core.tick(now)
    assert core.take_actions() == []


def test_a_send_that_failed_is_tried_again_after_the_retry_time(core):
    core.scene_started(0.0)
    target = volume(30.0)
    core.want(0.0, target, "scene:s", 0)
    core.take_actions()
    core.solved(0.1, target, answer_for(target))
    core.take_actions()
    core.send_failed(0.2, target, False, "no ACK after 5 sends")
    actions = core.take_actions()
    assert core.pending == "no ACK after 5 sends" and core.next_deadline() == pytest.approx(0.7)
    assert of_kind(actions, control.Tell)[0].level == "WARN"
    core.tick(0.6)
    assert core.take_actions() == []
    core.tick(0.7)
    assert [type(action) for action in core.take_actions()] == [control.SendSetpoints]
    assert core.next_deadline() is None                     # tried: nothing due until it is answered
    core.send_failed(0.8, target, False, "no ACK after 5 sends")
    core.board(0.9, False, "the link is silent")
    assert core.next_deadline() is None                     # the board holds it back, not the clock

def test_a_solve_that_failed_is_tried_again_after_the_retry_time(core):
    core.scene_started(0.0)
    target = volume(30.0)
    core.want(0.0, target, "scene:s", 0)
    core.take_actions()
    core.solve_failed(0.1, target, False, "the model failed: worker died")
    core.take_actions()
    core.tick(0.5)
    assert core.take_actions() == []
    core.tick(0.6)
    assert core.take_actions() == [control.Solve(target, None)]


def test_a_new_model_level_solves_the_held_target_again(core):
    hold(core, 0.0, volume(32.0))
    core.model_changed(5.0)
    assert core.take_actions() == [control.Solve(volume(32.0), None)]


def test_a_zero_in_progress_holds_targets_back(core):
    core.scene_started(0.0)
    core.zeroing(0.0, "waiting for the chambers to be still")
    core.want(0.0, volume(30.0), "scene:s", 0)
    actions = core.take_actions()
    assert of_kind(actions, control.Solve) == []
    assert core.pending == "the sensors are being zeroed: waiting for the chambers to be still"
    core.zeroing(2.0, None)
    assert of_kind(core.take_actions(), control.Solve) == [control.Solve(volume(30.0), None)]


# --- the last red team's cases (issue 23) ----------------------------------------------------------------------

def play_step(core, now, index, ml):
    core.want(now, volume(ml), "scene:rt", index)
    return core.take_actions()


@pytest.mark.parametrize("loss", ["unplug", "fault", "boot delay"])
def test_a_step_that_comes_while_the_board_cannot_take_it_is_not_claimed_and_is_held_once_it_can(loss):
    """Red team: the status claimed step 1 applied while the board was unplugged (or its fault latched, or it was
    still booting), and the board never held step 1 once it was back."""
    core = ControlCore(3)
    core.scene_started(0.0)
    if loss != "boot delay":
        core.board(0.0, True)
        play_step(core, 0.0, 0, 30.0)
        core.solved(0.1, volume(30.0), answer_for(volume(30.0)))
        core.sent(0.2, volume(30.0))
        assert control.StepApplied(0) in core.take_actions()
    if loss == "unplug":
        core.board(8.0, False, "the link is silent")
    elif loss == "fault":
        core.faults(8.0, ("SENSOR",))
    else:
        core.board(0.0, False, "the link is waiting for the board's boot delay")
    core.take_actions()
    actions = play_step(core, 12.0, 1, 38.0)
    for now in np.arange(12.0, 13.0, 0.1):
        core.tick(float(now))
        actions += core.take_actions()
    assert not of_kind(actions, control.SendSetpoints) and not of_kind(actions, control.StepApplied)
    assert not core.target_applied and core.target == volume(38.0) and core.pending
    if loss == "fault":
        core.faults(13.0, ())
    else:
        core.board(13.0, True)
    actions = core.take_actions()
    if not of_kind(actions, control.SendSetpoints):
        assert of_kind(actions, control.Solve) == [control.Solve(volume(38.0), None)]
        core.solved(13.1, volume(38.0), answer_for(volume(38.0), (2.0, 1.0, 1.0)))
        (send,) = of_kind(core.take_actions(), control.SendSetpoints)
    else:
        (send,) = of_kind(actions, control.SendSetpoints)
    assert send.target == volume(38.0)
    core.sent(13.2, volume(38.0))
    actions = core.take_actions()
    assert control.StepApplied(1) in actions and core.target_applied
    assert any("applied after" in tell.text for tell in of_kind(actions, control.Tell))


def test_a_board_that_comes_back_holds_none_of_ours_and_the_target_is_sent_again(core):
    hold(core, 0.0, volume(32.0))
    core.board(1.0, False, "the link is silent")
    core.board(2.0, True)
    (send,) = of_kind(core.take_actions(), control.SendSetpoints)
    assert send.target == volume(32.0)


def test_a_second_writer_on_the_board_is_vented_and_the_boards_settings_set_again(core):
    """Red team: a program beside the daemon set setpoints of its own; the daemon must not hold them."""
    hold(core, 0.0, volume(32.0))
    mine = np.asarray([1000.0, 500.0, 500.0])
    theirs = np.asarray([3000.0, 0.0, 0.0])
    now = MISMATCH_GRACE_S + 0.01
    core.board_setpoints(now, mine)
    assert core.take_actions() == []
    for frame in range(MISMATCH_FRAMES):
        core.board_setpoints(now + 0.02 * frame, theirs)
    actions = core.take_actions()
    (vent,) = of_kind(actions, control.SendVent)
    assert vent.level == "ERROR" and "did not send" in vent.why and "3.000, 0.000, 0.000 kPa" in vent.why
    assert of_kind(actions, control.ConfigureBoard) == [control.ConfigureBoard("after the mismatch")]
    assert outcomes(actions) == ["replaced"] and core.state is ControlState.VENTED and core.target is None


def test_a_frame_sampled_before_a_command_arrived_is_no_mismatch(core):
    hold(core, 0.0, volume(32.0))
    for frame in range(MISMATCH_FRAMES + 2):  # within the grace after the ACK
        core.board_setpoints(0.01 * frame, np.zeros(3))
    assert core.take_actions() == []


def test_an_idle_board_that_comes_online_must_hold_nothing():
    core = ControlCore(3)
    core.board(0.0, True)
    np.testing.assert_array_equal(core.setpoints_pa, np.zeros(3))
    for frame in range(MISMATCH_FRAMES):
        core.board_setpoints(1.0 + 0.02 * frame, np.asarray([500.0, 0.0, 0.0]))
    assert of_kind(core.take_actions(), control.SendVent)
