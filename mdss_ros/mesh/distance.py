"""Signed distance to a closed triangle surface (libigl).

    s(p) = +-|p - c(p)|,  c(p) the closest surface point,  negative inside

The magnitude and c come from libigl's point_mesh_squared_distance (exact point-to-triangle
distance on an AABB tree), the sign from its generalised winding number w(p) (inside where
w > 1/2: right for any closed surface, convex or not, where a pseudo-normal sign can flip
near sharp non-convex creases).

Why not igl.signed_distance(..., SIGNED_DISTANCE_TYPE_WINDING_NUMBER), which returns both:
in libigl 2.6.3 (the pinned wheel) its magnitudes are wrong at some points of meshes with
many coplanar triangles, and not the same from one call to the next. Measured: a 10 x 6 x 4
cm box subdivided to 768 triangles, a 2.5 mm grid of 40,425 points, 50-93 points off by up
to 14.6 mm (of 70 different ones in three calls); the two calls used here give the exact
box distance at every point (test/test_mesh_distance.py).
"""
import numpy as np


def signed_distance(points, vertices, triangles):
    """(s (p,), closest surface points (p, 3)) of points (p, 3) to the closed surface of
    vertices (n, 3) and outward triangles (t, 3); s < 0 inside."""
    import igl

    P = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
    V = np.ascontiguousarray(vertices, dtype=np.float64)
    F = np.ascontiguousarray(triangles, dtype=np.int64)
    d2, _, closest = igl.point_mesh_squared_distance(P, V, F)[:3]
    w = np.asarray(igl.winding_number(V, F, P), dtype=np.float64)
    s = np.sqrt(np.maximum(np.asarray(d2, dtype=np.float64), 0.0))
    return np.where(w > 0.5, -s, s), np.asarray(closest, dtype=np.float64)
