"""Voxel bodies: a union of primitives sampled on a grid, Kuhn-split into tets.

Large limbed bodies (hundreds of thousands of tets) come out in a second, identical on
every run and conforming by construction, where fTetWild takes minutes and differs from
run to run. The surface is a staircase at the cell size; for performance scenes that is
what we want (the element count and the limb structure, not a smooth skin).

Primitives use the same dicts as `composite` (shape, position, rotation_rpy; box size,
sphere radius, ellipsoid radii, capsule/cylinder radius and height along local z).
"""
import numpy as np

from ..errors import MeshError
from .generators import tensor_grid
from .tetmesh import TetMesh, remove_unreferenced


def _rotation(rpy):
    r, p, y = rpy
    cx, sx, cy, sy, cz, sz = np.cos(r), np.sin(r), np.cos(p), np.sin(p), np.cos(y), np.sin(y)
    Rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    Ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    Rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    return Rz @ Ry @ Rx


def signed_distance(spec, points):
    """Signed distance (negative inside) of one primitive at points (n, 3)."""
    shape = spec.get("shape")
    pos = np.asarray(spec.get("position", (0, 0, 0)), dtype=np.float64)
    R = _rotation(spec.get("rotation_rpy", (0, 0, 0)))
    p = (points - pos) @ R                                     # local coordinates
    try:
        if shape == "sphere":
            return np.linalg.norm(p, axis=1) - float(spec["radius"])
        if shape == "ellipsoid":
            radii = np.asarray(spec["radii"], dtype=np.float64)
            return (np.linalg.norm(p / radii, axis=1) - 1.0) * radii.min()
        if shape == "box":
            q = np.abs(p) - 0.5 * np.asarray(spec["size"], dtype=np.float64)
            return np.linalg.norm(np.maximum(q, 0.0), axis=1) + np.minimum(q.max(axis=1), 0.0)
        if shape in ("capsule", "cylinder"):
            h, r = 0.5 * float(spec["height"]), float(spec["radius"])
            if shape == "capsule":
                axial = p.copy()
                axial[:, 2] -= np.clip(p[:, 2], -h, h)
                return np.linalg.norm(axial, axis=1) - r
            d = np.stack([np.linalg.norm(p[:, :2], axis=1) - r, np.abs(p[:, 2]) - h], axis=1)
            return np.linalg.norm(np.maximum(d, 0.0), axis=1) + np.minimum(d.max(axis=1), 0.0)
    except KeyError as err:
        raise MeshError(f"primitive {shape!r} needs key {err.args[0]!r}") from err
    raise MeshError(f"unknown primitive shape {shape!r} (sphere, ellipsoid, box, capsule, cylinder)")


def largest_face_connected(occupied):
    """Keep the largest set of voxels connected through faces (bool (nz, ny, nx)).

    Voxels meeting only along an edge or at a corner share two or one vertices: a hinge
    that makes the stiffness singular. Dropping what hangs on by such contacts removes
    those zero-energy mechanisms."""
    from scipy import ndimage
    labels, count = ndimage.label(occupied)          # default structure: 6-connectivity
    if count <= 1:
        return occupied
    sizes = np.bincount(labels.ravel())
    sizes[0] = 0
    return labels == int(np.argmax(sizes))


def voxel_body(primitives, cell):
    """TetMesh of the union of primitives, voxelised at `cell` (6 tets per voxel).

    A voxel is in when the union's signed distance at its centre is <= 0. Vertices no tet
    uses are dropped.
    """
    if not primitives:
        raise MeshError("voxel_body needs at least one primitive")
    cell = float(cell)
    if not cell > 0:
        raise MeshError(f"cell must be positive, got {cell}")
    # Bounds from dense samples of each primitive's extent: pad generously, trim later.
    lo = np.full(3, np.inf)
    hi = np.full(3, -np.inf)
    for spec in primitives:
        pos = np.asarray(spec.get("position", (0, 0, 0)), dtype=np.float64)
        extent = max([float(spec.get("radius", 0)) + 0.5 * float(spec.get("height", 0))]
                     + [0.5 * float(np.linalg.norm(spec.get("size", (0, 0, 0))))]
                     + [float(np.max(spec.get("radii", (0,))))])
        lo, hi = np.minimum(lo, pos - extent), np.maximum(hi, pos + extent)
    n = np.maximum(1, np.ceil((hi - lo) / cell).astype(int) + 2)
    origin = lo - cell
    axes = [origin[a] + cell * np.arange(n[a] + 1) for a in range(3)]
    zc, yc, xc = np.meshgrid(*(ax[:-1] + 0.5 * cell for ax in axes[::-1]), indexing="ij")
    centres = np.stack([xc.ravel(), yc.ravel(), zc.ravel()], axis=1)
    sdf = np.min([signed_distance(spec, centres) for spec in primitives], axis=0)
    inside = sdf <= 0.0
    if not inside.any():
        raise MeshError(f"no voxel of size {cell} lies inside the primitives; use a smaller cell")
    inside = largest_face_connected(inside.reshape(n[2], n[1], n[0])).ravel()
    grid = tensor_grid(*axes)
    tets = grid.tets[np.repeat(inside, 6)]
    return remove_unreferenced(TetMesh(grid.vertices, tets))
