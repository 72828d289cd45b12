"""The reduced step's Newton line search (reduced/step.py, Step._line_search) on a quadratic
incremental potential Phi(Q) = 1/2 Q.H Q - b.Q, whose gradient is the residual r = H Q - b.
The matrix the step factors, A, stands in for a tangent that is exact (A = H), too soft, or
indefinite (the coupling tangent omits dJ, docs/method.md §8)."""
from types import SimpleNamespace

import numpy as np
import pytest

from mdss_ros.reduced.step import DAMPING, MIN_STEP, Step


def _problem(A, H, b):
    """(step, system, phi): a stand-in model whose _energy_at returns Phi and a system whose
    potential returns that value; Mgen = I."""
    phi = lambda Q: 0.5 * Q @ H @ Q - b @ Q                                  # noqa: E731
    step = SimpleNamespace(_solve=lambda A_ss, A_sI, A_ff, rhs: np.linalg.solve(A_ss, rhs),
                           _energy_at=lambda Q, base, dt: phi(Q))
    system = SimpleNamespace(potential=lambda Q, p0, Fn, e: e,
                             shifted=lambda A3, mu: (A3[0] + mu * np.eye(len(A3[0])), None, None))
    return step, system, phi


def _search(A, H, b, Q):
    step, system, phi = _problem(A, H, b)
    r = H @ Q - b
    terms = (None, None, phi(Q))
    dQ = np.linalg.solve(A, -r)
    return Step._line_search(step, system, (A, None, None), r, Q, dQ, terms, None, 1.0), phi


@pytest.fixture
def quadratic():
    rng = np.random.default_rng(3)
    B = rng.normal(size=(6, 6))
    H = B @ B.T + 6.0 * np.eye(6)
    return H, rng.normal(size=6), rng.normal(size=6)


def test_exact_tangent_takes_the_full_newton_step(quadratic):
    H, b, Q = quadratic
    (length, dQ, cuts, mu), phi = _search(H, H, b, Q)
    assert (length, cuts, mu) == (1.0, 0, 0.0)
    np.testing.assert_allclose(Q + dQ, np.linalg.solve(H, b), rtol=1e-12)


def test_too_soft_tangent_is_shortened_and_lowers_the_potential(quadratic):
    H, b, Q = quadratic
    (length, dQ, cuts, mu), phi = _search(1e-3 * H, H, b, Q)
    assert mu == 0.0 and cuts > 0 and length < 1.0
    r = H @ Q - b
    assert phi(Q + length * dQ) <= phi(Q) + 1e-4 * length * (r @ dQ) < phi(Q)


def test_indefinite_tangent_falls_back_to_a_damped_descent_direction(quadratic):
    H, b, Q = quadratic
    A = np.eye(6) - 3.0 * H          # indefinite, as with a large omitted dJ term
    r = H @ Q - b
    assert r @ np.linalg.solve(A, -r) > 0.0 or np.min(np.linalg.eigvalsh(A)) < 0.0
    (length, dQ, cuts, mu), phi = _search(A, H, b, Q)
    assert mu in DAMPING and length >= MIN_STEP
    assert r @ dQ < 0.0
    assert phi(Q + length * dQ) < phi(Q)


def test_no_descent_anywhere_takes_no_step(quadratic):
    H, b, Q = quadratic
    # A residual that is not the potential's gradient (here its negative): every direction
    # it calls downhill climbs Phi. No step is taken (the loop before took its shortest
    # length whatever that did to Phi).
    step, system, phi = _problem(H, H, b)
    r = -(H @ Q - b)
    length, dQ, cuts, mu = Step._line_search(step, system, (H, None, None), r, Q, np.linalg.solve(H, -r),
                                             (None, None, phi(Q)), None, 1.0)
    assert length == 0.0 and mu == DAMPING[-1]
