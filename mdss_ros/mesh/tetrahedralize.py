"""Closed triangle surface -> tet mesh, via fTetWild (pytetwild 0.2.3).

pytetwild quirks handled here:
- its tets come out negatively oriented (det(Dm) < 0): they are re-oriented
  and the result is validated so every tet has det(Dm) > 0;
- it writes a scratch file ``__tracked_surface.stl`` into the current working
  directory: the call runs inside a temporary directory instead;
- it meshes the generalised-winding-number interior of *any* input, so an open
  surface still yields tets: watertightness is checked before calling it;
- its output is not reproducible run to run (even with num_threads=1).
"""

from __future__ import annotations

import contextlib
import os
import tempfile
import threading
import warnings

import numpy as np

from mdss_ros.errors import MeshError
from mdss_ros.mesh.tetmesh import TetMesh, orient_tets, remove_unreferenced

# chdir is process-wide: serialise our own calls so two threads meshing at
# once cannot restore each other's working directory.
_CWD_LOCK = threading.Lock()


def tetrahedralize(
    surface_vertices: np.ndarray,
    surface_faces: np.ndarray,
    edge_length: float | None = None,
    epsilon: float = 1e-3,
    optimize: bool = True,
) -> TetMesh:
    """Tetrahedralise the solid bounded by a closed, consistently wound surface.

    Args:
        surface_vertices: (k, 3) float surface vertex positions.
        surface_faces: (t, 3) int triangle vertex indices.
        edge_length: target tet edge length (absolute). None uses fTetWild's
            default of 1/20 of the bbox diagonal. It is passed to fTetWild as
            the factor edge_length / bbox_diagonal; values above the diagonal
            are capped at 1 (one element across).
        epsilon: fTetWild envelope: max deviation of the output surface from
            the input, relative to the bbox diagonal.
        optimize: let fTetWild improve element quality (slower).
    Returns:
        TetMesh, every tet positively oriented, no unreferenced vertices.
    Raises:
        MeshError: bad arrays, surface not watertight / not consistently
            wound, or fTetWild producing no or degenerate tets.
    """
    import pytetwild

    vertices, faces = _checked_surface(surface_vertices, surface_faces)
    diagonal = float(np.linalg.norm(vertices.max(axis=0) - vertices.min(axis=0)))
    if edge_length is None:
        factor = 0.05
    else:
        if not np.isfinite(edge_length) or edge_length <= 0:
            raise MeshError(f"edge_length must be finite and > 0, got {edge_length!r}")
        factor = min(float(edge_length) / diagonal, 1.0)
    if not np.isfinite(epsilon) or epsilon <= 0:
        raise MeshError(f"epsilon must be finite and > 0, got {epsilon!r}")

    with _scratch_cwd():
        try:
            tet_vertices, tets = pytetwild.tetrahedralize(
                vertices,
                faces.astype(np.int32),
                edge_length_fac=factor,
                epsilon=float(epsilon),
                optimize=optimize,
                quiet=True,
            )
        except RuntimeError as exc:  # C++ exceptions surface as RuntimeError
            raise MeshError(f"fTetWild failed: {exc}") from exc
    tets = np.asarray(tets, dtype=np.int64).reshape(-1, 4)
    if tets.shape[0] == 0:
        raise MeshError("fTetWild produced no tets (surface encloses no volume?)")
    mesh = TetMesh(tet_vertices, orient_tets(tet_vertices, tets))
    return remove_unreferenced(mesh).validate(require_positive=True)


@contextlib.contextmanager
def _scratch_cwd():
    """Run the body inside a fresh temporary directory, then restore the cwd.

    fTetWild drops its scratch STL into the cwd; this keeps users' directories
    (and read-only cwds) out of it and deletes the file afterwards.
    """
    with _CWD_LOCK, tempfile.TemporaryDirectory(prefix="mdss_tetwild_") as scratch:
        previous = os.getcwd()
        os.chdir(scratch)
        try:
            yield scratch
        finally:
            os.chdir(previous)


def _checked_surface(vertices, faces) -> tuple[np.ndarray, np.ndarray]:
    """Validate arrays and topology; return (k, 3) float64, (t, 3) int64.

    Duplicate vertices are merged first (STL stores each triangle's corners
    separately), then the surface must be a closed 2-manifold with
    consistent winding. Inside-out surfaces are flipped rather than rejected.
    """
    import trimesh

    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces)
    if v.ndim != 2 or v.shape[1] != 3 or v.shape[0] < 4:
        raise MeshError(f"surface vertices must have shape (k >= 4, 3), got {v.shape}")
    if f.ndim != 2 or f.shape[1] != 3 or f.shape[0] < 4:
        raise MeshError(f"surface faces must have shape (t >= 4, 3) triangles, got {f.shape}")
    if f.dtype.kind not in "iu":
        raise MeshError(f"surface faces must be integer indices, got dtype {f.dtype}")
    if not np.all(np.isfinite(v)):
        raise MeshError("surface vertices contain NaN/Inf coordinates")
    if f.min() < 0 or f.max() >= v.shape[0]:
        raise MeshError(f"surface faces reference vertex indices outside [0, {v.shape[0]})")

    mesh = trimesh.Trimesh(v, f, process=True, validate=False)
    changes = []
    n0 = len(mesh.faces)
    mesh.update_faces(mesh.nondegenerate_faces())
    mesh.update_faces(mesh.unique_faces())
    if len(mesh.faces) < n0:
        changes.append(f"removed {n0 - len(mesh.faces)} degenerate or duplicate triangles")
    # Exported CAD and scan meshes are often not quite closed. What a library repairs
    # without changing the shape (holes of 3 or 4 edges, inconsistent winding) is repaired
    # and said; anything else is rejected with the defect and where it is.
    holes = boundary_loops(mesh.vertices, mesh.faces)
    if holes:
        trimesh.repair.fill_holes(mesh)
        left = boundary_loops(mesh.vertices, mesh.faces)
        if len(left) < len(holes):
            changes.append(f"filled {len(holes) - len(left)} small holes (3 or 4 edges)")
        if left:
            raise MeshError(f"surface is not watertight: {len(left)} hole(s) too large to fill without changing "
                            f"the shape; largest: {hole_summary(left)}. Close them in a mesh tool (e.g. MeshLab, "
                            f"Blender's 3D-print toolbox), or give a tet mesh (.vtu, .msh)")
    over = non_manifold_edges(mesh.faces)
    if len(over):
        raise MeshError(f"surface is not a 2-manifold: {len(over)} edges are shared by more than two triangles "
                        f"(the first near {edge_place(mesh.vertices, over)}); separate the touching parts or give "
                        f"a tet mesh")
    if not mesh.is_winding_consistent:
        trimesh.repair.fix_winding(mesh)
        if not mesh.is_winding_consistent:
            raise MeshError("surface is not consistently wound and could not be re-wound")
        changes.append("re-wound the triangles that faced inward")
    if changes:
        warnings.warn(f"surface repaired: {'; '.join(changes)}", MeshRepairWarning, stacklevel=3)
    if mesh.volume < 0:
        mesh.invert()
    if mesh.volume <= 0:
        raise MeshError("surface encloses zero volume")
    return np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces, dtype=np.int64)


class MeshRepairWarning(UserWarning):
    """A surface file was repaired on load; the message says exactly what changed."""


def _edges(faces):
    """(unique undirected edges (e, 2), their triangle counts (e,)) of triangles (t, 3)."""
    f = np.asarray(faces, dtype=np.int64)
    edges = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    return np.unique(edges, axis=0, return_counts=True)


def boundary_loops(vertices, faces):
    """The holes of a triangle surface, largest first: [(edge count, centre (3,), size)],
    from the edges used by one triangle only, grouped into connected loops; size is the
    largest distance between two of a loop's vertices."""
    import scipy.sparse as sp
    from scipy.sparse import csgraph

    edges, counts = _edges(faces)
    open_edges = edges[counts == 1]
    if not len(open_edges):
        return []
    ids, local = np.unique(open_edges, return_inverse=True)
    local = local.reshape(-1, 2)
    g = sp.coo_matrix((np.ones(len(local)), (local[:, 0], local[:, 1])), shape=(len(ids), len(ids)))
    n, label = csgraph.connected_components(g, directed=False)
    x = np.asarray(vertices, dtype=np.float64)[ids]
    out = []
    for k in range(n):                              # one entry per hole, not per vertex
        pts = x[label == k]
        size = float(np.linalg.norm(pts.max(0) - pts.min(0)))
        out.append((int(np.count_nonzero(label[local[:, 0]] == k)), pts.mean(0), size))
    return sorted(out, key=lambda h: (-h[0], -h[2]))


def hole_summary(holes, scale=1.0, most=3):
    """'24 edges around [x, y, z] (0.031 across), ...' for the largest holes (boundary_loops)."""
    return ", ".join(f"{n} edges around {np.round(c * scale, 4).tolist()} ({size * scale:.3g} across)"
                     for n, c, size in holes[:most])


def edge_place(vertices, edges, scale=1.0):
    """Where the first of edges (k, 2) is: its midpoint [x, y, z], rounded."""
    return np.round(np.asarray(vertices)[edges[0]].mean(0) * scale, 4).tolist()


def non_manifold_edges(faces):
    """(k, 2) edges shared by more than two triangles."""
    edges, counts = _edges(faces)
    return edges[counts > 2]


def count_unpaired_edges(faces: np.ndarray) -> int:
    """Number of undirected edges not shared by exactly two triangles.

    Args:
        faces: (n_tris, 3) int triangle vertex indices.
    Returns:
        0 for a closed 2-manifold surface.
    """
    _, counts = _edges(faces)
    return int(np.count_nonzero(counts != 2))
