"""`mdss stability --quick` end to end (slow): the JSON table, the heat maps, no failed
cell."""
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from mdss_ros.verify.stability_study import MATERIALS

ROOT = Path(__file__).resolve().parents[1]


def _key(r):
    return (r["kind"], r["material"], r["young"], r["poisson"], round(r["dt"], 12), r["spin"], r["force"],
            r.get("mu"), r.get("speed"))


def check_report(report):
    """The checks on a stability.json (also usable on a full run's JSON). Returns the failed
    full and reduced cells (the target: none); a failed meshless cell must say why."""
    rows = report["rows"]
    # {kind: materials}; a JSON from before the meshless column ran full and reduced x 3.
    per_kind = report["design"].get("kinds") or {"full": MATERIALS, "reduced": MATERIALS}
    runs = sum(len(m) for m in per_kind.values())
    assert len(rows) == report["design"]["cells"] * runs
    for kind, materials in per_kind.items():
        assert {r["material"] for r in rows if r["kind"] == kind} == set(materials)
    if "meshless" in per_kind:          # one material: the meshless law is its own
        assert per_kind["meshless"] == [report["design"]["meshless_material"]]
    # every value of every parameter appears (the contact cells have their own axes)
    matrix = [r for r in rows if "mu" not in r]
    for name in ("young", "poisson", "dt", "spin", "force"):
        assert {r[name] for r in matrix} == set(report["design"][name])
    contact = [r for r in rows if "mu" in r]
    assert len(contact) == report["design"]["contact"]["cells"] * runs
    if not report["design"]["quick"]:
        for name in ("mu", "speed", "young"):
            assert {r[name] for r in contact} == set(report["design"]["contact"][name])
    # The target of issue 7: no failed cell. (The last 5, a 1 kPa body under the 1 kN load,
    # were fixed by the compression barrier, fem/materials.py, and the guard's untangle.)
    # Issue 7's target is the full and reduced models'; the meshless model (a first version,
    # docs/method.md §19.6) is reported as it is.
    failed = [r for r in rows if r["status"] == "failed" and r["kind"] != "meshless"]
    assert not failed, [(_key(r), r["why"]) for r in failed]
    assert all(r["why"] for r in rows if r["status"] == "failed")
    for r in rows:
        if r["status"] == "recovered":          # every recovered cell says what the guard did
            assert r["actions"] and all(a.startswith(("rollback", "untangled")) for a in r["actions"])
        if any("untangled" in a for a in r["actions"]):
            assert r["kind"] == "reduced"        # full-space models un-invert through their materials
        if r["status"] == "stable":
            assert not r["actions"] and r["energy_created_ratio"] <= report["design"]["energy_bound"]
    return failed


@pytest.mark.claims
@pytest.mark.timeout(3600)
def test_stability_quick_matrix(tmp_path):
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    out = subprocess.run([sys.executable, "-W", "ignore", "-m", "mdss_ros.cli", "stability", "--quick",
                          "--out", str(tmp_path)], cwd=ROOT, env=env, capture_output=True, text=True,
                         timeout=3600)
    assert "stable" in out.stdout and "[  1/" in out.stdout, out.stdout[-2000:] + out.stderr[-2000:]
    report = json.loads((tmp_path / "stability.json").read_text())
    for kind in ("full", "reduced"):            # the default kinds (meshless: --kinds meshless)
        assert (tmp_path / f"stability_{kind}.png").stat().st_size > 10_000
    assert {r["kind"] for r in report["rows"]} == {"full", "reduced"}
    assert not check_report(report)
    assert out.returncode == 0, out.stdout[-2000:] + out.stderr[-2000:]


@pytest.mark.slow
def test_stiff_spun_reduced_corner_recovers():
    """The reduced corotated corner that failed runs 12 and earlier (E 1e11 Pa, nu 0, dt
    1/30, spin 50, force x 1e3): Newton's plain direction raised the potential at every
    line-search length and the loop took its shortest length anyway, 23 J -> 35,000 J in
    one sub-step, every rung failed (reduced/step.py, Step._line_search). About 40 s."""
    from mdss_ros.verify.stability_study import ENERGY_BOUND, run_cell
    r = run_cell("reduced", "corotated", {"young": 1e11, "poisson": 0.0, "dt": 1 / 30, "spin": 50.0,
                                          "force": 1000.0}, 24)
    assert r["status"] in ("stable", "recovered"), r
    assert r["energy_created_ratio"] <= ENERGY_BOUND


def test_observation_window_after_release():
    """A cell left inverted is observed on for up to OBSERVE_TRANSITS shear-wave transits
    after the release (capped): 0.28 s per transit for the 1 kPa, nu = 0 box."""
    from mdss_ros.verify import stability_study as st
    assert st.transit_time(1e3, 0.0) == pytest.approx(0.2 / (500.0 / 1000.0) ** 0.5)
    steps = st.STEPS
    after = steps - steps // 2
    cell = dict(young=1e3, poisson=0.0, dt=1.0 / 30.0)
    assert st.extra_steps(cell, steps) == int(-(-4 * st.transit_time(1e3, 0.0) * 30 // 1)) - after == 22
    assert st.extra_steps(dict(cell, dt=1.0 / 90.0), steps) == 102 - after
    assert st.extra_steps(dict(cell, dt=1e-4), steps) == st.OBSERVE_MAX_STEPS        # capped
    assert st.extra_steps(dict(cell, young=1e11), steps) == 0                         # stiff: no extension


def test_a_stable_cell_runs_its_steps_only():
    from mdss_ros.verify.stability_study import BASE, run_cell
    r = run_cell("full", "corotated", BASE, 8)
    assert r["status"] == "stable" and r["steps_run"] == 8 and r["inverted_release"] == 0
    assert r["inverted_end"] == 0 and not r["why"]


# ---------------------------------------------------------------------- the meshless column
def test_meshless_column_runs_one_material():
    from mdss_ros.verify import stability_study as st
    assert st.kind_materials("full") == st.MATERIALS == st.kind_materials("reduced")
    assert st.kind_materials("meshless") == [st.MESHLESS_MATERIAL]
    assert st.kind_materials("meshless", ["neohookean", "corotated"]) == ["neohookean"]
    assert st.kind_materials("full", ["corotated"]) == ["corotated"]


def test_meshless_cell_scene_has_no_domains_and_builds_a_meshless_model():
    from mdss_ros import Simulator
    from mdss_ros.verify import stability_study as st
    scene = st.cell_scene("meshless", "stvk", 1e7, 0.3, 1.0 / 90.0, 0.0)
    assert set(scene["model"]) == {"kind", "integrator"}
    # full and reduced cells keep their model section
    assert st.cell_scene("reduced", "stvk", 1e7, 0.3, 1.0 / 90.0, 0.0)["model"] == {
        "kind": "reduced", "domains": {"count": 2}, "modes": 8,
        "cubature": {"samples": 0, "interface": "exact"}, "integrator": {"dt": 1.0 / 90.0, "newton_iterations": 1}}
    sim = Simulator(scene)
    assert sim.model.kind == "meshless" and sim.model.newton_iterations == 1
    contact = Simulator(st.contact_scene("meshless", "stvk", 1e4, 0.5))
    assert contact.model.kind == "meshless" and set(contact.colliders) == {"floor", "ball"}


def test_meshless_base_and_contact_cells_run_and_are_classified(tmp_path):
    """The base cell (1e7 Pa cantilever, 1 N tip load) and a contact cell through run_cell
    and the study's summary, heat map and JSON, the meshless column alone (as
    `mdss stability --kinds meshless` runs it). A few seconds."""
    from mdss_ros.verify import stability_study as st
    steps = 8
    base = st.run_cell("meshless", "stvk", st.BASE, steps)
    assert base["kind"] == "meshless" and base["steps_run"] == steps
    # The base point is stable for the meshless model too (HEAD: stable, 0.9 s at 16 steps).
    assert base["status"] == "stable" and not base["why"] and base["inverted_end"] == 0
    cell = st.contact_design(quick=True)[0]
    contact = st.run_cell("meshless", "stvk", cell, steps)
    assert contact["status"] in st.COLOURS and contact["dofs"] > 0
    rows = [base, contact]
    counts, table = st.summary(rows)
    assert set(counts) == {"meshless"} and sum(counts["meshless"].values()) == 2
    assert "meshless stvk" in table and "one material (stvk)" in table
    png = st.heatmap(rows, "meshless", [st.BASE, cell], tmp_path / "m.png")
    assert (tmp_path / "m.png").stat().st_size > 5000 and png.endswith("m.png")
    report = {"design": {"cells": 2, "kinds": {"meshless": ["stvk"]}, "meshless_material": "stvk", "quick": True,
                         "young": sorted({r["young"] for r in rows if "mu" not in r}),
                         "poisson": [st.BASE["poisson"]], "dt": [st.BASE["dt"]], "spin": [0.0], "force": [1.0],
                         "energy_bound": st.ENERGY_BOUND, "contact": {"cells": 1}},
              "rows": rows}
    assert not check_report(report)


def test_contact_only_runs_the_contact_cells_alone(tmp_path):
    """`mdss stability --contact-only`: the contact cells and nothing else (quick: two)."""
    from mdss_ros.verify import stability_study as st
    report = st.run_study(tmp_path, quick=True, kinds=["reduced"], materials=["stvk"], log=lambda msg: None,
                          contact_only=True)
    assert report["design"]["cells"] == len(st.contact_design(quick=True)) == len(report["rows"]) == 2
    assert all("mu" in r for r in report["rows"])
    assert sum(report["counts"]["reduced"].values()) == 2
