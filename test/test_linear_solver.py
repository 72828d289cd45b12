"""SparseSolver's PARDISO memory: MKL holds each factorisation outside Python, so a
solver that is dropped or re-made without free_memory leaks it (issue 18: a block pressed
with contact grew from 4.9 to 15 GB; the failed factorisations of a compressed body each
dropped a solver)."""
import numpy as np
import pytest
import scipy.sparse as sp

from mdss_ros.linear_solver import NotPositiveDefinite, SparseSolver

pypardiso = pytest.importorskip("pypardiso")


def _count_pardiso_solvers(monkeypatch):
    made = []
    init = pypardiso.PyPardisoSolver.__init__

    def counting(self, *args, **kwargs):
        made.append(1)
        init(self, *args, **kwargs)
    monkeypatch.setattr(pypardiso.PyPardisoSolver, "__init__", counting)
    return made


def test_failed_factorisations_reuse_one_pardiso_solver(monkeypatch):
    made = _count_pardiso_solvers(monkeypatch)
    s = SparseSolver("pardiso")
    for _ in range(5):
        with pytest.raises(NotPositiveDefinite):
            s.factor(sp.diags([1.0, -1.0, 2.0]).tocsr())
        s.factor(sp.identity(3, format="csr"))
        np.testing.assert_allclose(s.solve(np.ones(3)), np.ones(3))
    assert len(made) == 1


def test_close_releases_the_factorisation_and_the_solver_factors_again(monkeypatch):
    freed = []
    free = pypardiso.PyPardisoSolver.free_memory
    monkeypatch.setattr(pypardiso.PyPardisoSolver, "free_memory",
                        lambda self, everything=False: (freed.append(everything), free(self, everything))[1])
    s = SparseSolver("pardiso").factor(sp.identity(3, format="csr") * 2.0)
    s.close()
    assert s._solver is None and freed == [True]
    np.testing.assert_allclose(s.factor(sp.identity(3, format="csr") * 2.0).solve(np.ones(3)), 0.5 * np.ones(3))
    del s                                        # __del__ frees the new factorisation too
    assert freed == [True, True]


def _laplacian_3d(n, shift=0.0):
    """SPD 7-point Laplacian on an n^3 grid (+ shift I), CSR."""
    one = sp.diags([-np.ones(n - 1), 2 * np.ones(n), -np.ones(n - 1)], [-1, 0, 1])
    eye = sp.identity(n)
    L = sp.kron(sp.kron(one, eye), eye) + sp.kron(sp.kron(eye, one), eye) + sp.kron(sp.kron(eye, eye), one)
    return (L + shift * sp.identity(n ** 3)).tocsr()


def test_pardiso_analyses_a_pattern_once_and_solves_every_new_matrix_on_it():
    """A model's stiffness keeps its pattern: the analysis (ordering, symbolic factor) runs
    once, every numeric factorisation after it reuses it, and each solve is the new
    matrix's. A new pattern analyses again; a factorisation that fails for a zero pivot
    keeps the analysis, so the retry on the same pattern (the projected tangent of a
    compressed body) reuses it and solves its own matrix."""
    s = SparseSolver("pardiso")
    rng = np.random.default_rng(0)
    b = rng.standard_normal(8 ** 3)
    for k, shift in enumerate((0.1, 0.5, 2.0)):
        A = _laplacian_3d(8, shift)
        s.factor(A)
        x = s.solve(b)
        assert np.linalg.norm(A @ x - b) < 1e-12 * np.linalg.norm(b)
        assert s.analyses == 1
    s.factor(_laplacian_3d(7, 0.1))                       # another pattern
    assert s.analyses == 2
    with pytest.raises(NotPositiveDefinite):
        s.factor(_laplacian_3d(7, -20.0))                 # same pattern, not positive definite
    A = _laplacian_3d(7, 0.3)
    s.factor(A)
    assert s.analyses == 2
    b7 = rng.standard_normal(7 ** 3)
    assert np.linalg.norm(A @ s.solve(b7) - b7) < 1e-12 * np.linalg.norm(b7)
    x = s.solve(b[:7 ** 3])
    assert np.linalg.norm(A @ x - b[:7 ** 3]) < 1e-12 * np.linalg.norm(b[:7 ** 3])


def _beam_stiffness():
    """K + M of a 1.0 x 0.1 x 0.1 m tet beam clamped at x = 0 (3000 DOFs), CSR: a matrix
    PARDISO runs multithreaded (a 3D Laplacian of that size it did not)."""
    from mdss_ros.fem.force_model import FEMForceModel
    from mdss_ros.fem.materials import make_material
    from mdss_ros.mesh import box
    mesh = box(size=(1.0, 0.1, 0.1), cell=0.025)
    mat = make_material({"model": "neohookean", "young": 1e6, "poisson": 0.3, "density": 1000})
    fem = FEMForceModel(mesh.vertices, mesh.tets, mat, pinned=np.flatnonzero(mesh.vertices[:, 0] < 1e-9))
    K = fem.pattern.matrix(fem.tangent(mesh.vertices)[2])
    return (K + 1e3 * sp.identity(K.shape[0])).tocsr()


def test_pardiso_solves_are_bit_reproducible_whatever_the_thread_count():
    """Issue 17: MKL PARDISO with its defaults (parallel nested dissection, dynamic
    scheduling) returned different round-off from one factorisation of the same matrix to
    the next once MKL ran more than one thread (16 of 29 fresh solves of a 3000-DOF
    stiffness differed from the first), which made the precompute differ build to build.
    Fresh solvers, re-factorisations on the analysed pattern and a run with one MKL thread
    must all give the same bits."""
    threadpoolctl = pytest.importorskip("threadpoolctl")
    A = _beam_stiffness()
    b = np.random.default_rng(1).standard_normal((A.shape[0], 3))
    first = None
    for _ in range(6):
        s = SparseSolver("pardiso").factor(A)
        x = s.solve(b)
        assert np.array_equal(x, first if first is not None else x)
        first = x if first is None else first
        for _ in range(3):
            assert np.array_equal(s.factor(A).solve(b), first)
        s.close()
    with threadpoolctl.threadpool_limits(1):
        assert np.array_equal(SparseSolver("pardiso").factor(A).solve(b), first)
    assert np.linalg.norm(A @ first - b) < 1e-12 * np.linalg.norm(b)


def test_the_kept_upper_triangle_is_scipys_triu_with_its_zeros():
    """SparseSolver._upper_of gathers the upper triangle by positions kept for the pattern:
    the same pattern and values as sp.triu (explicit zeros kept, duplicates summed,
    columns sorted), for new values on a kept pattern, for another pattern of the same
    size and nnz, and for unsorted or duplicated input, which it leaves untouched."""
    s = SparseSolver("pardiso")
    rng = np.random.default_rng(4)

    def check(A):
        before = (A.indptr.copy(), A.indices.copy(), A.data.copy())
        mine, ref = s._upper_of(A), sp.triu(A, format="csr")
        ref.sum_duplicates()
        np.testing.assert_array_equal(mine.indptr, ref.indptr)
        np.testing.assert_array_equal(mine.indices, ref.indices)
        np.testing.assert_array_equal(mine.data, ref.data)
        for a, b in zip(before, (A.indptr, A.indices, A.data)):
            np.testing.assert_array_equal(a, b)               # the caller's matrix untouched

    for size, shift in ((6, 0.1), (6, 0.7), (5, 0.2)):
        A = _laplacian_3d(size, shift).tocsr()
        A.data[rng.random(A.nnz) < 0.1] = 0.0                 # explicit zeros stay in the pattern
        check(A)
    # The same size and nnz, another pattern: a random symmetric matrix, then its entries
    # moved to other columns.
    n = 40
    M = sp.random(n, n, density=0.1, random_state=5)
    M = (M + M.T + sp.identity(n)).tocsr()
    check(M)
    P = sp.csr_matrix(M[rng.permutation(n)][:, rng.permutation(n)])
    P = (P + P.T).tocsr()
    check(P)
    # Unsorted columns within rows, and a duplicated entry.
    U = M.copy()
    for r in range(n):
        a, b = U.indptr[r], U.indptr[r + 1]
        order = rng.permutation(b - a)
        U.indices[a:b], U.data[a:b] = U.indices[a:b][order], U.data[a:b][order]
    U.has_sorted_indices = False
    check(U)
    Dup = sp.csr_matrix((np.array([1.0, 2.0, 3.0, 4.0]), np.array([0, 1, 1, 1]), np.array([0, 1, 4])), shape=(2, 2))
    check(Dup)


def test_a_solve_after_a_failed_factorisation_is_refused():
    s = SparseSolver("pardiso")
    with pytest.raises(RuntimeError):
        s.solve(np.ones(7 ** 3))
    s.factor(_laplacian_3d(7, 0.1))
    with pytest.raises(NotPositiveDefinite):
        s.factor(_laplacian_3d(7, -20.0))
    with pytest.raises(RuntimeError, match="no factorisation"):
        s.solve(np.ones(7 ** 3))


def test_a_first_factorisation_that_fails_keeps_its_analysis_for_the_retry():
    """The first factorisation of a pattern (analysis and numeric phase together) failing
    for a zero pivot: the retry on that pattern is numeric only and solves its own matrix."""
    s = SparseSolver("pardiso")
    with pytest.raises(NotPositiveDefinite):
        s.factor(_laplacian_3d(6, -20.0))
    assert s.analyses == 1
    A = _laplacian_3d(6, 0.2)
    s.factor(A)
    assert s.analyses == 1
    b = np.random.default_rng(2).standard_normal(6 ** 3)
    assert np.linalg.norm(A @ s.solve(b) - b) < 1e-12 * np.linalg.norm(b)


def test_pardiso_half_sweeps_compose_to_the_solve():
    """SparseSolver.forward / backward (PARDISO's phases 331 and 333): backward(forward(B))
    is A^-1 B, and forward(B1)^T forward(B2) is B1^T A^-1 B2 (the contact solves' Delassus
    block from one sweep per row, unilateral.HalfSweepSolves)."""
    s = SparseSolver("pardiso")
    A = _beam_stiffness()
    s.factor(A)
    rng = np.random.default_rng(6)
    B1, B2 = rng.standard_normal((A.shape[0], 7)), rng.standard_normal((A.shape[0], 4))
    Z1, Z2 = s.forward(B1), s.forward(B2)
    ref = np.linalg.solve(A.toarray(), B2)
    np.testing.assert_allclose(s.backward(Z2), ref, rtol=0, atol=1e-10 * np.abs(ref).max())
    np.testing.assert_allclose(s.backward(Z2[:, 0]), ref[:, 0], rtol=0, atol=1e-10 * np.abs(ref).max())
    gram = B1.T @ ref
    np.testing.assert_allclose(Z1.T @ Z2, gram, rtol=0, atol=1e-10 * np.abs(gram).max())
    assert s.solve(B2[:, 0]).shape == (A.shape[0],)          # the solve phase is restored
    np.testing.assert_allclose(s.solve(B2), ref, rtol=0, atol=1e-10 * np.abs(ref).max())


def test_pypardiso_is_pointed_at_the_venvs_mkl_rt_without_its_directory_walk(monkeypatch):
    """Every PyPardisoSolver() used to walk sys.prefix for libmkl_rt (0.6-0.7 s here):
    linear_solver sets PYPARDISO_MKL_RT to the venv's library before pypardiso is
    imported, and solvers load it without a glob; a path the user set is kept."""
    import glob
    import os
    import sys
    from mdss_ros import linear_solver
    venv_rt = sorted(glob.glob(os.path.join(sys.prefix, "lib", "libmkl_rt.so*")), key=len)
    monkeypatch.delenv("PYPARDISO_MKL_RT", raising=False)
    linear_solver._point_pypardiso_at_mkl_rt()
    if not venv_rt:
        assert "PYPARDISO_MKL_RT" not in os.environ     # pypardiso's own search, as before
        return
    path = os.environ["PYPARDISO_MKL_RT"]
    assert path in venv_rt and os.path.isfile(path)
    walks = []
    monkeypatch.setattr(glob, "glob", lambda *a, **k: walks.append(a) or [])
    solver = linear_solver.reproducible_pardiso()
    assert walks == [] and solver.libmkl._name == path
    monkeypatch.setenv("PYPARDISO_MKL_RT", "/a/custom/libmkl_rt.so")
    linear_solver._point_pypardiso_at_mkl_rt()
    assert os.environ["PYPARDISO_MKL_RT"] == "/a/custom/libmkl_rt.so"
