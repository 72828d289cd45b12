"""Explicit fourth-order Runge-Kutta with sub-steps (`model.meshless.integrator: rk4`,
docs/method.md §19.4), the scheme [HZ] ran in SOFA.

State y = (x, v) on the free DOFs; per sub-step h = dt / n_sub

    a(x, v) = M^-1 (f_ext - f_int(x) - alpha M v - beta K(x_n) v)      (M lumped, diagonal)
    k1 = (v, a(x, v)),  k2 = at y + h/2 k1,  k3 = at y + h/2 k2,  k4 = at y + h k3
    y' = y + h/6 (k1 + 2 k2 + 2 k3 + k4)

K(x_n) (Rayleigh beta) is evaluated once per step, only when beta > 0.

Stability: RK4 is stable for h |lambda| inside its region (about 2.8 on the imaginary
axis, 2.78 on the negative real axis). `substeps: auto` takes
omega_max^2 = the largest eigenvalue of M^-1 K at rest (power iteration) and uses
h <= 0.8 * 2.5 / max(omega_max, alpha + beta omega_max^2); stiffness-proportional damping
therefore costs many sub-steps.

Contact (the same unilateral LCP as the implicit step, §14): after the sub-steps, with
the unconstrained end state (x*, v*), the velocity change dv solves
M dv = C^T lam, C = dt [n^T] per candidate row, with gap
g = phi + n . (x* - x) + dt n . dv >= 0, lam >= 0, lam g = 0, and x' = x* + dt dv.
lam are contact forces in newtons as in the implicit model. The rows (vertices and sphere
faces) are built by BackwardEuler's own row builder, which this class inherits.
"""
import time

import numpy as np

from ..fem.backward_euler import BackwardEuler, NewtonSettings, contact_record, contact_stats

RK4_IMAG_LIMIT = 2.5          # a little inside RK4's 2.83 on the imaginary axis
SAFETY = 0.8


def max_frequency(force_model, iterations=60, seed=0):
    """omega_max (rad/s): sqrt of the largest eigenvalue of M^-1 K at rest on the free DOFs."""
    fm = force_model
    _, _, K_data = fm.tangent(fm.X, project=True)
    K = fm.pattern.matrix(K_data)
    m = fm.free(np.repeat(fm.vertex_mass, 3).reshape(-1, 3))
    s = 1.0 / np.sqrt(m)
    z = np.random.default_rng(seed).standard_normal(fm.n_free)
    lam = 0.0
    for _ in range(iterations):
        y = s * (K @ (s * z))
        lam = float(np.linalg.norm(y))
        if lam == 0.0:
            return 0.0
        z = y / lam
    return float(np.sqrt(lam * 1.02))          # power iteration approaches from below


def auto_substeps(dt, omega_max, alpha, beta):
    rate = max(omega_max, alpha + beta * omega_max ** 2, 1e-300)
    return max(1, int(np.ceil(dt * rate / (SAFETY * RK4_IMAG_LIMIT))))


class RK4(BackwardEuler):
    """Explicit RK4 over `substeps` sub-steps of dt; the interface of BackwardEuler
    (dt, settings, step(x, v, f_ext, contact) -> (x', v'), stats, contact)."""

    def __init__(self, model, dt, substeps, settings=None, solver_backend="auto"):
        super().__init__(model, dt, settings or NewtonSettings(max_iterations=1), solver_backend)
        self.substeps = int(substeps)

    def _accel(self, xf, vf, x_full, f_ext_free, Kv):
        m = self.model
        x_full = x_full.copy()
        x_full.reshape(-1)[m.pattern.free_dof >= 0] = xf
        _, f_int = m.forces(x_full)
        s = self.settings
        a = f_ext_free - m.free(f_int) - s.alpha * self._m * vf
        if Kv is not None:
            a = a - Kv(vf)
        return a / self._m

    def step(self, x, v, f_ext, contact=None):
        from ..contact.friction import frictional_correction
        from ..contact.unilateral import contact_correction
        m, dt, s = self.model, self.dt, self.settings
        t0 = time.perf_counter()
        self.contact = None
        self._m = m.free(np.repeat(m.vertex_mass, 3).reshape(-1, 3))
        Kv = None
        if s.beta > 0.0:
            _, _, K_data = m.tangent(x)
            K = m.pattern.matrix(K_data)
            Kv = (lambda vf: s.beta * (K @ vf))
        fe = m.free(f_ext)
        xf, vf = m.free(x).copy(), m.free(v).copy()
        n_sub = self.substeps
        h = dt / n_sub
        for _ in range(n_sub):
            a1 = self._accel(xf, vf, x, fe, Kv)
            x2, v2 = xf + 0.5 * h * vf, vf + 0.5 * h * a1
            a2 = self._accel(x2, v2, x, fe, Kv)
            x3, v3 = xf + 0.5 * h * v2, vf + 0.5 * h * a2
            a3 = self._accel(x3, v3, x, fe, Kv)
            x4, v4 = xf + h * v3, vf + h * a3
            a4 = self._accel(x4, v4, x, fe, Kv)
            xf = xf + h / 6.0 * (vf + 2.0 * v2 + 2.0 * v3 + v4)
            vf = vf + h / 6.0 * (a1 + 2.0 * a2 + 2.0 * a3 + a4)
        x_new = x.copy()
        x_new.reshape(-1)[m.pattern.free_dof >= 0] = xf
        v_new = m.expand(vf)
        lcp = {}
        if contact:
            # Rows from the start state; the predicted positions of the candidate search are
            # the unconstrained end positions (x + dt v_pred with v_pred = (x* - x) / dt).
            rows = self._contact_rows(contact, x, (x_new - x) / dt)
            if len(rows[0]):
                verts, C, phi, normals, which, friction = rows
                resolve = (lambda B: B / (self._m[:, None] if B.ndim == 2 else self._m))
                regularize = 1e-9 if contact.get("triangles") is not None else 0.0
                v_pred = (xf - m.free(x)) / dt
                if friction is None:                             # g: phi + n . (x* - x)
                    lam, corr, lcp = contact_correction(resolve, C, C @ v_pred + phi, regularize=regularize)
                else:
                    C3, g3, mu = friction[:3]
                    lam, corr, lcp = frictional_correction(resolve, C3, C3 @ v_pred + g3, mu, regularize=regularize)
                vf = vf + corr
                xf = xf + dt * corr
                x_new.reshape(-1)[m.pattern.free_dof >= 0] = xf
                v_new = m.expand(vf)
                self.contact = contact_record(contact["colliders"], rows, lam, self.points(x_new), lcp.get("w"), dt)
        self.stats = {"newton_iterations": 0, "converged": True, "residual": 0.0, "projected": False,
                      "line_search_cuts": 0, "substeps": n_sub, "step_ms": 1e3 * (time.perf_counter() - t0)}
        if lcp:
            self.stats.update(contact_stats(lcp))
        return x_new, v_new
