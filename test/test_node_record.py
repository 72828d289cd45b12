"""The node's recording parameters as real processes: mcap_path (MCAP, log time = sim time)
and rerun_mode file (.rrd at rerun_path); a SIGKILLed node's file is recoverable; an
unwritable mcap_path is reported at start and the simulation goes on."""
import json
import signal
import sys
from collections import Counter
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "launch_scripts"))
from record_helpers import read_torn  # noqa: E402
from test_node import _collider_scene, _pose, _start_node, _wrench  # noqa: E402
from launch_testing import Launch  # noqa: E402

pytestmark = pytest.mark.ros

POINTS, WRENCH, CLOCK = "/mdss/surface/points", "/mdss/wrench", "/clock"
EMPTY, TRIGGER = "std_srvs/srv/Empty", "std_srvs/srv/Trigger"


def _clock_s(msg):
    return msg["clock"]["sec"] + 1e-9 * msg["clock"]["nanosec"]


def _mcap_ros2_messages(path):
    """[(topic, log_time, publish_time, decoded)] with mcap's reader and mcap_ros2's decoder."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory
    out = []
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for schema, channel, message, decoded in reader.iter_decoded_messages(log_time_order=False):
            out.append((channel.topic, message.log_time, message.publish_time, decoded))
        metadata = {m.name: dict(m.metadata) for m in reader.iter_metadata()}
    return out, metadata


def test_node_records_mcap_and_rrd_and_finishes_on_sigint(tmp_path):
    mcap, rrd = tmp_path / "run.mcap", tmp_path / "run.rrd"
    with Launch(tmp_path) as launch:
        node = _start_node(launch, mcap_path=str(mcap), rerun_mode="file", rerun_path=str(rrd))
        probe = launch.probe()
        probe.sub(CLOCK, "rosgraph_msgs/msg/Clock", depth=50)
        pub = launch.script("publisher", "force_publisher.py", "wrench", "tip", "--force", "0", "0", "-20")
        assert pub.wait(60) == 0, pub.text
        probe.diagnostics(where={"inputs_applied": {"ge": 1}}, timeout=30)
        t_seen = _clock_s(probe.wait(CLOCK, new=True, timeout=30)[-1])
        assert node.stop(signal.SIGINT) == 0, node.text
        assert "MCAP: " in node.text and "rerun: " in node.text

    # mcap + mcap_ros2's decoder (summary present: the file was finished)
    messages, metadata = _mcap_ros2_messages(mcap)
    counts = Counter(m[0] for m in messages)
    n_clock = counts[CLOCK]
    assert n_clock >= 45, counts                                     # >= 0.5 s of sim time at 90 Hz
    assert counts[POINTS] >= n_clock // 3 - 2 and counts[POINTS] <= n_clock // 3 + 2, counts   # 30 Hz
    assert counts["/tf"] >= n_clock - 2 and counts["/tf"] <= n_clock + 1, counts          # 90 Hz
    assert counts["/mdss/surface/topology"] == 1 and counts["/diagnostics"] >= 1, counts
    assert counts[WRENCH] == 1, counts
    log_times = [m[1] for m in messages]
    assert log_times == sorted(log_times)                                        # never decreasing
    clocks = [m for m in messages if m[0] == CLOCK]
    for _, log_time, _, msg in clocks:
        assert msg.clock.sec * 10**9 + msg.clock.nanosec == log_time             # log time = sim time
    assert clocks[-1][1] * 1e-9 >= t_seen - 1e-9
    (wrench,) = [m for m in messages if m[0] == WRENCH]
    assert wrench[3].header.frame_id == "tip" and wrench[3].wrench.force.z == -20.0
    tf = [m[3] for m in messages if m[0] == "/tf"][-1]
    assert len(tf.transforms) == 2 and len({t.child_frame_id for t in tf.transforms}) == 2   # one per domain
    assert all(t.header.frame_id == "world" for t in tf.transforms)
    run = metadata["mdss_run"]
    assert run["namespace"] == "/mdss" and json.loads(run["scene_json"])["name"] == "cantilever"
    assert json.loads(run["rates_json"])["points"] == 30.0

    # rosbags reads it too
    from rosbags.highlevel import AnyReader
    with AnyReader([mcap]) as reader:
        topics = {c.topic for c in reader.connections}
        assert {POINTS, WRENCH, "/tf", CLOCK} <= topics
        n = 0
        for conn, _, raw in reader.messages(connections=[c for c in reader.connections
                                                         if c.topic in (POINTS, WRENCH, "/tf")]):
            reader.deserialize(raw, conn.msgtype)
            n += 1
        assert n == counts[POINTS] + counts[WRENCH] + counts["/tf"]

    # rerun's reader
    from rerun.chunk import RrdReader
    reader = RrdReader(rrd)
    assert len(reader.recordings()) == 1
    frames = sum(c.num_rows for c in reader.store().stream()
                 if c.entity_path == "/world/body/surface" and not c.is_static)
    assert frames >= n_clock // 3 - 2, frames


def test_sigkilled_node_leaves_a_recoverable_mcap(tmp_path):
    mcap = tmp_path / "killed.mcap"
    with Launch(tmp_path) as launch:
        node = _start_node(launch, mcap_path=str(mcap))
        probe = launch.probe()
        probe.sub(CLOCK, "rosgraph_msgs/msg/Clock", depth=50)
        probe.wait(CLOCK, where={"stamp_ge": 2.0}, timeout=30)
        node.popen.send_signal(signal.SIGKILL)
        node.wait(30)
        t_last = max(_clock_s(m) for m in probe.get(CLOCK))
    messages, error = read_torn(mcap)
    counts = Counter(m[0] for m in messages)
    assert error is not None                                   # no summary/footer: it was killed
    assert counts[CLOCK] > 90 and counts["/tf"] >= counts[CLOCK] - 2, counts
    t_file = max(m[1] for m in messages if m[0] == CLOCK) * 1e-9
    print(f"SIGKILL: last /clock seen {t_last:.3f} s, last recovered {t_file:.3f} s")
    assert t_last - t_file <= 1.0, (t_last, t_file)
    from mdss_ros.record import mcap_recorder as mr
    recovered, info = mr.recover(mcap)
    assert len(recovered) == len(messages) and not info["complete"]


def test_unwritable_mcap_path_is_reported_and_the_node_keeps_stepping(tmp_path):
    with Launch(tmp_path) as launch:
        node = _start_node(launch, mcap_path="/proc/x/run.mcap")
        node.wait_for(r"ERROR.*cannot .*/proc/x.*the simulation goes on", timeout=5)
        probe = launch.probe()
        first = float(probe.diagnostics(timeout=30)["steps"])
        later = float(probe.diagnostics(where={"steps": {"gt": first + 20}}, timeout=30)["steps"])
        assert later > first
        assert node.stop() == 0, node.text


@pytest.mark.claims
def test_replay_check_reproduces_a_node_recording_with_a_reset(tmp_path):
    """A node records a run fed from another process: a wrench that wrench_timeout_s
    clears, a collider pressed into the beam, its friction and the points rate changed at
    runtime (parameters), ~/clear_forces and ~/reset_simulation.
    `mdss replay --check` reproduces every output bit for bit; the node's /diagnostics
    (wall-clock timer) are named as not compared."""
    from mdss_ros.record.replay import replay
    mcap = tmp_path / "node.mcap"
    with Launch(tmp_path) as launch:
        node = _start_node(launch, scene=str(_collider_scene(tmp_path)), mcap_path=str(mcap),
                           wrench_timeout_s=0.2, points_publish_rate=90.0, mesh_publish_rate=10.0)
        probe = launch.probe()
        probe.sub(CLOCK, "rosgraph_msgs/msg/Clock", depth=50)
        probe.pub("/mdss/wrench", "geometry_msgs/msg/WrenchStamped", _wrench("tip", (0, 0, -20)))
        probe.pub("/mdss/colliders/ball/pose", "geometry_msgs/msg/PoseStamped", _pose((0.5, 0.05, 0.12)))
        probe.diagnostics(where={"inputs_applied": {"ge": 2}}, timeout=30)
        probe.wait(CLOCK, new=True, timeout=30)
        probe.set_params("/mdss", {"colliders.ball.friction_static": 0.8, "colliders.ball.friction_kinetic": 0.5,
                                   "points_publish_rate": 45.0})
        probe.wait(CLOCK, count=10, new=True, timeout=30)
        probe.call("/mdss/clear_forces", TRIGGER)
        probe.call("/mdss/reset_simulation", EMPTY)
        probe.pub("/mdss/wrench", "geometry_msgs/msg/WrenchStamped", _wrench("tip", (0, 5, 0)))
        probe.diagnostics(where={"inputs_applied": {"ge": 3}}, timeout=30)
        probe.wait(CLOCK, count=20, new=True, timeout=30)
        assert node.stop(signal.SIGINT) == 0, node.text

    messages, _ = _mcap_ros2_messages(mcap)
    counts = Counter(m[0] for m in messages)
    assert counts["/mdss/reset_simulation/request"] == 1 and counts["/mdss/clear_forces/request"] == 1, counts
    assert counts["/mdss/parameter_events"] >= 1, counts              # the runtime changes, as inputs
    assert counts["/mdss/domain_transforms"] == 2 * counts["/mdss/domain_poses"], counts
    assert counts["/mdss/contacts"] > 0, counts                       # the collider did touch
    log_times = [m[1] for m in messages]
    assert log_times == sorted(log_times)                             # on across the reset

    res = replay(mcap, check=True)
    assert res.ok, (res.first_mismatch, res.missing, res.extra)
    assert res.compared == sum(n for t, n in counts.items() if t not in (
        "/diagnostics", "/mdss/wrench", "/mdss/colliders/ball/pose", "/mdss/clear_forces/request",
        "/mdss/reset_simulation/request", "/mdss/parameter_events"))
    assert res.not_compared["/diagnostics"][0] == counts["/diagnostics"]


@pytest.mark.parametrize("nodes", ["mesh", "lattice"])
def test_a_meshless_node_records_and_replays_bit_for_bit(tmp_path, nodes):
    """The node on a meshless scene (model.kind: meshless, nodes on the mesh's vertices or
    on a lattice): a wrench from another process, a collider pressed into the beam (the
    lattice's contacts act through the MLS weights), MCAP and rerun written, and
    `mdss replay --check` reproduces every output bit for bit."""
    from mdss_ros.record.replay import replay
    mcap, rrd = tmp_path / "node.mcap", tmp_path / "node.rrd"
    overrides = ["body.mesh.cell=0.05", "model.kind=meshless", f"model.meshless.nodes={nodes}"]
    with Launch(tmp_path) as launch:
        node = _start_node(launch, scene=str(_collider_scene(tmp_path)), scene_overrides=overrides,
                           mcap_path=str(mcap), rerun_mode="file", rerun_path=str(rrd))
        assert "meshless" in node.text
        probe = launch.probe()
        probe.sub(CLOCK, "rosgraph_msgs/msg/Clock", depth=50)
        probe.pub("/mdss/wrench", "geometry_msgs/msg/WrenchStamped", _wrench("tip", (0, 0, -20)))
        probe.pub("/mdss/colliders/ball/pose", "geometry_msgs/msg/PoseStamped", _pose((0.5, 0.05, 0.12)))
        probe.diagnostics(where={"inputs_applied": {"ge": 2}}, timeout=60)
        probe.wait(CLOCK, count=20, new=True, timeout=60)
        assert node.stop(signal.SIGINT) == 0, node.text
    messages, _ = _mcap_ros2_messages(mcap)
    counts = Counter(m[0] for m in messages)
    assert counts["/mdss/contacts"] > 0 and counts[POINTS] > 0, counts
    assert rrd.stat().st_size > 0
    res = replay(mcap, check=True)
    assert res.ok, (res.first_mismatch, res.missing, res.extra)
