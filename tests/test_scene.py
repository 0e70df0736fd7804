"""Scene files: the built-in scene, relative mesh paths, and clear errors for bad scenes."""

import json

import numpy as np
import pytest

from phantom import PhantomError
from phantom.cli.main import main
from phantom.model import SceneError, load_scene
from phantom.model.scene import PRESSURE_LIMIT_PA, SCENES_DIR, ModelSettings, builtin_scene_path, scene_from_dict


def write_scene(tmp_path, text):
    path = tmp_path / "scene.toml"
    path.write_text(text)
    return path


GOOD = """
[phantom]
mesh = "meshes/p.msh"
units = "cm"
chambers = ["a", "b"]

[material]
model = "linear"
youngs_modulus_kpa = 20
poisson_ratio = 0.3

[[steps]]
at_s = 0
volume_ml = 30

[host]
rate_hz = 50
"""


def test_builtin_scene_names_the_shipped_file():
    for name in ("builtin", "builtin:prostate"):
        scene = load_scene(name)
        assert scene.path == builtin_scene_path(name)
        assert scene.mesh == "builtin:prostate"
        assert scene.chambers == ["chamber0", "chamber1", "chamber2"]
        assert scene.fixed == "fixed"
        assert scene.material.model == "corotational"
        assert scene.material.youngs_modulus_pa == pytest.approx(50e3)
        assert scene.units == "mm" and scene.length_scale_m == 1e-3


def test_the_calibrated_builtin_scene_is_a_finite_strain_fit_on_the_built_in_body():
    scene = load_scene("builtin:calibrated")
    assert scene.path == builtin_scene_path("builtin:calibrated") and scene.path.name == "prostate_calibrated.toml"
    assert scene.mesh == "builtin:prostate" and scene.chambers == load_scene("builtin").chambers
    # physically valid means a law that holds at the phantom's strains, not the small-strain surrogate it replaced
    assert scene.material.model == "gent" and scene.material.poisson_ratio == pytest.approx(0.45)
    # the geometry it was fitted with, meshed at the size it was fitted on, and a daemon answers from its table
    assert scene.geometry.lobe_chamber_scale > 1.0 and scene.geometry.mesh_size_mm == 4.0
    # (the table's volumes and its outer surface's shapes ship beside it)
    assert scene.model_settings == ModelSettings(
        fidelity="table", accuracy_pct=1.0, pressure_max_pa=3000.0,
        table_volumes=SCENES_DIR / "prostate_calibrated.volumes.npz",
        table_shapes=SCENES_DIR / "prostate_calibrated.shapes.npz")


@pytest.mark.slow
def test_the_converged_builtin_scene_reproduces_its_calibration_and_keeps_its_elements_volume(capsys):
    """``builtin:converged`` is the calibration made on the 7 mm 10-node mesh: ``phantom forward`` on it gives, at
    (1, 1, 1) kPa, the gland volume the calibration's own verification solve gave (29.2389 ml, a continuation along
    the ray where this is a solve from rest), and no element changes its volume by 1 %. Its shipped table volumes
    are those of this mesh and model: (1, 1, 1) kPa is a point of their 7^3 grid."""
    from phantom.model import PhantomModel
    from phantom.model.fidelity.response_table import shipped_table_volumes

    scene = load_scene("builtin:converged")
    assert scene.geometry is not None and scene.geometry.element_order == 2 and scene.geometry.mesh_size_mm == 7.0
    assert scene.material.model == "gent" and scene.material.bulk_modulus_pa >= 1000 * scene.material.lame_mu_pa
    assert main(["forward", "--scene", "builtin:converged", "--pressures-kpa", "1,1,1", "--json"]) == 0
    answer = json.loads(capsys.readouterr().out)
    assert answer["total_volume_ml"] == pytest.approx(29.2389, abs=2e-3)
    low, high = answer["element_volume_ratio_range"]
    assert 0.99 < low <= high < 1.01
    # (the model is checked against the file's: same material, mesh size, solver, and rest volumes within 0.05 %)
    model = PhantomModel.from_scene(scene)
    shipped = shipped_table_volumes(model, scene.model_settings.pressure_max_pa, scene.model_settings.table_points)
    assert shipped is not None and shipped.position_values is None and shipped.check_errors_pct < 0.2
    assert float(shipped.gland_values[2, 2, 2]) * 1e6 == pytest.approx(answer["total_volume_ml"], abs=2e-3)
    assert (np.asarray(shipped.chamber_values[2, 2, 2]) * 1e6 == pytest.approx(answer["chamber_volumes_ml"],
                                                                             abs=2e-3))


@pytest.mark.parametrize(("key", "without"), [("table_volumes", "the table is then built once per machine"),
                                              ("table_shapes", "each shape is then solved")])
def test_table_files_are_files_beside_the_scene_and_a_calibration_drops_them(tmp_path, key, without):
    from phantom.model.calibration.calibrate import scene_with

    (tmp_path / "table.npz").write_bytes(b"")
    scene = load_scene(write_scene(tmp_path, GOOD + f'[model]\nfidelity = "table"\n{key} = "table.npz"\n'))
    assert getattr(scene.model_settings, key) == tmp_path / "table.npz"
    with pytest.raises(SceneError, match=rf"{key} names .*absent.npz, which is not a file: restore it, or remove "
                                         rf"the key \({without}\)"):
        load_scene(write_scene(tmp_path, GOOD + f'[model]\n{key} = "absent.npz"\n'))
    for wrong in ("3", '"builtin:"'):
        with pytest.raises(SceneError, match=rf"{key} must be a file path \(a .npz that response_table.write_{key} "
                                             rf"wrote, or builtin:NAME for one beside the built-in scenes\), got "):
            load_scene(write_scene(tmp_path, GOOD + f"[model]\n{key} = {wrong}\n"))
    # builtin:NAME is the file beside the built-in scenes, wherever the scene lies (a copy of an example scene)
    shipped = f"prostate_converged.{key.removeprefix('table_')}.npz"
    scene = load_scene(write_scene(tmp_path, GOOD + f'[model]\n{key} = "builtin:{shipped}"\n'))
    assert getattr(scene.model_settings, key) == load_scene("builtin:converged").path.parent / shipped
    with pytest.raises(SceneError, match=rf"{key} names .*model/scenes/absent.npz, which is not a file"):
        load_scene(write_scene(tmp_path, GOOD + f'[model]\n{key} = "builtin:absent.npz"\n'))
    for escaping in ("../../x.npz", "sub/x.npz", "/etc/x.npz"):
        with pytest.raises(SceneError, match=r"builtin:NAME names a file in the built-in scenes' folder "
                                             r"\(prostate_calibrated.shapes.npz, prostate_calibrated.volumes.npz, "
                                             r"prostate_converged.shapes.npz, prostate_converged.volumes.npz\)"):
            load_scene(write_scene(tmp_path, GOOD + f'[model]\n{key} = "builtin:{escaping}"\n'))
    # the files belong to the scene's own parameters: a copy with others set (a calibration's) names none
    copied = scene_with(load_scene("builtin:converged").raw, {"gent_jm": 20.0})
    assert key not in copied["model"] and key in load_scene("builtin:converged").raw["model"]


def test_an_unknown_builtin_name_lists_the_shipped_ones():
    with pytest.raises(SceneError, match="builtin, builtin:prostate, builtin:calibrated, builtin:converged"):
        load_scene("builtin:liver")


def test_a_scene_file_is_read_with_its_mesh_relative_to_it(tmp_path):
    scene = load_scene(write_scene(tmp_path, GOOD))
    assert scene.mesh == str((tmp_path / "meshes" / "p.msh").resolve())
    assert scene.length_scale_m == pytest.approx(1e-2)
    assert scene.fixed is None
    assert scene.material.youngs_modulus_pa == pytest.approx(20e3)
    assert scene.steps == [{"at_s": 0, "volume_ml": 30}]
    assert scene.raw["host"] == {"rate_hz": 50}
    assert scene.outputs.volumes and not scene.outputs.shape
    # no [model] table: the defaults; two chambers: their group names are their labels
    assert scene.model_settings == ModelSettings(None, 1.0, PRESSURE_LIMIT_PA, 7)
    assert scene.chamber_labels == ["a", "b"]


def test_the_model_settings_and_chamber_labels_are_read_into_types(tmp_path):
    text = GOOD.replace('chambers = ["a", "b"]', 'chambers = ["a", "b"]\nchamber_labels = ["front", "back"]')
    text += '[model]\nfidelity = "updated"\naccuracy_pct = 2\npressure_max_kpa = 2.5\ntable_points = 5\n'
    scene = load_scene(write_scene(tmp_path, text))
    assert scene.model_settings == ModelSettings("updated", 2.0, 2500.0, 5)
    assert isinstance(scene.model_settings.accuracy_pct, float)
    assert scene.chamber_labels == ["front", "back"]
    assert load_scene("builtin").chamber_labels == ["base", "left lobe", "right lobe"]


@pytest.mark.parametrize(("table", "message"), [
    ('fidelity = "medium"', "[model] fidelity must be one of rest, updated, full, table, got 'medium'"),
    ("accuracy_pct = 0", "[model] accuracy_pct must be a positive number, got 0"),
    ("accuracy_pct = nan", "[model] accuracy_pct must be a positive number, got nan"),
    ('pressure_max_kpa = "3"', "[model] pressure_max_kpa must be a positive number, got '3'"),
    ("pressure_max_kpa = -3.0", "[model] pressure_max_kpa must be a positive number, got -3.0"),
    ("table_points = 1", "[model] table_points must be an integer of at least 2, got 1"),
    ("table_points = 7.0", "[model] table_points must be an integer of at least 2, got 7.0"),
    ("table_point = 7", "[model] has unknown key 'table_point' (did you mean 'table_points'?)"),
])
def test_bad_model_settings_are_refused_when_the_scene_loads(tmp_path, table, message):
    with pytest.raises(SceneError) as error:
        load_scene(write_scene(tmp_path, GOOD + f"[model]\n{table}\n"))
    assert message in str(error.value) and "\n" not in str(error.value)


@pytest.mark.parametrize("labels", ['["front"]', '["front", 2]', '"front, back"', '["front", ""]'])
def test_chamber_labels_name_every_chamber(tmp_path, labels):
    text = GOOD.replace('chambers = ["a", "b"]', f'chambers = ["a", "b"]\nchamber_labels = {labels}')
    with pytest.raises(SceneError, match=r"chamber_labels must name each of the 2 chambers \(a, b\)"):
        load_scene(write_scene(tmp_path, text))


@pytest.mark.parametrize(
    ("replace", "by", "message"),
    [
        ('units = "cm"', 'units = "inch"', "units = 'inch'"),
        ('chambers = ["a", "b"]', "chambers = []", "chambers must be a non-empty list"),
        ('chambers = ["a", "b"]', 'chambers = ["a", "a"]', "lists a group twice"),
        ('model = "linear"', 'model = "neohookean"', "use 'corotational' or 'linear'"),
        ("poisson_ratio = 0.3", "poisson_ratio = 0.5", "poisson_ratio must lie in (-1, 0.5)"),
        ("youngs_modulus_kpa = 20", "youngs_modulus_kpa = -1", "youngs_modulus_kpa must be a positive"),
        ('mesh = "meshes/p.msh"', 'mesh = "builtin:liver"', "unknown built-in mesh"),
        ("[phantom]", "[phantom_]", "the file has unknown key 'phantom_' (did you mean 'phantom'?)"),
        ("[host]", "[materials]", "the file has unknown key 'materials' (did you mean 'material'?)"),
        ('units = "cm"', 'unit = "cm"', "[phantom] has unknown key 'unit' (did you mean 'units'?)"),
        ('units = "cm"', "units = []", "units = [] is not one of"),
        ("youngs_modulus_kpa = 20", "youngs_modulus_kpa = inf", "youngs_modulus_kpa must be a positive"),
        ("youngs_modulus_kpa = 20", "youngs_modulus_kpa = true", "youngs_modulus_kpa must be a positive"),
        ("[host]", "[outputs]\nshape = 1\n[host]", "[outputs] shape must be true or false, got 1"),
        ("[phantom]", 'outputs = "all"\n[phantom]', "outputs must be a table ([outputs]), got 'all'"),
        # a quoted number was printed as a number: "must be a positive number, got 10"
        ("youngs_modulus_kpa = 20", 'youngs_modulus_kpa = "10"', "youngs_modulus_kpa must be a positive number, "
                                                                 "got '10'"),
        ("poisson_ratio = 0.3", 'poisson_ratio = "0.3"', "poisson_ratio must lie in (-1, 0.5), got '0.3'"),
        # an integer of 401 digits (TOML allows any): no float holds it; each was an OverflowError traceback
        ("youngs_modulus_kpa = 20", f"youngs_modulus_kpa = {10**400}", "youngs_modulus_kpa must be a positive number"),
        ('model = "linear"', f'model = "gent"\ngent_jm = {10**400}', "gent_jm must be the locking value"),
        ('model = "linear"', f'model = "yeoh"\nyeoh_c20_over_c10 = {10**400}\nyeoh_c30_over_c10 = 0',
         "model = 'yeoh' needs yeoh_c20_over_c10"),
        ("[host]", f"[model]\npressure_max_kpa = {10**400}\n[host]", "pressure_max_kpa must be a positive number"),
        ("[host]", f"[load]\ngravity_m_s2 = [0, 0, {10**400}]\n[host]", "gravity_m_s2 must be three numbers"),
    ],
)
def test_bad_scenes_say_what_is_wrong(tmp_path, replace, by, message):
    assert replace in GOOD
    with pytest.raises(SceneError) as error:
        load_scene(write_scene(tmp_path, GOOD.replace(replace, by)))
    assert message in str(error.value)
    assert isinstance(error.value, PhantomError)


@pytest.mark.parametrize(("table", "key", "value", "requirement"), [
    ("material", "poisson_ratio", 0.5, "must lie in (-1, 0.5)"),
    ("material", "youngs_modulus_kpa", -1, "must be a positive number"),
    ("material", "youngs_modulus_kpa", 5e6, "must lie in what a silicone or elastomer has, 0.1 kPa to 100 MPa, "
                                            "given in kPa (Ecoflex 00-10: about 50)"),
    ("material", "gent_jm", -2, "must be the locking value of I1 - 3 (a positive number, e.g. 20 for silicone)"),
    ("geometry", "lobe_chamber_scale", 5.0, "must lie in [0.3, 2.5]"),
    ("geometry", "min_wall_mm", 0.1, "must lie in [1, 10] (thinner walls cannot be cast)"),
    ("geometry", "mesh_size_mm", "7", "must be a number"),
])
def test_a_refused_value_names_its_key_and_what_it_must_be_for_a_caller_that_took_it_from_a_flag(
        table, key, value, requirement):
    # a command that set the value from a flag (calibrate's --grid, --size-mm) says the flag and the requirement,
    # taken from these fields: it once rewrote the message's text, and fell back to a vaguer one when it changed
    raw = load_scene("builtin").raw
    document = {**raw, table: {**raw.get(table, {}), key: value}}
    if key == "gent_jm":
        document["material"] = {"model": "gent", "youngs_modulus_kpa": 50.0, "gent_jm": value}
    with pytest.raises(SceneError) as error:
        scene_from_dict(document)
    assert (error.value.key, error.value.requirement) == (key, requirement)
    assert f"[{table}] {key} {requirement}, got {value!r}" in str(error.value)


@pytest.mark.parametrize(("replace", "by", "message"), [
    ("youngs_modulus_kpa = 50.0", "youngs_modulus_kPa = 20.0",
     "[material] has unknown key 'youngs_modulus_kPa' (did you mean 'youngs_modulus_kpa'?)"),
    ("poisson_ratio = 0.45", "poisson_ration = 0.45",
     "[material] has unknown key 'poisson_ration' (did you mean 'poisson_ratio'?)"),
    ("accuracy_pct = 10.0", "accuracy = 10.0", "[model] has unknown key 'accuracy' (did you mean 'accuracy_pct'?)"),
    ("shape = false", "shapes = false", "[outputs] has unknown key 'shapes' (did you mean 'shape'?)"),
    ('fixed = "fixed"', 'fixed_group = "fixed"', "[phantom] has unknown key 'fixed_group' (did you mean 'fixed'?)"),
])
def test_a_misspelt_key_in_a_copy_of_the_builtin_scene_is_named_with_the_nearest_known_one(tmp_path, replace, by,
                                                                                          message):
    """A misspelt key was ignored and its default used in silence (E = 50 kPa for youngs_modulus_kPa = 20)."""
    text = builtin_scene_path("builtin").read_text()
    assert replace in text
    with pytest.raises(SceneError) as error:
        load_scene(write_scene(tmp_path, text.replace(replace, by)))
    assert message in str(error.value) and "\n" not in str(error.value)
    assert "the known ones are" in str(error.value)


def test_missing_and_unparsable_scene_files(tmp_path):
    with pytest.raises(SceneError, match="does not exist"):
        load_scene(tmp_path / "nope.toml")
    with pytest.raises(SceneError, match="not valid TOML"):
        load_scene(write_scene(tmp_path, "[phantom\nmesh = 1"))


def test_a_10_node_builtin_scene_is_nearly_incompressible_unless_it_says_otherwise(tmp_path):
    """Poisson's ratio defaults to 0.45 on 4-node elements (they lock near 0.5) and to bulk/shear >= 1000 on the
    built-in 10-node mesh; a ratio the scene names is kept."""
    from phantom.model.scene import QUADRATIC_POISSON_RATIO

    base = '[phantom]\nmesh = "builtin:prostate"\nchambers = ["chamber0"]\n\n[material]\nmodel = "gent"\ngent_jm = 3\n'
    linear = load_scene(write_scene(tmp_path, base)).material
    quadratic = load_scene(write_scene(tmp_path, base + "\n[geometry]\nelement_order = 2\n")).material
    named = load_scene(write_scene(tmp_path, base + "poisson_ratio = 0.45\n[geometry]\nelement_order = 2\n")).material
    assert linear.poisson_ratio == 0.45 and named.poisson_ratio == 0.45
    assert quadratic.poisson_ratio == QUADRATIC_POISSON_RATIO
    assert quadratic.bulk_modulus_pa >= 1000 * quadratic.lame_mu_pa


def test_scene_check_prints_every_resolved_value_and_where_it_came_from(tmp_path, capsys):
    from phantom.model.scene import LOAD_KEYS, MATERIAL_KEYS, MODEL_KEYS, OUTPUT_KEYS, PHANTOM_KEYS

    path = write_scene(tmp_path, GOOD + "[model]\naccuracy_pct = 2\n")
    assert main(["scene", "check", str(path), "--json"]) == 0
    resolved = json.loads(capsys.readouterr().out)["resolved"]
    for section, keys in (("phantom", PHANTOM_KEYS), ("material", MATERIAL_KEYS), ("model", MODEL_KEYS),
                          ("load", LOAD_KEYS), ("outputs", OUTPUT_KEYS)):
        assert list(resolved[section]) == list(keys)
    assert resolved["material"]["youngs_modulus_kpa"] == {"value": 20.0, "from": "file"}
    assert resolved["model"]["accuracy_pct"] == {"value": 2.0, "from": "file"}
    assert resolved["model"]["pressure_max_kpa"] == {"value": PRESSURE_LIMIT_PA / 1e3, "from": "default"}
    assert resolved["phantom"]["chamber_labels"] == {"value": ["a", "b"], "from": "default"}
    assert main(["scene", "check", "builtin:converged"]) == 0
    table = capsys.readouterr().out
    assert "[geometry]" in table and "element_order = 2" in table and "# file" in table and "# default" in table


def test_scene_check_refuses_a_misspelt_key_with_exit_2(tmp_path, capsys):
    path = write_scene(tmp_path, GOOD.replace("youngs_modulus_kpa", "youngs_modulus_kPa"))
    assert main(["scene", "check", str(path)]) == 2
    assert "unknown key 'youngs_modulus_kPa' (did you mean 'youngs_modulus_kpa'?)" in capsys.readouterr().err


def test_run_scene_names_a_misspelt_key_instead_of_another_phantom(tmp_path):
    """A misspelt key in a copy of an example scene: run-scene said the scene "describes another phantom than the
    running one" (the default modulus differed), not which key was wrong."""
    from phantom.host.handlers import prepare_scene
    from phantom.host.scenes import example_scene_path

    text = example_scene_path("bph_growth").read_text()
    assert "[material]" not in text  # the example names its model; an override of its modulus, misspelt:
    path = write_scene(tmp_path, text + "\n[material]\nyoungs_modulus_kPa = 10.85573\n")
    with pytest.raises(SceneError, match=r"\[material\] has unknown key 'youngs_modulus_kPa' \(did you mean "
                                         r"'youngs_modulus_kpa'\?\)"):
        prepare_scene(str(path), 1.0, ["chamber0", "chamber1", "chamber2"], {}, "running.toml")


def test_scene_check_of_a_timeline_scene_checks_it_as_the_daemon_reads_it(capsys, tmp_path):
    """``phantom scene check host/scenes/bph_growth.toml`` said ``model must be a table ([model]), got
    'builtin:converged'``, then that a timeline scene is played, not checked: a trainer writing one had no way to
    check it without a daemon. It is checked as ``run_scene`` reads it: its model, what it overrides, its steps
    against the model's chambers."""
    from phantom.host.scenes import example_scene_path

    path = example_scene_path("bph_growth")
    assert main(["scene", "check", str(path)]) == 0
    said = capsys.readouterr().out
    assert f"scene {path}: valid, a timeline scene: 5 step(s) over 210 s on its model builtin:converged" in said
    assert "it overrides outputs.shape = true" in said and "phantom run-scene" in said
    assert main(["scene", "check", str(example_scene_path("lopsided")), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["steps"] == 4
    for name, steps, words in (
            ("nan", "[[steps]]\nat_s = 0\nvolume_ml = nan\n", "volume_ml"),
            ("chamber", "[[steps]]\nat_s = 0\nchamber_volumes_ml = [1, 2]\n", "chamber_volumes_ml"),
            ("order", "[[steps]]\nat_s = 5\nvolume_ml = 30\n[[steps]]\nat_s = 1\nvolume_ml = 32\n", "at_s"),
            ("shape", '[[steps]]\nat_s = 0\nshape = "absent.stl"\n', "steps[0]'s shape")):
        broken = tmp_path / f"{name}.toml"
        broken.write_text('model = "builtin:converged"\n' + steps)
        assert main(["scene", "check", str(broken)]) == 2, name
        error = capsys.readouterr().err.strip()
        assert str(broken) in error and words in error and len(error.splitlines()) == 1, error


def test_steps_that_are_not_an_array_of_tables_are_refused_by_scene_check_and_run_scene(tmp_path):
    """``steps = 5`` was TypeError: 'int' object is not iterable (run_scene answered ``internal``)."""
    from phantom.host.handlers import prepare_scene

    words = r"steps must be an array of tables \(\[\[steps\]\]\), got 5"
    with pytest.raises(SceneError, match=words):
        load_scene(write_scene(tmp_path, "steps = 5\n" + GOOD.split("[[steps]]")[0]))
    path = write_scene(tmp_path, 'model = "builtin:converged"\nsteps = 5\n')
    with pytest.raises(SceneError, match=words):
        prepare_scene(str(path), 1.0, ["chamber0", "chamber1", "chamber2"], {}, "running.toml")
