"""The paper's validation of its phantom by scanning (its section IV-C, Figs. 9 and 10), for the simulated rig:
at each target volume, the inverse's pressures, the scan, its volume against the target and the model, the mean
closest-point distance to the model and a heatmap, in a report (markdown and PNGs) and a Rerun recording.

The command line (``phantom scan validate --sim``) drives the daemon and the simulated board; what is here
measures and reports. Two distances are kept apart:

- against the **model** (the controller's: the scene at the measured pressures), after rigid alignment as
  ``compare-scan`` does: what the paper measured, here the model's error (the truth phantom is stiffer, as a
  real one differs from its model) plus the scanner's;
- against the **truth** (the simulated phantom's own surface), in the rig's frame without alignment: the
  scanner's error alone, since the truth is known.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

from phantom import require_extra
from phantom.model.mesh.surface import SurfaceIndex, TriangleMesh, subdivide, vertex_areas_mm2
from phantom.scan.camera import Pose, Rig
from phantom.scan.compare import weighted_statistics

if TYPE_CHECKING:
    from phantom.model import PhantomModel
    from phantom.scan.capture import CaptureFolder


@dataclass
class TargetResult:
    """One target volume's scan and its comparisons (ml, kPa, mm, %)."""

    target_ml: float
    inverse_pressures_kpa: list[float]
    measured_pressures_kpa: list[float]
    predicted_ml: float
    model_ml: float
    true_ml: float
    scan_ml: float
    model_distance_mm: dict[str, float]
    truth_distance_mm: dict[str, float]
    capture: str
    mesh: str
    heatmap: str
    views: int
    image_size: list[int]
    stage_s: dict[str, float] = field(default_factory=dict)

    @property
    def scan_vs_target_pct(self) -> float:
        return 100.0 * (self.scan_ml / self.target_ml - 1.0)

    @property
    def scan_vs_model_pct(self) -> float:
        return 100.0 * (self.scan_ml / self.model_ml - 1.0)

    @property
    def scan_vs_truth_pct(self) -> float:
        return 100.0 * (self.scan_ml / self.true_ml - 1.0)

    def to_json(self) -> dict[str, Any]:
        return {**asdict(self), "scan_vs_target_pct": self.scan_vs_target_pct,
                "scan_vs_model_pct": self.scan_vs_model_pct, "scan_vs_truth_pct": self.scan_vs_truth_pct}


def scene_targets_ml(scene_path: str) -> list[float]:
    """The gland volumes (ml) a scene's [[steps]] go through, in order, each once."""
    import tomllib

    from phantom import PhantomError, read_text
    from phantom.model.scene import MAX_SCENE_BYTES

    try:
        steps = tomllib.loads(read_text(scene_path, MAX_SCENE_BYTES, "the scene")).get("steps", [])
    except tomllib.TOMLDecodeError as error:
        raise PhantomError(f"cannot read the scene {scene_path}: {error}") from None
    volumes: list[float] = []
    for step in steps:
        volume = step.get("volume_ml")
        if isinstance(volume, (int, float)) and volume not in volumes:
            volumes.append(float(volume))
    if not volumes:
        raise PhantomError(f"the scene {scene_path} has no [[steps]] with volume_ml: give --targets")
    return volumes


class Truth(Protocol):
    """The simulated phantom's truth (``phantom.hil.truth_shape.TruthShape``): its surface (mm) and its gland's
    volume (ml) at chamber pressures (kPa)."""

    def surface(self, pressures_kpa: list[float] | np.ndarray) -> TriangleMesh: ...

    def gland_volume_ml(self, pressures_kpa: list[float] | np.ndarray) -> float: ...


def measure_target(target_ml: float, inverse: dict[str, Any], folder: CaptureFolder, rig: Rig, to_truth: Pose,
                   controller: PhantomModel, truth: Truth, out: Path,
                   voxel_mm: float) -> tuple[TargetResult, tuple[TriangleMesh, np.ndarray]]:
    """One target of the validation, from its capture ``folder``: the scan reconstructed with ``rig`` and written
    (``out/scan_<target>ml.ply``), compared with the model at the pressures held during the capture (a heatmap,
    ``out/heatmap_<target>ml.png``) and, mapped by ``to_truth``, with the truth there. ``inverse`` is what the
    daemon answered the target (``pressures_kpa``, ``predicted_volume_ml``). Returns the result and the model's
    surface in the rig's frame with its signed distance to the scan (mm), for the recording."""
    from phantom.model.mesh.surface import model_surface
    from phantom.scan.compare import compare, read_scan
    from phantom.scan.heatmap import write_heatmap
    from phantom.scan.reconstruct import reconstruct, write_mesh

    pressures = np.array([frame.pressures_kpa for frame in folder.frames], dtype=float).mean(axis=0)
    result = reconstruct(folder, rig, voxel_mm)
    mesh_path = write_mesh(result.mesh, out / f"scan_{target_ml:g}ml.ply")
    state = controller.equilibrium(pressures * 1e3)
    model = model_surface(state.positions_m, controller.outer_triangles)
    model_ml = state.gland_volume_m3 * 1e6
    comparison = compare(read_scan(mesh_path), model, model_ml)
    heatmap = write_heatmap(comparison, out / f"heatmap_{target_ml:g}ml.png",
                            f"scan against the model at the {target_ml:g} ml target\nmean "
                            f"{comparison.symmetric_mm['mean']:.3f} mm, volume {result.volume_ml:.2f} ml "
                            f"(model {model_ml:.2f} ml)")
    scanned = TriangleMesh(to_truth.apply(result.mesh.vertices_mm), result.mesh.triangles)
    measured = TargetResult(
        target_ml, [float(p) for p in inverse["pressures_kpa"]], pressures.tolist(),
        float(inverse["predicted_volume_ml"]), model_ml, truth.gland_volume_ml(pressures), result.volume_ml,
        comparison.symmetric_mm, truth_distances(scanned, truth.surface(pressures)), str(folder.path),
        str(mesh_path), str(heatmap), len(folder.frames), [rig.camera.width, rig.camera.height], result.stage_s)
    # the model into the rig's frame, where the reconstruction and the cameras are (x_model = R x + t)
    alignment = comparison.alignment
    in_rig_mm = (comparison.model_vertices_mm - alignment.translation_mm) @ alignment.rotation
    return measured, (TriangleMesh(in_rig_mm, comparison.model_triangles), comparison.model_signed_distance_mm)


def frame_map(calibrated: Rig, truth: Rig, elevation_deg: float) -> Pose:
    """The map from the calibrated rig's world into the true rig's (the phantom's frame): both see the camera at
    orbit 0 at the first elevation, so ``truth^-1 o calibrated`` through that camera's frame."""
    seen, true = calibrated.pose(0.0, elevation_deg), truth.pose(0.0, elevation_deg)
    rotation = true.rotation.T @ seen.rotation
    return Pose(rotation, true.rotation.T @ (seen.translation_mm - true.translation_mm))


def truth_distances(scan: TriangleMesh, truth: TriangleMesh, levels: int = 2) -> dict[str, float]:
    """Closest-point distances (mm) between a scan and the true surface in one frame, both ways, area-weighted
    and pooled as compare-scan pools them; the true surface subdivided ``levels`` times so that its side has
    as many points as it needs."""
    vertices, triangles = truth.vertices_mm, truth.triangles
    for _ in range(levels):
        vertices, triangles = subdivide(vertices, triangles)
    to_truth, _, _ = SurfaceIndex(truth.vertices_mm, truth.triangles).closest(scan.vertices_mm)
    to_scan, _, _ = SurfaceIndex(scan.vertices_mm, scan.triangles).closest(vertices)
    scan_weights = vertex_areas_mm2(scan.vertices_mm, scan.triangles)
    truth_weights = vertex_areas_mm2(vertices, triangles)
    return weighted_statistics(np.concatenate([to_truth, to_scan]),
                               np.concatenate([scan_weights / scan_weights.sum(), truth_weights / truth_weights.sum()]))


def write_figure(results: list[TargetResult], path: Path) -> Path:
    """The paper's Fig. 9 for the simulated rig: the mean closest-point distance to the model and to the truth
    (mm), and the scan's volume against the target, the model and the truth (%), per target volume."""
    with require_extra("scan"):
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

    targets = [result.target_ml for result in results]
    figure, (left, right) = plt.subplots(1, 2, figsize=(10, 4))
    left.plot(targets, [r.model_distance_mm["mean"] for r in results], "o-", label="scan to model (aligned)")
    left.plot(targets, [r.truth_distance_mm["mean"] for r in results], "s-", label="scan to truth (scanner alone)")
    left.set_xlabel("target volume (ml)")
    left.set_ylabel("mean closest-point distance (mm)")
    left.legend()
    left.grid(alpha=0.3)
    right.plot(targets, [r.scan_vs_target_pct for r in results], "o-", label="scan vs target")
    right.plot(targets, [r.scan_vs_model_pct for r in results], "^-", label="scan vs model")
    right.plot(targets, [r.scan_vs_truth_pct for r in results], "s-", label="scan vs truth")
    right.axhline(0.0, color="grey", linewidth=0.8)
    right.set_xlabel("target volume (ml)")
    right.set_ylabel("volume difference (%)")
    right.legend()
    right.grid(alpha=0.3)
    figure.suptitle("Simulated scans of the BPH targets (the paper's Fig. 9)")
    figure.tight_layout()
    figure.savefig(path, dpi=110)
    plt.close(figure)
    return path


def write_report(results: list[TargetResult], out: Path, meta: dict[str, Any]) -> Path:
    """``report.md`` (a table per target and the figures), ``fig9.png`` and ``results.json`` in ``out``."""
    out.mkdir(parents=True, exist_ok=True)
    figure = write_figure(results, out / "fig9.png")
    (out / "results.json").write_text(json.dumps({"meta": meta, "targets": [r.to_json() for r in results]},
                                                 indent=1) + "\n")
    lines = [
        "# The paper's validation on the simulated rig",
        "",
        f"{meta.get('command', '')}",
        "",
        f"Scene {meta.get('scene')}; the simulated phantom is the truth model ({meta.get('truth')}), which the "
        "controller does not share. Each target: the inverse's pressures, held by the firmware in simavr; the "
        f"orbit turned by the firmware's steppers; {results[0].views if results else 0} pictures of "
        f"{results[0].image_size[0] if results else 0}x{results[0].image_size[1] if results else 0} px from the "
        "virtual camera; the rig calibrated from rendered pictures of the ChArUco target; the reconstruction "
        "carved from the silhouettes.",
        "",
        "| target ml | inverse kPa | scan ml | vs target | vs model | vs truth | mean to model mm | p95 mm | "
        "mean to truth mm | heatmap |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in results:
        pressures = ", ".join(f"{p:.2f}" for p in r.inverse_pressures_kpa)
        lines.append(f"| {r.target_ml:g} | {pressures} | {r.scan_ml:.2f} | {r.scan_vs_target_pct:+.2f} % | "
                     f"{r.scan_vs_model_pct:+.2f} % | {r.scan_vs_truth_pct:+.2f} % | "
                     f"{r.model_distance_mm['mean']:.3f} | {r.model_distance_mm['p95']:.3f} | "
                     f"{r.truth_distance_mm['mean']:.3f} | [{Path(r.heatmap).name}]({Path(r.heatmap).name}) |")
    lines += [
        "",
        "'vs model' and 'mean to model' compare the scan with the controller's model at the measured pressures, "
        "aligned rigidly (as `phantom compare-scan`, and as the paper compares its Meshroom scans with SOFA): the "
        "model's own error shows there, since the simulated phantom is stiffer than the model. 'vs truth' and "
        "'mean to truth' compare it with the simulated phantom's true surface in the rig's frame: the scanner's "
        "error alone.",
        "",
        f"![Fig. 9]({figure.name})",
        "",
    ]
    lines += [f"![{r.target_ml:g} ml]({Path(r.heatmap).name})" for r in results]
    path = out / "report.md"
    path.write_text("\n".join(lines) + "\n")
    return path


def write_recording(results: list[TargetResult], rig: Rig, captures: list[Any], models: list[tuple[TriangleMesh,
                    np.ndarray]], path: Path, picture_scale: float = 0.25) -> Path:
    """A Rerun recording, in the calibrated rig's frame (mm): per target (the ``target_ml`` timeline) the
    reconstruction (``scan/reconstruction``), the model's surface aligned to it and coloured by its signed
    distance to the scan (``scan/model``: ``models`` are given in the rig's frame), and every picture with its
    camera's pose (``scan/cameras/NNN``: a pinhole with the rig's intrinsics, the picture at ``picture_scale``)."""
    with require_extra("record"):
        import rerun as rr
    with require_extra("scan"):
        import cv2
        import matplotlib

    from phantom.scan.capture import CaptureFolder
    from phantom.scan.compare import read_scan
    from phantom.scan.heatmap import COLOUR_MAP, colour_limit_mm

    stream = rr.RecordingStream("phantom_scan_validation")
    path.parent.mkdir(parents=True, exist_ok=True)
    stream.save(str(path))
    small_camera = rig.camera.scaled(picture_scale)
    small = (small_camera.width, small_camera.height)
    for result, folder_path, (model, signed) in zip(results, captures, models, strict=True):
        stream.set_time("target_ml", sequence=round(result.target_ml))
        mesh = read_scan(result.mesh)
        stream.log("scan/reconstruction", rr.Mesh3D(vertex_positions=mesh.vertices_mm.astype(np.float32),
                                                    triangle_indices=mesh.triangles.astype(np.uint32)))
        limit = colour_limit_mm(signed)
        rgba = matplotlib.colormaps[COLOUR_MAP](matplotlib.colors.Normalize(-limit, limit)(signed))
        stream.log("scan/model", rr.Mesh3D(vertex_positions=model.vertices_mm.astype(np.float32),
                                           triangle_indices=model.triangles.astype(np.uint32),
                                           vertex_colors=(255 * rgba).astype(np.uint8)))
        folder = CaptureFolder.open(folder_path)
        for frame in folder.frames:
            pose = rig.pose(frame.orbit_deg, frame.elevation_deg)
            entity = f"scan/cameras/{frame.index:03d}"
            stream.log(entity, rr.Transform3D(translation=pose.centre_mm, mat3x3=pose.rotation.T))
            stream.log(entity, rr.Pinhole(image_from_camera=small_camera.matrix, resolution=list(small)))
            picture = cv2.resize(folder.image(frame), small, interpolation=cv2.INTER_AREA)
            stream.log(f"{entity}/picture", rr.Image(picture))
    stream.flush()
    stream.disconnect()
    return path
