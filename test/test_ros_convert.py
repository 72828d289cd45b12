"""mdss_ros.ros.convert: messages from arrays; the numpy CDR encoders equal rclpy's."""
import numpy as np
import pytest

from rclpy.serialization import deserialize_message, serialize_message
from shape_msgs.msg import Mesh
from std_msgs.msg import ColorRGBA
from visualization_msgs.msg import Marker

from mdss_ros.ros import convert


@pytest.fixture
def surface():
    rng = np.random.default_rng(3)
    n = 40
    return rng.normal(size=(n, 3)), rng.integers(0, n, size=(70, 3)), rng.integers(0, 4, size=n)


def test_mesh_encoder_round_trips_and_follows_the_vertices(surface):
    x, tri, _ = surface
    enc = convert.MeshEncoder(tri)
    for k in range(3):                   # the template is reused; positions change
        xk = x + 0.1 * k
        msg = deserialize_message(enc.encode(xk), Mesh)
        assert [list(t.vertex_indices) for t in msg.triangles] == tri.tolist()
        np.testing.assert_array_equal([[v.x, v.y, v.z] for v in msg.vertices], xk)
    msg = deserialize_message(enc.encode(x[:5]), Mesh)       # another vertex count: a new template
    assert len(msg.vertices) == 5


def _reference_marker(t, frame, x, tri, dom):
    ref = Marker(header=convert.header(t, frame), ns="mdss_surface", id=0, type=Marker.TRIANGLE_LIST,
                 action=Marker.ADD)
    ref.pose.orientation.w = 1.0
    ref.scale.x = ref.scale.y = ref.scale.z = 1.0
    ref.color.r = ref.color.g = ref.color.b = ref.color.a = 1.0
    ref.points = [convert.point(x[i]) for i in tri.reshape(-1)]
    d = dom[tri]
    tri_dom = np.where(d[:, 1] == d[:, 2], d[:, 1], d[:, 0])          # majority of the corners
    ref.colors = [ColorRGBA(r=float(c[0]), g=float(c[1]), b=float(c[2]), a=1.0)
                  for c in np.repeat(convert.DOMAIN_PALETTE[tri_dom], 3, axis=0)]
    return ref


@pytest.mark.parametrize("frame", ["world", "w", "odom_frame_x", ""])
def test_marker_encoder_equals_the_message_rclpy_builds(surface, frame):
    x, tri, dom = surface
    enc = convert.MarkerEncoder(tri, dom)
    for t in (0.0, 12.345678901, 3.5):
        data = enc.encode(t, frame, x)
        ref = _reference_marker(t, frame, x, tri, dom)
        assert deserialize_message(data, Marker) == ref
        assert len(data) == len(serialize_message(ref))          # same layout, padding included


def test_surface_points_cloud_layout(surface):
    x, _, dom = surface
    msg = convert.SurfacePoints(dom).message(1.5, "world", x)
    assert [(f.name, f.offset, f.datatype, f.count) for f in msg.fields] == [
        ("x", 0, 7, 1), ("y", 4, 7, 1), ("z", 8, 7, 1), ("domain", 12, 2, 1)]
    assert msg.point_step == 16 and msg.width == len(x) and msg.height == 1 and not msg.is_bigendian
    rec = np.frombuffer(bytes(msg.data), dtype=convert.SURFACE_POINT_DTYPE)
    np.testing.assert_array_equal(np.stack([rec["x"], rec["y"], rec["z"]], 1), x.astype(np.float32))
    np.testing.assert_array_equal(rec["domain"], dom)
    assert msg.header.frame_id == "world" and convert.seconds(msg.header.stamp) == 1.5


def test_stamps_recover_the_step_index():
    dt = 1.0 / 90.0
    for k in (0, 1, 9, 12345, 10**7):
        st = convert.stamp(k * dt)
        assert 0 <= st.nanosec < 10**9
        assert abs(convert.seconds(st) - k * dt) < 1e-9 * max(1.0, k * dt) and round(convert.seconds(st) / dt) == k


def test_contacts_poses_wrench_and_diagnostics():
    c = np.arange(20, dtype=float).reshape(2, 10)
    msg = convert.contacts_cloud(0.1, "world", c)
    assert [f.name for f in msg.fields] == list(convert.CONTACT_FIELDS) and msg.width == 2
    poses = np.array([[1, 2, 3, 0, 0, 0, 1], [4, 5, 6, 0, 0, 1, 0]], dtype=float)
    pa = convert.pose_array(0.2, "world", poses)
    assert [p.position.x for p in pa.poses] == [1, 4] and pa.poses[1].orientation.z == 1
    tfs = convert.domain_transforms(0.2, "world", ["a", "b"], poses)
    assert [t.child_frame_id for t in tfs] == ["a", "b"] and tfs[1].transform.translation.z == 6
    w = convert.wrench_stamped(0.3, "world", [1, 2, 3, 4, 5, 6])
    assert (w.wrench.force.y, w.wrench.torque.z) == (2, 6)
    d = convert.diagnostics(0.4, "mdss: simulation", "scene:x", "warn", "slow", {"a": 1.5, "b": True, "c": "ok"})
    st = d.status[0]
    assert st.level == convert.DiagnosticStatus.WARN and [(kv.key, kv.value) for kv in st.values] == [
        ("a", "1.5"), ("b", "true"), ("c", "ok")]
