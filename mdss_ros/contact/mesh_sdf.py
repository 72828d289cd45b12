"""Mesh colliders: a closed triangle surface (.obj, .stl, .ply) as a signed distance grid.

    colliders:
      finger: {shape: mesh, file: finger.obj, scale: 1.0, resolution: 0.001}

`file` is relative to the scene file's folder; `scale` multiplies the file's coordinates
(default 1.0, > 0); `resolution` is the grid's cell size in metres (default: the largest
extent of the scaled mesh / 64). The grid covers the mesh's bounding box padded by
PAD_CELLS cells or PAD_FRACTION of the largest extent, whichever is larger, and has at
most MAX_CELLS nodes (a finer `resolution` is a SceneError naming the key).

Build (once; kept in the precompute cache, stage "collider_sdf"): phi at every grid node
by libigl's exact point-to-triangle distance with the generalised winding number as its
sign (mesh/distance.py: not igl.signed_distance, whose magnitudes are wrong at some points
in the pinned version). Why libigl:
it is a well-kept geometry library with an exact point-to-triangle distance on an AABB
tree, and its winding-number sign is exact for any closed mesh, convex or not (a pseudo-
normal sign can flip near sharp non-convex creases, which would make phantom contacts in a
notch). The gradient grid is numpy's second-order central differences of phi.

Query (every step, vectorised over points): trilinear interpolation of phi and of its
gradient at points in the collider frame; the normal is the interpolated gradient,
normalised. Points outside the grid: phi = phi(c) + |p - c| with c the closest point of
the grid box (an upper bound of the true distance, continuous with the grid; such points
are at least the padding away from the mesh, so they are contact candidates only when the
body's mean surface edge exceeds that padding) and its normal the gradient of that
extension.
"""
import hashlib
from pathlib import Path

import numpy as np

from ..errors import SceneError
from ..mesh.distance import signed_distance

EXTENSIONS = (".obj", ".stl", ".ply")
KEYS = ("file", "scale", "resolution")
CELLS_PER_EXTENT = 64           # default resolution: largest extent / 64
MAX_CELLS = 4_000_000           # grid nodes; a finer `resolution` is refused
PAD_CELLS = 3
PAD_FRACTION = 0.1


def check_spec(where, spec, base_dir=None):
    """Checks a mesh collider's own keys without reading the mesh (scene load): the file
    exists with a supported suffix, scale and resolution are positive numbers. Returns the
    file's path."""
    if "file" not in spec:
        raise SceneError(f"{where}.file: required for a mesh (a closed surface: {', '.join(EXTENSIONS)})")
    if not isinstance(spec["file"], str) or not spec["file"]:
        raise SceneError(f"{where}.file: expected a path, got {spec['file']!r}")
    path = Path(base_dir if base_dir is not None else Path.cwd()) / spec["file"]
    if path.suffix.lower() not in EXTENSIONS:
        raise SceneError(f"{where}.file: {str(path)!r} is not a supported surface file "
                         f"({', '.join(EXTENSIONS)})")
    if not path.is_file():
        raise SceneError(f"{where}.file: mesh file {str(path)!r} not found "
                         f"(relative paths are relative to the scene file's folder)")
    for key in ("scale", "resolution"):
        if key in spec:
            v = spec[key]
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not np.isfinite(v) or v <= 0:
                raise SceneError(f"{where}.{key}: expected a number > 0, got {v!r}")
    return path


def read_closed_surface(where, path, scale):
    """(vertices (k, 3) scaled, faces (t, 3) int64, outward) of a closed 2-manifold surface
    file; SceneError (naming `where`.file) for an unreadable, open or non-manifold one."""
    import trimesh

    from ..mesh.tetrahedralize import boundary_loops, edge_place, hole_summary, non_manifold_edges

    try:
        mesh = trimesh.load(str(path), force="mesh")
    except Exception as exc:                                   # any reader error names the file
        raise SceneError(f"{where}.file: cannot read surface file {str(path)!r} ({type(exc).__name__}: {exc})") \
            from None
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) < 4:
        raise SceneError(f"{where}.file: {str(path)!r} contains no closed triangle surface")
    holes = boundary_loops(mesh.vertices, mesh.faces)
    if holes:
        raise SceneError(f"{where}.file: {str(path)!r}: the mesh is not closed (a collider must be watertight "
                         f"so that inside and outside are defined): {len(holes)} hole(s); largest: "
                         f"{hole_summary(holes, scale)}. "
                         f"Close them in a mesh tool (e.g. MeshLab, Blender's 3D-print toolbox)")
    over = non_manifold_edges(mesh.faces)
    if len(over):
        raise SceneError(f"{where}.file: {str(path)!r}: the mesh is not a 2-manifold: {len(over)} edges are shared "
                         f"by more than two triangles (the first near {edge_place(mesh.vertices, over, scale)})")
    if not mesh.is_winding_consistent:
        raise SceneError(f"{where}.file: {str(path)!r}: the mesh's triangles are not consistently wound")
    v = np.asarray(mesh.vertices, dtype=np.float64) * float(scale)
    f = np.asarray(mesh.faces, dtype=np.int64)
    if trimesh.Trimesh(v, f, process=False).volume < 0:
        f = f[:, ::-1].copy()                                 # inside-out: flip to outward
    return v, f


def grid_layout(where, vertices, resolution=None):
    """(origin (3,), cell h, node counts (3,)) of the grid around vertices."""
    lo, hi = vertices.min(0), vertices.max(0)
    extent = float((hi - lo).max())
    if extent <= 0:
        raise SceneError(f"{where}.file: the mesh has no extent")
    h = float(resolution) if resolution is not None else extent / CELLS_PER_EXTENT
    pad = max(PAD_CELLS * h, PAD_FRACTION * extent)
    counts = np.ceil((hi - lo + 2 * pad) / h).astype(np.int64) + 1
    if int(np.prod(counts)) > MAX_CELLS:
        raise SceneError(f"{where}.resolution: {h:.4g} m gives a grid of {' x '.join(map(str, counts))} = "
                         f"{int(np.prod(counts)):,} nodes, more than {MAX_CELLS:,}; use a cell of at least "
                         f"{h * (np.prod(counts) / MAX_CELLS) ** (1 / 3):.3g} m")
    return lo - pad, h, counts


def sample_sdf(vertices, faces, origin, h, counts):
    """phi (nx, ny, nz) at the grid nodes, negative inside (mesh/distance.py: libigl's exact
    distance, winding-number sign)."""
    axes = [origin[k] + h * np.arange(counts[k]) for k in range(3)]
    nodes = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    phi, _ = signed_distance(nodes, vertices, faces)
    return phi.reshape(tuple(int(c) for c in counts))


class MeshSDF:
    """A sampled signed distance field: phi (nx, ny, nz) on nodes origin + h * (i, j, k)."""

    def __init__(self, phi, origin, h):
        self.phi = np.ascontiguousarray(phi, dtype=np.float64)
        self.origin = np.asarray(origin, dtype=np.float64)
        self.h = float(h)
        self.counts = np.array(self.phi.shape)
        self.upper = self.origin + self.h * (self.counts - 1)
        self.grad = np.stack(np.gradient(self.phi, self.h, edge_order=2), axis=-1)
        k = np.unravel_index(int(np.argmin(self.phi)), self.phi.shape)
        self.core = (self.origin + self.h * np.array(k))[None, :]        # deepest node (local frame)

    def evaluate(self, p):
        """phi (n,) and unit normals (n, 3) at local points p (n, 3)."""
        p = np.asarray(p, dtype=np.float64).reshape(-1, 3)
        c = np.clip(p, self.origin, self.upper)
        u = (c - self.origin) / self.h
        i = np.minimum(np.floor(u).astype(np.int64), self.counts - 2)
        t = u - i
        phi = np.zeros(len(p))
        g = np.zeros((len(p), 3))
        for corner in range(8):                      # 8 corners, vectorised over the points
            o = np.array([(corner >> 2) & 1, (corner >> 1) & 1, corner & 1])
            w = np.prod(np.where(o, t, 1.0 - t), axis=1)
            idx = (i[:, 0] + o[0], i[:, 1] + o[1], i[:, 2] + o[2])
            phi += w * self.phi[idx]
            g += w[:, None] * self.grad[idx]
        d = p - c
        out = np.linalg.norm(d, axis=1)
        far = out > 0
        if far.any():                                # outside the grid: phi(c) + |p - c|
            g[far] = np.where(d[far] != 0.0, 0.0, g[far]) + d[far] / out[far, None]
            phi[far] += out[far]
        norm = np.linalg.norm(g, axis=1)
        ok = norm > 1e-12
        n = np.zeros_like(g)
        n[ok] = g[ok] / norm[ok, None]
        n[~ok] = (0.0, 0.0, 1.0)                     # a medial point: any direction is a normal
        return phi, n


def _code():
    # the distance module too: a grid built by an older one is built again
    return Path(__file__).read_text() + (Path(__file__).parents[1] / "mesh" / "distance.py").read_text()


def build_mesh_sdf(where, spec, base_dir=None, cache=None, memo=None):
    """MeshSDF of a mesh collider's spec: from memo (a dict the caller keeps across resets),
    else the precompute cache (stage "collider_sdf"), else built and saved there."""
    from importlib.metadata import version

    from ..precompute import PrecomputeCache, cache_key, code_fingerprint

    path = check_spec(where, spec, base_dir)
    scale = float(spec.get("scale", 1.0))
    resolution = spec.get("resolution")
    key = cache_key("collider_sdf", hashlib.sha256(path.read_bytes()).hexdigest(), scale,
                    None if resolution is None else float(resolution), code_fingerprint(_code()),
                    version("libigl"))
    if memo is not None and key in memo:
        return memo[key]
    cache = cache if cache is not None else PrecomputeCache()
    hit = cache.load("collider_sdf", key)
    if hit is not None:
        arrays, _ = hit
        sdf = MeshSDF(arrays["phi"], arrays["origin"], float(arrays["h"]))
    else:
        v, f = read_closed_surface(where, path, scale)
        origin, h, counts = grid_layout(where, v, resolution)
        phi = sample_sdf(v, f, origin, h, counts)
        cache.save("collider_sdf", key, {"phi": phi, "origin": origin, "h": np.array(h)},
                   {"file": str(path), "scale": scale, "resolution": h})
        sdf = MeshSDF(phi, origin, h)
    if memo is not None:
        memo[key] = sdf
    return sdf
