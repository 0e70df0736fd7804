"""The quasi-static finite-element model of the phantom: solve, volumes, compliance (SI units throughout).

Equilibrium minimises the total energy

    Pi(x) = E_elastic(x) + 1/2 sum_fixed k_i |x_i - X_i|^2 - sum_c p_c V_c(x)

over node positions x (m): co-rotational (or small-strain linear) elasticity on linear tetrahedra, penalty
springs on the fixation, and a constant pressure p_c (Pa) in each closed chamber, whose load ``p_c dV_c/dx``
follows the walls. Springs have stiffness ``k_i = FIXED_PENALTY * E * A_i / h`` (A_i the node's share of the
fixed area, h the patch's mean edge length), a dimensionless multiple of E: the solution at (p, E) equals the
one at (p E0 / E, E0). Without a fixed group, a 3-2-1 set of displacement constraints removes rigid motion
only (the pressure load is self-equilibrated, so these carry no force).
"""

import dataclasses
import functools
import hashlib
import os
import tempfile
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

import phantom
from phantom.model.errors import MeshError, SolveError
from phantom.model.fem import kernels
from phantom.model.fem.linsolve import CholeskyFactor, Factorization
from phantom.model.mesh.tetmesh import Surfaces, TetMesh, enclosed_volume_m3, prepare_surfaces, volume_gradient_m2
from phantom.model.scene import HYPERELASTIC_MODELS, MATERIAL_MODELS, Material, Scene

if TYPE_CHECKING:
    import scipy.sparse

# scipy.sparse (0.15 s to import) only where a matrix is factorised or handed out: a warm solve multiplies the
# tangent with its own kernel and back-substitutes a stored factor.

#: Spring stiffness at the fixation as a multiple of E * area / edge length (dimensionless).
FIXED_PENALTY = 1.0e3
#: Newton stops when |residual| <= RELATIVE_TOLERANCE * |pressure load|.
RELATIVE_TOLERANCE = 1e-9
#: Accept a residual this small relative to the load when Newton stops making progress (rounding).
ROUNDING_TOLERANCE = 1e-6
MAX_ITERATIONS_PER_STEP = 40
#: A load step fails when the residual has not halved in this many iterations (past a limit point).
STALLED_ITERATIONS = 6
MAX_LOAD_BISECTIONS = 6
#: A stalled residual within this factor of the rounding floor (eps |diag K| |x|) is blamed on conditioning.
ROUNDING_FLOOR_MARGIN = 1e3
#: Inexact Newton: relative residual of the preconditioned CG solve, and its iteration budget.
KRYLOV_TOLERANCE = 1e-3
KRYLOV_ITERATIONS = 25
#: A Newton step whose residual shrinks by less than this factor triggers a new tangent factorisation.
TANGENT_REFRESH_RATIO = 0.25
#: Bump when the solver's numbers change, so cached compliances are recomputed.
SOLVER_VERSION = 2
FORMULATIONS = MATERIAL_MODELS


@dataclass
class State:
    """A solved equilibrium.

    positions_m : (n, 3) node positions; chamber_volumes_m3 : (n_chambers,); gland_volume_m3 : volume enclosed
    by the outer boundary; iterations : Newton iterations over all load steps; solve_time_s : wall time;
    pressures_pa : (n_chambers,) the gauge pressures solved for; formulation : "corotational" or "linear";
    load_positions_m : (n, 3) or None, for the linear formulation the configuration its (dead) pressure load was
    taken on when that was not the rest shape (None: rest).
    """

    positions_m: np.ndarray
    chamber_volumes_m3: np.ndarray
    gland_volume_m3: float
    iterations: int
    solve_time_s: float
    pressures_pa: np.ndarray
    formulation: str = "corotational"
    load_steps: int = 1
    load_positions_m: np.ndarray | None = None


@dataclass
class Compliance:
    """Volume (and displacement) per unit pressure at one state.

    chamber_m3_per_pa : (n_chambers, n_chambers) symmetric, W_ij = dV_i / dp_j = H_i K^-1 H_j^T;
    gland_m3_per_pa : (n_chambers,) d(gland volume) / dp_j; displacement_m_per_pa : (n_chambers, n_nodes, 3)
    the node displacement per pascal in each chamber (so a shape is ``x + sum_j dp_j displacement[j]``).
    """

    chamber_m3_per_pa: np.ndarray
    gland_m3_per_pa: np.ndarray
    displacement_m_per_pa: np.ndarray


@dataclass
class _Step:
    """Result of one Newton solve at a fixed load."""

    positions_m: np.ndarray
    converged: bool
    iterations: int
    reason: str = ""
    worst_element: int = -1
    #: Newton stopped making progress; the smallest residual it reached and the floating-point floor of the
    #: residual, both relative to the load.
    stalled: bool = False
    residual_ratio: float = 0.0
    rounding_floor_ratio: float = 0.0

    @property
    def ill_conditioned(self) -> bool:
        """Newton stalled (no inverted element) with its residual down at what rounding in the positions alone
        produces, so no iteration or smaller load step can meet the tolerance."""
        return (self.stalled and self.worst_element < 0
                and self.residual_ratio <= ROUNDING_FLOOR_MARGIN * self.rounding_floor_ratio)


@dataclass
class _Pattern:
    """The CSR sparsity of the stiffness and where each element entry and diagonal goes in its data array."""

    indptr: np.ndarray
    indices: np.ndarray
    scatter: np.ndarray
    diagonal: np.ndarray


def _dot(a: np.ndarray, b: np.ndarray) -> float:
    """``a . b`` without BLAS: OpenBLAS level-1 calls spin threads and cost milliseconds on a busy machine."""
    return float(np.einsum("i,i->", a, b))


def _norm(a: np.ndarray) -> float:
    """Euclidean norm without BLAS (see :func:`_dot`)."""
    return float(np.sqrt(np.einsum("i,i->", a, a)))


def _pressure_load(pressures: np.ndarray, gradients: np.ndarray) -> np.ndarray:
    """``sum_c p_c dV_c/dx`` (N, (3n,)) from the chamber rows of the volume gradients (m^2)."""
    return np.einsum("c,cj->j", pressures, gradients[: len(pressures)])


def _preconditioned_cg(multiply, rhs: np.ndarray, preconditioner, tolerance: float,
                       max_iterations: int) -> np.ndarray | None:
    """Solve ``A y = b`` by conjugate gradients preconditioned with a factorised ``M ~ A``; ``multiply(v)`` is
    ``A v``.

    A may be slightly indefinite (a sliver element under follower pressure): CG carries on through a step of
    negative curvature, and the caller checks that the result is a descent direction. Returns None when the
    relative residual does not reach ``tolerance`` in ``max_iterations`` or a curvature vanishes: the caller
    then factorises A itself.
    """
    solution = np.zeros_like(rhs)
    residual = rhs.copy()
    rhs_norm = _norm(rhs)
    preconditioned = preconditioner.solve(residual)
    direction = preconditioned.copy()
    product = _dot(residual, preconditioned)
    for _ in range(max_iterations):
        image = multiply(direction)
        curvature = _dot(direction, image)
        if abs(curvature) <= 1e-14 * _norm(direction) * _norm(image):
            return None
        step = product / curvature
        solution += step * direction
        residual -= step * image
        if _norm(residual) <= tolerance * rhs_norm:
            return solution
        preconditioned = preconditioner.solve(residual)
        new_product = _dot(residual, preconditioned)
        direction = preconditioned + (new_product / product) * direction
        product = new_product
    return None


def _sparse_pattern(tets: np.ndarray, n_nodes: int) -> _Pattern:
    """Build the CSR pattern once; ``scatter[e, i, j]`` is the data index of element e's entry (i, j).

    Built from the node graph (16 pairs per element instead of 144 dof pairs): node i's neighbours j (sorted,
    itself included) give dof row ``3 i + a`` the columns ``3 j + b`` in that order, so the row starts at
    ``9 nnz_before(i) + 3 a degree(i)`` and the pair's k-th neighbour entry sits ``3 k + b`` further on.
    """
    n_tets = len(tets)
    tets = tets.astype(np.int64)
    pair_keys = (tets[:, :, None] * n_nodes + tets[:, None, :]).ravel()
    node_pairs, pair_of = np.unique(pair_keys, return_inverse=True)
    pair_rows, pair_columns = np.divmod(node_pairs, n_nodes)
    degree = np.bincount(pair_rows, minlength=n_nodes)
    node_indptr = np.concatenate([[0], np.cumsum(degree)])
    rank_in_row = np.arange(len(node_pairs)) - node_indptr[pair_rows]
    row_start = 9 * node_indptr[:-1, None] + 3 * degree[:, None] * np.arange(3)
    indptr = np.append(row_start.ravel(), 9 * len(node_pairs)).astype(np.int64)
    axis = np.arange(3)
    entries = row_start[pair_rows][:, :, None] + 3 * rank_in_row[:, None, None] + axis
    indices = np.empty(9 * len(node_pairs), np.int32)
    indices[entries] = np.broadcast_to((3 * pair_columns[:, None, None] + axis), entries.shape)
    rank = rank_in_row[pair_of].reshape(n_tets, 4, 4)
    scatter = (row_start[tets][:, :, :, None, None] + 3 * rank[:, :, None, :, None] + axis)
    self_rank = np.zeros(n_nodes, np.int64)
    on_diagonal = pair_rows == pair_columns
    self_rank[pair_rows[on_diagonal]] = rank_in_row[on_diagonal]
    diagonal = (row_start + 3 * self_rank[:, None] + axis).ravel()
    return _Pattern(indptr, indices, scatter.reshape(n_tets, 12, 12), diagonal)


@dataclass
class _Constraints:
    """Held dofs (3-2-1, removing rigid motion) and the CSR data entries in their rows and columns."""

    dofs: np.ndarray
    free_mask: np.ndarray
    entries: np.ndarray

    @property
    def key(self) -> tuple:
        return tuple(self.dofs.tolist())


def _rigid_constraints(nodes_m: np.ndarray) -> np.ndarray:
    """Six dofs (3-2-1) whose fixing removes rigid motion only: all of A, two of B, one of C.

    A and B are the extreme nodes along x; C is the node farthest from line AB. B keeps its dof along AB's
    dominant axis, C is held along the axis in which a rotation about AB moves it most.
    """
    node_a, node_b = int(np.argmin(nodes_m[:, 0])), int(np.argmax(nodes_m[:, 0]))
    axis_ab = nodes_m[node_b] - nodes_m[node_a]
    axis_ab /= np.linalg.norm(axis_ab)
    offsets = nodes_m - nodes_m[node_a]
    perpendicular = offsets - np.outer(offsets @ axis_ab, axis_ab)
    node_c = int(np.argmax(np.linalg.norm(perpendicular, axis=1)))
    free_b = int(np.argmax(np.abs(axis_ab)))
    swing = np.cross(axis_ab, perpendicular[node_c])
    held_c = int(np.argmax(np.abs(swing)))
    dofs = [3 * node_a, 3 * node_a + 1, 3 * node_a + 2]
    dofs += [3 * node_b + k for k in range(3) if k != free_b]
    dofs.append(3 * node_c + held_c)
    return np.array(dofs, np.int64)


def _spring_stiffness(nodes_m: np.ndarray, fixed_triangles: np.ndarray, youngs_modulus_pa: float) -> tuple:
    """Fixed nodes and their spring stiffness ``FIXED_PENALTY * E * A_i / h`` (N/m)."""
    x0, x1, x2 = (nodes_m[fixed_triangles[:, k]] for k in range(3))
    areas_m2 = 0.5 * np.linalg.norm(np.cross(x1 - x0, x2 - x0), axis=1)
    edge_m = np.mean(np.linalg.norm(np.stack([x1 - x0, x2 - x1, x0 - x2]), axis=2))
    node_area_m2 = np.bincount(fixed_triangles.ravel(), np.repeat(areas_m2 / 3.0, 3), len(nodes_m))
    fixed_nodes = np.unique(fixed_triangles)
    return fixed_nodes, FIXED_PENALTY * youngs_modulus_pa * node_area_m2[fixed_nodes] / edge_m


class PhantomModel:
    """The phantom's finite-element model (mesh, material, fixation); see the module docstring.

    Build with :meth:`from_scene`. Attributes: ``chamber_names``, ``n_chambers``, ``nodes_m`` (n, 3) rest
    positions, ``tets`` (m, 4), ``outer_triangles`` (k, 3) outward, ``chamber_triangles`` (list, each
    oriented out of its cavity), ``rest_chamber_volumes_m3``, ``rest_gland_volume_m3``, ``material``,
    ``formulation`` (the scene's), ``scene`` (the Scene it was built from, None for a bare mesh: the inverse
    and the volume estimator read its ``[model]`` table).
    """

    def __init__(self, mesh: TetMesh, surfaces: Surfaces, chamber_names: list[str], material: Material,
                 source: str = "mesh", linear_solver: str | None = None, scene: Scene | None = None):
        if not 0 < material.youngs_modulus_pa < np.inf or not -1.0 < material.poisson_ratio < 0.5:
            raise SolveError(f"material out of range: E = {material.youngs_modulus_pa} Pa (> 0), "
                             f"nu = {material.poisson_ratio} (in (-1, 0.5))")
        if material.model not in FORMULATIONS:
            raise SolveError(f"unknown material model {material.model!r}: use one of {', '.join(FORMULATIONS)}")
        if material.gent_jm is not None and not 0 < material.gent_jm < np.inf:
            raise SolveError(f"material out of range: gent_jm = {material.gent_jm} (a positive number)")
        if material.model == "gent" and material.gent_jm is None:
            raise SolveError("the Gent material needs gent_jm, the locking value of I1 - 3 (e.g. 20)")
        self.mesh = mesh
        self.source = source
        self.scene = scene
        self.nodes_m = mesh.nodes_m
        self.tets = mesh.tets
        self.chamber_names = list(chamber_names)
        self.n_chambers = len(chamber_names)
        self.chamber_triangles = surfaces.chamber_triangles
        self.outer_triangles = surfaces.outer_triangles
        self.fixed_triangles = surfaces.fixed_triangles
        self.material = material
        self.formulation = material.model
        self.linear_solver = linear_solver
        self.rest_chamber_volumes_m3, self.rest_gland_volume_m3 = self.volumes(self.nodes_m)
        for name, volume in zip(self.chamber_names, self.rest_chamber_volumes_m3, strict=True):
            if volume <= 0:
                raise MeshError(f"{source}: chamber {name!r} encloses no volume ({volume:.3g} m^3)")
        self._dm_inverse, self._element_volumes_m3, self._element_stiffness = kernels.element_rest_data(
            self.nodes_m, self.tets, material.youngs_modulus_pa, material.poisson_ratio)
        self._pattern = _sparse_pattern(self.tets, len(self.nodes_m))
        if self.fixed_triangles is None:
            self._fixed_nodes, self._spring_n_per_m = np.zeros(0, np.int64), np.zeros(0)
        else:
            self._fixed_nodes, self._spring_n_per_m = _spring_stiffness(
                self.nodes_m, self.fixed_triangles, material.youngs_modulus_pa)
        self._factorizations: dict[tuple, Factorization | CholeskyFactor] = {}
        self._constraint_sets: dict[tuple, _Constraints] = {}
        self._rest_constraints = self._constraints_for(self.nodes_m)

    @property
    def held_dofs(self) -> np.ndarray:
        """Dofs (3 node + axis) held at rest to remove rigid motion when there is no fixed group (else empty)."""
        return self._rest_constraints.dofs

    def _constraints_for(self, positions_m: np.ndarray) -> _Constraints:
        """No held dofs when springs hold the fixation; else a 3-2-1 set chosen in this configuration's frame
        (so that a rigidly rotated start is held as the rest shape would be)."""
        n_dofs = 3 * len(self.nodes_m)
        dofs = np.zeros(0, np.int64) if self.fixed_triangles is not None else _rigid_constraints(positions_m)
        key = tuple(dofs.tolist())
        if key not in self._constraint_sets:
            free_mask = np.ones(n_dofs, bool)
            free_mask[dofs] = False
            entries = dofs
            if len(dofs):
                rows = np.repeat(np.arange(n_dofs), np.diff(self._pattern.indptr))
                entries = np.flatnonzero(~free_mask[rows] | ~free_mask[self._pattern.indices])
            self._constraint_sets[key] = _Constraints(dofs, free_mask, entries)
        return self._constraint_sets[key]

    @classmethod
    def from_scene(cls, scene: Scene, mesh_size_mm: float | None = None) -> "PhantomModel":
        """The model of a scene; the built-in mesh comes from the on-disk cache when it was made before."""
        from phantom.model.mesh.prostate import builtin_prostate
        from phantom.model.mesh.tetmesh import read_mesh

        if scene.mesh == "builtin:prostate":
            if scene.units != "mm":
                raise MeshError(f"the built-in mesh is in millimetres: set [phantom] units = \"mm\" (not "
                                f"{scene.units!r})")
            mesh, source = builtin_prostate(mesh_size_mm, scene.geometry), "builtin:prostate"
        else:
            if mesh_size_mm is not None:
                raise MeshError(f"mesh_size_mm applies to the built-in mesh only; {scene.mesh} is read as it is")
            mesh, source = read_mesh(scene.mesh, scene.length_scale_m), scene.mesh
        surfaces = prepare_surfaces(mesh, scene.chambers, scene.fixed, source)
        return cls(mesh, surfaces, scene.chambers, scene.material, source, scene=scene)

    def with_material(self, youngs_modulus_pa: float | None = None, poisson_ratio: float | None = None,
                      model: str | None = None, gent_jm: float | None = None) -> "PhantomModel":
        """The same mesh, fixation and scene settings with another material (modulus in Pa; ``gent_jm`` for
        model "gent", kept from the current material when not given)."""
        model = model or self.material.model
        if gent_jm is None and model == "gent":
            gent_jm = self.material.gent_jm
        material = Material(
            model,
            self.material.youngs_modulus_pa if youngs_modulus_pa is None else float(youngs_modulus_pa),
            self.material.poisson_ratio if poisson_ratio is None else float(poisson_ratio),
            None if model != "gent" or gent_jm is None else float(gent_jm),
        )
        surfaces = Surfaces(self.chamber_triangles, self.outer_triangles, self.fixed_triangles)
        scene = None if self.scene is None else dataclasses.replace(self.scene, material=material)
        return PhantomModel(self.mesh, surfaces, self.chamber_names, material, self.source, self.linear_solver, scene)

    # --- deformed shapes ---------------------------------------------------------------------------------

    def deformed_mesh(self, state: State) -> TetMesh:
        """The model's tetrahedral mesh at ``state`` (same node order, tetrahedra and surface groups as the
        rest mesh; positions in m), e.g. for ``mesh.write_mesh``."""
        return TetMesh(np.array(state.positions_m, float), self.tets, dict(self.mesh.surface_groups))

    def deformed_surface(self, pressures_pa, formulation: str | None = None,
                         initial_positions_m: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """The outer surface deformed by gauge pressures (Pa, chamber order): ``(positions_mm, triangles)``,
        the surface's own nodes (k, 3) in millimetres and its triangles (t, 3) indexing them, normals outward.

        Solves like :meth:`solve` (same arguments and errors). The surface's node order is fixed for a model
        (``np.unique`` of the outer triangles), so successive calls can be drawn as one changing mesh.
        """
        state = self.solve(pressures_pa, formulation=formulation, initial_positions_m=initial_positions_m)
        surface_nodes, triangles = self.outer_surface()
        return state.positions_m[surface_nodes] * 1e3, triangles

    def outer_surface(self) -> tuple[np.ndarray, np.ndarray]:
        """The outer surface as a mesh of its own: ``(surface_nodes, triangles)``, the indices of the model's
        nodes on it (sorted) and the outer triangles renumbered into them. Drawing only these keeps a mesh small.
        """
        surface_nodes, triangles = np.unique(self.outer_triangles, return_inverse=True)
        return surface_nodes, triangles.reshape(-1, 3)

    # --- volumes and loads -------------------------------------------------------------------------------

    def volumes(self, positions_m: np.ndarray) -> tuple[np.ndarray, float]:
        """Chamber volumes (m^3, chamber order) and the gland volume (m^3, inside the outer boundary)."""
        chambers = np.array([enclosed_volume_m3(positions_m, t) for t in self.chamber_triangles])
        return chambers, enclosed_volume_m3(positions_m, self.outer_triangles)

    def volume_gradients(self, positions_m: np.ndarray) -> np.ndarray:
        """``H``: (n_chambers + 1, 3 n) gradients of each chamber's volume and of the gland's (m^2)."""
        surfaces = [*self.chamber_triangles, self.outer_triangles]
        return np.stack([volume_gradient_m2(positions_m, t).ravel() for t in surfaces])

    # --- assembly --------------------------------------------------------------------------------------------

    def _elastic(self, positions_m: np.ndarray, formulation: str, matrix: int, constraints: _Constraints,
                 pressures: np.ndarray | None = None):
        """Elastic + spring forces (3n,), energy (J, +inf outside a hyperelastic law's domain), smallest det F,
        and, when ``matrix``, the CSR data of the tangent: 1 = ``R K R^T`` (co-rotational, positive definite),
        2 = the exact Hessian (co-rotational or hyperelastic), including the pressure's follower-load stiffness
        when ``pressures`` (Pa) are given; the linear model's is its stiffness either way."""
        data = np.zeros(len(self._pattern.indices)) if matrix else np.zeros(1)
        if formulation in HYPERELASTIC_MODELS:
            forces, energy_j, smallest_det = kernels.hyperelastic_forces(
                positions_m, self.tets, self._dm_inverse, self._element_volumes_m3, self.material.lame_mu_pa,
                self.material.lame_lambda_pa, self._inverse_jm(formulation), 2 if matrix else 0,
                self._pattern.scatter, data)
        else:
            forces, energy_j, smallest_det = kernels.internal_forces(
                positions_m, self.nodes_m, self.tets, self._dm_inverse, self._element_stiffness,
                formulation == "corotational", matrix, self._pattern.scatter, data)
        stretch = positions_m[self._fixed_nodes] - self.nodes_m[self._fixed_nodes]
        forces[self._fixed_nodes] += self._spring_n_per_m[:, None] * stretch
        energy_j += 0.5 * float(np.sum(self._spring_n_per_m[:, None] * stretch**2))
        forces = forces.ravel()
        forces[constraints.dofs] = 0.0
        if matrix:
            if matrix == 2 and pressures is not None:
                for pressure_pa, triangles in zip(pressures, self.chamber_triangles, strict=True):
                    kernels.add_pressure_stiffness(positions_m, triangles, pressure_pa, self._pattern.indptr,
                                                   self._pattern.indices, data)
            spring_dofs = (3 * self._fixed_nodes[:, None] + np.arange(3)).ravel()
            data[self._pattern.diagonal[spring_dofs]] += np.repeat(self._spring_n_per_m, 3)
            if len(constraints.dofs):
                scale = float(np.mean(data[self._pattern.diagonal]))
                data[constraints.entries] = 0.0
                data[self._pattern.diagonal[constraints.dofs]] = scale
        return forces, energy_j, smallest_det, data

    def _inverse_jm(self, formulation: str) -> float:
        """1 / Jm of the Gent law (0 for Neo-Hookean)."""
        if formulation != "gent":
            return 0.0
        if self.material.gent_jm is None:
            raise SolveError("the Gent formulation needs the material's gent_jm (scene [material] gent_jm)")
        return 1.0 / self.material.gent_jm

    def _factorize(self, data: np.ndarray, positive_definite: bool = True) -> Factorization:
        """Factorise a matrix of the model's pattern: ``linear_solver`` (None: the measured default) when it is
        positive definite, SuperLU when it may not be."""
        return Factorization(self._csr(data), self.linear_solver if positive_definite else "splu-mmd")

    def _csr(self, data: np.ndarray):
        """The scipy CSR matrix of the model's pattern with entries ``data``."""
        import scipy.sparse as sp

        n_dofs = 3 * len(self.nodes_m)
        return sp.csr_matrix((data, self._pattern.indices, self._pattern.indptr), shape=(n_dofs, n_dofs))

    def rest_factorization(self, constraints: _Constraints | None = None) -> Factorization | CholeskyFactor:
        """The factorised small-strain stiffness (elastic + springs + constraints), made once per model.

        A Cholesky factor is also kept on disk (``phantom.cache_dir("factorizations")``), keyed by everything
        but E: the stiffness is proportional to E, so one factor serves every modulus (rescaled), and a new
        process or a calibration loop does not factorise again.
        """
        constraints = constraints or self._rest_constraints
        if constraints.key not in self._factorizations:
            self._factorizations[constraints.key] = self._stored_rest_factorization(constraints)
        return self._factorizations[constraints.key]

    def _stored_rest_factorization(self, constraints: _Constraints) -> Factorization | CholeskyFactor:
        digest = hashlib.sha256()
        springs_per_pa = self._spring_n_per_m / self.material.youngs_modulus_pa
        for array in (self.nodes_m, self.tets, self._fixed_nodes, springs_per_pa, constraints.dofs):
            digest.update(np.ascontiguousarray(array).tobytes())
        digest.update(repr((self.material.poisson_ratio, FIXED_PENALTY, SOLVER_VERSION)).encode())
        path = phantom.cache_dir("factorizations") / f"{digest.hexdigest()[:32]}.npz"
        if path.is_file():
            try:
                with np.load(path) as stored:
                    scale = float(stored["youngs_modulus_pa"]) / self.material.youngs_modulus_pa
                    return CholeskyFactor(stored["indptr"], stored["indices"], stored["values"],
                                          stored["permutation"], scale)
            except (OSError, ValueError, KeyError):
                path.unlink(missing_ok=True)
        _, _, _, data = self._elastic(self.nodes_m, "linear", 1, constraints)
        factorization = self._factorize(data)
        if factorization.method == "cholmod":
            handle, temporary = tempfile.mkstemp(dir=path.parent, suffix=".npz")
            os.close(handle)
            arrays = factorization.cholesky.arrays()
            arrays["indices"] = arrays["indices"].astype(np.int32)
            np.savez(temporary, youngs_modulus_pa=self.material.youngs_modulus_pa, **arrays)
            os.replace(temporary, path)
        return factorization

    def stiffness_matrix(self, positions_m: np.ndarray | None = None, formulation: str = "linear",
                         pressures_pa=None, constraints: _Constraints | None = None) -> "scipy.sparse.csr_matrix":
        """The assembled tangent (N/m, CSR; held dofs replaced by scaled identity rows) at ``positions_m``.

        "linear": the small-strain stiffness; "corotational", "neo_hookean", "gent": the exact Hessian of the total
        energy, with the follower-load stiffness of ``pressures_pa`` when given.
        """
        return self._csr(self._tangent_data(positions_m, formulation, pressures_pa, constraints))

    def _tangent_data(self, positions_m=None, formulation="linear", pressures_pa=None, constraints=None):
        """The CSR data of :meth:`stiffness_matrix` (same arguments), in the model's pattern."""
        positions_m = self.nodes_m if positions_m is None else positions_m
        pressures = None if pressures_pa is None else self._check_pressures(pressures_pa)
        _, _, _, data = self._elastic(positions_m, formulation, 1 if formulation == "linear" else 2,
                                      constraints or self._rest_constraints, pressures)
        return data

    # --- solve -------------------------------------------------------------------------------------------

    def _check_pressures(self, pressures_pa) -> np.ndarray:
        pressures = np.asarray(pressures_pa, dtype=float).ravel()
        if pressures.shape != (self.n_chambers,):
            raise SolveError(f"expected {self.n_chambers} chamber pressures ({', '.join(self.chamber_names)}), "
                             f"got {pressures.size}")
        if not np.all(np.isfinite(pressures)):
            raise SolveError(f"chamber pressures must be finite numbers, got {pressures.tolist()} Pa")
        return pressures

    def solve(self, pressures_pa, formulation: str | None = None, initial_positions_m: np.ndarray | None = None,
              tolerance: float = RELATIVE_TOLERANCE) -> State:
        """Equilibrium under gauge pressures (Pa, chamber order).

        ``formulation`` None uses the scene's; "linear" is small-strain elasticity with the pressure load taken
        on the starting configuration (one linear solve); "corotational" follows the walls and is solved by
        Newton iterations with a line search on the total energy, cutting the load into steps when a full
        step fails. ``initial_positions_m`` starts from another configuration (default: rest); for a hyperelastic
        law Newton at the full load is tried from there first (it converges in a few iterations from a nearby
        equilibrium), path following from zero load when it does not converge.
        Raises SolveError (naming the chamber and pressure) when it cannot converge or elements invert.
        """
        started = time.perf_counter()
        pressures = self._check_pressures(pressures_pa)
        formulation = formulation or self.formulation
        if formulation not in FORMULATIONS:
            raise SolveError(f"unknown formulation {formulation!r}: use one of {', '.join(FORMULATIONS)}")
        self._inverse_jm(formulation)
        start_m = self.nodes_m.copy() if initial_positions_m is None else np.array(initial_positions_m, float)
        if start_m.shape != self.nodes_m.shape or not np.all(np.isfinite(start_m)):
            raise SolveError(f"initial_positions_m must be a finite array of shape {self.nodes_m.shape}")
        positions_m, iterations, steps = start_m, 0, 0
        if np.any(pressures) or initial_positions_m is not None:
            # The linear model's stiffness is that of the rest shape: its rigid modes are held in that frame.
            frame_m = self.nodes_m if formulation == "linear" else start_m
            constraints = self._constraints_for(frame_m)
            warm = None
            if initial_positions_m is not None and formulation in HYPERELASTIC_MODELS and np.any(pressures):
                # From a nearby equilibrium (an iteration's previous answer) Newton at the full load takes a few
                # iterations; path following would start again from zero load on the inflated shape.
                warm = self._newton(start_m, pressures, formulation, start_m, tolerance, constraints)
            if warm is not None and warm.converged:
                positions_m, iterations, steps = warm.positions_m, warm.iterations, 1
            else:
                positions_m, iterations, steps = self._continuation(start_m, pressures, formulation, tolerance,
                                                                    constraints)
        chamber_volumes_m3, gland_volume_m3 = self.volumes(positions_m)
        load_positions_m = start_m if formulation == "linear" and initial_positions_m is not None else None
        return State(positions_m, chamber_volumes_m3, gland_volume_m3, iterations,
                     time.perf_counter() - started, pressures, formulation, steps, load_positions_m)

    def _continuation(self, start_m, pressures, formulation, tolerance, constraints) -> tuple[np.ndarray, int, int]:
        """Path following from 0 to the full pressures (``pathfollow``): load steps with a secant predictor,
        volume control past where a chamber's pressure-volume curve flattens."""
        from phantom.model.fem.pathfollow import follow_path

        return follow_path(self, start_m, pressures, formulation, tolerance, constraints)

    def _failure(self, pressures, target, step: _Step) -> SolveError:
        """A SolveError that names the chamber most likely at fault, the pressure, and what to try; or, when
        the residual stalled at its rounding floor, the ill-conditioning and the penalty factor behind it."""
        pressures_kpa = ", ".join(f"{p / 1e3:g}" for p in pressures)
        if step.ill_conditioned:
            return SolveError(
                f"the stiffness is ill-conditioned: at pressures ({pressures_kpa}) kPa Newton's residual stagnated "
                f"at {step.residual_ratio:.2g} of the load, the floor that rounding the node positions alone "
                f"gives ({step.rounding_floor_ratio:.2g}: stiffness diagonal ratio {self._diagonal_ratio():.2g}, "
                f"condition number at least that), while the tolerance is {RELATIVE_TOLERANCE:g}; the fixation "
                f"springs are FIXED_PENALTY = {FIXED_PENALTY:g} times E: use a lower penalty factor (the default "
                f"1e3 already clamps the fixed patch; 1e6 converges)")
        chamber = int(np.argmax(np.abs(pressures)))
        if step.worst_element >= 0:
            centroid = self.nodes_m[self.tets[step.worst_element]].mean(axis=0)
            distances = [np.min(np.linalg.norm(self.nodes_m[np.unique(t)] - centroid, axis=1))
                         for t in self.chamber_triangles]
            chamber = int(np.argmin(distances))
        ratio = abs(pressures[chamber]) / self.material.youngs_modulus_pa
        return SolveError(
            f"the {step.reason} at pressures ({pressures_kpa}) kPa, near chamber {chamber} "
            f"({self.chamber_names[chamber]!r} at {pressures[chamber] / 1e3:g} kPa, p/E = {ratio:.3g}; reached "
            f"{100 * target:.0f} % of the load as a trial step): try a lower pressure in that chamber, a finer "
            f"mesh (--size-mm), or a stiffer material")

    def _load_and_energy(self, positions_m, pressures, formulation, start_m):
        """Pressure load (3n,) and its potential (J): ``sum p dV/dx`` and ``-sum p V`` (follower), or the
        dead load ``sum p dV/dx(start)`` and ``-load . x`` (linear)."""
        if formulation == "linear":
            load = _pressure_load(pressures, self.volume_gradients(start_m))
            return load, -_dot(load, positions_m.ravel())
        load = _pressure_load(pressures, self.volume_gradients(positions_m))
        chamber_volumes_m3 = np.array([enclosed_volume_m3(positions_m, t) for t in self.chamber_triangles])
        return load, -float(pressures @ chamber_volumes_m3)

    def _newton(self, start_positions_m, pressures, formulation, reference_m, tolerance, constraints,
                initial_imbalance=False) -> _Step:
        """Newton iterations with a backtracking line search on the total energy at one load.

        Converged when the residual is below ``tolerance`` times the load (or times the starting residual when
        ``initial_imbalance``, for a start that is not in equilibrium at zero load, e.g. rotated).
        """
        nonlinear = formulation != "linear"
        positions_m = start_positions_m
        arguments = (pressures, formulation, reference_m, constraints)
        residual, energy, _, hessian = self._residual(positions_m, *arguments)
        # Relative to the load, or to the starting imbalance when that is larger (a start far from rest).
        load_scale = max(_norm(_pressure_load(pressures, self.volume_gradients(reference_m))[constraints.free_mask]),
                         _norm(residual) if initial_imbalance else 0.0,
                         1e-12 * self.material.youngs_modulus_pa * self._length_scale_m**2)
        # Directions, cheapest first: "krylov" solves with the exact Hessian by conjugate gradients
        # preconditioned with the rest stiffness (factorised once per model: no factorisation per solve);
        # "exact" factorises the Hessian here; "positive" factorises R K R^T (positive definite: a descent
        # direction whenever the Hessian is not). The linear model's rest stiffness is its exact tangent.
        if not nonlinear:
            kind, factorization = "rest", self.rest_factorization(constraints)
        elif constraints.key == self._rest_constraints.key:
            kind, factorization = "krylov", self.rest_factorization(constraints)
        else:
            kind, factorization = "exact", self._tangent(positions_m, formulation, constraints, pressures, exact=True)
        previous_norm = best_norm = np.inf
        best_iteration = 0
        for iteration in range(1, MAX_ITERATIONS_PER_STEP + 1):
            residual_norm = _norm(residual)
            # Converged at the tolerance, or where rounding stops progress (tiny loads: forces are computed
            # from positions of order the phantom's size) once within ROUNDING_TOLERANCE of the load.
            stalled = residual_norm > 0.5 * previous_norm and residual_norm <= ROUNDING_TOLERANCE * load_scale
            if residual_norm <= tolerance * load_scale or stalled:
                return _Step(positions_m, True, iteration - 1)
            if residual_norm < 0.5 * best_norm:
                best_norm, best_iteration = residual_norm, iteration
            elif iteration - best_iteration >= STALLED_ITERATIONS:
                return _Step(positions_m, False, iteration, f"solve stopped converging after {iteration} iterations",
                             self._worst_element(positions_m), True, best_norm / load_scale,
                             self._rounding_floor_n(positions_m) / load_scale)
            previous_norm = residual_norm
            if kind == "krylov":
                if hessian is None:
                    hessian = self._tangent_data(positions_m, formulation, pressures, constraints)
                multiply = functools.partial(kernels.csr_multiply, self._pattern.indptr, self._pattern.indices, hessian)
                direction = _preconditioned_cg(multiply, -residual, factorization, KRYLOV_TOLERANCE, KRYLOV_ITERATIONS)
            else:
                direction = -factorization.solve(residual)
            accepted, slope = None, 0.0
            if direction is not None:
                direction = direction.reshape(-1, 3)
                slope = _dot(residual, direction.ravel())
            if slope < 0.0:
                accepted = self._line_search(positions_m, direction, residual_norm, energy, slope, arguments,
                                             with_tangent=kind == "krylov")
            if accepted is None:
                if not nonlinear or kind == "positive":
                    worst = self._worst_element(positions_m + direction)
                    reason = "solve inverted elements" if worst >= 0 else "line search found no descent"
                    return _Step(positions_m, False, iteration, reason, worst)
                kind = "exact" if kind in ("rest", "krylov") else "positive"
                factorization = self._tangent(positions_m, formulation, constraints, pressures, exact=kind == "exact")
                continue
            positions_m, residual, energy, hessian = accepted
            if kind != "krylov" and nonlinear and _norm(residual) > TANGENT_REFRESH_RATIO * residual_norm:
                kind, factorization = "exact", self._tangent(positions_m, formulation, constraints, pressures,
                                                             exact=True)
        return _Step(positions_m, False, MAX_ITERATIONS_PER_STEP, "solve did not converge in "
                     f"{MAX_ITERATIONS_PER_STEP} iterations", self._worst_element(positions_m))

    def _rest_diagonal_n_per_m(self) -> np.ndarray:
        """Diagonal of the small-strain stiffness with the springs (N/m) at the free dofs."""
        _, _, _, data = self._elastic(self.nodes_m, "linear", 1, self._rest_constraints)
        return data[self._pattern.diagonal][self._rest_constraints.free_mask]

    def _rounding_floor_n(self, positions_m: np.ndarray) -> float:
        """The residual (N) that rounding the positions to double precision alone produces: each force is a
        stiffness times a position known to ``eps |x|``, so ``eps |diag(K) |x||`` is as low as Newton can go."""
        free = self._rest_constraints.free_mask
        return float(np.finfo(float).eps * _norm(self._rest_diagonal_n_per_m() * np.abs(positions_m.ravel()[free])))

    def _diagonal_ratio(self) -> float:
        """Largest over smallest stiffness diagonal entry: a lower bound of the condition number."""
        diagonal = self._rest_diagonal_n_per_m()
        return float(diagonal.max() / diagonal.min())

    @property
    def _length_scale_m(self) -> float:
        return float(np.cbrt(self.rest_gland_volume_m3))

    def _tangent(self, positions_m, formulation, constraints, pressures, exact: bool):
        """Factorised tangent: the exact Hessian, or (``exact`` False) a positive definite stand-in that still
        gives a descent direction: R K R^T (co-rotational) or the small-strain stiffness (hyperelastic)."""
        if not exact and formulation in HYPERELASTIC_MODELS:
            return self.rest_factorization(constraints)
        _, _, _, data = self._elastic(positions_m, formulation, 2 if exact else 1, constraints, pressures)
        try:
            return self._factorize(data, positive_definite=not exact)
        except (RuntimeError, ArithmeticError):  # an exactly singular Hessian (at a limit point)
            if not exact:
                raise
            return self._tangent(positions_m, formulation, constraints, pressures, exact=False)

    def _residual(self, positions_m, pressures, formulation, reference_m, constraints, with_tangent=False):
        """Out-of-balance force (3n,), total energy (J) and the smallest det F (inf for the linear model); with
        ``with_tangent``, also the exact tangent's CSR data from the same element pass (else None)."""
        forces, elastic_energy, smallest_det, tangent = self._elastic(
            positions_m, formulation, 2 if with_tangent else 0, constraints, pressures if with_tangent else None)
        load, load_energy = self._load_and_energy(positions_m, pressures, formulation, reference_m)
        residual = forces - load
        residual[constraints.dofs] = 0.0
        return residual, elastic_energy + load_energy, smallest_det, tangent if with_tangent else None

    def _line_search(self, positions_m, direction, residual_norm, energy, slope, arguments, with_tangent=False):
        """Backtrack from the full step until the energy decreases (Armijo) or, where energy differences are
        lost in rounding, the residual does; never accept a step that inverts an element. With
        ``with_tangent`` the full step (accepted almost always near convergence) also assembles the tangent in
        the same element pass, so the next Newton direction needs no second pass over the elements."""
        step = 1.0
        rounding = 1e-13 * (abs(energy) + abs(slope))
        for attempt in range(12):
            trial = positions_m + step * direction
            residual, trial_energy, smallest_det, tangent = self._residual(
                trial, *arguments, with_tangent=with_tangent and attempt == 0)
            admissible = smallest_det > 0 and np.isfinite(trial_energy)
            if admissible and (trial_energy <= energy + 1e-4 * step * slope + rounding
                               or _norm(residual) < residual_norm):
                return trial, residual, trial_energy, tangent
            step *= 0.5
        return None

    def _worst_element(self, positions_m) -> int:
        """The element with the smallest det F if any is flat or inverted, else -1."""
        dets = kernels.deformation_determinants(positions_m, self.tets, self._dm_inverse)
        worst = int(np.argmin(dets))
        return worst if dets[worst] <= 0 else -1

    # --- compliance ----------------------------------------------------------------------------------------

    def _cache_key(self, extra: bytes = b"") -> str:
        digest = hashlib.sha256()
        for array in (self.nodes_m, self.tets, *self.chamber_triangles, self.outer_triangles, self._fixed_nodes,
                      self._spring_n_per_m, self._rest_constraints.dofs):
            digest.update(np.ascontiguousarray(array).tobytes())
        digest.update(repr((self.material.youngs_modulus_pa, self.material.poisson_ratio, self.material.gent_jm,
                            FIXED_PENALTY, SOLVER_VERSION)).encode())
        digest.update(extra)
        return digest.hexdigest()[:32]

    def compliance(self, state: State | None = None) -> Compliance:
        """Compliance at rest (``W = H K^-1 H^T`` with the rest stiffness) or the tangent at ``state``.

        At a co-rotational state the derivative of the nonlinear solution with respect to each chamber's
        pressure is taken by central differences of re-solves started from the state (step 1 % of the largest
        pressure, at least 1e-4 E), which includes the rotation and follower-load terms the Newton tangent leaves
        out. Cached on disk (``phantom.cache_dir("compliance")``) by a hash of mesh, material, solver and state.

        At a linear (small-strain) state ``x = X + K^-1 H(x_L)^T p``, with the rest stiffness K and the load
        taken on the solve's starting shape ``x_L`` (rest unless ``state.load_positions_m``), so the displacement
        per pascal ``D = K^-1 H(x_L)^T`` does not depend on p and the tangent is exactly
        ``dV_i/dp_j = H_i(x) . D_j``: the rest displacement, with the volume gradients of the deformed state
        (the volume measure's own nonlinearity). Re-solving from the state would take the load on the deformed
        shape instead, which is another problem. One back-substitution (none from rest), so not cached.

        At a hyperelastic (Neo-Hookean, Gent) state the law's Hessian is exact, follower-load stiffness
        included, so the tangent is ``D = K_t(x, p)^-1 H(x)^T``, ``dV_i/dp_j = H_i(x) . D_j``: one factorisation,
        which agrees with the central differences to their truncation error (tested) at a fraction of the cost
        (six path-following re-solves). Not cached either.
        """
        if state is not None and state.formulation == "linear":
            return self._linear_state_compliance(state)
        if state is not None and state.formulation in HYPERELASTIC_MODELS:
            return self._hyperelastic_state_compliance(state)
        extra = b"rest"
        if state is not None:
            extra = (state.formulation.encode() + np.ascontiguousarray(state.pressures_pa).tobytes()
                     + np.ascontiguousarray(state.positions_m).tobytes())
        path = phantom.cache_dir("compliance") / f"{self._cache_key(extra)}.npz"
        if path.is_file():
            try:
                with np.load(path) as stored:
                    return Compliance(stored["chamber"], stored["gland"], stored["displacement"])
            except (OSError, ValueError, KeyError):
                path.unlink(missing_ok=True)
        result = self._rest_compliance() if state is None else self._state_compliance(state)
        handle, temporary = tempfile.mkstemp(dir=path.parent, suffix=".npz")
        os.close(handle)
        np.savez(temporary, chamber=result.chamber_m3_per_pa, gland=result.gland_m3_per_pa,
                 displacement=result.displacement_m_per_pa)
        os.replace(temporary, path)
        return result

    def _rest_compliance(self) -> Compliance:
        displacement = self._small_strain_displacement(self.nodes_m)
        return self._compliance_of(displacement, self.nodes_m)

    def _small_strain_displacement(self, load_positions_m: np.ndarray) -> np.ndarray:
        """``D = K^-1 H(x_L)^T`` (n_chambers, 3n), m/Pa: the small-strain displacement per pascal of each chamber
        with the load taken on ``load_positions_m`` (held dofs do not move)."""
        gradients = self.volume_gradients(load_positions_m)[:-1]
        held = ~self._rest_constraints.free_mask
        gradients[:, held] = 0.0
        displacement = self.rest_factorization().solve(gradients.T).T
        displacement[:, held] = 0.0
        return displacement

    def _compliance_of(self, displacement: np.ndarray, positions_m: np.ndarray) -> Compliance:
        """Volume derivatives ``H(x) D^T`` at ``positions_m`` for a displacement per pascal ``D`` (n_chambers, 3n)."""
        gradients = self.volume_gradients(positions_m)
        return Compliance(gradients[:-1] @ displacement.T, gradients[-1] @ displacement.T,
                          displacement.reshape(self.n_chambers, -1, 3))

    def _linear_state_compliance(self, state: State) -> Compliance:
        if state.load_positions_m is None:
            displacement = self.compliance().displacement_m_per_pa.reshape(self.n_chambers, -1)
        else:
            displacement = self._small_strain_displacement(np.asarray(state.load_positions_m, float))
        return self._compliance_of(displacement, state.positions_m)

    def _hyperelastic_state_compliance(self, state: State) -> Compliance:
        from phantom.model.fidelity.levels import tangent_displacement_m_per_pa

        displacement = tangent_displacement_m_per_pa(self, np.asarray(state.positions_m, float),
                                                     np.asarray(state.pressures_pa, float), state.formulation)
        return self._compliance_of(displacement.reshape(self.n_chambers, -1), state.positions_m)

    def _state_compliance(self, state: State) -> Compliance:
        step_pa = max(1e-2 * float(np.max(np.abs(state.pressures_pa))), 1e-4 * self.material.youngs_modulus_pa)
        chamber = np.empty((self.n_chambers, self.n_chambers))
        gland = np.empty(self.n_chambers)
        displacement = np.empty((self.n_chambers, *self.nodes_m.shape))
        for j in range(self.n_chambers):
            solutions = []
            for sign in (1.0, -1.0):
                pressures = state.pressures_pa.copy()
                pressures[j] += sign * step_pa
                solutions.append(self._continuation(state.positions_m, pressures, state.formulation, 1e-11,
                                                    self._constraints_for(state.positions_m))[0])
            displacement[j] = (solutions[0] - solutions[1]) / (2 * step_pa)
            plus, minus = self.volumes(solutions[0]), self.volumes(solutions[1])
            chamber[:, j] = (plus[0] - minus[0]) / (2 * step_pa)
            gland[j] = (plus[1] - minus[1]) / (2 * step_pa)
        return Compliance(chamber, gland, displacement)

