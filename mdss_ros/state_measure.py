"""What the stability guard reads from a state (mdss_ros/guard.py): positions and
velocities, the energy parts and the number of inverted tets.

It sits below the models so that a model can measure itself in its own coordinates
(ReducedModel.guard_measure) without importing the guard, which sits above the models.
"""
from dataclasses import dataclass

import numpy as np
from numba import njit


@dataclass
class Measure:
    """What the guard reads from a state: x, v (n_verts, 3), energy parts, inverted tets."""

    x: np.ndarray
    v: np.ndarray
    kinetic: float
    elastic: float
    gravity: float
    inverted: int
    finite: bool
    speed: float = None        # largest vertex speed (or a bound); None: from v

    @property
    def total(self):
        return self.kinetic + self.elastic + self.gravity


def inverted_tets(x, tets):
    """Number of tets with det(Ds) <= 0 at positions x (n_verts, 3); tets (n_tets, 4) are
    positively oriented at rest, so this counts inverted (or flat) elements (NaN counts)."""
    return int(_count_inverted(np.ascontiguousarray(x, dtype=np.float64), np.ascontiguousarray(tets, dtype=np.int64)))


@njit(cache=True)
def _count_inverted(x, tets):
    # One pass with no temporaries: this runs after every step of a guarded simulation.
    n = 0
    for e in range(tets.shape[0]):
        a, b, c, d = tets[e, 0], tets[e, 1], tets[e, 2], tets[e, 3]
        e1x, e1y, e1z = x[b, 0] - x[a, 0], x[b, 1] - x[a, 1], x[b, 2] - x[a, 2]
        e2x, e2y, e2z = x[c, 0] - x[a, 0], x[c, 1] - x[a, 1], x[c, 2] - x[a, 2]
        e3x, e3y, e3z = x[d, 0] - x[a, 0], x[d, 1] - x[a, 1], x[d, 2] - x[a, 2]
        det = (e1y * e2z - e1z * e2y) * e3x + (e1z * e2x - e1x * e2z) * e3y + (e1x * e2y - e1y * e2x) * e3z
        if not det > 0.0:
            n += 1
    return n
