"""Coupling elements: ordinary elements whose vertices lie in different domains.

Their forces and stiffness are evaluated in the world frame from the world positions of
their vertices (which come from different frames), then mapped to the generalised DOFs
of every domain they touch with the velocity map J (docs/method.md §8-9):

    subspace vertex l of domain i:  xd_l = J_l [qd_i; v_i; w_i],
                                    J_l = [R_i U_l, I3, -[x_l - c_i]x]   (3 x (r_i + 6))
    subspace vertex of a fixed domain: J_l = [U_l]                        (3 x r_i)
    full-space vertex:               J_l = I3 on its own three DOFs.

    generalised force   G += J_l^T f_l             (f_l = dE_e/dx_l)
    generalised tangent A += J_a^T K_e[a, b] J_b    (for every vertex pair a, b of e)

so the reduced force on domain i is sum U_l^T R_i^T f_l, its force sum f_l and its
torque sum (x_l - c_i) x f_l, exactly the F_ij, f_ij, tau_ij of docs/method.md §8. One kernel
serves any element size (tets: 4 vertices; springs of the spring-coupling foil: 2).

Generalised DOFs are split into the subspace part (dense, size S) and the full-space
part (sparse, size F). Vertex pairs that are both full-space go through the full-space
FEM scatter instead of this kernel; a full-subspace pair lands in A_sI, the dense
block between subspace DOFs and the full-space DOFs that touch a coupling element.
"""
import numpy as np
from numba import njit, prange

from ..threads import pick, serial_twin


def skew_batch(p):
    """[p]x for p (n, 3): (n, 3, 3)."""
    z = np.zeros(len(p))
    return np.stack([np.stack([z, -p[:, 2], p[:, 1]], 1),
                     np.stack([p[:, 2], z, -p[:, 0]], 1),
                     np.stack([-p[:, 1], p[:, 0], z], 1)], 1)


@njit(cache=True, parallel=True)
def interface_jacobian(U, r_local, row_dom, r, movable, q, R, c, J, x):
    """J_l and world position of every subspace interface vertex (rows with row_dom < 0,
    full-space vertices, are left to the caller).

    U (n_I, 3, r_max) basis rows, r_local (n_I, 3) rest offsets about the frame origin,
    row_dom (n_I,) subspace domain of each row; per domain r (D,), movable (D,) bool,
    q (D, r_max) modal coordinates, R (D, 3, 3), c (D, 3). J (n_I, 3, s_max) and
    x (n_I, 3) are written: x_l = c + R (r_l + U_l q), J_l = [R U_l, I3, -[x_l - c]x, 0...].
    """
    n_I, _, s_max = J.shape
    for la in prange(n_I):
        k = row_dom[la]
        if k < 0:
            continue
        rk = r[k]
        p0 = r_local[la, 0]
        p1 = r_local[la, 1]
        p2 = r_local[la, 2]
        for t in range(rk):
            qt = q[k, t]
            p0 += U[la, 0, t] * qt
            p1 += U[la, 1, t] * qt
            p2 += U[la, 2, t] * qt
        # d = R p = x - c, kept in scalars: no allocation per vertex in the parallel loop.
        d0 = R[k, 0, 0] * p0 + R[k, 0, 1] * p1 + R[k, 0, 2] * p2
        d1 = R[k, 1, 0] * p0 + R[k, 1, 1] * p1 + R[k, 1, 2] * p2
        d2 = R[k, 2, 0] * p0 + R[k, 2, 1] * p1 + R[k, 2, 2] * p2
        x[la, 0] = c[k, 0] + d0
        x[la, 1] = c[k, 1] + d1
        x[la, 2] = c[k, 2] + d2
        for i in range(3):
            for t in range(rk):
                J[la, i, t] = R[k, i, 0] * U[la, 0, t] + R[k, i, 1] * U[la, 1, t] + R[k, i, 2] * U[la, 2, t]
            for t in range(rk, s_max):
                J[la, i, t] = 0.0
        if movable[k]:
            for i in range(3):
                J[la, i, rk + i] = 1.0
            # -[d]x: rows (0, d2, -d1), (-d2, 0, d0), (d1, -d0, 0)
            J[la, 0, rk + 4] = d2
            J[la, 0, rk + 5] = -d1
            J[la, 1, rk + 3] = -d2
            J[la, 1, rk + 5] = d0
            J[la, 2, rk + 3] = d1
            J[la, 2, rk + 4] = -d0


@njit(cache=True, inline="always")
def _k_times_j(K_e, e, a, b, J, cols, lb, T):
    """T (3, s_max) = K_e[e] block (a, b) times J of vertex lb (padding columns zero)."""
    for i in range(3):
        for t in range(J.shape[2]):
            acc = 0.0
            if cols[lb, t] >= 0:
                for j in range(3):
                    acc += K_e[e, 3 * a + i, 3 * b + j] * J[lb, j, t]
            T[i, t] = acc


@njit(cache=True)
def project_coupling(elem, f_e, K_e, J, cols, is_full, icol, G, A_ss, A_sI):
    """Accumulate J^T f and J^T K J of coupling elements, one element vertex pair at a
    time. The step uses TwoPhaseProjection (+ project_forces and project_coupling_full
    beside full-space domains), which computes the same sums with fewer flops; this
    direct form is the tests' reference for them.

    elem (n_c, k): index of each element vertex in the interface-vertex arrays.
    f_e (n_c, k, 3), K_e (n_c, 3k, 3k): world-frame element forces and stiffness.
    J (n_I, 3, s_max), cols (n_I, s_max): J_l and the generalised column of each of its
      columns (-1 = padding); for full-space vertices J = I3 and cols are their DOFs.
    is_full (n_I,) bool; icol (n_I, 3): column in A_sI of a full-space vertex's DOFs.
    G (S + F,), A_ss (S, S), A_sI (S, F_I): outputs, added to.
    """
    n_c, k = elem.shape
    s_max = J.shape[2]
    T = np.empty((3, s_max))
    for e in range(n_c):
        for a in range(k):
            la = elem[e, a]
            for s in range(s_max):
                c = cols[la, s]
                if c < 0:
                    continue
                acc = 0.0
                for i in range(3):
                    acc += J[la, i, s] * f_e[e, a, i]
                G[c] += acc
            if is_full[la]:
                continue            # rows of full-space DOFs: full-full via FEM, full-sub by symmetry
            for b in range(k):
                lb = elem[e, b]
                _k_times_j(K_e, e, a, b, J, cols, lb, T)
                for s in range(s_max):
                    row = cols[la, s]
                    if row < 0:
                        continue
                    for t in range(s_max):
                        if cols[lb, t] < 0:
                            continue
                        acc = J[la, 0, s] * T[0, t] + J[la, 1, s] * T[1, t] + J[la, 2, s] * T[2, t]
                        if is_full[lb]:
                            A_sI[row, icol[lb, t]] += acc
                        else:
                            A_ss[row, cols[lb, t]] += acc


@njit(cache=True)
def project_coupling_full(elem, K_e, J, cols, is_full, icol, A_sI):
    """A_sI += J_a^T K_e[a, b] for every subspace vertex a and full-space vertex b of a
    coupling element (J_b = I3 on b's own DOFs): the block between subspace DOFs and
    full-space interface DOFs. Arguments as in project_coupling."""
    n_c, k = elem.shape
    s_max = J.shape[2]
    for e in range(n_c):
        for a in range(k):
            la = elem[e, a]
            if is_full[la]:
                continue
            for b in range(k):
                lb = elem[e, b]
                if not is_full[lb]:
                    continue
                for t in range(3):
                    col = icol[lb, t]
                    if col < 0:
                        continue                 # a pinned full-space DOF
                    k0 = K_e[e, 3 * a, 3 * b + t]
                    k1 = K_e[e, 3 * a + 1, 3 * b + t]
                    k2 = K_e[e, 3 * a + 2, 3 * b + t]
                    for s in range(s_max):
                        row = cols[la, s]
                        if row >= 0:
                            A_sI[row, col] += J[la, 0, s] * k0 + J[la, 1, s] * k1 + J[la, 2, s] * k2


@njit(cache=True)
def project_forces(elem, f_e, J, cols, G):
    """Only G += J^T f (for energy-only evaluations and explicit forces)."""
    n_c, k = elem.shape
    s_max = J.shape[2]
    for e in range(n_c):
        for a in range(k):
            la = elem[e, a]
            for s in range(s_max):
                c = cols[la, s]
                if c >= 0:
                    G[c] += J[la, 0, s] * f_e[e, a, 0] + J[la, 1, s] * f_e[e, a, 1] + J[la, 2, s] * f_e[e, a, 2]


def spring_forces(x, springs, rest_length, k_spring, want_hessian=True):
    """Zero-damping springs between vertex pairs: the spring-coupling foil.

    x (n, 3); springs (n_s, 2); rest_length (n_s,); k_spring scalar (N/m).
    E = k/2 (|d| - L)^2 with d = x_b - x_a. Returns energy (n_s,), f (n_s, 2, 3)
    (f = dE/dx) and K (n_s, 6, 6).
    """
    d = x[springs[:, 1]] - x[springs[:, 0]]
    length = np.linalg.norm(d, axis=1)
    n = d / np.maximum(length, 1e-300)[:, None]
    stretch = length - rest_length
    energy = 0.5 * k_spring * stretch ** 2
    fb = (k_spring * stretch)[:, None] * n
    f = np.stack([-fb, fb], axis=1)
    if not want_hessian:
        return energy, f, None
    ratio = np.where(length > 0, stretch / np.maximum(length, 1e-300), 0.0)
    # d^2E/dd^2 = k n n^T + k (1 - L/|d|)(I - n n^T); not PSD when compressed, so clamp
    # the transverse term at zero (the usual spring projection).
    nn = n[:, :, None] * n[:, None, :]
    Kdd = k_spring * (nn + np.maximum(ratio, 0.0)[:, None, None] * (np.eye(3) - nn))
    K = np.zeros((len(springs), 6, 6))
    K[:, :3, :3] = Kdd
    K[:, 3:, 3:] = Kdd
    K[:, :3, 3:] = -Kdd
    K[:, 3:, :3] = -Kdd
    return energy, f, K


@njit(cache=True)
def project_coupling_left(elem, f_e, K_e, JL, J, cols, G, A_ss):
    """Like project_coupling for subspace-only systems, with a per-element left factor:
    G += JL_e^T f_e, A += JL_e^T K_e J_e. JL (n_c, k, 3, s_max) carries non-uniform
    cubature weights (different per row group), which makes A unsymmetric."""
    n_c, k = elem.shape
    s_max = J.shape[2]
    T = np.empty((3, s_max))
    for e in range(n_c):
        for a in range(k):
            la = elem[e, a]
            for s in range(s_max):
                c = cols[la, s]
                if c >= 0:
                    G[c] += JL[e, a, 0, s] * f_e[e, a, 0] + JL[e, a, 1, s] * f_e[e, a, 1] + JL[e, a, 2, s] * f_e[e, a, 2]
            for b in range(k):
                lb = elem[e, b]
                _k_times_j(K_e, e, a, b, J, cols, lb, T)
                for s in range(s_max):
                    row = cols[la, s]
                    if row < 0:
                        continue
                    for t in range(s_max):
                        col = cols[lb, t]
                        if col >= 0:
                            A_ss[row, col] += JL[e, a, 0, s] * T[0, t] + JL[e, a, 1, s] * T[1, t] + JL[e, a, 2, s] * T[2, t]


def vertex_incidence(elem, n_I):
    """CSR lists of the (element, slot) pairs at each interface vertex: (ptr (n_I+1,), inc (n, 2))."""
    flat = elem.ravel()
    order = np.argsort(flat, kind="stable")
    ptr = np.concatenate([[0], np.cumsum(np.bincount(flat, minlength=n_I))]).astype(np.int64)
    inc = np.stack([order // elem.shape[1], order % elem.shape[1]], axis=1).astype(np.int64)
    return ptr, inc


def coupling_entries(elem, vertex_sub):
    """Static data of the two-phase projection: one entry per (vertex a, domain l) pair that
    an element couples, ordered by (domain of a, l, a) so that each domain pair's entries
    are one contiguous block.

    elem (n_c, k) interface-vertex ids; vertex_sub (n_I,) subspace domain of each (-1 for a
    full-space vertex). Returns (entry_vertex (n_e,), entry_dom (n_e,), pair_entry
    (n_c, k, k): the entry of (a, domain of b) for every vertex pair of every element, -1
    where a or b is full-space).
    """
    n_c, k = elem.shape
    n_I = len(vertex_sub)
    if n_c == 0 or vertex_sub.max() < 0:
        z = np.zeros(0, dtype=np.int64)
        return z, z, np.full((n_c, k, k), -1, dtype=np.int64)
    nd = int(vertex_sub.max()) + 1
    a_ids = np.repeat(elem, k, axis=1).ravel()                 # (n_c k k,) vertex a of each pair
    b_dom = vertex_sub[np.tile(elem, (1, k)).ravel()]          # domain of b
    # Pairs with a full-space vertex (vertex_sub < 0) have no entry: see project_coupling_full.
    valid = (vertex_sub[a_ids] >= 0) & (b_dom >= 0)
    pair_key = (vertex_sub[a_ids] * nd + b_dom) * n_I + a_ids
    keys, inverse = np.unique(pair_key[valid], return_inverse=True)
    pair_entry = np.full(len(a_ids), -1, dtype=np.int64)
    pair_entry[valid] = inverse.ravel()
    entry_vertex, entry_dom = keys % n_I, (keys // n_I) % nd
    return entry_vertex.astype(np.int64), entry_dom.astype(np.int64), pair_entry.reshape(n_c, k, k).astype(np.int64)


def neighbour_slots(elem, pair_entry, n_e):
    """Each entry's distinct neighbour vertices: (nb_ptr (n_e + 1,), nb_vertex (n_nb,)) as
    CSR lists, and pair_slot (n_c, k, k), for every element vertex pair (a, b) with an entry,
    the index in nb_vertex of its b (-1 where pair_entry is -1). Built once per coupling set."""
    e_idx, a_idx, b_idx = np.nonzero(pair_entry >= 0)
    ent = pair_entry[e_idx, a_idx, b_idx]
    lb = elem[e_idx, b_idx]
    n_I = int(elem.max()) + 1 if elem.size else 1
    keys, inverse = np.unique(ent * n_I + lb, return_inverse=True)
    nb_ptr = np.concatenate([[0], np.cumsum(np.bincount(keys // n_I, minlength=n_e))]).astype(np.int64)
    pair_slot = np.full(pair_entry.shape, -1, dtype=np.int64)
    pair_slot[e_idx, a_idx, b_idx] = inverse.ravel()
    return nb_ptr, (keys % n_I).astype(np.int64), pair_slot


def entry_terms(pair_entry, pair_slot, nb_ptr):
    """Each entry's element vertex pairs, the terms of its block sums in chunk_products:
    (terms (n_t, 4): element, slot a, slot b and the neighbour slot of b local to the
    entry; term_ptr (n_e + 1,)), in the order (entry, element, b). Why a list: the loop
    it replaces read pair_entry for every b of every element at the entry's vertex and
    skipped those of other domains; the list took chunk_products on armadillo_class from
    3.64 to 3.52 ms on one thread and 2.10 to 1.97 ms on two (medians of 300,
    docs/performance.md "Session 28"). Within an entry the order is that of the vertex's
    incidences (vertex_incidence: ascending element), then b, as that loop summed: the
    same bits."""
    e_idx, a_idx, b_idx = np.nonzero(pair_entry >= 0)
    ent = pair_entry[e_idx, a_idx, b_idx]
    order = np.lexsort((b_idx, e_idx, ent))
    e_idx, a_idx, b_idx, ent = e_idx[order], a_idx[order], b_idx[order], ent[order]
    local = pair_slot[e_idx, a_idx, b_idx] - nb_ptr[ent]
    terms = np.stack([e_idx, a_idx, b_idx, local], axis=1).astype(np.int64)
    n_e = len(nb_ptr) - 1
    term_ptr = np.concatenate([[0], np.cumsum(np.bincount(ent, minlength=n_e))]).astype(np.int64)
    return terms, term_ptr


@njit(cache=True, parallel=True)
def chunk_products(chunks, w, f_e, K_e, J, terms, term_ptr, nb_ptr, nb_vertex, max_nb, ptr, inc,
                   entry_vertex, entry_diag, P, g):
    """Both phases of the projection, one chunk of a domain pair's entries at a time, in
    cache: for each entry en = (a, l) of chunk c, its K J rows
        KJ[en] = sum_b (sum_e w_e K_e[a, b]) J_b
    over its distinct neighbours b in l (nb_vertex[nb_ptr[en]:nb_ptr[en + 1]]) and the
    elements e at a that hold b (3, s_l), and then P[c] = JE_c^T KJ_c (s_k, s_l), the
    chunk's share of A[k, l] (JE_c: the J rows of the chunk's vertices a, all in domain k).
    Where l is a's own domain (entry_diag: each vertex has one such entry) it also adds
    J_a^T f_a to g[c] (s_k,), with f_a = sum of w_e f_e[a] over the elements at a: the
    chunk's share of G on k.

    chunks (n_ch, 4): first and one-past-last entry of each chunk, s_k and s_l (the
    generalised columns of domains k and l; J is zero beyond them); w (n_c,) element
    weights (cubature), f_e (n_c, k, 3), K_e (n_c, 3k, 3k), J (n_I, 3, s_max); terms (n_t,
    4) and term_ptr (n_e + 1,) each entry's element vertex pairs (entry_terms), max_nb the most
    neighbours of an entry; P (n_ch, s_max, s_max) and g (n_ch, s_max) are written on
    [:s_k, :s_l] and [:s_k].

    Why the 3 x 3 blocks are summed per neighbour before they meet J: a vertex pair (a, b)
    is shared by several elements (armadillo_class: 31,770 element pairs, 20,432 distinct;
    octopus 12,107 and 5,844), and each product with J is 18 s_l flops against 9 for a
    block sum: chunk_products went 0.70 -> 0.57 ms on octopus and 2.25 -> 2.07 ms on
    armadillo_class (medians of 300, one BLAS thread; session 22). The sums change order
    (2e-16 of P). Why chunks: the former two passes wrote every entry's K J (4.4 MB on
    armadillo_class) and a copy of its J rows (4.4 MB more), then read both back for one
    GEMM per pair, all out of cache; a chunk's 2 x 3 x 64 rows stay in the core's L2
    between the two phases (and J^T f, a pass over J of its own before, reads the J rows
    copied here). Parallel over chunks, each writing only its own P[c] and g[c], so the
    result does not depend on the thread schedule. Only the domains' own columns are
    formed: an automatic model's arms (r = 6, s = 12) beside a pinned core of 30 modes
    (s_max = 30) were 2.5-6x the work of their own widths."""
    for c in prange(chunks.shape[0]):
        e0, e1, sk, sl = chunks[c, 0], chunks[c, 1], chunks[c, 2], chunks[c, 3]
        n = e1 - e0
        KJ = np.zeros((3 * n, sl))
        JE = np.empty((3 * n, sk))
        Kb = np.empty((max_nb, 9))
        for t in range(sk):
            g[c, t] = 0.0
        for j in range(n):
            en = e0 + j
            la = entry_vertex[en]
            diag = entry_diag[en]
            for i in range(3):
                for t in range(sk):
                    JE[3 * j + i, t] = J[la, i, t]
            nb0, nb1 = nb_ptr[en], nb_ptr[en + 1]
            for u in range(nb1 - nb0):
                for v in range(9):
                    Kb[u, v] = 0.0
            f0 = 0.0
            f1 = 0.0
            f2 = 0.0
            if diag:
                for m in range(ptr[la], ptr[la + 1]):
                    e = inc[m, 0]
                    a = inc[m, 1]
                    we = w[e]
                    f0 += we * f_e[e, a, 0]
                    f1 += we * f_e[e, a, 1]
                    f2 += we * f_e[e, a, 2]
            for m in range(term_ptr[en], term_ptr[en + 1]):
                e = terms[m, 0]
                ra = 3 * terms[m, 1]
                cb = 3 * terms[m, 2]
                u = terms[m, 3]
                we = w[e]
                for ii in range(3):
                    for jj in range(3):
                        Kb[u, 3 * ii + jj] += we * K_e[e, ra + ii, cb + jj]
            r = 3 * j
            for u in range(nb1 - nb0):
                lb = nb_vertex[nb0 + u]
                # One pass along the columns that reads each J value once for all three
                # rows (a loop over rows outside re-read J three times: 1.6x slower,
                # load-bound).
                k00, k01, k02 = Kb[u, 0], Kb[u, 1], Kb[u, 2]
                k10, k11, k12 = Kb[u, 3], Kb[u, 4], Kb[u, 5]
                k20, k21, k22 = Kb[u, 6], Kb[u, 7], Kb[u, 8]
                for t in range(sl):
                    j0 = J[lb, 0, t]
                    j1 = J[lb, 1, t]
                    j2 = J[lb, 2, t]
                    KJ[r, t] += k00 * j0 + k01 * j1 + k02 * j2
                    KJ[r + 1, t] += k10 * j0 + k11 * j1 + k12 * j2
                    KJ[r + 2, t] += k20 * j0 + k21 * j1 + k22 * j2
            if diag:
                for t in range(sk):
                    g[c, t] += JE[r, t] * f0 + JE[r + 1, t] * f1 + JE[r + 2, t] * f2
        Pc = np.dot(JE.T, KJ)
        for s in range(sk):
            for t in range(sl):
                P[c, s, t] = Pc[s, t]


@njit(cache=True, parallel=True)
def sum_chunks(groups, group_chunks, sizes, offsets, P, g, A, G):
    """A[k, l] += sum of the pair's chunk products P[c] (in chunk order), for every domain
    pair k <= l of groups (n_g, 3: k, l, first entry), and A[l, k] += its transpose; on a diagonal pair (k, k)
    also G[k] += sum of its chunks' g[c] (G of length 0: forces not wanted). group_chunks
    (n_g + 1,) the first chunk of each pair. Parallel over pairs, each writing only its own
    blocks (and only pair (k, k) writes G's rows of k)."""
    for q in prange(groups.shape[0]):
        k, l = groups[q, 0], groups[q, 1]
        ok, ol, sk, sl = offsets[k], offsets[l], sizes[k], sizes[l]
        c0, c1 = group_chunks[q], group_chunks[q + 1]
        # Chunk by chunk into V, each P[c] read in order (summing all chunks of one entry
        # first strode through P), then into A.
        V = np.zeros((sk, sl))
        for c in range(c0, c1):
            for s in range(sk):
                for t in range(sl):
                    V[s, t] += P[c, s, t]
        for s in range(sk):
            for t in range(sl):
                A[ok + s, ol + t] += V[s, t]
                if l != k:
                    A[ol + t, ok + s] += V[s, t]
        if l == k and G.shape[0] > 0:
            for t in range(sk):
                v = 0.0
                for c in range(c0, c1):
                    v += g[c, t]
                G[ok + t] += v


chunk_products_serial = serial_twin(chunk_products)
sum_chunks_serial = serial_twin(sum_chunks)
interface_jacobian_serial = serial_twin(interface_jacobian)


class TwoPhaseProjection:
    """G += J^T f and A += J^T K J of coupling elements (subspace-only systems) in two
    phases: per-entry K J and force sums, then one GEMM per domain pair,
    A[k, l] += sum_{a in k} J_a^T (K J)_{a, l}, both run on one chunk of a pair's entries
    at a time (chunk_products, with J^T f), and the chunks summed (sum_chunks). About a
    third of the flops of the per-element-pair product, and the O(n_I s^2) part runs in
    BLAS on contiguous blocks. All of it is compiled: no Python loop over domains or
    domain pairs.

    chunk: entries per chunk. Measured on armadillo_class (7,013 entries, s_max 26, one BLAS
    thread, min of 200): 64 as fast as 32 and 128; against the former two passes over all
    entries, 2.45 against 2.9 ms serial and 1.38 against 1.46 ms on two threads, with 8.8
    MB less of buffers."""

    def __init__(self, elem, vertex_sub, sizes, offsets, chunk=64):
        self.elem = elem
        entry_vertex, entry_dom, pair_entry = coupling_entries(elem, vertex_sub)
        self.ptr, self.inc = vertex_incidence(elem, len(vertex_sub))
        self.sizes = np.asarray(sizes, dtype=np.int64)
        self.offsets = np.asarray(offsets, dtype=np.int64)
        self.row_dom = np.asarray(vertex_sub, dtype=np.int64)
        D = len(sizes)
        # A is symmetric (K_e is, and each element has one weight): only the blocks (k, l)
        # with k <= l are computed, and (l, k) is their transpose. Entries (a, l) of a vertex
        # a in domain k > l are dropped, which saves a quarter of the work on a body whose
        # interface vertices touch one other domain each.
        k_all = self.row_dom[entry_vertex]
        keep = entry_dom >= k_all
        new = np.full(len(entry_vertex) + 1, -1, dtype=np.int64)      # old entry -> new, -1 -> -1
        new[:-1][keep] = np.arange(int(keep.sum()))
        self.pair_entry = new[pair_entry]
        self.entry_vertex, entry_dom = entry_vertex[keep], entry_dom[keep]
        # Entries are ordered by (domain of a, l, a): each domain pair's entries are one run.
        n_e = len(self.entry_vertex)
        k_e = self.row_dom[self.entry_vertex]
        key = k_e * D + entry_dom
        starts = np.flatnonzero(np.r_[True, key[1:] != key[:-1]]) if n_e else np.zeros(0, np.int64)
        self.groups = np.stack([k_e[starts], entry_dom[starts], starts], axis=1).astype(np.int64)
        # Each pair's run cut into chunks of at most `chunk` entries (chunk_products).
        ends = np.append(starts[1:], n_e).astype(np.int64) if n_e else starts
        per_group = -(-(ends - starts) // chunk)
        self.group_chunks = np.r_[0, np.cumsum(per_group)].astype(np.int64)
        first = np.repeat(starts, per_group) + chunk * (np.arange(int(per_group.sum())) -
                                                        np.repeat(self.group_chunks[:-1], per_group))
        self.chunks = np.stack([first, np.minimum(first + chunk, np.repeat(ends, per_group)),
                                np.repeat(self.sizes[self.groups[:, 0]], per_group),
                                np.repeat(self.sizes[self.groups[:, 1]], per_group)], 1).astype(np.int64)
        self.entry_diag = (entry_dom == k_e)
        self.nb_ptr, self.nb_vertex, pair_slot = neighbour_slots(elem, self.pair_entry, n_e)
        self.terms, self.term_ptr = entry_terms(self.pair_entry, pair_slot, self.nb_ptr)
        self.max_nb = int(np.diff(self.nb_ptr).max(initial=0))
        self._buffers = None

    def add(self, f_e, K_e, J, G, A_ss, weights=None):
        """f_e (n_c, k, 3), K_e (n_c, 3k, 3k) world-frame element forces and stiffness,
        J (n_I, 3, s_max), weights (n_c,) or None (all 1); G (S,) and A_ss (S, S) are
        added to (G None: forces not projected). Only subspace-subspace vertex pairs: with
        full-space vertices, project_forces and project_coupling_full do the rest."""
        if weights is None:
            weights = np.ones(len(self.elem))
        n_e, s_max = len(self.entry_vertex), J.shape[2]
        shape = (len(self.chunks), s_max, s_max)
        if self._buffers is None or self._buffers[0].shape != shape:
            self._buffers = (np.empty(shape), np.empty(shape[:2]))
        P, g = self._buffers
        # An entry is its K J rows (about 18 s_max flops for each element vertex pair) and
        # its share of the pair's GEMM (6 s_max^2 flops): octopus (about 1,000 entries,
        # s_max 26) took 0.30 ms in GEMMs on one thread, which its entry count alone did
        # not count as worth two.
        pick(chunk_products, chunk_products_serial, n_e, weight=max(4, s_max ** 2 // 64))(
            self.chunks, weights, f_e, K_e, J, self.terms, self.term_ptr, self.nb_ptr,
            self.nb_vertex, self.max_nb, self.ptr, self.inc, self.entry_vertex, self.entry_diag, P, g)
        pick(sum_chunks, sum_chunks_serial, len(self.chunks), weight=max(1, s_max ** 2 // 64))(
            self.groups, self.group_chunks, self.sizes, self.offsets, P, g, A_ss, np.zeros(0) if G is None else G)
