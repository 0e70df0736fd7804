"""The daemon's status: everything ``phantom status --json`` shows (host/README.md, "The local API"), read from
the daemon, its control core and its parts.

What it reads of the daemon is :class:`StatusSource` (a Protocol the daemon satisfies, checked by mypy where
:meth:`phantom.host.daemon.Daemon.status` calls :func:`daemon_status`): the daemon imports this module, and this
module does not import the daemon.
"""

from __future__ import annotations

import os
from collections import deque
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

from phantom.host.parts import BoardSession, ControlState, Model, Recording
from phantom.host.session import fault_names
from phantom.host.verify import progress_text

if TYPE_CHECKING:
    from phantom.host.api import ApiServer
    from phantom.host.board_watch import BoardSettings
    from phantom.host.control import ControlCore
    from phantom.host.estimation import EstimateSchedule, VolumeEstimates
    from phantom.host.motion import Orbit
    from phantom.host.scene_runner import SceneRunner
    from phantom.host.session import Telemetry
    from phantom.host.sim_board import SimulatedBoardKeeper
    from phantom.host.stalls import LoopStalls
    from phantom.host.startup import BackgroundTable, StartupProgress
    from phantom.host.web import WebServer
    from phantom.host.zeroing import SensorZero

PA_PER_KPA = 1e3


class StatusSource(Protocol):
    """What the status reads of the daemon (:class:`phantom.host.daemon.Daemon`): its parts and its state."""

    telemetry: Telemetry | None
    session: BoardSession
    model: Model
    core: ControlCore
    schedule: EstimateSchedule
    estimates: VolumeEstimates
    chamber_names: list[str]
    chamber_labels: list[str]
    fault_flags: int
    board_settings: BoardSettings
    board_settings_source: str
    zero: SensorZero
    scenes: SceneRunner
    table: BackgroundTable
    ready: bool
    startup: StartupProgress
    api: ApiServer
    loop_stalls: LoopStalls
    recorder: Recording
    events: deque[dict[str, Any]]
    motion: Orbit
    web: WebServer | None
    sim_board: SimulatedBoardKeeper | None

    def now_s(self) -> float: ...

    def target_volume_ml(self) -> float | None: ...


def daemon_status(daemon: StatusSource) -> dict[str, Any]:
    """Everything ``phantom status --json`` shows."""
    telemetry = daemon.telemetry if daemon.session.online else None  # a stale frame is not shown
    link, info, core = daemon.session.status(), daemon.model.info, daemon.core
    window = daemon.schedule.window if telemetry is not None else None
    progress, motion = core.verify_progress, daemon.motion.status()
    status = {
        "link": link["state"], "link_detail": link, "control": core.state.value,
        "chambers": daemon.chamber_names, "chamber_labels": daemon.chamber_labels,
        "pressures_kpa": _kpa(telemetry.pressures_pa) if telemetry is not None else None,
        "setpoints_kpa": _kpa(core.setpoints_pa) if core.setpoints_pa is not None else None,
        "board_setpoints_kpa": _kpa(telemetry.setpoints_pa) if telemetry is not None else None,
        # the measured pressures averaged over the estimate's window (sensor noise averages out)
        "pressures_mean_kpa": (np.mean([frame for _, frame in window], axis=0) / PA_PER_KPA).tolist()
        if window else None,
        "drive_levels": telemetry.drive_levels.tolist() if telemetry is not None else None,
        "chamber_states": telemetry.states if telemetry is not None else None,
        "estimated_volume_ml": daemon.estimates.gland_ml if telemetry else None,
        "estimated_chamber_volumes_ml": daemon.estimates.chamber_ml if telemetry else None,
        "rest_volume_ml": info.rest_volume_ml, "target_volume_ml": daemon.target_volume_ml(),
        "target": core.target.to_json() if core.target is not None else None, "target_source": core.source,
        "target_applied": core.target_applied,
        # the verified target's rounds while they run, in words too (with its scan's pictures, motion.scan)
        "verify": None if progress is None else {**progress, "text": progress_text(progress, motion["scan"])},
        "target_pending": core.pending if core.target is not None and not core.target_applied else None,
        # what became of the target after the board lost its setpoints once it was reached (the reach rule's word,
        # not the panel's): {"state": not_held | settling (its setpoints acknowledged again) | held_again, "after":
        # fault | board restart | link loss}; None while nothing interrupted it
        "target_after_interruption": core.target_after_interruption,
        "reached_rule": {"settled_kpa": core.rule.settled_kpa, "settled_for_s": core.rule.settled_for_s,
                         "tolerance_pct": core.tolerance_pct or core.rule.tolerance_pct},
        "solution": core.answer.to_json() if core.answer is not None else None,
        "faults": fault_names(daemon.fault_flags),
        "vented_why": core.vented_why if core.state is ControlState.VENTED else None,
        "board_settings": {**daemon.board_settings.to_json(), "source": daemon.board_settings_source,
                           "board_config_source": (link.get("board_info") or {}).get("config_source")},
        "zero": {**daemon.zero.state, "sources": (link.get("board_info") or {}).get("zero_source")},
        "scene": daemon.scenes.to_json(), "startup_s": info.timings_s, "fidelity": info.fidelity,
        "fidelity_pending": info.pending_fidelity, "model_build": daemon.table.to_json(), "ready": daemon.ready,
        "starting": None if daemon.ready else {**daemon.startup.to_json(), "text": daemon.startup.text()},
        "pid": os.getpid(), "model_counts": daemon.estimates.model_counts,
        "model_worker_restarts": daemon.model.restarts,
        # the correction by the phantom's measured volumes in force, or why there is none
        "correction": daemon.model.correction_status(),
        "meshes_logged": daemon.estimates.meshes_logged,
        "api": daemon.api.stats(), "event_loop": daemon.loop_stalls.to_json(),
        "recording": daemon.recorder.status(), "uptime_s": daemon.now_s(), "events": list(daemon.events)[-10:],
        "motion": motion,
        "web": daemon.web.status() if daemon.web is not None else None,
    }
    if daemon.sim_board is not None:
        status["simulated_board"] = daemon.sim_board.status()
        if daemon.sim_board.plant_volume_ml is not None:
            status["plant_volume_ml"] = daemon.sim_board.plant_volume_ml
    return status


def _kpa(pressures_pa: np.ndarray) -> list[float]:
    return list((np.asarray(pressures_pa, dtype=float) / PA_PER_KPA).tolist())
