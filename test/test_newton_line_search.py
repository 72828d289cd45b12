"""The reduced step's Newton line search (reduced/step.py, Step._line_search) on a quadratic
incremental potential Phi(Q) = 1/2 Q.H Q - b.Q, whose gradient is the residual r = H Q - b.
The matrix the step factors, A, stands in for a tangent that is exact (A = H), too soft, or
indefinite (the coupling tangent omits dJ, docs/method.md §8)."""
from types import SimpleNamespace

import numpy as np
import pytest

from mdss_ros.reduced.step import DAMPING, MIN_STEP, Step


def _problem(H, b):
    """(step, system, phi): a stand-in model whose _energy_at returns Phi and a system whose
    potential returns that value; Mgen = I."""
    phi = lambda Q: 0.5 * Q @ H @ Q - b @ Q                                  # noqa: E731
    step = SimpleNamespace(_solve=lambda A_ss, A_sI, A_ff, rhs: np.linalg.solve(A_ss, rhs),
                           _energy_at=lambda Q, base, dt: phi(Q))
    system = SimpleNamespace(potential=lambda Q, p0, Fn, e: e,
                             shifted=lambda A3, mu: (A3[0] + mu * np.eye(len(A3[0])), None, None))
    return step, system, phi


def _search(A, H, b, Q):
    step, system, phi = _problem(H, b)
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


def test_ascent_tangent_falls_back_to_a_damped_descent_direction(quadratic):
    H, b, Q = quadratic
    A = -H                 # every plain direction climbs: r . A^-1 (-r) > 0
    r = H @ Q - b
    assert r @ np.linalg.solve(A, -r) > 0.0
    (length, dQ, cuts, mu), phi = _search(A, H, b, Q)
    assert mu in DAMPING and length >= MIN_STEP
    assert r @ dQ < 0.0 and phi(Q + length * dQ) < phi(Q)


def test_indefinite_tangent_still_lowers_the_potential(quadratic):
    H, b, Q = quadratic
    lam = np.linalg.eigvalsh(H)
    A = H - 0.5 * (lam[2] + lam[3]) * np.eye(6)      # three negative, three positive eigenvalues
    assert np.linalg.eigvalsh(A)[0] < 0.0 < np.linalg.eigvalsh(A)[-1]
    (length, dQ, cuts, mu), phi = _search(A, H, b, Q)
    assert length >= MIN_STEP and phi(Q + length * dQ) < phi(Q)


def test_no_descent_anywhere_takes_no_step(quadratic):
    H, b, Q = quadratic
    # A residual that is not the potential's gradient (here its negative): every direction
    # it calls downhill climbs Phi. No step is taken (the loop before took its shortest
    # length whatever that did to Phi).
    step, system, phi = _problem(H, b)
    r = -(H @ Q - b)
    length, dQ, cuts, mu = Step._line_search(step, system, (H, None, None), r, Q, np.linalg.solve(H, -r),
                                             (None, None, phi(Q)), None, 1.0)
    assert length == 0.0 and mu == DAMPING[-1]


def test_shifted_adds_mu_mgen_on_subspace_and_full_space_rows():
    """StepSystem.shifted(A, mu) = A + mu Mgen, A_sI unchanged, beside a full-space domain."""
    from test_reduced_model import _regions_scene
    from mdss_ros import Simulator
    from mdss_ros.reduced.unified_system import StepSystem
    m = Simulator(_regions_scene(["rest"], modes=6, integrator={"dt": 0.01})).model
    assert m.F > 0 and m.S > 0
    G, K_ss, K_sI, K_ff, _, _, _ = m._evaluate(m.q, m.frames, m.x_full)
    system = StepSystem(m, m._subspace_mass(m.frames, predicted_dt=m.dt), m.dt, m.alpha, m.beta, (K_ss, K_sI, K_ff))
    A = system.matrix(K_ss, K_sI, K_ff)
    S_ss, S_sI, S_ff = system.shifted(A, 2.5)
    assert np.allclose(S_ss - A[0], 2.5 * system.mass.dense(), rtol=0, atol=1e-12 * np.abs(A[0]).max())
    assert S_sI is A[1]
    assert np.allclose(S_ff - A[2], 2.5 * m.M_ff)
    assert not np.shares_memory(S_ss, A[0])


def test_a_stall_at_the_first_iterate_is_reported_and_the_guard_retries():
    """A line search that finds no descent from Q = 0 keeps Q = 0: the step ends with no
    modal or frame velocity, stats say newton_stalled "first", and the guard judges that a
    soft sign (a retry), not a stable step."""
    from test_reduced_model import _scene
    from mdss_ros import Simulator
    from mdss_ros.step_options import StepOptions
    sim = Simulator(_scene(modes=6, domains={"count": 2}, integrator={"dt": 0.01}))
    m = sim.model
    sim.set_wrench("tip", force=(0.0, 0.0, -1.0))
    sim.step(3)
    assert np.abs(m.qd).max() > 0
    m._line_search = lambda system, A, r, Q, dQ, terms, base, dt: (0.0, dQ, 14, DAMPING[-1])
    stats = m.step(sim.applied_loads(), sim.gravity, options=StepOptions(newton_iterations=3))
    assert stats["newton_stalled"] == "first" and stats["newton_damped"] == 0
    assert np.abs(m.qd).max() == 0.0
    now = sim.guard._current(sim.gravity, sim.step_count)
    verdict = sim.guard.judge(now, now, 0.0, stats, sim.gravity)
    assert "newton" in verdict.soft
