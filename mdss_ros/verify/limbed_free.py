"""A free-floating limbed body over time against full FEM (issue 15).

`mdss tradeoff star_limbs --out DIR --free-body [--quick]` (limbed_free_report).

The scene (free_overrides): the limbed scene with its pins removed, no gravity, and a
timeline of torques on every handle. Each arm's torque turns its tip up about the
horizontal axis d x z (d: horizontal direction from the body's centre to the handle),
its size T times a factor near 1 that makes the torques' sum zero (balanced_scales;
star_limbs: 0.92-1.07):
+T from t = 0, -T from `reverse_at` (the arms swing from curled up to curled down), all
loads cleared at `release_at` and the arms swing back freely until `horizon`. The
torques are spread over the handle's vertices at their current positions every step
(Simulator.set_wrench), so they turn with the arm. No net torque: the body turns only
through its limbs' motion (and the full-space backward Euler truth does not conserve
angular momentum exactly: measured on this body with beta = 0 under a constant 3 N m,
1.05 of the 2.0 N m s it should hold after 0.67 s at dt = 1/90, where the reduced models'
rigid frames keep 1.997; the row "full FEM, Newton to tol., dt/4" measures how far the
truth itself is from a finer-step truth).

Every configuration plays the same timeline through the Simulator API at the scene's dt
and is compared with the ground truth (full-space model, same mesh and dt, Newton to
1e-8 each step; accuracy.ground_truth) at probes every `probe_every` s:

    err(t)    RMS over surface vertices of |x - x_truth| at probe time t, / the truth's
              largest surface displacement over the run (accuracy.surface_error's scale)
    rms_rel   sqrt(mean over probes err(t)^2) (accuracy.metrics)
    max_rel   largest surface vertex error over probes, same scale

plus the truth's limb turns: each handle's best-fit rotation relative to the hub's (the
body's vertices within hub_radius of the vertical axis through the centre), largest over
the run. Cost: median ms per step playing the first timing_steps steps of the timeline,
every row re-timed in timing_rounds round-robin passes (smallest pass median kept), in one
process. Outputs: DIR/limbed_free.json, DIR/limbed_free_error.png (err(t) per row).
"""
import time
from pathlib import Path

import numpy as np

from ..accuracy import ground_truth, play
from ..precompute import PrecomputeCache
from ..rotations import rotation_angles
from ..scene import load_scene
from ..simulator import Simulator
from ..timeline import TimelinePlayer
from .peers import retime_round_robin
from .peers_limbed import ONE, one_domain
from .reduced_reports import Progress, ReportError, environment, format_table, write_json

SETTINGS = {"torque": 6.0,            # N m on every handle
            "reverse_at": 0.4,        # s: the torques change sign
            "release_at": 0.8,        # s: every load cleared
            "horizon": 1.2,           # s played
            "probe_every": 1.0 / 30.0,
            "hub_radius": 0.05,       # m: the hub's vertices for the relative limb turns
            "timing_steps": 60, "timing_rounds": 3, "warmup": 5,
            "truth_newton_iterations": 30, "truth_tolerance": 1e-8}
QUICK = {"horizon": 0.4, "reverse_at": 0.2, "release_at": 0.3, "timing_steps": 10, "timing_rounds": 1}
TRUTH_DT4 = "full FEM, Newton to tol., dt/4 (the truth's own step error)"
ROWS = [(TRUTH_DT4, None),
        ("full FEM, 1 Newton it./step", {"model.kind": "full", "model.integrator.newton_iterations": 1}),
        ("scene config (per-limb)", {}),
        ("per-limb domains, arms r = 20, hub r = 30", {"model.modes": 20}),
        ("1 domain, r = 12", dict(ONE)),
        ("1 domain, r = 20", one_domain(20)),
        ("1 domain, r = 30", one_domain(30)),
        ("1 domain, r = 40", one_domain(40)),
        ("1 domain, r = 60", one_domain(60))]
ROWS_QUICK = [ROWS[2], ROWS[6]]


def rotation_of(X, x, ids):
    """Best-fit rotation (3, 3) taking X[ids] to x[ids] (Kabsch, centroids removed)."""
    P = X[ids] - X[ids].mean(0)
    Q = x[ids] - x[ids].mean(0)
    U, _, Vt = np.linalg.svd(P.T @ Q)
    d = np.sign(np.linalg.det(U @ Vt))
    return (U @ np.diag([1.0, 1.0, d]) @ Vt).T


def angle_deg(R):
    return float(np.degrees(rotation_angles(R)))


def balanced_scales(axes):
    """Factors a (k,) closest to 1 (least squares) with sum_i a_i axes_i = 0: the arms'
    torques then have no net torque, so the body's spin comes from its limbs' motion only.
    axes (k, 3) horizontal unit axes. Raises ReportError when the balance needs a factor
    below 0.2 (the arms' directions cannot balance: the torque would nearly vanish on one)."""
    A = np.asarray(axes, dtype=np.float64)[:, :2].T                  # (2, k)
    ones = np.ones(A.shape[1])
    a = ones - A.T @ np.linalg.lstsq(A @ A.T, A @ ones, rcond=None)[0]
    if a.min() < 0.2:
        raise ReportError(f"the arms' torques cannot balance with factors near 1 (got {np.round(a, 3).tolist()})")
    return a


def free_overrides(scene_src, base, cfg):
    """Scene overrides of the free body: no pins, no gravity, the torque timeline."""
    from ..body import build_body
    scene = load_scene(scene_src, base)
    if len(scene["handles"]) < 2:
        raise ReportError(f"{scene.name}: the free limbed body needs two or more handles (one per arm)")
    body = build_body(scene)
    X = np.asarray(body.vertices)
    centre = X.mean(0)
    T = float(cfg["torque"])
    names, axes = list(body.handles), []
    for name in names:
        d = X[body.handles[name]].mean(0) - centre
        d[2] = 0.0
        if np.linalg.norm(d) <= 1e-9:
            raise ReportError(f"handle {name!r} sits on the body's vertical axis: no arm direction")
        axes.append(np.cross(d / np.linalg.norm(d), [0.0, 0.0, 1.0]))
    scale = balanced_scales(np.array(axes))
    timeline = []
    for t, sign in ((0.0, 1.0), (float(cfg["reverse_at"]), -1.0)):
        for name, axis, a in zip(names, axes, scale):
            timeline.append({"t": t, "topic": "wrench", "frame_id": name, "torque": (sign * T * a * axis).tolist()})
    timeline.append({"t": float(cfg["release_at"]), "topic": "clear_forces"})
    return dict(base, **{"pins": [], "gravity": [0.0, 0.0, 0.0], "timeline": timeline,
                         "duration": float(cfg["horizon"])})


def limb_turns(truth, X, handles, hub):
    """Largest turn (deg) over the run of each handle relative to the hub, and of the hub."""
    out = {name: 0.0 for name in handles}
    hub_turn = 0.0
    for x in truth["x"]:
        Rh = rotation_of(X, x, hub)
        hub_turn = max(hub_turn, angle_deg(Rh))
        for name, ids in handles.items():
            out[name] = max(out[name], angle_deg(Rh.T @ rotation_of(X, x, ids)))
    return out, hub_turn


def errors_over_time(X, xs, xs_ref, surface, peak, handles, hub):
    """Errors of a run's probes xs (p, n, 3) against the truth's xs_ref, surface vertices,
    as fractions of the truth's peak surface displacement: err_t (RMS), rms_rel, max_rel
    (accuracy.metrics' definitions), and err_aligned_t / rms_rel_aligned after the rigid
    motion that puts the run's hub onto the truth's hub (Kabsch over the hub's vertices):
    the error of the limbs' shape relative to the hub, without the drift of the body's
    orientation and position. misalignment_deg: the angle between the two hubs per probe;
    limb_turn_deg: each handle's largest turn relative to the hub over the run (as the
    truth's)."""
    err_t, err_al, mis, vmax = [], [], [], 0.0
    turns = {k: 0.0 for k in handles}
    for x, xr in zip(xs, xs_ref):
        d = np.linalg.norm(x[surface] - xr[surface], axis=1)
        err_t.append(float(np.sqrt((d ** 2).mean())) / peak)
        vmax = max(vmax, float(d.max()) / peak)
        R = rotation_of(x, xr, hub)                        # rotation taking x's hub onto xr's
        xa = (x - x[hub].mean(0)) @ R.T + xr[hub].mean(0)
        err_al.append(float(np.sqrt((np.linalg.norm(xa[surface] - xr[surface], axis=1) ** 2).mean())) / peak)
        mis.append(angle_deg(R))
        Rh = rotation_of(X, x, hub)
        for k, ids in handles.items():
            turns[k] = max(turns[k], angle_deg(Rh.T @ rotation_of(X, x, ids)))
    return {"err_t": err_t, "err_aligned_t": err_al, "misalignment_deg": mis,
            "misalignment_deg_max": max(mis), "limb_turn_deg": turns,
            "rms_rel": float(np.sqrt(np.mean(np.square(err_t)))), "max_rel": vmax,
            "rms_rel_aligned": float(np.sqrt(np.mean(np.square(err_al))))}


def timeline_timer(sim, steps, warmup):
    def timer():
        sim.reset()
        player = TimelinePlayer(sim.scene["timeline"])
        ms = []
        for k in range(warmup + steps):
            player.apply_due(sim)
            sim.step()
            if k >= warmup:
                ms.append(sim.stats()["step_ms"])
        sim.reset()
        return float(np.median(ms))
    return timer


def limbed_free_report(scene_src, out, quick=False, sets=None, log=None, rows=None):
    """Run the free-body comparison (module docstring) into `out`; returns the result dict.
    sets: --set pairs; tradeoff.NAME changes a SETTINGS entry, other keys override the scene."""
    log = log or Progress("limbed_free")
    t_start = time.perf_counter()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    sets = dict(sets or {})
    settings = {k.split(".", 1)[1]: v for k, v in sets.items() if k.startswith("tradeoff.")}
    unknown = sorted(set(settings) - set(SETTINGS))
    if unknown:
        raise ReportError(f"--free-body: unknown setting(s) {unknown} (settings: {', '.join(sorted(SETTINGS))})")
    cfg = dict(SETTINGS, **(QUICK if quick else {}), **settings)
    cfg["warmup"] = int(cfg["warmup"])
    base = {k: v for k, v in sets.items() if not k.startswith("tradeoff.")}
    env0 = environment()
    ov = free_overrides(scene_src, base, cfg)
    scene = load_scene(scene_src, ov)
    log(f"free limbed body {scene.name}: torque {cfg['torque']} N m on {len(scene['handles'])} handles, reversed at "
        f"{cfg['reverse_at']} s, released at {cfg['release_at']} s, {cfg['horizon']} s; load average "
        f"{env0['load_average']}")
    truth = ground_truth(scene_src, ov, scene.dt, cfg, log)
    probe_t = np.asarray(truth["t"][1:])
    peak = float(truth["peak"].max())
    sim0 = Simulator(load_scene(scene_src, dict(ov, **{"model.kind": "full"})))
    X = sim0.rest_positions()
    hub = np.flatnonzero(np.hypot(X[:, 0] - X[:, 0].mean(), X[:, 1] - X[:, 1].mean()) <= float(cfg["hub_radius"]))
    handles = {k: np.asarray(v) for k, v in sim0.body.handles.items()}
    surface = np.asarray(sim0.body.surface.vertex_ids)
    turns, hub_turn = limb_turns(truth, X, handles, hub)
    log(f"truth: peak surface displacement {1e3 * peak:.1f} mm; largest limb turns relative to the hub (deg): "
        + ", ".join(f"{k} {v:.0f}" for k, v in turns.items()) + f"; the hub itself turns {hub_turn:.0f} deg")
    result = {"scene": scene.name, "config": dict(cfg, quick=quick), "scene_overrides": base,
              "timeline": ov["timeline"], "truth": {"dofs": truth["dofs"], "step_ms": truth["step_ms"],
                                                    "newton_iterations_mean": truth["newton_iterations_mean"],
                                                    "unconverged": truth["unconverged"], "peak_displacement": peak,
                                                    "limb_turn_deg": turns, "hub_turn_deg": hub_turn},
              "probe_t": probe_t.tolist(), "rows": []}
    fine = None
    for label, row_ov in (rows if rows is not None else ROWS_QUICK if quick else ROWS):
        t0 = time.perf_counter()
        if row_ov is None:           # the truth at a quarter of its step: how far the truth is from converged
            row_ov = {"model.kind": "full", "model.integrator.dt": scene.dt / 4,
                      "model.integrator.newton_iterations": int(cfg["truth_newton_iterations"]),
                      "model.integrator.tolerance": float(cfg["truth_tolerance"])}
        sc = load_scene(scene_src, dict(ov, **({"model.kind": "reduced"} | row_ov)))
        cache = PrecomputeCache(out / "cache" / ("free_" + "".join(c if c.isalnum() else "_" for c in label)[:60]))
        try:
            sim = Simulator(sc, cache=cache)
            rec = play(sim, cfg["horizon"], cfg["probe_every"], cfg["warmup"])
        except ReportError as err:
            result["rows"].append({"label": label, "failed": str(err)})
            log(f"{label}: FAILED: {err}")
            continue
        if len(rec["x"]) != len(truth["x"]):
            raise ReportError(f"{label}: {len(rec['x'])} probes against the truth's {len(truth['x'])}")
        row = {"label": label, "kind": sim.model.kind, "dofs": int(sim.stats()["dofs"]),
               "domains": int(sim.stats().get("domains", 0) or 0), "overrides": row_ov,
               "step_ms": rec["step_ms"], "reference": label == TRUTH_DT4}
        if label != TRUTH_DT4:       # the reference row is not re-timed (it is not a candidate)
            row["_timer"] = timeline_timer(sim, int(cfg["timing_steps"]), cfg["warmup"])
        row.update(errors_over_time(X, rec["x"], truth["x"], surface, peak, handles, hub))
        if label == TRUTH_DT4:
            fine = rec["x"]
        elif fine is not None:       # the same errors against the truth at dt/4
            e4 = errors_over_time(X, rec["x"], fine, surface, peak, handles, hub)
            row.update({k + "_vs_dt4": e4[k] for k in ("err_t", "err_aligned_t", "rms_rel", "rms_rel_aligned")})
        result["rows"].append(row)
        log(f"{label}: {row['dofs']} DOFs, RMS over time {100 * row['rms_rel']:.3g} % (max vertex "
            f"{100 * row['max_rel']:.3g} %; with the hubs aligned {100 * row['rms_rel_aligned']:.3g} %), "
            f"largest hub misalignment {row['misalignment_deg_max']:.1f} deg, {row['step_ms']:.3g} ms/step "
            f"[{time.perf_counter() - t0:.1f} s]")
    retime_round_robin(result["rows"], int(cfg["timing_rounds"]))
    for r in result["rows"]:
        if "failed" not in r:
            r["error_x_ms"] = r["rms_rel"] * r["step_ms"]
    result["table"] = free_table(result["rows"])
    result["environment"] = dict(environment(), load_average_start=env0["load_average"])
    result["plots"] = [free_plot(result, out / "limbed_free_error.png")]
    result["wall_s"] = time.perf_counter() - t_start
    path = write_json(out, "limbed_free", result)
    print(f"\n== {scene.name}, free body under arm torques ({cfg['torque']} N m), {cfg['horizon']} s vs full FEM "
          f"(Newton to {cfg['truth_tolerance']:g}, {truth['step_ms']:.0f} ms/step) ==\n{result['table']}\n"
          f"truth: peak {1e3 * peak:.1f} mm; limb turns vs hub (deg) "
          + ", ".join(f"{k} {v:.0f}" for k, v in turns.items()) + f"; hub {hub_turn:.0f} deg\n"
          f"load average {env0['load_average']} at start, {result['environment']['load_average']} at end\n"
          f"wrote {path} and {Path(result['plots'][0]).name} ({result['wall_s']:.1f} s wall)", flush=True)
    return result


def free_table(rows):
    body = []
    for r in rows:
        if "failed" in r:
            body.append([r["label"], "-", "failed: " + r["failed"][:50]] + ["-"] * 9)
            continue
        body.append([r["label"], r["dofs"], f"{100 * r['rms_rel']:.3g}", f"{100 * max(r['err_t']):.3g}",
                     f"{100 * r['max_rel']:.3g}", f"{100 * r['rms_rel_aligned']:.3g}",
                     f"{r['misalignment_deg_max']:.0f}", f"{max(r['limb_turn_deg'].values()):.0f}",
                     f"{r['step_ms']:.3g}", f"{100 * r['error_x_ms']:.3g}",
                     f"{100 * r['rms_rel_vs_dt4']:.3g}" if "rms_rel_vs_dt4" in r else "-",
                     f"{100 * r['rms_rel_aligned_vs_dt4']:.3g}" if "rms_rel_vs_dt4" in r else "-"])
    return format_table(["model", "DOFs", "RMS err over time %", "worst probe RMS %", "max vertex err %",
                         "RMS err, hubs aligned %", "hub misalignment deg (max)", "largest limb turn deg",
                         "ms/step", "err x ms (% ms)", "RMS % vs truth at dt/4", "hubs aligned, vs dt/4"], body)


def free_plot(result, path):
    """err(t) of every row (log y), the reverse and release times marked."""
    from .plotting import pyplot, save_figure
    plt = pyplot()
    panels = [("err_t", "rms_rel", "vs full FEM at dt"), ("err_aligned_t", "rms_rel_aligned", "vs full FEM at dt, hubs aligned")]
    if any("err_t_vs_dt4" in r for r in result["rows"]):
        panels.append(("err_t_vs_dt4", "rms_rel_vs_dt4", "vs full FEM at dt/4"))
    fig, axes = plt.subplots(1, len(panels), figsize=(5.2 * len(panels), 4.6), sharey=True)
    t = np.asarray(result["probe_t"])
    cfg = result["config"]
    for ax, (key, agg_key, what) in zip(np.atleast_1d(axes), panels):
        for i, r in enumerate(result["rows"]):
            if "failed" in r or key not in r:
                continue
            e = 100 * np.asarray(r[key])
            one = r.get("domains") == 1
            agg = r[agg_key]
            ax.plot(t[:len(e)], e, ls="--" if one else "-", lw=1.2, color=plt.cm.tab10(i % 10),
                    label=f"{r['label'][:42]} ({r['dofs']}, {r['step_ms']:.2g} ms): {100 * agg:.2g} %")
        for when, note in ((cfg["reverse_at"], "reversed"), (cfg["release_at"], "released")):
            ax.axvline(when, color="0.5", ls=":", lw=1)
            ax.annotate(note, (when, 0.98), xycoords=("data", "axes fraction"), fontsize=7, va="top", ha="left")
        ax.set_yscale("log")
        ax.set_xlabel("t (s)")
        ax.set_title(f"RMS surface error {what}", fontsize=9)
        ax.grid(alpha=0.3, which="both")
        ax.legend(fontsize=6, loc="lower right")
    np.atleast_1d(axes)[0].set_ylabel("% of the truth's peak displacement")
    tr = result["truth"]
    fig.suptitle(f"{result['scene']} free body, {cfg['torque']} N m on every arm: limbs turn up to "
                 f"{max(tr['limb_turn_deg'].values()):.0f} deg vs the hub, the hub {tr['hub_turn_deg']:.0f} deg, "
                 f"peak {1e3 * tr['peak_displacement']:.0f} mm", fontsize=9)
    return save_figure(fig, path)
