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

from ..contact.unilateral import HalfSweepSolves, find_triangle_contacts
from ..linear_solver import NotPositiveDefinite, SparseSolver


@dataclass
class NewtonSettings:
    """max_iterations >= 1; tolerance on |r| relative to the first residual;
    line_search: backtrack on Phi; projection: 'auto' (PSD-project K only when the
    system is not positive definite), 'always' or 'never'; projection_memory (auto): start
    projected after an indefinite step (PROBE_EVERY) and damp a projected step with the
    projected K. False is the policy before it (the exact tangent first in every step, the
    damping's K the exact one), which the precompute's training keeps (training.py)."""

    max_iterations: int = 1
    tolerance: float = 1e-6
    line_search: bool = True
    projection: str = "auto"
    projection_memory: bool = True
    alpha: float = 0.0
    beta: float = 0.0


#: projection "auto": after a step whose step matrix was not positive definite, the next
#: steps start from the projected tangent, and every PROBE_EVERY-th of such a run tries the
#: exact one first again. A squeezed body stays squeezed: grasp_lift's unprojected
#: factorisation failed in 181 of its first 215 steps, and in every step after a failed
#: one (180 of 180), where that attempt (tangent and failed factorisation) was 1.6 of the
#: 4.5 ms its tangents, factorisations and solve took (medians under load;
#: docs/performance.md, Session 25).
PROBE_EVERY = 8


class BackwardEuler:
    """Steps a FEMForceModel; state x, v are (n_verts, 3) arrays. projected_run: the
    consecutive steps that used the projected tangent (part of the model's state)."""

    def __init__(self, model, dt, settings=None, solver_backend="auto"):
        if not dt > 0:
            raise ValueError(f"dt must be positive, got {dt}")
        self.model = model
        self.dt = float(dt)
        self.settings = settings or NewtonSettings()
        # A step's matrix is well conditioned: no iterative refinement of its solves (linear_solver.py).
        self.solver = SparseSolver(solver_backend, refine=False)
        self.stats = {}
        self.projected_run = 0

    def _potential(self, v, v0, x0, D, f_ext_free, elastic=None):
        """Phi(v); elastic is E(x0 + dt v) when the caller already has it."""
        m = self.model
        dv = v - v0
        if elastic is None:
            elastic = m.energy(x0 + self.dt * m.expand(v))
        return 0.5 * dv @ (m.M @ dv) + 0.5 * self.dt * v @ (D @ v) + elastic - self.dt * f_ext_free @ v

    def _contact_rows(self, contact, x, v):
        """Constraint data of candidate contacts: (vertices, C (m, n_free) sparse CSR, phi,
        normals, which, friction). C is sparse because candidates are many on fine meshes
        (a dense C of 1000 rows x 100K DOFs would be 800 MB). friction is None, or (C3
        (3m, n_free) with rows n, t1, t2 per contact, g3 (3m,) the rows' constant part:
        phi and minus the collider's own tangential displacement, mu (m,) static or
        kinetic by the last step's slip (contact["previous"]), tangents (m, 2, 3), the last
        step's forces as a first guess (m, 3) or None) when a collider has a friction
        coefficient (contact/friction.py)."""
        from ..contact.friction import coefficients, collider_slip, effective_mu, tangent_basis, warm_start
        from ..contact.unilateral import find_contacts
        m, dt = self.model, self.dt
        emb = getattr(m, "embedding", None)
        # Mesh vertices that are not the unknowns (meshless lattice nodes) are moved by the
        # nodes: contacts are found at the vertices, and act on their nodes.
        P, Pv = (x, v) if emb is None else (emb.apply(x), emb.apply(v))
        ids = contact["vertices"]
        verts, which, phi, normals = find_contacts(contact["colliders"], P[ids], P[ids] + dt * Pv[ids],
                                                   contact["margin"])
        verts = ids[verts]
        # A contact is a weighted point of up to three vertices: a vertex (weights 1, 0, 0)
        # or a sphere-face point (barycentric weights of its triangle's corners).
        corners = np.repeat(verts[:, None], 3, axis=1)
        weights = np.zeros((len(verts), 3))
        weights[:, 0] = 1.0
        if contact.get("triangles") is not None:
            t_idx, bary, t_which, t_phi, t_n = find_triangle_contacts(contact["colliders"], P[ids],
                                                                      contact["triangles"], contact["margin"])
            if len(t_idx):
                t_corners = ids[contact["triangles"][t_idx]]                 # (k, 3) global ids
                # A face contact is reported at its triangle's nearest corner.
                verts = np.concatenate([verts, t_corners[np.arange(len(t_idx)), bary.argmax(axis=1)]])
                which, phi = np.concatenate([which, t_which]), np.concatenate([phi, t_phi])
                normals = np.concatenate([normals, t_n])
                corners, weights = np.concatenate([corners, t_corners]), np.concatenate([weights, bary])
        if emb is not None:
            corners, weights = emb.corners(corners, weights)
        # A point on pinned vertices (nodes) alone cannot be pushed out: its constraint
        # would be infeasible.
        keep = ((m.pattern.free_dof[3 * corners] >= 0) & (weights != 0.0)).any(axis=1)
        verts, which, phi, normals, corners, weights = (a[keep] for a in (verts, which, phi, normals, corners,
                                                                          weights))
        friction = None
        mu = coefficients(contact, which)
        if mu is not None and len(verts):
            tangents = tangent_basis(normals)
            C3 = self._rows_along(np.concatenate([normals[:, None, :], tangents], axis=1), corners, weights)
            # The normal rows are every third row of C3, the same entries as
            # _rows_along(normals) gives: one build of the rows instead of two.
            C = C3[0::3]
            g3 = np.zeros((len(verts), 3))
            g3[:, 0] = phi
            g3[:, 1:] = collider_slip(contact, which, P[verts], tangents)
            n_col = len(contact["colliders"])
            keys, previous = verts * n_col + which, contact.get("previous")
            friction = (C3, g3.ravel(), effective_mu(*mu, keys, previous, n_col), tangents,
                        warm_start(previous, keys, tangents, n_col))
        else:
            C = self._rows_along(normals[:, None, :], corners, weights)
        return verts, C, phi, normals, which, friction

    def points(self, x):
        """The mesh vertices' positions (n_verts, 3) from the unknowns' x: x itself, or the
        vertices the meshless lattice's nodes move (the force model's embedding)."""
        emb = getattr(self.model, "embedding", None)
        return x if emb is None else emb.apply(x)

    def _rows_along(self, directions, corners, weights):
        """Rows (k r, n_free) CSR, row l r + j = dt d_lj^T sum_a w_la (DOFs of vertex a)
        for directions (k, r, 3), corners (k, c) vertex (node) ids, weights (k, c); pinned
        DOFs and zero weights are left out."""
        m, dt = self.model, self.dt
        k, r = directions.shape[:2]
        c = corners.shape[1]
        dofs = m.pattern.free_dof[3 * corners[:, :, None] + np.arange(3)]         # (k, c, 3) corner, axis
        rows = np.broadcast_to((np.arange(k)[:, None] * r + np.arange(r))[:, :, None, None], (k, r, c, 3))
        cols = np.broadcast_to(dofs[:, None], (k, r, c, 3))
        vals = dt * weights[:, None, :, None] * directions[:, :, None, :]
        ok = (cols >= 0) & (vals != 0.0)
        return sp.csr_matrix((vals[ok], (rows[ok], cols[ok])), shape=(k * r, m.n_free))

    @staticmethod
    def _contact_force(rows, lam):
        """C^T lam: the contact forces' generalised force (n_free,), frictional or not."""
        friction = rows[5]
        return rows[1].T @ lam if friction is None else friction[0].T @ lam.ravel()

    def step(self, x, v, f_ext, contact=None):
        """Advance one step. x, v, f_ext: (n_verts, 3). Returns (x', v').

        contact: None or {"colliders": [...], "vertices": candidate ids, "margin": m};
        the contact forces found are left in self.contact (see mdss_ros.contact.unilateral).
        """
        from ..contact.friction import frictional_correction
        from ..contact.unilateral import contact_correction
        m, dt, s = self.model, self.dt, self.settings
        self.contact = None
        rows = self._contact_rows(contact, x, v) if contact else None
        if rows is not None and len(rows[0]) == 0:
            rows = None
        lam = np.zeros(0 if rows is None else (len(rows[0]), 3) if rows[5] is not None else len(rows[0]))
        t_asm = t_fac = t_sol = 0.0
        v0 = m.free(v)
        f_ext_free = m.free(f_ext)
        vk = np.zeros_like(v0)
        # auto: the exact tangent first, unless the last steps needed the projected one
        # (PROBE_EVERY).
        memory = s.projection == "auto" and s.projection_memory
        project = s.projection == "always" or (memory and self.projected_run % PROBE_EVERY != 0)
        started_projected = project and memory
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
            # M, D, K and A share K's pattern (M's data is laid on it: force_model.py), so
            # they are summed as data arrays, in the order scipy's sparse sums used. Those
            # also dropped the entries that summed to zero, so A's pattern could change
            # from step to step (a new PARDISO analysis each time), and they took 341 / 430
            # us for D and A on grasp_lift's 375 DOFs against 114 / 141 us (min / median of
            # 500; session 23), where A is formed twice a step (the projected retry).
            if D is None:
                D_data = s.alpha * m.M_data + s.beta * K_data
                D = m.pattern.matrix(D_data)
            r = m.M @ (vk - v0) + dt * (D @ vk + m.free(f_int) - f_ext_free)
            t_asm += time.perf_counter() - t0
            r_norm = float(np.linalg.norm(r - (self._contact_force(rows, lam) if rows is not None else 0.0)))
            if r0_norm is None:
                r0_norm = r_norm
            if r_norm <= s.tolerance * max(r0_norm, 1e-300) and k > 0:
                converged = True
                break
            A = m.pattern.matrix(m.M_data + dt * D_data + dt * dt * K_data)
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
                if k == 0 and memory:
                    # The damping's stiffness is the first iterate's tangent, projected too:
                    # PSD damping, and the step projection: always takes (and a projected
                    # start). r does not change: D multiplies vk = 0 at the first iterate.
                    D_data = s.alpha * m.M_data + s.beta * K_data
                    D = m.pattern.matrix(D_data)
                A = m.pattern.matrix(m.M_data + dt * D_data + dt * dt * K_data)
                self.solver.factor(A)
            t1 = time.perf_counter()
            dv = self.solver.solve(-r)
            if rows is not None:
                # The working set's columns by forward sweeps of PARDISO's factor, the
                # Delassus block as their Gram matrix (unilateral.HalfSweepSolves): half
                # the sweeps of a solve per row.
                solves = HalfSweepSolves(self.solver) if self.solver.backend == "pardiso" else self.solver.solve
                # Contact: A dv = -r + C^T lam with C (vk + dv) + phi >= 0, lam >= 0.
                _, C, phi, _, _, friction = rows
                # Face and vertex rows can be dependent (a face point near a vertex): a
                # 1e-9 relative diagonal picks the least-norm split (unilateral.py).
                regularize = 1e-9 if contact.get("triangles") is not None else 0.0
                if friction is None:
                    lam, corr, lcp = contact_correction(solves, C, C @ (vk + dv) + phi, regularize=regularize)
                else:
                    # The same with Coulomb friction: three rows per contact (friction.py).
                    C3, g3, mu, _, last = friction
                    lam, corr, lcp = frictional_correction(solves, C3, C3 @ (vk + dv) + g3, mu,
                                                           regularize=regularize, lam_guess=lam if k else last)
                dv = dv + corr
                if k == 0:
                    # A body at rest pushed only by a collider has r0 = 0, which no residual
                    # meets: measure the tolerance against the contact forces' size instead.
                    r0_norm = max(r0_norm, float(np.linalg.norm(self._contact_force(rows, lam))))
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
        if memory:
            self.projected_run = self.projected_run + 1 if projected_any else 0
        v_new = m.expand(vk)
        x_new = x + dt * v_new
        if rows is not None:
            self.contact = contact_record(contact["colliders"], rows, lam, self.points(x_new), lcp.get("w"), dt)
        self.stats = {
            "newton_iterations": iterations,
            "converged": bool(converged or s.max_iterations == 1),
            "residual": r_norm / max(r0_norm, 1e-300) if r0_norm else 0.0,
            "projected": bool(projected_any),
            "projected_start": bool(started_projected),
            "line_search_cuts": line_search_cuts,
            "assembly_ms": 1e3 * t_asm,
            "factor_ms": 1e3 * t_fac,
            "solve_ms": 1e3 * t_sol,
        }
        if lcp:
            self.stats.update(contact_stats(lcp))
        return x_new, v_new


def contact_stats(info):
    """Step stats of a contact solve (unilateral.contact_correction or
    friction.frictional_correction): candidates, working set, and with friction the
    contacts that stick and slip and whether the Coulomb solve reached its tolerance."""
    out = {"contact_rows": info["rows"], "contact_working_set": info["working_set"]}
    if "stick" in info:
        out.update(contact_stick=info["stick"], contact_slip=info["slip"],
                   contact_unconverged=bool(info.get("unconverged", False)))
    return out


def contact_record(colliders, rows, lam, x_new, w=None, dt=None):
    """What a step reports of its contacts: the active rows (lam_n > 0) of the candidates
    rows = (vertices, C, phi, normals, which, friction) with their forces (normal lam_n n
    plus friction lam_t1 t1 + lam_t2 t2), points and depths at the end-of-step positions
    x_new (n_verts, 3); lam (m,) or, with friction, (m, 3) with w (m, 3) the rows' gap and
    slip after the step (for the slip speed). Loops over colliders, not vertices."""
    verts, _, _, normals, which, friction = rows
    depth = np.zeros(len(verts))
    for c_idx, col in enumerate(colliders):
        sel = which == c_idx
        if sel.any():
            depth[sel] = np.maximum(-col.signed_distance(x_new[verts[sel]])[0], 0.0)
    return contact_forces(verts, normals, which, lam, None if friction is None else friction[3],
                          x_new[verts], depth, w, dt)


def contact_forces(verts, normals, which, lam, tangents, points, depth, w=None, dt=None):
    """The contact record of the active contacts (lam_n > 0): vertices, normals, which,
    forces (normal plus friction, on the body), normal_force (k,) and friction (k, 3)
    apart, points and depth (the given arrays are over all candidates); with friction
    also slip_speed (k,), |w_t| / dt (m/s), which the next step's static or kinetic
    choice reads (friction.effective_mu)."""
    lam = np.asarray(lam)
    lam_n = lam if lam.ndim == 1 else lam[:, 0]
    active = lam_n > 0
    normal = lam_n[active, None] * normals[active]
    friction = (np.zeros_like(normal) if tangents is None
                else np.einsum("ki,kij->kj", lam[active, 1:], tangents[active]))
    record = {"vertices": verts[active], "normals": normals[active], "which": which[active],
              "forces": normal + friction, "normal_force": lam_n[active], "friction": friction,
              "points": points[active], "depth": depth[active], "candidates": int(len(verts))}
    if w is not None:
        record["slip_speed"] = np.linalg.norm(w[active, 1:], axis=1) / dt
    return record
