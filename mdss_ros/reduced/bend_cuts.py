"""Cuts where the scene bends a limb further than one frame and subspace carry
(docs/method.md §5.1).

A domain moves as a rigid frame plus a modal subspace: the frame takes the domain's mean
rotation, and the subspace has to carry every rotation about it. Modal derivatives
stretch that range, but not indefinitely (star_limbs: one domain per arm, 1.1 % RMS error
at a 54 degree bend, 4.0 % at 145 degrees; the arm cut in two halves the error). So the
automatic partition (auto_domains.py) cuts each limb where the scene's loads bend it
more than max_bend.

The training poses are the body's static answers at rest to the scene's load cases
(model_build.training_load_cases: gravity with each set of wrenches and point forces the
timeline holds at once, and each non-plane collider's deepest pose pushing the surface out
of it), with the scene's pins held. A pinned body's force cases are solved nonlinearly
(fem/statics.py, the load ramped), since a linear answer cannot see an arm curl under a
load along it; a floating body's force cases are linear in inertia relief (the load's
rigid part is answered by acceleration, as in residual_compliance.static_responses), and
pushed cases are linear with the pushed vertices prescribed.

Each element's rotation R_e is the polar factor of its deformation gradient F_e. Along a
limb (with its root zone in the core, auto_domains._root_zones), s is the distance from
its root, and a band of s turns by R(s), the polar factor of sum V_e R_e over its
elements (the chordal mean). The bend between two bands is the angle of R(s1)^T R(s2). A
limb is cut greedily from its root (greedy_cuts): the core keeps a piece that bends
little, and the rest is cut into as few pieces as keep their spans, the largest bend
between two of their bands over every case, within max_bend. Cuts therefore fall where
the loads bend the limb most (near the root for a tip load), and an unloaded limb stays
whole.

Shapes: n vertices, m tets, c load cases.
"""
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from ..fem.force_model import FEMForceModel
from ..fem.statics import ramped_equilibrium
from ..linear_solver import SparseSolver
from ..rotations import rotation_angles
from .residual_compliance import RestStatics


@dataclass(frozen=True)
class LoadCase:
    """One training pose's loads: label (what it is, for --explain); forces (n, 3) or
    None; pushed (ids (k,), displacement (k, 3)) prescribed vertices, or None."""

    label: str
    forces: object = None
    pushed: object = None

    def key(self):
        """What the precompute key hashes (the label is only words)."""
        return [self.forces, None if self.pushed is None else list(self.pushed)]


def polar_rotations(F):
    """The rotations R (k, 3, 3) of the polar decompositions F = R S of F (k, 3, 3)
    (SVD, reflections turned into rotations)."""
    U, _, Vt = np.linalg.svd(F)
    d = np.sign(np.linalg.det(U @ Vt))
    U[:, :, 2] *= d[:, None]
    return U @ Vt


def element_rotations(tets, grads, u):
    """R (m, 3, 3): each tet's rotation, the polar factor of F = I + sum_a u_a (x) grad N_a.
    tets (m, 4); grads (m, 4, 3); u (n, 3) displacements from rest."""
    return polar_rotations(np.eye(3) + np.einsum("tai,taj->tij", u[tets], grads))


def static_poses(body, vertex_mass, cases, progress=None):
    """Static displacements (c, n, 3) of the body from rest under each LoadCase, with the
    scene's pins held. A pinned body's force cases are nonlinear statics (the load ramped
    over LOAD_STEPS); a
    floating body answers them linearly in inertia relief (RestStatics.answers, one
    factorisation for all). A pushed case is linear and holds its pushed vertices
    at their displacements, K_uu u_u = f_u - K_up u_p; on a floating body a shift 1e-9
    mean(diag K) / mean(m) M ties down the rigid motions the pushed vertices leave free (a
    body squeezed from two sides can still spin about the squeeze axis)."""
    n = len(body.vertices)
    st = RestStatics.of(body, vertex_mass)
    nf = len(st.free)
    out = np.zeros((len(cases), 3 * n))
    forced = [c for c, case in enumerate(cases) if case.pushed is None]
    if forced and not st.floating:
        say = progress or (lambda msg: None)
        model = FEMForceModel(body.vertices, body.tets, body.material, pinned=body.pinned)
        for c in forced:                              # a few load cases, a Newton solve each
            x, info = ramped_equilibrium(model, np.asarray(cases[c].forces, dtype=np.float64), LOAD_STEPS, ACCEPT)
            say(f"training pose {c}: nonlinear statics, {info['load_steps']} load steps, residual "
                f"{info['residual']:.1e}")
            out[c] = (x - body.vertices).ravel()
    elif forced:
        F = np.stack([np.asarray(cases[c].forces, dtype=np.float64).ravel()[st.free] for c in forced], axis=1)
        U, _ = st.answers(F, progress=progress)
        out[np.ix_(forced, st.free)] = U.T
    K = st.K
    if st.floating:
        K = (K + sp.diags(1e-9 * float(K.diagonal().mean()) / float(st.m_dof.mean()) * st.m_dof)).tocsr()
    for c, case in enumerate(cases):                  # a few collider poses, a solve each
        if case.pushed is None:
            continue
        ids, disp = case.pushed
        dofs = st.free_dof[(3 * np.asarray(ids, dtype=np.int64)[:, None] + np.arange(3)).ravel()]
        ok = dofs >= 0                                # a pinned vertex stays where it is
        u = np.zeros(nf)
        u[dofs[ok]] = np.asarray(disp, dtype=np.float64).ravel()[ok]
        held = np.zeros(nf, dtype=bool)
        held[dofs[ok]] = True
        keep = np.flatnonzero(~held)
        f = np.zeros(nf) if case.forces is None else np.asarray(case.forces, dtype=np.float64).ravel()[st.free]
        Kk = K[keep][:, keep].tocsr()
        Kk.sort_indices()
        solver = SparseSolver().factor(Kk)
        u[keep] = np.asarray(solver.solve(f[keep] - K[keep][:, held] @ u[held])).ravel()
        solver.close()
        out[c, st.free] = u
    return out.reshape(len(cases), n, 3)


#: Load steps tried in turn by the nonlinear training poses, and the relative residual
#: accepted: a pose places cuts, it need not be a ground truth.
LOAD_STEPS, ACCEPT = (1, 4, 16), 1e-6


def limb_bend_profile(rot, volume, s_tet, in_limb, width, reach):
    """Each band's rotation along a limb: (bands (b,) lower edges in s, bend (c, b, b) the
    angle (rad) between every two bands' rotations in each case). rot (c, m, 3, 3) per case
    and tet; volume (m,); s_tet (m,) each tet's distance from the core; in_limb (m,) bool;
    width: band width (m); reach: the limb's length beyond the core. Bands that hold no tet
    are left out."""
    nb = max(1, int(np.ceil(reach / width)))
    edges = np.arange(nb) * (reach / nb)
    band = np.clip((s_tet[in_limb] / (reach / nb)).astype(np.int64), 0, nb - 1)
    c = rot.shape[0]
    acc = np.zeros((c, nb, 3, 3))
    np.add.at(acc, (slice(None), band), volume[in_limb][None, :, None, None] * rot[:, in_limb])
    has = np.flatnonzero(np.bincount(band, minlength=nb) > 0)      # bands that hold a tet
    edges, nb = edges[has], len(has)
    mean = polar_rotations(acc[:, has].reshape(-1, 3, 3)).reshape(c, nb, 3, 3)
    rel = np.einsum("cbji,cdjk->cbdik", mean, mean)                      # R_b^T R_d
    return edges, rotation_angles(rel)


def _grow(bend, start, limit, min_bands):
    """The band after the piece that starts at band start and grows while its span (the
    largest bend[:, i, j] between two of its bands over every case) stays within limit,
    at least min_bands long and leaving at least min_bands; bend (c, b, b). None when it
    reaches the last band."""
    nb = bend.shape[1]
    for b in range(start + min_bands, nb - min_bands + 1):      # a few dozen bands
        if float(bend[:, start:b + 1, start:b + 1].max()) > limit:
            return b
    return None


def greedy_cuts(bend, first_bend, max_bend, min_bands):
    """Bands (k,) where a limb's pieces start, and the spans (k + 1,) rad of its k + 1
    pieces. bend (c, b, b): the angle between every two bands' rotations, band 0 at the
    limb's root (in the core). The first piece, the core's share, grows while its span
    stays within first_bend; none is cut if the whole limb does. The rest is cut into as
    few pieces as keep within max_bend, with their spans balanced (the greedy limit is the
    rest's span over that count), at least min_bands bands each. first_bend None: no share
    for a core, the whole limb balanced so (a body without limbs)."""
    if first_bend is None:
        total = float(bend.max())
        first_bend = total / max(1, int(np.ceil(total / max_bend))) * (1.0 + 1e-9)
    first = _grow(bend, 0, first_bend, min_bands)
    if first is None:
        return np.zeros(0, dtype=np.int64), np.array([float(bend.max())])
    cuts = [first]
    total = float(bend[:, first:, first:].max())
    limit = total / max(1, int(np.ceil(total / max_bend))) * (1.0 + 1e-9)
    while True:
        nxt = _grow(bend, cuts[-1], limit, min_bands)
        if nxt is None:
            break
        cuts.append(nxt)
    bounds = [0] + cuts + [bend.shape[1]]
    spans = [float(bend[:, a:b, a:b].max()) for a, b in zip(bounds[:-1], bounds[1:])]
    return np.asarray(cuts, dtype=np.int64), np.asarray(spans)


def limb_cuts(rot, volume, tets, s, members, width, min_length, max_bend, first_bend):
    """Where to cut one limb: (cut positions (k,) in s, spans (k + 1,) rad of the pieces,
    the largest bend in the limb rad). rot (c, m, 3, 3) per case and tet; volume (m,);
    tets (m, 4); s (n,) each vertex's distance along the limb (0 at its root in the core);
    members: the vertex ids of the limb with its root zone; width: the profile's band
    width; min_length: the shortest piece; max_bend, first_bend: greedy_cuts' limits
    (rad; first_bend None: balanced from the root)."""
    inside = np.zeros(len(s), dtype=bool)
    inside[members] = True
    in_limb = inside[tets].all(axis=1)
    s_tet = np.where(in_limb, s[tets].mean(axis=1), 0.0)
    reach = float(s[members].max())
    if not reach > 0.0:
        # Every vertex is a root vertex (a free body that the poses move or turn as a whole:
        # _bend_body's calmest part is all of it): no length to cut along, and nothing bends.
        return np.zeros(0), np.zeros(1), 0.0
    edges, bend = limb_bend_profile(rot, volume, s_tet, in_limb, width, reach)
    min_bands = max(1, int(np.ceil(min_length / max(reach / len(edges), 1e-300))))
    cuts, spans = greedy_cuts(bend, first_bend, max_bend, min_bands)
    return edges[cuts], spans, float(bend.max())
