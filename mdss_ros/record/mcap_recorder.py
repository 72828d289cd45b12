"""MCAP recording in rosbag2's conventions, crash-safe.

    from mdss_ros.record.mcap_recorder import McapRecorder, RecordingError

    with McapRecorder("run.mcap", flush_interval_s=0.5) as rec:   # RecordingError if unwritable
        rec.add_metadata("mdss_scene", {"scene_json": ...})     # any time
        rec.write("/mdss/wrench", msg, log_time_ns)             # a message object, or
        rec.write("/mdss/surface/points", cdr_bytes, log_time_ns,
                  type_name="sensor_msgs/msg/PointCloud2", qos=qos_profile(10))
        rec.write_tf(transforms, log_time_ns)                   # /tf as tf2_msgs/msg/TFMessage
    # leaving the block calls finish(): summary, indexes, footer. finish() is idempotent.

What a file holds (what rosbag2's MCAP storage writes, so `ros2 bag`, rosbags, the
mcap_ros2 decoder and Foxglove read it): profile `ros2`; one schema per type, named
`pkg/msg/Type`, encoding `ros2msg`, data = rosbags' `generate_msgdef(type, ros_version=2)`
of the Jazzy typestore (ros.convert.TYPESTORE): the type's definition followed by each
dependency after a line of 80 `=` and a line `MSG: pkg/Type`. That is the ros2msg
format rosbag2 writes, in rosbags' normal form: comments and default values left out,
field types written in full (`geometry_msgs/Pose`), dependencies in field order, depth
first (rosbag2 copies the installed .msg files verbatim, dependencies sorted); every
decoder reads both alike, and the type hash below is the same. One channel per topic,
message encoding `cdr`, metadata `offered_qos_profiles` (rosbag2 YAML, v9 names) and
`topic_type_hash` (RIHS01, rosbags' `hash_rihs01`, equal to the hash rosidl installs
in share/<pkg>/msg/<T>.json; tests check it); payload = CDR bytes as given, or for a
message object (a TYPESTORE dataclass) rosbags' CDR with zeroed padding
(ros_messages.cdr_bytes), so equal messages are equal bytes; zstd
chunks with message indexes, chunk CRCs and the data-section CRC (so any changed byte
of the data section is detected); at finish the `rosbag2` metadata record rosbag2 writes and,
with bag_metadata=True, a `metadata.yaml` beside the file (version 9) so its folder
opens as a bag (`ros2 bag info DIR`).

Times. log_time_ns is whatever clock the caller records in (mdss run: sim time, so
players run at sim speed); a log_time earlier than the last one written is raised to it
(counted in `clamped`), so log times never decrease. publish_time_ns defaults to log_time.

Crash safety.
- finish() writes the summary; it runs on leaving the `with` block, on an exception, at
  interpreter exit (atexit) and from `stop_on_signals()`-driven loops.
- A writer thread. write() checks the message, fixes its log time and sequence number and
  queues it; every BATCH_S the thread adds what was queued to the file in order,
  compresses the chunks and flushes them. Closing a chunk on the caller's thread took a
  fifth of the node's time on armadillo_class with its 30 Hz points recorded (zstd: 31 ms
  for a 4.6 MB chunk of them; session 26); the thread does it on the other core (zstd
  and crc32 release the GIL). At most QUEUE_LIMIT messages and QUEUE_BYTES wait: a disk
  slower than the simulation makes write() wait rather than memory grow.
- SIGKILL: the data section is written as complete chunks: a chunk is closed and flushed
  to the OS whenever `flush_interval_s` of wall time passed since the last flush (the
  thread checks every BATCH_S, so an idle recorder flushes too) or it reaches chunk_size
  bytes. A killed process therefore loses at most about
  flush_interval_s * 1.25 of data; `recover()` (or mcap's StreamReader) reads a file
  that lacks its summary. The OS page cache survives a process kill; power loss is not
  covered (no fsync).
- Errors. An unwritable path raises RecordingError from the constructor (the header is
  written and flushed at once, so a full disk shows there too); so do a topic's type
  change, an unknown type and a time outside 0..2^64 ns, from write(). A write error
  later (disk full), or any error of the writer thread, stops the recording: `error` says
  why, `on_error(text)` hears it once, on the caller's thread at its next write, flush or
  finish (default: a line on stderr), later writes return False, and the caller's
  simulation goes on. on_error may call the recorder.

Signals. `stop_on_signals()` makes SIGINT/SIGTERM set `stop_requested` (a second one
raises KeyboardInterrupt) for a process that owns the recorder and polls it between
steps, as `mdss run` does; finish() restores the previous handlers. A ROS node handles
its own signals and calls finish() when it shuts down.
"""
import atexit
import os
import queue
import signal
import sys
import threading
import time
from pathlib import Path

import yaml

from ..errors import MdssError
from ..ros.convert import TYPESTORE

ROS_DISTRO = "jazzy"


class RecordingError(MdssError):
    """A recording cannot be started (path, permissions, disk) or a type is unknown."""


# --------------------------------------------------------------------- schemas
def _full_name(type_name):
    """'pkg/msg/Type' of 'pkg/msg/Type' or 'pkg/Type'."""
    parts = type_name.split("/")
    if len(parts) == 2:
        parts.insert(1, "msg")
    if len(parts) != 3 or not all(parts):
        raise RecordingError(f"type name {type_name!r} is not pkg/msg/Type")
    return "/".join(parts)


def _known(type_name):
    full = _full_name(type_name)
    if full not in TYPESTORE.types:
        raise RecordingError(f"{full} is not a type of rosbags' ROS 2 Jazzy typestore")
    return full


def message_definition(type_name):
    """The ros2msg schema text of a type (rosbags' generate_msgdef; see module doc)."""
    return TYPESTORE.generate_msgdef(_known(type_name), ros_version=2)[0]


def type_hash(type_name):
    """RIHS01 hash of a type (rosbags' hash_rihs01, rosidl's type description hash)."""
    return TYPESTORE.hash_rihs01(_known(type_name))


def type_name_of(msg):
    """'pkg/msg/Type' of a typestore message object."""
    name = getattr(msg, "__msgtype__", None)
    if name is None:
        raise RecordingError(f"cannot tell the ROS type of a {type(msg).__name__} (messages are rosbags "
                             f"typestore objects, mdss_ros.ros.convert); pass CDR bytes and type_name=")
    return name


def qos_yaml(profiles):
    """offered_qos_profiles text of a list of QoS dicts (ros_messages.qos_profile)."""
    return yaml.safe_dump(list(profiles), default_flow_style=False, sort_keys=False)


def _default_qos():
    from .ros_messages import qos_profile
    return qos_profile(10)


# --------------------------------------------------------------------- recorder
def _checked_time(t, what, name, low=0):
    """int(t) for an MCAP record's time (ns), or RecordingError outside [low, 2^64)."""
    t = int(t)
    if not low <= t < _TIME_MAX:
        raise RecordingError(f"{what}: {name} must be below 2^64 ns and not negative, got {t}")
    return t


def _default_on_error(text):
    print(f"mdss: WARNING: {text}", file=sys.stderr, flush=True)


#: What may wait for the writer thread (write() waits beyond either): messages, about 9 s
#: of the node's outputs at 90 Hz, and bytes, about 27 s of armadillo_class's.
QUEUE_LIMIT = 10_000
QUEUE_BYTES = 256 * 1024 * 1024
#: Times an MCAP record can hold (unsigned 64-bit nanoseconds).
_TIME_MAX = 2 ** 64
#: The writer thread's period (s): what it writes each time is what was queued meanwhile.
BATCH_S = 0.02


class McapRecorder:
    """Writes one MCAP file; see the module docstring for the API and guarantees.

    path: the .mcap file (its folder must exist). flush_interval_s: wall seconds between
    forced chunk flushes (bounds what SIGKILL loses; 0 or None: only by size).
    chunk_size: uncompressed bytes per chunk. compression: "zstd", "lz4" or "none".
    bag_metadata: also write metadata.yaml beside the file at finish.
    on_error(text): hears a write error once (default: stderr).
    """

    def __init__(self, path, flush_interval_s=0.5, chunk_size=4 * 1024 * 1024, compression="zstd",
                 bag_metadata=False, on_error=None, library=None):
        from mcap.writer import CompressionType, Writer
        self.path = Path(path)
        self.flush_interval_s = float(flush_interval_s or 0.0)
        self.bag_metadata = bag_metadata
        self.on_error = on_error or _default_on_error
        self.error = None
        self.finished = False
        self.stop_requested = False
        self.stop_signal = None
        self.counts = {}          # topic -> messages in the file (the writer thread counts)
        self.clamped = 0          # log times raised to keep them non-decreasing
        # The caller's side (write(), under _lock): each topic's type and channel metadata,
        # sequence numbers, log times. The writer thread's (under _wlock): the channel and
        # schema ids the file has, whether the open chunk holds anything, the last flush.
        self._topics = {}         # topic -> (type name, channel metadata)
        self._channels = {}       # topic -> (channel id, type name, channel metadata)
        self._schemas = {}        # type name -> schema id
        self._sequence = {}
        self._last_log = 0
        self._first_log = None
        self._dirty = False
        self._last_flush = time.monotonic()
        self._lock = threading.RLock()
        self._wlock = threading.RLock()
        self._old_handlers = {}
        if self.path.is_dir():
            raise RecordingError(f"cannot record to {self.path}: it is a directory (give a .mcap file path)")
        try:
            self._file = open(self.path, "wb")
        except OSError as err:
            raise RecordingError(f"cannot record to {self.path}: {err.strerror or err}") from err
        comp = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}[compression]
        from ..version import __version__
        import mcap
        lib = library or f"mdss_ros {__version__} (mcap-python {getattr(mcap, '__version__', '?')})"
        try:
            self._writer = Writer(self._file, chunk_size=chunk_size, compression=comp, enable_data_crcs=True)
            self._writer.start(profile="ros2", library=lib)
            self._file.flush()
        except OSError as err:
            self._close_file()
            raise RecordingError(f"cannot record to {self.path}: {err.strerror or err}") from err
        atexit.register(self.finish)
        self._queue = queue.Queue(maxsize=QUEUE_LIMIT)
        self._queued_bytes = 0
        self._room = threading.Condition()     # the writer thread made room (QUEUE_BYTES)
        self._closing = False                  # finish() has begun: nothing more is taken
        self._unreported = False               # an error on_error has not heard yet
        self._worker = threading.Thread(target=self._work, name="mcap-writer", daemon=True)
        self._worker.start()

    # ----------------------------------------------------------------- context
    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.finish()
        return False

    @property
    def ok(self):
        return self.error is None and not self.finished and not self._closing

    def _report(self):
        """on_error(error) once, on the caller's thread (the writer thread only records the
        error: a callback run there could wait on a lock its caller holds)."""
        if self._unreported:
            self._unreported = False
            try:
                self.on_error(self.error)
            except Exception:  # noqa: BLE001 - a reporting failure must not stop the caller
                pass

    def _put(self, item, size=0):
        """Queue a record for the writer thread (under _lock); False, with the error
        recorded, when the thread is gone."""
        if not self._worker.is_alive():
            self._fail(RuntimeError("the writer thread stopped"))
            self._report()
            return False
        if size:
            with self._room:
                while self._queued_bytes > QUEUE_BYTES and self._worker.is_alive():
                    self._room.wait(0.1)
                self._queued_bytes += size
        self._queue.put(item)
        return True

    # ----------------------------------------------------------------- writing
    def _topic(self, topic, type_name, qos):
        """Check a topic's type (the caller's side): its first message fixes it, and an
        unknown type is refused there and then, before anything is queued."""
        known = self._topics.get(topic)
        if known is not None:
            if known[0] != type_name:
                raise RecordingError(f"topic {topic} was recorded as {known[0]}, not {type_name}")
            return
        meta = {"offered_qos_profiles": qos_yaml([qos or _default_qos()]),
                "topic_type_hash": type_hash(type_name)}
        self._topics[topic] = (type_name, meta)

    def _channel(self, topic):
        """The channel id of a topic in the file, registered with its schema on first use
        (the writer thread's side)."""
        ch = self._channels.get(topic)
        if ch is not None:
            return ch[0]
        type_name, meta = self._topics[topic]
        sid = self._schemas.get(type_name)
        if sid is None:
            text = message_definition(type_name)
            sid = self._writer.register_schema(name=type_name, encoding="ros2msg", data=text.encode())
            self._schemas[type_name] = sid
        cid = self._writer.register_channel(topic=topic, message_encoding="cdr", schema_id=sid, metadata=meta)
        self._channels[topic] = (cid, type_name, meta)
        return cid

    def write(self, topic, msg, log_time_ns, type_name=None, qos=None, publish_time_ns=None):
        """Record one message (a typestore object or CDR bytes); True if taken (the writer
        thread writes it, in order), False if recording stopped. CDR bytes need type_name;
        an object has its own type. Times are ns below 2^64; publish_time_ns is not
        negative, and a log time below the last one (0 at first) is raised to it (clamped).

        qos: offered QoS dict (ros_messages.qos_profile) used when the topic is first seen.
        """
        if isinstance(msg, (bytes, bytearray, memoryview)):
            if type_name is None:
                raise RecordingError(f"{topic}: CDR bytes need type_name=")
            data = bytes(msg)
        else:
            from .ros_messages import cdr_bytes
            own = type_name_of(msg)
            if type_name is not None and _full_name(type_name) != own:
                raise RecordingError(f"{topic}: a {own} message given as {type_name}")
            type_name = own
            data = cdr_bytes(msg)
        # A log time below the last one written (0 at first) is raised to it, as before.
        log_time = _checked_time(log_time_ns, topic, "log_time_ns", low=-_TIME_MAX)
        publish_time = None if publish_time_ns is None else _checked_time(publish_time_ns, topic, "publish_time_ns")
        with self._lock:
            self._report()
            if not self.ok:
                return False
            if log_time < self._last_log:
                log_time = self._last_log
                self.clamped += 1
            self._topic(topic, type_name, qos)
            seq = self._sequence.get(topic, 0) + 1
            self._sequence[topic] = seq
            self._last_log = log_time
            if self._first_log is None:
                self._first_log = log_time
            # Queued under the lock: the thread gets messages in the order of their log times.
            return self._put(("message", topic, log_time, data, log_time if publish_time is None else publish_time,
                              seq), len(data))

    def write_tf(self, transforms, log_time_ns, topic="/tf"):
        """Record geometry_msgs/TransformStamped objects as one tf2_msgs/msg/TFMessage."""
        from ..ros.convert import tf_message
        from .ros_messages import qos_profile
        return self.write(topic, tf_message(transforms), log_time_ns, qos=qos_profile(100))

    def add_metadata(self, name, data):
        """An MCAP metadata record: name and a {str: str} map (written in turn with the
        messages queued before it)."""
        with self._lock:
            self._report()
            if not self.ok:
                return False
            return self._put(("metadata", name, {str(k): str(v) for k, v in data.items()}))

    def add_attachment(self, name, data, media_type="application/octet-stream", log_time_ns=0):
        log_time = _checked_time(log_time_ns, name, "log_time_ns")
        data = bytes(data)
        with self._lock:
            self._report()
            if not self.ok:
                return False
            return self._put(("attachment", name, data, media_type, log_time, time.time_ns()), len(data))

    def flush(self):
        """Write what is queued, close the open chunk and hand everything to the OS now;
        False if the recording has stopped (error says why) or the thread did not answer
        within 60 s."""
        done = threading.Event()
        with self._lock:
            self._report()
            if not self.ok or not self._put(("flush", done)):
                return False
        answered = done.wait(timeout=60.0)
        with self._lock:
            self._report()
        return answered and self.error is None

    def _flush_locked(self):
        self._writer.flush()
        self._last_flush = time.monotonic()
        self._dirty = False

    def _work(self):
        """The writer thread: every BATCH_S it takes all that is queued into the file, in
        order, and flushes whenever flush_interval_s passed since the last flush. None in
        the queue ends it (finish). It wakes on its own clock rather than on every
        message: woken for each of a step's dozen messages, it took the GIL from the
        simulation a dozen times a step, and the node's median cycle on armadillo_class
        grew by 1.2-1.8 ms (session 26). Any error stops the recording (_fail), never the
        thread: a thread gone silently would leave write() queueing into nothing."""
        while True:
            time.sleep(BATCH_S)
            items = []
            while True:
                try:
                    items.append(self._queue.get_nowait())
                except queue.Empty:
                    break
            last = bool(items) and items[-1] is None
            freed = 0
            with self._wlock:
                for item in items:
                    if item is None:
                        break
                    if item[0] in ("message", "attachment"):
                        freed += len(item[3] if item[0] == "message" else item[2])
                    if self.error is None:
                        try:
                            self._apply(item)
                        except Exception as err:  # noqa: BLE001 - stop the recording, not the thread
                            self._fail(err)
                    if item[0] == "flush":
                        item[1].set()
                if self.error is None and self.flush_interval_s and self._dirty and \
                        time.monotonic() - self._last_flush >= self.flush_interval_s:
                    try:
                        self._flush_locked()
                    except Exception as err:  # noqa: BLE001
                        self._fail(err)
            if freed:
                with self._room:
                    self._queued_bytes -= freed
                    self._room.notify_all()
            if last:
                return

    def _apply(self, item):
        """One queued record into the writer (the writer thread, under _wlock)."""
        kind = item[0]
        if kind == "message":
            _, topic, log_time, data, publish_time, seq = item
            self._writer.add_message(channel_id=self._channel(topic), log_time=log_time, data=data,
                                     publish_time=publish_time, sequence=seq)
            self.counts[topic] = self.counts.get(topic, 0) + 1        # what the file holds
        elif kind == "metadata":
            self._writer.add_metadata(item[1], item[2])
        elif kind == "attachment":
            _, name, data, media_type, log_time, create_time = item
            self._writer.add_attachment(create_time=create_time, log_time=log_time, name=name,
                                        media_type=media_type, data=data)
        elif kind == "flush":
            self._flush_locked()
            return
        self._dirty = True

    def _fail(self, err):
        """Stop the recording for err (on either thread); on_error hears it from _report."""
        if self.error is not None:
            return
        what = err.strerror if isinstance(err, OSError) and err.strerror else (str(err) or type(err).__name__)
        self.error = f"recording to {self.path} stopped: {what}; the simulation goes on"
        self._unreported = True
        self._close_file()

    def _close_file(self):
        try:
            self._file.close()
        except OSError:
            pass

    # ----------------------------------------------------------------- signals
    def stop_on_signals(self, signals=(signal.SIGINT, signal.SIGTERM)):
        """SIGINT/SIGTERM set stop_requested (a second signal raises KeyboardInterrupt).
        Main thread only; finish() restores the previous handlers."""

        def handler(signum, frame):
            if self.stop_requested:
                raise KeyboardInterrupt
            self.stop_requested = True
            self.stop_signal = signum

        for s in signals:
            self._old_handlers[s] = signal.signal(s, handler)
        return self

    def _restore_signals(self):
        for s, h in self._old_handlers.items():
            try:
                signal.signal(s, h)
            except (ValueError, TypeError):  # not the main thread, or a non-Python handler
                pass
        self._old_handlers = {}

    # ----------------------------------------------------------------- finish
    def summary(self):
        return {"path": str(self.path), "messages": sum(self.counts.values()), "topics": dict(self.counts),
                "clamped_log_times": self.clamped, "error": self.error, "finished": self.finished,
                "bytes": self.path.stat().st_size if self.path.exists() else 0}

    def finish(self):
        """Write what is queued, then the summary and footer, and close the file. Safe to
        call more than once."""
        with self._lock:
            if self.finished:
                return self.summary()
            # Nothing is taken from here on (ok is False); the thread writes what was queued.
            self._closing = True
            if self._worker.is_alive() and self._worker is not threading.current_thread():
                self._queue.put(None)
                self._worker.join()
        with self._wlock, self._lock:
            if self.finished:
                return self.summary()
            self._restore_signals()
            try:
                atexit.unregister(self.finish)
            except Exception:  # noqa: BLE001
                pass
            if self.error is None:
                try:
                    info = self._bag_info()
                    self._writer.add_metadata("rosbag2", {"serialized_metadata": yaml.safe_dump(
                        info, default_flow_style=False, sort_keys=False).strip(), "ros_distro": ROS_DISTRO})
                    self._writer.finish()
                    self._file.flush()
                    self._close_file()
                    if self.bag_metadata:
                        self._write_bag_metadata(info)
                except OSError as err:
                    self._fail(err)
            self.finished = True
            self._report()
            return self.summary()

    def _bag_info(self):
        start = self._first_log or 0
        duration = max(0, self._last_log - start) if self._first_log is not None else 0
        count = sum(self.counts.values())
        topics = []
        for topic, (cid, tname, meta) in self._channels.items():
            topics.append({"topic_metadata": {"name": topic, "type": tname, "serialization_format": "cdr",
                                              "offered_qos_profiles": yaml.safe_load(meta["offered_qos_profiles"]),
                                              "type_description_hash": meta["topic_type_hash"]},
                           "message_count": self.counts.get(topic, 0)})
        return {"version": 9, "storage_identifier": "mcap", "duration": {"nanoseconds": duration},
                "starting_time": {"nanoseconds_since_epoch": start}, "message_count": count,
                "topics_with_message_count": topics, "compression_format": "", "compression_mode": "",
                "relative_file_paths": [self.path.name],
                "files": [{"path": self.path.name, "starting_time": {"nanoseconds_since_epoch": start},
                           "duration": {"nanoseconds": duration}, "message_count": count}],
                "custom_data": None, "ros_distro": ROS_DISTRO}

    def _write_bag_metadata(self, info):
        meta = self.path.parent / "metadata.yaml"
        tmp = meta.with_suffix(".yaml.tmp")
        tmp.write_text(yaml.safe_dump({"rosbag2_bagfile_information": info}, default_flow_style=False,
                                      sort_keys=False))
        os.replace(tmp, meta)


def bag_paths(path):
    """(mcap file, is a bag folder) for a recording target: a `.mcap` path or an existing
    file is a file; any other path is a rosbag2 folder (created; must be new or empty)
    holding `<name>_0.mcap` and, at finish, metadata.yaml, as `ros2 bag record -s mcap -o DIR`
    lays it out."""
    p = Path(path)
    if p.suffix == ".mcap" or (p.exists() and not p.is_dir()):
        return p, False
    if p.is_dir() and any(p.iterdir()):
        raise RecordingError(f"cannot record to {p}: a bag folder must be new or empty "
                             f"(give a .mcap file path to record a single file)")
    try:
        p.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise RecordingError(f"cannot create bag folder {p}: {err.strerror or err}") from err
    return p / f"{p.name}_0.mcap", True


def mcap_of(path):
    """The .mcap file of a recording: the path itself, or the file a bag folder lists."""
    p = Path(path)
    if not p.is_dir():
        return p
    meta = p / "metadata.yaml"
    if meta.is_file():
        try:
            info = yaml.safe_load(meta.read_text())["rosbag2_bagfile_information"]
            files = info.get("relative_file_paths") or []
            if files:
                return p / files[0]
        except (yaml.YAMLError, KeyError, TypeError):
            pass
    found = sorted(p.glob("*.mcap"))
    if len(found) == 1:
        return found[0]
    raise RecordingError(f"{p}: a folder with {len(found)} .mcap files (give one of them)")


# --------------------------------------------------------------------- reading back
def recover(path, validate_crcs=True):
    """Read an MCAP that may lack its summary (a killed recorder): every message of every
    complete chunk, in file order, with mcap's StreamReader.

    Returns (messages, info): messages [(topic, schema_name, log_time, publish_time, data)],
    info {"complete": footer seen, "error": why reading stopped or None, "metadata": {name: map},
    "schemas": {name: text}}.
    """
    from mcap.records import Channel, Footer, Message, Metadata, Schema
    from mcap.stream_reader import StreamReader
    schemas, channels, messages, metadata = {}, {}, [], {}
    info = {"complete": False, "error": None}
    with open(path, "rb") as f:
        reader = StreamReader(f, validate_crcs=validate_crcs, record_size_limit=1 << 31)
        try:
            for rec in reader.records:
                if isinstance(rec, Schema):
                    schemas[rec.id] = rec
                elif isinstance(rec, Channel):
                    channels[rec.id] = rec
                elif isinstance(rec, Message):
                    ch = channels[rec.channel_id]
                    sch = schemas.get(ch.schema_id)
                    messages.append((ch.topic, sch.name if sch else "", rec.log_time, rec.publish_time, rec.data))
                elif isinstance(rec, Metadata):
                    metadata[rec.name] = dict(rec.metadata)
                elif isinstance(rec, Footer):
                    info["complete"] = True
        except Exception as err:  # noqa: BLE001 - truncated or corrupt tail: keep what was read
            info["error"] = f"{type(err).__name__}: {err}"
    info["metadata"] = metadata
    info["schemas"] = {s.name: s.data.decode(errors="replace") for s in schemas.values()}
    return messages, info
