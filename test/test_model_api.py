"""Every model kind offers model_api.Model, and StepOptions change one step only."""
import numpy as np
import pytest

from mdss_ros import Simulator
from mdss_ros.model_api import Model
from mdss_ros.step_options import StepOptions


def _scene(kind, **model):
    return {"name": "t",
            "body": {"mesh": {"generator": "box", "size": [0.2, 0.05, 0.05], "cell": 0.025},
                     "material": {"model": "neohookean", "young": 2e4, "poisson": 0.3, "density": 1000},
                     "damping": {"alpha": 0.1, "beta": 0.001}},
            "pins": [{"box": [[-0.001, -1, -1], [0.001, 1, 1]]}],
            "handles": {"tip": {"box": [[0.199, -1, -1], [0.201, 1, 1]]}},
            "gravity": [0.0, 0.0, -9.81],
            "model": {"kind": kind, **model}}


KINDS = {"full": {}, "reduced": {"domains": {"count": 2}, "modes": 6}, "meshless": {}}


@pytest.mark.parametrize("kind", sorted(KINDS))
def test_model_offers_the_interface(kind):
    sim = Simulator(_scene(kind, **KINDS[kind]))
    m = sim.model
    assert isinstance(m, Model)
    n = len(sim.rest_positions())
    assert np.asarray(m.vertex_domain).shape == (n,)
    assert len(m.domain_names()) == len(m.domain_poses())
    assert all(isinstance(line, str) for line in m.explain())
    sim.step(3)
    meas = m.guard_measure(sim.gravity)
    assert meas.finite and meas.kinetic > 0 and meas.inverted == 0
    M, V = m.mean_motion()
    assert M == pytest.approx(m.vertex_mass.sum()) and np.array_equal(V, np.zeros(3))   # pinned body


@pytest.mark.parametrize("kind", sorted(KINDS))
def test_step_options_change_one_step_only(kind):
    """A step with StepOptions(dt / 2, more iterations) equals a step of a model configured
    that way, and leaves the model's own settings as they were."""
    extra = {"integrator": {"newton_iterations": 1}} if kind != "meshless" else {}
    a = Simulator(_scene(kind, **KINDS[kind], **extra))
    dt = a.model.dt
    b = Simulator(_scene(kind, **KINDS[kind], **dict(extra, integrator={"newton_iterations": 3, "dt": dt / 2})))
    for sim in (a, b):
        sim.set_wrench("tip", force=(0.0, 0.2, -0.5))
    f = a.applied_loads()
    a.model.step(f, a.gravity, options=StepOptions(dt=dt / 2, newton_iterations=3))
    b.model.step(b.applied_loads(), b.gravity)
    assert a.model.dt == dt and a.model.newton_iterations == (1 if kind != "meshless" else a.model.newton_iterations)
    np.testing.assert_allclose(a.vertex_positions(), b.vertex_positions(), rtol=0, atol=1e-12)
    assert np.abs(a.vertex_positions() - a.rest_positions()).max() > 1e-7
