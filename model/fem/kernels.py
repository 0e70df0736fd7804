"""Element kernels of linear and quadratic tetrahedra (numba, compiled once and cached on disk).

:mod:`phantom.model.fem.jit` compiles them: ``python -m phantom.model.fem.kernels`` (run by scripts/bootstrap.sh
after an install) builds the exported kernels ahead of time with numba.pycc, which later imports load without
importing numba; otherwise numba compiles them on first use. Either way the callers get the same functions, which
take any array dtypes and convert them.

Notation per element: rest positions ``X_a``, current positions ``x_a`` (a = 0..3), ``Dm = [X1-X0, X2-X0,
X3-X0]``, deformation gradient ``F = Ds Dm^-1``. The co-rotational energy is ``1/2 u^T K_e u`` with the
unrotated displacement ``u_a = R^T x_a - X_a`` and ``R = polar(F)``, computed by SVD (``F = U S V^T``,
``R = U V^T`` with the last singular value taking the sign of ``det F``, so R is a proper rotation even for
flat or inverted elements; :func:`polar_rotation` computes this 3 x 3 SVD itself by Jacobi rotations, about
ten times faster than a LAPACK call per element). Its gradient is ``f_a = R (K_e u)_a``. Its Hessian is
``R K_ab R^T`` plus the terms from the rotation's derivative: with ``S = R^T F``, ``dR = R [w]x`` where
``w = (tr(S) I - S)^-1 sum_b [G_b]x R^T dx_b`` (``G_b`` the shape-function gradients), which gives the
block ``R Z_a (tr(S) I - S)^-1 [G_b]x R^T`` with ``Z_a = -[(K u)_a]x + sum_c K_ac [R^T x_c]x``.

The hyperelastic laws are :mod:`phantom.model.fem.materials`' functions of the first invariant; one generic kernel
per element order applies any of them (a law number and its parameters): :func:`hyperelastic_forces` (4-node,
energy, forces and the exact tangent in one element pass) and :func:`mixed_forces` (10-node, mixed).
"""

import os
import tempfile
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from phantom.model.arrays import FloatArray, Int32Array, IntArray
from phantom.model.fem.jit import (
    COMPILED,
    compiled_kernels_path,
    forget_stale_jit_cache,
    inline_kernel,
    kernel,
)
from phantom.model.fem.materials import law_energy

#: The kernels the model calls, with their argument dtypes (None: a scalar; "out": a float64 C array written in
#: place) and the signature of their ahead-of-time build (all arrays C-contiguous).
EXPORTS = {
    "element_rest_data": (("f8", "i8", None, None),
                          "Tuple((f8[:, :, ::1], f8[::1], f8[:, :, ::1]))(f8[:, ::1], i8[:, ::1], f8, f8)"),
    "polar_rotation": (("f8",), "f8[:, ::1](f8[:, ::1])"),
    "internal_forces": (("f8", "f8", "i8", "f8", "f8", None, None, "i8", "out"),
                        "Tuple((f8[:, ::1], f8, f8))(f8[:, ::1], f8[:, ::1], i8[:, ::1], f8[:, :, ::1], "
                        "f8[:, :, ::1], b1, i8, i8[:, :, ::1], f8[::1])"),
    "hyperelastic_forces": (("f8", "i8", "f8", "f8", None, "f8", None, None, None, "i8", "out"),
                            "Tuple((f8[:, ::1], f8, f8))(f8[:, ::1], i8[:, ::1], f8[:, :, ::1], f8[::1], i8, f8[::1], "
                            "f8, f8, i8, i8[:, :, ::1], f8[::1])"),
    "deformation_determinants": (("f8", "i8", "f8"), "f8[::1](f8[:, ::1], i8[:, ::1], f8[:, :, ::1])"),
    "add_pressure_stiffness": (("f8", "i8", None, "i8", "i4", "out"),
                               "void(f8[:, ::1], i8[:, ::1], f8, i8[::1], i4[::1], f8[::1])"),
    "csr_multiply": (("i8", "i4", "f8", "f8"), "f8[::1](i8[::1], i4[::1], f8[::1], f8[::1])"),
    "cholesky_solve": (("i8", "i4", "f8", "i8", "f8"), "f8[:, ::1](i8[::1], i4[::1], f8[::1], i8[::1], f8[:, ::1])"),
    "mixed_forces": (("f8", "i8", "f8", "f8", "f8", "f8", "f8", None, "f8", None, None, "i8", "i8", "out", "f8"),
                     "Tuple((f8[:, ::1], f8, f8))(f8[:, ::1], i8[:, ::1], f8[:, :, :, ::1], f8[:, ::1], f8[::1], "
                     "f8[:, :, ::1], f8[::1], i8, f8[::1], f8, i8, i8[:, :, ::1], i8[::1], f8[::1], f8[::1])"),
    "mixed_determinants": (("f8", "i8", "f8", "f8", "f8", "f8"),
                           "f8[::1](f8[:, ::1], i8[:, ::1], f8[:, :, :, ::1], f8[::1], f8[:, :, ::1], f8[::1])"),
    "add_element_pressure_forces": (("f8", "i8", "f8", "f8", "f8", "out"),
                                    "void(f8[:, ::1], i8[:, ::1], f8[:, :, ::1], f8[::1], f8[::1], f8[:, ::1])"),
    "mixed_volume_ratios": (("f8", "i8", "f8", "f8", "f8"),
                            "f8[::1](f8[:, ::1], i8[:, ::1], f8[::1], f8[:, :, ::1], f8[::1])"),
    "mixed_volume_ratio_rates": (("f8", "f8", "i8", "f8", "f8", "f8"),
                                 "f8[::1](f8[:, ::1], f8[:, ::1], i8[:, ::1], f8[::1], f8[:, :, ::1], f8[::1])"),
    "add_quadratic_pressure_stiffness": (("f8", "i8", None, "f8", "f8", "f8", "i8", "i4", "out"),
                                         "void(f8[:, ::1], i8[:, ::1], f8, f8[:, ::1], f8[:, :, ::1], f8[::1], "
                                         "i8[::1], i4[::1], f8[::1])"),
}


@kernel
def element_rest_data(rest_positions_m: FloatArray, tets: IntArray, youngs_modulus_pa: float,
                      poisson_ratio: float) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Inverse shape matrices ``Dm^-1`` (m, 3, 3), rest volumes (m^3) and linear stiffness matrices ``K_e``.

    ``K_e = V B^T D B`` (N/m, 12 x 12 per element, node-major dof order x0 y0 z0 x1 ...), with the strain
    matrix B of the constant shape-function gradients and the isotropic elasticity matrix D (Voigt order
    xx yy zz yz xz xy, engineering shear strains).
    """
    n_tets = tets.shape[0]
    dm_inverse = np.empty((n_tets, 3, 3))
    volumes_m3 = np.empty(n_tets)
    stiffness = np.empty((n_tets, 12, 12))
    lame_lambda = youngs_modulus_pa * poisson_ratio / ((1.0 + poisson_ratio) * (1.0 - 2.0 * poisson_ratio))
    lame_mu = youngs_modulus_pa / (2.0 * (1.0 + poisson_ratio))
    elasticity = np.zeros((6, 6))
    for i in range(3):
        for j in range(3):
            elasticity[i, j] = lame_lambda
        elasticity[i, i] = lame_lambda + 2.0 * lame_mu
        elasticity[i + 3, i + 3] = lame_mu
    dm = np.empty((3, 3))
    stress_of_dof = np.empty((6, 12))
    for e in range(n_tets):
        _edge_matrix(rest_positions_m, tets, e, dm)
        inverse = dm_inverse[e]
        volumes_m3[e] = _inverse3(dm, inverse) / 6.0
        gradients = np.empty((4, 3))
        for axis in range(3):
            gradients[1, axis] = inverse[0, axis]
            gradients[2, axis] = inverse[1, axis]
            gradients[3, axis] = inverse[2, axis]
            gradients[0, axis] = -(inverse[0, axis] + inverse[1, axis] + inverse[2, axis])
        strain = np.zeros((6, 12))
        for a in range(4):
            bx, by, bz = gradients[a, 0], gradients[a, 1], gradients[a, 2]
            c = 3 * a
            strain[0, c] = bx
            strain[1, c + 1] = by
            strain[2, c + 2] = bz
            strain[3, c + 1] = bz
            strain[3, c + 2] = by
            strain[4, c] = bz
            strain[4, c + 2] = bx
            strain[5, c] = by
            strain[5, c + 1] = bx
        # Loops rather than matmul: an ahead-of-time build would otherwise load scipy's BLAS (0.2 s) for it.
        for k in range(6):
            for j in range(12):
                total = 0.0
                for m in range(6):
                    total += elasticity[k, m] * strain[m, j]
                stress_of_dof[k, j] = total
        for i in range(12):
            for j in range(12):
                total = 0.0
                for k in range(6):
                    total += strain[k, i] * stress_of_dof[k, j]
                stiffness[e, i, j] = volumes_m3[e] * total
    return dm_inverse, volumes_m3, stiffness


@kernel
def _jacobi_rotate(a: FloatArray, vectors: FloatArray, p: int, q: int) -> None:
    """Zero ``a[p, q]`` of the symmetric matrix by one Jacobi rotation, accumulated into ``vectors``."""
    if a[p, q] == 0.0:
        return
    theta = (a[q, q] - a[p, p]) / (2.0 * a[p, q])
    t = 1.0 / (abs(theta) + np.sqrt(theta * theta + 1.0))
    if theta < 0.0:
        t = -t
    c = 1.0 / np.sqrt(t * t + 1.0)
    s = t * c
    for k in range(3):
        akp, akq = a[k, p], a[k, q]
        a[k, p] = c * akp - s * akq
        a[k, q] = s * akp + c * akq
    for k in range(3):
        apk, aqk = a[p, k], a[q, k]
        a[p, k] = c * apk - s * aqk
        a[q, k] = s * apk + c * aqk
    for k in range(3):
        vkp, vkq = vectors[k, p], vectors[k, q]
        vectors[k, p] = c * vkp - s * vkq
        vectors[k, q] = s * vkp + c * vkq


@kernel
def symmetric_eigen_into(a: FloatArray, vectors: FloatArray, values: FloatArray) -> None:
    """Eigen decomposition of a symmetric 3 x 3 matrix ``a`` (overwritten) into ``values`` (descending) and
    ``vectors`` (orthonormal columns, det +1).

    Cyclic Jacobi rotations, each zeroing one off-diagonal entry, until the off-diagonal part is below
    rounding (a few sweeps: the convergence is quadratic). Allocation-free: it runs once per element.
    """
    for i in range(3):
        for k in range(3):
            vectors[i, k] = 1.0 if i == k else 0.0
    scale = abs(a[0, 0]) + abs(a[1, 1]) + abs(a[2, 2]) + 1e-300
    for _ in range(20):
        if abs(a[0, 1]) + abs(a[0, 2]) + abs(a[1, 2]) <= 1e-17 * scale:
            break
        _jacobi_rotate(a, vectors, 0, 1)
        _jacobi_rotate(a, vectors, 0, 2)
        _jacobi_rotate(a, vectors, 1, 2)
    for i in range(3):
        values[i] = a[i, i]
    for i in range(3):
        for j in range(2 - i):
            if values[j] < values[j + 1]:
                values[j], values[j + 1] = values[j + 1], values[j]
                for k in range(3):
                    vectors[k, j], vectors[k, j + 1] = vectors[k, j + 1], vectors[k, j]
    if _det3(vectors) < 0.0:
        for k in range(3):
            vectors[k, 2] = -vectors[k, 2]


@kernel
def _det3(m: FloatArray) -> float:
    det: float = (m[0, 0] * (m[1, 1] * m[2, 2] - m[1, 2] * m[2, 1])
                  - m[0, 1] * (m[1, 0] * m[2, 2] - m[1, 2] * m[2, 0])
                  + m[0, 2] * (m[1, 0] * m[2, 1] - m[1, 1] * m[2, 0]))
    return det


@kernel
def polar_rotation_into(f: FloatArray, rotation: FloatArray, work: FloatArray, v: FloatArray,
                        values: FloatArray) -> None:
    """Rotation R of the polar decomposition ``F = R S``, from the SVD ``F = U Sigma V^T``: ``R = U V^T``.

    V and the singular values come from the eigen decomposition of ``F^T F``; ``u_i = F v_i / sigma_i`` for
    the two largest, re-orthogonalised, and ``u_3 = u_1 x u_2`` so that R is a proper rotation: for an
    inverted element the smallest singular value takes the sign of det F, and a flat element (sigma_3 = 0)
    still has a well-defined R. A collapsed element (sigma_1 = 0) gets R = I. ``work``, ``v`` (3 x 3) and
    ``values`` (3) are scratch space.
    """
    for i in range(3):
        for j in range(3):
            total = 0.0
            for k in range(3):
                total += f[k, i] * f[k, j]
            work[i, j] = total
    symmetric_eigen_into(work, v, values)
    if values[0] <= 0.0:
        for i in range(3):
            for j in range(3):
                rotation[i, j] = 1.0 if i == j else 0.0
        return
    # work's columns become u_1, u_2, u_3.
    for column in range(2):
        for i in range(3):
            work[i, column] = f[i, 0] * v[0, column] + f[i, 1] * v[1, column] + f[i, 2] * v[2, column]
    norm = np.sqrt(work[0, 0] ** 2 + work[1, 0] ** 2 + work[2, 0] ** 2)
    for i in range(3):
        work[i, 0] /= norm
    projection = work[0, 0] * work[0, 1] + work[1, 0] * work[1, 1] + work[2, 0] * work[2, 1]
    for i in range(3):
        work[i, 1] -= projection * work[i, 0]
    norm_second = np.sqrt(work[0, 1] ** 2 + work[1, 1] ** 2 + work[2, 1] ** 2)
    if norm_second <= 1e-12 * norm:
        # A needle-like element: any direction normal to u_1 completes the frame.
        helper = 0 if abs(work[0, 0]) < 0.9 else 1
        for i in range(3):
            work[i, 1] = (1.0 if i == helper else 0.0) - work[helper, 0] * work[i, 0]
        norm_second = np.sqrt(work[0, 1] ** 2 + work[1, 1] ** 2 + work[2, 1] ** 2)
    for i in range(3):
        work[i, 1] /= norm_second
    work[0, 2] = work[1, 0] * work[2, 1] - work[2, 0] * work[1, 1]
    work[1, 2] = work[2, 0] * work[0, 1] - work[0, 0] * work[2, 1]
    work[2, 2] = work[0, 0] * work[1, 1] - work[1, 0] * work[0, 1]
    for i in range(3):
        for j in range(3):
            rotation[i, j] = work[i, 0] * v[j, 0] + work[i, 1] * v[j, 1] + work[i, 2] * v[j, 2]


@kernel
def polar_rotation(deformation_gradient: FloatArray) -> FloatArray:
    """The proper rotation of the polar decomposition of one 3 x 3 ``F`` (see :func:`polar_rotation_into`)."""
    rotation = np.empty((3, 3))
    polar_rotation_into(deformation_gradient, rotation, np.empty((3, 3)), np.empty((3, 3)), np.empty(3))
    return rotation


@kernel
def _rotate_blocks(element_stiffness: FloatArray, rotation: FloatArray, work: FloatArray, out: FloatArray) -> None:
    """``out = diag(R) K_e diag(R)^T``: each 3 x 3 block K_ab becomes ``R K_ab R^T``."""
    for a in range(4):
        for b in range(4):
            for i in range(3):
                for j in range(3):
                    total = 0.0
                    for k in range(3):
                        total += element_stiffness[3 * a + i, 3 * b + k] * rotation[j, k]
                    work[i, j] = total
            for i in range(3):
                for j in range(3):
                    total = 0.0
                    for k in range(3):
                        total += rotation[i, k] * work[k, j]
                    out[3 * a + i, 3 * b + j] = total


@kernel
def _skew(vector: FloatArray, out: FloatArray) -> None:
    """``out = [v]x``, the matrix of the cross product ``v x .``."""
    out[0, 0], out[0, 1], out[0, 2] = 0.0, -vector[2], vector[1]
    out[1, 0], out[1, 1], out[1, 2] = vector[2], 0.0, -vector[0]
    out[2, 0], out[2, 1], out[2, 2] = -vector[1], vector[0], 0.0


@kernel
def _matmul3(a: FloatArray, b: FloatArray, out: FloatArray) -> None:
    for i in range(3):
        for j in range(3):
            out[i, j] = a[i, 0] * b[0, j] + a[i, 1] * b[1, j] + a[i, 2] * b[2, j]


@kernel
def _inverse3(m: FloatArray, out: FloatArray) -> float:
    """``out = m^-1`` by the adjugate; returns det m."""
    det = _det3(m)
    out[0, 0] = (m[1, 1] * m[2, 2] - m[1, 2] * m[2, 1]) / det
    out[0, 1] = (m[0, 2] * m[2, 1] - m[0, 1] * m[2, 2]) / det
    out[0, 2] = (m[0, 1] * m[1, 2] - m[0, 2] * m[1, 1]) / det
    out[1, 0] = (m[1, 2] * m[2, 0] - m[1, 0] * m[2, 2]) / det
    out[1, 1] = (m[0, 0] * m[2, 2] - m[0, 2] * m[2, 0]) / det
    out[1, 2] = (m[0, 2] * m[1, 0] - m[0, 0] * m[1, 2]) / det
    out[2, 0] = (m[1, 0] * m[2, 1] - m[1, 1] * m[2, 0]) / det
    out[2, 1] = (m[0, 1] * m[2, 0] - m[0, 0] * m[2, 1]) / det
    out[2, 2] = (m[0, 0] * m[1, 1] - m[0, 1] * m[1, 0]) / det
    return det


@inline_kernel
def _edge_matrix(positions_m: FloatArray, tets: IntArray, e: int, out: FloatArray) -> None:
    """``out = [x1 - x0, x2 - x0, x3 - x0]`` (columns) of element ``e``'s corners ``tets[e, :4]``."""
    for k in range(3):
        for axis in range(3):
            out[axis, k] = positions_m[tets[e, k + 1], axis] - positions_m[tets[e, 0], axis]


@inline_kernel
def _deformation_gradient(positions_m: FloatArray, tets: IntArray, e: int, dm_inverse: FloatArray, ds: FloatArray,
                          out: FloatArray) -> None:
    """``out = F = Ds Dm^-1`` of 4-node element ``e`` at node positions ``positions_m`` (``ds``: 3 x 3 scratch)."""
    _edge_matrix(positions_m, tets, e, ds)
    for i in range(3):
        for j in range(3):
            out[i, j] = (ds[i, 0] * dm_inverse[e, 0, j] + ds[i, 1] * dm_inverse[e, 1, j]
                         + ds[i, 2] * dm_inverse[e, 2, j])


@inline_kernel
def _quadratic_deformation_gradient(x: FloatArray, point_gradients: FloatArray, out: FloatArray) -> None:
    """``out = F = sum_a x_a G_a^T`` of a 10-node element with node positions ``x`` (10, 3) at a point where the
    shape functions' rest gradients are ``point_gradients`` (10, 3)."""
    for i in range(3):
        for j in range(3):
            total = 0.0
            for a in range(10):
                total += x[a, i] * point_gradients[a, j]
            out[i, j] = total


@kernel
def _add_rotation_stiffness(element_stiffness: FloatArray, rotation: FloatArray, deformation_gradient: FloatArray,
                            dm_inverse: FloatArray, local_force: FloatArray, unrotated_m: FloatArray, out: FloatArray,
                            scratch: FloatArray) -> None:
    """Add the Hessian terms from the rotation's derivative (module docstring) to the 12 x 12 ``out``.

    ``scratch`` is (14, 3, 3) work space: no allocation per element.
    """
    s, shifted, inverse, skew, z, product = scratch[0], scratch[1], scratch[2], scratch[3], scratch[4], scratch[5]
    left, right = scratch[6:10], scratch[10:14]
    for i in range(3):
        for j in range(3):
            s[i, j] = (rotation[0, i] * deformation_gradient[0, j] + rotation[1, i] * deformation_gradient[1, j]
                       + rotation[2, i] * deformation_gradient[2, j])
    trace = s[0, 0] + s[1, 1] + s[2, 2]
    for i in range(3):
        for j in range(3):
            shifted[i, j] = -s[i, j]
        shifted[i, i] += trace
    if _det3(shifted) <= 1e-12 * abs(trace) ** 3:
        return  # inverted past the point where the rotation is differentiable: keep R K R^T
    _inverse3(shifted, inverse)
    for a in range(4):
        _skew(local_force[3 * a:3 * a + 3], skew)
        for i in range(3):
            for j in range(3):
                z[i, j] = -skew[i, j]
        for c in range(4):
            _skew(unrotated_m[c], skew)
            for i in range(3):
                for j in range(3):
                    z[i, j] += (element_stiffness[3 * a + i, 3 * c] * skew[0, j]
                                + element_stiffness[3 * a + i, 3 * c + 1] * skew[1, j]
                                + element_stiffness[3 * a + i, 3 * c + 2] * skew[2, j])
        _matmul3(rotation, z, product)
        _matmul3(product, inverse, left[a])
        if a == 0:
            for axis in range(3):
                s[0, axis] = -(dm_inverse[0, axis] + dm_inverse[1, axis] + dm_inverse[2, axis])
        else:
            for axis in range(3):
                s[0, axis] = dm_inverse[a - 1, axis]
        _skew(s[0], skew)
        for i in range(3):
            for j in range(3):
                right[a][i, j] = skew[i, 0] * rotation[j, 0] + skew[i, 1] * rotation[j, 1] + skew[i, 2] * rotation[j, 2]
    for a in range(4):
        for b in range(4):
            _matmul3(left[a], right[b], product)
            for i in range(3):
                for j in range(3):
                    out[3 * a + i, 3 * b + j] += product[i, j]


@kernel
def internal_forces(positions_m: FloatArray, rest_positions_m: FloatArray, tets: IntArray, dm_inverse: FloatArray,
                    stiffness: FloatArray, corotational: bool, want_matrix: int, scatter: IntArray,
                    matrix_data: FloatArray) -> tuple[FloatArray, float, float]:
    """Elastic nodal forces (N, (n, 3)), elastic energy (J), smallest ``det F``; optionally the tangent.

    Corotational: ``f = R K_e (R^T x - X)``; linear: ``f = K_e (x - X)``. When ``want_matrix`` is 1, the
    blocks ``R K_e R^T`` (or ``K_e``) are added into ``matrix_data`` (the CSR data array, zeroed by the
    caller) at the positions ``scatter[e, i, j]``; when 2 (co-rotational only), the exact Hessian, with the
    rotation's derivative (it may be indefinite far from rest).
    """
    n_tets = tets.shape[0]
    forces = np.zeros(positions_m.shape)
    energy_j = 0.0
    smallest_det = np.inf
    rotation = np.eye(3)
    ds = np.empty((3, 3))
    deformation_gradient = np.empty((3, 3))
    work = np.empty((3, 3))
    singular_vectors = np.empty((3, 3))
    values = np.empty(3)
    displacement = np.empty(12)
    local_force = np.empty(12)
    rotated_stiffness = np.empty((12, 12))
    unrotated_m = np.empty((4, 3))
    scratch = np.empty((14, 3, 3))
    for e in range(n_tets):
        if corotational:
            _deformation_gradient(positions_m, tets, e, dm_inverse, ds, deformation_gradient)
            det = _det3(deformation_gradient)
            if det < smallest_det:
                smallest_det = det
            polar_rotation_into(deformation_gradient, rotation, work, singular_vectors, values)
        for a in range(4):
            node = tets[e, a]
            for i in range(3):
                rotated = 0.0
                for j in range(3):
                    rotated += rotation[j, i] * positions_m[node, j]
                displacement[3 * a + i] = rotated - rest_positions_m[node, i]
        element_energy = 0.0
        for i in range(12):
            total = 0.0
            for j in range(12):
                total += stiffness[e, i, j] * displacement[j]
            local_force[i] = total
            element_energy += displacement[i] * total
        energy_j += 0.5 * element_energy
        for a in range(4):
            node = tets[e, a]
            for i in range(3):
                value = 0.0
                for j in range(3):
                    value += rotation[i, j] * local_force[3 * a + j]
                forces[node, i] += value
        if want_matrix:
            if corotational:
                _rotate_blocks(stiffness[e], rotation, work, rotated_stiffness)
                if want_matrix == 2:
                    for a in range(4):
                        for i in range(3):
                            unrotated_m[a, i] = displacement[3 * a + i] + rest_positions_m[tets[e, a], i]
                    _add_rotation_stiffness(stiffness[e], rotation, deformation_gradient, dm_inverse[e],
                                            local_force, unrotated_m, rotated_stiffness, scratch)
                for i in range(12):
                    for j in range(12):
                        matrix_data[scatter[e, i, j]] += rotated_stiffness[i, j]
            else:
                for i in range(12):
                    for j in range(12):
                        matrix_data[scatter[e, i, j]] += stiffness[e, i, j]
    return forces, energy_j, smallest_det


@kernel
def hyperelastic_forces(positions_m: FloatArray, tets: IntArray, dm_inverse: FloatArray, volumes_m3: FloatArray,
                        law: int, parameters: FloatArray, lame_mu_pa: float, lame_lambda_pa: float, want_matrix: int,
                        scatter: IntArray, matrix_data: FloatArray) -> tuple[FloatArray, float, float]:
    """Nodal forces (N, (n, 3)), energy (J) and the smallest ``det F`` of 4-node elements of a hyperelastic law;
    optionally its exact tangent added into ``matrix_data`` at ``scatter``.

    ``W = W_law(I1) - mu ln J + (lambda / 2) (ln J)^2`` per unit rest volume, ``W_law`` the law number ``law``
    with ``parameters`` (:mod:`phantom.model.fem.materials`). With ``W' = dW_law/dI1``, ``W''``, ``c = lambda ln J
    - mu`` and ``H = F^-T``: ``P = 2 W' F + c H``, node force ``f_a = V P G_a`` (``G_a`` the shape-function
    gradients), and the 3 x 3 tangent block ``K_ab = V [2 W' (G_a . G_b) I + 4 W'' (F G_a)(F G_b)^T
    + lambda (H G_a)(H G_b)^T - c (H G_b)(H G_a)^T]``. An element with ``J <= 0`` or outside the law's domain
    (Gent's lock) has +inf energy (a line search rejects the step) and adds no force or stiffness.
    """
    n_tets = tets.shape[0]
    forces = np.zeros(positions_m.shape)
    energy_j = 0.0
    smallest_det = np.inf
    ds = np.empty((3, 3))
    f = np.empty((3, 3))
    h = np.empty((3, 3))
    gradients = np.empty((4, 3))
    stretched = np.empty((4, 3))
    pulled = np.empty((4, 3))
    block = np.empty((12, 12))
    for e in range(n_tets):
        _deformation_gradient(positions_m, tets, e, dm_inverse, ds, f)
        det = _cofactor3(f, h)
        if det < smallest_det:
            smallest_det = det
        first_invariant = 0.0
        for i in range(3):
            for j in range(3):
                first_invariant += f[i, j] * f[i, j]
        deviatoric, first, second = law_energy(law, first_invariant - 3.0, parameters)
        if not det > 0.0 or not deviatoric < np.inf:
            energy_j = np.inf
            continue
        log_det = np.log(det)
        volume = volumes_m3[e]
        energy_j += volume * (deviatoric - lame_mu_pa * log_det + 0.5 * lame_lambda_pa * log_det * log_det)
        inverse_det = 1.0 / det  # H = cof(F) / det F: one division, not nine
        for i in range(3):
            for j in range(3):
                h[i, j] *= inverse_det
        shear = 2.0 * first
        coupling = lame_lambda_pa * log_det - lame_mu_pa
        for axis in range(3):
            gradients[1, axis] = dm_inverse[e, 0, axis]
            gradients[2, axis] = dm_inverse[e, 1, axis]
            gradients[3, axis] = dm_inverse[e, 2, axis]
            gradients[0, axis] = -(dm_inverse[e, 0, axis] + dm_inverse[e, 1, axis] + dm_inverse[e, 2, axis])
        for a in range(4):
            for i in range(3):
                stretched[a, i] = f[i, 0] * gradients[a, 0] + f[i, 1] * gradients[a, 1] + f[i, 2] * gradients[a, 2]
                pulled[a, i] = h[i, 0] * gradients[a, 0] + h[i, 1] * gradients[a, 1] + h[i, 2] * gradients[a, 2]
            node = tets[e, a]
            for i in range(3):
                forces[node, i] += volume * (shear * stretched[a, i] + coupling * pulled[a, i])
        if want_matrix:
            stiffening_term = 4.0 * second
            for a in range(4):
                for b in range(4):
                    dot = (gradients[a, 0] * gradients[b, 0] + gradients[a, 1] * gradients[b, 1]
                           + gradients[a, 2] * gradients[b, 2])
                    for i in range(3):
                        for k in range(3):
                            value = (stiffening_term * stretched[a, i] * stretched[b, k]
                                     + lame_lambda_pa * pulled[a, i] * pulled[b, k]
                                     - coupling * pulled[b, i] * pulled[a, k])
                            if i == k:
                                value += shear * dot
                            block[3 * a + i, 3 * b + k] = volume * value
            for i in range(12):
                for j in range(12):
                    matrix_data[scatter[e, i, j]] += block[i, j]
    return forces, energy_j, smallest_det


@kernel
def deformation_determinants(positions_m: FloatArray, tets: IntArray, dm_inverse: FloatArray) -> FloatArray:
    """``det F_e`` of each element (volume ratio current / rest)."""
    dets = np.empty(tets.shape[0])
    ds = np.empty((3, 3))
    for e in range(tets.shape[0]):
        _edge_matrix(positions_m, tets, e, ds)
        dets[e] = _det3(ds) * _det3(dm_inverse[e])
    return dets


@kernel
def _cofactor3(m: FloatArray, out: FloatArray) -> float:
    """``out = cof(m) = det(m) m^-T`` (no division: defined for a singular m); returns det m."""
    out[0, 0] = m[1, 1] * m[2, 2] - m[1, 2] * m[2, 1]
    out[0, 1] = m[1, 2] * m[2, 0] - m[1, 0] * m[2, 2]
    out[0, 2] = m[1, 0] * m[2, 1] - m[1, 1] * m[2, 0]
    out[1, 0] = m[0, 2] * m[2, 1] - m[0, 1] * m[2, 2]
    out[1, 1] = m[0, 0] * m[2, 2] - m[0, 2] * m[2, 0]
    out[1, 2] = m[0, 1] * m[2, 0] - m[0, 0] * m[2, 1]
    out[2, 0] = m[0, 1] * m[1, 2] - m[0, 2] * m[1, 1]
    out[2, 1] = m[0, 2] * m[1, 0] - m[0, 0] * m[1, 2]
    out[2, 2] = m[0, 0] * m[1, 1] - m[0, 1] * m[1, 0]
    det: float = m[0, 0] * out[0, 0] + m[0, 1] * out[0, 1] + m[0, 2] * out[0, 2]
    return det


@kernel
def _element_volume(x: FloatArray, volume_derivatives: FloatArray, volume_weights: FloatArray,
                    jacobians: FloatArray, volume_gradient: FloatArray) -> float:
    """Current volume (m^3) of one 10-node element at node positions ``x`` (10, 3), exact (the degree-3 rule
    integrates ``det(dx/dxi)``, a cubic); its gradient into ``volume_gradient`` (10, 3) and ``dx/dxi`` at each
    point into ``jacobians`` (q, 3, 3)."""
    cofactor = np.empty((3, 3))
    volume = 0.0
    for a in range(10):
        for i in range(3):
            volume_gradient[a, i] = 0.0
    for q in range(volume_weights.shape[0]):
        for i in range(3):
            for k in range(3):
                total = 0.0
                for a in range(10):
                    total += x[a, i] * volume_derivatives[q, a, k]
                jacobians[q, i, k] = total
        det = _cofactor3(jacobians[q], cofactor)
        volume += volume_weights[q] * det
        for a in range(10):
            for i in range(3):
                volume_gradient[a, i] += volume_weights[q] * (
                    cofactor[i, 0] * volume_derivatives[q, a, 0] + cofactor[i, 1] * volume_derivatives[q, a, 1]
                    + cofactor[i, 2] * volume_derivatives[q, a, 2])
    return volume


@inline_kernel
def _element_volume_at(positions_m: FloatArray, tets: IntArray, e: int, x: FloatArray, volume_derivatives: FloatArray,
                       volume_weights: FloatArray, jacobians: FloatArray, volume_gradient: FloatArray) -> float:
    """:func:`_element_volume` of element ``e``, its node positions first gathered from ``positions_m`` into
    ``x`` (10, 3), which the caller may use after."""
    for a in range(10):
        for i in range(3):
            x[a, i] = positions_m[tets[e, a], i]
    return _element_volume(x, volume_derivatives, volume_weights, jacobians, volume_gradient)


@kernel
def mixed_forces(positions_m: FloatArray, tets: IntArray, gradients: FloatArray, weights: FloatArray,
                 rest_volumes_m3: FloatArray, volume_derivatives: FloatArray, volume_weights: FloatArray,
                 law: int, parameters: FloatArray, bulk_modulus_pa: float, want_matrix: int, block_start: IntArray,
                 degree: IntArray, matrix_data: FloatArray,
                 element_pressures_pa: FloatArray) -> tuple[FloatArray, float, float]:
    """Nodal forces (N, (n, 3)), energy (J) and the smallest volume ratio of 10-node tetrahedra in the mixed
    (displacement, pressure, dilatation) formulation condensed element by element; optionally its exact tangent.

    Per element, with a constant pressure and dilatation (P2/P0): ``Pi_e = integral W_iso(I1bar) dV + V_e U(Jbar)``,
    ``Jbar = v_e / V_e`` the element's current over rest volume (exact), ``U = K/2 (Jbar - 1)^2``, its pressure
    ``p = K (Jbar - 1)``; ``I1bar = J^(-2/3) I1`` at each quadrature point (``gradients`` (m, q, 10, 3) the shape
    functions' rest gradients there, ``weights`` (m, q) the rest volume they stand for). ``W_iso`` is the law
    number ``law`` with ``parameters`` (:mod:`phantom.model.fem.materials`) of ``I = I1bar``. With ``A =
    dI1bar/dF = 2 J^(-2/3) F - (2/3) I1bar F^-T``, ``psi' = dW/dI1bar``: ``P = psi' A``. The tangent's deviatoric
    block is ``psi'' (A G_a)(A G_b)^T + psi' [2 J^(-2/3) (G_a . G_b) I - (4/3) J^(-2/3) ((F G_a)(H G_b)^T + (H
    G_a)(F G_b)^T) + (4/9) I1bar (H G_a)(H G_b)^T + (2/3) I1bar (H G_b)(H G_a)^T]`` (``H = F^-T``), its volumetric
    one ``(K / V_e) dv_a dv_b^T + p d2v/dx_a dx_b`` with ``d2 det(D)/dx_ai dx_bk = eps_ikm (D (g_a x g_b))_m`` at
    each volume point. An element at ``J <= 0`` (at a point), ``Jbar <= 0`` or outside the law's domain (Gent's
    lock) has infinite energy and adds no force or stiffness. The tangent goes into ``matrix_data`` at
    ``block_start[e, A, B] + 3 a degree[node A] + b`` (the body's CSR layout).

    ``element_pressures_pa`` (m,), when not empty, are the pressures as an independent field (Newton's iterate of
    the mixed system, :func:`phantom.model.fem.newton.newton`): they replace ``K (Jbar - 1)`` in the forces and
    the tangent's ``p d2v`` term, and the volumetric energy is the perturbed Lagrangian's ``V_e (p (Jbar - 1) -
    p^2 / 2K)``, which equals ``V_e U(Jbar)`` where ``p = K (Jbar - 1)``.
    """
    given_pressures = element_pressures_pa.shape[0] == tets.shape[0]
    n_tets = tets.shape[0]
    n_points = gradients.shape[1]
    forces = np.zeros(positions_m.shape)
    energy_j = 0.0
    smallest_det = np.inf
    x = np.empty((10, 3))
    f = np.empty((3, 3))
    cofactor = np.empty((3, 3))
    jacobians = np.empty((volume_weights.shape[0], 3, 3))
    volume_gradient = np.empty((10, 3))
    local_force = np.empty((10, 3))
    stretched = np.empty((10, 3))
    pulled = np.empty((10, 3))
    directional = np.empty((10, 3))
    block = np.empty((30, 30))
    axial = np.empty(3)
    for e in range(n_tets):
        for a in range(10):
            node = tets[e, a]
            for i in range(3):
                x[a, i] = positions_m[node, i]
        rest_volume = rest_volumes_m3[e]
        volume_ratio = _element_volume(x, volume_derivatives, volume_weights, jacobians, volume_gradient) / rest_volume
        if volume_ratio < smallest_det:
            smallest_det = volume_ratio
        if not volume_ratio > 0.0:
            energy_j = np.inf
            continue
        if given_pressures:
            pressure = element_pressures_pa[e]
            element_energy = rest_volume * (pressure * (volume_ratio - 1.0) - 0.5 * pressure * pressure
                                            / bulk_modulus_pa)
        else:
            pressure = bulk_modulus_pa * (volume_ratio - 1.0)
            element_energy = 0.5 * bulk_modulus_pa * rest_volume * (volume_ratio - 1.0) ** 2
        for a in range(10):
            for i in range(3):
                local_force[a, i] = pressure * volume_gradient[a, i]
        if want_matrix:
            for i in range(30):
                for j in range(30):
                    block[i, j] = 0.0
        admissible = True
        for q in range(n_points):
            _quadratic_deformation_gradient(x, gradients[e, q], f)
            det = _cofactor3(f, cofactor)
            if det < smallest_det:
                smallest_det = det
            first_invariant = 0.0
            for i in range(3):
                for j in range(3):
                    first_invariant += f[i, j] * f[i, j]
            if not det > 0.0:
                admissible = False
                break
            scale = det ** (-2.0 / 3.0)
            isochoric = scale * first_invariant
            distortional, first, second = law_energy(law, isochoric - 3.0, parameters)
            if not distortional < np.inf:
                admissible = False
                break
            element_energy += weights[e, q] * distortional
            for a in range(10):
                for i in range(3):
                    stretched[a, i] = (f[i, 0] * gradients[e, q, a, 0] + f[i, 1] * gradients[e, q, a, 1]
                                       + f[i, 2] * gradients[e, q, a, 2])
                    pulled[a, i] = (cofactor[i, 0] * gradients[e, q, a, 0] + cofactor[i, 1] * gradients[e, q, a, 1]
                                    + cofactor[i, 2] * gradients[e, q, a, 2]) / det
                    directional[a, i] = 2.0 * scale * stretched[a, i] - (2.0 / 3.0) * isochoric * pulled[a, i]
                    local_force[a, i] += weights[e, q] * first * directional[a, i]
            if want_matrix:
                weight = weights[e, q]
                for a in range(10):
                    for b in range(a, 10):
                        dot = (gradients[e, q, a, 0] * gradients[e, q, b, 0] + gradients[e, q, a, 1]
                               * gradients[e, q, b, 1] + gradients[e, q, a, 2] * gradients[e, q, b, 2])
                        for i in range(3):
                            for k in range(3):
                                value = (second * directional[a, i] * directional[b, k] + first * (
                                    -(4.0 / 3.0) * scale * (stretched[a, i] * pulled[b, k]
                                                            + pulled[a, i] * stretched[b, k])
                                    + (4.0 / 9.0) * isochoric * pulled[a, i] * pulled[b, k]
                                    + (2.0 / 3.0) * isochoric * pulled[b, i] * pulled[a, k]))
                                if i == k:
                                    value += first * 2.0 * scale * dot
                                block[3 * a + i, 3 * b + k] += weight * value
        if not admissible:
            energy_j = np.inf
            continue
        energy_j += element_energy
        for a in range(10):
            node = tets[e, a]
            for i in range(3):
                forces[node, i] += local_force[a, i]
        if not want_matrix:
            continue
        stiffness = bulk_modulus_pa / rest_volume
        for a in range(10):
            for b in range(a, 10):
                for i in range(3):
                    for k in range(3):
                        block[3 * a + i, 3 * b + k] += stiffness * volume_gradient[a, i] * volume_gradient[b, k]
                for q in range(volume_weights.shape[0]):
                    # d2 det(D) / dx_ai dx_bk = eps_ikm (D (g_a x g_b))_m
                    ga0, ga1, ga2 = (volume_derivatives[q, a, 0], volume_derivatives[q, a, 1],
                                     volume_derivatives[q, a, 2])
                    gb0, gb1, gb2 = (volume_derivatives[q, b, 0], volume_derivatives[q, b, 1],
                                     volume_derivatives[q, b, 2])
                    c0, c1, c2 = ga1 * gb2 - ga2 * gb1, ga2 * gb0 - ga0 * gb2, ga0 * gb1 - ga1 * gb0
                    for m in range(3):
                        axial[m] = (jacobians[q, m, 0] * c0 + jacobians[q, m, 1] * c1
                                    + jacobians[q, m, 2] * c2) * pressure * volume_weights[q]
                    block[3 * a + 0, 3 * b + 1] += axial[2]
                    block[3 * a + 1, 3 * b + 0] -= axial[2]
                    block[3 * a + 1, 3 * b + 2] += axial[0]
                    block[3 * a + 2, 3 * b + 1] -= axial[0]
                    block[3 * a + 2, 3 * b + 0] += axial[1]
                    block[3 * a + 0, 3 * b + 2] -= axial[1]
        for a in range(10):
            row_node = tets[e, a]
            for b in range(10):
                start = block_start[e, a, b]
                stride = 3 * degree[row_node]
                for i in range(3):
                    for k in range(3):
                        value = block[3 * a + i, 3 * b + k] if b >= a else block[3 * b + k, 3 * a + i]
                        matrix_data[start + stride * i + k] += value
    return forces, energy_j, smallest_det


@kernel
def mixed_determinants(positions_m: FloatArray, tets: IntArray, gradients: FloatArray, rest_volumes_m3: FloatArray,
                       volume_derivatives: FloatArray, volume_weights: FloatArray) -> FloatArray:
    """The smallest volume ratio of each 10-node element: its ``Jbar`` (current over rest volume) or ``det F`` at
    one of its quadrature points, whichever is less (m,)."""
    n_tets = tets.shape[0]
    smallest = np.empty(n_tets)
    x = np.empty((10, 3))
    f = np.empty((3, 3))
    jacobians = np.empty((volume_weights.shape[0], 3, 3))
    volume_gradient = np.empty((10, 3))
    for e in range(n_tets):
        least = _element_volume_at(positions_m, tets, e, x, volume_derivatives, volume_weights, jacobians,
                                   volume_gradient) / rest_volumes_m3[e]
        for q in range(gradients.shape[1]):
            _quadratic_deformation_gradient(x, gradients[e, q], f)
            det = _det3(f)
            if det < least:
                least = det
        smallest[e] = least
    return smallest


@kernel
def mixed_volume_ratios(positions_m: FloatArray, tets: IntArray, rest_volumes_m3: FloatArray,
                        volume_derivatives: FloatArray, volume_weights: FloatArray) -> FloatArray:
    """Each 10-node element's current over rest volume, its ``Jbar`` (m,)."""
    ratios = np.empty(tets.shape[0])
    x = np.empty((10, 3))
    jacobians = np.empty((volume_weights.shape[0], 3, 3))
    volume_gradient = np.empty((10, 3))
    for e in range(tets.shape[0]):
        volume_m3 = _element_volume_at(positions_m, tets, e, x, volume_derivatives, volume_weights, jacobians,
                                       volume_gradient)
        ratios[e] = volume_m3 / rest_volumes_m3[e]
    return ratios


@kernel
def add_element_pressure_forces(positions_m: FloatArray, tets: IntArray, volume_derivatives: FloatArray,
                                volume_weights: FloatArray, element_pressures_pa: FloatArray,
                                forces_n: FloatArray) -> None:
    """``forces_n`` (n, 3) += each 10-node element's pressure times its volume's gradient, ``sum_e p_e dV_e/dx``:
    the pressure part of :func:`mixed_forces`' forces, which is linear in the pressures."""
    x = np.empty((10, 3))
    jacobians = np.empty((volume_weights.shape[0], 3, 3))
    volume_gradient = np.empty((10, 3))
    for e in range(tets.shape[0]):
        _element_volume_at(positions_m, tets, e, x, volume_derivatives, volume_weights, jacobians, volume_gradient)
        for a in range(10):
            for i in range(3):
                forces_n[tets[e, a], i] += element_pressures_pa[e] * volume_gradient[a, i]


@kernel
def mixed_volume_ratio_rates(positions_m: FloatArray, direction_m: FloatArray, tets: IntArray,
                             rest_volumes_m3: FloatArray, volume_derivatives: FloatArray,
                             volume_weights: FloatArray) -> FloatArray:
    """Each 10-node element's ``d Jbar / ds`` (m,) at ``positions_m`` moving along ``direction_m`` (n, 3): its
    volume's gradient dotted with the element's nodes' moves, over its rest volume."""
    rates = np.empty(tets.shape[0])
    x = np.empty((10, 3))
    jacobians = np.empty((volume_weights.shape[0], 3, 3))
    volume_gradient = np.empty((10, 3))
    for e in range(tets.shape[0]):
        _element_volume_at(positions_m, tets, e, x, volume_derivatives, volume_weights, jacobians, volume_gradient)
        total = 0.0
        for a in range(10):
            for i in range(3):
                total += volume_gradient[a, i] * direction_m[tets[e, a], i]
        rates[e] = total / rest_volumes_m3[e]
    return rates


@kernel
def add_quadratic_pressure_stiffness(positions_m: FloatArray, faces: IntArray, pressure_pa: float,
                                     shape: FloatArray, derivatives: FloatArray, face_weights: FloatArray,
                                     indptr: IntArray, indices: Int32Array, matrix_data: FloatArray) -> None:
    """Add ``-p d2V/dx2`` of one chamber of 6-node faces to a CSR tangent's data (N/m).

    ``dV/dx_a = integral N_a (x_xi x x_eta)`` over each face, whose derivative by ``x_b`` is the block
    ``M_ab = integral N_a (dN_b/deta [x_xi]x - dN_b/dxi [x_eta]x)`` (degree 4: exact with the 6-point rule,
    ``shape`` (q, 6), ``derivatives`` (q, 6, 2), ``face_weights`` (q,)); summed over a closed wall it is symmetric,
    so each face adds ``-p (M + M^T) / 2``.
    """
    along_xi = np.empty(3)
    along_eta = np.empty(3)
    block = np.empty((18, 18))
    for t in range(faces.shape[0]):
        for i in range(18):
            for j in range(18):
                block[i, j] = 0.0
        for q in range(face_weights.shape[0]):
            for i in range(3):
                total_xi = 0.0
                total_eta = 0.0
                for a in range(6):
                    total_xi += derivatives[q, a, 0] * positions_m[faces[t, a], i]
                    total_eta += derivatives[q, a, 1] * positions_m[faces[t, a], i]
                along_xi[i] = total_xi
                along_eta[i] = total_eta
            for a in range(6):
                for b in range(6):
                    weight = face_weights[q] * shape[q, a]
                    s_eta = weight * derivatives[q, b, 1]
                    s_xi = weight * derivatives[q, b, 0]
                    # s_eta [x_xi]x - s_xi [x_eta]x, a skew matrix with axial vector s_eta x_xi - s_xi x_eta
                    w0 = s_eta * along_xi[0] - s_xi * along_eta[0]
                    w1 = s_eta * along_xi[1] - s_xi * along_eta[1]
                    w2 = s_eta * along_xi[2] - s_xi * along_eta[2]
                    block[3 * a + 0, 3 * b + 1] -= w2
                    block[3 * a + 0, 3 * b + 2] += w1
                    block[3 * a + 1, 3 * b + 0] += w2
                    block[3 * a + 1, 3 * b + 2] -= w0
                    block[3 * a + 2, 3 * b + 0] -= w1
                    block[3 * a + 2, 3 * b + 1] += w0
        for a in range(6):
            for b in range(6):
                for i in range(3):
                    for k in range(3):
                        value = -0.5 * pressure_pa * (block[3 * a + i, 3 * b + k] + block[3 * b + k, 3 * a + i])
                        position = _csr_position(indptr, indices, 3 * faces[t, a] + i, 3 * faces[t, b] + k)
                        matrix_data[position] += value


@kernel
def add_pressure_stiffness(positions_m: FloatArray, triangles: IntArray, pressure_pa: float, indptr: IntArray,
                           indices: Int32Array, matrix_data: FloatArray) -> None:
    """Add ``-p d2V/dx2`` of one chamber (oriented triangles) to a CSR tangent's data (N/m).

    With ``V = sum_t x_a . (x_b x x_c) / 6``, the block ``d2V / dx_a dx_b = -[x_c]x / 6`` for each cyclic
    order (a, b, c) of a triangle, and its transpose for (b, a); the follower load ``p dV/dx`` enters the
    residual with a minus sign.
    """
    skew = np.empty((3, 3))
    for t in range(triangles.shape[0]):
        for corner in range(3):
            a = triangles[t, corner]
            b = triangles[t, (corner + 1) % 3]
            c = triangles[t, (corner + 2) % 3]
            _skew(positions_m[c], skew)
            for i in range(3):
                for j in range(3):
                    value = pressure_pa * skew[i, j] / 6.0
                    row, column = 3 * a + i, 3 * b + j
                    position = _csr_position(indptr, indices, row, column)
                    matrix_data[position] += value
                    row, column = 3 * b + j, 3 * a + i
                    position = _csr_position(indptr, indices, row, column)
                    matrix_data[position] += value


@kernel
def _csr_position(indptr: IntArray, indices: Int32Array, row: int, column: int) -> int:
    low: int = indptr[row]
    high: int = indptr[row + 1]
    while low < high:
        middle = (low + high) // 2
        if indices[middle] < column:
            low = middle + 1
        else:
            high = middle
    return low


@kernel
def csr_multiply(indptr: IntArray, indices: Int32Array, data: FloatArray, vector: FloatArray) -> FloatArray:
    """``A v`` for the CSR matrix ``A = (data, indices, indptr)`` (square, n = len(indptr) - 1)."""
    n = indptr.shape[0] - 1
    product = np.empty(n)
    for row in range(n):
        total = 0.0
        for position in range(indptr[row], indptr[row + 1]):
            total += data[position] * vector[indices[position]]
        product[row] = total
    return product


@kernel
def cholesky_solve(indptr: IntArray, indices: Int32Array, values: FloatArray, permutation: IntArray,
                   rhs: FloatArray) -> FloatArray:
    """Solve ``A x = b`` from ``A[P][:, P] = L L^T`` (L lower triangular, CSC, diagonal first in each column).

    ``x[P] = L^-T L^-1 b[P]``: a forward substitution by columns, then a backward one with L's columns as the
    rows of L^T. ``rhs`` is (n, k); the exported wrapper also takes (n,).
    """
    right = rhs
    n, k = right.shape
    solution = np.empty((n, k))
    work = np.empty(n)
    for column in range(k):
        for i in range(n):
            work[i] = right[permutation[i], column]
        for j in range(n):
            work[j] /= values[indptr[j]]
            value = work[j]
            for position in range(indptr[j] + 1, indptr[j + 1]):
                work[indices[position]] -= values[position] * value
        for j in range(n - 1, -1, -1):
            total = work[j]
            for position in range(indptr[j] + 1, indptr[j + 1]):
                total -= values[position] * work[indices[position]]
            work[j] = total / values[indptr[j]]
        for i in range(n):
            solution[permutation[i], column] = work[i]
    return solution


def _exported(name: str, implementation: Callable[..., Any],
              argument_dtypes: tuple[str | None, ...]) -> Callable[..., Any]:
    """``name`` with its array arguments made C-contiguous of the dtypes the build was typed for."""

    def call(*arguments: Any) -> Any:
        converted = []
        for argument, dtype in zip(arguments, argument_dtypes, strict=True):
            if dtype == "out":
                if argument.dtype != np.float64 or not argument.flags.c_contiguous:
                    raise TypeError(f"{name}: the output array must be C-contiguous float64")
            elif dtype is not None:
                argument = np.ascontiguousarray(argument, dtype=dtype)
            converted.append(argument)
        if name == "cholesky_solve" and converted[-1].ndim == 1:
            return implementation(*converted[:-1], converted[-1][:, None].copy())[:, 0].copy()
        return implementation(*converted)

    call.__name__ = name
    call.__doc__ = implementation.__doc__
    return call


#: The JIT dispatchers of the exported kernels (None when the ahead-of-time build is in use).
JIT_KERNELS: dict[str, Any] | None = None if COMPILED is not None else {name: globals()[name] for name in EXPORTS}
forget_stale_jit_cache(building=__name__ == "__main__")
for _name, (_dtypes, _) in EXPORTS.items():
    globals()[_name] = _exported(_name, getattr(COMPILED, _name) if COMPILED else globals()[_name], _dtypes)


def build_compiled() -> Path:
    """Compile the exported kernels ahead of time (numba.pycc, for this machine's CPU) to
    :func:`compiled_kernels_path`, which later imports of this module then use. Needs the JIT kernels (run it
    with ``PHANTOM_JIT_KERNELS=1``, as ``python -m phantom.model.fem.kernels`` does) and a C compiler."""
    if JIT_KERNELS is None:
        raise RuntimeError("build_compiled needs the JIT kernels: set PHANTOM_JIT_KERNELS=1")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # numba.pycc announces its future deprecation
        from numba.pycc import CC  # the JIT kernels loaded numba already; pycc only for this build
    path = compiled_kernels_path()
    with tempfile.TemporaryDirectory(dir=path.parent) as build_dir:
        compiler = CC(path.name.split(".")[0])
        compiler.output_dir = build_dir
        compiler.output_file = path.name
        compiler.target_cpu = "host"
        compiler.verbose = False
        for name, (_, signature) in EXPORTS.items():
            compiler.export(name, signature)(JIT_KERNELS[name].py_func)
        compiler.compile()
        os.replace(Path(build_dir) / path.name, path)
    for stale in path.parent.glob("phantom_kernels_*.so"):
        if stale != path:
            stale.unlink(missing_ok=True)
    return path


if __name__ == "__main__":
    if JIT_KERNELS is None:
        print(f"phantom: the kernels are already built ahead of time: {compiled_kernels_path()}")
    else:
        print(f"phantom: built the kernels ahead of time: {build_compiled()}")
