"""Neighbourhoods of the meshless nodes (docs/method.md §19.1).

Nodes are the body's tet-mesh vertices, X (n, 3) at rest. Each node i gets its k nearest
other nodes (scipy cKDTree, exact k-NN; ties broken by the tree) and a spherical support

    rbar_i = mean_{j in N(i)} |X_j - X_i|          (n,)   mean distance to the k nearest
    h_i    = support_scale * rbar_i                 (n,)   support radius

Arrays:
    nbr   (n, k) int64    neighbour ids, nearest first (node i itself excluded)
    dist  (n, k) float64  |X_j - X_i| at rest
    rbar  (n,)            mean neighbour distance
    h     (n,)            support radius

`grow` chooses the neighbourhoods of some nodes again (those with an ill-conditioned
moment matrix, mls.py): k neighbours balanced over the octants round the node instead of
the k nearest.

The neighbour lists are fixed at rest (total Lagrangian, like [HZ] and Mueller et al. 2004):
nothing is searched again while the body moves.
"""
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from ..errors import SceneError

PER_OCTANT = 2                 # direction-balanced regrowth (grow)
SUPPORT_OVER_FARTHEST = 1.25
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


def grow(X, nb, nodes, support_scale=2.0, round_=0):
    """Neighbourhoods nb with the rows of nodes (m,) chosen again, direction-balanced: of
    their 8k 4^round_ nearest candidates, the nearest PER_OCTANT in each octant round the
    node, then the nearest others, k in all (the row width stays k). The support radius
    follows from the new mean distance, and reaches past the farthest pick.

    Why octants: on a graded tensor-product mesh (graded_block: cells 0.02 m across one
    way and 0.15 m the other) a node's 16, 32 or 64 nearest all lie in one plane, and no
    count of nearest neighbours sees across it; two per octant always do, where the body
    has nodes on that side."""
    X = np.ascontiguousarray(X, dtype=np.float64)
    n, k = nb.nbr.shape
    nodes = np.asarray(nodes, dtype=np.int64)
    kc = int(min(8 * k * 4 ** round_, n - 1))
    if len(nodes) == 0 or kc <= k:
        return nb
    dist_c, idx_c = cKDTree(X).query(X[nodes], k=kc + 1)
    own = idx_c == nodes[:, None]
    idx_c = idx_c[~own].reshape(len(nodes), kc)
    dist_c = dist_c[~own].reshape(len(nodes), kc)
    rel = X[idx_c] - X[nodes][:, None, :]
    octant = (rel[..., 0] > 0) + 2 * (rel[..., 1] > 0) + 4 * (rel[..., 2] > 0)          # (m, kc)
    onehot = octant[..., None] == np.arange(8)
    rank = (np.cumsum(onehot, axis=1) - 1)[onehot].reshape(octant.shape)             # rank within its octant
    # Priority: octant picks first (by distance), then the rest by distance; keep k.
    key = np.where(rank < PER_OCTANT, 0, 1) * kc + np.arange(kc)
    pick = np.argsort(key, axis=1, kind="stable")[:, :k]
    pick.sort(axis=1)                                                              # nearest first again
    nbr, dist = nb.nbr.copy(), nb.dist.copy()
    nbr[nodes] = np.take_along_axis(idx_c, pick, axis=1)
    dist[nodes] = np.take_along_axis(dist_c, pick, axis=1)
    rbar = nb.rbar.copy()
    rbar[nodes] = dist[nodes].mean(axis=1)
    h = float(support_scale) * rbar
    # The octant picks may lie far beyond the mean distance: keep them inside the support
    # (weight w(0.8) = 0.1 for the farthest), or they would be chosen and weigh nothing.
    h[nodes] = np.maximum(h[nodes], SUPPORT_OVER_FARTHEST * dist[nodes].max(axis=1))
    return Neighbourhoods(nbr=nbr, dist=dist, rbar=rbar, h=h)
