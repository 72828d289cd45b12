"""Linear tetrahedral mesh container, orientation and validity checks.

Orientation convention used everywhere in mdss_ros: a tet (i0, i1, i2, i3) is
positively oriented when det(Dm) > 0 with Dm = [X1-X0, X2-X0, X3-X0] (columns),
i.e. its signed volume det(Dm)/6 is positive.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mdss_ros.errors import MeshError

# A tet is degenerate when |det(Dm)| <= _DEGENERATE_REL * (longest edge)^3.
# Relative to the tet's own size so the test is unit-independent; 1e-12 sits
# far above the ~1e-16 round-off of det and far below any usable element.
_DEGENERATE_REL = 1e-12
# How many offending element indices an error message lists.
_MAX_LISTED = 5


@dataclass(frozen=True, eq=False)
class TetMesh:
    """Linear tetrahedral mesh.

    Attributes:
        vertices: (n_verts, 3) float64, C-contiguous rest positions.
        tets: (n_tets, 4) int64, C-contiguous vertex indices per tet.

    eq=False: element-wise array comparison has no single truth value, so
    meshes compare (and hash) by identity.
    """

    vertices: np.ndarray
    tets: np.ndarray

    def __post_init__(self) -> None:
        # Frozen dataclass: normalise through object.__setattr__ so every
        # consumer (numba kernels included) can rely on dtype and layout.
        object.__setattr__(self, "vertices", _as_float_array(self.vertices))
        object.__setattr__(self, "tets", _as_index_array(self.tets, "tets"))

    @property
    def n_verts(self) -> int:
        return int(self.vertices.shape[0])

    @property
    def n_tets(self) -> int:
        return int(self.tets.shape[0])

    def validate(self, require_positive: bool = False) -> "TetMesh":
        """Raise MeshError naming the first problem found; return self if valid.

        Checks shape, emptiness, finite coordinates, index range, repeated
        vertices within a tet and zero-volume (degenerate) tets. Unreferenced
        vertices are allowed (see ``unreferenced_vertices``). With
        ``require_positive`` negatively oriented tets are an error too;
        otherwise they are accepted because ``orient_tets`` can fix them.
        """
        v, t = self.vertices, self.tets
        if v.ndim != 2 or v.shape[1] != 3:
            raise MeshError(f"vertices must have shape (n_verts, 3), got {v.shape}")
        if t.ndim != 2 or t.shape[1] != 4:
            raise MeshError(f"tets must have shape (n_tets, 4), got {t.shape}")
        if v.shape[0] == 0 or t.shape[0] == 0:
            raise MeshError(f"mesh is empty: {v.shape[0]} vertices, {t.shape[0]} tets")
        bad = np.flatnonzero(~np.isfinite(v).all(axis=1))
        if bad.size:
            raise MeshError(
                f"{bad.size} vertices have NaN/Inf coordinates, first indices {_first(bad)}"
            )
        bad = np.flatnonzero(((t < 0) | (t >= v.shape[0])).any(axis=1))
        if bad.size:
            raise MeshError(
                f"{bad.size} tets reference a vertex index outside [0, {v.shape[0]}), "
                f"first tet indices {_first(bad)}"
            )
        st = np.sort(t, axis=1)
        bad = np.flatnonzero((st[:, 1:] == st[:, :-1]).any(axis=1))
        if bad.size:
            raise MeshError(
                f"{bad.size} tets repeat a vertex, first tet indices {_first(bad)}"
            )
        det = 6.0 * signed_volumes(v, t)
        bad = np.flatnonzero(np.abs(det) <= _DEGENERATE_REL * _max_edge(v, t) ** 3)
        if bad.size:
            raise MeshError(
                f"{bad.size} degenerate (zero-volume) tets, first tet indices {_first(bad)}"
            )
        if require_positive:
            bad = np.flatnonzero(det < 0)
            if bad.size:
                raise MeshError(
                    f"{bad.size} negatively oriented (inverted) tets, "
                    f"first tet indices {_first(bad)}"
                )
        return self


def signed_volumes(vertices: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """Signed tet volumes det([X1-X0, X2-X0, X3-X0]) / 6.

    Args:
        vertices: (n_verts, 3) float.
        tets: (n_tets, 4) int.
    Returns:
        (n_tets,) float64, positive for positively oriented tets.
    """
    x0 = vertices[tets[:, 0]]
    a = vertices[tets[:, 1]] - x0
    b = vertices[tets[:, 2]] - x0
    c = vertices[tets[:, 3]] - x0
    # Triple product instead of np.linalg.det: no (n,3,3) stack, ~5x faster.
    return np.einsum("ij,ij->i", a, np.cross(b, c)) / 6.0


def orient_tets(vertices: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """Return a copy of tets with negatively oriented tets flipped.

    Swapping the last two indices negates det(Dm), so afterwards every
    non-degenerate tet has det(Dm) > 0. Zero-volume tets cannot be oriented
    and are left as they are; ``TetMesh.validate`` reports them.

    Args:
        vertices: (n_verts, 3) float.
        tets: (n_tets, 4) int.
    Returns:
        (n_tets, 4) int64, same tets in the same order.
    """
    out = np.array(tets, dtype=np.int64, order="C", copy=True)
    neg = signed_volumes(vertices, out) < 0
    out[neg] = out[neg][:, [0, 1, 3, 2]]
    return out


def unreferenced_vertices(mesh: TetMesh) -> np.ndarray:
    """Indices of vertices used by no tet.

    Returns:
        (k,) int64 sorted indices into mesh.vertices.
    """
    used = np.zeros(mesh.n_verts, dtype=bool)
    used[mesh.tets.ravel()] = True
    return np.flatnonzero(~used).astype(np.int64)


def remove_unreferenced(mesh: TetMesh) -> TetMesh:
    """Drop vertices used by no tet and renumber the tets.

    Surviving vertices keep their relative order, so a mesh without
    unreferenced vertices comes back with identical arrays.

    Returns:
        TetMesh with (n_used, 3) vertices and (n_tets, 4) renumbered tets.
    """
    used, inverse = np.unique(mesh.tets, return_inverse=True)
    if used.size == mesh.n_verts:
        return mesh
    return TetMesh(mesh.vertices[used], inverse.reshape(mesh.tets.shape))


def _as_float_array(values) -> np.ndarray:
    try:
        return np.ascontiguousarray(values, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise MeshError(f"vertices are not a numeric array: {exc}") from exc


def _as_index_array(values, name: str) -> np.ndarray:
    arr = np.asarray(values)
    if arr.dtype.kind == "f":
        # A silent float->int cast would truncate 2.9 to 2 and build a wrong mesh.
        if not np.all(np.isfinite(arr)) or np.any(arr != np.round(arr)):
            raise MeshError(f"{name} contain non-integer indices")
    elif arr.size and arr.dtype.kind not in "iu":
        raise MeshError(f"{name} must be integer indices, got dtype {arr.dtype}")
    return np.ascontiguousarray(arr, dtype=np.int64)


def _max_edge(vertices: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """(n_tets,) longest edge length per tet."""
    x = vertices[tets]  # (n_tets, 4, 3)
    i, j = np.triu_indices(4, k=1)
    return np.linalg.norm(x[:, i] - x[:, j], axis=2).max(axis=1)


def _first(indices: np.ndarray) -> list[int]:
    return [int(i) for i in indices[:_MAX_LISTED]]
