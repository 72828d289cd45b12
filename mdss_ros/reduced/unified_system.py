"""The unified implicit matrix and its solve (docs/method.md §9.1-9.3, §10, §11).

    A = Mgen + dt Dgen + dt^2 Kgen,    Dgen = alpha Mgen + beta Kgen

in three parts: the dense subspace block A_ss (S, S), the subspace-to-full-space block
A_sI (S, n_cols) on the full-space columns coupled to subspace domains, and the sparse
full-space block A_ff (the data of ff_pattern). Mgen = blockdiag(I_r, m I3, I(world))
on the subspace rows, lumped masses on the full-space rows. Without full-space domains A
is solved by the block Cholesky (block_cholesky.py), by LU when it is indefinite or
unsymmetric; with them by a sparse solver over the joint system.
"""
import time

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from ..errors import SceneError
from ..linear_solver import NotPositiveDefinite


class UnifiedSystem:
    """Generalised mass, the unified matrix, its solve and the two-step foil. Mixed into
    reduced_model.ReducedModel, whose build provides the attributes it reads."""

    def _mass_blocks(self, frames, predicted_dt=None):
        """Mgen's subspace part (S, S) dense. predicted=True puts each domain's inertia at
        the rotation exp(dt w) R it will have after the step: the angular rows are in
        momentum form I(t + dt) w' = I(t) w + dt tau, which conserves angular momentum
        where an explicit gyroscopic term -w x I w gains it."""
        L = self.layout
        mv = L.movers
        M = np.zeros((self.S, self.S))
        modal = L.q_index[L.mask]
        M[modal, modal] = 1.0
        if not len(mv):
            return M
        M[L.lin_index, L.lin_index] = L.total_mass[mv, None]
        R = (L.predicted_rotations(frames.R[mv], frames.w[mv], predicted_dt) if predicted_dt
             else frames.R[mv])
        M[L.ang_index[:, :, None], L.ang_index[:, None, :]] = R @ L.inertia(self.q)[mv] @ R.transpose(0, 2, 1)
        return M

    def _system(self, M_ss, K_ss, K_sI, K_ff, D, dt):
        """A = Mgen + dt Dgen + dt^2 K as (dense A_ss, dense A_sI, sparse-data A_ff)."""
        A_ss = M_ss + dt * D[0] + dt * dt * K_ss
        A_sI = dt * D[1] + dt * dt * K_sI if self.F else None
        A_ff = self.M_ff + dt * D[2] + dt * dt * K_ff if self.F else None
        return A_ss, A_sI, A_ff

    def _solve(self, A_ss, A_sI, A_ff, rhs):
        t0 = time.perf_counter()
        if self.F == 0 and self.unsymmetric:
            lu = sla.lu_factor(A_ss, check_finite=False)
            self._resolve = lambda b: sla.lu_solve(lu, b, check_finite=False)
            t1 = time.perf_counter()
            x = sla.lu_solve(lu, rhs, check_finite=False)
        elif self.F == 0:
            try:
                self.block_solver.factor(A_ss)
                self._resolve = self.block_solver.solve
            except NotPositiveDefinite:
                # Large compression (or a centrifugal stiffness) can make A indefinite; LU
                # still gives the Newton step of the linearised system. Its result is checked
                # by the Simulator's stability guard (mdss_ros/guard.py), which rolls the step
                # back and retries with more Newton iterations and smaller dt (A = M + dt^2 K
                # is positive definite for small enough dt) if it diverges, and counts the
                # accepted indefinite steps (stats "guard_indefinite_steps").
                lu = sla.lu_factor(A_ss, check_finite=False)
                self._resolve = lambda b: sla.lu_solve(lu, b, check_finite=False)
                self._indefinite = True
            t1 = time.perf_counter()
            x = self._resolve(rhs)
        else:
            cols = self.iface_full_cols
            B = sp.csr_matrix((np.ravel(A_sI), (np.repeat(np.arange(self.S), len(cols)), np.tile(cols, self.S))),
                              shape=(self.S, self.F))
            A = sp.bmat([[sp.csr_matrix(A_ss), B], [B.T, self.ff_pattern.matrix(A_ff)]], format="csr")
            try:
                self.sparse_solver.factor(A)
                self._resolve = self.sparse_solver.solve
            except NotPositiveDefinite:
                lu = spla.splu(A.tocsc())
                self._resolve = lu.solve
                self._indefinite = True
            t1 = time.perf_counter()
            x = self._resolve(rhs)
        t2 = time.perf_counter()
        self.timing["factor_ms"] = self.timing.get("factor_ms", 0.0) + 1e3 * (t1 - t0)
        self.timing["solve_ms"] = self.timing.get("solve_ms", 0.0) + 1e3 * (t2 - t1)
        return x

    def _matvec(self, A_ss, A_sI, A_ff, Q):
        out = np.zeros_like(Q)
        out[:self.S] = A_ss @ Q[:self.S]
        if self.F:
            cols = self.iface_full_cols
            out[:self.S] += A_sI @ Q[self.S:][cols]
            out[self.S:] = self.ff_pattern.matrix(A_ff) @ Q[self.S:]
            np.add.at(out[self.S:], cols, A_sI.T @ Q[:self.S]) if len(cols) else None
        return out

    def system_matrix(self):
        """The unified matrix A (n_gen, n_gen) at the current state, dense (diagnostics, tests)."""
        G, K_ss, K_sI, K_ff, _, _, _ = self._evaluate(self.q, self.frames, self.x_full)
        M_ss = self._mass_blocks(self.frames, predicted_dt=self.dt)
        D = (self.alpha * M_ss + self.beta * K_ss, self.beta * K_sI if self.F else None,
             self.alpha * self.M_ff + self.beta * K_ff if self.F else None)
        A_ss, A_sI, A_ff = self._system(M_ss, K_ss, K_sI, K_ff, D, self.dt)
        if not self.F:
            return A_ss
        A = np.zeros((self.n_gen, self.n_gen))
        A[:self.S, :self.S] = A_ss
        A[:self.S, self.S + self.iface_full_cols] = A_sI
        A[self.S + self.iface_full_cols, :self.S] = A_sI.T
        A[self.S:, self.S:] = self.ff_pattern.matrix(A_ff).toarray()
        return A

    def _potential(self, Q, p0, Mgen, D, Fn, elastic, dt):
        """Incremental potential whose gradient is the residual: 1/2 Q.Mgen Q - p0.Q
        + dt/2 Q.D Q + E(s(Q)) - dt Fn.Q."""
        return (0.5 * Q @ self._matvec(*Mgen, Q) - p0 @ Q + 0.5 * dt * Q @ self._matvec(*D, Q)
                + elastic - dt * Fn @ Q)

    def _two_step(self, M_ss, K_ss, D, p0, G, Fn, dt):
        """The paper's foil: rigid DOFs with deformation frozen, then deformation with
        frames frozen: block Gauss-Seidel on the one-step system."""
        if self.F:
            raise SceneError("the two-step scheme is available for subspace domains only")
        A = M_ss + dt * D[0] + dt * dt * K_ss
        b = p0 + dt * (Fn - G)
        Qn = np.linalg.solve(M_ss, p0)         # the step-start velocities the paper freezes
        rigid = np.zeros(self.S, dtype=bool)
        rigid[self.layout.lin_index] = True
        rigid[self.layout.ang_index] = True
        Q = Qn.copy()
        rr, dd = np.flatnonzero(rigid), np.flatnonzero(~rigid)
        if rr.size:
            Q[rr] = sla.solve(A[np.ix_(rr, rr)], b[rr] - A[np.ix_(rr, dd)] @ Qn[dd], assume_a="pos")
        Q[dd] = sla.solve(A[np.ix_(dd, dd)], b[dd] - A[np.ix_(dd, rr)] @ Q[rr], assume_a="pos")
        return Q
