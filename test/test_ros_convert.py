"""mdss_ros.ros.convert: messages from arrays; the numpy CDR encoders equal rosbags' bytes."""
import numpy as np
import pytest

from mdss_ros.ros import convert

TS = convert.TYPESTORE


def _rosbags(msg):
    return bytes(TS.serialize_cdr(msg, msg.__msgtype__, little_endian=True))


@pytest.fixture
def surface():
    rng = np.random.default_rng(3)
    n = 40
    return rng.normal(size=(n, 3)), rng.integers(0, n, size=(70, 3)), rng.integers(0, 4, size=n)


def _reference_mesh(x, tri):
    return convert.Mesh(triangles=[convert.MeshTriangle(vertex_indices=np.asarray(t, dtype=np.uint32)) for t in tri],
                        vertices=[convert.point(p) for p in x])


def test_mesh_encoder_bytes_are_rosbags_bytes_and_follow_the_vertices(surface):
    x, tri, _ = surface
    enc = convert.MeshEncoder(tri)
    for k in range(3):                   # the template is reused; positions change
        xk = x + 0.1 * k
        data = enc.encode(xk)
        assert data == _rosbags(_reference_mesh(xk, tri))
        msg = convert.decode(data, "shape_msgs/msg/Mesh")
        assert [t.vertex_indices.tolist() for t in msg.triangles] == tri.tolist()
        np.testing.assert_array_equal([[v.x, v.y, v.z] for v in msg.vertices], xk)
    data = enc.encode(x[:5])             # another vertex count: a new template
    assert data == _rosbags(_reference_mesh(x[:5], tri))
    assert convert.topology_mesh_bytes(x, tri) == _rosbags(_reference_mesh(x, tri))


def _reference_marker(t, frame, x, tri, dom):
    d = dom[tri]
    tri_dom = np.where(d[:, 1] == d[:, 2], d[:, 1], d[:, 0])          # majority of the corners
    empty = np.zeros(0, dtype=np.uint8)
    return convert.Marker(
        header=convert.header(t, frame), ns="mdss_surface", id=0, type=convert.Marker.TRIANGLE_LIST,
        action=convert.Marker.ADD,
        pose=convert.Pose(position=convert.point((0, 0, 0)), orientation=convert.quaternion((0, 0, 0, 1))),
        scale=convert.Vector3(x=1.0, y=1.0, z=1.0), color=convert.ColorRGBA(r=1.0, g=1.0, b=1.0, a=1.0),
        lifetime=convert.Duration(sec=0, nanosec=0), frame_locked=False,
        points=[convert.point(x[i]) for i in tri.reshape(-1)],
        colors=[convert.ColorRGBA(r=float(c[0]), g=float(c[1]), b=float(c[2]), a=1.0)
                for c in np.repeat(convert.DOMAIN_PALETTE[tri_dom], 3, axis=0)],
        texture_resource="", texture=convert.CompressedImage(header=convert.header(0.0, ""), format="", data=empty),
        uv_coordinates=[], text="", mesh_resource="", mesh_file=convert.MeshFile(filename="", data=empty),
        mesh_use_embedded_materials=False)


@pytest.mark.parametrize("frame", ["world", "w", "odom_frame_x", ""])
def test_marker_encoder_bytes_are_rosbags_bytes(surface, frame):
    x, tri, dom = surface
    enc = convert.MarkerEncoder(tri, dom)
    for t in (0.0, 12.345678901, 3.5):
        assert enc.encode(t, frame, x) == _rosbags(_reference_marker(t, frame, x, tri, dom))


def test_surface_points_cloud_layout(surface):
    x, _, dom = surface
    sp = convert.SurfacePoints(dom)
    msg = sp.message(1.5, "world", x)
    assert [(f.name, f.offset, f.datatype, f.count) for f in msg.fields] == [
        ("x", 0, 7, 1), ("y", 4, 7, 1), ("z", 8, 7, 1), ("domain", 12, 2, 1)]
    assert msg.point_step == 16 and msg.width == len(x) and msg.height == 1 and not msg.is_bigendian
    assert msg.data.dtype == np.uint8 and msg.row_step == len(msg.data) == 16 * len(x)
    rec = np.frombuffer(msg.data, dtype=convert.SURFACE_POINT_DTYPE)
    np.testing.assert_array_equal(np.stack([rec["x"], rec["y"], rec["z"]], 1), x.astype(np.float32))
    np.testing.assert_array_equal(rec["domain"], dom)
    assert msg.header.frame_id == "world" and convert.seconds(msg.header.stamp) == 1.5
    before = _rosbags(msg)
    sp.message(2.0, "world", x + 1.0)                                 # the buffer is reused...
    assert _rosbags(msg) == before                                    # ...the message kept its copy


def test_cloud_encoder_bytes_are_rosbags_bytes():
    """Contacts and surface points through CloudEncoder: the bytes of cloud() serialised by
    rosbags, for frame ids of every length mod 4 (the fields' alignment follows it), empty
    clouds, several stamps, and a template reused across frame ids and sizes."""
    rng = np.random.default_rng(11)
    contacts = convert.CloudEncoder(convert.CONTACT_DTYPE)
    for frame in ("world", "", "a", "ab", "abc", "odom_frame_x"):
        for k in (0, 1, 7, 25):
            c, t = rng.normal(size=(k, 10)), float(rng.uniform(0.0, 1e5))
            data = contacts.encode(t, frame, convert.contact_records(c))
            assert data == _rosbags(convert.contacts_cloud(t, frame, c)), (frame, k)
    msg = convert.decode(data, "sensor_msgs/msg/PointCloud2")
    np.testing.assert_array_equal(np.frombuffer(msg.data, dtype=convert.CONTACT_DTYPE)["fz"],
                                  c[:, 9].astype(np.float32))
    domain = rng.integers(0, 6, size=40)
    points, reference = convert.CloudEncoder(convert.SURFACE_POINT_DTYPE), convert.SurfacePoints(domain)
    fill = convert.SurfacePoints(domain)
    for t in (0.0, 1.25, 3600.5):
        x = rng.normal(size=(40, 3))
        assert points.encode(t, "world", fill.fill(x)) == _rosbags(reference.message(t, "world", x))
    with pytest.raises(TypeError, match="dtype"):
        points.encode(0.0, "world", convert.contact_records(np.zeros((1, 10))))


def test_poses_encoder_bytes_are_rosbags_bytes():
    """~/domain_poses, ~/domain_transforms and /tf through PosesEncoder: rosbags' bytes of
    pose_array, domain_transforms and tf_message, for one and for eleven domains, names and
    frame ids of every length mod 4 (the strings shift the alignment of the doubles)."""
    rng = np.random.default_rng(12)
    for names in ([], ["body"], ["a", "bb", "ccc", "dddd", "e"], ["wörld_ä", "世界"], [f"domain_{i}" for i in range(11)]):
        enc = convert.PosesEncoder(names, "mdss/")
        for frame in ("world", "", "ab", "abc", "a", "world"):     # one encoder, the frame changing
            for t in (0.0, 1.23456789, 7777.5):
                poses = rng.normal(size=(len(names), 7))
                assert enc.pose_array(t, frame, poses) == _rosbags(convert.pose_array(t, frame, poses))
                assert enc.transforms(t, frame, poses) == [_rosbags(m) for m in
                                                           convert.domain_transforms(t, frame, names, poses)]
                assert enc.tf(t, frame, poses) == _rosbags(convert.tf_message(
                    convert.domain_transforms(t, frame, names, poses, prefix="mdss/")))
    with pytest.raises(ValueError, match="domains"):
        enc.pose_array(0.0, "world", np.zeros((3, 7)))          # a pose count the names do not have
    assert enc.pose_array(1.0, "world", poses) == _rosbags(convert.pose_array(1.0, "world", poses))
    tf = convert.decode(enc.tf(2.5, "world", poses), "tf2_msgs/msg/TFMessage")
    assert [m.child_frame_id for m in tf.transforms] == [f"mdss/domain_{i}" for i in range(11)]
    assert tf.transforms[3].transform.rotation.w == poses[3, 6] and tf.transforms[0].header.stamp.sec == 2


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
    rec = np.frombuffer(msg.data, dtype=convert.CONTACT_DTYPE)
    np.testing.assert_array_equal(rec["depth"], [6, 16])
    np.testing.assert_array_equal(rec["fz"], [9, 19])
    assert convert.contacts_cloud(0.1, "world", np.zeros((0, 10))).width == 0
    poses = np.array([[1, 2, 3, 0, 0, 0, 1], [4, 5, 6, 0, 0, 1, 0]], dtype=float)
    pa = convert.pose_array(0.2, "world", poses)
    assert [p.position.x for p in pa.poses] == [1, 4] and pa.poses[1].orientation.z == 1
    tfs = convert.domain_transforms(0.2, "world", ["a", "b"], poses, prefix="mdss/")
    assert [t.child_frame_id for t in tfs] == ["mdss/a", "mdss/b"] and tfs[1].transform.translation.z == 6
    assert convert.tf_message(tfs).transforms == tfs
    ps = convert.pose_stamped(0.25, "world", (1, 2, 3), (0, 0, 0.6, 0.8))
    assert (ps.pose.position.y, ps.pose.orientation.w, ps.header.frame_id) == (2, 0.8, "world")
    w = convert.wrench_stamped(0.3, "world", [1, 2, 3, 4, 5, 6])
    assert (w.wrench.force.y, w.wrench.torque.z) == (2, 6)
    d = convert.diagnostics(0.4, "mdss: simulation", "scene:x", "warn", "slow", {"a": 1.5, "b": True, "c": "ok"})
    st = d.status[0]
    assert st.level == convert.DiagnosticStatus.WARN and [(kv.key, kv.value) for kv in st.values] == [
        ("a", "1.5"), ("b", "true"), ("c", "ok")]
    for m in (msg, pa, tfs[0], convert.tf_message(tfs), ps, w, d, convert.clock(1.0), convert.header(1.0, "abc")):
        assert m.__msgtype__ in TS.types and convert.decode(_rosbags(m), m.__msgtype__) is not None
