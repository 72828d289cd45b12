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
    matrix's. A new pattern, or a failed factorisation (its memory released), analyses again."""
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
    assert s.analyses == 3
    x = s.solve(b[:7 ** 3])
    assert np.linalg.norm(A @ x - b[:7 ** 3]) < 1e-12 * np.linalg.norm(b[:7 ** 3])
