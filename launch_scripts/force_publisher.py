#!/usr/bin/env python3
"""Publish inputs to a running mdss node from the command line (another ROS process).

    # a held wrench on handle "tip", stamped with the current sim time, then exit
    force_publisher.py wrench tip --force 0 0 -20
    # the same, taking effect exactly at t = 0.5 s of sim time
    force_publisher.py wrench tip --force 0 0 -20 --at 0.5
    # a sine of amplitude 20 N at 1 Hz, republished at 30 Hz of sim time for 5 s
    force_publisher.py wrench tip --force 0 0 -20 --pattern sine --frequency 1 --rate 30 --for 5
    # a point force held until ~/clear_forces (duration < 0)
    force_publisher.py points --point 1.0 0.05 0.1 --force 0 0 -5 --duration -1
    # a collider pose stream: from (0.5, 0, 0.3) down at 0.05 m/s, 90 Hz, for 2 s
    force_publisher.py collider ball --position 0.5 0 0.3 --velocity 0 0 -0.05 --rate 90 --for 2
    # a scene's timeline as messages, each published `--ahead` s of sim time before
    # it is due and stamped with its time, so the node applies it at that exact step
    force_publisher.py timeline cantilever [--all-now]

Stamps: inputs stamped with sim time t take effect at the step starting at t (see
mdss_ros/node.py); `--at T` stamps T; otherwise a message is stamped with the sim time
it is meant for (patterns, timelines) or the latest /clock (`--unstamped`: stamp 0,
applied at the node's next step). Patterns run on /clock, so a paused node pauses them.
Exits 0 when done (all messages acknowledged), or on SIGINT/SIGTERM.
"""
import argparse
import math
import os
import signal
import sys
import threading
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402
import rclpy  # noqa: E402
from rclpy.duration import Duration  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.node import Node  # noqa: E402
from rclpy.qos import QoSProfile, ReliabilityPolicy  # noqa: E402
from rclpy.signals import SignalHandlerOptions  # noqa: E402

from geometry_msgs.msg import PoseStamped, WrenchStamped  # noqa: E402
from rosgraph_msgs.msg import Clock  # noqa: E402
from std_srvs.srv import Trigger  # noqa: E402

from mdss_ros.ros import convert  # noqa: E402
from mdss_ros.record.ros_messages import cdr_bytes  # noqa: E402

POINT_FORCE_DTYPE = np.dtype([(f, "<f4") for f in ("x", "y", "z", "fx", "fy", "fz", "duration")])


class InputPublisher(Node):
    """Publishers for the inputs of the mdss node named `target` (e.g. "/mdss")."""

    def __init__(self, target="/mdss", name=None):
        # named after its body (/mdss -> mdss_force_publisher), so several bodies' publishers
        # are told apart in the graph
        name = name or f"{target.strip('/').replace('/', '_') or 'mdss'}_force_publisher"
        super().__init__(name)
        self.target = target.rstrip("/")
        self.qos = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
        self.pubs = {}
        self.sim_time = None
        self._clock_event = threading.Condition()
        self.create_subscription(Clock, "/clock", self._on_clock, QoSProfile(depth=10))

    def _on_clock(self, msg):
        with self._clock_event:
            self.sim_time = convert.seconds(msg.clock)
            self._clock_event.notify_all()

    def _pub(self, topic, msg_type):
        if topic not in self.pubs:
            self.pubs[topic] = self.create_publisher(msg_type, f"{self.target}/{topic}", self.qos)
        return self.pubs[topic]

    def wait_for_node(self, topic, msg_type, timeout):
        pub = self._pub(topic, msg_type)
        deadline = time.monotonic() + timeout
        while pub.get_subscription_count() == 0:
            if time.monotonic() > deadline:
                raise TimeoutError(f"no subscriber on {pub.topic_name} after {timeout} s: is the node running "
                                   f"(and in ROS_DOMAIN_ID {os.environ.get('ROS_DOMAIN_ID', '0')})?")
            time.sleep(0.02)
        return pub

    def wrench(self, handle, force, torque=(0, 0, 0), stamp=0.0):
        msg = convert.wrench_stamped(stamp, handle, list(force) + list(torque))
        self._pub("wrench", WrenchStamped).publish(cdr_bytes(msg))     # the package's messages are rosbags'

    def point_forces(self, points, forces, durations, stamp=0.0, frame_id=""):
        rec = np.zeros(len(points), dtype=POINT_FORCE_DTYPE)
        p, f = np.asarray(points, float).reshape(-1, 3), np.asarray(forces, float).reshape(-1, 3)
        for i, k in enumerate("xyz"):
            rec[k], rec["f" + k] = p[:, i], f[:, i]
        rec["duration"] = durations
        from sensor_msgs.msg import PointCloud2
        self._pub("point_forces", PointCloud2).publish(cdr_bytes(convert.cloud(stamp, frame_id, rec)))

    def collider_pose(self, name, position, orientation=(0, 0, 0, 1), stamp=0.0, frame_id=""):
        msg = convert.pose_stamped(stamp, frame_id, position, orientation)
        self._pub(f"colliders/{name}/pose", PoseStamped).publish(cdr_bytes(msg))

    def _call(self, srv_type, name, timeout):
        """Call the node's service ~/name with an empty request; its response (TimeoutError
        when the service is missing or does not answer in time)."""
        client = self.create_client(srv_type, f"{self.target}/{name}")
        try:
            if not client.wait_for_service(timeout_sec=timeout):
                raise TimeoutError(f"{self.target}/{name} is not available")
            fut = client.call_async(srv_type.Request())
            deadline = time.monotonic() + timeout
            while not fut.done() and time.monotonic() < deadline:
                time.sleep(0.005)
            if not fut.done():
                raise TimeoutError(f"{self.target}/{name} did not answer in {timeout} s")
            return fut.result()
        finally:
            self.destroy_client(client)

    def clear_forces(self, timeout=10.0):
        return self._call(Trigger, "clear_forces", timeout)

    def unpause(self, timeout=10.0):
        """Call ~/unpause_physics (std_srvs/Empty) and wait for the answer."""
        from std_srvs.srv import Empty
        self._call(Empty, "unpause_physics", timeout)

    def flush(self, timeout=10.0):
        """Wait until every subscriber acknowledged everything published (reliable QoS)."""
        return all(p.wait_for_all_acked(Duration(seconds=timeout)) for p in self.pubs.values())

    def wait_clock(self, t=None, timeout=None):
        """Sim time once /clock reaches t (None: the first /clock); None on timeout."""
        deadline = None if timeout is None else time.monotonic() + timeout
        with self._clock_event:
            while self.sim_time is None or (t is not None and self.sim_time < t - 1e-9):
                left = None if deadline is None else deadline - time.monotonic()
                if left is not None and left <= 0:
                    return None
                self._clock_event.wait(0.2 if left is None else min(left, 0.2))
            return self.sim_time


def _pattern_times(args, t0):
    """Sim times to publish at: once, or every 1/rate s for `for` s from t0."""
    if args.pattern == "once":
        return [t0]
    n = max(1, int(math.floor(args.duration_for * args.rate + 1e-9)) + 1)
    return [t0 + k / args.rate for k in range(n)]


def _scale(args, t, t0):
    if args.pattern == "sine":
        return math.sin(2 * math.pi * args.frequency * (t - t0))
    return 1.0


def run_pattern(node, args, send):
    """Publish send(t, stamp, scale) at the pattern's sim times t, each --ahead before it is due."""
    if args.pattern == "once" and (args.unstamped or args.at is not None):
        send(args.at or 0.0, 0.0 if args.unstamped else args.at, 1.0)   # no need to know the time
        return
    if args.at is not None:
        t0 = args.at
    else:
        now = node.wait_clock(timeout=args.wait)
        if now is None:
            raise TimeoutError("no /clock: is the node running?")
        t0 = now
    for t in _pattern_times(args, t0):
        if node.wait_clock(t - args.ahead) is None:
            return
        send(t, 0.0 if args.unstamped else t, _scale(args, t, t0))


def play_timeline(node, events, ahead, all_now=False):
    """Publish a scene's timeline events (mdss_ros.timeline format) stamped with their t."""
    for ev in sorted(events, key=lambda e: e["t"]):
        t, topic = float(ev["t"]), ev["topic"]
        if not all_now:
            node.wait_clock(t - (0.0 if topic == "clear_forces" else ahead))
        if topic == "wrench":
            node.wrench(ev["frame_id"], ev.get("force", (0, 0, 0)), ev.get("torque", (0, 0, 0)), stamp=t)
        elif topic == "point_force":
            node.point_forces([ev["point"]], [ev["force"]], [ev.get("duration", 0.0)], stamp=t)
        elif topic == "collider_pose":
            node.collider_pose(ev["name"], ev["position"], ev.get("orientation", (0, 0, 0, 1)), stamp=t)
        elif topic == "clear_forces":   # a service call: at the first step after t, not stamped
            node.clear_forces()
        node.get_logger().info(f"published {topic} for t = {t:g} s: "
                               f"{ {k: v for k, v in ev.items() if k not in ('t', 'topic')} }")


def parse_args(argv):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__)
    ap.add_argument("--node", default="/mdss", help="namespace of the mdss node's topics (default /mdss)")
    ap.add_argument("--wait", type=float, default=60.0, help="s to wait for the node (default 60)")
    sub = ap.add_subparsers(dest="what", required=True)

    def pattern_opts(p):
        p.add_argument("--pattern", choices=("once", "constant", "sine"), default="once")
        p.add_argument("--rate", type=float, default=30.0, help="messages per s of sim time (patterns)")
        p.add_argument("--for", dest="duration_for", type=float, default=1.0, help="s of sim time (patterns)")
        p.add_argument("--frequency", type=float, default=1.0, help="Hz of the sine pattern")
        p.add_argument("--at", type=float, default=None, help="sim time of the first message (its stamp)")
        p.add_argument("--ahead", type=float, default=0.1, help="publish this many s of sim time early")
        p.add_argument("--unstamped", action="store_true", help="stamp 0: applied at the node's next step")

    w = sub.add_parser("wrench", help="a wrench on a handle (frame_id = handle)")
    w.add_argument("handle")
    w.add_argument("--force", type=float, nargs=3, default=(0.0, 0.0, 0.0), metavar=("FX", "FY", "FZ"))
    w.add_argument("--torque", type=float, nargs=3, default=(0.0, 0.0, 0.0), metavar=("TX", "TY", "TZ"))
    pattern_opts(w)
    p = sub.add_parser("points", help="one or more point forces (repeat --point/--force)")
    p.add_argument("--point", type=float, nargs=3, action="append", required=True, metavar=("X", "Y", "Z"))
    p.add_argument("--force", type=float, nargs=3, action="append", required=True, metavar=("FX", "FY", "FZ"))
    p.add_argument("--duration", type=float, default=0.0, help="0: one step, > 0: s, < 0: until clear_forces")
    pattern_opts(p)
    c = sub.add_parser("collider", help="a pose stream for a collider")
    c.add_argument("name")
    c.add_argument("--position", type=float, nargs=3, required=True, metavar=("X", "Y", "Z"))
    c.add_argument("--velocity", type=float, nargs=3, default=(0.0, 0.0, 0.0), metavar=("VX", "VY", "VZ"))
    c.add_argument("--orientation", type=float, nargs=4, default=(0.0, 0.0, 0.0, 1.0),
                   metavar=("QX", "QY", "QZ", "QW"))
    pattern_opts(c)
    t = sub.add_parser("timeline", help="play a scene's timeline")
    t.add_argument("scene", help="scene path or name in msg_scenes/")
    t.add_argument("--ahead", type=float, default=0.2, help="publish this many s of sim time early")
    t.add_argument("--all-now", action="store_true", help="publish every event at once (future stamps)")
    t.add_argument("--unpause", action="store_true",
                   help="call ~/unpause_physics once the node's input topics are matched "
                        "(for a node started with start_paused)")
    sub.add_parser("clear", help="call ~/clear_forces")
    return ap.parse_args(argv)


def main(argv=None):
    args = parse_args(sys.argv[1:] if argv is None else argv)
    stop = threading.Event()

    def on_signal(signum, frame):
        stop.set()
        raise KeyboardInterrupt

    for s in (signal.SIGINT, signal.SIGTERM):
        signal.signal(s, on_signal)
    rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
    node = InputPublisher(args.node)
    executor = SingleThreadedExecutor()
    executor.add_node(node)

    def spin():
        while not stop.is_set():
            executor.spin_once(timeout_sec=0.05)

    spinner = threading.Thread(target=spin, daemon=True)
    spinner.start()
    code = 0
    try:
        if args.what == "clear":
            print(node.clear_forces(args.wait).message)
        elif args.what == "timeline":
            from mdss_ros.scene import load_scene
            scene = load_scene(args.scene)
            node.wait_for_node("wrench", WrenchStamped, args.wait)
            if args.unpause:
                # every input topic the timeline uses is matched before physics starts, so
                # the first event cannot be late whatever discovery takes
                from sensor_msgs.msg import PointCloud2
                for ev in scene["timeline"]:
                    if ev["topic"] == "point_force":
                        node.wait_for_node("point_forces", PointCloud2, args.wait)
                    elif ev["topic"] == "collider_pose":
                        node.wait_for_node(f"colliders/{ev['name']}/pose", PoseStamped, args.wait)
                node.unpause(args.wait)
                node.get_logger().info("inputs matched: physics unpaused")
            if not args.all_now:
                node.wait_clock(timeout=args.wait)
            play_timeline(node, scene["timeline"], args.ahead, args.all_now)
        elif args.what == "wrench":
            node.wait_for_node("wrench", WrenchStamped, args.wait)
            run_pattern(node, args, lambda t, st, k: node.wrench(args.handle, k * np.asarray(args.force),
                                                                 k * np.asarray(args.torque), stamp=st))
        elif args.what == "points":
            from sensor_msgs.msg import PointCloud2
            if len(args.point) != len(args.force):
                raise SystemExit("force_publisher: give one --force per --point")
            node.wait_for_node("point_forces", PointCloud2, args.wait)
            run_pattern(node, args, lambda t, st, k: node.point_forces(
                args.point, k * np.asarray(args.force), [args.duration] * len(args.point), stamp=st))
        elif args.what == "collider":
            node.wait_for_node(f"colliders/{args.name}/pose", PoseStamped, args.wait)
            t_first = []

            def send(t, st, k):
                if not t_first:
                    t_first.append(t)
                p = np.asarray(args.position) + np.asarray(args.velocity) * (t - t_first[0])
                node.collider_pose(args.name, p, args.orientation, stamp=st)
            run_pattern(node, args, send)
        node.flush()
        node.get_logger().info("done: every message acknowledged")
    except KeyboardInterrupt:
        pass
    except TimeoutError as err:
        node.get_logger().error(str(err))
        code = 1
    finally:
        for s in (signal.SIGINT, signal.SIGTERM):
            signal.signal(s, signal.SIG_IGN)
        stop.set()
        spinner.join(2.0)
        executor.remove_node(node)
        node.destroy_node()
        rclpy.try_shutdown()
    return code


if __name__ == "__main__":
    sys.exit(main())
