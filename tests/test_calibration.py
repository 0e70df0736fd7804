"""Calibration: measurement loading, the one-dimensional fit, leave-one-out, and the scene it writes.

The end-to-end check uses synthetic measurements made by the real model at a known modulus (independent
solves at E_true), so the right answer is known; the figures on the real measurements are in bench/README.md.
"""

import json
from pathlib import Path

import numpy as np
import pytest

from phantom.model import PhantomModel, load_scene
from phantom.model.calibrate import (
    CalibrationError,
    RayResponses,
    dump_toml,
    fit_linear_compliance,
    fit_load_factor,
    load_measurements,
    write_calibrated_scene,
)

MEASUREMENTS = Path(__file__).resolve().parent.parent / "model" / "data" / "forward_measurements.csv"
COARSE_MM = 6.0


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


def test_the_linear_compliance_fit_is_ordinary_relative_least_squares():
    rng = np.random.default_rng(3)
    pressures_pa = rng.uniform(0, 3000, size=(7, 3))
    slope = np.array([2e-9, 1.5e-9, 1e-9])
    measured = 26e-6 + 1.3 * pressures_pa @ slope + rng.normal(scale=2e-8, size=7)
    rays = [0, 1, 2, 4, 5, 6]
    factor = fit_linear_compliance(26e-6, slope, pressures_pa, measured, rays)
    # The same problem through numpy's least squares: minimise |(26e-6 + t h.p - m) / m|.
    design = (pressures_pa[rays] @ slope / measured[rays])[:, None]
    expected, *_ = np.linalg.lstsq(design, (measured[rays] - 26e-6) / measured[rays], rcond=None)
    assert factor == pytest.approx(expected[0], rel=1e-12)


def test_the_load_factor_fit_recovers_a_known_curve_minimum():
    load_factors = np.linspace(0, 4, 41)
    slopes = np.array([1.0, 2.0, 3.0])[:, None] * 1e-6
    # G_j(t) = 26 ml + a_j t + 0.2 a_j t^2: smooth, convex, like a softening response.
    volumes = 26e-6 + slopes * load_factors + 0.2 * slopes * load_factors**2
    responses = RayResponses(load_factors, volumes, 4.0, np.full(3, 4.0))
    true_factor = 2.37
    measured = 26e-6 + slopes[:, 0] * true_factor * (1 + 0.2 * true_factor)
    assert fit_load_factor(responses, measured, [0, 1, 2]) == pytest.approx(true_factor, rel=1e-4)
    assert fit_load_factor(responses, measured, [1]) == pytest.approx(true_factor, rel=1e-4)


def test_calibrate_recovers_a_known_modulus_from_the_models_own_measurements(tmp_path, capsys, monkeypatch):
    scene = load_scene("builtin")
    model = PhantomModel.from_scene(scene, mesh_size_mm=COARSE_MM)
    youngs_true_pa = 40e3
    truth = model.with_material(youngs_modulus_pa=youngs_true_pa)
    pressures_kpa = np.array([[0, 0, 0], [4, 0, 0], [2, 3, 3]], dtype=float)
    lines = ["p0_kpa,p1_kpa,p2_kpa,measured_ml"]
    for pressures in pressures_kpa:
        volume_ml = truth.solve(pressures * 1e3).gland_volume_m3 * 1e6
        lines.append(",".join(f"{value:g}" for value in pressures) + f",{volume_ml!r}")
    csv_path = tmp_path / "synthetic.csv"
    csv_path.write_text("\n".join(lines) + "\n")

    import argparse

    from phantom.model import calibrate as calibrate_module
    from phantom.model import inverse_cli

    parser = argparse.ArgumentParser(prog="phantom")
    inverse_cli.register(parser.add_subparsers(dest="command", required=True))
    output = tmp_path / "calibrated.toml"
    args = parser.parse_args(["calibrate", "--scene", "builtin", "--size-mm", str(COARSE_MM), "--measurements",
                              str(csv_path), "--output", str(output), "--json"])
    # A coarse continuation that stops just past the data keeps the test quick.
    monkeypatch.setattr(calibrate_module, "STEPS_PER_LINEAR_LOAD_FACTOR", 8)
    monkeypatch.setattr(calibrate_module, "OVERSHOOT", 1.15)
    assert args.run(args) == 0
    report = json.loads(capsys.readouterr().out)
    assert set(report) >= {"youngs_modulus_kpa", "fit_mean_abs_pct_error", "loo_mean_abs_pct_error"}
    # The co-rotational fit is exact up to the interpolation of the ray responses, and is the one kept.
    assert report["material_model"] == "corotational"
    assert report["youngs_modulus_kpa"] == pytest.approx(youngs_true_pa / 1e3, rel=5e-3)
    assert report["fit_mean_abs_pct_error"] < 0.02
    assert report["loo_mean_abs_pct_error"] < 0.05
    assert report["candidates"]["linear"]["loo_mean_abs_pct_error"] > report["loo_mean_abs_pct_error"]
    written = load_scene(output)
    assert written.material.youngs_modulus_pa == pytest.approx(report["youngs_modulus_kpa"] * 1e3, rel=1e-4)
    assert written.material.model == "corotational"
    assert written.mesh == "builtin:prostate"


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
    write_calibrated_scene(scene, 12345.0, output, "a comment\nover two lines", material_model="linear")
    written = load_scene(output)
    assert written.material.youngs_modulus_pa == pytest.approx(12345.0)
    assert written.material.model == "linear"
    assert Path(written.mesh) == (source_folder / "phantom.msh").resolve()
    assert written.raw["model"] == {"fidelity": "rest", "accuracy_pct": 2.0}
    assert written.steps == scene.steps
    assert output.read_text().startswith("# a comment\n# over two lines\n")
    with pytest.raises(CalibrationError, match="non-finite"):
        dump_toml({"material": {"youngs_modulus_kpa": float("nan")}})
