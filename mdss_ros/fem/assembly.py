"""Global assembly over a precomputed sparsity pattern of the free DOFs.

DOF layout: vertex v, axis i -> dof 3*v + i before pins are removed; the pattern
maps that to a free-DOF index (or -1 for pinned DOFs, whose rows and columns are
dropped). The pattern is built once per mesh; a step only scatters element arrays
into the CSR data array, which keeps assembly free of Python loops and of
scipy's COO->CSR conversion.
"""
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from numba import njit


@dataclass(frozen=True)
class StiffnessPattern:
    """CSR pattern of K restricted to free DOFs.

    n_free: number of free DOFs.
    free_dof: (3 * n_verts,) free index of each full DOF, -1 if pinned.
    indptr: (n_free + 1,), indices: (nnz,) CSR pattern (columns sorted).
    scatter: (n_elements, (3w)^2) position in the CSR data of element entry (r, c) =
             r*3w + c (w = 4 for a tet: 144), -1 when the entry touches a pinned DOF.
    diagonal: (n_free,) position of each diagonal entry in the data array.
    """

    n_free: int
    free_dof: np.ndarray
    indptr: np.ndarray
    indices: np.ndarray
    scatter: np.ndarray
    diagonal: np.ndarray

    @property
    def nnz(self):
        return int(self.indices.size)

    def matrix(self, data):
        """Wrap a data array (nnz,) as a scipy CSR matrix sharing the pattern."""
        return sp.csr_matrix((data, self.indices, self.indptr), shape=(self.n_free, self.n_free))


def element_dofs(tets):
    """Full DOF indices of each element: (n_elements, 3w) for elements of w vertices
    (tets: w = 4, 12 DOFs), ordered vertex-major."""
    n, w = tets.shape
    return (3 * tets[:, :, None] + np.arange(3)[None, None, :]).reshape(n, 3 * w)


def stiffness_pattern(tets, n_verts, pinned=()):
    """Build the CSR pattern of the free-DOF stiffness and the element scatter map.

    tets: (n_elements, w) vertex ids of each element: tets (w = 4), or the meshless
    model's stencils (a node and its neighbours); pinned: vertex indices whose DOFs are
    removed.
    """
    tets = np.asarray(tets, dtype=np.int64)
    is_free = np.ones(3 * n_verts, dtype=bool)
    pinned = np.asarray(pinned, dtype=np.int64)
    if pinned.size:
        is_free[(3 * pinned[:, None] + np.arange(3)).ravel()] = False
    free_dof = np.full(3 * n_verts, -1, dtype=np.int64)
    free_dof[is_free] = np.arange(int(is_free.sum()))
    n_free = int(is_free.sum())

    edofs = free_dof[element_dofs(tets)]                   # (n_elements, 3w)
    m = edofs.shape[1]
    rows = np.repeat(edofs, m, axis=1)                     # entry r*m+c -> row of r
    cols = np.tile(edofs, (1, m))                          # entry r*m+c -> col of c
    valid = (rows >= 0) & (cols >= 0)
    keys = rows * n_free + cols
    # Every free DOF gets its diagonal entry, also a vertex no element references (a
    # domain vertex whose tets are all coupling elements): diagonal[] must index it.
    uniq = np.union1d(keys[valid], np.arange(n_free, dtype=np.int64) * (n_free + 1))
    indptr = np.searchsorted(uniq // n_free, np.arange(n_free + 1)).astype(np.int64)
    indices = (uniq % n_free).astype(np.int64)
    scatter = np.full(keys.shape, -1, dtype=np.int64)
    scatter[valid] = np.searchsorted(uniq, keys[valid])
    diagonal = np.searchsorted(uniq, np.arange(n_free, dtype=np.int64) * (n_free + 1))
    return StiffnessPattern(n_free, free_dof, indptr, indices, scatter, diagonal)


@njit(cache=True)
def scatter_add(values, scatter, out):
    """out[scatter[e, j]] += values[e, j] for every entry with scatter >= 0 (a pattern's
    scatter, (n, k) into out's nnz): the assembly kernel, also used for element subsets."""
    n, k = scatter.shape
    for e in range(n):
        for j in range(k):
            s = scatter[e, j]
            if s >= 0:
                out[s] += values[e, j]


def assemble_matrix(pattern, element_mats, out=None):
    """Sum element matrices (n_elements, 3w, 3w) into the pattern's data array (nnz,)."""
    if out is None:
        out = np.zeros(pattern.nnz)
    else:
        out[:] = 0.0
    scatter_add(np.ascontiguousarray(element_mats).reshape(len(element_mats), -1), pattern.scatter, out)
    return out


def assemble_vector(tets, element_vecs, n_verts):
    """Sum element vectors (n_elements, w, 3) into a per-vertex array (n_verts, 3)."""
    out = np.zeros((n_verts, 3))
    for i in range(3):
        out[:, i] = np.bincount(tets.ravel(), weights=element_vecs[:, :, i].ravel(), minlength=n_verts)
    return out
