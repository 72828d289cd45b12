"""Natural frequencies from the linearised models (mdss_ros/verify/modes_study.py)."""
import numpy as np
import pytest

from mdss_ros import Simulator
from mdss_ros.verify.closed_forms import cantilever_first_frequency, cantilever_frequencies
from mdss_ros.verify.modes_study import full_frequencies, reduced_frequencies, reduced_matrices
from mdss_ros.verify.reduced_reports import beam_scene

SMALL = dict(size=(0.4, 0.1, 0.1), cell=0.05)


def test_closed_form_frequency_list_is_sorted_and_starts_with_bending():
    modes = cantilever_frequencies(1.0, 1e6, 0.3, 1000.0, 0.1, 0.1, count=6)
    labels = [m[0] for m in modes]
    assert labels[:2] == ["bending 1 (z)", "bending 1 (y)"] and "torsion 1" in labels and "axial 1" in labels
    assert [f for _, f in modes] == sorted(f for _, f in modes)
    assert modes[0][1] == pytest.approx(cantilever_first_frequency(1.0, 1e6, 1000.0, 0.1, 0.1), rel=1e-12)


def test_complete_reduced_basis_has_the_full_models_frequencies():
    """One pinned domain with a complete basis is a change of basis: same spectrum."""
    full = Simulator(beam_scene("full", **SMALL))
    red = Simulator(beam_scene("reduced", **SMALL, modes=1000, domains={"count": 1}, basis={"complete": True}))
    f_full = full_frequencies(full, 6)
    f_red = reduced_frequencies(red, 6)
    np.testing.assert_allclose(f_red, f_full, rtol=1e-7)


def test_reduced_matrices_are_symmetric_and_reproduce_the_system_matrix():
    sim = Simulator(beam_scene("reduced", **SMALL, modes=6, domains={"count": 2}))
    M, K = reduced_matrices(sim)
    dt = 0.007
    sim.model.set_dt(dt)
    np.testing.assert_allclose(M + dt * dt * K, sim.model.system_matrix(), rtol=1e-9, atol=1e-9 * np.abs(M).max())
    assert np.all(np.linalg.eigvalsh(M) > 0)


def test_multi_domain_reduction_only_stiffens():
    """Galerkin: each reduced frequency is at least the full model's on the same mesh."""
    full = full_frequencies(Simulator(beam_scene("full", **SMALL)), 4)
    red = reduced_frequencies(Simulator(beam_scene("reduced", **SMALL, modes=8, domains={"count": 2})), 4)
    assert np.all(red >= full * (1 - 1e-9)) and np.all(red < 1.2 * full)


def test_damped_model_is_refused():
    sim = Simulator(beam_scene("reduced", **SMALL, damping=(0.5, 0.0), modes=4, domains={"count": 1}))
    with pytest.raises(ValueError, match="without damping"):
        reduced_matrices(sim)
