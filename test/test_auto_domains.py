"""`model.domains: auto` (mdss_ros/reduced/auto_domains.py): a core domain and one per limb,
found from the body's shape; every limb of the limbed scenes gets a domain of its own."""
import numpy as np
import pytest
from scipy.sparse import csgraph

from mdss_ros import Simulator, load_scene
from mdss_ros.body import build_body
from mdss_ros.errors import SceneError
from mdss_ros.mesh import select_vertices
from mdss_ros.precompute import PrecomputeCache
from mdss_ros.reduced.auto_domains import auto_domains
from mdss_ros.reduced.partition import domain_labels, vertex_graph
from small_bodies import star3


def _auto(body, **settings):
    g = vertex_graph(body.tets, len(body.vertices), weights=body.vertices)
    return auto_domains(body.vertices, body.tets, g, **dict({"core_scale": 1.5, "min_limb": 1.0,
                                                             "limb_segments": 1}, **settings))


def _domain_of(labels, ids):
    """The one domain holding all of ids (fails if they are split)."""
    found = np.unique(labels[ids])
    assert len(found) == 1, found
    return int(found[0])


def _each_domain_connected(body, labels):
    g = vertex_graph(body.tets, len(body.vertices))
    for k in np.unique(labels):
        ids = np.flatnonzero(labels == k)
        n, _ = csgraph.connected_components(g[ids][:, ids], directed=False)
        assert n == 1, (k, n)


def test_star_limbs_gets_the_hub_and_one_domain_per_arm():
    body = build_body(load_scene("star_limbs"))
    labels, names, notes = _auto(body)
    assert names == ["core", "limb0", "limb1", "limb2", "limb3", "limb4"]
    arms = [_domain_of(labels, ids) for ids in body.handles.values()]     # the five arm tips
    assert sorted(arms) == [1, 2, 3, 4, 5]
    assert _domain_of(labels, body.pinned) == 0                            # the clamped hub is the core
    _each_domain_connected(body, labels)
    assert len(notes) == 6 and notes[0].startswith("core:") and "limb0" in notes[1]


def test_octopus_gets_the_head_and_one_domain_per_arm():
    scene = load_scene("octopus")
    body = build_body(scene)
    labels, names, _ = _auto(body)
    assert names == ["core"] + [f"limb{j}" for j in range(8)]
    regions = scene["model"]["domains"]["regions"]
    tips = [_domain_of(labels, select_vertices(body.vertices, regions[f"arm{a}_tip"])) for a in range(8)]
    assert sorted(tips) == list(range(1, 9))                               # eight arms, eight limbs
    head = select_vertices(body.vertices, {"sphere": {"center": [0.0, 0.0, 0.06], "radius": 0.08}})
    assert _domain_of(labels, head) == 0
    _each_domain_connected(body, labels)


def test_limb_segments_cut_each_limb_into_connected_bands_from_the_core_out():
    body = build_body(load_scene("star_limbs"))
    labels, names, notes = _auto(body, limb_segments=2)
    assert names == ["core"] + [f"limb{j}_{s}" for j in range(5) for s in range(2)]
    _each_domain_connected(body, labels)
    for ids in body.handles.values():                                      # tips sit in the outer band
        assert names[_domain_of(labels, ids)].endswith("_1")
    assert "cut into 2 bands" in notes[1]


def test_a_body_without_limbs_is_one_core():
    body = build_body(load_scene("cantilever", {"body.mesh.size": [0.12, 0.1, 0.1], "body.mesh.cell": 0.02,
                                                "handles": {}}))
    labels, names, _ = _auto(body)
    assert names == ["core"] and np.all(labels == 0)


def test_scene_key_and_bad_settings():
    sc = load_scene("cantilever", {"model.domains": "auto"})
    assert sc["model"]["domains"] == {"auto": True}
    sc = load_scene("cantilever", {"model.domains": {"auto": {"limb_segments": 2}}})
    assert sc["model"]["domains"]["auto"] == {"limb_segments": 2}
    for bad, words in [({"auto": True, "count": 3}, "one of count, regions or auto"),
                       ({"auto": {"limb_segments": 0}}, "limb_segments: expected an integer >= 1"),
                       ({"auto": {"core_scale": -1}}, "core_scale: expected a positive number"),
                       ({"auto": {"cuts": 3}}, "unknown key")]:
        with pytest.raises(SceneError, match=words):
            load_scene("cantilever", {"model.domains": bad})
    with pytest.raises(SceneError, match="auto"):
        domain_labels("automatic", np.zeros((4, 3)), np.array([[0, 1, 2, 3]]))


def test_automatic_domains_default_to_bases_grown_by_one_diameter():
    """scene.model_config: `domains: auto` without basis.extension or basis.layers takes
    auto_domains.AUTO_EXTENSION (1.0) and says so in model["implied"]; a scene's own
    extension or layers, and counts or regions, are left alone (0.5 from domains.py)."""
    from mdss_ros.reduced.auto_domains import AUTO_EXTENSION
    from mdss_ros.scene import model_config

    def cfg(model):
        return model_config(load_scene(star3(dict({"kind": "reduced"}, **model))))

    auto = cfg({"domains": "auto", "basis": {"modes": {"core": 8}}})
    assert AUTO_EXTENSION == 1.0
    assert auto["basis"] == {"modes": {"core": 8}, "extension": 1.0}
    assert "domains: auto" in auto["implied"]["basis.extension"]
    for model, basis in [({"domains": "auto", "basis": {"extension": 0.5}}, {"extension": 0.5}),
                         ({"domains": "auto", "basis": {"layers": 2}}, {"layers": 2}),
                         ({"domains": {"count": 2}}, {})]:
        out = cfg(model)
        assert out["basis"] == basis and "implied" not in out, (model, out)


def test_a_limbed_body_with_auto_domains_builds_explains_and_steps():
    """A small voxel star (a hub and three arms): the reduced model takes the auto domains,
    explains where they came from, and steps under gravity with the hub clamped."""
    scene = star3({"kind": "reduced", "domains": "auto", "modes": 4, "cubature": {"samples": 0, "interface": "exact"}})
    sim = Simulator(scene, cache=PrecomputeCache(enabled=False))
    assert sim.model.partition.names == ["core", "limb0", "limb1", "limb2"]
    text = "\n".join(sim.explain())
    assert "model.domains: auto" in text and "limb2:" in text
    assert "model.basis.extension 1: the default for model.domains: auto" in text, text
    x0 = sim.vertex_positions().copy()
    sim.step(3)
    x = sim.vertex_positions()
    assert np.all(np.isfinite(x)) and (x - x0)[:, 2].min() < 0          # the arms sag
