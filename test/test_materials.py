"""Hyperelastic material kernels: derivatives, invariance, linearisation, inversion, PSD projection."""
import dataclasses

import numpy as np
import pytest
from numba import njit

from mdss_ros.errors import SceneError
from mdss_ros.fem.materials import (
    BARRIER_DEFAULT,
    BARRIER_J_DEFAULT,
    KIND_COROTATED,
    KIND_NEOHOOKEAN,
    KIND_STVK,
    Corotated,
    NeoHookean,
    StVK,
    make_material,
    material_point,
    reference_barrier,
    reference_psi_P,
    signed_svd,
    svd3_signed,
)

E_, NU_, RHO_ = 1.0e5, 0.3, 1000.0
MATERIALS = [StVK(E_, NU_, RHO_), Corotated(E_, NU_, RHO_), NeoHookean(E_, NU_, RHO_)]
IDS = [m.name for m in MATERIALS]
# other Poisson ratios (lam = 0 and nearly incompressible)
OTHER_NU = [cls(2.0e6, nu, 1100.0) for nu in (0.0, 0.49) for cls in (StVK, Corotated, NeoHookean)]
OTHER_IDS = [f"{m.name}-nu{m.poisson}" for m in OTHER_NU]
S_MIN = MATERIALS[0].s_min


def rotation(rng):
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] *= -1.0
    return q


def with_singular_values(s, rng):
    return rotation(rng) @ np.diag(s) @ rotation(rng).T


def point(mat, F, want_hessian=True, project=False):
    P = np.empty((3, 3))
    H = np.zeros((9, 9))
    psi = material_point(mat.kind_id, np.ascontiguousarray(F, dtype=np.float64), mat.params,
                         P, H, want_hessian, project)
    return psi, P, H


def sample(kind, n=3, seed=0):
    """Deformation gradients of one regime (singular values kept away from s_min)."""
    rng = np.random.default_rng(seed + 101 * REGIMES.index(kind))
    out = []
    for _ in range(n):
        if kind == "identity":
            out.append(np.eye(3) + 0.05 * rng.normal(size=(3, 3)))
        elif kind == "compressed":  # just above StVK's clamp
            out.append(with_singular_values(0.55 + 0.03 * rng.uniform(-1, 1, 3), rng))
        elif kind == "crushed":  # all three StVK values clamped
            out.append(with_singular_values(0.4 + 0.04 * rng.uniform(-1, 1, 3), rng))
        elif kind == "stretched":
            out.append(with_singular_values([2.5, 1.8, 1.3] + 0.1 * rng.uniform(-1, 1, 3), rng))
        elif kind == "moderate":  # compressed but above StVK's clamp
            out.append(with_singular_values([0.95, 0.75, 0.65] + 0.03 * rng.uniform(-1, 1, 3), rng))
        elif kind == "mixed":  # one, two and two-with-inversion clamped StVK values
            s = [[1.6, 0.8, 0.35], [1.4, 0.42, 0.3], [1.2, 0.42, -0.3]][len(out) % 3]
            out.append(with_singular_values(s + 0.03 * rng.uniform(-1, 1, 3), rng))
        elif kind == "inverted":
            s = [1.1, 0.8, -0.5] + 0.05 * rng.uniform(-1, 1, 3)
            F = with_singular_values(s, rng)
            assert np.linalg.det(F) < 0
            out.append(F)
    return out


REGIMES = ["identity", "moderate", "compressed", "crushed", "stretched", "mixed", "inverted"]


def smooth(mat, F):
    """psi is smooth at F (StVK only above the clamp)."""
    return mat.name != "stvk" or signed_svd(F[None])[1].min() >= S_MIN


def rel(a, b):
    return np.linalg.norm(a - b) / max(np.linalg.norm(b), 1e-300)


def degenerate_Fs():
    rng = np.random.default_rng(7)
    a = rng.normal(size=3)
    b = rng.normal(size=3)
    return [np.zeros((3, 3)), np.diag([1.0, 1.0, 0.0]), np.diag([1.0, 0.0, 0.0]),
            np.diag([0.5, 0.5, 0.5]), np.diag([1.0, 1.0, -1.0]), -np.eye(3), np.eye(3),
            np.diag([1.0, -1.0, -1.0]), np.outer(a, b), np.diag([2.0, 1.0, 1.0]),
            np.diag([1.0, 1.0, -1e-12]), 1e-8 * rng.normal(size=(3, 3))]


# ---------------------------------------------------------------------------------------
# signed SVD
# ---------------------------------------------------------------------------------------
def test_signed_svd_reconstructs_with_rotations_and_sorted_signed_values():
    rng = np.random.default_rng(1)
    Fs = [rng.normal(size=(3, 3)) for _ in range(50)] + degenerate_Fs()
    Fs += [with_singular_values([1.0, 1e-9, 1e-10], rng), with_singular_values([3.0, 3.0, -3.0], rng)]
    U, V, B = np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3))
    s = np.empty(3)
    for F in Fs:
        svd3_signed(F, U, s, V, B)
        scale = max(np.linalg.norm(F), 1e-300)
        assert np.linalg.norm(U @ np.diag(s) @ V.T - F) <= 1e-14 * scale + 1e-300
        assert np.allclose(U.T @ U, np.eye(3), atol=1e-14) and np.allclose(V.T @ V, np.eye(3), atol=1e-14)
        assert np.linalg.det(U) > 0 and np.linalg.det(V) > 0
        assert s[0] >= s[1] >= abs(s[2]) - 1e-15 * scale
        ref = np.linalg.svd(F, compute_uv=False)
        assert np.allclose(np.abs(s), ref, rtol=0, atol=1e-14 * scale)
        if np.linalg.det(F) < -1e-12 * scale ** 3:
            assert s[2] < 0


# ---------------------------------------------------------------------------------------
# derivatives
# ---------------------------------------------------------------------------------------
def fd_gradient(fun, F, h):
    out = []
    for b in range(9):
        dF = np.zeros(9)
        dF[b] = h
        dF = dF.reshape(3, 3)
        out.append((fun(F + dF) - fun(F - dF)) / (2.0 * h))
    return np.array(out)


@pytest.mark.parametrize("regime", REGIMES)
@pytest.mark.parametrize("mat", MATERIALS, ids=IDS)
def test_P_is_gradient_of_psi(mat, regime):
    for F in sample(regime):
        if not smooth(mat, F):
            continue
        h = 1e-6 * np.linalg.norm(F)
        fd = fd_gradient(lambda G: point(mat, G, False)[0], F, h)
        assert rel(fd, point(mat, F, False)[1].ravel()) < 1e-6


@pytest.mark.parametrize("regime", REGIMES)
@pytest.mark.parametrize("mat", MATERIALS, ids=IDS)
def test_dPdF_is_derivative_of_P(mat, regime):
    for F in sample(regime):
        h = 1e-6 * np.linalg.norm(F)
        fd = fd_gradient(lambda G: point(mat, G, False)[1].ravel(), F, h).T  # [a, b]
        H = point(mat, F)[2]
        assert rel(fd, H) < 1e-6
        if smooth(mat, F):
            assert np.linalg.norm(H - H.T) <= 1e-12 * np.linalg.norm(H)


@pytest.mark.parametrize("mat", OTHER_NU, ids=OTHER_IDS)
def test_derivatives_other_poisson_ratios(mat):
    for regime in ("identity", "compressed", "mixed", "inverted"):
        for F in sample(regime, n=2, seed=21):
            h = 1e-6 * np.linalg.norm(F)
            H = point(mat, F)[2]
            fd = fd_gradient(lambda G: point(mat, G, False)[1].ravel(), F, h).T
            assert rel(fd, H) < 1e-6
            if smooth(mat, F):
                fd = fd_gradient(lambda G: point(mat, G, False)[0], F, h)
                assert rel(fd, point(mat, F, False)[1].ravel()) < 1e-6


def test_stvk_clamped_branch_is_continuous_and_not_a_gradient():
    mat = MATERIALS[0]
    rng = np.random.default_rng(3)
    U, V = rotation(rng), rotation(rng)
    on = U @ np.diag([1.3, 0.9, S_MIN]) @ V.T
    psi_a, P_a, H_a = point(mat, on * (1 + 1e-12))   # closed form
    psi_b, P_b, H_b = point(mat, on * (1 - 1e-12))   # clamped branch
    assert abs(psi_a - psi_b) < 1e-9 * mat.mu and rel(P_b, P_a) < 1e-9
    below = U @ np.diag([1.3, 0.9, 0.3]) @ V.T
    H = point(mat, below)[2]
    assert np.linalg.norm(H - H.T) > 1e-3 * np.linalg.norm(H)
    # energy extension: derivative along the clamped singular value equals the force
    s3 = lambda t: point(mat, U @ np.diag([1.3, 0.9, t]) @ V.T)[0]  # noqa: E731
    P = point(mat, below)[1]
    dpsi = (s3(0.3 + 1e-6) - s3(0.3 - 1e-6)) / 2e-6
    assert abs(dpsi - U[:, 2] @ P @ V[:, 2]) < 1e-6 * np.linalg.norm(P)


def test_stvk_push_back_grows_below_the_clamp():
    """Below s_min the principal stress along the clamped value is extrapolated with the rest
    stiffness k = 2 mu + lam: its slope is exactly -k further down (the restoring stress
    grows with the depth of compression or inversion), and under the lateral stretch of a
    hanging 1 kPa beam's top fibre (s = 2.2, where lam tr E makes the clamped stress tensile)
    it turns restoring at s_min - p(s_min) / k, before the element inverts at nu = 0.3 (at
    nu = 0.45 only just after: the weak point that is left, see fem/materials.py)."""
    rng = np.random.default_rng(4)
    U, V = rotation(rng), rotation(rng)
    for mat in (StVK(E_, NU_, RHO_, barrier=0.0), StVK(1e3, 0.3, 1000.0, barrier=0.0),
                StVK(1e3, 0.49, 1000.0, barrier=0.0)):       # the extrapolation alone
        mu, lam = mat.lame()
        k = 2 * mu + lam

        def stress(t, s0=1.3):                          # principal stress along the third value
            P = point(mat, U @ np.diag([s0, 0.9, t]) @ V.T, False)[1]
            return U[:, 2] @ P @ V[:, 2]
        ts = np.array([0.45, 0.3, 0.0, -0.3, -0.6])
        g = np.array([stress(t) for t in ts])
        np.testing.assert_allclose(np.diff(g) / np.diff(ts), k, rtol=1e-9)
        assert np.all(g[2:] < 0)                         # flat or inverted: pushed back
        if mat.poisson == 0.3:
            wide = np.array([stress(t, s0=2.2) for t in (0.45, 0.0, -0.2)])
            assert wide[0] > 0 and wide[1] < 0 and wide[2] < wide[1]


# ---------------------------------------------------------------------------------------
# invariance and rest state
# ---------------------------------------------------------------------------------------
@pytest.mark.parametrize("mat", MATERIALS, ids=IDS)
def test_frame_indifference_and_isotropy(mat):
    rng = np.random.default_rng(11)
    for regime in REGIMES:
        for F in sample(regime):
            R, Q = rotation(rng), rotation(rng)
            psi, P, _ = point(mat, F, False)
            psi_r, P_r, _ = point(mat, R @ F, False)
            assert abs(psi_r - psi) <= 1e-11 * max(abs(psi), mat.mu)
            assert rel(P_r, R @ P) < 1e-11
            psi_q, P_q, _ = point(mat, F @ Q, False)  # isotropy
            assert abs(psi_q - psi) <= 1e-11 * max(abs(psi), mat.mu)
            assert rel(P_q, P @ Q) < 1e-11


@pytest.mark.parametrize("mat", MATERIALS, ids=IDS)
def test_rigid_rotation_is_stress_free(mat):
    rng = np.random.default_rng(5)
    for R in [np.eye(3)] + [rotation(rng) for _ in range(5)]:
        psi, P, _ = point(mat, R, False)
        assert abs(psi) < 1e-10 * mat.mu
        assert np.linalg.norm(P) < 1e-10 * mat.mu


@pytest.mark.parametrize("mat", MATERIALS + OTHER_NU, ids=IDS + OTHER_IDS)
def test_small_strain_tangent_is_linear_elasticity(mat):
    mu, lam = mat.lame()
    d = np.eye(3)
    C = (lam * np.einsum("ij,kl->ijkl", d, d)
         + mu * (np.einsum("ik,jl->ijkl", d, d) + np.einsum("il,jk->ijkl", d, d))).reshape(9, 9)
    for project in (False, True):
        H = point(mat, np.eye(3), True, project)[2]
        assert np.abs(H - C).max() < 1e-10 * (lam + 2 * mu)


# ---------------------------------------------------------------------------------------
# inversion and degenerate input
# ---------------------------------------------------------------------------------------
@pytest.mark.parametrize("mat", MATERIALS, ids=IDS)
def test_inverted_element_is_pushed_towards_uninversion(mat):
    rng = np.random.default_rng(9)
    base = np.diag([1.0, 1.0, -0.5])
    Fs = [base] + [rotation(rng) @ base @ rotation(rng).T for _ in range(4)] + sample("inverted")
    for n, F in enumerate(Fs):
        psi, P, H = point(mat, F)
        assert np.isfinite(psi) and np.all(np.isfinite(P)) and np.all(np.isfinite(H))
        # the inverted (negative) singular value grows under a gradient-descent step F - h P
        U, s, V = signed_svd(F[None])
        assert s[0, 2] < 0 and U[0, :, 2] @ P @ V[0, :, 2] < 0
        # and J grows: always for the volumetric models; for StVK at diag(1, 1, -0.5) rotated
        # (with nu = 0.3; for lam >> mu the clamped StVK's lateral stress lam tr E(s_hat) can
        # make |J| grow through the other two singular values -- see the module docstring)
        if mat.name != "stvk" or n < 5:
            cof = np.linalg.det(F) * np.linalg.inv(F).T
            assert np.sum(P * cof) < 0
            h = 1e-3 * np.linalg.norm(F) / np.linalg.norm(P)
            assert np.linalg.det(F - h * P) > np.linalg.det(F)


@pytest.mark.parametrize("mat", MATERIALS + OTHER_NU, ids=IDS + OTHER_IDS)
def test_compression_barrier(mat):
    """The barrier k/(3 j) (j - J)^3 acts below J = barrier_j only: above it the material is
    bit for bit the bare one; below, it adds exactly dpsi/dJ cof(F) (the numpy reference),
    its energy is continuous at j, and the smallest singular value is pushed back by
    k (j - J)^2 / j * s0 s1 more than without it."""
    rng = np.random.default_rng(21)
    bare = dataclasses.replace(mat, barrier=0.0)
    k, j = mat.barrier * mat.mu, mat.barrier_j
    for svals in ([1.0, 1.0, 0.21], [1.3, 0.9, 0.5], [2.0, 1.0, 0.1001]):       # J >= j
        F = with_singular_values(svals, rng)
        assert np.linalg.det(F) >= j
        for a, b in zip(point(mat, F), point(bare, F)):
            assert np.array_equal(a, b)
    for svals in ([1.67, 1.0, -0.03], [1.0, 1.0, 0.1], [0.5, 0.5, 0.5], [1.0, 1.0, -0.5]):  # J < j
        F = with_singular_values(svals, rng)
        psi, P, _ = point(mat, F)
        psi0, P0, _ = point(bare, F)
        pb, Pb = reference_barrier(F[None], k, j)
        assert pb[0] > 0
        np.testing.assert_allclose(psi - psi0, pb[0], rtol=1e-12)
        np.testing.assert_allclose(P - P0, Pb[0], rtol=1e-10, atol=1e-12 * mat.mu)
        U, s, V = signed_svd(F[None])
        push = U[0, :, 2] @ (P - P0) @ V[0, :, 2]      # along the smallest singular value
        J = np.prod(s[0])
        assert push < 0
        np.testing.assert_allclose(push, -k * (j - J) ** 2 / j * s[0, 0] * s[0, 1], rtol=1e-9)
    F = np.diag([1.0, 1.0, j])
    assert point(mat, F)[0] == point(bare, F)[0]
    Fm = np.diag([1.0, 1.0, j - 1e-6])
    assert abs(point(mat, Fm)[0] - point(bare, Fm)[0]) < 1e-15 * k


def test_barrier_holds_a_flattened_element_the_bare_nu0_models_let_through():
    """A flat element at F = diag(1.67, 1, s) with nu = 0 under a compressive principal
    stress of 4 mu (a 1 kPa cantilever's self-weight at its clamp): without the barrier
    the fixed corotated and StVK stresses stay below 4 mu in magnitude down to s = -0.3, so
    the element can be pushed through; with it, the push back exceeds 4 mu before J = 0."""
    for cls in (StVK, Corotated):
        mat = cls(1e3, 0.0, 1000.0)
        bare = dataclasses.replace(mat, barrier=0.0)

        def push(m, t):
            return -point(m, np.diag([1.67, 1.0, t]), False)[1][2, 2]
        assert all(push(bare, t) < 4 * mat.mu for t in (0.1, 0.0, -0.3))
        assert push(mat, 0.0) > 4 * mat.mu and push(mat, -0.3) > push(mat, 0.0)


@pytest.mark.parametrize("project", [False, True])
@pytest.mark.parametrize("mat", MATERIALS, ids=IDS)
def test_degenerate_input_gives_finite_values(mat, project):
    for F in degenerate_Fs():
        psi, P, H = point(mat, F, True, project)
        assert np.isfinite(psi) and np.all(np.isfinite(P)) and np.all(np.isfinite(H)), F
        if project:
            assert np.array_equal(H, H.T)
            w = np.linalg.eigvalsh(H)
            assert w.min() >= -1e-8 * max(np.abs(w).max(), mat.mu)


@pytest.mark.parametrize("mat", MATERIALS, ids=IDS)
def test_degenerate_stress_is_restoring_where_defined(mat):
    # flattened (det = 0) and fully collapsed elements push outwards along the collapsed axis
    for F in (np.diag([1.0, 1.0, 0.0]), np.diag([1.0, 1.0, 1e-12])):
        P = point(mat, F, False)[1]
        assert P[2, 2] < 0


# ---------------------------------------------------------------------------------------
# PSD projection
# ---------------------------------------------------------------------------------------
def eig_clamp(H):
    w, Q = np.linalg.eigh(0.5 * (H + H.T))
    return (Q * np.maximum(w, 0.0)) @ Q.T


@pytest.mark.parametrize("regime", REGIMES)
@pytest.mark.parametrize("mat", MATERIALS, ids=IDS)
def test_projection_is_psd_and_the_nearest_one(mat, regime):
    bare = dataclasses.replace(mat, barrier=0.0)
    for F in sample(regime):
        H0 = point(bare, F)[2]
        H = point(mat, F)[2]
        for m, ref in ((bare, eig_clamp(H0)),
                       # with the compression barrier (J < barrier_j): material and barrier
                       # parts are projected each on its own, a sum of PSD matrices
                       (mat, eig_clamp(H0) + eig_clamp(H - H0))):
            Hp = point(m, F, True, True)[2]
            assert np.array_equal(Hp, Hp.T)
            w = np.linalg.eigvalsh(Hp)
            assert w.min() >= -1e-8 * np.abs(w).max()
            # identical to clamping the eigenvalues of (the symmetric part of) dPdF
            assert np.linalg.norm(Hp - ref) < 1e-9 * np.linalg.norm(H)


@pytest.mark.parametrize("mat", MATERIALS, ids=IDS)
def test_projection_leaves_psd_matrix_unchanged(mat):
    rng = np.random.default_rng(2)
    n_checked = 0
    for _ in range(10):
        stretch = np.diag(1.0 + rng.uniform(0.005, 0.03, 3))
        F = rotation(rng) @ stretch @ rotation(rng).T
        H = point(mat, F)[2]
        w = np.linalg.eigvalsh(H)
        assert w.min() > 1e-6 * w.max()  # strictly PSD sample
        assert np.array_equal(point(mat, F, True, True)[2], H)
        n_checked += 1
    assert n_checked == 10


@pytest.mark.parametrize("mat", MATERIALS, ids=IDS)
def test_projection_changes_indefinite_matrix(mat):
    # compressive prestress makes the twist modes negative for every model
    F = np.diag([0.7, 0.7, 0.7])
    H = point(mat, F)[2]
    assert np.linalg.eigvalsh(0.5 * (H + H.T)).min() < -1e-3 * mat.mu
    Hp = point(mat, F, True, True)[2]
    assert np.linalg.eigvalsh(Hp).min() >= -1e-8 * mat.mu


# ---------------------------------------------------------------------------------------
# batch API and numpy reference
# ---------------------------------------------------------------------------------------
@pytest.mark.parametrize("mat", MATERIALS, ids=IDS)
def test_batch_matches_numpy_reference_and_point_kernel(mat):
    Fs = np.array([F for r in REGIMES for F in sample(r, n=40, seed=4)])
    psi, P, H = mat.evaluate(Fs)
    rpsi, rP = reference_psi_P(mat, Fs)
    for n in range(len(Fs)):
        assert abs(psi[n] - rpsi[n]) <= 1e-12 * max(abs(rpsi[n]), 1e-3 * mat.mu)
        assert rel(P[n], rP[n]) <= 1e-12
    for n in (0, 45, 90, 130, 199, 239):
        p1, P1, H1 = point(mat, Fs[n])
        assert p1 == psi[n] and np.array_equal(P1, P[n]) and np.array_equal(H1, H[n])
    psi2, P2, H2 = mat.evaluate(Fs, want_hessian=False)
    assert H2 is None and np.array_equal(psi2, psi) and np.array_equal(P2, P)
    _, _, Hp = mat.evaluate(Fs, project=True)
    assert np.array_equal(Hp[7], point(mat, Fs[7], True, True)[2])
    assert mat.evaluate(np.empty((0, 3, 3)))[0].shape == (0,)
    with pytest.raises(ValueError, match="shape"):
        mat.evaluate(np.zeros((4, 3, 2)))
    with pytest.raises(ValueError, match="kind_id"):
        material_point(7, Fs[0], mat.params, np.empty((3, 3)), np.empty((9, 9)), True, False)


@njit(cache=False)
def _njit_caller(kind_id, params, F):
    P = np.empty((3, 3))
    H = np.empty((9, 9))
    return material_point(kind_id, F, params, P, H, True, False), P[0, 0], H[0, 0]


def test_point_kernels_are_callable_from_njit():
    F = np.eye(3) + 0.1 * np.arange(9.0).reshape(3, 3) / 9.0
    for mat in MATERIALS:
        psi, P00, H00 = _njit_caller(mat.kind_id, mat.params, F)
        ref = point(mat, F)
        assert psi == ref[0] and P00 == ref[1][0, 0] and H00 == ref[2][0, 0]


def test_kind_ids_params_and_derived_quantities():
    assert (KIND_STVK, KIND_COROTATED, KIND_NEOHOOKEAN) == (0, 1, 2)
    assert [m.kind_id for m in MATERIALS] == [0, 1, 2]
    for m in MATERIALS:
        assert m.params.dtype == np.float64 and m.params.shape == (5,)
        assert m.params[3] == BARRIER_DEFAULT * m.mu and m.params[4] == BARRIER_J_DEFAULT
        mu, lam = m.lame()
        assert np.isclose(mu, E_ / (2 * (1 + NU_))) and np.isclose(lam, E_ * NU_ / ((1 + NU_) * (1 - 2 * NU_)))
        assert np.isclose(m.wave_speed(), np.sqrt((lam + 2 * mu) / RHO_))
    assert MATERIALS[0].params[2] == S_MIN == 0.5
    with pytest.raises(ValueError, match="poisson"):
        StVK(1e5, 0.5, 1000)
    with pytest.raises(ValueError, match="young"):
        Corotated(-1.0, 0.3, 1000)
    with pytest.raises(ValueError, match="density"):
        NeoHookean(1e5, 0.3, 0.0)
    with pytest.raises(ValueError, match="s_min"):
        StVK(1e5, 0.3, 1000, s_min=0.0)


# ---------------------------------------------------------------------------------------
# make_material
# ---------------------------------------------------------------------------------------
GOOD = {"model": "stvk", "young": 1e5, "poisson": 0.3, "density": 1000}


def test_make_material_builds_each_model():
    for name, cls in (("stvk", StVK), ("corotated", Corotated), ("neohookean", NeoHookean)):
        m = make_material(dict(GOOD, model=name))
        assert type(m) is cls and m.name == name and m.young == 1e5 and m.density == 1000.0
    assert make_material(dict(GOOD, s_min=0.3)).s_min == 0.3
    assert make_material(dict(GOOD, poisson=0)).lam == 0.0
    m = make_material(dict(GOOD, model="corotated", barrier=0, barrier_j=0.1))
    assert m.barrier == 0.0 and m.barrier_j == 0.1 and m.params[3] == 0.0


@pytest.mark.parametrize("change, key", [
    ({"model": "rubber"}, "model"),
    ({"model": None}, "model"),
    ({"young": None}, "young"),
    ({"young": "stiff"}, "young"),
    ({"young": 0.0}, "young"),
    ({"young": -5.0}, "young"),
    ({"poisson": 0.5}, "poisson"),
    ({"poisson": 0.7}, "poisson"),
    ({"poisson": -0.1}, "poisson"),
    ({"density": 0.0}, "density"),
    ({"density": -1.0}, "density"),
    ({"density": None}, "density"),
    ({"youngs": 1e5}, "youngs"),
    ({"s_min": 1.5}, "s_min"),
    ({"barrier": -1.0}, "barrier"),
    ({"barrier": "on"}, "barrier"),
    ({"barrier_j": 0.0}, "barrier_j"),
    ({"barrier_j": 1.0}, "barrier_j"),
])
def test_make_material_errors_name_the_key(change, key):
    spec = dict(GOOD)
    for k, v in change.items():
        if v is None:
            spec.pop(k)
        else:
            spec[k] = v
    with pytest.raises(SceneError) as err:
        make_material(spec)
    assert f"'{key}'" in str(err.value)


def test_make_material_rejects_stvk_only_key_for_other_models():
    with pytest.raises(SceneError, match="s_min"):
        make_material(dict(GOOD, model="neohookean", s_min=0.3))
    with pytest.raises(SceneError, match="mapping"):
        make_material([1, 2])
