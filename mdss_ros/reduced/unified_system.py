"""The unified implicit matrix and its solve (docs/method.md §9.1-9.3, §10, §11).

    A = Mgen + dt Dgen + dt^2 Kgen,    Dgen = alpha Mgen + beta Kgen

in three parts: the dense subspace block A_ss (S, S), the subspace-to-full-space block
A_sI (S, n_cols) on the full-space columns coupled to subspace domains, and the sparse
full-space block A_ff (the data of ff_pattern). Mgen = blockdiag(I_r, m I3, I(world))
on the subspace rows, lumped masses on the full-space rows. Without full-space domains A
is solved by the block Cholesky (block_cholesky.py), by LU when it is indefinite or
unsymmetric; with them by a sparse solver over the joint system.

Mgen is kept as its structure (SubspaceMass): a step's mass products and its share of A
cost O(S), and A_ss is formed from K in one scaled pass (StepSystem.matrix). Formed as
dense (S, S) sums, they were about ten passes over an (S, S) array a step.
"""
import time
from dataclasses import dataclass

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from numba import njit

from ..errors import SceneError
from ..linear_solver import NotPositiveDefinite
from .frames import world_inertia_kernel


@njit(cache=True)
def pattern_matrix(K, a, K0, b, blocks, offsets, out):
    """out = a K + b K0 on the blocks (k, l) of blocks (n_b, 2) (rows offsets[k]:offsets[k +
    1], columns offsets[l]:offsets[l + 1]); b = 0: K0 is not read. K, K0, out (S, S).

    The unified matrix of a subspace-only model is zero outside its domains' diagonal
    blocks and the blocks of coupled domain pairs (the block Cholesky's pattern): a
    dense pass over all of it was 110 us on octopus (S = 442), whose blocks are a sixth of
    it. Each entry is a K + b K0 as the dense form computed it (the same bits)."""
    for t in range(blocks.shape[0]):
        k, l = blocks[t, 0], blocks[t, 1]
        for i in range(offsets[k], offsets[k + 1]):
            if b != 0.0:
                for j in range(offsets[l], offsets[l + 1]):
                    out[i, j] = a * K[i, j] + b * K0[i, j]
            else:
                for j in range(offsets[l], offsets[l + 1]):
                    out[i, j] = a * K[i, j]


@njit(cache=True)
def add_mass(A, scale, modal, lin_index, mass, ang_index, inertia):
    """A += scale Mgen on the subspace rows: scale on the modal diagonal (n_modal,), scale
    m_k on each mover's linear diagonal lin_index (M, 3), scale I_k (M, 3, 3) on its
    angular block ang_index (M, 3). Each entry gets A + (scale x), as numpy's in-place
    updates computed it."""
    for i in range(modal.shape[0]):
        A[modal[i], modal[i]] += scale
    for m in range(lin_index.shape[0]):
        sm = scale * mass[m]
        for k in range(3):
            A[lin_index[m, k], lin_index[m, k]] += sm
        for i in range(3):
            for j in range(3):
                A[ang_index[m, i], ang_index[m, j]] += scale * inertia[m, i, j]


@njit(cache=True)
def mass_matvec_kernel(x, modal, lin_index, mass, ang_index, inertia, out):
    """out = Mgen x on the subspace rows: x, out (S,); modal (n_modal,), lin_index,
    ang_index (M, 3), mass (M,), inertia (M, 3, 3). Each angular row sums its three
    products in order (I_i0 x_0 + I_i1 x_1) + I_i2 x_2; numpy's einsum over the stacked
    inertia added them as (I_i0 x_0 + I_i2 x_2) + I_i1 x_1, an order the compiled step
    (linear_step.py) could only copy by accident, so both use this kernel."""
    for i in range(modal.shape[0]):
        out[modal[i]] = x[modal[i]]
    for m in range(lin_index.shape[0]):
        for k in range(3):
            out[lin_index[m, k]] = mass[m] * x[lin_index[m, k]]
        x0, x1, x2 = x[ang_index[m, 0]], x[ang_index[m, 1]], x[ang_index[m, 2]]
        for i in range(3):
            out[ang_index[m, i]] = inertia[m, i, 0] * x0 + inertia[m, i, 1] * x1 + inertia[m, i, 2] * x2


@dataclass(frozen=True)
class SubspaceMass:
    """Mgen on the S subspace rows as its structure: 1 on the modal rows (n_modal,), m_k I3
    on the movers' linear rows lin_index (M, 3), the world inertia I_k (M, 3, 3) on their
    angular rows ang_index (M, 3); mass (M,). Every subspace row is one of these."""

    S: int
    modal: np.ndarray
    lin_index: np.ndarray
    mass: np.ndarray
    ang_index: np.ndarray
    inertia: np.ndarray

    def matvec(self, x):
        """Mgen x on the subspace rows: x (S,) -> (S,)."""
        out = np.empty(len(x))
        mass_matvec_kernel(np.ascontiguousarray(x, dtype=np.float64), self.modal, self.lin_index, self.mass,
                           self.ang_index, self.inertia, out)
        return out

    def add_to(self, A, scale):
        """A (S, S) += scale Mgen, in place; returns A. One compiled pass (add_mass) in
        place of three fancy-indexed updates (39 us of own time a step under cProfile on an
        automatic star_limbs model; the same bits)."""
        add_mass(A, float(scale), self.modal, self.lin_index, self.mass, self.ang_index, self.inertia)
        return A

    def dense(self):
        """Mgen's subspace part as a dense (S, S) array."""
        return self.add_to(np.zeros((self.S, self.S)), 1.0)


class StepSystem:
    """The unified system of one step (docs/method.md §9.2, §9.3, §9.5):

        Mgen Q,   Dgen Q = alpha Mgen Q + beta K0 Q - dt K_cf Q,
        A(K) = (1 + dt alpha) Mgen + dt beta K0 + dt^2 K - dt^2 K_cf

    mass: SubspaceMass at the predicted rotations; M_ff (full-space lumped masses, ff_pattern
    data) or None; K0 = (K_ss, K_sI, K_ff) the tangent at the step start (Dgen keeps it for
    the whole step); centrifugal (D, r_max, r_max) the implicit centrifugal stiffness on the
    modal blocks, or None; matvec: the model's product with (A_ss, A_sI, A_ff) parts."""

    def __init__(self, model, mass, dt, alpha, beta, K0, centrifugal=None):
        self.model, self.mass, self.dt, self.alpha, self.beta = model, mass, dt, alpha, beta
        self.K0, self.centrifugal = K0, centrifugal
        self.F = model.F

    def mass_matvec(self, Q):
        """Mgen Q (n_gen,)."""
        m = self.model
        out = np.empty_like(Q)
        out[:m.S] = self.mass.matvec(Q[:m.S])
        if self.F:
            out[m.S:] = m.ff_pattern.matrix(m.M_ff) @ Q[m.S:]
        return out

    def damping_matvec(self, Q):
        """Dgen Q (n_gen,)."""
        out = self.alpha * self.mass_matvec(Q)
        if self.beta:
            K_ss, K_sI, K_ff = self.K0
            out += self.beta * self.model._matvec(K_ss, K_sI, K_ff, Q)
        if self.centrifugal is not None:
            L = self.model.layout
            out[L.q_index[L.mask]] -= self.dt * np.einsum("dab,db->da", self.centrifugal, L.gather(Q))[L.mask]
        return out

    def matrix(self, K_ss, K_sI, K_ff):
        """A = (A_ss dense (S, S), A_sI dense or None, A_ff sparse data or None) at tangent K."""
        dt, K0 = self.dt, self.K0
        if K_ss is K0[0]:                                     # the first iteration: one pass
            a, b = dt * dt + dt * self.beta, 0.0
        else:
            a, b = dt * dt, (dt * self.beta if self.beta else 0.0)
        if not self.F:
            # Only the domains' blocks, into the model's buffer (zero elsewhere): A of
            # one iteration is dead once the next is formed (_solve factors or copies it,
            # the line search shifts a copy).
            A_ss = self.model._pattern_buffer()
            pattern_matrix(K_ss, a, K0[0], b, self.model._A_blocks, self.model.sub_offsets, A_ss)
        elif b == 0.0:
            A_ss = a * K_ss
        else:
            A_ss = a * K_ss
            A_ss += b * K0[0]
        self.mass.add_to(A_ss, 1.0 + dt * self.alpha)
        if self.centrifugal is not None:
            L = self.model.layout
            A_ss[L.block_rows, L.block_cols] -= dt * dt * self.centrifugal[L.block_valid]
        if not self.F:
            return A_ss, None, None
        A_sI = dt * self.beta * K0[1] + dt * dt * K_sI
        A_ff = (1.0 + dt * self.alpha) * self.model.M_ff + dt * self.beta * K0[2] + dt * dt * K_ff
        return A_ss, A_sI, A_ff

    def shifted(self, A, mu):
        """(A_ss, A_sI, A_ff) of matrix() plus mu Mgen, as new arrays: the damped Newton
        matrix of step.py's line search."""
        A_ss, A_sI, A_ff = A
        A_ss = self.mass.add_to(A_ss.copy(), mu)
        if A_ff is not None:
            A_ff = A_ff + mu * self.model.M_ff
        return A_ss, A_sI, A_ff

    def damping_dense(self):
        """Dgen's subspace part (S, S) dense (the two-step foil)."""
        D = self.alpha * self.mass.dense() + self.beta * self.K0[0]
        if self.centrifugal is not None:
            L = self.model.layout
            D[L.block_rows, L.block_cols] -= self.dt * self.centrifugal[L.block_valid]
        return D

    def potential(self, Q, p0, Fn, elastic):
        """Incremental potential whose gradient is the residual: 1/2 Q.Mgen Q - p0.Q
        + dt/2 Q.Dgen Q + E(s(Q)) - dt Fn.Q."""
        dt = self.dt
        return (0.5 * Q @ self.mass_matvec(Q) - p0 @ Q + 0.5 * dt * Q @ self.damping_matvec(Q)
                + elastic - dt * Fn @ Q)


class UnifiedSystem:
    """Generalised mass, the unified matrix, its solve and the two-step foil. Mixed into
    reduced_model.ReducedModel, whose build provides the attributes it reads."""

    #: The last step's block Cholesky factor, or None (set by _solve).
    _factor = None

    #: (S, S) buffer of StepSystem.matrix without full-space domains, and its blocks
    #: (n_b, 2): each domain's and both orders of each coupled pair (_pattern_buffer).
    _A_buffer = None
    _A_blocks = None

    def _pattern_buffer(self):
        """The zeroed-once (S, S) buffer StepSystem.matrix writes the unified matrix's
        blocks into (every other entry is zero for good), and its block list."""
        if self._A_buffer is None or self._A_buffer.shape != (self.S, self.S):
            edges = self._subspace_edges()
            D = len(self.subspace)
            blocks = np.concatenate([np.repeat(np.arange(D), 2).reshape(D, 2), edges, edges[:, ::-1]])
            self._A_blocks = np.unique(blocks, axis=0).astype(np.int64)
            self._A_buffer = np.zeros((self.S, self.S))
        return self._A_buffer

    def _subspace_mass(self, frames, predicted_dt=None, inertia=None):
        """Mgen's subspace part as a SubspaceMass. predicted_dt puts each domain's inertia
        at the rotation exp(dt w) R it will have after the step: the angular rows are in
        momentum form I(t + dt) w' = I(t) w + dt tau, which conserves angular momentum
        where an explicit gyroscopic term -w x I w gains it. inertia: the body-frame
        inertia (D, 3, 3) at the state's q when the caller has it."""
        L = self.layout
        mv = L.movers
        I_world = np.empty((len(mv), 3, 3))
        if len(mv):
            # One compiled pass (frames.world_inertia_kernel): the prediction and the two
            # stacked products in numpy were 20 us a call, twice a step (session 21).
            world_inertia_kernel(frames.R, frames.w, float(predicted_dt or 0.0),
                                 L.inertia(self.q) if inertia is None else inertia, mv, I_world)
        return SubspaceMass(S=self.S, modal=L.modal_rows, lin_index=L.lin_index,
                            mass=L.total_mass[mv], ang_index=L.ang_index, inertia=I_world)

    def _mass_blocks(self, frames, predicted_dt=None):
        """Mgen's subspace part (S, S) dense (see _subspace_mass)."""
        return self._subspace_mass(frames, predicted_dt).dense()

    def _solve(self, A_ss, A_sI, A_ff, rhs):
        t0 = time.perf_counter()
        # The block Cholesky factor, when the step has one: the contact solves use its
        # half sweeps (contact_rows.CholeskySolves); any other factor answers by _resolve.
        self._factor = None
        if self.F == 0 and self.unsymmetric:
            lu = sla.lu_factor(A_ss, check_finite=False)
            self._resolve = lambda b: sla.lu_solve(lu, b, check_finite=False)
            t1 = time.perf_counter()
            x = sla.lu_solve(lu, rhs, check_finite=False)
        elif self.F == 0:
            try:
                self.block_solver.factor(A_ss)
                self._resolve = self.block_solver.solve
                self._factor = self.block_solver
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
        system = StepSystem(self, self._subspace_mass(self.frames, predicted_dt=self.dt), self.dt, self.alpha,
                            self.beta, (K_ss, K_sI, K_ff))
        A_ss, A_sI, A_ff = system.matrix(K_ss, K_sI, K_ff)
        if not self.F:
            return A_ss.copy()                 # the step's buffer (_pattern_buffer)
        A = np.zeros((self.n_gen, self.n_gen))
        A[:self.S, :self.S] = A_ss
        A[:self.S, self.S + self.iface_full_cols] = A_sI
        A[self.S + self.iface_full_cols, :self.S] = A_sI.T
        A[self.S:, self.S:] = self.ff_pattern.matrix(A_ff).toarray()
        return A

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
