"""The model's user-facing errors: each says what was wrong and what to do."""

import difflib
from collections.abc import Iterable, Mapping

from phantom import PhantomError


class SceneError(PhantomError):
    """A scene file that cannot be read or says something the model cannot do.

    One that refuses a single setting's value (:func:`setting_refused`) names it in ``key`` (its name in its table,
    e.g. ``"poisson_ratio"``) and ``requirement`` (what the value must be, phrased to follow the name: ``"must lie
    in (-1, 0.5)"``), so that a command that took the value from a flag can say the flag instead; both are None
    otherwise."""

    def __init__(self, message: str, key: str | None = None, requirement: str | None = None):
        super().__init__(message)
        self.key = key
        self.requirement = requirement


def setting_refused(where: str, table: str, key: str, requirement: str, value: object) -> SceneError:
    """The SceneError of the ``[table] key`` of the scene at ``where`` whose ``value`` breaks ``requirement``:
    "WHERE: [TABLE] KEY REQUIREMENT, got VALUE"."""
    return SceneError(f"{where}: [{table}] {key} {requirement}, got {value!r}", key, requirement)


class MeshError(PhantomError):
    """A mesh that cannot be generated, read, or used: missing groups, open walls, bad tetrahedra."""


class SolveError(PhantomError):
    """A solve that did not converge or inverted elements; the message names the chamber and pressure."""


class PressureUnitWarning(UserWarning):
    """Chamber pressures that look like kPa given where Pa are taken (:func:`phantom.model.fem.model.warn_if_kpa`):
    ``equilibrium([1, 2, 0.5])`` answers all but the rest shape. A load of a few Pa on purpose silences it with
    ``warnings.filterwarnings("ignore", category=PressureUnitWarning)``."""


class PeakPressureError(SolveError):
    """A pressure above a chamber's peak: its pressure-volume curve rises to a limit point and falls beyond, so no
    equilibrium under that pressure lies on the path from rest (a pressure source would burst it through).

    Attributes
    ----------
    chamber : int
        The chamber whose curve peaks below its pressure.
    pressure_kpa : float
        The pressure asked of it (kPa).
    peak_pressure_kpa, peak_volume_ml : float
        The peak's pressure (kPa) and the chamber's volume there (ml), as the path located them.
    """

    def __init__(self, message: str, chamber: int, pressure_kpa: float, peak_pressure_kpa: float,
                 peak_volume_ml: float):
        super().__init__(message)
        self.chamber = chamber
        self.pressure_kpa = pressure_kpa
        self.peak_pressure_kpa = peak_pressure_kpa
        self.peak_volume_ml = peak_volume_ml


def check_known_keys(table: Mapping[str, object], known: Iterable[str], section: str, where: str) -> None:
    """Refuse a table's keys that are not ``known`` with one SceneError that names each and the nearest known
    key (a misspelt ``youngs_modulus_kPa`` would otherwise be ignored and its default used in silence)."""
    known = list(known)
    unknown = [key for key in table if key not in known]
    if not unknown:
        return
    by_lower = {key.lower(): key for key in known}
    named = []
    for key in unknown:
        nearest = difflib.get_close_matches(key.lower(), list(by_lower), n=1, cutoff=0.6)
        named.append(f"{key!r} (did you mean {by_lower[nearest[0]]!r}?)" if nearest else repr(key))
    raise SceneError(f"{where}: {section} has unknown key{'s' if len(unknown) > 1 else ''} {', '.join(named)}: "
                     f"the known ones are {', '.join(known)}")
