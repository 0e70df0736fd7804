"""A NIfTI mask read as a target gland (phantom.model.shape_file) keeps its volume and shape whatever its voxels:
ellipsoids of known volume (4/3 pi abc) voxelised at the spacings of thin slices, thick slices and a red team's
0.1 x 0.1 x 1.4 mm come back within 1 % of their volume and a tenth of a millimetre of their surface; a mask of a
few voxels is refused in one line."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from phantom.model.mesh.surface import enclosed_volume_ml, rotation_from_vector
from phantom.model.shape_file import PHANTOM_FROM_RAS, read_target_surface

nibabel = pytest.importorskip("nibabel")
pytest.importorskip("skimage")

#: The ellipsoid's centre (RAS, mm): off the voxel lattice, as a gland's is.
CENTRE_MM = np.array([0.13, -0.21, 0.37])


def ellipsoid_mask(path: Path, spacing_mm: tuple[float, float, float], semi_axes_mm: tuple[float, float, float],
                   rotation: np.ndarray | None = None) -> Path:
    """A binary NIfTI mask of the ellipsoid ``semi_axes_mm`` (RAS axes) about :data:`CENTRE_MM`: the voxels whose
    centres are inside, on a grid of ``spacing_mm`` whose axes are ``rotation``'s columns (RAS)."""
    axes = np.eye(3) if rotation is None else rotation
    semi = np.asarray(semi_axes_mm)
    # the ellipsoid's half extent along each voxel axis (its support function), and 4 mm to spare
    half_mm = np.sqrt(((axes * semi[:, None]) ** 2).sum(axis=0)) + 4.0
    shape = np.ceil(2 * half_mm / np.asarray(spacing_mm)).astype(int)
    linear = axes @ np.diag(spacing_mm)
    origin = CENTRE_MM - linear @ ((shape - 1) / 2.0)
    index = np.indices(shape).reshape(3, -1).T
    ras = index @ linear.T + origin
    inside = (((ras - CENTRE_MM) / semi) ** 2).sum(axis=1) <= 1.0
    affine = np.eye(4)
    affine[:3, :3], affine[:3, 3] = linear, origin
    nibabel.save(nibabel.Nifti1Image(inside.reshape(shape).astype(np.uint8), affine), str(path))
    return path


def distance_to_ellipsoid_mm(points_ras_mm: np.ndarray, semi_axes_mm: tuple[float, float, float]) -> np.ndarray:
    """Each point's distance to the ellipsoid's surface, to first order (|F - 1| / |grad F|, F = sum (x/a)^2):
    within a micrometre of the exact one at the tenth of a millimetre measured here."""
    semi = np.asarray(semi_axes_mm)
    p = points_ras_mm - CENTRE_MM
    level = ((p / semi) ** 2).sum(axis=1)
    gradient = np.linalg.norm(2 * p / semi**2, axis=1)
    distance: np.ndarray = np.abs(level - 1.0) / gradient
    return distance


GLAND_MM = (20.0, 15.0, 22.0)   # 27.6 ml, about the phantom's 26 ml
SMALL_MM = (12.0, 10.0, 14.0)   # 7.0 ml, a small gland


@pytest.mark.slow  # a mask of up to 4 million voxels blurred and surfaced a few times: 1-2 s a case
@pytest.mark.parametrize(("spacing_mm", "semi_axes_mm", "tilt_deg"), [
    ((0.1, 0.1, 1.4), GLAND_MM, 0.0),    # the red team's: read +1.3 to +2.4 %
    ((0.1, 0.1, 1.4), SMALL_MM, 0.0),    # +4.8 to +6.0 %
    ((0.1, 0.1, 1.4), GLAND_MM, 12.0),   # the same voxels turned about x, as an oblique acquisition
    ((1.4, 0.1, 0.1), SMALL_MM, 0.0),    # the long side first: the surface was left open
    ((0.5, 0.5, 3.6), GLAND_MM, 0.0),    # thick slices (the synthetic population's third institution): -2.4 %
    ((1.0, 1.0, 1.0), SMALL_MM, 0.0),    # isotropic: the blur's half level read it -2.6 %
])
def test_a_masks_surface_keeps_the_glands_volume_and_shape(tmp_path, spacing_mm, semi_axes_mm, tilt_deg):
    rotation = rotation_from_vector(np.radians(tilt_deg) * np.array([1.0, 0.0, 0.0]))
    path = ellipsoid_mask(tmp_path / "ellipsoid.nii.gz", spacing_mm, semi_axes_mm, rotation)
    surface = read_target_surface(path)
    exact_ml = 4.0 / 3.0 * math.pi * math.prod(semi_axes_mm) / 1e3
    assert enclosed_volume_ml(surface) == pytest.approx(exact_ml, rel=0.01)
    # the volume is not bought by moving the surface: it lies on the gland's within a tenth of the mask's longest
    # voxel side on average, and half of it everywhere (what the mask itself can say; the red team's mask was
    # surfaced 1.3 mm off on average, 3.7 mm at most)
    distance = distance_to_ellipsoid_mm(surface.vertices_mm * PHANTOM_FROM_RAS, semi_axes_mm)
    longest_mm = max(spacing_mm)
    assert distance.mean() < 0.1 * longest_mm and distance.max() < 0.5 * longest_mm


def test_a_speck_of_a_mask_is_refused_in_one_line(tmp_path, capsys):
    from phantom.cli import main as cli

    speck = np.zeros((20, 20, 20), np.uint8)
    speck[9:11, 10, 10] = 1
    path = tmp_path / "speck.nii.gz"
    nibabel.save(nibabel.Nifti1Image(speck, np.diag([0.7, 0.7, 1.4, 1.0])), str(path))
    assert cli.main(["inverse", "--shape", str(path)]) == 2
    error = capsys.readouterr().err.strip()
    assert len(error.splitlines()) == 1 and error.startswith("phantom inverse: error: ")
    assert "the gland is 2 voxels of 0.7 x 0.7 x 1.4 mm, 0.00137 ml: no gland's size (2-400 ml)" in error


def test_a_mask_of_scattered_voxels_is_refused_with_why(tmp_path):
    from phantom.model.shape_file import ShapeFileError

    scattered = np.zeros((40, 40, 40), np.uint8)
    scattered[::2, ::2, ::2] = 1   # 8000 voxels of 1 mm^3 (8 ml), none touching another: no body to surface
    path = tmp_path / "scattered.nii.gz"
    nibabel.save(nibabel.Nifti1Image(scattered, np.eye(4)), str(path))
    with pytest.raises(ShapeFileError, match="the mask's voxels are scattered or thinner than a voxel everywhere"):
        read_target_surface(path)
