"""The shape inverse (phantom.model.shape_inverse) against truths: a target made from the model's own deformed
surface at pressures no other test uses comes back at those pressures after a rigid move and noise; a target the
phantom cannot reach gets the box's closest point with its distance said; bad target files are refused with why."""

from __future__ import annotations

import json
from pathlib import Path

import meshio
import numpy as np
import pytest

from phantom.model.fidelity.response_table import shipped_table_shapes
from phantom.model.mesh.surface import TriangleMesh, rotation_angle_deg, rotation_from_vector
from phantom.model.shape_file import ShapeFileError, read_target_surface
from phantom.model.shape_inverse import ShapeInverse

#: The hidden target's pressures (kPa): off the shipped shapes' 1 kPa grid, used by no other test.
HIDDEN_KPA = (0.9, 2.3, 1.6)


@pytest.fixture(scope="session")
def shape_inverse(default_model_cached):
    model = default_model_cached
    shapes = shipped_table_shapes(model, model.model_settings.pressure_max_pa)
    assert shapes is not None, "builtin:converged ships its outer surface's shapes"
    return ShapeInverse(model, shapes)


def moved_and_noised(vertices_mm: np.ndarray, seed: int = 52) -> tuple[np.ndarray, np.ndarray]:
    """The vertices turned by 14 degrees about a slanted axis, shifted by (7, -4, 5) mm, and each moved by
    Gaussian noise of 0.1 mm RMS; and the rotation."""
    rng = np.random.default_rng(seed)
    axis = np.array([0.4, 0.8, 0.45]) / np.linalg.norm([0.4, 0.8, 0.45])
    rotation = rotation_from_vector(np.radians(14.0) * axis)
    noise = rng.normal(0.0, 0.1 / np.sqrt(3.0), vertices_mm.shape)
    return vertices_mm @ rotation.T + np.array([7.0, -4.0, 5.0]) + noise, rotation


def write_mesh_mm(path: Path, vertices_mm: np.ndarray, triangles: np.ndarray) -> Path:
    meshio.write(str(path), meshio.Mesh(vertices_mm, [("triangle", triangles)]))
    return path


@pytest.mark.slow
def test_a_hidden_target_of_the_model_comes_back_after_a_rigid_move_and_noise(shape_inverse, tmp_path):
    model = shape_inverse.model
    truth_pa = np.array(HIDDEN_KPA) * 1e3
    state = model.equilibrium(truth_pa)   # the truth: a full solve, apart from the table the inverse starts on
    moved, rotation = moved_and_noised(np.asarray(state.positions_m)[shape_inverse.nodes] * 1e3)
    target = read_target_surface(write_mesh_mm(tmp_path / "hidden.stl", moved, shape_inverse.triangles))

    result = shape_inverse.solve(target, refine_solves=3)

    # the table alone: within its resolution (the shapes' spline misses full solves by up to 0.11 mm here)
    assert np.max(np.abs(result.table_pressures_pa - truth_pa)) < 150.0, result.table_pressures_pa
    assert result.table_time_s < 20.0  # measured, not asserted tight: bench/README.md has the figure
    # refined by full solves: the pressures within 0.15 kPa, the distance at the noise's floor
    assert 1 <= result.solves <= 3
    assert np.max(np.abs(result.pressures_pa - truth_pa)) < 150.0, result.pressures_pa
    assert result.distance_mm < 0.1
    assert result.rest_distance_mm > 10 * result.distance_mm
    # the rigid move undone (the target's pose is its inverse)
    assert rotation_angle_deg(result.pose.rotation @ rotation) < 0.5
    assert result.volume_ml == pytest.approx(state.gland_volume_m3 * 1e6, rel=0.005)
    assert set(result.regions) == {"base", "left", "right"}
    assert all(error.mean_mm < 0.1 for error in result.regions.values())
    assert result.residual_mm.shape == (len(shape_inverse.nodes),)


def scaled_rest(shape_inverse: ShapeInverse, factor: float) -> TriangleMesh:
    rest = shape_inverse.rest_mm
    centre = rest.mean(axis=0)
    return TriangleMesh((rest - centre) * factor + centre, shape_inverse.triangles)


@pytest.mark.slow
def test_a_target_beyond_the_box_gets_its_closest_point_and_the_distance_said(shape_inverse):
    # the rest shape 1.45 times as large (2.9 times the volume): more than the phantom grows within 3 kPa
    result = shape_inverse.solve(scaled_rest(shape_inverse, 1.45), refine_solves=0)
    limit = shape_inverse.pressure_max_pa
    assert np.all(result.pressures_pa > 0.9 * limit)
    assert any(entry.endswith("its limit") for entry in result.at_limit)
    assert result.distance_mm > 1.0
    assert result.distance_mm < result.rest_distance_mm
    assert any("beyond what the phantom can show" in note and f"{result.distance_mm:.2f} mm" in note
               for note in result.notes)
    # the target reaches beyond the phantom everywhere: every region's signed error is negative
    assert all(error.signed_mm < 0 for error in result.regions.values())


@pytest.mark.slow
def test_a_target_smaller_than_the_rest_shape_gets_no_pressure(shape_inverse):
    result = shape_inverse.solve(scaled_rest(shape_inverse, 0.85), refine_solves=0)
    assert np.all(result.pressures_pa < 50.0)
    assert result.distance_mm == pytest.approx(result.rest_distance_mm, rel=0.05)


@pytest.mark.slow
@pytest.mark.parametrize("stretch", [(1.0, 1.0, 1.0), (1.0, 0.9, 1.05)])
def test_an_answer_is_never_farther_than_the_rest_shape(shape_inverse, stretch):
    # targets smaller than the rest shape: the fit from the grid's best start ended at 0 kPa too, its pose a few
    # nanometres from the rest fit's (+4e-7 and +1e-7 mm farther), and a reach table said the pressures made it worse
    rest = shape_inverse.rest_mm
    centre = rest.mean(axis=0)
    target = TriangleMesh((rest - centre) * 0.8 * np.array(stretch) + centre, shape_inverse.triangles)
    result = shape_inverse.solve(target, refine_solves=0)
    assert np.all(result.pressures_pa < 50.0)
    assert result.distance_mm <= result.rest_distance_mm


@pytest.mark.slow
def test_a_uniform_scale_is_fitted_only_when_asked_and_reported_apart(shape_inverse):
    # the rest shape 8 % larger (1.26 times the volume): rigidly, the box's closest point inflates the chambers;
    # with a scale, the target is brought to the phantom's size at rest, and the scale says by how much
    target = scaled_rest(shape_inverse, 1.08)
    scaled = shape_inverse.solve(target, refine_solves=0, scale=True)
    assert scaled.pose.scale == pytest.approx(1 / 1.08, rel=0.01)
    assert np.all(scaled.pressures_pa < 100.0) and scaled.distance_mm < 0.05
    assert scaled.to_json(["a", "b", "c"])["registration"]["kind"] == "rigid+scale"
    rigid = shape_inverse.solve(target, refine_solves=0)
    assert rigid.pose.scale == 1.0 and np.max(rigid.pressures_pa) > 500.0


@pytest.mark.slow
def test_the_table_answer_is_fast(shape_inverse):
    target = TriangleMesh(shape_inverse.table_surface(np.array([2000.0, 500.0, 1000.0]))[0], shape_inverse.triangles)
    result = shape_inverse.solve(target, refine_solves=0)
    assert result.solves == 0
    assert np.max(np.abs(result.pressures_pa - [2000.0, 500.0, 1000.0])) < 20.0
    assert result.distance_mm < 0.01


# --- bad target files ------------------------------------------------------------------------------------------


def write_mask(path: Path, mask: np.ndarray, affine: np.ndarray) -> Path:
    """A NIfTI mask; an affine that is not finite is written into the header's sform as a damaged file has it
    (nibabel refuses to make an image of one)."""
    nibabel = pytest.importorskip("nibabel")
    image = nibabel.Nifti1Image(mask.astype(np.uint8), np.eye(4) if not np.all(np.isfinite(affine)) else affine)
    if not np.all(np.isfinite(affine)):
        image.header.set_qform(None, code=0)
        image.header["sform_code"] = 1
        for row, name in enumerate(("srow_x", "srow_y", "srow_z")):
            image.header[name] = affine[row]
        image = nibabel.Nifti1Image(np.asarray(image.dataobj), None, image.header)
    nibabel.save(image, str(path))
    return path


def ball_mask(radius_voxels: float = 12.0, size: int = 36) -> np.ndarray:
    grid = np.indices((size, size, size)) - (size - 1) / 2.0
    return (np.sum(grid**2, axis=0) <= radius_voxels**2).astype(np.uint8)


def test_a_mask_is_read_in_mm_in_the_phantoms_frame(tmp_path):
    affine = np.diag([0.7, 0.7, 1.4, 1.0])
    surface = read_target_surface(write_mask(tmp_path / "ball.nii.gz", ball_mask(), affine))
    # an ellipsoid of semi-axes 12 * (0.7, 0.7, 1.4) mm: 4/3 pi abc
    expected_ml = 4.0 / 3.0 * np.pi * (12 * 0.7) ** 2 * (12 * 1.4) / 1e3
    from phantom.model.mesh.surface import enclosed_volume_ml

    assert enclosed_volume_ml(surface) == pytest.approx(expected_ml, rel=0.05)


@pytest.mark.parametrize(("mask", "affine", "why"), [
    (np.zeros((20, 20, 20), np.uint8), np.diag([1.0, 1.0, 1.0, 1.0]), "the mask is empty"),
    (ball_mask(), np.full((4, 4), np.nan), "affine (voxel to RAS mm) is not finite"),
    (ball_mask(), np.diag([0.001, 0.001, 0.001, 1.0]), "the header's units or spacing are wrong"),
    (ball_mask() * np.uint8(3) + (np.indices((36, 36, 36))[0] > 30), np.eye(4), "holds several labels"),
])
def test_a_bad_mask_is_refused_with_why(tmp_path, mask, affine, why):
    path = write_mask(tmp_path / "bad.nii", mask, affine)
    with pytest.raises(ShapeFileError, match=why.replace("(", r"\(").replace(")", r"\)")):
        read_target_surface(path)


def test_bad_meshes_are_refused_with_why(shape_inverse, tmp_path):
    rest, triangles = shape_inverse.rest_mm, shape_inverse.triangles
    with pytest.raises(ShapeFileError, match="not closed"):
        read_target_surface(write_mesh_mm(tmp_path / "open.stl", rest, triangles[:-5]))
    with pytest.raises(ShapeFileError, match="in millimetres: convert a mesh in metres"):
        read_target_surface(write_mesh_mm(tmp_path / "metres.stl", rest / 1e3, triangles))
    (tmp_path / "junk.stl").write_text("not a mesh")
    with pytest.raises(ShapeFileError, match="not a readable mesh"):
        read_target_surface(tmp_path / "junk.stl")
    with pytest.raises(ShapeFileError, match="no such file"):
        read_target_surface(tmp_path / "missing.nii.gz")


# --- phantom inverse --shape -----------------------------------------------------------------------------------


def lopsided_mask(path: Path, left_stretch: float = 1.18, voxel_mm: tuple[float, float, float] = (0.7, 0.7, 1.4),
                  ) -> Path:
    """A NIfTI mask (RAS, anisotropic voxels) of the built-in prostate's body with its left half (the patient's
    left, RAS -x) stretched sideways by ``left_stretch``: an enlarged left lobe, made apart from the FEM."""
    from phantom.model.mesh.shape import ANTERIOR_POSTERIOR_RATIO, HALF_LENGTH_MM, equator_radius_mm, profile_radius_mm

    extent_mm = np.array([44.0, 32.0, 48.0])
    voxel = np.array(voxel_mm)
    shape = np.ceil(extent_mm / voxel).astype(int)
    origin_mm = -extent_mm / 2.0
    ras = origin_mm + np.indices(shape).reshape(3, -1).T * voxel
    x, y, z = -ras[:, 0], ras[:, 1], ras[:, 2]   # the phantom's frame: x to the patient's left
    x = np.where(x > 0, x / left_stretch, x)
    radius = np.maximum(profile_radius_mm(np.clip(z / HALF_LENGTH_MM, -1.0, 1.0), equator_radius_mm()), 1e-9)
    inside = (np.abs(z) < HALF_LENGTH_MM) & ((x / radius) ** 2 + (y / (ANTERIOR_POSTERIOR_RATIO * radius)) ** 2 <= 1.0)
    affine = np.diag([*voxel_mm, 1.0])
    affine[:3, 3] = origin_mm
    return write_mask(path, inside.reshape(shape), affine)


@pytest.mark.slow
def test_phantom_inverse_shape_grows_the_enlarged_lobe(default_model_cached, tmp_path, capsys):
    from phantom.cli import main as cli

    mask = lopsided_mask(tmp_path / "lopsided.nii.gz")
    out = tmp_path / "answer"
    assert cli.main(["inverse", "--shape", str(mask), "--refine-solves", "1", "--json", "--out", str(out)]) == 0
    report = json.loads(capsys.readouterr().out)
    pressures = report["pressures_kpa"]
    assert report["chambers"] == ["base", "left lobe", "right lobe"]
    assert pressures[1] == max(pressures) and pressures[1] > pressures[2] + 0.3, pressures
    assert report["distance_mm"] < report["rest_distance_mm"]
    assert report["regions"]["left"]["mean_mm"] < report["rest_regions"]["left"]["mean_mm"]
    assert report["target_volume_ml"] > report["rest_volume_ml"]
    assert len(report["refinement"]) == 1
    assert json.loads((out / "shape_inverse.json").read_text())["pressures_kpa"] == pressures
    assert (out / "residual.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert read_target_surface(out / "answer.stl").vertices_mm.shape[1] == 3


def test_phantom_inverse_shape_refuses_what_goes_with_a_volume(tmp_path, capsys):
    from phantom.cli import main as cli

    assert cli.main(["inverse", "--shape", str(tmp_path / "none.nii.gz")]) != 0
    assert "no such file" in capsys.readouterr().err
    assert cli.main(["inverse", "--volume-ml", "30", "--out", str(tmp_path)]) != 0
    assert "go with --shape" in capsys.readouterr().err


# --- phantom shape reach ---------------------------------------------------------------------------------------


@pytest.mark.slow
def test_phantom_shape_reach_over_a_synthetic_population(default_model_cached, tmp_path, capsys):
    from phantom.cli import main as cli
    from phantom.shape.synthetic import synthesize

    synthesize(tmp_path / "population", cases=4, seed=3, images=False)
    out = tmp_path / "reach"
    assert cli.main(["shape", "reach", str(tmp_path / "population"), "--out", str(out), "--json"]) == 0
    figures = json.loads(capsys.readouterr().out)
    assert figures["cases"] == 4 and 0 <= figures["covered"] <= 4
    rows = (out / "reach.csv").read_text().splitlines()
    assert len(rows) == 5 and rows[0].startswith("case,volume_ml,pressure0_kpa")
    cases = json.loads((out / "reach.json").read_text())["cases"]
    # the best pressures never leave a case farther than the rest shape does
    assert all(case["distance_mm"] <= case["rest_distance_mm"] + 1e-6 for case in cases)
    assert any(case["distance_mm"] < case["rest_distance_mm"] - 0.1 for case in cases)
    assert (out / "reach_histogram.png").read_bytes()[:4] == b"\x89PNG"
    assert "latent" not in figures["files"]  # no run: no latent space to draw
