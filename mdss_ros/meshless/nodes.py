"""Meshless node sets other than the mesh's vertices (docs/method.md §19.9).

[HZ] §2.1 distributes the nodes regularly "in the case of a simulation domain with a
regular geometric shape", and takes a tetrahedralisation's vertices otherwise; the second
is the default (`model.meshless.nodes: mesh`). `nodes: lattice` is the first, for any
closed body surface:

    lattice_nodes   a cubic lattice of edge h over the surface's bounding box, centred on
                    it; the points inside deeper than SNAP_BAND h are nodes; the points
                    within SNAP_BAND h of the surface (inside or out) move to their closest
                    surface point, unless that lands closer than MIN_GAP h to a node already
                    kept. On a box whose edges are multiples of h this is the lattice itself,
                    faces, edges and corners included.
    lattice_volumes the nodes' Voronoi cells inside the body, sampled on a lattice
                    VOLUME_SAMPLES times finer, scaled to the body mesh's volume (so
                    sum m_i = rho V_mesh, as with mesh nodes).

The signed distance is mesh/distance.py's (libigl: exact point-to-triangle distance, sign by
the generalised winding number, right for any closed surface), as for the mesh colliders.
"""
import numpy as np
from scipy.spatial import cKDTree

from ..errors import SceneError
from ..mesh.distance import signed_distance

SNAP_BAND = 0.5          # lattice points within this many h of the surface move onto it
MIN_GAP = 0.35           # a moved point closer than this many h to a kept node is dropped
VOLUME_SAMPLES = 4       # volume sampling lattice: h / VOLUME_SAMPLES
VOLUME_FLOOR = 0.05      # smallest nodal volume, in h^3 (then all are rescaled to the body's)
MAX_NODES = 2_000_000


def _lattice(lo, hi, h):
    """(p, 3) points of the cubic lattice of edge h covering [lo - h, hi + h], centred on the
    box (a box whose edges are multiples of h has lattice points on its faces)."""
    n = np.floor((hi - lo) / h + 1e-9).astype(np.int64)
    start = lo + 0.5 * ((hi - lo) - n * h) - h
    count = n + 3
    if int(np.prod(count)) > MAX_NODES * 4:
        raise SceneError(f"model.meshless.spacing: {h:g} m gives about {int(np.prod(count)):,} lattice points over "
                         f"the body's bounding box; raise the spacing")
    axes = [start[k] + h * np.arange(count[k]) for k in range(3)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)


def lattice_nodes(vertices, triangles, spacing):
    """Nodes X (n, 3) on the cubic lattice of edge `spacing` clipped to the closed surface
    (vertices (v, 3), outward triangles (t, 3)): see the module docstring."""
    h = float(spacing)
    V = np.asarray(vertices, dtype=np.float64)
    P = _lattice(V.min(axis=0), V.max(axis=0), h)
    s, closest = signed_distance(P, V, triangles)
    inner = P[s < -SNAP_BAND * h]
    near = closest[np.abs(s) <= SNAP_BAND * h]
    # Moved points: drop those that land near an inner node, then thin the rest among
    # themselves (of each close pair the later one goes; a gap of at most 2 MIN_GAP h can
    # open where three crowd, which the neighbourhoods span).
    if len(inner) and len(near):
        d, _ = cKDTree(inner).query(near, k=1)
        near = near[d >= MIN_GAP * h]
    if len(near) > 1:
        pairs = cKDTree(near).query_pairs(MIN_GAP * h, output_type="ndarray")
        if len(pairs):
            near = np.delete(near, np.unique(pairs.max(axis=1)), axis=0)
    X = np.concatenate([inner, near])
    if len(X) < 5:
        raise SceneError(f"model.meshless.spacing: {h:g} m leaves {len(X)} lattice nodes in the body; at least 5 "
                         f"are needed (a smaller spacing, at most the body's thinnest part / 2)")
    if len(X) > MAX_NODES:
        raise SceneError(f"model.meshless.spacing: {h:g} m gives {len(X):,} nodes (more than {MAX_NODES:,}); "
                         f"raise the spacing")
    return X


def lattice_volumes(X, vertices, triangles, spacing, body_volume):
    """Nodal volumes V (n,) of nodes X (n, 3) in the closed surface: each node's share of
    sample points (a lattice of edge spacing / VOLUME_SAMPLES inside the surface) by nearest
    node (the centres of the sample cells), floored at VOLUME_FLOOR h^3, then scaled so that
    sum V = body_volume."""
    h = float(spacing)
    V = np.asarray(vertices, dtype=np.float64)
    hs = h / VOLUME_SAMPLES
    # Sample cell centres: off the surface and off the Voronoi faces of the nodes' lattice
    # (points on either would be shared by a tie, decided arbitrarily).
    S = _lattice(V.min(axis=0), V.max(axis=0), hs) + 0.5 * hs
    s, _ = signed_distance(S, V, triangles)
    S = S[s < 0.0]
    _, owner = cKDTree(X).query(S, k=1)
    vol = np.bincount(owner, minlength=len(X)) * hs ** 3
    vol = np.maximum(vol, VOLUME_FLOOR * h ** 3)
    return vol * (float(body_volume) / vol.sum())


def surface_quadrature(vertices, triangles, spacing):
    """(points (q, 3), area vectors (q, 3)) of a midpoint rule on the surface fine enough for
    nodes `spacing` apart: each triangle (vertices (v, 3), outward triangles (t, 3)) split
    into m^2 similar sub-triangles, m = ceil(longest edge / (spacing / 2)), each giving its
    centroid and its share of the triangle's area vector. The integration constraint's
    boundary vectors are then sum_q phi_j(p_q) a_q (a surface coarser than the lattice would
    otherwise hand all its area to the nodes at its vertices)."""
    V = np.asarray(vertices, dtype=np.float64)
    T = np.asarray(triangles, dtype=np.int64)
    a, b, c = V[T[:, 0]], V[T[:, 1]], V[T[:, 2]]
    area = 0.5 * np.cross(b - a, c - a)
    longest = np.max([np.linalg.norm(b - a, axis=1), np.linalg.norm(c - b, axis=1),
                      np.linalg.norm(a - c, axis=1)], axis=0)
    m = np.maximum(1, np.ceil(longest / (0.5 * float(spacing)))).astype(np.int64)
    points, areas = [], []
    for mm in np.unique(m):                    # a few refinement levels, each vectorised
        sel = np.flatnonzero(m == mm)
        i, j = np.meshgrid(np.arange(mm), np.arange(mm), indexing="ij")
        up = (i + j < mm)                     # upright sub-triangles: centroids at (i + 1/3, j + 1/3)
        down = (i + j < mm - 1)               # inverted ones: (i + 2/3, j + 2/3)
        bary = np.concatenate([np.stack([i[up] + 1 / 3, j[up] + 1 / 3], 1),
                               np.stack([i[down] + 2 / 3, j[down] + 2 / 3], 1)]) / mm     # (mm^2, 2)
        pts = (a[sel, None] + bary[None, :, :1] * (b - a)[sel, None] + bary[None, :, 1:] * (c - a)[sel, None])
        points.append(pts.reshape(-1, 3))
        areas.append(np.repeat(area[sel] / (mm * mm), mm * mm, axis=0))
    return np.concatenate(points), np.concatenate(areas)
