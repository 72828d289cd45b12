"""The simulation driver: the one loop the node, `mdss run` and `mdss replay` share.

    driver = Driver(sim, topics, world_frame, rates, emit, limits=Limits(), wrench_timeout_s=0.0)
    driver.start()                      # ~/surface/topology and the state at t = 0
    driver.submit(topic, data)          # an input's CDR bytes, from any thread: decoded and
                                        #   checked now, queued until due (or rejected, or
                                        #   dropped when the queue is full: each counted)
    driver.advance()                    # due inputs, wrench expiry, one guarded step and the
                                        #   outputs due after it; False if the step failed
    driver.reset("service")             # back to t = 0, recorded as an input
    driver.clear_forces()               # ~/clear_forces, recorded as an input
    driver.values()                     # the reproducible /diagnostics values

`emit(out, log_time_ns, is_input)` hears everything in the order it happens: every output
(ros_messages.Out: the node publishes and records it, `mdss run` records it, `mdss replay`
compares it with the recording) and every input when it is applied (is_input; recorded
with the run time as log time, so a replay applies it at the same step). Because the node,
the headless run and the replay all go through this class, a node recording replays bit
for bit by construction: there is no second copy of these rules to drift.

Inputs (docs/architecture.md, "Contracts: ROS interface").
- An input stamped s (sim time) is applied just before the step that starts at the first
  sim time t with s <= t + dt/2; an unstamped one (stamp 0) before the next step; inputs
  due at the same step are applied in stamp order, then arrival order. Stamps more than
  max_input_age before or max_input_lead after the sim time are rejected
  (validate.due_time). `submit(..., due_s=r)` gives the run time instead (a timeline
  event, a recorded input): it is applied before the first step starting at run time
  >= r - dt/2, and is not checked against the stamp limits.
- Every message is decoded and checked when it is submitted, so a bad one is rejected
  (and counted by kind) at once, whatever its stamp. An input that fails when applied
  (the simulator refuses it) is rejected as apply_error.
- The queue is bounded (queue_limit, None: unbounded for replays, which load a whole
  recording): a message that finds it full is dropped and counted (inputs_dropped), never
  lost silently. Inputs pending at a reset, and force inputs pending at clear_forces, are
  discarded and counted (inputs_cleared). So at any time
      received = applied + rejected_total + pending + dropped + cleared.
- submit() may be called from another thread than advance() (the node's subscriptions
  run beside the step): the queue and the counters are guarded by one lock, and the
  decoding and checking run outside it.
- A wrench that is not refreshed for wrench_timeout_s of sim time is cleared (0: held).

Failure. A step that raises, that the stability guard could not recover, or whose outputs
hold a non-finite value publishes nothing of that step: the driver resets to t = 0
(recorded as a reset input with reason "failure") and goes on. A replay, which runs the
same step, fails at the same place and resets by itself; it skips recorded resets whose
reason is "failure" (replay_failures=False).
"""
import heapq
import math
import threading
import time
from collections import deque

import numpy as np

from . import convert, validate
from .validate import InputRejected, Limits

#: reasons a reset is recorded with (the Header's frame_id of ~/reset_simulation/request)
RESET_REASONS = ("service", "failure", "clock")
#: input kinds that carry forces (~/clear_forces discards them from the queue)
FORCE_KINDS = ("wrench", "point_forces")
DEFAULT_QUEUE_LIMIT = 10000


def _ns(t):
    return int(round(float(t) * 1e9))


class _Item:
    __slots__ = ("due", "seq", "kind", "topic", "data", "command")

    def __init__(self, due, seq, kind, topic, data, command):
        self.due, self.seq, self.kind = due, seq, kind      # due: run time (s) or None (next step)
        self.topic, self.data, self.command = topic, data, command

    def __lt__(self, other):                                # heap order: unstamped first, then due
        a = -math.inf if self.due is None else self.due
        b = -math.inf if other.due is None else other.due
        return (a, self.seq) < (b, other.seq)


class Driver:
    """Inputs in, one guarded step, outputs out; see the module docstring.

    sim: a Simulator; topics: ros_messages.Topics; rates: ros_messages.OutputRates (Hz of
    sim time; rates.diagnostics > 0 emits /diagnostics on that sim-time grid, the node
    keeps it 0 and publishes its own on wall time); emit(out, log_time_ns, is_input);
    report(level, text, key=None) hears what a person should read (level "info", "warn",
    "error"; key: the rejection kind or "queue_full", for a reporter that throttles);
    rerun: a RerunLogger or None; on_collider_inside(name, info) hears collider poses
    that put a collider inside the body.
    """

    #: runtime parameters (the node's names) a run depends on; set_parameters records them.
    #: "colliders" stands for colliders.<name>.friction_static and _kinetic.
    PARAMETERS = ("points_publish_rate", "mesh_publish_rate", "marker_publish_rate", "pose_publish_rate",
                  "wrench_timeout_s", "world_frame", "max_force", "max_torque", "max_position",
                  "max_input_age", "max_input_lead", "max_point_forces", "colliders")

    def __init__(self, sim, topics, world_frame, rates, emit, limits=None, wrench_timeout_s=0.0,
                 emit_inputs=True, report=None, rerun=None, queue_limit=DEFAULT_QUEUE_LIMIT,
                 replay_failures=True, on_collider_inside=None):
        from ..record.ros_messages import SimOutputs
        self.sim = sim
        self.topics = topics
        self.world_frame = world_frame
        self.outputs = SimOutputs(sim, topics, world_frame, rates)
        self.emit = emit
        self.emit_inputs = emit_inputs
        self.report = report or (lambda level, text, key=None: None)
        self.rerun = rerun
        self.limits = limits or Limits()
        self.wrench_timeout_s = float(wrench_timeout_s)
        self.queue_limit = queue_limit
        self.replay_failures = replay_failures
        self.on_collider_inside = on_collider_inside
        self.handles = set(sim.scene["handles"])
        self.colliders = list(sim.scene["colliders"])
        self.offset = 0.0                  # run time at the last reset (sim time restarts at 0)
        self.held = {}                     # handle -> sim time its wrench was last set
        self._lock = threading.Lock()
        self._queue = []                   # heap of _Item
        self._seq = 0
        self.counts = dict.fromkeys(("received", "applied", "late", "dropped", "cleared"), 0)
        self.rejected = dict.fromkeys(validate.KINDS, 0)
        self.stability, self.failures, self.last_failure = "ok", 0, ""
        self._guard_seen = 0               # guard recoveries already reported
        self._failing = False
        self.step_ms = deque(maxlen=100000)          # since the last diagnostics window
        self.inside_poses, self.inside_last = 0, ""

    # ------------------------------------------------------------------ time
    @property
    def run_time(self):
        """Time since the start of the run, counting on across resets (the log time)."""
        return self.offset + self.sim.time

    def _log_ns(self):
        return _ns(self.run_time)

    # ------------------------------------------------------------------ inputs
    def submit(self, topic, data, due_s=None):
        """Take one input message (CDR bytes, or a decoded message): decode, check, queue.

        Returns True if queued; False if rejected (counted by kind, and reported) or
        dropped because the queue is full (counted in inputs_dropped)."""
        from ..record.ros_messages import cdr_bytes, decode_input, input_stamp
        with self._lock:
            self.counts["received"] += 1
        kind = self.topics.kind(topic)
        try:
            if kind not in self.topics.INPUTS:
                raise InputRejected("apply_error", f"{topic} is not an input topic of {self.topics.namespace}")
            if isinstance(data, (bytes, bytearray, memoryview)):
                data = bytes(data)
                try:
                    msg = decode_input(self.topics, topic, data)
                except Exception as err:  # noqa: BLE001 - any malformed CDR is a rejection, not a crash
                    raise InputRejected("malformed", f"the message does not decode: {type(err).__name__}: {err}") \
                        from err
            else:
                msg, data = data, cdr_bytes(data)
            try:
                command = self._check(kind, topic, msg)
            except InputRejected:
                raise
            except Exception as err:  # noqa: BLE001 - a message no check foresaw is still counted
                raise InputRejected("malformed", f"the message could not be checked: {type(err).__name__}: {err}") \
                    from err
            if due_s is None:
                stamp = validate.due_time(input_stamp(self.topics, topic, msg), self.sim.time, self.limits)
                due = None if stamp is None else self.offset + stamp
            else:
                due = float(due_s)
        except InputRejected as err:
            self._reject(err, topic)
            return False
        with self._lock:
            if self.queue_limit is not None and len(self._queue) >= self.queue_limit:
                self.counts["dropped"] += 1
                dropped = self.counts["dropped"]
            else:
                if due is not None and due < self.run_time - 0.5 * self.sim.dt:
                    self.counts["late"] += 1
                self._seq += 1
                heapq.heappush(self._queue, _Item(due, self._seq, kind, topic, data, command))
                return True
        self.report("warn", f"input queue full ({self.queue_limit} inputs): dropped {topic}; "
                            f"{dropped} dropped so far (/diagnostics inputs_dropped)", "queue_full")
        return False

    def _check(self, kind, topic, msg):
        """The command an input message asks for, or InputRejected (validate's checks)."""
        if kind == "wrench":
            w = msg.wrench
            return validate.wrench(msg.header.frame_id, (w.force.x, w.force.y, w.force.z),
                                   (w.torque.x, w.torque.y, w.torque.z), self.handles, self.limits)
        if kind == "point_forces":
            return validate.point_forces(msg, self.world_frame, self.limits)
        if kind == "collider_pose":
            name = self.topics.collider_of(topic)
            if name not in self.colliders:
                raise InputRejected("unknown_collider", f"the scene has no collider {name!r} "
                                                        f"(colliders: {', '.join(self.colliders) or 'none'})")
            validate.frame(msg.header.frame_id, self.world_frame, f"colliders/{name}/pose")
            p, o = msg.pose.position, msg.pose.orientation
            return (name,) + tuple(validate.pose((p.x, p.y, p.z), (o.x, o.y, o.z, o.w), self.limits))
        if kind == "reset":
            return msg.frame_id or "service"
        if kind == "parameters":
            return convert.parameter_values(msg)
        return None                                          # clear_forces

    def _reject(self, err, topic):
        with self._lock:
            self.rejected[err.kind] += 1
        self.report("warn", f"rejected {topic}: {err.reason}", err.kind)

    @property
    def pending(self):
        return len(self._queue)

    def apply_due(self):
        """Apply (and emit) the inputs due before the coming step; [(item, description)]."""
        limit = self.run_time + 0.5 * self.sim.dt
        with self._lock:
            due = []
            while self._queue and (self._queue[0].due is None or self._queue[0].due <= limit):
                due.append(heapq.heappop(self._queue))
        now = self.run_time
        due.sort(key=lambda i: (now if i.due is None else i.due, i.seq))
        applied = []
        for item in due:
            if item.kind == "reset" and item.command == "failure" and not self.replay_failures:
                with self._lock:
                    self.counts["applied"] += 1     # the replay's own failure reset stands for it
                continue
            if self.emit_inputs and item.kind != "reset":
                self._emit_input(item.topic, item.data)
            try:
                desc = self._apply(item)
            except (KeyError, ValueError) as err:
                self._reject(InputRejected("apply_error", f"{item.kind}: {err}"), item.topic)
                applied.append((item, f"rejected: {err}"))
                continue
            with self._lock:
                self.counts["applied"] += 1
            applied.append((item, desc))
        self._expire_wrenches()
        return applied

    def _emit_input(self, topic, data):
        from ..record.ros_messages import Out
        self.emit(Out(topic, self.topics.type_of(topic), data, self.sim.time), self._log_ns(), True)

    def _apply(self, item):
        sim, kind, c = self.sim, item.kind, item.command
        if kind == "wrench":
            handle, force, torque = c
            sim.set_wrench(handle, force, torque)
            if force.any() or torque.any():
                self.held[handle] = sim.time
            else:
                self.held.pop(handle, None)
            return f"wrench on {handle}: force {force.tolist()} torque {torque.tolist()}"
        if kind == "point_forces":
            points, forces, durations = c
            for p, f, d in zip(points, forces, durations):    # a few per message (max_point_forces)
                sim.add_point_force(p, f, float(d))
            return f"{len(points)} point force(s)"
        if kind == "collider_pose":
            name, pos, quat = c
            inside = sim.set_collider_pose(name, pos, quat)
            if inside:
                self.inside_poses += 1
                self.inside_last = f"{name}: {1e3 * inside['depth']:.1f} mm, {inside['vertices']} vertices"
                if self.on_collider_inside is not None:
                    self.on_collider_inside(name, inside)
            if self.rerun is not None:
                self.rerun.collider_pose(name, pos, quat)
            return f"collider {name} at {pos.tolist()}"
        if kind == "clear_forces":
            self._clear_forces()
            return "clear_forces"
        if kind == "reset":
            self._reset(c, record=self.emit_inputs, clear_queue=False)
            return f"reset ({c})"
        if kind == "parameters":
            self._apply_parameters(c)
            return f"parameters {c}"
        raise ValueError(f"unknown input kind {kind!r}")

    def set_parameters(self, values):
        """Runtime parameter values ({node parameter name: value}, names of PARAMETERS) the
        run depends on: applied now, between steps, and recorded as an input (a
        rcl_interfaces/ParameterEvent), so a replay applies them at the same step.
        ValueError (nothing applied) for a bad friction pair."""
        from ..record.ros_messages import cdr_bytes
        self._apply_parameters(values)
        if self.emit_inputs:
            self._emit_input(self.topics.parameters,
                             cdr_bytes(convert.parameter_event(self.sim.time, self.topics.namespace, values)))

    def _apply_parameters(self, values):
        from dataclasses import replace
        friction = {}
        for name, value in values.items():
            if name.startswith("colliders.") and name.rpartition(".")[2] in ("friction_static", "friction_kinetic"):
                collider, _, leaf = name[len("colliders."):].rpartition(".")
                friction.setdefault(collider, dict(zip(("static", "kinetic"), self.sim.colliders[collider].friction)))
                friction[collider][leaf[len("friction_"):]] = float(value)
            elif name.endswith("_publish_rate"):
                setattr(self.outputs.rates, name[:-len("_publish_rate")], float(value))
            elif name == "wrench_timeout_s":
                self.wrench_timeout_s = float(value)
            elif name == "world_frame":
                self.world_frame = self.outputs.frame = value
            elif name in Limits.__dataclass_fields__:
                self.limits = replace(self.limits, **{name: value})
        for collider, mu in friction.items():
            self.sim.set_collider_friction(collider, mu["static"], mu["kinetic"])
            # in the scene too, so a reset (which rebuilds colliders from it) keeps them
            self.sim.scene.data["colliders"][collider]["friction"] = dict(mu)

    def _expire_wrenches(self):
        timeout = self.wrench_timeout_s
        if timeout <= 0:
            return
        for handle, t_set in list(self.held.items()):
            if self.sim.time - t_set >= timeout - 1e-9:
                self.sim.set_wrench(handle)
                del self.held[handle]
                self.report("info", f"wrench on {handle!r} cleared: not refreshed for "
                                    f"wrench_timeout_s = {timeout:g} s")

    def clear_forces(self):
        """~/clear_forces: every wrench and point force, and the force inputs still pending;
        recorded as an input. Returns (handles that held a wrench, pending inputs discarded)."""
        from ..record.ros_messages import cdr_bytes
        held = sorted(self.held)
        with self._lock:
            keep = [i for i in self._queue if i.kind not in FORCE_KINDS]
            discarded = len(self._queue) - len(keep)
            heapq.heapify(keep)
            self._queue = keep
            self.counts["cleared"] += discarded
        if self.emit_inputs:
            self._emit_input(self.topics.clear_forces, cdr_bytes(convert.header(self.sim.time, "")))
        self._clear_forces()
        return held, discarded

    def _clear_forces(self):
        self.sim.clear_forces()
        self.held.clear()

    # ------------------------------------------------------------------ reset, failure
    def reset(self, reason="service"):
        """Back to t = 0 (sim time; the run time goes on), recorded as an input with its
        reason; pending inputs are discarded (counted), the state at t = 0 is emitted."""
        if reason == "service" or reason == "clock":
            self.stability, self.last_failure = "ok", ""
        self._reset(reason, record=self.emit_inputs, clear_queue=True)

    def _reset(self, reason, record, clear_queue):
        from ..record.ros_messages import cdr_bytes
        if record:
            self._emit_input(self.topics.reset, cdr_bytes(convert.header(self.sim.time, reason)))
        self.offset += self.sim.time
        self.sim.reset()
        self._guard_seen = 0
        self.held.clear()
        if clear_queue:
            with self._lock:
                self.counts["cleared"] += len(self._queue)
                self._queue = []
        self._emit_state(None)

    def fail(self, what):
        """A step or its outputs went wrong: nothing of it is published; reset to t = 0."""
        self.stability, self.failures, self.last_failure = "failed", self.failures + 1, what
        self.report("error", f"{what}: nothing of it is published; resetting the simulation to t = 0 "
                             f"(failure {self.failures})")
        if not self._failing:
            self._failing = True
            try:
                self._reset("failure", record=self.emit_inputs, clear_queue=self.queue_limit is not None)
            finally:
                self._failing = False

    # ------------------------------------------------------------------ stepping, outputs
    def start(self):
        """The topology (once) and the state at t = 0; the process's compiled kernels
        loaded from numba's cache first (threads.preload_kernels), so that no step of the run, the
        first contact's included, waits for one."""
        from ..threads import preload_kernels
        preload_kernels()
        for out in self.outputs.topology():
            self.emit(out, _ns(self.offset + out.stamp_s), False)
        self._emit_state(None)
        if self.outputs.rates.diagnostics > 0:
            self.emit_diagnostics()
        if self.rerun is not None:
            self._log_rerun(None)

    def advance(self):
        """One physics step: due inputs, Simulator.step() and the outputs due after it.
        Returns False when the step failed (the driver has reset)."""
        self.apply_due()
        sim = self.sim
        k = sim.step_count
        t0 = time.perf_counter()
        try:
            sim.step()
        except Exception as err:  # noqa: BLE001 - a solver failure must not stop the run
            self.fail(f"the step from t = {sim.time:.6g} s raised {type(err).__name__}: {err}")
            return False
        if sim.stats().get("stability") == "failed":
            # The guard kept the last good state; nothing diverged is published.
            self.fail(f"the step to t = {sim.time:.6g} s diverged and could not be recovered "
                      f"({sim.stats().get('guard_reason', '')})")
            return False
        step_ms = 1e3 * (time.perf_counter() - t0)
        self.step_ms.append(step_ms)
        if not self._emit_state(k):
            return False
        if self.outputs.diagnostics_due(k):
            self.emit_diagnostics()
        if self.rerun is not None:
            self._log_rerun(step_ms)
        return True

    def _emit_state(self, previous_step):
        """Emit /clock and every output due after the step from previous_step (None: all);
        False (and a failure reset) when the state is not finite."""
        try:
            outs = self.outputs.state(previous_step)
        except FloatingPointError as err:
            if previous_step is None and self._failing:
                return False                 # the state at t = 0 itself: nothing to fall back to
            self.fail(str(err))
            return False
        for out in outs:
            self.emit(out, _ns(self.offset + out.stamp_s), False)
        return True

    def _log_rerun(self, step_ms):
        try:
            self.rerun.log_step(step_ms)
        except Exception as err:  # noqa: BLE001 - a viewer gone away must not stop the simulation
            self.report("error", f"rerun logging stopped: {type(err).__name__}: {err}; the simulation goes on")
            rerun, self.rerun = self.rerun, None
            try:
                rerun.close()
            except Exception:  # noqa: BLE001
                pass

    # ------------------------------------------------------------------ diagnostics
    def stability_report(self):
        """ok, recovered (the guard rolled back a step since the last report) or failed."""
        stats = self.sim.stats()
        recoveries = stats.get("guard_recoveries", 0) + stats.get("guard_degraded", 0)
        recovered = recoveries > self._guard_seen
        self._guard_seen = recoveries
        return self.stability if self.stability != "ok" else ("recovered" if recovered else "ok")

    def values(self, stability=None):
        """The reproducible /diagnostics values (the same in a run and its replay)."""
        sim = self.sim
        energy = sim.energy()
        if not all(math.isfinite(v) for v in energy.values()):
            self.fail("non-finite energy")
            energy = sim.energy()
        stats = sim.stats()
        with self._lock:
            counts, rejected, pending = dict(self.counts), dict(self.rejected), len(self._queue)
        values = {
            "sim_time": sim.time,
            "steps": sim.step_count,
            "physics_dt": sim.dt,
            "energy_total": energy["total"],
            "energy_kinetic": energy["kinetic"],
            "energy_elastic": energy["elastic"],
            "stability": stability if stability is not None else self.stability_report(),
            "stability_failures": self.failures,
            "last_failure": self.last_failure,
            "guard": stats.get("stability", "off"),
            "guard_recoveries": stats.get("guard_recoveries", 0),
            "guard_degraded": stats.get("guard_degraded", 0),
            "guard_substeps_total": stats.get("guard_substeps_total", 0),
            "guard_untangles": stats.get("guard_untangles", 0),
            "guard_last_event": stats.get("guard_last_event", ""),
            "dofs": stats.get("dofs", 0),
            "domains": len(self.outputs.domain_names),
            "surface_vertices": len(self.outputs.surface_ids),
            "held_wrenches": ",".join(sorted(self.held)),
            "inputs_received": counts["received"],
            "inputs_applied": counts["applied"],
            "inputs_late": counts["late"],
            "inputs_pending": pending,
            "inputs_dropped": counts["dropped"],
            "inputs_cleared": counts["cleared"],
            "input_queue_limit": self.queue_limit if self.queue_limit is not None else 0,
            "rejected_total": sum(rejected.values()),
        }
        values.update({f"rejected_{k}": v for k, v in rejected.items()})
        values.update({"collider_poses_inside": self.inside_poses, "collider_inside_last": self.inside_last,
                       "colliders_inside_at_load": ",".join(sorted(sim.colliders_inside_at_load))})
        return values

    def take_step_ms(self):
        """The step times (ms) since the last call, as an array."""
        steps = np.array(self.step_ms)
        self.step_ms.clear()
        return steps

    def emit_diagnostics(self):
        """/diagnostics on the sim-time grid (`mdss run`): the values plus the window's timing
        (ros_messages.TIMING_KEYS, blanked when a replay compares)."""
        from ..record.ros_messages import Out
        steps = self.take_step_ms()
        values = {"state": "running"}
        values.update(self.values())
        values.update({"step_ms_median": float(np.median(steps)) if len(steps) else 0.0,
                       "step_ms_max": float(steps.max()) if len(steps) else 0.0,
                       "real_time_factor": 0.0})
        level, message = ("error", f"failed: {self.last_failure}") if values["stability"] == "failed" else \
            ("ok", "running")
        msg = convert.diagnostics(self.sim.time, f"{self.topics.node_name}: simulation",
                                  f"scene:{self.sim.scene.name}", level, message, values)
        from ..record.ros_messages import cdr_bytes
        out = Out(self.topics.diagnostics, self.topics.type_of(self.topics.diagnostics), cdr_bytes(msg), self.sim.time)
        self.emit(out, self._log_ns(), False)
