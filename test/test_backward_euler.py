"""Backward Euler: the linearly implicit first iterate, convergence, momentum, recovery."""
import numpy as np
import pytest

from mdss_ros.fem.backward_euler import BackwardEuler, NewtonSettings
from mdss_ros.fem.force_model import FEMForceModel
from mdss_ros.fem.materials import make_material
from mdss_ros.mesh import box


def _model(kind="stvk", pinned=(), young=1e4, cell=0.25, size=(1.0, 0.5, 0.5)):
    mesh = box(size=size, cell=cell)
    mat = make_material({"model": kind, "young": young, "poisson": 0.3, "density": 1000})
    return FEMForceModel(mesh.vertices, mesh.tets, mat, pinned)


def test_first_iterate_is_linearly_implicit_euler():
    m = _model(pinned=[0, 1, 2])
    dt, alpha, beta = 0.01, 0.3, 0.002
    be = BackwardEuler(m, dt, NewtonSettings(max_iterations=1, alpha=alpha, beta=beta))
    rng = np.random.default_rng(0)
    x = m.X + 0.02 * rng.normal(size=m.X.shape)
    v = 0.1 * rng.normal(size=m.X.shape)
    x[[0, 1, 2]], v[[0, 1, 2]] = m.X[[0, 1, 2]], 0.0
    f_ext = rng.normal(size=m.X.shape)
    x1, v1 = be.step(x, v, f_ext)
    _, f_int, K = m.tangent(x)
    Kd, M = m.pattern.matrix(K).toarray(), m.M.toarray()
    A = M + dt * (alpha * M + beta * Kd) + dt * dt * Kd
    b = M @ m.free(v) + dt * (m.free(f_ext) - m.free(f_int))
    np.testing.assert_allclose(m.free(v1), np.linalg.solve(A, b), rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(x1, x + dt * v1)


def test_newton_converges_to_backward_euler_residual():
    m = _model(pinned=np.arange(0, 25))
    dt = 0.02
    be = BackwardEuler(m, dt, NewtonSettings(max_iterations=30, tolerance=1e-10))
    f_ext = np.zeros_like(m.X)
    f_ext[:, 2] = -5.0
    x, v = m.X.copy(), np.zeros_like(m.X)
    for _ in range(3):
        x, v = be.step(x, v, f_ext)
        assert be.stats["converged"]
    xn, vn = x, v
    x1, v1 = be.step(xn, vn, f_ext)
    _, f_int = m.forces(x1)
    r = m.M @ (m.free(v1) - m.free(vn)) + dt * (m.free(f_int) - m.free(f_ext))
    assert np.linalg.norm(r) < 1e-8 * np.linalg.norm(dt * m.free(f_ext))


def test_free_body_keeps_linear_momentum_and_spins():
    m = _model("neohookean")
    be = BackwardEuler(m, 1 / 90, NewtonSettings(max_iterations=3))
    c = m.X.mean(0)
    w = np.array([0.0, 0.0, 2.0])
    x, v = m.X.copy(), np.cross(w, m.X - c) + np.array([0.5, 0.0, 0.0])
    p0 = (m.vertex_mass[:, None] * v).sum(0)
    for _ in range(45):
        x, v = be.step(x, v, np.zeros_like(x))
    p = (m.vertex_mass[:, None] * v).sum(0)
    assert np.abs(p - p0).max() < 1e-9 * np.abs(p0).max()
    L = (m.vertex_mass[:, None] * np.cross(x - (m.vertex_mass[:, None] * x).sum(0) / m.vertex_mass.sum(), v)).sum(0)
    assert L[2] > 0.5 * (m.vertex_mass * ((m.X - c)[:, :2] ** 2).sum(1)).sum() * 2.0  # still spinning


@pytest.mark.parametrize("kind", ["stvk", "corotated", "neohookean"])
def test_inverted_elements_recover(kind):
    """A hard push through the body inverts elements; they come back, with no NaN."""
    m = _model(kind, pinned=np.flatnonzero(box(size=(1.0, 0.5, 0.5), cell=0.25).vertices[:, 0] < 1e-9))
    be = BackwardEuler(m, 1 / 90, NewtonSettings(max_iterations=5, alpha=2.0))
    x, v = m.X.copy(), np.zeros_like(m.X)
    tip = m.X[:, 0] > 0.99
    x[tip, 0] -= 0.4          # tip layer pushed back through the layer before it
    from mdss_ros.mesh.tetmesh import signed_volumes
    assert (signed_volumes(x, m.tets) <= 0).sum() > 0
    for _ in range(300):
        x, v = be.step(x, v, np.zeros_like(x))
        assert np.all(np.isfinite(x))
    assert (signed_volumes(x, m.tets) <= 0).sum() == 0
    assert np.abs(x - m.X).max() < 0.05


def test_sparse_backends_agree():
    m = _model(pinned=[0, 1, 2, 3])
    rng = np.random.default_rng(3)
    f = rng.normal(size=m.X.shape)
    out = []
    for backend in ("pardiso", "cholmod", "splu"):
        be = BackwardEuler(m, 0.01, NewtonSettings(max_iterations=2), solver_backend=backend)
        out.append(be.step(m.X.copy(), np.zeros_like(m.X), f)[1])
    np.testing.assert_allclose(out[0], out[2], rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(out[1], out[2], rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("beta", [0.0, 1e-3])
def test_projection_auto_starts_projected_after_an_indefinite_step_and_probes(beta):
    """projection auto: a step whose exact step matrix is indefinite retries projected, the
    next steps start from the projected tangent, and every PROBE_EVERY-th step of such a
    run tries the exact one first. A projected step, started or retried, is the step
    projection always takes from the same state (its stiffness damping beta K too); any
    other is the exact step (projection never)."""
    from mdss_ros.fem.backward_euler import PROBE_EVERY
    m = _model("stvk", pinned=np.flatnonzero(box(size=(1.0, 0.5, 0.5), cell=0.25).vertices[:, 0] < 1e-9))
    steppers = {p: BackwardEuler(m, 1 / 30, NewtonSettings(max_iterations=1, projection=p, beta=beta))
                for p in ("auto", "always", "never")}
    be = steppers["auto"]
    x, v = m.X.copy(), np.zeros_like(m.X)
    x[m.X[:, 0] > 0.99, 0] -= 0.4             # inverted tip: indefinite for many steps
    runs, kinds = [], set()
    for k in range(3 * PROBE_EVERY):
        run = be.projected_run
        x1, v1 = be.step(x, v, np.zeros_like(x))
        st = be.stats
        assert st["projected_start"] == (run % PROBE_EVERY != 0), (k, run)
        same = steppers["always" if st["projected"] else "never"].step(x, v, np.zeros_like(x))
        assert np.array_equal(same[0], x1) and np.array_equal(same[1], v1), (k, st["projected"])
        kinds.add((st["projected_start"], st["projected"]))
        assert be.projected_run == (run + 1 if st["projected"] else 0)
        runs.append(run)
        x, v = x1, v1
    assert PROBE_EVERY in runs                   # a run of projected steps reached a probe
    assert {(False, True), (True, True), (False, False)} <= kinds   # retried, started, exact


def test_a_full_models_state_carries_its_projected_run():
    """The projected run is state: a snapshot restores it; reset and positions set by hand
    clear it."""
    from mdss_ros.simulator import Simulator
    sim = Simulator("cantilever", {"body.mesh.cell": 0.1, "model.kind": "full"})
    integ = sim.model.integrator
    integ.projected_run = 5
    snap = sim.model.get_state()
    integ.projected_run = 0
    sim.model.set_state(snap)
    assert integ.projected_run == 5
    sim.model.set_state(snap["x"], snap["v"])   # a configuration set by hand starts exact
    assert integ.projected_run == 0
    sim.model.set_state(snap)
    sim.reset()
    assert integ.projected_run == 0


def test_projection_without_memory_tries_the_exact_tangent_every_step():
    """projection_memory False (the precompute's training): every step tries the exact
    tangent first, and a projected retry keeps the exact tangent's stiffness damping, so
    with beta > 0 it is not projection always's step (the policy before the memory)."""
    m = _model("stvk", pinned=np.flatnonzero(box(size=(1.0, 0.5, 0.5), cell=0.25).vertices[:, 0] < 1e-9))
    old = BackwardEuler(m, 1 / 30, NewtonSettings(max_iterations=1, beta=1e-5, projection_memory=False))
    always = BackwardEuler(m, 1 / 30, NewtonSettings(max_iterations=1, beta=1e-5, projection="always"))
    x, v = m.X.copy(), np.zeros_like(m.X)
    x[m.X[:, 0] > 0.99, 0] -= 0.4
    projected = 0
    for _ in range(10):
        x1, v1 = old.step(x, v, np.zeros_like(x))
        assert not old.stats["projected_start"] and old.projected_run == 0
        if old.stats["projected"]:
            projected += 1
            assert not np.array_equal(always.step(x, v, np.zeros_like(x))[0], x1)
        x, v = x1, v1
    assert projected >= 1
