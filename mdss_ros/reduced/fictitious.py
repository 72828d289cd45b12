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
from numba import njit

from ..rotations import cross, exp_so3
from .frames import fictitious_rows_kernel, omega_B2_omega


@njit(cache=True)
def momentum_kernel(m, c, v, w, R, inertia, out):
    """Mass centre, velocity, angular momentum and inertia of point bodies with their own
    rotated inertia: rows k of m (n,), c, v, w (n, 3), R, inertia (n, 3, 3) (body frame;
    zero for a point mass). out (6, 3): rows C, V, L, then I (3, 3). One compiled pass:
    the same sums in numpy were about 40 small array operations, 0.10 ms on octopus's
    17 domains, and a free body's step makes two (session 20).

        C = sum m c / M,  V = sum m v / M,  rho = c - C,  I_k = R_k inertia_k R_k^T
        I = sum I_k + sum m (|rho|^2 E - rho rho^T),  L = sum rho x m (v - V) + sum I_k w
    """
    n = m.shape[0]
    M = 0.0
    C = np.zeros(3)
    V = np.zeros(3)
    for k in range(n):
        M += m[k]
        for i in range(3):
            C[i] += m[k] * c[k, i]
            V[i] += m[k] * v[k, i]
    for i in range(3):
        C[i] /= M
        V[i] /= M
    L = np.zeros(3)
    Iw = np.zeros(3)
    I = np.zeros((3, 3))
    RI = np.empty((3, 3))
    for k in range(n):
        r0, r1, r2 = c[k, 0] - C[0], c[k, 1] - C[1], c[k, 2] - C[2]
        mk = m[k]
        u0, u1, u2 = mk * (v[k, 0] - V[0]), mk * (v[k, 1] - V[1]), mk * (v[k, 2] - V[2])
        L[0] += r1 * u2 - r2 * u1
        L[1] += r2 * u0 - r0 * u2
        L[2] += r0 * u1 - r1 * u0
        rr = mk * (r0 * r0 + r1 * r1 + r2 * r2)
        rho = (r0, r1, r2)
        for i in range(3):
            for j in range(3):
                RI[i, j] = R[k, i, 0] * inertia[k, 0, j] + R[k, i, 1] * inertia[k, 1, j] + R[k, i, 2] * inertia[k, 2, j]
        for i in range(3):
            for j in range(3):
                Ik = RI[i, 0] * R[k, j, 0] + RI[i, 1] * R[k, j, 1] + RI[i, 2] * R[k, j, 2]
                I[i, j] += Ik - mk * rho[i] * rho[j] + (rr if i == j else 0.0)
                Iw[i] += Ik * w[k, j]
    for i in range(3):
        out[0, i] = C[i]
        out[1, i] = V[i]
        out[2, i] = L[i] + Iw[i]
        for j in range(3):
            out[3 + i, j] = I[i, j]


@njit(cache=True)
def global_rows_kernel(c, movers, lin_index, ang_index, total_mass, C, V, W, rigid, angular_only, centrifugal, Rc,
                       Q_in, Q):
    """The free body's mean rigid motion (C, V, W) (3,) each on the frames' rows of a
    generalised vector, one pass over the movable domains d = movers[m] (c (D, 3) their
    centres, lin_index, ang_index (M, 3) their rows, total_mass (D,)):
      rigid:        Q[ang] = W, and unless angular_only Q[lin] = V + W x (c_d - C)
                    (FictitiousTerms._rigid_Q);
      centrifugal:  Q[lin] = -m_d W x (W x (c_d - C))   (_global_fictitious);
      otherwise:    Q[lin] = Rc Q_in[lin], Rc (3, 3)    (_coriolis_rotate).
    Q (n_gen,) is written on those rows only."""
    for m in range(movers.shape[0]):
        d = movers[m]
        x0, x1, x2 = c[d, 0] - C[0], c[d, 1] - C[1], c[d, 2] - C[2]
        if rigid:
            for i in range(3):
                Q[ang_index[m, i]] = W[i]
            if not angular_only:
                Q[lin_index[m, 0]] = V[0] + (W[1] * x2 - W[2] * x1)
                Q[lin_index[m, 1]] = V[1] + (W[2] * x0 - W[0] * x2)
                Q[lin_index[m, 2]] = V[2] + (W[0] * x1 - W[1] * x0)
        elif centrifugal:
            y0, y1, y2 = W[1] * x2 - W[2] * x1, W[2] * x0 - W[0] * x2, W[0] * x1 - W[1] * x0
            mk = -total_mass[d]
            Q[lin_index[m, 0]] = mk * (W[1] * y2 - W[2] * y1)
            Q[lin_index[m, 1]] = mk * (W[2] * y0 - W[0] * y2)
            Q[lin_index[m, 2]] = mk * (W[0] * y1 - W[1] * y0)
        else:
            q0, q1, q2 = Q_in[lin_index[m, 0]], Q_in[lin_index[m, 1]], Q_in[lin_index[m, 2]]
            for i in range(3):
                Q[lin_index[m, i]] = q0 * Rc[i, 0] + q1 * Rc[i, 1] + q2 * Rc[i, 2]


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
        m, c, v, w, R = self.layout.total_mass, fr.c, fr.v, fr.w, fr.R
        inertia = self.layout.inertia(q) if inertia is None else inertia
        if self.F:
            # Full-space vertices join as point masses (no inertia of their own).
            full = self.is_full_vertex
            n_f = int(full.sum())
            m = np.concatenate([m, self.vertex_mass[full]])
            c, v = np.concatenate([c, x_full[full]]), np.concatenate([v, v_full[full]])
            w = np.concatenate([w, np.zeros((n_f, 3))])
            R = np.concatenate([R, np.tile(np.eye(3), (n_f, 1, 1))])
            inertia = np.concatenate([inertia, np.zeros((n_f, 3, 3))])
        out = np.empty((6, 3))
        momentum_kernel(m, np.ascontiguousarray(c), np.ascontiguousarray(v), np.ascontiguousarray(w),
                        np.ascontiguousarray(R), np.ascontiguousarray(inertia), out)
        return out[0], out[1], out[2], out[3:]

    def _global_rows(self, C, V, W, out, rigid=False, angular_only=False, centrifugal=False, Rc=None, Q_in=None):
        """global_rows_kernel on the movable frames' rows of out (n_gen,)."""
        L = self.layout
        f64 = np.float64
        global_rows_kernel(np.ascontiguousarray(self.frames.c), L.movers, L.lin_index, L.ang_index, L.total_mass,
                           np.asarray(C, dtype=f64), np.asarray(V, dtype=f64), np.asarray(W, dtype=f64), rigid,
                           angular_only, centrifugal, np.eye(3) if Rc is None else Rc,
                           out if Q_in is None else Q_in, out)

    def _rigid_Q(self, gm, angular_only=False):
        """Generalised velocities of the rigid motion (V, W) about C (n_gen,);
        angular_only: W on the domains' angular rows, zero elsewhere."""
        C, V, W = gm[:3]
        Q = np.zeros(self.n_gen)
        self._global_rows(C, V, W, Q, rigid=True, angular_only=angular_only)
        if self.F and not angular_only:
            Q[self.S:] = self._full_free(V + cross(W, self.x_full - C))
        return Q

    def _global_fictitious(self, gm):
        """Centrifugal force of the frame rotating with W on frame centres and full-space
        vertices (n_gen,). The angular rows take W through the momentum form, and the
        Coriolis force through _coriolis_rotate."""
        C, V, W = gm[:3]
        F = np.zeros(self.n_gen)
        self._global_rows(C, V, W, F, centrifugal=True)
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
        self._global_rows(gm[0], gm[1], gm[2], Q, Rc=Rc, Q_in=Q_rel)
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
        fictitious_rows_kernel(L.W, L.B1, L.B2, L.s, L.r, L.movers, L.q_index, np.ascontiguousarray(q),
                               np.ascontiguousarray(qd) if coriolis else np.zeros_like(qd),
                               np.ascontiguousarray(frames.R), np.ascontiguousarray(frames.w),
                               np.ascontiguousarray(frames.w_prev), float(dt), F)
        return F
