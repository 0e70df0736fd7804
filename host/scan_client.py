"""The scanner's rig through a running daemon's API, for a capture that runs in a client's process (``phantom scan
capture``, ``phantom scan validate --sim``): :class:`DaemonOrbit` (a ``phantom.scan.capture.Orbit``:
``motion_config``, ``motion_move``, ``motion_status`` for where the rig is at a picture, the simulated rig's true
angles on the simulated board, and ``motion_stop`` with the drivers released) and :class:`DaemonPhantom` (a
``phantom.scan.capture.PhantomState``: the measured pressures from ``status``; a latched fault or a lost link
stops the capture). The command line joins them to the capture loop; the daemon's own ``scan`` method drives the
rig in its process instead (``phantom.host.motion.ThreadRig``).
"""

from __future__ import annotations

from dataclasses import asdict
from typing import Any

from phantom import PhantomError
from phantom.host.client import DaemonClient, DaemonError
from phantom.host.motion import rig_position_deg, scannable_pressures_kpa
from phantom.protocol.motion import SCANNER_AXES


class DaemonOrbit:
    """The scanner's axes through the daemon's API (a ``phantom.scan.capture.Orbit``)."""

    def __init__(self, client: DaemonClient):
        self.client = client

    def configure(self) -> None:
        """Send the scanner's axes (``phantom.protocol.motion.SCANNER_AXES``) to the board."""
        for axis, config in enumerate(SCANNER_AXES):
            _call(self.client, "motion_config", {"axis": axis, **asdict(config)})

    def move_to(self, orbit_deg: float, elevation_deg: float) -> tuple[float, float]:
        status = _call(self.client, "motion_move", {"orbit_deg": orbit_deg, "elevation_deg": elevation_deg})
        axes = status["axes"]
        return float(axes[0]["position_deg"]), float(axes[1]["position_deg"])

    def position_deg(self) -> tuple[float, float]:
        """The simulated rig's true angles (``motion_status``'s ``simulated``), else those the board reports."""
        return rig_position_deg(_call(self.client, "motion_status"))

    def release(self) -> None:
        _call(self.client, "motion_stop", {"release": True})

    def simulated(self) -> dict[str, Any] | None:
        """The simulated board's truth now (``motion_status``'s ``simulated``: the rig's true angles, the plant's
        pressures), None on a real board: what the virtual camera photographs."""
        truth: dict[str, Any] | None = _call(self.client, "motion_status").get("simulated")
        return truth


class DaemonPhantom:
    """The phantom's state through the daemon's API (a ``phantom.scan.capture.PhantomState``)."""

    def __init__(self, client: DaemonClient):
        self.client = client

    def pressures_kpa(self) -> list[float] | None:
        return scannable_pressures_kpa(_call(self.client, "status"))


def _call(client: DaemonClient, method: str, params: dict[str, Any] | None = None) -> Any:
    try:
        return client.call(method, params)
    except DaemonError as error:
        raise PhantomError(f"the daemon refused {method}: {error}") from None
