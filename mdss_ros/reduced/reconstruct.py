"""World positions and velocities of vertices from the reduced state (docs/method.md §7):

    subspace vertex l of domain k:  x_l = c_k + R_k (r_l + U_l q_k)
                                    xd_l = v_k + w_k x (x_l - c_k) + R_k U_l qd_k
    full-space vertex:              x_l, xd_l are state (x_full, v_full)

One compiled pass over the requested vertices, parallel and without allocation per
vertex; the per-vertex data come stacked from layout.DomainLayout (U, r_local, rows).
"""
import numpy as np
from numba import njit, prange

from ..rotations import cross
from ..threads import pick, serial_twin


@njit(cache=True, parallel=True)
def positions_kernel(rows, ids, U, r_local, row_domain, q, R, c, x_full, out):
    """out[i] = world position of vertex ids[i]; rows[i] its stacked row (-1: full-space).

    rows, ids (m,); U (n_sub, 3, r_max); r_local (n_sub, 3); row_domain (n_sub,);
    q (D, r_max); R (D, 3, 3); c (D, 3); x_full (n_verts, 3); out (m, 3) written.
    """
    r_max = U.shape[2]
    for i in prange(rows.shape[0]):
        row = rows[i]
        if row < 0:
            out[i, 0] = x_full[ids[i], 0]
            out[i, 1] = x_full[ids[i], 1]
            out[i, 2] = x_full[ids[i], 2]
            continue
        k = row_domain[row]
        p0 = 0.0
        p1 = 0.0
        p2 = 0.0
        for t in range(r_max):
            qt = q[k, t]
            p0 += U[row, 0, t] * qt
            p1 += U[row, 1, t] * qt
            p2 += U[row, 2, t] * qt
        p0 += r_local[row, 0]
        p1 += r_local[row, 1]
        p2 += r_local[row, 2]
        for a in range(3):
            out[i, a] = c[k, a] + R[k, a, 0] * p0 + R[k, a, 1] * p1 + R[k, a, 2] * p2


positions_kernel_serial = serial_twin(positions_kernel)


_LOAD_CHUNK = 256


@njit(cache=True, parallel=True)
def loads_kernel(rows, forces, U, r_local, row_domain, q, R, c, modal, force, torque):
    """The transpose of reconstruction: point loads f_l on subspace vertices as the
    generalised forces of their domains (docs/method.md §13),

        modal[k] += U_l^T R_k^T f_l,   force[k] += f_l,   torque[k] += (x_l - c_k) x f_l,

    with x_l - c_k = R_k (r_l + U_l q_k). rows (m,) stacked rows of the loaded vertices
    (-1: full-space, skipped); forces (m, 3); U, r_local, row_domain, q, R, c as in
    positions_kernel; modal (D, r_max), force, torque (D, 3) are added to.

    Parallel over fixed chunks of _LOAD_CHUNK loads, each summing into its own partial
    arrays, which are then added chunk after chunk: the sums do not depend on the thread
    count (armadillo_class's two loaded handles: 0.2 ms a step on one thread)."""
    m = rows.shape[0]
    D, r_max = modal.shape
    n_chunks = (m + _LOAD_CHUNK - 1) // _LOAD_CHUNK
    pm = np.zeros((n_chunks, D, r_max))
    pf = np.zeros((n_chunks, D, 3))
    pt = np.zeros((n_chunks, D, 3))
    for ch in prange(n_chunks):
        for i in range(ch * _LOAD_CHUNK, min(m, (ch + 1) * _LOAD_CHUNK)):
            row = rows[i]
            if row < 0:
                continue
            k = row_domain[row]
            f0 = forces[i, 0]
            f1 = forces[i, 1]
            f2 = forces[i, 2]
            l0 = R[k, 0, 0] * f0 + R[k, 1, 0] * f1 + R[k, 2, 0] * f2        # R^T f
            l1 = R[k, 0, 1] * f0 + R[k, 1, 1] * f1 + R[k, 2, 1] * f2
            l2 = R[k, 0, 2] * f0 + R[k, 1, 2] * f1 + R[k, 2, 2] * f2
            p0 = r_local[row, 0]
            p1 = r_local[row, 1]
            p2 = r_local[row, 2]
            for t in range(r_max):
                pm[ch, k, t] += U[row, 0, t] * l0 + U[row, 1, t] * l1 + U[row, 2, t] * l2
                qt = q[k, t]
                p0 += U[row, 0, t] * qt
                p1 += U[row, 1, t] * qt
                p2 += U[row, 2, t] * qt
            d0 = R[k, 0, 0] * p0 + R[k, 0, 1] * p1 + R[k, 0, 2] * p2
            d1 = R[k, 1, 0] * p0 + R[k, 1, 1] * p1 + R[k, 1, 2] * p2
            d2 = R[k, 2, 0] * p0 + R[k, 2, 1] * p1 + R[k, 2, 2] * p2
            pf[ch, k, 0] += f0
            pf[ch, k, 1] += f1
            pf[ch, k, 2] += f2
            pt[ch, k, 0] += d1 * f2 - d2 * f1
            pt[ch, k, 1] += d2 * f0 - d0 * f2
            pt[ch, k, 2] += d0 * f1 - d1 * f0
    for ch in range(n_chunks):
        for k in range(D):
            for t in range(r_max):
                modal[k, t] += pm[ch, k, t]
            for a in range(3):
                force[k, a] += pf[ch, k, a]
                torque[k, a] += pt[ch, k, a]


loads_kernel_serial = serial_twin(loads_kernel)


def positions(layout, ids, q, frames, x_full):
    """World positions (len(ids), 3) of global vertex ids at state (q, frames, x_full)."""
    ids = np.ascontiguousarray(ids, dtype=np.int64)
    return _positions(layout.vertex_row[ids], ids, layout.U, layout.r_local, layout.row_domain, q, frames, x_full)


def _positions(rows, ids, U, r_local, row_domain, q, frames, x_full):
    out = np.empty((len(ids), 3))
    pick(positions_kernel, positions_kernel_serial, len(ids))(
        rows, ids, U, r_local, row_domain, np.ascontiguousarray(q), np.ascontiguousarray(frames.R),
        np.ascontiguousarray(frames.c), np.ascontiguousarray(x_full), out)
    return out


class VertexSet:
    """A vertex set read every step (the surface), with its basis rows copied out of the
    layout into contiguous arrays in the set's order.

    Gathering the rows from the layout's (n_sub, 3, r_max) stack reads them scattered
    among the interior vertices. On armadillo_class (19,147 of 60,266 vertices in the
    surface) the surface pass took 1.06 ms that way right after a step, and 0.36 ms from
    the contiguous copy (session 13, /tmp script, median of 100 steps); the copy costs
    len(ids) x 3 x r_max doubles (9.2 MB there). positions() gives the same numbers as
    reconstruct.positions: the same kernel, the same sums.
    """

    def __init__(self, layout, ids):
        self.ids = np.ascontiguousarray(ids, dtype=np.int64)
        rows = layout.vertex_row[self.ids]
        sub = rows >= 0
        self.rows = np.where(sub, np.cumsum(sub) - 1, -1).astype(np.int64)    # -1: full-space
        self.U = np.ascontiguousarray(layout.U[rows[sub]])
        self.r_local = np.ascontiguousarray(layout.r_local[rows[sub]])
        self.row_domain = np.ascontiguousarray(layout.row_domain[rows[sub]])

    def positions(self, q, frames, x_full):
        """World positions (len(ids), 3) at state (q, frames, x_full)."""
        return _positions(self.rows, self.ids, self.U, self.r_local, self.row_domain, q, frames, x_full)


def velocities(layout, x, qd, frames, v_full):
    """World velocities (n_verts, 3) of every vertex, x (n_verts, 3) their positions."""
    return velocities_of(layout, np.arange(len(v_full)), x, qd, frames, v_full)


def velocities_of(layout, ids, x, qd, frames, v_full):
    """World velocities (len(ids), 3) of global vertex ids at positions x (len(ids), 3):
    v + w x (x - c) + R U qd on subspace rows, v_full's rows on full-space ones."""
    out = v_full[ids]
    rows = layout.vertex_row[ids]
    sub = np.flatnonzero(rows >= 0)
    k = layout.row_domain[rows[sub]]
    local = np.einsum("lia,la->li", layout.U[rows[sub]], qd[k])
    d = x[sub] - frames.c[k]
    w, v = frames.w[k], frames.v[k]
    out[sub] = v + cross(w, d) + np.einsum("lij,lj->li", frames.R[k], local)
    return out
