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
                                                   contact_candidates(scene, body, model, modes["vertices"])))
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
    bkey = bases_cache_key(body, model)
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
