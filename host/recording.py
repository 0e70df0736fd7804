"""Rerun logging of what the daemon does: pressures, volumes, link statistics, solver time, events, the mesh.

Chambers are named as people name them (the scene's ``chamber_labels``: base, left lobe, right lobe), in the
plots' titles and legends and, made path-safe (anything but letters, digits, ``-`` and ``_`` turned into ``_``),
in the entity paths:

    chamber/<chamber>/commanded_kpa, measured_kpa, drive_level  per chamber, from telemetry (commanded: the setpoint)
    volume/commanded_ml, volume/estimated_ml, volume/true_ml    the gland: the target, the model's estimate at the
                                                                measured pressures, the simulated plant's own
    volume/chambers/<chamber>_ml                                estimated chamber volumes
    link/rtt_ms, link/retries, link/bad_frames, link/dropped    link statistics
    solver/qp_time_ms, solver/solve_time_ms                     the inverse
    events                                                      text log: faults, reconnects, targets
    phantom/mesh, phantom/rest, phantom/axes                    deformed outer surface (mm), its rest shape, and
                                                                the anatomical axes as 10 mm arrows
    phantom/scan                                                the last scan's surface (mm), over the model's

Nothing hides: Rerun draws a plot's series in the order of their entity paths, the last on top, whatever the
blueprint lists; so what was asked for sorts first (``commanded``, drawn wide and translucent) and what was
measured or estimated after it (thin and opaque, on top), and each chamber has its own plots (the two lobes often
hold the same pressure, and one line would hide the other).

Timelines: ``time`` (seconds since the daemon started) on everything, and ``scene_time`` (seconds into the
running scene's timeline) on what is logged while a scene runs, so that a scene's steps line up with its file.
The SDK adds ``log_time`` (the wall clock) to all but the telemetry, which is sent in columns.

The blueprint (the layout the viewer opens with): one column per chamber with its pressure, drive level and
volume; the gland volume under them; link and solver in tabs; legends in the top-left corner, where a recording
that starts vented has no data. The phantom view (only when meshes are logged) shows the deformed surface with
normals over a translucent rest-shape ghost, the anatomical axes (x left, y anterior, z apex to base) as
labelled 10 mm arrows, a 10 mm grid, and a camera fitted to the rest shape.

Files: a recording is never overwritten. :meth:`Recorder.open` takes a lock beside the file (another daemon
recording to the same path is refused), sets an existing file aside under a name stamped with the time it was
last written (``run.20261124-101500.rrd``), and writes the new session to the path given. Every file ends with
a footer (its chunk index; ``rerun rrd verify`` accepts it): the SDK keeps that index in memory until the file
is closed (about 2 MB a minute at the daemon's rates), so a long session is closed and set aside every
:data:`SEGMENT_S` and goes on in a new file at the same path, with the same recording id (``rerun run*.rrd``
shows the whole session). A disk that fills up pauses the recording (closed properly while it can be) before
the SDK's writer fails; it resumes in a new file once there is room, and both are events and in ``status``.
:func:`read_rrd` reads a file without its footer (a killed daemon's) and one cut short in the middle of a message
(a writer stopped by a full disk): everything before that message, with a :class:`RecordingCutShort` warning.

Memory stays bounded otherwise: the chunk batcher flushes every 0.5 s rather than every few milliseconds, so a
telemetry series is one chunk per half second rather than one per frame, and a moving mesh sends its triangles
once. ``bench/recording_memory.py`` measures it.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import logging
import os
import re
import struct
import tempfile
import time
import uuid
import warnings
from collections.abc import Callable, Iterator, Sequence
from datetime import datetime, timedelta
from pathlib import Path
from typing import IO, Any, TextIO

import numpy as np

from phantom import PhantomError, require_extra

logger = logging.getLogger(__name__)

#: One fixed colour per chamber, in chamber order (Okabe-Ito, distinguishable with the common colour-vision
#: deficiencies and on the viewer's dark background): orange, sky blue, bluish green, vermillion, blue, purple.
CHAMBER_COLOURS = ((230, 159, 0), (86, 180, 233), (0, 158, 115), (213, 94, 0), (0, 114, 178), (204, 121, 167))
#: Setpoints: the chamber's colour, translucent and wide, drawn under the measured line.
SETPOINT_ALPHA = 110
SETPOINT_WIDTH = 6.0
MEASURED_WIDTH = 1.5
#: Gland volume series, in drawing order: target (wide translucent grey dots, under the others; dots so that no
#: line bridges a time without a target), estimate (purple), each scan's volume (big green dots, one a scan),
#: the simulated plant's true volume (blue); none is a chamber's colour. Widths in points.
GLAND_SERIES = {"commanded_ml": ("target", (128, 128, 128, 120), 7.0),
                "estimated_ml": ("estimate", (204, 121, 167, 255), 1.5),
                "scanned_ml": ("scanned (measured)", (0, 158, 115, 255), 12.0),
                "true_ml": ("true (simulated plant)", (0, 114, 178, 255), 1.5),
                "uncorrected_ml": ("model's own, before the correction by measured volumes", (230, 159, 0, 200), 1.0)}
#: Surfaces: the deformed phantom (tissue pink, slightly translucent so that the rest shape shows through where
#: the gland has grown over it) and its rest shape (a pale blue ghost).
MESH_RGBA = (235, 150, 140, 200)
REST_GHOST_RGBA = (120, 170, 255, 90)
#: The last scan's surface, over the model's: the scanned volume's green, translucent so that the model's surface
#: shows where it lies inside the scan.
SCAN_RGBA = (0, 158, 115, 110)
#: The anatomical axes drawn in the phantom view: direction, label, colour (x red, y green, z blue, as the viewer's
#: own axes); each arrow is AXIS_MM long, the scale of the view.
ANATOMICAL_AXES = (((1, 0, 0), "x: patient's left", (220, 50, 47)), ((0, 1, 0), "y: anterior", (60, 170, 60)),
                   ((0, 0, 1), "z: apex to base", (50, 110, 220)))
AXIS_MM = 10.0
#: Batching: flush the SDK's chunk batcher this often (s; None: the SDK's default, a few ms). The viewer of a
#: live stream lags by at most this.
FLUSH_TICK_S: float | None = 0.5
#: Whether the .rrd ends with a footer (an index of its chunks, which `rerun rrd verify` requires). The file sink
#: keeps that index in memory until the file is closed, so a long session is written in segments (SEGMENT_S).
WRITE_FOOTER = True
#: A session's file is closed (with its footer) and a new one begun at the same path this often (s).
SEGMENT_S = 20 * 60.0
#: Free space on the recording's file system (bytes) below which recording pauses, and above which it resumes.
PAUSE_BELOW_BYTES = 64 * 2**20
RESUME_ABOVE_BYTES = 128 * 2**20
#: A file that has not grown for this long (s) while rows were logged lost its writer (an I/O error).
STALLED_AFTER_S = 15.0
#: How long a file that seems stalled is given to write out what is queued before it is called stalled (s).
STALL_FLUSH_TIMEOUT_S = 2.0
#: How often (s) :meth:`Recorder.check` looks at the disk and the file.
CHECK_PERIOD_S = 2.0
#: How long (s) a recording whose writer failed waits before it tries a new file.
RETRY_AFTER_S = 30.0
#: How long (s) closing a file may take: the SDK writes what is queued and the footer.
CLOSE_TIMEOUT_S = 30.0
#: Telemetry (50 frames a second, three series a chamber) is held and sent this often (s), one column of frames a
#: series (``send_columns``): a value logged at a time took 560 us of the daemon's event loop a frame, 2.8 % of a
#: core (bench/README.md, "The daemon's idle CPU"). A live viewer's plots lag by at most this.
TELEMETRY_BATCH_S = 0.5
#: The telemetry series of a chamber, in the order a held frame keeps them.
TELEMETRY_SERIES = ("commanded_kpa", "measured_kpa", "drive_level")


class RecordingError(PhantomError):
    """The recording could not be opened (unwritable path, full disk, a path another daemon records to, bad
    viewer address)."""


class RecordingCutShort(UserWarning):
    """The recording ends in the middle of a message (its writer stopped there: a full disk, or it is still being
    written): what comes before it is read, its last bytes are not."""


def entity_part(name: str) -> str:
    """A chamber name as one entity-path part: letters, digits, ``-`` and ``_`` kept, anything else ``_``."""
    return re.sub(r"[^A-Za-z0-9_-]", "_", name) or "_"


def chamber_colour(index: int) -> tuple[int, int, int]:
    return CHAMBER_COLOURS[index % len(CHAMBER_COLOURS)]


def vertex_normals(positions: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Unit vertex normals, each the area-weighted mean of its triangles' normals (triangles counter-clockwise
    seen from outside give outward normals)."""
    corners = positions[triangles]
    face = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    normals = np.zeros_like(positions, dtype=np.float64)
    for k in range(3):
        np.add.at(normals, triangles[:, k], face)
    length = np.linalg.norm(normals, axis=1, keepdims=True)
    return (normals / np.where(length > 0, length, 1.0)).astype(np.float32)


def default_blueprint(chamber_labels: list[str], camera: tuple[np.ndarray, np.ndarray] | None = None) -> Any:
    """The layout: one column of plots per chamber and the gland's volume under them; the phantom on the left
    when ``camera`` (eye position, look target, mm) is given, that is when meshes are logged; the event log."""
    with require_extra("record"):
        import rerun as rr
        import rerun.blueprint as rrb
        import rerun.blueprint.encodings as rrbe

    parts = [entity_part(name) for name in chamber_labels]
    legend = rrb.PlotLegend(corner=rrb.Corner2D.LeftTop)
    no_legend = rrb.PlotLegend(visible=False)
    # the whole recording on the time axis (else, following the latest data, a plot shows only the last minute)
    whole = rrb.TimeAxis(view_range=rr.TimeRange(start=rr.TimeRangeBoundary.infinite(),
                                                 end=rr.TimeRangeBoundary.infinite()))
    columns = []
    for index, (label, part) in enumerate(zip(chamber_labels, parts, strict=True)):
        columns.append(rrb.Vertical(
            rrb.TimeSeriesView(name=f"{label}: pressure (kPa)", origin=f"/chamber/{part}",
                               contents=[f"+ /chamber/{part}/commanded_kpa", f"+ /chamber/{part}/measured_kpa"],
                               plot_legend=legend if index == 0 else no_legend, axis_x=whole),
            rrb.TimeSeriesView(name=f"{label}: drive (0-1)", origin=f"/chamber/{part}",
                               contents=f"+ /chamber/{part}/drive_level", axis_y=rrb.ScalarAxis(range=(0.0, 1.05)),
                               plot_legend=no_legend, axis_x=whole),
            rrb.TimeSeriesView(name=f"{label}: volume (ml)", origin="/volume/chambers",
                               contents=f"+ /volume/chambers/{part}_ml", plot_legend=no_legend, axis_x=whole),
            row_shares=[3, 2, 2]))
    gland = rrb.TimeSeriesView(name="gland volume (ml)", origin="/volume",
                               contents=[f"+ /volume/{series}" for series in GLAND_SERIES], plot_legend=legend,
                               axis_x=whole)
    diagnostics = rrb.Tabs(rrb.TimeSeriesView(name="link", origin="/link", plot_legend=legend, axis_x=whole),
                           rrb.TimeSeriesView(name="solver (ms)", origin="/solver", plot_legend=legend, axis_x=whole),
                           rrb.TimeSeriesView(name="correction (ml; measurements)", origin="/correction",
                                              plot_legend=legend, axis_x=whole))
    plots = rrb.Vertical(rrb.Horizontal(*columns), gland, diagnostics, row_shares=[7, 3, 2])
    events = rrb.TextLogView(origin="/events", name="events", columns=rrb.TextLogColumns(
        timeline_columns=[rrbe.TimelineColumn("time"), rrbe.TimelineColumn("scene_time")],
        text_log_columns=[rrbe.TextLogColumn("loglevel"), rrbe.TextLogColumn("body"),
                          rrbe.TextLogColumn("entitypath", visible=False)]))
    if camera is None:
        layout = rrb.Horizontal(plots, events, column_shares=[3, 1])
    else:
        eye, target = camera
        phantom = rrb.Spatial3DView(
            origin="/phantom", name=f"phantom (mm, grid {AXIS_MM:g} mm): deformed over the rest shape",
            eye_controls=rrb.EyeControls3D(position=eye.tolist(), look_target=target.tolist(), eye_up=[0, 0, 1]),
            line_grid=rrb.LineGrid3D(visible=True, spacing=AXIS_MM))
        layout = rrb.Horizontal(rrb.Vertical(phantom, events, row_shares=[3, 1]), plots, column_shares=[2, 3])
    # following: the view opens at the latest time (the last shape), live or from a file
    time_panel = rrb.TimePanel(timeline="time", state="collapsed", play_state="following")
    return rrb.Blueprint(layout, time_panel, collapse_panels=True)


def axes_origin(positions_mm: np.ndarray) -> np.ndarray:
    """Where the anatomical axes start: beside the rest shape (mm), at its lowest right corner in front, out of
    its way (the camera looks from the front: behind the gland the arrows would be hidden)."""
    low, high = positions_mm.min(axis=0), positions_mm.max(axis=0)
    return np.array([low[0] - AXIS_MM, high[1] + AXIS_MM, low[2] - AXIS_MM])


def fitted_camera(positions_mm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """An eye in front of the phantom (anterior, +y), a little to its left and above, far enough to keep the
    whole rest shape, its growth and the axes beside it in view; and the point it looks at (their centre)."""
    shown = np.vstack([positions_mm, axes_origin(positions_mm)])
    low, high = shown.min(axis=0), shown.max(axis=0)
    centre = (low + high) / 2
    radius = float(np.linalg.norm(high - low)) / 2
    direction = np.array([0.55, 1.0, 0.45])
    return centre + 2.6 * radius * direction / np.linalg.norm(direction), centre


def set_aside(path: Path) -> Path:
    """Rename an existing recording beside itself, stamped with the time it was last written
    (``run.rrd`` -> ``run.20261124-101500.rrd``, ``-2`` etc. if that is taken); returns the new path."""
    stamp = datetime.fromtimestamp(path.stat().st_mtime).strftime("%Y%m%d-%H%M%S")
    candidate = path.with_name(f"{path.stem}.{stamp}{path.suffix}")
    number = 2
    while candidate.exists():
        candidate = path.with_name(f"{path.stem}.{stamp}-{number}{path.suffix}")
        number += 1
    os.rename(path, candidate)
    return candidate


def file_size(path: Path) -> int:
    """The size of a file in bytes (how far the SDK's writer has come)."""
    return path.stat().st_size


def free_bytes(folder: Path) -> int:
    """Bytes an unprivileged writer may still use on the file system of ``folder``."""
    stats = os.statvfs(folder)
    return stats.f_bavail * stats.f_frsize


class PathLock:
    """An exclusive lock on a recording path, held by one daemon for its whole session: a hidden file beside it
    (``.run.rrd.lock``) holding the owner's process id, locked with ``flock`` (released by the kernel when the
    owner dies, however it dies)."""

    def __init__(self, path: Path):
        self.path = path.with_name(f".{path.name}.lock")
        self._file: TextIO | None = None

    def acquire(self, recording: Path) -> None:
        """Take the lock; RecordingError naming the other daemon when it holds it."""
        while True:
            handle = open(self.path, "a+")
            try:
                fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                handle.seek(0)
                owner = handle.read().strip() or "unknown"
                handle.close()
                raise RecordingError(f"{recording} is being recorded by another daemon (process {owner}): give "
                                     "another --rerun-save path, or stop that daemon") from None
            # the lock is on the file this path names now, not on one its previous owner removed meanwhile
            with contextlib.suppress(FileNotFoundError):
                if os.fstat(handle.fileno()).st_ino == os.stat(self.path).st_ino:
                    break
            handle.close()
        handle.seek(0)
        handle.truncate()
        handle.write(f"{os.getpid()}\n")
        handle.flush()
        self._file = handle

    def release(self) -> None:
        if self._file is None:
            return
        with contextlib.suppress(FileNotFoundError):
            self.path.unlink()
        self._file.close()
        self._file = None


class Recorder:
    """A Rerun recording stream with the daemon's logging calls; every call is a no-op when nothing records.

    Nothing is opened until :meth:`open` (so a daemon that refuses to start never touches a file).

    Parameters
    ----------
    chamber_labels : list of str
        The chambers as people name them, in chamber order: the plots' titles and legends and, made path-safe,
        the entity paths.
    save_path : path, optional
        Write ``.rrd`` files here (see the module: an existing file is set aside, never overwritten).
    connect_url : str, optional
        Stream to a viewer (``rerun+http://host:9876/proxy``, as ``rerun`` prints when it starts).
    on_problem : callable(text, level), optional
        Told when recording pauses, fails or resumes (the daemon's events); the log by default.
    clock, free_space : callables, optional
        Seconds (monotonic), and the free bytes of a folder's file system (:func:`free_bytes`).
    """

    def __init__(self, chamber_labels: Sequence[str], save_path: str | Path | None = None,
                 connect_url: str | None = None, on_problem: Callable[[str, str], None] | None = None,
                 clock: Callable[[], float] = time.monotonic, free_space: Callable[[Path], int] = free_bytes):
        self.chamber_labels = list(chamber_labels)
        self.parts = [entity_part(name) for name in self.chamber_labels]
        if len(set(self.parts)) != len(self.parts):
            raise RecordingError(f"chamber names {self.chamber_labels} collide in entity paths ({self.parts}): "
                                 "give the chambers names that differ in letters or digits")
        self.save_path = Path(save_path) if save_path else None
        self.connect_url = connect_url
        self.on_problem = on_problem or (lambda text, level: logger.log(logging.getLevelName(
            "WARNING" if level == "WARN" else level), "%s", text))
        self.clock = clock
        self.free_space = free_space
        self.enabled = False
        #: ``off`` (nothing asked), ``recording``, ``paused`` (the disk is full, or the writer failed)
        self.state = "off"
        self.problem: str | None = None
        #: the files this session wrote, in order (the last is ``save_path`` while recording)
        self.files: list[Path] = []
        #: files of earlier sessions (or segments) set aside by this session
        self.set_aside: list[Path] = []
        # rerun's module and stream, set by open() (rerun is imported only when recording)
        self._rr: Any = None
        self._stream: Any = None
        self._recording_id = ""
        self._lock: PathLock | None = None
        self._scene_time_s: float | None = None
        self._rest: tuple[np.ndarray, np.ndarray] | None = None
        self._mesh_triangles: np.ndarray | None = None
        self._segment_started_s = 0.0
        self._next_check_s = 0.0
        self._retry_at_s = 0.0
        self._size = -1
        self._grew_s = 0.0
        self._logged_since_growth = False
        # telemetry frames held for the next send: their time, scene time (NaN: no scene) and values (one row a
        # frame: TELEMETRY_SERIES of each chamber in turn), and when (clock) the first of them came
        self._held_times_s: list[float] = []
        self._held_scene_times_s: list[float] = []
        self._held_values: list[np.ndarray] = []
        self._held_since_s = 0.0

    @property
    def wants_mesh(self) -> bool:
        """Whether someone records or views, so that computing a shape is worth it."""
        return self.enabled

    def open(self) -> None:
        """Lock the path, set an existing file aside and start writing (or connect to the viewer); the blueprint
        and the series' styles first.

        Raises RecordingError (one line) when the file cannot be written (missing permission, a directory in
        the way, a full disk) or another daemon records to the same path.
        """
        if self._stream is not None or not (self.save_path or self.connect_url):
            return
        with require_extra("record"):
            import rerun as rr

        self._rr = rr
        self._recording_id = str(uuid.uuid4())
        if self.save_path is None:
            self._connect()
            return
        lock = PathLock(self.save_path)
        try:
            self.save_path.parent.mkdir(parents=True, exist_ok=True)
            lock.acquire(self.save_path)
        except OSError as error:
            raise _unwritable(self.save_path, error) from None
        self._lock = lock
        try:
            self._start_segment()
        except BaseException:
            lock.release()
            self._lock = None
            raise

    def _stream_for(self) -> Any:
        rr = self._rr
        batching = None if FLUSH_TICK_S is None else rr.ChunkBatcherConfig(flush_tick=timedelta(seconds=FLUSH_TICK_S))
        return rr.RecordingStream("phantom", recording_id=self._recording_id, batcher_config=batching)

    def _connect(self) -> None:
        stream = self._stream_for()
        try:
            stream.connect_grpc(self.connect_url, default_blueprint=default_blueprint(self.chamber_labels))
        except Exception as error:  # rerun raises plain exceptions for bad addresses
            raise RecordingError(f"cannot record to {self.connect_url}: {error}; give another --rerun-connect "
                                 "address") from error
        self._stream, self.enabled, self.state = stream, True, "recording"
        self._log_styles()

    def _start_segment(self) -> None:
        """Set the file at the path aside (if any) and begin a new one there; RecordingError if it cannot be
        written."""
        assert self.save_path is not None  # only a file has segments
        path = self.save_path
        if path.is_file():  # never a device or a folder: writing to those fails below, with the reason
            aside = set_aside(path)
            if self.files and self.files[-1] == path:
                self.files[-1] = aside  # this session's previous segment
            else:
                self.set_aside.append(aside)
        _check_writable(path)
        stream = self._stream_for()
        camera = None if self._rest is None else fitted_camera(self._rest[0])
        try:
            stream.save(str(path), default_blueprint=default_blueprint(self.chamber_labels, camera),
                        write_footer=WRITE_FOOTER)
        except Exception as error:  # rerun raises plain exceptions for bad paths
            raise RecordingError(f"cannot record to {path}: {error}; give another --rerun-save path") from error
        self._stream, self.enabled, self.state, self.problem = stream, True, "recording", None
        self.files.append(path)
        self._segment_started_s = self._grew_s = self.clock()
        self._size, self._logged_since_growth = -1, False
        self._mesh_triangles = None
        self._log_styles()
        if self._rest is not None:
            self._log_rest(*self._rest)

    def _end_segment(self, timeout_s: float) -> None:
        """Write out what is queued and the footer, and close the file (or the viewer's connection)."""
        self._send_telemetry()
        stream, self._stream, self.enabled = self._stream, None, False
        if stream is None:
            return
        try:
            stream.flush(timeout_sec=timeout_s)
        except Exception as error:  # RuntimeError from the SDK: its writer died (a full disk), or a viewer is gone
            logger.warning("the recording could not be written out (%s); what was not written is lost", error)
        stream.disconnect()

    def _log_styles(self) -> None:
        """Series names, colours and widths, once per file (static: they hold on every timeline)."""
        rr, log = self._rr, self._stream.log
        colour: tuple[int, ...]
        for index, (label, part) in enumerate(zip(self.chamber_labels, self.parts, strict=True)):
            colour = chamber_colour(index)
            log(f"chamber/{part}/commanded_kpa", rr.SeriesLines(
                colors=[(*colour, SETPOINT_ALPHA)], names=[f"{label} setpoint"], widths=[SETPOINT_WIDTH],
                interpolation_mode=rr.components.InterpolationMode.StepAfter), static=True)
            log(f"chamber/{part}/measured_kpa", rr.SeriesLines(colors=[colour], names=[f"{label} measured"],
                                                               widths=[MEASURED_WIDTH]), static=True)
            log(f"chamber/{part}/drive_level", rr.SeriesLines(colors=[colour], names=[label],
                                                              widths=[MEASURED_WIDTH]), static=True)
            log(f"volume/chambers/{part}_ml", rr.SeriesLines(colors=[colour], names=[label],
                                                             widths=[MEASURED_WIDTH]), static=True)
        for series, (label, colour, width) in GLAND_SERIES.items():
            # the target as dots (10 Hz, dense enough to read as a line): where there is none (vented, or a
            # pressure target with no prediction) no dots, where a line would bridge the gap
            # the scans as big dots: one a scan, where a line would join scans minutes apart
            style = rr.SeriesPoints(colors=[colour], names=[label], marker_sizes=[width / 2]) if series in (
                "commanded_ml", "scanned_ml") else rr.SeriesLines(colors=[colour], names=[label], widths=[width])
            log(f"volume/{series}", style, static=True)
        for series, label in (("size_ml", "correction's size (ml)"), ("measurements", "measurements")):
            log(f"correction/{series}", rr.SeriesLines(names=[label], widths=[MEASURED_WIDTH]), static=True)
        log("phantom", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)

    # --- health: segments, a full disk, a failed writer -------------------------------------------------

    def check(self) -> None:
        """Called often (the daemon's control loop); at most every :data:`CHECK_PERIOD_S` it looks at the file:
        a new segment when this one is old, a pause when the disk fills up or the file stops growing, a resume
        once there is room again. Each change is told to ``on_problem``."""
        now_s = self.clock()
        if self._held_times_s and now_s - self._held_since_s >= TELEMETRY_BATCH_S:
            self._send_telemetry()
        if self.save_path is None or self._lock is None or now_s < self._next_check_s:
            return
        self._next_check_s = now_s + CHECK_PERIOD_S
        folder = self.save_path.parent
        try:
            free = self.free_space(folder)
        except OSError as error:
            free, why = 0, f"its folder cannot be read ({error.strerror})"
        else:
            why = f"only {free / 2**20:.0f} MB are free on the disk of {self.save_path}"
        if self.state == "recording":
            if free < PAUSE_BELOW_BYTES:
                self._pause(f"{why}; it resumes in a new file once {RESUME_ABOVE_BYTES / 2**20:.0f} MB are free")
            elif self._stalled(now_s):
                self._retry_at_s = now_s + RETRY_AFTER_S
                self._pause(f"{self.save_path} stopped growing for {STALLED_AFTER_S:g} s while data came: its "
                            f"writer failed (see the daemon's log); a new file is tried in {RETRY_AFTER_S:g} s")
            elif now_s - self._segment_started_s >= SEGMENT_S:
                self._end_segment(CLOSE_TIMEOUT_S)
                self._start_segment()
        elif self.state == "paused" and free >= RESUME_ABOVE_BYTES and now_s >= self._retry_at_s:
            try:
                self._start_segment()
            except RecordingError as error:
                self.problem = str(error)
                return
            self.on_problem(f"recording resumed in {self.save_path} ({free / 2**20:.0f} MB free)", "INFO")

    def _stalled(self, now_s: float) -> bool:
        """Whether the file has not grown for STALLED_AFTER_S while rows were logged (the SDK writes in the
        background: a dead writer only prints an error)."""
        assert self.save_path is not None  # only a file is checked
        try:
            size = file_size(self.save_path)
        except OSError:
            return True
        if size != self._size:
            self._size, self._grew_s, self._logged_since_growth = size, now_s, False
            return False
        if not (self._logged_since_growth and now_s - self._grew_s >= STALLED_AFTER_S):
            return False
        # a busy machine's writer may only be late: ask it to write out what is queued before calling it dead
        self._send_telemetry()
        if self._stream is not None:
            try:
                self._stream.flush(timeout_sec=STALL_FLUSH_TIMEOUT_S)
            except Exception:  # RuntimeError from the SDK: its writer died
                return True
        try:
            flushed_size = file_size(self.save_path)
        except OSError:
            return True
        if flushed_size == size:
            return True
        self._size, self._grew_s, self._logged_since_growth = flushed_size, now_s, False
        return False

    def _pause(self, why: str) -> None:
        self._end_segment(timeout_s=1.0)
        self.state, self.problem = "paused", why
        self.on_problem(f"recording paused: {why}", "ERROR")

    def status(self) -> dict[str, Any] | None:
        """What ``phantom status`` shows of the recording (None when nothing records)."""
        if self.save_path is None and self.connect_url is None:
            return None
        return {"path": str(self.save_path) if self.save_path else None, "viewer": self.connect_url,
                "state": self.state, "problem": self.problem, "files": [str(path) for path in self.files],
                "set_aside": [str(path) for path in self.set_aside]}

    # --- what is logged ---------------------------------------------------------------------------------

    def set_scene_time(self, scene_time_s: float | None) -> None:
        """Seconds into the running scene's timeline (None: no scene runs); stamps later logs on ``scene_time``."""
        self._scene_time_s = None if scene_time_s is None else float(scene_time_s)

    def _at(self, time_s: float) -> None:
        self._logged_since_growth = True
        self._stream.set_time("time", duration=float(time_s))
        if self._scene_time_s is None:
            self._stream.disable_timeline("scene_time")
        else:
            self._stream.set_time("scene_time", duration=self._scene_time_s)

    def _scalar(self, path: str, value: float | None) -> None:
        if value is not None and np.isfinite(value):
            self._stream.log(path, self._rr.Scalars(float(value)))

    def log_telemetry(self, time_s: float, measured_kpa: np.ndarray, setpoint_kpa: np.ndarray,
                      drive_levels: np.ndarray) -> None:
        """Per chamber: measured and set pressure (kPa) and drive level (0..1). Held, and sent with the frames of
        the next :data:`TELEMETRY_BATCH_S` (by this call or :meth:`check`); a value that is not finite is left out."""
        if not self.enabled:
            return
        self._logged_since_growth = True
        now_s = self.clock()
        if not self._held_times_s:
            self._held_since_s = now_s
        self._held_times_s.append(float(time_s))
        self._held_scene_times_s.append(np.nan if self._scene_time_s is None else self._scene_time_s)
        self._held_values.append(np.column_stack([setpoint_kpa, measured_kpa, drive_levels]).astype(float).ravel())
        if now_s - self._held_since_s >= TELEMETRY_BATCH_S:
            self._send_telemetry()

    def _send_telemetry(self) -> None:
        """Send the held telemetry frames: per series, its finite values at their times (and scene times, for the
        frames logged while a scene ran)."""
        if not self._held_times_s:
            return
        times_s, scene_times_s = np.array(self._held_times_s), np.array(self._held_scene_times_s)
        values = np.vstack(self._held_values)
        self._held_times_s, self._held_scene_times_s, self._held_values = [], [], []
        if self._stream is None:
            return
        rr = self._rr
        in_scene = np.isfinite(scene_times_s)
        paths = [f"chamber/{part}/{series}" for part in self.parts for series in TELEMETRY_SERIES]
        for column, path in enumerate(paths):
            finite = np.isfinite(values[:, column])
            for rows in (finite & in_scene, finite & ~in_scene):
                if not rows.any():
                    continue
                indexes = [rr.TimeColumn("time", duration=times_s[rows])]
                if in_scene[rows][0]:
                    indexes.append(rr.TimeColumn("scene_time", duration=scene_times_s[rows]))
                self._stream.send_columns(path, indexes=indexes,
                                          columns=rr.Scalars.columns(scalars=values[rows, column]))

    def log_volumes(self, time_s: float, target_ml: float | None, estimated_ml: float | None,
                    chamber_ml: Sequence[float] | None = None, true_ml: float | None = None,
                    model_ml: float | None = None) -> None:
        """Target and estimated gland volume, the true one when a simulated plant knows it, the model's own
        (uncorrected) estimate while a correction is in force, and the estimated chamber volumes (all ml)."""
        if not self.enabled:
            return
        self._at(time_s)
        self._scalar("volume/commanded_ml", target_ml)
        self._scalar("volume/estimated_ml", estimated_ml)
        self._scalar("volume/true_ml", true_ml)
        self._scalar("volume/uncorrected_ml", model_ml)
        if chamber_ml is not None:
            for part, volume_ml in zip(self.parts, chamber_ml, strict=True):
                self._scalar(f"volume/chambers/{part}_ml", volume_ml)

    def log_correction(self, time_s: float, size_ml: float | None, count: int) -> None:
        """The correction in force by the phantom's measured volumes: its size (its largest magnitude over the
        pressure box, ml; 0 without one) and from how many measurements."""
        if not self.enabled:
            return
        self._at(time_s)
        self._scalar("correction/size_ml", 0.0 if size_ml is None else size_ml)
        self._scalar("correction/measurements", float(count))

    def log_scanned_volume(self, time_s: float, volume_ml: float, round_: int, tolerance_pct: float) -> None:
        """A verified target's scan: its gland volume (ml, reconstructed: measured) on the volume plot, at the time
        of the scan, with its round (1 for a target's first scan) and the tolerance asked (%), which ``phantom
        report`` groups and judges the scans by."""
        if not self.enabled:
            return
        self._at(time_s)
        self._scalar("volume/scanned_ml", volume_ml)
        self._scalar("verify/round", float(round_))
        self._scalar("verify/tolerance_pct", tolerance_pct)

    def log_scan_surface(self, time_s: float, positions_mm: np.ndarray, triangles: np.ndarray) -> None:
        """A scan's reconstructed surface (mm, the model's frame) over the model's, at the time of the scan; it
        stands until the next scan's."""
        if not self.enabled:
            return
        self._at(time_s)
        positions = np.asarray(positions_mm, np.float32)
        triangles = np.asarray(triangles, np.uint32)
        self._stream.log("phantom/scan", self._rr.Mesh3D(vertex_positions=positions, triangle_indices=triangles,
                                                         vertex_normals=vertex_normals(positions, triangles),
                                                         albedo_factor=SCAN_RGBA))

    def log_link(self, time_s: float, rtt_ms: float | None, retries: int, bad_frames: int, dropped: int) -> None:
        """Round-trip time (ms) and the link's cumulative counters."""
        if not self.enabled:
            return
        self._at(time_s)
        self._scalar("link/rtt_ms", rtt_ms)
        self._scalar("link/retries", retries)
        self._scalar("link/bad_frames", bad_frames)
        self._scalar("link/dropped", dropped)

    def log_solver(self, time_s: float, qp_time_s: float, solve_time_s: float) -> None:
        """The inverse's QP time and whole solve time (logged in ms)."""
        if not self.enabled:
            return
        self._at(time_s)
        self._scalar("solver/qp_time_ms", 1e3 * qp_time_s)
        self._scalar("solver/solve_time_ms", 1e3 * solve_time_s)

    def log_event(self, time_s: float, text: str, level: str = "INFO") -> None:
        """A text event (fault, reconnect, new target ...); ``level`` is INFO, WARN or ERROR."""
        if not self.enabled:
            return
        self._at(time_s)
        self._stream.log("events", self._rr.TextLog(text, level=level))

    def log_rest_surface(self, positions_mm: np.ndarray, triangles: np.ndarray) -> None:
        """The rest shape (mm) as a translucent ghost, with the anatomical axes beside it, once, before the first
        :meth:`log_mesh`; it also puts the phantom view into the layout with a camera fitted to this shape (and
        into every later segment of the session)."""
        self._rest = (np.asarray(positions_mm, np.float32), np.asarray(triangles, np.uint32))
        if self.enabled:
            self._log_rest(*self._rest)

    def _log_rest(self, positions: np.ndarray, triangles: np.ndarray) -> None:
        rr, log = self._rr, self._stream.log
        log("phantom/rest", rr.Mesh3D(vertex_positions=positions, triangle_indices=triangles,
                                      vertex_normals=vertex_normals(positions, triangles),
                                      albedo_factor=REST_GHOST_RGBA), static=True)
        corner = axes_origin(positions)
        log("phantom/axes", rr.Arrows3D(
            origins=[corner] * len(ANATOMICAL_AXES),
            vectors=[np.asarray(direction, float) * AXIS_MM for direction, _, _ in ANATOMICAL_AXES],
            labels=[f"{label} ({AXIS_MM:g} mm)" for _, label, _ in ANATOMICAL_AXES], show_labels=True,
            colors=[colour for _, _, colour in ANATOMICAL_AXES], radii=0.3), static=True)
        self._stream.send_blueprint(default_blueprint(self.chamber_labels, fitted_camera(positions)))

    def log_mesh(self, time_s: float, positions_mm: np.ndarray, triangles: np.ndarray) -> None:
        """The deformed outer surface: vertex positions (mm, (n, 3)) and triangles ((k, 3) indices)."""
        if not self.enabled:
            return
        self._at(time_s)
        positions = np.asarray(positions_mm, np.float32)
        triangles = np.asarray(triangles, np.uint32)
        normals = vertex_normals(positions, triangles)
        if self._mesh_triangles is not None and np.array_equal(triangles, self._mesh_triangles):
            # the same surface moved: only the vertices change (the viewer keeps the latest triangles and colour),
            # a third less per mesh in the file
            self._stream.log("phantom/mesh", self._rr.Mesh3D.from_fields(vertex_positions=positions,
                                                                          vertex_normals=normals))
            return
        self._mesh_triangles = triangles
        self._stream.log("phantom/mesh", self._rr.Mesh3D(vertex_positions=positions, triangle_indices=triangles,
                                                         vertex_normals=normals, albedo_factor=MESH_RGBA))

    def close(self) -> None:
        """Write out and close the recording (the file is complete, with its footer) and release its path."""
        if self._stream is not None:
            # a file is written out completely; a viewer that is gone must not hold the daemon's shutdown
            self._end_segment(CLOSE_TIMEOUT_S if self.save_path is not None else 1.0)
        if self.state != "off":
            self.state = "closed"
        if self._lock is not None:
            self._lock.release()
            self._lock = None


def _unwritable(path: Path, error: OSError) -> RecordingError:
    """A one-line RecordingError for an OSError met writing ``path``: what was wrong and what to do."""
    reason = {errno.ENOSPC: "the disk is full", errno.EDQUOT: "the disk quota is exhausted",
              errno.EACCES: "permission denied", errno.EPERM: "permission denied",
              errno.EISDIR: "it is a directory", errno.EROFS: "the file system is read-only",
              errno.ENOTDIR: "a part of the path is not a directory",
              errno.EEXIST: "a part of the path is not a directory"}.get(error.errno or 0, error.strerror or "")
    remedy = "free some space or give another --rerun-save path" if error.errno in (errno.ENOSPC, errno.EDQUOT) \
        else "give another --rerun-save path"
    return RecordingError(f"cannot write the recording {path}: {reason}; {remedy}")


def _check_writable(path: Path) -> None:
    """Create the folder and the file, and write a little to it, so an unwritable path or a full disk is a
    one-line error now rather than a failure in the SDK's writer thread later."""
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        with open(path, "wb") as file:
            file.write(b"\0" * 65536)
            file.flush()
            os.fsync(file.fileno())
            file.truncate(0)
    except OSError as error:
        raise _unwritable(path, error) from None


#: Timelines read_rrd converts to seconds.
TIMELINES = ("time", "scene_time")


def read_rrd(path: str | Path, skip: frozenset[str] = frozenset()) -> dict[str, dict[str, list[Any]]]:
    """Read an ``.rrd`` back: entity path -> component column -> list of logged values (in ``time`` order).

    ``time`` and ``scene_time`` keys hold those timelines in seconds (``scene_time`` None for rows logged while
    no scene ran). Used by tests, by ``make demo`` and by ``phantom report``. The columns named in ``skip``
    (``"ENTITY:COMPONENT"``, e.g. ``"/phantom/mesh:Mesh3D:vertex_positions"``) are not read (their rows' times
    are): a report of a long recording with its meshes as lists of Python floats took 2.9 GB
    (:func:`read_points_at` reads the few rows of points wanted). A file cut short in the middle of a message is
    read up to it, with a :class:`RecordingCutShort` warning that says how many bytes were not read.
    """
    entities: dict[str, dict[str, list[Any]]] = {}
    for chunk in _chunks(path, compacted=True):
        batch = chunk.to_record_batch()
        columns = entities.setdefault(str(chunk.entity_path), {})
        before = len(columns.get("time", []))
        for name in batch.column_names:
            if name in TIMELINES:
                values = [None if ns is None else ns / 1e9 for ns in batch.column(name).cast("int64").to_pylist()]
                column = columns.setdefault(name, [])
                column.extend([None] * (before - len(column)))
            elif name.startswith("rerun.") or name in ("log_time", "log_tick") \
                    or f"{chunk.entity_path}:{name}" in skip:
                continue
            else:
                values = batch.column(name).to_pylist()
                column = columns.setdefault(name, [])
            column.extend(values)
        if "time" in columns:  # rows logged while no scene ran have no scene_time
            scene_time = columns.setdefault("scene_time", [])
            scene_time.extend([None] * (len(columns["time"]) - len(scene_time)))
    for columns in entities.values():
        if "time" in columns:
            order = np.argsort(columns["time"], kind="stable")
            for name in list(columns):
                if len(columns[name]) == len(order):
                    columns[name] = [columns[name][i] for i in order]
    return entities


def _chunks(path: str | Path, compacted: bool = False) -> Iterator[Any]:
    """The recording's chunks: the reader's lazy stream, one at a time as written (a long recording is not held
    whole), or ``compacted`` (collected first: each entity's rows together, what :func:`read_rrd`'s columns
    assume). A file cut short in the middle of a message is read up to that message (rerun's reader refuses the
    whole file: "Message payload ... exceeds file size"), from a copy of what comes before it in the temporary
    folder, and :class:`RecordingCutShort` says how many bytes were not read."""
    with require_extra("record"):
        from rerun.chunk import RrdReader

    with contextlib.ExitStack() as stack:
        whole = _whole_messages_end(path)
        if whole is not None:
            unread = os.path.getsize(path) - whole
            copy = stack.enter_context(tempfile.NamedTemporaryFile(prefix="cut-short.", suffix=".rrd"))
            _copy_head(path, whole, copy)
            warnings.warn(RecordingCutShort(
                f"{path} ends cut short, in the middle of a message (its writer stopped there: a full disk, or it "
                f"is still being written): its last {unread} bytes are not read"), stacklevel=3)
        with warnings.catch_warnings():  # "no footer": a crashed session's file has none; stream() reads it all
            warnings.filterwarnings("ignore", message="RRD file has no footer")
            reader = RrdReader(str(path) if whole is None else copy.name)
        yield from (reader.stream().collect().stream() if compacted else reader.stream())


#: An .rrd stream: a header ("RRF2", the format's version, the encoding options), then messages, each a header
#: (its kind and its payload's length, little-endian u64s) and its payload; kinds 1-3 are data (the store's info,
#: chunks, the blueprint's activation), kind 0 ends the stream (its payload and what follows: the footer).
RRD_MAGIC = b"RRF2"
RRD_HEADER_BYTES = 12
RRD_MESSAGE_HEADER = struct.Struct("<QQ")
RRD_MESSAGE_KINDS = (0, 1, 2, 3)


def _whole_messages_end(path: str | Path) -> int | None:
    """Where the file's whole messages end when it ends in the middle of one (in its header or its payload); None
    when it ends where a message does (with or without the end of the stream and its footer) or is not a stream
    of the messages above (rerun's reader judges it). Only the messages' headers are read."""
    size = os.path.getsize(path)
    with open(path, "rb") as file:
        if size <= RRD_HEADER_BYTES or file.read(len(RRD_MAGIC)) != RRD_MAGIC:
            return None
        end = RRD_HEADER_BYTES
        while end < size:
            file.seek(end)
            header = file.read(RRD_MESSAGE_HEADER.size)
            if len(header) < RRD_MESSAGE_HEADER.size:
                return end
            kind, length = RRD_MESSAGE_HEADER.unpack(header)
            if kind not in RRD_MESSAGE_KINDS:
                return None
            if end + RRD_MESSAGE_HEADER.size + length > size:
                return end
            if kind == 0:
                return None
            end += RRD_MESSAGE_HEADER.size + length
    return None


def _copy_head(path: str | Path, length: int, target: IO[bytes]) -> None:
    """Copy the first ``length`` bytes of the file at ``path`` to ``target`` (a MB at a time)."""
    with open(path, "rb") as source:
        while length > 0 and (block := source.read(min(length, 2**20))):
            target.write(block)
            length -= len(block)
    target.flush()


def read_points_at(path: str | Path, entity: str, component: str, times_s: set[float]) -> dict[float, np.ndarray]:
    """The rows of ``entity``'s ``component`` (lists of 3D points, e.g. a mesh's ``Mesh3D:vertex_positions``)
    logged at ``times_s`` (the ``time`` timeline, s, as :func:`read_rrd` gives it), each an (n, 3) float32 array:
    a second pass over the recording that converts only those rows."""
    found: dict[float, np.ndarray] = {}
    for chunk in _chunks(path):
        if str(chunk.entity_path) != entity:
            continue
        batch = chunk.to_record_batch()
        if "time" not in batch.column_names or component not in batch.column_names:
            continue
        times = batch.column("time").cast("int64").to_pylist()
        column = batch.column(component)
        for row, ns in enumerate(times):
            if ns is not None and ns / 1e9 in times_s and column[row].is_valid:
                points = column[row].values.flatten().to_numpy(zero_copy_only=False)
                found[ns / 1e9] = np.asarray(points, dtype=np.float32).reshape(-1, 3)
    return found
