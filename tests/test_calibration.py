"""Calibration: measurement loading, the constrained fit, leave-one-out, and the scene it writes.

The end-to-end checks use synthetic measurements made by the real model at known parameters (independent
solves at E_true on the true geometry), so the right answer is known; the figures on the real measurements are
in bench/README.md.
"""

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from phantom.model import PhantomModel, load_scene
from phantom.model.calibration.calibrate import (
    CalibrationError,
    CalibrationResult,
    Grid,
    Measurements,
    Responses,
    calibrate,
    dump_toml,
    fit,
    load_measurements,
    parse_grid,
    write_calibrated_scene,
)

MEASUREMENTS = Path(__file__).resolve().parent.parent / "model" / "data" / "forward_measurements.csv"


def test_the_papers_table_loads_in_si_units():
    measurements = load_measurements(MEASUREMENTS, n_chambers=3)
    assert measurements.pressures_pa.shape == (8, 3)
    np.testing.assert_array_equal(measurements.pressures_pa[6], [1000.0, 2000.0, 3000.0])
    assert measurements.volumes_m3[0] == pytest.approx(26.43e-6)
    assert measurements.volumes_m3[-1] == pytest.approx(40.10e-6)


@pytest.mark.parametrize("text, message", [
    ("p0_kpa,p1_kpa\n0,0\n1,1\n2,2\n", "needs columns"),
    ("p0_kpa,p2_kpa,measured_ml\n0,0,26\n1,1,27\n2,2,28\n", "must be"),
    ("p0_kpa,measured_ml\n0,26\n1,x\n2,28\n", "not a number"),
    ("p0_kpa,measured_ml\n0,26\n1,inf\n2,28\n", "non-finite"),
    ("p0_kpa,measured_ml\n0,26\n-1,27\n2,28\n", "negative pressures"),
    ("p0_kpa,measured_ml\n0,26\n1,0\n2,28\n", "<= 0 ml"),
    ("p0_kpa,measured_ml\n0,26\n1,27\n", "at least 3"),
    ("# only a comment\n", "holds no data"),
])
def test_bad_measurement_files_say_what_is_wrong(tmp_path, text, message):
    path = tmp_path / "m.csv"
    path.write_text(text)
    with pytest.raises(CalibrationError, match=message):
        load_measurements(path)


def test_missing_file_and_chamber_count_mismatch(tmp_path):
    with pytest.raises(CalibrationError, match="does not exist"):
        load_measurements(tmp_path / "absent.csv")
    path = tmp_path / "m.csv"
    path.write_text("p0_kpa,measured_ml\n0,26\n1,27\n2,28\n")
    with pytest.raises(CalibrationError, match="1 pressure columns but the model has 3"):
        load_measurements(path, n_chambers=3)


def test_a_scan_file_entry_is_measured_by_the_callable_given(tmp_path):
    """The model reads no scans: a measured_ml that names a scan file needs the scan_volume_ml the command line
    passes (the scan comparison's); without one the row is refused, naming the file."""
    path = tmp_path / "m.csv"
    path.write_text("p0_kpa,measured_ml\n0,26\n1,scans/at_1.stl\n2,28\n")
    measured = []
    measurements = load_measurements(path, scan_volume_ml=lambda scan: measured.append(scan) or 27.5)
    assert measured == [tmp_path / "scans" / "at_1.stl"]
    np.testing.assert_allclose(measurements.volumes_m3, [26e-6, 27.5e-6, 28e-6])
    with pytest.raises(CalibrationError, match=r"data row 2: scans/at_1.stl is a scan file, and nothing here "):
        load_measurements(path)


@pytest.mark.slow  # the scene's model built for its surface at rest
def test_phantom_calibrates_scan_files_are_measured_against_the_scenes_phantom(tmp_path):
    """``phantom calibrate``'s scan files: each is measured at the scene's phantom's size (a file in cm is refused
    naming the unit, not read as a speck of 0.03 ml), the scene's surface built once, at the first scan."""
    from phantom.cli.calibrate import _scan_volume_of
    from phantom.model.mesh.surface import enclosed_volume_ml
    from phantom.scan.compare import ScanError
    from phantom.scan.reconstruct import write_mesh
    from phantom.scan.synthetic import sphere

    gland = sphere(18.8, np.zeros(3))   # about the phantom's size at rest (its RMS radius), 27.8 ml
    in_mm, in_cm = tmp_path / "gland_mm.ply", tmp_path / "gland_cm.ply"
    write_mesh(gland, in_mm)
    write_mesh(dataclasses.replace(gland, vertices_mm=gland.vertices_mm / 10), in_cm)
    measured_ml = _scan_volume_of(load_scene("builtin"))
    assert measured_ml(in_mm) == pytest.approx(enclosed_volume_ml(gland), rel=1e-6)
    with pytest.raises(ScanError, match=r"in cm: export it in mm \(phantom calibrate reads scan files in mm\)") \
            as refused:
        measured_ml(in_cm)
    assert "units=" not in str(refused.value)  # a library's argument, which a CSV or a prompt cannot pass
    speck = tmp_path / "speck.ply"  # no unit makes it the phantom's size
    write_mesh(dataclasses.replace(gland, vertices_mm=gland.vertices_mm / 3000), speck)
    with pytest.raises(ScanError, match=r"is it a scan of this phantom \(the --scene\)\? Export it in mm, or give "
                                        r"the volume in ml") as refused:
        measured_ml(speck)
    assert "model=" not in str(refused.value)


def _synthetic_responses(admissible_below_t=np.inf, traced_below_t=np.inf, fixed_lobe_scale=None):
    """A known family: G_j(theta, t) = 26 ml + a_j t + c_j theta t^2, on a grid of theta and t; NaN (not
    traced, as beyond a trace's growth stop) above ``traced_below_t``; with ``fixed_lobe_scale``, a second,
    single-valued grid axis."""
    names, values = ("gent_jm",), (np.array([0.0, 0.5, 1.0, 1.5]),)
    if fixed_lobe_scale is not None:
        names, values = (*names, "lobe_chamber_scale"), (*values, np.array([fixed_lobe_scale]))
    grid = Grid(names, values)
    load_factors = np.linspace(0, 3, 301)
    theta = grid.values[0].reshape(-1, *(1,) * (len(names) + 1))
    t = load_factors[:, None]
    gland = np.broadcast_to(_family(theta, t), (*grid.shape, len(load_factors), 4)).copy()
    gland[..., t[:, 0] > traced_below_t, :] = np.nan
    admissible = np.broadcast_to(t <= admissible_below_t, gland.shape) & np.isfinite(gland)
    ones = np.where(np.isfinite(gland), 1.0, np.nan)
    measures = {"min_det": ones, "min_stretch": ones, "max_stretch": ones, "max_i1_minus_3": 0 * ones}
    return Responses(grid, load_factors, gland, admissible, measures, np.full(grid.shape, 100.0), "gent")


def _family(theta, t):
    slopes, curvatures = np.array([0.0, 1.0, 2.0, 3.0]) * 1e-6, np.array([0.0, 0.6, 0.1, 0.3]) * 1e-6
    return 26e-6 + slopes * t + curvatures * theta * t**2


def test_the_fit_recovers_known_parameters_and_leave_one_out_uses_the_others():
    responses = _synthetic_responses()
    theta_true, t_true = 0.8, 1.7
    measured = _family(theta_true, t_true)
    full = fit(responses, measured, [0, 1, 2, 3])
    # Linear interpolation in theta between grid values 0.5 and 1.0 is exact here (G is linear in theta).
    assert full.theta[0] == pytest.approx(theta_true, abs=2e-3)
    assert full.load_factor == pytest.approx(t_true, rel=2e-3)
    assert full.predicted_m3 == pytest.approx(measured, rel=1e-4)
    without_last = fit(responses, measured, [0, 1, 2])
    assert without_last.predicted_m3[3] == pytest.approx(measured[3], rel=1e-3)


def test_the_fit_refines_between_grid_values_where_traces_end_and_keeps_a_single_valued_axis():
    # As on the real traces: the fit at an eighth of the load-factor range, every trace stopped (its growth limit)
    # at twice that; the truth between fine load factors (0.01 apart) and between theta's grid values, and a
    # second grid axis with one value. The refinement must move off the grid search's point (t within 1/20 of a
    # fine step) and leave the single-valued axis alone.
    responses = _synthetic_responses(traced_below_t=0.8, fixed_lobe_scale=1.2)
    theta_true, t_true = 0.8, 0.4051
    measured = _family(theta_true, t_true)
    full = fit(responses, measured, [0, 1, 2, 3])
    assert full.load_factor == pytest.approx(t_true, abs=5e-4)
    assert full.theta[0] == pytest.approx(theta_true, abs=2e-3)
    assert full.theta[1] == 1.2
    assert full.predicted_m3 == pytest.approx(measured, rel=1e-4)


def test_the_fit_keeps_to_the_constraints_and_refuses_when_nothing_is_valid():
    responses = _synthetic_responses(admissible_below_t=1.2)
    measured = _family(0.8, 1.7)
    constrained = fit(responses, measured, [0, 1, 2, 3])
    assert constrained.load_factor <= 1.2 + 1e-9
    # The best admissible answer: the largest theta and t the constraint allows.
    assert constrained.theta[0] == pytest.approx(1.5, abs=1e-3)
    nothing = _synthetic_responses(admissible_below_t=-1.0)
    with pytest.raises(CalibrationError, match="refused: no state on the grid fits"):
        fit(nothing, measured, [0, 1, 2, 3])


def test_a_modulus_band_holds_the_fit_and_says_which_edge_it_sits_on():
    # The truth at t = 1.7 (E = E0 / 1.7); a band of t in [0.5, 1.2] (E from E0 / 1.2 to 2 E0, stiffer than the
    # truth) must hold the fit at its soft edge, t = 1.2, and say so; a band around the truth leaves it free.
    responses = _synthetic_responses()
    measured = _family(0.8, 1.7)
    held = fit(responses, measured, [0, 1, 2, 3], load_factor_range=(0.5, 1.2))
    assert held.load_factor == pytest.approx(1.2, abs=1e-6)
    assert "lower edge" in held.binding and "softer" in held.binding
    stiff = fit(responses, _family(0.8, 0.3), [0, 1, 2, 3], load_factor_range=(0.5, 1.2))
    assert stiff.load_factor == pytest.approx(0.5, abs=1e-6)
    assert "upper edge" in stiff.binding
    free = fit(responses, measured, [0, 1, 2, 3], load_factor_range=(1.0, 2.5))
    assert free.load_factor == pytest.approx(1.7, rel=2e-3)
    assert free.binding is None


@pytest.mark.parametrize("argv, message", [
    (["--modulus-band-pct", "100"], r"--modulus-band-pct must be within \(0, 100\), got 100"),
    (["--modulus-band-pct", "-5"], r"--modulus-band-pct must be within \(0, 100\), got -5"),
    (["--youngs-modulus-kpa", "0"], "--youngs-modulus-kpa must be a positive number, got 0"),
    (["--youngs-modulus-kpa", "nan"], "--youngs-modulus-kpa must be a positive number, got nan"),
])
def test_bad_modulus_options_say_what_is_wrong(tmp_path, argv, message):
    from phantom import PhantomError

    csv_path = tmp_path / "m.csv"
    csv_path.write_text("p0_kpa,p1_kpa,p2_kpa,measured_ml\n0,0,0,26\n1,0,0,27\n0,1,0,27\n")
    args = _parse(["calibrate", "--measurements", str(csv_path), "--size-mm", "6", *argv])
    with pytest.raises(PhantomError, match=message):
        args.run(args)


def test_a_band_that_misses_the_scenes_modulus_is_refused():
    scene = load_scene("builtin")
    measurements = Measurements(np.array([[0.0, 0, 0], [1e3, 0, 0], [0, 1e3, 0]]), np.array([26e-6, 27e-6, 27e-6]))
    with pytest.raises(CalibrationError, match="must hold the scene's modulus"):
        calibrate(scene, measurements, parse_grid(["lobe_chamber_scale=1"]), modulus_band_pa=(60e3, 80e3))


@pytest.mark.parametrize("items, message", [
    (["stiffness=1,2"], "unknown parameter 'stiffness'"),
    (["gent_jm=3,x"], "with numbers"),
    (["gent_jm=5,3"], "strictly increasing"),
    (["gent_jm=3", "gent_jm=4"], "twice"),
])
def test_bad_grids_say_what_is_wrong(items, message):
    with pytest.raises(CalibrationError, match=message):
        parse_grid(items)
    assert parse_grid(["lobe_chamber_scale=1,1.1"]).names == ("lobe_chamber_scale",)


def _synthetic_csv(tmp_path, scene_path, pressures_kpa):
    truth = PhantomModel.from_scene(load_scene(scene_path))
    lines = ["p0_kpa,p1_kpa,p2_kpa,measured_ml"]
    for pressures in np.asarray(pressures_kpa, dtype=float):
        volume_ml = truth.equilibrium(pressures * 1e3).gland_volume_m3 * 1e6
        lines.append(",".join(f"{value:g}" for value in pressures) + f",{volume_ml!r}")
    csv_path = tmp_path / f"{scene_path.stem}.csv"
    csv_path.write_text("\n".join(lines) + "\n")
    return csv_path


@pytest.mark.slow
def test_calibrate_recovers_known_material_and_geometry_on_a_two_worker_cluster(tmp_path, capsys, dask_scheduler):
    # Synthetic measurements from the model itself (linear law: cheap solves) at E = 100 kPa (strains within
    # the law's 10 %), lobes scaled 1.1.
    truth_path = tmp_path / "truth.toml"
    truth_path.write_text(SCENE_TEXT.format(model="linear", modulus=100.0) + "lobe_chamber_scale = 1.1\n")
    csv_path = _synthetic_csv(tmp_path, truth_path, [[0, 0, 0], [2, 0, 0], [0, 2, 0], [1, 2, 2], [2, 1, 1]])
    start_path = tmp_path / "start.toml"
    start_path.write_text(SCENE_TEXT.format(model="linear", modulus=120.0))
    output = tmp_path / "out" / "calibrated.toml"
    argv = ["calibrate", "--scene", str(start_path), "--measurements", str(csv_path), "--grid",
            "lobe_chamber_scale=1,1.1,1.2", "--scheduler", dask_scheduler, "--output", str(output), "--json"]
    args = _parse(argv)
    assert args.run(args) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["youngs_modulus_kpa"] == pytest.approx(100.0, rel=2e-3)
    assert report["parameters"]["lobe_chamber_scale"] == pytest.approx(1.1, abs=2e-3)
    assert report["fit_mean_abs_pct_error"] < 0.01
    assert report["loo_mean_abs_pct_error"] < 0.05
    assert report["validity"]["min_det"] > 0 and report["validity"]["max_stretch"] <= 1.1
    written = load_scene(output)
    assert written.geometry.lobe_chamber_scale == pytest.approx(1.1, abs=2e-3)
    assert written.material.youngs_modulus_pa == pytest.approx(100e3, rel=2e-3)
    # The same calibration again reads every trace from the cache.
    args = _parse(argv)
    assert args.run(args) == 0
    assert json.loads(capsys.readouterr().out)["traces_solved_now"] == 0


@pytest.mark.slow
def test_the_traces_interpolation_agrees_with_full_solves_at_a_gent_fit(tmp_path, capsys, dask_scheduler):
    # The leave-one-out predictions are the traces' interpolation, so it must match independent full solves at
    # the fitted parameters (continuation in four steps straight to the fitted modulus) on the paper's data.
    args = _parse(["calibrate", "--measurements", str(MEASUREMENTS), "--material", "gent", "--gent-jm", "3",
                   "--size-mm", "5", "--grid", "lobe_chamber_scale=1.2", "--scheduler", dask_scheduler,
                   "--output", str(tmp_path / "gent.toml"), "--json"])
    assert args.run(args) == 0
    report = json.loads(capsys.readouterr().out)
    full, interpolated = np.array(report["fit_predicted_ml"]), np.array(report["fit_interpolated_ml"])
    assert np.max(np.abs(interpolated - full) / full) < 0.01


@pytest.mark.slow
def test_a_left_out_point_beyond_its_trace_is_predicted_by_a_full_solve(tmp_path, capsys, dask_scheduler):
    # Exact measurements of a Neo-Hookean model at E = 10 kPa, but the last point's growth divided by 2.5: its
    # trace stops at 1.8 times that growth, so with it left out the others refit E = 10 kPa, beyond its trace.
    # Its leave-one-out prediction must be the model's volume at the refit (a solve straight from rest), not a
    # trace's end.
    truth_path = tmp_path / "truth.toml"
    truth_path.write_text(SCENE_TEXT.format(model="neo_hookean", modulus=10.0))
    points = [[0, 0, 0], [2, 0, 0], [0, 2, 0], [1, 2, 2], [2, 1, 1]]
    csv_path = _synthetic_csv(tmp_path, truth_path, points)
    rows = csv_path.read_text().splitlines()
    rest_ml, truth_ml = float(rows[1].split(",")[-1]), float(rows[-1].split(",")[-1])
    rows[-1] = "2,1,1," + repr(rest_ml + (truth_ml - rest_ml) / 2.5)
    csv_path.write_text("\n".join(rows) + "\n")
    args = _parse(["calibrate", "--scene", str(truth_path), "--measurements", str(csv_path), "--grid",
                   "lobe_chamber_scale=1", "--scheduler", dask_scheduler, "--output", str(tmp_path / "x.toml"),
                   "--json"])
    assert args.run(args) == 0
    report = json.loads(capsys.readouterr().out)
    loo_modulus_kpa = report["loo_youngs_modulus_kpa"][-1]
    assert loo_modulus_kpa == pytest.approx(10.0, rel=0.03)
    refit_path = tmp_path / "refit.toml"
    refit_path.write_text(SCENE_TEXT.format(model="neo_hookean", modulus=loo_modulus_kpa))
    refit_ml = PhantomModel.from_scene(load_scene(refit_path)).equilibrium([2e3, 1e3, 1e3]).gland_volume_m3 * 1e6
    assert report["loo_predicted_ml"][-1] == pytest.approx(refit_ml, rel=1e-4)
    assert report["loo_predicted_ml"][-1] == pytest.approx(truth_ml, rel=0.01)


@pytest.mark.slow
def test_a_small_strain_law_is_held_to_its_range_and_says_the_constraint_binds(tmp_path, capsys,
                                                                              dask_scheduler):
    # Measurements of a soft phantom (8 kPa): fitting them needs strains far beyond the linear law's 10 %.
    truth_path = tmp_path / "soft.toml"
    truth_path.write_text(SCENE_TEXT.format(model="linear", modulus=8.0))
    csv_path = _synthetic_csv(tmp_path, truth_path, [[0, 0, 0], [2, 0, 0], [0, 2, 2]])
    args = _parse(["calibrate", "--scene", str(truth_path), "--measurements", str(csv_path), "--grid",
                   "lobe_chamber_scale=1,1.1", "--scheduler", dask_scheduler, "--output", str(tmp_path / "x.toml"),
                   "--json"])
    assert args.run(args) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["validity"]["max_stretch"] <= 1.1
    assert "leave the linear law's range 0.9-1.1 (a finite-strain law holds there: --material gent" in (
        report["binding_constraint"])
    assert report["youngs_modulus_kpa"] > 8.0 * 1.5 and report["fit_mean_abs_pct_error"] > 1.0


def test_measurements_above_3_kpa_are_refused(tmp_path):
    csv_path = tmp_path / "high.csv"
    csv_path.write_text("p0_kpa,p1_kpa,p2_kpa,measured_ml\n0,0,0,26\n4,0,0,30\n0,1,0,27\n")
    args = _parse(["calibrate", "--measurements", str(csv_path), "--size-mm", "6"])
    with pytest.raises(CalibrationError, match="4 kPa is above the 3 kPa"):
        args.run(args)


SCENE_TEXT = ('[phantom]\nmesh = "builtin:prostate"\nchambers = ["chamber0", "chamber1", "chamber2"]\n'
              'fixed = "fixed"\n[material]\nmodel = "{model}"\nyoungs_modulus_kpa = {modulus}\n'
              'poisson_ratio = 0.45\n[geometry]\nmesh_size_mm = 6.0\n')


def _parse(argv):
    import argparse

    from phantom.cli import calibrate as calibrate_cli

    parser = argparse.ArgumentParser(prog="phantom")
    calibrate_cli.register(parser.add_subparsers(dest="command", required=True))
    return parser.parse_args(argv)


def test_the_written_scene_keeps_every_table_and_rebases_a_relative_mesh(tmp_path):
    source_folder = tmp_path / "source"
    source_folder.mkdir()
    (source_folder / "phantom.msh").write_text("not read here")
    scene_path = source_folder / "scene.toml"
    scene_path.write_text(
        '[phantom]\nmesh = "phantom.msh"\nunits = "mm"\nchambers = ["a", "b"]\nfixed = "base"\n'
        '[material]\nmodel = "corotational"\nyoungs_modulus_kpa = 50.0\npoisson_ratio = 0.45\n'
        '[model]\nfidelity = "rest"\naccuracy_pct = 2.0\n'
        '[[steps]]\nat_s = 0\nvolume_ml = 30\ngrowth_ratio = { chamber1 = 2.0, chamber2 = 1.0 }\n'
        '[[steps]]\nat_s = 5\npressures_kpa = [1.0, 0.5]\nramp_s = 2\n')
    scene = load_scene(scene_path)
    output = tmp_path / "elsewhere" / "calibrated.toml"
    result = CalibrationResult("linear", Grid((), ()), {}, 12345.0, *([np.zeros(2)] * 4), np.zeros(2), [],
                               np.zeros(0), {}, 0, 0)
    write_calibrated_scene(scene, result, output, "a comment\nover two lines")
    written = load_scene(output)
    assert written.material.youngs_modulus_pa == pytest.approx(12345.0)
    assert written.material.model == "linear"
    assert Path(written.mesh) == (source_folder / "phantom.msh").resolve()
    assert written.raw["model"] == {"fidelity": "rest", "accuracy_pct": 2.0}
    assert written.steps == scene.steps
    assert output.read_text().startswith("# a comment\n# over two lines\n")
    # a finite-strain fit gets the response table (a daemon cannot wait for full solves), unless the scene
    # already names a fidelity
    gent = dataclasses.replace(result, material_model="gent", parameters={"gent_jm": 3.0})
    write_calibrated_scene(scene, gent, output)
    assert load_scene(output).raw["model"]["fidelity"] == "rest"
    scene_path.write_text(scene_path.read_text().replace('fidelity = "rest"\n', ""))
    write_calibrated_scene(load_scene(scene_path), gent, output)
    assert load_scene(output).raw["model"] == {"fidelity": "table", "accuracy_pct": 2.0}
    with pytest.raises(CalibrationError, match="non-finite"):
        dump_toml({"material": {"youngs_modulus_kpa": float("nan")}})


def test_the_material_anchored_calibrations_scene_is_the_cast_silicone_on_10_node_elements():
    # bench/README.md's material-anchored calibration starts from this scene: the published modulus, nearly
    # incompressible 10-node elements, walls down to a lost-wax cast's 1 mm.
    scene = load_scene(Path(__file__).resolve().parents[1] / "bench" / "calibration_ecoflex.toml")
    assert scene.material.youngs_modulus_pa == 50e3 and scene.material.poisson_ratio >= 0.4995
    assert scene.geometry.element_order == 2 and scene.geometry.min_wall_mm == 1.0


def test_a_measurements_medium_column_says_where_each_point_hung(tmp_path):
    path = tmp_path / "m.csv"
    path.write_text("p0_kpa,measured_ml,medium\n0,26,air\n1,27, Water \n2,28,\n")
    assert load_measurements(path).media == ("air", "water", "air")  # blank: hanging in air, the default
    assert load_measurements(MEASUREMENTS).media == ("air",) * 8  # no column: every point in air
    path.write_text("p0_kpa,measured_ml,medium\n0,26,air\n1,27,oil\n2,28,air\n")
    with pytest.raises(CalibrationError, match=r"data row 2: medium 'oil' is not one of air, water"):
        load_measurements(path)


@pytest.mark.slow
@pytest.mark.parametrize("medium", ["air", "water"])
def test_a_ray_traced_under_gravity_is_the_full_solve_at_the_modulus_its_load_factor_stands_for(medium):
    """E is a load factor only if the body force scales with it too: the state at pressures p, weight b and
    modulus E0 / t is the one at (t p, t b) and E0. Checked against independent full solves at E0 / t."""
    from phantom.model.calibration.calibrate import ray_task
    from phantom.model.calibration.sweep import trace_ray
    from phantom.model.scene import Load

    scene = dataclasses.replace(load_scene("builtin:calibrated"), load=Load(gravity_m_s2=(0.0, 0.0, -9.80665)))
    raw = {**scene.raw, "load": {"gravity_m_s2": [0.0, 0.0, -9.80665]}}
    raw["geometry"] = {**raw["geometry"], "mesh_size_mm": 6.0}
    measurements = Measurements(np.array([[0.0, 0, 0], [1e3, 0, 0]]), np.array([26e-6, 27e-6]), media=(medium,) * 2)
    model = PhantomModel.from_scene(scene, mesh_size_mm=6.0)
    for row in range(2):
        task = ray_task(scene, raw, measurements, row, (0.0, 0.5, 2.0))
        trace = trace_ray(task)
        assert trace.stopped == "end"
        assert trace.gland_m3[0] == model.rest_gland_volume_m3  # t = 0: an infinitely stiff silicone
        for k, load_factor in enumerate(task.load_factors[1:], start=1):
            softer = model.with_material(youngs_modulus_pa=scene.material.youngs_modulus_pa / load_factor)
            state = softer.equilibrium(measurements.pressures_pa[row],
                                       body_force_n_per_m3=list(scene.load.body_force_n_per_m3(medium)))
            assert trace.gland_m3[k] == pytest.approx(state.gland_volume_m3, rel=1e-7)
            np.testing.assert_allclose(trace.chamber_m3[k], state.chamber_volumes_m3, rtol=1e-6)
        assert trace.gland_m3[-1] != trace.gland_m3[0]  # the weight alone moves the zero-pressure row too


@pytest.mark.long  # six 10-node solves, 30-35 s of CPU in make test's 20 minutes: make test-long runs it
@pytest.mark.timeout(900)  # six 10-node solves: about half a minute idle, minutes at a load average of 20
def test_a_trace_started_from_extrapolated_equilibria_is_the_trace_started_from_the_last_one(monkeypatch):
    """The traces' predictor (the last equilibria extrapolated in the load factor, positions and element
    pressures) only changes where Newton starts: the 10-node ray at (3, 1, 2) kPa gives the same states, to the
    solver's tolerance, as solves that each start from the previous equilibrium (PREDICTOR_POINTS = 1, what the
    traces did before), in fewer Newton iterations."""
    from phantom.model.calibration import sweep
    from phantom.model.calibration.calibrate import ray_task

    scene = load_scene(Path(__file__).resolve().parents[1] / "bench" / "calibration_ecoflex.toml")
    raw = {**scene.raw, "material": {**scene.raw["material"], "gent_jm": 5.0}}
    measurements = load_measurements(MEASUREMENTS, n_chambers=3)
    task = ray_task(scene, raw, measurements, 7, (0.0, 1.5, 3.0, 4.5))  # E = 50 kPa / t: down to 11 kPa
    iterations: list[int] = []
    solve = PhantomModel.equilibrium

    def counted(self, *args, **kwargs):
        state = solve(self, *args, **kwargs)
        iterations.append(state.iterations)
        return state

    monkeypatch.setattr(PhantomModel, "equilibrium", counted)
    predicted = sweep.trace_ray(task)
    predicted_iterations, iterations[:] = sum(iterations), []
    monkeypatch.setattr(sweep, "PREDICTOR_POINTS", 1)
    from_last = sweep.trace_ray(task)
    assert predicted.stopped == from_last.stopped == "end"
    np.testing.assert_allclose(predicted.gland_m3, from_last.gland_m3, rtol=1e-7)
    np.testing.assert_allclose(predicted.chamber_m3, from_last.chamber_m3, rtol=1e-6)
    np.testing.assert_allclose(predicted.max_i1_minus_3, from_last.max_i1_minus_3, rtol=1e-4)
    assert predicted_iterations < sum(iterations)
