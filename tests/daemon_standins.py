"""Stand-ins for the daemon's parts, for the unit tests of its wiring (test code only; end to end the parts are real).

:class:`DaemonStandIns` builds a :class:`phantom.host.daemon.Daemon` on a model (:class:`StandInModel`: its
:class:`ModelInfo` from :func:`model_info`, a fixed estimate, no correction), a recording and a board session that
note every call in :attr:`DaemonStandIns.calls` (the board answering ``OK``), an API server that is never started,
and a :class:`FakeClock`. A test's subclass changes only what is its own: :attr:`DaemonStandIns.model_type` (what
the model answers) and :meth:`DaemonStandIns.answer` (what the board answers a command).
:class:`ModelInProcess` is the model worker's own functions called in this process (its real answers, no process).
"""

from __future__ import annotations

from types import SimpleNamespace
from typing import Any

import numpy as np

from phantom.host.api import ApiServer
from phantom.host.config import DaemonConfig
from phantom.host.daemon import Daemon
from phantom.host.model_worker import Estimate, ModelInfo
from phantom.host.parts import Clock

CHAMBERS = ["chamber0", "chamber1", "chamber2"]


class FakeClock:
    """A monotonic clock that stands still at 100 s until a test moves :attr:`now_s`."""

    def __init__(self) -> None:
        self.now_s = 100.0

    def __call__(self) -> float:
        return self.now_s


def model_info(rest_volume_ml: float, fidelity: str, scene_path: str, wants_shape: bool = False,
               effective_model: dict[str, Any] | None = None) -> ModelInfo:
    """The stand-in model's info: the three chambers of :data:`CHAMBERS` (base and two lobes), 3 kPa at most."""
    return ModelInfo(CHAMBERS, ["base", "left lobe", "right lobe"], rest_volume_ml, {"total_s": 1.0}, fidelity, {},
                     scene_path, 3000.0, wants_shape, effective_model or {})


class StandInModel:
    """The model worker as a stand-in: its info, an estimate of fixed volumes (a two-triangle surface when a shape
    is asked, its ``counts`` the shapes asked so far), a three-point surface, no correction."""

    restarts = 0

    def __init__(self, parts: DaemonStandIns, info: ModelInfo):
        self.parts, self.info = parts, info

    async def estimate(self, pressures_pa: np.ndarray, with_surface: bool = False,
                       with_rest_surface: bool = False) -> Estimate:
        self.parts.calls.append(("estimate", with_surface))
        surface = (np.zeros((4, 3)), np.array([[0, 1, 2], [0, 2, 3]])) if with_surface else None
        rest = surface if with_surface and with_rest_surface else None
        shapes = sum(1 for call in self.parts.calls if call == ("estimate", True))
        return Estimate([2.0, 1.1, 1.1], 30.0, surface, {"shapes": shapes}, rest)

    async def surface_json(self, pressures_pa: np.ndarray | None) -> str:
        return '{"positions_mm": [[0, 0, 0], [1, 0, 0], [0, 1, 0]], "triangles": [[0, 1, 2]]}'

    def correction_status(self) -> dict[str, Any]:
        return {"in_force": False, "correction": None}

    def close(self) -> None:
        pass


class StandInRecording:
    """A recording whose every method notes ``(its name, its first argument)`` in the stand-ins' calls."""

    def __init__(self, parts: DaemonStandIns):
        self.parts = parts

    def __getattr__(self, name: str) -> Any:
        return lambda *args, **kwargs: self.parts.calls.append((name, *args[:1]))


class StandInSession:
    """A board session online that notes each command as ``("command", name)`` and answers what
    :meth:`DaemonStandIns.answer` says."""

    online = True
    transport = SimpleNamespace(description="stand-in", close=lambda: None)

    def __init__(self, parts: DaemonStandIns):
        self.parts = parts

    async def command(self, name: str, fields: dict[str, Any] | None = None) -> str:
        self.parts.calls.append(("command", name))
        return self.parts.answer(name)

    def status(self) -> dict[str, Any]:
        return {"state": "online", "stats": {"rtt_ms": None, "retries": 0, "bad_frames": 0, "tx_dropped": 0,
                                             "commands_failed": 0}}


class DaemonStandIns:
    """Stand-ins for the daemon's parts (a unit test of the wiring alone), made with the model's ``info``."""

    #: what the model is (a subclass of :class:`StandInModel` answers what a test needs)
    model_type: type[StandInModel] = StandInModel

    def __init__(self, info: ModelInfo):
        #: what the parts were asked, in order: ``("estimate", with_surface)``, ``("command", name)``,
        #: ``(recording method, its first argument)``
        self.calls: list[tuple[Any, ...]] = []
        self.model: Any = self.model_type(self, info)
        self.recorder: Any = StandInRecording(self)
        self.session: Any = StandInSession(self)
        self.api = ApiServer("/nonexistent/never-started.sock", {})

    @property
    def commands(self) -> list[str]:
        """The commands sent to the board, in order."""
        return [call[1] for call in self.calls if call[0] == "command"]

    def answer(self, name: str) -> str:
        """The board's answer to the command ``name`` (a subclass may raise CommandRejected)."""
        return "OK"

    def daemon(self, clock: Clock | None = None, **config: Any) -> Daemon:
        """A daemon of these parts on ``clock`` (a :class:`FakeClock` by default) told to simulate its board (none
        is started) with the other :class:`DaemonConfig` settings given."""
        return Daemon(DaemonConfig(sim=True, **config), self.api, self.model, self.recorder, self.session, None,
                      clock=FakeClock() if clock is None else clock)


class ModelInProcess:
    """The model worker's own functions, called in this process (the worker's answers without its process)."""

    restarts = 0

    def __init__(self, scene: str):
        from phantom.host import model_worker

        self.worker = model_worker
        self.info = model_worker._worker_start(scene)

    async def pressures_for(self, target: Any) -> Any:
        return self.worker._worker_pressures_for(target)

    async def pressures_on_ramp(self, start: Any, end: Any, target: Any) -> Any:
        return self.worker._worker_pressures_on_ramp(start, end, target)

    async def estimate(self, pressures_pa: np.ndarray, with_surface: bool = False,
                       with_rest_surface: bool = False) -> Estimate:
        return self.worker._worker_estimate(pressures_pa, with_surface, with_rest_surface)

    def correction_status(self) -> dict[str, Any]:
        return {"in_force": False, "correction": None}

    def close(self) -> None:
        pass
