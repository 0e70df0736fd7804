"""10-node tetrahedra in the mixed formulation: the curved faces' volumes, the kernel's forces and tangent against
its energy, the body force's consistent load, the meshes written and read back, and the scene's element order.

The convergence to the exact incompressible sphere is in test_fem_sphere.py (slow)."""

import dataclasses

import numpy as np
import pytest

from phantom.model.errors import SceneError
from phantom.model.fem.body import EXACT_TANGENT
from phantom.model.fem.model import PhantomModel
from phantom.model.mesh.prostate import generate_hollow_sphere
from phantom.model.mesh.tetmesh import prepare_surfaces, read_mesh, write_mesh
from phantom.model.scene import Material, scene_from_dict

INNER_MM, OUTER_MM, SIZE_MM = 10.0, 20.0, 8.0
YOUNGS_MODULUS_PA = 50e3


@pytest.fixture(scope="module")
def meshes():
    return {order: generate_hollow_sphere(INNER_MM, OUTER_MM, SIZE_MM, element_order=order) for order in (1, 2)}


def sphere_model(mesh, law="neo_hookean", poisson_ratio=0.4995, gent_jm=None, **coefficients):
    surfaces = prepare_surfaces(mesh, ["cavity"], None, "sphere")
    return PhantomModel(mesh, surfaces, ["cavity"], Material(law, YOUNGS_MODULUS_PA, poisson_ratio, gent_jm,
                                                             **coefficients))


def test_curved_faces_measure_the_sphere_far_better_than_flat_ones(meshes):
    exact_cavity = 4 / 3 * np.pi * (INNER_MM * 1e-3) ** 3
    errors = {}
    for order, mesh in meshes.items():
        model = sphere_model(mesh)
        errors[order] = abs(model.rest_chamber_volumes_m3[0] / exact_cavity - 1)
    assert meshes[2].tets.shape[1] == 10 and meshes[1].tets.shape[1] == 4
    # measured at 8 mm: 13.8 % (flat faces), 0.27 % (6-node faces)
    assert errors[2] < 5e-3 and errors[2] < errors[1] / 20, errors


def test_element_volumes_and_node_shares_add_up_to_the_body(meshes):
    model = sphere_model(meshes[2])
    solid_m3 = model.rest_gland_volume_m3 - model.rest_chamber_volumes_m3[0]
    assert model.body.element_volumes_m3.sum() == pytest.approx(solid_m3, rel=1e-10)
    # the consistent body-force load: each node's share integral N_a dV, vertices negative, mid-edge positive
    # (on the degree-2 points, which integrate a curved element's Jacobian to about 1e-7)
    assert model.body.node_volumes_m3.sum() == pytest.approx(solid_m3, rel=1e-5)
    vertices = np.unique(model.tets[:, :4])
    assert np.all(model.body.node_volumes_m3[vertices] < 0)
    assert np.all(model.body.element_volume_ratios(model.nodes_m) == pytest.approx(1.0, abs=1e-12))


def deformed(nodes_m, seed=3):
    """A large smooth deformation with a rotation and a little noise, no element inverted."""
    rng = np.random.default_rng(seed)
    angle = 0.7
    rotation = np.array([[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0], [0, 0, 1]])
    stretched = nodes_m * np.array([1.15, 0.92, 1.03]) + 0.05 * nodes_m[:, [1, 2, 0]] ** 2 / 0.02
    return stretched @ rotation.T + 2e-6 * rng.normal(size=nodes_m.shape)


@pytest.mark.parametrize(("law", "coefficients"), [
    ("neo_hookean", {}), ("gent", {"gent_jm": 3.0}), ("yeoh", {"yeoh_c20_over_c10": -0.1, "yeoh_c30_over_c10": 0.05})])
def test_mixed_forces_and_tangent_are_the_energys_derivatives(meshes, law, coefficients):
    model = sphere_model(meshes[2], law, 0.45, **coefficients)
    body, constraints = model.body, model.body.rest_constraints
    positions = deformed(model.nodes_m)
    evaluation = body.elastic(positions, law, EXACT_TANGENT, constraints)
    assert np.isfinite(evaluation.energy_j) and evaluation.smallest_det > 0
    direction = np.random.default_rng(5).normal(size=positions.shape) * 1e-4
    direction.reshape(-1)[constraints.dofs] = 0.0
    step = 1e-3
    plus, minus = (body.elastic(positions + sign * step * direction, law, EXACT_TANGENT, constraints)
                   for sign in (1.0, -1.0))
    assert (plus.energy_j - minus.energy_j) / (2 * step) == pytest.approx(
        np.sum(evaluation.forces_n.ravel() * direction.ravel()), rel=1e-6)
    change = (plus.forces_n - minus.forces_n).ravel() / (2 * step)
    product = body.multiply(evaluation.tangent_data, direction.ravel())
    free = constraints.free_mask
    assert np.linalg.norm(product[free] - change[free]) < 1e-6 * np.linalg.norm(change[free])


def test_carried_element_pressures_are_the_perturbed_lagrangians_derivatives(meshes):
    """With the pressures as an independent field, forces and tangent are the derivatives of ``W_iso + V_e (p (Jbar
    - 1) - p^2 / 2K)`` at fixed p, and p = K (Jbar - 1) gives back the eliminated evaluation."""
    model = sphere_model(meshes[2], "gent", 0.4995, 3.0)
    body, constraints = model.body, model.body.rest_constraints
    positions = deformed(model.nodes_m)
    ratios = body.element_volume_ratios(positions)
    bulk = model.material.bulk_modulus_pa
    eliminated = body.elastic(positions, "gent", EXACT_TANGENT, constraints)
    same = body.elastic(positions, "gent", EXACT_TANGENT, constraints, element_pressures_pa=bulk * (ratios - 1))
    np.testing.assert_allclose(same.forces_n, eliminated.forces_n, rtol=1e-12,
                               atol=1e-12 * abs(eliminated.forces_n).max())
    assert same.energy_j == pytest.approx(eliminated.energy_j, rel=1e-12)
    # away from the constraint: another pressure field, held fixed while the nodes move
    pressures = bulk * (ratios - 1) * 0.3 + 50.0 * np.random.default_rng(7).normal(size=ratios.shape)
    evaluation = body.elastic(positions, "gent", EXACT_TANGENT, constraints, element_pressures_pa=pressures)
    assert np.linalg.norm(evaluation.forces_n - eliminated.forces_n) > 1e-3 * np.linalg.norm(eliminated.forces_n)
    direction = np.random.default_rng(5).normal(size=positions.shape) * 1e-4
    direction.reshape(-1)[constraints.dofs] = 0.0
    step = 1e-3
    plus, minus = (body.elastic(positions + sign * step * direction, "gent", EXACT_TANGENT, constraints,
                                element_pressures_pa=pressures) for sign in (1.0, -1.0))
    assert (plus.energy_j - minus.energy_j) / (2 * step) == pytest.approx(
        np.sum(evaluation.forces_n.ravel() * direction.ravel()), rel=1e-6)
    # the volume ratios' rates are their directional derivatives
    rates = body.element_volume_ratio_rates(positions, direction)
    differences = (body.element_volume_ratios(positions + step * direction)
                   - body.element_volume_ratios(positions - step * direction)) / (2 * step)
    np.testing.assert_allclose(rates, differences, rtol=1e-5, atol=1e-9 * np.abs(differences).max())
    # the tangent is the condensed one Newton solves with: the forces' change as the nodes move and each
    # pressure takes its linearised update K dJbar
    plus, minus = (body.elastic(positions + sign * step * direction, "gent", EXACT_TANGENT, constraints,
                                element_pressures_pa=pressures + sign * step * bulk * rates) for sign in (1.0, -1.0))
    change = (plus.forces_n - minus.forces_n).ravel() / (2 * step)
    product = body.multiply(evaluation.tangent_data, direction.ravel())
    free = constraints.free_mask
    assert np.linalg.norm(product[free] - change[free]) < 1e-6 * np.linalg.norm(change[free])


def test_the_mixed_newton_solves_the_nearly_incompressible_prostate_in_a_handful_of_iterations():
    """Eliminating each element's pressure made a 10-node solve at bulk/shear 1250 crawl: (2,0,0) kPa at E 50 kPa
    took 58 iterations (26 s) on the 10 mm prostate. With the pressures carried as unknowns it takes 6; the
    answer is an equilibrium of the eliminated system to the solver's tolerance."""
    from phantom.model import load_scene
    from phantom.model.fem.newton import RELATIVE_TOLERANCE

    scene = load_scene("builtin:calibrated")
    scene = dataclasses.replace(scene, geometry=dataclasses.replace(scene.geometry, element_order=2))
    model = PhantomModel.from_scene(scene, mesh_size_mm=10.0).with_material(youngs_modulus_pa=50e3,
                                                                             poisson_ratio=0.4996)
    pressures = np.array([2000.0, 0.0, 0.0])
    state = model.equilibrium(pressures)
    assert state.iterations <= 10
    problem = model.problem(pressures)
    residual = problem.evaluate(state.positions_m).residual_n
    assert np.linalg.norm(residual) <= RELATIVE_TOLERANCE * problem.load_scale_n()
    # the convergence table's 10 mm figure (bench/README.md; the fixation patch ending on its radius since 72e9ebb)
    assert state.gland_volume_m3 - model.rest_gland_volume_m3 == pytest.approx(0.3741e-6, rel=2e-3)


@pytest.mark.slow
def test_the_converged_scene_reaches_3_kpa_in_a_handful_of_steps_on_cholmod_alone(capfd):
    """(3,1,2) kPa from rest on the converged scene's law at 10 mm: 27 accepted steps and 48 SuperLU
    factorisations (92.6 s) when each volume step's predictor had its element pressures eliminated (K (Jbar - 1)
    of a secant guess: an indefinite tangent) and an indefinite K went to SuperLU; 3 pressure steps and CHOLMOD
    alone (12 s) with the pressures extrapolated from the path and K shifted as Newton's is; now volume control
    from rest (the small-strain answer grows chamber 0 by more than half), Newton at every iterate and at the
    exact pressures from the predictor: 30 iterations in 6 steps; with Hermite's cubic through the last two path
    points and their directions, doubling after 3 iterations, 22 in 7. Same equilibrium: the residual at the
    solver's tolerance, the gland 38.9606 ml either way. (1,1,1) kPa, one pressure step: 28 iterations in 3 steps
    from rest, 5 in 1 from the small-strain answer."""
    from phantom.model import load_scene
    from phantom.model.fem import linsolve
    from phantom.model.fem.newton import RELATIVE_TOLERANCE

    model = PhantomModel.from_scene(load_scene("builtin:converged"), mesh_size_mm=10.0)
    methods: list[str] = []
    original = linsolve.Factorization.__init__

    def recording(self, matrix, method=None, analysis=None, ordering=None):
        methods.append(method or linsolve.default_method())
        original(self, matrix, method, analysis, ordering)

    linsolve.Factorization.__init__ = recording
    capfd.readouterr()  # (a cold cache's meshing message is not the solve's)
    try:
        state = model.equilibrium([3000.0, 1000.0, 2000.0])
    finally:
        linsolve.Factorization.__init__ = original
    # nothing from C on stdout or stderr (SuperLU's "On entry to DTRSV parameter number 6 had an illegal value"
    # came from its factor of an indefinite tangent during volume-controlled steps)
    assert capfd.readouterr() == ("", "")
    assert state.load_steps <= 7 and state.iterations <= 24, (state.load_steps, state.iterations)
    assert methods and set(methods) == {linsolve.default_method()}, sorted(set(methods))
    assert state.gland_volume_m3 * 1e6 == pytest.approx(38.96057, abs=1e-5)
    small = model.equilibrium([1000.0, 1000.0, 1000.0])
    assert small.load_steps == 1 and small.iterations <= 7, (small.load_steps, small.iterations)
    problem = model.problem([3000.0, 1000.0, 2000.0])
    assert np.linalg.norm(problem.evaluate(state.positions_m).residual_n) <= RELATIVE_TOLERANCE * problem.load_scale_n()
    assert state.gland_volume_m3 * 1e6 == pytest.approx(38.9606, abs=2e-4)


@pytest.mark.filterwarnings("ignore::phantom.model.PressureUnitWarning")  # a load of a few Pa on purpose
def test_small_pressure_follows_the_small_strain_answer(meshes):
    """At p/E = 1e-4 the mixed Neo-Hookean growth equals the 10-node small-strain ("linear") one to first order."""
    model = sphere_model(meshes[2])
    pressure = [1e-4 * YOUNGS_MODULUS_PA]
    growths = [model.equilibrium(pressure, formulation).chamber_volumes_m3[0] / model.rest_chamber_volumes_m3[0] - 1
               for formulation in ("neo_hookean", "linear")]
    assert growths[0] > 0
    assert growths[0] == pytest.approx(growths[1], rel=2e-3)


def test_the_corotational_law_is_refused_on_10_node_elements(meshes):
    with pytest.raises(Exception, match="4-node tetrahedra"):
        sphere_model(meshes[2], "corotational")


@pytest.mark.parametrize("suffix", [".vtu", ".msh"])
def test_a_10_node_mesh_is_written_and_read_back_node_for_node(meshes, tmp_path, suffix):
    mesh = meshes[2]
    path = tmp_path / f"sphere{suffix}"
    write_mesh(mesh, path, 1e-3)
    if suffix == ".vtu":
        import meshio

        assert {block.type for block in meshio.read(path).cells} >= {"tetra10", "triangle6"}
    back = read_mesh(path, 1e-3)
    assert back.order == 2
    np.testing.assert_allclose(back.nodes_m, mesh.nodes_m, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(back.tets, mesh.tets)
    for name, faces in mesh.surface_groups.items():
        np.testing.assert_array_equal(back.surface_groups[name], faces)


@pytest.mark.parametrize("order", [0, 3, 1.5, True, "2"])
def test_an_unknown_element_order_is_a_one_line_scene_error(order):
    raw = {"phantom": {"mesh": "builtin:prostate", "chambers": ["chamber0", "chamber1", "chamber2"]},
           "geometry": {"element_order": order}}
    with pytest.raises(SceneError, match="element_order must be 1"):
        scene_from_dict(raw)


def test_curved_chamber_load_and_its_stiffness_are_the_volumes_derivatives(meshes):
    """On 6-node faces the pressure load is ``p dV/dx`` and the follower stiffness its derivative: the problem's
    residual and exact tangent (elastic and pressure parts) against central differences of its energy and
    residual."""
    model = sphere_model(meshes[2], "neo_hookean", 0.45)
    problem = model.problem([0.2 * YOUNGS_MODULUS_PA])
    positions = deformed(model.nodes_m)
    evaluation = problem.evaluate(positions, with_tangent=True)
    direction = np.random.default_rng(7).normal(size=positions.shape) * 1e-4
    direction.reshape(-1)[problem.constraints.dofs] = 0.0
    step = 1e-3
    plus, minus = (problem.evaluate(positions + sign * step * direction) for sign in (1.0, -1.0))
    assert (plus.energy_j - minus.energy_j) / (2 * step) == pytest.approx(
        np.sum(evaluation.residual_n.ravel() * direction.ravel()), rel=1e-6)
    change = (plus.residual_n - minus.residual_n).ravel() / (2 * step)
    product = problem.multiply(evaluation.tangent_data)(direction.ravel())
    free = problem.constraints.free_mask
    assert np.linalg.norm(product[free] - change[free]) < 1e-6 * np.linalg.norm(change[free])


def test_a_folded_curved_element_is_straightened():
    """A mid-edge node pushed across its element folds it; the mesher's repair puts it back on its edge."""
    from phantom.model.mesh.elements import TET10_EDGES
    from phantom.model.mesh.prostate import _straighten_folded
    from phantom.model.mesh.tetmesh import curved_jacobian_determinants

    vertices = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    middles = np.array([(vertices[a] + vertices[b]) / 2 for a, b in TET10_EDGES.tolist()])
    nodes = np.vstack([vertices, middles])
    tets = np.arange(10)[None, :]
    nodes[4] += [0.0, 0.0, 0.9]  # the (0, 1) edge's middle pushed past the opposite face's side
    assert curved_jacobian_determinants(nodes, tets).min() <= 0
    repaired = _straighten_folded(nodes, tets)
    assert curved_jacobian_determinants(repaired, tets).min() > 0
    np.testing.assert_allclose(repaired[4], [0.5, 0.0, 0.0])
    np.testing.assert_array_equal(repaired[:4], vertices)


def test_newtons_tangent_off_equilibrium_is_damped_until_cholmod_factorises_it(meshes):
    """Far from equilibrium (the full pressure on the rest shape) the exact Hessian is indefinite: CHOLMOD refuses
    it, path following gets CHOLMOD's LDL' of it as it is, and Newton gets ``K + tau |diag K|``, whose direction
    descends."""
    model = sphere_model(meshes[2], "gent", 0.45, 3.0)
    problem = model.problem([2.0 * YOUNGS_MODULUS_PA])
    positions = deformed(model.nodes_m)
    data = problem.body.elastic(positions, "gent", EXACT_TANGENT, problem.constraints,
                                problem.pressures_pa).tangent_data
    with pytest.raises(ArithmeticError, match="not positive definite"):
        problem.body.factorize(data, positive_definite=True)
    assert problem.tangent(positions, exact=True).method == "cholmod-ldl"
    damped = problem.tangent(positions, exact=True, damped=True)
    assert damped.method == "cholmod"
    residual = problem.evaluate(positions).residual_n
    direction = -damped.solve(residual)
    assert np.dot(residual, direction) < 0


@pytest.mark.slow
def test_volume_control_carries_the_element_pressures_to_the_same_equilibrium(meshes):
    """Gent (Jm 20), bulk/shear 1000, at p/E 0.3: the cavity's pressure-volume curve flattens and the path goes
    on under volume control, whose bordered Newton carries the 10-node body's element pressures as the pressure-
    controlled Newton does. The end is an equilibrium of the eliminated system to the solver's tolerance, the
    cavity grown 15.54 times, as with the pressures eliminated (245 iterations then, 201 with them carried, 75
    now: issue 40's path, bench/README.md, "Through the limit points")."""
    from phantom.model.fem.newton import RELATIVE_TOLERANCE
    from phantom.model.fem.pathfollow import _Path

    model = sphere_model(meshes[2], "gent", 0.4995, 20.0)
    carried = []
    original = _Path._volume_residual

    def recording(self, positions_m, load_factor, target_m3, element_pressures_pa=None, with_tangent=False):
        carried.append(element_pressures_pa is not None)
        return original(self, positions_m, load_factor, target_m3, element_pressures_pa, with_tangent)

    _Path._volume_residual = recording
    try:
        state = model.equilibrium([0.3 * YOUNGS_MODULUS_PA])
    finally:
        _Path._volume_residual = original
    assert carried and all(carried)  # the path went through volume control, every iterate with its pressures
    # a quadratic predictor and Newton at every iterate: 42 element passes in the volume-controlled solves and 75
    # iterations in all (356 passes and 201 iterations with a kept factor's trials halved at most twice, 668
    # passes when they were halved 12 times; 64 and 52 when this one chamber was volume controlled from rest)
    assert len(carried) <= 80 and state.iterations <= 90, (len(carried), state.iterations)
    growth = state.chamber_volumes_m3[0] / model.rest_chamber_volumes_m3[0]
    assert growth == pytest.approx(15.539, rel=1e-3)
    problem = model.problem([0.3 * YOUNGS_MODULUS_PA])
    residual = problem.evaluate(state.positions_m).residual_n
    assert np.linalg.norm(residual) <= RELATIVE_TOLERANCE * problem.load_scale_n()
    assert model.body.element_volume_ratios(state.positions_m) == pytest.approx(1.0, abs=0.01)


def test_a_start_extrapolated_along_a_line_of_loads_is_exact_on_a_polynomial_path(meshes):
    """:meth:`PhantomModel.extrapolated_start`: the Lagrange polynomial through equally spaced states (nearest
    first, or at the load factors given) at the next load, exact on a path that is that polynomial; no prediction
    where only one is given or the polynomial would invert an element."""
    model = sphere_model(meshes[2], "gent", 0.4995, 20.0)
    rest = model.nodes_m
    rng = np.random.default_rng(5)
    linear, square = (2e-5 * rng.standard_normal(rest.shape) for _ in range(2))
    path = [rest + t * linear + t**2 * square for t in range(4)]
    quadratic, pressures = model.extrapolated_start([path[2], path[1], path[0]])
    np.testing.assert_allclose(quadratic, path[3], rtol=0, atol=1e-15)
    ratios = [model.body.element_volume_ratios(x) for x in path[:3]]
    np.testing.assert_allclose(pressures, model.body.eliminated_pressures_pa(3 * ratios[2] - 3 * ratios[1]
                                                                             + ratios[0]), rtol=1e-12)
    secant, _ = model.extrapolated_start([rest + 2 * linear, rest + linear])
    np.testing.assert_allclose(secant, rest + 3 * linear, rtol=0, atol=1e-15)
    # a calibration trace's load factors, unequally spaced (rest, 1, 3 -> 3.5)
    uneven, _ = model.extrapolated_start([path[3], path[1], path[0]], [3.0, 1.0, 0.0], 3.5)
    np.testing.assert_allclose(uneven, rest + 3.5 * linear + 3.5**2 * square, rtol=0, atol=1e-15)
    assert model.extrapolated_start([path[1]]) == (None, None)
    inside_out = rest.copy()
    inside_out[:, 0] *= -1.0  # a mirror image: every element's det F < 0 at the extrapolation
    halfway = (rest + inside_out) / 2
    assert model.extrapolated_start([halfway, rest]) == (None, None)
    linear_model = sphere_model(meshes[1], "gent", 0.45, 20.0)
    assert linear_model.extrapolated_start([linear_model.nodes_m, linear_model.nodes_m])[1] is None


def test_a_start_extrapolated_from_three_solved_loads_saves_newton_iterations(meshes):
    """The table's grid lines (bench/README.md, "The table's cost per point"): the next load's Newton from the
    quadratic through the three equilibria before it reaches the same equilibrium as from the nearest one, in
    fewer iterations."""
    model = sphere_model(meshes[2], "gent", 0.4995, 20.0)
    step_pa = 0.04 * YOUNGS_MODULUS_PA
    line = [model.equilibrium([step_pa]).positions_m]
    for load in (2, 3):
        line.insert(0, model.equilibrium([load * step_pa], initial_positions_m=line[0]).positions_m)
    from_nearest = model.equilibrium([4 * step_pa], initial_positions_m=line[0])
    start_m, start_pa = model.extrapolated_start(line)
    extrapolated = model.equilibrium([4 * step_pa], initial_positions_m=line[0], predicted_positions_m=start_m,
                                     predicted_element_pressures_pa=start_pa)
    assert extrapolated.load_steps == from_nearest.load_steps == 1  # Newton at the load, no path from rest
    assert extrapolated.iterations < from_nearest.iterations, (extrapolated.iterations, from_nearest.iterations)
    np.testing.assert_allclose(extrapolated.chamber_volumes_m3, from_nearest.chamber_volumes_m3, rtol=1e-9)
    np.testing.assert_allclose(extrapolated.positions_m, from_nearest.positions_m, rtol=0, atol=1e-10)
