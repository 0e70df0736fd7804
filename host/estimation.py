"""When the daemon estimates the phantom's volumes (and its shape) from the measured pressures.

Telemetry arrives at 50 Hz; the forward model runs in the model worker at most once per control period, on
the mean of the last :data:`ESTIMATE_WINDOW_S` of measured pressures (sensor noise and ADC quantisation average
out while a settled chamber does not move), and only when that mean moved by :data:`ESTIMATE_CHANGE_PA` or the
last estimate is older than :data:`ESTIMATE_MAX_AGE_S`. A shape is asked for only when someone wants it (the
scene's ``[outputs] shape`` and a recording), at ``mesh_hz``.
"""

from __future__ import annotations

import asyncio
from collections import deque
from collections.abc import Callable, Coroutine
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from phantom.host.model_worker import Estimate
    from phantom.host.parts import Model, Recording

#: Estimates average the measured pressures over this window (s of board time).
ESTIMATE_WINDOW_S = 0.5
#: A new estimate is made when the mean pressures moved by this much (Pa, a tenth of an ADC count; about
#: 0.05 % of the volume change) ...
ESTIMATE_CHANGE_PA = 5.0
#: ... or when the last one is this old (s): a held target costs almost nothing.
ESTIMATE_MAX_AGE_S = 1.0


@dataclass(frozen=True)
class EstimateRequest:
    """One estimate to make: at these mean pressures (Pa), with the shape or not, stamped ``time_s``."""

    pressures_pa: np.ndarray
    with_shape: bool
    time_s: float


class EstimateSchedule:
    """The pressure window and the rule for when an estimate (and a shape) is due.

    Parameters
    ----------
    mesh_hz : float
        Highest rate of shapes (Hz); 0 for none.
    """

    def __init__(self, mesh_hz: float = 1.0):
        self.mesh_hz = float(mesh_hz)
        self.window: deque[tuple[float, np.ndarray]] = deque()
        self.in_flight = False
        self._estimated_pa: np.ndarray | None = None
        self._estimated_s = -np.inf
        self._shape_due_s = 0.0

    def add(self, board_time_s: float, pressures_pa: np.ndarray) -> None:
        """One telemetry frame; frames older than the window (or from before a board restart) leave it."""
        self.window.append((board_time_s, pressures_pa))
        while self.window and (board_time_s - self.window[0][0] > ESTIMATE_WINDOW_S
                               or board_time_s < self.window[0][0]):
            self.window.popleft()

    def clear(self) -> None:
        """Forget the window (a new connection: the board's clock starts again)."""
        self.window.clear()

    def due(self, now_s: float, wants_shape: bool) -> EstimateRequest | None:
        """The estimate to make now, or None (one at a time; nothing new to learn; no telemetry)."""
        if self.in_flight or not self.window:
            return None
        mean_pa = np.mean([pressures for _, pressures in self.window], axis=0)
        with_shape = wants_shape and self.mesh_hz > 0 and now_s >= self._shape_due_s
        unchanged = self._estimated_pa is not None and float(np.max(np.abs(mean_pa - self._estimated_pa))) < (
            ESTIMATE_CHANGE_PA)
        if unchanged and not with_shape and now_s - self._estimated_s < ESTIMATE_MAX_AGE_S:
            return None
        self._estimated_pa, self._estimated_s = mean_pa, now_s
        if with_shape:
            self._shape_due_s = now_s + 1.0 / self.mesh_hz
        self.in_flight = True
        return EstimateRequest(mean_pa, with_shape, now_s)

    def finished(self) -> None:
        """The estimate in flight has ended (answered or failed): the next may start."""
        self.in_flight = False


class VolumeEstimates:
    """The daemon's estimates: the model is asked when :class:`EstimateSchedule` says one is due; the latest is
    kept for the status, logged to the recording (with the shape when one was asked), and handed to
    ``on_estimate(asked_s, estimate)`` (the control core's reached, the scene runner's record).

    ``logged_volumes()`` gives the target's and the simulated plant's volumes (ml or None) logged beside it.
    """

    def __init__(self, schedule: EstimateSchedule, model: Model, recorder: Recording,
                 event: Callable[[str, str, str], None], on_estimate: Callable[[float, Estimate], None],
                 logged_volumes: Callable[[], tuple[float | None, float | None]]):
        self.schedule, self.model, self.recorder, self.event = schedule, model, recorder, event
        self.on_estimate, self.logged_volumes = on_estimate, logged_volumes
        self.gland_ml: float | None = None
        self.chamber_ml: list[float] | None = None
        self.model_counts: dict[str, int] = {"full_solves": 0, "tangent_solves": 0, "shapes": 0}
        self.meshes_logged = 0
        self._rest_surface_logged = False
        self._restarts_seen = 0
        self._correction_logged: tuple[float | None, int] = (None, 0)

    def tick(self, now_s: float, asked_s: float, wants_shape: bool,
             spawn: Callable[[Coroutine[Any, Any, Estimate]], asyncio.Task[Estimate]]) -> None:
        """Ask for an estimate when one is due (``now_s`` on the recording's time line, ``asked_s`` on the
        daemon's clock)."""
        request = self.schedule.due(now_s, wants_shape)
        if request is None:
            return
        task = spawn(self.model.estimate(request.pressures_pa, request.with_shape, not self._rest_surface_logged))
        task.add_done_callback(lambda done: self._done(done, request, asked_s))

    def _done(self, done: asyncio.Task[Estimate], request: EstimateRequest, asked_s: float) -> None:
        self.schedule.finished()
        if done.cancelled():
            return
        try:
            estimate = done.result()
        except Exception as error:  # shown, not fatal: the next tick tries again
            # the last estimate is of pressures no longer measured: status shows none rather than a stale one
            self.chamber_ml = self.gland_ml = None
            self.event("estimate", f"volume estimate failed ({type(error).__name__}: {error}): no estimate until "
                       "the next one succeeds", "WARN")
            return
        if self.model.restarts != self._restarts_seen:
            self._restarts_seen = self.model.restarts
            self.event("model", f"the model worker died and was replaced ({self.model.restarts} since the daemon "
                       "started): its model was rebuilt from the cache", "WARN")
        self.model_counts = estimate.counts
        self.chamber_ml, self.gland_ml = estimate.chamber_volumes_ml, estimate.gland_volume_ml
        self.on_estimate(asked_s, estimate)
        target_ml, true_ml = self.logged_volumes()
        self.recorder.log_volumes(request.time_s, target_ml, estimate.gland_volume_ml, estimate.chamber_volumes_ml,
                                  true_ml=true_ml, model_ml=estimate.model_gland_volume_ml)
        correction = (estimate.correction_size_ml, estimate.correction_count)
        if correction != self._correction_logged:  # the correction in force changed (logged once per change)
            self._correction_logged = correction
            self.recorder.log_correction(request.time_s, *correction)
        if estimate.surface_mm is not None:
            if estimate.rest_surface_mm is not None and not self._rest_surface_logged:
                self._rest_surface_logged = True
                self.recorder.log_rest_surface(*estimate.rest_surface_mm)
            self.recorder.log_mesh(request.time_s, *estimate.surface_mm)
            self.meshes_logged += 1
