"""The test bench: the same checks against a simulated board (simavr) or a real one on a serial port.

Each check takes a :class:`~phantom.hil.link.BoardLink` and, for the faults that must be injected into the
plant or the line, the :class:`~phantom.hil.sim.SimulatedBoard`; on a real board those are skipped with the
reason. Times are in board time (the firmware's ``time_ms``) or, for fault reaction times, in simulated time
read from the harness, which sees the PWM registers at the plant's step (100 us).
"""

from __future__ import annotations

import json
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from phantom import PhantomError, require_extra
from phantom.hil.link import BoardLink, LinkError, Received
from phantom.hil.sim import SimulatedBoard
from phantom.protocol.codec import Message
from phantom.protocol.link import board_host_deadline_ms, fault_names
from phantom.protocol.messages import BITS, CONSTANTS, ENUMS, PROTOCOL_VERSION, SPEC_HASH
from phantom.protocol.sensor import ADC_COUNT_KPA

#: Telemetry period for the checks (ms): the finest the protocol allows, for the step's time resolution.
TELEMETRY_PERIOD_MS = CONSTANTS["MIN_TELEMETRY_PERIOD_MS"]
#: Dead-host deadline the checks configure (ms of wall clock): the firmware's default, which is a real board's;
#: a simulated board at another speed gets the deadline that gives its host as long (:func:`host_deadline_s`).
HOST_DEADLINE_MS = CONSTANTS["DEFAULT_HOST_DEADLINE_MS"]
#: Stated time within which the blowers must stop after each fault (s), and why:
STOP_LIMITS_S = {
    # from the injection: a few bad samples in a row at 500 Hz, plus the tick that acts on it
    "sensor_cut": 0.05,
    # from the injection: the reading falls to the room's within a few ms, the PID pushes at full drive, and
    # the firmware's plausibility time (the reading never moves) passes, then one tick
    "tube_off": CONSTANTS["PLAUSIBLE_TIME_MS"] / 1e3 + 0.05,
    # from the injection: the stuck blower first has to push the pressure from 1.5 kPa over the limit (4 kPa), then
    # one tick. The fill is the plant's: 1.92 s on the simulated board since its truth table (2026-11-27: 2.6 ml/kPa
    # over the first kPa where the linear plant had 1.0; 0.5 s before), 0.7 kPa/s near the limit, so one ADC count
    # is 0.08 s. The limit leaves a quarter of that fill for a real chamber's (a firmware that missed the latch
    # would let the blower run on for ever)
    "stuck_blower": 2.5,
    # from the step to 1.5 kPa with the severe leak already there: the blower runs at its ceiling from the first
    # tick, the chamber rises (the reading responds) but stays far below its setpoint, so the firmware's 2 s at
    # the ceiling, then one tick; 0.05 s of margin for the command's way to the board. (A severe leak that opens
    # under a held pressure is the plausibility rule's: the reading falls and never rises, see tube_off.)
    "leak": CONSTANTS["LEAK_TIME_MS"] / 1e3 + 0.05,
}
#: A silent host's stop limit from its last byte, past the session's deadline (:func:`host_deadline_s`): that
#: deadline counted from the tick that saw the last frame (up to one tick later) and compared strictly (one more
#: tick), then the drive update after that tick (under one tick).
SILENT_HOST_LATE_S = 0.006


def host_deadline_s(link: BoardLink) -> float:
    """The dead-host deadline :func:`start_session` gives the board on ``link`` (s of the board's clock): the
    checks' :data:`HOST_DEADLINE_MS` of wall clock at the link's speed."""
    return board_host_deadline_ms(HOST_DEADLINE_MS, link.time_scale) / 1e3


def stop_limit_s(fault: str, link: BoardLink) -> float:
    """How long ``fault`` may take to stop the blowers on ``link``'s board (s of its clock): :data:`STOP_LIMITS_S`,
    a silent host's from its session's deadline."""
    return host_deadline_s(link) + SILENT_HOST_LATE_S if fault == "silent_host" else STOP_LIMITS_S[fault]


#: The firmware's leak rule (protocol/spec.toml's constants, PROTOCOL.md section 7): LEAK_n latches when the
#: blower sits at its ceiling while the chamber reads more than this far below its setpoint (kPa) ...
LEAK_MIN_ERROR_KPA = CONSTANTS["LEAK_MIN_ERROR_PA"] / 1e3
#: ... for this long (s).
LEAK_TIME_S = CONSTANTS["LEAK_TIME_MS"] / 1e3
#: Extra leak (ml/s per kPa) of the severe leak: on the default plant the blower at full drive then holds only
#: about 0.6 kPa (13.3 ml/s of free flow against 1.8 + 20 ml/s/kPa of leak), far below the 1.5 kPa setpoint.
LEAK_SEVERE_ML_PER_S_PER_KPA = 20.0
#: Extra leak of the mild one: holding 1.5 kPa then takes 10.2 ml/s of the 12.3 ml/s the blower gives there at
#: full drive (a drive of about 0.83), so the PID compensates it.
LEAK_MILD_ML_PER_S_PER_KPA = 5.0
#: How long the mild leak is watched (s of board time): longer than the leak time limit.
LEAK_MILD_WATCH_S = LEAK_TIME_S + 1.5
#: The fault checks of a report, with the chamber each is injected into.
FAULT_CHECKS = (
    ("sensor_cut", 1), ("tube_off", 0), ("stuck_blower", 0), ("leak", 2), ("mild_leak", 2), ("silent_host", None)
)
#: Settling band of the step (fraction of the step).
SETTLING_BAND = 0.02
#: Window of the centred moving average the settling time is judged on (s). The 2 % band of a 2 kPa step,
#: +/-40 Pa, is under one ADC count (54 Pa): single noisy samples of the measurement cross it although the
#: pressure has settled; 50 ms of averaging (5 telemetry samples) removes that and shifts a settling time by
#: well under a sample for responses slower than about 0.1 s.
SETTLING_SMOOTHING_S = 0.05


class BenchError(PhantomError):
    """A bench check could not run (bad arguments, board not answering)."""


def fault_bits() -> dict[str, int]:
    return BITS["fault"]


def _settling_time(t: np.ndarray, p: np.ndarray, target: float, band: float) -> float | None:
    """The time after which p stays within target +/- band * target (None if it ends outside)."""
    outside = np.nonzero(np.abs(p - target) > band * target)[0]
    if outside.size == 0:
        return float(t[0])
    if outside[-1] == p.size - 1:
        return None
    return float(t[outside[-1] + 1])


def step_metrics(times_s: ArrayLike, pressures_kpa: ArrayLike, target_kpa: float, band: float = SETTLING_BAND,
                 smoothing_s: float = SETTLING_SMOOTHING_S) -> dict[str, Any]:
    """Rise time, overshoot, settling time and steady-state error of a step from 0 at t = 0.

    Parameters
    ----------
    times_s, pressures_kpa
        The response sampled from the step on (times relative to the step, s; pressures in kPa).
    target_kpa
        The setpoint.
    band
        Settling band as a fraction of the target.
    smoothing_s
        Width of the centred moving average the settling time is judged on (0: the raw samples).

    Returns
    -------
    dict
        ``rise_time_s`` (10 % to 90 % of the target, first crossings), ``overshoot_pct`` (peak above the target
        in % of it, 0 if none), ``settling_time_s`` (from then on the smoothed response stays inside
        target +/- band; None if it never settles), ``settling_time_raw_s`` (the same on the raw samples),
        ``steady_state_error_kpa`` (mean of target - p over the last 20 % of the record),
        ``steady_state_noise_kpa`` (standard deviation there).
    """
    t = np.asarray(times_s, dtype=float)
    p = np.asarray(pressures_kpa, dtype=float)
    if t.size < 5 or t.size != p.size:
        raise BenchError("a step response needs at least 5 samples of time and pressure")
    if target_kpa <= 0:
        raise BenchError(f"the step target must be > 0 kPa, got {target_kpa}")

    def first_crossing(level: float) -> float | None:
        above = np.nonzero(p >= level)[0]
        if above.size == 0:
            return None
        k = above[0]
        if k == 0:
            return float(t[0])
        # linear interpolation between the samples around the crossing
        return float(t[k - 1] + (level - p[k - 1]) * (t[k] - t[k - 1]) / (p[k] - p[k - 1]))

    t10, t90 = first_crossing(0.1 * target_kpa), first_crossing(0.9 * target_kpa)
    window = max(1, int(round(smoothing_s / np.median(np.diff(t))))) if smoothing_s > 0 else 1
    smoothed = np.convolve(p, np.ones(window) / window, mode="valid")
    centred_t = t[(window - 1) // 2 : (window - 1) // 2 + smoothed.size]
    tail = p[t >= t[0] + 0.8 * (t[-1] - t[0])]
    return {
        "rise_time_s": None if t10 is None or t90 is None else t90 - t10,
        "overshoot_pct": max(0.0, float(p.max() - target_kpa) / target_kpa * 100.0),
        "settling_time_s": _settling_time(centred_t, smoothed, target_kpa, band),
        "settling_time_raw_s": _settling_time(t, p, target_kpa, band),
        "steady_state_error_kpa": float(target_kpa - tail.mean()),
        "steady_state_noise_kpa": float(tail.std()),
    }


def start_session(link: BoardLink, telemetry_period_ms: int = TELEMETRY_PERIOD_MS) -> dict[str, Any]:
    """HELLO, configure telemetry and the deadline, start the keepalive, clear a latched fault if any."""
    reply = link.hello()
    link.command("SET_CONFIG", {"telemetry_period_ms": telemetry_period_ms,
                                "host_deadline_ms": round(host_deadline_s(link) * 1e3)})
    link.keepalive(True)
    if reply.fields["fault_flags"]:
        link.command("CLEAR_FAULT", accept_nack=True)
    return reply.fields


def latest_telemetry(link: BoardLink, timeout_s: float = 1.0) -> dict[str, Any]:
    """The next TELEMETRY message to arrive (its fields)."""
    got = link.wait_for(lambda m: m.name == "TELEMETRY", timeout_s, link.mark())
    if got is None:
        raise LinkError(f"no telemetry from the board within {timeout_s} s")
    return got.message.fields


def wait_on_board_clock(link: BoardLink, predicate: Callable[[Message], bool], seconds: float,
                        start: int) -> Received | None:
    """The first message from index start satisfying predicate within ``seconds`` of board time (telemetry
    clock), or None. Without telemetry, a generous host-side timeout ends the wait."""
    t0_ms = None

    def done(message: Message) -> bool:
        nonlocal t0_ms
        if predicate(message):
            return True
        if message.name == "TELEMETRY":
            t0_ms = message.fields["time_ms"] if t0_ms is None else t0_ms
            return bool(message.fields["time_ms"] - t0_ms > seconds * 1e3)
        return False

    got = link.wait_for(done, (5.0 + 10.0 * seconds) * link.time_scale, start)
    return got if got is not None and predicate(got.message) else None


def wait_board_time(link: BoardLink, seconds: float,
                    until: Callable[[dict[str, Any]], bool] | None = None) -> dict[str, Any] | None:
    """Wait on the board's telemetry clock until ``until(fields)`` holds or ``seconds`` of board time have
    passed; returns the last telemetry fields, or None when the board's clock ran out first.

    Waiting on the board's clock, not the host's, keeps the checks right when the simulator runs slower than
    asked (a loaded machine); the host-side timeout only catches a board that stopped talking.
    """
    start = link.mark()
    first = link.wait_for(lambda m: m.name == "TELEMETRY", 1.0, start)
    if first is None:
        raise BenchError("no telemetry from the board: is a session open?")
    t0_ms = first.message.fields["time_ms"]

    def done(message: Message) -> bool:
        if message.name != "TELEMETRY":
            return False
        return bool(message.fields["time_ms"] - t0_ms >= seconds * 1e3
                    or (until is not None and until(message.fields)))

    got = link.wait_for(done, (5.0 + 10.0 * seconds) * link.time_scale, start)
    if got is None:
        raise BenchError(f"the board's telemetry stopped before {seconds} s of board time had passed")
    fields = got.message.fields
    return fields if until is None or until(fields) else None


def vent_and_wait(link: BoardLink, below_kpa: float = 0.05, timeout_s: float = 20.0) -> None:
    """VENT, then wait until every chamber reads below below_kpa, for at most timeout_s of board time."""
    link.command("VENT")
    if wait_board_time(link, timeout_s, lambda fields: max(fields["pressure_pa"]) < below_kpa * 1e3) is None:
        raise BenchError(f"the chambers did not vent below {below_kpa} kPa within {timeout_s} s")


def zero_sensors(link: BoardLink, attempts: int = 10) -> None:
    """ZERO_SENSORS with the chambers vented. The board refuses it (NOT_SETTLED) until every blower has been off
    and every reading still for ZERO_SETTLE_MS, and answers BUSY while its own start-up zero runs: wait that
    long on the board's clock and ask again, so that the offsets are measured now."""
    names = {v: k for k, v in ENUMS["status"].items()}
    retry = {ENUMS["status"]["BUSY"], ENUMS["status"]["NOT_SETTLED"]}
    for _ in range(attempts):
        # one transmission with a long wait: a late retransmission would start a second zeroing
        answer = link.command("ZERO_SENSORS", timeout_s=2.0, attempts=1, accept_nack=True)
        if answer.name == "ACK":
            return
        if answer.fields["status"] not in retry:
            reason = names.get(answer.fields["status"], str(answer.fields["status"]))
            if answer.fields["status"] == ENUMS["status"]["FAULT_LATCHED"]:
                try:  # which fault: telemetry carries the latch (a session without telemetry gets the status alone)
                    reason += f" ({', '.join(fault_names(latest_telemetry(link)['fault_flags']))})"
                except LinkError:
                    pass
            raise BenchError(f"the board refused ZERO_SENSORS: {reason}")
        wait_board_time(link, CONSTANTS["ZERO_SETTLE_MS"] / 1e3 / 2)
    raise BenchError(f"ZERO_SENSORS still refused ({names.get(answer.fields['status'])}) after {attempts} tries")


def set_setpoints(link: BoardLink, setpoints_pa: list[int], attempts: int = 5) -> None:
    """SET_SETPOINTS, waiting out a zeroing in progress (NACK BUSY) before trying again."""
    zeroing = ENUMS["chamber_state"]["ZEROING"]
    for _ in range(attempts):
        answer = link.command("SET_SETPOINTS", {"setpoint_pa": list(setpoints_pa)}, accept_nack=True)
        if answer.name == "ACK":
            return
        if answer.fields["status"] != ENUMS["status"]["BUSY"]:
            names = {v: k for k, v in ENUMS["status"].items()}
            raise LinkError(f"the board refused SET_SETPOINTS: NACK {names.get(answer.fields['status'])}")
        link.wait_for(lambda m: m.name == "TELEMETRY" and zeroing not in m.fields["state"], 2.0, link.mark())
    raise LinkError(f"SET_SETPOINTS stayed busy after {attempts} tries")


def check_handshake(link: BoardLink) -> dict[str, Any]:
    """HELLO is answered with the board's identity; a HELLO with another spec hash is refused."""
    reply = link.hello().fields
    start = link.mark()
    link.send("HELLO", {"protocol_version": PROTOCOL_VERSION, "spec_hash": SPEC_HASH ^ 0xFFFFFFFF})
    refused = link.wait_for(lambda m: m.name == "HELLO_REPLY", 1.0, start)
    names = {kind: {v: k for k, v in values.items()} for kind, values in ENUMS.items()}
    link.hello()
    return {
        "passed": refused is not None and refused.message.fields["status"] == ENUMS["status"]["SPEC_MISMATCH"],
        "protocol_version": reply["protocol_version"],
        "spec_hash": f"0x{reply['spec_hash']:08X}",
        "firmware_version": f"{reply['firmware_major']}.{reply['firmware_minor']}.{reply['firmware_patch']}",
        "board": names["board"].get(reply["board"], reply["board"]),
        "chamber_count": reply["chamber_count"],
        "reset_cause": names["reset_cause"].get(reply["reset_cause"], reply["reset_cause"]),
        "mismatched_hello_refused": refused is not None
        and refused.message.fields["status"] == ENUMS["status"]["SPEC_MISMATCH"],
    }


def check_step(link: BoardLink, chamber: int, target_kpa: float, duration_s: float = 3.0,
               gains: Sequence[float] | None = None) -> dict[str, Any]:
    """A step 0 -> target_kpa on one chamber (the others off); metrics from the board's own telemetry.

    The step time is the board time of the first telemetry sample carrying the new setpoint, so it is late by
    at most one telemetry period (10 ms); the metrics' times count from there. ``gains`` (kp per kPa, ki per
    kPa s, kd s per kPa) are sent with SET_PID first (limits: 4 kPa, full drive); None keeps the board's.
    """
    if chamber not in (0, 1, 2):
        raise BenchError(f"chamber must be 0, 1 or 2, got {chamber!r}")
    if not 0 < target_kpa <= 20:
        raise BenchError(f"the step target must be in (0, 20] kPa, got {target_kpa!r}")
    start_session(link)
    if gains is not None:
        kp, ki, kd = (float(g) for g in gains)
        link.command("SET_PID", {"chamber": chamber, "kp_per_kpa": kp, "ki_per_kpa_s": ki, "kd_s_per_kpa": kd,
                                 "max_pressure_pa": CONSTANTS["DEFAULT_MAX_PRESSURE_PA"], "max_drive": 65535})
    vent_and_wait(link)
    zero_sensors(link)
    setpoints = [0, 0, 0]
    setpoints[chamber] = int(round(target_kpa * 1e3))
    start = link.mark()
    set_setpoints(link, setpoints)
    first = link.wait_for(
        lambda m: m.name == "TELEMETRY" and m.fields["setpoint_pa"][chamber] == setpoints[chamber], 1.0, start
    )
    if first is None:
        raise BenchError("the board acknowledged the setpoint but its telemetry never showed it")
    t0_ms = first.message.fields["time_ms"]
    # on the board's clock: the host-side timeout only catches a board that stopped talking (a loaded machine
    # runs the simulator slower than asked)
    link.wait_for(
        lambda m: m.name == "TELEMETRY" and m.fields["time_ms"] - t0_ms >= duration_s * 1e3,
        (5.0 + 10.0 * duration_s) * link.time_scale,
        start,
    )
    samples = [r.message.fields for r in link.telemetry(start) if r.message.fields["time_ms"] >= t0_ms]
    link.command("VENT")
    times_s = np.array([(s["time_ms"] - t0_ms) / 1e3 for s in samples])
    pressures_kpa = np.array([s["pressure_pa"][chamber] / 1e3 for s in samples])
    drives = np.array([s["drive"][chamber] / 65535 for s in samples])
    metrics = step_metrics(times_s, pressures_kpa, target_kpa)
    others = np.array([[s["pressure_pa"][k] / 1e3 for k in range(3) if k != chamber] for s in samples])
    metrics.update(
        chamber=chamber,
        target_kpa=target_kpa,
        gains=None if gains is None else [float(g) for g in gains],
        adc_count_kpa=ADC_COUNT_KPA,
        max_drive_level=float(drives.max()),
        final_drive_level=float(drives[-20:].mean()),
        other_chambers_max_kpa=float(others.max()),
        tick_overruns=samples[-1]["tick_overruns"] - samples[0]["tick_overruns"],
        fault_flags=(fault_flags := int(np.bitwise_or.reduce([s["fault_flags"] for s in samples]))),
        faults=fault_names(fault_flags),
        trace={"time_s": times_s.tolist(), "pressure_kpa": pressures_kpa.tolist(), "drive_level": drives.tolist()},
    )
    return metrics


def _regulate(link: BoardLink, kpa: float, settle_s: float) -> None:
    start_session(link)
    set_setpoints(link, [int(kpa * 1e3)] * 3)
    wait_board_time(link, settle_s)


def _recover(link: BoardLink, board: SimulatedBoard) -> None:
    """Remove the injected fault, re-open the session and clear the latch (retrying while its cause lasts)."""
    board.inject("clear")
    for _ in range(40):
        start_session(link)
        answer = link.command("CLEAR_FAULT", accept_nack=True)
        if answer.name == "ACK":
            break
        link.command("VENT", accept_nack=True)
        link.wait_for(lambda m: False, 0.25, link.mark())
    vent_and_wait(link)


def check_fault(link: BoardLink, board: SimulatedBoard | None, fault: str,
                chamber: int | None = None) -> dict[str, Any]:
    """Inject one fault while all chambers hold 1.5 kPa (the severe leak: before they are set to 1.5 kPa); the
    latch must trip and every blower stop in time.

    ``fault`` is ``sensor_cut``, ``tube_off``, ``stuck_blower``, ``leak`` (a severe leak,
    LEAK_SEVERE_ML_PER_S_PER_KPA, that the blower cannot overcome), ``mild_leak`` (LEAK_MILD_ML_PER_S_PER_KPA:
    the PID must compensate it and nothing may latch; these need ``board``, a SimulatedBoard) or
    ``silent_host``. The stop time is measured in simulated time from the injection (from the step for the
    severe leak, from the host's last byte for a silent host) to the first plant step at which every PWM output
    is off.
    """
    if fault == "mild_leak":
        return _check_mild_leak(link, board, chamber)
    bits = fault_bits()
    injected_s: float | None
    if fault == "silent_host":
        _regulate(link, 1.5, 1.5)
        start = link.mark()
        link.keepalive(False)
        injected_s = None
    elif board is None:
        return {"fault": fault, "skipped": "needs --sim: faults are injected into the simulated plant"}
    elif fault == "leak":
        start_session(link)
        board.inject(fault, chamber=chamber, conductance_ml_per_s_per_kpa=LEAK_SEVERE_ML_PER_S_PER_KPA)
        start = link.mark()
        injected_s = board.plant_state()["time_s"]
        set_setpoints(link, [1500] * 3)
    else:
        _regulate(link, 1.5, 1.5)
        start = link.mark()
        injected_s = board.inject(fault, chamber=chamber)
    got = wait_on_board_clock(link, lambda m: m.name == "FAULT", max(3.0, 1.0 + stop_limit_s(fault, link)),
                              start)
    result: dict[str, Any] = {"fault": fault, "chamber": chamber}
    if board is not None:
        state = board.plant_state()
        if fault == "silent_host":
            injected_s = state["last_host_byte_s"]
        off_since = state["all_off_since_s"]
        result["stop_time_s"] = None if off_since is None or got is None else off_since - injected_s
        result["pressures_kpa_after"] = [p / 1e3 for p in state["pressures_pa"]]
        # the highest true pressure each chamber reached from the injection on: at the latch for a fault
        # that pushes the pressure up (the blowers stop there)
        result["peak_true_kpa"] = [p / 1e3 for p in state["peak_pressures_pa"]]
    if board is None and fault == "silent_host" and got is not None:
        # on a real board, board time: from the board's clock at the last PING it answered to the latch
        before = [r for r in list(link.received) if r.host_time_s <= got.host_time_s]
        pongs = [r.message for r in before if r.message.name == "PONG"]
        if pongs:
            result["stop_time_s"] = (got.message.fields["time_ms"] - pongs[-1].fields["board_time_ms"]) / 1e3
    if got is not None:
        names = {v: k for k, v in bits.items()}
        result["latched"] = names.get(got.message.fields["fault_bit"], got.message.fields["fault_bit"])
        result["pressures_kpa_at_latch"] = [p / 1e3 for p in got.message.fields["pressure_pa"]]
    else:
        result["latched"] = None
    expected = {
        "sensor_cut": f"SENSOR_{chamber}",
        "tube_off": f"IMPLAUSIBLE_{chamber}",
        "stuck_blower": f"OVERPRESSURE_{chamber}",
        "leak": f"LEAK_{chamber}",
        "silent_host": "DEAD_HOST",
    }[fault]
    result["expected"] = expected
    result["limit_s"] = stop_limit_s(fault, link)
    stop = result.get("stop_time_s")
    result["passed"] = result["latched"] == expected and stop is not None and stop <= result["limit_s"]
    if board is not None:
        _recover(link, board)
    else:
        link.keepalive(True)
        start_session(link)
        link.command("CLEAR_FAULT", accept_nack=True)
        link.command("VENT")
    return result


def _check_mild_leak(link: BoardLink, board: SimulatedBoard | None, chamber: int | None) -> dict[str, Any]:
    """A leak the PID can outpump, while all chambers hold 1.5 kPa: no fault for LEAK_MILD_WATCH_S (longer
    than the leak time limit), the chamber held within 0.1 kPa (two ADC counts) at a higher drive, below the
    ceiling."""
    if board is None:
        return {"fault": "mild_leak", "skipped": "needs --sim: faults are injected into the simulated plant"}
    _regulate(link, 1.5, 1.5)
    tight_drive = latest_telemetry(link)["drive"][chamber] / 65535
    start = link.mark()
    board.inject("leak", chamber=chamber, conductance_ml_per_s_per_kpa=LEAK_MILD_ML_PER_S_PER_KPA)
    got = wait_on_board_clock(link, lambda m: m.name == "FAULT", LEAK_MILD_WATCH_S, start)
    telemetry = latest_telemetry(link)
    names = {v: k for k, v in fault_bits().items()}
    held_kpa = telemetry["pressure_pa"][chamber] / 1e3
    drive = telemetry["drive"][chamber] / 65535
    result = {
        "fault": "mild_leak",
        "chamber": chamber,
        "expected": None,
        "latched": None if got is None else names.get(got.message.fields["fault_bit"], got.message.fields["fault_bit"]),
        "watched_s": LEAK_MILD_WATCH_S,
        "held_kpa": held_kpa,
        "drive_level": drive,
        "drive_level_before": tight_drive,
        "passed": got is None and telemetry["fault_flags"] == 0 and abs(held_kpa - 1.5) < 0.1 and drive < 1.0,
    }
    _recover(link, board)
    return result


def check_line_noise(link: BoardLink, board: SimulatedBoard | None, commands: int = 30,
                     flip_probability: float = 0.01, drop_probability: float = 0.01) -> dict[str, Any]:
    """Setpoint commands through a noisy line: every one is acknowledged (retransmission recovers), the board
    never applies a value that was not sent, and its counters show the corrupted frames it dropped."""
    if board is None:
        return {"skipped": "needs --sim: line noise is injected into the simulated serial line"}
    start_session(link)
    before = latest_telemetry(link)
    board.inject("line_noise", flip_probability=flip_probability, drop_probability=drop_probability)
    start = link.mark()
    sent = []
    retransmissions = link.retransmissions
    for k in range(commands):
        setpoints = [500 + 37 * k, 700 + 23 * k, 900 + 11 * k]
        link.command("SET_SETPOINTS", {"setpoint_pa": setpoints}, attempts=12)
        sent.append(tuple(setpoints))
    board.inject("clear")
    after = latest_telemetry(link, timeout_s=2.0)
    seen = {tuple(r.message.fields["setpoint_pa"]) for r in link.telemetry(start)}
    foreign = sorted(seen - set(sent) - {tuple(before["setpoint_pa"])})
    dropped = sum(after[k] - before[k] for k in ("rx_bad_crc", "rx_bad_frame", "rx_overflow")) & 0xFFFF
    link.command("VENT")
    return {
        "commands": commands,
        "retransmissions": link.retransmissions - retransmissions,
        "board_frames_dropped": dropped,
        "host_frames_dropped": link.reader.bad_crc
        + link.reader.bad_cobs
        + link.reader.bad_length
        + link.reader.unknown_id,
        "foreign_setpoints_applied": [list(s) for s in foreign],
        "final_setpoint_pa": list(after["setpoint_pa"]),
        "passed": not foreign and tuple(after["setpoint_pa"]) == sent[-1] and dropped > 0,
    }


def check_watchdog(link: BoardLink, board: SimulatedBoard | None) -> dict[str, Any]:
    """TEST_HANG stops the firmware kicking the watchdog: the board resets, and HELLO reports it."""
    start_session(link)
    resets_before = board.plant_state()["resets"] if board is not None else None
    link.command("TEST_HANG", {"magic": CONSTANTS["TEST_HANG_MAGIC"]})
    link.keepalive(False)
    link.wait_for(lambda m: False, 0.2, link.mark())
    reply = None
    for _ in range(20):
        try:
            reply = link.hello(attempts=1, timeout_s=0.25)
        except LinkError:
            continue
        if reply.fields["reset_cause"] == ENUMS["reset_cause"]["WATCHDOG"]:
            break
    result: dict[str, Any] = {
        "reset_cause": None
        if reply is None
        else {v: k for k, v in ENUMS["reset_cause"].items()}.get(reply.fields["reset_cause"]),
        "watchdog_fault_latched": bool(reply and reply.fields["fault_flags"] >> fault_bits()["WATCHDOG_RESET"] & 1),
    }
    if board is not None:
        result["resets_seen_by_simulator"] = board.plant_state()["resets"] - resets_before
    result["passed"] = (
        result["reset_cause"] == "WATCHDOG"
        and result["watchdog_fault_latched"]
        and (board is None or result["resets_seen_by_simulator"] >= 1)
    )
    link.keepalive(True)
    start_session(link)
    link.command("CLEAR_FAULT", accept_nack=True)
    return result


#: Step-response thresholds a report judges each step against (the firmware's gains were chosen to meet them;
#: hil/README.md): settled within the band in under this long (s) ...
STEP_SETTLING_LIMIT_S = 1.0
#: ... overshooting by less than this (% of the target) ...
STEP_OVERSHOOT_LIMIT_PCT = 5.0
#: ... with a steady-state error under one ADC count (each step's ``adc_count_kpa``).


def step_within_thresholds(step: dict[str, Any]) -> bool:
    """Whether a step response meets the thresholds above."""
    settling = step["settling_time_s"]
    return (settling is not None and settling < STEP_SETTLING_LIMIT_S
            and step["overshoot_pct"] < STEP_OVERSHOOT_LIMIT_PCT
            and abs(step["steady_state_error_kpa"]) < step["adc_count_kpa"])


def _first_crossing_s(times_s: np.ndarray, pressures_kpa: np.ndarray, level_kpa: float) -> float | None:
    """When the response first reaches ``level_kpa`` (linear between samples), as step_metrics' rise time counts."""
    above = np.nonzero(pressures_kpa >= level_kpa)[0]
    if above.size == 0:
        return None
    k = above[0]
    if k == 0:
        return float(times_s[0])
    return float(np.interp(level_kpa, pressures_kpa[k - 1:k + 1], times_s[k - 1:k + 1]))


def board_description(board: str | None) -> str:
    """``simulated board (simavr)`` or ``real board on PORT`` from a report's ``board`` entry."""
    if board is None:
        return "board not stated"
    return "simulated board (simavr)" if board.startswith("simulated") else f"real board on {board}"


def plot_steps(steps: list[dict[str, Any]], path: Path, board: str | None = None) -> Path:
    """One PNG of the step responses: the setpoint, each chamber's pressure with its 10 % and 90 % crossings
    (rise time), a zoom on the settling band with each settling time, and the drive levels.

    ``board`` is the report's ``board`` entry (``simulated (simavr)`` or the port), named in the title.
    """
    with require_extra("hil"):
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

    figure, (top, zoom, bottom) = plt.subplots(3, 1, figsize=(8, 8.5), sharex=True,
                                               gridspec_kw={"height_ratios": [3, 2, 1.4]})
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    targets = sorted({step["target_kpa"] for step in steps})
    end_s = max((step["trace"]["time_s"][-1] for step in steps), default=1.0)
    for target in targets:
        # the setpoint: 0 before the step, the target from t = 0 on
        top.step([-0.05 * end_s, 0.0, end_s], [0.0, target, target], where="post", color="k", lw=1.2,
                 ls="--", label=f"setpoint {target:g} kPa")
        zoom.axhline(target, color="k", lw=1.2, ls="--")
        low, high = target * (1 - SETTLING_BAND), target * (1 + SETTLING_BAND)
        zoom.axhspan(low, high, color="0.85", zorder=0,
                     label=f"settling band ±{100 * SETTLING_BAND:g} % ({1e3 * SETTLING_BAND * target:.0f} Pa)")
        top.axhspan(low, high, color="0.85", zorder=0)
    for index, step in enumerate(steps):
        colour = colours[index % len(colours)]
        trace = step["trace"]
        t, p = np.asarray(trace["time_s"]), np.asarray(trace["pressure_kpa"])
        target = step["target_kpa"]
        rise, settling = step["rise_time_s"], step["settling_time_s"]
        label = (f"chamber {step['chamber']}: rise {_fmt(rise)} s, settling {_fmt(settling)} s, "
                 f"overshoot {_fmt(step['overshoot_pct'], 2)} %")
        top.plot(t, p, color=colour, lw=1.2, label=label)
        zoom.plot(t, p, color=colour, lw=1.0)
        bottom.plot(t, trace["drive_level"], color=colour, lw=1.0)
        crossings = [_first_crossing_s(t, p, fraction * target) for fraction in (0.1, 0.9)]
        if None not in crossings:
            top.plot(crossings, [0.1 * target, 0.9 * target], "o", color=colour, ms=5, mfc="white")
            height = (0.3 + 0.12 * (index % 4)) * target  # one arrow per chamber, apart
            top.annotate("", xy=(crossings[1], height), xytext=(crossings[0], height),
                         arrowprops={"arrowstyle": "<->", "color": colour, "lw": 1.0})
        if settling is not None:
            zoom.axvline(settling, color=colour, lw=1.2, ls=":", label=f"chamber {step['chamber']} settled at "
                         f"{settling:.2f} s")
    if targets:
        # the band in the upper part, room for the legend under it
        zoom.set_ylim(min(targets) * (1 - 8 * SETTLING_BAND), max(targets) * (1 + 4 * SETTLING_BAND))
    top.set_ylabel("pressure (kPa)")
    zoom.set_ylabel("near the setpoint (kPa)")
    bottom.set_ylabel("drive level (0-1)")
    bottom.set_ylim(-0.05, 1.05)
    bottom.set_xlabel("time since the step (s, board clock)")
    top.set_xlim(-0.05 * end_s, end_s)
    top.legend(loc="lower right", fontsize=8)
    zoom.legend(loc="lower right", fontsize=8)
    top.set_title(f"Step responses on the {board_description(board)}\n"
                  "rise time: 10 % to 90 % of the setpoint (circles, arrows); settling: inside the band from then on "
                  f"({1e3 * SETTLING_SMOOTHING_S:g} ms average)", fontsize=9)
    for axis in (top, zoom, bottom):
        axis.grid(alpha=0.3)
    figure.tight_layout()
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(path, dpi=100)
    plt.close(figure)
    return path


def progress(message: str) -> None:
    print(f"phantom hil: {message}", file=sys.stderr, flush=True)


def run_report(link: BoardLink, board: SimulatedBoard | None, out_dir: Path, target_kpa: float = 2.0) -> dict[str, Any]:
    """Every check, then report.json, report.md and steps.png in out_dir."""
    out_dir.mkdir(parents=True, exist_ok=True)
    report: dict[str, Any] = {"board": "simulated (simavr)" if board is not None else link.port_path}
    progress("handshake")
    report["handshake"] = check_handshake(link)
    report["steps"] = []
    for stepped in range(3):
        progress(f"step response, chamber {stepped}")
        report["steps"].append(check_step(link, stepped, target_kpa))
    report["faults"] = []
    for fault, chamber in FAULT_CHECKS:
        progress(f"fault: {fault}")
        report["faults"].append(check_fault(link, board, fault, chamber))
    progress("line noise")
    report["line_noise"] = check_line_noise(link, board)
    progress("watchdog")
    report["watchdog"] = check_watchdog(link, board)
    if board is not None:
        report["cycles"] = board.cycle_stats()
    plot_steps(report["steps"], out_dir / "steps.png", board=report["board"])
    (out_dir / "report.json").write_text(json.dumps(report, indent=1))
    (out_dir / "report.md").write_text(format_report(report))
    return report


def _fmt(value: object, digits: int = 3) -> str:
    return "n/a" if value is None else f"{value:.{digits}g}" if isinstance(value, float) else str(value)


def format_report(report: dict[str, Any]) -> str:
    """The short Markdown report."""
    lines = [f"# HIL bench report: {board_description(report['board'])}", ""]
    h = report["handshake"]
    lines += [
        f"Handshake: {'PASS' if h['passed'] else 'FAIL'}; firmware {h['firmware_version']} on {h['board']}, "
        f"protocol v{h['protocol_version']} ({h['spec_hash']}), reset cause {h['reset_cause']}.",
        "",
    ]
    adc_count_kpa = report["steps"][0]["adc_count_kpa"] if report["steps"] else None
    lines += [
        "## Step responses (steps.png)",
        "",
        f"Step 0 -> target on one chamber at a time. Rise: 10 % to 90 % of the target. Settling: from then on "
        f"inside target ±{100 * SETTLING_BAND:g} %, judged on a {1e3 * SETTLING_SMOOTHING_S:g} ms moving average. "
        f"Thresholds: settling < {STEP_SETTLING_LIMIT_S:g} s, overshoot < {STEP_OVERSHOOT_LIMIT_PCT:g} %, "
        f"steady-state error < one ADC count ({_fmt(adc_count_kpa)} kPa).",
        "",
        "| chamber | target kPa | rise s | overshoot % | settling s | steady-state error kPa | thresholds |",
        "|---|---|---|---|---|---|---|",
    ]
    for s in report["steps"]:
        lines.append(
            f"| {s['chamber']} | {s['target_kpa']} | {_fmt(s['rise_time_s'])} | {_fmt(s['overshoot_pct'])} | "
            f"{_fmt(s['settling_time_s'])} | {_fmt(s['steady_state_error_kpa'])} | "
            f"{'met' if step_within_thresholds(s) else 'NOT met'} |"
        )
    lines += ["", "## Faults", "", "| fault | latched | stop time s | limit s | result |", "|---|---|---|---|---|"]
    for f in report["faults"]:
        if "skipped" in f:
            lines.append(f"| {f['fault']} | | | | skipped: {f['skipped']} |")
            continue
        if f["fault"] == "mild_leak":
            latched = f["latched"] or (
                f"none in {_fmt(f['watched_s'])} s: held {f['held_kpa']:.2f} kPa at drive "
                f"{f['drive_level']:.2f} (was {f['drive_level_before']:.2f})"
            )
            lines.append(f"| mild_leak | {latched} | | | {'PASS' if f['passed'] else 'FAIL'} |")
            continue
        lines.append(
            f"| {f['fault']} | {f['latched']} | {_fmt(f.get('stop_time_s'))} | {_fmt(f.get('limit_s'))} | "
            f"{'PASS' if f['passed'] else 'FAIL'} |"
        )
    n = report["line_noise"]
    lines += ["", "## Line noise", ""]
    lines.append(
        f"skipped: {n['skipped']}"
        if "skipped" in n
        else f"{'PASS' if n['passed'] else 'FAIL'}: {n['commands']} commands, {n['retransmissions']} retransmissions, "
        f"{n['board_frames_dropped']} frames dropped by the board, {n['host_frames_dropped']} by the host, "
        f"foreign setpoints applied: {n['foreign_setpoints_applied'] or 'none'}."
    )
    w = report["watchdog"]
    lines += [
        "",
        "## Watchdog",
        "",
        f"{'PASS' if w['passed'] else 'FAIL'}: reset cause {w['reset_cause']}, "
        f"WATCHDOG_RESET latched: {w['watchdog_fault_latched']}.",
    ]
    if "cycles" in report:
        c = report["cycles"]
        lines += [
            "",
            "## CPU (simavr cycle counts)",
            "",
            f"control tick: mean {_fmt(c['control_tick_cycles_mean'], 5)}, max {_fmt(c['control_tick_cycles_max'])} "
            f"cycles; telemetry frame: mean {_fmt(c['telemetry_frame_cycles_mean'], 5)}, max "
            f"{_fmt(c['telemetry_frame_cycles_max'])} cycles; CPU use {_fmt(100 * (c['cpu_use_fraction'] or 0))} %.",
        ]
    return "\n".join(lines) + "\n"


def measure_cycles(link: BoardLink, board: SimulatedBoard | None, duration_s: float, telemetry_period_ms: int,
                   kpa: float) -> dict[str, Any]:
    """Cycle counts with all three chambers regulating at ``kpa`` and telemetry every telemetry_period_ms.

    The counters are reset once the pressures have settled (2 s), then read after duration_s of board time.
    """
    if board is None:
        raise BenchError("cycle counts need the simulator (--sim)")
    start_session(link, telemetry_period_ms=telemetry_period_ms)
    set_setpoints(link, [int(kpa * 1e3)] * 3)
    wait_board_time(link, 2.0)
    board.cycle_stats(reset=True)
    wait_board_time(link, duration_s)
    stats = board.cycle_stats()
    link.command("VENT")
    frequency = stats["frequency_hz"]
    elapsed_s = stats["elapsed_cycles"] / frequency
    return {
        "elapsed_s": elapsed_s,
        "control_tick_hz": stats["control_ticks"] / elapsed_s,
        "control_tick_cycles_mean": stats["control_tick_cycles_mean"],
        "control_tick_cycles_max": stats["control_tick_cycles_max"],
        "control_tick_us_max": stats["control_tick_cycles_max"] / frequency * 1e6,
        "telemetry_hz": stats["telemetry_frames"] / elapsed_s,
        "telemetry_frame_cycles_mean": stats["telemetry_frame_cycles_mean"],
        "telemetry_frame_cycles_max": stats["telemetry_frame_cycles_max"],
        "cpu_use_fraction": stats["cpu_use_fraction"],
        "control_cpu_fraction": stats["regions"]["control_tick"]["total_cycles"] / stats["elapsed_cycles"],
        "regions": stats["regions"],
    }
