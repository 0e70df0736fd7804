"""The simulated phantom a virtual camera photographs on the simulated board (:class:`SimulatedTruth`): which
scene, modulus and plant, and the truth shape built from them (``phantom.hil.truth_shape.TruthShape``) in the
process that renders (the daemon's scan worker, ``phantom scan capture --sim``).

``phantom daemon`` passes :meth:`SimulatedTruth.shape` to the daemon's scanner
(``phantom.scan.daemon_scan.DaemonScanner``), which calls it on its first virtual picture: the scanner imports
nothing of the HIL.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from phantom.hil.truth_shape import TruthShape


@dataclass(frozen=True)
class SimulatedTruth:
    """The simulated phantom a virtual camera photographs: the scene, its modulus factor, the plant whose
    gland volume its shape is scaled to and the truth's own shapes built with it (the defaults: the shipped
    truth, hil/truth_shape.py, with the scene's shipped shapes). Picklable."""

    scene: str | Path | None = None
    modulus_factor: float | None = None
    plant_path: Path | None = None
    shapes_path: Path | None = None

    def shape(self) -> TruthShape:
        """The truth shape (its surface at any pressures), built now."""
        from phantom.hil.plant import CALIBRATED_SCENE_PATH, DEFAULT_PLANT_PATH, TRUTH_MODULUS_FACTOR
        from phantom.hil.truth_shape import TruthShape

        return TruthShape(self.scene or CALIBRATED_SCENE_PATH, self.modulus_factor or TRUTH_MODULUS_FACTOR,
                          plant_path=self.plant_path or DEFAULT_PLANT_PATH, shapes_path=self.shapes_path)
