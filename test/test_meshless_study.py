"""`mdss verify meshless` (verify/meshless_study.py) at its smallest size: one row of each
model on the 0.05 m beam, and the equal-error comparison it reports."""
import numpy as np
import pytest

from mdss_ros.verify.meshless_study import MESHLESS, equal_error_comparison, run_row


@pytest.mark.claims
def test_meshless_rows_measure_errors_cost_and_hourglass_modes():
    cfg = dict(MESHLESS, timing_steps=2)
    rows = [run_row(v, 0.05, cfg, log=lambda *_: None) for v in ("full", "meshless")]
    full, ml = rows
    assert full["nodes"] == ml["nodes"] == 189
    for r in rows:
        assert np.isfinite([r["tip_rel_error"], r["sag_rel_error"], r["f1_rel_error"], r["step_ms"]]).all()
    # The same small-strain beam: tip load and self weight are both bending, so the two
    # errors agree to a few tenths of a percent; linear tets on 2 cells are much too stiff.
    assert abs(full["tip_rel_error"] - full["sag_rel_error"]) < 0.01 and full["tip_rel_error"] < -0.3
    assert ml["hourglass_modes"] == 0 and "hourglass_modes" not in full
    assert ml["stiffness_nnz"] > full["stiffness_nnz"]          # the 2-ring stencil couples more


def test_equal_error_comparison_picks_the_cheapest_full_row_at_least_as_accurate():
    rows = [{"model": "full", "tip_rel_error": -0.2, "step_ms": 5.0},
            {"model": "full", "tip_rel_error": -0.05, "step_ms": 50.0},
            {"model": "full", "tip_rel_error": -0.01, "step_ms": 500.0},
            {"model": "meshless", "tip_rel_error": 0.04, "step_ms": 40.0},
            {"model": "meshless", "tip_rel_error": 0.001, "step_ms": 400.0}]
    (m1, f1), (m2, f2) = equal_error_comparison(rows)
    assert f1["step_ms"] == 500.0 and f2 is None
