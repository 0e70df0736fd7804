"""The HIL plant: its parameter file, and the C integrator of the harness against independent solutions."""

import dataclasses
import re
import tomllib

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from phantom import PhantomError
from phantom.cli.main import main
from phantom.hil.harness import HarnessError, HarnessProcess
from phantom.hil.plant import (
    CALIBRATED_SCENE_PATH,
    DEFAULT_PLANT_PATH,
    PlantError,
    blower_flow_m3_per_s,
    chambers_from_scene,
    load_plant,
    write_chambers,
)

pytestmark = pytest.mark.timeout(120)


@pytest.fixture
def plant_file(tmp_path):
    """A copy of the shipped plant file that a test may edit."""

    def write(pattern: str | None = None, new: str | None = None):
        """The shipped file with the one match of the regular expression ``pattern`` (a line) replaced."""
        text = DEFAULT_PLANT_PATH.read_text()
        if pattern is not None:
            text, count = re.subn(pattern, lambda _: new, text, flags=re.MULTILINE)
            assert count == 1, pattern
        path = tmp_path / "plant.toml"
        path.write_text(text)
        return path

    return write


def plant_only(plant, seed=0) -> HarnessProcess:
    """The harness without the MCU on the linear chambers V0 + C p (the truth table: test_truth_plant.py)."""
    plant = dataclasses.replace(plant, truth_step_pa=0.0, truth_chamber_volume_m3=None, truth_gland_volume_m3=None)
    return HarnessProcess(["--no-mcu", "--seed", str(seed), *plant.harness_arguments()])


def test_shipped_plant_is_converted_to_si():
    """Every unit conversion, against the file's own numbers read with tomllib."""
    document = tomllib.loads(DEFAULT_PLANT_PATH.read_text())
    chambers, blower = document["chambers"], document["blower"]
    plant = load_plant()
    assert plant.atmospheric_pressure_pa == pytest.approx(1e3 * document["gas"]["atmospheric_pressure_kpa"])
    rest_ml = np.add(chambers["cavity_volume_ml"], chambers["tubing_volume_ml"])
    assert plant.rest_volume_m3 == pytest.approx(1e-6 * rest_ml, rel=1e-12)
    assert plant.compliance_m3_per_pa == pytest.approx(1e-9 * np.array(chambers["compliance_ml_per_kpa"]), rel=1e-12)
    assert plant.free_flow_m3_per_s == pytest.approx(np.array(blower["free_flow_ml_per_min"]) * 1e-6 / 60)
    leak_ml_per_s_per_kpa = np.array(blower["back_leak_ml_per_s_per_kpa"])
    assert plant.leak_conductance_m3_per_s_per_pa == pytest.approx(1e-9 * leak_ml_per_s_per_kpa)
    assert plant.sensor_gain_per_pa == pytest.approx(1e-3 * document["sensor"]["sensitivity_per_kpa"])
    # the harness gets the total air volume, tube included
    arguments = plant.harness_arguments()
    assert f"rest_volume_m3.1={float(plant.rest_volume_m3[1])!r}" in arguments


COMPLIANCE_MATRIX = r"^compliance_ml_per_kpa = \[\n(?:.*\n){3}\]$"


@pytest.mark.parametrize(
    ("pattern", "new", "message"),
    [
        (r"^cavity_volume_ml = .*$", "cavity_volume_ml = [2.0, -1.0, 2.0]", "cavity_volume_ml: must be > 0"),
        (r"^cavity_volume_ml = .*$", "cavity_volume_ml = [2.0, 2.0]", "list of 3 numbers"),
        (r"^tubing_volume_ml = .*$", "tubing_volume_ml = [1.0, -0.5, 1.0]", "tubing_volume_ml: must be >= 0"),
        (r"^tubing_volume_ml = .*$", "", "missing key 'tubing_volume_ml'"),
        (COMPLIANCE_MATRIX, "compliance_ml_per_kpa = [[2, 0.1, 0], [0, 1, 0], [0, 0, 1]]", "must be symmetric"),
        (
            COMPLIANCE_MATRIX,
            "compliance_ml_per_kpa = [[1, -0.9, -0.9], [-0.9, 1, -0.9], [-0.9, -0.9, 1]]",
            "positive definite",
        ),
        (COMPLIANCE_MATRIX, "compliance_ml_per_kpa = [[1, 0], [0, 1]]", "3x3 matrix"),
        (r"^supply_v = .*$", 'supply_v = "five"', "supply_v: expected a finite number"),
        (r"^step_us = .*$", "step_us = 5000.0", "too coarse"),
        (r"^\[integration\]$", "[integrator]", "missing table [integration]"),
        (r"^noise_mv = .*$", "", "missing key 'noise_mv'"),
        (r"^driver_threshold = .*$", "driver_threshold = [0.1, 1.0, 0.1]", "driver_threshold: must be below 1"),
        (r"^\[gas\]$", "[gas", "not valid TOML"),
    ],
)
def test_bad_plant_files_are_refused_with_the_key_named(plant_file, pattern, new, message):
    with pytest.raises(PlantError, match=re.escape(message)):
        load_plant(plant_file(pattern, new))


def test_shipped_chambers_match_the_fem_of_the_calibrated_scene():
    """The shipped volumes and compliance are the calibrated scene's FEM, so they cannot drift from it silently.

    Tolerance: 1e-3 relative, 20 times the file's rounding to 5 significant digits (<= 5e-5); a recalibration
    that moves E by 0.1 % (its leave-one-out values spread by +/-10 %) or a change of the mesh fails it. Plus
    1e-4 ml/kPa absolute (1e-4 of chamber 0's compliance) so the near-zero couplings (about 1 % of the diagonal)
    are not held to a relative precision no one needs.
    """
    fem = chambers_from_scene(CALIBRATED_SCENE_PATH)
    plant = load_plant()
    assert 1e6 * plant.cavity_volume_m3 == pytest.approx(fem.cavity_volume_ml, rel=1e-3)
    np.testing.assert_allclose(1e9 * plant.compliance_m3_per_pa, fem.compliance_ml_per_kpa, rtol=1e-3, atol=1e-4)
    assert "prostate_converged.toml (gent, E = 10.856 kPa, nu = 0.4996, 7 mm mesh)" in DEFAULT_PLANT_PATH.read_text()


def test_regenerating_from_another_scene_scales_with_its_modulus(plant_file, tmp_path, capsys):
    """The one-liner on the calibrated scene with its modulus doubled: the rest compliance of an elastic body
    (the Gent law's tangent at rest is the small-strain one) is proportional to 1/E, so it must be the shipped
    one halved, and the rest volumes the same; each side is rounded to 5 digits, hence 2e-4. Everything else in
    the file, the tubes' dead volume included, stays as it was."""
    stiffer = tmp_path / "stiffer.toml"
    stiffer.write_text(CALIBRATED_SCENE_PATH.read_text().replace("youngs_modulus_kpa = 10.85573",
                                                                 "youngs_modulus_kpa = 21.71146"))
    path = plant_file()
    before = path.read_text()
    assert main(["hil", "plant", "--from-scene", str(stiffer), "--plant", str(path)]) == 0
    assert "wrote" in capsys.readouterr().out
    shipped, regenerated = load_plant(), load_plant(path)
    np.testing.assert_allclose(
        regenerated.compliance_m3_per_pa, 0.5 * shipped.compliance_m3_per_pa, rtol=2e-4, atol=1e-16
    )
    assert regenerated.cavity_volume_m3 == pytest.approx(shipped.cavity_volume_m3, rel=2e-4)
    assert np.array_equal(regenerated.tubing_volume_m3, shipped.tubing_volume_m3)
    assert f"# FEM source: {stiffer} (gent, E = 21.711 kPa" in path.read_text()
    changed = {line for line in set(path.read_text().splitlines()) ^ set(before.splitlines())}
    assert all(line.startswith(("# FEM source:", "cavity_volume_ml", "  [")) for line in changed), changed


def test_regeneration_refuses_bad_input(plant_file, tmp_path, capsys):
    assert main(["hil", "plant", "--from-scene", str(tmp_path / "none.toml"), "--plant", str(plant_file())]) == 2
    assert "does not exist" in capsys.readouterr().err
    assert main(["hil", "plant", "--plant", str(plant_file())]) == 2
    assert capsys.readouterr().err.strip() == "phantom hil: error: give --from-scene, --truth-from-scene or both"
    # a file without the generated keys in the expected layout is not rewritten blindly
    path = plant_file(r"^cavity_volume_ml = .*$", "")
    fem = chambers_from_scene("builtin")
    with pytest.raises(PlantError, match="expected one cavity_volume_ml line"):
        write_chambers(fem, path)
    # nor is one whose result would be invalid: the file is left untouched
    path = plant_file(r"^tubing_volume_ml = .*$", "tubing_volume_ml = [1.0, 1.0]")
    before = path.read_text()
    with pytest.raises(PlantError, match="tubing_volume_ml"):
        write_chambers(fem, path)
    assert path.read_text() == before


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
    """Steady state of Q_max (a - p/p_blocked) = G p at the driver's amplitude a = (u - u0) / (1 - u0), with
    the idle chambers back at 0 through their leak."""
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
    amplitude = (drive - plant.driver_threshold[1]) / (1 - plant.driver_threshold[1])
    expected_pa = q_max * amplitude / (q_max / p_blocked + leak)
    # 30 s is 20 passive time constants (about 1.5 s): the remaining transient is far below 0.1 Pa.
    assert state["pressures_pa"][1] == pytest.approx(expected_pa, abs=0.1)
    assert state["pressures_pa"][0] == pytest.approx(0.0, abs=0.1)
    assert state["pressures_pa"][2] == pytest.approx(0.0, abs=0.1)
    volume_ml = 1e6 * (plant.rest_volume_m3[1] + plant.compliance_m3_per_pa[1, 1] * expected_pa)
    assert state["chamber_volumes_ml"][1] == pytest.approx(volume_ml, rel=1e-4)


def test_blower_follows_its_driver_not_the_duty_cycle():
    """Below the driver's threshold no air; at full drive the datasheet's two points (free flow at 0 kPa, none at
    the blocked pressure); in between the blocked pressure scales with the amplitude, so the flow is not
    proportional to the duty cycle."""
    plant = load_plant()
    q_max, p_blocked, u0 = plant.free_flow_m3_per_s, plant.blocked_pressure_pa, plant.driver_threshold
    assert blower_flow_m3_per_s(plant, u0, 0.0) == pytest.approx(0.0)
    assert blower_flow_m3_per_s(plant, 1.0, 0.0) == pytest.approx(q_max)
    assert blower_flow_m3_per_s(plant, 1.0, p_blocked) == pytest.approx(0.0)
    half = (1 + u0) / 2  # half amplitude: half the free flow, and nothing at half the blocked pressure
    assert blower_flow_m3_per_s(plant, half, 0.0) == pytest.approx(q_max / 2)
    assert blower_flow_m3_per_s(plant, half, p_blocked / 2) == pytest.approx(0.0, abs=1e-15)
    assert blower_flow_m3_per_s(plant, 0.5, 0.0)[0] != pytest.approx(0.5 * q_max[0])


def reference_rates(plant, drive):
    """dp/dt of the coupled isothermal chambers, written out from physics.md independently of plant.c."""

    def rates(_, p):
        amplitude = np.clip((drive - plant.driver_threshold) / (1 - plant.driver_threshold), 0, 1)
        pumped = plant.free_flow_m3_per_s * np.maximum(amplitude - p / plant.blocked_pressure_pa, 0)
        inflow = np.where(amplitude > 0, pumped, 0)
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
