"""Newton's method with a line search on the total energy, for an :class:`EquilibriumProblem` at one load.

Directions, cheapest first: "krylov" solves with the exact Hessian by conjugate gradients preconditioned with the
rest stiffness (factorised once per body: no factorisation per solve); "exact" factorises the Hessian (a
hyperelastic one shifted towards positive definite where it is not: Levenberg-Marquardt); "positive" factorises
a positive definite stand-in (``R K R^T``, or the small-strain stiffness), which gives a descent direction
whenever the Hessian does not. The linear formulation's rest stiffness is its exact tangent. Each step
is backtracked until the energy decreases (Armijo) or, where energy differences are lost in rounding, the
residual does; no accepted step inverts an element.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from phantom.model.arrays import FloatArray
from phantom.model.errors import SolveError
from phantom.model.fem.body import Factor, SolidBody
from phantom.model.fem.problem import EquilibriumProblem, Evaluation

#: Newton stops when |residual| <= RELATIVE_TOLERANCE * |pressure load|.
RELATIVE_TOLERANCE = 1e-9
#: Accept a residual this small relative to the load when Newton stops making progress (rounding).
ROUNDING_TOLERANCE = 1e-6
MAX_ITERATIONS_PER_STEP = 40
#: A load step fails when the residual has not halved in this many iterations (past a limit point).
STALLED_ITERATIONS = 6
#: A stalled residual within this factor of the rounding floor (eps |diag K| |x|) is blamed on conditioning.
ROUNDING_FLOOR_MARGIN = 1e3
#: Inexact Newton: relative residual of the preconditioned CG solve, and its iteration budget.
KRYLOV_TOLERANCE = 1e-3
KRYLOV_ITERATIONS = 25
#: A Newton step whose residual shrinks by less than this factor triggers a new tangent factorisation.
TANGENT_REFRESH_RATIO = 0.25
#: Halvings of a step before the line search gives up.
LINE_SEARCH_HALVINGS = 12


def dot(a: FloatArray, b: FloatArray) -> float:
    """``a . b`` without BLAS: OpenBLAS level-1 calls spin threads and cost milliseconds on a busy machine."""
    return float(np.einsum("i,i->", a, b))


def norm(a: FloatArray) -> float:
    """Euclidean norm without BLAS (see :func:`dot`)."""
    return float(np.sqrt(np.einsum("i,i->", a, a)))


@dataclass
class NewtonResult:
    """The outcome of one Newton solve at a fixed load: the last positions (n, 3) m, whether they converged, the
    iterations, and for a failure why (``reason``), the element at det F <= 0 if one is (else -1), and whether
    Newton stalled, with the smallest residual it reached and the floating-point floor of the residual, both
    relative to the load."""

    positions_m: FloatArray
    converged: bool
    iterations: int
    reason: str = ""
    worst_element: int = -1
    stalled: bool = False
    residual_ratio: float = 0.0
    rounding_floor_ratio: float = 0.0

    @property
    def ill_conditioned(self) -> bool:
        """Newton stalled (no inverted element) with its residual down at what rounding in the positions alone
        produces, so no iteration or smaller load step can meet the tolerance."""
        return (self.stalled and self.worst_element < 0
                and self.residual_ratio <= ROUNDING_FLOOR_MARGIN * self.rounding_floor_ratio)

    def error(self, problem: EquilibriumProblem, load_fraction: float) -> SolveError:
        """A SolveError for this failure on ``problem`` (its full pressures; ``load_fraction`` of them were tried)
        that names the chamber most likely at fault, the pressure, and what to try; or, when the residual stalled
        at its rounding floor, the ill-conditioning and the penalty factor behind it."""
        body, pressures = problem.body, problem.pressures_pa
        pressures_kpa = ", ".join(f"{p / 1e3:g}" for p in pressures)
        if self.ill_conditioned:
            return SolveError(
                f"the stiffness is ill-conditioned: at pressures ({pressures_kpa}) kPa Newton's residual stagnated "
                f"at {self.residual_ratio:.2g} of the load, the floor that rounding the node positions alone "
                f"gives ({self.rounding_floor_ratio:.2g}: stiffness diagonal ratio {body.diagonal_ratio():.2g}, "
                f"condition number at least that), while the tolerance is {RELATIVE_TOLERANCE:g}; the fixation "
                f"springs are FIXED_PENALTY = {body.fixed_penalty:g} times E: use a lower penalty factor (the "
                f"default 1e3 already clamps the fixed patch; 1e6 converges)")
        chamber = int(np.argmax(np.abs(pressures)))
        if self.worst_element >= 0:
            centroid = body.nodes_m[body.tets[self.worst_element]].mean(axis=0)
            distances = [np.min(np.linalg.norm(body.nodes_m[np.unique(t)] - centroid, axis=1))
                         for t in body.chamber_faces]
            chamber = int(np.argmin(distances))
        ratio = abs(pressures[chamber]) / body.material.youngs_modulus_pa
        return SolveError(
            f"the {self.reason} at pressures ({pressures_kpa}) kPa, near chamber {chamber} "
            f"({body.chamber_names[chamber]!r} at {pressures[chamber] / 1e3:g} kPa, p/E = {ratio:.3g}; reached "
            f"{100 * load_fraction:.0f} % of the load as a trial step): try a lower pressure in that chamber, a "
            f"finer mesh (--size-mm), or a stiffer material")


def preconditioned_cg(multiply: Callable[[FloatArray], FloatArray], rhs: FloatArray, preconditioner: Factor,
                      tolerance: float, max_iterations: int) -> FloatArray | None:
    """Solve ``A y = b`` by conjugate gradients preconditioned with a factorised ``M ~ A``; ``multiply(v)`` is
    ``A v``.

    A may be slightly indefinite (a sliver element under follower pressure): CG carries on through a step of
    negative curvature, and the caller checks that the result is a descent direction. Returns None when the
    relative residual does not reach ``tolerance`` in ``max_iterations`` or a curvature vanishes: the caller
    then factorises A itself.
    """
    solution = np.zeros_like(rhs)
    residual = rhs.copy()
    rhs_norm = norm(rhs)
    preconditioned = preconditioner.solve(residual)
    direction = preconditioned.copy()
    product = dot(residual, preconditioned)
    for _ in range(max_iterations):
        image = multiply(direction)
        curvature = dot(direction, image)
        if abs(curvature) <= 1e-14 * norm(direction) * norm(image):
            return None
        step = product / curvature
        solution += step * direction
        residual -= step * image
        if norm(residual) <= tolerance * rhs_norm:
            return solution
        preconditioned = preconditioner.solve(residual)
        new_product = dot(residual, preconditioned)
        direction = preconditioned + (new_product / product) * direction
        product = new_product
    return None


def line_search(problem: EquilibriumProblem, positions_m: FloatArray, direction: FloatArray,
                evaluation: Evaluation, slope: float,
                with_tangent: bool = False) -> tuple[FloatArray, Evaluation] | None:
    """Backtrack from the full step ``direction`` (n, 3) at ``positions_m`` (whose evaluation and directional
    derivative of the energy ``slope`` are given) until the energy decreases (Armijo) or, where energy
    differences are lost in rounding, the residual does; never accept a step that inverts an element. With
    ``with_tangent`` the full step (accepted almost always near convergence) also assembles the tangent in the
    same element pass, so the next Newton direction needs no second pass over the elements. Returns the accepted
    positions and their evaluation, or None."""
    step = 1.0
    energy, residual_norm = evaluation.energy_j, norm(evaluation.residual_n)
    rounding = 1e-13 * (abs(energy) + abs(slope))
    for attempt in range(LINE_SEARCH_HALVINGS):
        trial = positions_m + step * direction
        trial_evaluation = problem.evaluate(trial, with_tangent=with_tangent and attempt == 0)
        if trial_evaluation.admissible and (trial_evaluation.energy_j <= energy + 1e-4 * step * slope + rounding
                                            or norm(trial_evaluation.residual_n) < residual_norm):
            return trial, trial_evaluation
        step *= 0.5
    return None


def newton(problem: EquilibriumProblem, positions_m: FloatArray, tolerance: float = RELATIVE_TOLERANCE,
           initial_imbalance: bool = False, element_pressures_pa: FloatArray | None = None,
           max_iterations: int = MAX_ITERATIONS_PER_STEP) -> NewtonResult:
    """Newton iterations from ``positions_m`` (n, 3) with a backtracking line search on the total energy.

    Converged when the residual is below ``tolerance`` times the load (or times the starting residual when
    ``initial_imbalance`` and that is larger, for a start that is not in equilibrium at zero load, e.g. rotated).
    A 10-node hyperelastic body first iterates on the mixed system (:func:`mixed_newton`), from
    ``element_pressures_pa`` when given (a path's extrapolated ones) else those eliminated at ``positions_m``;
    where that finds no step, the iterations go on from where it stopped with the pressures eliminated. At most
    ``max_iterations`` in all (a path's attempt at the full load from a predictor gives up early and steps on).
    """
    evaluation = problem.evaluate(positions_m)
    load_scale = max(problem.load_scale_n(), norm(evaluation.residual_n) if initial_imbalance else 0.0)
    if not problem.loaded:
        # No load to be relative to: its floor (1e-12 E L^2) times the tolerance lies below the residual that
        # rounding the positions alone leaves, so a solve from the rest shape itself "stagnated" there and was
        # called ill-conditioned. Without a load, a residual within ROUNDING_FLOOR_MARGIN of that floor is the
        # equilibrium (1.8e-9 N on the built-in prostate: about 1e-12 m of position).
        load_scale = max(load_scale, ROUNDING_FLOOR_MARGIN * problem.rounding_floor_n(positions_m) / tolerance)
    spent = 0
    if problem.mixed:
        mixed = mixed_newton(problem, positions_m, evaluation, tolerance, load_scale, element_pressures_pa,
                             max_iterations)
        if mixed.converged or mixed.iterations >= max_iterations:
            return mixed
        positions_m, spent = mixed.positions_m, mixed.iterations
        evaluation = problem.evaluate(positions_m)
    result = _eliminated_newton(problem, positions_m, evaluation, tolerance, load_scale, max_iterations - spent)
    result.iterations += spent
    return result


def mixed_newton(problem: EquilibriumProblem, positions_m: FloatArray, evaluation: Evaluation, tolerance: float,
                 load_scale: float, element_pressures_pa: FloatArray | None = None,
                 max_iterations: int = MAX_ITERATIONS_PER_STEP) -> NewtonResult:
    """Newton on the mixed (displacement, element pressure) system of a 10-node body, the pressures condensed in
    each linear solve but carried from one iterate to the next.

    Eliminating each element's pressure, ``p = K (Jbar - 1)``, makes the residual at a new iterate carry ``K``
    times the second-order error of its volume ratios: with bulk/shear 1250 a Newton step that is right to first
    order can raise the residual 20-60-fold, and the energy line search then crawls (58 iterations at (2,0,0) kPa
    on the 10 mm prostate). Carried as an unknown, the pressure takes its linearised update, ``K (Jbar - 1 +
    dJbar)``, and the volume constraint's error, ``Jbar - 1 - p/K``, is a strain, not a force times K. The
    direction is the same condensed system: ``(K_t(p) + sum K/V_e G_e G_e^T) dx = -r(x)`` with ``r`` the
    residual at eliminated pressures and ``K_t(p)`` the tangent with the carried pressures in its ``p d2v`` term.

    A step (halved up to LINE_SEARCH_HALVINGS times) is accepted when it inverts nothing and lowers the merit
    ``|r(x, p)|^2 + sum (mu V_e^(2/3) (Jbar - 1 - p/K))^2`` (the constraint's error weighed at the shear modulus,
    not the bulk). Converged when the residual at eliminated pressures meets ``tolerance`` (as
    :func:`newton`'s), so the answer is the same state; returns unconverged (not raising) when no step lowers
    the merit or it stalls. ``evaluation`` is the problem's at ``positions_m`` (pressures eliminated);
    ``element_pressures_pa`` the pressures to start from (None: eliminated at ``positions_m``)."""
    body = problem.body
    assert body.quadratic is not None  # only 10-node bodies have the mixed pressure field
    ratios = body.element_volume_ratios(positions_m)
    pressures_pa = body.eliminated_pressures_pa(ratios) if element_pressures_pa is None else element_pressures_pa
    eliminated_n = evaluation.residual_n
    carried = evaluation if element_pressures_pa is None else problem.evaluate(positions_m,
                                                                                element_pressures_pa=pressures_pa)
    merit = _mixed_merit(body, carried.residual_n, ratios, pressures_pa)
    best_merit, best_iteration, previous_norm = np.inf, 0, np.inf
    tangent_data = None  # the exact tangent at the iterate, where the line search's element pass made it
    for iteration in range(1, max_iterations + 1):
        residual_norm = norm(eliminated_n)
        stalled = residual_norm > 0.5 * previous_norm and residual_norm <= ROUNDING_TOLERANCE * load_scale
        if residual_norm <= tolerance * load_scale or stalled:
            return NewtonResult(positions_m, True, iteration - 1)
        previous_norm = residual_norm
        if merit < 0.5 * best_merit:
            best_merit, best_iteration = merit, iteration
        elif iteration - best_iteration >= STALLED_ITERATIONS:
            return NewtonResult(positions_m, False, iteration - 1, "mixed solve stalled")
        factorization = problem.tangent(positions_m, exact=True, damped=True, element_pressures_pa=pressures_pa,
                                        tangent_data=tangent_data)
        direction = -factorization.solve(eliminated_n).reshape(-1, 3)
        pressure_step = body.eliminated_pressures_pa(ratios, body.element_volume_ratio_rates(positions_m, direction)) \
            - pressures_pa
        accepted = None
        scale = 1.0
        for halving in range(LINE_SEARCH_HALVINGS):
            trial_m, trial_pa = positions_m + scale * direction, pressures_pa + scale * pressure_step
            # (the full step, accepted almost always near convergence, assembles the next tangent in its pass)
            trial = problem.evaluate(trial_m, with_tangent=halving == 0, element_pressures_pa=trial_pa)
            if trial.admissible:
                trial_ratios = body.element_volume_ratios(trial_m)
                trial_merit = _mixed_merit(body, trial.residual_n, trial_ratios, trial_pa)
                if trial_merit < merit:
                    accepted = trial_m, trial_pa, trial_ratios, trial_merit, trial
                    break
            scale *= 0.5
        if accepted is None:
            return NewtonResult(positions_m, False, iteration, "mixed step found no descent")
        positions_m, pressures_pa, ratios, merit, carried = accepted
        tangent_data = carried.tangent_data
        eliminated_n = problem.eliminated_residual_n(positions_m, carried.residual_n, ratios, pressures_pa)
    return NewtonResult(positions_m, False, max_iterations, "mixed solve did not converge")


def _mixed_merit(body: SolidBody, residual_n: FloatArray, volume_ratios: FloatArray,
                 element_pressures_pa: FloatArray) -> float:
    """:func:`mixed_newton`'s merit: ``sqrt(|r(x, p)|^2 + |constraint error|^2)`` (N), the residual at the carried
    pressures and their volume constraint's error weighed at the shear modulus (zero at eliminated ones)."""
    constraint = body.volume_constraint_error_n(volume_ratios, element_pressures_pa)
    return float(np.sqrt(norm(residual_n) ** 2 + dot(constraint, constraint)))


def _eliminated_newton(problem: EquilibriumProblem, positions_m: FloatArray, evaluation: Evaluation,
                       tolerance: float, load_scale: float,
                       max_iterations: int = MAX_ITERATIONS_PER_STEP) -> NewtonResult:
    """:func:`newton`'s iterations on the residual with any element pressures eliminated, from ``positions_m``
    (whose ``evaluation`` is given)."""
    if not problem.nonlinear:
        kind, factorization = "rest", problem.rest_factorization()
    elif problem.preconditioned:
        kind, factorization = "krylov", problem.rest_factorization()
    else:
        kind, factorization = "exact", problem.tangent(positions_m, exact=True, damped=True)
    hessian = evaluation.tangent_data
    previous_norm = best_norm = np.inf
    best_iteration = 0
    for iteration in range(1, max_iterations + 1):
        residual = evaluation.residual_n
        residual_norm = norm(residual)
        # Converged at the tolerance, or where rounding stops progress (tiny loads: forces are computed
        # from positions of order the phantom's size) once within ROUNDING_TOLERANCE of the load.
        stalled = residual_norm > 0.5 * previous_norm and residual_norm <= ROUNDING_TOLERANCE * load_scale
        if residual_norm <= tolerance * load_scale or stalled:
            return NewtonResult(positions_m, True, iteration - 1)
        if residual_norm < 0.5 * best_norm:
            best_norm, best_iteration = residual_norm, iteration
        elif iteration - best_iteration >= STALLED_ITERATIONS:
            return NewtonResult(positions_m, False, iteration, f"solve stopped converging after {iteration} "
                                "iterations", problem.worst_element(positions_m), True, best_norm / load_scale,
                                problem.rounding_floor_n(positions_m) / load_scale)
        previous_norm = residual_norm
        if kind == "krylov":
            if hessian is None:
                hessian = problem.tangent_data(positions_m)
            direction = preconditioned_cg(problem.multiply(hessian), -residual, factorization, KRYLOV_TOLERANCE,
                                          KRYLOV_ITERATIONS)
        else:
            direction = -factorization.solve(residual)
        accepted, slope = None, 0.0
        if direction is not None:
            direction = direction.reshape(-1, 3)
            slope = dot(residual, direction.ravel())
        if direction is not None and slope < 0.0:
            accepted = line_search(problem, positions_m, direction, evaluation, slope, with_tangent=kind == "krylov")
        if accepted is None:
            if not problem.nonlinear or kind == "positive":
                worst = problem.worst_element(positions_m if direction is None else positions_m + direction)
                reason = "solve inverted elements" if worst >= 0 else "line search found no descent"
                return NewtonResult(positions_m, False, iteration, reason, worst)
            kind = "exact" if kind in ("rest", "krylov") else "positive"
            factorization = problem.tangent(positions_m, exact=kind == "exact", damped=True)
            continue
        positions_m, evaluation = accepted
        hessian = evaluation.tangent_data
        refresh = norm(evaluation.residual_n) > TANGENT_REFRESH_RATIO * residual_norm
        if kind != "krylov" and problem.nonlinear and refresh:
            kind, factorization = "exact", problem.tangent(positions_m, exact=True, damped=True)
    return NewtonResult(positions_m, False, max_iterations, f"solve did not converge in {max_iterations} "
                        "iterations", problem.worst_element(positions_m))
