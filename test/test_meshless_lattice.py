"""Meshless nodes on a regular lattice (`model.meshless.nodes: lattice`, meshless/nodes.py,
meshless/embedding.py, docs/method.md §19.9): the node set, its volumes, the MLS
interpolation that moves the mesh's vertices, contact rows through it, and the model
against the closed form, pins, momentum and the patch test. Small bodies, seconds each.
"""
import numpy as np
import pytest
import scipy.sparse as sp
import trimesh

from mdss_ros import Simulator
from mdss_ros.body import build_body
from mdss_ros.errors import SceneError
from mdss_ros.mesh import box
from mdss_ros.mesh.surface import boundary_faces
from mdss_ros.meshless.embedding import Embedding, shape_functions
from mdss_ros.meshless.forces import stvk_volume
from mdss_ros.mesh.distance import signed_distance
from mdss_ros.meshless.nodes import MIN_GAP, lattice_nodes, lattice_volumes
from mdss_ros.model_build import build_model
from mdss_ros.scene import load_scene
from mdss_ros.verify.closed_forms import cantilever_gravity_sag
from test_meshless import newton_static, pressed_block


def _beam_scene(L=0.5, cell=0.025, E=1e8, spacing="auto", gravity=(0, 0, -9.81), pins=True, **meshless):
    return {"name": "beam",
            "body": {"mesh": {"generator": "box", "size": [L, 0.1, 0.1], "cell": cell},
                     "material": {"model": "stvk", "young": E, "poisson": 0.3, "density": 1000}},
            "pins": [{"box": [[-1e-3, -1, -1], [1e-3, 1, 1]]}] if pins else [],
            "gravity": list(gravity),
            "model": {"kind": "meshless", "integrator": {"dt": 0.01},
                      "meshless": dict(meshless, nodes="lattice", spacing=spacing)}}


def test_the_lattice_of_a_box_whose_edges_are_multiples_of_the_spacing_is_the_grid():
    """Faces, edges and corners included, nothing moved, nothing dropped."""
    mesh = box([0.3, 0.2, 0.2], 0.1)
    X = lattice_nodes(mesh.vertices, boundary_faces(mesh.tets), 0.05)
    grid = np.stack(np.meshgrid(*[np.arange(0, s + 1e-9, 0.05) for s in (0.3, 0.2, 0.2)], indexing="ij"),
                    axis=-1).reshape(-1, 3)
    assert len(X) == len(grid) == 7 * 5 * 5
    rows = lambda a: a[np.lexsort(np.round(a, 9).T[::-1])]       # noqa: E731
    assert np.abs(rows(X) - rows(grid)).max() < 1e-12


def test_the_lattice_of_a_sphere_has_inner_lattice_points_and_surface_nodes_a_gap_apart():
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=0.1)
    h = 0.02
    X = lattice_nodes(sphere.vertices, sphere.faces, h)
    s, _ = signed_distance(X, sphere.vertices, sphere.faces)
    assert s.max() < 1e-9                                     # none outside
    on = np.abs(s) < 1e-9
    assert on.sum() > 50                                      # a surface layer of nodes
    inner = X[~on]
    assert np.abs(inner / h - np.round(inner / h)).max() < 1e-9   # the rest are lattice points (centred box)
    d = np.linalg.norm(X[:, None] - X[None], axis=2) + np.eye(len(X))
    assert d.min() >= MIN_GAP * h - 1e-12


def test_lattice_volumes_partition_the_body_and_give_inner_nodes_a_cell():
    mesh = box([0.3, 0.2, 0.2], 0.05)
    tri = boundary_faces(mesh.tets)
    X = lattice_nodes(mesh.vertices, tri, 0.05)
    V = lattice_volumes(X, mesh.vertices, tri, 0.05, 0.3 * 0.2 * 0.2)
    assert V.sum() == pytest.approx(0.012, rel=1e-12)
    inner = np.all((X > 1e-9) & (X < np.array([0.3, 0.2, 0.2]) - 1e-9), axis=1)
    assert np.abs(V[inner] / 0.05 ** 3 - 1.0).max() < 0.05
    face = np.isclose(X[:, 0], 0.0) & ~inner                  # boundary nodes: a part of a cell
    assert V[face].max() < 0.75 * 0.05 ** 3


def test_mls_shape_functions_reproduce_linear_fields_and_spread_is_their_transpose():
    rng = np.random.default_rng(0)
    X = rng.uniform(0, 1, (400, 3))
    P = rng.uniform(0.2, 0.8, (60, 3))
    idx, phi = shape_functions(X, P, k=16, support_scale=2.0)
    emb = Embedding(idx, phi)
    assert np.abs(phi.sum(1) - 1).max() < 1e-12
    A, b = rng.normal(size=(3, 3)), rng.normal(size=3)
    assert np.abs(emb.apply(X @ A.T + b) - (P @ A.T + b)).max() < 1e-12
    x, f = rng.normal(size=X.shape), rng.normal(size=P.shape)
    assert np.sum(f * emb.apply(x)) == pytest.approx(np.sum(emb.spread(f, len(X)) * x), rel=1e-12)


def test_contact_rows_through_the_embedding_are_the_points_velocity_along_the_normal():
    """A row of C is dt n^T (velocity of its point), the point a weighted set of mesh
    vertices (a face point's barycentric weights) and each vertex the MLS combination of
    nodes: C dv equals dt n . (sum_a w_a sum_j phi_aj dv_j) for any node velocities dv."""
    sim = Simulator(_beam_scene(L=0.3, cell=0.05, spacing=0.05))
    m = sim.model
    integ, emb = m.integrator, m.embedding
    rng = np.random.default_rng(3)
    pts = rng.choice(len(m.body.vertices), size=(6, 3))
    w = rng.uniform(0.1, 1.0, (6, 3))
    n = rng.normal(size=(6, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    corners, weights = emb.corners(pts, w)
    C = integ._rows_along(n[:, None, :], corners, weights)
    dv = rng.normal(size=m.x.shape)
    dv[m.lattice.pinned] = 0.0                               # pinned DOFs are not unknowns
    want = integ.dt * np.einsum("ki,ki->k", n, np.einsum("ka,kai->ki", w, emb.apply(dv)[pts]))
    assert isinstance(C, sp.csr_matrix)
    assert np.abs(C @ m.force_model.free(dv) - want).max() < 1e-12 * np.abs(want).max()


def _lattice_static_sag(L, cell, E, spacing):
    """Newton on f_int = f_ext of the lattice model of the 0.1 x 0.1 beam under its weight;
    (nodes, the tip vertices' mean sag, the pinned vertices' largest move)."""
    scene = load_scene(_beam_scene(L=L, cell=cell, E=E, spacing=spacing))
    body = build_body(scene)
    model = build_model(scene, body)
    fm, emb = model.force_model, model.embedding
    f_ext = fm.vertex_mass[:, None] * np.array([0.0, 0.0, -9.81])      # the nodes' masses
    x = newton_static(fm, fm.X, f_ext)
    xv = emb.apply(x)
    tip = np.abs(body.vertices[:, 0] - L) < 1e-9
    pin_move = np.abs(xv[body.pinned] - body.vertices[body.pinned]).max()
    return len(x), -(xv[tip, 2] - body.vertices[tip, 2]).mean(), pin_move


@pytest.mark.claims
def test_lattice_cantilever_static_sag_against_the_closed_form():
    """The 0.5 x 0.1 x 0.1 m beam of test_meshless's closed-form test, E = 1e8 Pa, its mesh
    (cell 0.025) giving only the surface: nodes on a 0.025 m lattice (the grid itself, 525
    nodes) and on a 0.02 m one, not aligned with the beam (faces snapped). The tip sag
    against Euler-Bernoulli + Timoshenko shear, measured -0.8 % and +1.5 % (0.0167 m, 1,080
    nodes: +4.0 %; 0.0125 m, 3,321 nodes: -1.4 %; mesh nodes: +1.1 % at 525, -0.9 % at
    3,321); the pinned vertices move 0.004 % and 0.03 % of the tip's sag."""
    ref = cantilever_gravity_sag(1000, 9.81, 0.5, 1e8, 0.1, 0.1, nu=0.3)
    for spacing, bound in ((0.025, 0.03), (0.02, 0.05)):
        n, sag, pin_move = _lattice_static_sag(0.5, 0.025, 1e8, spacing)
        err = sag / ref - 1.0
        assert sag > 0
        assert abs(err) < bound, (spacing, n, err)
        assert pin_move < 0.02 * sag, (spacing, pin_move, sag)


def test_lattice_free_body_keeps_linear_momentum_and_its_state_round_trips():
    sim = Simulator(_beam_scene(L=0.3, cell=0.05, spacing=0.04, pins=False, gravity=(0, 0, 0)))
    m = sim.model
    m.set_rigid_velocity([0.1, 0.0, 0.2], [0.0, 3.0, 1.0])
    rng = np.random.default_rng(5)
    m.v = m.v + rng.normal(size=m.v.shape)
    p0 = (m.state_mass[:, None] * m.v).sum(0)
    sim.step(5)
    p1 = (m.state_mass[:, None] * m.v).sum(0)
    assert np.abs(p1 - p0).max() < 1e-10 * (m.state_mass[:, None] * np.abs(m.v)).sum()
    snap = m.get_state()
    x_v = sim.vertex_positions().copy()
    sim.step(2)
    m.set_state(snap)
    assert np.array_equal(sim.vertex_positions(), x_v)
    with pytest.raises(ValueError, match="snapshot"):
        m.set_state(m.body.vertices, np.zeros_like(m.body.vertices))


def test_lattice_patch_test_uniform_stress_leaves_no_interior_force():
    """Consistent integration with the surface's area vectors spread to the nodes by the
    MLS weights at surface quadrature points (B*): under a uniform large stress P the nodes
    with no share of the surface (B*_b = 0) carry no force, the others P B*_b."""
    scene = _beam_scene(L=0.3, cell=0.05, spacing=0.03, pins=False)
    scene["body"]["mesh"]["size"] = [0.3, 0.2, 0.2]
    scene = load_scene(scene)
    model = build_model(scene, build_body(scene))
    fm, B = model.force_model, model.lattice.boundary
    X = fm.X
    G = np.random.default_rng(2).normal(size=(3, 3)) * 0.1
    _, f = fm.forces(X + X @ G.T)
    P = stvk_volume((np.eye(3) + G)[None], fm.mu, fm.lam, fm.kv)[1][0]
    inner = ~B.any(axis=1)
    assert inner.sum() > 10
    scale = np.abs(P).max() * 0.03 ** 2
    assert np.abs(f[inner]).max() < 1e-8 * scale
    assert np.abs(f - B @ P.T).max() < 1e-8 * scale


def test_lattice_block_pressed_by_a_sphere_pushes_back_like_the_mesh_nodes():
    """The sphere test of test_meshless on lattice nodes (the block's grid, 0.05 m): contact
    at the vertices through their nodes. The reaction points up, no contact point is left
    inside the ball beyond the linearisation error, and it is close to the mesh-node model's
    (the same nodes up to the MLS interpolation of the surface; measured 19.8 N against
    20.5 N)."""
    def run(nodes):
        return pressed_block({"nodes": nodes, "spacing": 0.05})
    lat, ref = run("lattice"), run("mesh")
    w, w_ref = lat.collider_wrench("ball"), ref.collider_wrench("ball")
    assert w[2] > 0 and abs(w[0]) < 0.02 * w[2] and abs(w[1]) < 0.02 * w[2], w
    assert w[2] == pytest.approx(w_ref[2], rel=0.15), (w, w_ref)
    c = lat.contacts()
    assert len(c) > 0 and c[:, 6].max() < 1e-3
    assert lat.stats()["stability"] in ("stable", "recovered")


def test_lattice_scene_keys_are_validated():
    for bad, msg in (({"nodes": "grid"}, "nodes"), ({"nodes": "lattice", "spacing": -0.1}, "spacing"),
                     ({"nodes": "lattice", "spacing": "fine"}, "spacing")):
        scene = _beam_scene()
        scene["model"]["meshless"] = bad
        with pytest.raises(SceneError, match=msg):
            load_scene(scene)
    with pytest.raises(SceneError, match="spacing"):           # no node left in a 0.1 m beam
        Simulator(_beam_scene(L=0.3, cell=0.05, spacing=1.0))


def test_lattice_cantilever_runs_records_and_replays_bit_for_bit(tmp_path, capsys):
    """`mdss run cantilever --set model.kind=meshless --set model.meshless.nodes=lattice`
    end to end: MCAP and rerun written, the MCAP replayed bit for bit."""
    from mdss_ros.cli import main as mdss
    mcap, rrd = tmp_path / "a.mcap", tmp_path / "a.rrd"
    args = ["run", "cantilever", "--set", "model.kind=meshless", "--set", "model.meshless.nodes=lattice",
            "--set", "body.mesh.cell=0.05", "--steps", "8", "--mcap", str(mcap), "--rrd", str(rrd), "--explain"]
    assert mdss(args) == 0
    out = capsys.readouterr().out
    assert "cubic lattice" in out and "MLS interpolation" in out
    assert mcap.stat().st_size > 0 and rrd.stat().st_size > 0
    assert mdss(["replay", str(mcap), "--check"]) == 0
    assert "reproduced bit for bit" in capsys.readouterr().out
