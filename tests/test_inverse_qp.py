"""The inverse QP and its outer iteration, against independent truths, on stand-in forward models.

These are unit tests of the inverse layer alone: the forward model is replaced by a closed-form one (linear,
or a smooth nonlinear one with an exact tangent) so that the right answer is known independently. The same
solver on the real finite-element model is tested in test_inverse_fem.py.
"""

from types import SimpleNamespace

import numpy as np
import pytest
from scipy.optimize import minimize

from phantom import PhantomError
from phantom.model.errors import SolveError
from phantom.model.inverse import (
    InverseSolver,
    LimitPointError,
    Target,
    UnreachableTargetError,
)
from phantom.model.scene import ModelSettings

ML = 1e-6          # m^3 per ml
KPA = 1e3          # Pa per kPa
ML_PER_KPA = 1e-9  # (m^3/Pa) per (ml/kPa)


class LinearStandIn:
    """A forward model that is exactly linear: c = c0 + W p, g = g0 + h . p (given in ml and kPa)."""

    # PhantomModel's attributes that the inverse reads: the default model settings (no scene), and the general
    # (nonlinear, warm-started) formulation, which SofteningStandIn below is.
    model_settings = ModelSettings()
    formulation = "corotational"

    def __init__(self, chamber_ml_per_kpa, gland_ml_per_kpa, rest_chambers_ml, rest_gland_ml):
        self.chamber_ml_per_kpa = np.asarray(chamber_ml_per_kpa, dtype=float)
        self.gland_ml_per_kpa = np.asarray(gland_ml_per_kpa, dtype=float)
        self.n_chambers = len(self.gland_ml_per_kpa)
        self.rest_chamber_volumes_m3 = np.asarray(rest_chambers_ml, dtype=float) * ML
        self.rest_gland_volume_m3 = rest_gland_ml * ML
        self.nodes_m = np.zeros((1, 3))

    def compliance(self, state=None):
        return SimpleNamespace(chamber_m3_per_pa=self.chamber_ml_per_kpa * ML_PER_KPA,
                               gland_m3_per_pa=self.gland_ml_per_kpa * ML_PER_KPA,
                               displacement_m_per_pa=np.zeros((self.n_chambers, 1, 3)))


class SofteningStandIn(LinearStandIn):
    """A smooth nonlinear model with an exact tangent: each volume change ``d`` of the linear model becomes
    ``d (1 + d / scale)`` (the response softens as the phantom inflates), and past ``limit_kpa`` of summed
    pressure there is no equilibrium (the solve raises, as a snap-through does)."""

    def __init__(self, *args, scale_ml=20.0, limit_kpa=np.inf):
        super().__init__(*args)
        self.scale_ml = scale_ml
        self.limit_kpa = limit_kpa
        self.solves = 0

    def _volumes_ml(self, pressures_kpa):
        chamber_change = self.chamber_ml_per_kpa @ pressures_kpa
        gland_change = self.gland_ml_per_kpa @ pressures_kpa
        return (self.rest_chamber_volumes_m3 / ML + chamber_change * (1 + chamber_change / self.scale_ml),
                self.rest_gland_volume_m3 / ML + gland_change * (1 + gland_change / self.scale_ml))

    def equilibrium(self, pressures_pa, formulation=None, initial_positions_m=None):
        self.solves += 1
        pressures_kpa = np.asarray(pressures_pa) / KPA
        if pressures_kpa.sum() > self.limit_kpa:
            raise SolveError(f"no equilibrium at {pressures_kpa.tolist()} kPa")
        chambers_ml, gland_ml = self._volumes_ml(pressures_kpa)
        return SimpleNamespace(positions_m=self.nodes_m, chamber_volumes_m3=chambers_ml * ML,
                               gland_volume_m3=gland_ml * ML, pressures_pa=np.asarray(pressures_pa, dtype=float))

    def compliance(self, state=None):
        if state is None:
            return super().compliance()
        pressures_kpa = np.asarray(state.pressures_pa) / KPA
        chamber_factor = 1 + 2 * (self.chamber_ml_per_kpa @ pressures_kpa) / self.scale_ml
        gland_factor = 1 + 2 * (self.gland_ml_per_kpa @ pressures_kpa) / self.scale_ml
        return SimpleNamespace(chamber_m3_per_pa=chamber_factor[:, None] * self.chamber_ml_per_kpa * ML_PER_KPA,
                               gland_m3_per_pa=gland_factor * self.gland_ml_per_kpa * ML_PER_KPA,
                               displacement_m_per_pa=np.zeros((self.n_chambers, 1, 3)))


COUPLED_W = np.array([[1.6, 0.3, 0.2], [0.3, 1.2, -0.1], [0.2, -0.1, 0.9]])   # ml/kPa, SPD
GLAND_H = np.array([2.0, 1.7, 1.5])                                            # ml/kPa
REST_CHAMBERS_ML = [1.5, 1.2, 1.1]
REST_GLAND_ML = 26.3


def least_energy_with_scipy(compliance_ml_per_kpa, equalities, bounds_kpa):
    """The limit epsilon -> 0+ of physics.md's regularised least squares, solved independently (SLSQP):
    minimise 1/2 x^T W x subject to rows . x = values and bounds (kPa, ml)."""
    constraints = [{"type": "eq", "fun": lambda x, row=row, value=value: row @ x - value}
                   for row, value in equalities]
    truth = minimize(lambda x: 0.5 * x @ compliance_ml_per_kpa @ x, np.full(len(bounds_kpa), 0.5),
                     jac=lambda x: compliance_ml_per_kpa @ x, method="SLSQP", bounds=bounds_kpa,
                     constraints=constraints, options={"ftol": 1e-14, "maxiter": 1000})
    assert truth.success, truth.message
    return truth.x


def test_total_volume_with_diagonal_compliance_matches_the_closed_form():
    compliance = np.diag([1.5, 1.0, 0.5])
    model = LinearStandIn(compliance, GLAND_H, REST_CHAMBERS_ML, REST_GLAND_ML)
    growth_ml = 8.0
    target = Target(gland_volume_m3=(REST_GLAND_ML + growth_ml) * ML)
    result = InverseSolver(model, fidelity="rest").pressures_for(target)
    # Lagrange: W x = lambda h and h . x = b give x = b W^-1 h / (h^T W^-1 h).
    inverse_h = GLAND_H / np.diag(compliance)
    expected_kpa = growth_ml * inverse_h / (GLAND_H @ inverse_h)
    np.testing.assert_allclose(result.pressures_pa / KPA, expected_kpa, rtol=1e-7)
    assert np.all(result.pressures_pa > 0)
    assert result.predicted_gland_volume_m3 / ML == pytest.approx(REST_GLAND_ML + growth_ml, rel=1e-9)
    assert result.iterations == 1


def test_the_answer_is_the_small_epsilon_limit_of_the_regularised_least_squares():
    model = LinearStandIn(COUPLED_W, GLAND_H, REST_CHAMBERS_ML, REST_GLAND_ML)
    result = InverseSolver(model, fidelity="rest").pressures_for(Target(gland_volume_m3=(REST_GLAND_ML + 7.0) * ML))
    for epsilon in (1e-4, 1e-6):
        # Unconstrained minimiser of 1/2 (h.x - b)^2 + eps/2 x^T W x, in closed form.
        regularised = np.linalg.solve(np.outer(GLAND_H, GLAND_H) + epsilon * COUPLED_W, GLAND_H * 7.0)
        np.testing.assert_allclose(result.pressures_pa / KPA, regularised, rtol=10 * epsilon)


def test_chamber_targets_with_an_active_bound_match_scipy():
    model = LinearStandIn(COUPLED_W, GLAND_H, REST_CHAMBERS_ML, REST_GLAND_ML)
    pressure_max_kpa = 1.5
    # Chamber 0 asks for more than p0 <= 1.5 kPa gives alone, so chamber 1 and 2 pressures must help it.
    targets_ml = [REST_CHAMBERS_ML[0] + 2.8, None, REST_CHAMBERS_ML[2] + 0.9]
    solver = InverseSolver(model, pressure_max_pa=pressure_max_kpa * KPA, fidelity="rest")
    target = Target(chamber_volumes_m3=[None if value is None else value * ML for value in targets_ml])
    result = solver.pressures_for(target)
    truth = least_energy_with_scipy(COUPLED_W, [(COUPLED_W[0], 2.8), (COUPLED_W[2], 0.9)],
                                    [(0, pressure_max_kpa)] * 3)
    assert np.isclose(truth, pressure_max_kpa).any(), "the case must have an active bound"
    np.testing.assert_allclose(result.pressures_pa / KPA, truth, atol=1e-6)
    np.testing.assert_allclose(result.predicted_chamber_volumes_m3[[0, 2]] / ML,
                               np.array(targets_ml)[[0, 2]].astype(float), rtol=1e-8)


def test_growth_ratio_shares_the_volume_as_asked_and_matches_scipy():
    model = LinearStandIn(COUPLED_W, GLAND_H, REST_CHAMBERS_ML, REST_GLAND_ML)
    target = Target(gland_volume_m3=(REST_GLAND_ML + 6.0) * ML, growth_ratio={1: 2.0, 2: 1.0})
    result = InverseSolver(model, fidelity="rest").pressures_for(target)
    growth_ml = result.predicted_chamber_volumes_m3 / ML - REST_CHAMBERS_ML
    assert growth_ml[1] == pytest.approx(2.0 * growth_ml[2], rel=1e-7)
    assert result.predicted_gland_volume_m3 / ML == pytest.approx(REST_GLAND_ML + 6.0, rel=1e-9)
    truth = least_energy_with_scipy(COUPLED_W, [(GLAND_H, 6.0), (COUPLED_W[1] - 2.0 * COUPLED_W[2], 0.0)],
                                    [(0, 3)] * 3)
    np.testing.assert_allclose(result.pressures_pa / KPA, truth, atol=1e-6)


def test_a_gland_volume_beyond_the_pressure_limit_states_the_reachable_range():
    model = LinearStandIn(COUPLED_W, GLAND_H, REST_CHAMBERS_ML, REST_GLAND_ML)
    highest_ml = REST_GLAND_ML + GLAND_H.sum() * 3.0
    with pytest.raises(UnreachableTargetError) as caught:
        InverseSolver(model, pressure_max_pa=3 * KPA, fidelity="rest").pressures_for(Target(gland_volume_m3=60 * ML))
    message = str(caught.value)
    assert "60.000 ml is unreachable" in message
    assert f"{REST_GLAND_ML:.3f} to {highest_ml:.3f} ml" in message


def test_a_gland_volume_below_rest_is_unreachable():
    model = LinearStandIn(COUPLED_W, GLAND_H, REST_CHAMBERS_ML, REST_GLAND_ML)
    with pytest.raises(UnreachableTargetError, match=f"{REST_GLAND_ML:.3f} to"):
        InverseSolver(model, fidelity="rest").pressures_for(Target(gland_volume_m3=20 * ML))


def test_contradictory_chamber_targets_are_named_not_averaged():
    model = LinearStandIn(COUPLED_W, GLAND_H, REST_CHAMBERS_ML, REST_GLAND_ML)
    # Chamber 0 near its top needs p0 about 3 kPa, which alone grows chamber 2 by 0.6 ml: chamber 2 cannot stay
    # at rest + 0.05 ml although that value is reachable on its own.
    target = Target(chamber_volumes_m3=[(REST_CHAMBERS_ML[0] + 4.7) * ML, None, (REST_CHAMBERS_ML[2] + 0.05) * ML])
    with pytest.raises(UnreachableTargetError, match="contradicts the other targets"):
        InverseSolver(model, fidelity="rest").pressures_for(target)


@pytest.mark.parametrize("weight", [-1.0, 0.0, float("nan")])
def test_a_growth_ratio_that_asks_a_chamber_to_shrink_is_refused(weight):
    model = LinearStandIn(COUPLED_W, GLAND_H, REST_CHAMBERS_ML, REST_GLAND_ML)
    with pytest.raises(UnreachableTargetError, match="weights must be positive"):
        InverseSolver(model, fidelity="rest").pressures_for(Target(gland_volume_m3=30 * ML, growth_ratio={1: 1.0,
                                                                                                   2: weight}))


def test_growth_limits_bound_the_answer():
    model = LinearStandIn(COUPLED_W, GLAND_H, REST_CHAMBERS_ML, REST_GLAND_ML)
    limits_ml = [1.0, None, None]
    solver = InverseSolver(model, fidelity="rest", max_growth_m3=[None if v is None else v * ML for v in limits_ml])
    result = solver.pressures_for(Target(gland_volume_m3=(REST_GLAND_ML + 5.0) * ML))
    assert result.predicted_chamber_volumes_m3[0] / ML - REST_CHAMBERS_ML[0] <= 1.0 + 1e-6
    assert result.predicted_gland_volume_m3 / ML == pytest.approx(REST_GLAND_ML + 5.0, rel=1e-5)
    with pytest.raises(UnreachableTargetError, match="growth limits"):
        solver.pressures_for(Target(gland_volume_m3=(REST_GLAND_ML + 14.0) * ML))


@pytest.mark.parametrize("target, message", [
    (Target(gland_volume_m3=float("nan")), "must be finite"),
    (Target(gland_volume_m3=float("inf")), "must be finite"),
    (Target(chamber_volumes_m3=[1e-6, 1e-6]), "needs 3 entries"),
    (Target(), "the target is empty"),
    (Target(gland_volume_m3=30e-6, pressures_pa=[0, 0, 0]), "not both"),
    (Target(gland_volume_m3=30e-6, growth_ratio={1: 1.0, 7: 1.0}), "chambers are 0..2"),
    (Target(gland_volume_m3=30e-6, growth_ratio={1: 1.0}), "at least two chambers"),
    (Target(pressures_pa=[0.0, float("nan"), 0.0]), "must be finite"),
    (Target(pressures_pa=[0.0, 0.0]), "needs 3 values"),
])
def test_bad_targets_say_what_is_wrong(target, message):
    model = LinearStandIn(COUPLED_W, GLAND_H, REST_CHAMBERS_ML, REST_GLAND_ML)
    with pytest.raises(PhantomError, match=message):
        InverseSolver(model, fidelity="rest").pressures_for(target)


def test_raw_pressures_are_only_bounds_checked():
    model = LinearStandIn(COUPLED_W, GLAND_H, REST_CHAMBERS_ML, REST_GLAND_ML)
    solver = InverseSolver(model, pressure_max_pa=3 * KPA, fidelity="rest")
    result = solver.pressures_for(Target(pressures_pa=[1000.0, 0.0, 2000.0]))
    np.testing.assert_array_equal(result.pressures_pa, [1000.0, 0.0, 2000.0])
    assert result.predicted_gland_volume_m3 / ML == pytest.approx(REST_GLAND_ML + GLAND_H @ [1.0, 0.0, 2.0])
    for pressures in ([-1.0, 0.0, 0.0], [0.0, 3001.0, 0.0]):
        with pytest.raises(UnreachableTargetError, match=r"\(chamber [01]\) at (-0.001 kPa is below 0 kPa: the blowers "
                           r"only push|3.001 kPa is above the 3 kPa limit)"):
            solver.pressures_for(Target(pressures_pa=pressures))


def test_bad_solver_settings_are_refused():
    model = LinearStandIn(COUPLED_W, GLAND_H, REST_CHAMBERS_ML, REST_GLAND_ML)
    with pytest.raises(PhantomError, match="must be positive"):
        InverseSolver(model, pressure_max_pa=-1.0, fidelity="rest")
    with pytest.raises(PhantomError, match="finite"):
        InverseSolver(model, pressure_max_pa=float("nan"), fidelity="rest")
    singular = LinearStandIn(np.zeros((3, 3)), GLAND_H, REST_CHAMBERS_ML, REST_GLAND_ML)
    with pytest.raises(PhantomError, match="not positive definite"):
        InverseSolver(singular, fidelity="rest")


def test_one_problem_per_shape_is_set_up_and_reused_warm(capfd):
    model = LinearStandIn(COUPLED_W, GLAND_H, REST_CHAMBERS_ML, REST_GLAND_ML)
    solver = InverseSolver(model, fidelity="rest")
    answers = [solver.pressures_for(Target(gland_volume_m3=(REST_GLAND_ML + growth) * ML))
               for growth in (3.0, 6.0, 9.0)]
    assert len(solver._problems) == 1
    # Linear and unconstrained inside the bounds: the answer scales with the wanted growth.
    np.testing.assert_allclose(answers[2].pressures_pa, 3 * answers[0].pressures_pa, rtol=1e-6)
    # One target row again (a chamber instead of the gland): the same shape, the same problem, new values.
    chamber = solver.pressures_for(Target(chamber_volumes_m3=[(REST_CHAMBERS_ML[0] + 1.0) * ML, None, None]))
    assert len(solver._problems) == 1
    assert chamber.predicted_chamber_volumes_m3[0] / ML == pytest.approx(REST_CHAMBERS_ML[0] + 1.0, rel=1e-9)
    solver.pressures_for(Target(gland_volume_m3=30 * ML, growth_ratio={0: 1.0, 1: 1.0}))
    assert len(solver._problems) == 2
    # OSQP stays silent: the CLI's --json output is stdout.
    assert capfd.readouterr().out == ""


def test_the_outer_iteration_meets_the_nonlinear_model_and_reports_its_iterations():
    model = SofteningStandIn(COUPLED_W, GLAND_H, REST_CHAMBERS_ML, REST_GLAND_ML, scale_ml=10.0)
    solver = InverseSolver(model, fidelity="full")
    result = solver.pressures_for(Target(gland_volume_m3=40 * ML))
    check = model.equilibrium(result.pressures_pa)
    assert check.gland_volume_m3 / ML == pytest.approx(40.0, rel=2e-5)
    # The first, rest-compliance answer misses by the nonlinearity; Newton on the exact tangent then converges in
    # a few steps (quadratically), not the max.
    assert 2 <= result.iterations <= 6
    errors = [entry["relative_error"] for entry in result.history]
    assert errors[0] > 1e-2 and errors[-1] <= 2e-5


def test_the_outer_iteration_keeps_growth_ratios_on_the_nonlinear_model():
    model = SofteningStandIn(COUPLED_W, GLAND_H, REST_CHAMBERS_ML, REST_GLAND_ML, scale_ml=10.0)
    target = Target(gland_volume_m3=36 * ML, growth_ratio={1: 2, 2: 1})
    result = InverseSolver(model, fidelity="full").pressures_for(target)
    check = model.equilibrium(result.pressures_pa)
    growth_ml = check.chamber_volumes_m3 / ML - REST_CHAMBERS_ML
    assert growth_ml[1] == pytest.approx(2 * growth_ml[2], rel=1e-4)
    assert check.gland_volume_m3 / ML == pytest.approx(36.0, rel=2e-5)


def test_past_the_limit_point_the_inverse_says_so_instead_of_diverging():
    model = SofteningStandIn(COUPLED_W, GLAND_H, REST_CHAMBERS_ML, REST_GLAND_ML, scale_ml=10.0, limit_kpa=4.0)
    solver = InverseSolver(model, fidelity="full")
    # Reachable below the limit point...
    below = solver.pressures_for(Target(gland_volume_m3=32 * ML))
    assert model.equilibrium(below.pressures_pa).gland_volume_m3 / ML == pytest.approx(32.0, rel=2e-5)
    # ...but 45 ml needs more than 4 kPa in total, where the model has no equilibrium.
    with pytest.raises(LimitPointError, match="limit point"):
        solver.pressures_for(Target(gland_volume_m3=45 * ML))


@pytest.mark.parametrize("volume_ml", [1e300, -1e300, 1e200])
def test_an_absurd_volume_is_unreachable_with_the_range_and_leaves_no_state_behind(volume_ml):
    model = LinearStandIn(COUPLED_W, GLAND_H, REST_CHAMBERS_ML, REST_GLAND_ML)
    solver = InverseSolver(model, pressure_max_pa=3 * KPA, fidelity="rest")
    highest_ml = REST_GLAND_ML + GLAND_H.sum() * 3.0
    for _ in range(2):
        with pytest.raises(UnreachableTargetError, match=f"{REST_GLAND_ML:.3f} to {highest_ml:.3f} ml"):
            solver.pressures_for(Target(gland_volume_m3=volume_ml * ML))
    # the next targets, of the gland and of a chamber, are solved as on a fresh solver
    fresh = InverseSolver(model, pressure_max_pa=3 * KPA, fidelity="rest")
    for target in (Target(gland_volume_m3=30 * ML), Target(chamber_volumes_m3=[2.0 * ML, None, None])):
        np.testing.assert_allclose(solver.pressures_for(target).pressures_pa, fresh.pressures_for(target).pressures_pa,
                                   rtol=1e-9)


def test_a_qp_whose_solve_raises_is_set_up_afresh_next_time():
    from phantom.model.inverse import VolumeQP

    qp = VolumeQP(1, 1)
    hessian, linear, matrix = np.eye(1), np.zeros(1), np.eye(1)
    with pytest.raises(UnreachableTargetError, match="out of scale"):
        qp.minimise(hessian, linear, matrix, np.array([1e300]), np.array([1e300]))
    assert qp._problem is None
    pressures, _ = qp.minimise(hessian, linear, matrix, np.array([0.5]), np.array([0.5]))
    np.testing.assert_allclose(pressures, [0.5], atol=1e-8)


@pytest.mark.parametrize("target, kind, values, described, as_json", [
    (Target(gland_volume_m3=32 * ML), "volume", (32 * ML,), "32.00 ml", {"volume_ml": 32.0}),
    (Target(gland_volume_m3=40 * ML, growth_ratio={2: 1.0, 1: 2.0}), "volume", (40 * ML,),
     "40.00 ml (growth ratio chamber1:2, chamber2:1)", {"volume_ml": 40.0, "growth_ratio": {"1": 2.0, "2": 1.0}}),
    (Target(chamber_volumes_m3=[2.1 * ML, None, None]), "chamber_volumes", (2.1 * ML, None, None),
     "chamber 2.10,free,free ml", {"chamber_volumes_ml": [2.1, None, None]}),
    (Target(pressures_pa=[1000.0, 0.0, 2500.0]), "pressures", (1000.0, 0.0, 2500.0),
     "pressures 1.00,0.00,2.50 kPa", {"pressures_kpa": [1.0, 0.0, 2.5]}),
])
def test_a_target_says_its_kind_values_and_people_units(target, kind, values, described, as_json):
    assert target.kind == kind
    assert target.values == values
    assert target.describe() == described
    # ml and kPa read back as they were written (32 ml, not 32.000000000000004)
    assert target.to_json() == as_json
    assert Target.of_kind(kind, values, target.growth_ratio) == target


def test_a_chamber_volume_target_names_its_free_chambers():
    assert Target(chamber_volumes_m3=[None, 1.2 * ML, None]).free_chambers == (0, 2)
    assert Target(gland_volume_m3=30 * ML).free_chambers == ()


@pytest.mark.parametrize("make, message", [
    (lambda: Target().kind, "gives nothing"),
    (lambda: Target(gland_volume_m3=30 * ML, chamber_volumes_m3=[None, 1e-6, None]).kind,
     "volume and chamber_volumes"),
    (lambda: Target.of_kind("volume_ml", [30 * ML]), "unknown target kind 'volume_ml'"),
    (lambda: Target.of_kind("pressures", [1e3, 0, 0], {1: 2.0, 2: 1.0}), "goes with a gland volume"),
    (lambda: Target.of_kind("volume", [30 * ML, 31 * ML]), "one gland volume"),
    (lambda: Target.of_kind("pressures", [1e3, None, 0]), "a pressure for every chamber"),
])
def test_a_target_of_no_single_kind_says_so(make, message):
    with pytest.raises(PhantomError, match=message):
        make()


def test_the_answer_reports_itself_in_the_units_people_see():
    model = LinearStandIn(COUPLED_W, GLAND_H, REST_CHAMBERS_ML, REST_GLAND_ML)
    target = Target(gland_volume_m3=(REST_GLAND_ML + 3.0) * ML)
    result = InverseSolver(model, fidelity="rest").pressures_for(target)
    report = result.to_json()
    assert result.target == target
    assert report["target"] == {"volume_ml": REST_GLAND_ML + 3.0}
    np.testing.assert_allclose(report["pressures_kpa"], result.pressures_pa / KPA)
    assert report["predicted_volume_ml"] == pytest.approx(REST_GLAND_ML + 3.0, rel=1e-6)
    np.testing.assert_allclose(report["predicted_chamber_volumes_ml"], result.predicted_chamber_volumes_m3 / ML)
    assert (report["iterations"], report["solve_time_s"], report["qp_time_s"]) == (
        result.iterations, result.solve_time_s, result.qp_solve_time_s)


def test_targets_and_the_daemon_load_no_finite_element_model():
    """Target and InverseResult live in a light module: the daemon states targets and reads answers without
    importing scipy, numba or the FEM (its worker process builds the model)."""
    import subprocess
    import sys

    code = ("import sys, phantom.model.target, phantom.host.daemon; "
            "print(sorted(m for m in sys.modules if m.split('.')[0] in ('scipy', 'numba') "
            "or m.startswith(('phantom.model.fem', 'phantom.model.inverse'))))")
    loaded = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert loaded.strip() == "[]"
