"""Element quality statistics of a tet mesh (all vectorised over tets)."""

from __future__ import annotations

import numpy as np

from mdss_ros.errors import MeshError
from mdss_ros.mesh.tetmesh import TetMesh, signed_volumes

# A tet whose smallest dihedral angle is below this is a sliver: its
# stiffness matrix is ill-conditioned even when its volume looks fine.
SLIVER_DIHEDRAL_DEG = 5.0

# Face k of _FACES is opposite vertex k (same winding as surface._TET_FACES).
_FACES = np.array([[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]], dtype=np.int64)
# Tet edge (i, j) is shared by the faces opposite the two other vertices.
_EDGES = np.array([[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]], dtype=np.int64)
_EDGE_FACE_PAIRS = np.array([[2, 3], [1, 3], [1, 2], [0, 3], [0, 2], [0, 1]], dtype=np.int64)


def quality_report(mesh: TetMesh, sliver_deg: float = SLIVER_DIHEDRAL_DEG) -> dict:
    """Summary statistics of element quality.

    Keys:
        n_verts, n_tets: counts.
        volume: sum of signed tet volumes.
        min_dihedral_deg, max_dihedral_deg: extremes over all 6 n_tets
            dihedral angles (degrees).
        n_inverted: tets with signed volume <= 0.
        n_slivers: tets whose min dihedral angle is below ``sliver_deg``
            (a flat tet is both inverted and a sliver).
        radius_ratio_min, radius_ratio_median: 3 r_in / R_circ, 1 for the
            regular tet, 0 for a flat one.
        edge_min, edge_mean, edge_max: over all 6 n_tets tet edges (shared
            edges counted once per tet).
    """
    if mesh.n_tets == 0:
        raise MeshError("quality_report: mesh has no tets")
    x = mesh.vertices[mesh.tets]  # (n_tets, 4, 3)
    volumes = signed_volumes(mesh.vertices, mesh.tets)
    dihedral = dihedral_angles(mesh.vertices, mesh.tets)
    ratio = radius_ratios(mesh.vertices, mesh.tets)
    edges = np.linalg.norm(x[:, _EDGES[:, 1]] - x[:, _EDGES[:, 0]], axis=2)
    min_dihedral = dihedral.min(axis=1)
    return {
        "n_verts": mesh.n_verts,
        "n_tets": mesh.n_tets,
        "volume": float(volumes.sum()),
        "min_dihedral_deg": float(min_dihedral.min()),
        "max_dihedral_deg": float(dihedral.max()),
        "n_inverted": int(np.count_nonzero(volumes <= 0)),
        "n_slivers": int(np.count_nonzero(min_dihedral < sliver_deg)),
        "sliver_deg": float(sliver_deg),
        "radius_ratio_min": float(ratio.min()),
        "radius_ratio_median": float(np.median(ratio)),
        "edge_min": float(edges.min()),
        "edge_mean": float(edges.mean()),
        "edge_max": float(edges.max()),
    }


def format_quality(report: dict) -> str:
    """One-line human summary of a ``quality_report``."""
    r = report
    return (
        f"{r['n_verts']} verts, {r['n_tets']} tets, volume {r['volume']:.6g}, "
        f"dihedral [{r['min_dihedral_deg']:.2f}, {r['max_dihedral_deg']:.2f}] deg, "
        f"{r['n_inverted']} inverted, {r['n_slivers']} slivers (<{r['sliver_deg']:g} deg), "
        f"radius ratio min {r['radius_ratio_min']:.3f} median {r['radius_ratio_median']:.3f}, "
        f"edge [{r['edge_min']:.4g}, {r['edge_mean']:.4g}, {r['edge_max']:.4g}] (min/mean/max)"
    )


def dihedral_angles(vertices: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """Interior dihedral angles at the 6 edges (01, 02, 03, 12, 13, 23).

    The angle at an edge is pi minus the angle between the outward normals of
    its two faces. Flipping a tet flips all its normals, so the result does
    not depend on orientation. Zero-area faces give 0 (worst quality).

    Args:
        vertices: (n_verts, 3) float.
        tets: (n_tets, 4) int.
    Returns:
        (n_tets, 6) float64 degrees in [0, 180].
    """
    x = vertices[tets]  # (n_tets, 4, 3)
    f = x[:, _FACES]  # (n_tets, 4, 3 corners, 3)
    normals = np.cross(f[:, :, 1] - f[:, :, 0], f[:, :, 2] - f[:, :, 0])
    length = np.linalg.norm(normals, axis=2, keepdims=True)
    unit = np.divide(normals, length, out=np.zeros_like(normals), where=length > 0)
    a = unit[:, _EDGE_FACE_PAIRS[:, 0]]
    b = unit[:, _EDGE_FACE_PAIRS[:, 1]]
    cos = -np.einsum("tei,tei->te", a, b)
    degenerate = (length[:, _EDGE_FACE_PAIRS[:, 0], 0] == 0) | (
        length[:, _EDGE_FACE_PAIRS[:, 1], 0] == 0
    )
    cos[degenerate] = 1.0
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def radius_ratios(vertices: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """Normalised radius ratio 3 r_in / R_circ per tet (1 regular, 0 flat).

    r_in = 3 |V| / (total face area); R_circ = |a^2 (b x c) + b^2 (c x a)
    + c^2 (a x b)| / (12 |V|) with a, b, c the edges from vertex 0.

    Args:
        vertices: (n_verts, 3) float.
        tets: (n_tets, 4) int.
    Returns:
        (n_tets,) float64 in [0, 1].
    """
    x = vertices[tets]
    a, b, c = (x[:, k] - x[:, 0] for k in (1, 2, 3))
    bc, ca, ab = np.cross(b, c), np.cross(c, a), np.cross(a, b)
    six_v = np.abs(np.einsum("ij,ij->i", a, bc))
    f = x[:, _FACES]
    area = 0.5 * np.linalg.norm(
        np.cross(f[:, :, 1] - f[:, :, 0], f[:, :, 2] - f[:, :, 0]), axis=2
    ).sum(axis=1)
    circ_num = np.linalg.norm(
        _norm2(a)[:, None] * bc + _norm2(b)[:, None] * ca + _norm2(c)[:, None] * ab, axis=1
    )
    # r = 6V / (2A), R = circ_num / (2 * 6V)  =>  3 r / R = 3 (6V)^2 / (A circ_num)
    denom = area * circ_num
    return np.divide(3.0 * six_v**2, denom, out=np.zeros_like(six_v), where=denom > 0)


def _norm2(v: np.ndarray) -> np.ndarray:
    """(n,) squared lengths of (n, 3) vectors."""
    return np.einsum("ij,ij->i", v, v)
