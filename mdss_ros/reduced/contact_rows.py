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

# Imported at module level: contact_rows already imports these modules, and a function's
# import statement costs microseconds a call on a step of a few hundred.
from ..contact.friction import (STICTION_SPEED, FrictionRows, coefficients, collider_slip, effective_mu,
                                frictional_correction, moving_colliders, previous_match, rows_of, tangent_basis,
                                warm_start)
from ..contact.unilateral import (HalfSweepSolves, Solves, contact_correction, find_contacts,
                                  find_triangle_contacts, member)
from ..rotations import cross
from .frictional_kernel import compiled_correction, vertex_rows_kernel, warm_kernel
from .residual_compliance import limit_dent
from .sparse_rows import ContactRowEntries


class CholeskySolves(HalfSweepSolves):
    """unilateral.HalfSweepSolves on the step's block Cholesky factor A = P^T L L^T P
    (block_cholesky.BlockCholesky), whose backward sweep takes (S, m) columns. Y = A^-1
    C_r^T took a forward and a backward sweep per row: 105 rows of three per contact at the
    caterpillar's friction at rest."""

    def correction(self, cols, lam):
        return self.factor.backward((cols @ lam)[:, None], overwrite=True)[:, 0]


class FrictionalRows:
    """A reduced body's frictional contact rows (n, t1, t2 per contact; docs/method.md
    §14.1) for one step's m candidates, whose tangential rows are built for the contacts
    that ask for them: the Coulomb solve (friction.frictional_correction) reads every
    contact's normal row, for its gap, but the tangential rows of its working set only,
    a few dozen of the caterpillar's 814 floor candidates. Building three rows for every
    candidate, with their tangents and collider slips, took the caterpillar's rows at rest
    0.64 ms against 0.48 now (min of 300 calls, docs/performance.md "Session 19").

    C (m, n_gen) the normal rows (sparse_rows.ContactRowEntries, or CSR beside full-space
    domains), g_n (m,) their constant part (phi_eff); mu (m,); corners: (vertex ids,
    positions, normals, weights) of the corner rows and each contact's first and end
    corner row (m,) (a face point has three); slip_at: (contact spec, which (m,), points (m,
    3)), for the collider's own slip; dt; rigid_v (m, 3) the rigid velocity a co-rotating
    step folds into the rows, or None; dent_shift (m, 3) the last dent's share of each
    row, or None. Built contacts have their tangents (m, 2, 3), their rows' constant part
    g3 (m, 3) (phi_eff; minus the collider's tangential displacement, plus the rigid
    velocity's share, minus the dent's) and rigid3 (m, 3) the rigid share alone; guess
    (m, 3) or None is the last step's forces."""

    def __init__(self, model, C, g_n, mu, corners, slip_at, dt, rigid_v, dent_shift):
        self.model, self.C, self.mu, self.corners, self.slip_at, self.dt = model, C, mu, corners, slip_at, dt
        self.rigid_v, self.dent_shift = rigid_v, dent_shift
        m = len(g_n)
        self.g_n = g_n
        self.slot = np.full(m, -1, dtype=np.int64)      # a contact's place in the built rows
        self.n_built = 0
        self.rows3 = None                               # the built contacts' rows, 3 per contact
        # Colliders whose own motion over the step drags a contact (collider_slip): none on
        # a fixed floor, whose contacts then skip that pass.
        self.moving = moving_colliders(slip_at[0])
        self.tangents = np.zeros((m, 2, 3))
        self.g3 = np.zeros((m, 3))
        self.g3[:, 0] = g_n
        self.rigid3 = np.zeros((m, 3))
        self.rigid3[:, 0] = model._contact_rigid
        self.guess = None

    @classmethod
    def built(cls, model, C, mu, slip_at, dt, rows3, tangents, g3, rigid3):
        """Rows with every contact's three rows already built (ContactRows._vertex_friction_rows):
        rows3 the (3m, n_gen) rows in contact order, tangents (m, 2, 3), g3 (m, 3) their
        constant parts without the colliders' own slip, which is added here, rigid3 (m, 3)."""
        self = cls.__new__(cls)
        m = len(g3)
        self.model, self.C, self.mu, self.slip_at, self.dt = model, C, mu, slip_at, dt
        self.rigid_v = self.dent_shift = None                  # read by ensure() only, which has nothing to build
        self.g_n = g3[:, 0].copy()
        self.corners = None
        self.slot = np.arange(m, dtype=np.int64)
        self.n_built = m
        self.rows3, self.tangents, self.g3, self.rigid3 = rows3, tangents, g3, rigid3
        self.moving = moving_colliders(slip_at[0])
        if self.moving:
            spec, which, points = slip_at
            g3[:, 1:] = collider_slip(spec, which, points, tangents, self.moving) + rigid3[:, 1:]
        self.guess = None
        return self

    def ensure(self, contacts, tangents=None):
        """Build the rows of those of contacts (k,) (distinct indices) not yet built;
        tangents (m, 2, 3): every contact's, when already had (else friction.tangent_basis
        of their normals)."""
        new = contacts[self.slot[contacts] < 0]
        if new.size == 0:
            return
        verts, xv, normals, weights, first, end = self.corners
        t = tangent_basis(normals[first[new]]) if tangents is None else tangents[new]
        if len(verts) == len(self.g_n):            # one corner row per contact (no face contacts)
            corner, starts = first[new], np.arange(new.size)
            # Every weight is 1 here (a face would add corner rows), so none is multiplied.
            dirs = np.concatenate([normals[corner][:, None, :], t], axis=1)
        else:
            counts = end[new] - first[new]
            starts = np.cumsum(counts) - counts
            corner = np.repeat(first[new] - starts, counts) + np.arange(int(counts.sum()))
            t_corner = np.repeat(t, counts, axis=0)
            dirs = np.concatenate([normals[corner][:, None, :], t_corner], axis=1) * weights[corner][:, None, None]
        built = self.model._rows_along(dirs, verts[corner], xv[corner], starts, self.dt)
        if self.rows3 is None:
            self.rows3 = built
        elif isinstance(built, ContactRowEntries):
            self.rows3 = self.rows3.stacked(built)
        else:
            self.rows3 = sp.vstack([self.rows3, built]).tocsr()
        self.slot[new] = np.arange(self.n_built, self.n_built + new.size)
        self.n_built += new.size
        self.tangents[new] = t
        spec, which, points = self.slip_at
        g_t = collider_slip(spec, which[new], points[new], t, self.moving) if self.moving else np.zeros((new.size, 2))
        if self.rigid_v is not None:
            self.rigid3[new, 1:] = self.dt * np.einsum("lij,lj->li", t, self.rigid_v[new])
            g_t += self.rigid3[new, 1:]
        if self.dent_shift is not None:
            g_t -= self.dent_shift[new, 1:]
        self.g3[new, 1:] = g_t

    def _rows(self, contacts, v):
        """The rows n, t1, t2 of built contacts (k,) for the solves (dense (3k, n_gen), or CSR
        beside full-space domains) and their products with v (n_gen,) (3k,)."""
        r = rows_of(self.slot[contacts])
        if isinstance(self.rows3, ContactRowEntries):
            return self.rows3[r], self.rows3.matvec_rows(r, v)
        rows = self.rows3[r]
        return rows, rows @ v

    def at(self, v):
        """The rows with their values at generalised velocities v (n_gen,), for
        friction.frictional_correction."""
        return _FrictionalRowsAt(self, v)

    def force(self, lam):
        """C3^T lam (n_gen,) for forces lam (m, 3), nonzero on built contacts only."""
        on = np.flatnonzero(lam.any(axis=1))
        if on.size == 0:
            return np.zeros(self.C.shape[1])
        r, f = rows_of(self.slot[on]), lam[on].ravel()
        if isinstance(self.rows3, ContactRowEntries):
            return self.rows3.rmatvec_rows(r, f)
        return self.rows3[r].T @ f

    def work(self, lam, Q):
        """lam . (C3 Q + rigid3): the work of the forces lam (m, 3) over the step's Q."""
        on = np.flatnonzero(lam.any(axis=1))
        if on.size == 0:
            return 0.0
        r = rows_of(self.slot[on])
        CQ = self.rows3.matvec_rows(r, Q) if isinstance(self.rows3, ContactRowEntries) else self.rows3[r] @ Q
        return float(lam[on].ravel() @ (CQ + self.rigid3[on].ravel()))


class _FrictionalRowsAt(FrictionRows):
    """FrictionalRows with their values g = C3 v + g3 at one v (friction.FrictionRows)."""

    def __init__(self, rows, v):
        self.rows, self.v = rows, v
        self.m, self.n = len(rows.g_n), rows.C.shape[1]

    def normal(self):
        return self.rows.C, self.rows.C @ self.v + self.rows.g_n

    def block(self, contacts):
        self.rows.ensure(contacts)
        dense, product = self.rows._rows(contacts, self.v)
        return dense, product + self.rows.g3[contacts].ravel()


class ContactRows:
    """Contact rows of the reduced model and the correction of a Newton step for contact. Mixed into
    reduced_model.ReducedModel, whose build provides the attributes it reads."""

    def _contact_rows(self, contact, gm, dt):
        """Candidate contacts of the surface: (vertices, C (m, n_gen), phi_eff (m,), normals, which,
        friction), or None. C = dt n^T J_l; under a co-rotating step the rigid part of the
        vertex velocity, V + W x (x - C), is a constant folded into phi_eff. friction is
        None (every collider frictionless) or the contacts' FrictionalRows (rows n, t1, t2
        per contact, mu static or kinetic by the last step's slip, the last step's forces as
        a first guess)."""
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
        if rough and self.compliance is None and not self.F and len(rows) == len(phi):
            return self._vertex_friction_rows(contact, ids, x, rows, which, phi, normals, weights, group, key, gm,
                                              dt)
        found = self._corner_rows(contact, ids, x, rows, which, phi, normals, weights, group, key, gm, dt, rough)
        if found is not None and found[5] is not None and not self.F:
            # Every contact's three rows: the compiled Coulomb solve (frictional_kernel.py)
            # grows its working set from them. A full-space body's CSR rows are built for
            # its working set only, which the Python solve asks for.
            found[5].ensure(np.arange(len(found[0])))
        return found

    def _corner_rows(self, contact, ids, x, rows, which, phi, normals, weights, group, key, gm, dt, rough=True):
        """_contact_rows' answer from the candidates' corner rows: ids (n_s,) the searched
        vertices at x (n_s, 3); rows (k,) the candidates' corners (rows of ids), with which,
        normals (k, 3) and weights (k,) per corner and group (k,) its contact (phi (c,) per
        contact); key (c,) the contacts' identities; rough: some collider has friction.
        Any body: face contacts, full-space domains, residual compliance."""
        verts = ids[rows]
        xv = x[rows]
        # group is non-decreasing (vertex rows, then three corners per face): one contact per run.
        # Without faces every row is a contact of its own (the corner gathers below are skipped).
        one_corner = len(rows) == len(phi)                  # a face adds three rows and one phi
        starts = group if one_corner else np.flatnonzero(np.r_[True, group[1:] != group[:-1]])
        # The normal rows of every contact. With friction a contact's tangential rows are
        # built when the Coulomb solve asks for them (FrictionalRows), except that the
        # residual compliance's rows need every contact's three directions at once.
        ends = np.arange(1, len(rows) + 1) if one_corner else np.append(starts[1:], len(rows))
        corners = (verts, xv, normals, weights, starts, ends)
        dirs = normals[:, None, :] * weights[:, None, None]
        C = self._rows_along(dirs, verts, xv, starts, dt)
        tangents = None
        if rough and self.compliance is not None:
            tangents = tangent_basis(normals)                                   # (corner rows, 2, 3)
            dirs = np.concatenate([dirs, tangents * weights[:, None, None]], axis=1)
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
        first, end = corners[4], corners[5]                # each contact's corner rows
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
            key, at, first, end = key[movable], at[movable], first[movable], end[movable]
            if tangents is not None:
                tangents = tangents[movable]
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
            fric = FrictionalRows(self, C, phi_eff, effective_mu(*coefficients(contact, which), keys, self.contact, n_col),
                                  corners[:4] + (first, end), (contact, which, xv), dt,
                                  None if gm is None else rigid_v, dent_shift)
            if tangents is not None:
                fric.ensure(np.arange(len(verts)), tangents)
            # The last step's forces as the first guess: their contacts' rows are built now
            # (they start the working set).
            match = previous_match(self.contact, keys, n_col)
            if match is not None:
                fric.ensure(np.flatnonzero(match[0]))
                fric.guess = warm_start(self.contact, keys, fric.tangents, n_col, match)
        return verts, C, phi_eff, normals, which, fric

    def _vertex_friction_rows(self, contact, ids, x, near, which, phi, normals, weights, group, key, gm, dt):
        """_contact_rows' answer for vertex candidates on a body of subspace domains without
        residual compliance (the rows of every contact in one compiled call,
        frictional_kernel.vertex_rows_kernel, for the compiled Coulomb solve): the same
        rows, gaps and first guess as _corner_rows (test_frictional_kernel.py), which
        takes about 40 numpy calls for them: 0.099 -> 0.049 ms on the reduced incline's 48
        candidates, 0.24 -> 0.25 on the caterpillar's 814, whose every row this builds
        against the working set's there (min of 300 calls, docs/performance.md "Session
        30"). ids (n_s,) the searched vertices at x (n_s, 3);
        near, which, phi, normals: find_contacts' candidates (one corner each: weights and
        group, _corner_rows' arguments, are not read); key (k,) their row keys."""
        L, k = self.layout, len(near)
        w = L.U.shape[2] + 6
        keep, tangents = np.empty(k, dtype=np.int64), np.empty((k, 2, 3))
        cols, vals = np.empty((3 * k, w), dtype=np.int64), np.empty((3 * k, w))
        count = np.empty(3 * k, dtype=np.int64)
        g3, rigid3 = np.empty((k, 3)), np.empty((k, 3))
        C, V, W = (np.zeros(3),) * 3 if gm is None else (np.asarray(a, dtype=np.float64) for a in gm[:3])
        near = np.ascontiguousarray(near, dtype=np.int64)
        f64 = np.float64
        m = vertex_rows_kernel(near, np.ascontiguousarray(ids[near], dtype=np.int64),
                               np.ascontiguousarray(phi, dtype=f64), np.ascontiguousarray(normals, dtype=f64),
                               np.ascontiguousarray(x, dtype=f64), L.U, L.row_domain, L.vertex_row, self.frames.R,
                               self.frames.c, L.q_index, L.mask, self._frame_cols, float(dt), gm is not None, C, V, W,
                               keep, tangents, cols, vals, count, g3, rigid3)
        if m == 0:
            return None
        keep = keep[:m]
        if m < k:
            near, which, normals, key = near[keep], which[keep], normals[keep], key[keep]
            cols, vals, count = cols[:3 * m], vals[:3 * m], count[:3 * m]
            tangents, g3, rigid3 = tangents[:m], g3[:m], rigid3[:m]
        verts, xv = ids[near], x[near]
        rows3 = ContactRowEntries(cols, vals, count, self.n_gen)
        C = rows3.take(np.arange(0, 3 * m, 3))
        self._contact_rigid = rigid3[:, 0].copy()
        self._contact_row_keys = key
        self._contact_at = near
        self._contact_compliance = None
        self._dent_cap = contact["margin"]
        n_col = len(contact["colliders"])
        keys = verts * n_col + which
        mu_s, mu_k = coefficients(contact, which)
        prev, guess = self.contact, None
        if prev is None or "slip_speed" not in prev:
            mu = mu_s
        else:
            # effective_mu, previous_match and warm_start in one pass (frictional_kernel.warm_kernel).
            mu, guess = np.empty(m), np.empty((m, 3))
            i64, f64 = np.int64, np.float64
            found = warm_kernel(np.ascontiguousarray(keys, dtype=i64), tangents, mu_s, mu_k,
                                np.ascontiguousarray(prev["vertices"], dtype=i64) * n_col
                                + np.ascontiguousarray(prev["which"], dtype=i64),
                                np.ascontiguousarray(prev["slip_speed"], dtype=f64),
                                np.ascontiguousarray(prev["normal_force"], dtype=f64),
                                np.ascontiguousarray(prev["friction"], dtype=f64), STICTION_SPEED,
                                bool(np.any(mu_k < mu_s)), mu, guess)
            guess = guess if found else None
        fric = FrictionalRows.built(self, C, mu, (contact, which, xv), dt, rows3, tangents, g3, rigid3)
        fric.guess = guess
        return verts, C, g3[:, 0].copy(), normals, which, fric

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
        elif friction is not None and friction.guess is not None:
            hint = None                   # a warm-started Coulomb solve starts from its guess instead
        else:
            hint = member(keys, np.concatenate(history)) if history else None
        # limit_dent solves the same contact again under a smaller compliance, and its rounds
        # ask the step's matrix for the same rows' solutions: they are kept for the step.
        keep = self._contact_compliance is not None
        resolve = (CholeskySolves(self._factor, keep) if self._factor is not None
                   else Solves(self._resolve, keep))
        # Rows through a few modes per domain are often dependent: regularise (unilateral.py).
        if friction is None:
            g = C @ (Q + dQ) + phi

            def solve(compliance):
                return contact_correction(resolve, C, g, regularize=1e-9, hint=hint, compliance=compliance)
        else:
            guess = self._contact_lam if same_step else friction.guess
            rows3, mu = friction.at(Q + dQ), friction.mu

            def solve(compliance):
                if compliance is None and self._factor is not None:
                    done = compiled_correction(friction, Q + dQ, guess, self._factor)
                    if done is not None:
                        return done
                return frictional_correction(resolve, rows3, None, mu, regularize=1e-9,
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
            return rows[5].force(lam)
        C = rows[1]
        return C.rmatvec(lam) if isinstance(C, ContactRowEntries) else C.T @ lam
