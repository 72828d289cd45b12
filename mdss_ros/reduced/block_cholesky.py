"""Block Cholesky of the unified system, one dense block per domain (paper, Appendix B).

A is symmetric positive definite with a block (i, j) != 0 only when i == j or domains i
and j share coupling elements. Eliminating domains in an order that follows the domain
graph (leaves of a tree first, minimum degree otherwise) creates little or no fill;
`factor_nonzeros` reports the stored entries of L for comparison with a generic order.

    A = L L^T,  L_kk = chol(A_kk - sum_{j<k} L_kj L_kj^T),
    L_ik = (A_ik - sum_{j<k} L_ij L_kj^T) L_kk^-T        (positions in elimination order)
"""
import numpy as np
import scipy.linalg as sla

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


class BlockCholesky:
    """Factor/solve a dense (S, S) matrix whose block structure follows a domain graph.

    sizes (d,) block sizes (in DOF order: block i occupies offsets[i]:offsets[i]+sizes[i]);
    edges (n_e, 2) coupled block pairs; order: elimination order (permutation of d).
    """

    def __init__(self, sizes, edges, order):
        self.sizes = np.asarray(sizes, dtype=np.int64)
        self.offsets = np.concatenate([[0], np.cumsum(self.sizes)])
        self.order = np.asarray(order, dtype=np.int64)
        self.later, self.fill = symbolic_elimination(len(sizes), edges, self.order)
        self.L = {}

    def _sl(self, i):
        return slice(self.offsets[i], self.offsets[i + 1])

    @property
    def factor_nonzeros(self):
        """Stored entries of L: lower triangles of the diagonal blocks plus off-diagonal blocks."""
        s = self.sizes
        nnz = int((s * (s + 1) // 2).sum())
        for k in range(len(s)):
            nnz += int(sum(s[j] * s[k] for j in self.later[k]))
        return nnz

    def factor(self, A):
        blocks = {}
        for k in self.order:
            blocks[(k, k)] = A[self._sl(k), self._sl(k)].copy()
            for j in self.later[k]:
                blocks[(j, k)] = A[self._sl(j), self._sl(k)].copy()
        L = {}
        for k in self.order:
            try:
                Lkk = np.linalg.cholesky(blocks[(k, k)])
            except np.linalg.LinAlgError as err:
                raise NotPositiveDefinite(f"diagonal block of domain {k} is not positive definite") from err
            L[(k, k)] = Lkk
            for j in self.later[k]:
                L[(j, k)] = sla.solve_triangular(Lkk, blocks[(j, k)].T, lower=True, check_finite=False).T
            rest = self.later[k]
            for a, i in enumerate(rest):
                for j in rest[: a + 1]:
                    # rest is in elimination order, so j comes no later than i: block (i, j).
                    blocks[(i, j)] = blocks.get((i, j), 0.0) - L[(i, k)] @ L[(j, k)].T
        self.L = L
        return self

    def solve(self, b):
        b = np.asarray(b, dtype=np.float64)
        y = b.copy()
        for k in self.order:          # forward: L y = b
            y[self._sl(k)] = sla.solve_triangular(self.L[(k, k)], y[self._sl(k)], lower=True, check_finite=False)
            for j in self.later[k]:
                y[self._sl(j)] -= self.L[(j, k)] @ y[self._sl(k)]
        x = y
        for k in self.order[::-1]:    # backward: L^T x = y
            for j in self.later[k]:
                x[self._sl(k)] -= self.L[(j, k)].T @ x[self._sl(j)]
            x[self._sl(k)] = sla.solve_triangular(self.L[(k, k)], x[self._sl(k)], lower=True, trans="T",
                                                  check_finite=False)
        return x
