"""Mesh colliders (shape: mesh): a closed surface file sampled into a signed distance grid
(contact/mesh_sdf.py), posed like every collider, cached, and validated with the key named."""
import numpy as np
import pytest
import trimesh

from mdss_ros import Simulator, load_scene
from mdss_ros.contact.colliders import ColliderInsideWarning, make_collider
from mdss_ros.errors import SceneError
from mdss_ros.precompute import PrecomputeCache


def _write(mesh, folder, name):
    path = folder / name
    mesh.export(path)
    return path


def _u_shape():
    """A U (closed, non-convex): a base 0.12 x 0.06 x 0.02 with two prongs 0.03 wide and
    0.06 tall at |x| >= 0.03; the notch is |x| < 0.03, 0.02 < z < 0.08 (outside the solid)."""
    base = trimesh.creation.box(extents=(0.12, 0.06, 0.02))
    base.apply_translation((0.0, 0.0, 0.01))
    left = trimesh.creation.box(extents=(0.03, 0.06, 0.07))
    left.apply_translation((-0.045, 0.0, 0.045))
    right = left.copy()
    right.apply_translation((0.09, 0.0, 0.0))
    u = trimesh.boolean.union([base, left, right], engine="manifold")
    assert u.is_watertight and u.volume > 0
    return u


def _sphere_points(rng, centre, radius, n, band):
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1)[:, None]
    r = radius + rng.uniform(-band, band, n)
    return centre + d * r[:, None], d


def test_mesh_sphere_matches_the_analytic_sphere_within_the_resolution(tmp_path):
    R, h = 0.05, 0.004
    path = _write(trimesh.creation.icosphere(subdivisions=3, radius=R), tmp_path, "ball.obj")
    centre = np.array([0.3, -0.1, 0.2])
    c = make_collider("ball", {"shape": "mesh", "file": str(path), "resolution": h, "position": [0, 0, 0]},
                      cache=PrecomputeCache(tmp_path / "cache"))
    c.set_pose(centre, (0.2, -0.3, 0.1, 0.9))                        # posed like any collider
    p, d = _sphere_points(np.random.default_rng(0), centre, R, 2000, 0.01)
    phi, n = c.signed_distance(p)
    exact = np.linalg.norm(p - centre, axis=1) - R
    # Measured: phi within 0.05 h (the icosphere's facets sit up to 0.13 mm inside the
    # sphere, trilinear interpolation adds ~h^2 / (8 R)); normals within 0.02 rad.
    err = np.abs(phi - exact)
    assert err.max() < 0.1 * h, err.max()
    angle = np.arccos(np.clip(np.einsum("ij,ij->i", n, d), -1, 1))
    assert angle.max() < h / R, angle.max()
    assert np.allclose(np.linalg.norm(n, axis=1), 1.0)
    # Outside the grid: distance to the grid box plus its boundary value; still an upper
    # bound of the true distance, and the normal points away.
    far = centre + np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -2.0]])
    phi_far, n_far = c.signed_distance(far)
    exact_far = np.linalg.norm(far - centre, axis=1) - R
    assert np.all(phi_far >= exact_far - 0.1 * h) and np.all(phi_far < exact_far * 1.5)
    assert np.all(np.einsum("ij,ij->i", n_far, far - centre) > 0)
    # The core (for the inside-the-body check) is the sphere's centre, to a cell.
    assert np.linalg.norm(c.core_points() - centre) < h


def test_mesh_box_matches_the_box_collider_at_a_pose(tmp_path):
    ext = np.array([0.08, 0.06, 0.04])
    path = _write(trimesh.creation.box(extents=ext), tmp_path, "box.stl")
    pose = ([0.1, 0.2, -0.05], [0.3, 0.1, -0.2, 0.9])
    m = make_collider("m", {"shape": "mesh", "file": path.name, "resolution": 0.002,
                            "position": pose[0], "orientation": pose[1]},
                      base_dir=tmp_path, cache=PrecomputeCache(tmp_path / "cache"))
    b = make_collider("b", {"shape": "box", "half_extents": (ext / 2).tolist(),
                            "position": pose[0], "orientation": pose[1]})
    rng = np.random.default_rng(1)
    local = rng.uniform(-1, 1, (2000, 3)) * (ext / 2 + 0.01)
    p = pose[0] + local @ b.rotation.T
    phi_m, n_m = m.signed_distance(p)
    phi_b, n_b = b.signed_distance(p)
    # Near the faces the box SDF is linear, so trilinear interpolation is exact there;
    # near edges and corners (and inside, near the medial planes) it is off by < 1 cell.
    assert np.abs(phi_m - phi_b).max() < 0.002
    near_face = np.abs(phi_b) < 0.004
    clear = near_face & (np.sort(np.abs(np.abs(local) - ext / 2), axis=1)[:, 1] > 0.006)
    assert clear.sum() > 50
    assert np.abs(phi_m[clear] - phi_b[clear]).max() < 1e-9
    assert np.abs(n_m[clear] - n_b[clear]).max() < 1e-6


def _press_scene(ball):
    return {"name": "press",
            "body": {"mesh": {"generator": "box", "size": [0.2, 0.2, 0.1], "cell": 0.025,
                              "origin": [-0.1, -0.1, 0.0]},
                     "material": {"model": "neohookean", "young": 1e5, "poisson": 0.3, "density": 1000}},
            "colliders": {"ball": ball},
            "pins": [{"box": [[-1, -1, -1e-6], [1, 1, 1e-6]]}],
            "gravity": [0.0, 0.0, 0.0],
            "model": {"kind": "full", "integrator": {"dt": 10.0, "newton_iterations": 12, "tolerance": 1e-8}}}


def test_mesh_sphere_pressed_into_a_block_gives_the_sphere_force(tmp_path):
    """A static press of 5 mm by a sphere of radius 0.1 into a 0.2 x 0.2 x 0.1 block (cell
    2.5 cm): the mesh sphere (icosphere, 3 subdivisions, default grid h = 3.1 mm) gives the
    analytic sphere's force (vertex contacts only, as a mesh collider has). The icosphere's
    facets lie up to s = 0.32 mm inside the sphere (circumradius^2 / 2R) and the grid adds
    < 0.1 h = 0.31 mm (the test above), so the press depth is short by at most e = 0.63 mm
    of d = 5 mm; with a force between linear and Hertzian (d^1.5) in the depth, the force is
    off by at most 1.5 e / d = 19 %: the tolerance is 20 %. Measured: analytic 19.89 N,
    mesh 17.95 N (-9.7 %, the mesh sphere is the smaller)."""
    R, depth = 0.1, 0.005
    path = _write(trimesh.creation.icosphere(subdivisions=3, radius=R), tmp_path, "ball.ply")
    forces = {}
    for kind, ball in (("analytic", {"shape": "sphere", "radius": R, "face_contacts": False}),
                       ("mesh", {"shape": "mesh", "file": str(path)})):
        with pytest.warns(ColliderInsideWarning):          # posed 5 mm into the top: a static press
            sim = Simulator(_press_scene(dict(ball, position=[0.0, 0.0, 0.1 + R - depth])),
                            cache=PrecomputeCache(tmp_path / "cache"))
        sim.step(3)
        forces[kind] = sim.collider_wrench("ball")[2]
        phi = sim.colliders["ball"].signed_distance(sim.vertex_positions())[0]
        assert phi.min() > -1e-6
    assert forces["analytic"] > 0
    rel = abs(forces["mesh"] - forces["analytic"]) / forces["analytic"]
    print(f"pressed force: analytic {forces['analytic']:.6g} N, mesh {forces['mesh']:.6g} N, rel {rel:.3g}")
    assert rel < 0.20, forces


def test_non_convex_mesh_has_no_phantom_contacts(tmp_path):
    path = _write(_u_shape(), tmp_path, "u.obj")
    spec = {"shape": "mesh", "file": str(path), "resolution": 0.0025}
    u = make_collider("u", spec, cache=PrecomputeCache(tmp_path / "cache"))
    rng = np.random.default_rng(2)
    notch = rng.uniform((-0.028, -0.028, 0.022), (0.028, 0.028, 0.078), (500, 3))
    phi, _ = u.signed_distance(notch)
    assert phi.min() > 0                                   # outside the solid, not inside its hull
    exact = np.minimum.reduce([0.03 - np.abs(notch[:, 0]), notch[:, 2] - 0.02])
    assert np.abs(phi - exact).max() < 0.0025
    inside = rng.uniform((-0.058, -0.028, 0.002), (0.058, 0.028, 0.018), (200, 3))   # in the base
    assert u.signed_distance(inside)[0].max() < 0
    # A block on a floor, under the U turned over (notch down): the prongs straddle the
    # block 1 cm from its sides, the notch's ceiling 5 mm above its top. Nothing touches.
    scene = {"name": "notch",
             "body": {"mesh": {"generator": "box", "size": [0.04, 0.04, 0.04], "cell": 0.01,
                               "origin": [-0.02, -0.02, 0.0]},
                      "material": {"model": "neohookean", "young": 1e5, "poisson": 0.3, "density": 1000}},
             "colliders": {"floor": {"shape": "plane"},
                           "u": dict(spec, position=[0.0, 0.0, 0.065], orientation=[1.0, 0.0, 0.0, 0.0])},
             "model": {"kind": "full", "integrator": {"dt": 0.01, "newton_iterations": 2}}}
    sim = Simulator(scene, cache=PrecomputeCache(tmp_path / "cache"))
    assert not sim.colliders_inside_at_load
    phi0 = sim.colliders["u"].signed_distance(sim.rest_positions())[0]
    assert phi0.min() > 0.004
    sim.step(30)
    assert np.allclose(sim.collider_wrench("u"), 0.0)
    assert sim.collider_wrench("floor")[2] < 0                 # the floor carries the block
    assert sim.colliders["u"].signed_distance(sim.vertex_positions())[0].min() > 0.004


def test_the_grid_is_cached_and_a_second_build_hits(tmp_path):
    path = _write(trimesh.creation.icosphere(subdivisions=2, radius=0.05), tmp_path, "ball.obj")
    spec = {"shape": "mesh", "file": str(path), "resolution": 0.005}
    first = PrecomputeCache(tmp_path / "cache")
    a = make_collider("a", spec, cache=first)
    assert [e[1] for e in first.events if e[0] == "collider_sdf"] == ["miss", "saved"]
    second = PrecomputeCache(tmp_path / "cache")
    b = make_collider("a", spec, cache=second)
    assert [e[1] for e in second.events if e[0] == "collider_sdf"] == ["hit"]
    assert np.array_equal(a.sdf.phi, b.sdf.phi)
    # Another scale or resolution is another entry.
    third = PrecomputeCache(tmp_path / "cache")
    make_collider("a", dict(spec, scale=2.0), cache=third)
    assert [e[1] for e in third.events if e[0] == "collider_sdf"] == ["miss", "saved"]
    # A memo (the Simulator keeps one across resets) skips the disk entirely.
    memo, fourth = {}, PrecomputeCache(tmp_path / "cache")
    make_collider("a", spec, cache=fourth, memo=memo)
    make_collider("a", spec, cache=fourth, memo=memo)
    assert [e[1] for e in fourth.events if e[0] == "collider_sdf"] == ["hit"]


def test_bad_mesh_collider_specs_name_the_key_and_the_problem(tmp_path):
    _write(trimesh.creation.icosphere(subdivisions=1, radius=0.05), tmp_path, "ball.obj")
    open_mesh = trimesh.creation.icosphere(subdivisions=1, radius=0.05)
    open_mesh.update_faces(np.arange(len(open_mesh.faces)) != 0)
    _write(open_mesh, tmp_path, "open.obj")
    (tmp_path / "ball.txt").write_text("not a mesh")
    cache = PrecomputeCache(tmp_path / "cache")
    cases = [({"file": "ball.obj", "radius": 1.0}, r"colliders\.m: unknown key\(s\) \['radius'\]"),
             ({}, r"colliders\.m\.file: required"),
             ({"file": "missing.obj"}, r"colliders\.m\.file: .*not found"),
             ({"file": "ball.txt"}, r"colliders\.m\.file: .*not a supported surface file"),
             ({"file": "open.obj"}, r"colliders\.m\.file: .*not closed.*1 hole\(s\); largest: 3 edges"),
             ({"file": "ball.obj", "scale": 0}, r"colliders\.m\.scale: expected a number > 0"),
             ({"file": "ball.obj", "scale": -1.0}, r"colliders\.m\.scale: expected a number > 0"),
             ({"file": "ball.obj", "resolution": "fine"}, r"colliders\.m\.resolution: expected a number > 0"),
             ({"file": "ball.obj", "resolution": 1e-5}, r"colliders\.m\.resolution: .* nodes, more than")]
    for extra, message in cases:
        with pytest.raises(SceneError, match=message):
            make_collider("m", dict(shape="mesh", **extra), base_dir=tmp_path, cache=cache)
    # The scene checks the keys and the file at load, relative to the scene file.
    scene = tmp_path / "s.yaml"
    body = "name: s\nbody: {mesh: {generator: box, size: [0.1, 0.1, 0.1], cell: 0.05}, material: {model: neohookean, young: 1.0e5, poisson: 0.3, density: 1000}}\n"
    scene.write_text(body + "colliders: {m: {shape: mesh, file: ball.obj}}\n")
    assert load_scene(str(scene))["colliders"]["m"]["file"] == "ball.obj"
    scene.write_text(body + "colliders: {m: {shape: mesh, file: nope.stl}}\n")
    with pytest.raises(SceneError, match=r"colliders\.m\.file: .*nope\.stl.*not found"):
        load_scene(str(scene))
    scene.write_text(body + "colliders: {m: {shape: mesh, file: ball.obj, size: 2}}\n")
    with pytest.raises(SceneError, match=r"colliders\.m: unknown key\(s\) \['size'\]"):
        load_scene(str(scene))


def test_grid_query_is_exact_for_a_linear_field_and_extends_outside_the_box():
    """The compiled trilinear query (mesh_sdf._trilinear) against closed forms: trilinear
    interpolation reproduces a linear field phi = a . x + b exactly, and np.gradient of it
    is a everywhere, so inside the grid phi is a . p + b and the normal a / |a|; outside it
    phi is phi(c) + |p - c| for c the closest point of the box, with the normal of that
    extension's gradient."""
    from mdss_ros.contact.mesh_sdf import MeshSDF
    a, b = np.array([0.3, -0.5, 0.8]), -0.02
    origin, h, counts = np.array([-0.05, -0.04, -0.03]), 0.01, (11, 9, 7)
    axes = [origin[k] + h * np.arange(counts[k]) for k in range(3)]
    nodes = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1)
    sdf = MeshSDF(nodes @ a + b, origin, h)
    rng = np.random.default_rng(3)
    inside = sdf.origin + (sdf.upper - sdf.origin) * rng.random((500, 3))
    inside[:3] = [sdf.origin, sdf.upper, sdf.origin + h * np.array([2, 3, 4])]    # corners and a node
    phi, n = sdf.evaluate(inside)
    np.testing.assert_allclose(phi, inside @ a + b, rtol=0, atol=1e-15)
    np.testing.assert_allclose(n, np.broadcast_to(a / np.linalg.norm(a), n.shape), rtol=0, atol=1e-13)
    np.testing.assert_array_equal(sdf.distance(inside), phi)
    # Outside: 2 cm beyond the +x face (grad of the extension: +x there, a's other parts kept).
    p = np.array([[sdf.upper[0] + 0.02, 0.0, 0.0], [sdf.origin[0] - 0.03, sdf.upper[1] + 0.04, 0.01]])
    c = np.clip(p, sdf.origin, sdf.upper)
    phi_out, n_out = sdf.evaluate(p)
    np.testing.assert_allclose(phi_out, c @ a + b + np.linalg.norm(p - c, axis=1), atol=1e-15)
    d = (p - c) / np.linalg.norm(p - c, axis=1)[:, None]
    g = np.where(p != c, 0.0, a) + d
    np.testing.assert_allclose(n_out, g / np.linalg.norm(g, axis=1)[:, None], atol=1e-13)
    # A flat field has no gradient: the medial fallback normal.
    flat = MeshSDF(np.zeros(counts), origin, h)
    np.testing.assert_array_equal(flat.evaluate(inside[:4])[1], np.tile([0.0, 0.0, 1.0], (4, 1)))


def test_grid_query_matches_trilinear_interpolation_of_a_curved_field():
    """The compiled query against trilinear interpolation written out here on a curved
    field (where a wrong corner or weight shows), phi and the interpolated gradient's
    direction, and a point with a non-finite coordinate reads no node: NaN."""
    from mdss_ros.contact.mesh_sdf import MeshSDF
    origin, h, counts = np.array([0.0, -0.02, 0.01]), 0.005, (9, 12, 7)
    axes = [origin[k] + h * np.arange(counts[k]) for k in range(3)]
    X, Y, Z = np.meshgrid(*axes, indexing="ij")
    sdf = MeshSDF(np.sin(40 * X) * np.cos(30 * Y) + 20 * Z ** 2, origin, h)
    p = sdf.origin + (sdf.upper - sdf.origin) * np.random.default_rng(8).random((300, 3))
    u = (p - origin) / h
    i = np.minimum(np.floor(u).astype(int), np.array(counts) - 2)
    t = u - i
    phi, g = np.zeros(len(p)), np.zeros((len(p), 3))
    for dx in (0, 1):
        for dy in (0, 1):
            for dz in (0, 1):
                w = ((t[:, 0] if dx else 1 - t[:, 0]) * (t[:, 1] if dy else 1 - t[:, 1])
                     * (t[:, 2] if dz else 1 - t[:, 2]))
                idx = (i[:, 0] + dx, i[:, 1] + dy, i[:, 2] + dz)
                phi += w * sdf.phi[idx]
                g += w[:, None] * sdf.grad[idx]
    got_phi, got_n = sdf.evaluate(p)
    np.testing.assert_allclose(got_phi, phi, rtol=0, atol=1e-14)
    np.testing.assert_allclose(got_n, g / np.linalg.norm(g, axis=1)[:, None], rtol=0, atol=1e-12)
    bad = np.array([[np.nan, 0.0, 0.02], [0.01, np.inf, 0.02]])
    assert np.isnan(sdf.evaluate(bad)[0]).all() and np.isnan(sdf.evaluate(bad)[1]).all()
    assert np.isnan(sdf.distance(bad)).all()
