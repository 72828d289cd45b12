"""Training poses for cubature (docs/method.md §13.2).

A simulation drives the body with random forces on each domain (a patch of the domain's
surface, new direction and magnitude every `hold` steps) and keeps a snapshot of all vertex
positions every `stride` steps. Each snapshot is then expressed per domain in its best-fit
frame (mass centre and the rotation of the polar decomposition of sum m (x - c) r^T) with
reduced coordinates q = U^T M (R^T (x - c) - r), U being mass-orthonormal.

source "full" runs the full-space FEM (invertible materials), as the method prescribes;
source "reduced" runs the multi-domain model with exact forces, which costs a fraction of a
full-space step on large meshes and yields exactly the poses the subspace can reach.
"auto" picks full up to `full_limit` tets.
"""
import time
from dataclasses import dataclass

import numpy as np

from ..loads import wrench_to_vertex_forces


@dataclass(frozen=True)
class TrainingSet:
    """positions (T, n_verts, 3) world snapshots; q: per subspace domain (T, r_k);
    c (T, d_sub, 3), R (T, d_sub, 3, 3) best-fit frames; source; seconds."""

    positions: np.ndarray
    q: list
    c: np.ndarray
    R: np.ndarray
    source: str
    seconds: float

    @property
    def n_poses(self):
        return len(self.positions)

    def reconstructed(self, model, t):
        """World positions at pose t as the reduced model represents them: (n_verts, 3)."""
        x = self.positions[t].copy()
        for k, dom in enumerate(model.subspace):
            p = dom.local_positions(self.q[k][t])
            x[dom.vertices] = self.c[t, k] + p @ self.R[t, k].T
        return x


def best_fit_frames(model, x, iterations=1):
    """Per subspace domain: (c (3,), R (3, 3), q (r,)) fitting positions x (n_verts, 3).

    The frame is the mass-weighted best rigid fit (c the mass centre: the modes carry no
    mass moment), q the mass-orthogonal projection of what is left. With iterations > 1 the
    rotation is refitted to the deformed shape r + U q and q projected again, alternately
    (the least-squares fit of frame and modes together; peers_limbed.subspace_fit)."""
    out = []
    for dom in model.subspace:
        xs, q = x[dom.vertices], None
        for _ in range(iterations):
            p = dom.r_local if q is None else dom.local_positions(q)
            if dom.movable:
                c = (dom.mass[:, None] * xs).sum(0) / dom.total_mass
                A = ((xs - c) * dom.mass[:, None]).T @ p
                U, _, Vt = np.linalg.svd(A)
                R = U @ Vt
                if np.linalg.det(R) < 0:
                    U[:, -1] *= -1
                    R = U @ Vt
            else:
                c, R = dom.cbar, np.eye(3)
            u = (xs - c) @ R - dom.r_local
            q = dom.U.T @ (np.repeat(dom.mass, 3) * u.reshape(-1))
        out.append((c, R, q))
    return out


def random_patch_forces(rng, model, surface_ids, scale):
    """Per-vertex forces (n_verts, 3): on each domain a patch around a random surface vertex
    pushed in a random direction with a magnitude of scale x the domain's weight."""
    X = model.body.vertices
    f = np.zeros_like(X)
    for dom in model.subspace + model.full:
        ids = np.intersect1d(dom.vertices, surface_ids)
        if ids.size == 0:
            continue
        centre = X[rng.choice(ids)]
        extent = np.linalg.norm(X[dom.vertices].max(0) - X[dom.vertices].min(0))
        patch = ids[np.linalg.norm(X[ids] - centre, axis=1) <= 0.25 * extent]
        direction = rng.normal(size=3)
        direction /= np.linalg.norm(direction)
        weight = model.vertex_mass[dom.vertices].sum() * 9.81
        magnitude = scale * weight * rng.uniform(0.5, 1.5)
        f[patch] += wrench_to_vertex_forces(X[patch], model.vertex_mass[patch], magnitude * direction, np.zeros(3))
    return f


def generate_training(model, n_poses=60, stride=3, hold=15, force_scale=1.0, source="auto",
                      full_limit=60000, seed=0, alpha=0.5, progress=None, reduced_simulation=None):
    """Run a training simulation and return a TrainingSet (see the module docstring).

    model provides the body, its domains and dt. reduced_simulation(alpha) -> (step(f),
    positions()) is the reduced source: a simulation from rest with exact forces, mass
    damping alpha and one Newton iteration (ReducedModel.training_simulation); the
    training never changes the model's settings itself."""
    from ..fem.full_model import FullSpaceModel
    t0 = time.perf_counter()
    say = progress or (lambda msg: None)
    body = model.body
    if source == "auto":
        source = "full" if len(body.tets) <= full_limit else "reduced"
    if source not in ("full", "reduced"):
        raise ValueError(f"training source must be full, reduced or auto, got {source!r}")
    rng = np.random.default_rng(seed)
    surface_ids = body.surface.vertex_ids
    if source == "full":
        # projection_memory off: the policy the cached models were trained with (the exact
        # tangent first in every step), so their poses and cubature stay as they were.
        sim = FullSpaceModel(body, model.dt, {"newton_iterations": 1, "tolerance": 1e-6, "line_search": False,
                                              "projection": "auto", "projection_memory": False},
                             {"alpha": alpha, "beta": model.beta})
        advance, positions_now = (lambda f: sim.step(f, None)), sim.vertex_positions
    else:
        if reduced_simulation is None:
            raise ValueError("training source 'reduced' needs reduced_simulation (a step function)")
        advance, positions_now = reduced_simulation(alpha)
    snaps = []
    n_steps = n_poses * stride
    f = np.zeros_like(body.vertices)
    for step in range(n_steps):
        if step % hold == 0:
            f = random_patch_forces(rng, model, surface_ids, force_scale)
        advance(f)
        if (step + 1) % stride == 0:
            x = positions_now()
            if not np.all(np.isfinite(x)):
                raise RuntimeError(f"training simulation ({source}) produced non-finite positions at step {step + 1}")
            snaps.append(x.copy())
        if (step + 1) % max(1, n_steps // 5) == 0:
            say(f"training ({source}): {step + 1}/{n_steps} steps, {len(snaps)} poses")
    positions = np.array(snaps)
    fits = [best_fit_frames(model, x) for x in positions]
    d = len(model.subspace)
    q = [np.array([fits[t][k][2] for t in range(len(fits))]) for k in range(d)]
    c = np.array([[fits[t][k][0] for k in range(d)] for t in range(len(fits))]).reshape(len(fits), d, 3)
    R = np.array([[fits[t][k][1] for k in range(d)] for t in range(len(fits))]).reshape(len(fits), d, 3, 3)
    return TrainingSet(positions=positions, q=q, c=c, R=R, source=source, seconds=time.perf_counter() - t0)
