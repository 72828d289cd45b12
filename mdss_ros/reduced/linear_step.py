"""The linearly implicit step of a subspace-only body in compiled calls (docs/method.md §9).

One Newton iteration of the unified backward Euler step from Q = 0, for a body with no
full-space domain, explicit fictitious forces and the symmetric system:

    p0 = Mgen(t) Qn,   Fn = F_app + F_grav + F_fict(q, qd, R, w, w_prev)
    r  = dt (G - Fn) - p0
    A  = (1 + dt alpha) Mgen(t + dt) + (dt^2 + dt beta) K            (pattern blocks only)
    dQ = -A^-1 r                                                     (block Cholesky)
    Q' = dQ + contact correction (contact_rows.py, in Python between the two kernels)
    q' = q + dt qd',   frames' = predict(frames, v', w')             (frames.predict_kernel)

Mgen(t) holds each mover's world inertia at the step start, Mgen(t + dt) at the rotation
predicted over dt (momentum form, unified_system.SubspaceMass). A free body (no pins)
steps relative to its mean rigid motion gm = (C, V, W) (docs/method.md §9.4): Qn is the
relative velocity turned by Rc = exp(-2 dt [W]x) (the Coriolis flow), Fn gains the
centrifugal force of the frame centres, p0 = Mgen(t) (Qn + Q_W) - Mgen(t + dt) Q_W with Q_W
carrying W on the angular rows, and the prediction carries every frame by exp(dt [W]x)
(fictitious.global_rows_kernel, frames.predict_kernel). The caller computes gm and
restores the angular momentum after the kernels (Step._rebalance). G and K are the start
state's (Step._start_evaluation: the cubature samples and the coupling projection, their
own kernels). Shapes: D domains, r_max padded modes, S subspace rows, M movers.

linear_solve_kernel forms and solves the system, leaving the factor where the contact
solves' half sweeps read it; linear_predict_kernel makes the new state from Q'; without
contact linear_step_kernel does both in one call.

Why compiled: every part of this was a compiled kernel already, and the numpy and Python
between them (the mass structure, the residual, the pattern matrix, the permuted factor,
the gather and scatter of Q, the frame prediction, the inertia) were most of a small
body's step: about 100 us of a 12-DOF cantilever's 0.23 ms (session 29,
docs/performance.md). The kernels perform the same operations in the same order as
step.Step._step does for such a step, calling the same kernels: the same bits
(test_linear_step.py). Any other step (Newton iterations, full-space domains, implicit
fictitious forces, the two-step foil, non-uniform interface cubature) runs
step.Step._step.

numba's cache=True keys a cached kernel on its own file only, and these kernels link the
kernels they call into their own machine code: a change to frames.py, fictitious.py,
generalised_forces.py, unified_system.py or block_cholesky.py (or rotations.py, which
frames.py inlines) must come with an edit of this file, or its cache serves the old
code. test_linear_step.py enforces it: it hashes those files and compares with
DEPENDENCY_STAMP below.
"""
import numpy as np
from numba import njit

from .block_cholesky import backward_blocks, factor_blocks, forward_blocks, permute_lower
from .fictitious import fictitious_rows_kernel, global_rows_kernel
from .frames import inertia_kernel, predict_kernel, world_inertia_kernel
from .generalised_forces import gravity_rows_kernel
from .unified_system import add_mass, mass_matvec_kernel, pattern_matrix

#: sha256 (first 16 hex digits) of the source files whose kernels these kernels call (paths
#: relative to this file's folder), in DEPENDENCIES order, joined by "-" (module docstring).
DEPENDENCY_STAMP = ("b1b50f44620c1759-9e7309b6243ca54d-b212032724dacdf0-2d24fd005e0f7789-1605a21662ed35ee"
                    "-0ef905968d922b1f")
DEPENDENCIES = ("frames.py", "fictitious.py", "generalised_forces.py", "unified_system.py", "block_cholesky.py",
                "../rotations.py")


@njit(cache=True)
def linear_solve_kernel(q, qd, c, R, v, w, w_prev, G, K, F_app, gravity, has_gravity, free, C, V, Wg, Rc, dt, alpha,
                        beta, r, movable, q_index, modal_rows, movers, lin_index, ang_index, total_mass, mass_moment,
                        inertia0, B1, B2, W, s, A, blocks, offsets, perm, po, later_ptr, later_idx, L,
                        dQ_out, r_out, inertia_out):
    """The system and solve of a linearly implicit step (module docstring): dQ = -A^-1 r.
    Start state q, qd (D, r_max), frames c, v, w, w_prev (D, 3), R (D, 3, 3); start
    evaluation G (S,), K (S, S); F_app (S,) the applied loads' generalised forces; gravity
    (3,) (has_gravity False: none); free: a free body, stepped relative to its mean rigid
    motion C, V, Wg (3,) with Rc (3, 3) = exp(-2 dt [Wg]x) (unread otherwise); layout
    arrays as in layout.DomainLayout; A (S, S) the pattern buffer (unified_system
    _pattern_buffer) and blocks (n_b, 2), offsets (D + 1,) its blocks; perm, po, later_ptr,
    later_idx, L (S, S) the block Cholesky (block_cholesky.BlockCholesky), which holds the
    factor afterwards (the contact solves' half sweeps read it).

    Writes dQ_out (S,), r_out (S,) the residual at Q = 0 and inertia_out (D, 3, 3) the
    body-frame inertia at q (inertia0 where no frame moves). Returns the failed block or
    -1: on a failed block (A not positive definite) only A, L, r_out and inertia_out are
    written, and the caller steps again by step.Step._step, which solves by LU."""
    D = q.shape[0]
    S = G.shape[0]
    M = movers.shape[0]
    # Body-frame inertia at the start (Step._inertia_of), world inertia now and predicted.
    I_start = inertia_out
    if M:
        inertia_kernel(q, r, inertia0, B1, B2, I_start)
    else:
        I_start[:] = inertia0
    mass = np.empty(M)
    for m in range(M):
        mass[m] = total_mass[movers[m]]
    I_now = np.empty((M, 3, 3))
    I_pred = np.empty((M, 3, 3))
    if M:
        world_inertia_kernel(R, w, dt, I_start, movers, I_pred)
        world_inertia_kernel(R, w, 0.0, I_start, movers, I_now)
    # Qn: the start velocities in generalised order (ReducedModel.get_Q).
    Qn = np.zeros(S)
    for d in range(D):
        for a in range(r[d]):
            Qn[q_index[d, a]] = qd[d, a]
    for m in range(M):
        for k in range(3):
            Qn[lin_index[m, k]] = v[movers[m], k]
            Qn[ang_index[m, k]] = w[movers[m], k]
    eye = np.eye(3)
    if free:
        # Qn - Q_rigid(gm), its linear rows turned by Rc (FictitiousTerms._coriolis_rotate).
        Q_rigid = np.zeros(S)
        global_rows_kernel(c, movers, lin_index, ang_index, total_mass, C, V, Wg, True, False, False, eye,
                           Q_rigid, Q_rigid)
        Q_rel = Qn - Q_rigid
        Qn = Q_rel.copy()
        global_rows_kernel(c, movers, lin_index, ang_index, total_mass, C, V, Wg, False, False, False, Rc,
                           Q_rel, Qn)
    # Fn = F_app + gravity + explicit fictitious forces, summed in that order.
    F_grav = np.zeros(S)
    if has_gravity:
        gravity_rows_kernel(mass_moment, r, q_index, R, gravity, total_mass, movers, lin_index, F_grav)
    F_fict = np.zeros(S)
    if M:
        fictitious_rows_kernel(W, B1, B2, s, r, movers, q_index, q, qd, R, w, w_prev, dt, F_fict)
    F_glob = np.zeros(S)                          # the frame centres' centrifugal force
    p0 = np.empty(S)
    if free:
        global_rows_kernel(c, movers, lin_index, ang_index, total_mass, C, V, Wg, False, False, True, eye,
                           F_glob, F_glob)
        # Momentum at the step start: Mgen(t) (Qn + Q_W) - Mgen(t + dt) Q_W.
        zero = np.zeros(3)
        Q_W = np.zeros(S)
        global_rows_kernel(c, movers, lin_index, ang_index, total_mass, zero, zero, Wg, True, True, False, eye,
                           Q_W, Q_W)
        p_now = np.empty(S)
        p_pred = np.empty(S)
        mass_matvec_kernel(Qn + Q_W, modal_rows, lin_index, mass, ang_index, I_now, p_now)
        mass_matvec_kernel(Q_W, modal_rows, lin_index, mass, ang_index, I_pred, p_pred)
        for i in range(S):
            p0[i] = p_now[i] - p_pred[i]
    else:
        mass_matvec_kernel(Qn, modal_rows, lin_index, mass, ang_index, I_now, p0)
    rhs = np.empty(S)
    for i in range(S):
        Fn = F_app[i] + F_grav[i] + F_fict[i]
        if free:
            Fn = Fn + F_glob[i]
        ri = dt * (G[i] - Fn) - p0[i]
        r_out[i] = ri
        rhs[i] = -ri
    # A = (dt^2 + dt beta) K + (1 + dt alpha) Mgen(t + dt) on the pattern's blocks.
    pattern_matrix(K, dt * dt + dt * beta, K, 0.0, blocks, offsets, A)
    add_mass(A, 1.0 + dt * alpha, modal_rows, lin_index, mass, ang_index, I_pred)
    permute_lower(A, perm, po, later_ptr, later_idx, L)
    failed = factor_blocks(L, po, later_ptr, later_idx)
    if failed >= 0:
        return failed
    y = np.empty((S, 1))
    for i in range(S):
        y[i, 0] = rhs[perm[i]]
    forward_blocks(L, po, later_ptr, later_idx, y)
    backward_blocks(L, po, later_ptr, later_idx, y)
    for i in range(S):
        dQ_out[perm[i]] = y[i, 0]
    return -1


@njit(cache=True)
def linear_predict_kernel(q, c, R, v, w, Q, dt, free, C, V, Wg, r, movable, q_index, movers, lin_index, ang_index,
                          inertia0, B1, B2, I_start, q_out, qd_out, c_out, R_out, v_out, w_out, inertia_out):
    """The state after a linearly implicit step with velocities Q (S,) (Step._predict; its
    angular momentum balance is the caller's): q_out, qd_out (D, r_max), the frames c_out,
    v_out, w_out (D, 3), R_out (D, 3, 3) and inertia_out (D, 3, 3) the body-frame inertia
    at q_out (inertia0 where no frame moves). Start state and layout as in
    linear_solve_kernel; I_start (D, 3, 3) its inertia_out."""
    D = q.shape[0]
    M = movers.shape[0]
    for d in range(D):
        for a in range(q.shape[1]):
            k = q_index[d, a]
            qd_out[d, a] = Q[k] if k >= 0 else 0.0
            q_out[d, a] = q[d, a] + dt * qd_out[d, a]
    v_new = v.copy()
    w_new = w.copy()
    for m in range(M):
        for k in range(3):
            v_new[movers[m], k] = Q[lin_index[m, k]]
            w_new[movers[m], k] = Q[ang_index[m, k]]
    # Fixed frames read no inertia (predict_kernel keeps them): inertia0 stands in.
    if M:
        inertia_kernel(q_out, r, inertia0, B1, B2, inertia_out)
    else:
        inertia_out[:] = inertia0
    predict_kernel(dt, c, R, w, v_new, w_new, movable, free, C, V, Wg, I_start, inertia_out,
                   c_out, R_out, v_out, w_out)


@njit(cache=True)
def linear_step_kernel(q, qd, c, R, v, w, w_prev, G, K, F_app, gravity, has_gravity, free, C, V, Wg, Rc, dt, alpha,
                       beta, r, movable, q_index, modal_rows, movers, lin_index, ang_index, total_mass, mass_moment,
                       inertia0, B1, B2, W, s, A, blocks, offsets, perm, po, later_ptr, later_idx, L,
                       q_out, qd_out, c_out, R_out, v_out, w_out, inertia_out, Q_out, r_out):
    """A whole linearly implicit step without contact: linear_solve_kernel, Q = 0 + 1 dQ
    (Step._step's first Newton iterate at step length 1) into Q_out (S,), then
    linear_predict_kernel. Arguments as there; returns linear_solve_kernel's answer (on a
    failed block nothing of the state is written)."""
    I_start = np.empty(inertia_out.shape)
    dQ = np.empty(Q_out.shape[0])
    failed = linear_solve_kernel(q, qd, c, R, v, w, w_prev, G, K, F_app, gravity, has_gravity, free, C, V, Wg, Rc,
                                 dt, alpha, beta, r, movable, q_index, modal_rows, movers, lin_index, ang_index,
                                 total_mass, mass_moment, inertia0, B1, B2, W, s, A, blocks, offsets, perm, po,
                                 later_ptr, later_idx, L, dQ, r_out, I_start)
    if failed >= 0:
        return failed
    for i in range(Q_out.shape[0]):
        Q_out[i] = 0.0 + 1.0 * dQ[i]
    linear_predict_kernel(q, c, R, v, w, Q_out, dt, free, C, V, Wg, r, movable, q_index, movers, lin_index,
                          ang_index, inertia0, B1, B2, I_start, q_out, qd_out, c_out, R_out, v_out, w_out, inertia_out)
    return -1
