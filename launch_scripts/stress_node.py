#!/usr/bin/env python3
"""Stress the mdss node's inputs: a fuzz of malformed and valid messages, and a soak of
several publishers at a high rate; each against a real node process.

    launch_scripts/stress_node.py fuzz [--scene soft_finger] [--messages 10000] [--seed 0]
                                       [--mcap DIR] [--json FILE] [--set KEY=VALUE ...]
    launch_scripts/stress_node.py soak [--scene cantilever] [--publishers 4] [--rate 1000]
                                       [--seconds 600] [--json FILE] [--set KEY=VALUE ...]

Processes (launch_testing.Launch: one private ROS_DOMAIN_ID, localhost-only DDS; logs in
--workdir, a new temporary folder by default):
- the node: `python -m mdss_ros.node --ros-args -p scene:=SCENE [-p scene_overrides:=[...]]`
  (--set KEY=VALUE, repeatable, become its scene_overrides);
- a watcher process: subscribes to ~/surface/points, ~/domain_poses, ~/domain_transforms,
  ~/contacts, ~/colliders/<c>/wrench, any other output of the node of those types it finds
  in the graph, and /diagnostics; checks that every float in them is finite, keeps the
  ~/domain_poses stamps and echoes each /diagnostics status of the node on its stdout
  (this process reads the counters from there);
- fuzz: one fuzzer process that publishes; soak: P publisher processes;
- this process: starts them, samples the node's VmRSS (/proc/<pid>/status) every second,
  waits for the final counters, stops the node with SIGINT, judges and reports.

fuzz. The fuzzer waits for the node's latched ~/surface/topology (the body's bounding box
places points and colliders) and for /clock >= 2.5 s, then sends --messages messages at
--rate per second in bursts of --burst, planned from --seed (each message from its own
generator seeded (seed, index), so a run is reproducible whatever the timing): ~/wrench
(frame_id a handle or garbage), ~/point_forces (PointCloud2 x y z fx fy fz [duration],
valid and broken layouts: offsets past point_step, point_step too small, missing fields,
wrong or unknown datatypes, field counts, duplicated fields, truncated or over-long data,
row_step too small, height or width 0, is_bigendian with and without big-endian data,
organized and padded clouds, more points than max_point_forces), ~/colliders/<c>/pose of
the scene's colliders and of unknown names (their publishers are created first and used
once the node subscribed, which it does when its diagnostics timer sees them), with
random, NaN, Inf and huge values, garbage frames, stamps 0, current, far past, negative,
far future. For every message the fuzzer predicts the node's verdict by running
mdss_ros.ros.validate on it (the functions the node calls) with the last /clock as the
sim time; stamps are chosen far from the limits (valid: -0.2..+0.5 s; past: <= -5 s;
future: >= +100 s), so the prediction is exact unless the simulation resets meanwhile.
Criteria: the node is alive at the end and exits 0 on SIGINT, no callback raised
(`callback failed` in its log); every message is counted: inputs_received == sent and
received == applied + rejected_total + pending + dropped + cleared (the last two 0 when
the node does not report them); rejected_<kind> == predicted for each kind (stamp kinds
are only compared when the simulation did not reset); no non-finite float in the
outputs (watcher), nor, with --mcap, in the node's recording (mcap + mcap_ros2).

soak. The node runs SCENE at real_time_factor 1 with the default output rates; P
publisher processes each send valid wrenches on ~/wrench at R Hz for S s (a schedule
on the monotonic clock; catch-up is capped at 50 ms worth, so a starved publisher sends
less and says so: `sent` is what it published), unstamped (applied at the next step).
Publisher 0 also sends one wrench in 100 stamped with the next sim time (/clock + dt) and
measures the wall time from publishing it to the /clock that reaches stamp + dt (the step
that applied it has ended), as bench_node.py latency does. Measured: node RSS (start at
the warm-up, default 10 s or S/4, end, growth), /diagnostics windows (real-time factor,
step_ms, inputs_pending, inputs_dropped), ~/domain_poses stamps against the output grid
(missed ticks), received vs sent, latency p50/p99/max. Criteria: alive and exit 0, RSS
growth < 5 %, median real-time factor >= 0.99, pending bounded (< 1 s worth of input),
no missed ~/domain_poses tick, received == sent and the counters balance, finite outputs.
Step time: /diagnostics gives per-second windows, so p50 is the median of the window
medians, max the largest window maximum, and the p99 column is the 99th percentile of the
window maxima (each at least its window's p99), not a per-step percentile.

Publishers use reliable KEEP_ALL QoS: a sample leaves a writer's history only once the
node's reader acknowledged it, and every publish call is checked, so `sent` messages
that the node does not count were lost inside the node's process (its DDS reader history
or later), not by the publisher.

--code DIR runs the node and the fuzzer's prediction from the mdss_ros package in DIR
instead of this checkout (e.g. the last commit: git archive HEAD mdss_ros msg_scenes |
tar -x -C DIR), to compare two versions of the input path under the same load.

Exit code 0 when every criterion passes, 1 otherwise; --json FILE writes the whole report.
"""
import argparse
import array
import json
import math
import os
import signal
import statistics
import sys
import tempfile
import threading
import time
from collections import Counter
from pathlib import Path

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
sys.path.insert(0, str(HERE))
sys.path.insert(0, str(REPO))

from launch_testing import Launch  # noqa: E402

THIS = Path(__file__).resolve()
NS = "/mdss"
DIAG_NAME = "mdss: simulation"
DIAG_PREFIX = "@@diag "
READY = r"\] \[mdss\]: ready:"
FLOAT32, FLOAT64 = 7, 8
NP_DTYPE = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}
START_SIM_TIME = 2.5          # fuzz: /clock before sending, so "far past" stamps exist
STAMP_KINDS = ("stamp_past", "stamp_future")
COUNTER_KEYS = ("inputs_received", "inputs_applied", "rejected_total", "inputs_pending", "inputs_dropped",
                "inputs_cleared")
NAN, INF = float("nan"), float("inf")


# ---------------------------------------------------------------------- shared helpers

def spin_in_background(node):
    """Spin node's callbacks on a daemon thread (the caller's loop publishes meanwhile);
    returns the function that stops it."""
    from rclpy.executors import SingleThreadedExecutor
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    running = [True]

    def spin():
        while running[0]:
            executor.spin_once(timeout_sec=0.02)

    spinner = threading.Thread(target=spin, daemon=True)
    spinner.start()

    def stop():
        running[0] = False
        spinner.join(2)
        executor.remove_node(node)
    return stop

def _pct(xs, q):
    xs = sorted(x for x in xs if x is not None and math.isfinite(x))
    if not xs:
        return float("nan")
    return xs[min(len(xs) - 1, int(round(q * (len(xs) - 1))))]


def _median(xs):
    xs = [x for x in xs if x is not None and math.isfinite(x)]
    return statistics.median(xs) if xs else float("nan")


def parse_sets(sets):
    """{dotted key: value} of --set KEY=VALUE items (values read as YAML, like the node)."""
    from mdss_ros.scene import read_yaml
    out = {}
    for item in sets:
        key, sep, text = item.partition("=")
        if not sep or not key.strip():
            raise ValueError(f"--set expects KEY=VALUE (e.g. model.modes=6), got {item!r}")
        out[key.strip()] = read_yaml(text)
    return out


def scene_info(scene, sets=()):
    """Handles, colliders and dt of the scene with its overrides (no model build)."""
    from mdss_ros.scene import load_scene
    s = load_scene(scene, parse_sets(sets) or None)
    return {"name": s.name, "handles": sorted(s["handles"]), "colliders": sorted(s["colliders"]),
            "dt": float(s.dt)}


def default_limits():
    from mdss_ros.ros.validate import Limits
    return dict(Limits().__dict__)


def cloud_nonfinite(msg):
    """Non-finite float32/float64 values in a PointCloud2 (rclpy or decoded MCAP message);
    -1 when its layout cannot hold its points (an output must never be like that)."""
    import numpy as np
    n = msg.width * msg.height
    if n == 0:
        return 0
    data = np.frombuffer(bytes(msg.data) if not isinstance(msg.data, (bytes, bytearray)) else msg.data, np.uint8)
    if msg.row_step < msg.width * msg.point_step or len(data) < msg.row_step * msg.height:
        return -1
    rows = data[:msg.row_step * msg.height].reshape(msg.height, msg.row_step)[:, :msg.width * msg.point_step]
    rows = rows.reshape(n, msg.point_step)
    order = ">" if msg.is_bigendian else "<"
    bad = 0
    for f in msg.fields:
        if f.datatype not in (FLOAT32, FLOAT64):
            continue
        size = 4 if f.datatype == FLOAT32 else 8
        for c in range(max(f.count, 1)):
            off = f.offset + c * size
            if off + size > msg.point_step:
                return -1
            col = np.ascontiguousarray(rows[:, off:off + size]).view(order + NP_DTYPE[f.datatype]).reshape(n)
            bad += int((~np.isfinite(col)).sum())
    return bad


def diag_nonfinite(values):
    """Keys of /diagnostics values (strings) that read as a non-finite number."""
    bad = []
    for k, v in values.items():
        try:
            x = float(v)
        except (TypeError, ValueError):
            continue
        if not math.isfinite(x):
            bad.append(k)
    return bad


# ---------------------------------------------------------------------- watcher process
def watcher_main(cfg, out):
    """Subscribe to the node's outputs, check finiteness, echo /diagnostics; until stdin
    closes or SIGINT/SIGTERM, then write the summary to `out`."""
    import numpy as np
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
    from rclpy.signals import SignalHandlerOptions
    from diagnostic_msgs.msg import DiagnosticArray
    from geometry_msgs.msg import PoseArray, TransformStamped, WrenchStamped
    from sensor_msgs.msg import PointCloud2

    stop = threading.Event()
    for s in (signal.SIGINT, signal.SIGTERM):
        signal.signal(s, lambda *a: stop.set())
    rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
    node = rclpy.create_node(f"mdss_stress_watcher_{os.getpid()}")
    qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1000, reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.VOLATILE)
    counts, bad_msgs, bad_values = Counter(), Counter(), Counter()
    examples, pose_ns, diags = [], [], []

    def note(topic, n_bad, what, stamp=None):
        counts[topic] += 1
        if n_bad:
            bad_msgs[topic] += 1
            bad_values[topic] += max(n_bad, 1)
            if len(examples) < 20:
                examples.append({"topic": topic, "what": what, "bad": n_bad, "stamp": stamp,
                                 "wall": time.time()})

    def t_of(h):
        return h.stamp.sec + 1e-9 * h.stamp.nanosec

    def on_cloud(topic, msg):
        n = cloud_nonfinite(msg)
        note(topic, n, "non-finite floats" if n > 0 else "broken layout", t_of(msg.header))

    def on_poses(msg):
        vals = [v for p in msg.poses for v in (p.position.x, p.position.y, p.position.z, p.orientation.x,
                                                p.orientation.y, p.orientation.z, p.orientation.w)]
        note(f"{NS}/domain_poses", int((~np.isfinite(vals)).sum()) if vals else 0, "non-finite pose",
             t_of(msg.header))
        pose_ns.append(msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec)

    def on_transform(msg):
        t, r = msg.transform.translation, msg.transform.rotation
        vals = (t.x, t.y, t.z, r.x, r.y, r.z, r.w)
        note(f"{NS}/domain_transforms", sum(not math.isfinite(v) for v in vals), "non-finite transform",
             t_of(msg.header))

    def on_wrench(topic, msg):
        f, m = msg.wrench.force, msg.wrench.torque
        vals = (f.x, f.y, f.z, m.x, m.y, m.z)
        note(topic, sum(not math.isfinite(v) for v in vals), "non-finite wrench", t_of(msg.header))

    def on_diag(msg):
        for st in msg.status:
            if st.name != DIAG_NAME:
                continue
            values = {kv.key: kv.value for kv in st.values}
            bad = diag_nonfinite(values)
            note("/diagnostics", len(bad), "non-finite " + ",".join(bad))
            rec = dict(values, _wall=time.time(), _level=int.from_bytes(st.level, "little")
                       if isinstance(st.level, bytes) else int(st.level), _message=st.message)
            diags.append(rec)
            sys.stdout.write(DIAG_PREFIX + json.dumps(rec) + "\n")
            sys.stdout.flush()

    handlers = {"sensor_msgs/msg/PointCloud2": (PointCloud2, lambda t: (lambda m: on_cloud(t, m))),
                "geometry_msgs/msg/WrenchStamped": (WrenchStamped, lambda t: (lambda m: on_wrench(t, m))),
                "geometry_msgs/msg/TransformStamped": (TransformStamped, lambda t: on_transform),
                "geometry_msgs/msg/PoseArray": (PoseArray, lambda t: on_poses if t == f"{NS}/domain_poses"
                                                else (lambda m: on_pose_array(t, m)))}
    inputs = {f"{NS}/wrench", f"{NS}/point_forces"}
    subs = {}

    def on_pose_array(topic, msg):
        vals = [v for p in msg.poses for v in (p.position.x, p.position.y, p.position.z, p.orientation.x,
                                                p.orientation.y, p.orientation.z, p.orientation.w)]
        note(topic, int((~np.isfinite(vals)).sum()) if vals else 0, "non-finite pose", t_of(msg.header))

    def ensure(topic, type_name):
        if topic in subs or type_name not in handlers:
            return
        cls, make = handlers[type_name]
        subs[topic] = node.create_subscription(cls, topic, make(topic), qos)

    for topic, type_name in ((f"{NS}/surface/points", "sensor_msgs/msg/PointCloud2"),
                             (f"{NS}/contacts", "sensor_msgs/msg/PointCloud2"),
                             (f"{NS}/domain_poses", "geometry_msgs/msg/PoseArray"),
                             (f"{NS}/domain_transforms", "geometry_msgs/msg/TransformStamped")):
        ensure(topic, type_name)
    for c in cfg.get("colliders", []):
        ensure(f"{NS}/colliders/{c}/wrench", "geometry_msgs/msg/WrenchStamped")
    subs["/diagnostics"] = node.create_subscription(DiagnosticArray, "/diagnostics", on_diag, qos)

    def discover():
        """Subscribe to every other output of the node of a type checked here (new outputs too)."""
        for topic, types in node.get_topic_names_and_types():
            if topic.startswith(NS + "/") and topic not in inputs and not topic.endswith("/pose"):
                for t in types:
                    ensure(topic, t)

    def read_stdin():
        for _ in sys.stdin:
            pass
        stop.set()

    threading.Thread(target=read_stdin, daemon=True).start()
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    deadline = time.monotonic() + 60
    while node.count_publishers(f"{NS}/domain_poses") == 0 and time.monotonic() < deadline and not stop.is_set():
        executor.spin_once(timeout_sec=0.05)
    discover()
    print("watcher ready", flush=True)
    next_discovery = time.monotonic() + 1.0
    while not stop.is_set():
        executor.spin_once(timeout_sec=0.1)
        if time.monotonic() >= next_discovery:
            discover()
            next_discovery = time.monotonic() + 1.0
    # take what is already delivered
    t_end = time.monotonic() + 0.5
    while time.monotonic() < t_end:
        executor.spin_once(timeout_sec=0.05)
    summary = {"counts": dict(counts), "nonfinite_messages": dict(bad_msgs), "nonfinite_values": dict(bad_values),
               "examples": examples, "pose_stamps_ns": pose_ns, "diagnostics": len(diags), "topics": sorted(subs)}
    Path(out).write_text(json.dumps(summary))
    executor.remove_node(node)
    node.destroy_node()
    rclpy.try_shutdown()
    return 0


# ---------------------------------------------------------------------- fuzz: message generator
# Weights of the categories of each input topic (relative).
WRENCH_CATS = {"valid": 30, "valid_large": 2, "release": 4, "unknown_handle": 8, "non_finite": 8,
               "magnitude": 7, "stamp_past": 4, "stamp_past_tiny": 2, "stamp_negative": 2, "stamp_future": 4,
               "stamp_max": 1, "garbage": 12}
CLOUD_CATS = {"valid": 24, "valid_duration": 6, "valid_organized": 2, "valid_row_padding": 2,
              "valid_extra_fields": 2, "valid_bigendian": 2, "held": 0.3, "at_limit": 0.3,
              "bigendian_mismatch": 2, "oversized": 3, "offset_past_step": 3, "step_too_small": 3,
              "missing_field": 3, "wrong_datatype": 3, "unknown_datatype": 1, "field_count": 1,
              "duplicate_field": 1, "duration_float64": 1, "truncated": 3, "data_too_long": 1,
              "row_step_small": 1, "height_zero_with_data": 1, "height_zero_empty": 1, "width_zero_empty": 1,
              "non_finite": 4, "magnitude_force": 3, "magnitude_position": 3, "bad_frame": 4,
              "stamp_past": 2, "stamp_negative": 1, "stamp_future": 2, "garbage": 8}
POSE_CATS = {"valid": 30, "valid_touching": 4, "valid_far": 2, "valid_unnormalised": 3, "inside": 1,
             "non_finite": 8, "magnitude": 5, "bad_quaternion": 6, "bad_frame": 6, "stamp_past": 3,
             "stamp_negative": 1, "stamp_future": 3, "garbage": 10}
GHOST_CATS = {"valid": 6, "garbage": 4}
GROUPS = {"wrench": 0.35, "point_forces": 0.30, "collider_pose": 0.25, "unknown_collider": 0.10}
GHOST_NAMES = ("ghost", "Probe", "probe_2", "tip")
CLOUD_MUTATIONS = ("offset_past_step", "step_too_small", "missing_field", "wrong_datatype", "unknown_datatype",
                   "field_count", "duplicate_field", "truncated", "data_too_long", "row_step_small",
                   "bigendian_mismatch", "non_finite", "magnitude_force", "magnitude_position", "bad_frame",
                   "height_zero_with_data", "random_bytes")


def make_plan(n, seed, has_colliders, has_ghosts):
    """[(group, category)] of n messages, deterministic from seed."""
    import numpy as np
    rng = np.random.default_rng([seed, 0x5eed])
    groups = {g: w for g, w in GROUPS.items()
              if (g != "collider_pose" or has_colliders) and (g != "unknown_collider" or has_ghosts)}
    names, w = list(groups), np.array(list(groups.values()), float)
    cats = {"wrench": WRENCH_CATS, "point_forces": CLOUD_CATS, "collider_pose": POSE_CATS,
            "unknown_collider": GHOST_CATS}
    out = []
    for g in rng.choice(len(names), size=n, p=w / w.sum()):
        c = cats[names[g]]
        cw = np.array(list(c.values()), float)
        out.append((names[g], list(c)[rng.choice(len(c), p=cw / cw.sum())]))
    return out


class Generator:
    """Builds one fuzz message of a (group, category) and predicts the node's verdict."""

    def __init__(self, cfg, bbox):
        import numpy as np
        from mdss_ros.ros import validate
        self.np, self.validate = np, validate
        self.handles = list(cfg["handles"])
        self.colliders = list(cfg["colliders"])
        self.ghosts = list(cfg.get("ghosts", []))
        self.world = cfg.get("world_frame", "world")
        self.limits = validate.Limits(**cfg["limits"])
        lo, hi = np.asarray(bbox[0], float), np.asarray(bbox[1], float)
        self.lo, self.hi = lo, hi
        self.size = np.maximum(hi - lo, 1e-3)

    # -- random pieces
    def direction(self, rng):
        v = rng.normal(size=3)
        return v / max(float(self.np.linalg.norm(v)), 1e-12)

    def wild(self, rng):
        r = rng.random()
        if r < 0.25:
            return float(rng.normal() * 10 ** rng.uniform(-3, 2))
        if r < 0.35:
            return float(rng.choice([0.0, -0.0, 5e-324, -5e-324, 1.7976931348623157e308, -1.7976931348623157e308]))
        if r < 0.50:
            return float(rng.choice([NAN, INF, -INF]))
        if r < 0.70:
            return float(rng.choice([-1.0, 1.0]) * 10 ** rng.uniform(3, 307.9))
        return float(rng.uniform(-10, 10))

    def garbage_string(self, rng, avoid):
        pool = ["", "world", "map", "base_link", "odom", " ", "WORLD", "world ", "/world", "tip", "top", "probe",
                "wörld✓", "名前", "../etc/passwd", "%s%s%n", "a" * 5000, "\t\n"]
        pool += [h.upper() for h in self.handles] + [" " + h for h in self.handles] + ["/" + h for h in self.handles]
        for _ in range(50):
            if rng.random() < 0.3:
                n = int(rng.integers(1, 40))
                s = "".join(chr(int(c)) for c in rng.integers(33, 127, size=n))
            else:
                s = pool[int(rng.integers(len(pool)))]
            if s not in avoid:
                return s
        return "no_such_frame_xyz"

    def stamp(self, rng, kind, clock):
        """(sec, nanosec) of a stamp kind, relative to the sim time `clock`."""
        if kind == "zero":
            return 0, 0
        if kind == "now":
            t = max(clock + rng.uniform(-0.2, 0.5), 1e-3)
        elif kind == "past":
            if clock <= 6.0:
                return self.stamp(rng, "negative", clock)
            t = max(clock - rng.uniform(5.0, clock), 1e-6)
        elif kind == "past_tiny":
            if clock <= 2.0:
                return self.stamp(rng, "negative", clock)
            return 0, int(rng.integers(1, 1000))
        elif kind == "negative":
            return -int(rng.integers(1, 2 ** 31)), int(rng.integers(0, 10 ** 9))
        elif kind == "future":
            t = clock + 10 ** rng.uniform(2, 8)
        elif kind == "max":
            return 2 ** 31 - 1, 999_999_999
        else:
            raise ValueError(kind)
        ns = int(round(t * 1e9))
        return ns // 1_000_000_000, ns % 1_000_000_000

    def stamp_kind(self, rng, cat):
        return {"stamp_past": "past", "stamp_past_tiny": "past_tiny", "stamp_negative": "negative",
                "stamp_future": "future", "stamp_max": "max"}.get(cat) or \
            (str(rng.choice(["zero", "now", "past", "past_tiny", "negative", "future", "max"]))
             if cat == "garbage" else str(rng.choice(["zero", "now"])))

    def verdict(self, check, stamp, clock):
        """'applied', a rejection kind, or 'error:<Exception>' (the node would not catch it)."""
        v = self.validate
        try:
            check()
            v.due_time(stamp[0] + 1e-9 * stamp[1], clock, self.limits)
            return "applied"
        except v.InputRejected as err:
            return err.kind
        except Exception as err:  # noqa: BLE001 - a finding: the node's checks raise something else
            return f"error:{type(err).__name__}"

    # -- ~/wrench
    def wrench(self, rng, cat, clock):
        from geometry_msgs.msg import WrenchStamped
        np = self.np
        handle = self.handles[int(rng.integers(len(self.handles)))] if self.handles else "no_handle"
        frame = handle
        force = self.direction(rng) * 10 ** rng.uniform(-3, math.log10(20.0))
        torque = self.direction(rng) * 10 ** rng.uniform(-4, -1)
        L = self.limits
        if cat == "valid_large":
            force = self.direction(rng) * 10 ** rng.uniform(3, math.log10(0.99 * L.max_force))
            if rng.random() < 0.5:
                torque = self.direction(rng) * 10 ** rng.uniform(1, math.log10(0.99 * L.max_torque))
        elif cat == "release":
            force, torque = np.zeros(3), np.zeros(3)
        elif cat == "unknown_handle":
            frame = self.garbage_string(rng, set(self.handles))
        elif cat == "non_finite":
            v = np.concatenate([force, torque])
            v[int(rng.integers(6))] = float(rng.choice([NAN, INF, -INF]))
            force, torque = v[:3], v[3:]
        elif cat == "magnitude":
            if rng.random() < 0.6:
                force = self.direction(rng) * 10 ** rng.uniform(math.log10(L.max_force) + 0.01, 307.9)
            else:
                torque = self.direction(rng) * 10 ** rng.uniform(math.log10(L.max_torque) + 0.01, 307.9)
        elif cat == "garbage":
            if rng.random() < 0.5:
                frame = self.garbage_string(rng, ())
            force = np.array([self.wild(rng) for _ in range(3)])
            torque = np.array([self.wild(rng) for _ in range(3)])
        stamp = self.stamp(rng, self.stamp_kind(rng, cat), clock)
        msg = WrenchStamped()
        msg.header.frame_id = frame
        msg.header.stamp.sec, msg.header.stamp.nanosec = stamp
        for obj, v in ((msg.wrench.force, force), (msg.wrench.torque, torque)):
            obj.x, obj.y, obj.z = (float(a) for a in v)
        w = msg.wrench
        verdict = self.verdict(lambda: self.validate.wrench(
            msg.header.frame_id, (w.force.x, w.force.y, w.force.z), (w.torque.x, w.torque.y, w.torque.z),
            set(self.handles), self.limits), stamp, clock)
        return "wrench", msg, verdict

    # -- ~/point_forces
    def near_points(self, rng, n):
        lo = self.lo - 0.1 * self.size
        return lo + rng.random((n, 3)) * 1.2 * self.size

    def cloud(self, rng, cat, clock):
        np = self.np
        L = self.limits
        n = int(rng.integers(1, 21))
        if cat == "at_limit":
            n = int(L.max_point_forces)
        elif cat == "oversized":
            n = int(L.max_point_forces) + int(rng.integers(1, 2 * L.max_point_forces))
        duration = cat in ("valid_duration", "held", "duration_float64") or rng.random() < 0.3
        if cat == "held":
            n = int(rng.integers(1, 4))
        cols = {}
        p = self.near_points(rng, n)
        f = np.stack([self.direction(rng) for _ in range(n)]) * 10 ** rng.uniform(-3, 1, size=(n, 1))
        cols.update(x=p[:, 0], y=p[:, 1], z=p[:, 2], fx=f[:, 0], fy=f[:, 1], fz=f[:, 2])
        names = ["x", "y", "z", "fx", "fy", "fz"]
        if duration:
            names.append("duration")
            d = np.where(rng.random(n) < 0.5, 0.0, rng.uniform(0, 0.1, n))
            if cat == "held":
                d = np.full(n, -1.0) if rng.random() < 0.7 else np.full(n, 1e30)
            cols["duration"] = d
        # layout: [name, offset, datatype, count]
        fields = [[nm, 4 * i, FLOAT32, 1] for i, nm in enumerate(names)]
        lay = {"fields": fields, "point_step": 4 * len(names), "height": 1, "width": n, "pad": 0,
               "flag_be": False, "data_be": False, "frame": str(rng.choice(["", self.world])), "cut": 0,
               "extra": b"", "empty": False, "random_bytes": False}
        muts = [cat]
        if cat == "garbage":
            k = int(rng.integers(1, 4))
            muts = [str(m) for m in rng.choice(CLOUD_MUTATIONS, size=k, replace=False)]
        for m in muts:
            self._mutate_cloud(rng, m, lay, cols, n)
        stamp_cat = cat if cat.startswith("stamp_") else ("garbage" if cat == "garbage" else "")
        stamp = self.stamp(rng, self.stamp_kind(rng, stamp_cat), clock)
        msg = self._encode_cloud(rng, lay, cols, stamp)
        verdict = self.verdict(lambda: self.validate.point_forces(msg, self.world, self.limits), stamp, clock)
        return "point_forces", msg, verdict

    def _mutate_cloud(self, rng, m, lay, cols, n):
        np = self.np
        fields = lay["fields"]
        L = self.limits
        i = int(rng.integers(len(fields)))
        if m == "valid_organized":
            h = int(rng.integers(2, 5))
            w = int(rng.integers(1, 6))
            lay["height"], lay["width"] = h, w
            p = self.near_points(rng, h * w)
            fr = np.stack([self.direction(rng) for _ in range(h * w)])
            for j, k in enumerate("xyz"):
                cols[k] = p[:, j]
                cols["f" + k] = fr[:, j]
            if "duration" in cols:
                cols["duration"] = np.zeros(h * w)
        elif m == "valid_row_padding":
            lay["pad"] = int(rng.integers(1, 17))
        elif m == "valid_extra_fields":
            step = lay["point_step"]
            fields.append(["intensity", step, FLOAT32, 1])
            fields.append(["ring", step + 4, 4, 1])          # UINT16
            fields.append(["t", step + 8, FLOAT64, 1])
            lay["point_step"] = step + 16
            cols["intensity"] = rng.random(n)
            cols["ring"] = rng.integers(0, 64, n).astype(float)
            cols["t"] = rng.random(n)
            order = rng.permutation(len(fields))
            lay["fields"] = [fields[j] for j in order]
        elif m == "valid_bigendian":
            lay["flag_be"] = lay["data_be"] = True
        elif m == "bigendian_mismatch":
            lay["flag_be"], lay["data_be"] = True, False
        elif m == "offset_past_step":
            fields[i][1] = lay["point_step"] - int(rng.integers(0, 4)) + int(rng.integers(0, 2)) * int(rng.integers(0, 100))
        elif m == "step_too_small":
            need = max(f[1] + 4 * max(f[3], 1) for f in fields)
            lay["point_step"] = int(rng.integers(0, need))
        elif m == "missing_field":
            req = [j for j, f in enumerate(fields) if f[0] in ("x", "y", "z", "fx", "fy", "fz")]
            del fields[int(rng.choice(req))]
        elif m == "wrong_datatype":
            req = [j for j, f in enumerate(fields) if f[0] in ("x", "y", "z", "fx", "fy", "fz")]
            fields[int(rng.choice(req))][2] = int(rng.choice([1, 2, 3, 4, 5, 6, 8]))
        elif m == "unknown_datatype":
            fields[i][2] = int(rng.choice([0, 9, 17, 255]))
        elif m == "field_count":
            fields[i][3] = int(rng.choice([0, 2, 3]))
        elif m == "duplicate_field":
            fields.append(list(fields[i]))
        elif m == "duration_float64":
            for f in fields:
                if f[0] == "duration":
                    f[2] = FLOAT64
        elif m == "truncated":
            lay["cut"] = int(rng.integers(1, 4 * len(fields) * max(n, 1) + 1))
        elif m == "data_too_long":
            lay["extra"] = rng.bytes(int(rng.integers(1, 65)))
        elif m == "row_step_small":
            lay["pad"] = -int(rng.integers(1, lay["point_step"] * lay["width"] + 1))
        elif m == "height_zero_with_data":
            lay["height"] = 0
        elif m == "height_zero_empty":
            lay["height"], lay["empty"] = 0, True
        elif m == "width_zero_empty":
            lay["width"], lay["empty"] = 0, True
        elif m == "non_finite":
            k = str(rng.choice([c for c in ("x", "y", "z", "fx", "fy", "fz", "duration") if c in cols]))
            cols[k] = np.array(cols[k], float)
            cols[k][int(rng.integers(len(cols[k])))] = float(rng.choice([NAN, INF, -INF]))
        elif m == "magnitude_force":
            j = int(rng.integers(len(cols["fx"])))
            v = self.direction(rng) * 10 ** rng.uniform(math.log10(L.max_force) + 0.01, 37.5)
            for a, k in enumerate(("fx", "fy", "fz")):
                cols[k] = np.array(cols[k], float)
                cols[k][j] = v[a]
        elif m == "magnitude_position":
            j = int(rng.integers(len(cols["x"])))
            v = self.direction(rng) * 10 ** rng.uniform(math.log10(L.max_position) + 0.01, 37.5)
            for a, k in enumerate(("x", "y", "z")):
                cols[k] = np.array(cols[k], float)
                cols[k][j] = v[a]
        elif m == "bad_frame":
            lay["frame"] = self.garbage_string(rng, {"", self.world})
        elif m == "random_bytes":
            lay["random_bytes"] = True

    def _encode_cloud(self, rng, lay, cols, stamp):
        from sensor_msgs.msg import PointCloud2, PointField
        np = self.np
        h, w, step = lay["height"], lay["width"], max(int(lay["point_step"]), 0)
        row_step = max(w * step + lay["pad"], 0)
        n = h * w
        buf = np.zeros((h, row_step), np.uint8)
        order = ">" if lay["data_be"] else "<"
        if n and step and row_step >= w * step:
            pts = buf[:, :w * step].reshape(h, w, step)
            for name, off, dt, count in lay["fields"]:
                if dt not in NP_DTYPE or name not in cols:
                    continue
                size = int(NP_DTYPE[dt][1:])
                if off + size > step:
                    continue
                vals = np.asarray(cols[name], float).reshape(-1)
                if len(vals) != n:
                    vals = np.resize(vals, n)
                if NP_DTYPE[dt][0] in "iu":
                    vals = np.nan_to_num(vals, nan=0, posinf=0, neginf=0).clip(-100, 100)
                    if NP_DTYPE[dt][0] == "u":
                        vals = np.abs(vals)
                with np.errstate(over="ignore", invalid="ignore"):
                    enc = vals.astype(order + NP_DTYPE[dt])
                pts[:, :, off:off + size] = enc.view(np.uint8).reshape(h, w, size)
        data = buf.tobytes()
        if lay["height"] == 0 and not lay["empty"]:
            data = np.zeros((max(1, w), max(step, 1)), np.uint8).tobytes()   # points' bytes with height 0
        if lay["random_bytes"]:
            data = rng.bytes(len(data))
        if lay["cut"]:
            data = data[:max(len(data) - lay["cut"], 0)]
        data += lay["extra"]
        if lay["empty"]:
            data = b""
        msg = PointCloud2()
        msg.header.frame_id = lay["frame"]
        msg.header.stamp.sec, msg.header.stamp.nanosec = stamp
        msg.height, msg.width = h, w
        msg.fields = [PointField(name=nm, offset=max(int(off), 0), datatype=int(dt), count=int(c))
                      for nm, off, dt, c in lay["fields"]]
        msg.is_bigendian = bool(lay["flag_be"])
        msg.point_step, msg.row_step = step, row_step
        msg.data = array.array("B", data)
        msg.is_dense = True
        return msg

    # -- ~/colliders/<name>/pose
    def pose(self, rng, cat, clock, name, known=True):
        from geometry_msgs.msg import PoseStamped
        np = self.np
        L = self.limits
        lo, hi, size = self.lo, self.hi, self.size
        xy = lo[:2] - 0.1 * size[:2] + rng.random(2) * 1.2 * size[:2]
        pos = np.array([xy[0], xy[1], hi[2] + rng.uniform(0.3, 1.0) * size[2]])
        q = rng.normal(size=4)
        q /= max(float(np.linalg.norm(q)), 1e-12)
        frame = str(rng.choice(["", self.world]))
        if cat == "valid_touching":
            pos[2] = hi[2] + rng.uniform(0.0, 0.3) * size[2]
        elif cat == "valid_far":
            pos = self.direction(rng) * rng.uniform(1.0, 0.99 * L.max_position)
        elif cat == "valid_unnormalised":
            q *= rng.uniform(0.6, 1.9)
        elif cat == "inside":
            pos = 0.5 * (lo + hi)
        elif cat == "non_finite":
            v = np.concatenate([pos, q])
            v[int(rng.integers(7))] = float(rng.choice([NAN, INF, -INF]))
            pos, q = v[:3], v[3:]
        elif cat == "magnitude":
            pos = self.direction(rng) * 10 ** rng.uniform(math.log10(L.max_position) + 0.01, 307.9)
        elif cat == "bad_quaternion":
            r = rng.random()
            q = np.zeros(4) if r < 0.3 else q * (rng.uniform(0, 0.49) if r < 0.65 else 10 ** rng.uniform(0.31, 200))
        elif cat == "bad_frame":
            frame = self.garbage_string(rng, {"", self.world})
        elif cat == "garbage":
            pos = np.array([self.wild(rng) for _ in range(3)])
            q = np.array([self.wild(rng) for _ in range(4)])
            if rng.random() < 0.4:
                frame = self.garbage_string(rng, ())
        stamp = self.stamp(rng, self.stamp_kind(rng, cat), clock)
        msg = PoseStamped()
        msg.header.frame_id = frame
        msg.header.stamp.sec, msg.header.stamp.nanosec = stamp
        msg.pose.position.x, msg.pose.position.y, msg.pose.position.z = (float(a) for a in pos)
        o = msg.pose.orientation
        o.x, o.y, o.z, o.w = (float(a) for a in q)
        topic = f"collider:{name}" if known else f"ghost:{name}"
        if not known:
            return topic, msg, "unknown_collider"
        pp = msg.pose.position

        def check():
            self.validate.frame(msg.header.frame_id, self.world, f"colliders/{name}/pose")
            self.validate.pose((pp.x, pp.y, pp.z), (o.x, o.y, o.z, o.w), self.limits)
        return topic, msg, self.verdict(check, stamp, clock)

    def build(self, group, cat, rng, clock):
        if group == "wrench":
            return self.wrench(rng, cat, clock)
        if group == "point_forces":
            return self.cloud(rng, cat, clock)
        if group == "collider_pose":
            return self.pose(rng, cat, clock, self.colliders[int(rng.integers(len(self.colliders)))])
        return self.pose(rng, cat, clock, self.ghosts[int(rng.integers(len(self.ghosts)))], known=False)


# ---------------------------------------------------------------------- fuzz: publisher process
def fuzz_client_main(cfg, out):
    import warnings
    warnings.simplefilter("ignore", RuntimeWarning)      # overflow in norms of the huge values sent
    t_proc = time.monotonic()
    import numpy as np
    import rclpy
    from rclpy.duration import Duration
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
    from rclpy.signals import SignalHandlerOptions
    from geometry_msgs.msg import PoseStamped, WrenchStamped
    from rosgraph_msgs.msg import Clock
    from sensor_msgs.msg import PointCloud2
    from shape_msgs.msg import Mesh

    rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
    node = rclpy.create_node(f"mdss_stress_fuzzer_{os.getpid()}")
    # KEEP_ALL: the writer never overwrites a sample the node has not acknowledged (a full
    # history makes publish block, then fail: counted), so a loss is the node's
    pub_qos = QoSProfile(history=HistoryPolicy.KEEP_ALL, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.VOLATILE)
    latched = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL)
    state = {"clock": None, "resets": 0, "topology": None}

    def on_clock(msg):
        t = msg.clock.sec + 1e-9 * msg.clock.nanosec
        if state["clock"] is not None and t < state["clock"] - 1e-9:
            state["resets"] += 1
        state["clock"] = t

    def on_topology(msg):
        if msg.vertices:
            v = np.array([[p.x, p.y, p.z] for p in msg.vertices])
            state["topology"] = (v.min(axis=0).tolist(), v.max(axis=0).tolist())

    node.create_subscription(Clock, "/clock", on_clock, latched)
    node.create_subscription(Mesh, f"{NS}/surface/topology", on_topology, latched)
    ghosts = list(cfg["ghosts"])
    pubs = {"wrench": node.create_publisher(WrenchStamped, f"{NS}/wrench", pub_qos),
            "point_forces": node.create_publisher(PointCloud2, f"{NS}/point_forces", pub_qos)}
    for c in cfg["colliders"]:
        pubs[f"collider:{c}"] = node.create_publisher(PoseStamped, f"{NS}/colliders/{c}/pose", pub_qos)
    for g in ghosts:       # first: the node subscribes only when its diagnostics timer sees them
        pubs[f"ghost:{g}"] = node.create_publisher(PoseStamped, f"{NS}/colliders/{g}/pose", pub_qos)
    stop_spinning = spin_in_background(node)

    def wait(cond, timeout, what):
        deadline = time.monotonic() + timeout
        while not cond():
            if time.monotonic() > deadline:
                raise TimeoutError(f"fuzzer: {what} within {timeout} s")
            time.sleep(0.02)

    known = [k for k in pubs if not k.startswith("ghost:")]
    waits = {"rclpy": time.monotonic() - t_proc}
    wait(lambda: all(pubs[k].get_subscription_count() > 0 for k in known), 60, "node subscribed to every input")
    waits["subscribed"] = time.monotonic() - t_proc
    wait(lambda: state["topology"] is not None, 60, f"{NS}/surface/topology")
    waits["topology"] = time.monotonic() - t_proc
    wait(lambda: state["clock"] is not None and state["clock"] >= START_SIM_TIME, 120, f"/clock >= {START_SIM_TIME}")
    waits["clock"] = time.monotonic() - t_proc
    ghosts_ok = []
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline and len(ghosts_ok) < len(ghosts):
        ghosts_ok = [g for g in ghosts if pubs[f"ghost:{g}"].get_subscription_count() > 0]
        time.sleep(0.05)
    waits["ghosts"] = time.monotonic() - t_proc
    gen_cfg = dict(cfg, ghosts=ghosts_ok)
    gen = Generator(gen_cfg, state["topology"])
    plan = make_plan(cfg["messages"], cfg["seed"], bool(cfg["colliders"]), bool(ghosts_ok))
    print(f"fuzzer sending {len(plan)} messages (sim time {state['clock']:.3f} s; unknown colliders "
          f"subscribed: {', '.join(ghosts_ok) or 'none'})", flush=True)

    sent, by_topic, expected, failed, last_error = 0, Counter(), Counter(), Counter(), [""]
    categories = {}
    errors = []
    rate, burst = float(cfg["rate"]), max(int(cfg["burst"]), 1)
    t0 = time.monotonic()
    waits["sending"] = t0 - t_proc
    clock0 = state["clock"]
    for i, (group, cat) in enumerate(plan):
        rng = np.random.default_rng([cfg["seed"], i])
        clock = state["clock"]
        topic, msg, verdict = gen.build(group, cat, rng, clock)
        try:
            pubs[topic].publish(msg)
        except Exception as err:  # noqa: BLE001 - a full KEEP_ALL history: not sent, counted
            failed[topic] += 1
            last_error[0] = f"{type(err).__name__}: {err}"
            continue
        sent += 1
        by_topic[topic] += 1
        expected[verdict] += 1
        row = categories.setdefault(f"{group}/{cat}", {"sent": 0, "expected": Counter()})
        row["sent"] += 1
        row["expected"][verdict] += 1
        if verdict.startswith("error:") and len(errors) < 20:
            errors.append({"index": i, "group": group, "category": cat, "verdict": verdict})
        if (i + 1) % burst == 0:
            delay = t0 + (i + 1) / rate - time.monotonic()
            if delay > 0:
                time.sleep(delay)
    t_sent = time.monotonic() - t0
    acked = all(p.wait_for_all_acked(Duration(seconds=30)) for p in pubs.values())
    result = {"sent": sent, "publish_failed": dict(failed), "publish_error": last_error[0],
              "sent_by_topic": dict(by_topic), "expected": dict(expected),
              "categories": {k: {"sent": v["sent"], "expected": dict(v["expected"])} for k, v in categories.items()},
              "error_examples": errors, "send_s": t_sent, "wait_s": waits["sending"], "waits": waits, "rate_achieved": sent / t_sent if t_sent > 0 else None,
              "acked": acked, "clock_start": clock0, "clock_end": state["clock"], "clock_resets": state["resets"],
              "ghosts": ghosts_ok, "ghosts_unsubscribed": [g for g in ghosts if g not in ghosts_ok],
              "bbox": state["topology"]}
    Path(out).write_text(json.dumps(result))
    print(f"fuzzer done: {sent} messages in {t_sent:.2f} s, acknowledged: {acked}", flush=True)
    stop_spinning()
    node.destroy_node()
    rclpy.try_shutdown()
    return 0


# ---------------------------------------------------------------------- soak: publisher process
def soak_pub_main(cfg, out):
    import numpy as np
    import rclpy
    from rclpy.duration import Duration
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
    from rclpy.signals import SignalHandlerOptions
    from geometry_msgs.msg import WrenchStamped
    from rosgraph_msgs.msg import Clock

    rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
    index = int(cfg["index"])
    node = rclpy.create_node(f"mdss_stress_publisher_{index}")
    pub = node.create_publisher(WrenchStamped, f"{NS}/wrench",
                                QoSProfile(history=HistoryPolicy.KEEP_ALL,                # as the fuzzer's
                                           reliability=ReliabilityPolicy.RELIABLE,
                                           durability=DurabilityPolicy.VOLATILE))
    dt = float(cfg["dt"])
    lock = threading.Lock()
    state = {"clock": None}
    samples = []          # latency probes: {"wall", "stamp", "at_stamp", "done"}
    waiting = []          # the probes not done yet

    def on_clock(msg):
        t = msg.clock.sec + 1e-9 * msg.clock.nanosec
        now = time.time()
        with lock:
            state["clock"] = t
            for s in waiting:
                if s["at_stamp"] is None and t >= s["stamp"] - 1e-9:
                    s["at_stamp"] = now
                if t >= s["stamp"] + dt - 1e-6:
                    s["done"] = now
            waiting[:] = [s for s in waiting if s["done"] is None]

    node.create_subscription(Clock, "/clock", on_clock,
                             QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10,
                                        reliability=ReliabilityPolicy.RELIABLE,
                                        durability=DurabilityPolicy.TRANSIENT_LOCAL))
    stop_spinning = spin_in_background(node)
    deadline = time.monotonic() + 120
    while (pub.get_subscription_count() == 0 or state["clock"] is None) and time.monotonic() < deadline:
        time.sleep(0.02)
    print("soak publisher ready", flush=True)
    line = sys.stdin.readline()
    if not line.startswith("go"):
        return 3
    rate, seconds = float(cfg["rate"]), float(cfg["seconds"])
    every = int(cfg.get("latency_every") or 0)
    handle = cfg["handle"]
    rng = np.random.default_rng(index)
    fz = -10.0
    from mdss_ros.record.ros_messages import cdr_bytes
    from mdss_ros.ros.convert import wrench_stamped
    sent, skipped, failed, last_error = 0, 0, 0, ""
    tried = 0                         # messages of the schedule taken: sent + failed
    t0 = time.monotonic()
    base, base_count = t0, 0          # schedule: message base_count + j is due at base + j / rate
    end = t0 + seconds
    max_lag = 0.05
    while True:
        now = time.monotonic()
        if now >= end:
            break
        due = base_count + int((now - base) * rate) + 1
        if due - tried > max_lag * rate:           # starved: drop the backlog from the schedule
            skipped += due - tried - int(max_lag * rate)
            base, base_count = now, tried
            due = tried + int(max_lag * rate)
        while tried < due:
            with lock:
                clock = state["clock"]
            fz = float(np.clip(fz + rng.normal(0, 0.5), -20.0, 0.0))
            probe = every and index == 0 and tried % every == 0
            # Unstamped (the next step), as a controller streaming wrenches sends them; the
            # latency probes carry the next sim time. (Stamping with this process's view of
            # /clock was tried: a publisher starved of CPU saw /clock over 1 s late, and
            # the node rejected 44 % as stamp_past.) CDR bytes, built with rosbags: an
            # rclpy message object costs more to publish, and the publishers must keep up.
            t = clock + dt if probe else 0.0
            data = cdr_bytes(wrench_stamped(t, handle, [1e-3 if probe else 0.0, 0.0, fz, 0.0, 0.0, 0.0]))
            sample = {"wall": time.time(), "stamp": t, "at_stamp": None, "done": None}
            tried += 1
            try:
                pub.publish(data)
            except Exception as err:  # noqa: BLE001 - a full KEEP_ALL history: not sent, counted
                failed += 1
                last_error = f"{type(err).__name__}: {err}"
                continue
            if probe:
                with lock:
                    samples.append(sample)
                    waiting.append(sample)
            sent += 1
        nxt = base + (tried - base_count) / rate
        delay = nxt - time.monotonic()
        if delay > 0:
            time.sleep(delay)
    elapsed = time.monotonic() - t0
    acked = pub.wait_for_all_acked(Duration(seconds=30))
    deadline = time.monotonic() + 3.0
    while time.monotonic() < deadline:
        with lock:
            if not waiting:
                break
        time.sleep(0.05)
    with lock:
        lat = [1e3 * (s["done"] - s["wall"]) for s in samples if s["done"] is not None]
        lat_stamp = [1e3 * (s["done"] - s["at_stamp"]) for s in samples
                     if s["done"] is not None and s["at_stamp"] is not None]
        unresolved = sum(1 for s in samples if s["done"] is None)
    result = {"index": index, "sent": sent, "skipped": skipped, "publish_failed": failed, "publish_error": last_error,
              "seconds": elapsed, "rate_target": rate,
              "rate_achieved": sent / elapsed if elapsed > 0 else None, "acked": acked,
              "latency_ms": lat, "latency_from_stamp_ms": lat_stamp, "latency_unresolved": unresolved}
    Path(out).write_text(json.dumps(result))
    print(f"soak publisher {index} done: {sent} sent in {elapsed:.2f} s, acknowledged: {acked}", flush=True)
    stop_spinning()
    node.destroy_node()
    rclpy.try_shutdown()
    return 0


# ---------------------------------------------------------------------- orchestration helpers
def _num(d, key, default=None):
    if d is None or key not in d:
        return default
    try:
        return float(d[key])
    except (TypeError, ValueError):
        return default


def diag_records(watcher):
    out = []
    for line in list(watcher.lines):
        if line.startswith(DIAG_PREFIX):
            try:
                out.append(json.loads(line[len(DIAG_PREFIX):]))
            except ValueError:
                pass
    return out


def counters(d):
    """The input counters of a /diagnostics status (absent ones as None)."""
    c = {k: (int(_num(d, k)) if _num(d, k) is not None else None) for k in COUNTER_KEYS}
    c["inputs_late"] = int(_num(d, "inputs_late", 0))
    accounted = sum(c[k] or 0 for k in ("inputs_applied", "rejected_total", "inputs_pending", "inputs_dropped",
                                          "inputs_cleared"))
    c["accounted"] = accounted
    return c


def wait_settled(watcher, since_wall, timeout, stable=3):
    """The last /diagnostics status once `stable` in a row (after since_wall) have inputs_pending
    0 and the same counters; (status, settled)."""
    deadline = time.monotonic() + timeout
    last = None
    while True:
        ds = [d for d in diag_records(watcher) if d.get("_wall", 0) >= since_wall]
        if ds:
            last = ds[-1]
        tail = ds[-stable:]
        if len(tail) == stable and all(_num(d, "inputs_pending", 0) == 0 for d in tail) \
                and len({tuple(d.get(k) for k in COUNTER_KEYS) for d in tail}) == 1:
            return last, True
        if time.monotonic() > deadline or watcher.returncode is not None:
            return last, False
        time.sleep(0.2)


def start_node(launch, scene, sets, code=None, **params):
    """The node process; code: run the mdss_ros package of that folder instead of this
    checkout's (its working directory, so `python -m` imports it first)."""
    from launch_testing import param_arg
    p = dict(scene=scene)
    if sets:
        p["scene_overrides"] = list(sets)
    p.update({k: v for k, v in params.items() if v is not None})
    args = ["-m", "mdss_ros.node", "--ros-args"]
    for k, v in p.items():
        args += ["-p", param_arg(k, v)]
    node = launch.start("node", args, cwd=Path(code).resolve() if code else None)
    node.wait_for(READY, timeout=3600)
    return node


def _role_args(role, cfg, out, code=None):
    return [THIS, "--role", role, "--config", json.dumps(cfg), "--out", str(out)] + \
        (["--code", str(Path(code).resolve())] if code else [])


def start_watcher(launch, colliders):
    out = launch.dir / "watcher.json"
    w = launch.script("watcher", *_role_args("watcher", {"colliders": colliders}, out))
    w.wait_for("watcher ready", timeout=120)
    return w, out


def stop_watcher(watcher, out):
    try:
        watcher.popen.stdin.close()
    except OSError:
        pass
    try:
        watcher.wait(30)
    except TimeoutError:
        watcher.stop()
    try:
        return json.loads(Path(out).read_text())
    except (OSError, ValueError):
        return None


def node_errors(node):
    """Lines of the node's output that say a callback raised (the node survived it)."""
    lines = node.text.splitlines()
    hits = [i for i, l in enumerate(lines) if "callback failed" in l]
    excerpt = "\n".join(lines[hits[0]:hits[0] + 14]) if hits else ""
    return len(hits), excerpt


def read_rss_kb(pid):
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1])
    except OSError:
        return None
    return None


def check_mcap(path, skip_topics=()):
    """Every float of every message in the recording (inputs and outputs), decoded with
    mcap + mcap_ros2; PointCloud2 data by its fields, /diagnostics values that read as
    numbers. Returns {"messages", "checked", "nonfinite_messages", "by_topic", "examples"}."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    def walk(obj):
        if isinstance(obj, float):
            return 0 if math.isfinite(obj) else 1
        if isinstance(obj, (bool, int, str, bytes, bytearray)) or obj is None:
            return 0
        if isinstance(obj, array.array):
            return sum(1 for v in obj if isinstance(v, float) and not math.isfinite(v)) if obj.typecode in "fd" else 0
        if isinstance(obj, (list, tuple)):
            return sum(walk(v) for v in obj)
        if hasattr(obj, "__dict__"):
            return sum(walk(v) for v in vars(obj).values())
        return 0

    counts, bad, examples = Counter(), Counter(), []
    skipped = Counter()
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for schema, channel, message, decoded in reader.iter_decoded_messages(log_time_order=False):
            topic = channel.topic
            if topic in skip_topics:
                skipped[topic] += 1
                continue
            counts[topic] += 1
            if schema.name == "sensor_msgs/msg/PointCloud2":
                n = cloud_nonfinite(decoded)
                n = n if n >= 0 else 1
                n += walk(decoded.header)
            elif schema.name == "diagnostic_msgs/msg/DiagnosticArray":
                n = sum(len(diag_nonfinite({kv.key: kv.value for kv in st.values})) for st in decoded.status)
            else:
                n = walk(decoded)
            if n:
                bad[topic] += 1
                if len(examples) < 10:
                    examples.append({"topic": topic, "log_time": message.log_time, "bad": n})
    return {"messages": sum(counts.values()) + sum(skipped.values()), "checked": sum(counts.values()),
            "skipped": dict(skipped), "by_topic": dict(counts), "nonfinite_messages": dict(bad),
            "examples": examples}


def _criterion(name, ok, detail):
    return {"name": name, "pass": bool(ok), "detail": detail}


def _watcher_finite(w):
    if w is None:
        return False, "watcher wrote no summary"
    bad = {k: v for k, v in (w.get("nonfinite_messages") or {}).items() if v}
    seen = w.get("counts", {})
    short = {(k[len(NS) + 1:] if k.startswith(NS + "/") else k): v for k, v in sorted(seen.items())}
    detail = f"{sum(seen.values())} output messages checked ({', '.join(f'{k} {v}' for k, v in short.items())})"
    if bad:
        detail += f"; NON-FINITE in {bad}; first: {w.get('examples', [])[:3]}"
    return not bad and sum(seen.values()) > 0, detail


# ---------------------------------------------------------------------- fuzz
def run_fuzz(scene="soft_finger", messages=10000, seed=0, mcap=None, sets=(), workdir=None, rate=500.0, burst=10,
             ghosts=3, settle_timeout=60.0, code=None, log=print):
    """Run the fuzz; returns the report (a dict with "criteria" and "passed")."""
    info = scene_info(scene, sets)
    limits = default_limits()
    workdir = Path(workdir or tempfile.mkdtemp(prefix="mdss_stress_fuzz_"))
    mcap_file = None
    if mcap:
        Path(mcap).mkdir(parents=True, exist_ok=True)
        mcap_file = Path(mcap) / f"fuzz_{info['name']}_seed{seed}_{time.strftime('%Y%m%d_%H%M%S')}.mcap"
    names = [g for g in GHOST_NAMES if g not in info["colliders"]][:max(int(ghosts), 0)]
    cfg = {"handles": info["handles"], "colliders": info["colliders"], "ghosts": names, "world_frame": "world",
           "limits": limits, "messages": int(messages), "seed": int(seed), "rate": float(rate), "burst": int(burst)}
    t_start = time.monotonic()
    log(f"fuzz: scene {' '.join([scene] + list(sets))}, {messages} messages, seed {seed}; logs in {workdir}")
    with Launch(workdir) as launch:
        node = start_node(launch, scene, sets, code, diagnostics_rate=2.0,
                          mcap_path=str(mcap_file) if mcap_file else None)
        t_ready = time.monotonic()
        watcher, watcher_out = start_watcher(launch, info["colliders"])
        t_watcher = time.monotonic()
        fuzz_out = launch.dir / "fuzzer.json"
        fuzzer = launch.script("fuzzer", *_role_args("fuzz-client", cfg, fuzz_out, code))
        rc = fuzzer.wait(timeout=messages / max(rate, 1.0) * 10 + 300)
        if rc != 0:
            raise RuntimeError(f"fuzzer exited {rc}:\n{fuzzer.tail(40)}")
        sent = json.loads(fuzz_out.read_text())
        t_sent = time.monotonic()
        final, settled = wait_settled(watcher, time.time(), settle_timeout)
        t_settled = time.monotonic()
        alive = node.returncode is None
        exit_code = node.stop()
        n_err, err_excerpt = node_errors(node)
        summary = stop_watcher(watcher, watcher_out)
        launch.shutdown()
    t_end = time.monotonic()
    mcap_res = check_mcap(mcap_file) if mcap_file and mcap_file.exists() else None

    c = counters(final)
    resets = int(_num(final, "stability_failures", 0)) if final else 0
    # rejection kinds: predicted vs counted
    kinds = [k[len("rejected_"):] for k in (final or {}) if k.startswith("rejected_") and k != "rejected_total"]
    expected = Counter(sent["expected"])
    errors_expected = sum(v for k, v in expected.items() if k.startswith("error:"))
    table, mismatched = [], []
    for k in sorted(set(kinds) | {k for k in expected if k != "applied" and not k.startswith("error:")}):
        node_k = int(_num(final, f"rejected_{k}", 0))
        exp_k = expected.get(k, 0)
        stamp_kind = k in STAMP_KINDS
        ok = exp_k <= node_k <= exp_k + errors_expected
        compared = not (stamp_kind and (resets or sent["clock_resets"]))
        table.append({"kind": k, "expected": exp_k, "node": node_k, "ok": ok, "compared": compared})
        if compared and not ok and k != "apply_error":
            mismatched.append(f"{k}: expected {exp_k}, node {node_k}")
    applied_exp = expected.get("applied", 0)
    # a valid input is applied, or discarded by a reset / clear_forces (cleared), or finds the
    # queue full (dropped), or is refused by the simulator (apply_error)
    fates = {"applied": c["inputs_applied"] or 0, "cleared": c["inputs_cleared"] or 0,
             "dropped": c["inputs_dropped"] or 0, "apply_error": int(_num(final, "rejected_apply_error", 0))}
    if sum(fates.values()) != applied_exp:
        mismatched.append(f"valid inputs: predicted {applied_exp}, node {sum(fates.values())}")

    criteria = []
    criteria.append(_criterion(
        "no crash", alive and exit_code == 0 and n_err == 0,
        f"node alive at the end: {alive}; exit code on SIGINT: {exit_code}; callbacks that raised: {n_err}"
        + (f"\n{err_excerpt}" if err_excerpt else "")))
    received = c["inputs_received"]
    dropped_s = "absent (0)" if c["inputs_dropped"] is None else str(c["inputs_dropped"])
    cleared_s = "absent (0)" if c["inputs_cleared"] is None else str(c["inputs_cleared"])
    criteria.append(_criterion(
        "every message counted", settled and received == sent["sent"] and received == c["accounted"],
        f"sent {sent['sent']} (acknowledged: {sent['acked']}), received {received}"
        + (f" ({sent['sent'] - received} LOST)" if received is not None and received < sent["sent"] else "")
        + f"; applied {c['inputs_applied']} + rejected {c['rejected_total']} + pending {c['inputs_pending']} + "
          f"dropped {dropped_s} + cleared {cleared_s} = {c['accounted']}"
        + ("" if received == c["accounted"] else f" ({(received or 0) - c['accounted']} UNACCOUNTED)")
        + ("" if settled else "; the counters did not settle (pending > 0 or still changing)")))
    criteria.append(_criterion(
        "rejections by kind match the prediction", not mismatched,
        ("; ".join(mismatched) if mismatched else "every kind as predicted")
        + f"; {applied_exp} predicted valid: " + " + ".join(f"{k} {v}" for k, v in fates.items())
        + (f"; {errors_expected} messages make mdss_ros.ros.validate raise (not InputRejected)" if errors_expected else "")
        + (f"; the simulation reset {resets} time(s), so a stamp kind may differ without failing"
           if resets or sent["clock_resets"] else "")))
    ok_w, detail_w = _watcher_finite(summary)
    criteria.append(_criterion("no non-finite output (subscriber)", ok_w, detail_w))
    if mcap_file:
        if mcap_res is None:
            criteria.append(_criterion("no non-finite value in the recording", False, f"{mcap_file} missing"))
        else:
            bad = mcap_res["nonfinite_messages"]
            criteria.append(_criterion(
                "no non-finite value in the recording", not bad and mcap_res["checked"] > 0,
                f"{mcap_file}: {mcap_res['checked']} messages on {len(mcap_res['by_topic'])} topics checked"
                + (f" (not decoded: {mcap_res['skipped']})" if mcap_res["skipped"] else "")
                + (f"; NON-FINITE: {bad}, {mcap_res['examples'][:3]}" if bad else "")))
    report = {
        "command": "fuzz", "scene": scene, "sets": list(sets), "messages": messages, "seed": seed,
        "rate": rate, "burst": burst, "workdir": str(workdir), "mcap": str(mcap_file) if mcap_file else None,
        "sent": sent, "counters": c, "final_diagnostics": final, "settled": settled,
        "kinds": table, "expected_applied": applied_exp, "simulation_resets": resets,
        "node_exit_code": exit_code, "node_alive": alive, "callback_errors": n_err,
        "callback_error_excerpt": err_excerpt, "watcher": {k: v for k, v in (summary or {}).items()
                                                           if k != "pose_stamps_ns"},
        "mcap_check": mcap_res,
        "times": {"node_start_s": t_ready - t_start, "watcher_start_s": t_watcher - t_ready,
                  "fuzzer_s": t_sent - t_watcher, "fuzzer_wait_s": sent.get("wait_s"), "send_s": sent["send_s"],
                  "settle_s": t_settled - t_sent, "stop_s": t_end - t_settled, "total_s": t_end - t_start},
        "criteria": criteria, "passed": all(x["pass"] for x in criteria),
    }
    return report


def print_fuzz(r, out=print):
    s = r["sent"]
    out(f"\n== fuzz: scene {' '.join([r['scene']] + r['sets'])}, {s['sent']} messages, seed {r['seed']} ==")
    out(f"sent in {s['send_s']:.2f} s ({s['rate_achieved']:.0f} msg/s, bursts of {r['burst']}), sim time "
        f"{s['clock_start']:.2f} -> {s['clock_end']:.2f} s; unknown colliders: {', '.join(s['ghosts']) or 'none'}"
        + (f" (never subscribed: {', '.join(s['ghosts_unsubscribed'])})" if s["ghosts_unsubscribed"] else ""))
    out("messages per topic: " + ", ".join(f"{k} {v}" for k, v in sorted(s["sent_by_topic"].items()))
        + (f"; publish failed (not sent): {s['publish_failed']} ({s['publish_error']})" if s["publish_failed"] else ""))
    out(f"\n{'topic/category':40s} {'sent':>6s}  predicted verdict")
    for k in sorted(s["categories"]):
        v = s["categories"][k]
        out(f"{k:40s} {v['sent']:6d}  " + ", ".join(f"{a} {b}" for a, b in sorted(v["expected"].items())))
    out(f"\n{'rejection kind':24s} {'predicted':>9s} {'node':>7s}")
    for row in r["kinds"]:
        flag = "" if row["ok"] else ("  MISMATCH" if row["compared"] else "  (differs; not compared: resets)")
        out(f"{row['kind']:24s} {row['expected']:9d} {row['node']:7d}{flag}")
    c = r["counters"]
    out(f"{'valid (all fates)':24s} {r['expected_applied']:9d} {(c['inputs_applied'] or 0):7d} applied + "
        f"{c['inputs_cleared'] or 0} cleared + {c['inputs_dropped'] or 0} dropped + "
        f"{int(_num(r['final_diagnostics'], 'rejected_apply_error', 0))} apply_error")
    errs = {k: v for k, v in s["expected"].items() if k.startswith("error:")}
    if errs:
        out(f"validate raised (not InputRejected) on: {errs}; e.g. {s['error_examples'][:3]}")
    c = r["counters"]
    out("\ncounters: " + ", ".join(f"{k} {v}" for k, v in c.items()))
    fd = r["final_diagnostics"] or {}
    out(f"simulation: stability {fd.get('stability')}, failures {fd.get('stability_failures')}, "
        f"guard recoveries {fd.get('guard_recoveries')}, collider poses inside {fd.get('collider_poses_inside')}, "
        f"sim time {fd.get('sim_time')}")
    t = r["times"]
    out(f"time: node start {t['node_start_s']:.1f} s, watcher {t['watcher_start_s']:.1f} s, fuzzer {t['fuzzer_s']:.1f} s "
        f"(of which waiting for the node {t['fuzzer_wait_s']:.1f} s, sending {t['send_s']:.1f} s), settling "
        f"{t['settle_s']:.1f} s, stopping {t['stop_s']:.1f} s, total {t['total_s']:.1f} s; logs: {r['workdir']}")
    _print_criteria(r, out)


def _print_criteria(r, out):
    out("")
    for cr in r["criteria"]:
        out(f"{'PASS' if cr['pass'] else 'FAIL'}  {cr['name']}: {cr['detail']}")
    out(f"\n{'PASS' if r['passed'] else 'FAIL'}")


# ---------------------------------------------------------------------- soak
def output_ticks(stamps_ns, dt, rate):
    """Missed ~/domain_poses ticks: for each run of increasing stamps (a reset starts a new
    one), the steps k between the first and last received whose tick floor(k dt rate)
    changed, against the distinct stamps received."""
    if not stamps_ns:
        return {"received": 0, "distinct": 0, "expected": 0, "missed": 0, "duplicates": 0, "segments": 0}
    tick = lambda k: math.floor(k * dt * rate + 1e-6)  # noqa: E731
    segments, cur = [], [stamps_ns[0]]
    for s in stamps_ns[1:]:
        if s < cur[-1]:
            segments.append(cur)
            cur = []
        cur.append(s)
    segments.append(cur)
    expected = distinct = 0
    missed_examples = []
    for seg in segments:
        ks = sorted({int(round(s * 1e-9 / dt)) for s in seg})
        distinct += len(ks)
        want = [k for k in range(ks[0], ks[-1] + 1) if k == ks[0] or tick(k) > tick(k - 1)]
        expected += len(want)
        have = set(ks)
        missing = [k for k in want if k not in have]
        missed_examples += missing[:10]
    return {"received": len(stamps_ns), "distinct": distinct, "expected": expected, "missed": expected - distinct,
            "duplicates": len(stamps_ns) - distinct, "segments": len(segments),
            "missed_steps_examples": missed_examples[:10]}


def run_soak(scene="cantilever", publishers=4, rate=1000.0, seconds=600.0, sets=(), workdir=None, mcap=None,
             warmup=None, latency_every=100, pose_rate=90.0, code=None, log=print):
    """Run the soak; returns the report (a dict with "criteria" and "passed")."""
    info = scene_info(scene, sets)
    if not info["handles"]:
        raise ValueError(f"scene {scene} has no handle to send wrenches to")
    handle = info["handles"][0]
    dt = info["dt"]
    warmup = min(10.0, seconds / 4) if warmup is None else warmup
    workdir = Path(workdir or tempfile.mkdtemp(prefix="mdss_stress_soak_"))
    mcap_file = None
    if mcap:
        Path(mcap).mkdir(parents=True, exist_ok=True)
        mcap_file = Path(mcap) / f"soak_{info['name']}_{time.strftime('%Y%m%d_%H%M%S')}.mcap"
    log(f"soak: scene {' '.join([scene] + list(sets))}, {publishers} publishers x {rate:g} Hz for {seconds:g} s on "
        f"{NS}/wrench ({handle}); logs in {workdir}")
    t_start = time.monotonic()
    rss = []
    with Launch(workdir) as launch:
        node = start_node(launch, scene, sets, code, real_time_factor=1.0,
                          mcap_path=str(mcap_file) if mcap_file else None)
        pid = node.popen.pid
        watcher, watcher_out = start_watcher(launch, info["colliders"])
        outs, pubs = [], []
        for i in range(publishers):
            out = launch.dir / f"publisher_{i}.json"
            cfg = {"index": i, "rate": rate, "seconds": seconds, "handle": handle, "dt": dt,
                   "latency_every": latency_every if i == 0 else 0}
            pubs.append(launch.script(f"publisher_{i}", *_role_args("soak-pub", cfg, out)))
            outs.append(out)
        for p in pubs:
            p.wait_for("soak publisher ready", timeout=180)
        stop_rss = threading.Event()
        t_go = time.monotonic()
        t_go_wall = time.time()

        def sample():
            while not stop_rss.is_set():
                kb = read_rss_kb(pid)
                if kb is not None:
                    rss.append((time.monotonic() - t_go, kb))
                stop_rss.wait(1.0)

        sampler = threading.Thread(target=sample, daemon=True)
        sampler.start()
        for p in pubs:
            p.popen.stdin.write("go\n")
            p.popen.stdin.flush()
        codes = [p.wait(seconds + 180) for p in pubs]
        t_pub_end_wall = time.time()
        stop_rss.set()
        sampler.join(3)
        final, settled = wait_settled(watcher, t_pub_end_wall, 120)
        alive = node.returncode is None
        exit_code = node.stop()
        n_err, err_excerpt = node_errors(node)
        diags = diag_records(watcher)
        summary = stop_watcher(watcher, watcher_out)
        launch.shutdown()
    t_end = time.monotonic()
    if any(codes):
        raise RuntimeError(f"publisher exit codes {codes}; logs in {workdir}")
    pres = [json.loads(o.read_text()) for o in outs]
    mcap_res = check_mcap(mcap_file) if mcap_file and mcap_file.exists() else None

    sent = sum(p["sent"] for p in pres)
    c = counters(final)
    received = c["inputs_received"]
    # /diagnostics windows while the publishers ran (the first one after go is partial)
    during = [d for d in diags if t_go_wall + 1.5 <= d["_wall"] <= t_pub_end_wall + 0.5]
    after_warm = [d for d in during if d["_wall"] >= t_go_wall + warmup] or during
    rtf = [_num(d, "real_time_factor") for d in after_warm if _num(d, "steps_in_window", 1) > 0]
    step_med = [_num(d, "step_ms_median") for d in during if _num(d, "steps_in_window", 1) > 0]
    step_max = [_num(d, "step_ms_max") for d in during if _num(d, "steps_in_window", 1) > 0]
    cycle_med = [_num(d, "cycle_ms_median") for d in during if _num(d, "steps_in_window", 1) > 0]
    pending = [_num(d, "inputs_pending", 0) for d in during]
    dropped = c["inputs_dropped"]
    # RSS: at the warm-up and at the end of publishing
    rss_start = next((kb for t, kb in rss if t >= warmup), rss[0][1] if rss else None)
    rss_end = rss[-1][1] if rss else None
    growth = 100.0 * (rss_end - rss_start) / rss_start if rss_start else float("nan")
    # output ticks while the publishers ran
    stamps = (summary or {}).get("pose_stamps_ns", [])
    sim0 = _num(next((d for d in diags if d["_wall"] >= t_go_wall), None), "sim_time", 0.0)
    sim1 = _num(([d for d in diags if d["_wall"] <= t_pub_end_wall] or [final])[-1], "sim_time", 0.0)
    ticks = output_ticks(stamps, dt, pose_rate)
    lat = [x for p in pres for x in p["latency_ms"]]
    lat_stamp = [x for p in pres for x in p["latency_from_stamp_ms"]]
    total_rate = rate * publishers

    criteria = []
    criteria.append(_criterion(
        "no crash", alive and exit_code == 0 and n_err == 0,
        f"node alive at the end: {alive}; exit code on SIGINT: {exit_code}; callbacks that raised: {n_err}"
        + (f"\n{err_excerpt}" if err_excerpt else "")))
    criteria.append(_criterion(
        "received == sent", settled and received == sent and received == c["accounted"],
        f"sent {sent} ({' + '.join(str(p['sent']) for p in pres)}; all acknowledged: {all(p['acked'] for p in pres)}"
        f"{'; publish failures (not counted as sent): ' + str(sum(p['publish_failed'] for p in pres)) if any(p['publish_failed'] for p in pres) else ''}), "
        f"received {received}" + (f" ({sent - received} LOST)" if received is not None and received < sent else "")
        + f"; applied {c['inputs_applied']} + rejected {c['rejected_total']} + pending {c['inputs_pending']} + "
          f"dropped {c['inputs_dropped'] if c['inputs_dropped'] is not None else 'absent (0)'} + cleared "
          f"{c['inputs_cleared'] if c['inputs_cleared'] is not None else 'absent (0)'} = {c['accounted']}"
        + ("" if settled else "; the counters did not settle")))
    ok_w, detail_w = _watcher_finite(summary)
    criteria.append(_criterion("no non-finite output (subscriber)", ok_w, detail_w))
    if mcap_file:
        bad = (mcap_res or {}).get("nonfinite_messages", {"missing": 1})
        criteria.append(_criterion("no non-finite value in the recording", mcap_res is not None and not bad,
                                   f"{mcap_file}: {(mcap_res or {}).get('checked')} messages checked"
                                   + (f"; NON-FINITE: {bad}" if bad else "")))
    criteria.append(_criterion(
        "RSS growth < 5 %", rss_start is not None and growth < 5.0,
        f"VmRSS {rss_start} kB at {warmup:g} s -> {rss_end} kB at the end ({growth:+.2f} %), max "
        f"{max((kb for _, kb in rss), default=None)} kB, {len(rss)} samples"))
    criteria.append(_criterion(
        "real-time factor median >= 0.99", bool(rtf) and _median(rtf) >= 0.99,
        f"median {_median(rtf):.4f}, min {min(rtf) if rtf else float('nan'):.4f} over {len(rtf)} windows "
        f"(after {warmup:g} s)"))
    criteria.append(_criterion(
        "inputs_pending bounded", bool(pending) and max(pending) < total_rate * 1.0,
        f"max {max(pending) if pending else None:.0f}, median {_median(pending):.0f} (bound: < 1 s of input = "
        f"{total_rate:.0f}); inputs_dropped {dropped if dropped is not None else 'absent'}"))
    criteria.append(_criterion(
        "no missed ~/domain_poses tick", ticks["expected"] > 0 and ticks["missed"] == 0,
        f"{ticks['distinct']} distinct stamps of {ticks['expected']} ticks between the first and last received "
        f"({ticks['missed']} missed{', e.g. steps ' + str(ticks['missed_steps_examples']) if ticks['missed'] else ''}; "
        f"{ticks['duplicates']} duplicates, {ticks['segments']} run(s)); sim time while publishing "
        f"{sim1 - sim0:.2f} s x {pose_rate:g} Hz = {(sim1 - sim0) * pose_rate:.0f}"))

    report = {
        "command": "soak", "scene": scene, "sets": list(sets), "publishers": publishers, "rate": rate,
        "seconds": seconds, "warmup_s": warmup, "workdir": str(workdir), "mcap": str(mcap_file) if mcap_file else None,
        "sent": sent, "publisher_results": [{k: v for k, v in p.items() if not k.startswith("latency_") or
                                             k == "latency_unresolved"} for p in pres],
        "counters": c, "settled": settled, "final_diagnostics": final,
        "rss_kb": {"start": rss_start, "end": rss_end, "growth_pct": growth,
                   "max": max((kb for _, kb in rss), default=None), "samples": rss},
        "real_time_factor": {"median": _median(rtf), "min": min(rtf) if rtf else None, "windows": len(rtf)},
        "inputs_pending": {"max": max(pending) if pending else None, "median": _median(pending)},
        "inputs_dropped": dropped,
        "step_ms": {"p50_median_of_windows": _median(step_med), "p99_of_window_max": _pct(step_max, 0.99),
                    "max": max(step_max) if step_max else None, "windows": len(step_med),
                    "cycle_ms_median": _median(cycle_med)},
        "latency_ms": {"n": len(lat), "p50": _pct(lat, 0.5), "p99": _pct(lat, 0.99),
                       "max": max(lat) if lat else None,
                       "from_stamp_p50": _pct(lat_stamp, 0.5), "from_stamp_p99": _pct(lat_stamp, 0.99),
                       "from_stamp_max": max(lat_stamp) if lat_stamp else None,
                       "unresolved": sum(p["latency_unresolved"] for p in pres)},
        "output_ticks": ticks, "sim_time": {"start": sim0, "end": sim1},
        "node_exit_code": exit_code, "node_alive": alive, "callback_errors": n_err,
        "watcher": {k: v for k, v in (summary or {}).items() if k != "pose_stamps_ns"}, "mcap_check": mcap_res,
        "times": {"total_s": t_end - t_start},
        "criteria": criteria, "passed": all(x["pass"] for x in criteria),
    }
    return report


def print_soak(r, out=print):
    out(f"\n== soak: scene {' '.join([r['scene']] + r['sets'])}, {r['publishers']} publishers x {r['rate']:g} Hz, "
        f"{r['seconds']:g} s ==")
    for p in r["publisher_results"]:
        out(f"publisher {p['index']}: sent {p['sent']} in {p['seconds']:.2f} s ({p['rate_achieved']:.1f} Hz"
            f"{', ' + str(p['skipped']) + ' skipped (starved)' if p['skipped'] else ''}"
            f"{', ' + str(p['publish_failed']) + ' publish calls failed: ' + p['publish_error'] if p['publish_failed'] else ''}"
            f"), acknowledged {p['acked']}")
    c = r["counters"]
    out("counters: " + ", ".join(f"{k} {v}" for k, v in c.items()))
    rs = r["rss_kb"]
    out(f"RSS: {rs['start']} kB at {r['warmup_s']:g} s -> {rs['end']} kB ({rs['growth_pct']:+.2f} %), max {rs['max']} kB")
    f = r["real_time_factor"]
    out(f"real-time factor: median {f['median']:.4f}, min {f['min'] if f['min'] is not None else float('nan'):.4f} "
        f"({f['windows']} windows)")
    s = r["step_ms"]
    out(f"step ms: p50 {s['p50_median_of_windows']:.2f} (median of 1-s window medians), p99 of window maxima "
        f"{s['p99_of_window_max']:.2f}, max {s['max'] if s['max'] is not None else float('nan'):.2f}; cycle median "
        f"{s['cycle_ms_median']:.2f}")
    out(f"inputs_pending: max {r['inputs_pending']['max']}, median {r['inputs_pending']['median']}; "
        f"inputs_dropped: {r['inputs_dropped'] if r['inputs_dropped'] is not None else 'absent'}")
    la = r["latency_ms"]
    out(f"latency (publish -> /clock at stamp + dt), {la['n']} samples: p50 {la['p50']:.1f} ms, p99 {la['p99']:.1f} ms, "
        f"max {la['max'] if la['max'] is not None else float('nan'):.1f} ms; from /clock reaching the stamp: p50 "
        f"{la['from_stamp_p50']:.1f}, p99 {la['from_stamp_p99']:.1f}, max "
        f"{la['from_stamp_max'] if la['from_stamp_max'] is not None else float('nan'):.1f} ms"
        + (f"; {la['unresolved']} unresolved" if la["unresolved"] else ""))
    t = r["output_ticks"]
    out(f"~/domain_poses: {t['received']} received, {t['distinct']} distinct of {t['expected']} ticks, "
        f"{t['missed']} missed")
    out(f"time: {r['times']['total_s']:.1f} s; logs: {r['workdir']}")
    _print_criteria(r, out)


# ---------------------------------------------------------------------- main
def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__)
    ap.add_argument("--role", choices=("watcher", "fuzz-client", "soak-pub"), help=argparse.SUPPRESS)
    ap.add_argument("--config", help=argparse.SUPPRESS)
    ap.add_argument("--out", help=argparse.SUPPRESS)
    ap.add_argument("--code", help=argparse.SUPPRESS)
    sub = ap.add_subparsers(dest="command")

    def common(p, scene):
        p.add_argument("--scene", default=scene)
        p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                       help="scene override, passed to the node as scene_overrides (repeatable)")
        p.add_argument("--json", default=None, help="write the report to this file")
        p.add_argument("--workdir", default=None, help="logs of every process (default: a new temporary folder)")
        p.add_argument("--mcap", default=None, metavar="DIR",
                       help="the node records an MCAP into DIR; every float in it is checked afterwards")
        p.add_argument("--code", default=None, metavar="DIR",
                       help="run the node (and the fuzzer's prediction) from the mdss_ros package in DIR, e.g. "
                            "an earlier commit: git archive HEAD | tar -x -C DIR")

    f = sub.add_parser("fuzz", help="malformed and valid messages on every input topic")
    common(f, "soft_finger")
    f.add_argument("--messages", type=int, default=10000)
    f.add_argument("--seed", type=int, default=0)
    f.add_argument("--rate", type=float, default=500.0, help="messages per second (default 500)")
    f.add_argument("--burst", type=int, default=10, help="messages per burst (default 10)")
    s = sub.add_parser("soak", help="P publishers of valid wrenches at R Hz for S s")
    common(s, "cantilever")
    s.add_argument("--publishers", type=int, default=4)
    s.add_argument("--rate", type=float, default=1000.0, help="Hz per publisher (default 1000)")
    s.add_argument("--seconds", type=float, default=600.0)
    s.add_argument("--warmup", type=float, default=None, help="RSS and RTF from this many s (default min(10, S/4))")
    args = ap.parse_args(sys.argv[1:] if argv is None else argv)

    if args.role:
        if args.code:
            sys.path.insert(0, args.code)
        cfg = json.loads(args.config)
        return {"watcher": watcher_main, "fuzz-client": fuzz_client_main, "soak-pub": soak_pub_main}[args.role](
            cfg, args.out)
    if args.command is None:
        ap.print_help()
        return 2
    for item in args.set:
        if "=" not in item:
            ap.error(f"--set expects KEY=VALUE, got {item!r}")
    if args.command == "fuzz":
        report = run_fuzz(args.scene, args.messages, args.seed, args.mcap, args.set, args.workdir, args.rate,
                          args.burst, code=args.code)
        print_fuzz(report)
    else:
        report = run_soak(args.scene, args.publishers, args.rate, args.seconds, args.set, args.workdir, args.mcap,
                          args.warmup, code=args.code)
        print_soak(report)
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(report, indent=1, default=str))
    return 0 if report["passed"] else 1


if __name__ == "__main__":
    sys.exit(main())
