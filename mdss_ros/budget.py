"""Budget mode (`model.budget`): pick modes and cubature samples from a quick trade-off probe.

    model:
      kind: reduced
      budget: {ms_per_step: 5.0}          # the most accurate candidate whose step fits
      budget: {max_error: 0.02}           # the cheapest candidate within 2 % RMS surface error

The probe plays the scene's timeline for `horizon` seconds (default: min(1 s, duration))
on a ladder of candidates: `modes` per domain (default 4, 6, 8, 12, 16, 24, 32; values
above the scene's mesh allow are skipped by the model itself), with the cubature sample
counts scaled with the modes in the scene's own ratio (an exact-cubature scene stays
exact). Each candidate is measured as `mdss tradeoff` measures a configuration
(verify/tradeoff.py): median Simulator step_ms after warm-up, and for max_error the RMS
surface error against the full-space ground truth (same mesh, dt and inputs, Newton to
1e-8). Cost grows with the modes, so the ladder is walked upwards and stops once a
candidate is past the budget (ms) or within it (error).

`probe: exact` walks the ladder with exact forces and trains only the chosen candidate's
cubature (measured again; the walk goes on if the samples take it past the error).
`domains: [auto, 1]` runs each domain split at every mode count and keeps the fastest
within the error. The automatic model (scene.automatic_model) uses both.

The choice is stored in the precompute cache (stage "budget", keyed by the scene and the
code), so a second start does not probe again; its report says what was chosen and why,
and Simulator.explain() / stats()["budget"] show it. Timings are of this machine under
its current load: a probe on a busy machine picks fewer modes.
"""
import copy
import json
import math
import time

import numpy as np

from .body import build_body
from .errors import SceneError
from .precompute import PrecomputeCache, cache_key
from .reduced.partition import domain_labels
from .scene import BUDGET_DEFAULT_MODES as DEFAULT_MODES, check_budget, load_scene  # noqa: F401
from .simulator import Simulator as BaseSimulator

def candidate_overrides(model, modes, domains=None):
    """Scene overrides of the candidate with `modes` per domain: cubature samples scaled
    with the modes in the scene's ratio (exact stays exact); the budget switched off.
    domains: a model.domains value for this candidate (None: the scene's own)."""
    cub = copy.deepcopy(model.get("cubature") or {})
    base_r = int(model["modes"])
    for key in ("samples", "interface_samples"):
        n = cub.get(key)
        if isinstance(n, int) and not isinstance(n, bool) and n > 0:
            cub[key] = max(1, int(math.ceil(n * modes / base_r)))
    ov = {"model.modes": int(modes), "model.cubature": cub, "model.budget": {}}
    if domains is not None:
        ov["model.domains"] = copy.deepcopy(domains)
    return ov


def _settings(budget, scene):
    horizon = float(budget.get("horizon") or min(1.0, float(scene["duration"])))
    return {"horizon": horizon, "warmup": 3, "probe_every": 1.0 / 15.0 if horizon >= 0.2 else scene.dt,
            "truth_newton_iterations": 30, "truth_tolerance": 1e-8}


def domain_options(scene, cache=None):
    """[(label, model.domains value or None)] the probe tries: the scene's own domains
    (None), or budget.domains ("auto" or a count each), without those that split this body
    exactly as an earlier one does (a body without limbs: auto is one domain)."""
    wanted = scene["model"]["budget"].get("domains")
    if not wanted:
        return [("scene's domains", None)]
    body = build_body(scene, cache)
    out, seen = [], []
    for w in wanted:
        spec = {"auto": True} if w == "auto" else {"count": int(w)}
        labels, names = domain_labels(spec, body.vertices, body.tets)
        if any(len(names) == n and np.array_equal(labels, lab) for lab, n in seen):
            continue
        seen.append((labels, len(names)))
        label = (f"auto ({len(names)} domain{'s' if len(names) > 1 else ''})" if w == "auto"
                 else f"{len(names)} domain{'s' if len(names) > 1 else ''}")
        out.append((label, spec))
    return out


def probe(scene, progress=None, cache=None):
    """Walk the candidate ladder of a scene with a budget. Returns the report dict:
    {"goal", "target", "chosen": {"modes", "overrides"[, "domains", "measured"]}, "met": bool,
    "candidates": [...], "horizon", "seconds"}.

    The ladder walks the modes upwards. With budget.domains (max_error only) it measures
    every domain option at each mode count, and stops at the first mode count where one
    is within the error, taking the fastest of those."""
    from .accuracy import ground_truth, metrics, play
    say = progress or (lambda msg: None)
    budget = scene["model"]["budget"]
    goal = "ms_per_step" if "ms_per_step" in budget else "max_error"
    target = float(budget[goal])
    cfg = _settings(budget, scene)
    t0 = time.perf_counter()
    plain = _without_budget(scene)
    options = domain_options(scene, cache)
    truth = None
    if goal == "max_error":
        say(f"budget: ground truth for the error probe (full space, {cfg['horizon']:.3g} s of the timeline)")
        truth = ground_truth(plain, {}, scene.dt, cfg, say, cache=cache)
    rows = []
    chosen = measured = None
    # probe: exact walks the ladder with exact forces (no cubature to train per candidate:
    # the subspace sets the error) and trains only the chosen candidate's cubature. If its
    # sampled forces take it past the error, the walk goes on to the next mode count.
    exact = budget.get("probe", "scene") == "exact"
    sampled = exact and int((scene["model"].get("cubature") or {}).get("samples", 0) or 0) > 0

    def run(r, label, domains, with_cubature):
        ov = candidate_overrides(scene["model"], r, domains)
        if exact and not with_cubature:
            ov["model.cubature"] = {"samples": 0, "interface": "exact"}
        sim = BaseSimulator(plain, overrides=ov, cache=cache)
        rec = play(sim, cfg["horizon"], cfg["probe_every"], cfg["warmup"], truth=truth)
        row = {"modes": int(r), "dofs": int(sim.stats()["dofs"]), "step_ms": rec["step_ms"],
               "samples": ov["model.cubature"].get("samples", 0), "domains": label,
               "domains_spec": domains, "n_domains": int(sim.stats()["domains"])}
        if with_cubature:
            row["with_cubature"] = True
        if truth is not None:
            row["rms_rel"] = metrics(rec, truth).get("rms_rel", float("nan"))
        say(f"budget: {r} modes per domain, {label}" + (f", {row['samples']} samples" if with_cubature else "")
            + f": {row['dofs']} DOFs, {row['step_ms']:.3g} ms/step"
            + (f", RMS surface error {100 * row['rms_rel']:.3g} %" if "rms_rel" in row else ""))
        return row

    for r in budget["modes"]:
        here = [run(r, label, domains, False) for label, domains in options]
        rows += here
        if goal == "ms_per_step":
            if here[0]["step_ms"] <= target:        # one domain option (check_budget)
                chosen = here[0]
                continue
            break                                    # more modes cost more
        within = [x for x in here if x["rms_rel"] <= target]
        if not within:
            continue
        best = min(within, key=lambda x: x["step_ms"])            # the cheapest within the error
        if not sampled:
            chosen = best
            break
        measured = run(r, best["domains"], best["domains_spec"], True)
        if measured["rms_rel"] <= target:
            chosen = best
            break
        say(f"budget: with its cubature {r} modes per domain is past the error; trying more modes")
        measured = None
    met = chosen is not None
    if not met:                            # nothing fits: the cheapest (ms) or the most accurate (error)
        chosen = rows[0] if goal == "ms_per_step" else min(rows, key=lambda x: x.get("rms_rel", math.inf))
    if sampled and measured is None:       # the chosen one as it will run, cubature included
        measured = run(chosen["modes"], chosen["domains"], chosen["domains_spec"], True)
    report = {"goal": goal, "target": target, "met": met,
              "chosen": {"modes": chosen["modes"], "domains": chosen["domains"],
                         "overrides": candidate_overrides(scene["model"], chosen["modes"], chosen["domains_spec"])},
              "candidates": rows, "horizon": cfg["horizon"]}
    if measured is not None:
        report["chosen"]["measured"] = measured
    report["seconds"] = time.perf_counter() - t0
    say(f"budget: chose {chosen['modes']} modes per domain, {chosen['domains']} "
        + ("" if met else f"(no candidate meets {goal} <= {target:g}; took the "
           f"{'cheapest' if goal == 'ms_per_step' else 'most accurate'}) ")
        + f"after a {report['seconds']:.1f} s probe")
    return report


def _without_budget(scene):
    return load_scene(scene, {"model.budget": {}})


def budget_key(scene):
    from .precompute import code_hash
    data = json.loads(json.dumps(scene.data, sort_keys=True, default=str))
    return cache_key("budget", code_hash("cubature"), data)


def cached_choice(scene, cache=None):
    """The scene with its cached budget choice applied, or None if the probe has not run
    (the node's start notice: what a start will cost). A scene without a budget: itself."""
    if not (scene["model"].get("budget") or {}):
        return scene
    hit = (cache if cache is not None else PrecomputeCache()).load("budget", budget_key(scene))
    return None if hit is None else load_scene(scene, hit[1]["chosen"]["overrides"])


def resolve_budget(scene, progress=None, cache=None):
    """(scene to build, budget report or None): a scene with model.budget gets the chosen
    modes and samples (from the cache, or from a probe that is then cached)."""
    budget = scene["model"].get("budget") or {}
    if not budget:
        return scene, None
    if scene["model"]["kind"] != "reduced":
        raise SceneError(f"{scene.source}: model.budget picks modes and samples of a reduced model; "
                         f"model.kind is {scene['model']['kind']!r}")
    cache = cache if cache is not None else PrecomputeCache()
    key = budget_key(scene)
    hit = cache.load("budget", key)
    if hit is not None:
        report = dict(hit[1], cached=True)
        (progress or (lambda m: None))(f"budget: {report['chosen']['modes']} modes per domain "
                                       f"(probe result from the cache)")
    else:
        report = probe(scene, progress, cache)
        cache.save("budget", key, {}, meta=json.loads(json.dumps(report, default=float)))
        report["cached"] = False
    return load_scene(scene, report["chosen"]["overrides"]), report


class Simulator(BaseSimulator):
    """`mdss_ros.Simulator`: mdss_ros.simulator.Simulator, with the scene's model.budget
    resolved first (from the cache, or probed once and cached). The automatic model of a
    scene without a `model` section has a budget, so this is the class users get."""

    def __init__(self, scene, overrides=None, progress=None, cache=None, budget=None):
        scene = load_scene(scene, overrides)
        if scene["model"].get("budget"):
            if budget is not None:
                raise SceneError(f"{scene.source}: a budget report was given with a scene whose "
                                 f"model.budget is not resolved; pass the scene resolve_budget returned")
            scene, budget = resolve_budget(scene, progress, cache)
        super().__init__(scene, progress=progress, cache=cache, budget=budget)


def build_simulator(scene, overrides=None, progress=None, cache=None):
    """A Simulator of a scene (Scene, path, name or dict) with its model.budget resolved
    first (probed once, then from the cache): what `mdss run`, the node and replay build."""
    return Simulator(scene, overrides, progress=progress, cache=cache)
