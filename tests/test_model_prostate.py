"""The built-in prostate through the public API and the CLI: inflation, symmetry, scaling with E, compliance."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from phantom.model import MeshError, PhantomModel, SolveError, load_scene
from phantom.model.mesh.shape import REST_VOLUME_ML

PHANTOM = Path(sys.executable).with_name("phantom")
MIRROR = np.array([-1.0, 1.0, 1.0])


@pytest.fixture(scope="module")
def model():
    return PhantomModel.from_scene(load_scene("builtin"))


@pytest.fixture(scope="module")
def coarse():
    return PhantomModel.from_scene(load_scene("builtin"), mesh_size_mm=5.0)


def test_public_attributes(model):
    assert model.chamber_names == ["chamber0", "chamber1", "chamber2"] and model.n_chambers == 3
    assert model.nodes_m.shape[1] == 3 and model.tets.shape[1] == 4 and model.outer_triangles.shape[1] == 3
    assert model.rest_chamber_volumes_m3.shape == (3,)
    assert model.rest_gland_volume_m3 * 1e6 == pytest.approx(REST_VOLUME_ML, rel=0.01)
    chambers, gland = model.volumes(model.nodes_m)
    np.testing.assert_array_equal(chambers, model.rest_chamber_volumes_m3)
    assert gland == model.rest_gland_volume_m3


def test_each_chamber_inflates_and_the_lobes_mirror_each_other(model):
    states = [model.equilibrium(1e3 * np.eye(3)[k]) for k in range(3)]
    for k, state in enumerate(states):
        growth = state.chamber_volumes_m3 - model.rest_chamber_volumes_m3
        assert growth[k] > 0 and growth[k] == growth.max()
        assert state.gland_volume_m3 > model.rest_gland_volume_m3
        assert state.iterations >= 1 and state.solve_time_s > 0
        np.testing.assert_array_equal(state.pressures_pa, 1e3 * np.eye(3)[k])
    left, right = states[1], states[2]
    # The mesh is a mirror image of itself about x = 0 (chambers 1 and 2 swap): the answers must swap too,
    # to the Newton tolerance.
    assert left.chamber_volumes_m3[1] == pytest.approx(right.chamber_volumes_m3[2], rel=1e-9)
    assert left.chamber_volumes_m3[0] == pytest.approx(right.chamber_volumes_m3[0], rel=1e-9)
    assert left.gland_volume_m3 == pytest.approx(right.gland_volume_m3, rel=1e-12)
    mirror_of = _mirror_map(model.nodes_m)
    displacement_left = left.positions_m - model.nodes_m
    displacement_right = right.positions_m - model.nodes_m
    scale = np.abs(displacement_left).max()
    assert np.abs(displacement_left[mirror_of] * MIRROR - displacement_right).max() < 1e-7 * scale


def _mirror_map(nodes_m):
    from scipy.spatial import cKDTree

    distances, mirror_of = cKDTree(nodes_m).query(nodes_m * MIRROR)
    assert distances.max() < 1e-12
    return mirror_of


def test_solution_scales_exactly_with_youngs_modulus(coarse):
    stiffer = coarse.with_material(youngs_modulus_pa=4 * coarse.material.youngs_modulus_pa)
    pressures = np.array([2e3, 1e3, 3e3])
    reference = coarse.equilibrium(pressures)
    scaled = stiffer.equilibrium(4 * pressures)
    # Springs are a multiple of E, so (p, E) and (4p, 4E) are the same problem: equal to the Newton tolerance.
    displacement = reference.positions_m - coarse.nodes_m
    assert np.abs(scaled.positions_m - reference.positions_m).max() < 1e-7 * np.abs(displacement).max()
    np.testing.assert_allclose(scaled.chamber_volumes_m3, reference.chamber_volumes_m3, rtol=1e-10)


@pytest.mark.filterwarnings("ignore::phantom.model.PressureUnitWarning")  # a load of a few Pa on purpose
def test_rest_compliance_predicts_small_inflations(coarse, tmp_path, monkeypatch):
    monkeypatch.setenv("PHANTOM_CACHE_DIR", str(tmp_path))
    compliance = coarse.compliance()
    assert len(list((tmp_path / "compliance").glob("*.npz"))) == 1
    w = compliance.chamber_m3_per_pa
    # W = H K^-1 H^T: symmetric to rounding, positive definite.
    assert np.abs(w - w.T).max() < 1e-9 * np.abs(w).max()
    assert np.all(np.linalg.eigvalsh(0.5 * (w + w.T)) > 0)
    pressures = np.array([1.0, 3.0, 2.0])  # p/E ~ 5e-5: the nonlinear answer is linear to that size
    state = coarse.equilibrium(pressures)
    np.testing.assert_allclose(state.chamber_volumes_m3 - coarse.rest_chamber_volumes_m3, w @ pressures, rtol=2e-4)
    assert state.gland_volume_m3 - coarse.rest_gland_volume_m3 == pytest.approx(
        compliance.gland_m3_per_pa @ pressures, rel=2e-4)
    linear = coarse.equilibrium(pressures, formulation="linear")
    shape = coarse.nodes_m + np.tensordot(pressures, compliance.displacement_m_per_pa, axes=1)
    assert np.abs(shape - linear.positions_m).max() < 1e-9 * np.abs(linear.positions_m - coarse.nodes_m).max()
    again = coarse.compliance()
    np.testing.assert_array_equal(again.chamber_m3_per_pa, w)
    softer = coarse.with_material(youngs_modulus_pa=coarse.material.youngs_modulus_pa / 2).compliance()
    np.testing.assert_allclose(softer.chamber_m3_per_pa, 2 * w, rtol=1e-9)
    assert len(list((tmp_path / "compliance").glob("*.npz"))) == 2


@pytest.mark.slow  # seconds of numerics: make test, not make check
def test_tangent_compliance_at_an_inflated_state(coarse, tmp_path, monkeypatch):
    monkeypatch.setenv("PHANTOM_CACHE_DIR", str(tmp_path))
    rest = coarse.compliance().chamber_m3_per_pa
    state = coarse.equilibrium(np.array([4e3, 4e3, 4e3]))
    tangent = coarse.compliance(state)
    w = tangent.chamber_m3_per_pa
    # Central differences of full nonlinear solves: symmetric only if the model is conservative and the
    # solves converged (1e-11), to the O(step^2) difference error.
    assert np.abs(w - w.T).max() < 1e-3 * np.abs(w).max()
    assert np.abs(w / rest - 1)[np.diag_indices(3)].min() > 0.05  # inflated, the phantom's response has changed
    step = 40.0
    plus = coarse.equilibrium(state.pressures_pa + [step, 0, 0], initial_positions_m=state.positions_m)
    secant = (plus.chamber_volumes_m3 - state.chamber_volumes_m3) / step
    np.testing.assert_allclose(secant, w[:, 0], rtol=2e-2)


def test_the_fill_ordering_is_kept_on_disk_read_by_a_new_body_and_made_again_when_bad(tmp_path, monkeypatch):
    """CHOLMOD's ordering of a body's pattern is made once (phantom.cache_dir("orderings")): a new body of the same
    mesh reads it instead of ordering again and factorises to the same bits; a file that is not a permutation of
    the pattern's rows is not trusted but made again."""
    from phantom.model.fem import body as fem_body

    mesh = PhantomModel.from_scene(load_scene("builtin"), mesh_size_mm=8.0)   # (meshed in the shared cache)
    monkeypatch.setenv("PHANTOM_CACHE_DIR", str(tmp_path))

    def solved(rhs):
        body = mesh.with_material().body                                         # a new body of the mesh
        data = body.elastic(body.nodes_m, "linear", fem_body.POSITIVE_TANGENT, body.rest_constraints).tangent_data
        return body.factorize(data).solve(rhs)

    rhs = np.random.default_rng(4).normal(size=3 * len(mesh.nodes_m))
    first = solved(rhs)
    stored = list((tmp_path / "orderings").glob("*.npy"))
    assert len(stored) == 1
    ordering = fem_body.cholmod_ordering
    orderings = []

    def counted(matrix):
        orderings.append(matrix.shape)
        return ordering(matrix)

    monkeypatch.setattr(fem_body, "cholmod_ordering", counted)
    np.testing.assert_array_equal(solved(rhs), first)
    assert orderings == []
    np.save(stored[0], np.arange(10))
    np.testing.assert_array_equal(solved(rhs), first)
    assert orderings == [(len(rhs), len(rhs))] and len(np.load(stored[0])) == len(rhs)


def test_the_rest_factor_is_stored_read_back_for_any_modulus_and_made_again_when_damaged(tmp_path, monkeypatch):
    """The small-strain stiffness's factor is kept on disk as a folder of arrays, read back (mapped) by a new body
    and rescaled for another E; a damaged file is not trusted: the stiffness is factorised and stored again."""
    from phantom.model.fem.linsolve import CholeskyFactor, Factorization

    mesh = PhantomModel.from_scene(load_scene("builtin"), mesh_size_mm=8.0)   # (meshed in the shared cache)
    monkeypatch.setenv("PHANTOM_CACHE_DIR", str(tmp_path))

    def model(youngs_modulus_pa=None):
        return mesh.with_material(youngs_modulus_pa=youngs_modulus_pa)             # a new body of the mesh

    first = model()
    made = first.body.rest_factorization()
    assert isinstance(made, Factorization)
    stored = list((tmp_path / "factorizations").iterdir())
    assert len(stored) == 1 and stored[0].is_dir()
    rhs = np.random.default_rng(5).normal(size=3 * len(first.nodes_m))
    expected = made.solve(rhs)
    read = model(2 * first.material.youngs_modulus_pa).body.rest_factorization()
    assert isinstance(read, CholeskyFactor)
    np.testing.assert_allclose(read.solve(rhs), expected / 2, rtol=0, atol=1e-10 * np.abs(expected).max())
    (stored[0] / "values.npy").write_bytes(b"not an array")
    again = model().body.rest_factorization()
    assert isinstance(again, Factorization)
    np.testing.assert_allclose(again.solve(rhs), expected, rtol=0, atol=1e-12 * np.abs(expected).max())
    assert isinstance(model().body.rest_factorization(), CholeskyFactor)          # stored again


def central_differences(solve, pressures_pa, step_pa):
    """dV/dp (chamber (3, 3) and gland (3,), m^3/Pa) by central differences of ``solve(pressures) -> State``."""
    chamber, gland = np.empty((3, 3)), np.empty(3)
    for j in range(3):
        offset = np.zeros(3)
        offset[j] = step_pa
        plus, minus = solve(pressures_pa + offset), solve(pressures_pa - offset)
        chamber[:, j] = (plus.chamber_volumes_m3 - minus.chamber_volumes_m3) / (2 * step_pa)
        gland[j] = (plus.gland_volume_m3 - minus.gland_volume_m3) / (2 * step_pa)
    return chamber, gland


def test_tangent_compliance_of_a_linear_state_matches_finite_differences_of_full_solves(coarse, tmp_path,
                                                                                      monkeypatch):
    # The calibrated material: small strain, E = 2.6 kPa, so 2-3 kPa is p ~ E and the volume measure is far from
    # linear in the (exactly linear) displacement: the tangent differs from the rest compliance by tens of %.
    monkeypatch.setenv("PHANTOM_CACHE_DIR", str(tmp_path))
    linear = coarse.with_material(youngs_modulus_pa=2630.1, model="linear")
    pressures_pa = np.array([2500.0, 1500.0, 2000.0])
    state = linear.equilibrium(pressures_pa)
    tangent = linear.compliance(state)
    # The truth: central differences of full linear solves from rest. The volumes are cubic in the pressures, so
    # the difference error is O(step^2 * d3V/dp3): at a 5 Pa step about 1e-7 of the entries, and the solves
    # converge to 1e-9 of the load; 1e-5 leaves room for both and is 4 orders below the error being fixed.
    chamber, gland = central_differences(linear.equilibrium, pressures_pa, 5.0)
    scale = np.abs(chamber).max()
    assert np.abs(tangent.chamber_m3_per_pa - chamber).max() <= 1e-5 * scale
    np.testing.assert_allclose(tangent.gland_m3_per_pa, gland, rtol=1e-5)
    rest = linear.compliance().chamber_m3_per_pa
    assert np.abs(rest - chamber).max() > 0.2 * scale  # the state's tangent is not the rest compliance
    # The displacement per pascal is the rest one: the load is taken on the rest shape whatever the pressure.
    np.testing.assert_array_equal(tangent.displacement_m_per_pa, linear.compliance().displacement_m_per_pa)
    # A linear solve started elsewhere takes its load on that start; its tangent follows (same truth).
    start_m = state.positions_m
    moved = linear.equilibrium(pressures_pa, initial_positions_m=start_m)
    np.testing.assert_array_equal(moved.load_positions_m, start_m)
    chamber, _ = central_differences(lambda p: linear.equilibrium(p, initial_positions_m=start_m), pressures_pa, 5.0)
    assert np.abs(linear.compliance(moved).chamber_m3_per_pa - chamber).max() <= 1e-5 * np.abs(chamber).max()


def test_bad_pressures_and_options_are_refused(coarse):
    with pytest.raises(SolveError, match="expected 3 chamber pressures"):
        coarse.equilibrium([1e3, 1e3])
    with pytest.raises(SolveError, match="finite"):
        coarse.equilibrium([1e3, float("nan"), 0])
    with pytest.raises(SolveError, match="unknown formulation"):
        coarse.equilibrium([0, 0, 0], formulation="hyperelastic")
    with pytest.raises(SolveError, match="initial_positions_m"):
        coarse.equilibrium([0, 0, 0], initial_positions_m=np.zeros((3, 3)))


@pytest.mark.slow
def test_a_pressure_beyond_the_limit_point_names_the_chamber(coarse):
    pressure_pa = 2.0 * coarse.material.youngs_modulus_pa
    with pytest.raises(SolveError) as error:
        coarse.equilibrium([0, pressure_pa, 0])
    message = str(error.value)
    assert "'chamber1' at 100 kPa" in message and "try a lower pressure" in message


def test_zero_pressure_is_the_rest_state(coarse):
    state = coarse.equilibrium([0, 0, 0])
    np.testing.assert_array_equal(state.positions_m, coarse.nodes_m)
    assert state.iterations == 0


def test_mesh_size_applies_to_the_builtin_mesh_only(tmp_path):
    (tmp_path / "s.toml").write_text('[phantom]\nmesh = "m.msh"\nchambers = ["c"]\n')
    with pytest.raises(MeshError, match="built-in mesh only"):
        PhantomModel.from_scene(load_scene(tmp_path / "s.toml"), mesh_size_mm=2.0)


def run_phantom(*arguments):
    return subprocess.run([str(PHANTOM), *arguments], capture_output=True, text=True, timeout=300)


@pytest.mark.slow
def test_forward_command_json_and_table(model):
    result = run_phantom("forward", "--scene", "builtin", "--pressures-kpa", "1,0.5,0", "--json")
    assert result.returncode == 0, result.stderr
    answer = json.loads(result.stdout)
    state = model.equilibrium([1e3, 0.5e3, 0])
    assert answer["chamber_volumes_ml"] == pytest.approx(list(state.chamber_volumes_m3 * 1e6), rel=1e-12)
    assert answer["total_volume_ml"] == pytest.approx(state.gland_volume_m3 * 1e6, rel=1e-12)
    assert answer["iterations"] == state.iterations and answer["solve_time_s"] > 0
    table = run_phantom("forward", "--scene", "builtin", "--pressures-kpa", "1,0.5,0")
    assert table.returncode == 0
    assert "gland" in table.stdout and "Newton iterations" in table.stdout


@pytest.mark.parametrize(("pressures", "message"), [("1,1", "has 2 values; the scene has 3 chambers (0 base, 1 left "
                                                                      "lobe, 2 right lobe)"),
                                                    ("1,x,1", "'x' is not a number")])
def test_forward_command_refuses_bad_pressures(pressures, message):
    result = run_phantom("forward", "--scene", "builtin", "--pressures-kpa", pressures)
    assert result.returncode == 2 and message in result.stderr


def test_forward_command_reports_a_missing_scene(tmp_path):
    result = run_phantom("forward", "--scene", str(tmp_path / "none.toml"), "--pressures-kpa", "1")
    assert result.returncode == 2
    assert result.stderr.strip().count("\n") == 0 and "does not exist" in result.stderr


@pytest.mark.parametrize("pressures_kpa", ["1e-6,0,0", "2e-12,0,2e-12"])
def test_pressures_below_the_resolution_answer_the_rest_shape(model, pressures_kpa):
    """phantom forward --pressures-kpa 1e-6,0,0 failed "the stiffness is ill-conditioned" (Newton's tolerance is
    relative to the load); the simulated plant reads +-2e-12 kPa after a vent (the command refuses a negative
    pressure as the daemon does; the model, which the plant's truth calls, takes it as zero)."""
    result = run_phantom("forward", "--scene", "builtin", "--pressures-kpa", pressures_kpa, "--json")
    assert result.returncode == 0, result.stderr
    answer = json.loads(result.stdout)
    assert answer["chamber_volumes_ml"] == pytest.approx(list(model.rest_chamber_volumes_m3 * 1e6), rel=1e-12)
    assert answer["iterations"] == 0
    vented = model.equilibrium([2e-9, -2e-9, 0.0])
    assert vented.iterations == 0
    np.testing.assert_array_equal(vented.chamber_volumes_m3, model.rest_chamber_volumes_m3)
    # at the resolution the load is solved, and gives a larger chamber
    assert model.pressure_resolution_pa == pytest.approx(0.5)  # 1e-5 of the built-in scene's 50 kPa
    state = model.equilibrium([model.pressure_resolution_pa, 0.0, 0.0])
    assert state.iterations > 0 and state.chamber_volumes_m3[0] > model.rest_chamber_volumes_m3[0]
