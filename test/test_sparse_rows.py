"""Contact rows held as their entries (reduced/sparse_rows.py) against the dense kernel
they replaced in the contact solves (contact_rows_kernel below, the product's until
session 18, kept here as the reference)."""
from types import SimpleNamespace

import numpy as np
from numba import njit

from mdss_ros.reduced.sparse_rows import ContactRowEntries


@njit
def contact_rows_kernel(dirs, rows, U, row_domain, R, c, xv, q_index, mask, frame_cols, row_of, dt, out):
    """Dense contact rows: out[row_of[i] r + j] += dt d_ij^T J_i for corner rows i (k,) of
    subspace vertices, directions dirs (k, r, 3) (weighted), so a face point's corners
    sum into their contact's row. d^T J = (R^T d)^T U on the domain's modal columns
    q_index (D, r_max) where mask, plus [d, (x - c) x d] on frame_cols (D, 6) of a movable
    domain (-1 for a fixed one). rows (k,) stacked rows; xv (k, 3) positions; out
    (m r, n_gen) zeroed. Serial: at most a few hundred corner rows, O(k r r_max)."""
    k, r = dirs.shape[0], dirs.shape[1]
    r_max = U.shape[2]
    for i in range(k):
        row = rows[i]
        dom = row_domain[row]
        ax = xv[i, 0] - c[dom, 0]
        ay = xv[i, 1] - c[dom, 1]
        az = xv[i, 2] - c[dom, 2]
        for j in range(r):
            d0, d1, d2 = dirs[i, j, 0], dirs[i, j, 1], dirs[i, j, 2]
            # R^T d
            e0 = d0 * R[dom, 0, 0] + d1 * R[dom, 1, 0] + d2 * R[dom, 2, 0]
            e1 = d0 * R[dom, 0, 1] + d1 * R[dom, 1, 1] + d2 * R[dom, 2, 1]
            e2 = d0 * R[dom, 0, 2] + d1 * R[dom, 1, 2] + d2 * R[dom, 2, 2]
            o = row_of[i] * r + j
            for b in range(r_max):
                if mask[dom, b]:
                    out[o, q_index[dom, b]] += dt * (e0 * U[row, 0, b] + e1 * U[row, 1, b] + e2 * U[row, 2, b])
            if frame_cols[dom, 0] >= 0:
                out[o, frame_cols[dom, 0]] += dt * d0
                out[o, frame_cols[dom, 1]] += dt * d1
                out[o, frame_cols[dom, 2]] += dt * d2
                out[o, frame_cols[dom, 3]] += dt * (ay * d2 - az * d1)
                out[o, frame_cols[dom, 4]] += dt * (az * d0 - ax * d2)
                out[o, frame_cols[dom, 5]] += dt * (ax * d1 - ay * d0)


def _layout_and_rows(seed=0, k=200, contacts=80):
    """A made-up layout of three domains (mode counts 5, 3, 4 padded to 5; domain 1 fixed,
    no frame columns) and k corner rows in `contacts` contacts (several corners per
    contact, often in one domain, as a face's corners)."""
    rng = np.random.default_rng(seed)
    D, r_max, n_rows = 3, 5, 40
    r = np.array([5, 3, 4])
    mask = np.arange(r_max)[None, :] < r[:, None]
    q_index = np.full((D, r_max), -1, dtype=np.int64)
    frame_cols = np.full((D, 6), -1, dtype=np.int64)
    col = 0
    for d in range(D):
        q_index[d, :r[d]] = col + np.arange(r[d])
        col += r[d]
        if d != 1:
            frame_cols[d] = col + np.arange(6)
            col += 6
    layout = SimpleNamespace(U=rng.normal(size=(n_rows, 3, r_max)) * np.repeat(mask, [14, 13, 13], axis=0)[:, None, :],
                             row_domain=np.repeat(np.arange(D), [14, 13, 13]).astype(np.int64),
                             q_index=q_index, mask=mask)
    group = np.sort(rng.integers(0, contacts, k))
    starts = np.flatnonzero(np.r_[True, group[1:] != group[:-1]])
    row_of = (np.searchsorted(starts, np.arange(k), side="right") - 1).astype(np.int64)
    vrow = rng.integers(0, n_rows, k).astype(np.int64)
    R = np.stack([np.linalg.qr(rng.normal(size=(3, 3)))[0] for _ in range(D)])
    c = rng.normal(size=(D, 3))
    return layout, frame_cols, col, R, c, vrow, row_of, len(starts), rng


def test_entries_give_the_dense_rows_and_their_products():
    layout, frame_cols, n, R, c, vrow, row_of, m, rng = _layout_and_rows()
    for r in (1, 3):
        dirs = rng.normal(size=(len(vrow), r, 3))
        xv = rng.normal(size=(len(vrow), 3))
        dense = np.zeros((m * r, n))
        contact_rows_kernel(dirs, vrow, layout.U, layout.row_domain, R, c, xv, layout.q_index,
                                        layout.mask, frame_cols, row_of, 0.01, dense)
        C = ContactRowEntries.build(dirs, vrow, layout, R, c, xv, frame_cols, row_of, m, 0.01, n)
        assert C.shape == dense.shape
        # Dense rows: the same values added in the same order, bit for bit.
        assert np.array_equal(C[np.arange(m * r)], dense)
        idx = rng.permutation(m * r)[:17]
        assert np.array_equal(C[idx], dense[idx])
        assert np.array_equal(C[np.arange(m * r) % 2 == 0], dense[::2])
        sub = C.take(idx)
        assert np.array_equal(sub[np.arange(len(idx))], dense[idx])
        # Products and norms: to round-off (a row's entries are summed in another order).
        x = rng.normal(size=n)
        lam = np.abs(rng.normal(size=m * r))
        lam[::4] = 0.0
        scale = np.abs(dense).max()
        assert np.allclose(C @ x, dense @ x, rtol=0, atol=1e-14 * scale * np.abs(x).sum())
        assert np.allclose(C.rmatvec(lam), dense.T @ lam, rtol=0, atol=1e-14 * scale * lam.sum())
        assert np.allclose(C.norms(), np.linalg.norm(dense, axis=1), rtol=1e-14, atol=1e-300)
        X = rng.normal(size=(n, 4))
        assert np.allclose(C @ X, dense @ X, rtol=0, atol=1e-14 * scale * np.abs(X).sum())
        # Products of some rows in place: take()'s products exactly (the same sums in order).
        assert np.array_equal(C.matvec_rows(idx, x), sub @ x)
        assert np.array_equal(C.rmatvec_rows(idx, lam[:len(idx)]), sub.rmatvec(lam[:len(idx)]))
        assert np.array_equal(C.matvec_rows(idx[:0], x), np.zeros(0))


def test_a_vertex_per_contact():
    layout, frame_cols, n, R, c, vrow, _, _, rng = _layout_and_rows(seed=3)
    k = len(vrow)
    row_of = np.arange(k, dtype=np.int64)
    dirs = rng.normal(size=(k, 1, 3))
    xv = rng.normal(size=(k, 3))
    dense = np.zeros((k, n))
    contact_rows_kernel(dirs, vrow, layout.U, layout.row_domain, R, c, xv, layout.q_index,
                                    layout.mask, frame_cols, row_of, 0.02, dense)
    C = ContactRowEntries.build(dirs, vrow, layout, R, c, xv, frame_cols, row_of, k, 0.02, n)
    assert C.cols.shape[1] == layout.U.shape[2] + 6          # one corner's columns a row
    assert np.array_equal(C[np.arange(k)], dense)


def test_frictional_correction_reads_entries_as_the_dense_rows():
    """friction.frictional_correction on a reduced body's frictional rows (n, t1, t2 per
    contact) held as entries: the same forces and correction as on the dense rows, to
    round-off, also when contacts join the working set in later rounds."""
    from mdss_ros.contact.friction import frictional_correction
    layout, frame_cols, n, R, c, vrow, row_of, m, rng = _layout_and_rows(seed=5, k=60, contacts=30)
    dirs = rng.normal(size=(len(vrow), 3, 3))
    xv = rng.normal(size=(len(vrow), 3))
    dense = np.zeros((3 * m, n))
    contact_rows_kernel(dirs, vrow, layout.U, layout.row_domain, R, c, xv, layout.q_index,
                                    layout.mask, frame_cols, row_of, 0.01, dense)
    C = ContactRowEntries.build(dirs, vrow, layout, R, c, xv, frame_cols, row_of, m, 0.01, n)
    B = rng.normal(size=(n, n))
    A = B @ B.T + n * np.eye(n)
    solve = lambda rhs: np.linalg.solve(A, rhs)                       # noqa: E731
    g = rng.normal(size=3 * m) * 0.01
    mu = np.full(m, 0.5)
    hint = np.zeros(m, dtype=bool)
    hint[:3] = True                                  # a small first working set: later rounds add rows
    lam_d, corr_d, info_d = frictional_correction(solve, dense, g, mu, regularize=1e-9, hint=hint)
    lam_e, corr_e, info_e = frictional_correction(solve, C, g, mu, regularize=1e-9, hint=hint)
    assert info_d["rounds"] > 1 and info_e["rounds"] == info_d["rounds"]
    assert info_d["working_set"] == info_e["working_set"] > 3
    scale = np.abs(lam_d).max()
    assert scale > 0 and np.allclose(lam_e, lam_d, rtol=0, atol=1e-12 * scale)     # measured: equal
    assert np.allclose(corr_e, corr_d, rtol=0, atol=1e-12 * np.abs(corr_d).max())


def test_frictional_rows_build_only_what_the_solve_reads():
    """reduced/contact_rows.FrictionalRows build a contact's tangential rows only when the
    Coulomb solve asks for them (its working set), and the solve's answer is the one on
    every contact's three rows built at once (bit for bit: the same rows, the same gaps),
    under a co-rotating step's rigid velocity (a free block on a tilted floor)."""
    from mdss_ros.contact.friction import FrictionRows, frictional_correction, rows_of
    from mdss_ros.simulator import Simulator
    from mdss_ros.verify.friction_study import MODELS, incline
    sim = Simulator(incline(20.0, MODELS["reduced"]))
    sim.step(5)
    model = sim.model
    gm = model._global_motion(model._inertia_of(model.q))
    assert gm is not None
    # The corner rows (ContactRows._corner_rows, which face contacts and full-space bodies
    # take) of the step's candidates; _contact_rows builds every row of a body of subspace
    # domains for the compiled solve (test_frictional_kernel.py).
    captured = {}
    orig = type(model)._vertex_friction_rows

    def spy(self, *args):
        captured["args"] = args
        return orig(self, *args)
    type(model)._vertex_friction_rows = spy
    try:
        model._contact_rows(sim._contact_spec(), gm, model.dt)
    finally:
        type(model)._vertex_friction_rows = orig
    lazy = model._corner_rows(*captured["args"])[5]
    every = model._corner_rows(*captured["args"])[5]
    m, n = len(lazy.mu), lazy.C.shape[1]
    every.ensure(np.arange(m))
    rng = np.random.default_rng(3)
    v = rng.normal(size=n) * 1e-2
    B = rng.normal(size=(n, n))
    A = B @ B.T + n * np.eye(n)
    solve = lambda rhs: np.linalg.solve(A, rhs)                       # noqa: E731
    whole = FrictionRows(*every.at(v).block(np.arange(m)))
    assert lazy.guess is not None                     # the last step's contacts: built first
    lam_w, corr_w, info_w = frictional_correction(solve, whole, None, every.mu, regularize=1e-9,
                                                  lam_guess=every.guess)
    lam_l, corr_l, info_l = frictional_correction(solve, lazy.at(v), None, lazy.mu, regularize=1e-9,
                                                  lam_guess=lazy.guess)
    built = np.flatnonzero(lazy.slot >= 0)
    assert 0 < info_l["working_set"] == len(built) < m            # only the working set's rows
    assert info_l["active"] == info_w["active"] > 0
    assert np.array_equal(lam_l, lam_w) and np.array_equal(corr_l, corr_w)
    dense, g = lazy.at(v).block(built)
    assert np.array_equal(dense, whole.C[rows_of(built)]) and np.array_equal(g, whole.g[rows_of(built)])
    assert np.array_equal(lazy.tangents[built], every.tangents[built])
