"""Element kernels: the SVD polar rotation, and forces that are the exact gradient of the energy."""

import numpy as np
import pytest

import phantom
from phantom.model.fem import kernels
from phantom.model.mesh.prostate import generate_hollow_sphere
from phantom.model.mesh.tetmesh import enclosed_volume_m3, prepare_surfaces, volume_gradient_m2


def numpy_polar_rotation(deformation_gradient):
    """Independent truth: LAPACK's SVD, with the last singular pair flipped to make R proper."""
    u, _, vt = np.linalg.svd(deformation_gradient)
    if np.linalg.det(u @ vt) < 0:
        u[:, 2] *= -1
    return u @ vt


@pytest.mark.parametrize("kind", ["general", "near_identity", "inverted", "flat", "needle"])
def test_polar_rotation_matches_lapack_svd(kind):
    rng = np.random.default_rng(7)
    for _ in range(300):
        matrix = rng.normal(size=(3, 3))
        if kind == "near_identity":
            matrix = np.eye(3) + 1e-4 * matrix
        elif kind == "inverted":
            matrix = np.diag([1.0, 1.0, -1.0]) @ (np.eye(3) + 0.2 * matrix)
        elif kind == "flat":
            matrix[:, 2] = 0.3 * matrix[:, 0] - 0.7 * matrix[:, 1]
        elif kind == "needle":
            matrix = np.outer(matrix[:, 0], matrix[0]) + 1e-3 * matrix
        rotation = kernels.polar_rotation(matrix)
        assert np.abs(rotation.T @ rotation - np.eye(3)).max() < 1e-12
        assert np.linalg.det(rotation) == pytest.approx(1.0, abs=1e-12)
        # Rounding in the SVD of a 3 x 3 matrix, amplified by the gap between singular values.
        assert np.abs(rotation - numpy_polar_rotation(matrix)).max() < 1e-8


def test_polar_rotation_of_a_rotation_is_itself():
    angle = 0.7
    rotation = np.array([[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0], [0, 0, 1.0]])
    stretch = np.diag([1.3, 0.8, 1.1])
    assert np.abs(kernels.polar_rotation(rotation @ stretch) - rotation).max() < 1e-14
    assert np.abs(kernels.polar_rotation(np.zeros((3, 3))) - np.eye(3)).max() == 0.0


@pytest.fixture(scope="module")
def sphere():
    mesh = generate_hollow_sphere(10.0, 20.0, 7.0)
    return mesh, prepare_surfaces(mesh, ["cavity"], None, "sphere")


def deformed(mesh, seed=3):
    """A large, smooth deformation with a rigid rotation: every element stretched and turned."""
    rng = np.random.default_rng(seed)
    angle = 0.9
    rotation = np.array([[1, 0, 0], [0, np.cos(angle), -np.sin(angle)], [0, np.sin(angle), np.cos(angle)]])
    x = mesh.nodes_m
    stretched = x * np.array([1.2, 0.9, 1.05]) + 0.2 * x[:, [1, 2, 0]] ** 2 / 0.02
    return stretched @ rotation.T + 1e-4 * rng.normal(size=x.shape)


@pytest.mark.parametrize("corotational", [True, False])
def test_forces_are_the_gradient_of_the_energy(sphere, corotational):
    mesh, _ = sphere
    dm_inverse, _, stiffness = kernels.element_rest_data(mesh.nodes_m, mesh.tets, 50e3, 0.45)
    positions = deformed(mesh)

    def energy_and_forces(x):
        forces, energy, _ = kernels.internal_forces(x, mesh.nodes_m, mesh.tets, dm_inverse, stiffness, corotational,
                                                    False, np.zeros((1, 12, 12), np.int64), np.zeros(1))
        return energy, forces

    energy, forces = energy_and_forces(positions)
    direction = np.random.default_rng(5).normal(size=positions.shape) * 1e-3
    step = 1e-4
    plus, _ = energy_and_forces(positions + step * direction)
    minus, _ = energy_and_forces(positions - step * direction)
    # Central differences: error O(step^2) relative, about 1e-8 here; rounding of the energy about 1e-10.
    assert (plus - minus) / (2 * step) == pytest.approx(np.sum(forces * direction), rel=1e-6)


def test_corotational_energy_ignores_rigid_motion(sphere):
    mesh, _ = sphere
    dm_inverse, _, stiffness = kernels.element_rest_data(mesh.nodes_m, mesh.tets, 50e3, 0.45)
    angle = 2.0
    rotation = np.array([[np.cos(angle), 0, np.sin(angle)], [0, 1, 0], [-np.sin(angle), 0, np.cos(angle)]])
    moved = mesh.nodes_m @ rotation.T + np.array([0.01, -0.02, 0.03])
    scatter, data = np.zeros((1, 12, 12), np.int64), np.zeros(1)
    forces, energy, smallest_det = kernels.internal_forces(moved, mesh.nodes_m, mesh.tets, dm_inverse, stiffness,
                                                           True, False, scatter, data)
    linear_forces, linear_energy, _ = kernels.internal_forces(moved, mesh.nodes_m, mesh.tets, dm_inverse,
                                                              stiffness, False, False, scatter, data)
    # Small-strain energy is not rotation invariant: it sees strain in a rotation. The co-rotational energy
    # is zero up to rounding (relative 1e-12 of that).
    assert energy < 1e-12 * linear_energy
    assert np.abs(forces).max() < 1e-9 * np.abs(linear_forces).max()
    assert smallest_det == pytest.approx(1.0)


def test_volume_gradient_is_the_derivative_of_the_volume(sphere):
    mesh, surfaces = sphere
    positions = deformed(mesh)
    direction = np.random.default_rng(9).normal(size=positions.shape) * 1e-3
    for triangles in (surfaces.chamber_triangles[0], surfaces.outer_triangles):
        gradient = volume_gradient_m2(positions, triangles)
        step = 1e-3
        difference = (enclosed_volume_m3(positions + step * direction, triangles)
                      - enclosed_volume_m3(positions - step * direction, triangles)) / (2 * step)
        # The volume is cubic in the positions: central differences are exact up to step^2 terms.
        assert difference == pytest.approx(np.sum(gradient * direction), rel=1e-6)


def test_element_stiffness_is_symmetric_and_annihilates_rigid_motion(sphere):
    mesh, _ = sphere
    _, volumes, stiffness = kernels.element_rest_data(mesh.nodes_m, mesh.tets, 50e3, 0.3)
    assert np.all(volumes > 0)
    assert np.abs(stiffness - stiffness.transpose(0, 2, 1)).max() <= 1e-12 * np.abs(stiffness).max()
    rest = mesh.nodes_m[mesh.tets]
    spin = np.cross(np.array([0.3, -0.2, 0.9]), rest).reshape(len(mesh.tets), 12)
    translation = np.tile([1.0, 2.0, 3.0], 4)
    for motion in (spin, np.broadcast_to(translation, spin.shape)):
        forces = np.einsum("eij,ej->ei", stiffness, motion)
        assert np.abs(forces).max() < 1e-9 * np.abs(stiffness).max()


def test_corotational_tangent_is_the_exact_hessian(sphere):
    from phantom.model.fem.model import PhantomModel
    from phantom.model.scene import Material

    mesh, surfaces = sphere
    model = PhantomModel(mesh, surfaces, ["cavity"], Material("corotational", 50e3, 0.45))
    positions = deformed(mesh)
    pressures = np.array([3e3])
    tangent = model.stiffness_matrix(positions, "corotational", pressures)
    assert abs(tangent - tangent.T).max() <= 1e-12 * abs(tangent).max()
    direction = np.random.default_rng(4).normal(size=positions.shape) * 1e-3
    direction.ravel()[model.held_dofs] = 0.0

    def out_of_balance(x):
        forces, _, _ = kernels.internal_forces(x, mesh.nodes_m, mesh.tets, *kernels.element_rest_data(
            mesh.nodes_m, mesh.tets, 50e3, 0.45)[::2], True, 0, np.zeros((1, 12, 12), np.int64), np.zeros(1))
        return (forces - pressures[0] * volume_gradient_m2(x, surfaces.chamber_triangles[0])).ravel()

    step = 1e-6
    difference = (out_of_balance(positions + step * direction) - out_of_balance(positions - step * direction)) / (
        2 * step)
    free = np.ones(difference.size, bool)
    free[model.held_dofs] = False
    # Elastic part (with the rotation's derivative) and follower-load part together: central differences of
    # the forces agree to O(step^2) and rounding, 1e-8 of the largest entry; R K R^T alone misses by ~10 %.
    expected = tangent @ direction.ravel()
    assert np.abs(difference - expected)[free].max() < 1e-7 * np.abs(expected).max()


KERNEL_OUTPUTS = r"""
import sys
import numpy as np
from scipy.spatial import Delaunay
from phantom.model.fem import kernels

rng = np.random.default_rng(11)
nodes = rng.uniform(0.0, 0.02, size=(60, 3))
tets = Delaunay(nodes).simplices.astype(np.int64)
_, volumes, _ = kernels.element_rest_data(nodes, tets, 50e3, 0.45)
tets[volumes < 0] = tets[volumes < 0][:, [0, 2, 1, 3]]
dm_inverse, volumes, stiffness = kernels.element_rest_data(nodes, tets, 50e3, 0.45)
moved = nodes + 1e-3 * rng.normal(size=nodes.shape)
scatter = np.arange(len(tets) * 144, dtype=np.int64).reshape(-1, 12, 12)
hessian = np.zeros(scatter.size)
forces, energy, smallest_det = kernels.internal_forces(moved, nodes, tets, dm_inverse, stiffness, True, 2, scatter,
                                                       hessian)
hyperelastic_tangent = np.zeros(scatter.size)
stretched = nodes @ np.array([[1.2, 0.1, 0.0], [0.0, 0.9, 0.2], [0.1, 0.0, 1.1]]).T  # no element inverted
gent = (1, np.array([17e3, 0.05]))  # law number and parameters (phantom.model.fem.materials)
hyperelastic = kernels.hyperelastic_forces(stretched, tets, dm_inverse, volumes, *gent, 17e3, 160e3, 2, scatter,
                                           hyperelastic_tangent)
yeoh_tangent = np.zeros(scatter.size)
yeoh = kernels.hyperelastic_forces(stretched, tets, dm_inverse, volumes, 2, np.array([8.5e3, 900.0, 40.0]), 17e3,
                                   160e3, 2, scatter, yeoh_tangent)
triangles = tets[:, :3].copy()
indptr = np.arange(0, 3 * len(nodes) * 3 * len(nodes) + 1, 3 * len(nodes), dtype=np.int64)
indices = np.tile(np.arange(3 * len(nodes), dtype=np.int32), 3 * len(nodes))
pressure_stiffness = np.zeros(len(indices))
kernels.add_pressure_stiffness(moved, triangles, 2e3, indptr, indices, pressure_stiffness)
vector = rng.normal(size=3 * len(nodes))
lower = np.tril(rng.normal(size=(8, 8)), -1) + np.diag(rng.uniform(1.0, 2.0, 8))
columns = [np.flatnonzero(lower[:, j]) for j in range(8)]
factor_indptr = np.cumsum([0] + [len(c) for c in columns]).astype(np.int64)
factor_indices = np.concatenate(columns).astype(np.int32)
factor_values = np.concatenate([lower[c, j] for j, c in enumerate(columns)])
permutation = rng.permutation(8).astype(np.int64)
np.savez(sys.argv[1], dm_inverse=dm_inverse, volumes=volumes, stiffness=stiffness, forces=forces,
         energy=energy, smallest_det=smallest_det, hessian=hessian, hyperelastic_forces=hyperelastic[0],
         hyperelastic_energy=hyperelastic[1], hyperelastic_tangent=hyperelastic_tangent, yeoh_forces=yeoh[0],
         yeoh_tangent=yeoh_tangent,
         pressure_stiffness=pressure_stiffness,
         product=kernels.csr_multiply(indptr, indices, pressure_stiffness, vector),
         determinants=kernels.deformation_determinants(moved, tets, dm_inverse),
         rotation=kernels.polar_rotation(rng.normal(size=(3, 3))),
         solution=kernels.cholesky_solve(factor_indptr, factor_indices, factor_values, permutation, vector[:8]),
         solutions=kernels.cholesky_solve(factor_indptr, factor_indices, factor_values, permutation,
                                          vector[:16].reshape(8, 2)),
         aot=kernels.JIT_KERNELS is None, numba_loaded="numba" in sys.modules)
"""


@pytest.mark.slow
def test_ahead_of_time_build_matches_the_jit_kernels_without_loading_numba(tmp_path):
    """The kernels built ahead of time (what bootstrap makes, so a CLI call skips numba's 0.6 s start) give the
    JIT kernels' numbers: the same source and IEEE operations, so they agree to rounding (1e-12 relative: the two
    compilers may contract multiply-adds differently); and a process using them never imports numba."""
    import os
    import subprocess
    import sys

    environment = dict(os.environ, PHANTOM_CACHE_DIR=str(tmp_path / "cache"),
                       NUMBA_CACHE_DIR=str(phantom.cache_dir("numba")))
    environment.pop("PHANTOM_JIT_KERNELS", None)
    build = subprocess.run([sys.executable, "-m", "phantom.model.fem.kernels"], env=environment, capture_output=True,
                           text=True, timeout=240)
    assert build.returncode == 0, build.stderr
    assert "built the kernels ahead of time" in build.stdout
    again = subprocess.run([sys.executable, "-m", "phantom.model.fem.kernels"], env=environment, capture_output=True,
                           text=True, timeout=60)
    assert "already built" in again.stdout
    runs = {}
    for mode, extra in (("aot", {}), ("jit", {"PHANTOM_JIT_KERNELS": "1"})):
        out = tmp_path / f"{mode}.npz"
        subprocess.run([sys.executable, "-c", KERNEL_OUTPUTS, str(out)], env=dict(environment, **extra), check=True,
                       timeout=240)
        runs[mode] = dict(np.load(out))
    assert runs["aot"]["aot"] and not runs["aot"]["numba_loaded"]
    assert not runs["jit"]["aot"] and runs["jit"]["numba_loaded"]
    for name, jit_value in runs["jit"].items():
        if name not in ("aot", "numba_loaded"):
            scale = max(np.abs(jit_value).max(), 1e-300)
            assert np.abs(runs["aot"][name] - jit_value).max() <= 1e-12 * scale, name
            assert np.any(jit_value != 0), name


#: One element's forces: compiles (or loads from numba's cache) the kernels the message is about.
ONE_ELEMENT_FORCES = """
import numpy as np
from phantom.model.fem import kernels
nodes = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
tets = np.array([[0, 1, 2, 3]])
dm_inverse, _, stiffness = kernels.element_rest_data(nodes, tets, 1e3, 0.3)
kernels.internal_forces(nodes, nodes, tets, dm_inverse, stiffness, True, 0, np.zeros((1, 12, 12), np.int64),
                        np.zeros(1))
"""


@pytest.mark.slow
def test_numba_forgets_the_kernels_it_compiled_when_the_laws_they_inline_change(tmp_path):
    """With no build ahead of time, importing the kernels says numba will compile them unless numba's cache has
    them: the cache NUMBA_CACHE_DIR names when a parent process set it (pytest, a daemon), not the phantom cache's
    own folder (each process here gets a phantom cache of its own), else a second process announced a compilation
    that never came (a stray second line on stderr).

    numba keys a kernel's cache by the kernel's own file, but the kernels compile in the laws of materials.py:
    a stamp of both files' digest beside numba's cache says whose code it holds, and when it is another's (an
    edited materials.py) the kernels' cache is emptied and compiled again (the message says so), and the stamp
    renewed. (One test for both: each compilation from an empty cache takes tens of seconds.)"""
    import itertools
    import os
    import subprocess
    import sys

    from phantom.model.fem.jit import sources_digest

    numba_cache = tmp_path / "numba"
    message = "compiling the model's kernels with numba"
    runs = itertools.count()

    def announced():
        environment = dict(os.environ, PHANTOM_CACHE_DIR=str(tmp_path / f"cache{next(runs)}"),
                           NUMBA_CACHE_DIR=str(numba_cache), PHANTOM_JIT_KERNELS="1")
        run = subprocess.run([sys.executable, "-c", ONE_ELEMENT_FORCES], env=environment, capture_output=True,
                             text=True, timeout=240)
        assert run.returncode == 0, run.stderr
        return message in run.stderr

    assert announced() and not announced()
    (stamp,) = numba_cache.glob("phantom_fem_sources_*.sha256")
    assert stamp.read_text() == sources_digest()
    stamp.write_text("the digest of an older materials.py")
    assert announced()
    assert stamp.read_text() == sources_digest() and not announced()
