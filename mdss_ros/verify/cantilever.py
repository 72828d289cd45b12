"""Cantilever studies of the full-space solver: static tip deflection and first
bending frequency from a free vibration, against the closed forms."""
import numpy as np

from ..fem.backward_euler import BackwardEuler, NewtonSettings
from ..fem.force_model import FEMForceModel
from ..fem.materials import make_material
from ..fem.statics import static_equilibrium
from ..loads import wrench_to_vertex_forces
from ..mesh import box, select_vertices
from ..mesh.generators import tensor_grid
from .closed_forms import cantilever_first_frequency, cantilever_tip_deflection

BEAM = {"L": 1.0, "b": 0.1, "h": 0.1, "E": 1e6, "nu": 0.3, "rho": 1000.0}


def beam_mesh(cell, beam=BEAM):
    """Beam mesh; cell is a cube size (float) or divisions (nx, ny, nz) along L, b, h.

    Linear tets lock in bending, and the error is driven by the divisions along the
    length and through the height, so anisotropic cells (e.g. 200 x 4 x 20) reach the
    closed form with far fewer tets than cubes do.
    """
    if np.ndim(cell) == 0:
        return box(size=(beam["L"], beam["b"], beam["h"]), cell=cell)
    nx, ny, nz = (int(n) for n in cell)
    return tensor_grid(np.linspace(0, beam["L"], nx + 1), np.linspace(0, beam["b"], ny + 1),
                       np.linspace(0, beam["h"], nz + 1))


def beam_model(cell, kind="stvk", beam=BEAM, mass="lumped"):
    """Clamped (x = 0) beam; returns the force model and the tip vertex ids."""
    mesh = beam_mesh(cell, beam)
    pinned = select_vertices(mesh.vertices, {"box": [[-1e-9, -1, -1], [1e-9, 1, 1]]})
    tip = select_vertices(mesh.vertices, {"box": [[beam["L"] - 1e-9, -1, -1], [beam["L"] + 1e-9, 1, 1]]})
    mat = make_material({"model": kind, "young": beam["E"], "poisson": beam["nu"], "density": beam["rho"]})
    return FEMForceModel(mesh.vertices, mesh.tets, mat, pinned, mass=mass), tip


def tip_load_forces(model, tip, P):
    f = np.zeros_like(model.X)
    f[tip] = wrench_to_vertex_forces(model.X[tip], model.vertex_mass[tip], [0.0, 0.0, -P], [0.0, 0.0, 0.0])
    return f


def static_tip_deflection(cell, P=0.01, kind="stvk", beam=BEAM):
    """(measured, closed form with shear) tip deflection under a small tip load P."""
    model, tip = beam_model(cell, kind, beam)
    x, info = static_equilibrium(model, tip_load_forces(model, tip, P))
    measured = -float((x[tip, 2] - model.X[tip, 2]).mean())
    return measured, cantilever_tip_deflection(P, beam["L"], beam["E"], beam["b"], beam["h"], beam["nu"])


def free_vibration_frequency(cell, kind="stvk", beam=BEAM, periods=3.0, steps_per_period=100, P=0.01):
    """(measured, closed form) first bending frequency in Hz.

    The beam is released from its static deflection under a small tip load and
    integrated with backward Euler (dt = T/steps_per_period of the closed-form
    period, so the integrator's period error is ~ (2 pi / steps)^2 / 3); the frequency
    is read off the upward zero crossings of the tip displacement.
    """
    f_ref = cantilever_first_frequency(beam["L"], beam["E"], beam["rho"], beam["b"], beam["h"])
    model, tip = beam_model(cell, kind, beam)
    x, _ = static_equilibrium(model, tip_load_forces(model, tip, P))
    dt = 1.0 / (f_ref * steps_per_period)
    be = BackwardEuler(model, dt, NewtonSettings(max_iterations=1))
    v = np.zeros_like(x)
    zero = np.zeros_like(x)
    n = int(periods * steps_per_period)
    w = np.empty(n + 1)
    w[0] = (x[tip, 2] - model.X[tip, 2]).mean()
    for k in range(n):
        x, v = be.step(x, v, zero)
        w[k + 1] = (x[tip, 2] - model.X[tip, 2]).mean()
    t = dt * np.arange(n + 1)
    up = np.flatnonzero((w[:-1] < 0) & (w[1:] >= 0))
    crossings = t[up] - w[up] * dt / (w[up + 1] - w[up])   # linear interpolation
    if len(crossings) < 2:
        raise RuntimeError("fewer than two zero crossings: increase periods")
    return 1.0 / float(np.mean(np.diff(crossings))), f_ref
