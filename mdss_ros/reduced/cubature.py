"""Cubature by greedy non-negative least squares (An, Kim and James 2008; METHOD.md section 7).

Given training poses t = 1..T and candidate elements e, the reduced force at pose t is
b_t = sum_e a_{e,t} (every element, weight 1). Cubature keeps a few elements S with
weights w >= 0 so that sum_{e in S} w_e a_{e,t} ~= b_t for all t. Each pose's rows are
divided by |b_t| so every pose counts equally. Greedy: repeatedly add the candidate (from
a random subset) whose column best matches the current residual, refit all weights by
NNLS on the selected columns, stop at the target count or error.
"""
import time
from dataclasses import dataclass

import numpy as np
from scipy.optimize import nnls


@dataclass(frozen=True)
class Cubature:
    """elements (s,) selected candidate ids; weights (s,) >= 0; errors: relative training
    error after each selection (s,); seconds: time spent."""

    elements: np.ndarray
    weights: np.ndarray
    errors: np.ndarray
    seconds: float

    @property
    def n_samples(self):
        return len(self.elements)

    @property
    def error(self):
        return float(self.errors[-1]) if len(self.errors) else 1.0


def normalise_poses(A, b, rows_per_pose):
    """Scale each pose's block of rows of A (T*k, m) and b (T*k,) by 1/|b_t|."""
    T = len(b) // rows_per_pose
    norms = np.linalg.norm(b.reshape(T, rows_per_pose), axis=1)
    scale = np.repeat(1.0 / np.maximum(norms, 1e-300 + 1e-12 * norms.max()), rows_per_pose)
    return A * scale[:, None], b * scale


def greedy_nnls(A, b, max_samples, tolerance=0.0, candidates=256, seed=0, progress=None, always=()):
    """Select columns of A (n_rows, m) and non-negative weights approximating b (n_rows,).

    max_samples: stop after this many; tolerance: stop when |A_S w - b| <= tolerance |b|;
    candidates: size of the random candidate subset examined per selection (all columns
    if larger than m); always: columns included from the start (e.g. elements that must
    stay exact). Returns a Cubature.
    """
    t0 = time.perf_counter()
    rng = np.random.default_rng(seed)
    m = A.shape[1]
    max_samples = min(int(max_samples), m)
    col_norm = np.linalg.norm(A, axis=0)
    usable = col_norm > 0
    chosen = list(dict.fromkeys(int(a) for a in always))
    b_norm = float(np.linalg.norm(b))
    if b_norm == 0.0:
        return Cubature(np.array(chosen, dtype=np.int64), np.ones(len(chosen)), np.zeros(0), 0.0)
    errors = []
    w = np.zeros(0)
    if chosen:
        w, _ = nnls(A[:, chosen], b, maxiter=50 * len(chosen) + 100)
    residual = b - (A[:, chosen] @ w if chosen else 0.0)
    available = usable.copy()
    available[chosen] = False
    while len(chosen) < max_samples and available.any():
        pool = np.flatnonzero(available)
        if len(pool) > candidates:
            pool = rng.choice(pool, size=candidates, replace=False)
        score = (A[:, pool].T @ residual) / col_norm[pool]
        best = int(pool[int(np.argmax(score))])
        if score.max() <= 0:
            # No candidate reduces the residual in a non-negative direction; try the whole set once.
            pool = np.flatnonzero(available)
            score = (A[:, pool].T @ residual) / col_norm[pool]
            if score.max() <= 0:
                break
            best = int(pool[int(np.argmax(score))])
        chosen.append(best)
        available[best] = False
        w, rnorm = nnls(A[:, chosen], b, maxiter=50 * len(chosen) + 100)
        residual = b - A[:, chosen] @ w
        errors.append(rnorm / b_norm)
        if progress and (len(chosen) % 25 == 0 or len(chosen) == max_samples):
            progress(f"{len(chosen)} samples, training error {errors[-1]:.3e}")
        if errors[-1] <= tolerance:
            break
    keep = w > 0
    return Cubature(elements=np.array(chosen, dtype=np.int64)[keep], weights=w[keep],
                    errors=np.array(errors), seconds=time.perf_counter() - t0)


def split_poses(n_poses, held_out_fraction=0.2, seed=0):
    """Indices (train, held_out) of a random split of the training poses."""
    idx = np.random.default_rng(seed).permutation(n_poses)
    n_held = max(1, int(round(held_out_fraction * n_poses))) if n_poses > 1 else 0
    return np.sort(idx[n_held:]), np.sort(idx[:n_held])


def relative_error(A, b, rows_per_pose, elements, weights):
    """Mean over poses of |A_S w - b|_t / |b|_t: the per-pose relative force error."""
    T = len(b) // rows_per_pose
    approx = (A[:, elements] @ weights) if len(elements) else np.zeros_like(b)
    err = np.linalg.norm((approx - b).reshape(T, rows_per_pose), axis=1)
    ref = np.linalg.norm(b.reshape(T, rows_per_pose), axis=1)
    return float(np.mean(err / np.maximum(ref, 1e-300)))


def domain_force_columns(dom, Q):
    """Per-element reduced forces of a subspace domain at poses Q (T, r): A (T r, m), b (T r,)."""
    from .sampled_forces import contributions, sample_jacobians
    fm = dom.forces
    G = sample_jacobians(dom.U3, fm.tets, fm.geom.grads)
    out = np.empty((len(Q), dom.r, len(fm.tets)))
    contributions(G, fm.geom.volume, np.ascontiguousarray(Q), fm.material.kind_id, fm.material.params, out)
    A = out.reshape(len(Q) * dom.r, len(fm.tets))
    return A, A.sum(axis=1)


def build_domain_cubature(dom, Q, samples, tolerance=0.0, seed=0, progress=None):
    """Greedy NNLS cubature of one subspace domain on training poses Q (T, r).

    Returns (SampledDomainForces, info) with info holding the training and held-out errors.
    """
    from .sampled_forces import SampledDomainForces
    train, held = split_poses(len(Q), seed=seed)
    A, b = domain_force_columns(dom, Q)
    rows = dom.r
    sel = (np.repeat(train * rows, rows) + np.tile(np.arange(rows), len(train)))
    A_t, b_t = normalise_poses(A[sel], b[sel], rows)
    cub = greedy_nnls(A_t, b_t, samples, tolerance, seed=seed, progress=progress)
    info = {"samples": cub.n_samples, "elements": len(dom.forces.tets), "train_error": cub.error,
            "seconds": cub.seconds}
    if len(held):
        hsel = (np.repeat(held * rows, rows) + np.tile(np.arange(rows), len(held)))
        info["held_out_error"] = relative_error(A[hsel], b[hsel], rows, cub.elements, cub.weights)
    fm = dom.forces
    forces = SampledDomainForces.build(dom.U3, fm.tets, fm.geom.grads, fm.geom.volume, fm.material,
                                       cub.elements, cub.weights)
    return forces, info
