"""`mdss stability --out DIR [--quick]`: the stability matrix of issue 7.

Every cell is a small body (a 0.2 x 0.1 x 0.1 m box, a few hundred tets) stepped a fixed
number of steps through the Simulator with its stability guard on (mdss_ros/guard.py).

Parameters (every value appears; the product space is sub-sampled, see `design`):
  young    {1e3, 1e5, 1e7, 1e9, 1e11} Pa      poisson  {0, 0.3, 0.45, 0.49, 0.499}
  dt       {1e-4, 1/90, 1/30} s                spin     {0, 10, 50} rad/s
  force    {1, 1e3} x a 1 N tip load (held for the first half of the steps, then released)
Base point: young 1e7, poisson 0.3, dt 1/90, spin 0, force 1. The design is
  * the young x poisson grid at the base dt, spin, force      (25 cells),
  * the dt x spin x force grid at the base young, poisson       (18 cells),
  * a half fraction (16) of the 32 corners of the box {1e3, 1e11} x {0, 0.499} x
    {1e-4, 1/30} x {0, 50} x {1, 1e3}: every pair of extremes meets (see `corners`),
minus duplicates: 58 cells, each for model kind {full, reduced} and material {stvk,
corotated, neohookean}, and for the meshless model (docs/method.md §19) with one material
(MESHLESS_MATERIAL, stvk): its law is its own StVK with a volume term and the compression
barrier whatever `material.model` says (young, poisson, density and the barrier keys are
read), so the three materials would run the same model three times. --quick runs
one-at-a-time around the base (14 cells) plus the 4 corners with spin 50, fewer steps.
`--kinds` picks model kinds (e.g. the meshless column alone), `--materials` materials (the
meshless column takes MESHLESS_MATERIAL if picked, else the first one picked).

Setup of a cell: spin 0 clamps the end x = 0 (a cantilever); spin > 0 frees the body
(no pins) and spins it about the tilted axis (0.2, 0.3, 1) (tumbling, not a principal
axis). Gravity -9.81 m/s^2, density 1000, no damping. The full model uses backward Euler
with one Newton iteration (the papers' linearly implicit step); the reduced model two
domains x 8 modes, exact forces (no cubature), one-step scheme, one Newton iteration; the
meshless model its default settings (16 neighbours, implicit: the same backward Euler with
one Newton iteration), no domains or modes.

Observation after release. A cell that ends its steps with inverted tets is stepped on
(load still released) until none is left, for at most OBSERVE_TRANSITS shear-wave transit
times of the body after the release (L / sqrt(mu / rho), L = 0.2 m: 0.28 s at 1 kPa) and
OBSERVE_MAX_STEPS extra steps. Why: at force scale 1e3 the tip load is ~100 x a 1 kPa
modulus; no model holds it without inverted tets while it is applied (checked: the full
neo-Hookean cantilever at nu 0, dt 1/30 has 25 inverted tets at release, its tip 48 m
below the clamp). Released, the undamped body swings back with an amplitude of the order
of that stretch and elements pass through inversion and back: the count 12 steps after
release says where that oscillation happens to be, not whether the model pushes inverted
elements back (the same cell had 3 at step 24 and none at step 37). The question the class
asks, "is an inversion left", is whether the model recovers once released: a stuck
inversion (the old StVK clamp, coupling elements a reduced model cannot un-fold) stays
through the whole window; steps of the extension count in every other check too (guard
failures, energy). At dt 1e-4 the cap keeps the window short (OBSERVE_MAX_STEPS x 0.1 ms).

Classification of a cell:
  failed     a step the guard could not recover (rolled back), a non-finite state, an
             inverted tet left at the end of the observation, or unbounded energy: the energy created beyond
             the work of the loads, max_t (E(t) - E(0) - W(t)), above ENERGY_BOUND x the
             run's energy scale max_t (E_kin + E_el + |W| + |gravity potential change|)
             (the guard's own "energy drift" check, guard.py, enforces the same bound);
  recovered  the guard acted (a step was rolled back and retried, or kept "degraded"
             with soft signs left, or a reduced model's lasting inversion was untangled)
             and the run ended finite, uninverted, energy bounded;
  stable     no guard action and the checks above pass.
Each recovered cell lists what the guard did (per-step actions, counted).

Contact cells (issue 18): the same box, free, on a floor plane, with a sphere (radius 3 cm)
that comes down 1 cm into the middle of its top and drags across it along x, crossing the
middle at half time, and is lifted clear at three quarters of the steps (the release);
floor and sphere share the friction coefficient.
  mu       {0, 0.5, 2}           speed  {0.1, 5} m/s          young  {1e4, 1e7} Pa
(12 cells; --quick: 2), poisson 0.3, dt 1/90, each for both model kinds and the three
materials, classified as above (the collider's work on the body counts as work of loads).
At 5 m/s the sphere moves 5.6 cm a step, beyond the contact margin: the Simulator sweeps it
in sub-steps (simulator.py).
"""
import itertools
import json
import time
from collections import Counter
from pathlib import Path

import numpy as np

YOUNG = [1e3, 1e5, 1e7, 1e9, 1e11]
POISSON = [0.0, 0.3, 0.45, 0.49, 0.499]
DTS = [1e-4, 1.0 / 90.0, 1.0 / 30.0]
SPINS = [0.0, 10.0, 50.0]
FORCES = [1.0, 1e3]
BASE = {"young": 1e7, "poisson": 0.3, "dt": 1.0 / 90.0, "spin": 0.0, "force": 1.0}
KINDS = ["full", "reduced", "meshless"]
# What `mdss stability` runs without --kinds: the models issue 7's target (no failed cell)
# is for. The meshless column is asked for by name (--kinds meshless, or all three).
DEFAULT_KINDS = ["full", "reduced"]
MATERIALS = ["stvk", "corotated", "neohookean"]
MESHLESS_MATERIAL = "stvk"      # the meshless column's one material (module docstring)
TIP_FORCE = 1.0                 # N at force scale 1, pointing -z
STEPS, QUICK_STEPS = 24, 16
ENERGY_BOUND = 0.1
OBSERVE_TRANSITS = 4.0          # longest observation after release, in shear-wave transits
OBSERVE_MAX_STEPS = 96          # and at most this many extra steps
BODY_LENGTH = 0.2               # m, the longest side of the box (cell_scene)
DENSITY = 1000.0
SPIN_AXIS = np.array([0.2, 0.3, 1.0]) / np.linalg.norm([0.2, 0.3, 1.0])
CELL = 0.03                     # m, mesh cell of the box generator


CONTACT_MU = [0.0, 0.5, 2.0]
CONTACT_SPEED = [0.1, 5.0]
CONTACT_YOUNG = [1e4, 1e7]
SPHERE_RADIUS, PRESS = 0.03, 0.01


def _key(c):
    return tuple(c.get(k) for k in ("young", "poisson", "dt", "spin", "force", "mu", "speed"))


def contact_design(quick=False):
    """The contact cells (dicts with mu and speed), in a documented order."""
    if quick:
        return [dict(BASE, young=1e7, mu=0.5, speed=0.1), dict(BASE, young=1e4, mu=2.0, speed=5.0)]
    return [dict(BASE, young=e, mu=mu, speed=v) for e in CONTACT_YOUNG for mu in CONTACT_MU for v in CONTACT_SPEED]


def corners():
    """The 2^(5-1) half fraction of the corners of the extreme box (defining relation
    I = ABCDE: the product of the five +-1 levels is +1): every pair of parameters meets in
    all four combinations of its extremes, with half the runs of the full 32."""
    ext = [(YOUNG[0], YOUNG[-1]), (POISSON[0], POISSON[-1]), (DTS[0], DTS[-1]), (SPINS[0], SPINS[-1]),
           (FORCES[0], FORCES[-1])]
    out = []
    for signs in itertools.product((0, 1), repeat=5):
        if sum(signs) % 2 == 0:
            out.append(dict(zip(("young", "poisson", "dt", "spin", "force"),
                                (e[s] for e, s in zip(ext, signs)))))
    return out


def design(quick=False):
    """The list of parameter cells (dicts), duplicates removed, in a documented order."""
    cells = []
    if quick:
        for name, values in (("young", YOUNG), ("poisson", POISSON), ("dt", DTS), ("spin", SPINS),
                             ("force", FORCES)):
            cells += [dict(BASE, **{name: v}) for v in values]
        cells += [dict(BASE, young=e, poisson=nu, spin=50.0, dt=1.0 / 30.0, force=1e3)
                  for e in (YOUNG[0], YOUNG[-1]) for nu in (POISSON[0], POISSON[-1])]
    else:
        cells += [dict(BASE, young=e, poisson=nu) for e in YOUNG for nu in POISSON]
        cells += [dict(BASE, dt=dt, spin=w, force=f) for dt in DTS for w in SPINS for f in FORCES]
        cells += corners()
    seen, out = set(), []
    for c in cells:
        if _key(c) not in seen:
            seen.add(_key(c))
            out.append(c)
    return out


def kind_materials(kind, materials=None):
    """The materials a model kind runs with, from the ones picked (default MATERIALS): every
    one, except the meshless model's single MESHLESS_MATERIAL (or the first picked)."""
    materials = list(materials or MATERIALS)
    if kind != "meshless":
        return materials
    return [MESHLESS_MATERIAL if MESHLESS_MATERIAL in materials else materials[0]]


def model_section(kind, dt):
    """The scene's model section of a cell: the reduced model's two domains x 8 modes with
    exact forces (full-space FEM ignores them); the meshless model has neither."""
    integrator = {"dt": float(dt), "newton_iterations": 1}
    if kind == "meshless":
        return {"kind": kind, "integrator": integrator}
    return {"kind": kind, "domains": {"count": 2}, "modes": 8,
            "cubature": {"samples": 0, "interface": "exact"}, "integrator": integrator}


def cell_scene(kind, material, young, poisson, dt, spin, force=1.0):
    """The scene dict of a cell (force is applied by run_cell, not the scene)."""
    return {
        "name": "stability_cell",
        "body": {"mesh": {"generator": "box", "size": [0.2, 0.1, 0.1], "cell": CELL},
                 "material": {"model": material, "young": float(young), "poisson": float(poisson),
                              "density": 1000.0},
                 "damping": {"alpha": 0.0, "beta": 0.0}},
        "pins": [] if spin else [{"box": [[-0.001, -1, -1], [0.001, 1, 1]]}],
        "handles": {"tip": {"box": [[0.199, -1, -1], [0.201, 1, 1]]}},
        "model": model_section(kind, dt),
        "initial_velocity": {"angular": [float(a) for a in spin * SPIN_AXIS]},
        "gravity": [0.0, 0.0, -9.81],
    }


def contact_scene(kind, material, young, mu):
    """The scene dict of a contact cell: the box free on a floor, a sphere above its top."""
    scene = cell_scene(kind, material, young, BASE["poisson"], BASE["dt"], 0.0)
    scene["pins"], scene["handles"], scene["initial_velocity"] = [], {}, {}
    scene["colliders"] = {"floor": {"shape": "plane", "friction": float(mu)},
                          "ball": {"shape": "sphere", "radius": SPHERE_RADIUS, "friction": float(mu),
                                   "position": [-1.0, 0.05, 0.1 + SPHERE_RADIUS + 0.005]}}
    return scene


def ball_pose(cell, k, steps):
    """The sphere's position before step k: along x at the cell's speed, crossing the top's
    middle (x = 0.1) at half time, lowered from 5 mm above the top to PRESS into it over the
    first four steps, and lifted 5 cm clear over four steps from three quarters of the
    steps on. Like the other cells' load, the press is then released, and the cell is
    judged on how the model recovers (an inverted element left is a failure)."""
    dt = cell["dt"]
    x = 0.1 + cell["speed"] * dt * (k - steps / 2)
    z = 0.1 + SPHERE_RADIUS + 0.005 - min(1.0, k / 4) * (0.005 + PRESS)
    z += min(1.0, max(0.0, k - 3 * steps // 4) / 4) * (PRESS + 0.05)
    return (x, 0.05, z)


def transit_time(young, poisson):
    """Time (s) a shear wave takes along the body, L / sqrt(mu / rho)."""
    mu = young / (2.0 * (1.0 + poisson))
    return BODY_LENGTH / np.sqrt(mu / DENSITY)


def extra_steps(cell, steps):
    """Most steps a cell may run after its `steps` while inverted tets are left (module
    docstring): up to OBSERVE_TRANSITS transit times after the release at steps // 2."""
    window = OBSERVE_TRANSITS * transit_time(cell["young"], cell["poisson"])
    after_release = steps - steps // 2
    return int(min(OBSERVE_MAX_STEPS, max(0, np.ceil(window / cell["dt"] - 1e-9) - after_release)))


def run_cell(kind, material, cell, steps, cache=None):
    """Step one cell; returns its row (classification, counts, energy numbers)."""
    from ..guard import inverted_tets
    from ..precompute import PrecomputeCache
    from ..simulator import Simulator
    t0 = time.perf_counter()
    contact = "mu" in cell
    scene = (contact_scene(kind, material, cell["young"], cell["mu"]) if contact else
             cell_scene(kind, material, cell["young"], cell["poisson"], cell["dt"], cell["spin"]))
    sim = Simulator(scene, cache=cache if cache is not None else PrecomputeCache(enabled=False))
    build = time.perf_counter() - t0
    if contact:
        # The sphere is posed before each step; the body settles on the floor meanwhile.
        sim.set_collider_pose("ball", ball_pose(cell, 0, steps))
    else:
        sim.set_wrench("tip", force=(0.0, 0.0, -TIP_FORCE * cell["force"]))
    e0 = sim.energy()
    E0, W = e0["total"], 0.0
    created, scale = 0.0, e0["kinetic"] + max(e0["elastic"], 0.0)
    states, actions, reasons = Counter(), Counter(), Counter()
    x = sim.vertex_positions()
    tets = sim.tetrahedra()
    inverted_release, k, limit = None, 0, steps + extra_steps(cell, steps)
    while k < limit:
        if contact:
            sim.set_collider_pose("ball", ball_pose(cell, k + 1, steps))
        elif k == steps // 2:
            sim.set_wrench("tip", force=(0.0, 0.0, 0.0))
            xr = sim.vertex_positions()
            inverted_release = inverted_tets(xr, tets) if np.isfinite(xr).all() else -1
        sim.step()
        k += 1
        st = sim.stats()
        x = sim.vertex_positions().copy()
        # Work of the load as the model accounts it (guard.py: backward-Euler work; a
        # chord f . dx is wrong when a free body turns a large angle in one step).
        W += st["guard_work"]
        states[st["stability"]] += 1
        if st["stability"] != "stable":
            actions[st["guard_action"]] += 1
            reasons[st["guard_reason"]] += 1
        e = sim.energy()
        created = max(created, e["total"] - E0 - W)
        scale = max(scale, e["kinetic"] + max(e["elastic"], 0.0) + abs(W) + abs(e["gravity"] - e0["gravity"]))
        if k >= steps and (not np.isfinite(x).all() or not inverted_tets(x, tets)):
            break                                   # observation over: none left (or NaN)
    finite = bool(np.isfinite(x).all())
    inverted = inverted_tets(x, tets) if finite else -1
    ratio = created / max(scale, 1e-300)
    why = []
    if states["failed"]:
        why.append(f"{states['failed']} step(s) not recoverable")
    if not finite:
        why.append("non-finite state")
    if inverted:
        why.append(f"{inverted} inverted tets at the end" + (f" (observed {k - steps // 2} steps after release)"
                                                             if k > steps else ""))
    if ratio > ENERGY_BOUND:
        why.append(f"energy created {ratio:.2f} x scale")
    acted = states["recovered"] + states["degraded"]
    status = "failed" if why else ("recovered" if acted else "stable")
    return dict(cell, kind=kind, material=material, status=status, why=why, steps=steps, steps_run=k,
                inverted_release=inverted_release,
                states=dict(states), actions=dict(actions), reasons=dict(reasons),
                energy_created_ratio=ratio, inverted_end=inverted, work=W, E0=E0,
                E_end=float(sim.energy()["total"]) if finite else None,
                indefinite_steps=int(sim.stats().get("guard_indefinite_steps", 0)),
                tets=int(len(sim.tetrahedra())), dofs=int(sim.stats()["dofs"]),
                build_s=build, seconds=time.perf_counter() - t0)


def cell_label(c):
    if "mu" in c:
        return f"contact E={c['young']:.0e} mu={c['mu']:g} v={c['speed']:g} m/s"
    dt = {1e-4: "1e-4", 1.0 / 90.0: "1/90", 1.0 / 30.0: "1/30"}.get(c["dt"], f"{c['dt']:g}")
    return f"E={c['young']:.0e} nu={c['poisson']:g} dt={dt} w={c['spin']:g} f={c['force']:g}"


COLOURS = {"stable": "#4caf50", "recovered": "#ffb300", "failed": "#d32f2f"}


def heatmap(rows, kind, cells, path, materials=None):
    """One PNG per model kind: rows = cells (design order, labelled with their parameters),
    columns = materials (default: those the kind ran with, kind_materials); colour = class,
    text = guard action count (r: recovered steps, d: degraded steps, F: failed steps)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import ListedColormap
    from matplotlib.patches import Patch
    code = {"stable": 0, "recovered": 1, "failed": 2}
    by = {(r["material"], _key(r)): r for r in rows if r["kind"] == kind}
    materials = list(materials or kind_materials(kind))
    grid = np.full((len(cells), len(materials)), np.nan)
    fig, ax = plt.subplots(figsize=(7.5 if len(materials) > 1 else 5.5, 0.22 * len(cells) + 1.6))
    for i, c in enumerate(cells):
        for j, m in enumerate(materials):
            r = by.get((m, _key(c)))
            if r is None:
                continue
            grid[i, j] = code[r["status"]]
            s = r["states"]
            text = " ".join(f"{t}{s[n]}" for t, n in (("r", "recovered"), ("d", "degraded"), ("F", "failed"))
                            if s.get(n))
            ax.text(j, i, text, ha="center", va="center", fontsize=6)
    ax.imshow(grid, aspect="auto", cmap=ListedColormap([COLOURS[k] for k in code]), vmin=0, vmax=2,
              interpolation="nearest")
    ax.set_xticks(range(len(materials)), [f"{m} (its own StVK law)" if kind == "meshless" else m
                                           for m in materials])
    ax.set_yticks(range(len(cells)), [cell_label(c) for c in cells], fontsize=6)
    ax.xaxis.tick_top()
    ax.legend(handles=[Patch(color=v, label=k) for k, v in COLOURS.items()], loc="upper center",
              bbox_to_anchor=(0.5, -0.005), ncol=3, fontsize=7)
    ax.set_title(f"stability matrix, {kind} model (text: steps recovered r / degraded d / failed F)",
                 fontsize=8, pad=18)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return str(path)


def summary(rows):
    """{kind: {stable, recovered, failed}} for the kinds in rows, and a printable table."""
    kinds = [k for k in KINDS if any(r["kind"] == k for r in rows)]
    counts = {k: Counter(r["status"] for r in rows if r["kind"] == k) for k in kinds}
    lines = [f"{'model':8s} {'material':11s} {'stable':>7s} {'recovered':>10s} {'failed':>7s}"]
    for k in kinds:
        for m in MATERIALS:
            c = Counter(r["status"] for r in rows if r["kind"] == k and r["material"] == m)
            if sum(c.values()):
                lines.append(f"{k:8s} {m:11s} {c['stable']:7d} {c['recovered']:10d} {c['failed']:7d}")
        lines.append(f"{k:8s} {'all':11s} {counts[k]['stable']:7d} {counts[k]['recovered']:10d} "
                     f"{counts[k]['failed']:7d}")
    if "meshless" in kinds:
        used = sorted({r["material"] for r in rows if r["kind"] == "meshless"})
        lines.append(f"meshless: one material ({', '.join(used)}): the meshless model's law is its own StVK "
                     f"with a volume term whatever material.model says")
    for k in kinds:
        rec = [r for r in rows if r["kind"] == k and r["status"] == "recovered"]
        if not rec:
            continue
        reasons, actions = Counter(), Counter()
        for r in rec:
            reasons.update(r["reasons"])
            actions.update(r["actions"])
        lines.append(f"{k}: guard steps in recovered cells, detected: "
                     + ", ".join(f"{n} x {w or '-'}" for w, n in reasons.most_common()))
        lines.append(f"{k}: ... fixed by: " + ", ".join(f"{n} x {a}" for a, n in actions.most_common()))
    return {k: dict(v) for k, v in counts.items()}, "\n".join(lines)


def run_study(out, quick=False, kinds=None, materials=None, log=print, contact_only=False):
    """Run the matrix, write stability.json and stability_<kind>.png into out; returns the
    report. contact_only: the contact cells alone (a change to contact touches no other)."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    cells = ([] if contact_only else design(quick)) + contact_design(quick)
    kinds = kinds or DEFAULT_KINDS
    materials = materials or MATERIALS
    per_kind = {k: kind_materials(k, materials) for k in kinds}
    steps = QUICK_STEPS if quick else STEPS
    total = len(cells) * sum(len(m) for m in per_kind.values())
    log(f"mdss stability: {len(cells)} cells x ("
        + " + ".join(f"{k} x {len(m)} material{'s' if len(m) > 1 else ''}" for k, m in per_kind.items())
        + f") = {total} runs of {steps} steps"
        + (f"; meshless with {per_kind['meshless'][0]} only (its own StVK law whatever material.model says)"
           if "meshless" in per_kind else ""))
    rows, t0, n = [], time.perf_counter(), 0
    for kind in kinds:
        for material in per_kind[kind]:
            for c in cells:
                n += 1
                r = run_cell(kind, material, c, steps)
                rows.append(r)
                extra = f" ({'; '.join(r['why'])})" if r["why"] else ""
                if r["status"] == "recovered":
                    extra = f" ({', '.join(f'{a}: {k}' for a, k in r['actions'].items())})"
                if r["steps_run"] > steps:
                    extra += f" [observed to step {r['steps_run']}, {r['inverted_release']} inverted at release]"
                log(f"  [{n:3d}/{total} {time.perf_counter() - t0:6.0f} s] {kind:8s} {material:10s} "
                    f"{cell_label(c):42s} {r['status']:9s} {r['seconds']:5.1f} s{extra}")
    counts, table = summary(rows)
    # The meshless column shows the material it ran with; full and reduced every material.
    plots = [heatmap(rows, k, cells, out / f"stability_{k}.png", per_kind[k] if k == "meshless" else None)
             for k in kinds]
    report = {"design": {"young": YOUNG, "poisson": POISSON, "dt": DTS, "spin": SPINS, "force": FORCES,
                         "base": BASE, "quick": quick, "steps": steps, "tip_force_N": TIP_FORCE,
                         "energy_bound": ENERGY_BOUND, "cells": len(cells), "kinds": per_kind,
                         "meshless_material": per_kind["meshless"][0] if "meshless" in per_kind else None,
                         "contact": {"mu": CONTACT_MU, "speed": CONTACT_SPEED, "young": CONTACT_YOUNG,
                                     "cells": len(contact_design(quick))}},
              "counts": counts, "rows": rows, "plots": plots, "seconds": time.perf_counter() - t0}
    (out / "stability.json").write_text(json.dumps(report, indent=1, default=_json))
    log(table)
    log(f"mdss stability: wrote {out / 'stability.json'} and {', '.join(plots)} "
        f"in {report['seconds']:.0f} s")
    return report


def _json(x):
    if isinstance(x, (np.floating, np.integer, np.bool_)):
        return x.item()
    raise TypeError(f"not JSON: {type(x).__name__}")
