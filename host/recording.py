"""Rerun logging of what the daemon does: pressures, volumes, link statistics, solver time, events, the mesh.

Entity paths (time line ``time``, seconds since the daemon started):

    chamber/<name>/measured_kpa, setpoint_kpa, drive_level     per chamber, from telemetry
    volume/target_ml, volume/estimated_ml                      the gland
    volume/chambers/<name>_ml                                  estimated chamber volumes
    link/rtt_ms, link/retries, link/bad_frames, link/dropped   link statistics
    solver/qp_time_ms, solver/solve_time_ms                    the inverse
    events                                                     text log: faults, reconnects, targets
    phantom/mesh                                               the deformed outer surface (mm), rate-limited

Nothing is recorded unless asked (``--rerun-save FILE`` or ``--rerun-connect ADDR``); the mesh is logged
only then. The default blueprint puts the phantom beside its pressure plots.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np


def default_blueprint(chamber_names: list[str]):
    """The layout: the phantom on the left; pressures and volumes plots and the event log on the right."""
    import rerun.blueprint as rrb

    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Spatial3DView(origin="/phantom", name="phantom"),
            rrb.Vertical(
                rrb.TimeSeriesView(origin="/chamber", name="pressures (kPa) and drive"),
                rrb.TimeSeriesView(origin="/volume", name="volumes (ml)"),
                rrb.Horizontal(
                    rrb.TimeSeriesView(origin="/link", name="link"),
                    rrb.TextLogView(origin="/events", name="events"),
                ),
            ),
            column_shares=[2, 3],
        ),
        collapse_panels=True,
    )


class Recorder:
    """A Rerun recording stream with the daemon's logging calls; every call is a no-op when disabled.

    Parameters
    ----------
    chamber_names : list of str
        Chamber names, used in entity paths.
    save_path : path, optional
        Write an ``.rrd`` file here.
    connect_url : str, optional
        Stream to a viewer (``rerun+http://host:9876/proxy``, as ``rerun`` prints when it starts).
    """

    def __init__(self, chamber_names: list[str], save_path: str | Path | None = None, connect_url: str | None = None):
        self.chamber_names = list(chamber_names)
        self.save_path = Path(save_path) if save_path else None
        self.enabled = bool(save_path or connect_url)
        self._stream = None
        if not self.enabled:
            return
        import rerun as rr

        self._rr = rr
        self._stream = rr.RecordingStream("phantom")
        blueprint = default_blueprint(self.chamber_names)
        if self.save_path is not None:
            self.save_path.parent.mkdir(parents=True, exist_ok=True)
            self._stream.save(str(self.save_path), default_blueprint=blueprint)
        else:
            self._stream.connect_grpc(connect_url, default_blueprint=blueprint)

    @property
    def wants_mesh(self) -> bool:
        """Whether someone records or views, so that computing a shape is worth it."""
        return self.enabled

    def _at(self, time_s: float) -> None:
        self._stream.set_time("time", duration=float(time_s))

    def _scalar(self, path: str, value: float) -> None:
        if value is not None and np.isfinite(value):
            self._stream.log(path, self._rr.Scalars(float(value)))

    def log_telemetry(self, time_s: float, measured_kpa, setpoint_kpa, drive_levels) -> None:
        """Per chamber: measured and set pressure (kPa) and drive level (0..1)."""
        if not self.enabled:
            return
        self._at(time_s)
        for index, name in enumerate(self.chamber_names):
            self._scalar(f"chamber/{name}/measured_kpa", measured_kpa[index])
            self._scalar(f"chamber/{name}/setpoint_kpa", setpoint_kpa[index])
            self._scalar(f"chamber/{name}/drive_level", drive_levels[index])

    def log_volumes(self, time_s: float, target_ml: float | None, estimated_ml: float | None,
                    chamber_estimated_ml=None) -> None:
        """Target and estimated gland volume (ml) and estimated chamber volumes (ml)."""
        if not self.enabled:
            return
        self._at(time_s)
        self._scalar("volume/target_ml", target_ml)
        self._scalar("volume/estimated_ml", estimated_ml)
        if chamber_estimated_ml is not None:
            for name, volume_ml in zip(self.chamber_names, chamber_estimated_ml, strict=True):
                self._scalar(f"volume/chambers/{name}_ml", volume_ml)

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

    def log_mesh(self, time_s: float, positions_mm: np.ndarray, triangles: np.ndarray) -> None:
        """The deformed outer surface: vertex positions (mm, (n, 3)) and triangles ((k, 3) indices)."""
        if not self.enabled:
            return
        self._at(time_s)
        self._stream.log("phantom/mesh", self._rr.Mesh3D(vertex_positions=np.asarray(positions_mm, np.float32),
                                                         triangle_indices=np.asarray(triangles, np.uint32),
                                                         albedo_factor=[230, 170, 160, 255]))

    def close(self) -> None:
        """Flush and close the recording (the .rrd is complete and readable afterwards)."""
        if self._stream is not None:
            self._stream.flush()
            self._stream.disconnect()
            self._stream = None
            self.enabled = False


def surface_mesh(nodes_m: np.ndarray, outer_triangles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The outer surface as its own small mesh: (used node indices, triangles renumbered into them).

    Logging only the surface nodes keeps each mesh message small (the interior nodes are never drawn).
    """
    used = np.unique(outer_triangles)
    renumber = np.full(len(nodes_m), -1, dtype=np.int64)
    renumber[used] = np.arange(len(used))
    return used, renumber[outer_triangles]


def read_rrd(path: str | Path) -> dict[str, dict[str, list]]:
    """Read an ``.rrd`` back: entity path -> component column -> list of logged values (in time order).

    A ``time`` key holds the time line in seconds. Used by tests and by ``make demo`` to check a recording.
    """
    from rerun.chunk import RrdReader

    entities: dict[str, dict[str, list]] = {}
    for chunk in RrdReader(str(path)).stream().collect().stream():
        batch = chunk.to_record_batch()
        columns = entities.setdefault(str(chunk.entity_path), {})
        for name in batch.column_names:
            if name == "time":
                values = [ns / 1e9 for ns in batch.column(name).cast("int64").to_pylist()]
            elif name.startswith("rerun.") or name == "log_time":
                continue
            else:
                values = batch.column(name).to_pylist()
            columns.setdefault(name, []).extend(values)
    for columns in entities.values():
        if "time" in columns:
            order = np.argsort(columns["time"], kind="stable")
            for name in list(columns):
                if len(columns[name]) == len(order):
                    columns[name] = [columns[name][i] for i in order]
    return entities
