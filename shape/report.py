"""The report of a trained run: the counterparts of the paper's shape figures (its section IV-A).

``report.md`` and ``report.json`` in the output folder, with:

- the training (cases, grid, voxel size, epochs, final loss, held-out reconstruction IoU) and its loss curves;
- the average shape (``average.ply``) and its volume (the paper: 27.3 ml);
- the average against the phantom model's rest shape (the built-in body, 26.3 ml: the paper's patient-derived
  model): mean closest-point distance after ICP (the paper: 1.00 mm) and latent distance (0.64), and the
  implicit distance of the rest shape to the aligned average as a heatmap (``average_vs_model.png``, Fig. 5);
- k-means clusters, their decoded centres and pairwise heatmaps (``cluster_<i>_vs_<j>.png``, Fig. 6).
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from typing import Any

from phantom.model.mesh.prostate import builtin_prostate
from phantom.model.mesh.surface import TriangleMesh, model_surface
from phantom.model.mesh.tetmesh import prepare_surfaces
from phantom.shape.analysis import ShapeModel
from phantom.shape.compare import compare_shapes, phantom_mesh
from phantom.shape.figures import cluster_figures, implicit_distance_mm, write_heatmap

#: The paper's figures (its section IV-A), shown beside this run's.
PAPER = {"average_volume_ml": 27.3, "model_volume_ml": 26.3, "mean_distance_mm": 1.00, "latent_distance": 0.64}


def model_rest_surface() -> TriangleMesh:
    """The outer surface of the phantom model's built-in body at rest (mm, the phantom's frame)."""
    mesh = builtin_prostate()
    chambers = sorted(name for name in mesh.surface_groups if name.startswith("chamber"))
    outer = prepare_surfaces(mesh, chambers, None, "built-in prostate").outer_triangles
    return model_surface(mesh.nodes_m, outer)


def training_summary(model: ShapeModel) -> dict[str, Any]:
    """What the run trained on and how it ended (from config.json and history.json)."""
    history = json.loads((model.run / "history.json").read_text())
    data = model.config["data"]
    last = history[-1]
    return {"cases": len(data["names"]), "held_out": len(data["held_out"]), "grid_size": model.grid_size,
            "voxel_mm": round(model.voxel_mm, 4), "epochs": model.config["epochs_done"],
            "seconds": model.config["seconds"], "final_loss": round(last["loss"], 2),
            "held_out_iou": None if last["validation_iou"] is None else round(last["validation_iou"], 4),
            "source": data["source"]}


def write_report(model: ShapeModel, out: str | Path, k: int = 3, seed: int = 0) -> dict[str, Any]:
    """Write the report (see the module docstring) under ``out``; returns what report.json holds."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    average = model.average()
    average_path = average.write(out / "average.ply")
    rest = model_rest_surface()
    comparison = compare_shapes(model, phantom_mesh(rest),
                                phantom_mesh(TriangleMesh(average.vertices_mm, average.triangles)),
                                ("the model's rest shape", "the average"))
    shown = comparison.surface_a.mirrored_x()
    distance = implicit_distance_mm(comparison.surface_a.vertices_mm, comparison.aligned_b.vertices_mm,
                                    comparison.aligned_b.triangles)
    heatmap = write_heatmap(shown.vertices_mm, shown.triangles, distance, out / "average_vs_model.png",
                            f"the model's rest shape ({comparison.volume_a_ml:.1f} ml) against the average "
                            f"({comparison.volume_b_ml:.1f} ml): mean closest-point distance "
                            f"{comparison.mean_distance_mm:.2f} mm, latent distance {comparison.latent_distance:.2f}",
                            "implicit distance to the average (mm, + outside it)")
    clusters = cluster_figures(model, k, out, seed=seed)
    if (model.run / "loss.png").is_file():
        shutil.copyfile(model.run / "loss.png", out / "loss.png")
    report = {"run": str(model.run), "training": training_summary(model),
              "average": {"volume_ml": round(average.volume_ml, 3), "mesh": str(average_path)},
              "average_vs_model": {"model": "builtin (rest)", **comparison.to_json(), "heatmap": str(heatmap)},
              "clusters": clusters, "paper": PAPER}
    (out / "report.json").write_text(json.dumps(report, indent=1))
    (out / "report.md").write_text(markdown(report))
    return report


def markdown(report: dict[str, Any]) -> str:
    """The report as Markdown, beside the paper's figures."""
    training, average, versus = report["training"], report["average"], report["average_vs_model"]
    lines = [
        "# Shape analysis report", "",
        f"Run `{report['run']}`: {training['cases']} shapes ({training['held_out']} held out) from "
        f"`{training['source']}`, a {training['grid_size']}^3 grid of {training['voxel_mm']} mm voxels, "
        f"{training['epochs']} epochs in {training['seconds']:.0f} s; final loss {training['final_loss']}, "
        f"held-out reconstruction IoU {training['held_out_iou']}.", "",
        "![loss](loss.png)", "",
        "| figure | this run | the paper |", "| --- | --- | --- |",
        f"| volume of the average shape | {average['volume_ml']:.2f} ml | {PAPER['average_volume_ml']} ml |",
        f"| volume of the phantom model's rest shape | {versus['volume_a_ml']:.2f} ml | "
        f"{PAPER['model_volume_ml']} ml |",
        f"| mean closest-point distance, average to model, after ICP | {versus['mean_distance_mm']:.2f} mm | "
        f"{PAPER['mean_distance_mm']:.2f} mm |",
        f"| latent distance, average to model | {versus['latent_distance']:.2f} | {PAPER['latent_distance']} |",
        "", "Latent distances depend on the run (the network's latent scale): compare them within a run.", "",
        "## The average against the model's rest shape (Fig. 5)", "", "![average vs model](average_vs_model.png)",
        "", "## Clusters (Fig. 6)", "", "| cluster | cases | volume (ml) |", "| --- | --- | --- |"]
    lines += [f"| {c['cluster']} | {c['cases']} | {c['volume_ml']:.2f} |" for c in report["clusters"]["clusters"]]
    lines += ["", "| pair | latent distance | implicit distance (mm) | mean abs (mm) |", "| --- | --- | --- | --- |"]
    lines += [f"| {p['a']} vs {p['b']} | {p['latent_distance']:.2f} | {p['min_mm']:+.2f} to {p['max_mm']:+.2f} | "
              f"{p['mean_abs_mm']:.2f} |" for p in report["clusters"]["pairs"]]
    lines += [""] + [f"![cluster {p['a']} vs {p['b']}]({Path(p['heatmap']).name})"
                     for p in report["clusters"]["pairs"]]
    return "\n".join(lines) + "\n"
