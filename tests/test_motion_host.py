"""The host's side of the scanner's motion without a board: axis configurations in degrees and on the wire, the
status a MOTION_STATUS carries, refusals turned into errors a user can act on, the speed and acceleration read
from a pulse train, and the command line's argument checks. (tests/test_motion_sim.py runs them against the
firmware in simavr.)"""

import math
import subprocess
import sys

import numpy as np
import pytest

from phantom.hil import motion as mo
from phantom.protocol.codec import Message, decode, encode
from phantom.protocol.messages import CONSTANTS, MESSAGES, Status

ORBIT = mo.AxisConfig(steps_per_rev=28800, max_speed_deg_s=30.0, max_accel_deg_s2=60.0, min_angle_deg=-190.0,
                      max_angle_deg=190.0, home_speed_deg_s=10.0, home_switch=True, release_when_idle=True)


def test_a_configuration_goes_to_the_wire_in_millidegrees_and_comes_back_from_motion_info():
    fields = ORBIT.fields(mo.ORBIT)
    assert fields == {"axis": 0, "steps_per_rev": 28800.0, "max_speed_mdeg_s": 30000, "max_accel_mdeg_s2": 60000,
                      "min_angle_mdeg": -190000, "max_angle_mdeg": 190000, "home_speed_mdeg_s": 10000,
                      "options": 0b10010}
    frame = encode("MOTION_CONFIG", 1, fields)  # every field fits its wire type
    assert decode(frame).fields == fields
    info = decode(encode("MOTION_INFO", 2, fields))
    assert mo.AxisConfig.from_fields(info.fields) == ORBIT
    assert ORBIT.steps(90.0) == 7200 and ORBIT.steps(12.345) == 988


@pytest.mark.parametrize(
    ("change", "complaint"),
    [
        ({"steps_per_rev": 0.5}, "steps_per_rev must be 0"),
        ({"steps_per_rev": 2e6}, "steps_per_rev must be 0"),
        ({"max_speed_deg_s": 0.0}, "max_speed_deg_s must be > 0"),
        ({"max_speed_deg_s": 40.0}, "3200 steps/s, over the board's 2500 (at most 31.25 deg/s"),
        ({"max_accel_deg_s2": -1.0}, "max_accel_deg_s2 must be > 0"),
        ({"min_angle_deg": 190.0}, "soft limits must satisfy"),
        ({"max_angle_deg": 721.0}, "soft limits must satisfy"),
        ({"home_speed_deg_s": 0.0}, "home_speed_deg_s must be in"),
        ({"home_speed_deg_s": 31.0}, "home_speed_deg_s must be in"),
    ],
)
def test_a_configuration_the_board_would_refuse_is_refused_here_with_the_reason(change, complaint):
    from dataclasses import replace

    bad = replace(ORBIT, **change)
    assert any(complaint in problem for problem in bad.problems())
    with pytest.raises(mo.MotionError, match="axis 0 configuration: .*" + complaint.split("(")[0].strip()):
        bad.fields(mo.ORBIT)
    with pytest.raises(mo.MotionError, match="axis must be 0 .orbit. or 1"):
        ORBIT.fields(2)


def test_the_board_s_largest_rate_is_the_spec_s():
    assert mo.MAX_STEP_RATE == CONSTANTS["MOTION_MAX_STEP_RATE"] == 2500
    assert mo.AxisConfig(28800, 31.25, 60, -1, 1).problems() == []


def test_a_motion_status_reads_states_flags_and_angles():
    fields = {"time_ms": 123456, "state": [2, 1], "flags": [0b0011, 0b1110], "result": [0, 5],
              "position_steps": [2400, -7], "position_mdeg": [30000, -196], "target_mdeg": [90000, -196],
              "velocity_mdeg_s": [29999, 0]}
    status = mo.MotionStatus.from_message(decode(encode("MOTION_STATUS", 0, fields)))
    assert status.board_time_s == pytest.approx(123.456)
    orbit, elevation = status.axes
    assert (orbit.state, orbit.result, orbit.enabled, orbit.referenced, orbit.at_rest) == (
        "MOVING", "NONE", True, True, False)
    assert (orbit.position_deg, orbit.target_deg, orbit.velocity_deg_s) == (30.0, 90.0, 29.999)
    assert (elevation.state, elevation.result, elevation.enabled, elevation.switch_homed, elevation.switch_active) == (
        "IDLE", "FAULT", False, True, True)
    assert elevation.at_rest and elevation.position_steps == -7


class _Refusing:
    """A link whose board refuses every command with one status (a fake of BoardLink's command for this layer)."""

    def __init__(self, status: str):
        self.status = Status[status]
        self.received = []

    def command(self, name, fields=None, accept_nack=False):
        assert accept_nack
        return Message("NACK", MESSAGES["NACK"].msg_id, 1,
                       {"ref_msg_id": MESSAGES[name].msg_id, "ref_seq": 3, "status": self.status})


@pytest.mark.parametrize(
    ("status", "says"),
    [
        ("NO_AXIS", "axis 1 is not configured: send its configuration first"),
        ("OUT_OF_LIMITS", "45 deg is outside axis 1's soft limits"),
        ("NOT_REFERENCED", "axis 1 lost its position .* home it first"),
        ("BUSY", "an axis is moving, homing or stopping .one moves at a time.: wait for it or stop it"),
        ("FAULT_LATCHED", "a fault is latched and has halted the motion: clear it"),
        ("BAD_VALUE", "the board refused the values for axis 1"),
    ],
)
def test_a_refusal_says_why_and_what_to_do(status, says):
    with pytest.raises(mo.MotionError, match=says):
        mo.move_to(_Refusing(status), mo.ELEVATION, 45.0)


def test_bad_arguments_are_refused_before_anything_is_sent():
    link = _Refusing("OK")
    with pytest.raises(mo.MotionError, match="axis must be 0"):
        mo.move_to(link, 3, 10.0)
    with pytest.raises(mo.MotionError, match="finite number"):
        mo.move_to(link, mo.ORBIT, math.nan)
    with pytest.raises(mo.MotionError, match="home method must be 'here' or 'switch'"):
        mo.home(link, mo.ORBIT, "there")


def _trapezoid_pulses(distance, speed, accel, period_s=16e-6):
    """The step times of an ideal trapezoid, rounded to the firmware's 16 us slots."""
    ramp_s, ramp_steps = speed / accel, speed**2 / (2 * accel)
    cruise_s = (distance - 2 * ramp_steps) / speed
    steps = np.arange(1, distance + 1) - 0.5
    t = np.where(steps < ramp_steps, np.sqrt(2 * steps / accel),
                 np.where(steps < distance - ramp_steps, ramp_s + (steps - ramp_steps) / speed,
                          2 * ramp_s + cruise_s - np.sqrt(2 * np.clip(distance - steps, 0, None) / accel)))
    return np.round(t / period_s) * period_s, np.ones(distance, dtype=int)


def test_profile_limits_read_the_speed_and_acceleration_of_a_trapezoid():
    times, directions = _trapezoid_pulses(7200, 2400.0, 4800.0)
    limits = mo.profile_limits(times, directions)
    assert limits["max_speed_steps_s"] == pytest.approx(2400, rel=0.002)
    assert limits["max_accel_steps_s2"] == pytest.approx(4800, rel=0.02)
    assert limits["duration_s"] == pytest.approx(7200 / 2400 + 2400 / 4800, abs=0.03)
    # twice the acceleration is seen as such, and a reversal counts as speed, not as steps lost
    fast = mo.profile_limits(*_trapezoid_pulses(7200, 2400.0, 9600.0))
    assert fast["max_accel_steps_s2"] == pytest.approx(9600, rel=0.03)
    back = mo.profile_limits(times, -directions)
    assert back["max_speed_steps_s"] == pytest.approx(2400, rel=0.002)
    assert mo.profile_limits(times[:1], directions[:1])["max_speed_steps_s"] == 0.0


def test_the_motion_command_refuses_bad_options_with_exit_status_2():
    for arguments, complaint in [
        (["--limits", "-190"], "--limits takes MIN,MAX"),
        (["--max-speed", "50"], "over the board's 2500"),
        (["--home-switch", "--home-speed", "0"], "home_speed_deg_s must be in"),
    ]:
        result = subprocess.run([sys.executable, "-m", "phantom", "motion", "move", "--port", "/dev/null", "--deg",
                                 "10", *arguments], capture_output=True, text=True)
        assert result.returncode == 2, result.stderr
        assert complaint in result.stderr and result.stderr.count("\n") == 1, result.stderr


def test_the_link_core_reports_a_motion_status_and_reads_the_board_clock_from_it():
    from phantom.protocol.link import BoardPeer, BoardRestarted, FrameIn, HostLink, MotionIn

    link, peer = HostLink(), BoardPeer()
    link.open(0.0)
    reader_frames = link.take_output()
    hello = decode(reader_frames[0])
    link.receive(peer.answer(hello, 5000), 0.01)
    fields = {"time_ms": 6000, "state": [2, 0], "flags": [3, 2], "result": [0, 0], "position_steps": [10, 0],
              "position_mdeg": [125, 0], "target_mdeg": [90000, 0], "velocity_mdeg_s": [1000, 0]}
    events = link.receive(peer.frame("MOTION_STATUS", fields), 0.02)
    motion = [e for e in events if isinstance(e, MotionIn)]
    assert len(motion) == 1 and motion[0].message.fields == fields
    assert mo.MotionStatus.from_message(motion[0].message).axes[0].position_deg == 0.125
    # a status stamped well before the last board time means the board restarted behind the port
    events = link.receive(peer.frame("MOTION_STATUS", {**fields, "time_ms": 1000}), 0.03)
    assert [type(e) for e in events if not isinstance(e, FrameIn)] == [MotionIn, BoardRestarted]


def test_the_move_to_worked_example_of_protocol_md_is_built_by_hand():
    """PROTOCOL.md section 12's bytes, from the definitions: the body, its CRC-16/MCRF4XX (0x3A48, computed
    bitwise here), COBS blocks ending at each zero."""
    from pathlib import Path

    body = bytes([0x18, 0x07, 0x00]) + (90000).to_bytes(4, "little", signed=True)
    crc = 0xFFFF
    for byte in body:
        crc ^= byte
        for _ in range(8):
            crc = (crc >> 1) ^ 0x8408 if crc & 1 else crc >> 1
    assert crc == 0x3A48
    body += crc.to_bytes(2, "little")
    on_wire = bytes.fromhex("03 18 07 04 90 5f 01 03 48 3a 00")
    assert body == bytes.fromhex("18 07 00 90 5f 01 00 48 3a")
    assert encode("MOVE_TO", 7, {"axis": 0, "angle_mdeg": 90000}) == on_wire
    protocol_md = (Path(__file__).parents[1] / "protocol" / "PROTOCOL.md").read_text()
    assert "on wire  03 18 07 04 90 5f 01 03 48 3a 00" in protocol_md


@pytest.mark.parametrize(("method", "params", "message"), [
    ("motion_move", {"orbit_deg": math.nan}, "orbit_deg must be a finite number of degrees within"),
    ("motion_move", {"elevation_deg": math.inf}, "elevation_deg must be a finite number of degrees within"),
    ("motion_move", {"orbit_deg": -math.inf}, "orbit_deg must be a finite number"),
    ("motion_move", {"orbit_deg": 1e12}, "orbit_deg must be a finite number of degrees within"),
    ("motion_move", {"orbit_deg": "90"}, "orbit_deg must be a finite number of degrees within"),
    ("motion_home", {"axis": 0, "angle_deg": math.nan}, "angle_deg must be a finite number"),
    ("motion_home", {"axis": 0, "angle_deg": math.inf}, "angle_deg must be a finite number"),
    ("motion_home", {"axis": 0, "method": ["here"]}, "method must be 'here' or 'switch'"),
    ("motion_config", {"axis": 0, "steps_per_rev": "28800", "max_speed_deg_s": 30, "max_accel_deg_s2": 60,
                       "min_angle_deg": -190, "max_angle_deg": 190}, "steps_per_rev must be a finite number"),
    ("motion_config", {"axis": 0, "steps_per_rev": [28800], "max_speed_deg_s": 30, "max_accel_deg_s2": 60,
                       "min_angle_deg": -190, "max_angle_deg": 190}, "steps_per_rev must be a finite number"),
    ("motion_config", {"axis": 0, "steps_per_rev": 28800, "max_speed_deg_s": math.nan, "max_accel_deg_s2": 60,
                       "min_angle_deg": -190, "max_angle_deg": 190}, "max_speed_deg_s must be a finite number"),
    ("motion_config", {"axis": 0, "steps_per_rev": 28800, "max_speed_deg_s": 30, "max_accel_deg_s2": 60,
                       "min_angle_deg": -190, "max_angle_deg": 190, "reverse": "yes"}, "reverse must be true or false"),
    ("motion_stop", {"release": "no"}, "release must be true or false"),
])
def test_motion_api_refuses_non_finite_and_mistyped_parameters_before_the_board(method, params, message):
    """NaN or Infinity (Python's json accepts them) and a string or list in motion_config were `internal` errors
    with tracebacks."""
    import asyncio

    from phantom.host.api import ApiError
    from phantom.host.motion import Orbit

    sent = []

    async def command(name, fields):
        sent.append(name)
        return 0

    async def call():
        orbit = Orbit(command, lambda *event: None)
        await orbit.api_methods()[method](params)

    with pytest.raises(ApiError, match=message) as raised:
        asyncio.run(call())
    assert raised.value.code == "invalid_params" and sent == []


class _BoardLosingReplies:
    """A board for host.motion's Orbit alone (the daemon's link and the firmware are test_motion_sim.py's): it
    ACKs each command, answers MOTION_CONFIG with MOTION_INFO and MOVE_TO with a MOTION_STATUS at rest there,
    sends a MOTION_STATUS every 100 ms of its clock (run 20 times as fast as the wall clock), and loses the
    replies it is told to: ``lose`` counts, per message name, the replies still to lose."""

    def __init__(self, lose):
        self.lose = dict(lose)
        self.sent = []
        self.time_ms = 0
        self.positions_mdeg = [0, 0]
        self.orbit = None

    def status(self):
        return decode(encode("MOTION_STATUS", 0, {
            "time_ms": self.time_ms, "state": [1, 1], "flags": [0b0011, 0b0011], "result": [1, 1],
            "position_steps": [0, 0], "position_mdeg": list(self.positions_mdeg),
            "target_mdeg": list(self.positions_mdeg), "velocity_mdeg_s": [0, 0]}))

    async def command(self, name, fields):
        import asyncio

        self.sent.append(name)
        reply = None
        if name == "MOTION_CONFIG":
            reply = decode(encode("MOTION_INFO", 0, fields))
        elif name == "MOVE_TO":
            self.positions_mdeg[fields["axis"]] = fields["angle_mdeg"]
            reply = self.status()
        if reply is not None:
            if self.lose.get(reply.name, 0) > 0:
                self.lose[reply.name] -= 1
            else:
                asyncio.get_running_loop().call_soon(self.orbit.on_message, reply)
        return "OK"

    async def tick(self):
        import asyncio

        while True:
            await asyncio.sleep(0.005)
            self.time_ms += 100
            self.orbit.on_message(self.status())


@pytest.mark.parametrize("lost", [1, 2])
def test_a_lost_motion_info_is_asked_for_again_and_the_configuration_and_the_move_complete(lost):
    """One late or lost reply ended a verification after four rounds ("the orbit's configuration did not end within
    2 s"): the configuration is asked for again (at most REPLY_TRIES times), and so is a move whose status is lost."""
    import asyncio

    from phantom.host.motion import REPLY_TRIES, LateReply, Orbit

    async def run(lose):
        board = _BoardLosingReplies(lose)
        events = []
        board.orbit = orbit = Orbit(board.command, lambda *event: events.append(event))
        ticking = asyncio.ensure_future(board.tick())
        try:
            await orbit.configure(mo.ORBIT, ORBIT)
            await orbit.move({mo.ORBIT: 45.0})
            return board, events
        finally:
            ticking.cancel()

    board, events = asyncio.run(run({"MOTION_INFO": lost}))
    assert board.sent.count("MOTION_CONFIG") == lost + 1
    assert [event[1] for event in events] == [
        f"the orbit's configuration did not end within 2 s (is the axis configured and the link up?): asked again "
        f"({attempt + 1} of {REPLY_TRIES})" for attempt in range(1, lost + 1)]
    # a configuration whose every reply is lost is refused, saying how often it was asked
    with pytest.raises(LateReply, match=f"the orbit's configuration did not end within 2 s .*{REPLY_TRIES} times"):
        asyncio.run(run({"MOTION_INFO": REPLY_TRIES}))

