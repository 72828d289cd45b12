"""Static equilibrium f_int(x) = f_ext by Newton with a line search on the potential.

Potential Pi(x) = E(x) - f_ext . x; each Newton step solves K dx = f_ext - f_int
on the free DOFs (PSD-projected K when K is indefinite). Used for closed-form checks
(cantilever deflection, gravity sag, Hertz indentation) and as a ground truth.
"""
import numpy as np

from ..linear_solver import NotPositiveDefinite, SparseSolver


def static_equilibrium(model, f_ext, x0=None, tol=1e-9, max_iterations=50, solver="auto", load_steps=1):
    """Solve for x (n_verts, 3) with pinned vertices at x0 (default: rest).

    model: FEMForceModel; f_ext (n_verts, 3); tol on |r| relative to |f_ext| (free DOFs).
    load_steps > 1 ramps the load, which helps large deformations.
    Returns (x, info) with info = {"iterations", "residual", "converged"}.
    """
    x = (model.X if x0 is None else np.asarray(x0, dtype=np.float64)).copy()
    lin = SparseSolver(solver)
    total_iters = 0
    res = np.inf
    for s in range(1, load_steps + 1):
        f = f_ext * (s / load_steps)
        f_free = model.free(f)
        scale = max(float(np.linalg.norm(f_free)), 1e-300)
        for _ in range(max_iterations):
            e, f_int, K_data = model.tangent(x)
            r = f_free - model.free(f_int)
            res = float(np.linalg.norm(r)) / scale
            if res <= tol:
                break
            try:
                lin.factor(model.pattern.matrix(K_data))
            except NotPositiveDefinite:
                _, _, K_data = model.tangent(x, project=True)
                lin.factor(model.pattern.matrix(K_data) + 1e-12 * scale * model.M)
            dx = model.expand(lin.solve(r))
            pi0 = e - float((f * x).sum())
            step = 1.0
            slope = -float(r @ model.free(dx))
            while step > 1e-6:
                xt = x + step * dx
                if model.energy(xt) - float((f * xt).sum()) <= pi0 + 1e-4 * step * slope:
                    break
                step *= 0.5
            x = x + step * dx
            total_iters += 1
    return x, {"iterations": total_iters, "residual": res, "converged": res <= tol}


def ramped_equilibrium(model, f_ext, ladder, accept, tol=1e-9, max_iterations=30):
    """static_equilibrium with the load ramped over the first load-step count of `ladder`
    whose residual gets within accept (large deformations need the ramp), else the one
    with the smallest residual. Returns (x (n_verts, 3), info) with info["load_steps"]."""
    best = None
    for steps in ladder:
        x, info = static_equilibrium(model, f_ext, tol=tol, max_iterations=max_iterations, load_steps=steps)
        info["load_steps"] = steps
        if best is None or info["residual"] < best[1]["residual"]:
            best = (x, info)
        if info["residual"] <= accept:
            break
    return best
