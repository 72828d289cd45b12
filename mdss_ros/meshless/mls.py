"""First-order moving least squares gradients at the nodes (docs/method.md §19.2; [HZ] §2.2).

Kernel, r = |X_j - X_i| / h_i ([HZ] eq. 1):

    w(r)  = 1 - 3 r^2 + 2 r^3      for r < 1, 0 otherwise
    w'(r) = -6 r + 6 r^2           for r < 1, 0 otherwise

For node i with neighbours j (offsets X_ij = X_j - X_i, weights w_ij = w(|X_ij| / h_i)), the
first-order Taylor fit u_j ~ u_i + grad u_i X_ij minimising sum_j w_ij |u_j - u_i - grad u_i X_ij|^2
([HZ] eqs. 6-9) gives

    A_i      = sum_j w_ij X_ij X_ij^T                    (3, 3)  moment matrix
    d_ij     = w_ij A_i^-1 X_ij                          (3,)    gradient weights
    grad u_i = sum_j (u_j - u_i) d_ij^T                  (3, 3)
    F_i      = I + grad u_i = sum_j (x_j - x_i) d_ij^T    (exact: sum_j X_ij d_ij^T = I)

so F_i = sum_a x_{s_ia} c_ia^T over the stencil s_i = (i, j_1 .. j_k) with
c_i0 = -sum_j d_ij and c_ij = d_ij, the same form as a tet's F = sum_a x_a g_a^T (§2).
A linear displacement field u = G X + t gives grad u_i = G exactly at every node (the
patch test) as long as A_i is inverted exactly.

Ill-conditioned moment matrices (neighbours nearly coplanar or collinear): A_i is
inverted through its eigen-decomposition with eigenvalues below rcond * max eigenvalue
raised to that floor (a Tikhonov-like pseudo-inverse); those nodes are counted and lose
the exact patch test in the direction of the small eigenvalue. A node with fewer than 3
weighted neighbours has a rank-deficient A_i and is an error (support too small).

Arrays (n nodes, k neighbours, w = k + 1 stencil width):
    stencil (n, w) int64   node i, then its neighbours
    c       (n, w, 3)      gradient coefficients, sum_a c_ia = 0
    weights (n, k)         w_ij
    cond    (n,)           condition number of A_i (before the floor)
"""
from dataclasses import dataclass

import numpy as np

from ..errors import SceneError


def kernel(r):
    """w(r) = 1 - 3 r^2 + 2 r^3 for 0 <= r < 1, else 0 (any array shape)."""
    r = np.asarray(r, dtype=np.float64)
    return np.where(r < 1.0, 1.0 - 3.0 * r * r + 2.0 * r * r * r, 0.0)


def kernel_derivative(r):
    """w'(r) = -6 r + 6 r^2 for 0 <= r < 1, else 0."""
    r = np.asarray(r, dtype=np.float64)
    return np.where(r < 1.0, -6.0 * r + 6.0 * r * r, 0.0)


@dataclass(frozen=True)
class GradientOperator:
    stencil: np.ndarray
    c: np.ndarray
    weights: np.ndarray
    cond: np.ndarray
    floored: int           # nodes whose A_i needed the eigenvalue floor

    def deformation_gradients(self, x):
        """F (n, 3, 3), F_i = sum_a x_{s_ia} c_ia^T, for positions x (n_nodes, 3)."""
        return np.einsum("nai,naj->nij", x[self.stencil], self.c, optimize=True)

    def gradients(self, u):
        """grad u (n, 3, 3) of a displacement (or any vector) field u (n_nodes, 3)."""
        return self.deformation_gradients(u)


def moments(X, nbr, h):
    """(X_ij (n, k, 3), w_ij (n, k), A_i (n, 3, 3)) of nodes X (n, 3), neighbours nbr (n, k)
    and support radii h (n,)."""
    X = np.asarray(X, dtype=np.float64)
    Xij = X[nbr] - X[:, None, :]                                   # (n, k, 3)
    r = np.linalg.norm(Xij, axis=2) / h[:, None]
    w = kernel(r)                                                  # (n, k)
    return Xij, w, np.einsum("nk,nka,nkb->nab", w, Xij, Xij, optimize=True)


def conditions(X, nbr, h):
    """Condition number (n,) of each node's moment matrix A_i; inf where A_i is singular
    or fewer than 3 neighbours carry weight."""
    _, w, A = moments(X, nbr, h)
    lam = np.linalg.eigvalsh(A)
    singular = ((w > 0).sum(1) < 3) | (lam[:, 0] <= 1e-14 * lam[:, 2])
    cond = np.full(len(A), np.inf)
    cond[~singular] = lam[~singular, 2] / lam[~singular, 0]
    return cond


def gradient_operator(X, nbr, h, rcond=1e-6):
    """MLS gradient operator of nodes X (n, 3) with neighbours nbr (n, k) and support radii
    h (n,). rcond: eigenvalue floor of the moment matrices relative to their largest."""
    n, k = nbr.shape
    Xij, w, A = moments(X, nbr, h)
    few = np.flatnonzero((w > 0).sum(1) < 3)
    if few.size:
        raise SceneError(f"meshless model: {few.size} nodes have fewer than 3 neighbours inside their "
                         f"support (e.g. node {few[0]}); raise model.meshless.support_scale or neighbours")
    lam, Q = np.linalg.eigh(A)                                     # ascending
    top = lam[:, 2:3]
    cond = top[:, 0] / np.maximum(lam[:, 0], 1e-300 * top[:, 0])
    if np.any(lam[:, 1] <= 1e-12 * top[:, 0]):
        bad = int(np.flatnonzero(lam[:, 1] <= 1e-12 * top[:, 0])[0])
        raise SceneError(f"meshless model: node {bad}'s weighted neighbours are collinear (moment matrix of "
                         f"rank < 2); raise model.meshless.support_scale or neighbours")
    floor = rcond * top
    lam_f = np.maximum(lam, floor)
    floored = int((lam < floor).any(axis=1).sum())
    Ainv = np.einsum("nab,nb,ncb->nac", Q, 1.0 / lam_f, Q, optimize=True)
    d = w[:, :, None] * np.einsum("nab,nkb->nka", Ainv, Xij, optimize=True)   # (n, k, 3)
    c = np.concatenate([-d.sum(axis=1, keepdims=True), d], axis=1)             # (n, k + 1, 3)
    stencil = np.concatenate([np.arange(n)[:, None], nbr], axis=1).astype(np.int64)
    return GradientOperator(stencil=stencil, c=np.ascontiguousarray(c), weights=w, cond=cond, floored=floored)
