"""The factorisations the model chooses between agree, and CHOLMOD refuses what it cannot factorise."""

import numpy as np
import pytest
import scipy.sparse as sp

from phantom.model.fem.linsolve import Factorization, default_method, indefinite_method


def laplacian_3d(n):
    """The 7-point Laplacian on an n^3 grid plus identity: sparse, symmetric positive definite."""
    one_d = sp.diags([-1.0, 2.0, -1.0], [-1, 0, 1], shape=(n, n))
    eye = sp.identity(n)
    return (sp.kron(sp.kron(one_d, eye), eye) + sp.kron(sp.kron(eye, one_d), eye)
            + sp.kron(sp.kron(eye, eye), one_d) + sp.identity(n**3)).tocsr()


def test_default_is_cholmod_when_installed():
    assert default_method() == "cholmod"


@pytest.mark.parametrize("method", ["cholmod", "cholmod-ldl", "splu-mmd", "splu-colamd"])
def test_factorisations_solve_to_rounding(method):
    matrix = laplacian_3d(12)
    rhs = np.random.default_rng(1).normal(size=(matrix.shape[0], 3))
    solution = Factorization(matrix, method).solve(rhs)
    # Condition number about 13 here: the residual is rounding, 1e-14 of the right-hand side.
    assert np.abs(matrix @ solution - rhs).max() < 1e-12 * np.abs(rhs).max()


def test_cholmod_refuses_an_indefinite_matrix_and_superlu_takes_it():
    matrix = laplacian_3d(6) - 3.0 * sp.identity(216)
    with pytest.raises(ArithmeticError, match="not positive definite"):
        Factorization(matrix, "cholmod")
    rhs = np.ones(216)
    assert np.abs(matrix @ Factorization(matrix, "splu-mmd").solve(rhs) - rhs).max() < 1e-10
    with pytest.raises(ValueError, match="unknown linear solver"):
        Factorization(matrix, "pardiso")


def test_an_indefinite_matrix_goes_to_cholmods_ldl_which_solves_it_and_prints_nothing(capfd):
    """A tangent past a limit point is symmetric indefinite: CHOLMOD's LDL' takes it as it is (SuperLU's
    symmetric-mode LU of such tangents printed "On entry to DTRSV parameter number 6 had an illegal value" from
    C during volume-controlled steps), to rounding, and nothing reaches the C-level stdout or stderr; a singular
    one (a zero pivot) is refused."""
    assert indefinite_method() == "cholmod-ldl"
    matrix = laplacian_3d(8) - 3.0 * sp.identity(512)
    rhs = np.random.default_rng(2).normal(size=(512, 2))
    factorization = Factorization(matrix, indefinite_method())
    solution = factorization.solve(rhs)
    assert np.abs(matrix @ solution - rhs).max() < 1e-10 * np.abs(rhs).max()
    assert capfd.readouterr() == ("", "")
    with pytest.raises(ArithmeticError, match="singular"):
        Factorization(sp.csr_matrix(np.diag([1.0, 0.0, 2.0])), "cholmod-ldl")
