"""Hyperelastic materials: St. Venant-Kirchhoff (invertible), fixed corotated, stable neo-Hookean.

Conventions
-----------
* ``F`` is the 3x3 deformation gradient. Flattening is row-major:
  ``vec(F)[3*i + j] = F[i, j]``. ``dPdF`` has shape (9, 9) with
  ``dPdF[a, b] = d vec(P)[a] / d vec(F)[b]``.
* ``psi(F)`` is the energy density per unit rest volume, ``P = dpsi/dF`` the first
  Piola-Kirchhoff stress, ``dPdF = d2psi/dF2`` (symmetric wherever psi is smooth).
* Lame parameters: ``mu = E / (2 (1 + nu))``, ``lam = E nu / ((1 + nu)(1 - 2 nu))``.
  ``young`` E > 0, ``poisson`` nu in [0, 0.5), ``density`` > 0 (ValueError naming the
  parameter otherwise; ``make_material`` turns it into a SceneError naming the key).
* Signed SVD ``F = U diag(s) V^T``: U, V proper rotations, ``s0 >= s1 >= |s2|`` and the
  smallest singular value carries the sign when ``det F < 0``.

Materials (``name``, ``kind_id``)
--------------------------------
``stvk`` (0) -- St. Venant-Kirchhoff with the invertible-FEM treatment (Irving et al. 2004,
    Teran et al. 2005). ``E = (F^T F - I)/2``, ``S = lam tr(E) I + 2 mu E``, ``P = F S``,
    ``psi = mu E:E + lam/2 tr(E)^2``. When the smallest signed singular value is
    >= ``s_min`` (in particular det F > 0) the closed form is used, with
    ``dP = dF S + F dS``. Below ``s_min`` (always when det F <= 0) the principal stress is
    evaluated at ``s_hat = max(s, s_min)`` and extrapolated linearly with the rest stiffness
    ``k = 2 mu + lam``: ``g_i = p_i(s_hat) + k min(s_i - s_min, 0)``, ``P = U diag(g) V^T``.
    (A stress held constant below s_min gives no growing restoring force: a 1 kPa StVK
    cantilever under its own weight, stretched 2.2x along its top fibres, had lam tr E make
    the clamped stress tensile and flattened elements through inversion. With the
    extrapolation, as in Irving et al. 2004, the push back grows with the depth of
    compression or inversion.) ``dPdF`` is the exact derivative of that P (isotropic SVD
    formulas, clamped coordinates have ``d s_hat / d s = 0``), which is NOT symmetric: P is
    no longer the gradient of an energy. The reported energy there is
    ``psihat(s_hat) + sum_{i: s_i < s_min} (p_i(s_hat) (s_i - s_min) + k/2 (s_i - s_min)^2)``
    (continuous at ``s_min``; its derivative along a clamped singular value equals the
    force component, so an energy-based line search sees the inversion penalty grow
    with the depth of inversion).

    Default ``s_min = 0.5``. StVK's uniaxial principal stress ``p(s) = (mu + lam/2)(s^3 - s)``
    has its largest compressive magnitude at ``s = 1/sqrt(3) ~ 0.577``, decays to 0 at
    s = 0 and changes sign for s < 0 (the energy has a second minimum at the mirror image),
    so the clamp must sit well above 0 to give a real restoring force. At 0.5 the clamped
    stress is 97 % of that peak (0.375 vs 0.385 (mu + lam/2)), while the model stays exact
    StVK -- variational, symmetric Hessian, usable with energy line searches -- down to 50 %
    compression per axis (the short softening branch 0.5 < s < 0.577 is handled by
    ``project=True``). Lower values (0.2-0.3) keep only 50-70 % of the peak and, through the
    lateral term below, fail to shrink |J| of inverted elements at ordinary nu.

    Inversion behaviour (tested): the clamped principal stress always pushes the inverted
    singular value back towards positive. The clamped ``tr E(s_hat) < 0`` also produces a
    lateral stress ``lam tr E`` that expands the two other axes, which for an inverted
    element makes J more negative. For ``F = diag(1, 1, s2 < 0)`` the gradient step increases
    J iff ``s_min > -2 s2 nu / (1 - nu)``; with the default that is nu < 1/3 at
    diag(1, 1, -0.5) (without the extrapolation; it only adds push back). Under strong
    lateral stretch ``lam tr E`` can make ``p_i(s_hat)`` tensile; the extrapolation then still
    pushes back below ``s_min - p_i(s_hat) / k``. Prefer ``neohookean`` or ``corotated`` when elements invert routinely
    or nu is near 0.5.

``corotated`` (1) -- fixed corotated (Stomakhin et al. 2012):
    ``psi = mu ||F - R||^2 + lam/2 (J - 1)^2`` with ``R = U V^T`` from the signed SVD,
    ``P = 2 mu (F - R) + lam (J - 1) cof(F)``. Smooth (with a symmetric Hessian) except on
    the set ``s_i + s_j = 0`` (e.g. a reflection), where R jumps.

``neohookean`` (2) -- stable neo-Hookean (Smith, de Goes, Kim 2018):
    ``psi = mu'/2 (I_C - 3) + lam'/2 (J - alpha)^2 - mu'/2 log(I_C + 1) - psi0`` with
    ``mu' = 4/3 mu``, ``lam' = lam + 5/6 mu``, ``alpha = 1 + mu/lam'`` (= 1 + 3mu'/(4lam'),
    so P(I) = 0) and the constant ``psi0`` making psi(I) = 0; the tangent at F = I is then
    the linear-elastic tensor of (mu, lam). Closed-form P and dPdF (cofactor Hessian of J).

Compression barrier (every material, on by default): ``psi_b = k/(3 j) (j - J)^3`` for
    ``J < j``, zero above, added to psi (``P_b = dpsi_b/dJ cof(F)``). It is C2 at ``j``, so a
    body never compressed below ``j`` (default 0.2: 80 % of an element's volume gone) behaves
    bit for bit as the bare model. Why: StVK and fixed corotated at nu = 0 have no volume term,
    so the force that un-inverts an element is bounded (about 1.4 mu and 2 mu at J = 0), and
    a load beyond that holds it inverted for good. Measured (stability matrix, 1 kPa
    cantilever at nu = 0, dt 1/30): under its own weight, stretched 1.7x at the clamp, the
    full-space StVK and corotated bodies ended at rest with 9 elements flattened through the
    clamp corner (J = -0.03 to -0.05) and stayed so for 200 steps; with the barrier none is
    left. Physically it stands for densification: no solid loses 80 % of its volume under a
    load of the order of its modulus. ``k = barrier * mu`` with ``barrier`` = 100 by default (push
    back ``k j s0 s1`` = 20 mu s0 s1 at J = 0, growing quadratically with the depth of
    inversion); ``barrier: 0`` turns it off. Scene keys ``barrier``, ``barrier_j``.
    With ``project=True`` the barrier's Hessian is projected on its own and added (a sum of
    PSD matrices).

Numerical treatments (material_kernels.py): the twist eigenvalue ``(p_i + p_j)/(s_i + s_j)``
uses ``max(s_i + s_j, TWIST_DENOM_MIN = 1e-6)`` (finite Hessian at F = 0 or reflections).
``project=True`` returns dPdF with negative eigenvalues set to zero, computed from the
analytic eigensystem in the SVD frame (3x3 block + three flip + three twist eigenvalues);
it is bit-identical to the unprojected matrix when no eigenvalue is below
``-1e-13 max|eig|``; in the StVK clamped region the symmetric part is projected.

API
---
Point kernels (numba, callable from njit code; kernels in ``material_kernels``):
``stvk_point(F, mu, lam, s_min, P_out, dPdF_out, want_hessian, project) -> psi``,
``corotated_point(F, mu, lam, P_out, dPdF_out, want_hessian, project) -> psi``,
``neohookean_point(F, mu, lam, P_out, dPdF_out, want_hessian, project) -> psi``,
``material_point(kind_id, F, params, P_out, dPdF_out, want_hessian, project) -> psi`` with
``params = [mu, lam, s_min, k, j]`` (N_PARAMS = 5; s_min ignored unless StVK; k, j the
compression barrier's, k = 0 turns it off), and the
allocation-free ``*_ws`` variants taking a ``np.empty(WORK_LEN)`` scratch last.
Batch: ``material_batch(kind_id, params, F, psi_out, P_out, dPdF_out, want_hessian, project)``
(parallel) and ``Material.evaluate``.
"""
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np

from ..errors import SceneError

from .material_kernels import (  # noqa: F401  (re-exported API)
    KIND_COROTATED,
    KIND_NEOHOOKEAN,
    KIND_STVK,
    N_PARAMS,
    PSD_TOL,
    STVK_S_MIN_DEFAULT,
    TWIST_DENOM_MIN,
    barrier_terms,
    WORK_LEN,
    corotated_point,
    corotated_point_ws,
    material_batch,
    material_point,
    material_point_ws,
    neohookean_point,
    neohookean_point_ws,
    snh_parameters,
    stvk_point,
    stvk_point_ws,
    svd3_signed,
)

BARRIER_DEFAULT = 100.0    # barrier stiffness k, in units of mu (module docstring)
BARRIER_J_DEFAULT = 0.2    # volume ratio below which the barrier acts

KIND_IDS = {"stvk": KIND_STVK, "corotated": KIND_COROTATED, "neohookean": KIND_NEOHOOKEAN}


def lame_parameters(young, poisson):
    """(mu, lam) from Young's modulus and Poisson's ratio (validated)."""
    young, poisson = _check_elastic(young, poisson)
    mu = young / (2.0 * (1.0 + poisson))
    lam = young * poisson / ((1.0 + poisson) * (1.0 - 2.0 * poisson))
    return mu, lam


def _real(name, value):
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise ValueError(f"{name} must be a number, got {value!r}")
    value = float(value)
    if not math.isfinite(value):
        raise ValueError(f"{name} must be finite, got {value!r}")
    return value


def _check_elastic(young, poisson):
    young = _real("young", young)
    poisson = _real("poisson", poisson)
    if young <= 0.0:
        raise ValueError(f"young must be > 0, got {young!r}")
    if not 0.0 <= poisson < 0.5:
        raise ValueError(f"poisson must be in [0, 0.5), got {poisson!r}")
    return young, poisson


@dataclass(frozen=True)
class _Material:
    young: float
    poisson: float
    density: float
    barrier: float = BARRIER_DEFAULT
    barrier_j: float = BARRIER_J_DEFAULT
    mu: float = field(init=False)
    lam: float = field(init=False)

    name: ClassVar[str] = ""
    kind_id: ClassVar[int] = -1

    def __post_init__(self):
        young, poisson = _check_elastic(self.young, self.poisson)
        density = _real("density", self.density)
        if density <= 0.0:
            raise ValueError(f"density must be > 0, got {density!r}")
        mu, lam = lame_parameters(young, poisson)
        barrier = _real("barrier", self.barrier)
        if barrier < 0.0:
            raise ValueError(f"barrier must be >= 0 (0 turns it off), got {barrier!r}")
        barrier_j = _real("barrier_j", self.barrier_j)
        if not 0.0 < barrier_j < 1.0:
            raise ValueError(f"barrier_j must be in (0, 1), got {barrier_j!r}")
        object.__setattr__(self, "barrier", barrier)
        object.__setattr__(self, "barrier_j", barrier_j)
        object.__setattr__(self, "young", young)
        object.__setattr__(self, "poisson", poisson)
        object.__setattr__(self, "density", density)
        object.__setattr__(self, "mu", mu)
        object.__setattr__(self, "lam", lam)

    @property
    def params(self):
        """float64 (N_PARAMS,) = [mu, lam, s_min or 0, barrier k (Pa), barrier j] for
        material_point / material_batch."""
        return np.array([self.mu, self.lam, getattr(self, "s_min", 0.0), self.barrier * self.mu,
                         self.barrier_j], dtype=np.float64)

    def lame(self):
        """(mu, lam)."""
        return self.mu, self.lam

    def wave_speed(self):
        """P-wave speed sqrt((lam + 2 mu) / density) [m/s] (CFL: dt < h_min / c)."""
        return math.sqrt((self.lam + 2.0 * self.mu) / self.density)

    def evaluate(self, F, want_hessian=True, project=False, out=None):
        """Evaluate m points in parallel.

        F (m, 3, 3) (or (3, 3), treated as m = 1). Returns (psi (m,), P (m, 3, 3),
        dPdF (m, 9, 9) or None). ``out=(psi, P, dPdF)`` reuses preallocated C-contiguous
        float64 arrays (dPdF may be None without hessian).
        """
        F = np.ascontiguousarray(F, dtype=np.float64)
        if F.ndim == 2:
            F = F[None]
        if F.ndim != 3 or F.shape[1:] != (3, 3):
            raise ValueError(f"F must have shape (m, 3, 3), got {F.shape}")
        m = F.shape[0]
        if out is None:
            psi = np.empty(m)
            P = np.empty((m, 3, 3))
            dPdF = np.empty((m, 9, 9)) if want_hessian else None
        else:
            psi, P, dPdF = out
            if want_hessian and (dPdF is None or dPdF.shape != (m, 9, 9)):
                raise ValueError("out: dPdF must have shape (m, 9, 9) when want_hessian")
            if psi.shape != (m,) or P.shape != (m, 3, 3):
                raise ValueError("out: psi and P must have shapes (m,) and (m, 3, 3)")
        dummy = dPdF if want_hessian else np.empty((1, 9, 9))
        if m:
            material_batch(self.kind_id, self.params, F, psi, P, dummy, bool(want_hessian), bool(project))
        return psi, P, (dPdF if want_hessian else None)


@dataclass(frozen=True)
class StVK(_Material):
    """St. Venant-Kirchhoff with the invertible-FEM clamp at ``s_min`` (module docstring)."""

    s_min: float = STVK_S_MIN_DEFAULT

    name: ClassVar[str] = "stvk"
    kind_id: ClassVar[int] = KIND_STVK

    def __post_init__(self):
        super().__post_init__()
        s_min = _real("s_min", self.s_min)
        if not 0.0 < s_min < 1.0:
            raise ValueError(f"s_min must be in (0, 1), got {s_min!r}")
        object.__setattr__(self, "s_min", s_min)


@dataclass(frozen=True)
class Corotated(_Material):
    """Fixed corotated: psi = mu ||F - R||^2 + lam/2 (J - 1)^2."""

    name: ClassVar[str] = "corotated"
    kind_id: ClassVar[int] = KIND_COROTATED


@dataclass(frozen=True)
class NeoHookean(_Material):
    """Stable neo-Hookean (Smith, de Goes, Kim 2018), Lame-matched at F = I."""

    name: ClassVar[str] = "neohookean"
    kind_id: ClassVar[int] = KIND_NEOHOOKEAN


MATERIALS = {cls.name: cls for cls in (StVK, Corotated, NeoHookean)}
_REQUIRED = ("young", "poisson", "density")
_OPTIONAL = {"stvk": ("s_min", "barrier", "barrier_j"), "corotated": ("barrier", "barrier_j"),
             "neohookean": ("barrier", "barrier_j")}


def make_material(spec):
    """Material from a scene dict ``{"model": "stvk"|"corotated"|"neohookean", "young": E,
    "poisson": nu, "density": rho[, "s_min": ...(stvk only)][, "barrier": k / mu (0 = off),
    "barrier_j": j]}``.

    Raises SceneError naming the offending key (unknown model, missing/unknown key,
    non-numeric value, E <= 0, nu outside [0, 0.5), density <= 0, s_min outside (0, 1),
    barrier < 0, barrier_j outside (0, 1)).
    """
    if not isinstance(spec, Mapping):
        raise SceneError(f"material must be a mapping, got {type(spec).__name__}")
    if "model" not in spec:
        raise SceneError(f"missing key 'model' (one of {sorted(MATERIALS)})")
    model = spec["model"]
    if model not in MATERIALS:
        raise SceneError(f"key 'model': unknown model {model!r} (one of {sorted(MATERIALS)})")
    allowed = ("model",) + _REQUIRED + _OPTIONAL[model]
    for key in spec:
        if key not in allowed:
            raise SceneError(f"unknown key {key!r} for model {model!r} (allowed: {', '.join(allowed)})")
    for key in _REQUIRED:
        if key not in spec:
            raise SceneError(f"missing key {key!r}")
    kwargs = {k: spec[k] for k in allowed[1:] if k in spec}
    try:
        return MATERIALS[model](**kwargs)
    except ValueError as err:
        key = str(err).split(" ", 1)[0]
        raise SceneError(f"key {key!r}: {err}") from err


# ---------------------------------------------------------------------------------------
# pure-numpy references (vectorised over m; used by the tests)
# ---------------------------------------------------------------------------------------
def signed_svd(F):
    """numpy signed SVD of (m, 3, 3): U, s, V with det U = det V = +1, s2 signed."""
    U, s, Vt = np.linalg.svd(F)
    V = np.swapaxes(Vt, 1, 2).copy()
    U = U.copy()
    s = s.copy()
    for M in (U, V):
        neg = np.linalg.det(M) < 0
        M[neg, :, 2] *= -1.0
        s[neg, 2] *= -1.0
    return U, s, V


def reference_stvk(F, mu, lam, s_min=STVK_S_MIN_DEFAULT):
    """numpy (psi, P) of StVK with the s_min clamp and its extrapolation, F (m, 3, 3)."""
    F = np.asarray(F, dtype=np.float64)
    eye = np.eye(3)
    C = np.einsum("mki,mkj->mij", F, F)
    E = 0.5 * (C - eye)
    trE = np.trace(E, axis1=1, axis2=2)
    S = lam * trE[:, None, None] * eye + 2.0 * mu * E
    psi = mu * np.einsum("mij,mij->m", E, E) + 0.5 * lam * trE ** 2
    P = F @ S
    U, s, V = signed_svd(F)
    cl = s.min(axis=1) < s_min
    if np.any(cl):
        sh = np.maximum(s[cl], s_min)
        e = 0.5 * (sh ** 2 - 1.0)
        tr = e.sum(axis=1)
        g = (2.0 * mu * e + lam * tr[:, None]) * sh
        depth = np.minimum(s[cl] - s_min, 0.0)               # below the clamp: extrapolated
        k = 2.0 * mu + lam
        psi[cl] = (mu * (e ** 2).sum(axis=1) + 0.5 * lam * tr ** 2
                   + (g * depth + 0.5 * k * depth ** 2).sum(axis=1))
        P[cl] = np.einsum("mik,mk,mjk->mij", U[cl], g + k * depth, V[cl])
    return psi, P


def reference_corotated(F, mu, lam):
    """numpy (psi, P) of the fixed corotated energy, F (m, 3, 3)."""
    F = np.asarray(F, dtype=np.float64)
    U, s, V = signed_svd(F)
    R = U @ np.swapaxes(V, 1, 2)
    J = np.linalg.det(F)
    psi = mu * ((s - 1.0) ** 2).sum(axis=1) + 0.5 * lam * (J - 1.0) ** 2
    P = 2.0 * mu * (F - R) + (lam * (J - 1.0))[:, None, None] * _cofactor(F)
    return psi, P


def reference_neohookean(F, mu, lam):
    """numpy (psi, P) of the stable neo-Hookean energy, F (m, 3, 3)."""
    F = np.asarray(F, dtype=np.float64)
    mup, lamp, alpha, psi0 = snh_parameters.py_func(mu, lam)
    Ic = np.einsum("mij,mij->m", F, F)
    J = np.linalg.det(F)
    psi = 0.5 * mup * (Ic - 3.0) + 0.5 * lamp * (J - alpha) ** 2 - 0.5 * mup * np.log(Ic + 1.0) - psi0
    P = (mup * (1.0 - 1.0 / (Ic + 1.0)))[:, None, None] * F + (lamp * (J - alpha))[:, None, None] * _cofactor(F)
    return psi, P


def reference_barrier(F, k, jb):
    """numpy (psi, P) of the compression barrier k/(3 jb) (jb - J)^3 [J < jb], F (m, 3, 3)."""
    F = np.asarray(F, dtype=np.float64)
    d = np.maximum(jb - np.linalg.det(F), 0.0) if k > 0.0 else np.zeros(len(F))
    return k * d ** 3 / (3.0 * jb), (-k * d ** 2 / jb)[:, None, None] * _cofactor(F)


def reference_psi_P(material, F):
    """numpy (psi, P) of any material instance (its compression barrier included)."""
    if material.name == "stvk":
        psi, P = reference_stvk(F, material.mu, material.lam, material.s_min)
    elif material.name == "corotated":
        psi, P = reference_corotated(F, material.mu, material.lam)
    else:
        psi, P = reference_neohookean(F, material.mu, material.lam)
    pb, Pb = reference_barrier(F, material.barrier * material.mu, material.barrier_j)
    return psi + pb, P + Pb


def _cofactor(F):
    C = np.empty_like(F)
    for i in range(3):
        a, b = (i + 1) % 3, (i + 2) % 3
        C[:, i, :] = np.cross(F[:, a, :], F[:, b, :])
    return C
