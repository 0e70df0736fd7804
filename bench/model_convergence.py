"""Convergence of the built-in prostate's growths under mesh refinement, 4-node and 10-node tetrahedra.

Usage: .venv/bin/python bench/model_convergence.py [--scene builtin:calibrated] [--linear-sizes-mm 4,3,2.5]
       [--quadratic-sizes-mm 8,6,4] [--poisson-ratio 0.45] [--youngs-modulus-kpa 50]
       [--json bench-out.json]

For each element order and mesh size (the scene's ``mesh_size_mm`` overridden; the 10-node mesh is graded where
walls are thin), full solves at the issue's five pressure points (kPa): the gland's growth and each chamber's
(ml). Then, per order and point, Richardson extrapolation from the three meshes, ``g(h) = g* + C h^q`` solved
for the converged growth ``g*`` and the observed order ``q`` (the sizes need not be in a constant ratio), and
each mesh's error against ``g*``. ``h`` is the effective element size ``nodes^(-1/3)``, not the nominal
``mesh_size_mm``: gmsh's curvature sizing keeps the built-in mesh from refining in proportion to it (4 mm to
2.5 mm nominal is 1671 to 2896 nodes, a ratio of 1.2 in effective size, not 1.6). The smallest and largest
element volume ratio of each solve (det F; for 10-node elements the element's dilatation, which the mixed
formulation holds near 1) show how far the material compresses. Solves run one at a time (one core); progress
goes to stderr, the tables to stdout as markdown.

The ladder (run time against error): every (element order, mesh size) at two fidelity levels, the full solve
from rest and the rest compliance (``c_0 + W_0 p``, one 3x3 product per answer once the compliance is made), each
with its worst error over the five points against the *converged* gland growth (the extrapolation of the
order whose three finest meshes give one at every point, 10-node first; where none does, the finest 10-node
mesh's growth, and the errors are lower bounds), both as % of the growth and as % of the gland's volume (what a
scene's ``accuracy_pct`` states), with its set-up time and its time per answer.
``--plot`` draws it.
"""

import argparse
import dataclasses
import json
import sys
import time

import numpy as np

PRESSURE_POINTS_KPA = ((1.0, 1.0, 1.0), (2.0, 2.0, 2.0), (2.0, 0.0, 0.0), (1.0, 2.0, 3.0), (3.0, 1.0, 2.0))


def progress(message: str) -> None:
    print(message, file=sys.stderr, flush=True)


def richardson(sizes_mm: list[float], values: list[float]) -> tuple[float, float]:
    """``(g*, q)`` with ``g(h) = g* + C h^q`` through three (size, value) pairs; NaN when the values do not
    approach a limit monotonically (the differences change sign)."""
    from scipy.optimize import brentq

    (h1, h2, h3), (g1, g2, g3) = sizes_mm[-3:], values[-3:]
    ratio = (g1 - g2) / (g2 - g3) if g2 != g3 else np.nan
    if not np.isfinite(ratio) or ratio <= 0:
        return np.nan, np.nan

    def gap(order: float) -> float:
        return (h1**order - h2**order) / (h2**order - h3**order) - ratio

    try:
        order = brentq(gap, 0.05, 12.0)
    except ValueError:
        return np.nan, np.nan
    coefficient = (g1 - g2) / (h1**order - h2**order)
    return g3 - coefficient * h3**order, order


def solve_row(scene, order: int, size_mm: float, poisson_ratio: float | None,
              youngs_modulus_kpa: float | None = None) -> list[dict]:
    from phantom.model import PhantomModel

    geometry = dataclasses.replace(scene.geometry, element_order=order)
    scene = dataclasses.replace(scene, geometry=geometry)
    started = time.perf_counter()
    model = PhantomModel.from_scene(scene, mesh_size_mm=size_mm)
    if poisson_ratio is not None or youngs_modulus_kpa is not None:
        model = model.with_material(youngs_modulus_pa=None if youngs_modulus_kpa is None else youngs_modulus_kpa * 1e3,
                                    poisson_ratio=poisson_ratio)
    setup_s = time.perf_counter() - started
    progress(f"order {order}, {size_mm} mm: {len(model.nodes_m)} nodes, {len(model.tets)} elements "
             f"({setup_s:.1f} s to mesh and set up)")
    started = time.perf_counter()
    compliance = model.compliance()
    compliance_s = time.perf_counter() - started
    rows = []
    for pressures_kpa in PRESSURE_POINTS_KPA:
        pressures_pa = np.array(pressures_kpa) * 1e3
        started = time.perf_counter()
        rest_level_growth_ml = float(compliance.gland_m3_per_pa @ pressures_pa) * 1e6
        rest_level_s = time.perf_counter() - started
        started = time.perf_counter()
        state = model.equilibrium(pressures_pa)
        solve_s = time.perf_counter() - started
        ratios = model.body.element_volume_ratios(state.positions_m)
        row = {"order": order, "size_mm": size_mm, "nodes": len(model.nodes_m), "pressures_kpa": pressures_kpa,
               "gland_growth_ml": (state.gland_volume_m3 - model.rest_gland_volume_m3) * 1e6,
               "chamber_growths_ml": ((state.chamber_volumes_m3 - model.rest_chamber_volumes_m3) * 1e6).tolist(),
               "volume_ratio_min": float(ratios.min()), "volume_ratio_max": float(ratios.max()),
               "iterations": state.iterations, "solve_s": solve_s, "setup_s": setup_s,
               "rest_gland_volume_ml": model.rest_gland_volume_m3 * 1e6, "rest_level_growth_ml": rest_level_growth_ml,
               "rest_level_s": rest_level_s, "compliance_s": compliance_s}
        progress(f"  {pressures_kpa} kPa: gland +{row['gland_growth_ml']:.4f} ml, J in "
                 f"[{row['volume_ratio_min']:.3f}, {row['volume_ratio_max']:.3f}], {state.iterations} iterations, "
                 f"{solve_s:.1f} s")
        rows.append(row)
    return rows


def extrapolations(rows: list[dict], order: int) -> dict[tuple, tuple[float, float]]:
    """Per point, ``(g*, q)`` of one element order's finest three meshes (NaN where a mesh lacks the point, fewer
    than three meshes ran, or the growths approach no limit)."""
    sizes = sorted({row["size_mm"] for row in rows if row["order"] == order}, reverse=True)
    nodes = {row["size_mm"]: row["nodes"] for row in rows if row["order"] == order}
    result = {}
    for point in PRESSURE_POINTS_KPA:
        growth = {row["size_mm"]: row["gland_growth_ml"] for row in rows
                  if row["order"] == order and tuple(row["pressures_kpa"]) == point}
        result[point] = (richardson([nodes[size] ** (-1.0 / 3.0) for size in sizes], [growth[size] for size in sizes])
                         if len(sizes) >= 3 and all(size in growth for size in sizes) else (np.nan, np.nan))
    return result


def table(rows: list[dict], order: int) -> str:
    """The markdown table of one element order: growth per size, g*, q, and each size's error."""
    sizes = sorted({row["size_mm"] for row in rows if row["order"] == order}, reverse=True)
    if not sizes:
        return ""
    nodes = {row["size_mm"]: row["nodes"] for row in rows if row["order"] == order}
    header = (["pressures (kPa)"] + [f"{size:g} mm ({nodes[size]} nodes)" for size in sizes]
              + ["extrapolated", "order"] + [f"error {size:g} mm" for size in sizes] + ["J range (finest)"])
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for point, (converged, observed) in extrapolations(rows, order).items():
        by_size = {row["size_mm"]: row for row in rows
                   if row["order"] == order and tuple(row["pressures_kpa"]) == point}
        growths = [by_size[size]["gland_growth_ml"] if size in by_size else np.nan for size in sizes]
        # without a limit, each mesh's change to the finest, in brackets: a lower bound on its error
        errors = [f"{100 * (growth / converged - 1):+.2f} %" if np.isfinite(converged) else
                  f"({100 * (growth / growths[-1] - 1):+.2f} %)" if np.isfinite(growths[-1]) else "-"
                  for growth in growths]
        finest = by_size.get(sizes[-1])
        j_range = f"{finest['volume_ratio_min']:.3f}-{finest['volume_ratio_max']:.3f}" if finest else "-"
        lines.append("| " + " | ".join([",".join(f"{p:g}" for p in point)] + [f"{g:.3f}" for g in growths]
                                       + [f"{converged:.3f}", f"{observed:.2f}"] + errors + [j_range]) + " |")
    return "\n".join(lines)


def converged_growths(rows: list[dict]) -> tuple[dict[tuple, float], str]:
    """The reference growth per point and what it is: the extrapolation of the element order whose finest three
    meshes extrapolate at every point (10-node first); else the finest 10-node mesh's growth (the errors against
    it are then lower bounds); ``({}, "")`` without a 10-node mesh at every point."""
    for order in (2, 1):
        converged = {point: value for point, (value, _) in extrapolations(rows, order).items()}
        if all(np.isfinite(value) for value in converged.values()):
            return converged, f"the {4 if order == 1 else 10}-node extrapolation"
    quadratic = [row for row in rows if row["order"] == 2]
    if not quadratic:
        return {}, ""
    finest_mm = min(row["size_mm"] for row in quadratic)
    finest = {tuple(row["pressures_kpa"]): row["gland_growth_ml"] for row in quadratic if row["size_mm"] == finest_mm}
    if set(finest) != set(PRESSURE_POINTS_KPA):
        return {}, ""
    return finest, (f"the finest 10-node mesh ({finest_mm:g} mm); no extrapolation: the growths do not approach "
                       "a limit steadily, so each error is a lower bound")


def ladder(rows: list[dict], converged: dict[tuple, float]) -> list[dict]:
    """Each (order, size, level) with its set-up time, median time per answer and worst errors against the
    ``converged`` growths (:func:`converged_growths`): % of the growth, and % of the gland's volume."""
    rungs = []
    for order, size_mm in sorted({(row["order"], row["size_mm"]) for row in rows}, key=lambda key: (key[0], -key[1])):
        level_rows = [row for row in rows if row["order"] == order and row["size_mm"] == size_mm]
        for level, growth_key, time_key, setup in (
                ("full", "gland_growth_ml", "solve_s", lambda row: row["setup_s"]),
                ("rest", "rest_level_growth_ml", "rest_level_s", lambda row: row["setup_s"] + row["compliance_s"])):
            growth_errors = [abs(row[growth_key] / converged[tuple(row["pressures_kpa"])] - 1) * 100
                             for row in level_rows]
            if level == "full" and max(growth_errors) == 0.0:
                continue  # the reference mesh itself (no extrapolation): its error is not known
            volume_errors = [abs(row[growth_key] - converged[tuple(row["pressures_kpa"])])
                             / (row["rest_gland_volume_ml"] + converged[tuple(row["pressures_kpa"])]) * 100
                             for row in level_rows]
            rungs.append({"order": order, "size_mm": size_mm, "nodes": level_rows[0]["nodes"], "level": level,
                          "setup_s": setup(level_rows[0]),
                          "answer_s": float(np.median([row[time_key] for row in level_rows])),
                          "growth_error_pct": max(growth_errors), "volume_error_pct": max(volume_errors)})
    return rungs


def ladder_table(rungs: list[dict], accuracy_pct: float) -> str:
    """The ladder as markdown, cheapest answer first, and the cheapest rung within ``accuracy_pct`` (of the
    growth, and of the volume)."""
    header = ["elements", "mesh (mm)", "nodes", "level", "set-up (s)", "per answer (s)",
              "worst error (% of growth)", "worst error (% of volume)"]
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for rung in sorted(rungs, key=lambda rung: rung["answer_s"]):
        lines.append(f"| {4 if rung['order'] == 1 else 10}-node | {rung['size_mm']:g} | {rung['nodes']} | "
                     f"{rung['level']} | {rung['setup_s']:.1f} | {rung['answer_s']:.3g} | "
                     f"{rung['growth_error_pct']:.2f} | {rung['volume_error_pct']:.3f} |")
    for key, what in (("growth_error_pct", "of the growth"), ("volume_error_pct", "of the volume")):
        meeting = [rung for rung in rungs if rung[key] <= accuracy_pct]
        cheapest = None
        if meeting:
            # answers within a factor 2 of the quickest cost the same (the rest level's 3x3 product takes a few
            # microseconds on any mesh): of those, the one quickest to set up
            quickest_s = min(rung["answer_s"] for rung in meeting)
            cheapest = min((rung for rung in meeting if rung["answer_s"] <= 2 * quickest_s),
                           key=lambda rung: rung["setup_s"])
        lines.append("")
        lines.append(f"Cheapest within {accuracy_pct:g} % {what}: " + (
            f"{4 if cheapest['order'] == 1 else 10}-node, {cheapest['size_mm']:g} mm, {cheapest['level']} "
            f"({cheapest['answer_s']:.3g} s per answer, {cheapest['setup_s']:.1f} s to set up)" if cheapest
            else "none of these"))
    return "\n".join(lines)


def plot_ladder(rungs: list[dict], accuracy_pct: float, path: str, reference: str) -> None:
    """Time per answer against worst error (% of the growth, against ``reference``), one marker per rung, the
    accuracy drawn."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, axes = plt.subplots(figsize=(7, 4.5))
    for order, colour in ((1, "tab:blue"), (2, "tab:red")):
        for level, marker in (("full", "o"), ("rest", "s")):
            chosen = [rung for rung in rungs if rung["order"] == order and rung["level"] == level]
            if not chosen:
                continue
            axes.scatter([rung["answer_s"] for rung in chosen], [rung["growth_error_pct"] for rung in chosen],
                         color=colour, marker=marker, label=f"{4 if order == 1 else 10}-node, {level}")
            for index, rung in enumerate(chosen):  # stacked: a group's rungs often sit on one spot
                axes.annotate(f"{rung['size_mm']:g} mm", (rung["answer_s"], rung["growth_error_pct"]),
                              textcoords="offset points", xytext=(6, 4 - 9 * index), fontsize=8)
    axes.axhline(accuracy_pct, color="grey", linestyle="--", linewidth=1)
    axes.set_xscale("log")
    axes.set_yscale("log")
    axes.set_xlabel("time per answer (s)")
    axes.margins(x=0.12, y=0.12)
    axes.set_ylabel(f"worst gland growth error (%)\nagainst {reference}")
    axes.set_title("The prostate's fidelity ladder: run time against error")
    axes.legend(fontsize=8)
    figure.tight_layout()
    figure.savefig(path, dpi=120)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", default="builtin:calibrated")
    parser.add_argument("--linear-sizes-mm", default="4,3,2.5", help="4-node mesh sizes, coarse to fine ('' none)")
    parser.add_argument("--quadratic-sizes-mm", default="8,6,4", help="10-node mesh sizes, coarse to fine")
    parser.add_argument("--poisson-ratio", type=float, default=None, help="override the scene's (e.g. 0.4995)")
    parser.add_argument("--youngs-modulus-kpa", type=float, default=None, help="override the scene's (e.g. 50)")
    parser.add_argument("--json", default=None, help="also write every solve's row to this JSON file")
    parser.add_argument("--from-json", default=None, help="tabulate the rows of an earlier --json run, solve nothing")
    parser.add_argument("--accuracy-pct", type=float, default=1.0, help="the ladder's line: the cheapest rung within")
    parser.add_argument("--plot", default=None, help="draw the ladder into this PNG")
    args = parser.parse_args()
    from phantom.model import load_scene

    scene = load_scene(args.scene)
    rows: list[dict] = []
    if args.from_json:
        with open(args.from_json) as handle:
            rows = json.load(handle)
    for order, sizes in ((1, args.linear_sizes_mm), (2, args.quadratic_sizes_mm)):
        for size_mm in [] if args.from_json else [float(size) for size in sizes.split(",") if size]:
            rows.extend(solve_row(scene, order, size_mm, args.poisson_ratio, args.youngs_modulus_kpa))
            if args.json:
                with open(args.json, "w") as handle:
                    json.dump(rows, handle, indent=1)
    material = scene.material
    poisson = args.poisson_ratio if args.poisson_ratio is not None else material.poisson_ratio
    youngs_kpa = args.youngs_modulus_kpa or material.youngs_modulus_pa / 1e3
    print(f"\n{args.scene}: {material.model}, E {youngs_kpa:.3f} kPa, nu {poisson}; "
          "gland growth (ml)\n")
    for order, name in ((1, "4-node tetrahedra"), (2, "10-node tetrahedra, mixed (u, p, J)")):
        text = table(rows, order)
        if text:
            print(f"{name}:\n\n{text}\n")
    converged, reference = converged_growths(rows)
    rungs = ladder(rows, converged) if converged else []
    if not rungs:
        print("No ladder: neither element order has three meshes that extrapolate at every point, nor a 10-node "
              "mesh every point.")
        return
    print(f"The ladder, errors against {reference}:\n")
    print(ladder_table(rungs, args.accuracy_pct))
    if args.plot:
        plot_ladder(rungs, args.accuracy_pct, args.plot, reference.split(";")[0])


if __name__ == "__main__":
    main()
