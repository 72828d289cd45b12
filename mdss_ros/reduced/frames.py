"""Rigid frames of subspace domains and the fictitious forces of their non-inertial frames.

Domain i: rest vertices X_l (l in X_i), lumped masses m_l, rest centre of mass cbar,
local rest coordinates r_l = X_l - cbar, basis U (3 n_i x r, mass-orthonormal and, for a
free domain, mass-orthogonal to the six rigid modes). State c, R, v, w (world), q, qd.

    x_l = c + R (r_l + U_l q),      xd_l = v + w x (x_l - c) + R U_l qd

Fictitious forces in the frame (omega = R^T w, alpha = d omega/dt, p_l = r_l + U_l q):
Coriolis -2 m omega x U_l qd, inertial -m R^T a, Euler -m alpha x p_l, centrifugal
-m omega x (omega x p_l). Projected on U they are polynomials in (q, qd, omega, alpha)
whose coefficients are the tensors below, computed once (the "sandwich" idea of Kim and
James 2011), so a step never loops over vertices:

    W[a, b]  = sum_l m_l u_la x u_lb                (r, r, 3), antisymmetric in a, b
    B1[a]    = sum_l m_l u_la r_l^T                  (r, 3, 3)
    B2[a, b] = sum_l m_l u_la u_lb^T                 (r, r, 3, 3)
    s[a]     = trace B1[a] = sum_l m_l u_la . r_l

    U^T f_fc = 2 W(qd) omega + W(q) alpha                       (Coriolis, Euler)
               - omega^T B1 omega - sum_b q_b omega^T B2[:, b] omega
               + |omega|^2 (s + q)                               (centrifugal)

with W(y)[a] = sum_b y_b W[a, b]. The inertial term vanishes because U is
mass-orthogonal to translations, and the q-free Euler term because it is
mass-orthogonal to rotations. u_la is the 3-vector of column a at vertex l.
"""
from dataclasses import dataclass

import numpy as np
from numba import njit

from ..rotations import exp_so3_into, orthonormalise_into
# numba's cache=True keys a cached kernel on its own file only: the kernels here inline
# exp_so3_into and orthonormalise_into, so a change to rotations.py must come with an edit
# of this file (or a cleared NUMBA_CACHE_DIR). Last rotations change: both made njit
# functions of one rotation (session 21).



@dataclass(frozen=True)
class FictitiousTensors:
    """Precomputed projections of the fictitious forces (shapes in the module docstring)."""

    W: np.ndarray
    B1: np.ndarray
    B2: np.ndarray
    s: np.ndarray


def fictitious_tensors(U, r_local, mass):
    """U (3 n_i, r); r_local (n_i, 3) rest coordinates about the centre of mass; mass (n_i,)."""
    n = len(mass)
    u = U.reshape(n, 3, -1)                                  # u[l, i, a]
    mu = mass[:, None, None] * u
    W = np.cross(mu.transpose(2, 0, 1)[:, None], u.transpose(2, 0, 1)[None, :]).sum(axis=2)
    B1 = np.einsum("lia,lj->aij", mu, r_local)
    B2 = np.einsum("lia,ljb->abij", mu, u)
    return FictitiousTensors(W=W, B1=B1, B2=B2, s=np.einsum("aii->a", B1))


def fictitious_forces(t, q, qd, omega, alpha):
    """U^T f_fc of every domain at once: (D, r_max).

    t: tensors stacked per domain (layout.DomainLayout: W, B1, B2, s, zero padded);
    q, qd (D, r_max); omega, alpha (D, 3) in each domain's frame. Rows of a fixed domain
    and padded rows are zero. One compiled pass
    (fictitious_kernel): the same sums as numpy einsums over the stacked tensors took about
    0.2 ms a step on armadillo_class's 11 domains, most of it call overhead.
    """
    out = np.empty(q.shape)
    fictitious_kernel(t.W, t.B1, t.B2, t.s, t.r, t.movable, np.ascontiguousarray(q), np.ascontiguousarray(qd),
                      np.ascontiguousarray(omega), np.ascontiguousarray(alpha), out)
    return out


@njit(cache=True)
def _fictitious_row(W, B1, B2, s, d, a, rd, q, qd, o0, o1, o2, a0, a1, a2):
    """Row a of domain d's U^T f_fc (module docstring), over its rd modes."""
    acc = 0.0
    for b in range(rd):
        wk0 = W[d, a, b, 0]
        wk1 = W[d, a, b, 1]
        wk2 = W[d, a, b, 2]
        acc += 2.0 * qd[d, b] * (wk0 * o0 + wk1 * o1 + wk2 * o2)
        acc += q[d, b] * (wk0 * a0 + wk1 * a1 + wk2 * a2)
        bo = (o0 * (B2[d, a, b, 0, 0] * o0 + B2[d, a, b, 0, 1] * o1 + B2[d, a, b, 0, 2] * o2)
              + o1 * (B2[d, a, b, 1, 0] * o0 + B2[d, a, b, 1, 1] * o1 + B2[d, a, b, 1, 2] * o2)
              + o2 * (B2[d, a, b, 2, 0] * o0 + B2[d, a, b, 2, 1] * o1 + B2[d, a, b, 2, 2] * o2))
        acc -= bo * q[d, b]
    b1 = (o0 * (B1[d, a, 0, 0] * o0 + B1[d, a, 0, 1] * o1 + B1[d, a, 0, 2] * o2)
          + o1 * (B1[d, a, 1, 0] * o0 + B1[d, a, 1, 1] * o1 + B1[d, a, 1, 2] * o2)
          + o2 * (B1[d, a, 2, 0] * o0 + B1[d, a, 2, 1] * o1 + B1[d, a, 2, 2] * o2))
    return acc - b1 + (o0 * o0 + o1 * o1 + o2 * o2) * (s[d, a] + q[d, a])


@njit(cache=True)
def fictitious_kernel(W, B1, B2, s, r, movable, q, qd, omega, alpha, out):
    """out[d, a] = 2 (W(qd) omega)_a + (W(q) alpha)_a - omega^T B1[a] omega
    - sum_b (omega^T B2[a, b] omega) q_b + |omega|^2 (s_a + q_a), per movable domain d
    and a < r[d]; 0 elsewhere (a fixed frame has no fictitious forces, and padded rows
    are not the domain's). W (D, r_max, r_max, 3), B1 (D, r_max, 3, 3), B2 (D, r_max,
    r_max, 3, 3), s, q, qd (D, r_max), r (D,), movable (D,), omega, alpha (D, 3).
    Looping only to each domain's own r: an automatic star_limbs model (a pinned core of 30
    modes, arms of 6) ran the padded 30 x 30 loops for all six domains."""
    D, r_max = q.shape
    for d in range(D):
        rd = r[d] if movable[d] else 0
        for a in range(rd, r_max):
            out[d, a] = 0.0
        for a in range(rd):
            out[d, a] = _fictitious_row(W, B1, B2, s, d, a, rd, q, qd, omega[d, 0], omega[d, 1], omega[d, 2],
                                        alpha[d, 0], alpha[d, 1], alpha[d, 2])


@njit(cache=True)
def fictitious_rows_kernel(W, B1, B2, s, r, movers, q_index, q, qd, R, w, w_prev, dt, F):
    """F[q_index[d, a]] += U^T f_fc of each movable domain d = movers[m] (fictitious_kernel's
    rows), from the frame's omega = R^T w and alpha = R^T (w - w_prev) / dt. F (n_gen,);
    R (D, 3, 3), w, w_prev (D, 3); the rest as in fictitious_kernel (qd zero: no Coriolis
    term). One pass for what FictitiousTerms._explicit_terms did in two einsums, the
    kernel and a masked scatter."""
    for m in range(movers.shape[0]):
        d = movers[m]
        o0 = R[d, 0, 0] * w[d, 0] + R[d, 1, 0] * w[d, 1] + R[d, 2, 0] * w[d, 2]
        o1 = R[d, 0, 1] * w[d, 0] + R[d, 1, 1] * w[d, 1] + R[d, 2, 1] * w[d, 2]
        o2 = R[d, 0, 2] * w[d, 0] + R[d, 1, 2] * w[d, 1] + R[d, 2, 2] * w[d, 2]
        e0, e1, e2 = w[d, 0] - w_prev[d, 0], w[d, 1] - w_prev[d, 1], w[d, 2] - w_prev[d, 2]
        a0 = (R[d, 0, 0] * e0 + R[d, 1, 0] * e1 + R[d, 2, 0] * e2) / dt
        a1 = (R[d, 0, 1] * e0 + R[d, 1, 1] * e1 + R[d, 2, 1] * e2) / dt
        a2 = (R[d, 0, 2] * e0 + R[d, 1, 2] * e1 + R[d, 2, 2] * e2) / dt
        for a in range(r[d]):
            F[q_index[d, a]] += _fictitious_row(W, B1, B2, s, d, a, r[d], q, qd, o0, o1, o2, a0, a1, a2)


def omega_B2_omega(B2, omega):
    """omega^T B2[a, b] omega of every domain: (D, r, r) from B2 (D, r, r, 3, 3), omega (D, 3)."""
    D, r = B2.shape[:2]
    Bw = (B2.reshape(D, r * r * 3, 3) @ omega[:, :, None]).reshape(D, r, r, 3)
    return np.einsum("dabi,di->dab", Bw, omega)


@dataclass
class FrameState:
    """Rigid state of all d subspace domains (world frame).

    c (d, 3) centres of mass; R (d, 3, 3) rotations; v (d, 3) linear and w (d, 3)
    angular velocities; w_prev (d, 3) the angular velocity of the previous step
    (for the explicit angular acceleration of the Euler force).
    """

    c: np.ndarray
    R: np.ndarray
    v: np.ndarray
    w: np.ndarray
    w_prev: np.ndarray

    @classmethod
    def at_rest(cls, centres):
        d = len(centres)
        return cls(c=np.array(centres, dtype=np.float64).reshape(d, 3), R=np.tile(np.eye(3), (d, 1, 1)),
                   v=np.zeros((d, 3)), w=np.zeros((d, 3)), w_prev=np.zeros((d, 3)))

    def copy(self):
        return FrameState(self.c.copy(), self.R.copy(), self.v.copy(), self.w.copy(), self.w_prev.copy())

    def predict(self, v_new, w_new, dt, movable, inertia_start, inertia_end, carry=None):
        """The frames after a step of dt with frame velocities v_new, w_new (d, 3) (rows of
        fixed domains ignored): a new FrameState, its w_prev this state's w.

        carry None: c' = c + dt v', R' = exp([dt w']x) R. carry = (C, V, W): v', w' are
        relative to the body's mean rigid motion about its mass centre C (a free body,
        step.py's _predict), which carries every frame by Rg = exp(dt [W]x):
        c' = C + dt V + Rg (c - C + dt v'), v = V + W x (c' - C - dt V) + Rg v',
        R' = Rg exp([dt w']x) R. Then each movable frame's angular velocity is re-expressed
        from the momentum it was solved for at the predicted rotation, I_p w_a with I_p =
        Rp I_s Rp^T, Rp = exp([dt w]x) R and w_a = w' (+ W when carried), with its inertia
        after the step: w = (R' I_e R'^T)^-1 I_p w_a. inertia_start, inertia_end (d, 3, 3)
        body-frame inertia at the step's start and end (layout.inertia). One compiled pass
        (predict_kernel): the same in numpy was about 30 small operations, 0.25 ms of an
        automatic star_limbs model's 0.64 ms step (session 21)."""
        out = FrameState(np.empty_like(self.c), np.empty_like(self.R), np.empty_like(self.v),
                         np.empty_like(self.w), self.w.copy())
        C, V, W = (np.zeros(3), np.zeros(3), np.zeros(3)) if carry is None else carry
        predict_kernel(dt, self.c, self.R, self.w, np.ascontiguousarray(v_new), np.ascontiguousarray(w_new), movable,
                       carry is not None, np.asarray(C, dtype=np.float64), np.asarray(V, dtype=np.float64),
                       np.asarray(W, dtype=np.float64), np.ascontiguousarray(inertia_start),
                       np.ascontiguousarray(inertia_end), out.c, out.R, out.v, out.w)
        return out


@njit(cache=True)
def _mul3(A, B, out):
    """out = A B for (3, 3) matrices (out not A or B)."""
    for i in range(3):
        for j in range(3):
            out[i, j] = A[i, 0] * B[0, j] + A[i, 1] * B[1, j] + A[i, 2] * B[2, j]


@njit(cache=True)
def _sandwich(R, I, out, T):
    """out = R I R^T (3, 3); T scratch (3, 3)."""
    _mul3(R, I, T)
    for i in range(3):
        for j in range(3):
            out[i, j] = T[i, 0] * R[j, 0] + T[i, 1] * R[j, 1] + T[i, 2] * R[j, 2]


@njit(cache=True)
def _predicted_world_inertia(R, w, dt, I, out, E, X):
    """out = Rp I Rp^T (3, 3), Rp = exp([dt w]x) R: a body-frame inertia I in the world at
    the rotation predicted over dt (dt = 0: R itself, exp(0) being exactly I). E, X (3, 3)
    scratch."""
    exp_so3_into(dt * w[0], dt * w[1], dt * w[2], E)
    _mul3(E, R, X)
    _sandwich(X, I, out, E)


@njit(cache=True)
def predict_kernel(dt, c0, R0, w0, v_new, w_new, movable, carry, C, V, W, I_start, I_end, c, R, v, w):
    """FrameState.predict for every frame d (shapes (D, 3), (D, 3, 3)): writes c, R, v, w.
    A fixed frame keeps c0, R0 with zero velocities. Each new rotation is the product
    (Rg) exp([dt w']x) R0 made orthonormal (rotations.orthonormalise_into: one Bjorck
    step, or the SVD's polar factor for a product far from a rotation)."""
    D = c0.shape[0]
    E = np.empty((3, 3))
    X = np.empty((3, 3))
    T = np.empty((3, 3))
    Ip = np.empty((3, 3))
    I1 = np.empty((3, 3))
    Rg = np.empty((3, 3))
    exp_so3_into(dt * W[0], dt * W[1], dt * W[2], Rg)
    for d in range(D):
        if not movable[d]:
            for i in range(3):
                c[d, i] = c0[d, i]
                v[d, i] = 0.0
                w[d, i] = 0.0
                for j in range(3):
                    R[d, i, j] = R0[d, i, j]
            continue
        exp_so3_into(dt * w_new[d, 0], dt * w_new[d, 1], dt * w_new[d, 2], E)
        if carry:
            # rho = Rg (c0 - C + dt v'); c = C + dt V + rho; v = V + W x rho + Rg v'; w = W + Rg w'
            p0 = c0[d, 0] - C[0] + dt * v_new[d, 0]
            p1 = c0[d, 1] - C[1] + dt * v_new[d, 1]
            p2 = c0[d, 2] - C[2] + dt * v_new[d, 2]
            r0 = Rg[0, 0] * p0 + Rg[0, 1] * p1 + Rg[0, 2] * p2
            r1 = Rg[1, 0] * p0 + Rg[1, 1] * p1 + Rg[1, 2] * p2
            r2 = Rg[2, 0] * p0 + Rg[2, 1] * p1 + Rg[2, 2] * p2
            c[d, 0] = C[0] + dt * V[0] + r0
            c[d, 1] = C[1] + dt * V[1] + r1
            c[d, 2] = C[2] + dt * V[2] + r2
            wx = (W[1] * r2 - W[2] * r1, W[2] * r0 - W[0] * r2, W[0] * r1 - W[1] * r0)
            for i in range(3):
                v[d, i] = V[i] + wx[i] + (Rg[i, 0] * v_new[d, 0] + Rg[i, 1] * v_new[d, 1] + Rg[i, 2] * v_new[d, 2])
                w[d, i] = W[i] + (Rg[i, 0] * w_new[d, 0] + Rg[i, 1] * w_new[d, 1] + Rg[i, 2] * w_new[d, 2])
            _mul3(Rg, E, T)
            _mul3(T, R0[d], X)
        else:
            for i in range(3):
                v[d, i] = v_new[d, i]
                w[d, i] = w_new[d, i]
                c[d, i] = c0[d, i] + dt * v_new[d, i]
            _mul3(E, R0[d], X)
        orthonormalise_into(X, R[d], T)
        # Momentum form: h = Rp I_s Rp^T w_a at the predicted rotation, then w = (R I_e R^T)^-1 h.
        _predicted_world_inertia(R0[d], w0[d], dt, I_start[d], Ip, E, X)
        if carry:
            a0, a1, a2 = W[0] + w_new[d, 0], W[1] + w_new[d, 1], W[2] + w_new[d, 2]
        else:
            a0, a1, a2 = w[d, 0], w[d, 1], w[d, 2]
        h0 = Ip[0, 0] * a0 + Ip[0, 1] * a1 + Ip[0, 2] * a2
        h1 = Ip[1, 0] * a0 + Ip[1, 1] * a1 + Ip[1, 2] * a2
        h2 = Ip[2, 0] * a0 + Ip[2, 1] * a1 + Ip[2, 2] * a2
        _sandwich(R[d], I_end[d], I1, T)
        # I1 is symmetric positive definite: Cramer's rule by cofactors.
        k00 = I1[1, 1] * I1[2, 2] - I1[1, 2] * I1[2, 1]
        k01 = I1[0, 2] * I1[2, 1] - I1[0, 1] * I1[2, 2]
        k02 = I1[0, 1] * I1[1, 2] - I1[0, 2] * I1[1, 1]
        k11 = I1[0, 0] * I1[2, 2] - I1[0, 2] * I1[2, 0]
        k12 = I1[0, 2] * I1[1, 0] - I1[0, 0] * I1[1, 2]
        k22 = I1[0, 0] * I1[1, 1] - I1[0, 1] * I1[1, 0]
        k10 = I1[1, 2] * I1[2, 0] - I1[1, 0] * I1[2, 2]
        k20 = I1[1, 0] * I1[2, 1] - I1[1, 1] * I1[2, 0]
        k21 = I1[0, 1] * I1[2, 0] - I1[0, 0] * I1[2, 1]
        det = I1[0, 0] * k00 + I1[0, 1] * k10 + I1[0, 2] * k20
        w[d, 0] = (k00 * h0 + k01 * h1 + k02 * h2) / det
        w[d, 1] = (k10 * h0 + k11 * h1 + k12 * h2) / det
        w[d, 2] = (k20 * h0 + k21 * h1 + k22 * h2) / det


@njit(cache=True)
def world_inertia_kernel(R, w, dt, inertia, movers, out):
    """out[m] = Rp I Rp^T for each movable domain d = movers[m], Rp = exp([dt w_d]x) R_d
    (dt = 0: R_d itself, exp(0) being exactly I). R (D, 3, 3), w (D, 3), inertia (D, 3, 3)
    body-frame, movers (M,), out (M, 3, 3)."""
    E = np.empty((3, 3))
    X = np.empty((3, 3))
    for m in range(movers.shape[0]):
        d = movers[m]
        _predicted_world_inertia(R[d], w[d], dt, inertia[d], out[m], E, X)


@njit(cache=True)
def inertia_kernel(q, r, inertia0, B1, B2, out):
    """out[d] = I0 + (tr L + tr B2(q, q)) I - L - B2(q, q), L = B1(q) + B1(q)^T, with
    B1(q) = sum_a q_a B1[a] and B2(q, q) = sum_ab q_a q_b B2[a, b] over domain d's own r[d]
    modes. q (D, r_max), r (D,), inertia0 (D, 3, 3), B1 (D, r_max, 3, 3), B2 (D, r_max,
    r_max, 3, 3), out (D, 3, 3)."""
    D = q.shape[0]
    for d in range(D):
        b1 = np.zeros((3, 3))
        b2 = np.zeros((3, 3))
        for a in range(r[d]):
            qa = q[d, a]
            for i in range(3):
                for j in range(3):
                    b1[i, j] += qa * B1[d, a, i, j]
            for b in range(r[d]):
                qab = qa * q[d, b]
                for i in range(3):
                    for j in range(3):
                        b2[i, j] += qab * B2[d, a, b, i, j]
        tr = 2.0 * (b1[0, 0] + b1[1, 1] + b1[2, 2]) + b2[0, 0] + b2[1, 1] + b2[2, 2]
        for i in range(3):
            for j in range(3):
                out[d, i, j] = inertia0[d, i, j] + (tr if i == j else 0.0) - (b1[i, j] + b1[j, i]) - b2[i, j]


def rest_inertia(r_local, mass):
    """Rest inertia tensor about the centre of mass: (3, 3)."""
    rr = (mass * (r_local * r_local).sum(1)).sum()
    return rr * np.eye(3) - np.einsum("l,li,lj->ij", mass, r_local, r_local)
