"""Sweeps: stretch measures against a homogeneous deformation, traces on a two-worker LocalCluster against
direct solves, the on-disk cache, and a missing scheduler."""

import numpy as np
import pytest

from phantom.model import PhantomModel
from phantom.model.calibration.sweep import RayTask, element_stretch_measures, run_sweep
from phantom.model.cluster import ClusterError

SCENE_RAW = {"phantom": {"mesh": "builtin:prostate", "units": "mm", "chambers": ["chamber0", "chamber1", "chamber2"],
                         "fixed": "fixed"},
             "material": {"model": "neo_hookean", "youngs_modulus_kpa": 20.0, "poisson_ratio": 0.45},
             "geometry": {"mesh_size_mm": 6.0}}


def test_stretch_measures_of_a_homogeneous_deformation_are_exact():
    rng = np.random.default_rng(0)
    rotation = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    rotation *= np.sign(np.linalg.det(rotation))
    stretches = np.array([0.7, 1.2, 1.9])
    deformation = np.broadcast_to(rotation @ np.diag(stretches), (5, 4, 3, 3))
    min_det, low, high, i1_minus_3 = element_stretch_measures(deformation)
    assert min_det == pytest.approx(np.prod(stretches), rel=1e-10)
    assert (low, high) == pytest.approx((0.7, 1.9), rel=1e-10)
    assert i1_minus_3 == pytest.approx(np.sum(stretches**2) - 3, rel=1e-10)


@pytest.mark.parametrize("order", [1, 2])
def test_the_measures_see_the_strain_where_the_law_is_evaluated(order):
    # A homogeneous stretch is seen by both element orders; a 10-node element bent by its mid-edge nodes alone
    # is strained at its quadrature points while its corners have not moved (the measures of a 10-node
    # calibration were its corners' until they let a Gent fit lock unseen, or refused one for a corner's strain).
    from phantom.model.fem.model import PhantomModel
    from phantom.model.mesh.prostate import generate_hollow_sphere
    from phantom.model.mesh.tetmesh import prepare_surfaces
    from phantom.model.scene import Material

    mesh = generate_hollow_sphere(10.0, 20.0, 8.0, element_order=order)
    model = PhantomModel(mesh, prepare_surfaces(mesh, ["cavity"], None, "sphere"), ["cavity"],
                         Material("neo_hookean", 50e3, 0.45))
    stretched = model.nodes_m * np.array([1.3, 1.0, 1 / 1.3])
    assert element_stretch_measures(model.body.deformation_gradients(stretched)) == pytest.approx(
        (1.0, 1 / 1.3, 1.3, 1.3**2 + 1.3**-2 - 2), rel=1e-9)
    if order == 2:
        bent = model.nodes_m.copy()
        mid_edge = np.unique(model.tets[:, 4:])
        bent[mid_edge] += np.array([0.0, 0.0, 0.5e-3])
        gradients = model.body.deformation_gradients(bent)
        assert gradients.shape == (len(model.tets), 4, 3, 3)
        low, high = element_stretch_measures(gradients)[1:3]
        assert high > 1.05 and low < 0.95


@pytest.mark.slow
def test_a_sweep_on_two_workers_matches_direct_solves_and_is_cached(tmp_path, monkeypatch, dask_scheduler):
    monkeypatch.setenv("PHANTOM_CACHE_DIR", str(tmp_path))
    tasks = [RayTask(SCENE_RAW, pressures, (0.0, 0.5, 1.0)) for pressures in
             ((1500.0, 0.0, 0.0), (0.0, 1500.0, 1500.0), (0.0, 0.0, 0.0))]
    seen = []
    traces = run_sweep(tasks, scheduler=dask_scheduler, progress=lambda done, total: seen.append((done, total)))
    assert seen[0] == (0, 3) and seen[-1] == (3, 3)
    model = PhantomModel.from_scene(_scene())
    for task, trace in zip(tasks, traces, strict=True):
        assert trace.stopped == "end"
        np.testing.assert_allclose(trace.load_factors, task.load_factors)
        # An independent solve from rest at the full load (the trace continued from t = 0.5).
        direct = model.equilibrium(np.asarray(task.pressures_pa))
        assert trace.gland_m3[-1] == pytest.approx(direct.gland_volume_m3, rel=1e-7)
        np.testing.assert_allclose(trace.chamber_m3[-1], direct.chamber_volumes_m3, rtol=1e-6)
        assert trace.min_det[0] == pytest.approx(1.0) and trace.max_stretch[-1] >= trace.max_stretch[1] >= 1.0
    # Cached: a second sweep needs no cluster at all (this address answers nothing).
    again = run_sweep(tasks, scheduler="tcp://127.0.0.1:9")
    np.testing.assert_array_equal(again[0].gland_m3, traces[0].gland_m3)


@pytest.mark.slow
def test_growth_stops_a_trace_and_a_missing_scheduler_is_one_line(tmp_path, monkeypatch, dask_scheduler):
    monkeypatch.setenv("PHANTOM_CACHE_DIR", str(tmp_path))
    task = RayTask(SCENE_RAW, (2000.0, 0.0, 0.0), (0.0, 0.5, 1.0, 1.5), stop_growth_m3=1e-9)
    trace, = run_sweep([task], scheduler=dask_scheduler)
    assert trace.stopped == "growth" and len(trace.load_factors) == 2
    other = RayTask(SCENE_RAW, (1000.0, 0.0, 0.0), (0.0, 1.0))
    with pytest.raises(ClusterError, match="no Dask scheduler answers at tcp://127.0.0.1:9") as raised:
        run_sweep([other], scheduler="tcp://127.0.0.1:9")
    assert "\n" not in str(raised.value)


def _scene():
    from phantom.model.scene import scene_from_dict

    return scene_from_dict(SCENE_RAW)
