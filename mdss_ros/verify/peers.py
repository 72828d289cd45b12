"""Peers a user would pick instead, on the clamped beam (issue 9): MuJoCo's flex.

MuJoCo (`pip install -r requirements-peers.txt`, mujoco==4.0.0) models a deformable
solid as a `flexcomp`: a grid of vertices and linear tets with an elasticity model
(`<elasticity young poisson damping>`), whose vertices either are degrees of freedom
themselves (dof="full") or are interpolated from a few nodes: dof="trilinear" (2x2x2
nodes) or dof="quadratic" (3x3x3 nodes, triquadratic shape functions over the whole
box): a fixed subspace, MuJoCo's counterpart of our reduced model. Nodes on the x = 0
face are pinned (`<pin gridrange>`), so the quadratic beam keeps 18 free nodes (54
DOFs). MuJoCo 4.0 refuses flex elasticity under the implicit integrators; the
`discrete` integrator is used (the one its error message recommends).

The comparison (beam_peer_comparison), in one run, for the scene's beam (length L along
x, b x h section, its material, clamped at x = 0, gravity along -z):

    static gravity sag of the tip face (mean z displacement of the x = L vertices),
        against the closed form (Euler-Bernoulli + Timoshenko shear, closed_forms.py) and
        against our full-space FEM static equilibrium on the same mesh (Newton statics);
        for rows on the scene's vertex grid also the RMS surface error vs that FEM state
        (reduced_reports.surface_error: MuJoCo's grid is the same 41 x 5 x 5 lattice);
    cost: median ms per step at the scene's dt under gravity from rest (MuJoCo: mj_step;
        ours: Simulator.step), measured in the same process, under the same load: every
        row once when built, then in `timing_rounds` round-robin passes; the smallest
        median is kept (step_ms_passes holds them all).

Statics: MuJoCo is stepped with a heavier elastic damping until every velocity is below
1e-9 (damping does not move the equilibrium); our reduced model is stepped with its dt
raised to 10 s and 10 Newton iterations per step (backward Euler far beyond the slowest
period is Newton on the static problem, reduced_reports.STATIC_INTEGRATOR) until the
largest vertex increment is below 1e-9 of the displacement; the same built model (same
bases and cubature) as the timed one.
"""
import time
from pathlib import Path

import numpy as np

from ..precompute import PrecomputeCache
from ..scene import load_scene
from .closed_forms import cantilever_gravity_sag
from .reduced_reports import ReportError, format_table, surface_error

MUJOCO_VERSION = "4.0.0"
INSTALL_HINT = ("MuJoCo is not installed: the peer rows are skipped. Install the peers with "
                "`pip install -r requirements-peers.txt` (mujoco==" + MUJOCO_VERSION + ") and run again.")


def mujoco_module():
    """(module, None) when `import mujoco` works, else (None, the reason and the install hint)."""
    try:
        import mujoco
    except Exception as err:          # ImportError, or a broken binary wheel (OSError)
        return None, f"{INSTALL_HINT} ({type(err).__name__}: {err})"
    return mujoco, None


# ---------------------------------------------------------------------- the beam
def is_clamped_box_beam(scene):
    """True for a scene whose body is a box mesh with its x = 0 face pinned, gravity along z."""
    mesh = scene["body"]["mesh"]
    g = np.asarray(scene["gravity"])
    if mesh.get("generator") != "box" or not scene["pins"] or np.any(g[:2] != 0.0) or g[2] >= 0.0:
        return False
    from ..body import build_body
    body = build_body(scene)
    X = body.vertices
    face = np.flatnonzero(np.abs(X[:, 0] - X[:, 0].min()) <= 1e-9)
    return np.array_equal(np.sort(body.pinned), face)


def beam_geometry(scene):
    """Dimensions, material and vertex lattice of a clamped box beam scene."""
    from ..body import build_body
    body = build_body(scene)
    X = body.vertices
    lo, hi = X.min(0), X.max(0)
    counts = [len(np.unique(np.round(X[:, a], 9))) for a in range(3)]
    mat = scene["body"]["material"]
    return {"L": float(hi[0] - lo[0]), "b": float(hi[1] - lo[1]), "h": float(hi[2] - lo[2]), "origin": lo,
            "counts": counts, "E": float(mat["young"]), "nu": float(mat["poisson"]),
            "rho": float(mat["density"]), "g": float(-scene["gravity"][2]), "dt": float(scene.dt),
            "beta": float(scene["body"]["damping"]["beta"]), "material": mat.get("model")}


def closed_form_sag(geo):
    """Tip sag under self weight: Euler-Bernoulli + Timoshenko shear (m, positive down)."""
    return cantilever_gravity_sag(geo["rho"], geo["g"], geo["L"], geo["E"], geo["b"], geo["h"], geo["nu"])


def flex_beam_xml(geo, dof, damping):
    """MJCF of the beam as a flexcomp grid with the scene's vertex lattice, mass and
    material, pinned on its x = 0 face. dof: full, trilinear or quadratic."""
    nx, ny, nz = geo["counts"]
    size = np.array([geo["L"], geo["b"], geo["h"]])
    spacing = size / (np.array(geo["counts"]) - 1)
    centre = geo["origin"] + size / 2
    mass = geo["rho"] * size.prod()
    grid = {"full": (nx, ny, nz), "trilinear": (2, 2, 2), "quadratic": (3, 3, 3)}[dof]
    pin = f"0 0 0 0 {grid[1] - 1} {grid[2] - 1}"
    f = lambda *v: " ".join(f"{float(a):.12g}" for a in v)        # noqa: E731
    return f"""<mujoco model="mdss_beam_{dof}">
  <option timestep="{f(geo['dt'])}" gravity="0 0 {f(-geo['g'])}" integrator="discrete" solver="Newton"/>
  <worldbody>
    <flexcomp name="beam" type="grid" dim="3" dof="{dof}" count="{nx} {ny} {nz}"
              spacing="{f(*spacing)}" pos="{f(*centre)}"
              mass="{f(mass)}" radius="0.001">
      <contact contype="0" conaffinity="0" selfcollide="none"/>
      <elasticity young="{f(geo['E'])}" poisson="{f(geo['nu'])}" damping="{f(damping)}"/>
      <pin gridrange="{pin}"/>
    </flexcomp>
  </worldbody>
</mujoco>"""


def mujoco_flex_beam(mj, geo, dof, timing_steps=60, warmup=5, settle_damping=0.05, settle_max=3000):
    """Cost and static sag of MuJoCo's flex beam.

    Returns {"dof", "nv", "nodes", "step_ms" (median mj_step at the scene dt, elastic damping
    = the scene's Rayleigh beta), "X" (n, 3) rest and "x" (n, 3) static vertex positions,
    "settle_steps", "settled"}."""
    # MuJoCo's warnings go to its log file in the working directory and to stdout; keep
    # them with the row instead (the full flex warns that its M + K solve is ill-conditioned).
    warnings = []
    previous = mj.get_mju_user_warning()
    mj.set_mju_user_warning(lambda msg: warnings.append(str(msg)))
    try:
        return _flex_beam_run(mj, geo, dof, timing_steps, warmup, settle_damping, settle_max, warnings)
    finally:
        mj.set_mju_user_warning(previous)


def mujoco_step_timer(mj, model, data, timing_steps, warmup):
    """timer(steps=timing_steps): median ms of `steps` mj_step calls after `warmup`
    untimed ones, continuing the motion of `data`."""
    def timer(steps=timing_steps):
        ms = np.empty(warmup + steps)
        for k in range(len(ms)):
            t0 = time.perf_counter()
            mj.mj_step(model, data)
            ms[k] = 1e3 * (time.perf_counter() - t0)
        return float(np.median(ms[warmup:]))
    return timer


def mujoco_settle(mj, model, data, settle_max):
    """Step until every velocity is below 1e-9 (checked every 10 steps) or settle_max
    steps. Returns (settled, steps)."""
    k = 0
    for k in range(1, settle_max + 1):
        mj.mj_step(model, data)
        if k % 10 == 0 and float(np.abs(data.qvel).max()) < 1e-9:
            return True, k
    return False, k


def _flex_beam_run(mj, geo, dof, timing_steps, warmup, settle_damping, settle_max, warnings):
    model = mj.MjModel.from_xml_string(flex_beam_xml(geo, dof, geo["beta"]))
    data = mj.MjData(model)
    mj.mj_forward(model, data)
    X = np.array(data.flexvert_xpos)
    timer = mujoco_step_timer(mj, model, data, timing_steps, warmup)
    step_ms = timer()
    ok = bool(np.all(np.isfinite(data.qpos)))
    static = mj.MjModel.from_xml_string(flex_beam_xml(geo, dof, settle_damping))
    sd = mj.MjData(static)
    settled, k = mujoco_settle(mj, static, sd, settle_max)
    x = np.array(sd.flexvert_xpos)
    return {"dof": dof, "nv": int(model.nv), "nodes": int(model.nflexnode) or int(model.nflexvert),
            "step_ms": step_ms, "finite": ok and bool(np.all(np.isfinite(x))),
            "X": X, "x": x, "settle_steps": k, "settled": settled, "timer": timer,
            "warnings": sorted(set(w.split(" Time =")[0] for w in warnings))}


class _Positions:
    """A Simulator stand-in for surface_error: our body, other positions (n_verts, 3)."""

    def __init__(self, body, x):
        self.body = body
        self._x = x

    def rest_positions(self):
        return self.body.vertices

    def surface_positions(self):
        return self._x[self.body.surface.vertex_ids]


def match_vertices(X_ours, X_other, tol=1e-7):
    """Index (n,) into X_other of each of our rest vertices (same lattice), or None."""
    from scipy.spatial import cKDTree
    if len(X_ours) != len(X_other):
        return None
    d, idx = cKDTree(X_other).query(X_ours)
    return idx if float(d.max()) <= tol else None


# ---------------------------------------------------------------------- ours
def ours_static_sag(sim, tol=1e-9, max_steps=40, loads=None):
    """Static equilibrium of a built reduced Simulator under gravity (see the module
    docstring); the model's dt and Newton settings are restored after. loads: called with
    sim after its reset to apply held loads (e.g. sim.set_wrench). Returns x (n, 3)."""
    m = sim.model
    saved = (m.dt, m.newton_iterations, m.tolerance)
    sim.reset()
    if loads is not None:
        loads(sim)
    m.set_dt(10.0)
    m.newton_iterations, m.tolerance = 10, 1e-10
    X = sim.rest_positions()
    prev = X.copy()
    try:
        for _ in range(max_steps):
            sim.step()
            x = sim.vertex_positions()
            if not np.all(np.isfinite(x)):
                raise ReportError("reduced static solve: non-finite state")
            inc = float(np.abs(x - prev).max())
            prev = x.copy()
            if inc <= tol * max(float(np.linalg.norm(x - X, axis=1).max()), 1e-300):
                return x.copy()
        raise ReportError(f"reduced static solve: no convergence in {max_steps} steps (last increment {inc:.3g} m)")
    finally:
        m.set_dt(saved[0])
        m.newton_iterations, m.tolerance = saved[1], saved[2]
        sim.reset()


def ours_fem_static(sim):
    """Full-space static equilibrium under the scene's gravity (Newton statics). Returns
    (x (n, 3), info)."""
    from ..fem.statics import static_equilibrium
    best = None
    for steps in (1, 3):
        x, info = static_equilibrium(sim.model.force_model, sim.external_forces(), tol=1e-9,
                                     max_iterations=30, load_steps=steps)
        if best is None or info["residual"] < best[1]["residual"]:
            best = (x, info)
        if info["converged"]:
            break
    if best[1]["residual"] > 1e-6:
        raise ReportError(f"full-space gravity statics did not converge: {best[1]}")
    return best


def median_ms_from_rest(sim, steps, warmup=5):
    """Median Simulator step_ms under gravity only (no timeline), from rest."""
    sim.reset()
    ms = []
    for k in range(warmup + steps):
        sim.step()
        if k >= warmup:
            ms.append(sim.stats()["step_ms"])
    out = float(np.median(ms))
    sim.reset()
    return out


def tip_sag(X, x, L):
    """Mean downward displacement of the vertices on the x = L face (m)."""
    tip = np.abs(X[:, 0] - X[:, 0].max()) <= 1e-9 * max(L, 1.0)
    return -float((x[tip, 2] - X[tip, 2]).mean())


# ---------------------------------------------------------------------- the comparison
OURS = [("mdss reduced: scene config", {}),
        ("mdss reduced: 1 domain", {"model.domains": {"count": 1}, "model.cubature.interface": "exact"}),
        ("mdss reduced: 1 domain, r/2", "half_modes")]
OURS_FINE = [("mdss reduced: 1 domain, cell/2", {"model.domains": {"count": 1}, "model.cubature.interface": "exact"}),
             ("mdss reduced: scene config, cell/2", {})]


def beam_peer_comparison(scene_src, base_overrides, out, quick=False, log=print, timing_steps=60, timing_rounds=3):
    """MuJoCo flex (quadratic, full) vs our full-space FEM and reduced configurations on
    the scene's clamped beam; see the module docstring. Returns a dict with rows, table,
    summary lines and the PNG path (or "skipped" when MuJoCo is missing)."""
    from ..simulator import Simulator
    scene = load_scene(scene_src, dict(base_overrides or {}, **{"model.kind": "reduced"}))
    geo = beam_geometry(scene)
    ref = closed_form_sag(geo)
    log(f"peers: beam L = {geo['L']:g} m, {geo['b']:g} x {geo['h']:g} m, E = {geo['E']:g} Pa, nu = {geo['nu']:g}, "
        f"rho = {geo['rho']:g}, g = {geo['g']:g}, dt = {geo['dt']:.6g} s; closed-form sag {ref:.5g} m")
    rows = []
    result = {"geometry": {k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in geo.items()},
              "closed_form_sag": ref, "closed_form": "Euler-Bernoulli + Timoshenko shear (Cowper kappa)",
              "rows": rows}

    # Our full-space FEM on the scene mesh: the same-mesh reference and the full-space row.
    full = Simulator(load_scene(scene_src, dict(base_overrides or {}, **{"model.kind": "full",
                                                "model.integrator.newton_iterations": 1})))
    t0 = time.perf_counter()
    x_fem, info = ours_fem_static(full)
    body = full.body
    fem_sag = tip_sag(body.vertices, x_fem, geo["L"])
    rows.append({"label": "mdss full FEM (1 Newton it./step)", "who": "mdss", "dofs": int(full.model.n_dofs),
                 "step_ms": median_ms_from_rest(full, max(5, timing_steps // 10)), "sag": fem_sag, "mesh": "scene",
                 "statics": dict(info, wall_s=time.perf_counter() - t0), "x": x_fem,
                 "_timer": lambda: median_ms_from_rest(full, max(5, timing_steps // 10))})
    log(f"peers: our full FEM static sag {fem_sag:.5g} m ({info['iterations']} Newton iterations, residual "
        f"{info['residual']:.2g}), {rows[-1]['step_ms']:.2f} ms/step")

    mj, why = mujoco_module()
    if mj is None:
        result["mujoco"] = {"skipped": why}
        log(f"peers: {why}")
    else:
        result["mujoco"] = {"version": mj.__version__}
        for dof in (("quadratic",) if quick else ("quadratic", "trilinear", "full")):
            r = mujoco_flex_beam(mj, geo, dof, timing_steps=timing_steps)
            idx = match_vertices(body.vertices, r["X"])
            row = {"label": f"MuJoCo {mj.__version__} flex dof={dof}", "who": "mujoco", "dofs": r["nv"],
                   "nodes": r["nodes"], "step_ms": r["step_ms"], "sag": tip_sag(r["X"], r["x"], geo["L"]),
                   "mesh": "scene" if idx is not None else "own", "settled": r["settled"],
                   "settle_steps": r["settle_steps"], "finite": r["finite"], "_timer": r["timer"],
                   "mujoco_warnings": r["warnings"]}
            if idx is not None:
                row["x"] = r["x"][idx]
            rows.append(row)
            log(f"peers: {row['label']}: {row['dofs']} DOFs, {row['step_ms']:.3f} ms/step, sag {row['sag']:.5g} m "
                f"(settled: {r['settled']} after {r['settle_steps']} steps"
                + (f"; MuJoCo warned: {' | '.join(r['warnings'])[:200]}" if r["warnings"] else "") + ")")

    # Our reduced configurations: built as the tradeoff rows are (own cache folder).
    configs = [(lab, ov, "scene") for lab, ov in OURS]
    if not quick:
        configs += [(lab, dict(ov, **{"body.mesh.cell": scene["body"]["mesh"]["cell"] / 2}), "cell/2")
                    for lab, ov in OURS_FINE]
    fine_fem = None
    for label, ov, mesh in configs:
        if ov == "half_modes":
            ov = {"model.domains": {"count": 1}, "model.cubature.interface": "exact",
                  "model.modes": max(2, scene["model"]["modes"] // 2)}
            label = f"mdss reduced: 1 domain, r = {ov['model.modes']}"
        t0 = time.perf_counter()
        try:
            sc = load_scene(scene_src, dict(base_overrides or {}, **{"model.kind": "reduced"}, **ov))
            cache_dir = Path(out) / "cache" / ("peers_" + "".join(c if c.isalnum() else "_" for c in label)[:40])
            sim = Simulator(sc, cache=PrecomputeCache(cache_dir))
            build_s = time.perf_counter() - t0
            x = ours_static_sag(sim)
            row = {"label": label, "who": "mdss", "dofs": int(sim.model.n_dofs), "mesh": mesh, "build_s": build_s,
                   "step_ms": median_ms_from_rest(sim, timing_steps), "sag": tip_sag(sim.rest_positions(), x, geo["L"]),
                   "x": x, "overrides": ov, "_timer": (lambda s=sim: median_ms_from_rest(s, timing_steps))}
        except ReportError as err:
            rows.append({"label": label, "who": "mdss", "mesh": mesh, "failed": str(err)})
            log(f"peers: {label}: FAILED: {err}")
            continue
        if mesh != "scene":
            if fine_fem is None:
                fsim = Simulator(load_scene(scene_src, dict(base_overrides or {}, **{
                    "model.kind": "full", "body.mesh.cell": scene["body"]["mesh"]["cell"] / 2})))
                xf, finfo = ours_fem_static(fsim)
                fine_fem = {"sag": tip_sag(fsim.rest_positions(), xf, geo["L"]), "statics": finfo,
                            "dofs": int(fsim.model.n_dofs)}
                result["fem_cell_half"] = fine_fem
                log(f"peers: our full FEM static sag at cell/2 ({fine_fem['dofs']} DOFs): {fine_fem['sag']:.5g} m")
            row["fem_sag_same_mesh"] = fine_fem["sag"]
        rows.append(row)
        log(f"peers: {label}: {row['dofs']} DOFs, {row['step_ms']:.3f} ms/step, sag {row['sag']:.5g} m "
            f"[{time.perf_counter() - t0:.1f} s]")

    retime_round_robin(rows, timing_rounds)
    log(f"peers: re-timed every row in {timing_rounds} round-robin passes")
    for row in rows:
        if "failed" in row:
            continue
        row["err_closed_form"] = (row["sag"] - ref) / ref
        fem = row.get("fem_sag_same_mesh", fem_sag if row["mesh"] == "scene" else None)
        row["err_vs_fem_same_mesh"] = None if fem is None else (row["sag"] - fem) / fem
        x = row.pop("x", None)
        if x is not None and row["mesh"] == "scene":
            row["rms_rel_vs_fem"] = surface_error(_Positions(body, x), x_fem)["rms_rel"]
        row["error_x_ms"] = abs(row["err_closed_form"]) * row["step_ms"]
    result["summary"] = peer_summary(rows)
    result["table"] = peer_table(rows, ref)
    result["plots"] = [peer_plot(rows, ref, Path(out) / "tradeoff_peers.png")]
    return result


def retime_round_robin(rows, rounds):
    """Re-time every row that has a "_timer" in `rounds` round-robin passes, alternating
    the order: a load spike from other processes hits MuJoCo and ours alike. Each row keeps
    the smallest of its pass medians ("step_ms"; all passes in "step_ms_passes")."""
    timed = [r for r in rows if "_timer" in r]
    for p in range(rounds):
        for r in (timed if p % 2 == 0 else timed[::-1]):
            r.setdefault("step_ms_passes", []).append(r["_timer"]())
    for r in timed:
        r["step_ms_first"] = r["step_ms"]
        r["step_ms"] = min(r["step_ms_passes"] + [r["step_ms"]])
        del r["_timer"]


METRIC_NAMES = {"err_closed_form": "|sag error| vs the closed form",
                "rms_rel_vs_fem": "RMS surface error vs our full-space FEM statics on the same grid"}


def compare_to(rows, peer, metric, names=None):
    """Sentences comparing our reduced rows with one peer row on one error metric
    (|value|, lower is better) and on error x ms. names: metric -> description
    (default METRIC_NAMES)."""
    ours = [r for r in rows if "failed" not in r and r["who"] == "mdss" and not r["label"].startswith("mdss full")
            and r.get(metric) is not None]
    if not ours or peer.get(metric) is None:
        return []
    ep = abs(peer[metric])
    out = [f"[{(names or METRIC_NAMES)[metric]}] {peer['label']}: {100 * ep:.3g} % at {peer['step_ms']:.3g} ms/step"]
    better = sorted((r for r in ours if abs(r[metric]) <= ep), key=lambda r: r["step_ms"])
    if better:
        b = better[0]
        out.append(f"  at equal or lower error: {b['label']} ({100 * abs(b[metric]):.3g} %, "
                   f"{ep / max(abs(b[metric]), 1e-12):.1f} x lower) costs {b['step_ms']:.3g} ms/step = "
                   f"{b['step_ms'] / peer['step_ms']:.2f} x the peer's time")
    else:
        out.append("  none of our configurations reaches the peer's error on this metric")
    cheap = min(ours, key=lambda r: r["step_ms"])
    out.append(f"  our cheapest, {cheap['label']}: {cheap['step_ms']:.3g} ms/step "
               f"({cheap['step_ms'] / peer['step_ms']:.2f} x the peer's time) at {100 * abs(cheap[metric]):.3g} % "
               f"(error ratio ours / peer {abs(cheap[metric]) / max(ep, 1e-12):.2f})")
    prod = lambda r: abs(r[metric]) * r["step_ms"]           # noqa: E731
    best = min(ours, key=prod)
    ratio = prod(peer) / max(prod(best), 1e-300)
    out.append(f"  error x ms (lower is better): peer {prod(peer):.3g}, our best ({best['label']}) {prod(best):.3g}: "
               + (f"ours {ratio:.2f} x better" if ratio > 1 else f"the peer {1 / ratio:.2f} x better"))
    return out


def peer_summary(rows):
    """Comparison sentences: ours vs MuJoCo's quadratic flex on both error metrics, and
    vs its full flex on cost."""
    ok = [r for r in rows if "failed" not in r]
    quad = next((r for r in ok if r["who"] == "mujoco" and "quadratic" in r["label"]), None)
    fullflex = next((r for r in ok if r["who"] == "mujoco" and r["label"].endswith("dof=full")), None)
    if quad is None:
        return ["no MuJoCo quadratic flex row: nothing to compare"]
    out = compare_to(ok, quad, "err_closed_form") + compare_to(ok, quad, "rms_rel_vs_fem")
    if fullflex is not None:
        same = [r for r in ok if r["who"] == "mdss" and r["mesh"] == "scene" and not r["label"].startswith("mdss full")]
        if same:
            f = min(same, key=lambda r: r["step_ms"])
            out.append(f"full-space peer: MuJoCo full flex {fullflex['step_ms']:.3g} ms/step ({fullflex['dofs']} DOFs, sag "
                       f"error {100 * fullflex['err_closed_form']:+.1f} %); {f['label']} is "
                       f"{fullflex['step_ms'] / f['step_ms']:.0f} x faster on the same grid")
    return out


def peer_table(rows, ref):
    def pct(v):
        return "-" if v is None else f"{100 * v:+.2f}"
    body = []
    for r in rows:
        if "failed" in r:
            body.append([r["label"], r["mesh"], "-", "-", "-", "failed", "-", "-"])
            continue
        body.append([r["label"], r["mesh"], r["dofs"], f"{r['step_ms']:.3g}", f"{r['sag']:.5f}",
                     pct(r["err_closed_form"]), pct(r["err_vs_fem_same_mesh"]),
                     "-" if r.get("rms_rel_vs_fem") is None else f"{100 * r['rms_rel_vs_fem']:.2f}"])
    return format_table(["model", "mesh", "DOFs", "ms/step", "sag (m)", "err vs closed form %",
                         "err vs our FEM same mesh %", "RMS surf. err vs FEM %"], body) + \
        f"\nclosed form (Euler-Bernoulli + Timoshenko shear): sag {ref:.5f} m"


def peer_plot(rows, ref, path):
    """Two log-log panels, ms/step vs error: |sag error| vs the closed form, and RMS
    surface error vs our FEM statics on the same grid (rows on that grid only)."""
    from .plotting import pyplot, save_figure
    plt = pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(14, 5.8))
    panels = [("err_closed_form", f"|static sag error| vs Euler-Bernoulli + shear ({ref:.4f} m), %"),
              ("rms_rel_vs_fem", "RMS surface error vs our full-space FEM statics, same grid, %")]
    for ax, (key, ylabel) in zip(axes, panels):
        for r in rows:
            if "failed" in r or r.get(key) is None or (key == "rms_rel_vs_fem" and r["label"].startswith("mdss full")):
                continue
            e = max(100 * abs(r[key]), 1e-3)
            mj = r["who"] == "mujoco"
            colour = "tab:orange" if mj else ("k" if r["label"].startswith("mdss full") else "tab:blue")
            ax.scatter([r["step_ms"]], [e], marker="s" if mj else "o", s=50, color=colour)
            short = r["label"].replace("mdss reduced: ", "ours: ").replace("MuJoCo 4.0.0 flex ", "MuJoCo ")
            ax.annotate(f"{short} ({r['dofs']})", (r["step_ms"], e), fontsize=7, textcoords="offset points",
                        xytext=(4, 3))
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("median ms / step at the scene's dt (measured under load)")
        ax.set_ylabel(ylabel, fontsize=9)
        ax.grid(alpha=0.3, which="both")
    axes[0].scatter([], [], marker="s", color="tab:orange", label="MuJoCo flex (DOFs)")
    axes[0].scatter([], [], marker="o", color="tab:blue", label="mdss reduced (DOFs)")
    axes[0].scatter([], [], marker="o", color="k", label="mdss full-space FEM")
    axes[0].legend(fontsize=8)
    fig.suptitle("Clamped beam under gravity: static sag, MuJoCo flex vs mdss", fontsize=11)
    return save_figure(fig, path)
