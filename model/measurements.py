"""The measured volumes of a phantom: one store per phantom, in the user's data directory.

Every scan of the phantom at a known pressure state (and every water-displacement measurement) is a measurement
of the gland volume the model predicts there. :class:`CorrectionStore` keeps them, one JSON file per phantom in the
user's data directory (``$PHANTOM_DATA_DIR``, else ``$XDG_DATA_HOME/phantom``, else ``~/.local/share/phantom``;
``corrections/NAME.json``), written atomically so that a kill or a full disk never leaves half a file, and
exports them as the measurements CSV ``phantom calibrate`` reads. The correction fitted to them is
:mod:`phantom.model.corrections`'s; this module reads no scans.

A measurement is checked before it is believed (:func:`plausibility`; ``phantom.model.corrections.judged``):
every path that stores a volume (``phantom corrections add``, ``phantom characterise``, the daemon's record of a
scan) compares it with the volume expected at its pressures, and one further from it than ``PLAUSIBLE_SIGMAS``
standard deviations (the expectation's 95 % half-width / 1.96) is stored *unconfirmed*, with the reason, and left
out of every fit (:meth:`CorrectionStore.confirmed`) until a person confirms it (``phantom corrections confirm
N``) or removes it (``remove N``). The expectation is the corrected model's where a correction is in force (its
95 % band), else the model's with its known error (``MODEL_ERROR_95_PCT``). The band is never narrower than
``MIN_HALF_WIDTH_PCT``.

The store is read defensively (a damaged store must never stop the daemon): a link, a pipe or a device in its
place is refused before it is opened, duplicate keys, wrong types and absurd numbers are refused with the field
named. One measured volume that is a number but no gland's (outside :data:`GLAND_VOLUME_RANGE_ML`: an older
version, or a hand edit, stored it) does not take the rest of the store with it: that entry is read *refused*,
with why, kept in the file and left out of every fit, until a person removes it (or corrects it by hand and
confirms it).
"""

from __future__ import annotations

import contextlib
import csv
import datetime
import fcntl
import io
import json
import os
import re
import stat
from collections.abc import Iterator
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from phantom import PhantomError, is_finite_number, read_text, unique_keys, written_atomically
from phantom.model.shape_file import GLAND_VOLUME_RANGE_ML

#: The store's file format.
FORMAT = "phantom-corrections/1"
#: How a stored volume was measured.
METHODS = ("scan", "water_displacement")
#: The largest store read (bytes): thousands of measurements are far smaller.
MAX_STORE_BYTES = 16 * 2**20
#: A phantom's name in the store: a file name's safe characters.
NAME_PATTERN = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,63}")
#: Whether a stored measurement is in the fit (``confirmed``), held out until a person confirms it
#: (``unconfirmed``), or held out because its volume is no gland's (``refused``: the store's reader gives it).
STATUSES = ("confirmed", "unconfirmed", "refused")
#: The largest model volume (ml) and pressure (kPa) a measurement may hold: far beyond any phantom (a prostate is
#: tens of ml; the blowers give a few kPa), far below what overflows a fit (1e300 ml crashed OSQP and the daemon).
#: The measured volume itself is a whole gland's (:data:`GLAND_VOLUME_RANGE_ML`).
MAX_VOLUME_ML = 10_000.0
MAX_PRESSURE_KPA = 1_000.0
#: The units a measured volume is mistaken for, and their size in ml: 40e-6 (m^3) was stored as 4e-05 ml and drew
#: the corrected gland to about 0 ml.
MISTAKEN_UNITS_ML = {"m^3": 1e6, "litres": 1e3, "mm^3": 1e-3}
#: The most chambers a measurement has pressures for.
MAX_CHAMBERS = 16
#: How many standard deviations from the expected volume a measured one may lie and still be believed (4: a true
#: measurement of a Gaussian error is held out once in 16 000; the red team's typo, 39.96 for 29.96 ml at 1,1,1
#: kPa, lies 6.5 of the model's own away).
PLAUSIBLE_SIGMAS = 4.0
#: The model's known error as a 95 % half-width (% of its volume), the band without a correction:
#: builtin:converged misses Table I's eight measurements by up to 10.03 % (at 2,0,0 kPa; 4.64 % on average) and
#: the simulated phantom's truth by up to 10.7 % over the pressure box.
MODEL_ERROR_95_PCT = 11.0
#: The narrowest 95 % half-width a volume is checked against (% of the volume): a scan's own error and a phantom's
#: drift between sessions, whatever a correction's leave-one-out says.
MIN_HALF_WIDTH_PCT = 2.0


class CorrectionError(PhantomError):
    """A bad measurement, a damaged store, or a correction the measurements cannot support."""


def data_dir() -> Path:
    """The user's data directory for the phantom (not a cache: nothing in it can be rebuilt)."""
    root = os.environ.get("PHANTOM_DATA_DIR")
    if root is None:
        root = os.path.join(os.environ.get("XDG_DATA_HOME", os.path.expanduser("~/.local/share")), "phantom")
    return Path(root)


@dataclass(frozen=True)
class Measurement:
    """One measured gland volume: when (UTC, ISO 8601), at which chamber pressures (kPa), how (``scan`` or
    ``water_displacement``), from which scan file, and the model it corrected with that model's volume there."""

    pressures_kpa: tuple[float, ...]
    volume_ml: float
    method: str = "scan"
    time_utc: str = ""
    scan_file: str | None = None
    model: str | None = None
    model_volume_ml: float | None = None
    #: ``confirmed`` (in the fit), ``unconfirmed`` (held out: ``reason`` says why, a person confirms it) or
    #: ``refused`` (held out: its volume is no gland's, ``reason`` says so; any other volume is refused outright)
    status: str = "confirmed"
    reason: str | None = None

    def __post_init__(self) -> None:
        pressures = self.pressures_kpa
        if not isinstance(pressures, tuple) or not 0 < len(pressures) <= MAX_CHAMBERS \
                or not all(is_finite_number(p) and 0 <= p <= MAX_PRESSURE_KPA for p in pressures):
            raise CorrectionError(f"a measurement's pressures must be finite numbers >= 0 kPa (gauge; the blowers "
                                  f"only push), at most {MAX_PRESSURE_KPA:g}, 1-{MAX_CHAMBERS} of them "
                                  f"(pressures_kpa), got "
                                  f"{_shown(list(pressures) if isinstance(pressures, tuple) else pressures)}")
        problem = gland_volume_problem(self.volume_ml)
        # a refused measurement holds the volume the store held, whatever it is, as long as it is a number
        if problem is not None and not (self.status == "refused" and is_finite_number(self.volume_ml)):
            raise CorrectionError(problem)
        if self.method not in METHODS:
            raise CorrectionError(f"a measurement's method is one of {', '.join(METHODS)}, got {_shown(self.method)}")
        if self.model_volume_ml is not None and not (is_finite_number(self.model_volume_ml)
                                                     and 0 < self.model_volume_ml <= MAX_VOLUME_ML):
            raise CorrectionError(f"the model's volume (model_volume_ml) must be a finite number of ml above 0 and "
                                  f"at most {MAX_VOLUME_ML:g}, got {_shown(self.model_volume_ml)}")
        for name in ("time_utc", "scan_file", "model", "reason"):
            value = getattr(self, name)
            if not (isinstance(value, str) and len(value) <= 4096) and not (value is None and name != "time_utc"):
                raise CorrectionError(f"a measurement's {name} must be text (at most 4096 characters)"
                                      f"{'' if name == 'time_utc' else ' or null'}, got {_shown(value)}")
        if self.status not in STATUSES:
            raise CorrectionError(f"a measurement's status is one of {', '.join(STATUSES)}, got {_shown(self.status)}")
        if self.status == "refused" and not self.reason:
            raise CorrectionError("a refused measurement says why it is refused (reason)")

    @classmethod
    def now(cls, pressures_kpa: ArrayLike, volume_ml: float, method: str = "scan", scan_file: str | None = None,
            model: str | None = None, model_volume_ml: float | None = None) -> Measurement:
        """A measurement taken now."""
        time_utc = datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds")
        return cls(tuple(float(p) for p in np.asarray(pressures_kpa, dtype=float).ravel()), float(volume_ml), method,
                   time_utc, scan_file, model, None if model_volume_ml is None else float(model_volume_ml))


def _check_chambers(entries: list[Measurement]) -> None:
    """Refuse the last of a phantom's measurements when it has another number of pressures (one per chamber) than
    the first: a store of two phantoms' exported misaligned rows and could not be fitted."""
    first, last = len(entries[0].pressures_kpa), len(entries[-1].pressures_kpa)
    if last != first:
        raise ValueError(f"it has {last} pressures, measurement 1 has {first}: a phantom's measurements have one "
                         f"per chamber; is it another phantom's?")


def is_gland_volume(volume: object) -> bool:
    """Whether a measured volume (ml) is a whole gland's: a finite number within :data:`GLAND_VOLUME_RANGE_ML`."""
    low, high = GLAND_VOLUME_RANGE_ML
    return is_finite_number(volume) and low <= volume <= high


def gland_volume_problem(volume: object, named: str = "a measured volume (volume_ml)") -> str | None:
    """What is wrong with a measured volume (ml), the input ``named`` (the store's field, a CSV column, a flag);
    None when it is a whole gland's (:func:`is_gland_volume`). One wording wherever a measured volume comes in."""
    if is_gland_volume(volume):
        return None
    low, high = GLAND_VOLUME_RANGE_ML
    return (f"{named} must be a whole gland's volume, a finite number of ml within {low:g}-{high:g} ml"
            f"{unit_hint(volume)}")


def _read_entry(entry: dict[str, Any]) -> Measurement:
    """A stored entry as a measurement: one whose volume is a number but no gland's is ``refused``, saying why (its
    stored status and reason give way: no fit may use it, whatever a person said of it before)."""
    fields = {**entry, "pressures_kpa": tuple(entry["pressures_kpa"])}
    problem = gland_volume_problem(entry.get("volume_ml"))
    if problem is not None and is_finite_number(entry.get("volume_ml")):
        fields |= {"status": "refused", "reason": f"read as {entry['volume_ml']:g} ml: {problem}; left out of every "
                                                  f"fit (an older version or a hand edit stored it)"}
    return Measurement(**fields)


def unit_hint(volume: object) -> str:
    """The end of the message for a volume outside a gland's range: ``: in ml? got 4e-05, which is 40 ml in m^3:
    convert it`` where another unit (:data:`MISTAKEN_UNITS_ML`) makes it a gland's, else ``, got VALUE``."""
    low, high = GLAND_VOLUME_RANGE_ML
    for unit, ml_per_unit in MISTAKEN_UNITS_ML.items():
        if is_finite_number(volume) and low <= volume * ml_per_unit <= high:
            return f": in ml? got {volume:g}, which is {volume * ml_per_unit:g} ml in {unit}: convert it"
    return f", got {_shown(volume)}"


def _shown(value: object) -> str:
    """A value for a message, cut short (a store may hold anything)."""
    text = repr(value)
    return text if len(text) <= 80 else text[:77] + "..."


# ----------------------------------------------------------------------------------------------- plausibility
@dataclass(frozen=True)
class Verdict:
    """Whether a measured volume is believed, and when not, why (for the store's ``reason`` and the user)."""

    plausible: bool
    reason: str = ""


def plausibility(volume_ml: float, expected_ml: float, half_width_95_ml: float, basis: str,
                 sigmas: float = PLAUSIBLE_SIGMAS) -> Verdict:
    """Whether ``volume_ml`` is within ``sigmas`` standard deviations of ``expected_ml``, whose 95 % half-width is
    ``half_width_95_ml`` (a standard deviation is it / 1.96); ``basis`` names where the expectation came from.

    Raises
    ------
    CorrectionError
        A half-width that is not a finite number above 0.
    """
    if not (is_finite_number(half_width_95_ml) and half_width_95_ml > 0) or not is_finite_number(expected_ml):
        raise CorrectionError(f"an expected volume needs a finite half-width above 0 ml, got {expected_ml!r} +- "
                              f"{half_width_95_ml!r}")
    sigma_ml = half_width_95_ml / 1.96
    miss_ml = volume_ml - expected_ml
    if abs(miss_ml) <= sigmas * sigma_ml:
        return Verdict(True)
    return Verdict(False, f"{volume_ml:.3f} ml is {miss_ml:+.3f} ml ({miss_ml / expected_ml * 100:+.1f} %) from the "
                          f"expected {expected_ml:.3f} ml +- {half_width_95_ml:.3f} (95 %) of {basis}: "
                          f"{abs(miss_ml) / sigma_ml:.1f} standard deviations, more than {sigmas:g}")


def expectation(pressures_kpa: ArrayLike, model_ml: float, corrected: Any | None = None,
                model_name: str = "the model") -> tuple[float, float, str]:
    """The volume expected at these pressures (ml), its 95 % half-width (ml) and where it came from.

    ``model_ml`` is the model's own volume there; ``corrected`` the corrected model in force (a
    ``phantom.model.corrections.CorrectedModel``; None: none). With a correction: its band (``judging_band_ml(
    pressures, model_half_width_ml) -> (mean, half-width)``, the Gaussian process's 95 %, as wide as the model's
    own known error away from the measurements). Without: the model's volume and ``MODEL_ERROR_95_PCT``. Never
    narrower than ``MIN_HALF_WIDTH_PCT``.
    """
    pressures = np.asarray(pressures_kpa, dtype=float)
    if corrected is None:
        expected, half_width, basis = model_ml, model_ml * MODEL_ERROR_95_PCT / 100, \
            f"{model_name} (its known error, {MODEL_ERROR_95_PCT:g} %)"
    else:
        expected, half_width = corrected.judging_band_ml(pressures, model_ml * MODEL_ERROR_95_PCT / 100)
        basis = f"the correction in force ({corrected.describe()})"
    return expected, max(half_width, expected * MIN_HALF_WIDTH_PCT / 100), basis


class CorrectionStore:
    """The measurements of one phantom, in ``path`` (see the module docstring)."""

    def __init__(self, path: str | Path):
        self.path = Path(path)

    @classmethod
    def for_phantom(cls, name: str = "default", root: str | Path | None = None) -> CorrectionStore:
        """The store of the phantom called ``name`` under ``root`` (default :func:`data_dir`)."""
        if not NAME_PATTERN.fullmatch(name):
            raise CorrectionError(f"a phantom's name is 1-64 letters, digits, '.', '_' or '-', starting with a letter "
                                  f"or digit, got {name!r}")
        return cls(Path(root if root is not None else data_dir()) / "corrections" / f"{name}.json")

    def signature(self) -> tuple[int, int, int] | None:
        """The file's modification time (ns), size and inode, None while there is none: a cheap check (one stat)
        of whether any writer changed the store since it was last read (every write replaces the file)."""
        try:
            info = self.path.stat()
        except FileNotFoundError:
            return None
        except OSError:  # unreadable (a folder without permission): the read says why, the daemon goes on
            return -1, -1, -1
        return info.st_mtime_ns, info.st_size, info.st_ino

    def entries(self) -> list[Measurement]:
        """The stored measurements, oldest first ([] when there are none).

        An entry whose volume is a number but no gland's is read ``refused`` (its reason says why), not as damage.

        Raises
        ------
        CorrectionError
            A store that is a link (another phantom's store would be merged into this one at the next write), not
            a regular file (a pipe would hang the reader: refused without being opened), too large, not UTF-8, or
            damaged (its message names the entry and the field).
        """
        text = self._text()
        if text is None:
            return []
        try:
            document = json.loads(text, object_pairs_hook=unique_keys)
            if not isinstance(document, dict) or document.get("format") != FORMAT:
                raise ValueError(f"format {document.get('format') if isinstance(document, dict) else None!r}, not "
                                 f"{FORMAT!r}")
            stored = document.get("measurements")
            if not isinstance(stored, list):
                raise ValueError(f"measurements is not a list but {type(stored).__name__}")
            entries = []
            for number, entry in enumerate(stored, start=1):
                try:
                    if not isinstance(entry, dict) or not isinstance(entry.get("pressures_kpa"), list):
                        raise ValueError("not an object with a list pressures_kpa")
                    entries.append(_read_entry(entry))
                    _check_chambers(entries)
                except (ValueError, TypeError, CorrectionError) as error:
                    raise ValueError(f"measurement {number}: {error}") from None
            return entries
        except (ValueError, TypeError, KeyError, AttributeError, RecursionError, CorrectionError) as error:
            raise CorrectionError(f"the correction store {self.path} is damaged ({error}): move it aside (the "
                                  f"measurements in it are then no longer used) or restore it from a copy") from None

    def _text(self) -> str | None:
        """The store's text (None: no store), refused unread when it is a link or not a regular file."""
        try:
            info = os.lstat(self.path)
        except FileNotFoundError:
            return None
        except OSError as error:
            raise CorrectionError(f"the correction store {self.path} cannot be read: {error.strerror}") from None
        if stat.S_ISLNK(info.st_mode):
            raise CorrectionError(f"the correction store {self.path} is a link (to {os.readlink(self.path)}): each "
                                  f"phantom's store is its own file (a link to another's would merge them); replace "
                                  f"it by a copy, or use that phantom's name")
        if not stat.S_ISREG(info.st_mode):
            raise CorrectionError(f"the correction store {self.path} is not a regular file (a pipe or a device): "
                                  f"move it aside")
        return read_text(self.path, MAX_STORE_BYTES, "the correction store", CorrectionError)

    def confirmed(self) -> list[Measurement]:
        """The stored measurements a fit uses: every one but those held unconfirmed or refused."""
        return [entry for entry in self.entries() if entry.status == "confirmed"]

    def confirm(self, number: int) -> Measurement:
        """Confirm measurement ``number`` (1 = the oldest, as listed): a person says it is right; it. CorrectionError
        for one whose volume is no gland's: no word of a person makes it one."""
        with self._locked():
            entries = self.entries()
            self._check_number(number, entries)
            if gland_volume_problem(entries[number - 1].volume_ml) is not None:
                raise CorrectionError(f"measurement {number} cannot be confirmed: {entries[number - 1].reason}. "
                                      f"Remove it (`phantom corrections remove {number}`) and add the volume again "
                                      f"in ml")
            entries[number - 1] = replace(entries[number - 1], status="confirmed", reason=None)
            self._write(entries)
            return entries[number - 1]

    def remove(self, number: int) -> Measurement:
        """Remove measurement ``number`` (1 = the oldest, as listed); the one removed."""
        with self._locked():
            entries = self.entries()
            self._check_number(number, entries)
            removed = entries.pop(number - 1)
            self._write(entries)
            return removed

    def _check_number(self, number: int, entries: list[Measurement]) -> None:
        if not 1 <= number <= len(entries):
            raise CorrectionError(f"no measurement {number}: phantom {self.path.stem!r} has {len(entries)} "
                                  f"(`phantom corrections list`)")

    def add(self, measurement: Measurement) -> int:
        """Store one more measurement (atomically) as it is given, confirmed unless its ``status`` says otherwise;
        the number stored. It judges nothing: a library user calls :func:`phantom.model.corrections.judged` first,
        which holds an implausible volume unconfirmed, out of every fit (as ``phantom corrections add``, ``phantom
        characterise`` and the daemon do); a volume added without it is in the next fit whatever it is."""
        with self._locked():
            return self._add(measurement)

    def _add(self, measurement: Measurement) -> int:
        entries = self.entries()
        if entries and len(entries[0].pressures_kpa) != len(measurement.pressures_kpa):
            raise CorrectionError(f"this phantom's measurements have {len(entries[0].pressures_kpa)} pressures, this "
                                  f"one {len(measurement.pressures_kpa)}: is it another phantom? give another name")
        entries.append(measurement)
        self._write(entries)
        return len(entries)

    def clear(self) -> int:
        """Remove every measurement; how many there were."""
        with self._locked():
            count = len(self.entries())
            if self.path.exists():
                self._write([])
            return count

    @contextlib.contextmanager
    def _locked(self) -> Iterator[None]:
        """One writer at a time (the daemon and a `phantom corrections` command may both add: each reads, appends
        and writes the whole file, so two at once would lose one's measurement). Under the lock no other writer is
        mid-write, so a temporary file beside the store is one a killed writer left: it is removed."""
        self.path.parent.mkdir(parents=True, exist_ok=True)
        with open(self.path.with_name(self.path.name + ".lock"), "a") as lock:
            fcntl.flock(lock, fcntl.LOCK_EX)
            for stale in self.path.parent.glob(f".{self.path.stem}.*{self.path.suffix}"):
                stale.unlink(missing_ok=True)
            yield

    def _write(self, entries: list[Measurement]) -> None:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        document = {"format": FORMAT, "measurements": [asdict(entry) | {"pressures_kpa": list(entry.pressures_kpa)}
                                                       for entry in entries]}
        with written_atomically(self.path, CorrectionError) as temporary:
            temporary.write_text(json.dumps(document, indent=1) + "\n")

    def to_csv(self, entries: list[Measurement] | None = None) -> str:
        """The measurements as the CSV ``phantom calibrate`` reads (``p0_kpa, ..., measured_ml``, ``medium``: a
        water displacement's phantom hung in water), with ``method``, ``time_utc``, ``scan_file`` and
        ``model_ml`` (the model's volume there when stored) beside, which it ignores. An unconfirmed measurement is
        a ``#`` line (a comment to calibrate) saying why, and so is a refused one: left out of calibrate's fit as
        out of every other, and kept in the copy. ``entries``: the measurements as read already (default: the
        store's now)."""
        entries = self.entries() if entries is None else entries
        if not entries:
            raise CorrectionError(f"no measurements stored in {self.path}: nothing to export")
        out = io.StringIO()
        writer = csv.writer(out, lineterminator="\n")
        chambers = len(entries[0].pressures_kpa)
        writer.writerow([*(f"p{i}_kpa" for i in range(chambers)), "measured_ml", "medium", "method", "time_utc",
                         "scan_file", "model_ml"])
        for number, entry in enumerate(entries, start=1):
            row = [*(f"{p:.6g}" for p in entry.pressures_kpa), f"{entry.volume_ml:.6g}",
                   "water" if entry.method == "water_displacement" else "air", entry.method, entry.time_utc,
                   entry.scan_file or "", "" if entry.model_volume_ml is None else f"{entry.model_volume_ml:.6g}"]
            if entry.status != "confirmed":
                out.write(f"# measurement {number} {entry.status} ({entry.reason or 'not confirmed'}), left out: ")
            writer.writerow(row)
        return out.getvalue()
