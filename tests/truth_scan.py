"""The daemon's verify scan of a simulated phantom's truth, without the board (test code only).

:func:`verify_scan_ml` photographs a truth (:class:`phantom.hil.truth_shape.TruthShape`) held at fixed pressures
with the virtual camera as ``phantom daemon --sim`` makes it (``truth_scene``, the verify plan's picture size and
poses), through the capture loop, and reads its volume with the verify scan's reconstruction
(``phantom.cli.scan_verify.VerifyScan``): what a verified target's round reads, less the board.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

from phantom.cli.scan_verify import VERIFY_PLAN, VerifyScan
from phantom.scan.camera import virtual_pose_at, virtual_rig
from phantom.scan.capture import CaptureFolder, Plan, capture
from phantom.scan.virtual import FixedPhantom, VirtualCamera, VirtualOrbit, truth_scene

#: The verify scan's own error allowed against a truth (a fraction of its volume): under the verified targets'
#: 0.3 %, so that a loop verified on the scan is verified in true volume.
SCANNER_TOLERANCE = 0.002


def verify_capture(truth: Any, pressures_kpa: Sequence[float], folder: Path) -> CaptureFolder:
    """The verify scan's capture of ``truth`` (anything with ``surface(pressures_kpa)``) at ``pressures_kpa`` into
    ``folder``, as ``phantom daemon --sim`` takes it: no rig kept with it (the virtual rig's own geometry)."""
    orbit = VirtualOrbit()

    def simulated() -> dict[str, Any]:
        return {"rig_deg": [orbit.orbit_deg, orbit.elevation_deg], "pressures_kpa": list(pressures_kpa)}

    elevations = tuple(VERIFY_PLAN["elevations_deg"])
    camera = VirtualCamera(virtual_rig(VERIFY_PLAN["scale"], elevations), truth_scene(simulated, truth),
                           pose_at=virtual_pose_at(VERIFY_PLAN["scale"]))
    plan = Plan(VERIFY_PLAN["views"], elevations, settle_s=0.0)
    return capture(orbit, camera, FixedPhantom(), plan, CaptureFolder.create(folder, camera.describe(), plan.to_json()))


def verify_scan(truth: Any, pressures_kpa: Sequence[float], folder: Path,
                model_surface_mm: tuple[Any, Any] | None = None) -> dict[str, Any]:
    """The verify scan's answer (``VerifyScan.volume``) for ``truth`` at ``pressures_kpa``, its capture made in
    ``folder``; with the model's surface there, the visual hull's error on it taken off."""
    verify_capture(truth, pressures_kpa, folder)
    return VerifyScan().volume(str(folder), model_surface_mm)


def verify_scan_ml(truth: Any, pressures_kpa: Sequence[float], folder: Path) -> float:
    """The verify scan's gland volume (ml) of ``truth`` at ``pressures_kpa`` as the hull reads it."""
    volume_ml: float = verify_scan(truth, pressures_kpa, folder)["volume_ml"]
    return volume_ml
