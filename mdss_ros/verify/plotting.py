"""PNG plots of the verification reports (matplotlib, Agg backend: no display needed).

Every function takes the report's plain data and a path, writes the PNG and returns the
path as a string.
"""
import numpy as np


def pyplot():
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    return plt


def save_figure(fig, path, rect=None):
    """Lay out (within rect (left, bottom, right, top) of the figure, default all of it),
    save at 110 dpi and close; the path as str."""
    fig.tight_layout(rect=rect)
    fig.savefig(path, dpi=110)
    pyplot().close(fig)
    return str(path)


SCHEME_STYLE = {"one_step": dict(color="tab:blue", label="one-step (unified)"),
                "two_step": dict(color="tab:red", ls="--", label="two-step (rigid, then deformation)")}


def energy_curves(runs, path, title=""):
    """E(t) / E0, one panel per dt, one line per scheme."""
    plt = pyplot()
    labels = list(dict.fromkeys(r["dt_label"] for r in runs))
    n = len(labels)
    cols = 2 if n > 1 else 1
    rows = (n + cols - 1) // cols
    fig, axes = plt.subplots(rows, cols, figsize=(6 * cols, 3.4 * rows), squeeze=False)
    for ax, lab in zip(axes.ravel(), labels):
        for r in runs:
            if r["dt_label"] != lab:
                continue
            t, E = np.asarray(r["t"]), np.asarray(r["total"])
            ax.plot(t, E / r["E0"], **SCHEME_STYLE.get(r["scheme"], {"label": r["scheme"]}))
        ax.set_title(f"dt = {lab} s")
        ax.set_xlabel("time (s)")
        ax.set_ylabel("E / E0")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    for ax in axes.ravel()[n:]:
        ax.axis("off")
    if title:
        fig.suptitle(title)
    return save_figure(fig, path)


def cantilever_errors(rows, path):
    """|relative error| vs closed forms of tip deflection, gravity sag and first frequency
    against DOFs (log-log): full-space lines over resolutions, reduced models as markers."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(7, 4.5))
    full = [r for r in rows if r.get("kind", "full") == "full"]
    red = [r for r in rows if r.get("kind") == "reduced"]
    series = (("static_rel_error", "o", "tab:blue", "static tip deflection"),
              ("sag_rel_error", "^", "tab:green", "gravity sag"),
              ("frequency_rel_error", "s", "tab:orange", "first bending frequency"))
    for key, marker, colour, label in series:
        if full and key in full[0]:
            ax.loglog([r["dofs"] for r in full], [abs(r[key]) for r in full], marker + "-", color=colour,
                      label=f"full FEM: {label}")
        if red and key in red[0]:
            ax.loglog([r["dofs"] for r in red], [abs(r[key]) for r in red], marker, color=colour, mfc="none",
                      ms=9, label=f"reduced: {label}")
    for r in full:
        ax.annotate(f"cell {r['cell']:.3g}", (r["dofs"], abs(r["static_rel_error"])), fontsize=7,
                    textcoords="offset points", xytext=(4, 4))
    for r in red:
        ax.annotate(f"{r['domains']}x{r['modes']}", (r["dofs"], abs(r["static_rel_error"])), fontsize=7,
                    textcoords="offset points", xytext=(4, -10))
    ax.set_xlabel("DOFs")
    ax.set_ylabel("|relative error| vs closed form")
    ax.set_title("Cantilever vs Euler-Bernoulli + shear (reduced: on the cell 0.025 mesh)", fontsize=10)
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=7)
    return save_figure(fig, path)


def coupling_bars(variants, path):
    """Bars (log scale, values on top): RMS surface error, and mean / max |interface edge
    stretch| per variant."""
    plt = pyplot()
    names = [v["label"] for v in variants]
    x = np.arange(len(names))
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.6))
    bars = axes[0].bar(x, [100 * v["rms_rel"] for v in variants], color="tab:blue")
    axes[0].bar_label(bars, fmt="%.3g", fontsize=7)
    axes[0].set_ylabel("RMS surface error / peak displacement (%)")
    axes[0].set_title("Surface error vs full-space FEM")
    w = 0.38
    for off, key, lab in ((-w / 2, "mean_abs", "mean |s|"), (w / 2, "max_abs", "max |s|")):
        bars = axes[1].bar(x + off, [100 * v["interface"][key] for v in variants], w, label=lab)
        axes[1].bar_label(bars, fmt="%.2g", fontsize=6)
    axes[1].set_ylabel("interface edge stretch vs FEM, |s| (% of rest length)")
    axes[1].set_title("Gap / overlap at the interface")
    axes[1].legend(fontsize=8)
    for ax in axes:
        ax.set_yscale("log")
        ax.set_xticks(x)
        ax.set_xticklabels(names, rotation=25, ha="right", fontsize=8)
        ax.grid(alpha=0.3, axis="y", which="both")
    return save_figure(fig, path)


def coupling_side_views(truth_xz, variants, interface_xz, path, window=0.06):
    """x-z scatter of surface vertices per variant (one row each) over the ground truth
    (grey): the whole beam (left) and a window of half-width `window` m around the
    interface (right), equal axes."""
    plt = pyplot()
    n = len(variants)
    fig, axes = plt.subplots(n, 2, figsize=(13, 2.9 * n), squeeze=False,
                             gridspec_kw={"width_ratios": [3.2, 1]})
    cx, cz = interface_xz
    for j, v in enumerate(variants):
        xz = np.asarray(v["surface_xz"])
        lab = np.asarray(v["surface_domain"])
        for col in range(2):
            ax = axes[j, col]
            ax.scatter(truth_xz[:, 0], truth_xz[:, 1], s=14 if col else 6, c="0.7", label="full-space FEM")
            for d, colour in zip(np.unique(lab), ("tab:blue", "tab:orange", "tab:green", "tab:red")):
                sel = lab == d
                ax.scatter(xz[sel, 0], xz[sel, 1], s=4 if col else 1.5, c=colour, label=f"domain {d}")
            ax.set_aspect("equal")
            ax.grid(alpha=0.3)
            ax.set_xlabel("x (m)")
            ax.set_ylabel("z (m)")
            if col == 1:
                ax.set_xlim(cx - window, cx + window)
                ax.set_ylim(cz - window, cz + window)
                ax.set_title("interface window", fontsize=9)
            else:
                ax.set_title(f"{v['label']}: RMS error {100 * v['rms_rel']:.2f} % of peak", fontsize=9)
                ax.legend(fontsize=7, loc="lower left", markerscale=3)
    return save_figure(fig, path)


DOMAIN_COLORS = {1: "tab:blue", 2: "tab:orange", 4: "tab:green", 8: "tab:red"}


def accuracy_error_vs_dofs(rows, path):
    """RMS surface error vs DOFs, one line per domain count (points labelled with r)."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(6.5, 4.5))
    for d in sorted({r["domains"] for r in rows}):
        rr = sorted((r for r in rows if r["domains"] == d), key=lambda r: r["dofs"])
        ax.loglog([r["dofs"] for r in rr], [100 * r["rms_rel"] for r in rr], "o-",
                  color=DOMAIN_COLORS.get(d), label=f"{d} domain{'s' if d > 1 else ''}")
        for r in rr:
            ax.annotate(f"r={r['modes']}", (r["dofs"], 100 * r["rms_rel"]), fontsize=7,
                        textcoords="offset points", xytext=(3, 3))
    ax.set_xlabel("reduced DOFs")
    ax.set_ylabel("RMS surface error / peak displacement (%)")
    ax.set_title("Reduced vs full-space FEM, static large deflection")
    ax.grid(alpha=0.3, which="both")
    ax.legend()
    return save_figure(fig, path)


def accuracy_cost_vs_error(rows, full_ms, path):
    """Median ms per step vs RMS error, marker colour by domain count; full-space line."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(6.5, 4.5))
    for d in sorted({r["domains"] for r in rows}):
        rr = [r for r in rows if r["domains"] == d]
        ax.scatter([100 * r["rms_rel"] for r in rr], [r["step_ms"] for r in rr], color=DOMAIN_COLORS.get(d),
                   label=f"{d} domain{'s' if d > 1 else ''}")
        for r in rr:
            ax.annotate(f"r={r['modes']}", (100 * r["rms_rel"], r["step_ms"]), fontsize=7,
                        textcoords="offset points", xytext=(3, 3))
    if full_ms:
        ax.axhline(full_ms, color="k", ls=":", label=f"full-space FEM ({full_ms:.0f} ms)")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("RMS surface error / peak displacement (%)")
    ax.set_ylabel("median ms / step (dt = 1/90, 1 Newton iteration)")
    ax.set_title("Cost vs accuracy")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8)
    return save_figure(fig, path)


def modes_errors(rows, mode_labels, path):
    """Left: |error| of each natural frequency vs the closed form against DOFs (full
    models, one line per mode). Right: reduced models' frequency error vs full FEM on
    the same mesh, one group of bars per configuration (log scale)."""
    plt = pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(13, 4.6))
    full = [r for r in rows if r["kind"] == "full"]
    red = [r for r in rows if r["kind"] == "reduced"]
    n = len(mode_labels)
    for i in range(n):
        axes[0].loglog([r["dofs"] for r in full], [max(abs(r["closed_form_rel_error"][i]), 1e-8) for r in full],
                       "o-", label=f"f{i + 1}: {mode_labels[i]}")
    axes[0].set_xlabel("DOFs")
    axes[0].set_ylabel("|f - f_closed| / f_closed")
    axes[0].set_title("Full-space FEM vs closed forms (EB bending, St-Venant torsion, axial)")
    axes[0].grid(alpha=0.3, which="both")
    axes[0].legend(fontsize=7)
    if red:
        x = np.arange(len(red))
        w = 0.8 / n
        for i in range(n):
            axes[1].bar(x + (i - (n - 1) / 2) * w, [max(abs(r["vs_full_rel_error"][i]), 1e-8) for r in red], w,
                        label=f"f{i + 1}")
        axes[1].set_xticks(x)
        axes[1].set_xticklabels([f"{r['domains']} x {r['modes']}\n{r['dofs']} DOFs" for r in red], fontsize=7)
        axes[1].set_xlabel("domains x modes per domain")
        axes[1].set_yscale("log")
        axes[1].set_ylabel("(f_reduced - f_full) / f_full")
        axes[1].set_title("Reduced models vs full FEM on the same mesh")
        axes[1].grid(alpha=0.3, axis="y", which="both")
        axes[1].legend(fontsize=7, ncol=2)
    else:
        axes[1].axis("off")
    return save_figure(fig, path)
