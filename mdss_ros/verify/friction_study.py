"""Coulomb friction against closed forms (docs/method.md §14.1): the incline of issue 18
and a pad dragged over a bonded block, for the full and the reduced model; and the same
incline side by side with MuJoCo's quadratic flex (`mdss verify friction`).

    PYTHONPATH=. python -m mdss_ros.verify.friction_study      # prints method.md's table
    mdss verify friction --out DIR                             # the peer comparison, JSON + PNG

test/test_friction.py builds the same scenes and asserts the bounds.

The peer comparison (`friction_report`). Every row steps the same block (0.10 x 0.08 x
0.04 m on a 0.02 m lattice, E 2e5 Pa, nu 0.3, 1000 kg/m^3, mu 0.5, dt 1/90) from rest for
2 s with gravity tilted by 20 degrees (below the friction angle: it must stick) and by 35
(above: it must slide at g (sin - mu cos) = 1.6088 m/s^2 without leaving the floor):

    full, reduced     ours (reduced: 1 domain, 12 modes and the residual contact compliance)
    MuJoCo quadratic  MuJoCo's flexcomp on the same lattice with dof="quadratic" (3x3x3
                      nodes), its defaults (pyramidal cone), and with the elliptic cone and
                      impratio 100 that its documentation recommends against slip; the
                      `discrete` integrator (MuJoCo 4.0 refuses flex elasticity under the
                      implicit ones), the plane's and the flex's friction 0.5

Measured per row: creep (the mass centre's travel over the last 1.5 s at 20 degrees, after
the elastic settle), the acceleration fitted over the last 1.5 s at 35 degrees, the highest
the lowest vertex rises above the floor while sliding (a hop), the deepest it sinks, and
ms per step: the median (and p90) over both angles' steps, the rows run one after the
other in one process (the report states the load average).
"""
import time

import numpy as np

G = 9.81
DT = 1.0 / 90.0
REDUCED = {"kind": "reduced", "domains": {"count": 1}, "modes": 12}
MODELS = {"full": {"kind": "full"}, "reduced": REDUCED}


def incline(theta_deg, model, friction=0.5):
    """Issue 18's incline: a 0.10 x 0.08 x 0.04 m block, E 2e5 Pa, on a floor with gravity
    tilted by theta about y (so it slides along +x)."""
    th = np.radians(theta_deg)
    return {"name": "incline",
            "body": {"mesh": {"generator": "box", "size": [0.10, 0.08, 0.04], "cell": 0.02,
                              "origin": [-0.05, -0.04, 0.0]},
                     "material": {"model": "neohookean", "young": 2e5, "poisson": 0.3, "density": 1000}},
            "colliders": {"floor": {"shape": "plane", "friction": friction}},
            "gravity": [G * np.sin(th), 0.0, -G * np.cos(th)],
            "model": {"integrator": {"dt": DT, "newton_iterations": 1}, **model}}


def pressed_block(model, mu=0.5):
    """A block bonded at the bottom, to be pressed 2 mm by a pad wider than its top."""
    return {"name": "drag",
            "body": {"mesh": {"generator": "box", "size": [0.10, 0.10, 0.04], "cell": 0.02,
                              "origin": [-0.05, -0.05, 0.0]},
                     "material": {"model": "neohookean", "young": 1e5, "poisson": 0.3, "density": 1000},
                     "damping": {"alpha": 2.0, "beta": 0.0}},
            "pins": [{"box": [[-1, -1, -1e-4], [1, 1, 1e-4]]}],
            "colliders": {"pad": {"shape": "box", "half_extents": [0.08, 0.08, 0.01], "position": [0, 0, 0.05],
                                  "friction": mu}},
            "gravity": [0, 0, 0],
            "model": {"integrator": {"dt": DT, "newton_iterations": 1}, **model}}


def run_incline(sim, steps):
    """Mean displacement along x (steps,), lowest vertex height (steps,), total energy
    (steps,) with the tilted gravity's potential."""
    x0 = sim.vertex_positions().copy()
    mean_x, low, energy = [], [], []
    for _ in range(steps):
        sim.step()
        x = sim.vertex_positions()
        mean_x.append((x[:, 0] - x0[:, 0]).mean())
        low.append(x[:, 2].min())
        energy.append(sim.energy()["total"])
    return np.array(mean_x), np.array(low), np.array(energy)


def drag(sim, steps=60, ledger=None):
    """Press the pad 2 mm over 20 steps, then drag it 2 cm along x over `steps`; returns
    the pad's tangential / normal reaction after each drag step.

    ledger: a list to which every step (press and drag) appends (dE, W): the change of
    the body's energy (Simulator.energy()["total"]) and the work the pad's contact force
    did on the body, W = -F . (c1 - c0), F the pad's reaction (collider_wrench, force on
    the pad, constant over the implicit step) and c0 -> c1 its translation over the step
    (the pad does not turn, so its torque does no work)."""
    def step(position):
        c0, e0 = sim.colliders["pad"].position.copy(), sim.energy()["total"]
        sim.set_collider_pose("pad", position)
        sim.step()
        w = sim.collider_wrench("pad")
        if ledger is not None:
            ledger.append((sim.energy()["total"] - e0, -float(w[:3] @ (sim.colliders["pad"].position - c0))))
        return w
    for k in range(20):
        step((0.0, 0.0, 0.05 - 0.002 * (k + 1) / 20))
    ratios = []
    for k in range(steps):
        w = step((0.02 * (k + 1) / steps, 0.0, 0.048))
        ratios.append(-w[0] / w[2])
    return np.array(ratios)


def table():
    """The rows of method.md §14.1's table, measured now."""
    from ..simulator import Simulator
    rows = {}
    for kind, model in MODELS.items():
        mean_x, low, _ = run_incline(Simulator(incline(20.0, model)), 180)
        r = {"creep_m": abs(mean_x[-1] - mean_x[44]), "shear_m": abs(mean_x[-1])}
        mean_x, low, _ = run_incline(Simulator(incline(35.0, model)), 180)
        t = DT * np.arange(1, 181)
        r["a"] = 2.0 * np.polyfit(t[45:], mean_x[45:], 2)[0]
        r["lowest_m"] = float(low.min())
        r["drag_ratio"] = float(drag(Simulator(pressed_block(model if kind == "full" else dict(REDUCED, modes=30))))[-1])
        rows[kind] = r
    return rows


FRICTION = {"seconds": 2.0, "angles": [20.0, 35.0], "models": ["full", "reduced"],
            "mujoco": ["pyramidal", "elliptic"]}
QUICK = {"seconds": 1.0}
MUJOCO_CONES = {"pyramidal": ("pyramidal", 1.0), "elliptic": ("elliptic", 100.0)}


def mujoco_incline_xml(theta_deg, cone="pyramidal", impratio=1.0, friction=0.5):
    """MJCF of the incline's block as a quadratic flexcomp on a plane. The lattice, mass and
    material are those of incline(): 6 x 5 x 3 vertices, 0.32 kg."""
    th = np.radians(theta_deg)
    f = lambda *v: " ".join(f"{float(a):.12g}" for a in v)        # noqa: E731
    return f"""<mujoco model="mdss_incline">
  <option timestep="{f(DT)}" gravity="{f(G * np.sin(th), 0.0, -G * np.cos(th))}" integrator="discrete"
          solver="Newton" cone="{cone}" impratio="{f(impratio)}"/>
  <worldbody>
    <geom name="floor" type="plane" size="5 5 0.1" friction="{f(friction)} 0.005 0.0001"/>
    <flexcomp name="block" type="grid" dim="3" dof="quadratic" count="6 5 3" spacing="0.02 0.02 0.02"
              pos="0 0 0.02" mass="0.32" radius="0">
      <contact condim="3" friction="{f(friction)} 0.005 0.0001" selfcollide="none"/>
      <elasticity young="2e5" poisson="0.3" damping="0"/>
    </flexcomp>
  </worldbody>
</mujoco>"""


def _ours(theta, kind):
    """(step(), positions()) of our model on the incline."""
    from ..simulator import Simulator
    sim = Simulator(incline(theta, MODELS[kind]))
    return sim.step, sim.vertex_positions


def _mujoco(mj, theta, cone):
    """(step(), positions()) of MuJoCo's quadratic flex on the incline. MuJoCo warns that a
    flex with zero elastic damping "has no passive forces"; its elasticity is applied all
    the same (with damping 1e-4 the 20-degree creep is the same to 1e-13 m: a one-off check
    in session 18), so the warning is silenced for the build."""
    previous = mj.get_mju_user_warning()
    mj.set_mju_user_warning(lambda msg: None)
    try:
        model = mj.MjModel.from_xml_string(mujoco_incline_xml(theta, *MUJOCO_CONES[cone]))
        data = mj.MjData(model)
        mj.mj_forward(model, data)
    finally:
        mj.set_mju_user_warning(previous)
    return (lambda: mj.mj_step(model, data)), (lambda: np.array(data.flexvert_xpos))


def run_rows(rows, steps):
    """Step each row `steps` times, one row after the other. rows: {label: (step,
    positions)}. Returns {label: {"mean_x" (steps,), "low" (steps,), "ms" (steps,)}}: the
    mass centre's (the vertices' mean) x travel, the lowest vertex's height, the step's wall
    time. Rows are not interleaved step by step: MKL's and numba's threads spin for a while
    after their work, and a row stepped right after another paid for them (the reduced row
    measured 8.6 ms a step interleaved with the full one, 1.9 ms alone)."""
    out = {}
    for label, (step, positions) in rows.items():
        start = positions().copy()
        run = out[label] = {"mean_x": np.empty(steps), "low": np.empty(steps), "ms": np.empty(steps)}
        for k in range(steps):
            t0 = time.perf_counter()
            step()
            run["ms"][k] = 1e3 * (time.perf_counter() - t0)
            x = positions()
            run["mean_x"][k] = (x[:, 0] - start[:, 0]).mean()
            run["low"][k] = x[:, 2].min()
    return out


def friction_report(out, quick=False, overrides=None, log=None):
    """`mdss verify friction`: the incline, ours against MuJoCo's quadratic flex (module
    docstring). Returns the report dict (rows, table, notes, plots)."""
    from pathlib import Path

    from .peers import mujoco_module
    from .reduced_reports import format_table, study_config
    cfg = study_config("friction", FRICTION, QUICK, quick, overrides)
    log = log or print
    steps = int(round(cfg["seconds"] / DT))
    settle = int(round(0.5 / DT))
    mj, missing = mujoco_module()
    notes = [missing] if missing else []
    labels = list(cfg["models"]) + ([f"MuJoCo quadratic, {c}" for c in cfg["mujoco"]] if mj else [])
    runs = {}
    for theta in cfg["angles"]:
        rows = {kind: _ours(theta, kind) for kind in cfg["models"]}
        if mj:
            rows.update({f"MuJoCo quadratic, {c}": _mujoco(mj, theta, c) for c in cfg["mujoco"]})
        runs[theta] = run_rows(rows, steps)
        log(f"{theta:g} degrees: {steps} steps of each of {', '.join(rows)}")
    stick, slide = min(cfg["angles"]), max(cfg["angles"])
    a_exact = G * (np.sin(np.radians(slide)) - 0.5 * np.cos(np.radians(slide)))
    t = DT * np.arange(1, steps + 1)
    result_rows = []
    for label in labels:
        s, m = runs[stick][label], runs[slide][label]
        ms = np.concatenate([runs[th][label]["ms"] for th in cfg["angles"]])
        result_rows.append({
            "model": label,
            "creep_m": float(abs(s["mean_x"][-1] - s["mean_x"][settle - 1])),
            "settle_m": float(abs(s["mean_x"][settle - 1])),
            "a": float(2.0 * np.polyfit(t[settle:], m["mean_x"][settle:], 2)[0]),
            "a_exact": float(a_exact),
            "lift_m": float(max(m["low"].max(), 0.0)),
            "sink_m": float(max(-min(s["low"].min(), m["low"].min()), 0.0)),
            "step_ms": float(np.median(ms)), "step_ms_p90": float(np.percentile(ms, 90))})
    for r in result_rows:
        r["a_error"] = r["a"] / a_exact - 1.0
    table = format_table(
        ["model", f"creep {stick:g} deg (m)", f"a {slide:g} deg (m/s^2)", "a error %", "lift-off (m)",
         "deepest sink (m)", "ms/step", "p90 ms"],
        [[r["model"], r["creep_m"], r["a"], 100 * r["a_error"], r["lift_m"], r["sink_m"], r["step_ms"],
          r["step_ms_p90"]] for r in result_rows])
    notes.append(f"closed form at {slide:g} degrees: a = g (sin - mu cos) = {a_exact:.4f} m/s^2; creep is the "
                 f"travel over the last {cfg['seconds'] - 0.5:g} s at {stick:g} degrees")
    plots = [incline_plot(runs, cfg["angles"], t, a_exact, Path(out) / "friction_incline.png")]
    return {"config": cfg, "rows": result_rows, "table": table, "notes": notes, "plots": plots}


def incline_plot(runs, angles, t, a_exact, path):
    """Three panels: the travel at the smaller angle (log), the travel at the larger one
    against the closed form, and the lowest vertex's height while sliding."""
    from .plotting import pyplot, save_figure
    plt = pyplot()
    stick, slide = min(angles), max(angles)
    fig, axes = plt.subplots(1, 3, figsize=(14, 3.9))
    for label, run in runs[stick].items():
        axes[0].semilogy(t, np.maximum(np.abs(run["mean_x"]), 1e-12), label=label)
        axes[1].plot(t, runs[slide][label]["mean_x"], label=label)
        axes[2].plot(t, 1e3 * runs[slide][label]["low"], label=label)
    axes[1].plot(t, 0.5 * a_exact * t ** 2, "k:", lw=1, label="closed form")
    axes[0].set(title=f"{stick:g} degrees: must stick", xlabel="t (s)", ylabel="mass centre travel (m)")
    axes[1].set(title=f"{slide:g} degrees: must slide", xlabel="t (s)", ylabel="mass centre travel (m)")
    axes[2].set(title=f"{slide:g} degrees: lowest vertex", xlabel="t (s)", ylabel="height above the floor (mm)")
    axes[1].legend(fontsize=7)
    return save_figure(fig, path)


if __name__ == "__main__":
    rows = table()
    a = G * (np.sin(np.radians(35)) - 0.5 * np.cos(np.radians(35)))
    print(f"{'':48s} {'full':>12s} {'reduced':>12s}")
    for key, label in (("creep_m", "20 deg: mass centre travel 0.5-2 s (m)"), ("shear_m", "20 deg: shear + edge slip (m)"),
                       ("a", f"35 deg: a (closed form {a:.4f})"), ("lowest_m", "35 deg: lowest vertex (m)"),
                       ("drag_ratio", "drag: tangential / normal (mu 0.5)")):
        print(f"{label:48s} {rows['full'][key]:12.6g} {rows['reduced'][key]:12.6g}")
