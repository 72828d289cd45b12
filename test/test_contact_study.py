"""`mdss verify contact` (mdss_ros/verify/contact_study.py): contact force at reduced cost
against full-space FEM, the README's contact claims at the quick size (soft_finger and
the squeezed cube; hertz_block's rows take minutes and run in the full report)."""
import json

import numpy as np
import pytest

from mdss_ros.verify import contact_study as cs


def test_rows_of_a_case_name_the_old_remedy_and_the_counts():
    labels = [label for label, _ in cs.case_rows("hertz_block", [50, 800])]
    assert labels == ["full", "modes only", "full-space patch", "residual 50", "residual 800"]
    ov = dict(cs.case_rows("soft_finger", [200]))
    assert ov["modes only"] == {"model.contact_compliance": 0}
    assert "colliders.probe.reach" in ov["reach patch"]
    with pytest.raises(ValueError, match="unknown case"):
        cs.case_rows("nothing", [1])
    # The anchors: contact modes instead of the residual compliance, samples per mode kept
    # (hertz_block: 400 samples for 40 modes).
    ov = dict(cs.case_rows("hertz_block", [50], ["static", "local"], [10, 90]))
    assert ov["static 90"] == {"model.contact_compliance": 0, "model.contact_modes.kind": "static",
                               "model.contact_modes.count": 90, "model.cubature.samples": 1300}
    assert ov["local 10"]["model.cubature.samples"] == 500
    assert "model.cubature.samples" not in dict(cs.case_rows("grasp", [50], ["static"], [10]))["static 10"]


@pytest.mark.claims
def test_quick_contact_report_meets_the_soft_finger_and_grasp_targets(tmp_path):
    """Held in contact, the default reduced models read full FEM's force within 10 % (the
    probe: measured -8.1 %; the pads' grip: -4.4 %) where their modes alone read 3.4x and
    5.3x too much. (Step times are the report's, not asserted here.)"""
    from mdss_ros.cli import main
    assert main(["verify", "contact", "--out", str(tmp_path), "--quick"]) == 0
    data = json.loads((tmp_path / "contact.json").read_text())
    rows = {(r["case"], r["model"]): r for r in data["rows"]}
    assert set(c for c, _ in rows) == {"soft_finger", "grasp"}
    for case in ("soft_finger", "grasp"):
        full, modes, res = rows[(case, "full")], rows[(case, "modes only")], rows[(case, "residual 200")]
        assert full["force"] > 0 and abs(full["error"]) == 0.0
        assert abs(res["error"]) < 0.10, (case, res["force"], full["force"])
        assert modes["error"] > 2.0, (case, modes["force"], full["force"])
        # at most 200: the 4 cm cube has 98 surface vertices
        assert 0 < res["compliance_vertices"] <= 200 and modes["compliance_vertices"] == 0
        assert res["dofs"] == modes["dofs"] < full["dofs"] / 10
    # The reach patch: closer than the modes, not as close as the residual compliance.
    reach = rows[("soft_finger", "reach patch")]
    assert abs(rows[("soft_finger", "residual 200")]["error"]) < abs(reach["error"]) < rows[("soft_finger", "modes only")]["error"]
    # The anchor (README, "Contact"): 30 static contact modes a domain come within 10 % on the
    # probe's one small contact (measured +6.2 %), but not on the pads' fifty contact
    # vertices (+256 %), which the residual compliance gets within 5 %.
    assert abs(rows[("soft_finger", "static 30")]["error"]) < 0.10, rows[("soft_finger", "static 30")]["force"]
    assert rows[("grasp", "static 30")]["error"] > 1.0, rows[("grasp", "static 30")]["force"]
    assert rows[("grasp", "static 30")]["dofs"] == rows[("grasp", "modes only")]["dofs"] + 30
    assert all(np.isfinite(r["step_ms"]) and r["step_ms"] > 0 for r in data["rows"])
    assert any("soft_finger" in n for n in data["notes"])
    assert (tmp_path / "contact_tradeoff.png").stat().st_size > 5000
