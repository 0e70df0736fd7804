"""Path following: limit points are followed (volume control), an unreachable target is named and explained."""

import time

import numpy as np
import pytest

from phantom.model import PeakPressureError, SolveError
from phantom.model.fem import kernels
from phantom.model.fem.materials import law_parameters
from phantom.model.fem.model import PhantomModel
from phantom.model.mesh.prostate import generate_hollow_sphere
from phantom.model.mesh.tetmesh import prepare_surfaces, volume_gradient_m2
from phantom.model.scene import Material

YOUNGS_MODULUS_PA = 50e3


@pytest.fixture(scope="module")
def sphere_mesh():
    mesh = generate_hollow_sphere(10.0, 20.0, 6.0)
    return mesh, prepare_surfaces(mesh, ["cavity"], None, "sphere")


def sphere(sphere_mesh, model, gent_jm=None):
    mesh, surfaces = sphere_mesh
    return PhantomModel(mesh, surfaces, ["cavity"], Material(model, YOUNGS_MODULUS_PA, 0.45, gent_jm))


def assert_equilibrium(model, state, gent_jm=None):
    """All elements upright and the element forces balancing the follower pressure to 1e-8 of the load."""
    dm_inverse, volumes, _ = kernels.element_rest_data(model.nodes_m, model.tets, YOUNGS_MODULUS_PA, 0.45)
    assert kernels.deformation_determinants(state.positions_m, model.tets, dm_inverse).min() > 0
    material = model.material
    forces, energy, _ = kernels.hyperelastic_forces(
        state.positions_m, model.tets, dm_inverse, volumes, *law_parameters(material.model, material),
        material.lame_mu_pa, material.lame_lambda_pa, 0, np.zeros((1, 12, 12), np.int64), np.zeros(1))
    load = state.pressures_pa[0] * volume_gradient_m2(state.positions_m, model.chamber_triangles[0])
    free = np.ones(load.size, bool)
    free[model.held_dofs] = False
    assert np.isfinite(energy)
    assert np.linalg.norm((forces - load).ravel()[free]) < 1e-8 * np.linalg.norm(load)


def test_a_flattening_pressure_volume_curve_is_followed_by_volume_control(sphere_mesh):
    """Gent (Jm = 20) on the thick sphere: the cavity's pressure-volume curve nearly flattens between 4 and 9
    times the rest volume (p/E 0.43-0.46); the path switches to volume control there and ends in an exact
    pressure-controlled equilibrium on the far side, about 12 times the rest volume."""
    model = sphere(sphere_mesh, "gent", 20.0)
    state = model.equilibrium([0.47 * YOUNGS_MODULUS_PA])
    assert_equilibrium(model, state, 20.0)
    growth = state.chamber_volumes_m3[0] / model.rest_chamber_volumes_m3[0]
    assert 8 < growth < 16, growth
    assert state.load_steps >= 4
    # the crossing of lam = 1 hands over to Newton at the exact pressures from within 1e-3 of it: 79 iterations
    # (87 when the bracket was closed to 1e-6 first)
    assert state.iterations <= 82, state.iterations


def test_just_below_a_limit_point_the_target_is_reached(sphere_mesh):
    """Neo-Hookean peaks near p/E = 0.41 on this mesh; 0.39 lies on the rising branch close to it, where the
    curve has flattened to a fifth of its initial slope."""
    model = sphere(sphere_mesh, "neo_hookean")
    state = model.equilibrium([0.39 * YOUNGS_MODULUS_PA])
    assert_equilibrium(model, state)


@pytest.mark.slow  # seconds of solves (3-5 s CPU): make test runs it, make check does not
def test_past_a_limit_point_the_error_names_the_chamber_the_peak_and_where_it_went(sphere_mesh):
    model = sphere(sphere_mesh, "neo_hookean")
    started = time.perf_counter()
    with pytest.raises(PeakPressureError) as caught:
        model.equilibrium([0.6 * YOUNGS_MODULUS_PA])
    error = caught.value
    message = str(error)
    print(f"\n{time.perf_counter() - started:.2f} s: {message}")
    assert message.startswith("chamber 0 ('cavity' at 30 kPa, p/E = 0.6) is out of reach")
    assert "limit point" in message and "finer mesh" not in message
    assert f"peaks at {error.peak_pressure_kpa:.4g} kPa (at {error.peak_volume_ml:.4g} ml)" in message
    assert isinstance(error, SolveError) and error.chamber == 0 and error.pressure_kpa == 30.0
    # The peak lies between what converged under pressure control and the target; its volume beyond that
    # equilibrium's, and the path went past it.
    below = model.equilibrium([0.4 * YOUNGS_MODULUS_PA])
    assert 20.0 < error.peak_pressure_kpa < 30.0
    assert error.peak_volume_ml > below.chamber_volumes_m3[0] * 1e6
    beyond_ml = float(message.split("the path went on to ")[1].split(" at ")[1].split(" ml")[0])
    assert beyond_ml > error.peak_volume_ml
