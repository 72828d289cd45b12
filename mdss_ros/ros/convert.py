"""Simulator arrays -> ROS messages as rosbags typestore objects; large ones as CDR bytes.

Every message here is a dataclass of the ROS 2 Jazzy typestore of rosbags (`TYPESTORE`,
one for the package): the node publishes, and a recording stores, their CDR bytes from
`TYPESTORE.serialize_cdr` (record.ros_messages.cdr_bytes), and inputs arrive as such
objects from `TYPESTORE.deserialize_cdr`. rosbags writes the layout rmw_fastrtps writes
(little-endian XCDR1) with its padding bytes zeroed, so equal messages are equal bytes:
recordings are compared byte for byte (rclpy's serialize_message leaves padding
uninitialised). Primitive arrays are numpy arrays in these objects (PointCloud2.data is
uint8), so clouds go through rosbags at numpy speed.

Shapes (one layout for the whole module):
  S surface vertices, T surface triangles, d domains, k contacts.
  positions (S, 3) float64, world frame, in topology order (Simulator.surface_positions());
  triangles (T, 3) int indices into positions (Simulator.surface_triangles());
  domain (S,) int, domain index of each surface vertex;
  poses (d, 7) float64: x y z qx qy qz qw (Simulator.domain_poses()).

shape_msgs/Mesh and a Marker TRIANGLE_LIST hold one Point object per vertex, which
rosbags builds and serialises at 2-3 us a point. Measured at 50K vertices and 100K
triangles (triangles and colours built once): a Mesh 140 ms through rosbags against
0.09 ms here, the Marker (300K corners) 670 ms against 2.3 ms. So `MeshEncoder` and
`MarkerEncoder` write those CDR bytes themselves: the fixed parts (triangles, colours)
once, the vertex block per frame with numpy; tests (test_ros_convert) check their
bytes equal `TYPESTORE.serialize_cdr` of the same message exactly. A PointCloud2's data
is one uint8 array (50K points: 1.0 ms built and serialised through rosbags), but the
small clouds a step publishes (~/contacts, one per collider) paid rosbags' fixed cost,
about 50-74 us each; `CloudEncoder` writes their header and fields once, the same way.
"""
import struct

import numpy as np
from rosbags.typesys import Stores, get_typestore

#: The typestore every message of the package is built from and (de)serialised with.
TYPESTORE = get_typestore(Stores.ROS2_JAZZY)
_T = TYPESTORE.types
Time = _T["builtin_interfaces/msg/Time"]
Duration = _T["builtin_interfaces/msg/Duration"]
Header = _T["std_msgs/msg/Header"]
ColorRGBA = _T["std_msgs/msg/ColorRGBA"]
Clock = _T["rosgraph_msgs/msg/Clock"]
Point = _T["geometry_msgs/msg/Point"]
Quaternion = _T["geometry_msgs/msg/Quaternion"]
Vector3 = _T["geometry_msgs/msg/Vector3"]
Pose = _T["geometry_msgs/msg/Pose"]
PoseArray = _T["geometry_msgs/msg/PoseArray"]
PoseStamped = _T["geometry_msgs/msg/PoseStamped"]
Transform = _T["geometry_msgs/msg/Transform"]
TransformStamped = _T["geometry_msgs/msg/TransformStamped"]
Wrench = _T["geometry_msgs/msg/Wrench"]
WrenchStamped = _T["geometry_msgs/msg/WrenchStamped"]
TFMessage = _T["tf2_msgs/msg/TFMessage"]
PointField = _T["sensor_msgs/msg/PointField"]
PointCloud2 = _T["sensor_msgs/msg/PointCloud2"]
CompressedImage = _T["sensor_msgs/msg/CompressedImage"]
MeshTriangle = _T["shape_msgs/msg/MeshTriangle"]
Mesh = _T["shape_msgs/msg/Mesh"]
Marker = _T["visualization_msgs/msg/Marker"]
MeshFile = _T["visualization_msgs/msg/MeshFile"]
KeyValue = _T["diagnostic_msgs/msg/KeyValue"]
DiagnosticStatus = _T["diagnostic_msgs/msg/DiagnosticStatus"]
DiagnosticArray = _T["diagnostic_msgs/msg/DiagnosticArray"]

#: ~/surface/points layout: float32 x, y, z and the uint8 domain index, 16 bytes a point.
SURFACE_POINT_DTYPE = np.dtype({"names": ["x", "y", "z", "domain"],
                                "formats": ["<f4", "<f4", "<f4", "u1"],
                                "offsets": [0, 4, 8, 12], "itemsize": 16})
#: ~/contacts layout (docs/architecture.md, "Contracts: ROS interface"): position, normal, depth, force on the body.
CONTACT_FIELDS = ("x", "y", "z", "nx", "ny", "nz", "depth", "fx", "fy", "fz")
CONTACT_DTYPE = np.dtype([(f, "<f4") for f in CONTACT_FIELDS])

_POINTFIELD_OF_DTYPE = {
    np.dtype("i1"): PointField.INT8, np.dtype("u1"): PointField.UINT8,
    np.dtype("<i2"): PointField.INT16, np.dtype("<u2"): PointField.UINT16,
    np.dtype("<i4"): PointField.INT32, np.dtype("<u4"): PointField.UINT32,
    np.dtype("<f4"): PointField.FLOAT32, np.dtype("<f8"): PointField.FLOAT64,
}

#: Domain colours (RGBA, tab10) for the marker; domain i takes entry i mod 10.
DOMAIN_PALETTE = np.array([
    (0.122, 0.467, 0.706), (1.000, 0.498, 0.055), (0.173, 0.627, 0.173), (0.839, 0.153, 0.157),
    (0.580, 0.404, 0.741), (0.549, 0.337, 0.294), (0.890, 0.467, 0.761), (0.498, 0.498, 0.498),
    (0.737, 0.741, 0.133), (0.090, 0.745, 0.812)], dtype=np.float32)


# --------------------------------------------------------------------- time
def stamp(t):
    """builtin_interfaces/Time of t seconds (rounded to the nanosecond)."""
    ns = int(round(float(t) * 1e9))
    return Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)


def seconds(time_msg):
    """Seconds of a builtin_interfaces/Time."""
    return time_msg.sec + 1e-9 * time_msg.nanosec


def header(t, frame_id):
    return Header(stamp=stamp(t), frame_id=frame_id)


def clock(t):
    return Clock(clock=stamp(t))


# --------------------------------------------------------------------- clouds
def cloud(t, frame_id, records):
    """sensor_msgs/PointCloud2 (height 1) of a structured array; fields from its dtype.

    data is a copy of the records' bytes (a uint8 array), so the message stays as it is
    when the caller reuses its buffer (SurfacePoints does, every frame)."""
    fields = []
    for name in records.dtype.names:
        dt, offset = records.dtype.fields[name][:2]
        if dt not in _POINTFIELD_OF_DTYPE:
            raise TypeError(f"field {name}: dtype {dt} has no PointField type (use little-endian)")
        fields.append(PointField(name=name, offset=offset, datatype=_POINTFIELD_OF_DTYPE[dt], count=1))
    records = np.ascontiguousarray(records).reshape(-1)
    return PointCloud2(header=header(t, frame_id), height=1, width=len(records), fields=fields,
                       is_bigendian=False, point_step=records.dtype.itemsize,
                       row_step=records.dtype.itemsize * len(records),
                       data=records.view(np.uint8).copy(), is_dense=True)


class SurfacePoints:
    """~/surface/points messages: a reused buffer; the domain column is written once.

    domain (S,) int.
    """

    def __init__(self, domain):
        self.records = np.zeros(len(domain), dtype=SURFACE_POINT_DTYPE)
        self.records["domain"] = np.asarray(domain, dtype=np.uint8)

    def message(self, t, frame_id, positions):
        return cloud(t, frame_id, self.fill(positions))

    def fill(self, positions):
        """The records (S,) of positions (S, 3), written into the reused buffer."""
        self.records["x"] = positions[:, 0]
        self.records["y"] = positions[:, 1]
        self.records["z"] = positions[:, 2]
        return self.records


def contact_records(contacts):
    """CONTACT_DTYPE records (k,) of contacts (k, 10): x y z nx ny nz depth fx fy fz."""
    return np.ascontiguousarray(np.asarray(contacts, dtype=np.float64).reshape(-1, len(CONTACT_FIELDS)),
                                dtype="<f4").view(CONTACT_DTYPE).reshape(-1)


def contacts_cloud(t, frame_id, contacts):
    """~/contacts of contacts (k, 10): x y z nx ny nz depth fx fy fz."""
    return cloud(t, frame_id, contact_records(contacts))


class CloudEncoder:
    """PointCloud2 CDR bytes (height 1, little-endian, dense) of records of one dtype:
    the bytes `cloud` + TYPESTORE.serialize_cdr give, written without rosbags.

    A node step publishes a cloud per collider (~/colliders/<name>/contacts), ~/contacts
    and, at the points rate, ~/surface/points. Through rosbags a 25-contact cloud took
    74 us built and serialised (grasp_lift, median of 300), most of it the ten PointField
    objects and the generic serialiser; here the header and fields are written once per
    frame_id and a message is its stamp, width, row_step and data written into that
    template. tests/test_ros_convert checks the bytes equal rosbags' exactly."""

    def __init__(self, dtype):
        self.dtype = np.dtype(dtype)
        fields = cloud(0.0, "", np.zeros(0, self.dtype)).fields      # validates the dtype
        self._fields = fields
        self._tpl, self._frame = None, None

    def _template(self, frame_id):
        c = _Cdr()
        c.time(0.0)
        c.string(frame_id)
        c.pack("I", 1)                            # height
        at_width = c.pos
        c.pack("I", 0)                            # width
        c.pack("I", len(self._fields))
        for f in self._fields:
            c.string(f.name)
            c.pack("I", f.offset)
            c.pack("B", f.datatype)
            c.pack("I", f.count)
        c.pack("?", False)                        # is_bigendian
        c.pack("I", self.dtype.itemsize)          # point_step
        at_row = c.pos
        c.pack("I", 0)                            # row_step
        c.pack("I", 0)                            # data: its length, then its bytes
        return bytearray(c.bytes()), 4 + at_width, 4 + at_row

    def encode(self, t, frame_id, records):
        """CDR bytes of the cloud of records (k,) of self.dtype, stamped t in frame_id."""
        if records.dtype != self.dtype:
            raise TypeError(f"records of dtype {records.dtype}, the encoder's is {self.dtype}")
        if self._tpl is None or frame_id != self._frame:
            self._tpl, self._frame = self._template(frame_id), frame_id
        buf, at_width, at_row = self._tpl
        st = stamp(t)
        n = len(records)
        size = n * self.dtype.itemsize
        struct.pack_into("<iI", buf, 4, st.sec, st.nanosec)
        struct.pack_into("<I", buf, at_width, n)
        struct.pack_into("<II", buf, at_row, size, size)
        return b"".join((buf, np.ascontiguousarray(records).tobytes(), b"\x01"))   # is_dense


# --------------------------------------------------------------------- CDR
class _Cdr:
    """Little-endian CDR (XCDR1, the layout TYPESTORE.serialize_cdr writes) into chunks,
    for the encoders of this module only (the module doc says why they exist).

    Alignment is relative to the start of the payload, after the 4-byte encapsulation;
    padding is zeros, as rosbags writes it.
    """

    def __init__(self):
        self.parts = [b"\x00\x01\x00\x00"]
        self.pos = 0

    def align(self, n):
        pad = (-self.pos) % n
        if pad:
            self.parts.append(b"\x00" * pad)
            self.pos += pad

    def raw(self, b, align=1):
        self.align(align)
        self.parts.append(b)
        self.pos += len(b)

    def pack(self, fmt, *values):
        # Every pack() call here is of one primitive type: align to its size.
        self.raw(struct.pack("<" + fmt, *values), struct.calcsize(fmt.lstrip("0123456789")[0]))

    def string(self, s):
        b = s.encode() + b"\x00"
        self.pack("I", len(b))
        self.raw(b)

    def time(self, t):
        st = stamp(t)
        self.pack("iI", st.sec, st.nanosec)

    def bytes(self):
        return b"".join(self.parts)


class _Template:
    """Bytes of a message whose layout is fixed, with writable float64 vertex blocks.

    Every frame writes the stamp and the vertex block in place, then copies the
    buffer once into the bytes that are published (and recorded) as they are.
    """

    def __init__(self, cdr, blocks, stamp_at=None):
        self.buf = bytearray(cdr.bytes())
        self.blocks = {name: np.frombuffer(self.buf, dtype="<f8", count=3 * n, offset=4 + off).reshape(n, 3)
                       for name, (off, n) in blocks.items()}
        self.stamp_at = stamp_at

    def set_stamp(self, t):
        st = stamp(t)
        struct.pack_into("<iI", self.buf, 4 + self.stamp_at, st.sec, st.nanosec)


class MeshEncoder:
    """shape_msgs/Mesh CDR bytes for fixed triangles (T, 3) and changing positions (S, 3)."""

    def __init__(self, triangles, n_vertices=None):
        self.triangles = np.ascontiguousarray(triangles, dtype="<u4").reshape(-1, 3)
        self.n_triangles = len(self.triangles)
        self._tpl = None if n_vertices is None else self._template(n_vertices)

    def _template(self, n):
        c = _Cdr()
        c.pack("I", self.n_triangles)
        c.raw(self.triangles.tobytes(), 4)
        c.pack("I", n)
        c.align(8)
        at = c.pos
        c.raw(bytes(24 * n))
        return _Template(c, {"vertices": (at, n)})

    def encode(self, positions):
        if self._tpl is None or len(self._tpl.blocks["vertices"]) != len(positions):
            self._tpl = self._template(len(positions))
        self._tpl.blocks["vertices"][:] = positions
        return bytes(self._tpl.buf)


class MarkerEncoder:
    """visualization_msgs/Marker TRIANGLE_LIST CDR bytes, one colour per domain.

    triangles (T, 3); domain (S,) int. Each triangle takes the colour of the domain of
    the majority of its vertices; the 3T corner colours are encoded once.
    """

    def __init__(self, triangles, domain, ns="mdss_surface", marker_id=0, alpha=1.0):
        tri = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
        self.corners = np.ascontiguousarray(tri.reshape(-1))
        d = np.asarray(domain, dtype=np.int64)[tri]
        tri_domain = np.where(d[:, 1] == d[:, 2], d[:, 1], d[:, 0])
        rgba = np.ones((len(tri_domain), 4), dtype="<f4")
        rgba[:, :3] = DOMAIN_PALETTE[tri_domain % len(DOMAIN_PALETTE)]
        rgba[:, 3] = alpha
        self._colors = np.repeat(rgba, 3, axis=0).tobytes()
        self.ns, self.marker_id = ns, marker_id
        self._tpl, self._frame = None, None

    def _template(self, frame_id):
        c = _Cdr()
        c.time(0.0)
        c.string(frame_id)                       # header
        c.string(self.ns)
        c.pack("iii", self.marker_id, 11, 0)     # id, TRIANGLE_LIST, ADD
        c.pack("7d", 0, 0, 0, 0, 0, 0, 1)        # pose (identity)
        c.pack("3d", 1, 1, 1)                    # scale
        c.pack("4f", 1, 1, 1, 1)                 # color (per-vertex colours override)
        c.pack("iI", 0, 0)                       # lifetime 0: forever
        c.pack("?", False)                       # frame_locked
        n = len(self.corners)
        c.pack("I", n)
        c.align(8)
        at = c.pos
        c.raw(bytes(24 * n))                     # points
        c.pack("I", n)
        c.raw(self._colors, 4)                   # colors
        c.string("")                             # texture_resource
        c.time(0.0)
        c.string("")                             # texture.header.frame_id
        c.string("")                             # texture.format
        c.pack("I", 0)                           # texture.data
        c.pack("I", 0)                           # uv_coordinates
        c.string("")                             # text
        c.string("")                             # mesh_resource
        c.string("")                             # mesh_file.filename
        c.pack("I", 0)                           # mesh_file.data
        c.pack("?", False)                       # mesh_use_embedded_materials
        return _Template(c, {"points": (at, n)}, stamp_at=0)

    def encode(self, t, frame_id, positions):
        if self._tpl is None or frame_id != self._frame:
            self._tpl, self._frame = self._template(frame_id), frame_id
        self._tpl.set_stamp(t)
        np.take(positions, self.corners, axis=0, out=self._tpl.blocks["points"])
        return bytes(self._tpl.buf)


def topology_mesh_bytes(rest_positions, triangles):
    """~/surface/topology: shape_msgs/Mesh of the rest surface (CDR bytes).

    Sent once, but through MeshEncoder all the same: rosbags would take ~140 ms at 50K
    vertices, and one encoder keeps ~/surface/topology and ~/surface/mesh one layout."""
    return MeshEncoder(triangles).encode(rest_positions)


def decode(data, type_name):
    """The TYPESTORE object of CDR bytes of type_name ('pkg/msg/Type'), for tests and tools."""
    return TYPESTORE.deserialize_cdr(bytes(data), type_name)


# --------------------------------------------------------------------- poses, wrenches
def point(p):
    return Point(x=float(p[0]), y=float(p[1]), z=float(p[2]))


def quaternion(q):
    """geometry_msgs/Quaternion of (4,) x y z w."""
    return Quaternion(x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3]))


def _pose(p):
    return Pose(position=point(p[:3]), orientation=quaternion(p[3:7]))


def pose_array(t, frame_id, poses):
    """geometry_msgs/PoseArray of poses (d, 7), in domain order."""
    return PoseArray(header=header(t, frame_id), poses=[_pose(p) for p in np.asarray(poses, dtype=float).tolist()])


def pose_stamped(t, frame_id, position, orientation=(0.0, 0.0, 0.0, 1.0)):
    """geometry_msgs/PoseStamped of position (3,) and orientation (4,) x y z w."""
    return PoseStamped(header=header(t, frame_id),
                       pose=Pose(position=point(position), orientation=quaternion(orientation)))


def domain_transforms(t, frame_id, names, poses, prefix=""):
    """One geometry_msgs/TransformStamped per domain: frame_id -> prefix + domain name
    (~/domain_transforms: no prefix; /tf: "<node name>/")."""
    return [TransformStamped(header=header(t, frame_id), child_frame_id=prefix + name,
                             transform=Transform(translation=Vector3(x=p[0], y=p[1], z=p[2]),
                                                 rotation=quaternion(p[3:7])))
            for name, p in zip(names, np.asarray(poses, dtype=float).tolist())]


def tf_message(transforms):
    """tf2_msgs/TFMessage of TransformStamped objects (/tf: domain_transforms with the prefix)."""
    return TFMessage(transforms=list(transforms))


class PosesEncoder:
    """~/domain_poses, ~/domain_transforms and /tf CDR bytes of poses (d, 7) for fixed
    domain names: the bytes of pose_array, domain_transforms and tf_message serialised by
    rosbags, written without it.

    The node publishes all three every step. Through rosbags, armadillo_class's 11 domains
    took 40 us (the PoseArray), 181 us (11 TransformStamped) and 155 us (the TFMessage),
    median of 300; here each message is a template, made again when the frame id changes
    (the node's world_frame parameter), whose stamps and 7-double poses are written in
    place. tests/test_ros_convert checks the bytes equal rosbags' exactly."""

    def __init__(self, names, tf_prefix=""):
        self.names, self.tf_prefix = list(names), tf_prefix
        self._frame = None

    def _templates(self, frame_id):
        if frame_id == self._frame:
            return
        c = _Cdr()
        c.time(0.0)
        c.string(frame_id)
        c.pack("I", len(self.names))
        if self.names:
            c.align(8)                            # rosbags pads an empty sequence not at all
        at = 4 + c.pos                            # the poses: one block of d x 7 doubles
        c.raw(bytes(56 * len(self.names)))
        self._array = (bytearray(c.bytes()), at)
        self._single = [self._transforms(frame_id, [n], tf=False) for n in self.names]
        self._tf = self._transforms(frame_id, [self.tf_prefix + n for n in self.names], tf=True)
        self._frame = frame_id

    @staticmethod
    def _transforms(frame_id, children, tf):
        """(buffer, stamp offsets, pose offsets) of TransformStampeds from frame_id to each
        of children: one message (tf False, one child), or a TFMessage (its count first)."""
        c = _Cdr()
        stamps, poses = [], []
        if tf:
            c.pack("I", len(children))
        for child in children:
            c.align(4)
            stamps.append(4 + c.pos)
            c.time(0.0)
            c.string(frame_id)
            c.string(child)
            c.align(8)
            poses.append(4 + c.pos)
            c.raw(bytes(56))                      # translation (3 doubles), rotation (4)
        return bytearray(c.bytes()), stamps, poses

    def _poses(self, poses):
        p = np.ascontiguousarray(poses, dtype="<f8")
        if p.shape != (len(self.names), 7):
            raise ValueError(f"poses of shape {p.shape} for {len(self.names)} domains: expected "
                             f"({len(self.names)}, 7)")
        return p

    def pose_array(self, t, frame_id, poses):
        """geometry_msgs/PoseArray of poses (d, 7), as pose_array(t, frame_id, poses)."""
        p = self._poses(poses).tobytes()
        self._templates(frame_id)
        buf, at = self._array
        st = stamp(t)
        struct.pack_into("<iI", buf, 4, st.sec, st.nanosec)
        buf[at:at + len(p)] = p
        return bytes(buf)

    def transforms(self, t, frame_id, poses):
        """[TransformStamped bytes] per domain, as domain_transforms(t, frame_id, names, poses)."""
        p = self._poses(poses)
        self._templates(frame_id)
        st = stamp(t)
        out = []
        for (buf, (at_stamp,), (at,)), row in zip(self._single, p):
            struct.pack_into("<iI", buf, at_stamp, st.sec, st.nanosec)
            buf[at:at + 56] = row.tobytes()
            out.append(bytes(buf))
        return out

    def tf(self, t, frame_id, poses):
        """tf2_msgs/TFMessage, as tf_message(domain_transforms(..., prefix=tf_prefix))."""
        p = self._poses(poses)
        self._templates(frame_id)
        buf, stamps, at = self._tf
        st = stamp(t)
        for offset, row in zip(at, p):
            buf[offset:offset + 56] = row.tobytes()
        for offset in stamps:
            struct.pack_into("<iI", buf, offset, st.sec, st.nanosec)
        return bytes(buf)


def wrench_stamped(t, frame_id, wrench):
    """geometry_msgs/WrenchStamped of wrench (6,): force then torque."""
    w = [float(v) for v in wrench]
    return WrenchStamped(header=header(t, frame_id), wrench=Wrench(force=Vector3(x=w[0], y=w[1], z=w[2]),
                                                                   torque=Vector3(x=w[3], y=w[4], z=w[5])))


# --------------------------------------------------------------------- diagnostics
_LEVELS = {"ok": DiagnosticStatus.OK, "warn": DiagnosticStatus.WARN, "error": DiagnosticStatus.ERROR}


def _text(v):
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, float):
        return f"{v:.6g}"
    return str(v)


def diagnostics(t, name, hardware_id, level, message, values):
    """diagnostic_msgs/DiagnosticArray with one status; values: ordered {key: value}."""
    status = DiagnosticStatus(level=_LEVELS[level], name=name, message=message, hardware_id=hardware_id,
                              values=[KeyValue(key=k, value=_text(v)) for k, v in values.items()])
    return DiagnosticArray(header=header(t, ""), status=[status])


# --------------------------------------------------------------------- parameters
_PARAMETER_TYPES = {bool: 1, int: 2, float: 3, str: 4}      # rcl_interfaces/ParameterType
_PARAMETER_FIELDS = {1: "bool_value", 2: "integer_value", 3: "double_value", 4: "string_value"}


def parameter_event(t, node, values):
    """rcl_interfaces/ParameterEvent announcing `values` ({name: bool, int, float or str})
    as changed parameters of node (its fully qualified name), stamped t."""
    ParameterEvent, Parameter, ParameterValue = (_T[f"rcl_interfaces/msg/{n}"] for n in
                                                 ("ParameterEvent", "Parameter", "ParameterValue"))
    changed = []
    for name, value in values.items():
        kind = _PARAMETER_TYPES[type(value)]
        fields = {"bool_value": False, "integer_value": 0, "double_value": 0.0, "string_value": "",
                  "byte_array_value": np.zeros(0, np.uint8), "bool_array_value": np.zeros(0, bool),
                  "integer_array_value": np.zeros(0, np.int64), "double_array_value": np.zeros(0),
                  "string_array_value": []}
        fields[_PARAMETER_FIELDS[kind]] = value
        changed.append(Parameter(name=name, value=ParameterValue(type=kind, **fields)))
    return ParameterEvent(stamp=stamp(t), node=node, new_parameters=[], changed_parameters=changed,
                          deleted_parameters=[])


def parameter_values(event):
    """{name: value} of a ParameterEvent's new and changed scalar parameters."""
    out = {}
    for p in list(event.new_parameters) + list(event.changed_parameters):
        field = _PARAMETER_FIELDS.get(p.value.type)
        if field is not None:
            out[p.name] = getattr(p.value, field)
    return out
