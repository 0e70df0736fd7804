"""The bench against the real firmware image running in simavr (the plant in the loop, the UART on a pty).

One simulated board serves the module; each check leaves it vented with no fault latched. The simulator is
asked for 2x real time; on a loaded machine it runs slower, which the checks tolerate because they wait on
the board's clock (telemetry time) rather than the host's.
"""

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import serial

from phantom import PhantomError
from phantom.hil import bench
from phantom.hil.link import BoardLink
from phantom.hil.sim import SimulatedBoard
from phantom.host.processes import child_pids
from phantom.protocol.messages import CONSTANTS
from phantom.protocol.sensor import ADC_COUNT_KPA

pytestmark = [pytest.mark.sim, pytest.mark.timeout(240)]

SPEED = 2.0


@pytest.fixture(scope="module")
def board():
    with SimulatedBoard(speed=SPEED, seed=1) as simulated:
        yield simulated


@pytest.fixture(scope="module")
def link(board):
    with BoardLink(board.port, time_scale=SPEED) as session:
        yield session


#: How far a blower stuck at full drive takes the true pressure past the 4 kPa limit before the averaged reading
#: latches it (measured: 0.20 kPa): a bound, with a margin of one ADC count.
STUCK_BLOWER_LAG_KPA = 0.2 + ADC_COUNT_KPA


def test_inject_refuses_bad_faults(board):
    with pytest.raises(PhantomError, match="unknown fault 'fire'"):
        board.inject("fire")
    with pytest.raises(PhantomError, match="needs chamber=0, 1 or 2"):
        board.inject("leak")
    with pytest.raises(PhantomError, match="needs chamber=0, 1 or 2"):
        board.inject("sensor_cut", chamber=3)
    with pytest.raises(PhantomError, match=r"level must be in \[0, 1\]"):
        board.inject("stuck_blower", chamber=0, level=2.0)
    with pytest.raises(PhantomError, match="whole board"):
        board.inject("line_noise", chamber=1)
    with pytest.raises(PhantomError, match=r"volts must be in \[2, 5.5\]"):
        board.inject("supply", volts=12.0)
    with pytest.raises(PhantomError, match="takes"):
        board.inject("leak", chamber=0, size=3)


def test_handshake_identifies_the_board_and_refuses_a_foreign_spec(link):
    result = bench.check_handshake(link)
    assert result["passed"] and result["mismatched_hello_refused"]
    assert result["board"] == "UNO" and result["chamber_count"] == 3
    assert result["reset_cause"] == "POWER_ON"


def test_step_reaches_the_setpoint_in_telemetry_and_in_the_plant(board, link):
    """The firmware's measured pressure settles on the setpoint (within one ADC count), and so does the plant's
    true pressure: after ZERO_SENSORS removes the sensor offset (60 Pa on chamber 1), the true pressure differs
    from the setpoint by the steady-state error plus sensor noise averaged over the firmware's samples, well
    under two counts."""
    result = bench.check_step(link, 1, 2.0, duration_s=2.5)
    truth_kpa = board.plant_state()["pressures_pa"][1] / 1e3
    assert abs(result["steady_state_error_kpa"]) < ADC_COUNT_KPA
    assert result["rise_time_s"] is not None and result["rise_time_s"] < 1.0
    assert result["overshoot_pct"] < 10
    assert result["max_drive_level"] == pytest.approx(1.0, abs=0.01), "a 2 kPa step saturates the blower first"
    # the state was read after VENT was sent, so allow the first milliseconds of deflation (< 20 Pa)
    assert truth_kpa == pytest.approx(2.0, abs=2 * ADC_COUNT_KPA)
    # the FEM couples the chambers by about 1 % of the diagonal compliance: the idle chambers (blowers off) move
    # by under 10 Pa, inside the sensor noise, so their readings stay within two ADC counts of zero
    assert abs(result["other_chambers_max_kpa"]) < 2 * ADC_COUNT_KPA


@pytest.mark.parametrize(
    ("fault", "chamber"), [("sensor_cut", 1), ("tube_off", 0), ("stuck_blower", 0), ("silent_host", None)]
)
def test_fault_trips_the_latch_and_stops_the_blowers_in_time(board, link, fault, chamber):
    result = bench.check_fault(link, board, fault, chamber)
    assert result["latched"] == result["expected"], result
    assert result["stop_time_s"] is not None and 0 <= result["stop_time_s"] <= result["limit_s"], result
    assert result["passed"], result
    if chamber is not None:
        # The true pressure stays near the limit it latched on (default 4 kPa). Two regimes: before the board has
        # measured its own zero at start-up the over-pressure ceiling is taken from the lowest zero the datasheet
        # allows and trips first (a stuck blower latched at 3.5 kPa, the true peak within a count of it); once it
        # has, the 4 kPa limit trips on the averaged reading, which lags a blower at full drive (about 2.7 kPa/s):
        # a clean-clone run latched there with the true pressure at 4.20 kPa. Which regime a run meets depends
        # on how long the board sat still after its reset, so the bound is the later one's.
        assert max(result["peak_true_kpa"]) <= 4.0 + STUCK_BLOWER_LAG_KPA, result
    state = board.plant_state()
    assert state["drive_levels"] == [0, 0, 0], "the bench leaves the board vented"


def test_severe_leak_latches_only_after_the_leak_time_limit(board, link):
    """The blower at full drive cannot reach the setpoint: LEAK_n latches, but not before the firmware's 2 s at
    the ceiling have passed from the step, and its FAULT frame shows the chamber far below its setpoint and the
    others holding."""
    result = bench.check_fault(link, board, "leak", 1)
    assert result["latched"] == "LEAK_1", result
    assert bench.LEAK_TIME_S <= result["stop_time_s"] <= result["limit_s"], result
    assert result["passed"], result
    at_latch = result["pressures_kpa_at_latch"]
    assert at_latch[1] < 1.5 - bench.LEAK_MIN_ERROR_KPA
    assert at_latch[0] == pytest.approx(1.5, abs=0.15) and at_latch[2] == pytest.approx(1.5, abs=0.15)
    assert board.plant_state()["drive_levels"] == [0, 0, 0], "the bench leaves the board vented"


def test_mild_leak_is_compensated_without_a_latch(board, link):
    result = bench.check_fault(link, board, "mild_leak", 2)
    assert result["latched"] is None, result
    assert result["watched_s"] > bench.LEAK_TIME_S
    assert result["held_kpa"] == pytest.approx(1.5, abs=0.1)
    # holding against the leak takes far more than the 0.2 a tight chamber needs at 1.5 kPa, but not full drive
    assert result["drive_level_before"] < 0.45 and 0.6 < result["drive_level"] < 1.0, result
    assert result["passed"]


def test_normal_step_to_3kpa_does_not_trip_the_leak_fault(link):
    """The blower sits at full drive while the chamber rises: for well under the leak time limit (measured
    from the board's own telemetry: drive at 1.0 and more than 0.2 kPa below the target), and nothing latches."""
    result = bench.check_step(link, 0, 3.0, duration_s=2.5)
    assert result["fault_flags"] == 0, result["fault_flags"]
    trace = result["trace"]
    starved = (np.array(trace["drive_level"]) >= 1.0) & (
        3.0 - np.array(trace["pressure_kpa"]) > bench.LEAK_MIN_ERROR_KPA
    )
    runs = np.diff(np.flatnonzero(np.diff(np.concatenate(([0], starved.astype(int), [0])))))[::2]
    longest_s = runs.max(initial=0) * np.median(np.diff(trace["time_s"]))
    assert 0.3 < longest_s < 0.6 * bench.LEAK_TIME_S, longest_s
    assert abs(result["steady_state_error_kpa"]) < ADC_COUNT_KPA


def test_link_survives_line_noise(board, link):
    result = bench.check_line_noise(link, board, commands=20, flip_probability=0.01, drop_probability=0.01)
    assert result["foreign_setpoints_applied"] == []
    assert result["board_frames_dropped"] > 0 and result["retransmissions"] > 0, "the noise was not there"
    assert result["passed"]
    stats = board.cycle_stats()["serial"]
    assert stats["bytes_flipped"] > 0 and stats["bytes_dropped"] > 0


def test_watchdog_reset_is_reported(board, link):
    result = bench.check_watchdog(link, board)
    assert result["reset_cause"] == "WATCHDOG"
    assert result["watchdog_fault_latched"]
    assert result["resets_seen_by_simulator"] == 1


def test_cycle_counts_follow_the_firmware_rates(board, link):
    """The spec's tick rate and 50 Hz telemetry are the firmware's design; the counts must match them to 1 %."""
    result = bench.measure_cycles(link, board, duration_s=2.0, telemetry_period_ms=20, kpa=1.0)
    assert result["control_tick_hz"] == pytest.approx(CONSTANTS["TICK_HZ"], rel=0.01)
    assert result["telemetry_hz"] == pytest.approx(50, rel=0.01)
    tick_budget_cycles = 16_000_000 // CONSTANTS["TICK_HZ"]
    assert 0 < result["control_tick_cycles_mean"] <= result["control_tick_cycles_max"] < tick_budget_cycles
    assert result["telemetry_frame_cycles_mean"] > 1500
    assert result["control_cpu_fraction"] < result["cpu_use_fraction"] < 1


def test_unplug_and_replug_like_a_usb_cable():
    """Unplug: the port vanishes, an open link sees the device go, the blowers lose power. Replug: the same
    path comes back and the board has restarted from a power-on reset. (A board of its own: a second reader
    on the module's port would steal bytes from the module's link.)"""
    with SimulatedBoard(speed=SPEED, seed=2) as board:
        check_unplug_and_replug(board)


def check_unplug_and_replug(board):
    path = board.port
    with BoardLink(path, time_scale=SPEED) as session:
        bench.start_session(session)
        session.command("SET_SETPOINTS", {"setpoint_pa": [1000, 0, 0]})
        bench.wait_board_time(session, 0.3)
        board.unplug()
        assert not os.path.exists(path)
        assert session.wait_for(lambda m: False, 0.5) is None and session.disconnected
    state = board.plant_state()
    assert state["drive_levels"] == [0, 0, 0] and not state["powered"]
    with pytest.raises(serial.SerialException):
        serial.Serial(path)
    board.replug()
    assert os.path.islink(path)
    with BoardLink(path, time_scale=SPEED) as session:
        assert session.hello().fields["reset_cause"] == 1  # POWER_ON
        bench.vent_and_wait(session)


def test_cli_step_prints_the_metrics_as_json():
    phantom = Path(sys.executable).with_name("phantom")
    result = subprocess.run(
        [str(phantom), "hil", "step", "--sim", "--sim-speed", str(SPEED), "--chamber", "2", "--kpa", "1.5",
         "--duration-s", "2", "--json"],
        capture_output=True, text=True, timeout=120,
    )
    assert result.returncode == 0, result.stderr
    metrics = json.loads(result.stdout)
    for key in ("rise_time_s", "overshoot_pct", "settling_time_s", "steady_state_error_kpa"):
        assert key in metrics
    assert metrics["chamber"] == 2 and abs(metrics["steady_state_error_kpa"]) < ADC_COUNT_KPA


def test_mega_image_runs_with_its_own_pins_and_vectors():
    """The second target: the ATmega2560 image, whose chamber 2 blower is OC2B on D9 and whose interrupt vectors
    are numbered differently; its handshake names the board and chamber 2 regulates."""
    from phantom.hil.firmware import default_elf, ensure_firmware

    ensure_firmware()
    mega = default_elf().parents[1] / "mega" / "phantom.elf"
    assert mega.is_file(), "`make -C firmware` should build the Mega image beside the Uno one"
    with SimulatedBoard(elf=mega, speed=SPEED) as board, BoardLink(board.port, time_scale=SPEED) as session:
        assert bench.check_handshake(session)["board"] == "MEGA2560"
        result = bench.check_step(session, 2, 1.5, duration_s=1.5)
        assert not result["faults"], f"a fault latched during the step: {result['faults']}"
        assert abs(result["steady_state_error_kpa"]) < ADC_COUNT_KPA
        stats = board.cycle_stats()
        assert stats["control_ticks"] > 0 and stats["regions"]["adc_isr"]["calls"] > 0


def test_a_zero_refused_for_a_latched_fault_names_the_fault(link):
    """A silent host latches DEAD_HOST; the zero the bench then asks for is refused, and the error names the fault
    (a lab reading "FAULT_LATCHED" alone cannot tell a host too slow from a tube off)."""
    bench.start_session(link)
    bench.vent_and_wait(link)
    link.keepalive(False)
    bench.wait_board_time(link, 2 * bench.host_deadline_s(link), until=lambda fields: fields["fault_flags"] != 0)
    with pytest.raises(bench.BenchError, match=r"FAULT_LATCHED \(DEAD_HOST\)"):
        bench.zero_sensors(link)
    bench.start_session(link)  # keepalive on, the latch cleared: as the other tests expect the board
    assert bench.latest_telemetry(link)["fault_flags"] == 0


def test_bench_against_a_port_runs_what_a_real_board_allows():
    """With only a port (as for /dev/ttyACM0), the injected faults are skipped with the reason, and the silent
    host's stop time comes from the board's own clock (last PONG to the FAULT frame)."""
    with SimulatedBoard(speed=SPEED, seed=3) as board, BoardLink(board.port, time_scale=SPEED) as session:
        assert bench.check_fault(session, None, "sensor_cut", 1)["skipped"].startswith("needs --sim")
        assert "skipped" in bench.check_line_noise(session, None)
        silent = bench.check_fault(session, None, "silent_host")
        assert silent["latched"] == "DEAD_HOST"
        # the board's deadline gives the host the firmware's 500 ms of wall clock at any speed (at twice real time
        # its 500 ms of board time were 250 ms of wall clock, which a test's link thread missed beside busy cores)
        assert bench.host_deadline_s(session) == pytest.approx(SPEED * bench.HOST_DEADLINE_MS / 1e3)
        assert bench.host_deadline_s(session) < silent["stop_time_s"] <= silent["limit_s"], silent
        assert silent["passed"]


def test_simulated_time_is_paced_to_the_wall_clock():
    """At speed 0.5 (which this machine sustains) one wall second is half a simulated second, to within the
    command round trips and one 1 ms service period; time the simulator could not keep up with is reported in
    lost_s, never caught up later."""
    import time

    with SimulatedBoard(speed=0.5) as board:
        # each reading's wall time is bracketed: the harness read it somewhere between asking and the answer, and
        # on a loaded machine this process can stall there too (timed from the answers alone, a loaded make test
        # once read 0.534 s against 0.500 +- 0.03: a stall around a reading, given up as lost by the harness, is
        # likely, the figures of that run were not kept)
        asked_first = time.monotonic()
        first, answered_first = board.plant_state(), time.monotonic()
        time.sleep(1.0)
        asked_second = time.monotonic()
        second, answered_second = board.plant_state(), time.monotonic()
    simulated_s = second["time_s"] - first["time_s"]
    lost_s = second["lost_s"] - first["lost_s"]
    shortest_s, longest_s = asked_second - answered_first, answered_second - asked_first
    assert simulated_s <= 0.5 * longest_s + 0.01
    assert 0.5 * shortest_s - 0.03 <= simulated_s + 0.5 * lost_s <= 0.5 * longest_s + 0.03, (
        simulated_s, lost_s, shortest_s, longest_s)


def _harness_pids() -> set[int]:
    """This process's phantom-hil children."""
    pids = set()
    for child in child_pids():
        if Path(f"/proc/{child}/comm").read_text().strip() == "phantom-hil":
            pids.add(child)
    return pids


def test_a_paced_harness_asks_for_a_real_time_priority_below_the_links_and_gives_it_up_when_it_cannot_keep_up():
    """The simulated board stands in for hardware, which never waits for a core: a paced harness runs at SCHED_FIFO
    (HARNESS_RT_PRIORITY, below the board link's), where it may (root, CAP_SYS_NICE); an unpaced one never does; one
    that cannot keep up at its speed (it sleeps under a tenth of 0.2 s) gives the priority up after that window,
    rather than keep a core from every other process (the tests beside it in make test's [sim] run among them).
    Where the right is missing, it says why."""
    import time

    from phantom.hil.sim import HARNESS_RT_PRIORITY
    from phantom.host.link_process import LINK_RT_PRIORITY

    assert 0 < HARNESS_RT_PRIORITY < LINK_RT_PRIORITY
    effective = int(next(line for line in open("/proc/self/status") if line.startswith("CapEff:")).split()[1], 16)
    may = bool(effective >> 23 & 1)  # CAP_SYS_NICE (a container may run root without it)
    before = _harness_pids()
    with SimulatedBoard(speed=SPEED) as paced:
        (pid,) = _harness_pids() - before
        if may:
            assert paced.scheduling == f"SCHED_FIFO {HARNESS_RT_PRIORITY}"
            assert os.sched_getscheduler(pid) & ~os.SCHED_RESET_ON_FORK == os.SCHED_FIFO  # its children would not
            assert os.sched_getparam(pid).sched_priority == HARNESS_RT_PRIORITY
        else:
            assert paced.scheduling.startswith(f"normal (SCHED_FIFO {HARNESS_RT_PRIORITY} refused: "), paced.scheduling
        assert paced.plant_state()["scheduling"] == paced.scheduling
    with SimulatedBoard(speed=0) as unpaced:
        (pid,) = _harness_pids() - before
        assert unpaced.scheduling.startswith("normal") and os.sched_getscheduler(pid) == os.SCHED_OTHER
    if not may:
        return
    with SimulatedBoard(speed=100) as flat_out:  # it cannot run 100x real time: flat out it runs 7-20x
        ready = time.monotonic()  # its first window starts when it says it is ready
        (pid,) = _harness_pids() - before
        while (said := flat_out.plant_state()["scheduling"]) == f"SCHED_FIFO {HARNESS_RT_PRIORITY}":
            assert time.monotonic() < ready + 20, "a harness that cannot keep up kept its real-time priority"
            time.sleep(0.02)
        seen_s = time.monotonic() - ready
        assert said.startswith(f"normal (SCHED_FIFO {HARNESS_RT_PRIORITY} given up at board time ") and \
            "cannot keep up at speed 100" in said, said
        assert os.sched_getscheduler(pid) == os.SCHED_OTHER
        # after its first window of 0.2 s: a window of a second held a core for a second from the tests beside it
        assert seen_s < 0.7, (seen_s, said)


def simulator_steps_per_cycle(board: SimulatedBoard, link: BoardLink, board_s: float) -> float:
    """The harness's steps (instructions, or jumps to the next event while the core sleeps) per simulated cycle
    over ``board_s`` of board time: the simulator's work, counted, whatever the machine's load."""
    board.cycle_stats(reset=True)
    bench.wait_board_time(link, board_s)
    stats = board.cycle_stats()
    return stats["simulator_steps"] / stats["elapsed_cycles"]


def test_the_simulator_skips_the_sleeping_cycles_after_every_kind_of_start():
    """simavr polls a low INT0 or INT1 pin on every cycle, enabled or not, and turns that polling on again at every
    reset; the Uno's STEP0 and blower-2 outputs sit on those pins, low for minutes, and with it the simulator
    stepped through every cycle the firmware slept (0.87 simulated seconds per CPU second flat out, one board a
    whole core). The harness turns it off at each start: the steps stay near the firmware's busy fraction (about
    a fifth of the cycles, bench/README.md) after a power-on, under load on all three chambers (blower 2's PWM
    toggling its pin), after a watchdog reset and after a replug."""
    with SimulatedBoard(speed=SPEED, seed=3) as board:
        with BoardLink(board.port, time_scale=SPEED) as session:
            bench.start_session(session)
            assert simulator_steps_per_cycle(board, session, 0.5) < 0.4
            session.command("SET_SETPOINTS", {"setpoint_pa": [1000, 1000, 1000]})
            assert simulator_steps_per_cycle(board, session, 1.0) < 0.4
            assert bench.check_watchdog(session, board)["passed"]
            assert simulator_steps_per_cycle(board, session, 0.5) < 0.4
        board.unplug()
        board.replug()
        with BoardLink(board.port, time_scale=SPEED) as session:
            bench.start_session(session)
            assert simulator_steps_per_cycle(board, session, 0.5) < 0.4
