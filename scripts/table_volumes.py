"""Write the response table's volumes that a scene ships (``[model] table_volumes``), from its full table.

    .venv/bin/python scripts/table_volumes.py --scene builtin:converged \
        --out model/scenes/prostate_converged.volumes.npz

The full table (volumes and every node's position) is read from the disk cache, or built there first: n^3 full
solves on every core, with progress (most of an hour on one core for builtin:converged). Only its volumes, the
model they belong to and its rest volumes are written (9 kB for 7^3 points); a scene that names the file answers
volumes on a fresh machine without the build (``phantom.model.fidelity.response_table.shipped_table_volumes``).
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scene", required=True, help="scene TOML path or built-in name, with [model] fidelity")
    parser.add_argument("--out", required=True, help="the .npz to write (the scene's [model] table_volumes)")
    args = parser.parse_args()

    from phantom import PhantomError
    from phantom.model import PhantomModel, load_scene
    from phantom.model.fidelity.response_table import response_table, write_table_volumes

    started = time.perf_counter()

    def progress(done: int, total: int) -> None:
        print(f"  {done}/{total} solves in {time.perf_counter() - started:.0f} s", file=sys.stderr, flush=True)

    try:
        scene = load_scene(args.scene)
        # the full table, not the volumes the scene may ship already
        scene = dataclasses.replace(scene, model_settings=dataclasses.replace(scene.model_settings,
                                                                              table_volumes=None))
        model = PhantomModel.from_scene(scene)
        settings = model.model_settings
        table = response_table(model, settings.pressure_max_pa, settings.table_points, progress=progress)
        write_table_volumes(table, model, args.out)
    except PhantomError as error:
        print(f"error: {error}", file=sys.stderr)
        return 1
    print(f"wrote {args.out}: {table.points_per_axis}^{table.n_chambers} points, within "
          f"{table.check_errors_pct:.2g} % of full solves at its checks")
    return 0


if __name__ == "__main__":
    sys.exit(main())
