"""Speed side by side: the Neo-Hookean solve against the co-rotational one and against FElupe, same mesh.

The built-in prostate without its fixation (3-2-1 held dofs in all three), nu = 0.45, E = 50 kPa, the same
pressures in each chamber. All solve to a residual of 1e-9 (model) / 1e-10 (FElupe) of the load; the table
gives the chamber-0 growth of each, so that "equal accuracy" can be read off. Times: best of --repeats warm
solves (model built, kernels compiled); FElupe: one solve (its setup included, one load step per 10 % of p/E).

    .venv/bin/python bench/fem_hyperelastic.py --sizes-mm 3.5,2.5 --pressure-kpa 1
"""

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from phantom.model.fem.model import PhantomModel
from phantom.model.mesh.prostate import builtin_prostate
from phantom.model.mesh.tetmesh import prepare_surfaces
from phantom.model.scene import Material

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))  # the oracles: tests/reference/
from reference.felupe_reference import felupe_solve  # noqa: E402

CHAMBERS = ["chamber0", "chamber1", "chamber2"]
YOUNGS_MODULUS_PA = 50e3


def best_time_s(function, repeats):
    best, result = np.inf, None
    for _ in range(repeats):
        started = time.perf_counter()
        result = function()
        best = min(best, time.perf_counter() - started)
    return best, result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes-mm", default="3.5,2.5")
    parser.add_argument("--pressure-kpa", type=float, default=1.0)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--no-felupe", action="store_true")
    args = parser.parse_args()
    pressures = np.full(3, args.pressure_kpa * 1e3)
    print("| h mm | nodes | model | solve ms | Newton it. | chamber 0 growth % | vs co-rotational time "
          "| vs FElupe time |")
    print("|---|---|---|---|---|---|---|---|")
    for size_mm in (float(s) for s in args.sizes_mm.split(",")):
        mesh = builtin_prostate(size_mm)
        surfaces = prepare_surfaces(mesh, CHAMBERS, None, "bench")
        rows = {}
        for law in ("corotational", "neo_hookean"):
            model = PhantomModel(mesh, surfaces, CHAMBERS, Material(law, YOUNGS_MODULUS_PA, 0.45))
            model.equilibrium(pressures)
            seconds, state = best_time_s(lambda model=model: model.equilibrium(pressures), args.repeats)
            growth = state.chamber_volumes_m3[0] / model.rest_chamber_volumes_m3[0] - 1
            rows[law] = (seconds, state.iterations, growth, model)
        felupe_s = None
        if not args.no_felupe:
            model = rows["neo_hookean"][3]
            steps = max(1, int(np.ceil(args.pressure_kpa * 1e3 / YOUNGS_MODULUS_PA / 0.1)))
            started = time.perf_counter()
            positions = felupe_solve(model, pressures, load_steps=steps)
            felupe_s = time.perf_counter() - started
            growth = model.volumes(positions)[0][0] / model.rest_chamber_volumes_m3[0] - 1
            rows["FElupe (Neo-Hookean)"] = (felupe_s, None, growth, model)
        corotational_s = rows["corotational"][0]
        for name, (seconds, iterations, growth, model) in rows.items():
            versus_felupe = f"{felupe_s / seconds:.1f}x faster" if felupe_s and name != "FElupe (Neo-Hookean)" else ""
            print(f"| {size_mm:g} | {len(model.nodes_m)} | {name} | {seconds * 1e3:.0f} | {iterations or ''} | "
                  f"{100 * growth:.4f} | {seconds / corotational_s:.2f}x | {versus_felupe} |", flush=True)


if __name__ == "__main__":
    main()
