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
    W (D, r_max, r_max, 3), each flattened in C order (_unpack reads them back as views).
    One array instead of ten: a numba call unboxes every argument, and the guard measures
    after every step (18 arguments took 1.3-1.8 us a call on a 12-DOF model)."""
    L = layout
    parts = (L.movable.astype(np.float64), L.total_mass, L.rho, L.sigma, L.inertia0, L.mass_r,
             L.mass_moment, L.B1, L.B2, L.W)
    return np.concatenate([np.ascontiguousarray(a, dtype=np.float64).ravel() for a in parts])


@njit(cache=True)
def _unpack(P, D, r):
    """measure_pack's arrays as views of P (the same values, so the same arithmetic)."""
    o = 4 * D
    inertia0 = P[o:o + 9 * D].reshape((D, 3, 3))
    o += 9 * D
    mass_r = P[o:o + 3 * D].reshape((D, 3))
    o += 3 * D
    mass_moment = P[o:o + 3 * D * r].reshape((D, 3, r))
    o += 3 * D * r
    B1 = P[o:o + 9 * D * r].reshape((D, r, 3, 3))
    o += 9 * D * r
    B2 = P[o:o + 9 * D * r * r].reshape((D, r, r, 3, 3))
    o += 9 * D * r * r
    W = P[o:o + 3 * D * r * r].reshape((D, r, r, 3))
    return P[:D], P[D:2 * D], P[2 * D:3 * D], P[3 * D:4 * D], inertia0, mass_r, mass_moment, B1, B2, W


@njit(cache=True)
def frame_measure(q, qd, c, R, v, w, P, g):
    """(all finite 1.0 / 0.0, kinetic, gravity potential, speed bound) as a tuple of floats.

    q, qd (D, r_max); c, v, w (D, 3); R (D, 3, 3); P (measure_pack(layout)) the layout's
    movable, total_mass, rho, sigma (D,), inertia0 (D, 3, 3), mass_r (D, 3),
    mass_moment (D, 3, r_max), B1 (D, r_max, 3, 3), B2 (D, r_max, r_max, 3, 3),
    W (D, r_max, r_max, 3); g (3,). A tuple, not an out array: no allocation and no
    tolist() on the caller's side.
    """
    D, r = q.shape
    movable, total_mass, rho, sigma, inertia0, mass_r, mass_moment, B1, B2, W = _unpack(P, D, r)
    finite = True
    kinetic = 0.0
    grav = 0.0
    speed = 0.0
    # One scratch allocation for the four small work arrays (each np.empty is a heap
    # allocation in compiled code too).
    scratch = np.empty(24)
    wl = scratch[0:3]
    L = scratch[3:12].reshape((3, 3))
    B = scratch[12:21].reshape((3, 3))
    p = scratch[21:24]
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
        if movable[d] != 0.0:
            for i in range(3):
                wl[i] = R[d, 0, i] * w[d, 0] + R[d, 1, i] * w[d, 1] + R[d, 2, i] * w[d, 2]
            for i in range(3):
                for j in range(3):
                    L[i, j] = 0.0
                    B[i, j] = 0.0
            for a in range(r):
                qa = q[d, a]
                if qa == 0.0:
                    continue
                for i in range(3):
                    for j in range(3):
                        L[i, j] += qa * B1[d, a, i, j]
                for b in range(r):
                    qab = qa * q[d, b]
                    for i in range(3):
                        for j in range(3):
                            B[i, j] += qab * B2[d, a, b, i, j]
            tr = 2.0 * (L[0, 0] + L[1, 1] + L[2, 2]) + B[0, 0] + B[1, 1] + B[2, 2]
            rot = 0.0
            for i in range(3):
                acc = 0.0
                for j in range(3):
                    inert = inertia0[d, i, j] - L[i, j] - L[j, i] - B[i, j]
                    if i == j:
                        inert += tr
                    acc += inert * wl[j]
                rot += wl[i] * acc
            cor = 0.0
            for a in range(r):
                for b in range(r):
                    qaqdb = q[d, a] * qd[d, b]
                    if qaqdb != 0.0:
                        cor += qaqdb * (W[d, a, b, 0] * wl[0] + W[d, a, b, 1] * wl[1] + W[d, a, b, 2] * wl[2])
            kinetic += 0.5 * total_mass[d] * vv + 0.5 * rot + cor
            sp = np.sqrt(vv) + np.sqrt(ww) * (rho[d] + sigma[d] * np.sqrt(qq)) + sigma[d] * np.sqrt(qdqd)
        else:
            sp = sigma[d] * np.sqrt(qdqd)
        if sp > speed:
            speed = sp
        for i in range(3):
            acc = mass_r[d, i]
            for a in range(r):
                acc += mass_moment[d, i, a] * q[d, a]
            p[i] = acc
        for i in range(3):
            moment = total_mass[d] * c[d, i] + R[d, i, 0] * p[0] + R[d, i, 1] * p[1] + R[d, i, 2] * p[2]
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
