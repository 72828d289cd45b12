"""Kinematic rigid colliders: geometry, pose and signed distance.

A collider is declared in the scene's `colliders` map and posed by the timeline, the API
(`Simulator.set_collider_pose`) or the ROS topic `~/colliders/<name>/pose`:

    colliders:
      ball:  {shape: sphere, radius: 0.05, position: [0, 0, 0.3]}
      rod:   {shape: capsule, radius: 0.02, half_height: 0.1, orientation: [0, 0, 0, 1]}
      block: {shape: box, half_extents: [0.1, 0.1, 0.05]}
      floor: {shape: plane, friction: 0.5}       # the local z = 0 plane, normal +z; Coulomb mu
      finger: {shape: mesh, file: finger.obj, scale: 0.001}   # closed surface: contact/mesh_sdf.py
      tool:  {shape: sphere, radius: 0.02, reach: {sphere: {center: [0, 0, 0.1], radius: 0.05}}}

`friction` (optional): the Coulomb coefficient, a number or {static: mu_s, kinetic: mu_k};
default 0, frictionless (contact/friction.py).

`reach` (optional, a vertex selector) marks the part of the body the collider can touch;
in a reduced model it becomes a full-space domain `<name>_reach` (scene.model_config).

A sphere also meets the surface triangles (a small sphere could slip through a face between
vertices); `face_contacts: false` keeps vertex contacts only (node-to-surface, the usual
discretisation of FE Hertz studies: faces may then cut into the sphere by about
h^2 / (8 R) for surface edges h, and the static rest is unique; with face rows a coarse
contact patch can switch its active faces from one static step to the next).

`signed_distance(points)` returns phi (n,) (negative inside the collider) and the unit
outward normal of the collider at the closest surface point (n, 3), both in the world
frame; phi is differentiable with d phi / d x = normal away from the medial set.

A collider can be posed inside the body (a forgotten `position` leaves it at the origin).
`Collider.penetration` measures that from the vertices inside it, `inside_body` tells
whether the collider's own centre (or capsule axis) lies in the body's volume; the
Simulator warns about the first, and does not sweep a collider that either finds inside
the body (docs/method.md §14, "A collider inside the body").
"""
import dataclasses
from dataclasses import dataclass, field

import numpy as np
from numba import njit

from ..errors import SceneError
from ..rotations import matrix_from_quat

SHAPES = {"sphere": ("radius",), "capsule": ("radius", "half_height"), "box": ("half_extents",), "plane": (),
          "mesh": ()}
# Keys of a mesh collider besides the common ones (file required; contact/mesh_sdf.py checks them).
MESH_KEYS = ("file", "scale", "resolution")


@dataclass
class Collider:
    """name; shape; size parameters; pose (position (3,), orientation x y z w);
    face_contacts: a sphere or capsule also meets surface triangles (unilateral.find_triangle_contacts)."""

    name: str
    shape: str
    radius: float = 0.0
    half_height: float = 0.0
    half_extents: np.ndarray = field(default_factory=lambda: np.zeros(3))
    position: np.ndarray = field(default_factory=lambda: np.zeros(3))
    orientation: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, 0.0, 1.0]))
    face_contacts: bool = True
    friction: tuple = (0.0, 0.0)  # Coulomb (static, kinetic); (0, 0) is frictionless (contact/friction.py)
    sdf: object = None           # a mesh collider's sampled field (contact.mesh_sdf.MeshSDF)

    def set_pose(self, position, orientation=(0.0, 0.0, 0.0, 1.0)):
        q = np.asarray(orientation, dtype=np.float64)
        n = np.linalg.norm(q)
        if not np.all(np.isfinite(q)) or n < 1e-9:
            raise ValueError(f"collider {self.name!r}: orientation must be a non-zero finite quaternion, got {orientation!r}")
        self.position = np.asarray(position, dtype=np.float64).copy()
        self.orientation = q / n

    @property
    def rotation(self):
        """R (3, 3) of the orientation, kept for its value (the orientation's bytes): the
        contact search, the rows and the slip read it three times a step, and
        matrix_from_quat takes 6 us a call (min of 5,000)."""
        key = np.asarray(self.orientation, dtype=np.float64).tobytes()
        kept = self.__dict__.get("_rotation_kept")
        if kept is None or kept[0] != key:
            R = matrix_from_quat(self.orientation)
            R.flags.writeable = False
            kept = self.__dict__["_rotation_kept"] = (key, R)
        return kept[1]

    def at(self, position, orientation):
        """A copy of this collider at another pose (for checks at a start or trial pose)."""
        return dataclasses.replace(self, position=np.asarray(position, dtype=np.float64),
                                   orientation=np.asarray(orientation, dtype=np.float64))

    def penetration(self, points, tol=0.0):
        """The points inside this collider, one vectorised signed_distance: (depth, count,
        index), depth = -min phi (m) over the points with phi < -tol, count how many, index
        the deepest (into points); (0.0, 0, -1) when none."""
        points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        if len(points) == 0:
            return 0.0, 0, -1
        phi = self.distance(points)
        inside = phi < -tol
        if not inside.any():
            return 0.0, 0, -1
        k = int(np.argmin(phi))
        return float(-phi[k]), int(inside.sum()), k

    def core_points(self):
        """Points (k, 3) of this collider's solid that lie deepest in it: a sphere's or box's
        centre, a capsule's axis ends and middle; none for a plane (a half-space)."""
        if self.shape in ("sphere", "box"):
            return self.position[None, :].copy()
        if self.shape == "mesh":                      # the grid node deepest inside the mesh
            return self.position + self.sdf.core @ self.rotation.T
        if self.shape == "capsule":
            half = self.half_height * self.rotation[:, 2]
            return np.stack([self.position - half, self.position, self.position + half])
        return np.zeros((0, 3))

    def distance(self, points):
        """phi (n,) alone at world points (n, 3). The candidate search reads it at every
        surface vertex each step and needs no normals there (for a sphere the normals were
        half of that pass; for a plane, two thirds of it: its normals are a tiled constant
        turned by a matrix product); other shapes take signed_distance's phi."""
        if self.shape == "sphere":
            d = np.asarray(points, dtype=np.float64) - self.position
            return np.sqrt(np.einsum("ij,ij->i", d, d)) - self.radius
        if self.shape == "plane":
            # The height above the local z = 0 plane: the local z axis is the rotation's last column.
            return (np.asarray(points, dtype=np.float64) - self.position) @ self.rotation[:, 2]
        if self.shape == "mesh":
            return self.sdf.distance((np.asarray(points, dtype=np.float64) - self.position) @ self.rotation)
        return self.signed_distance(points)[0]

    def near(self, points, margin):
        """Indices (k,) of the points (n, 3) with phi < margin: the contact search's candidates.

        A sphere's and a plane's in one compiled pass (_sphere_near, _plane_near): the
        search runs over every surface vertex each step, and distance()'s numpy passes cost
        about 110 us on hammock's 6882 vertices (sphere) and 45 us on the caterpillar's
        4964 (floor), the kernels 18 and 14 us. Their sums may round differently from
        distance()'s in the last bit, which only matters for a point at the margin to
        round-off: a candidate that far out carries no force. Other shapes by distance()."""
        if self.shape == "sphere":
            return _sphere_near(np.ascontiguousarray(points, dtype=np.float64), self.position,
                                float(self.radius), float(margin))
        if self.shape == "plane":
            return _plane_near(np.ascontiguousarray(points, dtype=np.float64), self.position,
                               np.ascontiguousarray(self.rotation[:, 2]), float(margin))
        return np.flatnonzero(self.distance(points) < margin)

    def signed_distance(self, points):
        """phi (n,) and outward normals (n, 3) at world points (n, 3)."""
        R = self.rotation
        p = (np.asarray(points, dtype=np.float64) - self.position) @ R        # local coordinates
        if self.shape == "sphere":
            phi, n = _sphere(p, self.radius)
        elif self.shape == "capsule":
            axial = np.clip(p[:, 2], -self.half_height, self.half_height)
            q = p.copy()
            q[:, 2] -= axial
            phi, n = _sphere(q, self.radius)
        elif self.shape == "box":
            phi, n = _box(p, self.half_extents)
        elif self.shape == "plane":
            # The normal is the local z axis, R's last column: what the tiled (0, 0, 1) @ R^T
            # gave, without the product (0 R_i0 + 0 R_i1 + 1 R_i2 is R_i2 exactly).
            return p[:, 2].copy(), np.tile(R[:, 2], (len(p), 1))
        elif self.shape == "mesh":
            phi, n = self.sdf.evaluate(p)
        else:                                                              # validated on creation
            raise ValueError(self.shape)
        return phi, n @ R.T


@njit(cache=True)
def _sphere_near(points, centre, radius, margin):
    """Indices (k,) of points (n, 3) with |p - centre| - radius < margin (Collider.near)."""
    out = np.empty(points.shape[0], dtype=np.int64)
    k = 0
    for i in range(points.shape[0]):
        d0, d1, d2 = points[i, 0] - centre[0], points[i, 1] - centre[1], points[i, 2] - centre[2]
        if np.sqrt(d0 * d0 + d1 * d1 + d2 * d2) - radius < margin:
            out[k] = i
            k += 1
    return out[:k]


@njit(cache=True)
def _plane_near(points, origin, normal, margin):
    """Indices (k,) of points (n, 3) with (p - origin) . normal < margin (Collider.near)."""
    out = np.empty(points.shape[0], dtype=np.int64)
    k = 0
    for i in range(points.shape[0]):
        h = ((points[i, 0] - origin[0]) * normal[0] + (points[i, 1] - origin[1]) * normal[1]
             + (points[i, 2] - origin[2]) * normal[2])
        if h < margin:
            out[k] = i
            k += 1
    return out[:k]


def _sphere(p, radius):
    d = np.linalg.norm(p, axis=1)
    safe = d > 1e-12
    n = np.zeros_like(p)
    n[safe] = p[safe] / d[safe, None]
    n[~safe] = (0.0, 0.0, 1.0)                 # the centre: any direction is a normal
    return d - radius, n


def _box(p, h):
    q = np.abs(p) - h
    outside = np.maximum(q, 0.0)
    d_out = np.linalg.norm(outside, axis=1)
    inside = d_out == 0.0
    phi = np.where(inside, q.max(axis=1), d_out)
    n = np.zeros_like(p)
    out = ~inside
    n[out] = np.sign(p[out]) * outside[out] / d_out[out, None]
    # Inside: push out through the nearest face.
    axis = np.argmax(q[inside], axis=1)
    rows = np.flatnonzero(inside)
    n[rows, axis] = np.where(p[rows, axis] >= 0.0, 1.0, -1.0)
    return phi, n


class ColliderInsideWarning(UserWarning):
    """A collider's scene pose puts it inside the body (Simulator, at load and reset)."""


def winding_numbers(points, positions, triangles):
    """Generalised winding numbers (k,) of points (k, 3) with respect to the closed surface
    positions (S, 3), triangles (T, 3): about +-1 inside, 0 outside (Van Oosterom and
    Strackee's solid angle, summed over the triangles; one pass per point, vectorised over
    the triangles)."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    out = np.zeros(len(points))
    corners = [positions[triangles[:, k]] for k in range(3)]
    for i, p in enumerate(points):                        # a few points (a collider's core)
        a, b, c = (q - p for q in corners)
        la, lb, lc = (np.linalg.norm(q, axis=1) for q in (a, b, c))
        det = np.einsum("ij,ij->i", a, np.cross(b, c))
        den = (la * lb * lc + np.einsum("ij,ij->i", a, b) * lc + np.einsum("ij,ij->i", b, c) * la
               + np.einsum("ij,ij->i", c, a) * lb)
        out[i] = 2.0 * np.arctan2(det, den).sum() / (4.0 * np.pi)
    return out


def inside_body(collider, positions, triangles):
    """True when the collider's core (core_points: a centre or a capsule's axis) lies inside
    the closed surface (positions, triangles): the collider overlaps the body's volume even
    where no vertex is inside it (the body pushed out around it)."""
    core = collider.core_points()
    if len(core) == 0 or len(triangles) == 0:
        return False
    return bool((np.abs(winding_numbers(core, positions, triangles)) > 0.5).any())


def clear_position(collider, points, clearance):
    """A suggested position for a collider that has points inside it: the shortest shift
    along the world axes (and, for a plane, against its normal) that leaves every point at
    least clearance outside it, in steps of a quarter of (depth + clearance). None if no
    shift within 64 steps clears the points."""
    depth = collider.penetration(points)[0]
    step = 0.25 * (depth + clearance) if depth + clearance > 0 else 1e-3
    dirs = list(np.vstack([np.eye(3), -np.eye(3)]))
    if collider.shape == "plane":
        dirs.append(-collider.rotation[:, 2])
    best = None
    for u in dirs:
        for k in range(1, 65):
            if best is not None and k * step >= best[0]:
                break
            p = collider.position + k * step * u
            if collider.at(p, collider.orientation).signed_distance(points)[0].min() >= clearance:
                best = (k * step, p)
                break
    return None if best is None else best[1]


def make_collider(name, spec, base_dir=None, cache=None, memo=None):
    """Collider from a scene's colliders.<name> mapping; SceneError names the bad key.

    A mesh collider's file is relative to base_dir (the scene's folder; default the working
    directory); its distance grid comes from memo (a dict kept by the caller across resets),
    the precompute cache (default PrecomputeCache()) or is built (contact/mesh_sdf.py)."""
    where = f"colliders.{name}"
    if not isinstance(spec, dict):
        raise SceneError(f"{where}: expected a mapping with a shape, got {spec!r}")
    shape = spec.get("shape")
    if shape not in SHAPES:
        raise SceneError(f"{where}.shape: {shape!r} is not one of {', '.join(SHAPES)}")
    allowed = set(SHAPES[shape]) | {"shape", "position", "orientation", "reach", "friction"} | (
        {"face_contacts"} if shape in ("sphere", "capsule") else set()) | (
        set(MESH_KEYS) if shape == "mesh" else set())
    unknown = sorted(set(spec) - allowed)
    if unknown:
        raise SceneError(f"{where}: unknown key(s) {unknown} for a {shape} (allowed: {sorted(allowed)})")
    c = Collider(name=name, shape=shape)
    if "face_contacts" in spec:
        if not isinstance(spec["face_contacts"], bool):
            raise SceneError(f"{where}.face_contacts: expected true or false, got {spec['face_contacts']!r}")
        c.face_contacts = spec["face_contacts"]
    if "friction" in spec:
        from .friction import parse_friction
        try:
            c.friction = parse_friction(where, spec["friction"])
        except ValueError as err:
            raise SceneError(str(err)) from err
    for key in SHAPES[shape]:
        if key not in spec:
            raise SceneError(f"{where}.{key}: required for a {shape}")
        value = np.asarray(spec[key], dtype=np.float64)
        if not np.all(np.isfinite(value)) or np.any(value <= 0) or (key == "half_extents" and value.shape != (3,)):
            raise SceneError(f"{where}.{key}: expected positive {'3 numbers' if key == 'half_extents' else 'number'}, "
                             f"got {spec[key]!r}")
        setattr(c, key, value if key == "half_extents" else float(value))
    try:
        c.set_pose(spec.get("position", (0.0, 0.0, 0.0)), spec.get("orientation", (0.0, 0.0, 0.0, 1.0)))
    except ValueError as err:
        raise SceneError(f"{where}: {err}") from err
    if np.asarray(c.position).shape != (3,):
        raise SceneError(f"{where}.position: expected 3 numbers, got {spec.get('position')!r}")
    if shape == "mesh":
        from .mesh_sdf import build_mesh_sdf
        c.sdf = build_mesh_sdf(where, spec, base_dir, cache, memo)
    return c
