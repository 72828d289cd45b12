"""The scenes in msg_scenes/: every one loads; a reduced-resolution version of each
precomputes and plays part of its timeline without NaN and with its inputs taking effect
(fast); the full scenes play their timelines (slow). Bad scene files fail on load with a
message naming the problem; `explain()` says what the model took and why."""
import contextlib
import io
import sys
from pathlib import Path

import numpy as np
import pytest

from mdss_ros import Simulator, load_scene
from mdss_ros.errors import SceneError
from mdss_ros.timeline import TimelinePlayer

SCENES_DIR = Path(__file__).resolve().parents[1] / "msg_scenes"
SCENES = sorted(p.stem for p in SCENES_DIR.glob("*.yaml"))

sys.path.insert(0, str(SCENES_DIR))
from make_octopus_mesh import octopus_primitives  # noqa: E402

# A short cubature training run: the fast versions check the pipeline, not its accuracy.
_TRAIN = {"n_poses": 8, "stride": 2, "hold": 4}


def _cubature(interface=True):
    c = {"samples": 20, "training": _TRAIN}
    if interface:
        c.update(interface="uniform", interface_samples=10)
    return c


# Per scene: overrides for a coarse version and how many steps of its timeline to play
# (enough to reach the first inputs: the load, the collider touching, the wrenches).
FAST = {
    "armadillo_class": ({"body.mesh.cell": 0.05, "model.modes": 4, "model.cubature": _cubature()}, 40),
    "beam_two_domain": ({"body.mesh.cell": 0.05, "model.modes": 6, "model.cubature": _cubature()}, 60),
    "cantilever": ({"body.mesh.cell": 0.05, "model.modes": 6, "model.cubature": _cubature()}, 60),
    "caterpillar": ({"body.mesh.cell": 0.02, "model.modes": 4, "model.cubature": _cubature()}, 50),
    "hammock": ({"body.mesh.cell": 0.1, "body.mesh.layers": 1, "model.modes": 6, "model.cubature": _cubature()},
                140),
    "hertz_block": ({"body.mesh.cell_coarse": 0.05, "body.mesh.cell_fine": 0.01, "body.mesh.radius": 0.0,
                     "model.modes": 6, "model.cubature": _cubature(interface=False)}, 60),
    "octopus": ({"body.mesh": {"generator": "voxels", "cell": 0.03, "primitives": octopus_primitives()},
                 "model.modes": 4, "model.cubature": _cubature()}, 50),
    "soft_finger": ({"body.mesh.cell": 0.005, "model.modes": 6, "model.cubature": _cubature()}, 55),
    "star_limbs": ({"body.mesh.cell": 0.03, "model.modes": 4, "model.cubature": _cubature()}, 60),
    "grasp_lift": ({}, 80),             # full model, 384 tets: the pads have closed and begun the lift
    # No model section: the automatic model, here with its modes fixed (no budget probe;
    # test_automatic_model.py runs the probe) on a coarser tet mesh.
    "bunny": ({"body.mesh.edge_length": 0.02, "model.modes": 6, "model.cubature": _cubature(interface=False)}, 40),
}


def _play(sim, steps):
    """Play the scene's timeline for `steps` steps; every position must stay finite.
    Returns the final positions (n_verts, 3) and the largest surface displacement seen."""
    player = TimelinePlayer(sim.scene["timeline"])
    rest = sim.rest_positions()[sim.surface_vertex_ids()]
    moved = 0.0
    for k in range(steps):
        player.apply_due(sim)
        sim.step()
        x = sim.surface_positions()
        assert np.all(np.isfinite(x)), f"{sim.scene.name}: non-finite positions at step {k + 1}"
        moved = max(moved, float(np.linalg.norm(x - rest, axis=1).max()))
    x = sim.vertex_positions()
    assert np.all(np.isfinite(x))
    return x, moved


def test_every_scene_of_the_issue_is_there():
    for name in ["cantilever", "hertz_block", "beam_two_domain", "hammock", "octopus", "caterpillar",
                 "armadillo_class", "soft_finger"]:
        assert name in SCENES
    assert set(SCENES) == set(FAST), "a new scene needs a fast version in FAST"


@pytest.mark.parametrize("name", SCENES)
def test_scene_loads_and_its_timeline_fits(name):
    s = load_scene(name)
    assert s.name == name
    assert s["timeline"], "every scene has a timeline that exercises it"
    assert max(ev["t"] for ev in s["timeline"]) < s["duration"]


def _model_facts(sim):
    """(pinned-domain DOFs == modes, free-domain DOFs == modes + 6) over all subspace domains."""
    pinned = np.zeros(len(sim.body.vertices), dtype=bool)
    pinned[sim.body.pinned] = True
    for dom in sim.model.subspace:
        holds = pinned[dom.vertices].any()
        assert dom.movable == (not holds)
        assert dom.n_dofs == dom.r + (0 if holds else 6)
        assert (dom.tensors is None) == holds        # fictitious-force tensors only where it can rotate


@pytest.mark.parametrize("name", SCENES)
def test_reduced_resolution_scene_runs_its_timeline(name):
    overrides, steps = FAST[name]
    sim = Simulator(name, overrides=overrides)
    x, moved = _play(sim, steps)
    if sim.model.kind == "reduced":
        _model_facts(sim)
    assert moved > 1e-4, f"{name}: the timeline had no effect (max displacement {moved:.2e} m)"
    for c in sim.colliders.values():                       # declared colliders never sink into the body
        assert c.signed_distance(sim.surface_positions())[0].min() > -0.25 * sim._contact_spec()["margin"]
    pushing = [n for n in sim.colliders if n != "floor"]
    for n in pushing:                                      # and the indenters are pressing by now
        assert np.linalg.norm(sim.collider_wrench(n)[:3]) > 0.0, f"{name}: collider {n} never touched the body"
    if name == "octopus":                                  # thrown with spin, no pins: it turns
        q = sim.domain_poses()[:, 3:]
        assert np.all(np.abs(q[:, 3]) < 0.999)


# ---------------------------------------------------------------- slow: the full scenes
@pytest.mark.slow
@pytest.mark.timeout(3600)            # includes the precompute: up to 10 min per scene on 2 busy cores
@pytest.mark.parametrize("name", SCENES)
def test_full_scene_runs_its_timeline(name):
    """Each scene as written (full mesh, modes and cubature; precompute built here), its
    timeline played to the end, or 300 steps for the longer ones."""
    sim = Simulator(name)
    steps = min(int(round(sim.scene["duration"] / sim.dt)), 300)
    _, moved = _play(sim, steps)
    assert moved > 1e-3, f"{name}: the timeline had no visible effect (max displacement {moved:.2e} m)"


# ---------------------------------------------------------------- bad scene files
BASE = {
    "name": "t",
    "body": {"mesh": {"generator": "box", "size": [0.2, 0.05, 0.05], "cell": 0.025},
             "material": {"model": "stvk", "young": 1e5, "poisson": 0.3, "density": 1000}},
    "pins": [{"box": [[-0.001, -1, -1], [0.001, 1, 1]]}],
    "handles": {"tip": {"box": [[0.199, -1, -1], [0.201, 1, 1]]}},
    "colliders": {"ball": {"shape": "sphere", "radius": 0.02, "position": [0.1, 0.0, 0.2]}},
    "model": {"kind": "full"},          # without a model section it would get the automatic model
}


@pytest.mark.parametrize("override, words", [
    ({"body.mesh": {"file": "no_such_mesh.vtu"}}, ["body.mesh.file", "no_such_mesh.vtu", "not found"]),
    ({"body.mesh": {"generator": "box", "file": "a.vtu"}}, ["body.mesh", "exactly one"]),
    ({"body.material.young": -5.0}, ["body.material", "young", "> 0"]),
    ({"body.material.poisson": 0.5}, ["body.material", "poisson", "0.5"]),
    ({"body.material.poisson": 0.62}, ["body.material", "poisson"]),
    ({"body.material.colour": "red"}, ["body.material", "unknown key", "colour"]),
    ({"body.colour": "red"}, ["unknown key", "body.colour"]),
    ({"model.domains": {"cout": 2}}, ["model.domains.cout", "count"]),
    ({"model.domains": {"count": 2, "regions": {}}}, ["model.domains", "one of count, regions or auto"]),
    ({"model.cubature": {"sample": 10}}, ["model.cubature.sample", "samples"]),
    ({"timeline": [{"t": 0.1, "topic": "wrench", "frame_id": "tip", "forse": [0, 0, 1]}]},
     ["timeline[0]", "forse"]),
    ({"timeline": [{"t": 0.1, "topic": "point_force", "force": [0, 0, 1]}]}, ["timeline[0].point", "required"]),
    ({"timeline": [{"t": 0.1, "topic": "wrench", "frame_id": "tip", "force": [0, 1]}]},
     ["timeline[0].force", "3 numbers"]),
])
def test_bad_scene_fails_on_load_naming_the_problem(override, words):
    """These are caught by load_scene itself: before any mesh is built."""
    with pytest.raises(SceneError) as err:
        load_scene(BASE, overrides=override)
    msg = str(err.value)
    for w in words:
        assert w in msg, (w, msg)


def test_unknown_names_in_the_timeline_are_warnings():
    """A timeline may carry inputs the node must reject (the recording tests replay one), so
    an unknown handle or collider is reported on load, not refused."""
    s = load_scene(BASE, overrides={"timeline": [
        {"t": 0.1, "topic": "wrench", "frame_id": "tipp", "force": [0, 0, 1]},
        {"t": 0.2, "topic": "collider_pose", "name": "bal", "position": [0, 0, 1]},
        {"t": 0.3, "topic": "wrench", "frame_id": "tip", "force": [0, 0, 1]}]})
    assert len(s.warnings) == 2
    assert "timeline[0].frame_id" in s.warnings[0] and "'tipp'" in s.warnings[0] and "['tip']" in s.warnings[0]
    assert "timeline[1].name" in s.warnings[1] and "'bal'" in s.warnings[1] and "['ball']" in s.warnings[1]
    assert load_scene(BASE).warnings == []


def test_missing_mesh_file_names_the_scene_file(tmp_path):
    scene = tmp_path / "bad.yaml"
    scene.write_text("name: bad\nbody:\n  mesh: {file: meshes/gone.vtu}\n"
                     "  material: {model: stvk, young: 1.0e5, poisson: 0.3, density: 1000}\n")
    with pytest.raises(SceneError) as err:
        load_scene(scene)
    assert str(scene) in str(err.value) and str(tmp_path / "meshes" / "gone.vtu") in str(err.value)


@pytest.mark.parametrize("override, words", [
    ({"pins": [{"box": [[5, 5, 5], [6, 6, 6]]}]}, ["pins[0]", "selects no vertex", "body bounds"]),
    ({"pins": [BASE["pins"][0], {"sphere": {"center": [0, 0, 1], "radius": 0.1}}]}, ["pins[1]", "selects no vertex"]),
    ({"pins": [{"cube": [0, 0, 0]}]}, ["pins[0]", "unknown keys", "cube"]),
    ({"handles": {"tip": {"sphere": {"center": [0.5, 0.5, 0.5], "radius": 0.05}}}},
     ["handles.tip", "outside the body"]),
])
def test_regions_selecting_nothing_fail_when_the_body_is_built(override, words):
    with pytest.raises(SceneError) as err:
        Simulator(BASE, overrides=override)
    for w in words:
        assert w in str(err.value), (w, str(err.value))


# ---------------------------------------------------------------- explain
_MIXED = {
    "name": "mixed",
    "body": {"mesh": {"generator": "box", "size": [0.4, 0.05, 0.05], "cell": 0.025},
             "material": {"model": "stvk", "young": 1e5, "poisson": 0.3, "density": 1000}},
    "pins": [{"box": [[-0.001, -1, -1], [0.001, 1, 1]]}],
    "handles": {"tip": {"box": [[0.399, -1, -1], [0.401, 1, 1]]}},
    "model": {"kind": "reduced", "modes": 4, "domains": {"regions": {"root": {"box": [[-1, -1, -1], [0.15, 1, 1]]},
                                                                      "mid": {"box": [[0.15, -1, -1], [0.3, 1, 1]]},
                                                                      "end": {"all": True}}},
              "full_space_domains": ["end"], "cubature": {"samples": 0}},
    "timeline": [{"t": 0.0, "topic": "wrench", "frame_id": "tip", "force": [0, 0, -1]}],
}


def test_explain_says_what_the_model_took():
    sim = Simulator(_MIXED)
    lines = sim.explain()
    text = "\n".join(lines)
    root = next(ln for ln in lines if "domain root" in ln)
    mid = next(ln for ln in lines if "domain mid" in ln)
    end = next(ln for ln in lines if "domain end" in ln)
    assert "pinned" in root and "no rigid DOFs" in root and "no fictitious" in root
    assert "6 rigid DOFs" in mid and "fictitious forces" in mid and "built" in mid
    assert "FULL SPACE" in end
    assert "no colliders declared" in text and "no contact" in text
    assert f"only the {len(sim.body.surface.vertex_ids)} surface vertices" in text
    assert "exact forces" in root and "cubature: off" in text
    # The account matches the model it describes.
    _model_facts(sim)
    assert sim.model.n_dofs == sum(d.n_dofs for d in sim.model.subspace) + sim.model.F
    assert f"{sim.model.n_dofs} DOFs" in text


def test_explain_lists_colliders_and_cubature_samples_per_domain():
    overrides, _ = FAST["soft_finger"]
    sim = Simulator("soft_finger", overrides=overrides)
    text = "\n".join(sim.explain())
    assert "contact: built only for the declared colliders: probe (sphere)" in text
    for d in sim.model.cubature_info["domains"]:
        assert f"cubature {d['samples']} of {d['elements']} elements" in text
    assert "uniform interface cubature" in text


def test_explain_on_a_full_space_scene():
    sim = Simulator(BASE, overrides={"colliders": {}})
    text = "\n".join(sim.explain())
    assert "full model: every vertex an unknown" in text and f"{sim.model.n_dofs} DOFs" in text


def test_cli_run_explain_prints_the_account(tmp_path):
    from mdss_ros.cli import main
    scene = tmp_path / "mixed.yaml"
    import yaml
    scene.write_text(yaml.safe_dump(_MIXED, sort_keys=False))
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        assert main(["run", str(scene), "--steps", "2", "--explain"]) == 0
    text = out.getvalue()
    assert "what was built and why" in text and "domain root" in text and "no rigid DOFs" in text


def test_cli_precompute_summary_ends_with_the_account(tmp_path):
    from mdss_ros.cli import main
    scene = tmp_path / "mixed.yaml"
    import yaml
    scene.write_text(yaml.safe_dump(_MIXED, sort_keys=False))
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        assert main(["precompute", str(scene), "--cache-dir", str(tmp_path / "cache")]) == 0
    text = out.getvalue()
    assert "mdss precompute: what was built and why" in text and "FULL SPACE" in text


def test_stiffness_pattern_has_a_diagonal_for_a_vertex_without_elements():
    """A region partition can leave a domain vertex all of whose tets are coupling
    elements; its domain force model must still build (it crashed indexing the diagonal)."""
    from mdss_ros.fem.assembly import stiffness_pattern
    tets = np.array([[0, 1, 2, 3]])
    pat = stiffness_pattern(tets, 5)                     # vertex 4 is in no tet
    dense = pat.matrix(np.arange(1.0, pat.nnz + 1)).toarray()
    assert pat.n_free == 15
    assert np.all(np.diag(dense) > 0)                    # every diagonal entry is stored (and addressed)
    assert np.all(dense[12:, :12] == 0) and np.all(dense[:12, 12:] == 0)
