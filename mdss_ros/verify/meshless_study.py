"""`mdss verify meshless`: the meshless model (docs/method.md §19) against the closed forms
of the clamped beam and against full-space FEM on the same tet mesh, at several node
counts: accuracy, cost per interactive step, and the measured zero-energy modes.

Models (the nodes of the meshless rows are the FEM mesh's vertices, so a row pair shares
its node count):
    full          linear tets, StVK (§2)
    meshless      the defaults: consistent nodal integration, mesh vertex volumes,
                  fit-residual stabilisation 0.1 (§19.6)
    meshless_hz   [HZ] as written: raw nodal integration, support volumes (eq. 2), no
                  stabilisation

Per model and cell, on verify/cantilever.py's beam (1 x 0.1 x 0.1 m, E 1 MPa, nu 0.3):
    tip     static tip deflection under a 0.01 N tip load vs Euler-Bernoulli + shear
    sag     static sag under 0.05 m/s^2 of gravity vs its closed form
    f1      first bending frequency (eigenvalue at rest) vs Euler-Bernoulli
    step    median wall ms of an interactive step (dt 1/90 s, 1 Newton iteration, gravity),
            the cost a user pays in `mdss run` or the node
    hourglass  how many of the 10 lowest elastic modes of the free beam are zero-energy
            (hourglass) modes: fit-residual energy above 10 x the mode's elastic energy
            (meshless rows at the coarsest two cells only; dense eigenproblems)
"""
import time
from pathlib import Path

import numpy as np

from .reduced_reports import Progress, beam_scene, build_sim, format_table, full_static, median_step_ms, study_config

MESHLESS = {
    # A fourth cell (0.0125, 6,561 nodes) costs the meshless rows more than ten minutes of
    # static solves on 2 cores; the three below took 13 minutes (docs/method.md §19.5).
    "cells": [0.05, 0.025, 1.0 / 60.0],
    "timing_steps": 10,
    "hourglass_max_nodes": 1200,
    "tip_load": 0.01,                 # N
    "sag_gravity": 0.05,              # m/s^2: small strain
}
QUICK = {"cells": [0.05, 0.025], "timing_steps": 4}

VARIANTS = {
    "full": {"kind": "full"},
    "meshless": {"kind": "meshless", "meshless": {}},
    "meshless_hz": {"kind": "meshless",
                    "meshless": {"integration": "nodal", "stabilisation": 0.0, "volumes": "support"}},
}
HOURGLASS_RATIO = 10.0


def _scene(variant, cell, gravity=0.0):
    from .cantilever import BEAM
    spec = VARIANTS[variant]
    scene = beam_scene(spec["kind"], size=(BEAM["L"], BEAM["b"], BEAM["h"]), cell=cell,
                       material={"model": "stvk", "young": BEAM["E"], "poisson": BEAM["nu"], "density": BEAM["rho"]},
                       **({"meshless": dict(spec["meshless"])} if "meshless" in spec else {}))
    scene["gravity"] = [0.0, 0.0, -float(gravity)]
    return scene


def _tip(sim):
    ids = sim.body.handles["tip"]
    return -float((sim.vertex_positions()[ids, 2] - sim.rest_positions()[ids, 2]).mean())


def hourglass_count(force_model, probe, modes=10):
    """(count, ratios (modes,)) over the lowest elastic modes of a free model: the number
    whose fit-residual energy (probe: the same nodes, stabilisation 1) exceeds
    HOURGLASS_RATIO x their elastic energy."""
    import scipy.linalg
    fm = force_model
    K = fm.pattern.matrix(fm.tangent(fm.X)[2]).toarray()
    s = 1.0 / np.sqrt(np.repeat(fm.vertex_mass, 3))
    _, Q = scipy.linalg.eigh(s[:, None] * K * s[None, :], subset_by_index=[6, 5 + modes])
    U = s[:, None] * Q
    x = fm.X.reshape(-1)
    ratios = np.array([2.0 * probe._stabilisation((x + u).reshape(-1, 3))[0] / probe.mu * fm.mu / (u @ K @ u)
                       for u in U.T])
    return int((ratios > HOURGLASS_RATIO).sum()), ratios


def _free_hourglass(variant, cell):
    from ..meshless.model import build_forces
    from ..simulator import Simulator
    scene = _scene(variant, cell)
    scene["pins"] = []
    sim = Simulator(scene)
    body = sim.model.body
    tri = body.surface.vertex_ids[body.surface.triangles]
    probe, _ = build_forces(body.vertices, body.tets, tri, body.material,
                            dict(sim.model.settings, stabilisation=1.0), ())
    return hourglass_count(sim.model.force_model, probe)


def run_row(variant, cell, cfg, log):
    """One model at one cell: errors against the closed forms, step cost, hourglass modes."""
    from .cantilever import BEAM
    from .closed_forms import cantilever_first_frequency, cantilever_gravity_sag, cantilever_tip_deflection
    from .modes_study import full_frequencies
    P, g = float(cfg["tip_load"]), float(cfg["sag_gravity"])
    t0 = time.perf_counter()
    sim = build_sim(_scene(variant, cell))
    build_s = time.perf_counter() - t0
    full_static(sim, (0.0, 0.0, -P))
    tip = _tip(sim)
    sim_g = build_sim(_scene(variant, cell, gravity=g))
    full_static(sim_g, (0.0, 0.0, 0.0))
    sag = _tip(sim_g)
    f1 = float(full_frequencies(sim, 1)[0])
    refs = {"tip": cantilever_tip_deflection(P, BEAM["L"], BEAM["E"], BEAM["b"], BEAM["h"], BEAM["nu"]),
            "sag": cantilever_gravity_sag(BEAM["rho"], g, BEAM["L"], BEAM["E"], BEAM["b"], BEAM["h"], BEAM["nu"]),
            "f1": cantilever_first_frequency(BEAM["L"], BEAM["E"], BEAM["rho"], BEAM["b"], BEAM["h"])}
    timed = _scene(variant, cell, gravity=9.81)
    timed["model"]["integrator"] = {"dt": 1.0 / 90.0, "newton_iterations": 1}
    ms = median_step_ms(build_sim(timed), int(cfg["timing_steps"]))
    fm = sim.model.force_model
    row = {"model": variant, "cell": cell, "nodes": int(len(sim.rest_positions())), "dofs": int(fm.n_free),
           "stiffness_nnz": int(fm.pattern.nnz), "build_s": build_s,
           "tip_rel_error": tip / refs["tip"] - 1.0, "sag_rel_error": sag / refs["sag"] - 1.0,
           "f1_hz": f1, "f1_rel_error": f1 / refs["f1"] - 1.0,
           "step_ms": ms["step_ms"], "assembly_ms": ms.get("assembly_ms"), "factor_ms": ms.get("factor_ms")}
    if variant != "full" and row["nodes"] <= int(cfg["hourglass_max_nodes"]):
        row["hourglass_modes"], ratios = _free_hourglass(variant, cell)
        row["hourglass_ratios"] = ratios.tolist()
    log(f"{variant:12s} cell {cell:.4g}: {row['nodes']} nodes, tip {100 * row['tip_rel_error']:+.2f} %, sag "
        f"{100 * row['sag_rel_error']:+.2f} %, f1 {100 * row['f1_rel_error']:+.2f} %, step {row['step_ms']:.1f} ms"
        + (f", hourglass modes {row['hourglass_modes']}/10" if "hourglass_modes" in row else "")
        + f" [{time.perf_counter() - t0:.1f} s]")
    return row


def equal_error_comparison(rows, key="tip_rel_error"):
    """For each meshless row: the cheapest full-FEM row at least as accurate (|error| <=),
    or None; [(meshless row, full row or None)]."""
    full = [r for r in rows if r["model"] == "full"]
    out = []
    for r in rows:
        if r["model"] != "meshless":
            continue
        ok = [f for f in full if abs(f[key]) <= abs(r[key])]
        out.append((r, min(ok, key=lambda f: f["step_ms"]) if ok else None))
    return out


def meshless_plot(rows, path):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(1, 3, figsize=(15, 4.4))
    style = {"full": ("C0", "o", "full-space FEM (linear tets)"), "meshless": ("C3", "s", "meshless (defaults)"),
             "meshless_hz": ("C7", "^", "meshless as [HZ] wrote it")}
    for model, (colour, marker, label) in style.items():
        rs = sorted((r for r in rows if r["model"] == model), key=lambda r: r["nodes"])
        if not rs:
            continue
        n = [r["nodes"] for r in rs]
        err = [100 * abs(r["tip_rel_error"]) for r in rs]
        ms = [r["step_ms"] for r in rs]
        ax[0].loglog(n, err, marker=marker, color=colour, label=label)
        ax[1].loglog(n, ms, marker=marker, color=colour, label=label)
        ax[2].loglog(ms, err, marker=marker, color=colour, label=label)
        for r, m, e in zip(rs, ms, err):
            ax[2].annotate(str(r["nodes"]), (m, e), textcoords="offset points", xytext=(4, 3), fontsize=7)
    ax[0].set(xlabel="nodes", ylabel="|tip deflection error| (%)", title="accuracy vs nodes (clamped beam)")
    ax[1].set(xlabel="nodes", ylabel="ms per step (dt 1/90 s, 1 Newton iteration)", title="cost vs nodes")
    ax[2].set(xlabel="ms per step", ylabel="|tip deflection error| (%)", title="the trade (labels: nodes)")
    for a in ax:
        a.grid(True, which="both", alpha=0.3)
        a.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def meshless_report(out, quick=False, overrides=None, log=None):
    cfg = study_config("meshless", MESHLESS, QUICK, quick, overrides)
    log = log or Progress("meshless")
    rows = []
    for cell in cfg["cells"]:
        for variant in VARIANTS:
            rows.append(run_row(variant, float(cell), cfg, log))
    table = format_table(
        ["model", "nodes", "K nnz", "tip err %", "sag err %", "f1 err %", "ms/step", "hourglass"],
        [[r["model"], r["nodes"], r["stiffness_nnz"], f"{100 * r['tip_rel_error']:+.2f}",
          f"{100 * r['sag_rel_error']:+.2f}", f"{100 * r['f1_rel_error']:+.2f}", f"{r['step_ms']:.1f}",
          f"{r['hourglass_modes']}/10" if "hourglass_modes" in r else "-"] for r in rows])
    notes = []
    for r, f in equal_error_comparison(rows):
        if f is None:
            notes.append(f"meshless at {r['nodes']} nodes ({100 * r['tip_rel_error']:+.2f} % tip, "
                         f"{r['step_ms']:.1f} ms): no full-FEM row in this run is as accurate")
        else:
            notes.append(f"meshless at {r['nodes']} nodes ({100 * r['tip_rel_error']:+.2f} % tip, {r['step_ms']:.1f} "
                         f"ms) vs the cheapest full FEM at least as accurate: {f['nodes']} nodes "
                         f"({100 * f['tip_rel_error']:+.2f} %, {f['step_ms']:.1f} ms)")
    plot = meshless_plot(rows, Path(out) / "meshless_beam.png")
    return {"config": cfg, "rows": rows, "table": table, "notes": notes, "plots": [plot]}
