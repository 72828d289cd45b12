"""Linear tetrahedral elements: rest geometry and the per-element force kernel.

Symbols: n_verts vertices, n_tets elements. A tet (a0, a1, a2, a3) is positively
oriented: det Dm > 0 with Dm = [X1-X0, X2-X0, X3-X0].

Sign convention (docs/method.md §1): f_int = dE/dx, the gradient of the elastic
energy, i.e. minus the force the element exerts; K = d f_int / dx.

With shape-function gradients g_a = dN_a/dX (g_{k+1} = row k of Dm^-1,
g_0 = -(g_1 + g_2 + g_3)):
    F      = sum_a x_a g_a^T
    f_a    = V P g_a
    K_ab   = V sum_jl dP/dF[(i,j),(k,l)] g_a[j] g_b[l]      (3x3 block, rows i, cols k)
"""
from dataclasses import dataclass

import numpy as np
from numba import njit, prange

from ..threads import pick, serial_twin
from .material_kernels import KIND_NEOHOOKEAN, WORK_LEN, barrier_terms, material_point_ws, snh_parameters
# numba's cache=True keys a cached kernel on its own file only: the kernels here inline
# material_point_ws, so a change to material_kernels.py must come with an edit of this file
# (or a cleared NUMBA_CACHE_DIR). Last material change: StVK's and corotated's scratch views made only
# where used (session 20), same bits as before. neohookean_stiffness below writes out the
# neo-Hookean and barrier tangent of material_kernels.py again, contracted: a change to
# either must be made there too (test_fem_assembly.py compares the two).


@dataclass(frozen=True)
class TetGeometry:
    """Rest geometry of all elements.

    volume: (n_tets,) rest volumes, > 0.
    grads:  (n_tets, 4, 3) shape-function gradients g_a = dN_a/dX.
    """

    volume: np.ndarray
    grads: np.ndarray

    def subset(self, ids):
        """The geometry of elements ids (k,) only, in that order."""
        return TetGeometry(volume=self.volume[ids], grads=np.ascontiguousarray(self.grads[ids]))


def tet_geometry(X, tets):
    """Rest volumes and shape-function gradients.

    X: (n_verts, 3) rest positions; tets: (n_tets, 4) positively oriented.
    """
    X = np.asarray(X, dtype=np.float64)
    tets = np.asarray(tets, dtype=np.int64)
    Dm = np.stack([X[tets[:, k]] - X[tets[:, 0]] for k in (1, 2, 3)], axis=2)  # columns are edges
    det = np.linalg.det(Dm)
    if np.any(det <= 0):
        bad = np.flatnonzero(det <= 0)
        raise ValueError(f"{bad.size} tets are degenerate or negatively oriented (first: {bad[:5].tolist()})")
    Dm_inv = np.linalg.inv(Dm)
    grads = np.empty((len(tets), 4, 3))
    grads[:, 1:, :] = Dm_inv
    grads[:, 0, :] = -Dm_inv.sum(axis=1)
    return TetGeometry(volume=det / 6.0, grads=np.ascontiguousarray(grads))


def deformation_gradients(x, tets, grads):
    """F per element: (n_tets, 3, 3) from positions x (n_verts, 3)."""
    return np.einsum("tai,taj->tij", x[tets], grads)


_CHUNK = 256


@njit(cache=True, parallel=True)
def element_kernel(x, tets, grads, volume, kind_id, params, want_hessian, project,
                   energy_out, force_out, stiff_out):
    """Energy, internal forces and stiffness of every element in one pass.

    x (n_verts, 3); tets (n_tets, 4); grads (n_tets, 4, 3); volume (n_tets,)
    energy_out (n_tets,); force_out (n_tets, 4, 3); stiff_out (n_tets, 12, 12) (untouched
    unless want_hessian). Row/column 3*a + i of stiff_out is vertex a, axis i.
    Work arrays are allocated once per chunk of elements, not per element.
    """
    m = tets.shape[0]
    # Small sets (coupling elements: a few thousand) in smaller chunks, so both threads
    # get a balanced share; large meshes keep the long chunks.
    chunk = _CHUNK if m > 64 * _CHUNK else _CHUNK // 4
    n_chunks = (m + chunk - 1) // chunk
    for c in prange(n_chunks):
        F = np.empty((3, 3))
        P = np.empty((3, 3))
        C = np.empty((9, 9))
        T = np.empty((9, 4, 3))
        UW = np.empty((2, 4, 3))
        work = np.empty(WORK_LEN)
        closed = want_hessian and not project and kind_id == KIND_NEOHOOKEAN
        for e in range(c * chunk, min(m, (c + 1) * chunk)):
            for i in range(3):
                for j in range(3):
                    s = 0.0
                    for a in range(4):
                        s += x[tets[e, a], i] * grads[e, a, j]
                    F[i, j] = s
            psi = material_point_ws(kind_id, F, params, P, C, want_hessian and not closed, project, work)
            V = volume[e]
            energy_out[e] = V * psi
            for a in range(4):
                for i in range(3):
                    s = 0.0
                    for j in range(3):
                        s += P[i, j] * grads[e, a, j]
                    force_out[e, a, i] = V * s
            if not want_hessian:
                continue
            if closed:
                neohookean_stiffness(F, grads, e, V, params, UW, stiff_out)
                continue
            # T[(i,j), b, k] = sum_l C[(i,j),(k,l)] g_b[l], then contract j with g_a.
            for r in range(9):
                for b in range(4):
                    for k in range(3):
                        T[r, b, k] = (C[r, 3 * k] * grads[e, b, 0] + C[r, 3 * k + 1] * grads[e, b, 1]
                                      + C[r, 3 * k + 2] * grads[e, b, 2])
            for a in range(4):
                for i in range(3):
                    row = 3 * a + i
                    g0, g1, g2 = grads[e, a, 0], grads[e, a, 1], grads[e, a, 2]
                    for b in range(4):
                        for k in range(3):
                            stiff_out[e, row, 3 * b + k] = V * (T[3 * i, b, k] * g0 + T[3 * i + 1, b, k] * g1
                                                                + T[3 * i + 2, b, k] * g2)


element_kernel_serial = serial_twin(element_kernel)


@njit(cache=True, inline="always")
def neohookean_stiffness(F, grads, e, V, params, UW, stiff_out):
    """stiff_out[e] (12, 12): the stable neo-Hookean element stiffness in closed form.

    F (3, 3) the element's deformation gradient, grads (n_tets, 4, 3), V its rest volume,
    params as material_point's (mu, lam, _, barrier k, barrier j); UW (2, 4, 3) scratch.
    With dP/dF = c2 f f^T + lam' a a^T + kap I + lj d cof(F)/dF (material_kernels,
    neohookean_point_ws: f = vec F, a = vec cof F; the compression barrier adds b to lam'
    and its slope to lj), the contraction with the gradients is, per vertex pair,

        K_ab = V [c2 u_a u_b^T + lam' w_a w_b^T + kap (g_a . g_b) I3 + lj [h_ab]],
        u_a = F g_a,   w_a = cof(F) g_a,   h_ab = F (g_a x g_b),   [h]_ik = eps_ikn h_n,

    and K_ba = K_ab^T, so only the ten blocks b >= a are formed. Why: the general
    contraction of dP/dF (9, 9) with the gradients is 756 multiply-adds an element after
    the 9 x 9 dP/dF itself; this is about 600 flops in all. The coupling elements of
    armadillo_class (2,587 tets) took 2.04 ms with their stiffness on one thread that
    way (docs/performance.md, "Session 28")."""
    mup, lamp, alpha, _ = snh_parameters(params[0], params[1])
    F00, F01, F02 = F[0, 0], F[0, 1], F[0, 2]
    F10, F11, F12 = F[1, 0], F[1, 1], F[1, 2]
    F20, F21, F22 = F[2, 0], F[2, 1], F[2, 2]
    # cof F: its rows are cross products of the rows of F (as neohookean_point_ws).
    A00, A01, A02 = F11 * F22 - F12 * F21, F12 * F20 - F10 * F22, F10 * F21 - F11 * F20
    A10, A11, A12 = F21 * F02 - F22 * F01, F22 * F00 - F20 * F02, F20 * F01 - F21 * F00
    A20, A21, A22 = F01 * F12 - F02 * F11, F02 * F10 - F00 * F12, F00 * F11 - F01 * F10
    J = F00 * A00 + F01 * A01 + F02 * A02
    Ic = (F00 * F00 + F01 * F01 + F02 * F02 + F10 * F10 + F11 * F11 + F12 * F12
          + F20 * F20 + F21 * F21 + F22 * F22)
    q = 1.0 / (Ic + 1.0)
    kap = V * mup * (1.0 - q)
    c2 = V * 2.0 * mup * q * q
    la = lamp
    lj = lamp * (J - alpha)
    if params[3] > 0.0 and J < params[4]:
        _, slope, curvature = barrier_terms(J, params[3], params[4])
        la += curvature
        lj += slope
    la *= V
    lj *= V
    for a in range(4):
        g0, g1, g2 = grads[e, a, 0], grads[e, a, 1], grads[e, a, 2]
        UW[0, a, 0] = F00 * g0 + F01 * g1 + F02 * g2
        UW[0, a, 1] = F10 * g0 + F11 * g1 + F12 * g2
        UW[0, a, 2] = F20 * g0 + F21 * g1 + F22 * g2
        UW[1, a, 0] = A00 * g0 + A01 * g1 + A02 * g2
        UW[1, a, 1] = A10 * g0 + A11 * g1 + A12 * g2
        UW[1, a, 2] = A20 * g0 + A21 * g1 + A22 * g2
    for a in range(4):
        a0, a1, a2 = grads[e, a, 0], grads[e, a, 1], grads[e, a, 2]
        for b in range(a, 4):
            b0, b1, b2 = grads[e, b, 0], grads[e, b, 1], grads[e, b, 2]
            d = kap * (a0 * b0 + a1 * b1 + a2 * b2)
            x0, x1, x2 = a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0
            h0 = lj * (F00 * x0 + F01 * x1 + F02 * x2)
            h1 = lj * (F10 * x0 + F11 * x1 + F12 * x2)
            h2 = lj * (F20 * x0 + F21 * x1 + F22 * x2)
            for i in range(3):
                ua = c2 * UW[0, a, i]
                wa = la * UW[1, a, i]
                for k in range(3):
                    v = ua * UW[0, b, k] + wa * UW[1, b, k]
                    if i == k:
                        v += d
                    elif k == i + 1 or k == i - 2:          # eps_ikn = +1 for n = the third axis
                        v += h2 if i == 0 else (h0 if i == 1 else h1)
                    else:
                        v -= h2 if k == 0 else (h0 if k == 1 else h1)
                    stiff_out[e, 3 * a + i, 3 * b + k] = v
                    if b != a:
                        stiff_out[e, 3 * b + k, 3 * a + i] = v


def element_forces(x, tets, geom, material, want_hessian=True, project=False, out=None):
    """Evaluate every element.

    Returns energy (n_tets,), forces (n_tets, 4, 3) and, if want_hessian,
    stiffness (n_tets, 12, 12) (else None). out: an ElementBuffers to write into
    (the stiffness array of a large mesh is hundreds of MB; reusing it saves the
    page faults of a fresh allocation every step).
    """
    m = len(tets)
    buf = out if out is not None else ElementBuffers(m, want_hessian)
    stiff = buf.stiffness if want_hessian else np.empty((1, 12, 12))
    pick(element_kernel, element_kernel_serial, m, weight=4)(
        np.ascontiguousarray(x, dtype=np.float64), tets, geom.grads, geom.volume, material.kind_id,
        material.params, want_hessian, project, buf.energy, buf.forces, stiff)
    return buf.energy, buf.forces, (stiff if want_hessian else None)


class ElementBuffers:
    """Output arrays of element_forces for n_tets elements; stiffness made on first need."""

    def __init__(self, n_tets, want_hessian=True):
        self.energy = np.empty(n_tets)
        self.forces = np.empty((n_tets, 4, 3))
        self._stiffness = np.empty((n_tets, 12, 12)) if want_hessian else None

    @property
    def stiffness(self):
        if self._stiffness is None:
            self._stiffness = np.empty((len(self.energy), 12, 12))
        return self._stiffness
