"""Frictionless unilateral contact as constraints of the linearised implicit step.

Each step solves A v' = b (backward Euler, Newton). A surface vertex l near a collider
gets the linearised non-penetration constraint at the end of the step

    phi_l + dt n_l . (J_l v') >= 0          (phi, n at the collider's end-of-step pose)

with multipliers lambda_l >= 0 (the normal contact forces, newtons) and complementarity
lambda_l (phi_l + dt n_l . J_l v') = 0:

    A v' = b + C^T lambda,   C = dt [n_l^T J_l],   C v' + phi >= 0,   lambda >= 0.

Eliminating v' = v0 + A^-1 C^T lambda (v0 = A^-1 b) leaves an LCP in the few contact
unknowns: w = S lambda + q >= 0, S = C A^-1 C^T (symmetric positive definite when the
contact rows are independent), q = C v0 + phi. It is solved exactly by an active-set
method, so the answer is the unilateral constraint itself, not a penalty whose result
depends on a tuned stiffness.
"""
import numpy as np
import scipy.sparse as sp
from numba import njit
from scipy.linalg.lapack import dposv


def solve_lcp(S, q, max_iterations=None, tol=1e-12, regularize=0.0, active=None, shift=0.0):
    """lambda >= 0 with w = S lambda + q >= 0 and lambda . w = 0, for S (m, m) SPD.

    The minimiser of 1/2 lambda.S lambda + q.lambda over lambda >= 0, by an active-set
    method in two gears. First block principal pivoting (Judice and Pires 1994): guess the
    active set A, solve S_AA lambda_A = -q_A, and swap every index that breaks a sign
    (lambda_i < 0 in A, w_i < 0 outside) at once; a good guess (the previous step's
    contacts) needs one or two solves. Block swaps can cycle when rows are dependent (a
    reduced body has more contact rows than DOFs), so after three swaps that do not lower
    the number of broken indices it goes on with Lawson and Hanson's method (NNLS,
    1974): add the most violated row, and where the new solution turns a multiplier
    negative, stop on the segment where it reaches zero and drop it. That lowers the
    objective at every step, so it cannot cycle. The LCP has one solution; either gear
    ends there.

    active: optional (m,) bool, the first guess (default: the rows with q < 0).
    Returns (lambda, info). regularize > 0 adds that fraction of mean(diag S) to the
    diagonal: for reduced bodies with more contact rows than DOFs, where S is singular (the
    total force is determined but not its split), it picks the least-norm split at a
    constraint error of that order; shift > 0 adds that absolute value instead.
    """
    m = len(q)
    lam = np.zeros(m)
    if m == 0:
        return lam, {"iterations": 0, "active": 0}
    if regularize > 0.0:
        shift = regularize * max(float(np.mean(np.diag(S))), 1e-300)
    if shift > 0.0:
        S = S + shift * np.eye(m)
    active = (q < 0.0) if active is None else np.asarray(active, dtype=bool).copy()
    scale = max(float(np.abs(q).max()), 1e-300)
    max_iterations = max_iterations or 10 * m + 10
    best, best_set, chances = m + 1, active.copy(), 3
    for it in range(max_iterations):
        lam = _solve_on(S, q, active)
        neg = active & (lam < -tol * scale)
        viol = ~active & (S @ lam + q < -tol * scale)
        n_broken = int(neg.sum() + viol.sum())
        if n_broken == 0:
            return np.maximum(lam, 0.0), {"iterations": it + 1, "active": int(active.sum())}
        if n_broken < best:
            best, best_set, chances = n_broken, active.copy(), 3
        else:
            chances -= 1
        if chances == 0:
            break
        active ^= neg | viol
    return _lawson_hanson(S, q, tol * scale, max_iterations, it + 1, best_set)


def _solve_on(S, q, active):
    """lambda (m,): S_AA lambda_A = -q_A on the active set, zero elsewhere.

    Cholesky through LAPACK's posv directly: the same routine and triangle (upper) as
    scipy.linalg.solve(assume_a="pos"), so the same numbers, without its 15-20 us of
    argument handling a call (an LCP makes a few of these a solve, a step a few solves).
    Not positive definite (posv's info > 0): least squares, as before."""
    lam = np.zeros(len(q))
    idx = np.flatnonzero(active)
    if idx.size:
        Sa = S[np.ix_(idx, idx)]
        _, x, info = dposv(Sa, -q[idx], lower=0)
        lam[idx] = x if info == 0 else np.linalg.lstsq(Sa, -q[idx], rcond=None)[0]
    return lam


def _lawson_hanson(S, q, tol, max_iterations, done, start):
    """solve_lcp's second gear; `done` iterations already spent. It starts from the best
    set of the first gear, less the rows whose multipliers come out non-positive (dropped
    until none does), so lambda >= 0 from the start (Bro and de Jong's warm start)."""
    m = len(q)
    lam = np.zeros(m)
    passive = start.copy()
    it = done
    while passive.any() and it < max_iterations:
        it += 1
        z = _solve_on(S, q, passive)
        bad = passive & (z <= 0.0)
        if not bad.any():
            lam = z
            break
        passive &= ~bad
    blocked = np.zeros(m, dtype=bool)           # rows whose entry failed in round-off
    while it < max_iterations:
        w = S @ lam + q
        cand = ~passive & ~blocked & (w < -tol)
        if not cand.any():
            return lam, {"iterations": it, "active": int(passive.sum()),
                         "unconverged": bool((~passive & (w < -tol)).any())}
        j = np.flatnonzero(cand)[np.argmin(w[cand])]
        passive[j] = True
        while it < max_iterations:
            it += 1
            z = _solve_on(S, q, passive)
            bad = passive & (z <= 0.0)
            if not bad.any():
                lam = z
                blocked[:] = False
                break
            if bad[j] and lam[j] == 0.0:
                # The row just added cannot enter (dependent on the set in round-off).
                passive[j] = False
                blocked[j] = True
                break
            # Move towards z until the first multiplier reaches zero, and drop it.
            alpha = np.min(lam[bad] / (lam[bad] - z[bad]))
            lam = lam + alpha * (z - lam)
            passive &= lam > 0.0
            lam[~passive] = 0.0
    return lam, {"iterations": it, "active": int(passive.sum()), "unconverged": True}


def member(keys, among):
    """np.isin(keys, among) for non-negative integer keys (k,), (a,), through a table over
    the keys' range: np.isin sorted both (contact keys, vertex id x colliders + collider,
    span about 10 times their count, too wide for its own table), about 0.2 ms of a loaded
    caterpillar step in the LCP's first guess (48 against 4 us hot)."""
    if len(keys) == 0 or len(among) == 0:
        return np.zeros(len(keys), dtype=bool)
    table = np.zeros(int(max(keys.max(), among.max())) + 1, dtype=bool)
    table[among] = True
    return table[keys]


class Solves:
    """What the contact solvers ask of the step's matrix A (n, n), for the rows C_r (k, n)
    of a working set (dense, or scipy sparse): their columns, the Delassus block C_a A^-1
    C_b^T of two row sets from their columns, and the velocity correction A^-1 C_r^T lam.
    This one from resolve(B), A X = B for B (n, k): the columns are Y = A^-1 C_r^T.
    keep: answer a right-hand side seen before with the same columns (a solve repeated
    under another residual compliance, residual_compliance.limit_dent). A Cholesky factor
    that gives its half sweeps is used through HalfSweepSolves instead."""

    #: Whether the Delassus blocks are positive semi-definite by their form (Gram matrices).
    definite = False

    def __init__(self, resolve=None, keep=False):
        self._resolve = resolve
        self._kept = {} if keep else None

    def columns(self, rows):
        B = np.ascontiguousarray(rows.T.toarray() if sp.issparse(rows) else rows.T)
        if self._kept is None:
            return self._sweep(B)
        key = (B.shape, B.tobytes())
        if key not in self._kept:
            self._kept[key] = self._sweep(B)
        return self._kept[key]

    def _sweep(self, B):
        return np.asarray(self._resolve(B)).reshape(B.shape[0], -1)

    def delassus(self, rows_a, cols_a, rows_b, cols_b):
        """C_a A^-1 C_b^T (k_a, k_b)."""
        return np.asarray(rows_a @ cols_b)

    def correction(self, cols, lam):
        """A^-1 C_r^T lam (n,) for lam (k,) on the rows whose columns are cols."""
        return cols @ lam


class HalfSweepSolves(Solves):
    """The contact solves from half sweeps of a Cholesky factorisation A = P^T L L^T P,
    factor.forward(B) = L^-1 P B and factor.backward(z) = P^T L^-T z: a working set's
    columns are Z = L^-1 P C_r^T, its Delassus block C_a A^-1 C_b^T = Z_a^T Z_b, and the
    correction A^-1 C^T lam one backward sweep of Z lam. Y = A^-1 C_r^T took a forward and
    a backward sweep per row. The block is then symmetric positive semi-definite by its
    form. A full-space body's PARDISO factorisation (linear_solver.SparseSolver) serves it;
    a reduced body's block Cholesky does through reduced/contact_rows.CholeskySolves."""

    definite = True

    def __init__(self, factor, keep=False):
        super().__init__(keep=keep)
        self.factor = factor

    def _sweep(self, B):
        return self.factor.forward(B)

    def delassus(self, rows_a, cols_a, rows_b, cols_b):
        return cols_a.T @ cols_b

    def correction(self, cols, lam):
        return self.factor.backward(cols @ lam)


def contact_correction(resolve, C, g, regularize=0.0, tol=1e-12, max_rounds=50, hint=None, compliance=None):
    """Multipliers and velocity correction of one linear solve with contact.

    The step dv of A dv = b is corrected to dv + Y lam, Y = A^-1 C^T, with lam >= 0,
    w = C Y lam + g >= 0 and lam . w = 0 (g = C dv + phi: the rows' gap after the
    unconstrained step). Only the rows that can matter get a solve: the working set starts
    with the rows the unconstrained step violates (or the hint), the LCP (solve_lcp) is solved on it,
    and rows outside it that the corrected step violates join it, until none does. A row
    left out has lam = 0 and w >= 0, so the answer is the LCP on all rows, exactly; the cost
    is one solve per working-set row instead of one per candidate (a pressed sphere has
    most candidates near, not in, the contact).

    hint: optional (m,) bool, rows expected active (the last step's or Newton iteration's
    contacts). When given, the working set starts with these rows alone (the LCP's first
    guess too): a body resting or pressed keeps most of its contacts, and the many rows
    the unconstrained step violates are mostly pushed out by the few that carry the load,
    so this costs a few solves instead of one per violated row. The answer does not
    depend on it (up to the regularisation below).
    regularize: the diagonal shift of solve_lcp as a fraction of the mean diagonal of S
    over the first working set, then fixed for the following rounds.

    compliance: optional residual compliance of the contact points (a reduced body's local
    dent, reduced/residual_compliance.ContactCompliance): its block(a, b) joins S, so
    w = (C Y + W_res) lam + g, and apply(b, lam) adds its share to every row's gap.

    resolve(B) solves A X = B for B (n, k), or resolve is a Solves; C (m, n) dense or scipy
    sparse; g (m,). Returns (lam (m,), correction (n,) = Y lam, info).
    """
    solves = resolve if isinstance(resolve, Solves) else Solves(resolve)
    m, n = C.shape
    lam = np.zeros(m)
    scale = max(float(np.abs(g).max()), 1e-300) if m else 1.0
    violated = g < -tol * scale
    if not violated.any():
        return lam, np.zeros(n), {"rows": m, "working_set": 0, "rounds": 0, "active": 0}
    hint = None if hint is None or not np.any(hint) else np.asarray(hint, dtype=bool)
    work = np.flatnonzero(violated if hint is None else hint)
    # C[idx]: an ndarray's rows, sparse rows, or the dense rows of a
    # reduced/sparse_rows.ContactRowEntries (built once per index set here).
    C_work = C[work]
    Y = solves.columns(C_work)
    S = solves.delassus(C_work, Y, C_work, Y)
    if compliance is not None:
        S = S + compliance.block(work, work)
    shift = regularize * max(float(np.mean(np.diag(S))), 1e-300) if regularize > 0.0 else 0.0
    guess = np.ones(work.size, dtype=bool)
    info = {}
    for rounds in range(1, max_rounds + 1):
        lam_w, info = solve_lcp(S, g[work], tol=tol, shift=shift, active=guess)
        corr = solves.correction(Y, lam_w)
        w = C @ corr + g
        if compliance is not None:
            w += compliance.apply(work, lam_w)
        out = np.ones(m, dtype=bool)
        out[work] = False
        viol = np.flatnonzero(out & (w < -tol * scale))
        if viol.size == 0:
            break
        # Rows the corrected step violates join: their solves and S's new rows and columns.
        C_viol = C[viol]
        Y_new = solves.columns(C_viol)
        S = np.block([[S, solves.delassus(C_work, Y, C_viol, Y_new)],
                      [solves.delassus(C_viol, Y_new, C_work, Y), solves.delassus(C_viol, Y_new, C_viol, Y_new)]])
        if compliance is not None:
            both = np.concatenate([work, viol])
            S[:, work.size:] += compliance.block(both, viol)
            S[work.size:, :work.size] += compliance.block(viol, work)
        Y = np.hstack([Y, Y_new])
        work = np.concatenate([work, viol])
        C_work = sp.vstack([C_work, C_viol]).tocsr() if sp.issparse(C_work) else np.vstack([C_work, C_viol])
        guess = np.concatenate([lam_w > 0, np.ones(viol.size, bool)])
    lam[work] = lam_w
    return lam, corr, {"rows": m, "working_set": int(work.size), "rounds": rounds,
                       "active": int((lam > 0).sum()), "unconverged": bool(viol.size) or info.get("unconverged", False)}


def find_contacts(colliders, x, x_pred, margin):
    """Candidate contacts: (vertex rows (k,), collider index (k,), phi (k,), normals (k, 3)).

    x (S, 3) current and x_pred (S, 3) predicted positions of candidate vertices; a vertex
    is a candidate for a collider when its predicted signed distance is below margin.
    Normals come from the current positions, so a vertex that a fast collider would carry
    past the collider's centre is still pushed out on the side it came from.
    """
    rows, which, phis, normals = [], [], [], []
    for c_idx, col in enumerate(colliders):
        near = col.near(x_pred, margin)
        if near.size == 0:
            continue
        phi_now, n_now = col.signed_distance(x[near])
        rows.append(near)
        which.append(np.full(near.size, c_idx))
        phis.append(phi_now)
        normals.append(n_now)
    if not rows:
        return (np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0), np.zeros((0, 3)))
    if len(rows) == 1:                   # one collider near (the usual case): no copies
        return rows[0], which[0], phis[0], normals[0]
    return np.concatenate(rows), np.concatenate(which), np.concatenate(phis), np.concatenate(normals)


def contact_wrenches(colliders, points, forces, which):
    """Reaction wrench (6,) on each collider: minus the sum of the contact forces on the
    body, torque about the collider's position. Returns {name: (6,)}.

    points, forces (k, 3), which (k,) collider index of each contact. One pass for all
    colliders (bincount per component): the node reads every collider's wrench each step,
    and a numpy pass per collider took 104 us a collider on grasp_lift's 25 contacts."""
    n = len(colliders)
    which = np.asarray(which, dtype=np.int64)
    origin = np.array([col.position for col in colliders]).reshape(n, 3)
    f = -np.asarray(forces, dtype=np.float64).reshape(-1, 3)
    lever = np.asarray(points, dtype=np.float64).reshape(-1, 3) - origin[which]
    per_contact = np.hstack([f, np.cross(lever, f)]) if len(f) else np.zeros((0, 6))
    w = np.zeros((n, 6))
    for j in range(6):                    # six bincounts: columns, not contacts or colliders
        w[:, j] = np.bincount(which, weights=per_contact[:, j], minlength=n)
    return {col.name: w[i] for i, col in enumerate(colliders)}


def _axis(col):
    """Segment (start (3,), end (3,)) a round collider is the offset of: a sphere's centre
    twice, a capsule's axis."""
    half = col.half_height * col.rotation[:, 2] if col.shape == "capsule" else np.zeros(3)
    return col.position - half, col.position + half


def closest_points_on_segment(a, b, p):
    """Closest points (n, 3) of the segment a-b ((3,) each) to points p (n, 3)."""
    ab = b - a
    L2 = float(ab @ ab)
    if L2 == 0.0:
        return np.broadcast_to(a, p.shape).copy()
    t = np.clip((p - a) @ ab / L2, 0.0, 1.0)
    return a + t[:, None] * ab


def sphere_time_of_impact(p0, p1, c0, c1, radius):
    """Continuous contact of points against a moving sphere over one (sub-)step.

    The points move linearly from p0 to p1 ((n, 3) each) while the sphere's centre moves
    linearly from c0 to c1 ((3,) each) over the same interval, t in [0, 1]. Relative to the
    centre a point then moves on the segment d(t) = a + t b, a = p0 - c0, b = (p1 - c1) - a,
    so both answers are closed forms of |d(t)|^2 = radius^2, a quadratic in t:

    toi (n,): the first t at which the point touches the sphere (0 for a point that starts
    inside or on it, inf for one that never touches it in [0, 1]);
    depth (n,): how deep the point gets inside the sphere on the way, radius - min |d(t)|
    (<= 0 for a point that stays outside). A point outside at both ends with a positive
    depth went inside the sphere in between, which contacts evaluated at the end of the
    (sub-)step alone cannot see; a path through the sphere has a depth near its radius.
    """
    p0, p1 = np.asarray(p0, dtype=np.float64), np.asarray(p1, dtype=np.float64)
    c0, c1 = np.asarray(c0, dtype=np.float64), np.asarray(c1, dtype=np.float64)
    a = p0 - c0
    b = (p1 - c1) - a
    bb = np.einsum("ij,ij->i", b, b)
    ab = np.einsum("ij,ij->i", a, b)
    c = np.einsum("ij,ij->i", a, a) - radius * radius
    moving = bb > 0.0
    with np.errstate(divide="ignore", invalid="ignore"):
        t_min = np.where(moving, np.clip(-ab / np.where(moving, bb, 1.0), 0.0, 1.0), 0.0)
        closest = a + t_min[:, None] * b
        depth = radius - np.sqrt(np.einsum("ij,ij->i", closest, closest))
        # The smaller root of bb t^2 + 2 ab t + c = 0, as c / (-ab + sqrt(disc)): no
        # cancellation when the point approaches (ab < 0), the only case with a root ahead.
        disc = ab * ab - bb * c
        approach = moving & (ab < 0.0) & (disc >= 0.0)
        root = np.where(approach, c / np.where(approach, -ab + np.sqrt(np.maximum(disc, 0.0)), 1.0), np.inf)
    toi = np.where(c <= 0.0, 0.0, np.where(root <= 1.0, root, np.inf))
    return toi, depth


def swept_depth(collider, start, p0, p1):
    """How deep points moving linearly from p0 to p1 ((n, 3) each) get inside a round
    collider (sphere or capsule) moving from the pose start = (position (3,), orientation
    (4,)) to its current pose over the same interval: radius - the least distance of each
    point's path to the collider's centre or axis (n,), <= 0 for a path that stays outside.

    A sphere is sphere_time_of_impact's depth. A capsule must keep its orientation (a pure
    translation): in its frame a point's path is then a segment, and the least distance is
    the one between that segment and the axis (Ericson 5.1.9). ValueError for other shapes
    or a rotating capsule."""
    p0, p1 = np.asarray(p0, dtype=np.float64), np.asarray(p1, dtype=np.float64)
    c0 = np.asarray(start[0], dtype=np.float64)
    if collider.shape == "sphere":
        return sphere_time_of_impact(p0, p1, c0, collider.position, collider.radius)[1]
    q0 = np.asarray(start[1], dtype=np.float64)
    if collider.shape != "capsule" or abs(abs(float(q0 @ collider.orientation)) - 1.0) > 1e-12:
        raise ValueError(f"swept_depth: a sphere or a translating capsule, not a {collider.shape}"
                         f"{' that rotates' if collider.shape == 'capsule' else ''}")
    a, b = _axis(collider.at(c0, collider.orientation))           # the axis at the start pose
    d1 = b - a
    rel = (p1 - p0) - (collider.position - c0)                     # each path in the capsule's frame
    s, t = _segment_segment(a, d1, p0, rel)
    # _segment_segment takes the second segments to have length; a point that does not move
    # relative to the capsule is its distance to the axis.
    still = np.einsum("ij,ij->i", rel, rel) == 0.0
    if still.any():
        s[still] = np.clip((p0[still] - a) @ d1 / float(d1 @ d1), 0.0, 1.0)
        t[still] = 0.0
    gap = (a + s[:, None] * d1) - (p0 + t[:, None] * rel)
    return collider.radius - np.sqrt(np.einsum("ij,ij->i", gap, gap))


def _segment_segment(a, d1, c, d2):
    """Parameters s (T,), t (T,) in [0, 1] of the closest points a + s d1 and c + t d2 of
    a segment (a, d1 (3,), d1 != 0) and segments (c, d2 (T, 3)); Ericson 5.1.9."""
    r = a - c
    A = float(d1 @ d1)
    E = (d2 * d2).sum(1)
    f = (d2 * r).sum(1)
    cc = r @ d1
    b = d2 @ d1
    denom = A * E - b * b
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.where(denom > 1e-14 * A * np.maximum(E, 1e-300), np.clip((b * f - cc * E) / denom, 0, 1), 0.0)
        t = np.where(E > 0, (b * s + f) / E, 0.0)
    low, high = t < 0, t > 1
    t = np.clip(t, 0, 1)
    s = np.where(low, np.clip(-cc / A, 0, 1), np.where(high, np.clip((b - cc) / A, 0, 1), s))
    return s, t


def segment_triangle_closest(a, b, tri):
    """Closest pair between the segment a-b ((3,) each) and each triangle (tri (T, 3, 3)).

    Away from an intersection one point of the pair is a segment end or on a triangle edge,
    so the pair is the best of: both ends against the triangle, the segment against the
    three edges. A segment through a triangle gets distance 0.
    Returns points on the segment (T, 3), squared distances (T,), barycentric (T, 3)."""
    from ..loads import closest_points_on_triangles
    T = len(tri)
    A, B, C = tri[:, 0], tri[:, 1], tri[:, 2]
    best_d2, best_bary = closest_points_on_triangles(a, A, B, C)
    best_p = np.broadcast_to(a, (T, 3)).copy()
    d1 = b - a
    if not np.any(d1):
        return best_p, best_d2, best_bary
    d2_b, bary_b = closest_points_on_triangles(b, A, B, C)
    better = d2_b < best_d2
    best_d2[better], best_bary[better], best_p[better] = d2_b[better], bary_b[better], b
    for i, j in ((0, 1), (1, 2), (2, 0)):
        s, t = _segment_segment(a, d1, tri[:, i], tri[:, j] - tri[:, i])
        p = a + s[:, None] * d1
        q = tri[:, i] + t[:, None] * (tri[:, j] - tri[:, i])
        d2 = ((p - q) ** 2).sum(1)
        better = d2 < best_d2
        bary = np.zeros((T, 3))
        bary[:, i], bary[:, j] = 1 - t, t
        best_d2[better], best_bary[better], best_p[better] = d2[better], bary[better], p[better]
    # Segment through the face: the ends on opposite sides and the crossing inside.
    n = np.cross(B - A, C - A)
    ha, hb = ((a - A) * n).sum(1), ((b - A) * n).sum(1)
    cross = (ha * hb < 0)
    if cross.any():
        x = a + (ha[cross] / (ha[cross] - hb[cross]))[:, None] * d1
        d2_x, bary_x = closest_points_on_triangles(x, A[cross], B[cross], C[cross])
        inside = d2_x < 1e-24
        rows = np.flatnonzero(cross)[inside]
        best_d2[rows], best_bary[rows], best_p[rows] = 0.0, bary_x[inside], x[inside]
    return best_p, best_d2, best_bary


# The two culling passes below ran as numpy over every surface triangle each step: a third
# of hammock's contact search (0.375 ms for the longest edge alone, numpy temporaries of
# (T, 3) per edge). Compiled, each is one pass without temporaries.
@njit(cache=True)
def bounding_box(positions):
    """(lo (3,), hi (3,)) of positions (n, 3), n > 0."""
    lo = positions[0].copy()
    hi = positions[0].copy()
    for i in range(1, positions.shape[0]):
        for c in range(3):
            v = positions[i, c]
            if v < lo[c]:
                lo[c] = v
            if v > hi[c]:
                hi[c] = v
    return lo, hi


@njit(cache=True)
def longest_edge_squared(positions, triangles):
    """max over triangles (T, 3) of their squared edge lengths, positions (n, 3)."""
    best = 0.0
    for t in range(triangles.shape[0]):
        for k in range(3):
            i, j = triangles[t, k], triangles[t, (k + 1) % 3]
            d = 0.0
            for c in range(3):
                e = positions[j, c] - positions[i, c]
                d += e * e
            if d > best:
                best = d
    return best


@njit(cache=True)
def triangles_near_segment(positions, triangles, a, b, reach):
    """Indices (k,) of the triangles (T, 3) with a corner closer than reach to the segment
    a-b ((3,) each; a == b for a sphere). positions (n, 3)."""
    n = positions.shape[0]
    ab = b - a
    L2 = ab[0] * ab[0] + ab[1] * ab[1] + ab[2] * ab[2]
    close = np.zeros(n, dtype=np.bool_)
    r2 = reach * reach
    for v in range(n):
        t = 0.0
        if L2 > 0.0:
            t = ((positions[v, 0] - a[0]) * ab[0] + (positions[v, 1] - a[1]) * ab[1]
                 + (positions[v, 2] - a[2]) * ab[2]) / L2
            t = min(max(t, 0.0), 1.0)
        d = 0.0
        for c in range(3):
            e = positions[v, c] - (a[c] + t * ab[c])
            d += e * e
        close[v] = d < r2
    out = np.empty(triangles.shape[0], dtype=np.int64)
    k = 0
    for t in range(triangles.shape[0]):
        if close[triangles[t, 0]] or close[triangles[t, 1]] or close[triangles[t, 2]]:
            out[k] = t
            k += 1
    return out[:k]


@njit(cache=True)
def sphere_triangles_closest(positions, triangles, near, centre, reach):
    """A sphere's narrow phase over the triangles near (k,) of triangles (T, 3): those whose
    bounding sphere (about the corners' mean) comes closer than reach (radius + margin) to
    centre (3,), and their closest points to centre. Returns (kept (s,) indices into near,
    squared distances (s,), barycentric (s, 3)).

    It is find_triangle_contacts' numpy culling and closest_points_on_triangles (Ericson
    5.1.5) operation for operation, sums left to right as numpy's reductions over three
    take them, so the numbers are the same; in one pass, without the dozens of (k, 3)
    temporaries (hammock pressed: 0.5 ms of numpy a step)."""
    k = near.shape[0]
    kept = np.empty(k, dtype=np.int64)
    d2_out = np.empty(k)
    bary_out = np.empty((k, 3))
    tri = np.empty((3, 3))
    s = 0
    for i in range(k):
        for corner in range(3):
            for c in range(3):
                tri[corner, c] = positions[triangles[near[i], corner], c]
        # Cull by the bounding sphere: |centroid - centre| < reach + max |corner - centroid|.
        g0 = ((tri[0, 0] + tri[1, 0]) + tri[2, 0]) / 3.0
        g1 = ((tri[0, 1] + tri[1, 1]) + tri[2, 1]) / 3.0
        g2 = ((tri[0, 2] + tri[1, 2]) + tri[2, 2]) / 3.0
        spread = 0.0
        for corner in range(3):
            e0, e1, e2 = tri[corner, 0] - g0, tri[corner, 1] - g1, tri[corner, 2] - g2
            spread = max(spread, np.sqrt((e0 * e0 + e1 * e1) + e2 * e2))
        e0, e1, e2 = g0 - centre[0], g1 - centre[1], g2 - centre[2]
        if not np.sqrt((e0 * e0 + e1 * e1) + e2 * e2) < reach + spread:
            continue
        # Closest point of the triangle (a, b, c) to p = centre.
        ab0, ab1, ab2 = tri[1, 0] - tri[0, 0], tri[1, 1] - tri[0, 1], tri[1, 2] - tri[0, 2]
        ac0, ac1, ac2 = tri[2, 0] - tri[0, 0], tri[2, 1] - tri[0, 1], tri[2, 2] - tri[0, 2]
        ap0, ap1, ap2 = centre[0] - tri[0, 0], centre[1] - tri[0, 1], centre[2] - tri[0, 2]
        bp0, bp1, bp2 = centre[0] - tri[1, 0], centre[1] - tri[1, 1], centre[2] - tri[1, 2]
        cp0, cp1, cp2 = centre[0] - tri[2, 0], centre[1] - tri[2, 1], centre[2] - tri[2, 2]
        d1 = (ab0 * ap0 + ab1 * ap1) + ab2 * ap2
        d2 = (ac0 * ap0 + ac1 * ap1) + ac2 * ap2
        d3 = (ab0 * bp0 + ab1 * bp1) + ab2 * bp2
        d4 = (ac0 * bp0 + ac1 * bp1) + ac2 * bp2
        d5 = (ab0 * cp0 + ab1 * cp1) + ab2 * cp2
        d6 = (ac0 * cp0 + ac1 * cp1) + ac2 * cp2
        va = d3 * d6 - d5 * d4
        vb = d5 * d2 - d1 * d6
        vc = d1 * d4 - d3 * d2
        denom = (va + vb) + vc
        v = vb / denom if denom != 0 else 0.0
        w = vc / denom if denom != 0 else 0.0
        b0, b1, b2 = (1 - v) - w, v, w
        # The regions outside the face, in closest_points_on_triangles' order (later ones win).
        if va <= 0 and d4 - d3 >= 0 and d5 - d6 >= 0:
            den = (d4 - d3) + (d5 - d6)
            t = min(max((d4 - d3) / (den if den != 0 else 1.0), 0.0), 1.0)
            b0, b1, b2 = 0.0, 1 - t, t
        if vb <= 0 and d2 >= 0 and d6 <= 0:
            t = min(max(d2 / (d2 - d6 if d2 - d6 != 0 else 1.0), 0.0), 1.0)
            b0, b1, b2 = 1 - t, 0.0, t
        if d6 >= 0 and d5 <= d6:
            b0, b1, b2 = 0.0, 0.0, 1.0
        if vc <= 0 and d1 >= 0 and d3 <= 0:
            t = min(max(d1 / (d1 - d3 if d1 - d3 != 0 else 1.0), 0.0), 1.0)
            b0, b1, b2 = 1 - t, t, 0.0
        if d3 >= 0 and d4 <= d3:
            b0, b1, b2 = 0.0, 1.0, 0.0
        if d1 <= 0 and d2 <= 0:
            b0, b1, b2 = 1.0, 0.0, 0.0
        q0 = (b0 * tri[0, 0] + b1 * tri[1, 0]) + b2 * tri[2, 0] - centre[0]
        q1 = (b0 * tri[0, 1] + b1 * tri[1, 1]) + b2 * tri[2, 1] - centre[1]
        q2 = (b0 * tri[0, 2] + b1 * tri[1, 2]) + b2 * tri[2, 2] - centre[2]
        kept[s] = i
        d2_out[s] = (q0 * q0 + q1 * q1) + q2 * q2
        bary_out[s, 0], bary_out[s, 1], bary_out[s, 2] = b0, b1, b2
        s += 1
    return kept[:s], d2_out[:s], bary_out[:s]


def find_triangle_contacts(colliders, positions, triangles, margin, corner=1e-3):
    """Sphere and capsule colliders (unless face_contacts is off) against surface triangles,
    where vertices alone let a round collider slip through a face: the closest point of each
    nearby triangle to the collider's centre (sphere) or axis (capsule).

    positions (S, 3) surface vertices; triangles (T, 3) into them. Returns (tri (k,),
    barycentric (k, 3), collider index (k,), phi (k,), normals (k, 3)); closest points at a
    corner are left to the vertex contacts.
    """
    out = [], [], [], [], []
    round_ = [(c_idx, col) for c_idx, col in enumerate(colliders)
              if col.shape in ("sphere", "capsule") and getattr(col, "face_contacts", True)]
    if not round_ or len(positions) == 0 or len(triangles) == 0:
        return np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros(0, np.int64), np.zeros(0), np.zeros((0, 3))
    # Cull by vertices first (the surface has half as many vertices as triangles): a point
    # of a triangle lies within its longest edge of each corner, so a triangle whose
    # corners are all farther than radius + margin + the longest surface edge from the
    # collider cannot touch it.
    positions = np.ascontiguousarray(positions, dtype=np.float64)
    triangles = np.ascontiguousarray(triangles, dtype=np.int64)
    # A triangle's points lie in the surface's bounding box, and a point within reach of
    # the axis in the axis' box grown by reach: where the two boxes are apart, no face is
    # a contact (hammock's weight before it arrives: the two culling passes below are
    # skipped). The slack keeps the test conservative against round-off.
    lo, hi = bounding_box(positions)
    axes = []
    for c_idx, col in round_:
        a, b = _axis(col)
        reach = (col.radius + margin) * (1.0 + 1e-6) + 1e-12
        if np.all(np.minimum(a, b) - reach <= hi) and np.all(np.maximum(a, b) + reach >= lo):
            axes.append((c_idx, col, a, b))
    if not axes:
        return np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros(0, np.int64), np.zeros(0), np.zeros((0, 3))
    longest = np.sqrt(longest_edge_squared(positions, triangles))
    for c_idx, col, a, b in axes:
        near = triangles_near_segment(positions, triangles, a, b, col.radius + margin + longest)
        if near.size == 0:
            continue
        if col.shape == "sphere":
            # Bounding spheres and closest points compiled (sphere_triangles_closest).
            kept, d2, bary = sphere_triangles_closest(positions, triangles, near, a, col.radius + margin)
            near = near[kept]
            t = positions[triangles[near]]
            centre = np.broadcast_to(a, (len(near), 3))
        else:
            # Then by the triangles' bounding spheres.
            tri_pos = positions[triangles[near]]
            centroid = tri_pos.mean(axis=1)
            reach = np.linalg.norm(tri_pos - centroid[:, None, :], axis=2).max(axis=1)
            gap = np.linalg.norm(centroid - closest_points_on_segment(a, b, centroid), axis=1)
            keep_sphere = gap < col.radius + margin + reach
            near, t = near[keep_sphere], tri_pos[keep_sphere]
            if near.size == 0:
                continue
            centre, d2, bary = segment_triangle_closest(a, b, t)
        dist = np.sqrt(d2)
        keep = (dist < col.radius + margin) & (bary.max(axis=1) < 1.0 - corner) & (dist > 1e-12)
        if not keep.any():
            continue
        q = np.einsum("ki,kij->kj", bary[keep], t[keep])
        n = (q - centre[keep]) / dist[keep, None]
        out[0].append(near[keep])
        out[1].append(bary[keep])
        out[2].append(np.full(keep.sum(), c_idx))
        out[3].append(dist[keep] - col.radius)
        out[4].append(n)
    if not out[0]:
        return np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros(0, np.int64), np.zeros(0), np.zeros((0, 3))
    return tuple(np.concatenate(a) for a in out)
