"""Neighbourhoods of the meshless nodes (docs/method.md §19.1).

Nodes are the body's tet-mesh vertices, X (n, 3) at rest. Each node i gets its k nearest
other nodes (scipy cKDTree, exact k-NN; ties broken by the tree) and a spherical support

    rbar_i = mean_{j in N(i)} |X_j - X_i|          (n,)   mean distance to the k nearest
    h_i    = support_scale * rbar_i                 (n,)   support radius

Arrays:
    nbr   (n, k) int64    neighbour ids, nearest first (node i itself excluded); a row
                          shorter than k (a grown one's neighbours, see `grow`) is padded
                          with i itself at distance inf, so its weight is 0
    dist  (n, k) float64  |X_j - X_i| at rest (inf in the padding)
    rbar  (n,)            mean neighbour distance (over the real neighbours)
    h     (n,)            support radius

`grow` widens the neighbourhoods of chosen nodes (those with an ill-conditioned moment
matrix, mls.py): their k nearest become their 2k nearest, the support radius follows from
the new mean distance, and every other row is padded to the new width.

The neighbour lists are fixed at rest (total Lagrangian, like [HZ] and Mueller et al. 2004):
nothing is searched again while the body moves.
"""
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from ..errors import SceneError

MAX_NEIGHBOURS_PAPER = 16      # [HZ] section 3.3: "the number of neighbouring nodes is limited to 16"


@dataclass(frozen=True)
class Neighbourhoods:
    nbr: np.ndarray
    dist: np.ndarray
    rbar: np.ndarray
    h: np.ndarray

    @property
    def k(self):
        return self.nbr.shape[1]


def find_neighbourhoods(X, k=MAX_NEIGHBOURS_PAPER, support_scale=2.0):
    """Neighbourhoods of the nodes X (n, 3): the k nearest (k is capped at n - 1) and
    support radii h = support_scale * (mean distance to them)."""
    X = np.ascontiguousarray(X, dtype=np.float64)
    n = len(X)
    if n < 5:
        raise SceneError(f"meshless model: {n} nodes; at least 5 are needed for a 3D gradient")
    k = int(min(k, n - 1))
    dist, idx = cKDTree(X).query(X, k=k + 1)
    # The query returns the node itself first (distance 0) unless a duplicate node ties
    # with it; drop the column holding i in each row, whatever its position.
    own = idx == np.arange(n)[:, None]
    if not np.all(own.sum(1) == 1):
        raise SceneError("meshless model: duplicate nodes (two mesh vertices at the same position)")
    keep = ~own
    nbr = idx[keep].reshape(n, k).astype(np.int64)
    dist = dist[keep].reshape(n, k)
    if np.any(dist <= 0.0):
        raise SceneError("meshless model: duplicate nodes (two mesh vertices at the same position)")
    rbar = dist.mean(axis=1)
    return Neighbourhoods(nbr=nbr, dist=dist, rbar=rbar, h=float(support_scale) * rbar)


def grow(X, nb, nodes, support_scale=2.0):
    """Neighbourhoods nb with the rows of nodes (m,) widened to the 2k nearest (capped at
    n - 1); other rows padded (module docstring)."""
    X = np.ascontiguousarray(X, dtype=np.float64)
    n, k = nb.nbr.shape
    k2 = int(min(2 * k, n - 1))
    if k2 <= k or len(nodes) == 0:
        return nb
    nodes = np.asarray(nodes, dtype=np.int64)
    dist2, idx2 = cKDTree(X).query(X[nodes], k=k2 + 1)
    own = idx2 == nodes[:, None]
    keep = ~own
    idx2, dist2 = idx2[keep].reshape(len(nodes), k2), dist2[keep].reshape(len(nodes), k2)
    nbr = np.repeat(np.arange(n, dtype=np.int64)[:, None], k2, axis=1)
    dist = np.full((n, k2), np.inf)
    nbr[:, :k], dist[:, :k] = nb.nbr, nb.dist
    nbr[nodes], dist[nodes] = idx2, dist2
    rbar = nb.rbar.copy()
    rbar[nodes] = dist2.mean(axis=1)
    return Neighbourhoods(nbr=nbr, dist=dist, rbar=rbar, h=float(support_scale) * rbar)
