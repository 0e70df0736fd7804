"""After `phantom characterise` on the simulated rig: do unverified targets land within 0.5 % of the true volume?

Offline, from a finished run's folder: the correction fitted to its scans (``fit_correction``) over the daemon's
model (the record's scene, its table level as the daemon answers), and for each target volume across the reachable
range the inverse's pressures uncorrected and corrected (``CorrectedModel.pressures_for_ml`` around the model's
own inverse); the simulated phantom's TRUE gland volume at those pressures is the shipped measured-phantom truth's
(hil/plant.py, ``truth_gland_volume_ml``: the volume the simulated plant holds and the virtual camera's shape is
scaled to). No target is a scanned state: the inverse's pressures share the growth between the chambers, the
scans sit on the design's points.

    .venv/bin/python bench/characterise_targets.py out/characterise [--targets 28,30.5,33,36.5,39,42.5,45.5]
    .venv/bin/python bench/characterise_targets.py --perfect-path 19 [--noise-pct 0.05] [--bias-pct -0.3]
    .venv/bin/python bench/characterise_targets.py --perfect-grid 0,1.5,3

``--perfect-path N`` / ``--perfect-grid VALUES``: no run, but what a run of that design (``phantom characterise
--path N`` / ``--grid VALUES``) would give with a perfect scanner (the truth's volume at each state), or one that
reads ``--bias-pct`` off with ``--noise-pct`` of Gaussian noise: the best the correction can do from the design.
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
from phantom.scan.characterise import CharacterisationRecord, PointResult, fit_run, grid_design, path_design


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", nargs="?", help="the folder of a finished `phantom characterise` run")
    design = parser.add_mutually_exclusive_group()
    design.add_argument("--perfect-path", type=int, metavar="N",
                        help="instead of a run: the truth at --path N's states")
    design.add_argument("--perfect-grid", metavar="KPA,...", help="instead of a run: the truth at this grid's states")
    parser.add_argument("--noise-pct", type=float, default=0.0, help="with --perfect-*: the scanner's noise (%%)")
    parser.add_argument("--bias-pct", type=float, default=0.0, help="with --perfect-*: the scanner's bias (%%)")
    parser.add_argument("--seed", type=int, default=0, help="with --noise-pct: the noise's seed")
    parser.add_argument("--targets", default="28,30.5,33,36.5,39,42.5,45.5", help="target gland volumes (ml)")
    parser.add_argument("--tolerance-pct", type=float, default=0.5, help="the goal (%% of the true volume)")
    args = parser.parse_args()
    plant = load_plant(DEFAULT_PLANT_PATH)
    scene = "builtin:converged"
    if args.run:
        record = CharacterisationRecord.load(args.run)
        scene = record.model
    model = PhantomModel.from_scene(load_scene(scene))
    solver = InverseSolver(model)
    grid = model_grid(solver.estimator, scene)

    def inverse(volume_ml: float) -> np.ndarray:
        return np.asarray(solver.pressures_for(Target(gland_volume_m3=volume_ml * 1e-6)).pressures_pa) / 1e3

    if args.perfect_path is not None:
        points = path_design(args.perfect_path, inverse, grid.gland_ml(np.zeros(3)), grid.gland_ml(np.full(3, 3.0)))
        record = perfect_run(points, {"kind": "path", "count": args.perfect_path}, args, plant)
    elif args.perfect_grid is not None:
        points = grid_design([float(v) for v in args.perfect_grid.split(",")], 3.0)
        record = perfect_run(points, {"kind": "grid", "values_kpa": args.perfect_grid}, args, plant)
    elif not args.run:
        parser.error("give a run's folder, --perfect-path N or --perfect-grid VALUES")
    started = time.perf_counter()
    correction, note = fit_run(record.measurements(), grid)
    fit_s = time.perf_counter() - started
    if note:
        print(note)
    corrected = CorrectedModel(grid, correction)

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


def perfect_run(points: np.ndarray, design: dict[str, object], args: argparse.Namespace,
                plant: PlantParameters) -> CharacterisationRecord:
    """A run's record (in a scratch folder) whose scans are the truth's volumes at the design's states, read
    ``args.bias_pct`` off with ``args.noise_pct`` of Gaussian noise."""
    import tempfile
    from pathlib import Path

    record = CharacterisationRecord(Path(tempfile.mkdtemp(prefix="perfect-run-")), "bench", "builtin:converged",
                                    design, 3.0, points.tolist(), {}, "rig.json")
    noise = np.random.default_rng(args.seed).standard_normal(len(points)) * args.noise_pct / 100
    for index, pressures in enumerate(points):
        truth = plant.truth_gland_volume_ml(pressures * 1e3)
        assert truth is not None
        record.results.append(PointResult(index, pressures.tolist(), pressures.tolist(),
                                          truth * (1 + args.bias_pct / 100 + noise[index]), truth, f"truth/{index}",
                                          "", 0.0, truth))
    return record


if __name__ == "__main__":
    main()
