"""What the daemon needs of each of its parts, as Protocols (the recording, the board's link session, the model),
and the control state, which the control core (host/control.py) holds.

The daemon is built from real parts (:class:`phantom.host.recording.Recorder`,
:class:`phantom.host.session.LinkSession`, :class:`phantom.host.model_worker.ModelWorker`); a unit test of its
wiring may give it stand-ins with these methods. mypy checks that the real parts satisfy them where the daemon
is built.
"""

from __future__ import annotations

import enum
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

if TYPE_CHECKING:
    from phantom.host.model_worker import Estimate, ModelInfo
    from phantom.host.session import LinkState, Transport
    from phantom.model.target import InverseResult, Target

class ControlState(enum.StrEnum):
    """What drives the setpoints: nothing (``idle``), a target from the API (``holding``), a scene's timeline
    (``scene``), or nothing since a vent (``vented``); the value is what ``status`` shows."""

    IDLE = "idle"
    HOLDING = "holding"
    SCENE = "scene"
    VENTED = "vented"


#: Seconds on a monotonic clock (``time.monotonic``; a counter in tests).
Clock = Callable[[], float]


class Recording(Protocol):
    """Where the daemon logs what it does (Rerun; every call a no-op when nothing records)."""

    def set_scene_time(self, scene_time_s: float | None) -> None: ...

    def log_telemetry(self, time_s: float, measured_kpa: np.ndarray, setpoint_kpa: np.ndarray,
                      drive_levels: np.ndarray) -> None: ...

    def log_volumes(self, time_s: float, target_ml: float | None, estimated_ml: float | None,
                    chamber_ml: Sequence[float] | None = None, true_ml: float | None = None,
                    model_ml: float | None = None) -> None: ...

    def log_correction(self, time_s: float, size_ml: float | None, count: int) -> None: ...

    def log_link(self, time_s: float, rtt_ms: float | None, retries: int, bad_frames: int, dropped: int) -> None: ...

    def log_scanned_volume(self, time_s: float, volume_ml: float, round_: int, tolerance_pct: float) -> None: ...

    def log_scan_surface(self, time_s: float, positions_mm: np.ndarray, triangles: np.ndarray) -> None: ...

    def log_solver(self, time_s: float, qp_time_s: float, solve_time_s: float) -> None: ...

    def log_event(self, time_s: float, text: str, level: str = "INFO") -> None: ...

    def log_rest_surface(self, positions_mm: np.ndarray, triangles: np.ndarray) -> None: ...

    def log_mesh(self, time_s: float, positions_mm: np.ndarray, triangles: np.ndarray) -> None: ...

    def check(self) -> None: ...

    def status(self) -> dict[str, Any] | None: ...

    def close(self) -> None: ...


class BoardSession(Protocol):
    """The link to the board (:class:`phantom.host.session.LinkSession`)."""

    @property
    def transport(self) -> Transport: ...

    @property
    def online(self) -> bool: ...

    @property
    def state(self) -> LinkState: ...

    async def run(self) -> None: ...

    def stop(self) -> None: ...

    async def command(self, name: str, fields: dict[str, Any] | None = None) -> str: ...

    async def end_session(self) -> bool: ...

    def status(self) -> dict[str, Any]: ...


class Model(Protocol):
    """The scene's model, inverse and estimator (:class:`phantom.host.model_worker.ModelWorker`)."""

    @property
    def info(self) -> ModelInfo: ...

    #: workers started again after one died
    restarts: int

    async def use_level(self, level: str) -> ModelInfo: ...

    async def pressures_for(self, target: Target) -> InverseResult: ...

    async def pressures_on_ramp(self, start: Target, end: Target, target: Target) -> InverseResult: ...

    async def estimate(self, pressures_pa: np.ndarray, with_surface: bool = False,
                       with_rest_surface: bool = False) -> Estimate: ...

    async def surface_json(self, pressures_pa: np.ndarray | None) -> str: ...

    async def shape_answer(self, shape: str | dict[str, Any], labels: list[int] | None,
                           refine_solves: int) -> dict[str, Any]: ...

    async def record_measurement(self, pressures_kpa: list[float], volume_ml: float, method: str = "scan",
                                 scan_file: str | None = None) -> dict[str, Any]: ...

    async def gland_band(self, pressures_pa: np.ndarray) -> tuple[float, float] | None: ...

    def correction_status(self) -> dict[str, Any]: ...

    def close(self) -> None: ...
