#!/usr/bin/env python3
"""Benchmarks of the ROS node (numbers for the README's "Measured" section).

    launch_scripts/bench_node.py latency [SCENE ...] [--seconds 10] [--set KEY=VALUE] [--record]
    launch_scripts/bench_node.py outputs [--sizes 10000,50000]
    launch_scripts/bench_node.py bodies [--scene cantilever] [--counts 1,2,4] [--seconds 20] [--json FILE]
    launch_scripts/bench_node.py all --json out/bench_node.json        (latency and outputs)

latency: the node runs SCENE (default: every scene in msg_scenes/) at 90 Hz physics
(real_time_factor 1) with 30 Hz points, in its own process; a client process publishes
a wrench every 0.25 s stamped with the next step's sim time and notes the wall time;
it then measures, in its own process, the wall time until the first message that
reflects the input arrives: /clock (the step that applied it), ~/domain_poses (a
per-step output) and ~/surface/points (30 Hz, so up to 33 ms of waiting for the grid
is included). The real-time factor is the median of /diagnostics over the run, and
the achievable one is measured again with real_time_factor 0 (as fast as possible).
With --record the node also records, as launch_scripts/demo.sh has it do: an MCAP bag of
every input and output (mcap_path) and a rerun file (rerun_mode file), both in the run's
work folder.

outputs: the cost per frame of building and publishing each output type for a
synthetic surface of S vertices (2S triangles, 8 domains), with a subscriber process
receiving every topic: in-process timings of the node's own encoders, plus the
shape_msgs/Mesh built from Python objects for comparison.

bodies: the real-time factor of N body nodes sharing this machine, for each N of
--counts. N node processes of --scene (--set overrides), named body_1..body_N, each in
clock_mode follow (several nodes in clock_mode source would be several /clock owners),
points at 30 Hz of sim time, the other outputs at the node's defaults, /diagnostics at
1 Hz of wall time. The nodes start one after the other (N concurrent model builds would
only slow each other). One clock-master process (run_scene.py's) then ticks /clock at
90 Hz in real time; after --warmup s (default 5) the run lasts --seconds and every
node's /diagnostics windows in it are kept. Per node (the table's columns):
  rtf med, rtf min   the node's own real_time_factor of each 1 s window (sim time
                     advanced / wall time, measured in the node): median and minimum;
  rtf all            sim_time advanced / receipt wall time, first to last window;
  master             the same for the master's time (clock_master_time): 1 unless the
                     master itself was starved;
  step ms            median of the windows' step_ms_median;
  p90w               90th percentile of the windows' step_ms_median (the node reports a
                     median and a max per window, not every step: this is the p90 over
                     windows, not over steps);
  max                the largest step_ms_max;
  lag end, lag max   clock_lag (master time - sim time) in the last window, and its largest;
  cpu %              CPU time of the node's process tree over the run / wall time
                     (100 % = one core);
and, for each N, os.getloadavg() at the end and the CPU % that processes outside this
benchmark used during the run (the machine's other work). In follow a node can never
pass the master, so rtf tops out at 1; a node that cannot keep up shows rtf < 1 and a
growing lag.
"""
import argparse
import json
import os
import shutil
import statistics
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
sys.path.insert(0, str(HERE))
sys.path.insert(0, str(REPO))

from launch_testing import Launch  # noqa: E402

def _wire(msg):
    """What rclpy's Publisher.publish takes: an rclpy message or CDR bytes. A rosbags
    typestore object (what mdss_ros.ros.convert builds when the node publishes CDR) is
    serialised here, as the node does, so its cost is in the timing."""
    if isinstance(msg, (bytearray, memoryview)):
        return bytes(msg)
    if isinstance(msg, bytes) or not hasattr(msg, "__msgtype__"):
        return msg
    from mdss_ros.ros import convert
    return bytes(convert.TYPESTORE.serialize_cdr(msg, msg.__msgtype__))


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
        pub.publish(_wire(convert.wrench_stamped(s, handle, list(force) + [0, 0, 0])))
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


def bench_latency(scenes, seconds, overrides, workdir, record=False):
    from mdss_ros.scene import load_scene
    rows = []
    for scene in scenes:
        handles = sorted(load_scene(scene)["handles"])
        if not handles:
            # grasp_lift's inputs are collider poses: no wrench to stamp. Skipped with a
            # line rather than an IndexError half-way through the default run over every scene.
            print(f"bench_node latency: {Path(scene).stem} skipped: it has no handles, and the latency "
                  f"client pushes a wrench on one", file=sys.stderr)
            continue
        for rtf in (1.0, 0.0):
            with Launch(Path(workdir) / f"latency_{Path(scene).stem}_{rtf:g}") as launch:
                params = dict(scene=scene, real_time_factor=rtf, points_publish_rate=30.0, pose_publish_rate=90.0,
                              mesh_publish_rate=0.0, marker_publish_rate=0.0, diagnostics_rate=1.0)
                if overrides:
                    params["scene_overrides"] = overrides
                if record:
                    # A new bag folder each run (a reused --workdir holds the last one, which the
                    # node would refuse, then run without recording).
                    shutil.rmtree(launch.dir / "bag", ignore_errors=True)
                    params.update(mcap_path=str(launch.dir / "bag"), rerun_mode="file",
                                  rerun_path=str(launch.dir / "run.rrd"))
                node = launch.node(**params)
                node.wait_for(r"\] \[mdss\]: ready:", timeout=3600)
                probe = launch.probe()
                probe.sub("/diagnostics", "diagnostic_msgs/msg/DiagnosticArray")
                out = launch.dir / "client.json"
                client = launch.script("client", Path(__file__).resolve(), "--client", str(out),
                                       "--seconds", str(seconds), "--handle", handles[0])
                client.wait(seconds + 180)
                diags = probe.get("/diagnostics")
                launch.shutdown()
            res = json.loads(out.read_text())
            values = [{kv["key"]: kv["value"] for kv in d["status"][0]["values"]} for d in diags]
            running = [v for v in values if v["state"] == "running" and int(v["steps_in_window"]) > 0]
            built = [line for line in node.lines if "model built" in line]
            recorded = record and any((launch.dir / "bag").glob("*.mcap")) and (launch.dir / "run.rrd").is_file()
            if record and not recorded:
                print(f"bench_node latency: {Path(scene).stem}: --record asked, but the node wrote no bag or rerun "
                      f"file (its log: {launch.dir})", file=sys.stderr)
            row = {"scene": Path(scene).stem, "real_time_factor_target": rtf, "record": bool(recorded), "dt": res["dt"],
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
    from geometry_msgs.msg import Point, PoseArray, TransformStamped
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
                "points": lambda t, x: pubs["points"].publish(_wire(sp.message(t, "world", x))),
                "mesh": lambda t, x: pubs["mesh"].publish(_wire(me.encode(x))),
                "mesh_objects": lambda t, x: pubs["mesh_objects"].publish(
                    Mesh(triangles=tri_objs, vertices=[Point(x=p[0], y=p[1], z=p[2]) for p in x.tolist()])),
                "marker": lambda t, x: pubs["marker"].publish(_wire(mk.encode(t, "world", x))),
                "poses": lambda t, x: pubs["poses"].publish(_wire(convert.pose_array(t, "world", poses))),
                "transforms": lambda t, x: [pubs["transforms"].publish(_wire(m)) for m in
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
            row["mesh_bytes"] = len(_wire(me.encode(x)))
            row["marker_bytes"] = len(_wire(mk.encode(0.0, "world", x)))
            rows.append(row)
            print(json.dumps(row), flush=True)
        node.destroy_node()
        rclpy.try_shutdown(context=ctx)
    return rows


# ---------------------------------------------------------------------- several bodies
def _cpu_seconds(pid):
    """utime + stime (s) of pid and its descendants (a process may re-execute itself)."""
    tick, total, todo = os.sysconf("SC_CLK_TCK"), 0.0, [pid]
    while todo:
        p = todo.pop()
        try:
            fields = Path(f"/proc/{p}/stat").read_text().rsplit(")", 1)[1].split()
            total += (int(fields[11]) + int(fields[12])) / tick        # utime, stime
            for task in Path(f"/proc/{p}/task").iterdir():
                todo += [int(c) for c in (task / "children").read_text().split()]
        except (OSError, ValueError, IndexError):
            continue
    return total


def _other_cpu_seconds():
    """{pid: utime + stime (s)} of every process outside this one's tree: the machine's
    other work, which the bodies share the CPUs with."""
    tick, procs = os.sysconf("SC_CLK_TCK"), {}
    for d in os.listdir("/proc"):
        if d.isdigit():
            try:
                f = Path(f"/proc/{d}/stat").read_text().rsplit(")", 1)[1].split()
                procs[int(d)] = (int(f[1]), (int(f[11]) + int(f[12])) / tick)      # ppid, cpu
            except (OSError, ValueError, IndexError):
                pass
    mine, grown = {os.getpid()}, True
    while grown:
        grown = False
        for pid, (ppid, _) in procs.items():
            if ppid in mine and pid not in mine:
                mine.add(pid)
                grown = True
    return {pid: cpu for pid, (_, cpu) in procs.items() if pid not in mine}


def _rate(points):
    """(value advanced) / (wall time) between the first and last (wall, value) points."""
    if len(points) < 2 or points[-1][0] <= points[0][0]:
        return float("nan")
    return (points[-1][1] - points[0][1]) / (points[-1][0] - points[0][0])


def bench_bodies(scene, counts, seconds, overrides, workdir, warmup=5.0, clock_hz=90.0, points_hz=30.0):
    from launch_testing import status_values
    rows = []
    for n in counts:
        names = [f"body_{i}" for i in range(1, n + 1)]
        with Launch(Path(workdir) / f"bodies_{Path(scene).stem}_{n}") as launch:
            nodes = {}
            for name in names:
                params = dict(scene=scene, clock_mode="follow", points_publish_rate=points_hz, diagnostics_rate=1.0)
                if overrides:
                    params["scene_overrides"] = overrides
                nodes[name] = launch.node(name=name, ros_args=["-r", f"__node:={name}"], **params)
                nodes[name].wait_for(rf"\] \[{name}\]: ready:", timeout=3600)
            probe = launch.probe()
            probe.sub("/diagnostics", "diagnostic_msgs/msg/DiagnosticArray")
            master = launch.script("clock", HERE / "run_scene.py", "--clock-master-process",
                                   "--dt", repr(1.0 / clock_hz), "--rtf", "1", "--until", "0",
                                   "--nodes", ",".join(names))
            master.wait_for(r"clock master: .* subscribed", timeout=120)
            time.sleep(warmup)
            t0, w0 = time.time(), time.monotonic()
            cpu0 = {name: _cpu_seconds(p.popen.pid) for name, p in nodes.items()}
            other0 = _other_cpu_seconds()
            time.sleep(seconds)
            t1, w1 = time.time(), time.monotonic()
            cpu1 = {name: _cpu_seconds(p.popen.pid) for name, p in nodes.items()}
            other1 = _other_cpu_seconds()
            # a process that started during the run counts whole, one that ended is missed
            other = 100.0 * sum(c - other0.get(pid, 0.0) for pid, c in other1.items()) / (w1 - w0)
            load = os.getloadavg()
            diags = probe.get("/diagnostics")
            codes = launch.shutdown()
        for name in names:
            win = [(d["_recv"], v) for d in diags if t0 <= d["_recv"] <= t1
                   for v in [status_values(d, f"{name}: simulation")] if v and v["state"] == "running"]
            steps = [float(v["step_ms_median"]) for _, v in win if int(v["steps_in_window"]) > 0]
            rtf = [float(v["real_time_factor"]) for _, v in win]
            lag = [float(v.get("clock_lag", "nan")) for _, v in win]
            rows.append({
                "scene": Path(scene).stem, "bodies": n, "node": name, "windows": len(win),
                "rtf_median": _median(rtf), "rtf_min": min(rtf) if rtf else float("nan"),
                "rtf_overall": _rate([(t, float(v["sim_time"])) for t, v in win]),
                "master_rtf": _rate([(t, float(v["clock_master_time"])) for t, v in win]),
                "step_ms_median": _median(steps), "step_ms_p90_of_windows": _pct(steps, 0.9),
                "step_ms_max": max((float(v["step_ms_max"]) for _, v in win), default=float("nan")),
                "cycle_ms_median": _median([float(v["cycle_ms_median"]) for _, v in win
                                            if int(v["steps_in_window"]) > 0]),
                "clock_lag_end": lag[-1] if lag else float("nan"), "clock_lag_max": max(lag, default=float("nan")),
                "cpu_percent": 100.0 * (cpu1[name] - cpu0[name]) / (w1 - w0),
                "dofs": int(win[-1][1]["dofs"]) if win else None,
                "surface_vertices": int(win[-1][1]["surface_vertices"]) if win else None,
                "loadavg_end": list(load), "exit_code": codes.get(name), "measured_wall": [t0, t1],
                "other_cpu_percent": other,
            })
        print(_bodies_table([r for r in rows if r["bodies"] == n]), flush=True)
    return rows


def _bodies_table(rows):
    head = ("bodies", "node", "rtf med", "rtf min", "rtf all", "master", "step ms", "p90w", "max",
            "lag end", "lag max", "cpu %")
    lines = [" | ".join(head)]
    for i, r in enumerate(rows):
        lines.append(" | ".join([str(r["bodies"]), r["node"], f"{r['rtf_median']:.3f}", f"{r['rtf_min']:.3f}",
                                 f"{r['rtf_overall']:.3f}", f"{r['master_rtf']:.3f}",
                                 f"{r['step_ms_median']:.2f}", f"{r['step_ms_p90_of_windows']:.2f}",
                                 f"{r['step_ms_max']:.1f}", f"{round(r['clock_lag_end'], 3) + 0.0:.3f}",
                                 f"{round(r['clock_lag_max'], 3) + 0.0:.3f}", f"{r['cpu_percent']:.0f}"]))
        if i + 1 == len(rows) or rows[i + 1]["bodies"] != r["bodies"]:
            la = r["loadavg_end"]
            lines.append(f"  load average at the end of the {r['bodies']}-body run: {la[0]:.2f} {la[1]:.2f} "
                         f"{la[2]:.2f} (1, 5, 15 min; {os.cpu_count()} CPUs); CPU used by other work on the "
                         f"machine meanwhile: {r['other_cpu_percent']:.0f} %")
    return "\n".join(lines)


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
    ap.add_argument("what", nargs="?", choices=("latency", "outputs", "bodies", "all"), default="all")
    ap.add_argument("scenes", nargs="*", help="scenes for latency (default: all of msg_scenes/)")
    ap.add_argument("--seconds", type=float, default=None, help="s measured (default: latency 10, bodies 20)")
    ap.add_argument("--scene", default="cantilever", help="bodies: the scene of every body")
    ap.add_argument("--counts", default="1,2,4", help="bodies: numbers of body nodes, one run each")
    ap.add_argument("--warmup", type=float, default=5.0, help="bodies: s of wall time before measuring")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    ap.add_argument("--sizes", default="10000,50000")
    ap.add_argument("--frames", type=int, default=20)
    ap.add_argument("--record", action="store_true", help="latency: the node records an MCAP bag and a rerun file "
                                                          "(latency only)")
    ap.add_argument("--json", default=None)
    ap.add_argument("--workdir", default=None)
    ap.add_argument("--client", default=None, help=argparse.SUPPRESS)
    ap.add_argument("--handle", default="tip", help=argparse.SUPPRESS)
    ap.add_argument("--sink", default=None, help=argparse.SUPPRESS)
    args = ap.parse_args(sys.argv[1:] if argv is None else argv)
    if args.client:
        return client_main(args.seconds if args.seconds is not None else 10.0, 0.25, args.client, args.handle)
    if args.sink:
        return sink_main(args.sink)
    import tempfile
    workdir = args.workdir or tempfile.mkdtemp(prefix="mdss_bench_node_")
    out = {}
    if args.what in ("latency", "all"):
        scenes = args.scenes or sorted(str(p) for p in (REPO / "msg_scenes").glob("*.yaml"))
        out["latency"] = bench_latency(scenes, args.seconds if args.seconds is not None else 10.0, args.set, workdir,
                                       record=args.record)
    if args.what in ("outputs", "all"):
        out["outputs"] = bench_outputs([int(s) for s in args.sizes.split(",")], args.frames, workdir)
    if args.what == "bodies":
        out["bodies"] = {"scene": args.scene, "overrides": args.set, "counts": [int(c) for c in args.counts.split(",")],
                         "seconds": args.seconds if args.seconds is not None else 20.0, "warmup": args.warmup,
                         "clock_hz": 90.0, "points_hz": 30.0, "clock_mode": "follow", "cpus": os.cpu_count()}
        out["bodies"]["rows"] = bench_bodies(args.scene, out["bodies"]["counts"], out["bodies"]["seconds"],
                                             args.set, workdir, warmup=args.warmup)
        print("\n" + _bodies_table(out["bodies"]["rows"]))
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(out, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
