"""Mass of linear tetrahedra: lumped (rho V / 4 per vertex) and consistent (rho V / 20 (1 + d_ab))."""
import numpy as np


def lumped_mass(tets, volume, density, n_verts):
    """Per-vertex mass (n_verts,) from tets (n_tets, 4) and rest volumes (n_tets,)."""
    per_vertex = np.repeat(density * volume / 4.0, 4)
    return np.bincount(tets.ravel(), weights=per_vertex, minlength=n_verts)


def consistent_mass_elements(volume, density):
    """Element mass matrices (n_tets, 12, 12): rho V / 20 (1 + d_ab) on each axis."""
    scalar = (np.ones((4, 4)) + np.eye(4)) / 20.0
    block = np.kron(scalar, np.eye(3))                                  # (12, 12), vertex-major
    return (density * volume)[:, None, None] * block[None, :, :]
