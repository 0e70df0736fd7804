"""Scene timelines: holds, ramps, the shipped example scenes, and every malformed step."""

import numpy as np
import pytest

from phantom import PhantomError
from phantom.host.scenes import (
    example_scene_path,
    gland_volume_ml,
    load_timeline_scene,
    parse_target,
    parse_timeline,
    read_timeline_scene,
)
from phantom.model.errors import SceneError
from phantom.model.scene import builtin_scene_path, read_scene_toml
from phantom.model.target import Target

CHAMBERS = ["chamber0", "chamber1", "chamber2"]


def timeline(*steps):
    return parse_timeline(list(steps), CHAMBERS, "test")


def test_a_step_holds_until_the_next_and_nothing_before_the_first():
    line = timeline({"at_s": 2, "volume_ml": 30}, {"at_s": 10, "volume_ml": 35})
    assert line.target_at(1.999) is None
    assert line.target_at(2).to_json() == {"volume_ml": 30.0}
    assert line.target_at(9.99).to_json() == {"volume_ml": 30.0}
    assert line.target_at(10).to_json() == {"volume_ml": 35.0}
    assert line.target_at(1e6) == Target(gland_volume_m3=35e-6)


def test_a_ramp_is_linear_from_the_previous_target_then_holds():
    line = timeline({"at_s": 0, "pressures_kpa": [0, 1, 2]}, {"at_s": 10, "ramp_s": 4, "pressures_kpa": [2, 1, 0]})
    for time_s in (10, 11, 12.5, 13.9):
        fraction = (time_s - 10) / 4
        expected = [0 + 2 * fraction, 1, 2 - 2 * fraction]
        assert line.target_at(time_s).values == pytest.approx([1e3 * kpa for kpa in expected], abs=1e-9)
    assert line.target_at(14).to_json() == {"pressures_kpa": [2.0, 1.0, 0.0]}
    assert line.duration_s == 14


def test_a_chamber_volume_ramp_keeps_free_chambers_free():
    line = timeline({"at_s": 0, "chamber_volumes_ml": [None, 4, 4]},
                    {"at_s": 5, "ramp_s": 10, "chamber_volumes_ml": [None, 6, 5]})
    assert line.target_at(10).to_json() == {"chamber_volumes_ml": [None, 5.0, 4.5]}
    assert line.target_at(10).free_chambers == (0,)


def test_growth_ratio_takes_chamber_names_or_indices():
    named = parse_target({"volume_ml": 40, "growth_ratio": {"chamber1": 2.0, "chamber2": 1}}, CHAMBERS)
    indexed = parse_target({"volume_ml": 40, "growth_ratio": {"2": 1, "1": 2.0}}, CHAMBERS)
    assert named == indexed == Target(gland_volume_m3=40e-6, growth_ratio={1: 2.0, 2: 1.0})
    assert named.to_json() == {"volume_ml": 40.0, "growth_ratio": {"1": 2.0, "2": 1.0}}


@pytest.mark.parametrize(("steps", "message"), [
    ([{"volume_ml": 30}], "needs at_s"),
    ([{"at_s": 0, "volume_ml": 30, "pressures_kpa": [1, 1, 1]}], "exactly one of"),
    ([{"at_s": 0}], "exactly one of .* got none"),
    ([{"at_s": 0, "volume_ml": -3}], "volume_ml must be positive"),
    ([{"at_s": 0, "volume_ml": "big"}], "volume_ml must be a number"),
    ([{"at_s": 0, "volume_ml": float("nan")}], "must be finite"),
    ([{"at_s": 0, "pressures_kpa": [1, 1]}], "list of 3 numbers"),
    ([{"at_s": 0, "pressures_kpa": [1, -1, 1]}], r"left lobe \(chamber 1\) at -1 kPa is below 0 kPa"),
    ([{"at_s": 0, "chamber_volumes_ml": [None, None, None]}], "at least one number"),
    ([{"at_s": 0, "pressures_kpa": [1, 1, 1], "growth_ratio": {"chamber1": 1}}], "goes with volume_ml only"),
    ([{"at_s": 0, "volume_ml": 30, "growth_ratio": {"lobe": 1}}], "unknown chamber 'lobe'"),
    ([{"at_s": 0, "volume_ml": 30, "growth_ratio": {"chamber1": 0}}], "must be positive"),
    ([{"at_s": 0, "volume_ml": 30, "colour": "red"}], "unknown key"),
    # a misspelt target key was "give exactly one of ...; got none"
    ([{"at_s": 0, "volum_ml": 30}], r"unknown key\(s\) 'volum_ml': a target gives exactly one of volume_ml"),
    # a step beyond any scene's time was accepted (and a scene without end_s then ran for 1e300 s)
    ([{"at_s": 1e300, "volume_ml": 30}], r"end by 604800 s \(a week.*got at_s=1e\+300"),
    ([{"at_s": 0, "volume_ml": 30}, {"at_s": 5, "ramp_s": 1e300, "volume_ml": 35}], r"end by 604800 s"),
    ([{"at_s": 604800, "ramp_s": 0, "volume_ml": 30}, {"at_s": 604801, "volume_ml": 35}], r"end by 604800 s"),
    ([{"at_s": -1, "volume_ml": 30}], "must be >= 0"),
    ([{"at_s": 5, "volume_ml": 30}, {"at_s": 5, "volume_ml": 31}], "must be later"),
    ([{"at_s": 0, "ramp_s": 3, "volume_ml": 30}], "first step cannot ramp"),
    ([{"at_s": 0, "volume_ml": 30}, {"at_s": 5, "ramp_s": 2, "pressures_kpa": [1, 1, 1]}], "same target form"),
    ([{"at_s": 0, "volume_ml": 30}, {"at_s": 5, "ramp_s": 20, "volume_ml": 35}, {"at_s": 10, "volume_ml": 40}],
     "ramps until 25"),
    ([{"at_s": 0, "chamber_volumes_ml": [None, 4, 4]}, {"at_s": 5, "ramp_s": 1, "chamber_volumes_ml": [4, 4, None]}],
     "same free chambers"),
])
def test_malformed_steps_are_refused_with_what_is_wrong(steps, message):
    with pytest.raises(SceneError, match=message):
        timeline(*steps)


def test_steps_must_be_an_array_of_tables():
    with pytest.raises(SceneError, match=r"\[\[steps\]\]"):
        parse_timeline({"at_s": 0}, CHAMBERS, "test")


def test_the_shipped_bph_scene_goes_through_the_papers_targets_over_minutes():
    # the paper's targets, the first just above the model's rest volume (26.30 ml) instead of 26 ml
    raw = load_timeline_scene(example_scene_path("bph_growth")).raw
    line = parse_timeline(raw["steps"], raw["phantom"]["chambers"], "bph_growth")
    volumes = [gland_volume_ml(step.target) for step in line.steps]
    assert volumes == [26.5, 30, 35, 40, 45]
    assert any(step.ramp_s > 0 for step in line.steps)
    assert 120 <= raw["timeline"]["end_s"] <= 600 and raw["timeline"]["end_s"] >= line.duration_s


def test_the_shipped_lopsided_scene_grows_one_lobe_more():
    raw = load_timeline_scene(example_scene_path("lopsided")).raw
    line = parse_timeline(raw["steps"], raw["phantom"]["chambers"], "lopsided")
    ratios = [dict(step.target.growth_ratio) for step in line.steps if step.target.growth_ratio]
    assert ratios[0][1] == 2 * ratios[0][2]


def test_the_example_scenes_name_their_model_and_hold_no_material_or_geometry():
    """Issue 35: the example scenes copied the model's E, geometry and tables, so every recalibration edited the
    timelines. Now they name their model; recalibrating builtin:converged edits no timeline."""
    from pathlib import Path

    from phantom import host

    scenes = sorted((Path(host.__file__).parent / "scenes").glob("*.toml"))
    assert [path.stem for path in scenes] == ["bph_growth", "lopsided"]
    for path in scenes:
        raw = read_scene_toml(path)
        assert raw["model"] == "builtin:converged", path
        assert not {"phantom", "material", "geometry", "load"} & raw.keys(), path
        scene = read_timeline_scene(path)
        assert scene.scene.material == load_timeline_scene("builtin:converged").material
        assert scene.overrides == (["outputs.shape = true (the model's: false)"] if path.stem == "bph_growth"
                                   else [])


def test_a_timeline_scene_lays_its_tables_over_its_model_and_says_what_it_overrides(tmp_path):
    (tmp_path / "models").mkdir()
    model_path = tmp_path / "models" / "stiff.toml"
    model_path.write_text(builtin_scene_path("builtin:converged").read_text().replace(
        "youngs_modulus_kpa = 10.85573", "youngs_modulus_kpa = 12.0"))
    path = tmp_path / "grow.toml"
    path.write_text('model = "models/stiff.toml"\n[material]\ngent_jm = 4.0\nyoungs_modulus_kpa = 12.0\n'
                    "[timeline]\nend_s = 5\n[[steps]]\nat_s = 0\nvolume_ml = 30\n")
    read = read_timeline_scene(path)
    assert read.model == "models/stiff.toml" and read.scene.path == path
    assert read.scene.material.gent_jm == 4.0 and read.scene.material.youngs_modulus_pa == pytest.approx(12e3)
    assert read.overrides == ["material.gent_jm = 4.0 (the model's: 5.0)"]    # the same E is no override
    assert read.scene.geometry == load_timeline_scene("builtin:converged").geometry
    assert read.scene.steps == [{"at_s": 0, "volume_ml": 30}]
    assert "on its model models/stiff.toml; it overrides material.gent_jm = 4.0" in read.describe("grow.toml")


def test_a_timeline_scene_whose_model_is_missing_or_names_a_model_is_refused(tmp_path):
    path = tmp_path / "grow.toml"
    path.write_text('model = "nowhere.toml"\n[[steps]]\nat_s = 0\nvolume_ml = 30\n')
    with pytest.raises(SceneError, match="nowhere.toml does not exist"):
        read_timeline_scene(path)
    (tmp_path / "nowhere.toml").write_text('model = "builtin:converged"\n')
    with pytest.raises(SceneError, match="names a model itself; name a whole scene"):
        read_timeline_scene(path)
    (tmp_path / "nowhere.toml").write_text("[material]\nmodel = 'gent'\n")
    with pytest.raises(SceneError, match=r"grow.toml on its model nowhere.toml: .*\[phantom\] table is missing"):
        read_timeline_scene(path)


def test_missing_or_broken_scene_files_say_so(tmp_path):
    with pytest.raises(SceneError, match="does not exist"):
        read_scene_toml(tmp_path / "nope.toml")
    broken = tmp_path / "broken.toml"
    broken.write_text("[[steps]\nat_s = ")
    with pytest.raises(SceneError, match="not valid TOML"):
        read_scene_toml(broken)
    with pytest.raises(SceneError, match="shipped: bph_growth, lopsided"):
        example_scene_path("nothing")


@pytest.mark.slow
@pytest.mark.parametrize("name", ["bph_growth", "lopsided"])
def test_the_shipped_scenes_use_the_calibrated_model_and_every_target_is_reachable(name, default_model_cached):
    from phantom.host.model_worker import LoadedModel
    from phantom.model import load_scene
    from phantom.model.target import UnreachableTargetError

    controller = LoadedModel(str(example_scene_path(name)), report=lambda message: None)
    calibrated = load_scene("builtin:converged")
    assert controller.scene.material == calibrated.material and controller.scene.geometry == calibrated.geometry
    # The scene's fidelity ("table": the Gent model's response, solved on a grid, its volumes shipped with the
    # model) answers with no solve.
    assert controller.estimator.level == "table"
    raw = controller.scene.raw
    answers = []
    for step in parse_timeline(raw["steps"], raw["phantom"]["chambers"], name).steps:
        answer = controller.pressures_for(step.target)
        assert np.all(answer.pressures_pa <= controller.pressure_max_pa + 1e-6)
        if step.target.kind == "volume":
            assert answer.predicted_gland_volume_m3 == pytest.approx(step.target.gland_volume_m3, rel=1e-4)
        answers.append(answer)
    assert controller.estimator.counts["full_solves"] == 0 and controller.estimator.counts["tangent_solves"] == 0
    # The truth: a full Gent solve at the second answer's pressures, within the table's 0.14 %; a solve from rest
    # takes up to a minute on the 10-node mesh near 3 kPa, so one per scene, at its lower pressures.
    state = controller.model.equilibrium(answers[1].pressures_pa)
    assert state.gland_volume_m3 == pytest.approx(answers[1].predicted_gland_volume_m3, rel=1.5e-3)
    if name == "bph_growth":
        # the paper's 45 ml is the last step; 55 ml is out of reach within 3 kPa per chamber, and the error says
        # how far one can go
        assert answers[-1].predicted_gland_volume_m3 == pytest.approx(45e-6, rel=1e-4)
        with pytest.raises(UnreachableTargetError, match=r"55.000 ml is unreachable.* give 26\.29\d* to 51\.5\d* ml"):
            controller.pressures_for(parse_target({"volume_ml": 55}, raw["phantom"]["chambers"], "test"))


def test_the_controller_honours_the_scenes_accuracy_when_it_names_no_fidelity(tmp_path):
    from phantom.host.model_worker import LoadedModel
    from phantom.model import load_scene

    # A soft small-strain material with 3 kPa everywhere (displacements as large as the gland, which a small-
    # strain law allows): "updated" is exact on the mesh, which is itself an estimated 47 % of a chamber's volume
    # from the converged answer (the probe refines it once to see), and "rest" 82 %. A scene that accepts 100 %
    # gets the cheapest level, "rest"; one that asks for 60 % gets "updated" (no solve); one that asks for 1 % is
    # refused, saying what would meet it.
    text = (load_scene("builtin").path.read_text().replace('model = "corotational"', 'model = "linear"')
            .replace("youngs_modulus_kpa = 50.0", "youngs_modulus_kpa = 2.63")
            .replace("accuracy_pct = 10.0", "pressure_max_kpa = 3.0\naccuracy_pct = {}"))
    levels, lines = {}, []
    for accuracy_pct in (100.0, 60.0):
        scene_path = tmp_path / f"scene_{accuracy_pct:g}.toml"
        scene_path.write_text(text.format(accuracy_pct))
        controller = LoadedModel(str(scene_path), report=lines.append)
        assert controller.scene.material.model == "linear"
        levels[accuracy_pct] = controller.estimator.level
        assert controller.estimator.accuracy_pct == accuracy_pct
    assert levels == {100.0: "rest", 60.0: "updated"}
    # the second scene's "inverse ready" line (the start-up's total follows it)
    assert any("chosen for accuracy_pct 60 from errors" in line and "against the converged answer (the mesh's own "
               "error" in line for line in lines), lines
    scene_path = tmp_path / "scene_1.toml"
    scene_path.write_text(text.format(1.0))
    with pytest.raises(PhantomError, match=r"no level meets accuracy_pct 1: the full solve on this mesh is an "
                       r"estimated 4\d % of a volume from the converged answer .* element_order = 2"):
        LoadedModel(str(scene_path), report=lines.append)


@pytest.fixture(scope="module")
def default_model(default_model_cached):
    """The model a daemon started with its defaults loads (builtin:converged, on its shipped response table)."""
    from phantom.host.model_worker import LoadedModel

    return LoadedModel("builtin:converged", report=lambda message: None)


@pytest.mark.slow
@pytest.mark.parametrize("name", ["bph_growth", "lopsided"])
def test_the_shipped_scenes_run_on_a_daemon_started_with_its_defaults(default_model, name):
    from phantom.host.scenes import effective_model, model_differences

    scene = load_timeline_scene(example_scene_path(name))
    assert model_differences(default_model.effective_model(), effective_model(scene)) == []


@pytest.mark.slow
@pytest.mark.parametrize(("change", "differing"), [
    (("youngs_modulus_kpa = 10.85573", "youngs_modulus_kpa = 9.0"), ["material"]),
    (("lobe_chamber_scale = 1.2", "lobe_chamber_scale = 1.1"), ["geometry"]),
    (('fidelity = "table"', 'fidelity = "rest"'), ["model"]),
    (("pressure_max_kpa = 3.0", "pressure_max_kpa = 2.5"), ["model"]),
    (('fidelity = "table"\n', ""), []),
    (('chambers = ["chamber0", "chamber1", "chamber2"]', 'chambers = ["chamber0", "chamber2", "chamber1"]'),
     ["phantom"]),
])
def test_a_scene_for_another_model_is_told_apart(default_model, tmp_path, change, differing):
    from phantom.host.scenes import effective_model, model_differences
    from phantom.model import load_scene

    # a whole scene that copies the model's values (as the example scenes did) still loads, and is told apart
    timeline = "[timeline]" + example_scene_path("bph_growth").read_text().split("[timeline]", 1)[1]
    text = load_scene("builtin:converged").path.read_text() + "\n" + timeline
    assert change[0] in text
    path = tmp_path / "changed.toml"
    path.write_text(text.replace(change[0], change[1]))
    assert model_differences(default_model.effective_model(), effective_model(load_timeline_scene(path))) == differing


@pytest.mark.slow
def test_the_inverse_is_warm_after_start_up(default_model):
    from phantom.model.target import UnreachableTargetError

    # the warm-up set up the gland's exact and closest problems: the first request sets up nothing new
    shapes = set(default_model.solver._problems)
    assert {shape[0] for shape in shapes} == {"exact", "closest"}
    default_model.pressures_for(parse_target({"volume_ml": 33}, CHAMBERS))
    with pytest.raises(UnreachableTargetError, match="unreachable"):
        default_model.pressures_for(parse_target({"volume_ml": 80}, CHAMBERS))
    assert set(default_model.solver._problems) == shapes
    assert default_model.timings_s["warm_up_s"] > 0


@pytest.mark.slow
def test_a_daemon_on_the_demo_scene_starts_on_its_shipped_volumes_and_shapes(monkeypatch, tmp_path):
    """``builtin:converged``'s table takes most of an hour to build; its volumes and its outer surface's shapes
    ship with it, so a daemon's model on the demo's scene (which records shapes) starts on the table at once (no
    build deferred to the background) and answers volumes and shapes with no solve."""
    from phantom.host.model_worker import LoadedModel
    from phantom.model.fidelity import response_table

    # as on a fresh machine: no full table stored (this machine may have built one)
    monkeypatch.setattr(response_table, "_cache_path", lambda *args: tmp_path / "no-table.npz")
    lines = []
    controller = LoadedModel(str(example_scene_path("bph_growth")), report=lines.append, defer_table=True)
    assert controller.pending_level is None and controller.estimator.level == "table"
    assert any("its volumes shipped with the scene, its outer surface's shapes too (4^3 points, within" in line
               for line in lines), lines
    # (1, 1, 1) kPa is a grid point: the calibration's own solve there gave 29.2389 ml
    _, gland_ml, _ = controller.estimate(np.full(3, 1000.0))
    assert gland_ml == pytest.approx(29.2389, abs=2e-3)
    rest_mm, triangles = controller.rest_surface_mm()
    pressures_pa = np.array([500.0, 1200.0, 300.0])
    shape_mm, shape_triangles = controller.outer_surface_mm(pressures_pa)
    assert controller.estimator.counts["full_solves"] == 0
    assert shape_mm.shape == rest_mm.shape and np.array_equal(shape_triangles, triangles)
    # against a full solve between the shapes' grid points: within a few times the shipped check's error
    state = controller.model.equilibrium(pressures_pa)
    used, _ = controller.model.outer_surface()
    off_mm = np.linalg.norm(shape_mm - 1e3 * state.positions_m[used], axis=1)
    moved_mm = np.linalg.norm(1e3 * state.positions_m[used] - rest_mm, axis=1)
    assert off_mm.max() < 3e3 * controller.estimator.shapes.check_error_m and moved_mm.max() > 1.0, (
        off_mm.max(), moved_mm.max())
