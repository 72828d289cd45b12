"""launch_scripts/run_scene.py with several bodies (its docstring, "Several bodies").

The bodies file and scene list are checked before any process starts (fast, no ROS:
the first tests). Then two scenes run the ROS way: two node processes under their own
names, one clock master owning /clock, each node in clock_mode follow, a timeline
publisher and a recorder per body; both bodies reach the duration under the one clock,
every process exits 0, and each recording holds its own body's topics only.
"""
import sys
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "launch_scripts"))
import run_scene  # noqa: E402
from run_scene import BodiesError, plan_bodies, read_bodies_file, scene_specs  # noqa: E402

SMALL = ["body.mesh.cell=0.05", "model.modes=6", "model.domains.count=2"]   # builds in seconds
DT = 1.0 / 90.0


def _file(tmp_path, text):
    path = tmp_path / "bodies.yaml"
    path.write_text(text)
    return path


# ---------------------------------------------------------------------- the plan (no ROS)
def test_example_bodies_file_plans_two_named_bodies():
    bodies = plan_bodies(read_bodies_file(REPO / "config" / "two_bodies.yaml"))
    assert [b.name for b in bodies] == ["beam", "star"]
    beam, star = bodies
    assert Path(beam.scene) == REPO / "msg_scenes" / "cantilever.yaml"
    assert beam.sets == ["body.material.young=5000000.0"]          # a mapping, written as KEY=VALUE
    assert star.sets == ["body.damping.beta=0.01"]                  # a list, as is
    assert beam.params == {"points_publish_rate": 30.0, "mesh_publish_rate": 0.0}
    assert beam.timeline and star.timeline and beam.dt == star.dt == pytest.approx(DT)


def test_default_names_are_the_scene_names_suffixed_when_repeated(tmp_path):
    bodies = plan_bodies(scene_specs(["cantilever", "cantilever", "star_limbs"]), ["model.modes=6"])
    assert [b.name for b in bodies] == ["cantilever", "cantilever_2", "star_limbs"]
    assert all(b.sets == ["model.modes=6"] for b in bodies)
    # an explicit name is kept, and the unnamed body steps past it
    text = "- {scene: cantilever}\n- {scene: cantilever, name: cantilever}\n"
    assert [b.name for b in plan_bodies(read_bodies_file(_file(tmp_path, text)))] == ["cantilever_2", "cantilever"]
    # a lone scene on the command line keeps the node's own name
    assert plan_bodies(scene_specs(["cantilever"]), single_name="mdss")[0].name == "mdss"


def test_common_overrides_come_first_and_a_scene_path_is_relative_to_the_file(tmp_path):
    (tmp_path / "scenes").mkdir()
    (tmp_path / "scenes" / "beam.yaml").write_text((REPO / "msg_scenes" / "cantilever.yaml").read_text())
    text = ("bodies:\n  - {scene: scenes/beam.yaml, set: {model.modes: 4}, params: {physics_dt: 0.005}}\n")
    (body,) = plan_bodies(read_bodies_file(_file(tmp_path, text)), common_sets=["model.modes=6"],
                          common_params=["points_publish_rate:=10.0"])
    assert body.scene == str((tmp_path / "scenes" / "beam.yaml").resolve())
    assert body.sets == ["model.modes=6", "model.modes=4"]         # the body's own wins (it comes last)
    assert body.name == "cantilever" and body.dt == 0.005


@pytest.mark.parametrize("text, match", [
    ("- {name: a}\n", "body 1: `scene` is missing"),
    ("- {scene: cantilever, name: a}\n- {scene: star_limbs, name: a}\n", "body 2.*duplicate name 'a'"),
    ("- {scene: cantilever, colour: red}\n", r"unknown key\(s\) colour"),
    ("bodies: [{scene: cantilever}]\nclock: master\n", "unknown top-level key"),
    ("[]\n", "non-empty list of bodies"),
    ("- cantilever\n", "expected a mapping"),
    ("- {scene: no_such_scene}\n", "scene 'no_such_scene' not found"),
    ("- {scene: cantilever, set: {model.modes: -1}}\n", "model.modes: expected an integer"),
    ("- {scene: cantilever, set: [model.modes]}\n", "KEY=VALUE"),
    ("- {scene: cantilever, params: {clock_mode: source}}\n", "clock_mode is set by run_scene"),
    ("- {scene: cantilever, params: {points_rate: 3}}\n", "unknown node parameter 'points_rate'"),
    ("- {scene: cantilever, name: 2fast}\n", "not a valid ROS node name"),
    ("- {scene: cantilever\n", "not valid YAML"),
])
def test_a_bad_bodies_file_is_an_error_that_says_where(tmp_path, text, match):
    with pytest.raises(BodiesError, match=match):
        plan_bodies(read_bodies_file(_file(tmp_path, text)))


def test_the_command_line_refuses_a_bad_run_before_starting_anything(tmp_path, capsys):
    bad = _file(tmp_path, "- {scene: cantilever, name: a}\n- {scene: cantilever, name: a}\n")
    assert run_scene.main(["--bodies", str(bad)]) == 2
    assert "duplicate name 'a'" in capsys.readouterr().err
    # several bodies cannot each own /clock
    assert run_scene.main(["cantilever", "star_limbs", "--clock", "source"]) == 2
    assert "--clock master" in capsys.readouterr().err
    # lockstep is one step per tick: the bodies must share physics_dt
    two_dt = _file(tmp_path, "- {scene: cantilever}\n- {scene: cantilever, params: {physics_dt: 0.005}}\n")
    assert run_scene.main(["--bodies", str(two_dt), "--lockstep"]) == 2
    assert "same physics_dt" in capsys.readouterr().err
    # a recording folder that exists would be overwritten
    (tmp_path / "rec" / "cantilever_2").mkdir(parents=True)
    assert run_scene.main(["cantilever", "cantilever", "--record", str(tmp_path / "rec")]) == 2
    assert "already exist" in capsys.readouterr().err
    assert run_scene.main(["cantilever", "-p", "scene:=star_limbs", "--clock", "master"]) == 2
    assert "scene is set by run_scene" in capsys.readouterr().err
    assert run_scene.tick_count(DT, 1.0) == 90 and run_scene.tick_count(DT, 0.001) == 1


# ---------------------------------------------------------------------- a real run
def _bag(path):
    """{topic: [deserialised messages]} of a rosbag2 folder."""
    from rosbags.rosbag2 import Reader
    from rosbags.typesys import Stores, get_typestore
    store = get_typestore(Stores.ROS2_JAZZY)
    out = {}
    with Reader(path) as reader:
        for conn in reader.connections:
            out.setdefault(conn.topic, [])
        for conn, _, raw in reader.messages():
            out[conn.topic].append(store.deserialize_cdr(raw, conn.msgtype))
    return out


def _t(stamp):
    return stamp.sec + 1e-9 * stamp.nanosec


@pytest.mark.ros
def test_two_scenes_run_as_two_bodies_under_one_clock_master(tmp_path):
    from launch_testing import Launch
    rec = tmp_path / "rec"
    args = ["cantilever", "cantilever", "--duration", "1.0", "--record", str(rec)]
    for s in SMALL:
        args += ["--set", s]
    with Launch(tmp_path / "launch") as launch:
        run = launch.script("run_scene", "run_scene.py", *args)
        # the master starts once both bodies, both timeline publishers and both recorders
        # subscribed /clock
        run.wait_for(r"clock master: 6 node\(s\) subscribed \(cantilever, cantilever_2, cantilever_2_force_publisher, "
                     r"cantilever_2_recorder, cantilever_force_publisher, cantilever_recorder\)", timeout=300)
        code = run.wait(timeout=120)
        launch.stop_all(expect=0)
    assert code == 0, run.tail(60)
    exits = [line for line in run.lines if line.startswith("run_scene: ") and " exited with " in line]
    labels = {line.split()[1] for line in exits}
    assert labels == {"clock", "cantilever", "cantilever_2", "cantilever/timeline", "cantilever_2/timeline",
                      "cantilever/recorder", "cantilever_2/recorder"}, exits
    assert all(line.endswith("exited with 0") for line in exits), exits
    assert "every body reached t = 1 s" in run.text
    assert "clock_mode follow" in run.text

    bags = {name: _bag(rec / name) for name in ("cantilever", "cantilever_2")}
    poses = {}
    for name, bag in bags.items():
        other = "cantilever_2" if name == "cantilever" else "cantilever"
        # each recording holds its own body's topics, never the other's
        assert not any(t.startswith(f"/{other}/") for t in bag), sorted(bag)
        assert f"/{name}/domain_poses" in bag
        # the master's ticks up to the duration, one every dt, and nobody else's: a node in
        # clock_mode source would have added its own /clock
        ticks = [_t(m.clock) for m in bag["/clock"]]
        assert [round(t / DT) for t in ticks] == list(range(1, 91)), ticks
        assert ticks[-1] == pytest.approx(1.0, abs=1e-6)
        # the body took every step up to the duration under it
        stamps = [_t(m.header.stamp) for m in bag[f"/{name}/domain_poses"]]
        assert stamps[-1] == pytest.approx(1.0, abs=1e-6)
        assert [round(t / DT) for t in stamps if t > 0] == list(range(1, 91))
        # its timeline publisher pushed it (the t = 0.5 s wrench; the 2 s release is past the end)
        wrenches = bag[f"/{name}/wrench"]
        assert [_t(m.header.stamp) for m in wrenches] == [0.5] and wrenches[0].wrench.force.z == -20.0
        poses[name] = {round(_t(m.header.stamp) / DT): np.array([[p.position.x, p.position.y, p.position.z]
                                                                  for p in m.poses])
                       for m in bag[f"/{name}/domain_poses"]}
    # each node applied its one push (its last recorded /diagnostics, 1 Hz of wall time: not
    # always the one at t = 1 s, which a starved recorder may not have had before the node left)
    last = {}
    for name, bag in bags.items():
        last[name] = max((v for v in (_status(m, name) for m in bag["/diagnostics"]) if v),
                         key=lambda v: float(v["sim_time"]))
        assert float(last[name]["sim_time"]) > 0.5 and last[name]["inputs_applied"] == "1", last
    # One scene twice, under one clock: the same motion step for step (from step 1: the state
    # at t = 0 is published as the node starts, maybe before its recorder matched). After the
    # push too, unless a starved timeline publisher delivered it late to one of them.
    a, b = poses["cantilever"], poses["cantilever_2"]
    on_time = all(v["inputs_late"] == "0" for v in last.values())
    for k in range(1, 91 if on_time else 46):       # the push applies at the step from t = 0.5 s
        assert np.array_equal(a[k], b[k]), (k, a[k], b[k], [v["inputs_late"] for v in last.values()])


def _status(diag_array, name):
    for st in diag_array.status:
        if st.name == f"{name}: simulation":
            return {kv.key: kv.value for kv in st.values}
    return None
