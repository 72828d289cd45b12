"""The ROS 2 node (docs/architecture.md, "Contracts: ROS interface"): a thin shell over Simulator.

    mdss_node --ros-args --params-file config/params.yaml -p scene:=cantilever
    python -m mdss_ros.node --ros-args -p scene:=msg_scenes/cantilever.yaml

Everything physical happens in `Simulator`; this module turns messages into Simulator
calls (through mdss_ros.ros.validate) and Simulator arrays into messages (through
mdss_ros.ros.convert), and decides *when*:

- Stepping. A steady-clock timer fires every physics_dt / real_time_factor seconds of
  wall time (real_time_factor <= 0: as fast as possible); a firing takes the steps the
  wall-clock schedule asks for (WallPace), each a Simulator.step() followed by /clock and
  the outputs that are due, one per executor cycle. A step that came late is made up
  for by the next firings, so sim time keeps to wall time through a hiccup; a node more
  than WallPace.CATCH_UP_S behind gives that lag up (/diagnostics pace_slips) and the
  measured real-time factor drops. That is clock_mode `source` (the default); the two
  other modes step on an external clock instead (below).
- Clock modes (parameter clock_mode, read-only). In `follow` and `lockstep` the node
  creates no step timer, ignores real_time_factor and publishes no /clock (an MCAP
  recording still gets a /clock record of the sim time every step, so `mdss replay`
  works unchanged); it subscribes to /clock (rosgraph_msgs/Clock, depth 100): BEST_EFFORT in
  follow (it matches reliable and best-effort masters alike, e.g. rclcpp's ClockQoS), and
  RELIABLE in lockstep, where a lost tick would be a lost step (it needs a reliable master).
  Sim time still starts at 0 and is step_count * physics_dt.
  - `follow`: after each tick of master time T the node takes, one step per executor
    cycle (inputs arriving in between are taken first, as in source mode), every step
    that ends at or before T + CLOCK_EPS_S (10 ns, for masters that truncate to the
    nanosecond): sim time never passes the master and lags it by less than one dt
    once caught up. A master period that dt does not divide is no special case: steps
    happen when they fit (90 Hz steps under a 50 Hz master: 1 or 2 per tick). A node
    behind (a slow model, a start against a master already at T, a reset) runs its
    steps back to back until it has caught up. ~/step is refused (the master drives).
  - `lockstep`: one step per ~/step call (also while running) and one per /clock tick
    whose time is later than the previous tick's (the first tick is compared with 0);
    a tick at the same time steps nothing, and nothing else steps. Ticks that arrive
    while a step runs are queued and each gets its step. Sim time is the number of
    steps times dt, not the master's time (they agree when the master ticks by dt).
  - The master jumps back (e.g. it was reset). follow: a tick earlier than the sim
    time logs a warning and resets the simulation to t = 0 (as ~/reset_simulation,
    recorded the same way), after which the node follows the master from there; a tick
    earlier than the previous one but not earlier than the sim time only holds the
    steps until the master passes the sim time again (nothing to undo). lockstep: a
    tick earlier than the previous tick logs a warning, resets to t = 0, drops steps
    still owed to earlier ticks and takes no step.
  - Pause: follow keeps reading the master and catches up on unpause; lockstep ignores
    ticks while paused (they are not made up for later) but ~/step still steps.
  - /diagnostics reports clock_mode in every mode; in follow and lockstep also
    clock_master_time (the last tick, 0 before one), clock_ticks, clock_jumps_back,
    and clock_lag (master time minus sim time, follow) or clock_steps_pending
    (lockstep). follow warns when clock_lag exceeds FOLLOW_LAG_WARN_S. The rule "how
    many steps fit before T" is `steps_before`, the tick rules are `ExternalClock`.
- The loop itself (inputs by stamp, the guarded step, outputs by schedule, resets,
  failures) is mdss_ros.ros.driver.Driver, the same one `mdss run --mcap` and `mdss
  replay` use; this module adds the ROS graph, the clock modes and the wall-clock parts.
- Inputs take effect at a defined step, so a run is reproducible from its inputs. An
  input stamped s (sim time, from /clock) is applied just before the step that starts
  at the first sim time t with s <= t + dt/2 (stamps round to the nearest step, as
  mdss_ros.timeline.TimelinePlayer does); an unstamped one (stamp 0) before the next
  step; inputs due at the same step are applied in stamp order, then arrival order.
  The input subscriptions are raw and live on an internal node `<name>_inputs` that a
  thread of its own spins, so messages are taken off the wire while a step computes:
  each is decoded and checked at once (a bad one is counted by kind) and waits in the
  driver's bounded queue (input_queue_limit; a message that finds it full is dropped
  and counted in inputs_dropped, never lost silently).
- Runtime changes of the parameters a run depends on (friction, output rates, wrench
  timeout, input limits, world_frame) are applied between steps and recorded as inputs
  (~/parameter_events), so a recording replays bit for bit across them.
- Outputs are due on a grid of their own rate in sim time: step k publishes an output
  of rate r when floor(k dt r) changed. At real_time_factor 1 that is wall time too; a
  rate >= 1/physics_dt publishes every step, 0 turns an output off. The state at t = 0
  is published at start and after every reset. /diagnostics runs on wall time.
- Every step goes through the Simulator's stability guard (mdss_ros/guard.py), which
  rolls back and retries a diverging step. /diagnostics reports stability "ok",
  "recovered" (the guard rolled back and retried a step since the last report) or
  "failed", with the guard's counters. A step the guard could not recover, and any
  non-finite array about to be published, resets the simulator and is logged.
"""
import math
import signal
import sys
import threading
import time
from collections import deque

import numpy as np
import rclpy
from rclpy.clock import Clock, ClockType
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.signals import SignalHandlerOptions
from rcl_interfaces.msg import ParameterDescriptor, SetParametersResult

from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseArray, PoseStamped, TransformStamped, WrenchStamped
from rosgraph_msgs.msg import Clock as ClockMsg
from sensor_msgs.msg import PointCloud2
from shape_msgs.msg import Mesh
from std_srvs.srv import Empty, Trigger
from visualization_msgs.msg import Marker

from .errors import MdssError
from .record.ros_messages import OutputRates, Topics, domain_names
from .ros import convert
from .ros.driver import DEFAULT_QUEUE_LIMIT, Driver
from .ros.validate import Limits
from .scene import load_scene, read_yaml, resolve_scene_path, scene_search_path
from .budget import build_simulator

NODE_NAME = "mdss"
# The /diagnostics status is "<node name>: simulation" ("mdss: simulation" by default), so
# several bodies, one node each (-r __node:=body_a), are told apart on the shared topic.
DIAGNOSTIC_NAME = "{node}: simulation"
WARN_PERIOD_S = 2.0   # one warning per rejection kind per this many seconds

# name: (default, description, changeable at runtime). physics_dt's default is the scene's.
PARAMETERS = {
    "scene": ("", "scene file (path) or name of a scene in msg_scenes/", False),
    "scene_overrides": ("", "dotted scene keys set on load: a list of KEY=VALUE "
                            "(-p scene_overrides:=\"[model.modes=6, body.mesh.cell=0.05]\") or a "
                            "YAML/JSON mapping in a string (params file: '{\"model.modes\": 6}')", False),
    "physics_dt": (0.0, "physics time step in s (default: the scene's model.integrator.dt)", False),
    "real_time_factor": (1.0, "sim seconds per wall second; <= 0 steps as fast as possible", True),
    "start_paused": (False, "start with physics paused (~/unpause_physics or ~/step to advance)", False),
    "clock_mode": ("source", "source: a steady timer steps and /clock is published; follow: step to track an "
                             "external /clock, never ahead of it; lockstep: one step per ~/step call or per "
                             "external /clock tick that moves forward (follow, lockstep: no /clock published, "
                             "real_time_factor ignored)", False),
    "points_publish_rate": (30.0, "~/surface/points rate in Hz of sim time (0: off)", True),
    "mesh_publish_rate": (1.0, "~/surface/mesh rate in Hz of sim time (0: off)", True),
    "marker_publish_rate": (10.0, "~/surface/marker rate in Hz of sim time (0: off)", True),
    "pose_publish_rate": (90.0, "~/domain_poses, ~/domain_transforms and collider wrench rate "
                                "in Hz of sim time (0: off)", True),
    "diagnostics_rate": (1.0, "/diagnostics rate in Hz of wall time (> 0)", True),
    "world_frame": ("world", "frame of all geometry in and out", True),
    "wrench_timeout_s": (0.0, "clear a wrench not refreshed for this many s of sim time (0: hold forever)", True),
    "max_force": (1.0e5, "reject wrench and point forces above this magnitude (N)", True),
    "max_torque": (1.0e4, "reject wrench torques above this magnitude (N m)", True),
    "max_position": (1.0e3, "reject points and collider positions farther from the origin (m)", True),
    "max_input_age": (1.0, "reject inputs stamped more than this many s before the sim time", True),
    "max_input_lead": (60.0, "reject inputs stamped more than this many s after the sim time", True),
    "max_point_forces": (1000, "reject ~/point_forces clouds with more points", True),
    "input_queue_limit": (DEFAULT_QUEUE_LIMIT, "inputs waiting for their step at most; one more is dropped and "
                                               "counted (/diagnostics inputs_dropped)", False),
    "mcap_path": ("", "MCAP recording (a .mcap file, or a rosbag2 folder): every input applied and "
                      "output published, log time = sim time; '' : off", False),
    "rerun_mode": ("off", "rerun logging: off, file (.rrd at rerun_path), spawn (a viewer), serve (gRPC + "
                          "web viewer)", False),
    "rerun_path": ("", "rerun .rrd file for rerun_mode file", False),
}
_RATES = ("points_publish_rate", "mesh_publish_rate", "marker_publish_rate", "pose_publish_rate")
_POSITIVE = ("diagnostics_rate", "max_force", "max_torque", "max_position", "max_input_age",
             "max_input_lead", "physics_dt")
_RERUN_MODES = ("off", "file", "spawn", "serve")
CLOCK_MODES = ("source", "follow", "lockstep")
CLOCK_EPS_S = 1e-8          # follow: a step fits before master time T if it ends at or before T + this
FOLLOW_LAG_WARN_S = 0.25    # follow: /diagnostics warns when the sim time lags the master by more
# Input subscriptions keep every sample until the inputs thread takes it (KEEP_ALL): with
# a reliable publisher DDS then pushes back instead of overwriting. KEEP_LAST 1000 lost
# 2,018 of 120,000 wrenches at 4 x 1 kHz on this loaded 2-core machine (stress_node.py
# soak), uncounted: a reader history overwrites without a trace.
INPUT_QOS = QoSProfile(history=HistoryPolicy.KEEP_ALL, reliability=ReliabilityPolicy.RELIABLE,
                       durability=DurabilityPolicy.VOLATILE)


class StartupError(MdssError):
    """The node cannot start (scene or parameters); the message says what to fix."""


def _qos(depth, latched=False):
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth, reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.TRANSIENT_LOCAL if latched else DurabilityPolicy.VOLATILE)


def available_scenes():
    names = set()
    for folder in scene_search_path()[1:]:
        if folder.is_dir():
            names.update(p.stem for p in folder.glob("*.yaml"))
    return sorted(names)


def precompute_notice(scene, cache=None):
    """What a start costs before the node spins, from model_build.cache_status(scene) of the
    model it will build (a budget's cached choice; no choice yet: the probe comes first)."""
    from .budget import cached_choice
    from .model_build import cache_status
    chosen = cached_choice(scene, cache)
    if chosen is None:
        return ("model.budget not probed yet (the automatic model of a scene without a model section has "
                "one): this start runs the full-space truth and the mode ladder first, then builds the "
                "chosen model and caches both; minutes on a large body (`mdss precompute SCENE` does it "
                "ahead of time)")
    status = cache_status(chosen, cache)
    if status.get("hit"):
        return f"precompute cache hit ({status.get('path')})"
    est = status.get("estimate_s")
    return (f"precompute cache missing ({status.get('path')}): building it takes about "
            f"{est:.0f} s" if est is not None else "precompute cache missing: building it now")


def parse_overrides(value):
    """{dotted key: value} of the scene_overrides parameter.

    value: "" (none); a list of "KEY=VALUE" strings (values parsed as YAML, like
    `mdss run --set`); or a string holding a YAML/JSON mapping or "KEY=VALUE[, ...]".
    """
    if isinstance(value, str):
        text = value.strip()
        if not text:
            return {}
        try:
            parsed = read_yaml(text)
        except Exception:
            parsed = None
        if isinstance(parsed, dict) and all(isinstance(k, str) for k in parsed):
            return parsed
        items = [t for t in text.replace(",", " ").split() if t]
    elif isinstance(value, (list, tuple)) and all(isinstance(v, str) for v in value):
        items = list(value)
    else:
        raise ValueError(f"scene_overrides must be a string or a list of KEY=VALUE strings, got {value!r}")
    out = {}
    for item in items:
        key, sep, text = item.partition("=")
        if not sep or not key.strip():
            raise ValueError(f"scene_overrides: expected KEY=VALUE (e.g. model.modes=6), got {item!r}")
        try:
            out[key.strip()] = read_yaml(text)
        except Exception as err:
            raise ValueError(f"scene_overrides: {item!r}: the value is not YAML: {err}") from err
    return out


def steps_before(step_count, dt, t, eps=CLOCK_EPS_S):
    """How many steps of dt, from step step_count, end at or before time t (+ eps): the
    n >= 0 with (step_count + n) dt <= t + eps < (step_count + n + 1) dt, or 0 when the
    sim time is already past t. Times are computed as Simulator.time is (k * dt)."""
    limit = t + eps
    n = math.floor(limit / dt) - step_count
    while n > 0 and (step_count + n) * dt > limit:        # rounding of the division
        n -= 1
    while (step_count + n + 1) * dt <= limit:
        n += 1
    return max(n, 0)


class ExternalClock:
    """The rules of clock_mode follow and lockstep (see the module docstring), without ROS.

    tick() takes one /clock message of the master and says whether it is a jump back that
    resets the simulation; steps_due() says how many steps to take now; stepped() that
    one was taken.
    """

    def __init__(self, mode):
        if mode not in ("follow", "lockstep"):
            raise ValueError(f"ExternalClock: mode must be follow or lockstep, got {mode!r}")
        self.mode = mode
        self.master = 0.0          # time of the last tick (s); 0 before the first
        self.ticks = 0
        self.jumps_back = 0
        self.pending = 0           # lockstep: steps owed to ticks

    def tick(self, t, sim_time, paused=False):
        """A tick at master time t (s) with the simulation at sim_time; True: reset to t = 0."""
        self.ticks += 1
        previous, self.master = self.master, float(t)
        if self.mode == "follow":
            # Only a tick before the sim time needs undoing; one back but not before the
            # sim time just holds the steps (steps_due is 0 until the master passes).
            if t < sim_time - CLOCK_EPS_S:
                self.jumps_back += 1
                return True
            return False
        if t < previous:
            self.jumps_back += 1
            self.pending = 0
            return True
        if t > previous and not paused:
            self.pending += 1
        return False

    def steps_due(self, step_count, dt):
        if self.mode == "follow":
            return steps_before(step_count, dt, self.master)
        return self.pending

    def stepped(self):
        self.pending = max(self.pending - 1, 0)

    def lag(self, sim_time):
        """Master time minus sim time (s): how far follow mode is behind."""
        return self.master - sim_time


class WallPace:
    """clock_mode source: how many steps are due so that sim time keeps to wall time x
    real_time_factor, without ROS (the node's step timer asks it at every firing).

    start(now, step_count) anchors the schedule where the timer (re)starts: step k0 + n is
    due n timer periods later. Due counts round at half a period, so timer jitter under
    half a period neither skips nor doubles a step; a firing that comes late (a slow step,
    the GIL held by the inputs thread, a loaded machine) finds two or more due and the node
    catches up, one step per executor cycle. Behind by more than CATCH_UP_S of sim time,
    the node gives the lag up instead of racing: it re-anchors and counts a slip.
    """

    CATCH_UP_S = 0.25

    def __init__(self):
        self.anchor = (0.0, 0)
        self.slips = 0

    def start(self, now, step_count):
        self.anchor = (float(now), int(step_count))

    def steps_due(self, now, step_count, dt, rtf):
        if rtf <= 0:                      # as fast as possible: one step per timer firing
            return 1
        wall0, k0 = self.anchor
        behind = k0 + math.floor((now - wall0) * rtf / dt + 0.5) - step_count
        if behind * dt > self.CATCH_UP_S:
            self.slips += 1
            self.start(now - dt / rtf, step_count)        # the step now is the new schedule's first
            return 1
        return max(behind, 0)


class MdssNode(Node):
    """The simulation node. Builds the simulator (the slow part) in the constructor."""

    def __init__(self, node_name=NODE_NAME, **kwargs):
        super().__init__(node_name, **kwargs)
        log = self.get_logger()
        self._declare("scene")
        self._declare("scene_overrides")
        scene = self._load_scene()
        self._declare("physics_dt", default=float(scene.dt))
        for name in PARAMETERS:
            if not self.has_parameter(name):
                self._declare(name)
        self._check_startup_parameters()
        self._scene_colliders = list(scene["colliders"])
        self._warn_unknown_parameters()
        self.add_on_set_parameters_callback(self._validate_parameters)
        self.add_post_set_parameters_callback(self._apply_parameters)

        if self._p("physics_dt") != scene.dt:
            scene = load_scene(scene, {"model.integrator.dt": self._p("physics_dt")})
        log.info(f"scene {scene.name!r} ({scene.source}): {scene['model']['kind']} model, "
                 f"dt = {scene.dt:.6g} s. {precompute_notice(scene)}")
        t0 = time.perf_counter()
        self.sim = build_simulator(scene, progress=lambda msg: log.info(f"precompute: {msg}"))
        for name, info in self.sim.colliders_inside_at_load.items():      # also a Python warning
            log.warn(f"collider {name!r} starts inside the body (" + (
                f"{info['vertices']} vertices inside it, {1e3 * info['depth']:.1f} mm deep" if info["vertices"]
                else "its centre inside the body's volume") + "): the first step pushes the body out of it "
                "along the shortest way, and it is not swept through the body when posed; /diagnostics "
                "colliders_inside_at_load lists it")
        st = self.sim.stats()
        log.info(f"model built in {time.perf_counter() - t0:.2f} s: {st['vertices']} vertices, "
                 f"{st['tets']} tets, {st['dofs']} DOFs, {st['domains']} domains, surface "
                 f"{len(self.sim.surface_vertex_ids())} vertices / {len(self.sim.surface_triangles())} triangles")

        self.colliders = list(scene["colliders"])
        self._declare_friction_parameters()

        # Bookkeeping. The step, the timers and the services run in the node's default
        # (mutually exclusive) callback group; the input subscriptions in their own group,
        # so a second executor thread takes messages off the wire while a step computes
        # (the driver's queue is the only state they share, behind its lock).
        self._paused = bool(self._p("start_paused"))
        mode = self._p("clock_mode")
        self._master = None if mode == "source" else ExternalClock(mode)   # None: the node is the clock
        self._warned = {}
        self._cycle_ms = deque(maxlen=100000)
        self._dropped_seen = 0                # inputs_dropped at the last /diagnostics
        self._pace = WallPace()               # source: the wall-clock schedule of the steps
        self._window = (time.monotonic(), self.sim.time)
        self._traps = {}
        self._inputs_thread, self._inputs_stop = None, threading.Event()
        self._recorder, self._rerun, self._closed = None, None, False
        self._topics = Topics(self.get_fully_qualified_name())
        self._open_recording()
        self._make_interfaces()
        rates = OutputRates(**{k: self._p(f"{k}_publish_rate") for k in ("points", "mesh", "marker", "pose")},
                            diagnostics=0.0)         # /diagnostics: the node's wall-clock timer
        self.driver = Driver(self.sim, self._topics, self._p("world_frame"), rates, self._emit,
                             limits=self._read_limits(), wrench_timeout_s=self._p("wrench_timeout_s"),
                             report=self._report, rerun=self._rerun,
                             queue_limit=self._p("input_queue_limit"),
                             on_collider_inside=self._collider_inside)
        self.domain_names = self.driver.outputs.domain_names
        self.surface_ids = self.driver.outputs.surface_ids
        self.driver.start()
        if self._step_timer is not None and not self._paused:
            self._restart_timer()              # the schedule starts now, not when the timer was made
        pace = (f"at real_time_factor {self._p('real_time_factor'):g}" if self._master is None else
                f"in clock_mode {self._master.mode} ("
                + ("stepping to follow /clock" if self._master.mode == "follow" else
                   "one step per ~/step call or /clock tick that moves forward")
                + "; real_time_factor ignored, no /clock published)")
        log.info(f"ready: {'paused' if self._paused else 'running'} {pace}; "
                 f"inputs on {self.resolve_topic_name('~/wrench')}, "
                 f"{self.resolve_topic_name('~/point_forces')}"
                 + "".join(f", {self._collider_topic(c, 'pose')}" for c in self.colliders)
                 + (f"; domain frames on /tf as {self._topics.tf_prefix}<domain>" if self.pub_tf is not None else
                    "; no tf2_msgs in this venv, so domain frames go to ~/domain_transforms only "
                    "(bash launch_scripts/build_tf2_msgs.sh adds /tf)"))

    # ------------------------------------------------------------------ parameters
    def _declare(self, name, default=None):
        value, text, runtime = PARAMETERS[name]
        if default is not None:
            value = default
        # -p real_time_factor:=0 is an int; scene_overrides is a string or a list of strings;
        # -p rerun_mode:=off is YAML 1.1's false (_p reads it as "off").
        dynamic = isinstance(value, float) or name in ("scene_overrides", "rerun_mode")
        desc = ParameterDescriptor(description=text, read_only=not runtime, dynamic_typing=dynamic)
        try:
            self.declare_parameter(name, value, desc)
        except Exception as err:   # e.g. -p max_point_forces:=10.5 for an integer parameter
            raise StartupError(f"parameter {name}: {err}") from err

    def _p(self, name):
        value = self.get_parameter(name).value
        if isinstance(PARAMETERS[name][0], float) and isinstance(value, int) and not isinstance(value, bool):
            return float(value)
        if name == "rerun_mode" and value is False:
            return "off"
        return value

    @staticmethod
    def _check(name, value):
        """None if value is acceptable for parameter name, else the reason."""
        default = PARAMETERS[name][0]
        if name == "rerun_mode" and isinstance(value, bool):
            # The command line's YAML reads off, no and false as False (rerun_mode off) and on,
            # yes and true as True, which names no mode.
            if value is False:
                return None
            return f"rerun_mode must be one of {', '.join(_RERUN_MODES)}, got {value!r} (a YAML true: on, yes, true)"
        if isinstance(default, float):
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
                return f"{name} must be a finite number, got {value!r}"
            if name in _RATES and value < 0:
                return f"{name} must be >= 0 (0 turns the output off), got {value}"
            if name in _POSITIVE and not value > 0:
                return f"{name} must be > 0, got {value}"
            if name == "wrench_timeout_s" and value < 0:
                return f"wrench_timeout_s must be >= 0 (0: no timeout), got {value}"
        elif name == "scene_overrides":
            try:
                parse_overrides(value)
            except ValueError as err:
                return str(err)
        elif type(value) is not type(default):
            return f"{name} must be a {type(default).__name__}, got {value!r}"
        if name in ("max_point_forces", "input_queue_limit") and value < 1:
            return f"{name} must be >= 1, got {value}"
        if name == "world_frame" and not value:
            return "world_frame must not be empty"
        if name == "rerun_mode" and value not in _RERUN_MODES:
            return f"rerun_mode must be one of {', '.join(_RERUN_MODES)}, got {value!r}"
        if name == "clock_mode" and value not in CLOCK_MODES:
            return f"clock_mode must be one of {', '.join(CLOCK_MODES)}, got {value!r}"
        return None

    def _check_startup_parameters(self):
        for name in PARAMETERS:
            reason = self._check(name, self.get_parameter(name).value)
            if reason:
                raise StartupError(f"parameter {reason}")

    @staticmethod
    def _friction_parameter(name):
        """(collider, 'static' or 'kinetic') of a parameter colliders.<name>.friction_<part>,
        else None."""
        if not name.startswith("colliders."):
            return None
        collider, _, leaf = name[len("colliders."):].rpartition(".")
        part = leaf[len("friction_"):] if leaf.startswith("friction_") else ""
        return (collider, part) if collider and part in ("static", "kinetic") else None

    def _declare_friction_parameters(self):
        """colliders.<name>.friction_static and .friction_kinetic per collider: the Coulomb
        coefficients (scene key colliders.<name>.friction), changeable at runtime; a value
        given at launch (-p) replaces the scene's."""
        for c in self.colliders:
            mu_s, mu_k = self.sim.colliders[c].friction
            for part, value in (("static", mu_s), ("kinetic", mu_k)):
                desc = ParameterDescriptor(description=f"Coulomb {part} friction coefficient of collider {c!r} "
                                                       f"(0: frictionless; kinetic <= static)",
                                           dynamic_typing=True)
                self.declare_parameter(f"colliders.{c}.friction_{part}", float(value), desc)
            try:
                self._set_friction(c)
            except ValueError as err:
                raise StartupError(f"parameters colliders.{c}.friction_*: {err}") from err

    def _set_friction(self, collider):
        """Apply the collider's launch-time friction parameters to the simulator, and to its
        scene, so a reset keeps them and a recording's scene holds them. (A change at runtime
        goes through Driver.set_parameters, which does the same and records it.)"""
        mu_s = self._number(f"colliders.{collider}.friction_static")
        mu_k = self._number(f"colliders.{collider}.friction_kinetic")
        self.sim.set_collider_friction(collider, mu_s, mu_k)
        self.sim.scene.data["colliders"][collider]["friction"] = {"static": mu_s, "kinetic": mu_k}

    def _number(self, name):
        value = self.get_parameter(name).value
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ValueError(f"{name}: expected a number, got {value!r}")
        return float(value)

    def _warn_unknown_parameters(self):
        known = set(PARAMETERS) | {"use_sim_time", "start_type_description_service"} | {
            f"colliders.{c}.friction_{part}" for c in self._scene_colliders for part in ("static", "kinetic")}
        for name in getattr(self, "_parameter_overrides", {}):
            if name not in known and not name.startswith("qos_overrides."):
                self.get_logger().warn(f"unknown parameter {name!r} ignored "
                                       f"(parameters: {', '.join(sorted(PARAMETERS))})")

    def _validate_parameters(self, params):
        friction = {}
        for p in params:
            if p.name in PARAMETERS:
                reason = self._check(p.name, p.value)
                if reason:
                    return SetParametersResult(successful=False, reason=reason)
            elif self._friction_parameter(p.name) and hasattr(self, "sim"):
                collider, part = self._friction_parameter(p.name)
                if collider not in friction:       # the pair as it stands: declared values, else the scene's
                    friction[collider] = {
                        k: (self.get_parameter(f"colliders.{collider}.friction_{k}").value
                            if self.has_parameter(f"colliders.{collider}.friction_{k}") else v)
                        for k, v in zip(("static", "kinetic"), self.sim.colliders[collider].friction)}
                    if not self.has_parameter(f"colliders.{collider}.friction_kinetic"):
                        friction[collider].pop("kinetic")       # being declared: static alone so far
                friction[collider][part] = p.value
        from .contact.friction import parse_friction
        for collider, value in friction.items():
            try:
                parse_friction(f"colliders.{collider}", value)
            except ValueError as err:
                return SetParametersResult(successful=False, reason=str(err))
        return SetParametersResult(successful=True)

    def _apply_parameters(self, params):
        names = {p.name for p in params}
        # What the run depends on goes through the driver, which records the change as an
        # input (a ParameterEvent), so `mdss replay` applies it at the same step.
        run = {}
        for collider in {self._friction_parameter(n)[0] for n in names if self._friction_parameter(n)}:
            # While they are declared one by one, the pair is applied once both exist.
            if hasattr(self, "driver") and self.has_parameter(f"colliders.{collider}.friction_kinetic"):
                for part in ("static", "kinetic"):
                    run[f"colliders.{collider}.friction_{part}"] = self._number(f"colliders.{collider}.friction_{part}")
        for name in names & (set(Driver.PARAMETERS) - {"colliders"}):
            run[name] = self._p(name)
        if run and hasattr(self, "driver"):
            self.driver.set_parameters(run)
        if "real_time_factor" in names and self._step_timer is not None:   # follow, lockstep: ignored
            self._step_timer.timer_period_ns = self._step_period_ns()
            if not self._paused:
                self._restart_timer()
            self._window = (time.monotonic(), self.sim.time)
        if "diagnostics_rate" in names:
            self._diag_timer.timer_period_ns = int(1e9 / self._p("diagnostics_rate"))
            self._diag_timer.reset()

    def _read_limits(self):
        return Limits(**{f: self._p(f) for f in ("max_force", "max_torque", "max_position", "max_input_age",
                                                  "max_input_lead", "max_point_forces")})

    def _load_scene(self):
        name = self._p("scene")
        if not name:
            raise StartupError("parameter scene is not set: -p scene:=NAME_OR_PATH "
                               f"(scenes: {', '.join(available_scenes()) or 'none found'})")
        try:
            overrides = parse_overrides(self._p("scene_overrides")) or None
        except ValueError as err:
            raise StartupError(str(err)) from err
        if overrides:
            self.get_logger().info(f"scene overrides: {overrides}")
        try:
            path = resolve_scene_path(name)
        except MdssError as err:
            raise StartupError(f"{err}; scenes by name: {', '.join(available_scenes()) or 'none'}") from err
        try:
            return load_scene(path, overrides)
        except MdssError as err:
            raise StartupError(str(err)) from err

    # ------------------------------------------------------------------ interfaces
    def _collider_topic(self, name, leaf):
        return self.resolve_topic_name(f"~/colliders/{name}/{leaf}")

    def _make_interfaces(self):
        for c in self.colliders:
            try:
                self._collider_topic(c, "pose")
            except Exception as err:
                raise StartupError(f"collider name {c!r} cannot be part of a topic name: {err}") from err
        tp = self._topics
        pub = self.create_publisher
        n_domains = len(self.sim.domain_poses())
        # Every output leaves as the CDR bytes the driver built (and records): topic -> publisher.
        self._output_pubs = {
            tp.topology: pub(Mesh, "~/surface/topology", _qos(1, latched=True)),
            tp.points: pub(PointCloud2, "~/surface/points", _qos(10)),
            tp.mesh: pub(Mesh, "~/surface/mesh", _qos(2)),
            tp.marker: pub(Marker, "~/surface/marker", _qos(2)),
            tp.domain_poses: pub(PoseArray, "~/domain_poses", _qos(10)),
            tp.domain_transforms: pub(TransformStamped, "~/domain_transforms", _qos(max(10, 2 * n_domains))),
            tp.contacts: pub(PointCloud2, "~/contacts", _qos(10)),
            tp.diagnostics: pub(DiagnosticArray, "/diagnostics", _qos(10)),
        }
        for c in self.colliders:
            self._output_pubs[tp.collider_wrench(c)] = pub(WrenchStamped, f"~/colliders/{c}/wrench", _qos(10))
            self._output_pubs[tp.collider_contacts(c)] = pub(PointCloud2, f"~/colliders/{c}/contacts", _qos(10))
        # latched: a late subscriber learns the sim time even while physics is paused
        # (follow, lockstep: the master owns /clock; the node only records its sim time)
        if self._master is None:
            self._output_pubs[tp.clock] = pub(ClockMsg, "/clock", _qos(1, latched=True))
        # /tf (tf2_msgs/TFMessage, child frames <node name>/<domain name>) as RViz and
        # Foxglove expect it. The pip ROS wheels have no tf2_msgs: launch_scripts/
        # build_tf2_msgs.sh builds it into the venv (the bootstrap runs it); without it the
        # frames go out on ~/domain_transforms only (and into a recording's /tf).
        try:
            from tf2_msgs.msg import TFMessage
        except ImportError:
            self.pub_tf = None
        else:
            self.pub_tf = self._output_pubs[tp.tf] = pub(TFMessage, "/tf", _qos(100))

        # Inputs arrive as raw CDR bytes (the driver decodes and checks them, as a replay
        # does) on a second, internal node "<name>_inputs" that its own thread spins, so
        # they are taken off the wire while a step computes and wait in the driver's
        # bounded, counted queue instead of DDS's. (A callback group of this node under a
        # MultiThreadedExecutor was tried: rclpy drops a guard condition triggered while
        # its group is busy, so the follow mode's steps stalled until the next tick.) DDS
        # keeps every sample until it is taken (INPUT_QOS; measured before this: 71-message
        # bursts lost 32 of 142 at KEEP_LAST 50 while the subscriptions waited for the step).
        self._inputs_node = Node(f"{self.get_name()}_inputs", namespace=self.get_namespace(), context=self.context,
                                 use_global_arguments=False, start_parameter_services=False,
                                 enable_rosout=False)
        self._input_subscription(WrenchStamped, tp.wrench)
        self._input_subscription(PointCloud2, tp.point_forces)
        for c in self.colliders:
            self._input_subscription(PoseStamped, tp.collider_pose(c))

        self.create_service(Empty, "~/pause_physics", self._srv_pause)
        self.create_service(Empty, "~/unpause_physics", self._srv_unpause)
        self.create_service(Empty, "~/reset_simulation", self._srv_reset)
        self.create_service(Trigger, "~/step", self._srv_step)
        self.create_service(Trigger, "~/clear_forces", self._srv_clear_forces)

        steady = Clock(clock_type=ClockType.STEADY_TIME)
        # The timer only triggers a guard condition whose callback steps, so a step timer
        # that is always ready (a model slower than real time, or real_time_factor <= 0)
        # still lets the services and the clock subscription of the same group run.
        self._step_guard = self.create_guard_condition(self._on_step_guard)
        if self._master is None:
            self._step_timer = self.create_timer(self._step_period_ns() * 1e-9, self._on_step_timer, clock=steady)
            if self._paused:
                self._step_timer.cancel()
        else:
            # Ticks trigger the same guard condition; depth 100 queues ticks during a step.
            # follow: BEST_EFFORT matches any master (rclcpp's ClockQoS is best effort), and
            # a lost tick costs nothing, the next one carries the time. lockstep: one step
            # per tick, so a lost tick is a lost step: RELIABLE, which needs a reliable master
            # (a best-effort one would not match; measured: 1 of 3 two-body runs lost ticks
            # to a best-effort subscription on this loaded 2-core machine).
            self._step_timer = None
            lossless = self._master.mode == "lockstep"
            self.create_subscription(ClockMsg, "/clock", self._on_clock,
                                     QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=100,
                                                reliability=ReliabilityPolicy.RELIABLE if lossless
                                                else ReliabilityPolicy.BEST_EFFORT,
                                                durability=DurabilityPolicy.VOLATILE))
        self._diag_timer = self.create_timer(1.0 / self._p("diagnostics_rate"), self._on_diag_timer, clock=steady)

    def _input_subscription(self, msg_type, topic):
        return self._inputs_node.create_subscription(msg_type, topic, lambda data, t=topic: self.driver.submit(t, data),
                                                     INPUT_QOS, raw=True)

    def start_inputs(self):
        """Start the thread that spins the inputs node (main() does; in-process users that
        call submit() themselves need not)."""
        if self._inputs_thread is None:
            self._inputs_executor = SingleThreadedExecutor(context=self.context)
            self._inputs_executor.add_node(self._inputs_node)
            self._inputs_thread = threading.Thread(target=self._spin_inputs, name="mdss inputs", daemon=True)
            self._inputs_thread.start()

    def _spin_inputs(self):
        while not self._inputs_stop.is_set() and self.context.ok():
            try:
                self._inputs_executor.spin_once(timeout_sec=0.1)
            except ExternalShutdownException:
                break
            except Exception:  # noqa: BLE001 - the node never stops taking inputs on one message
                import traceback
                self.get_logger().error(f"input callback failed (the node goes on):\n{traceback.format_exc()}")

    def stop_inputs(self):
        self._inputs_stop.set()
        thread, self._inputs_thread = self._inputs_thread, None
        if thread is not None:
            thread.join(timeout=5.0)
            self._inputs_executor.shutdown(timeout_sec=1.0)

    def _step_period_ns(self):
        rtf = self._p("real_time_factor")
        return int(round(1e9 * self.sim.dt / rtf)) if rtf > 0 else 0

    # ------------------------------------------------------------------ inputs
    def submit(self, topic, msg):
        """Hand an input to the driver as a subscription does (msg: CDR bytes or a message;
        topic: e.g. "~/wrench"). For tests and in-process use."""
        return self.driver.submit(self.resolve_topic_name(topic), msg)

    def _report(self, level, text, key=None):
        """The driver's messages to a person: rejections and warnings with a key are logged at
        most once per WARN_PERIOD_S per key, with a count of those held back."""
        log = self.get_logger()
        if key is not None:
            now = time.monotonic()
            last, suppressed = self._warned.get(key, (-math.inf, 0))
            if now - last < WARN_PERIOD_S:
                self._warned[key] = (last, suppressed + 1)
                return
            if suppressed:
                text += f" (and {suppressed} more '{key}' since the last warning)"
            self._warned[key] = (now, 0)
        # one call site per severity: rclpy's logger refuses a second severity at one call site
        if level == "info":
            log.info(text)
        elif level == "error":
            log.error(text)
        else:
            log.warn(text)

    def _trap_unknown_colliders(self):
        """Subscribe to ~/colliders/<name>/pose topics of names the scene lacks, to count them."""
        prefix = self.resolve_topic_name("~/colliders") + "/"
        for topic, types in self.get_topic_names_and_types():
            if not (topic.startswith(prefix) and topic.endswith("/pose")) or topic in self._traps:
                continue
            name = topic[len(prefix):-len("/pose")]
            if name in self.colliders or "/" in name or "geometry_msgs/msg/PoseStamped" not in types:
                continue
            self._traps[topic] = self._input_subscription(PoseStamped, topic)
            self.get_logger().warn(f"a publisher appeared on {topic}, but the scene has no collider {name!r} "
                                   f"(colliders: {', '.join(self.colliders) or 'none'}); its messages are "
                                   f"counted as rejected_unknown_collider")

    def _collider_inside(self, name, info):
        """A pose that puts a collider inside the body (Simulator.set_collider_pose): applied,
        counted by the driver (/diagnostics collider_poses_inside) and warned about at most
        once per WARN_PERIOD_S, like rejected inputs."""
        self._report("warn", f"~/colliders/{name}/pose puts the collider {1e3 * info['depth']:.1f} mm inside the "
                             f"body ({info['vertices']} surface vertices inside it, deepest vertex {info['vertex']}); "
                             f"applied: it is swept there if it starts the step outside the body, else moved "
                             f"straight there, and the contact pushes the body out along the shortest way",
                     key="collider_inside")

    # ------------------------------------------------------------------ stepping
    def _on_step_timer(self):
        if not self._paused:
            self._step_guard.trigger()

    def _on_step_guard(self):
        if self._paused:
            return
        if self._master is None:
            # source: the steps the wall clock asks for, one per executor cycle (the guard
            # is triggered again while more are due, so services run in between)
            rtf = self._p("real_time_factor")
            if self._pace.steps_due(time.monotonic(), self.sim.step_count, self.sim.dt, rtf) > 0:
                self.advance()
                if rtf > 0 and self._pace.steps_due(time.monotonic(), self.sim.step_count, self.sim.dt, rtf) > 0:
                    self._step_guard.trigger()
            return
        # follow, lockstep: one step per callback; the guard is triggered again while more
        # are due, so ticks and service calls that arrive meanwhile are taken between steps.
        if self._master.steps_due(self.sim.step_count, self.sim.dt) > 0:
            self._master.stepped()
            self.advance()
            self._kick_clock()

    def _kick_clock(self):
        """follow, lockstep: trigger the step guard condition while steps are due."""
        if self._master is not None and not self._paused and \
                self._master.steps_due(self.sim.step_count, self.sim.dt) > 0:
            self._step_guard.trigger()

    def _on_clock(self, msg):
        """A tick of the external master (follow, lockstep)."""
        t = convert.seconds(msg.clock)
        previous, sim_time = self._master.master, self.sim.time
        if self._master.tick(t, sim_time, self._paused):
            then = "follows the master from there" if self._master.mode == "follow" else "takes no step for it"
            self.get_logger().warn(f"/clock jumped back from {previous:.9g} s to {t:.9g} s (sim time "
                                   f"{sim_time:.9g} s): resetting the simulation to t = 0; the node {then} "
                                   f"(jump back {self._master.jumps_back})")
            self._reset("clock")
        self._kick_clock()

    def advance(self):
        """One physics step through the driver: due inputs, the step, /clock and due outputs."""
        w0 = time.perf_counter()
        if self.driver.advance():
            self._cycle_ms.append(1e3 * (time.perf_counter() - w0))

    def _reset(self, reason):
        self.driver.reset(reason)
        self._window = (time.monotonic(), self.sim.time)
        if self._step_timer is not None and not self._paused:
            self._restart_timer()

    def _restart_timer(self):
        """Restart the source-mode step timer and anchor the wall-clock schedule there."""
        self._step_timer.reset()
        self._pace.start(time.monotonic(), self.sim.step_count)

    def _emit(self, out, log_time_ns, is_input):
        """The driver's sink: outputs are published (bytes as built) and recorded; inputs,
        when applied, recorded."""
        if not is_input:
            pub = self._output_pubs.get(out.topic)
            if pub is not None:
                pub.publish(out.data)
        rec = self._recorder
        if rec is not None and rec.ok:
            rec.write(out.topic, out.data, log_time_ns, type_name=out.type_name,
                      qos=self._topics.qos_of(out.topic), publish_time_ns=time.time_ns())

    # ------------------------------------------------------------------ recording
    def _open_recording(self):
        """MCAP recorder and rerun logger of mcap_path / rerun_mode; a failure is logged and
        the node goes on without that recording."""
        log = self.get_logger()
        path = self._p("mcap_path")
        if path:
            from .record.mcap_recorder import McapRecorder, RecordingError, bag_paths
            try:
                target, folder = bag_paths(path)
                self._recorder = McapRecorder(target, bag_metadata=folder,
                                              on_error=lambda text: self.get_logger().error(text))
                self._recorder.add_metadata("mdss_run", self._run_metadata())
                log.info(f"recording to {target} (MCAP, log time = sim time)")
            except RecordingError as err:
                self._recorder = None
                log.error(f"{err}: nothing is recorded; the simulation goes on")
        mode = self._p("rerun_mode")
        if mode != "off":
            from .record.rerun_logger import RerunLogError, RerunLogger
            rrd = self._p("rerun_path") or None
            rate = self._p("points_publish_rate")
            try:
                self._rerun = RerunLogger(self.sim, mode=mode, path=rrd, rate=rate if rate > 0 else None,
                                          domain_names=domain_names(self.sim))
                where = rrd if mode == "file" else (self._rerun.url or "a spawned viewer")
                log.info(f"rerun logging ({mode}) to {where}")
            except RerunLogError as err:
                self._rerun = None
                log.error(f"{err}: no rerun logging; the simulation goes on")
            except Exception as err:  # noqa: BLE001 - e.g. rerun missing: the node goes on
                self._rerun = None
                log.error(f"rerun logging ({mode}) failed to start: {type(err).__name__}: {err}; "
                          f"the simulation goes on")

    def _run_metadata(self):
        """The `mdss_run` metadata `mdss run --mcap` writes, plus what the node adds."""
        import json
        from .record.replay import run_metadata
        rates = {"points": self._p("points_publish_rate"), "mesh": self._p("mesh_publish_rate"),
                 "marker": self._p("marker_publish_rate"), "pose": self._p("pose_publish_rate"),
                 "diagnostics": self._p("diagnostics_rate")}
        return run_metadata(self.sim, self._topics.namespace, self._p("world_frame"), rates,
                            recorder="mdss_ros.node",
                            diagnostics_clock="wall time (the node's /diagnostics)",
                            wrench_timeout_s=repr(self._p("wrench_timeout_s")),
                            limits_json=json.dumps(self._read_limits().__dict__),
                            real_time_factor=repr(self._p("real_time_factor")),
                            clock_mode=self._p("clock_mode"))

    def _close_recording(self):
        rerun = self.driver.rerun if hasattr(self, "driver") else self._rerun   # None once it failed
        self._rerun = None
        if hasattr(self, "driver"):
            self.driver.rerun = None
        if rerun is not None:
            try:
                rerun.close()
                self.get_logger().info(f"rerun: {rerun.frames} frames logged"
                                       + (f" to {rerun.path}" if rerun.mode == "file" else ""))
            except Exception as err:  # noqa: BLE001
                self.get_logger().error(f"rerun: closing failed: {type(err).__name__}: {err}")
        rec, self._recorder = self._recorder, None
        if rec is not None:
            s = rec.finish()
            if s["error"]:
                self.get_logger().error(f"MCAP: {s['error']} (the file keeps the chunks completed before)")
            else:
                self.get_logger().info(f"MCAP: {s['path']} ({s['messages']} messages on {len(s['topics'])} "
                                       f"topics, {s['bytes'] / 1e6:.2f} MB)")

    # ------------------------------------------------------------------ services
    def _srv_pause(self, request, response):
        if not self._paused:
            self._paused = True
            if self._step_timer is not None:
                self._step_timer.cancel()
            self.get_logger().info(f"physics paused at t = {self.sim.time:.6g} s")
        return response

    def _srv_unpause(self, request, response):
        if self._paused:
            self._paused = False
            self._window = (time.monotonic(), self.sim.time)
            if self._step_timer is not None:
                self._restart_timer()
            self._kick_clock()             # follow: catch up with the master
            self.get_logger().info(f"physics running from t = {self.sim.time:.6g} s")
        return response

    def _srv_reset(self, request, response):
        self._reset("service")
        self.get_logger().info("simulation reset to t = 0")
        self._kick_clock()                 # follow: catch up from 0 with the master
        return response

    def _srv_step(self, request, response):
        if self._master is not None and self._master.mode == "follow":
            response.success = False
            response.message = "clock_mode follow: the external /clock drives the steps"
            return response
        if not self._paused and self._master is None:
            response.success = False
            response.message = "physics is running: call ~/pause_physics first"
            return response
        self.advance()
        response.success = True
        response.message = f"t = {self.sim.time:.9f} s, step {self.sim.step_count}"
        return response

    def _srv_clear_forces(self, request, response):
        held, pending = self.driver.clear_forces()
        response.success = True
        response.message = (f"cleared wrenches on [{', '.join(held)}], all point forces and "
                            f"{pending} pending force inputs at t = {self.sim.time:.6g} s")
        return response

    # ------------------------------------------------------------------ diagnostics
    def _on_diag_timer(self):
        self._trap_unknown_colliders()
        from .record.ros_messages import Out, cdr_bytes
        tp = self._topics
        self._emit(Out(tp.diagnostics, tp.type_of(tp.diagnostics), cdr_bytes(self.diagnostics()), self.sim.time),
                   int(round(self.driver.run_time * 1e9)), False)

    def diagnostics(self):
        """The /diagnostics message of the window since the last call (wall-clock rates)."""
        now = time.monotonic()
        wall0, sim0 = self._window
        rtf = 0.0 if self._paused or now <= wall0 else (self.sim.time - sim0) / (now - wall0)
        self._window = (now, self.sim.time)
        steps, cycles = self.driver.take_step_ms(), np.array(self._cycle_ms)
        self._cycle_ms.clear()
        target = self._p("real_time_factor")
        values = {"state": "paused" if self._paused else "running", "clock_mode": self._p("clock_mode")}
        values.update(self.driver.values())
        values.update({
            "step_ms_median": float(np.median(steps)) if len(steps) else 0.0,
            "step_ms_max": float(steps.max()) if len(steps) else 0.0,
            "cycle_ms_median": float(np.median(cycles)) if len(cycles) else 0.0,
            "cycle_ms_max": float(cycles.max()) if len(cycles) else 0.0,
            "steps_in_window": len(steps),
            "real_time_factor": rtf,
            "real_time_factor_target": target,
        })
        stability, last_failure = values["stability"], values["last_failure"]
        clock, lag = self._master, 0.0
        if clock is None:
            values["pace_slips"] = self._pace.slips
        if clock is not None:
            values.update({"clock_master_time": clock.master, "clock_ticks": clock.ticks,
                           "clock_jumps_back": clock.jumps_back})
            if clock.mode == "follow":
                lag = clock.lag(self.sim.time)
                values["clock_lag"] = lag
            else:
                values["clock_steps_pending"] = clock.pending
        if stability == "failed":
            level, message = "error", f"failed: {last_failure}"
        elif stability == "recovered":
            level, message = "warn", f"recovered: {values['guard_last_event']}"
        elif values["inputs_dropped"] > self._dropped_seen:
            level, message = "warn", (f"input queue full: {values['inputs_dropped'] - self._dropped_seen} inputs "
                                      f"dropped in this window (input_queue_limit {values['input_queue_limit']})")
        elif clock is None and not self._paused and target > 0 and len(steps) and rtf < 0.9 * target:
            level, message = "warn", f"running slower than real_time_factor {target:g}: {rtf:.3g}"
        elif clock is not None and clock.mode == "follow" and not self._paused and lag > FOLLOW_LAG_WARN_S:
            level, message = "warn", f"behind the master /clock by {lag:.3g} s"
        else:
            level, message = "ok", values["state"]
        self._dropped_seen = values["inputs_dropped"]
        return convert.diagnostics(self.sim.time, DIAGNOSTIC_NAME.format(node=self._topics.node_name),
                                   f"scene:{self.sim.scene.name}", level, message, values)

    def close(self):
        """Log the end and finish the recordings (idempotent)."""
        if self._closed:
            return
        self._closed = True
        values = self.driver.values(stability=self.driver.stability)
        self.get_logger().info(f"shutting down at t = {self.sim.time:.6g} s after {self.sim.step_count} steps; "
                               f"inputs received {values['inputs_received']}, applied {values['inputs_applied']}, "
                               f"rejected {values['rejected_total']}, dropped {values['inputs_dropped']}")
        self._close_recording()

    def destroy_node(self):
        if hasattr(self, "_closed"):
            self.stop_inputs()
            self._close_recording()
        if getattr(self, "_inputs_node", None) is not None:
            self._inputs_node.destroy_node()
            self._inputs_node = None
        return super().destroy_node()


# ---------------------------------------------------------------------- main
class _Shutdown(BaseException):
    """SIGINT or SIGTERM before the node spins (during the model build)."""


def _usage():
    lines = ["usage: mdss_node [--ros-args] [--params-file FILE] [-p NAME:=VALUE ...]", "", "parameters:"]
    for name, (default, text, runtime) in PARAMETERS.items():
        lines.append(f"  {name} (default {default!r}{'' if runtime else ', read-only'}): {text}")
    return "\n".join(lines)


def _ros_args(argv):
    """argv with --ros-args inserted before the first -p / --params-file if missing."""
    argv = list(argv)
    if "--ros-args" not in argv:
        for i, a in enumerate(argv):
            if a in ("-p", "--param", "--params-file", "-r", "--remap") and i > 0:
                return argv[:i] + ["--ros-args"] + argv[i:]
    return argv


def _spin(node, state):
    """Spin until SIGINT/SIGTERM; a callback's unexpected error is logged, not fatal."""
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    while not state["stop"] and rclpy.ok():
        try:
            executor.spin_once(timeout_sec=0.2)
        except ExternalShutdownException:
            break
        except Exception:  # noqa: BLE001 - the node never crashes on one message
            import traceback
            node.get_logger().error(f"callback failed (the node goes on):\n{traceback.format_exc()}")
    executor.remove_node(node)


def main(args=None):
    """Start the node; exit code 0 on SIGINT/SIGTERM, 2 if the scene or parameters are bad."""
    argv = _ros_args(sys.argv if args is None else [sys.argv[0]] + list(args))
    if any(a in ("-h", "--help") for a in argv[1:argv.index("--ros-args") if "--ros-args" in argv else None]):
        print(_usage())
        return 0
    state = {"starting": True, "stop": False}

    def on_signal(signum, frame):
        state["stop"] = True
        if state["starting"]:
            raise _Shutdown(signal.Signals(signum).name)

    old = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
    rclpy.init(args=argv, signal_handler_options=SignalHandlerOptions.NO)
    node, code = None, 0
    try:
        try:
            node = MdssNode()
        except StartupError as err:
            rclpy.logging.get_logger(NODE_NAME).fatal(f"cannot start: {err}")
            code = 2
        state["starting"] = False
        if node is not None:
            node.start_inputs()
            _spin(node, state)
            node.stop_inputs()
            node.close()
    except (_Shutdown, KeyboardInterrupt):
        rclpy.logging.get_logger(NODE_NAME).info("interrupted while starting; exiting")
    finally:
        state["starting"] = False
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
        for s, h in old.items():
            signal.signal(s, h)
        sys.stdout.flush()
        sys.stderr.flush()
    return code


if __name__ == "__main__":
    sys.exit(main())
