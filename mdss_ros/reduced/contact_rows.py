"""Contact constraint rows in generalised velocities (docs/method.md §14, §14.1).

For contact l at a surface point x with collider normal n (a vertex, or a face point as
its corners' rows weighted by barycentric coordinates):

    C[l] = dt n^T J_x        (m, n_gen),    C Q' + phi_eff >= 0,   lam >= 0,   lam (C Q' + phi_eff) = 0

J_x = [R U_x, I3, -(x - c)x] on its domain's modal and frame columns, or I3 on a
full-space vertex's columns. With friction each contact has three rows (n, t1, t2) and the
Coulomb problem of contact/friction.py is solved on them. Each row's entries when every
vertex is in a subspace domain (sparse_rows.ContactRowEntries), CSR when full-space
domains make n_gen large.
"""

import numpy as np
import scipy.sparse as sp

from ..contact.unilateral import member
from ..rotations import cross
from .residual_compliance import limit_dent
from .sparse_rows import ContactRowEntries


def _kept_solves(resolve):
    """resolve(B) (A X = B, B (n, k)) answering a right-hand side it has seen before with
    the same X (not written into by the contact solvers) instead of solving again."""
    kept = {}

    def solve(B):
        key = (B.shape, B.tobytes())
        if key not in kept:
            kept[key] = resolve(B)
        return kept[key]
    return solve


class ContactRows:
    """Contact rows of the reduced model and the correction of a Newton step for contact. Mixed into
    reduced_model.ReducedModel, whose build provides the attributes it reads."""

    def _contact_rows(self, contact, gm, dt):
        """Candidate contacts of the surface: (vertices, C (m, n_gen), phi_eff (m,), normals, which,
        friction), or None. C = dt n^T J_l; under a co-rotating step the rigid part of the
        vertex velocity, V + W x (x - C), is a constant folded into phi_eff. friction is
        None (every collider frictionless) or (C3 (3m, n_gen) rows n, t1, t2 per contact,
        g3 (3m,) their constant part (phi_eff, minus the collider's tangential displacement,
        the rigid velocity's share), mu (m,) static or kinetic by the last step's slip,
        tangents (m, 2, 3), rigid3 (3m,) the rigid share alone, the last step's forces as
        a first guess (m, 3) or None), as in BackwardEuler._contact_rows (friction.py)."""
        from ..contact.friction import coefficients, collider_slip, effective_mu, tangent_basis, warm_start
        from ..contact.unilateral import find_contacts, find_triangle_contacts
        ids = contact["vertices"]
        x = self.positions_of(ids)                  # with the last step's dent (residual compliance)
        rows, which, phi, normals = find_contacts(contact["colliders"], x, x, contact["margin"])
        # Sphere-face contacts enter as weighted copies of their three corners' rows.
        weights = np.ones(len(rows))
        group = np.arange(len(rows))
        n_all = len(self.vertex_domain)
        key = ids[rows] + n_all * which                 # a row's identity from step to step
        if contact.get("triangles") is not None:
            t_idx, bary, t_which, t_phi, t_n = find_triangle_contacts(contact["colliders"], x,
                                                                      contact["triangles"], contact["margin"])
            if len(t_idx):
                base = len(rows)
                rows = np.concatenate([rows, contact["triangles"][t_idx].ravel()])
                weights = np.concatenate([weights, bary.ravel()])
                group = np.concatenate([group, base + np.repeat(np.arange(len(t_idx)), 3)])
                which = np.concatenate([which, np.repeat(t_which, 3)])
                phi = np.concatenate([phi, t_phi])
                normals = np.concatenate([normals, np.repeat(t_n, 3, axis=0)])
                # Face keys follow every vertex key: n_all n_col + t n_col + c for triangle t, collider c.
                n_col = len(contact["colliders"])
                key = np.concatenate([key, n_all * n_col + t_idx * n_col + t_which])
        if len(rows) == 0:
            return None
        rough = coefficients(contact, which) is not None    # else frictionless: one row per contact
        verts = ids[rows]
        xv = x[rows]
        # group is non-decreasing (vertex rows, then three corners per face): one contact per run.
        # Without faces every row is a contact of its own (the corner gathers below are skipped).
        one_corner = len(rows) == len(phi)                  # a face adds three rows and one phi
        starts = group if one_corner else np.flatnonzero(np.r_[True, group[1:] != group[:-1]])
        tangents = None
        if not rough:
            dirs = normals[:, None, :] * weights[:, None, None]
            C = self._rows_along(dirs, verts, xv, starts, dt)
        else:
            # Rows along n, t1, t2 at once; the normal rows are every third of them.
            tangents = tangent_basis(normals)                                   # (corner rows, 2, 3)
            dirs = np.concatenate([normals[:, None, :], tangents], axis=1) * weights[:, None, None]
            C3 = self._rows_along(dirs, verts, xv, starts, dt)
            C = (C3.take(np.arange(0, len(C3), 3)) if isinstance(C3, ContactRowEntries)
                 else C3[0::3] if sp.issparse(C3) else np.ascontiguousarray(C3[0::3]))
        # The residual compliance's rows (residual_compliance.py): the same directions on
        # the candidate vertices' dent, in their domains' rest axes.
        compliance = None
        if self.compliance is not None:
            row_of = np.searchsorted(starts, np.arange(len(verts)), side="right") - 1
            compliance = self.compliance.rows(dirs, verts, row_of, len(starts), self.frames.R)
        # Only compared with a threshold below: einsum needs no (m, n_gen) temporary as
        # np.linalg.norm does (a third faster on the caterpillar's 800 floor rows).
        norms = (np.sqrt(np.asarray(C.multiply(C).sum(axis=1)).ravel()) if sp.issparse(C)
                 else C.norms() if isinstance(C, ContactRowEntries) else np.sqrt(np.einsum("ij,ij->i", C, C)))
        at = rows                                                               # their rows of ids
        if not one_corner:
            verts, which, normals, xv = verts[starts], which[starts], normals[starts], xv[starts]  # a corner per contact
            at = rows[starts]
            tangents = None if tangents is None else tangents[starts]
        # Vertices that cannot move (pins: zero rows of U in a fixed domain) cannot be
        # pushed out; their constraints would be infeasible, so they are not contacts.
        movable = norms > 1e-12 * max(float(norms.max()), 1e-300)
        if not movable.all():
            verts, phi, normals, which, xv = verts[movable], phi[movable], normals[movable], which[movable], xv[movable]
            C = C.take(np.flatnonzero(movable)) if isinstance(C, ContactRowEntries) else C[movable]
            key, at = key[movable], at[movable]
            if tangents is not None:
                tangents = tangents[movable]
                keep3 = (3 * np.flatnonzero(movable)[:, None] + np.arange(3)).ravel()
                C3 = C3.take(keep3) if isinstance(C3, ContactRowEntries) else C3[keep3]
            if compliance is not None:
                r = 1 if tangents is None else 3
                compliance = compliance.take((r * np.flatnonzero(movable)[:, None] + np.arange(r)).ravel())
                if not compliance.G.any():                 # no row left on a candidate
                    compliance = None
            if len(verts) == 0:
                return None
        phi_eff = phi.copy()
        self._contact_rigid = np.zeros(len(phi))          # dt n . (rigid velocity) per row
        if gm is not None:
            Cg, Vg, Wg = gm[:3]
            rigid_v = Vg + cross(Wg, xv - Cg)
            self._contact_rigid = dt * np.einsum("li,li->l", normals, rigid_v)
            phi_eff += self._contact_rigid
        self._contact_row_keys = key
        self._contact_at = at
        self._contact_compliance = compliance
        self._dent_cap = contact["margin"]
        # A contact point is at its reduced position plus its dent C_res G^T lam, and the gaps
        # and normals above are those of that point under the last step's forces; over the
        # step it moves by C Q' and by the change of its dent. The new dent enters through
        # the compliance in the solve, so the last one comes off every row here.
        dent_shift = None
        if self._contact_compliance is not None:
            dent_shift = self._contact_compliance.shift(self._dent).reshape(len(verts), -1)
            phi_eff -= dent_shift[:, 0]
        fric = None
        if rough:
            n_col = len(contact["colliders"])
            keys = verts * n_col + which
            mu = effective_mu(*coefficients(contact, which), keys, self.contact, n_col)
            g3 = np.zeros((len(verts), 3))
            g3[:, 0] = phi_eff
            g3[:, 1:] = collider_slip(contact, which, xv, tangents)
            rigid3 = np.zeros((len(verts), 3))                 # dt (n, t1, t2) . (rigid velocity)
            rigid3[:, 0] = self._contact_rigid
            if gm is not None:
                rigid3[:, 1:] = dt * np.einsum("lij,lj->li", tangents, rigid_v)
                g3[:, 1:] += rigid3[:, 1:]
            if dent_shift is not None:
                g3[:, 1:] -= dent_shift[:, 1:]
            fric = (C3, g3.ravel(), mu, tangents, rigid3.ravel(), warm_start(self.contact, keys, tangents, n_col))
        return verts, C, phi_eff, normals, which, fric

    def _rows_along(self, dirs, verts, xv, starts, dt):
        """Constraint rows (m r, n_gen), row l r + j = dt d^T J at contact l along its j-th
        direction: dirs (k, r, 3) per corner row (weighted: a face point's corners carry
        their barycentric weights), verts (k,) vertex ids, xv (k, 3) their positions, starts
        (m,) the first corner row of each contact (corner rows of a contact are adjacent).
        Without full-space domains as sparse_rows.ContactRowEntries (each row's 26 or so
        entries instead of n_gen columns), else CSR (n_gen large, rows sparse)."""
        L = self.layout
        k, r = dirs.shape[:2]
        vrow = L.vertex_row[verts]
        m = len(starts)
        if not self.F:
            row_of = np.arange(k) if m == k else np.searchsorted(starts, np.arange(k), side="right") - 1
            return ContactRowEntries.build(dirs, vrow, L, self.frames.R, self.frames.c, xv, self._frame_cols,
                                           row_of, m, dt, self.n_gen)
        blocks = []                                          # (corner rows, direction, columns, values)
        sel = np.flatnonzero(vrow >= 0)
        if sel.size:
            # d^T R U_l = (R^T d)^T U_l per corner, into its domain's modal columns (padding
            # columns dropped); a movable domain adds [d, (x - c) x d] on its frame's columns.
            dom = L.row_domain[vrow[sel]]
            d = dirs[sel]                                                              # (s, r, 3)
            vals = np.einsum("lri,lib->lrb", np.einsum("lrj,lji->lri", d, self.frames.R[dom]), L.U[vrow[sel]])
            ok = np.broadcast_to(L.mask[dom][:, None, :], vals.shape)
            shape = vals.shape
            blocks.append((np.broadcast_to(sel[:, None, None], shape)[ok],
                           np.broadcast_to(np.arange(r)[None, :, None], shape)[ok],
                           np.broadcast_to(L.q_index[dom][:, None, :], shape)[ok], vals[ok]))
            mover = np.full(L.D, -1, dtype=np.int64)
            mover[L.movers] = np.arange(len(L.movers))
            mv = mover[dom] >= 0
            if mv.any():
                cols = np.hstack([L.lin_index, L.ang_index])[mover[dom[mv]]]          # (s, 6)
                arm = (xv[sel[mv]] - self.frames.c[dom[mv]])[:, None, :]
                frame_vals = np.concatenate([d[mv], cross(np.broadcast_to(arm, d[mv].shape), d[mv])], axis=2)
                shape = frame_vals.shape                                               # (s, r, 6)
                blocks.append((np.broadcast_to(sel[mv][:, None, None], shape).ravel(),
                               np.broadcast_to(np.arange(r)[None, :, None], shape).ravel(),
                               np.broadcast_to(cols[:, None, :], shape).ravel(), frame_vals.ravel()))
        full = np.flatnonzero(vrow < 0)
        if full.size:
            dofs = self.full_dof_of_vertex[verts[full]]
            okf = dofs >= 0
            f_rows = full[okf]
            shape = (len(f_rows), r, 3)
            blocks.append((np.broadcast_to(f_rows[:, None, None], shape).ravel(),
                           np.broadcast_to(np.arange(r)[None, :, None], shape).ravel(),
                           np.broadcast_to((self.S + 3 * dofs[okf, None] + np.arange(3))[:, None, :], shape).ravel(),
                           dirs[f_rows].ravel()))
        # A full-space domain makes n_gen large and its rows 3-sparse: C as CSR
        # (duplicates, a face's corners, are summed on construction).
        row_of = np.searchsorted(starts, np.arange(k), side="right") - 1
        r_idx = row_of[np.concatenate([b[0] for b in blocks])] * r + np.concatenate([b[1] for b in blocks])
        c_idx = np.concatenate([b[2] for b in blocks])
        values = np.concatenate([b[3] for b in blocks])
        return sp.csr_matrix((dt * values, (r_idx, c_idx)), shape=(m * r, self.n_gen))

    def _contact_solve(self, rows, Q, dQ):
        """Correct a Newton step for contact: C (Q + dQ') + phi >= 0 via the LCP (unilateral.py),
        or with friction the Coulomb problem on three rows per contact (friction.py).
        Returns (dQ + correction, lam (m,) or (m, 3))."""
        from ..contact.friction import frictional_correction
        from ..contact.unilateral import contact_correction
        verts, C, phi, _, which, friction = rows
        # The LCP's first guess: the rows active in the last Newton iteration, or in the last
        # two steps (a resting or pressed body keeps most of its contacts, and a coarse patch
        # under a held collider can swap its load between vertex and face rows every other
        # step). It saves solves and pivots only; the answer does not depend on it.
        keys = self._contact_row_keys
        history = self._contact_history                          # active keys per step, newest last
        same_step = self._contact_rows_seen is rows
        lam_n = None if not same_step else (self._contact_lam if friction is None else self._contact_lam[:, 0])
        if same_step:
            hint = lam_n > 0
        else:
            hint = member(keys, np.concatenate(history)) if history else None
        # limit_dent solves the same contact again under a smaller compliance, and its rounds
        # ask the step's matrix for the same rows' solutions: they are kept for the step.
        resolve = self._resolve if self._contact_compliance is None else _kept_solves(self._resolve)
        # Rows through a few modes per domain are often dependent: regularise (unilateral.py).
        if friction is None:
            g = C @ (Q + dQ) + phi

            def solve(compliance):
                return contact_correction(resolve, C, g, regularize=1e-9, hint=hint, compliance=compliance)
        else:
            C3, g3, mu = friction[:3]
            guess = self._contact_lam if same_step else friction[5]
            g = C3 @ (Q + dQ) + g3

            def solve(compliance):
                return frictional_correction(resolve, C3, g, mu, regularize=1e-9,
                                             hint=hint if guess is None else None, lam_guess=guess,
                                             compliance=compliance)
        if self._contact_compliance is None:
            lam, corr, info = solve(None)
        else:
            (lam, corr, info), self._contact_compliance = limit_dent(solve, self._contact_compliance.scaled(1.0),
                                                                    self._dent_cap)
        active = lam > 0 if friction is None else lam[:, 0] > 0
        self._contact_info = info
        self._contact_history = (history[:-1] if same_step else history[-1:]) + [keys[active]]
        self._contact_lam, self._contact_rows_seen = lam, rows
        return dQ + corr, lam

    @staticmethod
    def _contact_force(rows, lam):
        """C^T lam (n_gen,): the contact forces as generalised forces, frictional or not."""
        if rows[5] is not None:
            C3 = rows[5][0]
            return C3.rmatvec(lam.ravel()) if isinstance(C3, ContactRowEntries) else C3.T @ lam.ravel()
        C = rows[1]
        return C.rmatvec(lam) if isinstance(C, ContactRowEntries) else C.T @ lam
