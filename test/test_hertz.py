"""Hertz contact (docs/method.md §16.3): a rigid sphere pressed into a graded 2 m block.

The fast test runs full-space FEM at one named resolution; the slow test runs
`mdss verify hertz --quick` and checks its JSON. Both use mdss_ros.verify.hertz_study, whose
docstring gives the setup (bottom-fixed 2 m cube, contact radius <= 2 cm, so the block is
100 contact radii wide and its fixed bottom stiffens the answer by about 0.7 %).
"""
import json

import numpy as np
import pytest

from mdss_ros import Simulator
from mdss_ros.verify import hertz_study as hz


def test_hertz_closed_form_is_consistent():
    R, e_star = 0.5, hz.effective_modulus(1e5, 0.3)
    d = np.array([1e-4, 5e-4, 2e-3])
    np.testing.assert_allclose(hz.hertz_indentation(hz.hertz_force(d, R, e_star), R, e_star), d, rtol=1e-12)
    # a = sqrt(R d) and F = 4 E* a^3 / (3 R): the contact-radius form of the same law.
    a = np.sqrt(R * d)
    np.testing.assert_allclose(hz.hertz_force(d, R, e_star), 4 * e_star * a ** 3 / (3 * R), rtol=1e-12)
    e, l2, emax = hz.indentation_errors(hz.hertz_force(d, R, e_star), 1.02 * d, R, e_star)
    np.testing.assert_allclose(e, 0.02)
    assert abs(l2 - 0.02) < 1e-12 and abs(emax - 0.02) < 1e-12


LEVEL = 3          # a_ref / h: fine cells of 6.7 mm under a contact radius of up to 2 cm


def test_hertz_full_fem_indentation_within_5_percent_at_a_over_h_3():
    """Full-space FEM, graded 2 m cube (bottom fixed) with fine cells h = a_ref / 3 = 6.7 mm
    within 4 cm of the contact point (58806 DOFs); the sphere (R = 0.5 m) is pressed to rest
    at the Hertz indentations of three forces spanning a factor 2 (contact radius 1.6-2 cm,
    a / R <= 0.04: small strain). Each measured (F, d) pair is within 5 % of d_H(F) (measured
    -3.8, -2.4, -2.0 %). The coarser a/h = 2 mesh was off by 6.3 % at half the force, where
    the contact edge falls between fine nodes. About 40 s of CPU (two PARDISO threads)."""
    cfg = dict(hz.HERTZ)
    R = cfg["sphere_radius"]
    e_star = hz.effective_modulus(cfg["material"]["young"], cfg["material"]["poisson"])
    F_max = hz.hertz_force(cfg["a_ref"] ** 2 / R, R, e_star)
    sim = Simulator(hz.hertz_scene(cfg, LEVEL, "full"))
    forces, depths = [], []
    for frac in (0.5, 0.75, 1.0):
        res = hz.press_to_rest(sim, float(hz.hertz_indentation(frac * F_max, R, e_star)), R)
        forces.append(res["force"])
        depths.append(res["depth"])
        # At rest on the sphere: no vertex inside it beyond round-off, force along +z only.
        phi = sim.colliders["ball"].signed_distance(sim.vertex_positions())[0]
        assert phi.min() > -1e-6 * res["depth"]
        w = sim.collider_wrench("ball")
        assert np.abs(w[:2]).max() < 1e-3 * w[2]          # lateral only from the mesh's asymmetry
    e, l2, emax = hz.indentation_errors(forces, depths, R, e_star)
    print(f"a/h = {LEVEL}: {sim.model.n_dofs} DOFs, errors {np.round(100 * e, 2)} %, L2 {100 * l2:.2f} %")
    assert emax < 0.05, e
    # The model is a little stiffer than the half-space (finite block, discretisation).
    assert np.all(e < 0.0), e
    assert np.all(np.diff(forces) > 0)


@pytest.mark.claims
def test_verify_hertz_quick_report(tmp_path):
    from mdss_ros.cli import main
    assert main(["verify", "hertz", "--out", str(tmp_path), "--quick"]) == 0
    data = json.loads((tmp_path / "hertz.json").read_text())
    rows = data["rows"]
    full = sorted((r for r in rows if r["kind"] == "full"), key=lambda r: r["dofs"])
    reduced = [r for r in rows if r["kind"] == "reduced"]
    assert len(full) == len(hz.QUICK["levels"]) and len(reduced) == len(hz.QUICK["reduced_levels"])
    for r in rows:
        assert len(r["points"]) == len(hz.QUICK["force_fractions"])
        for p in r["points"]:
            # The pair's own error is what the row reports.
            assert abs(p["rel_error"] - (p["depth"] - p["depth_hertz"]) / p["depth_hertz"]) < 1e-12
            assert p["force"] > 0
        ff = r["fixed_force"]
        assert abs(ff["force"] - ff["target"]) <= data["config"]["force_tol"] * ff["target"] + 1e-12
        assert r["step_ms"] > 0
    # Refinement helps and the finer full model is within 5 % at every force.
    assert full[-1]["l2_error"] < full[0]["l2_error"]
    assert full[-1]["max_error"] < 0.05
    assert data["within"]["full"]["5%"] == full[-1]["dofs"]
    # Fig. 5: the force-controlled indentation at the fixed force approaches Hertz's.
    assert abs(full[-1]["fixed_force"]["rel_error"]) < abs(full[0]["fixed_force"]["rel_error"])
    # The reduced model (full-space contact zone in a subspace block) on the same mesh as a
    # full model: fewer DOFs, and its far-field subspace adds at most 3 % to the error.
    red = reduced[0]
    same = next(r for r in full if r["level"] == red["level"])
    assert red["dofs"] < same["dofs"] / 3
    for p_red, p_full in zip(red["points"], same["points"]):
        assert abs(p_red["rel_error"] - p_full["rel_error"]) < 0.03
    for name in data["plots"]:
        assert (tmp_path / name).stat().st_size > 5000
