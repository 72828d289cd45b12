"""Coulomb friction against closed forms (docs/method.md §14.1): the incline of issue 18
and a pad dragged over a bonded block, for the full and the reduced model.

    PYTHONPATH=. python -m mdss_ros.verify.friction_study      # prints method.md's table

test/test_friction.py builds the same scenes and asserts the bounds.
"""
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


if __name__ == "__main__":
    rows = table()
    a = G * (np.sin(np.radians(35)) - 0.5 * np.cos(np.radians(35)))
    print(f"{'':48s} {'full':>12s} {'reduced':>12s}")
    for key, label in (("creep_m", "20 deg: mass centre travel 0.5-2 s (m)"), ("shear_m", "20 deg: shear + edge slip (m)"),
                       ("a", f"35 deg: a (closed form {a:.4f})"), ("lowest_m", "35 deg: lowest vertex (m)"),
                       ("drag_ratio", "drag: tangential / normal (mu 0.5)")):
        print(f"{label:48s} {rows['full'][key]:12.6g} {rows['reduced'][key]:12.6g}")
