"""``phantom daemon --sim --sim-truth SCENE``: another phantom as the simulated board's truth, its plant built once
and cached; the flags' misuse is refused with why."""

import pytest

from phantom.cli.main import main
from phantom.hil import plant as plant_module
from phantom.hil.plant import DEFAULT_PLANT_PATH, PlantError, load_plant, truth_plant_path, truth_shapes_path


@pytest.mark.parametrize(("argv", "message"), [
    (["daemon", "--port", "/dev/ttyACM9", "--sim-truth", "builtin:calibrated"],
     "--sim-truth sets the simulated phantom: give --sim too"),
    (["daemon", "--sim", "--sim-truth-modulus-factor", "0.9"], "give --sim-truth SCENE too"),
])
def test_the_truth_flags_without_what_they_need_are_refused(argv, message, capsys, tmp_path):
    assert main([*argv, "--socket", str(tmp_path / "d.sock")]) == 2
    assert message in capsys.readouterr().err


def test_a_truth_plant_is_built_once_from_the_scene_then_found_in_the_cache(tmp_path, monkeypatch):
    """The plant of a scene: the shipped plant with the scene's chambers and truth table, cached by content (the
    FEM replaced by the shipped plant's own numbers here: the solves are the truth table's own tests)."""
    monkeypatch.setenv("PHANTOM_CACHE_DIR", str(tmp_path / "cache"))
    shipped = load_plant()
    calls = []

    def chambers(scene, mesh_size_mm=None):
        calls.append("chambers")
        return plant_module.FemChambers(str(scene), "test", 1e6 * shipped.cavity_volume_m3 * 1.1,
                                        1e9 * shipped.compliance_m3_per_pa)

    def table(scene, modulus_factor, workers=None, progress=None, shapes_path=None):
        calls.append(("table", modulus_factor))
        shapes_path.write_bytes(b"the truth's shapes")
        if progress is not None:
            progress(64, 64)
        return plant_module.TruthTable(plant_module.TRUTH_POINTS_KPA, 1e6 * shipped.truth_chamber_volume_m3,
                                       1e6 * shipped.truth_gland_volume_m3 * 0.9, "a test truth")

    monkeypatch.setattr(plant_module, "chambers_from_scene", chambers)
    monkeypatch.setattr(plant_module, "truth_table_from_scene", table)
    told = []
    path = truth_plant_path("builtin:calibrated", 0.9, progress=lambda done, total: told.append((done, total)))
    assert calls == ["chambers", ("table", 0.9)] and told == [(64, 64)]
    built = load_plant(path)
    assert truth_shapes_path(path).read_bytes() == b"the truth's shapes"      # beside it, from the same build
    assert built.truth_gland_volume_ml([0, 0, 0]) == pytest.approx(0.9 * shipped.truth_gland_volume_ml([0, 0, 0]),
                                                                    rel=1e-4)
    assert built.cavity_volume_m3 == pytest.approx(1.1 * shipped.cavity_volume_m3, rel=1e-4)
    assert path.read_text() != DEFAULT_PLANT_PATH.read_text()
    assert truth_plant_path("builtin:calibrated", 0.9) == path and len(calls) == 2      # cached: nothing solved
    assert truth_plant_path("builtin:calibrated", 0.8) != path                          # another factor: built
    with pytest.raises(PlantError, match="modulus factor must be a number from 0.1 to 10"):
        truth_plant_path("builtin:calibrated", float("nan"))
