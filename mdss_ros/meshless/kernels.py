"""Compiled per-node pass of the meshless model (docs/method.md §19.3): energy, stencil
forces and stencil stiffness of every node in one numba kernel.

It computes what forces.py's numpy reference computes (stvk_volume, stencil_stiffness and
the fit-residual stabilisation), node by node, so no (n, 9, 9) Hessians, (n, 27, w)
temporaries or einsum passes are made. Measured on the cantilever scene (1,025 nodes,
w = 17): the numpy tangent took 26 ms of a 68 ms step; test_meshless.py checks the two
agree to round-off.

    x (n_nodes, 3) positions; stencil (n, w); c (n, w, 3); V (n,); S (n, w, w) or (0, w, w)
    energy_out (n,); force_out (n, w, 3); stiff_out (n, 3w, 3w), rows 3a + p (untouched
    unless want_hessian)
"""
import numpy as np
from numba import njit, prange

from ..threads import pick, serial_twin

_CHUNK = 64


@njit(cache=True)
def _node_law(F, mu, lam, kv, kb, jb, P, H, want_hessian):
    """psi of the meshless law at F (3, 3); fills P (3, 3) and, if want_hessian, H (9, 9)
    with H[3p + J, 3q + L] = d2psi / dF_pJ dF_qL (forces.py's stvk_volume). kb, jb: the
    compression barrier kb/(3 jb) (jb - J)^3 for J < jb (kb = 0: none)."""
    C = F.T @ F
    E = 0.5 * (C - np.eye(3))
    tr = E[0, 0] + E[1, 1] + E[2, 2]
    S = 2.0 * mu * E
    for k in range(3):
        S[k, k] += lam * tr
    cof = np.empty((3, 3))
    cof[0, 0] = F[1, 1] * F[2, 2] - F[1, 2] * F[2, 1]
    cof[0, 1] = F[1, 2] * F[2, 0] - F[1, 0] * F[2, 2]
    cof[0, 2] = F[1, 0] * F[2, 1] - F[1, 1] * F[2, 0]
    cof[1, 0] = F[0, 2] * F[2, 1] - F[0, 1] * F[2, 2]
    cof[1, 1] = F[0, 0] * F[2, 2] - F[0, 2] * F[2, 0]
    cof[1, 2] = F[0, 1] * F[2, 0] - F[0, 0] * F[2, 1]
    cof[2, 0] = F[0, 1] * F[1, 2] - F[0, 2] * F[1, 1]
    cof[2, 1] = F[0, 2] * F[1, 0] - F[0, 0] * F[1, 2]
    cof[2, 2] = F[0, 0] * F[1, 1] - F[0, 1] * F[1, 0]
    J = F[0, 0] * cof[0, 0] + F[0, 1] * cof[0, 1] + F[0, 2] * cof[0, 2]
    ee = 0.0
    for a in range(3):
        for b in range(3):
            ee += E[a, b] * E[a, b]
    psi = mu * ee + 0.5 * lam * tr * tr + 0.5 * kv * (J - 1.0) ** 2
    # The volume terms are a function U(J) of J alone: g = U'(J), hJ = U''(J).
    g = kv * (J - 1.0)
    hJ = kv
    if kb > 0.0 and J < jb:
        d = jb - J
        psi += kb * d * d * d / (3.0 * jb)
        g -= kb * d * d / jb
        hJ += 2.0 * kb * d / jb
    FS = F @ S
    for a in range(3):
        for b in range(3):
            P[a, b] = FS[a, b] + g * cof[a, b]
    if not want_hessian:
        return psi
    FFt = F @ F.T
    for p in range(3):
        for J_ in range(3):
            for q in range(3):
                for L in range(3):
                    h = lam * F[p, J_] * F[q, L] + mu * F[p, L] * F[q, J_] + hJ * cof[p, J_] * cof[q, L]
                    if p == q:
                        h += S[L, J_]
                    if J_ == L:
                        h += mu * FFt[p, q]
                    H[3 * p + J_, 3 * q + L] = h
    # U'(J) eps_pqm eps_JLN F_mN: the second derivative of det F, nonzero for p != q, J != L.
    for p in range(3):
        for q in range(3):
            if p == q:
                continue
            m = 3 - p - q
            spq = 1.0 if (q - p) % 3 == 1 else -1.0
            for J_ in range(3):
                for L in range(3):
                    if J_ == L:
                        continue
                    N = 3 - J_ - L
                    sJL = 1.0 if (L - J_) % 3 == 1 else -1.0
                    H[3 * p + J_, 3 * q + L] += g * spq * sJL * F[m, N]
    return psi


@njit(cache=True)
def _project_psd(H):
    """H (9, 9) symmetric, in place: negative eigenvalues set to 0 (as forces.psd_project)."""
    Hs = 0.5 * (H + H.T)
    lam, Q = np.linalg.eigh(Hs)
    top = np.abs(lam).max()
    if lam[0] >= -1e-13 * top:
        H[:, :] = Hs
        return
    for k in range(9):
        if lam[k] < 0.0:
            lam[k] = 0.0
    H[:, :] = (Q * lam) @ Q.T


@njit(cache=True, parallel=True)
def node_kernel(x, stencil, c, V, mu, lam, kv, kb, jb, S, want_hessian, project, energy_out, force_out,
                stiff_out):
    """Energy, stencil forces and stencil stiffness of every node (module docstring).
    S with zero rows means no stabilisation."""
    n, w = stencil.shape
    stab = S.shape[0] == n
    n_chunks = (n + _CHUNK - 1) // _CHUNK
    for ch in prange(n_chunks):
        F = np.empty((3, 3))
        P = np.empty((3, 3))
        H = np.empty((9, 9))
        T = np.empty((9, w, 3))
        xs = np.empty((w, 3))
        for i in range(ch * _CHUNK, min(n, (ch + 1) * _CHUNK)):
            for a in range(w):
                for p in range(3):
                    xs[a, p] = x[stencil[i, a], p]
            for p in range(3):
                for J_ in range(3):
                    s = 0.0
                    for a in range(w):
                        s += xs[a, p] * c[i, a, J_]
                    F[p, J_] = s
            psi = _node_law(F, mu, lam, kv, kb, jb, P, H, want_hessian)
            Vi = V[i]
            e = Vi * psi
            for a in range(w):
                for p in range(3):
                    s = 0.0
                    for J_ in range(3):
                        s += P[p, J_] * c[i, a, J_]
                    force_out[i, a, p] = Vi * s
            if stab:
                for a in range(w):
                    for p in range(3):
                        s = 0.0
                        for b in range(w):
                            s += S[i, a, b] * xs[b, p]
                        force_out[i, a, p] += s
                        e += 0.5 * s * xs[a, p]
            energy_out[i] = e
            if not want_hessian:
                continue
            if project:
                _project_psd(H)
            # T[3p + J, b, q] = sum_L H[3p + J, 3q + L] c_b[L]; then contract J with c_a.
            for r in range(9):
                for b in range(w):
                    for q in range(3):
                        T[r, b, q] = (H[r, 3 * q] * c[i, b, 0] + H[r, 3 * q + 1] * c[i, b, 1]
                                      + H[r, 3 * q + 2] * c[i, b, 2])
            for a in range(w):
                for p in range(3):
                    for b in range(w):
                        for q in range(3):
                            s = (c[i, a, 0] * T[3 * p, b, q] + c[i, a, 1] * T[3 * p + 1, b, q]
                                 + c[i, a, 2] * T[3 * p + 2, b, q])
                            stiff_out[i, 3 * a + p, 3 * b + q] = Vi * s
            if stab:
                for a in range(w):
                    for b in range(w):
                        for p in range(3):
                            stiff_out[i, 3 * a + p, 3 * b + p] += S[i, a, b]


node_kernel_serial = serial_twin(node_kernel)


def node_pass(x, stencil, c, V, mu, lam, kv, S, want_hessian=False, project=False, stiff_out=None, kb=0.0, jb=0.2):
    """(energy (n,), forces (n, w, 3), stiffness (n, 3w, 3w) or None) of every node."""
    n, w = stencil.shape
    energy = np.empty(n)
    force = np.empty((n, w, 3))
    if want_hessian:
        stiff = stiff_out if stiff_out is not None else np.empty((n, 3 * w, 3 * w))
    else:
        stiff = np.empty((0, 3 * w, 3 * w))
    S_arr = S if S is not None else np.empty((0, w, w))
    kernel = pick(node_kernel, node_kernel_serial, n, weight=8 * w)
    kernel(np.ascontiguousarray(x, dtype=np.float64), stencil, c, V, float(mu), float(lam), float(kv), float(kb),
           float(jb), S_arr,
           bool(want_hessian), bool(project), energy, force, stiff)
    return energy, force, (stiff if want_hessian else None)
