"""The response table (the ``table`` fidelity): full solves on a grid over the operating box, interpolated.

Every check compares the interpolant with full solves it was not built from (off-grid pressures), with the
tolerance stated where it is used. The small tests use the built-in co-rotational scene on a coarse mesh,
whose response is mildly nonlinear; the slow ones the 4-node calibration (`builtin:calibrated`, Gent, 4 mm).
"""

import logging

import numpy as np
import pytest

from phantom import PhantomError
from phantom.model import PhantomModel, SceneError, load_scene
from phantom.model.fidelity.levels import VolumeEstimator
from phantom.model.fidelity.response_table import (
    SHIPPED_MODES_TOLERANCE_M,
    SHIPPED_NODE_TOLERANCE_M,
    ResponseTableError,
    _line_before,
    _predecessor,
    build_response_table,
    build_table_shapes,
    grid_pa,
    response_table,
    write_table_shapes,
    write_table_volumes,
)
from phantom.model.inverse import InverseSolver
from phantom.model.target import Target, UnreachableTargetError

COARSE_MM = 8.0
PRESSURE_MAX_PA = 3000.0
OFF_GRID_PA = np.array([[300.0, 2700.0, 1300.0], [2200.0, 700.0, 1900.0], [1700.0, 1700.0, 400.0]])


@pytest.fixture(scope="module")
def model():
    return PhantomModel.from_scene(load_scene("builtin"), mesh_size_mm=COARSE_MM)


@pytest.fixture(scope="module")
def table(model):
    return build_response_table(model, PRESSURE_MAX_PA, points_per_axis=4, workers=1)


def _growth_errors(model, table, pressures_pa):
    """|table - full solve| / the full solve's growth from rest, gland and each chamber, at one pressure set."""
    state = model.equilibrium(pressures_pa)
    chambers, gland = table.volumes(pressures_pa)
    exact = np.append(state.chamber_volumes_m3, state.gland_volume_m3)
    rest = np.append(model.rest_chamber_volumes_m3, model.rest_gland_volume_m3)
    return np.abs(np.append(chambers, gland) - exact) / np.abs(exact - rest), state


@pytest.mark.slow
def test_the_table_matches_full_solves_between_its_grid_points(model, table):
    # a cubic spline through 1 kPa steps of a mildly nonlinear response: well under 0.5 % of each growth (a
    # wrong grid index or spline weight would be off by tens of %)
    for pressures_pa in OFF_GRID_PA:
        errors, state = _growth_errors(model, table, pressures_pa)
        assert errors.max() < 5e-3, (pressures_pa, errors)
        # the shape too: within 1 % of the largest displacement
        displacement = np.abs(state.positions_m - model.nodes_m).max()
        assert np.abs(table.positions_m(pressures_pa) - state.positions_m).max() < 1e-2 * displacement
    assert 0 < table.check_errors_pct < 0.5 and table.build_time_s > 0


@pytest.mark.slow
def test_the_tables_gradient_is_the_models_tangent_compliance(model, table):
    pressures_pa = OFF_GRID_PA[1]
    tangent = model.compliance(model.equilibrium(pressures_pa))
    chamber, gland = table.compliance(pressures_pa)
    # the derivative of a cubic spline converges an order slower than its values: 3 % of the largest entry
    np.testing.assert_allclose(chamber, tangent.chamber_m3_per_pa, atol=3e-2 * np.abs(tangent.chamber_m3_per_pa).max())
    np.testing.assert_allclose(gland, tangent.gland_m3_per_pa, rtol=3e-2)


@pytest.mark.slow
def test_beyond_the_box_the_table_extends_linearly_not_as_a_cubic(model, table):
    # an overshoot of 200 Pa above the limit on one chamber: the tangent's extension misses the full solve by the
    # curvature's second-order term only
    pressures_pa = np.array([PRESSURE_MAX_PA + 200.0, 1000.0, 500.0])
    errors, _ = _growth_errors(model, table, pressures_pa)
    assert errors.max() < 1e-2
    inside_chambers, _ = table.volumes([PRESSURE_MAX_PA, 1000.0, 500.0])
    slope, _ = table.compliance([PRESSURE_MAX_PA, 1000.0, 500.0])
    chambers, _ = table.volumes(pressures_pa)
    np.testing.assert_allclose(chambers, inside_chambers + 200.0 * slope[:, 0], rtol=1e-12)


@pytest.mark.slow
def test_a_lookup_forms_each_chambers_weights_once_and_they_are_the_tensor_splines(table):
    # The weights and slopes of one lookup, from the splines' coefficients, are scipy's value and derivative of
    # the same tensor spline, on the grid's points, between them and at the box's top edge.
    from scipy.interpolate import CubicSpline

    points = table.points_per_axis
    splines = CubicSpline(np.arange(points, dtype=float), np.eye(points))
    for pressures_pa in ([0.0, 1000.0, 3000.0], [299.0, 2999.9, 1500.5], [3000.0, 3000.0, 0.0]):
        bases, excess = table._bases(np.array(pressures_pa))
        assert not np.any(excess)
        for (weights, slopes), pressure in zip(bases, pressures_pa, strict=True):
            x = (points - 1) * pressure / PRESSURE_MAX_PA
            np.testing.assert_allclose(weights, splines(x), atol=1e-12)
            np.testing.assert_allclose(slopes, splines(x, 1) * (points - 1) / PRESSURE_MAX_PA, atol=1e-15)
    calls = []
    original = table._bases
    try:
        object.__setattr__(table, "_bases", lambda pressures: calls.append(1) or original(pressures))
        table.volumes(OFF_GRID_PA[0])
    finally:
        object.__delattr__(table, "_bases")
    assert len(calls) == 1  # both quantities from one set of weights


@pytest.mark.slow  # seconds of solves (3-5 s CPU): make test runs it, make check does not
def test_a_table_is_built_once_and_then_read_from_the_cache(model, monkeypatch, tmp_path):
    monkeypatch.setenv("PHANTOM_CACHE_DIR", str(tmp_path))
    built = response_table(model, PRESSURE_MAX_PA, points_per_axis=2, workers=1)
    solves = []
    original = model.equilibrium
    monkeypatch.setattr(model, "equilibrium", lambda *args, **kwargs: solves.append(args) or original(*args, **kwargs))
    reported = []
    again = response_table(model, PRESSURE_MAX_PA, points_per_axis=2, workers=1,
                           progress=lambda *done: reported.append(done))
    assert solves == [] and reported == []
    np.testing.assert_array_equal(again.position_values, built.position_values)
    assert len(list((tmp_path / "response").glob("*.npz"))) == 1
    # another grid is another table
    response_table(model, PRESSURE_MAX_PA, points_per_axis=3, workers=1, progress=lambda *done: reported.append(done))
    assert reported[-1] == (27 + 4, 27 + 4) and len(solves) == 26 + 4


def test_a_model_that_has_factorised_with_cholmod_still_goes_to_a_worker_process(model, monkeypatch, tmp_path):
    # The table sends its model to worker processes; CHOLMOD's symbolic analysis, which the body keeps after its
    # first factorisation, and a rest factor made in this process (an empty cache, as on a fresh machine) cannot
    # be pickled (the Dask test below failed on a clean clone).
    import pickle

    monkeypatch.setenv("PHANTOM_CACHE_DIR", str(tmp_path))
    model.body._factorizations.clear()
    solved = model.equilibrium(np.array([1500.0, 1000.0, 500.0]))
    model.body.factorize(model.body.tangent_data())  # as a Newton step on the exact tangent does
    assert model.body._cholmod_analysis is not None
    copy = pickle.loads(pickle.dumps(model))
    again = copy.equilibrium(np.array([1500.0, 1000.0, 500.0]))
    assert again.chamber_volumes_m3 == pytest.approx(solved.chamber_volumes_m3, rel=1e-9)


@pytest.mark.slow
def test_points_as_dask_tasks_give_the_same_table(model, table, dask_scheduler, monkeypatch, tmp_path):
    # each point is solved from the same neighbour wherever it runs: the same table as in this process
    monkeypatch.setenv("PHANTOM_CACHE_DIR", str(tmp_path))
    spread = build_response_table(model, PRESSURE_MAX_PA, points_per_axis=4, scheduler=dask_scheduler)
    np.testing.assert_allclose(spread.position_values, table.position_values, rtol=0, atol=1e-12)
    np.testing.assert_allclose(spread.gland_values, table.gland_values, rtol=1e-12)
    assert spread.check_errors_pct == pytest.approx(table.check_errors_pct, rel=1e-9)
    assert not list(tmp_path.glob("response/*.points"))  # the solved points are dropped once the table is whole


def test_each_point_starts_from_a_neighbour_one_step_down_its_grid_line():
    assert _predecessor((0, 0, 0)) is None
    assert _predecessor((2, 0, 0)) == (1, 0, 0)
    assert _predecessor((2, 3, 0)) == (2, 2, 0)
    assert _predecessor((2, 3, 1)) == (2, 3, 0)
    assert _predecessor((0, 0, 4)) == (0, 0, 3)
    # every point reaches the origin, in at most n_chambers (n - 1) steps: the build's critical path
    for index in np.ndindex(5, 5, 5):
        steps = 0
        while index is not None:
            index, steps = _predecessor(index), steps + 1
        assert steps - 1 <= 3 * 4


def test_each_point_starts_from_up_to_three_points_down_its_grid_line_never_from_the_origin_it_left():
    # nearest first, along the axis to its predecessor: the points a quadratic predictor goes through
    assert _line_before((2, 3, 4), 3, True) == [(2, 3, 3), (2, 3, 2), (2, 3, 1)]
    assert _line_before((2, 3, 1), 3, True) == [(2, 3, 0)]
    assert _line_before((2, 3, 0), 2, True) == [(2, 2, 0), (2, 1, 0)]
    assert _line_before((0, 0, 2), 3, True) == [(0, 0, 1), (0, 0, 0)]
    # the rest shape is no equilibrium under a body force: not a point of the line then
    assert _line_before((0, 0, 2), 3, False) == [(0, 0, 1)]
    # a point next to the origin is solved from rest, and the origin has none
    assert _line_before((0, 1, 0), 3, True) == [] and _line_before((0, 0, 0), 3, True) == []


class _Killed(Exception):
    pass


@pytest.mark.slow  # seconds of solves (3-5 s CPU): make test runs it, make check does not
def test_a_killed_build_resumes_from_the_points_it_solved(model, monkeypatch, tmp_path):
    monkeypatch.setenv("PHANTOM_CACHE_DIR", str(tmp_path))
    whole = build_response_table(model, PRESSURE_MAX_PA, points_per_axis=3, workers=1)

    def kill_at_ten(done, total):
        if done == 10:
            raise _Killed

    with pytest.raises(_Killed):
        build_response_table(model, PRESSURE_MAX_PA, points_per_axis=3, workers=1, progress=kill_at_ten)
    folder, = (tmp_path / "response").glob("*.points")
    assert len(list(folder.glob("point-*.npz"))) == 9  # the origin is the model at rest: no file, no solve
    (folder / "point-0-0-2.npz").write_bytes(b"half a file")  # damaged: solved again
    solves = counted_solves(model, monkeypatch)
    reported = []
    resumed = build_response_table(model, PRESSURE_MAX_PA, points_per_axis=3, workers=1,
                                   progress=lambda *done: reported.append(done))
    assert reported[0] == (9, 27 + 4) and reported[-1] == (27 + 4, 27 + 4)
    assert len(solves) == 27 - 9 + 4  # the points not stored (one damaged), and the checks
    np.testing.assert_allclose(resumed.position_values, whole.position_values, rtol=0, atol=1e-12)
    assert not folder.exists()


@pytest.mark.slow
def test_a_worker_lost_mid_build_is_retried_not_fatal(model, table, monkeypatch, tmp_path):
    import os
    import signal

    from phantom.model.cluster import local_cluster

    monkeypatch.setenv("PHANTOM_CACHE_DIR", str(tmp_path))
    cluster = local_cluster(2)
    killed = []

    def kill_a_worker(done, total):
        if done == 8 and not killed:  # the grid lines have branched: both workers hold tasks and results
            process = next(iter(cluster.workers.values())).process.process
            killed.append(process.pid)
            os.kill(process.pid, signal.SIGKILL)

    try:
        rebuilt = build_response_table(model, PRESSURE_MAX_PA, points_per_axis=4, progress=kill_a_worker,
                                       scheduler=cluster.scheduler_address)
    finally:
        cluster.close()
    assert killed
    np.testing.assert_allclose(rebuilt.position_values, table.position_values, rtol=0, atol=1e-12)


@pytest.mark.slow
def test_a_script_without_a_main_guard_still_gets_its_table(tmp_path):
    # a spawned worker re-runs the calling script, which then dies trying to spawn its own: the build goes on
    # in the script's process, and says why
    import subprocess
    import sys

    script = tmp_path / "unguarded.py"
    script.write_text("from phantom.model import PhantomModel, load_scene\n"
                      "from phantom.model.fidelity.response_table import build_response_table\n"
                      f"model = PhantomModel.from_scene(load_scene('builtin'), mesh_size_mm={COARSE_MM})\n"
                      "table = build_response_table(model, 3000.0, points_per_axis=2, workers=2)\n"
                      "print('gland at 3 kPa', table.volumes([3000.0] * 3)[1])\n")
    result = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=240,
                            cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    assert "gland at 3 kPa" in result.stdout
    assert "worker processes could not start" in result.stderr


def test_bad_grids_are_refused(model):
    assert grid_pa(3000.0, 7)[[0, 1, -1]] == pytest.approx([0.0, 500.0, 3000.0])
    with pytest.raises(ResponseTableError, match="at least 2 points"):
        build_response_table(model, PRESSURE_MAX_PA, points_per_axis=1)
    with pytest.raises(ResponseTableError, match="positive number of Pa"):
        build_response_table(model, -1.0)


@pytest.mark.slow  # two worker processes start for eight solves
def test_an_inaccurate_table_is_refused_with_what_to_do(monkeypatch, tmp_path):
    # two points per axis: trilinear in the pressures, which misses the volume measure's curvature by far more
    # than the 0.001 % asked for
    monkeypatch.setenv("PHANTOM_CACHE_DIR", str(tmp_path))
    scene_path = tmp_path / "coarse_table.toml"
    scene_path.write_text(load_scene("builtin").path.read_text().replace(
        "accuracy_pct = 10.0", 'fidelity = "table"\ntable_points = 2\naccuracy_pct = 0.001'))
    coarse = PhantomModel.from_scene(load_scene(scene_path), mesh_size_mm=COARSE_MM)
    with pytest.raises(PhantomError, match=r"misses the full solve by .* raise \[model\] table_points"):
        VolumeEstimator(coarse)


# --- the 4-node calibration, whose table's volumes and shapes ship with it -----------------------------------

@pytest.fixture(scope="module")
def calibrated(tmp_path_factory):
    """The 4-node calibration and its estimator, on the table its scene ships (as on a machine that never built
    one: a table in this machine's cache would be read first)."""
    from phantom.model.fidelity import response_table

    model = PhantomModel.from_scene(load_scene("builtin:calibrated"))
    not_built = tmp_path_factory.mktemp("cache") / "none.npz"
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(response_table, "_cache_path", lambda *args: not_built)
        return model, VolumeEstimator(model)


@pytest.mark.slow
def test_the_calibrated_scene_answers_from_its_table_within_a_tenth_of_a_percent(calibrated):
    model, estimator = calibrated
    # the volumes shipped with the scene (no nodes' positions) and its outer surface's shapes, not a build
    assert estimator.level == "table" and estimator.table.position_values is None and estimator.shapes is not None
    used, _ = model.outer_surface()
    rng = np.random.default_rng(12)
    # Tolerance: 0.5 % of each growth and 0.1 % of the gland volume (the daemon's step tolerance is 1 %); the
    # outer surface between the shapes' 1 kPa grid points within three times their check's error (0.15 mm).
    for pressures_pa in rng.uniform(0.0, PRESSURE_MAX_PA, size=(3, 3)):
        errors, state = _growth_errors(model, estimator.table, pressures_pa)
        assert errors.max() < 5e-3, (pressures_pa, errors)
        _, gland = estimator.volumes(pressures_pa)
        assert gland == pytest.approx(state.gland_volume_m3, rel=1e-3)
        off_m = np.linalg.norm(estimator.shape(pressures_pa, nodes=used) - state.positions_m[used], axis=1)
        moved_m = np.linalg.norm(state.positions_m[used] - model.nodes_m[used], axis=1)
        assert off_m.max() < 3 * estimator.shapes.check_error_m and moved_m.max() > 1e-3, (off_m.max(), moved_m.max())
    assert estimator.counts["full_solves"] == 0


@pytest.mark.slow
@pytest.mark.parametrize("volume_ml", [26.0, 30.0, 33.0, 35.0, 40.0, 42.43, 43.0])
def test_the_inverse_on_the_table_reaches_the_bph_targets_checked_by_full_solves(calibrated, volume_ml):
    model, estimator = calibrated
    result = InverseSolver(model, estimator=estimator).pressures_for(Target(gland_volume_m3=volume_ml * 1e-6))
    assert np.all(result.pressures_pa >= 0) and np.all(result.pressures_pa <= PRESSURE_MAX_PA)
    forward = model.equilibrium(result.pressures_pa)
    # the table's error, 0.1 % of the volume
    assert forward.gland_volume_m3 * 1e6 == pytest.approx(volume_ml, rel=1e-3)


@pytest.mark.slow
def test_the_paper_s_45_ml_is_out_of_the_calibrated_model_s_reach(calibrated):
    model, estimator = calibrated
    with pytest.raises(UnreachableTargetError, match=r"45\.000 ml is unreachable.* give 25\.9\d* to 43\.7\d* ml"):
        InverseSolver(model, estimator=estimator).pressures_for(Target(gland_volume_m3=45e-6))


# --- table volumes shipped with a scene -----------------------------------------------------------------------

def counted_solves(model, monkeypatch):
    """A list that gets the arguments of each of ``model``'s full solves from now on."""
    solves = []
    original = model.equilibrium
    monkeypatch.setattr(model, "equilibrium", lambda *args, **kwargs: solves.append(args) or original(*args, **kwargs))
    return solves


def _shipping_scene(tmp_path, built, model, volumes_name="volumes.npz", material_line="youngs_modulus_kpa = 50.0"):
    """A copy of the built-in scene on the table level that ships ``built``'s volumes (written for ``model``)."""
    write_table_volumes(built, model, tmp_path / volumes_name)
    scene_path = tmp_path / "shipping.toml"
    scene_path.write_text(load_scene("builtin").path.read_text().replace(
        "youngs_modulus_kpa = 50.0", material_line).replace(
        "accuracy_pct = 10.0", f'fidelity = "table"\ntable_points = 2\naccuracy_pct = 50\n'
                               f'table_volumes = "{volumes_name}"'))
    return scene_path


@pytest.mark.slow  # seconds of numerics: make test, not make check
def test_shipped_table_volumes_answer_without_a_build_and_their_shapes_are_solved(model, monkeypatch, tmp_path):
    monkeypatch.setenv("PHANTOM_CACHE_DIR", str(tmp_path / "cache"))
    built = build_response_table(model, PRESSURE_MAX_PA, points_per_axis=2, workers=1)
    shipping = PhantomModel.from_scene(load_scene(_shipping_scene(tmp_path, built, model)), mesh_size_mm=COARSE_MM)
    solves = counted_solves(shipping, monkeypatch)
    estimator = VolumeEstimator(shipping)
    assert solves == [] and not list((tmp_path / "cache").glob("response/*"))  # nothing built, nothing stored
    assert estimator.level == "table" and estimator.table.position_values is None
    assert estimator.table.check_errors_pct == built.check_errors_pct
    for pressures_pa in OFF_GRID_PA:
        chambers, gland = estimator.volumes(pressures_pa)
        assert gland == pytest.approx(built.volumes(pressures_pa)[1], rel=1e-12)
        np.testing.assert_allclose(chambers, built.volumes(pressures_pa)[0], rtol=1e-12)
    # no positions are shipped: a shape is a full solve
    with pytest.raises(ResponseTableError, match="volumes only"):
        estimator.table.positions_m(OFF_GRID_PA[0])
    shape = estimator.shape(OFF_GRID_PA[0])
    assert len(solves) == 1 and estimator.counts["full_solves"] == 1
    np.testing.assert_allclose(shape, model.equilibrium(OFF_GRID_PA[0]).positions_m, rtol=0, atol=1e-12)


@pytest.mark.slow  # seconds of solves (3-5 s CPU): make test runs it, make check does not
def test_shipped_table_volumes_of_another_model_are_refused_with_what_differs(model, monkeypatch, tmp_path):
    monkeypatch.setenv("PHANTOM_CACHE_DIR", str(tmp_path / "cache"))
    built = build_response_table(model, PRESSURE_MAX_PA, points_per_axis=2, workers=1)
    remedy = r"use a copy of the scene without \[model\] table_volumes"
    # another modulus in the scene that names them
    stiffer = load_scene(_shipping_scene(tmp_path, built, model, material_line="youngs_modulus_kpa = 60.0"))
    with pytest.raises(ResponseTableError, match=r"belong to another model \(material.youngs_modulus_pa: made for "
                                                 r"50000.0, this model has 60000.0\): " + remedy):
        VolumeEstimator(PhantomModel.from_scene(stiffer, mesh_size_mm=COARSE_MM))
    # another mesh size
    scene = load_scene(_shipping_scene(tmp_path, built, model))
    with pytest.raises(ResponseTableError, match=r"\(geometry.mesh_size_mm: made for 8.0, this model has 10.0\)"):
        VolumeEstimator(PhantomModel.from_scene(scene, mesh_size_mm=10.0))
    # another table size
    with pytest.raises(ResponseTableError, match=r"points_per_axis: made for 2, this model has 3"):
        response_table(PhantomModel.from_scene(scene, mesh_size_mm=COARSE_MM), PRESSURE_MAX_PA, points_per_axis=3)
    # the same settings meshed otherwise: rest volumes 1 % apart
    path = tmp_path / "volumes.npz"
    with np.load(path) as stored:
        fields = dict(stored)
    np.savez(path, **{**fields, "rest_volumes_m3": fields["rest_volumes_m3"] * 1.01})
    with pytest.raises(ResponseTableError, match=r"rest volumes are up to 0.99 % from this one's .* the mesher made "
                                                 r"another mesh"):
        VolumeEstimator(PhantomModel.from_scene(scene, mesh_size_mm=COARSE_MM))
    path.write_bytes(b"not an npz")
    with pytest.raises(SceneError, match=r"volumes.npz \(\[model\] table_volumes\) is damaged .*" + remedy):
        VolumeEstimator(PhantomModel.from_scene(scene, mesh_size_mm=COARSE_MM))


# --- the outer surface's shapes shipped with a scene ----------------------------------------------------------

def _shapes_scene(tmp_path, model, shapes):
    """A copy of the built-in scene on the table level that ships a 2-point table's volumes and ``shapes``."""
    write_table_shapes(shapes, model, tmp_path / "shapes.npz")
    scene_path = _shipping_scene(tmp_path, build_response_table(model, PRESSURE_MAX_PA, 2, workers=1), model)
    scene_path.write_text(scene_path.read_text().replace('table_volumes = "volumes.npz"',
                                                         'table_volumes = "volumes.npz"\ntable_shapes = "shapes.npz"'))
    return scene_path


@pytest.mark.slow  # seconds of solves (3-5 s CPU): make test runs it, make check does not
def test_shipped_shapes_answer_the_outer_surface_without_a_solve_and_other_nodes_are_solved(model, monkeypatch,
                                                                                               tmp_path):
    monkeypatch.setenv("PHANTOM_CACHE_DIR", str(tmp_path / "cache"))
    shapes = build_table_shapes(model, PRESSURE_MAX_PA, points_per_axis=3, workers=1)
    surface, _ = model.outer_surface()
    np.testing.assert_array_equal(shapes.nodes, surface)
    # the build's check: interpolated between 1.5 kPa steps, a full solve's surface is a little elsewhere
    assert 0 < shapes.check_error_m < 0.05 * np.abs(model.equilibrium(
        [PRESSURE_MAX_PA] * 3).positions_m - model.nodes_m).max()
    shipping = PhantomModel.from_scene(load_scene(_shapes_scene(tmp_path, model, shapes)), mesh_size_mm=COARSE_MM)
    solves = counted_solves(shipping, monkeypatch)
    estimator = VolumeEstimator(shipping)
    # the check error written bounds the modes' error too
    assert estimator.shapes is not None
    assert shapes.check_error_m <= estimator.shapes.check_error_m <= shapes.check_error_m + SHIPPED_MODES_TOLERANCE_M
    for pressures_pa in OFF_GRID_PA:
        # the shipped displacements are their leading singular modes, within their tolerance at the grid points
        np.testing.assert_allclose(estimator.shape(pressures_pa, nodes=surface),
                                   shapes.table.positions_m(pressures_pa), rtol=0, atol=SHIPPED_MODES_TOLERANCE_M)
        # a subset of the surface is the same nodes' rows
        np.testing.assert_allclose(estimator.shape(pressures_pa, nodes=surface[::7]),
                                   estimator.shape(pressures_pa, nodes=surface)[::7], rtol=0, atol=1e-15)
    assert solves == [] and estimator.counts["full_solves"] == 0
    # against a full solve between the grid's points: within a few times the check error written (the build's
    # and the modes')
    state = model.equilibrium(OFF_GRID_PA[1])
    off_m = np.linalg.norm(estimator.shape(OFF_GRID_PA[1], nodes=surface) - state.positions_m[surface], axis=1)
    assert off_m.max() < 3 * estimator.shapes.check_error_m
    # a node inside the body, or every node, is not shipped: a full solve
    inside = np.setdiff1d(np.arange(len(model.nodes_m)), surface)[:5]
    np.testing.assert_allclose(estimator.shape(OFF_GRID_PA[0], nodes=inside),
                               model.equilibrium(OFF_GRID_PA[0]).positions_m[inside], rtol=0, atol=1e-12)
    assert len(solves) == 1
    assert estimator.shape(OFF_GRID_PA[0]).shape == model.nodes_m.shape and len(solves) == 1  # the state kept


@pytest.mark.slow  # seconds of solves (3-5 s CPU): make test runs it, make check does not
def test_shipped_shapes_of_another_mesh_are_solved_and_of_another_model_refused(model, monkeypatch, tmp_path,
                                                                                caplog):
    monkeypatch.setenv("PHANTOM_CACHE_DIR", str(tmp_path / "cache"))
    shapes = build_table_shapes(model, PRESSURE_MAX_PA, points_per_axis=2, workers=1)
    scene = load_scene(_shapes_scene(tmp_path, model, shapes))
    remedy = r"use a copy of the scene without \[model\] table_shapes \(each shape is then a full solve\)"
    path = tmp_path / "shapes.npz"
    with np.load(path) as stored:
        fields = dict(stored)
    # the same settings meshed otherwise (another gmsh release): the same volumes, the nodes elsewhere; the model
    # is the same, so it starts, says so, and solves its shapes
    moved = fields["rest_positions_m"].copy()
    moved[3] += 10 * SHIPPED_NODE_TOLERANCE_M
    np.savez(path, **{**fields, "rest_positions_m": moved})
    with caplog.at_level(logging.WARNING, logger="phantom.model.fidelity.response_table"):
        estimator = VolumeEstimator(PhantomModel.from_scene(scene, mesh_size_mm=COARSE_MM))
    assert estimator.level == "table" and estimator.shapes is None
    assert any("name nodes this mesh does not have where they were" in record.getMessage()
               and "each shape is a full solve" in record.getMessage() for record in caplog.records)
    # made for another pressure box
    provenance = str(fields["provenance"]).replace('"pressure_max_pa": 3000.0', '"pressure_max_pa": 2000.0')
    np.savez(path, **{**fields, "provenance": provenance})
    with pytest.raises(ResponseTableError, match=r"table shapes .* belong to another model \(pressure_max_pa: made "
                                                 r"for 2000.0, this model has 3000.0\): " + remedy):
        VolumeEstimator(PhantomModel.from_scene(scene, mesh_size_mm=COARSE_MM))
    # a file without the shapes' arrays
    np.savez(path, **{key: value for key, value in fields.items() if key != "modes_m"})
    with pytest.raises(SceneError, match=r"is damaged \(it has no array 'modes_m'\)"):
        VolumeEstimator(PhantomModel.from_scene(scene, mesh_size_mm=COARSE_MM))


# --- the build as a command, and the truth plant's build, on a LocalCluster ------------------------------------

def _coarse_scene(tmp_path, table_points):
    """The built-in scene on the coarse mesh with a ``table_points`` grid, as a file."""
    scene_path = tmp_path / "coarse.toml"
    scene_path.write_text(load_scene("builtin").path.read_text().replace(
        "accuracy_pct = 10.0", f"table_points = {table_points}\naccuracy_pct = 10.0")
        + f"\n[geometry]\nmesh_size_mm = {COARSE_MM}\n")
    return scene_path


@pytest.mark.slow
def test_phantom_model_table_writes_the_volumes_and_the_shapes_of_one_pass_on_a_cluster(tmp_path, monkeypatch,
                                                                                      dask_scheduler, capsys):
    from phantom.cli import main as cli
    from phantom.model.fidelity.response_table import shipped_table_shapes, shipped_table_volumes

    monkeypatch.setenv("PHANTOM_CACHE_DIR", str(tmp_path / "cache"))
    scene_path = _coarse_scene(tmp_path, 4)  # 4 points per axis: the shipped shapes' grid is the table's
    assert cli.main(["model", "table", str(scene_path), "--out", str(tmp_path / "out" / "volumes.npz"),
                     "--shapes-out", str(tmp_path / "out" / "shapes.npz"), "--scheduler", dask_scheduler]) == 0
    printed = capsys.readouterr()
    assert "wrote" in printed.out and "4^3 points" in printed.out
    # one build: the table's 64 points and checks; the shapes only their checks, which no bar counts
    assert "shapes: full solves" not in printed.err and "68/68" in printed.err.replace("\r", "\n")
    shipping = tmp_path / "shipping.toml"
    shipping.write_text(scene_path.read_text().replace(
        "table_points = 4", 'table_points = 4\ntable_volumes = "out/volumes.npz"\ntable_shapes = "out/shapes.npz"'))
    model = PhantomModel.from_scene(load_scene(shipping))
    volumes = shipped_table_volumes(model, PRESSURE_MAX_PA, 4)
    shapes = shipped_table_shapes(model, PRESSURE_MAX_PA)
    assert volumes is not None and shapes is not None and shapes.table.points_per_axis == 4
    state = model.equilibrium(OFF_GRID_PA[0])
    assert volumes.volumes(OFF_GRID_PA[0])[1] == pytest.approx(state.gland_volume_m3, rel=5e-3)
    np.testing.assert_allclose(shapes.table.gland_values, volumes.gland_values, rtol=1e-12)  # the same solves


def test_phantom_model_table_refuses_a_command_that_writes_nothing_or_has_no_worker(tmp_path, capsys):
    from phantom.cli import main as cli

    assert cli.main(["model", "table", "builtin"]) == 2
    assert "needs --out, --shapes-out or both" in capsys.readouterr().err
    assert cli.main(["model", "table", "builtin", "--out", str(tmp_path / "v.npz"), "--workers", "0"]) == 2
    assert "--workers must be at least 1, got 0" in capsys.readouterr().err
    with pytest.raises(SystemExit):  # argparse: one of the two
        cli.main(["model", "table", "builtin", "--out", "v.npz", "--workers", "2", "--scheduler", "tcp://x:1"])


@pytest.mark.slow
def test_phantom_hil_plant_builds_the_truth_on_the_cluster_at_scheduler(tmp_path, monkeypatch, dask_scheduler):
    import shutil

    import dask
    from dask.distributed import Client, get_task_stream

    from phantom.cli import main as cli
    from phantom.hil.plant import DEFAULT_PLANT_PATH, TRUTH_POINTS_KPA, WRITTEN_DIGITS, load_plant

    monkeypatch.setenv("PHANTOM_CACHE_DIR", str(tmp_path))
    scene_path = _coarse_scene(tmp_path, 4)
    plant_path = tmp_path / "plant.toml"
    shutil.copy(DEFAULT_PLANT_PATH, plant_path)
    assert cli.main(["hil", "plant", "--truth-from-scene", str(scene_path), "--truth-modulus-factor", "1.5",
                     "--scheduler", "tcp://x:1", "--workers", "2", "--plant", str(plant_path)]) == 2
    # the command leaves Dask's configuration as it was (it set scheduler-address for the whole process)
    assert dask.config.get("scheduler-address", None) is None
    with Client(dask_scheduler) as client, get_task_stream(client) as tasks:
        assert cli.main(["hil", "plant", "--truth-from-scene", str(scene_path), "--truth-modulus-factor", "1.5",
                         "--scheduler", dask_scheduler, "--plant", str(plant_path)]) == 0
    n = len(TRUTH_POINTS_KPA)
    assert sum(str(task["key"]).startswith("table-point") for task in tasks.data) >= n**3 - 1  # retries count too
    truth = load_plant(plant_path)
    # the truth is the scene at 1.5 x E: its state at p is the scene's at p / 1.5 (the stiffness scales with E)
    pressures_kpa = np.array([TRUTH_POINTS_KPA[-1], TRUTH_POINTS_KPA[1], TRUTH_POINTS_KPA[2]])
    state = PhantomModel.from_scene(load_scene(scene_path)).equilibrium(1e3 * pressures_kpa / 1.5)
    assert truth.truth_gland_volume_m3 is not None
    # to the digits the plant file keeps (WRITTEN_DIGITS significant: half a unit of the last one)
    assert truth.truth_gland_volume_m3[n - 1, 1, 2] == pytest.approx(state.gland_volume_m3,
                                                                    rel=0.5 * 10.0 ** (1 - WRITTEN_DIGITS))
