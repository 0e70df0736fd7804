"""The model's user-facing errors: each says what was wrong and what to do."""

import difflib
from collections.abc import Iterable, Mapping

from phantom import PhantomError


class SceneError(PhantomError):
    """A scene file that cannot be read or says something the model cannot do."""


class MeshError(PhantomError):
    """A mesh that cannot be generated, read, or used: missing groups, open walls, bad tetrahedra."""


class SolveError(PhantomError):
    """A solve that did not converge or inverted elements; the message names the chamber and pressure."""


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
