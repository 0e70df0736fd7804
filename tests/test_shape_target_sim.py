"""A gland as the daemon's target, on the simulated board (the real firmware in simavr): ``set_target`` with a
``shape`` (a mask on the daemon's machine, or a small mesh in the request), the Python client's ``set_shape``,
and a scene step's ``shape``; the shape inverse solved in the daemon's model worker, its answer held as
pressures."""

from __future__ import annotations

import numpy as np
import pytest
from daemon_rig import DaemonRig, calibrated_scene, wait_ready
from test_shape_inverse import lopsided_mask

import phantom
from phantom.host.client import DaemonClient

pytestmark = [pytest.mark.sim, pytest.mark.slow]


def ellipsoid_mesh(semi_axes_mm: tuple[float, float, float], subdivisions: int = 2) -> dict[str, list[list[float]]]:
    """A closed mesh of an ellipsoid (an icosphere subdivided, projected to the sphere, then stretched), as a
    request carries one."""
    from phantom.model.mesh.surface import subdivide

    golden = (1 + 5**0.5) / 2
    vertices = np.array([[-1, golden, 0], [1, golden, 0], [-1, -golden, 0], [1, -golden, 0], [0, -1, golden],
                         [0, 1, golden], [0, -1, -golden], [0, 1, -golden], [golden, 0, -1], [golden, 0, 1],
                         [-golden, 0, -1], [-golden, 0, 1]], float)
    triangles = np.array([[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9], [5, 11, 4],
                          [11, 10, 2], [10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8], [3, 8, 9],
                          [4, 9, 5], [2, 4, 11], [6, 2, 10], [8, 6, 7], [9, 8, 1]])
    for _ in range(subdivisions):
        vertices, triangles = subdivide(vertices, triangles)
    unit = vertices / np.linalg.norm(vertices, axis=1, keepdims=True)
    return {"vertices_mm": np.round(unit * np.array(semi_axes_mm), 3).tolist(), "triangles": triangles.tolist()}


@pytest.fixture(scope="module")
def rig(tmp_path_factory):
    """The daemon on its default model (builtin:converged, whose table of shapes ships) and a simulated board."""
    directory = tmp_path_factory.mktemp("shape_target")
    rig = DaemonRig(directory)
    try:
        wait_ready(rig.socket, rig.process, directory / "daemon.log", 180)
        yield rig
    finally:
        rig.close()


def test_set_shape_holds_the_shape_inverses_pressures(rig, tmp_path):
    mask = lopsided_mask(tmp_path / "lopsided.nii.gz")
    with phantom.connect(rig.socket) as ph:
        result = ph.set_shape(mask, refine_solves=0, timeout_s=120)
    shape = result.shape
    assert shape is not None, "the answer carries the shape inverse's"
    assert shape["source"] == str(mask)
    assert list(result.pressures_kpa) == pytest.approx(shape["pressures_kpa"], abs=1e-6)
    assert shape["pressures_kpa"][1] == max(shape["pressures_kpa"])
    assert shape["distance_mm"] < shape["rest_distance_mm"]
    assert result.measured_pressures_kpa is not None  # waited until reached and settled
    assert result.measured_pressures_kpa[1] == pytest.approx(shape["pressures_kpa"][1], abs=0.1)


def test_a_mesh_in_the_request_and_bad_shapes(rig):
    # an ellipsoid of 30 ml, wider than the phantom's rest shape: both lobes and the base grow
    mesh = ellipsoid_mesh((25.0, 16.0, 18.0))
    with DaemonClient(rig.socket, timeout_s=120) as client:
        answer = client.call("set_target", {"shape": mesh, "refine_solves": 0})
        assert answer["shape"]["source"] == "a mesh of 162 vertices"
        assert answer["shape"]["distance_mm"] < answer["shape"]["rest_distance_mm"]
        assert answer["target"] == {"pressures_kpa": pytest.approx(answer["shape"]["pressures_kpa"], abs=1e-9)}
        for params, why in (({"shape": "/nonexistent/gland.nii.gz"}, "no such file"),
                            ({"shape": mesh, "volume_ml": 30}, "shape goes alone"),
                            ({"shape": {"vertices_mm": mesh["vertices_mm"], "triangles": mesh["triangles"][:-3]}},
                             "not closed"),
                            ({"shape": mesh, "refine_solves": 9}, "refine_solves")):
            with pytest.raises(phantom.PhantomError, match=why):
                client.call("set_target", params)


def test_a_scene_step_gives_a_shape(rig):
    lopsided_mask(rig.directory / "lopsided.nii.gz")
    scene = rig.directory / "shape_scene.toml"
    scene.write_text(calibrated_scene([{"at_s": 0, "shape": "lopsided.nii.gz", "refine_solves": 0}], 20))
    with DaemonClient(rig.socket, timeout_s=120) as client:
        client.call("run_scene", {"path": str(scene)})
        status = rig.wait_status(lambda status: str(status.get("target_source")).startswith("scene")
                                 and status["target"], 30, "the scene's shape step in force")
    pressures = status["target"]["pressures_kpa"]
    assert pressures[1] == max(pressures) and pressures[1] > 0.5
