"""How far a run is from a ground truth: play a scene's timeline on a Simulator, probe it,
and measure surface, tip and energy errors against a full-space record of the same inputs.

`mdss tradeoff` (verify/tradeoff.py) measures every configuration this way, and budget
mode (mdss_ros/budget.py) probes its candidates with the same functions, so a budget's
"2 % error" means what the trade-off report means by it.

Errors are relative to the reference's largest surface displacement:
rms_rel = sqrt(mean over probes and surface vertices |x - x_ref|^2) / max |x_ref - X|.
"""
import time

import numpy as np

from .errors import ReportError
from .scene import load_scene
from .simulator import Simulator
from .timeline import TimelinePlayer


def dt_label(dt):
    inv = 1.0 / dt
    return f"1/{inv:.0f}" if abs(inv - round(inv)) < 1e-6 else f"{dt:.4g}"


def surface_error(sim, x_ref):
    """RMS over surface vertices of |x - x_ref|, relative to the largest surface
    displacement of the reference: sqrt(mean_s |x_s - xref_s|^2) / max_s |xref_s - X_s|.
    Also returns the max error (same scale) and the peak reference displacement (m)."""
    ids = sim.body.surface.vertex_ids
    X = sim.rest_positions()[ids]
    ref = np.asarray(x_ref)[ids]
    err = np.linalg.norm(sim.surface_positions() - ref, axis=1)
    peak = float(np.linalg.norm(ref - X, axis=1).max())
    return {"rms_rel": float(np.sqrt((err ** 2).mean()) / peak), "max_rel": float(err.max() / peak),
            "peak_displacement": peak}


def probe_steps(dt, horizon, every):
    """Step indices (k,) at which a run of step dt is probed: the steps nearest to
    every, 2 every, ... <= horizon (no probe at t = 0)."""
    n = int(round(horizon / dt))
    times = every * np.arange(1, int(np.floor(horizon / every + 1e-9)) + 1)
    return np.unique(np.clip(np.rint(times / dt).astype(np.int64), 1, n))


def tip_vertices(sim):
    """Vertex ids whose mean position is the 'tip': the scene's first handle, or None."""
    handles = sim.body.handles
    if handles:
        return np.asarray(handles[next(iter(handles))], dtype=np.int64)
    return None


def play(sim, horizon, every, warmup, truth=None, truth_scene_dt=None, log=None):
    """Play the scene's timeline on sim for `horizon` s; probe every `every` s.

    Without truth: returns the record a comparison needs (probe times, vertex positions
    (p, n, 3), energies, tip positions). With truth (a record of the same dt): returns the
    metrics (see the module docstring). Either way with ms/step median and the step count.
    Raises ReportError on a non-finite state."""
    player = TimelinePlayer(sim.scene["timeline"])
    n = int(round(horizon / sim.dt))
    steps = set(probe_steps(sim.dt, horizon, every).tolist())
    ms = np.empty(n)
    rec = {"t": [0.0], "energy": [sim.energy()["total"]], "x": [], "errors": [], "errors_scene_dt": [],
           "newton": np.zeros(n, dtype=np.int64), "unconverged": 0}
    ids = tip_vertices(sim) if truth is None else truth["tip_ids"]
    tip_of = (lambda x: x[ids].mean(0)) if ids is not None else None
    rec["tip"] = [tip_of(sim.vertex_positions()) if tip_of else None]
    report_every = max(1, n // 4)
    for k in range(1, n + 1):
        player.apply_due(sim)
        sim.step()
        st = sim.stats()
        ms[k - 1] = st["step_ms"]
        rec["newton"][k - 1] = st.get("newton_iterations", 0)
        rec["unconverged"] += int(st.get("converged") is False)
        if k not in steps:
            continue
        x = sim.vertex_positions()
        if not np.all(np.isfinite(x)):
            raise ReportError(f"non-finite state at t = {sim.time:.4f} s (step {k})")
        rec["t"].append(sim.time)
        rec["energy"].append(sim.energy()["total"])
        if tip_of:
            rec["tip"].append(tip_of(x))
        if truth is None:
            rec["x"].append(x.copy())
        else:
            rec["errors"].append(probe_error(sim, truth, sim.time))
            if truth_scene_dt is not None:
                rec["errors_scene_dt"].append(probe_error(sim, truth_scene_dt, sim.time))
        if log and k % report_every == 0:
            log(f"    step {k}/{n} (t = {sim.time:.3f} s)")
    rec["step_ms"] = float(np.median(ms[min(warmup, n - 1):]))
    rec["steps"] = n
    return rec


def probe_error(sim, truth, t):
    """Surface error of sim against truth's probe at time t, or None if truth has none there."""
    j = np.flatnonzero(np.abs(np.asarray(truth["t"][1:]) - t) <= 1e-9 * max(1.0, t))
    if len(j) == 0 or truth["peak"][j[0]] <= 0.0:
        return None      # no probe at this time, or the truth at rest (nothing to compare relative to)
    se = surface_error(sim, truth["x"][j[0]])
    return {"j": int(j[0]), "rms_abs": se["rms_rel"] * se["peak_displacement"],
            "max_abs": se["max_rel"] * se["peak_displacement"]}


def truth_record(rec, sim, free_from):
    """Finish a ground-truth record: peak surface displacement per probe, the tip ids, the
    energy range and the probe where the input-free stretch starts."""
    ids = sim.body.surface.vertex_ids
    X = sim.rest_positions()
    x = np.asarray(rec["x"])                                              # (p, n, 3)
    rec["peak"] = np.linalg.norm(x[:, ids] - X[ids][None], axis=2).max(axis=1)
    tip_ids = tip_vertices(sim)
    if tip_ids is None:                   # the surface vertex the truth moves most
        p = int(np.argmax(rec["peak"]))
        tip_ids = np.array([ids[np.argmax(np.linalg.norm(x[p, ids] - X[ids], axis=1))]])
        rec["tip"] = [X[tip_ids].mean(0)] + [xi[tip_ids].mean(0) for xi in x]
    rec["tip_ids"] = tip_ids
    rec["tip_rest"] = X[tip_ids].mean(0)
    E = np.asarray(rec["energy"])
    rec["energy_range"] = float(E.max() - E.min())
    rec["free_from"] = int(np.searchsorted(np.asarray(rec["t"]), free_from - 1e-9))
    return rec


def metrics(rec, truth, key="errors"):
    """Aggregate a run's probe errors against truth (see the module docstring)."""
    errs = [e for e in rec[key] if e is not None]
    if not errs:
        return {}
    peak = float(truth["peak"].max())
    out = {"rms_rel": float(np.sqrt(np.mean([e["rms_abs"] ** 2 for e in errs]))) / peak,
           "max_rel": max(e["max_abs"] for e in errs) / peak, "probes": len(errs)}
    if key != "errors":
        return out
    t_ref = np.asarray(truth["t"])
    t = np.asarray(rec["t"])
    if len(t) == len(t_ref) and np.allclose(t, t_ref, atol=1e-9):
        tip = np.asarray(rec["tip"])
        tip_ref = np.asarray(truth["tip"])
        scale = float(np.linalg.norm(tip_ref - truth["tip_rest"], axis=1).max())
        out["tip_rel"] = float(np.linalg.norm(tip - tip_ref, axis=1).max()) / scale
        E, E_ref = np.asarray(rec["energy"]), np.asarray(truth["energy"])
        rng = truth["energy_range"]
        out["energy_rel"] = float(np.abs(E - E_ref).max()) / rng
        f = truth["free_from"]
        if f < len(E) - 1:
            out["energy_drift"] = float((E[-1] - E[f]) - (E_ref[-1] - E_ref[f])) / rng
            out["free_phase_s"] = float(t_ref[-1] - t_ref[f])
    return out


def ground_truth(scene_src, base_overrides, dt, cfg, log, cache=None):
    """The full-space record at step dt: Newton iterated to truth_tolerance every step.
    cache: the PrecomputeCache the compared runs use. A surface-file body is tetrahedralised
    once per cache (fTetWild differs run to run), so the truth must read the same one."""
    ov = dict(base_overrides, **{"model.kind": "full", "model.element": cfg.get("truth_element", "linear"),
                                 "model.integrator.dt": float(dt),
                                 "model.integrator.newton_iterations": int(cfg["truth_newton_iterations"]),
                                 "model.integrator.tolerance": float(cfg["truth_tolerance"])})
    scene = load_scene(scene_src, ov)
    sim = Simulator(scene, cache=cache)
    log(f"ground truth at dt = {dt_label(dt)}: full space ({ov['model.element']} tets), {sim.stats()['dofs']} DOFs, Newton to "
        f"{cfg['truth_tolerance']:g} (at most {cfg['truth_newton_iterations']} iterations), "
        f"{cfg['horizon']:.3g} s of the timeline")
    t0 = time.perf_counter()
    rec = play(sim, cfg["horizon"], cfg["probe_every"], cfg["warmup"], log=log)
    events = [float(e["t"]) for e in scene["timeline"] if float(e["t"]) <= cfg["horizon"]]
    rec = truth_record(rec, sim, max(events) if events else 0.0)
    rec["newton_iterations_mean"] = float(rec["newton"].mean())
    rec["newton_iterations_max"] = int(rec["newton"].max())
    rec["wall_s"] = time.perf_counter() - t0
    rec["dofs"] = int(sim.stats()["dofs"])
    log(f"  ground truth: {rec['steps']} steps, Newton iterations mean {rec['newton_iterations_mean']:.2f} "
        f"(max {rec['newton_iterations_max']}; {rec['unconverged']} steps not converged), peak surface displacement {rec['peak'].max():.4g} m, "
        f"{rec['step_ms']:.1f} ms/step [{rec['wall_s']:.1f} s]")
    return rec
