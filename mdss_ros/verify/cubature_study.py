"""The paper's Fig. 5: held-out relative force error against cubature samples, for the
domains' internal forces and for the interfaces (uniform vs non-uniform weights).

`mdss verify cubature --out DIR [--quick]` writes cubature.json and cubature.png.
"""
import json
import time
from pathlib import Path

import numpy as np

from ..scene import load_scene
from ..simulator import Simulator


def _scene_overrides(quick):
    ov = {"model.cubature": {"samples": 0}, "gravity": [0.0, 0.0, 0.0]}
    if quick:
        ov.update({"body.mesh.cell": 0.05, "model.domains.count": 3, "model.modes": 8})
    else:
        ov.update({"body.mesh.cell": 0.025, "model.domains.count": 4, "model.modes": 12})
    return ov


def cubature_study(out_dir, scene="cantilever", quick=False, progress=print):
    """Run the study on `scene`; returns the result dict (also written as JSON and PNG)."""
    from ..reduced.cubature import INTERFACE_GROUPS, build_domain_cubature, build_interface_cubature
    from ..reduced.training import generate_training
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    sim = Simulator(load_scene(scene, overrides=_scene_overrides(quick)))
    model = sim.model
    n_poses = 40 if quick else 100
    training = generate_training(model, n_poses=n_poses, stride=2, hold=6, force_scale=2.0, seed=0,
                                 progress=progress)
    counts = [2, 4, 8, 16, 32] if quick else [2, 4, 8, 16, 32, 64, 128, 256]
    result = {"scene": scene, "quick": quick, "poses": n_poses, "held_out_fraction": 0.2,
              "counts": counts, "domains": [], "interfaces": []}
    for k, dom in enumerate(model.subspace):
        errs = []
        for s in counts:
            if s > len(dom.forces.tets):
                break
            _, info = build_domain_cubature(dom, training.q[k], s, seed=0)
            errs.append({"samples": info["samples"], "held_out": info["held_out_error"], "train": info["train_error"]})
        result["domains"].append({"domain": dom.name, "elements": len(dom.forces.tets), "errors": errs})
        progress(f"domain {dom.name}: held-out error {[round(e['held_out'], 4) for e in errs]}")
    tets_dom = model.vertex_domain[model.body.tets[model.c_tets]]
    lo, hi = tets_dom.min(1), tets_dom.max(1)
    two = (np.diff(np.sort(tets_dom, axis=1), axis=1) != 0).sum(1) == 1
    for i, j in np.unique(np.stack([lo[two], hi[two]], 1), axis=0):
        elems = model.c_tets[two & (lo == i) & (hi == j)]
        pair = (int(model.sub_index_of_domain[i]), int(model.sub_index_of_domain[j]))
        rows = {"pair": [model.partition.names[i], model.partition.names[j]], "elements": len(elems),
                "uniform": [], "nonuniform": []}
        for s in counts:
            if s > len(elems):
                break
            for scheme in ("uniform", "nonuniform"):
                _, _, info = build_interface_cubature(model, elems, pair, training, s, scheme, seed=0)
                h = info["held_out_error"]
                rows[scheme].append({"samples": info["samples"], "mean": float(np.mean(list(h.values()))), **h})
        result["interfaces"].append(rows)
        progress(f"interface {rows['pair']}: uniform {[round(e['mean'], 4) for e in rows['uniform']]} "
                 f"non-uniform {[round(e['mean'], 4) for e in rows['nonuniform']]}")
    result["groups"] = list(INTERFACE_GROUPS)
    result["seconds"] = time.perf_counter() - t0
    (out / "cubature.json").write_text(json.dumps(result, indent=2))
    _plot(result, out / "cubature.png")
    _print_summary(result, progress)
    return result


def _plot(result, path):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2))
    ax = axes[0]
    for d in result["domains"]:
        e = d["errors"]
        ax.loglog([x["samples"] for x in e], [x["held_out"] for x in e], "o-", label=d["domain"])
    ax.set_xlabel("samples per domain")
    ax.set_ylabel("held-out relative force error")
    ax.set_title("domain forces")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    ax = axes[1]
    for n, it in enumerate(result["interfaces"]):
        colour = f"C{n}"
        for scheme, style in (("uniform", "o--"), ("nonuniform", "s-")):
            e = it[scheme]
            ax.loglog([x["samples"] for x in e], [x["mean"] for x in e], style, color=colour,
                      label=f"{'-'.join(it['pair'])} {scheme}")
    ax.set_xlabel("samples per interface")
    ax.set_ylabel("held-out relative error (mean of F_i, F_j, f, tau)")
    ax.set_title("interface forces: uniform (dashed) vs non-uniform (solid)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7)
    from matplotlib.ticker import NullFormatter, ScalarFormatter
    for ax in axes:
        ax.xaxis.set_major_formatter(ScalarFormatter())
        ax.xaxis.set_minor_formatter(NullFormatter())
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def _print_summary(result, say):
    say(f"cubature study on {result['scene']} ({result['poses']} poses, 20% held out), {result['seconds']:.1f} s")
    say("  samples  " + "  ".join(f"{d['domain']:>10s}" for d in result["domains"]))
    for n, s in enumerate(result["counts"]):
        vals = [d["errors"][n]["held_out"] if n < len(d["errors"]) else float("nan") for d in result["domains"]]
        say(f"  {s:7d}  " + "  ".join(f"{v:10.2e}" for v in vals))
    for it in result["interfaces"]:
        say(f"  interface {'-'.join(it['pair'])} ({it['elements']} elements): samples / uniform / non-uniform")
        for u, v in zip(it["uniform"], it["nonuniform"]):
            say(f"    {u['samples']:5d}  {u['mean']:.2e}  {v['mean']:.2e}")


def cubature_report(out, quick=False, overrides=None, log=print):
    """`mdss verify cubature`: the registry entry (table and plots for the summary)."""
    if overrides:
        raise ValueError("mdss verify cubature takes no --set options")
    lines = []
    result = cubature_study(out, quick=quick, progress=lambda msg: (lines.append(msg), log(msg)))
    start = next(i for i, line in enumerate(lines) if line.startswith("cubature study"))
    result["table"] = "\n".join(lines[start:])
    result["plots"] = [str(Path(out) / "cubature.png")]
    return result
