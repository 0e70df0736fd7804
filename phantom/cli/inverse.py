"""Subcommand of ``phantom``: ``inverse`` (pressures for a wanted volume); ``calibrate`` is in calibrate.py.

Only argparse is imported at module load; handlers import what they need when they run.
"""

from __future__ import annotations

import argparse
import contextlib
from collections.abc import Iterator
from typing import TYPE_CHECKING

if TYPE_CHECKING:
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
    inverse.add_argument("--refine-solves", type=int,
                         help="with --shape: full solves that refine the table's answer at most (0: the table's; "
                              "default 3)")
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
                         help="upper pressure bound per chamber (kPa; default: the scene's, else 3); with the "
                              "scene's shipped table (fidelity table) at most the scene's bound")
    inverse.add_argument("--fidelity", choices=("rest", "updated", "full"),
                         help="forward model the answer must satisfy (default: the scene's, else full)")
    inverse.add_argument("--size-mm", type=float, help="element size of the built-in mesh (mm)")
    inverse.add_argument("--json", action="store_true", help="print one JSON object")
    inverse.set_defaults(run=run_inverse)


#: What a user who asks for a growth ratio writes (``--growth-ratio``'s syntax), for its messages.
GROWTH_RATIO_EXAMPLE = "e.g. --growth-ratio chamber1=2,chamber2=1 (chamber 1 grows twice as much as chamber 2)"


def _growth_ratio_by_index(text: str, chamber_names: list[str]) -> dict[int, float]:
    """``--growth-ratio`` (``chamber1=2,chamber2=1``, names or indices) as chamber index -> weight: at least two
    chambers, each once, with positive weights (refused in the command line's words before the model is built)."""
    from phantom import PhantomError
    from phantom.cli.common import parse_growth_ratio

    by_index: dict[int, float] = {}
    for name, weight in parse_growth_ratio(text).items():
        if name in chamber_names:
            index = chamber_names.index(name)
        elif name.isdigit() and int(name) < len(chamber_names):
            index = int(name)
        else:
            known = ", ".join(chamber_names)
            raise PhantomError(f"--growth-ratio names unknown chamber {name!r}; chambers are {known}")
        if index in by_index:
            raise PhantomError(f"--growth-ratio names chamber {index} twice ({text!r}): give each chamber once, "
                               f"{GROWTH_RATIO_EXAMPLE}")
        if not weight > 0:
            raise PhantomError(f"--growth-ratio weights must be positive (the blowers only inflate), got {name}="
                               f"{weight:g}: {GROWTH_RATIO_EXAMPLE}")
        by_index[index] = weight
    if len(by_index) < 2:
        raise PhantomError(f"--growth-ratio relates at least two chambers as NAME=WEIGHT pairs, got {text!r}: "
                           f"{GROWTH_RATIO_EXAMPLE}")
    return by_index


def _volume_ml(value: float) -> float:
    """``--volume-ml``: the gland's volume, a positive finite number of ml."""
    import math

    from phantom import PhantomError

    if not (math.isfinite(value) and value > 0):
        raise PhantomError(f"--volume-ml is the gland's total volume in ml, a positive number like 32; got {value:g}")
    return value


def _chamber_volumes_ml(text: str, scene: Scene) -> list[float | None]:
    """``--chamber-volumes-ml``: one volume (ml) or '-' (free) per chamber of ``scene``, at least one given."""
    from phantom import PhantomError
    from phantom.cli.common import parse_numbers
    from phantom.model.scene import describe_chambers

    volumes = parse_numbers(text, "--chamber-volumes-ml", allow_free=True)
    labels = scene.chamber_labels
    example = ",".join(["4"] + ["-"] * (len(labels) - 1))
    if len(volumes) != len(labels):
        raise PhantomError(f"--chamber-volumes-ml has {len(volumes)} entries; the scene has {len(labels)} chambers "
                           f"({describe_chambers(labels)}): give one volume (ml) per chamber, in that order, "
                           f"'-' for a free chamber, e.g. {example}")
    if all(value is None for value in volumes):
        raise PhantomError(f"--chamber-volumes-ml leaves every chamber free ('-' or an empty entry leaves one free): "
                           f"give at least one chamber's volume (ml), e.g. {example}")
    for label, value in zip(labels, volumes, strict=True):
        if value is not None and value <= 0:
            raise PhantomError(f"--chamber-volumes-ml gives {label} {value:g} ml: a chamber's volume is positive "
                               f"(ml), e.g. {example}")
    return volumes


def _max_growth_ml(text: str, scene: Scene) -> list[float | None]:
    """``--max-growth-ml``: one growth limit (ml above rest, 0 or more) or '-' (none) per chamber of ``scene``."""
    from phantom import PhantomError
    from phantom.cli.common import parse_numbers
    from phantom.model.scene import describe_chambers

    limits = parse_numbers(text, "--max-growth-ml", allow_free=True)
    labels = scene.chamber_labels
    if len(limits) != len(labels):
        raise PhantomError(f"--max-growth-ml has {len(limits)} values; the scene has {len(labels)} chambers "
                           f"({describe_chambers(labels)}): give one limit (ml above rest) per chamber, in that "
                           "order, '-' for none")
    for label, value in zip(labels, limits, strict=True):
        if value is not None and value < 0:
            raise PhantomError(f"--max-growth-ml gives {label} {value:g} ml: a limit is the growth above rest (ml), "
                               "0 or more (the blowers only inflate)")
    return limits


def _pressure_max_kpa(args: argparse.Namespace, scene: Scene, fidelity: str) -> float | None:
    """``--pressure-max-kpa`` checked (a positive finite kPa), or None when not given. A bound above the one the
    scene's shipped response table was made for (its ``[model] pressure_max_kpa``) is refused before the model is
    built: the table cannot answer beyond it. (A lower bound is honoured with the table: :func:`_estimator`.)"""
    import math

    from phantom import PhantomError

    value: float | None = args.pressure_max_kpa
    if value is None:
        return None
    if not (math.isfinite(value) and value > 0):
        raise PhantomError(f"--pressure-max-kpa is the upper pressure bound per chamber in kPa, a positive number "
                           f"like 3; got {value:g}")
    table_kpa = scene.model_settings.pressure_max_pa / 1e3
    if fidelity == "table" and scene.model_settings.table_volumes is not None and value > table_kpa:
        raise PhantomError(
            f"--pressure-max-kpa {value:g} is above the {table_kpa:g} kPa the scene's response table covers "
            f"({scene.model_settings.table_volumes.name}, [model] table_volumes): give at most {table_kpa:g}, or "
            "solve without the table with --fidelity full (full solves: about a minute an answer)")
    return value


def run_inverse(args: argparse.Namespace) -> int:
    """Handler of ``phantom inverse``: every argument is checked against the scene, in the command line's words
    (flags, ml, kPa), before the finite-element model is built."""
    import json

    from phantom import PhantomError
    from phantom.cli.common import scene_pressures_kpa
    from phantom.model import PhantomModel, load_scene
    from phantom.model.fidelity.levels import VolumeEstimator
    from phantom.model.inverse import InverseSolver
    from phantom.model.target import Target

    if args.shape is not None:
        from phantom.cli.inverse_shape import run_shape_inverse

        return run_shape_inverse(args)
    if args.labels or args.out or args.scale or args.refine_solves is not None:
        raise PhantomError("--labels, --scale, --out and --refine-solves go with --shape")
    if args.growth_ratio and args.volume_ml is None:
        raise PhantomError("--growth-ratio goes with --volume-ml (the gland volume it shares out)")
    scene = load_scene(args.scene)
    fidelity = args.fidelity or scene.model_settings.fidelity or "full"
    pressure_max_kpa = _pressure_max_kpa(args, scene, fidelity)
    if args.volume_ml is not None:
        target = Target(gland_volume_m3=_volume_ml(args.volume_ml) * 1e-6,
                        growth_ratio=_growth_ratio_by_index(args.growth_ratio, scene.chambers)
                        if args.growth_ratio else None)
    elif args.chamber_volumes_ml is not None:
        volumes = _chamber_volumes_ml(args.chamber_volumes_ml, scene)
        target = Target(chamber_volumes_m3=[None if value is None else value * 1e-6 for value in volumes])
    else:
        pressures_kpa = scene_pressures_kpa(args.pressures_kpa, scene, pressure_max_kpa=pressure_max_kpa)
        target = Target(pressures_pa=[value * 1e3 for value in pressures_kpa])
    max_growth_m3 = None
    if args.max_growth_ml:
        max_growth_m3 = [None if value is None else value * 1e-6 for value in _max_growth_ml(args.max_growth_ml, scene)]
    model = PhantomModel.from_scene(scene, mesh_size_mm=args.size_mm)
    pressure_max_pa = None if pressure_max_kpa is None else pressure_max_kpa * 1e3
    estimator = None
    scene_max_pa = scene.model_settings.pressure_max_pa
    if fidelity == "table" and pressure_max_pa is not None and pressure_max_pa < scene_max_pa:
        # the scene's table covers the box up to its own bound: the solver's lower bound is honoured within it
        estimator = VolumeEstimator(model, level="table", pressure_max_pa=scene_max_pa)
    solver = InverseSolver(model, pressure_max_pa=pressure_max_pa, fidelity=fidelity, max_growth_m3=max_growth_m3,
                           estimator=estimator)
    with _solver_output_silenced():
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


@contextlib.contextmanager
def _solver_output_silenced() -> Iterator[None]:
    """Standard output (the file descriptor) goes nowhere while the inverse solves: OSQP's C code prints
    "Polishing not needed ..." there whatever its ``verbose`` (osqp 1.x), which broke ``--json``'s one object.
    Nothing of ours prints during a solve (progress and logs go to stderr)."""
    import os
    import sys

    sys.stdout.flush()
    saved = os.dup(1)
    try:
        with open(os.devnull, "w") as nowhere:
            os.dup2(nowhere.fileno(), 1)
        yield
    finally:
        sys.stdout.flush()
        os.dup2(saved, 1)
        os.close(saved)
