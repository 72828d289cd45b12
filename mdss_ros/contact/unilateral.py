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
import scipy.linalg as sla


def solve_lcp(S, q, max_iterations=None, tol=1e-12, regularize=0.0):
    """lambda >= 0 with w = S lambda + q >= 0 and lambda . w = 0, for S (m, m) SPD.

    Active-set (block principal pivoting, one index at a time); returns (lambda, info).
    regularize > 0 adds that fraction of mean(diag S) to the diagonal: for reduced bodies
    with more contact rows than DOFs, where S is singular (the total force is determined
    but not its split), it picks the least-norm split at a constraint error of that order.
    """
    m = len(q)
    lam = np.zeros(m)
    if m == 0:
        return lam, {"iterations": 0, "active": 0}
    if regularize > 0.0:
        S = S + regularize * max(float(np.mean(np.diag(S))), 1e-300) * np.eye(m)
    # Start from the constraints the unconstrained step violates: usually the final set.
    active = q < 0.0
    scale = max(float(np.abs(q).max()), 1e-300)
    max_iterations = max_iterations or 10 * m + 10
    for it in range(max_iterations):
        lam[:] = 0.0
        if active.any():
            idx = np.flatnonzero(active)
            Sa = S[np.ix_(idx, idx)]
            try:
                lam[idx] = sla.solve(Sa, -q[idx], assume_a="pos", check_finite=False)
            except (np.linalg.LinAlgError, ValueError):
                lam[idx] = np.linalg.lstsq(Sa, -q[idx], rcond=None)[0]
        neg = active & (lam < -tol * scale)
        if neg.any():
            # Drop the most negative multiplier (a contact that pulls).
            k = np.flatnonzero(neg)[np.argmin(lam[neg])]
            active[k] = False
            continue
        w = S @ lam + q
        viol = (~active) & (w < -tol * scale)
        if not viol.any():
            return np.maximum(lam, 0.0), {"iterations": it + 1, "active": int(active.sum())}
        k = np.flatnonzero(viol)[np.argmin(w[viol])]
        active[k] = True
    return np.maximum(lam, 0.0), {"iterations": max_iterations, "active": int(active.sum()), "unconverged": True}


def contact_correction(resolve, C, g, regularize=0.0, tol=1e-12, max_rounds=50):
    """Multipliers and velocity correction of one linear solve with contact.

    The step dv of A dv = b is corrected to dv + Y lam, Y = A^-1 C^T, with lam >= 0,
    w = C Y lam + g >= 0 and lam . w = 0 (g = C dv + phi: the rows' gap after the
    unconstrained step). Only the rows that can matter get a solve: the working set starts
    with the rows the unconstrained step violates, the LCP (solve_lcp) is solved on it,
    and rows outside it that the corrected step violates join it, until none does. A row
    left out has lam = 0 and w >= 0, so the answer is the LCP on all rows, exactly; the cost
    is one solve per working-set row instead of one per candidate (a pressed sphere has
    most candidates near, not in, the contact).

    resolve(B) solves A X = B for B (n, k); C (m, n) dense or scipy sparse; g (m,).
    Returns (lam (m,), correction (n,) = Y lam, info).
    """
    m, n = C.shape
    lam = np.zeros(m)
    scale = max(float(np.abs(g).max()), 1e-300) if m else 1.0
    work = np.flatnonzero(g < -tol * scale)
    if work.size == 0:
        return lam, np.zeros(n), {"rows": m, "working_set": 0, "rounds": 0, "active": 0}
    dense_rows = (lambda idx: C[idx].T) if isinstance(C, np.ndarray) else (lambda idx: C[idx].T.toarray())
    Y = np.zeros((n, 0))
    lam_w = np.zeros(0)
    info = {}
    for rounds in range(1, max_rounds + 1):
        new = work[Y.shape[1]:]
        Y = np.hstack([Y, np.asarray(resolve(np.ascontiguousarray(dense_rows(new)))).reshape(n, -1)])
        S = np.asarray(C[work] @ Y)
        lam_w, info = solve_lcp(S, g[work], tol=tol, regularize=regularize)
        corr = Y @ lam_w
        w = C @ corr + g
        out = np.ones(m, dtype=bool)
        out[work] = False
        viol = np.flatnonzero(out & (w < -tol * scale))
        if viol.size == 0:
            break
        work = np.concatenate([work, viol])
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
        phi_pred, _ = col.signed_distance(x_pred)
        near = np.flatnonzero(phi_pred < margin)
        if near.size == 0:
            continue
        phi_now, n_now = col.signed_distance(x[near])
        rows.append(near)
        which.append(np.full(near.size, c_idx))
        phis.append(phi_now)
        normals.append(n_now)
    if not rows:
        return (np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0), np.zeros((0, 3)))
    return np.concatenate(rows), np.concatenate(which), np.concatenate(phis), np.concatenate(normals)


def contact_wrenches(colliders, points, forces, which):
    """Reaction wrench (6,) on each collider: minus the sum of the contact forces on the
    body, torque about the collider's position. Returns {name: (6,)}."""
    out = {}
    for c_idx, col in enumerate(colliders):
        sel = which == c_idx
        f = -forces[sel]
        tau = np.cross(points[sel] - col.position, f).sum(0) if sel.any() else np.zeros(3)
        out[col.name] = np.concatenate([f.sum(0), tau])
    return out


def find_triangle_contacts(colliders, positions, triangles, margin, corner=1e-3):
    """Sphere colliders (with face_contacts) against surface triangles, where vertices alone
    let a sphere slip through a face: the closest point of each nearby triangle to the
    sphere's centre.

    positions (S, 3) surface vertices; triangles (T, 3) into them. Returns (tri (k,),
    barycentric (k, 3), collider index (k,), phi (k,), normals (k, 3)); closest points at a
    corner are left to the vertex contacts.
    """
    from ..loads import closest_points_on_triangles
    out = [], [], [], [], []
    for c_idx, col in enumerate(colliders):
        if col.shape != "sphere" or not col.face_contacts:
            continue
        tri_pos = positions[triangles]
        # Cheap cull by the triangles' bounding spheres.
        centroid = tri_pos.mean(axis=1)
        reach = np.linalg.norm(tri_pos - centroid[:, None, :], axis=2).max(axis=1)
        near = np.flatnonzero(np.linalg.norm(centroid - col.position, axis=1) < col.radius + margin + reach)
        if near.size == 0:
            continue
        t = tri_pos[near]
        d2, bary = closest_points_on_triangles(col.position, t[:, 0], t[:, 1], t[:, 2])
        dist = np.sqrt(d2)
        keep = (dist < col.radius + margin) & (bary.max(axis=1) < 1.0 - corner) & (dist > 1e-12)
        if not keep.any():
            continue
        q = np.einsum("ki,kij->kj", bary[keep], t[keep])
        n = (q - col.position) / dist[keep, None]
        out[0].append(near[keep])
        out[1].append(bary[keep])
        out[2].append(np.full(keep.sum(), c_idx))
        out[3].append(dist[keep] - col.radius)
        out[4].append(n)
    if not out[0]:
        return np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros(0, np.int64), np.zeros(0), np.zeros((0, 3))
    return tuple(np.concatenate(a) for a in out)
