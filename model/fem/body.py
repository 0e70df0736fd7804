"""The phantom's discretised solid: its mesh, material, fixation and chamber walls, and what it assembles.

A :class:`SolidBody` knows the element rest data, the sparsity of the stiffness (:class:`SparsePattern`), the
springs that hold the fixation and the held dofs that remove rigid motion without one (:class:`Constraints`).
It assembles, at any node positions, the elastic and spring forces, their energy and a tangent (the positive
definite stand-in or the exact Hessian, with the follower-pressure stiffness), and measures the chambers'
volumes and their gradients. Its elements are 4-node tetrahedra (every law) or 10-node quadratic ones, for the
hyperelastic laws in the mixed (u, p, J) formulation of a nearly incompressible solid, condensed per element
(:func:`phantom.model.fem.kernels.mixed_forces`), and for "linear" their small-strain stiffness (the mixed
tangent at rest). It solves nothing: an :class:`phantom.model.fem.problem.EquilibriumProblem` binds
it to pressures, and Newton (:mod:`phantom.model.fem.newton`) and path following solve that.

Springs have stiffness ``k_i = FIXED_PENALTY * E * A_i / h`` (A_i the node's share of the fixed area, h the
patch's mean edge length), a dimensionless multiple of E: the solution at (p, E) equals the one at
(p E0 / E, E0). Without a fixed group, a 3-2-1 set of displacement constraints removes rigid motion only (the
pressure load is self-equilibrated, so these carry no force).
"""

from __future__ import annotations

import hashlib
import os
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

import phantom
from phantom.model.arrays import BoolArray, FloatArray, Int32Array, IntArray
from phantom.model.errors import MeshError, SolveError
from phantom.model.fem import kernels
from phantom.model.fem.linsolve import (
    CholeskyFactor,
    Factorization,
    FillOrdering,
    cholmod_ordering,
    default_method,
    indefinite_method,
)
from phantom.model.fem.materials import law_parameters
from phantom.model.mesh.elements import (
    TET_DEGREE2_POINTS,
    TET_DEGREE2_WEIGHTS,
    TET_DEGREE3_POINTS,
    TET_DEGREE3_WEIGHTS,
    TRIANGLE_DEGREE4_POINTS,
    TRIANGLE_DEGREE4_WEIGHTS,
    split_triangles,
    tet10_shape,
    triangle6_shape,
)
from phantom.model.mesh.tetmesh import Surfaces, TetMesh, enclosed_volume_m3, volume_gradient_m2
from phantom.model.scene import HYPERELASTIC_MODELS, MATERIAL_MODELS, Material

if TYPE_CHECKING:
    import scipy.sparse

#: Spring stiffness at the fixation as a multiple of E * area / edge length (dimensionless).
FIXED_PENALTY = 1.0e3
#: Bump when the solver's numbers change, so cached compliances and factors are recomputed (and write the tables
#: the built-in scenes ship again: model/scenes/*.toml say how).
SOLVER_VERSION = 2
#: The arrays of a stored rest factor (:class:`CholeskyFactor`'s), each an .npy file of its folder.
STORED_FACTOR_ARRAYS = ("indptr", "indices", "values", "permutation")
#: What :meth:`SolidBody.elastic` assembles besides forces and energy: no matrix, the positive definite
#: stand-in of the tangent (``R K R^T`` co-rotational; the small-strain stiffness for "linear"), or the exact
#: Hessian of the energy.
NO_TANGENT, POSITIVE_TANGENT, EXACT_TANGENT = 0, 1, 2

#: A factorised matrix: ``solve(rhs)`` is ``K^-1 rhs``.
Factor = Factorization | CholeskyFactor
#: The 6-node triangle's shape functions and derivatives at the points of its degree-4 rule.
_FACE_SHAPE, _FACE_DERIVATIVES = triangle6_shape(TRIANGLE_DEGREE4_POINTS)
#: The mixed kernel's "no independent pressures": each element's is then ``K (Jbar - 1)``.
_NO_PRESSURES = np.zeros(0)


@dataclass(frozen=True)
class SparsePattern:
    """The CSR sparsity of the stiffness (3 dofs per node) and where each element entry and each diagonal entry
    goes in its data array: ``indptr`` (3n + 1,), ``indices`` (nnz,) int32, ``diagonal`` (3n,); ``block_start``
    (elements, k, k) and ``degree`` (n,): element e's entry (3 A + i, 3 B + j) (A, B its local nodes) is at
    ``block_start[e, A, B] + 3 i degree[node A] + j``; ``scatter`` (elements, 12, 12) spells that out for 4-node
    elements (empty for 10-node ones, where it would take 7 kB per element)."""

    indptr: IntArray
    indices: Int32Array
    scatter: IntArray
    diagonal: IntArray
    block_start: IntArray
    degree: IntArray


@dataclass(frozen=True)
class Constraints:
    """Held dofs (3-2-1, removing rigid motion; none when springs hold a fixed patch): ``dofs`` (k,), ``free_mask``
    (3n,) True where a dof is free, and ``entries``, the CSR data entries in the held rows and columns."""

    dofs: IntArray
    free_mask: BoolArray
    entries: IntArray

    @property
    def key(self) -> tuple[int, ...]:
        """The held dofs as a tuple: equal keys, equal constraints."""
        return tuple(self.dofs.tolist())


@dataclass(frozen=True)
class ElasticEvaluation:
    """What :meth:`SolidBody.elastic` assembles at one configuration: elastic and spring forces ``forces_n``
    (3n,) N with the held dofs zeroed, their energy ``energy_j`` (J; +inf outside a hyperelastic law's domain),
    the smallest det F over the elements, and ``tangent_data``, the CSR data of the tangent in the body's
    pattern (N/m; a single zero when none was asked for)."""

    forces_n: FloatArray
    energy_j: float
    smallest_det: float
    tangent_data: FloatArray


def sparse_pattern(tets: IntArray, n_nodes: int) -> SparsePattern:
    """Build the CSR pattern once (see :class:`SparsePattern`) for elements of any number of nodes.

    Built from the node graph (k^2 pairs per element instead of 9 k^2 dof pairs): node i's neighbours j (sorted,
    itself included) give dof row ``3 i + a`` the columns ``3 j + b`` in that order, so the row starts at
    ``9 nnz_before(i) + 3 a degree(i)`` and the pair's k-th neighbour entry sits ``3 k + b`` further on.
    """
    n_tets, per_element = tets.shape
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
    rank = rank_in_row[pair_of].reshape(n_tets, per_element, per_element)
    block_start = 9 * node_indptr[:-1][tets][:, :, None] + 3 * rank
    scatter = np.zeros((0, 12, 12), np.int64)
    if per_element == 4:
        scatter = (row_start[tets][:, :, :, None, None] + 3 * rank[:, :, None, :, None] + axis
                   ).reshape(n_tets, 12, 12)
    self_rank = np.zeros(n_nodes, np.int64)
    on_diagonal = pair_rows == pair_columns
    self_rank[pair_rows[on_diagonal]] = rank_in_row[on_diagonal]
    diagonal = (row_start + 3 * self_rank[:, None] + axis).ravel()
    return SparsePattern(indptr, indices, scatter, diagonal, block_start, degree.astype(np.int64))


@dataclass(frozen=True)
class QuadraticRestData:
    """What the 10-node elements' kernels need at rest: ``gradients`` (m, 4, 10, 3) the shape functions' rest
    gradients (1/m) at the degree-2 points, ``weights`` (m, 4) the rest volume each point stands for (m^3),
    ``volumes_m3`` (m,) each element's exact rest volume, and the reference derivatives (5, 10, 3) and weights (5,)
    of the degree-3 rule, which measures element volumes exactly."""

    gradients: FloatArray
    weights: FloatArray
    volumes_m3: FloatArray
    volume_derivatives: FloatArray
    volume_weights: FloatArray


def quadratic_rest_data(nodes_m: FloatArray, tets: IntArray) -> QuadraticRestData:
    """The rest data of 10-node tetrahedra (:class:`QuadraticRestData`); curved elements included (their Jacobian
    varies inside)."""
    _, derivatives = tet10_shape(TET_DEGREE2_POINTS)
    corners = nodes_m[tets]                                                 # (m, 10, 3)
    jacobians = np.einsum("eai,qak->eqik", corners, derivatives)            # dX/dxi
    inverse = np.linalg.inv(jacobians)
    gradients = np.ascontiguousarray(np.einsum("eqki,qak->eqai", inverse, derivatives))
    weights = np.linalg.det(jacobians) * TET_DEGREE2_WEIGHTS
    _, volume_derivatives = tet10_shape(TET_DEGREE3_POINTS)
    volume_jacobians = np.einsum("eai,qak->eqik", corners, volume_derivatives)
    volumes = np.linalg.det(volume_jacobians) @ TET_DEGREE3_WEIGHTS
    return QuadraticRestData(gradients, np.ascontiguousarray(weights), volumes,
                             np.ascontiguousarray(volume_derivatives), TET_DEGREE3_WEIGHTS.copy())


def node_rest_volumes_m3(nodes_m: FloatArray, tets: IntArray,
                         quadratic: QuadraticRestData | None) -> FloatArray:
    """``integral N_a dV`` over the rest body for each node a (m^3, (n,)): a body force ``b`` (N/m^3) gives node a
    the consistent load ``b`` times this (a quarter of each element's volume for 4-node elements; for 10-node ones
    the vertices' share is negative and the mid-edge nodes' positive, as the shape functions integrate)."""
    if quadratic is None:
        volumes = tet_volumes_m3(nodes_m, tets)
        shares: FloatArray = np.repeat(volumes / 4.0, 4)
    else:
        shape, _ = tet10_shape(TET_DEGREE2_POINTS)
        shares = np.einsum("eq,qa->ea", quadratic.weights, shape).ravel()
    node_volumes: FloatArray = np.bincount(tets.ravel(), shares, len(nodes_m)).astype(np.float64)
    return node_volumes


def tet_volumes_m3(nodes_m: FloatArray, tets: IntArray) -> FloatArray:
    """Rest volumes of 4-node tetrahedra (m^3)."""
    edges = nodes_m[tets[:, 1:4]] - nodes_m[tets[:, :1]]
    volumes: FloatArray = np.linalg.det(edges) / 6.0
    return volumes


def rigid_constraints(nodes_m: FloatArray) -> IntArray:
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


def spring_stiffness(nodes_m: FloatArray, fixed_faces: IntArray, youngs_modulus_pa: float,
                     fixed_penalty: float) -> tuple[IntArray, FloatArray]:
    """Fixed nodes and their spring stiffness ``fixed_penalty * E * A_i / h`` (N/m); a 6-node face is split into
    its four triangles, so every node of it gets a share of its area."""
    fixed_triangles = split_triangles(fixed_faces)
    x0, x1, x2 = (nodes_m[fixed_triangles[:, k]] for k in range(3))
    areas_m2 = 0.5 * np.linalg.norm(np.cross(x1 - x0, x2 - x0), axis=1)
    edge_m = np.mean(np.linalg.norm(np.stack([x1 - x0, x2 - x1, x0 - x2]), axis=2))
    node_area_m2 = np.bincount(fixed_triangles.ravel(), np.repeat(areas_m2 / 3.0, 3), len(nodes_m))
    fixed_nodes = np.unique(fixed_triangles).astype(np.int64)
    return fixed_nodes, fixed_penalty * youngs_modulus_pa * node_area_m2[fixed_nodes] / edge_m


def load_from_gradients_n(pressures_pa: FloatArray, chamber_gradients_m2: FloatArray) -> FloatArray:
    """``sum_c p_c dV_c/dx`` (N, (3n,)) from the chamber rows of the volume gradients (m^2, (chambers, 3n))."""
    load: FloatArray = np.einsum("c,cj->j", pressures_pa, chamber_gradients_m2[: len(pressures_pa)])
    return load


class SolidBody:
    """The discretised solid (see the module docstring): checked material, element rest data, sparsity, springs.

    Parameters
    ----------
    mesh : TetMesh
        Nodes (m) and positively oriented tetrahedra.
    surfaces : Surfaces
        Chamber walls (oriented out of their cavities), the outer boundary (outward) and the fixed patch.
    chamber_names : list of str
        One name per chamber wall, for messages.
    material : Material
    source : str
        Where the mesh came from, for messages.
    linear_solver : str or None
        The factorisation of positive definite matrices (:data:`phantom.model.fem.linsolve.METHODS`; None: the
        measured default).

    Raises SolveError for a material out of range and MeshError for a chamber that encloses no volume.
    Attributes (read them, do not change them): ``nodes_m`` (n, 3), ``tets`` (m, 4 or 10), ``order`` (1 or 2),
    ``chamber_faces``, ``outer_faces``, ``fixed_faces`` (3- or 6-node faces), ``n_chambers``,
    ``rest_chamber_volumes_m3`` (chambers,), ``rest_gland_volume_m3``, ``element_volumes_m3`` (m,); for 4-node
    elements ``dm_inverse`` (m, 3, 3) each element's inverse rest edge matrix and ``element_stiffness``, for
    10-node ones ``quadratic`` (:class:`QuadraticRestData`); ``node_volumes_m3`` (n,) each node's share of the
    volume (the consistent body-force load per N/m^3); ``pattern``, ``fixed_nodes`` and ``spring_n_per_m`` (the
    springs), ``fixed_penalty`` (FIXED_PENALTY when the body was made), ``rest_constraints``.
    """

    def __init__(self, mesh: TetMesh, surfaces: Surfaces, chamber_names: list[str], material: Material,
                 source: str = "mesh", linear_solver: str | None = None):
        if not 0 < material.youngs_modulus_pa < np.inf or not -1.0 < material.poisson_ratio < 0.5:
            raise SolveError(f"material out of range: E = {material.youngs_modulus_pa} Pa (> 0), "
                             f"nu = {material.poisson_ratio} (in (-1, 0.5))")
        if material.model not in MATERIAL_MODELS:
            raise SolveError(f"unknown material model {material.model!r}: use one of {', '.join(MATERIAL_MODELS)}")
        if material.gent_jm is not None and not 0 < material.gent_jm < np.inf:
            raise SolveError(f"material out of range: gent_jm = {material.gent_jm} (a positive number)")
        if material.model == "gent" and material.gent_jm is None:
            raise SolveError("the Gent material needs gent_jm, the locking value of I1 - 3 (e.g. 20)")
        if material.model in HYPERELASTIC_MODELS:
            law_parameters(material.model, material)  # SolveError for a law without its coefficients
        self.mesh = mesh
        self.surfaces = surfaces
        self.source = source
        self.nodes_m = mesh.nodes_m
        self.tets = mesh.tets
        self.chamber_names = list(chamber_names)
        self.n_chambers = len(chamber_names)
        self.order = mesh.order
        self.chamber_faces = surfaces.chamber_faces
        self.outer_faces = surfaces.outer_faces
        self.fixed_faces = surfaces.fixed_faces
        self.material = material
        self.linear_solver = linear_solver
        self.rest_chamber_volumes_m3, self.rest_gland_volume_m3 = self.volumes(self.nodes_m)
        for name, volume in zip(self.chamber_names, self.rest_chamber_volumes_m3, strict=True):
            if volume <= 0:
                raise MeshError(f"{source}: chamber {name!r} encloses no volume ({volume:.3g} m^3)")
        self.quadratic: QuadraticRestData | None = None
        if self.order == 2:
            if material.model == "corotational":
                raise SolveError(f"the co-rotational law is for 4-node tetrahedra: use "
                                 f"{', '.join(HYPERELASTIC_MODELS)} (or linear) with 10-node ones, or [geometry] "
                                 "element_order = 1")
            self.quadratic = quadratic_rest_data(self.nodes_m, self.tets)
            self.element_volumes_m3 = self.quadratic.volumes_m3
        else:
            self.dm_inverse, self.element_volumes_m3, self.element_stiffness = kernels.element_rest_data(
                self.nodes_m, self.tets, material.youngs_modulus_pa, material.poisson_ratio)
        self.node_volumes_m3 = node_rest_volumes_m3(self.nodes_m, self.tets, self.quadratic)
        self.pattern = sparse_pattern(self.tets, len(self.nodes_m))
        self.fixed_penalty = FIXED_PENALTY
        self.fixed_nodes: IntArray = np.zeros(0, np.int64)
        self.spring_n_per_m: FloatArray = np.zeros(0)
        if self.fixed_faces is not None:
            self.fixed_nodes, self.spring_n_per_m = spring_stiffness(
                self.nodes_m, self.fixed_faces, material.youngs_modulus_pa, self.fixed_penalty)
        self._rest_tangent: FloatArray | None = None
        self._factorizations: dict[tuple[int, ...], Factor] = {}
        self._cholmod_analysis: Any = None
        self._ldl_analysis: Any = None
        self._fill_ordering: FillOrdering | None = None
        self._constraint_sets: dict[tuple[int, ...], Constraints] = {}
        self.rest_constraints = self.constraints_for(self.nodes_m)

    @property
    def length_scale_m(self) -> float:
        """The body's size: the cube root of its rest volume (m)."""
        return float(np.cbrt(self.rest_gland_volume_m3))

    def constraints_for(self, positions_m: FloatArray) -> Constraints:
        """No held dofs when springs hold the fixation; else a 3-2-1 set chosen in this configuration's frame
        (so that a rigidly rotated start is held as the rest shape would be)."""
        n_dofs = 3 * len(self.nodes_m)
        dofs = np.zeros(0, np.int64) if self.fixed_faces is not None else rigid_constraints(positions_m)
        key = tuple(dofs.tolist())
        if key not in self._constraint_sets:
            free_mask = np.ones(n_dofs, bool)
            free_mask[dofs] = False
            entries = dofs
            if len(dofs):
                rows = np.repeat(np.arange(n_dofs), np.diff(self.pattern.indptr))
                entries = np.flatnonzero(~free_mask[rows] | ~free_mask[self.pattern.indices])
            self._constraint_sets[key] = Constraints(dofs, free_mask, entries)
        return self._constraint_sets[key]

    # --- volumes ---------------------------------------------------------------------------------------------

    def chamber_volumes_m3(self, positions_m: FloatArray) -> FloatArray:
        """Each chamber's volume (m^3, chamber order) at node positions (n, 3) m."""
        return np.array([enclosed_volume_m3(positions_m, faces) for faces in self.chamber_faces])

    def volumes(self, positions_m: FloatArray) -> tuple[FloatArray, float]:
        """Chamber volumes (m^3, chamber order) and the gland volume (m^3, inside the outer boundary)."""
        return self.chamber_volumes_m3(positions_m), enclosed_volume_m3(positions_m, self.outer_faces)

    def volume_gradients(self, positions_m: FloatArray) -> FloatArray:
        """``H``: (n_chambers + 1, 3 n) gradients of each chamber's volume and of the gland's (m^2)."""
        return np.concatenate([self.chamber_volume_gradients(positions_m),
                               volume_gradient_m2(positions_m, self.outer_faces).reshape(1, -1)])

    def chamber_volume_gradients(self, positions_m: FloatArray) -> FloatArray:
        """(n_chambers, 3 n) gradients of each chamber's volume (m^2): the pressure load's, without the gland's
        outer surface (as many faces as the chambers' together on the prostate)."""
        return np.stack([volume_gradient_m2(positions_m, faces).ravel() for faces in self.chamber_faces])

    # --- elements --------------------------------------------------------------------------------------------

    def deformation_determinants(self, positions_m: FloatArray) -> FloatArray:
        """det F of every element (m,) at node positions (n, 3) m; for a 10-node element the least of its volume
        ratio and det F at its quadrature points."""
        if self.quadratic is not None:
            data = self.quadratic
            return kernels.mixed_determinants(positions_m, self.tets, data.gradients, data.volumes_m3,
                                              data.volume_derivatives, data.volume_weights)
        return kernels.deformation_determinants(positions_m, self.tets, self.dm_inverse)

    def __getstate__(self) -> dict[str, Any]:
        """A body goes to worker processes (the response table's Dask tasks) without CHOLMOD's objects, which cannot
        be pickled: its symbolic analysis is made again at the worker's first factorisation, and a rest factor
        made in this process travels as its arrays (as the disk cache stores it; SuperLU's is made again)."""
        state = self.__dict__.copy()
        state["_cholmod_analysis"] = state["_ldl_analysis"] = None
        state["_fill_ordering"] = None  # its gather is the size of the matrix: read again from the disk cache
        factors: dict[tuple[int, ...], Factor] = {}
        for key, factor in self._factorizations.items():
            arrays = factor.cholesky_factor() if isinstance(factor, Factorization) else factor
            if arrays is not None:
                factors[key] = arrays
        state["_factorizations"] = factors
        return state

    def deformation_gradients(self, positions_m: FloatArray) -> FloatArray:
        """F at every point where the law is evaluated (m, q, 3, 3): a 4-node element's one F (q = 1), a 10-node
        element's F at each of its quadrature points (its corners alone miss its bending)."""
        if self.quadratic is not None:
            gradients: FloatArray = np.einsum("eai,eqaj->eqij", positions_m[self.tets], self.quadratic.gradients)
            return gradients
        edges = positions_m[self.tets[:, 1:4]] - positions_m[self.tets[:, :1]]
        corners: FloatArray = np.einsum("eki,ekj->eij", edges, self.dm_inverse)[:, None]
        return corners

    def element_volume_ratios(self, positions_m: FloatArray) -> FloatArray:
        """Each element's current over rest volume (m,): det F of a 4-node element; for a 10-node one its exact
        volume ratio (the degree-3 rule), the dilatation ``Jbar`` the mixed formulation holds near 1."""
        if self.quadratic is None:
            return self.deformation_determinants(positions_m)
        data = self.quadratic
        ratios: FloatArray = kernels.mixed_volume_ratios(positions_m, self.tets, data.volumes_m3,
                                                         data.volume_derivatives, data.volume_weights)
        return ratios

    def element_volume_ratio_rates(self, positions_m: FloatArray, direction_m: FloatArray) -> FloatArray:
        """A 10-node body's ``d Jbar / ds`` of each element (m,) at ``positions_m`` moving along ``direction_m``
        (n, 3): its volume's gradient dotted with its nodes' moves, over its rest volume (Jacobi's formula,
        ``sum_q w_q det(J_q) tr(J_q^-1 dJ_q) / V_e``), the linearised change of its volume ratio."""
        assert self.quadratic is not None  # only 10-node bodies have the mixed pressure field
        data = self.quadratic
        rates: FloatArray = kernels.mixed_volume_ratio_rates(positions_m, direction_m, self.tets, data.volumes_m3,
                                                             data.volume_derivatives, data.volume_weights)
        return rates

    def eliminated_pressures_pa(self, volume_ratios: FloatArray,
                                volume_ratio_changes: FloatArray | float = 0.0) -> FloatArray:
        """A 10-node body's element pressures (m,) eliminated at its volume ratios ``Jbar``: ``K (Jbar - 1)``; with
        ``volume_ratio_changes`` (a step's linearised ``dJbar``), the pressures' linearised update
        ``K (Jbar - 1 + dJbar)`` (the mixed Newton's, :func:`phantom.model.fem.newton.mixed_newton`)."""
        pressures_pa: FloatArray = self.material.bulk_modulus_pa * (volume_ratios - 1.0 + volume_ratio_changes)
        return pressures_pa

    def element_pressure_forces_n(self, positions_m: FloatArray, element_pressures_pa: FloatArray) -> FloatArray:
        """A 10-node body's nodal forces (3n,) N of element pressures (m,) alone, ``sum_e p_e dV_e/dx``: how the
        elastic forces change when the pressures do (they are linear in them)."""
        assert self.quadratic is not None  # only 10-node bodies have the mixed pressure field
        forces_n = np.zeros_like(positions_m)
        kernels.add_element_pressure_forces(positions_m, self.tets, self.quadratic.volume_derivatives,
                                            self.quadratic.volume_weights, element_pressures_pa, forces_n)
        return forces_n.ravel()

    def volume_constraint_error_n(self, volume_ratios: FloatArray, element_pressures_pa: FloatArray) -> FloatArray:
        """How far carried element pressures (m,) are from the volume ratios' ``K (Jbar - 1)``, as a force (N):
        ``mu V_e^(2/3) (Jbar - 1 - p / K)``, the constraint's error weighed at the shear modulus, not the bulk (the
        mixed Newton's merit: a strain error, not K times one)."""
        assert self.quadratic is not None  # only 10-node bodies have the mixed pressure field
        material = self.material
        error_n: FloatArray = (material.lame_mu_pa * self.quadratic.volumes_m3 ** (2.0 / 3.0)
                               * (volume_ratios - 1.0 - element_pressures_pa / material.bulk_modulus_pa))
        return error_n

    def worst_element(self, positions_m: FloatArray) -> int:
        """The element with the smallest det F if any is flat or inverted, else -1."""
        dets = self.deformation_determinants(positions_m)
        worst = int(np.argmin(dets))
        return worst if dets[worst] <= 0 else -1

    def law(self, formulation: str) -> tuple[int, FloatArray]:
        """The hyperelastic law ``formulation`` of the body's material as the kernels take it: its number and
        parameters (:func:`phantom.model.fem.materials.law_parameters`; SolveError without its coefficients)."""
        return law_parameters(formulation, self.material)

    # --- assembly --------------------------------------------------------------------------------------------

    def elastic(self, positions_m: FloatArray, formulation: str, matrix: int, constraints: Constraints,
                pressures_pa: FloatArray | None = None,
                element_pressures_pa: FloatArray | None = None) -> ElasticEvaluation:
        """Elastic + spring forces, energy and smallest det F at node positions (n, 3) m, and the tangent's CSR
        data when ``matrix`` is POSITIVE_TANGENT (``R K R^T``, co-rotational, positive definite) or
        EXACT_TANGENT (the exact Hessian, co-rotational or hyperelastic), including the pressure's follower-load
        stiffness when ``pressures_pa`` (chambers,) are given; the linear model's is its stiffness either way.
        ``element_pressures_pa`` (m,): a 10-node body's pressure field as Newton's independent unknown (see
        :func:`phantom.model.fem.kernels.mixed_forces`); None: each element's ``K (Jbar - 1)``."""
        data = np.zeros(len(self.pattern.indices)) if matrix else np.zeros(1)
        if self.quadratic is not None:
            forces, energy_j, smallest_det = self._quadratic_elastic(positions_m, formulation, matrix, data,
                                                                     element_pressures_pa)
        elif formulation in HYPERELASTIC_MODELS:
            forces, energy_j, smallest_det = kernels.hyperelastic_forces(
                positions_m, self.tets, self.dm_inverse, self.element_volumes_m3, *self.law(formulation),
                self.material.lame_mu_pa, self.material.lame_lambda_pa, EXACT_TANGENT if matrix else NO_TANGENT,
                self.pattern.scatter, data)
        else:
            forces, energy_j, smallest_det = kernels.internal_forces(
                positions_m, self.nodes_m, self.tets, self.dm_inverse, self.element_stiffness,
                formulation == "corotational", matrix, self.pattern.scatter, data)
        stretch = positions_m[self.fixed_nodes] - self.nodes_m[self.fixed_nodes]
        forces[self.fixed_nodes] += self.spring_n_per_m[:, None] * stretch
        energy_j += 0.5 * float(np.sum(self.spring_n_per_m[:, None] * stretch**2))
        forces = forces.ravel()
        forces[constraints.dofs] = 0.0
        if matrix:
            if matrix == EXACT_TANGENT and pressures_pa is not None:
                for pressure_pa, faces in zip(pressures_pa, self.chamber_faces, strict=True):
                    if faces.shape[1] == 6:
                        kernels.add_quadratic_pressure_stiffness(
                            positions_m, faces, pressure_pa, _FACE_SHAPE, _FACE_DERIVATIVES, TRIANGLE_DEGREE4_WEIGHTS,
                            self.pattern.indptr, self.pattern.indices, data)
                    else:
                        kernels.add_pressure_stiffness(positions_m, faces, pressure_pa, self.pattern.indptr,
                                                       self.pattern.indices, data)
            spring_dofs = (3 * self.fixed_nodes[:, None] + np.arange(3)).ravel()
            data[self.pattern.diagonal[spring_dofs]] += np.repeat(self.spring_n_per_m, 3)
            if len(constraints.dofs):
                scale = float(np.mean(data[self.pattern.diagonal]))
                data[constraints.entries] = 0.0
                data[self.pattern.diagonal[constraints.dofs]] = scale
        return ElasticEvaluation(forces, float(energy_j), float(smallest_det), data)

    def _quadratic_elastic(self, positions_m: FloatArray, formulation: str, matrix: int, data: FloatArray,
                           element_pressures_pa: FloatArray | None = None) -> tuple[FloatArray, float, float]:
        """The 10-node elements' forces (n, 3), energy and smallest volume ratio, their tangent added to ``data``:
        the mixed hyperelastic kernel, or for "linear" the small-strain stiffness (its tangent at rest)."""
        assert self.quadratic is not None  # only 10-node bodies come here
        if formulation == "linear":
            stiffness = self.rest_tangent_data()
            displacement = (positions_m - self.nodes_m).ravel()
            forces = self.multiply(stiffness, displacement)
            if matrix:
                data += stiffness
            return forces.reshape(-1, 3), 0.5 * float(np.einsum("i,i->", forces, displacement)), np.inf
        if formulation not in HYPERELASTIC_MODELS:
            raise SolveError(f"the {formulation} law is for 4-node tetrahedra: use {', '.join(HYPERELASTIC_MODELS)} "
                             "or linear with 10-node ones")
        rest = self.quadratic
        forces, energy_j, smallest = kernels.mixed_forces(
            positions_m, self.tets, rest.gradients, rest.weights, rest.volumes_m3, rest.volume_derivatives,
            rest.volume_weights, *self.law(formulation), self.material.bulk_modulus_pa,
            EXACT_TANGENT if matrix else NO_TANGENT, self.pattern.block_start,
            self.pattern.degree, data, _NO_PRESSURES if element_pressures_pa is None else element_pressures_pa)
        return forces, float(energy_j), float(smallest)

    def rest_tangent_data(self) -> FloatArray:
        """A 10-node body's small-strain stiffness (CSR data, N/m, elements only): the mixed Neo-Hookean tangent
        at rest, which every hyperelastic law shares there (made once)."""
        if self._rest_tangent is None:
            assert self.quadratic is not None  # only 10-node bodies come here
            rest = self.quadratic
            data = np.zeros(len(self.pattern.indices))
            kernels.mixed_forces(self.nodes_m, self.tets, rest.gradients, rest.weights, rest.volumes_m3,
                                 rest.volume_derivatives, rest.volume_weights, *self.law("neo_hookean"),
                                 self.material.bulk_modulus_pa, EXACT_TANGENT, self.pattern.block_start,
                                 self.pattern.degree, data, _NO_PRESSURES)
            self._rest_tangent = data
        return self._rest_tangent

    def tangent_data(self, positions_m: FloatArray | None = None, formulation: str = "linear",
                     pressures_pa: FloatArray | None = None, constraints: Constraints | None = None,
                     element_pressures_pa: FloatArray | None = None) -> FloatArray:
        """The CSR data (N/m, in :attr:`pattern`) of the assembled tangent at ``positions_m`` (default: rest):
        "linear": the small-strain stiffness; "corotational" and the hyperelastic laws: the exact Hessian of the
        total energy, with the follower-load stiffness of ``pressures_pa`` when given (and a 10-node body's
        carried element pressures, as :meth:`elastic`'s). Held dofs (default: the rest constraints) get scaled
        identity rows."""
        positions_m = self.nodes_m if positions_m is None else positions_m
        matrix = POSITIVE_TANGENT if formulation == "linear" else EXACT_TANGENT
        return self.elastic(positions_m, formulation, matrix, constraints or self.rest_constraints,
                            pressures_pa, element_pressures_pa).tangent_data

    def csr(self, data: FloatArray) -> scipy.sparse.csr_matrix:
        """The scipy CSR matrix of the body's pattern with entries ``data``."""
        # scipy.sparse (0.15 s to import) only where a matrix is factorised or handed out: a warm solve
        # multiplies the tangent with its own kernel and back-substitutes a stored factor.
        import scipy.sparse as sp

        n_dofs = 3 * len(self.nodes_m)
        return sp.csr_matrix((data, self.pattern.indices, self.pattern.indptr), shape=(n_dofs, n_dofs))

    def multiply(self, data: FloatArray, vector: FloatArray) -> FloatArray:
        """``A v`` for the matrix of the body's pattern with entries ``data`` and a vector (3n,)."""
        return kernels.csr_multiply(self.pattern.indptr, self.pattern.indices, data, vector)

    @property
    def detects_indefinite(self) -> bool:
        """The body's solver (CHOLMOD) refuses a matrix that is not positive definite (SuperLU factorises it)."""
        return (self.linear_solver or default_method()) == "cholmod"

    def factorize(self, data: FloatArray, positive_definite: bool = True) -> Factorization:
        """Factorise a matrix of the body's pattern with ``linear_solver`` (None: the measured default). One that
        may be indefinite (the exact tangent: positive definite on the stable path, not past a limit point) goes
        to CHOLMOD's Cholesky first, when that is the solver, and to :func:`indefinite_method` (CHOLMOD's LDL')
        when CHOLMOD finds it is not positive definite (SuperLU when the solver is not CHOLMOD). CHOLMOD's
        symbolic analysis of the pattern is made once per body and mode, on the pattern's fill-reducing ordering
        (:meth:`fill_ordering`).

        Raises ArithmeticError when a matrix said to be positive definite is not (CHOLMOD), or an indefinite one
        is singular (a zero pivot in LDL').
        """
        matrix = self.csr(data)
        method = self.linear_solver or default_method()
        if method != "cholmod":
            return Factorization(matrix, method if positive_definite else "splu-mmd")
        ordering = self.fill_ordering(matrix)
        try:
            factorization = Factorization(matrix, method, self._cholmod_analysis, ordering)
        except ArithmeticError:
            if positive_definite:
                raise
            factorization = Factorization(matrix, indefinite_method(), self._ldl_analysis, ordering)
            self._ldl_analysis = factorization.analysis
            return factorization
        self._cholmod_analysis = factorization.analysis
        return factorization

    def fill_ordering(self, matrix: scipy.sparse.csr_matrix) -> FillOrdering:
        """CHOLMOD's fill-reducing ordering of the body's pattern (``matrix`` is one of its matrices), made once and
        kept on disk (``phantom.cache_dir("orderings")``, keyed by the pattern), so that a new process does not
        order the pattern again (AMD and METIS: 0.18 s of CPU on the 7 mm prostate). A stored file that is not a
        permutation of the pattern's rows is made again."""
        if self._fill_ordering is not None:
            return self._fill_ordering
        digest = hashlib.sha256()
        for array in (self.pattern.indptr, self.pattern.indices):
            digest.update(np.ascontiguousarray(array).tobytes())
        path = phantom.cache_dir("orderings") / f"{digest.hexdigest()[:32]}.npy"
        if path.is_file():
            try:
                self._fill_ordering = FillOrdering(np.load(path), self.pattern.indptr, self.pattern.indices)
                return self._fill_ordering
            except (OSError, ValueError, EOFError):
                path.unlink(missing_ok=True)
        permutation = cholmod_ordering(matrix)
        with phantom.written_atomically(path) as temporary:
            np.save(temporary, permutation.astype(np.int32))
        self._fill_ordering = FillOrdering(permutation, self.pattern.indptr, self.pattern.indices)
        return self._fill_ordering

    def rest_factorization(self, constraints: Constraints | None = None) -> Factor:
        """The factorised small-strain stiffness (elastic + springs + ``constraints``, default the rest ones),
        made once per body.

        A Cholesky factor is also kept on disk (``phantom.cache_dir("factorizations")``), keyed by everything
        but E: the stiffness is proportional to E, so one factor serves every modulus (rescaled), and a new
        process or a calibration loop does not factorise again.
        """
        constraints = constraints or self.rest_constraints
        if constraints.key not in self._factorizations:
            self._factorizations[constraints.key] = self._stored_rest_factorization(constraints)
        return self._factorizations[constraints.key]

    def _stored_rest_factorization(self, constraints: Constraints) -> Factor:
        digest = hashlib.sha256()
        springs_per_pa = self.spring_n_per_m / self.material.youngs_modulus_pa
        for array in (self.nodes_m, self.tets, self.fixed_nodes, springs_per_pa, constraints.dofs):
            digest.update(np.ascontiguousarray(array).tobytes())
        digest.update(repr((self.material.poisson_ratio, self.fixed_penalty, SOLVER_VERSION)).encode())
        # a folder of .npy files, mapped rather than read: the 7 mm prostate's 100 MB factor took 0.3 s to read
        # from an .npz (zip's CRC and a copy), and most solves use it for a few substitutions
        path = phantom.cache_dir("factorizations") / digest.hexdigest()[:32]
        path.with_suffix(".npz").unlink(missing_ok=True)  # (where an earlier version kept it)
        if path.is_dir():
            try:
                stored = {name: np.load(path / f"{name}.npy", mmap_mode="r") for name in STORED_FACTOR_ARRAYS}
                scale = float(np.load(path / "youngs_modulus_pa.npy")) / self.material.youngs_modulus_pa
                return CholeskyFactor(stored["indptr"], stored["indices"], stored["values"], stored["permutation"],
                                      scale)
            except (OSError, ValueError):
                shutil.rmtree(path, ignore_errors=True)
        factorization = self.factorize(self.elastic(self.nodes_m, "linear", POSITIVE_TANGENT,
                                                    constraints).tangent_data)
        factor_arrays = factorization.cholesky_factor()
        if factor_arrays is not None:
            temporary = Path(tempfile.mkdtemp(dir=path.parent, suffix=".partial"))
            arrays: dict[str, Any] = factor_arrays.arrays()
            arrays["indices"] = arrays["indices"].astype(np.int32)
            arrays["youngs_modulus_pa"] = np.float64(self.material.youngs_modulus_pa)
            for name, array in arrays.items():
                np.save(temporary / f"{name}.npy", array)
            try:
                os.replace(temporary, path)  # whole, or not at all
            except OSError:  # another process stored it first
                shutil.rmtree(temporary, ignore_errors=True)
        return factorization

    # --- conditioning ----------------------------------------------------------------------------------------

    def rest_diagonal_n_per_m(self) -> FloatArray:
        """Diagonal of the small-strain stiffness with the springs (N/m) at the free dofs."""
        data = self.elastic(self.nodes_m, "linear", POSITIVE_TANGENT, self.rest_constraints).tangent_data
        diagonal: FloatArray = data[self.pattern.diagonal][self.rest_constraints.free_mask]
        return diagonal

    def rounding_floor_n(self, positions_m: FloatArray) -> float:
        """The residual (N) that rounding the positions to double precision alone produces: each force is a
        stiffness times a position known to ``eps |x|``, so ``eps |diag(K) |x||`` is as low as Newton can go."""
        free = self.rest_constraints.free_mask
        product = self.rest_diagonal_n_per_m() * np.abs(positions_m.ravel()[free])
        return float(np.finfo(float).eps * np.sqrt(np.einsum("i,i->", product, product)))

    def diagonal_ratio(self) -> float:
        """Largest over smallest stiffness diagonal entry: a lower bound of the condition number."""
        diagonal = self.rest_diagonal_n_per_m()
        return float(diagonal.max() / diagonal.min())

    def cache_key(self, extra: bytes = b"") -> str:
        """A hash of everything the body's answers depend on (mesh, groups, springs, material, penalty, solver
        version) and ``extra``: the name of a file that stores one of them."""
        digest = hashlib.sha256()
        for array in (self.nodes_m, self.tets, *self.chamber_faces, self.outer_faces, self.fixed_nodes,
                      self.spring_n_per_m, self.rest_constraints.dofs):
            digest.update(np.ascontiguousarray(array).tobytes())
        digest.update(repr((self.material.youngs_modulus_pa, self.material.poisson_ratio, self.material.gent_jm,
                            self.fixed_penalty, SOLVER_VERSION)).encode())
        if self.material.model == "yeoh":  # only then: the other laws' keys stay those of the shipped tables
            digest.update(repr((self.material.yeoh_c20_over_c10, self.material.yeoh_c30_over_c10)).encode())
        digest.update(extra)
        return digest.hexdigest()[:32]
