"""MCAP recording of `mdss run --mcap` read back by independent readers, and `mdss replay`.

One small recorded run (module fixture) is read with rosbags and with mcap + the
mcap_ros2 decoder; its values are compared with a Simulator driven directly through the
library API (TimelinePlayer). Inputs use numbers exact in float32, so the point force the
recording applies from its float32 message is the library's float64 one.
"""
import hashlib
import json
import subprocess
import sys
from collections import Counter
from pathlib import Path

import numpy as np
import pytest

from mdss_ros.cli import main as mdss
from mdss_ros.record import mcap_recorder as mr
from mdss_ros.record import ros_messages as rm

TS = rm.convert.TYPESTORE

ROOT = Path(__file__).resolve().parent.parent
STEPS = 60
TIMELINE = ("[{t: 0.0, topic: wrench, frame_id: tip, force: [0, 0, -8.0]},"
            " {t: 0.1, topic: collider_pose, name: ball, position: [0.5, 0.0, 0.5], orientation: [0, 0, 0, 1]},"
            " {t: 0.2, topic: point_force, point: [1.0, 0.0625, 0.0625], force: [0, 0, -3.0], duration: 0.125},"
            " {t: 0.3, topic: clear_forces},"
            " {t: 0.36, topic: wrench, frame_id: tip, force: [0, 0.5, -4.0], torque: [0, 0, 0.25]},"
            " {t: 0.4, topic: wrench, frame_id: no_such_handle, force: [0, 0, -5.0]}]")
SETS = ["body.mesh.cell=0.05", "model.domains.count=2", "model.modes=6", "model.cubature={samples: 0}",
        "colliders={ball: {shape: sphere, radius: 0.05, position: [0.5, 0.0, 0.6]}}", f"timeline={TIMELINE}"]
SCENE_ARGS = ["cantilever"] + [a for s in SETS for a in ("--set", s)]
# The timeline's wrench on an unknown handle is rejected when it arrives, as the node does,
# so it is counted but not recorded: 2 of its 3 wrenches are.
INPUTS = {"/mdss/wrench": 2, "/mdss/colliders/ball/pose": 1, "/mdss/point_forces": 1, "/mdss/clear_forces/request": 1}


def _overrides():
    from mdss_ros.scene import read_yaml
    return {k: read_yaml(v) for k, v in (s.split("=", 1) for s in SETS)}


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    """(path of the MCAP, reference states per step from the library API)."""
    d = tmp_path_factory.mktemp("rec")
    path = d / "run.mcap"
    assert mdss(["run", *SCENE_ARGS, "--steps", str(STEPS), "--mcap", str(path)]) == 0
    # Reference: the same scene stepped through the plain API (the cache now holds its bases).
    from mdss_ros.simulator import Simulator
    from mdss_ros.timeline import apply_event
    sim = Simulator("cantilever", overrides=_overrides())
    events = sorted(sim.scene["timeline"], key=lambda e: e["t"])
    ref = []
    for k in range(STEPS + 1):
        if k:
            while events and events[0]["t"] <= sim.time + 0.5 * sim.dt:
                ev = events.pop(0)
                if ev.get("frame_id") != "no_such_handle":
                    apply_event(sim, ev)
            sim.step()
        ref.append({"t": sim.time, "x": np.asarray(sim.surface_positions(), np.float32).copy(),
                    "poses": np.asarray(sim.domain_poses()).copy()})
    dom = np.asarray(sim.model.vertex_domain)[sim.surface_vertex_ids()]
    return path, ref, dom


def _expected_counts():
    surface_every = 3            # points at 30 Hz of sim time with dt = 1/90
    n = STEPS + 1
    counts = {"/clock": n, "/mdss/domain_poses": n, "/tf": n, "/mdss/colliders/ball/wrench": n,
              "/mdss/colliders/ball/contacts": n,                 # the collider's touch, empty or not
              "/mdss/domain_transforms": 2 * n,                  # one per domain, as the node publishes
              "/mdss/surface/points": STEPS // surface_every + 1, "/mdss/surface/topology": 1,
              "/mdss/surface/marker": STEPS // 9 + 1, "/mdss/surface/mesh": 1, "/diagnostics": 1}
    counts.update(INPUTS)
    return counts


def test_rosbags_reads_every_topic_with_counts_and_values(recorded):
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore
    path, ref, dom = recorded
    by_time = {round(r["t"] * 1e9): r for r in ref}
    seen = Counter()
    with AnyReader([path], default_typestore=get_typestore(Stores.EMPTY)) as reader:
        assert {c.topic: c.msgcount for c in reader.connections} == _expected_counts()
        assert {c.topic: c.msgtype for c in reader.connections}["/tf"] == "tf2_msgs/msg/TFMessage"
        for conn, _, raw in reader.messages():
            msg = reader.deserialize(raw, conn.msgtype)
            seen[conn.topic] += 1
            if conn.topic == "/mdss/surface/points":
                stamp = msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec
                rec = np.frombuffer(msg.data.tobytes(), dtype=rm.convert.SURFACE_POINT_DTYPE)
                xyz = np.stack([rec["x"], rec["y"], rec["z"]], axis=1)
                np.testing.assert_array_equal(xyz, by_time[stamp]["x"])
                np.testing.assert_array_equal(rec["domain"], dom)
                assert [f.name for f in msg.fields] == ["x", "y", "z", "domain"] and msg.header.frame_id == "world"
            elif conn.topic == "/mdss/domain_poses":
                stamp = msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec
                got = [[p.position.x, p.position.y, p.position.z, p.orientation.x, p.orientation.y,
                        p.orientation.z, p.orientation.w] for p in msg.poses]
                np.testing.assert_array_equal(got, by_time[stamp]["poses"])
            elif conn.topic == "/tf":
                stamp = msg.transforms[0].header.stamp
                poses = by_time[stamp.sec * 10**9 + stamp.nanosec]["poses"]
                assert [t.child_frame_id for t in msg.transforms] == ["mdss/domain_0", "mdss/domain_1"]   # /tf: <node name>/<domain>
                assert {t.header.frame_id for t in msg.transforms} == {"world"}
                got = [[t.transform.translation.x, t.transform.translation.y, t.transform.translation.z,
                        t.transform.rotation.x, t.transform.rotation.y, t.transform.rotation.z,
                        t.transform.rotation.w] for t in msg.transforms]
                np.testing.assert_array_equal(got, poses)
            elif conn.topic == "/mdss/point_forces":
                rec = np.frombuffer(msg.data.tobytes(), dtype=rm.POINT_FORCE_DTYPE)
                assert rec.tolist() == [(1.0, 0.0625, 0.0625, 0.0, 0.0, -3.0, 0.125)]
            elif conn.topic == "/mdss/wrench" and seen[conn.topic] == 2:
                assert msg.header.frame_id == "tip" and (msg.header.stamp.sec, msg.header.stamp.nanosec) == (0, 360000000)
                assert (msg.wrench.force.y, msg.wrench.force.z, msg.wrench.torque.z) == (0.5, -4.0, 0.25)
            elif conn.topic == "/mdss/surface/topology":
                assert len(msg.vertices) == len(dom)
    assert dict(seen) == _expected_counts()


def test_mcap_ros2_decoder_reads_every_message(recorded):
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory
    path, ref, _ = recorded
    seen = Counter()
    last_log = -1
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for schema, channel, message, decoded in reader.iter_decoded_messages(log_time_order=False):
            seen[channel.topic] += 1
            assert message.log_time >= last_log            # never decreasing, in file order
            last_log = message.log_time
            if channel.topic == "/tf":
                assert [t.child_frame_id for t in decoded.transforms] == ["mdss/domain_0", "mdss/domain_1"]
                k = seen["/tf"] - 1
                tr = decoded.transforms[1].transform.translation
                assert [tr.x, tr.y, tr.z] == ref[k]["poses"][1, :3].tolist()
            if channel.topic == "/clock":
                assert decoded.clock.sec * 10**9 + decoded.clock.nanosec == message.log_time
    assert dict(seen) == _expected_counts()
    assert last_log == round(ref[-1]["t"] * 1e9)


def test_file_follows_the_rosbag2_conventions(recorded):
    from mcap.reader import make_reader
    path, _, _ = recorded
    with open(path, "rb") as f:
        reader = make_reader(f, validate_crcs=True)
        assert reader.get_header().profile == "ros2"
        summary = reader.get_summary()
        meta = {m.name: m.metadata for m in reader.iter_metadata()}
    assert summary.statistics.message_count == sum(_expected_counts().values())
    assert summary.chunk_indexes and {c.compression for c in summary.chunk_indexes} == {"zstd"}
    schemas = {s.id: s for s in summary.schemas.values()}
    for ch in summary.channels.values():
        s = schemas[ch.schema_id]
        assert ch.message_encoding == "cdr" and s.encoding == "ros2msg"
        # rosbags' ros2msg text of the type (its definition, then each dependency after 80 '='
        # and 'MSG: pkg/Type') and rosbags' RIHS01 hash, which is the one rosidl installs
        assert s.data.decode() == TS.generate_msgdef(s.name, ros_version=2)[0]
        assert ch.metadata["topic_type_hash"] == TS.hash_rihs01(s.name)
        installed = _installed_hash(s.name)
        assert installed in (None, ch.metadata["topic_type_hash"])
        qos = mr.yaml.safe_load(ch.metadata["offered_qos_profiles"])
        assert qos[0]["reliability"] == "reliable" and qos[0]["history"] == "keep_last"
    by_topic = {ch.topic: ch for ch in summary.channels.values()}
    assert by_topic["/tf"].metadata["topic_type_hash"] == \
        "RIHS01_e369d0f05a23ae52508854b66f6aa0437f3449d652e8cbf22d5abe85d020f087"     # Jazzy's tf2_msgs
    assert mr.yaml.safe_load(by_topic["/mdss/surface/topology"].metadata["offered_qos_profiles"])[0][
        "durability"] == "transient_local"
    assert "rosbag2" in meta and meta["rosbag2"]["ros_distro"] == "jazzy"
    run = meta["mdss_run"]
    assert json.loads(run["scene_json"])["model"]["modes"] == 6 and run["namespace"] == "/mdss"


@pytest.mark.claims
def test_replay_check_reproduces_every_output_bit_for_bit(recorded, capsys):
    path, _, _ = recorded
    assert mdss(["replay", str(path), "--check"]) == 0
    out = capsys.readouterr().out
    n_out = sum(v for k, v in _expected_counts().items() if k not in INPUTS)
    assert f"check passed: {n_out} recorded output messages reproduced bit for bit" in out
    assert "5 inputs, 60 steps" in out              # the rejected wrench is not recorded


def _rewrite(src, dst, change):
    """Copy an MCAP record by record with mcap's writer, passing messages through change()."""
    from mcap.reader import make_reader
    from mcap.writer import Writer
    with open(src, "rb") as f, open(dst, "wb") as g:
        reader = make_reader(f)
        summary = reader.get_summary()
        w = Writer(g)
        w.start(profile="ros2", library="test")
        sids = {s.id: w.register_schema(s.name, s.encoding, s.data) for s in summary.schemas.values()}
        cids = {c.id: w.register_channel(c.topic, c.message_encoding, sids[c.schema_id], c.metadata)
                for c in summary.channels.values()}
        for m in reader.iter_metadata():
            w.add_metadata(m.name, m.metadata)
        for schema, ch, msg in reader.iter_messages(log_time_order=False):
            w.add_message(cids[ch.id], msg.log_time, change(ch.topic, bytes(msg.data)), msg.publish_time)
        w.finish()


def test_a_changed_output_is_reported_as_the_first_mismatch(recorded, tmp_path, capsys):
    path, _, _ = recorded
    seen = Counter()

    def change(topic, data):
        seen[topic] += 1
        if topic == "/mdss/surface/points" and seen[topic] == 5:     # t = 12 dt: one coordinate
            b = bytearray(data)
            b[-16 * 7] ^= 0x01                                       # a low mantissa byte of an x
            return bytes(b)
        return data

    bad = tmp_path / "changed.mcap"
    _rewrite(path, bad, change)
    assert mdss(["replay", str(bad), "--check"]) == 1
    err = capsys.readouterr().err
    assert "check FAILED: 1 of" in err
    assert "first mismatch: /mdss/surface/points message 4 (t = 0.133333 s)" in err
    assert "largest position difference" in err


@pytest.mark.parametrize("damage", ["flip", "truncate", "garbage"])
def test_a_damaged_file_is_reported_not_crashed_on(recorded, tmp_path, damage):
    from mcap.reader import make_reader
    path, _, _ = recorded
    data = bytearray(path.read_bytes())
    with open(path, "rb") as f:
        chunk = make_reader(f).get_summary().chunk_indexes[0]
    if damage == "flip":                                   # bytes inside the first chunk's data
        mid = chunk.chunk_start_offset + chunk.chunk_length // 2
        for i in range(mid, mid + 4):
            data[i] ^= 0x5A
    elif damage == "truncate":
        data = data[:len(data) * 2 // 3]
    else:
        data = bytearray(b"not an mcap file at all" * 10)
    bad = tmp_path / f"{damage}.mcap"
    bad.write_bytes(bytes(data))
    res = subprocess.run([sys.executable, "-m", "mdss_ros.cli", "replay", str(bad), "--check"],
                         capture_output=True, text=True, cwd=ROOT, env=_env())
    assert res.returncode == 2, res.stderr
    assert "Traceback" not in res.stderr and res.stderr.startswith(f"mdss replay: {bad}: ")
    expected = {"flip": "damaged MCAP", "truncate": "truncated", "garbage": "not an MCAP file"}[damage]
    assert expected in res.stderr


def _env():
    import os
    env = dict(os.environ)
    env["PYTHONPATH"] = str(ROOT) + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    return env


def test_a_bag_folder_opens_as_a_bag_and_replays(tmp_path, capsys):
    from rosbags.rosbag2 import Reader
    bag = tmp_path / "bag"
    assert mdss(["run", *SCENE_ARGS, "--steps", "12", "--mcap", str(bag)]) == 0
    assert sorted(p.name for p in bag.iterdir()) == ["bag_0.mcap", "metadata.yaml"]
    with Reader(bag) as reader:                             # rosbags' reader of rosbag2 folders
        counts = {c.topic: c.msgcount for c in reader.connections}
        assert counts["/clock"] == 13 and counts["/tf"] == 13 and reader.message_count == sum(counts.values())
        tf = next(c for c in reader.connections if c.topic == "/tf")
        assert tf.digest == "RIHS01_e369d0f05a23ae52508854b66f6aa0437f3449d652e8cbf22d5abe85d020f087"
    assert mdss(["replay", str(bag), "--check"]) == 0
    assert "check passed" in capsys.readouterr().out


def test_unwritable_paths_are_reported_at_start(tmp_path):
    blocker = tmp_path / "a_file"
    blocker.write_text("x")
    for opt, name in (("--mcap", "x.mcap"), ("--rrd", "x.rrd")):
        with pytest.raises(SystemExit) as exc:
            mdss(["run", *SCENE_ARGS, "--steps", "2", opt, str(blocker / name)])
        assert str(exc.value).startswith("mdss run: cannot ") and "Not a directory" in str(exc.value)
    with pytest.raises(SystemExit) as exc:
        mdss(["run", *SCENE_ARGS, "--steps", "2", "--mcap", "/dev/full"])
    assert "No space left on device" in str(exc.value)


def test_a_disk_filling_up_mid_run_is_reported_and_the_run_goes_on(tmp_path):
    """RLIMIT_FSIZE makes writes past 60 kB fail with EFBIG, as a full disk fails with ENOSPC.
    Chunks are flushed every 0.05 s: with the default 0.5 s a fast machine wrote ~86 kB
    before the first flush (this run records ~170 kB/s), so no chunk fitted under the limit
    and nothing was readable."""
    import resource
    import signal

    def limit():
        resource.setrlimit(resource.RLIMIT_FSIZE, (60_000, 60_000))
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)

    out = tmp_path / "big.mcap"
    res = subprocess.run([sys.executable, "-m", "mdss_ros.cli", "run", *SCENE_ARGS, "--steps", "150",
                          "--mcap", str(out), "--mcap-flush", "0.05"], capture_output=True, text=True, cwd=ROOT,
                         env=_env(), preexec_fn=limit)
    assert res.returncode == 0, res.stderr
    assert "recording to" in res.stderr and "stopped: File too large; the simulation goes on" in res.stderr
    assert "done, 150 steps" in res.stdout
    messages, info = mr.recover(out)                         # what was flushed is readable
    assert messages and not info["complete"]


def test_sigterm_stops_the_run_and_finishes_the_file(tmp_path):
    import signal
    import time
    out = tmp_path / "term.mcap"
    proc = subprocess.Popen([sys.executable, "-m", "mdss_ros.cli", "run", *SCENE_ARGS, "--steps", "1000000",
                             "--mcap", str(out)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            cwd=ROOT, env=_env())
    t0 = time.monotonic()
    while time.monotonic() - t0 < 60 and (not out.exists() or out.stat().st_size < 20_000):
        time.sleep(0.1)
    proc.send_signal(signal.SIGTERM)
    stdout, stderr = proc.communicate(timeout=60)
    assert proc.returncode == 128 + signal.SIGTERM, stderr
    assert "SIGTERM at step" in stdout and "finishing the recording" in stdout
    from rosbags.rosbag2 import Reader
    with Reader(out) as reader:                              # needs the summary and footer
        counts = {c.topic: c.msgcount for c in reader.connections}
    assert counts["/clock"] > 10 and counts["/tf"] == counts["/clock"]


# --------------------------------------------------------------------- units
def _installed_hash(type_name):
    """The RIHS01 hash rosidl installed for a type (share/<pkg>/msg/<T>.json), or None."""
    import os
    pkg, _, name = type_name.split("/")
    prefixes = [Path(p) for p in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep) if p]
    prefixes += [Path(sys.prefix), Path(sys.prefix) / "tf2_msgs_ws" / "install" / "tf2_msgs"]
    for prefix in prefixes:
        p = prefix / "share" / pkg / "msg" / f"{name}.json"
        if p.is_file():
            return next(h["hash_string"] for h in json.loads(p.read_text())["type_hashes"] if h["type_name"] == type_name)
    return None


def test_recorder_api(tmp_path):
    path = tmp_path / "api.mcap"
    errors = []
    with mr.McapRecorder(path, flush_interval_s=0, on_error=errors.append) as rec:
        assert rec.write("/h", rm.convert.header(0.0, "a"), 5_000)
        assert rec.write("/h", rm.convert.header(0.0, "b"), 3_000)   # earlier: raised to 5000
        tr = rm.convert.domain_transforms(0.0, "world", ["c"], [[1.5, 0, 0, 0, 0, 0, 1]])[0]
        assert rec.write_tf([tr, tr], 6_000)
        with pytest.raises(mr.RecordingError):
            rec.write("/h", b"\x00\x01\x00\x00", 7_000, type_name="std_msgs/msg/String")   # type changed
        with pytest.raises(mr.RecordingError):
            rec.write("/c", rm.convert.clock(1.0), 7_000, type_name="std_msgs/msg/Header")   # not its type
        with pytest.raises(mr.RecordingError):
            rec.write("/x", b"\x00\x01\x00\x00", 7_000, type_name="no_pkg/msg/Nothing")   # unknown type
    assert rec.clamped == 1 and rec.finished and not errors
    assert rec.finish()["messages"] == 3                              # idempotent
    assert rec.write("/h", rm.convert.header(0.0, ""), 8_000) is False   # after finish
    messages, info = mr.recover(path)
    assert info["complete"] and [m[2] for m in messages] == [5_000, 5_000, 6_000]
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore
    with AnyReader([path], default_typestore=get_typestore(Stores.EMPTY)) as reader:
        msgs = [reader.deserialize(raw, c.msgtype) for c, _, raw in reader.messages()]
    assert [m.frame_id for m in msgs[:2]] == ["a", "b"]
    assert [t.transform.translation.x for t in msgs[2].transforms] == [1.5, 1.5]


@pytest.mark.parametrize("type_name", sorted(set(rm.Topics.TYPES.values())))
def test_schemas_are_complete_and_hashes_are_rosidls(type_name):
    """Each schema text alone rebuilds its type: parsed into an empty typestore it has the
    RIHS01 hash of the full type, which is rosidl's where installed (share/.../<T>.json)."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore
    text = mr.message_definition(type_name)
    alone = get_typestore(Stores.EMPTY)
    alone.register(get_types_from_msg(text, type_name))
    assert alone.hash_rihs01(type_name) == mr.type_hash(type_name) == TS.hash_rihs01(type_name)
    installed = _installed_hash(type_name)
    if installed is None:
        assert type_name == "tf2_msgs/msg/TFMessage"                  # only when tf2_msgs is not built here
    else:
        assert installed == mr.type_hash(type_name)
    heads = [line[len("MSG: "):] for line in text.splitlines() if line.startswith("MSG: ")]
    assert len(heads) == len(set(heads))                              # each dependency once
    assert mr.message_definition(type_name.replace("/msg/", "/")) == text   # pkg/Type names it too


def test_tf_hash_and_text_are_jazzys():
    assert mr.type_hash("tf2_msgs/msg/TFMessage") == \
        "RIHS01_e369d0f05a23ae52508854b66f6aa0437f3449d652e8cbf22d5abe85d020f087"
    assert mr.message_definition("tf2_msgs/msg/TFMessage").startswith("geometry_msgs/TransformStamped[] transforms\n")


def test_a_tf_message_decodes_in_mcap_ros2_with_its_schema():
    from mcap_ros2._dynamic import generate_dynamic
    transforms = rm.convert.domain_transforms(1.5, "world", ["a", "bb", "ccc"], np.arange(21.0).reshape(3, 7))
    data = rm.cdr_bytes(rm.convert.tf_message(transforms))
    decode = generate_dynamic("tf2_msgs/msg/TFMessage", mr.message_definition("tf2_msgs/msg/TFMessage"))
    msg = decode["tf2_msgs/msg/TFMessage"](data)
    assert [t.child_frame_id for t in msg.transforms] == ["a", "bb", "ccc"]
    assert [t.transform.rotation.w for t in msg.transforms] == [6.0, 13.0, 20.0]
    assert hashlib.sha256(data).digest() == hashlib.sha256(rm.cdr_bytes(rm.convert.tf_message(transforms))).digest()
