"""What the inverse is asked and what it answers: :class:`Target`, :class:`InverseResult` and
:data:`TARGET_KINDS`, apart from the solver (:mod:`phantom.model.inverse`) so that the daemon can state targets
and read answers without loading the finite-element model (numpy only).
"""

from __future__ import annotations

import numbers
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from phantom import PhantomError

#: Millilitres per cubic metre and pascals per kilopascal, for messages and the people's units of to_json.
ML_PER_M3 = 1e6
PA_PER_KPA = 1e3
class UnreachableTargetError(PhantomError):
    """A target no allowed pressures reach; the message states the reachable range, and ``gland_range_ml`` holds
    it (low, high) where the gland's volume is what is out of that range (the daemon's verify loop then asks for
    the range's edge), else None; ``corrected``: the range is the model's with a correction of its answers by
    measured volumes in force (:mod:`phantom.model.corrections`)."""

    def __init__(self, message: str, gland_range_ml: tuple[float, float] | None = None, corrected: bool = False):
        super().__init__(message)
        self.gland_range_ml = gland_range_ml
        self.corrected = corrected

    def __reduce__(self) -> tuple[type[UnreachableTargetError], tuple[str, tuple[float, float] | None, bool]]:
        # raised in the model worker's process: the range crosses with the message
        return type(self), (str(self), self.gland_range_ml, self.corrected)


#: The forms a target takes (:attr:`Target.kind`): the gland's volume, one volume per chamber, raw pressures.
TARGET_KINDS = ("volume", "chamber_volumes", "pressures")
#: Significant digits of the people's units (ml, kPa) in :meth:`Target.to_json`: a target given as 32 ml and
#: stored as 3.2e-05 m^3 reads back as 32, not 32.000000000000004.
JSON_DIGITS = 12


def _is_number(value: object) -> bool:
    """A real number (numpy's too), not a bool: the shape of a target's value. Whether it is finite and fits the
    model is the solver's check (:meth:`InverseSolver.pressures_for`), which knows the chambers."""
    return isinstance(value, numbers.Real) and not isinstance(value, bool)


def _are_numbers(values: object, none_allowed: bool = False) -> bool:
    """A flat sequence (a list, a tuple, a 1-D array) of :func:`_is_number` (or None where ``none_allowed``)."""
    if isinstance(values, np.ndarray) and values.ndim == 1:
        items = list(values)
    elif isinstance(values, Sequence) and not isinstance(values, str | bytes):
        items = list(values)
    else:
        return False
    return all(_is_number(value) or (none_allowed and value is None) for value in items)


def _people_units(value_si: float, per_si: float) -> float:
    """``value_si * per_si`` rounded to JSON_DIGITS significant digits."""
    return float(f"{value_si * per_si:.{JSON_DIGITS}g}")


@dataclass(frozen=True)
class Target:
    """What the inverse should reach (SI units): the one shape of a target from the scene or the API to the QP.

    Attributes
    ----------
    gland_volume_m3 : float or None
        The gland's total volume (m^3), the paper's case.
    chamber_volumes_m3 : sequence of (float or None), or None
        One entry per chamber: its wanted volume (m^3), or None to leave it free.
    growth_ratio : mapping of int to float, or None
        Chamber index -> weight: the growths (volume above rest) of the named chambers keep these proportions;
        ``{1: 2.0, 2: 1.0}`` = the left lobe grows twice as much as the right. Weights must be positive.
    pressures_pa : sequence of float, or None
        Raw chamber pressures (Pa): no QP, only checked against the bounds.

    A target normally gives one of the three forms (its :attr:`kind`); the inverse also accepts a gland volume
    together with chamber volumes, and checks every target against the model (:meth:`InverseSolver.pressures_for`).
    """

    gland_volume_m3: float | None = None
    chamber_volumes_m3: Sequence[float | None] | None = None
    growth_ratio: Mapping[int, float] | None = None
    pressures_pa: Sequence[float] | None = None

    def __post_init__(self) -> None:
        # Each value's shape, when the target is made: an array for the gland's volume, a bool for a chamber or a
        # list for a weight used to crash deep in numpy's QP set-up with nothing said of the target. (``!r:.80``:
        # a value's repr cut to 80 characters, however large an array was given.)
        if self.gland_volume_m3 is not None and not _is_number(self.gland_volume_m3):
            raise PhantomError(f"a target's gland_volume_m3 is one volume (m^3), a number, got "
                               f"{self.gland_volume_m3!r:.80}")
        if self.chamber_volumes_m3 is not None and not _are_numbers(self.chamber_volumes_m3, none_allowed=True):
            raise PhantomError(f"a target's chamber_volumes_m3 is one volume (m^3) or None per chamber, e.g. "
                               f"[2e-06, None, None], got {self.chamber_volumes_m3!r:.80}")
        if self.pressures_pa is not None and not _are_numbers(self.pressures_pa):
            raise PhantomError(f"a target's pressures_pa is one pressure (Pa) per chamber, e.g. [1000.0, 0.0, 0.0], "
                               f"got {self.pressures_pa!r:.80}")
        if self.growth_ratio is not None and not (
                isinstance(self.growth_ratio, Mapping)
                and all(isinstance(index, int | np.integer) and not isinstance(index, bool) and _is_number(weight)
                        for index, weight in self.growth_ratio.items())):
            raise PhantomError(f"a target's growth_ratio maps chamber indices (integers) to weights (numbers), e.g. "
                               f"{{1: 2.0, 2: 1.0}}, got {self.growth_ratio!r:.80}")

    @classmethod
    def of_kind(cls, kind: str, values: Sequence[float | None],
                growth_ratio: Mapping[int, float] | None = None) -> Target:
        """The target of ``kind`` (one of :data:`TARGET_KINDS`) with ``values`` in SI units: one gland volume
        (m^3) for "volume", one volume (m^3, or None for a free chamber) per chamber for "chamber_volumes", one
        pressure (Pa) per chamber for "pressures". ``growth_ratio`` goes with "volume" only."""
        if kind not in TARGET_KINDS:
            raise PhantomError(f"unknown target kind {kind!r}: use one of {', '.join(TARGET_KINDS)}")
        if growth_ratio and kind != "volume":
            raise PhantomError(f"a growth ratio goes with a gland volume target, not with {kind}")
        if kind == "volume":
            if len(values) != 1 or values[0] is None:
                raise PhantomError(f"a volume target has one gland volume, got {list(values)}")
            return cls(gland_volume_m3=float(values[0]), growth_ratio=dict(growth_ratio) if growth_ratio else None)
        if kind == "chamber_volumes":
            return cls(chamber_volumes_m3=[None if value is None else float(value) for value in values])
        if any(value is None for value in values):
            raise PhantomError(f"a pressure target has a pressure for every chamber, got {list(values)}")
        return cls(pressures_pa=[float(value) for value in values if value is not None])

    @property
    def kind(self) -> str:
        """Which form the target gives: "volume", "chamber_volumes" or "pressures" (:data:`TARGET_KINDS`);
        PhantomError for a target that gives none or more than one."""
        forms = [kind for kind, value in zip(TARGET_KINDS, (self.gland_volume_m3, self.chamber_volumes_m3,
                                                            self.pressures_pa), strict=True) if value is not None]
        if len(forms) != 1:
            raise PhantomError(f"the target gives {' and '.join(forms) or 'nothing'}: a target of one kind gives "
                               f"exactly one of {', '.join(TARGET_KINDS)}")
        return forms[0]

    @property
    def values(self) -> tuple[float | None, ...]:
        """The target's numbers in SI units, as :meth:`of_kind` takes them (m^3, or Pa for "pressures")."""
        kind = self.kind
        if kind == "volume":
            return (self.gland_volume_m3,)
        if kind == "chamber_volumes":
            return tuple(self.chamber_volumes_m3 or ())
        return tuple(self.pressures_pa or ())

    @property
    def free_chambers(self) -> tuple[int, ...]:
        """The chambers a chamber-volume target leaves free (None); none for the other kinds."""
        return tuple(index for index, value in enumerate(self.chamber_volumes_m3 or ()) if value is None)

    def describe(self) -> str:
        """A short form in the units people see, e.g. ``32.00 ml``, ``chamber 2.00,free,free ml``,
        ``pressures 1.00,1.00,1.00 kPa``."""
        kind = self.kind
        if kind == "volume":
            assert self.gland_volume_m3 is not None  # the kind says so
            ratio = "" if not self.growth_ratio else " (growth ratio " + ", ".join(
                f"chamber{index}:{weight:g}" for index, weight in sorted(self.growth_ratio.items())) + ")"
            return f"{self.gland_volume_m3 * ML_PER_M3:.2f} ml{ratio}"
        per_si, unit = (ML_PER_M3, "ml") if kind == "chamber_volumes" else (1 / PA_PER_KPA, "kPa")
        numbers = ",".join("free" if value is None else f"{value * per_si:.2f}" for value in self.values)
        return f"{kind.split('_')[0]} {numbers} {unit}"

    def to_json(self) -> dict[str, Any]:
        """The target as the daemon's API and a scene's step state it: ``{"volume_ml": 32.0, "growth_ratio":
        {"1": 2.0, "2": 1.0}}``, ``{"chamber_volumes_ml": [2.0, None, None]}`` or ``{"pressures_kpa": [1, 1, 1]}``
        (ml and kPa, to JSON_DIGITS significant digits)."""
        kind = self.kind
        if kind == "volume":
            assert self.gland_volume_m3 is not None  # the kind says so
            result: dict[str, Any] = {"volume_ml": _people_units(self.gland_volume_m3, ML_PER_M3)}
            if self.growth_ratio:
                result["growth_ratio"] = {str(index): float(weight)
                                          for index, weight in sorted(self.growth_ratio.items())}
            return result
        if kind == "chamber_volumes":
            return {"chamber_volumes_ml": [None if value is None else _people_units(value, ML_PER_M3)
                                           for value in self.values]}
        return {"pressures_kpa": [_people_units(value, 1 / PA_PER_KPA) for value in self.pressures_pa or ()]}


@dataclass
class InverseResult:
    """The answer of :meth:`InverseSolver.pressures_for` (SI units): the pressures for ``target`` and the
    volumes they give at the solver's fidelity level.

    ``iterations`` counts linearisations (QP solves); ``solve_time_s`` is the whole inverse, including the
    forward evaluations; ``qp_solve_time_s`` the OSQP time summed over the iterations; ``history`` has one
    entry per linearisation (pressures, relative error, whether the QP met the target, the step taken).
    """

    target: Target
    pressures_pa: np.ndarray
    predicted_gland_volume_m3: float
    predicted_chamber_volumes_m3: np.ndarray
    iterations: int
    solve_time_s: float
    qp_solve_time_s: float
    history: list[dict[str, Any]] = field(default_factory=list)
    #: with a correction by measured volumes in force: the 95 % half-width (ml) of the predicted gland volume, and
    #: from how many measurements (None and 0 without one)
    band_ml: float | None = None
    measurements: int = 0

    def to_json(self) -> dict[str, Any]:
        """The answer as the daemon's API reports it: the target (:meth:`Target.to_json`), ``pressures_kpa``,
        ``predicted_volume_ml``, ``predicted_chamber_volumes_ml``, ``iterations``, ``solve_time_s`` and
        ``qp_time_s``; with a correction in force, ``band_ml`` and ``measurements``."""
        band = {} if self.band_ml is None else {"band_ml": float(self.band_ml), "measurements": int(self.measurements)}
        return {**band, "target": self.target.to_json(),
                "pressures_kpa": (np.asarray(self.pressures_pa, dtype=float) / PA_PER_KPA).tolist(),
                "predicted_volume_ml": float(self.predicted_gland_volume_m3) * ML_PER_M3,
                "predicted_chamber_volumes_ml": (np.asarray(self.predicted_chamber_volumes_m3, dtype=float)
                                                 * ML_PER_M3).tolist(),
                "iterations": int(self.iterations), "solve_time_s": float(self.solve_time_s),
                "qp_time_s": float(self.qp_solve_time_s)}
