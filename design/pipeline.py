"""``phantom design``'s stages in order, each timed: surface, chambers, mesh and scene, cast, growth, report.

:func:`design` writes into ``out``: ``gland.msh`` and ``scene.toml`` (the model), ``gland.stl`` (the designed outer
surface), the cast's STLs, ``report.md`` with ``report.png`` and ``design.json`` (the same figures for programs).
"""

from __future__ import annotations

import json
import os
import tempfile
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np

from phantom import require_extra, written_atomically
from phantom.design.cast import make_cast, undercut_warnings
from phantom.design.chambers import place_chambers, surface_samples_mm
from phantom.design.errors import DesignError
from phantom.design.latent import latent_distance
from phantom.design.material import inherited_material
from phantom.design.meshing import check_mesh_options, mesh_design, write_scene
from phantom.design.result import Design, DesignOptions
from phantom.design.sizing import (
    GrowthTarget,
    Sizing,
    growth_target,
    size_chambers,
    target_reached,
)
from phantom.design.surface import Surface, read_gland
from phantom.model.arrays import FloatArray
from phantom.model.mesh.tetmesh import TetMesh, boundary_faces, enclosed_volume_m3, surface_components, write_mesh

#: ``phantom design``'s defaults (DesignOptions is frozen: one instance serves every call).
DEFAULT_OPTIONS = DesignOptions()


def design(source: str | Path, out: str | Path, options: DesignOptions = DEFAULT_OPTIONS,
           progress: Callable[[str], None] = print) -> Design:
    """Run every stage (see the module docstring); DesignError (or the shape analysis's ShapeError for a file it
    cannot read) on bad input, before anything is written."""
    out = Path(out)
    if options.min_wall_mm < 1.0:
        raise DesignError(f"--min-wall-mm {options.min_wall_mm:g} is thinner than a lost-wax cast makes (1 mm)")
    if not 1.0 <= options.stem_diameter_mm <= 8.0:
        raise DesignError(f"--stem-diameter-mm {options.stem_diameter_mm:g} is out of range: use 1 to 8 mm")
    if not options.chambers:
        raise DesignError("--chambers is empty: give one or more of base,left,right")
    # before the sizing's solves: a mesh option is refused in a second, not after a minute of them
    check_mesh_options(options.size_mm, options.element_order)
    if options.elements_per_wall not in (1, 2):
        raise DesignError(f"--elements-per-wall {options.elements_per_wall} is not 1 (a preview) or 2 (the design)")
    check_out_folder(out)
    times: dict[str, float] = {}
    started = time.perf_counter()

    def stage(name: str) -> None:
        nonlocal started
        now = time.perf_counter()
        times[name] = now - started
        progress(f"design: {name} done in {times[name]:.1f} s")
        started = now

    material = inherited_material(options.material_from, options.element_order)
    progress(f"design: reading {source}")
    gland = read_gland(source, options.volume_ml, options.labels, options.smoothing_iterations)
    target = growth_target(options.volume_ml, options.growth_target_ml, options.growth_target_kpa)
    stage("surface")
    latent = None
    if options.shape_run is not None:
        progress(f"design: encoding the source with the shape run {options.shape_run}")
        latent = latent_distance(source, options.shape_run)
        stage("latent")
    samples = surface_samples_mm(gland.surface)
    sizing = None
    if options.chamber_scale is None:
        progress(f"design: sizing the chambers to grow the gland to {target.volume_ml:.1f} ml at "
                 f"{target.pressure_kpa:g} kPa")
        chambers, sizing = size_chambers(gland.surface, samples, options.chambers, options.min_wall_mm, target,
                                         options.size_mm, options.fixation_radius_mm, progress, material)
    else:
        chambers = place_chambers(gland.surface, options.min_wall_mm, options.chamber_scale, samples,
                                  options.chambers)
    stage("chambers")
    out.mkdir(parents=True, exist_ok=True)
    mesh = mesh_design(gland.surface, chambers.chambers, options.size_mm, material.element_order,
                       options.fixation_radius_mm, samples, options.elements_per_wall)
    write_mesh(mesh, out / "gland.msh")
    write_scene(out / "gland.msh", out / "scene.toml", material, chambers.chambers)
    _write_stl(gland.surface, out / "gland.stl")
    stage("mesh")
    progress("design: the cast (mould halves, cores)")
    cast = make_cast(gland.surface, chambers.chambers, options.min_wall_mm, options.stem_diameter_mm, out)
    stage("cast")
    # the curve, and the target's pressure once more when the sizing needs it confirmed and the curve lacks it
    pressures = list(options.growth_pressures_kpa)
    if sizing is not None and target.pressure_kpa not in pressures:
        pressures.append(target.pressure_kpa)
    rest_ml, volumes_ml = _growth(out / "scene.toml", pressures, progress)
    stage("growth")
    target_reached_ml = None
    if target.pressure_kpa in pressures:
        # the model's growth on the designed gland's volume (the mesh's own rest volume is its discretised surface's)
        target_reached_ml = gland.surface.volume_ml() + volumes_ml[pressures.index(target.pressure_kpa)] - rest_ml
    warnings = growth_warnings(out / "scene.toml", gland.surface.volume_ml(), target, target_reached_ml, sizing,
                               options.min_wall_mm)
    warnings += undercut_warnings(cast.split, cast.coronal_undercut_mm2)
    result = Design(out, gland.surface.volume_ml(), gland.source_volume_ml, gland.smoothing_change_pct,
                    gland.scale, [chamber.label for chamber in chambers.chambers],
                    [chamber.volume_ml for chamber in chambers.chambers], chambers.scales,
                    chambers.walls_mm, mesh.n_nodes, len(mesh.tets), rest_ml,
                    outer_surface_distance_mm(mesh, gland.reference), cast, list(options.growth_pressures_kpa),
                    volumes_ml[:len(options.growth_pressures_kpa)], target, target_reached_ml, sizing, latent,
                    gland.notes,
                    warnings, times, material, options.size_mm, options.elements_per_wall)
    stage("checks")
    from phantom.design.report import write_report

    write_report(result, gland, chambers)
    stage("report")
    with written_atomically(out / "design.json", DesignError) as temporary:
        temporary.write_text(json.dumps(design_summary(result), indent=1) + "\n")
    return result


def check_out_folder(out: Path) -> None:
    """Refuse ``out`` (DesignError) when it is a file or no folder can be made there: before the slow stages, not
    after a minute of the sizing's solves. Nothing is left: a bad input refused later leaves no folder behind, so
    the check makes a folder in the nearest one that exists and removes it at once."""
    try:
        if out.exists() and not out.is_dir():
            raise DesignError(f"--out {out} is a file: give a folder")
        held = sorted(path.name for path in out.iterdir()) if out.is_dir() else []
        if held:  # a design over another would leave the other's files beside it (a core of a chamber it has not)
            raise DesignError(f"--out {out} holds files already ({', '.join(held[:3])}"
                              f"{', ...' if len(held) > 3 else ''}): give a new or empty folder")
        nearest = next(folder for folder in (out, *out.parents) if folder.exists())
        os.rmdir(tempfile.mkdtemp(prefix=".design-", dir=nearest))
    except OSError as problem:
        raise DesignError(f"--out {out} cannot be made a folder ({problem.strerror or problem}): give a folder you "
                          "can write") from None


def _write_stl(surface: Surface, path: Path) -> None:
    with require_extra("design"):
        import trimesh

    with written_atomically(path, DesignError) as temporary:
        trimesh.Trimesh(surface.vertices_mm, surface.triangles, process=False).export(str(temporary), file_type="stl")


def _growth(scene_path: Path, pressures_kpa: Sequence[float],
            progress: Callable[[str], None]) -> tuple[float, list[float]]:
    """The designed model's rest gland volume and its volume at each pressure (all chambers alike), ml."""
    from phantom.model.fem.model import PhantomModel
    from phantom.model.scene import HYPERELASTIC_MODELS, load_scene

    model = PhantomModel.from_scene(load_scene(scene_path))
    volumes: dict[float, float] = {}
    previous = None
    # upward, each solve started from the one below (a hyperelastic solve from rest to 3 kPa follows the whole path)
    for pressure in sorted(set(pressures_kpa)):
        progress(f"design: growth at {pressure:g} kPa ({len(volumes) + 1}/{len(set(pressures_kpa))})")
        warm = previous is not None and model.formulation in HYPERELASTIC_MODELS  # small strain: from rest
        previous = model.equilibrium([pressure * 1e3] * model.n_chambers,
                                     initial_positions_m=previous.positions_m if warm and previous else None)
        volumes[pressure] = float(previous.gland_volume_m3) * 1e6
    return float(model.rest_gland_volume_m3) * 1e6, [volumes[pressure] for pressure in pressures_kpa]


def growth_warnings(scene_path: Path, gland_volume_ml: float, target: GrowthTarget, reached_ml: float | None,
                    sizing: Sizing | None, min_wall_mm: float) -> list[str]:
    """What a user must know about the growth target: nothing when the designed model reaches it (or was not solved
    at its pressure), else how far it falls short and why (the walls' limit, the coarse search's error, or chambers
    fixed by --chamber-scale)."""
    from phantom.model.scene import load_scene

    if reached_ml is None or target_reached(gland_volume_ml, target, reached_ml):
        return []
    material = load_scene(scene_path).material
    short_ml = target.volume_ml - reached_ml
    short = (f"the growth target ({target.volume_ml:.1f} ml at {target.pressure_kpa:g} kPa) is not reached: the "
             f"designed model grows the gland to {reached_ml:.2f} ml at {target.pressure_kpa:g} kPa, {short_ml:.2f} ml "
             f"({100 * short_ml / (target.volume_ml - gland_volume_ml):.0f} % of the growth wanted) short, with the "
             f"scene's material ({material.model}, E {material.youngs_modulus_pa / 1e3:g} kPa; calibrate it to the "
             f"cast's measurements)")
    if sizing is None:
        return [f"{short}; the chambers are fixed by --chamber-scale (leave it out to size them to the target)"]
    if not sizing.reached:
        return [f"{short}: the chambers are the largest the {min_wall_mm:g} mm walls allow; thinner walls "
                f"(--min-wall-mm), a softer silicone or a lower target reach it"]
    return [f"{short}: the coarse search put the target at {sizing.scale:.3f} of the template "
            f"({sizing.coarse_volume_ml:.2f} ml there); the designed mesh grows less"]


def outer_surface_distance_mm(mesh: TetMesh, reference: Surface) -> float:
    """The mean distance (mm) between the mesh's outer surface and ``reference``, both ways, each point to the
    other surface's samples 0.25 mm apart."""
    from scipy.spatial import cKDTree
    with require_extra("design"):
        from trimesh import remesh

    faces, _ = boundary_faces(mesh.tets)
    faces = faces[:, :3]
    labels = surface_components(faces)
    nodes_mm = mesh.nodes_m * 1e3
    enclosed = [enclosed_volume_m3(mesh.nodes_m, faces[labels == k]) for k in range(labels.max() + 1)]
    outer = Surface(nodes_mm, faces[labels == int(np.argmax(enclosed))]).compacted()

    def dense(surface: Surface) -> FloatArray:
        vertices, _ = remesh.subdivide_to_size(surface.vertices_mm, surface.triangles, max_edge=0.25, max_iter=30)
        return np.asarray(vertices, float)

    designed, source = dense(outer), dense(reference)
    there = np.asarray(cKDTree(source).query(designed)[0])
    back = np.asarray(cKDTree(designed).query(source)[0])
    return float(0.5 * (there.mean() + back.mean()))


def design_summary(result: Design) -> dict[str, Any]:
    """The design's figures as one JSON-able dict."""
    name, thinnest = result.thinnest_wall
    return {
        "out": str(result.out),
        "gland_volume_ml": result.gland_volume_ml,
        "source_volume_ml": result.source_volume_ml,
        "smoothing_change_pct": result.smoothing_change_pct,
        "scale": result.scale,
        "chambers": [{"label": label, "volume_ml": volume, "scale_of_template": scale}
                     for label, volume, scale in zip(result.chamber_labels, result.chamber_volumes_ml,
                                                     result.chamber_scales, strict=True)],
        "walls_mm": result.walls_mm,
        "thinnest_wall": {"where": name, "mm": thinnest},
        "mesh": {"nodes": result.mesh_nodes, "tetrahedra": result.mesh_tets, "size_mm": result.mesh_size_mm,
                 "elements_per_wall": result.elements_per_wall},
        "rest_volume_ml": result.rest_volume_ml,
        "outer_surface_mean_distance_mm": result.surface_distance_mm,
        "growth": {"pressures_kpa": result.growth_kpa, "gland_volumes_ml": result.growth_volumes_ml},
        "cast": {"silicone_ml": result.cast.silicone_ml,
                 "split_plane": {"normal": list(result.cast.split.normal), "offset_mm": result.cast.split.offset_mm,
                                 "tilt_from_coronal_degrees": result.cast.split.tilt_degrees()},
                 "undercut_mm2": result.cast.split.undercut_mm2,
                 "coronal_undercut_mm2": result.cast.coronal_undercut_mm2,
                 "stem_clearances_mm": result.cast.stem_clearances_mm,
                 "parts": [{**asdict(part), "path": str(part.path), "printable": part.printable}
                           for part in result.cast.parts]},
        "growth_target": {"volume_ml": result.target.volume_ml, "pressure_kpa": result.target.pressure_kpa,
                          "designed_volume_ml": result.target_reached_ml,
                          "reached": target_reached(result.gland_volume_ml, result.target, result.target_reached_ml),
                          "sizing": None if result.sizing is None else {
                              "scale_of_template": result.sizing.scale, "coarse_reached": result.sizing.reached,
                              "at_walls_limit": result.sizing.at_walls_limit,
                              "coarse_size_mm": result.sizing.coarse_size_mm,
                              "steps": [{"scale_of_template": scale, "coarse_volume_ml": volume}
                                        for scale, volume in result.sizing.steps]}},
        "latent": None if result.latent is None else {
            "shape_run": result.latent.run, "distance_to_average": result.latent.distance,
            "population_spread": result.latent.spread, "in_spreads": result.latent.in_spreads,
            "percentile": result.latent.percentile, "cases": result.latent.cases},
        "material": None if result.material is None else {
            "from": result.material.source, "table": result.material.table,
            "element_order": result.material.element_order, "caveat": result.material.caveat},
        "notes": result.notes,
        "warnings": result.warnings,
        "stage_times_s": result.stage_times_s,
    }
