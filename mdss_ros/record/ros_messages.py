"""The ROS messages of a run without a ROS graph: what the node receives and publishes.

A headless run (`mdss run --mcap`) and a replay (`mdss replay`) build here the same
messages the node exchanges (docs/architecture.md, "Contracts: ROS interface"), under the node's namespace
(default `/mdss`), so a recording of either opens like a bag of the node. The message
building itself is mdss_ros.ros.convert (the node's converters); this module adds only
what recording needs on top:

    topics = Topics("/mdss")                        # topic names, types and offered QoS
    outputs = SimOutputs(sim, topics, rates=OutputRates())
    outputs.topology()                              # [Out] once: ~/surface/topology
    outputs.state(previous_step=None)               # [Out] /clock + every output due after
                                                    #   the step from previous_step (None: all)
    outputs.diagnostics(step_ms)                    # Out: /diagnostics of the last window
    inputs = InputApplier(sim, topics)
    for topic, msg in event_messages(event, topics):  # a scene timeline event -> messages
        inputs.apply(topic, msg)                    # applied as the node applies them
    tf_message_bytes(transforms)                    # tf2_msgs/msg/TFMessage CDR bytes

An `Out` is (topic, type_name, data: CDR bytes, stamp_s). Bytes, not message objects:
the recorder stores them as they are and replay compares them byte for byte.

Output times follow the node: step k publishes an output of rate r (Hz of sim time)
when floor(k dt r) changed; /clock goes out every step; rate 0 turns an output off.
/diagnostics runs at `diagnostics_rate` Hz of *sim* time here (the node uses wall time);
its timing values (TIMING_KEYS) differ from run to run, everything else is reproducible.

Inputs are applied through mdss_ros.ros.validate, as the node does, from the decoded
message: point forces therefore act in float32, as they arrive on ~/point_forces.
A call of the ~/clear_forces service is not a message; it is recorded on
`~/clear_forces/request` as a std_msgs/msg/Header stamped with its sim time (a service
event type would not decode in mcap_ros2 or rosbags).
"""
import math
import struct
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from geometry_msgs.msg import PoseStamped, WrenchStamped
from rclpy.serialization import deserialize_message
from sensor_msgs.msg import PointCloud2
from std_msgs.msg import Header

from ..ros import convert, validate

NAMESPACE = "/mdss"
WORLD_FRAME = "world"

#: /diagnostics values that measure wall time (differ between a run and its replay).
TIMING_KEYS = frozenset({"step_ms_median", "step_ms_max", "real_time_factor"})

#: ~/point_forces layout written for timeline point forces (node: x y z fx fy fz [duration]).
POINT_FORCE_DTYPE = np.dtype([(f, "<f4") for f in ("x", "y", "z", "fx", "fy", "fz", "duration")])

# QoS as the node offers it (node.py _qos): (depth, latched).
_INFINITE = {"sec": 9223372036, "nsec": 854775807}


def qos_profile(depth=10, latched=False, reliable=True):
    """An offered QoS profile as rosbag2 writes it in `offered_qos_profiles` (version 9 names)."""
    return {"history": "keep_last", "depth": int(depth),
            "reliability": "reliable" if reliable else "best_effort",
            "durability": "transient_local" if latched else "volatile",
            "deadline": dict(_INFINITE), "lifespan": dict(_INFINITE),
            "liveliness": "automatic", "liveliness_lease_duration": dict(_INFINITE),
            "avoid_ros_namespace_conventions": False}


class Topics:
    """Topic names, ROS types and offered QoS of the node under `namespace` (e.g. /mdss)."""

    TYPES = {
        "wrench": "geometry_msgs/msg/WrenchStamped",
        "point_forces": "sensor_msgs/msg/PointCloud2",
        "clear_forces": "std_msgs/msg/Header",
        "reset": "std_msgs/msg/Header",
        "collider_pose": "geometry_msgs/msg/PoseStamped",
        "topology": "shape_msgs/msg/Mesh",
        "points": "sensor_msgs/msg/PointCloud2",
        "mesh": "shape_msgs/msg/Mesh",
        "marker": "visualization_msgs/msg/Marker",
        "domain_poses": "geometry_msgs/msg/PoseArray",
        "domain_transforms": "geometry_msgs/msg/TransformStamped",
        "contacts": "sensor_msgs/msg/PointCloud2",
        "collider_wrench": "geometry_msgs/msg/WrenchStamped",
        "clock": "rosgraph_msgs/msg/Clock",
        "diagnostics": "diagnostic_msgs/msg/DiagnosticArray",
        "tf": "tf2_msgs/msg/TFMessage",
    }
    # (depth, latched) per kind, as node.py creates its publishers; tf as tf2_ros does.
    QOS = {"topology": (1, True), "clock": (1, True), "mesh": (2, False), "marker": (2, False),
           "tf": (100, False)}
    # reset: the ~/reset_simulation service call, recorded as a Header stamped with the sim
    # time it ended, so a replay resets where the run did.
    INPUTS = ("wrench", "point_forces", "clear_forces", "collider_pose", "reset")

    def __init__(self, namespace=NAMESPACE):
        ns = "/" + namespace.strip("/") if namespace.strip("/") else ""
        self.namespace = ns
        # the node's own name (the last part of its namespace): it names the /diagnostics
        # status and prefixes the domain frames on /tf, so several bodies never collide
        self.node_name = ns.rsplit("/", 1)[-1] or NAMESPACE.strip("/")
        self.wrench = f"{ns}/wrench"
        self.point_forces = f"{ns}/point_forces"
        self.clear_forces = f"{ns}/clear_forces/request"
        self.reset = f"{ns}/reset_simulation/request"
        self.topology = f"{ns}/surface/topology"
        self.points = f"{ns}/surface/points"
        self.mesh = f"{ns}/surface/mesh"
        self.marker = f"{ns}/surface/marker"
        self.domain_poses = f"{ns}/domain_poses"
        self.domain_transforms = f"{ns}/domain_transforms"
        self.contacts = f"{ns}/contacts"
        self.clock = "/clock"
        self.diagnostics = "/diagnostics"
        self.tf = "/tf"
        self.tf_prefix = f"{self.node_name}/"             # /tf child frames: <node name>/<domain name>

    def collider_pose(self, name):
        return f"{self.namespace}/colliders/{name}/pose"

    def collider_wrench(self, name):
        return f"{self.namespace}/colliders/{name}/wrench"

    def kind(self, topic):
        """The kind of a topic name (a key of TYPES), or None for a topic not of this node."""
        for k in ("wrench", "point_forces", "clear_forces", "reset", "topology", "points", "mesh", "marker",
                  "domain_poses", "domain_transforms", "contacts", "clock", "diagnostics", "tf"):
            if getattr(self, k) == topic:
                return k
        prefix = f"{self.namespace}/colliders/"
        if topic.startswith(prefix) and topic.count("/") == prefix.count("/") + 1:
            leaf = topic.rsplit("/", 1)[1]
            return {"pose": "collider_pose", "wrench": "collider_wrench"}.get(leaf)
        return None

    def collider_of(self, topic):
        return topic[len(f"{self.namespace}/colliders/"):].rsplit("/", 1)[0]

    def type_of(self, topic):
        return self.TYPES[self.kind(topic)]

    def qos_of(self, topic):
        depth, latched = self.QOS.get(self.kind(topic), (10, False))
        return qos_profile(depth, latched)

    def is_input(self, topic):
        return self.kind(topic) in self.INPUTS


class Out(NamedTuple):
    topic: str
    type_name: str
    data: bytes
    stamp_s: float


@dataclass
class OutputRates:
    """Publish rates in Hz of sim time (0: off), the node's defaults (node.py PARAMETERS)."""

    points: float = 30.0
    mesh: float = 1.0
    marker: float = 10.0
    pose: float = 90.0
    diagnostics: float = 1.0


def due(rate, dt, step, previous_step):
    """The node's rule: an output of `rate` is due after the step from previous_step to
    step when floor(k dt rate) changed (None: always, the state at start)."""
    if rate <= 0:
        return False
    if previous_step is None:
        return True
    tick = lambda k: math.floor(k * dt * rate + 1e-6)  # noqa: E731
    return tick(step) > tick(previous_step)


def domain_names(sim):
    """Domain (tf child frame) names, as the node names them."""
    n = len(sim.domain_poses())
    names = list(sim.model.domain_names())
    if len(names) != n:
        names = ["body"] if n == 1 else [f"domain_{i}" for i in range(n)]
    return names


def surface_domain(sim):
    """Domain index of each surface vertex (S,), in topology order."""
    ids = np.asarray(sim.surface_vertex_ids())
    return np.asarray(sim.model.vertex_domain)[ids]


def seconds_of(stamp):
    return convert.seconds(stamp)


# --------------------------------------------------------------------- canonical CDR
_BASIC = {"boolean": "?", "octet": "B", "char": "B", "uint8": "B", "int8": "b", "int16": "h",
          "uint16": "H", "int32": "i", "uint32": "I", "int64": "q", "uint64": "Q", "float": "f",
          "double": "d"}


class CanonicalCdr:
    """Little-endian CDR (XCDR1, rmw_fastrtps's layout) of an rclpy message, padding zeroed.

    rclpy.serialization.serialize_message leaves CDR padding bytes uninitialised (the same
    message serialises to different bytes), so recordings that replay compares byte for
    byte are encoded here: the same layout, with zeros in the padding. Decoders read both
    alike. `padding` lists the padding byte positions of the last encode (tests).
    """

    def __init__(self):
        self.buf = bytearray()
        self.padding = []

    def encode(self, msg):
        self.buf = bytearray(b"\x00\x01\x00\x00")
        self.padding = []
        self._struct(msg)
        return bytes(self.buf)

    def _align(self, n):
        pad = (-(len(self.buf) - 4)) % n
        if pad:
            self.padding.extend(range(len(self.buf), len(self.buf) + pad))
            self.buf.extend(b"\x00" * pad)

    def _basic(self, typename, value):
        fmt = _BASIC[typename]
        size = struct.calcsize(fmt)
        self._align(size)
        if typename in ("octet", "char") and isinstance(value, (bytes, str)):
            value = ord(value)
        self.buf.extend(struct.pack("<" + fmt, value))

    def _basic_block(self, typename, values):
        fmt = _BASIC[typename]
        n = len(values)
        if not n:
            return
        self._align(struct.calcsize(fmt))
        if typename in ("octet", "char") and isinstance(values, (bytes, bytearray)):
            self.buf.extend(values)
        elif typename in ("octet", "char") and len(values) and isinstance(values[0], (bytes, str)):
            self.buf.extend(bytes(ord(v) for v in values))
        else:
            self.buf.extend(np.asarray(values, dtype="<" + fmt if fmt != "?" else "?").tobytes())

    def _string(self, s):
        b = s.encode() + b"\x00"
        self._align(4)
        self.buf.extend(struct.pack("<I", len(b)))
        self.buf.extend(b)

    def _value(self, t, value):
        from rosidl_parser import definition as d
        if isinstance(t, d.BasicType):
            self._basic(t.typename, value)
        elif isinstance(t, d.AbstractString):
            self._string(value)
        elif isinstance(t, d.NamespacedType):
            self._struct(value)
        elif isinstance(t, (d.Array, d.AbstractSequence)):
            if not isinstance(t, d.Array):
                self._align(4)
                self.buf.extend(struct.pack("<I", len(value)))
            vt = t.value_type
            if isinstance(vt, d.BasicType):
                self._basic_block(vt.typename, value)
            else:
                for v in value:
                    self._value(vt, v)
        else:
            raise TypeError(f"cannot encode a field of type {t!r}")

    def _struct(self, msg):
        for slot, t in zip(msg.__slots__, msg.SLOT_TYPES):
            if slot == "_check_fields":
                continue
            self._value(t, getattr(msg, slot))


def cdr_bytes(msg):
    """Canonical CDR bytes of an rclpy message object (see CanonicalCdr); bytes pass through."""
    if isinstance(msg, (bytes, bytearray)):
        return bytes(msg)
    return CanonicalCdr().encode(msg)


# --------------------------------------------------------------------- /tf
def tf_message_bytes(transforms):
    """tf2_msgs/msg/TFMessage CDR bytes (tf2_msgs is not installable here).

    transforms: geometry_msgs/msg/TransformStamped objects (convert.domain_transforms).
    Little-endian CDR as rmw_fastrtps writes it; alignment counts from after the 4-byte
    encapsulation header, so each element is laid out in place (not concatenated).
    """
    out = bytearray(b"\x00\x01\x00\x00")

    def align(n):
        pad = (-(len(out) - 4)) % n
        out.extend(b"\x00" * pad)

    def string(s):
        b = s.encode() + b"\x00"
        align(4)
        out.extend(struct.pack("<I", len(b)))
        out.extend(b)

    align(4)
    out.extend(struct.pack("<I", len(transforms)))
    for tr in transforms:
        align(4)
        out.extend(struct.pack("<iI", tr.header.stamp.sec, tr.header.stamp.nanosec))
        string(tr.header.frame_id)
        string(tr.child_frame_id)
        t, q = tr.transform.translation, tr.transform.rotation
        align(8)
        out.extend(struct.pack("<7d", t.x, t.y, t.z, q.x, q.y, q.z, q.w))
    return bytes(out)


# --------------------------------------------------------------------- outputs
class SimOutputs:
    """The node's output messages of a Simulator's state, as CDR bytes (see module doc)."""

    def __init__(self, sim, topics=None, world_frame=WORLD_FRAME, rates=None):
        self.sim = sim
        self.topics = topics or Topics()
        self.frame = world_frame
        self.rates = rates or OutputRates()
        self.domain_names = domain_names(sim)
        self.surface_ids = np.asarray(sim.surface_vertex_ids())
        self.triangles = np.asarray(sim.surface_triangles())
        self.surface_domain = surface_domain(sim)
        self.colliders = list(sim.scene["colliders"])
        self._points = convert.SurfacePoints(self.surface_domain)
        self._mesh = convert.MeshEncoder(self.triangles)
        self._marker = convert.MarkerEncoder(self.triangles, self.surface_domain)

    def _out(self, topic, data, t):
        return Out(topic, self.topics.type_of(topic), cdr_bytes(data), t)

    def topology(self):
        rest = np.asarray(self.sim.rest_positions())[self.surface_ids]
        return [self._out(self.topics.topology, convert.topology_mesh_bytes(rest, self.triangles), 0.0)]

    def state(self, previous_step=None):
        """/clock and every output due after the step from previous_step (None: all).

        Raises FloatingPointError for a non-finite state (nothing of it is returned)."""
        sim, tp, r = self.sim, self.topics, self.rates
        t, k, dt = sim.time, sim.step_count, sim.dt
        out = [self._out(tp.clock, convert.clock(t), t)]
        surface = [n for n in ("points", "mesh", "marker") if due(getattr(r, n), dt, k, previous_step)]
        if surface:
            x = sim.surface_positions()
            _finite("surface positions", x, t)
            if "points" in surface:
                out.append(self._out(tp.points, self._points.message(t, self.frame, x), t))
            if "mesh" in surface:
                out.append(self._out(tp.mesh, self._mesh.encode(x), t))
            if "marker" in surface:
                out.append(self._out(tp.marker, self._marker.encode(t, self.frame, x), t))
        if due(r.pose, dt, k, previous_step):
            poses = np.asarray(sim.domain_poses())
            _finite("domain poses", poses, t)
            out.append(self._out(tp.domain_poses, convert.pose_array(t, self.frame, poses), t))
            transforms = convert.domain_transforms(t, self.frame, self.domain_names, poses)
            out.extend(self._out(tp.domain_transforms, msg, t) for msg in transforms)
            tf = convert.domain_transforms(t, self.frame, self.domain_names, poses, prefix=tp.tf_prefix)
            out.append(self._out(tp.tf, tf_message_bytes(tf), t))
            for c in self.colliders:
                w = sim.collider_wrench(c)
                _finite(f"wrench on collider {c!r}", w, t)
                out.append(self._out(tp.collider_wrench(c), convert.wrench_stamped(t, self.frame, w), t))
        contacts_of = getattr(sim, "contacts", None)
        if callable(contacts_of):
            contacts = np.asarray(contacts_of(), dtype=np.float64)
            if len(contacts):
                _finite("contacts", contacts, t)
                out.append(self._out(tp.contacts, convert.contacts_cloud(t, self.frame, contacts), t))
        return out

    def diagnostics_due(self, previous_step):
        return due(self.rates.diagnostics, self.sim.dt, self.sim.step_count, previous_step)

    def diagnostics(self, step_ms=(), wall_s=None, sim_s=None, inputs_applied=0, inputs_rejected=0):
        """/diagnostics of a window: step_ms of its steps, wall_s and sim_s it took."""
        sim = self.sim
        steps = np.asarray(step_ms, dtype=np.float64)
        energy = sim.energy()
        stats = sim.stats()
        values = {
            "state": "running",
            "sim_time": sim.time,
            "steps": sim.step_count,
            "physics_dt": sim.dt,
            "step_ms_median": float(np.median(steps)) if len(steps) else 0.0,
            "step_ms_max": float(steps.max()) if len(steps) else 0.0,
            "real_time_factor": (sim_s / wall_s) if wall_s and sim_s is not None else 0.0,
            "energy_total": energy["total"],
            "energy_kinetic": energy["kinetic"],
            "energy_elastic": energy["elastic"],
            "stability": stats.get("stability", "ok"),
            "dofs": stats.get("dofs", 0),
            "domains": len(self.domain_names),
            "surface_vertices": len(self.surface_ids),
            "inputs_applied": inputs_applied,
            "rejected_total": inputs_rejected,
        }
        msg = convert.diagnostics(sim.time, f"{self.topics.node_name}: simulation", f"scene:{sim.scene.name}", "ok", "running", values)
        return self._out(self.topics.diagnostics, msg, sim.time)


def _finite(what, a, t):
    if not np.all(np.isfinite(a)):
        raise FloatingPointError(f"non-finite {what} at t = {t:.6g} s")


def mask_timing(diagnostics_bytes):
    """/diagnostics bytes with the TIMING_KEYS values blanked (for run-vs-replay comparison)."""
    from diagnostic_msgs.msg import DiagnosticArray
    msg = deserialize_message(diagnostics_bytes, DiagnosticArray)
    for status in msg.status:
        for kv in status.values:
            if kv.key in TIMING_KEYS:
                kv.value = ""
    return cdr_bytes(msg)


# --------------------------------------------------------------------- inputs
def _stamp(t):
    return convert.stamp(t)


def event_messages(ev, topics=None, world_frame=WORLD_FRAME):
    """[(topic, message)] the node would receive for a scene timeline event (stamped at ev t)."""
    topics = topics or Topics()
    t = float(ev["t"])
    kind = ev["topic"]
    if kind == "wrench":
        w = list(ev.get("force", (0, 0, 0))) + list(ev.get("torque", (0, 0, 0)))
        return [(topics.wrench, convert.wrench_stamped(t, ev["frame_id"], w))]
    if kind == "point_force":
        rec = np.zeros(1, dtype=POINT_FORCE_DTYPE)
        for name, v in zip(("x", "y", "z"), ev["point"]):
            rec[name] = v
        for name, v in zip(("fx", "fy", "fz"), ev["force"]):
            rec[name] = v
        rec["duration"] = ev.get("duration", 0.0)
        return [(topics.point_forces, convert.cloud(t, world_frame, rec))]
    if kind == "collider_pose":
        msg = PoseStamped(header=convert.header(t, world_frame))
        p, o = msg.pose.position, msg.pose.orientation
        p.x, p.y, p.z = (float(v) for v in ev["position"])
        o.x, o.y, o.z, o.w = (float(v) for v in ev.get("orientation", (0, 0, 0, 1)))
        return [(topics.collider_pose(ev["name"]), msg)]
    if kind == "clear_forces":
        return [(topics.clear_forces, Header(stamp=_stamp(t), frame_id=""))]
    raise ValueError(f"unknown timeline topic {kind!r}")


_MSG_CLASS = {"wrench": WrenchStamped, "point_forces": PointCloud2, "clear_forces": Header,
              "collider_pose": PoseStamped, "reset": Header}


def input_stamp(topics, topic, msg):
    """Sim time (s) an input is stamped with (0: unstamped)."""
    stamp = msg.stamp if topics.kind(topic) in ("clear_forces", "reset") else msg.header.stamp
    return seconds_of(stamp)


def decode_input(topics, topic, data):
    """The message object of an input topic's CDR bytes."""
    return deserialize_message(data, _MSG_CLASS[topics.kind(topic)])


class InputApplier:
    """Applies input messages to a Simulator with the node's checks (mdss_ros.ros.validate).

    apply(topic, msg) -> short description; raises validate.InputRejected for an input the
    node would reject (the caller counts it and goes on, as the node does).
    on_collider_pose(name, position, orientation) hears applied collider poses (rerun).
    """

    def __init__(self, sim, topics=None, world_frame=WORLD_FRAME, limits=None, on_collider_pose=None):
        self.sim = sim
        self.topics = topics or Topics()
        self.world_frame = world_frame
        self.limits = limits or validate.Limits()
        self.handles = set(sim.scene["handles"])
        self.colliders = set(sim.scene["colliders"])
        self.on_collider_pose = on_collider_pose
        self.applied = 0
        self.rejected = 0

    def apply(self, topic, msg):
        kind = self.topics.kind(topic)
        try:
            desc = self._apply(kind, topic, msg)
        except validate.InputRejected:
            self.rejected += 1
            raise
        except (KeyError, ValueError) as err:
            self.rejected += 1
            raise validate.InputRejected("apply_error", f"{kind}: {err}") from err
        self.applied += 1
        return desc

    def _apply(self, kind, topic, msg):
        sim = self.sim
        if kind == "wrench":
            w = msg.wrench
            handle, f, tq = validate.wrench(msg.header.frame_id, (w.force.x, w.force.y, w.force.z),
                                            (w.torque.x, w.torque.y, w.torque.z), self.handles, self.limits)
            sim.set_wrench(handle, f, tq)
            return f"wrench on {handle}: force {f.tolist()} torque {tq.tolist()}"
        if kind == "point_forces":
            p, f, d = validate.point_forces(msg, self.world_frame, self.limits)
            for pi, fi, di in zip(p, f, d):
                sim.add_point_force(pi, fi, float(di))
            return f"{len(p)} point force(s)"
        if kind == "clear_forces":
            sim.clear_forces()
            return "clear_forces"
        if kind == "collider_pose":
            name = self.topics.collider_of(topic)
            if name not in self.colliders:
                raise validate.InputRejected("unknown_collider", f"the scene has no collider {name!r}")
            validate.frame(msg.header.frame_id, self.world_frame, f"colliders/{name}/pose")
            pp, o = msg.pose.position, msg.pose.orientation
            pos, quat = validate.pose((pp.x, pp.y, pp.z), (o.x, o.y, o.z, o.w), self.limits)
            sim.set_collider_pose(name, pos, quat)
            if self.on_collider_pose:
                self.on_collider_pose(name, pos, quat)
            return f"collider {name} at {pos.tolist()}"
        raise validate.InputRejected("apply_error", f"{topic} is not an input topic of {self.topics.namespace}")
