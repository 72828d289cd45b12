"""`mdss` command line (docs/architecture.md, "Contracts: Command line"). Each command prints what it did."""
import argparse
import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from .scene import read_yaml


def _parse_sets(items):
    """--set model.modes=10 --set body.mesh.cell=0.02 -> {"model.modes": 10, ...} (values parsed as YAML)."""
    out = {}
    for item in items or []:
        if "=" not in item:
            raise SystemExit(f"mdss: --set expects KEY=VALUE, got {item!r}")
        k, v = item.split("=", 1)
        out[k.strip()] = read_yaml(v)
    return out


def _peak_rss_mb():
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _make_sim(args):
    from .budget import build_simulator
    from .errors import MdssError
    try:
        return build_simulator(args.scene, overrides=_parse_sets(args.set) or None)
    except MdssError as err:
        raise SystemExit(f"mdss: {err}")


def cmd_run(args):
    import signal
    from .errors import MdssError
    from .record.replay import RunRecording
    from .record.ros_messages import OutputRates
    # The node's driver runs the timeline (mdss_ros.ros.driver): inputs as the messages
    # the node would receive, checked and applied at their steps, the guarded step, a
    # failed step reset. With --mcap/--rrd the outputs are recorded (the files are opened
    # before the model build, so a bad path fails at once); without, none is built.
    # SIGINT/SIGTERM stop the run and finish the files.
    if not args.mcap_flush > 0:
        raise SystemExit(f"mdss run: --mcap-flush must be > 0 seconds, got {args.mcap_flush}")
    recording = bool(args.mcap or args.rrd)
    try:
        rec = RunRecording(mcap=args.mcap, rrd=args.rrd, flush_interval_s=args.mcap_flush,
                           rates=None if recording else OutputRates(0.0, 0.0, 0.0, 0.0, 0.0))
    except MdssError as err:
        raise SystemExit(f"mdss run: {err}")
    t0 = time.perf_counter()
    try:
        sim = rec.build(args.scene, _parse_sets(args.set))
    except MdssError as err:
        rec.finish()
        raise SystemExit(f"mdss run: {err}")
    st = sim.stats()
    print(f"mdss run: scene {sim.scene.name!r} ({sim.scene.source}): {st['kind']} model, "
          f"{st['vertices']} vertices, {st['tets']} tets, {st['dofs']} DOFs, "
          f"dt = {sim.dt:.6g} s, built in {time.perf_counter() - t0:.2f} s")
    for w in sim.scene.warnings:
        print(f"mdss run: warning: {w}")
    if args.explain:
        _print_explain(sim, "mdss run")
    steps = args.steps if args.steps is not None else int(round(sim.scene["duration"] / sim.dt))
    rec.start(sim)
    step_ms = []
    rest = sim.rest_positions()
    report_every = max(1, steps // 10)
    try:
        for k in range(steps):
            if rec.stop_requested:
                print(f"mdss run: {signal.Signals(rec.stop_signal).name} at step {k} (t = {sim.time:.3f} s); "
                      f"finishing the recording")
                steps = k
                break
            t_now = sim.time
            events, ok = rec.advance()
            for ev in events:
                print(f"  t = {t_now:7.3f} s  input {ev['topic']}: "
                      f"{ {k2: v for k2, v in ev.items() if k2 not in ('t', 'topic')} }")
            if not ok:
                continue                   # reported by the driver, which reset to t = 0
            step_ms.append(sim.stats()["step_ms"])
            x = sim.vertex_positions()
            if not np.all(np.isfinite(x)):
                raise SystemExit(f"mdss run: non-finite positions at step {k + 1} (t = {sim.time:.4f} s)")
            if (k + 1) % report_every == 0 or k + 1 == steps:
                disp = np.linalg.norm(x - rest, axis=1).max()
                e = sim.energy()
                print(f"  step {k + 1:6d}/{steps}  t = {sim.time:7.3f} s  max |u| = {disp:.5g} m  "
                      f"E_total = {e['total']:.6g} J  step {step_ms[-1]:.2f} ms")
    finally:
        for line in rec.finish():
            print(f"mdss run: {line}")
    wall = time.perf_counter() - t0
    summary = {
        "scene": sim.scene.name, "kind": st["kind"], "steps": steps, "sim_time": sim.time,
        "dofs": st["dofs"], "step_ms_median": float(np.median(step_ms)) if step_ms else None,
        "max_displacement": float(np.linalg.norm(sim.vertex_positions() - rest, axis=1).max()),
        "energy": sim.energy(), "wall_s": wall,
    }
    # The stability guard's run totals: a user should see at a glance whether it acted.
    last = sim.stats() if step_ms else {}
    summary["guard"] = {k: last[k] for k in ("guard_recoveries", "guard_degraded", "guard_failures",
                                             "guard_projections", "guard_untangles", "guard_last_event")
                        if k in last}
    median = f"{summary['step_ms_median']:.2f}" if step_ms else "-"
    print(f"mdss run: done, {steps} steps to t = {sim.time:.3f} s in {wall:.2f} s wall "
          f"(median step {median} ms)")
    if summary["guard"]:
        g = summary["guard"]
        print(f"mdss run: stability guard: {g.get('guard_recoveries', 0)} recovered, {g.get('guard_degraded', 0)} "
              f"degraded, {g.get('guard_failures', 0)} failed steps, {g.get('guard_untangles', 0)} untangles"
              + (f"; last event: {g['guard_last_event']}" if g.get("guard_last_event") else ""))
    if args.json:
        Path(args.json).write_text(json.dumps(summary, indent=2))
        print(f"mdss run: summary written to {args.json}")
    return 128 + rec.stop_signal if rec.stop_signal else 0


def _print_explain(sim, prefix):
    """Print Simulator.explain(): what the model took and why."""
    print(f"{prefix}: what was built and why:")
    for line in sim.explain():
        print(f"  {line}")


def cmd_replay(args):
    """`mdss replay LOG.mcap [--scene S] [--check]` (mdss_ros.record.replay). Exit 0: replayed
    (and with --check, every recorded output reproduced); 1: outputs differ; 2: bad file."""
    from .errors import MdssError
    from .record.replay import replay
    t0 = time.perf_counter()
    try:
        res = replay(args.log, scene=args.scene, overrides=_parse_sets(args.set), check=args.check)
    except MdssError as err:
        print(f"mdss replay: {err}", file=sys.stderr)
        return 2
    for w in res.warnings:
        print(f"mdss replay: warning: {w}")
    print(f"mdss replay: {args.log}: {res.inputs} inputs, {res.steps} steps to t = {res.sim_time:.3f} s "
          f"in {time.perf_counter() - t0:.2f} s")
    if not args.check:
        return 0
    for topic, (n, why) in res.not_compared.items():
        print(f"mdss replay: {topic}: {n} recorded message(s) not compared ({why})")
    if res.ok:
        print(f"mdss replay: check passed: {res.compared} recorded output messages reproduced bit for bit")
        return 0
    print(f"mdss replay: check FAILED: {res.mismatches} of {res.compared} output messages differ", file=sys.stderr)
    if res.first_mismatch:
        print(f"  first mismatch: {res.first_mismatch}", file=sys.stderr)
    for topic, n in res.missing.items():
        print(f"  {topic}: {n} recorded message(s) not reproduced", file=sys.stderr)
    for topic, n in res.extra.items():
        print(f"  {topic}: {n} replayed message(s) not in the recording", file=sys.stderr)
    return 1


COMPARE = [
    ("single domain", ["model.domains.count=1", "model.cubature.interface=exact"]),
    ("no interface cubature", ["model.cubature.interface=exact"]),
    ("full cubature", []),
    ("full space", ["model.kind=full"]),
]


def bench_compare(args):
    """The paper's Tables 3 and 4 on this machine: per-phase medians and frame rate for
    one domain (same modes per domain), domain cubature with exact interfaces, full
    cubature (the scene as written) and the full-space model, each in its own process."""
    rows = []
    print(f"mdss bench --compare {args.scene}: each configuration in its own process "
          f"(precompute is built or loaded first; --steps {args.steps})", flush=True)
    for label, sets in COMPARE:
        steps = args.steps if label != "full space" else min(args.steps, 3)
        out = Path(args.json or "bench_compare.json").with_suffix(f".{label.replace(' ', '_')}.json")
        cmd = [sys.executable, "-m", "mdss_ros.cli", "bench", args.scene, "--steps", str(steps), "--json", str(out)]
        for item in (args.set or []) + sets:
            cmd += ["--set", item]
        t0 = time.perf_counter()
        run = subprocess.run(cmd, capture_output=True, text=True)
        if run.returncode != 0:
            print(f"  {label}: failed\n{run.stderr[-1500:]}", flush=True)
            continue
        r = json.loads(out.read_text())
        m = r["median_ms"]
        row = {"config": label, "dofs": r["dofs"], "domains": r["domains"], "wall_s": time.perf_counter() - t0,
               "domain_ms": m.get("domain_ms", m.get("assembly_ms", float("nan"))),
               "coupling_ms": m.get("coupling_ms", 0.0),
               "factor_solve_ms": m.get("factor_ms", 0.0) + m.get("solve_ms", 0.0),
               "surface_ms": m["surface_ms"], "step_and_surface_ms": m["step_and_surface_ms"]}
        row["fps"] = 1000.0 / row["step_and_surface_ms"]
        rows.append(row)
        print(f"  {label:22s} done in {row['wall_s']:.0f} s", flush=True)
    print(f"\n  {'configuration':22s} {'DOFs':>7s} {'domains':>7s} {'domain':>9s} {'coupling':>9s} "
          f"{'fact+solve':>10s} {'surface':>8s} {'step+surf':>10s} {'fps':>7s}")
    for r in rows:
        print(f"  {r['config']:22s} {r['dofs']:7d} {r['domains']:7d} {r['domain_ms']:8.2f}ms {r['coupling_ms']:8.2f}ms "
              f"{r['factor_solve_ms']:9.2f}ms {r['surface_ms']:7.2f}ms {r['step_and_surface_ms']:9.2f}ms {r['fps']:7.1f}")
    print("  (full space: 'domain' is assembly; one Newton iteration per step)")
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=2))
        print(f"mdss bench: written {args.json}")
    return 0


def cmd_bench(args):
    if args.fem_scaling:
        return bench_fem_scaling(args)
    if args.compare:
        if not args.scene:
            raise SystemExit("mdss bench --compare needs a SCENE")
        return bench_compare(args)
    if not args.scene:
        raise SystemExit("mdss bench: give a SCENE or --fem-scaling")
    t0 = time.perf_counter()
    sim = _make_sim(args)
    build_s = time.perf_counter() - t0
    # As a node or `mdss run` does before its first step (threads.preload_kernels): a kernel first
    # called mid-run (the first contact's) is not loaded inside a timed step.
    from .threads import preload_kernels
    preload_kernels()
    load_before = os.getloadavg()[0]
    from .timeline import TimelinePlayer
    player = TimelinePlayer(sim.scene["timeline"])
    warm = min(3, args.steps)
    rows = []
    for k in range(warm + args.steps):
        player.apply_due(sim)
        c0 = time.process_time()
        sim.step()
        t_s = time.perf_counter()
        sim.surface_positions()       # what a publisher needs every frame
        surface_ms = 1e3 * (time.perf_counter() - t_s)
        cpu_ms = 1e3 * (time.process_time() - c0)
        if k >= warm:
            st = sim.stats()
            # CPU time of all the process's threads: unlike wall time it does not count
            # the waits for a core that other processes hold.
            rows.append(dict(st, surface_ms=surface_ms, step_and_surface_ms=st["step_ms"] + surface_ms,
                             cpu_step_and_surface_ms=cpu_ms))
    keys = [k for k, v in rows[0].items() if k.endswith("_ms")]
    med = {k: float(np.median([r[k] for r in rows])) for k in keys}
    total = np.array([r["step_and_surface_ms"] for r in rows])
    st = rows[-1]
    # A real-time loop cares about the slow steps too, and every timing depends on what
    # else runs: the load average before and after is part of the result.
    result = {"scene": sim.scene.name, "kind": st["kind"], "dofs": st["dofs"], "domains": st["domains"],
              "vertices": st["vertices"], "tets": st["tets"], "steps": args.steps,
              "build_s": build_s, "median_ms": med, "p90_step_and_surface_ms": float(np.percentile(total, 90)),
              "max_step_and_surface_ms": float(total.max()),
              "guard_actions": int(sum(1 for r in rows if r.get("guard_action"))),
              "load_average": [load_before, os.getloadavg()[0]], "peak_rss_mb": _peak_rss_mb()}
    print(f"mdss bench: {sim.scene.name} ({st['kind']}), {st['dofs']} DOFs, {st['tets']} tets, "
          f"{args.steps} steps after {warm} warm-up, build {build_s:.2f} s, peak RSS {result['peak_rss_mb']:.0f} MB, "
          f"load average {load_before:.1f} -> {result['load_average'][1]:.1f}")
    for k in keys:
        print(f"  {k[:-3]:>16s}: {med[k]:9.3f} ms median")
    print(f"  step + surface: p90 {result['p90_step_and_surface_ms']:.3f} ms, max "
          f"{result['max_step_and_surface_ms']:.3f} ms; steps where the guard acted: {result['guard_actions']}")
    if args.profile:
        result["profile"] = profile_steps(sim, player, args.profile)
        p = result["profile"]
        print(f"  profile over {p['steps']} more steps (step + surface): {p['python_calls_per_step']:.0f} Python "
              f"function calls and {p['c_calls_per_step']:.0f} calls into C (numpy, numba, builtins) per step; "
              f"by own time:")
        for f in p["top"]:
            print(f"    {f['own_ms_per_step']:8.3f} ms {f['calls_per_step']:8.1f} calls  {f['function']}")
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=2))
        print(f"mdss bench: written {args.json}")
    return 0


def profile_steps(sim, player, steps, top=15):
    """Where a step's Python time goes: the Python function calls and the calls into C
    (numpy, numba kernels, builtins) per step + surface, counted exactly by a profile hook
    over `steps` steps, then the functions with the most own time from cProfile over as
    many more (its overhead inflates the times; the ranking and the call counts are what
    to read). The compiled-step work aims at few calls per step, independent of domains."""
    import cProfile
    import pstats
    counts = {"call": 0, "c_call": 0}

    def hook(frame, event, arg):
        if event in counts:
            counts[event] += 1

    def run():
        for _ in range(steps):
            player.apply_due(sim)
            sim.step()
            sim.surface_positions()

    sys.setprofile(hook)
    try:
        run()
    finally:
        sys.setprofile(None)
    prof = cProfile.Profile()
    prof.runcall(run)
    stats = pstats.Stats(prof).stats             # {(file, line, name): (cc, nc, tt, ct, callers)}
    rows = sorted(stats.items(), key=lambda kv: -kv[1][2])[:top]
    root = str(Path(__file__).resolve().parent.parent)
    return {"steps": steps, "python_calls_per_step": counts["call"] / steps,
            "c_calls_per_step": counts["c_call"] / steps,
            "top": [{"function": f"{fn.replace(root + '/', '')}:{line}({name})",
                     "own_ms_per_step": 1e3 * tt / steps, "calls_per_step": nc / steps}
                    for (fn, line, name), (cc, nc, tt, ct, _) in rows]}


def bench_fem_one(n_tets_target, iterations=5):
    """Time the phases of one Newton iteration of the full-space solver on a clamped beam
    of about n_tets_target tets (StVK). Runs in its own process so peak memory is its own."""
    from .fem.backward_euler import BackwardEuler, NewtonSettings
    from .fem.force_model import FEMForceModel
    from .fem.materials import make_material
    from .mesh import box, select_vertices
    # Beam 4:1:1 with cubic cells split into 6 tets: 6 * 4n * n * n tets.
    n = max(1, int(round((n_tets_target / 24.0) ** (1.0 / 3.0))))
    t0 = time.perf_counter()
    mesh = box(size=(4.0, 1.0, 1.0), cell=1.0 / n)
    pinned = select_vertices(mesh.vertices, {"box": [[-1e-9, -1, -1], [1e-9, 2, 2]]})
    mat = make_material({"model": "stvk", "young": 1e6, "poisson": 0.3, "density": 1000})
    model = FEMForceModel(mesh.vertices, mesh.tets, mat, pinned)
    model.M                         # the pattern and mass matrix are made on first use: count them in the build
    build_s = time.perf_counter() - t0
    integ = BackwardEuler(model, 1.0 / 90.0, NewtonSettings(max_iterations=1))
    f_ext = model.vertex_mass[:, None] * np.array([0.0, 0.0, -9.81])
    x, v = mesh.vertices.copy(), np.zeros_like(mesh.vertices)
    x, v = integ.step(x, v, f_ext)  # JIT warm-up and first analysis
    rows = []
    for _ in range(iterations):
        x, v = integ.step(x, v, f_ext)
        rows.append(dict(integ.stats, **model.timings))
    med = {k: float(np.median([r[k] for r in rows])) for k in rows[0] if k.endswith("_ms")}
    return {"tets": int(len(mesh.tets)), "vertices": int(len(mesh.vertices)), "dofs": int(model.n_free),
            "nnz": int(model.pattern.nnz), "build_s": build_s, "solver": integ.solver.backend,
            "median_ms": med, "newton_iteration_ms": med["assembly_ms"] + med["factor_ms"] + med["solve_ms"],
            "peak_rss_mb": _peak_rss_mb(), "iterations": iterations}


def bench_fem_scaling(args):
    sizes = [int(s) for s in args.fem_sizes.split(",")]
    results = []
    print(f"mdss bench --fem-scaling: full-space StVK, one Newton iteration per step, sizes {sizes} tets "
          f"(each size in its own process for its own peak memory)", flush=True)
    print(f"  {'tets':>8s} {'DOFs':>8s} {'element':>9s} {'scatter':>9s} {'assembly':>9s} {'factor':>9s} "
          f"{'solve':>8s} {'iter':>9s} {'peak MB':>8s}")
    for n in sizes:
        out = subprocess.run([sys.executable, "-m", "mdss_ros.cli", "_bench_fem_one", str(n)],
                             capture_output=True, text=True)
        if out.returncode != 0:
            raise SystemExit(f"mdss bench: size {n} failed:\n{out.stderr[-2000:]}")
        r = json.loads(out.stdout.strip().splitlines()[-1])
        m = r["median_ms"]
        print(f"  {r['tets']:8d} {r['dofs']:8d} {m['element_ms']:8.1f}ms {m['scatter_ms']:8.1f}ms "
              f"{m['assembly_ms']:8.1f}ms {m['factor_ms']:8.1f}ms {m['solve_ms']:7.1f}ms "
              f"{r['newton_iteration_ms']:8.1f}ms {r['peak_rss_mb']:8.0f}", flush=True)
        results.append(r)
    print("  element = F, P, dP/dF and element matrices (numba, all tets); scatter = sum into CSR; "
          "assembly = both plus residual; factor = sparse Cholesky analyse+factor (backend in the JSON); solve = triangular solves")
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=2))
        print(f"mdss bench: written {args.json}")
    return 0


def cmd_verify(args):
    """`mdss verify NAME --out DIR [--quick] [--set KEY=VALUE]`: reports in verify/reduced_reports.py."""
    from .errors import ReportError
    from .verify.reports import run_reports
    try:
        return run_reports(args.name, args.out, quick=args.quick, overrides=_parse_sets(args.set))
    except ReportError as err:
        raise SystemExit(f"mdss verify: {err}")


def cmd_tradeoff(args):
    """`mdss tradeoff SCENE --out DIR [--quick] [--set KEY=VALUE]`: verify/tradeoff.py."""
    from .errors import MdssError
    from .errors import ReportError
    from .verify.tradeoff import run_tradeoff
    try:
        if getattr(args, "levels", None) or getattr(args, "free_body", False):
            from .verify.peers_limbed import LOAD_LEVELS, limbed_levels_report
            from .verify.limbed_free import limbed_free_report
            sets = _parse_sets(args.set)
            if args.levels:
                levels = list(LOAD_LEVELS) if args.levels == "all" else [v for v in args.levels.split(",") if v]
                limbed_levels_report(args.scene, args.out, levels=levels, quick=args.quick, sets=dict(sets))
            if args.free_body:
                limbed_free_report(args.scene, args.out, quick=args.quick, sets=dict(sets))
            return 0
        run_tradeoff(args.scene, args.out, quick=args.quick, sets=_parse_sets(args.set))
    except (MdssError, ReportError) as err:
        raise SystemExit(f"mdss tradeoff: {err}")
    return 0


def cmd_stability(args):
    """`mdss stability --out DIR [--quick]`: the stability matrix (verify/stability_study.py)."""
    from .verify.stability_study import KINDS, MATERIALS, run_study
    kinds = args.kinds.split(",") if args.kinds else None
    materials = args.materials.split(",") if args.materials else None
    for given, allowed, what in ((kinds, KINDS, "--kinds"), (materials, MATERIALS, "--materials")):
        bad = sorted(set(given or []) - set(allowed))
        if bad:
            raise SystemExit(f"mdss stability: {what}: unknown {bad} (allowed: {', '.join(allowed)})")
    report = run_study(args.out, quick=args.quick, kinds=kinds, materials=materials,
                       log=lambda msg: print(msg, flush=True), contact_only=args.contact_only)
    return 0 if not any(c.get("failed") for c in report["counts"].values()) else 1


def cmd_precompute(args):
    """Build (or load) a scene's precompute with progress, then summarise the cache."""
    from .errors import MdssError
    from .budget import build_simulator
    from .precompute import PrecomputeCache
    cache = PrecomputeCache(args.cache_dir) if args.cache_dir else PrecomputeCache()
    t0 = time.perf_counter()
    start = time.perf_counter()

    def progress(msg):
        print(f"  [{time.perf_counter() - start:7.1f} s] {msg}", flush=True)

    print(f"mdss precompute: cache folder {cache.folder}")
    try:
        sim = build_simulator(args.scene, overrides=_parse_sets(args.set) or None, progress=progress, cache=cache)
    except MdssError as err:
        raise SystemExit(f"mdss precompute: {err}")
    total = time.perf_counter() - t0
    st = sim.stats()
    print(f"mdss precompute: scene {sim.scene.name!r}: {st['kind']} model, {st['vertices']} vertices, "
          f"{st['tets']} tets, {st['dofs']} DOFs, {st['domains']} domains, ready in {total:.2f} s")
    for stage, kind, where in cache.events:
        size = ""
        if kind in ("hit", "saved") and Path(where).exists():
            size = f" ({Path(where).stat().st_size / 1e6:.2f} MB)"
        print(f"  {stage:9s} {kind:8s} {where}{size}")
    info = getattr(sim.model, "cubature_info", None)
    if info and info.get("samples"):
        for k, d in enumerate(info.get("domains", [])):
            print(f"  cubature domain {k}: {d['samples']} of {d['elements']} elements, "
                  f"held-out error {d.get('held_out_error', float('nan')):.2e}")
    _print_explain(sim, "mdss precompute")
    if args.json:
        Path(args.json).write_text(json.dumps({"scene": sim.scene.name, "seconds": total,
                                               "events": cache.events, "stats": st,
                                               "explain": sim.explain()}, indent=2, default=str))
    return 0


def main(argv=None):
    parser = argparse.ArgumentParser(prog="mdss", description="multi-domain subspace simulation tools")
    sub = parser.add_subparsers(dest="cmd", required=True)

    def scene_args(p, required=True):
        p.add_argument("scene", nargs=None if required else "?", help="scene file or name in msg_scenes/")
        p.add_argument("--set", action="append", metavar="KEY=VALUE",
                       help="override a scene key, e.g. --set model.kind=full --set body.mesh.cell=0.02")

    p = sub.add_parser("run", help="run a scene headless (no ROS), playing its timeline")
    scene_args(p)
    p.add_argument("--steps", type=int, help="number of steps (default: scene duration / dt)")
    p.add_argument("--mcap", help="record an MCAP file")
    p.add_argument("--mcap-flush", type=float, default=0.5, metavar="SECONDS",
                   help="wall seconds between MCAP chunk flushes: at most about this much is lost if "
                        "the run is killed or the disk fills (default 0.5)")
    p.add_argument("--rrd", help="record a rerun .rrd file")
    p.add_argument("--json", help="write a JSON summary here")
    p.add_argument("--explain", action="store_true",
                   help="print what the model took and why (domains, pins, rigid DOFs, cubature, contact, outputs)")
    p.set_defaults(func=cmd_run)

    p = sub.add_parser("replay", help="replay a recorded run's inputs headless; --check compares its outputs")
    p.add_argument("log", metavar="LOG.mcap", help="an MCAP recorded by mdss run --mcap")
    p.add_argument("--scene", help="scene to replay in (default: the scene stored in the recording)")
    p.add_argument("--set", action="append", metavar="KEY=VALUE", help="override a key of --scene")
    p.add_argument("--check", action="store_true",
                   help="compare every recorded output message with the replayed one, byte for byte")
    p.set_defaults(func=cmd_replay)

    p = sub.add_parser("precompute", help="build a scene's bases and cubature into the cache, with progress")
    scene_args(p)
    p.add_argument("--cache-dir", help="cache folder (default $MDSS_CACHE_DIR or ~/.cache/mdss_ros)")
    p.add_argument("--json", help="write a summary here")
    p.set_defaults(func=cmd_precompute)

    p = sub.add_parser("bench", help="time the step phases of a scene, or the full-space FEM scaling")
    scene_args(p, required=False)
    p.add_argument("--steps", type=int, default=20)
    p.add_argument("--json", help="write results here")
    p.add_argument("--fem-scaling", action="store_true", help="full-space Newton iteration cost vs mesh size")
    p.add_argument("--compare", action="store_true",
                   help="Tables 3/4: single domain, no interface cubature, full cubature, full space")
    p.add_argument("--fem-sizes", default="10000,50000,240000", help="tet counts for --fem-scaling")
    p.add_argument("--profile", type=int, default=0, metavar="N",
                   help="also count Python calls per step over N more steps and list where the time goes")
    p.set_defaults(func=cmd_bench)

    p = sub.add_parser("verify", help="verification reports (JSON + PNG plots into --out)")
    p.add_argument("name", help="energy, coupling, reduced, cantilever, modes, cubature, hertz, meshless, contact, friction or all")
    p.add_argument("--out", required=True, help="output directory")
    p.add_argument("--quick", action="store_true", help="a small version of the report")
    p.add_argument("--set", action="append", metavar="KEY=VALUE",
                   help="override a study setting, e.g. --set horizon=0.5 (one report only)")
    p.set_defaults(func=cmd_verify)

    p = sub.add_parser("tradeoff", help="speed vs accuracy sweep of a scene's model against full-space FEM "
                                        "(JSON, Pareto PNG, table; MuJoCo flex peers for a clamped beam "
                                        "or a limbed body such as star_limbs)")
    p.add_argument("scene", help="scene file or name in msg_scenes/")
    p.add_argument("--out", required=True, help="output directory")
    p.add_argument("--quick", action="store_true", help="a few configurations over 1 s (the slow test)")
    p.add_argument("--set", action="append", metavar="KEY=VALUE",
                   help="tradeoff.NAME=V changes a study setting (horizon, warmup, probe_every, "
                        "truth_newton_iterations, truth_tolerance, truth_element (linear | quadratic tets), "
                        "variants, peers, peers_only: the MuJoCo peer comparison alone); other keys override "
                        "the scene")
    p.add_argument("--levels", metavar="LIST",
                   help="limbed body only (star_limbs): instead of the sweep, the static peer study at the load "
                        "levels LIST of small,medium,large (or all), one table and Pareto plot per level "
                        "(verify/peers_limbed.py; --quick: two of our rows and MuJoCo's quadratic flex)")
    p.add_argument("--free-body", action="store_true",
                   help="limbed body only: the body with its pins removed and torques on every arm's handle, "
                        "error over time against full FEM (verify/limbed_free.py)")
    p.set_defaults(func=cmd_tradeoff)

    p = sub.add_parser("stability", help="stability matrix: material x stiffness x dt x spin x force "
                                          "(JSON + heat maps into --out)")
    p.add_argument("--out", required=True, help="output directory")
    p.add_argument("--quick", action="store_true", help="one-at-a-time cells around the base point, fewer steps")
    p.add_argument("--kinds", help="comma-separated model kinds of full,reduced,meshless (default: full,reduced; "
                                   "the meshless model runs with one material, its own law)")
    p.add_argument("--materials", help="comma-separated materials (default: stvk,corotated,neohookean)")
    p.add_argument("--contact-only", action="store_true", help="only the contact cells (friction x sphere speed "
                                                              "x stiffness)")
    p.set_defaults(func=cmd_stability)

    p = sub.add_parser("_bench_fem_one", help=argparse.SUPPRESS)
    p.add_argument("n", type=int)
    p.set_defaults(func=lambda a: print(json.dumps(bench_fem_one(a.n))) or 0)

    args = parser.parse_args(argv)
    return args.func(args)


if __name__ == "__main__":
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    sys.exit(main())
