"""Path following for the pressure-controlled solve: load steps with a predictor, or volume control.

The pressures ``p`` are applied as ``lam p`` with the load factor ``lam`` going from 0 to 1. Where the small-strain
estimate grows no chamber by more than ``FIRST_STEP_GROWTH`` the whole load is one pressure-controlled Newton
solve (else the share of it that would), then steps started from a secant predictor (the last two equilibria
extrapolated to the new load); where the pressure-volume curve flattens (the load gained per unit of volume falls below
``FLATTENING_RATIO`` of the first step's) or a pressure-controlled step fails, the path switches to volume
control. Where the estimate grows a chamber by more than that under a load on several chambers, the path is
volume controlled from rest: a pressure step there failed after 21 iterations (bench/README.md, "Through the
limit points"; one chamber alone takes fewer iterations under pressure control). Volume control is
SoftRobots' volume actuation: the control is the load-weighted chamber volume ``c(x) = sum_i w_i V_i(x)`` with
``w = p / max|p|`` (one loaded chamber: exactly its volume), stepped forward, and the load factor is the
Lagrange multiplier of ``c(x) = c_target``. Each volume-controlled step solves the bordered system

    K dx - q dlam = -R,    h . dx = -(c - c_target)

(``K`` the exact tangent with the follower-pressure stiffness, ``q = sum p_i dV_i/dx`` the load per unit lam,
``h = dc/dx``) by block elimination (``dx = a + b dlam``, ``K a = -R``, ``K b = q``) with CG preconditioned by
the rest factor while it converges, else the exact K at every iterate, so limit points of the
pressure-controlled problem, where K is singular along the volume mode, are passed. K is solved as it is:
CHOLMOD's LL' where it is positive definite, else (past a limit point, or a predictor off the path) MINRES
preconditioned with the LL' of ``K + s K0`` (K0 the small-strain stiffness, ``s`` the least of STIFFNESS_SHIFTS
that is positive definite), whose solution is Newton's; far off the path, where MINRES does not converge in
EXACT_KRYLOV_ITERATIONS, the shifted factor's own (damped) step, which the merit's line search accepts or
refuses. A damped step at every iterate stalled just below a thick sphere's peak (minutes, then "did not
converge"): past the peak the exact tangent is legitimately indefinite and only its step converges. Each step starts
from Hermite's cubic through the last two equilibria and the path's direction at each (``K b = q`` with the
tangent factorised at a step's last iterate: one back-substitution), else a quadratic through the last three
equilibria in the control volume (a secant through two, the tangent from one: at rest the kept small-strain
factor), a 10-node body's element pressures extrapolated as the positions are. When the next step is predicted
to carry lam past 1, Newton at the exact pressures starts from the predictor where lam reaches 1 (at most
FINAL_NEWTON_ITERATIONS); where it does not converge the path steps on, and a step past lam = 1 is bracketed
(Newton from the interpolation between the two, then Illinois regula falsi on c) until the final state is a
pressure-controlled equilibrium at the exact pressures.

The peak is detected by the load's sign change along the path (dlam/dc = 1 / (h . K^-1 q) turns negative as K
gains a negative eigenvalue: the tangent's inertia) and located to PEAK_LOAD_TOLERANCE by volume solves at the
maximum of Hermite's cubic of lam(c) through the equilibria that bracket it (one or two solves). For a law
without strain stiffening (all but Gent and Yeoh) a load factor that fell is the answer: the pressures lie above
the peak, and a PeakPressureError names the chamber, the peak's pressure and volume (its attributes too). A
stiffening law's path goes on; it is unreachable when, past its peak, the load factor falls below ``PEAK_DROP``
of it (PeakPressureError too), the control volume grows beyond ``MAX_CONTROL_GROWTH`` times its rest value, or a
volume step cannot be made without inverting an element (or, for Gent, locking its chains) even after halving it
``MAX_VOLUME_BISECTIONS`` times; the SolveError then names the chamber, the pressure and volume where the path
stopped, and why.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from phantom.model.arrays import FloatArray
from phantom.model.errors import PeakPressureError, SolveError
from phantom.model.fem.body import Factor
from phantom.model.fem.linsolve import ShiftPreconditioned
from phantom.model.fem.newton import LINE_SEARCH_HALVINGS, newton, preconditioned_cg
from phantom.model.fem.problem import DAMPING_SHIFTS, EquilibriumProblem
from phantom.model.scene import HYPERELASTIC_MODELS

#: Switch to volume control when the secant slope d(lam)/d(c) falls below this fraction of the first step's.
FLATTENING_RATIO = 0.2
#: The first load step is cut so that the small-strain estimate grows no chamber by more than this fraction.
FIRST_STEP_GROWTH = 0.5
#: Pressure-controlled step failures (each followed by a halved step) before volume control takes over.
PRESSURE_FAILURES_BEFORE_VOLUME_CONTROL = 1
#: A pressure-controlled path gives up after this many failed load steps.
MAX_LOAD_BISECTIONS = 6
MAX_PATH_STEPS = 60
MAX_VOLUME_BISECTIONS = 8
#: The first volume step where no pressure-controlled step was made, relative to the control's rest value.
FIRST_VOLUME_STEP = 0.1
#: The smallest volume step (relative to the control's rest value) before the path gives up: the mesh is then
#: collapsing (an element about to invert, or Gent's chains about to lock), not turning a limit point.
MIN_CONTROL_STEP = 1e-2
#: A volume-controlled path stops, unreachable, past a peak of lam when lam falls below this fraction of it...
PEAK_DROP = 0.5
#: ... or, for laws without strain stiffening (all but these), as soon as lam has fallen on a volume step and its
#: peak is located: their pressure falls for good past the peak (a Neo-Hookean balloon: p ~ 1/lambda - 1/lambda^7),
#: while Gent's rises again as its chains lock, and Yeoh's as its higher terms grow.
STIFFENING_LAWS = ("gent", "yeoh")
#: The peak is located by volume solves at the maximum of Hermite's cubic of lam(c) through the equilibria that
#: bracket it, until the solved load factor is within this of the cubic's (relative), or PEAK_SOLVES solves.
PEAK_LOAD_TOLERANCE = 1e-5
PEAK_SOLVES = 4
#: ... or when the control volume exceeds this multiple of its rest value.
MAX_CONTROL_GROWTH = 20.0
VOLUME_NEWTON_ITERATIONS = 30
#: A volume step that converged in this many Newton iterations or fewer doubles the next. With the cubic predictor
#: a step takes 2-4 (builtin:converged): doubling after 4 or 5 made the (3,3,3) kPa path's late steps take 7-10.
DOUBLING_ITERATIONS = 3
#: Residual of a volume-controlled equilibrium on the path, relative to the full load (the end point is then
#: solved to the caller's tolerance under pressure control). The path's points only feed the predictor: 1e-8
#: took one more iteration a step than 1e-6 on builtin:converged, and 1e-6 one more a path than this ((3,3,3)
#: and (2,2,2) kPa; 1e-4 no fewer), the same end points.
PATH_TOLERANCE = 1e-5
#: The control volume constraint, relative to the control's rest value.
CONTROL_TOLERANCE = 1e-11
CROSSING_ITERATIONS = 30
#: How close to lam = 1 the crossing's bracket comes before the pressure-controlled Newton at the exact pressures
#: takes over: first near (that Newton converges in two or three iterations from there), then, if it fails,
#: as near as the bracket goes.
CROSSING_LOAD_TOLERANCES = (1e-3, 1e-6)
#: A volume-controlled Newton solve fails after CRAWL_ITERATIONS steps in a row cut by 2^CRAWL_HALVINGS or more.
CRAWL_HALVINGS = 4
CRAWL_ITERATIONS = 2
#: Equilibria the volume step's predictor extrapolates (a polynomial of one degree less in the control volume).
PREDICTOR_POINTS = 3
#: Newton iterations at the exact pressures from a predictor near lam = 1 before the path steps on instead.
FINAL_NEWTON_ITERATIONS = 8
#: Multiples of the small-strain stiffness K0 tried in turn as the shift of an indefinite tangent, ``K + s K0``,
#: whose Cholesky factor preconditions MINRES on K (:meth:`_Path._exact_solve`). A shift of the diagonal,
#: ``tau |diag K|``, moved every shear mode of a nearly incompressible body (its diagonal is the bulk modulus's):
#: 94-133 MINRES iterations a solve on the 10-node sphere; K0 has the body's own proportions.
STIFFNESS_SHIFTS = (1e-3, 3e-3, 1e-2, 3e-2, 0.1, 0.3, 1.0, 3.0, 10.0, 100.0)
#: A volume-controlled iterate takes Newton's exact step, not the damped one, once a damped step lowered the merit by
#: less than this factor.
DAMPED_PROGRESS = 0.25
#: ... near the path only (merit below this: residual about 1 % of the load): far off it the damped step is a
#: descent all the same, and MINRES there needed a large shift and 150 iterations (the sphere's first volume step).
EXACT_STEP_MERIT = 1e-4
#: MINRES on an indefinite tangent: relative residual, and the iterations before the shifted factor's own (damped)
#: step is taken instead. Near the path past a limit point a shift of 1e-3 K0 served, and MINRES took 26-47
#: iterations; far off it (a predictor's first iterate) the shift was 0.1-0.3 K0 and MINRES 250-480.
EXACT_KRYLOV_TOLERANCE = 1e-9
EXACT_KRYLOV_ITERATIONS = 80
VOLUME_KRYLOV_TOLERANCE = 1e-4
VOLUME_KRYLOV_ITERATIONS = 40


class DampedFactor:
    """The factor of a shifted tangent, ``K + tau |diag K|``, standing in for K (a damped Newton step)."""

    def __init__(self, factor: Factor):
        self.factor = factor

    def solve(self, rhs: FloatArray) -> FloatArray:
        """``(K + tau |diag K|)^-1 rhs``."""
        return self.factor.solve(rhs)

    def negative_pivots(self) -> int | None:
        """Not K's: unknown."""
        return None


#: A solver for the tangent: a factorisation, MINRES preconditioned with a shifted one, or a shifted one (damped).
Solver = Factor | ShiftPreconditioned | DampedFactor


@dataclass(frozen=True)
class PathRate:
    """The path's direction at an equilibrium, per m^3 of the control volume: node positions (n, 3), load factor,
    and a 10-node body's element pressures (None for a 4-node body)."""

    positions_m_per_m3: FloatArray
    load_factor_per_m3: float
    pressures_pa_per_m3: FloatArray | None
    #: negative eigenvalues of the tangent it was solved with (None: the factorisation does not tell)
    negative_pivots: int | None = None


@dataclass
class PathPoint:
    """An equilibrium on the path: load factor, node positions (n, 3) m, control volume (m^3), and the path's
    direction there where it was solved (``rate``, for the cubic predictor)."""

    load_factor: float
    positions_m: FloatArray
    control_m3: float
    rate: PathRate | None = None


@dataclass
class PathResult:
    """The equilibrium at the full pressures: node positions (n, 3) m, the Newton iterations spent on the way and
    the accepted steps."""

    positions_m: FloatArray
    iterations: int
    steps: int


@dataclass(frozen=True)
class _VolumeState:
    """The bordered system at one (positions, load factor): out-of-balance force ``residual_n`` (3n,), control
    volume gap (m^3), merit (dimensionless: the squared residual relative to the load plus the squared gap
    relative to the control's rest volume, plus a 10-node body's squared constraint error when its pressures
    are carried) and admissibility (no element at det F <= 0, finite energy). ``eliminated_n``: the residual at
    eliminated element pressures (``residual_n`` itself unless they are carried); ``volume_ratios``: the
    elements' Jbar where they are carried; ``tangent_data``: the exact tangent's data at this state where the
    same element pass made it (else None)."""

    residual_n: FloatArray
    gap_m3: float
    merit: float
    admissible: bool
    eliminated_n: FloatArray
    volume_ratios: FloatArray | None = None
    tangent_data: FloatArray | None = None


@dataclass
class _VolumeStep:
    converged: bool
    point: PathPoint | None
    iterations: int
    reason: str = ""
    worst_element: int = -1
    #: the tangent factorised at the last iterate (None where the step took no iteration or solved by CG)
    factor: Solver | None = None


class _Path:
    """One path-following solve of ``problem`` from its start."""

    def __init__(self, problem: EquilibriumProblem, tolerance: float):
        self.problem = problem
        self.body = problem.body
        self.start_m = problem.start_m
        self.pressures = problem.pressures_pa
        self.formulation = problem.formulation
        self.tolerance = tolerance
        self.constraints = problem.constraints
        self.weights = self.pressures / np.max(np.abs(self.pressures)) if np.any(self.pressures) else self.pressures
        self.iterations = 0
        self.steps = 0
        self.load_scale = problem.load_scale_n()
        self.control_rest_m3 = (abs(self._control(self.start_m))
                                or float(np.max(self.body.rest_chamber_volumes_m3)))
        self.peak: PathPoint | None = None
        #: the small-strain displacement (n, 3) m under the whole load from the start, where it was solved
        self.small_strain_m: FloatArray | None = None
        #: conjugate gradients on a volume step's tangent failed once: later steps factorise it straight away
        self.krylov_failed = False
        #: the lowest load factor at which a pressure-controlled step failed: the volume-controlled path makes no
        #: Newton attempt at the full pressures from a prediction below it (the pressure may lie past a peak)
        self.failed_load_factor: float | None = None
        #: the first of STIFFNESS_SHIFTS to try on an indefinite tangent (:meth:`_exact_solve`)
        self.shift_index = 0
        #: the small-strain stiffness's data (the shift of an indefinite tangent), made when first needed
        self.rest_stiffness: FloatArray | None = None

    # --- quantities --------------------------------------------------------------------------------------

    def _control(self, positions_m: FloatArray) -> float:
        return float(self.weights @ self.body.chamber_volumes_m3(positions_m))

    def _point(self, load_factor: float, positions_m: FloatArray) -> PathPoint:
        return PathPoint(float(load_factor), positions_m, self._control(positions_m))

    def _upright(self, positions_m: FloatArray) -> bool:
        return self.problem.worst_element(positions_m) < 0

    # --- the whole path ----------------------------------------------------------------------------------

    def run(self) -> FloatArray:
        points = [self._point(0.0, self.start_m)]
        # volume control needs a chamber to control: under a body force alone the path is pressure controlled
        allow_switch = self.problem.nonlinear and bool(np.any(self.pressures))
        increment = self._first_increment() if allow_switch else 1.0
        at_rest = np.array_equal(self.start_m, self.body.nodes_m)  # (an equilibrium at lam = 0, as a path's points)
        if increment < 1.0 and np.count_nonzero(self.pressures) > 1 and at_rest:
            # The small-strain answer grows a chamber by more than FIRST_STEP_GROWTH under a load on several
            # chambers: on builtin:converged their pressure steps from rest failed after 21 iterations (2,2,2) or
            # took 14 a step (3,1,2), where volume control from the start takes 29 in all; one chamber alone
            # took 15-18 in two pressure steps at 2 kPa, and 26-30 under volume control (bench/README.md,
            # "Through the limit points"). A measured rule, not a law: the load-weighted control follows either.
            return self._volume_controlled(points)
        return self._pressure_controlled(points, allow_switch, increment)

    def _predict(self, points: list[PathPoint], load_factor: float) -> tuple[FloatArray, FloatArray | None]:
        """Secant extrapolation of the last two equilibria to ``load_factor`` (the last one when that would
        invert an element, or with a single point), with a 10-node body's element pressures extrapolated alike
        (None: eliminated at the guess). From the start alone: :meth:`_small_strain_guess`."""
        if len(points) < 2:
            return self._small_strain_guess(points[-1], load_factor)
        last, before = points[-1], points[-2]
        ratio = (load_factor - last.load_factor) / (last.load_factor - before.load_factor)
        guess = last.positions_m + ratio * (last.positions_m - before.positions_m)
        if not self._upright(guess):
            return last.positions_m, None
        return guess, self._extrapolated_pressures(before, last, ratio)

    def _small_strain_guess(self, start: PathPoint, load_factor: float) -> tuple[FloatArray, FloatArray | None]:
        """The first pressure step's start: the small-strain answer at ``load_factor`` (:meth:`_first_increment`'s
        back-substitution) with a 10-node body's element pressures its volume ratios give, ``K dJbar``; the start
        itself where there is none or it would invert an element. From rest, (1,1,1) kPa on builtin:converged
        took 6 iterations from it, 14 from rest; (2,0,0) 9, 18 (bench/README.md, "Through the limit points")."""
        if self.small_strain_m is None or start.load_factor != 0.0:
            return start.positions_m, None
        change = load_factor * self.small_strain_m
        guess = start.positions_m + change
        if not self._upright(guess):
            return start.positions_m, None
        pressures = self._combined_pressures([start], np.ones(1))
        if pressures is not None:
            pressures = pressures + self.body.material.bulk_modulus_pa * self.body.element_volume_ratio_rates(
                start.positions_m, change)
        return guess, pressures

    def _extrapolated_pressures(self, before: PathPoint, last: PathPoint, ratio: float) -> FloatArray | None:
        """A 10-node body's element pressures extrapolated as the positions are, ``last + ratio (last - before)``
        (at an equilibrium they are the eliminated ones): the predictor's own eliminated pressures, ``K (Jbar -
        1)``, carry K times the secant's second-order error in the volume ratios, and gave an indefinite tangent
        at nearly every volume step of a 7 mm prostate solve (a SuperLU factorisation, 4 s, instead of CHOLMOD's
        0.3 s) and 6-8 iterations a step instead of 4-6. None for a 4-node body."""
        return self._combined_pressures([before, last], np.array([-ratio, 1.0 + ratio]))

    def _pressure_controlled(self, points: list[PathPoint], allow_switch: bool, increment: float) -> FloatArray:
        failures = 0
        first_slope: float | None = None
        while points[-1].load_factor < 1.0:
            done = points[-1].load_factor
            target = min(1.0, done + increment)
            guess_m, guess_pa = self._predict(points, target)
            step = newton(self.problem.at_load_factor(target), guess_m, self.tolerance,
                          initial_imbalance=self.steps == 0, element_pressures_pa=guess_pa)
            self.iterations += step.iterations
            if step.converged:
                points.append(self._point(target, step.positions_m))
                self.steps += 1
                increment *= 2.0 if step.iterations < 8 else 1.0
                slope = self._slope(points[-2], points[-1])
                first_slope = slope if first_slope is None else first_slope
                if allow_switch and target < 1.0 and slope < FLATTENING_RATIO * first_slope:
                    return self._volume_controlled(points)
                continue
            failures += 1
            self.failed_load_factor = target
            # A smaller load cannot help a linear model, nor a residual stuck at the rounding floor (the floor
            # relative to the load only grows as the load shrinks).
            if not allow_switch or step.ill_conditioned or failures > MAX_LOAD_BISECTIONS:
                raise step.error(self.problem, target)
            if failures >= PRESSURE_FAILURES_BEFORE_VOLUME_CONTROL:
                return self._volume_controlled(points)
            increment /= 2.0
        return points[-1].positions_m

    def _first_increment(self) -> float:
        """The whole load at once, unless the small-strain answer (one back-substitution with the rest factor)
        grows a chamber by more than FIRST_STEP_GROWTH of its volume: then the share of the load that would."""
        if not self.problem.preconditioned:
            return 1.0
        displacement = self.problem.rest_factorization().solve(self.problem.load_n(self.start_m))
        self.small_strain_m = displacement.reshape(-1, 3)
        gradients = self.body.chamber_volume_gradients(self.start_m)
        chambers = self.body.chamber_volumes_m3(self.start_m)
        growth = float(np.max(np.abs(gradients @ displacement) / chambers))
        return 1.0 if growth <= FIRST_STEP_GROWTH else FIRST_STEP_GROWTH / growth

    def _slope(self, before: PathPoint, after: PathPoint) -> float:
        """d(lam)/d(c), in units of the rest control volume (infinite when the volume did not move)."""
        change = (after.control_m3 - before.control_m3) / self.control_rest_m3
        return (after.load_factor - before.load_factor) / change if change > 0 else np.inf

    # --- volume control ----------------------------------------------------------------------------------

    def _tangent_direction(self, point: PathPoint, factor: Solver | None = None) -> PathRate | None:
        """The path's direction at an equilibrium from ``K b = q``: ``dx/dc = b / (h . b)``, ``dlam/dc = 1 / (h .
        b)``, a 10-node body's element pressures ``K dJbar/dc``; None where the tangent gives no forward direction.
        ``factor``: a factorised tangent near ``point`` (a volume step's last iterate's) instead of a new one."""
        load = self.problem.load_n(point.positions_m)
        if isinstance(factor, DampedFactor):  # not K's: its direction past a peak is not the path's
            factor = None
        if factor is None:
            factor, b = self._exact_solve(point.load_factor, point.positions_m, None, None, load)
        else:
            b = factor.solve(load)
        curvature = float(self._control_gradient(point.positions_m) @ b)
        if not np.isfinite(curvature) or curvature == 0:
            return None
        # (past a limit point K has a negative eigenvalue along the volume mode, h . K^-1 q < 0: the load falls as
        # the volume grows, and the direction is still the path's)
        direction = b.reshape(-1, 3) / curvature
        pressures = (self.body.material.bulk_modulus_pa * self.body.element_volume_ratio_rates(point.positions_m,
                                                                                                direction)
                     if self.problem.mixed else None)
        return PathRate(direction, 1.0 / curvature, pressures, factor.negative_pivots())

    def _control_gradient(self, positions_m: FloatArray) -> FloatArray:
        gradients = self.body.chamber_volume_gradients(positions_m)
        gradient: FloatArray = self.weights @ gradients
        gradient[self.constraints.dofs] = 0.0
        return gradient

    def _volume_controlled(self, points: list[PathPoint]) -> FloatArray:
        point = points[-1]
        previous = points[-2] if len(points) > 1 else None
        if previous is not None and point.control_m3 > previous.control_m3:
            control_step = point.control_m3 - previous.control_m3
        else:
            control_step = FIRST_VOLUME_STEP * self.control_rest_m3
        history = [p for p in (previous, point) if p is not None]
        bisections = 0
        located = False  # the last peak was located (the load has fallen since)
        peak = self.peak = max(points, key=lambda p: p.load_factor)
        for _ in range(MAX_PATH_STEPS):
            target = point.control_m3 + control_step
            guess_m, guess_factor, guess_pa = self._volume_guess(history, point, target)
            if guess_factor >= 1.0 and len(history) >= 2 and bisections == 0 and (
                    self.failed_load_factor is None or point.load_factor >= self.failed_load_factor):
                span = point.control_m3 - history[-2].control_m3
                crossing_m3 = self._crossing(point, target, guess_factor)
                if crossing_m3 is not None and crossing_m3 - point.control_m3 > span:
                    # The predictor puts lam = 1 more than one span past the last point, where its cubic (or
                    # quadratic) is extrapolated furthest: on builtin:converged at (3,3,3) kPa it put lam = 1.09
                    # where 0.84 was, and Newton at the exact pressures from there failed (8 iterations), then the
                    # step itself (a bisection). One span's step first, where the predictor is near.
                    control_step, target = span, point.control_m3 + span
                    guess_m, guess_factor, guess_pa = self._volume_guess(history, point, target)
                elif crossing_m3 is not None:
                    final = self._final_from_prediction(history, point, crossing_m3)
                    if final is not None:
                        return final
            worst = self.problem.worst_element(guess_m)
            if worst >= 0:  # the predictor itself inverts an element: a shorter step, no Newton spent
                step = _VolumeStep(False, None, 0, "solve would invert elements", worst)
            else:
                step = self._volume_newton(guess_m, guess_factor, target, guess_pa)
            self.iterations += step.iterations
            if not step.converged:
                bisections += 1
                control_step /= 2.0
                if bisections > MAX_VOLUME_BISECTIONS or control_step < MIN_CONTROL_STEP * self.control_rest_m3:
                    raise self._unreachable(point, f"the {step.reason} one volume step further",
                                            step.worst_element)
                continue
            new = step.point
            assert new is not None  # a converged step has its point
            if step.factor is not None:
                new.rate = self._tangent_direction(new, step.factor)
            self.steps += 1
            history = [*history[-(PREDICTOR_POINTS - 1):], new]
            if new.load_factor >= 1.0:
                return self._cross(point, new)
            if new.load_factor < point.load_factor and not located:
                # The load fell: a limit point lies behind (the tangent's inertia changed there, and the path's
                # dlam/dc changed sign). Located, it is the answer for a law whose pressure then falls for good.
                peak = self.peak = self._locate_peak(history)
                located = True
                if self.formulation not in STIFFENING_LAWS:
                    raise self._past_peak(peak, new)
            elif new.load_factor > peak.load_factor:
                peak = self.peak = new
                located = False
            point = new
            if point.load_factor < PEAK_DROP * peak.load_factor:
                raise self._past_peak(peak, point)
            if point.control_m3 > MAX_CONTROL_GROWTH * self.control_rest_m3:
                raise self._unreachable(point, "the volume grows without the pressure reaching the target")
            if step.iterations <= DOUBLING_ITERATIONS and bisections == 0:
                control_step *= 2.0
            bisections = 0
        raise self._unreachable(point, f"the path took more than {MAX_PATH_STEPS} volume steps")

    def _volume_guess(self, history: list[PathPoint], point: PathPoint,
                      target_m3: float) -> tuple[FloatArray, float, FloatArray | None]:
        """Predictor for a volume step: Hermite's cubic through the last two equilibria and the path's direction
        at each (:meth:`_hermite`) where they carry it, else the last equilibria (up to PREDICTOR_POINTS: a
        quadratic through three, whose error at a doubled step is a third of the secant's order) extrapolated in
        the control volume, else the tangent at the last (the caller checks that it inverts no element):
        positions, load factor, and a 10-node body's element pressures extrapolated alike (None: eliminated at the
        guess). A guess that would invert an element gives way to the next of these. The cubic cut a (3,3,3) kPa
        solve of builtin:converged from 40 to 27 iterations with the doubling rule (bench/README.md)."""
        if len(history) >= 2 and np.all(np.diff([p.control_m3 for p in history]) > 0):
            cubic = self._hermite(history[-2], history[-1], target_m3)
            if cubic is not None and self._upright(cubic[0]):
                return cubic
            for count in range(len(history), 1, -1):
                guess, factor, pressures = self._extrapolated(history[-count:], target_m3)
                if count == 2 or self._upright(guess):
                    return guess, factor, pressures
        at_rest = (point.load_factor == 0.0 and self.problem.preconditioned
                   and np.array_equal(point.positions_m, self.body.nodes_m))
        # at rest the exact tangent is the small-strain stiffness, whose factor is kept (and on disk)
        tangent = point.rate = point.rate or self._tangent_direction(
            point, self.problem.rest_factorization() if at_rest else None)
        if tangent is None:
            return point.positions_m, point.load_factor, None
        change = target_m3 - point.control_m3
        pressures = None
        if tangent.pressures_pa_per_m3 is not None:
            pressures = self._combined_pressures([point], np.ones(1))
            assert pressures is not None  # a mixed body's
            pressures = pressures + change * tangent.pressures_pa_per_m3
        return (point.positions_m + change * tangent.positions_m_per_m3,
                point.load_factor + change * tangent.load_factor_per_m3, pressures)

    def _hermite(self, before: PathPoint, last: PathPoint,
                 target_m3: float) -> tuple[FloatArray, float, FloatArray | None] | None:
        """The cubic through two equilibria with the path's direction at each (Hermite's, in the control volume)
        at ``target_m3``: positions, load factor, element pressures; None where a point has no direction."""
        if before.rate is None or last.rate is None:
            return None
        span = last.control_m3 - before.control_m3
        t = (target_m3 - before.control_m3) / span
        # the Hermite basis: values at 0 and 1, then derivatives (per unit of t) at 0 and 1
        weights = np.array([2 * t**3 - 3 * t**2 + 1, -2 * t**3 + 3 * t**2, span * (t**3 - 2 * t**2 + t),
                            span * (t**3 - t**2)])
        rates = (before.rate, last.rate)
        guess: FloatArray = (weights[0] * before.positions_m + weights[1] * last.positions_m
                             + weights[2] * rates[0].positions_m_per_m3 + weights[3] * rates[1].positions_m_per_m3)
        factor = float(weights[0] * before.load_factor + weights[1] * last.load_factor
                       + weights[2] * rates[0].load_factor_per_m3 + weights[3] * rates[1].load_factor_per_m3)
        pressures = None
        if self.problem.mixed and rates[0].pressures_pa_per_m3 is not None and rates[1].pressures_pa_per_m3 is not None:
            values = self._combined_pressures([before, last], weights[:2])
            assert values is not None  # a mixed body's
            pressures = values + weights[2] * rates[0].pressures_pa_per_m3 + weights[3] * rates[1].pressures_pa_per_m3
        return guess, factor, pressures

    def _extrapolated(self, points: list[PathPoint], target_m3: float) -> tuple[FloatArray, float, FloatArray | None]:
        """The Lagrange polynomial through ``points`` (in the control volume) at ``target_m3``: positions, load
        factor and a 10-node body's element pressures (eliminated at each point; None for a 4-node body)."""
        controls = np.array([p.control_m3 for p in points])
        weights = np.array([np.prod([(target_m3 - other) / (own - other) for other in np.delete(controls, j)])
                            for j, own in enumerate(controls)])
        guess: FloatArray = np.tensordot(weights, np.stack([p.positions_m for p in points]), axes=1)
        factor = float(weights @ np.array([p.load_factor for p in points]))
        return guess, factor, self._combined_pressures(points, weights)

    def _combined_pressures(self, points: list[PathPoint], weights: FloatArray) -> FloatArray | None:
        """``sum w_j p_j`` of a 10-node body's element pressures eliminated at each of ``points`` (at an
        equilibrium they are the carried ones); None for a 4-node body. Extrapolated from the path, not eliminated
        at the predictor: eliminated there, ``K (Jbar - 1)`` carries K times the predictor's error in the volume
        ratios (see :meth:`_extrapolated_pressures`)."""
        if not self.problem.mixed:
            return None
        eliminated = np.stack([self.body.eliminated_pressures_pa(self.body.element_volume_ratios(p.positions_m))
                               for p in points])
        combined: FloatArray = np.asarray(weights) @ eliminated
        return combined

    @staticmethod
    def _crossing(point: PathPoint, target_m3: float, guess_factor: float) -> float | None:
        """The control volume where the line from ``point`` to the prediction ``guess_factor`` at ``target_m3``
        crosses lam = 1; None where the prediction does not rise."""
        if guess_factor <= point.load_factor:
            return None
        return point.control_m3 + (1.0 - point.load_factor) / (guess_factor - point.load_factor) * (
            target_m3 - point.control_m3)

    def _final_from_prediction(self, history: list[PathPoint], point: PathPoint,
                               crossing_m3: float) -> FloatArray | None:
        """The next volume step is predicted to carry the load factor past 1: Newton at the exact pressures from
        the predictor at ``crossing_m3``, where it reaches 1 (:meth:`_crossing`), at most FINAL_NEWTON_ITERATIONS;
        the equilibrium, or None (no iteration is lost to the path: it steps on, and a step past lam = 1 is
        bracketed by :meth:`_cross`)."""
        guess_m, _, guess_pa = self._volume_guess(history, point, crossing_m3)
        return self._final_newton(guess_m, guess_pa)

    def _final_newton(self, guess_m: FloatArray, guess_pa: FloatArray | None) -> FloatArray | None:
        """Newton at the exact pressures from a guess near lam = 1, at most FINAL_NEWTON_ITERATIONS: the
        equilibrium (one more accepted step), or None."""
        if not self._upright(guess_m):
            return None
        final = newton(self.problem, guess_m, self.tolerance, element_pressures_pa=guess_pa,
                       max_iterations=FINAL_NEWTON_ITERATIONS)
        self.iterations += final.iterations
        if not final.converged:
            return None
        self.steps += 1
        return final.positions_m

    def _volume_newton(self, positions_m: FloatArray, load_factor: float, target_m3: float,
                       element_pressures_pa: FloatArray | None = None) -> _VolumeStep:
        """Equilibrium with ``c(x) = target_m3``, the load factor free (bordered Newton, module docstring).

        A 10-node body carries its element pressures from one iterate to the next, as
        :func:`phantom.model.fem.newton.mixed_newton` does and for the same reason (eliminated, ``K (Jbar - 1)``,
        they make a nearly incompressible body's residual K times the volume ratios' second-order error, and the
        line search crawls): the linear solves are the same condensed ones with the carried pressures in the
        tangent, each pressure takes its linearised update, and the merit weighs the constraint's error at the
        shear modulus. Convergence is judged at eliminated pressures, so the answer is the same state. The
        carried pressures start at ``element_pressures_pa`` when given (the predictor's), else eliminated at
        ``positions_m``."""
        free = self.constraints.free_mask
        body = self.body
        carried = None
        if self.problem.mixed:
            carried = (element_pressures_pa if element_pressures_pa is not None
                       else body.eliminated_pressures_pa(body.element_volume_ratios(positions_m)))
        # Solves with K: conjugate gradients preconditioned by the rest factor while they converge (the tangent
        # is close to it until the strain is large; once they fail on the path they are not tried again, as the
        # strain only grows: a failed try cost 40 CG iterations, a third of a 7 mm step; on a nearly
        # incompressible 10-node body they failed on every volume step of the 7 mm prostate, and are not tried),
        # else K factorised at every iterate. A factor kept from the iterate before was refused by the line
        # search on nearly every 7 mm step (three element passes) and then made anyway.
        krylov = not self.krylov_failed and self.problem.preconditioned and not self.problem.mixed
        crawling = 0
        # A damped step (the shifted factor's) where K is not positive definite, until one gains too little: then
        # Newton's own (exact) step, which converges where the tangent is legitimately indefinite (past a peak).
        # A damped step first keeps the paths that meet an indefinite iterate only off the path (a predictor's)
        # as they were: builtin:converged at (3,1,2) kPa took 2 iterations and 3 s of MINRES more with the exact
        # step at every iterate.
        exact = False
        factor: Solver | None = None
        state = self._volume_residual(positions_m, load_factor, target_m3, carried, with_tangent=not krylov)
        if element_pressures_pa is not None:
            state = self._with_eliminated(state, positions_m, element_pressures_pa)
        for iteration in range(1, VOLUME_NEWTON_ITERATIONS + 1):
            residual, gap, merit = state.eliminated_n, state.gap_m3, state.merit
            if (np.linalg.norm(residual[free]) <= PATH_TOLERANCE * self.load_scale
                    and abs(gap) <= CONTROL_TOLERANCE * self.control_rest_m3):
                return _VolumeStep(True, self._point(load_factor, positions_m), iteration - 1, factor=factor)
            load = self.problem.load_n(positions_m)
            solutions = (self._krylov_solves(positions_m, load_factor, (-residual, load), carried) if krylov
                         else None)
            factor = None
            if solutions is None:
                self.krylov_failed = self.krylov_failed or krylov
                krylov = False
                # The exact tangent, indefinite past a limit point: CHOLMOD's LL' where it is positive definite,
                # else its LDL' (:meth:`SolidBody.factorize`). Newton's step on the bordered system lowers the merit
                # (a sum of squared residuals) whatever K's inertia; a shifted K (Levenberg-Marquardt) gave a damped
                # step that stalled just before the peak of a thick sphere (bench/README.md, "Through the peak").
                factor, both = self._exact_solve(load_factor, positions_m, carried, state.tangent_data,
                                                 np.column_stack([-residual, load]), damped=not exact)
                solutions = [both[:, 0], both[:, 1]]
            a, b = solutions
            h = self._control_gradient(positions_m)
            denominator = float(h @ b)
            if not np.isfinite(denominator) or denominator == 0.0:
                return _VolumeStep(False, None, iteration, "the bordered system is singular")
            change_factor = (-gap - float(h @ a)) / denominator
            change = (a + b * change_factor).reshape(-1, 3)
            pressure_step = None
            if carried is not None:
                assert state.volume_ratios is not None  # a state at carried pressures has its volume ratios
                pressure_step = body.eliminated_pressures_pa(
                    state.volume_ratios, body.element_volume_ratio_rates(positions_m, change)) - carried
            accepted: tuple[FloatArray, float, FloatArray | None, _VolumeState] | None = None
            halving = 0
            for halving in range(LINE_SEARCH_HALVINGS):
                scale = 0.5**halving
                trial_m = positions_m + scale * change
                trial_pa = None if carried is None or pressure_step is None else carried + scale * pressure_step
                # (the full step, accepted almost always near convergence, assembles the next iterate's tangent in
                # the same element pass)
                trial = self._volume_residual(trial_m, load_factor + scale * change_factor, target_m3, trial_pa,
                                              with_tangent=halving == 0 and not krylov)
                if trial.admissible and trial.merit < merit:
                    accepted = trial_m, load_factor + scale * change_factor, trial_pa, trial
                    break
            if accepted is None:
                if krylov:
                    krylov = False
                    continue
                worst = self.problem.worst_element(positions_m + change)
                reason = "solve would invert elements" if worst >= 0 else "volume-controlled solve found no descent"
                return _VolumeStep(False, None, iteration, reason, worst)
            if (isinstance(factor, DampedFactor) and accepted[3].merit > DAMPED_PROGRESS * merit
                    and accepted[3].merit < EXACT_STEP_MERIT):
                exact = True
            positions_m, load_factor, carried, state = accepted
            if carried is not None:  # the convergence test and the next right-hand side: eliminated pressures
                state = self._with_eliminated(state, positions_m, carried)
            # Crawling: tiny admissible steps in a row mean an element is being squeezed flat (or a Gent element
            # is locking) on the way to the target volume; a smaller volume step is the cure, not more iterations.
            crawling = crawling + 1 if halving >= CRAWL_HALVINGS else 0
            if crawling >= CRAWL_ITERATIONS:
                worst = self.problem.worst_element(positions_m + change)
                return _VolumeStep(False, None, iteration, "solve would invert elements" if worst >= 0 else
                                   "volume-controlled solve is crawling", worst)
        return _VolumeStep(False, None, VOLUME_NEWTON_ITERATIONS, "volume-controlled solve did not converge",
                           self.problem.worst_element(positions_m))

    def _exact_solve(self, load_factor: float, positions_m: FloatArray, carried: FloatArray | None,
                     tangent_data: FloatArray | None, right_hand_sides: FloatArray,
                     damped: bool = False) -> tuple[Solver, FloatArray]:
        """The exact tangent at ``positions_m`` (and a 10-node body's ``carried`` element pressures) and its
        solutions for ``right_hand_sides`` (3n, k). Positive definite (before a limit point, the common case):
        CHOLMOD's supernodal LL'. Indefinite (past it, or an iterate off the path): with ``damped``, the
        Levenberg-Marquardt step of ``K + tau |diag K|`` (the first tau of DAMPING_SHIFTS that CHOLMOD takes,
        a :class:`DampedFactor`); else MINRES preconditioned with the LL' of ``K + s K0``, the first ``s`` of
        STIFFNESS_SHIFTS (from near the last one that served) that is positive definite
        (:class:`ShiftPreconditioned`), that shifted factor's own step where MINRES does not converge, and LDL'
        where no shift is positive definite. The simplicial
        LDL' of a 10-node sphere's tangent (h = 1.75 mm, 18k dofs) took 7-15 s where LL' took 0.3-0.6 s (load 7-13
        on two cores); MINRES took 20-75 iterations, 0.2-0.8 s at h = 2.5 mm (bench/README.md, "Through the peak")."""
        loaded = self.problem.at_load_factor(load_factor)
        body = self.body
        if not (body.detects_indefinite and self.formulation in HYPERELASTIC_MODELS):
            factor = loaded.tangent(positions_m, exact=True, element_pressures_pa=carried, tangent_data=tangent_data)
            return factor, factor.solve(right_hand_sides)
        data = tangent_data if tangent_data is not None else loaded.tangent_data(positions_m, carried)
        try:
            factor = body.factorize(data, positive_definite=True)
            return factor, factor.solve(right_hand_sides)
        except ArithmeticError:
            pass
        if damped:
            diagonal = body.pattern.diagonal
            for shift in DAMPING_SHIFTS:
                shifted = data.copy()
                shifted[diagonal] += shift * np.abs(data[diagonal])
                try:
                    damped_factor = DampedFactor(body.factorize(shifted, positive_definite=True))
                except ArithmeticError:
                    continue
                return damped_factor, damped_factor.solve(right_hand_sides)
        if self.rest_stiffness is None:
            self.rest_stiffness = body.tangent_data(constraints=self.constraints)
        for index in range(self.shift_index, len(STIFFNESS_SHIFTS)):
            shifted = data + STIFFNESS_SHIFTS[index] * self.rest_stiffness
            try:
                preconditioner = body.factorize(shifted, positive_definite=True)
            except ArithmeticError:
                continue
            self.shift_index = max(index - 2, 0)
            solver = ShiftPreconditioned(lambda vector: body.multiply(data, vector), preconditioner,
                                         EXACT_KRYLOV_TOLERANCE, EXACT_KRYLOV_ITERATIONS)
            try:
                return solver, solver.solve(right_hand_sides)
            except ArithmeticError:
                # far off the path (a predictor's first iterates) the shift is large and MINRES slow: the shifted
                # factor's own step there, a damped Newton step that the merit's line search takes or refuses
                return preconditioner, preconditioner.solve(right_hand_sides)
        factor = body.factorize(data, positive_definite=False)
        return factor, factor.solve(right_hand_sides)

    def _krylov_solves(self, positions_m: FloatArray, load_factor: float, right_hand_sides: tuple[FloatArray, ...],
                       element_pressures_pa: FloatArray | None = None) -> list[FloatArray] | None:
        """``K^-1 v`` for each v by CG on the exact tangent (at the carried element pressures, if given)
        preconditioned with the rest factor, or None when one does not converge in the budget (see
        :func:`phantom.model.fem.newton.preconditioned_cg`)."""
        if not self.problem.preconditioned:
            return None
        loaded = self.problem.at_load_factor(load_factor)
        multiply = loaded.multiply(loaded.tangent_data(positions_m, element_pressures_pa))
        preconditioner = self.problem.rest_factorization()
        solutions = []
        for rhs in right_hand_sides:
            solution = preconditioned_cg(multiply, rhs, preconditioner, VOLUME_KRYLOV_TOLERANCE,
                                         VOLUME_KRYLOV_ITERATIONS)
            if solution is None:
                return None
            solutions.append(solution)
        return solutions

    def _volume_residual(self, positions_m: FloatArray, load_factor: float, target_m3: float,
                         element_pressures_pa: FloatArray | None = None, with_tangent: bool = False) -> _VolumeState:
        """The bordered system's residual at ``positions_m`` and ``load_factor`` (see :class:`_VolumeState`), at
        carried element pressures when given (their constraint's error then joins the merit); with
        ``with_tangent``, the exact tangent's data from the same element pass."""
        evaluation = self.problem.at_load_factor(load_factor).evaluate(positions_m, with_tangent=with_tangent,
                                                                        element_pressures_pa=element_pressures_pa)
        gap = self._control(positions_m) - target_m3
        free = self.constraints.free_mask
        merit = float((np.linalg.norm(evaluation.residual_n[free]) / self.load_scale) ** 2
                      + (gap / self.control_rest_m3) ** 2)
        if element_pressures_pa is None:
            return _VolumeState(evaluation.residual_n, gap, merit, evaluation.admissible, evaluation.residual_n,
                                tangent_data=evaluation.tangent_data)
        ratios = self.body.element_volume_ratios(positions_m)
        constraint_n = self.body.volume_constraint_error_n(ratios, element_pressures_pa)
        merit += float(constraint_n @ constraint_n) / self.load_scale**2
        return _VolumeState(evaluation.residual_n, gap, merit, evaluation.admissible, evaluation.residual_n, ratios,
                            evaluation.tangent_data)

    def _with_eliminated(self, state: _VolumeState, positions_m: FloatArray,
                         carried_pa: FloatArray) -> _VolumeState:
        """``state`` (at carried pressures ``carried_pa``) with its residual at eliminated pressures (the
        convergence test's and Newton's right-hand side)."""
        assert state.volume_ratios is not None  # a state at carried pressures has its volume ratios
        return dataclasses.replace(state, eliminated_n=self.problem.eliminated_residual_n(
            positions_m, state.residual_n, state.volume_ratios, carried_pa))

    def _cross(self, below: PathPoint, above: PathPoint) -> FloatArray:
        """The equilibrium at lam = 1 between two path points: Illinois regula falsi on the control volume,
        then a pressure-controlled Newton solve at the exact pressures from the bracketed state (first from within
        CROSSING_LOAD_TOLERANCES[0] of lam = 1; where that fails, the bracket closes further and Newton tries
        again: closing it to 1e-6 took ten more volume solves of a shipped-scene solve's 46 iterations)."""
        # Between two equilibria that close on lam = 1, the line through them there is usually within Newton's
        # reach at the exact pressures (two to four iterations); where not, the bracket closes first.
        ratio = (1.0 - below.load_factor) / (above.load_factor - below.load_factor)
        interpolated = self._final_newton(below.positions_m + ratio * (above.positions_m - below.positions_m),
                                          self._combined_pressures([below, above], np.array([1.0 - ratio, ratio])))
        if interpolated is not None:
            return interpolated
        low, high = below, above
        low_weight = high_weight = 1.0
        best = above
        bracket_failed = False
        newton_from: PathPoint | None = None
        for load_tolerance in CROSSING_LOAD_TOLERANCES:
            for _ in range(CROSSING_ITERATIONS):
                if abs(best.load_factor - 1.0) <= load_tolerance or bracket_failed:
                    break
                low_gap, high_gap = (low.load_factor - 1.0) * low_weight, (high.load_factor - 1.0) * high_weight
                target = low.control_m3 + (high.control_m3 - low.control_m3) * low_gap / (low_gap - high_gap)
                ratio = (target - low.control_m3) / (high.control_m3 - low.control_m3)
                guess = low.positions_m + ratio * (high.positions_m - low.positions_m)
                if not self._upright(guess):
                    guess = low.positions_m
                step = self._volume_newton(guess, low.load_factor + ratio * (high.load_factor - low.load_factor),
                                           target)
                self.iterations += step.iterations
                if not step.converged:
                    bracket_failed = True
                    break
                assert step.point is not None  # a converged step has its point
                best = step.point
                if best.load_factor < 1.0:
                    low, low_weight, high_weight = best, 1.0, high_weight * 0.5
                else:
                    high, high_weight, low_weight = best, 1.0, low_weight * 0.5
            if best is newton_from:  # the bracket came no closer: Newton would fail from the same state again
                break
            newton_from = best
            final = newton(self.problem, best.positions_m, self.tolerance)
            self.iterations += final.iterations
            if final.converged:
                self.steps += 1
                return final.positions_m
            if bracket_failed:
                break
        raise self._unreachable(best, f"the {final.reason} at the exact pressures", final.worst_element)

    def _locate_peak(self, history: list[PathPoint]) -> PathPoint:
        """The equilibrium at the limit point behind the last step of ``history`` (whose load factor fell), to
        PEAK_LOAD_TOLERANCE: the maximum of Hermite's cubic of lam(c) through the bracketing equilibria and their
        directions, solved there under volume control, the bracket narrowed on the sign of dlam/dc at the
        solution. Where a solve fails, the highest equilibrium found."""
        point, new = history[-2], history[-1]
        if point.rate is None:
            point.rate = self._tangent_direction(point)
        if len(history) >= 3 and point.rate is not None and point.rate.load_factor_per_m3 < 0:
            low, high = history[-3], point  # the load already fell at the last point: the peak lies before it
        else:
            low, high = point, new
        best = max((low, high), key=lambda p: p.load_factor)
        for _ in range(PEAK_SOLVES):
            for end in (low, high):
                if end.rate is None:
                    end.rate = self._tangent_direction(end)
            fraction = self._cubic_peak(low, high)
            if fraction is None:
                break
            target = low.control_m3 + fraction * (high.control_m3 - low.control_m3)
            cubic = self._hermite(low, high, target)
            assert cubic is not None  # both ends have their direction
            guess_m, predicted, guess_pa = cubic
            if not self._upright(guess_m):
                break
            step = self._volume_newton(guess_m, predicted, target, guess_pa)
            self.iterations += step.iterations
            if not step.converged or step.point is None:
                break
            middle = step.point
            middle.rate = self._tangent_direction(middle, step.factor)
            self.steps += 1
            if middle.load_factor > best.load_factor:
                best = middle
            if abs(middle.load_factor - predicted) <= PEAK_LOAD_TOLERANCE * abs(middle.load_factor):
                break
            if middle.rate is None:
                break
            if middle.rate.load_factor_per_m3 > 0:
                low = middle
            else:
                high = middle
        return best

    @staticmethod
    def _cubic_peak(low: PathPoint, high: PathPoint) -> float | None:
        """Where (0..1 between ``low`` and ``high``, in the control volume) Hermite's cubic of the load factor peaks;
        None where an end lacks its direction."""
        if low.rate is None or high.rate is None:
            return None
        span = high.control_m3 - low.control_m3
        start, end = low.load_factor, high.load_factor
        slope_start, slope_end = span * low.rate.load_factor_per_m3, span * high.rate.load_factor_per_m3
        # lam(t) = a t^3 + b t^2 + c t + d: its stationary points with lam'' < 0 inside the bracket
        a = 2.0 * (start - end) + slope_start + slope_end
        b = 3.0 * (end - start) - 2.0 * slope_start - slope_end
        c = slope_start
        roots = np.roots([3.0 * a, 2.0 * b, c]) if abs(a) > 1e-14 * (abs(b) + abs(c)) else np.array([-c / (2.0 * b)])
        maxima = [float(t.real) for t in roots
                  if abs(t.imag) < 1e-12 and 0.0 < t.real < 1.0 and 6.0 * a * t.real + 2.0 * b < 0.0]
        if maxima:
            return maxima[0]
        grid = np.linspace(0.0, 1.0, 101)
        fraction = float(grid[np.argmax(((a * grid + b) * grid + c) * grid)])
        return fraction if 0.0 < fraction < 1.0 else None

    def _moved_most(self, point: PathPoint) -> tuple[int, FloatArray, str, float]:
        """The chamber that grew most (weighted by the load) at ``point``, the chamber volumes (m^3) there, the
        chamber described (name, target pressure, p/E) and its target pressure (kPa)."""
        body = self.body
        chambers = body.chamber_volumes_m3(point.positions_m)
        growth = np.abs(self.weights) * (chambers / body.rest_chamber_volumes_m3 - 1.0)
        chamber = int(np.argmax(growth))
        target_kpa = float(self.pressures[chamber] / 1e3)
        ratio = abs(self.pressures[chamber]) / body.material.youngs_modulus_pa
        return (chamber, chambers, f"chamber {chamber} ({body.chamber_names[chamber]!r} at {target_kpa:g} kPa, "
                f"p/E = {ratio:.3g})", target_kpa)

    def _past_peak(self, peak: PathPoint, point: PathPoint) -> PeakPressureError:
        """The pressure asked of the chamber that grew most lies above its peak (``peak``); the path went on to
        ``point``."""
        body = self.body
        chamber, chambers, described, target_kpa = self._moved_most(peak)
        peak_kpa = peak.load_factor * target_kpa
        peak_ml = chambers[chamber] * 1e6
        others = ("" if np.count_nonzero(self.pressures) <= 1 else
                  " with the other chambers' pressures in the same proportion")
        beyond_ml = body.chamber_volumes_m3(point.positions_m)[chamber] * 1e6
        return PeakPressureError(
            f"{described} is out of reach: its "
            f"pressure-volume curve peaks at {peak_kpa:.4g} kPa (at {peak_ml:.4g} ml){others} and falls beyond (a "
            f"limit point: a pressure source would burst it through; the path went on to "
            f"{point.load_factor * target_kpa:.4g} kPa at {beyond_ml:.4g} ml, rest "
            f"{body.rest_chamber_volumes_m3[chamber] * 1e6:.4g} ml); ask for at most {peak_kpa:.4g} kPa "
            f"there, control its volume instead (phantom inverse --chamber-volumes-ml), or use a stiffer or "
            f"strain-stiffening material (gent)", chamber, float(target_kpa), float(peak_kpa), float(peak_ml))

    def _unreachable(self, point: PathPoint, why: str, worst_element: int = -1) -> SolveError:
        """The chamber that moved most (weighted), where the path stopped, and why."""
        body = self.body
        chamber, chambers, described, target_kpa = self._moved_most(point)
        reached_kpa = point.load_factor * target_kpa
        detail = why
        if worst_element >= 0:
            detail = f"{why} (element {worst_element} at det F <= 0)"
        return SolveError(
            f"{described} is out of reach: {detail}; "
            f"the path stopped at {reached_kpa:.4g} kPa and {chambers[chamber] * 1e6:.4g} ml (rest "
            f"{body.rest_chamber_volumes_m3[chamber] * 1e6:.4g} ml, after {self.steps} accepted steps); try a lower "
            f"pressure in that chamber, a stiffer or strain-stiffening material (gent), or a finer mesh (--size-mm)")


def follow_path(problem: EquilibriumProblem, tolerance: float) -> PathResult:
    """The equilibrium of ``problem`` at its full pressures, from its start by path following (module
    docstring), to the Newton ``tolerance`` (relative to the load). Raises SolveError naming the chamber out of
    reach and why."""
    path = _Path(problem, tolerance)
    positions_m = path.run()
    return PathResult(positions_m, path.iterations, path.steps)


@dataclass
class VolumePoint:
    """An equilibrium under volume control: node positions (n, 3) m, the load factor (the pressures are ``lam p``),
    the control volume (m^3), and the path's dlam/dc there (1/m^3; negative past a peak, None where not solved)."""

    positions_m: FloatArray
    load_factor: float
    control_m3: float
    load_factor_per_m3: float | None


def follow_volume(problem: EquilibriumProblem, controls_m3: FloatArray | list[float]) -> list[VolumePoint]:
    """Equilibria of ``problem`` under volume control at each of ``controls_m3`` (the load-weighted chamber volume
    ``c = sum w_i V_i``, ``w = p / max|p|``: one loaded chamber, its volume), from its start, through limit points:
    the load factor at each is the pressure (``lam p``) that holds the chambers there, on the rising branch or the
    falling one beyond a peak. The path steps as :func:`follow_path`'s volume control does (Hermite predictor,
    doubling after a quick step, halving after a failed one). Raises SolveError where a step cannot be made (an
    element would invert) even after halving it MAX_VOLUME_BISECTIONS times."""
    path = _Path(problem, PATH_TOLERANCE)
    point = path._point(0.0, path.start_m)
    history = [point]
    control_step = FIRST_VOLUME_STEP * path.control_rest_m3
    answers = []
    for wanted in sorted(float(c) for c in controls_m3):
        bisections = 0
        while point.control_m3 < wanted - CONTROL_TOLERANCE * path.control_rest_m3:
            target = min(point.control_m3 + control_step, wanted)
            guess_m, guess_factor, guess_pa = path._volume_guess(history, point, target)
            worst = problem.worst_element(guess_m)
            step = (path._volume_newton(guess_m, guess_factor, target, guess_pa) if worst < 0
                    else _VolumeStep(False, None, 0, "solve would invert elements", worst))
            path.iterations += step.iterations
            if not step.converged or step.point is None:
                bisections += 1
                control_step /= 2.0
                if bisections > MAX_VOLUME_BISECTIONS:
                    raise path._unreachable(point, f"the {step.reason} one volume step further", step.worst_element)
                continue
            new = step.point
            new.rate = path._tangent_direction(new, step.factor)
            history = [*history[-(PREDICTOR_POINTS - 1):], new]
            if step.iterations <= DOUBLING_ITERATIONS and bisections == 0:
                control_step *= 2.0
            bisections = 0
            point = new
        if point.rate is None and point.load_factor != 0.0:
            point.rate = path._tangent_direction(point)
        answers.append(VolumePoint(point.positions_m, point.load_factor, point.control_m3,
                                   None if point.rate is None else point.rate.load_factor_per_m3))
    return answers
