"""A phantom characterised by its own scans: the pressure states to visit, the run's record, and its report.

``phantom characterise`` (phantom/cli/characterise.py) sets each pressure state of a design through the running
daemon, scans the phantom there, reconstructs the scan and stores the scanned gland volume as a measurement
(``phantom.model.corrections``); then fits the model's correction to them and writes a report. This module holds
what needs no daemon:

- the design: :func:`path_design` (rest and the states the model's inverse gives for volumes evenly across its
  range: where volume targets are set, and where a correction is asked), :func:`grid_design` (the product of
  given pressures on every chamber) and :func:`space_filling_design` (a Latin hypercube of N states in the
  pressure box, optimised for its centred discrepancy, scipy's ``LatinHypercube(optimization="random-cd")``), the
  last two visited in the order of :func:`short_path` (nearest neighbour from rest: the blowers change as little
  as they can between states);
- :class:`CharacterisationRecord`: ``DIR/characterisation.json``, the design, the scan plan and each finished
  point, written atomically after every step, so that a stopped run resumes where it stopped: a finished point is
  never scanned again, and a point is finished only once its scan is reconstructed and its measurement written;
  a point is stored in the phantom's CorrectionStore after it is recorded (``stored``), and a run resumed after a
  stop between the two stores it then;
- :func:`write_report`: ``report.md`` (per point the model, the corrected model, the scan and on the simulated
  rig the truth; each correction kind's leave-one-out error) and ``report.png`` (the volumes against pressure).
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike

from phantom import PhantomError, read_text, require_extra, unique_keys, written_atomically
from phantom.model.corrections import CorrectedModel, Correction, ModelGrid, fit_correction
from phantom.model.measurements import Measurement

if TYPE_CHECKING:
    from phantom.scan.camera import Rig
    from phantom.scan.capture import CaptureFolder

#: The record's file format, and its name in the run's folder.
FORMAT = "phantom-characterisation/1"
RECORD_NAME = "characterisation.json"
#: The most pressure states one run visits (a 10^3 grid; each takes a scan of a minute or more).
MAX_POINTS = 1000
#: The fewest: a correction's leave-one-out needs two.
MIN_POINTS = 2
#: Pressures are rounded to this (kPa): a tenth of the sensor's ADC count, so a design prints as it is set.
PRESSURE_STEP_KPA = 0.001
#: How many of the inverse's answers measure its path's length (:func:`path_design`; 14 ms each on the table).
PATH_SAMPLES = 100
#: The largest record read (bytes).
MAX_RECORD_BYTES = 16 * 2**20


class CharacterisationError(PhantomError):
    """A bad design, a record that does not match the run asked for, or a damaged record."""


# ----------------------------------------------------------------------------------------------- the design
def grid_design(values_kpa: Sequence[float], pressure_max_kpa: float, chambers: int = 3) -> np.ndarray:
    """Every combination of ``values_kpa`` on the ``chambers`` chambers ((n^chambers, chambers) kPa), in the order
    of :func:`short_path`. CharacterisationError for values outside 0..``pressure_max_kpa``, repeated or too many."""
    values = np.asarray(values_kpa, dtype=float).ravel()
    _check_box(pressure_max_kpa, chambers)
    if values.size == 0 or not np.all(np.isfinite(values)):
        raise CharacterisationError(f"--grid needs finite pressures (kPa), got {list(values_kpa)}")
    if np.any(values < 0) or np.any(values > pressure_max_kpa + 1e-9):
        raise CharacterisationError(f"--grid's pressures must lie in the daemon's pressure box, 0 to "
                                    f"{pressure_max_kpa:g} kPa, got {', '.join(f'{v:g}' for v in values)}")
    if len(np.unique(values)) != len(values):
        raise CharacterisationError(f"--grid's pressures must differ, got {', '.join(f'{v:g}' for v in values)}")
    count = len(values) ** chambers
    if not MIN_POINTS <= count <= MAX_POINTS:
        raise CharacterisationError(f"--grid of {len(values)} pressures on {chambers} chambers is {count} states: "
                                    f"give {MIN_POINTS} to {MAX_POINTS}")
    points = np.stack(np.meshgrid(*[np.sort(values)] * chambers, indexing="ij"), -1).reshape(-1, chambers)
    return short_path(points)


def space_filling_design(count: int, pressure_max_kpa: float, chambers: int = 3, seed: int = 0) -> np.ndarray:
    """``count`` pressure states ((count, chambers) kPa) filling the box 0..``pressure_max_kpa`` on every chamber:
    a Latin hypercube (each chamber's pressures one in each of ``count`` equal slices) whose centred discrepancy
    scipy has lowered by swapping (``LatinHypercube(optimization="random-cd")``, ``seed``), in the order of
    :func:`short_path`."""
    from scipy.stats import qmc

    _check_box(pressure_max_kpa, chambers)
    if isinstance(count, bool) or not isinstance(count, int) or not MIN_POINTS <= count <= MAX_POINTS:
        raise CharacterisationError(f"--points must be a whole number from {MIN_POINTS} to {MAX_POINTS}, got "
                                    f"{count!r}")
    unit = qmc.LatinHypercube(d=chambers, optimization="random-cd", seed=seed).random(count)
    return short_path(np.round(unit * pressure_max_kpa / PRESSURE_STEP_KPA) * PRESSURE_STEP_KPA)


def path_design(count: int, inverse_kpa: Callable[[float], np.ndarray], rest_ml: float, top_ml: float,
                samples: int = PATH_SAMPLES) -> np.ndarray:
    """``count`` pressure states ((count, chambers) kPa) along the inverse's path, from rest to the top, in that
    order: rest, then the pressures ``inverse_kpa`` (the model's own inverse: volume in ml -> pressures in kPa)
    gives for ``count - 1`` gland volumes between rest (``rest_ml``) and the model's top (``top_ml``, every
    chamber at the box's top), spaced evenly along the path's length in kPa (measured through ``samples``
    answers), not its volume: the model grows slowly near rest, so equal steps of its volume leave the first
    kPa, where the phantom departs from it most, with one state.

    Every volume target is set on this path, the corrected ones too (a correction asks the model's inverse for
    another volume: ``CorrectedModel.pressures_for_ml``), so scans along it measure the
    phantom where it is asked to be (bench/README.md, "Characterisation": perfect scans of the simulated phantom
    at these states put targets between them within 0.5 % of its true volume; the 27 states of the grid 0, 1.5,
    3 kPa missed by up to 2.8 %)."""
    if isinstance(count, bool) or not isinstance(count, int) or not MIN_POINTS <= count <= MAX_POINTS:
        raise CharacterisationError(f"--path must be a whole number from {MIN_POINTS} to {MAX_POINTS}, got "
                                    f"{count!r}")
    if not (math.isfinite(rest_ml) and math.isfinite(top_ml) and 0 < rest_ml < top_ml):
        raise CharacterisationError(f"the model's volumes must grow from rest to the top of its box, got {rest_ml!r} "
                                    f"to {top_ml!r} ml")
    volumes = rest_ml + (top_ml - rest_ml) * np.arange(1, max(samples, count)) / (max(samples, count) - 1)
    path = np.array([np.asarray(inverse_kpa(float(volume)), dtype=float) for volume in volumes])
    path = np.vstack([np.zeros(path.shape[1]), path])
    length = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(path, axis=0), axis=1))])
    asked = np.interp(length[-1] * np.arange(1, count) / (count - 1), length, np.concatenate([[rest_ml], volumes]))
    points = [path[0]] + [np.asarray(inverse_kpa(float(volume)), dtype=float) for volume in asked]
    return np.clip(np.round(np.array(points) / PRESSURE_STEP_KPA) * PRESSURE_STEP_KPA, 0.0, None)


def _check_box(pressure_max_kpa: float, chambers: int) -> None:
    if not (math.isfinite(pressure_max_kpa) and pressure_max_kpa > 0):
        raise CharacterisationError(f"the pressure box's top must be a positive number of kPa, got "
                                    f"{pressure_max_kpa!r}")
    if chambers < 1:
        raise CharacterisationError(f"a phantom has at least one chamber, got {chambers}")


def short_path(points_kpa: ArrayLike) -> np.ndarray:
    """The points in the order of a short path: from the one nearest rest, each time the nearest not visited
    (ties to the first): the pressures change little between points, so each settles fast."""
    points = np.asarray(points_kpa, dtype=float)
    left = list(range(len(points)))
    here = np.zeros(points.shape[1])
    order = []
    while left:
        distances = [float(np.abs(points[i] - here).sum()) for i in left]
        nearest = left.pop(int(np.argmin(distances)))
        order.append(nearest)
        here = points[nearest]
    return points[order]


# ----------------------------------------------------------------------------------------------- the record
@dataclass
class PointResult:
    """One finished point: the pressures asked and measured (kPa, the mean over the scan's pictures), the scanned
    gland volume (ml), the model's there (ml), the simulated phantom's true volume (ml, None on a real board), the
    scan's folder, when (UTC), how long it took (s), and whether it is in the phantom's CorrectionStore yet."""

    index: int
    asked_kpa: list[float]
    pressures_kpa: list[float]
    volume_ml: float
    model_ml: float
    scan_folder: str
    time_utc: str
    seconds: float
    true_ml: float | None = None
    stored: bool = False
    #: the visual hull's error on the model's shape at the pressures (%), taken off ``volume_ml``; None: not taken
    #: off (a record from before it was, or the model's surface fit no motion onto the scan)
    hull_error_pct: float | None = None

    def measurement(self, model: str) -> Measurement:
        return Measurement(tuple(self.pressures_kpa), self.volume_ml, "scan", self.time_utc, self.scan_folder,
                           model, self.model_ml)


@dataclass
class CharacterisationRecord:
    """``DIR/characterisation.json`` (see the module docstring): the phantom's name, the model (scene), the
    design (``{"kind": "grid", "values_kpa": [...]}`` or ``{"kind": "points", "count": N, "seed": S}``), the
    pressure box, the points in the order visited, the scan's parameters, the rig, the finished points, the
    skipped ones (index -> why: not reached, refused), and the elapsed time of each session of the run."""

    folder: Path
    phantom: str
    model: str
    design: dict[str, Any]
    pressure_max_kpa: float
    points_kpa: list[list[float]]
    scan: dict[str, Any]
    rig: str
    results: list[PointResult] = field(default_factory=list)
    skipped: dict[int, str] = field(default_factory=dict)
    sessions: list[dict[str, Any]] = field(default_factory=list)

    @property
    def path(self) -> Path:
        return self.folder / RECORD_NAME

    @classmethod
    def exists(cls, folder: str | Path) -> bool:
        return (Path(folder) / RECORD_NAME).exists()

    def done(self) -> set[int]:
        return {result.index for result in self.results}

    def pending(self) -> list[int]:
        """The points not finished, in the order visited (the skipped ones too: they are tried again)."""
        done = self.done()
        return [index for index in range(len(self.points_kpa)) if index not in done]

    def scan_folder(self, index: int) -> Path:
        return self.folder / "scans" / f"{index:03d}"

    def finish(self, result: PointResult) -> None:
        """Record a finished point (not yet stored in the phantom's CorrectionStore) and save."""
        if result.index in self.done():
            raise CharacterisationError(f"point {result.index} is finished already: it is not scanned twice")
        self.results.append(result)
        self.skipped.pop(result.index, None)
        self.save()

    def mark_stored(self, index: int) -> None:
        for result in self.results:
            if result.index == index:
                result.stored = True
        self.save()

    def forget(self, index: int) -> None:
        """Take a finished point back to pending (its row refused on resume: it is scanned again) and save."""
        self.results = [result for result in self.results if result.index != index]
        self.save()

    def skip(self, index: int, why: str) -> None:
        self.skipped[index] = why
        self.save()

    def measurements(self) -> list[Measurement]:
        return [result.measurement(self.model) for result in self.results]

    def to_json(self) -> dict[str, Any]:
        return {"format": FORMAT, "phantom": self.phantom, "model": self.model, "design": self.design,
                "pressure_max_kpa": self.pressure_max_kpa, "points_kpa": self.points_kpa, "scan": self.scan,
                "rig": self.rig, "results": [asdict(result) for result in self.results],
                "skipped": {str(index): why for index, why in sorted(self.skipped.items())},
                "sessions": self.sessions}

    def save(self) -> Path:
        self.folder.mkdir(parents=True, exist_ok=True)
        with written_atomically(self.path, CharacterisationError) as temporary:
            temporary.write_text(json.dumps(self.to_json(), indent=1) + "\n")
        return self.path

    @classmethod
    def load(cls, folder: str | Path) -> CharacterisationRecord:
        """The record in ``folder``; CharacterisationError when there is none or it is damaged."""
        folder = Path(folder)
        path = folder / RECORD_NAME
        if not path.exists():
            raise CharacterisationError(f"{folder} holds no characterisation ({RECORD_NAME}) to resume: start one "
                                        f"with --grid or --points")
        text = read_text(path, MAX_RECORD_BYTES, "the characterisation record", CharacterisationError)
        try:
            document = json.loads(text, object_pairs_hook=unique_keys)
            if document.get("format") != FORMAT:
                raise ValueError(f"format {document.get('format')!r}, not {FORMAT!r}")
            record = cls(folder, str(document["phantom"]), str(document["model"]), dict(document["design"]),
                         float(document["pressure_max_kpa"]),
                         [[float(p) for p in point] for point in document["points_kpa"]], dict(document["scan"]),
                         str(document["rig"]), [PointResult(**entry) for entry in document["results"]],
                         {int(index): str(why) for index, why in document["skipped"].items()},
                         list(document.get("sessions", [])))
            _check_design(record.design)
            for result in record.results:
                if not 0 <= result.index < len(record.points_kpa):
                    raise ValueError(f"a result for point {result.index} of {len(record.points_kpa)}")
                result.measurement(record.model)  # its numbers are checked as a measurement's
                if not np.allclose(result.asked_kpa, record.points_kpa[result.index], atol=PRESSURE_STEP_KPA):
                    raise ValueError(f"point {result.index} was asked at {result.asked_kpa} kPa, not the design's "
                                     f"{record.points_kpa[result.index]}")
        except (ValueError, TypeError, KeyError, AttributeError, PhantomError) as error:
            raise CharacterisationError(f"the characterisation record {path} is damaged ({error}): start the run "
                                        f"again in another folder") from None
        if len(record.done()) != len(record.results):
            raise CharacterisationError(f"the characterisation record {path} is damaged (a point finished twice): "
                                        f"start the run again in another folder")
        return record


def _check_design(design: dict[str, Any]) -> None:
    """A record's design holds the keys its kind needs, of the right types (ValueError: why)."""
    kind = design.get("kind")
    needs = {"grid": ("values_kpa",), "path": ("count",), "points": ("count", "seed")}
    if kind not in needs:
        raise ValueError(f"the design's kind is one of {', '.join(needs)}, got {kind!r:.40}")
    for key in needs[kind]:
        if key not in design:
            raise ValueError(f"the {kind} design has no {key}")
    values = design.get("values_kpa", [])
    if not isinstance(values, list) or not all(isinstance(v, (int, float)) and math.isfinite(v) for v in values):
        raise ValueError(f"the design's values_kpa must be a list of numbers (kPa), got {values!r:.60}")
    for key in ("count", "seed"):
        if key in design and (not isinstance(design[key], int) or isinstance(design[key], bool)):
            raise ValueError(f"the design's {key} must be a whole number, got {design[key]!r:.40}")


#: How far a stored row's volume may be from its scan reconstructed again (relative): the same pictures, rig and
#: voxel give the same carving; this is rounding.
RESCAN_TOLERANCE = 1e-4


def verified_row(record: CharacterisationRecord, result: PointResult, grid: ModelGrid,
                 confirmed: list[Measurement], volume_of: Callable[[Path], float]) -> Measurement:
    """The measurement a row finished but not stored gives, once verified: its scan folder is this run's and
    holds a scan (``volume_of(folder)``: its volume reconstructed again, ml; CharacterisationError or a
    PhantomError when it is no scan) whose volume is the row's; judged plausible or not against the model
    corrected by the ``confirmed`` measurements (:func:`phantom.model.corrections.judged`: an implausible one is
    stored unconfirmed).

    Raises
    ------
    CharacterisationError
        The row is refused (why): no scan folder, another volume than its scan's, or no scan there.
    """
    from phantom.model.corrections import judged

    folder = record.scan_folder(result.index)
    if not folder.is_dir():
        raise CharacterisationError(f"point {result.index}: not stored: no scan folder {folder} (the record says "
                                    f"{result.volume_ml:.3f} ml)")
    try:
        scanned_ml = float(volume_of(folder))
    except PhantomError as error:
        raise CharacterisationError(f"point {result.index}: not stored: its scan in {folder} cannot be "
                                    f"reconstructed ({error})") from None
    if not math.isclose(scanned_ml, result.volume_ml, rel_tol=RESCAN_TOLERANCE):
        raise CharacterisationError(f"point {result.index}: not stored: the record says {result.volume_ml:.3f} ml, "
                                    f"its scan in {folder} {scanned_ml:.3f} ml")
    return judged(result.measurement(record.model), grid, confirmed, record.model)


def check_same_folder(record: CharacterisationRecord) -> None:
    """Refuse a record whose rows' scans are not in its own folder: a record copied from another run."""
    for result in record.results:
        own = record.scan_folder(result.index).resolve()
        if Path(result.scan_folder).resolve() != own:
            raise CharacterisationError(f"{record.path}: point {result.index}'s scan is in {result.scan_folder}, not "
                                        f"this run's {own}: the record is from another run (copied or moved?): "
                                        f"start the run again in another folder, or resume it where it was made")


def held_pressures_kpa(frames_kpa: Sequence[Sequence[float]]) -> list[float]:
    """The pressures a scan was taken at (kPa): the mean over its pictures, a chamber's noise about 0 kPa at rest
    (a mean of -0.001 kPa) read as 0: the blowers only push, and a measurement's pressures are gauge, >= 0."""
    pressures = np.asarray(frames_kpa, dtype=float)
    if pressures.ndim != 2 or len(pressures) == 0 or not np.all(np.isfinite(pressures)):
        raise CharacterisationError(f"a scan's pictures need finite measured pressures, got {pressures.shape}")
    return [float(p) for p in np.clip(pressures.mean(axis=0), 0.0, None)]


def scan_params(record: CharacterisationRecord, index: int, folder: Path) -> dict[str, Any]:
    """The daemon's ``scan`` params for point ``index`` into ``folder``: the run's plan, the rig kept with the run,
    the camera (none named: the daemon's own, its --camera on a real board, else the virtual one, whose picture
    size is the run's scale; a real camera's size is the rig's)."""
    scan = record.scan
    params: dict[str, Any] = {"out": str(folder.resolve()), "views": scan["views"],
                              "elevations_deg": scan["elevations_deg"], "settle_s": scan["settle_s"],
                              "seed": scan["seed"] + index, "rig": str((record.folder / record.rig).resolve())}
    camera = scan["camera"]
    if camera is not None:
        params["camera"] = int(camera) if str(camera).isdigit() else camera
    if camera in ("virtual", None):
        params["scale"] = scan["scale"]
    return params


def measured_point(record: CharacterisationRecord, index: int, folder: Path, rig: Rig, grid: ModelGrid,
                   time_utc: str, seconds: float, true_ml: float | None, label: str,
                   model_surface_at: SurfaceAt | None = None) -> PointResult:
    """Point ``index`` from its scan's capture ``folder``: complete, every picture with its measured pressures
    (held: their mean), reconstructed with ``rig`` at the run's voxel (:func:`scanned_ml`); the model's volume
    there from ``grid``. CharacterisationError (saying that ``--resume`` scans it again) for a scan that cannot
    be stored."""
    from phantom.scan.capture import CaptureFolder

    capture = CaptureFolder.open(folder)
    if capture.status != "complete":
        raise CharacterisationError(f"{label}: the scan ended {capture.status}, not complete; the point is not "
                                    f"stored: --resume scans it again")
    measured = [frame.pressures_kpa for frame in capture.frames if frame.pressures_kpa is not None]
    if len(measured) != len(capture.frames):
        raise CharacterisationError(f"{label}: {len(capture.frames) - len(measured)} of the scan's pictures have no "
                                    f"measured pressures: the point is not stored (--resume scans it again)")
    pressures = held_pressures_kpa(measured)
    volume_ml, hull_error_pct = scanned_ml(capture, rig, record.scan["voxel_mm"], pressures, model_surface_at)
    return PointResult(index, list(record.points_kpa[index]), pressures, volume_ml,
                       grid.gland_ml(np.asarray(pressures)), str(folder.resolve()), time_utc, seconds, true_ml,
                       hull_error_pct=hull_error_pct)


#: The model's outer surface at pressures (kPa): positions (mm) and triangles.
SurfaceAt = Callable[[list[float]], tuple[Any, Any]]


def scanned_ml(capture: CaptureFolder, rig: Rig, voxel_mm: float, pressures_kpa: list[float],
               model_surface_at: SurfaceAt | None) -> tuple[float, float | None]:
    """A complete capture's gland volume (ml) reconstructed at ``voxel_mm``, with the visual hull's error on the
    model's surface at ``pressures_kpa`` taken off (``phantom.scan.hull_bias``, as a verified round's scan), and
    that error (%; None: no surface, or it fit no motion onto the scan: the hull's volume as it is)."""
    from phantom.scan.hull_bias import measured_hull_bias
    from phantom.scan.reconstruct import reconstruct

    result = reconstruct(capture, rig, voxel_mm)
    if model_surface_at is None:
        return float(result.volume_ml), None
    hull = measured_hull_bias(capture, rig, result, model_surface_at(pressures_kpa))
    if isinstance(hull, str):
        return float(result.volume_ml), None
    return float(hull.corrected_ml(result.volume_ml)), hull.error_pct


# ----------------------------------------------------------------------------------------------- the fit
def fit_run(measurements: Sequence[Measurement], grid: ModelGrid) -> tuple[Correction, str]:
    """The correction of the model by a run's scans (``fit_correction``: a Gaussian process over every trend), and
    a note for the report (none: every trend is fitted). A bad measurement is an error, not a note."""
    return fit_correction(measurements, grid), ""


# ----------------------------------------------------------------------------------------------- the report
@dataclass(frozen=True)
class ReportRow:
    """One finished point in the report: its pressures (kPa), the model's, the corrected model's, the scanned
    and (simulated) the true gland volume (ml)."""

    index: int
    pressures_kpa: list[float]
    model_ml: float
    corrected_ml: float
    scan_ml: float
    true_ml: float | None


def report_rows(record: CharacterisationRecord, grid: ModelGrid, correction: Correction) -> list[ReportRow]:
    corrected = CorrectedModel(grid, correction)
    return [ReportRow(result.index, result.pressures_kpa, grid.gland_ml(np.asarray(result.pressures_kpa)),
                      corrected.gland_ml(result.pressures_kpa), result.volume_ml, result.true_ml)
            for result in sorted(record.results, key=lambda r: r.index)]


def _pct(value: float, reference: float) -> str:
    return f"{(value / reference - 1) * 100:+.2f} %"


def write_report(record: CharacterisationRecord, grid: ModelGrid, correction: Correction,
                 extra: Sequence[str] = ()) -> tuple[Path, Path]:
    """``report.md`` and ``report.png`` in the record's folder; their paths. ``extra``: lines added at the end
    (the calibration's summary)."""
    rows = report_rows(record, grid, correction)
    simulated = all(row.true_ml is not None for row in rows)
    seconds = [result.seconds for result in record.results]
    elapsed = sum(session.get("elapsed_s", 0.0) for session in record.sessions)
    described = describe_design(record.design)
    scan = record.scan
    lines = [f"# Characterisation of phantom {record.phantom!r}", "",
             f"{len(rows)} of {len(record.points_kpa)} pressure states scanned ({described} in 0-"
             f"{record.pressure_max_kpa:g} kPa); the model {record.model}; each scan {scan.get('views')} views per "
             f"turn at {', '.join(f'{e:g}' for e in scan.get('elevations_deg', []))} deg, picture scale "
             f"{scan.get('scale')}, {scan.get('voxel_mm')} mm voxels.",
             f"Time: {elapsed:.0f} s in all over {len(record.sessions)} session(s); per point "
             + (f"{np.mean(seconds):.1f} s on average ({min(seconds):.1f}-{max(seconds):.1f} s)." if seconds else "-"),
             ""]
    if record.skipped:
        lines += ["Not scanned:", ""] + [f"- point {index} ({_kpa_text(record.points_kpa[index])} kPa): {why}"
                                         for index, why in sorted(record.skipped.items())] + [""]
    lines += ["## The correction", "",
              f"The model misses the scans by {correction.uncorrected_pct:.2f} % on average. In force: "
              f"**{correction.kind}**, a Gaussian process ({correction.hyperparameters()}), fitted to "
              f"{correction.count} scans; its largest size over the pressure box "
              f"{correction.size_ml(grid):.3f} ml.", "",
              "Leave-one-out (each scan left out in turn, predicted by the correction fitted to the rest; mean abs "
              "error, % of the scanned volume):", "", "| correction | leave-one-out |", "|---|---|",
              "| none (the model) | " + f"{correction.uncorrected_pct:.2f} % |"]
    lines += [f"| {kind}{' (in force)' if kind == correction.kind else ''} | {error:.2f} % |"
              for kind, error in correction.leave_one_out_pct.items()]
    header = "| point | pressures (kPa) | model (ml) | corrected (ml) | scan (ml) | model vs scan | corrected vs scan |"
    rule = "|---|---|---|---|---|---|---|"
    if simulated:
        header += " truth (ml) | scan vs truth |"
        rule += "---|---|"
    lines += ["", "## Per point", "", "The corrected model here is fitted to every scan, this one included (the "
              "leave-one-out above says how it predicts a state not scanned).", "", header, rule]
    for row in rows:
        line = (f"| {row.index} | {_kpa_text(row.pressures_kpa)} | {row.model_ml:.3f} | {row.corrected_ml:.3f} | "
                f"{row.scan_ml:.3f} | {_pct(row.model_ml, row.scan_ml)} | {_pct(row.corrected_ml, row.scan_ml)} |")
        if simulated and row.true_ml is not None:
            line += f" {row.true_ml:.3f} | {_pct(row.scan_ml, row.true_ml)} |"
        lines.append(line)
    lines += ["", "![model, corrected model and scans against pressure](report.png)", "", *extra]
    markdown = record.folder / "report.md"
    with written_atomically(markdown, CharacterisationError) as temporary:
        temporary.write_text("\n".join(lines) + "\n")
    return markdown, write_plot(record, grid, correction, rows)


def describe_design(design: dict[str, Any]) -> str:
    """A record's design in words."""
    if design["kind"] == "grid":
        return f"a grid of {', '.join(f'{v:g}' for v in design['values_kpa'])} kPa on every chamber"
    if design["kind"] == "path":
        return (f"rest and {design['count'] - 1} states along the model's inverse, at volumes evenly from rest to "
                f"its top")
    return f"{design['count']} states of a Latin hypercube (centred discrepancy lowered, seed {design['seed']})"


def _kpa_text(pressures: Sequence[float]) -> str:
    return ", ".join(f"{p:.2f}" for p in pressures)


def write_plot(record: CharacterisationRecord, grid: ModelGrid, correction: Correction,
               rows: Sequence[ReportRow]) -> Path:
    """``report.png``: left, the gland volume against the mean chamber pressure (the scans, the model and the
    corrected model at each, and both along the diagonal, every chamber at the same pressure); right, the model's
    and the corrected model's error against each scan (%)."""
    with require_extra("scan"):
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

    corrected = CorrectedModel(grid, correction)
    mean_kpa = np.array([np.mean(row.pressures_kpa) for row in rows])
    chambers = grid.chamber_ml.shape[-1]
    line_kpa = np.linspace(0.0, record.pressure_max_kpa, 31)
    figure, (volumes, errors) = plt.subplots(1, 2, figsize=(12, 5), constrained_layout=True)
    volumes.plot(line_kpa, [grid.gland_ml(np.full(chambers, p)) for p in line_kpa], color="tab:blue", lw=1,
                 label="model, every chamber at p")
    volumes.plot(line_kpa, [corrected.gland_ml(np.full(chambers, p)) for p in line_kpa], color="tab:orange", lw=1,
                 label="corrected model, every chamber at p")
    volumes.scatter(mean_kpa, [row.model_ml for row in rows], marker="x", color="tab:blue", label="model")
    volumes.scatter(mean_kpa, [row.corrected_ml for row in rows], marker="+", s=80, color="tab:orange",
                    label="corrected model")
    volumes.scatter(mean_kpa, [row.scan_ml for row in rows], s=14, color="black", label="scan", zorder=3)
    if all(row.true_ml is not None for row in rows):
        volumes.scatter(mean_kpa, [row.true_ml for row in rows], s=40, facecolors="none", edgecolors="tab:green",
                        label="simulated truth")
    volumes.set_xlabel("mean chamber pressure (kPa)")
    volumes.set_ylabel("gland volume (ml)")
    volumes.set_title(f"phantom {record.phantom!r}: {len(rows)} scans")
    volumes.legend(fontsize=8)
    errors.axhspan(-0.5, 0.5, color="0.9", label="within 0.5 %")
    errors.axhline(0.0, color="0.5", lw=0.8)
    errors.scatter(mean_kpa, [(row.model_ml / row.scan_ml - 1) * 100 for row in rows], marker="x",
                   color="tab:blue", label=f"model (mean abs {correction.uncorrected_pct:.2f} %)")
    errors.scatter(mean_kpa, [(row.corrected_ml / row.scan_ml - 1) * 100 for row in rows], marker="+", s=80,
                   color="tab:orange", label=f"corrected, {correction.kind} (in sample)")
    errors.set_xlabel("mean chamber pressure (kPa)")
    errors.set_ylabel("volume vs the scan (%)")
    loo = ", ".join(f"{kind} {error:.2f} %" for kind, error in correction.leave_one_out_pct.items())
    errors.set_title("leave-one-out: " + (loo or "needs two scans"), fontsize=9)
    errors.legend(fontsize=8)
    path = record.folder / "report.png"
    with written_atomically(path, CharacterisationError) as temporary:
        figure.savefig(temporary, dpi=110, format="png")
    plt.close(figure)
    return path
