#!/usr/bin/env python3
"""Benchmarks of the ROS node (numbers for the README's "Measured" section).

    launch_scripts/bench_node.py latency [SCENE ...] [--seconds 10] [--set KEY=VALUE]
    launch_scripts/bench_node.py outputs [--sizes 10000,50000]
    launch_scripts/bench_node.py all --json out/bench_node.json

latency: the node runs SCENE (default: every scene in msg_scenes/) at 90 Hz physics
(real_time_factor 1) with 30 Hz points, in its own process; a client process publishes
a wrench every 0.25 s stamped with the next step's sim time and notes the wall time;
it then measures, in its own process, the wall time until the first message that
reflects the input arrives: /clock (the step that applied it), ~/domain_poses (a
per-step output) and ~/surface/points (30 Hz, so up to 33 ms of waiting for the grid
is included). The real-time factor is the median of /diagnostics over the run, and
the achievable one is measured again with real_time_factor 0 (as fast as possible).

outputs: the cost per frame of building and publishing each output type for a
synthetic surface of S vertices (2S triangles, 8 domains), with a subscriber process
receiving every topic: in-process timings of the node's own encoders, plus the
shape_msgs/Mesh built from Python objects for comparison.
"""
import argparse
import json
import os
import statistics
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
sys.path.insert(0, str(HERE))
sys.path.insert(0, str(REPO))

from launch_testing import Launch  # noqa: E402

def _median(xs):
    return statistics.median(xs) if xs else float("nan")


def _pct(xs, q):
    if not xs:
        return float("nan")
    xs = sorted(xs)
    return xs[min(len(xs) - 1, int(round(q * (len(xs) - 1))))]


# ---------------------------------------------------------------------- latency client
def client_main(seconds, period, out, handle):
    """Publishes stamped wrenches, measures receipt of the outputs reflecting them."""
    import threading

    import rclpy
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from geometry_msgs.msg import PoseArray, WrenchStamped
    from rosgraph_msgs.msg import Clock
    from sensor_msgs.msg import PointCloud2

    from mdss_ros.ros import convert

    rclpy.init()
    node = rclpy.create_node("mdss_bench_client")
    rel = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
    lock = threading.Lock()
    state = {"clock": None, "dt": None, "pending": [], "clock_wall": {}}

    def on_stamp(kind, t):
        now = time.time()
        with lock:
            for p in state["pending"]:
                if kind not in p["recv"] and t >= p["stamp"] + 0.5 * state["dt"] - 1e-9:
                    p["recv"][kind] = now

    def on_clock(msg):
        t = convert.seconds(msg.clock)
        with lock:
            if state["clock"] is not None and state["dt"] is None and t > state["clock"]:
                state["dt"] = t - state["clock"]
            state["clock"] = t
            for p in state["pending"]:      # the wall time the sim reached the input's stamp
                if p["at_stamp"] is None and t >= p["stamp"] - 1e-9:
                    p["at_stamp"] = time.time()
        if state["dt"]:
            on_stamp("clock", t)

    node.create_subscription(Clock, "/clock", on_clock, QoSProfile(depth=10, durability=DurabilityPolicy.TRANSIENT_LOCAL))
    node.create_subscription(PoseArray, "/mdss/domain_poses", lambda m: on_stamp("poses", convert.seconds(m.header.stamp)), rel)
    node.create_subscription(PointCloud2, "/mdss/surface/points", lambda m: on_stamp("points", convert.seconds(m.header.stamp)), rel)
    pub = node.create_publisher(WrenchStamped, "/mdss/wrench", rel)
    spin = threading.Thread(target=lambda: rclpy.spin(node), daemon=True)
    spin.start()
    deadline = time.time() + 120
    while (state["dt"] is None or pub.get_subscription_count() == 0) and time.time() < deadline:
        time.sleep(0.01)
    t_end, k, clock_start = time.time() + seconds, 0, (state["clock"], time.time())
    while time.time() < t_end:
        with lock:
            # the next step's start: clock now + the sim time elapsed since it was received
            s = state["clock"] + state["dt"]      # due at the step after the coming one
            wall = time.time()
            p = {"stamp": s, "wall": wall, "recv": {}, "at_stamp": None}
            state["pending"].append(p)
        force = (0.0, 0.0, -10.0 if k % 2 == 0 else 0.0)
        pub.publish(convert.wrench_stamped(s, handle, list(force) + [0, 0, 0]))
        k += 1
        time.sleep(period)
    time.sleep(0.5)
    sim_elapsed = state["clock"] - clock_start[0]
    wall_elapsed = time.time() - clock_start[1]
    with lock:
        res = {"dt": state["dt"], "inputs": len(state["pending"]), "rtf_client": sim_elapsed / wall_elapsed}
        for kind in ("clock", "poses", "points"):
            # from the moment the sim time reached the input's stamp (its /clock arrived here)
            lat = [1e3 * (p["recv"][kind] - p["at_stamp"]) for p in state["pending"]
                   if kind in p["recv"] and p["at_stamp"] is not None]
            pub = [1e3 * (p["recv"][kind] - p["wall"]) for p in state["pending"] if kind in p["recv"]]
            res[kind] = {"n": len(lat), "median_ms": _median(lat), "p90_ms": _pct(lat, 0.9),
                         "max_ms": max(lat) if lat else float("nan"),
                         "from_publish_median_ms": _median(pub)}
    Path(out).write_text(json.dumps(res, indent=2))
    node.destroy_node()
    rclpy.try_shutdown()
    return 0


def bench_latency(scenes, seconds, overrides, workdir):
    rows = []
    for scene in scenes:
        for rtf in (1.0, 0.0):
            with Launch(Path(workdir) / f"latency_{Path(scene).stem}_{rtf:g}") as launch:
                params = dict(scene=scene, real_time_factor=rtf, points_publish_rate=30.0, pose_publish_rate=90.0,
                              mesh_publish_rate=0.0, marker_publish_rate=0.0, diagnostics_rate=1.0)
                if overrides:
                    params["scene_overrides"] = overrides
                node = launch.node(**params)
                node.wait_for(r"\] \[mdss\]: ready:", timeout=3600)
                probe = launch.probe()
                probe.sub("/diagnostics", "diagnostic_msgs/msg/DiagnosticArray")
                out = launch.dir / "client.json"
                from mdss_ros.scene import load_scene
                handle = sorted(load_scene(scene)["handles"])[0]
                client = launch.script("client", Path(__file__).resolve(), "--client", str(out),
                                       "--seconds", str(seconds), "--handle", handle)
                client.wait(seconds + 180)
                diags = probe.get("/diagnostics")
                launch.shutdown()
            res = json.loads(out.read_text())
            values = [{kv["key"]: kv["value"] for kv in d["status"][0]["values"]} for d in diags]
            running = [v for v in values if v["state"] == "running" and int(v["steps_in_window"]) > 0]
            built = [line for line in node.lines if "model built" in line]
            row = {"scene": Path(scene).stem, "real_time_factor_target": rtf, "dt": res["dt"],
                   "rtf_median": _median([float(v["real_time_factor"]) for v in running]),
                   "rtf_client": res["rtf_client"],
                   "step_ms_median": _median([float(v["step_ms_median"]) for v in running]),
                   "cycle_ms_median": _median([float(v["cycle_ms_median"]) for v in running]),
                   "inputs": res["inputs"], "inputs_late": int(values[-1]["inputs_late"]) if values else None,
                   "model": built[0].split("]: ", 1)[-1] if built else ""}
            for kind in ("clock", "poses", "points"):
                row[f"latency_{kind}_median_ms"] = res[kind]["median_ms"]
                row[f"latency_{kind}_p90_ms"] = res[kind]["p90_ms"]
                row[f"latency_{kind}_from_publish_median_ms"] = res[kind]["from_publish_median_ms"]
            rows.append(row)
            print(json.dumps(row), flush=True)
    return rows


# ---------------------------------------------------------------------- output costs
def synthetic_surface(n_target):
    """A closed tube surface with about n_target vertices: positions (S, 3), triangles (2S, 3)."""
    import numpy as np
    ring = max(8, int(round((n_target / 4) ** 0.5)))
    rows = max(2, n_target // ring)
    th = np.linspace(0, 2 * np.pi, ring, endpoint=False)
    z = np.linspace(0, 1, rows)
    x = np.stack([np.repeat(z, ring), np.tile(0.1 * np.cos(th), rows), np.tile(0.1 * np.sin(th), rows)], 1)
    i, j = np.meshgrid(np.arange(rows - 1), np.arange(ring), indexing="ij")
    a = i * ring + j
    b = i * ring + (j + 1) % ring
    c, d = a + ring, b + ring
    tri = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([b, d, c], -1).reshape(-1, 3)])
    return x, tri


def bench_outputs(sizes, frames, workdir):
    import numpy as np
    import rclpy
    from rclpy.context import Context
    from rclpy.signals import SignalHandlerOptions
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from geometry_msgs.msg import PoseArray, TransformStamped
    from sensor_msgs.msg import PointCloud2
    from shape_msgs.msg import Mesh, MeshTriangle
    from visualization_msgs.msg import Marker

    from mdss_ros.ros import convert

    rows = []
    with Launch(Path(workdir) / "outputs") as launch:
        os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = launch.env["ROS_AUTOMATIC_DISCOVERY_RANGE"]
        ctx = Context()
        rclpy.init(context=ctx, domain_id=launch.domain_id, signal_handler_options=SignalHandlerOptions.NO)
        node = rclpy.create_node("mdss_bench_outputs", context=ctx)
        qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.VOLATILE)
        pubs = {"points": node.create_publisher(PointCloud2, "/bench/points", qos),
                "mesh": node.create_publisher(Mesh, "/bench/mesh", qos),
                "mesh_objects": node.create_publisher(Mesh, "/bench/mesh_objects", qos),
                "marker": node.create_publisher(Marker, "/bench/marker", qos),
                "poses": node.create_publisher(PoseArray, "/bench/poses", qos),
                "transforms": node.create_publisher(TransformStamped, "/bench/transforms", qos)}
        types = {"points": "sensor_msgs/msg/PointCloud2", "mesh": "shape_msgs/msg/Mesh",
                 "mesh_objects": "shape_msgs/msg/Mesh", "marker": "visualization_msgs/msg/Marker",
                 "poses": "geometry_msgs/msg/PoseArray", "transforms": "geometry_msgs/msg/TransformStamped"}
        sink = launch.script("sink", Path(__file__).resolve(), "--sink", json.dumps(
            {f"/bench/{k}": v for k, v in types.items()}))
        sink.wait_for("sink ready", timeout=120)
        deadline = time.time() + 60
        while any(p.get_subscription_count() == 0 for p in pubs.values()) and time.time() < deadline:
            time.sleep(0.05)
        for n in sizes:
            x, tri = synthetic_surface(n)
            dom = (np.arange(len(x)) * 8 // len(x)).astype(np.int64)
            poses = np.tile([0, 0, 0, 0, 0, 0, 1.0], (8, 1))
            names = [f"domain_{i}" for i in range(8)]
            sp, me, mk = convert.SurfacePoints(dom), convert.MeshEncoder(tri), convert.MarkerEncoder(tri, dom)
            tri_objs = [MeshTriangle(vertex_indices=t) for t in tri.tolist()]
            jobs = {
                "points": lambda t, x: pubs["points"].publish(sp.message(t, "world", x)),
                "mesh": lambda t, x: pubs["mesh"].publish(me.encode(x)),
                "mesh_objects": lambda t, x: pubs["mesh_objects"].publish(
                    Mesh(triangles=tri_objs, vertices=[convert.point(p) for p in x])),
                "marker": lambda t, x: pubs["marker"].publish(mk.encode(t, "world", x)),
                "poses": lambda t, x: pubs["poses"].publish(convert.pose_array(t, "world", poses)),
                "transforms": lambda t, x: [pubs["transforms"].publish(m) for m in
                                            convert.domain_transforms(t, "world", names, poses)],
            }
            row = {"surface_vertices": len(x), "triangles": len(tri)}
            for name, job in jobs.items():
                ms = []
                k_frames = frames if name != "mesh_objects" else max(3, frames // 5)
                for k in range(k_frames + 2):
                    xk = x + 1e-3 * k
                    t0 = time.perf_counter()
                    job(k / 30.0, xk)
                    if k >= 2:
                        ms.append(1e3 * (time.perf_counter() - t0))
                    time.sleep(0.02)       # let the sink take it (reliable, depth 10)
                row[f"{name}_ms"] = _median(ms)
            row["points_bytes"] = len(x) * 16
            row["mesh_bytes"] = len(me.encode(x))
            row["marker_bytes"] = len(mk.encode(0.0, "world", x))
            rows.append(row)
            print(json.dumps(row), flush=True)
        node.destroy_node()
        rclpy.try_shutdown(context=ctx)
    return rows


def sink_main(topics):
    import importlib

    import rclpy
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    rclpy.init()
    node = rclpy.create_node("mdss_bench_sink")
    for topic, typ in json.loads(topics).items():
        pkg, _, name = typ.split("/")
        cls = getattr(importlib.import_module(f"{pkg}.msg"), name)
        node.create_subscription(cls, topic, lambda m: None, QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE),
                                 raw=True)
    print("sink ready", flush=True)
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, Exception):
        pass
    return 0


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__)
    ap.add_argument("what", nargs="?", choices=("latency", "outputs", "all"), default="all")
    ap.add_argument("scenes", nargs="*", help="scenes for latency (default: all of msg_scenes/)")
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    ap.add_argument("--sizes", default="10000,50000")
    ap.add_argument("--frames", type=int, default=20)
    ap.add_argument("--json", default=None)
    ap.add_argument("--workdir", default=None)
    ap.add_argument("--client", default=None, help=argparse.SUPPRESS)
    ap.add_argument("--handle", default="tip", help=argparse.SUPPRESS)
    ap.add_argument("--sink", default=None, help=argparse.SUPPRESS)
    args = ap.parse_args(sys.argv[1:] if argv is None else argv)
    if args.client:
        return client_main(args.seconds, 0.25, args.client, args.handle)
    if args.sink:
        return sink_main(args.sink)
    import tempfile
    workdir = args.workdir or tempfile.mkdtemp(prefix="mdss_bench_node_")
    out = {}
    if args.what in ("latency", "all"):
        scenes = args.scenes or sorted(str(p) for p in (REPO / "msg_scenes").glob("*.yaml"))
        out["latency"] = bench_latency(scenes, args.seconds, args.set, workdir)
    if args.what in ("outputs", "all"):
        out["outputs"] = bench_outputs([int(s) for s in args.sizes.split(",")], args.frames, workdir)
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(out, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
