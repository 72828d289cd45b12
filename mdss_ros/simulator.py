"""The Simulator facade (docs/architecture.md, "Contracts: Python API"): one API over every model kind.

It owns the inputs (handle wrenches, point forces, collider poses, gravity), turns
them into per-vertex external forces each step, and delegates the dynamics to the
model the scene asks for. Nothing here imports rclpy.
"""
import time
from types import MappingProxyType

import numpy as np

from .body import build_body
from .contact.colliders import inside_body
from .errors import SceneError
from .guard import GuardSettings, StabilityGuard
from .loads import VertexLoads, closest_surface_point, wrench_to_vertex_forces
from .model_build import build_model
from .scene import Scene, load_scene
from .step_options import StepOptions
from .threads import BlasThreads

#: The collider part of a snapshot of a Simulator without colliders (Simulator._save):
#: no sweep starts, no poses. Read-only, so every snapshot may share it.
_NO_SWEEP = MappingProxyType({})


class Simulator:
    """Steps one deformable body of a scene.

    scene: a Scene, a path or scene name, or a dict (validated by load_scene).
    progress: callable(str) that hears long build steps; cache: a PrecomputeCache
    (default: $MDSS_CACHE_DIR or ~/.cache/mdss_ros; PrecomputeCache(enabled=False) turns it off).
    budget: the report of mdss_ros.budget.resolve_budget for a scene whose model.budget was
    resolved (stats() and explain() show it). This class refuses a scene with an unresolved
    model.budget: the probe runs Simulators itself. The public `mdss_ros.Simulator`
    (mdss_ros.budget.Simulator) resolves it first, so a scene without a `model` section
    (the automatic model has a budget) works there.
    """

    def __init__(self, scene, overrides=None, progress=None, cache=None, budget=None):
        if not isinstance(scene, Scene) or overrides:
            scene = load_scene(scene, overrides)
        if scene["model"].get("budget"):
            raise SceneError(f"{scene.source}: model.budget {scene['model']['budget']} must be resolved before "
                             f"this Simulator is built: use mdss_ros.Simulator (it resolves it) or "
                             f"mdss_ros.budget.build_simulator(scene, ...)")
        t0 = time.perf_counter()
        self.budget = budget
        self.scene = scene
        self.body = build_body(scene, cache)
        self.model = build_model(scene, self.body, progress, cache)
        self.build_seconds = time.perf_counter() - t0
        self.gravity = np.asarray(scene["gravity"], dtype=np.float64)
        self._dt = self.model.dt
        self._collider_cache, self._collider_sdfs = cache, {}     # mesh colliders' grids (reset reuses them)
        self._contact_margin = None                               # a mean surface edge, on first contact
        self._make_colliders()
        self._collider_names = set(self.colliders)
        self.model.watch(self.body.surface.vertex_ids)         # only the surface is rebuilt per frame
        self.guard = StabilityGuard(self.model, self.body.tets, GuardSettings.from_scene(scene["model"]["guard"]))
        n = scene["model"]["blas_threads"]
        # auto: one BLAS thread for a reduced model; a full-space one keeps MKL's threads for
        # PARDISO and gets one thread of any other BLAS for its small dense products (threads.py).
        self._blas_threads = (BlasThreads(n) if n != "auto" else BlasThreads(1) if self.model.kind == "reduced"
                              else BlasThreads(1, skip=("mkl",)))
        self.reset()

    # ----------------------------------------------------------------- state
    def _make_colliders(self):
        from .contact.colliders import make_collider
        try:
            self.colliders = {name: make_collider(name, spec, self.scene.base_dir, self._collider_cache,
                                                  self._collider_sdfs)
                              for name, spec in self.scene["colliders"].items()}
        except SceneError as err:
            raise SceneError(f"{self.scene.source}: {err}") from err
        # Poses at the start of the coming step, for sweeping fast colliders.
        self._collider_start = {name: (c.position.copy(), c.orientation.copy()) for name, c in self.colliders.items()}

    def _check_colliders_at_load(self):
        """Colliders whose scene pose is inside the body at rest (docs/method.md §14, "A collider
        inside the body"): a ColliderInsideWarning each, kept in self.colliders_inside_at_load
        {name: {"depth" m, "vertices", "vertex", "core_inside", "suggested" (3,) or None}}."""
        import warnings
        from .contact.colliders import ColliderInsideWarning, clear_position, inside_body
        x = self.body.vertices
        tol = 1e-6 * float(np.linalg.norm(np.ptp(x, axis=0)))          # round-off of a touching pose
        surf = self.body.surface
        self.colliders_inside_at_load = {}
        for name, c in self.colliders.items():
            depth, count, k = c.penetration(x, tol)                     # every vertex, vectorised
            core = inside_body(c, x[surf.vertex_ids], surf.triangles)
            if not count and not core:
                continue
            margin = self._contact_spec()["margin"]
            suggested = clear_position(c, x[surf.vertex_ids], 0.5 * margin)
            self.colliders_inside_at_load[name] = {"depth": depth, "vertices": count, "vertex": k,
                                                   "core_inside": core, "suggested": suggested}
            where = (f"{count} vertex{'es' if count != 1 else ''} inside it, the deepest {1e3 * depth:.1f} mm deep "
                     f"(vertex {k} at {np.round(x[k], 4).tolist()})" if count else
                     "no vertex inside it, but its centre is inside the body's volume")
            hint = (f"; if that is not intended, give it a position clear of the body, e.g. "
                    f"position: {np.round(suggested, 4).tolist()}" if suggested is not None else "")
            warnings.warn(f"{self.scene.source}: collider {name!r} ({c.shape}) starts inside the body: {where}. "
                          f"The first step's contact pushes the body out of it along the shortest way (its "
                          f"outward normal), and while it is inside the body it is not swept when posed: it "
                          f"moves straight to each new pose{hint}", ColliderInsideWarning, stacklevel=3)

    def reset(self):
        """Back to the rest state at t = 0 with no inputs; colliders at their scene poses."""
        self._make_colliders()
        self._check_colliders_at_load()
        self.colliders_inside = {n: dict(v) for n, v in self.colliders_inside_at_load.items()}
        self.model.reset()
        iv = self.scene["initial_velocity"]
        if any(iv["linear"]) or any(iv["angular"]):
            self.model.set_rigid_velocity(iv["linear"], iv["angular"])
        self.guard.reset()
        self.time = 0.0
        self.step_count = 0
        self._wrenches = {}
        self._point_forces = []   # (tri vertex ids (3,), barycentric (3,), force (3,), t_end or None)
        self._stats = {}

    @property
    def dt(self):
        return self._dt

    #: A collider may move at most this fraction of the contact margin per (sub-)step;
    #: faster motion is split into sub-steps so it cannot jump over surface vertices.
    MAX_COLLIDER_TRAVEL = 0.5
    MAX_SUBSTEPS = 32

    # ----------------------------------------------------------------- inputs
    def set_wrench(self, handle, force=(0.0, 0.0, 0.0), torque=(0.0, 0.0, 0.0)):
        """Hold a wrench (world frame) on a handle until replaced; all zeros clears it."""
        if handle not in self.body.handles:
            raise KeyError(f"unknown handle {handle!r} (scene handles: {sorted(self.body.handles)})")
        force = _finite3(force, "force")
        torque = _finite3(torque, "torque")
        if not force.any() and not torque.any():
            self._wrenches.pop(handle, None)
        else:
            self._wrenches[handle] = (force, torque)

    def add_point_force(self, point, force, duration=0.0):
        """Apply force (3,) at the surface point nearest to point (3,).

        duration 0: the next step only; > 0: for that many seconds; < 0: until clear_forces().
        """
        point = _finite3(point, "point")
        force = _finite3(force, "force")
        tris = self.body.surface.triangles
        ids = self.body.surface.vertex_ids
        k, bary, _ = closest_surface_point(point, self.model.positions_of(ids), tris)
        t_end = None if duration < 0 else self.time + max(float(duration), 0.0)
        self._point_forces.append((ids[tris[k]], bary, force, t_end))

    def clear_forces(self):
        """Drop all wrenches and point forces."""
        self._wrenches.clear()
        self._point_forces.clear()

    def set_collider_friction(self, name, static, kinetic=None):
        """Set a collider's Coulomb coefficients from the next step on: static mu_s and
        kinetic mu_k (default mu_s); 0 is frictionless. ValueError for a negative or
        non-finite value or mu_k > mu_s; KeyError for an unknown collider. A reset restores
        the scene's values (the node writes its friction parameters into the scene, so its
        reset keeps them)."""
        if name not in self._collider_names:
            raise KeyError(f"unknown collider {name!r} (scene colliders: {sorted(self._collider_names)})")
        from .contact.friction import parse_friction
        value = {"static": static} if kinetic is None else {"static": static, "kinetic": kinetic}
        self.colliders[name].friction = parse_friction(f"colliders.{name}", value)

    def set_collider_pose(self, name, position, orientation=(0.0, 0.0, 0.0, 1.0)):
        """Pose a kinematic collider (world frame; orientation x y z w, normalised here).

        Returns None, or when the new pose puts the collider deeper than inside_depth into the
        body's current surface {"depth" m, "vertices" (how many), "vertex" (the deepest's id)}:
        the node counts these. Such a collider is swept to the pose in sub-steps if it starts
        the step outside the body, and moved straight there if it starts inside (§14)."""
        if name not in self._collider_names:
            raise KeyError(f"unknown collider {name!r} (scene colliders: {sorted(self._collider_names)})")
        c = self.colliders[name]
        c.set_pose(_finite3(position, "position"), orientation)
        # Deeper than the sweep's per-step travel into the current surface: reported (the
        # node counts it); a slow press of a few tenths of a millimetre is ordinary contact.
        depth, count, k = c.penetration(self.surface_positions(), self.inside_depth)
        if not count:
            self.colliders_inside.pop(name, None)
            return None
        info = {"depth": depth, "vertices": count, "vertex": int(self.body.surface.vertex_ids[k])}
        self.colliders_inside[name] = info
        return info

    @property
    def inside_depth(self):
        """Depth (m) beyond which a collider counts as posed inside the body at a pose update
        or a step's start: the sweep's largest travel per sub-step (half a mean surface edge)."""
        return self.MAX_COLLIDER_TRAVEL * self._margin()

    def _margin(self):
        """The contact search's margin (m): a mean surface edge, computed once."""
        if self._contact_margin is None:
            tri = self.body.surface.triangles
            pos = self.rest_positions()[self.body.surface.vertex_ids]
            edges = np.linalg.norm(pos[tri[:, [1, 2, 0]]] - pos[tri], axis=2)
            # Vertices within a surface edge of a collider (predicted) become candidates.
            self._contact_margin = float(edges.mean())
        return self._contact_margin

    def _embedded_colliders(self):
        """Colliders about to be swept this step (moved more than inside_depth since their last
        step) whose start pose is inside the body: a surface vertex deeper than inside_depth
        in it, or its centre inside the surface. They are not swept (docs/method.md §14)."""
        out, surface, box = [], None, None
        depth = self.inside_depth       # once: every step runs this, colliders moved or not
        for name, c in self.colliders.items():
            p0, q0 = self._collider_start.get(name, (c.position, c.orientation))
            if float(np.linalg.norm(c.position - p0)) <= depth:
                continue
            surface = self.surface_positions() if surface is None else surface
            if c.shape == "sphere":
                # A sphere whose bounding box misses the surface's has no surface vertex
                # inside it, and its centre, outside the closed surface's box, has winding
                # number 0: not embedded, without the winding number's pass over every
                # surface triangle (hammock's lowered weight: about 3 ms a move).
                box = (surface.min(0), surface.max(0)) if box is None else box
                p = np.asarray(p0, dtype=np.float64)
                if np.any(p + c.radius < box[0]) or np.any(p - c.radius > box[1]):
                    continue
            start = c.at(p0, q0)
            if start.penetration(surface, depth)[1] or \
                    inside_body(start, surface, self.body.surface.triangles):
                out.append(name)
        return out

    def external_forces(self):
        """Per-vertex external force (n_verts, 3) for the coming step, gravity included."""
        return self.applied_forces() + self.model.vertex_mass[:, None] * self.gravity[None, :]

    def applied_loads(self):
        """The applied loads (wrenches and point forces, no gravity) as VertexLoads: only the
        loaded vertices, so a reduced step never touches an (n_verts, 3) array."""
        parts = []
        for handle, (force, torque) in self._wrenches.items():
            ids = self.body.handles[handle]
            parts.append((ids, wrench_to_vertex_forces(lambda ids=ids: self.model.positions_of(ids),
                                                       self.model.vertex_mass[ids], force, torque)))
        for ids, bary, force, _ in self._point_forces:
            parts.append((ids, bary[:, None] * force[None, :]))
        return VertexLoads(len(self.body.vertices), parts)

    def applied_forces(self):
        """Per-vertex applied loads (n_verts, 3): wrenches and point forces, no gravity
        (models treat gravity in closed form, so a step touches only loaded vertices)."""
        return self.applied_loads().dense()

    # ----------------------------------------------------------------- stepping
    def step(self, n=1):
        """Advance n steps of dt. Every step goes through the stability guard (mdss_ros.guard):
        a diverging step is rolled back and retried; if nothing helps the last good state is
        kept and stats()["stability"] says "failed". Time advances either way."""
        with self._blas_threads():
            for _ in range(int(n)):
                self._step_once()

    def _step_once(self):
        """One step of dt through the guard (see step)."""
        t0 = time.perf_counter()
        f_app = self.applied_loads()
        t1 = time.perf_counter()
        # Collider poses set for the end of this step; guard sub-steps interpolate towards them.
        self._collider_targets = {name: (c.position.copy(), c.orientation.copy())
                                  for name, c in self.colliders.items()}
        embedded = self._embedded_colliders() if self.colliders else []
        for name in embedded:
            # Inside the body at the step's start: no sweep through it, straight to the target
            # (the contact then pushes the body out of it along the shortest way).
            self._collider_start[name] = self._collider_targets[name]
        self._collider_step_start = dict(self._collider_start)
        model_stats, report = self.guard.step(lambda k, n_sub, options: self._advance(f_app, k, n_sub, options),
                                              self._save, self._restore, f_app, self.gravity,
                                              self.step_count)
        t2 = time.perf_counter()
        self.time = (self.step_count + 1) * self.dt
        self.step_count += 1
        # A zero-duration force lasts exactly the step it was applied in.
        self._point_forces = [p for p in self._point_forces if p[3] is None or p[3] > self.time + 1e-12]
        self._stats = dict(model_stats, **report, loads_ms=1e3 * (t1 - t0), step_ms=1e3 * (t2 - t0))
        if embedded:
            self._stats["colliders_not_swept"] = embedded

    def _advance(self, f_app, k, n_sub, options=None):
        """Sub-step k (1..n_sub) of a step, with the guard's StepOptions (dt / n_sub). Colliders
        move to their pose at k / n_sub of the way from the step's start to its target."""
        if not self.colliders:
            return self.model.step(f_app, self.gravity, options=options)
        if n_sub > 1:
            a = k / n_sub
            for name, c in self.colliders.items():
                (p0, q0), (p1, q1) = self._collider_step_start.get(name, self._collider_targets[name]), \
                    self._collider_targets[name]
                c.set_pose((1 - a) * p0 + a * p1, (1 - a) * q0 + a * (q1 if np.dot(q0, q1) >= 0 else -q1))
        return self._step_with_colliders(f_app, options)

    def _save(self):
        """Everything a step changes: the model state and the collider sweep bookkeeping.
        Only the guard saves, to roll back steps, so the model may share what its steps
        replace rather than copy it (get_state(share=True))."""
        if not self.colliders:             # every step: no sweep bookkeeping (_collider_start is {})
            # _NO_SWEEP: two empty mappings made once (_restore only reads them).
            return self.model.get_state(share=True), _NO_SWEEP, _NO_SWEEP
        return (self.model.get_state(share=True), dict(self._collider_start),
                {name: (c.position.copy(), c.orientation.copy()) for name, c in self.colliders.items()})

    def _restore(self, snapshot):
        state, start, poses = snapshot
        self.model.set_state(state)
        self._collider_start = dict(start)
        for name, (p, q) in poses.items():
            self.colliders[name].set_pose(p, q)

    # ----------------------------------------------------------------- outputs
    def surface_triangles(self):
        return self.body.surface.triangles

    def surface_positions(self):
        with self._blas_threads():           # per frame, like a step (threads.py)
            return self.model.positions_of(self.body.surface.vertex_ids)

    def surface_vertex_ids(self):
        return self.body.surface.vertex_ids

    def vertex_positions(self):
        return self.model.vertex_positions()

    def rest_positions(self):
        return self.body.vertices

    def tetrahedra(self):
        return self.body.tets

    def pinned_vertices(self):
        return self.body.pinned

    def domain_poses(self):
        return self.model.domain_poses()

    def energy(self):
        kinetic, elastic, gravity = self.model.energies(self.gravity)
        return {"kinetic": kinetic, "elastic": elastic, "gravity": gravity,
                "total": kinetic + elastic + gravity}

    def _step_with_colliders(self, f_app, options=None):
        """One step with contact. Colliders that moved more than MAX_COLLIDER_TRAVEL x the
        contact margin since the last step are swept in sub-steps (poses interpolated,
        dt split) so a fast collider cannot pass through the surface between two steps."""
        spec = self._contact_spec()
        moved = 0.0
        surface = None
        for name, c in self.colliders.items():
            p0, _ = self._collider_start.get(name, (c.position, c.orientation))
            travel = float(np.linalg.norm(c.position - p0))
            if travel <= self.MAX_COLLIDER_TRAVEL * spec["margin"]:
                continue
            # Only a collider whose sweep can reach the body needs sub-steps (they change
            # the trajectory, so a far-away collider must not trigger them).
            surface = self.surface_positions() if surface is None else surface
            if c.distance(surface).min() < travel + spec["margin"]:
                moved = max(moved, travel)
        n_sub = int(min(self.MAX_SUBSTEPS, max(1, np.ceil(moved / (self.MAX_COLLIDER_TRAVEL * spec["margin"])))))
        options = options or StepOptions()
        dt = options.dt or self.model.dt         # the step, or a guard sub-step of it
        if n_sub == 1:
            stats = self.model.step(f_app, self.gravity, contact=spec, options=options)
        else:
            targets = {name: (c.position.copy(), c.orientation.copy()) for name, c in self.colliders.items()}
            starts = {name: self._collider_start.get(name, targets[name]) for name in targets}
            # The guard judges the whole sweep against the work done over it, so the work
            # each sub-step reports is summed (the last sub-step's alone made a load held
            # during a far collider's sweep look like created energy).
            work = {"external_work": 0.0, "contact_work": 0.0}
            for k in range(1, n_sub + 1):
                a = k / n_sub
                spec["starts"] = [(c.position.copy(), c.orientation.copy()) if k > 1 else starts[name]
                                  for name, c in self.colliders.items()]
                for name, c in self.colliders.items():
                    (p0, q0), (p1, q1) = starts[name], targets[name]
                    q = (1 - a) * q0 + a * (q1 if np.dot(q0, q1) >= 0 else -q1)
                    c.set_pose((1 - a) * p0 + a * p1, q)
                stats = self.model.step(f_app, self.gravity, contact=spec, options=options.split(dt, n_sub))
                for key in work:
                    if work[key] is not None and isinstance(stats, dict) and stats.get(key) is not None:
                        work[key] += float(stats[key])
                    else:
                        work[key] = None     # not reported: the guard measures it itself
            stats = dict(stats, collider_substeps=n_sub, **{k: w for k, w in work.items() if w is not None})
        self._collider_start = {name: (c.position.copy(), c.orientation.copy()) for name, c in self.colliders.items()}
        return stats

    def _contact_spec(self):
        margin = self._margin()
        # Round colliders press into faces between vertices; boxes and planes are left to
        # vertex contacts (a box edge can still cut a coarse face between two vertices).
        round_ = any(c.shape in ("sphere", "capsule") for c in self.colliders.values())
        colliders = list(self.colliders.values())
        # Start poses of this (sub-)step: a moving collider drags what sticks to it (friction.py).
        starts = [self._collider_start.get(name) for name in self.colliders]
        return {"colliders": colliders, "vertices": self.body.surface.vertex_ids,
                "margin": margin,
                "triangles": self.body.surface.triangles if round_ else None,
                "friction": [c.friction for c in colliders], "starts": starts}

    def contacts(self, split=False):
        """Active contacts of the last step: (k, 10) rows x y z nx ny nz depth fx fy fz
        (point on the body, collider normal, penetration depth, force on the body: the
        normal force plus friction).

        split=True returns the parts apart instead, a dict of arrays over the k contacts:
        points (k, 3), normals (k, 3), depth (k,), normal_force (k,) (newtons, >= 0, along
        the normal), friction (k, 3) (tangential, on the body), force (k, 3) (their sum)
        and collider (k,) names."""
        c = self.model.contact
        names = list(self.colliders)
        if split:
            if not c or len(c["vertices"]) == 0:
                return {"points": np.zeros((0, 3)), "normals": np.zeros((0, 3)), "depth": np.zeros(0),
                        "normal_force": np.zeros(0), "friction": np.zeros((0, 3)), "force": np.zeros((0, 3)),
                        "collider": np.array([], dtype=object)}
            return {"points": c["points"], "normals": c["normals"], "depth": c["depth"],
                    "normal_force": c["normal_force"], "friction": c["friction"], "force": c["forces"],
                    "collider": np.array([names[i] for i in c["which"]], dtype=object)}
        if not c or len(c["vertices"]) == 0:
            return np.zeros((0, 10))
        return np.hstack([c["points"], c["normals"], c["depth"][:, None], c["forces"]])

    def collider_wrench(self, name):
        """Reaction (6,) force and torque (about the collider's position) on a collider."""
        if name not in self._collider_names:
            raise KeyError(f"unknown collider {name!r} (scene colliders: {sorted(self._collider_names)})")
        return self.collider_wrenches()[name]

    def collider_wrenches(self):
        """{name: (6,)} the reaction wrench of every collider (as collider_wrench), in one pass."""
        from .contact.unilateral import contact_wrenches
        c = self.model.contact
        if not c or len(c["vertices"]) == 0:
            return {name: np.zeros(6) for name in self.colliders}
        return contact_wrenches(list(self.colliders.values()), c["points"], c["forces"], c["which"])

    def explain(self):
        """What was built for this scene and why (list of str): body, the model's own account
        (ReducedModel.explain), contact and per-step outputs. `mdss run --explain` prints it."""
        b = self.body
        sc = self.scene
        lines = [f"scene {sc.name!r} ({sc.source}): {len(b.vertices)} vertices, {len(b.tets)} tets, "
                 f"{len(b.surface.vertex_ids)} surface vertices, {b.pinned.size} pinned, "
                 f"handles {sorted(b.handles) or 'none'}, dt = {self.dt:.6g} s"]
        lines += self.model.explain()
        if self.colliders:
            shapes = ", ".join(f"{n} ({c.shape})" for n, c in self.colliders.items())
            faces = [n for n, c in self.colliders.items()
                     if c.shape in ("sphere", "capsule") and getattr(c, "face_contacts", True)]
            lines.append(f"contact: built only for the declared colliders: {shapes}; candidates are surface "
                         f"vertices within {self._contact_spec()['margin']:.3g} m (a mean surface edge)"
                         + (f"; {', '.join(faces)} also test surface faces" if faces else ""))
            rough = [f"{n} (static {c.friction[0]:g}, kinetic {c.friction[1]:g})" for n, c in self.colliders.items()
                     if c.friction[0] > 0.0]
            lines.append("friction: " + (f"Coulomb, exact stick, in the implicit step: {', '.join(rough)}; the "
                                         f"others frictionless" if rough else
                                         "none (every collider frictionless; colliders.<name>.friction sets mu)"))
            for n, info in self.colliders_inside_at_load.items():
                lines.append(f"collider {n!r} starts inside the body: " + (
                    f"{info['vertices']} vertices inside it, the deepest {1e3 * info['depth']:.1f} mm"
                    if info["vertices"] else "its centre is inside the body's volume")
                    + "; the first step pushes the body out of it along the shortest way, and it is not "
                      "swept through the body when posed" + (
                    f" (a clear position: {np.round(info['suggested'], 4).tolist()})"
                    if info["suggested"] is not None else ""))
            reach = [n for n, spec in sc["colliders"].items() if isinstance(spec, dict) and spec.get("reach")]
            if reach:
                lines.append(f"collider reach: {', '.join(f'{n}_reach' for n in reach)} simulated in full space "
                             f"(the region each collider can touch); the rest of the body stays as the model says")
        else:
            lines.append("contact: no colliders declared, so no contact search or LCP in the step "
                         "(declare one under colliders: to turn it on)")
        if self.budget:
            bud = self.budget
            several = len({c.get("domains") for c in bud["candidates"]}) > 1
            cands = ", ".join(f"{c['modes']} modes" + (f" {c['domains']}" if several else "")
                              + f" {c['step_ms']:.3g} ms" + (f" {100 * c['rms_rel']:.3g} %" if "rms_rel" in c else "")
                              for c in bud["candidates"])
            lines.append(f"budget {bud['goal']} <= {bud['target']:g}: chose {bud['chosen']['modes']} modes per "
                         f"domain" + (f", {bud['chosen']['domains']}" if several else "")
                         + f" ({'met' if bud['met'] else 'NOT met: closest candidate'}; "
                         f"{'cached probe' if bud.get('cached') else 'probe'} of {cands})"
                         + (f"; the probe used exact forces, and with its cubature the chosen model runs "
                            f"{bud['chosen']['measured']['step_ms']:.3g} ms"
                            + (f" at {100 * bud['chosen']['measured']['rms_rel']:.3g} %"
                               if "rms_rel" in bud["chosen"]["measured"] else "")
                            if "measured" in bud["chosen"] else ""))
        if self.scene.automatic_model:
            lines.append("model: automatic (the scene has no model section): reduced, domains placed from the "
                         "body's shape (weighed against one domain by the budget), cubature at 10 samples per "
                         "mode, modes from the budget ladder for 5 % RMS surface error against full FEM; give a "
                         "model section to choose yourself")
        guard = self.scene["model"]["guard"]
        untangle = (f"; inverted elements a reduced model keeps for {guard['untangle_after']} steps are untangled"
                    if guard["untangle_after"] and self.model.can_untangle else "")
        lines.append("stability guard: " + ("on (every step checked for NaN, energy growth, speed and new "
                                              f"inversions; a bad step is rolled back and retried{untangle})"
                                              if guard["enabled"] else "off (model.guard.enabled: false)"))
        lines.append(f"outputs per step: only the {len(b.surface.vertex_ids)} surface "
                     f"vertices of {len(b.vertices)} are reconstructed for publishing; all vertices, energies, "
                     f"contacts and wrenches only when asked (vertex_positions(), energy(), ...)")
        iv = sc["initial_velocity"]
        lines.append(f"gravity {sc['gravity']}" + (f"; initial velocity linear {iv['linear']} angular "
                                                    f"{iv['angular']}" if any(iv['linear']) or any(iv['angular'])
                                                    else ""))
        return lines

    def stats(self):
        extra = ({"budget": {k: self.budget[k] for k in ("goal", "target", "met")}
                  | {"modes": self.budget["chosen"]["modes"], "domains": self.budget["chosen"].get("domains")}}
                 if self.budget else {})
        return dict(self._stats, **extra, kind=self.model.kind, dofs=self.model.n_dofs,
                    domains=len(self.model.domain_poses()),
                    vertices=len(self.body.vertices), tets=len(self.body.tets), time=self.time)


def _finite3(v, what):
    a = np.asarray(v, dtype=np.float64).reshape(-1)
    if a.shape != (3,) or not np.all(np.isfinite(a)):
        raise ValueError(f"{what} must be 3 finite numbers, got {v!r}")
    return a
