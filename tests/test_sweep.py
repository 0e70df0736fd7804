"""Sweeps: stretch measures against a homogeneous deformation, traces on a two-worker LocalCluster against
direct solves, the on-disk cache, and a missing scheduler."""

import numpy as np
import pytest

from phantom.model import PhantomModel
from phantom.model.calibration.sweep import RayTask, SweepError, element_stretch_measures, local_cluster, run_sweep

SCENE_RAW = {"phantom": {"mesh": "builtin:prostate", "units": "mm", "chambers": ["chamber0", "chamber1", "chamber2"],
                         "fixed": "fixed"},
             "material": {"model": "neo_hookean", "youngs_modulus_kpa": 20.0, "poisson_ratio": 0.45},
             "geometry": {"mesh_size_mm": 6.0}}


@pytest.fixture(scope="module")
def dask_scheduler():
    cluster = local_cluster(2)
    yield cluster.scheduler_address
    cluster.close()


def test_stretch_measures_of_a_homogeneous_deformation_are_exact():
    rng = np.random.default_rng(0)
    nodes = rng.uniform(size=(40, 3))
    tets = np.array([[0, 1, 2, 3], [4, 5, 6, 7], [8, 9, 10, 11]])
    edges = nodes[tets[:, 1:]] - nodes[tets[:, :1]]
    rest_edge_inverse = np.linalg.inv(edges.transpose(0, 2, 1))
    rotation = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    rotation *= np.sign(np.linalg.det(rotation))
    stretches = np.array([0.7, 1.2, 1.9])
    deformed = nodes @ (rotation @ np.diag(stretches)).T
    min_det, low, high, i1_minus_3 = element_stretch_measures(deformed, tets, rest_edge_inverse)
    assert min_det == pytest.approx(np.prod(stretches), rel=1e-10)
    assert (low, high) == pytest.approx((0.7, 1.9), rel=1e-10)
    assert i1_minus_3 == pytest.approx(np.sum(stretches**2) - 3, rel=1e-10)
    # 10-node elements (a calibration of a 10-node scene crashed here): their corners, the first four nodes, carry
    # the affine part of the deformation
    quadratic_tets = np.column_stack([tets, np.arange(12, 30).reshape(3, 6)])
    assert element_stretch_measures(deformed, quadratic_tets, rest_edge_inverse) == pytest.approx(
        (min_det, low, high, i1_minus_3), rel=1e-12)


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
    with pytest.raises(SweepError, match="no Dask scheduler answers at tcp://127.0.0.1:9") as raised:
        run_sweep([other], scheduler="tcp://127.0.0.1:9")
    assert "\n" not in str(raised.value)


def _scene():
    from phantom.model.scene import scene_from_dict

    return scene_from_dict(SCENE_RAW)
