"""Structured generators (box, sheet, graded_block) and CSG composites: exact geometry."""
import time

import numpy as np
import pytest

from mdss_ros.errors import MeshError
from mdss_ros.mesh import box, composite, graded_block, sheet
from mdss_ros.mesh.generators import graded_axis, tensor_grid
from mdss_ros.mesh.surface import boundary_faces, triangle_areas
from mdss_ros.mesh.tetmesh import signed_volumes


def _edge_use_counts(faces):
    """Counts of each directed edge and each undirected edge of a triangle set."""
    directed = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    _, undirected = np.unique(np.sort(directed, axis=1), axis=0, return_counts=True)
    _, directed_counts = np.unique(directed, axis=0, return_counts=True)
    return undirected, directed_counts


def _assert_closed_outward(mesh, volume):
    faces = boundary_faces(mesh.tets)
    undirected, directed = _edge_use_counts(faces)
    assert np.all(undirected == 2), "every surface edge must be shared by exactly 2 triangles"
    assert np.all(directed == 1), "neighbouring triangles must traverse their edge oppositely"
    x = mesh.vertices[faces]
    cross = np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0])
    # Divergence theorem with F = x / 3: V = sum (c . n) A / 3 = sum c . cross / 6.
    div_volume = np.einsum("ij,ij->", x.mean(axis=1), cross) / 6.0
    assert div_volume > 0
    assert div_volume == pytest.approx(volume, rel=1e-12)
    return faces


def test_box_volume_bbox_and_orientation_exact():
    size, origin = np.array([0.3, 0.2, 0.1]), np.array([1.0, -2.0, 0.5])
    mesh = box(size=size, cell=0.05, origin=origin)
    vol = signed_volumes(mesh.vertices, mesh.tets)
    assert vol.min() > 0
    assert vol.sum() == pytest.approx(0.3 * 0.2 * 0.1, rel=1e-12)
    assert np.array_equal(mesh.vertices.min(axis=0), origin)
    assert np.array_equal(mesh.vertices.max(axis=0), origin + size)
    assert mesh.vertices.dtype == np.float64 and mesh.tets.dtype == np.int64
    assert mesh.vertices.flags.c_contiguous and mesh.tets.flags.c_contiguous


def test_box_cell_counts_are_rounded_and_cells_uniform():
    mesh = box(size=(1.0, 0.1, 0.02), cell=0.03)
    n = (33, 3, 1)  # round(1/0.03)=33, round(0.1/0.03)=3, max(1, round(0.67))=1
    assert mesh.n_verts == (n[0] + 1) * (n[1] + 1) * (n[2] + 1)
    assert mesh.n_tets == 6 * n[0] * n[1] * n[2]
    xs = np.unique(mesh.vertices[:, 0])
    assert np.allclose(np.diff(xs), 1.0 / 33, rtol=1e-12)


def test_box_vertex_numbering_is_x_fastest():
    mesh = box(size=(2.0, 3.0, 4.0), cell=1.0)
    nx1, ny1 = 3, 4
    assert np.array_equal(mesh.vertices[0], [0, 0, 0])
    assert np.array_equal(mesh.vertices[1], [1, 0, 0])
    assert np.array_equal(mesh.vertices[nx1], [0, 1, 0])
    assert np.array_equal(mesh.vertices[nx1 * ny1], [0, 0, 1])
    i, j, k = 2, 1, 3
    assert np.array_equal(mesh.vertices[i + nx1 * (j + ny1 * k)], [i, j, k])


def test_box_is_conforming_closed_and_outward():
    nx, ny, nz = 5, 3, 4
    mesh = box(size=(nx * 0.1, ny * 0.1, nz * 0.1), cell=0.1)
    faces = _assert_closed_outward(mesh, 0.5 * 0.3 * 0.4)
    # A non-conforming split would leave unmatched triangles inside the box.
    assert len(faces) == 2 * (2 * nx * ny + 2 * ny * nz + 2 * nx * nz)
    assert triangle_areas(mesh.vertices, faces).sum() == pytest.approx(
        2 * (0.5 * 0.3 + 0.3 * 0.4 + 0.5 * 0.4), rel=1e-12
    )
    # Every interior triangle is shared by exactly two tets (no T-junctions).
    local_faces = [[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]]
    all_faces = np.sort(mesh.tets[:, local_faces].reshape(-1, 3), axis=1)
    _, counts = np.unique(all_faces, axis=0, return_counts=True)
    assert set(np.unique(counts)) == {1, 2}


def test_kuhn_split_of_single_cube_is_six_positive_tets_filling_it():
    mesh = tensor_grid([0.0, 2.0], [0.0, 3.0], [0.0, 5.0])
    vol = signed_volumes(mesh.vertices, mesh.tets)
    assert mesh.n_tets == 6
    assert np.all(vol > 0)
    assert np.allclose(vol, 30.0 / 6.0)  # each Kuhn tet is 1/6 of the box
    assert np.all((mesh.tets == 0).any(axis=1) & (mesh.tets == 7).any(axis=1))


def test_box_speed():
    t0 = time.perf_counter()
    mesh = box(size=(1.0, 0.1, 0.1), cell=0.01)
    fast = time.perf_counter() - t0
    assert mesh.n_tets == 60_000
    assert fast < 0.5
    t0 = time.perf_counter()
    big = box(size=(4.0, 1.0, 1.0), cell=1.0 / 22)
    assert big.n_tets == 6 * 88 * 22 * 22  # 255552
    assert time.perf_counter() - t0 < 3.0


def test_box_rejects_bad_parameters():
    with pytest.raises(MeshError, match="size"):
        box(size=(1.0, -1.0, 1.0), cell=0.1)
    with pytest.raises(MeshError, match="cell"):
        box(size=(1.0, 1.0, 1.0), cell=0.0)
    with pytest.raises(MeshError, match="tets"):
        box(size=(1.0, 1.0, 1.0), cell=1e-4)


def test_sheet_layers_and_volume():
    mesh = sheet(size=(0.5, 0.3), thickness=0.004, cell=0.05, layers=2, origin=(0, 0, 1))
    zs = np.unique(mesh.vertices[:, 2])
    assert np.allclose(zs, [1.0, 1.002, 1.004], atol=1e-15)
    assert mesh.n_tets == 6 * 10 * 6 * 2
    vol = signed_volumes(mesh.vertices, mesh.tets)
    assert vol.min() > 0
    assert vol.sum() == pytest.approx(0.5 * 0.3 * 0.004, rel=1e-12)
    _assert_closed_outward(mesh, 0.5 * 0.3 * 0.004)
    with pytest.raises(MeshError, match="layers"):
        sheet(size=(1, 1), thickness=0.01, cell=0.1, layers=0)


def _assert_graded(nodes, lo, hi, h_fine, h_coarse, growth):
    h = np.diff(nodes)
    assert nodes[0] == lo and nodes[-1] == hi
    assert np.all(h > 0)
    assert h.max() <= h_coarse * (1 + 1e-12)
    assert h.min() > 0.5 * h_fine
    ratio = h[1:] / h[:-1]
    assert np.all(np.maximum(ratio, 1 / ratio) <= growth * (1 + 1e-9))
    # Unimodal: sizes shrink towards the fine zone, then grow away from it.
    step = np.sign(np.round(np.log(ratio), 9))
    assert not np.any((step[:-1] > 0) & (np.minimum.accumulate(step[::-1])[::-1][1:] < 0))


def test_graded_axis_properties():
    nodes = graded_axis(0.0, 1.0, focus=0.3, radius=0.05, h_fine=0.01, h_coarse=0.1, growth=1.3)
    _assert_graded(nodes, 0.0, 1.0, 0.01, 0.1, 1.3)
    h = np.diff(nodes)
    mid = 0.5 * (nodes[1:] + nodes[:-1])
    assert np.allclose(h[np.abs(mid - 0.3) < 0.05], 0.01, rtol=1e-9)
    assert np.count_nonzero(np.abs(mid - 0.3) < 0.05) == 10
    assert h.max() > 0.07  # it does reach the coarse regime


def test_graded_axis_random_parameters_keep_the_bounds():
    rng = np.random.default_rng(7)
    for _ in range(300):
        h_fine = 10 ** rng.uniform(-3, -1)
        h_coarse = h_fine * 10 ** rng.uniform(0, 1.5)
        growth = rng.uniform(1.05, 1.8)
        lo, length = rng.uniform(-1, 1), 10 ** rng.uniform(-1, 0.5)
        focus = lo + rng.uniform(-0.2, 1.2) * length
        radius = rng.uniform(0, 0.2) * length
        nodes = graded_axis(lo, lo + length, focus, radius, h_fine, h_coarse, growth)
        _assert_graded(nodes, lo, lo + length, h_fine, h_coarse, growth)


@pytest.mark.parametrize("focus", [0.0, 1.0, 0.995, 2.0, -1.0])
def test_graded_axis_focus_at_or_beyond_the_ends(focus):
    nodes = graded_axis(0.0, 1.0, focus=focus, radius=0.0, h_fine=0.01, h_coarse=0.1)
    _assert_graded(nodes, 0.0, 1.0, 0.01, 0.1, 1.3)
    h = np.diff(nodes)
    nearest = np.argmin(np.abs(0.5 * (nodes[1:] + nodes[:-1]) - np.clip(focus, 0, 1)))
    assert h[nearest] <= 0.0131


def test_graded_block_exact_volume_and_finer_near_focus():
    size, focus = (1.0, 0.8, 0.5), np.array([0.5, 0.4, 0.5])  # focus on the top face
    mesh = graded_block(size, cell_coarse=0.1, cell_fine=0.02, focus=focus, radius=0.06)
    vol = signed_volumes(mesh.vertices, mesh.tets)
    assert vol.min() > 0
    assert vol.sum() == pytest.approx(0.4, rel=1e-12)
    assert np.array_equal(mesh.vertices.min(axis=0), [0, 0, 0])
    assert np.array_equal(mesh.vertices.max(axis=0), size)
    x = mesh.vertices[mesh.tets]
    edge = np.linalg.norm(x[:, 1:] - x[:, :1], axis=2).max(axis=1)
    dist = np.linalg.norm(x.mean(axis=1) - focus, axis=1)
    assert edge[dist < 0.05].max() < 0.02 * np.sqrt(3) * 1.001
    assert edge[dist > 0.4].min() > 0.05
    assert mesh.n_tets < 0.1 * box(size, cell=0.02).n_tets
    _assert_closed_outward(mesh, 0.4)


def test_graded_block_rejects_fine_coarser_than_coarse():
    with pytest.raises(MeshError, match="cell_fine"):
        graded_block((1, 1, 1), cell_coarse=0.01, cell_fine=0.1, focus=(0, 0, 0), radius=0.1)


def test_composite_box_sphere_union(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    prims = [
        {"shape": "box", "size": [1.0, 1.0, 1.0]},
        {"shape": "sphere", "radius": 0.5, "position": [0.5, 0.0, 0.0]},
    ]
    mesh = composite(prims, edge_length=0.2, epsilon=5e-3)
    vol = signed_volumes(mesh.vertices, mesh.tets)
    assert vol.min() > 0
    exact = 1.0 + 0.5 * (4.0 / 3.0) * np.pi * 0.5**3  # half the ball sticks out
    assert vol.sum() == pytest.approx(exact, rel=0.03)
    _assert_closed_outward(mesh, vol.sum())
    assert list(tmp_path.iterdir()) == [], "fTetWild scratch files must not land in the cwd"


def test_composite_places_and_rotates_primitives(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    prim = {"shape": "box", "size": [0.4, 0.2, 0.1], "position": [1.0, 2.0, 3.0],
            "rotation_rpy": [0.0, 0.0, np.pi / 2]}
    mesh = composite([prim], edge_length=0.1, epsilon=5e-3)
    lo, hi = mesh.vertices.min(axis=0), mesh.vertices.max(axis=0)
    envelope = 5e-3 * np.linalg.norm([0.4, 0.2, 0.1])  # fTetWild's surface tolerance
    assert np.allclose(lo, [0.9, 1.8, 2.95], atol=envelope)
    assert np.allclose(hi, [1.1, 2.2, 3.05], atol=envelope)
    assert signed_volumes(mesh.vertices, mesh.tets).sum() == pytest.approx(0.008, rel=1e-3)


@pytest.mark.parametrize(
    "prims, match",
    [
        ([{"shape": "torus", "radius": 1.0}], "torus"),
        ([{"shape": "sphere"}], "radius"),
        ([{"shape": "cylinder", "radius": 0.1}], "height"),
        ([{"radius": 0.1}], "shape"),
        ([{"shape": "sphere", "radius": 0.1, "positon": [0, 0, 0]}], "positon"),
        ([{"shape": "ellipsoid", "radii": [1, 2]}], "radii"),
        ([], "non-empty"),
    ],
)
def test_composite_errors_name_the_problem(prims, match):
    with pytest.raises(MeshError, match=match):
        composite(prims, edge_length=0.1)
