import numpy as np

from mdss_ros.loads import closest_points_on_triangles, closest_surface_point, wrench_to_vertex_forces


def test_closest_point_matches_dense_sampling():
    rng = np.random.default_rng(0)
    for _ in range(200):
        a, b, c = rng.normal(size=(3, 3))
        p = rng.normal(size=3) * 2
        d2, bary = closest_points_on_triangles(p, a[None], b[None], c[None])
        # Brute force over a fine barycentric grid.
        u, v = np.meshgrid(np.linspace(0, 1, 301), np.linspace(0, 1, 301))
        keep = u + v <= 1
        pts = a + u[keep, None] * (b - a) + v[keep, None] * (c - a)
        best = ((pts - p) ** 2).sum(1).min()
        assert d2[0] <= best + 1e-12
        assert d2[0] >= best - 5e-3 * (1 + best)
        assert np.all(bary >= -1e-12) and abs(bary.sum() - 1) < 1e-12


def test_closest_surface_point_picks_nearest_triangle():
    pos = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [5, 5, 0], [6, 5, 0], [5, 6, 0]], float)
    tris = np.array([[0, 1, 2], [3, 4, 5]])
    k, bary, dist = closest_surface_point([5.2, 5.2, 1.0], pos, tris)
    assert k == 1 and abs(dist - 1.0) < 1e-12
    np.testing.assert_allclose(bary @ pos[tris[1]], [5.2, 5.2, 0.0], atol=1e-12)


def test_wrench_spread_reproduces_force_and_torque():
    rng = np.random.default_rng(1)
    x = rng.normal(size=(20, 3))
    m = rng.uniform(0.5, 2.0, 20)
    force, torque = np.array([1.0, -2.0, 0.5]), np.array([0.3, 0.1, -0.7])
    f = wrench_to_vertex_forces(x, m, force, torque)
    c = (m[:, None] * x).sum(0) / m.sum()
    np.testing.assert_allclose(f.sum(0), force, atol=1e-12)
    np.testing.assert_allclose(np.cross(x - c, f).sum(0), torque, atol=1e-12)
    # Positions given as a function are read for a torque only: a pure force needs none.
    np.testing.assert_array_equal(wrench_to_vertex_forces(lambda: x, m, force, torque), f)
    np.testing.assert_allclose(wrench_to_vertex_forces(lambda: 1 / 0, m, force, np.zeros(3)).sum(0), force, atol=1e-12)


def test_vertex_loads_sum_repeated_ids_and_match_the_dense_array():
    from mdss_ros.loads import VertexLoads, sparse_loads
    a = (np.array([3, 7]), np.array([[1.0, 0, 0], [0, 2.0, 0]]))
    b = (np.array([7, 1]), np.array([[0, 1.0, 0], [0, 0, 5.0]]))
    loads = VertexLoads(10, [a, b])
    assert loads.ids.tolist() == [1, 3, 7]
    np.testing.assert_array_equal(loads.forces, [[0, 0, 5.0], [1.0, 0, 0], [0, 3.0, 0]])
    dense = loads.dense()
    assert dense.shape == (10, 3) and dense.sum() == 9.0
    ids, f = sparse_loads(dense)
    np.testing.assert_array_equal(ids, loads.ids)
    np.testing.assert_array_equal(f, loads.forces)
    # Many parts with repeated ids: the same sums as adding them one by one.
    rng = np.random.default_rng(2)
    parts = [(np.sort(rng.choice(30, 12, replace=False)), rng.normal(size=(12, 3))) for _ in range(4)]
    want = np.zeros((30, 3))
    for i, f in parts:
        want[i] += f
    np.testing.assert_allclose(VertexLoads(30, parts).dense(), want, rtol=0, atol=1e-14)
    single = VertexLoads(10, [a])
    np.testing.assert_array_equal(single.dense()[[3, 7]], a[1])
    assert VertexLoads(10).dense().sum() == 0.0
