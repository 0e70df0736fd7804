"""The boot path of a real board in simavr: the stock bootloaders (Optiboot on the Uno, stk500v2 on the Mega)
flashed with the application, reset as a DTR pulse does; the reset cause; settings kept in EEPROM across a
reset; and the safety checks that need the whole board (a zero refused while a chamber deflates, a sensor tube
that comes off, the production image refusing TEST_HANG).

Every wait is on the simulator's clock (``plant_state()["time_s"]``) or the board's (telemetry), not the host's.
"""

import re
import time
from pathlib import Path

import numpy as np
import pytest

from phantom.hil import bench
from phantom.hil.firmware import default_elf
from phantom.hil.link import BoardLink
from phantom.hil.sim import SimulatedBoard
from phantom.protocol.codec import encode
from phantom.protocol.messages import BITS, CONSTANTS, ENUMS, PROTOCOL_VERSION, SPEC_HASH

pytestmark = [pytest.mark.sim, pytest.mark.timeout(240)]

SPEED = 2.0
CAUSES = {v: k for k, v in ENUMS["reset_cause"].items()}
STATUS = ENUMS["status"]
#: How long each stock bootloader keeps the application waiting after an external reset (board time, s):
#: Optiboot 4.4 waits for its 1 s watchdog, stk500v2 for its boot_timeout loop (about 0.8 s measured here).
#: This is the wait a host must leave after opening a port (the link drivers' boot delay) before it sends.
BOOTLOADER_WAIT_S = {"uno": 1.1, "mega": 1.0}


def elf_of(board_name: str, bench_build: bool = True):
    return default_elf().parents[1] / (f"{board_name}-bench" if bench_build else board_name) / "phantom.elf"


def wait_sim(board: SimulatedBoard, seconds: float, until=None) -> dict:
    """Poll the simulator until ``seconds`` of simulated time passed or ``until(state)`` holds; the last state."""
    state = board.plant_state()
    end_s = state["time_s"] + seconds
    while state["time_s"] < end_s and not (until and until(state)):
        time.sleep(0.02)
        state = board.plant_state()
    return state


def hello_after_boot(board: SimulatedBoard, board_name: str) -> dict:
    """What a host does once it has waited out the bootloader (the link's boot delay): HELLO; the reply."""
    wait_sim(board, BOOTLOADER_WAIT_S[board_name], lambda s: s["control_since_s"] is not None)
    with BoardLink(board.port, time_scale=SPEED) as link:
        return link.hello().fields


@pytest.mark.parametrize("board_name", ["uno", "mega"])
def test_stock_bootloader_keeps_the_blowers_off_until_the_control_loop_runs_and_the_handshake_follows(board_name):
    with SimulatedBoard(elf=elf_of(board_name), speed=SPEED, bootloader=True) as board:
        wait_sim(board, 0.2)
        reset_s = board.reset("external")
        state = wait_sim(board, 3.0, lambda s: s["control_since_s"] is not None)
        assert state["reset_s"] == pytest.approx(reset_s, abs=1e-3)
        boot_s = state["control_since_s"] - reset_s
        assert 0.5 < boot_s < 2.0, boot_s  # the bootloader's wait for an upload
        assert not state["driven_before_control"]
        # Meanwhile the pins were inputs: only the pull-downs of docs/hardware.md hold the drivers off.
        assert state["floating_before_control_s"] == pytest.approx(boot_s, abs=0.01)
        assert state["blower_pins"] == ["low", "low", "low"]
        reply = hello_after_boot(board, board_name)
        assert reply["board"] == ENUMS["board"]["UNO" if board_name == "uno" else "MEGA2560"]
        # The bootloader cleared MCUSR: the cause cannot be known, and the board says so.
        assert CAUSES[reply["reset_cause"]] == "UNKNOWN"


def test_stk500v2_never_starts_the_application_while_bytes_keep_arriving():
    """Why the host must wait out the bootloader after opening a port: a Mega whose host sends HELLO at once,
    and keeps retrying, stays in its bootloader (any byte puts stk500v2 into its programming loop, which it
    leaves only after F_CPU / 2 polls without a byte, a few seconds)."""
    with SimulatedBoard(elf=elf_of("mega"), speed=SPEED, bootloader=True) as board:
        wait_sim(board, 0.1)
        board.reset("external")
        hello = encode("HELLO", 0, {"protocol_version": PROTOCOL_VERSION, "spec_hash": SPEC_HASH})
        with open(board.port, "wb", buffering=0) as port:
            state = board.plant_state()
            end_s = state["time_s"] + 3.0
            while state["time_s"] < end_s:
                port.write(hello)
                time.sleep(0.05 / SPEED)
                state = board.plant_state()
            assert state["control_since_s"] is None
            quiet_s = state["time_s"]
        state = wait_sim(board, 10.0, lambda s: s["control_since_s"] is not None)
        assert state["control_since_s"] is not None  # silence lets it time out and start the application
        print(f"stk500v2 started the application {state['control_since_s'] - quiet_s:.2f} s after the bytes stopped")


@pytest.mark.parametrize("bootloader", [False, True], ids=["no-bootloader", "optiboot"])
def test_reset_cause_is_right_where_it_can_be_known_and_unknown_where_it_cannot(bootloader):
    expected = {
        # power-on, external (DTR), watchdog
        False: ("POWER_ON", "EXTERNAL", "WATCHDOG"),
        # Optiboot 4.4 clears MCUSR; only the watchdog interrupt's mark in RAM survives it
        True: ("UNKNOWN", "UNKNOWN", "WATCHDOG"),
    }[bootloader]
    with SimulatedBoard(speed=SPEED, bootloader=bootloader) as board:
        seen = [CAUSES[hello_after_boot(board, "uno")["reset_cause"]]]
        board.reset("external")
        seen.append(CAUSES[hello_after_boot(board, "uno")["reset_cause"]])
        with BoardLink(board.port, time_scale=SPEED) as link:
            result = bench.check_watchdog(link, board)
        seen.append(result["reset_cause"])
        assert tuple(seen) == expected
        assert result["watchdog_fault_latched"]


def test_settings_survive_a_reset_in_eeprom():
    with SimulatedBoard(speed=SPEED, seed=3) as board:
        with BoardLink(board.port, time_scale=SPEED) as link:
            bench.start_session(link)
            start = link.mark()
            link.hello()
            info = link.wait_for(lambda m: m.name == "BOARD_INFO", 1.0, start).message.fields
            assert info["config_source"] == ENUMS["config_source"]["DEFAULTS"]
            link.command("SET_PID", {"chamber": 1, "kp_per_kpa": 3.0, "ki_per_kpa_s": 12.0, "kd_s_per_kpa": 0.0,
                                     "max_pressure_pa": 3500, "max_drive": 60000})
            bench.zero_sensors(link)
            start = link.mark()
            link.hello()
            zeroed = link.wait_for(lambda m: m.name == "BOARD_INFO", 1.0, start).message.fields
            assert zeroed["zero_source"] == [ENUMS["zero_source"]["HOST"]] * 3
            bench.wait_board_time(link, 0.5)  # 57 bytes at 3.4 ms each
        for cause in ("external", "power"):
            board.reset(cause)
            with BoardLink(board.port, time_scale=SPEED) as link:
                start = link.mark()
                link.hello()
                info = link.wait_for(lambda m: m.name == "BOARD_INFO", 1.0, start).message.fields
            assert info["config_source"] == ENUMS["config_source"]["EEPROM"], cause
            assert info["zero_source"] == [ENUMS["zero_source"]["STORED"]] * 3
            assert info["zero_offset_pa"] == zeroed["zero_offset_pa"]
            # the plant's offsets (hil/plant.toml: 60, -40, 30 Pa) within two ADC counts
            assert info["zero_offset_pa"] == pytest.approx([60, -40, 30], abs=110)


def test_production_image_refuses_test_hang():
    with SimulatedBoard(elf=elf_of("uno", bench_build=False), speed=SPEED) as board:
        with BoardLink(board.port, time_scale=SPEED) as link:
            bench.start_session(link)
            answer = link.command("TEST_HANG", {"magic": CONSTANTS["TEST_HANG_MAGIC"]}, accept_nack=True)
            assert answer.name == "NACK" and answer.fields["status"] == STATUS["BAD_MAGIC"]
            assert bench.latest_telemetry(link)["fault_flags"] == 0


@pytest.fixture(scope="module")
def board():
    with SimulatedBoard(speed=SPEED, seed=4) as simulated:
        yield simulated


@pytest.fixture(scope="module")
def link(board):
    with BoardLink(board.port, time_scale=SPEED) as session:
        bench.start_session(session)
        yield session


def test_zero_right_after_vent_at_2_4kpa_is_refused_until_the_chamber_has_deflated(board, link):
    bench.set_setpoints(link, [2400, 0, 0])
    bench.wait_board_time(link, 2.0)
    assert board.plant_state()["pressures_pa"][0] == pytest.approx(2400, abs=100)
    link.command("VENT")
    answer = link.command("ZERO_SENSORS", timeout_s=2.0, attempts=1, accept_nack=True)
    assert answer.name == "NACK" and answer.fields["status"] == STATUS["NOT_SETTLED"]
    bench.zero_sensors(link)
    true_pa = board.plant_state()["pressures_pa"][0]
    assert true_pa < 150  # what was left in the chamber when the zero was taken


def test_tube_off_latches_within_half_a_second_under_the_ceiling(board, link):
    bench.vent_and_wait(link)
    for chamber in (0, 1):
        board.inject("tube_off", chamber=chamber)
        start = link.mark()
        setpoints = [0, 0, 0]
        setpoints[chamber] = 2000
        bench.set_setpoints(link, setpoints)
        got = bench.wait_on_board_clock(link, lambda m: m.name == "FAULT", 1.0, start)
        true_pa = board.plant_state()["pressures_pa"][chamber]
        assert got is not None
        sent = next(r for r in link.received[start:] if r.message.name == "TELEMETRY"
                    and r.message.fields["setpoint_pa"][chamber] == 2000)
        latch_s = (got.message.fields["time_ms"] - sent.message.fields["time_ms"]) / 1e3
        assert got.message.fields["fault_bit"] == BITS["fault"][f"IMPLAUSIBLE_{chamber}"]
        assert latch_s < 0.5
        assert true_pa < CONSTANTS["PRESSURE_CEILING_PA"]
        print(f"tube off, chamber {chamber}: IMPLAUSIBLE after {latch_s:.3f} s, true {true_pa:.0f} Pa")
        board.inject("clear")
        bench.vent_and_wait(link)
        link.command("CLEAR_FAULT")


def test_over_pressure_latches_at_or_under_the_ceiling_after_a_host_zero(tmp_path):
    """The host raises chamber 0's limit as far as it can (clamped to the ceiling) and zeroes the sensors; a
    blower stuck at a level whose equilibrium lies just above the ceiling (on a plant with a tight back-leak)
    then creeps past it: the latch comes at a true pressure at or under the ceiling."""
    text = (Path(__file__).parents[1] / "hil" / "plant.toml").read_text()
    tight = re.sub(r"(?m)^back_leak_ml_per_s_per_kpa = .*$", "back_leak_ml_per_s_per_kpa = [0.3, 0.3, 0.3]", text)
    plant_file = tmp_path / "tight.toml"
    plant_file.write_text(tight)
    with SimulatedBoard(plant=plant_file, speed=SPEED, seed=5) as board:
        with BoardLink(board.port, time_scale=SPEED) as link:
            bench.start_session(link)
            answer = link.command("SET_PID", {"chamber": 0, "kp_per_kpa": 4.0, "ki_per_kpa_s": 15.0,
                                              "kd_s_per_kpa": 0.0, "max_pressure_pa": 30000, "max_drive": 65535})
            assert answer.fields["status"] == STATUS["CLAMPED"]
            bench.zero_sensors(link)
            start = link.mark()
            board.inject("stuck_blower", chamber=0, level=0.6)  # equilibrium about 7.7 kPa on this plant
            # (simulated time, true pressure) until the FAULT arrives, about 6 s of board time; given up after 30 s
            # (a cap on samples was reached first on a loaded machine: they come faster than the board's time)
            trace = []
            while ((got := link.wait_for(lambda m: m.name == "FAULT", 0.01, start)) is None
                   and (len(trace) < 2 or trace[-1][0] - trace[0][0] < 30.0)):
                state = board.plant_state()
                trace.append((state["time_s"], state["pressures_pa"][0]))
            board.inject("clear")
            assert got is not None and got.message.fields["fault_bit"] == BITS["fault"]["OVERPRESSURE_0"]
            # board time counts from the first control tick
            state = board.plant_state()
            trip_s = state["control_since_s"] + got.message.fields["time_ms"] / 1e3 - 0.002
            times, pressures = np.array(trace).T
            true_pa = float(np.interp(trip_s, times, pressures))
            print(f"over-pressure latched at a true {true_pa:.0f} Pa (read {got.message.fields['pressure_pa'][0]} Pa) "
                  f"{trip_s - times[0]:.1f} s of board time after the blower stuck ({len(trace)} samples)")
            assert times[0] < trip_s < times[-1] + 0.05
            assert true_pa <= CONSTANTS["PRESSURE_CEILING_PA"] + 60  # one ADC count
            assert true_pa > CONSTANTS["PRESSURE_CEILING_PA"] - 300


def test_supply_is_measured_on_the_1v1_reference_and_a_sag_latches_supply(board, link):
    bench.vent_and_wait(link)
    start = link.mark()
    link.hello()
    info = link.wait_for(lambda m: m.name == "BOARD_INFO", 1.0, start).message.fields
    assert info["supply_mv"] == pytest.approx(5000, abs=25)  # the plant's 5.0 V rail, to about 2 ADC counts
    start = link.mark()
    board.inject("supply", volts=4.0)
    got = bench.wait_on_board_clock(link, lambda m: m.name == "FAULT", 1.0, start)
    board.inject("clear")
    assert got is not None and got.message.fields["fault_bit"] == BITS["fault"]["SUPPLY"]
    answer = link.command("CLEAR_FAULT", accept_nack=True)
    if answer.name == "NACK":  # the rail's cause was still present at that tick: once more
        bench.wait_board_time(link, 0.1)
        link.command("CLEAR_FAULT")
    assert bench.latest_telemetry(link)["fault_flags"] == 0
