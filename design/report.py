"""The design's report: ``report.md`` (volumes, walls, the growth curve, the cast and its silicone, each stage's
time) and ``report.png`` (the gland's coronal and axial sections with the chambers and the stems' plane, and the
predicted growth curve)."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from phantom import require_extra, written_atomically
from phantom.design.chambers import CHAMBER_LABELS, ChamberDesign
from phantom.design.errors import DesignError
from phantom.design.surface import Gland

if TYPE_CHECKING:
    from phantom.design.pipeline import Design


def write_report(result: Design, gland: Gland, chambers: ChamberDesign) -> None:
    """Write ``report.md`` and ``report.png`` into the design's folder."""
    _write_figure(result, gland, chambers)
    name, thinnest = result.thinnest_wall
    lines = [
        "# Phantom design",
        "",
        "![sections and growth](report.png)",
        "",
        f"- gland: {result.gland_volume_ml:.2f} ml (the source {result.source_volume_ml:.2f} ml, smoothing changed "
        f"it by {result.smoothing_change_pct:+.2f} %, scaled by {result.scale:.4f}); the model's rest volume "
        f"{result.rest_volume_ml:.2f} ml",
        f"- the model's outer surface lies {result.surface_distance_mm:.3f} mm (mean, both ways) from the source's "
        f"surface scaled alike",
        f"- mesh: {result.mesh_nodes} nodes, {result.mesh_tets} tetrahedra (gland.msh, scene.toml)",
        f"- thinnest wall: {thinnest:.2f} mm ({name})",
        "",
        "| chamber | volume ml | scale of the template |",
        "|---|---|---|",
    ]
    lines += [f"| {label} | {volume:.3f} | {scale:.3f} |" for label, volume, scale in
              zip(CHAMBER_LABELS, result.chamber_volumes_ml, result.chamber_scales, strict=True)]
    lines += ["", "| wall | mm |", "|---|---|"] + [f"| {wall} | {value:.2f} |" for wall, value in
                                                   result.walls_mm.items()]
    if result.growth_kpa:
        lines += ["", "Predicted growth, all chambers at one pressure (the scene's material):", "",
                  "| pressure kPa | gland ml |", "|---|---|", f"| 0 | {result.rest_volume_ml:.3f} |"]
        lines += [f"| {p:g} | {v:.3f} |" for p, v in zip(result.growth_kpa, result.growth_volumes_ml, strict=True)]
    cast = result.cast
    lines += ["", f"The cast: mix {cast.silicone_ml:.1f} ml of silicone (the gland less the cores) plus what the "
              f"spout and vents hold; split on y = {cast.split_y_mm:.2f} mm, undercut across it "
              f"{cast.undercut_mm2:.1f} mm^2.", "", "| part | ml | bodies | closed | normals consistent |",
              "|---|---|---|---|---|"]
    lines += [f"| {part.path.name} | {part.volume_ml:.2f} | {part.bodies} | {part.watertight} | "
              f"{part.winding_consistent} |" for part in cast.parts]
    lines += ["", "Stem clearances to the other chambers (mm): " + ", ".join(
        f"{name} {value:.2f}" for name, value in cast.stem_clearances_mm.items())]
    if result.notes:
        lines += ["", "Notes:", ""] + [f"- {note}" for note in result.notes]
    lines += ["", "Stages (s): " + ", ".join(f"{stage} {seconds:.1f}" for stage, seconds in
                                             result.stage_times_s.items())]
    with written_atomically(result.out / "report.md", DesignError) as temporary:
        temporary.write_text("\n".join(lines) + "\n")


def _write_figure(result: Design, gland: Gland, chambers: ChamberDesign) -> None:
    with require_extra("design"):
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
        import trimesh

    mesh = trimesh.Trimesh(gland.surface.vertices_mm, gland.surface.triangles, process=False)
    figure, axes = plt.subplots(1, 3, figsize=(13, 4.2))
    angle = np.linspace(0, 2 * np.pi, 200)
    views = [("coronal section y = {:.1f} mm", 1, (0, 2), "x (left) mm", "z (base) mm"),
             ("axial section z = {:.1f} mm", 2, (0, 1), "x (left) mm", "y (anterior) mm")]
    heights = [result.cast.split_y_mm, chambers.chambers[1].centre_mm[2]]
    for axis, (title, normal_axis, (u, v), u_label, v_label), height in zip(axes[:2], views, heights, strict=True):
        normal = np.zeros(3)
        normal[normal_axis] = 1.0
        origin = np.zeros(3)
        origin[normal_axis] = height
        section = mesh.section(plane_origin=origin, plane_normal=normal)
        if section is not None:
            for polyline in section.discrete:
                axis.plot(polyline[:, u], polyline[:, v], "k-", lw=1.2)
        for index, (label, chamber) in enumerate(zip(CHAMBER_LABELS, chambers.chambers, strict=True)):
            centre, semi = np.asarray(chamber.centre_mm), np.asarray(chamber.semi_axes_mm)
            across = (height - centre[normal_axis]) / semi[normal_axis]
            if abs(across) < 1:
                shrink = np.sqrt(1 - across**2)
                axis.plot(centre[u] + shrink * semi[u] * np.cos(angle), centre[v] + shrink * semi[v] * np.sin(angle),
                          lw=1.2, label=label, color=f"C{index}")
        axis.set_aspect("equal")
        axis.set_title(title.format(height))
        axis.set_xlabel(u_label)
        axis.set_ylabel(v_label)
    axes[0].legend(fontsize=8, loc="lower right")
    if result.growth_kpa:
        axes[2].plot([0.0] + result.growth_kpa, [result.rest_volume_ml] + result.growth_volumes_ml, "o-")
    axes[2].set_xlabel("pressure in every chamber, kPa")
    axes[2].set_ylabel("gland volume, ml")
    axes[2].set_title("predicted growth")
    axes[2].grid(alpha=0.3)
    figure.tight_layout()
    with written_atomically(result.out / "report.png", DesignError) as temporary:
        figure.savefig(temporary, format="png", dpi=110)
    plt.close(figure)
