"""Coupling elements: ordinary elements whose vertices lie in different domains.

Their forces and stiffness are evaluated in the world frame from the world positions of
their vertices (which come from different frames), then mapped to the generalised DOFs
of every domain they touch with the velocity map J (METHOD.md sections 5-6):

    subspace vertex l of domain i:  xd_l = J_l [qd_i; v_i; w_i],
                                    J_l = [R_i U_l, I3, -[x_l - c_i]x]   (3 x (r_i + 6))
    subspace vertex of a fixed domain: J_l = [U_l]                        (3 x r_i)
    full-space vertex:               J_l = I3 on its own three DOFs.

    generalised force   G += J_l^T f_l             (f_l = dE_e/dx_l)
    generalised tangent A += J_a^T K_e[a, b] J_b    (for every vertex pair a, b of e)

so the reduced force on domain i is sum U_l^T R_i^T f_l, its force sum f_l and its
torque sum (x_l - c_i) x f_l, exactly the F_ij, f_ij, tau_ij of section 5. One kernel
serves any element size (tets: 4 vertices; springs of the spring-coupling foil: 2).

Generalised DOFs are split into the subspace part (dense, size S) and the full-space
part (sparse, size F). Vertex pairs that are both full-space go through the full-space
FEM scatter instead of this kernel; a full-subspace pair lands in A_sI, the dense
block between subspace DOFs and the full-space DOFs that touch a coupling element.
"""
import numpy as np
from numba import njit, prange


def skew_batch(p):
    """[p]x for p (n, 3): (n, 3, 3)."""
    z = np.zeros(len(p))
    return np.stack([np.stack([z, -p[:, 2], p[:, 1]], 1),
                     np.stack([p[:, 2], z, -p[:, 0]], 1),
                     np.stack([-p[:, 1], p[:, 0], z], 1)], 1)


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
    """Accumulate J^T f and J^T K J of coupling elements.

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


def vertex_pair_slots(elem, vertex_sub, max_slots=None):
    """Static data of the two-phase projection (subspace-only systems).

    elem (n_c, k) interface-vertex ids; vertex_sub (n_I,) subspace domain of each.
    Returns (slot_dom (n_I, D) domains each vertex couples to, -1 padded;
             pair_slot (n_c, k, k) slot of b's domain in a's list).
    """
    n_c, k = elem.shape
    n_I = len(vertex_sub)
    if n_c == 0:
        return np.full((n_I, 1), -1, dtype=np.int64), np.zeros((0, k, k), dtype=np.int64)
    a_ids = np.repeat(elem, k, axis=1).ravel()                 # (n_c*k*k,) vertex a of each pair
    b_dom = vertex_sub[np.tile(elem, (1, k)).ravel()]          # domain of b
    key = np.unique(a_ids * (vertex_sub.max() + 1) + b_dom)
    va, dom = key // (vertex_sub.max() + 1), key % (vertex_sub.max() + 1)
    counts = np.bincount(va, minlength=n_I)
    D = int(counts.max()) if max_slots is None else max_slots
    start = np.concatenate([[0], np.cumsum(counts)[:-1]])
    rank = np.arange(len(va)) - start[va]
    slot_dom = np.full((n_I, D), -1, dtype=np.int64)
    slot_dom[va, rank] = dom
    pair_slot = np.searchsorted(key, a_ids * (vertex_sub.max() + 1) + b_dom) - start[a_ids]
    return slot_dom, pair_slot.reshape(n_c, k, k).astype(np.int64)


def vertex_incidence(elem, n_I):
    """CSR lists of the (element, slot) pairs at each interface vertex: (ptr (n_I+1,), inc (n, 2))."""
    flat = elem.ravel()
    order = np.argsort(flat, kind="stable")
    ptr = np.concatenate([[0], np.cumsum(np.bincount(flat, minlength=n_I))]).astype(np.int64)
    inc = np.stack([order // elem.shape[1], order % elem.shape[1]], axis=1).astype(np.int64)
    return ptr, inc


@njit(cache=True, parallel=True)
def accumulate_KJ(elem, K_e, J, pair_slot, ptr, inc, KJ):
    """Phase 1: KJ[a, slot] += K_e[a, b] J_b for every vertex pair of every element,
    parallel over interface vertices a (each writes only its own rows).
    KJ (n_I, D, 3, s_max) must be zeroed by the caller."""
    n_I = ptr.shape[0] - 1
    k = elem.shape[1]
    s_max = J.shape[2]
    for la in prange(n_I):
        for m in range(ptr[la], ptr[la + 1]):
            e = inc[m, 0]
            a = inc[m, 1]
            for b in range(k):
                lb = elem[e, b]
                sl = pair_slot[e, a, b]
                for i in range(3):
                    k0 = K_e[e, 3 * a + i, 3 * b]
                    k1 = K_e[e, 3 * a + i, 3 * b + 1]
                    k2 = K_e[e, 3 * a + i, 3 * b + 2]
                    for t in range(s_max):
                        KJ[la, sl, i, t] += k0 * J[lb, 0, t] + k1 * J[lb, 1, t] + k2 * J[lb, 2, t]


class TwoPhaseProjection:
    """J^T K J of coupling elements as per-vertex K J sums, then one GEMM per domain pair:
    A[k, l] += sum_{a in k} J_a^T (K J)_{a, l}. About a third of the flops of the
    per-element-pair product, and the O(n_I s^2) part runs in BLAS."""

    def __init__(self, elem, vertex_sub, sizes, offsets):
        self.elem = elem
        self.slot_dom, self.pair_slot = vertex_pair_slots(elem, vertex_sub)
        self.ptr, self.inc = vertex_incidence(elem, len(vertex_sub))
        self.sizes, self.offsets = sizes, offsets
        self.groups = []                       # (k, l, vertex ids, slot ids)
        n_I, D = self.slot_dom.shape
        va = np.repeat(np.arange(n_I), D)
        sl = np.tile(np.arange(D), n_I)
        dom_l = self.slot_dom.ravel()
        ok = dom_l >= 0
        va, sl, dom_l = va[ok], sl[ok], dom_l[ok]
        dom_k = vertex_sub[va]
        for k, l in np.unique(np.stack([dom_k, dom_l], 1), axis=0):
            sel = (dom_k == k) & (dom_l == l)
            self.groups.append((int(k), int(l), va[sel], sl[sel]))

    def add(self, K_e, J, A_ss):
        n_I, D = self.slot_dom.shape
        KJ = np.zeros((n_I, D, 3, J.shape[2]))
        accumulate_KJ(self.elem, K_e, J, self.pair_slot, self.ptr, self.inc, KJ)
        for k, l, va, sl in self.groups:
            sk, sl_ = self.sizes[k], self.sizes[l]
            Jk = J[va, :, :sk].reshape(-1, sk)
            KJk = KJ[va, sl, :, :sl_].reshape(-1, sl_)
            ok, ol = self.offsets[k], self.offsets[l]
            A_ss[ok:ok + sk, ol:ol + sl_] += Jk.T @ KJk
