"""The simulated board's truth: a table of chamber volumes over the three pressures from the physical model at
parameters the controller does not use, interpolated by the harness (C) next to the real firmware in simavr.

The harness's interpolation is checked against the Python one on the same table, the table against an
independent full solve of the truth model, and both against the controller's linear plant to show they differ.
"""

import re
from pathlib import Path

import numpy as np
import pytest

from phantom.hil import bench
from phantom.hil.link import BoardLink
from phantom.hil.plant import (
    DEFAULT_PLANT_PATH,
    TRUTH_MODULUS_FACTOR,
    PlantError,
    load_plant,
    trilinear,
)
from phantom.hil.sim import SimulatedBoard

pytestmark = [pytest.mark.timeout(300), pytest.mark.sim]


def _air_volumes_ml(plant, pressures_pa):
    """What plant.c must compute: rest air volume + truth(p) - truth(0), trilinear."""
    table = plant.truth_chamber_volume_m3
    points_kpa = plant.truth_step_pa / 1e3 * np.arange(table.shape[0])
    return 1e6 * (plant.rest_volume_m3 - table[0, 0, 0] + trilinear(table, points_kpa, np.asarray(pressures_pa) / 1e3))


def test_the_shipped_truth_is_the_physical_calibration_at_its_offset_modulus():
    from phantom.model import PhantomModel, load_scene

    plant = load_plant()
    assert f"prostate_converged.toml with E x {TRUTH_MODULUS_FACTOR:g}" in DEFAULT_PLANT_PATH.read_text()
    scene = load_scene("builtin:converged")
    truth = PhantomModel.from_scene(scene).with_material(youngs_modulus_pa=scene.material.youngs_modulus_pa
                                                         * TRUTH_MODULUS_FACTOR)
    state = truth.equilibrium([1000.0, 1000.0, 0.0])
    # Written to 5 significant digits; the table's solves are Newton's to its tolerance from another start.
    np.testing.assert_allclose(1e6 * plant.truth_chamber_volume_m3[1, 1, 0], 1e6 * state.chamber_volumes_m3,
                               rtol=1e-4)
    assert 1e6 * plant.truth_gland_volume_m3[1, 1, 0] == pytest.approx(1e6 * state.gland_volume_m3, rel=1e-4)


def test_the_board_plant_follows_the_truth_not_the_controllers_linear_model():
    plant = load_plant()
    with SimulatedBoard(speed=2.0, seed=3) as board, BoardLink(board.port, time_scale=2.0) as link:
        bench.start_session(link)
        bench.zero_sensors(link)
        bench.set_setpoints(link, [1500, 2500, 700])
        bench.wait_board_time(link, 2.0)
        state = board.plant_state()
        bench.vent_and_wait(link)
    pressures_pa = np.asarray(state["pressures_pa"])
    assert pressures_pa == pytest.approx([1500, 2500, 700], abs=150)
    # The harness prints 9 significant digits.
    np.testing.assert_allclose(state["chamber_volumes_ml"], _air_volumes_ml(plant, pressures_pa), rtol=1e-7)
    expected_gland = 1e6 * trilinear(plant.truth_gland_volume_m3, np.arange(4.0), pressures_pa / 1e3)
    assert state["gland_volume_ml"] == pytest.approx(float(expected_gland), rel=1e-7)
    linear_ml = 1e6 * (plant.rest_volume_m3 + plant.compliance_m3_per_pa @ pressures_pa)
    # The controller's rest compliance misses the truth's nonlinear, stiffer-or-softer chambers by far more
    # than the sensors' resolution would hide.
    assert np.max(np.abs(np.asarray(state["chamber_volumes_ml"]) - linear_ml)) > 0.2


def test_a_partial_truth_table_is_refused(tmp_path):
    text = DEFAULT_PLANT_PATH.read_text()
    path = tmp_path / "plant.toml"
    path.write_text(re.sub(r"^truth_step_kpa = .*\n", "", text, flags=re.MULTILINE))
    with pytest.raises(PlantError, match="a truth table needs all of"):
        load_plant(path)
    path.write_text(re.sub(r"^truth_gland_volume_ml = \[", "truth_gland_volume_ml = [1.0, ", text,
                           flags=re.MULTILINE))
    with pytest.raises(PlantError, match="64 volumes"):
        load_plant(path)


def test_a_truth_of_a_scene_with_a_load_table_hangs_it_in_air(tmp_path, monkeypatch):
    """The truth model carries the scene's weight (in air) like the scene's own solves, at the truth's modulus;
    the build is stopped at the model it is given."""
    from phantom.hil.plant import truth_table_from_scene
    from phantom.model import load_scene
    from phantom.model.fidelity import response_table

    scene = tmp_path / "hanging.toml"
    shipped = load_scene("builtin:calibrated").path
    assert shipped is not None
    scene.write_text(Path(shipped).read_text() + '\n[load]\ngravity_m_s2 = [0, 0, -9.81]\n')
    weight = load_scene(scene).load.body_force_n_per_m3()
    assert weight[2] < 0
    seen = []

    def stop(model, *_, **__):
        seen.append(model)
        raise RuntimeError("model seen")

    monkeypatch.setattr(response_table, "build_response_table", stop)
    with pytest.raises(RuntimeError, match="model seen"):
        truth_table_from_scene(scene, modulus_factor=1.5)
    (model,) = seen
    np.testing.assert_array_equal(model.body_force_n_per_m3, weight)
    assert model.material.youngs_modulus_pa == pytest.approx(1.5 * load_scene(scene).material.youngs_modulus_pa)
