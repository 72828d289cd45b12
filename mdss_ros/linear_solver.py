"""Sparse symmetric positive-definite solves: PARDISO, CHOLMOD or scipy LU.

Backends, all from wheels: "pardiso" (MKL PARDISO through pypardiso: supernodal,
multithreaded, nested-dissection ordering; 5 s for 140K DOFs of a 3D tet mesh here),
"cholmod" (cholespy's CHOLMOD: ~9x slower than PARDISO on 24K DOFs of a 3D mesh here),
"splu" (scipy, any non-singular matrix). "auto" takes the first one installed.
A matrix that is not positive definite raises NotPositiveDefinite (PARDISO and CHOLMOD
detect it) so the caller can fall back, e.g. to a PSD-projected stiffness.
"""
import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

try:
    import cholespy
except ImportError:  # the fallbacks keep the product working; the speed is reported in stats
    cholespy = None
try:
    import pypardiso
except ImportError:
    pypardiso = None


class NotPositiveDefinite(ArithmeticError):
    """The matrix handed to a Cholesky factorisation is not positive definite."""


class SparseSolver:
    """Factor once, solve many right-hand sides.

    backend: "pardiso", "cholmod", "splu" or "auto" (see the module docstring).
    """

    def __init__(self, backend="auto"):
        if backend == "auto":
            backend = "pardiso" if pypardiso is not None else "cholmod" if cholespy is not None else "splu"
        if backend not in ("pardiso", "cholmod", "splu"):
            raise ValueError(f"unknown sparse solver backend {backend!r} (pardiso, cholmod, splu, auto)")
        if backend == "pardiso" and pypardiso is None:
            raise ImportError("pypardiso is not installed; use backend='cholmod' or 'splu'")
        if backend == "cholmod" and cholespy is None:
            raise ImportError("cholespy is not installed; use backend='splu'")
        self.backend = backend
        self._solver = None
        self.n = 0

    def close(self):
        """Release the factorisation's native memory. PARDISO keeps it inside MKL, not in
        Python objects, and pypardiso has no __del__: a PyPardisoSolver dropped without
        free_memory keeps one factorisation until the process exits (measured: about
        80 MB for each Simulator of 8.7K DOFs built and dropped). The solver factors
        again after this."""
        solver, self._solver = getattr(self, "_solver", None), None
        if solver is not None and getattr(self, "backend", None) == "pardiso":
            try:
                solver.free_memory(everything=True)
            except Exception:           # interpreter shutdown: ctypes or the library may be gone
                pass

    def __del__(self):
        self.close()

    def factor(self, A):
        """Factor A, a (n, n) symmetric sparse matrix (CSR or anything scipy converts)."""
        A = sp.csr_matrix(A)
        self.n = A.shape[0]
        if self.backend == "pardiso":
            upper = sp.triu(A, format="csr")
            upper.sort_indices()
            if self._solver is None:
                self._solver = pypardiso.PyPardisoSolver(mtype=2)     # real symmetric positive definite
            try:
                self._solver.factorize(upper)
            except pypardiso.pardiso_wrapper.PyPardisoError as err:
                # Keep the solver: a new PyPardisoSolver searches sys.prefix for mkl_rt
                # (300 ms here, every step of a compressed body whose first factorisation
                # fails), and the dropped one's MKL memory was never released: a leak of
                # one factorisation a step. Release MKL's memory and reuse the object.
                self._solver.free_memory(everything=True)
                raise NotPositiveDefinite(str(err)) from err
            self._upper = upper
        elif self.backend == "cholmod":
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
        if self.backend == "pardiso":
            return self._solver.solve(self._upper, b)
        if self.backend == "cholmod":
            x = np.empty_like(b)
            self._solver.solve(b, x)
            return x
        return self._solver.solve(b)
