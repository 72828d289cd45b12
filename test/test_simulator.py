"""The Simulator facade (DESIGN.md Python API) on the full-space model."""
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
    assert sim.collider_wrench.__call__ is not None


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
    from threadpoolctl import threadpool_info
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
    with pytest.raises(SceneError, match="blas_threads"):
        load_scene("cantilever", {"model.blas_threads": 0})
    assert load_scene("cantilever", {"model.blas_threads": None})["model"]["blas_threads"] is None
    sim = Simulator("cantilever", {"body.mesh.cell": 0.05, "model.kind": "full"})
    assert sim._blas_threads.n is None           # auto: a full-space model keeps every core
