"""Where the meshless row of `mdss tradeoff msg_scenes/cantilever.yaml --quick` gets its error
(docs/method.md §19.7). Usage:

    python -m mdss_ros.verify.meshless_tradeoff_check [--horizon 1.0] [--fine 0.0125]

Plays the scene's timeline as the report's quick run does (`horizon` s, error probes every
1/15 s, the truth = full FEM on the same mesh with Newton to 1e-8) and changes one
candidate at a time:

    mass         the two models' vertex masses (and so the wrench's vertex forces, which
                 are spread by vertex mass) compared directly
    damping      Rayleigh beta 0 in both (same BackwardEuler and NewtonSettings either way)
    integrator   meshless Newton iterated to 1e-8 instead of one iteration
    stiffness    first frequencies at rest (generalised eigenproblem K, M) of both models
                 and Euler-Bernoulli's; the truth re-run with E scaled so that its first
                 frequency is the meshless one

--fine CELL adds a finer full-FEM truth (Newton to 1e-8) and compares every run's tip with
it (tip only: the meshes differ). Prints one line per run: RMS surface error and tip error
relative to the truth, as the report defines them (accuracy.py).
"""
import argparse
import time

import numpy as np
import scipy.sparse.linalg as sla

SCENE = "msg_scenes/cantilever.yaml"
EVERY = 1.0 / 15.0
FULL = {"model.kind": "full", "model.integrator.newton_iterations": 1}
MESHLESS = {"model.kind": "meshless", "model.integrator.newton_iterations": 1}
CONVERGED = {"model.integrator.newton_iterations": 30, "model.integrator.tolerance": 1e-8}


def _sim(overrides):
    from ..scene import load_scene
    from ..simulator import Simulator
    return Simulator(load_scene(SCENE, overrides))


def play(overrides, horizon):
    """{tip (n, 3) every step, x (p, n_verts, 3) at the probes, sim, tip_rest, wall}."""
    from ..timeline import TimelinePlayer
    sim = _sim(overrides)
    player = TimelinePlayer(sim.scene["timeline"])
    n, every = int(round(horizon / sim.dt)), int(round(EVERY / sim.dt))
    ids = np.asarray(sim.body.handles["tip"])
    tips, xs, t0 = [], [], time.perf_counter()
    for k in range(1, n + 1):
        player.apply_due(sim)
        sim.step()
        x = sim.vertex_positions()
        tips.append(x[ids].mean(0))
        if k % every == 0:
            xs.append(x.copy())
    return {"tip": np.array(tips), "x": np.array(xs), "sim": sim, "every": every,
            "tip_rest": sim.rest_positions()[ids].mean(0), "wall": time.perf_counter() - t0}


def compare(run, truth):
    """rms_rel (same mesh only) and tip_rel of a run against a truth (accuracy.metrics)."""
    sim = truth["sim"]
    out = {}
    if run["x"].shape == truth["x"].shape:
        sid = sim.body.surface.vertex_ids
        X = sim.rest_positions()[sid]
        err = np.linalg.norm(run["x"][:, sid] - truth["x"][:, sid], axis=2)
        peak = np.linalg.norm(truth["x"][:, sid] - X[None], axis=2).max()
        out["rms_rel"] = float(np.sqrt((err ** 2).mean(axis=1).mean()) / peak)
    p = truth["every"]
    a, b = run["tip"][p - 1::p], truth["tip"][p - 1::p]
    out["tip_rel"] = float(np.linalg.norm(a - b, axis=1).max()
                           / np.linalg.norm(b - truth["tip_rest"], axis=1).max())
    return out


def frequencies(overrides, k=3):
    """(lowest k frequencies in Hz at rest, sim) of a model kind on the scene."""
    sim = _sim(overrides)
    fm = sim.model.force_model
    K = fm.pattern.matrix(fm.tangent(sim.rest_positions())[2]).tocsc()
    w2 = sla.eigsh(K, k=k, M=fm.M.tocsc(), sigma=0.0, which="LM", return_eigenvectors=False)
    return np.sqrt(np.sort(w2)) / (2.0 * np.pi), sim


def _fmt(d):
    return ", ".join(f"{k} {100 * v:.2f} %" for k, v in d.items())


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--horizon", type=float, default=1.0, help="s of the timeline (the report's --quick: 1)")
    ap.add_argument("--fine", type=float, default=None, help="cell of a finer full-FEM truth (e.g. 0.0125)")
    args = ap.parse_args(argv)
    h = args.horizon

    f_full, s_full = frequencies(FULL)
    f_ml, s_ml = frequencies(MESHLESS)
    mat = s_full.scene["body"]["material"]
    size = s_full.scene["body"]["mesh"]["size"]
    L, b, t = size
    f_eb = 1.8751 ** 2 / (2 * np.pi * L ** 2) * np.sqrt(mat["young"] * b * t ** 3 / 12.0 / (mat["density"] * b * t))
    print(f"stiffness: f1 full {f_full[0]:.4f} Hz ({f_full[0] / f_eb - 1:+.2%} vs Euler-Bernoulli {f_eb:.4f}), "
          f"meshless {f_ml[0]:.4f} Hz ({f_ml[0] / f_eb - 1:+.2%}); meshless / full {f_ml[0] / f_full[0] - 1:+.2%}")
    m_f, m_m = s_full.model.vertex_mass, s_ml.model.vertex_mass
    print(f"mass: max |m_meshless - m_full| / max m_full = {np.abs(m_f - m_m).max() / m_f.max():.1e}, "
          f"totals {m_f.sum():.6g} / {m_m.sum():.6g} kg")
    print(f"damping: {s_full.scene['body']['damping']}, integrators {type(s_full.model.integrator).__name__} / "
          f"{type(s_ml.model.integrator).__name__}, same Newton settings: "
          f"{s_full.model.integrator.settings == s_ml.model.integrator.settings}")

    runs = {}

    def run(name, overrides, truth=None):
        r = play(overrides, h)
        runs[name] = r
        print(f"{name} [{r['wall']:.1f} s]" + (f": {_fmt(compare(r, truth))}" if truth is not None else ""), flush=True)
        return r

    truth = run("truth: full, Newton to 1e-8", dict(FULL, **CONVERGED))
    run("full, 1 Newton iteration (the report's row)", FULL, truth)
    ml = run("meshless, 1 Newton iteration (the report's row)", MESHLESS, truth)
    mlc = run("integrator: meshless, Newton to 1e-8", dict(MESHLESS, **CONVERGED), truth)
    print(f"  meshless 1 iteration vs Newton to 1e-8: {_fmt(compare(ml, mlc))}")
    t0 = run("truth with beta 0", dict(FULL, **CONVERGED, **{"body.damping.beta": 0.0}))
    run("damping: meshless with beta 0, vs that truth", dict(MESHLESS, **{"body.damping.beta": 0.0}), t0)
    scale = (f_ml[0] / f_full[0]) ** 2
    tE = run(f"truth with E x {scale:.4f} (its f1 = the meshless f1)",
             dict(FULL, **CONVERGED, **{"body.material.young": mat["young"] * scale}))
    print(f"stiffness: meshless 1 iteration vs that truth: {_fmt(compare(ml, tE))}")
    if args.fine:
        fine = run(f"finer truth: full at cell {args.fine:g}, Newton to 1e-8",
                   dict(FULL, **CONVERGED, **{"body.mesh.cell": args.fine}))
        for name in ("truth: full, Newton to 1e-8", "full, 1 Newton iteration (the report's row)",
                     "meshless, 1 Newton iteration (the report's row)"):
            print(f"  {name} vs the finer truth: {_fmt(compare(runs[name], fine))}")


if __name__ == "__main__":
    main()
