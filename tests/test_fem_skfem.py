"""The linear model against scikit-fem: same mesh, same loads, same constraints, independent assembly."""

import numpy as np
import pytest
import skfem
from skfem.helpers import dot
from skfem.models.elasticity import lame_parameters, linear_elasticity

from phantom.model.fem import PhantomModel
from phantom.model.mesh import prepare_surfaces
from phantom.model.scene import Material
from phantom.model.shapes import builtin_prostate, generate_hollow_sphere


def skfem_displacement(model: PhantomModel, pressures_pa) -> np.ndarray:
    """Small-strain displacement (m, (n, 3)) by scikit-fem: pressure tractions -p n on each chamber wall, the
    model's own constrained dofs held at zero."""
    mesh = skfem.MeshTet(model.nodes_m.T.copy(), model.tets.T.copy())
    basis = skfem.Basis(mesh, skfem.ElementVector(skfem.ElementTetP1()))
    material = model.material
    stiffness = skfem.asm(linear_elasticity(*lame_parameters(material.youngs_modulus_pa, material.poisson_ratio)),
                          basis)
    facet_of = {tuple(sorted(f)): i for i, f in enumerate(mesh.facets.T.tolist())}
    load = np.zeros(basis.N)
    for pressure_pa, triangles in zip(pressures_pa, model.chamber_triangles, strict=True):
        facets = np.array([facet_of[tuple(sorted(t))] for t in triangles.tolist()])

        @skfem.LinearForm
        def traction(v, w, pressure_pa=pressure_pa):
            # w.n is the solid's outward normal, which on a cavity wall points into the cavity.
            return -pressure_pa * dot(w.n, v)

        load += skfem.asm(traction, skfem.FacetBasis(mesh, basis.elem, facets=facets))
    # The model numbers dofs 3 * node + axis; scikit-fem's are basis.nodal_dofs[axis, node].
    held = basis.nodal_dofs.T.ravel()[model.held_dofs]
    solution = skfem.solve(*skfem.condense(stiffness, load, D=held))
    return solution[basis.nodal_dofs.T]


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
    state = model.solve(pressures_pa, formulation="linear")
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
