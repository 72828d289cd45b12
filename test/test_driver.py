"""The simulation driver's rules without ROS (mdss_ros/ros/driver.py): every input counted,
the bounded queue, stamp order, failures that reset, and a run with a failure that replays
bit for bit."""
import numpy as np
import pytest

from mdss_ros import Simulator, load_scene
from mdss_ros.record.ros_messages import OutputRates, Topics, cdr_bytes
from mdss_ros.ros import convert
from mdss_ros.ros.driver import Driver
from mdss_ros.timeline import TimelinePlayer

OVERRIDES = {"body.mesh.cell": 0.05, "model.domains.count": 2, "model.modes": 6}


@pytest.fixture(scope="module")
def scene():
    return load_scene("cantilever", OVERRIDES)


def _driver(scene, queue_limit=100, **kw):
    out = []
    sim = Simulator(scene)
    d = Driver(sim, Topics("/mdss"), "world", OutputRates(diagnostics=0.0),
               lambda o, t, is_input: out.append((o, t, is_input)), queue_limit=queue_limit, **kw)
    d.start()
    return d, out


def _wrench(t, handle="tip", fz=-10.0):
    return cdr_bytes(convert.wrench_stamped(t, handle, [0, 0, fz, 0, 0, 0]))


def _counted(d):
    v = d.values()
    return v["inputs_received"] == (v["inputs_applied"] + v["rejected_total"] + v["inputs_pending"]
                                    + v["inputs_dropped"] + v["inputs_cleared"])


def test_every_input_is_counted_once_and_a_full_queue_drops_with_a_count(scene):
    d, _ = _driver(scene, queue_limit=3)
    tp = d.topics
    assert d.submit(tp.wrench, _wrench(0.5))                     # stamped ahead: waits
    assert not d.submit(tp.wrench, _wrench(0.0, "no_such_handle"))        # rejected: unknown handle
    assert not d.submit(tp.wrench, b"\x00\x01\x00\x00\x07")      # rejected: does not decode
    assert not d.submit(tp.collider_pose("ghost"), cdr_bytes(convert.pose_stamped(0.0, "world", (0, 0, 0))))
    assert not d.submit(tp.wrench, _wrench(0.0, fz=np.nan))      # rejected: non-finite
    assert d.submit(tp.wrench, _wrench(0.6)) and d.submit(tp.wrench, _wrench(0.7))
    assert not d.submit(tp.wrench, _wrench(0.8))                 # the fourth waiting input: dropped
    v = d.values()
    assert (v["inputs_received"], v["inputs_pending"], v["inputs_dropped"], v["rejected_total"]) == (8, 3, 1, 4)
    assert (v["rejected_unknown_handle"], v["rejected_unknown_collider"], v["rejected_non_finite"],
            v["rejected_malformed"]) == (1, 1, 1, 1)
    assert _counted(d)
    for _ in range(50):                                          # to t = 0.56: the first is applied
        d.advance()
    assert d.values()["inputs_applied"] == 1 and _counted(d)
    d.reset("service")                                           # the other two are discarded
    v = d.values()
    assert v["inputs_cleared"] == 2 and v["inputs_pending"] == 0 and _counted(d)


def test_an_empty_point_force_cloud_is_applied_as_nothing(scene):
    """A cloud of 0 points (height or width 0) is a no-op, not a crash (it once raised
    in the subscription and went uncounted: stress_node.py fuzz)."""
    d, _ = _driver(scene)
    empty = np.zeros(0, dtype=[(f, "<f4") for f in ("x", "y", "z", "fx", "fy", "fz")])
    assert d.submit(d.topics.point_forces, cdr_bytes(convert.cloud(0.0, "world", empty)))
    d.advance()
    v = d.values()
    assert v["inputs_applied"] == 1 and v["rejected_total"] == 0 and _counted(d)


def test_inputs_apply_at_their_stamps_like_the_timeline_player(scene):
    d, _ = _driver(scene)
    tp = d.topics
    d.submit(tp.wrench, _wrench(0.3, fz=0.0))                    # out of order: the later one first
    d.submit(tp.wrench, _wrench(0.1, fz=-20.0))
    for _ in range(45):
        d.advance()
    sim = Simulator(scene)
    player = TimelinePlayer([{"t": 0.1, "topic": "wrench", "frame_id": "tip", "force": [0, 0, -20]},
                             {"t": 0.3, "topic": "wrench", "frame_id": "tip", "force": [0, 0, 0]}])
    for _ in range(45):
        player.apply_due(sim)
        sim.step()
    np.testing.assert_array_equal(d.sim.surface_positions(), sim.surface_positions())


def test_a_failed_step_resets_publishes_nothing_of_it_and_is_recorded(scene, monkeypatch):
    d, out = _driver(scene)
    for _ in range(3):
        d.advance()
    real = d.sim.model.step
    monkeypatch.setattr(d.sim.model, "step", lambda *a, **k: (_ for _ in ()).throw(np.linalg.LinAlgError("x")))
    n = len(out)
    assert d.advance() is False
    monkeypatch.setattr(d.sim.model, "step", real)
    assert d.sim.time == 0.0 and d.stability == "failed" and d.failures == 1
    after = out[n:]
    tp = d.topics
    assert after[0][0].topic == tp.reset and after[0][2]                    # the reset, as an input
    assert convert.decode(after[0][0].data, "std_msgs/msg/Header").frame_id == "failure"
    assert {o.stamp_s for o, _, is_input in after[1:]} == {0.0}              # then the state at t = 0
    assert d.advance() and d.sim.step_count == 1


def test_a_run_with_a_failed_step_replays_bit_for_bit(tmp_path, monkeypatch):
    """The run fails at its 10th step and resets; the replay fails at the same step by
    itself (it skips the recorded 'failure' reset) and reproduces every output."""
    from mdss_ros.record.replay import RunRecording, replay
    from mdss_ros.simulator import Simulator as Sim
    real = Sim.step
    calls = {}

    def flaky(self):
        n = calls[id(self)] = calls.get(id(self), 0) + 1
        if n == 10:
            raise np.linalg.LinAlgError("the 10th step of this simulator fails")
        return real(self)
    monkeypatch.setattr(Sim, "step", flaky)
    rec = RunRecording(mcap=tmp_path / "run.mcap", out=lambda text: None)
    sim = rec.build("cantilever", OVERRIDES)
    rec.start(sim)
    oks = [rec.advance()[1] for _ in range(30)]
    rec.finish()
    assert oks.count(False) == 1 and rec.driver.failures == 1
    result = replay(tmp_path / "run.mcap", check=True, out=lambda text: None)
    assert result.ok, (result.first_mismatch, result.missing, result.extra)
    assert result.compared > 100


INSIDE_SCENE = {"name": "inside",
                "body": {"mesh": {"generator": "box", "size": [0.2, 0.2, 0.1], "cell": 0.05},
                         "material": {"model": "neohookean", "young": 1.0e5, "poisson": 0.3, "density": 1000},
                         "damping": {"alpha": 2.0, "beta": 0.002}},
                "colliders": {"ball": {"shape": "sphere", "radius": 0.06, "position": [0.1, 0.1, 0.2]}},
                "model": {"kind": "full"}}


def test_collider_poses_inside_the_body_are_counted_once_each_with_their_depth():
    """A pose that puts a collider deep inside the body (Simulator.set_collider_pose returns
    its depth) is counted by the driver, once per pose message, in /diagnostics
    collider_poses_inside, its depth in collider_inside_last; each is handed to
    on_collider_inside (where the node's throttled warning is: test_node_unit.py). Poses
    clear of the body, or only a hair into it (ordinary contact), are not counted."""
    seen = []
    d, out = _driver(INSIDE_SCENE, on_collider_inside=lambda name, info: seen.append((name, dict(info))))
    tp, sim = d.topics, d.sim
    r, dd = 0.06, 0.02
    top = np.array([0.1, 0.1, 0.1])            # the top face's centre vertex

    def pose(z):
        return cdr_bytes(convert.pose_stamped(0.0, "world", (top[0], top[1], z)))
    # A burst of 5 poses between two steps (a publisher faster than the step), all with
    # the sphere's centre dd below that vertex: it is the deepest, r - dd in. A vertex
    # counts when it is deeper than inside_depth (half a mean surface edge, 28 mm here;
    # shallower is ordinary contact): that vertex only, its four neighbours on the face
    # are 6 mm in.
    assert sim.inside_depth < r - dd
    rest = sim.rest_positions()[sim.surface_vertex_ids()]
    depth = r - np.linalg.norm(rest - (top - [0, 0, dd]), axis=1)
    n_in = int((depth > sim.inside_depth).sum())
    assert n_in == 1 and int((depth > 0).sum()) == 5
    for _ in range(5):
        assert d.submit(tp.collider_pose("ball"), pose(top[2] - dd))
    assert d.submit(tp.collider_pose("ball"), pose(top[2] + r - 0.5 * sim.inside_depth))   # a hair in: contact
    assert d.submit(tp.collider_pose("ball"), pose(0.3))                                  # clear
    assert d.submit(tp.collider_pose("ball"), pose(top[2] - dd))                          # inside again
    assert d.advance()
    v = d.values()
    assert v["inputs_applied"] == 8 and _counted(d)
    assert v["collider_poses_inside"] == 6
    assert len(seen) == 6 and {name for name, _ in seen} == {"ball"}
    for _, info in seen:
        assert info["depth"] == pytest.approx(r - dd, abs=1e-12) and info["vertices"] == n_in
        np.testing.assert_allclose(sim.rest_positions()[info["vertex"]], top, atol=1e-12)
    assert v["collider_inside_last"] == "ball: 40.0 mm, 1 vertices"
    # Counted per pose, not per step: steps with the collider held where it is add nothing.
    for _ in range(3):
        assert d.advance()
    assert d.values()["collider_poses_inside"] == 6 and len(seen) == 6
    # The count is in the /diagnostics message itself.
    n = len(out)
    d.emit_diagnostics()
    (diag, _, is_input), = out[n:]
    assert diag.topic == tp.diagnostics and not is_input
    msg = convert.decode(diag.data, tp.type_of(tp.diagnostics))
    values = {kv.key: kv.value for kv in msg.status[0].values}
    assert values["collider_poses_inside"] == "6"
    assert values["collider_inside_last"] == "ball: 40.0 mm, 1 vertices"
    # A reset starts from the scene again but keeps the count (it counts the input stream).
    d.reset("service")
    assert d.values()["collider_poses_inside"] == 6


def test_collider_wrench_topic_carries_the_torque_about_the_collider():
    """~/colliders/<name>/wrench (world frame) carries Simulator.collider_wrench as it is:
    force, and torque about the collider's position. A pad pressed 2 mm off the block's
    centre, posed by messages: the published torque is the moment of the contacts the node
    publishes on ~/colliders/<name>/contacts (float32) about the pad's position, to their
    rounding, and is not small (the closed form against a shifted pad:
    test_friction.py::test_pad_torque_is_the_contact_forces_moment_about_the_pad)."""
    from mdss_ros.verify import friction_study as fs
    d, out = _driver(fs.pressed_block({"kind": "full"}))
    tp, sim = d.topics, d.sim
    offset = np.array([0.02, 0.01, 0.0])
    for k in range(20):
        c = offset + [0.0, 0.0, 0.05 - 0.002 * (k + 1) / 20]
        assert d.submit(tp.collider_pose("pad"), cdr_bytes(convert.pose_stamped(0.0, "world", c)))
        n = len(out)
        assert d.advance()
    step_out = {o.topic: o for o, _, is_input in out[n:] if not is_input}
    wmsg = convert.decode(step_out[tp.collider_wrench("pad")].data, "geometry_msgs/msg/WrenchStamped")
    cmsg = convert.decode(step_out[tp.collider_contacts("pad")].data, "sensor_msgs/msg/PointCloud2")
    assert wmsg.header.frame_id == "world"
    force = np.array([wmsg.wrench.force.x, wmsg.wrench.force.y, wmsg.wrench.force.z])
    torque = np.array([wmsg.wrench.torque.x, wmsg.wrench.torque.y, wmsg.wrench.torque.z])
    np.testing.assert_array_equal(np.concatenate([force, torque]), sim.collider_wrench("pad"))
    rows = np.frombuffer(cmsg.data, dtype=convert.CONTACT_DTYPE)
    p = np.stack([rows[k] for k in ("x", "y", "z")], axis=1).astype(float)
    f = np.stack([rows[k] for k in ("fx", "fy", "fz")], axis=1).astype(float)
    r = p - sim.colliders["pad"].position
    # float32 rounding of p and f: |d(r x f)| <= eps32 (|p| |f| + |r| |f|) a contact.
    bound = np.finfo(np.float32).eps * (np.linalg.norm(f, axis=1) * (np.linalg.norm(p, axis=1)
                                                                    + np.linalg.norm(r, axis=1))).sum()
    np.testing.assert_allclose(torque, np.cross(r, -f).sum(0), rtol=0, atol=2 * bound)
    np.testing.assert_allclose(force, -f.sum(0), rtol=0, atol=np.finfo(np.float32).eps * np.abs(f).sum())
    # The pad presses on the block's top, centred 20 / 10 mm from its own centre: about the
    # pad, tau = (-o_y, o_x, 0) F_z up to the centre of pressure's distance from the top's
    # middle times F_z (the tet mesh is not mirror-symmetric; measured 0.1 mm with this
    # friction, 0.7 mm without: 1 mm allowed).
    assert force[2] > 10.0
    np.testing.assert_allclose(torque[:2], [-offset[1] * force[2], offset[0] * force[2]], rtol=0,
                               atol=1e-3 * force[2])
