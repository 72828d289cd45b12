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
- SIGKILL: the data section is written as complete chunks: a chunk is closed and flushed
  to the OS whenever `flush_interval_s` of wall time passed since the last flush (checked
  at every write and by a background thread, so an idle recorder flushes too) or it
  reaches chunk_size bytes. A killed process therefore loses at most about
  flush_interval_s * 1.25 of data; `recover()` (or mcap's StreamReader) reads a file
  that lacks its summary. The OS page cache survives a process kill; power loss is not
  covered (no fsync).
- Errors. An unwritable path raises RecordingError from the constructor (the header is
  written and flushed at once, so a full disk shows there too). A write error later (disk
  full) stops the recording: `error` says why, `on_error(text)` hears it once (default:
  a line on stderr), later writes return False, and the caller's simulation goes on.

Signals. `stop_on_signals()` makes SIGINT/SIGTERM set `stop_requested` (a second one
raises KeyboardInterrupt) for a process that owns the recorder and polls it between
steps, as `mdss run` does; finish() restores the previous handlers. A ROS node handles
its own signals and calls finish() when it shuts down.
"""
import atexit
import os
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
def _default_on_error(text):
    print(f"mdss: WARNING: {text}", file=sys.stderr, flush=True)


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
        self.counts = {}          # topic -> messages written
        self.clamped = 0          # log times raised to keep them non-decreasing
        self._channels = {}       # topic -> (channel id, type name)
        self._schemas = {}        # type name -> schema id
        self._sequence = {}
        self._last_log = 0
        self._first_log = None
        self._dirty = False
        self._last_flush = time.monotonic()
        self._lock = threading.RLock()
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
        self._stop = threading.Event()
        self._flusher = None
        if self.flush_interval_s > 0:
            self._flusher = threading.Thread(target=self._flush_loop, name="mcap-flush", daemon=True)
            self._flusher.start()

    # ----------------------------------------------------------------- context
    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.finish()
        return False

    @property
    def ok(self):
        return self.error is None and not self.finished

    # ----------------------------------------------------------------- writing
    def _channel(self, topic, type_name, qos):
        ch = self._channels.get(topic)
        if ch is not None:
            if ch[1] != type_name:
                raise RecordingError(f"topic {topic} was recorded as {ch[1]}, not {type_name}")
            return ch[0]
        sid = self._schemas.get(type_name)
        if sid is None:
            text = message_definition(type_name)
            sid = self._writer.register_schema(name=type_name, encoding="ros2msg", data=text.encode())
            self._schemas[type_name] = sid
        meta = {"offered_qos_profiles": qos_yaml([qos or _default_qos()]),
                "topic_type_hash": type_hash(type_name)}
        cid = self._writer.register_channel(topic=topic, message_encoding="cdr", schema_id=sid, metadata=meta)
        self._channels[topic] = (cid, type_name, meta)
        return cid

    def write(self, topic, msg, log_time_ns, type_name=None, qos=None, publish_time_ns=None):
        """Record one message (a typestore object or CDR bytes); True if written, False if
        recording stopped. CDR bytes need type_name; an object has its own type.

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
        with self._lock:
            if not self.ok:
                return False
            log_time = int(log_time_ns)
            if log_time < self._last_log:
                log_time = self._last_log
                self.clamped += 1
            try:
                cid = self._channel(topic, type_name, qos)
                seq = self._sequence.get(topic, 0) + 1
                self._sequence[topic] = seq
                self._writer.add_message(channel_id=cid, log_time=log_time, data=data,
                                         publish_time=log_time if publish_time_ns is None else int(publish_time_ns),
                                         sequence=seq)
                self._last_log = log_time
                if self._first_log is None:
                    self._first_log = log_time
                self.counts[topic] = self.counts.get(topic, 0) + 1
                self._dirty = True
                if self.flush_interval_s and time.monotonic() - self._last_flush >= self.flush_interval_s:
                    self._flush_locked()
            except OSError as err:
                self._fail(err)
                return False
            return True

    def write_tf(self, transforms, log_time_ns, topic="/tf"):
        """Record geometry_msgs/TransformStamped objects as one tf2_msgs/msg/TFMessage."""
        from ..ros.convert import tf_message
        from .ros_messages import qos_profile
        return self.write(topic, tf_message(transforms), log_time_ns, qos=qos_profile(100))

    def add_metadata(self, name, data):
        """An MCAP metadata record: name and a {str: str} map."""
        with self._lock:
            if not self.ok:
                return False
            try:
                self._writer.add_metadata(name, {str(k): str(v) for k, v in data.items()})
                self._dirty = True
            except OSError as err:
                self._fail(err)
                return False
            return True

    def add_attachment(self, name, data, media_type="application/octet-stream", log_time_ns=0):
        with self._lock:
            if not self.ok:
                return False
            try:
                t = int(log_time_ns)
                self._writer.add_attachment(create_time=time.time_ns(), log_time=t, name=name,
                                            media_type=media_type, data=bytes(data))
                self._dirty = True
            except OSError as err:
                self._fail(err)
                return False
            return True

    def flush(self):
        """Close the open chunk and hand everything to the OS now."""
        with self._lock:
            if self.ok:
                try:
                    self._flush_locked()
                except OSError as err:
                    self._fail(err)

    def _flush_locked(self):
        self._writer.flush()
        self._last_flush = time.monotonic()
        self._dirty = False

    def _flush_loop(self):
        period = max(0.02, self.flush_interval_s / 4.0)
        while not self._stop.wait(period):
            if self._dirty and time.monotonic() - self._last_flush >= self.flush_interval_s:
                self.flush()

    def _fail(self, err):
        what = err.strerror if isinstance(err, OSError) and err.strerror else str(err)
        self.error = f"recording to {self.path} stopped: {what}; the simulation goes on"
        self._close_file()
        try:
            self.on_error(self.error)
        except Exception:  # noqa: BLE001 - a reporting failure must not stop the caller
            pass

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
        """Write the summary and footer and close the file. Safe to call more than once."""
        if self._flusher is not None:
            self._stop.set()
            if self._flusher is not threading.current_thread():
                self._flusher.join(timeout=5.0)
            self._flusher = None
        with self._lock:
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
