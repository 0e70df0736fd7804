"""The correction of the model by the measured volumes (:mod:`phantom.model.measurements` keeps them).

:func:`fit_correction` models the residual, the measured minus the model's gland volume, over the pressure box as
a Gaussian process (Kennedy and O'Hagan's calibration of a computer model): the calibrated model is the mean, and
the residual is a smooth function of the three pressures (a squared-exponential kernel with a length scale per
chamber, scikit-learn's ``GaussianProcessRegressor`` fitting its amplitude and length scales by marginal
likelihood within :data:`LENGTH_SCALE_BOUNDS_KPA` and :data:`AMPLITUDE_BOUNDS_ML`), plus at most a low-order
trend, each of the candidates of :data:`TRENDS`:

- ``gp``: no trend, the model's volume is the mean;
- ``gp+offset``: a constant (the rest volume's error: silicone, not air);
- ``gp+growth``: a constant plus a multiple of the model's growth above rest (what a refit of the modulus does
  to first order: the growth goes as 1/E).

A trend's coefficients are Gaussian with broad priors (:data:`TREND_PRIOR_SD`), so the candidates are Gaussian
processes whose leave-one-out errors have a closed form; the one with the least mean leave-one-out error (with a
single measurement: the greatest marginal likelihood) is used. Each measurement's noise is its method's
(:data:`NOISE_SD_PCT` for a scan, the scanner's error model in bench/README.md "Scanner"; :data:`NOISE_SD_ML` for
water displacement, the README's repeatability), plus a fitted white noise for what the measurements disagree by
beyond that, never less than what measurements at the same pressures disagree by (:func:`_replicate_noise_ml`:
below three measurements nothing else is fitted, and two scans of 35 and 39 ml at one state gave a band of +-0.06
ml there). The posterior mean passes within the noise of each measurement and, without a trend, returns to
the model away from them; its standard deviation gives a 95 % band at any pressures
(:meth:`CorrectedModel.gland_band_ml`). **The bound**: the correction is nowhere in the box larger than
:attr:`Correction.bound_pct` of the model's volume there, the largest measured miss plus twice that
measurement's noise, as a share of the model's volume at it (the mean is clipped to it: a trend fitted near rest
extrapolates at most in proportion to the volume, not as the old field's 24 ml over a 45 ml box). A fit of 200
measurements takes well under a second (bench/correction_fit.py).

:class:`CorrectedModel` applies it to a model's estimate and inverse. The module reads no scans (a scan's volume
comes from ``phantom.scan``, passed in by the command line or the daemon).
"""

from __future__ import annotations

import contextlib
import functools
import json
import math
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field, replace
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from phantom import written_atomically
from phantom.model.measurements import CorrectionError, Measurement, expectation, plausibility
from phantom.model.target import UnreachableTargetError

#: A measured pressure this close outside the model's box (kPa: two counts of the board's ADC, its settled band)
#: is on the box's edge: a chamber held at 3 kPa reads 3.01 on average, and its scan is a measurement at 3 kPa.
EDGE_SLACK_KPA = 0.1
#: A volume target this close outside the corrected model's range (ml: the corrected inverse's own tolerance) is
#: still searched for: the search meets it at the edge.
RANGE_SLACK_ML = 1e-3
#: The candidate trends beneath the Gaussian process, from the fewest parameters.
TRENDS = ("gp", "gp+offset", "gp+growth")
#: The prior standard deviations of the trends' coefficients: the offset (ml) and the growth's factor (a
#: modulus 2x off halves the growth): broad beside what a calibrated model misses by (0.1-2 ml, a few %).
TREND_PRIOR_SD = {"offset": 5.0, "growth": 0.5}
#: A scan's standard deviation (% of its volume): the verify plan's scans (then 60 pictures of 640x480) read -0.14 to
#: +0.18 % of the truth across the volumes (bench/README.md "Scanner" and "Characterisation").
NOISE_SD_PCT = {"scan": 0.12}
#: A water displacement's standard deviation (ml): two repeats within 0.3 ml of each other (README.md,
#: "Calibrating your phantom"), averaged.
NOISE_SD_ML = {"water_displacement": 0.1}
#: The bounds of the residual's length scales (kPa): from a tenth of the 0-3 kPa box (no wiggle between two
#: close scans) to far beyond it (a residual that is nearly linear).
LENGTH_SCALE_BOUNDS_KPA = (0.3, 3.0)
#: The bounds of the residual's standard deviation (ml) and of the white noise beyond the methods' (ml) the marginal
#: likelihood fits (what measurements at the same pressures disagree by is the white noise's floor, unbounded).
AMPLITUDE_BOUNDS_ML = (1e-3, 10.0)
WHITE_NOISE_BOUNDS_ML = (1e-4, 3.0)
#: The most measurements the kernel's hyperparameters are fitted to (evenly through the store; the posterior
#: takes them all): five hyperparameters are well set by 100 measurements, and the optimisation of the marginal
#: likelihood costs a factorisation of all of them at each step.
HYPERPARAMETER_MEASUREMENTS = 100
#: The band's width in standard deviations (95 %, two-sided).
BAND_Z = 1.959964
#: The longest length scale (kPa) the band assumes, whatever the fit's: fitted to clusters of scans (a verified
#: target's rounds), the marginal likelihood takes the residual as smooth over 1.6-2.6 kPa and the band was
#: narrow between the clusters, where the shipped simulated phantom (a table on a 1 kPa grid) kinks: after make
#: demo's scans alone, 7-12 of 40 verify="auto" targets had a band within 0.3 % and were 0.65-1.51 % off in true
#: volume. With the band's length scales at most 1 kPa (a third of the box) none was; after a characterisation of
#: 19 scans along the path 20-32 of 40 are still sure, at most 0.23 % off (bench/verify_rounds.py --auto; 0.5
#: kPa left none sure even then). The mean keeps the fitted scales.
BAND_LENGTH_SCALE_MAX_KPA = 1.0


def pressures_in_box(pressures_kpa: ArrayLike, top_kpa: float, what: str = "a measurement") -> np.ndarray:
    """Measured pressures (kPa) as a state of the box 0-``top_kpa``: those within EDGE_SLACK_KPA outside it are on
    its edge (clipped to it: a chamber held at the top reads a little over it, one vented a little under 0).

    Raises
    ------
    CorrectionError
        A pressure further outside, or not finite.
    """
    pressures = np.asarray(pressures_kpa, dtype=float)
    if not np.all(np.isfinite(pressures)) or np.any(pressures < -EDGE_SLACK_KPA) \
            or np.any(pressures > top_kpa + EDGE_SLACK_KPA):
        raise CorrectionError(f"{what} must lie on the grid, 0-{top_kpa:g} kPa, the model's pressure box "
                              f"({EDGE_SLACK_KPA:g} kPa outside it is on its edge), got "
                              f"{np.round(pressures, 4).tolist()}")
    clipped: np.ndarray = np.clip(pressures, 0.0, top_kpa)
    return clipped


@dataclass(frozen=True)
class ModelGrid:
    """A model's volumes (ml) on a grid of pressures (kPa, the same on every axis), the box the correction lives
    in, and its gland volume anywhere (``gland_ml(pressures_kpa)``: the model's own estimate, e.g. its
    VolumeEstimator)."""

    points_kpa: np.ndarray
    chamber_ml: np.ndarray     # (n, n, n, 3)
    gland_grid_ml: np.ndarray  # (n, n, n)
    gland_ml: Callable[[np.ndarray], float]
    description: str = ""
    _measured_ml: dict[tuple[float, ...], float] = field(default_factory=dict, compare=False, repr=False)

    def measured_states_ml(self, pressures_kpa: np.ndarray) -> np.ndarray:
        """The model's gland volume (ml) at each measured state (rows of kPa), each state's kept: a fitter that
        refits a store of 200 measurements after each new one evaluates the model once for the new one (an
        evaluation is 3-13 ms of the table's interpolant, most of a fit of 200 otherwise)."""
        volumes = []
        for row in np.asarray(pressures_kpa, dtype=float):
            key = tuple(float(p) for p in row)
            if key not in self._measured_ml:
                self._measured_ml[key] = float(self.gland_ml(row))
            volumes.append(self._measured_ml[key])
        return np.array(volumes)


# ----------------------------------------------------------------------------- the correction
def noise_sd_ml(measurement: Measurement) -> float:
    """A measurement's standard deviation (ml) by its method: :data:`NOISE_SD_ML`, else :data:`NOISE_SD_PCT` of
    its volume."""
    if measurement.method in NOISE_SD_ML:
        return NOISE_SD_ML[measurement.method]
    return NOISE_SD_PCT[measurement.method] / 100.0 * measurement.volume_ml


def _trend(kind: str, growth_ml: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A trend's columns at the model's growths (ml, (k,)) and its coefficients' prior variances."""
    growth = np.asarray(growth_ml, dtype=float).reshape(-1)
    if kind == "gp":
        return np.zeros((len(growth), 0)), np.zeros(0)
    if kind == "gp+offset":
        return np.ones((len(growth), 1)), np.array([TREND_PRIOR_SD["offset"] ** 2])
    return (np.column_stack([np.ones_like(growth), growth]),
            np.array([TREND_PRIOR_SD["offset"] ** 2, TREND_PRIOR_SD["growth"] ** 2]))


def _signal(first_kpa: np.ndarray, second_kpa: np.ndarray, amplitude_ml: float,
            length_scales_kpa: np.ndarray) -> np.ndarray:
    """The residual's squared-exponential covariance (ml^2) between two sets of pressures (kPa, (k, 3))."""
    scaled = (first_kpa[:, None, :] - second_kpa[None, :, :]) / length_scales_kpa
    return np.asarray(amplitude_ml ** 2 * np.exp(-0.5 * np.sum(scaled ** 2, axis=-1)))


@dataclass(frozen=True)
class _Posterior:
    """What a prediction needs of a fitted process: the pressures and trend columns measured, the Cholesky factor
    of the measurements' covariance and its solve against the residuals."""

    pressures_kpa: np.ndarray
    trend: np.ndarray
    prior: np.ndarray
    cholesky: np.ndarray
    weights: np.ndarray
    amplitude_ml: float
    length_scales_kpa: np.ndarray


def _posterior(kind: str, pressures_kpa: np.ndarray, growth_ml: np.ndarray, residual_ml: np.ndarray,
               noise_ml: np.ndarray, amplitude_ml: float, length_scales_kpa: np.ndarray) -> _Posterior:
    from scipy.linalg import cho_solve, cholesky

    trend, prior = _trend(kind, growth_ml)
    covariance = (_signal(pressures_kpa, pressures_kpa, amplitude_ml, length_scales_kpa)
                  + (trend * prior) @ trend.T + np.diag(noise_ml ** 2))
    factor = cholesky(covariance, lower=True)
    return _Posterior(pressures_kpa, trend, prior, factor, cho_solve((factor, True), residual_ml), amplitude_ml,
                      length_scales_kpa)


def _deviation_ml(posterior: _Posterior, pressures_kpa: np.ndarray, trend: np.ndarray,
                  prior: np.ndarray) -> np.ndarray:
    """The posterior standard deviation (ml) of the residual at pressures (kPa, (k, 3)), whose trend columns are
    ``trend`` with prior variances ``prior``, of a fitted process (``posterior``)."""
    from scipy.linalg import solve_triangular

    amplitude_ml = posterior.amplitude_ml
    cross = (_signal(pressures_kpa, posterior.pressures_kpa, amplitude_ml, posterior.length_scales_kpa)
             + (trend * prior) @ posterior.trend.T)
    projected = solve_triangular(posterior.cholesky, cross.T, lower=True)
    variance = amplitude_ml ** 2 + np.sum(trend ** 2 * prior, axis=1) - np.sum(projected ** 2, axis=0)
    deviation: np.ndarray = np.sqrt(np.clip(variance, 0.0, None))
    return deviation


@dataclass(frozen=True)
class Correction:
    """The residual over the pressures as a Gaussian process (see the module docstring).

    ``kind``: the trend beneath it (one of :data:`TRENDS`); ``count`` measurements at ``pressures_kpa``, where
    the model grew ``growth_ml`` above its rest and missed by ``residual_at_ml`` (measured minus model), each with
    its noise ``noise_ml`` (its method's and the fitted white noise, ml); the kernel's ``amplitude_ml`` and
    ``length_scales_kpa``; ``bound_pct``, the largest the correction is anywhere as a share of the model's volume
    there (the model's rest is ``rest_ml``); ``offset_ml`` and
    ``growth_factor``, the trend's coefficients (their posterior means); ``leave_one_out_pct``, each trend's mean
    leave-one-out error (% of the volume); ``uncorrected_pct``, the model's own mean error on the measurements."""

    kind: str
    count: int
    pressures_kpa: tuple[tuple[float, ...], ...] = ()
    growth_ml: tuple[float, ...] = ()
    residual_at_ml: tuple[float, ...] = ()
    noise_ml: tuple[float, ...] = ()
    amplitude_ml: float = AMPLITUDE_BOUNDS_ML[0]
    length_scales_kpa: tuple[float, ...] = ()
    white_noise_ml: float = 0.0
    bound_pct: float = 0.0
    rest_ml: float = 0.0
    offset_ml: float = 0.0
    growth_factor: float = 0.0
    leave_one_out_pct: dict[str, float] = field(default_factory=dict)
    uncorrected_pct: float = 0.0
    log_marginal_likelihood: float = 0.0

    @functools.cached_property
    def _fitted(self) -> _Posterior:
        return _posterior(self.kind, np.asarray(self.pressures_kpa, dtype=float), np.asarray(self.growth_ml),
                          np.asarray(self.residual_at_ml), np.asarray(self.noise_ml), self.amplitude_ml,
                          np.asarray(self.length_scales_kpa))

    @property
    def _band_length_scales_kpa(self) -> np.ndarray:
        scales_kpa: np.ndarray = np.minimum(np.asarray(self.length_scales_kpa, dtype=float),
                                            BAND_LENGTH_SCALE_MAX_KPA)
        return scales_kpa

    @functools.cached_property
    def _for_band(self) -> _Posterior:
        """The posterior the band's variance comes from: the fitted one, its length scales at most
        :data:`BAND_LENGTH_SCALE_MAX_KPA`."""
        if np.all(np.asarray(self.length_scales_kpa, dtype=float) <= BAND_LENGTH_SCALE_MAX_KPA):
            return self._fitted
        return _posterior(self.kind, np.asarray(self.pressures_kpa, dtype=float), np.asarray(self.growth_ml),
                          np.asarray(self.residual_at_ml), np.asarray(self.noise_ml), self.amplitude_ml,
                          self._band_length_scales_kpa)

    def band_ml(self, pressures_kpa: ArrayLike, model_growth_ml: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
        """The correction (ml, within +-``bound_pct`` of the model's volume) and its standard deviation (ml) at
        pressures (kPa, one row of one per chamber each, or one such row), where the model grew
        ``model_growth_ml`` above its rest."""
        pressures = np.atleast_2d(np.asarray(pressures_kpa, dtype=float))
        growth = np.asarray(model_growth_ml, dtype=float).reshape(-1)
        fitted = self._fitted
        trend, prior = _trend(self.kind, growth)
        cross = (_signal(pressures, fitted.pressures_kpa, self.amplitude_ml, np.asarray(self.length_scales_kpa))
                 + (trend * prior) @ fitted.trend.T)
        bound = self.bound_pct / 100.0 * np.abs(self.rest_ml + growth)
        mean = np.clip(cross @ fitted.weights, -bound, bound)
        # the band assumes the residual smooth over at most BAND_LENGTH_SCALE_MAX_KPA
        return mean, _deviation_ml(self._for_band, pressures, trend, prior)

    def deviation_with_amplitude_ml(self, pressures_kpa: ArrayLike, model_growth_ml: ArrayLike,
                                    amplitude_ml: float) -> np.ndarray:
        """The band's standard deviation (ml, as :meth:`band_ml`'s) of the process whose spread before any
        measurement is ``amplitude_ml`` instead of the fitted one: near the measurements their noise, away from
        them that amplitude."""
        pressures = np.atleast_2d(np.asarray(pressures_kpa, dtype=float))
        trend, prior = _trend(self.kind, np.asarray(model_growth_ml, dtype=float).reshape(-1))
        posterior = _posterior(self.kind, np.asarray(self.pressures_kpa, dtype=float), np.asarray(self.growth_ml),
                               np.asarray(self.residual_at_ml), np.asarray(self.noise_ml), amplitude_ml,
                               self._band_length_scales_kpa)
        return _deviation_ml(posterior, pressures, trend, prior)

    def residual_ml(self, pressures_kpa: ArrayLike, model_growth_ml: float) -> float:
        """What to add to the model's gland volume at these pressures (kPa), where the model grew
        ``model_growth_ml`` above its rest."""
        return float(self.band_ml(pressures_kpa, [model_growth_ml])[0][0])

    def size_ml(self, grid: ModelGrid) -> float:
        """The correction's largest magnitude over the grid's box (ml): how far the model was from the
        measurements anywhere (at most ``bound_pct`` of the model's largest volume)."""
        n = len(grid.points_kpa)
        pressures = np.array([grid.points_kpa[list(index)] for index in np.ndindex(n, n, n)])
        growth = np.asarray(grid.gland_grid_ml, dtype=float).reshape(-1) - float(grid.gland_grid_ml[0, 0, 0])
        return float(np.max(np.abs(self.band_ml(pressures, growth)[0])))

    def hyperparameters(self) -> str:
        """The kernel's and the trend's fitted values in words, for reports."""
        scales = ", ".join(f"{scale:.3g}" for scale in self.length_scales_kpa)
        trend = {"gp": "no trend", "gp+offset": f"offset {self.offset_ml:+.3f} ml",
                 "gp+growth": f"offset {self.offset_ml:+.3f} ml, growth x {1 + self.growth_factor:.4f}"}[self.kind]
        return (f"amplitude {self.amplitude_ml:.3g} ml, length scales {scales} kPa, white noise "
                f"{self.white_noise_ml:.3g} ml, {trend}; bound {self.bound_pct:.3f} % of the model's volume")

    def to_json(self) -> dict[str, Any]:
        """For the daemon's status and the report: the kind, from how many measurements, the hyperparameters, the
        bound, the leave-one-out."""
        return {"kind": self.kind, "measurements": self.count, "offset_ml": self.offset_ml,
                "growth_factor": self.growth_factor, "amplitude_ml": self.amplitude_ml,
                "length_scales_kpa": list(self.length_scales_kpa), "white_noise_ml": self.white_noise_ml,
                "bound_pct": self.bound_pct, "leave_one_out_pct": dict(self.leave_one_out_pct),
                "uncorrected_pct": self.uncorrected_pct}

    def to_document(self) -> dict[str, Any]:
        """Everything the correction is, as JSON (:meth:`from_document` reads it)."""
        document: dict[str, Any] = json.loads(json.dumps(asdict(self)))
        return document

    @classmethod
    def from_document(cls, document: dict[str, Any]) -> Correction:
        """The correction :meth:`to_document` wrote."""
        return cls(**{**document, "pressures_kpa": tuple(tuple(float(p) for p in row)
                                                         for row in document["pressures_kpa"]),
                      **{name: tuple(float(v) for v in document[name])
                         for name in ("growth_ml", "residual_at_ml", "noise_ml", "length_scales_kpa")}})

    def summary(self, grid: ModelGrid) -> dict[str, Any]:
        """:meth:`to_json` with the correction's size over the grid's box (``size_ml``, :meth:`size_ml`) and the
        number of measurements (``count``): what the daemon reports of the correction in force."""
        return self.to_json() | {"size_ml": self.size_ml(grid), "count": self.count}


def _hyperparameters(pressures_kpa: np.ndarray, residual_ml: np.ndarray, noise_ml: np.ndarray,
                     optimise: bool) -> tuple[float, np.ndarray, float]:
    """The residual's amplitude (ml), length scales (kPa) and white noise (ml) by scikit-learn's
    GaussianProcessRegressor (the marginal likelihood, bounded); with ``optimise`` False, its starting values."""
    import warnings

    from sklearn.exceptions import ConvergenceWarning
    from sklearn.gaussian_process import GaussianProcessRegressor
    from sklearn.gaussian_process.kernels import RBF, ConstantKernel, WhiteKernel

    chambers = pressures_kpa.shape[1]
    # the residual's root mean square (its size about the zero mean), not its spread: two scans that agree on a
    # residual of 0.5 ml are a residual of 0.5 ml, not one of their 0.02 ml difference (a start that near the
    # bound left two scans' residual unrepresented, and the next round 0.8 % off near rest)
    amplitude = float(np.clip(np.sqrt(np.mean(residual_ml ** 2)), *AMPLITUDE_BOUNDS_ML))
    kernel = (ConstantKernel(amplitude ** 2, tuple(b ** 2 for b in AMPLITUDE_BOUNDS_ML))
              * RBF(np.full(chambers, 1.5), LENGTH_SCALE_BOUNDS_KPA)
              # started at the methods' own noise, not at its bound: there its gradient in log space vanishes
              + WhiteKernel(float(np.clip(np.median(noise_ml), *WHITE_NOISE_BOUNDS_ML)) ** 2,
                            tuple(b ** 2 for b in WHITE_NOISE_BOUNDS_ML)))
    process = GaussianProcessRegressor(kernel, alpha=noise_ml ** 2, optimizer="fmin_l_bfgs_b" if optimise else None,
                                       normalize_y=False)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ConvergenceWarning)  # a bound reached is a bound kept
        process.fit(pressures_kpa, residual_ml)
    fitted = process.kernel_
    white = math.sqrt(fitted.k2.noise_level) if optimise else WHITE_NOISE_BOUNDS_ML[0]  # unfitted: the methods'
    return math.sqrt(fitted.k1.k1.constant_value), np.atleast_1d(fitted.k1.k2.length_scale).astype(float), white


def _replicate_noise_ml(pressures_kpa: np.ndarray, residual_ml: np.ndarray, method_noise_ml: np.ndarray) -> float:
    """The white noise (ml) that measurements at the same pressures (rows of kPa, equal to the last digit) say there
    is beyond their methods' own: the pooled standard deviation of their residuals (ml) about each state's mean,
    less the methods' share; 0 where no state is measured twice or the methods' noise explains the spread. It is
    what the data say, not bounded by WHITE_NOISE_BOUNDS_ML: the process cannot bend between equal pressures, so
    only the white noise can hold a disagreement there, however large."""
    _, state, counts = np.unique(pressures_kpa, axis=0, return_inverse=True, return_counts=True)
    state = state.reshape(-1)
    replicated = counts[state] > 1
    if not np.any(replicated):
        return 0.0
    means_ml = np.bincount(state, residual_ml) / counts
    spread_ml2 = float(np.sum((residual_ml - means_ml[state]) ** 2)) / float(np.sum(counts[counts > 1] - 1))
    return math.sqrt(max(0.0, spread_ml2 - float(np.mean(method_noise_ml[replicated] ** 2))))


def fit_correction(measurements: Sequence[Measurement], grid: ModelGrid,
                   kinds: Sequence[str] = TRENDS) -> Correction:
    """The correction of the model (``grid``) by the measurements: of the trends ``kinds``, the one with the least
    mean leave-one-out error (one measurement: the greatest marginal likelihood), see the module docstring.
    CorrectionError when there are no measurements, a trend is unknown, or a pressure is off the model's box."""
    from threadpoolctl import threadpool_limits

    # one BLAS thread: the matrices are at most a few hundred wide, and on a busy two-core machine BLAS's threads
    # made a fit of 200 measurements 30 times slower (4 s against 0.12 s for one kernel's fit)
    with threadpool_limits(1):
        return _fit_correction(measurements, grid, kinds)


def _fit_correction(measurements: Sequence[Measurement], grid: ModelGrid, kinds: Sequence[str]) -> Correction:
    from scipy.linalg import cho_solve

    if not measurements:
        raise CorrectionError("no measurements to correct the model with: scan the phantom first")
    unknown = sorted(set(kinds) - set(TRENDS))
    if unknown or not kinds:
        raise CorrectionError(f"unknown correction kinds {unknown}: choose from {', '.join(TRENDS)}")
    pressures = np.array([m.pressures_kpa for m in measurements], dtype=float)
    chambers = grid.chamber_ml.shape[-1]
    if pressures.shape[1] != chambers:
        raise CorrectionError(f"the measurements have {pressures.shape[1]} pressures, the model "
                              f"{chambers} chambers: they are of another phantom")
    pressures = pressures_in_box(pressures, float(grid.points_kpa[-1]), f"{len(measurements)} measurements")
    volumes = np.array([m.volume_ml for m in measurements], dtype=float)
    model_ml = grid.measured_states_ml(pressures)
    rest_ml = grid.gland_ml(np.zeros(chambers))
    growth = model_ml - rest_ml
    residual = volumes - model_ml
    method_noise = np.array([noise_sd_ml(m) for m in measurements])
    count = len(volumes)
    bound_pct = float(np.max((np.abs(residual) + 2.0 * method_noise) / model_ml) * 100.0)
    replicate_noise = _replicate_noise_ml(pressures, residual, method_noise)
    fits: dict[str, Correction] = {}
    leave_one_out: dict[str, float] = {}
    likelihoods: dict[str, float] = {}
    for kind in kinds:
        trend, prior = _trend(kind, growth)
        detrended = residual
        if trend.shape[1]:  # the kernel's hyperparameters are fitted to what the trend leaves (weighted)
            coefficients, *_ = np.linalg.lstsq(trend / method_noise[:, None], residual / method_noise, rcond=None)
            detrended = residual - trend @ coefficients
        # the kernel's five hyperparameters from at most HYPERPARAMETER_MEASUREMENTS of them, evenly through the
        # store: its marginal likelihood's optimisation is most of a fit (each step a factorisation of them all)
        subset = np.unique(np.linspace(0, count - 1, min(count, HYPERPARAMETER_MEASUREMENTS)).round().astype(int))
        amplitude, scales, white = _hyperparameters(pressures[subset], detrended[subset], method_noise[subset],
                                                    optimise=count >= 3)
        white = max(white, replicate_noise)  # what repeated states disagree by is noise, fitted or not
        noise = np.sqrt(method_noise ** 2 + white ** 2)
        posterior = _posterior(kind, pressures, growth, residual, noise, amplitude, scales)
        inverse_diagonal = np.diag(cho_solve((posterior.cholesky, True), np.eye(count)))
        leave_one_out[kind] = float(np.mean(np.abs(posterior.weights / inverse_diagonal) / volumes * 100))
        likelihoods[kind] = float(-0.5 * residual @ posterior.weights - np.sum(np.log(np.diag(posterior.cholesky)))
                                  - 0.5 * count * math.log(2 * math.pi))
        coefficients = prior * (trend.T @ posterior.weights)
        fits[kind] = Correction(kind, count, tuple(tuple(float(p) for p in row) for row in pressures),
                                tuple(growth.tolist()), tuple(residual.tolist()), tuple(noise.tolist()), amplitude,
                                tuple(scales.tolist()), white, bound_pct, rest_ml,
                                float(coefficients[0]) if len(coefficients) else 0.0,
                                float(coefficients[1]) if len(coefficients) > 1 else 0.0,
                                log_marginal_likelihood=likelihoods[kind])
    best = (min(leave_one_out, key=leave_one_out.__getitem__) if count >= 2
            else max(likelihoods, key=likelihoods.__getitem__))
    uncorrected = float(np.mean(np.abs(residual) / volumes * 100))
    return replace(fits[best], leave_one_out_pct=leave_one_out if count >= 2 else {}, uncorrected_pct=uncorrected)


#: Bumped when what a cached fit holds, or how a fit is made, changes.
FIT_CACHE_VERSION = 5


def cached_fit(measurements: Sequence[Measurement], grid: ModelGrid) -> Correction:
    """:func:`fit_correction`, kept in the cache folder ``corrections`` keyed by the measurements and the model's
    grid (its volumes), so that a daemon started again with many stored measurements does not fit them again
    (the fit is under a second; read back, a few ms). A cached file that cannot be read is fitted again."""
    import hashlib

    from phantom import cache_dir

    digest = hashlib.sha256(json.dumps({"version": FIT_CACHE_VERSION, "trends": TRENDS, "prior": TREND_PRIOR_SD,
                                        "noise": [NOISE_SD_PCT, NOISE_SD_ML],
                                        "bounds": [LENGTH_SCALE_BOUNDS_KPA, AMPLITUDE_BOUNDS_ML,
                                                   WHITE_NOISE_BOUNDS_ML, HYPERPARAMETER_MEASUREMENTS],
                                        "measurements": [asdict(m) for m in measurements]},
                                       sort_keys=True).encode())
    for array in (grid.points_kpa, grid.chamber_ml, grid.gland_grid_ml):
        digest.update(np.ascontiguousarray(array, dtype=float).tobytes())
    path = cache_dir("corrections") / f"{digest.hexdigest()[:24]}.json"
    with contextlib.suppress(OSError, ValueError, KeyError, TypeError):
        return Correction.from_document(json.loads(path.read_text()))
    correction = fit_correction(measurements, grid)
    with contextlib.suppress(CorrectionError, OSError), written_atomically(path, CorrectionError) as temporary:
        temporary.write_text(json.dumps(correction.to_document()))
    return correction


#: Asked volumes this close (ml) on either side of a target the corrected volume does not meet between them: a
#: jump along the inverse's path (:meth:`CorrectedModel.pressures_for_ml`).
JUMP_ML = 1e-4
#: The corrected volume's slope in the asked one (ml per ml) that a correction, smooth and small beside the
#: growth, keeps within: the secant steps' bounds; a bracket steeper than the upper one holds a jump.
SLOPE_BOUNDS = (0.2, 5.0)


class CorrectedModel:
    """A model's gland volume and inverse with a correction applied (the daemon's model can wrap its own).

    ``grid.gland_ml`` is the model's estimate; ``pressures_for_ml`` wraps any inverse (``inverse(volume_ml)`` ->
    pressures in kPa) by asking it for another volume, moved by secant steps, until the corrected volume at its
    answer meets the target: the correction is smooth and small beside the growth, so this converges in a few
    rounds."""

    def __init__(self, grid: ModelGrid, correction: Correction):
        self.grid = grid
        self.correction = correction
        chambers = grid.chamber_ml.shape[-1]
        self.rest_ml = grid.gland_ml(np.zeros(chambers))
        #: the model's largest volume in the box: with the rest, the range the inverse is asked within
        self.top_ml = grid.gland_ml(np.full(chambers, float(grid.points_kpa[-1])))
        #: the corrected volumes at rest and at the box's top: the range of volume targets with the correction
        self.range_ml = (self.corrected_ml(np.zeros(chambers), self.rest_ml),
                         self.corrected_ml(np.full(chambers, float(grid.points_kpa[-1])), self.top_ml))

    def describe(self) -> str:
        """The correction in words, for messages: its kind and from how many measurements."""
        return f"{self.correction.kind} from {self.correction.count} measurement(s)"

    def gland_ml(self, pressures_kpa: ArrayLike) -> float:
        """The corrected gland volume (ml) at these pressures (kPa)."""
        pressures = np.asarray(pressures_kpa, dtype=float)
        return self.corrected_ml(pressures, self.grid.gland_ml(pressures))

    def gland_band_ml(self, pressures_kpa: ArrayLike) -> tuple[float, float]:
        """The corrected gland volume (ml) at these pressures (kPa) and the half-width (ml) of its 95 % band: where
        the correction knows the phantom (measured nearby), narrow; away from the measurements, as wide as the
        residual's own spread."""
        pressures = np.asarray(pressures_kpa, dtype=float)
        model_ml = self.grid.gland_ml(pressures)
        mean, deviation = self.correction.band_ml(pressures, [model_ml - self.rest_ml])
        return float(model_ml + mean[0]), float(BAND_Z * deviation[0])

    def judging_band_ml(self, pressures_kpa: ArrayLike, model_half_width_ml: float) -> tuple[float, float]:
        """:meth:`gland_band_ml` for judging a new measurement: the band of the process whose spread before any
        measurement is at least the model's own known error (``model_half_width_ml``, 95 %), so that away from
        the measurements the half-width is that error, not the fitted amplitude, which only says how much the
        residual varied where it was measured: a phantom measured only near rest is not thought known at 3 kPa
        (:meth:`Correction.deviation_with_amplitude_ml`)."""
        pressures = np.asarray(pressures_kpa, dtype=float)
        model_ml = self.grid.gland_ml(pressures)
        growth = [model_ml - self.rest_ml]
        mean, deviation = self.correction.band_ml(pressures, growth)
        prior_sd_ml = model_half_width_ml / BAND_Z
        if prior_sd_ml > self.correction.amplitude_ml:
            deviation = self.correction.deviation_with_amplitude_ml(pressures, growth, prior_sd_ml)
        return float(model_ml + mean[0]), float(BAND_Z * deviation[0])

    def corrected_ml(self, pressures_kpa: ArrayLike, model_ml: float) -> float:
        """The corrected gland volume (ml) at these pressures (kPa), where the model's own is ``model_ml`` (a caller
        that has it already spares the model a second evaluation)."""
        return float(model_ml) + self.correction.residual_ml(pressures_kpa, float(model_ml) - self.rest_ml)

    def pressures_for_ml(self, volume_ml: float, inverse: Callable[[float], np.ndarray],
                         tolerance_ml: float = 1e-3, max_rounds: int = 30) -> tuple[np.ndarray, float, int]:
        """Pressures (kPa) whose corrected gland volume is ``volume_ml``, that volume, and the inverse's rounds.

        Raises
        ------
        UnreachableTargetError
            ``volume_ml`` beyond the corrected range (:attr:`range_ml`, stated as "give LOW to HIGH ml" and held as
            its ``gland_range_ml``, whose edge the daemon's verify loop asks), though perhaps inside the model's
            own: one scan near rest corrects by an offset the phantom at rest does not hold, and searched for, such
            a target met nothing.
        CorrectionError
            The search did not converge (the corrected volume too steep there: the edge of the reachable range).
        """
        low_ml, high_ml = self.range_ml
        if not low_ml - RANGE_SLACK_ML <= volume_ml <= high_ml + RANGE_SLACK_ML:
            raise UnreachableTargetError(f"{volume_ml:.2f} ml is beyond the model's range with the correction in force "
                                         f"({self.describe()}): give {low_ml:.3f} to {high_ml:.3f} ml",
                                         gland_range_ml=(low_ml, high_ml), corrected=True)
        # within the model's range from the first ask: the corrected range may reach past the model's
        asked = float(np.clip(volume_ml, self.rest_ml, self.top_ml))
        previous: tuple[float, float] | None = None
        # once the target is bracketed, the asked volumes below and above it with their misses (ml), and which end
        # was replaced last: regula falsi, Illinois (an end kept twice counts its miss half), since the inverse's
        # path has kinks (one chamber's pressure turning) where secant steps from one side crawl
        ends: dict[str, tuple[float, float, np.ndarray]] = {}
        replaced, halved = "", {"below": 1.0, "above": 1.0}
        for rounds in range(1, max_rounds + 1):
            pressures = np.asarray(inverse(asked), dtype=float)
            corrected = self.gland_ml(pressures)
            miss = corrected - volume_ml
            if abs(miss) <= tolerance_ml:
                return pressures, corrected, rounds
            side = "below" if miss < 0 else "above"
            ends[side] = (asked, miss, pressures)
            halved[side] = 1.0
            if len(ends) == 2:
                other = "above" if side == "below" else "below"
                if side == replaced:
                    halved[other] /= 2
                replaced = side
                (low, low_miss, _), (high, high_miss, _) = ends["below"], ends["above"]
                if abs(high - low) <= JUMP_ML:
                    # the target lies in a jump of the corrected volume along the inverse's path (the inverse
                    # turns to another branch there, and the correction differs between the two): the nearer end
                    _, miss, pressures = min(ends.values(), key=lambda end: abs(end[1]))
                    return pressures, volume_ml + miss, rounds
                if (high_miss - low_miss) / (high - low) > SLOPE_BOUNDS[1]:
                    # steeper than a correction makes it: a jump inside, where false position crawls from the
                    # side whose miss is the smaller (a target a hair beyond a jump's low side took 30 rounds)
                    asked = 0.5 * (low + high)
                    continue
                low_miss, high_miss = low_miss * halved["below"], high_miss * halved["above"]
                asked = low - low_miss * (high - low) / (high_miss - low_miss)
                continue
            # secant steps: the corrected volume's slope in the asked one (1 at first: a constant correction)
            slope = 1.0
            if previous is not None and previous[0] != asked:
                slope = float(np.clip((corrected - previous[1]) / (asked - previous[0]), *SLOPE_BOUNDS))
            previous = (asked, corrected)
            # within the model's range: near rest or the top a step may overshoot it (a phantom that grows faster
            # than the model at first asked the model for less than its rest)
            asked = float(np.clip(asked - miss / slope, self.rest_ml, self.top_ml))
        raise CorrectionError(f"the corrected inverse did not meet {volume_ml:g} ml in {max_rounds} rounds (last "
                              f"{corrected:.3f} ml): the corrected volume is too steep there (the edge of what the "
                              "phantom reaches?); ask a volume a little further inside the range")


def model_grid(estimator: Any, description: str = "") -> ModelGrid:
    """A model's grid from its estimator (``phantom.model.fidelity.levels.VolumeEstimator``): the grid of its
    response table (the table level's own, else the model's table, built and cached on first use), and the
    estimator's gland volume anywhere."""
    from phantom.model.fidelity.response_table import grid_pa, response_table

    table = estimator.table if estimator.table is not None else response_table(estimator.model,
                                                                               estimator.pressure_max_pa)
    points_kpa = grid_pa(table.pressure_max_pa, table.gland_values.shape[0]) / 1e3

    def gland_ml(pressures_kpa: np.ndarray) -> float:
        return float(estimator.volumes(np.asarray(pressures_kpa, dtype=float) * 1e3)[1] * 1e6)

    return ModelGrid(points_kpa, 1e6 * np.asarray(table.chamber_values), 1e6 * np.asarray(table.gland_values),
                     gland_ml, description)


def judged(measurement: Measurement, grid: Any, confirmed: list[Measurement], model_name: str = "the model",
           fit: Callable[[Sequence[Measurement], Any], Correction] = cached_fit) -> Measurement:
    """``measurement`` with its status: ``unconfirmed`` with the reason when it is implausible against the model
    (``grid``: a :class:`ModelGrid`) corrected by the ``confirmed`` measurements already stored
    (:func:`phantom.model.measurements.expectation`; their ``fit`` is the cached one, the daemon's when it fitted
    them already); a fit that fails leaves the model's own expectation."""
    pressures = np.clip(np.asarray(measurement.pressures_kpa, dtype=float), 0.0, float(grid.points_kpa[-1]))
    corrected = None
    if confirmed:
        try:
            corrected = CorrectedModel(grid, fit(confirmed, grid))
        except (CorrectionError, ValueError, ArithmeticError):
            corrected = None
    expected, half_width, basis = expectation(pressures, grid.gland_ml(pressures), corrected, model_name)
    verdict = plausibility(measurement.volume_ml, expected, half_width, basis)
    if verdict.plausible:
        return measurement
    return replace(measurement, status="unconfirmed", reason=verdict.reason)
