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

from ..rotations import exp_so3_batch, orthonormalise_batch


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
        o0, o1, o2 = omega[d, 0], omega[d, 1], omega[d, 2]
        a0, a1, a2 = alpha[d, 0], alpha[d, 1], alpha[d, 2]
        w2 = o0 * o0 + o1 * o1 + o2 * o2
        for a in range(rd):
            acc = 0.0
            for b in range(rd):
                wk0 = W[d, a, b, 0]
                wk1 = W[d, a, b, 1]
                wk2 = W[d, a, b, 2]
                acc += 2.0 * qd[d, b] * (wk0 * o0 + wk1 * o1 + wk2 * o2)
                acc += q[d, b] * (wk0 * a0 + wk1 * a1 + wk2 * a2)
                bo = 0.0
                for i in range(3):
                    bo += omega[d, i] * (B2[d, a, b, i, 0] * o0 + B2[d, a, b, i, 1] * o1 + B2[d, a, b, i, 2] * o2)
                acc -= bo * q[d, b]
            b1 = 0.0
            for i in range(3):
                b1 += omega[d, i] * (B1[d, a, i, 0] * o0 + B1[d, a, i, 1] * o1 + B1[d, a, i, 2] * o2)
            out[d, a] = acc - b1 + w2 * (s[d, a] + q[d, a])


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

    def advance(self, v_new, w_new, dt, movable):
        """c' = c + dt v', R' = exp([dt w']x) R for the movable domains (bool (d,))."""
        self.w_prev = self.w.copy()
        self.v = np.where(movable[:, None], v_new, 0.0)
        self.w = np.where(movable[:, None], w_new, 0.0)
        self.c = self.c + dt * self.v
        mv = np.flatnonzero(movable)
        if len(mv):              # a pinned body's frames stay put (and small arrays cost per call)
            self.R[mv] = orthonormalise_batch(exp_so3_batch(dt * self.w[mv]) @ self.R[mv])


def rest_inertia(r_local, mass):
    """Rest inertia tensor about the centre of mass: (3, 3)."""
    rr = (mass * (r_local * r_local).sum(1)).sum()
    return rr * np.eye(3) - np.einsum("l,li,lj->ij", mass, r_local, r_local)
