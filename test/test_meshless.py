"""The meshless model (`model.kind: meshless`, mdss_ros/meshless, docs/method.md §19).

Small meshes, each test a few seconds: the kernel, the MLS patch test, forces and
stiffness as exact derivatives of the discrete energy, momentum, pins, the cantilever
against its closed form, and the Simulator API with contact and both integrators.
"""
from types import SimpleNamespace

import numpy as np
import pytest
import scipy.linalg

from mdss_ros import Simulator
from mdss_ros.body import build_body
from mdss_ros.errors import SceneError
from mdss_ros.linear_solver import SparseSolver
from mdss_ros.mesh import box
from mdss_ros.mesh.surface import boundary_faces
from mdss_ros.meshless.mls import kernel, kernel_derivative
from mdss_ros.meshless.forces import stvk_volume
from mdss_ros.meshless.integration import boundary_vectors
from mdss_ros.meshless.model import build_forces
from mdss_ros.model_build import build_model
from mdss_ros.scene import load_scene
from mdss_ros.verify.closed_forms import cantilever_gravity_sag

SIZE = np.array([0.3, 0.2, 0.2])


MATERIAL = SimpleNamespace(mu=3.8e5, lam=5.8e5, density=1000.0)


def _cloud(cell=0.05, perturb=0.15, seed=0):
    """Box mesh with interior nodes moved by up to perturb * cell (an irregular cloud; the
    tets stay positive): (mesh, interior mask (n,))."""
    mesh = box(SIZE, cell)
    X = mesh.vertices.copy()
    inner = np.all((X > 1e-9) & (X < SIZE - 1e-9), axis=1)
    X[inner] += perturb * cell * np.random.default_rng(seed).uniform(-1, 1, (inner.sum(), 3))
    return SimpleNamespace(vertices=X, tets=mesh.tets, triangles=boundary_faces(mesh.tets)), inner


def _forces(mesh, kv=0.3, pinned=(), **settings):
    """The model's own force build (model.build_forces) with the scene defaults unless given."""
    fm, _ = build_forces(mesh.vertices, mesh.tets, mesh.triangles, MATERIAL,
                            dict(settings, volume_stiffness=kv), pinned)
    return fm


def _deformed(X, seed=1, amp=0.02):
    """A smooth large deformation (bend, twist, stretch) plus small noise."""
    rng = np.random.default_rng(seed)
    x = X.copy()
    x[:, 2] += 0.3 * X[:, 0] ** 2
    x[:, 1] += 0.2 * X[:, 0] * X[:, 2]
    x[:, 0] *= 1.1
    return x + amp * 0.05 * rng.standard_normal(X.shape)


def test_kernel_and_its_derivative():
    r = np.linspace(0.0, 1.3, 131)
    w, dw = kernel(r), kernel_derivative(r)
    assert w[0] == 1.0 and dw[0] == 0.0
    assert np.all(w[r >= 1.0] == 0.0) and np.all(dw[r >= 1.0] == 0.0)
    assert abs(kernel(1.0 - 1e-9)) < 1e-15 and abs(kernel_derivative(1.0 - 1e-9)) < 1e-8     # C1 at r = 1
    assert np.all(np.diff(w[r <= 1.0]) < 0)                                                 # decreasing
    h = 1e-6
    inside = r[(r > 0.01) & (r < 0.99)]
    fd = (kernel(inside + h) - kernel(inside - h)) / (2 * h)
    assert np.abs(fd - kernel_derivative(inside)).max() < 1e-8


@pytest.mark.parametrize("integration", ["consistent", "nodal"])
def test_mls_gradient_is_exact_for_a_linear_field(integration):
    """Patch test, gradient part: u = G X + t gives grad u_i = G at every node (boundary
    nodes included) on an irregular cloud, and the net internal force is zero; the
    consistent correction keeps this (its constraints), the raw MLS fit has it by itself."""
    mesh, _ = _cloud()
    X = mesh.vertices
    fm = _forces(mesh, integration=integration)
    G = np.random.default_rng(2).normal(size=(3, 3)) * 1e-3
    u = X @ G.T + np.array([0.1, -0.2, 0.3])
    assert np.abs(fm.op.gradients(u) - G).max() < 1e-12
    assert fm.op.floored == 0 and fm.op.cond.max() < 1e3
    _, f = fm.forces(X + u)
    assert np.abs(f.sum(0)).max() < 1e-9 * np.abs(f).max()


def _uniform_stress_forces(integration):
    """Nodal forces (n, 3) under a large uniform deformation F = I + G, the first Piola
    stress P (3, 3) there, the mesh and its interior mask."""
    mesh, inner = _cloud()
    X = mesh.vertices
    fm = _forces(mesh, kv=0.5, integration=integration)
    G = np.random.default_rng(2).normal(size=(3, 3)) * 0.1
    _, f = fm.forces(X + X @ G.T)
    _, P, _ = stvk_volume((np.eye(3) + G)[None], fm.mu, fm.lam, fm.kv)
    return f, P[0], mesh, inner


def test_a_uniform_stress_gives_the_boundary_tractions_and_no_interior_force():
    """Patch test, force part (the integration constraint, §19.6): under a uniform stress
    P the force on every interior node is 0 and on a surface node P B*_b, B*_b its third
    of the area vectors of its surface triangles (the tractions of the piecewise-linear
    surface). Large strain (|G| about 0.3) and the volume term on; the fit-residual
    stabilisation is 0 for a linear field."""
    f, P, mesh, inner = _uniform_stress_forces("consistent")
    B = boundary_vectors(mesh.vertices, mesh.triangles, len(mesh.vertices))
    scale = np.abs(P).max() * 0.05 ** 2
    assert np.abs(f[inner]).max() < 1e-9 * scale
    assert np.abs(f - B @ P.T).max() < 1e-9 * scale


def test_raw_nodal_integration_leaves_an_interior_force_imbalance():
    """Why the correction exists: the raw MLS coefficients (integration: nodal) leave an
    interior force under a uniform stress of the order of the stress times a cell area."""
    f, P, _, inner = _uniform_stress_forces("nodal")
    assert np.abs(f[inner]).max() > 0.1 * np.abs(P).max() * 0.05 ** 2


def test_stabilisation_vanishes_for_affine_motion_and_penalises_the_rest():
    """The fit-residual energy is 0 (to round-off) for any affine map, a 90-degree rotation
    and a stretch included, and positive for a motion its first-order fit cannot see: a
    checkerboard displacement of the nodes."""
    mesh, _ = _cloud()
    X = mesh.vertices
    fm = _forces(mesh, kv=0.0, stabilisation=1.0)
    R = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    for A in (R, np.diag([1.5, 0.7, 1.0]) @ R):
        e_hg, _ = fm._stabilisation(X @ A.T + 0.3)
        assert abs(e_hg) < 1e-12 * fm.mu * fm.V.sum()
    parity = (np.round(X / 0.05).sum(1) % 2) * 2 - 1.0
    e_hg, _ = fm._stabilisation(X + 1e-3 * parity[:, None] * np.array([0.0, 0.0, 1.0]))
    assert e_hg > 1e-3 * fm.mu * fm.V.sum() * 1e-3 ** 2 / 0.05 ** 2


def _hourglass_ratios(stabilisation, modes=10):
    """For the lowest elastic modes of a free 0.5 x 0.1 x 0.1 m beam (525 nodes): each
    mode's fit-residual energy (at gamma = 1) over its elastic energy. A smooth mode has a
    small ratio; a zero-energy (hourglass) mode of nodal integration a large one."""
    mesh = box([0.5, 0.1, 0.1], 0.025)
    mesh = SimpleNamespace(vertices=mesh.vertices, tets=mesh.tets, triangles=boundary_faces(mesh.tets))
    fm = _forces(mesh, kv=0.1, stabilisation=stabilisation)
    probe = _forces(mesh, kv=0.1, stabilisation=1.0)
    K = fm.pattern.matrix(fm.tangent(fm.X)[2]).toarray()
    s = 1.0 / np.sqrt(np.repeat(fm.vertex_mass, 3))
    _, Q = scipy.linalg.eigh(s[:, None] * K * s[None, :], subset_by_index=[6, 5 + modes])   # skip the rigid six
    U = s[:, None] * Q
    x = fm.X.reshape(-1)
    ratios = []
    for u in U.T:
        e_hg, _ = probe._stabilisation((x + u).reshape(-1, 3))
        ratios.append(2.0 * e_hg / probe.mu * fm.mu / (u @ K @ u))
    return np.array(ratios)


def test_stabilisation_removes_the_hourglass_modes_from_the_low_spectrum():
    """Measured zero-energy modes (§19.6): without stabilisation, 7 of the 10 lowest elastic
    modes of the free beam are hourglass modes (fit-residual / elastic energy about 50; the
    smooth bending modes about 1); at the default gamma = 0.1 none is (all below 0.5)."""
    raw, stab = _hourglass_ratios(0.0), _hourglass_ratios(0.1)
    assert (raw > 10.0).sum() >= 5, raw
    assert stab.max() < 0.5, stab


def test_forces_are_the_gradient_of_the_energy():
    """f_int = dE/dx (§1 sign convention: the elastic force on the nodes is -f_int),
    against central differences of E, with the volume term on and a large deformation."""
    mesh, _ = _cloud(perturb=0.1)
    X = mesh.vertices
    fm = _forces(mesh, kv=0.5)
    x = _deformed(X)
    E, f = fm.forces(x)
    assert E > 0 and np.isclose(E, fm.energy(x))
    rng = np.random.default_rng(3)
    h = 1e-7
    for _ in range(5):
        d = rng.standard_normal(x.shape)
        fd = (fm.energy(x + h * d) - fm.energy(x - h * d)) / (2 * h)
        assert abs(fd - (f * d).sum()) < 1e-6 * np.abs(f).sum() * np.abs(d).max(), (fd, (f * d).sum())


def test_stiffness_matches_differences_of_the_forces():
    mesh, _ = _cloud(perturb=0.1)
    X = mesh.vertices
    pinned = np.flatnonzero(X[:, 0] < 1e-9)
    fm = _forces(mesh, kv=0.5, pinned=pinned)
    x = _deformed(X)
    x[pinned] = X[pinned]
    E, f, K_data = fm.tangent(x)
    K = fm.pattern.matrix(K_data)
    assert abs(K - K.T).max() < 1e-8 * abs(K).max()
    rng = np.random.default_rng(4)
    h = 1e-6
    for _ in range(3):
        d = rng.standard_normal(fm.n_free)
        dx = fm.expand(d)
        fd = (fm.free(fm.forces(x + h * dx)[1]) - fm.free(fm.forces(x - h * dx)[1])) / (2 * h)
        assert np.linalg.norm(fd - K @ d) < 1e-6 * np.linalg.norm(K @ d)
    # The projected stiffness is positive semi-definite.
    Kp = fm.pattern.matrix(fm.tangent(x, project=True)[2]).toarray()
    assert np.linalg.eigvalsh(0.5 * (Kp + Kp.T)).min() > -1e-8 * np.abs(Kp).max()


def _scene(kind="meshless", pins=True, colliders=None, gravity=(0, 0, -9.81), **meshless):
    return {"name": "m",
            "body": {"mesh": {"generator": "box", "size": [0.3, 0.1, 0.1], "cell": 0.05},
                     "material": {"model": "stvk", "young": 1e6, "poisson": 0.3, "density": 1000}},
            "pins": [{"box": [[-1e-3, -1, -1], [1e-3, 1, 1]]}] if pins else [],
            "colliders": colliders or {},
            "gravity": list(gravity),
            "model": {"kind": kind, "integrator": {"dt": 0.01}, "meshless": meshless}}


@pytest.mark.parametrize("integrator", ["implicit", "rk4"])
def test_free_body_keeps_linear_momentum(integrator):
    """No pins, no gravity, a deformed body with a random velocity: internal forces sum to
    zero, so m v is kept to round-off (relative 1e-10) by both integrators."""
    sim = Simulator(_scene(pins=False, gravity=(0, 0, 0), integrator=integrator))
    m = sim.model
    rng = np.random.default_rng(5)
    m.set_state(_deformed(m.body.vertices, amp=0.1), rng.standard_normal(m.x.shape))
    p0 = (m.vertex_mass[:, None] * m.v).sum(0)
    sim.step(5)
    p1 = (m.vertex_mass[:, None] * m.v).sum(0)
    scale = (m.vertex_mass[:, None] * np.abs(m.v)).sum()
    assert np.abs(p1 - p0).max() < 1e-10 * scale, (p0, p1)
    assert sim.stats()["stability"] in ("stable", "recovered")


def test_pins_hold_exactly():
    """Pinned nodes are removed from the unknowns: after steps under gravity they sit at
    their rest positions bit for bit (tolerance 0) with zero velocity."""
    sim = Simulator(_scene())
    sim.step(10)
    pinned = sim.model.body.pinned
    assert pinned.size == 9
    assert np.array_equal(sim.vertex_positions()[pinned], sim.model.body.vertices[pinned])
    assert not sim.model.v[pinned].any()


def newton_static(fm, x0, f_ext, tol=1e-10, iterations=10, floor=1e-8):
    """x (n, 3) with f_int(x) = f_ext on the free DOFs, by plain Newton from x0 (no line
    search: fem.statics' energy line search stalls at 1e-6-1e-9 on these, on round-off);
    fm a force model (tangent, free, expand, pattern). Stops at tol (relative residual);
    after `iterations` a residual below `floor` is round-off (stiff beams stall near 1e-10)
    and accepted, one above it fails."""
    x = np.array(x0, dtype=np.float64)
    solver = SparseSolver()
    for _ in range(iterations):
        _, f, K_data = fm.tangent(x)
        r = fm.free(f_ext - f)
        if np.linalg.norm(r) < tol * np.linalg.norm(fm.free(f_ext)):
            return x
        solver.factor(fm.pattern.matrix(K_data))
        x = x + fm.expand(solver.solve(r))
    r = fm.free(f_ext - fm.forces(x)[1])
    if np.linalg.norm(r) < floor * np.linalg.norm(fm.free(f_ext)):
        return x
    raise AssertionError(f"Newton: residual {np.linalg.norm(r) / np.linalg.norm(fm.free(f_ext)):.1e} after "
                         f"{iterations} iterations")


def _static_sag(L, cell, E):
    scene = load_scene({"name": "beam",
                        "body": {"mesh": {"generator": "box", "size": [L, 0.1, 0.1], "cell": cell},
                                 "material": {"model": "stvk", "young": E, "poisson": 0.3, "density": 1000}},
                        "pins": [{"box": [[-1e-3, -1, -1], [1e-3, 1, 1]]}],
                        "model": {"kind": "meshless"}})
    body = build_body(scene)
    fm = build_model(scene, body).force_model
    x = newton_static(fm, body.vertices, fm.vertex_mass[:, None] * np.array([0.0, 0.0, -9.81]))
    tip = np.abs(body.vertices[:, 0] - L) < 1e-9
    return len(body.vertices), -(x[tip, 2] - body.vertices[tip, 2]).mean()


@pytest.mark.claims
def test_cantilever_static_sag_against_the_closed_form():
    """0.5 x 0.1 x 0.1 m beam, cell 0.025 (525 nodes), E = 1e8 Pa (small strain), the
    defaults (16 neighbours, support 2 x mean distance, k_v = 0.1 mu, consistent
    integration, stabilisation 0.1). The static tip sag under self weight against
    Euler-Bernoulli + Timoshenko shear (§16.1): measured +1.1 % (1519 nodes +2.3 %, 3321
    nodes -0.9 %; linear tets on the same mesh -22 %, -12 %, -8 %). Before the consistent
    integration it was -17.5 %."""
    n, sag = _static_sag(0.5, 0.025, 1e8)
    ref = cantilever_gravity_sag(1000, 9.81, 0.5, 1e8, 0.1, 0.1, nu=0.3)
    err = sag / ref - 1.0
    assert n == 525
    assert sag > 0                              # sags down, with gravity
    assert abs(err) < 0.03, err


def test_simulator_cantilever_sags_under_gravity():
    sim = Simulator("cantilever", overrides={"model.kind": "meshless", "body.mesh.cell": 0.05})
    tip = np.abs(sim.model.body.vertices[:, 0] - 1.0) < 1e-9
    sim.step(5)
    dz = sim.vertex_positions()[tip, 2] - sim.model.body.vertices[tip, 2]
    assert np.all(dz < 0)
    assert sim.stats()["kind"] == "meshless" and sim.stats()["stability"] == "stable"
    assert sim.surface_positions().shape == (len(sim.surface_vertex_ids()), 3)
    e = sim.energy()
    assert e["elastic"] > 0 and e["kinetic"] > 0


def pressed_block(meshless):
    """The bottom-pinned 0.2 x 0.2 x 0.1 m block (0.05 m cells) after a sphere of 4 cm was
    pressed 5 mm into its top over 20 of 30 steps; meshless: its model.meshless settings."""
    scene = {"name": "block",
             "body": {"mesh": {"generator": "box", "size": [0.2, 0.2, 0.1], "cell": 0.05,
                               "origin": [-0.1, -0.1, 0.0]},
                      "material": {"model": "stvk", "young": 1e5, "poisson": 0.3, "density": 1000},
                      "damping": {"alpha": 5.0, "beta": 0.0}},
             "pins": [{"box": [[-1, -1, -1e-6], [1, 1, 1e-6]]}],
             "colliders": {"ball": {"shape": "sphere", "radius": 0.04, "position": [0, 0, 0.2]}},
             "gravity": [0, 0, 0],
             "model": {"kind": "meshless", "integrator": {"dt": 0.01, "newton_iterations": 2},
                       "meshless": dict(meshless)}}
    sim = Simulator(scene)
    for k in range(30):
        sim.set_collider_pose("ball", (0, 0, 0.14 - 0.005 * min(1, (k + 1) / 20)))
        sim.step()
    return sim


@pytest.mark.parametrize("integrator", ["implicit", "rk4"])
def test_sphere_pressed_into_a_block_pushes_back(integrator):
    """A bottom-pinned block pressed 5 mm by a sphere: the same unilateral solve as the FEM
    model; the reaction on the sphere points up and no contact vertex is left inside it
    beyond the linearisation error. The sideways reaction is not zero: k-nearest stencils
    break ties between equidistant grid nodes arbitrarily, so the discrete body is not
    mirror-symmetric (implicit: measured 0.33 % of the normal force)."""
    sim = pressed_block({"integrator": integrator})
    w = sim.collider_wrench("ball")
    assert w[2] > 0 and abs(w[0]) < 0.01 * w[2] and abs(w[1]) < 0.01 * w[2], w
    c = sim.contacts()
    assert len(c) > 0 and c[:, 6].max() < 1e-3
    assert sim.stats()["stability"] in ("stable", "recovered")


def test_meshless_scene_keys_are_validated():
    base = _scene()
    with pytest.raises(SceneError, match="model.meshless.neighbours"):
        load_scene(base, {"model.meshless.neighbours": 2})
    with pytest.raises(SceneError, match="model.meshless.integrator"):
        load_scene(base, {"model.meshless.integrator": "euler"})
    with pytest.raises(SceneError, match="model.meshless.substeps"):
        load_scene(base, {"model.meshless.substeps": 0})
    with pytest.raises(SceneError, match="model.meshless.support_scale"):
        load_scene(base, {"model.meshless.support_scale": -1})
    with pytest.raises(SceneError, match="unknown key model.meshless.kernel"):
        load_scene(base, {"model.meshless.kernel": "cubic"})
    s = load_scene(base)
    with pytest.raises(SceneError, match="model.meshless.integration"):
        load_scene(base, {"model.meshless.integration": "scni"})
    with pytest.raises(SceneError, match="model.meshless.stabilisation"):
        load_scene(base, {"model.meshless.stabilisation": -0.1})
    with pytest.raises(SceneError, match="model.meshless.volumes"):
        load_scene(base, {"model.meshless.volumes": "voronoi"})
    assert s["model"]["meshless"] == {"neighbours": 16, "support_scale": 2.0, "volume_stiffness": 0.1,
                                      "integrator": "implicit", "substeps": "auto", "integration": "consistent",
                                      "stabilisation": 0.1, "volumes": "mesh", "tet_barrier": True,
                                      "nodes": "mesh", "spacing": "auto"}
    # Too small a support: the nodes without 3 weighted neighbours get neighbours chosen over
    # the octants (and so larger supports); at 0.1 x the mean distance even those stay empty.
    b = Simulator(_scene(support_scale=0.5)).model.build
    assert b.grown > 0 and b.ill_conditioned == 0
    with pytest.raises(SceneError, match="support_scale"):
        Simulator(_scene(support_scale=0.1))


@pytest.mark.parametrize("project", [False, True])
def test_compiled_node_pass_matches_the_numpy_reference(project):
    """kernels.node_kernel against forces.py's numpy path: energy, forces and stiffness on
    a large deformation with the volume term and the stabilisation on, projected or not."""
    mesh, _ = _cloud(perturb=0.1)
    fm = _forces(mesh, kv=0.5, stabilisation=0.2)
    x = _deformed(mesh.vertices, amp=0.2)
    x[:, 0] -= 0.4 * mesh.vertices[:, 2]          # and a strong shear, so some H_i are indefinite
    got = fm.tangent(x, project=project)
    fm.backend = "numpy"
    ref = fm.tangent(x, project=project)
    assert np.isclose(got[0], ref[0], rtol=1e-12)
    assert np.abs(got[1] - ref[1]).max() < 1e-10 * np.abs(ref[1]).max()
    assert np.abs(got[2] - ref[2]).max() < 1e-10 * np.abs(ref[2]).max()


def test_thin_parts_rechoose_ill_conditioned_neighbourhoods():
    """A plate two nodes thick whose layers are 1/40 of the in-plane spacing apart: the
    16 nearest give moment matrices with condition numbers about 1e3-1e4, so those nodes get
    neighbours chosen over the octants. It still cannot see across 0.5 mm well, so the build
    says so (warning, explain) instead of failing; a gradient stays exact for a linear field."""
    scene = {"name": "plate",
             "body": {"mesh": {"generator": "box", "size": [0.2, 0.2, 0.0005], "cell": 0.02},
                      "material": {"model": "stvk", "young": 1e6, "poisson": 0.3, "density": 1000}},
             "gravity": [0, 0, 0], "model": {"kind": "meshless"}}
    with pytest.warns(UserWarning, match="ill-conditioned moment matrix"):
        sim = Simulator(scene)
    b = sim.model.build
    assert b.grown > 0 and b.ill_conditioned > 0
    text = "\n".join(sim.model.explain())
    assert f"{b.grown} nodes with ill-conditioned moment matrices" in text
    X = sim.model.body.vertices
    G = np.random.default_rng(7).normal(size=(3, 3)) * 1e-3
    assert np.abs(sim.model.op.gradients(X @ G.T) - G).max() < 1e-9
    # A well-shaped body changes nothing.
    ok = Simulator(_scene()).model.build
    assert ok.grown == 0 and ok.ill_conditioned == 0


# ---------------------------------------------------------------------- graded node sets
# The Hertz study's meshless nodes (verify/hertz_study.meshless_mesh) at a tenth of its size:
# fine 1 cm cells under a focus on the top face, doubling every 2 cells out to 10 cm.
GRADED = dict(size=[0.4, 0.4, 0.4], cell_coarse=0.1, cell_fine=0.01, focus=[0.0, 0.0, 0.0], radius=0.02,
              origin=[-0.2, -0.2, -0.4])


def test_graded_bcc_block_fills_the_block_with_isotropic_graded_cells():
    from mdss_ros.mesh.generators import graded_bcc_block
    from mdss_ros.mesh.tetmesh import signed_volumes
    mesh = graded_bcc_block(**GRADED, layers=2)
    X, lo, hi = mesh.vertices, np.array(GRADED["origin"]), np.array(GRADED["origin"]) + 0.4
    vol = signed_volumes(X, mesh.tets)
    assert vol.min() > 0 and np.isclose(vol.sum(), 0.4 ** 3, rtol=1e-12)       # Delaunay of a box: fills it
    tri = boundary_faces(mesh.tets)
    on = lambda P: (np.abs(P - lo) < 1e-12) | (np.abs(P - hi) < 1e-12)          # noqa: E731
    assert np.all(on(X[tri]).all(axis=1).any(axis=1))        # every surface triangle lies in a block face
    # Graded: nearest-node spacing ~ the fine cell at the focus, ~ the coarse one far away.
    from scipy.spatial import cKDTree
    d = cKDTree(X).query(X, k=2)[0][:, 1]
    r = np.linalg.norm(X - GRADED["focus"], axis=1)
    assert np.median(d[r < 0.02]) < 0.011 and np.median(d[r > 0.3]) > 0.03
    # Deterministic (seeded perturbation), and a different seed moves the nodes.
    again = graded_bcc_block(**GRADED, layers=2)
    np.testing.assert_array_equal(again.vertices, X)
    np.testing.assert_array_equal(again.tets, mesh.tets)
    assert not np.array_equal(graded_bcc_block(**GRADED, layers=2, seed=1).vertices, X)


def test_graded_bcc_nodes_have_well_conditioned_moment_matrices():
    """The tensor-product graded_block at the same cells leaves many nodes with nearly coplanar
    neighbours (cells 1 cm one way, 10 cm the other); the isotropic BCC grading leaves none,
    and the consistent integration's constraint is then met to round-off."""
    from mdss_ros.mesh.generators import graded_bcc_block, graded_block
    from mdss_ros.meshless.mls import conditions
    from mdss_ros.meshless.model import COND_LIMIT
    from mdss_ros.meshless.neighbourhoods import find_neighbourhoods
    tp = graded_block(GRADED["size"], GRADED["cell_coarse"], GRADED["cell_fine"], GRADED["focus"],
                      GRADED["radius"], GRADED["origin"], growth=1.5)
    nb = find_neighbourhoods(tp.vertices)
    assert (conditions(tp.vertices, nb.nbr, nb.h) > COND_LIMIT).sum() > 0.2 * len(tp.vertices)
    mesh = graded_bcc_block(**GRADED, layers=2)
    nb = find_neighbourhoods(mesh.vertices)
    assert conditions(mesh.vertices, nb.nbr, nb.h).max() < 50.0                 # before any regrowth
    fm, build = build_forces(mesh.vertices, mesh.tets, boundary_faces(mesh.tets), MATERIAL, {}, ())
    assert build.grown == 0 and build.ill_conditioned == 0 and fm.op.floored == 0
    assert build.integration_residual < 1e-8
    # The patch test holds on it.
    G = np.random.default_rng(3).normal(size=(3, 3)) * 1e-3
    assert np.abs(fm.op.gradients(mesh.vertices @ G.T) - G).max() < 1e-9


BARRIER_MATERIAL = SimpleNamespace(mu=3.8e5, lam=5.8e5, density=1000.0, barrier=100.0, barrier_j=0.2)


def _crushed(X, seed=5):
    """A deformation that compresses every nodal fit below the barrier's J (z squashed to
    12 %) and pushes two interior-ish nodes through neighbouring tets (inverted tets)."""
    rng = np.random.default_rng(seed)
    x = X * np.array([1.0, 0.9, 0.12]) + 1e-3 * rng.standard_normal(X.shape)
    x[10] += np.array([0.0, 0.0, 0.03])
    x[25] -= np.array([0.02, 0.0, 0.02])
    return x


def test_compression_barrier_acts_below_its_threshold_only():
    """The nodal and the tet barrier (docs/method.md §19.7) are zero for every J >= j: the
    large smooth deformation of the other tests gives the same energy, forces and stiffness
    bit for bit; the crushed one has nodes and tets below j and costs more."""
    mesh, _ = _cloud(perturb=0.1)
    fm0, _ = build_forces(mesh.vertices, mesh.tets, mesh.triangles, MATERIAL, {"volume_stiffness": 0.5})
    fm1, _ = build_forces(mesh.vertices, mesh.tets, mesh.triangles, BARRIER_MATERIAL, {"volume_stiffness": 0.5})
    assert fm1.kb == 100.0 * BARRIER_MATERIAL.mu and fm1.tets is not None and fm0.tets is None
    x = _deformed(mesh.vertices)
    a, b = fm0.tangent(x), fm1.tangent(x)
    assert a[0] == b[0] and np.array_equal(a[1], b[1])
    assert np.array_equal(fm0.pattern.matrix(a[2]).toarray(), fm1.pattern.matrix(b[2]).toarray())
    xc = _crushed(mesh.vertices)
    J = np.linalg.det(fm1.op.deformation_gradients(xc))
    assert (J < fm1.jb).sum() > len(J) // 2
    assert fm1.tet_barrier(xc)[0] > 0.0
    assert fm1.energy(xc) > fm0.energy(xc) + fm1.tet_barrier(xc)[0]


@pytest.mark.parametrize("project", [False, True])
def test_compression_barrier_forces_and_stiffness_are_exact_derivatives(project):
    """With nodes and tets below the barrier's J: f = dE/dx and K = df/dx by central
    differences, the compiled node pass equals the numpy one, projected K is PSD."""
    mesh, _ = _cloud(perturb=0.1)
    X = mesh.vertices
    pinned = np.flatnonzero(X[:, 0] < 1e-9)
    fm, _ = build_forces(X, mesh.tets, mesh.triangles, BARRIER_MATERIAL, {"volume_stiffness": 0.5}, pinned)
    x = _crushed(X)
    x[pinned] = X[pinned]
    E, f, K_data = fm.tangent(x, project=project)
    fm.backend = "numpy"
    ref = fm.tangent(x, project=project)
    fm.backend = "numba"
    assert np.isclose(E, ref[0], rtol=1e-12)
    assert np.abs(f - ref[1]).max() < 1e-10 * np.abs(ref[1]).max()
    assert np.abs(K_data - ref[2]).max() < 1e-10 * np.abs(ref[2]).max()
    K = fm.pattern.matrix(K_data)
    rng = np.random.default_rng(6)
    if project:
        Kd = K.toarray()
        assert np.linalg.eigvalsh(0.5 * (Kd + Kd.T)).min() > -1e-8 * np.abs(Kd).max()
        return
    assert abs(K - K.T).max() < 1e-8 * abs(K).max()
    for _ in range(3):
        d = rng.standard_normal(x.shape)
        d[pinned] = 0.0
        h = 1e-7
        fd = (fm.energy(x + h * d) - fm.energy(x - h * d)) / (2 * h)
        assert abs(fd - (f * d).sum()) < 1e-6 * np.abs(f).sum() * np.abs(d).max()
        h = 1e-7                  # the tets' cubic barrier: the h^2 term is 5e-6 at h = 1e-6
        dx = fm.free(d)
        fdf = (fm.free(fm.forces(x + h * d)[1]) - fm.free(fm.forces(x - h * d)[1])) / (2 * h)
        assert np.linalg.norm(fdf - K @ dx) < 1e-6 * np.linalg.norm(K @ dx)


@pytest.mark.parametrize("poisson", [0.0, 0.499])
def test_soft_spinning_body_under_a_large_load_recovers_from_inversion(poisson):
    """The two cells of the quick meshless stability column that failed before the barrier
    (docs/method.md §19.7): 1 kPa, 1 kN tip load, dt 1/30, spin 50 rad/s. Without the nodal
    barrier the nu = 0 body ended with 68 inverted tets; with it but without the tet barrier
    the nu = 0.499 body kept 93 (its nodal J all above 0.16: the nodes had passed through
    each other inside the stencils)."""
    from mdss_ros.verify import stability_study as s
    cell = dict(s.BASE, young=1e3, poisson=poisson, spin=50.0, dt=1.0 / 30.0, force=1e3)
    row = s.run_cell("meshless", s.MESHLESS_MATERIAL, cell, s.QUICK_STEPS)
    assert row["status"] in ("stable", "recovered"), row["why"]
    assert row["inverted_end"] == 0


def test_mass_damping_and_integrator_are_the_full_models_on_the_same_mesh():
    """What the trade-off row's dynamic error was checked against (docs/method.md §19.7):
    the meshless model's nodal masses are the full model's lumped masses on the same
    vertices, and it steps with the same backward Euler, Newton settings and Rayleigh
    damping. Its difference from the full model on the cantilever scene is the stiffness
    (linear tets lock in bending), not these."""
    scene = _scene()
    scene["body"]["damping"] = {"alpha": 0.3, "beta": 0.002}
    full = Simulator(dict(scene, model={"kind": "full", "integrator": {"dt": 0.01}})).model
    ml = Simulator(scene).model
    assert np.abs(ml.vertex_mass - full.vertex_mass).max() < 1e-12 * full.vertex_mass.max()
    assert type(ml.integrator) is type(full.integrator)
    assert ml.integrator.settings == full.integrator.settings
    assert ml.integrator.settings.alpha == 0.3 and ml.integrator.settings.beta == 0.002
    Mf, Mm = full.force_model.M.diagonal(), ml.force_model.M.diagonal()
    assert np.abs(Mf - Mm).max() < 1e-12 * Mf.max()


def test_kernel_volumes_follow_the_paper_and_overweigh_bodies_near_their_surface():
    """`volumes: kernel`, [HZ] eqs. 1-3 as written: m_i = s rho rbar_i^3, rho_i the kernel-
    weighted sum of the masses, s so that the mean rho_i is rho, V_i = m_i / rho_i. The mean
    density is rho exactly; the kernel sums are cut at the surface (SPH's boundary
    deficiency), so the masses come out too large, less so as the nodes refine (0.3 m cube:
    1.69 x the body's mass at 0.03 m, 1.31 x at 0.015 m; the 0.5 m beam 2.4 x). Why the
    default is the mesh's volumes (docs/method.md §19.4)."""
    ratios = []
    for cell in (0.03, 0.02):
        scene = load_scene({"name": "cube", "body": {"mesh": {"generator": "box", "size": [0.3, 0.3, 0.3], "cell": cell},
                            "material": {"model": "stvk", "young": 1e6, "poisson": 0.3, "density": 1000}},
                            "model": {"kind": "meshless", "meshless": {"volumes": "kernel"}}})
        fm = build_model(scene, build_body(scene)).force_model
        assert fm.V.min() > 0 and fm.vertex_mass.min() > 0
        assert np.mean(fm.vertex_mass / fm.V) == pytest.approx(1000.0, rel=1e-12)
        ratios.append(fm.vertex_mass.sum() / (1000.0 * 0.027))
    assert 1.0 < ratios[1] < ratios[0], ratios
