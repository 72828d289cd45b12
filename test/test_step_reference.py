"""The reduced step reproduces its recorded answers to round-off (test/step_reference.py)."""
import numpy as np
import pytest

import step_reference as ref


@pytest.mark.parametrize("name", sorted(ref.CASES))
def test_step_reproduces_reference_positions(name):
    recorded = np.load(ref.PATH)[name]
    x, rest = ref.run(name)
    assert np.abs(recorded - rest).max() > 1e-3          # the case moves the body
    assert ref.relative_error(x, recorded, rest) <= ref.TOLERANCE


@pytest.mark.parametrize("name", ["cubature_nonuniform_free", "contact"])
def test_step_is_bit_identical_from_run_to_run(name):
    """The parallel kernels write disjoint outputs and sum in a fixed order, so the same
    scene and inputs give the same bits whatever the thread schedule."""
    a, _ = ref.run(name, steps=50)
    b, _ = ref.run(name, steps=50)
    assert np.array_equal(a, b)
