"""The compiled frame and force kernels of the reduced step (reduced/frames.py,
generalised_forces.gravity_rows_kernel) against their formulas written in numpy, on random
domains of different mode counts (padded to r_max), fixed and movable."""
import numpy as np

from mdss_ros.reduced.frames import (FrameState, fictitious_kernel, fictitious_rows_kernel, inertia_kernel,
                                     world_inertia_kernel)
from mdss_ros.reduced.generalised_forces import gravity_rows_kernel
from mdss_ros.rotations import cross, exp_so3, exp_so3_batch


def _domains(seed, r=(5, 3, 7, 4), movable=(True, False, True, True)):
    rng = np.random.default_rng(seed)
    D, r_max = len(r), max(r)
    r = np.array(r, dtype=np.int64)
    movable = np.array(movable)
    mask = np.arange(r_max)[None, :] < r[:, None]
    B1 = rng.normal(size=(D, r_max, 3, 3)) * mask[:, :, None, None]
    B2 = rng.normal(size=(D, r_max, r_max, 3, 3))
    B2 = (B2 + B2.transpose(0, 2, 1, 4, 3)) * (mask[:, :, None] & mask[:, None, :])[..., None, None]
    W = rng.normal(size=(D, r_max, r_max, 3))
    W = (W - W.transpose(0, 2, 1, 3)) * (mask[:, :, None] & mask[:, None, :])[..., None]
    s = rng.normal(size=(D, r_max)) * mask
    q, qd = rng.normal(size=(D, r_max)) * mask, rng.normal(size=(D, r_max)) * mask
    A = rng.normal(size=(D, 3, 3))
    I0 = A @ A.transpose(0, 2, 1) + 3 * np.eye(3)
    R = exp_so3_batch(rng.normal(size=(D, 3)))
    offsets = np.concatenate([[0], np.cumsum(r)[:-1]])
    q_index = np.where(mask, offsets[:, None] + np.arange(r_max)[None, :], -1)
    return rng, dict(r=r, movable=movable, mask=mask, B1=B1, B2=B2, W=W, s=s, q=q, qd=qd, I0=I0, R=R,
                     q_index=q_index, n=int(r.sum()))


def _inertia_numpy(d, k):
    """I(q) = I0 + (tr L + tr B2(q, q)) I - L - B2(q, q), L = B1(q) + B1(q)^T (frames.py)."""
    q = d["q"][k]
    b1 = np.einsum("a,aij->ij", q, d["B1"][k])
    b2 = np.einsum("a,b,abij->ij", q, q, d["B2"][k])
    L = b1 + b1.T
    return d["I0"][k] + (np.trace(L) + np.trace(b2)) * np.eye(3) - L - b2


def test_inertia_kernel_is_the_inertia_formula():
    _, d = _domains(0)
    out = np.empty((4, 3, 3))
    inertia_kernel(d["q"], d["r"], d["I0"], d["B1"], d["B2"], out)
    for k in range(4):
        np.testing.assert_allclose(out[k], _inertia_numpy(d, k), rtol=1e-13, atol=1e-13)


def test_world_inertia_kernel_rotates_to_the_predicted_frame():
    rng, d = _domains(1)
    w = rng.normal(size=(4, 3))
    movers = np.flatnonzero(d["movable"])
    for dt in (0.0, 0.01):
        out = np.empty((len(movers), 3, 3))
        world_inertia_kernel(d["R"], w, dt, d["I0"], movers, out)
        Rp = exp_so3_batch(dt * w[movers]) @ d["R"][movers]
        np.testing.assert_allclose(out, Rp @ d["I0"][movers] @ Rp.transpose(0, 2, 1), rtol=1e-13, atol=1e-13)


def test_predict_moves_frames_and_keeps_the_solved_momentum():
    """FrameState.predict against its docstring's formulas, with and without the carried
    global motion; fixed frames stay put with zero velocities."""
    rng, d = _domains(2)
    D, dt = 4, 0.01
    f0 = FrameState(c=rng.normal(size=(D, 3)), R=d["R"].copy(), v=rng.normal(size=(D, 3)),
                    w=rng.normal(size=(D, 3)), w_prev=rng.normal(size=(D, 3)))
    v_new, w_new = rng.normal(size=(D, 3)), rng.normal(size=(D, 3))
    I_s, I_e = d["I0"], d["I0"][::-1].copy()
    mv = d["movable"]
    for carry in (None, (rng.normal(size=3), rng.normal(size=3), rng.normal(size=3))):
        f1 = f0.predict(v_new, w_new, dt, mv, I_s, I_e, carry)
        np.testing.assert_array_equal(f1.w_prev, f0.w)
        np.testing.assert_array_equal(f1.c[~mv], f0.c[~mv])
        np.testing.assert_array_equal(f1.R[~mv], f0.R[~mv])
        assert not f1.v[~mv].any() and not f1.w[~mv].any()
        if carry is None:
            c = f0.c + dt * v_new
            R = exp_so3_batch(dt * w_new) @ f0.R
            v, w_a = v_new, w_new
        else:
            C, V, W = carry
            Rg = exp_so3(dt * W)
            rho = (f0.c - C + dt * v_new) @ Rg.T
            c = C + dt * V + rho
            v = V + cross(W, rho) + v_new @ Rg.T
            R = Rg @ exp_so3_batch(dt * w_new) @ f0.R
            w_a = W + w_new
        np.testing.assert_allclose(f1.c[mv], c[mv], rtol=1e-14, atol=1e-14)
        np.testing.assert_allclose(f1.v[mv], v[mv], rtol=1e-14, atol=1e-14)
        np.testing.assert_allclose(f1.R[mv], R[mv], rtol=1e-13, atol=1e-13)
        # The momentum solved for at the predicted rotation, re-expressed after the step.
        Rp = exp_so3_batch(dt * f0.w) @ f0.R
        h = np.einsum("dij,dj->di", Rp @ I_s @ Rp.transpose(0, 2, 1), w_a)
        h1 = np.einsum("dij,dj->di", f1.R @ I_e @ f1.R.transpose(0, 2, 1), f1.w)
        np.testing.assert_allclose(h1[mv], h[mv], rtol=1e-12, atol=1e-12)


def test_explicit_fictitious_rows_and_gravity_rows_write_each_domains_own_rows():
    rng, d = _domains(3)
    D, dt = 4, 0.01
    w, w_prev = rng.normal(size=(D, 3)), rng.normal(size=(D, 3))
    movers = np.flatnonzero(d["movable"])
    F = np.zeros(d["n"])
    fictitious_rows_kernel(d["W"], d["B1"], d["B2"], d["s"], d["r"], movers, d["q_index"], d["q"], d["qd"],
                           d["R"], w, w_prev, dt, F)
    omega = np.einsum("dji,dj->di", d["R"], w)
    alpha = np.einsum("dji,dj->di", d["R"], w - w_prev) / dt
    f = np.empty_like(d["q"])
    fictitious_kernel(d["W"], d["B1"], d["B2"], d["s"], d["r"], d["movable"], d["q"], d["qd"], omega, alpha, f)
    rows = d["mask"] & d["movable"][:, None]
    expect = np.zeros(d["n"])
    expect[d["q_index"][rows]] = f[rows]
    np.testing.assert_allclose(F, expect, rtol=1e-13, atol=1e-13)
    assert not f[~rows].any()
    for k in movers:                       # the formula of frames.py's docstring, one domain
        rk, o, a = d["r"][k], omega[k], alpha[k]
        q, qd = d["q"][k, :rk], d["qd"][k, :rk]
        direct = (2.0 * np.einsum("b,abk,k->a", qd, d["W"][k, :rk, :rk], o)
                  + np.einsum("b,abk,k->a", q, d["W"][k, :rk, :rk], a)
                  - np.einsum("i,aij,j->a", o, d["B1"][k, :rk], o)
                  - np.einsum("b,i,abij,j->a", q, o, d["B2"][k, :rk, :rk], o) + (o @ o) * (d["s"][k, :rk] + q))
        np.testing.assert_allclose(f[k, :rk], direct, rtol=1e-12, atol=1e-12)
    # Gravity: modes get (sum_l m_l U_l)^T R^T g, movable frames m g.
    mass_moment = rng.normal(size=(D, 3, d["q"].shape[1])) * d["mask"][:, None, :]
    total_mass = rng.uniform(1, 2, D)
    lin_index = d["n"] + 3 * np.arange(len(movers))[:, None] + np.arange(3)
    G = np.zeros(d["n"] + 3 * len(movers))
    g = np.array([0.3, -1.0, -9.81])
    gravity_rows_kernel(mass_moment, d["r"], d["q_index"], d["R"], g, total_mass, movers, lin_index, G)
    modal = np.einsum("dia,di->da", mass_moment, np.einsum("dji,j->di", d["R"], g))
    np.testing.assert_allclose(G[d["q_index"][d["mask"]]], modal[d["mask"]], rtol=1e-13, atol=1e-13)
    np.testing.assert_allclose(G[lin_index], total_mass[movers, None] * g, rtol=1e-15)


def test_global_rows_kernel_is_the_rigid_motion_on_the_frames_rows():
    """fictitious.global_rows_kernel against _rigid_Q's, _global_fictitious's and
    _coriolis_rotate's numpy formulas (FictitiousTerms), on three of four frames movable."""
    from mdss_ros.reduced.fictitious import global_rows_kernel
    rng = np.random.default_rng(4)
    D, n = 4, 30
    c = rng.normal(size=(D, 3))
    movers = np.array([0, 2, 3])
    lin_index = 10 + 6 * np.arange(3)[:, None] + np.arange(3)
    ang_index = lin_index + 3
    m = rng.uniform(1, 2, D)
    C, V, W = rng.normal(size=3), rng.normal(size=3), rng.normal(size=3)
    Rc = exp_so3(rng.normal(size=3))
    Q_in = rng.normal(size=n)
    for rigid, angular_only, centrifugal in ((True, False, False), (True, True, False), (False, False, True),
                                             (False, False, False)):
        Q = np.full(n, 7.0)
        global_rows_kernel(c, movers, lin_index, ang_index, m, C, V, W, rigid, angular_only, centrifugal, Rc, Q_in, Q)
        expect = np.full(n, 7.0)
        if rigid:
            expect[ang_index] = W
            if not angular_only:
                expect[lin_index] = V + cross(W, c[movers] - C)
        elif centrifugal:
            expect[lin_index] = -m[movers, None] * cross(W, cross(W, c[movers] - C))
        else:
            expect[lin_index] = Q_in[lin_index] @ Rc.T
        np.testing.assert_allclose(Q, expect, rtol=1e-14, atol=1e-14)
