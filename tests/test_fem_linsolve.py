"""The factorisations the model chooses between agree, and CHOLMOD refuses what it cannot factorise."""

import os

import numpy as np
import pytest
import scipy.sparse as sp

from phantom.model.fem.linsolve import (
    Factorization,
    FillOrdering,
    cholmod_ordering,
    default_method,
    indefinite_method,
)


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


@pytest.mark.parametrize("shift", [0.0, 3.0])   # positive definite (LL'), indefinite (LDL')
def test_a_kept_ordering_factorises_the_permuted_matrix_to_the_same_solution(shift):
    """With CHOLMOD's ordering kept (FillOrdering), the permuted matrix is factorised in its natural order: the
    same solutions as CHOLMOD ordering it itself, and a stored factor whose permutation is the composition."""
    matrix = laplacian_3d(9) - shift * sp.identity(729, format="csr")
    matrix = matrix.tocsr()
    matrix.sort_indices()
    permutation = cholmod_ordering(laplacian_3d(9))
    assert not np.array_equal(permutation, np.arange(729))        # (a real reordering, not the identity)
    ordering = FillOrdering(permutation, matrix.indptr, matrix.indices)
    rhs = np.random.default_rng(3).normal(size=(729, 2))
    method = "cholmod" if shift == 0.0 else "cholmod-ldl"
    ordered = Factorization(matrix, method, ordering=ordering)
    again = Factorization(matrix * 2.0, method, ordered.analysis, ordering)       # the analysis reused
    for factorization, scale in ((ordered, 1.0), (again, 2.0)):
        solution = factorization.solve(rhs)
        np.testing.assert_allclose(solution, Factorization(matrix, method).solve(rhs) / scale, rtol=0,
                                   atol=1e-11 * np.abs(solution).max())
        np.testing.assert_allclose(factorization.solve(rhs[:, 0]), solution[:, 0], rtol=0,
                                   atol=1e-14 * np.abs(solution).max())                 # one right-hand side
    if shift == 0.0:
        stored = ordered.cholesky_factor()
        assert stored is not None
        np.testing.assert_allclose(stored.solve(rhs), ordered.solve(rhs), rtol=0, atol=1e-11 * np.abs(rhs).max())


def test_an_ordering_that_is_not_a_permutation_is_refused():
    matrix = laplacian_3d(4)
    for bad in (np.arange(63), np.zeros(64, dtype=int), np.arange(1, 65)):
        with pytest.raises(ValueError, match="not a permutation of the pattern's 64 rows"):
            FillOrdering(bad, matrix.indptr, matrix.indices)


def test_a_cholmod_factorisation_starts_no_threads():
    """Debian's CHOLMOD ran its supernodal loops on four OpenMP threads whatever OMP_NUM_THREADS said: on two
    cores they spent a third of a full solve in system time. Importing the solver caps OpenMP at one thread."""
    import subprocess
    import sys

    script = (
        "import os, numpy as np, scipy.sparse as sp\n"
        "from phantom.model.fem.linsolve import Factorization\n"
        # a factorisation too small for CHOLMOD's parallel loops loads every library and its own threads
        "Factorization(sp.identity(3, format='csr') * 2.0, 'cholmod').solve(np.ones(3))\n"
        "matrix = (sp.diags([-1.0, 6.5, -1.0], [-1, 0, 1], shape=(20000, 20000))\n"
        "          + sp.diags([-1.0, -1.0], [-400, 400], shape=(20000, 20000))).tocsr()\n"
        "before = len(os.listdir('/proc/self/task'))\n"
        "Factorization(matrix, 'cholmod').solve(np.ones(matrix.shape[0]))\n"
        "print(before, len(os.listdir('/proc/self/task')))\n"
    )
    environment = {key: value for key, value in os.environ.items() if not key.startswith("OMP_")}
    result = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, check=True,
                            env=environment)
    before, after = (int(count) for count in result.stdout.split())
    assert after == before, f"a CHOLMOD factorisation started {after - before} threads"
