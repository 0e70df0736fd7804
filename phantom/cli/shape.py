"""Subcommands of ``phantom``: ``shape ...``, the paper's shape analysis (a 3D VAE of prostate shapes).

``phantom shape synthesize | train | average | clusters | encode | compare | report``. Only argparse is
imported at module load; each handler imports what it needs when it runs.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from phantom.shape.analysis import ShapeModel

    Subcommands = argparse._SubParsersAction[argparse.ArgumentParser]


def register(subparsers: Subcommands) -> None:
    """Add ``shape`` and its subcommands to the ``phantom`` parser."""
    shape = subparsers.add_parser(
        "shape", help="shape analysis: train a 3D VAE on prostate segmentations, the average shape, clusters, "
                      "latent distances",
        description="The paper's shape analysis. Train a 3D convolutional VAE on labelled pelvic MRI (the "
                    "Cross-institution Male Pelvic Structures layout: DATA/data/<id>_mask.nii), a folder of "
                    "masks or of closed meshes; then decode the average shape, cluster the latent space and "
                    "measure how far a mesh (the phantom's model, a scan) is from another.")
    commands = shape.add_subparsers(dest="shape_command", metavar="SUBCOMMAND", required=True)

    synthesize = commands.add_parser(
        "synthesize", help="write a synthetic population of prostates as NIfTI in the dataset's layout",
        description="Write OUT/data/<id>_img.nii and <id>_mask.nii (labels as in the real dataset: 4 TZ, 5 CG, "
                    "1 bladder, 6 rectum, 7 seminal vesicles) and OUT/institution.txt: the phantom's body "
                    "varied in size, anteroposterior and proximodistal length, lobe asymmetry and smooth random "
                    "deformations, imaged with seven institutions' spacings and orientations.")
    synthesize.add_argument("--out", required=True, help="folder to write (created)")
    synthesize.add_argument("--cases", type=int, default=120, help="number of cases (default 120)")
    synthesize.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    synthesize.add_argument("--no-images", action="store_true", help="write only the label maps")
    synthesize.add_argument("--symmetric", action="store_true",
                            help="every second case the mirror image of the one before (a symmetric population)")
    synthesize.set_defaults(run=run_synthesize)

    train = commands.add_parser(
        "train", help="train the VAE on a dataset, a folder of masks or a folder of meshes",
        description="Voxelise every shape in DATA onto one grid (isotropic, centred on its centroid, one scale "
                    "for the set) and train the VAE; write the run folder RUN (checkpoint, latents, loss curves).")
    train.add_argument("data", metavar="DATA", help="the dataset folder (with data/), or a folder of masks or "
                                                    "closed meshes")
    train.add_argument("--out", required=True, metavar="RUN", help="run folder to write")
    train.add_argument("--replace", action="store_true", help="train again over a run already in --out")
    train.add_argument("--epochs", type=int, default=500, help="training epochs (default 500, as the paper)")
    train.add_argument("--seed", type=int, default=0, help="seed of weights, split and batches (default 0)")
    train.add_argument("--batch-size", type=int, default=10, help="cases per step (default 10)")
    train.add_argument("--learning-rate", type=float, default=1e-3, help="Adam's step size (default 1e-3)")
    train.add_argument("--kld-weight", type=float, default=0.01, help="weight of the KL term (default 0.01)")
    train.add_argument("--latent-dim", type=int, default=64, help="latent dimensions (default 64)")
    train.add_argument("--grid-size", type=int, default=32, help="voxels per grid side (default 32)")
    train.add_argument("--channels", default="16,32,64",
                       help="encoder channels per level, each level halving the grid (default 16,32,64)")
    train.add_argument("--validation-fraction", type=float, default=0.1,
                       help="share of the cases held out to measure reconstruction (default 0.1)")
    train.add_argument("--labels", default="4,5",
                       help="label numbers of the shape in label maps (default 4,5: the prostate's TZ and CG)")
    train.set_defaults(run=run_train)

    average = _run_command(
        commands, "average", run_average, "decode the mean latent vector: the average shape as a mesh, with its volume",
        "Decode the mean of the cases' latent vectors (the paper's average prostate), surface it by marching cubes "
        "and write it (.obj, .ply, .stl; mm, the phantom's frame); the JSON has volume_ml.")
    average.add_argument("--out", required=True, metavar="MESH", help="mesh file to write")

    clusters = _run_command(
        commands, "clusters", run_clusters, "k-means of the latent vectors: decoded centres and implicit-distance "
        "heatmaps",
        "Cluster the cases' latent vectors by k-means, decode each centre (cluster_<i>.ply) and draw the implicit "
        "distance between every pair of centres on the first one's surface, front and side, with a colour bar in "
        "mm (the paper's Fig. 6).")
    clusters.add_argument("--k", type=int, default=3, help="number of clusters (default 3)")
    clusters.add_argument("--out", required=True, metavar="DIR", help="folder for the meshes and heatmaps")
    clusters.add_argument("--seed", type=int, default=0, help="k-means seed (default 0)")

    encode = _run_command(
        commands, "encode", run_encode, "the latent vector of one shape (mask, label map or closed mesh)",
        "Put one shape on the run's grid and print its latent vector (the encoder's mean).")
    encode.add_argument("input", metavar="INPUT", help=SHAPE_FILE_HELP)

    compare = _run_command(
        commands, "compare", run_compare, "latent distance and mean closest-point distance (after ICP) between two "
        "shapes",
        "Align B to A rigidly (ICP), then report the mean closest-point distance between their surfaces and the "
        "distance between their latent vectors (the paper's Figs. 5 and 9).")
    compare.add_argument("a", metavar="A", help=SHAPE_FILE_HELP)
    compare.add_argument("b", metavar="B", help=SHAPE_FILE_HELP)

    report = _run_command(
        commands, "report", run_report, "the paper's shape figures for a trained run: average, distances to the "
        "model, clusters",
        "Write DIR/report.md and report.json: the average shape and its volume, its mean closest-point distance "
        "(after ICP) and latent distance to the phantom model's rest shape with a heatmap (Fig. 5), and the "
        "k-means clusters' heatmaps (Fig. 6).", with_json=False)
    report.add_argument("--out", required=True, metavar="DIR", help="folder for the report")
    report.add_argument("--k", type=int, default=3, help="number of clusters (default 3)")


    reach = commands.add_parser(
        "reach", help="how much of a population the phantom can show: each case's best pressures and distance",
        description="For each case of a population (a shape dataset or folder of masks or meshes, or a trained "
                    "run's cluster centres), the pressures that bring the phantom closest to it (the shape "
                    "inverse: phantom inverse --shape) and the distance before and after; writes reach.csv, "
                    "reach.json, a histogram and, with a run, the latent-space picture of the cases covered.")
    reach.add_argument("source", metavar="RUN_OR_DATA",
                       help="a run folder (its k-means cluster centres) or a dataset folder, folder of masks or "
                            "meshes (each case)")
    reach.add_argument("--scene", default="builtin:converged", help="the phantom (default builtin:converged)")
    reach.add_argument("--out", required=True, metavar="DIR", help="folder for the table and pictures")
    reach.add_argument("--within-mm", type=float, default=1.0,
                       help="a case is covered when the phantom comes this close (mm, default 1)")
    reach.add_argument("--run", dest="shape_run", metavar="RUN",
                       help="with a dataset: the run whose latent space the picture uses")
    reach.add_argument("--k", type=int, default=3, help="with a run: number of cluster centres (default 3)")
    reach.add_argument("--labels", default=None, help="the gland's labels in label maps (default 4,5)")
    reach.add_argument("--refine-solves", type=int, default=0,
                       help="full solves that refine each case's table answer (default 0: the table's)")
    reach.add_argument("--scale", action="store_true", help="fit a uniform scale of each case too")
    reach.add_argument("--json", action="store_true", help="print one JSON object")
    reach.set_defaults(run=run_reach)


SHAPE_FILE_HELP = "a NIfTI mask or label map (the run's labels), or a closed mesh (mm, the phantom's frame)"


def run_reach(args: argparse.Namespace) -> int:
    """Handler of ``phantom shape reach``."""
    import json
    import sys
    from pathlib import Path

    import numpy as np

    from phantom.model import PhantomModel, load_scene
    from phantom.model.mesh.surface import TriangleMesh
    from phantom.model.shape_file import checked_gland, largest_body
    from phantom.model.shape_inverse import ShapeInverse, surface_shapes
    from phantom.shape.dataset import find_cases
    from phantom.shape.errors import ShapeError
    from phantom.shape.reach import population, reach, summary, write_reach

    if args.refine_solves < 0:
        raise ShapeError(f"--refine-solves must be 0 or more, got {args.refine_solves}")
    labels = _labels(args.labels) if args.labels else None
    source = Path(args.source)
    is_run = (source / "config.json").is_file()
    if is_run and args.shape_run:
        raise ShapeError("--run goes with a dataset: RUN_OR_DATA is a run already (its cluster centres)")
    background = None
    if is_run:
        shape_model = _run_model(args.source)
        centres, _, decoded = shape_model.clusters(args.k)
        # a decoded centre may carry islands of voxels above one half: its largest body is the gland
        cases = [(f"cluster {index}", checked_gland(largest_body(TriangleMesh(shape.vertices_mm, shape.triangles),
                                                                 f"cluster {index}"), f"cluster {index}'s centre"))
                 for index, shape in enumerate(decoded)]
        latents: list[np.ndarray | None] = list(centres)
        background = shape_model.case_latents()[1]
        title = f"{args.source}: {args.k} cluster centres on {args.scene}"
    else:
        cases = population(source, labels)
        latents = [None] * len(cases)
        if args.shape_run:
            shape_model = _run_model(args.shape_run)
            latents = [shape_model.encode_file(case.path) for case in find_cases(source)]
        title = f"{args.source}: {len(cases)} cases on {args.scene}"
    model = PhantomModel.from_scene(load_scene(args.scene))

    def told(message: str) -> None:
        if not args.json:
            print(message, file=sys.stderr, flush=True)

    inverse = ShapeInverse(model, surface_shapes(model, progress=lambda done, total: told(
        f"shape reach: the table of shapes, {done}/{total} solves")))
    results = reach(inverse, cases, args.within_mm, args.refine_solves, args.scale, told)
    for result, latent in zip(results, latents, strict=True):
        result.latent = latent
    files = write_reach(results, Path(args.out), args.within_mm, title, background)
    figures = {**summary(results, args.within_mm), "files": files}
    if args.json:
        print(json.dumps(figures))
        return 0
    print(f"{'case':<16} {'ml':>7} {'kPa':>17} {'rest mm':>8} {'mm':>7} covered")
    for result in results:
        print(f"{result.name:<16} {result.volume_ml:7.2f} {','.join(f'{v:.2f}' for v in result.pressures_kpa):>17} "
              f"{result.rest_distance_mm:8.3f} {result.distance_mm:7.3f} {'yes' if result.covered else 'no'}")
    print(f"covered within {args.within_mm:g} mm: {figures['covered']} of {figures['cases']} cases "
          f"({figures['covered_at_rest']} at rest); {figures['time_s']:.1f} s")
    for kind, path in files.items():
        print(f"{kind}: {path}")
    return 0


def _run_command(commands: Subcommands, name: str, handler: Callable[[argparse.Namespace], int], summary: str,
                 description: str, with_json: bool = True) -> argparse.ArgumentParser:
    """A subcommand on a trained run: its RUN argument, and --json where it prints a result."""
    parser: argparse.ArgumentParser = commands.add_parser(name, help=summary, description=description)
    parser.add_argument("run_dir", metavar="RUN", help="a run folder written by phantom shape train")
    if with_json:
        parser.add_argument("--json", action="store_true", help="print one JSON object")
    parser.set_defaults(run=handler)
    return parser


def _run_model(path: str) -> ShapeModel:
    from phantom.shape.analysis import ShapeModel

    return ShapeModel.load(path)


def _labels(text: str) -> tuple[int, ...]:
    from phantom.cli.common import parse_numbers
    from phantom.shape.errors import ShapeError

    values = parse_numbers(text, "--labels")
    if not values or any(v is None or v != int(v) or v < 1 for v in values):
        raise ShapeError(f"--labels takes positive label numbers like 4,5; got {text!r}")
    return tuple(int(v) for v in values if v is not None)


def run_synthesize(args: argparse.Namespace) -> int:
    """Handler of ``phantom shape synthesize``."""
    from phantom.cli.common import progress_reporter
    from phantom.shape.synthetic import PopulationSpec, synthesize

    spec = PopulationSpec(mirror_pairs=args.symmetric)
    out = synthesize(args.out, cases=args.cases, seed=args.seed, spec=spec, images=not args.no_images,
                     progress=progress_reporter("shape synthesize: cases written"))
    print(f"wrote {args.cases} synthetic cases under {out} (data/<id>_mask.nii, institution.txt)")
    return 0


def run_train(args: argparse.Namespace) -> int:
    """Handler of ``phantom shape train``."""
    from phantom.cli.common import parse_numbers
    from phantom.shape.dataset import load_shapes
    from phantom.shape.errors import ShapeError
    from phantom.shape.training import TrainConfig, compute_device, train
    from phantom.shape.vae import VAEConfig

    done = Path(args.out) / "config.json"
    if done.is_file() and not args.replace:  # a run is hours of training: it is not replaced by a slip
        raise ShapeError(f"--out {args.out} holds a trained run already ({done.name}): give another --out, or "
                         "--replace to train again over it")
    values = parse_numbers(args.channels, "--channels")
    if any(v is None or v != int(v) or v < 1 for v in values):
        raise ShapeError(f"--channels takes positive whole numbers like 16,32,64; got {args.channels!r}")
    channels = tuple(int(v) for v in values if v is not None)
    vae = VAEConfig(grid_size=args.grid_size, latent_dim=args.latent_dim, channels=channels)
    training = TrainConfig(epochs=args.epochs, batch_size=args.batch_size, learning_rate=args.learning_rate,
                           kld_weight=args.kld_weight, seed=args.seed,
                           validation_fraction=args.validation_fraction)
    shapes = load_shapes(args.data, grid_size=args.grid_size, labels=_labels(args.labels), progress=True)
    print(f"shape: {len(shapes.names)} shapes on a {args.grid_size}^3 grid of {shapes.voxel_mm:.3f} mm voxels; "
          f"training {args.epochs} epochs on {compute_device()}", flush=True)
    run = train(shapes, args.out, vae, training, source=str(args.data))
    print(f"wrote the run {run} (parameters.npz, config.json, latents.npz, loss.png)")
    _warn_if_undertrained(run)
    return 0


def _warn_if_undertrained(run: str | Path) -> None:
    """A warning on stderr when the run's held-out IoU is below the threshold (phantom.shape.training)."""
    import sys

    from phantom.shape.training import held_out_iou_warning, run_held_out_iou

    warning = held_out_iou_warning(*run_held_out_iou(run))
    if warning:
        print(f"phantom shape: warning: {run}: {warning}", file=sys.stderr, flush=True)


def run_average(args: argparse.Namespace) -> int:
    """Handler of ``phantom shape average``."""
    import json

    model = _run_model(args.run_dir)
    _warn_if_undertrained(args.run_dir)
    average = model.average()
    path = average.write(args.out)
    if args.json:
        print(json.dumps({"run": args.run_dir, "mesh": str(path), "volume_ml": round(average.volume_ml, 4),
                          "latent": [round(float(v), 6) for v in average.latent]}))
    else:
        print(f"average shape: {average.volume_ml:.2f} ml, written to {path}")
    return 0


def run_clusters(args: argparse.Namespace) -> int:
    """Handler of ``phantom shape clusters``."""
    import json

    from phantom.shape.figures import cluster_figures

    summary = cluster_figures(_run_model(args.run_dir), args.k, args.out, seed=args.seed)
    if args.json:
        print(json.dumps(summary))
        return 0
    for cluster in summary["clusters"]:
        print(f"cluster {cluster['cluster']}: {cluster['cases']} cases, {cluster['volume_ml']:.2f} ml "
              f"({cluster['mesh']})")
    for pair in summary["pairs"]:
        print(f"cluster {pair['a']} vs {pair['b']}: implicit distance {pair['min_mm']:+.2f} to "
              f"{pair['max_mm']:+.2f} mm, mean |d| {pair['mean_abs_mm']:.2f} mm ({pair['heatmap']})")
    return 0


def run_encode(args: argparse.Namespace) -> int:
    """Handler of ``phantom shape encode``."""
    import json

    latent = _run_model(args.run_dir).encode_file(args.input)
    values = [round(float(v), 6) for v in latent]
    if args.json:
        print(json.dumps({"input": args.input, "latent": values}))
    else:
        print(" ".join(f"{v:.6g}" for v in values))
    return 0


def run_compare(args: argparse.Namespace) -> int:
    """Handler of ``phantom shape compare``."""
    import json

    from phantom.shape.compare import compare_files

    result = compare_files(_run_model(args.run_dir), args.a, args.b)
    _warn_if_undertrained(args.run_dir)
    if args.json:
        print(json.dumps(result.to_json()))
    else:
        print(f"latent distance {result.latent_distance:.3f}; mean closest-point distance "
              f"{result.mean_distance_mm:.3f} mm after ICP (rotation {result.rotation_deg:.1f} deg); "
              f"volumes {result.volume_a_ml:.2f} and {result.volume_b_ml:.2f} ml")
    return 0


def run_report(args: argparse.Namespace) -> int:
    """Handler of ``phantom shape report``."""
    from phantom.shape.report import write_report

    report = write_report(_run_model(args.run_dir), args.out, k=args.k)
    versus = report["average_vs_model"]
    print(f"average {report['average']['volume_ml']:.2f} ml; against the model's rest shape "
          f"({versus['volume_a_ml']:.2f} ml): mean closest-point distance {versus['mean_distance_mm']:.2f} mm, "
          f"latent distance {versus['latent_distance']:.2f}; report in {args.out}/report.md")
    return 0
