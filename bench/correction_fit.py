"""The daemon's correction by measured volumes: how long a fit takes, and how far it misses held-out volumes.

On the daemon's default model (builtin:converged, its shipped response table) and the shipped simulated phantom
(hil/plant.toml's truth: the paper's phantom as measured), the "scans" are the truth's gland volumes at the
pressures (stand-ins for scans, which measure to 0.03-0.14 %). For Table I's eight pressure states, the 27-point
grid 0, 1.5, 3 kPa and the 19 states of `phantom characterise --path 19` (along the model's inverse): the fit's
time (all four candidates' leave-one-out and the chosen one), the kind chosen, its leave-one-out, and the mean and
largest error against the truth at 200 random pressure states in the box, beside the model's own (uncorrected)
error at the same states.

    nice -n 10 .venv/bin/python bench/correction_fit.py
"""

from __future__ import annotations

import itertools
import time

import numpy as np

TABLE_ONE_KPA = [(0, 0, 0), (1, 1, 1), (2, 2, 2), (2, 0, 0), (0, 2, 0), (0, 0, 2), (1, 2, 3), (3, 1, 2)]
GRID_KPA = list(itertools.product((0.0, 1.5, 3.0), repeat=3))
HELD_OUT = 200


def main() -> None:
    from phantom.hil.plant import load_plant
    from phantom.host.scenes import load_timeline_scene
    from phantom.model import PhantomModel
    from phantom.model.corrections import CorrectedModel, fit_correction, model_grid
    from phantom.model.inverse import InverseSolver
    from phantom.model.measurements import Measurement
    from phantom.model.target import Target
    from phantom.scan.characterise import path_design

    plant = load_plant()

    def true_ml(pressures_kpa: np.ndarray) -> float:
        volume = plant.truth_gland_volume_ml(np.asarray(pressures_kpa, dtype=float) * 1e3)
        assert volume is not None
        return volume

    solver = InverseSolver(PhantomModel.from_scene(load_timeline_scene("builtin:converged")))
    grid = model_grid(solver.estimator)

    def inverse_kpa(volume_ml: float) -> np.ndarray:
        return np.asarray(solver.pressures_for(Target(gland_volume_m3=volume_ml * 1e-6)).pressures_pa) / 1e3

    path = path_design(19, inverse_kpa, grid.gland_ml(np.zeros(3)), grid.gland_ml(np.full(3, 3.0)))
    held_out = np.random.default_rng(0).uniform(0, 3, (HELD_OUT, 3))
    truth = np.array([true_ml(p) for p in held_out])
    model_pct = np.abs(np.array([grid.gland_ml(p) for p in held_out]) / truth - 1) * 100
    print("| scans | fit (s) | kind | leave-one-out (%) | held-out error, mean / max (%) "
          "| model's own, mean / max (%) |")
    print("|---|---|---|---|---|---|")
    designs = (("Table I's 8", TABLE_ONE_KPA), ("grid 0, 1.5, 3 kPa: 27", GRID_KPA),
               ("the inverse's path: 19", path.tolist()))
    for name, points in designs:
        scans = [Measurement(tuple(map(float, p)), true_ml(np.array(p, dtype=float))) for p in points]
        started = time.perf_counter()
        correction = fit_correction(scans, grid)
        fit_s = time.perf_counter() - started
        corrected = CorrectedModel(grid, correction)
        error_pct = np.abs(np.array([corrected.gland_ml(p) for p in held_out]) / truth - 1) * 100
        print(f"| {name} | {fit_s:.1f} | {correction.kind} | {correction.leave_one_out_pct[correction.kind]:.2f} | "
              f"{error_pct.mean():.2f} / {error_pct.max():.2f} | {model_pct.mean():.2f} / {model_pct.max():.2f} |")


if __name__ == "__main__":
    main()
