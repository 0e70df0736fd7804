"""The measured volumes of a phantom: one store per phantom, in the user's data directory.

Every scan of the phantom at a known pressure state (and every water-displacement measurement) is a measurement
of the gland volume the model predicts there. :class:`CorrectionStore` keeps them, one JSON file per phantom in the
user's data directory (``$PHANTOM_DATA_DIR``, else ``$XDG_DATA_HOME/phantom``, else ``~/.local/share/phantom``;
``corrections/NAME.json``), written atomically so that a kill or a full disk never leaves half a file, and
exports them as the measurements CSV ``phantom calibrate`` reads. The correction fitted to them is
:mod:`phantom.model.corrections`'s; this module reads no scans and fits nothing.
"""

from __future__ import annotations

import contextlib
import csv
import datetime
import fcntl
import io
import json
import math
import os
import re
from collections.abc import Iterator
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike

from phantom import PhantomError, read_text, written_atomically

#: The store's file format.
FORMAT = "phantom-corrections/1"
#: How a stored volume was measured.
METHODS = ("scan", "water_displacement")
#: The largest store read (bytes): thousands of measurements are far smaller.
MAX_STORE_BYTES = 16 * 2**20
#: A phantom's name in the store: a file name's safe characters.
NAME_PATTERN = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,63}")


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

    def __post_init__(self) -> None:
        pressures = self.pressures_kpa
        if not pressures or not all(_is_number(p) and p >= 0 for p in pressures):
            raise CorrectionError(f"a measurement's pressures must be finite numbers >= 0 kPa (gauge; the blowers "
                                  f"only push), got {list(pressures)}")
        if not (_is_number(self.volume_ml) and self.volume_ml > 0):
            raise CorrectionError(f"a measured volume must be a finite number of ml above 0, got {self.volume_ml!r}")
        if self.method not in METHODS:
            raise CorrectionError(f"a measurement's method is one of {', '.join(METHODS)}, got {self.method!r}")
        if self.model_volume_ml is not None and not (_is_number(self.model_volume_ml) and self.model_volume_ml > 0):
            raise CorrectionError(f"the model's volume must be a finite number of ml above 0, got "
                                  f"{self.model_volume_ml!r}")

    @classmethod
    def now(cls, pressures_kpa: ArrayLike, volume_ml: float, method: str = "scan", scan_file: str | None = None,
            model: str | None = None, model_volume_ml: float | None = None) -> Measurement:
        """A measurement taken now."""
        time_utc = datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds")
        return cls(tuple(float(p) for p in np.asarray(pressures_kpa, dtype=float).ravel()), float(volume_ml), method,
                   time_utc, scan_file, model, None if model_volume_ml is None else float(model_volume_ml))


def _is_number(value: object) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


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
            stat = self.path.stat()
        except FileNotFoundError:
            return None
        return stat.st_mtime_ns, stat.st_size, stat.st_ino

    def entries(self) -> list[Measurement]:
        """The stored measurements, oldest first ([] when there are none)."""
        if not self.path.exists():
            return []
        text = read_text(self.path, MAX_STORE_BYTES, "the correction store", CorrectionError)
        try:
            document = json.loads(text)
            if document.get("format") != FORMAT:
                raise ValueError(f"format {document.get('format')!r}, not {FORMAT!r}")
            return [Measurement(**{**entry, "pressures_kpa": tuple(entry["pressures_kpa"])})
                    for entry in document["measurements"]]
        except (ValueError, TypeError, KeyError, AttributeError, CorrectionError) as error:
            raise CorrectionError(f"the correction store {self.path} is damaged ({error}): move it aside (the "
                                  f"measurements in it are then no longer used) or restore it from a copy") from None

    def add(self, measurement: Measurement) -> int:
        """Store one more measurement (atomically); the number stored."""
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

    def to_csv(self) -> str:
        """The measurements as the CSV ``phantom calibrate`` reads (``p0_kpa, ..., measured_ml``, ``medium``: a
        water displacement's phantom hung in water), with ``method``, ``time_utc``, ``scan_file`` and
        ``model_ml`` (the model's volume there when stored) beside, which it ignores."""
        entries = self.entries()
        if not entries:
            raise CorrectionError(f"no measurements stored in {self.path}: nothing to export")
        out = io.StringIO()
        writer = csv.writer(out, lineterminator="\n")
        chambers = len(entries[0].pressures_kpa)
        writer.writerow([*(f"p{i}_kpa" for i in range(chambers)), "measured_ml", "medium", "method", "time_utc",
                         "scan_file", "model_ml"])
        for entry in entries:
            writer.writerow([*(f"{p:.6g}" for p in entry.pressures_kpa), f"{entry.volume_ml:.6g}",
                             "water" if entry.method == "water_displacement" else "air", entry.method,
                             entry.time_utc, entry.scan_file or "",
                             "" if entry.model_volume_ml is None else f"{entry.model_volume_ml:.6g}"])
        return out.getvalue()
