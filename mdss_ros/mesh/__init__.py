"""Tet mesh pipeline: generation, import, surface extraction, selection, quality.

Heavy third-party libraries (trimesh, pytetwild, meshio) are imported inside
the functions that need them, so importing this package stays cheap for code
that only builds structured meshes.
"""

from mdss_ros.mesh.generators import box, composite, graded_block, sheet
from mdss_ros.mesh.io import load_mesh, save_mesh
from mdss_ros.mesh.quality import quality_report
from mdss_ros.mesh.selectors import select_vertices
from mdss_ros.mesh.surface import Surface, boundary_faces, extract_surface
from mdss_ros.mesh.tetmesh import TetMesh
from mdss_ros.mesh.tetrahedralize import tetrahedralize

__all__ = [
    "TetMesh",
    "box",
    "sheet",
    "graded_block",
    "composite",
    "tetrahedralize",
    "load_mesh",
    "save_mesh",
    "extract_surface",
    "Surface",
    "boundary_faces",
    "select_vertices",
    "quality_report",
]
