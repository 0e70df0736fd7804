"""The design's report: ``report.md`` (volumes, walls, the growth curve, the cast and its silicone, each stage's
time) and ``report.png`` (the gland's coronal and axial sections with the chambers and the stems' plane, and the
predicted growth curve)."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from phantom import require_extra, written_atomically
from phantom.design.chambers import BASE, ChamberDesign
from phantom.design.errors import DesignError
from phantom.design.sizing import GROWTH_TOLERANCE, target_reached
from phantom.design.surface import Gland

if TYPE_CHECKING:
    from phantom.design.result import Design


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
        f"- mesh: {result.mesh_nodes} nodes, {result.mesh_tets} tetrahedra (gland.msh, scene.toml), "
        f"{result.mesh_size_mm:g} mm, {result.elements_per_wall} through the thinnest wall"
        + (" (a preview: design with 2 before casting)" if result.elements_per_wall == 1 else ""),
        f"- thinnest wall: {thinnest:.2f} mm ({name})",
        *latent_lines(result),
        *([] if result.material is None else [f"- material: {result.material.caveat}"]),
        "",
        "| chamber | volume ml | scale of the template |",
        "|---|---|---|",
    ]
    lines += [f"| {label} | {volume:.3f} | {scale:.3f} |" for label, volume, scale in
              zip(result.chamber_labels, result.chamber_volumes_ml, result.chamber_scales, strict=True)]
    lines += ["", "| wall | mm |", "|---|---|"] + [f"| {wall} | {value:.2f} |" for wall, value in
                                                   result.walls_mm.items()]
    if result.growth_kpa:
        lines += ["", "Predicted growth, all chambers at one pressure (the scene's material):", "",
                  "| pressure kPa | gland ml |", "|---|---|", f"| 0 | {result.rest_volume_ml:.3f} |"]
        lines += [f"| {p:g} | {v:.3f} |" for p, v in zip(result.growth_kpa, result.growth_volumes_ml, strict=True)]
    lines += ["", *growth_target_lines(result)]
    cast = result.cast
    lines += ["", f"The cast: mix {cast.silicone_ml:.1f} ml of silicone (the gland less the cores) plus what the "
              f"spout and vents hold. The mould splits on the plane n . x = {cast.split.offset_mm:.2f} mm, n = "
              f"({', '.join(f'{value:.3f}' for value in cast.split.normal)}), {cast.split.tilt_degrees():.1f} "
              f"degrees from coronal, the least undercut of the planes searched: {cast.split.undercut_mm2:.1f} mm^2 "
              f"(the coronal plane through the chambers' centres: {cast.coronal_undercut_mm2:.1f} mm^2).", "",
              "| part | ml | bodies | closed | normals consistent |",
              "|---|---|---|---|---|"]
    lines += [f"| {part.path.name} | {part.volume_ml:.2f} | {part.bodies} | {part.watertight} | "
              f"{part.winding_consistent} |" for part in cast.parts]
    lines += ["", "Stem clearances to the other chambers (mm): " + ", ".join(
        f"{name} {value:.2f}" for name, value in cast.stem_clearances_mm.items())]
    if result.notes or result.warnings:
        lines += ["", "Notes:", ""] + [f"- {note}" for note in result.warnings + result.notes]
    lines += ["", "Stages (s): " + ", ".join(f"{stage} {seconds:.1f}" for stage, seconds in
                                             result.stage_times_s.items())]
    with written_atomically(result.out / "report.md", DesignError) as temporary:
        temporary.write_text("\n".join(lines) + "\n")


def latent_lines(result: Design) -> list[str]:
    """The source's latent distance to the shape run's average, when a run was given."""
    latent = result.latent
    if latent is None:
        return []
    return [f"- latent distance to the population's average (shape run {latent.run}): {latent.distance:.3f}, "
            f"{latent.in_spreads:.2f} times the population's spread (the root-mean-square distance of its "
            f"{latent.cases} cases), at the {latent.percentile:.0f}th percentile of their distances"]


def growth_target_lines(result: Design) -> list[str]:
    """The growth target, whether the designed model reaches it, and the sizing search's steps."""
    target = result.target
    wanted = f"Growth target: {target.volume_ml:.2f} ml at {target.pressure_kpa:g} kPa in every chamber"
    if result.target_reached_ml is None:
        lines = [f"{wanted}; not solved (the chambers' scale given, the growth curve without that pressure)."]
    else:
        reached = (f"reaches it, to {GROWTH_TOLERANCE:.0%} of the growth"
                   if target_reached(result.gland_volume_ml, target, result.target_reached_ml) else "falls short")
        lines = [f"{wanted}; the designed model grows the gland to {result.target_reached_ml:.2f} ml there "
                 f"({reached})."]
    sizing = result.sizing
    if sizing is None:
        return lines + ["The chambers' scale was given (--chamber-scale), not searched."]
    limit = " (the largest the walls allow)" if sizing.at_walls_limit else ""
    lines += ["", f"Sizing: the chambers at {sizing.scale:.3f} of the template{limit}, searched (the largest "
              f"first, then secant steps in log-log) on a coarse {sizing.coarse_size_mm:g} mm mesh with small-strain "
              f"solves:", "", "| scale of the template | gland ml at the target pressure (the coarse model's growth) |",
              "|---|---|"]
    return lines + [f"| {scale:.3f} | {volume:.3f} |" for scale, volume in sizing.steps]


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
    lobes = [chamber for chamber in chambers.chambers if chamber.kind != BASE] or chambers.chambers
    centres = np.array([chamber.centre_mm for chamber in chambers.chambers])
    heights = [float(centres[:, 1].mean()), lobes[0].centre_mm[2]]
    for axis, (title, normal_axis, (u, v), u_label, v_label), height in zip(axes[:2], views, heights, strict=True):
        normal = np.zeros(3)
        normal[normal_axis] = 1.0
        origin = np.zeros(3)
        origin[normal_axis] = height
        section = mesh.section(plane_origin=origin, plane_normal=normal)
        if section is not None:
            for polyline in section.discrete:
                axis.plot(polyline[:, u], polyline[:, v], "k-", lw=1.2)
        for index, chamber in enumerate(chambers.chambers):
            label = chamber.label
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
    # the mould's split plane where it crosses the axial section: n_x x + n_y y = offset - n_z z
    n_x, n_y, n_z = result.cast.split.normal
    x = np.array(axes[1].get_xlim())
    axes[1].plot(x, (result.cast.split.offset_mm - n_z * heights[1] - n_x * x) / n_y, "k--", lw=0.8,
                 label="mould split")
    axes[0].legend(fontsize=8, loc="lower right")
    axes[1].legend(fontsize=8, loc="lower right")
    if result.target_reached_ml is not None:
        axes[2].plot([result.target.pressure_kpa], [result.rest_volume_ml + result.target_reached_ml
                                                    - result.gland_volume_ml], "ko", label="designed, at the target")
    if result.growth_kpa:
        axes[2].plot([0.0] + result.growth_kpa, [result.rest_volume_ml] + result.growth_volumes_ml, "o-",
                     label="designed model")
    # the target's growth on the model's own rest volume, as the curve is
    axes[2].plot([result.target.pressure_kpa], [result.rest_volume_ml + result.target.volume_ml
                                                - result.gland_volume_ml], "r*", markersize=10, label="target growth")
    axes[2].legend(fontsize=8)
    axes[2].set_xlabel("pressure in every chamber, kPa")
    axes[2].set_ylabel("gland volume, ml")
    axes[2].set_title("predicted growth")
    axes[2].grid(alpha=0.3)
    figure.tight_layout()
    with written_atomically(result.out / "report.png", DesignError) as temporary:
        figure.savefig(temporary, format="png", dpi=110)
    plt.close(figure)
