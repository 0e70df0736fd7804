"""Subcommand of ``phantom``: ``inverse`` (pressures for a wanted volume); ``calibrate`` is in calibrate.py.

Only argparse is imported at module load; handlers import what they need when they run.
"""

from __future__ import annotations

import argparse
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from phantom.model.fem.model import PhantomModel
    from phantom.model.scene import Scene


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """Add ``inverse`` to the ``phantom`` parser."""
    inverse = subparsers.add_parser(
        "inverse", help="chamber pressures that give a wanted volume (offline)",
        description="Solve the inverse problem: the chamber pressures (kPa) that give a wanted gland volume, "
                    "chamber volumes, or a gland volume with a growth ratio between chambers.")
    inverse.add_argument("--scene", default="builtin:converged",
                         help="scene TOML path, 'builtin', 'builtin:converged' (default: the phantom as measured, on "
                              "a converged mesh) or 'builtin:calibrated' (its coarse 4-node fit)")
    target = inverse.add_mutually_exclusive_group(required=True)
    target.add_argument("--volume-ml", type=float, help="the gland's total volume (ml)")
    target.add_argument("--chamber-volumes-ml",
                        help="one volume (ml) per chamber, comma-separated; '-' leaves a chamber free")
    target.add_argument("--pressures-kpa", help="raw pressures (kPa), comma-separated: only bounds-checked")
    target.add_argument("--shape", metavar="FILE",
                        help="a gland to look like: a NIfTI mask or label map (.nii, .nii.gz) or a closed mesh in mm "
                             "in the phantom's frame; answers the pressures that bring the phantom's surface closest "
                             "to it (phantom.model.shape_inverse)")
    inverse.add_argument("--labels", help="with --shape: the gland's labels in a label map, comma-separated (4,5)")
    inverse.add_argument("--refine-solves", type=int, default=3,
                         help="with --shape: full solves that refine the table's answer at most (0: the table's)")
    inverse.add_argument("--scale", action="store_true",
                         help="with --shape: fit a uniform scale of the target too (reported apart; default rigid)")
    inverse.add_argument("--out", metavar="DIR",
                         help="with --shape: write shape_inverse.json, the residual map residual.png and the "
                              "phantom's surface at the answer (answer.stl) here")
    inverse.add_argument("--growth-ratio",
                         help="with --volume-ml: NAME=WEIGHT pairs (chamber names or indices), e.g. "
                              "'chamber1=2,chamber2=1' = chamber 1 grows twice as much as chamber 2")
    inverse.add_argument("--max-growth-ml",
                         help="upper limit on each chamber's growth above rest (ml), comma-separated; '-' for none")
    inverse.add_argument("--pressure-max-kpa", type=float,
                         help="upper pressure bound per chamber (kPa; default: the scene's, else 3)")
    inverse.add_argument("--fidelity", choices=("rest", "updated", "full"),
                         help="forward model the answer must satisfy (default: the scene's, else full)")
    inverse.add_argument("--size-mm", type=float, help="element size of the built-in mesh (mm)")
    inverse.add_argument("--json", action="store_true", help="print one JSON object")
    inverse.set_defaults(run=run_inverse)


def _growth_ratio_by_index(text: str, chamber_names: list[str]) -> dict[int, float]:
    """``--growth-ratio`` (``chamber1=2,chamber2=1``, names or indices) as chamber index -> weight."""
    from phantom import PhantomError
    from phantom.cli.common import parse_growth_ratio

    by_index = {}
    for name, weight in parse_growth_ratio(text).items():
        if name in chamber_names:
            by_index[chamber_names.index(name)] = weight
        elif name.isdigit() and int(name) < len(chamber_names):
            by_index[int(name)] = weight
        else:
            known = ", ".join(chamber_names)
            raise PhantomError(f"--growth-ratio names unknown chamber {name!r}; chambers are {known}")
    return by_index


def _load_model(args: argparse.Namespace) -> tuple[Scene, PhantomModel]:
    from phantom.model import PhantomModel, load_scene

    scene = load_scene(args.scene)
    return scene, PhantomModel.from_scene(scene, mesh_size_mm=args.size_mm)


def run_inverse(args: argparse.Namespace) -> int:
    """Handler of ``phantom inverse``."""
    import json

    from phantom import PhantomError
    from phantom.cli.common import parse_numbers
    from phantom.model.inverse import InverseSolver
    from phantom.model.target import Target

    if args.shape is not None:
        from phantom.cli.inverse_shape import run_shape_inverse

        return run_shape_inverse(args)
    if args.labels or args.out or args.scale:
        raise PhantomError("--labels, --scale and --out go with --shape")
    if args.growth_ratio and args.volume_ml is None:
        raise PhantomError("--growth-ratio goes with --volume-ml (the gland volume it shares out)")
    scene, model = _load_model(args)
    fidelity = args.fidelity or model.model_settings.fidelity or "full"
    if args.volume_ml is not None:
        target = Target(gland_volume_m3=args.volume_ml * 1e-6,
                        growth_ratio=_growth_ratio_by_index(args.growth_ratio, model.chamber_names)
                        if args.growth_ratio else None)
    elif args.chamber_volumes_ml is not None:
        volumes = parse_numbers(args.chamber_volumes_ml, "--chamber-volumes-ml", allow_free=True)
        target = Target(chamber_volumes_m3=[None if value is None else value * 1e-6 for value in volumes])
    else:
        target = Target(pressures_pa=[value * 1e3 for value in parse_numbers(args.pressures_kpa, "--pressures-kpa")])
    max_growth_m3 = None
    if args.max_growth_ml:
        limits_ml = parse_numbers(args.max_growth_ml, "--max-growth-ml", allow_free=True)
        if len(limits_ml) != model.n_chambers:
            raise PhantomError(f"--max-growth-ml needs {model.n_chambers} values ('-' for none), got {len(limits_ml)}")
        max_growth_m3 = [None if value is None else value * 1e-6 for value in limits_ml]
    pressure_max_pa = None if args.pressure_max_kpa is None else args.pressure_max_kpa * 1e3
    solver = InverseSolver(model, pressure_max_pa=pressure_max_pa, fidelity=fidelity, max_growth_m3=max_growth_m3)
    result = solver.pressures_for(target)
    report = {
        "pressures_kpa": (result.pressures_pa / 1e3).tolist(),
        "predicted_volume_ml": result.predicted_gland_volume_m3 * 1e6,
        "predicted_chamber_volumes_ml": (result.predicted_chamber_volumes_m3 * 1e6).tolist(),
        "iterations": result.iterations,
        "solve_time_s": result.solve_time_s,
        "qp_solve_time_s": result.qp_solve_time_s,
        "fidelity": solver.estimator.level,
    }
    if args.json:
        print(json.dumps(report))
    else:
        labels = scene.chamber_labels
        print(f"{'chamber':<26} " + " ".join(f"{label:>11}" for label in labels))
        print(f"{'pressure (kPa)':<26} " + " ".join(f"{value:11.4f}" for value in report["pressures_kpa"]))
        print(f"{'predicted volume (ml)':<26} "
              + " ".join(f"{value:11.3f}" for value in report["predicted_chamber_volumes_ml"]))
        print(f"predicted gland volume: {report['predicted_volume_ml']:.4f} ml\niterations: {result.iterations} "
              f"({report['fidelity']} model), {result.solve_time_s * 1e3:.1f} ms "
              f"(QP {result.qp_solve_time_s * 1e6:.0f} us)")
    return 0
