"""``phantom design``'s stages in order, each timed: surface, chambers, mesh and scene, cast, growth, report.

:func:`design` writes into ``out``: ``gland.msh`` and ``scene.toml`` (the model), ``gland.stl`` (the designed outer
surface), the cast's STLs, ``report.md`` with ``report.png`` and ``design.json`` (the same figures for programs).
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from phantom import require_extra, written_atomically
from phantom.design.cast import Cast, make_cast
from phantom.design.chambers import CHAMBER_LABELS, place_chambers, surface_samples_mm
from phantom.design.errors import DesignError
from phantom.design.meshing import mesh_design, write_scene
from phantom.design.surface import Surface, read_gland
from phantom.model.arrays import FloatArray
from phantom.model.mesh.tetmesh import TetMesh, boundary_faces, enclosed_volume_m3, surface_components, write_mesh

#: The paper's targets: the average gland's volume (ml) and the growth its phantom reaches (to 45 ml) within 3 kPa.
PAPER_VOLUME_ML = 26.3
PAPER_GROWN_VOLUME_ML = 45.0
PAPER_PRESSURE_KPA = 3.0
#: The pressures (kPa, all three chambers alike) of the predicted growth curve.
GROWTH_PRESSURES_KPA = (0.5, 1.0, 1.5, 2.0, 2.5, 3.0)


@dataclass(frozen=True)
class DesignOptions:
    """What ``phantom design`` is asked for (its options; see its --help)."""

    volume_ml: float = PAPER_VOLUME_ML
    min_wall_mm: float = 2.0
    chamber_scale: float = 1.0
    size_mm: float = 2.5
    element_order: int = 1
    fixation_radius_mm: float = 6.0
    stem_diameter_mm: float = 3.0
    labels: tuple[int, ...] | None = None
    smoothing_iterations: int | None = None
    growth_pressures_kpa: tuple[float, ...] = GROWTH_PRESSURES_KPA


@dataclass
class Design:
    """What was designed: the figures of the report, the stages' times (s) and the files written."""

    out: Path
    gland_volume_ml: float
    source_volume_ml: float
    smoothing_change_pct: float
    scale: float
    chamber_volumes_ml: list[float]
    chamber_scales: list[float]
    walls_mm: dict[str, float]
    mesh_nodes: int
    mesh_tets: int
    rest_volume_ml: float
    surface_distance_mm: float
    cast: Cast
    growth_kpa: list[float]
    growth_volumes_ml: list[float]
    notes: list[str]
    stage_times_s: dict[str, float] = field(default_factory=dict)

    @property
    def thinnest_wall(self) -> tuple[str, float]:
        name = min(self.walls_mm, key=lambda key: self.walls_mm[key])
        return name, self.walls_mm[name]


def design(source: str | Path, out: str | Path, options: DesignOptions = DesignOptions(),
           progress: Callable[[str], None] = print) -> Design:
    """Run every stage (see the module docstring); DesignError (or the shape analysis's ShapeError for a file it
    cannot read) on bad input, before anything is written."""
    out = Path(out)
    if options.min_wall_mm < 1.0:
        raise DesignError(f"--min-wall-mm {options.min_wall_mm:g} is thinner than a lost-wax cast makes (1 mm)")
    if not 1.0 <= options.stem_diameter_mm <= 8.0:
        raise DesignError(f"--stem-diameter-mm {options.stem_diameter_mm:g} is out of range: use 1 to 8 mm")
    times: dict[str, float] = {}
    started = time.perf_counter()

    def stage(name: str) -> None:
        nonlocal started
        now = time.perf_counter()
        times[name] = now - started
        progress(f"design: {name} done in {times[name]:.1f} s")
        started = now

    progress(f"design: reading {source}")
    gland = read_gland(source, options.volume_ml, options.labels, options.smoothing_iterations)
    stage("surface")
    samples = surface_samples_mm(gland.surface)
    chambers = place_chambers(gland.surface, options.min_wall_mm, options.chamber_scale, samples)
    stage("chambers")
    out.mkdir(parents=True, exist_ok=True)
    mesh = mesh_design(gland.surface, chambers.chambers, options.size_mm, options.element_order,
                       options.fixation_radius_mm, samples)
    write_mesh(mesh, out / "gland.msh")
    write_scene(out / "gland.msh", out / "scene.toml", options.element_order)
    _write_stl(gland.surface, out / "gland.stl")
    stage("mesh")
    progress("design: the cast (mould halves, cores)")
    cast = make_cast(gland.surface, chambers.chambers, options.min_wall_mm, options.stem_diameter_mm, out)
    stage("cast")
    rest_ml, volumes_ml = _growth(out / "scene.toml", options.growth_pressures_kpa, progress)
    stage("growth")
    result = Design(out, gland.surface.volume_ml(), gland.source_volume_ml, gland.smoothing_change_pct,
                    gland.scale, [chamber.volume_ml for chamber in chambers.chambers], chambers.scales,
                    chambers.walls_mm, mesh.n_nodes, len(mesh.tets), rest_ml,
                    outer_surface_distance_mm(mesh, gland.reference), cast, list(options.growth_pressures_kpa),
                    volumes_ml, gland.notes + _growth_notes(out / "scene.toml", rest_ml, options.growth_pressures_kpa,
                                                            volumes_ml),
                    times)
    stage("checks")
    from phantom.design.report import write_report

    write_report(result, gland, chambers)
    stage("report")
    with written_atomically(out / "design.json", DesignError) as temporary:
        temporary.write_text(json.dumps(design_summary(result), indent=1) + "\n")
    return result


def _write_stl(surface: Surface, path: Path) -> None:
    with require_extra("design"):
        import trimesh

    with written_atomically(path, DesignError) as temporary:
        trimesh.Trimesh(surface.vertices_mm, surface.triangles, process=False).export(str(temporary), file_type="stl")


def _growth(scene_path: Path, pressures_kpa: Sequence[float],
            progress: Callable[[str], None]) -> tuple[float, list[float]]:
    """The designed model's rest gland volume and its volume at each pressure (all chambers alike), ml."""
    from phantom.model.fem.model import PhantomModel
    from phantom.model.scene import load_scene

    model = PhantomModel.from_scene(load_scene(scene_path))
    volumes: list[float] = []
    for pressure in pressures_kpa:
        progress(f"design: growth at {pressure:g} kPa ({len(volumes) + 1}/{len(pressures_kpa)})")
        state = model.equilibrium([pressure * 1e3] * model.n_chambers)
        volumes.append(float(state.gland_volume_m3) * 1e6)
    return float(model.rest_gland_volume_m3) * 1e6, volumes


def _growth_notes(scene_path: Path, rest_ml: float, pressures_kpa: Sequence[float],
                  volumes_ml: list[float]) -> list[str]:
    """Whether the designed model reaches the paper's growth (45 ml from 26.3, scaled to this gland) by 3 kPa;
    nothing when the curve stops short of 3 kPa."""
    from phantom.model.scene import load_scene

    reaching = [volume for pressure, volume in zip(pressures_kpa, volumes_ml, strict=True)
                if pressure >= PAPER_PRESSURE_KPA]
    if not reaching:
        return []
    target = PAPER_GROWN_VOLUME_ML * rest_ml / PAPER_VOLUME_ML
    if max(reaching) >= target:
        return [f"reaches {target:.1f} ml (the paper's 45 ml scaled to this gland) by {PAPER_PRESSURE_KPA:g} kPa"]
    material = load_scene(scene_path).material
    return [f"the paper's growth ({target:.1f} ml, its 45 ml scaled to this gland) is not reached: "
            f"{max(reaching):.2f} ml at {PAPER_PRESSURE_KPA:g} kPa with the scene's material ({material.model}, E "
            f"{material.youngs_modulus_pa / 1e3:g} kPa; calibrate it to the cast's measurements); the chambers are "
            f"as large as the template and the walls allow, and sizing them to a growth target is not implemented"]


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
                     for label, volume, scale in zip(CHAMBER_LABELS, result.chamber_volumes_ml, result.chamber_scales,
                                                     strict=True)],
        "walls_mm": result.walls_mm,
        "thinnest_wall": {"where": name, "mm": thinnest},
        "mesh": {"nodes": result.mesh_nodes, "tetrahedra": result.mesh_tets},
        "rest_volume_ml": result.rest_volume_ml,
        "outer_surface_mean_distance_mm": result.surface_distance_mm,
        "growth": {"pressures_kpa": result.growth_kpa, "gland_volumes_ml": result.growth_volumes_ml},
        "cast": {"silicone_ml": result.cast.silicone_ml, "split_y_mm": result.cast.split_y_mm,
                 "undercut_mm2": result.cast.undercut_mm2, "stem_clearances_mm": result.cast.stem_clearances_mm,
                 "parts": [{**asdict(part), "path": str(part.path), "printable": part.printable}
                           for part in result.cast.parts]},
        "notes": result.notes,
        "stage_times_s": result.stage_times_s,
    }
