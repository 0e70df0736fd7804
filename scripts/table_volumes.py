"""Write what a scene ships of its response table: its volumes (``[model] table_volumes``), from its full table,
and its outer surface's shapes (``[model] table_shapes``), from a coarser grid.

    .venv/bin/python scripts/table_volumes.py --scene builtin:converged \
        --out model/scenes/prostate_converged.volumes.npz \
        --shapes-out model/scenes/prostate_converged.shapes.npz

The full table (volumes and every node's position) is read from the disk cache, or built there first: n^3 full
solves on every core, with progress (most of an hour on one core for builtin:converged). Only its volumes, the
model they belong to and its rest volumes are written (9 kB for 7^3 points); a scene that names the file answers
volumes on a fresh machine without the build (``phantom.model.fidelity.response_table.shipped_table_volumes``).
The shapes are solved on their own grid (4^3 points at 1 kPa steps; minutes) and checked against full solves
between its points; only the outer surface's nodes are written. Either output may be left out.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scene", required=True, help="scene TOML path or built-in name, with [model] fidelity")
    parser.add_argument("--out", help="the volumes' .npz to write (the scene's [model] table_volumes)")
    parser.add_argument("--shapes-out", help="the shapes' .npz to write (the scene's [model] table_shapes)")
    args = parser.parse_args()
    if not args.out and not args.shapes_out:
        parser.error("give --out, --shapes-out or both")

    from phantom import PhantomError
    from phantom.model import PhantomModel
    from phantom.model.fidelity.response_table import (
        build_table_shapes,
        response_table,
        write_table_shapes,
        write_table_volumes,
    )
    from phantom.model.scene import (
        BUILTIN_SCENES,
        builtin_scene_path,
        read_scene_toml,
        scene_from_dict,
        without_shipped_tables,
    )

    started = time.perf_counter()

    def progress(done: int, total: int) -> None:
        print(f"  {done}/{total} solves in {time.perf_counter() - started:.0f} s", file=sys.stderr, flush=True)

    try:
        path = builtin_scene_path(args.scene) if args.scene in BUILTIN_SCENES else Path(args.scene)
        # the full table, not what the scene may ship already (or names before it is written)
        model = PhantomModel.from_scene(scene_from_dict(without_shipped_tables(read_scene_toml(path)), path))
        settings = model.model_settings
        if args.out:
            table = response_table(model, settings.pressure_max_pa, settings.table_points, progress=progress)
            write_table_volumes(table, model, args.out)
            print(f"wrote {args.out}: {table.points_per_axis}^{table.n_chambers} points, within "
                  f"{table.check_errors_pct:.2g} % of full solves at its checks")
        if args.shapes_out:
            shapes = build_table_shapes(model, settings.pressure_max_pa, progress=progress)
            write_table_shapes(shapes, model, args.shapes_out)
            print(f"wrote {args.shapes_out}: {len(shapes.nodes)} outer-surface nodes on "
                  f"{shapes.table.points_per_axis}^{shapes.table.n_chambers} points, within "
                  f"{shapes.check_error_m * 1e3:.3g} mm of full solves at its checks")
    except PhantomError as error:
        print(f"error: {error}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
