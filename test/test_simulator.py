"""The Simulator facade (docs/architecture.md, "Contracts: Python API") on the full-space model."""
import numpy as np
import pytest

from mdss_ros import Simulator, load_scene

SMALL = {"body.mesh.cell": 0.05, "model.kind": "full", "model.integrator.newton_iterations": 2}


@pytest.fixture(scope="module")
def sim():
    return Simulator(load_scene("cantilever", overrides=SMALL))


def test_api_shapes_and_pins(sim):
    sim.reset()
    sim.set_wrench("tip", force=(0, 0, -5.0))
    sim.step(5)
    assert abs(sim.time - 5 * sim.dt) < 1e-12
    tris, pos = sim.surface_triangles(), sim.surface_positions()
    assert tris.ndim == 2 and tris.shape[1] == 3 and tris.max() < len(pos)
    assert sim.vertex_positions().shape == sim.rest_positions().shape
    assert sim.tetrahedra().shape[1] == 4
    pins = sim.pinned_vertices()
    np.testing.assert_array_equal(sim.vertex_positions()[pins], sim.rest_positions()[pins])
    assert sim.domain_poses().shape == (1, 7)
    e = sim.energy()
    assert set(e) >= {"kinetic", "elastic", "total"} and e["elastic"] > 0
    st = sim.stats()
    for k in ("step_ms", "assembly_ms", "factor_ms", "solve_ms", "dofs", "domains"):
        assert k in st
    with pytest.raises(KeyError, match="unknown collider"):     # this scene declares none
        sim.collider_wrench("ball")


def test_collider_wrench_is_minus_the_force_on_the_body_and_zero_apart():
    """A ball pushed down onto the top of a free beam (no pins, no gravity): while they touch,
    the wrench on the ball is minus the force the body receives, measured independently as
    its momentum change per step (backward Euler: internal and stiffness-damping forces sum
    to zero, so dP = dt * contact force); it pushes the ball up; its torque is the contact
    forces' moment about the ball's centre. Apart (before and after), it is exactly zero."""
    R = 0.05
    sim = Simulator(load_scene("cantilever", overrides={
        **SMALL, "pins": [], "gravity": [0.0, 0.0, 0.0], "timeline": [],
        "colliders": {"ball": {"shape": "sphere", "radius": R, "position": [0.5, 0.05, 0.1 + R + 0.002]}}}))
    m = sim.model.vertex_mass

    def momentum():
        return (m[:, None] * sim.model.vertex_velocities()).sum(0)
    sim.step(2)                                                  # 2 mm above the top face
    assert len(sim.contacts()) == 0
    np.testing.assert_array_equal(sim.collider_wrench("ball"), np.zeros(6))
    z0 = sim.colliders["ball"].position[2]
    touching = 0
    for k in range(40):                                          # down 0.2 mm per step (no collider sub-steps)
        sim.set_collider_pose("ball", (0.5, 0.05, z0 - 2e-4 * (k + 1)))
        p0 = momentum()
        sim.step()
        w = sim.collider_wrench("ball")
        c = sim.contacts()
        if len(c) == 0:
            np.testing.assert_array_equal(w, np.zeros(6))
            continue
        touching += 1
        assert sim.stats().get("collider_substeps", 1) == 1
        F = np.linalg.norm(w[:3])
        assert w[2] > 0.99 * F            # it pushes the ball back up (lateral measured <= 4.3e-4 F)
        # Measured |w_f + dP/dt| / |w_f| <= 5e-14 (round-off of the direct solve); 1e-9 leaves
        # room for other BLAS/solver builds and still fails any real imbalance.
        np.testing.assert_allclose(w[:3], -(momentum() - p0) / sim.dt, rtol=0, atol=1e-9 * F)
        # Torque about the ball's position from the reported contacts (points, forces on the body).
        tau = np.cross(c[:, :3] - sim.colliders["ball"].position, -c[:, 7:10]).sum(0)
        np.testing.assert_allclose(w[3:], tau, rtol=0, atol=1e-12 * F * R)
        # Frictionless sphere: forces along its normals, through its centre, so the torque
        # nearly vanishes. Measured <= 1.8e-4 F R (normals taken at the step's predicted
        # positions, points at its end); 1e-3 F R is 5x that, far below a lever of R.
        assert np.linalg.norm(w[3:]) < 1e-3 * F * R
    assert touching >= 3, touching                               # measured: 5 contact steps
    for k in range(5):                                           # lift it well clear
        sim.set_collider_pose("ball", (0.5, 0.05, z0 + 0.05 * (k + 1)))
        sim.step()
    assert len(sim.contacts()) == 0
    np.testing.assert_array_equal(sim.collider_wrench("ball"), np.zeros(6))


def test_wrench_bends_the_tip_down_and_zero_clears(sim):
    sim.reset()
    sim.scene.data["gravity"] = [0.0, 0.0, 0.0]
    sim.gravity = np.zeros(3)
    tip = sim.body.handles["tip"]
    sim.set_wrench("tip", force=(0, 0, -5.0))
    sim.step(20)
    assert (sim.vertex_positions()[tip, 2] - sim.rest_positions()[tip, 2]).mean() < -1e-3
    sim.set_wrench("tip", force=(0, 0, 0))
    assert not sim._wrenches


def test_point_force_lasts_its_duration(sim):
    sim.reset()
    sim.add_point_force((0.5, 0.05, 0.2), (0, 0, -1.0), duration=0.0)
    assert len(sim._point_forces) == 1
    f = sim.applied_forces()
    np.testing.assert_allclose(f.sum(0), [0, 0, -1.0], atol=1e-12)
    sim.step()
    assert len(sim._point_forces) == 0
    sim.add_point_force((0.5, 0.05, 0.2), (0, 0, -1.0), duration=-1)
    sim.step(3)
    assert len(sim._point_forces) == 1
    sim.clear_forces()
    assert len(sim._point_forces) == 0


def test_bad_inputs_raise_clear_errors(sim):
    with pytest.raises(KeyError, match="unknown handle"):
        sim.set_wrench("nose", force=(1, 0, 0))
    with pytest.raises(ValueError, match="finite"):
        sim.set_wrench("tip", force=(np.nan, 0, 0))
    with pytest.raises(KeyError, match="unknown collider"):
        sim.set_collider_pose("ball", (0, 0, 0))


def test_headless_run_command(tmp_path, capsys):
    from mdss_ros.cli import main
    out = tmp_path / "s.json"
    assert main(["run", "cantilever", "--steps", "60", "--set", "body.mesh.cell=0.05", "--json", str(out)]) == 0
    text = capsys.readouterr().out
    assert "input wrench" in text and "done, 60 steps" in text
    assert out.exists()


def test_reduced_cantilever_scene_api():
    sim = Simulator(load_scene("cantilever", overrides={"body.mesh.cell": 0.05, "model.domains.count": 2,
                                                         "model.modes": 6}))
    sim.set_wrench("tip", force=(0, 0, -5.0))
    sim.step(3)
    assert sim.domain_poses().shape == (2, 7)
    np.testing.assert_allclose(np.linalg.norm(sim.domain_poses()[:, 3:], axis=1), 1.0)
    st = sim.stats()
    assert st["kind"] == "reduced" and st["domains"] == 2
    for k in ("domain_ms", "coupling_ms", "factor_ms", "solve_ms", "step_ms"):
        assert k in st
    pins = sim.pinned_vertices()
    np.testing.assert_allclose(sim.vertex_positions()[pins], sim.rest_positions()[pins], atol=1e-12)
    assert np.allclose(sim.external_forces() - sim.applied_forces(),
                       sim.model.vertex_mass[:, None] * sim.gravity)


def test_steps_run_with_the_scene_blas_threads_and_restore_them():
    """model.blas_threads limits BLAS inside a step (threads.py) and nowhere else."""
    from threadpoolctl import threadpool_info, threadpool_limits
    from mdss_ros.errors import SceneError
    from mdss_ros.threads import BlasThreads

    def blas_threads():
        return [p["num_threads"] for p in threadpool_info() if p["user_api"] == "blas"]
    before = blas_threads()
    with BlasThreads(1)():
        assert blas_threads() and all(n == 1 for n in blas_threads())
    assert blas_threads() == before
    with BlasThreads(None)():
        assert blas_threads() == before
    limit = BlasThreads(1)
    with limit():
        with limit():          # nested (a surface read inside a step): nothing to change
            assert all(n == 1 for n in blas_threads())
        assert all(n == 1 for n in blas_threads())
    assert blas_threads() == before
    with pytest.raises(SceneError, match="blas_threads"):
        load_scene("cantilever", {"model.blas_threads": 0})
    assert load_scene("cantilever", {"model.blas_threads": None})["model"]["blas_threads"] is None
    sim = Simulator("cantilever", {"body.mesh.cell": 0.05, "model.kind": "full"})
    sim.step()                                   # PARDISO (MKL) loaded

    def by_library():
        return {p["filepath"]: (p["internal_api"], p["num_threads"]) for p in threadpool_info()
                if p["user_api"] == "blas"}
    # auto: a full-space model keeps MKL's threads (PARDISO) and gets one thread of every
    # other BLAS, whatever the process set before (two threads everywhere here).
    with threadpool_limits(limits=2, user_api="blas"):
        outside = by_library()
        with sim._blas_threads():
            inside = by_library()
        assert by_library() == outside and set(inside) == set(outside)
    apis = {api for api, _ in outside.values()}
    if "mkl" not in apis or any(n != 2 for _, n in outside.values()):
        pytest.skip(f"needs MKL (pypardiso) beside another BLAS, each able to run 2 threads: {outside}")
    assert len(apis) > 1
    for path, (api, n) in inside.items():
        assert n == (2 if api == "mkl" else 1), (path, api, n)


def test_a_collider_swept_in_sub_steps_counts_the_work_of_every_sub_step():
    """A load applied in the step where a collider is swept near the body in sub-steps: the
    guard judges the whole sweep, so the work it is given must be the sum over the sub-steps.
    (With the last sub-step's work alone, a -5 N tip wrench looked like created energy and
    the guard rolled the step back: the node test's intermittent "recovered".)"""
    sim = Simulator(load_scene("cantilever", overrides={
        "gravity": [0.0, 0.0, 0.0], "timeline": [],
        "colliders": {"ball": {"shape": "sphere", "radius": 0.05, "position": [0.5, 0.05, 0.5]}}}))
    sim.step(3)
    e0 = sim.energy()["total"]
    sim.set_collider_pose("ball", (0.5, 0.0, 0.3))        # 0.15 m above the beam: swept, no contact
    sim.set_wrench("tip", force=(0, 0, -5.0))
    sim.step()
    st = sim.stats()
    assert st["collider_substeps"] > 1 and len(sim.contacts()) == 0
    assert st["stability"] == "stable" and st["guard_attempts"] == 1, st["guard_last_event"]
    # Backward Euler only dissipates: the energy gained is at most the work, and most of it.
    gained = sim.energy()["total"] - e0
    assert 0.5 * st["guard_work"] < gained <= st["guard_work"]
