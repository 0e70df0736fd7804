"""Co-rotational against linear: equal at small pressure; only the co-rotational answer ignores a rigid rotation."""

import numpy as np
import pytest

from phantom.model.fem.model import PhantomModel
from phantom.model.mesh.prostate import builtin_prostate
from phantom.model.mesh.tetmesh import prepare_surfaces
from phantom.model.scene import Material

CHAMBERS = ["chamber0", "chamber1", "chamber2"]
YOUNGS_MODULUS_PA = 50e3
LOAD_SHAPE = np.array([1.0, 0.5, 0.8])


@pytest.fixture(scope="module")
def free_prostate():
    """The built-in prostate without its fixation (rigid motion removed only), coarse."""
    mesh = builtin_prostate(5.0)
    return PhantomModel(mesh, prepare_surfaces(mesh, CHAMBERS, None, "test"), CHAMBERS,
                        Material("corotational", YOUNGS_MODULUS_PA, 0.45))


def volume_changes(model, state):
    return np.r_[state.chamber_volumes_m3 - model.rest_chamber_volumes_m3,
                 state.gland_volume_m3 - model.rest_gland_volume_m3]


@pytest.mark.filterwarnings("ignore::phantom.model.PressureUnitWarning")  # a load of a few Pa on purpose
def test_equal_to_linear_at_small_pressure(free_prostate):
    model = free_prostate
    differences = []
    for pressure_pa in (5.0, 50.0):
        pressures = LOAD_SHAPE * pressure_pa
        corotational = volume_changes(model, model.equilibrium(pressures))
        linear = volume_changes(model, model.equilibrium(pressures, formulation="linear"))
        differences.append(np.abs(corotational / linear - 1).max())
    # The models differ by geometric nonlinearity, O(p/E): 1e-4 of relative size at p/E = 1e-4, and ten times
    # more at ten times the pressure (a first-order difference, not a bias).
    assert differences[0] < 5e-4
    assert differences[1] / differences[0] == pytest.approx(10.0, rel=0.1)


def rotated_90_degrees(positions_m):
    centre = positions_m.mean(axis=0)
    quarter_turn = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    return (positions_m - centre) @ quarter_turn.T + centre


def test_only_the_corotational_answer_is_invariant_to_a_rigid_rotation(free_prostate):
    model = free_prostate
    pressures = LOAD_SHAPE * 0.1 * YOUNGS_MODULUS_PA  # large: p/E = 0.1
    start = rotated_90_degrees(model.nodes_m)
    upright = model.equilibrium(pressures)
    turned = model.equilibrium(pressures, initial_positions_m=start)
    # Same equilibrium, rotated: volumes agree to the Newton tolerance (1e-9 of the load).
    np.testing.assert_allclose(volume_changes(model, turned), volume_changes(model, upright), rtol=1e-6)
    assert abs(volume_changes(model, upright)[-1]) > 1e-7  # a large load: over 0.1 ml of growth
    upright_linear = model.equilibrium(pressures, formulation="linear")
    turned_linear = model.equilibrium(pressures, formulation="linear", initial_positions_m=start)
    # Small strain sees a rotation as a huge strain: its answer changes completely.
    assert np.abs(volume_changes(model, turned_linear) / volume_changes(model, upright_linear) - 1).max() > 1.0
    # At this load the co-rotational and linear answers differ by geometric nonlinearity, about 10 %.
    assert np.abs(volume_changes(model, upright) / volume_changes(model, upright_linear) - 1).max() > 0.02
