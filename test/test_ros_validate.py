"""mdss_ros.ros.validate: every bad input gets one rejection kind and a reason.

Clouds are rosbags typestore objects, as ros_messages.decode_input makes them of the
bytes an input topic carries (data a uint8 numpy array, fields PointField dataclasses)."""
import numpy as np
import pytest

from mdss_ros.record import ros_messages as rm
from mdss_ros.ros import convert, validate
from mdss_ros.ros.convert import PointCloud2, PointField
from mdss_ros.ros.validate import InputRejected, Limits

FORCE_FIELDS = ("x", "y", "z", "fx", "fy", "fz")


def _cloud(rows, fields=FORCE_FIELDS, dtype="<f4", frame_id="", pad=0):
    rows = np.asarray(rows, dtype=np.float64).reshape(-1, len(fields))
    names = list(fields) + (["_pad"] if pad else [])
    formats = [dtype] * len(fields) + ([f"V{pad}"] if pad else [])
    rec = np.zeros(len(rows), dtype=np.dtype({"names": names, "formats": formats}))
    for i, f in enumerate(fields):
        rec[f] = rows[:, i]
    size = np.dtype(dtype).itemsize
    kind = {4: PointField.FLOAT32, 8: PointField.FLOAT64}[size]
    msg = PointCloud2(header=convert.header(0.0, frame_id), height=1, width=len(rows),
                      fields=[PointField(name=f, offset=i * size, datatype=kind, count=1) for i, f in enumerate(fields)],
                      point_step=rec.dtype.itemsize, row_step=rec.dtype.itemsize * len(rows),
                      is_bigendian=dtype.startswith(">"), is_dense=True, data=rec.view(np.uint8).copy())
    # through CDR and back, as the node and replay receive it
    topics = rm.Topics()
    return rm.decode_input(topics, topics.point_forces, rm.cdr_bytes(msg))


def _kind(fn, *args):
    with pytest.raises(InputRejected) as err:
        fn(*args)
    return err.value.kind, err.value.reason


def test_point_forces_accept_padding_big_endian_and_durations():
    rows = [[0.5, 0.05, 0.1, 0, 0, -1, 0.25], [1, 0, 0, 1, 2, 3, -1]]
    for dtype, pad in (("<f4", 0), ("<f4", 4), (">f4", 0)):
        p, f, d = validate.point_forces(_cloud(rows, FORCE_FIELDS + ("duration",), dtype, pad=pad), "world", Limits())
        np.testing.assert_allclose(p, np.asarray(rows)[:, :3], rtol=1e-6)
        np.testing.assert_allclose(f, np.asarray(rows)[:, 3:6])
        np.testing.assert_allclose(d, [0.25, -1])
    msg = _cloud(rows[0][:6])
    assert msg.data.dtype == np.uint8 and type(msg.fields[0]) is PointField      # what decode_input gives
    p, f, d = validate.point_forces(msg, "world", Limits())
    assert d.tolist() == [0.0]                                         # duration optional


def test_point_forces_rejections():
    L, good = Limits(max_point_forces=3), [0.5, 0.05, 0.1, 0, 0, -1]
    assert _kind(validate.point_forces, _cloud([0.5, 0, 0], ("x", "y", "z")), "world", L)[0] == "bad_cloud"
    kind, why = _kind(validate.point_forces, _cloud(good, dtype="<f8"), "world", L)
    assert kind == "bad_cloud" and "FLOAT64" in why
    short = _cloud(good)
    short.data = short.data[:-4]
    kind, why = _kind(validate.point_forces, short, "world", L)
    assert kind == "bad_cloud" and "expected row_step" in why
    narrow = _cloud(good)
    narrow.point_step = 8
    assert _kind(validate.point_forces, narrow, "world", L)[0] == "bad_cloud"
    assert _kind(validate.point_forces, _cloud([0.5, 0, 0, 0, np.nan, 0]), "world", L)[0] == "non_finite"
    assert _kind(validate.point_forces, _cloud([0.5, 0, 0, 0, 0, 1e9]), "world", L)[0] == "magnitude"
    assert _kind(validate.point_forces, _cloud([1e9, 0, 0, 0, 0, 1]), "world", L)[0] == "magnitude"
    assert _kind(validate.point_forces, _cloud([good] * 4), "world", L)[0] == "magnitude"
    assert _kind(validate.point_forces, _cloud(good, frame_id="camera"), "world", L)[0] == "bad_frame"
    dur = _cloud(good + [np.inf], FORCE_FIELDS + ("duration",))
    assert _kind(validate.point_forces, dur, "world", L)[0] == "non_finite"


def test_wrench_pose_and_stamp_rules():
    L = Limits(max_force=100, max_torque=10, max_input_age=0.5, max_input_lead=5)
    assert validate.wrench("tip", (0, 0, -1), (0, 0, 0), {"tip"}, L)[0] == "tip"
    assert _kind(validate.wrench, "nose", (0, 0, -1), (0, 0, 0), {"tip"}, L)[0] == "unknown_handle"
    assert _kind(validate.wrench, "tip", (0, 0, np.nan), (0, 0, 0), {"tip"}, L)[0] == "non_finite"
    assert _kind(validate.wrench, "tip", (0, 0, 0), (0, np.inf, 0), {"tip"}, L)[0] == "non_finite"
    assert _kind(validate.wrench, "tip", (0, 0, 101), (0, 0, 0), {"tip"}, L)[0] == "magnitude"
    assert _kind(validate.wrench, "tip", (0, 0, 1), (0, 11, 0), {"tip"}, L)[0] == "magnitude"
    p, q = validate.pose((1, 2, 3), (0, 0, 0, 2 * 0.99), L)
    np.testing.assert_allclose(q, [0, 0, 0, 1])
    assert _kind(validate.pose, (1, 2, 3), (0, 0, 0, 0), L)[0] == "bad_quaternion"
    assert _kind(validate.pose, (1, 2, np.nan), (0, 0, 0, 1), L)[0] == "non_finite"
    assert validate.due_time(0.0, 3.0, L) is None                      # unstamped: next step
    assert validate.due_time(2.7, 3.0, L) == 2.7                       # a little late: next step
    assert validate.due_time(7.9, 3.0, L) == 7.9                       # future: queued
    assert _kind(validate.due_time, 2.4, 3.0, L)[0] == "stamp_past"
    assert _kind(validate.due_time, 8.1, 3.0, L)[0] == "stamp_future"
