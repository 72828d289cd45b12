"""The automatic model (issue 15): a scene with no `model` section, here a user's OBJ.

msg_scenes/bunny.yaml is the Stanford bunny as a surface file, tetrahedralised on load,
with no model settings. The product picks a reduced model whose error against full FEM
it measures itself (the budget probe), so the README's claim is rechecked here at a
coarser mesh and a shorter probe. Its speed is a benchmark (`mdss bench bunny` against
`mdss bench bunny --set model.kind=full`), not a test.
"""
import pytest

from mdss_ros import Simulator, load_scene
from mdss_ros.precompute import PrecomputeCache


@pytest.mark.claims
def test_a_users_obj_without_model_settings_gets_a_model_within_5_percent_of_full_fem(tmp_path):
    scene = load_scene("bunny", {"body.mesh.edge_length": 0.02, "model.budget.horizon": 0.5})
    assert scene.automatic_model and scene["model"]["budget"]["max_error"] == 0.05
    sim = Simulator(scene, cache=PrecomputeCache(tmp_path))
    bud = sim.budget
    measured = bud["chosen"]["measured"]                  # the chosen model as it runs: cubature on
    assert bud["met"] and measured["with_cubature"] and measured["rms_rel"] <= 0.05, bud
    assert sim.model.kind == "reduced" and sim.scene["model"]["cubature"]["samples"] == 10 * measured["modes"]
    assert sim.scene["model"]["modes"] == measured["modes"] == bud["chosen"]["modes"]
    assert any(line.startswith("model: automatic") for line in sim.explain())
    # A second start reads the tets, the bases, the cubature and the choice from the cache.
    cache = PrecomputeCache(tmp_path)
    again = Simulator(load_scene("bunny", {"body.mesh.edge_length": 0.02, "model.budget.horizon": 0.5}),
                      cache=cache)
    assert again.budget["cached"] and again.stats()["tets"] == sim.stats()["tets"]
    assert cache.events and all(e[1] == "hit" for e in cache.events), cache.events
