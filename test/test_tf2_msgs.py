"""tf2_msgs built from the pip rosidl generators (launch_scripts/build_tf2_msgs.sh, run by
the bootstrap where cmake, make and g++ exist) is a real ROS type: tf2_msgs/msg/TFMessage
published on /tf from one process (fastrtps typesupport) arrives, whole, in another process
subscribed with the same type (DDS matches the two only when both register
tf2_msgs::msg::dds_::TFMessage_). The node publishes its domain frames there, named
<node name>/<domain name>.

Skipped when the package was not built into this venv, with the command that builds it.
"""
import os
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "launch_scripts"))
from launch_testing import Launch  # noqa: E402

pytestmark = pytest.mark.ros

PREFIX = Path(sys.prefix) / "tf2_msgs_ws" / "install" / "tf2_msgs"
SITE = PREFIX / "lib" / f"python{sys.version_info[0]}.{sys.version_info[1]}" / "site-packages"


def _built():
    return (SITE / "tf2_msgs" / "msg" / "_tf_message.py").is_file() and any(
        (PREFIX / "lib").glob("libtf2_msgs__rosidl_typesupport_fastrtps_c.so*"))


def _tf_env():
    """This process's environment: the build is registered in the venv (its libraries
    linked into the venv's lib, a .pth for the package), so nothing needs adding."""
    env = dict(os.environ)
    env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"   # Launch adds a leased ROS_DOMAIN_ID
    return env


def _transform(child, x, yaw_w):
    return {"header": {"stamp": {"sec": 12, "nanosec": 345}, "frame_id": "world"},
            "child_frame_id": child,
            "transform": {"translation": {"x": x, "y": -0.25, "z": 0.5},
                          "rotation": {"x": 0.0, "y": 0.0, "z": (1.0 - yaw_w ** 2) ** 0.5, "w": yaw_w}}}


NOT_BUILT = pytest.mark.skipif(not _built(), reason=f"tf2_msgs is not built in this venv ({PREFIX} missing): "
                                                   "run `bash launch_scripts/build_tf2_msgs.sh` to build it")


@NOT_BUILT
def test_tfmessage_published_in_one_process_arrives_in_another(tmp_path):
    msg = {"transforms": [_transform("domain_0", 1.5, 1.0), _transform("domain_1", -2.0, 0.6)]}
    with Launch(tmp_path / "launch", env=_tf_env()) as launch:
        listener = launch.probe("listener")
        listener.sub("/tf", "tf2_msgs/msg/TFMessage")
        talker = launch.probe("talker")
        talker.pub("/tf", "tf2_msgs/msg/TFMessage", msg, ack=True)
        got = listener.wait("/tf", count=1, timeout=30)[0]
        graph = listener.graph("/tf")
        launch.stop_all(expect=0)
    assert [t["child_frame_id"] for t in got["transforms"]] == ["domain_0", "domain_1"]
    first, second = got["transforms"]
    assert first["header"]["frame_id"] == "world"
    assert first["header"]["stamp"] == {"sec": 12, "nanosec": 345}
    assert first["transform"]["translation"] == {"x": 1.5, "y": -0.25, "z": 0.5}
    assert second["transform"]["translation"]["x"] == -2.0
    assert second["transform"]["rotation"]["w"] == pytest.approx(0.6)
    assert second["transform"]["rotation"]["z"] == pytest.approx(0.8)
    assert graph == {"publishers": 1, "subscribers": 1}


@NOT_BUILT
def test_the_node_publishes_its_domain_frames_on_tf_named_after_itself(tmp_path):
    """Two domains of a small cantilever: /tf carries world -> mdss/domain_0, mdss/domain_1
    at the pose rate, with the same poses as ~/domain_poses at the same stamp."""
    with Launch(tmp_path / "launch", env=_tf_env()) as launch:
        node = launch.node(scene="cantilever", scene_overrides=["body.mesh.cell=0.05", "model.domains.count=2",
                                                                "model.modes=6"], pose_publish_rate=30.0)
        node.wait_for(r"\] \[mdss\]: ready:", timeout=120)
        probe = launch.probe()
        probe.sub("/tf", "tf2_msgs/msg/TFMessage")
        probe.sub("/mdss/domain_poses", "geometry_msgs/msg/PoseArray")
        tfs = probe.wait("/tf", count=5, timeout=30)
        poses = probe.wait("/mdss/domain_poses", count=5, timeout=30)
        launch.stop_all(expect=0)
    assert "domain frames on /tf as mdss/<domain>" in node.text
    for msg in tfs:
        assert [t["child_frame_id"] for t in msg["transforms"]] == ["mdss/domain_0", "mdss/domain_1"]
        assert all(t["header"]["frame_id"] == "world" for t in msg["transforms"])
    by_stamp = {(p["header"]["stamp"]["sec"], p["header"]["stamp"]["nanosec"]): p for p in poses}
    matched = 0
    for msg in tfs:
        stamp = msg["transforms"][0]["header"]["stamp"]
        p = by_stamp.get((stamp["sec"], stamp["nanosec"]))
        if p is None:
            continue
        for t, pose in zip(msg["transforms"], p["poses"]):
            assert t["transform"]["translation"] == pose["position"]
            assert t["transform"]["rotation"] == pose["orientation"]
        matched += 1
    assert matched >= 1
