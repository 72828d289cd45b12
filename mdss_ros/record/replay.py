"""Recorded headless runs and their replay (`mdss run --mcap/--rrd`, `mdss replay`).

Recording (what `mdss run SCENE --mcap F --rrd R` does, usable from Python):

    rec = RunRecording(mcap="run.mcap", rrd="run.rrd")   # opens both now: a bad path fails
    sim = rec.build("cantilever", overrides)             # the Simulator, cache events noted
    rec.start(sim)                                       # metadata, topology, state at t = 0
    for k in range(steps):
        events, ok = rec.advance()                       # due inputs, the step, its outputs
    rec.finish()                                         # idempotent; also on SIGINT/SIGTERM

The loop is the node's: mdss_ros.ros.driver.Driver, the one driver the node, the
headless run and the replay share. Every timeline event becomes the message the node
would receive (ros_messages.event_messages), stamped with its time, and goes through the
driver as a received message does: decoded, checked, applied at its step and recorded
then (log time = the run time of the step it precedes). The outputs are the node's
topics under /mdss (ros_messages.SimOutputs). Log times are sim
time in ns; publish times are the wall clock (time.time_ns()) at which the message was
produced, which is how a killed run's loss is measured. The MCAP also holds metadata
`mdss_run` (the validated scene as JSON, its base folder, namespace, frame, output
rates, dt, versions, precompute cache events) and the scene as an attachment
`scene.yaml`, so replay needs nothing else.

Replay (`mdss replay LOG.mcap [--scene S] [--check]`):

    result = replay("run.mcap", check=True)    # ReplayError for an unreadable/tampered file
    result.ok, result.first_mismatch, result.compared, result.mismatches

reads the file once with CRC checks (chunk CRCs, the data-section CRC, the summary CRC),
builds the scene it holds (or --scene), feeds the same driver the recorded inputs at their log times
(the run time at which the run applied them: a node applies a late input after its stamp,
so the stamp is not enough), with ~/reset_simulation calls (recorded as inputs) resetting
the simulator where the run did and the node's wrench_timeout_s and input limits taken from
the metadata, steps until the last recorded /clock, and with check=True compares every
recorded output message with the replayed one byte for byte (/diagnostics of `mdss run`
with its wall-time values, ros_messages.TIMING_KEYS, blanked; the node's /diagnostics come
from a wall-clock timer and are listed as not compared). The first mismatch is reported with
topic, index, sim time, first differing byte and, for ~/surface/points, the largest
position difference. Bit-for-bit equality needs the same machine, package versions and
precompute cache (MDSS_CACHE_DIR): a cache stage rebuilt during replay is reported.
"""
import hashlib
import json
import platform
import sys
import time
import zlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import MdssError
from ..ros.driver import Driver

MCAP_MAGIC = b"\x89MCAP0\r\n"


class ReplayError(MdssError):
    """A recording cannot be replayed: unreadable, truncated, tampered, or not of mdss."""


def _ns(t):
    return int(round(float(t) * 1e9))


@dataclass
class Input:
    due_s: float          # apply before the first step starting at run time (time since the
                          # start, counting on across resets) r with due_s <= r + dt/2
    topic: str
    data: bytes
    event: dict = None    # the timeline event it came from (recording only)


def build_simulator(scene, overrides=None, base_dir=None):
    """(Simulator, cache events) of a scene (name, path, dict or Scene)."""
    from ..budget import build_simulator as build
    from ..precompute import PrecomputeCache
    from ..scene import Scene, load_scene
    if isinstance(scene, dict) and base_dir is not None:
        scene = load_scene(Scene(data=scene, source="<recording>", base_dir=Path(base_dir)))
    cache = PrecomputeCache()
    sim = build(scene, overrides=overrides or None, cache=cache)
    return sim, [list(e) for e in cache.events]


def run_metadata(sim, namespace, world_frame, rates, cache_events=(), **extra):
    """The `mdss_run` metadata of a recording (`mdss run --mcap` and the node): everything
    replay needs to rebuild the run. rates: dict of OutputRates fields; extra: recorder-
    specific string entries (the node's recorder, wrench timeout, limits)."""
    from ..version import __version__
    scene = sim.scene
    meta = {
        "format": "mdss_run/1",
        "scene_name": scene.name,
        "scene_source": str(scene.source),
        "scene_base_dir": str(Path(scene.base_dir).resolve()),
        "scene_json": json.dumps(scene.data, sort_keys=True),
        "namespace": namespace,
        "world_frame": world_frame,
        "rates_json": json.dumps(dict(rates)),
        "dt": repr(float(sim.dt)),
        "mdss_ros_version": __version__,
        "numpy_version": np.__version__,
        "python": sys.version.split()[0],
        "platform": platform.platform(),
        "machine": platform.machine(),
        "cache_events_json": json.dumps([[s, k, Path(p).name if k in ("hit", "saved", "miss") else p]
                                         for s, k, p in cache_events]),
        "log_time": "sim time (ns) since the start, counting on across resets",
        "publish_time": "wall clock (ns since the epoch) when the message was produced",
    }
    meta.update(extra)
    return meta


def timeline_inputs(events, topics, world_frame):
    """Input list (application order) of a scene timeline: each event as CDR message bytes."""
    from .ros_messages import cdr_bytes, event_messages, input_stamp
    out = []
    for ev in sorted(events, key=lambda e: e["t"]):
        for topic, msg in event_messages(ev, topics, world_frame):
            out.append(Input(input_stamp(topics, topic, msg), topic, cdr_bytes(msg), ev))
    return out


# --------------------------------------------------------------------- recording
class RunRecording:
    """A headless run recorded to MCAP and/or rerun; see the module docstring."""

    def __init__(self, mcap=None, rrd=None, namespace=None, world_frame=None, rates=None,
                 flush_interval_s=0.5, out=print):
        from .mcap_recorder import McapRecorder
        from .ros_messages import NAMESPACE, WORLD_FRAME, OutputRates, Topics
        self.topics = Topics(namespace or NAMESPACE)
        self.world_frame = world_frame or WORLD_FRAME
        self.rates = rates or OutputRates()
        self.out = out
        self.rrd = rrd
        self.rerun = None
        self.driver = None
        self._events = []                  # (due, timeline event) not yet applied
        self.cache_events = []
        self.recorder = None
        self.stop_signal = None
        self._old_handlers = {}
        if rrd:
            from .rerun_logger import RerunLogError
            try:
                with open(rrd, "wb"):
                    pass
            except OSError as err:
                raise RerunLogError(f"cannot write rerun file {rrd}: {err.strerror or err}") from err
        if mcap:
            from .mcap_recorder import bag_paths
            path, folder = bag_paths(mcap)
            self.recorder = McapRecorder(path, flush_interval_s=flush_interval_s, bag_metadata=folder)

    def _stop_on_signals(self):
        """SIGINT/SIGTERM set stop_signal (the run loop stops and finishes the files); a
        second one raises KeyboardInterrupt. Restored by finish()."""
        import signal

        def handler(signum, frame):
            if self.stop_signal is not None:
                raise KeyboardInterrupt
            self.stop_signal = signum

        for s in (signal.SIGINT, signal.SIGTERM):
            try:
                self._old_handlers[s] = signal.signal(s, handler)
            except ValueError:          # not the main thread: the caller handles signals
                pass

    @property
    def stop_requested(self):
        return self.stop_signal is not None

    def build(self, scene, overrides=None):
        sim, self.cache_events = build_simulator(scene, overrides)
        return sim

    def _metadata(self, sim):
        return run_metadata(sim, self.topics.namespace, self.world_frame, self.rates.__dict__, self.cache_events)

    def start(self, sim):
        from .rerun_logger import RerunLogger
        import yaml
        if self.recorder is not None:
            self.recorder.add_metadata("mdss_run", self._metadata(sim))
            self.recorder.add_attachment("scene.yaml", yaml.safe_dump(json.loads(json.dumps(sim.scene.data)),
                                                                      sort_keys=False).encode(),
                                         media_type="application/yaml")
        self._stop_on_signals()
        if self.rrd:
            self.rerun = RerunLogger(sim, mode="file", path=self.rrd)
        self.driver = Driver(sim, self.topics, self.world_frame, self.rates, self._write, rerun=self.rerun,
                             report=self._report, queue_limit=None)
        for item in timeline_inputs(sim.scene["timeline"], self.topics, self.world_frame):
            if self.driver.submit(item.topic, item.data, due_s=item.due_s):   # a rejected one is reported now
                self._events.append((item.due_s, item.event))
        self.driver.start()

    def _report(self, level, text, key=None):
        self.out(f"  {text}")

    def _write(self, out, log_time_ns, is_input):
        if self.recorder is not None:
            self.recorder.write(out.topic, out.data, log_time_ns, type_name=out.type_name,
                                qos=self.topics.qos_of(out.topic), publish_time_ns=time.time_ns())

    def advance(self):
        """One step through the driver; the timeline events applied before it (each once),
        and whether the step went well (False: it failed and the driver reset)."""
        limit = self.driver.run_time + 0.5 * self.driver.sim.dt
        events = []
        while self._events and self._events[0][0] <= limit:
            ev = self._events.pop(0)[1]
            if not events or events[-1] is not ev:
                events.append(ev)
        return events, self.driver.advance()

    def finish(self):
        """Finish the MCAP and the .rrd; a summary line per file. Idempotent."""
        import signal
        for sig, h in self._old_handlers.items():
            signal.signal(sig, h)
        self._old_handlers = {}
        lines = []
        if self.rerun is not None:
            self.rerun.close()
            lines.append(f"rerun: {self.rrd} ({self.rerun.frames} frames)")
        if self.recorder is not None:
            s = self.recorder.finish()
            if s["error"]:
                lines.append(f"MCAP: {s['error']} (the file keeps the chunks completed before; "
                             f"read it with mdss_ros.record.mcap_recorder.recover)")
            else:
                lines.append(f"MCAP: {s['path']} ({s['messages']} messages on {len(s['topics'])} topics, "
                             f"{s['bytes'] / 1e6:.2f} MB)")
        return lines


# --------------------------------------------------------------------- reading
@dataclass
class Recording:
    path: str
    metadata: dict
    inputs: list                     # [Input] in file order
    outputs: dict                    # topic -> [(log_time, sha256 digest)]
    clock_times: list                # /clock log times (ns)
    channels: dict                   # topic -> type name
    message_count: int = 0


def verify_summary_crc(path):
    """None if the footer's summary CRC matches (or there is no summary), else the problem."""
    size = Path(path).stat().st_size
    with open(path, "rb") as f:
        head = f.read(8)
        if size < 8 + 37 or head != MCAP_MAGIC:
            return "not an MCAP file (bad magic)"
        f.seek(size - 37)
        tail = f.read(37)
        if tail[-8:] != MCAP_MAGIC:
            return "the file is truncated (no footer): the recording did not finish"
        footer = tail[:29]
        if footer[0] != 0x02:
            return "the footer record is damaged"
        summary_start = int.from_bytes(footer[9:17], "little")
        crc = int.from_bytes(footer[25:29], "little")
        if crc == 0:
            return None
        start = summary_start if summary_start else size - 37
        if not 8 <= start <= size - 37:
            return "the footer points outside the file"
        f.seek(start)
        value, left = 0, size - 12 - start            # the summary and the footer up to its CRC
        while left > 0:
            block = f.read(min(left, 1 << 20))
            if not block:
                break
            value = zlib.crc32(block, value)
            left -= len(block)
    if value != crc:
        return "summary section CRC mismatch (the file was modified)"
    return None


def _digest(topic, data):
    """SHA-256 of an output message; /diagnostics with its wall-time values blanked."""
    if topic == "/diagnostics":
        from .ros_messages import mask_timing
        data = mask_timing(bytes(data))
    return hashlib.sha256(data).digest()


_INPUT_LEAVES = ("/wrench", "/point_forces", "/clear_forces/request", "/reset_simulation/request", "/pose",
                 "/parameter_events")


def read_recording(path, topics=None):
    """Read and verify a recording in one pass (StreamReader with CRC checks): metadata,
    input messages (bytes) and, per output topic, (log time, digest) of each message."""
    from mcap.records import Channel, Footer, Message, Metadata, Schema
    from mcap.stream_reader import StreamReader
    from .mcap_recorder import RecordingError, mcap_of
    from .ros_messages import Topics, decode_input
    try:
        path = str(mcap_of(path))
    except RecordingError as err:
        raise ReplayError(str(err)) from err
    if not Path(path).is_file():
        raise ReplayError(f"{path}: no such file")
    problem = verify_summary_crc(path)
    if problem:
        raise ReplayError(f"{path}: {problem}")
    metadata, schemas, channels = {}, {}, {}
    maybe_inputs, outputs = [], {}
    count, footer = 0, False
    try:
        with open(path, "rb") as f:
            reader = StreamReader(f, validate_crcs=True, record_size_limit=1 << 31)
            for rec in reader.records:
                if isinstance(rec, Schema):
                    schemas[rec.id] = rec
                elif isinstance(rec, Channel):
                    channels[rec.id] = rec
                elif isinstance(rec, Metadata):
                    metadata[rec.name] = dict(rec.metadata)
                elif isinstance(rec, Message):
                    count += 1
                    topic = channels[rec.channel_id].topic
                    if topic.endswith(_INPUT_LEAVES):          # sorted out once the namespace is known
                        maybe_inputs.append((topic, rec.log_time, bytes(rec.data)))
                    outputs.setdefault(topic, []).append((rec.log_time, _digest(topic, rec.data)))
                elif isinstance(rec, Footer):
                    footer = True
    except Exception as err:  # noqa: BLE001 - any reader failure means a damaged file
        raise ReplayError(f"{path}: damaged MCAP ({type(err).__name__}: {err}); "
                          f"it was modified or truncated after recording") from err
    if not footer:
        raise ReplayError(f"{path}: the file ends before its footer: the recording did not finish")
    run = metadata.get("mdss_run", {})
    if topics is None:
        topics = Topics(run.get("namespace", "/mdss"))
    inputs = []
    for topic, log_time, data in maybe_inputs:
        if topics.is_input(topic):
            try:
                decode_input(topics, topic, data)
            except Exception as err:  # noqa: BLE001
                raise ReplayError(f"{path}: input message on {topic} does not decode: {err}") from err
            # Log time is when the run applied it (the node applies a late input later than
            # its stamp says), so it, not the stamp, says when to apply it again.
            inputs.append(Input(log_time * 1e-9, topic, data))
            outputs.pop(topic, None)
    return Recording(path, metadata, inputs, outputs,
                     [t for t, _ in outputs.get(topics.clock, [])],
                     {c.topic: schemas[c.schema_id].name if c.schema_id in schemas else "" for c in channels.values()},
                     count)


def _recorded_message(path, topic, index):
    """The bytes of the index-th recorded message on topic."""
    from mcap.reader import make_reader
    with open(path, "rb") as f:
        for i, (_, _, msg) in enumerate(make_reader(f).iter_messages(topics=[topic], log_time_order=False)):
            if i == index:
                return bytes(msg.data)
    return None


def _explain(topic, recorded, replayed, topics):
    if recorded is None:
        return "the recording has no such message"
    n = min(len(recorded), len(replayed))
    diff = next((i for i in range(n) if recorded[i] != replayed[i]), n)
    text = f"{len(recorded)} vs {len(replayed)} bytes, first difference at byte {diff}"
    if topics.kind(topic) == "points":
        try:
            from sensor_msgs.msg import PointCloud2
            from rclpy.serialization import deserialize_message
            a, b = (np.frombuffer(deserialize_message(x, PointCloud2).data, dtype="<f4").reshape(-1, 4)[:, :3]
                    for x in (recorded, replayed))
            if a.shape == b.shape:
                text += f"; largest position difference {float(np.abs(a - b).max()):.3e} m"
        except Exception:  # noqa: BLE001 - the explanation is best effort
            pass
    return text


@dataclass
class ReplayResult:
    steps: int
    sim_time: float
    inputs: int
    compared: int = 0
    mismatches: int = 0
    missing: dict = field(default_factory=dict)     # topic -> recorded messages not reproduced
    extra: dict = field(default_factory=dict)       # topic -> replayed messages not recorded
    first_mismatch: str = None
    warnings: list = field(default_factory=list)
    not_compared: dict = field(default_factory=dict)   # topic -> (recorded messages, why)

    @property
    def ok(self):
        return self.mismatches == 0 and not self.missing and not self.extra


def replay(path, scene=None, overrides=None, check=False, out=print):
    """Replay a recording (see the module docstring); ReplayError for a bad file or scene."""
    from .ros_messages import OutputRates, Topics
    rec = read_recording(path)
    path = rec.path
    run = rec.metadata.get("mdss_run")
    if run is None and scene is None:
        raise ReplayError(f"{path}: no mdss_run metadata (not recorded by mdss run?); give --scene")
    run = run or {}
    topics = Topics(run.get("namespace", "/mdss"))
    world_frame = run.get("world_frame", "world")
    from ..ros.validate import Limits
    try:
        rates = OutputRates(**json.loads(run["rates_json"])) if "rates_json" in run else OutputRates()
        limits = Limits(**json.loads(run["limits_json"])) if "limits_json" in run else None
        wrench_timeout_s = float(run.get("wrench_timeout_s", "0"))
        if scene is None:
            scene = json.loads(run["scene_json"])
    except (KeyError, TypeError, ValueError) as err:
        raise ReplayError(f"{path}: the mdss_run metadata is damaged ({type(err).__name__}: {err})") from err
    try:
        sim, events = build_simulator(scene, overrides, base_dir=run.get("scene_base_dir") if isinstance(scene, dict) else None)
    except MdssError as err:
        raise ReplayError(f"{path}: the recorded scene does not build: {err}") from err
    if not rec.clock_times:
        raise ReplayError(f"{path}: no /clock messages: nothing to replay")
    end_s = rec.clock_times[-1] * 1e-9
    result = ReplayResult(steps=0, sim_time=0.0, inputs=len(rec.inputs))
    if run.get("recorder") == "mdss_ros.node":
        # The node publishes /diagnostics on a wall-clock timer: neither their number nor
        # their sim times are reproducible, so they are left out of the check.
        n = len(rec.outputs.pop(topics.diagnostics, []))
        if n:
            result.not_compared[topics.diagnostics] = (n, "published on the node's wall-clock timer")
        rates.diagnostics = 0.0
    rebuilt = [f"{s} ({k})" for s, k, _ in events if k not in ("hit",)]
    if rebuilt and check:
        result.warnings.append("precompute stages not loaded from the cache: " + ", ".join(rebuilt)
                               + "; bases rebuilt here may differ in the last bits from the recording's")
    if run.get("numpy_version") and run["numpy_version"] != np.__version__:
        result.warnings.append(f"recorded with numpy {run['numpy_version']}, replaying with {np.__version__}")

    cursor = {t: 0 for t in rec.outputs}
    produced = {}

    def report(level, text, key=None):
        out(f"  {text}")

    def compare(o, log_time_ns, is_input=False):
        produced[o.topic] = produced.get(o.topic, 0) + 1
        if not check:
            return
        i = cursor.get(o.topic, 0)
        expected = rec.outputs.get(o.topic, [])
        if i >= len(expected):
            result.extra[o.topic] = result.extra.get(o.topic, 0) + 1
            return
        cursor[o.topic] = i + 1
        result.compared += 1
        if _digest(o.topic, o.data) != expected[i][1]:
            result.mismatches += 1
            if result.first_mismatch is None:
                recorded = _recorded_message(path, o.topic, i)
                data = o.data
                if o.topic == "/diagnostics" and recorded is not None:
                    from .ros_messages import mask_timing
                    recorded, data = mask_timing(recorded), mask_timing(data)
                result.first_mismatch = (f"{o.topic} message {i} (t = {o.stamp_s:.6f} s): "
                                         + _explain(o.topic, recorded, data, topics))

    # The node's own driver, fed the recorded inputs at the run times they were applied;
    # a failed step resets by itself, as it did in the run, so the run's "failure" resets
    # are not applied a second time.
    driver = Driver(sim, topics, world_frame, rates, compare, emit_inputs=False, report=report,
                    limits=limits, wrench_timeout_s=wrench_timeout_s, queue_limit=None, replay_failures=False)
    for item in rec.inputs:
        driver.submit(item.topic, item.data, due_s=item.due_s)
    driver.start()
    while True:
        driver.apply_due()
        if driver.run_time >= end_s - 0.5 * sim.dt:
            break
        driver.advance()
        result.steps += 1
    if check:
        for topic, expected in rec.outputs.items():
            left = len(expected) - cursor.get(topic, 0)
            if left > 0:
                result.missing[topic] = left
    if driver.pending:
        result.warnings.append(f"{len(driver.pending)} recorded input(s) stamped after the last step were not applied")
    result.sim_time = sim.time
    return result
