"""Logging and replay: MCAP (rosbag2 conventions) and rerun.

Modules (import them directly; this package imports nothing heavy on its own):

- `mcap_recorder`: `McapRecorder(path, flush_interval_s=0.5, bag_metadata=False, on_error=None)`,
  a context manager; `write(topic, msg_or_cdr_bytes, log_time_ns, type_name=None, qos=None,
  publish_time_ns=None)`, `write_tf(transforms, log_time_ns)`, `add_metadata(name, map)`,
  `add_attachment(name, data, media_type)`, `flush()`, `finish()` (idempotent, also at exit),
  `stop_on_signals()` for a process that owns it; `RecordingError` for an unwritable path;
  a write error later sets `error`, calls `on_error` once and the caller goes on.
  `recover(path)` reads a file a killed process left behind; `bag_paths`/`mcap_of` handle
  rosbag2 folders (a folder with `<name>_0.mcap` and metadata.yaml).
- `ros_messages`: topic names/types/QoS of the node (`Topics("/mdss")`), the node's
  outputs of a Simulator as CDR bytes (`SimOutputs`), timeline events as input messages
  (`event_messages`) and their application with the node's checks (`InputApplier`),
  `tf_message_bytes` (tf2_msgs/msg/TFMessage) and `cdr_bytes` (deterministic CDR).
- `rerun_logger`: `RerunLogger(sim, mode="off"|"file"|"spawn"|"serve", path=None)`,
  `log_step(step_ms=None)`, `collider_pose(name, p, q)`, `close()`.
- `replay`: `RunRecording` (what `mdss run --mcap/--rrd` does), `replay(path, check=True)`
  (what `mdss replay` does), `read_recording(path)` (verified read of a recording).

For the node (mdss_ros.node), the intended use:

    from mdss_ros.record.mcap_recorder import McapRecorder, RecordingError
    from mdss_ros.record.ros_messages import Topics
    rec = McapRecorder(self._p("mcap_path"))          # at start; RecordingError -> log, no recording
    topics = Topics(self.get_namespace().rstrip("/") + "/" + self.get_name())
    # after publishing msg (object or CDR bytes) on topic, and for each input taken:
    rec.write(topic, msg, log_time_ns, type_name=..., qos=topics.qos_of(topic))
    rec.write_tf(convert.domain_transforms(t, frame, names, poses), log_time_ns)
    rec.finish()                                      # in close()

with log_time_ns the sim time in ns (what replay expects for unstamped inputs; the
recorder raises a log time that went back, e.g. after ~/reset_simulation, to the last
one). Replaying a node recording needs the `mdss_run` metadata (RunRecording._metadata
lists the keys: scene_json, scene_base_dir, namespace, world_frame, rates_json, ...).
"""
