"""`mdss tradeoff SCENE --out DIR`: the speed-accuracy trade of a scene's model (issue 7).

A sweep over the knobs a user turns, one knob at a time around the scene's own model
configuration plus a few combinations (`sweep_variants`): modes per domain, cubature
(exact, then several sample counts, interface weights), domain count, dt, one-step vs
two-step, element vs spring coupling, Newton iterations, and the other model kinds with
one Newton iteration per step on the same mesh and dt (what a user would run instead): the
full-space model, and the meshless model (docs/method.md §19; its own settings, the
scene's model.meshless, default 16 neighbours; the reduced keys are ignored).

Every configuration plays the scene's timeline for `horizon` seconds and is compared
with the ground truth on the same inputs: the full-space model (`model.kind: full`, same
mesh, same dt) with Newton iterated to `truth_tolerance` every step. At probe times
(every `probe_every` s) it records

    rms_rel       sqrt(mean over probes of RMS_s |x_s - x_ref,s|^2) / max over probes of the
                  truth's largest surface displacement (surface vertices; reduced_reports.surface_error)
    max_rel       largest surface vertex error over probes, same scale
    tip_rel       max over probes |tip - tip_ref| / max over probes |tip_ref - tip_rest|, where
                  tip = mean position of the scene's first handle (else the surface vertex the
                  truth moves most)
    energy_rel    max over probes |E - E_ref| / (range of E_ref), E = kinetic + elastic + gravity
    energy_drift  energy change over the input-free end of the run (after the last timeline
                  event) minus the truth's, / range of E_ref (negative: the model loses energy)

and its cost: median ms per step (Simulator step_ms, steps after `warmup`), the cold build
(precompute into an empty cache folder under DIR/cache, so it is a real build) and the
warm build (a second start from that cache; the cache events say it was a hit).
A configuration with another dt is compared with the truth at its own dt (rms_rel) and,
at the probe times both share, with the truth at the scene's dt (rms_rel_vs_scene_dt).

Outputs: DIR/tradeoff.json (every number, the configurations as scene overrides, the
Pareto front), DIR/tradeoff_pareto.png (ms/step vs error, log axes, front highlighted,
each point labelled) and a printed table to pick a configuration from. For a clamped
box beam the peer comparison with MuJoCo's flex (verify/peers.py) runs in the same
report (DIR/tradeoff_peers.png); for a limbed body (pinned on one face of its bounding box,
handles, a wrench in the timeline: msg_scenes/star_limbs.yaml) the static comparison of
verify/peers_limbed.py does (DIR/tradeoff_peers_limbed.png). `--set tradeoff.peers_only=true`
runs the peer comparison alone (no sweep, no ground-truth run). The limbed comparison's
large-deformation case: `--set tradeoff.tip_force_scale=12 --set tradeoff.side_force=15`
(star_limbs: arm0 turns ~54 degrees up, arm2 ~29 degrees sideways in our FEM statics).

--set KEY=VALUE: keys `tradeoff.NAME` change a study setting (SETTINGS); other keys
override the scene (the base configuration every variant starts from).
"""
import copy
import shutil
import time
from pathlib import Path

import numpy as np

from ..accuracy import (dt_label as _dt_label, ground_truth, metrics, play, probe_error,  # noqa: F401
                        probe_steps, tip_vertices, truth_record)
from ..body import pinned_mesh_overrides
from ..errors import MdssError
from ..precompute import PrecomputeCache
from ..scene import load_scene
from .reduced_reports import Progress, ReportError, environment, format_table, study_config, write_json

SETTINGS = {
    "horizon": None,                  # s of the timeline played; None: the scene's duration
    "warmup": 5,                      # steps left out of the ms/step median
    "probe_every": 1.0 / 15.0,        # s between error probes (a multiple of 1/30, 1/45, 1/90, 1/180)
    "truth_newton_iterations": 30,
    "truth_tolerance": 1e-8,          # Newton residual relative to its first, every truth step
    # linear: the truth is the scene's own mesh (what a reduced model can reach at best);
    # quadratic: 10-node tets on it (fem/quadratic.py), which do not lock in bending
    # (the yardstick for models on other discretisations: meshless)
    "truth_element": "linear",
    "variants": "sweep",              # sweep | quick
    "peers": True,                    # MuJoCo flex comparison (clamped box beam, or a limbed body)
    "peers_only": False,              # only the peer comparison: skip the sweep and its ground truth
    "timing_rounds": 3,               # round-robin re-timing passes over all configurations
    "timing_steps": 60,               # steps per configuration and pass (after warm-up)
    "tip_force_scale": 1.0,           # limbed peers: the static tip force x this (large deformation: ~10)
    "side_force": 0.0,                # limbed peers: N sideways on a second arm (0: none)
}
QUICK = {"horizon": 1.0, "variants": "quick", "timing_rounds": 2, "timing_steps": 30}

METRICS = {
    "rms_rel": "sqrt(mean over probes of RMS over surface vertices of |x - x_truth|^2) / max over probes "
               "of the truth's largest surface displacement",
    "max_rel": "largest surface vertex error over probes / the same peak",
    "tip_rel": "max over probes |tip - tip_truth| / max over probes |tip_truth - tip_rest|; tip = mean "
               "position of the scene's first handle (else the surface vertex the truth moves most)",
    "energy_rel": "max over probes |E - E_truth| / (max - min of E_truth), E = kinetic + elastic + gravity",
    "energy_drift": "(E_end - E_free) - (E_truth,end - E_truth,free) over the input-free end of the run "
                    "(after the last timeline event), / range of E_truth",
    "step_ms": "min over timing_rounds round-robin passes (every configuration rebuilt from its warm cache "
               "and stepped timing_steps steps of the timeline in turn) of the median Simulator step_ms: "
               "load from other processes hits every configuration alike; step_ms_run is the median "
               "over the error run itself",
    "cold_build_s": "Simulator build into an empty cache folder (a real precompute)",
    "warm_build_s": "second build from that cache (warm_cache_hit: every stage loaded)",
    "rms_rel_vs_scene_dt": "a dt variant's rms_rel against the truth at the scene's dt (shared probe times)",
}
KNOB_MARKERS = {"scene": "*", "modes": "o", "cubature": "s", "domains": "D", "dt": "^", "scheme": "v",
                "coupling": "P", "newton": "X", "kind": "h", "combination": "p"}


# ---------------------------------------------------------------------- Pareto front
def pareto_front(cost, error):
    """Mask (n,) of the points no other point dominates: point j dominates i when
    cost_j <= cost_i and error_j <= error_i with one of them strictly smaller.
    Non-finite points are never on the front. cost, error: (n,) arrays."""
    c = np.asarray(cost, dtype=np.float64)
    e = np.asarray(error, dtype=np.float64)
    ok = np.isfinite(c) & np.isfinite(e)
    le = (c[None, :] <= c[:, None]) & (e[None, :] <= e[:, None])       # [i, j]: j at least as good as i
    lt = (c[None, :] < c[:, None]) | (e[None, :] < e[:, None])
    dominated = (le & lt & ok[None, :]).any(axis=1)
    return ok & ~dominated


# ---------------------------------------------------------------------- variants
def _fmt(x):
    return f"{x:.4g}"


def sweep_variants(model, which="sweep"):
    """Configurations to measure: [(label, knob, overrides)], overrides are dotted scene
    keys applied to the scene. model: the scene's validated `model` section.

    One knob at a time around the scene's configuration (the 'scene' row), then a few
    combinations. `which` = "quick" keeps a handful (the slow test and --quick)."""
    r = int(model["modes"])
    cub = dict(model.get("cubature") or {})
    samples = int(cub.get("samples", 0) or 0)
    interface = cub.get("interface", "exact")
    dom = model.get("domains") or {}
    count = dom.get("count") if isinstance(dom, dict) and "regions" not in dom else None
    dt = float(model["integrator"]["dt"])
    exact_cub = {"model.cubature": {"samples": 0, "interface": "exact"}}
    full = ("full space, 1 Newton iteration", "kind",
            {"model.kind": "full", "model.integrator.newton_iterations": 1})
    meshless = ("meshless, 1 Newton iteration", "kind",
                {"model.kind": "meshless", "model.integrator.newton_iterations": 1})
    out = [("scene", "scene", {"model.kind": "reduced"})]
    if which == "quick":
        out += [full, meshless,
                (f"r = {max(2, r // 2)}", "modes", {"model.modes": max(2, r // 2)}),
                ("exact cubature", "cubature", exact_cub),
                ("two-step", "scheme", {"model.integrator.scheme": "two_step"})]
        return [(lab, knob, dict({"model.kind": "reduced"}, **ov) if knob != "kind" else ov)
                for lab, knob, ov in out]
    for m in sorted({max(2, r // 3), max(2, r // 2), 2 * r} - {r}):
        out.append((f"r = {m}", "modes", {"model.modes": m}))
    out.append(("exact cubature", "cubature", exact_cub))
    base_s = samples or 60
    for s in sorted({max(8, base_s // 2), 2 * base_s, 4 * base_s} - {samples}):
        ov = {"model.cubature": dict(cub, samples=s)}
        if not samples:
            ov["model.cubature"]["interface"] = "exact"
        out.append((f"{s} samples", "cubature", ov))
    if samples:
        for iface in ("exact", "uniform", "nonuniform"):
            if iface != interface:
                out.append((f"interface {iface}", "cubature", {"model.cubature.interface": iface}))
    if count is not None:
        for d in sorted({1, 2, 2 * count} - {count}):
            ov = {"model.domains": {"count": d}}
            if d == 1:
                ov["model.cubature.interface"] = "exact"          # one domain: no interface
            out.append((f"{d} domain{'s' if d > 1 else ''}", "domains", ov))
    for f in (2.0, 0.5):
        out.append((f"dt = {_dt_label(dt * f)}", "dt", {"model.integrator.dt": dt * f}))
    other = "two_step" if model["integrator"]["scheme"] != "two_step" else "one_step"
    out.append((other.replace("_", "-"), "scheme", {"model.integrator.scheme": other}))
    out.append(("spring coupling", "coupling", {"model.coupling": {"kind": "spring"},
                                                "model.cubature.interface": "exact"}))
    out.append(("3 Newton iterations", "newton", {"model.integrator.newton_iterations": 3}))
    out += [full, meshless]
    # Combinations: the cheap end, the accurate end, and the single-domain fast path.
    combos = [(f"1 domain, r = {2 * r}", {"model.domains": {"count": 1}, "model.modes": 2 * r,
                                         "model.cubature.interface": "exact"}),
              (f"1 domain, r = {max(2, r // 2)}", {"model.domains": {"count": 1}, "model.modes": max(2, r // 2),
                                                    "model.cubature.interface": "exact"}),
              (f"r = {2 * r}, exact cubature", dict(exact_cub, **{"model.modes": 2 * r})),
              (f"r = {2 * r}, {4 * base_s} samples", {"model.modes": 2 * r,
                                                     "model.cubature": dict(cub, samples=4 * base_s)})]
    if count is not None and count > 2:
        combos.append((f"2 domains, r = {max(2, r // 2)}", {"model.domains": {"count": 2},
                                                            "model.modes": max(2, r // 2)}))
    out += [(lab, "combination", ov) for lab, ov in combos if count is not None or "domain" not in lab]
    return [(lab, knob, dict({"model.kind": "reduced"}, **ov) if knob != "kind" else ov)
            for lab, knob, ov in out]


# ---------------------------------------------------------------------- playing a scene
# ---------------------------------------------------------------------- one configuration
def build_timed(scene, cache_dir, warm=True):
    """(sim, build info): a cold build into an empty cache folder, then (reduced, warm=True)
    a second build from that cache, timed, whose cache events must all be hits."""
    from ..simulator import Simulator
    shutil.rmtree(cache_dir, ignore_errors=True)
    cache = PrecomputeCache(cache_dir)
    t0 = time.perf_counter()
    sim = Simulator(scene, cache=cache)
    info = {"cold_build_s": time.perf_counter() - t0, "cold_cache_events": [e[:2] for e in cache.events]}
    if scene["model"]["kind"] == "reduced" and warm:
        cache2 = PrecomputeCache(cache_dir)
        t0 = time.perf_counter()
        sim = Simulator(scene, cache=cache2)
        info["warm_build_s"] = time.perf_counter() - t0
        info["warm_cache_events"] = [e[:2] for e in cache2.events]
        info["warm_cache_hit"] = bool(cache2.events) and all(e[1] == "hit" for e in cache2.events)
    cub = getattr(sim.model, "cubature_info", None) or {}
    if cub.get("samples"):
        info["cubature_samples"] = [d["samples"] for d in cub.get("domains", [])]
        info["training_s"] = cub.get("training_seconds")
    return sim, info


def run_variant(scene_src, base_overrides, label, knob, overrides, cfg, truths, out, log):
    """Build, play and score one configuration; a failure becomes a row with 'failed'."""
    row = {"label": label, "knob": knob, "overrides": overrides}
    t0 = time.perf_counter()
    try:
        scene = load_scene(scene_src, dict(base_overrides, **overrides))
        slug = row["slug"] = "".join(c if c.isalnum() else "_" for c in label)[:48]
        sim, info = build_timed(scene, Path(out) / "cache" / slug)
        row.update(info)
        truth = truths.get(round(sim.dt, 12))
        if truth is None:
            truth = truths[round(sim.dt, 12)] = ground_truth(scene_src, base_overrides, sim.dt, cfg, log)
        base_truth = truths["scene_dt"]
        other_dt = base_truth is not truth
        rec = play(sim, cfg["horizon"], cfg["probe_every"], cfg["warmup"], truth=truth,
                   truth_scene_dt=base_truth if other_dt else None)
        st = sim.stats()
        row.update(kind=st["kind"], dofs=int(st["dofs"]), domains=int(st["domains"]), dt=sim.dt,
                   step_ms=rec["step_ms"], steps=rec["steps"], **metrics(rec, truth))
        if other_dt:
            m2 = metrics(rec, base_truth, key="errors_scene_dt")
            row["rms_rel_vs_scene_dt"] = m2.get("rms_rel")
        row["truth_step_ms"] = truth["step_ms"]
    except (MdssError, ReportError, ValueError, np.linalg.LinAlgError) as err:
        row["failed"] = f"{type(err).__name__}: {err}"
    row["wall_s"] = time.perf_counter() - t0
    if "failed" in row:
        log(f"  {label}: FAILED: {row['failed']} [{row['wall_s']:.1f} s]")
    else:
        log(f"  {label}: {row['dofs']} DOFs, {row['step_ms']:.3g} ms/step, RMS error "
            f"{100 * row['rms_rel']:.3g} %, tip {100 * row.get('tip_rel', np.nan):.3g} %, energy "
            f"{100 * row.get('energy_rel', np.nan):.3g} %, cold build {row['cold_build_s']:.1f} s"
            + (f", warm {row['warm_build_s']:.2f} s (hit: {row['warm_cache_hit']})" if "warm_build_s" in row else "")
            + f" [{row['wall_s']:.1f} s]")
    return row


def retime(scene_src, base_overrides, rows, cfg, out, log):
    """Round-robin re-timing: in each of timing_rounds passes every configuration is
    rebuilt from its warm cache and steps timing_steps steps of the timeline (after
    warmup); row["step_ms"] becomes the smallest of its per-pass medians. Passes
    alternate their order so a load spike does not always hit the same rows."""
    from ..simulator import Simulator
    from ..timeline import TimelinePlayer
    ok = [r for r in rows if "failed" not in r]
    per = {id(r): [] for r in ok}
    for p in range(int(cfg["timing_rounds"])):
        order = ok if p % 2 == 0 else ok[::-1]
        for r in order:
            scene = load_scene(scene_src, dict(base_overrides, **r["overrides"]))
            sim = Simulator(scene, cache=PrecomputeCache(Path(out) / "cache" / r["slug"]))
            player = TimelinePlayer(scene["timeline"])
            ms = []
            for k in range(int(cfg["warmup"]) + int(cfg["timing_steps"])):
                player.apply_due(sim)
                sim.step()
                if k >= cfg["warmup"]:
                    ms.append(sim.stats()["step_ms"])
            per[id(r)].append(float(np.median(ms)))
        log(f"timing pass {p + 1}/{cfg['timing_rounds']} done")
    for r in ok:
        r["step_ms_run"] = r["step_ms"]
        r["step_ms_passes"] = per[id(r)]
        r["step_ms"] = min(per[id(r)])


# ---------------------------------------------------------------------- report
def tradeoff_report(scene_src, out, quick=False, settings=None, scene_overrides=None, log=None):
    """Run the sweep (and the peer comparison) into `out`; returns the result dict."""
    from . import plotting
    cfg = study_config("tradeoff", SETTINGS, QUICK, quick, settings)
    log = log or Progress("tradeoff")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    base = dict(scene_overrides or {})
    scene = load_scene(scene_src, base)
    base.update(pinned_mesh_overrides(scene, out))     # every configuration on the same tets
    if cfg["horizon"] is None:
        cfg["horizon"] = float(scene["duration"])
    cfg["horizon"] = min(float(cfg["horizon"]), float(scene["duration"])) if not quick else float(cfg["horizon"])
    if cfg["peers_only"]:
        return _peers_only_report(scene_src, scene, base, cfg, out, quick, log)
    variants = sweep_variants(scene["model"], cfg["variants"])
    log(f"scene {scene.name!r} ({scene.source}): {len(variants)} configurations, horizon {cfg['horizon']:.3g} s, "
        f"dt {_dt_label(scene.dt)}, probes every {cfg['probe_every']:.4g} s")
    truths = {}
    truths[round(scene.dt, 12)] = truths["scene_dt"] = ground_truth(scene_src, base, scene.dt, cfg, log)
    rows = []
    for i, (label, knob, ov) in enumerate(variants):
        log(f"[{i + 1}/{len(variants)}] {label} ({knob}): {ov}")
        rows.append(run_variant(scene_src, base, label, knob, ov, cfg, truths, out, log))

    if cfg["timing_rounds"]:
        log(f"re-timing every configuration: {cfg['timing_rounds']} round-robin passes of {cfg['timing_steps']} steps")
        retime(scene_src, base, rows, cfg, out, log)
    ok = [r for r in rows if "failed" not in r]
    front = pareto_front([r["step_ms"] for r in ok], [r["rms_rel"] for r in ok])
    for r, f in zip(ok, front):
        r["pareto"] = bool(f)
    truth = truths["scene_dt"]
    plots = [pareto_plot(ok, truth, Path(out) / "tradeoff_pareto.png",
                         title=f"{scene.name}: cost vs error against full-space FEM, {cfg['truth_element']} tets "
                               f"({cfg['horizon']:.3g} s)", truth_element=cfg["truth_element"])]
    table = tradeoff_table(rows)
    notes = [f"ground truth: full space ({cfg['truth_element']} tets) at dt {_dt_label(scene.dt)}, {truth['dofs']} DOFs, "
             f"{truth['step_ms']:.1f} ms/step with Newton to {cfg['truth_tolerance']:g} "
             f"(mean {truth['newton_iterations_mean']:.2f} iterations)"]
    if truth["unconverged"]:
        notes.append(f"ground truth: {truth['unconverged']} of {truth['steps']} steps stopped at "
                     f"{cfg['truth_newton_iterations']} Newton iterations above the tolerance")
    result = {"scene": scene.name, "source": scene.source, "config": dict(cfg, quick=quick, scene_overrides=base),
              "ground_truth": {k: truth[k] for k in ("dofs", "step_ms", "steps", "newton_iterations_mean",
                                                      "newton_iterations_max", "unconverged", "wall_s",
                                                      "energy_range")}
              | {"peak_displacement": float(truth["peak"].max()), "probe_times": truth["t"][1:],
                 "other_dt": {str(k): {"step_ms": v["step_ms"], "dofs": v["dofs"]} for k, v in truths.items()
                              if k != "scene_dt" and v is not truth}},
              "rows": rows, "pareto_front": [r["label"] for r in ok if r["pareto"]],
              "metrics": METRICS,
              "plots": plots, "table": table, "notes": notes}
    if cfg["peers"]:
        result["peers"] = peer_comparison(scene_src, scene, base, cfg, out, quick, log)
        plots += result["peers"].get("plots", [])
    return result


def peer_comparison(scene_src, scene, base, cfg, out, quick, log):
    """The MuJoCo peer comparison that fits the scene: the clamped beam's (peers.py) or the
    limbed body's (peers_limbed.py); {"skipped": why} for other scenes."""
    from .peers import beam_peer_comparison, is_clamped_box_beam
    from .peers_limbed import is_limbed_scene, limbed_peer_comparison
    kw = dict(quick=quick, log=log, timing_rounds=int(cfg["timing_rounds"]))
    if is_clamped_box_beam(scene):
        return dict(beam_peer_comparison(scene_src, base, out, **kw), kind="beam")
    if is_limbed_scene(scene):
        return dict(limbed_peer_comparison(scene_src, base, out, timing_steps=int(cfg["timing_steps"]),
                                           tip_force_scale=float(cfg["tip_force_scale"]),
                                           side_force=float(cfg["side_force"]), **kw), kind="limbed")
    return {"skipped": "the peer comparison needs a clamped box beam (box mesh, x = 0 face pinned) or a limbed "
                       "body (pins on one face of its bounding box, two or more handles, a wrench in the timeline)"}


def _peers_only_report(scene_src, scene, base, cfg, out, quick, log):
    """tradeoff.peers_only: the peer comparison without the sweep."""
    log(f"scene {scene.name!r} ({scene.source}): peer comparison only (tradeoff.peers_only)")
    peers = peer_comparison(scene_src, scene, base, cfg, out, quick, log)
    return {"scene": scene.name, "source": scene.source, "config": dict(cfg, quick=quick, scene_overrides=base),
            "rows": [], "pareto_front": [], "metrics": METRICS, "plots": list(peers.get("plots", [])),
            "table": "(sweep skipped: tradeoff.peers_only)", "notes": [], "peers": peers}


def tradeoff_table(rows):
    """Plain-text table of the rows: '*' marks the Pareto front (ms/step vs RMS error)."""
    def pct(r, k):
        v = r.get(k)
        return "-" if v is None else f"{100 * v:.3g}"
    body = []
    for r in rows:
        if "failed" in r:
            body.append(["", r["label"], "failed", "-", "-", "-", "-", "-", "-", "-", "-", r["failed"][:50]])
            continue
        body.append(["*" if r.get("pareto") else "", r["label"], r["kind"], r["dofs"], _fmt(r["step_ms"]),
                     pct(r, "rms_rel"), pct(r, "tip_rel"), pct(r, "energy_rel"), pct(r, "energy_drift"),
                     _fmt(r["cold_build_s"]),
                     _fmt(r["warm_build_s"]) if "warm_build_s" in r else "-",
                     pct(r, "rms_rel_vs_scene_dt") if "rms_rel_vs_scene_dt" in r else ""])
    return format_table(["front", "configuration", "kind", "DOFs", "ms/step", "RMS err %", "tip err %",
                         "energy err %", "drift %", "cold build s", "warm build s", "note / RMS % vs scene dt"],
                        body)


def pareto_plot(rows, truth, path, title="", truth_element="linear"):
    """ms/step vs RMS error (log-log), one marker shape per knob, the front as a red
    staircase with its points ringed, every point labelled; the ground truth's cost as a
    dotted line."""
    from .plotting import pyplot, save_figure
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(10, 6.5))
    for r in rows:
        e = max(100 * r["rms_rel"], 1e-6)
        ax.scatter([r["step_ms"]], [e], marker=KNOB_MARKERS.get(r["knob"], "o"), s=46,
                   color="tab:red" if r.get("pareto") else "tab:blue", zorder=3,
                   edgecolors="k" if r.get("pareto") else "none")
        ax.annotate(r["label"], (r["step_ms"], e), fontsize=7, textcoords="offset points", xytext=(4, 3),
                    color="darkred" if r.get("pareto") else "0.25")
    fr = sorted((r for r in rows if r.get("pareto")), key=lambda r: r["step_ms"])
    if fr:
        ax.step([r["step_ms"] for r in fr], [100 * r["rms_rel"] for r in fr], where="post", color="tab:red",
                lw=1.5, alpha=0.7, label="Pareto front")
    ax.axvline(truth["step_ms"], color="k", ls=":", label=f"ground truth (full, {truth_element} tets, Newton to tol.) "
                                                          f"{truth['step_ms']:.1f} ms/step")
    for knob, m in KNOB_MARKERS.items():
        if any(r["knob"] == knob for r in rows):
            ax.scatter([], [], marker=m, color="0.5", label=knob)
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("median ms / step (measured under load)")
    ax.set_ylabel(f"RMS surface error vs full-space FEM, {truth_element} tets (% of peak displacement)")
    ax.set_title(title, fontsize=10)
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=7, loc="upper right")
    return save_figure(fig, path)


def run_tradeoff(scene_src, out, quick=False, sets=None):
    """`mdss tradeoff`: split --set into study settings (tradeoff.NAME) and scene overrides,
    run, write DIR/tradeoff.json, print the table. Returns the result dict."""
    sets = dict(sets or {})
    settings = {k.split(".", 1)[1]: v for k, v in sets.items() if k.startswith("tradeoff.")}
    scene_ov = {k: v for k, v in sets.items() if not k.startswith("tradeoff.")}
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    log = Progress("tradeoff")
    env0 = environment()
    log(f"start ({'quick' if quick else 'full'} run) -> {out}; load average {env0['load_average']} "
        f"on {env0['cpus']} CPUs (timings are measured under that load)")
    result = tradeoff_report(scene_src, out, quick=quick, settings=settings, scene_overrides=scene_ov, log=log)
    result["wall_s"] = log.elapsed()
    result["environment"] = dict(environment(), load_average_start=env0["load_average"])
    result["plots"] = [Path(p).name for p in result["plots"]]
    path = write_json(out, "tradeoff", copy.deepcopy(result))
    print(f"\n== mdss tradeoff {result['scene']}: pick a configuration (* = Pareto front, ms/step vs RMS error) ==\n"
          f"{result['table']}", flush=True)
    for note in result["notes"]:
        print(f"  note: {note}")
    peers = result.get("peers") or {}
    if peers.get("table"):
        what = ("static equilibrium of the limbed body under gravity + one arm's tip force (MuJoCo flex on the "
                "same tet mesh)" if peers.get("kind") == "limbed" else "static gravity sag of the clamped beam")
        print(f"\n== peers: {what} ==\n{peers['table']}")
        for line in peers.get("summary", []):
            print(f"  {line}")
    elif peers.get("skipped"):
        print(f"  peers: skipped: {peers['skipped']}")
    print(f"wrote {path} and {', '.join(result['plots'])} ({result['wall_s']:.1f} s wall)", flush=True)
    return result
