"""`mdss verify cantilever`: full-space FEM at several resolutions and reduced models
against the closed forms of a clamped beam (docs/method.md §16.1, §16.2)."""
import time
from pathlib import Path

from .reduced_reports import (STATIC_INTEGRATOR, Progress, beam_scene, build_sim, format_table, full_static,
                              reduced_static, study_config)


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


