"""Sparse symmetric positive-definite solves: CHOLMOD through cholespy, scipy as fallback.

cholespy ships CHOLMOD in a wheel (no SuiteSparse headers needed). It re-analyses the
pattern on every factorisation; that is part of the factorisation time we report.
A matrix that is not positive definite raises NotPositiveDefinite so the caller can
fall back (e.g. to a PSD-projected stiffness) instead of getting a wrong answer.
"""
import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

try:
    import cholespy
except ImportError:  # the fallback keeps the product working; the speed is reported in stats
    cholespy = None


class NotPositiveDefinite(ArithmeticError):
    """The matrix handed to a Cholesky factorisation is not positive definite."""


class SparseSolver:
    """Factor once, solve many right-hand sides.

    backend: "cholmod" (cholespy), "splu" (scipy LU, works for any non-singular A),
    or "auto" (cholmod when installed).
    """

    def __init__(self, backend="auto"):
        if backend == "auto":
            backend = "cholmod" if cholespy is not None else "splu"
        if backend == "cholmod" and cholespy is None:
            raise ImportError("cholespy is not installed; use backend='splu'")
        if backend not in ("cholmod", "splu"):
            raise ValueError(f"unknown sparse solver backend {backend!r} (cholmod, splu, auto)")
        self.backend = backend
        self._solver = None
        self.n = 0

    def factor(self, A):
        """Factor A, a (n, n) symmetric sparse matrix (CSR or anything scipy converts)."""
        A = sp.csr_matrix(A)
        self.n = A.shape[0]
        if self.backend == "cholmod":
            try:
                self._solver = cholespy.CholeskySolverD(
                    self.n, A.indptr.astype(np.int32), A.indices.astype(np.int32),
                    np.ascontiguousarray(A.data, dtype=np.float64), cholespy.MatrixType.CSR)
            except ValueError as err:
                raise NotPositiveDefinite(str(err)) from err
        else:
            self._solver = spla.splu(A.tocsc())
        return self

    def solve(self, b):
        """Solve A x = b for b (n,) or (n, k)."""
        b = np.ascontiguousarray(b, dtype=np.float64)
        if self.backend == "cholmod":
            x = np.empty_like(b)
            self._solver.solve(b, x)
            return x
        return self._solver.solve(b)
