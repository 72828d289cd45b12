#!/usr/bin/env python3
"""Watch a running mdss node from another process: every 0.25 s of sim time, print the
sim time and the surface vertex that moved farthest from its rest position.

    .venv/bin/python docs/tutorial/watch_pad.py [--node /mdss] [--seconds 10]

Rest positions come from ~/surface/topology (latched, sent once), deformed ones from
~/surface/points (same vertex order). Run it in the node's ROS_DOMAIN_ID. Exits after
--seconds of wall time; exit code 1 if nothing arrived.
"""
import argparse
import sys
import time

import numpy as np
import rclpy
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import PointCloud2
from shape_msgs.msg import Mesh

_TYPES = {2: "u1", 7: "<f4", 8: "<f8"}   # PointField UINT8, FLOAT32, FLOAT64


def xyz(cloud):
    """(n, 3) array of a PointCloud2's x, y, z fields."""
    dtype = np.dtype({"names": [f.name for f in cloud.fields],
                      "formats": [_TYPES[f.datatype] for f in cloud.fields],
                      "offsets": [f.offset for f in cloud.fields], "itemsize": cloud.point_step})
    rec = np.frombuffer(bytes(cloud.data), dtype=dtype, count=cloud.width * cloud.height)
    return np.stack([rec["x"], rec["y"], rec["z"]], axis=1).astype(float)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--node", default="/mdss", help="namespace of the node's topics (default /mdss)")
    ap.add_argument("--seconds", type=float, default=10.0, help="wall seconds to watch (default 10)")
    args = ap.parse_args()
    ns = args.node.rstrip("/")
    rclpy.init()
    node = rclpy.create_node("mdss_watcher")
    state = {"rest": None, "last": -1.0}

    def on_topology(msg):
        state["rest"] = np.array([[v.x, v.y, v.z] for v in msg.vertices])

    def on_points(msg):
        t = msg.header.stamp.sec + 1e-9 * msg.header.stamp.nanosec
        if state["rest"] is None or t - state["last"] < 0.25 - 1e-6:
            return
        p = xyz(msg)
        d = p - state["rest"]
        i = int(np.argmax(np.linalg.norm(d, axis=1)))
        print(f"t = {t:5.2f} s   largest displacement {1e3 * np.linalg.norm(d[i]):6.2f} mm "
              f"(dx, dy, dz = {1e3 * d[i, 0]:+.2f}, {1e3 * d[i, 1]:+.2f}, {1e3 * d[i, 2]:+.2f} mm)", flush=True)
        state["last"] = t

    reliable = dict(reliability=ReliabilityPolicy.RELIABLE)
    node.create_subscription(Mesh, f"{ns}/surface/topology", on_topology,
                             QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL, **reliable))
    node.create_subscription(PointCloud2, f"{ns}/surface/points", on_points, QoSProfile(depth=10, **reliable))
    end = time.monotonic() + args.seconds
    while time.monotonic() < end:
        rclpy.spin_once(node, timeout_sec=0.1)
    node.destroy_node()
    rclpy.try_shutdown()
    return 0 if state["last"] >= 0 else 1


if __name__ == "__main__":
    sys.exit(main())
