"""A short training on a small synthetic population (a 16^3 grid), and the analyses on it: held-out shapes are
reconstructed, the latent distance is zero for a rigid motion and grows with a known stretch, the average of a
symmetric population is symmetric, and the ``phantom shape`` commands work end to end."""

import json

import numpy as np
import pytest

pytest.importorskip("jax")
pytest.importorskip("nibabel")
pytest.importorskip("skimage")

from phantom.cli.main import main  # noqa: E402
from phantom.model.mesh.surface import TriangleMesh, rotation_from_vector  # noqa: E402
from phantom.shape.analysis import ShapeModel, write_surface  # noqa: E402
from phantom.shape.compare import closed_surface, compare_shapes, latent_distance, phantom_mesh  # noqa: E402
from phantom.shape.dataset import find_cases, load_shapes, read_label_mask  # noqa: E402
from phantom.shape.synthetic import PopulationSpec, synthesize  # noqa: E402
from phantom.shape.training import TrainConfig, intersection_over_union, train  # noqa: E402
from phantom.shape.vae import VAEConfig  # noqa: E402

pytestmark = pytest.mark.slow
GRID = 16


@pytest.fixture(scope="module")
def population(tmp_path_factory):
    """Sixteen cases in mirror pairs (a symmetric population of asymmetric shapes)."""
    out = tmp_path_factory.mktemp("symmetric")
    synthesize(out, cases=16, seed=11, spec=PopulationSpec(lobe_asymmetry_sd=0.15, mirror_pairs=True),
               images=False)
    return out


@pytest.fixture(scope="module")
def run(population, tmp_path_factory):
    shapes = load_shapes(population, grid_size=GRID)
    return train(shapes, tmp_path_factory.mktemp("run") / "run", VAEConfig(grid_size=GRID, channels=(16, 32)),
                 TrainConfig(epochs=90, batch_size=4, validation_fraction=0.125, seed=1), on_epoch=None)


@pytest.fixture(scope="module")
def model(run):
    return ShapeModel.load(run)


def test_training_lowers_the_loss_and_reconstructs_held_out_shapes(run, model, population):
    history = json.loads((run / "history.json").read_text())
    assert history[-1]["loss"] < 0.3 * history[0]["loss"]
    shapes = load_shapes(population, grid_size=GRID, voxel_mm=model.voxel_mm)
    held_out = np.isin(shapes.names, model.config["data"]["held_out"])
    assert held_out.sum() == 2
    decoded = model.decode_grids(model.encode_grids(shapes.occupancy[held_out]))
    iou = intersection_over_union(decoded, shapes.occupancy[held_out])
    assert iou.mean() > 0.8 and iou.min() > 0.7, f"held-out IoU {iou}"
    assert history[-1]["validation_iou"] == pytest.approx(iou.mean(), abs=1e-6)


def test_the_average_of_a_symmetric_population_is_symmetric(model, population):
    shapes = load_shapes(population, grid_size=GRID, voxel_mm=model.voxel_mm)
    average = model.average().probabilities
    # the grid's first axis is x (RAS), centred on each shape's centroid: flipping it mirrors the shape
    average_symmetry = intersection_over_union(average[None], average[None, ::-1])[0]
    case_symmetry = intersection_over_union(shapes.occupancy, shapes.occupancy[:, ::-1])
    assert average_symmetry > 0.95
    assert average_symmetry > np.median(case_symmetry)


def _case_surface(model, population, name):
    """A case's closed surface, in the phantom's frame (mm), as a TriangleMesh."""
    mask = read_label_mask(find_cases(population / "data" / f"{name}_mask.nii")[0])
    surface = closed_surface(model, mask).mirrored_x()
    return TriangleMesh(surface.vertices_mm, surface.triangles)


def _moved(mesh, rotation_vector, translation_mm, stretch=(1.0, 1.0, 1.0)):
    centre = mesh.vertices_mm.mean(axis=0)
    vertices = (mesh.vertices_mm - centre) * np.asarray(stretch) + centre
    return TriangleMesh(vertices @ rotation_from_vector(np.asarray(rotation_vector)).T + translation_mm,
                        mesh.triangles)


def test_latent_distance_is_zero_for_a_rigid_motion_and_grows_with_a_stretch(model, population):
    _, latents = model.case_latents()
    spread = np.median(np.linalg.norm(latents[:, None] - latents[None], axis=2)[np.triu_indices(len(latents), 1)])
    shape = _case_surface(model, population, "000002")
    rigid = compare_shapes(model, phantom_mesh(shape), phantom_mesh(_moved(shape, [0.2, -0.35, 0.25], [6, -4, 9])))
    assert rigid.rotation_deg == pytest.approx(np.degrees(np.linalg.norm([0.2, -0.35, 0.25])), abs=1.0)
    assert rigid.mean_distance_mm < 0.05
    assert rigid.latent_distance < 0.05 * spread
    stretched = [compare_shapes(model, phantom_mesh(shape), phantom_mesh(_moved(shape, [0.1, 0.0, -0.2], [3, 0, 0],
                                                                                (1.0, factor, 1.0))))
                 for factor in (1.08, 1.16, 1.3)]
    distances = [result.latent_distance for result in stretched]
    assert distances == sorted(distances) and distances[0] > 3 * rigid.latent_distance
    assert distances[-1] > 0.2 * spread
    assert [r.mean_distance_mm for r in stretched] == sorted(r.mean_distance_mm for r in stretched)
    assert latent_distance(model, shape, _moved(shape, [0.0, 0.3, 0.0], [1, 2, 3])) < 0.05 * spread


def test_the_shape_commands_end_to_end(run, model, population, tmp_path, capsys):
    assert main(["shape", "average", str(run), "--out", str(tmp_path / "average.ply"), "--json"]) == 0
    average = json.loads(capsys.readouterr().out)
    assert average["volume_ml"] == pytest.approx(model.average().volume_ml, rel=1e-4)
    assert (tmp_path / "average.ply").stat().st_size > 1000
    assert main(["shape", "encode", str(run), str(population / "data" / "000003_mask.nii"), "--json"]) == 0
    encoded = json.loads(capsys.readouterr().out)["latent"]
    names, latents = model.case_latents()
    np.testing.assert_allclose(encoded, latents[names.index("000003")], atol=1e-4)
    shape = _case_surface(model, population, "000004")
    write_surface(shape.vertices_mm, shape.triangles, tmp_path / "a.ply")
    moved = _moved(shape, [0.0, 0.0, 0.5], [10, 0, 0])
    write_surface(moved.vertices_mm, moved.triangles, tmp_path / "b.stl")
    assert main(["shape", "compare", str(run), str(tmp_path / "a.ply"), str(tmp_path / "b.stl"), "--json"]) == 0
    compared = json.loads(capsys.readouterr().out)
    assert compared["mean_distance_mm"] < 0.05 and compared["rotation_deg"] == pytest.approx(28.65, abs=1.0)
    assert main(["shape", "clusters", str(run), "--k", "2", "--out", str(tmp_path / "clusters")]) == 0
    assert "cluster 1 vs 2" in capsys.readouterr().out
    assert (tmp_path / "clusters" / "cluster_1_vs_2.png").stat().st_size > 10000
    assert main(["shape", "report", str(run), "--out", str(tmp_path / "report"), "--k", "2"]) == 0
    report = json.loads((tmp_path / "report" / "report.json").read_text())
    assert report["average"]["volume_ml"] == pytest.approx(average["volume_ml"], rel=1e-3)
    assert report["average_vs_model"]["volume_a_ml"] == pytest.approx(26.3, rel=0.02)
    assert report["average_vs_model"]["mean_distance_mm"] > 0
    assert "| volume of the average shape |" in (tmp_path / "report" / "report.md").read_text()


def test_the_commands_refuse_bad_input_in_one_line(run, tmp_path, capsys):
    assert main(["shape", "average", str(tmp_path), "--out", str(tmp_path / "a.ply")]) == 2
    error = capsys.readouterr().err
    assert "not a trained run (no config.json)" in error and len(error.strip().splitlines()) == 1
    assert main(["shape", "encode", str(run), str(tmp_path / "missing.nii")]) == 2
    assert "no such file or folder" in capsys.readouterr().err
    assert main(["shape", "train", str(tmp_path), "--out", str(tmp_path / "run"), "--labels", "4,x"]) == 2
    assert "--labels" in capsys.readouterr().err
    assert main(["shape", "train", str(tmp_path), "--out", str(tmp_path / "run"), "--channels", "16,2.5"]) == 2
    assert "--channels takes positive whole numbers" in capsys.readouterr().err
    # a run is hours of training: another over it was written in its place without a word
    assert main(["shape", "train", str(tmp_path), "--out", str(run)]) == 2
    assert "holds a trained run already (config.json): give another --out, or --replace" in capsys.readouterr().err
    assert main(["shape", "average", str(run), "--out", str(tmp_path / "average.vtk")]) == 2
    assert "write the mesh as .obj, .ply or .stl" in capsys.readouterr().err


def test_compare_scan_reports_the_latent_distance_given_a_shape_run(run, model, tmp_path, capsys):
    """The paper's Fig. 9 beside the closest-point distances: a scan of the model at rest against the model."""
    scan = tmp_path / "scan.ply"
    assert main(["scan", "synthetic", "--out", str(scan), "--scene", "builtin", "--pressures-kpa", "0,0,0",
                 "--holes", "1", "--noise-mm", "0.02"]) == 0
    capsys.readouterr()
    assert main(["compare-scan", str(scan), "--scene", "builtin", "--pressures-kpa", "0,0,0", "--out",
                 str(tmp_path), "--shape-run", str(run), "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    _, latents = model.case_latents()
    spread = np.median(np.linalg.norm(latents[:, None] - latents[None], axis=2)[np.triu_indices(len(latents), 1)])
    assert 0.0 <= report["latent_distance"] < 0.1 * spread
    assert report["shape_run"] == str(run) and report["distance_mm"]["mean"] < 0.1
    assert main(["compare-scan", str(scan), "--scene", "builtin", "--pressures-kpa", "0,0,0", "--out",
                 str(tmp_path), "--shape-run", str(tmp_path / "no-run")]) == 2
    assert "no such run folder" in capsys.readouterr().err


def test_shape_reach_over_the_runs_own_cluster_centres(run, model, default_model_cached, tmp_path, capsys):
    """``phantom shape reach RUN``: the population is the trained run's k-means centres, decoded. Each centre's
    volume is its decoded shape's, the best pressures bring the phantom no farther than its rest shape, the rest
    distance is the one the shape analysis' own comparison (its ICP, a separate alignment) measures between the
    centre and the phantom at rest, and the latent picture draws the centres over the run's cases."""
    from phantom.model.mesh.surface import TriangleMesh as Mesh

    out = tmp_path / "reach"
    assert main(["shape", "reach", str(run), "--out", str(out), "--k", "2", "--json"]) == 0
    figures = json.loads(capsys.readouterr().out)
    assert figures["cases"] == 2 and set(figures["files"]) == {"table", "json", "histogram", "latent"}
    cases = json.loads((out / "reach.json").read_text())["cases"]
    assert [case["case"] for case in cases] == ["cluster 0", "cluster 1"]
    _, _, decoded = model.clusters(2)
    nodes, triangles = default_model_cached.outer_surface()
    rest = phantom_mesh(Mesh(np.asarray(default_model_cached.nodes_m)[nodes] * 1e3, triangles))
    for case, centre in zip(cases, decoded, strict=True):
        assert case["volume_ml"] == pytest.approx(centre.volume_ml, rel=0.02)
        # (at 0 kPa the answer's surface is the table's, a few nanometres from the rest nodes)
        assert case["distance_mm"] <= case["rest_distance_mm"] + 1e-4
        if centre.volume_ml < 0.9 * default_model_cached.rest_gland_volume_m3 * 1e6:
            # a gland smaller than the phantom: it only inflates, so rest is its closest (17.4 ml measured)
            assert case["pressures_kpa"] == [0.0, 0.0, 0.0] and len(case["at_limit"]) == 3
        else:   # 33.3 ml measured: 1.55 mm at rest, 0.56 at 0.87, 1.79, 1.78 kPa
            assert case["distance_mm"] < 0.6 * case["rest_distance_mm"]
        assert all(0.0 <= value <= 3.0 + 1e-9 for value in case["pressures_kpa"])
        compared = compare_shapes(model, rest, phantom_mesh(Mesh(centre.vertices_mm, centre.triangles)))
        assert case["rest_distance_mm"] == pytest.approx(compared.mean_distance_mm, rel=0.15), compared
    for name in ("reach_histogram.png", "reach_latent.png"):
        assert (out / name).read_bytes()[:4] == b"\x89PNG" and (out / name).stat().st_size > 10000
    assert main(["shape", "reach", str(run), "--out", str(out), "--k", "40"]) == 2
    assert "--k must be between 1 and the run's 16 cases, got 40" in capsys.readouterr().err
    assert main(["shape", "reach", str(run), "--out", str(out), "--run", str(run)]) == 2
    assert "--run goes with a dataset" in capsys.readouterr().err
