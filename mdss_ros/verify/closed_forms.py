"""Closed-form results the solvers are checked against (docs/method.md §16).

Beams are rectangular, width b (y), height h (z, the bending direction), length L.
"""
import numpy as np

BETA1 = 1.8751040687  # first root of cos(b) cosh(b) = -1 (cantilever)


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


def torsion_constant(b, h):
    """Saint-Venant torsion constant J of a b x h rectangle (Roark's series fit, < 1 %)."""
    a, c = max(b, h), min(b, h)
    return a * c ** 3 * (1.0 / 3.0 - 0.21 * (c / a) * (1.0 - c ** 4 / (12.0 * a ** 4)))


def cantilever_frequencies(L, E, nu, rho, b, h, count=6):
    """The lowest `count` natural frequencies (Hz) of a clamped-free rectangular beam with
    their kinds, [(label, f)] ascending: Euler-Bernoulli bending about both axes (no shear
    or rotary inertia, so from the second bending mode on a thick beam sits a few percent
    lower), Saint-Venant torsion (warping at the clamp ignored) and axial modes."""
    A = b * h
    G = E / (2.0 * (1.0 + nu))
    betas = [1.8751040687, 4.6940911330, 7.8547574382, 10.9955407349]
    out = []
    for n, beta in enumerate(betas, start=1):
        for axis, I in (("z", b * h ** 3 / 12.0), ("y", h * b ** 3 / 12.0)):
            out.append((f"bending {n} ({axis})", beta ** 2 / (2.0 * np.pi) * np.sqrt(E * I / (rho * A * L ** 4))))
    Ip = (b * h ** 3 + h * b ** 3) / 12.0
    for n in (1, 2, 3):
        out.append((f"torsion {n}", (2 * n - 1) / (4.0 * L) * np.sqrt(G * torsion_constant(b, h) / (rho * Ip))))
        out.append((f"axial {n}", (2 * n - 1) / (4.0 * L) * np.sqrt(E / rho)))
    out.sort(key=lambda lf: lf[1])
    return out[:count]
