"""The scanner's own error on the simulated rig: how the reconstruction's volume and mean closest-point distance
fall with the number of views and the picture size, and what the visual hull cannot see (a concavity).

The truth is the simulated phantom's surface (the truth model of hil/truth_shape.py) at the pressures the inverse
gives for the BPH scene's top target (the most deformed shape), and at rest. For each picture size (a fraction
of 1280x960) the virtual rig is calibrated from rendered pictures of the ChArUco target, the truth is rendered from
60 orbit stops at each of the two elevations, and reconstructions are carved from every k-th stop (so the
fewer-view rows are subsets of the same pictures), with the calibrated poses; the reconstruction is mapped into
the truth's frame through the camera at orbit 0 (``phantom.scan.validation.frame_map``) and compared without any
alignment. Then a sphere with a round dent shows the hull filling what no line of sight grazes: a cut through the
dent, truth against reconstruction.

Writes a table (markdown, stdout), ``bench/scan_accuracy.png`` and ``bench/scan_concavity.png``.

Run: ``.venv/bin/python bench/scan_accuracy.py [--scales 0.25,0.5,1] [--views 6,12,30,60] [--out bench]``
(about 12 minutes on two cores shared with other work); ``--concavity-only`` for the dented sphere alone.

Another simulated phantom (``phantom daemon --sim --sim-truth SCENE --sim-truth-modulus-factor F``'s):
``--sim-truth SCENE --modulus-factor F`` photographs that truth (its plant and shapes, built once and cached, as
the daemon builds them); ``--pressures-kpa A,B,C`` a state of its own (default: the BPH target's); ``--true-poses``
carves with the virtual rig's true geometry, as the daemon's verify scan does, instead of a calibration. For each
shape it also prints the volume the camera renders against the plant's gland volume and the FE surface's own, and
where the reconstruction lies off the truth, by height (signed closest-point distance, + outside). No plots then.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import matplotlib
import matplotlib.ticker

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from phantom.cli.scan_verify import VERIFY_SETTLE_S  # noqa: E402
from phantom.hil.plant import truth_plant_path, truth_shapes_path  # noqa: E402
from phantom.hil.truth_shape import TruthShape  # noqa: E402
from phantom.host.scenes import load_timeline_scene  # noqa: E402
from phantom.model import PhantomModel  # noqa: E402
from phantom.model.cluster import stderr_progress  # noqa: E402
from phantom.model.inverse import InverseSolver, Target  # noqa: E402
from phantom.model.mesh.surface import SurfaceIndex, TriangleMesh, enclosed_volume_ml, vertex_areas_mm2  # noqa: E402
from phantom.protocol.motion import SCANNER_AXES  # noqa: E402
from phantom.scan.calibrate import calibrate_rig, target_views  # noqa: E402
from phantom.scan.camera import VIRTUAL_CENTRE_MM, virtual_rig  # noqa: E402
from phantom.scan.capture import CaptureFolder, Plan  # noqa: E402
from phantom.scan.reconstruct import VOXEL_MM, reconstruct  # noqa: E402
from phantom.scan.synthetic import sphere  # noqa: E402
from phantom.scan.validation import frame_map, truth_distances  # noqa: E402
from phantom.scan.virtual import render_capture, render_target_captures  # noqa: E402

BPH_SCENE = Path(__file__).resolve().parent.parent / "host" / "scenes" / "bph_growth.toml"


def section(mesh: TriangleMesh, z_mm: float) -> list[np.ndarray]:
    """The segments where the plane z = z_mm cuts a surface ((2, 2) arrays of x, y)."""
    segments = []
    for triangle in mesh.vertices_mm[mesh.triangles]:
        heights = triangle[:, 2] - z_mm
        points = []
        for a, b in ((0, 1), (1, 2), (2, 0)):
            if heights[a] * heights[b] < 0:
                t = heights[a] / (heights[a] - heights[b])
                points.append(triangle[a, :2] + t * (triangle[b, :2] - triangle[a, :2]))
        if len(points) == 2:
            segments.append(np.array(points))
    return segments


def signed_distance_mm(points_mm: np.ndarray, truth: TriangleMesh) -> np.ndarray:
    """Each point's closest-point distance (mm) to a closed surface, + outside it (by the closest triangle's
    outward normal)."""
    distance, closest, triangle = SurfaceIndex(truth.vertices_mm, truth.triangles).closest(points_mm)
    corners = truth.vertices_mm[truth.triangles[triangle]]
    normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    side = np.sign(np.einsum("ij,ij->i", points_mm - closest, normals))
    signed: np.ndarray = np.where(side < 0, -distance, distance)
    return signed


def by_height(scanned: TriangleMesh, truth: TriangleMesh, bands: int = 6) -> list[tuple[float, float, float, float]]:
    """Where a reconstruction lies off the truth, in ``bands`` bands of height: each band's lowest and highest z
    (mm), its area-weighted mean signed distance (mm, + outside the truth) and the volume that puts outside (ml:
    the area times the signed distance, summed)."""
    signed = signed_distance_mm(scanned.vertices_mm, truth)
    areas = vertex_areas_mm2(scanned.vertices_mm, scanned.triangles)
    heights = scanned.vertices_mm[:, 2]
    edges = np.linspace(heights.min(), heights.max(), bands + 1)
    band = np.clip(np.searchsorted(edges, heights, side="right") - 1, 0, bands - 1)
    rows = []
    for number in range(bands):
        chosen = band == number
        rows.append((float(edges[number]), float(edges[number + 1]),
                     float(np.average(signed[chosen], weights=areas[chosen])),
                     float(np.sum(areas[chosen] * signed[chosen]) / 1e3)))
    return rows


def plot_accuracy(rows: list[tuple], path: Path) -> None:
    """|volume error| and mean distance against the views, a line per shape and picture size (rows as printed:
    shape, scale, width, height, views, volume %, mean mm, p95 mm, seconds)."""
    figure, (left, right) = plt.subplots(1, 2, figsize=(10, 4))
    for name, width, height in dict.fromkeys((row[0], row[2], row[3]) for row in rows):
        chosen = [row for row in rows if (row[0], row[2], row[3]) == (name, width, height)]
        label = f"{name}, {width}x{height}"
        left.plot([row[4] for row in chosen], [abs(row[5]) for row in chosen], "o-", label=label)
        right.plot([row[4] for row in chosen], [row[6] for row in chosen], "o-", label=label)
    views = sorted({row[4] for row in rows})
    for axes, what in ((left, "|volume error| (%)"), (right, "mean closest-point distance (mm)")):
        axes.set_xscale("log")
        axes.set_yscale("log")
        axes.set_xticks(views, [str(v) for v in views])
        axes.xaxis.set_minor_locator(matplotlib.ticker.NullLocator())
        axes.set_xlabel("views (two elevations)")
        axes.set_ylabel(what)
        axes.grid(alpha=0.3, which="both")
    left.axhline(1.0, color="red", linewidth=0.8)
    right.axhline(0.3, color="red", linewidth=0.8)
    right.legend(fontsize=7)
    figure.suptitle("The scanner's own error on the simulated rig (red: the goals)")
    figure.tight_layout()
    figure.savefig(path, dpi=110)
    plt.close(figure)


def concavity(out: Path, voxel_mm: float, scratch: Path) -> None:
    """What the visual hull cannot see: a sphere with a round 6 mm dent (a bowl whose bottom curves inwards every
    way) and the plain sphere, each carved from 120 views of 640x480 with the true poses; the dent's fill is the
    dented hull's excess volume over its truth less the plain hull's (the pipeline's own bias), and a cut through
    the dent, truth against hull, is ``scan_concavity.png``."""
    true_rig = virtual_rig(0.5)
    excess_ml, hulls = {}, {}
    for dent_mm in (0.0, 6.0):
        shape = sphere(15.0, VIRTUAL_CENTRE_MM, levels=5, dent_mm=dent_mm)
        folder = render_capture(shape, true_rig, Plan(60), scratch / f"dent{dent_mm:g}")
        result = reconstruct(CaptureFolder.open(folder.path), true_rig, voxel_mm)
        excess_ml[dent_mm] = result.volume_ml - enclosed_volume_ml(shape)
        hulls[dent_mm] = (shape, result.mesh)
    dented, hull = hulls[6.0]
    dent_ml = enclosed_volume_ml(hulls[0.0][0]) - enclosed_volume_ml(dented)
    filled_ml = excess_ml[6.0] - excess_ml[0.0]
    bottom = VIRTUAL_CENTRE_MM + np.array([0.0, 9.0, 0.0])
    above_mm = float(SurfaceIndex(hull.vertices_mm, hull.triangles).closest(bottom[None])[0][0])
    print(f"\nconcavity: a 6 mm dent in a 15 mm sphere holds {dent_ml * 1000:.0f} mm^3; the hull from 120 views "
          f"(640x480, true poses) fills {filled_ml * 1000:.0f} mm^3 of it ({100 * filled_ml / dent_ml:.0f} %; the "
          f"plain sphere's hull is off by {excess_ml[0.0] * 1000:+.0f} mm^3) and stands {above_mm:.1f} mm above the "
          "dent's bottom")
    figure, axes = plt.subplots(figsize=(5, 5))
    cut_z = float(VIRTUAL_CENTRE_MM[2]) + 0.013  # off the plane the meshes' vertices lie on
    for mesh, colour, label in ((dented, "black", "truth"), (hull, "tab:red", "visual hull")):
        for number, segment in enumerate(section(mesh, cut_z)):
            axes.plot(segment[:, 0], segment[:, 1], color=colour, linewidth=1.2, label=label if number == 0 else None)
    axes.set_aspect("equal")
    axes.set_xlabel("x (mm)")
    axes.set_ylabel("y (mm)")
    axes.legend()
    axes.set_title(f"a dent no silhouette shows: {100 * filled_ml / dent_ml:.0f} % stays filled")
    figure.tight_layout()
    figure.savefig(out / "scan_concavity.png", dpi=110)
    plt.close(figure)


def truth_and_shapes(args: argparse.Namespace) -> tuple[TruthShape, dict[str, TriangleMesh]]:
    """The simulated phantom (the shipped truth, or ``--sim-truth``'s) and its surfaces at rest and at the state
    photographed (``--pressures-kpa``, else the pressures the controller's model gives for the BPH scene's top
    target), with the volumes the camera sees and the plant holds."""
    if args.sim_truth is None:
        truth = TruthShape()
    else:
        plant = truth_plant_path(args.sim_truth, args.modulus_factor, progress=stderr_progress("the truth's plant"))
        truth = TruthShape(args.sim_truth, args.modulus_factor, plant_path=plant, shapes_path=truth_shapes_path(plant))
    if args.pressures_kpa is not None:
        pressures_kpa = np.array([float(value) for value in args.pressures_kpa.split(",")])
        name = "at " + ", ".join(f"{value:g}" for value in pressures_kpa) + " kPa"
    else:
        scene = load_timeline_scene(str(BPH_SCENE))
        top_ml = max(step["volume_ml"] for step in scene.raw["steps"])
        pressures_kpa = InverseSolver(PhantomModel.from_scene(scene), fidelity="full").pressures_for(
            Target(gland_volume_m3=top_ml * 1e-6)).pressures_pa / 1e3
        name = f"{top_ml:g} ml target"
    print(f"truth: {truth.description}; {name}: pressures {np.round(pressures_kpa, 3).tolist()} kPa")
    shapes = {}
    for label, state_kpa in (("rest", np.zeros(3)), (name, pressures_kpa)):
        shapes[label] = truth.surface(state_kpa)
        tabulated_m = truth._tabulated_m(state_kpa, 0.0)
        fem = "" if tabulated_m is None else (
            f", the FE surface's own {enclosed_volume_ml(TriangleMesh(tabulated_m * 1e3, shapes[label].triangles)):.3f}"
            " ml (scaled to the plant's)")
        plant_ml = None if truth.plant is None else truth.plant.truth_gland_volume_ml(1e3 * state_kpa)
        print(f"  {label}: the camera sees {enclosed_volume_ml(shapes[label]):.3f} ml, the plant holds "
              f"{plant_ml if plant_ml is None else round(plant_ml, 3)} ml{fem}")
    return truth, shapes


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scales", default="0.25,0.5,1", help="picture sizes, fractions of 1280x960")
    parser.add_argument("--views", default="6,12,30,60", help="orbit stops per elevation (divisors of 60)")
    parser.add_argument("--elevations", default="0+30",
                        help="the elevation sets (deg) to carve from, ','-separated, each '+'-joined (e.g. "
                             "0+30,0+15+30,15+45): the pictures are rendered at all of their elevations once, and each "
                             "set's rows carved from its own")
    parser.add_argument("--spans", default="360",
                        help="the orbit's spans (deg, ','-separated): 360 a whole turn; 180 the stops of the first "
                             "half turn only (-180 up to 0 deg, both passes over the same arc), as a plan's span_deg")
    parser.add_argument("--voxel-mm", type=float, default=VOXEL_MM)
    parser.add_argument("--out", default=str(Path(__file__).resolve().parent))
    parser.add_argument("--concavity-only", action="store_true", help="only the dented sphere (a few minutes)")
    parser.add_argument("--sim-truth", metavar="SCENE", help="another simulated phantom (phantom daemon --sim-truth)")
    parser.add_argument("--modulus-factor", type=float, default=1.0, help="--sim-truth's E factor")
    parser.add_argument("--pressures-kpa", metavar="A,B,C", help="the state photographed besides rest")
    parser.add_argument("--true-poses", action="store_true",
                        help="carve with the virtual rig's true geometry (as the verify scan does), no calibration")
    args = parser.parse_args()
    if args.modulus_factor != 1.0 and args.sim_truth is None:
        parser.error("--modulus-factor is --sim-truth's: give --sim-truth SCENE too")
    scales = [float(value) for value in args.scales.split(",")]
    view_counts = [int(value) for value in args.views.split(",")]
    elevation_sets = [tuple(float(value) for value in chosen.split("+")) for chosen in args.elevations.split(",")]
    rendered_deg = tuple(sorted({elevation for chosen in elevation_sets for elevation in chosen}))
    spans_deg = [float(value) for value in args.spans.split(",")]
    out = Path(args.out)
    if args.concavity_only:
        with tempfile.TemporaryDirectory(prefix="scan-accuracy-") as scratch:
            concavity(out, args.voxel_mm, Path(scratch))
        return

    _, shapes = truth_and_shapes(args)
    rows = []
    with tempfile.TemporaryDirectory(prefix="scan-accuracy-") as scratch:
        for scale in scales:
            true_rig = virtual_rig(scale, rendered_deg)
            started = time.perf_counter()
            if args.true_poses:
                rig, to_truth = true_rig, frame_map(true_rig, true_rig, 0.0)
                print(f"scale {scale:g} ({true_rig.camera.width}x{true_rig.camera.height}): the true poses")
            else:
                folders = render_target_captures(true_rig, Path(scratch) / f"target{scale:g}")
                rig = calibrate_rig(target_views(folders), true_rig.camera.width, true_rig.camera.height)
                to_truth = frame_map(rig, true_rig, 0.0)
                print(f"scale {scale:g} ({true_rig.camera.width}x{true_rig.camera.height}): calibrated in "
                      f"{time.perf_counter() - started:.0f} s, RMS {rig.calibration['rms_px']:.3f} px")
            for name, shape in shapes.items():
                folder = render_capture(shape, true_rig, Plan(60, rendered_deg), Path(scratch) / f"{name}{scale:g}")
                folder = CaptureFolder.open(folder.path)
                for elevations, views, span_deg in ((chosen, views, span) for chosen in elevation_sets
                                                    for views in view_counts for span in spans_deg):
                    step = 60 // views
                    frames = [frame for frame in folder.frames if round((frame.orbit_deg + 180.0) / 6.0) % step == 0
                              and frame.orbit_deg + 180.0 < span_deg - 1e-6
                              and any(abs(frame.elevation_deg - elevation) < 1e-6 for elevation in elevations)]
                    result = reconstruct(folder, rig, args.voxel_mm, frames)
                    scanned = TriangleMesh(to_truth.apply(result.mesh.vertices_mm), result.mesh.triangles)
                    distance = truth_distances(scanned, shape)
                    volume_pct = 100 * (result.volume_ml / enclosed_volume_ml(shape) - 1)
                    stops = len(frames) // len(elevations)
                    arc_deg = 360.0 if span_deg >= 360.0 else (stops - 1) * 6.0 * step
                    board_s = Plan(stops, elevations, span_deg=arc_deg, settle_s=VERIFY_SETTLE_S).board_s(SCANNER_AXES)
                    at = "+".join(f"{elevation:g}" for elevation in elevations) + (
                        "" if span_deg >= 360.0 else f" over {arc_deg:g}")
                    rows.append((name, scale, true_rig.camera.width, true_rig.camera.height, len(frames), volume_pct,
                                 distance["mean"], distance["p95"], sum(result.stage_s.values()), at, board_s))
                    print(f"  {name:>16} {stops:3d} x {at:>8} deg ({board_s:.1f} s on the board): volume "
                          f"{volume_pct:+.3f} %, mean {distance['mean']:.4f} mm, p95 {distance['p95']:.4f} mm, "
                          f"reconstruction {rows[-1][-3]:.1f} s", flush=True)
                print("    where, by height (z mm: mean signed distance, volume outside the truth): " + "; ".join(
                    f"{low:.1f}..{high:.1f}: {mean_mm:+.3f} mm, {outside_ml:+.4f} ml"
                    for low, high, mean_mm, outside_ml in by_height(scanned, shape)), flush=True)
        print("\n| shape | picture | elevations (deg) | views | scan (board) | volume vs truth | mean distance | "
              "p95 distance | reconstruction |")
        print("|---|---|---|---|---|---|---|---|---|")
        for name, _, width, height, views, volume_pct, mean, p95, seconds, at, board_s in rows:
            print(f"| {name} | {width}x{height} | {at} | {views} | {board_s:.1f} s | {volume_pct:+.3f} % | "
                  f"{mean:.3f} mm | {p95:.3f} mm | {seconds:.1f} s |")
        if args.sim_truth is None and len(elevation_sets) == 1:
            plot_accuracy([row[:-2] for row in rows], out / "scan_accuracy.png")
            concavity(out, args.voxel_mm, Path(scratch))


if __name__ == "__main__":
    main()
