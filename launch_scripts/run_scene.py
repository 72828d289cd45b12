#!/usr/bin/env python3
"""Run a scene the ROS way: the mdss node, a publisher process playing the scene's
timeline as ROS messages (other nodes publishing forces), optionally a recorder.

    launch_scripts/run_scene.py cantilever
    launch_scripts/run_scene.py cantilever --set model.modes=6 --duration 4 --record out/bag
    launch_scripts/run_scene.py msg_scenes/cantilever.yaml -p real_time_factor:=0 -p points_publish_rate:=90

The node gets `--params-file config/params.yaml`, `-p scene:=SCENE`, the --set
overrides (as scene_overrides) and every -p given here. The timeline publisher
(force_publisher.py timeline) publishes each event 0.2 s of sim time before it is due,
stamped with its time, so the node applies it at the same step `mdss run` would.
--record DIR writes a rosbag2 (MCAP storage, rosbags' writer) of the node's outputs
and inputs. Stops after --duration s of sim time (default: the scene's duration), or
on Ctrl-C; every process gets SIGINT and the exit codes are checked.

Unless set, ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST (DDS stays on this machine);
ROS_DOMAIN_ID is the caller's (--domain N to choose one).
"""
import argparse
import os
import signal
import subprocess
import sys
import threading
import time
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


def record_main(out, node_ns="/mdss", colliders=()):
    """Recorder process: raw CDR of RECORD_TOPICS into a rosbag2 (MCAP) until SIGINT."""
    import importlib

    import rclpy
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from rclpy.signals import SignalHandlerOptions
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    stop = threading.Event()
    for s in (signal.SIGINT, signal.SIGTERM):
        signal.signal(s, lambda *a: stop.set())
    rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
    node = rclpy.create_node("mdss_recorder")
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
        qos = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL if latched else DurabilityPolicy.VOLATILE)

        def on_raw(data, conn=conn, full=full):
            with lock:
                writer.write(conn, time.time_ns(), data)
                counts[full] = counts.get(full, 0) + 1
        node.create_subscription(cls, full, on_raw, qos, raw=True)
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


def _relay(name, proc, ready=None):
    for line in proc.stdout:
        sys.stdout.write(f"[{name}] {line}")
        sys.stdout.flush()
        if ready is not None and READY_MARK in line:
            ready.set()


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__)
    ap.add_argument("scene", nargs="?", help="scene path or name in msg_scenes/")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="scene override (repeat)")
    ap.add_argument("-p", action="append", default=[], metavar="NAME:=VALUE", help="node parameter (repeat)")
    ap.add_argument("--params-file", default=str(REPO / "config" / "params.yaml"))
    ap.add_argument("--duration", type=float, default=None, help="s of sim time (default: the scene's)")
    ap.add_argument("--record", metavar="DIR", help="record a rosbag2 (MCAP) into DIR (must not exist)")
    ap.add_argument("--no-timeline", action="store_true", help="do not play the scene's timeline")
    ap.add_argument("--domain", type=int, default=None, help="ROS_DOMAIN_ID for every process")
    ap.add_argument("--recorder", metavar="DIR", help=argparse.SUPPRESS)   # internal: the recorder process
    ap.add_argument("--colliders", default="", help=argparse.SUPPRESS)
    args = ap.parse_args(sys.argv[1:] if argv is None else argv)
    if args.recorder:
        return record_main(args.recorder, colliders=[c for c in args.colliders.split(",") if c])
    if not args.scene:
        ap.error("give a scene (a path or a name in msg_scenes/)")

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
