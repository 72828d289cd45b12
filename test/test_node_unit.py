"""The node's rules in-process (no other processes): when inputs take effect, output
grids, the non-finite guard, wrench timeouts, parameter parsing."""
import contextlib
import os
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from mdss_ros import Simulator, load_scene
from mdss_ros.ros import convert
from mdss_ros.timeline import TimelinePlayer

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "launch_scripts"))
from launch_testing import DomainLease  # noqa: E402

pytestmark = pytest.mark.ros       # an rclpy node in this process (its own DDS domain)

OVERRIDES = {"body.mesh.cell": 0.05, "model.domains.count": 2, "model.modes": 6}


@contextlib.contextmanager
def node_in_process(tmp_path, scene, parameters=()):
    """An MdssNode on a scene dict, in this process, on a leased ROS domain limited to
    localhost; destroyed and shut down after the block."""
    import yaml
    import rclpy
    from rclpy.context import Context
    from rclpy.signals import SignalHandlerOptions
    from rclpy.parameter import Parameter
    from mdss_ros.node import MdssNode

    path = tmp_path / f"{scene['name']}.yaml"
    path.write_text(yaml.safe_dump(scene))
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    lease = DomainLease()
    ctx = Context()
    rclpy.init(context=ctx, domain_id=lease.domain_id, signal_handler_options=SignalHandlerOptions.NO)
    try:
        n = MdssNode(context=ctx, parameter_overrides=[Parameter("scene", value=str(path)),
                                                         Parameter("start_paused", value=True), *parameters])
        yield n
        n.destroy_node()
    finally:
        rclpy.try_shutdown(context=ctx)
        lease.release()


@pytest.fixture(scope="module")
def node():
    import rclpy
    from rclpy.context import Context
    from rclpy.signals import SignalHandlerOptions
    from rclpy.parameter import Parameter
    from mdss_ros.node import MdssNode

    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    lease = DomainLease()
    ctx = Context()
    rclpy.init(context=ctx, domain_id=lease.domain_id, signal_handler_options=SignalHandlerOptions.NO)
    params = [Parameter("scene", value="cantilever"),
              Parameter("scene_overrides", value=[f"{k}={v}" for k, v in OVERRIDES.items()]),
              Parameter("start_paused", value=True), Parameter("real_time_factor", value=0),
              Parameter("points_publish_rate", value=30.0)]
    n = MdssNode(context=ctx, parameter_overrides=params)
    sent = {}
    tp = n._topics
    for name, topic in (("points", tp.points), ("poses", tp.domain_poses), ("mesh", tp.mesh),
                        ("marker", tp.marker), ("clock", tp.clock)):
        pub = n._output_pubs[topic]
        sent[name] = []
        pub.publish = (lambda data, name=name, topic=topic: sent[name].append(
            convert.decode(data, tp.type_of(topic))))           # the CDR bytes the node sends
    n.sent = sent
    yield n
    n.destroy_node()
    rclpy.try_shutdown(context=ctx)
    lease.release()


def _clear(node):
    node._srv_reset(None, None)
    node.driver.counts["applied"] = 0
    for v in node.sent.values():
        v.clear()


def _wrench_msg(handle, force, t):
    return convert.wrench_stamped(t, handle, list(force) + [0, 0, 0])


def test_stamped_and_unstamped_inputs_take_effect_like_the_timeline_player(node):
    _clear(node)
    node.submit("~/wrench", _wrench_msg("tip", (0, 0, -20), 0.1))      # stamped: at the step starting at 0.1 s
    node.submit("~/wrench", _wrench_msg("tip", (0, 0, 0), 0.3))
    for _ in range(20):
        node.advance()
    node.submit("~/wrench", _wrench_msg("tip", (0, 0, -5), 0.0))        # unstamped: the next step (k = 20)
    for _ in range(25):
        node.advance()
    sim = Simulator(load_scene("cantilever", OVERRIDES))
    player = TimelinePlayer([{"t": 0.1, "topic": "wrench", "frame_id": "tip", "force": [0, 0, -20]},
                             {"t": 0.3, "topic": "wrench", "frame_id": "tip", "force": [0, 0, 0]},
                             {"t": 20 * sim.dt, "topic": "wrench", "frame_id": "tip", "force": [0, 0, -5]}])
    for _ in range(45):
        player.apply_due(sim)
        sim.step()
    np.testing.assert_array_equal(node.sim.surface_positions(), sim.surface_positions())
    assert node.driver.counts["applied"] == 3 and node.driver.pending == 0


def test_outputs_follow_their_own_grid_of_sim_time(node):
    _clear(node)
    node.set_parameters([__import__("rclpy").parameter.Parameter("mesh_publish_rate", value=0.0)])
    for _ in range(9):
        node.advance()
    stamps = [round(convert.seconds(m.header.stamp) * 90) for m in node.sent["points"]]
    assert stamps == [3, 6, 9]                                   # 30 Hz of 90 Hz steps
    assert len(node.sent["poses"]) == 9 and len(node.sent["clock"]) == 9
    assert not node.sent["mesh"]


def test_non_finite_state_is_never_published_and_resets(node, monkeypatch):
    _clear(node)
    for _ in range(2):
        node.advance()
    monkeypatch.setattr(node.sim, "surface_positions", lambda: np.full((170, 3), np.nan))
    node.advance()                                               # step 3 would publish points: NaN
    monkeypatch.undo()
    assert node.sim.time == 0.0 and node.driver.stability == "failed"
    for msg in node.sent["points"]:
        rec = np.frombuffer(bytes(msg.data), dtype=convert.SURFACE_POINT_DTYPE)
        assert np.all(np.isfinite(rec["x"]))
    values = {kv.key: kv.value for kv in node.diagnostics().status[0].values}
    assert values["stability"] == "failed" and values["stability_failures"] == "1"
    # a step that raises is a failure too, and the node goes on
    monkeypatch.setattr(node.sim.model, "step", lambda *a, **k: (_ for _ in ()).throw(np.linalg.LinAlgError("x")))
    node.advance()
    monkeypatch.undo()
    assert node.driver.failures == 2 and node.sim.time == 0.0
    node.advance()
    assert node.sim.step_count == 1
    node._srv_reset(None, None)
    assert node.driver.stability == "ok"


def test_diagnostics_report_a_guard_recovery_then_ok(node, monkeypatch):
    _clear(node)
    node.diagnostics()
    model = node.sim.model
    real, calls = model.step, {"n": 0}

    def spoiled(*a, **k):                        # the first attempt ends in NaN
        out = real(*a, **k)
        calls["n"] += 1
        if calls["n"] == 1:
            model.q = np.full_like(model.q, np.nan)
        return out
    monkeypatch.setattr(model, "step", spoiled)
    node.advance()
    monkeypatch.undo()
    assert node.sim.step_count == 1 and node.driver.stability == "ok"       # recovered: no reset
    status = node.diagnostics().status[0]
    values = {kv.key: kv.value for kv in status.values}
    assert values["stability"] == "recovered" and values["guard"] == "recovered"
    assert values["guard_recoveries"] == "1" and "non-finite" in values["guard_last_event"]
    assert status.message.startswith("recovered")
    node.advance()
    values = {kv.key: kv.value for kv in node.diagnostics().status[0].values}
    assert values["stability"] == "ok" and values["guard"] == "stable"


def test_wrench_timeout_clears_stale_wrenches(node):
    from rclpy.parameter import Parameter
    _clear(node)
    node.set_parameters([Parameter("wrench_timeout_s", value=0.05)])
    try:
        node.submit("~/wrench", _wrench_msg("tip", (0, 0, -20), 0.0))
        node.advance()
        assert "tip" in node.driver.held
        for _ in range(5):
            node.advance()
        assert "tip" not in node.driver.held and not node.sim._wrenches
    finally:
        node.set_parameters([Parameter("wrench_timeout_s", value=0.0)])


def test_parse_overrides_and_ros_args():
    from mdss_ros.node import _ros_args, parse_overrides
    assert parse_overrides("") == {}
    assert parse_overrides(["model.modes=6", "body.mesh.cell=0.05"]) == {"model.modes": 6, "body.mesh.cell": 0.05}
    assert parse_overrides('{"model.modes": 6}') == {"model.modes": 6}
    assert parse_overrides("model.modes=6, model.kind=full") == {"model.modes": 6, "model.kind": "full"}
    with pytest.raises(ValueError, match="KEY=VALUE"):
        parse_overrides(["model.modes"])
    assert _ros_args(["mdss_node", "-p", "scene:=x"]) == ["mdss_node", "--ros-args", "-p", "scene:=x"]
    assert _ros_args(["mdss_node", "--ros-args", "-p", "a:=1"]) == ["mdss_node", "--ros-args", "-p", "a:=1"]


def test_rerun_mode_off_from_the_command_line_is_yaml_false(tmp_path):
    """-p rerun_mode:=off reaches the node as False (YAML 1.1 reads off as a bool): it is
    the default mode off, not a type error at start; a YAML true names no mode."""
    from rclpy.parameter import Parameter
    from mdss_ros.node import StartupError

    scene = {"name": "pad", "body": {"mesh": {"generator": "box", "size": [0.1, 0.1, 0.04], "cell": 0.05},
                                     "material": {"model": "neohookean", "young": 1e5, "poisson": 0.3, "density": 1000}},
             "model": {"kind": "full"}}
    with node_in_process(tmp_path, scene, [Parameter("rerun_mode", value=False)]) as n:
        assert n._p("rerun_mode") == "off" and n.driver.rerun is None
    with pytest.raises(StartupError, match="rerun_mode must be one of off, file, spawn, serve, got True"):
        with node_in_process(tmp_path, scene, [Parameter("rerun_mode", value=True)]):
            pass


def test_collider_friction_is_a_node_parameter(tmp_path):
    from rclpy.parameter import Parameter

    scene = {"name": "pad", "body": {"mesh": {"generator": "box", "size": [0.1, 0.1, 0.04], "cell": 0.05},
                                     "material": {"model": "neohookean", "young": 1e5, "poisson": 0.3, "density": 1000}},
             "colliders": {"floor": {"shape": "plane", "friction": 0.3}},
             "model": {"kind": "full"}}
    with node_in_process(tmp_path, scene, [Parameter("colliders.floor.friction_static", value=0.8),
                                           Parameter("colliders.floor.friction_kinetic", value=0.6)]) as n:
        assert n.sim.colliders["floor"].friction == (0.8, 0.6)          # launch values replace the scene's
        bad = n.set_parameters([Parameter("colliders.floor.friction_kinetic", value=0.9)])
        assert not bad[0].successful and "must not exceed static" in bad[0].reason
        assert n.sim.colliders["floor"].friction == (0.8, 0.6)
        assert not n.set_parameters([Parameter("colliders.floor.friction_static", value=-1.0)])[0].successful
        ok = n.set_parameters_atomically([Parameter("colliders.floor.friction_static", value=0.2),
                                          Parameter("colliders.floor.friction_kinetic", value=0.1)])
        assert ok.successful
        assert n.sim.colliders["floor"].friction == (0.2, 0.1)
        n._srv_reset(None, None)                                        # a reset keeps the parameters' values
        assert n.sim.colliders["floor"].friction == (0.2, 0.1)


def test_collider_posed_inside_the_body_is_counted_and_warned_about_throttled(tmp_path, monkeypatch):
    """Issue 18, bad input: a pose that puts a collider deep inside the body is counted
    (/diagnostics collider_poses_inside) and warned about with its depth, at most once per
    WARN_PERIOD_S however many such poses arrive; the next warning says how many were held
    back. The node's own path: subscription -> driver -> on_collider_inside -> _report."""
    from mdss_ros import node as node_module
    from mdss_ros.node import WARN_PERIOD_S

    scene = {"name": "inside", "body": {"mesh": {"generator": "box", "size": [0.2, 0.2, 0.1], "cell": 0.05},
                                        "material": {"model": "neohookean", "young": 1e5, "poisson": 0.3,
                                                     "density": 1000}},
             "colliders": {"ball": {"shape": "sphere", "radius": 0.06, "position": [0.1, 0.1, 0.2]}},
             "model": {"kind": "full"}}
    with node_in_process(tmp_path, scene) as n:
        # The node's wall clock, held still or moved on by the test (the throttle reads
        # time.monotonic), and its logger's warnings.
        class Clock:
            now = 1000.0

            def monotonic(self):
                return self.now

            def __getattr__(self, name):
                return getattr(time, name)
        clock = Clock()
        monkeypatch.setattr(node_module, "time", clock)
        warned = []

        class Log:
            def warn(self, text):
                warned.append(text)

            def info(self, text):
                pass
            error = warning = warn
        monkeypatch.setattr(n, "get_logger", lambda: Log())

        def pose(z):
            return convert.pose_stamped(0.0, "world", (0.1, 0.1, z))

        def diag():
            return {kv.key: kv.value for kv in n.diagnostics().status[0].values}
        topic = "~/colliders/ball/pose"
        # A burst of 20 poses between two steps (a publisher faster than the step), each
        # 40 mm deep (the sphere's centre 20 mm under the top face's centre vertex) and
        # applied before the step: 20 counted, one warning.
        for _ in range(20):
            assert n.submit(topic, pose(0.08))
        n.advance()
        assert n.driver.inside_poses == 20
        assert diag()["collider_poses_inside"] == "20"
        assert len(warned) == 1, warned
        assert "~/colliders/ball/pose puts the collider 40.0 mm inside the body" in warned[0]
        # Clear of the body: not counted, nothing said.
        assert n.submit(topic, pose(0.3))
        n.advance()
        assert n.driver.inside_poses == 20 and len(warned) == 1
        # Back to the rest shape (the count and the throttle outlive a reset). Within the
        # period an inside pose is counted but not warned about; after it, the next one
        # warns again and says how many were held back.
        n._srv_reset(None, None)
        clock.now += 0.5 * WARN_PERIOD_S
        assert n.submit(topic, pose(0.08))
        n.advance()
        assert n.driver.inside_poses == 21 and len(warned) == 1
        n._srv_reset(None, None)
        clock.now += 0.5 * WARN_PERIOD_S + 0.1
        assert n.submit(topic, pose(0.08))
        n.advance()
        assert diag()["collider_poses_inside"] == "22"
        assert len(warned) == 2, warned
        assert "puts the collider 40.0 mm inside the body" in warned[1]
        assert warned[1].endswith("(and 20 more 'collider_inside' since the last warning)")
