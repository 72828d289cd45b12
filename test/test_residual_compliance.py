"""The residual contact compliance (mdss_ros/reduced/residual_compliance.py).

Kernel checks against finite differences and dense linear algebra on small bodies, and
the contact force of a pressed block against full-space FEM."""
import numpy as np
import pytest

from mdss_ros import Simulator
from mdss_ros.fem.force_model import FEMForceModel
from mdss_ros.reduced.modal_basis import rigid_modes
from mdss_ros.reduced.residual_compliance import ResidualCompliance, build_residual_compliance, kinematics_at_rest
from mdss_ros.rotations import exp_so3_batch


def _block(pins, colliders=None, **model):
    scene = {"name": "block",
             "body": {"mesh": {"generator": "box", "size": [0.08, 0.08, 0.04], "cell": 0.01,
                               "origin": [-0.04, -0.04, 0.0]},
                      "material": {"model": "neohookean", "young": 1e5, "poisson": 0.3, "density": 1000},
                      "damping": {"alpha": 2.0, "beta": 0.0}},
             "colliders": colliders or {"ball": {"shape": "sphere", "radius": 0.02, "position": [0, 0, 0.07]}},
             "model": dict({"kind": "reduced", "domains": {"count": 2}, "modes": 8, "cubature": {"samples": 0}},
                           **model)}
    if pins:
        scene["pins"] = [{"box": [[-1, -1, -1e-6], [1, 1, 1e-6]]}]
    return scene


@pytest.mark.parametrize("pinned", [True, False])
def test_kinematics_at_rest_are_the_derivatives_of_the_positions(pinned):
    """J's columns: central differences of the reconstructed positions in each modal
    coordinate, frame translation and frame rotation (exp of a small angle)."""
    sim = Simulator(_block(pinned))
    m = sim.model
    L = m.layout
    J = kinematics_at_rest(L, m.n_gen, len(m.body.vertices)).toarray()
    ids = np.arange(len(m.body.vertices))
    eps = 1e-6
    for d in range(L.D):
        for j in range(L.r[d]):
            q = m.q.copy()
            q[d, j] = eps
            xp = m.positions_of(ids, q=q)
            q[d, j] = -eps
            xm = m.positions_of(ids, q=q)
            np.testing.assert_allclose((xp - xm).ravel() / (2 * eps), J[:, L.q_index[d, j]], atol=1e-7)
    for k, d in enumerate(L.movers):
        for b in range(3):
            for which, cols in (("c", L.lin_index), ("R", L.ang_index)):
                out = []
                for s in (eps, -eps):
                    frames = m.frames.copy()
                    if which == "c":
                        frames.c[d, b] += s
                    else:
                        frames.R[d] = exp_so3_batch(s * np.eye(3)[b][None])[0] @ frames.R[d]
                    out.append(m.positions_of(ids, frames=frames))
                np.testing.assert_allclose((out[0] - out[1]).ravel() / (2 * eps), J[:, cols[k, b]], atol=1e-7)
    assert pinned or len(L.movers) > 0


@pytest.mark.parametrize("pinned", [True, False])
def test_residual_compliance_is_full_minus_reduced_static_compliance(pinned):
    """C_res equals the dense formula E^T (K^+ - J (J^T K J)^+ J^T) P E with both answers
    taken M-orthogonal to the rigid modes (a floating body: inertia relief), and it is
    symmetric positive semi-definite."""
    sim = Simulator(_block(pinned))
    m = sim.model
    body = m.body
    cand = m.compliance.vertices[:12]
    comp = build_residual_compliance(body, m.layout, m.n_gen, m.vertex_mass, cand)
    fem = FEMForceModel(body.vertices, body.tets, body.material, pinned=body.pinned)
    K = fem.pattern.matrix(fem.tangent(body.vertices)[2]).toarray()
    free = np.flatnonzero(fem.pattern.free_dof >= 0)
    J = kinematics_at_rest(m.layout, m.n_gen, len(body.vertices)).toarray()[free]
    mass = np.repeat(m.vertex_mass, 3)[free]
    E = np.zeros((len(free), 3 * len(cand)))
    E[fem.pattern.free_dof[(3 * cand[:, None] + np.arange(3)).ravel()], np.arange(3 * len(cand))] = 1.0
    if pinned:
        P = np.eye(len(free))
        proj = np.eye(len(free))
    else:
        R = rigid_modes(body.vertices, m.vertex_mass)
        P = np.eye(len(free)) - (mass[:, None] * R) @ R.T
        proj = np.eye(len(free)) - R @ (R.T * mass)
    u = proj @ np.linalg.pinv(K, rcond=1e-10, hermitian=True) @ P @ E
    u_r = proj @ J @ np.linalg.pinv(J.T @ K @ J, rcond=1e-10, hermitian=True) @ J.T @ P @ E
    expected = E.T @ (u - u_r)
    scale = np.abs(expected).max()
    np.testing.assert_allclose(comp.C, 0.5 * (expected + expected.T), atol=1e-8 * scale)
    assert np.linalg.eigvalsh(comp.C).min() > -1e-10 * scale
    assert comp.info["clipped"] < 1e-8
    # The modes carry some of the compliance, never more than all of it.
    assert 0.0 < comp.info["diagonal_ratio"] < 1.0


def _press(kind, depth, **model):
    """Reaction (N) on a flat punch (a box 3 x 3 cm) held `depth` into the top of a
    bottom-pinned block after a slow press; the simulator. A punch presses nine vertices
    (a sphere on this coarse mesh would touch one: a point load, whose answer depends on
    which faces it meets)."""
    scene = _block(True, {"ball": {"shape": "box", "half_extents": [0.015, 0.015, 0.02],
                                   "position": [0, 0, 0.07]}}, kind=kind, **model)
    scene["model"]["integrator"] = {"dt": 0.01, "newton_iterations": 2}
    # No gravity: the modes' own error under the body's weight (a sag of 0.1 mm here, the
    # size of the press) is not the contact's.
    scene["gravity"] = [0.0, 0.0, 0.0]
    sim = Simulator(scene)
    top = 0.04
    for k in range(80):
        sim.set_collider_pose("ball", (0.0, 0.0, top + 0.02 - depth * min(1.0, (k + 1) / 50)))
        sim.step()
    return float(sim.collider_wrench("ball")[2]), sim


@pytest.mark.claims
def test_residual_compliance_brings_a_shallow_press_to_the_full_fem_force():
    """A 0.3 mm press (linear regime): with the residual compliance the reduced block
    (2 domains x 8 modes) reads the full-space FEM's force within 3 %; its modes alone read
    it several times too high. The dented vertices do not enter the punch."""
    f_full, _ = _press("full", 3e-4)
    f_res, sim = _press("reduced", 3e-4)
    f_modes, _ = _press("reduced", 3e-4, contact_compliance=0)
    assert f_full > 0
    assert abs(f_res / f_full - 1.0) < 0.03, (f_full, f_res, f_modes)
    assert f_modes / f_full > 2.0, (f_full, f_modes)
    x = sim.vertex_positions()
    phi = sim.colliders["ball"].signed_distance(x)[0]
    assert phi.min() > -2e-6                    # the dent follows the sphere (linearised gap)
    undented = sim.model.positions_of(np.arange(len(x)), dent=False)
    assert sim.colliders["ball"].signed_distance(undented)[0].min() < -1e-4   # the modes alone would enter it


def test_a_collider_driven_deep_in_one_step_dents_no_more_than_the_margin():
    """The punch driven 15 mm into the 4 cm block in one step: the residual compliance alone
    would take 11.8 mm of it as a dent; limit_dent caps every vertex's dent at the contact
    margin (a mean surface edge, 1.1 cm here) and the modes carry the rest."""
    scene = _block(True, {"ball": {"shape": "box", "half_extents": [0.015, 0.015, 0.02],
                                   "position": [0, 0, 0.061]}})
    sim = Simulator(scene)
    sim.step()
    sim.set_collider_pose("ball", (0.0, 0.0, 0.045))
    sim.step()
    margin = sim._contact_spec()["margin"]
    dent = np.linalg.norm(sim.model._dent, axis=1).max()
    assert 0.5 * margin < dent <= margin * (1 + 1e-9), (dent, margin)
    assert sim.model._contact_compliance.scale < 1.0
    assert sim.collider_wrench("ball")[2] > 0


def test_the_dent_is_state_a_snapshot_restores():
    """get_state / set_state carry the dent: a rolled-back step repeats bit for bit."""
    _, sim = _press("reduced", 3e-4)
    state = sim.model.get_state()
    x0 = sim.vertex_positions().copy()
    sim.step()
    x1 = sim.vertex_positions().copy()
    sim.model.set_state(state)
    np.testing.assert_array_equal(sim.vertex_positions(), x0)
    sim.step()
    np.testing.assert_array_equal(sim.vertex_positions(), x1)


def test_energy_is_the_vertex_sums_with_the_dent():
    """Simulator.energy, from the reduced coordinates with the dent's share added on its
    candidates, equals the sums over every vertex of 1/2 m |v|^2 and -m g . x (positions
    and velocities as the model outputs them, dent included) with the frames moving and
    turning; the dent's share is far above round-off here."""
    # A free block on a floor, a ball held 1 mm into its top: the ball's candidates dent.
    sim = Simulator(_block(False, {"floor": {"shape": "plane"},
                                   "ball": {"shape": "sphere", "radius": 0.02, "position": [0, 0, 0.062]}}))
    for k in range(30):
        sim.set_collider_pose("ball", (0.0, 0.0, 0.06 - 1e-3 * min(1.0, (k + 1) / 10)))
        sim.step()
    m = sim.model
    movers = m.layout.movers
    assert m._dent.any() and len(movers)
    rng = np.random.default_rng(3)
    m.frames.v[movers] = rng.standard_normal((len(movers), 3))
    m.frames.w[movers] = rng.standard_normal((len(movers), 3))
    sim.gravity = np.array([0.3, -0.2, -9.81])
    e = sim.energy()
    x, v = m.vertex_positions(), m.vertex_velocities()
    kinetic = 0.5 * float((m.vertex_mass * (v * v).sum(1)).sum())
    gravity = -float((m.vertex_mass * (x @ sim.gravity)).sum())
    assert e["kinetic"] == pytest.approx(kinetic, rel=1e-12)
    assert e["gravity"] == pytest.approx(gravity, rel=1e-12)
    assert e["elastic"] == m.elastic_energy()
    dk, dg = m._dent_energies(sim.gravity)
    assert abs(dk) > 1e-9 * kinetic and abs(dg) > 1e-9 * abs(gravity), (dk, dg)


def test_contact_compliance_products_are_the_dense_formulas():
    """ContactCompliance keeps G dense on the columns its rows touch and reads C in place;
    its block, apply, dent and shift equal s G C G^T, s G C G[b]^T lam, s C G^T lam and
    G dent with G (rows, 3 n_c) written out one corner at a time. Corners off the
    candidate set add nothing; a face's three corners share a contact row."""
    rng = np.random.default_rng(7)
    n_c, n_verts, r, m = 12, 20, 3, 5
    A = rng.standard_normal((3 * n_c, 3 * n_c))
    C = A @ A.T
    candidates = np.arange(4, 4 + n_c)
    domain = rng.integers(0, 2, n_c)
    comp = ResidualCompliance.on(candidates, domain, C, n_verts, {})
    R = exp_so3_batch(rng.standard_normal((2, 3)))
    # Five contacts: vertex contacts and faces (three corners), some corners not candidates.
    verts = np.array([5, 0, 7, 9, 15, 6, 1, 12, 13, 2])
    row_of = np.array([0, 1, 2, 2, 2, 3, 3, 3, 4, 4])
    dirs = rng.standard_normal((len(verts), r, 3))
    cc = comp.rows(dirs, verts, row_of, m, R)
    G = np.zeros((m * r, 3 * n_c))
    for i, v in enumerate(verts):
        k = comp.index[v]
        if k >= 0:
            G[row_of[i] * r + np.arange(r)[:, None], 3 * k + np.arange(3)] += dirs[i] @ R[domain[k]]
    s = 0.4
    cs = cc.scaled(s)
    a, b = np.array([0, 4, 7, 13]), np.array([2, 3, 7, 11, 14])
    lam = rng.uniform(0.0, 1.0, len(b))
    lam[1] = 0.0
    np.testing.assert_allclose(cs.block(a, b), s * G[a] @ C @ G[b].T, rtol=1e-12, atol=1e-12 * np.abs(C).max())
    np.testing.assert_allclose(cs.apply(b, lam), s * G @ C @ G[b].T @ lam, rtol=1e-12,
                               atol=1e-12 * np.abs(C).max())
    lam_all = rng.uniform(0.0, 1.0, m * r)
    lam_all[:r] = 0.0
    dent = cs.dent(lam_all)
    np.testing.assert_allclose(dent, (s * C @ G.T @ lam_all).reshape(-1, 3), rtol=1e-12,
                               atol=1e-12 * np.abs(C).max())
    assert cs.dent(lam_all.copy()) is dent                  # kept for the same forces
    np.testing.assert_allclose(cs.shift(dent), G @ dent.ravel(), rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(cc.normal().block(np.arange(m), np.arange(m)), G[0::r] @ C @ G[0::r].T,
                               rtol=1e-12, atol=1e-12 * np.abs(C).max())
    keep = np.array([0, 1, 2, 9, 10, 11])
    np.testing.assert_allclose(cc.take(keep).block(np.arange(6), np.arange(6)), G[keep] @ C @ G[keep].T,
                               rtol=1e-12, atol=1e-12 * np.abs(C).max())
    assert comp.rows(dirs[1:2], verts[1:2], np.zeros(1, dtype=np.int64), 1, R) is None   # vertex 0: no candidate


def test_candidates_are_the_surface_vertices_nearest_the_collider_paths():
    """The set follows the timeline's poses, holds no pinned vertex, and is capped."""
    scene = _block(True, contact_compliance=30)
    scene["timeline"] = [{"t": 0.1, "topic": "collider_pose", "name": "ball", "position": [0.03, 0.0, 0.055]}]
    sim = Simulator(scene)
    comp = sim.model.compliance
    assert comp.n == 30
    X = sim.body.vertices[comp.vertices]
    assert not np.isin(comp.vertices, sim.body.pinned).any()
    assert np.all(X[:, 2] >= 0.03 - 1e-9)                 # the top and its edge, where the ball goes
    assert X[:, 0].max() > 0.02                          # ... along its path to x = 3 cm
    assert any("residual compliance" in line for line in sim.explain())


def test_no_colliders_builds_no_compliance():
    scene = _block(True)
    scene["colliders"] = {}
    assert Simulator(scene).model.compliance is None


# ------------------------------------------------------------- contact modes (the anchors)
@pytest.mark.parametrize("pinned", [True, False])
def test_static_contact_modes_hold_the_full_static_answer(pinned):
    """One domain with all 3 n_c static contact modes: the Galerkin answer of the reduced
    model to any load on the candidates, J (J^T K J)^+ J^T P f, is the full-space FEM's
    K^+ P f on every DOF (both M-orthogonal to the rigid modes when floating); the basis
    stays M-orthonormal, and a movable domain's stays free of rigid motion."""
    from mdss_ros.reduced.contact_modes import add_contact_modes
    n_c = 4
    sim = Simulator(_block(pinned, domains={"count": 1}, contact_compliance=0,
                           contact_modes={"kind": "static", "vertices": n_c, "count": 3 * n_c}))
    m = sim.model
    body = m.body
    cand = np.asarray(m.contact_mode_vertices)
    assert len(cand) == n_c and m.subspace[0].U.shape[1] == 8 + 3 * n_c
    assert any("static contact modes" in line for line in sim.explain())
    fem = FEMForceModel(body.vertices, body.tets, body.material, pinned=body.pinned)
    K = fem.pattern.matrix(fem.tangent(body.vertices)[2]).toarray()
    free = np.flatnonzero(fem.pattern.free_dof >= 0)
    J = kinematics_at_rest(m.layout, m.n_gen, len(body.vertices)).toarray()[free]
    mass = np.repeat(m.vertex_mass, 3)[free]
    rng = np.random.default_rng(2)
    f = np.zeros(len(free))
    f[fem.pattern.free_dof[(3 * cand[:, None] + np.arange(3)).ravel()]] = rng.normal(size=3 * n_c)
    P = proj = np.eye(len(free))
    if not pinned:
        R = rigid_modes(body.vertices, m.vertex_mass)
        P = np.eye(len(free)) - (mass[:, None] * R) @ R.T
        proj = np.eye(len(free)) - R @ (R.T * mass)
    u = proj @ np.linalg.pinv(K, rcond=1e-10, hermitian=True) @ P @ f
    u_r = proj @ J @ np.linalg.pinv(J.T @ K @ J, rcond=1e-10, hermitian=True) @ J.T @ P @ f
    np.testing.assert_allclose(u_r, u, atol=1e-7 * np.abs(u).max())
    dom = m.subspace[0]
    md = np.repeat(dom.mass, 3)
    np.testing.assert_allclose(dom.U.T @ (md[:, None] * dom.U), np.eye(dom.U.shape[1]), atol=1e-9)
    if not pinned:
        Rd = rigid_modes(dom.r_local, dom.mass)
        assert np.abs(Rd.T @ (md[:, None] * dom.U)).max() < 1e-9
    # Without the contact modes the same load is answered far from exactly.
    base = Simulator(_block(pinned, domains={"count": 1}, contact_compliance=0)).model
    J0 = kinematics_at_rest(base.layout, base.n_gen, len(body.vertices)).toarray()[free]
    u0 = proj @ J0 @ np.linalg.pinv(J0.T @ K @ J0, rcond=1e-10, hermitian=True) @ J0.T @ P @ f
    assert np.linalg.norm(u0 - u) > 0.3 * np.linalg.norm(u)
    # Fewer directions than fields: count is a cap.
    fewer, _ = add_contact_modes(base.subspace, body, base.vertex_mass, cand,
                                 {"kind": "static", "count": 5, "radius": 0.0})
    assert fewer[0].U.shape[1] == 8 + 5


def test_local_contact_modes_are_patch_answers_with_compact_support():
    """Each local field solves K u = e on the patch's free DOFs and is zero on every vertex
    farther than the radius from all candidates (held there)."""
    from mdss_ros.reduced.contact_modes import local_responses
    from mdss_ros.reduced.residual_compliance import static_responses
    sim = Simulator(_block(True, contact_compliance=0))
    body = sim.model.body
    top = np.flatnonzero(np.isclose(body.vertices[:, 2], 0.04))
    cand = top[np.argsort(np.linalg.norm(body.vertices[top, :2], axis=1))[:3]]
    radius = 0.021
    fields, patch = local_responses(body, sim.model.vertex_mass, cand, radius)
    X = body.vertices
    far = np.linalg.norm(X[:, None] - X[cand][None], axis=2).min(axis=1) > radius
    assert 0 < patch < len(X) and patch == int((~far).sum())
    assert np.abs(fields.reshape(len(X), 3, -1)[far]).max() == 0.0
    fem = FEMForceModel(X, body.tets, body.material)
    K = fem.pattern.matrix(fem.tangent(X)[2]).toarray()                 # no pins: every DOF
    held = np.zeros(len(X), dtype=bool)
    held[body.pinned] = True
    inside = np.repeat(~far & ~held, 3)
    E = np.zeros((3 * len(X), 3 * len(cand)))
    E[(3 * cand[:, None] + np.arange(3)).ravel(), np.arange(3 * len(cand))] = 1.0
    np.testing.assert_allclose((K @ fields)[inside], E[inside], atol=1e-9 * np.abs(K @ fields).max())
    # A patch that covers a floating body holds nothing: the static family's answers.
    free = Simulator(_block(False, contact_compliance=0)).model
    whole, patch = local_responses(free.body, free.vertex_mass, cand, 1.0)
    assert patch == len(X) and len(free.body.pinned) == 0
    np.testing.assert_array_equal(whole, static_responses(free.body, free.vertex_mass, cand)[0])


def test_static_contact_modes_bring_a_shallow_press_to_the_full_fem_force():
    """The punch's nine vertices' 27 static fields in the subspace, no residual compliance:
    the 0.3 mm press reads the full-space FEM's force within 3 %, like the residual
    compliance (test above)."""
    f_full, _ = _press("full", 3e-4)
    f_modes, sim = _press("reduced", 3e-4, contact_compliance=0,
                          contact_modes={"kind": "static", "vertices": 9, "count": 27})
    assert sim.model.compliance is None
    assert abs(f_modes / f_full - 1.0) < 0.03, (f_full, f_modes)


def test_interface_modes_hold_the_static_answer_to_interface_loads():
    """model.basis.interface_modes: every domain gets the static answers to unit loads on
    the coupling elements' free vertices. With all of them, the Galerkin answer of the
    two-domain block to any load on those vertices is the full-space FEM's on every DOF
    (each vertex belongs to one domain, so each domain's share of a field is in its span);
    with none it is far off."""
    base = Simulator(_block(True, contact_compliance=0)).model
    body = base.body
    iface = np.setdiff1d(np.unique(body.tets[base.c_tets]), body.pinned)
    n = 3 * len(iface)
    sim = Simulator(_block(True, contact_compliance=0, basis={"interface_modes": n}))
    m = sim.model
    # Fewer than n directions a domain are independent (rank of the fields on its vertices).
    assert all(8 < d.U.shape[1] <= 8 + n for d in m.subspace)
    assert any("static interface modes" in line for line in sim.explain())
    fem = FEMForceModel(body.vertices, body.tets, body.material, pinned=body.pinned)
    K = fem.pattern.matrix(fem.tangent(body.vertices)[2]).toarray()
    free = np.flatnonzero(fem.pattern.free_dof >= 0)
    f = np.zeros(len(free))
    f[fem.pattern.free_dof[(3 * iface[:, None] + np.arange(3)).ravel()]] = np.random.default_rng(4).normal(size=n)
    u = np.linalg.solve(K, f)

    def galerkin(model):
        J = kinematics_at_rest(model.layout, model.n_gen, len(body.vertices)).toarray()[free]
        return J @ np.linalg.solve(J.T @ K @ J, J.T @ f)

    np.testing.assert_allclose(galerkin(m), u, atol=1e-7 * np.abs(u).max())
    assert np.linalg.norm(galerkin(base) - u) > 0.2 * np.linalg.norm(u)
    from mdss_ros.errors import SceneError
    with pytest.raises(SceneError, match="interface_modes"):
        Simulator(_block(True, basis={"interface_modes": -1}))
