"""Consistent nodal integration of the MLS gradients, and the fit-residual stabilisation
(docs/method.md §19.6).

Nodal integration E = sum_i V_i psi(F_i) with F_i = sum_a x_{s_ia} c_ia^T (mls.py) passes
the gradient half of the linear patch test, but not the force half: under a uniform
stress P the force on node b is P B_b with

    B_b = sum_{(i, a): s_ia = b} V_i c_ia                    (3,)   the integration vector of b

and a Galerkin discretisation is exact for linear fields only if B_b equals the boundary
integral of b's share of the surface normal (0 inside the body). Raw MLS coefficients
miss that by about a stress x cell area at interior nodes (measured), which is the
"integration constraint" failure of nodal integration (Chen et al. 2001). Stabilised
conforming nodal integration fixes it with smoothed gradients over Voronoi cells; here
the nodes are tet-mesh vertices, and the correction is instead made on the coefficients
themselves, once, at build (Krongauz and Belytschko 1997's consistent pseudo-derivatives
do the same for the derivative operator):

    min  sum_ia |c~_ia - c_ia|^2   subject to, for every quadrature node i,
         sum_a c~_ia = 0,   sum_a X_{s_ia} c~_ia^T = I          (the patch test, exact F)
    and for every node b:   sum_{s_ia = b} V_i c~_ia = B*_b      (the integration constraint)

B*_b = sum over the surface triangles t at b of area_t n_t / 3 (the piecewise-linear
surface's share), 0 for interior nodes. The energy keeps its form with c~ in place of c,
so forces and stiffness stay its exact derivatives, K stays symmetric and backward Euler a
minimisation. Each spatial column d of c is a separate least-norm problem with the same
matrix: with G_i (4, w) = [1; X_{s_i}^T] and P_i = I - G_i^T (G_i G_i^T)^-1 G_i the
projector onto its null space, delta_i = P_i (V_i y_{s_i}) where

    L y = r,   L_bc = sum_{i, a, a': s_ia = b, s_ia' = c} V_i^2 P_i[a, a'],   r = B* - B    (n,)

L is singular along affine y (P_i kills them); r is orthogonal to them when B* is
consistent, which it is (sum_b B*_b = 0, sum_b X_b B*_b^T = V_mesh I = sum_i V_i I), so
y is pinned to 0 at four nodes spanning the body and L is solved on the rest.

Fit-residual stabilisation (an hourglass control in the sense of Ganzenmueller 2015 for
total-Lagrangian SPH): nodal integration sees a neighbourhood only through F_i, so a
motion whose first-order fit is unchanged costs no energy (zero-energy modes). The
residual of the fit

    e_ij = x_j - x_i - F_i X_ij = sum_a R_i[j, a] x_{s_ia},    R_i[j, a] = [a = j] - [a = 0] - c_ia . X_ij

vanishes for every affine motion (rigid ones included, at any rotation), and

    E_hg = gamma mu / 2 sum_i V_i sum_j what_ij |e_ij|^2 / |X_ij|^2,    what_ij = w_ij / sum_j w_ij

penalises the rest. It is quadratic in x, so its stiffness is a constant scalar stencil
matrix S_i = gamma mu V_i R_i^T diag(what_ij / |X_ij|^2) R_i (w, w), times I_3.

Arrays (n nodes, k neighbours, w = k + 1): stencil (n, w); c (n, w, 3); V (n,);
X (n_nodes, 3); R (n, k, w); S (n, w, w).
"""
import numpy as np
import scipy.sparse as sp

from ..errors import SceneError
from ..linear_solver import SparseSolver


def integration_vectors(stencil, c, V, n_nodes):
    """B (n_nodes, 3): B_b = sum_{s_ia = b} V_i c_ia."""
    B = np.zeros((n_nodes, 3))
    np.add.at(B, stencil.reshape(-1), (V[:, None, None] * c).reshape(-1, 3))
    return B


def boundary_vectors(X, triangles, n_nodes):
    """B* (n_nodes, 3): each outward surface triangle's area vector shared equally by its
    three vertices; X (n_nodes, 3), triangles (t, 3) node ids wound outward."""
    a, b, c = X[triangles[:, 0]], X[triangles[:, 1]], X[triangles[:, 2]]
    area_normal = 0.5 * np.cross(b - a, c - a)                    # (t, 3)
    out = np.zeros((n_nodes, 3))
    np.add.at(out, triangles.reshape(-1), np.repeat(area_normal / 3.0, 3, axis=0))
    return out


def _nullspace_projectors(X, stencil, h):
    """P_i (n, w, w): projector onto the null space of G_i = [1; (X_{s_i} - X_i) / h_i]."""
    rel = (X[stencil] - X[stencil[:, :1]]) / h[:, None, None]     # (n, w, 3), scaled for conditioning
    G = np.concatenate([np.ones(stencil.shape + (1,)), rel], axis=2)          # (n, w, 4)
    # pinv, not a solve: a stencil whose points are coplanar (a node that stayed
    # ill-conditioned, mls.py) has a singular G^T G; its correction then stays in the
    # null space of the rank-deficient G, which is what the least change asks for.
    return np.eye(stencil.shape[1])[None] - G @ np.linalg.pinv(G, rcond=1e-10)


def _anchors(X):
    """Four node ids spanning the cloud (a tetrahedron of large volume): extremes of x,
    then the farthest from their line, then the farthest from their plane."""
    a = int(np.argmin(X[:, 0]))
    b = int(np.argmax(np.linalg.norm(X - X[a], axis=1)))
    ab = X[b] - X[a]
    d = X - X[a]
    c = int(np.argmax(np.linalg.norm(np.cross(d, ab), axis=1)))
    nrm = np.cross(ab, X[c] - X[a])
    e = int(np.argmax(np.abs(d @ nrm)))
    ids = np.array([a, b, c, e])
    if len(set(ids.tolist())) < 4 or abs(d[e] @ nrm) < 1e-12 * np.linalg.norm(ab) ** 3:
        raise SceneError("meshless model: the nodes are coplanar; a 3D body needs nodes off one plane")
    return ids


def consistent_coefficients(X, stencil, c, V, h, B_target):
    """c~ (n, w, 3): the least change of c (n, w, 3) that keeps the patch test and meets the
    integration constraint B(c~) = B_target (n_nodes, 3) (module docstring).

    X (n_nodes, 3) rest positions; stencil (n, w); V (n,) nodal volumes; h (n,) support radii
    (only to scale the projectors). Returns c~ and the residual max |B(c~) - B*| / max |B*|."""
    n, w = stencil.shape
    n_nodes = len(X)
    P = _nullspace_projectors(X, stencil, h)                      # (n, w, w)
    Lblocks = (V * V)[:, None, None] * P
    rows = np.repeat(stencil, w, axis=1).reshape(-1)
    cols = np.tile(stencil, (1, w)).reshape(-1)
    L = sp.coo_matrix((Lblocks.reshape(-1), (rows, cols)), shape=(n_nodes, n_nodes)).tocsr()
    r = B_target - integration_vectors(stencil, c, V, n_nodes)    # (n_nodes, 3)
    anchors = _anchors(X)
    keep = np.setdiff1d(np.arange(n_nodes), anchors)
    solver = SparseSolver()
    try:
        solver.factor(L[keep][:, keep].tocsr())
        y = np.zeros((n_nodes, 3))
        for d in range(3):                                        # three right-hand sides, one factor
            y[keep, d] = solver.solve(r[keep, d])
    finally:
        solver.close()
    delta = np.einsum("nab,nbd->nad", P, V[:, None, None] * y[stencil])     # (n, w, 3)
    c_new = c + delta
    scale = max(np.abs(B_target).max(), np.abs(integration_vectors(stencil, c, V, n_nodes)).max())
    resid = np.abs(integration_vectors(stencil, c_new, V, n_nodes) - B_target).max() / scale
    return np.ascontiguousarray(c_new), float(resid)


def fit_residual_operator(X, stencil, c):
    """R (n, k, w): e_ij = sum_a R[i, j, a] x_{s_ia} is the first-order fit's residual at
    neighbour j of node i (module docstring). X (n_nodes, 3) rest positions."""
    n, w = stencil.shape
    Xij = X[stencil[:, 1:]] - X[stencil[:, :1]]                    # (n, k, 3)
    R = -np.einsum("njd,nad->nja", Xij, c)                       # - c_ia . X_ij
    R[:, :, 0] -= 1.0
    R[:, np.arange(w - 1), np.arange(1, w)] += 1.0
    return R


def stabilisation_matrices(X, stencil, c, weights, V, mu, gamma):
    """S (n, w, w): the scalar stencil stiffness of E_hg = 1/2 sum_i x_{s_i}^T (S_i x I_3) x_{s_i}
    for gamma (dimensionless) and shear modulus mu (Pa); weights (n, k) the kernel w_ij."""
    Xij = X[stencil[:, 1:]] - X[stencil[:, :1]]
    wn = weights / weights.sum(axis=1, keepdims=True)
    omega = wn / np.einsum("njd,njd->nj", Xij, Xij)              # (n, k)
    R = fit_residual_operator(X, stencil, c)
    return (gamma * mu * V)[:, None, None] * np.einsum("nja,nj,njb->nab", R, omega, R)
