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
def permute_lower(A, perm, po, later_ptr, later_idx, out):
    """out[i, j] = A[perm[i], perm[j]] on the blocks the factor reads and writes: the lower
    triangle of each diagonal block p (rows po[p]:po[p + 1] in elimination order) and the
    blocks (q, p) of its later neighbours q (later_idx[later_ptr[p]:later_ptr[p + 1]],
    fill included). Every other entry of out is never read or written by factor_blocks or
    the sweeps, and stays as it was (zero). perm keeps each domain's rows together
    (BlockCholesky.perm), so a block's columns are read as one run. A 2-D fancy-index copy
    of the whole matrix took 40 % of the factor's time; the whole lower triangle 58-85 us
    on octopus (S = 442, 17 domains, its blocks 17 % of the triangle), these blocks 20-28
    (min of 2,000; session 22)."""
    for p in range(po.shape[0] - 1):
        a0, a1 = po[p], po[p + 1]
        c0 = perm[a0]                   # a block's columns are one contiguous run of A's
        for i in range(a0, a1):
            pi = perm[i]
            for j in range(i + 1 - a0):
                out[i, a0 + j] = A[pi, c0 + j]
        for t in range(later_ptr[p], later_ptr[p + 1]):
            q = later_idx[t]
            for i in range(po[q], po[q + 1]):
                pi = perm[i]
                for j in range(a1 - a0):
                    out[i, a0 + j] = A[pi, c0 + j]


@njit(cache=True)
def _column_below(A, j, a0, i0, i1, d):
    """A[i, j] = (A[i, j] - sum_{m = a0}^{j - 1} A[i, m] A[j, m]) / d for rows i0 <= i < i1.

    Four rows at a time, each with its own running sum in the order m = a0, a0 + 1, ...:
    one row at a time, each sum was a chain of dependent multiply-adds (numba keeps the
    order of a float sum, so it cannot split one), which left the factor waiting on their
    latency. Four chains side by side give the same bits about three times as fast."""
    i = i0
    while i + 4 <= i1:
        s0, s1, s2, s3 = A[i, j], A[i + 1, j], A[i + 2, j], A[i + 3, j]
        for m in range(a0, j):
            ajm = A[j, m]
            s0 -= A[i, m] * ajm
            s1 -= A[i + 1, m] * ajm
            s2 -= A[i + 2, m] * ajm
            s3 -= A[i + 3, m] * ajm
        A[i, j], A[i + 1, j], A[i + 2, j], A[i + 3, j] = s0 / d, s1 / d, s2 / d, s3 / d
        i += 4
    for i in range(i, i1):
        acc = A[i, j]
        for m in range(a0, j):
            acc -= A[i, m] * A[j, m]
        A[i, j] = acc / d


@njit(cache=True)
def _row_update(A, i, j0, j1, a0, a1):
    """A[i, j] -= sum_{m = a0}^{a1 - 1} A[i, m] A[j, m] for j0 <= j < j1, four columns at
    a time with a running sum each (see _column_below)."""
    j = j0
    while j + 4 <= j1:
        s0 = s1 = s2 = s3 = 0.0
        for m in range(a0, a1):
            aim = A[i, m]
            s0 += aim * A[j, m]
            s1 += aim * A[j + 1, m]
            s2 += aim * A[j + 2, m]
            s3 += aim * A[j + 3, m]
        A[i, j] -= s0
        A[i, j + 1] -= s1
        A[i, j + 2] -= s2
        A[i, j + 3] -= s3
        j += 4
    for j in range(j, j1):
        acc = 0.0
        for m in range(a0, a1):
            acc += A[i, m] * A[j, m]
        A[i, j] -= acc


@njit(cache=True)
def factor_blocks(A, po, later_ptr, later_idx):
    """In-place block Cholesky of A (S, S), already permuted to elimination order: block p
    spans rows po[p]:po[p + 1]; later_idx[later_ptr[p]:later_ptr[p + 1]] are the blocks
    after p that L couples to it (ascending). Only the lower triangle of those blocks is
    read and written. Returns -1, or the first block whose diagonal is not positive definite.

    Right-looking over blocks, left-looking inside a block: after block p is factored its
    outer products update the blocks of its later neighbours only, so the work follows
    the domain graph (no pass over zero blocks). Every entry is the same sum, in the same
    order, as an entry-by-entry loop; the helpers only run several of them side by side."""
    n_blocks = len(po) - 1
    for p in range(n_blocks):
        a0, a1 = po[p], po[p + 1]
        for j in range(a0, a1):                        # L_pp = chol(A_pp), column by column
            d = A[j, j]
            for m in range(a0, j):
                d -= A[j, m] * A[j, m]
            if not d > 0.0:
                return p
            d = np.sqrt(d)
            A[j, j] = d
            _column_below(A, j, a0, j + 1, a1, d)
        for t in range(later_ptr[p], later_ptr[p + 1]):  # L_qp = A_qp L_pp^-T, column by column
            q = later_idx[t]
            for j in range(a0, a1):
                _column_below(A, j, a0, po[q], po[q + 1], A[j, j])
        for ta in range(later_ptr[p], later_ptr[p + 1]):  # A_ab -= L_ap L_bp^T, b <= a
            qa = later_idx[ta]
            for tb in range(later_ptr[p], ta + 1):
                qb = later_idx[tb]
                for i in range(po[qa], po[qa + 1]):
                    _row_update(A, i, po[qb], i + 1 if qa == qb else po[qb + 1], a0, a1)
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
        permute_lower(np.ascontiguousarray(A), self.perm, self.po, self.later_ptr, self.later_idx, L)
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
