"""Hyperelastic materials (Neo-Hookean, Gent, Yeoh): kernels against finite differences, scene parsing, solves."""

import numpy as np
import pytest

from phantom.model.errors import SceneError, SolveError
from phantom.model.fem import kernels
from phantom.model.fem.materials import law_parameters
from phantom.model.fem.model import PhantomModel
from phantom.model.mesh.prostate import generate_hollow_sphere
from phantom.model.mesh.tetmesh import prepare_surfaces, volume_gradient_m2
from phantom.model.scene import Material, load_scene, scene_from_dict

YOUNGS_MODULUS_PA = 50e3
#: Each law with its coefficients (Material's keyword arguments).
LAWS = [("neo_hookean", {}), ("gent", {"gent_jm": 5.0}),
        ("yeoh", {"yeoh_c20_over_c10": 0.2, "yeoh_c30_over_c10": 0.02})]


def closed_form_energy_pa(law, coefficients, mu, shifted):
    """The distortional energy density of each law at ``shifted = I1 - 3``, written from its formula."""
    if law == "gent":
        jm = coefficients["gent_jm"]
        return -mu * jm / 2 * np.log(1 - shifted / jm)
    if law == "yeoh":
        c10 = mu / 2
        return c10 * (shifted + coefficients["yeoh_c20_over_c10"] * shifted**2
                      + coefficients["yeoh_c30_over_c10"] * shifted**3)
    return mu / 2 * shifted


def curvature_at_rest_pa(law, coefficients, mu):
    """``d2W/dI1^2`` at rest from each formula: Gent ``mu / (2 Jm)``, Yeoh ``2 C20``, Neo-Hookean 0."""
    if law == "gent":
        return mu / (2 * coefficients["gent_jm"])
    if law == "yeoh":
        return 2 * coefficients["yeoh_c20_over_c10"] * mu / 2
    return 0.0


@pytest.fixture(scope="module")
def sphere():
    mesh = generate_hollow_sphere(10.0, 20.0, 7.0)
    return mesh, prepare_surfaces(mesh, ["cavity"], None, "sphere")


def deformed(mesh, seed=3):
    """A large smooth deformation with a rigid rotation, every element stretched, none inverted."""
    rng = np.random.default_rng(seed)
    angle = 0.9
    rotation = np.array([[1, 0, 0], [0, np.cos(angle), -np.sin(angle)], [0, np.sin(angle), np.cos(angle)]])
    x = mesh.nodes_m
    stretched = x * np.array([1.2, 0.9, 1.05]) + 0.1 * x[:, [1, 2, 0]] ** 2 / 0.02
    return stretched @ rotation.T + 1e-5 * rng.normal(size=x.shape)


def material_terms(poisson_ratio=0.45, law="neo_hookean", coefficients=None):
    """The kernel's material arguments: the law's number and parameters, mu and lambda."""
    material = Material(law, YOUNGS_MODULUS_PA, poisson_ratio, **(coefficients or {}))
    return *law_parameters(law, material), material.lame_mu_pa, material.lame_lambda_pa


def forces_and_energy(mesh, positions, law="neo_hookean", coefficients=None, poisson_ratio=0.45, tangent=None):
    dm_inverse, volumes, _ = kernels.element_rest_data(mesh.nodes_m, mesh.tets, YOUNGS_MODULUS_PA, poisson_ratio)
    scatter = np.arange(len(mesh.tets) * 144, dtype=np.int64).reshape(-1, 12, 12)
    forces, energy, smallest_det = kernels.hyperelastic_forces(
        positions, mesh.tets, dm_inverse, volumes, *material_terms(poisson_ratio, law, coefficients),
        0 if tangent is None else 2, scatter, np.zeros(1) if tangent is None else tangent)
    return forces, energy, smallest_det


@pytest.mark.parametrize(("law", "coefficients"), LAWS)
def test_forces_are_the_gradient_of_the_energy(sphere, law, coefficients):
    mesh, _ = sphere
    positions = deformed(mesh)
    forces, energy, smallest_det = forces_and_energy(mesh, positions, law, coefficients)
    assert smallest_det > 0 and np.isfinite(energy) and energy > 0
    direction = np.random.default_rng(5).normal(size=positions.shape) * 1e-3
    step = 1e-4
    plus = forces_and_energy(mesh, positions + step * direction, law, coefficients)[1]
    minus = forces_and_energy(mesh, positions - step * direction, law, coefficients)[1]
    # Central differences: O(step^2) relative error, about 1e-8 here.
    assert (plus - minus) / (2 * step) == pytest.approx(np.sum(forces * direction), rel=1e-6)


def test_energy_matches_the_closed_form_of_a_homogeneous_stretch(sphere):
    """Every element under the same F: the energy is W(F) times the mesh's volume, W from the formula."""
    mesh, _ = sphere
    f = np.array([[1.3, 0.2, 0.0], [0.0, 0.9, 0.1], [0.05, 0.0, 1.1]])
    _, volumes, _ = kernels.element_rest_data(mesh.nodes_m, mesh.tets, YOUNGS_MODULUS_PA, 0.45)
    for law, coefficients in LAWS:
        *_, mu, lam = material_terms(0.45, law, coefficients)
        i1, log_j = np.sum(f * f), np.log(np.linalg.det(f))
        deviatoric = closed_form_energy_pa(law, coefficients, mu, i1 - 3)
        expected = (deviatoric - mu * log_j + lam / 2 * log_j**2) * volumes.sum()
        energy = forces_and_energy(mesh, mesh.nodes_m @ f.T, law, coefficients)[1]
        assert energy == pytest.approx(expected, rel=1e-12), law
    # Gent and this Yeoh stiffen: the same stretch costs more energy than Neo-Hookean; past I1 - 3 = Jm Gent
    # has none.
    neo_hookean = forces_and_energy(mesh, mesh.nodes_m @ f.T)[1]
    for law, coefficients in LAWS[1:]:
        assert forces_and_energy(mesh, mesh.nodes_m @ f.T, law, coefficients)[1] > neo_hookean, law
    assert forces_and_energy(mesh, mesh.nodes_m * 2.0, *LAWS[1])[1] == np.inf


def test_an_inverted_element_has_infinite_energy_and_no_force(sphere):
    mesh, _ = sphere
    positions = mesh.nodes_m.copy()
    positions[mesh.tets[0, 0]] = positions[mesh.tets[0, 1:]].mean(axis=0) * 2 - positions[mesh.tets[0, 0]]
    forces, energy, smallest_det = forces_and_energy(mesh, positions)
    assert smallest_det < 0 and energy == np.inf and np.all(np.isfinite(forces))


@pytest.mark.parametrize(("law", "coefficients"), LAWS)
def test_tangent_is_the_exact_hessian_with_the_follower_load(sphere, law, coefficients):
    mesh, surfaces = sphere
    model = PhantomModel(mesh, surfaces, ["cavity"], Material(law, YOUNGS_MODULUS_PA, 0.45, **coefficients))
    positions = deformed(mesh)
    pressures = np.array([3e3])
    tangent = model.stiffness_matrix(positions, law, pressures)
    assert abs(tangent - tangent.T).max() <= 1e-12 * abs(tangent).max()
    direction = np.random.default_rng(4).normal(size=positions.shape) * 1e-3
    direction.ravel()[model.held_dofs] = 0.0

    def out_of_balance(x):
        forces = forces_and_energy(mesh, x, law, coefficients)[0]
        return (forces - pressures[0] * volume_gradient_m2(x, surfaces.chamber_triangles[0])).ravel()

    step = 1e-6
    difference = (out_of_balance(positions + step * direction) - out_of_balance(positions - step * direction)) / (
        2 * step)
    free = np.ones(difference.size, bool)
    free[model.held_dofs] = False
    expected = tangent @ direction.ravel()
    assert np.abs(difference - expected)[free].max() < 1e-7 * np.abs(expected).max()


@pytest.mark.parametrize(("law", "coefficients"), LAWS)
def test_at_rest_the_tangent_is_the_small_strain_stiffness(sphere, law, coefficients):
    """Linearised at F = I, Neo-Hookean is linear elasticity with the same mu and lambda; a law's curvature in
    I1 adds ``4 W_11`` to lambda (``4 W_11 I x I`` at rest: ``2 mu / Jm`` for Gent, ``8 C20`` for Yeoh)."""
    mesh, _ = sphere
    *_, mu, lam = material_terms(0.3, law, coefficients)
    lam += 4 * curvature_at_rest_pa(law, coefficients, mu)
    youngs_modulus_pa, poisson_ratio = mu * (3 * lam + 2 * mu) / (lam + mu), lam / (2 * (lam + mu))
    _, _, linear = kernels.element_rest_data(mesh.nodes_m, mesh.tets, youngs_modulus_pa, poisson_ratio)
    tangent = np.zeros(linear.size)
    forces_and_energy(mesh, mesh.nodes_m, law, coefficients, 0.3, tangent)
    assert np.abs(tangent - linear.ravel()).max() < 1e-9 * np.abs(linear).max()


SCENE = {"phantom": {"mesh": "builtin:prostate", "chambers": ["chamber0", "chamber1", "chamber2"],
                     "fixed": "fixed"}}


def test_scene_reads_the_hyperelastic_materials():
    scene = scene_from_dict({**SCENE, "material": {"model": "gent", "youngs_modulus_kpa": 20, "poisson_ratio": 0.45,
                                                   "gent_jm": 12}})
    assert scene.material == Material("gent", 20e3, 0.45, 12.0)
    assert scene_from_dict({**SCENE, "material": {"model": "neo_hookean"}}).material.model == "neo_hookean"
    yeoh = scene_from_dict({**SCENE, "material": {"model": "yeoh", "youngs_modulus_kpa": 20, "poisson_ratio": 0.45,
                                                  "yeoh_c20_over_c10": -0.05, "yeoh_c30_over_c10": 0.01}})
    assert yeoh.material == Material("yeoh", 20e3, 0.45, yeoh_c20_over_c10=-0.05, yeoh_c30_over_c10=0.01)


@pytest.mark.parametrize(("material", "message"), [
    ({"model": "gent"}, "needs gent_jm"),
    ({"model": "gent", "gent_jm": -1}, "gent_jm must be the locking value of I1 - 3"),
    ({"model": "gent", "gent_jm": "20"}, "gent_jm must be the locking value of I1 - 3"),
    ({"model": "neo_hookean", "gent_jm": 20}, "applies to model = 'gent' only"),
    ({"model": "mooney"}, "'neo_hookean', 'gent' and 'yeoh'"),
    ({"model": "yeoh"}, "needs yeoh_c20_over_c10 and yeoh_c30_over_c10"),
    ({"model": "yeoh", "yeoh_c20_over_c10": 0.1}, "got yeoh_c30_over_c10 = None"),
    ({"model": "yeoh", "yeoh_c20_over_c10": "0.1", "yeoh_c30_over_c10": 0}, "got yeoh_c20_over_c10 = '0.1'"),
    ({"model": "yeoh", "yeoh_c20_over_c10": 0.1, "yeoh_c30_over_c10": float("nan")}, "got yeoh_c30_over_c10 = nan"),
    ({"model": "gent", "gent_jm": 5, "yeoh_c20_over_c10": 0.1}, "apply to model = 'yeoh' only, not 'gent'"),
])
def test_scene_rejects_bad_materials(material, message):
    with pytest.raises(SceneError, match=message):
        scene_from_dict({**SCENE, "material": material})


@pytest.fixture(scope="module")
def coarse_prostate():
    return PhantomModel.from_scene(load_scene("builtin"), mesh_size_mm=5.0)


@pytest.mark.parametrize(("law", "coefficients"), LAWS)
@pytest.mark.filterwarnings("ignore::phantom.model.PressureUnitWarning")  # its small-strain check: a few Pa on purpose
def test_prostate_solves_with_every_element_upright(coarse_prostate, law, coefficients):
    model = coarse_prostate.with_material(model=law, **coefficients)
    pressures = np.array([6e3, 4e3, 4e3])  # p/E = 0.12 in chamber 0
    state = model.equilibrium(pressures)
    assert state.formulation == law
    assert model.body.deformation_determinants(state.positions_m).min() > 0
    # Equilibrium at the returned positions: the element forces and the fixation springs balance the load.
    forces = forces_and_energy(model.mesh, state.positions_m, law, coefficients)[0]
    fixed = model.body.fixed_nodes
    forces[fixed] += model.body.spring_n_per_m[:, None] * (state.positions_m[fixed] - model.nodes_m[fixed])
    load = sum(p * volume_gradient_m2(state.positions_m, t)
               for p, t in zip(pressures, model.chamber_triangles, strict=True))
    assert np.linalg.norm(forces - load) < 1e-8 * np.linalg.norm(load)
    # At small load the law agrees with linear elasticity of the same small-strain moduli (lambda 4 W_11 higher,
    # see the tangent test), to the load's own nonlinearity, O(p/E) = 1e-4.
    small = pressures * 1e-3
    mu = model.material.lame_mu_pa
    lam = model.material.lame_lambda_pa + 4 * curvature_at_rest_pa(law, coefficients, mu)
    linear_model = model.with_material(mu * (3 * lam + 2 * mu) / (lam + mu), lam / (2 * (lam + mu)), "linear")
    hyperelastic = model.equilibrium(small).chamber_volumes_m3 - model.rest_chamber_volumes_m3
    linear = linear_model.equilibrium(small).chamber_volumes_m3 - model.rest_chamber_volumes_m3
    assert hyperelastic == pytest.approx(linear, rel=1e-3)


def test_gent_is_stiffer_than_neo_hookean_at_large_strain(coarse_prostate):
    pressures = np.array([8e3, 0.0, 0.0])
    neo = coarse_prostate.with_material(model="neo_hookean").equilibrium(pressures)
    gent = coarse_prostate.with_material(model="gent", gent_jm=3.0).equilibrium(pressures)
    rest = coarse_prostate.rest_chamber_volumes_m3[0]
    assert gent.chamber_volumes_m3[0] - rest < 0.99 * (neo.chamber_volumes_m3[0] - rest)


def test_gent_without_its_parameter_is_an_error(coarse_prostate):
    with pytest.raises(SolveError, match="gent_jm"):
        coarse_prostate.with_material(model="gent")


def test_yeoh_without_its_coefficients_is_an_error(coarse_prostate):
    with pytest.raises(SolveError, match="yeoh_c20_over_c10 and yeoh_c30_over_c10"):
        coarse_prostate.with_material(model="yeoh", yeoh_c20_over_c10=0.1)
