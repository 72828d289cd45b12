"""Vertex selection by region (box, sphere, half-space), explicit indices or all.

Selector specs come from scene files, so a bad spec raises SceneError naming
the offending key.
"""

from __future__ import annotations

import numpy as np

from mdss_ros.errors import SceneError

_REGION_KEYS = ("box", "sphere", "plane", "indices", "all")
_OPTION_KEYS = ("surface_only", "tolerance")
# Default inclusion tolerance relative to the mesh bbox diagonal: generated
# grid coordinates carry ~1e-16 relative round-off, so a point typed as 0.3
# in a scene file must still catch the node at 0.30000000000000004.
_REL_TOL = 1e-9


def select_vertices(
    vertices: np.ndarray,
    spec: dict,
    surface_ids: np.ndarray | None = None,
) -> np.ndarray:
    """Indices of the vertices matched by a selector spec.

    Spec: a dict with exactly one region key

    - ``{"box": [[xmin, ymin, zmin], [xmax, ymax, zmax]]}`` (closed box),
    - ``{"sphere": {"center": [x, y, z], "radius": r}}`` (closed ball),
    - ``{"plane": {"point": [x, y, z], "normal": [nx, ny, nz]}}``: the closed
      half-space the normal points into (points on the plane included),
    - ``{"indices": [i, ...]}``,
    - ``{"all": true}``,

    and optionally ``"surface_only": true`` (keep only ``surface_ids``) and
    ``"tolerance": t`` (absolute inclusion slack for geometric regions,
    default 1e-9 times the bbox diagonal of ``vertices``).

    Args:
        vertices: (n_verts, 3) float positions.
        spec: selector dict as above.
        surface_ids: (S,) int surface vertex indices, required by surface_only.
    Returns:
        (k,) int64 ascending unique vertex indices (k may be 0).
    Raises:
        SceneError: naming the bad key or value.
    """
    x = np.asarray(vertices, dtype=np.float64)
    if x.ndim != 2 or x.shape[1] != 3:
        raise SceneError(f"selector: vertices must have shape (n_verts, 3), got {x.shape}")
    if not isinstance(spec, dict):
        raise SceneError(f"selector must be a mapping, got {type(spec).__name__}")
    unknown = sorted(set(spec) - set(_REGION_KEYS) - set(_OPTION_KEYS))
    if unknown:
        raise SceneError(f"selector has unknown keys {unknown}; regions are {list(_REGION_KEYS)}")
    regions = [k for k in _REGION_KEYS if k in spec]
    if len(regions) != 1:
        raise SceneError(
            f"selector needs exactly one of {list(_REGION_KEYS)}, got {regions or 'none'}"
        )
    key = regions[0]
    tol = _tolerance(x, spec.get("tolerance"))
    value = spec[key]

    if key == "box":
        mask = _in_box(x, value, tol)
    elif key == "sphere":
        mask = _in_sphere(x, value, tol)
    elif key == "plane":
        mask = _in_half_space(x, value, tol)
    elif key == "indices":
        mask = _index_mask(x.shape[0], value)
    else:
        if value is not True:
            raise SceneError(f"selector 'all' must be true, got {value!r}")
        mask = np.ones(x.shape[0], dtype=bool)

    surface_only = spec.get("surface_only", False)
    if not isinstance(surface_only, bool):
        raise SceneError(f"selector 'surface_only' must be true or false, got {surface_only!r}")
    if surface_only:
        if surface_ids is None:
            raise SceneError("selector 'surface_only' needs the surface vertex ids")
        on_surface = np.zeros(x.shape[0], dtype=bool)
        on_surface[np.asarray(surface_ids, dtype=np.int64)] = True
        mask &= on_surface
    return np.flatnonzero(mask).astype(np.int64)


def _tolerance(x: np.ndarray, value) -> float:
    if value is None:
        if x.shape[0] == 0:
            return 0.0
        return _REL_TOL * float(np.linalg.norm(x.max(axis=0) - x.min(axis=0)))
    t = _number(value, "tolerance")
    if t < 0:
        raise SceneError(f"selector 'tolerance' must be >= 0, got {value!r}")
    return t


def _in_box(x: np.ndarray, value, tol: float) -> np.ndarray:
    corners = _vector(value, (2, 3), "box", "[[xmin, ymin, zmin], [xmax, ymax, zmax]]")
    lo, hi = corners
    if np.any(lo > hi):
        raise SceneError(f"selector 'box' min corner {lo.tolist()} exceeds max {hi.tolist()}")
    return np.all((x >= lo - tol) & (x <= hi + tol), axis=1)


def _in_sphere(x: np.ndarray, value, tol: float) -> np.ndarray:
    fields = _fields(value, "sphere", ("center", "radius"))
    center = _vector(fields["center"], (3,), "sphere.center", "[x, y, z]")
    radius = _number(fields["radius"], "sphere.radius")
    if radius < 0:
        raise SceneError(f"selector 'sphere.radius' must be >= 0, got {radius!r}")
    return np.linalg.norm(x - center, axis=1) <= radius + tol


def _in_half_space(x: np.ndarray, value, tol: float) -> np.ndarray:
    fields = _fields(value, "plane", ("point", "normal"))
    point = _vector(fields["point"], (3,), "plane.point", "[x, y, z]")
    normal = _vector(fields["normal"], (3,), "plane.normal", "[nx, ny, nz]")
    length = np.linalg.norm(normal)
    if length == 0:
        raise SceneError("selector 'plane.normal' must be non-zero")
    # Unit normal so tol is a distance, whatever length the user typed.
    return (x - point) @ (normal / length) >= -tol


def _index_mask(n: int, value) -> np.ndarray:
    if isinstance(value, (str, bytes, dict)):
        raise SceneError(f"selector 'indices' must be a list of integers, got {value!r}")
    idx = np.asarray(value)
    if idx.size == 0:
        return np.zeros(n, dtype=bool)
    if idx.ndim != 1 or idx.dtype.kind not in "iu":
        raise SceneError(f"selector 'indices' must be a flat list of integers, got {value!r}")
    bad = idx[(idx < 0) | (idx >= n)]
    if bad.size:
        raise SceneError(
            f"selector 'indices' has {bad.size} values outside [0, {n}), e.g. {bad[:5].tolist()}"
        )
    mask = np.zeros(n, dtype=bool)
    mask[idx] = True
    return mask


def _fields(value, key: str, required: tuple[str, ...]) -> dict:
    if not isinstance(value, dict):
        raise SceneError(f"selector '{key}' must be a mapping with keys {list(required)}")
    for name in required:
        if name not in value:
            raise SceneError(f"selector '{key}' is missing key '{name}'")
    unknown = sorted(set(value) - set(required))
    if unknown:
        raise SceneError(f"selector '{key}' has unknown keys {unknown}")
    return value


def _vector(value, shape: tuple[int, ...], key: str, form: str) -> np.ndarray:
    try:
        v = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise SceneError(
            f"selector '{key}' must be numbers of the form {form}, got {value!r}"
        ) from None
    if v.shape != shape or not np.all(np.isfinite(v)):
        raise SceneError(
            f"selector '{key}' must be finite numbers of the form {form}, got {value!r}"
        )
    return v


def _number(value, key: str) -> float:
    if isinstance(value, bool):
        raise SceneError(f"selector '{key}' must be a number, got {value!r}")
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise SceneError(f"selector '{key}' must be a number, got {value!r}") from None
    if not np.isfinite(v):
        raise SceneError(f"selector '{key}' must be finite, got {value!r}")
    return v
