"""Accuracy and cost of the multi-domain subspace model against full-space FEM, and the
block Cholesky fill of the domain-graph order against generic orders (paper Fig. 4).

Setup: a beam clamped at x = 0 under a dead tip load large enough to turn the tip by
more than 45 degrees in the ground truth (full-space static equilibrium on the same
mesh). For every (domain count d, modes per domain r): the reduced static equilibrium
(reduced_reports.reduced_static) and its RMS surface error relative to the peak FEM
displacement; then the cost of the paper's method at that state: a second simulator
(one-step, dt = timing_dt, one Newton iteration, no damping) gets the equilibrium state
and the load and is stepped timing_steps times (median Simulator step_ms and phases).

Block Cholesky factor non-zeros (stored entries of L, BlockCholesky.factor_nonzeros) for
the model's domain-graph order (minimum degree: leaves of the path first, no fill), the
identity order of the domain labels, a middle-first order along the beam (domains sorted
by rest centre x, eliminated from the middle outwards: one fill block per elimination
after the first) and the mean over 20 seeded random orders.
"""
import time
from pathlib import Path

import numpy as np

from ..reduced.block_cholesky import BlockCholesky
from .reduced_reports import (MATERIAL, STATIC_INTEGRATOR, Progress, ReportError, beam_scene, build_sim,
                              copy_reduced_state, format_table, full_static, median_step_ms, reduced_static,
                              study_config, surface_error, tip_rotation)

ACCURACY = {
    "size": [1.0, 0.1, 0.1], "cell": 1.0 / 60.0, "material": MATERIAL,
    "tip_force": [0.0, 0.0, -25.0],          # N, dead load: ~55 degrees tip rotation at cell 1/60
    "domains": [1, 2, 4, 8], "modes": [5, 10, 20],
    "timing_dt": 1.0 / 90.0, "timing_steps": 15, "full_timing_steps": 4,
    "random_orders": 20,
}
QUICK = {"cell": 0.05, "domains": [1, 2], "modes": [5, 10], "timing_steps": 5, "full_timing_steps": 2}


def middle_first_order(centres_x):
    """Domains sorted along x, eliminated from the middle outwards: (d,) order."""
    along = np.argsort(np.asarray(centres_x))
    d = len(along)
    mid = (d - 1) // 2
    seq = [mid]
    for k in range(1, d):
        seq += [c for c in (mid - k, mid + k) if 0 <= c < d]
    return along[np.array(seq[:d], dtype=np.int64)]


def factor_fill(model, n_random=20, seed=0):
    """Factor non-zeros and fill blocks of the model's order vs generic orders."""
    bs = model.block_solver
    sizes = np.asarray(bs.sizes)
    edges = np.asarray(model._subspace_edges(), dtype=np.int64).reshape(-1, 2)
    d = len(sizes)
    orders = {"domain graph": np.asarray(model.order),
              "identity": np.arange(d),
              "middle first": middle_first_order([dom.cbar[0] for dom in model.subspace])}
    out = {}
    for name, order in orders.items():
        bc = bs if name == "domain graph" else BlockCholesky(sizes, edges, order)
        out[name] = {"order": order, "factor_nonzeros": int(bc.factor_nonzeros), "fill_blocks": len(bc.fill)}
    rng = np.random.default_rng(seed)
    nnz, fill = [], []
    for _ in range(n_random if d > 2 else 0):
        bc = BlockCholesky(sizes, edges, rng.permutation(d))
        nnz.append(bc.factor_nonzeros)
        fill.append(len(bc.fill))
    if nnz:
        out["random (mean)"] = {"factor_nonzeros": float(np.mean(nnz)), "fill_blocks": float(np.mean(fill)),
                                "max_factor_nonzeros": int(np.max(nnz)), "samples": len(nnz)}
    dense = int(sizes.sum() * (sizes.sum() + 1) // 2)
    return {"block_sizes": sizes, "graph_edges": edges, "dense_lower_nonzeros": dense, "orders": out}


def accuracy_report(out, quick=False, overrides=None, log=None):
    from . import plotting
    cfg = study_config("reduced", ACCURACY, QUICK, quick, overrides)
    log = log or Progress("reduced")
    geo = dict(size=cfg["size"], cell=cfg["cell"], material=cfg["material"])
    force = np.asarray(cfg["tip_force"], dtype=np.float64)
    timing_integ = {"scheme": "one_step", "dt": float(cfg["timing_dt"]), "newton_iterations": 1}

    # Ground truth and its cost per step.
    full = build_sim(beam_scene("full", integrator=dict(timing_integ), **geo), log, "full-space ground truth")
    info = full_static(full, force)
    x_ref = full.vertex_positions().copy()
    X = full.rest_positions()
    tip = full.body.handles["tip"]
    rot = tip_rotation(X[tip], x_ref[tip])
    full_ms = median_step_ms(full, int(cfg["full_timing_steps"]), warmup=1)
    truth = {"static": info, "tip_displacement": (x_ref[tip] - X[tip]).mean(0), "tip_rotation": rot,
             "dofs": full.stats()["dofs"], "vertices": full.stats()["vertices"], "tets": full.stats()["tets"],
             "step_ms": full_ms["step_ms"], "phases_ms": full_ms}
    log(f"ground truth: static in {info['iterations']} Newton iterations (residual {info['residual']:.2g}), "
        f"tip displacement {np.round(truth['tip_displacement'], 4).tolist()} m, tip rotation "
        f"{rot['total_deg']:.1f} deg (bending {rot['bending_deg']:.1f} deg), {truth['dofs']} DOFs, "
        f"{full_ms['step_ms']:.0f} ms/step")
    notes = []
    if rot["bending_deg"] <= 45.0:
        notes.append(f"ground-truth tip bending rotation {rot['bending_deg']:.1f} deg is not above 45 deg "
                     f"(load {cfg['tip_force']} N on this mesh)")

    rows = []
    for d in cfg["domains"]:
        for r in cfg["modes"]:
            label = f"{d} domain(s) x r = {r}"
            t0 = time.perf_counter()
            common = dict(domains={"count": int(d)}, modes=int(r), **geo)
            row = {"domains": int(d), "modes": int(r)}
            try:
                sim = build_sim(beam_scene("reduced", integrator=dict(STATIC_INTEGRATOR), **common), log, label)
                row["static"] = reduced_static(sim, force)
            except ReportError as err:
                row.update(failed=str(err), wall_s=time.perf_counter() - t0)
                rows.append(row)
                log(f"  {label}: FAILED: {err}")
                continue
            x = sim.vertex_positions()
            row.update(surface_error(sim, x_ref))
            row["tip_displacement"] = (x[tip] - X[tip]).mean(0)
            row["tip_rotation"] = tip_rotation(X[tip], x[tip])
            part = sim.model.partition
            row["domain_vertices"] = [int(len(v)) for v in part.domain_vertices]
            row["graph_edges"] = np.asarray(part.graph_edges)
            tsim = build_sim(beam_scene("reduced", integrator=dict(timing_integ), **common))
            row["copy_gap_m"] = copy_reduced_state(sim, tsim)
            tsim.set_wrench("tip", force=force)
            timing = median_step_ms(tsim, int(cfg["timing_steps"]))
            row["step_ms"] = timing["step_ms"]
            row["phases_ms"] = timing
            row["drift_after_timing"] = float(np.abs(tsim.vertex_positions() - x).max())
            row["dofs"] = int(tsim.stats()["dofs"])
            row["fill"] = factor_fill(tsim.model, int(cfg["random_orders"]))
            row["wall_s"] = time.perf_counter() - t0
            rows.append(row)
            fo = row["fill"]["orders"]
            log(f"  {label}: {row['dofs']} DOFs, RMS error {100 * row['rms_rel']:.3f} % "
                f"(max {100 * row['max_rel']:.2f} %), tip rotation {row['tip_rotation']['bending_deg']:.1f} deg, {row['step_ms']:.1f} ms/step "
                f"(factor {timing.get('factor_ms', float('nan')):.2f} ms), L nnz graph/identity/middle "
                f"{fo['domain graph']['factor_nonzeros']}/{fo['identity']['factor_nonzeros']}/"
                f"{fo['middle first']['factor_nonzeros']} [{row['wall_s']:.1f} s]")

    ok = [r for r in rows if "failed" not in r]
    plots = [plotting.accuracy_error_vs_dofs(ok, Path(out) / "reduced_error_vs_dofs.png"),
             plotting.accuracy_cost_vs_error(ok, truth["step_ms"], Path(out) / "reduced_cost_vs_error.png")]

    def fill_cell(r, name):
        o = r["fill"]["orders"].get(name)
        if o is None:
            return "-"
        return f"{o['factor_nonzeros']:.0f}" + (f" ({o['fill_blocks']:.3g})" if o["fill_blocks"] else "")

    table_rows = []
    for r in rows:
        if "failed" in r:
            table_rows.append([r["domains"], r["modes"], "failed", "-", "-", "-", "-", "-", "-", "-", "-"])
            continue
        table_rows.append([r["domains"], r["modes"], r["dofs"], 100 * r["rms_rel"], 100 * r["max_rel"],
                           r["tip_rotation"]["bending_deg"], r["step_ms"], r["phases_ms"].get("factor_ms", 0.0),
                           fill_cell(r, "domain graph"), fill_cell(r, "identity"), fill_cell(r, "middle first")])
    table = format_table(["domains", "r", "DOFs", "RMS err %", "max err %", "tip rot deg", "ms/step", "factor ms",
                          "L nnz graph", "L nnz identity", "L nnz middle-first (fill blocks)"], table_rows)
    table += (f"\nfull-space FEM: {truth['dofs']} DOFs, tip rotation {rot['bending_deg']:.1f} deg "
              f"(total {rot['total_deg']:.1f} deg), {truth['step_ms']:.0f} ms/step")
    notes.append(f"beam {cfg['size']} m, cell {cfg['cell']:.4g} m: {truth['vertices']} vertices, {truth['tets']} tets; "
                 f"timing: one-step, dt = {cfg['timing_dt']:.4g} s, 1 Newton iteration, from the equilibrium")
    return {"config": dict(cfg, quick=quick, boundary="clamped at x = 0", load="dead tip load on the x = L face",
                           statics="reduced: backward Euler with dt = 10 s and up to 10 Newton iterations per step "
                           "until the step's largest increment < 1e-9 x peak displacement; full: Newton statics",
                           error="RMS over surface vertices of |x - x_FEM| / max surface |u_FEM|"),
            "ground_truth": truth, "rows": rows, "plots": plots, "table": table, "notes": notes}
