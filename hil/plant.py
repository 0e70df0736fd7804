"""The pneumatic plant's parameters: read ``hil/plant.toml``, check them, convert them to SI.

The plant itself is integrated inside the simavr harness (``hil/harness/plant.c``), next to the firmware, at
a fixed step in simulated time. Per chamber i, with gauge pressures p (Pa), air volumes V = V0 + C p (m^3),
blower inflow Q_in = Q_max u (1 - p / p_blocked) and back-leak Q_out = G p (m^3/s at atmospheric
conditions), the isothermal air content (p_atm + p_i) V_i changes by p_atm (Q_in - Q_out)_i:

    sum_j [V_i delta_ij + (p_atm + p_i) C_ij] dp_j/dt = p_atm (Q_in,i - Q_out,i)

which for one chamber is physics.md's dp/dt = p_atm (Q_in - Q_out) / (V + (p_atm + p) C).
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from phantom import PhantomError

#: The shipped plant parameter file.
DEFAULT_PLANT_PATH = Path(__file__).resolve().parent / "plant.toml"

N_CHAMBERS = 3


class PlantError(PhantomError):
    """The plant parameter file is missing, malformed or physically impossible."""


@dataclass(frozen=True)
class PlantParameters:
    """The plant in SI units (Pa, m^3, m^3/s, V, s); arrays have one entry per chamber."""

    path: Path
    atmospheric_pressure_pa: float
    rest_volume_m3: np.ndarray
    compliance_m3_per_pa: np.ndarray
    free_flow_m3_per_s: np.ndarray
    blocked_pressure_pa: np.ndarray
    leak_conductance_m3_per_s_per_pa: np.ndarray
    sensor_supply_v: float
    sensor_gain_per_pa: float
    sensor_offset_pa: np.ndarray
    sensor_noise_v: float
    sensor_response_time_s: float
    step_s: float

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
            "leak_conductance_m3_per_s_per_pa",
            "sensor_offset_pa",
        ):
            for chamber, value in enumerate(getattr(self, name)):
                arguments += ["--param", f"{name}.{chamber}={float(value)!r}"]
        for (row, column), value in np.ndenumerate(self.compliance_m3_per_pa):
            arguments += ["--param", f"compliance_m3_per_pa.{row}.{column}={float(value)!r}"]
        return arguments


def _section(document: dict, name: str, path: Path) -> dict:
    section = document.get(name)
    if not isinstance(section, dict):
        raise PlantError(f"{path}: missing table [{name}]; see hil/plant.toml for the expected layout")
    return section


def _number(section: dict, key: str, where: str, *, positive: bool = False, allow_zero: bool = True) -> float:
    if key not in section:
        raise PlantError(f"{where}: missing key {key!r}; see hil/plant.toml for the expected layout")
    value = section[key]
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise PlantError(f"{where}.{key}: expected a finite number, got {value!r}")
    if positive and not (value > 0 or (allow_zero and value == 0)):
        raise PlantError(f"{where}.{key}: must be {'>= 0' if allow_zero else '> 0'}, got {value!r}")
    return float(value)


def _per_chamber(section: dict, key: str, where: str, *, positive: bool = False, allow_zero: bool = True) -> np.ndarray:
    if key not in section:
        raise PlantError(f"{where}: missing key {key!r} (a list of {N_CHAMBERS} numbers, one per chamber)")
    values = section[key]
    if not isinstance(values, list) or len(values) != N_CHAMBERS:
        raise PlantError(f"{where}.{key}: expected a list of {N_CHAMBERS} numbers (one per chamber), got {values!r}")
    return np.array(
        [_number({key: v}, key, where, positive=positive, allow_zero=allow_zero) for v in values], dtype=float
    )


def _compliance(section: dict, where: str) -> np.ndarray:
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
    try:
        document = tomllib.loads(path.read_text())
    except FileNotFoundError:
        raise PlantError(f"the plant file {path} does not exist: pass a path to a file like hil/plant.toml") from None
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
        rest_volume_m3=1e-6
        * _per_chamber(chambers, "rest_volume_ml", f"{path} [chambers]", positive=True, allow_zero=False),
        compliance_m3_per_pa=_compliance(chambers, f"{path} [chambers]"),
        free_flow_m3_per_s=1e-6 / 60 * _per_chamber(blower, "free_flow_ml_per_min", f"{path} [blower]", positive=True),
        blocked_pressure_pa=1e3
        * _per_chamber(blower, "blocked_pressure_kpa", f"{path} [blower]", positive=True, allow_zero=False),
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
    )
