"""The scanner's motion messages in degrees: an axis's configuration (MOTION_CONFIG, MOTION_INFO) and its status
(MOTION_STATUS), their checks, and what each refusal means (PROTOCOL.md, section 12). Angles are degrees here and
millidegrees on the wire. Both drivers of the link use them: the HIL bench (``phantom.hil.motion``) and the
daemon (``phantom.host.motion``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from phantom import PhantomError
from phantom.protocol.codec import Message
from phantom.protocol.messages import CONSTANTS, MotionFlags, MotionOptions, MotionResult, MotionState

ORBIT = 0
ELEVATION = 1
AXES = CONSTANTS["MOTION_AXES"]
#: The board's fastest step rate (steps/s) and the angles it accepts (deg).
MAX_STEP_RATE = CONSTANTS["MOTION_MAX_STEP_RATE"]
ANGLE_LIMIT_DEG = CONSTANTS["MOTION_ANGLE_LIMIT_MDEG"] / 1e3

#: What each refusal means, for the error a user reads.
REFUSALS = {
    "NO_AXIS": "axis {axis} is not configured: send its configuration first (configure)",
    "OUT_OF_LIMITS": "{angle} is outside axis {axis}'s soft limits (MOTION_CONFIG sets them)",
    "NOT_REFERENCED": "axis {axis} lost its position (a fault stopped it while it moved, or its steps per turn "
                      "or direction changed): home it first",
    "BUSY": "an axis is moving, homing or stopping (one moves at a time): wait for it or stop it",
    "FAULT_LATCHED": "a fault is latched and has halted the motion: clear it (CLEAR_FAULT) first",
    "BAD_VALUE": "the board refused the values for axis {axis}: {detail}",
}


class MotionError(PhantomError):
    """A motion command was refused or did not end as asked, or its arguments are wrong."""


@dataclass(frozen=True)
class AxisConfig:
    """One axis's configuration, in degrees.

    ``steps_per_rev`` is the axis's steps per turn: the motor's full steps times the driver's microsteps times
    the gear (belt) ratio, e.g. 200 x 16 x 9 = 28800. The board accepts a step rate (max_speed x steps_per_rev /
    360) up to :data:`MAX_STEP_RATE`.
    """

    steps_per_rev: float
    max_speed_deg_s: float
    max_accel_deg_s2: float
    min_angle_deg: float
    max_angle_deg: float
    home_speed_deg_s: float = 0.0
    reverse: bool = False
    home_switch: bool = False
    switch_active_low: bool = False
    home_positive: bool = False
    release_when_idle: bool = False

    def problems(self) -> list[str]:
        """What the board would refuse in this configuration, in words (empty when it is acceptable)."""
        found = []
        if not (self.steps_per_rev == 0 or 1 <= self.steps_per_rev <= CONSTANTS["MOTION_MAX_STEPS_PER_REV"]):
            found.append(f"steps_per_rev must be 0 (no axis) or 1..{CONSTANTS['MOTION_MAX_STEPS_PER_REV']}, "
                         f"got {self.steps_per_rev!r}")
        if not self.max_speed_deg_s > 0:
            found.append(f"max_speed_deg_s must be > 0, got {self.max_speed_deg_s!r}")
        elif self.max_speed_deg_s * self.steps_per_rev / 360 > MAX_STEP_RATE:
            rate = self.max_speed_deg_s * self.steps_per_rev / 360
            found.append(f"max_speed_deg_s {self.max_speed_deg_s:g} is {rate:.0f} steps/s, over the board's "
                         f"{MAX_STEP_RATE} (at most {MAX_STEP_RATE * 360 / self.steps_per_rev:.4g} deg/s with "
                         f"{self.steps_per_rev:g} steps/rev)")
        if not self.max_accel_deg_s2 > 0:
            found.append(f"max_accel_deg_s2 must be > 0, got {self.max_accel_deg_s2!r}")
        if not -ANGLE_LIMIT_DEG <= self.min_angle_deg < self.max_angle_deg <= ANGLE_LIMIT_DEG:
            found.append(f"the soft limits must satisfy -{ANGLE_LIMIT_DEG:g} <= min_angle_deg < max_angle_deg <= "
                         f"{ANGLE_LIMIT_DEG:g}, got [{self.min_angle_deg!r}, {self.max_angle_deg!r}]")
        if self.home_switch and not 0 < self.home_speed_deg_s <= self.max_speed_deg_s:
            found.append(f"with a home switch, home_speed_deg_s must be in (0, max_speed_deg_s], got "
                         f"{self.home_speed_deg_s!r}")
        return found

    def move_s(self, distance_deg: float) -> float:
        """The board's time (s) for a move of ``distance_deg`` (either way) on this axis's trapezoidal profile: up
        to ``max_speed_deg_s`` at ``max_accel_deg_s2`` and down again (a triangle when too short to reach it)."""
        distance_deg = abs(distance_deg)
        if distance_deg == 0.0:
            return 0.0
        ramps_deg = self.max_speed_deg_s ** 2 / self.max_accel_deg_s2  # both ramps at full speed
        if distance_deg <= ramps_deg:
            return 2.0 * math.sqrt(distance_deg / self.max_accel_deg_s2)
        return self.max_speed_deg_s / self.max_accel_deg_s2 + distance_deg / self.max_speed_deg_s

    def fields(self, axis: int) -> dict[str, Any]:
        """MOTION_CONFIG's fields for this axis; MotionError naming every problem first."""
        check_axis(axis)
        found = self.problems()
        if found:
            raise MotionError(f"axis {axis} configuration: {'; '.join(found)}")
        options = (MotionOptions.REVERSE * self.reverse | MotionOptions.HOME_SWITCH * self.home_switch
                   | MotionOptions.SWITCH_ACTIVE_LOW * self.switch_active_low
                   | MotionOptions.HOME_POSITIVE * self.home_positive
                   | MotionOptions.RELEASE_WHEN_IDLE * self.release_when_idle)
        return {
            "axis": axis,
            "steps_per_rev": float(self.steps_per_rev),
            "max_speed_mdeg_s": mdeg(self.max_speed_deg_s),
            "max_accel_mdeg_s2": mdeg(self.max_accel_deg_s2),
            "min_angle_mdeg": mdeg(self.min_angle_deg),
            "max_angle_mdeg": mdeg(self.max_angle_deg),
            "home_speed_mdeg_s": mdeg(self.home_speed_deg_s),
            "options": int(options),
        }

    @classmethod
    def from_fields(cls, fields: dict[str, Any]) -> AxisConfig:
        """The configuration a MOTION_INFO (or MOTION_CONFIG) carries."""
        options = MotionOptions(fields["options"])
        return cls(
            steps_per_rev=fields["steps_per_rev"],
            max_speed_deg_s=fields["max_speed_mdeg_s"] / 1e3,
            max_accel_deg_s2=fields["max_accel_mdeg_s2"] / 1e3,
            min_angle_deg=fields["min_angle_mdeg"] / 1e3,
            max_angle_deg=fields["max_angle_mdeg"] / 1e3,
            home_speed_deg_s=fields["home_speed_mdeg_s"] / 1e3,
            reverse=MotionOptions.REVERSE in options,
            home_switch=MotionOptions.HOME_SWITCH in options,
            switch_active_low=MotionOptions.SWITCH_ACTIVE_LOW in options,
            home_positive=MotionOptions.HOME_POSITIVE in options,
            release_when_idle=MotionOptions.RELEASE_WHEN_IDLE in options,
        )

    def steps(self, angle_deg: float) -> int:
        """The step count of an angle, as the board rounds it."""
        return round(angle_deg * self.steps_per_rev / 360.0)


@dataclass(frozen=True)
class AxisStatus:
    """One axis in a MOTION_STATUS: what it is doing, how its last move ended, where it is."""

    state: str  # MotionState's name: ABSENT, IDLE, MOVING, HOMING, STOPPING
    result: str  # MotionResult's name: NONE, REACHED, STOPPED, HOMED, SWITCH_NOT_FOUND, FAULT
    enabled: bool
    referenced: bool
    switch_homed: bool
    switch_active: bool
    position_steps: int
    position_deg: float
    target_deg: float
    velocity_deg_s: float

    @property
    def at_rest(self) -> bool:
        return self.state in ("IDLE", "ABSENT")


@dataclass(frozen=True)
class MotionStatus:
    """A MOTION_STATUS: the board time (s) and both axes."""

    board_time_s: float
    axes: tuple[AxisStatus, ...]

    @classmethod
    def from_message(cls, message: Message) -> MotionStatus:
        f = message.fields
        axes = []
        for n in range(AXES):
            flags = MotionFlags(f["flags"][n])
            axes.append(AxisStatus(
                state=MotionState(f["state"][n]).name,
                result=MotionResult(f["result"][n]).name,
                enabled=MotionFlags.ENABLED in flags,
                referenced=MotionFlags.REFERENCED in flags,
                switch_homed=MotionFlags.SWITCH_HOMED in flags,
                switch_active=MotionFlags.SWITCH_ACTIVE in flags,
                position_steps=f["position_steps"][n],
                position_deg=f["position_mdeg"][n] / 1e3,
                target_deg=f["target_mdeg"][n] / 1e3,
                velocity_deg_s=f["velocity_mdeg_s"][n] / 1e3,
            ))
        return cls(board_time_s=f["time_ms"] / 1e3, axes=tuple(axes))


def mdeg(degrees: float) -> int:
    if not math.isfinite(degrees):
        raise MotionError(f"an angle, speed or acceleration must be a finite number, got {degrees!r}")
    return int(round(degrees * 1e3))


def check_axis(axis: int) -> None:
    if axis not in range(AXES):
        raise MotionError(f"axis must be {ORBIT} (orbit) or {ELEVATION} (elevation), got {axis!r}")


#: The scanner of docs/hardware.md: the orbit (axis 0) a 200-step motor at 16 microsteps on a 9:1 belt, 30 deg/s
#: (2400 steps/s, under the board's MOTION_MAX_STEP_RATE), 240 deg/s^2, +-190 deg (the camera's cable allows a
#: little over a turn); the elevation (axis 1) a 200-step motor at 8 microsteps on a 9:1 belt (14400 steps a turn:
#: 30 deg is a whole number of steps), 40 deg/s, 160 deg/s^2, -10..70 deg. The accelerations ask a few per cent of
#: the motors' torque of the light camera arm (docs/hardware.md, "The orbit's speed"): a verify scan's 12 deg stop
#: takes 0.53 s (0.89 s at the 60 deg/s^2 of before), the 30 deg tilt between passes 1.0 s (2.0 s).
SCANNER_AXES = (AxisConfig(steps_per_rev=28800, max_speed_deg_s=30.0, max_accel_deg_s2=240.0, min_angle_deg=-190.0,
                           max_angle_deg=190.0),
                AxisConfig(steps_per_rev=14400, max_speed_deg_s=40.0, max_accel_deg_s2=160.0, min_angle_deg=-10.0,
                           max_angle_deg=70.0))
