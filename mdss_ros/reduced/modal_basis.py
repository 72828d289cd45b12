"""Per-domain subspace bases: linear modes plus modal derivatives, mass-PCA (docs/method.md §6).

A domain is a rigid frame plus a subspace ``x_l = c + R (r_l + U_l q)``. Its basis U must be
mass-orthonormal (``U^T M U = I``) and, when the domain has rigid DOFs, mass-orthogonal to the
six rigid modes of the domain so that deformation moves neither its mass centre nor its
frame. The construction follows Barbic and James 2005:

1. Linear modes: the smallest eigenpairs of ``K phi = lambda M phi`` on the free DOFs of the
   sub-mesh, M the lumped (diagonal) mass handed in by the caller. Shift-invert Lanczos
   (ARPACK through ``scipy.sparse.linalg.eigsh``) with a small negative shift; for a free
   domain the rigid space is projected out of the shift-invert operator explicitly, so the
   six zero modes never appear (nothing is identified "by gap"). Small problems, or requests
   close to the number of DOFs, use a dense eigensolver on the rigid complement.
2. Modal derivatives ``psi_ab = -K^+ (dK/du[phi_a] phi_b)``, a <= b. ``dK/du[phi_a]`` is a
   central difference of the assembled tangent stiffness along phi_a (exact up to round-off
   for StVK, whose K is quadratic in u). The singular free-domain system is solved on the
   mass-orthogonal complement of the rigid modes: ``K psi = -(I - M R R^T) g``,
   ``R^T M psi = 0`` (the Lagrange-multiplier form of the augmented system).
   All right-hand sides are solved at once with the single Cholesky factorisation of
   ``K - sigma M`` made for step 1 (deflated iterative refinement, see _solve_complement).
3. Stack the weighted columns w_a phi_a and w_a w_b psi_ab (w_a = lambda_1 / lambda_a),
   restrict them to the ``keep`` vertices, project out the rigid modes of the keep set,
   mass-PCA to r columns, project again and mass-orthonormalise.

   The PCA is done in two blocks (a deliberate refinement of Barbic-James' joint PCA):
   first the linear modes, then the derivatives after removing their component along the
   retained linear directions. psi_ab and phi_a have different units, so a joint PCA depends
   on an arbitrary relative scale, and the derivatives overlap the linear modes heavily
   (psi_11 lies ~89 % in span(phi) on a bar): with a joint PCA at equal scale the basis lost
   ~1.5 % of phi_1 and its Ritz eigenvalues were 1 % (mode 1) to 15 % (mode 4) too stiff. With
   the two blocks, every linear mode kept is exactly in span(U) (when r >= n_linear: all of
   them), the derivatives only add new directions, and the result is scale-invariant.

Symbols: n sub-mesh vertices, n_free free DOFs (3n minus 3 per fixed vertex), k = len(keep),
r the basis size. DOF layout everywhere: row 3*l + i is vertex l, axis i.
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from ..fem.elements import deformation_gradients
from ..fem.force_model import FEMForceModel
from ..linear_solver import NotPositiveDefinite, SparseSolver

# Shift of the shift-invert eigensolve: sigma = -SHIFT_FACTOR * lambda_scale, where
# lambda_scale is a Rayleigh-Ritz upper bound of the smallest non-rigid eigenvalue from a
# few smooth quadratic fields. Negative: K - sigma M is positive definite for a free domain
# too (its rigid modes sit at -sigma). 1e-3 keeps K - sigma M far from singular for the
# Cholesky factorisation while the refinement of step 2 contracts by ~1e-3 per iteration.
SHIFT_FACTOR = 1e-3
# Central-difference step of dK/du[phi]: eps such that the largest element displacement
# gradient |eps grad(phi)|_F equals FD_STRAIN. Truncation error ~ C FD_STRAIN^2 (relative),
# round-off ~ 1e-16 / FD_STRAIN: at 1e-4 the step-halving difference is ~2e-9 for
# neo-Hookean / corotated and ~3e-11 (round-off only) for StVK, whose K is quadratic in u.
FD_STRAIN = 1e-4
# Directions whose mass-PCA singular value is below RANK_TOL * (largest) count as dependent.
RANK_TOL = 1e-8
# A non-rigid eigenvalue below ZERO_MODE_TOL * lambda_scale is a zero-energy mode the
# rigid projection / pins did not remove (disconnected sub-mesh, too few pins).
ZERO_MODE_TOL = 1e-7
# |K R| relative to |K| |R| above this: the rigid modes are not in the null space of K.
RIGID_NULL_TOL = 1e-8
# Deflated refinement of the derivative solves: stop at this relative residual (the FD
# right-hand sides themselves carry ~1e-9 for non-StVK materials; the round-off floor is ~1e-12).
REFINE_TOL = 1e-10
REFINE_MAX_ITERATIONS = 60
# Dense eigensolver when the request is large relative to the problem (ARPACK needs
# ncv ~ 2k+1 < n and loses its advantage long before that).
DENSE_FRACTION = 3


@dataclass(frozen=True)
class ModalBasis:
    """Subspace basis of one domain.

    U: (3k, r) mass-orthonormal basis; row 3*l + i is keep vertex l (in ``keep`` order), axis i.
        Rows of fixed vertices are zero. For a free domain U^T M R = 0 with R the rigid modes
        of the keep vertices (rigid_modes(X[keep], vertex_mass[keep])).
    eigenvalues: (n_linear,) ascending eigenvalues of the linear modes used (rad^2/s^2).
    n_linear: number of linear modes computed and stacked.
    n_derivatives: number of modal-derivative columns stacked (0 when derivatives are off).
    mass: (3k,) the diagonal mass of the keep vertices (each vertex mass repeated 3 times).
    is_free: True when the domain has rigid DOFs (no fixed vertices).
    build_seconds: wall time of the construction.
    derivative_source: where the derivatives were taken: "domain" (keep_derivatives),
        "region" (the sub-mesh's modes as they are), "region (...failed...)" or "none".
    """

    U: np.ndarray
    eigenvalues: np.ndarray
    n_linear: int
    n_derivatives: int
    mass: np.ndarray
    is_free: bool
    build_seconds: float
    derivative_source: str = "region"

    @property
    def r(self):
        return int(self.U.shape[1])


# ---------------------------------------------------------------------------------------------
# Rigid modes and mass-inner-product helpers


def rigid_modes(X, mass):
    """Mass-orthonormal rigid modes (3k, 6): translations x, y, z, then infinitesimal
    rotations about the mass centre (principal axes of inertia, scaled to unit M-norm).

    X: (k, 3) positions; mass: (k,) vertex masses >= 0 with a positive total.
    Translations and rotations about the mass centre are mass-orthogonal by construction;
    the rotations are orthonormalised with the inverse square root of the inertia tensor.
    Raises ValueError when the vertices cannot carry three independent rotations
    (fewer than three non-collinear massive vertices).
    """
    X = np.asarray(X, dtype=np.float64)
    mass = np.asarray(mass, dtype=np.float64)
    if X.ndim != 2 or X.shape[1] != 3 or mass.shape != (len(X),):
        raise ValueError(f"rigid_modes: X must be (k, 3) and mass (k,), got {X.shape} and {mass.shape}")
    total = float(mass.sum())
    if not np.all(np.isfinite(mass)) or np.any(mass < 0) or total <= 0:
        raise ValueError("rigid_modes: masses must be finite, >= 0, with a positive total")
    k = len(X)
    centre = mass @ X / total
    rel = X - centre
    modes = np.zeros((k, 3, 6))
    modes[:, [0, 1, 2], [0, 1, 2]] = 1.0 / np.sqrt(total)
    inertia = (mass * (rel * rel).sum(axis=1)).sum() * np.eye(3) - (rel.T * mass) @ rel
    w, V = np.linalg.eigh(inertia)
    if w[0] <= 1e-12 * max(w[-1], 1e-300):
        raise ValueError("rigid_modes: the vertices are (nearly) collinear or a single point; "
                         "their rotations are not independent")
    axes = V / np.sqrt(w)                                  # omega_j = axes[:, j], unit M-norm
    modes[:, :, 3:] = np.cross(axes.T[None, :, :], rel[:, None, :]).transpose(0, 2, 1)
    return modes.reshape(3 * k, 6)


def mass_project(V, R, m):
    """Remove the span of the M-orthonormal columns R from V: V - R R^T M V (R None: V)."""
    if R is None:
        return V
    return V - R @ (R.T @ (m[:, None] * V))


def mass_orthonormalise(V, m):
    """Mass-orthonormalise the columns of V (Cholesky QR, twice for stability)."""
    for _ in range(2):
        G = V.T @ (m[:, None] * V)
        G = 0.5 * (G + G.T)
        L = np.linalg.cholesky(G)
        V = sla.solve_triangular(L, V.T, lower=True).T
    return V


def _fix_signs(V):
    """Deterministic column signs: the entry of largest magnitude is positive."""
    idx = np.argmax(np.abs(V), axis=0)
    s = np.sign(V[idx, np.arange(V.shape[1])])
    s[s == 0] = 1.0
    return V * s


# ---------------------------------------------------------------------------------------------
# Step 1: linear modes


def lambda_scale(K, m, X, free_mask, R=None, fixed=()):
    """Rayleigh-Ritz upper bound of the smallest non-rigid eigenvalue of K phi = lambda M phi.

    Trial space: smooth quadratic fields. Free domain: (X_j - c_j)(X_l - c_l) e_i with the
    rigid modes projected out. Pinned domain: d^2 {1, X_j - c_j} e_i, d the distance to the
    nearest fixed vertex (so the fields vanish on the pins instead of shearing the first
    element layer). Any field of the complement bounds lambda_1 from above, and smooth fields
    give a bound within a small factor of it for ordinary shapes.
    """
    X = np.asarray(X, dtype=np.float64)
    n = len(X)
    c = X.mean(axis=0)
    L = max(float(np.ptp(X, axis=0).max()), 1e-300)
    rel = (X - c) / L
    fixed = np.asarray(fixed, dtype=np.int64)
    if fixed.size:
        from scipy.spatial import cKDTree
        d, _ = cKDTree(X[fixed]).query(X)
        d = d / L
        scalars = [d * d] + [d * d * rel[:, j] for j in range(3)]
    else:
        scalars = [rel[:, j] * rel[:, l] for j in range(3) for l in range(j, 3)]
    S = np.stack(scalars, axis=1)                                          # (n, s)
    fields = np.zeros((n, 3, 3 * S.shape[1]))
    for i in range(3):                                                      # 3 axes, vectorised over fields
        fields[:, i, i::3] = S
    V = fields.reshape(3 * n, -1)[free_mask]
    V = mass_project(V, R, m)
    # M-orthonormal basis of the trial space (drop dependent fields), then the smallest Ritz value.
    Y = np.sqrt(m)[:, None] * V
    Uy, s, _ = np.linalg.svd(Y, full_matrices=False)
    Uy = Uy[:, s > 1e-10 * s[0]]
    B = Uy / np.sqrt(m)[:, None]
    Kr = B.T @ (K @ B)
    return float(np.linalg.eigvalsh(0.5 * (Kr + Kr.T))[0])


class _ShiftInvert:
    """Cholesky factorisation of K - sigma M (sigma < 0) and the rigid-projected solve."""

    def __init__(self, K, m, sigma, R=None):
        self.K, self.m, self.sigma, self.R = K, m, float(sigma), R
        A = (K - sigma * sp.diags(m)).tocsr()
        A.sort_indices()
        try:
            self.solver = SparseSolver().factor(A)
        except NotPositiveDefinite as err:
            raise ValueError("K - sigma M is not positive definite: the stiffness at the rest "
                             "state has negative eigenvalues (is the material stress-free at rest?)") from err

    def solve(self, B):
        """P (K - sigma M)^{-1} B with P = I - R R^T M (rigid components removed)."""
        return mass_project(self.solver.solve(B), self.R, self.m)


def linear_modes(K, m, n, rigid=None, method="auto", sigma=None, shift_invert=None, seed=0):
    """Smallest n non-rigid eigenpairs of K phi = lambda M phi, M = diag(m).

    K: (n_free, n_free) sparse symmetric PSD; m: (n_free,) positive diagonal mass;
    rigid: (n_free, 6) M-orthonormal rigid modes for a free domain (None when pinned).
    method: "arpack" (shift-invert Lanczos on the rigid-projected operator), "dense"
    (dense eigensolver on the M-complement of the rigid modes) or "auto" (dense when
    DENSE_FRACTION * (n + 6) >= n_free).
    sigma: the (negative) shift for arpack; shift_invert: a prebuilt _ShiftInvert to reuse.
    Returns (lambdas (n,) ascending, Phi (n_free, n) M-orthonormal, M-orthogonal to rigid).
    """
    n_free = K.shape[0]
    n_rigid = 0 if rigid is None else rigid.shape[1]
    if n < 1 or n > n_free - n_rigid:
        raise ValueError(f"linear_modes: n={n} must be in [1, {n_free - n_rigid}] "
                         f"({n_free} free DOFs, {n_rigid} rigid modes)")
    if method == "auto":
        method = "dense" if DENSE_FRACTION * (n + n_rigid) >= n_free else "arpack"
    sq = np.sqrt(m)
    if method == "dense":
        Kt = K.toarray() / sq[:, None] / sq[None, :]
        Kt = 0.5 * (Kt + Kt.T)
        if rigid is not None:
            Q, _ = np.linalg.qr(sq[:, None] * rigid, mode="complete")
            Q2 = Q[:, n_rigid:]                                               # Euclidean complement
            lam, Y = sla.eigh(Q2.T @ Kt @ Q2, subset_by_index=[0, n - 1])
            Phi = (Q2 @ Y) / sq[:, None]
        else:
            lam, Y = sla.eigh(Kt, subset_by_index=[0, n - 1])
            Phi = Y / sq[:, None]
    elif method == "arpack":
        if shift_invert is None:
            if sigma is None:
                raise ValueError("linear_modes: arpack needs sigma or shift_invert")
            shift_invert = _ShiftInvert(K, m, sigma, rigid)
        si = shift_invert
        op = spla.LinearOperator((n_free, n_free), dtype=np.float64,
                                 matvec=lambda x: si.solve(x.reshape(-1, 1))[:, 0])
        v0 = mass_project(np.random.default_rng(seed).standard_normal((n_free, 1)), rigid, m)[:, 0]
        _, Phi = spla.eigsh(K, k=n, M=sp.diags(m).tocsr(), sigma=si.sigma, which="LM",
                            OPinv=op, v0=v0)
        # Polish: rigid projection, M-orthonormalisation and a Rayleigh-Ritz step.
        Phi = mass_orthonormalise(mass_project(Phi, rigid, m), m)
        Kr = Phi.T @ (K @ Phi)
        lam, Y = np.linalg.eigh(0.5 * (Kr + Kr.T))
        Phi = Phi @ Y
    else:
        raise ValueError(f"linear_modes: unknown method {method!r} (auto, arpack, dense)")
    order = np.argsort(lam)
    return np.asarray(lam)[order], _fix_signs(np.asarray(Phi)[:, order])


# ---------------------------------------------------------------------------------------------
# Step 2: modal derivatives


def _full_columns(model, V):
    """(n_free, c) free-DOF columns -> (3 n_verts, c) with zero rows on pinned DOFs."""
    out = np.zeros((3 * model.n_verts, V.shape[1]))
    out[model.pattern.free_dof >= 0] = V
    return out


def fd_step(model, direction):
    """Central-difference step along ``direction`` (n_verts, 3): the largest element
    displacement gradient of eps * direction is FD_STRAIN."""
    G = deformation_gradients(np.asarray(direction, dtype=np.float64), model.tets, model.geom.grads)
    g = float(np.sqrt((G * G).sum(axis=(1, 2))).max())
    if g == 0.0:
        raise ValueError("fd_step: the direction does not deform any element")
    return FD_STRAIN / g


def stiffness_derivative(model, direction, eps=None):
    """dK/du[direction] at the rest state by central differences of the tangent stiffness.

    model: FEMForceModel; direction: (n_verts, 3) (pinned rows are ignored: the pins stay
    at rest). Returns a (n_free, n_free) CSR matrix on the model's pattern.
    """
    direction = np.asarray(direction, dtype=np.float64).reshape(model.n_verts, 3)
    direction = model.expand(model.free(direction))                           # pinned rows -> 0
    if eps is None:
        eps = fd_step(model, direction)
    _, _, Kp = model.tangent(model.X + eps * direction)
    _, _, Km = model.tangent(model.X - eps * direction)
    return model.pattern.matrix((Kp - Km) / (2.0 * eps))


def _solve_complement(si, K, m, R, B, Phi=None, lam=None):
    """X with K X = B and R^T M X = 0 for right-hand sides with R^T B = 0 (columns of B).

    Iterative refinement with the factorisation of A = K - sigma M: X += P A^{-1} (B - K X).
    Its error contracts by |sigma| / (lambda_j - sigma) along eigenvector j, so the start
    X0 = Phi Lambda^-1 Phi^T B removes the known lowest modes exactly (deflation) and the
    rest contracts by <= |sigma| / lambda_{n+1} ~ 1e-3 per iteration.
    """
    X = np.zeros_like(B) if Phi is None else Phi @ ((Phi.T @ B) / lam[:, None])
    scale = np.maximum(np.linalg.norm(B, axis=0), 1e-300)
    best = np.inf
    for _ in range(REFINE_MAX_ITERATIONS):
        Res = B - K @ X
        if R is not None:
            Res -= (m[:, None] * R) @ (R.T @ Res)                             # keep it in range(K)
        err = float((np.linalg.norm(Res, axis=0) / scale).max())
        if err <= REFINE_TOL:
            break
        if err >= 0.5 * best:                                               # round-off floor reached
            break
        best = err
        X = X + si.solve(Res)
    Res = B - K @ X
    if R is not None:
        Res -= (m[:, None] * R) @ (R.T @ Res)
    err = float((np.linalg.norm(Res, axis=0) / scale).max())
    if err > 1e-8:
        raise RuntimeError(f"modal derivative solve did not converge (relative residual {err:.2e})")
    return mass_project(X, R, m)


def modal_derivatives(model, Phi, m, rigid=None, eigenvalues=None, pairs=None, eps=None,
                      shift_invert=None, sigma=None, K=None):
    """Modal derivatives psi_ab = -K^+ (dK/du[phi_a] phi_b) on the model's free DOFs.

    model: FEMForceModel of the sub-mesh (pins = the domain's fixed vertices);
    Phi: (n_free, n_linear) linear modes; m: (n_free,) diagonal mass; rigid: (n_free, 6)
    M-orthonormal rigid modes for a free domain. pairs: (p, 2) mode index pairs (default all
    a <= b, a-major); eps: fixed FD step (default fd_step per mode a); eigenvalues: those of
    Phi (enables the deflated start); shift_invert / sigma: reuse a factorisation / choose
    the shift; K: the rest stiffness if already assembled.
    For a free domain psi solves K psi = -(I - M R R^T) g with R^T M psi = 0.
    Returns (psi (n_free, p), pairs (p, 2)).
    """
    n_lin = Phi.shape[1]
    if pairs is None:
        a, b = np.triu_indices(n_lin)
        pairs = np.stack([a, b], axis=1)
    pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
    if K is None:
        K = model.pattern.matrix(model.tangent(model.X)[2])
    if shift_invert is None:
        if sigma is None:
            sigma = -SHIFT_FACTOR * lambda_scale(K, m, model.X, model.pattern.free_dof >= 0,
                                                 rigid, model.pinned)
        shift_invert = _ShiftInvert(K, m, sigma, rigid)
    full = _full_columns(model, Phi)
    G = np.empty((K.shape[0], len(pairs)))
    for a in np.unique(pairs[:, 0]):                                          # two tangents per mode
        sel = np.flatnonzero(pairs[:, 0] == a)
        dK = stiffness_derivative(model, full[:, a].reshape(-1, 3), eps)
        G[:, sel] = dK @ Phi[:, pairs[sel, 1]]                                # one sparse matmul
    B = -G
    if rigid is not None:
        B -= (m[:, None] * rigid) @ (rigid.T @ B)
    psi = _solve_complement(shift_invert, K, m, rigid, B, Phi if eigenvalues is not None else None,
                            eigenvalues)
    return psi, pairs


# ---------------------------------------------------------------------------------------------
# Step 3 and the public constructors


def _default_n_linear(r, derivatives):
    """r linear modes without derivatives (span(U) = span(linear modes)). With derivatives
    n = r // 2 + 1 (r=20 -> 11 modes, 66 derivatives, PCA picks 9 of their directions): all n
    linear modes are kept exactly (two-block PCA, n <= r), the derivative block offers
    ~3x more candidates than the r - n slots it fills, and the cost (2 tangents per mode,
    n(n+1)/2 right-hand sides) stays small."""
    if not derivatives:
        return r
    return max(1, r // 2 + 1)


def _check_indices(name, idx, n):
    idx = np.asarray(idx, dtype=np.int64).reshape(-1)
    if idx.size and (idx.min() < 0 or idx.max() >= n):
        raise ValueError(f"{name}: vertex indices must lie in [0, {n}), got range "
                         f"[{idx.min()}, {idx.max()}]")
    if np.unique(idx).size != idx.size:
        raise ValueError(f"{name}: repeated vertex indices")
    return idx


def _is_int(v):
    return isinstance(v, (int, np.integer)) and not isinstance(v, bool)


def modal_basis(X, tets, material, vertex_mass, r, fixed=(), keep=None, n_linear=None,
                derivatives=True, derivative_method="fd", derivatives_on="domain"):
    """Mass-orthonormal, rigid-free basis of one domain (linear modes + modal derivatives, PCA).

    X: (n, 3) rest positions of the sub-mesh used for the stiffness (the domain's elements
        plus a layer around them); tets: (m, 4) positively oriented tets into X;
    material: mdss_ros.fem.materials material; vertex_mass: (n,) positive lumped masses of
        these vertices (the full body's, not re-lumped from the sub-mesh);
    r: basis size; fixed: local indices of pinned vertices (boundary conditions; the domain
        then has no rigid DOFs, is_free=False); keep: local indices whose rows form U, in
        order (default all): rows outside keep are dropped after the modes are computed and
        the result is re-projected and re-orthonormalised on keep;
    n_linear: number of linear modes (default _default_n_linear); derivatives: stack modal
        derivatives; derivative_method: "fd" (central differences of K);
    derivatives_on: "domain" (default) or "region". Only matters for a free domain whose
        keep set is smaller than the sub-mesh (a grown region): "domain" differentiates the
        linear modes restricted to the keep vertices with their rigid part there removed,
        on the keep vertices' elements plus one ring (keep_derivatives); "region"
        differentiates the region's modes as they are, rigid part included (the code before
        issue 15; the frame already carries that motion exactly, and the derivatives of a
        local rigid rotation are its second-order terms, which crowd out the bending ones).

    Columns (phi mass-normalised): w_a phi_a with w_a = lambda_1 / lambda_a, and
    w_a w_b s_ab psi_ab with s_ab = sqrt(2) for a < b (the PCA then weighs psi_ab and psi_ba,
    which makes it invariant to the choice of basis inside degenerate eigenspaces). PCA (thin
    SVD of M^1/2 W on the keep rows, after projecting out the keep set's rigid modes), in two
    blocks: the min(r, rank) dominant linear directions first (keep = all: exactly the first
    min(r, n_linear) linear modes), then the remaining r - n_linear dominant directions of the
    derivative block with the retained linear directions projected out. U is then projected
    and Cholesky-QR-orthonormalised again; rows of fixed vertices are exactly zero.
    Derivatives are computed whenever derivatives=True (used only if r > n_linear).

    Raises ValueError for r <= 0, r above the available DOFs (3 per non-fixed keep vertex,
    minus 6 for a free domain), fewer than r independent stacked directions, bad indices,
    non-positive masses, vertices in no tet, or a sub-mesh with zero-energy modes besides the
    rigid ones (disconnected, too few pins).
    """
    t0 = time.perf_counter()
    X = np.ascontiguousarray(X, dtype=np.float64)
    tets = np.ascontiguousarray(tets, dtype=np.int64)
    if X.ndim != 2 or X.shape[1] != 3 or tets.ndim != 2 or tets.shape[1] != 4 or len(tets) == 0:
        raise ValueError(f"modal_basis: X must be (n, 3) and tets (m>0, 4), got {X.shape} and {tets.shape}")
    n = len(X)
    if not _is_int(r) or r <= 0:
        raise ValueError(f"modal_basis: r must be a positive integer, got r={r!r}")
    vertex_mass = np.asarray(vertex_mass, dtype=np.float64).reshape(-1)
    if vertex_mass.shape != (n,) or not np.all(np.isfinite(vertex_mass)) or np.any(vertex_mass <= 0):
        raise ValueError(f"modal_basis: vertex_mass must be ({n},) finite and positive")
    if tets.min() < 0 or tets.max() >= n:
        raise ValueError(f"modal_basis: tets index vertices outside [0, {n})")
    fixed = _check_indices("fixed", fixed, n)
    keep = np.arange(n) if keep is None else _check_indices("keep", keep, n)
    if keep.size == 0:
        raise ValueError("modal_basis: keep is empty")
    if derivative_method != "fd":
        raise ValueError(f"modal_basis: derivative_method must be 'fd', got {derivative_method!r}")
    if derivatives_on not in ("domain", "region"):
        raise ValueError(f"modal_basis: derivatives_on must be 'domain' or 'region', got {derivatives_on!r}")
    is_free = fixed.size == 0
    unused = np.bincount(tets.ravel(), minlength=n) == 0
    unused[fixed] = False
    if unused.any():
        raise ValueError(f"modal_basis: {int(unused.sum())} non-fixed vertices belong to no tet "
                         f"(first: {np.flatnonzero(unused)[:5].tolist()}); they have no stiffness")
    n_rigid = 6 if is_free else 0
    keep_free = ~np.isin(keep, fixed)
    available = 3 * int(keep_free.sum()) - n_rigid
    if r > available:
        raise ValueError(f"modal_basis: r={r} exceeds the {available} available DOFs of the kept "
                         f"vertices ({int(keep_free.sum())} non-fixed keep vertices"
                         f"{', minus 6 rigid modes' if is_free else ''})")
    n_free_total = 3 * (n - fixed.size) - n_rigid
    if n_linear is None:
        n_linear = min(_default_n_linear(r, derivatives), n_free_total)
    if not _is_int(n_linear) or n_linear < 1 or n_linear > n_free_total:
        raise ValueError(f"modal_basis: n_linear must be an integer in [1, {n_free_total}], got {n_linear!r}")
    n_candidates = n_linear + (n_linear * (n_linear + 1) // 2 if derivatives else 0)
    if n_candidates < r:
        raise ValueError(f"modal_basis: r={r} exceeds the {n_candidates} stacked columns "
                         f"(n_linear={n_linear}, derivatives={derivatives})")

    # Sub-mesh stiffness at rest on the free DOFs, diagonal mass, rigid modes.
    model = FEMForceModel(X, tets, material, pinned=fixed)
    free_mask = model.pattern.free_dof >= 0
    K = model.pattern.matrix(model.tangent(X)[2])
    m = np.repeat(vertex_mass, 3)[free_mask]
    R = None
    if is_free:
        R = rigid_modes(X, vertex_mass)
        KR = K @ R
        rel = np.linalg.norm(KR) / (spla.norm(K) * np.linalg.norm(R))
        if rel > RIGID_NULL_TOL:
            raise ValueError(f"modal_basis: rigid motions are not in the null space of K at rest "
                             f"(|K R| / |K||R| = {rel:.1e}); the rest state is not stress-free")

    # Step 1: linear modes (one factorisation of K - sigma M, reused by step 2).
    lam_s = lambda_scale(K, m, X, free_mask, R, fixed)
    sigma = -SHIFT_FACTOR * lam_s
    n_dofs = K.shape[0]
    dense = DENSE_FRACTION * (n_linear + n_rigid) >= n_dofs
    si = _ShiftInvert(K, m, sigma, R) if (derivatives or not dense) else None
    lam, Phi = linear_modes(K, m, n_linear, rigid=R, method="dense" if dense else "arpack",
                            shift_invert=si)
    if lam[0] <= ZERO_MODE_TOL * lam_s:
        raise ValueError(f"modal_basis: the sub-mesh has a zero-energy mode besides the rigid ones "
                         f"(lambda_1 = {lam[0]:.3e}, scale {lam_s:.3e}): is it disconnected, or do "
                         f"the fixed vertices leave a rigid motion free?")

    # Weighted columns on the free DOFs: w_a phi_a and w_a w_b s_ab psi_ab.
    w = lam[0] / lam
    W_lin = Phi * w
    W_der = None          # derivative columns on the sub-mesh's free DOFs, or
    W_der_keep = None     # on the keep rows (3k, p) when taken on the domain (keep_derivatives)
    source = "region" if derivatives else "none"
    if derivatives and derivatives_on == "domain" and is_free and keep.size < n:
        try:
            psi_k, pairs = keep_derivatives(model, X, tets, material, vertex_mass, keep, Phi)
            a, b = pairs[:, 0], pairs[:, 1]
            W_der_keep = psi_k * (w[a] * w[b] * np.where(a < b, np.sqrt(2.0), 1.0))
            source = "domain"
        except (ValueError, RuntimeError, NotPositiveDefinite) as err:    # a hinged ring: the region's
            source = f"region (domain derivatives failed: {err})"
    if derivatives and W_der_keep is None:
        psi, pairs = modal_derivatives(model, Phi, m, rigid=R, eigenvalues=lam, shift_invert=si, K=K)
        a, b = pairs[:, 0], pairs[:, 1]
        W_der = psi * (w[a] * w[b] * np.where(a < b, np.sqrt(2.0), 1.0))

    # Step 3 on the keep rows: rigid projection, two-block mass-PCA, projection, orthonormalisation.
    mk = np.repeat(vertex_mass[keep], 3)
    Rk = rigid_modes(X[keep], vertex_mass[keep]) if is_free else None

    def on_keep(V):
        V = _full_columns(model, V).reshape(n, 3, -1)[keep].reshape(3 * keep.size, -1)
        return mass_project(V, Rk, mk)

    n_deriv = W_der.shape[1] if W_der is not None else (0 if W_der_keep is None else W_der_keep.shape[1])
    U_lin, rank_lin = mass_pca(on_keep(W_lin), mk, r)
    blocks, rank = [U_lin], rank_lin
    if (W_der is not None or W_der_keep is not None) and rank < r:
        Wd0 = on_keep(W_der) if W_der is not None else mass_project(W_der_keep, Rk, mk)
        Wd = Wd0 - U_lin @ (U_lin.T @ (mk[:, None] * Wd0))                     # new directions only
        U_der, rank_der = mass_pca(Wd, mk, r - rank, reference=_m_norms(Wd0, mk).max())
        blocks.append(U_der)
        rank += rank_der
    if rank < r:
        raise ValueError(f"modal_basis: only {rank} independent directions on the kept vertices "
                         f"({rank_lin} from {n_linear} linear modes"
                         f"{'' if n_deriv == 0 else f', the rest from {n_deriv} derivatives'}"
                         f"), fewer than r={r}; raise n_linear or enable derivatives")
    U = np.concatenate(blocks, axis=1)
    U[np.repeat(np.isin(keep, fixed), 3)] = 0.0                                 # exact zeros on pins
    U = _fix_signs(mass_orthonormalise(mass_project(U, Rk, mk), mk))
    return ModalBasis(U=U, eigenvalues=lam, n_linear=int(n_linear), n_derivatives=int(n_deriv),
                      derivative_source=source,
                      mass=mk, is_free=bool(is_free), build_seconds=time.perf_counter() - t0)


def keep_derivatives(model, X, tets, material, vertex_mass, keep, Phi):
    """Modal derivatives of a free domain's linear modes, taken on the domain itself.

    Phi (n_free, n_lin): linear modes of the grown region (model: its FEMForceModel, no
    pins); keep (k,) the domain's vertices in X. The modes are restricted to the keep
    vertices plus one ring of elements around them (the ring gives every keep vertex,
    also one that only coupling elements touch, stiffness), their rigid part there is
    projected out, and psi_ab = -K^+ (dK/du[phi_a] phi_b) is solved on that sub-mesh
    (free-free, R^T M psi = 0). Returns (psi (3 k, p) on the keep rows, pairs (p, 2)).

    Why: restricted to a limb, a low mode of the grown region is mostly the limb turning
    about the region's rest, a motion the limb's frame represents exactly. Differentiated
    as it is, that rotation yields its own second-order terms (the shortening of a turned
    segment), and the derivative slots of the basis go to them instead of to the bending
    nonlinearity (measured on star_limbs' loaded arm, issue 15: best-fit misfit of a 145
    degree curl 6.3 % of the peak displacement with the region's derivatives, 6.0 % with
    linear modes only, 2.7 % with these).
    """
    n = len(X)
    in_keep = np.zeros(n, dtype=bool)
    in_keep[keep] = True
    ring = np.unique(tets[in_keep[tets].any(axis=1)])
    in_ring = np.zeros(n, dtype=bool)
    in_ring[ring] = True
    local = np.full(n, -1, dtype=np.int64)
    local[ring] = np.arange(ring.size)
    rmodel = FEMForceModel(X[ring], local[tets[in_ring[tets].all(axis=1)]], material)
    mr = np.repeat(vertex_mass[ring], 3)
    Rr = rigid_modes(X[ring], vertex_mass[ring])
    P = mass_project(_full_columns(model, Phi).reshape(n, 3, -1)[ring].reshape(3 * ring.size, -1), Rr, mr)
    K = rmodel.pattern.matrix(rmodel.tangent(rmodel.X)[2])
    si = _ShiftInvert(K, mr, -SHIFT_FACTOR * lambda_scale(K, mr, rmodel.X, np.ones(3 * ring.size, bool), Rr), Rr)
    # The ring's own lowest modes deflate the refinement (the restricted modes are not its
    # eigenvectors): without them a slender domain's first bending mode contracts too slowly.
    n_def = min(12, K.shape[0] - 7)
    lam_r, Phi_r = linear_modes(K, mr, n_def, rigid=Rr, shift_invert=si)
    if lam_r[0] <= ZERO_MODE_TOL * si.sigma / -SHIFT_FACTOR:
        raise ValueError("modal_basis: the domain with one ring of elements has a zero-energy mode besides the "
                         "rigid ones; use basis.derivatives_on: region")
    a, b = np.triu_indices(P.shape[1])
    pairs = np.stack([a, b], axis=1)
    G = np.empty((K.shape[0], len(pairs)))
    for ia in range(P.shape[1]):                                              # two tangents per mode
        sel = np.flatnonzero(pairs[:, 0] == ia)
        G[:, sel] = stiffness_derivative(rmodel, P[:, ia].reshape(-1, 3)) @ P[:, pairs[sel, 1]]
    B = -G
    B -= (mr[:, None] * Rr) @ (Rr.T @ B)
    psi = _solve_complement(si, K, mr, Rr, B, Phi_r, lam_r)
    return psi.reshape(ring.size, 3, -1)[local[keep]].reshape(3 * keep.size, -1), pairs


def _m_norms(V, m):
    return np.sqrt((m[:, None] * V * V).sum(axis=0)) if V.size else np.zeros(1)


def mass_pca(W, m, count, reference=None):
    """Up to ``count`` dominant directions of the columns of W in the M-inner product.

    Thin SVD of M^1/2 W; directions with singular value <= RANK_TOL * reference (default the
    largest singular value) are dependent. Returns (M^-1/2 left singular vectors (rows, q),
    number of independent directions found (may exceed q = min(count, that number)))."""
    sq = np.sqrt(m)
    if W.shape[1] == 0:
        return np.zeros((len(m), 0)), 0
    Us, s, _ = np.linalg.svd(sq[:, None] * W, full_matrices=False)
    ref = s[0] if reference is None else reference
    rank = int((s > RANK_TOL * ref).sum()) if ref > 0 else 0
    q = min(count, rank)
    return Us[:, :q] / sq[:, None], rank


def complete_basis(X, tets, material, vertex_mass, fixed=(), keep=None):
    """A basis spanning every non-rigid DOF of the keep vertices (r = 3 * non-fixed keep
    vertices, minus 6 for a free domain): all linear modes of the sub-mesh (dense
    eigensolver), no derivatives, PCA on keep. Square and full rank on the free rows of a
    pinned domain, so a reduced solver using it is an exact change of basis. For small
    domains only (dense O(n_free^3))."""
    X = np.asarray(X, dtype=np.float64)
    n = len(X)
    fixed_i = _check_indices("fixed", fixed, n)
    keep_i = np.arange(n) if keep is None else _check_indices("keep", keep, n)
    n_rigid = 0 if fixed_i.size else 6
    r = 3 * int((~np.isin(keep_i, fixed_i)).sum()) - n_rigid
    n_linear = 3 * (n - fixed_i.size) - n_rigid
    return modal_basis(X, tets, material, vertex_mass, r, fixed=fixed_i, keep=keep_i,
                       n_linear=n_linear, derivatives=False)
