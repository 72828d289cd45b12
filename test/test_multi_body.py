"""Two soft bodies, two node processes, one clock master (docs/architecture.md, "Clock modes").

Each body is its own mdss node under its own name (`-r __node:=body_a`), so its topics
live under /body_a/ and /body_b/. A third process (the probe) is the clock master and the
input publisher: it ticks /clock and pushes one body only. Both nodes run in lockstep,
record their own MCAP, and each recording replays bit for bit. This is how a rigid-body
simulator that owns /clock co-simulates several soft bodies over ROS 2 (on other machines
too: the same graph over DDS, with a shared ROS_DOMAIN_ID and a discovery range wider
than LOCALHOST).
"""
import sys
import time
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "launch_scripts"))
from launch_testing import Launch  # noqa: E402

pytestmark = pytest.mark.ros

OVERRIDES = ["body.mesh.cell=0.05", "model.domains.count=2", "model.modes=6"]
DT = 1.0 / 90.0
POSE_T, WRENCH_T = "geometry_msgs/msg/PoseArray", "geometry_msgs/msg/WrenchStamped"


def _t(stamp):
    return stamp["sec"] + 1e-9 * stamp["nanosec"]


def _body(launch, name, mcap):
    node = launch.node(name=name, ros_args=["-r", f"__node:={name}"], scene="cantilever",
                       scene_overrides=OVERRIDES, clock_mode="lockstep", mcap_path=str(mcap),
                       diagnostics_rate=5.0, points_publish_rate=0.0, mesh_publish_rate=0.0,
                       marker_publish_rate=0.0, pose_publish_rate=90.0)
    node.wait_for(rf"\] \[{name}\]: ready:", timeout=120)
    return node


def test_two_bodies_in_two_processes_step_in_lockstep_under_one_clock_master(tmp_path, ros_env):
    from mdss_ros.record.replay import replay
    ticks = [0.02 * i for i in range(1, 41)]               # 40 forward ticks: 40 steps each
    mcaps = {name: tmp_path / f"{name}.mcap" for name in ("body_a", "body_b")}
    push = {"header": {"frame_id": "tip", "stamp": {"sec": 0, "nanosec": 100_000_000}},
            "wrench": {"force": {"x": 0.0, "y": 0.0, "z": -30.0}}}
    with Launch(tmp_path, env=ros_env) as launch:
        assert launch.env["ROS_AUTOMATIC_DISCOVERY_RANGE"] == "LOCALHOST"
        for name in mcaps:
            _body(launch, name, mcaps[name])
        probe = launch.probe()
        for name in mcaps:
            probe.sub(f"/{name}/domain_poses", POSE_T)
        probe.pub("/body_a/wrench", WRENCH_T, push)        # body_a only, stamped 0.1 s
        probe.diagnostics(where={"inputs_pending": "1"}, name="body_a: simulation")
        probe.play_clock(ticks, period=0.02, subscribers=2)      # both bodies matched before the first tick
        probe.wait("@sent/clock", count=len(ticks), timeout=30)
        for name in mcaps:
            probe.wait(f"/{name}/domain_poses", where={"stamp_ge": 40 * DT - 1e-6}, timeout=30)
        time.sleep(0.5)
        poses = {name: probe.get(f"/{name}/domain_poses") for name in mcaps}
        # (discovery has long settled: the master's ticks reached both nodes)
        graph = {topic: probe.graph(topic) for topic in
                 ("/body_a/wrench", "/body_b/wrench", "/mdss/wrench", "/clock")}
        launch.stop_all(expect=0)
    # Distinct topics: each node subscribes its own inputs, nobody uses the default name,
    # and both follow the one clock (two subscribers; the master is its only publisher).
    assert graph["/body_a/wrench"]["subscribers"] == 1 and graph["/body_b/wrench"]["subscribers"] == 1
    assert graph["/mdss/wrench"]["subscribers"] == 0
    assert graph["/clock"] == {"publishers": 1, "subscribers": 2}, graph
    # Lockstep: one step per tick in both bodies, the same sim times.
    stamps = {name: [round(_t(p["header"]["stamp"]) / DT) for p in poses[name]] for name in poses}
    assert stamps["body_a"] == stamps["body_b"] == list(range(1, 41)), stamps
    # The push reached body_a only: its tip domain moved down, body_b's did not move.
    z = {name: np.array([p["poses"][-1]["position"]["z"] for p in poses[name]]) for name in poses}
    assert z["body_a"][-1] < z["body_b"][-1] - 1e-3, (z["body_a"][-1], z["body_b"][-1])
    # Separate recordings, each reproduced bit for bit by replay.
    for name, mcap in mcaps.items():
        res = replay(mcap, check=True)
        assert res.ok, (name, res.first_mismatch, res.missing, res.extra)
        assert res.steps == 40
