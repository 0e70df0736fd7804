"""The linear model against scikit-fem: same mesh, same loads, same constraints, independent assembly."""

import numpy as np
import pytest
from reference.skfem_reference import skfem_displacement

from phantom.model.fem.model import PhantomModel
from phantom.model.mesh.prostate import builtin_prostate, generate_hollow_sphere
from phantom.model.mesh.tetmesh import prepare_surfaces
from phantom.model.scene import Material


def unfixed_model(mesh, chambers, poisson_ratio):
    surfaces = prepare_surfaces(mesh, chambers, None, "test")
    return PhantomModel(mesh, surfaces, chambers, Material("linear", 40e3, poisson_ratio))


@pytest.mark.parametrize(("name", "pressures_kpa", "poisson_ratio"),
                         [("sphere", [1.0], 0.3), ("sphere", [2.0], 0.45), ("prostate", [1.0, 2.0, 3.0], 0.45)])
def test_linear_model_agrees_with_scikit_fem(name, pressures_kpa, poisson_ratio):
    if name == "sphere":
        model = unfixed_model(generate_hollow_sphere(10.0, 20.0, 5.0), ["cavity"], poisson_ratio)
    else:
        model = unfixed_model(builtin_prostate(5.0), ["chamber0", "chamber1", "chamber2"], poisson_ratio)
    pressures_pa = np.array(pressures_kpa) * 1e3
    state = model.equilibrium(pressures_pa, formulation="linear")
    ours = state.positions_m - model.nodes_m
    theirs = skfem_displacement(model, pressures_pa)
    # Both are direct solves of the same linear system, assembled independently: they agree to the solvers'
    # rounding (condition number ~1e6 times 1e-16), far below any discretisation error.
    assert np.abs(ours - theirs).max() <= 1e-9 * np.abs(theirs).max()
    chamber_volumes, gland_volume = model.volumes(model.nodes_m + theirs)
    rest_chambers = model.rest_chamber_volumes_m3
    np.testing.assert_allclose(state.chamber_volumes_m3 - rest_chambers, chamber_volumes - rest_chambers, rtol=1e-9)
    assert state.gland_volume_m3 - model.rest_gland_volume_m3 == pytest.approx(
        gland_volume - model.rest_gland_volume_m3, rel=1e-9)
    assert state.iterations == 1
