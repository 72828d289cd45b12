"""Mesh files and fTetWild: round trips, surface import, clean cwd, clear errors."""
import meshio
import numpy as np
import pytest
import trimesh

from mdss_ros.errors import MeshError
from mdss_ros.mesh import TetMesh, box, boundary_faces, load_mesh, save_mesh, tetrahedralize
from mdss_ros.mesh.tetmesh import signed_volumes


def _assert_closed(mesh):
    faces = boundary_faces(mesh.tets)
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    _, counts = np.unique(np.sort(edges, axis=1), axis=0, return_counts=True)
    assert np.all(counts == 2)


@pytest.mark.parametrize("ext", [".vtu", ".msh", ".vtk"])
def test_save_load_round_trip_is_exact(tmp_path, ext):
    mesh = box(size=(0.3, 0.2, 0.1), cell=0.05, origin=(0.1, 0.2, 0.3))
    path = tmp_path / f"body{ext}"
    save_mesh(path, mesh)
    back = load_mesh(path)
    assert np.array_equal(back.vertices, mesh.vertices)
    assert np.array_equal(back.tets, mesh.tets)


def test_load_reorients_tets_and_drops_unreferenced_vertices(tmp_path):
    mesh = box(size=(0.2, 0.2, 0.2), cell=0.1)
    flipped = mesh.tets[:, [0, 2, 1, 3]]
    points = np.vstack([mesh.vertices, [[9.0, 9.0, 9.0]]])  # e.g. a gmsh geometry point
    path = tmp_path / "flipped.vtu"
    cells = [("tetra", flipped), ("vertex", [[points.shape[0] - 1]])]
    meshio.write(path, meshio.Mesh(points, cells))
    back = load_mesh(path)
    assert back.n_verts == mesh.n_verts
    assert np.all(signed_volumes(back.vertices, back.tets) > 0)
    assert signed_volumes(back.vertices, back.tets).sum() == pytest.approx(0.008, rel=1e-12)


def test_load_obj_surface_is_tetrahedralised_in_a_clean_cwd(tmp_path, monkeypatch):
    surface = trimesh.creation.box(extents=(0.4, 0.3, 0.2))
    path = tmp_path / "part.obj"
    surface.export(path)
    workdir = tmp_path / "cwd"
    workdir.mkdir()
    monkeypatch.chdir(workdir)
    mesh = load_mesh(path, edge_length=0.1)
    vol = signed_volumes(mesh.vertices, mesh.tets)
    assert vol.min() > 0
    # fTetWild keeps the surface within its envelope (1e-3 of the bbox
    # diagonal), not exactly: flat faces may ripple by ~1e-6 here.
    assert vol.sum() == pytest.approx(0.024, rel=1e-4)
    assert np.allclose(mesh.vertices.min(axis=0), [-0.2, -0.15, -0.1], atol=5e-4)
    _assert_closed(mesh)
    assert list(workdir.iterdir()) == []


def test_tetrahedralize_accepts_inside_out_surface(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    surface = trimesh.creation.box(extents=(1.0, 1.0, 1.0))
    mesh = tetrahedralize(surface.vertices, surface.faces[:, ::-1], edge_length=0.5)
    assert isinstance(mesh, TetMesh)
    assert signed_volumes(mesh.vertices, mesh.tets).min() > 0
    assert signed_volumes(mesh.vertices, mesh.tets).sum() == pytest.approx(1.0, rel=1e-4)
    used = np.zeros(mesh.n_verts, bool)
    used[mesh.tets.ravel()] = True
    assert used.all()
    assert list(tmp_path.iterdir()) == []


def test_an_obj_missing_two_faces_is_repaired_not_rejected(tmp_path):
    """Two triangles missing from a box leave one 4-edge hole: trimesh fills it (the shape
    is unchanged: the two triangles come back), where this used to be rejected."""
    from mdss_ros.mesh.tetrahedralize import MeshRepairWarning
    surface = trimesh.creation.box(extents=[0.2, 0.2, 0.2])
    keep = np.ones(len(surface.faces), dtype=bool)
    keep[:2] = False
    opened = trimesh.Trimesh(surface.vertices, surface.faces[keep], process=False)
    opened.export(tmp_path / "open.obj")
    with pytest.warns(MeshRepairWarning, match="filled 1 small holes"):
        mesh = load_mesh(tmp_path / "open.obj")
    np.testing.assert_allclose(np.ptp(mesh.vertices, axis=0), [0.2, 0.2, 0.2], rtol=1e-9)


def test_tetrahedralize_rejects_bad_arrays():
    surface = trimesh.creation.box()
    v = surface.vertices.copy()
    v[0, 1] = np.nan
    with pytest.raises(MeshError, match="NaN"):
        tetrahedralize(v, surface.faces)
    with pytest.raises(MeshError, match="outside"):
        tetrahedralize(surface.vertices, surface.faces + 100)
    with pytest.raises(MeshError, match="edge_length"):
        tetrahedralize(surface.vertices, surface.faces, edge_length=-1.0)


def test_load_errors_name_the_problem(tmp_path):
    with pytest.raises(MeshError, match="not found"):
        load_mesh(tmp_path / "missing.vtu")
    with pytest.raises(MeshError, match="unsupported mesh extension '.step'"):
        load_mesh(tmp_path / "part.step")
    garbage = tmp_path / "garbage.vtu"
    garbage.write_text("not a mesh")
    with pytest.raises(MeshError, match="garbage.vtu: cannot read"):
        load_mesh(garbage)
    tris_only = tmp_path / "tris.vtu"
    meshio.write(tris_only, meshio.Mesh(np.eye(3), [("triangle", [[0, 1, 2]])]))
    with pytest.raises(MeshError, match=r"no linear 'tetra' cells \(found \['triangle'\]\)"):
        load_mesh(tris_only)
    degenerate = tmp_path / "flat.vtu"
    flat = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]])
    meshio.write(degenerate, meshio.Mesh(flat, [("tetra", [[0, 1, 2, 3]])]))
    with pytest.raises(MeshError, match="flat.vtu: 1 degenerate"):
        load_mesh(degenerate)
    with pytest.raises(MeshError, match="cannot save"):
        save_mesh(tmp_path / "out.obj", box(size=(1, 1, 1), cell=1.0))


def _surface_scene(tmp_path, **mesh):
    if not (tmp_path / "pad.obj").exists():
        trimesh.creation.capsule(height=0.04, radius=0.01, count=[12, 12]).export(tmp_path / "pad.obj")
    return {"name": "pad", "body": {"mesh": {"file": str(tmp_path / "pad.obj"), "edge_length": 0.006, **mesh},
                                    "material": {"model": "neohookean", "young": 2e5, "poisson": 0.4,
                                                 "density": 1100}},
            "pins": [{"box": [[-1, -1, -1], [1, 1, -0.026]]}],
            "model": {"kind": "reduced", "domains": {"count": 2}, "modes": 6,
                      "cubature": {"samples": 0, "interface": "exact"}}}


def test_a_surface_scene_loaded_twice_gets_the_same_tets_and_builds_nothing(tmp_path):
    """fTetWild meshes a surface differently each time; the body keeps the first result in
    the precompute cache (keyed by the file's bytes and the options), so a second start has
    the same topology and hits the bases and cubature cache."""
    from mdss_ros import Simulator, load_scene
    from mdss_ros.precompute import PrecomputeCache
    scene = load_scene(_surface_scene(tmp_path))
    first = Simulator(scene, cache=PrecomputeCache(tmp_path / "cache"))
    cache = PrecomputeCache(tmp_path / "cache")
    second = Simulator(scene, cache=cache)
    np.testing.assert_array_equal(second.tetrahedra(), first.tetrahedra())
    np.testing.assert_array_equal(second.rest_positions(), first.rest_positions())
    assert {(stage, what) for stage, what, _ in cache.events} == {("tetmesh", "hit"), ("bases", "hit")}
    # Another edge length, or another file content, is meshed anew.
    from mdss_ros.body import build_body
    other = PrecomputeCache(tmp_path / "cache")
    build_body(load_scene(_surface_scene(tmp_path, edge_length=0.008)), other)
    assert [(s, w) for s, w, _ in other.events] == [("tetmesh", "miss"), ("tetmesh", "saved")]
    trimesh.creation.capsule(height=0.05, radius=0.01, count=[12, 12]).export(tmp_path / "pad.obj")
    other = PrecomputeCache(tmp_path / "cache")
    longer = build_body(load_scene(_surface_scene(tmp_path)), other)
    assert [(s, w) for s, w, _ in other.events] == [("tetmesh", "miss"), ("tetmesh", "saved")]
    assert np.ptp(longer.vertices[:, 2]) > np.ptp(first.rest_positions()[:, 2]) + 0.009


def test_a_study_pins_a_surface_body_to_one_tet_mesh(tmp_path):
    """mdss tradeoff builds each configuration in an emptied cache; the surface body is
    meshed once and every configuration reads that .vtu (fTetWild differs run to run)."""
    from mdss_ros import load_scene
    from mdss_ros.body import build_body, pinned_mesh_overrides
    from mdss_ros.precompute import PrecomputeCache
    scene = load_scene(_surface_scene(tmp_path))
    cache = PrecomputeCache(tmp_path / "cache")
    ov = pinned_mesh_overrides(scene, tmp_path / "study", cache)
    assert ov["body.mesh"]["file"].endswith("_tets.vtu")
    first = build_body(scene, cache)
    for _ in range(2):                                   # fresh caches, the same tets
        pinned = build_body(load_scene(_surface_scene(tmp_path), ov), PrecomputeCache(tmp_path / "other"))
        np.testing.assert_array_equal(pinned.tets, first.tets)
        np.testing.assert_allclose(pinned.vertices, first.vertices, rtol=0, atol=1e-12)
    assert pinned_mesh_overrides(load_scene("cantilever"), tmp_path / "study") == {}


def test_a_surface_with_a_small_hole_is_repaired_and_says_so(tmp_path, monkeypatch):
    from mdss_ros.mesh.tetrahedralize import MeshRepairWarning
    monkeypatch.chdir(tmp_path)
    s = trimesh.creation.icosphere(subdivisions=2, radius=0.05)
    trimesh.Trimesh(s.vertices, s.faces[1:], process=False).export(tmp_path / "holed.obj")
    with pytest.warns(MeshRepairWarning, match="filled 1 small holes"):
        mesh = load_mesh(tmp_path / "holed.obj", edge_length=0.02)
    assert len(mesh.tets) > 0 and np.all(signed_volumes(mesh.vertices, mesh.tets) > 0)


def test_a_surface_with_a_flipped_triangle_is_rewound_and_says_so(tmp_path, monkeypatch):
    from mdss_ros.mesh.tetrahedralize import MeshRepairWarning
    monkeypatch.chdir(tmp_path)
    s = trimesh.creation.icosphere(subdivisions=2, radius=0.05)
    f = s.faces.copy()
    f[5] = f[5][::-1]
    trimesh.Trimesh(s.vertices, f, process=False).export(tmp_path / "flipped.obj")
    with pytest.warns(MeshRepairWarning, match="re-wound"):
        load_mesh(tmp_path / "flipped.obj", edge_length=0.02)


def test_a_surface_with_a_large_hole_is_rejected_with_where_the_hole_is(tmp_path):
    s = trimesh.creation.icosphere(subdivisions=2, radius=0.05)
    keep = s.triangles_center[:, 2] < 0.04                 # a cap of 28 triangles cut off the top
    trimesh.Trimesh(s.vertices, s.faces[keep], process=False).export(tmp_path / "open.obj")
    with pytest.raises(MeshError) as err:
        load_mesh(tmp_path / "open.obj", edge_length=0.02)
    msg = str(err.value)
    assert "1 hole(s) too large to fill" in msg and "edges around" in msg
    centre = [float(v) for v in msg.split("around [")[1].split("]")[0].split(",")]
    assert centre[2] > 0.04 and abs(centre[0]) < 0.01 and abs(centre[1]) < 0.01      # at the top


def test_scale_turns_millimetres_into_metres_and_a_huge_body_gets_a_unit_note(tmp_path, monkeypatch):
    from mdss_ros import load_scene
    from mdss_ros.body import build_body
    monkeypatch.chdir(tmp_path)
    trimesh.creation.box(extents=[40.0, 20.0, 20.0]).export(tmp_path / "pad_mm.stl")   # 40 x 20 x 20 mm
    scene = {"name": "mm", "body": {"mesh": {"file": str(tmp_path / "pad_mm.stl"), "scale": 0.001,
                                             "edge_length": 0.01},
                                    "material": {"model": "stvk", "young": 1e5, "poisson": 0.3, "density": 1000}},
             "model": {"kind": "full"}}
    body = build_body(load_scene(scene))
    np.testing.assert_allclose(np.ptp(body.vertices, axis=0), [0.04, 0.02, 0.02], rtol=1e-6)
    scene["body"]["mesh"] = {"file": str(tmp_path / "pad_mm.stl"), "edge_length": 10.0}
    with pytest.warns(UserWarning, match="body.mesh.scale: 0.001"):
        build_body(load_scene(scene))
    with pytest.raises(MeshError, match="scale must be a positive number"):
        load_mesh(tmp_path / "pad_mm.stl", scale=-1.0)
