"""Verification reports of the multi-domain subspace model (`mdss verify NAME --out DIR`).

Each report runs a study, prints progress and a summary table, and writes
DIR/NAME.json (every number it measured, its configuration and wall time) plus PNG
plots DIR/NAME_*.png:

    energy      paper Fig. 3: energy of an undamped two-domain beam, one-step vs two-step
    coupling    paper Fig. 8: element coupling vs spring coupling vs full-space FEM
    reduced     accuracy and cost vs full-space FEM over domains x modes, block fill (Fig. 4)
    cantilever  full-space FEM vs Euler-Bernoulli + shear and the first bending frequency
    modes       natural frequencies of full and reduced beams vs closed forms and full FEM
    cubature    cubature sample counts vs exact integration
    hertz       sphere pressed into a 2 m block vs Hertz theory: F-d curves, L2 error vs DOFs
                (second paper Fig. 3), fixed-force convergence (Fig. 5), ms per step; full-space
                FEM and the reduced model with a full-space contact zone (hertz_study)

`quick=True` runs a small version of each (the slow-marked tests use it); `overrides`
replaces entries of a study's configuration dict (e.g. {"horizon": 0.2}).

This module holds the helpers the studies share: beam scenes, the reduced static solve,
state transfer between two simulators of one body, the surface error metric, JSON and
table output. The studies live in energy_study, coupling_study, accuracy_study,
cubature_study and hertz_study.
"""
import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

from ..accuracy import surface_error  # noqa: F401  (the reports import it from here)
from ..errors import ReportError  # noqa: F401  (the reports import it from here)
from ..rotations import rotation_angles


# Material of every beam study unless a study says otherwise: a soft StVK rubber
# (the papers' material), 1 m x 0.1 m x 0.1 m, clamped at x = 0.
MATERIAL = {"model": "stvk", "young": 1.0e6, "poisson": 0.3, "density": 1000.0}
BEAM_SIZE = (1.0, 0.1, 0.1)

# Static equilibrium of a reduced model through its own step: backward Euler with a
# time step far above the slowest period (dt^2 K >> Mgen) and Newton iterations per step
# is Newton's method on the static problem with a tiny mass regularisation; the fixed
# point (zero velocity) is exactly the reduced static equilibrium.
STATIC_INTEGRATOR = {"scheme": "one_step", "dt": 10.0, "newton_iterations": 10, "tolerance": 1e-10}


# ---------------------------------------------------------------------- output
class Progress:
    """Timestamped progress lines: `[name   12.3 s] message` (flushed)."""

    def __init__(self, name, stream=None):
        self.name = name
        self.t0 = time.perf_counter()
        self.stream = stream or sys.stdout

    def __call__(self, msg):
        print(f"[{self.name} {self.elapsed():7.1f} s] {msg}", file=self.stream, flush=True)

    def elapsed(self):
        return time.perf_counter() - self.t0


def format_table(headers, rows):
    """Plain-text table; floats as 4 significant digits, other values with str()."""
    def cell(v):
        if isinstance(v, (float, np.floating)):
            return f"{v:.4g}"
        return str(v)
    text = [[cell(v) for v in row] for row in rows]
    widths = [max(len(h), *(len(r[i]) for r in text)) if text else len(h) for i, h in enumerate(headers)]
    line = lambda vals: "  ".join(v.rjust(w) for v, w in zip(vals, widths))    # noqa: E731
    return "\n".join([line(headers), line(["-" * w for w in widths])] + [line(r) for r in text])


def _plain(obj):
    """JSON-ready copy: numpy scalars and arrays to Python, tuple keys to strings."""
    if isinstance(obj, dict):
        return {(k if isinstance(k, str) else str(k)): _plain(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_plain(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _plain(obj.tolist())
    if isinstance(obj, (np.bool_,)):
        return bool(obj)
    if isinstance(obj, np.integer):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        v = float(obj)
        return v if np.isfinite(v) else None
    return obj


def environment():
    """Machine facts a timing depends on (load_average: 1, 5, 15 min, at the call)."""
    return {"python": platform.python_version(), "numpy": np.__version__, "cpus": os.cpu_count(),
            "load_average": list(os.getloadavg()) if hasattr(os, "getloadavg") else None,
            "machine": platform.machine(),
            "threads_env": {k: os.environ.get(k) for k in
                            ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS")}}


def write_json(out, name, data):
    path = Path(out) / f"{name}.json"
    path.write_text(json.dumps(_plain(data), indent=1))
    return path


def study_config(name, base, quick_changes, quick, overrides):
    """base, updated by quick_changes when quick, then by overrides (keys must exist)."""
    unknown = sorted(set(overrides or {}) - set(base))
    if unknown:
        raise ReportError(f"{name}: unknown setting(s) {', '.join(unknown)} (settings: {', '.join(sorted(base))})")
    cfg = dict(base)
    cfg.update(quick_changes if quick else {})
    cfg.update(overrides or {})
    return cfg


# ---------------------------------------------------------------------- scenes
def beam_scene(kind="reduced", size=BEAM_SIZE, cell=0.05, material=MATERIAL, damping=(0.0, 0.0),
               clamped=True, name="verify_beam", **model):
    """Scene dict of a box beam along x, clamped at x = 0 (clamped=True), a `tip` handle on
    the x = size[0] face, no gravity. model: keys of the scene's model section."""
    L = float(size[0])
    return {"name": name,
            "body": {"mesh": {"generator": "box", "size": [float(s) for s in size], "cell": float(cell)},
                     "material": dict(material),
                     "damping": {"alpha": float(damping[0]), "beta": float(damping[1])}},
            "pins": [{"box": [[-1e-3 * L, -1e9, -1e9], [1e-3 * L, 1e9, 1e9]]}] if clamped else [],
            "handles": {"tip": {"box": [[L - 1e-3 * L, -1e9, -1e9], [L + 1e-3 * L, 1e9, 1e9]]}},
            "gravity": [0.0, 0.0, 0.0],
            "model": {"kind": kind, **model}}


def build_sim(scene, log=None, what=""):
    from ..simulator import Simulator
    t0 = time.perf_counter()
    sim = Simulator(scene)
    if log:
        st = sim.stats()
        log(f"built {what or scene['model']['kind']}: {st['vertices']} vertices, {st['tets']} tets, "
            f"{st['dofs']} DOFs, {st['domains']} domain(s) in {time.perf_counter() - t0:.2f} s")
    return sim


# ---------------------------------------------------------------------- statics
def full_static(sim, force, handle="tip", load_steps=(1, 4, 8), accept=1e-6):
    """Static equilibrium of a full-space Simulator under a dead load `force` (3,) on a
    handle (no gravity); the state is set to it.

    statics.static_equilibrium (Newton, Armijo line search on the potential, |r| <= 1e-9
    |f|) is tried with each load-step count in turn until one converges. Its line search
    can stall near the solution at the round-off floor of the potential (seen at residuals
    ~1e-6 with small loads on fine meshes); if no attempt reaches 1e-9, the best one is
    kept when its residual is below `accept` (recorded in the returned info as
    "converged": False, "residual"). Returns info with "load_steps" and "wall_s".
    """
    from ..fem.statics import static_equilibrium
    t0 = time.perf_counter()
    sim.set_wrench(handle, force=force)
    f = sim.external_forces()
    best = None
    for n in load_steps:
        x, info = static_equilibrium(sim.model.force_model, f, load_steps=n)
        info = dict(info, load_steps=n)
        if best is None or info["residual"] < best[1]["residual"]:
            best = (x, info)
        if info["converged"]:
            break
    x, info = best
    if not info["residual"] <= accept:
        raise ReportError(f"full-space static solve did not converge: {info}")
    sim.model.set_state(x, np.zeros_like(x))
    return dict(info, wall_s=time.perf_counter() - t0)


def reduced_static(sim, force, handle="tip", ramp_steps=6, max_steps=80, tol=1e-9):
    """Static equilibrium of a reduced Simulator built with STATIC_INTEGRATOR (see there):
    the load on `handle` ramps linearly over ramp_steps steps, then steps continue until
    the largest vertex increment of a step is below tol * (largest displacement).

    Returns {"steps", "last_increment" (m), "converged", "wall_s"}; raises ReportError
    when max_steps do not converge or the state is not finite.
    """
    t0 = time.perf_counter()
    force = np.asarray(force, dtype=np.float64)
    X = sim.rest_positions()
    prev = sim.vertex_positions().copy()
    inc = np.inf
    for k in range(max_steps):
        sim.set_wrench(handle, force=force * min(1.0, (k + 1) / ramp_steps))
        sim.step()
        x = sim.vertex_positions()
        if not np.all(np.isfinite(x)):
            raise ReportError(f"reduced static solve: non-finite state at step {k + 1}")
        inc = float(np.abs(x - prev).max())
        peak = float(np.linalg.norm(x - X, axis=1).max())
        prev = x.copy()
        if k + 1 >= ramp_steps and inc <= tol * max(peak, 1e-300):
            return {"steps": k + 1, "last_increment": inc, "converged": True,
                    "wall_s": time.perf_counter() - t0}
    raise ReportError(f"reduced static solve: no convergence in {max_steps} steps "
                      f"(last increment {inc:.3g} m)")


def copy_reduced_state(src, dst, at_rest=True):
    """Give reduced Simulator dst the configuration of src (same body and partition:
    scenes that differ only in dt, scheme, damping or coupling), with zero velocities
    when at_rest.

    The reduced coordinates are carried through the displacement they stand for,
    q_dst = U_dst^T M (U_src q_src) per domain (bases are mass-orthonormal), because two
    builds of one scene can return the same span with rotated columns. The copy is checked:
    the vertex positions must agree to 1e-7 of the body size (fails loudly when the two
    spans differ). Returns that largest position difference (m).
    """
    ms, md = src.model, dst.model
    if len(ms.subspace) != len(md.subspace) or any(
            not np.array_equal(a.vertices, b.vertices) for a, b in zip(ms.subspace, md.subspace)):
        raise ReportError("copy_reduced_state: the two models have different domains")
    q, qd = [], []
    for ds, dd, qs, qds in zip(ms.subspace, md.subspace, ms.q, ms.qd):
        m = np.repeat(dd.mass, 3)
        q.append(dd.U.T @ (m * (ds.U @ qs[:ds.r])))
        qd.append(np.zeros(dd.r) if at_rest else dd.U.T @ (m * (ds.U @ qds[:ds.r])))
    md.q, md.qd = md.layout.pad(q), md.layout.pad(qd)
    md.frames = ms.frames.copy()
    if at_rest:
        for a in (md.frames.v, md.frames.w, md.frames.w_prev):
            a[:] = 0.0
    xs, xd = src.vertex_positions(), dst.vertex_positions()
    scale = float(np.ptp(src.rest_positions(), axis=0).max())
    gap = float(np.abs(xs - xd).max())
    if gap > 1e-7 * scale:
        raise ReportError(f"copy_reduced_state: positions differ by {gap:.3g} m after the copy "
                          f"(the two simulators' bases span different spaces)")
    return gap


# ---------------------------------------------------------------------- metrics
def tip_rotation(X_tip, x_tip):
    """Rotation of the tip face: best-fit (polar) rotation of its vertices, as the total
    angle and the bending angle about y (x axis turned towards -z positive), in degrees."""
    A = (x_tip - x_tip.mean(0)).T @ (X_tip - X_tip.mean(0))
    U, _, Vt = np.linalg.svd(A)
    if np.linalg.det(U @ Vt) < 0:
        U[:, -1] *= -1
    R = U @ Vt
    total = np.degrees(rotation_angles(R))
    bend = np.degrees(np.arctan2(-R[2, 0], R[0, 0]))
    return {"total_deg": float(total), "bending_deg": float(bend)}


def median_step_ms(sim, steps, warmup=2):
    """Median wall ms of sim.step() (Simulator's step_ms) over `steps` steps after warm-up,
    and the median of each phase it reports."""
    rows = []
    for k in range(warmup + steps):
        sim.step()
        if k >= warmup:
            rows.append(sim.stats())
    keys = [k for k, v in rows[0].items() if k.endswith("_ms") and isinstance(v, (int, float))]
    return {k: float(np.median([r[k] for r in rows])) for k in keys}
