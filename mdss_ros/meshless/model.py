"""MeshlessModel (`model.kind: meshless`): [HZ]'s MLS meshless model with nodal integration
(docs/method.md §19).

Nodes are the body's tet-mesh vertices X (n, 3); the tets serve only for the nodal
volumes, the surface (the integration constraint's boundary vectors) and the guard's
inversion count. The surface output is the surface vertices, which are nodes: the fit at
node i is centred on x_i, so the MLS interpolant there is the node's own position. Per
node i (build_forces):

    rbar_i, h_i                   neighbourhoods.py (k nearest, support radius; octants
                                  where the moment matrix is ill-conditioned)
    V_i                           the tet mesh's vertex volume (volumes: mesh), or
                                  s rbar_i^3 scaled to V_mesh ([HZ] eq. 2, volumes: support)
    m_i = rho V_i                 so sum m_i = rho V_mesh exactly
    c_i                           mls.py, corrected by integration.py (consistent)
    F_i, E = sum_i V_i psi(F_i) + E_hg    forces.py, kernels.py, integration.py
    + the compression barrier on the tets' J   forces.MeshlessForces.tet_barrier (tet_barrier: true)

State x, v (n, 3). Time integration:
    implicit (default): backward Euler with Newton on the analytic stiffness, the same
        integrator, settings (model.integrator.*), Rayleigh damping and contact as the
        full-space model (fem/backward_euler.py, §4, §14);
    rk4: explicit RK4 with sub-steps (explicit.py).
Pins: fixed nodes (their DOFs are removed from the unknowns, they stay neighbours).
"""
import warnings
from dataclasses import dataclass, replace

import numpy as np
from scipy.spatial import cKDTree

from ..fem.backward_euler import BackwardEuler, NewtonSettings
from ..fem.full_model import EmbeddedNodes, VertexState
from ..fem.mass import lumped_mass
from ..mesh.distance import signed_distance
from ..mesh.selectors import select_vertices
from ..mesh.tetmesh import signed_volumes
from .embedding import Embedding, shape_functions
from .explicit import RK4, auto_substeps, max_frequency
from .forces import MeshlessForces
from .integration import boundary_vectors, consistent_coefficients, stabilisation_matrices
from .mls import conditions, gradient_operator, kernel
from .neighbourhoods import find_neighbourhoods, grow
from .nodes import lattice_nodes, lattice_volumes, surface_quadrature

#: Moment matrices with a condition number above this get their node's neighbourhood
#: chosen again over the octants round it (neighbourhoods.grow, at most GROWTH_ROUNDS
#: times, from 8k, 32k, then 128k candidates). On the product's scenes the
#: largest is 13 (a one-cell-thick hammock); a first-order fit through neighbours that
#: span a thousand times less across one direction than along the others amplifies the
#: second-order part of the motion in that direction as much.
COND_LIMIT = 1.0e3
GROWTH_ROUNDS = 3


@dataclass(frozen=True)
class Build:
    """What build_forces found: the neighbourhoods, how many nodes had theirs chosen again
    over the octants, how many stayed ill-conditioned after that, and the integration
    constraint's residual (None with integration: nodal)."""
    neighbourhoods: object
    grown: int
    ill_conditioned: int
    integration_residual: object

DEFAULTS = {"neighbours": 16, "support_scale": 2.0, "volume_stiffness": 0.1, "integrator": "implicit",
            "substeps": "auto", "integration": "consistent", "stabilisation": 0.1,
            "volumes": "mesh", "tet_barrier": True, "nodes": "mesh", "spacing": "auto"}


def build_forces(X, tets, triangles, material, settings, pinned=(), volumes=None, boundary=None):
    """(MeshlessForces, Build) of nodes X (n, 3), the
    vertices of tets (t, 4) with outward surface triangles (s, 3), for a material (mu, lam,
    density) and model.meshless settings (DEFAULTS for missing keys).
    Nodes that are not a mesh's vertices (nodes: lattice) come with tets and triangles None,
    their volumes (n,) and the integration constraint's boundary vectors (n, 3)."""
    cfg = dict(DEFAULTS, **(settings or {}))
    nb = find_neighbourhoods(X, cfg["neighbours"], cfg["support_scale"])
    grown = np.zeros(len(X), dtype=bool)
    for round_ in range(GROWTH_ROUNDS):
        # Nearly coplanar or collinear neighbours (thin parts, edges, graded meshes): choose
        # those nodes' neighbourhoods again before inverting their moment matrices (§19.2).
        bad = np.flatnonzero(conditions(X, nb.nbr, nb.h) > COND_LIMIT)
        if bad.size == 0:
            break
        grown[bad] = True
        nb = grow(X, nb, bad, cfg["support_scale"], round_)
    op = gradient_operator(X, nb.nbr, nb.h)
    mass = None
    if volumes is not None:
        V = np.asarray(volumes, dtype=np.float64)
    elif cfg["volumes"] == "kernel":
        V, mass = kernel_volumes(X, nb, material.density)
    elif cfg["volumes"] == "mesh":
        # The tet mesh's lumped vertex volumes (a quarter of each tet's): a partition of
        # the body, so boundary nodes get their share and no more (docs/method.md §19.4).
        V = lumped_mass(tets, signed_volumes(X, tets), 1.0, len(X))
    else:
        r3 = nb.rbar ** 3                      # [HZ] eq. 2, scaled to the mesh's volume
        V = r3 * (float(signed_volumes(X, tets).sum()) / r3.sum())
    residual = None
    if cfg["integration"] == "consistent":
        c, residual = consistent_coefficients(X, op.stencil, op.c, V, nb.h,
                                              boundary if boundary is not None else
                                              boundary_vectors(X, triangles, len(X)))
        op = replace(op, c=c)
    S = (stabilisation_matrices(X, op.stencil, op.c, op.weights, V, material.mu, float(cfg["stabilisation"]))
         if cfg["stabilisation"] > 0 else None)
    kv = float(cfg["volume_stiffness"]) * material.mu
    # The FEM materials' compression barrier (docs/method.md §3.4) on the nodal J, same keys.
    kb = float(getattr(material, "barrier", 0.0)) * material.mu
    jb = float(getattr(material, "barrier_j", 0.2))
    forces = MeshlessForces(X, op, V, material.density * V if mass is None else mass, material.mu, material.lam, kv, pinned, S, kb, jb,
                            tets if cfg["tet_barrier"] and tets is not None else None)
    return forces, Build(nb, int(grown.sum()), int((op.cond > COND_LIMIT).sum()), residual)


#: integral of the kernel w(|x|) over the unit ball: 4 pi (1/3 - 3/5 + 1/3)
KERNEL_INTEGRAL = 4.0 * np.pi / 15.0


def kernel_volumes(X, nb, density):
    """(V (n,), m (n,)) by [HZ] eqs. 1-3 (`volumes: kernel`): masses m_i = s rho rbar_i^3,
    densities rho_i = sum_j m_j W(|X_j - X_i|, h_i) over every node within the support h_i
    (not only the k neighbours: a support of 2 rbar holds about twice as many), with the
    kernel normalised to unit integral, W = w(r / h) / (KERNEL_INTEGRAL h^3), s such that the
    mean of rho_i is rho ([HZ]: "so that the average of the assigned densities is close to
    the actual material density"), and volumes V_i = m_i / rho_i (Mueller et al. 2004). The
    masses need not sum to rho V_mesh (the explain line says by how much)."""
    r3 = nb.rbar ** 3
    pairs = cKDTree(X).query_pairs(float(nb.h.max()), output_type="ndarray")
    i, j = np.concatenate([pairs[:, 0], pairs[:, 1]]), np.concatenate([pairs[:, 1], pairs[:, 0]])
    W = kernel(np.linalg.norm(X[j] - X[i], axis=1) / nb.h[i]) / (KERNEL_INTEGRAL * nb.h[i] ** 3)
    rho1 = r3 / (KERNEL_INTEGRAL * nb.h ** 3) + np.bincount(i, weights=r3[j] * W, minlength=len(X))
    s = 1.0 / rho1.mean()                                   # rho_i = s rho rho1_i
    m = s * density * r3
    return m / (s * density * rho1), m


class MeshlessModel(VertexState):
    """State x, v (n_verts, 3); step(f_ext, gravity, contact) advances by dt.

    settings: the scene's model.meshless mapping (DEFAULTS for missing keys);
    volume_stiffness is k_v in units of the material's mu."""

    kind = "meshless"

    def __init__(self, body, dt, integrator, damping, settings=None, solver="auto"):
        self.body = body
        cfg = dict(DEFAULTS, **(settings or {}))
        self.settings = cfg
        self.force_model, self.build = self._build_forces(body, cfg)
        self.op = self.force_model.op
        self.neighbourhoods = self.build.neighbourhoods
        self.integration_residual = self.build.integration_residual
        if self.build.ill_conditioned:
            warnings.warn(f"meshless model: {self.build.ill_conditioned} nodes keep an ill-conditioned moment matrix "
                          f"(condition > {COND_LIMIT:g}) after choosing their neighbourhoods over the octants: their nodes are "
                          f"nearly coplanar there (a part thinner than the node spacing, or cells far longer one way "
                          f"than another); refine the mesh across it; see --explain")
        self.vertex_mass = self.force_model.vertex_mass
        newton = NewtonSettings(max_iterations=integrator["newton_iterations"], tolerance=integrator["tolerance"],
                                line_search=integrator["line_search"], projection=integrator["projection"],
                                alpha=damping["alpha"], beta=damping["beta"])
        self.omega_max = None
        if cfg["integrator"] == "rk4":
            n_sub = cfg["substeps"]
            if n_sub == "auto":
                self.omega_max = max_frequency(self.force_model)
                n_sub = auto_substeps(dt, self.omega_max, damping["alpha"], damping["beta"])
            self.integrator = RK4(self.force_model, dt, n_sub, newton, solver)
        else:
            self.integrator = BackwardEuler(self.force_model, dt, newton, solver)
        self.reset()

    @staticmethod
    def _build_forces(body, cfg):
        """(MeshlessForces, Build): the nodes are the mesh's vertices."""
        return build_forces(body.vertices, body.tets, body.surface.vertex_ids[body.surface.triangles],
                            body.material, cfg, body.pinned)

    def kinetic_energy(self):
        return 0.5 * float((self.state_mass * (self.v * self.v).sum(1)).sum())

    def explain(self):
        cfg, nb = self.settings, self.neighbourhoods
        scheme = (f"explicit RK4, {self.integrator.substeps} sub-steps per step"
                  + (f" (auto: omega_max {self.omega_max:.4g} rad/s)" if self.omega_max else "")
                  if cfg["integrator"] == "rk4" else
                  f"backward Euler, {self.integrator.settings.max_iterations} Newton iteration(s)")
        b = self.build
        cond = (f"{b.grown} nodes with ill-conditioned moment matrices (condition > {COND_LIMIT:g}: nearly "
                f"coplanar neighbours) got neighbours chosen over the octants round them"
                + (f", {b.ill_conditioned} stayed ill-conditioned (nearly coplanar nodes: a thin part or "
                   f"strongly anisotropic cells; refine the mesh across it)" if b.ill_conditioned else "")
                + (f", {self.op.floored} moment matrices floored" if self.op.floored else ""))
        integ = ("consistent nodal integration (integration constraint met to "
                 f"{b.integration_residual:.1e})" if cfg["integration"] == "consistent" else
                 "raw nodal integration (no integration-constraint correction)")
        return [f"meshless model ([HZ] MLS, docs/method.md §19): {len(self.x)} nodes "
                f"({self._nodes_said()}), {self.n_dofs} DOFs, {nb.k} neighbours each, support radius {cfg['support_scale']:g} x mean neighbour distance "
                f"({nb.h.min():.3g} to {nb.h.max():.3g} m); {cond}",
                f"  {integ}; fit-residual stabilisation {cfg['stabilisation']:g} mu; integration weights "
                f"{self._volumes_said()}; "
                f"[HZ]'s StVK law with k_v = {cfg['volume_stiffness']:g} mu"
                + (f", compression barrier {self.force_model.kb / self.force_model.mu:g} mu below J = "
                   f"{self.force_model.jb:g} on the nodes{' and the tets' if self.force_model.tets is not None else ''}"
                   if self.force_model.kb > 0 else "") + f"; {scheme}"]

    def _nodes_said(self):
        return "the mesh vertices"

    def _volumes_said(self):
        v = self.settings["volumes"]
        if v == "kernel":
            m = float(self.force_model.vertex_mass.sum())
            return (f"[HZ] eqs. 1-3 kernel densities and volumes (total mass {m:.4g} kg, "
                    f"{m / (self.body.material.density * float(self.force_model.V.sum())):.3f} x rho sum V)")
        return "the tet mesh vertex volumes" if v == "mesh" else "[HZ] eq. 2 support volumes"


@dataclass(frozen=True)
class Lattice:
    """The nodes of `nodes: lattice` (nodes.py) and how the mesh's vertices follow them."""
    spacing: float            # m, the lattice's cube edge
    X: np.ndarray             # (n, 3) nodes at rest
    V: np.ndarray             # (n,) nodal volumes, summing to the mesh's volume
    pinned: np.ndarray        # (p,) pinned node ids
    embedding: Embedding      # every mesh vertex from the nodes (embedding.py)
    boundary: np.ndarray      # (n, 3) the surface's area vectors, spread to the nodes (B*)


def build_lattice(body, cfg, pins=()):
    """Lattice of the body (model.meshless settings cfg): nodes, volumes, pins, embedding.

    Pinned nodes: those the scene's pin regions (`pins`, the selectors that pinned the
    body's vertices) select among the nodes (surface_only: among the nodes on the
    surface), and the node nearest each pinned vertex (an `indices` pin, or a region
    thinner than the lattice). Not "the nodes nearest a pinned vertex": on a mesh coarser
    than the lattice that clamps a beam over half a mesh cell (measured: the 0.5 m beam's
    sag -8.6 % with 0.0125 m nodes in a 0.05 m mesh, -1.2 % with the regions). The pinned
    vertices follow the nodes' fit: they hold to its accuracy (test_meshless_lattice)."""
    tri = body.surface.vertex_ids[body.surface.triangles]
    volume = float(signed_volumes(body.vertices, body.tets).sum())
    h = (float(cfg["spacing"]) if cfg["spacing"] != "auto"
         else (volume / len(body.vertices)) ** (1.0 / 3.0))     # about as many nodes as vertices
    X = lattice_nodes(body.vertices, tri, h)
    V = lattice_volumes(X, body.vertices, tri, h, volume)
    emb = Embedding(*shape_functions(X, body.vertices, cfg["neighbours"], cfg["support_scale"]))
    pinned = np.empty(0, dtype=np.int64)
    if body.pinned.size:
        s, _ = signed_distance(X, body.vertices, tri)
        on_surface = np.flatnonzero(np.abs(s) <= 1e-9 * h)
        selected = [select_vertices(X, region, on_surface) for region in pins if "indices" not in region]
        _, nearest_node = cKDTree(X).query(body.vertices[body.pinned])
        pinned = np.unique(np.concatenate(selected + [nearest_node]))
    q_points, q_areas = surface_quadrature(body.vertices, tri, h)
    boundary = Embedding(*shape_functions(X, q_points, cfg["neighbours"], cfg["support_scale"])).spread(q_areas, len(X))
    return Lattice(h, X, V, pinned.astype(np.int64), emb, boundary)


class LatticeMeshlessModel(EmbeddedNodes, MeshlessModel):
    """`model.meshless.nodes: lattice`: the unknowns x, v (n_nodes, 3) are the nodes of a
    regular lattice clipped to the body (nodes.py); the mesh's vertices (output, loads,
    contacts, the guard's inverted tets) move by the nodes' MLS interpolation
    (embedding.py). vertex_mass stays the mesh's lumped vertex masses (what the Simulator
    distributes a handle's wrench by); the dynamics use the nodes' masses."""

    def _build_forces(self, body, cfg):
        self.lattice = build_lattice(body, cfg, self.pins)
        lat = self.lattice
        forces, build = build_forces(lat.X, None, None, body.material, cfg, lat.pinned,
                                     volumes=lat.V, boundary=lat.boundary)
        forces.embedding = self.embedding = lat.embedding
        return forces, build

    def __init__(self, body, dt, integrator, damping, settings=None, solver="auto", pins=()):
        self.pins = list(pins)          # the scene's pin regions, applied to the nodes
        super().__init__(body, dt, integrator, damping, settings, solver)
        self.vertex_mass = body.material.density * lumped_mass(body.tets, signed_volumes(body.vertices, body.tets),
                                                               1.0, len(body.vertices))

    @property
    def node_rest(self):
        return self.lattice.X

    @property
    def node_pinned(self):
        return self.lattice.pinned

    def _nodes_said(self):
        lat = self.lattice
        return (f"a cubic lattice of {lat.spacing:.4g} m clipped to the body, {lat.pinned.size} pinned; the "
                f"{len(self.body.vertices)} mesh vertices follow them by MLS interpolation")

    def _volumes_said(self):
        return "the nodes' Voronoi cells in the body (sampled)"
