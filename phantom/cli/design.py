"""Subcommand of ``phantom``: ``design``, a phantom from a patient's shape (:mod:`phantom.design`).

Only argparse is imported at module load; the handler imports what it needs when it runs.
"""

from __future__ import annotations

import argparse
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    Subcommands = argparse._SubParsersAction[argparse.ArgumentParser]


def register(subparsers: Subcommands) -> None:
    """Add ``design`` to the ``phantom`` parser."""
    parser = subparsers.add_parser(
        "design", help="a phantom from a patient's shape: MRI mask or closed mesh to a model, a scene and a cast",
        description=("The paper's design step. From FROM (a NIfTI label mask in the pelvic MRI dataset's layout, or a "
                    "closed mesh in mm in the phantom's frame, e.g. what phantom shape average writes): the gland's "
                    "surface (largest component, smoothed without shrinking, base up, scaled to --volume-ml), the "
                    "built-in prostate's chambers (--chambers) laid into its anatomy, sized so the model reaches the "
                    "growth target (else as large as walls of --min-wall-mm allow), a tagged tetrahedral mesh and a "
                    "scene that phantom forward, inverse, calibrate and the daemon accept, the cast's STLs (two mould"
                    " halves, a wax core per chamber) and report.md. Minutes at the default mesh size."))
    parser.add_argument("source", metavar="FROM", help="a NIfTI mask or label map (.nii, .nii.gz), or a closed "
                                                       "mesh (.stl, .obj, .ply; mm, the phantom's frame)")
    parser.add_argument("--out", required=True, metavar="DIR", help="folder to write (created)")
    parser.add_argument("--volume-ml", type=float, default=26.3,
                        help="the gland's volume to scale to (default 26.3, the paper's average prostate)")
    parser.add_argument("--min-wall-mm", type=float, default=2.0,
                        help="the thinnest wall, chamber to surface and chamber to chamber (default 2)")
    parser.add_argument("--chambers", default="base,left,right",
                        help="which of the built-in prostate's chambers to design, comma-separated (default "
                             "base,left,right; any non-empty subset)")
    parser.add_argument("--growth-target-ml", type=float, default=None,
                        help="the grown gland's volume the chambers are sized for (default: the paper's 45 ml from "
                             "26.3, scaled to --volume-ml)")
    parser.add_argument("--growth-target-kpa", type=float, default=3.0,
                        help="the pressure in every chamber at which the target is to be reached (default 3)")
    parser.add_argument("--chamber-scale", type=float, default=None,
                        help="fix the chambers' size instead of sizing them to the target: times the built-in "
                             "prostate's proportions (walls below the minimum shrink them further)")
    parser.add_argument("--labels", default=None,
                        help="the gland's label numbers in a label map (a dataset *_mask.nii defaults to 4,5)")
    parser.add_argument("--size-mm", type=float, default=2.5, help="element size of the mesh (default 2.5)")
    parser.add_argument("--elements-per-wall", type=int, choices=(1, 2), default=2,
                        help="elements through the thinnest wall (default 2; 1: a preview on a mesh as coarse as the "
                             "sizing's, several times quicker to solve, its growth a few percent off the design's)")
    parser.add_argument("--element-order", type=int, choices=(1, 2), default=None,
                        help="1: 4-node tetrahedra, 2: 10-node (default: the inherited material's; 10-node for "
                             "builtin:converged)")
    parser.add_argument("--material-from", default="builtin:converged", metavar="SCENE",
                        help="the scene whose calibrated material law and element order the design inherits and "
                             "is sized with (default builtin:converged: Gent, E 10.86 kPa, 10-node); the cast must "
                             "still be measured and the scene calibrated to it")
    parser.add_argument("--fixation-radius-mm", type=float, default=6.0,
                        help="the fixed patch's radius about the base pole, the tube junction (default 6)")
    parser.add_argument("--stem-diameter-mm", type=float, default=3.0,
                        help="the tube channels' diameter, each core's stem (default 3)")
    parser.add_argument("--smooth-iterations", type=int, default=None,
                        help="Taubin smoothing passes (default 20 for a mask, 0 for a mesh)")
    parser.add_argument("--growth-kpa", default="0.5,1,1.5,2,2.5,3",
                        help="pressures of the predicted growth curve, kPa (default 0.5,1,...,3; 'none' skips "
                             "the solves)")
    parser.add_argument("--shape-run", default=None, metavar="RUN",
                        help="a trained shape run (phantom shape train): report the source's latent distance to "
                             "the run's population average (in its spread, and its percentile among the cases)")
    parser.add_argument("--json", action="store_true", help="print the design's figures as one JSON object")
    parser.set_defaults(run=run_design)


def run_design(args: argparse.Namespace) -> int:
    """Handler of ``phantom design``."""
    import json
    import sys

    from phantom.cli.common import parse_numbers
    from phantom.design.chambers import parse_chamber_kinds
    from phantom.design.errors import DesignError
    from phantom.design.pipeline import design, design_summary
    from phantom.design.result import DesignOptions

    labels = None
    if args.labels is not None:
        values = parse_numbers(args.labels, "--labels")
        if not values or any(value != int(value) or value < 1 for value in values):
            raise DesignError(f"--labels takes positive label numbers like 4,5; got {args.labels!r}")
        labels = tuple(int(value) for value in values)
    growth: tuple[float, ...] = ()
    if args.growth_kpa.strip().lower() != "none":
        growth = tuple(parse_numbers(args.growth_kpa, "--growth-kpa"))
        if any(not 0 < value <= 3.0 for value in growth):
            raise DesignError(f"--growth-kpa takes pressures above 0 and up to 3 kPa (the phantom's limit); got "
                              f"{args.growth_kpa!r}")
    if args.chamber_scale is not None and args.growth_target_ml is not None:
        raise DesignError("--chamber-scale fixes the chambers' size and --growth-target-ml sizes them: give one")
    options = DesignOptions(args.volume_ml, args.min_wall_mm, args.chamber_scale, args.size_mm, args.element_order,
                            args.fixation_radius_mm, args.stem_diameter_mm, labels, args.smooth_iterations, growth,
                            args.growth_target_ml, args.growth_target_kpa, parse_chamber_kinds(args.chambers),
                            args.shape_run, args.material_from, args.elements_per_wall)
    result = design(args.source, args.out, options,
                    progress=(lambda line: None) if args.json else (lambda line: print(line, flush=True)))
    for warning in result.warnings:
        print(f"warning: {warning}", file=sys.stderr)
    if args.json:
        print(json.dumps(design_summary(result)))
        return 0
    name, thinnest = result.thinnest_wall
    print(f"gland {result.gland_volume_ml:.2f} ml; chambers "
          + ", ".join(f"{volume:.2f}" for volume in result.chamber_volumes_ml)
          + f" ml; thinnest wall {thinnest:.2f} mm ({name}); outer surface {result.surface_distance_mm:.3f} mm from "
          f"the source's; silicone {result.cast.silicone_ml:.1f} ml")
    if result.latent is not None:
        print(f"latent distance to the population's average: {result.latent.distance:.3f} "
              f"({result.latent.in_spreads:.2f} spreads; the {result.latent.percentile:.0f}th percentile of the run's "
              f"{result.latent.cases} cases)")
    for note in result.notes:
        print(f"note: {note}")
    if result.material is not None:
        print(f"note: {result.material.caveat}")
    print(f"wrote {result.out}/scene.toml (try: phantom forward --scene {result.out}/scene.toml --pressures-kpa "
          f"1,1,1) and report.md")
    return 0
