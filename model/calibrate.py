"""Calibration of the material to measured gland volumes, with leave-one-out cross-validation.

The model scales exactly with Young's modulus ``E`` (the fixation springs are a multiple of it), so the gland
volume at pressures ``p`` and modulus ``E`` is the one at ``p E_0 / E`` and the scene's modulus ``E_0``:

    g(p; E) = g(t p; E_0),   t = E_0 / E

For each measured pressure combination ``p_j`` the response along its ray, ``G_j(t) = g(t p_j; E_0)``, is
computed once by continuation (warm-started full solves on a grid of ``t``, up to where the predicted growth
overshoots the measured one) and interpolated (monotone cubic).
The fit and every leave-one-out refit are then one-dimensional least-squares problems over ``t`` on those
curves, with relative residuals ``(G_j(t) - m_j) / m_j`` (the error measure reported):

    t* = argmin_t  sum_j ((G_j(t) - m_j) / m_j)^2,    E = E_0 / t*

The errors reported are the mean of ``|m_j - predicted_j| / m_j`` in percent, over the fit (all points) and
leave-one-out (each point predicted by the fit to the others, E refitted without it). Both material
formulations are fitted (co-rotational, and small-strain linear whose displacement is exactly proportional to
``t``); the one with the lower leave-one-out error is kept, and the scene written with it.
"""

from __future__ import annotations

import csv
import sys
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from phantom import PhantomError

#: A ray's continuation stops once its gland growth exceeds this multiple of the measured growth.
OVERSHOOT = 1.6
#: Continuation steps per linear-estimate load factor (the rest-compliance fit's t).
STEPS_PER_LINEAR_LOAD_FACTOR = 40
#: The search for t stops at this multiple of the linear estimate.
MAX_LINEAR_MULTIPLE = 4.0
#: Formulations fitted; the one with the lowest leave-one-out error is kept.
FORMULATIONS = ("corotational", "linear")


class CalibrationError(PhantomError):
    """Bad measurement file, or a calibration the data cannot support."""


@dataclass(frozen=True)
class Measurements:
    """Measured gland volumes (m^3) at chamber pressures (Pa), one row per experiment."""

    pressures_pa: np.ndarray       # (k, n_chambers)
    volumes_m3: np.ndarray         # (k,)
    path: str = ""


def load_measurements(path, n_chambers: int | None = None) -> Measurements:
    """Read a CSV with columns ``p0_kpa, p1_kpa, ..., measured_ml`` (``#`` lines are comments).

    A ``measured_ml`` entry may instead name a scan file (.obj, .ply or .stl, in mm, relative to the CSV's
    folder): its cleaned, watertight volume is used (``phantom.model.scan.scan_volume_ml``).

    Raises
    ------
    CalibrationError
        Missing file or columns, non-numeric, non-finite or negative values, a chamber count that does not
        match the model, or fewer than three rows.
    """
    path = Path(path)
    if not path.is_file():
        raise CalibrationError(f"the measurement file {path} does not exist: check the path")
    lines = [line for line in path.read_text().splitlines() if line.strip() and not line.lstrip().startswith("#")]
    if not lines:
        raise CalibrationError(f"{path} holds no data: expected a header p0_kpa,p1_kpa,...,measured_ml and rows")
    reader = csv.DictReader(lines)
    header = [name.strip() for name in reader.fieldnames or []]
    pressure_columns = sorted((name for name in header if name.startswith("p") and name.endswith("_kpa")),
                              key=lambda name: int(name[1:-4]) if name[1:-4].isdigit() else 10**6)
    if "measured_ml" not in header or not pressure_columns:
        raise CalibrationError(f"{path} needs columns p0_kpa, p1_kpa, ... and measured_ml; it has {header}")
    expected = [f"p{index}_kpa" for index in range(len(pressure_columns))]
    if pressure_columns != expected:
        raise CalibrationError(f"{path}: pressure columns must be {expected}, got {pressure_columns}")
    if n_chambers is not None and len(pressure_columns) != n_chambers:
        raise CalibrationError(f"{path} has {len(pressure_columns)} pressure columns but the model has "
                               f"{n_chambers} chambers")
    pressures_kpa, volumes_ml = [], []
    for line_number, row in enumerate(reader, start=2):
        row = {key.strip(): value for key, value in row.items() if key is not None}
        try:
            pressures_kpa.append([float(row[name]) for name in pressure_columns])
            volumes_ml.append(_measured_volume_ml(row["measured_ml"], path.parent))
        except (TypeError, ValueError) as error:
            raise CalibrationError(f"{path}, data row {line_number - 1}: not a number ({error})") from None
    pressures_kpa, volumes_ml = np.array(pressures_kpa), np.array(volumes_ml)
    if not (np.all(np.isfinite(pressures_kpa)) and np.all(np.isfinite(volumes_ml))):
        raise CalibrationError(f"{path} holds non-finite values (nan or inf): fix the measurements")
    if np.any(pressures_kpa < 0):
        raise CalibrationError(f"{path} holds negative pressures: the blowers only push, gauge pressures are >= 0")
    if np.any(volumes_ml <= 0):
        raise CalibrationError(f"{path} holds volumes <= 0 ml: fix the measurements")
    if len(volumes_ml) < 3:
        raise CalibrationError(f"{path} has {len(volumes_ml)} rows: a fit with leave-one-out needs at least 3")
    return Measurements(pressures_kpa * 1e3, volumes_ml * 1e-6, str(path))


def _measured_volume_ml(entry: str, folder: Path) -> float:
    """A ``measured_ml`` entry: a number, or a scan file whose volume is measured."""
    text = (entry or "").strip()
    if Path(text).suffix.lower() not in (".obj", ".ply", ".stl"):
        return float(text)
    from phantom.model.scan import scan_volume_ml

    return scan_volume_ml(folder / text)


def relative_abs_errors_pct(predicted_m3: np.ndarray, measured_m3: np.ndarray) -> np.ndarray:
    """``|measured - predicted| / measured`` in percent, per point."""
    return np.abs(np.asarray(measured_m3) - np.asarray(predicted_m3)) / np.asarray(measured_m3) * 100


@dataclass
class RayResponses:
    """Gland volume (m^3) along each measurement's pressure ray, ``G_j(t) = g(t p_j)``, at the scene's modulus.

    ``load_factors`` is the grid of ``t`` solved; ``volumes_m3`` has shape (rays, len(load_factors)), NaN where
    not solved; ``ray_limits`` the largest ``t`` solved on each ray, ``max_load_factor`` their minimum.
    """

    load_factors: np.ndarray
    volumes_m3: np.ndarray
    max_load_factor: float
    ray_limits: np.ndarray
    interpolants: list = field(default_factory=list)

    def __post_init__(self):
        from scipy.interpolate import PchipInterpolator

        self.interpolants = []
        for volumes in self.volumes_m3:
            valid = np.isfinite(volumes)
            if valid.sum() < 2 or np.ptp(volumes[valid]) == 0:
                constant = float(volumes[valid][0])
                self.interpolants.append(lambda t, constant=constant: np.full(np.shape(t), constant))
            else:
                self.interpolants.append(PchipInterpolator(self.load_factors[valid], volumes[valid],
                                                           extrapolate=False))

    def predict(self, load_factor: float, rays=None) -> np.ndarray:
        """Gland volumes (m^3) of the chosen rays at one load factor ``t = E_0 / E``."""
        rays = range(len(self.interpolants)) if rays is None else rays
        return np.array([float(self.interpolants[ray](load_factor)) for ray in rays])


def ray_responses(model, pressures_pa: np.ndarray, measured_m3: np.ndarray, load_factor_step: float,
                  max_load_factor: float, formulation: str = "corotational", overshoot: float | None = None,
                  progress=None) -> RayResponses:
    """The gland volume along each ray ``t p_j``, on the grid ``t = 0, step, 2 step, ... max_load_factor``.

    Co-rotational: continuation, each solve warm-started from the previous one. A ray stops once its gland
    growth exceeds ``overshoot`` times the measured growth (no fit lies beyond: this keeps the solves away from
    the limit point, where the response runs away) or at its first failed solve (``SolveError``: the limit
    point). The usable range of ``t`` is where every ray was solved. Linear: one solve per ray, since the
    displacement is ``t u(p_j)``; the volume of the displaced surface is then evaluated on the grid.
    """
    from phantom.model import SolveError

    overshoot = OVERSHOOT if overshoot is None else overshoot
    load_factors = np.arange(0.0, max_load_factor + 0.5 * load_factor_step, load_factor_step)
    volumes = np.full((len(pressures_pa), len(load_factors)), np.nan)
    volumes[:, 0] = model.rest_gland_volume_m3
    ray_limits = np.full(len(pressures_pa), float(load_factors[-1]))
    steps_per_ray = len(load_factors) - 1
    for ray, pressures in enumerate(pressures_pa):
        if progress is not None:
            progress(ray * steps_per_ray, len(pressures_pa) * steps_per_ray)
        if not np.any(pressures):
            volumes[ray, :] = model.rest_gland_volume_m3
            continue
        if formulation == "linear":
            displacement_m = model.solve(pressures, formulation="linear").positions_m - model.nodes_m
            volumes[ray] = [model.volumes(model.nodes_m + factor * displacement_m)[1] for factor in load_factors]
            continue
        wanted_growth_m3 = overshoot * max(measured_m3[ray] - model.rest_gland_volume_m3, 0.0)
        positions_m = None
        for column in range(1, len(load_factors)):
            try:
                state = model.solve(load_factors[column] * pressures, formulation=formulation,
                                    initial_positions_m=positions_m)
            except SolveError:
                ray_limits[ray] = float(load_factors[column - 1])
                break
            positions_m = state.positions_m
            volumes[ray, column] = state.gland_volume_m3
            if progress is not None:
                progress(ray * steps_per_ray + column, len(pressures_pa) * steps_per_ray)
            if state.gland_volume_m3 - model.rest_gland_volume_m3 > wanted_growth_m3:
                ray_limits[ray] = float(load_factors[column])
                break
    if progress is not None:
        progress(len(pressures_pa) * steps_per_ray, len(pressures_pa) * steps_per_ray)
    reached = float(ray_limits.min())
    if reached <= 0:
        raise CalibrationError("the model fails at the smallest load factor of the calibration: the scene's "
                               "modulus is far too soft for these pressures; raise youngs_modulus_kpa")
    return RayResponses(load_factors, volumes, reached, ray_limits)


def fit_load_factor(responses: RayResponses, measured_m3: np.ndarray, rays) -> float:
    """The ``t`` in (0, max_load_factor] minimising the relative squared residuals of ``rays``."""
    from scipy.optimize import minimize_scalar

    rays = list(rays)
    measured = measured_m3[rays]

    def cost(load_factor: float) -> float:
        residual = (responses.predict(load_factor, rays) - measured) / measured
        return float(residual @ residual) if np.all(np.isfinite(residual)) else np.inf

    grid = np.linspace(0.0, responses.max_load_factor, 400)[1:]
    costs = np.array([cost(value) for value in grid])
    best = int(np.argmin(costs))
    low, high = grid[max(best - 1, 0)], grid[min(best + 1, len(grid) - 1)]
    refined = minimize_scalar(cost, bounds=(low, high), method="bounded", options={"xatol": 1e-10})
    return float(refined.x) if refined.fun <= costs[best] else float(grid[best])


@dataclass
class FormulationFit:
    """Young's modulus (Pa) fitted for one formulation, with its fit and leave-one-out errors (%)."""

    formulation: str
    youngs_modulus_pa: float
    fit_mean_abs_pct_error: float
    loo_mean_abs_pct_error: float
    fit_predicted_m3: np.ndarray
    loo_predicted_m3: np.ndarray
    loo_youngs_modulus_pa: np.ndarray
    at_search_limit: bool
    ray_limit_youngs_modulus_pa: np.ndarray

    def as_json(self) -> dict:
        """kPa, ml, %."""
        return {
            "youngs_modulus_kpa": self.youngs_modulus_pa / 1e3,
            "fit_mean_abs_pct_error": self.fit_mean_abs_pct_error,
            "loo_mean_abs_pct_error": self.loo_mean_abs_pct_error,
            "fit_predicted_ml": (self.fit_predicted_m3 * 1e6).tolist(),
            "loo_predicted_ml": (self.loo_predicted_m3 * 1e6).tolist(),
            "loo_youngs_modulus_kpa": (self.loo_youngs_modulus_pa / 1e3).tolist(),
            "fit_at_search_limit": self.at_search_limit,
            "softest_solved_kpa_per_ray": (self.ray_limit_youngs_modulus_pa / 1e3).tolist(),
        }


def fit_formulation(model, measurements: Measurements, youngs_modulus_pa: float, formulation: str,
                    linear_load_factor: float, steps_per_linear_load_factor: int | None = None,
                    progress=None) -> FormulationFit:
    """Fit and leave-one-out for one formulation, on the ray responses (see the module docstring)."""
    measured_m3 = measurements.volumes_m3
    everyone = range(len(measured_m3))
    steps_per_linear_load_factor = steps_per_linear_load_factor or STEPS_PER_LINEAR_LOAD_FACTOR
    # The co-rotational response softens, so its best t lies below the linear estimate's, inside the range.
    responses = ray_responses(model, measurements.pressures_pa, measured_m3,
                              linear_load_factor / steps_per_linear_load_factor,
                              MAX_LINEAR_MULTIPLE * linear_load_factor, formulation=formulation, progress=progress)
    load_factor = fit_load_factor(responses, measured_m3, everyone)
    fit_predicted = responses.predict(load_factor)
    loo_predicted, loo_moduli = [], []
    for left_out in everyone:
        factor = fit_load_factor(responses, measured_m3, [index for index in everyone if index != left_out])
        loo_predicted.append(responses.predict(factor, [left_out])[0])
        loo_moduli.append(youngs_modulus_pa / factor)
    loo_predicted = np.array(loo_predicted)
    return FormulationFit(
        formulation, youngs_modulus_pa / load_factor,
        float(relative_abs_errors_pct(fit_predicted, measured_m3).mean()),
        float(relative_abs_errors_pct(loo_predicted, measured_m3).mean()),
        fit_predicted, loo_predicted, np.array(loo_moduli),
        bool(load_factor >= 0.99 * responses.max_load_factor),
        youngs_modulus_pa / np.maximum(responses.ray_limits, 1e-300))


@dataclass
class CalibrationResult:
    """The chosen fit (lowest leave-one-out error among the formulations tried) and every candidate."""

    best: FormulationFit
    candidates: dict
    linear_compliance_youngs_modulus_pa: float

    @property
    def youngs_modulus_pa(self) -> float:
        return self.best.youngs_modulus_pa

    @property
    def fit_mean_abs_pct_error(self) -> float:
        return self.best.fit_mean_abs_pct_error

    @property
    def loo_mean_abs_pct_error(self) -> float:
        return self.best.loo_mean_abs_pct_error

    def as_json(self, measurements: Measurements) -> dict:
        """The report's JSON (kPa, ml, %): the chosen fit's figures at the top level, then every candidate."""
        report = self.best.as_json()
        report["material_model"] = self.best.formulation
        report["measured_ml"] = (measurements.volumes_m3 * 1e6).tolist()
        report["candidates"] = {name: fit.as_json() for name, fit in self.candidates.items()}
        report["rest_compliance_youngs_modulus_kpa"] = self.linear_compliance_youngs_modulus_pa / 1e3
        return report


def fit_linear_compliance(rest_gland_m3: float, gland_m3_per_pa: np.ndarray, pressures_pa: np.ndarray,
                          measured_m3: np.ndarray, rays) -> float:
    """Closed-form relative least squares of ``g = g_0 + t h . p`` for the load factor ``t`` (rest compliance)."""
    rays = list(rays)
    slope = (pressures_pa[rays] @ gland_m3_per_pa) / measured_m3[rays]
    residual_at_zero = (measured_m3[rays] - rest_gland_m3) / measured_m3[rays]
    denominator = float(slope @ slope)
    return float(slope @ residual_at_zero / denominator) if denominator > 0 else 1.0


def calibrate(model, measurements: Measurements, youngs_modulus_pa: float, formulations=FORMULATIONS,
              steps_per_linear_load_factor: int | None = None, progress=None) -> CalibrationResult:
    """Fit Young's modulus to ``measurements`` for each formulation and keep the one with the lowest
    leave-one-out error; ``youngs_modulus_pa`` is the modulus ``model`` was built with (Pa)."""
    youngs_modulus_pa = float(youngs_modulus_pa)
    gland_m3_per_pa = np.asarray(model.compliance().gland_m3_per_pa, dtype=float)
    linear_load_factor = fit_linear_compliance(model.rest_gland_volume_m3, gland_m3_per_pa,
                                               measurements.pressures_pa, measurements.volumes_m3,
                                               range(len(measurements.volumes_m3)))
    if linear_load_factor <= 0:
        raise CalibrationError("the measurements do not grow with pressure: no positive modulus fits them")
    candidates = {}
    for formulation in formulations:
        report = None
        if progress is not None:
            def report(done, total, formulation=formulation):
                progress(done, total, formulation)
        candidates[formulation] = fit_formulation(model, measurements, youngs_modulus_pa, formulation,
                                                  linear_load_factor, steps_per_linear_load_factor, report)
    best = min(candidates.values(), key=lambda fit: fit.loo_mean_abs_pct_error)
    return CalibrationResult(best, candidates, youngs_modulus_pa / linear_load_factor)


# --------------------------------------------------------------------- writing the calibrated scene
def _toml_value(value) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (int, np.integer)):
        return str(int(value))
    if isinstance(value, (float, np.floating)):
        if not np.isfinite(value):
            raise CalibrationError(f"cannot write the non-finite value {value} to a scene")
        return repr(float(value))
    if isinstance(value, str):
        return '"' + value.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_toml_value(item) for item in value) + "]"
    if isinstance(value, dict):
        return "{ " + ", ".join(f"{key} = {_toml_value(item)}" for key, item in value.items()) + " }"
    raise CalibrationError(f"cannot write a {type(value).__name__} to a scene")


def dump_toml(document: dict, header_comment: str = "") -> str:
    """TOML text for a scene dictionary: top-level tables of scalars, lists and inline tables, and arrays of
    tables (``[[steps]]``)."""
    lines = [f"# {line}" if line else "#" for line in header_comment.splitlines()]
    scalars = {key: value for key, value in document.items() if not isinstance(value, (dict, list))
               or (isinstance(value, list) and not all(isinstance(item, dict) for item in value))}
    for key, value in scalars.items():
        lines.append(f"{key} = {_toml_value(value)}")
    for key, value in document.items():
        if isinstance(value, dict):
            lines.append("")
            lines.append(f"[{key}]")
            lines.extend(f"{name} = {_toml_value(item)}" for name, item in value.items())
        elif isinstance(value, list) and value and all(isinstance(item, dict) for item in value):
            for item in value:
                lines.append("")
                lines.append(f"[[{key}]]")
                lines.extend(f"{name} = {_toml_value(entry)}" for name, entry in item.items())
    return "\n".join(lines) + "\n"


def write_calibrated_scene(scene, youngs_modulus_pa: float, output_path, header_comment: str = "",
                           material_model: str | None = None) -> Path:
    """Write ``scene`` with ``[material] youngs_modulus_kpa`` (and ``model``, if given) replaced, its mesh path
    made relative to the new file; returns the path written."""
    import copy
    import os

    output_path = Path(output_path)
    document = copy.deepcopy(scene.raw)
    phantom_table = document.setdefault("phantom", {})
    mesh = phantom_table.get("mesh", "builtin:prostate")
    if not str(mesh).startswith("builtin"):
        source = (Path(scene.path).parent / mesh).resolve() if scene.path else Path(mesh).resolve()
        phantom_table["mesh"] = os.path.relpath(source, output_path.resolve().parent)
    material = document.setdefault("material", {})
    material["youngs_modulus_kpa"] = round(youngs_modulus_pa / 1e3, 4)
    if material_model is not None:
        material["model"] = material_model
    output_path.parent.mkdir(parents=True, exist_ok=True)
    output_path.write_text(dump_toml(document, header_comment))
    return output_path


def stderr_progress(label: str):
    """A progress callback that redraws ``label (stage) [#####.....] done/total`` on stderr."""
    def report(done: int, total: int, stage: str = "") -> None:
        width = 30
        filled = int(width * done / max(total, 1))
        sys.stderr.write(f"\r{label} ({stage}) [{'#' * filled}{'.' * (width - filled)}] {done}/{total}  ")
        if done >= total:
            sys.stderr.write("\n")
        sys.stderr.flush()
    return report
