"""Boundary surface extraction: outward winding, closedness, determinism, normals."""
import numpy as np
import pytest

from mdss_ros.mesh import Surface, box, boundary_faces, extract_surface
from mdss_ros.mesh.surface import surface_vertices, triangle_areas, vertex_normals
from mdss_ros.mesh.tetmesh import orient_tets, signed_volumes


def _random_positive_tet(rng):
    x = rng.normal(size=(4, 3))
    tet = orient_tets(x, np.array([[0, 1, 2, 3]]))
    return x, tet


def test_single_tet_faces_point_away_from_the_opposite_vertex():
    rng = np.random.default_rng(3)
    for _ in range(20):
        x, tet = _random_positive_tet(rng)
        faces = boundary_faces(tet)
        assert faces.shape == (4, 3)
        for f in faces:
            opposite = np.setdiff1d(tet[0], f)[0]
            n = np.cross(x[f[1]] - x[f[0]], x[f[2]] - x[f[0]])
            assert n @ (x[f[0]] - x[opposite]) > 0


def test_documented_local_face_table_is_outward():
    # For tet (0,1,2,3) with det(Dm) > 0 the outward faces are (1,2,3), (0,3,2), (0,1,3), (0,2,1).
    x = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    assert signed_volumes(x, np.array([[0, 1, 2, 3]]))[0] > 0
    centroid = x.mean(axis=0)
    for f in [(1, 2, 3), (0, 3, 2), (0, 1, 3), (0, 2, 1)]:
        n = np.cross(x[f[1]] - x[f[0]], x[f[2]] - x[f[0]])
        assert n @ (x[list(f)].mean(axis=0) - centroid) > 0


def test_box_surface_closed_outward_area_and_volume():
    lx, ly, lz = 0.6, 0.4, 0.2
    mesh = box(size=(lx, ly, lz), cell=0.1, origin=(-1.0, 2.0, 0.5))
    faces = boundary_faces(mesh.tets)
    nx, ny, nz = 6, 4, 2
    assert len(faces) == 2 * (2 * nx * ny + 2 * ny * nz + 2 * nx * nz)
    directed = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    _, und = np.unique(np.sort(directed, axis=1), axis=0, return_counts=True)
    _, dir_counts = np.unique(directed, axis=0, return_counts=True)
    assert np.all(und == 2) and np.all(dir_counts == 1)
    area = triangle_areas(mesh.vertices, faces)
    assert area.sum() == pytest.approx(2 * (lx * ly + ly * lz + lx * lz), rel=1e-12)
    x = mesh.vertices[faces]
    n = np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0])
    unit = n / np.linalg.norm(n, axis=1, keepdims=True)
    # Divergence theorem with F = x/3: V = sum (centroid . n_hat) area / 3 (origin not at 0).
    volume = np.sum(np.einsum("ij,ij->i", x.mean(axis=1), unit) * area) / 3.0
    assert volume == pytest.approx(lx * ly * lz, rel=1e-12)
    assert volume > 0


def test_boundary_faces_order_is_sorted_and_independent_of_tet_order():
    mesh = box(size=(0.3, 0.2, 0.2), cell=0.1)
    faces = boundary_faces(mesh.tets)
    keys = np.sort(faces, axis=1)
    assert np.array_equal(keys, keys[np.lexsort((keys[:, 2], keys[:, 1], keys[:, 0]))])
    perm = np.random.default_rng(0).permutation(mesh.n_tets)
    assert np.array_equal(boundary_faces(mesh.tets[perm]), faces)
    assert faces.dtype == np.int64


def test_extract_surface_local_numbering():
    mesh = box(size=(0.4, 0.3, 0.2), cell=0.1)
    surf = extract_surface(mesh.tets)
    assert isinstance(surf, Surface)
    interior = (4 - 1) * (3 - 1) * (2 - 1)
    assert surf.vertex_ids.size == mesh.n_verts - interior
    assert np.array_equal(surf.vertex_ids, np.unique(surf.vertex_ids))
    assert np.array_equal(surf.vertex_ids, surface_vertices(boundary_faces(mesh.tets)))
    assert surf.triangles.min() == 0 and surf.triangles.max() == surf.vertex_ids.size - 1
    assert np.array_equal(surf.faces, boundary_faces(mesh.tets))
    assert surf.vertex_ids.dtype == np.int64 and surf.triangles.dtype == np.int64


def test_vertex_normals_unit_outward_and_exact_on_flat_faces():
    mesh = box(size=(1.0, 1.0, 1.0), cell=0.25)
    surf = extract_surface(mesh.tets)
    pos = mesh.vertices[surf.vertex_ids]
    normals = vertex_normals(pos, surf.triangles)
    assert normals.shape == pos.shape
    assert np.allclose(np.linalg.norm(normals, axis=1), 1.0)
    assert np.all(np.einsum("ij,ij->i", normals, pos - 0.5) > 0)
    # A vertex in the middle of the top face only touches top triangles.
    top_centre = np.flatnonzero(np.all(np.isclose(pos, [0.5, 0.5, 1.0]), axis=1))[0]
    assert np.allclose(normals[top_centre], [0.0, 0.0, 1.0], atol=1e-15)


def test_vertex_normals_area_weighting_and_isolated_vertices():
    # Two triangles sharing vertex 0: normals +z (area 2) and +x (area 0.5), vertex 5 unused.
    pos = np.array([[0, 0, 0], [2, 0, 0], [0, 2, 0], [0, 1, 0], [0, 0, 1], [9, 9, 9]], float)
    tris = np.array([[0, 1, 2], [0, 3, 4]])
    assert np.allclose(triangle_areas(pos, tris), [2.0, 0.5])
    n = vertex_normals(pos, tris)
    assert np.allclose(n[0], np.array([0.5, 0.0, 2.0]) / np.hypot(0.5, 2.0))
    assert np.array_equal(n[5], [0.0, 0.0, 0.0])
