"""Closed-form results the solvers are checked against (METHOD.md sections 11-12).

Beams are rectangular, width b (y), height h (z, the bending direction), length L.
"""
import numpy as np

BETA1 = 1.8750104065  # first root of cos(b) cosh(b) = -1 (cantilever)


def rect_section(b, h):
    """Area A and second moment I (bending about y) of a b x h rectangle."""
    return b * h, b * h ** 3 / 12.0


def cowper_shear_factor(nu):
    """Timoshenko shear coefficient of a rectangle (Cowper 1966)."""
    return 10.0 * (1.0 + nu) / (12.0 + 11.0 * nu)


def cantilever_tip_deflection(P, L, E, b, h, nu=None):
    """Tip deflection under a tip load P: P L^3 / (3 E I), plus the Timoshenko shear
    term P L / (kappa G A) when nu is given."""
    A, I = rect_section(b, h)
    w = P * L ** 3 / (3.0 * E * I)
    if nu is not None:
        G = E / (2.0 * (1.0 + nu))
        w += P * L / (cowper_shear_factor(nu) * G * A)
    return w


def cantilever_gravity_sag(rho, g, L, E, b, h, nu=None):
    """Tip deflection under self weight w = rho g A: w L^4 / (8 E I) (+ shear w L^2 / (2 kappa G A))."""
    A, I = rect_section(b, h)
    q = rho * g * A
    d = q * L ** 4 / (8.0 * E * I)
    if nu is not None:
        G = E / (2.0 * (1.0 + nu))
        d += q * L ** 2 / (2.0 * cowper_shear_factor(nu) * G * A)
    return d


def cantilever_first_frequency(L, E, rho, b, h):
    """First bending frequency in Hz: beta1^2 / (2 pi) sqrt(E I / (rho A L^4))."""
    A, I = rect_section(b, h)
    return BETA1 ** 2 / (2.0 * np.pi) * np.sqrt(E * I / (rho * A * L ** 4))


def hertz_force(depth, R, E, nu):
    """Force of a rigid sphere (radius R) pressed depth into a half-space: 4/3 E* sqrt(R) d^1.5."""
    e_star = E / (1.0 - nu ** 2)
    return 4.0 / 3.0 * e_star * np.sqrt(R) * np.power(depth, 1.5)


def hertz_depth(force, R, E, nu):
    """Inverse of hertz_force."""
    e_star = E / (1.0 - nu ** 2)
    return np.power(3.0 * force / (4.0 * e_star * np.sqrt(R)), 2.0 / 3.0)
