"""Block Cholesky of the unified system, one dense block per domain (paper, Appendix B).

A is symmetric positive definite with a block (i, j) != 0 only when i == j or domains i
and j share coupling elements. Eliminating domains in an order that follows the domain
graph (leaves of a tree first, minimum degree otherwise) creates little or no fill;
`factor_nonzeros` reports the stored entries of L for comparison with a generic order.

    A = L L^T,  L_kk = chol(A_kk - sum_{j<k} L_kj L_kj^T),
    L_ik = (A_ik - sum_{j<k} L_ij L_kj^T) L_kk^-T        (positions in elimination order)
"""
import numpy as np
from numba import njit

from ..linear_solver import NotPositiveDefinite


def symbolic_elimination(n_blocks, edges, order):
    """Later-neighbour lists after elimination in `order`, and the fill edges created.

    edges (n_e, 2) block pairs; order (n_blocks,) a permutation.
    Returns (later, fill) with later[k] = blocks eliminated after k that L couples to k.
    """
    nbrs = [set() for _ in range(n_blocks)]
    for i, j in np.asarray(edges, dtype=np.int64).reshape(-1, 2):
        if i != j:
            nbrs[i].add(int(j))
            nbrs[j].add(int(i))
    pos = np.empty(n_blocks, dtype=np.int64)
    pos[np.asarray(order)] = np.arange(n_blocks)
    later = [None] * n_blocks
    fill = []
    for k in order:
        rest = sorted((j for j in nbrs[k] if pos[j] > pos[k]), key=lambda j: pos[j])
        later[k] = rest
        for a in range(len(rest)):
            for b in range(a + 1, len(rest)):
                i, j = rest[a], rest[b]
                if j not in nbrs[i]:
                    nbrs[i].add(j)
                    nbrs[j].add(i)
                    fill.append((i, j))
    return later, fill


@njit(cache=True)
def permute_lower(A, perm, out):
    """out[i, j] = A[perm[i], perm[j]] for j <= i (the triangle the factor reads): a 2-D
    fancy-index copy of the whole matrix took 40 % of the factor's time."""
    n = perm.shape[0]
    for i in range(n):
        pi = perm[i]
        for j in range(i + 1):
            out[i, j] = A[pi, perm[j]]


@njit(cache=True)
def factor_blocks(A, po, later_ptr, later_idx):
    """In-place block Cholesky of A (S, S), already permuted to elimination order: block p
    spans rows po[p]:po[p + 1]; later_idx[later_ptr[p]:later_ptr[p + 1]] are the blocks
    after p that L couples to it (ascending). Only the lower triangle of those blocks is
    read and written. Returns -1, or the first block whose diagonal is not positive definite.

    Right-looking over blocks, left-looking inside a block: after block p is factored its
    outer products update the blocks of its later neighbours only, so the work follows
    the domain graph (no pass over zero blocks)."""
    n_blocks = len(po) - 1
    for p in range(n_blocks):
        a0, a1 = po[p], po[p + 1]
        for j in range(a0, a1):                        # L_pp = chol(A_pp)
            d = A[j, j]
            for m in range(a0, j):
                d -= A[j, m] * A[j, m]
            if not d > 0.0:
                return p
            d = np.sqrt(d)
            A[j, j] = d
            for i in range(j + 1, a1):
                acc = A[i, j]
                for m in range(a0, j):
                    acc -= A[i, m] * A[j, m]
                A[i, j] = acc / d
        for t in range(later_ptr[p], later_ptr[p + 1]):  # L_qp = A_qp L_pp^-T
            q = later_idx[t]
            for i in range(po[q], po[q + 1]):
                for j in range(a0, a1):
                    acc = A[i, j]
                    for m in range(a0, j):
                        acc -= A[i, m] * A[j, m]
                    A[i, j] = acc / A[j, j]
        for ta in range(later_ptr[p], later_ptr[p + 1]):  # A_ab -= L_ap L_bp^T, b <= a
            qa = later_idx[ta]
            for tb in range(later_ptr[p], ta + 1):
                qb = later_idx[tb]
                for i in range(po[qa], po[qa + 1]):
                    j_end = i + 1 if qa == qb else po[qb + 1]
                    for j in range(po[qb], j_end):
                        acc = 0.0
                        for m in range(a0, a1):
                            acc += A[i, m] * A[j, m]
                        A[i, j] -= acc
    return -1


@njit(cache=True)
def forward_blocks(L, po, later_ptr, later_idx, y):
    """Solve L Z = Y in place: y (S, m) right-hand sides, permuted to elimination order;
    L from factor_blocks."""
    n_blocks = len(po) - 1
    n_rhs = y.shape[1]
    for p in range(n_blocks):
        a0, a1 = po[p], po[p + 1]
        for j in range(a0, a1):
            for m in range(a0, j):
                for c in range(n_rhs):
                    y[j, c] -= L[j, m] * y[m, c]
            for c in range(n_rhs):
                y[j, c] /= L[j, j]
        for t in range(later_ptr[p], later_ptr[p + 1]):
            q = later_idx[t]
            for i in range(po[q], po[q + 1]):
                for m in range(a0, a1):
                    for c in range(n_rhs):
                        y[i, c] -= L[i, m] * y[m, c]


@njit(cache=True)
def backward_blocks(L, po, later_ptr, later_idx, y):
    """Solve L^T X = Z in place: y (S, m), in elimination order."""
    n_blocks = len(po) - 1
    n_rhs = y.shape[1]
    for p in range(n_blocks - 1, -1, -1):
        a0, a1 = po[p], po[p + 1]
        for t in range(later_ptr[p], later_ptr[p + 1]):
            q = later_idx[t]
            for i in range(po[q], po[q + 1]):
                for m in range(a0, a1):
                    for c in range(n_rhs):
                        y[m, c] -= L[i, m] * y[i, c]
        for j in range(a1 - 1, a0 - 1, -1):
            for m in range(j + 1, a1):
                for c in range(n_rhs):
                    y[j, c] -= L[m, j] * y[m, c]
            for c in range(n_rhs):
                y[j, c] /= L[j, j]


class BlockCholesky:
    """Factor/solve a dense (S, S) matrix whose block structure follows a domain graph.

    sizes (d,) block sizes (in DOF order: block i occupies offsets[i]:offsets[i]+sizes[i]);
    edges (n_e, 2) coupled block pairs; order: elimination order (permutation of d).

    The factor runs in one compiled pass (factor_blocks) on A permuted to elimination
    order. It replaced a Python loop over blocks calling LAPACK per block: for
    armadillo_class's 11 blocks of 20-26 rows, that made 43 scipy calls a step, and their
    wrappers cost more than the ~1 MFLOP of the factor itself.
    """

    def __init__(self, sizes, edges, order):
        self.sizes = np.asarray(sizes, dtype=np.int64)
        self.offsets = np.concatenate([[0], np.cumsum(self.sizes)])
        self.order = np.asarray(order, dtype=np.int64)
        self.later, self.fill = symbolic_elimination(len(sizes), edges, self.order)
        pos = np.empty(len(self.order), dtype=np.int64)
        pos[self.order] = np.arange(len(self.order))
        self.perm = np.concatenate([np.arange(self.offsets[k], self.offsets[k + 1]) for k in self.order]
                                   ).astype(np.int64) if len(self.order) else np.zeros(0, np.int64)
        self.po = np.concatenate([[0], np.cumsum(self.sizes[self.order])]).astype(np.int64)
        counts = [len(self.later[k]) for k in self.order]
        self.later_ptr = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
        self.later_idx = np.array([pos[j] for k in self.order for j in self.later[k]], dtype=np.int64)
        self.L = None

    @property
    def factor_nonzeros(self):
        """Stored entries of L: lower triangles of the diagonal blocks plus off-diagonal blocks."""
        s = self.sizes
        nnz = int((s * (s + 1) // 2).sum())
        for k in range(len(s)):
            nnz += int(sum(s[j] * s[k] for j in self.later[k]))
        return nnz

    def factor(self, A):
        if self.L is None:
            self.L = np.zeros((len(self.perm), len(self.perm)))     # reused: only its lower triangle is read
        L = self.L
        permute_lower(np.ascontiguousarray(A), self.perm, L)
        failed = factor_blocks(L, self.po, self.later_ptr, self.later_idx)
        if failed >= 0:
            raise NotPositiveDefinite(f"diagonal block of domain {self.order[failed]} is not positive definite")
        self.L = L
        return self

    def solve(self, b):
        """x (S,) or (S, m) with A x = b."""
        b = np.asarray(b, dtype=np.float64)
        return self.backward(self.forward(b.reshape(len(b), -1)), overwrite=True).reshape(b.shape)

    def forward(self, b):
        """Z = L^-1 P b (S, m) for b (S, m): half a solve, in elimination order. With it
        b1^T A^-1 b2 = Z1^T Z2 (A = P^T L L^T P), which the contact solvers use to form
        C A^-1 C^T from one sweep per column instead of two."""
        y = np.ascontiguousarray(np.asarray(b, dtype=np.float64)[self.perm])
        forward_blocks(self.L, self.po, self.later_ptr, self.later_idx, y)
        return y

    def backward(self, z, overwrite=False):
        """x = P^T L^-T z (S, m) for z (S, m) in elimination order: the other half
        (overwrite: z, C-contiguous float64, may be used as the work array)."""
        y = z if overwrite else np.array(z, dtype=np.float64, order="C")
        backward_blocks(self.L, self.po, self.later_ptr, self.later_idx, y)
        x = np.empty_like(y)
        x[self.perm] = y
        return x
