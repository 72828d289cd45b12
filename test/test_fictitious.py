"""The free body's mean rigid motion (reduced/fictitious.py) against its definition."""
import numpy as np

from mdss_ros.reduced.fictitious import momentum_kernel
from mdss_ros.rotations import exp_so3


def test_momentum_kernel_matches_the_sums_it_stands_for():
    """C, V, L and I of rotated rigid bodies plus point masses, against the sums written
    out one body at a time (the point masses are the full-space vertices: no inertia)."""
    rng = np.random.default_rng(4)
    n = 7
    m = rng.uniform(0.5, 2.0, n)
    c, v, w = rng.normal(size=(3, n, 3))
    R = np.array([exp_so3(a) for a in rng.normal(size=(n, 3))])
    A = rng.normal(size=(n, 3, 3))
    inertia = A @ A.transpose(0, 2, 1)                  # symmetric positive body inertia
    inertia[5:] = 0.0                                    # two point masses
    out = np.empty((6, 3))
    momentum_kernel(m, c, v, w, R, inertia, out)
    M = m.sum()
    C = (m[:, None] * c).sum(0) / M
    V = (m[:, None] * v).sum(0) / M
    L = np.zeros(3)
    I = np.zeros((3, 3))
    for k in range(n):
        rho = c[k] - C
        I_k = R[k] @ inertia[k] @ R[k].T
        I += I_k + m[k] * (rho @ rho * np.eye(3) - np.outer(rho, rho))
        L += np.cross(rho, m[k] * (v[k] - V)) + I_k @ w[k]
    np.testing.assert_allclose(out[0], C, rtol=1e-14, atol=1e-14)
    np.testing.assert_allclose(out[1], V, rtol=1e-14, atol=1e-14)
    np.testing.assert_allclose(out[2], L, rtol=1e-13, atol=1e-13)
    np.testing.assert_allclose(out[3:], I, rtol=1e-13, atol=1e-13)
    # A rigid rotation about the mass centre: every body moves with v = W x rho and turns
    # with W, so L = I W.
    W = np.array([0.3, -1.2, 0.7])
    v_rigid = np.cross(W, c - C)
    momentum_kernel(m, c, v_rigid, np.tile(W, (n, 1)), R, inertia, out)
    np.testing.assert_allclose(out[1], 0.0, atol=1e-14)
    np.testing.assert_allclose(out[2], out[3:] @ W, rtol=1e-13)
