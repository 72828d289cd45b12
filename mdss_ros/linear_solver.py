"""Sparse symmetric positive-definite solves: PARDISO, CHOLMOD or scipy LU.

Backends, all from wheels: "pardiso" (MKL PARDISO through pypardiso: supernodal,
multithreaded, nested-dissection ordering; 5 s for 140K DOFs of a 3D tet mesh here),
"cholmod" (cholespy's CHOLMOD: ~9x slower than PARDISO on 24K DOFs of a 3D mesh here),
"splu" (scipy, any non-singular matrix). "auto" takes the first one installed.
A matrix that is not positive definite raises NotPositiveDefinite (PARDISO and CHOLMOD
detect it) so the caller can fall back, e.g. to a PSD-projected stiffness.
"""
import os

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

# MKL's strict conditional numerical reproducibility, read once when MKL loads (pypardiso
# loads it with the first solver, after this import). PARDISO's CNR mode (iparm[33],
# reproducible_pardiso) gave the same bits at 2, 3 and 4 MKL threads but other bits at one
# thread (1.2e-15 relative) on an AVX-512 machine, so a full-space step (BLAS at one
# thread) and a precompute (two) solved the same matrix differently; with STRICT they agree
# (session 20; an AVX2 machine had agreed without it). "AUTO" keeps MKL's choice of code
# path for this CPU. A value the user set is kept.
os.environ.setdefault("MKL_CBWR", "AUTO,STRICT")

try:
    import cholespy
except ImportError:  # the fallbacks keep the product working; the speed is reported in stats
    cholespy = None


def _point_pypardiso_at_mkl_rt():
    """Tell pypardiso where MKL's runtime is (PYPARDISO_MKL_RT): the venv's pinned
    libmkl_rt, when it is there and the user set no path of their own.

    Without it pypardiso looks for libmkl_rt on every PyPardisoSolver() (one is made when
    pypardiso is imported): ctypes' find_library, and when that fails (MKL from a pip wheel
    lives in the venv's lib, which the loader does not search) a recursive glob of
    sys.prefix. In this repository's venv that glob walks about 11K folders: 0.6-0.7 s
    for every solver made. A node's first step made one (grasp_lift's first step: 625 ms
    against 8 ms for the next), a small model's build made four (cantilever at cell 0.05,
    2 domains: 2.8 s of its 4.3 s), and the import another. Where the venv has no
    libmkl_rt, pypardiso's own search runs as before."""
    if os.environ.get("PYPARDISO_MKL_RT"):
        return
    import ctypes
    import glob
    import sys
    # pypardiso's order (the shortest name first), then the highest version of equal length
    found = sorted(glob.glob(os.path.join(sys.prefix, "lib", "libmkl_rt.so*")),
                   key=lambda p: (len(p), [-ord(ch) for ch in p]))
    for path in found:
        try:
            ctypes.CDLL(path)            # pypardiso would CDLL it unguarded: only a library that loads
        except OSError:
            continue
        os.environ["PYPARDISO_MKL_RT"] = path
        return


_point_pypardiso_at_mkl_rt()
try:
    import pypardiso
except (ImportError, OSError):           # OSError: a PYPARDISO_MKL_RT the user set that does not load
    pypardiso = None


#: The thread count PARDISO's conditional numerical reproducibility (CNR) mode splits its work
#: for (iparm[33]). Its round-off depends on this number only, not on the threads MKL runs
#: (measured: the same bits with MKL at 1 and 2 threads; 1-3 give one result, 4 another, 8 a
#: third), so a fixed value keeps results independent of MKL_NUM_THREADS and of the core
#: count. Cost on this 2-core machine (load 3.7-4.4, the variants interleaved in one
#: process, medians of 8): a numeric factorisation of caterpillar's stiffness (33K DOFs)
#: 260/378 ms against 230/362 ms with the defaults (+4-13 %), hammock's (29K) 156 against
#: 149 ms; analysis and solves about the same.
PARDISO_CNR_THREADS = 4


def reproducible_pardiso(refine=True):
    """A pypardiso solver (real symmetric positive definite) whose results are bit for bit
    the same from run to run (issue 17).

    With its defaults (iparm[0] = 0), MKL PARDISO orders with the parallel nested
    dissection (iparm[1] = 3: what pardisoinit of the oneMKL 2026.2 pinned here sets) and factorises with dynamic
    scheduling: with more than one MKL thread the same matrix gave different round-off from
    one factorisation to the next (cantilever's 3000-DOF stiffness: 16 of 29 fresh solves
    differed from the first, about 1e-15 relative). Every build of the precompute runs
    hundreds of such solves (shift-invert bases, modal derivatives, the full-space training
    run, the residual compliance), so two builds of the same inputs differed by ~1e-12 in
    the steps they gave, and runs sharing a cache stepped as whichever build wrote it last.
    Here PARDISO gets its own defaults (pardisoinit) with the sequential METIS ordering
    (iparm[1] = 2: the parallel one rules out CNR) and CNR on (iparm[33] > 0). iparm[0] = 1
    tells PARDISO to take iparm as given instead of refilling its defaults.

    refine=False sets iparm[7] = 0: no iterative refinement of a solve unless the
    factorisation perturbed a pivot (which an SPD factorisation never does; it fails
    instead). pardisoinit's default (refine=True) makes every solve two refinement steps
    (iparm[6] reads 2 after each), each a product with A and another pair of triangular
    sweeps: 60 right-hand sides on grasp_lift's 375-DOF step matrix took 5.1 ms against 1.4
    ms without them, on a 2,187-DOF cube 32.6 against 7.2 ms, for a residual |A x - b| of
    1.2e-13 either way at 375 DOFs and 3.9e-13 against 1.9e-13 at 2,187 (session 23).
    A time step's matrix M + dt D + dt^2 K is mass-dominated and well conditioned, so its
    solves drop the refinement (SparseSolver(refine=False): fem/backward_euler.py and the
    reduced model's full-space domains). The precompute's solves keep it: they include
    nearly singular systems (shift-invert bases, a free body's static poses), where it
    does buy accuracy. Without it, a free block's gravity pose in bend_cuts read a bend of
    1.7e-6 degrees instead of 0 (test_bend_cuts)."""
    import ctypes
    solver = pypardiso.PyPardisoSolver(mtype=2)
    iparm = np.zeros(64, dtype=np.int32)
    pt = np.zeros(64, dtype=np.int64)
    solver.libmkl.pardisoinit(pt.ctypes.data_as(ctypes.c_void_p), ctypes.byref(ctypes.c_int32(2)),
                              iparm.ctypes.data_as(ctypes.c_void_p))
    iparm[0] = 1
    iparm[1] = 2
    if not refine:
        iparm[7] = 0
    iparm[33] = PARDISO_CNR_THREADS
    solver.iparm[:] = iparm
    return solver


class NotPositiveDefinite(ArithmeticError):
    """The matrix handed to a Cholesky factorisation is not positive definite."""


class SparseSolver:
    """Factor once, solve many right-hand sides.

    backend: "pardiso", "cholmod", "splu" or "auto" (see the module docstring); refine:
    PARDISO's iterative refinement of each solve (reproducible_pardiso: off for a time
    step's well-conditioned matrix).
    """

    def __init__(self, backend="auto", refine=True):
        if backend == "auto":
            backend = "pardiso" if pypardiso is not None else "cholmod" if cholespy is not None else "splu"
        if backend not in ("pardiso", "cholmod", "splu"):
            raise ValueError(f"unknown sparse solver backend {backend!r} (pardiso, cholmod, splu, auto)")
        if backend == "pardiso" and pypardiso is None:
            raise ImportError("pypardiso is not installed; use backend='cholmod' or 'splu'")
        if backend == "cholmod" and cholespy is None:
            raise ImportError("cholespy is not installed; use backend='splu'")
        self.backend = backend
        self.refine = bool(refine)
        self._solver = None
        self._pattern = None       # PARDISO: (indptr, indices) of the last analysed matrix
        self._triangle = None      # PARDISO: the upper triangle's positions in A (_upper_of)
        self._upper = None         # PARDISO: the factorised upper triangle, None until one holds
        self.analyses = 0          # PARDISO analyses (phase 11) run
        self.n = 0

    def close(self):
        """Release the factorisation's native memory. PARDISO keeps it inside MKL, not in
        Python objects, and pypardiso has no __del__: a PyPardisoSolver dropped without
        free_memory keeps one factorisation until the process exits (measured: about
        80 MB for each Simulator of 8.7K DOFs built and dropped). The solver factors
        again after this."""
        solver, self._solver = getattr(self, "_solver", None), None
        self._pattern = None
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
            upper = self._upper_of(A)
            if self._solver is None:
                self._solver = reproducible_pardiso(self.refine)     # real symmetric positive definite
            try:
                self._factor_pardiso(upper)
            except pypardiso.pardiso_wrapper.PyPardisoError as err:
                # Keep the solver and its analysis: a new PyPardisoSolver searches
                # sys.prefix for mkl_rt (300 ms here, every step of a compressed body whose
                # first factorisation fails), and a dropped one's MKL memory is never
                # released. The next factorisation of the same pattern reuses both the
                # analysis and the factor's memory: 2,000 cycles of a failed and a good
                # factorisation of grasp_lift's step matrix kept one analysis, the same
                # solution to the bit and the same peak RSS (session 23). Releasing the
                # memory here instead (as before) made the retry a full analysis again:
                # every step of a squeezed body paid two.
                # The failed numeric phase overwrote the factor held before: solve() refuses
                # until a factorisation succeeds.
                self._upper = None
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

    def _upper_of(self, A):
        """The upper triangle of A (CSR) as PARDISO reads it, the same matrix as sp.triu's
        (explicit zeros kept, duplicates summed, columns sorted), gathered by the positions
        kept for A's pattern: a model's step matrix keeps its pattern step after step. On
        grasp_lift's 375-DOF step matrix (two factorisations a step: the first fails)
        sp.triu's COO round trip took 259 / 371 us, this 112 / 115 us with its pattern check
        and the CSR it builds (min / median of 500 calls; session 23)."""
        if not A.has_canonical_format:        # sorted, no duplicates; the caller's matrix untouched
            A = A.copy()
            A.sum_duplicates()
        kept = self._triangle
        if kept is None or not (np.array_equal(kept[0], A.indptr) and np.array_equal(kept[1], A.indices)):
            n = A.shape[0]
            rows = np.repeat(np.arange(n), np.diff(A.indptr))
            pos = np.flatnonzero(A.indices >= rows)
            indptr = np.concatenate([[0], np.cumsum(np.bincount(rows[pos], minlength=n))])
            kept = self._triangle = (A.indptr.copy(), A.indices.copy(), pos, A.indices[pos], indptr)
        _, _, pos, indices, indptr = kept
        return sp.csr_matrix((A.data[pos], indices, indptr), shape=A.shape)

    def _factor_pardiso(self, upper):
        """PARDISO's factorisation of the upper triangle, its analysis (ordering, symbolic
        factorisation: phase 11) only when the pattern changed since the last one: a model's
        stiffness keeps its pattern step after step. pypardiso's factorize() always runs
        phase 12 (analysis + numeric); this calls its phases itself, as factorize() does
        (pypardiso 0.4.7, pinned). Measured on the Hertz study's matrices (session 14,
        /tmp script): analysis 0.65 of 4.8 s for the meshless a/h = 2 (24,840 DOFs), 0.12
        of 0.52 s for full FEM at a/h = 2 (32,805)."""
        solver = self._solver
        same = (self._pattern is not None and np.array_equal(self._pattern[0], upper.indptr)
                and np.array_equal(self._pattern[1], upper.indices))
        solver._check_A(upper)
        solver.factorized_A = (solver._hash_csr_matrix(upper) if upper.nnz > solver.size_limit_storage
                               else upper.copy())
        solver.set_phase(22 if same else 12)
        self._pattern = None                  # until the factorisation succeeded
        self.analyses += 0 if same else 1
        try:
            solver._call_pardiso(upper, np.zeros((upper.shape[0], 1)))
        except pypardiso.pardiso_wrapper.PyPardisoError as err:
            # -4, a zero pivot (a matrix that is not positive definite): the numeric phase
            # failed after the analysis, which still holds for the pattern. Any other code
            # leaves the next factorisation to analyse again.
            if err.value == -4:
                self._pattern = (upper.indptr.copy(), upper.indices.copy())
            raise
        self._pattern = (upper.indptr.copy(), upper.indices.copy())

    def forward(self, B):
        """Z = L^-1 P B (n, k) for B (n, k), A = P^T L L^T P the factorisation held (PARDISO's
        phase 331, the forward substitution alone): half a solve. With backward, A^-1 B =
        backward(forward(B)) and B1^T A^-1 B2 = forward(B1)^T forward(B2): a contact working
        set's Delassus block from one sweep per row (contact/unilateral.HalfSweepSolves).
        On grasp_lift's 375-DOF matrix, 90 columns took 1.02 ms this way against 2.33 ms
        as solves (medians of 50, beside a CI run; session 23). PARDISO only."""
        return self._substitute(331, B)

    def backward(self, z):
        """x = P^T L^-T z for z (n,) or (n, k): the other half (phase 333)."""
        return self._substitute(333, z)

    def _substitute(self, phase, b):
        if self.backend != "pardiso":
            raise NotImplementedError(f"SparseSolver.forward/backward: PARDISO only, not {self.backend!r}")
        if self._upper is None:
            raise RuntimeError("SparseSolver.forward/backward: no factorisation is held (the last factor() failed)")
        solver = self._solver
        solver.set_phase(phase)
        try:
            return solver._call_pardiso(self._upper, np.asfortranarray(b, dtype=np.float64))
        finally:
            solver.set_phase(33)

    def solve(self, b):
        """Solve A x = b for b (n,) or (n, k)."""
        b = np.ascontiguousarray(b, dtype=np.float64)
        if self.backend == "pardiso":
            if self._upper is None:
                raise RuntimeError("SparseSolver.solve: no factorisation is held (the last factor() failed)")
            return self._solver.solve(self._upper, b)
        if self.backend == "cholmod":
            x = np.empty_like(b)
            self._solver.solve(b, x)
            return x
        return self._solver.solve(b)
