"""The 10-node mixed solve against FElupe's mixed field at equal answers, and CHOLMOD's factorisation as the floor.

The thick hollow sphere (a = 10 mm, b = 20 mm, 6 mm 10-node, Neo-Hookean, E 50 kPa, nu 0.4996), as
tests/test_fem_felupe.py: FElupe (P2/P1 mixed field, ``ThreeFieldVariation``, Newton on the whole mixed system
with SuperLU, tests/reference/felupe_reference.py) holds the cavity wall at stretches up to 1.15 and reports the
pressure that takes; the model solves that pressure from rest (its Newton and path following). Equal answers
when the cavity volumes agree (different discretisations, P2/P0 against P2/P1: to the mesh's error). The
floor is the model's Newton iterations times one CHOLMOD factorisation of its tangent at the answer: what the
solve would cost if an iteration were its factorisation alone. Then the 10 mm 10-node prostate at (3,1,2) kPa
(:func:`prostate`). All in one process, one after the other.

Run: ``nice .venv/bin/python bench/fem_mixed_peers.py [--size-mm 6]``
"""

import argparse
import dataclasses
import os
import sys
import time
from pathlib import Path

import numpy as np
import scipy.sparse.linalg

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))  # the oracles: tests/reference/
from reference.felupe_reference import felupe_mixed_dead_load, felupe_mixed_sphere  # noqa: E402

from phantom.model.fem.body import EXACT_TANGENT  # noqa: E402
from phantom.model.fem.model import PhantomModel  # noqa: E402
from phantom.model.mesh.prostate import generate_hollow_sphere  # noqa: E402
from phantom.model.mesh.tetmesh import prepare_surfaces  # noqa: E402
from phantom.model.scene import Material, load_scene  # noqa: E402

INNER_MM, OUTER_MM, YOUNGS_MODULUS_PA, POISSON_RATIO = 10.0, 20.0, 50e3, 0.4996
#: FElupe's wall stretches, in order (as tests/test_fem_felupe.py: 52 % cavity growth at the last).
STRETCHES = (1.05, 1.10, 1.15)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size-mm", type=float, default=6.0)
    args = parser.parse_args()
    mesh = generate_hollow_sphere(INNER_MM, OUTER_MM, args.size_mm, element_order=2)
    surfaces = prepare_surfaces(mesh, ["cavity"], None, "sphere")
    model = PhantomModel(mesh, surfaces, ["cavity"], Material("neo_hookean", YOUNGS_MODULUS_PA, POISSON_RATIO))
    model.equilibrium([100.0])  # compile the kernels, factorise the rest stiffness
    print(f"{len(model.nodes_m)} nodes, load average {os.getloadavg()[0]:.1f} (2 cores)")

    (answers, solves), felupe_s, felupe_cpu_s = timed(lambda: counting_solves(
        lambda: felupe_mixed_sphere(model, list(STRETCHES), INNER_MM * 1e-3)))
    pressure_pa, reference_m = answers[-1]

    state, ours_s, ours_cpu_s = timed(lambda: model.equilibrium([pressure_pa]))
    difference_pct = 100 * (state.chamber_volumes_m3[0] / model.volumes(reference_m)[0][0] - 1)
    factor_s = factorisation_s(model, state)

    print(f"cavity stretch {STRETCHES[-1]}: FElupe's pressure {pressure_pa / 1e3:.4f} kPa; the model at that pressure "
          f"grows the cavity {difference_pct:+.3f} % from FElupe's")
    print("| solver | wall | CPU | Newton iterations (linear solves) |")
    print("|---|---|---|---|")
    print(f"| FElupe P2/P1, wall held at {', '.join(map(str, STRETCHES))} | {felupe_s:.2f} s | {felupe_cpu_s:.2f} s "
          f"| {solves} (SuperLU) |")
    print(f"| phantom P2/P0, the pressure from rest | {ours_s:.2f} s | {ours_cpu_s:.2f} s | {state.iterations} |")
    floor_s = state.iterations * factor_s
    print(f"| floor: {state.iterations} CHOLMOD factorisations of the model's tangent | {floor_s:.2f} s | "
          f"| one: {factor_s:.3f} s |")


def prostate() -> None:
    """The 10 mm 10-node prostate at (3, 1, 2) kPa as tests/test_fem_felupe.py holds it (Neo-Hookean, E 30 kPa,
    nu 0.4996, its fixation): the model from rest; FElupe under the model's pressure forces at its answer as a
    dead load (FElupe has no pressure on 10-node faces), in one step."""
    scene = load_scene("builtin")
    scene = dataclasses.replace(scene, material=Material("neo_hookean", 30e3, 0.4996),
                                geometry=dataclasses.replace(scene.geometry, element_order=2, lobe_chamber_scale=1.2))
    model = PhantomModel.from_scene(scene, mesh_size_mm=10.0)
    model.equilibrium([100.0, 0.0, 0.0])
    pressures_pa = [3e3, 1e3, 2e3]
    state, ours_s, ours_cpu_s = timed(lambda: model.equilibrium(pressures_pa))
    forces_n = np.tensordot(pressures_pa, model.volume_gradients(state.positions_m)[: model.n_chambers], axes=1)
    (reference_m, solves), felupe_s, felupe_cpu_s = timed(lambda: counting_solves(
        lambda: felupe_mixed_dead_load(model, forces_n.reshape(-1, 3), load_steps=1)))
    ours, theirs = model.volumes(state.positions_m), model.volumes(reference_m)
    difference_pct = 100 * np.max(np.abs(np.append(ours[0], ours[1]) / np.append(theirs[0], theirs[1]) - 1))
    factor_s = factorisation_s(model, state)
    print(f"\nprostate, 10 mm, {len(model.nodes_m)} nodes, (3,1,2) kPa, load average {os.getloadavg()[0]:.1f}: volumes "
          f"within {difference_pct:.3f} % of FElupe's")
    print("| solver | wall | CPU | Newton iterations (linear solves) |")
    print("|---|---|---|---|")
    print(f"| FElupe P2/P1, the model's pressure forces dead, one step | {felupe_s:.2f} s | {felupe_cpu_s:.2f} s | "
          f"{solves} (SuperLU) |")
    print(f"| phantom P2/P0, the pressures from rest | {ours_s:.2f} s | {ours_cpu_s:.2f} s | {state.iterations} |")
    print(f"| floor: {state.iterations} CHOLMOD factorisations | {state.iterations * factor_s:.2f} s | | "
          f"one: {factor_s:.3f} s |")


def timed(call):
    """``call()``, its wall time and its CPU time (s)."""
    started, cpu = time.perf_counter(), time.process_time()
    result = call()
    return result, time.perf_counter() - started, time.process_time() - cpu


def counting_solves(call):
    """``call()`` and the sparse direct solves (FElupe's Newton iterations) it made."""
    solves = []
    original = scipy.sparse.linalg.spsolve

    def counting(*arguments, **keywords):
        solves.append(1)
        return original(*arguments, **keywords)

    scipy.sparse.linalg.spsolve = counting
    try:
        return call(), len(solves)
    finally:
        scipy.sparse.linalg.spsolve = original


def factorisation_s(model, state):
    """One CHOLMOD factorisation of the model's exact tangent at ``state`` (s)."""
    problem = model.problem(state.pressures_pa)
    data = model.body.elastic(state.positions_m, state.formulation, EXACT_TANGENT, problem.constraints,
                              problem.pressures_pa).tangent_data
    _, seconds, _ = timed(lambda: model.body.factorize(data))
    return seconds


if __name__ == "__main__":
    main()
    prostate()
