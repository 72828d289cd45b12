"""What the stability guard reads from a reduced state, in one compiled pass per quantity.

Per subspace domain d (layout.py for the stacked arrays; omega = R^T w in the domain frame):

    kinetic  = 1/2 |qd|^2                                            (mass-orthonormal basis)
             + 1/2 M |v|^2 + 1/2 omega^T I(q) omega + omega . (q^T W qd)   (movable domains)
    gravity  = -(M c + R (sum m r + (sum m U) q)) . g
    speed   <= |v| + |w| (rho + sigma |q|) + sigma |qd|             (movable; else sigma |qd|)

with I(q) = I0 + (tr L + tr B2(q, q)) 1 - L - B2(q, q), L = B1(q) + B1(q)^T, as in
layout.DomainLayout.inertia. The guard measures after every step, so these are small numba
loops: the numpy expressions they replace cost a fixed ~50 us a step, a quarter of a
12-DOF model's step.
"""
import numpy as np
from numba import njit


def measure_pack(layout):
    """The layout's constants frame_measure reads, in one float64 array (P,): per domain
    movable (1.0 / 0.0), total_mass, rho, sigma, then inertia0 (D, 3, 3), mass_r (D, 3),
    mass_moment (D, 3, r_max), B1 (D, r_max, 3, 3), B2 (D, r_max, r_max, 3, 3),
    W (D, r_max, r_max, 3), each flattened in C order (frame_measure indexes them in place).
    One array instead of ten: a numba call unboxes every argument, and the guard measures
    after every step (18 arguments took 1.3-1.8 us a call on a 12-DOF model)."""
    L = layout
    parts = (L.movable.astype(np.float64), L.total_mass, L.rho, L.sigma, L.inertia0, L.mass_r,
             L.mass_moment, L.B1, L.B2, L.W)
    return np.concatenate([np.ascontiguousarray(a, dtype=np.float64).ravel() for a in parts])


@njit(cache=True)
def frame_measure(q, qd, c, R, v, w, P, g):
    """(all finite 1.0 / 0.0, kinetic, gravity potential, speed bound) as a tuple of floats.

    q, qd (D, r_max); c, v, w (D, 3); R (D, 3, 3); P (measure_pack(layout)) the layout's
    movable, total_mass, rho, sigma (D,), inertia0 (D, 3, 3), mass_r (D, 3),
    mass_moment (D, 3, r_max), B1 (D, r_max, 3, 3), B2 (D, r_max, r_max, 3, 3),
    W (D, r_max, r_max, 3); g (3,). A tuple, not an out array: no allocation and no
    tolist() on the caller's side.

    P is read in place at the offsets below, not through ten reshaped views of it: making
    the views was about 0.4 of the call's 1.1 us on a 12-DOF model (the guard measures
    after every step). The work array (L, B (3, 3) and omega in the domain frame) is
    allocated only when a domain moves, and the sums run in the order they always did.
    """
    D, r = q.shape
    # Offsets of P's blocks (measure_pack's order); movable, total_mass, rho, sigma at d,
    # D + d, 2 D + d, 3 D + d.
    o_inertia0 = 4 * D
    o_mass_r = o_inertia0 + 9 * D
    o_moment = o_mass_r + 3 * D
    o_B1 = o_moment + 3 * D * r
    o_B2 = o_B1 + 9 * D * r
    o_W = o_B2 + 9 * D * r * r
    finite = True
    kinetic = 0.0
    grav = 0.0
    speed = 0.0
    moves = False
    for d in range(D):
        if P[d] != 0.0:
            moves = True
    # L (3, 3) at 0, B (3, 3) at 9, omega at 18, C order.
    work = np.empty(21 if moves else 0)
    for d in range(D):
        qq = 0.0
        qdqd = 0.0
        for a in range(r):
            qq += q[d, a] * q[d, a]
            qdqd += qd[d, a] * qd[d, a]
        vv = v[d, 0] * v[d, 0] + v[d, 1] * v[d, 1] + v[d, 2] * v[d, 2]
        ww = w[d, 0] * w[d, 0] + w[d, 1] * w[d, 1] + w[d, 2] * w[d, 2]
        s = qq + qdqd + vv + ww
        for i in range(3):
            s += c[d, i]
            for j in range(3):
                s += R[d, i, j]
        if not np.isfinite(s):
            finite = False
            continue
        kinetic += 0.5 * qdqd
        mass = P[D + d]
        sigma = P[3 * D + d]
        if P[d] != 0.0:
            for i in range(3):
                work[18 + i] = R[d, 0, i] * w[d, 0] + R[d, 1, i] * w[d, 1] + R[d, 2, i] * w[d, 2]
            for k in range(18):
                work[k] = 0.0
            for a in range(r):
                qa = q[d, a]
                if qa == 0.0:
                    continue
                b1 = o_B1 + 9 * (d * r + a)                   # B1[d, a]
                for k in range(9):
                    work[k] += qa * P[b1 + k]
                for b in range(r):
                    qab = qa * q[d, b]
                    b2 = o_B2 + 9 * ((d * r + a) * r + b)     # B2[d, a, b]
                    for k in range(9):
                        work[9 + k] += qab * P[b2 + k]
            tr = 2.0 * (work[0] + work[4] + work[8]) + work[9] + work[13] + work[17]
            rot = 0.0
            for i in range(3):
                acc = 0.0
                for j in range(3):
                    inert = P[o_inertia0 + 9 * d + 3 * i + j] - work[3 * i + j] - work[3 * j + i] - work[9 + 3 * i + j]
                    if i == j:
                        inert += tr
                    acc += inert * work[18 + j]
                rot += work[18 + i] * acc
            cor = 0.0
            for a in range(r):
                for b in range(r):
                    qaqdb = q[d, a] * qd[d, b]
                    if qaqdb != 0.0:
                        ow = o_W + 3 * ((d * r + a) * r + b)      # W[d, a, b]
                        cor += qaqdb * (P[ow] * work[18] + P[ow + 1] * work[19] + P[ow + 2] * work[20])
            kinetic += 0.5 * mass * vv + 0.5 * rot + cor
            sp = np.sqrt(vv) + np.sqrt(ww) * (P[2 * D + d] + sigma * np.sqrt(qq)) + sigma * np.sqrt(qdqd)
        else:
            sp = sigma * np.sqrt(qdqd)
        if sp > speed:
            speed = sp
        # p = mass_r[d] + mass_moment[d] q[d], each component summed over the modes in order.
        p0 = P[o_mass_r + 3 * d]
        p1 = P[o_mass_r + 3 * d + 1]
        p2 = P[o_mass_r + 3 * d + 2]
        mm = o_moment + 3 * r * d
        for a in range(r):
            p0 += P[mm + a] * q[d, a]
        for a in range(r):
            p1 += P[mm + r + a] * q[d, a]
        for a in range(r):
            p2 += P[mm + 2 * r + a] * q[d, a]
        for i in range(3):
            moment = mass * c[d, i] + R[d, i, 0] * p0 + R[d, i, 1] * p1 + R[d, i, 2] * p2
            grav -= moment * g[i]
    return (1.0 if finite else 0.0), kinetic, grav, speed


@njit(cache=True)
def inverted_samples(G, q, valid):
    """Cubature samples whose F = I + unvec(G_s q) has det F <= 0 (NaN counts).
    G (D, s, 9, r_max); q (D, r_max); valid (D, s) bool (padding excluded)."""
    D, s_count, _, r = G.shape
    n = 0
    F = np.empty(9)
    for d in range(D):
        for s in range(s_count):
            if not valid[d, s]:
                continue
            for a in range(9):
                acc = 1.0 if a % 4 == 0 else 0.0
                for b in range(r):
                    acc += G[d, s, a, b] * q[d, b]
                F[a] = acc
            det = (F[0] * (F[4] * F[8] - F[5] * F[7]) - F[1] * (F[3] * F[8] - F[5] * F[6])
                   + F[2] * (F[3] * F[7] - F[4] * F[6]))
            if not det > 0.0:
                n += 1
    return n


@njit(cache=True)
def count_not_positive(det, valid):
    """How many entries of det (D, s) are not > 0 (NaN counts) where valid (D, s) is set."""
    n = 0
    for d in range(det.shape[0]):
        for s in range(det.shape[1]):
            if valid[d, s] and not det[d, s] > 0.0:
                n += 1
    return n
