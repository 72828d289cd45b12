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
from .material_kernels import WORK_LEN, material_point_ws
# numba's cache=True keys a cached kernel on its own file only: the kernels here inline
# material_point_ws, so a change to material_kernels.py must come with an edit of this file
# (or a cleared NUMBA_CACHE_DIR). Last material change: StVK's and corotated's scratch views made only
# where used (session 20), same bits as before.


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
        work = np.empty(WORK_LEN)
        for e in range(c * chunk, min(m, (c + 1) * chunk)):
            for i in range(3):
                for j in range(3):
                    s = 0.0
                    for a in range(4):
                        s += x[tets[e, a], i] * grads[e, a, j]
                    F[i, j] = s
            psi = material_point_ws(kind_id, F, params, P, C, want_hessian, project, work)
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
