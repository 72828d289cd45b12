"""Model build: the dynamics model a scene asks for, and what building it will cost.

Between the scene (mdss_ros/scene.py, body.py) and the Simulator: `build_model` turns a
validated scene and its body into a FullSpaceModel or a ReducedModel; `cache_status`
says, before building, whether the precompute cache holds every stage the scene needs
(the node logs it at start).
"""
from .body import build_body
from .errors import SceneError
from .precompute import PrecomputeCache, bases_cache_key, cubature_cache_key
from .scene import model_config


def build_model(scene, body, progress=None, cache=None):
    """The dynamics model of a scene (`model.kind`); progress(msg) hears long build steps."""
    model = model_config(scene)
    kind = model["kind"]
    if model.get("element", "linear") == "quadratic":
        if kind != "full":
            raise SceneError(f"{scene.source}: model.element: quadratic is for model.kind: full (got {kind!r})")
        from .fem.quadratic import QuadraticFullModel
        return QuadraticFullModel(body, scene.dt, model["integrator"], scene["body"]["damping"], solver=model["solver"])
    if kind == "full":
        from .fem.full_model import FullSpaceModel
        return FullSpaceModel(body, scene.dt, model["integrator"], scene["body"]["damping"],
                              mass=scene["body"]["mass"], solver=model["solver"])
    if kind == "reduced":
        from .reduced.reduced_model import ReducedModel
        modes = model["contact_modes"]
        return ReducedModel(body, model, scene.dt, scene["body"]["damping"], solver=model["solver"],
                            progress=progress, cache=cache, contact_vertices=contact_candidates(scene, body, model),
                            contact_mode_vertices=(None if modes["kind"] == "none" else
                                                   contact_candidates(scene, body, model, modes["vertices"])),
                            training_loads=training_load_cases(scene, body, model))
    if kind == "meshless":
        from .meshless.model import LatticeMeshlessModel, MeshlessModel
        if model["meshless"]["nodes"] == "lattice":
            return LatticeMeshlessModel(body, scene.dt, model["integrator"], scene["body"]["damping"],
                                        settings=model["meshless"], solver=model["solver"], pins=scene["pins"])
        return MeshlessModel(body, scene.dt, model["integrator"], scene["body"]["damping"],
                             settings=model["meshless"], solver=model["solver"])
    raise SceneError(f"{scene.source}: model.kind: {kind!r} is not available in this version "
                     f"(available: full, reduced, meshless)")


def contact_candidates(scene, body, model, count=None):
    """Free surface vertex ids (k,) where the scene's colliders other than planes can touch,
    nearest their scene paths first (contact/envelope.py), at most count (default
    model.contact_compliance) of them; None when there is no such collider or the count is 0.

    Planes are left out. A floor under a body touches its whole underside, and with the
    dent every vertex there carries load: the caterpillar resting on its floor had 231
    contacts instead of 39, and its step went from 5.3 to 28 ms frictionless, and to about
    100 ms with friction, for the same total reaction (its weight). The dent matters where
    a tool presses a body locally, which a plane does not."""
    count = int((model.get("contact_compliance", 0) if count is None else count) or 0)
    specs = {name: spec for name, spec in scene["colliders"].items() if spec.get("shape") != "plane"}
    if count <= 0 or not specs:
        return None
    import numpy as np
    from .contact.colliders import make_collider
    from .contact.envelope import nearest_vertices
    colliders = {name: make_collider(name, spec, scene.base_dir) for name, spec in specs.items()}
    surf = body.surface
    free = np.setdiff1d(surf.vertex_ids, body.pinned)
    faces = surf.faces
    edges = body.vertices[faces[:, [1, 2, 0]]] - body.vertices[faces]
    spacing = 0.5 * float(np.linalg.norm(edges, axis=2).mean())
    ids, _ = nearest_vertices(scene, colliders, body.vertices[free], free, count, spacing)
    return ids if len(ids) else None


def bends_from_loads(model):
    """True when the model's domains are placed automatically with cuts from the scene's
    loads (`model.domains: auto` with max_bend > 0): only then do the loads shape the
    partition, and the bases' cache key holds them."""
    dom = model.get("domains")
    if not isinstance(dom, dict) or "auto" not in dom:
        return False
    from .reduced.auto_domains import auto_settings
    return auto_settings(dom["auto"])["max_bend"] > 0


def training_load_cases(scene, body, model):
    """The scene's load cases for placing cuts ([bend_cuts.LoadCase]), or None when the
    partition does not use them (bends_from_loads):
    - gravity with each set of handle wrenches and point forces (duration != 0) that the
      timeline holds at once, after each of its instants (gravity alone when it holds none);
    - for each collider other than a plane, its deepest pose (scene or timeline) into the
      body at rest: the surface vertices inside it pushed out along its normal.
    Pins are the body's. Loads are spread as the Simulator spreads them (loads.py)."""
    if not bends_from_loads(model):
        return None
    import numpy as np
    from .contact.colliders import make_collider
    from .fem.elements import tet_geometry
    from .fem.mass import lumped_mass
    from .loads import closest_surface_point, wrench_to_vertex_forces
    from .reduced.bend_cuts import LoadCase
    X, n = body.vertices, len(body.vertices)
    mass = lumped_mass(body.tets, tet_geometry(X, body.tets).volume, body.material.density, n)
    g = np.asarray(scene["gravity"], dtype=np.float64)
    weight = mass[:, None] * g[None, :]
    held, points, cases = {}, [], []
    surf = body.surface
    events = sorted(scene["timeline"], key=lambda e: e["t"])
    for i, ev in enumerate(events):                    # a scene's timeline: tens of events
        if ev["topic"] == "wrench":
            f, tau = np.asarray(ev.get("force", (0, 0, 0)), float), np.asarray(ev.get("torque", (0, 0, 0)), float)
            if f.any() or tau.any():
                held[ev["frame_id"]] = (f, tau)
            else:
                held.pop(ev["frame_id"], None)
        elif ev["topic"] == "point_force" and ev.get("duration", 0.0) != 0.0:
            k, bary, _ = closest_surface_point(np.asarray(ev["point"], float), X[surf.vertex_ids], surf.triangles)
            points.append((surf.vertex_ids[surf.triangles[k]], bary, np.asarray(ev["force"], float)))
        elif ev["topic"] == "clear_forces":
            held, points = {}, []
        if i + 1 < len(events) and events[i + 1]["t"] == ev["t"]:
            continue                                    # the instant's last event makes the case
        if held or points:
            f = weight.copy()
            for h, (force, torque) in held.items():
                ids = body.handles[h]
                f[ids] += wrench_to_vertex_forces(X[ids], mass[ids], force, torque)
            for ids, bary, force in points:
                f[ids] += bary[:, None] * force[None, :]
            label = (f"t = {ev['t']:g} s: " + ", ".join([f"wrench on {h}" for h in held]
                                                       + [f"{len(points)} point force(s)"] * bool(points)))
            if not any(np.array_equal(f, c.forces) for c in cases):
                cases.append(LoadCase(label, forces=f))
    if not cases and g.any():
        cases.append(LoadCase("gravity", forces=weight))
    for name, spec in scene["colliders"].items():
        if spec.get("shape") == "plane":
            continue
        col = make_collider(name, spec, scene.base_dir)
        poses = [(0.0, col.position, col.orientation)] + [
            (ev["t"], ev["position"], ev.get("orientation", (0, 0, 0, 1))) for ev in events
            if ev["topic"] == "collider_pose" and ev["name"] == name]
        best = None
        for t, pos, orient in poses:                   # a collider's poses: tens
            phi, normal = col.at(np.asarray(pos, float), np.asarray(orient, float)).signed_distance(X[surf.vertex_ids])
            if phi.min() < 0 and (best is None or phi.min() < best[0]):
                inside = phi < 0
                best = (float(phi.min()), t, surf.vertex_ids[inside], -phi[inside, None] * normal[inside])
        if best is not None:
            cases.append(LoadCase(f"collider {name} {-best[0]:.3g} m in at t = {best[1]:g} s",
                                  pushed=(best[2], best[3])))
    return cases


def estimate_precompute_seconds(n_tets, n_domains, modes, samples):
    """Rough build time of a missing cache on a 2-core machine, scaled from measurements
    of this project: bases ~1 ms per tet at 20 modes (armadillo_class: 11 domains, 301K
    tets), training ~180 exact steps, cubature ~6 s per domain at 180 samples."""
    bases = 1.0e-3 * n_tets * max(modes, 1) / 20.0
    training = 180 * 0.8e-6 * n_tets if samples else 0.0
    cubature = 6.0 * n_domains * samples / 180.0 if samples else 0.0
    return bases + training + cubature


def cache_status(scene, cache=None):
    """{"hit": bool, "path": str, "estimate_s": float or None} for a scene's precompute:
    hit when every stage the scene needs is in the cache. Builds only the mesh."""
    model = model_config(scene)
    if model["kind"] != "reduced":
        return {"hit": True, "path": "(a full-space model has no precompute)", "estimate_s": 0.0}
    cache = cache or PrecomputeCache()
    body = build_body(scene, cache)
    bkey = bases_cache_key(body, model, training_load_cases(scene, body, model))
    paths = [cache.path("bases", bkey)]
    ccfg = model.get("cubature") or {}
    samples = int(ccfg.get("samples", 0) or 0)
    if samples > 0:
        damping = scene["body"]["damping"]
        paths.append(cache.path("cubature", cubature_cache_key(bkey, ccfg, scene.dt, damping["alpha"],
                                                               damping["beta"], model)))
    hit = all(p.exists() for p in paths)
    domains = (model.get("domains") or {}).get("count", 1) if isinstance(model.get("domains"), dict) else 1
    est = None if hit else estimate_precompute_seconds(len(body.tets), domains, model["modes"], samples)
    return {"hit": hit, "path": str(paths[-1]), "estimate_s": est}
