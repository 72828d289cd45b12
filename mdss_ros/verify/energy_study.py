"""Energy of an undamped two-domain beam: one-step vs two-step integration (paper Fig. 3).

Setup: a beam clamped at x = 0, two domains (the clamped one has modes only, the other a
rigid frame plus modes), no gravity, no Rayleigh damping. Initial deformation: the static
equilibrium of the reduced model under a tip load (reduced_reports.reduced_static); the
load is then removed and the beam released from rest. The total energy (kinetic +
elastic; gravity is off) is recorded for `horizon` seconds with each scheme and time
step, from one initial state (copied into every run: positions agree to 1e-7 m or better,
reduced_reports.copy_reduced_state; the copy gap is recorded per run).

Both schemes are backward Euler with one linearisation per step, so both lose energy as
dt grows; the paper's point is that the two-step scheme (rigid DOFs first with the
deformation frozen, then deformation with the frames frozen: block Gauss-Seidel) loses
more than the one-step unified solve.
"""
import time
from pathlib import Path

import numpy as np

from .reduced_reports import (MATERIAL, STATIC_INTEGRATOR, Progress, ReportError, beam_scene, build_sim,
                              copy_reduced_state, format_table, reduced_static, study_config)

ENERGY = {
    "size": [1.0, 0.1, 0.1], "cell": 0.05, "material": MATERIAL,
    "domains": 2, "modes": 10,
    "tip_force": [0.0, 0.0, -2.0],          # N, dead load for the initial deformation
    "dts": [1e-4, 1e-3, 1e-2, 1.0 / 90.0],
    "schemes": ["one_step", "two_step"],
    "horizon": 5.0,                         # s of free vibration recorded
    "horizon_by_dt": {},                    # {dt: horizon} to shorten a run (documented in JSON)
    "samples": 1000,                        # energy samples kept per curve (about)
}
QUICK = {"horizon": 1.0, "dts": [1e-3, 1e-2, 1.0 / 90.0]}


def _dt_label(dt):
    return "1/90" if abs(dt - 1.0 / 90.0) < 1e-12 else f"{dt:g}"


def _horizon(cfg, dt):
    for k, v in (cfg.get("horizon_by_dt") or {}).items():
        if abs(float(k) - dt) <= 1e-12 * dt:
            return float(v)
    return float(cfg["horizon"])


def run_energy(sim, horizon, samples, log=None):
    """Step sim for `horizon` s, recording the energy about `samples` times.

    Returns {"t", "total", "kinetic", "elastic"} lists, "steps", "step_ms_median",
    "diverged" (non-finite or above 100 x the initial energy: stopped there)."""
    n = int(round(horizon / sim.dt))
    every = max(1, n // samples)
    e = sim.energy()
    E0 = e["total"]
    rec = {"t": [0.0], "total": [e["total"]], "kinetic": [e["kinetic"]], "elastic": [e["elastic"]]}
    step_ms = np.empty(n)
    diverged = False
    report_every = max(1, n // 5)
    for k in range(n):
        sim.step()
        step_ms[k] = sim.stats()["step_ms"]
        if (k + 1) % every == 0 or k + 1 == n:
            e = sim.energy()
            for key in ("total", "kinetic", "elastic"):
                rec[key].append(e[key])
            rec["t"].append((k + 1) * sim.dt)
            if not np.isfinite(e["total"]) or e["total"] > 100.0 * E0:
                diverged = True
                step_ms = step_ms[:k + 1]
                break
        if log and (k + 1) % report_every == 0:
            log(f"    step {k + 1}/{n}  E/E0 = {rec['total'][-1] / E0:.6f}")
    return dict(rec, steps=len(step_ms), step_ms_median=float(np.median(step_ms)), diverged=diverged)


def energy_report(out, quick=False, overrides=None, log=None):
    from . import plotting
    cfg = study_config("energy", ENERGY, QUICK, quick, overrides)
    log = log or Progress("energy")
    common = dict(size=cfg["size"], cell=cfg["cell"], material=cfg["material"],
                  domains={"count": int(cfg["domains"])}, modes=int(cfg["modes"]))

    # Initial deformation: reduced static equilibrium under the tip load.
    src = build_sim(beam_scene("reduced", integrator=dict(STATIC_INTEGRATOR), **common), log, "settle model")
    info = reduced_static(src, cfg["tip_force"])
    X = src.rest_positions()
    tip = src.body.handles["tip"]
    tip_defl = (src.vertex_positions()[tip] - X[tip]).mean(0)
    log(f"initial deformation: static under tip load {cfg['tip_force']} N in {info['steps']} steps, "
        f"tip displacement {np.round(tip_defl, 5).tolist()} m")

    runs = []
    for dt in cfg["dts"]:
        horizon = _horizon(cfg, dt)
        for scheme in cfg["schemes"]:
            integ = {"scheme": scheme, "dt": float(dt), "newton_iterations": 1}
            sim = build_sim(beam_scene("reduced", integrator=integ, damping=(0.0, 0.0), **common))
            gap = copy_reduced_state(src, sim)
            log(f"dt = {_dt_label(dt)}, {scheme}: {int(round(horizon / dt))} steps to t = {horizon:g} s")
            t0 = time.perf_counter()
            rec = run_energy(sim, horizon, int(cfg["samples"]), log)
            E = np.asarray(rec["total"])
            E0 = float(E[0])
            if not np.isfinite(E0) or E0 <= 0:
                raise ReportError(f"initial energy {E0} is not positive")
            t = np.asarray(rec["t"])
            ratio = E / E0
            run = {"dt": float(dt), "dt_label": _dt_label(dt), "scheme": scheme, "horizon": horizon,
                   "E0": E0, "final_ratio": float(ratio[-1]), "min_ratio": float(ratio.min()),
                   "max_ratio": float(ratio.max()),
                   # time average of E/E0 over the run (trapezoid on the recorded samples)
                   "mean_ratio": float(np.trapezoid(ratio, t) / t[-1]) if t[-1] > 0 else 1.0,
                   # largest rise of E/E0 above its running minimum: energy put back in
                   "max_rise": float(np.max(ratio - np.minimum.accumulate(ratio))),
                   "copy_gap_m": gap, "wall_s": time.perf_counter() - t0, **rec}
            runs.append(run)
            log(f"  E(T)/E0 = {run['final_ratio']:.6f} (min {run['min_ratio']:.6f}, time mean {run['mean_ratio']:.6f}, "
                f"largest rise {run['max_rise']:.4f}), "
                f"median step {run['step_ms_median']:.2f} ms, {run['wall_s']:.1f} s"
                + ("  DIVERGED" if run["diverged"] else ""))

    plots = [plotting.energy_curves(runs, Path(out) / "energy_curves.png",
                                    title=f"Undamped clamped two-domain beam, r = {cfg['modes']} per domain")]
    by = {(r["dt_label"], r["scheme"]): r for r in runs}
    def get(run, key):
        return run[key] if run else "-"

    rows = []
    for dt in cfg["dts"]:
        lab = _dt_label(dt)
        one, two = by.get((lab, "one_step")), by.get((lab, "two_step"))
        rows.append([lab, get(one or two, "horizon"), get(one or two, "steps"),
                     get(one, "final_ratio"), get(two, "final_ratio"), get(one, "mean_ratio"), get(two, "mean_ratio"),
                     get(one, "min_ratio"), get(two, "min_ratio"), get(one, "max_rise"), get(two, "max_rise"),
                     get(one, "step_ms_median"), get(two, "step_ms_median")])
    table = format_table(["dt (s)", "T (s)", "steps", "E(T)/E0 one", "E(T)/E0 two", "mean one", "mean two",
                          "min one", "min two", "rise one", "rise two", "ms/step one", "ms/step two"], rows)
    table += ("\nE(T)/E0 at the end; mean: time average of E/E0; min: its minimum; rise: largest rise of "
              "E/E0 above its running minimum (energy put back)")
    notes = [f"clamped beam {cfg['size']} m, cell {cfg['cell']} m, {src.stats()['vertices']} vertices, "
             f"{cfg['domains']} domains x {cfg['modes']} modes, StVK E = {cfg['material']['young']:g} Pa; "
             f"E0 = {runs[0]['E0']:.6g} J"]
    shortened = {_dt_label(float(k)): v for k, v in (cfg.get("horizon_by_dt") or {}).items()}
    if shortened:
        notes.append(f"shortened horizons: {shortened}")
    # Curves are kept subsampled (about cfg['samples'] points each).
    return {"config": dict(cfg, quick=quick, boundary="clamped at x = 0", damping="none (alpha = beta = 0)",
                           gravity="off", initial_state="reduced static equilibrium under tip_force, "
                           "released from rest", energy="kinetic + elastic (J)"),
            "initial": {"tip_displacement": tip_defl, "settle": info, "E0": runs[0]["E0"]},
            "runs": runs, "plots": plots, "table": table, "notes": notes}
