"""`model.domains: auto`: one domain for the body's core and one per limb, found from its
shape (docs/method.md §5).

The multi-domain method pays where parts of a body move far from each other: limbs that
bend and swing about a core. Limbs are found from geodesic distances on the tet mesh's
edge graph (lengths in metres):

    depth(v) = distance from v to the surface          (multi-source Dijkstra)
    c        = argmax depth                             the core: the thickest point
    T        = depth(c)                                 the core's half-thickness
    d(v)     = distance from c to v                     (Dijkstra)

The core is the geodesic ball d <= R. Outside it the body falls apart into connected
pieces; a piece reaching further than min_limb * T beyond the ball is a limb and gets a
domain, a shorter one (a rim, a bump) joins the core. R is the smallest radius from
core_scale * T (1.5 T: a little more than the core's own radius, so the core domain
holds where the limbs attach) upwards, in steps of T / 4, that separates the most limbs:
a core wider than its depth says (a pedestal hub whose top joins every arm) needs a
larger ball before its limbs come apart. With limb_segments = n, each limb is cut into n bands of equal geodesic length
(cuts across the limb, where a long limb bends).

Every domain is connected by construction: limbs and their bands are connected pieces
of the graph, and the core is a geodesic ball (connected) with the short pieces that
touch it. The cuts lie where a limb leaves the core, which is where it bends relative to
it. The graph has one edge per tet edge, so all of this is O(E log V) in scipy's
compiled Dijkstra and connected-components; there is no Python loop over vertices.
"""
from __future__ import annotations

import numpy as np
from scipy.sparse import csgraph

from mdss_ros.errors import SceneError
from mdss_ros.fem.elements import tet_geometry
from mdss_ros.reduced.bend_cuts import element_rotations, limb_cuts
from mdss_ros.rotations import rotation_angles

AUTO_KEYS = {"core_scale", "min_limb", "limb_segments", "max_bend"}
#: max_bend (degrees): the largest bend a limb's domain is left to carry in the scene's
#: training poses (bend_cuts.py); 0 turns the cuts from the scene's loads off.
#: Off by default: every cut measured cost more than it gained. An added interface
#: stiffens the model more than a second frame and subspace relieve it, and a limb start
#: moved into the core's root zone (a "cut" into one piece) lost accuracy too
#: (docs/verification.md, session 19, at basis.extension 1.0). star_limbs with the load
#: levels' loads as timeline: large (arm0 at 145 deg) 1.64 % RMS without cuts against
#: 3.13 % at 90 deg and 3.65 % at 150 deg; medium 0.44 % against 0.73 % at 90 deg; small
#: no cut at any angle. A clamped beam bent 153 deg: 9.5 % in one domain, 17.7 % cut at
#: 90 deg. Off, the build also skips the training poses' nonlinear statics. A scene that
#: wants the cuts sets max_bend itself.
DEFAULTS = {"core_scale": 1.5, "min_limb": 1.0, "limb_segments": 1, "max_bend": 0.0}
#: model.basis.extension of automatic domains when the scene gives neither basis.extension
#: nor basis.layers (scene.model_config sets it; explicit counts and regions keep
#: domains.build_subspace_domain's 0.5). Each domain's modes are computed on its region
#: grown by about one diameter, so a limb's modes see the neighbour it hangs from: the
#: cheapest remedy for the stiff interfaces measured (docs/verification.md, session 18:
#: star_limbs' plain auto 2.62 -> 1.64 % RMS at the large load, 0.78 -> 0.44 % at the
#: medium one; octopus -0.04 points, capped by basis.max_growth; a one-domain body
#: unchanged; no build cost).
AUTO_EXTENSION = 1.0


def auto_settings(spec):
    """The settings of `model.domains: auto` (the string) or `{auto: {...}}`."""
    if spec == "auto" or spec is True:
        return dict(DEFAULTS)
    if not isinstance(spec, dict):
        raise SceneError(f"model.domains.auto: expected true or a mapping of {sorted(AUTO_KEYS)}, got {spec!r}")
    unknown = sorted(set(spec) - AUTO_KEYS)
    if unknown:
        raise SceneError(f"model.domains.auto: unknown key(s) {', '.join(unknown)} (allowed: {', '.join(sorted(AUTO_KEYS))})")
    out = dict(DEFAULTS, **spec)
    for k in ("core_scale", "min_limb"):
        if isinstance(out[k], bool) or not isinstance(out[k], (int, float)) or not out[k] > 0:
            raise SceneError(f"model.domains.auto.{k}: expected a positive number, got {out[k]!r}")
    b = out["max_bend"]
    if isinstance(b, bool) or not isinstance(b, (int, float)) or not 0 <= b <= 360:
        raise SceneError(f"model.domains.auto.max_bend: expected degrees in [0, 360] (0: no cuts from the "
                         f"scene's loads), got {b!r}")
    n = out["limb_segments"]
    if isinstance(n, bool) or not isinstance(n, int) or n < 1:
        raise SceneError(f"model.domains.auto.limb_segments: expected an integer >= 1, got {n!r}")
    return out


def surface_vertices(tets):
    """Sorted ids of the vertices on the boundary (faces used by one tet only)."""
    from mdss_ros.mesh.surface import boundary_faces
    return np.unique(boundary_faces(np.asarray(tets, dtype=np.int64)))


def _limbs(graph, d, R, reach_min, max_contact=0.5):
    """(limbs [(vertex ids, reach)], outside ids): the connected pieces of {d > R}
    reaching further than reach_min beyond R, longest first (ties: lowest vertex id).

    A limb hangs off the core through a neck: a piece that touches more than max_contact
    of the core's boundary vertices wraps around it (the shell of a compact body, the rest
    of a uniform beam) and is not a limb."""
    n = len(d)
    outside = np.flatnonzero(d > R)
    if not len(outside):
        return [], outside
    count, piece = csgraph.connected_components(graph[outside][:, outside], directed=False)
    reach = np.zeros(count)
    np.maximum.at(reach, piece, d[outside] - R)
    first = np.full(count, n)
    np.minimum.at(first, piece, outside)
    # core boundary vertices each piece touches (an edge from the core to the piece)
    piece_of = np.full(n, -1, dtype=np.int64)
    piece_of[outside] = piece
    coo = graph.tocoo()
    cross = (piece_of[coo.row] < 0) & (piece_of[coo.col] >= 0)
    pairs = np.unique(np.stack([piece_of[coo.col[cross]], coo.row[cross]], axis=1), axis=0)
    touched = np.bincount(pairs[:, 0], minlength=count)
    boundary = max(1, len(np.unique(pairs[:, 1])))
    order = sorted(range(count), key=lambda p: (-reach[p], first[p]))
    return [(outside[piece == p], float(reach[p])) for p in order
            if reach[p] > reach_min and touched[p] <= max_contact * boundary], outside


def _core_radius(graph, d, T, core_scale, min_limb):
    """The core radius R >= core_scale T that separates the most limbs (the smallest such R).

    A core much wider than its thickest point's depth (a pedestal hub whose top joins every
    arm) keeps the limbs joined in one piece at R = core_scale T; growing R in steps of
    T / 4 until half the body's reach finds the radius where they come apart."""
    best = None
    for scale in np.arange(core_scale, max(core_scale, 0.5 * float(d.max()) / T) + 1e-9, 0.25):
        R = float(scale * T)
        limbs, outside = _limbs(graph, d, R, min_limb * T)
        if best is None or len(limbs) > len(best[1]):
            best = (R, limbs, outside)
    return best


def auto_domains(vertices, tets, graph, core_scale=1.5, min_limb=1.0, limb_segments=1, max_bend=0.0,
                 poses=None):
    """Core and limb domains of a body.

    vertices (n, 3); tets (m, 4); graph: the (n, n) edge-length graph (partition.vertex_graph
    with weights=vertices); poses: None, or a callable giving the scene's training poses
    (case labels [str], displacements (c, n, 3)), called only when max_bend > 0: each limb
    (or a body without limbs, from its calmest part) is then cut where they bend it more
    than max_bend degrees (bend_cuts.py). Returns (labels (n,) int64, names [str], notes
    [str]): label 0 is "core", then "limb0", "limb1", ... (or "limb0_0", "limb0_1", ...
    with segments or bend cuts; "bend1", "bend2", ... on a body without limbs), limbs
    ordered by decreasing reach; notes say where each cut is and why.
    """
    n = len(vertices)
    surf = surface_vertices(tets)
    depth = csgraph.dijkstra(graph, directed=False, indices=surf, min_only=True)
    c = int(np.argmax(depth))
    T = float(depth[c])
    d = csgraph.dijkstra(graph, directed=False, indices=c)
    if not np.all(np.isfinite(d)):
        raise SceneError("model.domains: auto needs a connected body; this mesh has "
                         f"{int((~np.isfinite(d)).sum())} vertices not connected to the rest")
    R, limbs, outside = _core_radius(graph, d, T, core_scale, min_limb)
    labels = np.zeros(n, dtype=np.int64)
    names, notes = ["core"], []
    short = len(outside) - sum(len(v) for v, _ in limbs)
    bends = _bend_rotations(vertices, tets, poses) if (limbs and poses is not None and max_bend > 0
                                                        and limb_segments == 1) else None
    if bends is not None:
        root_of = _root_zones(graph, d, core_scale * T, limbs)
    for j, (verts, length) in enumerate(limbs):
        if bends is not None:
            rot, volume, case_labels = bends
            pieces, why = _bend_pieces(graph, d, rot, volume, tets, verts, np.flatnonzero(root_of == j), T,
                                       max_bend)
            for k, ids in enumerate(pieces):
                labels[ids] = len(names)
                names.append(f"limb{j}" if len(pieces) == 1 else f"limb{j}_{k}")
            notes.append(f"limb{j}: {len(verts)} vertices reaching {length:.4g} m beyond the core; the training "
                         f"poses ({'; '.join(case_labels)}) {why}")
            continue
        if limb_segments == 1:
            labels[verts] = len(names)
            names.append(f"limb{j}")
        else:
            band = np.minimum(((d[verts] - R) / length * limb_segments).astype(np.int64), limb_segments - 1)
            for s in range(limb_segments):
                labels[verts[band == s]] = len(names)
                names.append(f"limb{j}_{s}")
        notes.append(f"limb{j}: {len(verts)} vertices reaching {length:.4g} m beyond the core"
                     + (f", cut into {limb_segments} bands of {length / limb_segments:.4g} m" if limb_segments > 1 else ""))
    if not limbs and poses is not None and max_bend > 0:
        bends = _bend_rotations(vertices, tets, poses)
        if bends is not None:
            pieces, why = _bend_body(graph, tets, bends, T, max_bend)
            for k, ids in enumerate(pieces[1:]):
                labels[ids] = len(names)
                names.append(f"bend{k + 1}")
            notes.append(f"no limbs; the training poses ({'; '.join(bends[2])}) {why}")
    notes.insert(0, f"core: the {int((labels == 0).sum())} vertices within {R:.4g} m ({R / T:.3g} x the core's "
                    f"half-thickness {T:.4g} m: the smallest radius from {core_scale:g} x that separates the "
                    f"most limbs) of the thickest point "
                    f"{np.round(vertices[c], 4).tolist()}; cuts where each limb leaves it"
                 + (f"; {short} vertices beyond it in no limb (pieces reaching less than {min_limb:g} x {T:.4g} m, "
                    f"or wrapping the core) joined it" if short else ""))
    return labels, names, notes


#: The share of max_bend a limb may bend inside the core's domain: the core's frame and
#: modes carry every limb's root, so a limb that bends near the core is cut close to it.
CORE_SHARE = 0.25


def _root_zones(graph, d, R_inner, limbs):
    """(n,) the limb whose root zone each vertex is in, else -1: the core's vertices
    farther than R_inner (core_scale x its half-thickness) from its centre, each given to
    the nearest limb. A core grown wider than that to separate the limbs (a pedestal hub)
    holds the limbs' roots, where a load on a limb bends it most."""
    n = len(d)
    owner = np.full(n, -1, dtype=np.int64)
    for j, (verts, _) in enumerate(limbs):
        owner[verts] = j
    limb_ids = np.flatnonzero(owner >= 0)
    _, _, source = csgraph.dijkstra(graph, directed=False, indices=limb_ids, min_only=True,
                                    return_predecessors=True)
    out = np.full(n, -1, dtype=np.int64)
    zone = (owner < 0) & (d > R_inner) & (source >= 0)
    out[zone] = owner[source[zone]]
    return out


def _bend_pieces(graph, d, rot, volume, tets, verts, root, T, max_bend):
    """The pieces [(ids)] of one limb cut where the training poses bend it (bend_cuts.py),
    and what was done, in words. verts: the limb's vertices; root: its root zone in the core
    (_root_zones). Along the limb s is the distance from the root zone's deepest vertex,
    measured from the limb's tip: 0 at the root. Root-zone vertices before the first cut
    stay in the core (CORE_SHARE of max_bend); no cut leaves the limb whole, as without
    poses."""
    ext = np.concatenate([root, verts])
    tip = int(np.argmax(d[ext]))
    t = csgraph.dijkstra(graph[ext][:, ext], directed=False, indices=tip)
    # Root-zone vertices the limb does not reach within the zone stay in the core.
    reached = np.isfinite(t)
    root, ext, t = root[reached[:len(root)]], ext[reached], t[reached]
    s = np.zeros(len(d))
    s[ext] = t.max() - t
    cuts, spans, whole = limb_cuts(rot, volume, tets, s, ext, 0.25 * T, T, np.radians(max_bend),
                                   np.radians(CORE_SHARE * max_bend))
    start = float(s[verts].min())
    if len(cuts) and cuts[0] >= start:
        # The core's share reaches past the root zone: the limb still starts where it
        # leaves the core (its own frame swings it), and the core keeps its root zone.
        cuts, spans = cuts[1:], np.concatenate([[max(spans[0], spans[1])], spans[2:]])
    if not len(cuts):
        return [verts], f"bend it {np.degrees(whole):.3g} deg (max_bend {max_bend:g} deg: one domain)"
    band = np.searchsorted(cuts, s[ext], side="right")
    band[len(root):] = np.maximum(band[len(root):], 1)           # the limb proper leaves the core
    keep = band > 0
    pieces = _connected_pieces(graph, ext[keep], band[keep])
    return pieces, (f"bend it {np.degrees(whole):.3g} deg, more than {CORE_SHARE:g} x max_bend {max_bend:g} deg "
                    f"from the core: cut at {', '.join(f'{c - start:+.3g}' for c in cuts)} m from where it "
                    f"leaves the core ({len(root)} root vertices in the core's domain before), into {len(pieces)} "
                    f"piece(s) bending {', '.join(f'{np.degrees(a):.3g}' for a in spans[1:])} deg "
                    f"({np.degrees(spans[0]):.3g} deg left to the core)")


def _bend_body(graph, tets, bends, T, max_bend, root_share=0.05):
    """A body without limbs cut where the training poses bend it (a clamped beam under a
    tip load): [(ids)] of its pieces, the first one staying the core, and what was done.
    Along the body s is the geodesic distance from its root, the vertices of the tets that
    turn least (within root_share of the range of the largest turn over the cases: the
    pins of a clamped body, the calmest part of a free one)."""
    rot, volume, _ = bends
    turn = rotation_angles(rot).max(axis=0)                                      # (m,)
    calm = turn <= turn.min() + root_share * (turn.max() - turn.min())
    root = np.unique(tets[calm])
    s = csgraph.dijkstra(graph, directed=False, indices=root, min_only=True)
    everything = np.flatnonzero(np.isfinite(s))
    # No core shared by limbs here: the body's pieces are balanced from the root.
    cuts, spans, whole = limb_cuts(rot, volume, tets, s, everything, 0.25 * T, T, np.radians(max_bend), None)
    if not len(cuts):
        return [everything], f"bend it {np.degrees(whole):.3g} deg (max_bend {max_bend:g} deg: one domain)"
    band = np.searchsorted(cuts, s[everything], side="right")
    pieces = _connected_pieces(graph, everything, band)
    return pieces, (f"bend it {np.degrees(whole):.3g} deg from its calmest part (its {len(root)} root vertices): "
                    f"cut at {', '.join(f'{c:.3g}' for c in cuts)} m from there into {len(pieces)} domains bending "
                    f"{', '.join(f'{np.degrees(a):.3g}' for a in spans)} deg")


def _bend_rotations(vertices, tets, poses):
    """(rot (c, m, 3, 3) each tet's rotation, volume (m,), case labels) of the training poses, or None when the
    scene has no load case."""
    case_labels, u = poses()
    if not len(case_labels):
        return None
    geom = tet_geometry(vertices, tets)
    rot = np.stack([element_rotations(tets, geom.grads, u_c) for u_c in u])
    return rot, geom.volume, case_labels


def _connected_pieces(graph, verts, band, keep=0.2):
    """The pieces [(ids)] of a limb's bands, in band order: a band of geodesic distance
    across a forked limb falls apart into connected pieces, and each of them at least keep
    times its band's largest becomes a piece of its own. Smaller fragments (corners a
    band's edge clips) stay with their band's largest piece, and partition.repair_hinges
    moves them to the neighbour they touch."""
    out = []
    for b in np.unique(band):                 # a few bands per limb
        ids = verts[band == b]
        count, piece = csgraph.connected_components(graph[ids][:, ids], directed=False)
        size = np.bincount(piece, minlength=count)
        big = np.flatnonzero(size >= keep * size.max())
        main = int(np.argmax(size))
        out.extend(ids[(piece == p) | ((p == main) & ~np.isin(piece, big))] for p in big)
    return out
