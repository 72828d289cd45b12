"""The package's CDR (rosbags' typestore, ros_messages.cdr_bytes) is what ROS reads and writes.

For a message of every type the node publishes or takes in (Topics.TYPES), built as the
package builds it with strings of odd length so that padding occurs:
- rclpy.serialization.deserialize_message reads cdr_bytes, and what rclpy serialises of
  the result decodes in rosbags to the same bytes again (so every field survived, and
  both sides lay it out alike), rclpy's bytes differing from ours only where ours are
  zero (its uninitialised padding) and being of the same length;
- serialising twice, or an equal message built anew, gives identical bytes.
"""
import importlib

import numpy as np
import pytest
from rclpy.serialization import deserialize_message, serialize_message

from mdss_ros.record import ros_messages as rm
from mdss_ros.ros import convert

TOPICS = rm.Topics("/mdss")
FRAMES = ("world", "w", "odd", "abcd", "")


def _messages(frame):
    """{kind: (message builder)} for every kind of Topics.TYPES; a builder gives an equal
    message each call."""
    rng = np.random.default_rng(len(frame))
    x, tri, dom = rng.normal(size=(13, 3)), rng.integers(0, 13, size=(9, 3)), rng.integers(0, 3, size=13)
    poses = rng.normal(size=(3, 7))
    contacts = rng.normal(size=(4, 10))
    names = ["a", "bb", "ccc"]
    t = 12.345678901
    values = {f"key_{'k' * (i % 4)}{i}": (float(rng.normal()) if i % 3 else ("x" * (i % 5) if i % 2 else i))
              for i in range(40)}
    events = {e["topic"]: e for e in (
        {"t": 0.25, "topic": "wrench", "frame_id": "tip", "force": [0, 0.5, -4.0], "torque": [0, 0, 0.25]},
        {"t": 0.2, "topic": "point_force", "point": [1.0, 0.0625, 0.0625], "force": [0, 0, -3.0], "duration": 0.125},
        {"t": 0.1, "topic": "collider_pose", "name": "ball", "position": [0.5, 0, 0.5], "orientation": [0, 0, 0.6, 0.8]},
        {"t": 0.3, "topic": "clear_forces"})}

    def event(kind):
        return lambda: rm.event_messages(events[kind], TOPICS, frame or "world")[0][1]

    def decoded(kind, data_of):
        return lambda: convert.decode(data_of(), TOPICS.TYPES[kind])

    return {
        "wrench": event("wrench"),
        "point_forces": event("point_force"),
        "clear_forces": event("clear_forces"),
        "reset": lambda: convert.header(t, frame),
        "parameters": lambda: convert.parameter_event(t, f"/{frame}", {
            f"colliders.{frame or 'c'}.friction_static": 0.25, "points_publish_rate": 45.0,
            "world_frame": frame or "w", "max_point_forces": 7, "flag": True}),
        "collider_pose": event("collider_pose"),
        "topology": decoded("topology", lambda: convert.topology_mesh_bytes(x, tri)),
        "points": lambda: convert.SurfacePoints(dom).message(t, frame, x),
        "mesh": decoded("mesh", lambda: convert.MeshEncoder(tri).encode(x)),
        "marker": decoded("marker", lambda: convert.MarkerEncoder(tri, dom).encode(t, frame, x)),
        "domain_poses": lambda: convert.pose_array(t, frame, poses),
        "domain_transforms": lambda: convert.domain_transforms(t, frame, names, poses)[1],
        "contacts": lambda: convert.contacts_cloud(t, frame, contacts),
        "collider_contacts": lambda: convert.contacts_cloud(t, frame, contacts[:0]),
        "collider_wrench": lambda: convert.wrench_stamped(t, frame, [1, -2, 3.5, 0.25, 0, -1e-9]),
        "clock": lambda: convert.clock(t),
        "diagnostics": lambda: convert.diagnostics(t, "mdss: simulation", f"scene:{frame}", "warn", "slow", values),
        "tf": lambda: convert.tf_message(convert.domain_transforms(t, frame, names, poses, prefix="mdss/")),
    }


def _rclpy_class(type_name):
    pkg, ns, name = type_name.split("/")
    if pkg == "tf2_msgs":
        pytest.importorskip("tf2_msgs.msg", reason="tf2_msgs is not built in this venv (launch_scripts/build_tf2_msgs.sh)")
    return getattr(importlib.import_module(f"{pkg}.{ns}"), name)


def test_every_topic_type_is_covered():
    assert set(rm.Topics.TYPES) <= set(_messages("w"))


@pytest.mark.parametrize("kind", sorted(rm.Topics.TYPES))
def test_rclpy_reads_our_cdr_and_rosbags_reads_rclpys(kind):
    type_name = rm.Topics.TYPES[kind]
    cls = _rclpy_class(type_name)
    for frame in FRAMES:
        build = _messages(frame)[kind]
        msg = build()
        assert msg.__msgtype__ == type_name
        ours = rm.cdr_bytes(msg)
        assert ours[:4] == b"\x00\x01\x00\x00"                          # little-endian plain CDR
        assert rm.cdr_bytes(msg) == ours and rm.cdr_bytes(build()) == ours   # deterministic
        theirs = serialize_message(deserialize_message(ours, cls))
        if kind == "parameters":
            # ParameterValue always holds empty int64 and float64 sequences: Fast CDR pads to
            # 8 bytes before an empty one, rosbags does not (and cannot read Fast CDR's).
            # rclpy and mcap_ros2 read ours; only our own recordings are decoded by us.
            field = {1: "bool_value", 2: "integer_value", 3: "double_value", 4: "string_value"}
            back = deserialize_message(ours, cls)
            got = {p.name: getattr(p.value, field[p.value.type]) for p in back.changed_parameters}
            assert got == convert.parameter_values(msg) and got["points_publish_rate"] == 45.0
            continue
        assert len(theirs) == len(ours)
        assert all(a == b or a == 0 for a, b in zip(ours, theirs))       # only (zeroed) padding differs
        assert rm.cdr_bytes(convert.decode(theirs, type_name)) == ours   # every field survived both ways


def test_rclpy_sees_the_values_we_set():
    from geometry_msgs.msg import PoseArray
    from diagnostic_msgs.msg import DiagnosticArray
    poses = np.arange(14.0).reshape(2, 7)
    pa = deserialize_message(rm.cdr_bytes(convert.pose_array(1.5, "odd", poses)), PoseArray)
    assert pa.header.frame_id == "odd" and (pa.header.stamp.sec, pa.header.stamp.nanosec) == (1, 500_000_000)
    assert [[p.position.x, p.orientation.w] for p in pa.poses] == [[0.0, 6.0], [7.0, 13.0]]
    d = deserialize_message(rm.cdr_bytes(convert.diagnostics(0.0, "n", "h", "error", "m", {"k": 2.5, "b": False})),
                            DiagnosticArray)
    assert d.status[0].level == b"\x02" and [(v.key, v.value) for v in d.status[0].values] == [("k", "2.5"), ("b", "false")]


def test_bytes_pass_through_and_foreign_objects_are_refused():
    assert rm.cdr_bytes(bytearray(b"\x00\x01\x00\x00ab")) == b"\x00\x01\x00\x00ab"
    from std_msgs.msg import Header
    with pytest.raises(TypeError, match="rosbags typestore objects"):
        rm.cdr_bytes(Header())


def test_mask_timing_blanks_only_the_timing_values():
    values = {"sim_time": 1.0, "step_ms_median": 1.23, "real_time_factor": 0.5, "state": "running"}
    data = rm.cdr_bytes(convert.diagnostics(1.0, "n", "h", "ok", "running", values))
    masked = convert.decode(rm.mask_timing(data), "diagnostic_msgs/msg/DiagnosticArray")
    assert [(v.key, v.value) for v in masked.status[0].values] == [
        ("sim_time", "1"), ("step_ms_median", ""), ("real_time_factor", ""), ("state", "running")]
    other = rm.cdr_bytes(convert.diagnostics(1.0, "n", "h", "ok", "running", {**values, "step_ms_median": 9.0}))
    assert rm.mask_timing(other) == rm.mask_timing(data)


def test_decode_input_gives_the_objects_inputs_are_applied_from():
    for kind in rm.Topics.INPUTS:
        msg = _messages("world")[kind]()
        topic = TOPICS.collider_pose("ball") if kind == "collider_pose" else getattr(TOPICS, kind)
        back = rm.decode_input(TOPICS, topic, rm.cdr_bytes(msg))
        assert back.__msgtype__ == msg.__msgtype__ and rm.cdr_bytes(back) == rm.cdr_bytes(msg)
        assert rm.input_stamp(TOPICS, topic, back) == rm.input_stamp(TOPICS, topic, msg)
    with pytest.raises(KeyError):
        rm.decode_input(TOPICS, TOPICS.points, rm.cdr_bytes(_messages("world")["points"]()))
