"""``phantom report RECORDING.rrd --out FILE.html``: a static, self-contained report of a daemon's recording.

One HTML file that any browser opens without a network or a display and that can be mailed: the gland's volume
(target, estimate, the true volume where the recording has one: the simulated plant's, and each verified target's
scans), each verified target's scans round by round against its target, each chamber's
pressure (setpoint and measured) and drive level, a table of the scene's steps with the estimate's and the true
volume's error at the end of each step, pictures of the gland at the end of each step (coloured by how far its
surface moved from the rest shape), and the event log. The plots are PNGs drawn with matplotlib and embedded as
base64, so the file holds everything it shows.

It reads the ``.rrd`` back with the SDK's reader (:func:`phantom.host.recording.read_rrd`), so it shows what was
recorded and nothing else: a recording without meshes has no pictures, one without a true volume no true
column; one cut short in the middle of a message (a full disk) up to that message, and the report (and the command
line) says so. The entity paths are those :mod:`phantom.host.recording` writes.
"""

from __future__ import annotations

import argparse
import base64
import contextlib
import html
import io
import logging
import re
import warnings
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from phantom import PhantomError, require_extra

if TYPE_CHECKING:
    import numpy as np
    from matplotlib.figure import Figure

logger = logging.getLogger(__name__)

#: The gland's volume series in the recording, and how the report names them.
VOLUME_SERIES = {"commanded_ml": "target", "estimated_ml": "estimate", "true_ml": "true (simulated plant)",
                 "scanned_ml": "scanned (measured)"}
#: A verified target's scans: each one's round and the tolerance asked, logged beside its volume.
VERIFY_SERIES = ("round", "tolerance_pct")
#: A step event's text as the daemon logs it ("step 2 at 60 s: 35.00 ml over 15 s"): its index and target.
STEP_EVENT = re.compile(r"^step (?P<index>\d+) at [^:]+: (?P<target>.*)$")
#: The recording's columns not read at first (the deformed surfaces, their normals and triangles: the rest
#: shape's are drawn); the surfaces pictured are read after, by a second pass over the recording, so that a long
#: recording's report takes memory for what it draws. The scans' surfaces are not drawn (their volumes are), and
#: not read: the five verified volumes of `make demo` logged 13, and turning them into Python lists took 2.3 s of
#: the report's 5.
MESH_SKIPPED = frozenset({"/phantom/mesh:Mesh3D:vertex_positions", "/phantom/mesh:Mesh3D:vertex_normals",
                          "/phantom/mesh:Mesh3D:triangle_indices", "/phantom/mesh:Mesh3D:albedo_factor",
                          "/phantom/rest:Mesh3D:vertex_normals",
                          "/phantom/scan:Mesh3D:vertex_positions", "/phantom/scan:Mesh3D:vertex_normals",
                          "/phantom/scan:Mesh3D:triangle_indices", "/phantom/scan:Mesh3D:albedo_factor"})
#: Pictures of the gland at most (when the recording has no steps, frames evenly spread over it).
MAX_PICTURES = 12
#: Figure sizes (inches at PLOT_DPI) and resolution.
PLOT_WIDTH_IN = 10.0
PLOT_DPI = 96


@dataclass(frozen=True)
class Series:
    """One scalar series of the recording: daemon time (s) and values."""

    time_s: np.ndarray
    values: np.ndarray

    def at(self, time_s: float) -> float | None:
        """The last value logged at or before ``time_s`` (None if none was)."""
        import numpy as np

        index = int(np.searchsorted(self.time_s, time_s, side="right")) - 1
        return None if index < 0 else float(self.values[index])


@dataclass(frozen=True)
class Chamber:
    """One chamber's series: its name as people say it, its colour (RGB 0-1), and pressures and drive."""

    index: int
    name: str
    colour: tuple[float, float, float]
    setpoint_kpa: Series | None
    measured_kpa: Series | None
    drive_level: Series | None


@dataclass(frozen=True)
class Event:
    time_s: float
    level: str
    text: str


@dataclass(frozen=True)
class Surfaces:
    """The gland's outer surface: the rest shape, the times a deformed one was logged (s), and the deformed ones
    read (mm; those pictured, by their time)."""

    rest_mm: np.ndarray
    triangles: np.ndarray
    time_s: np.ndarray
    positions_mm: dict[float, np.ndarray]

    def logged_at(self, time_s: float) -> float:
        """The time of the last surface logged at or before ``time_s`` (the first one's before it)."""
        import numpy as np

        return float(self.time_s[max(int(np.searchsorted(self.time_s, time_s, side="right")) - 1, 0)])

    def at(self, time_s: float) -> np.ndarray:
        import numpy as np

        return np.asarray(self.positions_mm[self.logged_at(time_s)], dtype=float)  # kept as the recording's float32


@dataclass(frozen=True)
class Step:
    """A scene step as played: when it started and ended (daemon time, s) and the volumes at its end (ml)."""

    index: int
    target: str
    start_s: float
    end_s: float
    target_ml: float | None
    estimate_ml: float | None
    true_ml: float | None

    @property
    def true_error_pct(self) -> float | None:
        return _error_pct(self.true_ml, self.target_ml)


@dataclass(frozen=True)
class Scan:
    """A verified target's scan: when (daemon time, s), its round (1, 2, ...), the target, the scanned and the true
    volume then (ml) and the tolerance asked (%); None where the recording has no value."""

    time_s: float
    round: int
    target_ml: float | None
    scanned_ml: float
    true_ml: float | None
    tolerance_pct: float | None

    @property
    def error_pct(self) -> float | None:
        return _error_pct(self.scanned_ml, self.target_ml)

    @property
    def true_error_pct(self) -> float | None:
        return _error_pct(self.true_ml, self.target_ml)


@dataclass(frozen=True)
class Run:
    """What a recording holds, as the report shows it."""

    path: Path
    end_s: float
    volumes: dict[str, Series]
    chambers: list[Chamber]
    events: list[Event]
    surfaces: Surfaces | None
    steps: list[Step]
    #: the verified targets' scans, in the order taken
    scans: list[Scan]
    #: what the recording held that the report could not show, and why (a mesh whose triangles name vertices it
    #: does not have)
    notes: tuple[str, ...] = ()


def _error_pct(value: float | None, reference: float | None) -> float | None:
    if value is None or reference is None or reference == 0:
        return None
    return (value - reference) / reference * 100.0


def _series(columns: dict[str, list[Any]] | None) -> Series | None:
    """A scalar entity's rows as a Series (rows without a value dropped); None when it logged nothing."""
    import numpy as np

    if not columns or "Scalars:scalars" not in columns or "time" not in columns:
        return None
    pairs = [(time_s, value[0]) for time_s, value in zip(columns["time"], columns["Scalars:scalars"], strict=False)
             if time_s is not None and value]
    if not pairs:
        return None
    time_s, values = zip(*pairs, strict=True)
    return Series(np.asarray(time_s, dtype=float), np.asarray(values, dtype=float))


def _colour(packed: int) -> tuple[float, float, float]:
    """A colour as Rerun stores it (0xRRGGBBAA) as matplotlib's RGB in 0-1."""
    return ((packed >> 24) & 255) / 255, ((packed >> 16) & 255) / 255, ((packed >> 8) & 255) / 255


def _chambers(entities: dict[str, dict[str, list[Any]]]) -> list[Chamber]:
    """Each chamber the recording has, in chamber order (the recorder's colours are in chamber order), named as
    the recorder named its series."""
    from phantom.host.recording import CHAMBER_COLOURS

    parts = sorted({key.split("/")[2] for key in entities if key.startswith("/chamber/") and key.count("/") == 3})
    chambers: list[Chamber] = []
    for part in parts:
        measured = entities.get(f"/chamber/{part}/measured_kpa", {})
        drive = entities.get(f"/chamber/{part}/drive_level", {})
        names = drive.get("SeriesLines:names") or [[part]]
        colours = drive.get("SeriesLines:colors") or measured.get("SeriesLines:colors") or [[0x808080FF]]
        rgb = _colour(int(colours[0][0]))
        recorded = tuple(round(channel * 255) for channel in rgb)
        index = CHAMBER_COLOURS.index(recorded) if recorded in CHAMBER_COLOURS else len(parts) + len(chambers)
        chambers.append(Chamber(index, str(names[0][0]), rgb,
                                _series(entities.get(f"/chamber/{part}/commanded_kpa")), _series(measured or None),
                                _series(drive or None)))
    chambers.sort(key=lambda chamber: chamber.index)
    return [Chamber(k, c.name, c.colour, c.setpoint_kpa, c.measured_kpa, c.drive_level)
            for k, c in enumerate(chambers)]


def _events(entities: dict[str, dict[str, list[Any]]]) -> list[Event]:
    columns = entities.get("/events", {})
    rows = zip(columns.get("time", []), columns.get("TextLog:level", []), columns.get("TextLog:text", []),
               strict=False)
    return [Event(float(time_s), str(level[0]) if level else "", str(text[0]))
            for time_s, level, text in rows if time_s is not None and text]


def _surfaces(entities: dict[str, dict[str, list[Any]]], notes: list[str]) -> Surfaces | None:
    """The rest shape and the deformed surfaces, when the recording has both (the daemon logs them when its scene
    asks for shapes) and they hold together: finite (n, 3) positions, (k, 3) triangles of those vertices; else
    None, and ``notes`` says why."""
    import numpy as np

    rest = entities.get("/phantom/rest", {})
    moving = entities.get("/phantom/mesh", {})
    if not rest.get("Mesh3D:vertex_positions") or not moving.get("time"):
        return None
    try:
        rest_mm = np.asarray(rest["Mesh3D:vertex_positions"][0], dtype=float)
        triangles = np.asarray((rest.get("Mesh3D:triangle_indices") or [[]])[0], dtype=np.int64)
    except (TypeError, ValueError, OverflowError) as error:
        notes.append(f"the rest surface cannot be read ({error}): no pictures of the gland")
        return None
    if rest_mm.ndim != 2 or rest_mm.shape[1:] != (3,) or not np.all(np.isfinite(rest_mm)) \
            or triangles.ndim != 2 or triangles.shape[1:] != (3,) or len(triangles) == 0:
        notes.append(f"the rest surface is not a triangle mesh (positions {rest_mm.shape}, triangles "
                     f"{triangles.shape}): no pictures of the gland")
        return None
    if triangles.min() < 0 or triangles.max() >= len(rest_mm):
        notes.append(f"the rest surface's triangle indices run from {triangles.min()} to {triangles.max()} but it "
                     f"has {len(rest_mm)} vertices: no pictures of the gland")
        return None
    times = sorted({time_s for time_s in moving.get("time", []) if time_s is not None})
    if not times:
        return None
    return Surfaces(rest_mm, triangles, np.asarray(times, dtype=float), {})


def _read_pictured(path: Path, surfaces: Surfaces, wanted_s: list[float], notes: list[str]) -> Surfaces | None:
    """``surfaces`` with the deformed surfaces at the times pictured read (a second pass over the recording);
    None, and ``notes`` says why, when one of them is not the rest shape's vertices."""
    from phantom.host.recording import read_points_at

    logged = {surfaces.logged_at(time_s - 1e-6) for time_s in wanted_s}
    found = read_points_at(path, "/phantom/mesh", "Mesh3D:vertex_positions", logged)
    wrong = sorted(time_s for time_s in logged if time_s not in found or found[time_s].shape != surfaces.rest_mm.shape)
    if wrong:
        notes.append(f"the surface logged at {wrong[0]:.1f} s is not the rest shape's {len(surfaces.rest_mm)} "
                     f"vertices: no pictures of the gland")
        return None
    return Surfaces(surfaces.rest_mm, surfaces.triangles, surfaces.time_s, found)


def _steps(events: list[Event], volumes: dict[str, Series], end_s: float) -> list[Step]:
    """The scene's steps from its step events; each ends where the next begins, or where the scene finished
    or the recording ends. Its volumes are the last ones logged before its end."""
    starts = [(event.time_s, match) for event in events if (match := STEP_EVENT.match(event.text))]
    finished = [event.time_s for event in events if event.text.startswith("scene ") and " finished" in event.text]
    steps = []
    for k, (start_s, match) in enumerate(starts):
        later = [time_s for time_s in finished if time_s > start_s]
        step_end_s = starts[k + 1][0] if k + 1 < len(starts) else min(later, default=end_s)

        def value(name: str, at_s: float = step_end_s) -> float | None:
            series = volumes.get(name)
            return None if series is None else series.at(at_s - 1e-6)

        steps.append(Step(int(match["index"]), match["target"], start_s, step_end_s, value("commanded_ml"),
                          value("estimated_ml"), value("true_ml")))
    return steps


def scans_in(volumes: dict[str, Series], verify: dict[str, Series]) -> list[Scan]:
    """The verified targets' scans: each scanned volume with the round and tolerance logged at its time, and the
    target and the true volume then. A recording from before rounds were logged numbers a target's scans in a
    row from 1, a new target starting again."""
    scanned = volumes.get("scanned_ml")
    if scanned is None:
        return []
    def value(series: Series | None, time_s: float) -> float | None:
        """The series' value logged with the scan (at its time) or last before it."""
        return None if series is None else series.at(time_s + 1e-9)

    scans: list[Scan] = []
    for time_s, volume_ml in zip(scanned.time_s.tolist(), scanned.values.tolist(), strict=True):
        target_ml = value(volumes.get("commanded_ml"), time_s)
        logged_round = value(verify.get("round"), time_s)
        if logged_round is not None:
            round_ = int(logged_round)
        else:
            round_ = scans[-1].round + 1 if scans and scans[-1].target_ml == target_ml else 1
        scans.append(Scan(time_s, round_, target_ml, volume_ml, value(volumes.get("true_ml"), time_s),
                          value(verify.get("tolerance_pct"), time_s)))
    return scans


@contextlib.contextmanager
def _cut_short_noted(notes: list[str]) -> Iterator[None]:
    """The reader's word that the recording ends cut short (:class:`phantom.host.recording.RecordingCutShort`)
    as a note of the report, once, and a warning on the command line; other warnings go on as they came."""
    from phantom.host.recording import RecordingCutShort

    with warnings.catch_warnings(record=True) as told:
        warnings.simplefilter("always", RecordingCutShort)
        yield
    for warning in told:
        if not issubclass(warning.category, RecordingCutShort):
            warnings.warn_explicit(warning.message, warning.category, warning.filename, warning.lineno)
        elif str(warning.message) not in notes:
            notes.append(str(warning.message))
            logger.warning("%s", warning.message)


def load_run(path: str | Path) -> Run:
    """Read a recording back; PhantomError when the file is missing or is not a recording of the daemon. One cut
    short in the middle of a message is read up to it, and its notes say so."""
    from phantom.host.recording import read_rrd

    path = Path(path)
    if not path.is_file():
        raise PhantomError(f"{path}: no such recording (give the .rrd the daemon wrote with --rerun-save, e.g. "
                           "out/demo.rrd)")
    notes: list[str] = []
    try:
        with _cut_short_noted(notes):
            entities = read_rrd(path, skip=MESH_SKIPPED)  # the surfaces pictured are read once it is known which
    except (ValueError, OSError, RuntimeError) as error:
        raise PhantomError(f"{path} cannot be read as a Rerun recording ({error}); give an .rrd the daemon "
                           "wrote") from None
    volumes = {name: series for name in VOLUME_SERIES if (series := _series(entities.get(f"/volume/{name}")))}
    chambers = _chambers(entities)
    if not volumes and not chambers:
        raise PhantomError(f"{path} holds no volumes and no chamber pressures: it is not a recording of the "
                           "phantom's daemon")
    times = [float(t) for columns in entities.values() for t in columns.get("time", []) if t is not None]
    end_s = max(times, default=0.0)
    events = _events(entities)
    surfaces = _surfaces(entities, notes)
    steps = _steps(events, volumes, end_s)
    verify = {name: series for name in VERIFY_SERIES if (series := _series(entities.get(f"/verify/{name}")))}
    scans = scans_in(volumes, verify)
    run = Run(path, end_s, volumes, chambers, events, surfaces, steps, scans)
    if surfaces is not None:
        try:
            with _cut_short_noted(notes):
                surfaces = _read_pictured(path, surfaces, [time_s for _, time_s in picture_times(run)], notes)
        except (ValueError, OSError, RuntimeError) as error:
            raise PhantomError(f"{path} cannot be read as a Rerun recording ({error}); give an .rrd the daemon "
                               "wrote") from None
    return Run(path, end_s, volumes, chambers, events, surfaces, steps, scans, tuple(notes))


# ------------------------------------------------------------------------------------------------ figures
def _png(figure: Figure) -> str:
    """A figure as a base64 PNG (the figure is closed)."""
    with require_extra("record"):
        import matplotlib.pyplot as plt

    buffer = io.BytesIO()
    figure.savefig(buffer, format="png", dpi=PLOT_DPI, bbox_inches="tight")
    plt.close(figure)
    return base64.b64encode(buffer.getvalue()).decode("ascii")


def _mark_steps(axes: Any, steps: list[Step]) -> None:
    for step in steps:
        axes.axvline(step.start_s, color="0.75", linewidth=0.8, zorder=0)


def volume_figure(run: Run) -> str:
    """The gland's volume over the recording: target (grey dots), estimate, true, the verified targets' scans
    (green diamonds); steps as thin lines."""
    with require_extra("record"):
        import matplotlib.pyplot as plt

    figure, axes = plt.subplots(figsize=(PLOT_WIDTH_IN, 3.6))
    styles: dict[str, dict[str, Any]] = {
        "commanded_ml": {"color": "0.55", "marker": ".", "linestyle": "none", "markersize": 4},
        "estimated_ml": {"color": "#cc79a7", "linewidth": 1.6},  # the recording's colours for these series
        "true_ml": {"color": "#0072b2", "linewidth": 1.6},
        "scanned_ml": {"color": "#009e73", "marker": "D", "linestyle": "none", "markersize": 5}}
    for name, series in run.volumes.items():
        axes.plot(series.time_s, series.values, label=VOLUME_SERIES[name], **styles[name])
    _mark_steps(axes, run.steps)
    axes.set_xlabel("time since the daemon started (s)")
    axes.set_ylabel("gland volume (ml)")
    axes.grid(alpha=0.3)
    axes.legend(loc="upper left")
    return _png(figure)


def verified_targets(scans: list[Scan]) -> list[list[Scan]]:
    """The scans by verified target: a round 1 (or a round not after the one before) starts another."""
    targets: list[list[Scan]] = []
    for scan in scans:
        if not targets or scan.round <= targets[-1][-1].round:
            targets.append([])
        targets[-1].append(scan)
    return targets


def scans_figure(run: Run) -> str:
    """Each verified target's scans against its target, round by round (%: scanned solid, true dashed where the
    recording has it), the tolerance asked shaded; the axis linear within the tolerance and logarithmic beyond,
    so that a first round's few percent and a last round's tenths both show."""
    with require_extra("record"):
        import matplotlib.pyplot as plt
    import numpy as np

    targets = verified_targets(run.scans)
    tolerances = sorted({scan.tolerance_pct for scan in run.scans if scan.tolerance_pct is not None})
    figure, axes = plt.subplots(figsize=(PLOT_WIDTH_IN, 3.6))
    colours = plt.get_cmap("tab10")
    for index, scans in enumerate(targets):
        rounds = [scan.round for scan in scans]
        colour = colours(index % 10)
        target = "-" if scans[0].target_ml is None else f"{scans[0].target_ml:.2f} ml"
        scanned = [np.nan if (error := scan.error_pct) is None else error for scan in scans]
        axes.plot(rounds, scanned, color=colour, marker="o", label=target)
        true = [value for scan in scans if (value := scan.true_error_pct) is not None]
        if len(true) == len(scans):  # the simulated plant's, recorded at every scan
            axes.plot(rounds, true, color=colour, marker="x", linestyle="--", linewidth=1.0)
    for tolerance in tolerances:
        axes.axhspan(-tolerance, tolerance, color="#009e73", alpha=0.12, zorder=0,
                     label=f"the tolerance asked, +-{tolerance:g} %")
    axes.axhline(0.0, color="0.4", linewidth=0.8)
    errors = [abs(value) for scan in run.scans for value in (scan.error_pct, scan.true_error_pct) if value is not None]
    reach = 1.5 * max([*errors, *tolerances, 0.3])
    axes.set_yscale("symlog", linthresh=min(tolerances, default=0.3), linscale=0.5)
    axes.set_ylim(-reach, reach)
    ticks = [0.0] + [sign * tick for tick in (0.1, 0.3, 1.0, 3.0, 10.0, 30.0) if tick < reach for sign in (-1, 1)]
    axes.set_yticks(sorted(ticks), [f"{tick:+g}" if tick else "0" for tick in sorted(ticks)])
    axes.xaxis.set_major_locator(plt.MaxNLocator(integer=True))
    axes.set_xlabel("round")
    axes.set_ylabel("error against the target (%)")
    axes.grid(alpha=0.3)
    axes.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize="small")
    return _png(figure)


def chamber_figure(run: Run) -> str:
    """Each chamber's pressure (setpoint wide and translucent, measured on top) and drive level, one column each."""
    with require_extra("record"):
        import matplotlib.pyplot as plt

    columns = max(len(run.chambers), 1)
    figure, axes = plt.subplots(2, columns, figsize=(PLOT_WIDTH_IN, 4.8), sharex=True, squeeze=False,
                                gridspec_kw={"height_ratios": (2, 1)})
    for k, chamber in enumerate(run.chambers):
        pressure, drive = axes[0][k], axes[1][k]
        if chamber.setpoint_kpa is not None:
            pressure.plot(chamber.setpoint_kpa.time_s, chamber.setpoint_kpa.values, color=chamber.colour,
                          alpha=0.35, linewidth=5, label="setpoint")
        if chamber.measured_kpa is not None:
            pressure.plot(chamber.measured_kpa.time_s, chamber.measured_kpa.values, color=chamber.colour,
                          linewidth=1.2, label="measured")
        if chamber.drive_level is not None:
            drive.plot(chamber.drive_level.time_s, chamber.drive_level.values, color=chamber.colour, linewidth=1.0)
        # a name is text, whatever it holds (not mathtext: "$\\undefinedcommand$" stopped the report)
        pressure.set_title(f"{chamber.name} (chamber {chamber.index})", parse_math=False)
        pressure.legend(loc="upper left", fontsize="small")
        for part in (pressure, drive):
            _mark_steps(part, run.steps)
            part.grid(alpha=0.3)
        drive.set_xlabel("time (s)")
    axes[0][0].set_ylabel("pressure (kPa)")
    axes[1][0].set_ylabel("drive level (0-1)")
    figure.tight_layout()
    return _png(figure)


def picture_times(run: Run) -> list[tuple[str, float]]:
    """When to picture the gland, with a caption: the end of each step, else frames spread over the recording."""
    import numpy as np

    if run.surfaces is None:
        return []
    if run.steps:
        return [(f"step {step.index}: {step.target}", step.end_s) for step in run.steps][:MAX_PICTURES]
    times = run.surfaces.time_s
    chosen = np.unique(np.linspace(0, len(times) - 1, min(MAX_PICTURES, len(times))).round().astype(int))
    return [(f"at {times[k]:.0f} s", float(times[k])) for k in chosen]


def gland_pictures(run: Run) -> list[tuple[str, str]]:
    """The gland at each picture time, coloured by how far its surface moved from the rest shape (mm, one scale
    for all), seen from the front left; (caption, base64 PNG) each."""
    import numpy as np

    with require_extra("record"):
        import matplotlib.pyplot as plt
        from matplotlib import colormaps
        from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    surfaces = run.surfaces
    wanted = picture_times(run)
    if surfaces is None or not wanted:
        return []
    shapes = [surfaces.at(time_s - 1e-6) for _, time_s in wanted]
    moved = [np.linalg.norm(shape - surfaces.rest_mm, axis=1) for shape in shapes]
    top_mm = max(max(float(m.max()) for m in moved), 1e-3)
    low, high = np.min([s.min(axis=0) for s in shapes], axis=0), np.max([s.max(axis=0) for s in shapes], axis=0)
    light = np.array([0.4, 0.6, 0.7]) / np.linalg.norm([0.4, 0.6, 0.7])
    colour_map = colormaps["viridis"]
    pictures = []
    for (caption, time_s), shape, distance in zip(wanted, shapes, moved, strict=True):
        corners = shape[surfaces.triangles]
        normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
        normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
        shade = 0.45 + 0.55 * np.abs(normals @ light)
        colours = colour_map(distance[surfaces.triangles].mean(axis=1) / top_mm)
        colours[:, :3] *= shade[:, None]
        figure = plt.figure(figsize=(3.2, 3.2))
        axes = figure.add_subplot(projection="3d")
        axes.add_collection3d(Poly3DCollection(corners, facecolors=colours, edgecolors="none"))
        axes.set(xlim=(low[0], high[0]), ylim=(low[1], high[1]), zlim=(low[2], high[2]))
        axes.set_box_aspect(tuple(high - low), zoom=1.35)  # the 3D axes' default margin is for tick labels
        axes.view_init(elev=15, azim=60)
        axes.set_axis_off()
        figure.subplots_adjust(0, 0, 1, 1)
        pictures.append((f"{caption} (at {time_s:.0f} s; moved up to {distance.max():.1f} mm)", _png(figure)))
    return pictures


def colour_scale(run: Run) -> str:
    """The pictures' colour bar: distance from the rest shape, 0 to the largest any picture shows (mm)."""
    import numpy as np

    with require_extra("record"):
        import matplotlib.pyplot as plt
        from matplotlib import colormaps
        from matplotlib.cm import ScalarMappable
        from matplotlib.colors import Normalize

    surfaces = run.surfaces
    assert surfaces is not None
    top_mm = max(float(np.linalg.norm(surfaces.at(time_s - 1e-6) - surfaces.rest_mm, axis=1).max())
                 for _, time_s in picture_times(run))
    figure, axes = plt.subplots(figsize=(5.0, 0.6))
    figure.colorbar(ScalarMappable(Normalize(0, max(top_mm, 1e-3)), colormaps["viridis"]), cax=axes,
                    orientation="horizontal", label="surface moved from the rest shape (mm)")
    return _png(figure)


# ------------------------------------------------------------------------------------------------ HTML
def _number(value: float | None, digits: int = 2, signed: bool = False) -> str:
    if value is None:
        return "-"
    return f"{value:+.{digits}f}" if signed else f"{value:.{digits}f}"


def steps_table(steps: list[Step]) -> str:
    """The steps as an HTML table: the target, the estimate and the true volume at each step's end, the true
    volume's error against the target, and the mean of those errors under it."""
    import numpy as np

    with_true = any(step.true_ml is not None for step in steps)
    head = ["step", "start (s)", "target", "estimate ml"] + (["true ml", "true error %"] if with_true else [])
    rows = []
    for step in steps:
        target = step.target if step.target_ml is None else f"{step.target_ml:.2f} ml"
        cells = [str(step.index), f"{step.start_s:.1f}", html.escape(target), _number(step.estimate_ml)]
        if with_true:
            cells += [_number(step.true_ml), _number(step.true_error_pct, signed=True)]
        rows.append("<tr>" + "".join(f"<td>{cell}</td>" for cell in cells) + "</tr>")
    errors = [abs(e) for step in steps if (e := step.true_error_pct) is not None]
    summary = (f"<p>Mean |true error| {np.mean(errors):.2f} %, largest {max(errors):.2f} %: how far the phantom "
               "itself was from each target, which the estimate (what the controller drives to the target) "
               "does not show.</p>") if errors else ""
    return ("<table><tr>" + "".join(f"<th>{html.escape(name)}</th>" for name in head) + "</tr>"
            + "".join(rows) + "</table>" + summary)


def scans_table(scans: list[Scan]) -> str:
    """The verified targets' scans as an HTML table: each target's rounds, the scanned volume and its error, the
    true volume and its error where the recording has it, and whether the scan was within the tolerance asked."""
    with_true = any(scan.true_ml is not None for scan in scans)
    head = ["time (s)", "target", "round", "scanned ml", "error %"]
    head += (["true ml", "true error %"] if with_true else []) + ["within the tolerance"]
    rows = []
    for scan in scans:
        error = scan.error_pct
        within = ("-" if error is None or scan.tolerance_pct is None
                  else f"{'yes' if abs(error) <= scan.tolerance_pct else 'no'} (+-{scan.tolerance_pct:g} %)")
        cells = [f"{scan.time_s:.1f}", "-" if scan.target_ml is None else f"{scan.target_ml:.2f} ml", str(scan.round),
                 f"{scan.scanned_ml:.3f}", _number(error, signed=True)]
        if with_true:
            cells += [_number(scan.true_ml, 3), _number(scan.true_error_pct, signed=True)]
        rows.append("<tr>" + "".join(f"<td>{cell}</td>" for cell in cells + [within]) + "</tr>")
    return ("<table><tr>" + "".join(f"<th>{html.escape(name)}</th>" for name in head) + "</tr>"
            + "".join(rows) + "</table>")


def events_table(events: list[Event]) -> str:
    rows = "".join(f'<tr class="{html.escape(event.level.lower())}"><td>{event.time_s:.2f}</td>'
                   f"<td>{html.escape(event.level)}</td><td>{html.escape(event.text)}</td></tr>" for event in events)
    return f"<table><tr><th>time (s)</th><th>level</th><th>event</th></tr>{rows}</table>"


STYLE = """
body { font-family: sans-serif; max-width: 1000px; margin: 1em auto; color: #222; background: #fff; }
table { border-collapse: collapse; margin: 0.5em 0; font-size: 90%; }
th, td { border: 1px solid #ccc; padding: 2px 8px; text-align: right; }
td:last-child, th:last-child { text-align: left; }
tr.warn td { background: #fff4d6; } tr.error td { background: #fde0e0; }
.pictures { display: flex; flex-wrap: wrap; gap: 8px; }
figure { margin: 0; width: 240px; } figure img { width: 240px; } figcaption { font-size: 80%; }
img.plot { width: 100%; }
"""


def render_html(run: Run) -> str:
    """The whole report as one HTML document (everything inline)."""
    def image(data: str, alt: str, css: str = "plot") -> str:
        return f'<img class="{css}" alt="{html.escape(alt)}" src="data:image/png;base64,{data}">'

    parts = [f"<h1>Recording {html.escape(run.path.name)}</h1>",
             f"<p>{html.escape(str(run.path))}: {run.end_s:.1f} s of the daemon, {len(run.chambers)} chambers, "
             f"{len(run.events)} events. Times are seconds since the daemon started; thin grey lines mark the "
             "scene's steps.</p>"]
    if run.steps:
        parts += ["<h2>Steps</h2>", "<p>Volumes at the end of each step. The estimate is the model's at the "
                  "measured pressures (what the controller drives to); the true volume is the simulated plant's "
                  "own, where the recording has it.</p>", steps_table(run.steps)]
    if run.volumes:
        parts += ["<h2>Gland volume</h2>", image(volume_figure(run), "gland volume over time")]
    if run.scans:
        targets = verified_targets(run.scans)
        parts += ["<h2>Verified targets: the scans</h2>",
                  f"<p>{len(run.scans)} scans of {len(targets)} verified targets, "
                  f"{len(run.scans) / len(targets):.1f} rounds a target. Each scan's volume against its target, "
                  "round by round (scanned: solid; the simulated plant's true volume: dashed, where the recording "
                  "has it); the tolerance asked is shaded. The axis is linear within it and logarithmic "
                  "beyond.</p>", image(scans_figure(run), "each verified target's scans, round by round"),
                  scans_table(run.scans)]
    if run.chambers:
        parts += ["<h2>Chambers: pressure and drive</h2>", image(chamber_figure(run), "chamber pressures")]
    pictures = gland_pictures(run)
    if pictures:
        parts += ["<h2>The gland</h2>", "<p>Its outer surface at the end of each step, seen from the front left "
                  "(x to the patient's left, y anterior, z apex to base), coloured by how far it moved from the "
                  "rest shape.</p>", image(colour_scale(run), "colour scale", "scale"),
                  '<div class="pictures">' + "".join(
                      f"<figure>{image(data, caption, 'gland')}<figcaption>{html.escape(caption)}</figcaption>"
                      "</figure>" for caption, data in pictures) + "</div>"]
    if run.notes:
        parts += ["<h2>Not shown</h2>", "".join(f"<p>{html.escape(note)}</p>" for note in run.notes)]
    parts += ["<h2>Events</h2>", events_table(run.events)]
    return (f'<!DOCTYPE html>\n<html lang="en"><head><meta charset="utf-8"><title>{html.escape(run.path.name)}'
            f"</title><style>{STYLE}</style></head><body>{''.join(parts)}</body></html>\n")


def write_report(recording: str | Path, out: str | Path) -> Path:
    """Read ``recording`` and write its report to ``out`` (atomically); the path written."""
    from phantom import written_atomically
    from phantom.cli.common import output_file

    with require_extra("record"):
        import matplotlib

        matplotlib.use("Agg")  # no display: the report is drawn to PNGs
        run = load_run(recording)
        document = render_html(run)
    path = output_file(out)
    with written_atomically(path, PhantomError) as temporary:
        Path(temporary).write_text(document, encoding="utf-8")
    return path


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """Add ``report`` to the ``phantom`` parser."""
    report = subparsers.add_parser(
        "report", help="a static HTML report of a recording (.rrd): plots, steps, pictures, events",
        description="Read a recording the daemon wrote (--rerun-save) and write one self-contained HTML file: "
                    "the gland's volume (target, estimate, true where recorded), each chamber's pressure and "
                    "drive, the scene's steps with their errors, pictures of the gland at each step, and the "
                    "events. Opens in any browser, no network or display needed; mail it as it is.")
    report.add_argument("recording", metavar="RECORDING", help="the .rrd file, e.g. out/demo.rrd")
    report.add_argument("--out", help="HTML file to write (default: the recording's name with .html)")
    report.set_defaults(run=run_report)


def run_report(args: argparse.Namespace) -> int:
    """Handler of ``phantom report``."""
    out = args.out or str(Path(args.recording).with_suffix(".html"))
    path = write_report(args.recording, out)
    print(f"wrote {path} ({path.stat().st_size / 1e6:.1f} MB): open it in a browser")
    return 0
