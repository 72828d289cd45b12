"""Numba point kernels of the hyperelastic materials (see ``materials.py`` for conventions).

Everything here is ``@njit(cache=True)`` and callable from other njit code. Conventions
(repeated from ``materials``):

* ``F`` (3, 3) float64 deformation gradient; vec is row-major, ``vec(F)[3*i+j] = F[i, j]``.
* ``psi`` energy per unit rest volume, ``P = dpsi/dF`` (first Piola-Kirchhoff),
  ``dPdF[a, b] = d vec(P)[a] / d vec(F)[b]`` (9, 9).
* Signed SVD ``F = U diag(s) V^T`` with ``U, V`` proper rotations,
  ``s[0] >= s[1] >= |s[2]|`` and ``s[2] < 0`` exactly when ``det F < 0``.

Kernel layout. A point kernel ``*_point(F, mu, lam, [s_min,] P_out, dPdF_out,
want_hessian, project) -> psi`` allocates one small scratch vector (``WORK_LEN``
float64) and calls the ``*_point_ws`` variant, which takes that scratch as its last
argument and allocates nothing; hot loops should hold one scratch per thread and call
``material_point_ws``. ``dPdF_out`` is left untouched when ``want_hessian`` is False
(``project`` is then ignored).

SVD-frame Hessian. For an isotropic ``psi(F) = psihat(s)`` with principal stresses
``p_i = dpsihat/ds_i`` and the rotated perturbation ``dFh = U^T dF V``:

* the diagonal ``(dFh_00, dFh_11, dFh_22)`` couples through the 3x3 block
  ``H_ij = d p_i / d s_j``;
* each pair ``(i, j)`` in ``PAIRS`` couples ``(dFh_ij, dFh_ji)`` through
  ``[[a, b], [b, a]]`` whose eigenvalues are ``flip = (p_i - p_j)/(s_i - s_j)``
  (eigenvector (1, 1)/sqrt2) and ``twist = (p_i + p_j)/(s_i + s_j)`` ((1, -1)/sqrt2).

``dPdF = K A K^T`` with ``K = kron(U, V)`` (orthogonal) and ``A`` that sparse 9x9
matrix, so the 9 eigenvalues of ``dPdF`` are the 3 of ``H`` plus 3 flips plus 3
twists (Teran et al. 2005; Smith et al. 2019). Each material writes ``flip`` and
``twist`` in a closed form without the removable 0/0 at ``s_i = s_j``; the only true
singularity is ``s_i + s_j = 0`` (a reflection-like F, where the polar rotation jumps),
where ``s_i + s_j`` is replaced by ``max(s_i + s_j, TWIST_DENOM_MIN)``. With the signed
SVD ``s_i + s_j >= 0`` always.

PSD projection (``project=True``): the eigenvalues above are computed analytically
(the 3x3 block by a Jacobi eigensolver). If none is below ``-PSD_TOL * max|eig|``
the unprojected matrix is returned bit-for-bit unchanged; otherwise every negative
eigenvalue is set to zero and ``dPdF = K A+ K^T`` is rebuilt. The result is symmetric
PSD. (For StVK in its clamped region ``dPdF`` is not symmetric; there the symmetric part
is projected and the result is always rebuilt.)
"""
import math

import numpy as np
from numba import njit, prange

KIND_STVK = 0
KIND_COROTATED = 1
KIND_NEOHOOKEAN = 2
N_PARAMS = 5  # params = [mu, lam, s_min (StVK; 0.0 for the others), barrier k, barrier j]

STVK_S_MIN_DEFAULT = 0.5  # see the materials module docstring
TWIST_DENOM_MIN = 1e-6
PSD_TOL = 1e-13

_JACOBI_TOL = 1e-15
_MAX_SWEEPS = 20

# scratch layout (offsets into the WORK_LEN float64 vector)
_O_U = 0
_O_V = 9
_O_B = 18
_O_H = 27
_O_Q = 36
_O_A = 45
_O_S = 54
_O_G = 57
_O_FL = 60
_O_TW = 63
_O_W = 66
_O_K = 72
_O_M = 153
_O_T = 234
WORK_LEN = 315

_JIT = dict(cache=True, nogil=True, error_model="numpy")


# ---------------------------------------------------------------------------------------
# small linear algebra
# ---------------------------------------------------------------------------------------
@njit(**_JIT)
def _pair(k):
    """Index pair k of PAIRS = ((0, 1), (0, 2), (1, 2)) and the third index."""
    if k == 0:
        return 0, 1, 2
    elif k == 1:
        return 0, 2, 1
    return 1, 2, 0


@njit(**_JIT)
def _givens_rows(B, Q, p, q, col):
    """Left Givens rotation on rows p, q of B zeroing B[q, col] (B[p, col] >= 0 after);
    Q <- Q G^T so that Q B stays invariant."""
    a = B[p, col]
    b = B[q, col]
    r = math.hypot(a, b)
    if r == 0.0:
        return
    c = a / r
    s = b / r
    for k in range(3):
        t0 = B[p, k]
        t1 = B[q, k]
        B[p, k] = c * t0 + s * t1
        B[q, k] = -s * t0 + c * t1
    B[q, col] = 0.0
    B[p, col] = r
    for k in range(3):
        t0 = Q[k, p]
        t1 = Q[k, q]
        Q[k, p] = c * t0 + s * t1
        Q[k, q] = -s * t0 + c * t1


@njit(**_JIT)
def _swap_cols(A, p, q):
    for k in range(3):
        t = A[k, p]
        A[k, p] = A[k, q]
        A[k, q] = t


@njit(**_JIT)
def svd3_signed(F, U, s, V, B):
    """Signed SVD F = U diag(s) V^T of a 3x3 matrix (B: 3x3 scratch).

    U, V proper rotations, s[0] >= s[1] >= |s[2]|, s[2] carries the sign of det F.
    One-sided (Hestenes) Jacobi on the columns of F gives V and orthogonal columns
    B = F V with high relative accuracy; a Givens QR of B gives U (det +1) and the
    signed diagonal. Finite for any finite F (F = 0 gives U = V = I, s = 0).
    """
    for i in range(3):
        for j in range(3):
            B[i, j] = F[i, j]
            V[i, j] = 1.0 if i == j else 0.0
    for _sweep in range(_MAX_SWEEPS):
        rotated = False
        for k in range(3):
            p, q, _r = _pair(k)
            al = B[0, p] * B[0, p] + B[1, p] * B[1, p] + B[2, p] * B[2, p]
            be = B[0, q] * B[0, q] + B[1, q] * B[1, q] + B[2, q] * B[2, q]
            ga = B[0, p] * B[0, q] + B[1, p] * B[1, q] + B[2, p] * B[2, q]
            if ga == 0.0 or abs(ga) <= _JACOBI_TOL * math.sqrt(al) * math.sqrt(be):
                continue
            rotated = True
            zeta = (be - al) / (2.0 * ga)
            if abs(zeta) > 1e150:
                t = 0.5 / zeta
            else:
                t = math.copysign(1.0, zeta) / (abs(zeta) + math.sqrt(1.0 + zeta * zeta))
            c = 1.0 / math.sqrt(1.0 + t * t)
            sn = c * t
            for m in range(3):
                bp = B[m, p]
                bq = B[m, q]
                B[m, p] = c * bp - sn * bq
                B[m, q] = sn * bp + c * bq
                vp = V[m, p]
                vq = V[m, q]
                V[m, p] = c * vp - sn * vq
                V[m, q] = sn * vp + c * vq
        if not rotated:
            break
    # sort columns by decreasing norm, keep det V = +1
    n0 = B[0, 0] * B[0, 0] + B[1, 0] * B[1, 0] + B[2, 0] * B[2, 0]
    n1 = B[0, 1] * B[0, 1] + B[1, 1] * B[1, 1] + B[2, 1] * B[2, 1]
    n2 = B[0, 2] * B[0, 2] + B[1, 2] * B[1, 2] + B[2, 2] * B[2, 2]
    flip = False
    if n0 < n1:
        _swap_cols(B, 0, 1)
        _swap_cols(V, 0, 1)
        n0, n1 = n1, n0
        flip = not flip
    if n1 < n2:
        _swap_cols(B, 1, 2)
        _swap_cols(V, 1, 2)
        n1, n2 = n2, n1
        flip = not flip
    if n0 < n1:
        _swap_cols(B, 0, 1)
        _swap_cols(V, 0, 1)
        flip = not flip
    if flip:
        for m in range(3):
            B[m, 2] = -B[m, 2]
            V[m, 2] = -V[m, 2]
    for i in range(3):
        for j in range(3):
            U[i, j] = 1.0 if i == j else 0.0
    _givens_rows(B, U, 0, 1, 0)
    _givens_rows(B, U, 0, 2, 0)
    _givens_rows(B, U, 1, 2, 1)
    s[0] = B[0, 0]
    s[1] = B[1, 1]
    s[2] = B[2, 2]


@njit(**_JIT)
def sym3_eig(A, w, Q):
    """Eigen-decomposition of a symmetric 3x3 A (destroyed) by cyclic Jacobi:
    A_in = Q diag(w) Q^T (unsorted)."""
    for i in range(3):
        for j in range(3):
            Q[i, j] = 1.0 if i == j else 0.0
    for _sweep in range(_MAX_SWEEPS):
        off = A[0, 1] * A[0, 1] + A[0, 2] * A[0, 2] + A[1, 2] * A[1, 2]
        dia = A[0, 0] * A[0, 0] + A[1, 1] * A[1, 1] + A[2, 2] * A[2, 2]
        if off == 0.0 or off <= 1e-34 * dia:
            break
        for k in range(3):
            p, q, r = _pair(k)
            apq = A[p, q]
            if apq == 0.0:
                continue
            theta = (A[q, q] - A[p, p]) / (2.0 * apq)
            if abs(theta) > 1e150:
                t = 0.5 / theta
            else:
                t = math.copysign(1.0, theta) / (abs(theta) + math.sqrt(theta * theta + 1.0))
            c = 1.0 / math.sqrt(t * t + 1.0)
            sn = t * c
            A[p, p] -= t * apq
            A[q, q] += t * apq
            A[p, q] = 0.0
            A[q, p] = 0.0
            arp = A[r, p]
            arq = A[r, q]
            A[r, p] = c * arp - sn * arq
            A[p, r] = A[r, p]
            A[r, q] = sn * arp + c * arq
            A[q, r] = A[r, q]
            for m in range(3):
                qp = Q[m, p]
                qq = Q[m, q]
                Q[m, p] = c * qp - sn * qq
                Q[m, q] = sn * qp + c * qq
    w[0] = A[0, 0]
    w[1] = A[1, 1]
    w[2] = A[2, 2]


@njit(**_JIT)
def _cofactor(F, C):
    """C = cof(F) = dJ/dF (rows are cross products of rows of F); returns J = det F."""
    for i in range(3):
        a = (i + 1) % 3
        b = (i + 2) % 3
        C[i, 0] = F[a, 1] * F[b, 2] - F[a, 2] * F[b, 1]
        C[i, 1] = F[a, 2] * F[b, 0] - F[a, 0] * F[b, 2]
        C[i, 2] = F[a, 0] * F[b, 1] - F[a, 1] * F[b, 0]
    return F[0, 0] * C[0, 0] + F[0, 1] * C[0, 1] + F[0, 2] * C[0, 2]


@njit(**_JIT)
def _frame_to_P(U, g, V, P_out):
    """P_out = U diag(g) V^T."""
    for i in range(3):
        for j in range(3):
            P_out[i, j] = U[i, 0] * g[0] * V[j, 0] + U[i, 1] * g[1] * V[j, 1] + U[i, 2] * g[2] * V[j, 2]


@njit(**_JIT)
def _assemble_frame(U, V, H, fl, tw, K, M, out, symmetric):
    """out = K A K^T, K = kron(U, V); A from the 3x3 block H and flip/twist per pair."""
    for a in range(3):
        for b in range(3):
            r = 3 * a + b
            for i in range(3):
                for j in range(3):
                    K[r, 3 * i + j] = U[a, i] * V[b, j]
    for r in range(9):
        for i in range(3):
            M[r, 4 * i] = K[r, 0] * H[0, i] + K[r, 4] * H[1, i] + K[r, 8] * H[2, i]
        for k in range(3):
            i, j, _o = _pair(k)
            m1 = 3 * i + j
            m2 = 3 * j + i
            ca = 0.5 * (fl[k] + tw[k])
            cb = 0.5 * (fl[k] - tw[k])
            k1 = K[r, m1]
            k2 = K[r, m2]
            M[r, m1] = k1 * ca + k2 * cb
            M[r, m2] = k1 * cb + k2 * ca
    if symmetric:
        for r in range(9):
            for c in range(r, 9):
                acc = 0.0
                for m in range(9):
                    acc += M[r, m] * K[c, m]
                out[r, c] = acc
                out[c, r] = acc
    else:
        for r in range(9):
            for c in range(9):
                acc = 0.0
                for m in range(9):
                    acc += M[r, m] * K[c, m]
                out[r, c] = acc


@njit(**_JIT)
def _needs_projection(H, fl, tw, A, w, Q):
    """Eigenvalues of the frame Hessian (H symmetric): True if any is below
    -PSD_TOL * max|eig|. Leaves the eigen-decomposition of H in (w, Q)."""
    for i in range(3):
        for j in range(3):
            A[i, j] = H[i, j]
    sym3_eig(A, w, Q)
    lo = 0.0
    big = 0.0
    for k in range(3):
        lo = min(lo, w[k], fl[k], tw[k])
        big = max(big, abs(w[k]), abs(fl[k]), abs(tw[k]))
    return lo < -PSD_TOL * big


@njit(**_JIT)
def _clamp_frame(H, fl, tw, w, Q):
    """Set negative eigenvalues to zero (H <- Q diag(max(w, 0)) Q^T, given (w, Q))."""
    for k in range(3):
        if fl[k] < 0.0:
            fl[k] = 0.0
        if tw[k] < 0.0:
            tw[k] = 0.0
    w0 = max(w[0], 0.0)
    w1 = max(w[1], 0.0)
    w2 = max(w[2], 0.0)
    for i in range(3):
        for j in range(3):
            H[i, j] = Q[i, 0] * w0 * Q[j, 0] + Q[i, 1] * w1 * Q[j, 1] + Q[i, 2] * w2 * Q[j, 2]


@njit(**_JIT)
def _views(work):
    U = work[_O_U:_O_U + 9].reshape((3, 3))
    V = work[_O_V:_O_V + 9].reshape((3, 3))
    B = work[_O_B:_O_B + 9].reshape((3, 3))
    H = work[_O_H:_O_H + 9].reshape((3, 3))
    Q = work[_O_Q:_O_Q + 9].reshape((3, 3))
    A = work[_O_A:_O_A + 9].reshape((3, 3))
    s = work[_O_S:_O_S + 3]
    g = work[_O_G:_O_G + 3]
    fl = work[_O_FL:_O_FL + 3]
    tw = work[_O_TW:_O_TW + 3]
    w = work[_O_W:_O_W + 3]
    K = work[_O_K:_O_K + 81].reshape((9, 9))
    M = work[_O_M:_O_M + 81].reshape((9, 9))
    return U, V, B, H, Q, A, s, g, fl, tw, w, K, M


# ---------------------------------------------------------------------------------------
# St. Venant-Kirchhoff with the invertible-FEM clamp
# ---------------------------------------------------------------------------------------
@njit(**_JIT)
def _stvk_frame(s, s_min, mu, lam, g, H, fl, tw):
    """Principal data of StVK evaluated at s_hat = max(s, s_min), extrapolated below s_min.

    g: principal stress, g_i = p_i(s_hat) + k (s_i - s_min) [s_i < s_min] with k = 2 mu + lam
    (the rest stiffness along one axis: the restoring stress grows with the depth of
    compression or inversion, Irving et al. 2004, instead of staying at its value at s_min);
    H[i, j] = dg_i/ds_j: d p_i/ds_j (s_hat) * [s_j unclamped] + k [i == j clamped];
    fl/tw: flip/twist eigenvalues of d(U diag(g) V^T)/dF. Returns (psi, n_clamped),
    psi = psihat(s_hat) + sum_{clamped i} (p_i(s_hat) (s_i - s_min) + k/2 (s_i - s_min)^2).
    """
    sh0 = max(s[0], s_min)
    sh1 = max(s[1], s_min)
    sh2 = max(s[2], s_min)
    e0 = 0.5 * (sh0 * sh0 - 1.0)
    e1 = 0.5 * (sh1 * sh1 - 1.0)
    e2 = 0.5 * (sh2 * sh2 - 1.0)
    tr = e0 + e1 + e2
    psi = mu * (e0 * e0 + e1 * e1 + e2 * e2) + 0.5 * lam * tr * tr
    T = lam * tr - mu
    d = 2.0 * mu + lam
    sh = (sh0, sh1, sh2)
    ee = (e0, e1, e2)
    n_cl = 0
    ex = (min(s[0] - s_min, 0.0) * d, min(s[1] - s_min, 0.0) * d, min(s[2] - s_min, 0.0) * d)
    for i in range(3):
        Si = 2.0 * mu * ee[i] + lam * tr
        g[i] = Si * sh[i]
        if s[i] < s_min:
            n_cl += 1
            psi += (g[i] + 0.5 * ex[i]) * (s[i] - s_min)
            g[i] += ex[i]
        for j in range(3):
            if s[j] < s_min:
                H[i, j] = d if i == j else 0.0
            elif i == j:
                H[i, j] = Si + d * sh[i] * sh[i]
            else:
                H[i, j] = lam * sh[i] * sh[j]
    for k in range(3):
        i, j, _o = _pair(k)
        si = sh[i]
        sj = sh[j]
        fbase = mu * (si * si + si * sj + sj * sj) + T
        tbase = mu * (si * si - si * sj + sj * sj) + T
        ci = s[i] < s_min
        cj = s[j] < s_min
        if not ci and not cj:
            fl[k] = fbase
            tw[k] = tbase
        else:
            # (g_i -+ g_j) / (s_i -+ s_j) with the extrapolation ex in g
            if ci and cj:
                fl[k] = d
            else:
                fl[k] = (fbase * (si - sj) + ex[i] - ex[j]) / (s[i] - s[j])
            tw[k] = (tbase * (si + sj) + ex[i] + ex[j]) / max(s[i] + s[j], TWIST_DENOM_MIN)
    return psi, n_cl


@njit(**_JIT)
def _shifted_pd(C, c):
    """True if C - c I is positive definite (Sylvester, C symmetric 3x3)."""
    a00 = C[0, 0] - c
    a11 = C[1, 1] - c
    a22 = C[2, 2] - c
    if a00 <= 0.0:
        return False
    m2 = a00 * a11 - C[0, 1] * C[0, 1]
    if m2 <= 0.0:
        return False
    det = (a00 * (a11 * a22 - C[1, 2] * C[1, 2]) - C[0, 1] * (C[0, 1] * a22 - C[1, 2] * C[0, 2])
           + C[0, 2] * (C[0, 1] * C[1, 2] - a11 * C[0, 2]))
    return det > 0.0


@njit(**_JIT)
def stvk_point_ws(F, mu, lam, s_min, P_out, dPdF_out, want_hessian, project, work):
    """St. Venant-Kirchhoff point kernel with scratch ``work`` (WORK_LEN,); see stvk_point."""
    # The closed form needs three views of the scratch; the SVD branches make the rest.
    # Each view made costs an atomic reference count (see neohookean_point_ws): all
    # thirteen made here cost a point 810 ns instead of 306-353 without its Hessian (one
    # thread, 2,500 points near F = I, session 20), with the same bits.
    B = work[_O_B:_O_B + 9].reshape((3, 3))
    A = work[_O_A:_O_A + 9].reshape((3, 3))
    Q = work[_O_Q:_O_Q + 9].reshape((3, 3))
    # C = F^T F (in B), closed-form check min(s) > s_min  <=>  det F > 0 and C - s_min^2 I > 0
    for i in range(3):
        for j in range(3):
            B[i, j] = F[0, i] * F[0, j] + F[1, i] * F[1, j] + F[2, i] * F[2, j]
    detF = (F[0, 0] * (F[1, 1] * F[2, 2] - F[1, 2] * F[2, 1])
            - F[0, 1] * (F[1, 0] * F[2, 2] - F[1, 2] * F[2, 0])
            + F[0, 2] * (F[1, 0] * F[2, 1] - F[1, 1] * F[2, 0]))
    if detF > 0.0 and _shifted_pd(B, s_min * s_min):
        # S = lam tr(E) I + 2 mu E, E = (C - I)/2  (S stored in A)
        trE = 0.5 * (B[0, 0] + B[1, 1] + B[2, 2] - 3.0)
        psi = 0.5 * lam * trE * trE
        for i in range(3):
            for j in range(3):
                Eij = 0.5 * (B[i, j] - (1.0 if i == j else 0.0))
                psi += mu * Eij * Eij
                A[i, j] = 2.0 * mu * Eij + (lam * trE if i == j else 0.0)
        for i in range(3):
            for j in range(3):
                P_out[i, j] = F[i, 0] * A[0, j] + F[i, 1] * A[1, j] + F[i, 2] * A[2, j]
        if want_hessian:
            # G = F F^T (in Q)
            for i in range(3):
                for k in range(3):
                    Q[i, k] = F[i, 0] * F[k, 0] + F[i, 1] * F[k, 1] + F[i, 2] * F[k, 2]
            # dPdF[(i,j),(k,l)] = d_ik S_lj + lam F_ij F_kl + mu F_il F_kj + mu G_ik d_jl
            # (symmetric by construction: upper triangle, mirrored)
            for r in range(9):
                i = r // 3
                j = r % 3
                for c in range(r, 9):
                    k = c // 3
                    l = c % 3
                    v = lam * F[i, j] * F[k, l] + mu * F[i, l] * F[k, j]
                    if i == k:
                        v += A[l, j]
                    if j == l:
                        v += mu * Q[i, k]
                    dPdF_out[r, c] = v
                    dPdF_out[c, r] = v
            if project:
                U, V, B, H, Q, A, s, g, fl, tw, w, K, M = _views(work)
                svd3_signed(F, U, s, V, B)
                for i in range(3):  # all s > s_min here; guard against round-off at the edge
                    s[i] = max(s[i], s_min)
                _stvk_frame(s, s_min, mu, lam, g, H, fl, tw)
                if _needs_projection(H, fl, tw, A, w, Q):
                    _clamp_frame(H, fl, tw, w, Q)
                    _assemble_frame(U, V, H, fl, tw, K, M, dPdF_out, True)
        return psi
    # clamped (or inverted / degenerate) branch: stress from s_hat = max(s, s_min)
    U, V, B, H, Q, A, s, g, fl, tw, w, K, M = _views(work)
    svd3_signed(F, U, s, V, B)
    psi, n_cl = _stvk_frame(s, s_min, mu, lam, g, H, fl, tw)
    _frame_to_P(U, g, V, P_out)
    if want_hessian:
        symmetric = n_cl == 0
        if project:
            if not symmetric:
                for i in range(3):
                    for j in range(i + 1, 3):
                        hs = 0.5 * (H[i, j] + H[j, i])
                        H[i, j] = hs
                        H[j, i] = hs
            if _needs_projection(H, fl, tw, A, w, Q):
                _clamp_frame(H, fl, tw, w, Q)
            symmetric = True
        _assemble_frame(U, V, H, fl, tw, K, M, dPdF_out, symmetric)
    return psi


@njit(**_JIT)
def stvk_point(F, mu, lam, s_min, P_out, dPdF_out, want_hessian, project):
    """St. Venant-Kirchhoff, psi = mu E:E + lam/2 tr(E)^2, E = (F^T F - I)/2, P = F S.

    Closed form when min signed singular value > s_min; otherwise P = U diag(g) V^T with
    g_i = p_i(s_hat) + k min(s_i - s_min, 0), s_hat = max(s, s_min), k = 2 mu + lam, and
    psi = psihat(s_hat) + sum_{s_i < s_min} (p_i(s_hat) (s_i - s_min) + k/2 (s_i - s_min)^2)
    (not the potential of P there; dPdF is the exact derivative of that P and not symmetric).
    Writes P_out (3, 3) and, if want_hessian, dPdF_out (9, 9); returns psi.
    """
    work = np.empty(WORK_LEN)
    return stvk_point_ws(F, mu, lam, s_min, P_out, dPdF_out, want_hessian, project, work)


# ---------------------------------------------------------------------------------------
# fixed corotated
# ---------------------------------------------------------------------------------------
@njit(**_JIT)
def _corot_frame(s, mu, lam, H, fl, tw):
    J = s[0] * s[1] * s[2]
    c0 = s[1] * s[2]
    c1 = s[0] * s[2]
    c2 = s[0] * s[1]
    cc = (c0, c1, c2)
    lj = lam * (J - 1.0)
    for i in range(3):
        H[i, i] = 2.0 * mu + lam * cc[i] * cc[i]
    for k in range(3):
        i, j, o = _pair(k)
        hij = lam * cc[i] * cc[j] + lj * s[o]
        H[i, j] = hij
        H[j, i] = hij
        fl[k] = 2.0 * mu - lj * s[o]
        tw[k] = 2.0 * mu - 4.0 * mu / max(s[i] + s[j], TWIST_DENOM_MIN) + lj * s[o]


@njit(**_JIT)
def corotated_point_ws(F, mu, lam, P_out, dPdF_out, want_hessian, project, work):
    """Fixed corotated point kernel with scratch ``work`` (WORK_LEN,); see corotated_point."""
    # Only the views each part needs (see stvk_point_ws): the stress needs five.
    U = work[_O_U:_O_U + 9].reshape((3, 3))
    V = work[_O_V:_O_V + 9].reshape((3, 3))
    B = work[_O_B:_O_B + 9].reshape((3, 3))
    A = work[_O_A:_O_A + 9].reshape((3, 3))
    s = work[_O_S:_O_S + 3]
    svd3_signed(F, U, s, V, B)
    J = _cofactor(F, A)
    psi = mu * ((s[0] - 1.0) ** 2 + (s[1] - 1.0) ** 2 + (s[2] - 1.0) ** 2) + 0.5 * lam * (J - 1.0) ** 2
    lj = lam * (J - 1.0)
    for i in range(3):
        for j in range(3):
            Rij = U[i, 0] * V[j, 0] + U[i, 1] * V[j, 1] + U[i, 2] * V[j, 2]
            P_out[i, j] = 2.0 * mu * (F[i, j] - Rij) + lj * A[i, j]
    if want_hessian:
        H = work[_O_H:_O_H + 9].reshape((3, 3))
        fl = work[_O_FL:_O_FL + 3]
        tw = work[_O_TW:_O_TW + 3]
        K = work[_O_K:_O_K + 81].reshape((9, 9))
        M = work[_O_M:_O_M + 81].reshape((9, 9))
        _corot_frame(s, mu, lam, H, fl, tw)
        if project:
            Q = work[_O_Q:_O_Q + 9].reshape((3, 3))
            w = work[_O_W:_O_W + 3]
        if project and _needs_projection(H, fl, tw, A, w, Q):
            _clamp_frame(H, fl, tw, w, Q)
        _assemble_frame(U, V, H, fl, tw, K, M, dPdF_out, True)
    return psi


@njit(**_JIT)
def corotated_point(F, mu, lam, P_out, dPdF_out, want_hessian, project):
    """Fixed corotated (Stomakhin et al. 2012): psi = mu ||F - R||^2 + lam/2 (J - 1)^2,
    R = U V^T from the signed SVD; P = 2 mu (F - R) + lam (J - 1) cof(F).
    Writes P_out and, if want_hessian, dPdF_out; returns psi."""
    work = np.empty(WORK_LEN)
    return corotated_point_ws(F, mu, lam, P_out, dPdF_out, want_hessian, project, work)


# ---------------------------------------------------------------------------------------
# stable neo-Hookean
# ---------------------------------------------------------------------------------------
def _cofactor_derivative_table():
    """d cof(F)_ij / dF_kl = eps_ikn eps_jlq F_nq: its 18 non-zero entries above the
    diagonal of the (9, 9) vec layout, as rows (r, c, sign, n, q), int64."""
    rows = []
    for r in range(9):
        i, j = divmod(r, 3)
        for c in range(r + 1, 9):
            k, l = divmod(c, 3)
            if i != k and j != l:
                e1 = 1 if (k - i) % 3 == 1 else -1
                e2 = 1 if (l - j) % 3 == 1 else -1
                rows.append((r, c, e1 * e2, 3 - i - k, 3 - j - l))
    return np.array(rows, dtype=np.int64)


_COF = _cofactor_derivative_table()


@njit(**_JIT)
def snh_parameters(mu, lam):
    """(mu', lam', alpha, psi0) of Smith et al. 2018 matching the Lame pair (mu, lam) at F = I:
    mu' = 4/3 mu, lam' = lam + 5/6 mu, alpha = 1 + mu/lam' (= 1 + 3 mu'/(4 lam')),
    psi0 = psi'(I) subtracted so that psi(R) = 0."""
    mup = 4.0 * mu / 3.0
    lamp = lam + 5.0 * mu / 6.0
    alpha = 1.0 + mu / lamp
    psi0 = 0.5 * lamp * (1.0 - alpha) ** 2 - 0.5 * mup * math.log(4.0)
    return mup, lamp, alpha, psi0


@njit(**_JIT)
def neohookean_point_ws(F, mu, lam, P_out, dPdF_out, want_hessian, project, work):
    """Stable neo-Hookean point kernel with scratch ``work`` (WORK_LEN,); see neohookean_point."""
    # Without the integer division and branches per entry of the loop over (r, c) this
    # replaces: a point with its Hessian took 295 ns, and 173 ns so (one thread, a loop of
    # 1M points, session 13), with the same bits.
    # vec(cof F) and vec(F) live in the scratch at offsets _O_A and _O_T (the barrier's
    # slot: it runs after this), indexed there rather than through slices of it: a slice
    # is a new array view whose reference count numba raises and lowers atomically, and
    # the two views made this point cost 111 ns instead of 36 without its Hessian (one
    # thread, 2,500 points, session 20), with the same bits.
    mup, lamp, alpha, psi0 = snh_parameters(mu, lam)
    F00, F01, F02 = F[0, 0], F[0, 1], F[0, 2]
    F10, F11, F12 = F[1, 0], F[1, 1], F[1, 2]
    F20, F21, F22 = F[2, 0], F[2, 1], F[2, 2]
    a, f = _O_A, _O_T                        # rows of cof F are cross products of rows of F
    work[a + 0] = F11 * F22 - F12 * F21
    work[a + 1] = F12 * F20 - F10 * F22
    work[a + 2] = F10 * F21 - F11 * F20
    work[a + 3] = F21 * F02 - F22 * F01
    work[a + 4] = F22 * F00 - F20 * F02
    work[a + 5] = F20 * F01 - F21 * F00
    work[a + 6] = F01 * F12 - F02 * F11
    work[a + 7] = F02 * F10 - F00 * F12
    work[a + 8] = F00 * F11 - F01 * F10
    J = F00 * work[a] + F01 * work[a + 1] + F02 * work[a + 2]
    work[f + 0], work[f + 1], work[f + 2] = F00, F01, F02
    work[f + 3], work[f + 4], work[f + 5] = F10, F11, F12
    work[f + 6], work[f + 7], work[f + 8] = F20, F21, F22
    Ic = 0.0
    for r in range(9):
        Ic += work[f + r] * work[f + r]
    q = 1.0 / (Ic + 1.0)
    kap = mup * (1.0 - q)
    lj = lamp * (J - alpha)
    psi = 0.5 * mup * (Ic - 3.0) + 0.5 * lamp * (J - alpha) ** 2 - 0.5 * mup * math.log(Ic + 1.0) - psi0
    for r in range(9):
        P_out[r // 3, r % 3] = kap * work[f + r] + lj * work[a + r]
    if want_hessian:
        # dP/dF = c2 vec(F) vec(F)^T + lam' vec(A) vec(A)^T + kap I + lj d cof/dF, the last
        # from the constant table _COF. The upper triangle is formed as (c2 f_r) f_c +
        # (lam' a_r) a_c and mirrored: the same operations, in the same order, as the loop
        # it replaces, so the same bits (a chaotic stability cell follows round-off).
        c2 = 2.0 * mup * q * q
        for r in range(9):
            fr = c2 * work[f + r]
            ar = lamp * work[a + r]
            for c in range(r, 9):
                v = fr * work[f + c] + ar * work[a + c]
                dPdF_out[r, c] = v
                dPdF_out[c, r] = v
            dPdF_out[r, r] += kap
        for m in range(_COF.shape[0]):
            r, c = _COF[m, 0], _COF[m, 1]
            v = dPdF_out[r, c] + lj * _COF[m, 2] * work[f + 3 * _COF[m, 3] + _COF[m, 4]]
            dPdF_out[r, c] = v
            dPdF_out[c, r] = v
        if project:
            U, V, B, H, Q, A, s, g, fl, tw, w, K, M = _views(work)
            svd3_signed(F, U, s, V, B)
            Js = s[0] * s[1] * s[2]
            ljs = lamp * (Js - alpha)
            cc = (s[1] * s[2], s[0] * s[2], s[0] * s[1])
            for i in range(3):
                for j in range(3):
                    H[i, j] = c2 * s[i] * s[j] + lamp * cc[i] * cc[j]
                H[i, i] += kap
            for k in range(3):
                i, j, o = _pair(k)
                H[i, j] += ljs * s[o]
                H[j, i] += ljs * s[o]
                fl[k] = kap - ljs * s[o]
                tw[k] = kap + ljs * s[o]
            if _needs_projection(H, fl, tw, A, w, Q):
                _clamp_frame(H, fl, tw, w, Q)
                _assemble_frame(U, V, H, fl, tw, K, M, dPdF_out, True)
    return psi


@njit(**_JIT)
def neohookean_point(F, mu, lam, P_out, dPdF_out, want_hessian, project):
    """Stable neo-Hookean (Smith, de Goes, Kim 2018) with Lame parameters (mu, lam):
    psi = mu'/2 (I_C - 3) + lam'/2 (J - alpha)^2 - mu'/2 log(I_C + 1) - psi0 (snh_parameters).
    Closed-form P and dPdF (no SVD unless project). Returns psi."""
    work = np.empty(WORK_LEN)
    return neohookean_point_ws(F, mu, lam, P_out, dPdF_out, want_hessian, project, work)


# ---------------------------------------------------------------------------------------
# compression barrier (every material)
# ---------------------------------------------------------------------------------------
@njit(**_JIT)
def barrier_terms(J, k, jb):
    """(psi, dpsi/dJ, d2psi/dJ2) of the compression barrier psi_b = k/(3 jb) (jb - J)^3 for
    J < jb, 0 above: C2 at jb, so small-strain behaviour and Newton are untouched."""
    if k <= 0.0 or J >= jb:
        return 0.0, 0.0, 0.0
    d = jb - J
    return k * d * d * d / (3.0 * jb), -k * d * d / jb, 2.0 * k * d / jb


@njit(cache=True, inline="always")
def _det3(F):
    """det F of a (3, 3) F."""
    return (F[0, 0] * (F[1, 1] * F[2, 2] - F[1, 2] * F[2, 1])
            - F[0, 1] * (F[1, 0] * F[2, 2] - F[1, 2] * F[2, 0])
            + F[0, 2] * (F[1, 0] * F[2, 1] - F[1, 1] * F[2, 0]))


@njit(**_JIT)
def _add_barrier(F, k, jb, P_out, dPdF_out, want_hessian, project, work):
    """Add the compression barrier to (P_out, dPdF_out) in place; returns its psi.
    P_b = a cof(F); dP_b = b cof (x) cof + a d cof/dF (a, b = dpsi/dJ, d2psi/dJ2). With
    project, the barrier's own Hessian is projected in the SVD frame before it is added
    (a sum of PSD parts is PSD)."""
    # The common case (J >= jb) must cost a determinant, not the scratch views below
    # (material_point_ws tests it before calling).
    if _det3(F) >= jb:
        return 0.0
    U, V, B, H, Q, A, s, g, fl, tw, w, K, M = _views(work)
    J = _cofactor(F, A)
    psi, a, b = barrier_terms(J, k, jb)
    for i in range(3):
        for j in range(3):
            P_out[i, j] += a * A[i, j]
    if not want_hessian:
        return psi
    if not project:
        for r in range(9):
            i = r // 3
            j = r % 3
            for c in range(9):
                kk = c // 3
                l = c % 3
                v = b * A[i, j] * A[kk, l]
                if i != kk and j != l:
                    e1 = 1.0 if (kk - i) % 3 == 1 else -1.0
                    e2 = 1.0 if (l - j) % 3 == 1 else -1.0
                    v += a * e1 * e2 * F[3 - i - kk, 3 - j - l]
                dPdF_out[r, c] += v
        return psi
    svd3_signed(F, U, s, V, B)
    cc = (s[1] * s[2], s[0] * s[2], s[0] * s[1])
    for i in range(3):
        for j in range(3):
            H[i, j] = b * cc[i] * cc[j]
    for m in range(3):
        i, j, o = _pair(m)
        H[i, j] += a * s[o]
        H[j, i] += a * s[o]
        fl[m] = -a * s[o]
        tw[m] = a * s[o]
    if _needs_projection(H, fl, tw, A, w, Q):
        _clamp_frame(H, fl, tw, w, Q)
    T = work[_O_T:_O_T + 81].reshape((9, 9))
    _assemble_frame(U, V, H, fl, tw, K, M, T, True)
    for r in range(9):
        for c in range(9):
            dPdF_out[r, c] += T[r, c]
    return psi


# ---------------------------------------------------------------------------------------
# dispatch and batch
# ---------------------------------------------------------------------------------------
@njit(**_JIT)
def material_point_ws(kind_id, F, params, P_out, dPdF_out, want_hessian, project, work):
    """material_point with caller-held scratch ``work`` (WORK_LEN,) float64: no allocation."""
    if kind_id == KIND_STVK:
        psi = stvk_point_ws(F, params[0], params[1], params[2], P_out, dPdF_out,
                            want_hessian, project, work)
    elif kind_id == KIND_COROTATED:
        psi = corotated_point_ws(F, params[0], params[1], P_out, dPdF_out,
                                 want_hessian, project, work)
    elif kind_id == KIND_NEOHOOKEAN:
        psi = neohookean_point_ws(F, params[0], params[1], P_out, dPdF_out,
                                  want_hessian, project, work)
    else:
        raise ValueError("material_point: unknown kind_id (0 stvk, 1 corotated, 2 neohookean)")
    # The barrier acts below J = params[4] only: tested here, because even a call of
    # _add_barrier that returns at once cost a neo-Hookean point 90 ns (session 20).
    if params[3] > 0.0 and _det3(F) < params[4]:
        psi += _add_barrier(F, params[3], params[4], P_out, dPdF_out, want_hessian, project, work)
    return psi


@njit(**_JIT)
def material_point(kind_id, F, params, P_out, dPdF_out, want_hessian, project):
    """Generic point kernel: kind_id in {KIND_STVK 0, KIND_COROTATED 1, KIND_NEOHOOKEAN 2},
    params (N_PARAMS,) = [mu, lam, s_min, barrier k, barrier j] (s_min used by StVK only;
    k = 0 turns the compression barrier off). Returns psi."""
    work = np.empty(WORK_LEN)
    return material_point_ws(kind_id, F, params, P_out, dPdF_out, want_hessian, project, work)


_BATCH_CHUNK = 128


@njit(cache=True, parallel=True, error_model="numpy")
def material_batch(kind_id, params, F, psi_out, P_out, dPdF_out, want_hessian, project):
    """Evaluate m points in parallel: F (m, 3, 3) -> psi_out (m,), P_out (m, 3, 3),
    dPdF_out (m, 9, 9) (any (>=1, 9, 9) array and untouched if not want_hessian)."""
    if kind_id < 0 or kind_id > 2:
        raise ValueError("material_batch: unknown kind_id (0 stvk, 1 corotated, 2 neohookean)")
    m = F.shape[0]
    nchunk = (m + _BATCH_CHUNK - 1) // _BATCH_CHUNK
    for c in prange(nchunk):
        work = np.empty(WORK_LEN)
        lo = c * _BATCH_CHUNK
        hi = min(m, lo + _BATCH_CHUNK)
        for n in range(lo, hi):
            if want_hessian:
                psi_out[n] = material_point_ws(kind_id, F[n], params, P_out[n], dPdF_out[n],
                                               True, project, work)
            else:
                psi_out[n] = material_point_ws(kind_id, F[n], params, P_out[n], dPdF_out[0],
                                               False, False, work)
