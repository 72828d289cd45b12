"""TetMesh validity checks, orientation helpers and the quality report."""
import numpy as np
import pytest

from mdss_ros.errors import MeshError
from mdss_ros.mesh import TetMesh, box, quality_report
from mdss_ros.mesh.quality import dihedral_angles, format_quality, radius_ratios
from mdss_ros.mesh.tetmesh import (
    orient_tets,
    remove_unreferenced,
    signed_volumes,
    unreferenced_vertices,
)

UNIT_TET = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
REGULAR_TET = np.array([[1.0, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1]])


def test_post_init_normalises_dtypes_and_layout():
    v = np.asfortranarray(UNIT_TET.astype(np.float32))
    mesh = TetMesh(v, np.array([[0, 1, 2, 3]], dtype=np.int32))
    assert mesh.vertices.dtype == np.float64 and mesh.vertices.flags.c_contiguous
    assert mesh.tets.dtype == np.int64 and mesh.tets.flags.c_contiguous
    assert TetMesh(UNIT_TET, [[0.0, 1.0, 2.0, 3.0]]).tets.dtype == np.int64
    with pytest.raises(MeshError, match="non-integer"):
        TetMesh(UNIT_TET, [[0, 1, 2, 2.5]])
    with pytest.raises(AttributeError):
        mesh.tets = None  # frozen


def test_signed_volumes_and_orientation():
    rng = np.random.default_rng(1)
    x = rng.normal(size=(50, 3))
    tets = np.array([rng.choice(50, 4, replace=False) for _ in range(200)])
    vol = signed_volumes(x, tets)
    dm = np.stack([x[tets[:, k]] - x[tets[:, 0]] for k in (1, 2, 3)], axis=2)
    assert np.allclose(vol, np.linalg.det(dm) / 6.0, rtol=1e-10, atol=1e-14)
    oriented = orient_tets(x, tets)
    assert np.all(signed_volumes(x, oriented) > 0)
    assert np.allclose(signed_volumes(x, oriented), np.abs(vol))
    assert np.array_equal(np.sort(oriented, axis=1), np.sort(tets, axis=1))
    assert signed_volumes(UNIT_TET, np.array([[0, 1, 2, 3]]))[0] == pytest.approx(1.0 / 6.0)


@pytest.mark.parametrize(
    "vertices, tets, match",
    [
        (np.zeros((0, 3)), np.zeros((0, 4), int), "empty"),
        (UNIT_TET[:, :2], [[0, 1, 2, 3]], "vertices must have shape"),
        (UNIT_TET, [[0, 1, 2]], "tets must have shape"),
        (np.where([[0], [0], [1], [0]], np.nan, UNIT_TET), [[0, 1, 2, 3]], "NaN/Inf"),
        (UNIT_TET, [[0, 1, 2, 4]], "outside"),
        (UNIT_TET, [[0, 1, 2, -1]], "outside"),
        (UNIT_TET, [[0, 1, 1, 3]], "repeat a vertex"),
        (np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]]), [[0, 1, 2, 3]], "degenerate"),
    ],
)
def test_validate_names_the_problem(vertices, tets, match):
    with pytest.raises(MeshError, match=match):
        TetMesh(vertices, tets).validate()


def test_validate_lists_count_and_first_indices_of_degenerate_tets():
    x = np.vstack([UNIT_TET, [[2.0, 0, 0]]])  # vertex 4 is collinear with 0 and 1
    tets = np.array([[0, 1, 2, 3], [0, 1, 4, 2], [0, 1, 2, 3], [0, 4, 1, 3]])
    with pytest.raises(MeshError, match=r"2 degenerate .* \[1, 3\]"):
        TetMesh(x, tets).validate()


def test_validate_orientation_only_on_request():
    inverted = TetMesh(UNIT_TET, [[0, 2, 1, 3]])
    assert inverted.validate() is inverted
    with pytest.raises(MeshError, match="inverted"):
        inverted.validate(require_positive=True)
    box(size=(1, 1, 1), cell=0.5).validate(require_positive=True)


def test_unreferenced_vertices_reported_and_removed():
    x = np.vstack([[[5.0, 5, 5]], UNIT_TET, [[7.0, 7, 7]]])
    mesh = TetMesh(x, [[1, 2, 3, 4]]).validate()
    assert unreferenced_vertices(mesh).tolist() == [0, 5]
    clean = remove_unreferenced(mesh)
    assert np.array_equal(clean.vertices, UNIT_TET)
    assert clean.tets.tolist() == [[0, 1, 2, 3]]
    assert remove_unreferenced(clean) is clean


def test_quality_of_kuhn_box_matches_hand_computed_values():
    h = 0.25
    mesh = box(size=(1.0, 1.0, 1.0), cell=h)
    q = quality_report(mesh)
    assert q["n_verts"] == 125 and q["n_tets"] == 384
    assert q["volume"] == pytest.approx(1.0, rel=1e-12)
    assert q["n_inverted"] == 0 and q["n_slivers"] == 0
    # Kuhn tet of a cube (orthoscheme): dihedral angles 45, 60, 45 and three 90.
    assert q["min_dihedral_deg"] == pytest.approx(45.0, abs=1e-9)
    assert q["max_dihedral_deg"] == pytest.approx(90.0, abs=1e-9)
    angles = np.sort(dihedral_angles(mesh.vertices, mesh.tets[:1])[0])
    assert np.allclose(angles, [45, 45, 60, 90, 90, 90])
    # V = h^3/6, faces h^2 (1/2 + 1/2 + sqrt2/2 + sqrt2/2): r_in = 3V/A = h / (2 (1 + sqrt2));
    # R = half the cube diagonal = sqrt3 h / 2  ->  3 r / R = sqrt3 / (1 + sqrt2).
    assert q["radius_ratio_min"] == pytest.approx(np.sqrt(3) / (1 + np.sqrt(2)), rel=1e-12)
    assert q["radius_ratio_median"] == pytest.approx(np.sqrt(3) / (1 + np.sqrt(2)), rel=1e-12)
    assert q["edge_min"] == pytest.approx(h) and q["edge_max"] == pytest.approx(h * np.sqrt(3))
    line = format_quality(q)
    assert "\n" not in line and "384 tets" in line and "0 slivers" in line


def test_regular_tet_reference_values():
    tets = np.array([[0, 1, 2, 3]])
    tets = orient_tets(REGULAR_TET, tets)
    assert np.allclose(dihedral_angles(REGULAR_TET, tets), np.degrees(np.arccos(1 / 3)))
    assert radius_ratios(REGULAR_TET, tets)[0] == pytest.approx(1.0, rel=1e-12)


def test_flat_and_inverted_tets_are_counted():
    flat = np.vstack([UNIT_TET, [[0.3, 0.3, 0.0]]])  # vertex 4 lies in the z = 0 face
    tets = np.array([[0, 1, 2, 3], [0, 1, 2, 4], [0, 2, 1, 3]])  # ok, flat, inverted
    q = quality_report(TetMesh(flat, tets))
    assert q["n_inverted"] == 2  # the flat one (volume 0) and the swapped one
    assert q["n_slivers"] == 1  # only the flat one: inversion does not change angles
    assert q["min_dihedral_deg"] == pytest.approx(0.0, abs=1e-9)
    assert q["radius_ratio_min"] == 0.0
    nearly_flat = np.vstack([UNIT_TET, [[0.3, 0.3, 0.01]]])
    q = quality_report(TetMesh(nearly_flat, [[0, 1, 2, 4]]))
    assert q["n_inverted"] == 0 and q["n_slivers"] == 1
    assert quality_report(TetMesh(nearly_flat, [[0, 1, 2, 4]]), sliver_deg=1.0)["n_slivers"] == 0
