"""Rerun logging of what the daemon does: pressures, volumes, link statistics, solver time, events, the mesh.

Entity paths (``<chamber>`` is the chamber's name with anything but letters, digits, ``-`` and ``_`` turned
into ``_``; the legends show the name itself):

    chamber/<chamber>/measured_kpa, setpoint_kpa, drive_level   per chamber, from telemetry
    volume/target_ml, volume/estimated_ml, volume/true_ml       the gland (true: the simulated plant's)
    volume/chambers/<chamber>_ml                                estimated chamber volumes
    link/rtt_ms, link/retries, link/bad_frames, link/dropped    link statistics
    solver/qp_time_ms, solver/solve_time_ms                     the inverse
    events                                                      text log: faults, reconnects, targets
    phantom/mesh, phantom/rest                                  deformed outer surface (mm) and its rest shape

Timelines: ``time`` (seconds since the daemon started) on everything, and ``scene_time`` (seconds into the
running scene's timeline) on what is logged while a scene runs, so that a scene's steps line up with its file.
The SDK adds ``log_time`` (the wall clock).

The blueprint (the layout the viewer opens with) gives each quantity its own plot with its own scale: pressures
(measured thin, setpoint wide and translucent, one colour per chamber), drive levels (0-1), the gland volume,
one small plot per chamber volume, link and solver; legends sit in the top-left corner, where a recording that
starts vented has no data. The phantom view (only when meshes are logged) shows the deformed surface with
normals over a translucent rest-shape ghost, anatomical axes (x left, y anterior, z apex to base) and a camera
fitted to the rest shape.

Memory stays bounded while recording: the ``.rrd`` is written without a footer (a footer makes the file sink
keep every chunk's metadata until the end: about 5 MB more per minute at the daemon's rates with the SDK's
default batching), and the chunk batcher flushes every 0.5 s rather than every few milliseconds, so a telemetry
series is one chunk per half second rather than one per frame. A moving mesh sends its triangles once.
``bench/recording_memory.py`` measures it.
"""

from __future__ import annotations

import errno
import logging
import os
import re
import warnings
from collections.abc import Sequence
from datetime import timedelta
from pathlib import Path
from typing import Any

import numpy as np

from phantom import PhantomError, require_extra

logger = logging.getLogger(__name__)

#: One fixed colour per chamber, in chamber order (Okabe-Ito, distinguishable with the common colour-vision
#: deficiencies and on the viewer's dark background): orange, sky blue, bluish green, vermillion, blue, purple.
CHAMBER_COLOURS = ((230, 159, 0), (86, 180, 233), (0, 158, 115), (213, 94, 0), (0, 114, 178), (204, 121, 167))
#: Setpoints: the chamber's colour, translucent and wide, so the measured line shows on top of it.
SETPOINT_ALPHA = 110
SETPOINT_WIDTH = 5.0
MEASURED_WIDTH = 1.5
#: Gland volume series: target (grey dots, translucent: readable on the light and the dark theme), estimate
#: (purple), the simulated plant's true volume (blue); none is a chamber's colour. Widths in points.
GLAND_SERIES = {"target_ml": ("target", (128, 128, 128, 130), 5.0),
                "estimated_ml": ("estimate", (204, 121, 167, 255), 1.5),
                "true_ml": ("true (simulated plant)", (0, 114, 178, 255), 1.5)}
#: Surfaces: the deformed phantom (tissue pink, slightly translucent so that the rest shape shows through where
#: the gland has grown over it) and its rest shape (a pale blue ghost).
MESH_RGBA = (235, 150, 140, 200)
REST_GHOST_RGBA = (120, 170, 255, 90)
#: Batching: flush the SDK's chunk batcher this often (s; None: the SDK's default, a few ms). The viewer of a
#: live stream lags by at most this.
FLUSH_TICK_S: float | None = 0.5
#: Whether the .rrd ends with a footer (an index of its chunks). The file sink keeps that index in memory until
#: the end, so it grows with the recording: off.
WRITE_FOOTER = False


class RecordingError(PhantomError):
    """The recording could not be opened (unwritable path, full disk, bad viewer address)."""


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


def default_blueprint(chamber_names: list[str], camera: tuple[np.ndarray, np.ndarray] | None = None) -> Any:
    """The layout: plots on the right, one per quantity; the phantom on the left when ``camera`` (eye position,
    look target, mm) is given, that is when meshes are logged; the event log under it."""
    with require_extra("record"):
        import rerun as rr
        import rerun.blueprint as rrb
        import rerun.blueprint.encodings as rrbe

    parts = [entity_part(name) for name in chamber_names]
    legend = rrb.PlotLegend(corner=rrb.Corner2D.LeftTop)
    # the whole recording on the time axis (else, following the latest data, a plot shows only the last minute)
    whole = rrb.TimeAxis(view_range=rr.TimeRange(start=rr.TimeRangeBoundary.infinite(),
                                                 end=rr.TimeRangeBoundary.infinite()))
    pressures = rrb.TimeSeriesView(
        name="pressure (kPa): measured (thin), setpoint (wide)", origin="/chamber",
        contents=[f"+ /chamber/{part}/{series}" for part in parts for series in ("setpoint_kpa", "measured_kpa")],
        plot_legend=legend, axis_x=whole)
    drives = rrb.TimeSeriesView(
        name="drive level (0-1)", origin="/chamber", contents=[f"+ /chamber/{part}/drive_level" for part in parts],
        axis_y=rrb.ScalarAxis(range=(0.0, 1.05)), plot_legend=legend, axis_x=whole)
    gland = rrb.TimeSeriesView(name="gland volume (ml)", origin="/volume",
                               contents=[f"+ /volume/{series}" for series in GLAND_SERIES], plot_legend=legend,
                               axis_x=whole)
    chambers = rrb.Horizontal(*[
        rrb.TimeSeriesView(name=f"{name} (ml)", origin="/volume/chambers", contents=f"+ /volume/chambers/{part}_ml",
                           plot_legend=rrb.PlotLegend(visible=False), axis_x=whole)
        for name, part in zip(chamber_names, parts, strict=True)])
    diagnostics = rrb.Tabs(rrb.TimeSeriesView(name="link", origin="/link", plot_legend=legend, axis_x=whole),
                           rrb.TimeSeriesView(name="solver (ms)", origin="/solver", plot_legend=legend, axis_x=whole))
    plots = rrb.Vertical(pressures, drives, gland, chambers, diagnostics, row_shares=[3, 2, 2, 2, 2])
    events = rrb.TextLogView(origin="/events", name="events", columns=rrb.TextLogColumns(
        timeline_columns=[rrbe.TimelineColumn("time"), rrbe.TimelineColumn("scene_time")],
        text_log_columns=[rrbe.TextLogColumn("loglevel"), rrbe.TextLogColumn("body"),
                          rrbe.TextLogColumn("entitypath", visible=False)]))
    if camera is None:
        layout = rrb.Horizontal(plots, events, column_shares=[3, 1])
    else:
        eye, target = camera
        phantom = rrb.Spatial3DView(
            origin="/phantom", name="phantom (mm): deformed over the rest shape",
            eye_controls=rrb.EyeControls3D(position=eye.tolist(), look_target=target.tolist(), eye_up=[0, 0, 1]),
            line_grid=rrb.LineGrid3D(visible=True, spacing=10.0))
        layout = rrb.Horizontal(rrb.Vertical(phantom, events, row_shares=[3, 1]), plots, column_shares=[2, 3])
    # following: the view opens at the latest time (the last shape), live or from a file
    time_panel = rrb.TimePanel(timeline="time", state="collapsed", play_state="following")
    return rrb.Blueprint(layout, time_panel, collapse_panels=True)


def fitted_camera(positions_mm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """An eye in front of the phantom (anterior, +y), a little to its left and above, far enough to keep the
    whole rest shape and its growth in view; and the point it looks at (the rest shape's centre)."""
    low, high = positions_mm.min(axis=0), positions_mm.max(axis=0)
    centre = (low + high) / 2
    radius = float(np.linalg.norm(high - low)) / 2
    direction = np.array([0.55, 1.0, 0.45])
    return centre + 2.6 * radius * direction / np.linalg.norm(direction), centre


class Recorder:
    """A Rerun recording stream with the daemon's logging calls; every call is a no-op when disabled.

    Nothing is opened until :meth:`open` (so a daemon that refuses to start never touches a file).

    Parameters
    ----------
    chamber_names : list of str
        Chamber names, shown in legends and plot titles (and, made path-safe, in entity paths).
    save_path : path, optional
        Write an ``.rrd`` file here.
    connect_url : str, optional
        Stream to a viewer (``rerun+http://host:9876/proxy``, as ``rerun`` prints when it starts).
    """

    def __init__(self, chamber_names: list[str], save_path: str | Path | None = None, connect_url: str | None = None):
        self.chamber_names = list(chamber_names)
        self.parts = [entity_part(name) for name in self.chamber_names]
        if len(set(self.parts)) != len(self.parts):
            raise RecordingError(f"chamber names {self.chamber_names} collide in entity paths ({self.parts}): "
                                 "give the chambers names that differ in letters or digits")
        self.save_path = Path(save_path) if save_path else None
        self.connect_url = connect_url
        self.enabled = False
        # rerun's module and stream, set by open() (rerun is imported only when recording)
        self._rr: Any = None
        self._stream: Any = None
        self._scene_time_s: float | None = None
        self._rest_logged = False
        self._mesh_triangles: np.ndarray | None = None

    @property
    def wants_mesh(self) -> bool:
        """Whether someone records or views, so that computing a shape is worth it."""
        return self.enabled

    def open(self) -> None:
        """Open the file (truncating it) or connect to the viewer, and write the blueprint and series styles.

        Raises RecordingError (one line) when the file cannot be written: missing permission, a directory in the
        way, a full disk.
        """
        if self._stream is not None or not (self.save_path or self.connect_url):
            return
        # the SDK warns on stderr, at every start, that a file without a footer is slower to seek: that is the
        # choice made above (WRITE_FOOTER), not news for the daemon's log; a RUST_LOG the user set wins
        os.environ.setdefault("RUST_LOG", "warn,re_log_encoding::rrd::file_sink=error")
        with require_extra("record"):
            import rerun as rr

        if self.save_path is not None:
            _check_writable(self.save_path)
        self._rr = rr
        batching = None if FLUSH_TICK_S is None else rr.ChunkBatcherConfig(flush_tick=timedelta(seconds=FLUSH_TICK_S))
        stream = rr.RecordingStream("phantom", batcher_config=batching)
        blueprint = default_blueprint(self.chamber_names)
        try:
            if self.save_path is not None:
                stream.save(str(self.save_path), default_blueprint=blueprint, write_footer=WRITE_FOOTER)
            else:
                stream.connect_grpc(self.connect_url, default_blueprint=blueprint)
        except Exception as error:  # rerun raises plain exceptions for bad paths and addresses
            target = self.save_path or self.connect_url
            raise RecordingError(f"cannot record to {target}: {error}; give another --rerun-save path or "
                                 "--rerun-connect address") from error
        self._stream = stream
        self.enabled = True
        self._log_styles()

    def _log_styles(self) -> None:
        """Series names, colours and widths, once (static: they hold on every timeline)."""
        rr, log = self._rr, self._stream.log
        colour: tuple[int, ...]
        for index, (name, part) in enumerate(zip(self.chamber_names, self.parts, strict=True)):
            colour = chamber_colour(index)
            log(f"chamber/{part}/measured_kpa", rr.SeriesLines(colors=[colour], names=[name],
                                                               widths=[MEASURED_WIDTH]), static=True)
            log(f"chamber/{part}/setpoint_kpa", rr.SeriesLines(
                colors=[(*colour, SETPOINT_ALPHA)], names=[f"{name} setpoint"], widths=[SETPOINT_WIDTH],
                interpolation_mode=rr.components.InterpolationMode.StepAfter), static=True)
            log(f"chamber/{part}/drive_level", rr.SeriesLines(colors=[colour], names=[name],
                                                              widths=[MEASURED_WIDTH]), static=True)
            log(f"volume/chambers/{part}_ml", rr.SeriesLines(colors=[colour], names=[name],
                                                             widths=[MEASURED_WIDTH]), static=True)
        for series, (label, colour, width) in GLAND_SERIES.items():
            # the target as dots (10 Hz, dense enough to read as a line): where there is none (vented, or a
            # pressure target with no prediction) no dots, where a line would bridge the gap
            style = rr.SeriesPoints(colors=[colour], names=[label], marker_sizes=[width / 2]) if series == (
                "target_ml") else rr.SeriesLines(colors=[colour], names=[label], widths=[width])
            log(f"volume/{series}", style, static=True)
        log("phantom", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)

    def set_scene_time(self, scene_time_s: float | None) -> None:
        """Seconds into the running scene's timeline (None: no scene runs); stamps later logs on ``scene_time``."""
        self._scene_time_s = None if scene_time_s is None else float(scene_time_s)

    def _at(self, time_s: float) -> None:
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
        """Per chamber: measured and set pressure (kPa) and drive level (0..1)."""
        if not self.enabled:
            return
        self._at(time_s)
        for index, part in enumerate(self.parts):
            self._scalar(f"chamber/{part}/measured_kpa", measured_kpa[index])
            self._scalar(f"chamber/{part}/setpoint_kpa", setpoint_kpa[index])
            self._scalar(f"chamber/{part}/drive_level", drive_levels[index])

    def log_volumes(self, time_s: float, target_ml: float | None, estimated_ml: float | None,
                    chamber_ml: Sequence[float] | None = None, true_ml: float | None = None) -> None:
        """Target and estimated gland volume, the true one when a simulated plant knows it, and the estimated
        chamber volumes (all ml)."""
        if not self.enabled:
            return
        self._at(time_s)
        self._scalar("volume/target_ml", target_ml)
        self._scalar("volume/estimated_ml", estimated_ml)
        self._scalar("volume/true_ml", true_ml)
        if chamber_ml is not None:
            for part, volume_ml in zip(self.parts, chamber_ml, strict=True):
                self._scalar(f"volume/chambers/{part}_ml", volume_ml)

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
        """The rest shape (mm) as a translucent ghost, once, before the first :meth:`log_mesh`; it also puts the
        phantom view into the layout with a camera fitted to this shape."""
        if not self.enabled:
            return
        positions = np.asarray(positions_mm, np.float32)
        triangles = np.asarray(triangles, np.uint32)
        self._stream.log("phantom/rest", self._rr.Mesh3D(
            vertex_positions=positions, triangle_indices=triangles, vertex_normals=vertex_normals(positions, triangles),
            albedo_factor=REST_GHOST_RGBA), static=True)
        self._stream.send_blueprint(default_blueprint(self.chamber_names, fitted_camera(positions)))
        self._rest_logged = True

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
        """Flush and close the recording (the .rrd is complete and readable afterwards)."""
        if self._stream is not None:
            try:
                # a file is written out completely; a viewer that is gone must not hold the daemon's shutdown
                self._stream.flush(timeout_sec=1e9 if self.save_path is not None else 1.0)
            except Exception as error:  # the SDK raises RuntimeError when a viewer never answered
                logger.warning("the recording could not be flushed (%s); what was not sent is lost", error)
            self._stream.disconnect()
            self._stream = None
            self.enabled = False


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
        reason = {errno.ENOSPC: "the disk is full", errno.EDQUOT: "the disk quota is exhausted",
                  errno.EACCES: "permission denied", errno.EPERM: "permission denied",
                  errno.EISDIR: "it is a directory", errno.EROFS: "the file system is read-only",
                  errno.ENOTDIR: "a part of the path is not a directory",
                  errno.EEXIST: "a part of the path is not a directory"}.get(error.errno or 0, error.strerror or "")
        remedy = "free some space or give another --rerun-save path" if error.errno in (errno.ENOSPC, errno.EDQUOT) \
            else "give another --rerun-save path"
        raise RecordingError(f"cannot write the recording {path}: {reason}; {remedy}") from None


#: Timelines read_rrd converts to seconds.
TIMELINES = ("time", "scene_time")


def read_rrd(path: str | Path) -> dict[str, dict[str, list[Any]]]:
    """Read an ``.rrd`` back: entity path -> component column -> list of logged values (in ``time`` order).

    ``time`` and ``scene_time`` keys hold those timelines in seconds (``scene_time`` None for rows logged while
    no scene ran). Used by tests and by ``make demo``.
    """
    with require_extra("record"):
        from rerun.chunk import RrdReader

    entities: dict[str, dict[str, list[Any]]] = {}
    with warnings.catch_warnings():  # "no footer": the daemon writes none (WRITE_FOOTER); stream() reads it all
        warnings.filterwarnings("ignore", message="RRD file has no footer")
        reader = RrdReader(str(path))
    for chunk in reader.stream().collect().stream():
        batch = chunk.to_record_batch()
        columns = entities.setdefault(str(chunk.entity_path), {})
        before = len(columns.get("time", []))
        for name in batch.column_names:
            if name in TIMELINES:
                values = [None if ns is None else ns / 1e9 for ns in batch.column(name).cast("int64").to_pylist()]
                column = columns.setdefault(name, [])
                column.extend([None] * (before - len(column)))
            elif name.startswith("rerun.") or name in ("log_time", "log_tick"):
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
