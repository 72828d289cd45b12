"""Collider geometry: signed distances against closed forms, normals = gradient of phi."""
import numpy as np
import pytest

from mdss_ros.contact.colliders import make_collider
from mdss_ros.errors import SceneError
from mdss_ros.rotations import exp_so3, quat_from_matrix

SPECS = {
    "sphere": {"shape": "sphere", "radius": 0.3},
    "capsule": {"shape": "capsule", "radius": 0.2, "half_height": 0.4},
    "box": {"shape": "box", "half_extents": [0.3, 0.2, 0.1]},
    "plane": {"shape": "plane"},
}


@pytest.mark.parametrize("shape", list(SPECS))
def test_normal_is_gradient_of_signed_distance(shape):
    c = make_collider("c", SPECS[shape])
    c.set_pose([0.1, -0.2, 0.3], quat_from_matrix(exp_so3(np.array([0.3, -0.5, 0.8]))))
    rng = np.random.default_rng(0)
    p = c.position + rng.uniform(-0.8, 0.8, size=(400, 3))
    phi, n = c.signed_distance(p)
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-12)
    h = 1e-6
    grad = np.stack([(c.signed_distance(p + h * e)[0] - c.signed_distance(p - h * e)[0]) / (2 * h)
                     for e in np.eye(3)], axis=1)
    smooth = np.linalg.norm(grad, axis=1) > 0.999       # away from medial sets (kinks)
    assert smooth.mean() > 0.8
    np.testing.assert_allclose(grad[smooth], n[smooth], atol=1e-5)


@pytest.mark.parametrize("shape", list(SPECS))
def test_distance_is_the_phi_of_signed_distance(shape):
    c = make_collider("c", SPECS[shape])
    c.set_pose([0.1, -0.2, 0.3], quat_from_matrix(exp_so3(np.array([0.3, -0.5, 0.8]))))
    p = c.position + np.random.default_rng(1).uniform(-0.8, 0.8, size=(300, 3))
    np.testing.assert_allclose(c.distance(p), c.signed_distance(p)[0], rtol=0, atol=1e-14)


@pytest.mark.parametrize("shape", list(SPECS))
def test_near_is_where_distance_is_below_the_margin(shape):
    """Collider.near (compiled for a sphere) selects the points distance() puts within the
    margin."""
    c = make_collider("c", SPECS[shape])
    c.set_pose([0.1, -0.2, 0.3], quat_from_matrix(exp_so3(np.array([0.3, -0.5, 0.8]))))
    p = c.position + np.random.default_rng(3).uniform(-0.8, 0.8, size=(2000, 3))
    for margin in (0.0, 0.05, 0.3):
        near = c.near(p, margin)
        np.testing.assert_array_equal(near, np.flatnonzero(c.distance(p) < margin))
        assert near.dtype == np.int64


def test_triangle_culling_kernels_match_numpy():
    """unilateral.longest_edge_squared and triangles_near_segment against numpy on a random
    soup, for a sphere (a == b) and a segment."""
    from mdss_ros.contact.unilateral import closest_points_on_segment, longest_edge_squared, triangles_near_segment
    rng = np.random.default_rng(2)
    x = rng.uniform(-1, 1, size=(200, 3))
    tri = rng.integers(0, 200, size=(500, 3))
    e = np.concatenate([x[tri[:, (k + 1) % 3]] - x[tri[:, k]] for k in range(3)])
    assert longest_edge_squared(x, tri) == pytest.approx((e * e).sum(1).max(), rel=1e-15)
    for a, b in ((np.array([0.1, 0.2, 0.0]),) * 2, (np.array([-0.5, 0.0, 0.2]), np.array([0.4, 0.3, -0.1]))):
        d = np.linalg.norm(x - closest_points_on_segment(a, b, x), axis=1)
        for reach in (0.2, 0.5):
            want = np.flatnonzero(d[tri].min(axis=1) < reach)
            assert 0 < len(want) < len(tri)
            np.testing.assert_array_equal(triangles_near_segment(x, tri, a, b, reach), want)


def test_closed_form_distances():
    s = make_collider("s", {"shape": "sphere", "radius": 0.5, "position": [1, 0, 0]})
    phi, n = s.signed_distance(np.array([[3.0, 0, 0], [1.0, 0.25, 0]]))
    np.testing.assert_allclose(phi, [1.5, -0.25])
    np.testing.assert_allclose(n[0], [1, 0, 0])
    b = make_collider("b", {"shape": "box", "half_extents": [1, 1, 1]})
    phi, _ = b.signed_distance(np.array([[2.0, 2.0, 0.0], [0.0, 0.0, 0.5]]))
    np.testing.assert_allclose(phi, [np.sqrt(2.0), -0.5])
    f = make_collider("f", {"shape": "plane", "position": [0, 0, -1]})
    phi, n = f.signed_distance(np.array([[5.0, 3.0, 0.5]]))
    np.testing.assert_allclose(phi, [1.5])
    np.testing.assert_allclose(n[0], [0, 0, 1])


@pytest.mark.parametrize("spec, words", [
    ({"shape": "cone"}, "shape"), ({"shape": "sphere"}, "radius"), ({"shape": "sphere", "radius": -1}, "radius"),
    ({"shape": "box", "half_extents": [1, 1]}, "half_extents"), ({"shape": "plane", "radius": 1}, "unknown"),
    ({"shape": "sphere", "radius": 1, "orientation": [0, 0, 0, 0]}, "orientation"),
])
def test_bad_collider_specs_name_the_key(spec, words):
    with pytest.raises(SceneError, match=words):
        make_collider("c", spec)
