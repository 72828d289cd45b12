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

The choice is stored in the precompute cache (stage "budget", keyed by the scene and the
code), so a second start does not probe again; its report says what was chosen and why,
and Simulator.explain() / stats()["budget"] show it. Timings are of this machine under
its current load: a probe on a busy machine picks fewer modes.
"""
import copy
import json
import math
import time

from .errors import SceneError
from .precompute import PrecomputeCache, cache_key
from .scene import BUDGET_DEFAULT_MODES as DEFAULT_MODES, check_budget, load_scene  # noqa: F401

def candidate_overrides(model, modes):
    """Scene overrides of the candidate with `modes` per domain: cubature samples scaled
    with the modes in the scene's ratio (exact stays exact); the budget switched off."""
    cub = copy.deepcopy(model.get("cubature") or {})
    base_r = int(model["modes"])
    for key in ("samples", "interface_samples"):
        n = cub.get(key)
        if isinstance(n, int) and not isinstance(n, bool) and n > 0:
            cub[key] = max(1, int(math.ceil(n * modes / base_r)))
    return {"model.modes": int(modes), "model.cubature": cub, "model.budget": {}}


def _settings(budget, scene):
    horizon = float(budget.get("horizon") or min(1.0, float(scene["duration"])))
    return {"horizon": horizon, "warmup": 3, "probe_every": 1.0 / 15.0 if horizon >= 0.2 else scene.dt,
            "truth_newton_iterations": 30, "truth_tolerance": 1e-8}


def probe(scene, progress=None, cache=None):
    """Walk the candidate ladder of a scene with a budget. Returns the report dict:
    {"goal", "target", "chosen": {"modes", "overrides"}, "met": bool, "candidates": [...],
    "horizon", "seconds"}."""
    from .accuracy import ground_truth, metrics, play
    from .simulator import Simulator
    say = progress or (lambda msg: None)
    budget = scene["model"]["budget"]
    goal = "ms_per_step" if "ms_per_step" in budget else "max_error"
    target = float(budget[goal])
    cfg = _settings(budget, scene)
    t0 = time.perf_counter()
    plain = _without_budget(scene)
    truth = None
    if goal == "max_error":
        say(f"budget: ground truth for the error probe (full space, {cfg['horizon']:.3g} s of the timeline)")
        truth = ground_truth(plain, {}, scene.dt, cfg, say)
    rows = []
    chosen = None
    for r in budget["modes"]:
        ov = candidate_overrides(scene["model"], r)
        sim = Simulator(plain, overrides=ov, cache=cache)
        rec = play(sim, cfg["horizon"], cfg["probe_every"], cfg["warmup"], truth=truth)
        row = {"modes": int(r), "dofs": int(sim.stats()["dofs"]), "step_ms": rec["step_ms"],
               "samples": ov["model.cubature"].get("samples", 0)}
        if truth is not None:
            row["rms_rel"] = metrics(rec, truth).get("rms_rel", float("nan"))
        rows.append(row)
        say(f"budget: {r} modes per domain: {row['dofs']} DOFs, {row['step_ms']:.3g} ms/step"
            + (f", RMS surface error {100 * row['rms_rel']:.3g} %" if "rms_rel" in row else ""))
        if goal == "ms_per_step":
            if row["step_ms"] <= target:
                chosen = row
            else:
                break                      # more modes cost more
        elif row["rms_rel"] <= target:
            chosen = row
            break                          # the cheapest within the error
    met = chosen is not None
    if not met:                            # nothing fits: the cheapest (ms) or the most accurate (error)
        chosen = rows[0] if goal == "ms_per_step" else min(rows, key=lambda x: x.get("rms_rel", math.inf))
    report = {"goal": goal, "target": target, "met": met, "chosen": {"modes": chosen["modes"],
              "overrides": candidate_overrides(scene["model"], chosen["modes"])},
              "candidates": rows, "horizon": cfg["horizon"], "seconds": time.perf_counter() - t0}
    say(f"budget: chose {chosen['modes']} modes per domain "
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


def build_simulator(scene, overrides=None, progress=None, cache=None):
    """A Simulator of a scene (Scene, path, name or dict) with its model.budget resolved
    first (probed once, then from the cache): what `mdss run`, the node and replay build."""
    from .simulator import Simulator
    scene = load_scene(scene, overrides)
    scene, report = resolve_budget(scene, progress, cache)
    return Simulator(scene, progress=progress, cache=cache, budget=report)
