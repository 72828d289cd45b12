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


def positions(layout, ids, q, frames, x_full):
    """World positions (len(ids), 3) of global vertex ids at state (q, frames, x_full)."""
    ids = np.ascontiguousarray(ids, dtype=np.int64)
    out = np.empty((len(ids), 3))
    pick(positions_kernel, positions_kernel_serial, len(ids))(layout.vertex_row[ids], ids, layout.U, layout.r_local, layout.row_domain,
                     np.ascontiguousarray(q), np.ascontiguousarray(frames.R), np.ascontiguousarray(frames.c),
                     np.ascontiguousarray(x_full), out)
    return out


def velocities(layout, x, qd, frames, v_full):
    """World velocities (n_verts, 3) of every vertex, x (n_verts, 3) their positions."""
    out = v_full.copy()
    rows = layout.vertex_row
    sub = np.flatnonzero(rows >= 0)
    k = layout.row_domain[rows[sub]]
    local = np.einsum("lia,la->li", layout.U[rows[sub]], qd[k])
    d = x[sub] - frames.c[k]
    w, v = frames.w[k], frames.v[k]
    out[sub] = v + cross(w, d) + np.einsum("lij,lj->li", frames.R[k], local)
    return out


@njit(cache=True)
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
