"""The deformable body of a scene: mesh, material, pinned vertices, handles, surface.

Everything here is geometry and bookkeeping shared by every model kind; it is built
once from the scene and never changes during a run.
"""
import hashlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .errors import MeshError, SceneError
from .fem.materials import make_material
from .mesh import box, composite, extract_surface, graded_block, load_mesh, select_vertices, sheet
from .mesh.io import SURFACE_EXTENSIONS
from .mesh.voxels import voxel_body


@dataclass(frozen=True)
class Body:
    """vertices (n_verts, 3) rest positions; tets (n_tets, 4); surface (mesh.Surface);
    pinned (k,) sorted vertex ids; handles {name: (h,) vertex ids}; material."""

    vertices: np.ndarray
    tets: np.ndarray
    surface: object
    pinned: np.ndarray
    handles: dict
    material: object


_GENERATORS = {"box": box, "sheet": sheet, "graded_block": graded_block, "voxels": voxel_body}


def build_mesh(spec, base_dir, source="<scene>", cache=None):
    """TetMesh from a scene's body.mesh mapping (a generator or a file). cache: the
    PrecomputeCache that keeps tetrahedralised surface files (default: the user's)."""
    spec = dict(spec)
    from_file = "file" in spec
    where = f"{source}: body.mesh"
    try:
        if "file" in spec:
            path = base_dir / spec.pop("file")
            if path.suffix.lower() in SURFACE_EXTENSIONS and path.is_file():
                mesh = _tetrahedralised_surface(path, spec, cache)
            else:
                mesh = load_mesh(path, **spec)
        elif "generator" in spec:
            gen = spec.pop("generator")
            if gen == "composite":
                mesh = composite(**spec)
            elif gen in _GENERATORS:
                mesh = _GENERATORS[gen](**spec)
            else:
                raise SceneError(f"{where}.generator: unknown generator {gen!r} "
                                 f"(box, sheet, graded_block, voxels, composite)")
        else:
            raise SceneError(f"{where}: needs either 'generator' or 'file'")
    except TypeError as err:
        raise SceneError(f"{where}: {err}") from err
    except MeshError as err:
        raise SceneError(f"{where}: {err}") from err
    mesh.validate()
    if from_file:
        _unit_note(mesh, spec, where)
    return mesh


def _unit_note(mesh, spec, where):
    """Scenes are in metres, and CAD exports are often in millimetres: a body tens of metres
    across from a file without a scale key is most likely one (a robot part is not)."""
    import warnings
    size = float(np.linalg.norm(mesh.vertices.max(0) - mesh.vertices.min(0)))
    if "scale" not in spec and size > 10.0:
        warnings.warn(f"{where}: the body is {size:.4g} m across; scene units are metres. If the file is in "
                      f"millimetres, set body.mesh.scale: 0.001 (and edge_length in metres)", stacklevel=3)


def _tetrahedralised_surface(path, spec, cache):
    """load_mesh of a surface file, kept in the precompute cache under the file's bytes,
    the meshing options and the mesher's code. fTetWild does not mesh the same surface the
    same way twice, so without this every start of a surface-file scene got a new tet mesh:
    its precompute never hit the cache, and recordings of two runs had different topology."""
    import pytetwild

    from .mesh.tetmesh import TetMesh
    from .precompute import PrecomputeCache, cache_key, code_fingerprint

    cache = cache if cache is not None else PrecomputeCache()
    here = Path(__file__).resolve().parent / "mesh"
    code = [code_fingerprint((here / name).read_text()) for name in ("io.py", "tetrahedralize.py")]
    key = cache_key(hashlib.sha256(path.read_bytes()).hexdigest(), spec,
                    getattr(pytetwild, "__version__", "?"), code)
    hit = cache.load("tetmesh", key)
    if hit is not None:
        arrays, _ = hit
        return TetMesh(arrays["vertices"], arrays["tets"])
    mesh = load_mesh(path, **spec)
    cache.save("tetmesh", key, {"vertices": mesh.vertices, "tets": mesh.tets},
               {"file": str(path), "options": {k: v for k, v in spec.items()}})
    return mesh


def pinned_mesh_overrides(scene, folder, cache=None):
    """Scene overrides that pin a surface-file body to one tet mesh: {} for a generator or
    a volume file, else {"body.mesh": {"file": <folder>/<name>_tets.vtu}} after meshing
    it once (or reading it from cache). Studies that build each configuration in its own,
    emptied cache (mdss tradeoff) need this: fTetWild meshes a surface differently every
    time, and errors between runs on different meshes mean nothing."""
    from .mesh import save_mesh
    spec = scene["body"]["mesh"]
    if "file" not in spec or Path(spec["file"]).suffix.lower() not in SURFACE_EXTENSIONS:
        return {}
    mesh = build_mesh(spec, scene.base_dir, scene.source, cache)
    path = Path(folder).resolve() / f"{scene.name}_tets.vtu"
    path.parent.mkdir(parents=True, exist_ok=True)
    save_mesh(path, mesh)
    return {"body.mesh": {"file": str(path)}}


def build_body(scene, cache=None):
    """Body of a validated Scene. cache: PrecomputeCache for tetrahedralised surface files."""
    src = scene.source
    mesh = build_mesh(scene["body"]["mesh"], scene.base_dir, src, cache)
    try:
        material = make_material(scene["body"]["material"])
    except SceneError as err:
        raise SceneError(f"{src}: body.material: {err}") from err
    surface = extract_surface(mesh.tets)
    pinned = [np.empty(0, dtype=np.int64)]
    for i, region in enumerate(scene["pins"]):
        ids = _select(mesh.vertices, region, surface.vertex_ids, f"{src}: pins[{i}]")
        if ids.size == 0:
            raise SceneError(f"{src}: pins[{i}]: the region {region} selects no vertex of the body "
                             f"(body bounds {_bounds(mesh.vertices)})")
        pinned.append(ids)
    handles = {}
    for name, region in scene["handles"].items():
        ids = _select(mesh.vertices, region, surface.vertex_ids, f"{src}: handles.{name}")
        if ids.size == 0:
            raise SceneError(f"{src}: handles.{name}: the region {region} selects no vertex of the body, "
                             f"so it lies outside the body (body bounds {_bounds(mesh.vertices)})")
        handles[name] = ids
    return Body(vertices=mesh.vertices, tets=mesh.tets, surface=surface,
                pinned=np.unique(np.concatenate(pinned)), handles=handles, material=material)


def _select(vertices, region, surface_ids, where):
    """select_vertices with the scene key in front of a bad-selector message."""
    try:
        return select_vertices(vertices, region, surface_ids)
    except SceneError as err:
        raise SceneError(f"{where}: {err}") from err


def _bounds(vertices):
    return f"{vertices.min(0).round(4).tolist()} .. {vertices.max(0).round(4).tolist()}"
