"""Fictitious forces of moving domain frames, and the free body's mean rigid motion
(docs/method.md §7, §9.4, §9.5).

In a movable domain's frame (omega = R^T w, alpha = R^T dw/dt, per domain) the modal rows
feel the Coriolis, Euler and centrifugal forces of the frame's motion:

    U^T f_fict = -C qd - K_cf q + (terms free of q and qd)
    C    = 2 W[a, b] . omega                  (D, r_max, r_max), skew
    K_cf = |omega|^2 I - omega^T B2 omega     (D, r_max, r_max), symmetric PSD

with the precomputed tensors W and B2 of layout.DomainLayout. Explicitly (the paper) they
enter b; implicitly (`fictitious: implicit`) C is integrated exactly as qd <- exp(dt C) qd
and K_cf joins the damping. A free body (no pins) steps relative to its mean rigid motion
gm = (C, V, W, L) (3,) each: mass centre, its velocity, angular velocity, angular momentum.
Frame centres then feel -m W x (W x (c - C)), and relative linear velocities are turned by
exp(-2 dt W), the exact flow of the Coriolis force. Shapes: Q, F (n_gen,).
"""

import numpy as np
import scipy.linalg as sla

from ..rotations import cross, exp_so3
from .frames import fictitious_forces, omega_B2_omega


class FictitiousTerms:
    """Fictitious forces and the free body's mean rigid motion, for ReducedModel. Mixed into
    reduced_model.ReducedModel, whose build provides the attributes it reads."""

    def _global_motion(self, inertia=None):
        """(C, V, W, L): mass centre, velocity, angular velocity and angular momentum of
        the whole body, W fitted to L (frames and full-space vertices), or None for a body
        held by pins."""
        if self.body.pinned.size or not self.movable.all():
            return None
        C, V, L, I = self._momentum(self.frames, self.q, self.x_full, self.v_full, inertia)
        return C, V, np.linalg.solve(I, L), L

    def _momentum(self, fr, q, x_full, v_full, inertia=None):
        """Mass centre C, its velocity V, angular momentum L about C and inertia I (3, 3)
        of a state, from the domain frames (the deformation's own angular momentum is
        second order because U is mass-orthogonal to rotations) and full-space vertices."""
        m_d = self.layout.total_mass
        full = self.is_full_vertex
        m_f = self.vertex_mass[full]
        x_f, v_f = x_full[full], v_full[full]
        m = m_d.sum() + m_f.sum()
        C = ((m_d[:, None] * fr.c).sum(0) + (m_f[:, None] * x_f).sum(0)) / m
        V = ((m_d[:, None] * fr.v).sum(0) + (m_f[:, None] * v_f).sum(0)) / m
        rho, rho_f = fr.c - C, x_f - C
        I_d = fr.R @ (self.layout.inertia(q) if inertia is None else inertia) @ fr.R.transpose(0, 2, 1)
        I = (I_d.sum(0) + ((m_d * (rho * rho).sum(1)).sum() + (m_f * (rho_f * rho_f).sum(1)).sum()) * np.eye(3)
             - np.einsum("i,ij,ik->jk", m_d, rho, rho) - np.einsum("i,ij,ik->jk", m_f, rho_f, rho_f))
        L = (cross(rho, m_d[:, None] * (fr.v - V)).sum(0) + np.einsum("ijk,ik->j", I_d, fr.w)
             + cross(rho_f, m_f[:, None] * (v_f - V)).sum(0))
        return C, V, L, I

    def _rigid_Q(self, gm, angular_only=False):
        """Generalised velocities of the rigid motion (V, W) about C (n_gen,);
        angular_only: W on the domains' angular rows, zero elsewhere."""
        C, V, W = gm[:3]
        L = self.layout
        Q = np.zeros(self.n_gen)
        Q[L.ang_index] = W
        if not angular_only:
            Q[L.lin_index] = V + cross(W, self.frames.c[L.movers] - C)
        if self.F and not angular_only:
            Q[self.S:] = self._full_free(V + cross(W, self.x_full - C))
        return Q

    def _global_fictitious(self, gm):
        """Centrifugal force of the frame rotating with W on frame centres and full-space
        vertices (n_gen,). The angular rows take W through the momentum form, and the
        Coriolis force through _coriolis_rotate."""
        C, V, W = gm[:3]
        L = self.layout
        F = np.zeros(self.n_gen)
        F[L.lin_index] = -L.total_mass[L.movers, None] * cross(W, cross(W, self.frames.c[L.movers] - C))
        if self.F:
            f = -self.vertex_mass[:, None] * cross(W, cross(W, self.x_full - C))
            F[self.S:] = self._full_free(f)
        return F

    def _coriolis_rotate(self, gm, Q_rel, dt):
        """Exact flow of the Coriolis force -2 m W x v over dt: rotate the relative linear
        velocities by exp(-2 dt W). Explicit Euler would inflate |v_rel| every step (the
        force is gyroscopic) and pump energy and angular momentum into a spinning body;
        the rotation keeps |v_rel| and sum m v_rel = 0 exactly."""
        Rc = exp_so3(-2.0 * dt * gm[2])
        Q = Q_rel.copy()
        lin = self.layout.lin_index
        Q[lin] = Q_rel[lin] @ Rc.T
        if self.F:
            Q[self.S:] = self._full_free(self._full_expand(Q_rel[self.S:]) @ Rc.T)
        return Q

    def _fictitious_matrices(self, frames):
        """Coriolis C and centrifugal stiffness K_cf (D, r_max, r_max) on each domain's q
        rows at the step start (omega = R^T w; zero for a fixed domain): U^T f_fc = C qd +
        K_cf q + (terms free of q and qd), C[a, b] = 2 W[a, b] . omega (skew, W is
        antisymmetric in a, b) and K_cf = |omega|^2 I - omega^T B2 omega (symmetric positive
        semi-definite). Padded rows and columns are zero."""
        L = self.layout
        omega = np.einsum("dji,dj->di", frames.R, frames.w) * L.movable[:, None]
        C = 2.0 * np.einsum("dabk,dk->dab", L.W, omega)
        eye = L.mask[:, :, None] & np.eye(L.r_max, dtype=bool)
        Kc = ((omega * omega).sum(1)[:, None, None] * eye * L.movable[:, None, None]
              - omega_B2_omega(L.B2, omega))
        return C, Kc

    def _modal_coriolis_rotate(self, C, Q, dt):
        """Exact flow of qd' = C qd over dt on the q rows (Mgen is I there): qd <- exp(dt C) qd,
        a rotation because C is skew, so the Coriolis force does no work, as in the continuum
        (explicit Euler multiplies |qd| by sqrt(1 + dt^2 |C|^2) per step). C (D, r_max, r_max)
        from _fictitious_matrices; a fixed domain's block is zero, its exp the identity."""
        L = self.layout
        Q = Q.copy()
        qd = np.einsum("dab,db->da", sla.expm(dt * C), L.gather(Q))
        Q[L.q_index[L.mask]] = qd[L.mask]
        return Q

    def _explicit_terms(self, frames, q, qd, dt, coriolis=True):
        """Fictitious forces (q rows) at the step start; the gyroscopic term lives in the
        momentum form of the angular rows (see _mass_blocks). coriolis=False leaves out the
        Coriolis term (the implicit treatment rotates qd instead)."""
        L = self.layout
        F = np.zeros(self.n_gen)
        if not len(L.movers):
            return F                     # fixed frames: no fictitious forces
        omega = np.einsum("dji,dj->di", frames.R, frames.w)
        alpha = np.einsum("dji,dj->di", frames.R, frames.w - frames.w_prev) / dt
        f = fictitious_forces(L, q, qd if coriolis else np.zeros_like(qd), omega, alpha)
        rows = L.mask & L.movable[:, None]
        F[L.q_index[rows]] = f[rows]
        return F
