"""The Neo-Hookean model against FElupe (an independent hyperelastic FEM library) on the same meshes."""

import dataclasses

import numpy as np
import pytest
from reference.felupe_reference import felupe_forces, felupe_solve

from phantom.model.fem import kernels
from phantom.model.fem.materials import law_parameters
from phantom.model.fem.model import PhantomModel
from phantom.model.mesh.prostate import builtin_prostate, generate_hollow_sphere
from phantom.model.mesh.tetmesh import prepare_surfaces
from phantom.model.scene import Material

YOUNGS_MODULUS_PA = 50e3
CHAMBERS = ["chamber0", "chamber1", "chamber2"]


@pytest.fixture(scope="module")
def sphere():
    mesh = generate_hollow_sphere(10.0, 20.0, 6.0)
    return PhantomModel(mesh, prepare_surfaces(mesh, ["cavity"], None, "sphere"), ["cavity"],
                        Material("neo_hookean", YOUNGS_MODULUS_PA, 0.45))


@pytest.fixture(scope="module")
def free_prostate():
    """The built-in prostate at 6 mm without its fixation (3-2-1 held dofs, which the reference holds too)."""
    mesh = builtin_prostate(6.0)
    return PhantomModel(mesh, prepare_surfaces(mesh, CHAMBERS, None, "prostate"), CHAMBERS,
                        Material("neo_hookean", YOUNGS_MODULUS_PA, 0.45))


def test_element_forces_equal_felupes(sphere):
    stretch = np.array([[1.3, 0.2, 0.0], [0.0, 0.8, 0.1], [0.05, 0.0, 1.15]])
    positions = sphere.nodes_m @ stretch.T + 0.3 * sphere.nodes_m[:, [1, 2, 0]] ** 2
    material = sphere.material
    dm_inverse, volumes, _ = kernels.element_rest_data(sphere.nodes_m, sphere.tets, YOUNGS_MODULUS_PA, 0.45)
    ours, energy, _ = kernels.hyperelastic_forces(positions, sphere.tets, dm_inverse, volumes,
                                                  *law_parameters("neo_hookean", material), material.lame_mu_pa,
                                                  material.lame_lambda_pa, 0, np.zeros((1, 12, 12), np.int64),
                                                  np.zeros(1))
    assert np.isfinite(energy)
    reference = felupe_forces(sphere, positions)
    assert np.abs(ours - reference).max() < 1e-10 * np.abs(reference).max()



def test_yeoh_element_forces_and_tangent_equal_felupes_automatic_derivatives(sphere):
    """The 4-node Yeoh law's forces and exact tangent against FElupe's assembly of the same energy, differentiated
    by tensortrax (the law and the kernel are written by hand here, their derivatives nowhere in FElupe).
    Measured: forces within 4e-15, tangent within 7e-16 of their largest entries."""
    from reference.felupe_reference import felupe_compressible_yeoh, felupe_solid

    material = Material("yeoh", YOUNGS_MODULUS_PA, 0.45, yeoh_c20_over_c10=0.2, yeoh_c30_over_c10=0.02)
    model = sphere.with_material(model="yeoh", yeoh_c20_over_c10=0.2, yeoh_c30_over_c10=0.02)
    assert model.material == material
    stretch = np.array([[1.3, 0.2, 0.0], [0.0, 0.8, 0.1], [0.05, 0.0, 1.15]])
    positions = model.nodes_m @ stretch.T + 0.3 * model.nodes_m[:, [1, 2, 0]] ** 2
    body = model.body
    tangent = np.zeros(len(body.pattern.indices))
    ours, energy, _ = kernels.hyperelastic_forces(positions, body.tets, body.dm_inverse, body.element_volumes_m3,
                                                  *law_parameters("yeoh", material), material.lame_mu_pa,
                                                  material.lame_lambda_pa, 2, body.pattern.scatter, tangent)
    assert np.isfinite(energy)
    solid, field = felupe_solid(model, felupe_compressible_yeoh(material))
    field[0].values[:] = positions - model.nodes_m
    reference = np.asarray(solid.assemble.vector(field).todense()).reshape(-1, 3)
    reference_tangent = solid.assemble.matrix(field).tocsr()
    assert np.abs(ours - reference).max() < 1e-12 * np.abs(reference).max()
    assert abs(body.csr(tangent) - reference_tangent).max() < 1e-12 * abs(reference_tangent).max()

def growths(model, positions_m):
    return model.volumes(positions_m)[0] / model.rest_chamber_volumes_m3 - 1.0


@pytest.mark.parametrize("pressure_over_e", [0.1, 0.25])
def test_sphere_volume_change_matches_felupe_beyond_50_percent_growth(sphere, pressure_over_e):
    pressures = [pressure_over_e * YOUNGS_MODULUS_PA]
    ours = growths(sphere, sphere.equilibrium(pressures).positions_m)
    reference = growths(sphere, felupe_solve(sphere, pressures))
    if pressure_over_e == 0.25:
        assert reference[0] > 0.5, reference
    # Same discrete problem: the two agree to the solvers' tolerances, far inside the 0.5 % asked.
    assert ours == pytest.approx(reference, rel=1e-6)


@pytest.mark.slow
def test_prostate_volume_changes_match_felupe(free_prostate):
    pressures = np.array([0.16, 0.08, 0.12]) * YOUNGS_MODULUS_PA
    state = free_prostate.equilibrium(pressures)
    reference_m = felupe_solve(free_prostate, pressures, load_steps=2)
    ours, reference = growths(free_prostate, state.positions_m), growths(free_prostate, reference_m)
    print(f"\nchamber growths: model {ours}, FElupe {reference}")
    assert reference[0] > 0.5, reference
    # The issue asks for 0.5 %; the same discrete problem agrees to the solvers' tolerances.
    assert ours == pytest.approx(reference, rel=1e-6)
    rest_m3 = free_prostate.rest_gland_volume_m3
    gland, reference_gland = (free_prostate.volumes(x)[1] - rest_m3 for x in (state.positions_m, reference_m))
    assert gland == pytest.approx(reference_gland, rel=1e-6)


@pytest.mark.slow
def test_quadratic_mixed_sphere_agrees_with_felupes_p2_p1_beyond_50_percent_growth():
    """The 10-node mixed model (P2, pressure and dilatation constant per element) against FElupe's P2/P1 mixed
    field on the same 10-node hollow sphere (a = 10, b = 20 mm, h = 6 mm, Neo-Hookean, bulk/shear 1250): FElupe
    holds the cavity wall at stretches up to 1.15 (52 % cavity growth), the model is loaded with FElupe's
    reaction pressure, and the cavity volumes agree within 0.5 %; FElupe's pressures are within 1.5 % of the exact
    incompressible sphere's (measured: +1.1 % to +0.7 %, both discretisations converging to it)."""
    from reference.felupe_reference import felupe_mixed_sphere
    from reference.sphere_reference import incompressible_neo_hookean_pressure_pa

    inner_m, outer_m = 10e-3, 20e-3
    mesh = generate_hollow_sphere(10.0, 20.0, 6.0, element_order=2)
    model = PhantomModel(mesh, prepare_surfaces(mesh, ["cavity"], None, "sphere"), ["cavity"],
                         Material("neo_hookean", YOUNGS_MODULUS_PA, 0.4996))
    stretches = (1.05, 1.10, 1.15)
    growths_seen = []
    for stretch, (pressure_pa, reference_m) in zip(stretches, felupe_mixed_sphere(model, stretches, inner_m),
                                                   strict=True):
        exact_pa = incompressible_neo_hookean_pressure_pa(inner_m, outer_m, stretch, model.material.lame_mu_pa)
        assert abs(pressure_pa / exact_pa - 1) < 0.015, (stretch, pressure_pa, exact_pa)
        reference_volume = model.volumes(reference_m)[0][0]
        ours = model.equilibrium([pressure_pa]).chamber_volumes_m3[0]
        difference_pct = 100 * (ours / reference_volume - 1)
        print(f"\nstretch {stretch}: FElupe p {pressure_pa:.1f} Pa (exact {exact_pa:.1f}), cavity FElupe "
              f"{reference_volume * 1e6:.4f} ml, model {ours * 1e6:.4f} ml ({difference_pct:+.3f} %)")
        assert ours == pytest.approx(reference_volume, rel=5e-3)
        growths_seen.append(reference_volume / model.rest_chamber_volumes_m3[0] - 1)
    assert growths_seen[-1] > 0.5, growths_seen


@pytest.mark.slow
def test_the_10_node_prostate_agrees_with_felupes_p2_p1_beyond_50_percent_chamber_growth():
    """The 10-node mixed prostate (10 mm graded mesh, its fixation, Neo-Hookean, E 30 kPa, bulk/shear 1250) at
    (3, 1, 2) kPa, where the base chamber grows 59 %, against FElupe's P2/P1 mixed field on the same mesh.
    FElupe has no pressure load on 10-node faces, so it gets the model's chamber pressure forces at the model's
    equilibrium as a dead load: where both discretisations hold the same body, FElupe comes to rest at the same
    shape. (The pressure forces and volumes on curved faces themselves are checked on the sphere against the
    exact solution, tests/test_fem_sphere.py.) Measured: chamber volumes within 0.15 %, the gland's 0.01 %."""
    from reference.felupe_reference import felupe_mixed_dead_load

    from phantom.model import load_scene

    scene = load_scene("builtin")
    quadratic = dataclasses.replace(scene, material=Material("neo_hookean", 30e3, 0.4996),
                                    geometry=dataclasses.replace(scene.geometry, element_order=2,
                                                                 lobe_chamber_scale=1.2))
    model = PhantomModel.from_scene(quadratic, mesh_size_mm=10.0)
    pressures_pa = np.array([3.0, 1.0, 2.0]) * 1e3
    state = model.equilibrium(pressures_pa)
    assert growths(model, state.positions_m)[0] > 0.5
    forces_n = np.tensordot(pressures_pa, model.volume_gradients(state.positions_m)[: model.n_chambers], axes=1)
    reference_m = felupe_mixed_dead_load(model, forces_n.reshape(-1, 3), load_steps=1)
    reference_chambers_m3, reference_gland_m3 = model.volumes(reference_m)
    print(f"\nchambers: model {state.chamber_volumes_m3 * 1e6} ml, FElupe {reference_chambers_m3 * 1e6} ml")
    np.testing.assert_allclose(state.chamber_volumes_m3, reference_chambers_m3, rtol=5e-3)
    assert state.gland_volume_m3 == pytest.approx(reference_gland_m3, rel=5e-3)


@pytest.mark.slow
def test_yeoh_on_the_10_node_sphere_agrees_with_felupes_yeoh_beyond_50_percent_growth():
    """The Yeoh law (C20 = 0.2 C10, C30 = 0.02 C10) on the 10-node hollow sphere (a = 10, b = 20 mm, h = 8 mm,
    bulk/shear 1000) at p = 0.2 E, where the cavity grows 92 %, against FElupe's own Yeoh
    (``felupe.constitution.tensortrax``'s ``yeoh``, derivatives by automatic differentiation) in FElupe's nearly
    incompressible solid (cell-wise constant pressure and volume ratio, the model's mixed formulation) under the
    model's pressure forces at its equilibrium as a dead load. Measured: FElupe comes to rest 2.5e-4 of the
    largest displacement from the model's nodes, the cavity's volume 4e-5 from the model's (FElupe integrates
    the cells' volume with its degree-2 rule, the model exactly); Neo-Hookean at the same pressure is 9 % off."""
    from reference.felupe_reference import felupe_nearly_incompressible_equilibrium, felupe_yeoh

    mesh = generate_hollow_sphere(10.0, 20.0, 8.0, element_order=2)
    model = PhantomModel(mesh, prepare_surfaces(mesh, ["cavity"], None, "sphere"), ["cavity"],
                         Material("yeoh", YOUNGS_MODULUS_PA, 0.4995, yeoh_c20_over_c10=0.2, yeoh_c30_over_c10=0.02))
    pressure_pa = 0.2 * YOUNGS_MODULUS_PA
    state = model.equilibrium([pressure_pa])
    assert growths(model, state.positions_m)[0] > 0.5
    forces_n = pressure_pa * model.volume_gradients(state.positions_m)[0].reshape(-1, 3)
    reference_m, start_residual = felupe_nearly_incompressible_equilibrium(model, felupe_yeoh(model.material),
                                                                           forces_n, state.positions_m)
    largest_displacement_m = np.abs(state.positions_m - model.nodes_m).max()
    apart = np.abs(reference_m - state.positions_m).max() / largest_displacement_m
    reference_volume_m3 = model.volumes(reference_m)[0][0]
    neo_hookean_m3 = model.with_material(model="neo_hookean").equilibrium([pressure_pa]).chamber_volumes_m3[0]
    print(f"\nFElupe's residual at the model's nodes {start_residual:.2e} of the load; nodes apart {apart:.2e} of the "
          f"largest displacement; cavity: model {state.chamber_volumes_m3[0] * 1e6:.5f} ml, FElupe "
          f"{reference_volume_m3 * 1e6:.5f} ml, Neo-Hookean {neo_hookean_m3 * 1e6:.5f} ml")
    assert apart < 1e-3
    assert state.chamber_volumes_m3[0] == pytest.approx(reference_volume_m3, rel=2e-4)
    # The check tells the laws apart: the law without C20 and C30 misses by far more than its tolerance.
    assert neo_hookean_m3 != pytest.approx(reference_volume_m3, rel=100 * 2e-4)
