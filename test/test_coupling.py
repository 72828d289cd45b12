"""Coupling projection kernels: the two-phase projection (per-vertex K J, then per domain
pair GEMMs) against the direct per-element-pair product, on random data."""
import numpy as np

from mdss_ros.reduced.coupling import TwoPhaseProjection, coupling_entries, project_coupling


def _random_coupling(seed, n_I=40, n_c=60, sizes=(7, 10, 4)):
    rng = np.random.default_rng(seed)
    sub = np.sort(rng.integers(0, len(sizes), n_I))          # interface vertices ordered by domain
    elem = np.stack([rng.choice(n_I, 4, replace=False) for _ in range(n_c)])
    s_max = max(sizes)
    offsets = np.concatenate([[0], np.cumsum(sizes)[:-1]])
    J = np.zeros((n_I, 3, s_max))
    cols = np.full((n_I, s_max), -1, dtype=np.int64)
    for a in range(n_I):
        s = sizes[sub[a]]
        J[a, :, :s] = rng.standard_normal((3, s))
        cols[a, :s] = offsets[sub[a]] + np.arange(s)
    K = rng.standard_normal((n_c, 12, 12))
    K = K + K.transpose(0, 2, 1)
    f = rng.standard_normal((n_c, 4, 3))
    return sub, elem, J, cols, K, f, np.array(sizes), offsets


def test_two_phase_projection_equals_the_per_element_product():
    for seed in range(3):
        sub, elem, J, cols, K, f, sizes, offsets = _random_coupling(seed)
        S = int(sizes.sum())
        G_ref, A_ref = np.zeros(S), np.zeros((S, S))
        project_coupling(elem, f, K, J, cols, np.zeros(len(sub), bool), np.zeros((len(sub), 3), np.int64),
                         G_ref, A_ref, np.zeros((S, 0)))
        tp = TwoPhaseProjection(elem, sub, sizes, offsets)
        G, A = np.zeros(S), np.zeros((S, S))
        tp.add(f, K, J, G, A)
        assert np.allclose(G, G_ref, rtol=1e-12, atol=1e-12)
        assert np.allclose(A, A_ref, rtol=1e-12, atol=1e-11)
        # Pairs cut into many chunks (one entry each, and a few) sum to the same.
        for chunk in (1, 3):
            tp_c = TwoPhaseProjection(elem, sub, sizes, offsets, chunk=chunk)
            assert len(tp_c.chunks) > len(tp_c.groups)
            G_c, A_c = np.zeros(S), np.zeros((S, S))
            tp_c.add(f, K, J, G_c, A_c)
            assert np.allclose(G_c, G_ref, rtol=1e-12, atol=1e-12)
            assert np.allclose(A_c, A_ref, rtol=1e-12, atol=1e-11)
        G2, A2 = np.zeros(S), np.zeros((S, S))
        tp.add(f, K, J, G2, A2)             # buffers are reused: a second call is not accumulated twice
        assert np.allclose(A2, A_ref, rtol=1e-12, atol=1e-11)
        # Cubature weights applied inside the kernel = weighted element forces and stiffness.
        w = np.random.default_rng(seed).uniform(0.2, 3.0, len(elem))
        G_w, A_w = np.zeros(S), np.zeros((S, S))
        project_coupling(elem, f * w[:, None, None], K * w[:, None, None], J, cols, np.zeros(len(sub), bool),
                         np.zeros((len(sub), 3), np.int64), G_w, A_w, np.zeros((S, 0)))
        G3, A3 = np.zeros(S), np.zeros((S, S))
        tp.add(f, K, J, G3, A3, weights=w)
        assert np.allclose(G3, G_w, rtol=1e-12, atol=1e-12) and np.allclose(A3, A_w, rtol=1e-12, atol=1e-10)


def test_coupling_entries_group_by_domain_pair():
    sub, elem, *_ = _random_coupling(4)
    ev, ed, pair_entry = coupling_entries(elem, sub)
    key = sub[ev] * 10 + ed
    assert np.all(np.diff(key) >= 0)                          # one block per domain pair
    k = elem.shape[1]
    a = np.repeat(elem, k, axis=1).reshape(-1, k, k)
    b = np.tile(elem, (1, k)).reshape(-1, k, k)
    assert np.array_equal(ev[pair_entry], a) and np.array_equal(ed[pair_entry], sub[b])


def test_two_phase_plus_full_block_equals_the_per_element_product_beside_full_space_vertices():
    """Mixed systems: subspace pairs two-phase, subspace-full pairs by project_coupling_full,
    forces by project_forces; together they must equal project_coupling."""
    from mdss_ros.reduced.coupling import project_coupling_full, project_forces
    sub, elem, J, cols, K, f, sizes, offsets = _random_coupling(7)
    n_I = len(sub)
    S = int(sizes.sum())
    full = np.zeros(n_I, bool)
    full[-6:] = True                                   # the last vertices are full-space, ordered last
    full[-1] = True
    icol = np.full((n_I, 3), -1, dtype=np.int64)
    F_I = 0
    for a in np.flatnonzero(full)[:-1]:                # the very last one is pinned: no DOFs
        icol[a] = 3 * F_I + np.arange(3)
        F_I += 1
    J[full] = 0.0
    cols[full] = -1
    J[full, :, :3] = np.eye(3)
    for a in np.flatnonzero(full):
        cols[a, :3] = S + icol[a] if icol[a, 0] >= 0 else -1
    cols[full, 3:] = -1
    sub = np.where(full, -1, sub)
    G_ref, A_ref, B_ref = np.zeros(S + 3 * F_I), np.zeros((S, S)), np.zeros((S, 3 * F_I))
    project_coupling(elem, f, K, J, cols, full, icol, G_ref, A_ref, B_ref)
    G, A, B = np.zeros(S + 3 * F_I), np.zeros((S, S)), np.zeros((S, 3 * F_I))
    project_forces(elem, f, J, cols, G)
    TwoPhaseProjection(elem, sub, sizes, offsets).add(f, K, J, None, A)
    project_coupling_full(elem, K, J, cols, full, icol, B)
    assert np.allclose(G, G_ref, rtol=1e-12, atol=1e-12)
    assert np.allclose(A, A_ref, rtol=1e-12, atol=1e-11)
    assert np.allclose(B, B_ref, rtol=1e-12, atol=1e-11) and np.abs(B).max() > 0
