"""Tet mesh generators: structured boxes, sheets, graded blocks, CSG composites.

Structured generators (``box``, ``sheet``, ``graded_block``) build a tensor
grid of hexahedra from three 1D node arrays and split every hex into the same
6 Kuhn (Freudenthal) tets along its (min corner -> max corner) diagonal.
Because every hex uses the same diagonal, each shared quad face is cut along
the same face diagonal from both sides, so the mesh is conforming.

Vertex numbering: with node counts (NX, NY, NZ) = (nx+1, ny+1, nz+1), the
vertex at grid node (i, j, k) has index i + NX * (j + NY * k) (x fastest,
then y, then z). Tets are emitted cell by cell in the same x-fastest cell
order, 6 consecutive tets per cell. All tets are positively oriented.

Kuhn tets of a rectangular cell are orthoschemes: every dihedral angle is
<= 90 deg (45/60/90 for a cube), so even stretched cells never produce the
obtuse angles that spoil interpolation; only their min angle shrinks.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from mdss_ros.errors import MeshError
from mdss_ros.mesh.tetmesh import TetMesh

# Guard against a unit mistake (cell in mm, size in m) exhausting memory.
_MAX_TETS = 50_000_000

# Hex corner c = bx + 2*by + 4*bz. Each Kuhn tet walks 0 -> 7 along the axes in
# one of the 6 permutations; odd permutations have det < 0, so their last two
# vertices are swapped to make all six positively oriented.
_KUHN = np.array(
    [
        [0, 1, 3, 7],  # x, y, z
        [0, 1, 7, 5],  # x, z, y (swapped)
        [0, 2, 7, 3],  # y, x, z (swapped)
        [0, 2, 6, 7],  # y, z, x
        [0, 4, 5, 7],  # z, x, y
        [0, 4, 7, 6],  # z, y, x (swapped)
    ],
    dtype=np.int64,
)


def box(
    size: Sequence[float],
    cell: float,
    origin: Sequence[float] = (0.0, 0.0, 0.0),
) -> TetMesh:
    """Structured tet mesh of the axis-aligned box [origin, origin + size].

    Each axis gets n_i = max(1, round(l_i / cell)) equal cells, so the outer
    dimensions are exact and the cell size along axis i is l_i / n_i.

    Args:
        size: (3,) edge lengths (lx, ly, lz) > 0.
        cell: target cell edge length > 0.
        origin: (3,) min corner.
    Returns:
        TetMesh with n_verts = (nx+1)(ny+1)(nz+1), n_tets = 6 nx ny nz.
    """
    size = _positive_vector(size, 3, "size")
    cell = _positive_scalar(cell, "cell")
    origin = _finite_vector(origin, 3, "origin")
    counts = np.maximum(1, np.round(size / cell)).astype(np.int64)
    axes = [_uniform_axis(o, l, n) for o, l, n in zip(origin, size, counts)]
    return tensor_grid(*axes)


def sheet(
    size: Sequence[float],
    thickness: float,
    cell: float,
    layers: int = 1,
    origin: Sequence[float] = (0.0, 0.0, 0.0),
) -> TetMesh:
    """Thin plate in the xy plane, ``layers`` cells through the thickness (z).

    In-plane cells follow ``box`` (n_i = max(1, round(l_i / cell))); the
    through-thickness cell height is thickness / layers, independent of cell.

    Args:
        size: (2,) in-plane lengths (lx, ly) > 0.
        thickness: plate thickness > 0 along z.
        cell: target in-plane cell length > 0.
        layers: number of cells through the thickness, >= 1.
        origin: (3,) min corner.
    Returns:
        TetMesh with n_tets = 6 nx ny layers, numbered as in ``box``.
    """
    size = _positive_vector(size, 2, "size")
    thickness = _positive_scalar(thickness, "thickness")
    cell = _positive_scalar(cell, "cell")
    origin = _finite_vector(origin, 3, "origin")
    if isinstance(layers, bool) or not isinstance(layers, (int, np.integer)) or layers < 1:
        raise MeshError(f"layers must be an integer >= 1, got {layers!r}")
    counts = np.maximum(1, np.round(size / cell)).astype(np.int64)
    return tensor_grid(
        _uniform_axis(origin[0], size[0], counts[0]),
        _uniform_axis(origin[1], size[1], counts[1]),
        _uniform_axis(origin[2], thickness, int(layers)),
    )


def _graded_arguments(size, cell_coarse, cell_fine, focus, origin, radius):
    """The checked arguments both graded blocks share: (size (3,), h_coarse, h_fine,
    focus (3,), origin (3,), radius); MeshError names the bad one."""
    size = _positive_vector(size, 3, "size")
    h_coarse = _positive_scalar(cell_coarse, "cell_coarse")
    h_fine = _positive_scalar(cell_fine, "cell_fine")
    focus = _finite_vector(focus, 3, "focus")
    origin = _finite_vector(origin, 3, "origin")
    if h_fine > h_coarse:
        raise MeshError(f"cell_fine ({h_fine}) must not exceed cell_coarse ({h_coarse})")
    return size, h_coarse, h_fine, focus, origin, _positive_scalar(radius, "radius", allow_zero=True)


def graded_block(
    size: Sequence[float],
    cell_coarse: float,
    cell_fine: float,
    focus: Sequence[float],
    radius: float,
    origin: Sequence[float] = (0.0, 0.0, 0.0),
    growth: float = 1.3,
) -> TetMesh:
    """Block [origin, origin + size] refined near ``focus`` (e.g. a contact point).

    Per axis, nodes are spaced ``cell_fine`` within ``radius`` of the focus
    coordinate and grow geometrically by ``growth`` up to ``cell_coarse`` away
    from it (see ``graded_axis``). The tensor product is split as in ``box``.
    Cells where a fine axis crosses a coarse one are anisotropic (aspect up to
    cell_coarse / cell_fine), which is inherent to tensor-product grading:
    max dihedral angles stay <= 90 deg, but the min dihedral drops to about
    atan(cell_fine / cell_coarse) (5.7 deg at a ratio of 10), so large ratios
    show up as slivers in ``quality_report``.

    Args:
        size: (3,) edge lengths > 0.
        cell_coarse: far-field cell length, >= cell_fine.
        cell_fine: cell length near the focus, > 0.
        focus: (3,) refinement centre (world coordinates, may lie outside).
        radius: half-width of the uniformly fine zone per axis, >= 0.
        origin: (3,) min corner.
        growth: max ratio of neighbouring cell sizes in the transition, > 1.
    Returns:
        TetMesh with exact outer dimensions, numbered as in ``box``.
    """
    size, h_coarse, h_fine, focus, origin, radius = _graded_arguments(size, cell_coarse, cell_fine, focus,
                                                                      origin, radius)
    growth = _positive_scalar(growth, "growth")
    if growth <= 1.0:
        raise MeshError(f"growth must be > 1, got {growth!r}")
    axes = [
        graded_axis(o, o + l, f, radius, h_fine, h_coarse, growth)
        for o, l, f in zip(origin, size, focus)
    ]
    return tensor_grid(*axes)


def graded_axis(
    lo: float,
    hi: float,
    focus: float,
    radius: float,
    h_fine: float,
    h_coarse: float,
    growth: float = 1.3,
) -> np.ndarray:
    """1D node coordinates on [lo, hi], fine near ``focus``, coarse away.

    The fine zone [focus - r, focus + r] (r >= h_fine / 2 so the focus always
    has a fine cell) is clipped to [lo, hi], widened to at least one fine
    cell if clipping left less (a focus outside refines the nearest end),
    and split into equal cells of h_fine / 2 < h_f <= h_fine. Each remaining
    side gets cells min(h_f * growth^k, c), k = 1, 2, ..., where the cap
    c <= h_coarse is solved so the side is filled exactly (see
    ``_growing_cells``). A side too short to grade (its cells would come out
    smaller than h_f, e.g. a thin layer at the boundary) is absorbed into the
    fine zone. Hence cell sizes are
    non-increasing towards the focus, lie in (h_fine / 2, h_coarse], and
    neighbours differ by at most the factor ``growth``.

    Returns:
        (n + 1,) float64 strictly increasing nodes, first == lo, last == hi.
    """
    r = max(radius, 0.5 * h_fine)
    a, b = float(np.clip(focus - r, lo, hi)), float(np.clip(focus + r, lo, hi))
    width = min(h_fine, hi - lo)
    if b - a < width:
        # Focus near or beyond an end clips the zone to a sliver (or nothing):
        # widen it to one fine cell inside the domain, nearest the focus.
        a = float(np.clip(np.clip(focus, lo, hi) - 0.5 * width, lo, hi - width))
        b = a + width
    # A side whose cells would have to be finer than the fine zone's (too
    # short to grade) is absorbed into it; at most one absorption per side.
    for _ in range(3):
        # The tiny relative slack keeps e.g. 0.1 / 0.01 from rounding up to 11 cells.
        n_fine = max(1, int(np.ceil((b - a) / h_fine * (1.0 - 1e-9))))
        h_f = (b - a) / n_fine
        left_cells = _growing_cells(a - lo, h_f, h_coarse, growth)
        right_cells = _growing_cells(hi - b, h_f, h_coarse, growth)
        left_ok = left_cells.size == 0 or left_cells[0] >= h_f * (1.0 - 1e-9)
        right_ok = right_cells.size == 0 or right_cells[0] >= h_f * (1.0 - 1e-9)
        if left_ok and right_ok:
            break
        a, b = (a if left_ok else lo), (b if right_ok else hi)
    fine = np.linspace(a, b, n_fine + 1)
    left = a - np.cumsum(left_cells)[::-1]
    right = b + np.cumsum(right_cells)
    nodes = np.concatenate([left, fine, right])
    nodes[0], nodes[-1] = lo, hi
    return nodes


def tensor_grid(xs: np.ndarray, ys: np.ndarray, zs: np.ndarray) -> TetMesh:
    """Kuhn-split tet mesh of the tensor grid with the given 1D node arrays.

    Args:
        xs, ys, zs: (NX,), (NY,), (NZ,) strictly increasing node coordinates,
            each with at least 2 entries.
    Returns:
        TetMesh with n_verts = NX NY NZ (x fastest) and
        n_tets = 6 (NX-1)(NY-1)(NZ-1), all positively oriented.
    """
    axes = [np.asarray(a, dtype=np.float64) for a in (xs, ys, zs)]
    for name, a in zip("xyz", axes):
        if a.ndim != 1 or a.size < 2 or not np.all(np.diff(a) > 0):
            raise MeshError(f"{name} nodes must be a strictly increasing 1D array of >= 2 values")
    nx, ny, nz = (a.size - 1 for a in axes)
    n_tets = 6 * nx * ny * nz
    if n_tets > _MAX_TETS:
        raise MeshError(
            f"grid of {nx}x{ny}x{nz} cells would create {n_tets} tets (limit {_MAX_TETS}); "
            "check the cell size and its units"
        )
    NX, NY = nx + 1, ny + 1
    # meshgrid in (z, y, x) order so that the C-order ravel makes x fastest.
    z, y, x = np.meshgrid(axes[2], axes[1], axes[0], indexing="ij")
    vertices = np.stack([x.ravel(), y.ravel(), z.ravel()], axis=1)

    k, j, i = np.meshgrid(np.arange(nz), np.arange(ny), np.arange(nx), indexing="ij")
    base = (i + NX * (j + NY * k)).ravel()
    bits = np.arange(8)
    corner_offset = (bits & 1) + NX * ((bits >> 1) & 1) + NX * NY * ((bits >> 2) & 1)
    tets = base[:, None, None] + corner_offset[_KUHN][None, :, :]
    return TetMesh(vertices, tets.reshape(-1, 4))


def composite(
    primitives: Sequence[dict],
    edge_length: float,
    epsilon: float = 1e-3,
) -> TetMesh:
    """Union of primitive solids, tetrahedralised with fTetWild.

    Each primitive is a dict with ``"shape"`` and shape keys, plus optional
    ``"position"`` (3,) and ``"rotation_rpy"`` (3,) [rad] placing the shape's
    centre: R = Rz(yaw) Ry(pitch) Rx(roll) (ROS/URDF fixed-axis convention).
    Shapes are centred on their local origin (unlike ``box()``, whose origin
    is the min corner); axial shapes lie along local z:

    - ``box``: ``size`` (3,) full edge lengths.
    - ``sphere``: ``radius``.
    - ``ellipsoid``: ``radii`` (3,) semi-axes.
    - ``cylinder``: ``radius``, ``height`` (total length).
    - ``capsule``: ``radius``, ``height`` (distance between the hemisphere
      centres, i.e. the straight part; total length is height + 2 radius).

    Curved shapes are tessellated at about edge_length / 2 so the faceting
    error of the union stays small compared with the tet size.

    Args:
        primitives: non-empty list of primitive dicts.
        edge_length: target tet edge length (absolute, > 0).
        epsilon: fTetWild envelope, relative to the bbox diagonal.
    Returns:
        TetMesh, positively oriented, without unreferenced vertices.
    """
    import trimesh

    from mdss_ros.mesh.tetrahedralize import tetrahedralize

    edge_length = _positive_scalar(edge_length, "edge_length")
    if isinstance(primitives, dict) or not isinstance(primitives, Sequence) or not primitives:
        raise MeshError("primitives must be a non-empty list of primitive dicts")
    solids = [_primitive_surface(p, i, edge_length) for i, p in enumerate(primitives)]
    if len(solids) == 1:
        union = solids[0]
    else:
        # manifold3d is exact and robust on coplanar/touching inputs, unlike
        # the legacy engines; it always returns a closed 2-manifold.
        union = trimesh.boolean.union(solids, engine="manifold")
    if union.is_empty or union.volume <= 0:
        raise MeshError("union of primitives is empty")
    return tetrahedralize(union.vertices, union.faces, edge_length=edge_length, epsilon=epsilon)


# Keys each primitive shape requires; "shape", "position", "rotation_rpy" are common.
_SHAPE_KEYS = {
    "box": ("size",),
    "sphere": ("radius",),
    "ellipsoid": ("radii",),
    "cylinder": ("radius", "height"),
    "capsule": ("radius", "height"),
}
_COMMON_KEYS = ("shape", "position", "rotation_rpy")


def _primitive_surface(spec: dict, index: int, edge_length: float):
    """Closed trimesh of one primitive dict, placed in the world frame."""
    import trimesh

    where = f"primitives[{index}]"
    if not isinstance(spec, dict):
        raise MeshError(f"{where} must be a dict, got {type(spec).__name__}")
    if "shape" not in spec:
        raise MeshError(f"{where} is missing key 'shape'")
    shape = spec["shape"]
    if shape not in _SHAPE_KEYS:
        raise MeshError(
            f"{where} has unknown shape {shape!r}; expected one of {sorted(_SHAPE_KEYS)}"
        )
    for key in _SHAPE_KEYS[shape]:
        if key not in spec:
            raise MeshError(f"{where} (shape {shape!r}) is missing key {key!r}")
    # Typos like "positon" would otherwise silently place the shape at 0.
    unknown = sorted(set(spec) - set(_SHAPE_KEYS[shape]) - set(_COMMON_KEYS))
    if unknown:
        raise MeshError(f"{where} (shape {shape!r}) has unknown keys {unknown}")

    seg = 0.5 * edge_length
    if shape == "box":
        mesh = trimesh.creation.box(extents=_positive_vector(spec["size"], 3, f"{where}.size"))
    elif shape == "sphere":
        r = _positive_scalar(spec["radius"], f"{where}.radius")
        mesh = trimesh.creation.icosphere(subdivisions=_ico_level(r, seg), radius=r)
    elif shape == "ellipsoid":
        radii = _positive_vector(spec["radii"], 3, f"{where}.radii")
        mesh = trimesh.creation.icosphere(subdivisions=_ico_level(radii.max(), seg), radius=1.0)
        mesh.apply_scale(radii)
    elif shape == "cylinder":
        r = _positive_scalar(spec["radius"], f"{where}.radius")
        h = _positive_scalar(spec["height"], f"{where}.height")
        mesh = trimesh.creation.cylinder(radius=r, height=h, sections=_sections(r, seg))
    else:  # capsule
        r = _positive_scalar(spec["radius"], f"{where}.radius")
        h = _positive_scalar(spec["height"], f"{where}.height")
        n = _sections(r, seg)
        mesh = trimesh.creation.capsule(height=h, radius=r, count=[n, n])

    transform = trimesh.transformations.euler_matrix(
        *_finite_vector(spec.get("rotation_rpy", (0.0, 0.0, 0.0)), 3, f"{where}.rotation_rpy"),
        axes="sxyz",  # static x, then y, then z: R = Rz(yaw) Ry(pitch) Rx(roll)
    )
    transform[:3, 3] = _finite_vector(spec.get("position", (0.0, 0.0, 0.0)), 3, f"{where}.position")
    mesh.apply_transform(transform)
    return mesh


def _ico_level(radius: float, seg: float) -> int:
    """Icosphere subdivision level whose edges are about seg long.

    A level-s icosphere of radius r has edges of about 1.2 r / 2^s; levels are
    capped at 5 (20480 faces) to bound the fTetWild input size.
    """
    return int(np.clip(np.ceil(np.log2(1.2 * radius / seg)), 2, 5))


def _sections(radius: float, seg: float) -> int:
    """Number of circumferential segments of about seg length, in [16, 256]."""
    return int(np.clip(np.ceil(2.0 * np.pi * radius / seg), 16, 256))


def _uniform_axis(origin: float, length: float, n: int) -> np.ndarray:
    """(n + 1,) equally spaced nodes; linspace makes both ends exact."""
    return np.linspace(origin, origin + length, int(n) + 1)


def _growing_cells(length: float, h0: float, h_max: float, growth: float) -> np.ndarray:
    """Cell sizes growing from h0 outward that sum exactly to ``length``.

    Nominal sizes are s_k = min(h0 * growth^k, h_max), k = 1..n, with n the
    fewest cells reaching ``length``. Instead of rescaling all cells (which
    would break the growth bound at the fine side) the sizes are capped,
    min(s_k, c), with the cap c solved from sum = length. The sum is
    piecewise linear and increasing in c, so c is found exactly on the piece
    where it lies between consecutive nominal sizes.

    Returns (n,) non-decreasing sizes from the fine side outward, each
    <= h_max, ratio of neighbours <= growth; empty if length <= 0.
    """
    if length <= 0.0:
        return np.zeros(0)
    n_geo = int(np.ceil(np.log(h_max / h0) / np.log(growth))) if h_max > h0 else 0
    geo = np.minimum(h0 * growth ** np.arange(1, n_geo + 1), h_max)
    n_uniform = int(np.ceil(max(length - geo.sum(), 0.0) / h_max)) + 1
    nominal = np.concatenate([geo, np.full(n_uniform, h_max)])
    n = int(np.searchsorted(np.cumsum(nominal), length * (1.0 - 1e-12))) + 1
    nominal = nominal[:n]
    # Piece j: cells 0..j-1 keep their nominal size, cells j..n-1 are capped at c_j.
    before = np.concatenate([[0.0], np.cumsum(nominal)[:-1]])
    cap = (length - before) / (n - np.arange(n))
    lower = np.concatenate([[0.0], nominal[:-1]])
    valid = (cap >= lower * (1.0 - 1e-12)) & (cap <= nominal * (1.0 + 1e-12))
    return np.minimum(nominal, cap[np.flatnonzero(valid)[0]])


def _positive_scalar(value, name: str, allow_zero: bool = False) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError) as exc:
        raise MeshError(f"{name} must be a number, got {value!r}") from exc
    if not np.isfinite(v) or v < 0 or (v == 0 and not allow_zero):
        bound = ">= 0" if allow_zero else "> 0"
        raise MeshError(f"{name} must be finite and {bound}, got {value!r}")
    return v


def _finite_vector(value, n: int, name: str) -> np.ndarray:
    try:
        v = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise MeshError(f"{name} must be {n} numbers, got {value!r}") from exc
    if v.shape != (n,) or not np.all(np.isfinite(v)):
        raise MeshError(f"{name} must be {n} finite numbers, got {value!r}")
    return v


def _positive_vector(value, n: int, name: str) -> np.ndarray:
    v = _finite_vector(value, n, name)
    if np.any(v <= 0):
        raise MeshError(f"{name} entries must be > 0, got {value!r}")
    return v


def graded_bcc_block(
    size: Sequence[float],
    cell_coarse: float,
    cell_fine: float,
    focus: Sequence[float],
    radius: float,
    origin: Sequence[float] = (0.0, 0.0, 0.0),
    layers: int = 3,
    jitter: float = 0.05,
    seed: int = 0,
) -> TetMesh:
    """Block [origin, origin + size] refined isotropically round ``focus``: nested
    body-centred cubic (BCC) point lattices, Delaunay-tetrahedralised (scipy/Qhull).

    Unlike ``graded_block`` (a tensor product, whose cells where a fine axis crosses a
    coarse one are cell_coarse / cell_fine long), every zone here has cells of aspect
    about 1: a graded unstructured mesh whose vertices can serve as meshless nodes.

    Levels l = 0, 1, ...: BCC lattices (cube corners and centres) of cube edge
    h_l = cell_fine 2^l anchored at ``focus``. Level 0 fills the box Z_0 of half-width
    max(radius, cell_fine) round the focus; level l the box Z_l of half-width r_l, the
    smallest multiple of h_l >= r_{l-1} + layers h_l, less Z_{l-1}: each level adds
    ``layers`` cells of its own size round the finer zone (the cell doubles every
    ``layers`` cells); a box ending less than 2 h_l short of a block face is extended to
    it. The last level has h_l <= cell_coarse < 2 h_l and fills the rest of
    the block. Boxes are clipped to the block; lattice points up to one cell outside the
    block are moved onto its faces (so every face is covered whatever the lattice's
    alignment), and a point closer than 0.35 h_l to one kept before it (finer levels and
    face points first) is dropped.

    The points are then perturbed by ``jitter`` x their level's cell (uniform, seeded; on
    the block's faces only within the face, on its edges only along it), which makes the
    Delaunay tetrahedralisation unique where the lattices meet, and tetrahedralised. The
    block is convex, so the tets fill it; flat tets on its planar faces are dropped.

    Args:
        size, origin: (3,) block edge lengths > 0 and min corner.
        cell_coarse: largest cell, >= cell_fine.
        cell_fine: cube edge of the finest zone, > 0.
        focus: (3,) refinement centre, inside the block or on its boundary.
        radius: half-width of the finest zone.
        layers: cells of each coarser level round the finer zone, >= 1.
        jitter: perturbation / cell, in [0, 0.25).
        seed: random seed of the perturbation.
    Returns:
        TetMesh, every tet positively oriented; volume = the block's.
    """
    from scipy.spatial import Delaunay, cKDTree

    from mdss_ros.mesh.tetmesh import orient_tets, remove_unreferenced, signed_volumes

    size, h_coarse, h_fine, focus, origin, radius = _graded_arguments(size, cell_coarse, cell_fine, focus,
                                                                      origin, radius)
    layers = int(layers)
    if layers < 1:
        raise MeshError(f"layers must be >= 1, got {layers!r}")
    if not 0.0 <= float(jitter) < 0.25:
        raise MeshError(f"jitter must be in [0, 0.25), got {jitter!r}")
    lo, hi = origin, origin + size
    if np.any(focus < lo - 1e-9 * size) or np.any(focus > hi + 1e-9 * size):
        raise MeshError(f"focus {focus.tolist()} lies outside the block")
    n_coarse = float(np.prod(size / h_coarse + 2.0))
    if 2.0 * n_coarse > _MAX_TETS:
        raise MeshError(f"block of {size.tolist()} with cell_coarse {h_coarse} is too large; check the units")
    tol = 1e-9 * float(size.max())

    def bcc(h, box_lo, box_hi):
        """BCC points of cube edge h anchored at the focus inside the closed box."""
        pts = []
        for shift in (0.0, 0.5):
            axes = []
            for d in range(3):
                i0 = int(np.ceil((box_lo[d] - focus[d]) / h - shift - 1e-9))
                i1 = int(np.floor((box_hi[d] - focus[d]) / h - shift + 1e-9))
                axes.append(focus[d] + h * (np.arange(i0, i1 + 1) + shift))
            if all(a.size for a in axes):
                g = np.meshgrid(*axes, indexing="ij")
                pts.append(np.stack([a.ravel() for a in g], axis=1))
        return np.concatenate(pts) if pts else np.zeros((0, 3))

    kept, kept_h = [np.zeros((0, 3))], [np.zeros(0)]
    h, r, prev = h_fine, max(radius, h_fine), None
    while True:
        last = 2.0 * h > h_coarse * (1.0 + 1e-9)
        if prev is not None:
            r = np.ceil((r + layers * h) / h - 1e-9) * h
        z_lo, z_hi = np.maximum(focus - r, lo), np.minimum(focus + r, hi)
        # A zone ending less than the next level's cell short of a face reaches the face
        # (else the next level would have a sliver of a layer there).
        z_lo = np.where(z_lo - lo < 2.0 * h, lo, z_lo)
        z_hi = np.where(hi - z_hi < 2.0 * h, hi, z_hi)
        last = last or bool(np.all(z_lo <= lo + tol) and np.all(z_hi >= hi - tol))
        if last:
            z_lo, z_hi = lo, hi
        # Lattice points of the zone, one cell beyond the block moved onto its faces.
        P = bcc(h, np.where(z_lo <= lo + tol, lo - h, z_lo), np.where(z_hi >= hi - tol, hi + h, z_hi))
        P = np.clip(P, lo, hi)
        if prev is not None:                      # the finer zone has its own points
            P = P[~np.all((P >= prev[0] - tol) & (P <= prev[1] + tol), axis=1)]
        # Face points first, then the rest, each by distance to the focus.
        n_face = (np.abs(P - lo) < tol).sum(1) + (np.abs(P - hi) < tol).sum(1)
        P = P[np.lexsort((np.linalg.norm(P - focus, axis=1), -n_face))]
        A = np.concatenate(kept)
        near = cKDTree(A).query(P, k=1, distance_upper_bound=0.35 * h)[0] if len(A) else np.full(len(P), np.inf)
        P = P[~np.isfinite(near)]
        drop = np.zeros(len(P), dtype=bool)
        for i, j in sorted(cKDTree(P).query_pairs(0.35 * h)):          # i < j: i has priority
            if not drop[i]:
                drop[j] = True
        P = P[~drop]
        kept.append(P)
        kept_h.append(np.full(len(P), h))
        if last:
            break
        prev = (z_lo, z_hi)
        h *= 2.0
    X, hc = np.concatenate(kept), np.concatenate(kept_h)
    if float(jitter) > 0.0:
        dx = np.random.default_rng(int(seed)).uniform(-1.0, 1.0, X.shape) * (float(jitter) * hc)[:, None]
        dx[(np.abs(X - lo) < tol) | (np.abs(X - hi) < tol)] = 0.0      # stay on the face / edge / corner
        X = X + dx
    tets = orient_tets(X, np.asarray(Delaunay(X).simplices, dtype=np.int64))
    vol = signed_volumes(X, tets)
    tets = tets[vol > 1e-9 * h_fine ** 3]
    # Qhull leaves out points within round-off of a facet (none with jitter > 0, as a rule).
    return remove_unreferenced(TetMesh(np.ascontiguousarray(X), np.ascontiguousarray(tets)))
