"""The contact LCP solver at the sizes scenes give it: many rows, rank-deficient S
(reduced bodies), warm starts. Reference: the same LCP as a non-negative least-squares
problem (S = L L^T: min |L^T lam + L^-1 q| over lam >= 0), solved by scipy."""
import numpy as np
import pytest
import scipy.linalg as sla
from scipy.optimize import nnls

from mdss_ros.contact.unilateral import contact_correction, solve_lcp


def _reference(S, q):
    L = np.linalg.cholesky(S)
    return nnls(L.T, -sla.solve_triangular(L, q, lower=True), maxiter=50 * len(q))[0]


def _lcp_error(S, q, lam):
    w = S @ lam + q
    return max(-lam.min(), -w.min(), abs(lam @ w) / max(np.abs(q).max(), 1e-300))


@pytest.mark.parametrize("seed", range(4))
def test_block_pivoting_matches_nnls_on_large_problems(seed):
    rng = np.random.default_rng(seed)
    m = 120
    B = rng.normal(size=(m, m))
    S = B @ B.T / m + 0.05 * np.eye(m)
    q = rng.normal(size=m)
    lam, info = solve_lcp(S, q)
    assert not info.get("unconverged") and 0 < info["active"] < m
    assert _lcp_error(S, q, lam) < 1e-9
    np.testing.assert_allclose(lam, _reference(S, q), atol=1e-8)


def test_rank_deficient_rows_with_regularisation_match_the_regularised_reference():
    """A reduced body: 300 contact rows through 40 DOFs make S = C A^-1 C^T singular; the
    regularised LCP is unique and the solver finds it (many active rows at once)."""
    rng = np.random.default_rng(7)
    n, m = 40, 300
    C = rng.normal(size=(m, n))
    G = rng.normal(size=(n, n))
    A = G @ G.T + n * np.eye(n)
    S = C @ np.linalg.solve(A, C.T)
    # A feasible problem, as contact gives: the correction -u meets every row (gap s >= 0).
    q = C @ rng.normal(size=n) + rng.uniform(0.0, 0.5, size=m)
    eps = 1e-9
    lam, info = solve_lcp(S, q, regularize=eps)
    S_reg = S + eps * np.mean(np.diag(S)) * np.eye(m)
    assert not info.get("unconverged")
    assert info["active"] > n // 2                # many rows, near the rank of S, active at once
    assert _lcp_error(S_reg, q, lam) < 1e-8
    np.testing.assert_allclose(S @ lam, S @ _reference(S_reg, q), atol=1e-6 * np.abs(S @ lam).max())


@pytest.mark.parametrize("guess", ["empty", "all", "random", "exact"])
def test_any_first_guess_gives_the_same_solution(guess):
    rng = np.random.default_rng(11)
    m = 80
    B = rng.normal(size=(m, m))
    S = B @ B.T / m + 0.1 * np.eye(m)
    q = rng.normal(size=m)
    ref, _ = solve_lcp(S, q)
    first = {"empty": np.zeros(m, bool), "all": np.ones(m, bool), "random": rng.random(m) < 0.5,
             "exact": ref > 0}[guess]
    lam, info = solve_lcp(S, q, active=first)
    np.testing.assert_allclose(lam, ref, atol=1e-10)
    if guess == "exact":
        assert info["iterations"] == 1            # a right guess costs one solve


def test_hinted_working_set_gives_the_same_correction():
    """contact_correction with a hint (last step's contacts) equals the one without."""
    rng = np.random.default_rng(5)
    n, m = 60, 50
    B = rng.normal(size=(n, n))
    A = B @ B.T + n * np.eye(n)
    C = np.zeros((m, n))
    for i in range(m):
        C[i, rng.choice(n, 3, replace=False)] = rng.normal(size=3)
    g = rng.normal(size=m) + 0.3

    def resolve(rhs):
        return np.linalg.solve(A, rhs)

    lam, corr, info = contact_correction(resolve, C, g)
    for hint in (lam > 0, rng.random(m) < 0.3, np.ones(m, bool)):
        lam_h, corr_h, info_h = contact_correction(resolve, C, g, hint=hint)
        np.testing.assert_allclose(lam_h, lam, atol=1e-10)
        np.testing.assert_allclose(corr_h, corr, atol=1e-10)
    assert contact_correction(resolve, C, g, hint=lam > 0)[2]["rounds"] == 1


def _faces_by_brute_force(col, positions, triangles, margin, corner=1e-3):
    """find_triangle_contacts' answer without any cull: every triangle tested exactly."""
    from mdss_ros.contact.unilateral import _axis, segment_triangle_closest
    a, b = _axis(col)
    _, d2, bary = segment_triangle_closest(a, b, positions[triangles])
    dist = np.sqrt(d2)
    return np.flatnonzero((dist < col.radius + margin) & (bary.max(axis=1) < 1.0 - corner) & (dist > 1e-12))


@pytest.mark.parametrize("shape", ["sphere", "capsule"])
def test_triangle_cull_keeps_every_face_the_exact_test_finds(shape):
    """The vertex-then-bounding-sphere cull of find_triangle_contacts drops no touching face:
    a jittered grid of small faces plus one large face whose corners are all far from the
    collider while its interior touches it."""
    from mdss_ros.contact.colliders import make_collider
    from mdss_ros.contact.unilateral import find_triangle_contacts
    rng = np.random.default_rng(2)
    n = 12
    gx, gy = np.meshgrid(np.linspace(-0.3, 0.3, n), np.linspace(-0.3, 0.3, n), indexing="ij")
    pos = np.stack([gx.ravel(), gy.ravel(), 0.01 * rng.normal(size=n * n)], axis=1)
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    tris = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    big = np.array([[2.0, -1.0, 0.5], [-1.0, 2.0, 0.5], [-1.0, -1.0, 0.5]])   # far corners, plane z = 0.5
    pos = np.concatenate([pos, big])
    tris = np.concatenate([tris, [[n * n, n * n + 1, n * n + 2]]])
    spec = {"shape": shape, "radius": 0.05, "position": [0.0, 0.0, 0.0]}
    if shape == "capsule":
        spec["half_height"] = 0.1
    found = 0
    tip = 0.1 if shape == "capsule" else 0.0             # the capsule's axis is along z
    for centre in ([0.0, 0.0, 0.45 - tip], [0.01, 0.02, 0.04], [0.1, -0.05, 0.03], [0.2, 0.2, 0.2]):
        col = make_collider("c", dict(spec, position=centre))
        t_idx = find_triangle_contacts([col], pos, tris, margin=0.02)[0]
        ref = _faces_by_brute_force(col, pos, tris, margin=0.02)
        np.testing.assert_array_equal(np.sort(t_idx), ref)
        found += len(ref)
        if centre[2] == 0.45 - tip:
            assert len(tris) - 1 in ref            # the large face is found
    assert found > 3


def test_sphere_narrow_phase_is_the_numpy_one_bit_for_bit():
    """sphere_triangles_closest (compiled) keeps the triangles whose bounding sphere about
    the corners' mean comes within reach of the centre, and gives
    closest_points_on_triangles' distances and barycentric coordinates exactly: points in
    every Voronoi region of a triangle (inside, beyond each edge and each corner)."""
    from mdss_ros.contact.unilateral import sphere_triangles_closest
    from mdss_ros.loads import closest_points_on_triangles
    rng = np.random.default_rng(11)
    positions = rng.standard_normal((80, 3))
    triangles = np.array([rng.choice(80, 3, replace=False) for _ in range(400)], dtype=np.int64)
    for centre, reach in ((np.zeros(3), 0.7), (rng.standard_normal(3), 1.5), (np.array([0.3, -0.2, 0.1]), 0.2)):
        near = np.sort(rng.choice(len(triangles), 300, replace=False))
        kept, d2, bary = sphere_triangles_closest(positions, triangles, near, centre, reach)
        tri = positions[triangles[near]]
        centroid = tri.mean(axis=1)
        spread = np.linalg.norm(tri - centroid[:, None, :], axis=2).max(axis=1)
        expect = np.flatnonzero(np.linalg.norm(centroid - centre, axis=1) < reach + spread)
        np.testing.assert_array_equal(kept, expect)
        d2_ref, bary_ref = closest_points_on_triangles(centre, tri[kept, 0], tri[kept, 1], tri[kept, 2])
        np.testing.assert_array_equal(d2, d2_ref)
        np.testing.assert_array_equal(bary, bary_ref)
        regions = (bary_ref > 0).sum(axis=1)
        assert {1, 2, 3} <= set(regions.tolist())          # corners, edges and faces all met


def test_resting_reduced_block_solves_only_for_the_contacts_that_carry_it():
    """Warm start across steps: once a reduced block rests on the floor, the LCP's working
    set is the set of load-carrying contacts of the last step, not every bottom vertex the
    unconstrained step pushes through the floor; the floor still carries the weight. A
    plane gets no residual contact compliance (model_build.contact_candidates), so the
    block's modes carry it on a few vertices (13 of 81 measured)."""
    from mdss_ros import Simulator
    scene = {"name": "block",
             "body": {"mesh": {"generator": "box", "size": [0.2, 0.2, 0.1], "cell": 0.025,
                               "origin": [-0.1, -0.1, 0.0]},
                      "material": {"model": "neohookean", "young": 1e5, "poisson": 0.3, "density": 1000},
                      "damping": {"alpha": 5.0, "beta": 0.0}},
             "colliders": {"floor": {"shape": "plane"}},
             "model": {"kind": "reduced", "domains": {"count": 2}, "modes": 10, "cubature": {"samples": 0},
                       "integrator": {"dt": 0.01, "newton_iterations": 2}}}
    sim = Simulator(scene)
    assert sim.model.compliance is None
    assert any("planes only" in line for line in sim.explain())
    bottom = int((sim.rest_positions()[:, 2] < 1e-9).sum())
    sim.step(60)
    st = sim.stats()
    active = len(sim.contacts())
    assert 0 < active < bottom
    assert st["contact_working_set"] == active < st["contact_rows"] // 4
    weight = sim.model.vertex_mass.sum() * 9.81
    assert abs(-sim.collider_wrench("floor")[2] - weight) < 0.02 * weight


def test_reset_repeats_contact_steps_bit_for_bit():
    """The LCP's warm start is part of the model state: after Simulator.reset() the same
    inputs give the same contact forces bit for bit (replays and the guard rely on it)."""
    from mdss_ros import Simulator
    scene = {"name": "block",
             "body": {"mesh": {"generator": "box", "size": [0.2, 0.2, 0.1], "cell": 0.025,
                               "origin": [-0.1, -0.1, 0.0]},
                      "material": {"model": "neohookean", "young": 1e5, "poisson": 0.3, "density": 1000},
                      "damping": {"alpha": 5.0, "beta": 0.0}},
             "colliders": {"floor": {"shape": "plane"},
                           "ball": {"shape": "sphere", "radius": 0.04, "position": [0.0, 0.0, 0.2]}},
             "model": {"kind": "reduced", "domains": {"count": 2}, "modes": 10, "cubature": {"samples": 0}}}
    sim = Simulator(scene)

    def run():
        out = []
        for k in range(30):
            sim.set_collider_pose("ball", (0.0, 0.0, 0.14 - 0.0002 * min(k, 25)))   # 5 mm in, held
            sim.step()
            out.append(np.concatenate([sim.collider_wrench("ball"), sim.collider_wrench("floor")]))
        return np.array(out)

    first = run()
    sim.reset()
    again = run()
    assert np.abs(first[10:, 2]).min() > 0               # the ball is pressing
    np.testing.assert_array_equal(first, again)


def test_member_is_np_isin_for_contact_keys():
    from mdss_ros.contact.unilateral import member
    rng = np.random.default_rng(2)
    for n_keys, n_among, span in ((0, 5, 10), (5, 0, 10), (200, 40, 3000), (50, 50, 60)):
        keys = rng.integers(0, span, n_keys)
        among = rng.integers(0, span, n_among)
        assert np.array_equal(member(keys, among), np.isin(keys, among))
