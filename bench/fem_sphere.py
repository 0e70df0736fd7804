"""Error against run time: the thick hollow sphere (a = 10 mm, b = 20 mm) against the Lame closed form.

Relative error of the cavity and outer volume compliance (linear model) at each element size, the observed
order between successive sizes, the Richardson extrapolation (order 2) from each pair, and the time to
mesh, build and solve. This is the study behind the tolerances of tests/test_fem_sphere.py.

Run: ``.venv/bin/python bench/fem_sphere.py [--sizes-mm 4,2.83,2,1.41]``
"""

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))
from test_fem_sphere import lame_volume_changes_m3_per_pa, sphere_model  # noqa: E402


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes-mm", default="4,2.83,2,1.41")
    parser.add_argument("--poisson-ratios", default="0.3,0.45")
    args = parser.parse_args()
    sizes = [float(size) for size in args.sizes_mm.split(",")]
    print("| nu | h mm | nodes | cavity error | outer error | order (cavity) | extrapolated cavity error "
          "| time s |")
    print("|---|---|---|---|---|---|---|---|")
    for poisson_ratio in (float(nu) for nu in args.poisson_ratios.split(",")):
        exact = np.array(lame_volume_changes_m3_per_pa(poisson_ratio))
        previous = None
        for size in sizes:
            started = time.perf_counter()
            model = sphere_model(size, poisson_ratio)
            compliance = model.rest_compliance()
            elapsed = time.perf_counter() - started
            computed = np.array([compliance.chamber_m3_per_pa[0, 0], compliance.gland_m3_per_pa[0]])
            errors = computed / exact - 1
            order = extrapolated = ""
            if previous is not None:
                order = f"{np.log(previous[1][0] / errors[0]) / np.log(previous[0] / size):.2f}"
                ratio_squared = (previous[0] / size) ** 2
                value = (ratio_squared * computed[0] - previous[2][0]) / (ratio_squared - 1)
                extrapolated = f"{value / exact[0] - 1:+.4f}"
            print(f"| {poisson_ratio} | {size} | {len(model.nodes_m)} | {errors[0]:+.4f} | {errors[1]:+.4f} "
                  f"| {order} | {extrapolated} | {elapsed:.1f} |")
            previous = (size, errors, computed)


if __name__ == "__main__":
    main()
