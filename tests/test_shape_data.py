"""The shape data: the dataset's layout written by the synthetic generator and read back by the loader (spacing,
orientation, label selection, volume through voxelisation and back), meshes voxelised, and bad inputs. Writing
and reading NIfTI populations takes seconds: those tests are marked slow."""

import json

import numpy as np
import pytest

pytest.importorskip("nibabel")
pytest.importorskip("skimage")

from phantom.shape.dataset import (  # noqa: E402
    PROSTATE_LABELS,
    find_cases,
    load_shapes,
    read_closed_mesh,
    read_institutions,
    read_label_mask,
)
from phantom.shape.errors import ShapeError  # noqa: E402
from phantom.shape.synthetic import ACQUISITIONS, PopulationSpec, synthesize  # noqa: E402
from phantom.shape.voxels import RAS_FROM_PHANTOM, ClosedSurface, column_parity, surface_of  # noqa: E402

CASES = len(ACQUISITIONS)  # one case per institution: every spacing and orientation


@pytest.fixture(scope="module")
def population(tmp_path_factory):
    """Seven asymmetric cases, one per institution's acquisition."""
    out = tmp_path_factory.mktemp("population")
    spec = PopulationSpec(lobe_asymmetry_sd=0.0, deformation_mm=0.0)
    synthesize(out, cases=CASES, seed=3, spec=spec)
    return out


@pytest.mark.slow
def test_the_generator_writes_the_datasets_layout(population):
    import nibabel

    names = sorted(p.name for p in (population / "data").iterdir())
    assert names == sorted([f"{i:06d}_img.nii" for i in range(CASES)] + [f"{i:06d}_mask.nii" for i in range(CASES)])
    assert read_institutions(population) == {f"{i:06d}": str(i + 1) for i in range(CASES)}
    for number, acquisition in enumerate(ACQUISITIONS):
        image = nibabel.load(str(population / "data" / f"{number:06d}_mask.nii"))
        assert image.header.get_zooms() == pytest.approx(acquisition.spacing_mm, abs=1e-5)
        labels = set(np.unique(np.asarray(image.dataobj)).tolist())
        assert {0, 1, 4, 5, 6}.issubset(labels)
    assert [case.kind for case in find_cases(population)] == ["labels"] * CASES


@pytest.mark.slow
def test_each_grid_is_the_cases_shape_whatever_the_spacing_and_orientation(tmp_path):
    """The grid (RAS axes, centred on the centroid) holds the generator's analytic shape: a loader that ignored
    the affine's orientation (a flip, the sagittal axes, the obliques) would not."""
    from phantom.shape.synthetic import CaseParameters, label_map

    spec = PopulationSpec(lobe_asymmetry_sd=0.4, deformation_mm=0.0)
    # seed 10 draws a lobe asymmetry between 0.23 and 0.62 for every one of the seven cases
    synthesize(tmp_path, cases=CASES, seed=10, spec=spec, images=False)
    shapes = load_shapes(tmp_path, grid_size=32)
    records = json.loads((tmp_path / "synthetic.json").read_text())["records"]
    axis = (np.arange(32) - 15.5) * shapes.voxel_mm
    grid = np.stack(np.meshgrid(axis, axis, axis, indexing="ij"), axis=-1).reshape(-1, 3)
    asymmetric = 0
    for record, occupancy in zip(records, shapes.occupancy, strict=True):
        case = CaseParameters(**{k: v for k, v in record.items() if k not in ("case", "institution")})
        phantom_points = grid * RAS_FROM_PHANTOM
        inside = np.isin(label_map(case, phantom_points), PROSTATE_LABELS)
        centroid = phantom_points[inside].mean(axis=0)
        truth = np.isin(label_map(case, phantom_points + centroid), PROSTATE_LABELS).reshape(occupancy.shape)
        loaded = occupancy >= 0.5
        iou = np.logical_and(loaded, truth).sum() / np.logical_or(loaded, truth).sum()
        assert iou > 0.9, f"case {record['case']} (institution {record['institution']}): IoU {iou:.3f}"
        # A loader that flipped x would give the IoU of the truth with its own mirror image: below 0.88 here.
        mirror = truth[::-1]
        asymmetric += np.logical_and(mirror, truth).sum() / np.logical_or(mirror, truth).sum() < 0.88
    assert asymmetric == CASES, "a case is not asymmetric enough to show a flipped x"


@pytest.mark.slow
def test_label_selection_and_volume_through_voxelisation_and_back(population):
    shapes = load_shapes(population, grid_size=32)
    transition = load_shapes(population, grid_size=32, labels=(4,), voxel_mm=shapes.voxel_mm)
    bladder = load_shapes(population, grid_size=32, labels=(1,))
    for index, name in enumerate(shapes.names):
        mask = read_label_mask(find_cases(population / "data" / f"{name}_mask.nii")[0])
        assert shapes.volumes_ml[index] == pytest.approx(mask.volume_ml())
        back_ml = surface_of(shapes.occupancy[index], shapes.voxel_mm).volume_ml()
        assert back_ml == pytest.approx(mask.volume_ml(), rel=0.02), name
        assert 0.1 * shapes.volumes_ml[index] < transition.volumes_ml[index] < 0.6 * shapes.volumes_ml[index]
        bladder_mask = read_label_mask(find_cases(population / "data" / f"{name}_mask.nii")[0], labels=(1,))
        # in RAS, z is superior: the bladder sits on the prostate's base
        assert bladder_mask.centroid_mm()[2] > mask.centroid_mm()[2] + 10.0
        assert bladder.volumes_ml[index] == pytest.approx(bladder_mask.volume_ml())
    assert transition.voxel_mm == shapes.voxel_mm
    assert shapes.labels == PROSTATE_LABELS and transition.labels == (4,)


@pytest.mark.slow
def test_a_shape_fills_the_grid_but_its_margin(population):
    shapes = load_shapes(population, grid_size=24, margin_voxels=3)
    occupied = np.argwhere(shapes.occupancy.max(axis=0) > 0)
    assert occupied.min() >= 2 and occupied.max() <= 21
    assert occupied.min() <= 4 or occupied.max() >= 19


def _ellipsoid(semi_axes_mm, subdivisions=4):
    import trimesh

    sphere = trimesh.creation.icosphere(subdivisions=subdivisions)
    return sphere.vertices * np.asarray(semi_axes_mm), sphere.faces


@pytest.mark.slow
def test_a_closed_mesh_is_voxelised_by_ray_parity_with_its_volume(tmp_path):
    import trimesh

    vertices, faces = _ellipsoid((20.0, 14.0, 17.0))
    path = tmp_path / "ellipsoid.stl"
    trimesh.Trimesh(vertices + [5.0, -3.0, 40.0], faces).export(str(path))
    surface = read_closed_mesh(path)
    exact_ml = surface.volume_ml()
    assert exact_ml == pytest.approx(4 / 3 * np.pi * 20 * 14 * 17 / 1e3, rel=0.01)
    assert surface.centroid_mm() == pytest.approx([-5.0, -3.0, 40.0], abs=1e-6)  # x mirrored into RAS
    shapes = load_shapes(tmp_path, grid_size=32)
    occupancy_ml = shapes.occupancy[0].sum() * shapes.voxel_mm**3 / 1e3
    assert occupancy_ml == pytest.approx(exact_ml, rel=0.01)
    assert surface_of(shapes.occupancy[0], shapes.voxel_mm).volume_ml() == pytest.approx(exact_ml, rel=0.02)


def test_ray_parity_of_a_cube():
    corners = np.array([[x, y, z] for x in (0.0, 1.0) for y in (0.0, 1.0) for z in (0.0, 1.0)])
    faces = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1], [2, 3, 7], [2, 7, 6],
                      [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]])
    axis = np.linspace(-0.45, 1.45, 20) + 1e-7
    inside = column_parity(corners, faces, axis, axis + 2e-7, axis)
    x, y, z = np.meshgrid(axis, axis + 2e-7, axis, indexing="ij")
    expected = (x > 0) & (x < 1) & (y > 0) & (y < 1) & (z > 0) & (z < 1)
    assert np.array_equal(inside, expected)


@pytest.mark.slow
def test_bad_inputs_say_what_is_wrong(tmp_path, population):
    import nibabel
    import trimesh

    with pytest.raises(ShapeError, match="no such file or folder"):
        find_cases(tmp_path / "missing")
    (tmp_path / "empty").mkdir()
    with pytest.raises(ShapeError, match="holds no shapes"):
        find_cases(tmp_path / "empty")
    images = tmp_path / "images"
    images.mkdir()
    (images / "000000_img.nii").write_bytes((population / "data" / "000000_img.nii").read_bytes())
    with pytest.raises(ShapeError, match="no label maps"):
        find_cases(images)
    with pytest.raises(ShapeError, match=r"no voxel is labelled 8 \(NVB\).*--labels"):
        load_shapes(population, labels=(8,))
    empty = tmp_path / "masks"
    empty.mkdir()
    nibabel.save(nibabel.Nifti1Image(np.zeros((8, 8, 8), np.uint8), np.eye(4)), str(empty / "blank.nii.gz"))
    with pytest.raises(ShapeError, match="the mask is empty"):
        load_shapes(empty)
    vertices, faces = _ellipsoid((10.0, 10.0, 10.0), subdivisions=2)
    open_mesh = tmp_path / "open.ply"
    trimesh.Trimesh(vertices, faces[:-3]).export(str(open_mesh))
    with pytest.raises(ShapeError, match="not closed"):
        read_closed_mesh(open_mesh)
    broken = tmp_path / "broken.nii"
    broken.write_bytes(b"not a nifti file")
    with pytest.raises(ShapeError, match="not a readable NIfTI"):
        read_label_mask(find_cases(broken)[0])
    with pytest.raises(ShapeError, match="not a shape file"):
        find_cases(population / "institution.txt")


@pytest.mark.slow
def test_a_shape_larger_than_the_grid_is_refused(population):
    shapes = load_shapes(population, grid_size=32)
    with pytest.raises(ShapeError, match="larger than the shapes the run was trained on"):
        load_shapes(population, grid_size=32, voxel_mm=0.5 * shapes.voxel_mm)


def test_surface_of_an_empty_grid_is_refused():
    with pytest.raises(ShapeError, match="holds no shape"):
        surface_of(np.zeros((8, 8, 8)), 1.0)


def test_mirroring_keeps_a_surface_outward():
    vertices, faces = _ellipsoid((10.0, 8.0, 6.0), subdivisions=2)
    surface = ClosedSurface(vertices + [3.0, 0.0, 0.0], faces).outward()
    assert surface.signed_volume_ml() > 0
    mirrored = surface.mirrored_x()
    assert mirrored.signed_volume_ml() == pytest.approx(surface.signed_volume_ml())
    assert mirrored.centroid_mm() == pytest.approx([-3.0, 0.0, 0.0], abs=1e-9)


def test_a_missing_extra_names_the_pip_command(monkeypatch, tmp_path, capsys):
    import sys

    from phantom.cli.main import main

    # the shape modules import again, and find no jax
    for name in [name for name in sys.modules if name.startswith("phantom.shape.") or name.split(".")[0] == "jax"]:
        monkeypatch.delitem(sys.modules, name)
    monkeypatch.setitem(sys.modules, "jax", None)
    assert main(["shape", "average", str(tmp_path), "--out", str(tmp_path / "a.ply")]) == 2
    error = capsys.readouterr().err
    assert "jax is not installed; it comes with the optional dependencies 'shape'" in error
    assert "[shape]'" in error and len(error.strip().splitlines()) == 1


def _ball_mask(path, affine, side=20, radius=6.0):
    import nibabel

    index = np.indices((side, side, side)) - side / 2.0
    ball = (np.sqrt((index**2).sum(axis=0)) < radius).astype(np.uint8)
    nibabel.save(nibabel.Nifti1Image(ball, affine), str(path))
    return path


def _affine(diagonal, translation=(0.0, 0.0, 0.0)):
    affine = np.diag([*diagonal, 1.0])
    affine[:3, 3] = translation
    return affine


@pytest.mark.parametrize(("affine", "message"), [
    (_affine((1.0, 1.0, 1.0), (np.nan, 0.0, 0.0)), r"the affine \(voxel to RAS mm\) is not finite"),
    (_affine((0.001, 0.001, 0.001)), r"the voxel sides are 0.001, 0.001, 0.001 mm, outside \[0.05, 20\] mm"),
    (_affine((1000.0, 1.0, 1.0)), "the voxel sides are 1e\\+03, 1, 1 mm, outside"),
    (np.array([[1.0, 1.0, 0, 0], [0, 0, 0, 0], [0, 0, 1.0, 0], [0, 0, 0, 1.0]]), "singular"),
])
def test_a_mask_whose_affine_is_not_a_voxel_grid_in_mm_is_refused(tmp_path, affine, message):
    """A NaN affine or micrometre voxels encoded as the empty grid (the same latent for both, exit 0); a singular
    affine was a LinAlgError traceback."""
    path = _ball_mask(tmp_path / "ball.nii.gz", affine)
    with pytest.raises(ShapeError, match=message) as raised:
        load_shapes(path, grid_size=16, voxel_mm=2.0)
    assert "\n" not in str(raised.value)


def test_a_mask_is_read_as_booleans_and_a_good_one_encodes(tmp_path):
    path = _ball_mask(tmp_path / "ball.nii.gz", _affine((1.0, 1.0, 1.0)))
    mask = read_label_mask(find_cases(path)[0])
    assert mask.mask.dtype == bool
    shapes = load_shapes(path, grid_size=16, voxel_mm=2.0)
    assert shapes.occupancy.sum() * 8.0 / 1e3 == pytest.approx(4 / 3 * np.pi * 6.0**3 / 1e3, rel=0.15)


def test_a_mask_that_comes_out_empty_on_the_grid_is_an_error_not_a_latent(tmp_path):
    path = _ball_mask(tmp_path / "ball.nii.gz", _affine((0.05, 0.05, 0.05)), radius=1.0)
    with pytest.raises(ShapeError, match="comes out empty on the grid .* smaller than a voxel; check its units"):
        load_shapes(path, grid_size=16, voxel_mm=5.0)


def test_a_mask_header_of_too_many_voxels_is_refused_before_its_data_is_read(tmp_path):
    """A 1000^3 .nii.gz of 4.5 MB took 2.2 GB (cast to float32); the header alone says how large it is."""
    import nibabel

    header = nibabel.Nifti1Header()
    header.set_data_shape((1000, 1000, 1000))
    header.set_data_dtype(np.uint8)
    header.set_sform(np.eye(4), code=1)
    path = tmp_path / "huge_mask.nii"
    path.write_bytes(header.binaryblock + b"\0" * (352 - len(header.binaryblock)) + b"\1" * 4096)
    with pytest.raises(ShapeError, match=r"declares 1000 x 1000 x 1000 voxels, more than the 134217728 of a 512\^3 "
                                         r"mask: crop or resample it"):
        read_label_mask(find_cases(path)[0])


def test_a_mask_shorter_than_its_header_or_with_nan_values_is_refused(tmp_path):
    import nibabel

    header = nibabel.Nifti1Header()
    header.set_data_shape((64, 64, 64))
    header.set_data_dtype(np.uint8)
    short = tmp_path / "short_mask.nii"
    short.write_bytes(header.binaryblock + b"\0" * (352 - len(header.binaryblock)) + b"\1" * 4096)
    with pytest.raises(ShapeError, match="not a readable NIfTI file"):
        read_label_mask(find_cases(short)[0])
    values = np.zeros((8, 8, 8), np.float32)
    values[2:5, 2:5, 2:5], values[0, 0, 0] = 1.0, np.nan
    nibabel.save(nibabel.Nifti1Image(values, np.eye(4)), str(tmp_path / "nan_mask.nii"))
    with pytest.raises(ShapeError, match="the mask holds NaN or infinite values"):
        read_label_mask(find_cases(tmp_path / "nan_mask.nii")[0])


@pytest.mark.slow
def test_worker_processes_put_the_shapes_on_the_same_grids_and_name_a_shape_that_does_not_fit(
        population, monkeypatch, capsys):
    """589 cases took 150 s on one core to grid (most of `phantom shape train` on a GPU): worker processes make
    them now, the same grids; a shape that does not fit is refused by name from a worker as in this process."""
    from phantom.shape import dataset

    alone = load_shapes(population, grid_size=32, workers=1)
    monkeypatch.setattr(dataset, "PARALLEL_FROM_CASES", 2)  # seven cases: in workers all the same
    together = load_shapes(population, grid_size=32, workers=2, progress=True)
    assert together.names == alone.names and together.voxel_mm == alone.voxel_mm
    np.testing.assert_array_equal(together.occupancy, alone.occupancy)
    assert f"shape: put {CASES}/{CASES} shapes on the grid" in capsys.readouterr().out
    with pytest.raises(ShapeError, match=r"_mask\.nii reaches .* beyond the grid's"):
        load_shapes(population, grid_size=32, voxel_mm=alone.voxel_mm / 3, workers=2)


def test_a_closed_mesh_with_every_other_triangle_turned_reads_as_the_consistent_one(tmp_path):
    """Each triangle of a closed mesh is wound one way and outward as it is read (the shape analysis, and phantom
    design through it): every other triangle turned read as a sliver of the volume before. A mesh that cannot be
    wound one way is refused naming why."""
    import trimesh

    vertices, faces = _ellipsoid((20.0, 14.0, 17.0), subdivisions=3)
    vertices = vertices + [5.0, -3.0, 40.0]
    mixed = np.asarray(faces).copy()
    mixed[::2] = mixed[::2, ::-1]
    trimesh.Trimesh(vertices, faces, process=False).export(str(tmp_path / "consistent.ply"))
    trimesh.Trimesh(vertices, mixed, process=False).export(str(tmp_path / "mixed.ply"))
    consistent = read_closed_mesh(tmp_path / "consistent.ply")
    repaired = read_closed_mesh(tmp_path / "mixed.ply")
    assert repaired.signed_volume_ml() == pytest.approx(consistent.signed_volume_ml(), rel=1e-12)
    np.testing.assert_array_equal(repaired.triangles, consistent.triangles)
    assert consistent.signed_volume_ml() == pytest.approx(4 / 3 * np.pi * 20 * 14 * 17 / 1e3, rel=0.02)
    # closed but one-sided: an n x n grid of quads, its columns a ring, its last row joined to the first mirrored
    n = 6
    index = np.arange(n * n).reshape(n, n)
    above = np.vstack([index[1:], index[0, (-np.arange(n)) % n]])
    quads = np.stack([index, np.roll(index, -1, axis=1), np.roll(above, -1, axis=1), above], -1).reshape(-1, 4)
    bottle = np.vstack([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]])
    points = np.random.default_rng(0).normal(size=(n * n, 3))
    trimesh.Trimesh(points, bottle, process=False).export(str(tmp_path / "bottle.ply"))
    with pytest.raises(ShapeError, match=r"bottle\.ply: the surface is one-sided"):
        read_closed_mesh(tmp_path / "bottle.ply")
