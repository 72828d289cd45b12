"""Element coupling vs spring coupling against full-space FEM (paper Fig. 8).

Setup: a beam clamped at x = 0, split into two domains, under a dead tip load; static
equilibrium of each reduced variant (reduced_reports.reduced_static) and of the
full-space model on the same mesh (the ground truth). Variants: coupling elements (the
method: the tets spanning the two domains are ordinary FEM elements), and zero-length-
free springs on the crossing edges of those tets (E = k/2 (|d| - L)^2) at a low and a
high stiffness k. Every variant uses the same partition and bases.

Metrics, per variant:
  rms_rel   RMS over surface vertices of |x - x_FEM|, relative to the peak FEM surface
            displacement (reduced_reports.surface_error);
  interface stretch: for every interface edge (an edge of a coupling tet whose two
            vertices lie in different domains), s_e = (l_e - l_e^FEM) / L_e with l_e its
            deformed length, l_e^FEM the ground truth's and L_e the rest length. s > 0 is
            a gap (the domains pulled apart more than in FEM), s < 0 an overlap. Reported:
            mean |s|, max |s|, RMS s, max s (largest gap) and min s (largest overlap).
"""
import time
from pathlib import Path

import numpy as np

from .reduced_reports import (MATERIAL, STATIC_INTEGRATOR, Progress, beam_scene, build_sim, format_table,
                              full_static, reduced_static, study_config, surface_error)

COUPLING = {
    "size": [1.0, 0.1, 0.1], "cell": 0.025, "material": MATERIAL,
    "domains": 2,
    # Modes per domain: every variant runs with each. A small basis leaves a subspace error
    # (too stiff) that soft springs can partly cancel; with a rich one the coupling error
    # dominates and element coupling converges to full-space FEM while springs do not.
    "modes": [20, 80],
    "tip_force": [0.0, 0.0, -4.0],          # N, dead load
    # Spring stiffness in N/m. Reference scale: an edge-sized bar of the material,
    # E * cell = 2.5e4 N/m at E = 1 MPa, cell = 0.025 m; low = 0.1x, high = 100x that.
    "spring_low": 2.5e3, "spring_high": 2.5e6,
}
QUICK = {"cell": 0.05, "modes": [10, 30]}

_TET_EDGES = np.array([[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]])


def interface_edges(sim):
    """(n_e, 2) vertex pairs: edges of coupling tets joining two different domains."""
    part = sim.model.partition
    tets = sim.tetrahedra()[np.asarray(part.coupling_elements, dtype=np.int64)]
    pairs = np.sort(tets[:, _TET_EDGES].reshape(-1, 2), axis=1)
    labels = np.asarray(part.labels)
    pairs = pairs[labels[pairs[:, 0]] != labels[pairs[:, 1]]]
    return np.unique(pairs, axis=0)


def edge_stretch(x, x_ref, X, edges):
    """s_e = (|x_b - x_a| - |xref_b - xref_a|) / |X_b - X_a| per edge, and its summary."""
    length = lambda p: np.linalg.norm(p[edges[:, 1]] - p[edges[:, 0]], axis=1)   # noqa: E731
    s = (length(x) - length(x_ref)) / length(X)
    return s, {"edges": int(len(s)), "mean_abs": float(np.abs(s).mean()), "max_abs": float(np.abs(s).max()),
               "rms": float(np.sqrt((s * s).mean())), "max_gap": float(s.max()), "max_overlap": float(-s.min())}


def coupling_report(out, quick=False, overrides=None, log=None):
    from . import plotting
    cfg = study_config("coupling", COUPLING, QUICK, quick, overrides)
    log = log or Progress("coupling")
    geo = dict(size=cfg["size"], cell=cfg["cell"], material=cfg["material"])
    force = np.asarray(cfg["tip_force"], dtype=np.float64)

    full = build_sim(beam_scene("full", **geo), log, "full-space ground truth")
    info = full_static(full, force)
    x_ref = full.vertex_positions().copy()
    X = full.rest_positions()
    tip = full.body.handles["tip"]
    log(f"ground truth: static in {info['iterations']} Newton iterations (residual {info['residual']:.2g}), "
        f"tip displacement {np.round((x_ref[tip] - X[tip]).mean(0), 5).tolist()} m")

    specs = [("element coupling", {"kind": "element"}),
             (f"springs k = {cfg['spring_low']:.3g} N/m", {"kind": "spring", "stiffness": float(cfg["spring_low"])}),
             (f"springs k = {cfg['spring_high']:.3g} N/m", {"kind": "spring", "stiffness": float(cfg["spring_high"])})]
    variants = []
    edges = None
    for (name, coupling), r in [(spec, int(r)) for r in cfg["modes"] for spec in specs]:
        label = f"{name}, r = {r}"
        sim = build_sim(beam_scene("reduced", domains={"count": int(cfg["domains"])}, modes=r,
                                   integrator=dict(STATIC_INTEGRATOR), coupling=coupling, **geo), log, label)
        t0 = time.perf_counter()
        st = reduced_static(sim, force)
        x = sim.vertex_positions()
        if edges is None:
            edges = interface_edges(sim)
            labels = np.asarray(sim.model.partition.labels)
        s, summary = edge_stretch(x, x_ref, X, edges)
        err = surface_error(sim, x_ref)
        ids = sim.body.surface.vertex_ids
        v = {"label": label, "coupling": coupling, "modes": r, **err, "interface": summary, "stretch": s,
             "tip_displacement": (x[tip] - X[tip]).mean(0), "static": st, "dofs": sim.stats()["dofs"],
             "surface_xz": x[ids][:, [0, 2]], "surface_domain": labels[ids], "wall_s": time.perf_counter() - t0}
        variants.append(v)
        log(f"  {label}: RMS error {100 * err['rms_rel']:.3f} % of peak, interface |s| mean "
            f"{100 * summary['mean_abs']:.3f} % max {100 * summary['max_abs']:.3f} % "
            f"(gap {100 * summary['max_gap']:.3f} %, overlap {100 * summary['max_overlap']:.3f} %)")

    ids = full.body.surface.vertex_ids
    truth_xz = x_ref[ids][:, [0, 2]]
    centre = x_ref[np.unique(edges)][:, [0, 2]].mean(0)
    plots = [plotting.coupling_bars(variants, Path(out) / "coupling_errors.png"),
             plotting.coupling_side_views(truth_xz, variants, centre, Path(out) / "coupling_side_views.png")]
    table = format_table(["variant, modes per domain", "RMS err %", "max err %", "mean |s| %", "max |s| %", "max gap %",
                          "max overlap %", "tip dz (m)"],
                         [[v["label"], 100 * v["rms_rel"], 100 * v["max_rel"], 100 * v["interface"]["mean_abs"],
                           100 * v["interface"]["max_abs"], 100 * v["interface"]["max_gap"],
                           100 * v["interface"]["max_overlap"], float(v["tip_displacement"][2])]
                          for v in variants]
                         + [["full-space FEM", 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, float((x_ref[tip] - X[tip]).mean(0)[2])]])
    notes = [f"{full.stats()['vertices']} vertices, {full.stats()['tets']} tets, {cfg['domains']} domains, "
             f"{len(edges)} interface edges; s = (l - l_FEM) / L_rest per interface edge",
             f"peak FEM surface displacement {variants[0]['peak_displacement']:.4g} m"]
    return {"config": dict(cfg, quick=quick, boundary="clamped at x = 0", load="dead tip load on the x = L face",
                           statics="reduced: backward Euler with dt = 10 s and up to 10 Newton iterations per step "
                           "until the step's largest increment < 1e-9 x peak displacement; full: Newton statics"),
            "ground_truth": {"static": info, "tip_displacement": (x_ref[tip] - X[tip]).mean(0),
                             "surface_xz": truth_xz, "interface_edges": edges},
            "variants": variants, "plots": plots, "table": table, "notes": notes}
