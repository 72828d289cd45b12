"""Where the scene's colliders can touch the body: its surface vertices ordered by their
distance to the colliders' paths.

A collider's path is its pose in the scene file followed by every collider_pose event of
the timeline, with poses added between consecutive ones so that no two are further apart
than `spacing` (a collider swept across the surface passes near every vertex on the
way). A vertex's distance to the paths is its smallest distance to any collider at any of
these poses. The reduced model builds its residual contact compliance
(reduced/residual_compliance.py) on the nearest vertices, so the part of the body that a
scene presses gets the local dent; a collider a node moves elsewhere at run time meets
the modes alone there (`mdss run --explain` says how far the set reaches).
"""
import numpy as np

#: At most this many poses per collider path (interpolated ones included).
MAX_POSES = 2000


def collider_paths(scene, colliders, spacing):
    """{name: [(position (3,), orientation (4,)), ...]}: each collider's scene pose, then its
    timeline poses in time order, with interpolated positions (the earlier orientation)
    so that consecutive positions are at most `spacing` apart (up to MAX_POSES)."""
    paths = {name: [(np.asarray(c.position, float), np.asarray(c.orientation, float))]
             for name, c in colliders.items()}
    for ev in sorted(scene["timeline"], key=lambda e: e["t"]):
        if ev["topic"] != "collider_pose" or ev["name"] not in paths:
            continue
        paths[ev["name"]].append((np.asarray(ev["position"], float),
                                  np.asarray(ev.get("orientation", (0.0, 0.0, 0.0, 1.0)), float)))
    out = {}
    for name, poses in paths.items():
        dense = [poses[0]]
        for (p0, q0), (p1, q1) in zip(poses[:-1], poses[1:]):
            n = int(min(MAX_POSES, max(1, np.ceil(np.linalg.norm(p1 - p0) / spacing))))
            dense += [(p0 + (p1 - p0) * (k / n), q0) for k in range(1, n)] + [(p1, q1)]
        if len(dense) > MAX_POSES:
            dense = [dense[i] for i in np.linspace(0, len(dense) - 1, MAX_POSES).round().astype(int)]
        out[name] = dense
    return out


def distance_to_paths(colliders, paths, points):
    """(n,) smallest signed distance of each point (n, 3) to any collider at any pose of its path."""
    best = np.full(len(points), np.inf)
    for name, c in colliders.items():
        for p, q in paths[name]:
            np.minimum(best, c.at(p, q).distance(points), out=best)
    return best


def nearest_vertices(scene, colliders, positions, ids, count, spacing):
    """(vertex ids (k,), distances (k,)): the `count` vertices of ids (with positions (n, 3))
    nearest the colliders' paths, nearest first; empty without colliders."""
    if not colliders or count <= 0 or len(ids) == 0:
        return np.zeros(0, dtype=np.int64), np.zeros(0)
    d = distance_to_paths(colliders, collider_paths(scene, colliders, spacing), positions)
    order = np.argsort(d, kind="stable")[:count]
    return np.asarray(ids)[order], d[order]
