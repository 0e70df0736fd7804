"""The deformed mesh as output: `phantom forward --out` (read back with meshio) and the deformed outer surface."""

import json

import meshio
import numpy as np
import pytest

from phantom.cli.main import main
from phantom.model import PhantomModel, load_scene
from phantom.model.mesh.tetmesh import enclosed_volume_m3, read_mesh

SIZE = ["--size-mm", "5"]


@pytest.fixture(scope="module")
def model():
    return PhantomModel.from_scene(load_scene("builtin"), mesh_size_mm=5.0).with_material(model="neo_hookean")


def forward_json(capsys, *arguments) -> dict:
    assert main(["forward", "--scene", "builtin", *SIZE, "--formulation", "neo_hookean", "--json", *arguments]) == 0
    return json.loads(capsys.readouterr().out)


@pytest.mark.parametrize("suffix", [".vtu", ".msh", ".vtk"])
def test_forward_writes_the_deformed_mesh_in_the_format_of_its_extension(tmp_path, capsys, model, suffix):
    rest_path, out = tmp_path / f"rest{suffix}", tmp_path / "missing" / "folder" / f"deformed{suffix}"
    assert main(["mesh", "--scene", "builtin", *SIZE, "--out", str(rest_path)]) == 0
    capsys.readouterr()
    answer = forward_json(capsys, "--pressures-kpa", "3,2,2", "--out", str(out))
    assert answer["out"] == str(out)
    rest, deformed = meshio.read(rest_path), meshio.read(out)
    # Same nodes in the same order, same tetrahedra and the same groups: only the positions moved (mm).
    assert deformed.points.shape == rest.points.shape == model.nodes_m.shape
    np.testing.assert_allclose(rest.points, model.nodes_m * 1e3, atol=1e-9)
    for kind in ("tetra", "triangle"):
        np.testing.assert_array_equal(deformed.cells_dict[kind], rest.cells_dict[kind])
    if suffix != ".vtk":  # legacy VTK keeps no group names; .vtu keeps them as cell data, .msh as groups
        groups = read_mesh(out, 1e-3).surface_groups
        assert groups.keys() == model.mesh.surface_groups.keys()
        for name, triangles in model.mesh.surface_groups.items():
            np.testing.assert_array_equal(np.sort(groups[name], axis=1), np.sort(triangles, axis=1))
    state = model.equilibrium([3e3, 2e3, 2e3])
    np.testing.assert_allclose(deformed.points, state.positions_m * 1e3, atol=1e-9)
    # The file's own geometry gives back the reported volumes.
    for triangles, volume_ml in zip(model.chamber_triangles, answer["chamber_volumes_ml"], strict=True):
        assert enclosed_volume_m3(deformed.points * 1e-3, triangles) * 1e6 == pytest.approx(volume_ml, rel=1e-9)


def test_an_unwritable_output_is_a_one_line_error(tmp_path, capsys):
    blocker = tmp_path / "file"
    blocker.write_text("")
    code = main(["forward", "--scene", "builtin", *SIZE, "--pressures-kpa", "1,1,1", "--out",
                 str(blocker / "x.vtu")])
    error = capsys.readouterr().err.strip()
    assert code == 2 and "--out" in error and "\n" not in error


def test_the_deformed_outer_surface_encloses_the_gland_volume(model):
    pressures = np.array([4e3, 2e3, 2e3])
    positions_mm, triangles = model.deformed_surface(pressures)
    state = model.equilibrium(pressures)
    assert triangles.shape[1] == 3 and triangles.max() == len(positions_mm) - 1
    assert enclosed_volume_m3(positions_mm * 1e-3, triangles) == pytest.approx(state.gland_volume_m3, rel=1e-12)
    rest_mm, rest_triangles = model.deformed_surface([0, 0, 0])
    np.testing.assert_array_equal(rest_triangles, triangles)
    assert enclosed_volume_m3(rest_mm * 1e-3, triangles) == pytest.approx(model.rest_gland_volume_m3, rel=1e-12)


@pytest.mark.parametrize("material", ['model = "neo_hookean"', 'model = "gent"\ngent_jm = 20.0',
                                      'model = "yeoh"\nyeoh_c20_over_c10 = 0.2\nyeoh_c30_over_c10 = 0.02'])
def test_forward_on_a_tagged_mesh_scene_with_a_hyperelastic_material(tmp_path, capsys, material):
    assert main(["mesh", "--scene", "builtin", *SIZE, "--out", str(tmp_path / "prostate.msh")]) == 0
    (tmp_path / "scene.toml").write_text(
        '[phantom]\nmesh = "prostate.msh"\nunits = "mm"\nchambers = ["chamber0", "chamber1", "chamber2"]\n'
        f'fixed = "fixed"\n\n[material]\n{material}\nyoungs_modulus_kpa = 50.0\npoisson_ratio = 0.45\n')
    capsys.readouterr()
    assert main(["forward", "--scene", str(tmp_path / "scene.toml"), "--pressures-kpa", "3,2,2", "--json"]) == 0
    answer = json.loads(capsys.readouterr().out)
    scene = load_scene(tmp_path / "scene.toml")
    expected = PhantomModel.from_scene(scene).equilibrium([3e3, 2e3, 2e3])
    assert answer["formulation"] == scene.material.model
    assert answer["chamber_volumes_ml"] == pytest.approx(list(expected.chamber_volumes_m3 * 1e6), rel=1e-12)
    assert all(v > r for v, r in zip(answer["chamber_volumes_ml"], answer["rest_chamber_volumes_ml"], strict=True))
    if scene.material.model != "neo_hookean":  # the law reached the solve: it stiffens, less growth than Neo-Hookean
        neo_hookean = PhantomModel.from_scene(scene).with_material(model="neo_hookean").equilibrium([3e3, 2e3, 2e3])
        assert all(np.array(answer["chamber_volumes_ml"]) < neo_hookean.chamber_volumes_m3 * 1e6)


def test_forward_with_a_law_whose_coefficients_the_scene_lacks_says_which(capsys):
    assert main(["forward", "--scene", "builtin", *SIZE, "--formulation", "yeoh", "--pressures-kpa", "1,1,1"]) != 0
    assert "yeoh_c20_over_c10 and yeoh_c30_over_c10" in capsys.readouterr().err


def test_mesh_writes_into_a_missing_folder_and_reports_json(tmp_path, capsys):
    out = tmp_path / "new" / "folder" / "prostate.vtu"
    assert main(["mesh", "--scene", "builtin", *SIZE, "--out", str(out), "--json"]) == 0
    answer = json.loads(capsys.readouterr().out)
    written = meshio.read(out)
    assert answer["nodes"] == len(written.points) and answer["tetrahedra"] == len(written.cells_dict["tetra"])
    assert answer["groups"] == ["chamber0", "chamber1", "chamber2", "fixed"]
    blocker = tmp_path / "file"
    blocker.write_text("")
    assert main(["mesh", "--scene", "builtin", *SIZE, "--out", str(blocker / "x.vtu")]) == 2
    error = capsys.readouterr().err.strip()
    assert "--out" in error and "\n" not in error



@pytest.mark.slow
def test_a_quadratic_scene_writes_tetra10_in_the_rest_meshs_node_order(tmp_path, capsys):
    """`forward --out` of a 10-node scene (the thick sphere written as tetra10, bulk/shear 1250) at 3 kPa: meshio
    tetra10 with the nodes, in the order, of `phantom mesh --out`, and every element's volume ratio, written with
    it, within 1 +/- 0.01."""
    from phantom.model.mesh.prostate import generate_hollow_sphere
    from phantom.model.mesh.tetmesh import write_mesh

    write_mesh(generate_hollow_sphere(10.0, 20.0, 8.0, element_order=2), tmp_path / "sphere.vtu")
    (tmp_path / "quadratic.toml").write_text(
        '[phantom]\nmesh = "sphere.vtu"\nunits = "mm"\nchambers = ["cavity"]\n\n[material]\n'
        'model = "neo_hookean"\nyoungs_modulus_kpa = 50.0\npoisson_ratio = 0.4996\n')
    scene = str(tmp_path / "quadratic.toml")
    assert main(["mesh", "--scene", scene, "--out", str(tmp_path / "rest.vtu")]) == 0
    capsys.readouterr()
    assert main(["forward", "--scene", scene, "--pressures-kpa", "3", "--out", str(tmp_path / "x.vtu"),
                 "--json"]) == 0
    answer = json.loads(capsys.readouterr().out)
    assert answer["element_order"] == 2
    assert answer["chamber_volumes_ml"][0] > 1.05 * answer["rest_chamber_volumes_ml"][0]
    low, high = answer["element_volume_ratio_range"]
    assert 0.99 < low <= high < 1.01
    rest, deformed = meshio.read(tmp_path / "rest.vtu"), meshio.read(tmp_path / "x.vtu")
    rest_tets = [block.data for block in rest.cells if block.type == "tetra10"]
    deformed_tets = [block.data for block in deformed.cells if block.type == "tetra10"]
    assert rest_tets and np.array_equal(rest_tets[0], deformed_tets[0])
    assert len(rest.points) == len(deformed.points)
    assert 0 < np.linalg.norm(deformed.points - rest.points, axis=1).max() < 5.0
    written_ratios = deformed.cell_data["volume_ratio"][0]
    assert len(written_ratios) == len(deformed_tets[0])
    assert written_ratios.min() == pytest.approx(low) and written_ratios.max() == pytest.approx(high)


@pytest.mark.slow
def test_the_10_node_prostate_at_3_1_2_kpa_keeps_every_element_within_1_percent_of_its_volume(tmp_path, capsys):
    """The built-in prostate on 10-node elements (10 mm, Gent, E 50 kPa, Poisson's ratio left to the 10-node
    default, bulk/shear 1250) at (3, 1, 2) kPa: `forward --out x.vtu` writes each element's volume ratio, and all
    lie within 1 +/- 0.01 (nu = 0.45 on the same mesh swells elements to 1.89)."""
    (tmp_path / "quadratic.toml").write_text(
        '[phantom]\nmesh = "builtin:prostate"\nunits = "mm"\nchambers = ["chamber0", "chamber1", "chamber2"]\n'
        'fixed = "fixed"\n\n[material]\nmodel = "gent"\nyoungs_modulus_kpa = 50.0\ngent_jm = 3.0\n\n'
        '[geometry]\nmesh_size_mm = 10.0\nelement_order = 2\nlobe_chamber_scale = 1.2\n')
    out = tmp_path / "x.vtu"
    assert main(["forward", "--scene", str(tmp_path / "quadratic.toml"), "--pressures-kpa", "3,1,2", "--out",
                 str(out), "--json"]) == 0
    answer = json.loads(capsys.readouterr().out)
    assert answer["volume_change_ml"] > 0.5
    ratios = meshio.read(out).cell_data["volume_ratio"][0]
    assert answer["element_order"] == 2 and len(ratios) > 1000
    assert answer["element_volume_ratio_range"] == pytest.approx([ratios.min(), ratios.max()])
    assert np.all(np.abs(ratios - 1.0) < 0.01), (ratios.min(), ratios.max())
