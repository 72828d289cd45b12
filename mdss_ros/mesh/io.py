"""Read and write tet meshes; surface files are tetrahedralised on load."""

from __future__ import annotations

import os

import numpy as np

from mdss_ros.errors import MeshError
from mdss_ros.mesh.tetmesh import TetMesh, orient_tets, remove_unreferenced

VOLUME_EXTENSIONS = (".vtu", ".msh", ".vtk")
SURFACE_EXTENSIONS = (".obj", ".stl", ".ply", ".off")


def load_mesh(path: str | os.PathLike, edge_length: float | None = None, scale: float = 1.0) -> TetMesh:
    """Load a tet mesh, or tetrahedralise a closed surface file.

    Volume files (.vtu, .msh, .vtk) are read with meshio; all linear
    ``tetra`` blocks are concatenated, other cell types ignored. Tets are
    re-oriented to det(Dm) > 0 (file conventions differ) and vertices used by
    no tet (e.g. gmsh geometry points) are dropped, which renumbers the
    vertices only when such vertices exist. Surface files (.obj, .stl, .ply,
    .off) are read with trimesh and tetrahedralised with ``edge_length``.

    Args:
        path: file path; the extension selects the reader (case-insensitive).
        edge_length: target tet edge length for surface files, in metres of the
            scaled body; ignored for volume files. None uses fTetWild's default
            (bbox diagonal / 20).
        scale: factor from the file's units to metres (0.001 for a CAD file in
            millimetres), applied before meshing.
    Returns:
        TetMesh with (n_verts, 3) vertices and (n_tets, 4) positive tets.
    Raises:
        MeshError: missing file, unsupported extension, unreadable file, no
            tets, degenerate tets, or a non-watertight surface.
    """
    path = os.fspath(path)
    ext = os.path.splitext(path)[1].lower()
    if ext not in VOLUME_EXTENSIONS + SURFACE_EXTENSIONS:
        raise MeshError(
            f"{path}: unsupported mesh extension {ext!r}; "
            f"expected one of {VOLUME_EXTENSIONS + SURFACE_EXTENSIONS}"
        )
    if not os.path.isfile(path):
        raise MeshError(f"{path}: mesh file not found")
    if isinstance(scale, bool) or not isinstance(scale, (int, float)) or not (np.isfinite(scale) and scale > 0):
        raise MeshError(f"{path}: scale must be a positive number (0.001 for millimetres), got {scale!r}")
    if ext in VOLUME_EXTENSIONS:
        mesh = _load_volume(path)
        return mesh if scale == 1.0 else TetMesh(mesh.vertices * float(scale), mesh.tets)
    return _load_surface(path, edge_length, float(scale))


def save_mesh(path: str | os.PathLike, mesh: TetMesh) -> None:
    """Write a tet mesh as a single ``tetra`` block (.vtu, .vtk, or .msh as gmsh 4.1).

    Args:
        path: output file; the extension selects the format.
        mesh: TetMesh with (n_verts, 3) vertices and (n_tets, 4) tets.
    """
    import meshio

    path = os.fspath(path)
    ext = os.path.splitext(path)[1].lower()
    if ext not in VOLUME_EXTENSIONS:
        raise MeshError(
            f"{path}: cannot save a tet mesh as {ext!r}; "
            f"expected one of {VOLUME_EXTENSIONS}"
        )
    # meshio maps .msh to ANSYS first; gmsh 4.1 is what .msh means to users.
    file_format = "gmsh" if ext == ".msh" else None
    meshio.write(path, meshio.Mesh(mesh.vertices, [("tetra", mesh.tets)]), file_format=file_format)


def _load_volume(path: str) -> TetMesh:
    import meshio

    # Format readers are called directly: meshio.read() prints and calls
    # sys.exit(1) when its reader rejects a file (meshio 5.3.5).
    readers = {".vtu": meshio.vtu.read, ".msh": _read_msh, ".vtk": meshio.vtk.read}
    ext = os.path.splitext(path)[1].lower()
    try:
        data = readers[ext](path)
    except Exception as exc:
        detail = f"{type(exc).__name__}: {exc}" if str(exc) else type(exc).__name__
        raise MeshError(f"{path}: cannot read as {ext} mesh ({detail})") from None
    blocks = [np.asarray(c.data) for c in data.cells if c.type == "tetra"]
    if not blocks:
        found = sorted({c.type for c in data.cells})
        raise MeshError(f"{path}: no linear 'tetra' cells (found {found or 'no cells'})")
    vertices = np.asarray(data.points, dtype=np.float64)
    if vertices.ndim != 2 or vertices.shape[1] != 3:
        raise MeshError(f"{path}: points must be 3D, got shape {vertices.shape}")
    mesh = TetMesh(vertices, np.concatenate(blocks))
    try:
        mesh.validate()
    except MeshError as exc:
        raise MeshError(f"{path}: {exc}") from None
    return remove_unreferenced(TetMesh(mesh.vertices, orient_tets(mesh.vertices, mesh.tets)))


def _read_msh(path: str):
    """Gmsh .msh (any version meshio reads), falling back to ANSYS/Fluent .msh."""
    import meshio

    with open(path, "rb") as f:
        head = f.read(4096)
    if b"$MeshFormat" in head:
        return meshio.gmsh.read(path)
    return meshio.ansys.read(path)


def _load_surface(path: str, edge_length: float | None, scale: float = 1.0) -> TetMesh:
    import trimesh

    from mdss_ros.mesh.tetrahedralize import tetrahedralize

    try:
        surface = trimesh.load(path, force="mesh")
    except Exception as exc:
        detail = f"{type(exc).__name__}: {exc}" if str(exc) else type(exc).__name__
        raise MeshError(f"{path}: cannot read surface file ({detail})") from None
    if not isinstance(surface, trimesh.Trimesh) or len(surface.faces) == 0:
        raise MeshError(f"{path}: surface file contains no triangles")
    try:
        return tetrahedralize(np.asarray(surface.vertices) * scale, surface.faces, edge_length=edge_length)
    except MeshError as exc:
        raise MeshError(f"{path}: {exc}") from None
