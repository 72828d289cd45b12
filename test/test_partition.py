"""Vertex-based domain partition (docs/method.md §5) and the block elimination order."""

import itertools

import numpy as np
import pytest
import scipy.sparse as sp
from scipy.sparse import csgraph

from mdss_ros.errors import SceneError
from mdss_ros.mesh import box
from mdss_ros.reduced.partition import (
    block_factor_blocks,
    block_fill,
    build_partition,
    domain_elimination_order,
    imbalance,
    make_contiguous,
    partition_from_regions,
    partition_vertices,
)

_EDGES = [(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)]


# ---------------------------------------------------------------------------
# helpers (independent of the module under test)


def _adjacency(tets, n):
    e = np.concatenate([tets[:, [a, b]] for a, b in _EDGES])
    g = sp.coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n, n))
    return (g + g.T).tocsr()


def _components_per_domain(tets, labels, d):
    """Number of connected pieces of each domain in the tet-edge graph."""
    g = _adjacency(tets, labels.shape[0])
    out = []
    for k in range(d):
        ids = np.flatnonzero(labels == k)
        out.append(csgraph.connected_components(g[ids][:, ids], directed=False)[0] if ids.size else 0)
    return out


def _plus_body(cell=0.05):
    """Plus-shaped body: a central cube with four arms, conforming structured tets."""
    parts = [
        box((0.3, 0.3, 0.3), cell, origin=(0.0, 0.0, 0.0)),
        box((0.6, 0.3, 0.3), cell, origin=(0.3, 0.0, 0.0)),
        box((0.6, 0.3, 0.3), cell, origin=(-0.6, 0.0, 0.0)),
        box((0.3, 0.6, 0.3), cell, origin=(0.0, 0.3, 0.0)),
        box((0.3, 0.6, 0.3), cell, origin=(0.0, -0.6, 0.0)),
    ]
    offsets = np.cumsum([0] + [p.n_verts for p in parts])
    x = np.concatenate([p.vertices for p in parts])
    t = np.concatenate([p.tets + o for p, o in zip(parts, offsets)])
    # Every box uses the same global Kuhn diagonal, so merging coincident
    # grid nodes gives a conforming mesh.
    keys = np.round(x / cell).astype(np.int64)
    _, first, inverse = np.unique(keys, axis=0, return_index=True, return_inverse=True)
    return x[first], inverse.ravel()[t]


@pytest.fixture(scope="module")
def beam():
    return box(size=(1.0, 0.1, 0.1), cell=0.025)


# ---------------------------------------------------------------------------
# automatic partition


def test_beam_split_in_four(beam):
    labels = partition_vertices(beam.vertices, beam.tets, 4)
    assert labels.dtype == np.int64 and labels.shape == (beam.n_verts,)
    assert labels.min() == 0 and labels.max() == 3
    assert _components_per_domain(beam.tets, labels, 4) == [1, 1, 1, 1]
    assert imbalance(labels) < 0.10

    p = build_partition(beam.tets, labels)
    assert p.n_domains == 4 and p.names == [f"domain_{i}" for i in range(4)]
    # X_i: sorted, disjoint, covering.
    allv = np.concatenate(p.domain_vertices)
    assert np.array_equal(np.sort(allv), np.arange(beam.n_verts))
    for k, xv in enumerate(p.domain_vertices):
        assert xv.size > 0 and np.all(np.diff(xv) > 0) and np.all(labels[xv] == k)
    # The E_i and the coupling elements partition the tets.
    alle = np.concatenate(p.domain_elements + [p.coupling_elements])
    assert alle.size == beam.n_tets
    assert np.array_equal(np.sort(alle), np.arange(beam.n_tets))
    for k, e in enumerate(p.domain_elements):
        assert np.all(labels[beam.tets[e]] == k)
    # Coupling tets touch >= 2 domains; coupling_domains are their vertex labels.
    assert np.array_equal(p.coupling_domains, labels[beam.tets[p.coupling_elements]])
    assert np.all(p.n_domains_touched() >= 2)
    # A beam cut in 4 along its axis: the domain graph is a path.
    assert p.graph_edges.shape == (3, 2)
    deg = sorted(len(s) for s in p.neighbours)
    assert deg == [1, 1, 2, 2]
    assert set(p.interfaces) == {tuple(e) for e in p.graph_edges.tolist()}
    # Each coupling tet is in exactly the interfaces of the pairs it touches.
    member = {}
    for key, tets in p.interfaces.items():
        assert np.all(np.diff(tets) > 0)
        for t in tets.tolist():
            member.setdefault(t, set()).add(key)
    for t, dom in zip(p.coupling_elements.tolist(), p.coupling_domains):
        assert member[t] == set(itertools.combinations(sorted(set(dom.tolist())), 2))
    assert len(member) == p.coupling_elements.size

    s = p.summary()
    assert sum(s["domain_vertex_counts"]) == beam.n_verts
    assert sum(s["domain_element_counts"]) + s["n_coupling"] == beam.n_tets
    assert s["imbalance"] == pytest.approx(imbalance(labels))
    text = p.format_summary()
    assert "4 domains" in text and "domain_3" in text and len(text.splitlines()) >= 9


def test_beam_path_elimination(beam):
    p = build_partition(beam.tets, partition_vertices(beam.vertices, beam.tets, 4))
    order = domain_elimination_order(p.n_domains, p.graph_edges)
    assert sorted(order.tolist()) == [0, 1, 2, 3]
    assert block_fill(p.n_domains, p.graph_edges, order) == 0
    assert block_factor_blocks(p.n_domains, p.graph_edges, order) == 3
    middle = [k for k in range(4) if len(p.neighbours[k]) == 2][0]
    bad = [middle] + [k for k in range(4) if k != middle]
    assert block_fill(p.n_domains, p.graph_edges, bad) > 0


def test_count_one_and_invalid_count(beam):
    assert np.array_equal(partition_vertices(beam.vertices, beam.tets, 1), np.zeros(beam.n_verts))
    for bad in (0, -1, beam.n_verts + 1):
        with pytest.raises(ValueError, match="count"):
            partition_vertices(beam.vertices, beam.tets, bad)
    with pytest.raises(ValueError, match="count"):
        partition_vertices(beam.vertices, beam.tets, 2.5)


def test_deterministic(beam):
    a = partition_vertices(beam.vertices, beam.tets, 5, seed=3)
    b = partition_vertices(beam.vertices, beam.tets, 5, seed=3)
    assert np.array_equal(a, b)
    x, t = _plus_body()
    assert np.array_equal(partition_vertices(x, t, 7), partition_vertices(x, t, 7))


def test_plus_body_five_contiguous_domains():
    x, t = _plus_body()
    labels = partition_vertices(x, t, 5)
    assert _components_per_domain(t, labels, 5) == [1] * 5
    assert imbalance(labels) < 0.10
    p = build_partition(t, labels)
    assert min(len(v) for v in p.domain_vertices) > 0
    order = domain_elimination_order(p.n_domains, p.graph_edges)
    assert block_fill(p.n_domains, p.graph_edges, order) <= block_fill(
        p.n_domains, p.graph_edges, np.arange(p.n_domains)
    )


def test_many_domains_all_used_and_contiguous():
    m = box((1.0, 1.0, 1.0), 1.0)  # one hex: 8 vertices
    for count in (7, 8):
        labels = partition_vertices(m.vertices, m.tets, count)
        assert np.array_equal(np.unique(labels), np.arange(count))
        assert _components_per_domain(m.tets, labels, count) == [1] * count


def test_make_contiguous_repairs_stripes(beam):
    x = beam.vertices[:, 0]
    stripe = np.minimum((x / 0.2).astype(np.int64), 4)
    labels = stripe % 2  # domains 0 and 1 in alternating stripes: 3 + 2 pieces
    assert _components_per_domain(beam.tets, labels, 2) == [3, 2]
    fixed = make_contiguous(beam.tets, labels, 2)
    assert _components_per_domain(beam.tets, fixed, 2) == [1, 1]
    # Domain 0 keeps one of its pieces untouched.
    assert np.any([np.all(fixed[stripe == s] == 0) for s in (0, 2, 4)])


# ---------------------------------------------------------------------------
# partition from regions


def test_regions_two_halves(beam):
    regions = {
        "left": {"box": [[-1, -1, -1], [0.5, 1, 1]]},
        "right": {"box": [[0.5, -1, -1], [2, 1, 1]]},
    }
    labels = partition_from_regions(beam.vertices, beam.tets, regions)
    x = beam.vertices[:, 0]
    # Vertices on the plane x = 0.5 are in both regions: the first one wins.
    assert x[labels == 0].max() == pytest.approx(0.5)
    assert x[labels == 1].min() == pytest.approx(0.525)
    assert np.array_equal(labels, (x > 0.5 + 1e-9).astype(np.int64))
    p = build_partition(beam.tets, labels, names=list(regions))
    assert p.names == ["left", "right"]
    assert p.graph_edges.tolist() == [[0, 1]]
    # Coupling tets straddle the plane: they span x in [0.5, 0.525].
    cx = x[beam.tets[p.coupling_elements]]
    assert np.allclose(cx.min(axis=1), 0.5) and np.allclose(cx.max(axis=1), 0.525)

    swapped = partition_from_regions(beam.vertices, beam.tets, [regions["right"], regions["left"]])
    assert x[swapped == 0].min() == pytest.approx(0.5)


def test_regions_gap_goes_to_nearer_region(beam):
    regions = [{"box": [[-1, -1, -1], [0.3, 1, 1]]}, {"box": [[0.6, -1, -1], [2, 1, 1]]}]
    labels = partition_from_regions(beam.vertices, beam.tets, regions)
    x = beam.vertices[:, 0]
    assert np.all(labels[x <= 0.3] == 0) and np.all(labels[x >= 0.6] == 1)
    clear = np.abs(x - 0.45) > 1e-6
    assert np.array_equal(labels[clear], (x[clear] > 0.45).astype(np.int64))
    assert _components_per_domain(beam.tets, labels, 2) == [1, 1]
    with pytest.raises(SceneError, match="no region"):
        partition_from_regions(beam.vertices, beam.tets, regions, fill=None)


def test_regions_errors_name_the_region(beam):
    with pytest.raises(SceneError, match="'nowhere'"):
        partition_from_regions(
            beam.vertices,
            beam.tets,
            {"all": {"all": True}, "nowhere": {"box": [[5, 5, 5], [6, 6, 6]]}},
        )
    with pytest.raises(SceneError, match=r"regions\[1\]"):
        partition_from_regions(beam.vertices, beam.tets, [{"all": True}, {"sphere": {"radius": 1}}])
    with pytest.raises(SceneError, match="'shadowed'.*already claimed"):
        partition_from_regions(
            beam.vertices,
            beam.tets,
            {"all": {"all": True}, "shadowed": {"box": [[0, 0, 0], [0.2, 1, 1]]}},
        )
    with pytest.raises(SceneError, match="empty"):
        partition_from_regions(beam.vertices, beam.tets, [])


# ---------------------------------------------------------------------------
# tets touching three or four domains


def test_tets_touching_three_domains_are_kept():
    m = box((1.0, 1.0, 1.0), 0.25)
    x, y = m.vertices[:, 0], m.vertices[:, 1]
    labels = np.where(x < 0.5, 0, np.where(y < 0.5, 1, 2)).astype(np.int64)
    p = build_partition(m.tets, labels)
    touched = p.n_domains_touched()
    multi = p.coupling_elements[touched == 3]
    assert multi.size > 0 and p.summary()["n_coupling_multi"] == multi.size
    for row in p.coupling_domains[touched == 3]:
        assert sorted(set(row.tolist())) == [0, 1, 2]
    for pair in [(0, 1), (0, 2), (1, 2)]:
        assert np.all(np.isin(multi, p.interfaces[pair]))
    alle = np.concatenate(p.domain_elements + [p.coupling_elements])
    assert np.array_equal(np.sort(alle), np.arange(m.n_tets))


def test_single_tet_touching_four_domains():
    tets = np.array([[0, 1, 2, 3]])
    p = build_partition(tets, np.array([2, 0, 3, 1]), names=list("abcd"))
    assert p.coupling_elements.tolist() == [0]
    assert p.coupling_domains.tolist() == [[2, 0, 3, 1]]
    assert all(e.size == 0 for e in p.domain_elements)
    assert p.graph_edges.tolist() == [list(c) for c in itertools.combinations(range(4), 2)]
    assert all(p.interfaces[c].tolist() == [0] for c in itertools.combinations(range(4), 2))
    assert p.neighbours == [{1, 2, 3}, {0, 2, 3}, {0, 1, 3}, {0, 1, 2}]
    assert p.summary()["n_coupling_multi"] == 1


def test_build_partition_validation():
    tets = np.array([[0, 1, 2, 3]])
    with pytest.raises(ValueError, match="domain_2"):
        build_partition(tets, np.array([0, 0, 1, 1]), n_domains=3)
    with pytest.raises(ValueError, match="names"):
        build_partition(tets, np.array([0, 0, 1, 1]), names=["a"])
    with pytest.raises(ValueError, match="labels"):
        build_partition(tets, np.array([0, 0, 1, 5]), n_domains=2)
    p = build_partition(tets, np.array([0, 0, 1, 1]))
    with pytest.raises(ValueError):
        p.labels[0] = 1  # read-only


# ---------------------------------------------------------------------------
# elimination order on the domain graph


def _brute_force_min_fill(d, edges):
    return min(block_fill(d, edges, perm) for perm in itertools.permutations(range(d)))


def test_trees_and_forests_eliminate_without_fill():
    rng = np.random.default_rng(0)
    for d in (1, 2, 5, 20, 40):
        parent = [int(rng.integers(0, i)) for i in range(1, d)]
        edges = np.array([[p, i] for i, p in enumerate(parent, start=1)]).reshape(-1, 2)
        forest = edges[rng.random(len(edges)) > 0.3]
        for e in (edges, forest):
            order = domain_elimination_order(d, e)
            assert sorted(order.tolist()) == list(range(d))
            assert block_fill(d, e, order) == 0
    # A star eliminated centre first fills the whole leaf clique.
    star = np.array([[0, k] for k in range(1, 6)])
    assert block_fill(6, star, [0, 1, 2, 3, 4, 5]) == 10
    assert domain_elimination_order(6, star)[-2:].tolist().count(0) == 1


def test_ring_of_six_min_degree_is_optimal():
    ring = np.array([[k, (k + 1) % 6] for k in range(6)])
    best = _brute_force_min_fill(6, ring)
    assert best == 3  # a minimal triangulation of a 6-cycle has 3 chords
    assert block_fill(6, ring, domain_elimination_order(6, ring)) == best


def test_min_degree_beats_bad_order_on_ring_with_pendants():
    # 4-ring 0-1-2-3 with leaves 4 (on 0) and 5 (on 2).
    edges = np.array([[0, 1], [1, 2], [2, 3], [3, 0], [0, 4], [2, 5]])
    best = _brute_force_min_fill(6, edges)
    order = domain_elimination_order(6, edges)
    assert best == 1 and block_fill(6, edges, order) == best
    # Identity: eliminating 0 joins {1, 3, 4} (3 fill), then 1 joins {2, 3, 4}
    # (+ 2-4), then 2 joins {3, 4, 5} (+ 3-5, 4-5): 6 fill blocks.
    assert block_fill(6, edges, [0, 1, 2, 3, 4, 5]) == 6


def test_block_fill_rejects_non_permutation():
    with pytest.raises(ValueError, match="permutation"):
        block_fill(3, [[0, 1]], [0, 0, 1])


def test_empty_domain_gets_a_vertex_without_breaking_its_donor(beam):
    from mdss_ros.reduced.partition import _fill_empty_domains, vertex_graph

    labels = (beam.vertices[:, 0] > 0.5).astype(np.int64)  # domain 2 empty
    filled = _fill_empty_domains(vertex_graph(beam.tets, beam.n_verts), labels, 3)
    assert np.bincount(filled, minlength=3)[2] == 1
    assert np.count_nonzero(filled != labels) == 1
    assert _components_per_domain(beam.tets, filled, 3) == [1, 1, 1]


# ---------------------------------------------------------------------------
# any mesh a user brings: no hinged or empty domain at any count


def _face_pieces_per_domain(tets, labels):
    """{domain: number of face-connected pieces of its own elements} (0: no element)."""
    from mdss_ros.reduced.partition import tet_face_pairs
    t = np.asarray(tets)
    lab = labels[t]
    own = np.all(lab == lab[:, :1], axis=1)
    out = {}
    pairs = tet_face_pairs(t)
    for k in np.unique(labels):
        ids = np.flatnonzero(own & (lab[:, 0] == k))
        if not len(ids):
            out[int(k)] = 0
            continue
        pos = np.full(len(t), -1)
        pos[ids] = np.arange(len(ids))
        p = pairs[(pos[pairs[:, 0]] >= 0) & (pos[pairs[:, 1]] >= 0)]
        g = sp.coo_matrix((np.ones(len(p)), (pos[p[:, 0]], pos[p[:, 1]])), shape=(len(ids), len(ids)))
        out[int(k)] = csgraph.connected_components(g, directed=False)[0]
    return out


def _thin_bodies(tmp_path):
    import trimesh
    from mdss_ros.mesh import load_mesh, sheet
    trimesh.creation.torus(major_radius=0.05, minor_radius=0.012, major_sections=40,
                           minor_sections=12).export(tmp_path / "torus.obj")
    yield "torus", load_mesh(tmp_path / "torus.obj", edge_length=0.014)
    yield "sheet", sheet(size=[0.3, 0.2], thickness=0.004, cell=0.05)
    from mdss_ros import load_scene
    from mdss_ros.body import build_body
    for name in ("star_limbs", "octopus"):
        yield name, build_body(load_scene(name))


def test_automatic_domains_are_never_hinged_or_empty_on_thin_bodies(tmp_path, monkeypatch):
    """METIS on a torus and a one-tet-thick sheet leaves domains whose own elements touch
    only along an edge, or that hold none (measured before the repair: torus 4 and sheet 52
    such domains over counts 1-16); repair_hinges joins them, and says what it changed."""
    monkeypatch.chdir(tmp_path)
    from mdss_ros.reduced.partition import domain_labels
    said = []
    for name, mesh in _thin_bodies(tmp_path):
        for count in range(1, 17):
            notes = []
            labels, names = domain_labels({"count": count}, mesh.vertices, mesh.tets, notes)
            pieces = _face_pieces_per_domain(mesh.tets, labels)
            assert set(pieces.values()) == {1}, (name, count, pieces)
            assert len(names) == len(pieces) <= count
            if len(names) < count:
                assert notes and f"of the {count} requested domains held no element" in notes[0], notes
            said += notes
    assert said                                    # the sheet needed it, and it was said
