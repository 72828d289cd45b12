"""External loads on vertices: handle wrenches and point forces on the surface."""
import numpy as np


class VertexLoads:
    """Loads on a few vertices of an n-vertex body, so a step touches only those:
    ids (k,) unique ascending, forces (k, 3); dense() gives the (n, 3) array."""

    __slots__ = ("ids", "forces", "n")

    def __init__(self, n, parts=()):
        """parts: iterable of (ids (h,), forces (h, 3)); repeated ids add up."""
        parts = [(np.asarray(i, dtype=np.int64).reshape(-1), np.asarray(f, dtype=np.float64).reshape(-1, 3))
                 for i, f in parts]
        self.n = int(n)
        if not parts:
            self.ids, self.forces = np.zeros(0, np.int64), np.zeros((0, 3))
            return
        if len(parts) == 1 and np.all(np.diff(parts[0][0]) > 0):     # one handle: already unique, sorted
            self.ids, self.forces = parts[0]
            return
        ids = np.concatenate([i for i, _ in parts])
        f = np.concatenate([f for _, f in parts])
        # A stable sort and one reduceat over the runs of equal ids: the same sums, in the
        # same order, as np.unique + np.add.at, which took 0.2 ms a step for two handles of
        # armadillo_class.
        order = np.argsort(ids, kind="stable")
        ids = ids[order]
        starts = np.flatnonzero(np.r_[True, ids[1:] != ids[:-1]])
        self.ids = ids[starts]
        self.forces = np.add.reduceat(f[order], starts, axis=0) if len(starts) < len(ids) else f[order]

    def dense(self):
        out = np.zeros((self.n, 3))
        out[self.ids] = self.forces
        return out

    def __add__(self, other):
        return VertexLoads(self.n, [(self.ids, self.forces), (other.ids, other.forces)])


def sparse_loads(f_ext):
    """(ids (k,), forces (k, 3)) of the loaded vertices of a VertexLoads or an (n, 3) array."""
    if isinstance(f_ext, VertexLoads):
        return f_ext.ids, f_ext.forces
    ids = np.flatnonzero(np.any(f_ext != 0.0, axis=1))
    return ids, f_ext[ids]


def wrench_to_vertex_forces(x, mass, force, torque):
    """Spread a wrench over a set of vertices by mass.

    x (h, 3) current positions, or a function giving them (called only for a torque: a
    pure force needs no positions); mass (h,); force, torque (3,) world frame, torque about
    the set's centre of mass. Returns (h, 3) forces f_a = m_a (force / m + alpha x r_a)
    with alpha = I^-1 torque, so that sum f = force and sum r x f = torque exactly.
    """
    m = mass.sum()
    f = mass[:, None] * (np.asarray(force, dtype=np.float64) / m)
    torque = np.asarray(torque, dtype=np.float64)
    if np.any(torque != 0.0):
        x = x() if callable(x) else x
        c = (mass[:, None] * x).sum(0) / m
        r = x - c
        inertia = (mass * (r * r).sum(1)).sum() * np.eye(3) - (mass[:, None, None] * r[:, :, None] * r[:, None, :]).sum(0)
        # A handle on a line (or one vertex) has a singular inertia: lstsq gives the
        # minimum-norm angular acceleration, which still reproduces the torque it can.
        alpha = np.linalg.lstsq(inertia, torque, rcond=None)[0]
        f += mass[:, None] * np.cross(alpha, r)
    return f


def closest_points_on_triangles(p, a, b, c):
    """Closest point of p (3,) to each triangle (a, b, c each (T, 3)).

    Returns squared distances (T,) and barycentric coordinates (T, 3).
    Ericson, Real-Time Collision Detection 5.1.5, vectorised over triangles.
    """
    ab, ac, ap = b - a, c - a, p - a
    d1, d2 = (ab * ap).sum(1), (ac * ap).sum(1)
    bp = p - b
    d3, d4 = (ab * bp).sum(1), (ac * bp).sum(1)
    cp = p - c
    d5, d6 = (ab * cp).sum(1), (ac * cp).sum(1)
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2
    with np.errstate(divide="ignore", invalid="ignore"):
        denom = va + vb + vc
        v = np.where(denom != 0, vb / denom, 0.0)
        w = np.where(denom != 0, vc / denom, 0.0)
        bary = np.stack([1 - v - w, v, w], axis=1)
        # Regions outside the face, in the order Ericson tests them (later ones win last).
        t_ab = np.clip(d1 / np.where(d1 - d3 != 0, d1 - d3, 1), 0, 1)
        t_ac = np.clip(d2 / np.where(d2 - d6 != 0, d2 - d6, 1), 0, 1)
        t_bc = np.clip((d4 - d3) / np.where((d4 - d3) + (d5 - d6) != 0, (d4 - d3) + (d5 - d6), 1), 0, 1)
    edge_bc = (va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0)
    bary[edge_bc] = np.stack([0 * t_bc, 1 - t_bc, t_bc], 1)[edge_bc]
    edge_ac = (vb <= 0) & (d2 >= 0) & (d6 <= 0)
    bary[edge_ac] = np.stack([1 - t_ac, 0 * t_ac, t_ac], 1)[edge_ac]
    vert_c = (d6 >= 0) & (d5 <= d6)
    bary[vert_c] = (0, 0, 1)
    edge_ab = (vc <= 0) & (d1 >= 0) & (d3 <= 0)
    bary[edge_ab] = np.stack([1 - t_ab, t_ab, 0 * t_ab], 1)[edge_ab]
    vert_b = (d3 >= 0) & (d4 <= d3)
    bary[vert_b] = (0, 1, 0)
    vert_a = (d1 <= 0) & (d2 <= 0)
    bary[vert_a] = (1, 0, 0)
    q = bary[:, :1] * a + bary[:, 1:2] * b + bary[:, 2:] * c
    return ((q - p) ** 2).sum(1), bary


def closest_surface_point(p, positions, triangles):
    """Nearest point of a triangle mesh to p (3,).

    positions (S, 3); triangles (n_tris, 3) into positions.
    Returns (triangle index, barycentric (3,), distance).
    """
    tri = positions[triangles]
    d2, bary = closest_points_on_triangles(np.asarray(p, dtype=np.float64), tri[:, 0], tri[:, 1], tri[:, 2])
    k = int(np.argmin(d2))
    return k, bary[k], float(np.sqrt(d2[k]))
