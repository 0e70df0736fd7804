"""A built response table and its shapes against the shipped ones of ``builtin:converged``: the largest difference
of each volume (relative to the value) and of each node's position at each grid point (mm).

The shapes are stored as float32 modes and coefficients fitted per build, so two builds of the same solves may have
other modes of the same space: the positions they give are compared, not the arrays. A grid point's Newton stops at
1e-7 of the load (``response_table.POINT_TOLERANCE``), so two builds whose solves took other iterates differ by
about that much: the whole build of 2026-11-27 17:51 matched to 4e-11 of each volume, the one of 22:00 (after
issue 40's solver changes) to 4.3e-11, both 1e-6 mm or better at every node; the tolerances below are 1e-9 of each
volume and 1e-6 mm, far inside the files' own stated accuracy (their check errors, 0.139 % and 0.260 mm), which
are compared too.

    .venv/bin/python bench/table_against_shipped.py t.npz s.npz
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

import numpy as np

SHIPPED = Path(__file__).resolve().parent.parent / "model" / "scenes"
VOLUME_TOLERANCE = 1e-9
POSITION_TOLERANCE_MM = 1e-6


def shape_positions_mm(shapes: np.lib.npyio.NpzFile) -> np.ndarray:
    """Every stored node's position (mm) at every grid point, (i, j, k, nodes, 3)."""
    displacement = np.einsum("ijkm,mna->ijkna", shapes["coefficients"].astype(float), shapes["modes_m"].astype(float))
    return (shapes["rest_positions_m"] + displacement) * 1e3


def volumes_agree(built: Any, shipped: Any, what: str) -> bool:
    """Whether the built chamber and gland volumes are the shipped ones to VOLUME_TOLERANCE of each value."""
    agree = True
    for key in ("chamber", "gland"):
        worst = float(np.max(np.abs(built[key] - shipped[key]) / np.abs(shipped[key])))
        agree &= worst <= VOLUME_TOLERANCE
        print(f"{what} {key}: most off {worst:.1e} of the value (tolerance {VOLUME_TOLERANCE:g})")
    return agree


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("volumes", help="the built volumes' .npz (phantom model table --out)")
    parser.add_argument("shapes", help="the built shapes' .npz (--shapes-out)")
    args = parser.parse_args()
    ok = True
    with np.load(args.volumes) as built, np.load(SHIPPED / "prostate_converged.volumes.npz") as shipped:
        ok &= volumes_agree(built, shipped, "volumes")
        ok &= bool(np.isclose(built["check_errors_pct"], shipped["check_errors_pct"], rtol=1e-3))
        print(f"volumes check error: built {float(built['check_errors_pct']):.4g} %, shipped "
              f"{float(shipped['check_errors_pct']):.4g} %; build time {float(built['build_time_s']):.0f} s")
    with np.load(args.shapes) as built, np.load(SHIPPED / "prostate_converged.shapes.npz") as shipped:
        same_nodes = np.array_equal(built["nodes"], shipped["nodes"])
        worst_mm = (float(np.max(np.abs(shape_positions_mm(built) - shape_positions_mm(shipped)))) if same_nodes
                    else np.inf)
        ok &= worst_mm <= POSITION_TOLERANCE_MM
        print(f"shapes: same nodes {same_nodes}, most off {worst_mm:.1e} mm (tolerance {POSITION_TOLERANCE_MM:g})")
        ok &= volumes_agree(built, shipped, "shapes' volumes")
        ok &= bool(np.isclose(built["check_error_m"], shipped["check_error_m"], rtol=1e-3))
        print(f"shapes check error: built {float(built['check_error_m']) * 1e3:.4g} mm, shipped "
              f"{float(shipped['check_error_m']) * 1e3:.4g} mm")
    print("equal to the shipped files within the tolerances" if ok else "NOT equal to the shipped files")
    raise SystemExit(0 if ok else 1)


if __name__ == "__main__":
    main()
