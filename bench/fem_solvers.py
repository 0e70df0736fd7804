"""Linear solvers for the model's stiffness, measured on the built-in prostate (the choice in linsolve.py).

The rest stiffness of the built-in scene (fixed by springs: symmetric positive definite), E = 50 kPa,
nu = 0.45. For each solver: the factorisation (or preconditioner set-up) and one solve, best of
``--repeats``, and the relative residual. CHOLMOD comes from scikit-sparse 0.4.16 built against Debian 12's
SuiteSparse 5.12 (0.5 needs SuiteSparse 7). Times are relative to SuperLU with COLAMD (scipy's default).

Run: ``.venv/bin/python bench/fem_solvers.py [--sizes-mm 3.5,2.5] [--repeats 3]``
"""

import argparse
import time

import numpy as np

from phantom.model.fem.linsolve import METHODS, Factorization, default_method
from phantom.model.fem.model import PhantomModel
from phantom.model.scene import load_scene


def best(function, repeats):
    times, result = [], None
    for _ in range(repeats):
        started = time.perf_counter()
        result = function()
        times.append(time.perf_counter() - started)
    return min(times), result


def measure(name, factorize, matrix, rhs, repeats):
    """Best factorisation and solve times (s) and the solution (None if the iterative solver failed)."""
    factor_s, solve = best(lambda: factorize(matrix), repeats)
    try:
        solve_s, solution = best(lambda: solve(rhs), repeats)
    except ArithmeticError:
        return name, factor_s, np.inf, None
    return name, factor_s, solve_s, solution


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes-mm", default="3.5,2.5")
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    print("| h mm | dofs | solver | factorise ms | solve ms | relative residual | factorise+solve vs splu-colamd |")
    print("|---|---|---|---|---|---|---|")
    for size in args.sizes_mm.split(","):
        model = PhantomModel.from_scene(load_scene("builtin"), mesh_size_mm=float(size))
        matrix = model.stiffness_matrix()
        rhs = np.random.default_rng(0).normal(size=matrix.shape[0])
        methods = [method for method in METHODS if method != "cholmod" or default_method() == "cholmod"]
        solvers = [(method, lambda matrix, method=method: Factorization(matrix, method).solve) for method in methods]
        rows = [measure(name, factorize, matrix, rhs, args.repeats) for name, factorize in solvers]
        baseline = next(factor_s + solve_s for name, factor_s, solve_s, _ in rows if name == "splu-colamd")
        for name, factor_s, solve_s, solution in rows:
            if solution is None:
                print(f"| {size} | {matrix.shape[0]} | {name} | {1e3 * factor_s:.0f} | did not converge | | |")
                continue
            residual = np.linalg.norm(matrix @ solution - rhs) / np.linalg.norm(rhs)
            print(f"| {size} | {matrix.shape[0]} | {name} | {1e3 * factor_s:.0f} | {1e3 * solve_s:.1f} "
                  f"| {residual:.1e} | {(factor_s + solve_s) / baseline:.2f} |")


if __name__ == "__main__":
    main()
