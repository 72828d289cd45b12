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

BUILT = ("energy", "coupling", "reduced", "cantilever", "modes", "cubature", "hertz")
NOT_BUILT = ()

# Material of every beam study unless a study says otherwise: a soft StVK rubber
# (the papers' material), 1 m x 0.1 m x 0.1 m, clamped at x = 0.
MATERIAL = {"model": "stvk", "young": 1.0e6, "poisson": 0.3, "density": 1000.0}
BEAM_SIZE = (1.0, 0.1, 0.1)

# Static equilibrium of a reduced model through its own step: backward Euler with a
# time step far above the slowest period (dt^2 K >> Mgen) and Newton iterations per step
# is Newton's method on the static problem with a tiny mass regularisation; the fixed
# point (zero velocity) is exactly the reduced static equilibrium.
STATIC_INTEGRATOR = {"scheme": "one_step", "dt": 10.0, "newton_iterations": 10, "tolerance": 1e-10}


class ReportError(RuntimeError):
    """A study could not produce its numbers (e.g. a static solve did not converge)."""


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
        q.append(dd.U.T @ (m * (ds.U @ qs)))
        qd.append(np.zeros(dd.r) if at_rest else dd.U.T @ (m * (ds.U @ qds)))
    md.q, md.qd = q, qd
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


def tip_rotation(X_tip, x_tip):
    """Rotation of the tip face: best-fit (polar) rotation of its vertices, as the total
    angle and the bending angle about y (x axis turned towards -z positive), in degrees."""
    A = (x_tip - x_tip.mean(0)).T @ (X_tip - X_tip.mean(0))
    U, _, Vt = np.linalg.svd(A)
    if np.linalg.det(U @ Vt) < 0:
        U[:, -1] *= -1
    R = U @ Vt
    total = np.degrees(np.arccos(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0)))
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


# ---------------------------------------------------------------------- cantilever
CANTILEVER = {"cells": [0.05, 0.025, 1.0 / 60.0, 0.0125], "quick_cells": [0.05, 0.025],
              "periods": 3.0, "steps_per_period": 100, "sag_gravity": 0.05,
              "reduced_cell": 0.025, "reduced": [[1, 6], [2, 12], [4, 12], [4, 20]],
              "quick_reduced": [[2, 12]]}


def _tip_deflection(sim):
    ids = sim.body.handles["tip"]
    return -float((sim.vertex_positions()[ids, 2] - sim.rest_positions()[ids, 2]).mean())


def _full_sag(cell, g, log):
    """Tip sag of the full-space beam under its own weight at gravity g (static)."""
    scene = beam_scene("full", cell=cell)
    scene["gravity"] = [0.0, 0.0, -g]
    sim = build_sim(scene)
    full_static(sim, (0.0, 0.0, 0.0))            # no tip load: gravity alone
    return _tip_deflection(sim)


def cantilever_report(out, quick=False, overrides=None, log=None):
    """Full-space FEM (StVK, lumped mass) at several resolutions and reduced models on one
    of them vs closed forms: static tip deflection under a small tip load and tip sag
    under a small gravity (Euler-Bernoulli + Timoshenko shear), first bending frequency
    (the eigenvalue of the model linearised at rest, verify/modes_study.py; for full FEM
    also measured from a free vibration, verify/cantilever.py). Reduced rows are also compared with full FEM
    on their own mesh, which is what the reduction alone costs."""
    from . import plotting
    from .cantilever import BEAM, beam_model, free_vibration_frequency, static_tip_deflection
    from .closed_forms import cantilever_gravity_sag
    from .modes_study import full_frequencies, reduced_frequencies
    cfg = study_config("cantilever", CANTILEVER, {}, quick, overrides)
    log = log or Progress("cantilever")
    cells = cfg["quick_cells"] if quick else cfg["cells"]
    g = float(cfg["sag_gravity"])
    sag_ref = cantilever_gravity_sag(BEAM["rho"], g, BEAM["L"], BEAM["E"], BEAM["b"], BEAM["h"], BEAM["nu"])
    rows = []
    for cell in cells:
        model, _ = beam_model(cell)
        t0 = time.perf_counter()
        w, w_ref = static_tip_deflection(cell)
        sag = _full_sag(cell, g, log)
        t1 = time.perf_counter()
        f_vib, f_ref = free_vibration_frequency(cell, periods=cfg["periods"], steps_per_period=cfg["steps_per_period"])
        f = float(full_frequencies(build_sim(beam_scene("full", cell=cell)), 1)[0])
        t2 = time.perf_counter()
        row = {"kind": "full", "frequency_free_vibration_hz": f_vib,
               "frequency_free_vibration_rel_error": (f_vib - f_ref) / f_ref, "config": f"full, cell {cell:.4g}", "cell": cell, "dofs": int(model.n_free),
               "tets": int(len(model.tets)),
               "tip_deflection": w, "tip_deflection_ref": w_ref, "static_rel_error": (w - w_ref) / w_ref,
               "sag": sag, "sag_ref": sag_ref, "sag_rel_error": (sag - sag_ref) / sag_ref,
               "frequency_hz": f, "frequency_ref_hz": f_ref, "frequency_rel_error": (f - f_ref) / f_ref,
               "static_s": t1 - t0, "frequency_s": t2 - t1}
        rows.append(row)
        log(f"cell {cell:.4g}: {row['dofs']} DOFs, tip {w:.5g} m vs {w_ref:.5g} m "
            f"({100 * row['static_rel_error']:+.2f} %), sag {sag:.5g} m vs {sag_ref:.5g} m "
            f"({100 * row['sag_rel_error']:+.2f} %), f1 {f:.4g} Hz (free vibration {f_vib:.4g}) vs {f_ref:.4g} Hz "
            f"({100 * row['frequency_rel_error']:+.2f} %) [{t2 - t0:.1f} s]")
    # Reduced models on one mesh, with full FEM on that mesh beside them.
    cell = float(cfg["reduced_cell"])
    full_same = next((r for r in rows if abs(r["cell"] - cell) < 1e-12), None)
    if full_same is None:
        w_full, _ = static_tip_deflection(cell)
        full_same = {"tip_deflection": w_full, "sag": _full_sag(cell, g, log),
                     "frequency_hz": float(full_frequencies(build_sim(beam_scene("full", cell=cell)), 1)[0])}
    w_ref, f_ref = rows[0]["tip_deflection_ref"], rows[0]["frequency_ref_hz"]
    P = 0.01
    for domains, modes in (cfg["quick_reduced"] if quick else cfg["reduced"]):
        t0 = time.perf_counter()
        label = f"reduced {domains} x {modes}, cell {cell:.4g}"
        model = dict(domains={"count": int(domains)}, modes=int(modes), integrator=dict(STATIC_INTEGRATOR))
        sim = build_sim(beam_scene("reduced", cell=cell, **model), log, label)
        f = float(reduced_frequencies(sim, 1)[0])
        reduced_static(sim, (0.0, 0.0, -P))
        w = _tip_deflection(sim)
        scene = beam_scene("reduced", cell=cell, **model)
        scene["gravity"] = [0.0, 0.0, -g]
        sim = build_sim(scene)
        reduced_static(sim, (0.0, 0.0, 0.0), ramp_steps=1)
        sag = _tip_deflection(sim)
        row = {"kind": "reduced", "config": label, "cell": cell, "domains": int(domains), "modes": int(modes),
               "dofs": int(sim.stats()["dofs"]), "tets": int(sim.stats()["tets"]),
               "tip_deflection": w, "tip_deflection_ref": w_ref, "static_rel_error": (w - w_ref) / w_ref,
               "sag": sag, "sag_ref": sag_ref, "sag_rel_error": (sag - sag_ref) / sag_ref,
               "frequency_hz": f, "frequency_ref_hz": f_ref, "frequency_rel_error": (f - f_ref) / f_ref,
               "vs_full": {"static": w / full_same["tip_deflection"] - 1, "sag": sag / full_same["sag"] - 1,
                           "frequency": f / full_same["frequency_hz"] - 1},
               "wall_s": time.perf_counter() - t0}
        rows.append(row)
        log(f"{label}: {row['dofs']} DOFs, tip {100 * row['static_rel_error']:+.2f} %, sag "
            f"{100 * row['sag_rel_error']:+.2f} %, f1 {100 * row['frequency_rel_error']:+.2f} % vs closed forms; "
            f"vs full FEM on the same mesh {100 * row['vs_full']['static']:+.2f} / {100 * row['vs_full']['sag']:+.2f} / "
            f"{100 * row['vs_full']['frequency']:+.2f} %")
    plots = [plotting.cantilever_errors(rows, Path(out) / "cantilever_errors.png")]
    pct = lambda v: f"{100 * v:+.2f}"        # noqa: E731
    table = format_table(["model", "DOFs", "tip (m)", "tip err %", "sag (m)", "sag err %", "f1 (Hz)", "f1 err %",
                          "vs full tip/sag/f1 %"],
                         [[r["config"], r["dofs"], r["tip_deflection"], pct(r["static_rel_error"]), r["sag"],
                           pct(r["sag_rel_error"]), r["frequency_hz"], pct(r["frequency_rel_error"]),
                           "/".join(pct(v) for v in r["vs_full"].values()) if "vs_full" in r else "-"]
                          for r in rows])
    return {"config": dict(cfg, beam=BEAM, quick=quick, cells_run=cells, static_load_N=P,
                           closed_forms={"tip_deflection_m": w_ref, "sag_m": sag_ref, "frequency_hz": f_ref},
                           frequency="eigenvalue at rest; full rows also from a free vibration with "
                           f"backward Euler, 1 Newton iteration, dt = T1 / {cfg['steps_per_period']}"),
            "rows": rows, "plots": plots, "table": table}


# ---------------------------------------------------------------------- registry
def _study(name):
    if name == "energy":
        from .energy_study import energy_report
        return energy_report
    if name == "coupling":
        from .coupling_study import coupling_report
        return coupling_report
    if name == "reduced":
        from .accuracy_study import accuracy_report
        return accuracy_report
    if name == "cantilever":
        return cantilever_report
    if name == "cubature":
        from .cubature_study import cubature_report
        return cubature_report
    if name == "modes":
        from .modes_study import modes_report
        return modes_report
    if name == "hertz":
        from .hertz_study import hertz_report
        return hertz_report
    raise KeyError(name)


def check_name(name):
    """Raise ReportError with a clear message for a report that is not available."""
    if name in BUILT or name == "all":
        return
    if name in NOT_BUILT:
        raise ReportError(f"verify report {name!r} is not built yet in this version "
                          f"(built: {', '.join(BUILT)}, all)")
    planned = f"; planned: {', '.join(NOT_BUILT)}" if NOT_BUILT else ""
    raise ReportError(f"unknown verify report {name!r} (available: {', '.join(BUILT)}, all{planned})")


def run_report(name, out, quick=False, overrides=None):
    """Run one report into directory `out`; returns its result dict (also in out/NAME.json)."""
    check_name(name)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    log = Progress(name)
    env_start = environment()
    log(f"start ({'quick' if quick else 'default'} run) -> {out}; load average {env_start['load_average']} "
        f"on {env_start['cpus']} CPUs")
    result = _study(name)(out, quick=quick, overrides=overrides, log=log)
    result["wall_s"] = log.elapsed()
    result["report"] = name
    result["environment"] = dict(environment(), load_average_start=env_start["load_average"])
    result["plots"] = [str(Path(p).name) for p in result.get("plots", [])]
    path = write_json(out, name, result)
    print(f"\n== mdss verify {name}: summary ==\n{result['table']}", flush=True)
    for note in result.get("notes", []):
        print(f"  note: {note}")
    load = lambda env: "?" if not env["load_average"] else f"{env['load_average'][0]:.2f}"    # noqa: E731
    print(f"wrote {path} and {', '.join(result['plots'])} ({result['wall_s']:.1f} s wall; 1-min load average "
          f"{load(env_start)} at start, {load(result['environment'])} at end, {os.cpu_count()} CPUs)\n", flush=True)
    return result


def run_reports(name, out, quick=False, overrides=None):
    """`mdss verify NAME`: one report, or all built ones for NAME == "all". Returns 0."""
    check_name(name)
    if name != "all":
        run_report(name, out, quick, overrides)
        return 0
    if overrides:
        raise ReportError("--set applies to one report; run the reports one by one to override settings")
    t0 = time.perf_counter()
    walls = {}
    for n in BUILT:
        walls[n] = run_report(n, out, quick)["wall_s"]
    print("== mdss verify all ==\n" + format_table(["report", "wall (s)"], [[n, w] for n, w in walls.items()])
          + f"\ntotal {time.perf_counter() - t0:.1f} s", flush=True)
    return 0
