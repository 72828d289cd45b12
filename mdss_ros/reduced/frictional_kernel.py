"""The Coulomb correction of a reduced body's linear solve in one compiled call
(docs/method.md §14.1; contact/friction.frictional_correction is its reference).

With A = P^T L L^T P the step's block Cholesky factor and C_w (3k, S) the rows n, t1, t2
of a working set of k contacts,

    Z = L^-1 P C_w^T  (S, 3k),    W = Z^T Z  (3k, 3k),    g_w = C_w v + g3_w  (3k,),

the forces lam_w (k, 3) solve the Coulomb problem on (W, g_w) by proximal rounds
(friction.solve_proximal), the correction is dv = P^T L^-T Z lam_w (S,), and every
contact's gap C_n dv + g_n decides who joins the working set, until no contact outside it
is violated.

Why compiled: on the reduced incline (48 candidates, 7 in contact) frictional_correction
took 0.088 ms a call in numpy around its 0.020 ms of compiled Newton rounds, this kernel
0.027; on the caterpillar's rough floor (814 candidates, 35 in contact) 0.60 and 0.50
(min of 300 calls at one state, two runs; `micro.py`, docs/performance.md "Session 30").

The kernel reads the rows as reduced/sparse_rows.ContactRowEntries entries, three per
contact in slot order (every contact's rows built), and declines (returns -1, nothing
written that the caller keeps) whatever frictional_correction would hand to its Python
fallbacks: a round whose Newton system is singular or unconverged (the proximal kernel's
ok), or a working set still growing after max_rounds. The caller then runs
frictional_correction. The answer equals frictional_correction's to round-off, not bit
for bit: W = Z^T Z is numba's BLAS product of Z^T's rows here, numpy's of Z there, and
the correction's sums run in another order (test_frictional_kernel.py).
"""
import numpy as np
from numba import njit

from ..contact.friction import (NEWTON_FIRST, PROXIMAL_ROUNDS, PROXIMAL_SHIFT, UNCONVERGED, proximal_kernel,
                                tangent_kernel)
from .block_cholesky import BlockCholesky, backward_blocks, forward_blocks
from .sparse_rows import ContactRowEntries, row_entries_kernel

#: Entries of the kernel's info array (ints): working set size, rounds of the working
#: set, contacts with a force, of them sticking, slipping, and the last proximal
#: round's Newton iterations.
INFO = ("working_set", "rounds", "active", "stick", "slip", "newton")


@njit(cache=True)
def vertex_rows_kernel(near, verts, phi, normals, x, U, row_domain, vertex_row, R, c, q_index, mask, frame_cols, dt,
                       moving, C, V, W, keep, tangents, cols, vals, count, g3, rigid3):
    """The rows n, t1, t2 of k vertex candidates (contact_rows.ContactRows._contact_rows
    for a body of subspace domains without face contacts or residual compliance): near
    (k,) their rows of the searched positions x (n_s, 3), phi (k,) and normals (k, 3) the
    colliders' at them. A candidate whose normal row is zero to round-off (a pinned
    vertex: 1e-12 of the largest row's norm, as _contact_rows) cannot be pushed out and is
    dropped. Writes, for the m kept (returned): keep[:m] their candidate indices,
    tangents[:m] (friction.tangent_basis), the rows' entries at 3 a + (0, 1, 2)
    (row_entries_kernel; cols, vals (3k, w) need no zeroing, count is zeroed here),
    g3[:m] the rows' constant parts (phi plus the rigid share; the tangential rows'
    collider slip is the caller's) and rigid3[:m] the rigid share dt d . (V + W x (x - C))
    of a co-rotating step (moving; else zero)."""
    k = near.shape[0]
    t_all = np.empty((k, 2, 3))
    tangent_kernel(normals, t_all)
    dirs = np.empty((k, 3, 3))
    xv = np.empty((k, 3))
    vrow = np.empty(k, dtype=np.int64)
    for i in range(k):
        for j in range(3):
            dirs[i, 0, j] = normals[i, j]
            dirs[i, 1, j] = t_all[i, 0, j]
            dirs[i, 2, j] = t_all[i, 1, j]
            xv[i, j] = x[near[i], j]
        vrow[i] = vertex_row[verts[i]]
    row_of = np.arange(k)
    for o in range(3 * k):
        count[o] = 0
    row_entries_kernel(dirs, vrow, U, row_domain, R, c, xv, q_index, mask, frame_cols, row_of, dt, cols, vals, count)
    # The normal rows' norms (a vertex row's columns are distinct: no entries to merge).
    top = 0.0
    norms = np.empty(k)
    for i in range(k):
        acc = 0.0
        o = 3 * i
        for t in range(count[o]):
            acc += vals[o, t] * vals[o, t]
        norms[i] = np.sqrt(acc)
        top = max(top, norms[i])
    m = 0
    for i in range(k):
        if norms[i] > 1e-12 * max(top, 1e-300):
            keep[m] = i
            for j in range(3):
                o, o_new = 3 * i + j, 3 * m + j
                if o_new < o:               # compacted in place: row o_new's own was read before
                    count[o_new] = count[o]
                    for t in range(count[o]):
                        cols[o_new, t] = cols[o, t]
                        vals[o_new, t] = vals[o, t]
                tangents[m, 0, j] = t_all[i, 0, j]
                tangents[m, 1, j] = t_all[i, 1, j]
            for j in range(3):
                r = 0.0
                if moving:
                    a0, a1, a2 = xv[i, 0] - C[0], xv[i, 1] - C[1], xv[i, 2] - C[2]
                    v0 = V[0] + (W[1] * a2 - W[2] * a1)
                    v1 = V[1] + (W[2] * a0 - W[0] * a2)
                    v2 = V[2] + (W[0] * a1 - W[1] * a0)
                    r = dt * (dirs[i, j, 0] * v0 + dirs[i, j, 1] * v1 + dirs[i, j, 2] * v2)
                rigid3[m, j] = r
            g3[m, 0] = phi[i] + rigid3[m, 0]
            g3[m, 1] = rigid3[m, 1]
            g3[m, 2] = rigid3[m, 2]
            m += 1
    return m


@njit(cache=True)
def _row_dot(cols, vals, count, o, x):
    acc = 0.0
    for t in range(count[o]):
        acc += vals[o, t] * x[cols[o, t]]
    return acc


@njit(cache=True)
def frictional_kernel(cols, vals, count, slot, g3, v, mu, guess, L, perm, po, later_ptr, later_idx, tol,
                      max_rounds, lam, corr, w, info):
    """frictional_correction for m contacts from the warm start guess (m, 3).

    cols, vals, count: ContactRowEntries of the rows (3 per built contact), contact i's
    rows at 3 slot[i] + (0, 1, 2); g3 (m, 3) their constant parts; v (S,) the free step's
    velocities; mu (m,); L, perm, po, later_ptr, later_idx: block_cholesky's factor;
    tol: the solve's tolerance; max_rounds of the working set. Writes lam (m, 3), corr
    (S,), w (m, 3) (every contact's gap, and the working set's slip) and info (len(INFO),)
    and returns 0; 1 when no contact is violated by the free step (lam, corr zero, w and
    info unwritten, as frictional_correction's early answer); -1 when declined."""
    m = slot.shape[0]
    S = v.shape[0]
    gn = np.empty(m)                        # every contact's gap after the free step
    scale = 0.0
    for i in range(m):
        gn[i] = _row_dot(cols, vals, count, 3 * slot[i], v) + g3[i, 0]
        scale = max(scale, abs(gn[i]))
    scale = max(scale, 1e-300) if m else 1.0
    n_viol = 0
    for i in range(m):
        if gn[i] < -tol * scale:
            n_viol += 1
    for i in range(m):
        for j in range(3):
            lam[i, j] = 0.0
    for i in range(S):
        corr[i] = 0.0
    if n_viol == 0:
        return 1
    # The working set: the guess's contacts, or those the free step violates.
    n_hint = 0
    for i in range(m):
        if guess[i, 0] > 0.0:
            n_hint += 1
    work = np.empty(m, dtype=np.int64)
    in_work = np.zeros(m, dtype=np.bool_)
    k = 0
    for i in range(m):
        if (guess[i, 0] > 0.0) if n_hint else (gn[i] < -tol * scale):
            work[k] = i
            in_work[i] = True
            k += 1
    place = np.empty(S, dtype=np.int64)     # each column's place in elimination order
    for s in range(S):
        place[perm[s]] = s
    Zt = np.empty((3 * m, S))               # the working set's half-swept columns Z^T, in work order
    g_w = np.empty(3 * m)
    lam0 = np.zeros((m, 3))                 # each round's first guess, in work order
    for a in range(k):
        for j in range(3):
            lam0[a, j] = guess[work[a], j]
    done = 0                                # contacts whose columns are in Z
    lam_w = lam0[:k].copy()
    gap = np.empty(m)
    x = np.empty(S)
    rounds = 0
    viol = 0
    it = 0
    stick = np.empty(0, dtype=np.bool_)
    for rounds in range(1, max_rounds + 1):
        # Columns, values and W of the contacts that joined.
        y = np.zeros((S, 3 * (k - done)))
        for a in range(done, k):
            i = work[a]
            for j in range(3):
                o = 3 * slot[i] + j
                c = 3 * (a - done) + j
                for t in range(count[o]):
                    y[place[cols[o, t]], c] += vals[o, t]
                g_w[3 * a + j] = _row_dot(cols, vals, count, o, v) + g3[i, j]
        forward_blocks(L, po, later_ptr, later_idx, y)
        for s in range(S):
            for c in range(3 * (k - done)):
                Zt[3 * done + c, s] = y[s, c]
        done = k
        n = 3 * k
        # W = Z^T Z by BLAS (numba's np.dot): 105 rows through 208 DOFs on the caterpillar's
        # floor, where a loop took 1.3 ms. Symmetrised as frictional_correction does.
        Zk = Zt[:n]
        W = np.dot(Zk, Zk.T)
        for a in range(n):
            for b in range(a):
                W[a, b] = W[b, a] = 0.5 * (W[a, b] + W[b, a])
        diag = 0.0
        for a in range(n):
            diag += W[a, a]
        diag = max(diag / n, 1e-300)
        mu_w = np.empty(k)
        for a in range(k):
            mu_w[a] = mu[work[a]]
        stick = np.empty(k, dtype=np.bool_)
        lam_w, _k, it, _cuts, _merit, _f, ok = proximal_kernel(W, g_w[:n].copy(), mu_w, lam0[:k].copy(),
                                                                PROXIMAL_SHIFT * diag, tol, PROXIMAL_ROUNDS,
                                                                NEWTON_FIRST, UNCONVERGED, stick)
        if not ok:
            return -1
        # The correction P^T L^-T Z lam_w, and every contact's gap under it.
        z = np.zeros((S, 1))
        for a in range(n):
            la = lam_w[a // 3, a % 3]
            for s in range(S):
                z[s, 0] += Zt[a, s] * la
        backward_blocks(L, po, later_ptr, later_idx, z)
        for s in range(S):
            x[perm[s]] = z[s, 0]
        viol = 0
        for i in range(m):
            gap[i] = _row_dot(cols, vals, count, 3 * slot[i], x) + gn[i]
            if not in_work[i] and gap[i] < -tol * scale:
                viol += 1
        if viol == 0:
            break
        if rounds == max_rounds:
            return -1
        for a in range(k):
            for j in range(3):
                lam0[a, j] = lam_w[a, j]
        for i in range(m):
            if not in_work[i] and gap[i] < -tol * scale:
                work[k] = i
                in_work[i] = True
                for j in range(3):
                    lam0[k, j] = 0.0
                k += 1
    active = n_stick = 0
    for a in range(k):
        i = work[a]
        for j in range(3):
            lam[i, j] = lam_w[a, j]
        if lam_w[a, 0] > 0.0:
            active += 1
            if stick[a]:
                n_stick += 1
    for s in range(S):
        corr[s] = x[s]
    for i in range(m):
        w[i, 0] = gap[i]
        w[i, 1] = 0.0
        w[i, 2] = 0.0
    for a in range(k):
        i = work[a]
        for j in range(3):
            w[i, j] = _row_dot(cols, vals, count, 3 * slot[i] + j, x) + g_w[3 * a + j]
    info[0], info[1], info[2], info[3], info[4], info[5] = k, rounds, active, n_stick, active - n_stick, it
    return 0



def compiled_correction(rows, v, guess, factor, tol=1e-12, max_rounds=50):
    """friction.frictional_correction(CholeskySolves(factor), rows.at(v), None, rows.mu,
    regularize=1e-9, lam_guess=guess) in one frictional_kernel call: (lam (m, 3),
    correction (S,), info) as it returns them, or None where the kernel declines or does
    not apply (some contact's rows not built, rows not held as ContactRowEntries, no warm
    start). rows: a reduced body's contact_rows.FrictionalRows; v (S,) the free step's
    velocities; guess (m, 3) the warm start; factor: the step's
    block_cholesky.BlockCholesky."""
    m = len(rows.g_n)
    entries = rows.rows3
    if (guess is None or m == 0 or rows.n_built != m or not isinstance(entries, ContactRowEntries)
            or not isinstance(factor, BlockCholesky)):
        return None
    S = len(v)
    lam, corr, w = np.empty((m, 3)), np.empty(S), np.empty((m, 3))
    info = np.zeros(len(INFO), dtype=np.int64)
    # A writable copy always: a read-only array would compile a second variant of the kernel.
    mu = np.broadcast_to(np.asarray(rows.mu, dtype=np.float64), (m,)).copy()
    status = frictional_kernel(entries.cols, entries.vals, entries.count, rows.slot, rows.g3,
                               np.ascontiguousarray(v, dtype=np.float64), mu,
                               np.ascontiguousarray(guess, dtype=np.float64), factor.L, factor.perm, factor.po,
                               factor.later_ptr, factor.later_idx, tol, max_rounds, lam, corr, w, info)
    if status < 0:
        return None
    if status == 1:
        return lam, corr, {"rows": m, "working_set": 0, "rounds": 0, "active": 0, "stick": 0, "slip": 0}
    out = {"rows": m, **{key: int(val) for key, val in zip(INFO, info)}, "w": w, "unconverged": False}
    return lam, corr, out


@njit(cache=True)
def record_kernel(lam, normals, tangents, w, dt, cols, vals, count, slot, rigid3, Q, active, forces, friction, slip):
    """The contact record of a step's Coulomb answer (fem/backward_euler.contact_forces,
    and FrictionalRows.work): lam (m, 3), normals (m, 3), tangents (m, 2, 3), w (m, 3)
    the solve's gaps and slips, the rows' entries (3 per contact at 3 slot + j) with their
    rigid shares rigid3 (m, 3), Q (S,) the step's velocities. Writes, for the n contacts
    with lam_n > 0 (returned first): active[:n] their indices, forces[:n] (normal plus
    friction, on the body), friction[:n] lam_t1 t1 + lam_t2 t2 and slip[:n] |w_t| / dt;
    returns (n, the work lam . (C3 Q + rigid3) of every contact with a force)."""
    m = lam.shape[0]
    n = 0
    work = 0.0
    for i in range(m):
        if lam[i, 0] != 0.0 or lam[i, 1] != 0.0 or lam[i, 2] != 0.0:
            for j in range(3):
                o = 3 * slot[i] + j
                acc = 0.0
                for t in range(count[o]):
                    acc += vals[o, t] * Q[cols[o, t]]
                work += lam[i, j] * (acc + rigid3[i, j])
        if lam[i, 0] > 0.0:
            active[n] = i
            for j in range(3):
                f = lam[i, 1] * tangents[i, 0, j] + lam[i, 2] * tangents[i, 1, j]
                friction[n, j] = f
                forces[n, j] = lam[i, 0] * normals[i, j] + f
            slip[n] = np.sqrt(w[i, 1] * w[i, 1] + w[i, 2] * w[i, 2]) / dt
            n += 1
    return n, work


@njit(cache=True)
def warm_kernel(keys, tangents, mu_s, mu_k, prev_keys, prev_slip, prev_normal, prev_friction, stiction, kinetic,
                mu, guess):
    """friction.effective_mu, previous_match and warm_start in one pass, for contacts keys
    (m,) (vertex id x colliders + collider) with tangents (m, 2, 3) and coefficients mu_s,
    mu_k (m,), against the last step's record: its keys (p,), slip_speed, normal_force
    (p,) and friction (p, 3). Writes mu (m,) (mu_k where the same contact slid faster than
    stiction, when kinetic: some mu_k < mu_s) and guess (m, 3) (the last forces in this
    step's directions, zero for a new contact); returns how many contacts were found. A
    repeated previous key maps to its last place, as previous_match's table."""
    top = 0
    for i in range(keys.shape[0]):
        top = max(top, keys[i])
    for i in range(prev_keys.shape[0]):
        top = max(top, prev_keys[i])
    table = np.full(top + 1, -1, dtype=np.int64)
    slid = np.zeros(top + 1, dtype=np.bool_)
    for i in range(prev_keys.shape[0]):
        table[prev_keys[i]] = i
        if kinetic and prev_slip[i] > stiction:
            slid[prev_keys[i]] = True
    n = 0
    for i in range(keys.shape[0]):
        mu[i] = mu_k[i] if slid[keys[i]] else mu_s[i]
        j = table[keys[i]]
        if j < 0:
            guess[i, 0] = guess[i, 1] = guess[i, 2] = 0.0
            continue
        n += 1
        guess[i, 0] = prev_normal[j]
        for a in range(2):
            guess[i, 1 + a] = (tangents[i, a, 0] * prev_friction[j, 0] + tangents[i, a, 1] * prev_friction[j, 1]
                               + tangents[i, a, 2] * prev_friction[j, 2])
    return n
