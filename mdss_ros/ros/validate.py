"""Incoming messages -> checked arrays, or InputRejected(kind, reason).

Every check the node makes on an input lives here, as a plain function of the message
fields, so each rejection has one kind (a /diagnostics counter `rejected_<kind>`) and a
reason a user can act on. Nothing here touches the simulator.

Messages are what ros_messages.decode_input makes of an input's CDR bytes: rosbags
typestore objects (convert.TYPESTORE), read by field name only, so a PointCloud2's
`fields` are PointField dataclasses and its `data` a uint8 numpy array (any buffer of
bytes is read alike).
"""
import math
from dataclasses import dataclass

import numpy as np

#: Rejection kinds, in the order /diagnostics lists their counters.
KINDS = ("non_finite", "magnitude", "unknown_handle", "unknown_collider", "bad_cloud",
         "bad_frame", "bad_quaternion", "stamp_past", "stamp_future", "malformed", "apply_error")

# sensor_msgs/PointField datatypes -> numpy (little-endian; big-endian swaps the byte order).
_DTYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}
_TYPE_NAMES = {1: "INT8", 2: "UINT8", 3: "INT16", 4: "UINT16", 5: "INT32", 6: "UINT32",
               7: "FLOAT32", 8: "FLOAT64"}
FLOAT32 = 7


class InputRejected(Exception):
    """An input the node will not apply; kind is one of KINDS."""

    def __init__(self, kind, reason):
        assert kind in KINDS, kind
        super().__init__(f"{kind}: {reason}")
        self.kind, self.reason = kind, reason


@dataclass
class Limits:
    """Bounds on inputs (node parameters of the same names)."""

    max_force: float = 1.0e5            # N, |force| of a wrench or point force
    max_torque: float = 1.0e4           # N m, |torque| of a wrench
    max_position: float = 1.0e3         # m, |point| of a point force, |position| of a collider
    max_input_age: float = 1.0          # s of sim time a stamp may lie in the past
    max_input_lead: float = 60.0        # s of sim time a stamp may lie in the future
    max_point_forces: int = 1000        # points in one ~/point_forces cloud


def vector(values, what, limit, limit_name):
    """(n,) float64 of finite values with norm <= limit."""
    v = np.asarray(values, dtype=np.float64)
    if not np.all(np.isfinite(v)):
        raise InputRejected("non_finite", f"{what} {v.tolist()} is not finite")
    with np.errstate(over="ignore"):            # |v| of 1e300 is inf: rejected below, no warning
        n = float(np.linalg.norm(v))
    if n > limit:
        raise InputRejected("magnitude", f"|{what}| = {n:.4g} exceeds {limit_name} = {limit:.4g}")
    return v


def frame(frame_id, world_frame, what):
    """Geometry inputs are in the world frame (no tf2 here): '' or world_frame only."""
    if frame_id not in ("", world_frame):
        raise InputRejected("bad_frame", f"{what}: frame_id {frame_id!r} is not the world frame "
                                         f"{world_frame!r} (the node does not transform between frames)")


def wrench(frame_id, force, torque, handles, limits):
    """~/wrench: (handle, force (3,), torque (3,)); frame_id names the handle."""
    if frame_id not in handles:
        raise InputRejected("unknown_handle", f"frame_id {frame_id!r} is not a handle of the scene "
                                              f"(handles: {', '.join(sorted(handles)) or 'none'})")
    f = vector(force, "force", limits.max_force, "max_force")
    t = vector(torque, "torque", limits.max_torque, "max_torque")
    return frame_id, f, t


def pose(position, orientation, limits):
    """~/colliders/<name>/pose: position (3,), unit quaternion (4,) x y z w."""
    p = vector(position, "position", limits.max_position, "max_position")
    q = np.asarray(orientation, dtype=np.float64)
    if not np.all(np.isfinite(q)):
        raise InputRejected("non_finite", f"orientation {q.tolist()} is not finite")
    with np.errstate(over="ignore"):
        n = float(np.linalg.norm(q))
    if not 0.5 < n < 2.0:
        raise InputRejected("bad_quaternion", f"orientation {q.tolist()} has norm {n:.4g}, "
                                              f"not a rotation (x y z w with norm 1)")
    return p, q / n


def cloud_fields(fields, point_step):
    """{name: (offset, datatype)} of PointCloud2 fields; checks each fits in a point."""
    out = {}
    for f in fields:
        if f.name in out:
            raise InputRejected("bad_cloud", f"field {f.name!r} appears twice")
        if f.datatype not in _DTYPES:
            raise InputRejected("bad_cloud", f"field {f.name!r} has unknown datatype {f.datatype}")
        size = int(_DTYPES[f.datatype][1:])
        if f.offset + size * max(f.count, 1) > point_step:
            raise InputRejected("bad_cloud", f"field {f.name!r} (offset {f.offset}) does not fit in "
                                             f"point_step {point_step}")
        out[f.name] = (f.offset, f.datatype, f.count)
    return out


def cloud_columns(msg, required, optional=(), datatype=FLOAT32):
    """{name: (n,) float64} of a PointCloud2's fields; required/optional field names.

    Checks the layout (fields present, of `datatype`, count 1, inside the point;
    data length = row_step * height; row_step >= width * point_step) and raises
    InputRejected("bad_cloud", reason) naming what is wrong.
    """
    height, width, step, row_step = msg.height, msg.width, msg.point_step, msg.row_step
    n = height * width
    fields = cloud_fields(msg.fields, step)
    missing = [f for f in required if f not in fields]
    if missing:
        raise InputRejected("bad_cloud", f"missing field{'s' if len(missing) > 1 else ''} "
                                         f"{', '.join(missing)} (have: {', '.join(fields) or 'none'}; "
                                         f"need float32 {', '.join(required)})")
    for name in list(required) + [o for o in optional if o in fields]:
        _, dt, count = fields[name]
        if dt != datatype or count != 1:
            raise InputRejected("bad_cloud", f"field {name!r} is {count} x {_TYPE_NAMES.get(dt, dt)}, "
                                             f"expected 1 x {_TYPE_NAMES[datatype]}")
    data = np.frombuffer(msg.data, dtype=np.uint8)
    if n and step <= 0:
        raise InputRejected("bad_cloud", f"point_step {step} with {n} points")
    if row_step < width * step:
        raise InputRejected("bad_cloud", f"row_step {row_step} < width {width} x point_step {step}")
    if len(data) != row_step * height:
        raise InputRejected("bad_cloud", f"data has {len(data)} bytes, expected row_step {row_step} x "
                                         f"height {height} = {row_step * height}")
    rows = data.reshape(height, row_step)[:, :width * step].reshape(n, step) if n else np.zeros((0, 0), np.uint8)
    order = ">" if msg.is_bigendian else "<"
    out = {}
    for name in list(required) + [o for o in optional if o in fields]:
        off, dt, _ = fields[name]
        size = int(_DTYPES[dt][1:])
        col = np.ascontiguousarray(rows[:, off:off + size]).view(order + _DTYPES[dt]).reshape(n)
        out[name] = col.astype(np.float64)
    return out


def point_forces(msg, world_frame, limits):
    """~/point_forces: points (n, 3), forces (n, 3), durations (n,) (0 when absent)."""
    frame(msg.header.frame_id, world_frame, "point_forces")
    n = msg.height * msg.width
    if n > limits.max_point_forces:
        raise InputRejected("magnitude", f"{n} point forces in one message exceed "
                                         f"max_point_forces = {limits.max_point_forces}")
    cols = cloud_columns(msg, ("x", "y", "z", "fx", "fy", "fz"), ("duration",))
    p = np.stack([cols["x"], cols["y"], cols["z"]], axis=1)
    f = np.stack([cols["fx"], cols["fy"], cols["fz"]], axis=1)
    d = cols.get("duration", np.zeros(n))
    if n == 0:                                  # an empty cloud asks for nothing: a no-op
        return p.reshape(0, 3), f.reshape(0, 3), d.reshape(0)
    for what, a in (("point", p), ("force", f), ("duration", d)):
        bad = ~np.isfinite(a).reshape(n, -1).all(axis=1)
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            raise InputRejected("non_finite", f"{what} of point {i} is not finite "
                                              f"({int(bad.sum())} of {n} points)")
    for what, a, lim, name in (("point", p, limits.max_position, "max_position"),
                               ("force", f, limits.max_force, "max_force")):
        with np.errstate(over="ignore"):
            norms = np.linalg.norm(a, axis=1)
        if norms.max() > lim:
            i = int(np.argmax(norms))
            raise InputRejected("magnitude", f"|{what}| of point {i} = {norms[i]:.4g} exceeds {name} = {lim:.4g}")
    return p, f, d


def due_time(stamp_s, sim_time, limits):
    """When a stamped input takes effect: None (unstamped: the next step) or its stamp.

    An input stamped s is applied before the step that starts at the first sim time t
    with s <= t + dt/2 (stamps round to the nearest step, as TimelinePlayer does), so a
    stamp a little in the past is applied at the next step. Stamps more than
    max_input_age behind or max_input_lead ahead of the sim time are rejected.
    """
    if stamp_s == 0.0:
        return None
    if not math.isfinite(stamp_s):
        raise InputRejected("non_finite", f"stamp {stamp_s}")
    if stamp_s < sim_time - limits.max_input_age:
        raise InputRejected("stamp_past", f"stamp {stamp_s:.6f} s is {sim_time - stamp_s:.3f} s before the "
                                          f"sim time {sim_time:.6f} s (max_input_age = {limits.max_input_age} s)")
    if stamp_s > sim_time + limits.max_input_lead:
        raise InputRejected("stamp_future", f"stamp {stamp_s:.6f} s is {stamp_s - sim_time:.3f} s after the "
                                            f"sim time {sim_time:.6f} s (max_input_lead = {limits.max_input_lead} s); "
                                            f"stamp inputs with the time of /clock, or leave the stamp zero")
    return stamp_s
