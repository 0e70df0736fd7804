"""Run time against error of the forward model: mesh sizes x fidelity levels, and the inverse's solve times.

Usage: .venv/bin/python bench/model_fidelity.py [--sizes-mm 6,5,4,3] [--reference-mm 2] [--out bench/model_fidelity.png]

Built-in prostate (scene ``builtin``): for each mesh size and level (rest compliance, updated compliance, full
co-rotational solve), over pressure combinations spanning 0-3 kPa, the error against the reference (finest
mesh, full solve) in gland volume growth, chamber volume growth (%, of the reference growth) and shape (mean
nodal displacement distance at the reference nodes, um), with the cold time (model setup and first answer) and
the warm time per answer. Hollow sphere (a = 10 mm, b = 20 mm, nu = 0.45): the cavity and outer volume change
per pascal against the Lame closed form. Inverse: the warm OSQP solve and the full inverse with its iterations,
each as a ratio against a peer timed in the same run (a cold QP setup; one forward full solve).
"""

import argparse
import sys
import time

import numpy as np

PRESSURE_COMBINATIONS_KPA = np.array([
    [3.0, 0.0, 0.0], [0.0, 3.0, 0.0], [0.0, 0.0, 3.0], [1.5, 1.5, 1.5], [3.0, 3.0, 3.0], [1.0, 2.0, 3.0],
])
LEVELS = ("rest", "updated", "full")


def progress(message: str) -> None:
    print(message, file=sys.stderr, flush=True)


def displacement_at(points_m, rest_nodes_m, displacement_m):
    """Piecewise-linear interpolation of a nodal displacement field to other points (nearest node outside)."""
    from scipy.interpolate import LinearNDInterpolator, NearestNDInterpolator

    inside = LinearNDInterpolator(rest_nodes_m, displacement_m)(points_m)
    missing = np.isnan(inside).any(axis=1)
    if missing.any():
        inside[missing] = NearestNDInterpolator(rest_nodes_m, displacement_m)(points_m[missing])
    return inside


def prostate_rows(sizes_mm, reference_mm, material="corotational"):
    """Rows of the built-in prostate's levels for one material model (its full solve on the finest mesh is the
    reference)."""
    from phantom.model import PhantomModel, load_scene
    from phantom.model.fidelity.levels import VolumeEstimator

    scene = load_scene("builtin")
    progress(f"reference: {reference_mm} mm, full {material}")
    reference_model = PhantomModel.from_scene(scene, mesh_size_mm=reference_mm).with_material(model=material)
    reference = []
    for pressures_kpa in PRESSURE_COMBINATIONS_KPA:
        state = reference_model.equilibrium(pressures_kpa * 1e3)
        reference.append((state.chamber_volumes_m3 - reference_model.rest_chamber_volumes_m3,
                          state.gland_volume_m3 - reference_model.rest_gland_volume_m3,
                          state.positions_m - reference_model.nodes_m))
    rows = []
    for size_mm in sizes_mm:
        for level in LEVELS:
            progress(f"prostate {size_mm} mm, {level}")
            started = time.perf_counter()
            model = PhantomModel.from_scene(scene, mesh_size_mm=size_mm).with_material(model=material)
            estimator = VolumeEstimator(model, level=level)
            estimator.volumes(PRESSURE_COMBINATIONS_KPA[0] * 1e3)
            cold_s = time.perf_counter() - started
            warm, gland_errors, chamber_errors, shape_errors = [], [], [], []
            for pressures_kpa, (chamber_ref, gland_ref, displacement_ref) in zip(
                    PRESSURE_COMBINATIONS_KPA, reference, strict=True):
                started = time.perf_counter()
                chambers, gland = estimator.volumes(pressures_kpa * 1e3)
                warm.append(time.perf_counter() - started)
                gland_errors.append(abs(gland - model.rest_gland_volume_m3 - gland_ref) / gland_ref * 100)
                grown = chamber_ref > 1e-3 * chamber_ref.max()
                chamber_errors.append(np.max(np.abs(chambers - model.rest_chamber_volumes_m3 - chamber_ref)[grown]
                                             / chamber_ref[grown]) * 100)
                displacement = estimator.shape(pressures_kpa * 1e3) - model.nodes_m
                at_reference = displacement_at(reference_model.nodes_m, model.nodes_m, displacement)
                shape_errors.append(np.mean(np.linalg.norm(at_reference - displacement_ref, axis=1)) * 1e6)
            case = "prostate" if material == "corotational" else f"prostate {material}"
            rows.append({"case": case, "size_mm": size_mm, "nodes": len(model.nodes_m), "level": level,
                         "cold_s": cold_s, "warm_s": float(np.median(warm)),
                         "gland_error_pct": float(np.mean(gland_errors)),
                         "chamber_error_pct": float(np.mean(chamber_errors)),
                         "shape_error_um": float(np.mean(shape_errors))})
    return rows


def sphere_rows(sizes_mm):
    from phantom.model.fem.model import PhantomModel
    from phantom.model.fidelity.levels import VolumeEstimator
    from phantom.model.mesh.prostate import generate_hollow_sphere
    from phantom.model.mesh.tetmesh import prepare_surfaces
    from phantom.model.scene import Material

    inner_m, outer_m, youngs_pa, poisson = 10e-3, 20e-3, 50e3, 0.45
    bulk, shear = youngs_pa / (3 * (1 - 2 * poisson)), youngs_pa / (2 * (1 + poisson))
    shell = inner_m**3 / (outer_m**3 - inner_m**3)
    cavity_exact = 4 * np.pi * shell * (inner_m**3 / (3 * bulk) + outer_m**3 / (4 * shear))
    outer_exact = 6 * np.pi * (1 - poisson) * shell * outer_m**3 / youngs_pa
    # Small load: the closed form is linear elasticity.
    pressure_pa = 1e-3 * youngs_pa
    rows = []
    for size_mm in sizes_mm:
        for level in LEVELS:
            progress(f"sphere {size_mm} mm, {level}")
            started = time.perf_counter()
            mesh = generate_hollow_sphere(inner_m * 1e3, outer_m * 1e3, size_mm)
            model = PhantomModel(mesh, prepare_surfaces(mesh, ["cavity"], None, "sphere"), ["cavity"],
                                 Material("corotational", youngs_pa, poisson))
            estimator = VolumeEstimator(model, level=level)
            chambers, gland = estimator.volumes([pressure_pa])
            cold_s = time.perf_counter() - started
            started = time.perf_counter()
            chambers, gland = estimator.volumes([pressure_pa])
            warm_s = time.perf_counter() - started
            cavity = (chambers[0] - model.rest_chamber_volumes_m3[0]) / pressure_pa
            outer = (gland - model.rest_gland_volume_m3) / pressure_pa
            rows.append({"case": "sphere", "size_mm": size_mm, "nodes": len(model.nodes_m), "level": level,
                         "cold_s": cold_s, "warm_s": warm_s,
                         "gland_error_pct": abs(outer / outer_exact - 1) * 100,
                         "chamber_error_pct": abs(cavity / cavity_exact - 1) * 100, "shape_error_um": float("nan")})
    return rows


def inverse_rows(size_mm):
    from phantom.model import PhantomModel, load_scene
    from phantom.model.inverse import InverseSolver, Target, VolumeQP

    model = PhantomModel.from_scene(load_scene("builtin"), mesh_size_mm=size_mm)
    solver = InverseSolver(model, pressure_max_pa=3000.0, fidelity="full")
    rest_ml = model.rest_gland_volume_m3 * 1e6
    reachable_ml = float(model.compliance().gland_m3_per_pa.sum() * 3000.0 * 1e6)
    targets_ml = rest_ml + reachable_ml * np.array([0.2, 0.4, 0.6, 0.8])
    # The QP alone, warm: the same problem updated with new targets, against a cold setup of the same QP.
    rows = solver._rows(Target(gland_volume_m3=targets_ml[0] * 1e-6), solver.rest)
    inputs = solver._qp_inputs(rows, exact=True)
    cold = []
    for _ in range(20):
        problem = VolumeQP(model.n_chambers, inputs[2].shape[0])
        started = time.perf_counter()
        problem.minimise(*inputs)
        cold.append(time.perf_counter() - started)
    warm_wall, warm_osqp = [], []
    for repeat in range(400):
        target_ml = targets_ml[repeat % len(targets_ml)]
        rows = solver._rows(Target(gland_volume_m3=target_ml * 1e-6), solver.rest)
        inputs = solver._qp_inputs(rows, exact=True)
        started = time.perf_counter()
        _, osqp_s = problem.minimise(*inputs)
        warm_wall.append(time.perf_counter() - started)
        warm_osqp.append(osqp_s)
    forward = []
    for pressures_kpa in PRESSURE_COMBINATIONS_KPA[:3]:
        started = time.perf_counter()
        model.equilibrium(pressures_kpa * 1e3)
        forward.append(time.perf_counter() - started)
    inverse = []
    for target_ml in targets_ml:
        progress(f"inverse {size_mm} mm, target {target_ml:.3f} ml")
        result = solver.pressures_for(Target(gland_volume_m3=target_ml * 1e-6))
        check = model.equilibrium(result.pressures_pa).gland_volume_m3 * 1e6
        inverse.append({"target_ml": target_ml, "iterations": result.iterations, "time_s": result.solve_time_s,
                        "qp_time_us": result.qp_solve_time_s * 1e6, "error_pct": abs(check / target_ml - 1) * 100})
    return {"size_mm": size_mm, "qp_cold_us": float(np.median(cold)) * 1e6,
            "qp_warm_us": float(np.median(warm_wall)) * 1e6, "qp_warm_osqp_us": float(np.median(warm_osqp)) * 1e6,
            "forward_full_s": float(np.median(forward)), "inverse": inverse}


def print_table(rows):
    print("| case | mesh (mm) | nodes | level | cold (s) | warm (ms) | gland err (%) | chamber err (%) | "
          "shape err (um) |")
    print("|---|---|---|---|---|---|---|---|---|")
    for row in rows:
        shape = "-" if np.isnan(row["shape_error_um"]) else f"{row['shape_error_um']:.2f}"
        print(f"| {row['case']} | {row['size_mm']:g} | {row['nodes']} | {row['level']} | {row['cold_s']:.2f} | "
              f"{row['warm_s'] * 1e3:.2f} | {row['gland_error_pct']:.3f} | {row['chamber_error_pct']:.3f} | "
              f"{shape} |")


def plot(rows, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, axes = plt.subplots(1, 2, figsize=(11, 4.5))
    markers = {"rest": "o", "updated": "s", "full": "^"}
    cases = sorted({row["case"] for row in rows if row["case"].startswith("prostate")})
    for axis, case_list, title in ((axes[0], cases, "built-in prostate vs finest full solve"),
                                   (axes[1], ["sphere"], "hollow sphere vs Lame")):
        for case, level in ((case, level) for case in case_list for level in LEVELS):
            chosen = [row for row in rows if row["case"] == case and row["level"] == level]
            times_ms = [max(row["warm_s"], 1e-6) * 1e3 for row in chosen]
            errors = [max(row["gland_error_pct"], 1e-4) for row in chosen]
            label = level if case == "sphere" else f"{case.removeprefix('prostate').strip() or 'corotational'} {level}"
            axis.loglog(times_ms, errors, marker=markers[level], label=label,
                        linestyle="--" if "neo_hookean" in case else "-")
            for row, time_ms, error in zip(chosen, times_ms, errors, strict=True):
                axis.annotate(f"{row['size_mm']:g}", (time_ms, error), fontsize=7, xytext=(3, 3),
                              textcoords="offset points")
        axis.set_xlabel("warm time per answer (ms)")
        axis.set_ylabel("gland volume error (%)")
        axis.set_title(title)
        axis.grid(True, which="both", alpha=0.3)
        axis.legend()
    figure.tight_layout()
    figure.savefig(path, dpi=80)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes-mm", default="6,5,4,3")
    parser.add_argument("--reference-mm", type=float, default=2.0)
    parser.add_argument("--sphere-sizes-mm", default="6,4,3,2.5")
    parser.add_argument("--inverse-mm", type=float, default=3.0)
    parser.add_argument("--out", default="bench/model_fidelity.png")
    parser.add_argument("--materials", default="corotational,neo_hookean",
                        help="material models whose prostate ladder is measured")
    args = parser.parse_args(argv)
    sizes = [float(value) for value in args.sizes_mm.split(",")]
    rows = []
    for material in args.materials.split(","):
        rows += prostate_rows(sizes, args.reference_mm, material)
    rows += sphere_rows([float(value) for value in args.sphere_sizes_mm.split(",")])
    print_table(rows)
    plot(rows, args.out)
    print(f"\nplot: {args.out}")
    inverse = inverse_rows(args.inverse_mm)
    print(f"\nInverse on the built-in prostate at {inverse['size_mm']:g} mm (pressure max 3 kPa):")
    print(f"- QP alone, warm (updated in place): {inverse['qp_warm_us']:.1f} us wall, "
          f"{inverse['qp_warm_osqp_us']:.1f} us inside OSQP; a cold setup + solve of the same QP: "
          f"{inverse['qp_cold_us']:.1f} us "
          f"(warm/cold = {inverse['qp_warm_us'] / inverse['qp_cold_us']:.3f})")
    print(f"- one forward full solve (peer): {inverse['forward_full_s']:.3f} s")
    print("| target (ml) | iterations | inverse time (s) | / forward solve | QP time (us) | error vs forward (%) |")
    print("|---|---|---|---|---|---|")
    for entry in inverse["inverse"]:
        print(f"| {entry['target_ml']:.3f} | {entry['iterations']} | {entry['time_s']:.2f} | "
              f"{entry['time_s'] / inverse['forward_full_s']:.1f} | {entry['qp_time_us']:.0f} | "
              f"{entry['error_pct']:.5f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
