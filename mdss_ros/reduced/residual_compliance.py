"""Residual compliance: the local dent a subspace cannot make (docs/method.md §14.2).

A reduced body moves in the span of its kinematics J (n_dofs, n_gen) at rest: every
vertex x_l = c + R (r_l + U_l q), linearised, dx_l = U_l dq + dv + dw x r_l on its
domain's modal and frame columns. Under a static load f the full-space FEM (stiffness K
at rest, the scene's pins) and the reduced model move by

    u   = K^+ P f                              (n_dofs,)
    u_J = J (J^T K J)^+ J^T P f                 (n_dofs,)

P = I - M R R^T removes the part of the load a free body answers with rigid
acceleration (inertia relief; R (n_dofs, 6) its M-orthonormal rigid modes, P = I when
pinned), and both answers are taken M-orthogonal to R. On the vertices a collider can
touch (E (n_dofs, 3 n_c) selects their DOFs),

    C_res = E^T (u - u_J)|_{f = E} = E^T (K^+ - J (J^T K J)^+ J^T) P E      (3 n_c, 3 n_c)

is the residual flexibility of structural dynamics (MacNeal 1971; the static correction
of mode acceleration): the response of every shape the subspace leaves out. J^T K J is
the Galerkin projection of K, so C_res is symmetric positive semi-definite. A collider
pressing a few vertices loads mostly those left-out, high-frequency shapes, which answer
quasi-statically; contact adds C_res to the reduced contact operator (contact_rows.py),

    W = C A^-1 C^T + G C_res G^T         G (m r, 3 n_c): each contact row's direction,
                                          in its domain's axes, on its vertices' columns,

and each vertex in contact sits at its reduced position plus the dent C_res G^T lam. For
a linear material at rest the contact vertices then follow the full-space FEM's static
compliance exactly, at the cost of an (m, m) block, with no change of basis in a step and
no new cubature (Harmon and Zorin 2013 add local modes at run time; Teng et al. 2015
condense a full-space patch: both re-factor the step). The price: the dent has no mass
and no damping, and it is the compliance at rest, rotated with its domain's frame.

Shapes: n_c candidate vertices, n_dofs = 3 n_verts, n_gen generalised DOFs.
"""
from dataclasses import dataclass

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp
from numba import njit

from ..fem.force_model import FEMForceModel
from ..linear_solver import SparseSolver
from .modal_basis import rigid_modes

#: Right-hand sides per batch of full-space solves: (n_dofs, BATCH) doubles at a time.
BATCH = 96


@dataclass(frozen=True)
class ResidualCompliance:
    """vertices (n_c,) global ids; domain (n_c,) each one's subspace domain; C (3 n_c, 3 n_c)
    in rest axes (vertex-major: 3 i + axis); index (n_verts,) a vertex's row in vertices or
    -1; info: what was built (explain)."""

    vertices: np.ndarray
    domain: np.ndarray
    C: np.ndarray
    index: np.ndarray
    info: dict

    @classmethod
    def on(cls, vertices, domain, C, n_verts, info):
        """The compliance C on candidate ids vertices (n_c,) of a body of n_verts vertices."""
        index = np.full(n_verts, -1, dtype=np.int64)
        index[vertices] = np.arange(len(vertices))
        return cls(vertices=vertices, domain=domain, C=C, index=index, info=info)

    @property
    def n(self):
        return len(self.vertices)

    def rows(self, dirs, verts, row_of, m, R):
        """The ContactCompliance of m contacts' rows, or None when no corner is a candidate.

        Its G (m r, k): row a r + j holds direction j of contact a, turned into its
        domain's rest axes (R[domain]^T d), on the three columns of each corner vertex that
        is a candidate; cols (k,) those columns of C (3 i + axis, ascending). dirs (p, r, 3)
        per corner row (weights folded in), verts (p,) their vertex ids, row_of (p,) their
        contact, R (D, 3, 3) the domains' rotations. A contact has at most three corners, so
        G is dense on the few columns its rows touch, built by one scatter."""
        ci = self.index[verts]
        sel = np.flatnonzero(ci >= 0)
        if sel.size == 0:
            return None
        r = dirs.shape[1]
        local = np.einsum("krj,kji->kri", dirs[sel], R[self.domain[ci[sel]]])            # (s, r, 3)
        touched, slot = np.unique(ci[sel], return_inverse=True)                          # candidates (t,)
        cols = (3 * touched[:, None] + np.arange(3)).ravel()                              # (3 t,)
        G = np.zeros((m * r, len(cols)))
        # Summed, not assigned: two corners of one contact on the same vertex would add, as
        # the sparse build did (a face's corners are distinct vertices, so none do).
        np.add.at(G, ((row_of[sel] * r)[:, None, None] + np.arange(r)[None, :, None],
                      (3 * slot)[:, None, None] + np.arange(3)[None, None, :]), local)
        return ContactCompliance(G, cols, self.C)


@njit(cache=True)
def _gather(C, rows, cols):
    """C[rows][:, cols] (len(rows), len(cols)) of a large C: numpy's np.ix_ indexing costs
    1.5 to 2 times as much for these few thousand entries."""
    out = np.empty((rows.shape[0], cols.shape[0]))
    for i in range(rows.shape[0]):
        for j in range(cols.shape[0]):
            out[i, j] = C[rows[i], cols[j]]
    return out


@njit(cache=True)
def _combine_rows(C, rows, f, out):
    """out (n,) += sum_i f[i] C[rows[i], :]: a few rows of a large C (n, n) in place, with
    no copy of them."""
    for i in range(rows.shape[0]):
        row, fi = rows[i], f[i]
        for j in range(C.shape[1]):
            out[j] += fi * C[row, j]


class ContactCompliance:
    """The residual compliance as the contact solvers see it (unilateral.contact_correction,
    friction.frictional_correction): blocks of s G C_res G^T between row sets, its product
    with forces on some rows, and the dent those forces make. G (rows, k) dense on cols
    (k,), the columns of C (3 n_c, 3 n_c) the rows touch (ResidualCompliance.rows); scale
    s in [0, 1] (limit_dent).

    A row touches at most nine columns (three corners, three axes), so every product is
    taken on the columns its rows touch, and only those entries of C are read (_gather,
    _combine_rows): nothing of C's size is gathered or copied a step. Gathering C's k
    touched rows (k x 3 n_c) whenever the touched set changed, as before, cost about
    0.9 ms a step on hammock, whose set changes nearly every step; the step then costs
    about the same for 50 candidates as for 800."""

    def __init__(self, G, cols, C, scale=1.0, products=None):
        self.G, self.cols, self.C = G, cols, C
        self.scale = float(scale)
        self._last_dent = None             # (lam, dent) of the last dent() (see dent)
        # The unscaled blocks G[a] C G[b]^T by row sets, shared with scaled() copies:
        # limit_dent's rounds solve the same contact under another scale, with the same blocks.
        self._products = {} if products is None else products

    def _on_touched(self, rows):
        """(G[rows] on the columns it touches (len(rows), t), their indices into cols (t,))."""
        g = self.G[rows]
        on = np.flatnonzero(g.any(axis=0))
        return g[:, on], on

    def block(self, a, b):
        """(len(a), len(b)) dense: s G[a] C G[b]^T; a, b integer row indices."""
        key = (np.asarray(a).tobytes(), np.asarray(b).tobytes())
        product = self._products.get(key)
        if product is None:
            ga, ca = self._on_touched(a)
            gb, cb = self._on_touched(b)
            product = self._products[key] = ga @ _gather(self.C, self.cols[ca], self.cols[cb]) @ gb.T
        return self.scale * product

    def normal(self):
        """The same on the normal rows alone (every third row of a frictional G)."""
        return ContactCompliance(self.G[0::3], self.cols, self.C, self.scale)

    def take(self, rows):
        """The same on some of its rows (rows: indices or a mask)."""
        return ContactCompliance(self.G[rows], self.cols, self.C, self.scale)

    def apply(self, b, lam):
        """(rows,): s G C G[b]^T lam, the compliance's share of every row's gap."""
        gb, cb = self._on_touched(b)
        f = gb.T @ lam                                            # forces on b's columns (t,)
        on = np.flatnonzero(f)                                    # columns only idle rows touch
        return self.scale * (self.G @ (_gather(self.C, self.cols, self.cols[cb[on]]) @ f[on]))

    def shift(self, dent):
        """(rows,): G times a dent (n_c, 3), each row's share of it (the last step's dent,
        which the rows' gaps already hold)."""
        return self.G @ dent.ravel()[self.cols]

    def dent(self, lam):
        """(n_c, 3) every candidate's dent in its domain's rest axes: s C G^T lam.

        limit_dent measures the dent of its answer and the step then keeps the same dent as
        state, so the last one is kept and returned again (read-only) for the same forces."""
        lam = np.asarray(lam, dtype=np.float64)
        last = self._last_dent
        if last is not None and last[0].shape == lam.shape and np.array_equal(last[0], lam):
            return last[1]
        f = self.G.T @ lam                                        # forces on the columns (k,)
        on = np.flatnonzero(f)
        out = np.zeros(self.C.shape[1])
        # C is symmetric: C G^T lam is a sum of C's rows on the loaded columns.
        _combine_rows(self.C, self.cols[on], f[on], out)
        dent = (self.scale * out).reshape(-1, 3)
        dent.flags.writeable = False
        self._last_dent = (lam.copy(), dent)
        return dent

    def scaled(self, s):
        return ContactCompliance(self.G, self.cols, self.C, s, self._products)


#: Rounds of limit_dent, and the share of the cap they aim at.
DENT_ROUNDS, DENT_AIM = 8, 0.95


def _largest_dent(compliance, lam):
    return float(np.sqrt((compliance.dent(np.ravel(lam)) ** 2).sum(axis=1).max()))


def limit_dent(solve, compliance, cap):
    """Contact under a compliance whose dent stays within cap (m) at every vertex.

    The residual compliance is that of the body at rest, linear in the load. A collider
    driven into the body faster than it can move away (5 m/s into a 1e5 Pa block) would
    sink into that dent by centimetres: vertices beyond the contact search's reach are
    then carried by their neighbours' dent into the collider, and the body, which feels only
    the force, is not pushed away as a full-space body is (its elements stiffen as they
    flatten). The dent is therefore capped at the contact margin (a mean surface edge, the
    distance within which the search finds new contacts) by scaling the compliance by
    s in (0, 1] and solving the contact again.

    For one contact of depth h the dent is d(s) = h s c / (s c + w) (c the residual and w
    the modes' compliance), so 1/d is affine in 1/s: the rounds are secant steps in
    (1/s, 1/d) towards d = aim cap, which that model solves in one step. Where the residual
    compliance dominates (c >> w) d(s) is nearly flat until s is small, and the plain
    fixed point s <- s aim cap / d would crawl (measured: 0.92, 0.86, 0.81 ... for a punch
    driven 15 mm into a 4 cm block). The first s whose dent is within the cap is kept; if
    none is within DENT_ROUNDS, the compliance is dropped for the step (s = 0: the modes
    alone, which never dent).

    solve(compliance) -> (lam, ...) solves the contact; returns (its result, the compliance
    used)."""
    out = solve(compliance)
    d = _largest_dent(compliance, out[0])
    if d <= cap:
        return out, compliance
    target = DENT_AIM * cap
    s_prev, d_prev = None, None
    s = compliance.scale
    for _ in range(DENT_ROUNDS):
        if s_prev is None or abs(1.0 / d - 1.0 / d_prev) < 1e-12 / target:
            s_new = s * target / d                                  # the fixed point, first
        else:
            slope = (1.0 / s - 1.0 / s_prev) / (1.0 / d - 1.0 / d_prev)
            inv = 1.0 / s + slope * (1.0 / target - 1.0 / d)
            s_new = 1.0 / inv if np.isfinite(inv) and inv > 1.0 / s else s * target / d
        s_prev, d_prev, s = s, d, s_new
        compliance = compliance.scaled(s)
        out = solve(compliance)
        d = _largest_dent(compliance, out[0])
        if d <= cap:
            return out, compliance
    compliance = compliance.scaled(0.0)
    return solve(compliance), compliance


def kinematics_at_rest(layout, n_gen, n_verts):
    """J (3 n_verts, n_gen) CSR: the reduced model's vertex displacements per generalised DOF
    at rest: U_l on its domain's modal columns, and for a movable domain I3 on v and
    [e_b x r_l] on w (r_l the rest offset about the frame's origin). Full-space vertices
    (no subspace row) get no entries here."""
    L = layout
    verts = np.flatnonzero(L.vertex_row >= 0)
    rows_v = L.vertex_row[verts]
    dom = L.row_domain[rows_v]
    # Modal part: (s, 3, r_max) values, padding columns dropped.
    vals = L.U[rows_v]
    ok = np.broadcast_to(L.mask[dom][:, None, :], vals.shape)
    r_idx = np.broadcast_to((3 * verts)[:, None, None] + np.arange(3)[None, :, None], vals.shape)
    c_idx = np.broadcast_to(L.q_index[dom][:, None, :], vals.shape)
    parts = [(r_idx[ok], c_idx[ok], vals[ok])]
    mover = np.full(L.D, -1, dtype=np.int64)
    mover[L.movers] = np.arange(len(L.movers))
    mv = mover[dom] >= 0
    if mv.any():
        v_mv, k = verts[mv], mover[dom[mv]]
        arm = L.r_local[rows_v[mv]]                                                      # (s, 3)
        # dw x r = -[r]x dw: column b of the angular block is e_b x r.
        ang = np.cross(np.eye(3)[None, :, :], arm[:, None, :]).transpose(0, 2, 1)       # (s, 3 axis, 3 b)
        lin = np.broadcast_to(np.eye(3), ang.shape)
        vals = np.concatenate([lin, ang], axis=2)                                        # (s, 3, 6)
        cols = np.hstack([L.lin_index, L.ang_index])[k]                                  # (s, 6)
        shape = vals.shape
        parts.append((np.broadcast_to((3 * v_mv)[:, None, None] + np.arange(3)[None, :, None], shape).ravel(),
                      np.broadcast_to(cols[:, None, :], shape).ravel(), vals.ravel()))
    r_all, c_all, v_all = (np.concatenate([p[i] for p in parts]) for i in range(3))
    return sp.csr_matrix((v_all, (r_all, c_all)), shape=(3 * n_verts, n_gen))


def six_supports(R):
    """Six DOFs (6,) whose rigid-mode rows are best conditioned: holding them removes the
    rigid motions and, for a load with no rigid part, adds no reaction (inertia relief).
    Pivoted QR of R^T (6, n_dofs) picks them."""
    _, _, piv = sla.qr(R.T, mode="economic", pivoting=True)
    return np.sort(piv[:6])


@dataclass(frozen=True)
class RestStatics:
    """The full-space FEM at rest with the scene's pins removed, for linear static answers.
    K (n_free, n_free) CSR; free_dof (3 n,) -> free index or -1; free (n_free,) the free
    global DOFs; m_dof (n_free,) their lumped masses; R (3 n, 6) the M-orthonormal rigid
    modes of a floating body, None when pinned; Rf = R[free]."""

    K: object
    free_dof: np.ndarray
    free: np.ndarray
    m_dof: np.ndarray
    R: object

    @classmethod
    def of(cls, body, vertex_mass):
        X = body.vertices
        fem = FEMForceModel(X, body.tets, body.material, pinned=body.pinned)
        K = fem.pattern.matrix(fem.tangent(X)[2]).tocsr()
        free_dof = fem.pattern.free_dof
        free = np.flatnonzero(free_dof >= 0)
        R = rigid_modes(X, vertex_mass) if len(body.pinned) == 0 else None
        return cls(K, free_dof, free, np.repeat(vertex_mass, 3)[free], R)

    @property
    def floating(self):
        return self.R is not None

    @property
    def Rf(self):
        return None if self.R is None else self.R[self.free]

    def answers(self, loads, rows=None, progress=None):
        """u = K^+ P B on the free DOFs rows (default all) for loads B (n_free, k), dense or
        scipy.sparse, M-orthogonal to the rigid modes of a floating body (P = I - M R R^T:
        inertia relief; the body is held at six DOFs that carry no reaction for a load with
        no rigid part). One factorisation, BATCH right-hand sides at a time: only the rows
        asked for are kept, so k may be thousands. Returns (u (len(rows), k), info)."""
        say = progress or (lambda msg: None)
        n_free, k = loads.shape
        rows = np.arange(n_free) if rows is None else np.asarray(rows, dtype=np.int64)
        Rf = self.Rf
        held = six_supports(Rf) if self.floating else np.zeros(0, dtype=np.int64)
        keep = np.setdiff1d(np.arange(n_free), held)
        Kk = self.K[keep][:, keep].tocsr()
        Kk.sort_indices()
        solver = SparseSolver().factor(Kk)
        say(f"static responses: {k} full-space solves of {len(keep)} DOFs")
        out = np.zeros((len(rows), k))
        MR = self.m_dof[:, None] * Rf if self.floating else None
        for s in range(0, k, BATCH):
            B = loads[:, s:s + BATCH]
            B = B.toarray() if sp.issparse(B) else np.array(B, dtype=np.float64)
            if self.floating:
                B -= MR @ (Rf.T @ B)                                                     # P B
            U = np.zeros_like(B)
            U[keep] = np.asarray(solver.solve(B[keep])).reshape(len(keep), -1)
            if self.floating:
                U -= Rf @ (MR.T @ U)
            out[:, s:s + BATCH] = U[rows]
        solver.close()
        return out, {"full_dofs": int(len(keep)), "floating": bool(self.floating)}


def static_responses(body, vertex_mass, candidates, dofs=None, progress=None):
    """The full-space FEM's static answers to a unit load on each DOF of each candidate:
    u = K^+ P E_c at rest with the scene's pins, M-orthogonal to the rigid modes of a
    floating body (P = I - M R R^T: inertia relief). Returns (u on the global DOF ids
    dofs (len(dofs), 3 n_c), default every DOF (3 n_verts, 3 n_c); pinned DOFs are zero,
    the full stiffness K (n_free, n_free) CSR, the pattern's free_dof (3 n_verts,) -> free
    index or -1, R (3 n_verts, 6) or None when pinned, info)."""
    n = len(body.vertices)
    candidates = np.asarray(candidates, dtype=np.int64)
    st = RestStatics.of(body, vertex_mass)
    cand_dof = st.free_dof[(3 * candidates[:, None] + np.arange(3)).ravel()]            # (3 n_c,)
    if np.any(cand_dof < 0):
        raise ValueError("static_responses: candidates must be free vertices")
    dofs = np.arange(3 * n) if dofs is None else np.asarray(dofs, dtype=np.int64)
    out_free = st.free_dof[dofs]                                                         # -1: pinned row
    u = np.zeros((len(dofs), len(cand_dof)))
    E = sp.csc_matrix((np.ones(len(cand_dof)), (cand_dof, np.arange(len(cand_dof)))),
                      shape=(len(st.free), len(cand_dof)))
    u[out_free >= 0], info = st.answers(E, rows=out_free[out_free >= 0], progress=progress)
    return u, st.K, st.free_dof, st.R, info


def build_residual_compliance(body, layout, n_gen, vertex_mass, candidates, progress=None):
    """ResidualCompliance of the reduced model with kinematics layout (all vertices in
    subspace domains) on the candidate vertex ids (n_c,). Raises ValueError when a
    candidate is pinned or not in a subspace domain."""
    n = len(body.vertices)
    candidates = np.asarray(candidates, dtype=np.int64)
    pinned = np.zeros(n, dtype=bool)
    pinned[body.pinned] = True
    if np.any(pinned[candidates]) or np.any(layout.vertex_row[candidates] < 0):
        raise ValueError("residual compliance: candidates must be free vertices of subspace domains")
    dofs = (3 * candidates[:, None] + np.arange(3)).ravel()                              # (3 n_c,)
    u_c, K, free_dof, R, built = static_responses(body, vertex_mass, candidates, dofs=dofs, progress=progress)
    free = np.flatnonzero(free_dof >= 0)
    cand_dof = free_dof[dofs]
    floating = built["floating"]
    J = kinematics_at_rest(layout, n_gen, n)[free]                                      # (n_free, n_gen)
    if floating:
        R = R[free]
        MR = np.repeat(vertex_mass, 3)[free][:, None] * R

    # Reduced: (J^T K J)^+ J^T P E_c through the eigenpairs of the small dense J^T K J
    # (a floating body's rigid motions are its null space).
    Kr = np.asarray((J.T @ (K @ J)).todense())
    w, V = np.linalg.eigh(0.5 * (Kr + Kr.T))
    ok = w > 1e-10 * max(float(w[-1]), 1e-300)
    Jc = np.asarray(J[cand_dof].todense())                                               # (3 n_c, n_gen)
    F = Jc.T.copy()
    if floating:
        F -= (J.T @ MR) @ R[cand_dof].T                                                  # J^T P E_c
    q = V[:, ok] @ ((V[:, ok].T @ F) / w[ok][:, None])
    u_r = Jc @ q
    if floating:
        u_r -= R[cand_dof] @ (MR.T @ (J @ q))
    C = u_c - u_r
    C = 0.5 * (C + C.T)
    # Round-off (and cubature-free approximations of the interface) can leave tiny negative
    # eigenvalues; a negative compliance would pull a contact in, so they are clipped.
    lam, Q = np.linalg.eigh(C)
    clipped = float(-lam[lam < 0].sum() / max(float(np.abs(lam).sum()), 1e-300))
    C = (Q * np.maximum(lam, 0.0)) @ Q.T
    info = {"vertices": int(len(candidates)), "full_dofs": built["full_dofs"], "floating": bool(floating),
            "clipped": clipped, "megabytes": C.nbytes / 1e6,
            "diagonal_ratio": float(np.median(np.diag(C) / np.maximum(np.diag(u_c), 1e-300)))}
    return ResidualCompliance.on(candidates, layout.row_domain[layout.vertex_row[candidates]], C, n, info)
