"""How long the inverse takes to refuse an unreachable target on the full model, against the work it cannot avoid.

Usage: .venv/bin/python bench/inverse_unreachable.py [--scene builtin:calibrated] [--volume-ml 60]
       [--element-order 2 --size-mm 10 --youngs-modulus-kpa 50 --poisson-ratio 0.4996] [--runs 3]

A gland volume above what the pressure limit gives is refused with the reachable range, whose upper end is the
full solve at the pressure limit: no refusal can be cheaper than that solve. The peer, measured in the same run,
is therefore one forward full solve at the limit from rest on a fresh model; the refusal is timed on another
fresh model (cold: the solve at the limit included) and again on the same one (warm: its states kept), and the
table gives the time beyond the peer's. Each row is the median of ``--runs``.
"""

import argparse
import dataclasses
import statistics
import time

import numpy as np


def fresh_model(args):
    from phantom.model import PhantomModel, load_scene

    scene = load_scene(args.scene)
    if args.element_order is not None:
        scene = dataclasses.replace(scene, geometry=dataclasses.replace(scene.geometry,
                                                                        element_order=args.element_order))
    model = PhantomModel.from_scene(scene, mesh_size_mm=args.size_mm)
    if args.youngs_modulus_kpa is not None or args.poisson_ratio is not None:
        model = model.with_material(
            youngs_modulus_pa=None if args.youngs_modulus_kpa is None else args.youngs_modulus_kpa * 1e3,
            poisson_ratio=args.poisson_ratio)
    return model


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", default="builtin:calibrated")
    parser.add_argument("--volume-ml", type=float, default=60.0, help="an unreachable gland volume")
    parser.add_argument("--element-order", type=int, default=None)
    parser.add_argument("--size-mm", type=float, default=None)
    parser.add_argument("--youngs-modulus-kpa", type=float, default=None)
    parser.add_argument("--poisson-ratio", type=float, default=None)
    parser.add_argument("--runs", type=int, default=3)
    args = parser.parse_args()
    from phantom.model.inverse import InverseSolver, UnreachableTargetError
    from phantom.model.target import Target

    peer_s, cold_s, warm_s, message = [], [], [], ""
    for _ in range(args.runs):
        model = fresh_model(args)
        limit_pa = np.full(model.n_chambers, model.model_settings.pressure_max_pa)
        started = time.perf_counter()
        model.equilibrium(limit_pa)
        peer_s.append(time.perf_counter() - started)
        solver = InverseSolver(fresh_model(args), fidelity="full")
        for times in (cold_s, warm_s):
            started = time.perf_counter()
            try:
                solver.pressures_for(Target(gland_volume_m3=args.volume_ml * 1e-6))
            except UnreachableTargetError as error:
                message = str(error)
            else:
                raise SystemExit(f"{args.volume_ml} ml was reached: pass an unreachable --volume-ml")
            times.append(time.perf_counter() - started)
    peer, cold, warm = (statistics.median(values) for values in (peer_s, cold_s, warm_s))
    print(f"{args.scene}: {len(model.nodes_m)} nodes, {model.material.model}, E "
          f"{model.material.youngs_modulus_pa / 1e3:.3g} kPa, nu {model.material.poisson_ratio}; "
          f"median of {args.runs}\n\nrefused: {message}\n")
    print("| what | time (s) | beyond the solve at the limit (s) | ratio to the solve at the limit |")
    print("|---|---|---|---|")
    print(f"| peer: full solve at the pressure limit, fresh model | {peer:.3f} | - | 1 |")
    print(f"| refusal, fresh model | {cold:.3f} | {cold - peer:.3f} | {cold / peer:.2f} |")
    print(f"| refusal again, same model | {warm:.3f} | - | {warm / peer:.3f} |")


if __name__ == "__main__":
    main()
