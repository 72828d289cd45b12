"""The ROS 2 node (docs/architecture.md, "Contracts: ROS interface"): a thin shell over Simulator.

    mdss_node --ros-args --params-file config/params.yaml -p scene:=cantilever
    python -m mdss_ros.node --ros-args -p scene:=msg_scenes/cantilever.yaml

Everything physical happens in `Simulator`; this module turns messages into Simulator
calls (through mdss_ros.ros.validate) and Simulator arrays into messages (through
mdss_ros.ros.convert), and decides *when*:

- Stepping. A steady-clock timer fires every physics_dt / real_time_factor seconds of
  wall time (real_time_factor <= 0: as fast as possible); each firing is one
  Simulator.step() followed by /clock and the outputs that are due, run after the
  input messages that arrived meanwhile. A late step is not made up for: under load
  the measured real-time factor drops instead. That is clock_mode `source` (the
  default); the two other modes step on an external clock instead (below).
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
- Inputs take effect at a defined step, so a run is reproducible from its inputs. An
  input stamped s (sim time, from /clock) is applied just before the step that starts
  at the first sim time t with s <= t + dt/2 (stamps round to the nearest step, as
  mdss_ros.timeline.TimelinePlayer does); an unstamped one (stamp 0) before the next
  step; inputs due at the same step are applied in stamp order, then arrival order.
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
from std_msgs.msg import Header
from std_srvs.srv import Empty, Trigger
from visualization_msgs.msg import Marker

from .errors import MdssError
from .record.ros_messages import Topics
from .ros import convert
from .ros import validate
from .ros.validate import InputRejected, Limits
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
_FORCE_INPUTS = ("wrench", "point_forces")


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


def precompute_notice(scene):
    """What a start costs before the node spins, from model_build.cache_status(scene)."""
    from .model_build import cache_status
    status = cache_status(scene)
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


class _Input:
    __slots__ = ("due", "seq", "kind", "apply", "topic", "msg")

    def __init__(self, due, seq, kind, apply, topic=None, msg=None):
        self.due, self.seq, self.kind, self.apply = due, seq, kind, apply
        self.topic, self.msg = topic, msg     # recorded when applied


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
        self.surface_ids = np.asarray(self.sim.surface_vertex_ids())
        self.triangles = np.asarray(self.sim.surface_triangles())
        log.info(f"model built in {time.perf_counter() - t0:.2f} s: {st['vertices']} vertices, "
                 f"{st['tets']} tets, {st['dofs']} DOFs, {st['domains']} domains, surface "
                 f"{len(self.surface_ids)} vertices / {len(self.triangles)} triangles")

        self.handles = set(scene["handles"])
        self.colliders = list(scene["colliders"])
        self._declare_friction_parameters()
        self.domain_names = self._domain_names()
        self.surface_domain = np.asarray(self.sim.model.vertex_domain)[self.surface_ids]
        self._points = convert.SurfacePoints(self.surface_domain)
        self._mesh = convert.MeshEncoder(self.triangles)
        self._marker = convert.MarkerEncoder(self.triangles, self.surface_domain)
        self._limits = self._read_limits()

        # Bookkeeping (all touched only from callbacks of this node's executor).
        self._paused = bool(self._p("start_paused"))
        mode = self._p("clock_mode")
        self._master = None if mode == "source" else ExternalClock(mode)   # None: the node is the clock
        self._queue = []
        self._seq = 0
        self._held = {}                       # handle -> sim time its wrench was last set
        self._rejected = dict.fromkeys(validate.KINDS, 0)
        self._warned = {}
        self._counts = dict.fromkeys(("received", "applied", "late"), 0)
        self._inside_poses, self._inside_last = 0, ""    # collider poses inside the body (applied)
        self._stability, self._failures, self._last_failure = "ok", 0, ""
        self._guard_seen = 0                  # guard recoveries already reported
        self._failing = False
        self._step_ms, self._cycle_ms = deque(maxlen=100000), deque(maxlen=100000)
        self._window = (time.monotonic(), self.sim.time)
        self._traps = {}
        self._recorder, self._rerun, self._closed = None, None, False
        self._log_offset = 0.0                # sim time run before the last reset (log time goes on)
        self._topics = Topics(self.get_fully_qualified_name())
        self._open_recording()

        self._make_interfaces()
        self._publish_topology()
        self._publish_state(initial=True)
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
        # -p real_time_factor:=0 is an int; scene_overrides is a string or a list of strings
        dynamic = isinstance(value, float) or name == "scene_overrides"
        desc = ParameterDescriptor(description=text, read_only=not runtime, dynamic_typing=dynamic)
        try:
            self.declare_parameter(name, value, desc)
        except Exception as err:   # e.g. -p max_point_forces:=10.5 for an integer parameter
            raise StartupError(f"parameter {name}: {err}") from err

    def _p(self, name):
        value = self.get_parameter(name).value
        if isinstance(PARAMETERS[name][0], float) and isinstance(value, int) and not isinstance(value, bool):
            return float(value)
        return value

    @staticmethod
    def _check(name, value):
        """None if value is acceptable for parameter name, else the reason."""
        default = PARAMETERS[name][0]
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
        if name == "max_point_forces" and value < 1:
            return f"max_point_forces must be >= 1, got {value}"
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
        """Apply the collider's friction parameters to the simulator, and to its scene, so a
        reset keeps them and a recording started after this replays them. (A change at
        runtime is not an input of the recording: `mdss replay --check` reports the
        outputs after it as different.)"""
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
        for collider in {self._friction_parameter(n)[0] for n in names if self._friction_parameter(n)}:
            # While they are declared one by one, the pair is applied once both exist.
            if hasattr(self, "sim") and self.has_parameter(f"colliders.{collider}.friction_kinetic"):
                self._set_friction(collider)
        if names & {"max_force", "max_torque", "max_position", "max_input_age", "max_input_lead",
                    "max_point_forces"}:
            self._limits = self._read_limits()
        if "real_time_factor" in names and self._step_timer is not None:   # follow, lockstep: ignored
            self._step_timer.timer_period_ns = self._step_period_ns()
            if not self._paused:
                self._step_timer.reset()
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

    def _domain_names(self):
        n = len(self.sim.domain_poses())
        names = list(self.sim.model.domain_names())
        if len(names) != n:
            names = ["body"] if n == 1 else [f"domain_{i}" for i in range(n)]
        return names

    # ------------------------------------------------------------------ interfaces
    def _collider_topic(self, name, leaf):
        return self.resolve_topic_name(f"~/colliders/{name}/{leaf}")

    def _make_interfaces(self):
        for c in self.colliders:
            try:
                self._collider_topic(c, "pose")
            except Exception as err:
                raise StartupError(f"collider name {c!r} cannot be part of a topic name: {err}") from err
        self.pub_topology = self.create_publisher(Mesh, "~/surface/topology", _qos(1, latched=True))
        self.pub_points = self.create_publisher(PointCloud2, "~/surface/points", _qos(10))
        self.pub_mesh = self.create_publisher(Mesh, "~/surface/mesh", _qos(2))
        self.pub_marker = self.create_publisher(Marker, "~/surface/marker", _qos(2))
        self.pub_poses = self.create_publisher(PoseArray, "~/domain_poses", _qos(10))
        self.pub_transforms = self.create_publisher(TransformStamped, "~/domain_transforms",
                                                    _qos(max(10, 2 * len(self.domain_names))))
        self.pub_contacts = self.create_publisher(PointCloud2, "~/contacts", _qos(10))
        self.pub_collider_wrench = {c: self.create_publisher(WrenchStamped, f"~/colliders/{c}/wrench", _qos(10))
                                    for c in self.colliders}
        # latched: a late subscriber learns the sim time even while physics is paused
        # (follow, lockstep: the master owns /clock; the node only records its sim time)
        self.pub_clock = (self.create_publisher(ClockMsg, "/clock", _qos(1, latched=True))
                          if self._master is None else None)
        self.pub_diag = self.create_publisher(DiagnosticArray, "/diagnostics", _qos(10))
        # /tf (tf2_msgs/TFMessage, child frames <node name>/<domain name>) as RViz and
        # Foxglove expect it. The pip ROS wheels have no tf2_msgs: launch_scripts/
        # build_tf2_msgs.sh builds it into the venv (the bootstrap runs it); without it the
        # frames go out on ~/domain_transforms only (and into a recording's /tf).
        try:
            from tf2_msgs.msg import TFMessage
        except ImportError:
            self._tf_type, self.pub_tf = None, None
        else:
            self._tf_type = TFMessage
            self.pub_tf = self.create_publisher(TFMessage, "/tf", _qos(100))

        self.create_subscription(WrenchStamped, "~/wrench", self._on_wrench, _qos(50))
        self.create_subscription(PointCloud2, "~/point_forces", self._on_point_forces, _qos(50))
        for c in self.colliders:
            self.create_subscription(PoseStamped, f"~/colliders/{c}/pose",
                                     lambda msg, c=c: self._on_collider_pose(c, msg), _qos(50))

        self.create_service(Empty, "~/pause_physics", self._srv_pause)
        self.create_service(Empty, "~/unpause_physics", self._srv_unpause)
        self.create_service(Empty, "~/reset_simulation", self._srv_reset)
        self.create_service(Trigger, "~/step", self._srv_step)
        self.create_service(Trigger, "~/clear_forces", self._srv_clear_forces)

        steady = Clock(clock_type=ClockType.STEADY_TIME)
        # The timer only triggers a guard condition whose callback steps: rclpy's executor
        # runs ready timers before subscriptions, guard conditions after them, so inputs
        # that arrived during a step are taken before the next one even when the timer is
        # always ready (a model slower than real time, or real_time_factor <= 0).
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

    def _step_period_ns(self):
        rtf = self._p("real_time_factor")
        return int(round(1e9 * self.sim.dt / rtf)) if rtf > 0 else 0

    # ------------------------------------------------------------------ inputs
    def _reject(self, err, source):
        self._rejected[err.kind] += 1
        now = time.monotonic()
        last, suppressed = self._warned.get(err.kind, (-math.inf, 0))
        if now - last >= WARN_PERIOD_S:
            more = f" (and {suppressed} more '{err.kind}' rejections since the last warning)" if suppressed else ""
            self.get_logger().warn(f"rejected {source}: {err.reason}{more}")
            self._warned[err.kind] = (now, 0)
        else:
            self._warned[err.kind] = (last, suppressed + 1)

    def _enqueue(self, stamp, kind, apply, topic=None, msg=None):
        due = validate.due_time(stamp, self.sim.time, self._limits)
        if due is not None and due < self.sim.time - 0.5 * self.sim.dt:
            self._counts["late"] += 1
        self._seq += 1
        self._queue.append(_Input(due, self._seq, kind, apply, topic, msg))

    def _on_wrench(self, msg):
        self._counts["received"] += 1
        w = msg.wrench
        try:
            handle, force, torque = validate.wrench(
                msg.header.frame_id, (w.force.x, w.force.y, w.force.z),
                (w.torque.x, w.torque.y, w.torque.z), self.handles, self._limits)
            self._enqueue(convert.seconds(msg.header.stamp), "wrench",
                          lambda: self._apply_wrench(handle, force, torque), self._topics.wrench, msg)
        except InputRejected as err:
            self._reject(err, "~/wrench")

    def _apply_wrench(self, handle, force, torque):
        self.sim.set_wrench(handle, force, torque)
        if force.any() or torque.any():
            self._held[handle] = self.sim.time
        else:
            self._held.pop(handle, None)

    def _on_point_forces(self, msg):
        self._counts["received"] += 1
        try:
            points, forces, durations = validate.point_forces(msg, self._p("world_frame"), self._limits)
            self._enqueue(convert.seconds(msg.header.stamp), "point_forces",
                          lambda: [self.sim.add_point_force(p, f, d) for p, f, d in zip(points, forces, durations)],
                          self._topics.point_forces, msg)
        except InputRejected as err:
            self._reject(err, "~/point_forces")

    def _on_collider_pose(self, name, msg):
        self._counts["received"] += 1
        p, o = msg.pose.position, msg.pose.orientation
        try:
            validate.frame(msg.header.frame_id, self._p("world_frame"), f"colliders/{name}/pose")
            pos, quat = validate.pose((p.x, p.y, p.z), (o.x, o.y, o.z, o.w), self._limits)
            self._enqueue(convert.seconds(msg.header.stamp), "collider_pose",
                          lambda: self._apply_collider_pose(name, pos, quat),
                          self._topics.collider_pose(name), msg)
        except InputRejected as err:
            self._reject(err, f"~/colliders/{name}/pose")

    def _on_unknown_collider(self, name, msg):
        self._counts["received"] += 1
        self._reject(InputRejected("unknown_collider", f"the scene has no collider {name!r} "
                                                       f"(colliders: {', '.join(self.colliders) or 'none'})"),
                     f"~/colliders/{name}/pose")

    def _trap_unknown_colliders(self):
        """Subscribe to ~/colliders/<name>/pose topics of names the scene lacks, to count them."""
        prefix = self.resolve_topic_name("~/colliders") + "/"
        for topic, types in self.get_topic_names_and_types():
            if not (topic.startswith(prefix) and topic.endswith("/pose")) or topic in self._traps:
                continue
            name = topic[len(prefix):-len("/pose")]
            if name in self.colliders or "/" in name or "geometry_msgs/msg/PoseStamped" not in types:
                continue
            self._traps[topic] = self.create_subscription(
                PoseStamped, topic, lambda msg, n=name: self._on_unknown_collider(n, msg), _qos(50))
            self.get_logger().warn(f"a publisher appeared on {topic}, but the scene has no collider {name!r} "
                                   f"(colliders: {', '.join(self.colliders) or 'none'}); its messages are "
                                   f"counted as rejected_unknown_collider")

    def _apply_due_inputs(self):
        t_limit = self.sim.time + 0.5 * self.sim.dt
        due = [i for i in self._queue if i.due is None or i.due <= t_limit]
        if not due:
            return
        self._queue = [i for i in self._queue if not (i.due is None or i.due <= t_limit)]
        due.sort(key=lambda i: (self.sim.time if i.due is None else i.due, i.seq))
        for item in due:
            try:
                item.apply()
                self._counts["applied"] += 1
                if item.msg is not None:
                    self._record(item.topic, item.msg)
            except (KeyError, ValueError) as err:
                self._reject(InputRejected("apply_error", f"{item.kind}: {err}"), item.kind)

    def _expire_wrenches(self):
        timeout = self._p("wrench_timeout_s")
        if timeout <= 0:
            return
        for handle, t_set in list(self._held.items()):
            if self.sim.time - t_set >= timeout - 1e-9:
                self.sim.set_wrench(handle)
                del self._held[handle]
                self.get_logger().info(f"wrench on {handle!r} cleared: not refreshed for "
                                       f"wrench_timeout_s = {timeout:g} s")

    # ------------------------------------------------------------------ stepping
    def _on_step_timer(self):
        if not self._paused:
            self._step_guard.trigger()

    def _on_step_guard(self):
        if self._paused:
            return
        if self._master is None:
            self.advance()
            return
        # follow, lockstep: one step per callback; the guard is triggered again while more
        # are due, so inputs (and ticks) that arrive meanwhile are taken between steps.
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
            self._stability, self._last_failure = "ok", ""
            self._reset()
        self._kick_clock()

    def advance(self):
        """One physics step: due inputs, Simulator.step(), /clock and due outputs."""
        w0 = time.perf_counter()
        self._apply_due_inputs()
        self._expire_wrenches()
        k = self.sim.step_count
        s0 = time.perf_counter()
        try:
            self.sim.step()
        except Exception as err:  # a solver failure must not take the node down
            self._fail(f"the step from t = {self.sim.time:.6g} s raised {type(err).__name__}: {err}")
            return
        st = self.sim.stats()
        if st.get("stability") == "failed":
            # The guard kept the last good state; nothing diverged is published.
            self._fail(f"the step to t = {self.sim.time:.6g} s diverged and could not be recovered "
                       f"({st.get('guard_reason', '')})")
            return
        step_ms = 1e3 * (time.perf_counter() - s0)
        self._step_ms.append(step_ms)
        self._publish_state(previous_step=k)
        if self._rerun is not None:
            self._log_rerun(step_ms)
        self._cycle_ms.append(1e3 * (time.perf_counter() - w0))

    def _due(self, rate_name, previous_step):
        rate = self._p(rate_name)
        if rate <= 0:
            return False
        if previous_step is None:
            return True
        tick = lambda k: math.floor(k * self.sim.dt * rate + 1e-6)  # noqa: E731
        return tick(self.sim.step_count) > tick(previous_step)

    def _finite(self, what, a):
        if np.all(np.isfinite(a)):
            return True
        self._fail(f"non-finite {what} at t = {self.sim.time:.6g} s")
        return False

    def _publish_state(self, previous_step=None, initial=False):
        """/clock and every output due after the step from previous_step (None: all)."""
        t, frame, tp = self.sim.time, self._p("world_frame"), self._topics
        if self.pub_clock is not None:
            self._publish(self.pub_clock, tp.clock, convert.clock(t))
        else:                      # follow, lockstep: recorded only (replay steps to the last one)
            self._record(tp.clock, convert.clock(t))
        surface = [n for n in ("points_publish_rate", "mesh_publish_rate", "marker_publish_rate")
                   if self._due(n, previous_step)]
        if surface:
            x = self.sim.surface_positions()
            if not self._finite("surface positions", x):
                return
            if "points_publish_rate" in surface:
                self._publish(self.pub_points, tp.points, self._points.message(t, frame, x))
            if "mesh_publish_rate" in surface:
                self._publish(self.pub_mesh, tp.mesh, self._mesh.encode(x))
            if "marker_publish_rate" in surface:
                self._publish(self.pub_marker, tp.marker, self._marker.encode(t, frame, x))
        if self._due("pose_publish_rate", previous_step):
            poses = self.sim.domain_poses()
            wrenches = {c: self.sim.collider_wrench(c) for c in self.colliders}
            if not self._finite("domain poses", poses) or not all(
                    self._finite(f"wrench on collider {c!r}", w) for c, w in wrenches.items()):
                return
            self._publish(self.pub_poses, tp.domain_poses, convert.pose_array(t, frame, poses))
            transforms = convert.domain_transforms(t, frame, self.domain_names, poses)
            for msg in transforms:
                self._publish(self.pub_transforms, tp.domain_transforms, msg)
            tf = convert.domain_transforms(t, frame, self.domain_names, poses, prefix=tp.tf_prefix)
            if self.pub_tf is not None:
                self.pub_tf.publish(self._tf_type(transforms=tf))
            if self._recorder is not None:
                self._recorder.write_tf(tf, self._log_time())
            for c, w in wrenches.items():
                self._publish(self.pub_collider_wrench[c], tp.collider_wrench(c), convert.wrench_stamped(t, frame, w))
        contacts_of = getattr(self.sim, "contacts", None)
        if callable(contacts_of):
            contacts = np.asarray(contacts_of(), dtype=np.float64)
            if len(contacts) and self._finite("contacts", contacts):
                self._publish(self.pub_contacts, tp.contacts, convert.contacts_cloud(t, frame, contacts))

    def _publish_topology(self):
        rest = np.asarray(self.sim.rest_positions())[self.surface_ids]
        self._publish(self.pub_topology, self._topics.topology, convert.topology_mesh_bytes(rest, self.triangles))

    def _fail(self, what):
        self._stability, self._failures = "failed", self._failures + 1
        self._last_failure = what
        self.get_logger().error(f"{what}: nothing of it is published; resetting the simulation to t = 0 "
                                f"(failure {self._failures})")
        if not self._failing:
            self._failing = True
            try:
                self._reset()
            finally:
                self._failing = False

    def _reset(self):
        # Recorded as an input, so a replay resets where this run did; log time keeps
        # counting from here (sim time restarts at 0).
        self._record(self._topics.reset, Header(stamp=convert.stamp(self.sim.time), frame_id=""))
        self._log_offset += self.sim.time
        self.sim.reset()
        self._guard_seen = 0
        self._queue.clear()
        self._held.clear()
        self._window = (time.monotonic(), self.sim.time)
        if self.sim.step_count == 0 and np.all(np.isfinite(self.sim.surface_positions())):
            self._publish_state(initial=True)

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
                                          domain_names=self.domain_names)
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
                            limits_json=json.dumps(self._limits.__dict__),
                            real_time_factor=repr(self._p("real_time_factor")),
                            clock_mode=self._p("clock_mode"))

    def _log_time(self):
        return int(round((self._log_offset + self.sim.time) * 1e9))

    def _record(self, topic, msg, type_name=None):
        rec = self._recorder
        if rec is not None and rec.ok:
            rec.write(topic, msg, self._log_time(), type_name=type_name, qos=self._topics.qos_of(topic),
                      publish_time_ns=time.time_ns())

    def _publish(self, pub, topic, msg):
        """Publish msg (an object, or CDR bytes of the publisher's type) and record it."""
        pub.publish(msg)
        if self._recorder is not None:
            self._record(topic, msg, type_name=None if not isinstance(msg, (bytes, bytearray)) else
                         f"{pub.msg_type.__module__.split('.')[0]}/msg/{pub.msg_type.__name__}")

    def _apply_collider_pose(self, name, pos, quat):
        inside = self.sim.set_collider_pose(name, pos, quat)
        if inside:
            self._collider_inside(name, inside)
        if self._rerun is not None:
            self._rerun.collider_pose(name, pos, quat)

    def _collider_inside(self, name, info):
        """A pose that puts a collider inside the body (Simulator.set_collider_pose): applied,
        counted (/diagnostics collider_poses_inside) and warned about at most once per
        WARN_PERIOD_S, like rejected inputs."""
        self._inside_poses += 1
        self._inside_last = f"{name}: {1e3 * info['depth']:.1f} mm, {info['vertices']} vertices"
        now = time.monotonic()
        last, suppressed = self._warned.get("collider_inside", (-math.inf, 0))
        if now - last >= WARN_PERIOD_S:
            more = f" (and {suppressed} more such poses since the last warning)" if suppressed else ""
            self.get_logger().warn(
                f"~/colliders/{name}/pose puts the collider {1e3 * info['depth']:.1f} mm inside the body "
                f"({info['vertices']} surface vertices inside it, deepest vertex {info['vertex']}); applied: it is "
                f"swept there if it starts the step outside the body, else moved straight there, and the "
                f"contact pushes the body out along the shortest way{more}")
            self._warned["collider_inside"] = (now, 0)
        else:
            self._warned["collider_inside"] = (last, suppressed + 1)

    def _log_rerun(self, step_ms):
        try:
            self._rerun.log_step(step_ms)
        except Exception as err:  # noqa: BLE001 - a viewer gone away must not stop the simulation
            self.get_logger().error(f"rerun logging stopped: {type(err).__name__}: {err}; the simulation goes on")
            rerun, self._rerun = self._rerun, None
            try:
                rerun.close()
            except Exception:  # noqa: BLE001
                pass

    def _close_recording(self):
        rerun, self._rerun = self._rerun, None
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
                self._step_timer.reset()
            self._kick_clock()             # follow: catch up with the master
            self.get_logger().info(f"physics running from t = {self.sim.time:.6g} s")
        return response

    def _srv_reset(self, request, response):
        self._stability, self._last_failure = "ok", ""
        self._reset()
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
        held = sorted(self._held)
        pending = sum(1 for i in self._queue if i.kind in _FORCE_INPUTS)
        self.sim.clear_forces()
        self._held.clear()
        self._record(self._topics.clear_forces, Header(stamp=convert.stamp(self.sim.time), frame_id=""))
        self._queue = [i for i in self._queue if i.kind not in _FORCE_INPUTS]
        response.success = True
        response.message = (f"cleared wrenches on [{', '.join(held)}], all point forces and "
                            f"{pending} pending force inputs at t = {self.sim.time:.6g} s")
        return response

    # ------------------------------------------------------------------ diagnostics
    def _on_diag_timer(self):
        self._trap_unknown_colliders()
        self._publish(self.pub_diag, self._topics.diagnostics, self.diagnostics())

    def diagnostics(self):
        now = time.monotonic()
        wall0, sim0 = self._window
        rtf = 0.0 if self._paused or now <= wall0 else (self.sim.time - sim0) / (now - wall0)
        self._window = (now, self.sim.time)
        steps, cycles = np.array(self._step_ms), np.array(self._cycle_ms)
        self._step_ms.clear()
        self._cycle_ms.clear()
        energy = self.sim.energy()
        if not all(math.isfinite(v) for v in energy.values()):
            self._fail("non-finite energy")
            energy = self.sim.energy()
        stats = self.sim.stats()
        recoveries = stats.get("guard_recoveries", 0) + stats.get("guard_degraded", 0)
        recovered = recoveries > self._guard_seen
        self._guard_seen = recoveries
        stability = self._stability if self._stability != "ok" else ("recovered" if recovered else "ok")
        target = self._p("real_time_factor")
        values = {
            "state": "paused" if self._paused else "running",
            "sim_time": self.sim.time,
            "steps": self.sim.step_count,
            "physics_dt": self.sim.dt,
            "clock_mode": self._p("clock_mode"),
            "step_ms_median": float(np.median(steps)) if len(steps) else 0.0,
            "step_ms_max": float(steps.max()) if len(steps) else 0.0,
            "cycle_ms_median": float(np.median(cycles)) if len(cycles) else 0.0,
            "cycle_ms_max": float(cycles.max()) if len(cycles) else 0.0,
            "steps_in_window": len(steps),
            "real_time_factor": rtf,
            "real_time_factor_target": target,
            "energy_total": energy["total"],
            "energy_kinetic": energy["kinetic"],
            "energy_elastic": energy["elastic"],
            "stability": stability,
            "stability_failures": self._failures,
            "last_failure": self._last_failure,
            "guard": stats.get("stability", "off"),
            "guard_recoveries": stats.get("guard_recoveries", 0),
            "guard_degraded": stats.get("guard_degraded", 0),
            "guard_substeps_total": stats.get("guard_substeps_total", 0),
            "guard_untangles": stats.get("guard_untangles", 0),
            "guard_last_event": stats.get("guard_last_event", ""),
            "dofs": stats.get("dofs", 0),
            "domains": len(self.domain_names),
            "surface_vertices": len(self.surface_ids),
            "held_wrenches": ",".join(sorted(self._held)),
            "inputs_received": self._counts["received"],
            "inputs_applied": self._counts["applied"],
            "inputs_late": self._counts["late"],
            "inputs_pending": len(self._queue),
            "rejected_total": sum(self._rejected.values()),
        }
        values.update({f"rejected_{k}": v for k, v in self._rejected.items()})
        values.update({"collider_poses_inside": self._inside_poses, "collider_inside_last": self._inside_last,
                       "colliders_inside_at_load": ",".join(sorted(self.sim.colliders_inside_at_load))})
        clock, lag = self._master, 0.0
        if clock is not None:
            values.update({"clock_master_time": clock.master, "clock_ticks": clock.ticks,
                           "clock_jumps_back": clock.jumps_back})
            if clock.mode == "follow":
                lag = clock.lag(self.sim.time)
                values["clock_lag"] = lag
            else:
                values["clock_steps_pending"] = clock.pending
        if stability == "failed":
            level, message = "error", f"failed: {self._last_failure}"
        elif stability == "recovered":
            level, message = "warn", f"recovered: {stats.get('guard_last_event', '')}"
        elif clock is None and not self._paused and target > 0 and len(steps) and rtf < 0.9 * target:
            level, message = "warn", f"running slower than real_time_factor {target:g}: {rtf:.3g}"
        elif clock is not None and clock.mode == "follow" and not self._paused and lag > FOLLOW_LAG_WARN_S:
            level, message = "warn", f"behind the master /clock by {lag:.3g} s"
        else:
            level, message = "ok", values["state"]
        return convert.diagnostics(self.sim.time, DIAGNOSTIC_NAME.format(node=self._topics.node_name),
                                   f"scene:{self.sim.scene.name}",
                                   level, message, values)

    def close(self):
        """Log the end and finish the recordings (idempotent)."""
        if self._closed:
            return
        self._closed = True
        self.get_logger().info(f"shutting down at t = {self.sim.time:.6g} s after {self.sim.step_count} steps; "
                               f"rejected inputs: {sum(self._rejected.values())}")
        self._close_recording()

    def destroy_node(self):
        if hasattr(self, "_closed"):
            self._close_recording()
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
            _spin(node, state)
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
