"""When the daemon estimates the phantom's volumes (and its shape) from the measured pressures.

Telemetry arrives at 50 Hz; the forward model runs in the model worker at most once per control period, on
the mean of the last :data:`ESTIMATE_WINDOW_S` of measured pressures (sensor noise and ADC quantisation average
out while a settled chamber does not move), and only when that mean moved by :data:`ESTIMATE_CHANGE_PA` or the
last estimate is older than :data:`ESTIMATE_MAX_AGE_S`. A shape is asked for only when someone wants it (the
scene's ``[outputs] shape`` and a recording), at ``mesh_hz``.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np

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
