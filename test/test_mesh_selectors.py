"""Vertex selectors on a structured grid: counts, tolerance, errors naming the key."""
import numpy as np
import pytest

from mdss_ros.errors import SceneError
from mdss_ros.mesh import box, extract_surface, select_vertices


@pytest.fixture(scope="module")
def grid():
    # 11 x 11 x 11 nodes at multiples of 0.1; linspace makes some of them
    # inexact (0.30000000000000004), which the default tolerance must absorb.
    return box(size=(1.0, 1.0, 1.0), cell=0.1)


def test_box_selector_counts(grid):
    x = grid.vertices
    face = select_vertices(x, {"box": [[-1, -1, -1], [0, 2, 2]]})
    assert face.size == 121 and np.all(x[face, 0] == 0)
    slab = select_vertices(x, {"box": [[0.3, -1, -1], [0.5, 2, 2]]})
    assert slab.size == 3 * 121
    assert select_vertices(x, {"box": [[0, 0, 0], [1, 1, 1]]}).size == grid.n_verts
    assert select_vertices(x, {"box": [[2, 2, 2], [3, 3, 3]]}).size == 0


def test_sphere_selector_matches_brute_force(grid):
    x = grid.vertices
    ids = select_vertices(x, {"sphere": {"center": [0.5, 0.5, 0.5], "radius": 0.1}})
    assert ids.size == 7  # centre and its 6 axis neighbours at exactly 0.1
    ids = select_vertices(x, {"sphere": {"center": [0.5, 0.5, 0.5], "radius": 0.25}})
    expected = np.flatnonzero(np.linalg.norm(x - 0.5, axis=1) <= 0.25 + 1e-9)
    assert np.array_equal(ids, expected)
    # Integer offsets v with |v|^2 <= 6.25: |v|^2 = 0, 1, 2, 3, 4, 5, 6 -> 1+6+12+8+6+24+24.
    assert ids.size == 81


def test_plane_selector_is_closed_half_space_and_normal_length_free(grid):
    x = grid.vertices
    ids = select_vertices(x, {"plane": {"point": [0.3, 0, 0], "normal": [1, 0, 0]}})
    assert ids.size == 8 * 121  # x in {0.3, ..., 1.0}, including the plane itself
    same = select_vertices(x, {"plane": {"point": [0.3, 0, 0], "normal": [5, 0, 0]}})
    assert np.array_equal(ids, same)
    below = select_vertices(x, {"plane": {"point": [0, 0, 0.3], "normal": [0, 0, -1]}})
    assert below.size == 4 * 121
    diag = select_vertices(x, {"plane": {"point": [1, 1, 1], "normal": [1, 1, 1]}})
    assert diag.tolist() == [grid.n_verts - 1]


def test_indices_all_and_surface_only(grid):
    x = grid.vertices
    assert select_vertices(x, {"indices": [5, 3, 3, 0]}).tolist() == [0, 3, 5]
    assert select_vertices(x, {"indices": []}).size == 0
    assert np.array_equal(select_vertices(x, {"all": True}), np.arange(grid.n_verts))
    surface = extract_surface(grid.tets).vertex_ids
    ids = select_vertices(x, {"all": True, "surface_only": True}, surface_ids=surface)
    assert ids.size == 11**3 - 9**3
    ids = select_vertices(x, {"sphere": {"center": [0.5, 0.5, 0.5], "radius": 0.25},
                              "surface_only": True}, surface_ids=surface)
    assert ids.size == 0
    top = select_vertices(x, {"box": [[0.0, 0.0, 0.5], [1.0, 1.0, 1.0]], "surface_only": True},
                          surface_ids=surface)
    assert top.size == 121 + 5 * (4 * 10)  # top face plus 5 side rings below it
    assert top.dtype == np.int64


def test_tolerance_override(grid):
    x = grid.vertices
    spec = {"plane": {"point": [0.305, 0, 0], "normal": [1, 0, 0]}}
    assert select_vertices(x, spec).size == 7 * 121
    assert select_vertices(x, dict(spec, tolerance=0.01)).size == 8 * 121


@pytest.mark.parametrize(
    "spec, match",
    [
        ({"boxx": [[0, 0, 0], [1, 1, 1]]}, "boxx"),
        ({}, "exactly one"),
        ({"all": True, "indices": [1]}, "exactly one"),
        ({"box": [[0, 0, 0]]}, "box"),
        ({"box": [[1, 1, 1], [0, 0, 0]]}, "box"),
        ({"sphere": {"center": [0, 0, 0]}}, "radius"),
        ({"sphere": {"center": [0, 0], "radius": 1}}, "sphere.center"),
        ({"sphere": {"center": [0, 0, 0], "radius": -1}}, "sphere.radius"),
        ({"plane": {"point": [0, 0, 0], "normal": [0, 0, 0]}}, "plane.normal"),
        ({"plane": {"point": [0, 0, 0]}}, "normal"),
        ({"indices": [0, 99999]}, "indices"),
        ({"indices": [0.5]}, "indices"),
        ({"indices": [-1]}, "indices"),
        ({"all": False}, "all"),
        ({"all": True, "surface_only": True}, "surface_only"),
        ({"all": True, "surface_only": "yes"}, "surface_only"),
        ([1, 2, 3], "mapping"),
    ],
)
def test_bad_specs_raise_scene_error_naming_the_key(grid, spec, match):
    with pytest.raises(SceneError, match=match):
        select_vertices(grid.vertices, spec)
