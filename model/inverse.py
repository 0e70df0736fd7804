"""The inverse problem: which chamber pressures give a wanted gland or chamber volume.

Around a state with pressures ``p_k`` (Pa), chamber volumes ``c_k`` and gland volume ``g_k`` (m^3), the
volumes are linear in the pressures to first order:

    c(p) = c_k + W_k (p - p_k)          g(p) = g_k + h_k . p - h_k . p_k

with ``W_k`` the chamber compliance (m^3/Pa, symmetric) and ``h_k`` the gland compliance. Each target is a
row ``a . p = b``. physics.md's formulation is the regularised least squares

    minimise   1/2 |A p - b|^2 + epsilon/2 p^T W_0 p        (W_0: rest compliance, the actuation energy)
    subject to 0 <= p <= p_max,  growth ratios (equalities),  growth limits (upper bounds)

whose answer, as epsilon -> 0+, is the least actuation energy among the pressures that meet the targets: that
is what a total-volume target (one combination of three pressures) needs to be unique and well spread. For a
reachable target we solve that limit directly, which is exact and well conditioned (P = W_0):

    minimise   1/2 p^T W_0 p    subject to  A p = b,  the bounds and constraints above

and only when it is infeasible do we solve the least-squares form (epsilon = 1e-3 relative), to find the
closest pressures and explain what is reachable. Both are QPs solved with OSQP, set up once per problem shape
and updated in place, warm-started. The linearisation is then iterated (Newton with the tangent compliance at
the full level, a chord iteration with ``W_0`` at the others): the volumes at the answer are recomputed at
the solver's fidelity level, the compliance updated at the inflated state, until those volumes meet the
target. Inside, the QP's pressures and volumes are scaled so that its entries are of order one.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass
from itertools import pairwise
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike

from phantom import PhantomError, is_finite_number
from phantom.model.arrays import FloatArray
from phantom.model.errors import PeakPressureError, SolveError
from phantom.model.fem.model import PhantomModel
from phantom.model.fem.newton import RELATIVE_TOLERANCE
from phantom.model.fidelity.levels import Evaluation, VolumeEstimator
from phantom.model.fidelity.response_table import ResponseTableError, stored_response_table
from phantom.model.scene import chamber_labels_of, pressure_limit_error
from phantom.model.target import ML_PER_M3, InverseResult, Target, UnreachableTargetError

if TYPE_CHECKING:
    import scipy.sparse

#: Weight of the actuation energy relative to the targets' curvature in the least-squares (closest) QP used
#: when a target is out of reach, dimensionless: it fixes the null space of a rank-one (total volume) target.
CLOSEST_REGULARISER_WEIGHT = 1e-3
#: Largest magnitude of a QP entry in scaled units (entries are of order one): a target past it (1e300 ml) is
#: out of reach by orders of magnitude and is answered from the reachable range without asking OSQP.
QP_ENTRY_LIMIT = 1e12


#: The exact QP's least-energy answer slides along the target's level set, which is curved: near 3 kPa on the
#: calibrated Gent model two tangents a few pascal apart put it 300-800 Pa apart, so the outer iteration bounced
#: between two branches, every full step refused, and the error stalled at 0.1-1 %. So the QP minimises the
#: energy of the move from ``theta`` times the current pressures, ``1/2 (x - theta p)^T W_0 (x - theta p)``
#: (the least energy plus a proximal term of weight theta / (1 - theta); its fixed points are still the
#: least-energy answers for theta < 1): theta starts at 0 and goes halfway to 1 at every damped step, ...
PROXIMAL_AFTER_DAMPING = 0.5
#: ... and is 1 (the least move that meets the linearised targets, which converges like Newton) once the relative
#: volume error is below this: the answer is then the least-energy one to within what 0.1 % of the volume allows.
POLISH_RELATIVE_ERROR = 1e-3
#: Halvings of an outer step before the least-error trial is taken anyway (the next linearisation is made there).
STEP_HALVINGS = 6
#: A trial step stays below this fraction of a peak met before (:meth:`InverseSolver._above_known_peak`): the path
#: locates a peak to 1e-5 of its load, and the curve is flat there (the thick sphere at the cavity stretch 1.75,
#: its peak's 1.83, needs 0.997 of the peak's pressure).
PEAK_MARGIN = 0.9999
#: Armijo fraction: a step of fraction t is taken when it cuts the relative volume error by at least this times t.
SUFFICIENT_DECREASE = 1e-4
#: The outer iteration's tolerances (relative volume errors, fractions) an InverseSolver takes: none finer than the
#: forward solve's own Newton tolerance (relative to its load), which the volumes it measures the error with are
#: good to, and none looser than 10 %, the model's own known error (11 %, measurements.MODEL_ERROR_95_PCT): 1
#: meant as 1 % was taken as 100 %, and 0, -1 or nan ran 15 linearisations (47 s) to "did not converge".
TOLERANCE_RANGE = (RELATIVE_TOLERANCE, 0.1)


class LimitPointError(UnreachableTargetError):
    """The target lies at or past the pressure-control limit point, where the chamber snaps through."""


@dataclass(frozen=True)
class Linearisation:
    """Volumes and their derivatives at one state (SI): the QP's model of the forward problem."""

    pressures_pa: np.ndarray
    chamber_volumes_m3: np.ndarray
    gland_volume_m3: float
    chamber_m3_per_pa: np.ndarray
    gland_m3_per_pa: np.ndarray

    def predict(self, pressures_pa: np.ndarray) -> tuple[np.ndarray, float]:
        """First-order chamber volumes (m^3) and gland volume (m^3) at ``pressures_pa``."""
        step_pa = np.asarray(pressures_pa, dtype=float) - self.pressures_pa
        return (self.chamber_volumes_m3 + self.chamber_m3_per_pa @ step_pa,
                float(self.gland_volume_m3 + self.gland_m3_per_pa @ step_pa))


def _finite(name: str, values: ArrayLike) -> FloatArray:
    array = np.asarray(values, dtype=float)
    if not np.all(np.isfinite(array)):
        raise PhantomError(f"{name} must be finite numbers, got {np.asarray(values).tolist()}")
    return array


def _one_or_per_chamber(shape: tuple[int, ...], n_chambers: int) -> bool:
    """Whether a bound of ``shape`` is one value (a number, or a list of one) or one per chamber."""
    return shape in ((), (1,), (n_chambers,))


def _dense_csc_pattern(matrix: FloatArray, upper: bool) -> scipy.sparse.csc_matrix:
    """A CSC matrix (scipy) holding every entry of ``matrix`` (the upper triangle only when ``upper``),
    zeros included, so that later value updates keep one fixed sparsity pattern."""
    # scipy.sparse (0.15 s to import) only where a QP is set up
    from scipy import sparse

    rows, columns = matrix.shape
    data: list[float] = []
    indices: list[int] = []
    indptr = [0]
    for column in range(columns):
        last_row = column + 1 if upper else rows
        indices.extend(range(last_row))
        data.extend(matrix[:last_row, column])
        indptr.append(len(indices))
    return sparse.csc_matrix((np.array(data, dtype=np.float64), np.array(indices), np.array(indptr)),
                             shape=(rows, columns))


def _dense_values(matrix: np.ndarray, upper: bool) -> np.ndarray:
    """The values of :func:`_dense_csc_pattern` in storage order."""
    if upper:
        return np.concatenate([matrix[: column + 1, column] for column in range(matrix.shape[1])])
    return matrix.T.reshape(-1).copy()


class _Infeasible(Exception):
    """The QP's constraints admit no point (internal: the caller falls back or explains)."""


class VolumeQP:
    """One OSQP problem of a fixed shape, in scaled units, updated in place and warm-started.

    Variables: chamber pressures ``x`` (scaled). Objective ``1/2 x^T P x + q^T x``, constraints ``l <= C x <= u``
    whose first rows are the identity (pressure bounds). The sparsity patterns are dense and fixed, so later
    solves only update values.
    """

    def __init__(self, n_chambers: int, n_constraint_rows: int):
        # osqp (0.3 s to import, with scipy.sparse) only where a volume target is solved
        import osqp

        self.n_chambers = n_chambers
        self.n_constraint_rows = n_constraint_rows
        self._osqp = osqp
        self._problem: Any = None  # an osqp.OSQP once set up

    def minimise(self, objective_hessian: np.ndarray, objective_linear: np.ndarray, constraint_matrix: np.ndarray,
              lower: np.ndarray, upper: np.ndarray) -> tuple[np.ndarray, float]:
        """Minimise the QP; returns the pressures (scaled) and OSQP's own solve time (s).

        Raises ``_Infeasible`` when the constraints contradict each other.
        """
        if constraint_matrix.shape != (self.n_constraint_rows, self.n_chambers):
            raise ValueError(f"constraint matrix shape {constraint_matrix.shape} does not match this QP")
        for array in (objective_hessian, objective_linear, constraint_matrix, lower, upper):
            finite = np.asarray(array, dtype=float)[np.isfinite(array)]  # infinite bounds are OSQP's "none"
            if np.isnan(array).any() or (finite.size and np.abs(finite).max() > QP_ENTRY_LIMIT):
                # OSQP's setup fails on such data (and used to leave a half-built problem behind)
                raise UnreachableTargetError("the volume QP's data are out of scale (a target orders of magnitude "
                                             "out of reach?): check the target and the model")
        try:
            if self._problem is None:
                problem = self._osqp.OSQP()
                problem.setup(_dense_csc_pattern(objective_hessian, upper=True), objective_linear,
                              _dense_csc_pattern(constraint_matrix, upper=False), lower, upper,
                              verbose=False, warm_starting=True, polishing=True, eps_abs=1e-10, eps_rel=1e-10,
                              eps_prim_inf=1e-9, eps_dual_inf=1e-9, max_iter=20000)
                self._problem = problem
            else:
                self._problem.update(Px=_dense_values(objective_hessian, upper=True),
                                     Ax=_dense_values(constraint_matrix, upper=False),
                                     q=objective_linear, l=lower, u=upper)
            result = self._problem.solve(raise_error=False)
        except Exception as error:
            # a problem whose update or solve failed holds partial data: the next call sets it up afresh
            self._problem = None
            raise UnreachableTargetError(f"the volume QP could not be solved ({error}): check the target and "
                                         "the model") from error
        status = self._osqp.SolverStatus(result.info.status_val)
        if status in (self._osqp.SolverStatus.OSQP_PRIMAL_INFEASIBLE,
                      self._osqp.SolverStatus.OSQP_PRIMAL_INFEASIBLE_INACCURATE):
            raise _Infeasible()
        if status not in (self._osqp.SolverStatus.OSQP_SOLVED, self._osqp.SolverStatus.OSQP_SOLVED_INACCURATE):
            raise UnreachableTargetError(f"the volume QP did not solve (OSQP status {status.name}); "
                                         "the compliance may be singular: check the model")
        return np.asarray(result.x, dtype=float), float(result.info.solve_time)


@dataclass
class _Rows:
    """A target turned into rows (in the QP's scaled units) at one linearisation."""

    objective_rows: np.ndarray          # (k, n): scaled volume per scaled pressure
    objective_targets: np.ndarray       # (k,): scaled volume
    objective_names: list[str]
    constraint_rows: np.ndarray         # (m, n), after the n pressure-bound rows
    constraint_lower: np.ndarray
    constraint_upper: np.ndarray


class InverseSolver:
    """Chamber pressures (Pa) that give a wanted volume, for one model.

    Parameters
    ----------
    model : PhantomModel
        The forward model (``phantom.model``).
    pressure_max_pa : float or sequence of float, or None
        Upper pressure bound per chamber (Pa); the lower bound is 0 (the blowers only push). None: the model's
        settings' (the scene's ``[model] pressure_max_kpa``, else PRESSURE_LIMIT_PA).
    fidelity : {"rest", "updated", "full", "table"} or None
        How the volumes at a candidate answer are computed (:class:`phantom.model.fidelity.levels.VolumeEstimator`);
        None takes the scene's ``[model] fidelity``, else the cheapest level that meets its ``accuracy_pct``.
    max_growth_m3 : float or sequence of (float or None), optional
        Upper limit on each chamber's growth above its rest volume (m^3).
    tolerance : float
        Relative volume tolerance of the outer iteration (a fraction of the target volume: 0.001 is 0.1 %), within
        :data:`TOLERANCE_RANGE`.
    max_iterations : int
        Linearisations before giving up (at least 1).
    estimator : VolumeEstimator, optional
        A ready estimator to share (its level wins over ``fidelity``).

    The scene's settings are the model's (:attr:`PhantomModel.model_settings`).
    """

    def __init__(self, model: PhantomModel, pressure_max_pa: float | Sequence[float] | None = None,
                 fidelity: str | None = None, max_growth_m3: float | Sequence[float | None] | None = None,
                 tolerance: float = 2e-5, max_iterations: int = 15, estimator: VolumeEstimator | None = None):
        low, high = TOLERANCE_RANGE
        if not (is_finite_number(tolerance) and low <= tolerance <= high):
            raise PhantomError(f"tolerance is the relative volume error the inverse stops at, a fraction: 0.001 is "
                               f"0.1 %; give one from {low:g} to {high:g}, got {tolerance!r}")
        if isinstance(max_iterations, bool) or not isinstance(max_iterations, int | np.integer) or max_iterations < 1:
            raise PhantomError(f"max_iterations must be an integer of at least 1, got {max_iterations!r} (the "
                               "linearisations before the inverse gives up)")
        self.model = model
        self.n_chambers = int(model.n_chambers)
        #: what a target beyond the box should raise: the scene's bound, or the one this solver was given below it
        self.bound_to_raise = "the scene's pressure_max_kpa"
        if pressure_max_pa is None:
            pressure_max_pa = model.model_settings.pressure_max_pa
        elif np.any(np.asarray(pressure_max_pa, dtype=float) < model.model_settings.pressure_max_pa):
            self.bound_to_raise = (f"the pressure bound asked, up to the scene's pressure_max_kpa "
                                   f"({model.model_settings.pressure_max_pa / 1e3:g} kPa)")
        limits_pa = _finite("pressure_max_pa", pressure_max_pa)
        if not _one_or_per_chamber(np.shape(limits_pa), self.n_chambers):
            raise PhantomError(f"pressure_max_pa is one pressure (Pa) or one per chamber ({self.n_chambers}), got "
                               f"{limits_pa.tolist()}")
        self.pressure_max_pa = np.broadcast_to(limits_pa, (self.n_chambers,)).astype(float)
        if np.any(self.pressure_max_pa <= 0):
            raise PhantomError(f"pressure_max_pa must be positive, got {self.pressure_max_pa.tolist()}")
        if max_growth_m3 is None:
            max_growth_m3 = [None] * self.n_chambers
        growths = np.array(max_growth_m3, dtype=object)
        if not _one_or_per_chamber(growths.shape, self.n_chambers):
            raise PhantomError(f"max_growth_m3 is one growth (m^3) or one (or None) per chamber ({self.n_chambers}), "
                               f"got {growths.tolist()!r:.80}")
        self.max_growth_m3 = [None if value is None else float(value)
                              for value in np.broadcast_to(growths, (self.n_chambers,))]
        # QP units: pressures in units of the largest bound, volumes in units of the rest compliance's volume
        # change at that pressure, so that every entry of the QP is of order one whatever E and the mesh.
        self.pressure_per_pa = 1.0 / float(self.pressure_max_pa.max())
        self.tolerance = float(tolerance)
        self.max_iterations = int(max_iterations)
        self.estimator = estimator or VolumeEstimator(model, level=fidelity,
                                                      pressure_max_pa=float(self.pressure_max_pa.max()))
        rest = model.compliance()
        self.rest = Linearisation(np.zeros(self.n_chambers), np.asarray(model.rest_chamber_volumes_m3, dtype=float),
                                  float(model.rest_gland_volume_m3), np.asarray(rest.chamber_m3_per_pa, dtype=float),
                                  np.asarray(rest.gland_m3_per_pa, dtype=float))
        eigenvalues = np.linalg.eigvalsh(0.5 * (self.rest.chamber_m3_per_pa + self.rest.chamber_m3_per_pa.T))
        if not np.all(np.isfinite(eigenvalues)) or eigenvalues.min() <= 0:
            raise PhantomError(f"the rest compliance is not positive definite (eigenvalues {eigenvalues.tolist()} "
                               "m^3/Pa): the model is not restrained or not elastic; check the scene")
        self.volume_per_m3 = 1.0 / (float(np.mean(eigenvalues)) / self.pressure_per_pa)
        self._problems: dict[tuple[str, int, int], VolumeQP] = {}
        #: the pressures (Pa) at the peaks that trials met, each along its trial's ray (:meth:`_above_known_peak`)
        self._peaks_pa: list[FloatArray] = []
        self._solved_range: tuple[FloatArray, FloatArray] | None = None

    # ----------------------------------------------------------------- targets -> rows
    def _check_target(self, target: Target) -> None:
        n = self.n_chambers
        forms = [target.gland_volume_m3 is not None, target.chamber_volumes_m3 is not None,
                 target.pressures_pa is not None]
        if target.pressures_pa is not None and sum(forms) > 1:
            raise PhantomError("a target gives either raw pressures or volumes, not both")
        if not any(forms):
            raise PhantomError("the target is empty: give a gland volume, chamber volumes or pressures")
        if target.gland_volume_m3 is not None:
            _finite("gland_volume_m3", target.gland_volume_m3)
        if target.chamber_volumes_m3 is not None:
            if len(target.chamber_volumes_m3) != n:
                raise PhantomError(f"chamber_volumes_m3 needs {n} entries (None for a free chamber), "
                                   f"got {len(target.chamber_volumes_m3)}")
            for value in target.chamber_volumes_m3:
                if value is not None:
                    _finite("chamber_volumes_m3", value)
        if target.growth_ratio is not None:
            if len(target.growth_ratio) < 2:
                raise PhantomError("a growth ratio relates at least two chambers, e.g. {1: 2.0, 2: 1.0}")
            for index, weight in target.growth_ratio.items():
                if not (isinstance(index, (int, np.integer)) and 0 <= index < n):
                    raise PhantomError(f"growth_ratio names chamber {index!r}: chambers are 0..{n - 1}")
                if not np.isfinite(weight) or weight <= 0:
                    raise UnreachableTargetError(
                        f"growth_ratio weight {weight} for chamber {index} asks for a chamber to shrink or stay: "
                        "the blowers only inflate, so weights must be positive")

    def _rows(self, target: Target, linearisation: Linearisation) -> _Rows:
        """The target's rows and constraint rows at ``linearisation`` (scaled units)."""
        scale = self.volume_per_m3 / self.pressure_per_pa
        chamber_scaled_slope = linearisation.chamber_m3_per_pa * scale
        gland_scaled_slope = linearisation.gland_m3_per_pa * scale
        pressures_scaled = linearisation.pressures_pa * self.pressure_per_pa
        # Constant parts: the volume the linear model gives at zero pressure.
        chamber_offset_scaled = (linearisation.chamber_volumes_m3 * self.volume_per_m3
                                 - chamber_scaled_slope @ pressures_scaled)
        gland_offset_scaled = linearisation.gland_volume_m3 * self.volume_per_m3 - gland_scaled_slope @ pressures_scaled
        rest_chamber_scaled = self.rest.chamber_volumes_m3 * self.volume_per_m3

        rows, values, names = [], [], []
        if target.gland_volume_m3 is not None:
            rows.append(gland_scaled_slope)
            values.append(target.gland_volume_m3 * self.volume_per_m3 - gland_offset_scaled)
            names.append("gland")
        for index, volume in enumerate(target.chamber_volumes_m3 or []):
            if volume is not None:
                rows.append(chamber_scaled_slope[index])
                values.append(volume * self.volume_per_m3 - chamber_offset_scaled[index])
                names.append(f"chamber {index}")

        constraint_rows, lower, upper = [], [], []
        if target.growth_ratio:
            for (first, first_weight), (second, second_weight) in pairwise(sorted(target.growth_ratio.items())):
                # growth_first / w_first = growth_second / w_second, growth = offset + row . x - rest
                constraint_rows.append(second_weight * chamber_scaled_slope[first]
                                       - first_weight * chamber_scaled_slope[second])
                constant = (second_weight * (chamber_offset_scaled[first] - rest_chamber_scaled[first])
                            - first_weight * (chamber_offset_scaled[second] - rest_chamber_scaled[second]))
                lower.append(-constant)
                upper.append(-constant)
        for index, limit in enumerate(self.max_growth_m3):
            if limit is not None:
                constraint_rows.append(chamber_scaled_slope[index])
                lower.append(-np.inf)
                upper.append(limit * self.volume_per_m3 + rest_chamber_scaled[index] - chamber_offset_scaled[index])
        n = self.n_chambers
        return _Rows(np.array(rows, dtype=float).reshape(-1, n), np.array(values, dtype=float), names,
                     np.array(constraint_rows, dtype=float).reshape(-1, n), np.array(lower, dtype=float),
                     np.array(upper, dtype=float))

    def _qp_inputs(self, rows: _Rows, exact: bool, anchor_scaled: FloatArray | None = None
                   ) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray]:
        """OSQP data (scaled units). Exact: the targets are equalities and the objective is the actuation energy
        ``1/2 x^T W_0 x`` (of the move from ``anchor_scaled``, ``1/2 (x - a)^T W_0 (x - a)``, when given).
        Closest: the targets are least squares ``1/2 |A x - b|^2 + epsilon/2 x^T W_0 x``."""
        n = self.n_chambers
        rest_scaled_slope = self.rest.chamber_m3_per_pa * (self.volume_per_m3 / self.pressure_per_pa)
        energy = 0.5 * (rest_scaled_slope + rest_scaled_slope.T)
        bounds_lower, bounds_upper = np.zeros(n), self.pressure_max_pa * self.pressure_per_pa
        if exact:
            hessian, linear = energy, np.zeros(n) if anchor_scaled is None else -energy @ anchor_scaled
            constraint_matrix = np.vstack([np.eye(n), rows.objective_rows, rows.constraint_rows])
            lower = np.concatenate([bounds_lower, rows.objective_targets, rows.constraint_lower])
            upper = np.concatenate([bounds_upper, rows.objective_targets, rows.constraint_upper])
            return hessian, linear, constraint_matrix, lower, upper
        # Closest: the growth ratios join the least squares (the linearised ratio may not hold at any allowed
        # pressure); the one-sided growth limits stay constraints.
        equality = rows.constraint_lower == rows.constraint_upper
        least_squares_rows = np.vstack([rows.objective_rows, rows.constraint_rows[equality]])
        least_squares_targets = np.concatenate([rows.objective_targets, rows.constraint_upper[equality]])
        curvature = least_squares_rows.T @ least_squares_rows
        epsilon = CLOSEST_REGULARISER_WEIGHT * max(np.trace(curvature), 1e-12) / np.trace(energy)
        constraint_matrix = np.vstack([np.eye(n), rows.constraint_rows[~equality]])
        return (curvature + epsilon * energy, -least_squares_rows.T @ least_squares_targets, constraint_matrix,
                np.concatenate([bounds_lower, rows.constraint_lower[~equality]]),
                np.concatenate([bounds_upper, rows.constraint_upper[~equality]]))

    def _problem(self, kind: str, rows: _Rows, n_constraint_rows: int) -> VolumeQP:
        shape = (kind, len(rows.objective_names), n_constraint_rows)
        problem = self._problems.get(shape)
        if problem is None:
            problem = self._problems[shape] = VolumeQP(self.n_chambers, n_constraint_rows)
        return problem

    def pressures_for_linearisation(self, target: Target, linearisation: Linearisation,
                                    anchor_pa: FloatArray | None = None) -> tuple[FloatArray, float, _Rows, bool]:
        """One QP at ``linearisation``; with ``anchor_pa`` the exact QP's objective is the actuation energy of
        the move from there (``1/2 (x - a)^T W_0 (x - a)``) instead of from zero (see PROXIMAL_AFTER_DAMPING).

        Returns the pressures (Pa), the OSQP time (s), the rows used, and whether the targets are met exactly
        (False: no allowed pressures meet them to first order, and the pressures are the least-squares closest).
        """
        rows = self._rows(target, linearisation)
        qp_time_s = 0.0
        try:
            inputs = self._qp_inputs(rows, exact=True,
                                     anchor_scaled=None if anchor_pa is None else anchor_pa * self.pressure_per_pa)
            pressures_scaled, qp_time_s = self._problem("exact", rows, inputs[2].shape[0]).minimise(*inputs)
            reached = True
        except _Infeasible:
            inputs = self._qp_inputs(rows, exact=False)
            try:
                pressures_scaled, closest_time_s = self._problem("closest", rows, inputs[2].shape[0]).minimise(*inputs)
            except _Infeasible:
                raise UnreachableTargetError(
                    "the constraints contradict each other: no pressures between the bounds satisfy the growth "
                    "ratio and growth limits together; relax one of them") from None
            qp_time_s += closest_time_s
            reached = False
        pressures_scaled = np.clip(pressures_scaled, 0.0, self.pressure_max_pa * self.pressure_per_pa)
        return pressures_scaled / self.pressure_per_pa, qp_time_s, rows, reached

    def reachable_range_ml(self, target: Target, linearisation: Linearisation, row_name: str) -> tuple[float, float]:
        """The least and greatest value (ml) of one target row over the allowed pressures, to first order
        at ``linearisation`` (a linear program over the bounds and constraints), the row's volume then evaluated
        at those extreme pressures at the solver's fidelity level (a linearisation made at the pressure limit
        would otherwise extrapolate the low end below the rest volume)."""
        # scipy.optimize (0.5 s to import) only where an unreachable target's range is reported
        from scipy.optimize import linprog

        rows = self._rows(target, linearisation)
        index = rows.objective_names.index(row_name)
        bounds = [(0.0, value * self.pressure_per_pa) for value in self.pressure_max_pa]
        equality = np.isfinite(rows.constraint_lower) & (rows.constraint_lower == rows.constraint_upper)
        inequality = ~equality
        extremes = []
        # The greatest first: it is usually where the iteration stopped, which the estimator has solved already.
        for sign in (-1.0, 1.0):
            solution = linprog(sign * rows.objective_rows[index], bounds=bounds,
                               A_eq=rows.constraint_rows[equality] if equality.any() else None,
                               b_eq=rows.constraint_upper[equality] if equality.any() else None,
                               A_ub=rows.constraint_rows[inequality] if inequality.any() else None,
                               b_ub=rows.constraint_upper[inequality] if inequality.any() else None,
                               method="highs")
            if not solution.success:
                raise UnreachableTargetError("the constraints contradict each other: no pressures between the "
                                             "bounds satisfy them; relax the growth ratio or growth limits")
            chamber_volumes_m3, gland_volume_m3, _ = self._evaluate(np.asarray(solution.x) / self.pressure_per_pa)
            volume_m3 = gland_volume_m3 if row_name == "gland" else chamber_volumes_m3[int(row_name.split()[1])]
            extremes.append(float(volume_m3) * ML_PER_M3)
        return extremes[1], extremes[0]

    # ----------------------------------------------------------------- the outer iteration
    def _linearise(self, pressures_pa: FloatArray, evaluation: Evaluation) -> Linearisation:
        """The linearisation at an evaluated state: the response table's gradient on the ``table`` level, the
        model's tangent compliance where the estimator has a state (exact, and one back-substitution for a
        small-strain material), else the rest one (a chord iteration, which converges while the response is
        mildly nonlinear)."""
        chamber_volumes_m3, gland_volume_m3, state = evaluation
        if self.estimator.table is not None:
            slope_chamber, slope_gland = self.estimator.table.compliance(pressures_pa)
        elif state is None or not np.any(pressures_pa):
            slope_chamber, slope_gland = self.rest.chamber_m3_per_pa, self.rest.gland_m3_per_pa
        else:
            tangent = self.model.compliance(state)
            slope_chamber = np.asarray(tangent.chamber_m3_per_pa, dtype=float)
            slope_gland = np.asarray(tangent.gland_m3_per_pa, dtype=float)
            eigenvalues = np.linalg.eigvalsh(0.5 * (slope_chamber + slope_chamber.T))
            if not np.all(np.isfinite(eigenvalues)) or eigenvalues.min() <= 0:
                raise LimitPointError(
                    f"at pressures {np.round(pressures_pa / 1e3, 3).tolist()} kPa the tangent compliance has "
                    f"eigenvalues {eigenvalues.tolist()} m^3/Pa: the phantom is at the pressure-control limit point "
                    "(it would snap through); ask for a smaller volume, or control it by volume")
        return Linearisation(pressures_pa.copy(), chamber_volumes_m3, gland_volume_m3, slope_chamber, slope_gland)

    def pressures_for(self, target: Target) -> InverseResult:
        """The pressures (Pa) that reach ``target`` with the solver's fidelity level.

        Raises
        ------
        UnreachableTargetError
            The target needs pressures outside the bounds or contradicts the constraints; the message gives
            the reachable range.
        LimitPointError
            The target lies past the pressure-control limit point.
        """
        started = time.perf_counter()
        self._check_target(target)
        if target.pressures_pa is not None:
            return self._evaluate_raw_pressures(target, target.pressures_pa, started)

        self._refuse_out_of_scale(target)
        self._refuse_outside_solved_range(target)
        linearisation = self.rest
        pressures_pa = np.zeros(self.n_chambers)
        error = self._relative_error(target, self.rest.chamber_volumes_m3, self.rest.gland_volume_m3)
        qp_time_s = 0.0
        history: list[dict[str, Any]] = []
        proximity = 0.0  # theta of PROXIMAL_AFTER_DAMPING
        for iteration in range(1, self.max_iterations + 1):
            if error < POLISH_RELATIVE_ERROR:
                proximity = 1.0
            candidate_pa, qp_step_s, rows, reached = self.pressures_for_linearisation(target, linearisation,
                                                                           proximity * pressures_pa)
            qp_time_s += qp_step_s
            # The linearisation's answer is where it already stands: its best (closest) pressures.
            settled = iteration > 1 and np.allclose(candidate_pa, pressures_pa, rtol=1e-6,
                                                    atol=1e-6 * float(self.pressure_max_pa.max()))
            if not reached and (settled or self.estimator.level == "rest"):
                residual_scaled = rows.objective_rows @ (candidate_pa * self.pressure_per_pa) - rows.objective_targets
                worst = rows.objective_names[int(np.argmax(np.abs(residual_scaled) / self._row_offsets_scaled(rows)))]
                low_ml, high_ml = self.reachable_range_ml(target, linearisation, worst)
                raise self._unreachable_error(target, worst, low_ml, high_ml)
            pressures_pa, evaluation, error, step = self._damped_step(target, pressures_pa, error, candidate_pa)
            chamber_volumes_m3, gland_volume_m3, _ = evaluation
            history.append({"pressures_pa": pressures_pa.tolist(), "relative_error": error, "reached": reached,
                            "step": step})
            if step < 1.0:
                proximity += PROXIMAL_AFTER_DAMPING * (1.0 - proximity)
            if reached and step == 1.0 and error <= self.tolerance:
                return InverseResult(target, pressures_pa, gland_volume_m3, chamber_volumes_m3, iteration,
                                     time.perf_counter() - started, qp_time_s, history)
            linearisation = self._linearise(pressures_pa, evaluation)
        errors = [round(entry["relative_error"] * 100, 4) for entry in history]
        raise LimitPointError(
            f"the inverse did not converge in {len(history)} linearisations (relative volume errors {errors} %): "
            "the response is too nonlinear here, which happens near the pressure-control limit point; "
            "ask for a smaller volume")

    def _damped_step(self, target: Target, pressures_pa: FloatArray, error: float,
                     candidate_pa: FloatArray) -> tuple[FloatArray, Evaluation, float, float]:
        """Move from ``pressures_pa`` (relative error ``error``) towards the linearisation's answer
        ``candidate_pa``: the full step, else halved until the error falls (Armijo, on the relative volume
        error). An undamped Newton step oscillates where the pressure-volume curve has an inflection (a
        hyperelastic chamber stiffens again after softening): the tangent at the upper state is flatter than
        the secant, and the one at the lower state is too, so each step overshoots the other way.

        Returns the pressures (Pa), their evaluation, their relative error and the step fraction taken. The
        pressures stay within the bounds and linear constraints (a convex combination of two points that
        satisfy them)."""
        step = 1.0
        best: tuple[FloatArray, Evaluation, float, float] | None = None
        above_peak: PeakPressureError | None = None
        for _ in range(STEP_HALVINGS + 1):
            trial_pa = pressures_pa + step * (candidate_pa - pressures_pa)
            # below the peaks met so far (each failed trial costs a path to its peak)
            while self._above_known_peak(trial_pa) and step > 1e-3:
                step *= 0.9
                trial_pa = pressures_pa + step * (candidate_pa - pressures_pa)
            try:
                evaluation = self._evaluate(trial_pa, above_peak_ok=True)
            except PeakPressureError as refusal:
                # The linearisation overshot past a chamber's peak (a rest or chord compliance is stiffer than the
                # path near it): a shorter step, below the peak the path found on the way. A target that only
                # pressures past the peak reach is refused with it below.
                above_peak = refusal
                fraction = refusal.peak_pressure_kpa / refusal.pressure_kpa if refusal.pressure_kpa else 0.5
                self._peaks_pa.append(fraction * trial_pa)
                step *= min(0.5, 0.98 * fraction)
                continue
            trial_error = self._relative_error(target, evaluation[0], evaluation[1])
            if trial_error <= (1.0 - SUFFICIENT_DECREASE * step) * error or trial_error <= self.tolerance:
                return trial_pa, evaluation, trial_error, step
            if best is None or trial_error < best[2]:
                best = (trial_pa, evaluation, trial_error, step)
            step *= 0.5
        if best is None:
            assert above_peak is not None  # every trial was refused for lying past a peak
            raise LimitPointError(
                f"every step towards the target lies past a chamber's peak ({above_peak}); the target lies past the "
                "pressure-control limit point: ask for a smaller volume, or for the pressure that holds one chamber "
                "there under volume control (pressure_on_path: its falling branch)") from above_peak
        return best

    def _above_known_peak(self, pressures_pa: FloatArray) -> bool:
        """``pressures_pa`` lie at or above PEAK_MARGIN of a peak a trial met before, along its ray (the peak's
        pressures scaled alike: exact for one loaded chamber, an estimate for several)."""
        for peak_pa in self._peaks_pa:
            loaded = peak_pa > 0
            if np.any(loaded) and np.max(pressures_pa[loaded] / peak_pa[loaded]) >= PEAK_MARGIN:
                return True
        return False

    def _refuse_out_of_scale(self, target: Target) -> None:
        """A target orders of magnitude out of reach (1e300 ml) is refused with the reachable range before any
        QP sees it: its scaled entries would overflow OSQP's setup."""
        rows = self._rows(target, self.rest)
        targets = rows.objective_targets
        if np.all(np.isfinite(targets)) and (targets.size == 0 or np.abs(targets).max() <= QP_ENTRY_LIMIT):
            return
        with np.errstate(invalid="ignore", over="ignore"):
            badness = np.nan_to_num(np.abs(targets) / self._row_offsets_scaled(rows), nan=np.inf)
        worst = rows.objective_names[int(np.argmax(badness))]
        low_ml, high_ml = self.reachable_range_ml(target, self.rest, worst)
        raise self._unreachable_error(target, worst, low_ml, high_ml)

    def solved_range_m3(self) -> tuple[FloatArray, FloatArray] | None:
        """The least and greatest chamber volumes then gland volume (m^3, each (n_chambers + 1,)) that full solves
        over the pressure box give, read from the model's response table where one is at hand (the estimator's,
        the disk cache's or the one its scene ships: no solve), or None without one (or with one made for another
        model), or for a box other than the table's. Kept after the first call."""
        if self._solved_range is None:
            table = self.estimator.table
            try:
                if table is None and isinstance(self.model, PhantomModel):  # (a stand-in model has no cache)
                    table = stored_response_table(self.model, float(self.pressure_max_pa.max()))
            except ResponseTableError:  # a shipped table made for another model (another modulus, mesh): none
                return None
            if table is None or not np.all(self.pressure_max_pa == table.pressure_max_pa):
                return None
            chambers = np.asarray(table.chamber_values, dtype=float).reshape(-1, self.n_chambers)
            volumes = np.column_stack([chambers, np.asarray(table.gland_values, dtype=float).reshape(-1)])
            self._solved_range = volumes.min(axis=0), volumes.max(axis=0)
        return self._solved_range

    def _refuse_outside_solved_range(self, target: Target) -> None:
        """A volume beyond what the full solves over the pressure box give (:meth:`solved_range_m3`, by more than
        the tolerance) is refused with that range at once, whatever the fidelity: no solve, no QP. (The growth
        ratio and growth limits only narrow the range: a target outside the box's is out of reach with them.)"""
        solved = self.solved_range_m3()
        if solved is None:
            return
        low_m3, high_m3 = solved
        wanted = [("gland", self.n_chambers, target.gland_volume_m3)]
        wanted += [(f"chamber {index}", index, volume) for index, volume in enumerate(target.chamber_volumes_m3 or [])]
        for row_name, column, volume_m3 in wanted:
            if volume_m3 is None:
                continue
            margin_m3 = self.tolerance * abs(volume_m3)
            if not low_m3[column] - margin_m3 <= volume_m3 <= high_m3[column] + margin_m3:
                raise self._unreachable_error(
                    target, row_name, low_m3[column] * ML_PER_M3, high_m3[column] * ML_PER_M3, constrained=False)

    def _evaluate(self, pressures_pa: FloatArray, above_peak_ok: bool = False) -> Evaluation:
        """The estimator's volumes at a candidate answer; a failed forward solve there means the candidate lies
        past the limit point (``above_peak_ok``: a PeakPressureError, which names the peak, passes through)."""
        try:
            return self.estimator.evaluate(pressures_pa)
        except SolveError as error:
            if above_peak_ok and isinstance(error, PeakPressureError):
                raise
            raise LimitPointError(
                f"the forward model has no equilibrium at {np.round(pressures_pa / 1e3, 4).tolist()} kPa ({error}): "
                "the target lies past the pressure-control limit point; ask for a smaller volume") from error

    def _relative_error(self, target: Target, chamber_volumes_m3: FloatArray, gland_volume_m3: float) -> float:
        errors = []
        if target.gland_volume_m3 is not None:
            errors.append(abs(gland_volume_m3 - target.gland_volume_m3) / abs(target.gland_volume_m3))
        for index, volume in enumerate(target.chamber_volumes_m3 or []):
            if volume is not None:
                errors.append(abs(chamber_volumes_m3[index] - volume) / abs(volume))
        if target.growth_ratio:
            growth_m3 = np.asarray(chamber_volumes_m3) - self.rest.chamber_volumes_m3
            shares_m3 = np.array([growth_m3[index] / weight for index, weight in sorted(target.growth_ratio.items())])
            errors.append(float(np.ptp(shares_m3) / max(np.abs(shares_m3).max(), 1e-30)))
        return max(errors) if errors else 0.0

    def _row_offsets_scaled(self, rows: _Rows) -> np.ndarray:
        """A volume scale per row (ml): the rest volume of what the row targets."""
        offsets = []
        for name in rows.objective_names:
            if name == "gland":
                offsets.append(self.rest.gland_volume_m3 * self.volume_per_m3)
            else:
                offsets.append(self.rest.chamber_volumes_m3[int(name.split()[1])] * self.volume_per_m3)
        return np.array(offsets)

    def _unreachable_error(self, target: Target, row_name: str, low_ml: float, high_ml: float,
                           constrained: bool = True) -> UnreachableTargetError:
        """Why a row is out of reach, with its range (ml) over the pressure box (and, ``constrained``, under the
        target's growth ratio and the growth limits); the gland's range also as data."""
        wanted_m3 = (target.gland_volume_m3 if row_name == "gland"
                     else (target.chamber_volumes_m3 or [])[int(row_name.split()[1])])
        assert wanted_m3 is not None  # a row exists only for a wanted volume
        wanted_ml = wanted_m3 * ML_PER_M3
        wanted = f"{wanted_ml:.3f}" if abs(wanted_ml) < 1e9 else f"{wanted_ml:.3g}"
        what = "the gland volume" if row_name == "gland" else f"the volume of {row_name}"
        limits = ", ".join(f"{value / 1e3:g}" for value in self.pressure_max_pa)
        constraints = []
        if target.growth_ratio and constrained:
            constraints.append(f"growth ratio {dict(target.growth_ratio)}")
        if any(limit is not None for limit in self.max_growth_m3) and constrained:
            constraints.append("growth limits")
        with_constraints = f" with the {' and '.join(constraints)}" if constraints else ""
        if low_ml - 1e-9 <= wanted_ml <= high_ml + 1e-9:
            return UnreachableTargetError(
                f"{what} target {wanted} ml is within the reachable range {low_ml:.3f}-{high_ml:.3f} ml on its own, "
                f"but contradicts the other targets{with_constraints}; drop or change one of them")
        return UnreachableTargetError(
            f"{what} target {wanted} ml is unreachable: pressures between 0 and [{limits}] kPa{with_constraints} "
            f"give {low_ml:.3f} to {high_ml:.3f} ml; ask for a volume in that range or raise {self.bound_to_raise}",
            gland_range_ml=(low_ml, high_ml) if row_name == "gland" else None)

    def _evaluate_raw_pressures(self, target: Target, raw_pa: Sequence[float], started: float) -> InverseResult:
        pressures_pa = _finite("pressures_pa", raw_pa)
        if pressures_pa.shape != (self.n_chambers,):
            raise PhantomError(f"pressures_pa needs {self.n_chambers} values, got {pressures_pa.size}")
        scene = getattr(self.model, "scene", None)  # a model built without a scene names its chambers by default
        labels = scene.chamber_labels if scene is not None else chamber_labels_of({}, [
            f"chamber{index}" for index in range(self.n_chambers)])
        refused = pressure_limit_error((pressures_pa / 1e3).tolist(), labels, (self.pressure_max_pa / 1e3).tolist())
        if refused:
            raise UnreachableTargetError(refused)
        chamber_volumes_m3, gland_volume_m3, _ = self.estimator.evaluate(pressures_pa)
        return InverseResult(target, pressures_pa, gland_volume_m3, chamber_volumes_m3, 0,
                             time.perf_counter() - started, 0.0, [])


@dataclass(frozen=True)
class PathAnswer:
    """The pressure that holds one chamber at a volume on its equilibrium path from rest (the others at zero gauge
    pressure): ``branch`` is "rising" before the chamber's pressure-volume peak, "falling" beyond it (where only a
    volume-controlled actuator holds it; under a pressure source it would burst through)."""

    chamber: int
    volume_m3: float
    pressure_pa: float
    branch: str
    chamber_volumes_m3: FloatArray
    gland_volume_m3: float


def pressure_on_path(model: PhantomModel, chamber: int, volume_m3: float,
                     pressure_max_pa: float | None = None) -> PathAnswer:
    """The pressure (Pa) in ``chamber`` that holds it at ``volume_m3`` on its equilibrium path from rest, the other
    chambers at zero: the path followed under volume control through the chamber's peak
    (:func:`phantom.model.fem.pathfollow.follow_volume`), so a volume beyond the peak, which no pressure reaches
    on the rising branch, is answered on the falling one, saying so.

    Raises UnreachableTargetError for a volume below the chamber's rest volume or one whose pressure exceeds
    ``pressure_max_pa`` (None: the scene's bound), SolveError where the path cannot be followed (an element
    would invert)."""
    from phantom.model.fem.pathfollow import follow_volume

    if not (isinstance(chamber, (int, np.integer)) and 0 <= chamber < model.n_chambers):
        raise PhantomError(f"chamber {chamber!r}: chambers are 0..{model.n_chambers - 1}")
    volume_m3 = float(_finite("volume_m3", volume_m3))
    rest_m3 = float(model.rest_chamber_volumes_m3[chamber])
    limit_pa = float(model.model_settings.pressure_max_pa if pressure_max_pa is None else pressure_max_pa)
    if volume_m3 < rest_m3:
        raise UnreachableTargetError(f"chamber {chamber}'s volume {volume_m3 * ML_PER_M3:.4g} ml lies below its rest "
                                     f"volume {rest_m3 * ML_PER_M3:.4g} ml: the blowers only inflate")
    unit_pa = np.zeros(model.n_chambers)
    unit_pa[chamber] = limit_pa
    [point] = follow_volume(model.problem(unit_pa), [volume_m3])
    pressure_pa = point.load_factor * limit_pa
    if pressure_pa > limit_pa * (1.0 + 1e-9):
        raise UnreachableTargetError(f"chamber {chamber} at {volume_m3 * ML_PER_M3:.4g} ml needs "
                                     f"{pressure_pa / 1e3:.4g} kPa, above the bound {limit_pa / 1e3:g} kPa; raise "
                                     "pressure_max or ask for a smaller volume")
    falling = point.load_factor_per_m3 is not None and point.load_factor_per_m3 < 0
    chamber_volumes_m3, gland_volume_m3 = model.volumes(point.positions_m)
    return PathAnswer(chamber, volume_m3, float(pressure_pa), "falling" if falling else "rising",
                      np.asarray(chamber_volumes_m3, dtype=float), float(gland_volume_m3))
