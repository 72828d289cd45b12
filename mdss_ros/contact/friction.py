"""Coulomb friction in the implicit step: the contact problem with a tangential force.

Each contact l gets three constraint rows in the step's unknowns (normal n_l and two
tangents t1_l, t2_l, all scaled by dt so that a row times the end-of-step velocity is a
displacement over the step), and three multipliers lambda_l = (lambda_n, lambda_t) in
newtons. Eliminating the velocity as in unilateral.py leaves, per contact,

    w = W lambda + g        W = C A^-1 C^T (3m, 3m),  g the rows' value after the free step

where w_n is the gap at the end of the step and w_t the slip over the step relative to
the collider's surface (a moving collider's displacement is folded into g). Coulomb's
law at the end of the step, with the cone radius mu lambda_n:

    0 <= lambda_n  _|_  w_n >= 0
    |lambda_t| <= mu lambda_n;   |lambda_t| < mu lambda_n  =>  w_t = 0         (stick)
                                 |lambda_t| = mu lambda_n  =>  w_t = -g lambda_t, g >= 0 (slip)

Why this formulation (docs/method.md §14, "Friction"):
- It is the exact law, not a relaxation. Anitescu's convex cone (and SAP, which
  regularises it) swaps the normal condition for w_n + mu |w_t| >= 0: a sliding body
  rises by mu |w_t| a step (at 3 m/s, mu 0.5, dt 1/90: 17 mm), the hop the incline test
  forbids. A polyhedral cone (boxed LCP) is anisotropic by 1 - cos(pi/k) unless k is
  large. Staggered projections (Kaufman et al. 2008) solve the same law as here, but as
  an outer loop of two convex problems with no bound on its iterations.
- It sticks exactly: in the stick set the conditions are the linear equations w_t = 0,
  which the last Newton step solves to round-off, and no stiffness is tuned. Slip is
  opposite the force by construction, so friction only removes energy relative to the
  collider (it cannot create it; test_friction.py measures it).
- The problem is small (three unknowns per contact in contact), so it is solved by the
  semismooth Newton method of Alart and Curnier (1991) on the dense W: the conditions
  above are the zeros of

      F_n = lambda_n - max(0, lambda_n - rho w_n)
      F_t = lambda_t - proj_{disk(mu max(lambda_n, 0))}(lambda_t - rho w_t)

  (rho > 0 per contact; rho = 1 / W_nn makes rho W of order one), piecewise smooth, and
  Newton on its generalised Jacobian with a backtracking line search on |F|^2 converges
  in a few iterations from the frictionless answer. Each iteration is one dense LU of
  size 3m, vectorised over the contacts.

Static and kinetic coefficients (effective_mu): a contact that slipped faster than
STICTION_SPEED in the last step feels mu_k, any other mu_s. Switching within the step
instead (mu_k wherever the mu_s answer slips) lets the few micrometres of partial slip
at a loaded block's edges (Cattaneo-Mindlin) drop those contacts to mu_k at once, and the
rest cannot hold: a block at 40 degrees with mu_s 0.9 and mu_k 0.5 slid off its incline.
"""
import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp
from numba import njit

from .unilateral import Solves, contact_correction, member, solve_lcp


#: |F| / (force scale) above which a solve counts as unconverged (restarts, then reported):
#: a stick error w_t of 1e-6 of the displacement the contact forces cause in a step.
UNCONVERGED = 1e-6


def parse_friction(where, value):
    """(mu_s, mu_k) from a scene's colliders.<name>.friction: a number (static = kinetic) or
    {static: mu_s, kinetic: mu_k}; None is (0, 0). Raises ValueError naming the key."""
    if value is None:
        return 0.0, 0.0
    if isinstance(value, dict):
        unknown = sorted(set(value) - {"static", "kinetic"})
        if unknown or "static" not in value:
            raise ValueError(f"{where}.friction: expected a number or {{static: mu_s, kinetic: mu_k}}, got {value!r}")
        mu_s = _coefficient(where + ".friction.static", value["static"])
        mu_k = _coefficient(where + ".friction.kinetic", value.get("kinetic", mu_s))
        if mu_k > mu_s:
            raise ValueError(f"{where}.friction: kinetic ({mu_k:g}) must not exceed static ({mu_s:g}); "
                             f"a contact that starts to slip would need more force to keep slipping")
        return mu_s, mu_k
    mu = _coefficient(where + ".friction", value)
    return mu, mu


def _coefficient(where, value):
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not np.isfinite(value) or value < 0:
        raise ValueError(f"{where}: expected a finite number >= 0 (the Coulomb coefficient), got {value!r}")
    return float(value)


def tangent_basis(normals):
    """Two unit tangents (k, 2, 3) orthogonal to unit normals (k, 3) and to each other,
    right-handed (t1 x t2 = n); t1 is n crossed with the world axis least aligned with n
    (the first of them on a tie, as argmin). Compiled (tangent_kernel): its numpy form (an
    argmin, two crosses, a norm and a stack) took 33 us for the incline's 30 contacts, this
    1.8 us (min of 3,000; session 22)."""
    n = np.ascontiguousarray(normals, dtype=np.float64).reshape(-1, 3)
    out = np.empty((len(n), 2, 3))
    tangent_kernel(n, out)
    return out


@njit(cache=True)
def tangent_kernel(n, out):
    """tangent_basis's loop: n (k, 3), out (k, 2, 3) written. The same operations in the
    same order as the numpy form it replaced (n x e_axis, divided by its norm, then n x t1)."""
    for i in range(n.shape[0]):
        n0, n1, n2 = n[i, 0], n[i, 1], n[i, 2]
        a0, a1, a2 = abs(n0), abs(n1), abs(n2)
        # n x e_0 = (0, n2, -n1); n x e_1 = (-n2, 0, n0); n x e_2 = (n1, -n0, 0)
        if a0 <= a1 and a0 <= a2:
            t0, t1, t2 = n1 * 0.0 - n2 * 0.0, n2 * 1.0 - n0 * 0.0, n0 * 0.0 - n1 * 1.0
        elif a1 <= a2:
            t0, t1, t2 = n1 * 0.0 - n2 * 1.0, n2 * 0.0 - n0 * 0.0, n0 * 1.0 - n1 * 0.0
        else:
            t0, t1, t2 = n1 * 1.0 - n2 * 0.0, n2 * 0.0 - n0 * 1.0, n0 * 0.0 - n1 * 0.0
        norm = np.sqrt(t0 * t0 + t1 * t1 + t2 * t2)
        t0, t1, t2 = t0 / norm, t1 / norm, t2 / norm
        out[i, 0, 0], out[i, 0, 1], out[i, 0, 2] = t0, t1, t2
        out[i, 1, 0] = n1 * t2 - n2 * t1
        out[i, 1, 1] = n2 * t0 - n0 * t2
        out[i, 1, 2] = n0 * t1 - n1 * t0


def collider_displacement(collider, start, points):
    """Displacement (k, 3) over a step of the collider's material points now at points
    (k, 3), from its start pose (position (3,), orientation x y z w) to its current one:
    the velocity a contact's slip is measured against (a moving finger drags the body)."""
    from ..rotations import matrix_from_quat
    if start is None:
        return np.zeros_like(points)
    p0, q0 = start
    R1, R0 = collider.rotation, matrix_from_quat(np.asarray(q0, dtype=np.float64))
    local = (points - collider.position) @ R1                          # R1^T (p - c1)
    return points - (np.asarray(p0, dtype=np.float64) + local @ R0.T)


def solve_coulomb(W, g, mu, lam0=None, tol=1e-12):
    """lambda (m, 3) of the Coulomb contact problem w = W lambda + g (see the module
    docstring). W (3m, 3m) symmetric positive definite (where rows are dependent and W is
    singular, solve_proximal solves it by rounds of this on a shifted W), rows in contact
    order (n, t1, t2); g (3m,); mu (m,) each
    contact's coefficient (static or kinetic: effective_mu). lam0 (m, 3): a first guess
    (default: the frictionless LCP's answer, no tangential force). Returns (lambda (m, 3),
    info) with info["stick"], info["slip"] (m,) bool and info["unconverged"].

    Newton from lam0 settles most steps in one or two iterations (a warm start from the
    last step). Where it does not within NEWTON_FIRST iterations (the contact and stick
    sets keep changing: a body landing or lifting, rows through a few modes, where the
    forces are not unique and Newton jumps between the sets), projected Gauss-Seidel (pgs)
    runs until the law holds to PHYSICAL_TOL (violation), and Newton tries to polish
    that to round-off. The answer is the better of the two; unconverged means the law is
    broken by more than PHYSICAL_TOL."""
    m = len(g) // 3
    if not (isinstance(mu, np.ndarray) and mu.shape == (m,) and mu.dtype == np.float64):
        mu = np.broadcast_to(np.asarray(mu, dtype=np.float64), (m,))     # 3 us: only when needed
    if lam0 is None:
        n_idx = 3 * np.arange(m)
        lam_n, _ = solve_lcp(W[np.ix_(n_idx, n_idx)], g[n_idx], tol=tol)
        lam0 = np.zeros((m, 3))
        lam0[:, 0] = lam_n
    lam, info = _newton(W, g, mu, np.asarray(lam0, dtype=np.float64).reshape(m, 3), tol, NEWTON_FIRST)
    if not info["unconverged"]:
        return lam, dict(info, violation=0.0)
    x, sweeps = project_cone(lam, mu), 0
    viol = violation(W, g, mu, x)
    while sweeps < PGS_SWEEPS and viol > PHYSICAL_TOL:
        x, done = pgs(W, g, mu, x, PGS_CHUNK, 1e-14)
        sweeps += done
        viol = violation(W, g, mu, x)
    lam2, info2 = _newton(W, g, mu, x, tol, NEWTON_FIRST)
    iterations = info["iterations"] + info2["iterations"]
    if info2["unconverged"]:
        # Newton's best iterate can lie outside the cone; Gauss-Seidel's never does.
        info2 = _info(W, g, mu, _rho(W, m), x)
        lam2 = x
        info2["unconverged"] = viol > PHYSICAL_TOL
    else:
        viol = 0.0
    return lam2, dict(info2, iterations=iterations, pgs_sweeps=sweeps, violation=viol)


def violation(W, g, mu, lam):
    """How far lam (m, 3) breaks Coulomb's law, as a length relative to the rows' scale
    (max |g|: the free step's overlap and slip): penetration, a gap where the normal force
    is positive, slip inside the cone, and slip not straight against the friction on its
    rim (lam is taken in the cone: lambda_n >= 0, |lambda_t| <= mu lambda_n)."""
    m = len(mu)
    w = (W @ lam.ravel() + g).reshape(m, 3)
    scale = max(float(np.abs(g).max(initial=0.0)), 1e-300)
    f_scale = max(float(lam[:, 0].max(initial=0.0)), 1e-300)
    pressed = lam[:, 0] > 1e-9 * f_scale
    nt = np.linalg.norm(lam[:, 1:], axis=1)
    rim = pressed & (nt >= mu * lam[:, 0] * (1.0 - 1e-9))
    inside = pressed & ~rim
    t_hat = np.divide(lam[:, 1:], nt[:, None], out=np.zeros((m, 2)), where=nt[:, None] > 0.0)
    along = np.einsum("ki,ki->k", w[:, 1:], t_hat)
    across = np.abs(w[:, 1] * t_hat[:, 1] - w[:, 2] * t_hat[:, 0])
    worst = max(float(np.max(-w[:, 0], initial=0.0)),
                float(np.max(np.abs(w[pressed, 0]), initial=0.0)),
                float(np.max(np.linalg.norm(w[inside, 1:], axis=1), initial=0.0)),
                float(np.max(np.maximum(along[rim], 0.0), initial=0.0)),
                float(np.max(across[rim], initial=0.0)))
    return worst / scale


def project_cone(lam, mu):
    """lam (m, 3) put into the friction cones: lambda_n >= 0, |lambda_t| <= mu lambda_n."""
    out = lam.copy()
    out[:, 0] = np.maximum(out[:, 0], 0.0)
    nt = np.linalg.norm(out[:, 1:], axis=1)
    over = nt > mu * out[:, 0]
    out[over, 1:] *= (mu[over] * out[over, 0] / nt[over])[:, None]
    return out


def _rho(W, m):
    """rho (m,) = 1 / W_nn per contact: rho W is of order one in the Alart-Curnier function."""
    diag = W.diagonal()[0::3]
    return 1.0 / np.maximum(diag, 1e-300 + 1e-12 * (max(float(diag.max()), 0.0) if m else 0.0))


def _force_scale(g, rho, lam):
    """Scale of the forces the residual is measured against: those of lam (m, 3), or
    the force the free step's overlap calls for, rho (-g_n)."""
    if len(rho) == 0:
        return 1e-300
    # Without max(initial=0.0), numpy's Python-level path: 5.4 -> 3.9 us a call (min of 5,000).
    return max(float(np.abs(lam).max()), float((-g[0::3] * rho).max()), 0.0, 1e-300)


def _info(W, g, mu, rho, lam):
    """What _newton reports, for an answer found another way."""
    F, parts = _residual(W, g, mu, rho, lam)
    scale = _force_scale(g, rho, lam)
    residual = float(np.sqrt((F * F).sum())) / scale
    in_contact = lam[:, 0] > 0.0
    return {"iterations": 0, "line_search_cuts": 0, "residual": residual, "stick": in_contact & parts[2],
            "slip": in_contact & ~parts[2], "unconverged": residual > UNCONVERGED}


#: Newton iterations before projected Gauss-Seidel takes over (solve_coulomb), its sweeps
#: (at most, in chunks), and the violation of the law (a fraction of the rows' scale, the
#: free step's overlap: 1e-6 of a millimetre is 1 nm) at which Gauss-Seidel stops.
#: Measured on the caterpillar lifting its segments off a mu 0.5 floor (20-130 contacts
#: through 208 DOFs, W's condition number up to 6e10, forces not unique): Newton left most
#: such solves at 1e-3 - 1e-5 after 80 iterations; Gauss-Seidel converges on all of them
#: (to round-off after 5e4 sweeps), slowly, at 3 us a sweep for 37 contacts. A resting or
#: sliding body's step starts from the last step's forces and Newton ends it exactly.
NEWTON_FIRST = 12
PGS_SWEEPS = 1000
PGS_CHUNK = 100
PHYSICAL_TOL = 1e-6


@njit(cache=True)
def pgs(W, g, mu, lam0, sweeps, tol):
    """Projected Gauss-Seidel on the Coulomb problem: per contact, the normal force by
    lambda_n <- max(0, lambda_n - w_n / W_nn), then the friction by lambda_t <- proj onto
    the disk of radius mu lambda_n of lambda_t - w_t / s, s the larger eigenvalue of the
    2 x 2 W_tt (a scalar step, so a fixed point on the disk's rim slips exactly against
    the force). It converges where rows are dependent, slowly; solve_coulomb polishes its
    answer by Newton. Compiled: a loop over contacts inside a sweep is its nature.
    Returns (lambda (m, 3), sweeps done); stops when no force changes by tol x scale."""
    m = mu.shape[0]
    lam = lam0.copy().reshape(3 * m)
    w = W @ lam + g
    scale = 1e-300
    for i in range(3 * m):
        scale = max(scale, abs(lam[i]))
    for i in range(m):
        scale = max(scale, -g[3 * i] / W[3 * i, 3 * i])
    done = 0
    for sweep in range(sweeps):
        done = sweep + 1
        change = 0.0
        for i in range(m):
            a = 3 * i
            old0, old1, old2 = lam[a], lam[a + 1], lam[a + 2]
            ln = max(0.0, old0 - w[a] / W[a, a])
            if ln != old0:
                d = ln - old0
                for r in range(3 * m):
                    w[r] += W[r, a] * d
            t11, t12, t22 = W[a + 1, a + 1], W[a + 1, a + 2], W[a + 2, a + 2]
            s = 0.5 * (t11 + t22) + np.sqrt(0.25 * (t11 - t22) ** 2 + t12 * t12)
            z1 = old1 - w[a + 1] / s
            z2 = old2 - w[a + 2] / s
            nz = np.sqrt(z1 * z1 + z2 * z2)
            radius = mu[i] * ln
            if nz > radius:
                f = radius / nz
                z1 *= f
                z2 *= f
            d1, d2 = z1 - old1, z2 - old2
            if d1 != 0.0 or d2 != 0.0:
                for r in range(3 * m):
                    w[r] += W[r, a + 1] * d1 + W[r, a + 2] * d2
            lam[a], lam[a + 1], lam[a + 2] = ln, z1, z2
            change = max(change, abs(ln - old0), abs(d1), abs(d2))
        if change <= tol * scale:
            break
    return lam.reshape(m, 3), done


def _residual(W, g, mu, rho, lam):
    """F (m, 3) of the Alart-Curnier function and the pieces its Jacobian needs."""
    m = len(mu)
    w = (W @ lam.ravel() + g).reshape(m, 3)
    zn = lam[:, 0] - rho * w[:, 0]
    touching = zn > 0.0
    F = np.empty((m, 3))
    F[:, 0] = np.where(touching, rho * w[:, 0], lam[:, 0])
    z = lam[:, 1:] - rho[:, None] * w[:, 1:]
    nz = np.linalg.norm(z, axis=1)
    radius = mu * np.maximum(lam[:, 0], 0.0)
    stick = nz <= radius
    z_hat = np.divide(z, nz[:, None], out=np.zeros_like(z), where=nz[:, None] > 0.0)
    F[:, 1:] = np.where(stick[:, None], rho[:, None] * w[:, 1:], lam[:, 1:] - radius[:, None] * z_hat)
    return F, (w, touching, stick, z_hat, nz, radius)


def _jacobian(W, mu, rho, lam, parts):
    """The generalised Jacobian dF / dlambda (3m, 3m) at lam (vectorised over contacts)."""
    w, touching, stick, z_hat, nz, radius = parts
    m = len(mu)
    RW = rho[:, None, None] * W.reshape(m, 3, 3 * m)               # rho W, rows by contact
    J = np.zeros((m, 3, 3 * m))
    idx = np.arange(m)
    # Normal row: rho W_n in contact, else the identity (lambda_n = 0).
    J[:, 0, :] = np.where(touching[:, None], RW[:, 0, :], 0.0)
    J[idx[~touching], 0, 3 * idx[~touching]] = 1.0
    # Tangent rows. Stick: rho W_t. Slip: d(lambda_t - r z_hat) = E_t - z_hat dr - P dz with
    # P = (r / |z|)(I - z_hat z_hat^T), dz = E_t - rho W_t, dr = mu [lambda_n > 0] e_n.
    slip = ~stick
    P = np.divide(radius, nz, out=np.zeros_like(nz), where=nz > 0.0)[:, None, None] * (
        np.eye(2) - z_hat[:, :, None] * z_hat[:, None, :])
    J[:, 1:, :] = np.where(stick[:, None, None], RW[:, 1:, :], np.einsum("kab,kbj->kaj", P, RW[:, 1:, :]))
    s = idx[slip]
    cols = 3 * s[:, None] + np.array([1, 2])
    J[s[:, None, None], np.array([1, 2])[None, :, None], cols[:, None, :]] += np.eye(2) - P[s]
    J[s, 1, 3 * s] -= mu[s] * (lam[s, 0] > 0.0) * z_hat[s, 0]
    J[s, 2, 3 * s] -= mu[s] * (lam[s, 0] > 0.0) * z_hat[s, 1]
    return J.reshape(3 * m, 3 * m)


@njit(cache=True)
def _residual_kernel(W, g, mu, rho, lam, F, stick):
    """Compiled _residual: fills F (m, 3) and stick (m,) bool; returns |F|^2."""
    m = mu.shape[0]
    w = W @ lam.ravel() + g
    merit = 0.0
    for k in range(m):
        wn, w1, w2 = w[3 * k], w[3 * k + 1], w[3 * k + 2]
        ln = lam[k, 0]
        F[k, 0] = rho[k] * wn if ln - rho[k] * wn > 0.0 else ln
        z1 = lam[k, 1] - rho[k] * w1
        z2 = lam[k, 2] - rho[k] * w2
        nz = np.sqrt(z1 * z1 + z2 * z2)
        radius = mu[k] * max(ln, 0.0)
        stick[k] = nz <= radius
        if stick[k]:
            F[k, 1], F[k, 2] = rho[k] * w1, rho[k] * w2
        else:
            h1, h2 = (z1 / nz, z2 / nz) if nz > 0.0 else (0.0, 0.0)
            F[k, 1], F[k, 2] = lam[k, 1] - radius * h1, lam[k, 2] - radius * h2
        merit += F[k, 0] * F[k, 0] + F[k, 1] * F[k, 1] + F[k, 2] * F[k, 2]
    return merit


@njit(cache=True)
def _jacobian_kernel(W, g, mu, rho, lam, J):
    """Compiled _jacobian: fills J (3m, 3m) at lam."""
    m = mu.shape[0]
    n = 3 * m
    w = W @ lam.ravel() + g
    J[:, :] = 0.0
    for k in range(m):
        a = 3 * k
        if lam[k, 0] - rho[k] * w[a] > 0.0:                 # touching: rho W_n
            for j in range(n):
                J[a, j] = rho[k] * W[a, j]
        else:
            J[a, a] = 1.0
        z1 = lam[k, 1] - rho[k] * w[a + 1]
        z2 = lam[k, 2] - rho[k] * w[a + 2]
        nz = np.sqrt(z1 * z1 + z2 * z2)
        radius = mu[k] * max(lam[k, 0], 0.0)
        if nz <= radius:                                    # stick: rho W_t
            for j in range(n):
                J[a + 1, j] = rho[k] * W[a + 1, j]
                J[a + 2, j] = rho[k] * W[a + 2, j]
            continue
        h1, h2 = (z1 / nz, z2 / nz) if nz > 0.0 else (0.0, 0.0)
        c = radius / nz if nz > 0.0 else 0.0
        p11, p12, p22 = c * (1.0 - h1 * h1), -c * h1 * h2, c * (1.0 - h2 * h2)
        for j in range(n):                                  # P rho W_t
            r1, r2 = rho[k] * W[a + 1, j], rho[k] * W[a + 2, j]
            J[a + 1, j] = p11 * r1 + p12 * r2
            J[a + 2, j] = p12 * r1 + p22 * r2
        J[a + 1, a + 1] += 1.0 - p11                        # + (I - P) on its own tangent columns
        J[a + 1, a + 2] += -p12
        J[a + 2, a + 1] += -p12
        J[a + 2, a + 2] += 1.0 - p22
        if lam[k, 0] > 0.0:
            J[a + 1, a] -= mu[k] * h1
            J[a + 2, a] -= mu[k] * h2


@njit(cache=True)
def _newton_kernel(W, g, mu, rho, lam0, tol_abs, max_iterations):
    """_newton's loop compiled (same steps, same line search, same stall rule). Returns
    (best lam (m, 3), iterations, line-search cuts, best |F|^2, ok): ok is False when a
    Newton system was singular (the caller then runs the numpy loop, which falls back to
    least squares)."""
    m = mu.shape[0]
    lam = lam0.copy()
    F = np.empty((m, 3))
    F_t = np.empty((m, 3))
    stick = np.empty(m, dtype=np.bool_)
    stick_t = np.empty(m, dtype=np.bool_)
    J = np.empty((3 * m, 3 * m))
    merit = _residual_kernel(W, g, mu, rho, lam, F, stick)
    best_merit, best_lam = merit, lam.copy()
    it, cuts, stalled = 0, 0, 0
    while it < max_iterations and np.sqrt(merit) > tol_abs and stalled < 2:
        it += 1
        _jacobian_kernel(W, g, mu, rho, lam, J)
        try:
            d = np.linalg.solve(J, -F.ravel()).reshape(m, 3)
        except Exception:
            return best_lam, it, cuts, best_merit, False
        step = 1.0
        while True:
            merit_t = _residual_kernel(W, g, mu, rho, lam + step * d, F_t, stick_t)
            if merit_t <= (1.0 - 1e-4 * step) * merit:
                break
            if step < 1e-6:
                step = 1.0
                merit_t = _residual_kernel(W, g, mu, rho, lam + d, F_t, stick_t)
                break
            step *= 0.5
            cuts += 1
        # The contact set: F's normal row is rho w_n exactly where touching.
        same_sets = np.array_equal(stick_t, stick)
        if same_sets:
            w_old = W @ lam.ravel() + g
            lam_new = lam + step * d
            w_new = W @ lam_new.ravel() + g
            for k in range(m):
                if (lam[k, 0] - rho[k] * w_old[3 * k] > 0.0) != (lam_new[k, 0] - rho[k] * w_new[3 * k] > 0.0):
                    same_sets = False
                    break
        lam = lam + step * d
        F[:, :] = F_t
        stick[:] = stick_t
        merit = merit_t
        stalled = stalled + 1 if (same_sets and merit > 0.25 * best_merit) else 0
        if merit < best_merit:
            best_merit, best_lam = merit, lam.copy()
    return best_lam, it, cuts, best_merit, True


def _newton(W, g, mu, lam0, tol, max_iterations):
    """Alart-Curnier semismooth Newton, compiled (_newton_kernel; its numpy form,
    _newton_numpy, is the tested reference and the fallback for a singular system)."""
    m = len(mu)
    rho = _rho(W, m)
    lam0 = np.array(lam0, dtype=np.float64).reshape(m, 3)
    scale = _force_scale(g, rho, lam0)
    W = np.ascontiguousarray(W, dtype=np.float64)
    lam, it, cuts, merit, ok = _newton_kernel(W, np.ascontiguousarray(g, dtype=np.float64),
                                              np.ascontiguousarray(mu, dtype=np.float64), rho, lam0,
                                              tol * scale, max_iterations)
    if not ok:
        return _newton_numpy(W, g, mu, lam0, tol, max_iterations)
    stick = np.empty(m, dtype=np.bool_)
    _residual_kernel(W, np.ascontiguousarray(g, dtype=np.float64), np.ascontiguousarray(mu, dtype=np.float64),
                     rho, lam, np.empty((m, 3)), stick)
    in_contact = lam[:, 0] > 0.0
    return lam, {"iterations": it, "line_search_cuts": cuts, "residual": float(np.sqrt(merit)) / scale,
                 "stick": in_contact & stick, "slip": in_contact & ~stick,
                 "unconverged": bool(np.sqrt(merit) > UNCONVERGED * scale)}


def _newton_numpy(W, g, mu, lam0, tol, max_iterations):
    """Alart-Curnier semismooth Newton from lam0, with a backtracking line search on
    |F|^2 (Armijo). Where the search finds no decrease the full step is taken anyway
    (non-monotone: a kink of F can make every short step look worse), and the best
    iterate is kept. It ends when |F| is below tol x the scale of the forces."""
    m = len(mu)
    rho = _rho(W, m)
    lam = np.array(lam0, dtype=np.float64).reshape(m, 3)
    F, parts = _residual(W, g, mu, rho, lam)
    scale = _force_scale(g, rho, lam)
    merit = float((F * F).sum())
    best = (merit, lam, parts)
    it, cuts, stalled = 0, 0, 0
    while it < max_iterations and np.sqrt(merit) > tol * scale and stalled < 2:
        it += 1
        J = _jacobian(W, mu, rho, lam, parts)
        try:
            d = sla.solve(J, -F.ravel(), check_finite=False).reshape(m, 3)
        except (np.linalg.LinAlgError, ValueError):
            d = np.linalg.lstsq(J, -F.ravel(), rcond=None)[0].reshape(m, 3)
        step = 1.0
        while True:
            F_t, parts_t = _residual(W, g, mu, rho, lam + step * d)
            merit_t = float((F_t * F_t).sum())
            if merit_t <= (1.0 - 1e-4 * step) * merit:
                break
            if step < 1e-6:
                step = 1.0
                F_t, parts_t = _residual(W, g, mu, rho, lam + d)
                merit_t = float((F_t * F_t).sum())
                break
            step *= 0.5
            cuts += 1
        same_sets = np.array_equal(parts_t[1], parts[1]) and np.array_equal(parts_t[2], parts[2])
        lam, F, parts, merit = lam + step * d, F_t, parts_t, merit_t
        # Rows through few DOFs (a reduced body) make W nearly singular: |F| then stops at a
        # round-off floor above tol. With the contact and stick sets settled a Newton step
        # should reach that floor at once, so two such steps without halving |F|^2 end it.
        stalled = stalled + 1 if (same_sets and merit > 0.25 * best[0]) else 0
        if merit < best[0]:
            best = (merit, lam, parts)
    merit, lam, parts = best
    w, touching, stick, _, nz, radius = parts
    in_contact = lam[:, 0] > 0.0
    slip = in_contact & ~stick
    return lam, {"iterations": it, "line_search_cuts": cuts, "residual": float(np.sqrt(merit)) / scale,
                 "stick": in_contact & stick, "slip": slip,
                 "unconverged": bool(np.sqrt(merit) > UNCONVERGED * scale)}


def _positive(W, shift):
    """(W + shift I, lifted): made positive definite if it is not. An indefinite step
    matrix A (a reduced model's implicit fictitious forces at a large step, solved by LU)
    gives an indefinite W = C A^-1 C^T, where the contact problem has no bounded answer
    (forces of 1e9 N were seen). Its eigenvalues are then lifted to at least the shift, so
    the contact stays finite and the guard judges the step (it retries such steps with
    sub-steps, where A is positive again); lifted says so."""
    Ws = W + shift * np.eye(len(W))
    try:
        np.linalg.cholesky(Ws)
        return Ws, False
    except np.linalg.LinAlgError:
        low = float(np.linalg.eigvalsh(Ws)[0])
        return Ws + (max(shift, 1e-9 * float(np.mean(np.abs(np.diag(W))))) - low) * np.eye(len(W)), True


#: The proximal solve's shift, a fraction of W's mean diagonal, and its most rounds
#: (solve_proximal). Measured on the reduced block at rest on the incline (7 contacts, 21
#: rows through 18 DOFs: W has 3 null directions and its least other eigenvalue is 1e-3 of
#: its mean diagonal): at 1e-9 (the fixed shift this replaces) Newton stalls at |F| of
#: 5e-7 of the forces, the shift's 1e9 amplification of round-off in the null directions
#: against contacts within 1e-8 of the cone's rim; at 1e-6 each solve ends at round-off
#: and a warm-started solve needs one round (180 of 183 on that block; 197 of 206 on the
#: caterpillar at rest with mu 0.5, and over its timeline 175 of 216, at most 5); at 1e-4
#: 20 rounds did not end the block's resting solves (each takes about 1e-4 / 1e-3 of the
#: error on that eigenvalue away).
PROXIMAL_SHIFT = 1e-6
PROXIMAL_ROUNDS = 10


def solve_proximal(W, g, mu, lam0=None, tol=1e-12, shift=None, rounds=PROXIMAL_ROUNDS, definite=False):
    """solve_coulomb for W symmetric positive semi-definite with dependent rows (a reduced
    body: more contact rows than the modes can move apart, so W is singular and its
    forces not unique), by proximal-point iterations (Rockafellar 1976): round k solves
    the Coulomb problem of the shifted W + eps I centred on the last answer,

        w = (W + eps I) lambda + g - eps lambda_k        (eps = shift x mean diag W)

    whose w is the true gap and slip W lambda + g less eps (lambda - lambda_k). Each
    round's problem is well conditioned, and at a fixed point lambda = lambda_k it is the
    unshifted law exactly. A fixed shift instead (solve_coulomb on W + eps I) leaves
    w = -eps lambda: every pressed contact sinks eps lambda_n into its collider, and where
    eps is small enough for that to be negligible its amplification of round-off (1 /
    eps along W's null directions) stalls Newton above the law's tolerance.

    The first round is centred on lam0 (a warm start: the last step's forces), else on
    zero (the least-norm split, as the fixed shift picks). The rounds end when a round
    moves w by at most tol x the rows' scale (max |g|): then the answer's w is within
    that of the true one, which the round solved to round-off. They also end, keeping the
    last answer, when a round moves w by more than half the round before (what is left
    changes along W's null directions, where no force moves anything: rows the body
    cannot all meet exactly), when a round is unconverged, and after `rounds`. W that is
    not positive semi-definite (an indefinite step matrix, _positive) gets one solve of
    the lifted W: its unshifted problem may have no bounded answer. definite: W is known
    positive semi-definite (a Gram matrix Z^T Z from a Cholesky factor's half sweeps), so
    that check is skipped. Returns solve_coulomb's (lambda, info) with
    info["proximal_rounds"]."""
    m = len(g) // 3
    diag = max(float(W.diagonal().mean()), 1e-300)
    eps = (PROXIMAL_SHIFT if shift is None else shift) * diag
    if definite and lam0 is not None and m:
        # A warm start on a known Gram matrix: the rounds in one compiled call (the shifted
        # W formed there), unless a round needs solve_coulomb's fallbacks.
        done = _proximal_compiled(W, g, mu, lam0, eps, tol, rounds)
        if done is not None:
            return done
    if definite:
        Ws, lifted = W.copy(), False
        Ws.flat[::len(W) + 1] += eps           # W + eps I without an identity
    else:
        Ws, lifted = _positive(W, eps)
    if lifted:
        lam, info = solve_coulomb(Ws, g, mu, lam0=lam0, tol=tol)
        return lam, dict(info, proximal_rounds=1)
    centre = np.zeros((m, 3)) if lam0 is None else np.asarray(lam0, dtype=np.float64).reshape(m, 3)
    scale = max(float(np.abs(g).max(initial=0.0)), 1e-300)
    return _proximal_rounds(Ws, g, mu, eps, centre, lam0, tol, scale, rounds)


def _proximal_compiled(W, g, mu, lam0, eps, tol, rounds):
    """solve_proximal's rounds on W + eps I (W a Gram matrix, lam0 (m, 3) the first
    centre) in one compiled call (proximal_kernel), when every round's Newton ends
    converged, which a warm-started step's does unless its contact set changes; None
    otherwise (a singular Newton system or an unconverged round: the caller then runs
    the rounds in Python from the start, with solve_coulomb's Gauss-Seidel and
    least-squares fallbacks). The same operations as _proximal_rounds, bit for bit
    (test_friction.py). Why compiled: the rounds' numpy around the Newton kernel was half
    of solve_proximal's time on the reduced incline's 7 contacts, 52 -> 24 us a call (min
    of 3,000; docs/performance.md, Session 25)."""
    m = len(g) // 3
    f64 = np.float64
    # The kernel adds the shift in float64, and declines non-finite input (its maxima
    # skip NaN where numpy's propagate it): other input goes the Python way.
    if W.dtype != f64:
        return None
    mu = mu if (isinstance(mu, np.ndarray) and mu.shape == (m,) and mu.dtype == f64 and mu.flags.c_contiguous) \
        else np.ascontiguousarray(np.broadcast_to(np.asarray(mu, dtype=f64), (m,)))
    stick = np.empty(m, dtype=np.bool_)
    lam, k, it, cuts, merit, f_scale, ok = proximal_kernel(
        np.ascontiguousarray(W, dtype=f64), np.ascontiguousarray(g, dtype=f64), mu,
        np.ascontiguousarray(np.asarray(lam0, dtype=f64).reshape(m, 3)), eps, tol, rounds,
        NEWTON_FIRST, UNCONVERGED, stick)
    if not ok:
        return None
    in_contact = lam[:, 0] > 0.0
    return lam, {"iterations": it, "line_search_cuts": cuts, "residual": float(np.sqrt(merit)) / f_scale,
                 "stick": in_contact & stick, "slip": in_contact & ~stick, "unconverged": False,
                 "violation": 0.0, "proximal_rounds": k}


@njit(cache=True)
def proximal_kernel(W, g, mu, lam0, eps, tol, rounds, max_iterations, unconverged, stick):
    """_proximal_rounds compiled from a warm start lam0 (m, 3): Ws = W + eps I, rho =
    _rho(Ws), and round k runs _newton_kernel on Ws and g - eps centre from the centre,
    which the round's answer replaces. Returns (lam (m, 3), rounds, the last round's
    iterations, cuts, |F|^2 and force scale, ok) and fills stick (m,) at the answer; ok
    is False for non-finite input and where a round's Newton system was singular or its
    answer unconverged."""
    m = mu.shape[0]
    n = 3 * m
    for i in range(n):
        if not np.isfinite(g[i]) or not np.isfinite(lam0.ravel()[i]):
            return lam0, 0, 0, 0, 0.0, 1e-300, False
        for j in range(n):
            if not np.isfinite(W[i, j]):
                return lam0, 0, 0, 0, 0.0, 1e-300, False
    Ws = W.copy()
    for i in range(n):
        Ws[i, i] += eps
    top = Ws[0, 0]                                  # _rho
    for i in range(1, m):
        top = max(top, Ws[3 * i, 3 * i])
    floor = 1e-300 + 1e-12 * max(top, 0.0)
    rho = np.empty(m)
    for i in range(m):
        rho[i] = 1.0 / max(Ws[3 * i, 3 * i], floor)
    scale = 0.0                                     # max |g|, the rows' scale
    for i in range(n):
        scale = max(scale, abs(g[i]))
    scale = max(scale, 1e-300)
    centre = lam0
    last_move = np.inf
    lam = centre.copy()
    it, cuts, merit, f_scale = 0, 0, 0.0, 1e-300
    gk = g.copy()
    k = 0
    for k in range(1, rounds + 1):
        c = centre.ravel()
        for i in range(n):
            gk[i] = g[i] - eps * c[i]
        f_scale = 0.0                               # _force_scale(gk, rho, centre)
        for i in range(m):
            for j in range(3):
                f_scale = max(f_scale, abs(centre[i, j]))
        top = -gk[0] * rho[0]
        for i in range(1, m):
            top = max(top, -gk[3 * i] * rho[i])
        f_scale = max(max(f_scale, top), 0.0, 1e-300)
        lam, it, cuts, merit, ok = _newton_kernel(Ws, gk, mu, rho, centre, tol * f_scale, max_iterations)
        if not ok or np.sqrt(merit) > unconverged * f_scale:
            return lam, k, it, cuts, merit, f_scale, False
        move = 0.0
        for i in range(m):
            for j in range(3):
                move = max(move, abs(lam[i, j] - centre[i, j]))
        move = eps * move
        centre = lam
        if move <= tol * scale or move > 0.5 * last_move:
            break
        last_move = move
    _residual_kernel(Ws, gk, mu, rho, lam, np.empty((m, 3)), stick)
    return lam, k, it, cuts, merit, f_scale, True


def _proximal_rounds(Ws, g, mu, eps, centre, lam0, tol, scale, rounds):
    """solve_proximal's rounds (see there) in Python, with solve_coulomb's fallbacks."""
    last_move = np.inf
    for k in range(1, rounds + 1):
        lam, info = solve_coulomb(Ws, g - eps * centre.ravel(), mu, lam0=lam0 if k == 1 else centre, tol=tol)
        move = eps * float(np.abs(lam - centre).max(initial=0.0))
        centre = lam
        if info["unconverged"] or move <= tol * scale or move > 0.5 * last_move:
            break
        last_move = move
    return lam, dict(info, proximal_rounds=k)


def rows_of(contacts):
    """Row indices (3k,) of the rows n, t1, t2 of contacts (k,)."""
    return (3 * np.asarray(contacts, dtype=np.int64)[:, None] + np.arange(3)).ravel()


class FrictionRows:
    """The rows (n, t1, t2) of m contacts and their values after the free step, as
    frictional_correction reads them: normal() gives every contact's normal row and gap
    (the contacts outside the working set are checked on these alone), block(contacts)
    the three rows of some contacts and their values (the working set's solve). This one
    holds them all: C (3m, n) (ndarray, scipy sparse or sparse_rows.ContactRowEntries)
    and g (3m,). A reduced body's rows build a contact's tangential rows only when asked
    (reduced/contact_rows.FrictionalRows)."""

    def __init__(self, C, g):
        self.C, self.g = C, np.asarray(g)
        self.m, self.n = C.shape[0] // 3, C.shape[1]

    def normal(self):
        """(C_n (m, n), g_n (m,))."""
        return _normal_rows(self.C), self.g[0::3]

    def block(self, contacts):
        """(rows (3k, n): dense, or scipy sparse when C is, g (3k,)) of contacts (k,)."""
        r = rows_of(contacts)
        return self.C[r], self.g[r]


def frictional_correction(resolve, C, g, mu, regularize=0.0, tol=1e-12, max_rounds=50, hint=None,
                          lam_guess=None, compliance=None):
    """Multipliers and velocity correction of one linear solve with frictional contact.

    As unilateral.contact_correction, with three rows per contact: C (3m, n) in contact
    order (n, t1, t2), dense or scipy sparse; g (3m,) the rows' value after the
    unconstrained step (gap for n, slip relative to the collider for t); or C a
    FrictionRows that gives them (g None). Contacts that
    can matter form a working set: those the free step violates (or the hint), solved with
    solve_coulomb on W = C_w A^-1 C_w^T; contacts outside it whose gap the corrected step
    violates join it, until none does. A contact left out has lambda = 0 and a positive
    gap, so the answer is that of all rows.

    mu (m,) (effective_mu); regularize > 0: the rows may be dependent (a reduced body), so
    the problem is solved by solve_proximal (the frictionless first guess, if any, by
    solve_lcp with that diagonal shift); hint (m,) bool; lam_guess (m, 3) a first guess (the last
    Newton iteration's forces); compliance: a reduced body's residual contact compliance
    on the 3m rows (as in unilateral.contact_correction), added to W. Returns (lam (m, 3), correction (n,), info); info["w"]
    (m, 3) is each contact's gap after the correction, and the working set's slip (zero
    elsewhere: a contact outside it has no force, and its slip is not asked for).
    """
    rows = C if isinstance(C, FrictionRows) else FrictionRows(C, g)
    solves = resolve if isinstance(resolve, Solves) else Solves(resolve)
    m, n = rows.m, rows.n
    lam = np.zeros((m, 3))
    C_n, gn = rows.normal()
    scale = max(float(np.abs(gn).max()), 1e-300) if m else 1.0
    violated = gn < -tol * scale
    if not violated.any() and (hint is None or not np.any(hint)):
        return lam, np.zeros(n), {"rows": m, "working_set": 0, "rounds": 0, "active": 0, "stick": 0, "slip": 0}
    hint = None if hint is None or not np.any(hint) else np.asarray(hint, dtype=bool)
    if hint is None and lam_guess is not None:
        hint = lam_guess[:, 0] > 0
    if hint is None and lam_guess is None:
        # No guess: the frictionless answer's contacts. Far fewer than the rows the free
        # step violates when a collider first meets a reduced body (9 of 121 for a pad on
        # a 30-mode block), whose rows are then strongly dependent and slow Newton down.
        lam_n, _, _ = contact_correction(solves, C_n, gn, regularize=regularize, tol=tol,
                                         compliance=None if compliance is None else compliance.normal())
        hint = lam_n > 0
        lam_guess = np.zeros((m, 3))
        lam_guess[:, 0] = lam_n
    work = np.flatnonzero(violated if not np.any(hint) else hint)
    r = rows_of(work)
    # The working set's rows: dense ndarrays, or scipy sparse rows (a full-space body's).
    C_r, g_r = rows.block(work)
    Y = solves.columns(C_r)
    Wd = solves.delassus(C_r, Y, C_r, Y)
    if compliance is not None:
        Wd = Wd + compliance.block(r, r)
    Wd = 0.5 * (Wd + Wd.T)
    guess = None if lam_guess is None else lam_guess[work]
    info = {}
    for rounds in range(1, max_rounds + 1):
        if regularize > 0.0:
            lam_w, info = solve_proximal(Wd, g_r, mu[work], lam0=guess, tol=tol, definite=solves.definite)
        else:
            lam_w, info = solve_coulomb(_positive(Wd, 0.0)[0], g_r, mu[work], lam0=guess, tol=tol)
        corr = solves.correction(Y, lam_w.ravel())
        # Gaps of every contact, the working set's gap and slip: the rows outside it only
        # decide who joins.
        gap = C_n @ corr + gn
        w_r = C_r @ corr + g_r
        if compliance is not None:
            shared = compliance.apply(r, lam_w.ravel())
            gap += shared[0::3]
            w_r += shared[r]
        out = np.ones(m, dtype=bool)
        out[work] = False
        viol = np.flatnonzero(out & (gap < -tol * scale))
        if viol.size == 0:
            break
        r_new = rows_of(viol)
        C_new, g_new = rows.block(viol)
        Y_new = solves.columns(C_new)
        Wd = np.block([[Wd, solves.delassus(C_r, Y, C_new, Y_new)],
                       [solves.delassus(C_new, Y_new, C_r, Y), solves.delassus(C_new, Y_new, C_new, Y_new)]])
        if compliance is not None:
            both = np.concatenate([r, r_new])
            Wd[:, r.size:] += compliance.block(both, r_new)
            Wd[r.size:, :r.size] += compliance.block(r_new, r)
        Wd = 0.5 * (Wd + Wd.T)
        Y = np.hstack([Y, Y_new])
        work = np.concatenate([work, viol])
        r = np.concatenate([r, r_new])
        g_r = np.concatenate([g_r, g_new])
        C_r = sp.vstack([C_r, C_new]).tocsr() if sp.issparse(C_r) else np.vstack([C_r, C_new])
        guess = np.vstack([lam_w, np.zeros((viol.size, 3))])
    lam[work] = lam_w
    w = np.zeros((m, 3))
    w[:, 0] = gap
    w[work] = w_r.reshape(-1, 3)
    return lam, corr, {"rows": m, "working_set": int(work.size), "rounds": rounds, "w": w,
                       "active": int((lam[:, 0] > 0).sum()), "stick": int(info["stick"].sum()),
                       "slip": int(info["slip"].sum()), "newton": info["iterations"],
                       "unconverged": bool(viol.size) or info.get("unconverged", False)}


def _normal_rows(C):
    """The normal rows C[0::3] of frictional rows C (3m, n): an ndarray's or a sparse
    matrix's slice, or the take() of a reduced body's sparse_rows.ContactRowEntries."""
    if isinstance(C, np.ndarray) or sp.issparse(C):
        return C[0::3]
    return C.take(np.arange(0, C.shape[0], 3))


#: Slip speed (m/s) in the last step above which a contact counts as sliding (kinetic
#: coefficient). The edge micro-slip of a block settling under a tangential load is
#: slower (measured below 1e-4 m/s on the incline of test_friction.py); a sliding body
#: is far faster. Regularised friction models carry the same kind of tolerance.
STICTION_SPEED = 1e-3


def effective_mu(mu_s, mu_k, keys, previous, n_colliders):
    """Each contact's coefficient (k,): mu_k where the same contact (keys (k,), vertex id
    x n_colliders + collider index) slipped faster than STICTION_SPEED in the previous
    step's record (a model's .contact: vertices, which, slip_speed), else mu_s."""
    if previous is None or "slip_speed" not in previous or not np.any(mu_k < mu_s):
        return mu_s
    fast = previous["slip_speed"] > STICTION_SPEED
    sliding = np.asarray(previous["vertices"])[fast] * n_colliders + np.asarray(previous["which"])[fast]
    return np.where(member(keys, sliding), mu_k, mu_s)


def previous_match(previous, keys, n_colliders):
    """(found (k,) bool, src (found.sum(),)): which contacts keys (k,) (as in effective_mu)
    the previous step's record holds, and their index in it; None when it holds none."""
    if previous is None or "slip_speed" not in previous or len(previous["vertices"]) == 0:
        return None
    found = np.empty(len(keys), dtype=np.bool_)
    src = np.empty(len(keys), dtype=np.int64)
    n = _match_kernel(np.ascontiguousarray(previous["vertices"], dtype=np.int64),
                      np.ascontiguousarray(previous["which"], dtype=np.int64), int(n_colliders),
                      np.ascontiguousarray(keys, dtype=np.int64), found, src)
    return None if n == 0 else (found, src[:n])


@njit(cache=True)
def _match_kernel(vertices, which, n_colliders, keys, found, src):
    """previous_match's lookup through a key table (as unilateral.member; keys span about
    the mesh's vertices x colliders; a repeated previous key maps to its last place):
    fills found (k,) and src[:n] in key order, returns n. Compiled: its numpy form (a
    table, four gathers and a mask) was 8 calls a step around nothing."""
    top = 0
    for i in range(keys.shape[0]):
        top = max(top, keys[i])
    for i in range(vertices.shape[0]):
        top = max(top, vertices[i] * n_colliders + which[i])
    table = np.full(top + 1, -1, dtype=np.int64)
    for i in range(vertices.shape[0]):
        table[vertices[i] * n_colliders + which[i]] = i
    n = 0
    for i in range(keys.shape[0]):
        j = table[keys[i]]
        found[i] = j >= 0
        if j >= 0:
            src[n] = j
            n += 1
    return n


def warm_start(previous, keys, tangents, n_colliders, match=None):
    """The last step's forces as this step's first guess: lam (k, 3) in this step's
    normal and tangent directions (tangents (k, 2, 3), read at the found contacts only)
    for contacts keys (k,) (as in effective_mu) found in the previous record, zero for
    new ones; None when none is found. match: previous_match's answer, if already had.
    A resting, held or steadily sliding body then needs one or two Newton
    iterations instead of finding its stick set again from the frictionless answer
    (ten on the caterpillar at rest)."""
    match = previous_match(previous, keys, n_colliders) if match is None else match
    if match is None:
        return None
    found, src = match
    lam = np.zeros((len(keys), 3))
    lam[found, 0] = previous["normal_force"][src]
    lam[found, 1:] = np.einsum("kij,kj->ki", tangents[found], previous["friction"][src])
    return lam


def coefficients(contact, which):
    """(mu_s, mu_k) (k,) of contacts with collider indices which (k,), from a contact spec's
    "friction" list (one (mu_s, mu_k) per collider); None when every coefficient is zero
    (the frictionless solve, unilateral.contact_correction, is then used unchanged)."""
    table = contact.get("friction")
    if not table or not any(mu_s > 0.0 for mu_s, _ in table):
        return None
    table = np.asarray(table, dtype=np.float64).reshape(-1, 2)
    return table[which, 0], table[which, 1]


def moving_colliders(contact):
    """Indices of the spec's colliders that moved over the step (their "starts" pose, one
    or None per collider, differs from the current one): the only ones that drag."""
    starts = contact.get("starts") or [None] * len(contact["colliders"])
    return [c_idx for c_idx, (col, start) in enumerate(zip(contact["colliders"], starts))
            if start is not None and not (np.array_equal(start[0], col.position)
                                          and np.array_equal(start[1], col.orientation))]


def collider_slip(contact, which, points, tangents, moving=None):
    """The rows' share of the colliders' own motion: minus the tangential displacement
    (k, 2) over the step of the collider surface at the contact points (k, 3) (tangents
    (k, 2, 3)), from the spec's "starts" (one start pose or None per collider). A fixed
    collider gives zeros. One vectorised pass per moving collider (moving: their indices,
    moving_colliders' answer when already had)."""
    out = np.zeros((len(which), 2))
    starts = contact.get("starts") or [None] * len(contact["colliders"])
    for c_idx in (moving_colliders(contact) if moving is None else moving):
        col, start = contact["colliders"][c_idx], starts[c_idx]
        sel = np.flatnonzero(which == c_idx)
        if sel.size:
            d = collider_displacement(col, start, points[sel])
            out[sel] = -np.einsum("kj,kij->ki", d, tangents[sel])
    return out
