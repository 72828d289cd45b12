"""The guard's energy projection (guard.project_energy): it removes exactly the excess from
the kinetic energy, never adds energy, keeps linear momentum of a free body and the pins at
rest, refuses what velocities cannot pay for, and the guard's last rung uses it."""
import numpy as np
import pytest

from mdss_ros import Simulator, load_scene
from mdss_ros.guard import mean_motion, measure, project_energy
from mdss_ros.precompute import PrecomputeCache

SMALL = {"body.mesh.cell": 0.05, "model.cubature": {"samples": 0, "interface": "exact"}, "model.modes": 6}
GRAVITY = np.array([0.0, 0.0, -9.81])


def _sim(kind, free=True, **over):
    extra = {"pins": [], "initial_velocity.angular": [0.5, 1.0, 6.0],
             "initial_velocity.linear": [0.3, -0.2, 0.1]} if free else {}
    scene = load_scene("cantilever", overrides=dict(SMALL, **{"model.kind": kind}, **extra, **over))
    sim = Simulator(scene, cache=PrecomputeCache(enabled=False))
    sim.set_wrench("tip", force=(0, 0, -30.0))
    sim.step(4)                                       # deformed and moving
    return sim


def _momentum(sim):
    m, v = sim.model.vertex_mass, sim.model.vertex_velocities()
    return (m[:, None] * v).sum(0)


def _measure(sim):
    return measure(sim.model, sim.tetrahedra(), GRAVITY)


@pytest.mark.parametrize("kind", ["full", "reduced"])
def test_projection_removes_exactly_the_excess_and_keeps_linear_momentum(kind):
    sim = _sim(kind)
    before = _measure(sim)
    x0, p0 = sim.vertex_positions().copy(), _momentum(sim)
    M, V = mean_motion(sim.model)
    rel = before.kinetic - 0.5 * M * V @ V
    assert rel > 1e-3 * before.kinetic                # a real relative motion to scale
    excess = 0.4 * rel
    assert project_energy(sim.model, before, excess) == pytest.approx(excess)
    after = _measure(sim)
    assert after.kinetic == pytest.approx(before.kinetic - excess, rel=1e-9)
    # the vertex sums agree (the reduced measure is in its own coordinates)
    assert sim.model.kinetic_energy() == pytest.approx(after.kinetic, rel=1e-9)
    assert after.elastic == before.elastic and after.gravity == before.gravity
    np.testing.assert_array_equal(sim.vertex_positions(), x0)
    np.testing.assert_allclose(_momentum(sim), p0, rtol=0, atol=1e-9 * np.abs(p0).max())
    assert after.total < before.total


@pytest.mark.parametrize("kind", ["full", "reduced"])
def test_projection_refuses_what_velocities_cannot_pay(kind):
    sim = _sim(kind)
    before = _measure(sim)
    v0 = sim.model.vertex_velocities().copy()
    M, V = mean_motion(sim.model)
    rel = before.kinetic - 0.5 * M * float(V @ V)
    # excess == rel exactly is a boundary that rounding decides either way (the guard and this
    # test sum the same terms in different orders), so ask for clearly more than rel can pay.
    for excess in (0.0, -1.0, rel * (1.0 + 1e-9), 2.0 * rel, np.inf, np.nan):
        assert project_energy(sim.model, before, excess) is None
    np.testing.assert_array_equal(sim.model.vertex_velocities(), v0)
    # ... and just below the boundary it pays, leaving (1e-9 of) the relative motion
    assert project_energy(sim.model, before, rel * (1.0 - 1e-9)) is not None


@pytest.mark.parametrize("kind", ["full", "reduced"])
def test_projection_on_a_pinned_body_keeps_pins_at_rest(kind):
    sim = _sim(kind, free=False)
    before = _measure(sim)
    assert np.all(mean_motion(sim.model)[1] == 0.0)   # pins: no momentum to keep, all motion scales
    assert project_energy(sim.model, before, 0.5 * before.kinetic) is not None
    assert _measure(sim).kinetic == pytest.approx(0.5 * before.kinetic, rel=1e-9)
    pinned = sim.body.pinned
    assert pinned.size and np.all(sim.model.vertex_velocities()[pinned] == 0.0)


def _pump(sim, factor):
    """Every model step (every attempt and sub-step) scales the motion relative to the mass
    centre by `factor`: energy created that no integration setting removes."""
    model, real = sim.model, sim.model.step

    def pumped(*a, **k):
        out = real(*a, **k)
        M, V = mean_motion(model)
        if hasattr(model, "scale_relative_motion"):
            model.scale_relative_motion(factor, V)
        else:
            model.v = V + factor * (model.v - V)
        return out
    model.step = pumped


@pytest.mark.parametrize("kind", ["full", "reduced"])
def test_guard_last_rung_projects_a_step_that_keeps_creating_energy(kind):
    results = {}
    for project in (True, False):
        sim = _sim(kind, **{"model.guard.max_substeps": 4, "model.guard.energy_projection": project})
        sim.set_wrench("tip", force=(0, 0, 0))
        _pump(sim, 1.5)
        e0 = sim.energy()["total"]
        sim.step()
        st = sim.stats()
        results[project] = st
        if project:
            assert st["stability"] == "recovered" and "energy" in st["guard_reason"]
            assert st["guard_action"].endswith("4 sub-steps x energy projection")
            assert st["guard_projected"] > 0 and st["guard_projections"] == 1
            # no sub-step created energy: the step ends at or below its start (no load, no work)
            assert sim.energy()["total"] <= e0 + 1e-9 * abs(e0)
        else:
            assert st["stability"] == "failed" and st["guard_projected"] == 0.0
    assert results[True]["guard_attempts"] == results[False]["guard_attempts"]   # no extra rung
