"""After `phantom characterise` on the simulated rig: do unverified targets land within 0.5 % of the true volume?

Offline, from a finished run's folder: the correction fitted to its scans (``fit_correction``) over the daemon's
model (the record's scene, its table level as the daemon answers), and for each target volume across the reachable
range the inverse's pressures uncorrected and corrected (``CorrectedModel.pressures_for_ml`` around the model's
own inverse); the simulated phantom's TRUE gland volume at those pressures is the shipped measured-phantom truth's
(hil/plant.py, ``truth_gland_volume_ml``: the volume the simulated plant holds and the virtual camera's shape is
scaled to). No target is a scanned state: the inverse's pressures share the growth between the chambers, the
scans sit on the design's points.

    .venv/bin/python bench/characterise_targets.py out/characterise [--targets 27,30,33,36,39,42]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from phantom.hil.plant import DEFAULT_PLANT_PATH, load_plant
from phantom.model import PhantomModel, load_scene
from phantom.model.corrections import CorrectedModel, model_grid
from phantom.model.inverse import InverseSolver
from phantom.model.target import Target
from phantom.scan.characterise import CharacterisationRecord, fit_run


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", help="the folder of a finished `phantom characterise` run")
    parser.add_argument("--targets", default="27,30,33,36,39,42", help="target gland volumes (ml)")
    parser.add_argument("--tolerance-pct", type=float, default=0.5, help="the goal (%% of the true volume)")
    args = parser.parse_args()
    record = CharacterisationRecord.load(args.run)
    model = PhantomModel.from_scene(load_scene(record.model))
    solver = InverseSolver(model)
    grid = model_grid(solver.estimator, record.model)
    started = time.perf_counter()
    correction, note = fit_run(record.measurements(), grid)
    fit_s = time.perf_counter() - started
    if note:
        print(note)
    corrected = CorrectedModel(grid, correction)
    plant = load_plant(DEFAULT_PLANT_PATH)

    def inverse(volume_ml: float) -> np.ndarray:
        return np.asarray(solver.pressures_for(Target(gland_volume_m3=volume_ml * 1e-6)).pressures_pa) / 1e3

    def true_ml(pressures_kpa: np.ndarray) -> float:
        value = plant.truth_gland_volume_ml(pressures_kpa * 1e3)
        assert value is not None, "the shipped plant has a truth table"
        return value

    print(f"{len(record.results)} scans of {record.folder} ({record.model}); correction {correction.kind} "
          f"(fitted in {fit_s:.1f} s), leave-one-out "
          + ", ".join(f"{kind} {error:.3f} %" for kind, error in correction.leave_one_out_pct.items()))
    scanned = np.array([result.pressures_kpa for result in record.results])
    print("| target (ml) | pressures, uncorrected (kPa) | true (ml) | error | pressures, corrected (kPa) | true (ml) "
          "| error | nearest scan (kPa away) |")
    print("|---|---|---|---|---|---|---|---|")
    errors = []
    for target in (float(t) for t in args.targets.split(",")):
        plain = inverse(target)
        fixed, _, _ = corrected.pressures_for_ml(target, inverse)
        plain_true, fixed_true = true_ml(plain), true_ml(fixed)
        errors.append((target / fixed_true - 1) * 100)
        nearest = float(np.min(np.abs(scanned - fixed).max(axis=1)))
        print(f"| {target:g} | {', '.join(f'{p:.3f}' for p in plain)} | {plain_true:.3f} | "
              f"{(plain_true / target - 1) * 100:+.2f} % | {', '.join(f'{p:.3f}' for p in fixed)} | {fixed_true:.3f} | "
              f"{(fixed_true / target - 1) * 100:+.2f} % | {nearest:.2f} |")
    worst = max(abs(e) for e in errors)
    print(f"corrected: mean abs {np.mean(np.abs(errors)):.3f} %, worst {worst:.3f} % "
          f"({'within' if worst <= args.tolerance_pct else 'NOT within'} {args.tolerance_pct:g} %)")


if __name__ == "__main__":
    main()
