"""The HIL plant: its parameter file, and the C integrator of the harness against independent solutions."""

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from phantom import PhantomError
from phantom.hil.harness import HarnessError, HarnessProcess
from phantom.hil.plant import DEFAULT_PLANT_PATH, PlantError, load_plant

pytestmark = pytest.mark.timeout(120)


@pytest.fixture
def plant_file(tmp_path):
    """A copy of the shipped plant file that a test may edit."""

    def write(old: str | None = None, new: str | None = None):
        text = DEFAULT_PLANT_PATH.read_text()
        if old is not None:
            assert old in text
            text = text.replace(old, new)
        path = tmp_path / "plant.toml"
        path.write_text(text)
        return path

    return write


def plant_only(plant, seed=0) -> HarnessProcess:
    return HarnessProcess(["--no-mcu", "--seed", str(seed), *plant.harness_arguments()])


def test_shipped_plant_is_converted_to_si():
    plant = load_plant()
    assert plant.atmospheric_pressure_pa == pytest.approx(101325.0)
    assert plant.rest_volume_m3 == pytest.approx([4e-6] * 3)
    assert plant.compliance_m3_per_pa[0, 0] == pytest.approx(2.75e-9)
    assert plant.free_flow_m3_per_s[1] == pytest.approx(800e-6 / 60)
    assert plant.leak_conductance_m3_per_s_per_pa[2] == pytest.approx(1.8e-9)
    assert plant.sensor_gain_per_pa == pytest.approx(1.8e-5)


@pytest.mark.parametrize(
    ("old", "new", "message"),
    [
        ("rest_volume_ml = [4.0, 4.0, 4.0]", "rest_volume_ml = [4.0, -1.0, 4.0]", "rest_volume_ml: must be > 0"),
        ("rest_volume_ml = [4.0, 4.0, 4.0]", "rest_volume_ml = [4.0, 4.0]", "list of 3 numbers"),
        ("[2.75, -0.6, -0.6],\n  [-0.6, 2.75", "[2.75, -0.5, -0.6],\n  [-0.6, 2.75", "must be symmetric"),
        (
            "[2.75, -0.6, -0.6],\n  [-0.6, 2.75, -0.6],\n  [-0.6, -0.6, 2.75]",
            "[2.75, -2.0, -2.0],\n  [-2.0, 2.75, -2.0],\n  [-2.0, -2.0, 2.75]",
            "positive definite",
        ),
        ("supply_v = 5.0", 'supply_v = "five"', "supply_v: expected a finite number"),
        ("step_us = 100.0", "step_us = 5000.0", "too coarse"),
        ("[integration]", "[integrator]", "missing table [integration]"),
        ("noise_mv = 1.5", "", "missing key 'noise_mv'"),
        ("[gas]", "[gas", "not valid TOML"),
    ],
)
def test_bad_plant_files_are_refused_with_the_key_named(plant_file, old, new, message):
    with pytest.raises(PlantError, match=message.replace("[", r"\[").replace("]", r"\]")):
        load_plant(plant_file(old, new))


def test_missing_plant_file_is_a_user_error(tmp_path):
    with pytest.raises(PhantomError, match="does not exist"):
        load_plant(tmp_path / "nope.toml")


def test_harness_refuses_unknown_and_missing_parameters():
    arguments = load_plant().harness_arguments()
    with pytest.raises(HarnessError, match="unknown plant parameter .*volume_litres"):
        HarnessProcess(["--no-mcu", *arguments, "--param", "volume_litres=1"])
    step = arguments.index(next(a for a in arguments if a.startswith("step_s=")))
    without_step = arguments[: step - 1] + arguments[step + 1 :]
    with pytest.raises(HarnessError, match="step_s is missing"):
        HarnessProcess(["--no-mcu", *without_step])


def test_harness_refuses_bad_commands():
    harness = plant_only(load_plant())
    try:
        for bad in ("fly", "fault leak 5 1e-9", "fault stuck_blower 0 1.5", "drive 1 2", "advance -1"):
            with pytest.raises(HarnessError, match="refused"):
                harness.command(bad)
        assert harness.command("state")["time_s"] == 0.0
    finally:
        harness.close()


def test_driven_chamber_settles_at_the_analytic_equilibrium():
    """Steady state of Q_max u (1 - p/p_blocked) = G p, with the idle chambers back at 0 through their leak."""
    plant = load_plant()
    harness = plant_only(plant)
    try:
        drive = 0.4
        harness.command(f"drive 0 {drive} 0")
        state = harness.command("advance 30")
    finally:
        harness.close()
    q_max, p_blocked = plant.free_flow_m3_per_s[1], plant.blocked_pressure_pa[1]
    leak = plant.leak_conductance_m3_per_s_per_pa[1]
    expected_pa = q_max * drive / (q_max * drive / p_blocked + leak)
    # 30 s is 20 passive time constants (about 1.5 s): the remaining transient is far below 0.1 Pa.
    assert state["pressures_pa"][1] == pytest.approx(expected_pa, abs=0.1)
    assert state["pressures_pa"][0] == pytest.approx(0.0, abs=0.1)
    assert state["pressures_pa"][2] == pytest.approx(0.0, abs=0.1)
    volume_ml = 1e6 * (plant.rest_volume_m3[1] + plant.compliance_m3_per_pa[1, 1] * expected_pa)
    assert state["chamber_volumes_ml"][1] == pytest.approx(volume_ml, rel=1e-4)


def reference_rates(plant, drive):
    """dp/dt of the coupled isothermal chambers, written out from physics.md independently of plant.c."""

    def rates(_, p):
        inflow = np.maximum(plant.free_flow_m3_per_s * drive * (1 - p / plant.blocked_pressure_pa), 0)
        outflow = plant.leak_conductance_m3_per_s_per_pa * p
        volume = plant.rest_volume_m3 + plant.compliance_m3_per_pa @ p
        matrix = np.diag(volume) + (plant.atmospheric_pressure_pa + p)[:, None] * plant.compliance_m3_per_pa
        return np.linalg.solve(matrix, plant.atmospheric_pressure_pa * (inflow - outflow))

    return rates


def test_transient_matches_scipy_on_the_coupled_chambers():
    """The RK4 at a 100 us step against scipy's adaptive DOP853 at rtol 1e-10.

    The step is about 1e-4 of the fastest time constant (about 0.3 s), so RK4's global error is of order
    (1e-4)^4 relative: anything above 1e-3 Pa on a kPa-sized trajectory is a bug, not truncation.
    """
    plant = load_plant()
    drive = np.array([1.0, 0.3, 0.0])
    harness = plant_only(plant)
    try:
        harness.command("drive " + " ".join(map(str, drive)))
        states = [harness.command("advance 0.25") for _ in range(4)]
        harness.command("drive 0 0 0")
        states += [harness.command("advance 0.25") for _ in range(4)]
    finally:
        harness.close()
    first = solve_ivp(
        reference_rates(plant, drive), (0, 1.0), np.zeros(3), method="DOP853", rtol=1e-10, atol=1e-9, dense_output=True
    )
    second = solve_ivp(
        reference_rates(plant, np.zeros(3)),
        (1.0, 2.0),
        first.y[:, -1],
        method="DOP853",
        rtol=1e-10,
        atol=1e-9,
        dense_output=True,
    )
    for k, state in enumerate(states):
        expected = (first if k < 4 else second).sol(state["time_s"])
        assert state["pressures_pa"] == pytest.approx(expected, abs=1e-3)
    assert max(states[3]["pressures_pa"]) > 1500, "full drive should pass 1.5 kPa within 1 s on this plant"


def test_sensor_follows_the_mpxv7025g_transfer_function():
    """Vout = 5 V (0.018/kPa (p + offset) + 0.5) from the datasheet; a cut wire reads 0 V."""
    plant = load_plant()
    harness = plant_only(plant)
    try:
        harness.command("drive 0.5 0.5 0.5")
        state = harness.command("advance 2")
        harness.command("fault sensor_cut 2")
        cut = harness.command("advance 0.001")
    finally:
        harness.close()
    pressure_kpa = np.array(state["pressures_pa"]) / 1e3
    offset_kpa = np.array([0.06, -0.04, 0.03])
    expected_v = 5.0 * (0.018 * (pressure_kpa + offset_kpa) + 0.5)
    # The reported voltage is the noiseless one of the sensor's 1 ms lagged pressure; at 2 s the pressure still
    # rises at under 0.5 kPa/s, so the lag is under 0.5 Pa, i.e. 45 uV at 90 mV/kPa.
    assert state["sensor_voltages_v"] == pytest.approx(expected_v, abs=45e-6)
    assert cut["sensor_voltages_v"][2] == 0.0
    assert cut["sensor_voltages_v"][0] > 2.5
