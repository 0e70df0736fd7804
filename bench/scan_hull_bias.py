"""The verify scan's error against a simulated phantom's truth, with and without the visual hull's error on the
model's shape taken off (``phantom.scan.hull_bias``), at make demo's states.

For each phantom (the shipped simulated one; ``--sim-truth``'s lobes 1.1, E x 0.9, whose shape the model does not
share) and look (``ideal``: a matt gland floating before an even backdrop; ``real``: hung by its tubes, gloss, an
uneven cloth), at the controller's pressures for make demo's five volumes and one lopsided state: the truth
photographed by the virtual camera through the capture loop with the verify plan, reconstructed as the daemon's
verify scan does; then the hull's error read on the model's own surface at those pressures (the scene's shipped
shapes: what the daemon's model worker gives), in the model's frame (the virtual rig) and placed by alignment (a
calibrated rig's path), taken off. Prints a table: the true volume, the scan's error, the corrected errors, the
seconds the correction took.

    nice -n 5 .venv/bin/python bench/scan_hull_bias.py [--looks ideal,real] [--phantoms shipped,lobes]
        [--views N] [--elevations A+B]

(``--views``/``--elevations``: another plan than the verify plan's, to size it with the hull's error taken off.)
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

#: The controller's pressures (kPa) for make demo's volumes (its daemon log, 2026-11-29 09:22) and a lopsided state.
STATES_KPA = {"26.5 ml": (0.098, 0.097, 0.097), "30 ml": (0.821, 1.108, 1.108), "35 ml": (0.838, 2.05, 2.05),
              "40 ml": (0.798, 2.588, 2.588), "45 ml": (2.157, 2.945, 2.945), "lopsided": (1.2, 2.2, 0.6)}


def truth_of(phantom: str) -> Any:
    from phantom.hil.plant import truth_plant_path, truth_shapes_path
    from phantom.hil.simulated_truth import SimulatedTruth

    if phantom == "shipped":
        return SimulatedTruth().shape()
    plant = truth_plant_path("hil/truths/lobes_1_1.toml", 0.9)
    return SimulatedTruth("hil/truths/lobes_1_1.toml", 0.9, plant, truth_shapes_path(plant)).shape()


def main() -> None:
    from phantom.cli.scan_verify import VERIFY_PLAN
    from phantom.hil.plant import CALIBRATED_SCENE_PATH
    from phantom.hil.truth_shape import TruthShape
    from phantom.scan.camera import virtual_rig
    from phantom.scan.capture import Plan
    from phantom.scan.hull_bias import hull_bias
    from phantom.scan.reconstruct import reconstruct
    from phantom.scan.render import LOOKS
    from phantom.scan.virtual import render_capture

    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--looks", default="ideal,real")
    parser.add_argument("--phantoms", default="shipped,lobes")
    parser.add_argument("--views", type=int, default=VERIFY_PLAN["views"], help="orbit stops per elevation")
    parser.add_argument("--elevations", default="+".join(f"{e:g}" for e in VERIFY_PLAN["elevations_deg"]),
                        help="the elevations (deg), joined by +")
    args = parser.parse_args()
    model = TruthShape(CALIBRATED_SCENE_PATH, 1.0, plant_path=None)   # the controller's model's own shapes
    views, elevations, scale = args.views, tuple(map(float, args.elevations.split("+"))), VERIFY_PLAN["scale"]
    rig = virtual_rig(scale, elevations)
    print(f"the plan: {views} stops at {elevations} deg, scale {scale}\n")
    print("| phantom | look | state | true ml | scan error % | hull on the model % | corrected % | placed by "
          "alignment: corrected % | s (in frame / aligned) |")
    print("|---|---|---|---|---|---|---|---|---|")
    worst: dict[str, float] = {}
    for phantom in args.phantoms.split(","):
        truth = truth_of(phantom)
        for look in args.looks.split(","):
            for state, pressures in STATES_KPA.items():
                with tempfile.TemporaryDirectory() as folder:
                    # the virtual rig's pictures of the truth's surface at the pressures (its poses are the
                    # daemon's simulated rig's); the correction is told which frame to take
                    captured = render_capture(truth.surface(pressures), rig, Plan(views, elevations),
                                              Path(folder) / "scan", look=LOOKS[look])
                    scanned = reconstruct(captured, rig)
                    surface = model.surface(pressures)
                    in_frame = hull_bias(captured, rig, scanned, surface, in_model_frame=True)
                    aligned = hull_bias(captured, rig, scanned, surface, in_model_frame=False)
                true_ml = truth.plant.truth_gland_volume_ml(1e3 * np.asarray(pressures))
                errors = [100 * (value / true_ml - 1) for value in
                          (scanned.volume_ml, in_frame.corrected_ml(scanned.volume_ml),
                           aligned.corrected_ml(scanned.volume_ml))]
                for key, value in zip(("scan", "corrected", "aligned"), errors, strict=True):
                    worst[f"{phantom} {look} {key}"] = max(worst.get(f"{phantom} {look} {key}", 0.0), abs(value))
                print(f"| {phantom} | {look} | {state} | {true_ml:.3f} | {errors[0]:+.3f} | "
                      f"{in_frame.error_pct:+.3f} | {errors[1]:+.3f} | {errors[2]:+.3f} | {in_frame.seconds:.1f} / "
                      f"{aligned.seconds:.1f} |", flush=True)
    print("\nlargest |error| %: " + "; ".join(f"{key} {value:.3f}" for key, value in worst.items()))


if __name__ == "__main__":
    main()
