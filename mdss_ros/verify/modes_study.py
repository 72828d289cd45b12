"""`mdss verify modes`: natural frequencies of the clamped beam, full-space FEM and reduced
models, against the closed forms and against full FEM on the same mesh.

Frequencies come from the model linearised at rest, with no time stepping:
- full space: the generalised eigenproblem K phi = w^2 M phi of the free DOFs (lumped M,
  shift-invert Lanczos at 0);
- reduced: the unified system matrix is A(dt) = Mgen + dt^2 Kgen with damping off
  (docs/method.md §9), so two evaluations at dt1, dt2 give Mgen and Kgen exactly, and
  eigh(Kgen, Mgen) gives the reduced model's own frequencies (frames, modes and coupling
  included). A Galerkin reduction can only stiffen: reduced frequencies are >= the full
  model's on the same mesh, which the report checks.
"""
import time
from pathlib import Path

import numpy as np
import scipy.linalg as sla
import scipy.sparse.linalg as spla

from .closed_forms import cantilever_frequencies
from .reduced_reports import BEAM_SIZE, MATERIAL, Progress, beam_scene, build_sim, format_table, study_config

MODES = {
    "count": 6,
    "full_cells": [0.05, 0.025, 1.0 / 60.0, 0.0125],
    "reduced_cell": 0.025,
    "reduced": [[1, 6], [1, 12], [2, 6], [2, 12], [4, 6], [4, 12], [4, 20]],   # [domains, modes]
}
MODES_QUICK = {"full_cells": [0.05, 0.025], "reduced": [[1, 6], [2, 12], [4, 12]]}


def full_frequencies(sim, count):
    """Lowest `count` natural frequencies (Hz) of a full-space Simulator at rest."""
    fm = sim.model.force_model
    _, _, K_data = fm.tangent(fm.X)
    K = fm.pattern.matrix(K_data)
    w2 = spla.eigsh(K.tocsc(), k=count, M=fm.M.tocsc(), sigma=0.0, which="LM", return_eigenvectors=False)
    return np.sqrt(np.sort(np.abs(w2))) / (2.0 * np.pi)


def reduced_matrices(sim, dts=(1e-3, 2e-3)):
    """(Mgen, Kgen) dense of a reduced Simulator at its current state, from the unified
    matrix A(dt) = Mgen + dt^2 Kgen at two steps (damping must be off)."""
    model = sim.model
    if model.alpha or model.beta:
        raise ValueError("reduced_matrices needs a model without damping (A would hold dt D)")
    dt0 = model.dt
    try:
        A = []
        for dt in dts:
            model.set_dt(dt)
            A.append(model.system_matrix())
    finally:
        model.set_dt(dt0)
    (d1, d2), (A1, A2) = dts, A
    K = (A2 - A1) / (d2 ** 2 - d1 ** 2)
    M = A1 - d1 ** 2 * K
    return 0.5 * (M + M.T), 0.5 * (K + K.T)


def reduced_frequencies(sim, count):
    """Lowest `count` natural frequencies (Hz) of a reduced Simulator at rest."""
    M, K = reduced_matrices(sim)
    w2 = sla.eigh(K, M, eigvals_only=True)
    return np.sqrt(np.abs(w2[:count])) / (2.0 * np.pi)


def _row(label, kind, sim, f, ref, f_full, wall):
    st = sim.stats()
    row = {"config": label, "kind": kind, "dofs": int(st["dofs"]), "tets": int(st["tets"]),
           "frequencies_hz": [float(v) for v in f], "closed_form_rel_error": [float(v) for v in (f - ref) / ref],
           "wall_s": wall}
    if f_full is not None:
        row["vs_full_rel_error"] = [float(v) for v in (f - f_full) / f_full]
    return row


def modes_report(out, quick=False, overrides=None, log=None):
    from . import plotting
    cfg = study_config("modes", MODES, MODES_QUICK, quick, overrides)
    log = log or Progress("modes")
    n = int(cfg["count"])
    L, b, h = BEAM_SIZE
    closed = cantilever_frequencies(L, MATERIAL["young"], MATERIAL["poisson"], MATERIAL["density"], b, h, n)
    ref = np.array([f for _, f in closed])
    log("closed forms: " + ", ".join(f"{lab} {f:.4g} Hz" for lab, f in closed))
    rows, full_at = [], {}
    for cell in cfg["full_cells"]:
        t0 = time.perf_counter()
        sim = build_sim(beam_scene("full", cell=cell), log, f"full, cell {cell:.4g}")
        f = full_frequencies(sim, n)
        full_at[float(cell)] = f
        rows.append(_row(f"full, cell {cell:.4g}", "full", sim, f, ref, None, time.perf_counter() - t0))
        log(f"full cell {cell:.4g}: " + ", ".join(f"{v:.4g}" for v in f) + " Hz")
    cell = float(cfg["reduced_cell"])
    if cell not in full_at:
        sim = build_sim(beam_scene("full", cell=cell), log, f"full, cell {cell:.4g}")
        full_at[cell] = full_frequencies(sim, n)
    notes = []
    for domains, modes in cfg["reduced"]:
        t0 = time.perf_counter()
        label = f"reduced {domains} x {modes}, cell {cell:.4g}"
        sim = build_sim(beam_scene("reduced", cell=cell, domains={"count": int(domains)}, modes=int(modes)), log, label)
        f = reduced_frequencies(sim, n)
        row = _row(label, "reduced", sim, f, ref, full_at[cell], time.perf_counter() - t0)
        row.update(domains=int(domains), modes=int(modes))
        rows.append(row)
        log(f"{label}: " + ", ".join(f"{v:.4g}" for v in f) + " Hz; vs full "
            + ", ".join(f"{100 * e:+.2f}%" for e in row["vs_full_rel_error"]))
        if min(row["vs_full_rel_error"]) < -1e-6:
            notes.append(f"{label}: a frequency below full FEM's on the same mesh "
                         f"({100 * min(row['vs_full_rel_error']):+.3f} %): not a Galerkin reduction of it")
    plots = [plotting.modes_errors(rows, [lab for lab, _ in closed], Path(out) / "modes_errors.png")]
    headers = ["model", "DOFs"] + [f"f{i + 1} (Hz)" for i in range(n)] + ["f1 vs closed %", "max vs full %"]
    table = format_table(headers, [
        [r["config"], r["dofs"]] + [f"{v:.4g}" for v in r["frequencies_hz"]]
        + [f"{100 * r['closed_form_rel_error'][0]:+.2f}",
           f"{100 * max(r.get('vs_full_rel_error', [0.0]), key=abs):+.2f}" if "vs_full_rel_error" in r else "-"]
        for r in rows])
    return {"config": dict(cfg, beam={"size": BEAM_SIZE, **MATERIAL}, quick=quick,
                           method="eigenproblem of the model linearised at rest (see module doc)"),
            "closed_forms": [{"mode": lab, "frequency_hz": f} for lab, f in closed],
            "full_reference_cell": cell, "rows": rows, "plots": plots, "table": table, "notes": notes}
