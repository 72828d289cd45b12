"""Full-space cantilever against Euler-Bernoulli/Timoshenko closed forms.

Linear tets lock in bending, so accuracy needs resolution: the fast suite checks that
the error falls with refinement; the slow study checks the 3 % targets at a named
resolution: 200 x 4 x 20 cells along length, width and height (96,000 tets); cubic
cells would need about 245,000 tets for the same error.
"""
import pytest

from mdss_ros.verify.cantilever import free_vibration_frequency, static_tip_deflection

FINE = (200, 4, 20)


def _err(measured, ref):
    return abs(measured - ref) / abs(ref)


def test_static_deflection_error_falls_with_refinement():
    errs = [_err(*static_tip_deflection(cell)) for cell in (0.05, 0.025)]
    assert errs[1] < 0.75 * errs[0], errs


def test_frequency_error_falls_with_refinement():
    errs = [_err(*free_vibration_frequency(cell, periods=1.6, steps_per_period=60)) for cell in (0.05, 0.025)]
    assert errs[1] < 0.75 * errs[0], errs


@pytest.mark.claims
def test_static_deflection_at_8_cells_through_the_height_is_the_reported_7_percent():
    """The README's row: linear tets lock in bending, so 8 cubic cells through the height
    (80 x 8 x 8 cells, 30,720 tets) give a tip deflection 7.03 % short of Euler-Bernoulli +
    Timoshenko (`mdss verify cantilever` reports the whole ladder). About 14 s."""
    err = _err(*static_tip_deflection(0.0125))
    assert err == pytest.approx(0.0703, abs=5e-4)


@pytest.mark.slow
def test_static_deflection_within_3_percent_fine_mesh():
    measured, ref = static_tip_deflection(FINE)
    assert _err(measured, ref) < 0.03, (measured, ref)


@pytest.mark.slow
def test_first_frequency_within_3_percent_fine_mesh():
    measured, ref = free_vibration_frequency(FINE, periods=1.6)
    assert _err(measured, ref) < 0.03, (measured, ref)
