"""Frictionless unilateral contact: LCP, weight balance, no penetration, clean release."""
import itertools

import numpy as np
import pytest

from mdss_ros import Simulator
from mdss_ros.contact.unilateral import solve_lcp


def test_lcp_matches_brute_force_enumeration():
    rng = np.random.default_rng(0)
    for _ in range(30):
        m = 5
        B = rng.normal(size=(m, m))
        S = B @ B.T + 0.1 * np.eye(m)
        q = rng.normal(size=m)
        lam, info = solve_lcp(S, q)
        w = S @ lam + q
        assert np.all(lam >= 0) and np.all(w >= -1e-10) and abs(lam @ w) < 1e-9
        # The solution of an LCP with SPD S is unique: compare with enumeration.
        for active in itertools.product([0, 1], repeat=m):
            idx = np.flatnonzero(active)
            x = np.zeros(m)
            if idx.size:
                x[idx] = np.linalg.solve(S[np.ix_(idx, idx)], -q[idx])
            if np.all(x >= -1e-12) and np.all(S @ x + q >= -1e-10):
                np.testing.assert_allclose(lam, np.maximum(x, 0), atol=1e-9)


def _block_scene(colliders, **model):
    return {"name": "block",
            "body": {"mesh": {"generator": "box", "size": [0.2, 0.2, 0.1], "cell": 0.025, "origin": [-0.1, -0.1, 0.0]},
                     "material": {"model": "neohookean", "young": 1e5, "poisson": 0.3, "density": 1000},
                     "damping": {"alpha": 5.0, "beta": 0.0}},
            "colliders": colliders,
            "model": {"kind": "full", "integrator": {"dt": 0.01, "newton_iterations": 2}, **model}}


@pytest.mark.claims
def test_block_on_floor_reaction_equals_weight_without_penetration():
    sim = Simulator(_block_scene({"floor": {"shape": "plane"}}))
    weight = sim.model.vertex_mass.sum() * 9.81
    sim.step(150)
    wrench = sim.collider_wrench("floor")
    # At rest the exact contact solve carries the weight to round-off (measured 4e-16)
    assert abs(-wrench[2] - weight) < 1e-12 * weight
    assert np.abs(wrench[:2]).max() < 1e-9 * weight
    phi = sim.colliders["floor"].signed_distance(sim.vertex_positions())[0]
    assert phi.min() > -1e-9
    c = sim.contacts()
    assert c.shape[1] == 10 and len(c) > 0 and np.all(c[:, 9] > 0)


def test_collider_wrenches_are_the_reaction_sums_and_torques():
    """contact_wrenches against its definition, collider by collider: minus the sum of the
    contact forces on the body, torque about the collider's position; a collider without
    contacts reads zero; Simulator.collider_wrenches() is collider_wrench of each."""
    from types import SimpleNamespace
    from mdss_ros.contact.unilateral import contact_wrenches
    rng = np.random.default_rng(4)
    cols = [SimpleNamespace(name=n, position=rng.normal(size=3)) for n in ("a", "b", "c")]
    points, forces = rng.normal(size=(30, 3)), rng.normal(size=(30, 3))
    which = rng.choice([0, 2], size=30)                    # "b" touches nothing
    got = contact_wrenches(cols, points, forces, which)
    for i, col in enumerate(cols):
        sel = which == i
        f = -forces[sel]
        expected = np.concatenate([f.sum(0), sum((np.cross(p - col.position, fi) for p, fi in zip(points[sel], f)),
                                                 np.zeros(3))])
        np.testing.assert_allclose(got[col.name], expected, rtol=1e-13, atol=1e-13)
    assert not got["b"].any()
    assert set(contact_wrenches(cols, np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0, int))) == {"a", "b", "c"}
    sim = Simulator(_block_scene({"floor": {"shape": "plane"},
                                  "ball": {"shape": "sphere", "radius": 0.04, "position": [0.0, 0.0, 0.145]}}))
    for z in np.linspace(0.143, 0.137, 4):             # press 3 mm into the top
        sim.set_collider_pose("ball", (0.0, 0.0, z))
        sim.step()
    all_of = sim.collider_wrenches()
    assert list(all_of) == ["floor", "ball"] and all_of["ball"][2] > 0 and all_of["floor"][2] < 0
    for name, w in all_of.items():
        np.testing.assert_array_equal(sim.collider_wrench(name), w)
    with pytest.raises(KeyError, match="unknown collider"):
        sim.collider_wrench("nope")


def test_sphere_pressed_then_withdrawn_releases_cleanly():
    sim = Simulator(_block_scene({"floor": {"shape": "plane"},
                                  "ball": {"shape": "sphere", "radius": 0.04, "position": [0, 0, 0.2]}}))
    sim.step(50)                                        # settle on the floor
    top = 0.1
    for k in range(40):                                 # press 1 cm into the top over 0.4 s
        sim.set_collider_pose("ball", (0.0, 0.0, top + 0.04 - 0.01 * (k + 1) / 40))
        sim.step()
    pressed = sim.collider_wrench("ball")
    assert pressed[2] > 0.0                             # the block pushes the ball up
    phi = sim.colliders["ball"].signed_distance(sim.vertex_positions())[0]
    assert phi.min() > -1e-6
    e_before = sim.energy()["total"]
    for k in range(40):                                 # withdraw well clear
        sim.set_collider_pose("ball", (0.0, 0.0, top + 0.03 + 0.1 * (k + 1) / 40))
        sim.step()
    assert np.allclose(sim.collider_wrench("ball"), 0.0)
    # No sticking: the top surface is back near its rest height, and no energy was gained.
    ids = sim.body.surface.vertex_ids
    z_top = sim.vertex_positions()[ids][:, 2].max()
    assert z_top < top + 1e-3
    assert sim.energy()["total"] <= e_before + 1e-6


@pytest.mark.claims
@pytest.mark.parametrize("domains, full_space", [(2, []), (2, ["domain_1"])])
def test_reduced_block_on_floor_reaction_equals_weight(domains, full_space):
    sim = Simulator(_block_scene({"floor": {"shape": "plane"}}, kind="reduced", domains={"count": domains},
                                 modes=10, full_space_domains=full_space, cubature={"samples": 0}))
    weight = sim.model.vertex_mass.sum() * 9.81
    sim.step(150)
    wrench = sim.collider_wrench("floor")
    # the same round-off through J (measured 1.4e-15 and 3.8e-15)
    assert abs(-wrench[2] - weight) < 1e-12 * weight
    phi = sim.colliders["floor"].signed_distance(sim.vertex_positions())[0]
    assert phi.min() > -1e-6


def _fast_ball_run(kind, check_shadow, young=1e5, continuous=False):
    """A sphere driven at 5 m/s into a soft block (5.6 cm per 1/90 s step, more than its
    radius). Returns after asserting per step: finite, no surface vertex inside the ball,
    and (check_shadow) the surface vertices in the ball's path stay ahead of its centre.

    continuous: also every model (sub-)step the step kept, in between its ends (the guard's
    rejected attempts are discarded; when the kept chain cannot be told, every attempt is
    checked): no surface vertex's path (linear over the sub-step, against the ball's linear
    sweep) gets 2 mm into the ball (unilateral.sphere_time_of_impact), and at every step's
    end the ball's centre is outside the body's volume (its winding number with respect to
    the surface is 0). Returns (sim, deepest path depth (m))."""
    from mdss_ros.contact.colliders import winding_numbers
    from mdss_ros.contact.unilateral import sphere_time_of_impact
    scene = _block_scene({"floor": {"shape": "plane"},
                          "ball": {"shape": "sphere", "radius": 0.04, "position": [-0.3, 0.0, 0.05]}},
                         kind=kind, integrator={"dt": 1 / 90, "newton_iterations": 1})
    scene["body"]["material"]["young"] = young
    if kind == "reduced":
        scene["model"].update({"domains": {"count": 2}, "modes": 10, "cubature": {"samples": 0}})
    sim = Simulator(scene)
    ids = sim.body.surface.vertex_ids
    ball = sim.colliders["ball"]
    which = list(sim.colliders).index("ball")
    substeps = []
    if continuous:
        model_step = sim.model.step

        def recorded(*args, **kwargs):
            # The ball's pose at the sub-step's start is the contact spec's "starts" entry.
            start = kwargs["contact"]["starts"][which] if kwargs.get("contact") else None
            c0 = ball.position.copy() if start is None else np.array(start[0])
            x0 = sim.model.positions_of(ids).copy()
            out = model_step(*args, **kwargs)
            substeps.append((c0, x0, ball.position.copy(), sim.model.positions_of(ids).copy()))
            return out
        sim.model.step = recorded
    deepest = -np.inf
    for k in range(12):                                  # from x = -0.3 to +0.37: through the block's volume
        ball_x = -0.3 + 5.0 * (k + 1) / 90
        sim.set_collider_pose("ball", (ball_x, 0.0, 0.05))
        sim.step()
        x = sim.vertex_positions()[ids]
        assert np.all(np.isfinite(x))
        assert sim.colliders["ball"].signed_distance(x)[0].min() > -2e-3
        if continuous:
            assert len(substeps) >= sim.stats().get("collider_substeps", 1)
            for c0, x0, c1, x1 in _kept_substeps(substeps, sim.model.positions_of(ids)):
                deepest = max(deepest, float(sphere_time_of_impact(x0, x1, c0, c1, ball.radius)[1].max()))
            assert deepest < 2e-3, (k, deepest)
            substeps.clear()
            assert abs(winding_numbers(ball.position, x, sim.body.surface.triangles)[0]) < 0.5, k
        if check_shadow:
            shadow = x[(x[:, 1] ** 2 + (x[:, 2] - 0.05) ** 2) < 0.02 ** 2]
            assert np.all(shadow[:, 0] > ball_x), (k, ball_x, shadow[:, 0].min())
    return (sim, deepest) if continuous else sim


def _kept_substeps(substeps, end):
    """The model sub-steps [(c0, x0, c1, x1), ...] of one step that led to its end positions:
    walked back from the last one ending there, each one's start the end of the one before
    (the guard restores the step's start for every retry). All of them when no chain ends
    there (a state changed outside the model's step)."""
    chain, target = [], end
    for sub in reversed(substeps):
        if np.array_equal(sub[3], target):
            chain.append(sub)
            target = sub[1]
    return chain[::-1] if chain else substeps


@pytest.mark.parametrize("kind", ["full", "reduced"])
def test_fast_collider_does_not_tunnel(kind):
    """E = 1e5 Pa block; with vertex contacts alone the ball slips through a face by step 4-5
    at 1e4-1e6 Pa; the sphere-face contacts stop it."""
    sim = _fast_ball_run(kind, check_shadow=True)
    assert sim.stats().get("collider_substeps", 1) > 1


@pytest.mark.parametrize("kind", ["full", "reduced"])
def test_fast_collider_does_not_cross_jelly(kind):
    """E = 1e4 Pa: the ball outruns the block's elastic waves (3.7 m/s longitudinal, 2.0 m/s
    shear; 11.6 and 6.2 m/s at 1e5 Pa) and buries itself in it. Checked continuously, no
    vertex path enters the ball within any sub-step (the deepest: 0.027 mm full; reduced
    none, 0.012 mm clear) and the ball's centre never enters the body's volume."""
    sim, deepest = _fast_ball_run(kind, check_shadow=False, young=1e4, continuous=True)
    assert sim.stats().get("collider_substeps", 1) > 1
    assert deepest < 2e-3


@pytest.mark.parametrize("kind", [
    pytest.param("full", marks=pytest.mark.xfail(
        strict=True, reason="not tunnelling: the full-space block's front face wraps round the ball like a "
                            "sock and at step 8 the sock's neck closes behind it: front-face vertices 3.5-10 cm "
                            "off the ball's line at rest (outside the 2 cm shadow) are drawn to within 2 cm of "
                            "it 5-16 cm behind the centre, having gone round the ball "
                            "(test_fast_collider_does_not_cross_jelly checks the same run continuously; "
                            "docs/verification.md, Contact)")),
    "reduced"])
def test_fast_collider_does_not_tunnel_through_jelly(kind):
    _fast_ball_run(kind, check_shadow=True, young=1e4)


def test_sphere_time_of_impact_closed_form_and_sampling():
    from mdss_ros.contact.unilateral import sphere_time_of_impact
    # Head-on and 0.6 off the line through a unit sphere at rest: x(t) = -2 + 4 t meets
    # x^2 + y^2 = 1 at t = 1/4 and t = 0.3; the deepest points are the centre and 0.6 from it.
    p0 = np.array([[-2.0, 0.0, 0.0], [-2.0, 0.6, 0.0], [-2.0, 1.5, 0.0], [0.2, 0.0, 0.0], [-3.0, 0.0, 0.0]])
    p1 = p0 + [4.0, 0.0, 0.0]
    p1[4] = [-2.5, 0.0, 0.0]                             # stops short
    toi, depth = sphere_time_of_impact(p0, p1, np.zeros(3), np.zeros(3), 1.0)
    np.testing.assert_allclose(toi[:2], [0.25, 0.3], rtol=1e-14)
    np.testing.assert_allclose(depth[:3], [1.0, 0.4, -0.5], rtol=1e-14)
    assert toi[2] == np.inf and toi[3] == 0.0 and toi[4] == np.inf and depth[4] == -1.5
    # Only the relative motion counts: the same paths seen from a sphere swept by (5, -1, 2).
    shift = np.array([5.0, -1.0, 2.0])
    toi_m, depth_m = sphere_time_of_impact(p0, p1 + shift, np.zeros(3), shift, 1.0)
    np.testing.assert_allclose(toi_m, toi, rtol=1e-12)
    np.testing.assert_allclose(depth_m, depth, atol=1e-12)
    # Random motions of points and sphere against 20,001 samples of t.
    rng = np.random.default_rng(5)
    p0, p1 = rng.normal(size=(300, 3)), rng.normal(size=(300, 3))
    c0, c1, r = rng.normal(size=3) * 0.3, rng.normal(size=3) * 0.3, 0.7
    toi, depth = sphere_time_of_impact(p0, p1, c0, c1, r)
    t = np.linspace(0.0, 1.0, 20001)
    d = np.linalg.norm(p0[:, None] + t[None, :, None] * (p1 - p0)[:, None] - (c0 + t[:, None] * (c1 - c0))[None],
                       axis=2) - r                       # (300, 20001)
    # Between samples the distance changes by at most the relative speed times half a gap.
    speed = np.linalg.norm((p1 - p0) - (c1 - c0), axis=1)
    assert np.all(-d.min(axis=1) <= depth + 1e-12) and np.all(depth + d.min(axis=1) <= speed * 0.5 / 20000 + 1e-12)
    inside = d <= 0.0
    hit = inside.any(axis=1)
    assert np.array_equal(np.isfinite(toi), hit)
    first = t[np.argmax(inside, axis=1)]
    assert np.all(np.abs(toi[hit] - first[hit]) <= 1.0 / 20000 + 1e-12)


def test_swept_depth_of_capsule_matches_sampling():
    from mdss_ros.contact.colliders import make_collider
    from mdss_ros.contact.unilateral import swept_depth
    rng = np.random.default_rng(6)
    q = np.array([0.3, -0.2, 0.5, 0.8]) / np.linalg.norm([0.3, -0.2, 0.5, 0.8])
    cap = make_collider("rod", {"shape": "capsule", "radius": 0.3, "half_height": 0.5,
                                "position": [0.4, 0.1, -0.2], "orientation": q.tolist()})
    start = (np.array([-0.3, 0.2, 0.1]), q)
    p0, p1 = rng.normal(size=(200, 3)), rng.normal(size=(200, 3))
    p1[:5] = p0[:5] + (cap.position - start[0])          # at rest relative to the capsule
    depth = swept_depth(cap, start, p0, p1)
    t = np.linspace(0.0, 1.0, 4001)
    ref = np.full(len(p0), -np.inf)
    for s in t:                                          # 4001 poses of the sweep
        moved = cap.at((1 - s) * start[0] + s * cap.position, q)
        ref = np.maximum(ref, -moved.distance((1 - s) * p0 + s * p1))
    # Between samples the distance changes by at most the relative speed times half a gap.
    speed = np.linalg.norm((p1 - p0) - (cap.position - start[0]), axis=1)
    assert np.all(ref <= depth + 1e-12) and np.all(depth - ref <= speed * 0.5 / 4000 + 1e-12)
    assert (depth > 0).sum() > 20                         # some paths cross the capsule
    ball = make_collider("ball", {"shape": "sphere", "radius": 0.3})
    d_ball = swept_depth(ball, (np.ones(3), q), p0, p1)
    ref = np.max([0.3 - np.linalg.norm((1 - s) * (p0 - 1.0) + s * p1, axis=1) for s in t], axis=0)
    speed = np.linalg.norm(p1 - p0 + 1.0, axis=1)
    assert np.all(ref <= d_ball + 1e-12) and np.all(d_ball - ref <= speed * 0.5 / 4000 + 1e-12)
    with pytest.raises(ValueError):
        swept_depth(cap, (start[0], np.array([0.0, 0.0, 0.0, 1.0])), p0, p1)


def test_segment_triangle_closest_pair_matches_dense_sampling():
    from mdss_ros.contact.unilateral import segment_triangle_closest
    rng = np.random.default_rng(3)
    tri = rng.normal(size=(40, 3, 3))
    tri[:5, :, 2] = 0.0                                  # some faces parallel to the segment below
    a, b = np.array([-0.7, 0.1, 0.4]), np.array([0.9, -0.2, 0.4])
    p, d2, bary = segment_triangle_closest(a, b, tri)
    # Dense reference: 400 segment points x a 60 x 60 barycentric grid per triangle.
    s = a + np.linspace(0, 1, 400)[:, None] * (b - a)
    u, v = np.meshgrid(np.linspace(0, 1, 60), np.linspace(0, 1, 60))
    keep = (u + v) <= 1
    w = np.stack([1 - u[keep] - v[keep], u[keep], v[keep]], 1)
    for k in range(len(tri)):
        pts = w @ tri[k]
        ref = ((s[:, None, :] - pts[None, :, :]) ** 2).sum(-1).min()
        q = bary[k] @ tri[k]
        assert abs(((q - p[k]) ** 2).sum() - d2[k]) < 1e-12
        assert d2[k] <= ref + 1e-12 and np.sqrt(ref) - np.sqrt(d2[k]) < 0.03    # grid spacing bounds the gap


def test_capsule_between_vertices_is_held_by_the_face():
    """A thin capsule (r = 1 cm) lying across a coarse block (5 cm cells) between two rows
    of surface vertices, pressed 5 mm below the top: no vertex is near it, so only the
    capsule-face contacts hold it. The block pushes back and the face stays below it."""
    c = np.sqrt(0.5)
    sim = Simulator(_block_scene({"floor": {"shape": "plane"},
                                  "rod": {"shape": "capsule", "radius": 0.01, "half_height": 0.06,
                                          "position": [0.0, 0.025, 0.2], "orientation": [0, c, 0, c]}}))
    sim.step(30)                                         # settle on the floor
    for k in range(30):
        sim.set_collider_pose("rod", (0.0, 0.025, 0.1 + 0.01 - 0.015 * (k + 1) / 30), (0, c, 0, c))
        sim.step()
    assert sim.collider_wrench("rod")[2] > 0.0
    assert len(sim.contacts()) > 0
    # The deformed top face under the rod's axis is below the rod's bottom line.
    ids = sim.body.surface.vertex_ids
    tris = sim.body.surface.triangles
    t = sim.vertex_positions()[ids][tris[np.all(sim.rest_positions()[ids][tris][:, :, 2] > 0.1 - 1e-9, axis=1)]]
    bottom = sim.colliders["rod"].position[2] - 0.01
    for px in np.linspace(-0.055, 0.055, 12):
        # the top triangle straight below (px, 0.025): barycentric of its xy projection
        e1, e2, r = t[:, 1, :2] - t[:, 0, :2], t[:, 2, :2] - t[:, 0, :2], np.array([px, 0.025]) - t[:, 0, :2]
        det = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
        v = (r[:, 0] * e2[:, 1] - r[:, 1] * e2[:, 0]) / det
        w = (e1[:, 0] * r[:, 1] - e1[:, 1] * r[:, 0]) / det
        k = np.flatnonzero((v >= -1e-12) & (w >= -1e-12) & (v + w <= 1 + 1e-12))[0]
        z_face = (1 - v[k] - w[k]) * t[k, 0, 2] + v[k] * t[k, 1, 2] + w[k] * t[k, 2, 2]
        assert z_face <= bottom + 1e-4, (px, z_face, bottom)


def _pressed_block(kind, reach, **model):
    """A bottom-pinned block pressed 5 mm by a sphere (r = 4 cm) over 40 steps; the
    sphere's reaction force z after 60 steps and the simulator."""
    ball = {"shape": "sphere", "radius": 0.04, "position": [0, 0, 0.2]}
    if reach:
        ball["reach"] = {"sphere": {"center": [0, 0, 0.1], "radius": 0.06}}
    scene = _block_scene({"ball": ball}, kind=kind, **model)
    scene["pins"] = [{"box": [[-1, -1, -1e-6], [1, 1, 1e-6]]}]
    sim = Simulator(scene)
    for k in range(60):
        sim.set_collider_pose("ball", (0, 0, 0.14 - 0.005 * min(1, (k + 1) / 40)))
        sim.step()
    return sim.collider_wrench("ball")[2], sim


def test_collider_reach_becomes_a_full_space_domain():
    """A collider's `reach` region is simulated in full space inside the reduced body: the
    indentation force comes within 25 % of full-space FEM, where the modes alone (2 domains
    x 10 modes, no residual compliance) are several times too stiff. The default residual
    compliance, with no region drawn, comes closer still (measured +3.4 % against the
    reach's +18 %)."""
    reduced = dict(domains={"count": 2}, modes=10, cubature={"samples": 0})
    f_full, _ = _pressed_block("full", False)
    f_modes, _ = _pressed_block("reduced", False, contact_compliance=0, **reduced)
    f_reach, sim = _pressed_block("reduced", True, **reduced)
    f_res, _ = _pressed_block("reduced", False, **reduced)
    assert sim.model.partition.names == ["domain_0", "domain_1", "ball_reach"]
    assert [k for k, _ in sim.model.domain_kind] == ["sub", "sub", "full"]
    assert sim.model.compliance is None                # a full-space domain: no residual built
    assert f_full > 0
    err_modes, err_reach, err_res = (abs(f / f_full - 1) for f in (f_modes, f_reach, f_res))
    assert err_reach < 0.25 and err_reach < err_modes / 4, (f_full, f_modes, f_reach)
    assert err_res < 0.05 and err_res < err_reach, (f_full, f_res, f_reach)


def test_a_reach_region_selecting_nothing_is_a_scene_error():
    from mdss_ros.errors import SceneError
    scene = _block_scene({"ball": {"shape": "sphere", "radius": 0.04, "position": [0, 0, 0.2],
                                   "reach": {"sphere": {"center": [5, 5, 5], "radius": 0.01}}}},
                         kind="reduced", domains={"count": 2}, modes=6, cubature={"samples": 0})
    with pytest.raises(SceneError, match="colliders.ball.reach: the region selects no vertex"):
        Simulator(scene)


@pytest.mark.parametrize("sparse", [False, True])
def test_working_set_contact_correction_equals_full_lcp(sparse):
    """contact_correction solves only for rows that can be active, yet gives the LCP on
    all candidate rows: same multipliers and correction as solve_lcp with every row."""
    import scipy.sparse as sp
    from mdss_ros.contact.unilateral import contact_correction
    rng = np.random.default_rng(3)
    n, m = 60, 40
    B = rng.normal(size=(n, n))
    A = B @ B.T + n * np.eye(n)
    C = np.zeros((m, n))
    for i in range(m):                                   # vertex-like rows: 3 DOFs each
        cols = rng.choice(n, 3, replace=False)
        C[i, cols] = rng.normal(size=3)
    g = rng.normal(size=m) + 0.3                         # some rows violated, most not
    solves = []

    def resolve(rhs):
        solves.append(rhs.shape[1])
        return np.linalg.solve(A, rhs)

    lam, corr, info = contact_correction(resolve, sp.csr_matrix(C) if sparse else C, g)
    Y = np.linalg.solve(A, C.T)
    lam_ref, _ = solve_lcp(C @ Y, g)
    np.testing.assert_allclose(lam, lam_ref, atol=1e-10)
    np.testing.assert_allclose(corr, Y @ lam_ref, atol=1e-10)
    w = C @ corr + g
    assert np.all(w >= -1e-10) and np.all(lam >= 0) and abs(lam @ w) < 1e-9
    assert info["active"] > 0 and sum(solves) == info["working_set"] < m


def test_working_set_contact_correction_without_violation_solves_nothing():
    from mdss_ros.contact.unilateral import contact_correction
    lam, corr, info = contact_correction(lambda b: pytest.fail("no solve expected"), np.eye(3), np.ones(3))
    assert not lam.any() and not corr.any() and info["working_set"] == 0


def test_sphere_face_contacts_can_be_turned_off():
    """A sphere touching a triangle's interior (between its vertices) gets a face contact
    by default and none with face_contacts: false (vertex contacts only)."""
    from mdss_ros.contact.colliders import make_collider
    from mdss_ros.contact.unilateral import find_triangle_contacts
    from mdss_ros.errors import SceneError
    tri = np.array([[0, 1, 2]])
    pos = np.array([[-1.0, -1.0, 0.0], [1.0, -1.0, 0.0], [0.0, 1.0, 0.0]])
    spec = {"shape": "sphere", "radius": 0.1, "position": [0.0, -0.2, 0.09]}
    on = find_triangle_contacts([make_collider("ball", spec)], pos, tri, margin=0.05)
    off = find_triangle_contacts([make_collider("ball", dict(spec, face_contacts=False))], pos, tri, margin=0.05)
    assert len(on[0]) == 1 and abs(on[3][0] + 0.01) < 1e-12
    assert len(off[0]) == 0
    with pytest.raises(SceneError, match="face_contacts"):
        make_collider("ball", dict(spec, face_contacts="no"))
    with pytest.raises(SceneError, match="unknown key"):
        make_collider("floor", {"shape": "plane", "face_contacts": False})


def test_reduced_newton_with_contact_stops_at_tolerance():
    """The Newton loop of a reduced step in contact measures its residual net of the contact
    forces (C^T lam), so a body resting on the floor converges before max iterations."""
    scene = _block_scene({"floor": {"shape": "plane"}}, kind="reduced", domains={"count": 2}, modes=10,
                         full_space_domains=["domain_1"], cubature={"samples": 0},
                         integrator={"dt": 10.0, "newton_iterations": 10, "tolerance": 1e-6})
    sim = Simulator(scene)
    weight = sim.model.vertex_mass.sum() * 9.81
    sim.step(3)
    assert sim.stats()["newton_iterations"] < 10
    assert abs(-sim.collider_wrench("floor")[2] - weight) < 0.01 * weight


@pytest.mark.parametrize("kind", ["full", "reduced"])
def test_static_press_from_rest_converges_to_the_tolerance(kind):
    """A body at rest pushed only by a sphere (no gravity, no loads) starts Newton with a
    zero residual; the tolerance is then measured against the contact forces' size, so the
    step stops as soon as the residual net of the contact forces is below it (not after
    max iterations or a round-off-sized update)."""
    model = {"integrator": {"dt": 10.0, "newton_iterations": 12, "tolerance": 1e-6}}
    if kind == "reduced":
        model.update(kind="reduced", domains={"count": 2}, modes=10, cubature={"samples": 0},
                     full_space_domains=["domain_0", "domain_1"])
    scene = _block_scene({"ball": {"shape": "sphere", "radius": 0.1, "position": [0.0, 0.0, 0.198],
                                   "face_contacts": False}}, **model)
    scene["gravity"] = [0.0, 0.0, 0.0]
    scene["pins"] = [{"box": [[-1, -1, -1e-6], [1, 1, 1e-6]]}]
    from mdss_ros.contact.colliders import ColliderInsideWarning
    with pytest.warns(ColliderInsideWarning, match="2.0 mm deep"):    # started 2 mm in, on purpose
        sim = Simulator(scene)
    sim.step()
    st = sim.stats()
    assert sim.collider_wrench("ball")[2] > 0
    assert st["newton_iterations"] <= 4, st
    if kind == "full":
        assert 0.0 < st["residual"] <= 1e-6


def test_sphere_resting_on_a_floor_supported_block_floor_carries_the_weight():
    """A kinematic sphere brought to rest on the top of a block that stands on a floor, under
    gravity: the sphere touches (20 um into the settled top), the block is in equilibrium
    between floor and sphere, the floor's reaction equals the block's weight to 1 %, and
    nothing penetrates either collider."""
    sim = Simulator(_block_scene({"floor": {"shape": "plane"},
                                  "ball": {"shape": "sphere", "radius": 0.04, "position": [0, 0, 0.3]}}))
    weight = sim.model.vertex_mass.sum() * 9.81
    sim.step(150)                                            # the block settles on the floor
    x = sim.vertex_positions()
    centre = np.argmin(np.linalg.norm(sim.rest_positions() - (0.0, 0.0, 0.1), axis=1))
    sim.set_collider_pose("ball", (0.0, 0.0, x[centre, 2] + 0.04 - 2e-5))
    sim.step(100)
    floor, ball = sim.collider_wrench("floor"), sim.collider_wrench("ball")
    assert ball[2] > 0.0 and len(sim.contacts()) > 0            # the sphere does touch the block
    assert abs(-floor[2] - weight - ball[2]) < 1e-6 * weight    # at rest: floor = weight + sphere load
    assert abs(-floor[2] - weight) < 0.01 * weight
    x = sim.vertex_positions()
    for name in ("floor", "ball"):
        assert sim.colliders[name].signed_distance(x)[0].min() > -1e-6


def _rss_mb():
    with open("/proc/self/status") as f:
        return next(int(line.split()[1]) / 1024 for line in f if line.startswith("VmRSS:"))


@pytest.mark.parametrize("kind", ["full", "reduced"])
def test_memory_stays_flat_while_a_sphere_squeezes_the_block(kind, monkeypatch):
    """Issue 18, bad input: a 192K-tet block pressed by a sphere grew from 4.9 to 15 GB.
    The cause was a sparse factorisation that failed (the squeezed body's tangent is
    indefinite) dropping its PARDISO solver without freeing MKL's memory (CHANGELOG,
    session 7). Here a 1e4 Pa block is squeezed 8 cm deep by a sphere that also wobbles
    sideways, so the contact set changes every step and the full model's factorisation
    fails on most steps; over the last 30 of 60 steps the process's resident memory must
    not grow by 25 MB (measured: under 1 MB, full and reduced; with the old drop emulated,
    a failed factorisation's solver discarded unfreed, the full model grew 120 MB)."""
    from mdss_ros import linear_solver as ls
    failed = []
    factor = ls.SparseSolver.factor

    def counting(self, *args, **kwargs):
        try:
            return factor(self, *args, **kwargs)
        except ls.NotPositiveDefinite:
            failed.append(1)
            raise
    monkeypatch.setattr(ls.SparseSolver, "factor", counting)
    # Every step tries the exact tangent first (projection auto probes every 8th step of a
    # projected run otherwise), so the failing path is taken on most steps.
    from mdss_ros.fem import backward_euler
    monkeypatch.setattr(backward_euler, "PROBE_EVERY", 1)
    scene = _block_scene({"floor": {"shape": "plane"},
                          "ball": {"shape": "sphere", "radius": 0.04, "position": [0.0, 0.0, 0.2]}}, kind=kind)
    scene["body"]["material"]["young"] = 1e4
    if kind == "reduced":
        scene["model"].update({"domains": {"count": 2}, "modes": 10, "cubature": {"samples": 0}})
    sim = Simulator(scene)
    for k in range(60):
        sim.set_collider_pose("ball", (0.01 * np.sin(k / 7), 0.0, 0.14 - 0.08 * min(k + 1, 30) / 30))
        sim.step()
        if k == 29:
            before, failed_before = _rss_mb(), len(failed)
    assert len(sim.contacts()) >= 10                      # in contact (full 87, reduced 15 at the end)
    if kind == "full":
        assert len(failed) - failed_before >= 10          # the path that leaked is taken
    assert _rss_mb() - before < 25.0
