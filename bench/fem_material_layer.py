"""The material layer against the kernels it replaced: same answers, and the time of each element pass.

The hyperelastic element kernels before the material layer (Neo-Hookean and Gent written into them) are read
from git (``git show REF:model/fem/kernels.py``, default the commit before the layer) into a module of their
own, and called side by side with today's generic kernels, which take a law number and its parameters
(phantom.model.fem.materials), on the same meshes, positions and material: the built-in prostate's 4-node mesh
(``hyperelastic_forces``) and its 10-node one (``mixed_forces``), each at a large smooth deformation (every
element stretched and turned, p/E about 0.1 deep), for forces only and for forces and the exact tangent. Both
are numba's JIT (``PHANTOM_JIT_KERNELS=1``: the same compiler for both; compiled before timing). Times: the
process's CPU time, best of --repeats calls, old and new interleaved so that the machine's load falls on both
alike. The table: the largest difference of forces, energy and tangent relative to their largest entry, the
times and new / old.
A Yeoh row shows the third law's time on the same pass (no old kernel had it).

    .venv/bin/python bench/fem_material_layer.py --size-mm 3 --quadratic-size-mm 7 --repeats 15
"""

import argparse
import importlib.util
import os
import subprocess
import sys
import time
from pathlib import Path

os.environ["PHANTOM_JIT_KERNELS"] = "1"  # both kernels by numba's JIT, before phantom's kernels are imported

import numpy as np  # noqa: E402

import phantom  # noqa: E402
from phantom.model.fem import kernels, materials  # noqa: E402
from phantom.model.fem.body import NO_TANGENT  # noqa: E402
from phantom.model.fem.model import PhantomModel  # noqa: E402
from phantom.model.mesh.prostate import builtin_prostate  # noqa: E402
from phantom.model.mesh.tetmesh import prepare_surfaces  # noqa: E402
from phantom.model.scene import Material  # noqa: E402

#: The last commit whose kernels had the laws written into them.
BEFORE_LAYER = "d0626fb"
CHAMBERS = ["chamber0", "chamber1", "chamber2"]
YOUNGS_MODULUS_PA = 50e3
#: Gent's Jm and the Yeoh coefficients (C20/C10, C30/C10) of the rows.
GENT_JM = 5.0
YEOH = (0.1, 0.01)
EXACT = 2


def old_kernels(ref: str):
    """The kernels module of git revision ``ref``, imported from a file in the cache (a fixed path, so that
    numba's cache keeps its compiled code between runs)."""
    root = Path(__file__).resolve().parent.parent
    source = subprocess.run(["git", "show", f"{ref}:model/fem/kernels.py"], cwd=root, check=True,
                            capture_output=True, text=True).stdout
    path = phantom.cache_dir("bench") / f"kernels_before_{ref}.py"
    if not path.is_file() or path.read_text() != source:
        path.write_text(source)
    spec = importlib.util.spec_from_file_location(f"kernels_before_{ref}", path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # numba's cache finds a kernel's module by name when it loads one
    spec.loader.exec_module(module)
    return module


def deformed(nodes_m):
    """A large smooth deformation with a rigid rotation: every element stretched and turned, none inverted."""
    angle = 0.6
    rotation = np.array([[1, 0, 0], [0, np.cos(angle), -np.sin(angle)], [0, np.sin(angle), np.cos(angle)]])
    centred = nodes_m - nodes_m.mean(axis=0)
    size = np.abs(centred).max()
    stretched = centred * np.array([1.15, 0.92, 1.05]) + 0.08 * centred[:, [1, 2, 0]] ** 2 / size
    return stretched @ rotation.T


def best_times_s(calls, repeats):
    """The least CPU seconds of each call, the calls interleaved ``repeats`` times (CPU time and the least: on a
    shared machine the other load only ever adds, to wall time most)."""
    seconds = [[] for _ in calls]
    for repeat in range(repeats):
        order = list(zip(calls, seconds, strict=True))
        for call, times in order if repeat % 2 else order[::-1]:  # each first as often: caches favour neither
            started = time.process_time()
            call()
            times.append(time.process_time() - started)
    return [min(times) for times in seconds]


def difference(old, new):
    """The largest difference of forces, energy and tangent, each relative to its largest entry."""
    worst = 0.0
    for a, b in zip(old, new, strict=True):
        a, b = np.asarray(a, float), np.asarray(b, float)
        worst = max(worst, float(np.abs(a - b).max() / max(np.abs(a).max(), 1e-300)))
    return worst


def linear_rows(old, size_mm, repeats):
    mesh = builtin_prostate(size_mm)
    model = PhantomModel(mesh, prepare_surfaces(mesh, CHAMBERS, None, "bench"), CHAMBERS,
                         Material("neo_hookean", YOUNGS_MODULUS_PA, 0.45))
    body, material = model.body, model.material
    positions = deformed(body.nodes_m)
    mu, lam = material.lame_mu_pa, material.lame_lambda_pa
    rows = []
    for law, inverse_jm in (("neo_hookean", 0.0), ("gent", 1.0 / GENT_JM), ("yeoh", None)):
        parameters = materials.law_parameters(law, Material(law, YOUNGS_MODULUS_PA, 0.45,
                                                            GENT_JM if law == "gent" else None, *YEOH))
        for matrix in (NO_TANGENT, EXACT):
            size = len(body.pattern.indices) if matrix else 1
            old_data, new_data = np.zeros(size), np.zeros(size)

            def new_call(new_data=new_data, matrix=matrix, parameters=parameters):
                new_data[:] = 0.0
                return kernels.hyperelastic_forces(positions, body.tets, body.dm_inverse, body.element_volumes_m3,
                                                   *parameters, mu, lam, matrix, body.pattern.scatter, new_data)

            calls = [new_call]
            if inverse_jm is not None:
                def old_call(old_data=old_data, matrix=matrix, inverse_jm=inverse_jm):
                    old_data[:] = 0.0
                    return old.hyperelastic_forces(positions, body.tets, body.dm_inverse, body.element_volumes_m3,
                                                   mu, lam, inverse_jm, matrix, body.pattern.scatter, old_data)
                calls.insert(0, old_call)
            answers = [call() for call in calls]
            times = best_times_s(calls, repeats)
            rows.append(row(f"4-node, {len(body.tets)} el.", law, matrix, answers, [old_data, new_data], times))
    return rows


def quadratic_rows(old, size_mm, repeats):
    mesh = builtin_prostate(size_mm, element_order=2)
    model = PhantomModel(mesh, prepare_surfaces(mesh, CHAMBERS, None, "bench"), CHAMBERS,
                         Material("neo_hookean", YOUNGS_MODULUS_PA, 0.4995))
    body, material = model.body, model.material
    rest = body.quadratic
    assert rest is not None
    positions = deformed(body.nodes_m)
    no_pressures = np.zeros(0)
    rows = []
    for law, inverse_jm in (("neo_hookean", 0.0), ("gent", 1.0 / GENT_JM), ("yeoh", None)):
        parameters = materials.law_parameters(law, Material(law, YOUNGS_MODULUS_PA, 0.4995,
                                                            GENT_JM if law == "gent" else None, *YEOH))
        for matrix in (NO_TANGENT, EXACT):
            size = len(body.pattern.indices) if matrix else 1
            old_data, new_data = np.zeros(size), np.zeros(size)

            def new_call(new_data=new_data, matrix=matrix, parameters=parameters):
                new_data[:] = 0.0
                return kernels.mixed_forces(positions, body.tets, rest.gradients, rest.weights, rest.volumes_m3,
                                            rest.volume_derivatives, rest.volume_weights, *parameters,
                                            material.bulk_modulus_pa, matrix, body.pattern.block_start,
                                            body.pattern.degree, new_data, no_pressures)

            calls = [new_call]
            if inverse_jm is not None:
                def old_call(old_data=old_data, matrix=matrix, inverse_jm=inverse_jm):
                    old_data[:] = 0.0
                    return old.mixed_forces(positions, body.tets, rest.gradients, rest.weights, rest.volumes_m3,
                                            rest.volume_derivatives, rest.volume_weights, material.lame_mu_pa,
                                            material.bulk_modulus_pa, inverse_jm, matrix, body.pattern.block_start,
                                            body.pattern.degree, old_data, no_pressures)
                calls.insert(0, old_call)
            answers = [call() for call in calls]
            times = best_times_s(calls, repeats)
            rows.append(row(f"10-node, {len(body.tets)} el.", law, matrix, answers, [old_data, new_data], times))
    return rows


def row(mesh, law, matrix, answers, data, times):
    what = "forces + tangent" if matrix else "forces"
    if len(answers) == 1:
        return f"| {mesh} | {law} | {what} | (new law) | - | {times[0] * 1e3:.2f} | - |"
    (old_forces, old_energy, old_det), (new_forces, new_energy, new_det) = answers
    compared = [old_forces, [old_energy], [old_det]] + ([data[0]] if matrix else [])
    now = [new_forces, [new_energy], [new_det]] + ([data[1]] if matrix else [])
    return (f"| {mesh} | {law} | {what} | {difference(compared, now):.1e} | {times[0] * 1e3:.2f} | "
            f"{times[1] * 1e3:.2f} | {times[1] / times[0]:.3f} |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--before", default=BEFORE_LAYER, help="git revision of the kernels before the layer")
    parser.add_argument("--size-mm", type=float, default=3.0, help="the 4-node mesh's element size")
    parser.add_argument("--quadratic-size-mm", type=float, default=7.0, help="the 10-node mesh's element size")
    parser.add_argument("--repeats", type=int, default=15)
    args = parser.parse_args()
    old = old_kernels(args.before)
    print(f"kernels before the layer: git {args.before}; numba JIT for both; CPU time, best of {args.repeats} calls")
    print("| mesh | law | pass | max rel. difference | before ms | layer ms | layer / before |")
    print("|---|---|---|---|---|---|---|")
    for line in linear_rows(old, args.size_mm, args.repeats) + quadratic_rows(old, args.quadratic_size_mm,
                                                                             args.repeats):
        print(line, flush=True)


if __name__ == "__main__":
    main()
