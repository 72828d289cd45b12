"""Mesh vertices that are not nodes, moved by the MLS interpolation of the nodes
(docs/method.md §19.9; the issue's "surface output ... moved by the MLS interpolation of
nodal displacements").

First-order MLS shape functions at a point p, over its k nearest nodes X_j (offsets
d_j = X_j - p, support radius h_p = support_scale * mean |d_j|, weights w_j = w(|d_j| / h_p),
the kernel of mls.py), with the linear basis q_j = (1, d_j) (4,):

    M(p)     = sum_j w_j q_j q_j^T                  (4, 4) moment matrix
    phi_j(p) = w_j q_j^T M(p)^-1 e_0                 (k,)

They reproduce every linear field exactly (sum_j phi_j = 1, sum_j phi_j X_j = p), so a
rigid motion moves the points rigidly, and forces spread back by phi (W^T f) keep their
total and moment. They do not interpolate (phi_j(X_i) != delta_ij): the points follow the
nodes' fitted field.

Arrays: idx (p, k) int64 node ids; phi (p, k).
"""
import numpy as np
from scipy.spatial import cKDTree

from ..errors import SceneError
from .mls import kernel

SINGULAR = 0.05


def shape_functions(X, points, k=16, support_scale=2.0):
    """(idx (p, k), phi (p, k)): MLS shape functions at points (p, 3) over nodes X (n, 3)."""
    X = np.asarray(X, dtype=np.float64)
    points = np.asarray(points, dtype=np.float64)
    k = int(min(k, len(X)))
    dist, idx = cKDTree(X).query(points, k=k)
    d = X[idx] - points[:, None, :]                                        # (p, k, 3)
    h = float(support_scale) * dist.mean(axis=1)
    rbar = np.maximum(dist.mean(axis=1), 1e-300)[:, None]
    w = kernel(dist / np.maximum(h, 1e-300)[:, None]) / ((dist / rbar) ** 2 + SINGULAR ** 2)   # (p, k)
    q = np.concatenate([np.ones(d.shape[:2] + (1,)), d / np.maximum(h, 1e-300)[:, None, None]], axis=2)
    M = np.einsum("pk,pka,pkb->pab", w, q, q, optimize=True)
    lam = np.linalg.eigvalsh(M)
    bad = lam[:, 0] <= 1e-10 * lam[:, 3]
    if bad.any():
        raise SceneError(f"meshless model: {int(bad.sum())} mesh vertices have nearly coplanar nearest nodes "
                         f"(e.g. vertex {int(np.flatnonzero(bad)[0])}), so the MLS interpolation there is "
                         f"undefined; lower model.meshless.spacing")
    a = np.linalg.solve(M, np.broadcast_to(np.eye(4)[0], (len(M), 4))[..., None])[..., 0]   # M^-1 e_0 (p, 4)
    phi = w * np.einsum("pka,pa->pk", q, a)
    return idx.astype(np.int64), phi


class Embedding:
    """Points (p of them) moved by nodes: position_a = sum_j phi_aj x_{idx_aj}."""

    def __init__(self, idx, phi):
        self.idx = np.ascontiguousarray(idx, dtype=np.int64)
        self.phi = np.ascontiguousarray(phi, dtype=np.float64)
        self.n_nodes = int(self.idx.max()) + 1 if self.idx.size else 0

    def __len__(self):
        return len(self.idx)

    def apply(self, x, ids=None):
        """Positions (or velocities, displacements) (p, 3) of the points, or of points ids,
        from the nodes' x (n, 3)."""
        idx, phi = (self.idx, self.phi) if ids is None else (self.idx[ids], self.phi[ids])
        return np.einsum("pk,pki->pi", phi, x[idx], optimize=True)

    def spread(self, f, n_nodes):
        """Node forces (n_nodes, 3) = W^T f of point forces f (p, 3): the same virtual work
        for every node motion."""
        out = np.zeros((n_nodes, 3))
        np.add.at(out, self.idx.ravel(), (self.phi[:, :, None] * f[:, None, :]).reshape(-1, 3))
        return out

    def corners(self, points, weights):
        """Contact points given as weighted points (corners (m, c) point ids, weights (m, c))
        as weighted nodes: (node ids (m, c k), weights (m, c k))."""
        points = np.asarray(points, dtype=np.int64)
        shape = (len(points), points.shape[1] * self.idx.shape[1])
        return (self.idx[points].reshape(shape),
                (np.asarray(weights)[:, :, None] * self.phi[points]).reshape(shape))
