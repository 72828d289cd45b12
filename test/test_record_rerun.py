"""rerun logging: `mdss run --rrd` read back with rerun's own reader (rerun.chunk.RrdReader);
the web-viewer screenshot (slow, needs Debian chromium)."""
import shutil
import subprocess
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np
import pytest

from mdss_ros.cli import main as mdss
from mdss_ros.record.rerun_logger import RerunLogError, RerunLogger

ROOT = Path(__file__).resolve().parent.parent
STEPS = 45
SETS = ["body.mesh.cell=0.05", "model.domains.count=2", "model.modes=6", "model.cubature={samples: 0}",
        "colliders={ball: {shape: sphere, radius: 0.05, position: [0.5, 0.0, 0.6]}, "
        "rod: {shape: capsule, radius: 0.02, half_height: 0.1, position: [0.2, 0.0, 0.6]}}",
        "timeline=[{t: 0.0, topic: wrench, frame_id: tip, force: [0, 0, -8.0]},"
        " {t: 0.2, topic: collider_pose, name: ball, position: [0.5, 0.0, 0.5]},"
        " {t: 0.3, topic: collider_pose, name: ball, position: [0.5, 0.0, 0.45]}]"]


def _small_sim():
    from mdss_ros.scene import read_yaml
    from mdss_ros.simulator import Simulator
    return Simulator("cantilever", overrides={k: read_yaml(v) for k, v in (s.split("=", 1) for s in SETS)})


@pytest.fixture(scope="module")
def rrd(tmp_path_factory):
    path = tmp_path_factory.mktemp("rrd") / "run.rrd"
    args = ["run", "cantilever", "--steps", str(STEPS), "--rrd", str(path)]
    for s in SETS:
        args += ["--set", s]
    assert mdss(args) == 0
    return path


def _chunks(path):
    from rerun.chunk import RrdReader
    reader = RrdReader(path)
    assert len(reader.recordings()) == 1 and len(reader.blueprints()) == 1     # the default blueprint
    return list(reader.store().stream())


def test_rrd_holds_the_expected_entities_and_frame_counts(rrd):
    static, temporal, timelines = defaultdict(set), defaultdict(int), defaultdict(set)
    steps = defaultdict(list)
    for c in _chunks(rrd):
        if c.entity_path.startswith("/__"):
            continue
        rb = c.to_record_batch()
        cols = {n.split(":")[-1] for n in rb.schema.names if ":" in n and not n.startswith("rerun.")}
        if c.is_static:
            static[c.entity_path] |= cols
        else:
            temporal[c.entity_path] += c.num_rows
            timelines[c.entity_path] |= set(c.timeline_names)
            steps[c.entity_path] += rb.column("step").to_pylist()
    frames = STEPS + 1                                     # t = 0 and every step
    assert static["/world/body/surface"] == {"triangle_indices", "vertex_colors"}
    for entity in ("/world/body/surface", "/world/domains",
                   "/plots/energy/total", "/plots/energy/kinetic", "/plots/energy/elastic",
                   "/plots/contact_force"):
        assert temporal[entity] == frames, entity
        assert {"step", "sim_time"} <= timelines[entity]
        assert sorted(steps[entity]) == list(range(frames))
    assert temporal["/plots/step_ms"] == STEPS                # no step time at t = 0
    assert {"colors", "labels", "show_labels"} <= static["/world/domains"]
    # The ball never reaches the beam: its empty contacts are logged once
    # (test_rrd_contacts_are_logged_when_they_change has contacts).
    for entity in ("/world/contacts", "/world/contacts/forces"):
        assert steps[entity] == [0], entity
    assert "half_sizes" in static["/world/colliders/ball"] and "lengths" in static["/world/colliders/rod"]
    assert temporal["/world/colliders/ball"] == 3             # initial pose and two changes
    assert temporal["/world/colliders/rod"] == 1


def test_rrd_vertex_positions_are_the_simulators(rrd):
    sim = _small_sim()
    sim.set_wrench("tip", force=(0, 0, -8.0))
    sim.step(STEPS)
    want = np.asarray(sim.surface_positions(), dtype=np.float32)
    last = None
    for c in _chunks(rrd):
        if c.entity_path == "/world/body/surface" and not c.is_static:
            rb = c.to_record_batch()
            k = rb.column("step").to_pylist()
            col = rb.column("Mesh3D:vertex_positions")
            for i in range(len(k)):
                if k[i] == STEPS:
                    last = np.asarray(col[i].values.flatten(), dtype=np.float32).reshape(-1, 3)
    assert last is not None
    np.testing.assert_array_equal(last, want)


def test_rrd_domain_axes_are_the_simulators_frames(rrd):
    """The last frame's axis arrows: each domain's origin, and its rotation's columns."""
    from scipy.spatial.transform import Rotation
    sim = _small_sim()
    sim.set_wrench("tip", force=(0, 0, -8.0))
    sim.step(STEPS)
    poses = np.asarray(sim.domain_poses())
    found = None
    for c in _chunks(rrd):
        if c.entity_path == "/world/domains" and not c.is_static:
            rb = c.to_record_batch()
            k = rb.column("step").to_pylist()
            for i in range(len(k)):
                if k[i] == STEPS:
                    found = [np.asarray(rb.column(f"Arrows3D:{n}")[i].values.flatten(), dtype=np.float64).reshape(-1, 3)
                             for n in ("origins", "vectors")]
    assert found is not None
    origins, vectors = found
    assert len(origins) == 3 * len(poses) and abs(poses[:, 3:]).max() > 0 and np.any(poses[:, 3:6] != 0)
    np.testing.assert_allclose(origins, np.repeat(poses[:, :3], 3, axis=0), atol=1e-6)
    R = Rotation.from_quat(poses[:, 3:7]).as_matrix()            # scipy: (x, y, z, w), as the poses
    length = np.linalg.norm(vectors, axis=1)
    np.testing.assert_allclose(length, length[0], rtol=1e-5)
    np.testing.assert_allclose(vectors.reshape(-1, 3, 3) / length[0], np.swapaxes(R, 1, 2), atol=1e-5)


def test_rrd_contacts_are_logged_when_they_change(tmp_path):
    """Contacts are logged at the first frame, at every frame with contacts and at the first
    one without after them: the viewer shows the latest value, so an empty frame after an
    empty one would change nothing. The ball is put into the beam, which sags under
    gravity, then lifted off."""
    sim = _small_sim()
    path = tmp_path / "contacts.rrd"
    counts = []
    with RerunLogger(sim, mode="file", path=path) as log:
        for k in range(12):
            if k == 3:
                sim.set_collider_pose("ball", (0.5, 0.05, 0.125))       # into the sagging beam (top at z = 0.1)
            if k == 7:
                sim.set_collider_pose("ball", (0.5, 0.05, 0.6))
            if k:
                sim.step()
            counts.append(len(sim.contacts()))
            assert log.log_step()
    assert counts[0] == 0 and any(counts[3:7]) and counts[-1] == 0
    points, arrows, static = {}, {}, defaultdict(set)
    for c in _chunks(path):
        rb = c.to_record_batch()
        if c.is_static:
            static[c.entity_path] |= set(rb.schema.names)
        elif c.entity_path == "/world/contacts":
            for k, row in zip(rb.column("step").to_pylist(), rb.column("Points3D:positions").to_pylist()):
                points[k] = None if row is None else len(row)   # an empty batch clears the view; None would not
        elif c.entity_path == "/world/contacts/forces":
            for k, row in zip(rb.column("step").to_pylist(), rb.column("Arrows3D:vectors").to_pylist()):
                arrows[k] = None if row is None else len(row)
    want = [0] + [k for k in range(1, len(counts)) if counts[k] or counts[k - 1]]
    assert sorted(points) == want
    assert [points[k] for k in want] == [counts[k] for k in want]
    assert sorted(arrows) == want and [arrows[k] for k in want] == [counts[k] for k in want]
    assert {"Points3D:radii", "Points3D:colors"} <= static["/world/contacts"]
    assert "Arrows3D:colors" in static["/world/contacts/forces"]


def test_rrd_contacts_after_a_reset_are_the_new_runs(tmp_path):
    """A reset rewinds the step timeline, and the viewer shows at a step the latest row at or
    before it: up to the highest step logged before the reset, every frame after it logs its
    contacts (none here) and collider poses, so no row of the run before shows through."""
    sim = _small_sim()
    path = tmp_path / "reset.rrd"
    with RerunLogger(sim, mode="file", path=path) as log:
        sim.set_collider_pose("ball", (0.5, 0.05, 0.125))
        before = []
        for k in range(6):
            sim.step()
            log.log_step()
            before.append(len(sim.contacts()))
        assert any(before)
        sim.set_collider_pose("ball", (0.5, 0.05, 0.6))
        log.log_step()                                     # the pose the run after the reset keeps
        sim.reset()
        sim.set_collider_pose("ball", (0.5, 0.05, 0.6))
        for k in range(9):
            log.log_step()
            sim.step()

    def rows_of(entity, column):                           # [(step, value)] in log order
        rows = []
        for c in _chunks(path):
            if c.entity_path == entity and not c.is_static:
                rb = c.to_record_batch()
                rows += list(zip(rb.column("rerun.controls.RowId").to_pylist(), rb.column("step").to_pylist(),
                                 rb.column(column).to_pylist()))
        return [(k, v) for _, k, v in sorted(rows, key=lambda r: r[0])]

    def shown(rows, step):                                 # the viewer's latest-at: highest step, then last logged
        best = max((k, i) for i, (k, _) in enumerate(rows) if k <= step)
        return rows[best[1]][1]

    contacts = rows_of("/world/contacts", "Points3D:positions")
    ball = rows_of("/world/colliders/ball", "Transform3D:translation")
    reset_at = next(i for i in range(1, len(contacts)) if contacts[i][0] < contacts[i - 1][0])
    after = contacts[reset_at:]
    assert [k for k, _ in after] == list(range(7)) and not any(len(v) for _, v in after)
    for step in range(9):                                  # the new run has no contacts, the ball up
        assert len(shown(contacts, step)) == 0, step
        np.testing.assert_allclose(np.ravel(shown(ball, step)), [0.5, 0.05, 0.6])


def test_logger_modes_and_errors(tmp_path):
    sim = _small_sim()
    off = RerunLogger(sim, mode="off")
    assert off.log_step() is False
    off.close()
    with pytest.raises(RerunLogError, match="must be one of"):
        RerunLogger(sim, mode="video")
    with pytest.raises(RerunLogError, match="needs a path"):
        RerunLogger(sim, mode="file")
    (tmp_path / "f").write_text("")
    with pytest.raises(RerunLogError, match="Not a directory"):
        RerunLogger(sim, mode="file", path=tmp_path / "f" / "x.rrd")
    # rate: at most 30 Hz of sim time at dt = 1/90 -> every third step
    path = tmp_path / "rate.rrd"
    with RerunLogger(sim, mode="file", path=path, rate=30.0) as log:
        logged = []
        for _ in range(10):
            logged.append(log.log_step())
            sim.step()
    assert logged == [True, False, False, True, False, False, True, False, False, True]
    assert log.frames == 4 and path.stat().st_size > 0


@pytest.mark.slow
@pytest.mark.skipif(shutil.which("chromium") is None, reason="needs Debian chromium (apt-get install chromium)")
def test_web_viewer_screenshot_shows_the_mesh(tmp_path):
    from PIL import Image
    out = tmp_path / "viewer.png"
    res = subprocess.run([sys.executable, str(ROOT / "launch_scripts" / "rerun_screenshot.py"), "--steps", "30",
                          "--out", str(out)] + [a for s in SETS[:4] for a in ("--set", s)],
                         capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert res.returncode == 0, res.stderr
    img = np.asarray(Image.open(out).convert("RGB")).astype(int)
    assert img.shape[0] >= 600 and img.shape[1] >= 1000
    # the surface is drawn in the domain colours (tab10 blue and orange), shaded: count pixels near them
    for rgb in ((31, 119, 180), (255, 127, 14)):
        near = (np.abs(img - np.array(rgb)).sum(axis=2) < 60).sum()
        assert near > 2000, (rgb, near)


def test_a_mesh_collider_is_drawn_with_its_own_triangles(tmp_path):
    """shape: mesh colliders are logged as their file's (scaled) triangles, static, in the
    collider's frame, which then moves with the pose like every other collider."""
    import trimesh
    from mdss_ros.scene import read_yaml
    from mdss_ros.simulator import Simulator
    ball = trimesh.creation.icosphere(subdivisions=1, radius=50.0)            # in millimetres
    ball.export(tmp_path / "ball.obj")
    over = {k: read_yaml(v) for k, v in (s.split("=", 1) for s in SETS[:4])}
    over["colliders"] = {"m": {"shape": "mesh", "file": str(tmp_path / "ball.obj"), "scale": 0.001,
                               "position": [0.5, 0.0, 0.6], "resolution": 0.01}}
    sim = Simulator("cantilever", overrides=over)
    log = RerunLogger(sim, mode="file", path=str(tmp_path / "m.rrd"))
    sim.step()
    log.log_step(1.0)
    log.close()
    static = {}
    for c in _chunks(tmp_path / "m.rrd"):
        if c.is_static and c.entity_path == "/world/colliders/m":
            rb = c.to_record_batch()
            static.update({n.split(":")[-1]: rb.column(n).to_pylist() for n in rb.schema.names if ":" in n})
    assert {"vertex_positions", "triangle_indices"} <= set(static)
    pts = np.array(static["vertex_positions"][0])
    assert len(pts) == len(ball.vertices) and np.abs(np.linalg.norm(pts, axis=1) - 0.05).max() < 1e-6
