#!/usr/bin/env python3
"""Launch-test helper: real ROS 2 processes from pytest (ros2 launch is not on pip).

    from launch_testing import Launch          # launch_scripts/ on sys.path
    with Launch(tmp_path) as launch:           # a DDS domain no other run uses
        node = launch.node(scene="cantilever", real_time_factor=0.0)
        node.wait_for(r"ready:")
        probe = launch.probe()                 # a separate process you drive
        probe.sub("/mdss/surface/points", "sensor_msgs/msg/PointCloud2")
        probe.wait("/mdss/surface/points", count=3)
        clouds = probe.get("/mdss/surface/points")
        assert node.stop() == 0                # SIGINT, then the exit code
    # node.text holds everything it printed; launch.dir / "node.log" the same on disk

Every child runs with the same venv python as the caller (the rclpy wheels re-execute
the interpreter with LD_LIBRARY_PATH set; a different python would inherit a wrong
one), in an environment with a ROS_DOMAIN_ID reserved for this Launch through a lock
file (so concurrent test runs on one machine never meet), ROS_AUTOMATIC_DISCOVERY_RANGE
= LOCALHOST unless the caller set it, and ROS_LOG_DIR inside the launch directory.

The probe (`python launch_testing.py probe`) is a small rclpy process that reads one
JSON command a line on stdin and answers one JSON line on stdout: subscribe and keep
what arrives (with receipt wall time), publish a message given as a dict, call a
service, set parameters, wait for a topic or for a number of messages, play a clock
master (/clock ticks on a wall-time schedule, `Probe.play_clock`). Point clouds come back
decoded into columns.
"""
import base64
import errno
import fcntl
import json
import os
import queue
import re
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
DOMAIN_IDS = range(1, 102)     # 0..101 map to ports below Linux's ephemeral range
_RESPONSE = "@@probe "


# ---------------------------------------------------------------------- environment
class DomainLease:
    """A ROS_DOMAIN_ID held through an exclusive lock file until release()."""

    def __init__(self, lock_dir=None):
        self.dir = Path(lock_dir or Path(tempfile.gettempdir()) / "mdss_ros_domains")
        self.dir.mkdir(parents=True, exist_ok=True)
        start = (os.getpid() * 7 + int(time.monotonic() * 1000)) % len(DOMAIN_IDS)
        for i in range(len(DOMAIN_IDS)):
            d = DOMAIN_IDS[(start + i) % len(DOMAIN_IDS)]
            f = open(self.dir / f"{d}.lock", "w")
            try:
                fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError as err:
                f.close()
                if err.errno in (errno.EAGAIN, errno.EACCES):
                    continue
                raise
            self.domain_id, self._file = d, f
            return
        raise RuntimeError(f"all ROS domain ids {DOMAIN_IDS.start}..{DOMAIN_IDS.stop - 1} are in use "
                           f"(lock files in {self.dir})")

    def release(self):
        if self._file is not None:
            fcntl.flock(self._file, fcntl.LOCK_UN)
            self._file.close()
            self._file = None


def ros_env(domain_id, log_dir=None, base=None):
    """Environment for a child ROS process: its own domain, localhost-only DDS."""
    env = dict(os.environ if base is None else base)
    env["ROS_DOMAIN_ID"] = str(domain_id)
    env.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    env["PYTHONUNBUFFERED"] = "1"
    env["RCUTILS_COLORIZED_OUTPUT"] = "0"
    env["RCUTILS_LOGGING_BUFFERED_STREAM"] = "0"
    env.setdefault("NUMBA_CACHE_DIR", str(REPO / ".venv" / "numba_cache"))
    env["PYTHONPATH"] = os.pathsep.join([str(REPO)] + [p for p in env.get("PYTHONPATH", "").split(os.pathsep) if p])
    if log_dir is not None:
        env["ROS_LOG_DIR"] = str(log_dir)
    return env


def param_arg(name, value):
    """`name:=value` for -p, with value written so rcl's YAML parser reads it back."""
    if isinstance(value, bool):
        text = "true" if value else "false"
    elif isinstance(value, (int, float)):
        text = repr(value)
    elif isinstance(value, (list, tuple)):
        text = json.dumps(list(value))
    else:
        text = str(value)
        if not re.fullmatch(r"[A-Za-z_/~.][A-Za-z0-9_/~.\-]*", text) or text in ("true", "false", "null"):
            text = json.dumps(text)
    return f"{name}:={text}"


# ---------------------------------------------------------------------- processes
class Process:
    """A child process whose merged output is read line by line (kept and logged to a file)."""

    def __init__(self, name, argv, env, cwd, log_path):
        self.name, self.argv, self.log_path = name, argv, Path(log_path)
        self.lines = []
        self._cond = threading.Condition()
        self._log = open(self.log_path, "w")
        self.popen = subprocess.Popen(argv, env=env, cwd=str(cwd), stdin=subprocess.PIPE,
                                      stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, bufsize=1)
        self._reader = threading.Thread(target=self._read, name=f"read-{name}", daemon=True)
        self._reader.start()

    def _read(self):
        for line in self.popen.stdout:
            self._on_line(line.rstrip("\n"))
        with self._cond:
            self._cond.notify_all()
        self._log.close()

    def _on_line(self, line):
        if not self._log.closed:
            self._log.write(line + "\n")
            self._log.flush()
        with self._cond:
            self.lines.append(line)
            self._cond.notify_all()

    @property
    def text(self):
        with self._cond:
            return "\n".join(self.lines)

    @property
    def returncode(self):
        return self.popen.poll()

    def tail(self, n=40):
        with self._cond:
            return "\n".join(self.lines[-n:])

    def wait_for(self, pattern, timeout=60.0):
        """The first re.Match of pattern in the output (waits for it); TimeoutError with the tail."""
        rx = re.compile(pattern)
        deadline = time.monotonic() + timeout
        with self._cond:
            i = 0
            while True:
                for line in self.lines[i:]:
                    m = rx.search(line)
                    if m:
                        return m
                i = len(self.lines)
                left = deadline - time.monotonic()
                if self.popen.poll() is not None and not self._reader.is_alive():
                    raise RuntimeError(f"{self.name} exited ({self.popen.returncode}) before printing "
                                       f"{pattern!r}; its output:\n{self.tail()}")
                if left <= 0:
                    raise TimeoutError(f"{self.name}: no {pattern!r} within {timeout} s; output:\n{self.tail()}")
                self._cond.wait(min(left, 0.5))

    def stop(self, sig=signal.SIGINT, timeout=20.0):
        """Send sig (once), wait for the exit; kill after timeout. Returns the exit code."""
        if self.popen.poll() is None:
            self.popen.send_signal(sig)
            try:
                self.popen.wait(timeout)
            except subprocess.TimeoutExpired:
                self.popen.kill()
                self.popen.wait(10)
                self._on_line(f"[launch_testing] {self.name} did not exit within {timeout} s of "
                              f"{signal.Signals(sig).name}: killed")
        self._reader.join(10)
        return self.popen.returncode

    def wait(self, timeout=60.0):
        """Wait for the process to end by itself; its exit code (TimeoutError with its output)."""
        try:
            self.popen.wait(timeout)
        except subprocess.TimeoutExpired:
            raise TimeoutError(f"{self.name} still running after {timeout} s; output:\n{self.tail()}") from None
        self._reader.join(10)
        return self.popen.returncode


class Probe(Process):
    """The probe process: ROS operations on request (see `probe_main`)."""

    def __init__(self, *args, **kwargs):
        self._responses = queue.Queue()
        self.subscribed = set()
        super().__init__(*args, **kwargs)

    def _on_line(self, line):
        if line.startswith(_RESPONSE):
            self._responses.put(json.loads(line[len(_RESPONSE):]))
        else:
            super()._on_line(line)

    def request(self, op, timeout=60.0, **kw):
        self.popen.stdin.write(json.dumps(dict(kw, op=op)) + "\n")
        self.popen.stdin.flush()
        try:
            out = self._responses.get(timeout=timeout + 10.0)
        except queue.Empty:
            raise TimeoutError(f"probe: no answer to {op} {kw} within {timeout + 10} s; output:\n{self.tail()}")
        if "error" in out:
            raise RuntimeError(f"probe {op} {kw}: {out['error']}")
        return out.get("result")

    # conveniences
    def sub(self, topic, msg_type, qos="reliable", depth=1000):
        self.subscribed.add(topic)
        return self.request("sub", topic=topic, type=msg_type, qos=qos, depth=depth)

    def pub(self, topic, msg_type, msg, wait_subscribers=30.0, qos="reliable", ack=False):
        """Publish msg (a dict, or a list of them) once a subscriber matched; ack: wait for
        every subscriber to acknowledge (reliable QoS; takes up to Fast DDS's 3 s heartbeat)."""
        return self.request("pub", topic=topic, type=msg_type, msg=msg, wait_subscribers=wait_subscribers,
                            qos=qos, ack=ack, timeout=wait_subscribers + 10)

    def call(self, service, srv_type, request=None, timeout=30.0):
        return self.request("call", service=service, type=srv_type, request=request or {}, timeout=timeout)

    def wait(self, topic, count=1, timeout=60.0, where=None, partial=False, new=False):
        """Wait until count messages (matching where, see _matches) arrived on topic; returns
        them. new: count only messages arriving after this call. On timeout: TimeoutError,
        or (partial=True) the ones that did arrive."""
        return self.request("wait", topic=topic, count=count, where=where, timeout=timeout, partial=partial,
                            new=new)

    def get(self, topic, start=0):
        return self.request("get", topic=topic, start=start)

    def clear(self, topic):
        return self.request("clear", topic=topic)

    def set_params(self, node, params, timeout=30.0):
        return self.request("set_params", node=node, params=params, timeout=timeout)

    def wait_topic(self, topic, timeout=60.0, publishers=1):
        return self.request("wait_topic", topic=topic, publishers=publishers, timeout=timeout)

    def graph(self, topic):
        """{"publishers": n, "subscribers": m} the probe sees on topic now."""
        return self.request("graph", topic=topic)

    def play_clock(self, times, period, topic="/clock", qos="reliable", wait_subscribers=30.0, subscribers=1):
        """Be a clock master: publish rosgraph_msgs/Clock at each of times (s, in order) every
        `period` s of wall time, from a thread; returns once `subscribers` subscriptions matched. Each tick
        is kept under "@sent" + topic (get / wait read it) with, as _recv, the wall time
        taken just before it was published."""
        return self.request("play_clock", topic=topic, times=[float(t) for t in times], period=period,
                            qos=qos, wait_subscribers=wait_subscribers, subscribers=subscribers,
                            timeout=wait_subscribers + 10)

    def diagnostics(self, where=None, timeout=30.0, name="mdss: simulation"):
        """Values (a dict of str) of the first /diagnostics status `name` matching where that
        arrives after this call."""
        if "/diagnostics" not in self.subscribed:
            self.sub("/diagnostics", "diagnostic_msgs/msg/DiagnosticArray")
        cond = {"diag": name}
        cond.update(where or {})
        msgs = self.wait("/diagnostics", count=1, where=cond, timeout=timeout, new=True)
        return status_values(msgs[-1], name)


def status_values(diag_array, name="mdss: simulation"):
    for st in diag_array["status"]:
        if st["name"] == name:
            return {kv["key"]: kv["value"] for kv in st["values"]}
    return None


class Launch:
    """Processes sharing one reserved DDS domain, stopped (SIGINT) when the block ends."""

    def __init__(self, directory=None, python=None, env=None):
        self.dir = Path(directory or tempfile.mkdtemp(prefix="mdss_launch_"))
        self.dir.mkdir(parents=True, exist_ok=True)
        self.lease = DomainLease()
        self.domain_id = self.lease.domain_id
        self.python = python or sys.executable
        self.env = ros_env(self.domain_id, log_dir=self.dir / "ros_log", base=env)
        self.processes = []

    def __enter__(self):
        return self

    def __exit__(self, exc_type, exc, tb):
        self.shutdown()
        if exc_type is not None:
            for p in self.processes:
                sys.stderr.write(f"\n----- {p.name} (exit {p.returncode}) -----\n{p.tail(60)}\n")
        return False

    def start(self, name, args, cls=Process, cwd=None):
        """A child `python args...` (args: a list, e.g. ["-m", "mdss_ros.node", ...])."""
        taken = {p.name for p in self.processes}
        base, k = name, 1
        while name in taken:
            k += 1
            name = f"{base}{k}"
        p = cls(name, [self.python] + [str(a) for a in args], self.env, cwd or REPO, self.dir / f"{name}.log")
        self.processes.append(p)
        return p

    def node(self, name="node", params_file=None, ros_args=(), **params):
        """The mdss node with parameters (-p name:=value each)."""
        args = ["-m", "mdss_ros.node", "--ros-args"]
        if params_file:
            args += ["--params-file", params_file]
        for k, v in params.items():
            args += ["-p", param_arg(k, v)]
        return self.start(name, args + list(ros_args))

    def script(self, name, path, *args):
        """A script of launch_scripts/ (or any path) with arguments."""
        path = Path(path)
        if not path.is_absolute() and not path.exists():
            path = REPO / "launch_scripts" / path
        return self.start(name, [path] + list(args))

    def probe(self, name="probe"):
        p = self.start(name, [Path(__file__).resolve(), "probe"], cls=Probe)
        p.request("ping", timeout=60.0)
        return p

    def stop_all(self, expect=0, sig=signal.SIGINT):
        """shutdown(), then AssertionError (with each failing process's output) unless every
        exit code is `expect`."""
        codes = self.shutdown(sig)
        bad = {n: c for n, c in codes.items() if c != expect}
        if bad:
            tails = "\n".join(f"----- {p.name} (exit {p.returncode}) -----\n{p.tail()}"
                              for p in self.processes if p.name in bad)
            raise AssertionError(f"exit codes {bad} (expected {expect}):\n{tails}")
        return codes

    def shutdown(self, sig=signal.SIGINT):
        """Stop every running process (last started first); returns {name: exit code}."""
        codes = {}
        for p in reversed(self.processes):
            if p.returncode is None and isinstance(p, Probe):
                try:                      # a probe ends when its stdin does
                    p.popen.stdin.close()
                    p.popen.wait(10)
                except (OSError, subprocess.TimeoutExpired):
                    pass
            codes[p.name] = p.stop(sig)
        self.lease.release()
        return codes


# ---------------------------------------------------------------------- the probe process
def _import_type(name):
    """rclpy message/service class of 'pkg/msg/Type' or 'pkg/srv/Type'."""
    import importlib
    parts = name.split("/")
    if len(parts) == 2:
        parts = [parts[0], "msg", parts[1]]
    pkg, kind, typ = parts
    return getattr(importlib.import_module(f"{pkg}.{kind}"), typ)


def _set_fields(msg, values):
    """Fill a message from a dict (nested dicts and lists; 'x_b64' sets uint8[] x from base64)."""
    import array
    types = msg.get_fields_and_field_types()
    for key, value in values.items():
        if key.endswith("_b64"):
            field = key[:-4]
            setattr(msg, field, array.array("B", base64.b64decode(value)))
            continue
        if key not in types:
            raise KeyError(f"{type(msg).__name__} has no field {key!r} (fields: {', '.join(types)})")
        t = types[key]
        current = getattr(msg, key)
        if isinstance(value, dict) and hasattr(current, "get_fields_and_field_types"):
            _set_fields(current, value)
        elif isinstance(value, list) and value and isinstance(value[0], dict):
            inner = re.match(r"sequence<([^,>]+)", t) or re.match(r"([^\[]+)\[", t)
            cls = _import_type(inner.group(1))
            items = []
            for v in value:
                m = cls()
                _set_fields(m, v)
                items.append(m)
            setattr(msg, key, items)
        else:
            setattr(msg, key, value)
    return msg


def _to_dict(msg):
    """A JSON-able dict of a message; PointCloud2 gets decoded 'columns'."""
    import array
    import numpy as np
    if hasattr(msg, "get_fields_and_field_types"):
        out = {k: _to_dict(getattr(msg, k)) for k in msg.get_fields_and_field_types()}
        if type(msg).__name__ == "PointCloud2":
            out.pop("data")
            out["columns"] = _cloud_columns(msg)
        return out
    if isinstance(msg, (list, tuple)):
        return [_to_dict(v) for v in msg]
    if isinstance(msg, (array.array, np.ndarray)):
        return [float(v) if isinstance(v, (float, np.floating)) else int(v) for v in msg]
    if isinstance(msg, bytes):
        return list(msg)
    if isinstance(msg, float):
        return msg if np.isfinite(msg) else repr(msg)
    return msg


def _cloud_columns(msg):
    """{field: list} of a PointCloud2 (fields of count 1; None when the layout is broken)."""
    import numpy as np
    types = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}
    n = msg.width * msg.height
    data = np.frombuffer(msg.data, dtype=np.uint8)
    if n == 0 or len(data) < msg.row_step * msg.height or msg.row_step < msg.width * msg.point_step:
        return {}
    rows = data[:msg.row_step * msg.height].reshape(msg.height, msg.row_step)[:, :msg.width * msg.point_step]
    rows = rows.reshape(n, msg.point_step)
    out = {}
    for f in msg.fields:
        if f.datatype not in types or f.count != 1:
            continue
        size = int(types[f.datatype][1:])
        col = np.ascontiguousarray(rows[:, f.offset:f.offset + size]).view(
            (">" if msg.is_bigendian else "<") + types[f.datatype]).reshape(n)
        out[f.name] = [float(v) if np.isfinite(v) else repr(float(v)) for v in col.astype(np.float64)]
    return out


def _matches(d, where):
    """where: {"stamp_ge": t, "stamp_le": t} (header stamp >= / <= t s), {"diag": name,
    key: value or {"ge": x} ...} (a /diagnostics status with those values), or None."""
    if not where:
        return True
    where = dict(where)
    st = d.get("header", {}).get("stamp") or d.get("clock") or {}
    t = st.get("sec", 0) + 1e-9 * st.get("nanosec", 0)
    if "stamp_ge" in where and t < where.pop("stamp_ge") - 1e-12:
        return False
    if "stamp_le" in where and t > where.pop("stamp_le") + 1e-12:
        return False
    if "diag" in where:
        values = status_values(d, where.pop("diag"))
        if values is None:
            return False
        for k, want in where.items():
            have = values.get(k)
            if have is None:
                return False
            if isinstance(want, dict):
                x = float(have)
                if "ge" in want and not x >= want["ge"]:
                    return False
                if "le" in want and not x <= want["le"]:
                    return False
                if "gt" in want and not x > want["gt"]:
                    return False
            elif str(want) != have:
                return False
    return True


def probe_main():
    """The probe process: JSON commands on stdin, JSON answers on stdout."""
    import rclpy
    from rclpy.duration import Duration
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from rcl_interfaces.srv import SetParameters
    from rclpy.parameter import Parameter

    from rclpy.signals import SignalHandlerOptions
    rclpy.init(signal_handler_options=SignalHandlerOptions.NO)   # SIGINT: KeyboardInterrupt
    node = Node(f"mdss_probe_{os.getpid()}")
    lock = threading.Condition()
    store, subs, pubs = {}, {}, {}
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    running = [True]

    def spin_loop():
        while running[0]:
            executor.spin_once(timeout_sec=0.05)

    spin = threading.Thread(target=spin_loop, daemon=True)
    spin.start()

    def qos(kind, depth):
        return QoSProfile(depth=depth,
                          reliability=ReliabilityPolicy.BEST_EFFORT if kind == "best_effort" else ReliabilityPolicy.RELIABLE,
                          durability=DurabilityPolicy.TRANSIENT_LOCAL if kind == "latched" else DurabilityPolicy.VOLATILE)

    def on_msg(topic, msg):
        t = time.time()
        with lock:
            store[topic].append((t, msg))
            lock.notify_all()

    def entries(topic, start=0):
        out = []
        for t, msg in store.get(topic, [])[start:]:
            d = _to_dict(msg)
            d["_recv"] = t
            out.append(d)
        return out

    def matched_publisher(cls, topic, cmd):
        """The probe's publisher of topic (made once), once cmd["subscribers"] (default 1)
        subscriptions matched it: with two nodes on one clock, starting after the first
        match let the second miss the first ticks."""
        if topic not in pubs:
            pubs[topic] = node.create_publisher(cls, topic, qos(cmd.get("qos", "reliable"), 100))
        pub = pubs[topic]
        deadline = time.monotonic() + cmd.get("wait_subscribers", 30.0)
        while pub.get_subscription_count() < cmd.get("subscribers", 1):
            if time.monotonic() > deadline:
                raise TimeoutError(f"fewer than {cmd.get('subscribers', 1)} subscribers on {topic}")
            time.sleep(0.02)
        return pub

    def wait_future(fut, timeout):
        done = threading.Event()
        fut.add_done_callback(lambda f: done.set())
        if not done.wait(timeout):
            raise TimeoutError(f"no response within {timeout} s")
        return fut.result()

    def handle(cmd):
        op = cmd["op"]
        if op == "ping":
            return os.getpid()
        if op == "sub":
            topic = cmd["topic"]
            if topic not in subs:
                with lock:
                    store.setdefault(topic, [])
                subs[topic] = node.create_subscription(_import_type(cmd["type"]), topic,
                                                       lambda m, t=topic: on_msg(t, m),
                                                       qos(cmd.get("qos", "reliable"), cmd.get("depth", 1000)))
            return True
        if op == "pub":
            topic = cmd["topic"]
            cls = _import_type(cmd["type"])
            pub = matched_publisher(cls, topic, cmd)
            msgs = cmd["msg"] if isinstance(cmd["msg"], list) else [cmd["msg"]]
            for m in msgs:
                pub.publish(_set_fields(cls(), m))
            if cmd.get("ack"):      # Fast DDS acknowledges on its heartbeat: up to 3 s
                pub.wait_for_all_acked(Duration(seconds=10))
            return len(msgs)
        if op == "call":
            cls = _import_type(cmd["type"])
            client = node.create_client(cls, cmd["service"])
            try:
                if not client.wait_for_service(timeout_sec=cmd.get("timeout", 30.0)):
                    raise TimeoutError(f"service {cmd['service']} not available")
                res = wait_future(client.call_async(_set_fields(cls.Request(), cmd.get("request", {}))),
                                  cmd.get("timeout", 30.0))
                return _to_dict(res)
            finally:
                node.destroy_client(client)
        if op == "set_params":
            client = node.create_client(SetParameters, cmd["node"].rstrip("/") + "/set_parameters")
            try:
                if not client.wait_for_service(timeout_sec=cmd.get("timeout", 30.0)):
                    raise TimeoutError(f"{cmd['node']}/set_parameters not available")
                req = SetParameters.Request(parameters=[Parameter(k, value=v).to_parameter_msg()
                                                        for k, v in cmd["params"].items()])
                res = wait_future(client.call_async(req), cmd.get("timeout", 30.0))
                return [{"successful": r.successful, "reason": r.reason} for r in res.results]
            finally:
                node.destroy_client(client)
        if op == "wait":
            topic, count, where = cmd["topic"], cmd.get("count", 1), cmd.get("where")
            deadline = time.monotonic() + cmd.get("timeout", 60.0)
            found = []
            with lock:
                seen = len(store.get(topic, [])) if cmd.get("new") else 0
                while True:
                    for t, msg in store.get(topic, [])[seen:]:
                        d = _to_dict(msg)
                        if _matches(d, where):
                            d["_recv"] = t
                            found.append(d)
                    seen = len(store.get(topic, []))
                    if len(found) >= count:
                        return found
                    left = deadline - time.monotonic()
                    if left <= 0 and cmd.get("partial"):
                        return found
                    if left <= 0:
                        raise TimeoutError(f"{len(found)} of {count} messages on {topic} matching {where} "
                                           f"within {cmd.get('timeout', 60.0)} s ({seen} received)")
                    lock.wait(min(left, 0.2))
        if op == "get":
            with lock:
                return entries(cmd["topic"], cmd.get("start", 0))
        if op == "clear":
            with lock:
                n = len(store.get(cmd["topic"], []))
                store[cmd["topic"]] = []
            return n
        if op == "graph":
            return {"publishers": node.count_publishers(cmd["topic"]),
                    "subscribers": node.count_subscribers(cmd["topic"])}
        if op == "play_clock":
            from rosgraph_msgs.msg import Clock
            topic, key = cmd["topic"], "@sent" + cmd["topic"]
            pub = matched_publisher(Clock, topic, cmd)
            with lock:
                store[key] = []

            def play(times=cmd["times"], period=cmd["period"]):
                due = time.monotonic()
                for t in times:
                    ns = int(round(t * 1e9))
                    msg = Clock()
                    msg.clock.sec, msg.clock.nanosec = ns // 1_000_000_000, ns % 1_000_000_000
                    sent = time.time()
                    pub.publish(msg)
                    with lock:
                        store[key].append((sent, msg))
                        lock.notify_all()
                    due += period
                    time.sleep(max(0.0, due - time.monotonic()))

            threading.Thread(target=play, name="clock-master", daemon=True).start()
            return len(cmd["times"])
        if op == "wait_topic":
            deadline = time.monotonic() + cmd.get("timeout", 60.0)
            while node.count_publishers(cmd["topic"]) < cmd.get("publishers", 1):
                if time.monotonic() > deadline:
                    raise TimeoutError(f"no publisher on {cmd['topic']} within {cmd.get('timeout')} s")
                time.sleep(0.05)
            return True
        raise ValueError(f"unknown op {op!r}")

    code = 0
    try:
        for line in sys.stdin:
            line = line.strip()
            if not line:
                continue
            try:
                cmd = json.loads(line)
                if cmd.get("op") == "quit":
                    break
                out = {"result": handle(cmd)}
            except Exception as err:  # noqa: BLE001 - reported to the caller
                out = {"error": f"{type(err).__name__}: {err}"}
            sys.stdout.write(_RESPONSE + json.dumps(out) + "\n")
            sys.stdout.flush()
    except KeyboardInterrupt:
        pass
    finally:
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        signal.signal(signal.SIGTERM, signal.SIG_IGN)
        running[0] = False
        spin.join(5.0)
        executor.remove_node(node)
        node.destroy_node()
        rclpy.try_shutdown()
    return code


def main(argv=None):
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["probe"]:
        return probe_main()
    print(__doc__)
    print("usage: launch_testing.py probe   (JSON commands on stdin; see Probe in this file)")
    return 0 if argv[:1] in ([], ["-h"], ["--help"]) else 2


if __name__ == "__main__":
    sys.exit(main())
