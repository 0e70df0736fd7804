"""The daemon's API methods (host/README.md, "The local API"): each checks its params, acts on the daemon and
answers JSON-ready data, or raises ``ApiError`` with one of the API's error codes."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

from phantom.host.api import ApiError, Handler
from phantom.host.parts import ControlState
from phantom.host.scenes import effective_model, model_differences, parse_target
from phantom.host.session import fault_names
from phantom.model.errors import SceneError
from phantom.model.scene import load_scene

if TYPE_CHECKING:
    from phantom.host.daemon import Daemon

PA_PER_KPA = 1e3


class ApiHandlers:
    """The methods of the local API, bound to one daemon."""

    def __init__(self, daemon: Daemon):
        self.daemon = daemon

    def table(self) -> dict[str, Handler]:
        """Method name -> handler, for :class:`phantom.host.api.ApiServer`."""
        return {"status": self.status, "set_target": self.set_target, "vent": self.vent,
                "clear_fault": self.clear_fault, "run_scene": self.run_scene, "zero": self.zero,
                "surface": self.surface}

    async def status(self, params: dict[str, Any]) -> dict[str, Any]:
        return self.daemon.status()

    async def set_target(self, params: dict[str, Any]) -> dict[str, Any]:
        daemon = self.daemon
        try:
            target = parse_target(params, daemon.chamber_names, "set_target")
        except SceneError as error:
            raise ApiError("invalid_params", str(error)) from error
        if not daemon.session.online:
            raise ApiError("link_down", f"no board: the link is {daemon.session.state.value}; the target was not set")
        daemon.scenes.stop("a set_target request")
        result = await daemon.apply_target(target, "api")
        daemon.control_state = ControlState.HOLDING
        return result

    async def vent(self, params: dict[str, Any]) -> dict[str, Any]:
        daemon = self.daemon
        daemon.scenes.stop("vented")
        await daemon.board_command("VENT")
        daemon.control_state = ControlState.VENTED
        daemon.setpoints_pa = np.zeros(len(daemon.chamber_names))
        daemon.target, daemon.inverse_result, daemon.target_source = None, None, None
        daemon.event("vent", "vented on request: every setpoint is 0")
        return {"vented": True}

    async def clear_fault(self, params: dict[str, Any]) -> dict[str, Any]:
        daemon = self.daemon
        before = fault_names(daemon.fault_flags)
        await daemon.board_command("CLEAR_FAULT")
        daemon.event("fault", f"faults cleared on request (were: {', '.join(before) or 'none'})")
        restored = False
        if daemon.setpoints_pa is not None and daemon.control_state is not ControlState.VENTED and np.any(
                daemon.setpoints_pa > 0):
            await daemon.send_setpoints(daemon.setpoints_pa)
            restored = True
        return {"cleared": before, "setpoints_restored": restored}

    async def zero(self, params: dict[str, Any]) -> dict[str, Any]:
        """ZERO_SENSORS on request: the board measures each sensor's zero (it must be vented and settled)."""
        acknowledged = await self.daemon.zero_sensors()
        self.daemon.event("zero", "sensors zeroed on request")
        return {"zeroed": True, "acknowledged": acknowledged}

    async def surface(self, params: dict[str, Any]) -> dict[str, Any]:
        """The deformed outer surface (positions mm, triangles): at ``pressures_kpa`` if given, else at the
        latest measured pressures (at rest when there are none)."""
        daemon = self.daemon
        pressures = params.get("pressures_kpa")
        if pressures is not None:
            try:
                target = parse_target({"pressures_kpa": pressures}, daemon.chamber_names, "surface")
            except SceneError as error:
                raise ApiError("invalid_params", str(error)) from error
            pressures_pa: np.ndarray | None = np.asarray(target.values, dtype=float)
        elif daemon.schedule.window:
            pressures_pa = np.mean([frame for _, frame in daemon.schedule.window], axis=0)
        else:
            pressures_pa = None
        positions_mm, triangles = await daemon.model.surface(pressures_pa)
        return {"pressures_kpa": None if pressures_pa is None else (pressures_pa / PA_PER_KPA).tolist(),
                "positions_mm": np.round(positions_mm, 4).tolist(), "triangles": np.asarray(triangles).tolist()}

    async def run_scene(self, params: dict[str, Any]) -> dict[str, Any]:
        daemon = self.daemon
        path = params.get("path")
        time_scale: Any = params.get("time_scale", 1.0)
        if not isinstance(path, str) or not path:
            raise ApiError("invalid_params", "run_scene needs params.path: the scene TOML file (absolute path)")
        if isinstance(time_scale, bool) or not isinstance(time_scale, (int, float)):
            raise ApiError("invalid_params", f"time_scale must be a number, got {time_scale!r}")
        try:
            scene = load_scene(path)
            # the timeline runs on the loaded model: a scene for another phantom, material or model setting needs
            # its own model, so the daemon must be restarted with it
            differing = model_differences(daemon.model.info.effective_model, effective_model(scene))
            if differing:
                raise SceneError(f"{path} describes another phantom than the running one (its "
                                 f"[{'], ['.join(differing)}] differ from {daemon.model.info.scene_path}): restart "
                                 f"the daemon with --scene {path}")
            return daemon.start_scene(scene.raw, str(path), float(time_scale), bool(scene.outputs.shape))
        except SceneError as error:
            raise ApiError("invalid_params", str(error)) from error
