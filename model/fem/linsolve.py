"""Sparse factorisations of the stiffness, chosen by measurement (bench/fem_solvers.py, bench/README.md).

``Factorization(matrix, method)`` factorises once; ``solve(rhs)`` applies the inverse to one or several
right-hand sides, as often as needed while the matrix does not change. For symmetric positive definite
matrices (the rest stiffness, R K R^T, and the exact hyperelastic tangent on the stable path) the default is
CHOLMOD's supernodal Cholesky (scikit-sparse, 2.5 to 7 times faster than SuperLU here) when it is installed, else
SuperLU; CHOLMOD reports a matrix that is not positive definite (a tangent past a limit point), which the caller
then hands to :func:`indefinite_method`: CHOLMOD's simplicial LDL' ("cholmod-ldl"), which factorises a symmetric
indefinite matrix as it is (no pivoting: only an exactly zero pivot stops it), or SuperLU without CHOLMOD.
SuperLU's symmetric-mode LU ("splu-mmd": no partial pivoting) of such a tangent printed "On entry to DTRSV
parameter number 6 had an illegal value" from its C code during volume-controlled steps (bench/README.md): with
CHOLMOD installed no solve goes through SuperLU any more. A CHOLMOD factorisation solves with CHOLMOD's own
substitutions and may reuse the symbolic analysis (fill-reducing ordering, supernodes) of an earlier matrix of
the same pattern and mode; a Cholesky factor can be taken out as arrays (:class:`CholeskyFactor`) to be stored,
and a stored one is solved by numba substitutions. A :class:`FillOrdering` (CHOLMOD's own fill-reducing choice for a
pattern, kept) lets CHOLMOD factorise the permuted matrix in its natural order: no ordering again in each process,
no permuted copy made inside each factorisation.
"""

from __future__ import annotations

import os
from typing import TYPE_CHECKING, Any

import numpy as np

from phantom import require_extra
from phantom.model.arrays import FloatArray, Int32Array, IntArray
from phantom.model.fem import kernels

if TYPE_CHECKING:
    import scipy.sparse

METHODS = ("cholmod", "cholmod-ldl", "splu-mmd", "splu-colamd", "cg-ilu")

# Debian's CHOLMOD runs its supernodal loops on a fixed four OpenMP threads (a num_threads clause, so
# OMP_NUM_THREADS does not reach it): on two cores they woke some 30 000 times a second and took a third of a
# full solve in system time (builtin:converged at (3,1,2) kPa: 33 s wall, 20 s user, 9 s system; with one
# thread 17 s, 14 s, 3 s, the same equilibrium to the last digit; bench/README.md). OMP_THREAD_LIMIT caps even
# those clauses. libgomp reads it when it loads, which is with CHOLMOD, imported only below; a value the user
# set is kept, and the variable passes to the Dask workers and the solving processes this one starts.
os.environ.setdefault("OMP_THREAD_LIMIT", "1")


def default_method() -> str:
    """"cholmod" when scikit-sparse imports, else "splu-mmd"."""
    # scikit-sparse is optional (it needs SuiteSparse): its absence is what this asks
    try:
        import sksparse.cholmod  # noqa: F401
    except ImportError:
        return "splu-mmd"
    return "cholmod"


def indefinite_method() -> str:
    """The factorisation for a symmetric matrix that may be indefinite (a tangent past a limit point):
    CHOLMOD's LDL' ("cholmod-ldl") when scikit-sparse imports, else SuperLU ("splu-mmd")."""
    return "cholmod-ldl" if default_method() == "cholmod" else "splu-mmd"


class CholeskyFactor:
    """``A[P][:, P] = L L^T`` as arrays, solved by numba substitutions; storable, and rescalable when A is.

    Because the model's stiffness is proportional to E, a factor of ``A`` serves ``c A`` too:
    ``scale`` multiplies every solution (``(c A)^-1 = A^-1 / c``).
    """

    def __init__(self, indptr: IntArray, indices: Int32Array, values: FloatArray, permutation: IntArray,
                 scale: float = 1.0):
        self.indptr = np.ascontiguousarray(indptr, dtype=np.int64)
        self.indices = np.ascontiguousarray(indices, dtype=np.int32)  # as stored: no 17 MB conversion per load
        self.values = np.ascontiguousarray(values, dtype=np.float64)
        self.permutation = np.ascontiguousarray(permutation, dtype=np.int64)
        self.scale = scale

    def solve(self, rhs: FloatArray) -> FloatArray:
        """``A^-1 rhs`` for one right-hand side (n,) or several (n, k)."""
        solution = kernels.cholesky_solve(self.indptr, self.indices, self.values, self.permutation,
                                          np.ascontiguousarray(rhs, dtype=np.float64))
        return solution * self.scale if self.scale != 1.0 else solution

    def negative_pivots(self) -> int:
        """0: a Cholesky factor's matrix is positive definite (see :meth:`Factorization.negative_pivots`)."""
        return 0

    def arrays(self) -> dict[str, FloatArray | IntArray | Int32Array]:
        """The factor's arrays by name, as :meth:`__init__` takes them (for storing)."""
        return {"indptr": self.indptr, "indices": self.indices, "values": self.values,
                "permutation": self.permutation}


class ShiftPreconditioned:
    """Solves with a symmetric indefinite matrix ``K`` (a tangent past a limit point) by MINRES, preconditioned
    with the Cholesky factor of ``K`` shifted towards positive definite (``K + tau |diag K|``, which CHOLMOD's
    supernodal LL' factorises in a tenth of a second where its simplicial LDL' of ``K`` took 7-15 s on a 10-node
    sphere: bench/README.md, "Through the peak").

    The preconditioned operator is the identity but for the few modes the shift moved (the volume mode past a
    limit point, the softest others), so MINRES converges in a few tens of back-substitutions. ``multiply(v)``
    is ``K v``; ``solve`` raises ArithmeticError when MINRES does not reach ``tolerance`` (relative residual) in
    ``max_iterations``: the caller then factorises ``K`` by LDL'.
    """

    def __init__(self, multiply: Any, preconditioner: Any, tolerance: float = 1e-10, max_iterations: int = 300):
        self.multiply = multiply
        self.preconditioner = preconditioner
        self.tolerance = tolerance
        self.max_iterations = max_iterations
        #: MINRES iterations spent in all solves
        self.iterations = 0

    def solve(self, rhs: FloatArray) -> FloatArray:
        """``K^-1 rhs`` for one right-hand side (n,) or several (n, k)."""
        if rhs.ndim == 2:
            return np.column_stack([self.solve(column) for column in rhs.T])
        import scipy.sparse.linalg as spla

        size = rhs.shape[0]
        operator = spla.LinearOperator((size, size), matvec=self.multiply, dtype=np.float64)
        preconditioner = spla.LinearOperator((size, size), matvec=self.preconditioner.solve, dtype=np.float64)
        counted = [0]

        def count(_: FloatArray) -> None:
            counted[0] += 1

        solution, info = spla.minres(operator, rhs, M=preconditioner, rtol=self.tolerance,
                                     maxiter=self.max_iterations, callback=count)
        self.iterations += counted[0]
        if info != 0 or not np.all(np.isfinite(solution)):
            raise ArithmeticError(f"MINRES on the indefinite tangent did not converge ({info})")
        result: FloatArray = solution
        return result

    def negative_pivots(self) -> int | None:
        """Not counted (the shifted factor is positive definite; ``K`` has at least one negative eigenvalue)."""
        return None


class FillOrdering:
    """A fill-reducing ordering ``P`` of one symmetric sparsity pattern, with the CSR pattern of ``A[P][:, P]`` and
    where each of its entries lies in the data of a matrix ``A`` of the pattern (``gather``).

    CHOLMOD orders a pattern in every process that factorises it (AMD and METIS, keeping the one that fills less:
    0.18 s of CPU on the 7 mm prostate's tangent) and, given an ordering, makes the permuted copy inside every
    factorisation (0.025 s of its 0.26 s). With the ordering kept (:func:`cholmod_ordering` makes it once) the
    matrix is permuted by one gather (0.005 s) and factorised in its natural order (bench/README.md).
    """

    def __init__(self, permutation: IntArray, indptr: IntArray, indices: Int32Array | IntArray):
        import scipy.sparse

        size = len(indptr) - 1
        self.permutation = np.ascontiguousarray(permutation, dtype=np.int64)
        if self.permutation.shape != (size,) or not np.array_equal(np.sort(self.permutation), np.arange(size)):
            raise ValueError(f"not a permutation of the pattern's {size} rows")
        # each entry's position in A's data (1-based: an explicit zero would not survive scipy's indexing)
        positions = scipy.sparse.csr_matrix((np.arange(1, len(indices) + 1, dtype=np.float64), indices, indptr),
                                            shape=(size, size))
        permuted = positions[self.permutation][:, self.permutation]
        permuted.sort_indices()
        self.indptr, self.indices = permuted.indptr, permuted.indices
        self.gather = permuted.data.astype(np.int64) - 1

    def permuted(self, data: FloatArray) -> scipy.sparse.csc_matrix:
        """``A[P][:, P]`` of the matrix of the pattern with entries ``data``, as CSC (CSR arrays read as CSC are the
        transpose: the same symmetric matrix)."""
        import scipy.sparse

        size = len(self.indptr) - 1
        return scipy.sparse.csc_matrix((data[self.gather], self.indices, self.indptr), shape=(size, size))


def cholmod_ordering(matrix: scipy.sparse.csr_matrix) -> IntArray:
    """CHOLMOD's fill-reducing ordering of a symmetric matrix's pattern (its default choice: AMD or METIS)."""
    import scipy.sparse

    with require_extra("cholmod"):
        from sksparse.cholmod import analyze
    columns = scipy.sparse.csc_matrix((matrix.data, matrix.indices, matrix.indptr), shape=matrix.shape)
    permutation: IntArray = analyze(columns, mode="supernodal").P().astype(np.int64)
    return permutation


class Factorization:
    """A reusable solver for ``K y = b``; ``method`` is one of METHODS (None: :func:`default_method`).

    Raises ``ArithmeticError`` when "cholmod" finds the matrix not positive definite, or "cholmod-ldl" meets a
    zero pivot. ``ordering``: a :class:`FillOrdering` of a CSR ``matrix``'s pattern, for the CHOLMOD methods (the
    others order as they do without it); ``analysis`` must then be one made with the same ordering.
    """

    def __init__(self, matrix: scipy.sparse.csr_matrix, method: str | None = None, analysis: Any = None,
                 ordering: FillOrdering | None = None):
        # scipy.sparse.linalg costs a tenth of a second to import: only the factorising paths pay for it.
        import scipy.sparse
        import scipy.sparse.linalg as spla

        self.method = method or default_method()
        self.matrix = matrix
        #: CHOLMOD's symbolic analysis of the matrix's pattern (the CHOLMOD methods): pass it as ``analysis`` to
        #: factorise another matrix of the same pattern by the same method without ordering it again. None for the
        #: others.
        self.analysis: Any = None
        self._cholmod: Any = None
        self._lu: Any = None
        self._preconditioner: Any = None
        self.ordering: FillOrdering | None = None
        if self.method in ("cholmod", "cholmod-ldl"):
            # scikit-sparse is an optional extra and loads SuiteSparse: only the CHOLMOD methods need it
            with require_extra("cholmod"):
                from sksparse.cholmod import CholmodNotPositiveDefiniteError, analyze

            # CHOLMOD reads one triangle of a symmetric matrix: a CSR matrix's arrays, read as CSC, are its
            # transpose, the same matrix, without scipy's conversion (0.15 s a factorisation on the 7 mm prostate)
            if ordering is not None:
                self.ordering = ordering
                columns = ordering.permuted(matrix.data)
            else:
                columns = (scipy.sparse.csc_matrix((matrix.data, matrix.indices, matrix.indptr), shape=matrix.shape)
                           if scipy.sparse.isspmatrix_csr(matrix) else matrix.tocsc())
            # supernodal: LL' (positive definite only); simplicial: LDL', which takes a negative pivot as it comes
            mode = "supernodal" if self.method == "cholmod" else "simplicial"
            self.analysis = analysis if analysis is not None else analyze(
                columns, mode=mode, ordering_method="natural" if ordering is not None else "default")
            try:
                self._cholmod = self.analysis.cholesky(columns)
            except CholmodNotPositiveDefiniteError as error:
                what = "not positive definite" if self.method == "cholmod" else "singular (a zero pivot in LDL')"
                raise ArithmeticError(f"CHOLMOD: the matrix is {what} ({error})") from error
        elif self.method == "splu-colamd":
            self._lu = spla.splu(matrix.tocsc(), permc_spec="COLAMD")
        elif self.method == "splu-mmd":
            # The stiffness is symmetric: a minimum-degree ordering of A^T + A fills in less than COLAMD.
            self._lu = spla.splu(matrix.tocsc(), permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                                 options={"SymmetricMode": True})
        elif self.method == "cg-ilu":
            incomplete = spla.spilu(matrix.tocsc(), drop_tol=1e-4, fill_factor=10)
            self._preconditioner = spla.LinearOperator(matrix.shape, incomplete.solve)
        else:
            raise ValueError(f"unknown linear solver {self.method!r}: use one of {METHODS}")

    def solve(self, rhs: FloatArray) -> FloatArray:
        """``K^-1 rhs`` for one right-hand side (n,) or several (n, k)."""
        if self._cholmod is not None:
            if self.ordering is None:
                solution: FloatArray = self._cholmod(rhs)
                return solution
            permutation = self.ordering.permutation
            permuted: FloatArray = self._cholmod(np.ascontiguousarray(rhs[permutation]))
            solution = np.empty_like(permuted)
            solution[permutation] = permuted
            return solution
        if self.method.startswith("splu"):
            solution = self._lu.solve(rhs)
            return solution
        if rhs.ndim == 2:
            return np.column_stack([self.solve(column) for column in rhs.T])
        # scipy.sparse.linalg (0.1 s to import): loaded by __init__ already, named here for CG
        import scipy.sparse.linalg as spla

        solution, info = spla.cg(self.matrix, rhs, rtol=1e-12, atol=0.0, M=self._preconditioner, maxiter=2000)
        if info != 0:
            raise ArithmeticError(f"preconditioned CG did not converge ({info})")
        return solution

    def negative_pivots(self) -> int | None:
        """The number of negative eigenvalues of the matrix (Sylvester's law of inertia: those of D in LDL'): 0
        for a Cholesky factor, the negative entries of D for CHOLMOD's LDL'; None where the method does not tell
        (SuperLU, CG). Counting them costs one pass over D (n entries)."""
        if self._cholmod is None:
            return None
        if self.method == "cholmod":
            return 0
        return int(np.count_nonzero(self._cholmod.D() < 0.0))

    def cholesky_factor(self) -> CholeskyFactor | None:
        """The Cholesky factor as arrays, to be stored ("cholmod"; None for the other methods)."""
        if self._cholmod is None or self.method != "cholmod":
            return None
        lower = self._cholmod.L()
        lower.sort_indices()
        permutation = self._cholmod.P()
        if self.ordering is not None:  # CHOLMOD's of A[P][:, P]: A's is their composition
            permutation = self.ordering.permutation[permutation]
        return CholeskyFactor(lower.indptr, lower.indices, lower.data, permutation)
