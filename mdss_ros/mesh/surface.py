"""Boundary surface of a tet mesh and per-triangle / per-vertex geometry."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# Outward faces of a positively oriented tet (0, 1, 2, 3): face k is opposite
# vertex k and wound counter-clockwise seen from outside, i.e. its right-hand
# normal points away from vertex k.
_TET_FACES = np.array([[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]], dtype=np.int64)


def boundary_faces(tets: np.ndarray) -> np.ndarray:
    """Triangles belonging to exactly one tet, wound outward.

    Outward winding assumes positively oriented tets (see ``orient_tets``).
    Order is deterministic: ascending lexicographic order of each face's
    sorted vertex triple. Faces shared by more than two tets (non-manifold
    input) are interior by this definition and are not returned.

    Args:
        tets: (n_tets, 4) int vertex indices.
    Returns:
        (n_tris, 3) int64 vertex indices into the mesh vertices.
    """
    tets = np.asarray(tets, dtype=np.int64)
    faces = tets[:, _TET_FACES].reshape(-1, 3)  # (4 n_tets, 3), tet-major
    keys = np.sort(faces, axis=1)
    # lexsort + run lengths instead of np.unique(axis=0): same result, but no
    # structured-dtype view and we keep the index of each face's first copy.
    order = np.lexsort((keys[:, 2], keys[:, 1], keys[:, 0]))
    sorted_keys = keys[order]
    starts = np.flatnonzero(
        np.concatenate([[True], (sorted_keys[1:] != sorted_keys[:-1]).any(axis=1)])
    )
    counts = np.diff(np.append(starts, len(order)))
    return faces[order[starts[counts == 1]]]


def surface_vertices(faces: np.ndarray) -> np.ndarray:
    """Sorted unique vertex indices used by the faces.

    Args:
        faces: (n_tris, 3) int.
    Returns:
        (S,) int64 ascending.
    """
    return np.unique(np.asarray(faces, dtype=np.int64))


@dataclass(frozen=True, eq=False)
class Surface:
    """Boundary surface with local vertex numbering.

    Attributes:
        vertex_ids: (S,) int64 ascending indices into the mesh vertices.
        triangles: (n_tris, 3) int64 indices into vertex_ids, wound outward,
            so surface positions are x[vertex_ids] and triangles index them.
    """

    vertex_ids: np.ndarray
    triangles: np.ndarray

    @property
    def faces(self) -> np.ndarray:
        """(n_tris, 3) int64 triangles in global (mesh) vertex numbering."""
        return self.vertex_ids[self.triangles]


def extract_surface(tets: np.ndarray) -> Surface:
    """Outward boundary surface of a positively oriented tet mesh.

    Args:
        tets: (n_tets, 4) int vertex indices.
    Returns:
        Surface with vertex_ids (S,) and triangles (n_tris, 3) local indices.
    """
    faces = boundary_faces(tets)
    vertex_ids = surface_vertices(faces)
    triangles = np.searchsorted(vertex_ids, faces).astype(np.int64)
    return Surface(vertex_ids, triangles)


def triangle_areas(positions: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Triangle areas.

    Args:
        positions: (S, 3) float vertex positions.
        triangles: (n_tris, 3) int indices into positions.
    Returns:
        (n_tris,) float64.
    """
    return 0.5 * np.linalg.norm(_doubled_area_normals(positions, triangles), axis=1)


def vertex_normals(positions: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals (zero for vertices in no triangle).

    Args:
        positions: (S, 3) float vertex positions.
        triangles: (n_tris, 3) int indices into positions, wound outward.
    Returns:
        (S, 3) float64.
    """
    positions = np.asarray(positions, dtype=np.float64)
    triangles = np.asarray(triangles, dtype=np.int64)
    # The unnormalised cross product has length 2*area, so summing it over the
    # incident triangles is already the area weighting.
    n = _doubled_area_normals(positions, triangles)
    s = positions.shape[0]
    idx = triangles.ravel()
    acc = np.stack(
        [np.bincount(idx, weights=np.repeat(n[:, d], 3), minlength=s) for d in range(3)],
        axis=1,
    )
    length = np.linalg.norm(acc, axis=1, keepdims=True)
    return np.divide(acc, length, out=np.zeros_like(acc), where=length > 0)


def _doubled_area_normals(positions: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """(n_tris, 3) cross products (x1-x0) x (x2-x0); length is twice the area."""
    p = np.asarray(positions, dtype=np.float64)
    t = np.asarray(triangles, dtype=np.int64)
    x0 = p[t[:, 0]]
    return np.cross(p[t[:, 1]] - x0, p[t[:, 2]] - x0)
