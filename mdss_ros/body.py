"""The deformable body of a scene: mesh, material, pinned vertices, handles, surface.

Everything here is geometry and bookkeeping shared by every model kind; it is built
once from the scene and never changes during a run.
"""
from dataclasses import dataclass

import numpy as np

from .errors import MeshError, SceneError
from .fem.materials import make_material
from .mesh import box, composite, extract_surface, graded_block, load_mesh, select_vertices, sheet
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


def build_mesh(spec, base_dir, source="<scene>"):
    """TetMesh from a scene's body.mesh mapping (a generator or a file)."""
    spec = dict(spec)
    where = f"{source}: body.mesh"
    try:
        if "file" in spec:
            path = base_dir / spec.pop("file")
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
    return mesh


def build_body(scene):
    """Body of a validated Scene."""
    src = scene.source
    mesh = build_mesh(scene["body"]["mesh"], scene.base_dir, src)
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
