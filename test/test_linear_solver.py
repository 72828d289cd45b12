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
