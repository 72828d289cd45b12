"""The grasp-and-lift scene (issue 18): two finger pads close on a soft cube resting on a
floor, squeeze it, lift it 10 cm and hold it, and the closed form it must meet.

Geometry (metres): a 4 cm cube on the floor z = 0, centred on the z axis; two pads (mesh
colliders, msg_scenes/meshes/finger_pad.obj: a 1 x 3 x 6 cm box) on either side along x.
Timeline: settle, close until each pad is `squeeze` into the cube, hold, lift by `lift`
along a cosine ramp (peak acceleration lift pi^2 / (2 T^2): 0.22 m/s^2 for 10 cm in
1.5 s, 2 % of g), hold.

Closed form. A cube of mass m held by two pads pressing with N each, with Coulomb
coefficient mu, is carried when the friction available, 2 mu N, exceeds what it must
carry, m (g + a): it stays in the grasp (slip under 2 mm over the lift). Below it, it
slides out. The flip is at mu* = m (g + a) / (2 N), N the grip force each pad reads.

Commands: `PYTHONPATH=. python -m mdss_ros.verify.grasp_study` writes the scene and the pad
mesh; `... grasp_study --plot docs/img/grasp_lift.png` the picture; test/test_grasp.py
checks the closed form.
"""
from pathlib import Path

import numpy as np

CUBE = 0.04                         # m, side
PAD_HALF = (0.005, 0.015, 0.03)     # m, the pad box's half extents (x thickness, y, z): taller than the cube
GAP = 0.005                         # m, each pad's clearance before it closes
T_SETTLE, T_CLOSE, T_HOLD, T_LIFT, T_END = 0.15, 0.3, 0.15, 1.5, 0.3
LIFT = 0.10
PAD_Z = 0.02                        # pad centre height at the start: the cube's middle
SCENE_FILE = Path(__file__).resolve().parents[2] / "msg_scenes" / "grasp_lift.yaml"


def duration():
    return T_SETTLE + T_CLOSE + T_HOLD + T_LIFT + T_END


def lift_start():
    return T_SETTLE + T_CLOSE + T_HOLD


def pad_positions(t, squeeze):
    """Left and right pad centres (3,) each at time t for a squeeze (m) per side."""
    open_x = CUBE / 2 + PAD_HALF[0] + GAP
    closed_x = CUBE / 2 + PAD_HALF[0] - squeeze
    a = np.clip((t - T_SETTLE) / T_CLOSE, 0.0, 1.0)
    x = open_x + (closed_x - open_x) * 0.5 * (1.0 - np.cos(np.pi * a))
    b = np.clip((t - lift_start()) / T_LIFT, 0.0, 1.0)
    z = PAD_Z + LIFT * 0.5 * (1.0 - np.cos(np.pi * b))
    return np.array([-x, 0.0, z]), np.array([x, 0.0, z])


def peak_lift_acceleration():
    return LIFT * np.pi ** 2 / (2.0 * T_LIFT ** 2)


def scene(kind="full", mu=1.0, squeeze=0.003, young=5e4, cell=0.01, timeline_rate=None, pad_file=None):
    """The scene dict; timeline_rate (Hz) writes the pad poses as a timeline (the shipped
    YAML); None leaves the poses to the caller (run_grasp sets them every step).
    pad_file: the pads' mesh as the scene gives it (default: its absolute path, for a
    scene dict, whose relative paths would be read from the working directory)."""
    model = {"kind": kind, "integrator": {"dt": 1.0 / 90.0, "newton_iterations": 1}}
    if kind == "reduced":
        model.update({"domains": {"count": 1}, "modes": 12})
    pad = {"shape": "mesh", "file": pad_file or str(SCENE_FILE.parent / "meshes" / "finger_pad.obj"), "friction": mu}
    left, right = pad_positions(0.0, squeeze)
    data = {"name": "grasp_lift",
            "description": "two finger pads squeeze a 4 cm soft cube, lift it 10 cm and hold it",
            "body": {"mesh": {"generator": "box", "size": [CUBE] * 3, "cell": cell,
                              "origin": [-CUBE / 2, -CUBE / 2, 0.0]},
                     "material": {"model": "neohookean", "young": young, "poisson": 0.3, "density": 1000.0},
                     "damping": {"alpha": 2.0, "beta": 0.0}},
            "colliders": {"floor": {"shape": "plane", "friction": 0.5},
                          "left": dict(pad, position=[round(float(v), 6) for v in left]),
                          "right": dict(pad, position=[round(float(v), 6) for v in right])},
            "model": model,
            "gravity": [0.0, 0.0, -9.81],
            "duration": round(duration(), 6)}
    if timeline_rate:
        events = []
        for t in np.arange(1.0 / timeline_rate, duration() - 0.5 / timeline_rate, 1.0 / timeline_rate):
            for name, p in zip(("left", "right"), pad_positions(t, squeeze)):
                events.append({"t": round(float(t), 4), "topic": "collider_pose", "name": name,
                               "position": [round(float(v), 6) for v in p]})
        data["timeline"] = events
    return data


def write_pad_mesh(path):
    """The pad: a closed box of half extents PAD_HALF, outward-wound triangles, as OBJ."""
    h = np.array(PAD_HALF)
    v = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=float) * h
    # corners indexed by (x, y, z) bits: 4x + 2y + z
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    lines = ["# finger pad, a 1 x 3 x 6 cm box (mdss_ros/verify/grasp_study.py)"]
    lines += [f"v {a:.6f} {b:.6f} {c:.6f}" for a, b, c in v]
    for a, b, c, d in quads:
        lines += [f"f {a + 1} {b + 1} {c + 1}", f"f {a + 1} {c + 1} {d + 1}"]
    Path(path).write_text("\n".join(lines) + "\n")


def run_grasp(sim, squeeze, log=None, until=None):
    """Step a grasp scene (built with timeline_rate None) through its timeline (up to time
    `until`, default the whole of it), posing the pads every step. Returns a trace dict of
    arrays over steps: t, cube_z (mass centre height), pad_z, grip (normal force on each
    pad: mean of the two, N), step_ms (the Simulator's), and the summary: hold_grip (N while
    held before the lift), slip (m, how far the cube fell behind the pads over the lift),
    lifted (m, the cube's rise), mass (kg)."""
    mass = float(sim.model.vertex_mass.sum())
    steps = int(round((duration() if until is None else until) / sim.dt))
    t_out, cube_z, pad_z, grip, step_ms = [], [], [], [], []
    z0 = None
    for k in range(steps):
        t = (k + 1) * sim.dt
        left, right = pad_positions(t, squeeze)
        sim.set_collider_pose("left", left)
        sim.set_collider_pose("right", right)
        sim.step()
        step_ms.append(float(sim.stats()["step_ms"]))
        x = sim.vertex_positions()
        zc = float((sim.model.vertex_mass * x[:, 2]).sum() / mass)
        z0 = zc if z0 is None else z0
        c = sim.contacts(split=True)
        pads = np.isin(c["collider"], ["left", "right"])
        t_out.append(t)
        cube_z.append(zc)
        pad_z.append(left[2])
        grip.append(0.5 * float(c["normal_force"][pads].sum()))
    t_out, cube_z, pad_z, grip, step_ms = map(np.array, (t_out, cube_z, pad_z, grip, step_ms))
    before = (t_out > lift_start() - T_HOLD / 2) & (t_out <= lift_start())
    start = np.searchsorted(t_out, lift_start())
    # A trace stopped at the lift's start has no lift: no slip, no rise.
    lifting = start < len(t_out) - 1
    slip = float((pad_z[-1] - pad_z[start]) - (cube_z[-1] - cube_z[start])) if lifting else float("nan")
    return {"t": t_out, "cube_z": cube_z, "pad_z": pad_z, "grip": grip, "step_ms": step_ms, "mass": mass,
            "hold_grip": float(grip[before].mean()), "slip": slip,
            "lifted": float(cube_z[-1] - cube_z[start]) if lifting else float("nan")}


def flip_mu(trace):
    """The closed form's flip point mu* = m (g + a_peak) / (2 N) for the trace's grip N."""
    return trace["mass"] * (9.81 + peak_lift_acceleration()) / (2.0 * trace["hold_grip"])


def plot(out, kind="full"):
    """The picture of the grasp (docs/img/grasp_lift.png): the cube held between the pads
    at the end of a lift with mu 1 (3D, surface triangles), and the cube's height against
    the pads' for mu 1 (held) and mu 0.01 (2 mu N < m g: it slides out). Returns the
    two traces."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection
    from ..simulator import Simulator
    sims, traces = {}, {}
    for mu in (1.0, 0.01):
        sims[mu] = Simulator(scene(kind, mu=mu))
        traces[mu] = run_grasp(sims[mu], 0.003)
    fig = plt.figure(figsize=(10, 4.2))
    ax = fig.add_subplot(1, 2, 1, projection="3d")
    sim = sims[1.0]
    x = sim.surface_positions()
    ax.add_collection3d(Poly3DCollection(x[sim.surface_triangles()], facecolor="#7fb3d5", edgecolor="#1f4e79",
                                         linewidth=0.3, alpha=0.95))
    for name in ("left", "right"):
        c = sim.colliders[name]
        h = np.array(PAD_HALF)
        corners = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]) * h + c.position
        faces = [[0, 1, 3, 2], [4, 6, 7, 5], [0, 4, 5, 1], [2, 3, 7, 6], [0, 2, 6, 4], [1, 5, 7, 3]]
        ax.add_collection3d(Poly3DCollection([corners[f] for f in faces], facecolor="#b0b0b0", edgecolor="#404040",
                                             linewidth=0.5, alpha=0.35))
    ax.set_xlim(-0.04, 0.04), ax.set_ylim(-0.04, 0.04), ax.set_zlim(0.08, 0.16)
    ax.set_box_aspect((1, 1, 1))
    ax.set_title(f"held at t = {duration():.1f} s (mu 1, grip {traces[1.0]['hold_grip']:.1f} N a pad)", fontsize=9)
    ax2 = fig.add_subplot(1, 2, 2)
    for mu, style in ((1.0, "-"), (0.01, "--")):
        tr = traces[mu]
        ax2.plot(tr["t"], 1e3 * (tr["cube_z"] - tr["cube_z"][0]), style, label=f"cube, mu {mu:g}")
    ax2.plot(traces[1.0]["t"], 1e3 * (traces[1.0]["pad_z"] - PAD_Z), ":", color="k", label="pads")
    ax2.axvline(lift_start(), color="#999999", linewidth=0.5)
    ax2.set_xlabel("t (s)"), ax2.set_ylabel("rise (mm)")
    ax2.set_title(f"{kind} model: held when 2 mu N > m (g + a), mu* = {flip_mu(traces[0.01]):.4f}", fontsize=9)
    ax2.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out, dpi=110)
    plt.close(fig)
    return traces


if __name__ == "__main__":     # writes the shipped scene and the pad mesh; --plot PNG the picture
    import sys
    if len(sys.argv) == 3 and sys.argv[1] == "--plot":
        traces = plot(sys.argv[2])
        for mu, tr in traces.items():
            print(f"mu {mu:g}: grip {tr['hold_grip']:.3f} N a pad, slip {1e3 * tr['slip']:.2f} mm, "
                  f"lifted {1e3 * tr['lifted']:.1f} mm")
        sys.exit(0)
    import yaml
    write_pad_mesh(SCENE_FILE.parent / "meshes" / "finger_pad.obj")
    data = scene("full", mu=1.0, timeline_rate=30.0, pad_file="meshes/finger_pad.obj")
    header = (__doc__.split("\n\n")[0].replace('"""', "").strip() + "\n"
              "Generated by: PYTHONPATH=. python -m mdss_ros.verify.grasp_study\n")
    SCENE_FILE.write_text("".join(f"# {line}\n" for line in header.splitlines()) +
                          yaml.safe_dump(data, sort_keys=False, default_flow_style=None, width=120))
    print(f"wrote {SCENE_FILE} and the pad mesh")
