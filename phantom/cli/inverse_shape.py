"""``phantom inverse --shape FILE``: the pressures that make the phantom look most like a given gland.

The answer (:mod:`phantom.model.shape_inverse`) printed as a table or one JSON object; with ``--out DIR`` also
``shape_inverse.json``, the residual map ``residual.png`` (the phantom's surface at the answer coloured by its
signed distance to the target: where the phantom cannot follow) and ``answer.stl`` (that surface, mm).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from phantom.model.shape_inverse import ShapeInverseResult


def _labels(text: str | None) -> list[int] | None:
    from phantom.cli.common import parse_numbers

    if not text:
        return None
    return [int(value) for value in parse_numbers(text, "--labels") if value is not None]


def refine_solves(args: argparse.Namespace) -> int:
    """``--refine-solves``: the full solves that refine the table's answer at most, the model's default when not
    given (None: given or not is told apart, so that it is refused without ``--shape``)."""
    from phantom import PhantomError
    from phantom.model.shape_inverse import REFINE_SOLVES

    if args.refine_solves is None:
        return REFINE_SOLVES
    if args.refine_solves < 0:
        raise PhantomError(f"--refine-solves must be 0 or more, got {args.refine_solves}")
    return int(args.refine_solves)


#: What ``--shape`` reads: said when a folder is given in its place.
SHAPE_FILE = "a NIfTI mask (.nii, .nii.gz) or a closed mesh file in mm (STL, PLY, OBJ, VTK)"


def run_shape_inverse(args: argparse.Namespace) -> int:
    """Handler of ``phantom inverse --shape``."""
    from phantom import PhantomError
    from phantom.cli.common import check_input_size
    from phantom.model import PhantomModel, load_scene
    from phantom.model.shape_file import read_target_surface
    from phantom.model.shape_inverse import ShapeInverse, surface_shapes

    if args.growth_ratio or args.max_growth_ml or args.fidelity:
        raise PhantomError("--growth-ratio, --max-growth-ml and --fidelity go with a volume target, not --shape")
    solves = refine_solves(args)
    check_input_size(args.shape, None, "--shape", give=SHAPE_FILE)
    target = read_target_surface(args.shape, _labels(args.labels))
    scene = load_scene(args.scene)
    model = PhantomModel.from_scene(scene, mesh_size_mm=args.size_mm)
    pressure_max_pa = None if args.pressure_max_kpa is None else args.pressure_max_kpa * 1e3

    def told(done: int, total: int) -> None:
        print(f"shape inverse: the table of shapes, {done}/{total} solves", file=sys.stderr, flush=True)

    inverse = ShapeInverse(model, surface_shapes(model, progress=told), pressure_max_pa)
    result = inverse.solve(target, solves, scale=args.scale,
                           progress=lambda message: print(message, file=sys.stderr, flush=True))
    report = result.to_json(list(scene.chamber_labels))
    if args.out:
        report["files"] = write_outputs(result, Path(args.out), report, Path(args.shape).name)
    if args.json:
        print(json.dumps(report))
    else:
        print(describe(result, list(scene.chamber_labels), report.get("files", {})))
    return 0


def write_outputs(result: ShapeInverseResult, folder: Path, report: dict[str, object], name: str) -> dict[str, str]:
    """The answer's files in ``folder``: the JSON report, the residual map and the surface at the answer."""
    import meshio

    from phantom import PhantomError
    from phantom.scan.heatmap import write_surface_heatmap

    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        raise PhantomError(f"cannot write into --out {folder}: {error.strerror or error}") from None
    files = {"report": str(folder / "shape_inverse.json"), "residual_map": str(folder / "residual.png"),
             "surface": str(folder / "answer.stl")}
    pressures = ", ".join(f"{value / 1e3:.2f}" for value in result.pressures_pa)
    write_surface_heatmap(result.surface_mm, result.triangles, result.residual_mm, files["residual_map"],
                          f"{name}: the phantom at {pressures} kPa, {result.distance_mm:.2f} mm from the target "
                          f"(at rest {result.rest_distance_mm:.2f} mm)",
                          "signed distance to the target (mm); -: target beyond")
    try:
        meshio.write(files["surface"], meshio.Mesh(result.surface_mm, [("triangle", result.triangles)]))
        Path(files["report"]).write_text(json.dumps({**report, "files": files}, indent=2) + "\n")
    except OSError as error:
        raise PhantomError(f"cannot write into --out {folder}: {error.strerror or error}") from None
    return files


def describe(result: ShapeInverseResult, labels: list[str], files: dict[str, str]) -> str:
    """The answer as people read it."""
    from phantom.model.mesh.surface import rotation_angle_deg

    lines = [f"{'chamber':<26} " + " ".join(f"{label:>11}" for label in labels),
             f"{'pressure (kPa)':<26} " + " ".join(f"{value / 1e3:11.3f}" for value in result.pressures_pa),
             f"{'chamber volume (ml)':<26} " + " ".join(f"{value:11.3f}" for value in result.chamber_volumes_ml),
             f"distance to the target: {result.distance_mm:.3f} mm at the answer, {result.rest_distance_mm:.3f} mm "
             "at rest (symmetric mean closest-point distance)",
             f"volumes: target {result.target_volume_ml:.2f} ml, phantom at rest {result.rest_volume_ml:.2f} ml, "
             f"at the answer {result.volume_ml:.2f} ml",
             "per region (mean distance, signed; -: the target reaches beyond the phantom):"]
    for name, error in result.regions.items():
        rest = result.rest_regions[name]
        lines.append(f"  {name:<6} {error.mean_mm:7.3f} mm ({error.signed_mm:+.3f}), at rest {rest.mean_mm:.3f} mm "
                     f"({rest.signed_mm:+.3f})")
    pose = result.pose
    lines.append(f"registration: rigid, turned {rotation_angle_deg(pose.rotation):.2f} deg"
                 + (f", scale {pose.scale:.4f} (fitted on request)" if pose.scale != 1.0 else ""))
    lines.append(f"from the table: {', '.join(f'{value / 1e3:.3f}' for value in result.table_pressures_pa)} kPa, "
                 f"{result.table_distance_mm:.3f} mm in {result.table_time_s:.2f} s ({result.table_cpu_s:.2f} s "
                 f"CPU); then {result.solves} full solve(s) in {result.refine_time_s:.1f} s: "
                 + (", ".join(f"{distance:.3f}" for _, distance in result.refinement) or "none") + " mm")
    lines.extend(f"note: {note}" for note in result.notes)
    lines.extend(f"{kind.replace('_', ' ')}: {path}" for kind, path in files.items())
    return "\n".join(lines)
