"""The pneumatic plant's parameters: read ``hil/plant.toml``, check them, convert them to SI.

The plant itself is integrated inside the simavr harness (``hil/harness/plant.c``), next to the firmware, at
a fixed step in simulated time. Per chamber i, with gauge pressures p (Pa), air volumes V = V0 + C p (m^3),
blower inflow Q_in = Q_max max(a - p / p_blocked, 0) at driver amplitude a = max(u - u0, 0) / (1 - u0) for a
drive level u (see :func:`blower_flow_m3_per_s`) and back-leak Q_out = G p (m^3/s at atmospheric
conditions), the isothermal air content (p_atm + p_i) V_i changes by p_atm (Q_in - Q_out)_i:

    sum_j [V_i delta_ij + (p_atm + p_i) C_ij] dp_j/dt = p_atm (Q_in,i - Q_out,i)

which for one chamber is physics.md's dp/dt = p_atm (Q_in - Q_out) / (V + (p_atm + p) C).

The rest volumes V0 (each cavity's air plus its tube's dead volume) and the compliance C come from the FEM at
rest; :func:`chambers_from_scene` computes them and :func:`write_chambers` puts them into a plant file:

    phantom hil plant --from-scene model/scenes/prostate_converged.toml [--plant hil/plant.toml]
"""

from __future__ import annotations

import math
import re
import tomllib
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from phantom import PhantomError, is_finite_number
from phantom.hil.truth_residual import trilinear

#: The shipped plant parameter file.
DEFAULT_PLANT_PATH = Path(__file__).resolve().parent / "plant.toml"
#: The scene whose FEM gives the shipped plant's chamber volumes and compliance.
CALIBRATED_SCENE_PATH = Path(__file__).resolve().parent.parent / "model" / "scenes" / "prostate_converged.toml"
#: Significant digits written for volumes (ml) and compliances (ml/kPa): rounding moves a value by <= 5e-5 of it.
WRITTEN_DIGITS = 5

N_CHAMBERS = 3
#: Points per pressure axis of the truth table (PLANT_TRUTH_POINTS in plant.h).
TRUTH_GRID_POINTS = 4


class PlantError(PhantomError):
    """The plant parameter file is missing, malformed or physically impossible."""


@dataclass(frozen=True)
class PlantParameters:
    """The plant in SI units (Pa, m^3, m^3/s, V, s); arrays have one entry per chamber."""

    path: Path
    atmospheric_pressure_pa: float
    cavity_volume_m3: np.ndarray
    tubing_volume_m3: np.ndarray
    compliance_m3_per_pa: np.ndarray
    free_flow_m3_per_s: np.ndarray
    blocked_pressure_pa: np.ndarray
    driver_threshold: np.ndarray
    leak_conductance_m3_per_s_per_pa: np.ndarray
    sensor_supply_v: float
    sensor_gain_per_pa: float
    sensor_offset_pa: np.ndarray
    sensor_noise_v: float
    sensor_response_time_s: float
    step_s: float
    #: The truth's pressure-volume table (None: the linear V0 + C p): grid step (Pa), chamber volumes (m^3,
    #: (n, n, n, 3)) and gland volumes (m^3, (n, n, n)) at pressures (i, j, k) * step.
    truth_step_pa: float = 0.0
    truth_chamber_volume_m3: np.ndarray | None = None
    truth_gland_volume_m3: np.ndarray | None = None

    def truth_gland_volume_ml(self, pressures_pa: ArrayLike) -> float | None:
        """The truth's gland volume (ml) at these pressures, as the harness interpolates the chambers; None
        without a truth table."""
        if self.truth_gland_volume_m3 is None:
            return None
        points_kpa = self.truth_step_pa / 1e3 * np.arange(self.truth_gland_volume_m3.shape[0])
        return float(1e6 * trilinear(self.truth_gland_volume_m3, points_kpa, np.asarray(pressures_pa) / 1e3))

    @property
    def rest_volume_m3(self) -> np.ndarray:
        """Air volume of each chamber at 0 gauge (m^3): the cavity's plus its tube's."""
        return np.asarray(self.cavity_volume_m3 + self.tubing_volume_m3)

    def harness_arguments(self) -> list[str]:
        """The ``--param NAME=VALUE`` arguments that give the harness this plant (names as in plant.c)."""
        arguments = []
        for name in (
            "atmospheric_pressure_pa",
            "sensor_supply_v",
            "sensor_gain_per_pa",
            "sensor_noise_v",
            "sensor_response_time_s",
            "step_s",
        ):
            arguments += ["--param", f"{name}={getattr(self, name)!r}"]
        for name in (
            "rest_volume_m3",
            "free_flow_m3_per_s",
            "blocked_pressure_pa",
            "driver_threshold",
            "leak_conductance_m3_per_s_per_pa",
            "sensor_offset_pa",
        ):
            for chamber, value in enumerate(getattr(self, name)):
                arguments += ["--param", f"{name}.{chamber}={float(value)!r}"]
        for (row, column), value in np.ndenumerate(self.compliance_m3_per_pa):
            arguments += ["--param", f"compliance_m3_per_pa.{row}.{column}={float(value)!r}"]
        table = self.truth_chamber_volume_m3
        if table is None:
            table = np.zeros((TRUTH_GRID_POINTS,) * 3 + (N_CHAMBERS,))
        arguments += ["--param", f"truth_step_pa={self.truth_step_pa!r}"]
        for flat, value in enumerate(table.ravel()):
            arguments += ["--param", f"truth_volume_m3.{flat}={float(value)!r}"]
        return arguments


def _section(document: dict[str, Any], name: str, path: Path) -> dict[str, Any]:
    section = document.get(name)
    if not isinstance(section, dict):
        raise PlantError(f"{path}: missing table [{name}]; see hil/plant.toml for the expected layout")
    return section


def _number(section: dict[str, Any], key: str, where: str, *, positive: bool = False, allow_zero: bool = True) -> float:
    if key not in section:
        raise PlantError(f"{where}: missing key {key!r}; see hil/plant.toml for the expected layout")
    value = section[key]
    if not is_finite_number(value):
        raise PlantError(f"{where}.{key}: expected a finite number, got {value!r}")
    if positive and not (value > 0 or (allow_zero and value == 0)):
        raise PlantError(f"{where}.{key}: must be {'>= 0' if allow_zero else '> 0'}, got {value!r}")
    return float(value)


def _per_chamber(section: dict[str, Any], key: str, where: str, *, positive: bool = False,
                 allow_zero: bool = True) -> np.ndarray:
    if key not in section:
        raise PlantError(f"{where}: missing key {key!r} (a list of {N_CHAMBERS} numbers, one per chamber)")
    values = section[key]
    if not isinstance(values, list) or len(values) != N_CHAMBERS:
        raise PlantError(f"{where}.{key}: expected a list of {N_CHAMBERS} numbers (one per chamber), got {values!r}")
    return np.array(
        [_number({key: v}, key, where, positive=positive, allow_zero=allow_zero) for v in values], dtype=float
    )


def _driver_threshold(section: dict[str, Any], where: str) -> np.ndarray:
    values = _per_chamber(section, "driver_threshold", where, positive=True)
    if np.any(values >= 1):
        raise PlantError(f"{where}.driver_threshold: must be below 1 (a drive level), got {values.tolist()}")
    return values


def blower_flow_m3_per_s(plant: PlantParameters, drive: ArrayLike, pressure_pa: ArrayLike) -> np.ndarray:
    """Air each blower delivers (m^3/s at atmospheric conditions) at drive levels u in [0, 1] against gauge
    pressures p: the driver's amplitude a = max(u - u0, 0) / (1 - u0) scales both the free flow and the blocked
    pressure, Q = Q_max max(a - p / p_blocked, 0). The same law as the harness's plant.c, for tests and benches."""
    threshold = plant.driver_threshold
    amplitude = np.clip((np.asarray(drive, dtype=float) - threshold) / (1 - threshold), 0, 1)
    flow = plant.free_flow_m3_per_s * np.maximum(amplitude - np.asarray(pressure_pa) / plant.blocked_pressure_pa, 0)
    return np.where(amplitude > 0, flow, 0.0)  # a blower that does not run pumps nothing, even against suction


def _compliance(section: dict[str, Any], where: str) -> np.ndarray:
    key = "compliance_ml_per_kpa"
    rows = section.get(key)
    if (
        not isinstance(rows, list)
        or len(rows) != N_CHAMBERS
        or any(not isinstance(row, list) or len(row) != N_CHAMBERS for row in rows)
    ):
        raise PlantError(f"{where}.{key}: expected a {N_CHAMBERS}x{N_CHAMBERS} matrix (a list of lists), got {rows!r}")
    matrix = np.array([[_number({key: v}, key, where) for v in row] for row in rows])
    if not np.array_equal(matrix, matrix.T):
        raise PlantError(f"{where}.{key}: the compliance matrix must be symmetric (C[i][j] == C[j][i])")
    if np.any(np.linalg.eigvalsh(matrix) <= 0):
        raise PlantError(
            f"{where}.{key}: the compliance matrix must be positive definite (a chamber cannot shrink when all "
            f"are inflated); eigenvalues {np.linalg.eigvalsh(matrix).round(3).tolist()} ml/kPa"
        )
    return matrix * 1e-6 / 1e3


def load_plant(path: str | Path | None = None) -> PlantParameters:
    """Read a plant parameter file (default ``hil/plant.toml``) into SI units.

    Raises
    ------
    PlantError
        When the file is missing, is not TOML, or a value is missing, of the wrong shape or unphysical;
        the message names the key.
    """
    path = Path(path) if path is not None else DEFAULT_PLANT_PATH
    return _plant_from_text(_read_plant_text(path), path)


def _read_plant_text(path: Path) -> str:
    try:
        return path.read_text()
    except FileNotFoundError:
        raise PlantError(f"the plant file {path} does not exist: pass a path to a file like hil/plant.toml") from None


def _plant_from_text(text: str, path: Path) -> PlantParameters:
    try:
        document = tomllib.loads(text)
    except tomllib.TOMLDecodeError as error:
        raise PlantError(f"the plant file {path} is not valid TOML: {error}") from None
    gas, chambers = _section(document, "gas", path), _section(document, "chambers", path)
    blower, sensor = _section(document, "blower", path), _section(document, "sensor", path)
    integration = _section(document, "integration", path)
    step_us = _number(integration, "step_us", f"{path} [integration]", positive=True, allow_zero=False)
    if step_us > 1000:
        raise PlantError(f"{path} [integration].step_us: {step_us} is too coarse for the plant; use <= 1000")
    return PlantParameters(
        path=path,
        atmospheric_pressure_pa=1e3
        * _number(gas, "atmospheric_pressure_kpa", f"{path} [gas]", positive=True, allow_zero=False),
        cavity_volume_m3=1e-6
        * _per_chamber(chambers, "cavity_volume_ml", f"{path} [chambers]", positive=True, allow_zero=False),
        tubing_volume_m3=1e-6 * _per_chamber(chambers, "tubing_volume_ml", f"{path} [chambers]", positive=True),
        compliance_m3_per_pa=_compliance(chambers, f"{path} [chambers]"),
        free_flow_m3_per_s=1e-6 / 60 * _per_chamber(blower, "free_flow_ml_per_min", f"{path} [blower]", positive=True),
        blocked_pressure_pa=1e3
        * _per_chamber(blower, "blocked_pressure_kpa", f"{path} [blower]", positive=True, allow_zero=False),
        driver_threshold=_driver_threshold(blower, f"{path} [blower]"),
        leak_conductance_m3_per_s_per_pa=1e-6
        / 1e3
        * _per_chamber(blower, "back_leak_ml_per_s_per_kpa", f"{path} [blower]", positive=True),
        sensor_supply_v=_number(sensor, "supply_v", f"{path} [sensor]", positive=True, allow_zero=False),
        sensor_gain_per_pa=1e-3
        * _number(sensor, "sensitivity_per_kpa", f"{path} [sensor]", positive=True, allow_zero=False),
        sensor_offset_pa=1e3 * _per_chamber(sensor, "offset_kpa", f"{path} [sensor]"),
        sensor_noise_v=1e-3 * _number(sensor, "noise_mv", f"{path} [sensor]", positive=True),
        sensor_response_time_s=1e-3 * _number(sensor, "response_time_ms", f"{path} [sensor]", positive=True),
        step_s=1e-6 * step_us,
        **_truth(chambers, f"{path} [chambers]"),
    )


def _truth(chambers: dict[str, Any], where: str) -> dict[str, Any]:
    """The optional truth table of [chambers] in SI units (empty when the file has none)."""
    keys = ("truth_step_kpa", "truth_chamber_volume_ml", "truth_gland_volume_ml")
    present = [key for key in keys if key in chambers]
    if not present:
        return {}
    if len(present) != len(keys):
        raise PlantError(f"{where}: a truth table needs all of {', '.join(keys)}; regenerate it with "
                         f"phantom hil plant --truth-from-scene SCENE")
    n = TRUTH_GRID_POINTS
    step_kpa = _number(chambers, "truth_step_kpa", where, positive=True, allow_zero=False)
    try:
        volumes = np.array(chambers["truth_chamber_volume_ml"], dtype=float).reshape(n, n, n, N_CHAMBERS)
        gland = np.array(chambers["truth_gland_volume_ml"], dtype=float).reshape(n, n, n)
    except (TypeError, ValueError):
        raise PlantError(f"{where}: truth_chamber_volume_ml must be {n ** 3} rows of {N_CHAMBERS} volumes and "
                         f"truth_gland_volume_ml {n ** 3} volumes (ml), i, j, k in C order") from None
    if not (np.all(np.isfinite(volumes)) and np.all(volumes > 0) and np.all(gland > 0)):
        raise PlantError(f"{where}: the truth table's volumes must be finite and positive")
    return {"truth_step_pa": 1e3 * step_kpa, "truth_chamber_volume_m3": 1e-6 * volumes,
            "truth_gland_volume_m3": 1e-6 * gland}


@dataclass(frozen=True)
class FemChambers:
    """The chambers of a scene's FEM at rest, in the plant file's units (ml, ml/kPa).

    ``compliance_ml_per_kpa`` is W = H K^-1 H^T (physics.md), symmetrised as (W + W^T) / 2 so that the file's
    exact symmetry check holds after rounding.
    """

    scene: str
    description: str
    cavity_volume_ml: np.ndarray
    compliance_ml_per_kpa: np.ndarray


def chambers_from_scene(scene: str | Path, mesh_size_mm: float | None = None) -> FemChambers:
    """The rest air volume of each chamber and the compliance matrix from the FEM of a scene.

    ``PhantomModel.from_scene(load_scene(scene), mesh_size_mm)``: ``rest_chamber_volumes_m3`` (m^3 -> ml) and
    ``compliance().chamber_m3_per_pa`` (m^3/Pa -> ml/kPa, a factor 1e9). The tubes' dead volume is not part of
    the FEM (see :func:`write_chambers`).

    Raises
    ------
    PlantError
        When the scene does not have exactly three chambers (the plant and the board have three).
    phantom.PhantomError
        From the model, when the scene or its mesh is unusable.
    """
    # the FEM's stack (scipy, numba) loads only when a plant is regenerated, not when one is read
    from phantom.model import PhantomModel, load_scene

    loaded = load_scene(scene)
    model = PhantomModel.from_scene(loaded, mesh_size_mm=mesh_size_mm)
    if model.n_chambers != N_CHAMBERS:
        raise PlantError(
            f"the scene {scene} has {model.n_chambers} chambers ({', '.join(model.chamber_names)}); the plant and "
            f"the board have {N_CHAMBERS}: give a scene with three"
        )
    compliance_m3_per_pa = model.compliance().chamber_m3_per_pa
    material = loaded.material
    scene_size_mm = loaded.geometry.mesh_size_mm if loaded.geometry is not None else None
    size_mm = mesh_size_mm if mesh_size_mm is not None else scene_size_mm
    mesh = "the mesh file" if size_mm is None else f"{size_mm:g} mm mesh"
    return FemChambers(
        scene=str(scene),
        description=f"{material.model}, E = {material.youngs_modulus_pa / 1e3:.5g} kPa, "
        f"nu = {material.poisson_ratio:g}, {mesh}",
        cavity_volume_ml=1e6 * np.asarray(model.rest_chamber_volumes_m3, dtype=float),
        compliance_ml_per_kpa=1e9 * 0.5 * (compliance_m3_per_pa + compliance_m3_per_pa.T),
    )


def toml_list(values: np.ndarray) -> str:
    """Numbers as a TOML array, each to :data:`WRITTEN_DIGITS` significant digits."""
    return "[" + ", ".join(f"{value:.{WRITTEN_DIGITS}g}" for value in values) + "]"


def _replace_once(text: str, pattern: str, replacement: str, what: str, path: Path) -> str:
    new_text, count = re.subn(pattern, lambda _: replacement, text, flags=re.MULTILINE)
    if count != 1:
        raise PlantError(
            f"{path}: expected one {what} in [chambers] to replace, found {count}; start from a copy of "
            f"hil/plant.toml"
        )
    return new_text


def write_chambers(chambers: FemChambers, path: str | Path | None = None) -> PlantParameters:
    """Put the FEM's chamber volumes and compliance into a plant file (default ``hil/plant.toml``), in place.

    Rewrites ``cavity_volume_ml``, ``compliance_ml_per_kpa`` (to WRITTEN_DIGITS significant digits) and the
    ``# FEM source:`` comment; every other line, ``tubing_volume_ml`` (the tubes' dead volume, which the FEM
    does not know) included, is kept. The result is checked with the file's own rules before it is written.

    Returns
    -------
    PlantParameters
        The plant as read back from the new text.
    """
    path = Path(path) if path is not None else DEFAULT_PLANT_PATH
    text = _read_plant_text(path)
    rows = ",\n".join(f"  {toml_list(row)}" for row in chambers.compliance_ml_per_kpa)
    text = _replace_once(
        text, r"^# FEM source: .*$", f"# FEM source: {chambers.scene} ({chambers.description})", "'# FEM source:'", path
    )
    text = _replace_once(
        text,
        r"^cavity_volume_ml = \[[^\]\n]*\]$",
        f"cavity_volume_ml = {toml_list(chambers.cavity_volume_ml)}",
        "cavity_volume_ml line",
        path,
    )
    text = _replace_once(
        text,
        r"^compliance_ml_per_kpa = \[\n(?:\s*\[[^\]\n]*\],?\n){3}\]$",
        f"compliance_ml_per_kpa = [\n{rows},\n]",
        "compliance_ml_per_kpa matrix (one row per line)",
        path,
    )
    plant = _plant_from_text(text, path)
    path.write_text(text)
    return plant


# ------------------------------------------------------------------------- the truth the plant integrates
#: Pressures (kPa) of the truth table's grid, the same on each chamber's axis; beyond it the plant extrapolates
#: the last cell linearly.
TRUTH_POINTS_KPA = tuple(float(k) for k in range(TRUTH_GRID_POINTS))
#: The default truth: the calibrated model with its modulus moved by the jackknife standard error of its
#: leave-one-out moduli (0.646 of 10.81 kPa on the 10 mm mesh, whose fit is 0.4 % from the 7 mm one's;
#: bench/README.md "A calibration anchored on the material"): a phantom as far from the controller's model as the
#: calibration's own uncertainty.
TRUTH_MODULUS_FACTOR = 1.06


@dataclass(frozen=True)
class TruthTable:
    """Chamber and gland volumes (ml) of a truth model on the grid TRUTH_POINTS_KPA^3 (index i, j, k = the
    pressures of chambers 0, 1, 2), and what it is."""

    points_kpa: tuple[float, ...]
    chamber_volume_ml: np.ndarray   # (n, n, n, 3)
    gland_volume_ml: np.ndarray     # (n, n, n)
    description: str


def truth_model(scene: str | Path, modulus_factor: float) -> Any:
    """The simulated phantom's model (a ``PhantomModel``): the scene without the tables it ships (they are its
    own modulus's) with its modulus times ``modulus_factor``; what the truth table and the truth shapes solve."""
    # the FEM's stack loads only when a truth is made, not when a plant is read
    from phantom.model import PhantomModel, load_scene
    from phantom.model.scene import scene_from_dict, without_shipped_tables

    loaded = load_scene(scene)
    model = PhantomModel.from_scene(scene_from_dict(without_shipped_tables(loaded.raw), loaded.path))
    return model.with_material(youngs_modulus_pa=model.material.youngs_modulus_pa * modulus_factor)


def truth_table_from_scene(scene: str | Path, modulus_factor: float = TRUTH_MODULUS_FACTOR,
                           workers: int | None = None,
                           progress: Callable[[int, int], None] | None = None,
                           scheduler: str | None = None, shapes_path: str | Path | None = None) -> TruthTable:
    """Full solves of the scene with its modulus times ``modulus_factor`` (:func:`truth_model`) at every grid
    point: the response table's build (:func:`phantom.model.fidelity.response_table.build_response_table`, each
    point started from a solved neighbour, as Dask tasks on ``workers`` local processes or the cluster at
    ``scheduler``), whose grid over 0-3 kPa is the truth's. Given ``shapes_path``, the same solves' outer
    surfaces are written there too (``write_table_shapes``, checked against 4 more full solves): the truth's
    shapes, which :class:`phantom.hil.truth_shape.TruthShape` reads instead of solving each."""
    from phantom.model.fidelity.response_table import (
        CHECK_FRACTIONS,
        ResponseTableError,
        build_response_table,
        build_table_shapes,
        write_table_shapes,
    )

    truth = truth_model(scene, modulus_factor)
    n = len(TRUTH_POINTS_KPA)
    checks = 0 if shapes_path is None else len(CHECK_FRACTIONS)   # the shapes' own check: full solves
    total = n ** N_CHAMBERS + len(CHECK_FRACTIONS) + checks
    told = (lambda done, _: progress(done, total)) if progress is not None else None
    try:
        table = build_response_table(truth, 1e3 * TRUTH_POINTS_KPA[-1], n, told, workers, scheduler)
        if shapes_path is not None:
            write_table_shapes(build_table_shapes(truth, table.pressure_max_pa, n, table=table), truth, shapes_path)
            if progress is not None:
                progress(total, total)
    except ResponseTableError as error:
        raise PlantError(f"the truth model does not solve: {error}") from None
    modulus_kpa = truth.material.youngs_modulus_pa / 1e3
    description = f"{scene} with E x {modulus_factor:g} = {modulus_kpa:.4g} kPa ({truth.material.model})"
    return TruthTable(TRUTH_POINTS_KPA, 1e6 * table.chamber_values, 1e6 * table.gland_values, description)


#: The physical phantom's measured gland volumes (the paper's Table I), which the shipped truth passes through.
MEASURED_VOLUMES_PATH = Path(__file__).resolve().parent.parent / "model" / "data" / "forward_measurements.csv"
def truth_through_measurements(table: TruthTable, pressures_kpa: ArrayLike, volumes_ml: ArrayLike,
                               source: str = "the measurements") -> TruthTable:
    """The truth table plus the smoothest residual field that takes its gland volume, as the plant interpolates
    it, through measured volumes (:func:`phantom.hil.truth_residual.smoothest_residual`: per chamber, zero while
    the chamber is not inflated, every chamber's and the gland's growth kept positive).

    Raises
    ------
    PlantError
        When the measurements cannot be met so (two that contradict the growth's sign), or a pressure is
        negative or beyond the table's grid.
    """
    from phantom.hil.truth_residual import smoothest_residual
    from phantom.model.measurements import CorrectionError

    points = np.asarray(table.points_kpa, dtype=float)
    pressures = np.atleast_2d(np.asarray(pressures_kpa, dtype=float))
    measured = np.asarray(volumes_ml, dtype=float).ravel()
    if pressures.shape != (len(measured), N_CHAMBERS):
        raise PlantError(f"the truth's measurements need {N_CHAMBERS} pressures per volume, got {pressures.shape[0]} "
                         f"rows of {pressures.shape[1]} for {len(measured)} volumes")
    try:
        gaps = [volume - float(trilinear(table.gland_volume_ml, points, pressure))
                for pressure, volume in zip(pressures, measured, strict=True)]
        residual = smoothest_residual(points, table.chamber_volume_ml, table.gland_volume_ml, pressures, gaps,
                                      f"the truth's measurements ({source})")
    except CorrectionError as error:
        raise PlantError(str(error)) from None
    return TruthTable(table.points_kpa, table.chamber_volume_ml + residual.chamber_ml,
                      table.gland_volume_ml + residual.gland_ml,
                      f"{table.description}, plus the smoothest residual through {len(measured)} measured volumes "
                      f"of {source}")


#: Bumped when what a cached truth plant holds changes (2: its truth shapes beside it).
TRUTH_PLANT_VERSION = 2


def truth_shapes_path(plant_path: str | Path) -> Path:
    """Where :func:`truth_plant_path` keeps the truth's outer surface shapes beside its plant file."""
    return Path(plant_path).with_suffix(".shapes.npz")


def truth_plant_path(scene: str | Path, modulus_factor: float = TRUTH_MODULUS_FACTOR, workers: int | None = None,
                     progress: Callable[[int, int], None] | None = None) -> Path:
    """A plant file whose simulated phantom is ``scene`` at ``modulus_factor`` x its modulus: the shipped plant
    with the scene's chambers at rest (:func:`chambers_from_scene`) and its truth table
    (:func:`truth_table_from_scene`, 64 solves and 8 checks, told to ``progress``), built on first use and cached
    (keyed by the scene's content, the factor and the shipped plant) in the cache folder ``truth-plants``, with
    the truth's outer surface shapes from the same solves beside it (:func:`truth_shapes_path`), so that the
    virtual camera photographs the truth without a solve per pressure state."""
    import hashlib
    import json

    from phantom import cache_dir, written_atomically
    from phantom.model import load_scene

    if not (math.isfinite(modulus_factor) and 0.1 <= modulus_factor <= 10):
        raise PlantError(f"the truth's modulus factor must be a number from 0.1 to 10, got {modulus_factor!r}")
    loaded = load_scene(scene)
    key = hashlib.sha256(json.dumps({"scene": loaded.raw, "modulus_factor": modulus_factor,
                                     "plant": DEFAULT_PLANT_PATH.read_text(), "version": TRUTH_PLANT_VERSION},
                                    sort_keys=True, default=str).encode()).hexdigest()[:20]
    path = cache_dir("truth-plants") / f"{key}.toml"
    if path.exists():
        return path
    # the shapes are renamed into place first: a plant file in the cache says that both are whole
    with written_atomically(path, PlantError) as temporary, \
            written_atomically(truth_shapes_path(path), PlantError) as shapes:
        temporary.write_text(DEFAULT_PLANT_PATH.read_text())
        write_chambers(chambers_from_scene(scene), temporary)
        write_truth(truth_table_from_scene(scene, modulus_factor, workers, progress, shapes_path=shapes),
                    temporary)
    return path


def write_truth(table: TruthTable, path: str | Path | None = None) -> PlantParameters:
    """Put a truth table into a plant file's [chambers] (replacing one that is there), checked before writing."""
    path = Path(path) if path is not None else DEFAULT_PLANT_PATH
    text = _read_plant_text(path)
    text = re.sub(r"^# Truth source: .*\n(?:.*\n)*?truth_gland_volume_ml = \[[^\]]*\]\n", "", text, flags=re.MULTILINE)
    n = len(table.points_kpa)
    rows = ",\n".join(f"  {toml_list(table.chamber_volume_ml[index])}" for index in np.ndindex(n, n, n))
    block = (f"# Truth source: {table.description}.\n"
             f"# The simulated board's plant interpolates these chamber volumes over the three pressures (grid step\n"
             f"# truth_step_kpa, rows i, j, k in C order) instead of V0 + C p above, so it does not share the\n"
             f"# controller's model. Regenerate: phantom hil plant --truth-from-scene SCENE [--truth-through CSV]\n"
             f"truth_step_kpa = {table.points_kpa[1] - table.points_kpa[0]:g}\n"
             f"truth_chamber_volume_ml = [\n{rows},\n]\n"
             f"truth_gland_volume_ml = {toml_list(table.gland_volume_ml.ravel())}\n")
    text, count = re.subn(r"^(tubing_volume_ml = \[[^\]\n]*\]\n)", lambda m: m.group(1) + block, text,
                          flags=re.MULTILINE)
    if count != 1:
        raise PlantError(f"{path}: expected one tubing_volume_ml line in [chambers] to put the truth after, found "
                         f"{count}; start from a copy of hil/plant.toml")
    plant = _plant_from_text(text, path)
    path.write_text(text)
    return plant
