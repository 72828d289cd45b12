#!/usr/bin/env python3
"""Run scenes the ROS way: a mdss node process per body, a publisher process per body
playing its scene's timeline as ROS messages (other nodes publishing forces), optionally
a recorder per body, and, with several bodies, one clock-master process.

    launch_scripts/run_scene.py cantilever
    launch_scripts/run_scene.py cantilever --set model.modes=6 --duration 4 --record out/bag
    launch_scripts/run_scene.py msg_scenes/cantilever.yaml -p real_time_factor:=0 -p points_publish_rate:=90
    launch_scripts/run_scene.py cantilever star_limbs --record out/run       # two bodies, one clock
    launch_scripts/run_scene.py --bodies config/two_bodies.yaml --lockstep --rtf 0.5

One scene: the node (named mdss, topics under /mdss/) gets `--params-file
config/params.yaml`, `-p scene:=SCENE`, the --set overrides (as scene_overrides) and
every -p given here. The timeline publisher (force_publisher.py timeline) publishes each
event 0.2 s of sim time before it is due, stamped with its time, so the node applies it
at the same step `mdss run` would. --record DIR writes a rosbag2 (MCAP storage, rosbags'
writer) of the node's outputs and inputs. Stops after --duration s of sim time
(default: the scene's duration), or on Ctrl-C; every process gets SIGINT and the exit
codes are checked.

Several bodies: scenes on the command line, or --bodies FILE (example:
config/two_bodies.yaml), a YAML list of bodies (or a mapping whose one key `bodies`
holds it), each with
  scene   (required) a path (relative to the file, else searched as usual) or a name in msg_scenes/;
  name    its node name (default: the scene's name, suffixed _2, _3 when it repeats);
  set     scene overrides: a mapping of dotted keys, or a list of KEY=VALUE;
  params  node parameters, a mapping (not scene, scene_overrides or clock_mode: those are
          this script's).
Each body is one node process under its own name (`-r __node:=NAME`: topics under
/NAME/, /tf child frames NAME/<domain>, /diagnostics status "NAME: simulation"), with its
own timeline publisher on /NAME/ and, with --record DIR, its own recording DIR/NAME/.
--set and -p apply to every body; a body's own `set` and `params` come after them and
win. Everything is checked before any process starts (unknown keys, a scene that does not
load with its overrides, duplicate or invalid names, unknown parameters), so a bad file
costs no model build. One scene with --clock master (or --lockstep, --rtf) runs this way
too, as one body named mdss (recording into DIR/mdss/).

The clock (--clock). /clock must have one owner: a node in clock_mode source steps on its
own timer and publishes /clock, so two of them would publish two sim times on one topic.
  source  (the default for one scene) the node steps itself and owns /clock; one body only.
  master  (the default, and the only choice, for several bodies) a clock-master process
          (this script, as a child) publishes /clock (reliable, volatile, depth 100): ticks
          at k dt, dt the smallest physics_dt of the bodies, one every dt / --rtf s of wall
          time (--rtf 1: real time), from when every node subscribed until the duration.
          Every node runs clock_mode follow: it takes the steps that fit before the master's
          time, never ahead; one that falls behind lags and catches up back to back, and
          holds no other body back. That is why follow is the default: a body slower than
          the pace shows up as clock_lag in its /diagnostics instead of losing steps.
  --lockstep  clock_mode lockstep instead: exactly one step per tick (every body must
          have the same physics_dt). The master keeps its pace and does not wait for the
          nodes: a node slower than --rtf queues the ticks, and one more than 100 ticks
          behind loses steps (a node whose first step compiled numba kernels for a new
          model lost 35 of 135 ticks so). Use it when every body keeps the pace and the
          step counts must agree tick for tick.
With a timeline, each node starts paused and its timeline publisher unpauses it once its
topics are matched; the master starts ticking only once every node is ready and running,
so sim time 0 is the same instant for every body. With --record it also waits until
each recorder matched /clock and its timeline publisher's topics, so a recording holds
every tick and every input; the recorders stop last. The run stops once the master has
ticked the duration (--duration, default: the longest of the scenes' durations) and
every node's sim time (its /diagnostics) has caught up with it, or on Ctrl-C. A running
node whose sim time stays short of the last tick for 10 s after it (lockstep ticks lost)
ends the run with exit code 1.

Unless set, ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST (DDS stays on this machine);
ROS_DOMAIN_ID is the caller's (--domain N to choose one).
"""
import argparse
import json
import math
import os
import re
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

HERE = Path(__file__).resolve().parent
REPO = HERE.parent

RECORD_TOPICS = [   # (topic, type, latched)
    ("/clock", "rosgraph_msgs/msg/Clock", True),
    ("/diagnostics", "diagnostic_msgs/msg/DiagnosticArray", False),
    ("surface/topology", "shape_msgs/msg/Mesh", True),
    ("surface/points", "sensor_msgs/msg/PointCloud2", False),
    ("surface/mesh", "shape_msgs/msg/Mesh", False),
    ("surface/marker", "visualization_msgs/msg/Marker", False),
    ("domain_poses", "geometry_msgs/msg/PoseArray", False),
    ("domain_transforms", "geometry_msgs/msg/TransformStamped", False),
    ("contacts", "sensor_msgs/msg/PointCloud2", False),
    ("wrench", "geometry_msgs/msg/WrenchStamped", False),
    ("point_forces", "sensor_msgs/msg/PointCloud2", False),
]
DEFAULT_NODE = "mdss"            # the node's own default name (mdss_ros.node.NODE_NAME)
RECORDER_MATCHED_MARK = "recorder: matched a publisher on "
TEARDOWN_S = 10.0                # the clock master exits after this long in a hung DDS teardown
DIAG_SUFFIX = ": simulation"     # the node's /diagnostics status is "<node name>: simulation"


def recorder_name(node_ns):
    """The recorder's node name: one per body, so the graph has no two nodes of one name
    (and the clock master can wait for each recorder by name)."""
    return f"{node_ns.strip('/')}_recorder"


def timeline_name(node_ns):
    """The timeline publisher's node name (force_publisher.InputPublisher's default for the
    node `node_ns`): the clock master waits for its /clock subscription by this name."""
    return f"{node_ns.strip('/').replace('/', '_')}_force_publisher"


def record_main(out, node_ns="/mdss", colliders=(), clock_volatile=False, report_matches=False):
    """Recorder process: raw CDR of RECORD_TOPICS into a rosbag2 (MCAP) until SIGINT.

    clock_volatile: subscribe /clock VOLATILE. The clock master publishes it volatile, and a
    TRANSIENT_LOCAL subscription does not match a volatile publisher (nothing would be recorded).
    report_matches: print RECORDER_MATCHED_MARK + topic each time a publisher matched.
    """
    import importlib

    import rclpy
    from rclpy.event_handler import SubscriptionEventCallbacks
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from rclpy.signals import SignalHandlerOptions
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    stop = threading.Event()
    for s in (signal.SIGINT, signal.SIGTERM):
        signal.signal(s, lambda *a: stop.set())
    rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
    node = rclpy.create_node(recorder_name(node_ns))
    typestore = get_typestore(Stores.ROS2_JAZZY)
    writer = Writer(out, version=9, storage_plugin=StoragePlugin.MCAP)
    writer.open()
    lock = threading.Lock()
    topics = list(RECORD_TOPICS)
    for c in colliders:
        topics += [(f"colliders/{c}/pose", "geometry_msgs/msg/PoseStamped", False),
                   (f"colliders/{c}/wrench", "geometry_msgs/msg/WrenchStamped", False)]
    counts = {}
    for topic, typename, latched in topics:
        full = topic if topic.startswith("/") else f"{node_ns}/{topic}"
        pkg, _, name = typename.split("/")
        cls = getattr(importlib.import_module(f"{pkg}.msg"), name)
        conn = writer.add_connection(full, typename, typestore=typestore)
        latched = latched and not (clock_volatile and full == "/clock")
        qos = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL if latched else DurabilityPolicy.VOLATILE)

        def on_raw(data, conn=conn, full=full):
            with lock:
                writer.write(conn, time.time_ns(), data)
                counts[full] = counts.get(full, 0) + 1

        def on_matched(info, full=full):
            # run_scene waits for this on the input topics before the clock master starts: an
            # input published before its recorder matched its publisher would be missing here
            if report_matches and info.current_count_change > 0:
                print(f"{RECORDER_MATCHED_MARK}{full} ({info.current_count})", flush=True)
        node.create_subscription(cls, full, on_raw, qos, raw=True,
                                 event_callbacks=SubscriptionEventCallbacks(matched=on_matched))
    node.get_logger().info(f"recording {len(topics)} topics into {out}")
    try:
        while not stop.is_set():
            rclpy.spin_once(node, timeout_sec=0.1)
    finally:
        with lock:
            writer.close()
        node.get_logger().info(f"recorded {sum(counts.values())} messages: "
                               + ", ".join(f"{k} {v}" for k, v in sorted(counts.items())))
        node.destroy_node()
        rclpy.try_shutdown()
    return 0


# ---------------------------------------------------------------------- the clock master
def tick_count(dt, until):
    """Ticks k dt, k = 1..n, of a master running until `until` s: the last one reaches it."""
    return max(1, math.ceil(until / dt - 1e-9))


def clock_master_main(dt, rtf, until, nodes, wait=120.0):
    """Clock-master process: once every node in `nodes` subscribed /clock, publish ticks
    k dt (k = 1, 2, ...) every dt / rtf s of wall time, up to `until` s (<= 0: until
    SIGINT); then keep the publisher until SIGINT. Exit 1 when the nodes do not subscribe
    within `wait` s."""
    import rclpy
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
    from rclpy.signals import SignalHandlerOptions
    from rosgraph_msgs.msg import Clock

    stop = threading.Event()
    for s in (signal.SIGINT, signal.SIGTERM):
        signal.signal(s, lambda *a: stop.set())
    rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
    node = rclpy.create_node("mdss_clock_master")
    # RELIABLE: in lockstep a lost tick is a lost step (follow's BEST_EFFORT subscription
    # matches a reliable publisher too). VOLATILE: a subscriber that joins late must not be
    # handed old ticks (a lockstep node would step once for each). Depth 100, the nodes'
    # subscription depth: a node briefly behind still gets every tick.
    qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=100, reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.VOLATILE)
    pub = node.create_publisher(Clock, "/clock", qos)

    def log(text):
        print(f"clock master: {text}", flush=True)

    code = 0
    try:
        # Wait for every node by name (the graph), and for the publisher to have matched
        # every subscription the graph shows: a tick sent before a node matched is lost to it.
        want, deadline = set(nodes), time.monotonic() + wait
        while not stop.is_set():
            infos = node.get_subscriptions_info_by_topic("/clock")
            have = {i.node_name for i in infos}
            if want <= have and pub.get_subscription_count() >= len(infos):
                break
            if time.monotonic() > deadline:
                log(f"no /clock subscription from {', '.join(sorted(want - have)) or '(matching)'} "
                    f"within {wait:g} s")
                return 1
            time.sleep(0.02)
        n = tick_count(dt, until) if until > 0 else None
        period = dt / rtf
        log(f"{len(want)} node(s) subscribed ({', '.join(sorted(want))}); ticking {dt:.9g} s of sim time every "
            f"{1e3 * period:.4g} ms of wall time" + (f" up to t = {n * dt:.9g} s" if n else " until stopped"))
        late, k, t0 = [], 0, time.monotonic()
        while not stop.is_set() and (n is None or k < n):
            k += 1
            due = t0 + k * period
            left = due - time.monotonic()
            if left > 0:
                time.sleep(left)
            if stop.is_set():
                break
            # A late tick is sent at once, not skipped: in lockstep each tick is a step.
            ns = int(round(k * dt * 1e9))
            msg = Clock()
            msg.clock.sec, msg.clock.nanosec = ns // 1_000_000_000, ns % 1_000_000_000
            pub.publish(msg)
            late.append(time.monotonic() - due)
        if late:
            late.sort()
            log(f"{'done' if n is not None and k >= n else 'stopped'}: {len(late)} ticks up to t = "
                f"{len(late) * dt:.9g} s; sent late by median {1e3 * late[len(late) // 2]:.3g} ms, "
                f"max {1e3 * late[-1]:.3g} ms")
        while not stop.is_set():
            time.sleep(0.1)
    finally:
        # Every tick is out; a DDS teardown that hangs (Fast DDS, seen once in CI) must not
        # keep run_scene waiting 30 s and then fail a run whose work is done.
        watchdog = threading.Timer(TEARDOWN_S, lambda: (log(f"DDS teardown did not finish in {TEARDOWN_S:g} s: "
                                                            "exiting without it"), os._exit(code)))
        watchdog.daemon = True
        watchdog.start()
        node.destroy_node()
        rclpy.try_shutdown()
        watchdog.cancel()
    return code


def watch_main():
    """Watcher process: one line "@diag NAME SIM_TIME STATE" per mdss /diagnostics status
    (run_scene reads the bodies' sim times from it and stays rclpy-free itself)."""
    import rclpy
    from rclpy.qos import QoSProfile
    from rclpy.signals import SignalHandlerOptions
    from diagnostic_msgs.msg import DiagnosticArray

    stop = threading.Event()
    for s in (signal.SIGINT, signal.SIGTERM):
        signal.signal(s, lambda *a: stop.set())
    rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
    node = rclpy.create_node("mdss_run_scene_watch")

    def on_diag(msg):
        for st in msg.status:
            if st.name.endswith(DIAG_SUFFIX):
                v = {kv.key: kv.value for kv in st.values}
                print(f"@diag {st.name[:-len(DIAG_SUFFIX)]} {v.get('sim_time', 'nan')} {v.get('state', '?')}",
                      flush=True)
    node.create_subscription(DiagnosticArray, "/diagnostics", on_diag, QoSProfile(depth=50))
    try:
        while not stop.is_set():
            rclpy.spin_once(node, timeout_sec=0.1)
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
    return 0


# ---------------------------------------------------------------------- bodies
BODY_KEYS = ("name", "scene", "set", "params")
# Set by this script for every body, so a body's params may not: (what to use instead)
RESERVED_PARAMS = {"scene": "the body's `scene`", "scene_overrides": "the body's `set` (or --set)",
                   "clock_mode": "--clock and --lockstep"}
NODE_NAME_RX = re.compile(r"[A-Za-z][A-Za-z0-9_]*\Z")


class BodiesError(ValueError):
    """A bad bodies file or scene list: the message says where, and what to fix."""


@dataclass
class Body:
    """One body: one node process named `name`."""

    name: str
    scene: str                 # as the node and the timeline publisher get it
    sets: list = field(default_factory=list)      # scene overrides, KEY=VALUE (common --set first)
    params: dict = field(default_factory=dict)    # the body's own node parameters
    dt: float = 0.0            # physics_dt
    duration: float = 0.0      # the scene's
    timeline: bool = False     # the scene has timeline events
    colliders: tuple = ()
    scene_name: str = ""       # the scene's `name` (the default node name)
    timeline_topics: tuple = ()  # the node's input topics its timeline publishes on (relative)


def _set_list(value, where):
    """A body's `set` as KEY=VALUE strings (a mapping's values written as YAML-readable JSON)."""
    if value is None:
        return []
    if isinstance(value, dict):
        return [f"{k}={json.dumps(v)}" for k, v in value.items()]
    if isinstance(value, list) and all(isinstance(v, str) and "=" in v for v in value):
        return list(value)
    raise BodiesError(f"{where}: `set` must be a mapping of dotted keys ({{model.modes: 6}}) or a list of "
                      f"KEY=VALUE strings, got {value!r}")


def read_bodies_file(path):
    """The entries of a bodies file, shape-checked (the scenes are loaded by plan_bodies):
    a list of {"scene", "name" (or None), "set" (KEY=VALUE list), "params" (dict), "where"}."""
    import yaml
    from mdss_ros.scene import read_yaml      # the scenes' YAML reading (5.0e6 is a number there)
    path = Path(path)
    try:
        data = read_yaml(path.read_text())
    except OSError as err:
        raise BodiesError(f"{path}: cannot read it: {err}") from err
    except yaml.YAMLError as err:
        raise BodiesError(f"{path}: not valid YAML: {err}") from err
    if isinstance(data, dict):
        extra = sorted(str(k) for k in data if k != "bodies")
        if extra:
            raise BodiesError(f"{path}: unknown top-level key(s) {', '.join(extra)} (expected a list of bodies, "
                              f"or `bodies:` holding one)")
        data = data.get("bodies")
    if not isinstance(data, list) or not data:
        raise BodiesError(f"{path}: expected a non-empty list of bodies, each a mapping with `scene` "
                          f"(and optionally name, set, params)")
    specs = []
    for i, entry in enumerate(data, 1):
        where = f"{path}: body {i}"
        if not isinstance(entry, dict):
            raise BodiesError(f"{where}: expected a mapping with `scene` (and optionally name, set, params), "
                              f"got {entry!r}")
        unknown = sorted(str(k) for k in entry if k not in BODY_KEYS)
        if unknown:
            raise BodiesError(f"{where}: unknown key(s) {', '.join(unknown)} (allowed: {', '.join(BODY_KEYS)})")
        scene = entry.get("scene")
        if not isinstance(scene, str) or not scene.strip():
            raise BodiesError(f"{where}: `scene` is missing (a scene path or a name in msg_scenes/)")
        name = entry.get("name")
        if name is not None and not isinstance(name, str):
            raise BodiesError(f"{where}: `name` must be a string, got {name!r}")
        params = entry.get("params") or {}
        if not isinstance(params, dict) or not all(isinstance(k, str) for k in params):
            raise BodiesError(f"{where}: `params` must be a mapping of node parameter names to values, "
                              f"got {params!r}")
        # A path relative to the bodies file, so the file works from any directory.
        beside = path.parent / scene
        if not Path(scene).is_absolute() and beside.is_file():
            scene = str(beside.resolve())
        specs.append({"scene": scene, "name": name, "set": _set_list(entry.get("set"), where),
                      "params": dict(params), "where": where})
    return specs


def scene_specs(scenes):
    """Entries like read_bodies_file's for scenes given on the command line."""
    return [{"scene": s, "name": None, "set": [], "params": {}, "where": f"scene {i} ({s})"}
            for i, s in enumerate(scenes, 1)]


def _param_name_ok(name, colliders):
    from mdss_ros.node import PARAMETERS
    if name in PARAMETERS or name == "use_sim_time" or name.startswith("qos_overrides."):
        return True
    m = re.fullmatch(r"colliders\.(.+)\.friction_(static|kinetic)", name)
    return bool(m and m.group(1) in colliders)


def _timeline_topics(events):
    """The input topics force_publisher.py timeline --unpause publishes on (it creates the
    wrench publisher always, the others for the events that need them)."""
    topics = ["wrench"]
    for ev in events:
        topic = {"point_force": "point_forces", "collider_pose": f"colliders/{ev.get('name')}/pose"}.get(ev["topic"])
        if topic and topic not in topics:
            topics.append(topic)
    return tuple(topics)


def _node_name(text):
    """A valid ROS node name made of text (a scene's name)."""
    name = re.sub(r"[^A-Za-z0-9_]", "_", text).strip("_") or "body"
    return name if name[0].isalpha() else f"body_{name}"


def plan_bodies(specs, common_sets=(), common_params=(), single_name=None):
    """Bodies of specs (read_bodies_file or scene_specs): scenes loaded with their
    overrides, names assigned and checked, parameters checked. BodiesError on any problem.

    common_sets: --set KEY=VALUE for every body (a body's own `set` comes after, and wins);
    common_params: -p NAME:=VALUE for every body; single_name: the name of a lone body
    that has none (run_scene keeps "mdss" for a single scene on the command line).
    """
    from mdss_ros.node import parse_overrides
    from mdss_ros.scene import load_scene, resolve_scene_path

    common_dt = 0.0
    for p in common_params:
        key, sep, value = p.partition(":=")
        key = key.strip()
        if not sep or not key:
            raise BodiesError(f"-p {p!r}: expected NAME:=VALUE")
        if key in RESERVED_PARAMS:
            raise BodiesError(f"-p {p!r}: {key} is set by run_scene for each body: use {RESERVED_PARAMS[key]}")
        if key == "physics_dt":
            try:
                common_dt = float(value)
            except ValueError:
                raise BodiesError(f"-p {p!r}: physics_dt must be a number") from None
    bodies = []
    for spec in specs:
        where = spec["where"]
        sets = list(common_sets) + list(spec["set"])
        try:
            overrides = parse_overrides(sets)
            scene = load_scene(spec["scene"], overrides or None)
            path = resolve_scene_path(spec["scene"])
        except Exception as err:     # noqa: BLE001 - SceneError, ValueError, ...: reported as is
            raise BodiesError(f"{where}: {err}") from err
        colliders = tuple(scene["colliders"])
        for key, value in spec["params"].items():
            if key in RESERVED_PARAMS:
                raise BodiesError(f"{where}: params: {key} is set by run_scene: use {RESERVED_PARAMS[key]}")
            if not _param_name_ok(key, colliders):
                raise BodiesError(f"{where}: params: unknown node parameter {key!r} "
                                  f"(see mdss_ros/node.py PARAMETERS)")
            if isinstance(value, dict) or value is None:
                raise BodiesError(f"{where}: params: {key} must be a number, string, bool or list, got {value!r}")
        dt = spec["params"].get("physics_dt") or common_dt or scene.dt
        if not isinstance(dt, (int, float)) or isinstance(dt, bool) or dt <= 0:
            raise BodiesError(f"{where}: params: physics_dt must be a number > 0, got {dt!r}")
        # The node gets an absolute path: it runs in the repository, not in the caller's cwd.
        bodies.append(Body(name=spec["name"], scene=str(path.resolve()), sets=sets, params=dict(spec["params"]),
                           dt=float(dt), duration=float(scene["duration"]), timeline=bool(scene["timeline"]),
                           colliders=colliders, scene_name=scene.name,
                           timeline_topics=_timeline_topics(scene["timeline"])))
    # Names: explicit ones are checked and kept, then each unnamed body gets its scene's
    # name, suffixed _2, _3 ... past any name already taken.
    taken = {}
    for spec, body in zip(specs, bodies):
        if body.name is None:
            continue
        if not NODE_NAME_RX.match(body.name):
            raise BodiesError(f"{spec['where']}: name {body.name!r} is not a valid ROS node name "
                              f"(a letter, then letters, digits and _)")
        if body.name in taken:
            raise BodiesError(f"{spec['where']}: duplicate name {body.name!r} (also {taken[body.name]}): "
                              f"two nodes of one name would share their topics")
        taken[body.name] = spec["where"]
    for spec, body in zip(specs, bodies):
        if body.name is not None:
            continue
        if single_name and len(bodies) == 1:
            body.name = single_name
            continue
        base = _node_name(body.scene_name)
        name, k = base, 1
        while name in taken:
            k += 1
            name = f"{base}_{k}"
        body.name = name
        taken[name] = spec["where"]
    return bodies


# ---------------------------------------------------------------------- processes
def _env(domain):
    env = dict(os.environ)
    env.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    if domain is not None:
        env["ROS_DOMAIN_ID"] = str(domain)
    env["PYTHONUNBUFFERED"] = "1"
    env["PYTHONPATH"] = os.pathsep.join([str(REPO)] + [p for p in env.get("PYTHONPATH", "").split(os.pathsep) if p])
    env.setdefault("NUMBA_CACHE_DIR", str(REPO / ".venv" / "numba_cache"))
    return env


# The node logs this once its model is built and its topics exist (MdssNode.__init__).
READY_MARK = "]: ready: "
# force_publisher.py timeline --unpause logs this once it unpaused the node.
UNPAUSED_MARK = "inputs matched: physics unpaused"
MASTER_DONE_MARK = "clock master: done"
STALL_S = 10.0   # s of wall time a running body may show no progress after the master's last tick
RECORDER_WAIT_S = 30.0   # s the clock master's start waits for the recorders to match the inputs


def _relay(name, proc, ready=None):
    for line in proc.stdout:
        sys.stdout.write(f"[{name}] {line}")
        sys.stdout.flush()
        if ready is not None and READY_MARK in line:
            ready.set()


def _pump(name, proc, marks=(), on_line=None, echo=True):
    """Relay proc's lines prefixed [name] (echo), set the Event of each (text, Event) in
    marks whose text a line holds, and hand every line to on_line."""
    for line in proc.stdout:
        if echo:
            sys.stdout.write(f"[{name}] {line}")
            sys.stdout.flush()
        for text, event in marks:
            if text in line:
                event.set()
        if on_line is not None:
            on_line(line)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__)
    ap.add_argument("scenes", nargs="*", metavar="scene",
                    help="scene path or name in msg_scenes/ (several: one body each)")
    ap.add_argument("--bodies", metavar="FILE", help="a multi-body file (see above; config/two_bodies.yaml)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="scene override (repeat)")
    ap.add_argument("-p", action="append", default=[], metavar="NAME:=VALUE", help="node parameter (repeat)")
    ap.add_argument("--params-file", default=str(REPO / "config" / "params.yaml"))
    ap.add_argument("--duration", type=float, default=None,
                    help="s of sim time (default: the scene's; several bodies: the longest)")
    ap.add_argument("--record", metavar="DIR",
                    help="record a rosbag2 (MCAP) into DIR (must not exist); several bodies: DIR/<name>/ each")
    ap.add_argument("--no-timeline", action="store_true", help="do not play the scenes' timelines")
    ap.add_argument("--clock", choices=("source", "master"), default=None,
                    help="who owns /clock: the node (source; one body only) or a clock-master process "
                         "(master); default: source for one body, master for several")
    ap.add_argument("--lockstep", action="store_true",
                    help="clock master: the nodes run clock_mode lockstep (default: follow)")
    ap.add_argument("--rtf", type=float, default=None,
                    help="clock master: sim s per wall s of its ticks (default 1: real time)")
    ap.add_argument("--domain", type=int, default=None, help="ROS_DOMAIN_ID for every process")
    # internal: the helper processes this script starts
    ap.add_argument("--recorder", metavar="DIR", help=argparse.SUPPRESS)
    ap.add_argument("--recorder-ns", default="/mdss", help=argparse.SUPPRESS)
    ap.add_argument("--recorder-clock-volatile", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--recorder-report-matches", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--colliders", default="", help=argparse.SUPPRESS)
    ap.add_argument("--clock-master-process", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--dt", type=float, default=None, help=argparse.SUPPRESS)
    ap.add_argument("--until", type=float, default=0.0, help=argparse.SUPPRESS)
    ap.add_argument("--nodes", default="", help=argparse.SUPPRESS)
    ap.add_argument("--watch-diagnostics", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args(sys.argv[1:] if argv is None else argv)
    if args.recorder:
        return record_main(args.recorder, node_ns=args.recorder_ns,
                           colliders=[c for c in args.colliders.split(",") if c],
                           clock_volatile=args.recorder_clock_volatile,
                           report_matches=args.recorder_report_matches)
    if args.clock_master_process:
        return clock_master_main(args.dt, args.rtf or 1.0, args.until, [n for n in args.nodes.split(",") if n])
    if args.watch_diagnostics:
        return watch_main()
    if args.bodies and args.scenes:
        ap.error("give scenes or --bodies FILE, not both")
    if not args.bodies and not args.scenes:
        ap.error("give a scene (a path or a name in msg_scenes/), several, or --bodies FILE")
    if args.clock == "source" and (args.lockstep or args.rtf is not None):
        ap.error("--lockstep and --rtf are for --clock master (in source, the node's own -p real_time_factor)")
    if args.rtf is not None and args.rtf <= 0:
        ap.error("--rtf must be > 0: the clock master ticks on wall time")
    if args.duration is not None and args.duration <= 0:
        ap.error("--duration must be > 0 (s of sim time)")
    master_asked = args.clock == "master" or args.lockstep or args.rtf is not None
    if not args.bodies and len(args.scenes) == 1 and not master_asked:
        args.scene = args.scenes[0]
        return run_single(args)     # one scene: the behaviour this script always had

    sys.path.insert(0, str(REPO))
    try:
        specs = read_bodies_file(args.bodies) if args.bodies else scene_specs(args.scenes)
        bodies = plan_bodies(specs, args.set, args.p, single_name=None if args.bodies else DEFAULT_NODE)
        clock = args.clock or ("master" if len(bodies) > 1 or master_asked else "source")
        check_run(bodies, clock, args.lockstep, args.record)
    except BodiesError as err:
        print(f"run_scene: {err}", file=sys.stderr, flush=True)
        return 2
    return run_bodies(args, bodies, clock)


def check_run(bodies, clock, lockstep, record):
    """BodiesError when the bodies cannot run this way (before anything starts)."""
    if clock == "source" and len(bodies) > 1:
        raise BodiesError(f"{len(bodies)} bodies with --clock source: each node would publish its own /clock; "
                          f"use --clock master (the default for several bodies)")
    if lockstep and len({round(b.dt, 15) for b in bodies}) > 1:
        raise BodiesError("--lockstep takes one step per tick, so every body needs the same physics_dt; got "
                          + ", ".join(f"{b.name} {b.dt:.9g}" for b in bodies) + " (use follow, the default)")
    if record:
        there = [str(Path(record) / b.name) for b in bodies if (Path(record) / b.name).exists()]
        if there:
            raise BodiesError(f"--record: {', '.join(there)} already exist(s) (each body records into a new folder)")


def run_bodies(args, bodies, clock):
    """One node per body, its timeline publisher and recorder; with clock master, one clock
    master and every node in clock_mode follow (or lockstep). Returns the exit code."""
    sys.path.insert(0, str(HERE))
    from launch_testing import param_arg

    master = clock == "master"
    dt = min(b.dt for b in bodies)
    duration = args.duration if args.duration is not None else max(b.duration for b in bodies)
    rtf = args.rtf if args.rtf is not None else 1.0
    mode = "lockstep" if args.lockstep else "follow"
    user_paused = any(p.split(":=")[0].strip() == "start_paused" for p in args.p)
    if master and any(p.split(":=")[0].strip() == "real_time_factor" for p in args.p + [
            k + ":=" for b in bodies for k in b.params]):
        print(f"run_scene: the nodes ignore real_time_factor in clock_mode {mode}; --rtf sets the master's pace",
              flush=True)
    env, py = _env(args.domain), sys.executable
    procs = []                 # (label, Popen), stopped in reverse order, the recorders last
    me = str(HERE / "run_scene.py")

    def start(label, argv, marks=(), on_line=None, echo=True, track=True):
        p = subprocess.Popen([py] + argv, env=env, cwd=str(REPO), stdout=subprocess.PIPE,
                             stderr=subprocess.STDOUT, text=True, bufsize=1)
        threading.Thread(target=_pump, args=(label, p, marks, on_line, echo), daemon=True).start()
        if track:
            procs.append((label, p))
        return p

    print(f"run_scene: {len(bodies)} {'body' if len(bodies) == 1 else 'bodies'}: " + ", ".join(f"{b.name} ({Path(b.scene).stem})" for b in bodies)
          + (f"; clock master at {1 / dt:.6g} Hz, real-time factor {rtf:g}, nodes in clock_mode {mode}"
             if master else "; the node owns /clock (clock_mode source)")
          + f"; {duration:g} s of sim time", flush=True)
    sim, moved = {}, {}        # body name -> last sim time from /diagnostics, wall time it last changed
    running = {}               # body name -> its state is "running" (not paused)

    def on_watch(line):
        parts = line.split()
        if len(parts) >= 4 and parts[0] == "@diag":
            try:
                t = float(parts[2])
            except ValueError:
                return
            if sim.get(parts[1]) != t:
                moved[parts[1]] = time.monotonic()
            sim[parts[1]], running[parts[1]] = t, parts[3] == "running"
    watch = start("watch", [me, "--watch-diagnostics"], on_line=on_watch, echo=False, track=False)
    clock_watch = None if master else _ClockWatch(env, py)
    timeline = {b.name: b.timeline and not args.no_timeline for b in bodies}
    # As with one scene: a node with a timeline starts paused and its timeline publisher
    # unpauses it once its topics are matched (unless the user asked for start_paused).
    unpause = {b.name: timeline[b.name] and not user_paused and "start_paused" not in b.params for b in bodies}
    # With a clock master, the timeline's first input comes only after the master started;
    # the master waits until each recorder matched the timeline publisher's publishers, so
    # the recording has every input (an unpausing timeline publisher creates them all first).
    recorded = {}              # (body name, topic) -> Event: its recorder matched a publisher on it
    if args.record:
        Path(args.record).mkdir(parents=True, exist_ok=True)
        for b in bodies:
            marks = []
            if master and unpause[b.name]:
                for topic in b.timeline_topics:
                    if topic.startswith("colliders/") and topic.split("/")[1] not in b.colliders:
                        continue            # not a topic the recorder subscribes
                    recorded[b.name, topic] = threading.Event()
                    marks.append((f"{RECORDER_MATCHED_MARK}/{b.name}/{topic} (", recorded[b.name, topic]))
            start(f"{b.name}/recorder", [me, "--recorder", str(Path(args.record) / b.name),
                                         "--recorder-ns", f"/{b.name}", "--colliders", ",".join(b.colliders)]
                  + (["--recorder-clock-volatile", "--recorder-report-matches"] if master else []), marks=marks)
    nodes, ready, unpaused, timelines = {}, {}, {}, {}
    for b in bodies:
        argv = ["-m", "mdss_ros.node", "--ros-args", "--params-file", args.params_file,
                "-r", f"__node:={b.name}", "-p", param_arg("scene", b.scene)]
        if master:
            argv += ["-p", f"clock_mode:={mode}"]
        if unpause[b.name]:
            argv += ["-p", "start_paused:=true"]
        if b.sets:
            argv += ["-p", "scene_overrides:=" + json.dumps(b.sets)]
        for p in args.p:
            argv += ["-p", p]
        for k, v in b.params.items():
            argv += ["-p", param_arg(k, v)]
        ready[b.name], unpaused[b.name] = threading.Event(), threading.Event()
        if not unpause[b.name]:
            unpaused[b.name].set()
        timelines[b.name] = ([str(HERE / "force_publisher.py"), "--node", f"/{b.name}", "timeline", b.scene]
                             + (["--unpause"] if unpause[b.name] else [])) if timeline[b.name] else None
        nodes[b.name] = start(b.name, argv, marks=[(READY_MARK, ready[b.name])])

    interrupted = threading.Event()
    for s in (signal.SIGINT, signal.SIGTERM):
        signal.signal(s, lambda *a: interrupted.set())
    master_done, master_done_at, master_proc, tl_procs = threading.Event(), None, None, {}
    t_last = tick_count(dt, duration) * dt if master else duration
    phase, code, unpaused_at, missing = "build", 0, None, []
    t_start, heartbeat = time.monotonic(), time.monotonic()
    try:
        while not interrupted.is_set():
            gone = [n for n, p in nodes.items() if p.poll() is not None]
            if gone:
                for n in gone:
                    print(f"run_scene: node {n} exited with {nodes[n].returncode}"
                          + ("" if ready[n].is_set() else " before it was ready (see its messages above)"),
                          flush=True)
                code = nodes[gone[0]].returncode or 1
                break
            bad = [n for n, p in tl_procs.items() if p.poll() not in (None, 0) and not unpaused[n].is_set()]
            if bad:
                print(f"run_scene: the timeline publisher of {', '.join(bad)} failed before unpausing its node",
                      flush=True)
                code = 1
                break
            if master_proc is not None and master_proc.poll() is not None and not master_done.is_set():
                print(f"run_scene: the clock master exited with {master_proc.returncode}", flush=True)
                code = master_proc.returncode or 1
                break
            now = time.monotonic()
            if master_done.is_set() and master_done_at is None:
                master_done_at = now
            if phase == "build":
                if all(e.is_set() for e in ready.values()):
                    print(f"run_scene: every node ready after {now - t_start:.1f} s", flush=True)
                    for b in bodies:
                        if timelines[b.name]:
                            tl_procs[b.name] = start(f"{b.name}/timeline", timelines[b.name],
                                                     marks=[(UNPAUSED_MARK, unpaused[b.name])])
                    phase = "unpause"
                elif now - heartbeat >= 10.0:
                    heartbeat = now
                    print(f"run_scene: waiting for {', '.join(n for n, e in ready.items() if not e.is_set())} to "
                          f"build their models ({now - t_start:.0f} s so far; the first run of a scene builds "
                          f"and caches its precompute)", flush=True)
            if phase == "unpause" and all(e.is_set() for e in unpaused.values()):
                unpaused_at = unpaused_at or now
                missing = [f"/{n}/{t}" for (n, t), e in recorded.items() if not e.is_set()]
                if missing and now - unpaused_at > RECORDER_WAIT_S:
                    print(f"run_scene: the recorders matched no publisher on {', '.join(missing)} within "
                          f"{RECORDER_WAIT_S:g} s: starting the clock anyway (inputs there may be missing from "
                          f"the recordings)", flush=True)
                    missing = []
            if phase == "unpause" and all(e.is_set() for e in unpaused.values()) and not missing:
                if master:
                    # Only now: a node still paused would ignore (lockstep) or race to catch up
                    # with (follow) the first ticks.
                    # the recorders too: a tick sent before a recorder matched would be missing
                    # from its recording
                    # and the timeline publishers: one whose /clock subscription matches late
                    # in the run publishes its inputs late or never (seen under load: a 1 s
                    # run ended before its t = 0.5 s wrench went out)
                    wait_for = ([b.name for b in bodies] + [timeline_name(b.name) for b in bodies if timelines[b.name]]
                                + ([recorder_name(b.name) for b in bodies] if args.record else []))
                    master_proc = start("clock", [me, "--clock-master-process", "--dt", repr(dt), "--rtf", repr(rtf),
                                                  "--until", repr(duration), "--nodes", ",".join(wait_for)],
                                        marks=[(MASTER_DONE_MARK, master_done)])
                phase = "run"
            if phase == "run":
                if master:
                    # done once the master sent its last tick and every node took the steps
                    # that fit before it (a node behind catches up back to back)
                    behind = [b.name for b in bodies if not sim.get(b.name, -1.0) + b.dt > t_last + 1e-8]
                    if master_done.is_set() and not behind:
                        print(f"run_scene: every body reached t = {t_last:.6g} s: stopping", flush=True)
                        break
                    # A running node that no longer moves, after the master's last tick, will not
                    # get there: in lockstep it lost ticks (it fell more than 100 behind).
                    stuck = [n for n in behind if master_done.is_set() and running.get(n)
                             and now - max(moved.get(n, now), master_done_at or now) > STALL_S]
                    if stuck:
                        print(f"run_scene: {', '.join(stuck)} stopped short of the master's last tick "
                              f"{t_last:.6g} s (bodies behind it: "
                              f"{', '.join(f'{n} at t = {sim.get(n, 0.0):.6g} s' for n in behind)})"
                              + (": in lockstep a node more than 100 ticks behind the master loses ticks; use "
                                 "follow (the default) or a lower --rtf" if args.lockstep else ""), flush=True)
                        code = 1
                        break
                else:
                    t = clock_watch.time()
                    if t is not None and t >= duration:
                        print(f"run_scene: sim time {t:.3f} s >= duration {duration:g} s: stopping", flush=True)
                        break
                if now - heartbeat >= 10.0:
                    heartbeat = now
                    print("run_scene: sim time " + ", ".join(f"{b.name} {sim.get(b.name, 0.0):.3f} s"
                                                             for b in bodies), flush=True)
            time.sleep(0.1)
    finally:
        if clock_watch is not None:
            clock_watch.close()
        # The recorders stop once everything they record has exited: what the nodes publish
        # up to their end (the last /diagnostics) is in the recordings. The clock master
        # stops after them, when no subscriber of its reliable /clock writer is left: once
        # (CI, session 14) its DDS teardown, with both recorders still subscribed, hung until
        # it was killed 30 s later.
        kind = lambda label: 2 if label == "clock" else 1 if label.endswith("/recorder") else 0
        for k in range(3):
            code = stop_processes([x for x in procs if kind(x[0]) == k], code)
        if watch.poll() is None:
            watch.send_signal(signal.SIGINT)
            try:
                watch.wait(10)
            except subprocess.TimeoutExpired:
                watch.kill()
    return code


def run_single(args):
    """One scene, the node owning /clock (clock_mode source): this script's original path."""
    sys.path.insert(0, str(REPO))
    from mdss_ros.scene import load_scene
    from mdss_ros.node import parse_overrides
    overrides = parse_overrides(args.set)
    scene = load_scene(args.scene, overrides or None)
    duration = args.duration if args.duration is not None else scene["duration"]
    env, py = _env(args.domain), sys.executable
    procs = []

    def start(name, argv, ready=None):
        p = subprocess.Popen([py] + argv, env=env, cwd=str(REPO), stdout=subprocess.PIPE,
                             stderr=subprocess.STDOUT, text=True, bufsize=1)
        threading.Thread(target=_relay, args=(name, p, ready), daemon=True).start()
        procs.append((name, p))
        return p

    node_argv = ["-m", "mdss_ros.node", "--ros-args", "--params-file", args.params_file,
                 "-p", f"scene:={args.scene}"]
    timeline = bool(scene["timeline"]) and not args.no_timeline
    # With a timeline, the node starts paused and the timeline publisher unpauses it once its
    # topics are matched, so sim time 0 is the same instant for both (unless the user asked
    # for start_paused, and then unpausing is theirs).
    user_paused = any(p.split(":=")[0].strip() == "start_paused" for p in args.p)
    unpause = timeline and not user_paused
    if unpause:
        node_argv += ["-p", "start_paused:=true"]
    if args.set:
        node_argv += ["-p", "scene_overrides:=[" + ", ".join(f'"{s}"' for s in args.set) + "]"]
    for p in args.p:
        node_argv += ["-p", p]
    if args.record:
        start("recorder", [str(HERE / "run_scene.py"), "--recorder", args.record,
                           "--colliders", ",".join(scene["colliders"])])
    ready = threading.Event()
    node = start("node", node_argv, ready)
    # The timeline starts once the node is ready, however long its model build (precompute,
    # numba compilation) takes: a fixed wait raced the build and lost on a loaded machine.

    interrupted = threading.Event()
    for s in (signal.SIGINT, signal.SIGTERM):
        signal.signal(s, lambda *a: interrupted.set())
    clock = _ClockWatch(env, py)
    code = 0
    t_start, heartbeat = time.monotonic(), time.monotonic()
    try:
        while not interrupted.is_set():
            if node.poll() is not None:
                print(f"run_scene: the node exited with {node.returncode}"
                      + ("" if ready.is_set() else " before it was ready (see its messages above)"),
                      flush=True)
                code = node.returncode or 1
                break
            if not ready.is_set():
                if time.monotonic() - heartbeat >= 10.0:
                    heartbeat = time.monotonic()
                    print(f"run_scene: waiting for the node to build its model "
                          f"({heartbeat - t_start:.0f} s so far; the first run of a scene builds and "
                          f"caches its precompute)", flush=True)
                time.sleep(0.1)
                continue
            if timeline:
                timeline = False
                print(f"run_scene: node ready after {time.monotonic() - t_start:.1f} s; "
                      f"starting the timeline publisher", flush=True)
                start("timeline", [str(HERE / "force_publisher.py"), "timeline", args.scene]
                      + (["--unpause"] if unpause else []))
            t = clock.time()
            if t is not None and t >= duration:
                print(f"run_scene: sim time {t:.3f} s >= duration {duration:g} s: stopping", flush=True)
                break
            time.sleep(0.1)
    finally:
        clock.close()
        code = stop_processes(procs, code)
    return code


def stop_processes(procs, code=0):
    """SIGINT to each (name, Popen), last started first, then wait (kill after 30 s); the
    first non-zero exit code becomes `code` if it was 0."""
    for name, p in reversed(procs):
        if p.poll() is None:
            p.send_signal(signal.SIGINT)
    for name, p in reversed(procs):
        try:
            rc = p.wait(30)
        except subprocess.TimeoutExpired:
            p.kill()
            rc = p.wait()
        print(f"run_scene: {name} exited with {rc}", flush=True)
        if rc != 0:
            code = code or rc
    return code


class _ClockWatch:
    """The sim time from /clock, read in a small child process (keeps this one rclpy-free)."""

    SCRIPT = ("import rclpy,sys\n"
              "from rclpy.qos import QoSProfile,DurabilityPolicy\n"
              "from rosgraph_msgs.msg import Clock\n"
              "rclpy.init(); n=rclpy.create_node('mdss_run_scene_clock')\n"
              "q=QoSProfile(depth=1,durability=DurabilityPolicy.TRANSIENT_LOCAL)\n"
              "n.create_subscription(Clock,'/clock',lambda m: print(m.clock.sec+1e-9*m.clock.nanosec,flush=True),q)\n"
              "try:\n    rclpy.spin(n)\nexcept Exception:\n    pass\n")

    def __init__(self, env, py):
        self.t = None
        self.p = subprocess.Popen([py, "-c", self.SCRIPT], env=env, stdout=subprocess.PIPE,
                                  stderr=subprocess.DEVNULL, text=True, bufsize=1)
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self):
        for line in self.p.stdout:
            try:
                self.t = float(line)
            except ValueError:
                pass

    def time(self):
        return self.t

    def close(self):
        if self.p.poll() is None:
            self.p.send_signal(signal.SIGINT)
            try:
                self.p.wait(10)
            except subprocess.TimeoutExpired:
                self.p.kill()


if __name__ == "__main__":
    sys.exit(main())
