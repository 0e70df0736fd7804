"""After `phantom characterise` on the simulated rig: do unverified targets land within 0.5 % of the true volume?

Offline, from a finished run's folder: the correction fitted to its scans (``fit_correction``) over the daemon's
model (the record's scene, its table level as the daemon answers), and for each target volume across the reachable
range the inverse's pressures uncorrected and corrected (``CorrectedModel.pressures_for_ml`` around the model's
own inverse); the simulated phantom's TRUE gland volume at those pressures is the shipped measured-phantom truth's
(hil/plant.py, ``truth_gland_volume_ml``: the volume the simulated plant holds and the virtual camera's shape is
scaled to). No target is a scanned state: the inverse's pressures share the growth between the chambers, the
scans sit on the design's points.

    .venv/bin/python bench/characterise_targets.py out/characterise [--targets 29,32,35,38,41,44]
    .venv/bin/python bench/characterise_targets.py --perfect-grid 0,1.5,3 [--noise-pct 0.15]

``--perfect-grid``: no run, but what a run on that grid would give with a perfect scanner (the truth's volume at
each state, with ``--noise-pct`` of Gaussian scanner noise): the best the correction can do from such a design.
"""

from __future__ import annotations

import argparse
import math
import time

import numpy as np

from phantom import PhantomError
from phantom.hil.plant import DEFAULT_PLANT_PATH, PlantParameters, load_plant
from phantom.model import PhantomModel, load_scene
from phantom.model.corrections import CorrectedModel, model_grid
from phantom.model.inverse import InverseSolver
from phantom.model.target import Target
from phantom.scan.characterise import CharacterisationRecord, PointResult, fit_run, grid_design


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", nargs="?", help="the folder of a finished `phantom characterise` run")
    parser.add_argument("--perfect-grid", metavar="KPA,...", help="instead of a run: the truth at this grid's states")
    parser.add_argument("--noise-pct", type=float, default=0.0, help="with --perfect-grid: the scanner's noise (%%)")
    parser.add_argument("--targets", default="29,32,35,38,41,44", help="target gland volumes (ml)")
    parser.add_argument("--tolerance-pct", type=float, default=0.5, help="the goal (%% of the true volume)")
    args = parser.parse_args()
    plant = load_plant(DEFAULT_PLANT_PATH)
    record = CharacterisationRecord.load(args.run) if args.run else perfect_run(args.perfect_grid, args.noise_pct,
                                                                                 plant)
    model = PhantomModel.from_scene(load_scene(record.model))
    solver = InverseSolver(model)
    grid = model_grid(solver.estimator, record.model)
    started = time.perf_counter()
    correction, note = fit_run(record.measurements(), grid)
    fit_s = time.perf_counter() - started
    if note:
        print(note)
    corrected = CorrectedModel(grid, correction)

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
        try:
            fixed, _, _ = corrected.pressures_for_ml(target, inverse)
        except PhantomError as error:
            print(f"| {target:g} | {', '.join(f'{p:.3f}' for p in plain)} | {true_ml(plain):.3f} | "
                  f"{(true_ml(plain) / target - 1) * 100:+.2f} % | not reached: {error} | | | |")
            errors.append(math.inf)
            continue
        plain_true, fixed_true = true_ml(plain), true_ml(fixed)
        errors.append((fixed_true / target - 1) * 100)
        nearest = float(np.min(np.abs(scanned - fixed).max(axis=1)))
        print(f"| {target:g} | {', '.join(f'{p:.3f}' for p in plain)} | {plain_true:.3f} | "
              f"{(plain_true / target - 1) * 100:+.2f} % | {', '.join(f'{p:.3f}' for p in fixed)} | {fixed_true:.3f} | "
              f"{(fixed_true / target - 1) * 100:+.2f} % | {nearest:.2f} |")
    worst = max(abs(e) for e in errors)
    print(f"corrected: mean abs {np.mean(np.abs(errors)):.3f} %, worst {worst:.3f} % "
          f"({'within' if worst <= args.tolerance_pct else 'NOT within'} {args.tolerance_pct:g} %)")


def perfect_run(values: str, noise_pct: float, plant: PlantParameters) -> CharacterisationRecord:
    """A run's record (in a scratch folder) whose scans are the truth's volumes at a grid's states."""
    import tempfile
    from pathlib import Path

    points = grid_design([float(v) for v in values.split(",")], 3.0)
    record = CharacterisationRecord(Path(tempfile.mkdtemp(prefix="perfect-run-")), "bench", "builtin:converged",
                                    {"kind": "grid", "values_kpa": values}, 3.0, points.tolist(), {}, "rig.json")
    noise = np.random.default_rng(0).standard_normal(len(points)) * noise_pct / 100
    for index, pressures in enumerate(points):
        truth = plant.truth_gland_volume_ml(pressures * 1e3)
        assert truth is not None
        record.results.append(PointResult(index, pressures.tolist(), pressures.tolist(), truth * (1 + noise[index]),
                                          truth, f"truth/{index}", "", 0.0, truth))
    return record


if __name__ == "__main__":
    main()
