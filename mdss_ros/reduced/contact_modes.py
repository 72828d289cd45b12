"""Contact modes: answers to contact loads added to the subspace (docs/method.md §14.3).

The product's remedy for the dent a few modes cannot make is the residual compliance
(residual_compliance.py, §14.2): a massless static correction added to the contact, with
no change to the step's matrix. This module builds the alternatives it is measured against
(`mdss verify contact`, issue 18's anchors): shapes that join the subspace itself, so they
carry mass, go through the nonlinear forces and the cubature, and enlarge the step's
system. Two families, on the candidate vertices a collider can touch
(model_build.contact_candidates, `model.contact_modes.vertices` of them):

    static   u = K^+ P E_c                 the whole body's static answer to a unit load on
                                            each DOF of each candidate (inertia relief for a
                                            floating body): static contact-response modes
                                            from the precompute
    local    u = K_pp^-1 E_c               the same with every vertex farther than `radius`
                                            from all candidates held: compact support, like
                                            the local deformation functions Harmon and Zorin
                                            (2013) add where contact starts (built here once,
                                            where the colliders' paths touch)

E_c (3 n, 3 n_c) selects the candidates' DOFs; K is the stiffness at rest with the scene's
pins; p the patch's free DOFs. In each subspace domain holding candidates, the fields on its
vertices W (3 n_i, 3 n_c) are made M-orthogonal to the domain's rigid motions (a movable
domain's frame carries them) and to its modes U, compressed by mass PCA to `count`
directions, and appended:

    U' = [U, Y],   Y = pca_M( (I - U U^T M)(I - R R^T M) W, count )   U'^T M U' = I

A linear material at rest held by a collider on candidate vertices only then answers
exactly in the static family (the load lies in E_c, its full answer in span(W)) when
count >= 3 n_c; fewer directions are a compression, and the local family is stiffer by
its held boundary.

Shapes: n vertices, n_c candidates, n_i vertices of a domain.
"""
import dataclasses

import numpy as np
import scipy.sparse as sp
from scipy.spatial import cKDTree

from ..fem.force_model import FEMForceModel
from ..linear_solver import SparseSolver
from .modal_basis import mass_pca, mass_project, mass_orthonormalise, rigid_modes
from .residual_compliance import static_responses

KINDS = ("static", "local")
#: Default patch radius of the local family, in mean surface edges.
LOCAL_RADIUS_EDGES = 4.0


def local_responses(body, vertex_mass, candidates, radius, progress=None):
    """(3 n, 3 n_c) the answers to a unit load on each candidate DOF with every vertex
    farther than radius (m) from all candidates held (and the scene's pins): zero outside
    the patch. Returns (fields, patch vertex count)."""
    say = progress or (lambda msg: None)
    X, n = body.vertices, len(body.vertices)
    candidates = np.asarray(candidates, dtype=np.int64)
    near = cKDTree(X[candidates]).query(X, distance_upper_bound=radius)[0] <= radius     # (n,)
    held = np.flatnonzero(~near)
    if held.size == 0 and len(body.pinned) == 0:
        # The patch is the whole floating body: nothing holds it, and its answers are the
        # static family's (inertia relief). The 4 cm grasp cube's patch, solved as it was,
        # read its pads' force at 36 times full FEM's.
        return static_responses(body, vertex_mass, candidates, progress=progress)[0], n
    fem = FEMForceModel(X, body.tets, body.material, pinned=np.union1d(held, body.pinned))
    K = fem.pattern.matrix(fem.tangent(X)[2]).tocsr()
    K.sort_indices()
    free_dof = fem.pattern.free_dof
    cand_dof = free_dof[(3 * candidates[:, None] + np.arange(3)).ravel()]
    if np.any(cand_dof < 0):
        raise ValueError("contact modes: candidates must be free vertices")
    say(f"local contact modes: patch of {int(near.sum())} vertices within {radius:.4g} m of "
        f"{len(candidates)} candidates, {len(cand_dof)} solves")
    B = sp.csr_matrix((np.ones(len(cand_dof)), (cand_dof, np.arange(len(cand_dof)))),
                      shape=(K.shape[0], len(cand_dof))).toarray()
    solver = SparseSolver().factor(K)
    u_free = np.asarray(solver.solve(B)).reshape(K.shape[0], -1)
    solver.close()
    fields = np.zeros((3 * n, len(cand_dof)))
    rows = np.flatnonzero(free_dof >= 0)
    fields[rows] = u_free[free_dof[rows]]
    return fields, int(near.sum())


def contact_fields(body, vertex_mass, candidates, settings, progress=None):
    """(3 n, 3 n_c) fields of the family settings["kind"] on the candidates, and what was
    built (dict)."""
    kind = settings["kind"]
    if kind == "static":
        fields, _, _, _, built = static_responses(body, vertex_mass, candidates, progress=progress)
        return fields, {"kind": kind, "full_dofs": built["full_dofs"]}
    if kind == "local":
        radius = float(settings.get("radius") or 0.0)
        if radius <= 0:
            faces = body.surface.faces
            edges = body.vertices[faces[:, [1, 2, 0]]] - body.vertices[faces]
            radius = LOCAL_RADIUS_EDGES * float(np.linalg.norm(edges, axis=2).mean())
        fields, patch = local_responses(body, vertex_mass, candidates, radius, progress=progress)
        return fields, {"kind": kind, "radius": radius, "patch_vertices": patch}
    raise ValueError(f"contact modes: kind {kind!r} (one of {', '.join(KINDS)})")


def domain_contact_modes(dom, fields, count):
    """(3 n_i, q) at most count new M-orthonormal directions of the fields (3 n, k) on
    domain dom's vertices, M-orthogonal to its rigid motions (movable domain) and its modes;
    q may be smaller when the fields hold fewer independent directions."""
    rows = (3 * dom.vertices[:, None] + np.arange(3)).ravel()
    W = fields[rows]
    m = np.repeat(dom.mass, 3)
    if dom.movable:
        W = mass_project(W, rigid_modes(dom.r_local, dom.mass), m)
    for _ in range(2):                      # twice: one pass leaves round-off along U
        W = mass_project(W, dom.U, m)
    Y, _ = mass_pca(W, m, count)
    return mass_orthonormalise(Y, m) if Y.shape[1] else Y


def add_contact_modes(subspace, body, vertex_mass, candidates, settings, progress=None, what="contact modes"):
    """The subspace domains with contact modes appended where they hold candidates
    (list of SubspaceDomain), and a note for `--explain`. candidates (n_c,) global free
    vertex ids in subspace domains. The same modes on the coupling elements' vertices
    are interface (attachment) modes (what="interface modes", model.basis.interface_modes)."""
    say = progress or (lambda msg: None)
    fields, built = contact_fields(body, vertex_mass, candidates, settings, progress=say)
    count = int(settings["count"])
    out, added = [], {}
    for dom in subspace:
        if not np.isin(candidates, dom.vertices).any():
            out.append(dom)
            continue
        Y = domain_contact_modes(dom, fields, count)
        added[dom.name] = int(Y.shape[1])
        out.append(dataclasses.replace(dom, U=np.hstack([dom.U, Y]),
                                       basis_info=dict(dom.basis_info, contact_modes=int(Y.shape[1]))))
    extra = ", radius {radius:.4g} m, patch of {patch_vertices} vertices".format(**built) if "radius" in built else ""
    note = (f"{built['kind']} {what} on {len(candidates)} vertices{extra}: "
            + ", ".join(f"{name} +{q}" for name, q in added.items()))
    say(f"{what}: {note}")
    return out, note
