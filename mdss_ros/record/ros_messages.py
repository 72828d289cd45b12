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
    event_messages(event, topics)                   # [(topic, message)] of a timeline event
    cdr_bytes(msg)                                  # CDR bytes of a message object
    decode_input(topics, topic, data)               # an input topic's CDR bytes -> message

Messages are objects of rosbags' Jazzy typestore (convert.TYPESTORE); their CDR is
rosbags' (`cdr_bytes`): rmw_fastrtps's layout with the padding bytes zeroed, so equal
messages are equal bytes. An `Out` is (topic, type_name, data: CDR bytes, stamp_s).
Bytes, not message objects: the node publishes them as they are, the recorder stores
them as they are and replay compares them byte for byte.

Output times follow the node: step k publishes an output of rate r (Hz of sim time)
when floor(k dt r) changed; /clock goes out every step; rate 0 turns an output off.
/diagnostics runs at `diagnostics_rate` Hz of *sim* time here (the node uses wall time);
its timing values (TIMING_KEYS) differ from run to run, and its input counts
(INPUT_COUNT_PREFIXES) from a run to its replay; everything else is reproducible.

Inputs are decoded (decode_input), checked (mdss_ros.ros.validate) and applied by the one
driver the node, the run and the replay share (mdss_ros.ros.driver), from their bytes as
the node's raw subscriptions receive them: point forces therefore act in float32, as they
arrive on ~/point_forces.
A call of the ~/clear_forces service is not a message; it is recorded on
`~/clear_forces/request` as a std_msgs/msg/Header stamped with its sim time (a service
event type would not decode in mcap_ros2 or rosbags).
"""
import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from ..ros import convert

NAMESPACE = "/mdss"
WORLD_FRAME = "world"

#: /diagnostics values that measure wall time (differ between a run and its replay).
TIMING_KEYS = frozenset({"step_ms_median", "step_ms_max", "real_time_factor"})
#: /diagnostics values that count the input stream (inputs_*, rejected_*): a recording holds
#: only the inputs that were applied, so a replay cannot count what was rejected or pending.
INPUT_COUNT_PREFIXES = ("inputs_", "rejected_")

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
        "parameters": "rcl_interfaces/msg/ParameterEvent",
        "collider_pose": "geometry_msgs/msg/PoseStamped",
        "topology": "shape_msgs/msg/Mesh",
        "points": "sensor_msgs/msg/PointCloud2",
        "mesh": "shape_msgs/msg/Mesh",
        "marker": "visualization_msgs/msg/Marker",
        "domain_poses": "geometry_msgs/msg/PoseArray",
        "domain_transforms": "geometry_msgs/msg/TransformStamped",
        "contacts": "sensor_msgs/msg/PointCloud2",
        "collider_wrench": "geometry_msgs/msg/WrenchStamped",
        "collider_contacts": "sensor_msgs/msg/PointCloud2",
        "clock": "rosgraph_msgs/msg/Clock",
        "diagnostics": "diagnostic_msgs/msg/DiagnosticArray",
        "tf": "tf2_msgs/msg/TFMessage",
    }
    # (depth, latched) per kind, as node.py creates its publishers; tf as tf2_ros does.
    QOS = {"topology": (1, True), "clock": (1, True), "mesh": (2, False), "marker": (2, False),
           "tf": (100, False)}
    # reset: the ~/reset_simulation service call, recorded as a Header stamped with the sim
    # time it ended, so a replay resets where the run did. parameters: a runtime change of
    # the node's parameters that the run depends on (friction, output rates, wrench
    # timeout, input limits), recorded as the ParameterEvent rclpy would announce.
    INPUTS = ("wrench", "point_forces", "clear_forces", "collider_pose", "reset", "parameters")

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
        self.parameters = f"{ns}/parameter_events"
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
        self._kinds = {}                                  # topic -> kind, filled by kind()

    def collider_pose(self, name):
        return f"{self.namespace}/colliders/{name}/pose"

    def collider_wrench(self, name):
        return f"{self.namespace}/colliders/{name}/wrench"

    def collider_contacts(self, name):
        return f"{self.namespace}/colliders/{name}/contacts"

    def kind(self, topic):
        """The kind of a topic name (a key of TYPES), or None for a topic not of this node.
        Remembered per topic: a step's outputs ask it about 24 times (type and QoS)."""
        try:
            return self._kinds[topic]
        except KeyError:
            k = self._kinds[topic] = self._find_kind(topic)
            return k

    def _find_kind(self, topic):
        for k in ("wrench", "point_forces", "clear_forces", "reset", "parameters", "topology", "points", "mesh", "marker",
                  "domain_poses", "domain_transforms", "contacts", "clock", "diagnostics", "tf"):
            if getattr(self, k) == topic:
                return k
        prefix = f"{self.namespace}/colliders/"
        if topic.startswith(prefix) and topic.count("/") == prefix.count("/") + 1:
            leaf = topic.rsplit("/", 1)[1]
            return {"pose": "collider_pose", "wrench": "collider_wrench", "contacts": "collider_contacts"}.get(leaf)
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


# --------------------------------------------------------------------- CDR
def cdr_bytes(msg):
    """CDR bytes of a typestore message object (convert.TYPESTORE); bytes pass through.

    Little-endian, padding zeroed (rosbags' serialize_cdr), so the same message is always
    the same bytes, as replay's byte-for-byte comparison needs."""
    if isinstance(msg, (bytes, bytearray, memoryview)):
        return bytes(msg)
    type_name = getattr(msg, "__msgtype__", None)
    if type_name is None:
        raise TypeError(f"cannot serialise a {type(msg).__module__}.{type(msg).__name__}: messages are "
                        f"rosbags typestore objects (mdss_ros.ros.convert) or CDR bytes")
    return bytes(convert.TYPESTORE.serialize_cdr(msg, type_name, little_endian=True))


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
        self._points_bytes = convert.CloudEncoder(convert.SURFACE_POINT_DTYPE)
        self._contacts_bytes = convert.CloudEncoder(convert.CONTACT_DTYPE)
        self._mesh = convert.MeshEncoder(self.triangles)
        self._marker = convert.MarkerEncoder(self.triangles, self.surface_domain)
        self._poses = convert.PosesEncoder(self.domain_names, self.topics.tf_prefix)

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
                out.append(self._out(tp.points, self._points_bytes.encode(t, self.frame, self._points.fill(x)), t))
            if "mesh" in surface:
                out.append(self._out(tp.mesh, self._mesh.encode(x), t))
            if "marker" in surface:
                out.append(self._out(tp.marker, self._marker.encode(t, self.frame, x), t))
        contacts = None                  # (k, 10), read once a step for every cloud that needs it
        if due(r.pose, dt, k, previous_step):
            poses = np.asarray(sim.domain_poses())
            _finite("domain poses", poses, t)
            out.append(self._out(tp.domain_poses, self._poses.pose_array(t, self.frame, poses), t))
            out.extend(self._out(tp.domain_transforms, msg, t) for msg in self._poses.transforms(t, self.frame, poses))
            out.append(self._out(tp.tf, self._poses.tf(t, self.frame, poses), t))
            # Touch per collider (a tactile sensor's reading): its net wrench, and its own
            # contacts as a cloud in ~/contacts' layout, empty when it touches nothing.
            if self.colliders:
                wrenches = sim.collider_wrenches()
                names = sim.contacts(split=True)["collider"]
                contacts = np.asarray(sim.contacts(), dtype=np.float64)
                _finite("contacts", contacts, t)
            for c in self.colliders:
                w = wrenches[c]
                _finite(f"wrench on collider {c!r}", w, t)
                out.append(self._out(tp.collider_wrench(c), convert.wrench_stamped(t, self.frame, w), t))
                out.append(self._out(tp.collider_contacts(c), self._contacts_bytes.encode(
                    t, self.frame, convert.contact_records(contacts[names == c])), t))
        contacts_of = getattr(sim, "contacts", None)
        if contacts is None and callable(contacts_of):
            contacts = np.asarray(contacts_of(), dtype=np.float64)
            _finite("contacts", contacts, t)
        if contacts is not None and len(contacts):
            out.append(self._out(tp.contacts, self._contacts_bytes.encode(
                t, self.frame, convert.contact_records(contacts)), t))
        return out

    def diagnostics_due(self, previous_step):
        return due(self.rates.diagnostics, self.sim.dt, self.sim.step_count, previous_step)


def _finite(what, a, t):
    if not np.all(np.isfinite(a)):
        raise FloatingPointError(f"non-finite {what} at t = {t:.6g} s")


def mask_timing(diagnostics_bytes):
    """/diagnostics bytes with the TIMING_KEYS and input-count values blanked (for
    run-vs-replay comparison)."""
    msg = convert.decode(diagnostics_bytes, "diagnostic_msgs/msg/DiagnosticArray")
    for status in msg.status:
        for kv in status.values:
            if kv.key in TIMING_KEYS or kv.key.startswith(INPUT_COUNT_PREFIXES):
                kv.value = ""
    return cdr_bytes(msg)


# --------------------------------------------------------------------- inputs
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
        msg = convert.pose_stamped(t, world_frame, ev["position"], ev.get("orientation", (0, 0, 0, 1)))
        return [(topics.collider_pose(ev["name"]), msg)]
    if kind == "clear_forces":
        return [(topics.clear_forces, convert.header(t, ""))]
    raise ValueError(f"unknown timeline topic {kind!r}")


def input_stamp(topics, topic, msg):
    """Sim time (s) an input is stamped with (0: unstamped)."""
    kind = topics.kind(topic)
    stamp = msg.stamp if kind in ("clear_forces", "reset", "parameters") else msg.header.stamp
    return seconds_of(stamp)


def decode_input(topics, topic, data):
    """The message object (convert.TYPESTORE) of an input topic's CDR bytes.

    Raises KeyError for a topic that is not an input of `topics` (replay reports it);
    rosbags' errors for bytes that do not decode as the topic's type."""
    kind = topics.kind(topic)
    if kind not in topics.INPUTS:
        raise KeyError(f"{topic} is not an input topic of {topics.namespace or '/'}")
    return convert.decode(data, topics.TYPES[kind])
