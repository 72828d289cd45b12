"""Cuts from the scene's loads (mdss_ros/reduced/bend_cuts.py, auto_domains.py): a limb the
scene's training poses bend further than max_bend is cut where it bends, the others stay
whole, and the loads are part of the bases' cache key."""
import numpy as np

from mdss_ros import load_scene
from mdss_ros.body import build_body
from mdss_ros.fem.elements import tet_geometry
from mdss_ros.fem.mass import lumped_mass
from mdss_ros.model_build import training_load_cases
from mdss_ros.precompute import bases_cache_key
from mdss_ros.reduced.bend_cuts import element_rotations, greedy_cuts, polar_rotations
from mdss_ros.reduced.partition import domain_labels, vertex_graph
from mdss_ros.reduced.reduced_model import _training_poses
from mdss_ros.rotations import exp_so3
from mdss_ros.scene import model_config
from scipy.sparse import csgraph
from small_bodies import star3

TIPS = {"tip_x": {"box": [[0.34, -1, -1], [1, 1, 1]]}, "tip_y": {"box": [[-1, 0.34, -1], [1, 1, 1]]}}
# The cuts are off by default (auto_domains.DEFAULTS: max_bend 0); these tests ask for them.
CUTS = {"auto": {"max_bend": 90}}


def _star(force_x=None, domains=CUTS, **scene):
    timeline = [] if force_x is None else [{"t": 0.1, "topic": "wrench", "frame_id": "tip_x", "force": force_x}]
    return load_scene(star3({"kind": "reduced", "domains": domains}, handles=TIPS, timeline=timeline, **scene))


def _partition(scene):
    body = build_body(scene)
    model = model_config(scene)
    cases = training_load_cases(scene, body, model)
    mass = lumped_mass(body.tets, tet_geometry(body.vertices, body.tets).volume, body.material.density,
                       len(body.vertices))
    notes = []
    labels, names = domain_labels(model["domains"], body.vertices, body.tets, notes,
                                  poses=_training_poses(body, mass, cases, None))
    return body, labels, names, notes


def test_polar_and_element_rotations_are_exact_for_rotations():
    rng = np.random.default_rng(3)
    R = np.stack([exp_so3(rng.normal(size=3)) for _ in range(20)])
    B = rng.normal(size=(20, 3, 3)) * 0.2
    S = np.eye(3) + 0.5 * (B + B.transpose(0, 2, 1))              # symmetric positive definite
    np.testing.assert_allclose(polar_rotations(R @ S), R, atol=1e-12)
    # A rigid rotation of a mesh: every tet turns by it.
    body = build_body(_star())
    geom = tet_geometry(body.vertices, body.tets)
    Q = exp_so3(np.array([0.3, -1.2, 0.7]))
    u = body.vertices @ Q.T - body.vertices
    np.testing.assert_allclose(element_rotations(body.tets, geom.grads, u), np.broadcast_to(Q, (len(body.tets), 3, 3)),
                               atol=1e-12)


def _bend_matrix(theta_deg):
    t = np.radians(np.asarray(theta_deg, dtype=float))
    return np.abs(t[:, None] - t[None, :])[None]                  # one case, turns about one axis


def test_greedy_cuts_leave_the_core_its_share_and_balance_the_rest():
    theta = [0, 1, 2, 3] + list(np.linspace(5, 155, 16))          # 20 bands, a bend from band 4 on
    bend = _bend_matrix(theta)
    cuts, spans = greedy_cuts(bend, np.radians(22.5), np.radians(90), 1)
    # The core's share ends before the bend passes 22.5 deg, the remaining 130 deg or so
    # make two pieces of about 65 deg, within 90 each.
    assert len(cuts) == 2 and theta[cuts[0]] > 22.5 and theta[cuts[0] - 1] <= 22.5
    assert len(spans) == 3 and spans[0] <= np.radians(22.5) and np.all(spans[1:] <= np.radians(90))
    assert abs(spans[1] - spans[2]) < np.radians(15)
    # A limb that bends within the core's share is not cut; min_bands holds short pieces off.
    assert len(greedy_cuts(_bend_matrix(np.linspace(0, 20, 20)), np.radians(22.5), np.radians(90), 1)[0]) == 0
    cuts, _ = greedy_cuts(bend, np.radians(22.5), np.radians(10), 6)
    assert np.all(np.diff(np.r_[0, cuts, 20]) >= 6)


def test_training_load_cases_follow_the_timeline_and_the_colliders():
    scene = load_scene(star3({"kind": "reduced", "domains": CUTS}, handles=TIPS, colliders={
        "ball": {"shape": "sphere", "radius": 0.05, "position": [0.2, 0, 0.3]}}, timeline=[
        {"t": 0.1, "topic": "wrench", "frame_id": "tip_x", "force": [0, 0, 5]},
        {"t": 0.3, "topic": "wrench", "frame_id": "tip_y", "force": [1, 0, 0]},
        {"t": 0.6, "topic": "clear_forces"},
        {"t": 0.8, "topic": "wrench", "frame_id": "tip_x", "force": [0, 0, 5]},       # the first case again
        {"t": 0.9, "topic": "collider_pose", "name": "ball", "position": [0.2, 0, 0.1]}]))
    body = build_body(scene)
    cases = training_load_cases(scene, body, model_config(scene))
    assert [c.label for c in cases[:2]] == ["t = 0.1 s: wrench on tip_x", "t = 0.3 s: wrench on tip_x, wrench on tip_y"]
    weight = lumped_mass(body.tets, tet_geometry(body.vertices, body.tets).volume, body.material.density,
                         len(body.vertices)).sum() * -9.81
    np.testing.assert_allclose(cases[1].forces.sum(0), [1, 0, 5 + weight], rtol=1e-12)
    # The ball's deepest pose (its centre 2 cm under the arm's top at z = 0.12, radius 5 cm)
    # pushes the surface vertices inside it out along its normal, each by its depth.
    assert len(cases) == 3 and cases[2].label.startswith("collider ball ") and cases[2].label.endswith("at t = 0.9 s")
    ids, disp = cases[2].pushed
    dist = np.linalg.norm(body.vertices[body.surface.vertex_ids] - [0.2, 0, 0.1], axis=1)
    np.testing.assert_array_equal(np.sort(ids), np.sort(body.surface.vertex_ids[dist < 0.05]))
    np.testing.assert_allclose(np.linalg.norm(disp, axis=1), 0.05 - np.linalg.norm(body.vertices[ids] - [0.2, 0, 0.1],
                                                                                   axis=1), rtol=1e-9)
    assert f"{0.05 - dist.min():.3g} m in" in cases[2].label
    # Not automatic domains: the loads do not place cuts, and none is built.
    fixed = load_scene(star3({"kind": "reduced", "domains": {"count": 2}}, handles=TIPS, timeline=[]))
    assert training_load_cases(fixed, build_body(fixed), model_config(fixed)) is None


def test_a_limb_the_loads_bend_far_is_cut_where_it_bends_and_the_rest_stay_whole():
    body, plain, plain_names, _ = _partition(_star())              # gravity alone: no cut
    body, labels, names, notes = _partition(_star(force_x=[-200.0, 0.0, 100.0]))
    assert plain_names == ["core", "limb0", "limb1", "limb2"]
    assert names == ["core", "limb0", "limb1", "limb2_0", "limb2_1"]
    X = body.vertices
    loaded = [k for k in range(len(names)) if X[labels == k, 0].min() > 0.0]
    assert [names[k] for k in loaded] == ["limb2_0", "limb2_1"]
    # The unloaded limbs are the domains they were; the loaded one is cut in two with its
    # cut where it bends, nearer the root than the tip.
    for k in (1, 2):
        np.testing.assert_array_equal(labels == k, plain == k)
    root, tip = (X[labels == names.index(nm), 0].mean() for nm in ("limb2_0", "limb2_1"))
    assert root < tip
    assert any(n.startswith("limb2:") and "into 2 piece(s)" in n for n in notes)
    g = vertex_graph(body.tets, len(X))
    for k in range(len(names)):
        ids = np.flatnonzero(labels == k)
        assert csgraph.connected_components(g[ids][:, ids], directed=False)[0] == 1
    # max_bend 0 turns the cuts off.
    _, off, off_names, _ = _partition(_star(force_x=[-200.0, 0.0, 100.0], domains={"auto": {"max_bend": 0}}))
    assert off_names == plain_names and np.array_equal(off, plain)
    # So does the default: plain `domains: auto` builds no training poses and cuts nothing.
    scene = _star(force_x=[-200.0, 0.0, 100.0], domains="auto")
    assert training_load_cases(scene, build_body(scene), model_config(scene)) is None
    _, dflt, dflt_names, _ = _partition(scene)
    assert dflt_names == plain_names and np.array_equal(dflt, plain)


def test_the_loads_that_place_cuts_are_in_the_bases_key():
    keys = {}
    for label, force in (("none", None), ("a", [0.0, 0.0, 5.0]), ("b", [0.0, 0.0, 6.0])):
        for kind, domains in (("cuts", CUTS), ("auto", "auto"), ("count", {"count": 2})):
            scene = _star(force_x=force, domains=domains)
            body, model = build_body(scene), model_config(scene)
            keys[label, kind] = bases_cache_key(body, model, training_load_cases(scene, body, model))
    assert len({keys[k, "cuts"] for k in ("none", "a", "b")}) == 3
    # Without cuts (a count, or auto at its default max_bend 0) the loads place nothing.
    assert len({keys[k, "auto"] for k in ("none", "a", "b")}) == 1
    assert len({keys[k, "count"] for k in ("none", "a", "b")}) == 1


def _beam(force, max_bend=90):
    return load_scene({"name": "beam", "body": {
        "mesh": {"generator": "box", "size": [0.6, 0.1, 0.1], "cell": 0.04},
        "material": {"model": "stvk", "young": 1e6, "poisson": 0.3, "density": 1000}},
        "pins": [{"box": [[-0.001, -1, -1], [0.001, 1, 1]]}],
        "handles": {"tip": {"box": [[0.599, -1, -1], [0.601, 1, 1]]}},
        "model": {"kind": "reduced", "domains": {"auto": {"max_bend": max_bend}}}, "gravity": [0, 0, 0],
        "timeline": [{"t": 0.1, "topic": "wrench", "frame_id": "tip", "force": [0, 0, force]}]})


def test_a_body_without_limbs_is_cut_from_its_root_where_the_loads_bend_it():
    # A dead tip load turns a clamped beam's tip towards its own direction, at most 90 deg:
    # this one by 73 deg. Within max_bend the beam stays one domain.
    assert _partition(_beam(-400.0))[2] == ["core"]
    body, labels, names, notes = _partition(_beam(-400.0, max_bend=30))
    assert names == ["core", "bend1", "bend2"], notes
    # The clamped end is the root: the pieces follow each other along the beam, the core
    # (clamped) first, as few as keep within max_bend.
    X = body.vertices
    ends = [X[labels == k, 0].max() for k in range(len(names))]
    assert np.all(np.diff(ends) > 0) and np.all(X[body.pinned, 0] < ends[0])
    note = next(n for n in notes if n.startswith("no limbs;"))
    spans = [float(a) for a in note.split("bending ")[1].split(" deg")[0].split(", ")]
    whole = float(note.split("bend it ")[1].split(" deg")[0])
    assert len(spans) == int(np.ceil(whole / 30)) == 3 and max(spans) <= 30, note


def test_a_free_block_that_the_loads_move_whole_is_one_domain_without_warnings():
    # Issue 18's incline block: free, under gravity only. Its training pose moves it as a
    # whole, so every tet is its calmest part and the distance along it is zero everywhere
    # (a 0 / 0 band width gave NaN bands and numpy warnings before). The block's automatic
    # model no longer asks for cuts by default; the cuts are asked for here.
    import warnings
    scene = load_scene({"name": "block", "body": {
        "mesh": {"generator": "box", "size": [0.10, 0.08, 0.04], "cell": 0.02},
        "material": {"model": "neohookean", "young": 2e5, "poisson": 0.3, "density": 1000}},
        "colliders": {"floor": {"shape": "plane"}}, "gravity": [3.36, 0.0, -9.22],
        "model": {"kind": "reduced", "domains": CUTS}})
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        _, labels, names, notes = _partition(scene)
    assert names == ["core"] and np.all(labels == 0)
    note = next(n for n in notes if n.startswith("no limbs;"))
    # Moved whole: no bend but round-off (rotations.rotation_angles keeps small angles; the
    # arccos of the trace read 1e-6 degrees here once the stiffness's round-off changed).
    assert float(note.split("bend it ")[1].split(" deg")[0]) < 1e-9, note
