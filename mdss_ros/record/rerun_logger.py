"""rerun logging of a Simulator (rerun-sdk 0.41), for `mdss run --rrd` and the node.

    from mdss_ros.record.rerun_logger import RerunLogger
    log = RerunLogger(sim, mode="file", path="run.rrd")   # off | file | spawn | serve
    log.log_step()                       # the state now (call after reset and each step)
    log.collider_pose(name, position, orientation)   # when a collider pose is applied
    log.close()                          # flush and close; idempotent (also a context manager)

mode: "off" (every call is a no-op), "file" (write `path`; a bad path raises
RerunLogError at construction), "spawn" (start a native viewer and stream to it),
"serve" (an in-process gRPC server plus the web viewer; `url` is the viewer address).

Entities (all in world coordinates, the `world` frame of the ROS outputs):
  world/body/surface          Mesh3D: triangle indices and per-vertex domain colours
                              logged once as static, vertex positions every logged step
  world/domains               Arrows3D: every domain frame's axes (x red, y green, z blue,
                              labelled with the domain's name: static), logged in one call
  world/colliders/<name>      the scene's collider shapes (static, local frame), Transform3D
                              whenever the pose changed (and every frame up to the highest
                              step logged before a reset, which rewinds the timelines)
  world/contacts              Points3D of the contact points, and
  world/contacts/forces       Arrows3D of the contact forces (when sim.contacts() exists;
                              logged when there are contacts or were at the last frame, and
                              after a reset as the collider poses are)
  plots/energy/{total,kinetic,elastic}, plots/step_ms, plots/contact_force   Scalars
Timelines: `step` (sequence: sim.step_count) and `sim_time` (duration, seconds).
A default blueprint shows the 3D view beside the three plots.

rate: log every step (None) or at most `rate` Hz of sim time, with the node's rule
(step k is logged when floor(k dt rate) changed).
"""
import math

import numpy as np

from ..errors import MdssError
from ..rotations import matrices_from_quats

MODES = ("off", "file", "spawn", "serve")


class RerunLogError(MdssError):
    """rerun logging cannot start (bad mode, unwritable file, no viewer)."""


def _palette():
    from ..ros.convert import DOMAIN_PALETTE
    return (np.asarray(DOMAIN_PALETTE) * 255).round().astype(np.uint8)


def blueprint(bounds=None):
    """The default layout: the 3D view (eye fitted to bounds (2, 3), z up) beside the plots."""
    import rerun.blueprint as rrb
    eye = None
    if bounds is not None:
        lo, hi = np.asarray(bounds, dtype=float)
        center, size = 0.5 * (lo + hi), float(np.max(hi - lo)) or 1.0
        eye = rrb.EyeControls3D(position=center + size * np.array([0.25, -1.1, 0.45]), look_target=center,
                                eye_up=(0.0, 0.0, 1.0))
    view = rrb.Spatial3DView(origin="world", name="body", eye_controls=eye)
    return rrb.Blueprint(
        rrb.Horizontal(
            view,
            rrb.Vertical(
                rrb.TimeSeriesView(origin="plots/energy", name="energy (J)"),
                rrb.TimeSeriesView(origin="plots/step_ms", name="step (ms)"),
                rrb.TimeSeriesView(origin="plots/contact_force", name="contact force (N)"),
            ),
            column_shares=[3, 2],
        ),
        rrb.SelectionPanel(state="collapsed"),
    )


class RerunLogger:
    """Logs a Simulator to rerun; see the module docstring."""

    def __init__(self, sim, mode="file", path=None, application_id="mdss_ros", recording_id=None,
                 rate=None, domain_names=None, spawn_port=9876, web_port=None, grpc_port=None):
        if mode not in MODES:
            raise RerunLogError(f"rerun mode must be one of {', '.join(MODES)}, got {mode!r}")
        self.sim = sim
        self.mode = mode
        self.path = path
        self.rate = rate
        self.url = None
        self.closed = mode == "off"
        self.frames = 0
        self._last_logged = None
        self._collider_poses = {}
        self._logged_pose = {}
        self._logged_contacts = None          # contacts in the last logged frame (None: none logged yet)
        self._high = -1                       # the highest step logged so far
        self._shadowed = -1                   # steps up to this one hold rows from before a reset
        if mode == "off":
            return
        import rerun as rr
        self.rr = rr
        self.rec = rr.RecordingStream(application_id, recording_id=recording_id)
        self.rec.set_log_tick_enabled(False)
        rest = np.asarray(sim.rest_positions())
        bp = blueprint((rest.min(axis=0), rest.max(axis=0)))
        try:
            if mode == "file":
                if not path:
                    raise RerunLogError("rerun mode 'file' needs a path (rerun_path / --rrd)")
                try:                              # rerun reports a bad path only in its log
                    with open(path, "wb"):
                        pass
                except OSError as err:
                    raise RerunLogError(f"cannot write rerun file {path}: {err.strerror or err}") from err
                self.rec.save(str(path), default_blueprint=bp)
            elif mode == "spawn":
                self.rec.spawn(port=spawn_port, default_blueprint=bp)
            else:
                self.url = self.rec.serve_grpc(grpc_port=grpc_port, default_blueprint=bp)
                rr.serve_web_viewer(web_port=web_port, open_browser=False, connect_to=self.url)
        except RerunLogError:
            raise
        except Exception as err:  # noqa: BLE001 - rerun raises various types for a missing viewer
            raise RerunLogError(f"rerun mode {mode!r}: {type(err).__name__}: {err}") from err
        if domain_names is None:
            from .ros_messages import domain_names as names_of
            domain_names = names_of(sim)
        self.domain_names = list(domain_names)
        self._log_static()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
        return False

    # ----------------------------------------------------------------- static
    def _log_static(self):
        rr, rec, sim = self.rr, self.rec, self.sim
        pal = _palette()
        ids = np.asarray(sim.surface_vertex_ids())
        dom = np.asarray(sim.model.vertex_domain)[ids]
        colors = pal[dom % len(pal)]
        rec.log("world/body/surface", rr.Mesh3D.from_fields(
            triangle_indices=np.asarray(sim.surface_triangles(), dtype=np.uint32), vertex_colors=colors),
            static=True)
        extent = float(np.ptp(np.asarray(sim.rest_positions()), axis=0).max()) or 1.0
        # Every domain's axes as one Arrows3D, three arrows a domain: a Transform3D per
        # domain entity cost one log call each, 70 us apiece standalone and 0.87 ms a frame
        # for armadillo_class's 11 domains on the node's thread (quiet machine). The colours
        # and names are static; each frame logs the arrows' origins and vectors only.
        self._axis_length = 0.1 * extent
        n_dom = len(self.domain_names)
        rgb = np.array([(230, 40, 40), (40, 180, 40), (40, 90, 230)], dtype=np.uint8)
        labels = [lab for name in self.domain_names for lab in (name, "", "")]
        rec.log("world/domains", rr.Arrows3D.from_fields(colors=np.tile(rgb, (n_dom, 1)), labels=labels,
                                                         show_labels=True), static=True)
        # The contacts' look is static; each frame logs their positions (and arrows) only.
        red = [(230, 30, 30)]
        rec.log("world/contacts", rr.Points3D.from_fields(radii=[0.003], colors=red), static=True)
        rec.log("world/contacts/forces", rr.Arrows3D.from_fields(colors=red), static=True)
        for name, spec in sim.scene["colliders"].items():
            shape = _collider_shape(rr, spec, extent, sim.scene.base_dir)
            if shape is not None:
                rec.log(f"world/colliders/{name}", shape, static=True)
        for path, color in (("plots/energy/total", (40, 40, 40)), ("plots/energy/kinetic", (214, 39, 40)),
                            ("plots/energy/elastic", (31, 119, 180)), ("plots/step_ms", (255, 127, 14)),
                            ("plots/contact_force", (44, 160, 44))):
            rec.log(path, rr.SeriesLines(colors=[color], names=[path.rsplit("/", 1)[1]]), static=True)

    # ----------------------------------------------------------------- per step
    def collider_pose(self, name, position, orientation=(0.0, 0.0, 0.0, 1.0)):
        """Remember a collider pose (logged with the next step). Not needed when the
        Simulator has `colliders` (name -> object with position, orientation): those are read."""
        self._collider_poses[name] = (np.asarray(position, float), np.asarray(orientation, float))

    def _due(self):
        k = self.sim.step_count
        if self.rate is None or self._last_logged is None or k < self._last_logged:
            return True
        tick = lambda s: math.floor(s * self.sim.dt * self.rate + 1e-6)  # noqa: E731
        return tick(k) > tick(self._last_logged)

    def log_step(self, step_ms=None):
        """Log the simulator's current state on the `step` and `sim_time` timelines."""
        if self.closed or not self._due():
            return False
        rr, rec, sim = self.rr, self.rec, self.sim
        k = sim.step_count
        if self._last_logged is not None and k < self._last_logged:
            # A reset rewinds the timelines, and the viewer shows at a step the latest row at
            # or before it: the rows logged before the reset, up to the highest step, would
            # show through every frame the new run leaves out. Up to that step every frame is
            # logged in full.
            self._shadowed = self._high
        self._last_logged = k
        self._high = max(self._high, k)
        every = k <= self._shadowed
        rec.set_time("step", sequence=int(sim.step_count))
        rec.set_time("sim_time", duration=float(sim.time))
        x = np.asarray(sim.surface_positions(), dtype=np.float32)
        if np.all(np.isfinite(x)):
            rec.log("world/body/surface", rr.Mesh3D.from_fields(vertex_positions=x))
        poses = np.asarray(sim.domain_poses(), dtype=np.float64).reshape(-1, 7)
        if len(poses):
            # A domain whose pose is not finite gets zero-length arrows at the origin; the
            # others are drawn (each arrow keeps its place, and so its colour and label).
            bad = ~np.all(np.isfinite(poses), axis=1)
            if bad.any():
                poses = poses.copy()
                poses[bad] = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0)
            origins, vectors = domain_axes(poses, self._axis_length)
            if bad.any():
                vectors[np.repeat(bad, 3)] = 0.0
            rec.log("world/domains", rr.Arrows3D.from_fields(origins=origins, vectors=vectors))
        poses = dict(self._collider_poses)
        for name, c in (getattr(sim, "colliders", None) or {}).items():   # mdss_ros.contact colliders
            if hasattr(c, "position") and hasattr(c, "orientation"):
                poses[name] = (np.asarray(c.position, float), np.asarray(c.orientation, float))
        for name, (pos, quat) in poses.items():
            if every or self._logged_pose.get(name) is None or not (np.array_equal(self._logged_pose[name][0], pos)
                                                          and np.array_equal(self._logged_pose[name][1], quat)):
                rec.log(f"world/colliders/{name}", rr.Transform3D(translation=pos, quaternion=quat))
                self._logged_pose[name] = (pos.copy(), quat.copy())
        self._collider_poses = {}
        contact_force = 0.0
        contacts_of = getattr(sim, "contacts", None)
        if callable(contacts_of):
            c = np.asarray(contacts_of(), dtype=np.float64).reshape(-1, 10)
            c = c[np.all(np.isfinite(c), axis=1)]
            # The viewer shows the latest value: an empty frame after an empty frame changes
            # nothing (unless rows from before a reset are in the way, above), and its two log
            # calls cost 0.2 ms a frame on armadillo_class, which touches nothing.
            if len(c) or self._logged_contacts != 0 or every:
                points = np.ascontiguousarray(c[:, :3], dtype=np.float32)
                rec.log("world/contacts", rr.Points3D.from_fields(positions=points))
                rec.log("world/contacts/forces", rr.Arrows3D.from_fields(
                    origins=points, vectors=np.asarray(c[:, 7:10] * 0.01, dtype=np.float32)))
                self._logged_contacts = len(c)
            contact_force = float(np.linalg.norm(c[:, 7:10], axis=1).sum()) if len(c) else 0.0
        e = sim.energy()
        for key in ("total", "kinetic", "elastic"):
            if math.isfinite(e[key]):
                rec.log(f"plots/energy/{key}", rr.Scalars(e[key]))
        if step_ms is not None:
            rec.log("plots/step_ms", rr.Scalars(float(step_ms)))
        rec.log("plots/contact_force", rr.Scalars(contact_force))
        self.frames += 1
        return True

    def close(self):
        """Flush everything to the sink (file, viewer) and stop logging. Idempotent."""
        if self.closed:
            return
        self.closed = True
        try:
            self.rec.flush(timeout_sec=30.0)
        finally:
            if self.mode in ("file", "spawn"):
                self.rec.disconnect()


def domain_axes(poses, length):
    """Arrows (origins, vectors), each (3 D, 3) float32, of the axes of D frames poses (D, 7)
    (x, y, z, qx, qy, qz, qw): domain k's x, y, z axes of the given length are arrows 3 k,
    3 k + 1, 3 k + 2 from its origin, the columns of its rotation."""
    R = matrices_from_quats(poses[:, 3:7])               # R[k, :, j]: axis j of frame k
    vectors = length * np.swapaxes(R, 1, 2).reshape(-1, 3)
    origins = np.repeat(poses[:, :3], 3, axis=0)
    return origins.astype(np.float32), vectors.astype(np.float32)


def _collider_shape(rr, spec, extent, base_dir=None):
    """A static rerun shape of a scene collider spec in its local frame (mdss_ros.contact.colliders:
    sphere radius; capsule radius, half_height along local z; box half_extents; plane z = 0;
    mesh: its file's triangles, scaled, relative to the scene's folder base_dir)."""
    shape = spec.get("shape")
    color = [(150, 150, 160, 110)]
    if shape == "mesh":
        import trimesh
        from pathlib import Path
        mesh = trimesh.load(str(Path(base_dir or ".") / spec["file"]), force="mesh")
        return rr.Mesh3D(vertex_positions=np.asarray(mesh.vertices) * float(spec.get("scale", 1.0)),
                         triangle_indices=np.asarray(mesh.faces, dtype=np.uint32),
                         vertex_colors=np.tile(np.array(color[0], dtype=np.uint8), (len(mesh.vertices), 1)))
    if shape == "sphere":
        return rr.Ellipsoids3D(radii=[float(spec["radius"])], colors=color, fill_mode="solid")
    if shape == "capsule":
        hh = float(spec["half_height"])           # rerun's capsule runs from its origin along +z
        return rr.Capsules3D(lengths=[2.0 * hh], radii=[float(spec["radius"])], translations=[(0.0, 0.0, -hh)],
                             colors=color)
    if shape == "box":
        return rr.Boxes3D(half_sizes=[spec["half_extents"]], colors=color, fill_mode="solid")
    if shape == "plane":
        s = 2.0 * extent
        return rr.Boxes3D(half_sizes=[[s, s, 1e-4 * s]], colors=color, fill_mode="solid")
    return None
