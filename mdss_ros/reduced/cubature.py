"""Cubature by greedy non-negative least squares (An, Kim and James 2008; docs/method.md §13).

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


def domain_force_columns(dom, Q, max_candidates=40000, seed=0, chunk=20000):
    """Per-element reduced forces of a subspace domain at poses Q (T, r).

    Returns (A (T r, c), b (T r,), candidates (c,)): columns for at most max_candidates
    elements (a random subset when the domain has more, which keeps memory bounded for
    one-domain models of large meshes), and b the force of ALL elements, accumulated
    in chunks."""
    from .sampled_forces import contributions, sample_jacobians
    fm = dom.forces
    m = len(fm.tets)
    Qc = np.ascontiguousarray(Q)
    cand = np.arange(m) if m <= max_candidates else np.sort(
        np.random.default_rng(seed).choice(m, size=max_candidates, replace=False))
    b = np.zeros(len(Q) * dom.r)
    cols = []
    is_cand = np.zeros(m, dtype=bool)
    is_cand[cand] = True
    for lo in range(0, m, chunk):
        ids = np.arange(lo, min(m, lo + chunk))
        G = sample_jacobians(dom.U3, fm.tets[ids], fm.geom.grads[ids])
        out = np.empty((len(Q), dom.r, len(ids)))
        contributions(G, fm.geom.volume[ids], Qc, fm.material.kind_id, fm.material.params, False, False, out)
        A_chunk = out.reshape(len(Q) * dom.r, len(ids))
        b += A_chunk.sum(axis=1)
        cols.append(A_chunk[:, is_cand[ids]])
    return np.concatenate(cols, axis=1), b, cand


def build_domain_cubature(dom, Q, samples, tolerance=0.0, seed=0, progress=None):
    """Greedy NNLS cubature of one subspace domain on training poses Q (T, r).

    Returns (SampledDomainForces, info) with info holding the training and held-out errors.
    """
    from .sampled_forces import SampledDomainForces
    train, held = split_poses(len(Q), seed=seed)
    A, b, cand = domain_force_columns(dom, Q, seed=seed)
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
                                       cand[cub.elements], cub.weights)
    info["candidates"] = int(len(cand))
    return forces, info


# ---------------------------------------------------------------------- interfaces
#
# A coupling element e of the interface (i, j) contributes, at a pose, to
#   F_i = sum_{l in e, l in i} U_l^T R_i^T f_l      (reduced force on i, r_i)
#   F_j                                              (r_j)
#   f_i = sum_{l in i} f_l,  f_j = -f_i              (forces on the frames)
#   t_i = sum_{l in i} (x_l - O) x f_l,  t_j         (torques about O = (c_i + c_j) / 2)
# Uniform cubature fits one weight per sample to all groups together. Non-uniform keeps
# the samples and fits four weight sets: F_i, F_j, (f_i, f_j) shared and (t_i, t_j)
# shared. Shared weights keep sum f = 0 and sum t(O) = 0, and the torque about each frame
# centre is rebuilt as t_i(c_i) = w_t t_i(O) - (c_i - O) x w_f f_i, so linear and angular
# momentum of the coupling forces are conserved exactly.

INTERFACE_GROUPS = ("F_i", "F_j", "force", "torque")


def interface_features(model, elements, pair, training, poses):
    """Per-element contributions of one interface at the given poses.

    elements (n_g,) global tet ids touching exactly the subspace domains pair = (i, j)
    (subspace indices). Returns a dict group -> array (T, rows, n_g).
    """
    from ..fem.elements import element_forces
    i, j = pair
    tets = model.body.tets[elements]
    geom = model.geom
    sub = geom.subset(elements)
    doms = (model.subspace[i], model.subspace[j])
    slot_dom = model.vertex_domain[tets]                              # (n_g, 4) global domain ids
    out = {g: [] for g in INTERFACE_GROUPS}
    for t in poses:
        x = training.reconstructed(model, t)
        _, f, _ = element_forces(x, tets, sub, model.body.material, want_hessian=False)
        f = f.copy()
        c = training.c[t]
        R = training.R[t]
        O = 0.5 * (c[i] + c[j])
        Fs, fs, ts = [], [], []
        for side, k in enumerate((i, j)):
            dom = doms[side]
            mask = (slot_dom == dom.index)                             # (n_g, 4)
            F = np.zeros((len(elements), dom.r))
            fsum = np.zeros((len(elements), 3))
            tsum = np.zeros((len(elements), 3))
            for a in range(4):
                rows = np.flatnonzero(mask[:, a])
                if rows.size == 0:
                    continue
                loc = model.vertex_local[tets[rows, a]]
                fa = f[rows, a]
                F[rows] += np.einsum("lib,li->lb", dom.U3[loc], fa @ R[k])
                fsum[rows] += fa
                tsum[rows] += np.cross(x[tets[rows, a]] - O, fa)
            Fs.append(F)
            fs.append(fsum)
            ts.append(tsum)
        out["F_i"].append(Fs[0].T)
        out["F_j"].append(Fs[1].T)
        out["force"].append(np.concatenate([fs[0], fs[1]], axis=1).T)
        out["torque"].append(np.concatenate([ts[0], ts[1]], axis=1).T)
    return {g: np.array(v) for g, v in out.items()}


def _stack(features, groups, poses_idx):
    """Normalised (rows, n_g) column matrix and target of the given groups and poses."""
    As, bs = [], []
    for g in groups:
        F = features[g][poses_idx]                      # (T, rows, n_g)
        b = F.sum(axis=2)                               # (T, rows)
        norm = np.linalg.norm(b, axis=1)
        scale = 1.0 / np.maximum(norm, 1e-12 * max(norm.max(), 1e-300))
        As.append((F * scale[:, None, None]).reshape(-1, F.shape[2]))
        bs.append((b * scale[:, None]).reshape(-1))
    return np.concatenate(As), np.concatenate(bs)


def _regularised_nnls(A, b, w_uniform, lam):
    """argmin |A w - b|^2 + lam^2 |w - w_uniform|^2 over w >= 0 (lam = inf: uniform)."""
    if not np.isfinite(lam):
        return w_uniform.copy()
    n = A.shape[1]
    A_aug = np.vstack([A, lam * np.eye(n)])
    b_aug = np.concatenate([b, lam * w_uniform])
    return nnls(A_aug, b_aug, maxiter=50 * n + 100)[0]


def _nonuniform_weights(feats, group, train, elements, w_uniform, seed, folds=4):
    """One group's weights on the uniform samples: NNLS pulled toward the uniform weights
    with a strength chosen by k-fold cross-validation on the training poses (the grid
    includes 'uniform'), so a group refits only where that generalises to unseen poses."""
    A, b = _stack(feats, (group,), train)
    rows = A.shape[0] // len(train)
    A = A[:, elements]
    scale = np.linalg.norm(A) / np.sqrt(max(A.shape[1], 1))
    grid = [0.0, 0.03, 0.1, 0.3, 1.0, np.inf]
    order = np.random.default_rng(seed + 1).permutation(len(train))
    fold_of = np.empty(len(train), dtype=np.int64)
    fold_of[order] = np.arange(len(train)) % folds
    best, best_err = np.inf, np.inf
    if len(train) >= 2 * folds:
        for lam in grid:
            errs = []
            for f in range(folds):
                tr = np.repeat(fold_of != f, rows)
                va = ~tr
                w = _regularised_nnls(A[tr], b[tr], w_uniform, lam * scale)
                errs.append(relative_error(A[va], b[va], rows, np.arange(A.shape[1]), w))
            if np.mean(errs) < best_err - 1e-12:
                best, best_err = lam, float(np.mean(errs))
    return _regularised_nnls(A, b, w_uniform, best * scale)


def build_interface_cubature(model, elements, pair, training, samples, scheme="uniform", seed=0):
    """Samples and weights (s, 4) for one interface; columns of the weights follow
    INTERFACE_GROUPS. Returns (sample tet ids, weights, info)."""
    train, held = split_poses(training.n_poses, seed=seed)
    feats = interface_features(model, elements, pair, training, np.arange(training.n_poses))
    A, b = _stack(feats, INTERFACE_GROUPS, train)
    cub = greedy_nnls(A, b, samples, seed=seed)
    W = np.repeat(cub.weights[:, None], 4, axis=1)
    if scheme == "nonuniform":
        for g, group in enumerate(INTERFACE_GROUPS):
            W[:, g] = _nonuniform_weights(feats, group, train, cub.elements, cub.weights, seed)
    elif scheme != "uniform":
        raise ValueError(f"interface cubature scheme must be uniform or nonuniform, got {scheme!r}")
    info = {"pair": [int(pair[0]), int(pair[1])], "elements": len(elements), "samples": int(cub.n_samples)}
    for name, idx in (("train", train), ("held_out", held)):
        if len(idx) == 0:
            continue
        errs = {}
        for g, group in enumerate(INTERFACE_GROUPS):
            Ag, bg = _stack(feats, (group,), idx)
            rows = Ag.shape[0] // len(idx)
            errs[group] = relative_error(Ag, bg, rows, cub.elements, W[:, g])
        info[f"{name}_error"] = errs
    return elements[cub.elements], W, info
