"""Vertex-based partition of a tet mesh into domains (docs/method.md §5).

The vertex set is split into d disjoint sets X_i, either automatically
(``partition_vertices``: METIS on the vertex adjacency graph, then a
contiguity repair) or from user regions (``partition_from_regions``: selector
specs seed the domains, the rest is filled by nearest graph distance).
``build_partition`` then derives everything the multi-domain solver needs:

- E_i, the domain elements: tets whose four vertices all lie in X_i;
- the coupling elements: tets whose vertices lie in two or more domains.
  Tets touching three or four domains are kept (the coupling formulas of
  docs/method.md §8 sum over each vertex's own domain, so they apply unchanged);
- the interfaces E_ij (i < j): coupling tets touching both i and j, so a tet
  touching three domains is listed under each of its three pairs;
- the domain graph (neighbours, sorted edge list).

Every tet lands in exactly one E_i or in the coupling set, so the domain
elements and the coupling elements together partition the tets.

``domain_elimination_order`` orders the domains for a block Cholesky of the
block matrix whose sparsity is the domain graph (minimum degree on the
domain graph: leaves first on a tree, hence zero fill), and ``block_fill``
counts the fill blocks an order creates, to compare against a generic order.

Everything that scales with the mesh is vectorised (sorting, ``np.unique``,
``bincount``, ``scipy.sparse.csgraph``); Python loops run over domains or
domain pairs only.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
from scipy.sparse import csgraph

from mdss_ros.errors import SceneError
from mdss_ros.mesh.selectors import select_vertices

# The 6 edges of a tet as pairs of local vertex indices.
_TET_EDGES = np.array([[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]], dtype=np.int64)

# Safety bound on the contiguity repair sweeps (each sweep merges every
# orphan piece that touches a main piece; a few sweeps suffice in practice).
_MAX_REPAIR_SWEEPS = 100


# ---------------------------------------------------------------------------
# graph helpers


def vertex_graph(tets: np.ndarray, n_verts: int, weights: np.ndarray | None = None) -> sp.csr_matrix:
    """Symmetric vertex adjacency of a tet mesh (the tet edges), CSR, no diagonal.

    Args:
        tets: (n_tets, 4) int vertex indices.
        n_verts: number of vertices (unreferenced vertices become isolated nodes).
        weights: optional (n_verts, 3) positions; if given, each entry is the
            Euclidean edge length, else 1.
    Returns:
        (n_verts, n_verts) csr_matrix with sorted indices, each edge stored in
        both directions once.
    """
    tets = np.asarray(tets, dtype=np.int64)
    e = tets[:, _TET_EDGES].reshape(-1, 2)
    e = e[e[:, 0] != e[:, 1]]
    rows = np.concatenate([e[:, 0], e[:, 1]])
    cols = np.concatenate([e[:, 1], e[:, 0]])
    # COO -> CSR sums the duplicates (an edge shared by several tets) in C;
    # much faster than np.unique(axis=0) on the edge rows.
    g = sp.csr_matrix((np.ones(rows.shape[0]), (rows, cols)), shape=(n_verts, n_verts))
    g.sum_duplicates()
    if weights is None:
        g.data[:] = 1.0
    else:
        x = np.asarray(weights, dtype=np.float64)
        r = np.repeat(np.arange(n_verts), np.diff(g.indptr))
        length = np.linalg.norm(x[g.indices] - x[r], axis=1)
        # A zero-length edge would read as "no edge" in csgraph; keep it tiny but present.
        g.data[:] = np.maximum(length, np.finfo(np.float64).tiny)
    g.sort_indices()
    return g


def _check_mesh(vertices, tets) -> tuple[np.ndarray, np.ndarray]:
    x = np.asarray(vertices, dtype=np.float64)
    if x.ndim != 2 or x.shape[1] != 3:
        raise ValueError(f"vertices must have shape (n_verts, 3), got {x.shape}")
    t = np.asarray(tets)
    if t.ndim != 2 or t.shape[1] != 4:
        raise ValueError(f"tets must have shape (n_tets, 4), got {t.shape}")
    if t.size and not np.issubdtype(t.dtype, np.integer):
        raise ValueError(f"tets must hold integer vertex indices, got dtype {t.dtype}")
    t = t.astype(np.int64, copy=False)
    if t.size and (t.min() < 0 or t.max() >= x.shape[0]):
        raise ValueError(
            f"tets index vertices in [{int(t.min())}, {int(t.max())}] but there are "
            f"{x.shape[0]} vertices"
        )
    return x, t


def imbalance(labels: np.ndarray, n_domains: int | None = None) -> float:
    """Load imbalance of a vertex labelling: max / mean domain size - 1 (0 = perfect)."""
    labels = np.asarray(labels, dtype=np.int64)
    d = int(labels.max()) + 1 if n_domains is None else int(n_domains)
    counts = np.bincount(labels, minlength=d)
    return float(counts.max() / counts.mean() - 1.0)


def _same_label_components(graph: sp.csr_matrix, labels: np.ndarray) -> tuple[int, np.ndarray]:
    """Connected components of the graph restricted to edges inside one label.

    All domains at once: an edge survives only if both ends share a label, so
    each component lies inside one domain.
    """
    coo = graph.tocoo()
    keep = labels[coo.row] == labels[coo.col]
    inner = sp.csr_matrix(
        (np.ones(int(keep.sum())), (coo.row[keep], coo.col[keep])), shape=graph.shape
    )
    return csgraph.connected_components(inner, directed=False)


def _repair_contiguity(graph: sp.csr_matrix, labels: np.ndarray, count: int) -> np.ndarray:
    """Make each domain one connected piece of the vertex graph.

    Per domain the largest connected piece is its main piece; every other
    piece (an orphan) moves to the domain whose main piece it shares the most
    graph edges with (ties: lowest domain id). Orphans that only touch other
    orphans wait for the next sweep. Sweeps repeat until no orphan is left or
    no orphan can move (a mesh made of several disconnected bodies: a body
    holding only orphans has no main piece to join; such labels are left as
    METIS gave them).
    """
    labels = labels.copy()
    coo = graph.tocoo()
    u, v = coo.row.astype(np.int64), coo.col.astype(np.int64)
    for _ in range(_MAX_REPAIR_SWEEPS):
        n_comp, comp = _same_label_components(graph, labels)
        comp_label = np.empty(n_comp, dtype=np.int64)
        comp_label[comp] = labels
        comp_size = np.bincount(comp, minlength=n_comp)
        # Main piece of each domain: the largest (ties: lowest component id).
        order = np.lexsort((np.arange(n_comp), -comp_size, comp_label))
        first = np.ones(n_comp, dtype=bool)
        first[1:] = comp_label[order[1:]] != comp_label[order[:-1]]
        is_main = np.zeros(n_comp, dtype=bool)
        is_main[order[first]] = True
        if is_main.all():
            break
        # Edges from an orphan piece to another domain's main piece.
        cu, cv = comp[u], comp[v]
        sel = ~is_main[cu] & is_main[cv]
        if not sel.any():
            break
        pair_comp = cu[sel]
        pair_label = comp_label[cv[sel]]
        key, n_shared = np.unique(pair_comp * count + pair_label, return_counts=True)
        k_comp, k_label = key // count, key % count
        # Per orphan piece the label with most shared edges (ties: lowest label).
        best = np.lexsort((k_label, -n_shared, k_comp))
        take = np.ones(best.shape[0], dtype=bool)
        take[1:] = k_comp[best[1:]] != k_comp[best[:-1]]
        target = np.full(n_comp, -1, dtype=np.int64)
        target[k_comp[best[take]]] = k_label[best[take]]
        move = target[comp] >= 0
        labels[move] = target[comp[move]]
    return labels


def make_contiguous(tets, labels, n_domains: int | None = None) -> np.ndarray:
    """Repair a vertex labelling so every domain is one connected piece.

    The pass ``partition_vertices`` runs after METIS, exposed for labellings
    from elsewhere: per domain the largest connected piece stays, every other
    piece moves to the neighbouring domain it shares the most tet edges with.
    A domain never loses its largest piece, so no domain becomes empty.

    Args:
        tets: (n_tets, 4) int vertex indices.
        labels: (n_verts,) int labels in [0, n_domains).
        n_domains: d; default labels.max() + 1.
    Returns:
        (n_verts,) int64 repaired labels (a new array).
    """
    labels = np.asarray(labels, dtype=np.int64)
    if labels.ndim != 1:
        raise ValueError(f"labels must be 1-D, got shape {labels.shape}")
    _, t = _check_mesh(np.zeros((labels.shape[0], 3)), tets)
    d = int(labels.max()) + 1 if n_domains is None else int(n_domains)
    if labels.min() < 0 or labels.max() >= d:
        raise ValueError(f"labels must lie in [0, n_domains={d})")
    return _repair_contiguity(vertex_graph(t, labels.shape[0]), labels, d)


def tet_face_pairs(tets: np.ndarray) -> np.ndarray:
    """(k, 2) pairs of tets that share a triangle (each interior face once)."""
    t = np.asarray(tets, dtype=np.int64)
    faces = np.sort(np.concatenate([t[:, [0, 1, 2]], t[:, [0, 1, 3]], t[:, [0, 2, 3]], t[:, [1, 2, 3]]]), axis=1)
    owner = np.tile(np.arange(len(t)), 4)
    _, inv = np.unique(faces, axis=0, return_inverse=True)
    order = np.argsort(inv.ravel(), kind="stable")
    inv_s, own = inv.ravel()[order], owner[order]
    same = inv_s[1:] == inv_s[:-1]
    return np.stack([own[:-1][same], own[1:][same]], axis=1)


def repair_hinges(tets, labels, graph=None):
    """Make every domain's own elements (tets with all four vertices in it) one piece
    joined through faces, and give every domain at least one such element.

    A domain whose elements touch only along an edge or at a vertex (a hinge), or that
    holds no element of its own (a layer one tet thick), has a floppy sub-mesh: its modal
    basis finds a zero-energy mode besides the rigid ones and the build fails. METIS
    balances vertices and keeps domains edge-connected, which does not prevent either on
    thin parts. Per sweep: each domain keeps its largest face-connected piece of elements;
    the vertices of its other pieces, and all vertices of a domain without elements, move
    to the neighbouring domain they share the most tet edges with (ties: lowest label).

    Returns (labels (n,) int64 with consecutive labels from 0, old label of each new label
    (d',), number of vertices moved). A domain can vanish (its vertices all moved): the
    second array says which ones are left."""
    t = np.asarray(tets, dtype=np.int64)
    labels = np.asarray(labels, dtype=np.int64).copy()
    n = len(labels)
    graph = vertex_graph(t, n) if graph is None else graph
    coo = graph.tocoo()
    pairs = tet_face_pairs(t)
    moved = np.zeros(n, dtype=bool)
    protected = -1          # a domain without elements allowed to stay and absorb (see below)
    for _ in range(_MAX_REPAIR_SWEEPS * 4):
        lab_t = labels[t]
        own = np.all(lab_t == lab_t[:, :1], axis=1)                    # domain elements
        el_label = np.where(own, lab_t[:, 0], -1)
        keep = own[pairs[:, 0]] & own[pairs[:, 1]] & (el_label[pairs[:, 0]] == el_label[pairs[:, 1]])
        m = len(t)
        g = sp.coo_matrix((np.ones(int(keep.sum())), (pairs[keep, 0], pairs[keep, 1])), shape=(m, m))
        _, piece = csgraph.connected_components(g, directed=False)
        piece = np.where(own, piece, -1)
        # main piece per label: the one with most elements (ties: lowest piece id)
        ids = np.flatnonzero(own)
        key, size = np.unique(np.stack([el_label[ids], piece[ids]], axis=1), axis=0, return_counts=True)
        order = np.lexsort((key[:, 1], -size, key[:, 0]))
        first = np.ones(len(order), dtype=bool)
        first[1:] = key[order[1:], 0] != key[order[:-1], 0]
        main = set(map(int, key[order[first], 1]))
        has_elements = np.zeros(int(labels.max()) + 1, dtype=bool)
        has_elements[key[:, 0]] = True
        in_main = np.zeros(n, dtype=bool)
        main_t = np.isin(piece, list(main))
        in_main[t[main_t].ravel()] = True
        in_other = np.zeros(n, dtype=bool)
        in_other[t[own & ~main_t].ravel()] = True
        to_move = (in_other & ~in_main) | (~has_elements[labels] & (labels != protected))
        if not to_move.any():
            break
        # target: the other label sharing the most edges with each moving vertex
        sel = to_move[coo.row] & (labels[coo.col] != labels[coo.row]) & ~to_move[coo.col]
        if not sel.any():
            # every neighbour moves too (no domain of a thin body holds an element): the
            # largest domain stays and absorbs its neighbours until it holds elements
            sizes = np.bincount(labels[to_move], minlength=int(labels.max()) + 1)
            if protected == int(np.argmax(sizes)):
                break
            protected = int(np.argmax(sizes))
            continue
        d = int(labels.max()) + 1
        k, cnt = np.unique(coo.row[sel] * d + labels[coo.col[sel]], return_counts=True)
        v_of, l_of = k // d, k % d
        best = np.lexsort((l_of, -cnt, v_of))
        take = np.ones(len(best), dtype=bool)
        take[1:] = v_of[best[1:]] != v_of[best[:-1]]
        labels[v_of[best[take]]] = l_of[best[take]]
        moved[v_of[best[take]]] = True
    used, labels = np.unique(labels, return_inverse=True)
    return labels.astype(np.int64), used, int(moved.sum())


def _fill_empty_domains(graph: sp.csr_matrix, labels: np.ndarray, count: int) -> np.ndarray:
    """Give every empty domain one vertex, keeping the donor domain connected.

    METIS may leave a part empty when count approaches n_verts. The donor is
    the largest domain; the vertex it gives up is the last one of a
    breadth-first order from its first vertex (a leaf of the BFS tree, so the
    rest of the donor stays connected). Loops over empty domains only.
    """
    labels = labels.copy()
    sizes = np.bincount(labels, minlength=count)
    for k in np.flatnonzero(sizes == 0):
        donor = int(np.argmax(sizes))
        members = np.flatnonzero(labels == donor)
        sub = graph[members][:, members]
        bfs = csgraph.breadth_first_order(sub, 0, directed=False, return_predecessors=False)
        leaf = members[bfs[-1]] if bfs.shape[0] == members.shape[0] else members[-1]
        labels[leaf] = k
        sizes[donor] -= 1
        sizes[k] += 1
    return labels


# ---------------------------------------------------------------------------
# automatic partition


def partition_vertices(vertices, tets, count: int, seed: int = 0) -> np.ndarray:
    """Split the mesh vertices into ``count`` balanced, contiguous domains.

    METIS (pymetis' default scheme: recursive bisection for count <= 8,
    k-way above) on the vertex adjacency graph (tet edges), unit vertex
    weights, so domains get about n_verts / count vertices each. METIS' own
    contiguity option (honoured by k-way) is switched on when the graph is
    connected, and a repair pass afterwards
    guarantees contiguity anyway: every disconnected piece of a domain but its
    largest moves to the neighbouring domain it shares the most edges with.
    Empty domains (possible only when count approaches n_verts) get one vertex
    from the largest domain. Check the balance with ``imbalance(labels)``.

    Deterministic: METIS runs with a fixed ``seed`` (single-threaded), and the
    repair pass breaks every tie by index.

    Contiguity is guaranteed for a connected mesh. For a mesh made of several
    bodies, a domain can only be contiguous if it lies in one body; pieces that
    have no other domain to join keep their METIS label.

    Args:
        vertices: (n_verts, 3) rest positions (only the count is used by METIS).
        tets: (n_tets, 4) int vertex indices.
        count: number of domains, 1 <= count <= n_verts.
        seed: METIS random seed.
    Returns:
        (n_verts,) int64 labels in [0, count), every label used.
    Raises:
        ValueError: count is not an integer in [1, n_verts], or bad array shapes.
    """
    x, t = _check_mesh(vertices, tets)
    n = x.shape[0]
    if isinstance(count, bool) or not isinstance(count, (int, np.integer)):
        raise ValueError(f"count must be an integer number of domains, got {count!r}")
    count = int(count)
    if count < 1 or count > n:
        raise ValueError(f"count must be in [1, n_verts={n}], got {count}")
    if count == 1:
        return np.zeros(n, dtype=np.int64)

    import pymetis

    graph = vertex_graph(t, n)
    idx = pymetis.zero_copy_dtype()
    adjacency = pymetis.CSRAdjacency(
        adj_starts=np.ascontiguousarray(graph.indptr, dtype=idx),
        adjacent=np.ascontiguousarray(graph.indices, dtype=idx),
    )
    n_comp, _ = csgraph.connected_components(graph, directed=False)
    # METIS' contig option aborts on a disconnected graph, so only ask for it
    # when the graph is connected; the repair pass covers the rest.
    options = pymetis.Options(seed=int(seed), contig=1 if n_comp == 1 else 0)
    _, parts = pymetis.part_graph(count, adjacency=adjacency, options=options)
    labels = np.asarray(parts, dtype=np.int64)
    labels = _repair_contiguity(graph, labels, count)
    if np.bincount(labels, minlength=count).min() == 0:
        labels = _fill_empty_domains(graph, labels, count)
    return labels


# ---------------------------------------------------------------------------
# partition from user regions


def partition_from_regions(
    vertices,
    tets,
    regions: Sequence[dict] | Mapping[str, dict],
    fill: str | None = "nearest",
) -> np.ndarray:
    """Domains from user regions: region k seeds domain k.

    Each region is a selector spec (``mdss_ros.mesh.select_vertices``); its
    selected vertices get domain k (the region's position in the list, or in
    the dict's insertion order; pass ``names=list(regions)`` to
    ``build_partition`` to keep the dict keys as domain names). A vertex
    selected by several regions goes to the FIRST of them, so list specific
    regions before catch-all ones.

    Unselected vertices (``fill="nearest"``) go to the region at the shortest
    graph distance along tet edges, weighted by edge length, found by one
    multi-source Dijkstra (``min_only=True``). Every filled vertex is joined
    to its region by its shortest path, all of whose vertices went to the
    same region, so a connected region grows into a connected domain. With
    ``fill=None`` every vertex must be selected.

    Args:
        vertices: (n_verts, 3) rest positions.
        tets: (n_tets, 4) int vertex indices.
        regions: non-empty list of selector specs, or dict name -> spec.
        fill: "nearest" or None.
    Returns:
        (n_verts,) int64 labels in [0, len(regions)).
    Raises:
        SceneError: a bad spec, a region selecting nothing (or only vertices
            claimed by earlier regions), or vertices left unassigned (fill=None,
            or parts of the mesh no region reaches); the message names the region.
        ValueError: unknown fill mode or bad array shapes.
    """
    x, t = _check_mesh(vertices, tets)
    if fill not in ("nearest", None):
        raise ValueError(f"fill must be 'nearest' or None, got {fill!r}")
    if isinstance(regions, Mapping):
        names = [str(k) for k in regions]
        specs = list(regions.values())
    elif isinstance(regions, Sequence) and not isinstance(regions, (str, bytes)):
        names = [f"regions[{i}]" for i in range(len(regions))]
        specs = list(regions)
    else:
        raise SceneError(
            f"regions must be a list of selector specs or a mapping name -> spec, "
            f"got {type(regions).__name__}"
        )
    if not specs:
        raise SceneError("regions is empty: at least one region is needed")

    n = x.shape[0]
    labels = np.full(n, -1, dtype=np.int64)
    for k, (name, spec) in enumerate(zip(names, specs)):
        try:
            ids = select_vertices(x, spec)
        except SceneError as err:
            raise SceneError(f"region {name!r}: {err}") from err
        if ids.size == 0:
            raise SceneError(f"region {name!r} selects no vertex")
        free = ids[labels[ids] < 0]
        if free.size == 0:
            raise SceneError(
                f"region {name!r} selects only vertices already claimed by earlier regions "
                f"(the first region to select a vertex wins)"
            )
        labels[free] = k

    missing = labels < 0
    if not missing.any():
        return labels
    if fill is None:
        raise SceneError(
            f"{int(missing.sum())} vertices lie in no region and fill is None"
        )
    graph = vertex_graph(t, n, weights=x)
    seeds = np.flatnonzero(~missing)
    _, _, source = csgraph.dijkstra(
        graph, directed=False, indices=seeds, min_only=True, return_predecessors=True
    )
    unreached = missing & (source < 0)
    if unreached.any():
        raise SceneError(
            f"{int(unreached.sum())} vertices are not connected by tet edges to any region "
            f"(e.g. vertex {int(np.flatnonzero(unreached)[0])}); add a region covering them"
        )
    labels[missing] = labels[source[missing]]
    return labels


# ---------------------------------------------------------------------------
# derived partition data


def _readonly(a: np.ndarray) -> np.ndarray:
    a.setflags(write=False)
    return a


@dataclass(frozen=True, eq=False)
class Partition:
    """Domains, their elements, coupling elements and the domain graph.

    Build with ``build_partition``. All arrays are int64 and read-only.

    Attributes:
        labels: (n_verts,) domain of each vertex.
        n_domains: d.
        names: d domain names.
        domain_vertices: d sorted arrays, X_i.
        domain_elements: d sorted arrays of tet indices, E_i (all 4 vertices in X_i).
        coupling_elements: (n_c,) sorted tet indices with vertices in >= 2 domains.
        coupling_domains: (n_c, 4) domain of each of those tets' 4 vertices
            (row k belongs to coupling_elements[k], columns in the tet's vertex order).
        interfaces: {(i, j), i < j: sorted coupling tet indices touching both
            i and j}; a tet touching m domains is in all m (m - 1) / 2 pairs.
        neighbours: d sets of neighbouring domain ids.
        graph_edges: (n_e, 2) domain pairs (i < j), lexicographically sorted;
            the keys of ``interfaces``.

    eq=False: arrays have no single truth value, so partitions compare by identity.
    """

    labels: np.ndarray
    n_domains: int
    names: list[str]
    domain_vertices: list[np.ndarray]
    domain_elements: list[np.ndarray]
    coupling_elements: np.ndarray
    coupling_domains: np.ndarray
    interfaces: dict[tuple[int, int], np.ndarray]
    neighbours: list[set[int]]
    graph_edges: np.ndarray
    n_tets: int = field(default=0)

    @property
    def n_verts(self) -> int:
        return int(self.labels.shape[0])

    def n_domains_touched(self) -> np.ndarray:
        """(n_c,) number of distinct domains each coupling element touches (2..4)."""
        s = np.sort(self.coupling_domains, axis=1)
        return 1 + np.count_nonzero(s[:, 1:] != s[:, :-1], axis=1)

    def summary(self) -> dict:
        """Plain-data report: per-domain sizes, coupling counts, balance, graph.

        ``imbalance`` is max / mean vertices per domain - 1 (0 = perfect);
        ``element_imbalance`` the same for domain element counts.
        """
        nv = np.array([a.shape[0] for a in self.domain_vertices], dtype=np.int64)
        ne = np.array([a.shape[0] for a in self.domain_elements], dtype=np.int64)
        touched = self.n_domains_touched()
        return {
            "n_domains": self.n_domains,
            "n_verts": self.n_verts,
            "n_tets": self.n_tets,
            "names": list(self.names),
            "domain_vertex_counts": nv.tolist(),
            "domain_element_counts": ne.tolist(),
            "n_coupling": int(self.coupling_elements.shape[0]),
            "n_coupling_multi": int(np.count_nonzero(touched >= 3)),
            "imbalance": float(nv.max() / nv.mean() - 1.0),
            "element_imbalance": float(ne.max() / ne.mean() - 1.0) if ne.mean() > 0 else 0.0,
            "graph_edges": [tuple(int(v) for v in e) for e in self.graph_edges],
            "interface_counts": {
                (int(i), int(j)): int(a.shape[0]) for (i, j), a in self.interfaces.items()
            },
            "max_degree": max((len(s) for s in self.neighbours), default=0),
        }

    def format_summary(self) -> str:
        """Readable multi-line report of the domains and the domain graph."""
        s = self.summary()
        width = max(len(n) for n in self.names)
        lines = [
            f"partition: {s['n_domains']} domains, {s['n_verts']} vertices, {s['n_tets']} tets",
            f"  vertex imbalance {100 * s['imbalance']:.1f}% (max/mean - 1), "
            f"element imbalance {100 * s['element_imbalance']:.1f}%",
            f"  coupling elements {s['n_coupling']} "
            f"({s['n_coupling_multi']} touch >= 3 domains)",
            f"  domain graph: {len(s['graph_edges'])} edges, max degree {s['max_degree']}",
            f"  {'id':>3} {'name':<{width}} {'verts':>8} {'elems':>8}  neighbours",
        ]
        for i, name in enumerate(self.names):
            nb = ", ".join(str(j) for j in sorted(self.neighbours[i])) or "-"
            lines.append(
                f"  {i:>3} {name:<{width}} {s['domain_vertex_counts'][i]:>8} "
                f"{s['domain_element_counts'][i]:>8}  {nb}"
            )
        if s["interface_counts"]:
            lines.append("  interfaces (coupling tets):")
            for (i, j), c in s["interface_counts"].items():
                lines.append(f"    {self.names[i]} - {self.names[j]}: {c}")
        return "\n".join(lines)


def _split_sorted(values: np.ndarray, keys: np.ndarray, d: int) -> list[np.ndarray]:
    """Group ``values`` by integer ``keys`` in [0, d) (stable, so sorted values stay sorted)."""
    order = np.argsort(keys, kind="stable")
    bounds = np.cumsum(np.bincount(keys, minlength=d))[:-1]
    return [_readonly(np.ascontiguousarray(a)) for a in np.split(values[order], bounds)]


def build_partition(
    tets,
    labels,
    n_domains: int | None = None,
    names: Sequence[str] | None = None,
) -> Partition:
    """Derive domain elements, coupling elements and the domain graph from vertex labels.

    Args:
        tets: (n_tets, 4) int vertex indices.
        labels: (n_verts,) int domain per vertex, in [0, n_domains).
        n_domains: d; default labels.max() + 1.
        names: d domain names; default "domain_0", "domain_1", ...
    Returns:
        Partition.
    Raises:
        ValueError: shapes, labels out of range, an empty domain (named), or
            wrong number of names.
    """
    labels = np.array(labels, copy=True)
    if labels.ndim != 1 or labels.size == 0:
        raise ValueError(f"labels must be a non-empty 1-D array, got shape {labels.shape}")
    if not np.issubdtype(labels.dtype, np.integer):
        raise ValueError(f"labels must be integers, got dtype {labels.dtype}")
    labels = labels.astype(np.int64)
    n = labels.shape[0]
    t = np.asarray(tets)
    if t.ndim != 2 or t.shape[1] != 4:
        raise ValueError(f"tets must have shape (n_tets, 4), got {t.shape}")
    t = t.astype(np.int64, copy=False)
    if t.size and (t.min() < 0 or t.max() >= n):
        raise ValueError(f"tets index vertices up to {int(t.max())} but labels has {n} entries")
    d = int(labels.max()) + 1 if n_domains is None else int(n_domains)
    if labels.min() < 0 or labels.max() >= d:
        raise ValueError(
            f"labels must lie in [0, n_domains={d}), got [{int(labels.min())}, {int(labels.max())}]"
        )
    if names is None:
        names = [f"domain_{i}" for i in range(d)]
    else:
        names = [str(s) for s in names]
        if len(names) != d:
            raise ValueError(f"names has {len(names)} entries for {d} domains")
    nv = np.bincount(labels, minlength=d)
    if nv.min() == 0:
        empty = [names[i] for i in np.flatnonzero(nv == 0)]
        raise ValueError(f"domains without vertices: {empty}")

    domain_vertices = _split_sorted(np.arange(n, dtype=np.int64), labels, d)

    tl = labels[t]  # (n_tets, 4)
    lo, hi = tl.min(axis=1), tl.max(axis=1)
    inner = lo == hi
    inner_ids = np.flatnonzero(inner).astype(np.int64)
    domain_elements = _split_sorted(inner_ids, lo[inner], d)

    coupling = np.flatnonzero(~inner).astype(np.int64)
    cdom = np.ascontiguousarray(tl[coupling])

    # Every pair of distinct domains a coupling tet touches, once per tet.
    a = cdom[:, _TET_EDGES[:, 0]].ravel()
    b = cdom[:, _TET_EDGES[:, 1]].ravel()
    tet = np.repeat(coupling, _TET_EDGES.shape[0])
    differ = a != b
    i, j, tet = np.minimum(a, b)[differ], np.maximum(a, b)[differ], tet[differ]
    pair = i * d + j
    # Unique (pair, tet) rows, sorted by pair then tet.
    key = np.unique(pair * (t.shape[0] + 1) + tet)
    pair, tet = key // (t.shape[0] + 1), key % (t.shape[0] + 1)
    pairs, starts = np.unique(pair, return_index=True)
    chunks = np.split(tet, starts[1:])
    interfaces: dict[tuple[int, int], np.ndarray] = {}
    for p, chunk in zip(pairs, chunks):  # one iteration per domain-graph edge
        interfaces[(int(p // d), int(p % d))] = _readonly(np.ascontiguousarray(chunk))
    graph_edges = np.stack([pairs // d, pairs % d], axis=1).astype(np.int64).reshape(-1, 2)

    neighbours: list[set[int]] = [set() for _ in range(d)]
    for p, q in graph_edges.tolist():
        neighbours[p].add(q)
        neighbours[q].add(p)

    return Partition(
        labels=_readonly(labels),
        n_domains=d,
        names=names,
        domain_vertices=domain_vertices,
        domain_elements=domain_elements,
        coupling_elements=_readonly(coupling),
        coupling_domains=_readonly(cdom),
        interfaces=interfaces,
        neighbours=neighbours,
        graph_edges=_readonly(graph_edges),
        n_tets=int(t.shape[0]),
    )


# ---------------------------------------------------------------------------
# block elimination order on the domain graph


def _adjacency_sets(n_domains: int, graph_edges) -> list[set[int]]:
    d = int(n_domains)
    if d < 0:
        raise ValueError(f"n_domains must be >= 0, got {n_domains}")
    e = np.asarray(graph_edges, dtype=np.int64).reshape(-1, 2)
    if e.size and (e.min() < 0 or e.max() >= d):
        raise ValueError(f"graph_edges reference domains outside [0, {d})")
    adj: list[set[int]] = [set() for _ in range(d)]
    for p, q in e.tolist():
        if p != q:
            adj[p].add(q)
            adj[q].add(p)
    return adj


def _eliminate(adj: list[set[int]], node: int) -> int:
    """Eliminate ``node``: its neighbours become a clique; return the fill edges added."""
    nb = sorted(adj[node])
    fill = 0
    for a_i, p in enumerate(nb):
        for q in nb[a_i + 1:]:
            if q not in adj[p]:
                adj[p].add(q)
                adj[q].add(p)
                fill += 1
    for p in nb:
        adj[p].discard(node)
    adj[node] = set()
    return fill


def domain_elimination_order(n_domains: int, graph_edges) -> np.ndarray:
    """Order of the domains for block Cholesky with little fill (minimum degree).

    Simulates symbolic elimination on the domain graph: repeatedly eliminate
    the remaining domain with the fewest remaining neighbours (ties: lowest
    id) and connect its neighbours (the fill). On a tree or forest the
    minimum degree is always <= 1, so leaves go first and the fill is zero;
    on general graphs it is the classic greedy heuristic (optimal on a cycle:
    d - 3 fill blocks).

    Args:
        n_domains: d.
        graph_edges: (n_e, 2) domain pairs.
    Returns:
        (d,) int64 permutation: order[k] is the k-th domain to eliminate.
    """
    adj = _adjacency_sets(n_domains, graph_edges)
    d = len(adj)
    alive = set(range(d))
    order = []
    for _ in range(d):
        node = min(alive, key=lambda k: (len(adj[k]), k))
        _eliminate(adj, node)
        alive.remove(node)
        order.append(node)
    return np.array(order, dtype=np.int64)


def block_fill(n_domains: int, graph_edges, order) -> int:
    """Number of fill blocks (new off-diagonal block pairs) eliminating in ``order``.

    The block Cholesky factor then holds d diagonal blocks plus
    len(graph_edges) + fill off-diagonal blocks.

    Raises:
        ValueError: order is not a permutation of range(n_domains).
    """
    adj = _adjacency_sets(n_domains, graph_edges)
    order = np.asarray(order, dtype=np.int64).ravel()
    if order.shape[0] != len(adj) or not np.array_equal(np.sort(order), np.arange(len(adj))):
        raise ValueError(f"order must be a permutation of range({len(adj)}), got {order.tolist()}")
    return int(sum(_eliminate(adj, int(k)) for k in order))


def block_factor_blocks(n_domains: int, graph_edges, order) -> int:
    """Off-diagonal blocks of the block Cholesky factor for ``order`` (edges + fill)."""
    e = np.unique(np.sort(np.asarray(graph_edges, dtype=np.int64).reshape(-1, 2), axis=1), axis=0)
    e = e[e[:, 0] != e[:, 1]]
    return int(e.shape[0]) + block_fill(n_domains, graph_edges, order)


__all__ = [
    "Partition",
    "block_factor_blocks",
    "block_fill",
    "build_partition",
    "domain_elimination_order",
    "imbalance",
    "make_contiguous",
    "partition_from_regions",
    "partition_vertices",
    "vertex_graph",
]


def domain_labels(domains_cfg, vertices, tets, notes=None, poses=None):
    """Vertex labels and domain names of a scene's `model.domains`: {count: N[, seed]},
    {regions: {name: selector}} or {auto: true | {settings}} (reduced/auto_domains.py),
    optionally with `reach` {name: selector} regions that get domains of their own, carved
    out last (scene.model_config puts colliders' reach regions there). Domains left empty
    by the carving are dropped. notes: a list that hears why the domains are where they
    are (auto placement). poses: the scene's training poses for auto placement, a callable
    giving (case labels, displacements (c, n, 3)) (bend_cuts.py), or None.

    Returns (labels (n_verts,) int64, names [str])."""
    dcfg = domains_cfg or {"count": 1}
    if dcfg == "auto":
        dcfg = {"auto": True}
    if not isinstance(dcfg, dict):
        raise SceneError(f"model.domains: expected {{count: N}}, {{regions: ...}} or auto, got {dcfg!r}")
    if "auto" in dcfg:
        from mdss_ros.reduced.auto_domains import auto_domains, auto_settings
        graph = vertex_graph(tets, len(vertices), weights=vertices)
        labels, names, why = auto_domains(vertices, tets, graph, poses=poses, **auto_settings(dcfg["auto"]))
        # Bend cuts across a limb can clip small corners off a band (auto_domains._connected_pieces).
        labels, kept, moved = repair_hinges(tets, labels)
        names = [names[i] for i in kept]
        if moved:
            why.append(f"{moved} vertices of pieces that a cut clipped moved to the neighbouring domain")
        if notes is not None:
            notes.extend(why)
    elif "regions" in dcfg:
        regions = dcfg["regions"]
        labels = partition_from_regions(vertices, tets, regions)
        names = list(regions) if isinstance(regions, dict) else [f"domain_{i}" for i in range(len(regions))]
    else:
        count = dcfg.get("count", 1)
        if not isinstance(count, int) or count < 1:
            raise SceneError(f"model.domains.count: expected an integer >= 1, got {count!r}")
        labels = partition_vertices(vertices, tets, count, seed=int(dcfg.get("seed", 0)))
        labels, kept, moved = repair_hinges(tets, labels)
        names = [f"domain_{i}" for i in range(len(kept))]
        if notes is not None and moved:
            lost = count - len(kept)
            notes.append(f"{moved} vertices moved to a neighbouring domain so that every domain's own elements "
                         f"join through faces (METIS left pieces hinged on an edge or vertex, or too thin to "
                         f"hold an element)"
                         + (f"; {lost} of the {count} requested domains held no element of their own and "
                            f"were merged into their neighbours: {len(kept)} domains" if lost else ""))
    labels = np.asarray(labels, dtype=np.int64).copy()
    names = list(names)
    for name, spec in (dcfg.get("reach") or {}).items():
        where = f"colliders.{name[:-len('_reach')]}.reach" if name.endswith("_reach") else f"model.domains.reach.{name}"
        try:
            ids = select_vertices(vertices, spec)
        except Exception as err:  # noqa: BLE001 - a selector error names the spec
            raise SceneError(f"{where}: {err}") from err
        if len(ids) == 0:
            raise SceneError(f"{where}: the region selects no vertex of the body")
        labels[ids] = len(names)
        names.append(name)
    used = np.unique(labels)
    if len(used) < len(names):
        remap = np.full(len(names), -1, dtype=np.int64)
        remap[used] = np.arange(len(used))
        labels, names = remap[labels], [names[i] for i in used]
    return labels, names
