"""Domains of a partitioned body: subspace domains (frame + modal basis) and full-space ones.

A subspace domain owns its vertices X_i, its domain elements E_i (evaluated exactly in
its own frame, where elasticity does not see the rigid motion) and its basis U_i.
A full-space domain (docs/method.md §12) keeps every vertex of X_i as an unknown in
the world frame; its elements can be cut at run time.
"""
import time
from dataclasses import dataclass, field

import numpy as np

from ..fem.force_model import FEMForceModel
from .frames import fictitious_tensors, rest_inertia


@dataclass
class SubspaceDomain:
    """vertices (n_i,) global ids; r_local (n_i, 3) rest coordinates about cbar;
    mass (n_i,) lumped vertex masses; U (3 n_i, r); movable: has rigid DOFs (no pins)."""

    index: int
    name: str
    vertices: np.ndarray
    cbar: np.ndarray
    r_local: np.ndarray
    mass: np.ndarray
    U: np.ndarray
    movable: bool
    forces: FEMForceModel
    basis_info: dict = field(default_factory=dict)
    sampled: object = None          # SampledDomainForces once cubature is built

    def __post_init__(self):
        self.total_mass = float(self.mass.sum())
        self.inertia0 = rest_inertia(self.r_local, self.mass)
        self.tensors = fictitious_tensors(self.U, self.r_local, self.mass) if self.movable else None
        self.U3 = self.U.reshape(len(self.vertices), 3, -1)       # (n_i, 3, r) view per vertex
        # sum_l m_l U_l (3, r): gravity on the modes; zero for a free domain's basis.
        self.mass_moment = np.einsum("l,lia->ia", self.mass, self.U3)

    def inertia(self, q):
        """Inertia about the centre of mass in the domain frame at deformation q: (3, 3).

        I(q) = sum m (|p|^2 I - p p^T), p = r + U q, a quadratic in q from the
        fictitious-force tensors (B1[a] = sum m u_a r^T, B2[a, b] = sum m u_a u_b^T), so a
        spinning domain that stretches slows down as it should.
        """
        if self.tensors is None:
            return self.inertia0
        B1 = np.einsum("a,aij->ij", q, self.tensors.B1)
        B2 = np.einsum("a,b,abij->ij", q, q, self.tensors.B2)
        lin = B1 + B1.T
        return self.inertia0 + (np.trace(lin) + np.trace(B2)) * np.eye(3) - lin - B2

    @property
    def r(self):
        return self.U.shape[1]

    @property
    def n_dofs(self):
        return self.r + (6 if self.movable else 0)

    def local_positions(self, q):
        """p_l = r_l + U_l q: (n_i, 3) positions in the domain frame."""
        return self.r_local + (self.U @ q).reshape(-1, 3)

    def reduced_tangent(self, q, want_hessian=True):
        """Elastic energy, U^T f_int (r,) and U^T K U (r, r) of the domain elements at q:
        from the cubature samples when the domain has them, else from every element."""
        if self.sampled is not None:
            return self.sampled.evaluate(q, want_hessian)
        p = self.local_positions(q)
        if not want_hessian:
            e, f = self.forces.forces(p)
            return e, self.U.T @ f.reshape(-1), None
        e, f, K_data = self.forces.tangent(p)
        if K_data is None:
            return e, self.U.T @ f.reshape(-1), np.zeros((self.r, self.r))
        K = self.forces.pattern.matrix(K_data)
        return e, self.U.T @ f.reshape(-1), self.U.T @ (K @ self.U)


@dataclass
class FullDomain:
    """A domain simulated in full space: vertices (n_i,) global ids, of which `free`
    (bool (n_i,)) are unknowns (pinned ones are not)."""

    index: int
    name: str
    vertices: np.ndarray
    free: np.ndarray
    elements: np.ndarray          # global tet ids of its domain elements
    alive: np.ndarray = None      # bool per element; cutting clears entries

    def __post_init__(self):
        if self.alive is None:
            self.alive = np.ones(len(self.elements), dtype=bool)

    @property
    def n_dofs(self):
        return 3 * int(self.free.sum())


def submesh_around(tets, vertices_of_domain, n_verts, layers=1, max_growth=3.0):
    """The domain's vertices grown by `layers` rings of elements (stopping once the region
    has max_growth times the domain's vertices), and the tets inside.

    Returns (sub_vertices (k,) global ids, sub_tets (m, 4) local ids, keep (n_i,) local
    ids of the domain's own vertices, -1 for a vertex left out). Modes computed on the
    grown region and then restricted to the domain see an attached boundary rather than a
    free one: free-free modes of a segment have no curvature at its ends, yet the
    interface carries moment.

    The region is one piece joined through faces: the piece holding most of the domain's
    vertices. Tets that join it only along an edge or at a vertex would hang on a hinge,
    and the region's stiffness would have a zero-energy mode besides the rigid ones
    (seen on a coarse armadillo and on users' meshes with thin parts). A domain vertex
    outside that piece gets no modal rows: it moves with the domain's frame.
    """
    in_dom = np.zeros(n_verts, dtype=bool)
    in_dom[vertices_of_domain] = True
    limit = max_growth * len(vertices_of_domain)
    for k in range(layers):
        if k > 0 and in_dom.sum() >= limit:
            break
        in_dom[np.unique(tets[in_dom[tets].any(axis=1)])] = True
    # Tets wholly inside the grown vertex set: a tet that only touches it at a vertex or
    # an edge would hang on a hinge and give the stiffness a zero-energy mode.
    touching = in_dom[tets].all(axis=1)
    sub_t = tets[touching]
    sub_t = _main_face_piece(sub_t, vertices_of_domain, n_verts)
    sub_v = np.unique(sub_t)
    local = np.full(n_verts, -1, dtype=np.int64)
    local[sub_v] = np.arange(len(sub_v))
    return sub_v, local[sub_t], local[vertices_of_domain]


def _main_face_piece(tets, vertices_of_domain, n_verts):
    """The tets (m, 4) of the face-connected piece holding the most domain vertices."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    from .partition import tet_face_pairs
    if len(tets) < 2:
        return tets
    pairs = tet_face_pairs(tets)
    g = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(len(tets), len(tets)))
    n, piece = connected_components(g, directed=False)
    if n == 1:
        return tets
    is_dom = np.zeros(n_verts, dtype=bool)
    is_dom[vertices_of_domain] = True
    # distinct domain vertices per piece: unique (piece, vertex) pairs, counted per piece
    pv = np.unique(np.stack([np.repeat(piece, 4), tets.ravel()], axis=1), axis=0)
    score = np.bincount(pv[:, 0], weights=is_dom[pv[:, 1]], minlength=n)
    return tets[piece == int(np.argmax(score))]


#: model.basis.extension when the scene gives none (automatic domains: scene.model_config
#: sets auto_domains.AUTO_EXTENSION instead).
EXTENSION = 0.5


def layers_for_extension(X, tets, verts, extension):
    """Element rings that grow a domain by about extension x its diameter (at least 1)."""
    diameter = float(np.linalg.norm(X[verts].max(0) - X[verts].min(0)))
    edges = X[tets[:, [1, 2, 3, 2, 3, 3]]] - X[tets[:, [0, 0, 0, 1, 1, 2]]]
    mean_edge = float(np.linalg.norm(edges, axis=2).mean())
    return max(1, int(np.ceil(extension * diameter / max(mean_edge, 1e-300))))


def build_subspace_domain(index, name, body, vertex_mass, verts, elements, r, basis_opts, pinned_mask,
                          U=None, basis_info=None):
    """Basis and local force model of one subspace domain (U, basis_info: from the cache)."""
    from .modal_basis import complete_basis, modal_basis
    t0 = time.perf_counter()
    X = body.vertices
    basis_opts = dict(basis_opts)
    complete = basis_opts.pop("complete", False)
    extension = float(basis_opts.pop("extension", EXTENSION))
    layers = basis_opts.pop("layers", None)
    if layers is None:
        layers = layers_for_extension(X, body.tets[elements] if len(elements) else body.tets, verts, extension)
    layers = int(layers)
    m = vertex_mass[verts]
    cbar = (m[:, None] * X[verts]).sum(0) / m.sum()
    fixed_local = np.flatnonzero(pinned_mask[verts])
    local = np.full(len(X), -1, dtype=np.int64)
    local[verts] = np.arange(len(verts))
    tets_local = local[body.tets[elements]]
    forces = FEMForceModel(X[verts] - cbar, tets_local, body.material) if len(elements) else _NoElements(len(verts))
    if U is not None:
        return SubspaceDomain(index=index, name=name, vertices=verts, cbar=cbar, r_local=X[verts] - cbar,
                              mass=m, U=U, movable=fixed_local.size == 0, forces=forces,
                              basis_info=dict(basis_info or {}, seconds=time.perf_counter() - t0, cached=True))
    sub_v, sub_t, keep = submesh_around(body.tets, verts, len(X), layers,
                                        float(basis_opts.pop("max_growth", 3.0)))
    sub_local = np.full(len(X), -1, dtype=np.int64)
    sub_local[sub_v] = np.arange(len(sub_v))
    present = keep >= 0                   # domain vertices in the region's main piece
    fixed_sub = sub_local[verts[fixed_local]]
    fixed_sub = fixed_sub[fixed_sub >= 0]
    if complete:    # every free DOF: the reduced model is an exact change of basis (tests)
        basis = complete_basis(X[sub_v], sub_t, body.material, vertex_mass[sub_v],
                               fixed=fixed_sub, keep=keep[present])
    else:
        basis = modal_basis(X[sub_v], sub_t, body.material, vertex_mass[sub_v], r,
                            fixed=fixed_sub, keep=keep[present], **basis_opts)
    U = basis.U
    if not present.all():                 # hinged-off vertices: no modal rows (zero), see submesh_around
        U = np.zeros((3 * len(verts), basis.U.shape[1]))
        U[np.repeat(present, 3)] = basis.U
    return SubspaceDomain(index=index, name=name, vertices=verts, cbar=cbar, r_local=X[verts] - cbar,
                          mass=m, U=U, movable=fixed_local.size == 0, forces=forces,
                          basis_info={"n_linear": int(basis.n_linear), "n_derivatives": int(basis.n_derivatives),
                                      "layers": layers, "region_vertices": int(len(sub_v)),
                                      "hinged_vertices": int((~present).sum()),
                                      "derivatives_on": basis.derivative_source,
                                      "eigenvalues": [float(v) for v in basis.eigenvalues],
                                      "seconds": time.perf_counter() - t0, "cached": False})


class _NoElements:
    """Force model of a domain with no domain elements (all its tets are coupling ones)."""

    def __init__(self, n):
        self.n = n

    def forces(self, p):
        return 0.0, np.zeros((self.n, 3))

    def energy(self, p):
        return 0.0

    def tangent(self, p):
        return 0.0, np.zeros((self.n, 3)), None
