"""The scanner's stepper axes through a board link: configure, move, home, stop, read the position; and the
simulated board's side: its mechanism, home switches and the pulses its drivers took.

Axis 0 (:data:`ORBIT`) turns the camera around the hanging phantom, axis 1 (:data:`ELEVATION`) tilts it. The
board moves one axis at a time (the other's move is refused BUSY until the first is at rest). Angles are degrees
here and millidegrees on the wire (PROTOCOL.md, section "Motion").

>>> with SimulatedBoard() as board, BoardLink(board.port) as link:        # doctest: +SKIP
...     bench.start_session(link)
...     rig = SimulatedRig(board)
...     rig.set_axis(ORBIT, steps_per_rev=28800)
...     configure(link, ORBIT, AxisConfig(steps_per_rev=28800, max_speed_deg_s=30, max_accel_deg_s2=60,
...                                       min_angle_deg=-190, max_angle_deg=190))
...     move_to(link, ORBIT, 90.0).axes[ORBIT].position_deg, rig.angle_deg(ORBIT)
(90.0, 90.0)
"""

from __future__ import annotations

import math
import tempfile
from collections.abc import Callable
from dataclasses import asdict, replace
from pathlib import Path
from typing import Any, Literal, overload

import numpy as np

from phantom.hil import bench
from phantom.hil.link import BoardLink
from phantom.hil.sim import SimulatedBoard
from phantom.protocol.codec import Message
from phantom.protocol.link import fault_names
from phantom.protocol.messages import CONSTANTS, Status
from phantom.protocol.motion import ANGLE_LIMIT_DEG, REFUSALS, SCANNER_AXES, check_axis, mdeg

# the axes' messages in degrees are the protocol's (the daemon reads them too); the bench's callers find them here
from phantom.protocol.motion import AXES as AXES
from phantom.protocol.motion import ELEVATION as ELEVATION
from phantom.protocol.motion import MAX_STEP_RATE as MAX_STEP_RATE
from phantom.protocol.motion import ORBIT as ORBIT
from phantom.protocol.motion import AxisConfig as AxisConfig
from phantom.protocol.motion import AxisStatus as AxisStatus
from phantom.protocol.motion import MotionError as MotionError
from phantom.protocol.motion import MotionStatus as MotionStatus

#: How long to wait for a move, a homing or a stop to end when the caller gives no time (s of board time).
DEFAULT_WAIT_S = 120.0
#: A step the firmware counted is made by its step interrupt within the next window (5 control ticks of 2 ms):
#: twice that of board time after a move's REACHED its driver has taken every pulse.
PULSES_MADE_WITHIN_S = 0.02


def _command(link: BoardLink, name: str, fields: dict[str, Any], axis: int, angle: str = "") -> Message:
    """An acknowledged motion command; a NACK becomes a MotionError saying why and what to do."""
    answer = link.command(name, fields, accept_nack=True)
    if answer.name == "NACK":
        status = Status(answer.fields["status"]).name
        template = REFUSALS.get(status, "the board refused {name}: {status}")
        raise MotionError(template.format(axis=axis, angle=angle, name=name, status=status,
                                          detail=f"{name} {fields}"))
    return answer


def _statuses_after(link: BoardLink, message: Message) -> int:
    """The index in link.received just after a received message: the board sent what follows it later."""
    for index in range(len(link.received) - 1, -1, -1):
        if link.received[index].message is message:
            return index + 1
    return link.mark()


def _wait_status(link: BoardLink, start: int, done: Callable[[MotionStatus], bool], timeout_s: float,
                 what: str) -> MotionStatus:
    """The first MOTION_STATUS from index start for which done(status) holds, within timeout_s of board time (on
    the board's telemetry clock: a simulator running slower than asked still gets its time)."""
    got = bench.wait_on_board_clock(
        link, lambda m: m.name == "MOTION_STATUS" and done(MotionStatus.from_message(m)), timeout_s, start)
    if got is None:
        raise MotionError(f"{what} did not end within {timeout_s:g} s (is the session open, the axis configured?)")
    return MotionStatus.from_message(got.message)


def status(link: BoardLink, timeout_s: float = 1.0) -> MotionStatus:
    """The next MOTION_STATUS the board sends (every 100 ms while an axis is configured)."""
    return wait_for_status(link, lambda s: True, timeout_s)


def wait_for_status(link: BoardLink, done: Callable[[MotionStatus], bool], timeout_s: float) -> MotionStatus:
    """The first MOTION_STATUS arriving from now on for which done(status) holds, within timeout_s of board
    time (MotionError when none does)."""
    return _wait_status(link, link.mark(), done, timeout_s, "waiting for the motion status asked for")


def configure(link: BoardLink, axis: int, config: AxisConfig, timeout_s: float = 1.0) -> AxisConfig:
    """MOTION_CONFIG; returns the configuration the board then reports (MOTION_INFO)."""
    answer = _command(link, "MOTION_CONFIG", config.fields(axis), axis)
    got = bench.wait_on_board_clock(link, lambda m: m.name == "MOTION_INFO" and m.fields["axis"] == axis, timeout_s,
                                    _statuses_after(link, answer))
    if got is None:
        raise MotionError(f"the board took axis {axis}'s configuration but did not report it (MOTION_INFO)")
    return AxisConfig.from_fields(got.message.fields)


@overload
def move_to(link: BoardLink, axis: int, angle_deg: float, wait: Literal[True] = ...,
            timeout_s: float = ...) -> MotionStatus: ...
@overload
def move_to(link: BoardLink, axis: int, angle_deg: float, wait: Literal[False],
            timeout_s: float = ...) -> None: ...
def move_to(link: BoardLink, axis: int, angle_deg: float, wait: bool = True,
            timeout_s: float = DEFAULT_WAIT_S) -> MotionStatus | None:
    """MOVE_TO an absolute angle; with wait, the status once the axis is at rest there (MotionError if a stop
    or a fault ended the move first)."""
    check_axis(axis)
    answer = _command(link, "MOVE_TO", {"axis": axis, "angle_mdeg": mdeg(angle_deg)}, axis, f"{angle_deg:g} deg")
    if not wait:
        return None
    return _at_rest(link, answer, axis, "REACHED", f"the move of axis {axis} to {angle_deg:g} deg", timeout_s)


@overload
def home(link: BoardLink, axis: int, method: str = ..., angle_deg: float = ..., wait: Literal[True] = ...,
         timeout_s: float = ...) -> MotionStatus: ...
@overload
def home(link: BoardLink, axis: int, method: str, angle_deg: float, wait: Literal[False],
         timeout_s: float = ...) -> None: ...
def home(link: BoardLink, axis: int, method: str = "here", angle_deg: float = 0.0, wait: bool = True,
         timeout_s: float = DEFAULT_WAIT_S) -> MotionStatus | None:
    """HOME: ``"here"`` makes the position now angle_deg; ``"switch"`` searches the home switch, whose edge is
    angle_deg. With wait, the status once homed (MotionError if the switch was not found, or a stop or a fault
    ended the search)."""
    check_axis(axis)
    methods = {"here": 0, "switch": 1}
    if method not in methods:
        raise MotionError(f"home method must be 'here' or 'switch', got {method!r}")
    answer = _command(link, "HOME", {"axis": axis, "method": methods[method], "angle_mdeg": mdeg(angle_deg)}, axis,
                      f"{angle_deg:g} deg")
    if not wait:
        return None
    return _at_rest(link, answer, axis, "HOMED", f"homing axis {axis} ({method})", timeout_s)


@overload
def stop(link: BoardLink, release: bool = ..., wait: Literal[True] = ..., timeout_s: float = ...) -> MotionStatus: ...
@overload
def stop(link: BoardLink, release: bool, wait: Literal[False], timeout_s: float = ...) -> None: ...
def stop(link: BoardLink, release: bool = False, wait: bool = True, timeout_s: float = 10.0) -> MotionStatus | None:
    """MOTION_STOP: every axis decelerates to rest (and its driver is released if asked); with wait, the status
    once both are at rest."""
    answer = _command(link, "MOTION_STOP", {"release": int(release)}, ORBIT)
    if not wait:
        return None
    return _wait_status(link, _statuses_after(link, answer), lambda s: all(a.at_rest for a in s.axes), timeout_s,
                        "the stop")


def _at_rest(link: BoardLink, answer: Message, axis: int, expected: str, what: str, timeout_s: float) -> MotionStatus:
    """The first status after a command's ACK with the axis at rest, returned once its driver has taken every
    pulse; MotionError unless it ended as expected."""
    final = _wait_status(link, _statuses_after(link, answer), lambda s: s.axes[axis].at_rest, timeout_s, what)
    result = final.axes[axis].result
    if result == expected:
        # the board counts a step when it hands it to its step interrupt, which makes it in the next window: the
        # last pulses of a move come up to a window after its REACHED (read at once on a loaded machine, the
        # motion check counted 1599 of 1600 pulses, and a test found the rig a step short of where it was sent)
        wait_for_status(link, lambda later: later.board_time_s >= final.board_time_s + PULSES_MADE_WITHIN_S,
                        timeout_s)
        return final
    if result == "FAULT":
        faults = [r.message.fields["fault_flags"] for r in link.received if r.message.name == "FAULT"]
        latched = ", ".join(fault_names(faults[-1])) if faults else "a fault"
        raise MotionError(f"{what} was halted by a latched fault ({latched}); its position is "
                          f"{'kept' if final.axes[axis].referenced else 'lost: home it again'}")
    if result == "SWITCH_NOT_FOUND":
        raise MotionError(f"{what}: the home switch was not found within the search travel (110 % of the soft "
                          "range); check its wiring, its active level (SWITCH_ACTIVE_LOW) and the search direction")
    raise MotionError(f"{what} ended {result} at {final.axes[axis].position_deg:g} deg")


# ---- the simulated rig ------------------------------------------------------------------------------------------


class SimulatedRig:
    """The simulated board's mechanism (phantom.hil.sim.SimulatedBoard): each axis's steps per turn and its
    angle at step count 0, home switches, and what its drivers did with the STEP, DIR and EN pins.

    The harness counts a pulse only while the axis's EN pin is driven low (as a driver does) and keeps the angle
    from the count, so the simulated orbit turns as the firmware drives it.
    """

    def __init__(self, board: SimulatedBoard) -> None:
        self.board = board

    def set_axis(self, axis: int, steps_per_rev: float, start_deg: float = 0.0) -> None:
        """The mechanism: steps per turn (as the drivers' microsteps and the gears make them) and the angle at
        step count 0 (where the rig was at power-up)."""
        check_axis(axis)
        if not (math.isfinite(steps_per_rev) and steps_per_rev > 0 and math.isfinite(start_deg)):
            raise MotionError(f"steps_per_rev must be > 0 and start_deg finite, got {steps_per_rev!r}, {start_deg!r}")
        self.board.motion(f"axis {axis} {steps_per_rev!r} {start_deg!r}")

    def set_home_switch(self, axis: int, low_deg: float, high_deg: float, active_high: bool = True) -> None:
        """A home switch that is active while the axis's angle is in [low_deg, high_deg] (a flag on the ring
        passing a switch), its input then high (active_high) or low."""
        check_axis(axis)
        if not (math.isfinite(low_deg) and math.isfinite(high_deg) and low_deg <= high_deg):
            raise MotionError(f"the switch's window must be finite with low <= high, got [{low_deg!r}, {high_deg!r}]")
        self.board.motion(f"switch {axis} {low_deg!r} {high_deg!r} {int(active_high)}")

    def remove_home_switch(self, axis: int) -> None:
        """No switch: the input floats (the firmware's pull-up reads it high)."""
        check_axis(axis)
        self.board.motion(f"switch {axis} off")

    def axes(self) -> list[dict[str, Any]]:
        """Each axis as its driver saw it: steps, angle_deg (None until set_axis), enabled, dir_high, pulses,
        pulses_while_released (a driver ignores them), released_since_s (simulated time; None while enabled),
        home_input_high, and the pulse timing minima in cycles of 16 MHz: min_high_cycles, min_low_cycles,
        min_dir_setup_cycles, min_dir_hold_cycles, min_interval_cycles (None before any)."""
        axes: list[dict[str, Any]] = self.board.motion()["axes"]
        return axes

    def angle_deg(self, axis: int) -> float | None:
        angle: float | None = self.axes()[axis]["angle_deg"]
        return angle

    def reset_counters(self) -> None:
        """Forget the pulse counters, timing minima and the pulse log (the angles stay)."""
        self.board.motion("reset")

    def pulse_log(self, axis: int) -> tuple[np.ndarray, np.ndarray]:
        """The pulses the axis's driver took since the last reset: their times (s of simulated time) and
        directions (+1, -1)."""
        check_axis(axis)
        with tempfile.TemporaryDirectory(prefix="phantom-pulses-") as directory:
            path = Path(directory) / "pulses.bin"
            self.board.motion(f"log {axis} {path}")
            records = np.fromfile(path, dtype=np.dtype([("cycle", "<u8"), ("direction", "i1")]))
        frequency_hz = self.board.cycle_stats()["frequency_hz"]
        return records["cycle"] / float(frequency_hz), records["direction"].astype(int)


def profile_limits(times_s: np.ndarray, directions: np.ndarray, span_s: float = 0.05) -> dict[str, float]:
    """The fastest speed and the largest acceleration of a pulse train, in steps/s and steps/s^2.

    The position (the running sum of the directions) is interpolated linearly between pulses and sampled every
    ``span_s``; the speed is its difference over one span and the acceleration its second difference over two:
    averages over those spans, which the pulse times' quantization (16 us) and jitter barely touch.
    """
    times_s = np.asarray(times_s, dtype=float)
    positions = np.cumsum(np.asarray(directions, dtype=float))
    grid = np.arange(times_s[0], times_s[-1], span_s) if len(times_s) >= 2 else np.array([])
    path = np.interp(grid, times_s, positions) if grid.size else grid
    speed = np.diff(path) / span_s
    accel = np.diff(path, 2) / span_s**2
    return {
        "max_speed_steps_s": float(np.abs(speed).max()) if speed.size else 0.0,
        "max_accel_steps_s2": float(np.abs(accel).max()) if accel.size else 0.0,
        "duration_s": float(times_s[-1] - times_s[0]) if len(times_s) else 0.0,
    }


def measure_cycles(link: BoardLink, board: SimulatedBoard | None, step_rate: float, duration_s: float = 4.0,
                   telemetry_period_ms: int = 20, kpa: float = 2.0) -> dict[str, Any]:
    """CPU use with all three chambers regulating at ``kpa``, telemetry every telemetry_period_ms, and the orbit
    moving at ``step_rate`` steps/s (0: no axis configured) for duration_s of board time.

    The orbit is configured with 64000 steps per turn and a speed of step_rate steps/s, and sent on a move long
    enough to cruise through the measurement (its ramps, a tenth of a second, are over before it starts).
    Returns the CPU use, the control tick's cycles (mean, max, budget), step_rate, steps (the pulses its driver
    took meanwhile), pulse_rate_hz (their rate in board time, from the driver's pulse log), step_isr_cycles_mean,
    stack_bytes_max and tick_overruns (from telemetry).
    """
    if board is None:
        raise MotionError("cycle counts need the simulator (--sim)")
    if not 0 <= step_rate <= MAX_STEP_RATE:
        raise MotionError(f"step_rate must be in [0, {MAX_STEP_RATE}] steps/s, got {step_rate!r}")
    bench.start_session(link, telemetry_period_ms=telemetry_period_ms)
    steps_per_rev = 64000.0
    rig = SimulatedRig(board)
    rig.set_axis(ORBIT, steps_per_rev)
    if step_rate:
        speed_deg_s = step_rate * 360.0 / steps_per_rev
        configure(link, ORBIT, AxisConfig(steps_per_rev, speed_deg_s, speed_deg_s * 20, -ANGLE_LIMIT_DEG,
                                          ANGLE_LIMIT_DEG))
        angle = status(link).axes[ORBIT].position_deg
        target = angle + math.copysign(speed_deg_s * (duration_s + 3.0), -angle or 1.0)
        move_to(link, ORBIT, target, wait=False)
    bench.set_setpoints(link, [int(kpa * 1e3)] * 3)
    bench.wait_board_time(link, 2.0)
    rig.reset_counters()
    board.cycle_stats(reset=True)
    first = bench.latest_telemetry(link)
    bench.wait_board_time(link, duration_s)
    stats = board.cycle_stats()
    last = bench.latest_telemetry(link)
    steps = rig.axes()[ORBIT]["pulses"]
    # the pulses' own rate in board time: the counters and the cycle statistics are reset and read by separate
    # round trips, so the steps counted also cover the board time between them (70 ms, +2.3 %, on a loaded
    # machine's make test)
    pulse_times_s, _ = rig.pulse_log(ORBIT)
    pulse_rate_hz = (len(pulse_times_s) - 1) / (pulse_times_s[-1] - pulse_times_s[0]) if len(pulse_times_s) > 1 \
        else 0.0
    link.command("VENT")
    if step_rate:
        stop(link, release=True)
    frequency = stats["frequency_hz"]
    elapsed = stats["elapsed_cycles"]
    step_isr = stats["regions"].get("step_isr", {"calls": 0, "total_cycles": 0})
    return {
        "step_rate": step_rate,
        "steps": steps,
        "pulse_rate_hz": float(pulse_rate_hz),
        "elapsed_s": elapsed / frequency,
        "cpu_use_fraction": stats["cpu_use_fraction"],
        "control_tick_cycles_mean": stats["control_tick_cycles_mean"],
        "control_tick_cycles_max": stats["control_tick_cycles_max"],
        "control_tick_budget_cycles": frequency // CONSTANTS["TICK_HZ"],
        "step_isr_cycles_mean": step_isr["total_cycles"] / step_isr["calls"] if step_isr["calls"] else None,
        "stack_bytes_max": stats["stack_bytes_max"],
        "tick_overruns": (last["tick_overruns"] - first["tick_overruns"]) & 0xFFFF,
        "regions": stats["regions"],
    }


#: The orbit of docs/hardware.md: a 200-step motor at 16 microsteps on a 9:1 belt, 30 deg/s, 240 deg/s^2,
#: +-190 deg (the camera's cable allows a little over a turn), homed at 10 deg/s onto a switch at -185 deg.
BENCH_ORBIT = SCANNER_AXES[ORBIT]


def check_motion(link: BoardLink, board: SimulatedBoard | None = None, config: AxisConfig = BENCH_ORBIT,
                 move_deg: float = 90.0, axis: int = ORBIT) -> dict[str, Any]:
    """The bench's motion check of one axis: configure it, move it by move_deg and back, and read its status.

    With the simulated board (``board``) it also compares the board's position with the steps its driver took,
    checks the pulse timing against the drivers' datasheets (2 us high and low, 1 us DIR set-up and hold) and the
    speed and acceleration limits against the pulse times, and homes against a simulated switch. On a real board
    the position is the board's own; watch the axis turn by move_deg and back.
    """
    bench.start_session(link)
    report: dict[str, Any] = {"axis": axis, "config": asdict(configure(link, axis, config))}
    start = status(link).axes[axis]
    rig = SimulatedRig(board) if board is not None else None
    if rig is not None:
        rig.set_axis(axis, config.steps_per_rev, start_deg=start.position_deg - rig.axes()[axis]["steps"] * 360
                     / config.steps_per_rev)
        rig.remove_home_switch(axis)
        rig.reset_counters()
    target = start.position_deg + move_deg
    there = move_to(link, axis, target)
    report["there_deg"] = there.axes[axis].position_deg if there else None
    checks = {"reached": there is not None and there.axes[axis].position_steps == config.steps(target)}
    if rig is not None:
        simulated = rig.axes()[axis]  # every pulse of the move made: move_to returns once they are
        times_s, directions = rig.pulse_log(axis)
        limits = profile_limits(times_s, directions)
        speed, accel = config.steps(config.max_speed_deg_s), config.steps(config.max_accel_deg_s2)
        report.update(
            steps_made=simulated["pulses"], pulses_while_released=simulated["pulses_while_released"],
            rig_angle_deg=simulated["angle_deg"],
            min_high_us=simulated["min_high_cycles"] / 16, min_low_us=simulated["min_low_cycles"] / 16,
            max_speed_deg_s=limits["max_speed_steps_s"] * 360 / config.steps_per_rev,
            max_accel_deg_s2=limits["max_accel_steps_s2"] * 360 / config.steps_per_rev,
        )
        checks["steps_counted"] = simulated["pulses"] == abs(config.steps(target) - start.position_steps)
        checks["pulse_widths"] = simulated["min_high_cycles"] >= 32 and simulated["min_low_cycles"] >= 32
        checks["speed_limit"] = limits["max_speed_steps_s"] <= speed * 1.005
        checks["accel_limit"] = limits["max_accel_steps_s2"] <= accel * 1.02
    back = move_to(link, axis, start.position_deg)
    report["back_deg"] = back.axes[axis].position_deg if back else None
    checks["back"] = back is not None and back.axes[axis].position_steps == start.position_steps
    if rig is not None:
        switch_deg = start.position_deg - min(move_deg, 20.0)
        rig.set_home_switch(axis, switch_deg - 5.0, switch_deg, active_high=True)
        homing = replace(config, home_switch=True, home_speed_deg_s=min(10.0, config.max_speed_deg_s))
        configure(link, axis, homing)
        homed = home(link, axis, "switch", angle_deg=switch_deg)
        rig_deg = rig.angle_deg(axis)
        error_deg = homed.axes[axis].position_deg - rig_deg if homed is not None and rig_deg is not None else None
        report["home_error_deg"] = error_deg
        checks["homed"] = error_deg is not None and abs(error_deg) <= homing.home_speed_deg_s * 0.002 + 2 * 360 / (
            config.steps_per_rev)
        rig.remove_home_switch(axis)
        configure(link, axis, config)
        move_to(link, axis, start.position_deg)
    report["checks"] = checks
    report["passed"] = all(checks.values())
    return report
