"""The inverse on the real finite-element model: its answer, checked by an independent forward solve.

A coarse built-in mesh (6 mm) keeps this quick. The check is what the user does: solve the forward model at
the returned pressures and compare with the target (issue: within 0.1 %).
"""

import argparse
import json

import numpy as np
import pytest

from phantom.cli import inverse as inverse_cli
from phantom.model import PhantomModel, load_scene
from phantom.model.inverse import InverseSolver
from phantom.model.target import Target, UnreachableTargetError

COARSE_MM = 6.0


@pytest.fixture(scope="module")
def model():
    return PhantomModel.from_scene(load_scene("builtin"), mesh_size_mm=COARSE_MM)


def run_cli(*arguments: str) -> tuple[int, str]:
    parser = argparse.ArgumentParser(prog="phantom")
    inverse_cli.register(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(arguments)
    return args.run(args), args


def test_the_cli_answer_meets_the_target_on_the_full_model_within_0_1_percent(model, capsys):
    target_ml = model.rest_gland_volume_m3 * 1e6 + 0.8
    status, _ = run_cli("inverse", "--scene", "builtin", "--size-mm", str(COARSE_MM), "--volume-ml", str(target_ml),
                        "--pressure-max-kpa", "20", "--fidelity", "full", "--json")
    assert status == 0
    report = json.loads(capsys.readouterr().out)
    assert set(report) >= {"pressures_kpa", "predicted_volume_ml", "iterations", "solve_time_s"}
    # The forward model, solved afresh at the answer, is the independent check.
    check = model.equilibrium(np.array(report["pressures_kpa"]) * 1e3)
    assert check.gland_volume_m3 * 1e6 == pytest.approx(target_ml, rel=1e-3)
    assert report["predicted_volume_ml"] == pytest.approx(target_ml, rel=1e-4)
    # The co-rotational response is not linear: the rest compliance alone is not enough, the tangent is updated.
    assert report["iterations"] >= 2
    assert all(value > 0 for value in report["pressures_kpa"])


def test_a_growth_ratio_holds_on_the_full_model(model):
    solver = InverseSolver(model, pressure_max_pa=20e3, fidelity="full")
    target_m3 = model.rest_gland_volume_m3 + 0.6e-6
    result = solver.pressures_for(Target(gland_volume_m3=target_m3, growth_ratio={1: 2.0, 2: 1.0}))
    check = model.equilibrium(result.pressures_pa)
    growth_m3 = check.chamber_volumes_m3 - model.rest_chamber_volumes_m3
    assert growth_m3[1] == pytest.approx(2.0 * growth_m3[2], rel=1e-3)
    assert check.gland_volume_m3 == pytest.approx(target_m3, rel=1e-4)
    # The mirror-image lobes: twice the growth needs a higher pressure in chamber 1 than in chamber 2.
    assert result.pressures_pa[1] > result.pressures_pa[2]


def test_an_unreachable_volume_states_the_range_the_full_model_reaches(model, capsys):
    with pytest.raises(UnreachableTargetError) as caught:
        run_cli("inverse", "--scene", "builtin", "--size-mm", str(COARSE_MM), "--volume-ml", "45",
                "--pressure-max-kpa", "3", "--fidelity", "full")
    message = str(caught.value)
    assert "45.000 ml is unreachable" in message and "between 0 and [3, 3, 3] kPa" in message
    lowest_ml, highest_ml = (float(value) for value in message.split(" give ")[1].split(" ml")[0].split(" to "))
    at_limit = model.equilibrium([3e3, 3e3, 3e3])
    assert highest_ml == pytest.approx(at_limit.gland_volume_m3 * 1e6, rel=1e-3)
    # The low end is the model at zero pressure, not the linearisation at the limit extrapolated down to zero.
    assert lowest_ml == pytest.approx(model.rest_gland_volume_m3 * 1e6, abs=5e-4)  # printed to 0.001 ml


def test_raw_pressures_and_chamber_targets_through_the_cli(model, capsys):
    status, _ = run_cli("inverse", "--scene", "builtin", "--size-mm", str(COARSE_MM), "--pressures-kpa", "1,0,2",
                        "--fidelity", "rest", "--json")
    assert status == 0
    report = json.loads(capsys.readouterr().out)
    assert report["pressures_kpa"] == [1.0, 0.0, 2.0]
    assert report["iterations"] == 0
    wanted_ml = model.rest_chamber_volumes_m3[0] * 1e6 + 0.05
    status, _ = run_cli("inverse", "--scene", "builtin", "--size-mm", str(COARSE_MM), "--chamber-volumes-ml",
                        f"{wanted_ml},-,-", "--fidelity", "rest", "--json")
    report = json.loads(capsys.readouterr().out)
    assert report["predicted_chamber_volumes_ml"][0] == pytest.approx(wanted_ml, rel=1e-6)


def test_growth_limits_through_the_cli(model, capsys):
    target_ml = model.rest_gland_volume_m3 * 1e6 + 0.3
    status, _ = run_cli("inverse", "--scene", "builtin", "--size-mm", str(COARSE_MM), "--volume-ml", str(target_ml),
                        "--pressure-max-kpa", "20", "--max-growth-ml", "0.1,-,-", "--fidelity", "rest", "--json")
    report = json.loads(capsys.readouterr().out)
    assert report["predicted_chamber_volumes_ml"][0] - model.rest_chamber_volumes_m3[0] * 1e6 <= 0.1 + 1e-6
    assert report["predicted_volume_ml"] == pytest.approx(target_ml, rel=1e-6)


@pytest.mark.parametrize("arguments, message", [
    (("--volume-ml", "30", "--growth-ratio", "1:two"), "NAME=WEIGHT pairs"),
    (("--chamber-volumes-ml", "1,x,2"), "comma-separated numbers"),
    (("--pressures-kpa", "1,1,1", "--growth-ratio", "1:2,2:1"), "goes with --volume-ml"),
    (("--volume-ml", "26.5", "--max-growth-ml", "0.1,0.1"), "has 2 values; the scene has 3 chambers"),
])
def test_cli_input_errors_say_what_to_do(arguments, message):
    from phantom import PhantomError

    with pytest.raises(PhantomError, match=message):
        run_cli("inverse", "--scene", "builtin", "--size-mm", str(COARSE_MM), "--fidelity", "rest", *arguments)


@pytest.fixture(scope="module")
def converged():
    return PhantomModel.from_scene(load_scene("builtin:converged"))


@pytest.mark.parametrize("fidelity", ["rest", "updated", "full", "table"])
def test_a_volume_beyond_the_tables_solves_is_refused_on_every_fidelity_without_a_solve(converged, fidelity):
    """The converged scene ships the full solves over its pressure box (its response table): a target beyond
    their range is refused with it at once on every level, the full one included (a full solve at the limit
    took a minute before), with no solve and no tangent."""
    from phantom.model.fidelity.response_table import stored_response_table

    table = stored_response_table(converged, 3000.0)
    assert table is not None
    solver = InverseSolver(converged, fidelity=fidelity)
    for target, values in ((Target(gland_volume_m3=60e-6), table.gland_values),
                           (Target(chamber_volumes_m3=[1e-6, None, None]), table.chamber_values[..., 0])):
        with pytest.raises(UnreachableTargetError) as caught:
            solver.pressures_for(target)
        message = str(caught.value)
        assert "is unreachable: pressures between 0 and [3, 3, 3] kPa give" in message, message
        assert f"give {values.min() * 1e6:.3f} to {values.max() * 1e6:.3f} ml" in message, message
        # the gland's range as data too (the daemon's verify loop asks for its edge); a chamber's is not the gland's
        expected = (values.min() * 1e6, values.max() * 1e6) if target.gland_volume_m3 else None
        assert caught.value.gland_range_ml == (None if expected is None else pytest.approx(expected))
        assert not caught.value.corrected
    assert solver.estimator.counts == {"full_solves": 0, "tangent_solves": 0, "shapes": 0}
    # a target within the range is not refused by the bound (the rest level answers it here: no solve)
    if fidelity == "rest":
        result = solver.pressures_for(Target(gland_volume_m3=30e-6))
        assert result.predicted_gland_volume_m3 == pytest.approx(30e-6, rel=1e-4)


def test_a_table_shipped_for_another_model_gives_no_bound_and_refuses_nothing(converged):
    """The same scene at another modulus ships no table for itself: the inverse bounds nothing from the scene's
    (made for the fitted modulus), and answers as before (here the rest level: no solve)."""
    stiffer = converged.with_material(youngs_modulus_pa=2.0 * converged.material.youngs_modulus_pa)
    solver = InverseSolver(stiffer, fidelity="rest")
    assert solver.solved_range_m3() is None
    result = solver.pressures_for(Target(gland_volume_m3=28e-6))
    assert result.predicted_gland_volume_m3 == pytest.approx(28e-6, rel=1e-4)
