"""Speed of the FEM against scikit-fem on the same mesh and load, as ratios measured in one run.

The built-in prostate at three element sizes, without its fixation (3-2-1 held dofs, so both codes solve the
identical problem), E = 50 kPa, nu = 0.45, 1 kPa in each chamber. Each time is the best of ``--repeats``
runs (the machine is shared). Columns:

- assembly: the small-strain stiffness. phantom "refill" is the numba kernel writing into the precomputed
  CSR pattern; "corot. tangent" is what a Newton iteration pays (exact co-rotational Hessian with the
  pressure stiffness, SVD per element); "setup" adds element matrices and the pattern, as a new model does.
  scikit-fem: ``Basis`` + ``asm(linear_elasticity)``.
- linear solve: phantom: factorise (SuperLU, MMD on A^T + A) + one solve; scikit-fem: ``solve(*condense(K, f))``.
- full solve: phantom's co-rotational Newton solve on a fresh model (element data, pattern, the rest
  Cholesky factor read from its on-disk cache as in a warm CLI call, Newton) against scikit-fem's whole
  linear solve (assembly + load + factorisation + solve): what the nonlinear model costs in practice.

Run: ``.venv/bin/python bench/fem_speed.py [--repeats 3] [--plot build/bench/fem_speed.png]``
"""

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import skfem

from phantom.model.fem.linsolve import Factorization
from phantom.model.fem.model import PhantomModel
from phantom.model.mesh.prostate import builtin_prostate
from phantom.model.mesh.tetmesh import prepare_surfaces
from phantom.model.scene import Material

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))  # the oracles: tests/reference/
from reference.skfem_reference import skfem_problem, skfem_stiffness  # noqa: E402

CHAMBERS = ["chamber0", "chamber1", "chamber2"]
YOUNGS_MODULUS_PA, POISSON_RATIO = 50e3, 0.45
PRESSURES_PA = np.array([1e3, 1e3, 1e3])


def best_time_s(function, repeats):
    times = []
    for _ in range(repeats):
        started = time.perf_counter()
        function()
        times.append(time.perf_counter() - started)
    return min(times)


def model_at(size_mm):
    mesh = builtin_prostate(size_mm)
    surfaces = prepare_surfaces(mesh, CHAMBERS, None, "bench")
    return mesh, surfaces, PhantomModel(mesh, surfaces, CHAMBERS,
                                        Material("corotational", YOUNGS_MODULUS_PA, POISSON_RATIO))


def measure(size_mm, repeats):
    mesh, surfaces, model = model_at(size_mm)
    model.equilibrium(PRESSURES_PA)  # compile and warm every kernel once
    _, stiffness, load, held = skfem_problem(model, PRESSURES_PA)
    row = {"size_mm": size_mm, "nodes": len(mesh.nodes_m), "tets": len(mesh.tets)}
    row["refill_s"] = best_time_s(lambda: model.stiffness_matrix(), repeats)
    deformed = model.equilibrium(PRESSURES_PA).positions_m
    row["tangent_s"] = best_time_s(lambda: model.stiffness_matrix(deformed, "corotational", PRESSURES_PA), repeats)
    row["setup_s"] = best_time_s(lambda: PhantomModel(mesh, surfaces, CHAMBERS, model.material).stiffness_matrix(),
                                 repeats)
    row["skfem_assembly_s"] = best_time_s(lambda: skfem_stiffness(model), repeats)
    matrix = model.stiffness_matrix()
    right_hand_side = PRESSURES_PA @ model.volume_gradients(model.nodes_m)[:-1]
    right_hand_side[model.held_dofs] = 0.0
    row["phantom_linear_s"] = best_time_s(lambda: Factorization(matrix).solve(right_hand_side), repeats)
    row["skfem_linear_s"] = best_time_s(lambda: skfem.solve(*skfem.condense(stiffness, load, D=held)), repeats)

    def fresh_corotational():
        return PhantomModel(mesh, surfaces, CHAMBERS, model.material).equilibrium(PRESSURES_PA)

    row["phantom_full_s"] = best_time_s(fresh_corotational, repeats)
    row["iterations"] = fresh_corotational().iterations

    def skfem_whole():
        _, k, f, d = skfem_problem(model, PRESSURES_PA)
        return skfem.solve(*skfem.condense(k, f, D=d))

    row["skfem_full_s"] = best_time_s(skfem_whole, repeats)
    return row


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes-mm", default="5,3.5,2.5")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--plot", type=Path, default=None, help="write a PNG of the ratios here")
    args = parser.parse_args()
    rows = [measure(float(size), args.repeats) for size in args.sizes_mm.split(",")]
    print("| h mm | nodes | tets | refill ms | corot. tangent ms | setup ms | skfem asm ms | refill ratio "
          "| linear solve ms "
          "| skfem ms | ratio | corot. solve ms (Newton it.) | skfem linear total ms | ratio |")
    print("|---" * 14 + "|")
    for r in rows:
        print(f"| {r['size_mm']:g} | {r['nodes']} | {r['tets']} | {1e3 * r['refill_s']:.1f} "
              f"| {1e3 * r['tangent_s']:.0f} | {1e3 * r['setup_s']:.0f} "
              f"| {1e3 * r['skfem_assembly_s']:.0f} | {r['skfem_assembly_s'] / r['refill_s']:.1f}x faster "
              f"| {1e3 * r['phantom_linear_s']:.0f} | {1e3 * r['skfem_linear_s']:.0f} "
              f"| {r['skfem_linear_s'] / r['phantom_linear_s']:.2f}x faster "
              f"| {1e3 * r['phantom_full_s']:.0f} ({r['iterations']}) | {1e3 * r['skfem_full_s']:.0f} "
              f"| {r['phantom_full_s'] / r['skfem_full_s']:.2f}x the time |")
    if args.plot:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        nodes = [r["nodes"] for r in rows]
        figure, axes = plt.subplots(figsize=(6, 4))
        axes.loglog(nodes, [r["skfem_assembly_s"] / r["refill_s"] for r in rows], "o-", label="assembly (refill)")
        axes.loglog(nodes, [r["skfem_linear_s"] / r["phantom_linear_s"] for r in rows], "s-", label="linear solve")
        axes.loglog(nodes, [r["skfem_full_s"] / r["phantom_full_s"] for r in rows], "^-",
                    label="co-rotational vs skfem linear")
        axes.axhline(1.0, color="grey", lw=0.8)
        axes.set_xlabel("nodes")
        axes.set_ylabel("scikit-fem time / phantom time")
        axes.legend()
        args.plot.parent.mkdir(parents=True, exist_ok=True)
        figure.tight_layout()
        figure.savefig(args.plot, dpi=120)
        print(f"wrote {args.plot}")


if __name__ == "__main__":
    main()
