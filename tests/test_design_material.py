"""The material a designed phantom inherits (design/material.py): builtin:converged's calibrated law and element
order by default, or a scene's given with --material-from; the chambers sized with it, and the scene and report
saying which calibration it is and that the cast must be measured and calibrated."""

from __future__ import annotations

import json

import pytest
from test_design import asymmetric_gland, oblique_affine, run, write_mask

from phantom.design.errors import DesignError
from phantom.design.material import inherited_material

pytest.importorskip("trimesh")
pytest.importorskip("manifold3d")


def test_the_default_is_the_shipped_calibration():
    material = inherited_material()
    assert material.source == "builtin:converged" and material.element_order == 2
    assert material.table["model"] == "gent" and material.table["youngs_modulus_kpa"] == pytest.approx(10.86, abs=0.01)
    assert material.table["gent_jm"] == 5 and material.table["poisson_ratio"] > 0.499
    assert "builtin:converged's calibration" in material.caveat and "phantom calibrate" in material.caveat
    # on 4-node elements the same law, compressible enough not to lock
    assert inherited_material(element_order=1).table == {**material.table, "poisson_ratio": 0.45}
    # the uncalibrated built-in material, as designs had it before
    old = inherited_material("builtin")
    assert (old.table["model"], old.table["youngs_modulus_kpa"], old.element_order) == ("corotational", 50.0, 1)
    # a small-strain law on 10-node elements: the hyperelastic one of the same small-strain modulus
    assert inherited_material("builtin", element_order=2).table["model"] == "neo_hookean"


def test_a_material_scene_that_cannot_be_read_is_refused(tmp_path):
    with pytest.raises(DesignError, match="--material-from .*does not exist"):
        inherited_material(str(tmp_path / "absent.toml"))


def _check_the_bilobed_design(summary, out, err, grown_at_1_kpa=True):
    """The done-when line of issue 52 on a design of the bilobed mask: the calibrated material said in the scene and
    report, at least 2 ml of growth at 1,1,1 kPa (``grown_at_1_kpa``: the design's growth solved there), and the
    default growth target (45 ml at 3 kPa) within 5 % of the growth wanted, either way."""
    assert summary["material"]["from"] == "builtin:converged" and summary["material"]["element_order"] == 2
    scene = (out / "scene.toml").read_text()
    assert 'model = "gent"' in scene and "youngs_modulus_kpa = 10.8" in scene
    assert "builtin:converged's" in scene and "calibrate" in scene
    assert "builtin:converged's calibration" in (out / "report.md").read_text()
    if grown_at_1_kpa:
        assert summary["growth"]["pressures_kpa"] == [1.0]
        grown_ml = summary["growth"]["gland_volumes_ml"][0] - summary["rest_volume_ml"]
        assert grown_ml >= 2.0, grown_ml    # the uncalibrated material: 0.17 ml
    target = summary["growth_target"]
    wanted_ml = target["volume_ml"] - summary["gland_volume_ml"]
    assert target["volume_ml"] == pytest.approx(45.0) and target["reached"], target
    assert abs(target["designed_volume_ml"] - target["volume_ml"]) <= 0.05 * wanted_ml, target
    assert "is not reached" not in err
    assert min(summary["walls_mm"].values()) >= 2.0


def _bilobed_mask(tmp_path):
    return write_mask(tmp_path / "bilobed.nii.gz", asymmetric_gland, affine=oblique_affine((0.7, 0.7, 1.4)),
                      grid=(90, 80, 40))


@pytest.mark.long
@pytest.mark.timeout(2400)  # two 10-node sizing solves and the growth to 3 kPa: 13 min at a load average of 6-7
def test_a_bilobed_mask_grows_with_the_calibrated_material(tmp_path, capsys):
    """The asymmetric bilobed gland on 0.7 x 0.7 x 1.4 mm voxels at the default 2 mm walls, on a 4 mm mesh (two
    10-node elements through the thinnest wall): with the uncalibrated material it grew by 0.17 ml at 1,1,1 kPa and
    reached 26.85 of 45 ml at 3 kPa; sized with the calibrated law (and its chambers each as large as its walls
    allow), +2.23 ml at 1,1,1 kPa and 44.46 ml at 3 kPa (2.9 % of the growth wanted short; chambers 1.80, 1.63,
    1.61 ml at 0.96, 1.11, 1.11 of the template, the base one at its walls, from two coarse solves: 50.07 ml at the
    largest the walls allow, 44.95 ml at the scale chosen)."""
    out = tmp_path / "d"
    status, printed, err = run(capsys, "design", str(_bilobed_mask(tmp_path)), "--out", str(out), "--size-mm", "4",
                               "--growth-kpa", "1", "--json")
    assert status == 0, err
    summary = json.loads(printed)
    assert summary["mesh"]["elements_per_wall"] == 2
    _check_the_bilobed_design(summary, out, err)


@pytest.mark.slow
@pytest.mark.timeout(900)  # 2.9 min at a load average of 7 on two cores
def test_a_bilobed_mask_previewed_on_a_coarse_mesh_grows_as_the_design_does(tmp_path, capsys):
    """The long test's design in make test: the same mask, walls, material and sizing, previewed with
    --elements-per-wall 1 on a 6.4 mm mesh (one 10-node element through the thinnest wall; 7,247 nodes), its growth
    to the target confirmed on it: 45.04 ml at 3 kPa here, 44.46 ml on the long test's 4 mm mesh with two elements
    through the wall (28,352 nodes). The growth at 1,1,1 kPa (+2.23 ml on both meshes; 72 s of solve here, 11.6 min
    there) is the long test's alone: make test's 20 minutes (48 s here without it, 90 s with it)."""
    out = tmp_path / "d"
    status, printed, err = run(capsys, "design", str(_bilobed_mask(tmp_path)), "--out", str(out), "--size-mm", "6.4",
                               "--elements-per-wall", "1", "--growth-kpa", "none", "--json")
    assert status == 0, err
    summary = json.loads(printed)
    assert summary["mesh"]["elements_per_wall"] == 1 and summary["mesh"]["size_mm"] == 6.4
    assert "a preview: design with 2 before casting" in (out / "report.md").read_text()
    _check_the_bilobed_design(summary, out, err, grown_at_1_kpa=False)


def test_elements_per_wall_takes_one_or_two(tmp_path):
    """(The command line's choices are argparse's; the library refuses the rest before reading anything.)"""
    from phantom.design.pipeline import design
    from phantom.design.result import DesignOptions

    with pytest.raises(DesignError, match="--elements-per-wall 3 is not 1 .a preview. or 2 .the design."):
        design(tmp_path / "absent.nii.gz", tmp_path / "d", DesignOptions(elements_per_wall=3))
