"""Backward Euler with Newton iterations on the end-of-step velocity.

Equation (docs/method.md §4; sign convention f_int = dE/dx, §1):

    r(v') = M (v' - v) + dt (D v' + f_int(x + dt v') - f_ext) = 0,   x' = x + dt v'
    D = alpha M + beta K(x)      (Rayleigh, stiffness frozen at the start of the step)

r is the gradient of the incremental potential

    Phi(v') = 1/2 |v' - v|_M^2 + dt/2 v'^T D v' + E(x + dt v') - dt f_ext . v'

so Newton steps  (M + dt D + dt^2 K(x_k)) dv = -r(v_k)  are safeguarded by a backtracking
(Armijo) line search on Phi. Newton starts from v' = 0, which makes its first
iterate exactly the linearly implicit Euler step of the papers
(M + dt D + dt^2 K) v' = M v + dt (f_ext - f_int(x)); more iterations converge to
backward Euler. Unknowns are the free DOFs only.
"""
import time
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from ..linear_solver import NotPositiveDefinite, SparseSolver


@dataclass
class NewtonSettings:
    """max_iterations >= 1; tolerance on |r| relative to the first residual;
    line_search: backtrack on Phi; projection: 'auto' (PSD-project K only when the
    system is not positive definite), 'always' or 'never'."""

    max_iterations: int = 1
    tolerance: float = 1e-6
    line_search: bool = True
    projection: str = "auto"
    alpha: float = 0.0
    beta: float = 0.0


class BackwardEuler:
    """Steps a FEMForceModel; state x, v are (n_verts, 3) arrays."""

    def __init__(self, model, dt, settings=None, solver_backend="auto"):
        if not dt > 0:
            raise ValueError(f"dt must be positive, got {dt}")
        self.model = model
        self.dt = float(dt)
        self.settings = settings or NewtonSettings()
        self.solver = SparseSolver(solver_backend)
        self.stats = {}

    def _potential(self, v, v0, x0, D, f_ext_free, elastic=None):
        """Phi(v); elastic is E(x0 + dt v) when the caller already has it."""
        m = self.model
        dv = v - v0
        if elastic is None:
            elastic = m.energy(x0 + self.dt * m.expand(v))
        return 0.5 * dv @ (m.M @ dv) + 0.5 * self.dt * v @ (D @ v) + elastic - self.dt * f_ext_free @ v

    def _contact_rows(self, contact, x, v):
        """Constraint data of candidate contacts: (vertices, C (m, n_free) sparse CSR, phi,
        normals, which). C is sparse because candidates are many on fine meshes (a dense
        C of 1000 rows x 100K DOFs would be 800 MB)."""
        from ..contact.unilateral import find_contacts
        m, dt = self.model, self.dt
        ids = contact["vertices"]
        verts, which, phi, normals = find_contacts(contact["colliders"], x[ids], x[ids] + dt * v[ids],
                                                   contact["margin"])
        verts = ids[verts]
        dofs = m.pattern.free_dof[3 * verts[:, None] + np.arange(3)]          # (k, 3), -1 if pinned
        keep = (dofs >= 0).all(axis=1)
        verts, which, phi, normals, dofs = verts[keep], which[keep], phi[keep], normals[keep], dofs[keep]
        rows = [np.repeat(np.arange(len(verts)), 3)], [dofs.ravel()], [(dt * normals).ravel()]
        if contact.get("triangles") is not None:
            verts, phi, normals, which = self._triangle_rows(contact, x, rows, verts, phi, normals, which)
        C = sp.csr_matrix((np.concatenate(rows[2]), (np.concatenate(rows[0]), np.concatenate(rows[1]))),
                          shape=(len(verts), m.n_free))
        return verts, C, phi, normals, which

    def _triangle_rows(self, contact, x, rows, verts, phi, normals, which):
        """Append sphere-face contacts to the triplets `rows` (row, col, value lists): row
        dt n^T sum_i b_i (free DOFs of vertex i); the contact 'vertex' of such a row is
        reported as the triangle's nearest corner."""
        from ..contact.unilateral import find_triangle_contacts
        m, dt = self.model, self.dt
        ids = contact["vertices"]
        tris = contact["triangles"]
        t_idx, bary, t_which, t_phi, t_n = find_triangle_contacts(contact["colliders"], x[ids], tris,
                                                                  contact["margin"])
        if len(t_idx) == 0:
            return verts, phi, normals, which
        corners = ids[tris[t_idx]]                                           # (k, 3) global ids
        row = len(verts) + np.arange(len(t_idx))
        for a in range(3):
            d = m.pattern.free_dof[3 * corners[:, a, None] + np.arange(3)]
            ok = (d >= 0).all(axis=1)
            rows[0].append(np.repeat(row[ok], 3))
            rows[1].append(d[ok].ravel())
            rows[2].append((dt * bary[ok, a, None] * t_n[ok]).ravel())
        return (np.concatenate([verts, corners[np.arange(len(t_idx)), bary.argmax(axis=1)]]),
                np.concatenate([phi, t_phi]), np.concatenate([normals, t_n]), np.concatenate([which, t_which]))

    def step(self, x, v, f_ext, contact=None):
        """Advance one step. x, v, f_ext: (n_verts, 3). Returns (x', v').

        contact: None or {"colliders": [...], "vertices": candidate ids, "margin": m};
        the contact forces found are left in self.contact (see mdss_ros.contact.unilateral).
        """
        from ..contact.unilateral import contact_correction
        m, dt, s = self.model, self.dt, self.settings
        self.contact = None
        rows = self._contact_rows(contact, x, v) if contact else None
        if rows is not None and len(rows[0]) == 0:
            rows = None
        lam = np.zeros(0 if rows is None else len(rows[0]))
        t_asm = t_fac = t_sol = 0.0
        v0 = m.free(v)
        f_ext_free = m.free(f_ext)
        vk = np.zeros_like(v0)
        project = s.projection == "always"
        D = None
        r0_norm = None
        iterations = 0
        projected_any = project
        line_search_cuts = 0
        converged = False
        lcp = {}
        for k in range(s.max_iterations):
            t0 = time.perf_counter()
            xk = x + dt * m.expand(vk)
            e_k, f_int, K_data = m.tangent(xk, project=project)
            K = m.pattern.matrix(K_data)
            if D is None:
                D = s.alpha * m.M + s.beta * K
            r = m.M @ (vk - v0) + dt * (D @ vk + m.free(f_int) - f_ext_free)
            t_asm += time.perf_counter() - t0
            r_norm = float(np.linalg.norm(r - (rows[1].T @ lam if rows is not None else 0.0)))
            if r0_norm is None:
                r0_norm = r_norm
            if r_norm <= s.tolerance * max(r0_norm, 1e-300) and k > 0:
                converged = True
                break
            A = m.M + dt * D + dt * dt * K
            t0 = time.perf_counter()
            try:
                self.solver.factor(A)
            except NotPositiveDefinite:
                if s.projection == "never":
                    raise
                # Indefinite K (compression, inversion): the projected tangent keeps the
                # Newton direction a descent direction of Phi.
                project = projected_any = True
                _, _, K_data = m.tangent(xk, project=True)
                K = m.pattern.matrix(K_data)
                A = m.M + dt * D + dt * dt * K
                self.solver.factor(A)
            t1 = time.perf_counter()
            dv = self.solver.solve(-r)
            if rows is not None:
                # Contact: A dv = -r + C^T lam with C (vk + dv) + phi >= 0, lam >= 0.
                _, C, phi, _, _ = rows
                # Face and vertex rows can be dependent (a face point near a vertex): a
                # 1e-9 relative diagonal picks the least-norm split (unilateral.py).
                lam, corr, lcp = contact_correction(
                    self.solver.solve, C, C @ (vk + dv) + phi,
                    regularize=1e-9 if contact.get("triangles") is not None else 0.0)
                dv = dv + corr
                if k == 0:
                    # A body at rest pushed only by a collider has r0 = 0, which no residual
                    # meets: measure the tolerance against the contact forces' size instead.
                    r0_norm = max(r0_norm, float(np.linalg.norm(C.T @ lam)))
            t_fac += t1 - t0
            t_sol += time.perf_counter() - t1
            iterations += 1
            step_len = 1.0
            if s.line_search and s.max_iterations > 1 and rows is None:
                phi0 = self._potential(vk, v0, x, D, f_ext_free, elastic=e_k)
                slope = float(r @ dv)
                while step_len > 1e-4:
                    if self._potential(vk + step_len * dv, v0, x, D, f_ext_free) <= phi0 + 1e-4 * step_len * slope:
                        break
                    step_len *= 0.5
                    line_search_cuts += 1
            vk = vk + step_len * dv
            if s.max_iterations > 1 and float(np.linalg.norm(step_len * dv)) <= 1e-12 * (1.0 + float(np.linalg.norm(vk))):
                converged = True
                break
        v_new = m.expand(vk)
        x_new = x + dt * v_new
        if rows is not None:
            self.contact = contact_record(contact["colliders"], rows, lam, x_new)
        self.stats = {
            "newton_iterations": iterations,
            "converged": bool(converged or s.max_iterations == 1),
            "residual": r_norm / max(r0_norm, 1e-300) if r0_norm else 0.0,
            "projected": bool(projected_any),
            "line_search_cuts": line_search_cuts,
            "assembly_ms": 1e3 * t_asm,
            "factor_ms": 1e3 * t_fac,
            "solve_ms": 1e3 * t_sol,
        }
        if lcp:
            self.stats.update(contact_rows=lcp["rows"], contact_working_set=lcp["working_set"])
        return x_new, v_new


def contact_record(colliders, rows, lam, x_new):
    """What a step reports of its contacts: the active rows (lam > 0) of the candidates
    rows = (vertices, C, phi, normals, which) with their forces lam n, points and depths
    at the end-of-step positions x_new (n_verts, 3). Loops over colliders, not vertices."""
    verts, _, _, normals, which = rows
    depth = np.zeros(len(verts))
    for c_idx, col in enumerate(colliders):
        sel = which == c_idx
        if sel.any():
            depth[sel] = np.maximum(-col.signed_distance(x_new[verts[sel]])[0], 0.0)
    active = lam > 0
    return {"vertices": verts[active], "normals": normals[active], "which": which[active],
            "forces": lam[active, None] * normals[active], "points": x_new[verts[active]],
            "depth": depth[active], "candidates": int(len(verts))}
