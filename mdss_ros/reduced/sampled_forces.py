"""Reduced internal forces of a subspace domain from weighted element samples.

    g(q) = sum_s w_s V_s G_s^T vec(P(F_s)),        K(q) = sum_s w_s V_s G_s^T C_s G_s
    vec(F_s) = vec(I) + G_s q,                      C_s = dP/dF at F_s

For a linear tet in the domain frame, F is affine in q: G_s = d vec(F)/dq (9 x r) is
constant, so it is precomputed (An, Kim and James 2008; docs/method.md §13.1).
A step evaluates P and dP/dF at the samples only (numba, no allocation in the loop) and
forms K as one GEMM over the stacked samples. With every element a sample of weight 1
this is exactly the domain's full reduced force and stiffness.

Flattening is row-major (vec(F)[3 i + j] = F[i, j]), as in mdss_ros.fem.materials.
"""
from dataclasses import dataclass

import numpy as np
from numba import njit, prange

from ..fem.material_kernels import WORK_LEN, material_point_ws
from ..threads import pick, serial_twin
from .measure import count_not_positive, inverted_samples
# numba's cache=True keys a cached kernel on its own file only: the kernels here inline
# material_point_ws, so a change to material_kernels.py must come with an edit of this file
# (or a cleared NUMBA_CACHE_DIR). Last material change: StVK's and corotated's scratch views made only
# where used (session 20), same bits as before.


def sample_jacobians(U3, tets, grads):
    """G_s = d vec(F_s)/dq for samples: (s, 9, r).

    U3 (n_i, 3, r) per-vertex basis rows; tets (s, 4) local vertex ids; grads (s, 4, 3).
    G[3 i + j, b] = sum_a U3[v_a, i, b] g_a[j].
    """
    G = np.einsum("saib,saj->sijb", U3[tets], grads)
    return np.ascontiguousarray(G.reshape(len(tets), 9, U3.shape[2]))


_CHUNK = 64


@njit(cache=True, inline="always")
def _deformation_gradient(G_s, q, F):
    """F = I + unvec(G_s q) for one sample: G_s (9, r), q (r,), F (3, 3) written.

    Nine running sums side by side, the modes outermost, rather than nine chains of r
    dependent additions one after another (numba keeps the order of a float sum). Each
    entry's sum keeps its order: the same bits. It did not measure faster: forming F is
    0.18 ms of octopus's 0.93 ms no-Hessian pass on one thread (session 20), and the
    kernel's time did not change with this form."""
    f0, f1, f2, f3, f4, f5, f6, f7, f8 = 1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0
    for b in range(G_s.shape[1]):
        qb = q[b]
        f0 += G_s[0, b] * qb
        f1 += G_s[1, b] * qb
        f2 += G_s[2, b] * qb
        f3 += G_s[3, b] * qb
        f4 += G_s[4, b] * qb
        f5 += G_s[5, b] * qb
        f6 += G_s[6, b] * qb
        f7 += G_s[7, b] * qb
        f8 += G_s[8, b] * qb
    F[0, 0], F[0, 1], F[0, 2] = f0, f1, f2
    F[1, 0], F[1, 1], F[1, 2] = f3, f4, f5
    F[2, 0], F[2, 1], F[2, 2] = f6, f7, f8


@njit(cache=True, parallel=True)
def sampled_kernel(G, wV, q, kind_id, params, want_hessian, project, energy_out, g_out, WG_out, CG_out):
    """Per-sample energy, reduced force and the two factors of the reduced stiffness.

    G (s, 9, r); wV (s,) weight times rest volume; q (r,); project: clamp each sample's
    dP/dF to positive semi-definite (the reduced step passes False).
    energy_out (s,), g_out (s, r), WG_out, CG_out (s, 9, r): K = sum_s WG_s^T CG_s.

    The flags are arguments from Python, never literals in njit code: numba compiles a
    separate copy of material_point_ws (every material inlined) for each literal flag
    combination, and three copies made a fresh install's first scene compile for ~3x longer.
    """
    s_count, _, r = G.shape
    n_chunks = (s_count + _CHUNK - 1) // _CHUNK
    for c in prange(n_chunks):
        F = np.empty((3, 3))
        P = np.empty((3, 3))
        C = np.empty((9, 9))
        work = np.empty(WORK_LEN)
        for s in range(c * _CHUNK, min(s_count, (c + 1) * _CHUNK)):
            _deformation_gradient(G[s], q, F)
            psi = material_point_ws(kind_id, F, params, P, C, want_hessian, project, work)
            w = wV[s]
            energy_out[s] = w * psi
            for b in range(r):
                acc = 0.0
                for a in range(9):
                    acc += G[s, a, b] * P[a // 3, a % 3]
                g_out[s, b] = w * acc
            if want_hessian:
                for a in range(9):
                    for b in range(r):
                        acc = 0.0
                        for k in range(9):
                            acc += C[a, k] * G[s, k, b]
                        CG_out[s, a, b] = acc
                        WG_out[s, a, b] = w * G[s, a, b]


@dataclass
class SampledDomainForces:
    """A domain's reduced force model on weighted samples.

    elements: (s,) domain-local element ids of the samples; weights (s,); G (s, 9, r);
    volume (s,); material.
    """

    elements: np.ndarray
    weights: np.ndarray
    G: np.ndarray
    volume: np.ndarray
    material: object

    @classmethod
    def build(cls, U3, tets, grads, volume, material, elements=None, weights=None):
        """tets (m, 4) local ids, grads (m, 4, 3), volume (m,) of ALL domain elements;
        elements/weights select the samples (default: every element, weight 1)."""
        if elements is None:
            elements = np.arange(len(tets))
        elements = np.asarray(elements, dtype=np.int64)
        weights = np.ones(len(elements)) if weights is None else np.asarray(weights, dtype=np.float64)
        G = sample_jacobians(U3, tets[elements], grads[elements])
        return cls(elements, weights, G, volume[elements].copy(), material)

    @property
    def n_samples(self):
        return len(self.elements)

    def evaluate(self, q, want_hessian=True):
        """(energy, g (r,), K (r, r) or None) at reduced coordinates q (r,)."""
        s, _, r = self.G.shape
        e = np.empty(s)
        g = np.empty((s, r))
        WG = np.empty((s, 9, r)) if want_hessian else np.empty((1, 9, r))
        CG = np.empty((s, 9, r)) if want_hessian else np.empty((1, 9, r))
        sampled_kernel(self.G, self.weights * self.volume, np.ascontiguousarray(q, dtype=np.float64),
                       self.material.kind_id, self.material.params, bool(want_hessian), False, e, g, WG, CG)
        if not want_hessian:
            return float(e.sum()), g.sum(0), None
        K = WG.reshape(-1, r).T @ CG.reshape(-1, r)
        return float(e.sum()), g.sum(0), K


@njit(cache=True, parallel=True)
def contributions(G, volume, Q, kind_id, params, want_hessian, project, out):
    """Per-element reduced force at many poses, for cubature training.

    G (m, 9, r); volume (m,); Q (T, r) training poses; want_hessian, project: pass False
    (arguments, not literals, for the reason in sampled_kernel). out (T, r, m): column e of
    the (T r) x m matrix whose weighted column sum is the reduced force at every pose.
    """
    m, _, r = G.shape
    T = Q.shape[0]
    n_chunks = (m + _CHUNK - 1) // _CHUNK
    for c in prange(n_chunks):
        F = np.empty((3, 3))
        P = np.empty((3, 3))
        C = np.empty((9, 9))
        work = np.empty(WORK_LEN)
        for e in range(c * _CHUNK, min(m, (c + 1) * _CHUNK)):
            for t in range(T):
                _deformation_gradient(G[e], Q[t], F)
                material_point_ws(kind_id, F, params, P, C, want_hessian, project, work)
                for b in range(r):
                    acc = 0.0
                    for a in range(9):
                        acc += G[e, a, b] * P[a // 3, a % 3]
                    out[t, b, e] = volume[e] * acc


@njit(cache=True, parallel=True)
def stacked_kernel(G, wV, q, kind_id, params, want_hessian, project, energy_out, g_out, CG_out, det_out):
    """sampled_kernel for every domain in one pass: samples stacked per domain and padded
    with zero-weight samples (a padded sample is skipped and its outputs are zero).

    G (D, s, 9, r_max); wV (D, s); q (D, r_max); energy_out (D, s); g_out (D, s, r_max);
    det_out (D, s): det F of each sample (1 for a skipped one), which the stability guard
    counts inverted samples from without forming F again;
    CG_out (D, s, 9, r_max) = w C_s G_s: domain k's K = sum_s G[k, s]^T CG[k, s]. The
    weight rides on C G so that the GEMM's left factor is G itself: a second (D, s, 9,
    r_max) array w G, written every step, was 3 MB of stores on armadillo_class.
    """
    D, s_count, _, r = G.shape
    n_chunks_d = (s_count + _CHUNK - 1) // _CHUNK
    for job in prange(D * n_chunks_d):
        d = job // n_chunks_d
        c = job % n_chunks_d
        F = np.empty((3, 3))
        P = np.empty((3, 3))
        C = np.empty((9, 9))
        work = np.empty(WORK_LEN)
        for s in range(c * _CHUNK, min(s_count, (c + 1) * _CHUNK)):
            w = wV[d, s]
            if w == 0.0:
                energy_out[d, s] = 0.0
                det_out[d, s] = 1.0
                for b in range(r):
                    g_out[d, s, b] = 0.0
                if want_hessian:
                    for a in range(9):
                        for b in range(r):
                            CG_out[d, s, a, b] = 0.0
                continue
            _deformation_gradient(G[d, s], q[d], F)
            det_out[d, s] = (F[0, 0] * (F[1, 1] * F[2, 2] - F[1, 2] * F[2, 1])
                             - F[0, 1] * (F[1, 0] * F[2, 2] - F[1, 2] * F[2, 0])
                             + F[0, 2] * (F[1, 0] * F[2, 1] - F[1, 1] * F[2, 0]))
            psi = material_point_ws(kind_id, F, params, P, C, want_hessian, project, work)
            energy_out[d, s] = w * psi
            # The innermost loop runs along the modes (contiguous rows of G) and sums the 9
            # entries of F in registers, unrolled: it vectorises, and writes each output
            # once. Accumulating in the output row, one entry of F after another, made 9
            # passes of loads and stores over it (CG: 1.76 -> 1.18 ms on octopus's 2,364
            # samples, one thread, session 20); a sum over the 9 entries per mode as a
            # loop did not vectorise. The sums keep their order: the same bits.
            p0, p1, p2 = P[0, 0], P[0, 1], P[0, 2]
            p3, p4, p5 = P[1, 0], P[1, 1], P[1, 2]
            p6, p7, p8 = P[2, 0], P[2, 1], P[2, 2]
            for b in range(r):
                acc = 0.0 + G[d, s, 0, b] * p0
                acc += G[d, s, 1, b] * p1
                acc += G[d, s, 2, b] * p2
                acc += G[d, s, 3, b] * p3
                acc += G[d, s, 4, b] * p4
                acc += G[d, s, 5, b] * p5
                acc += G[d, s, 6, b] * p6
                acc += G[d, s, 7, b] * p7
                acc += G[d, s, 8, b] * p8
                g_out[d, s, b] = w * acc
            if want_hessian:
                for a in range(9):
                    c0, c1, c2 = w * C[a, 0], w * C[a, 1], w * C[a, 2]
                    c3, c4, c5 = w * C[a, 3], w * C[a, 4], w * C[a, 5]
                    c6, c7, c8 = w * C[a, 6], w * C[a, 7], w * C[a, 8]
                    for b in range(r):
                        acc = 0.0 + c0 * G[d, s, 0, b]
                        acc += c1 * G[d, s, 1, b]
                        acc += c2 * G[d, s, 2, b]
                        acc += c3 * G[d, s, 3, b]
                        acc += c4 * G[d, s, 4, b]
                        acc += c5 * G[d, s, 5, b]
                        acc += c6 * G[d, s, 6, b]
                        acc += c7 * G[d, s, 7, b]
                        acc += c8 * G[d, s, 8, b]
                        CG_out[d, s, a, b] = acc


stacked_kernel_serial = serial_twin(stacked_kernel)


@njit(cache=True)
def sum_samples(g, out):
    """out[d] = sum_s g[d, s] for g (D, s, r), out (D, r) written: the samples' forces
    summed per domain, s = 0, 1, ... in turn, as numpy's g.sum(1) adds them (the same bits).
    numpy's strided reduction took 38 us on star_limbs at 11 domains (11 x 150 x 12) and 76
    on octopus's 17 x 150 x 20, this loop 6 and 14 (session 22)."""
    D, s_count, r = g.shape
    for d in range(D):
        for t in range(r):
            out[d, t] = g[d, 0, t]
        for k in range(1, s_count):
            for t in range(r):
                out[d, t] += g[d, k, t]


@njit(cache=True, parallel=True)
def stacked_stiffness(G, CG, K):
    """K[d] = G[d]^T CG[d] for every domain d, one GEMM each, the domains over the threads.

    G, CG (D, s 9, r) contiguous; K (D, r, r) written. The step runs BLAS on one thread
    (threads.py), so numpy's batched matmul did the domains one after another: on
    octopus (17 domains, 147 samples, r = 20) 0.53 ms, and 0.30 ms so, with the same
    bits (both call dgemm per domain; session 20)."""
    for d in prange(G.shape[0]):
        K[d] = np.dot(G[d].T, CG[d])


stacked_stiffness_serial = serial_twin(stacked_stiffness)


class SampleStack:
    """Cubature samples of domains with the same mode count in one array, for one kernel
    call and one batched GEMM per evaluation.

    G (D, s_max, 9, r) and wV (D, s_max) (weight times rest volume), padded with
    zero-weight samples; the buffers are reused from step to step.
    """

    def __init__(self, sampled, r, material):
        D = len(sampled)
        s_max = max([sm.n_samples for sm in sampled] + [1])
        self.G = np.zeros((D, s_max, 9, r))
        self.wV = np.zeros((D, s_max))
        self.valid = np.zeros((D, s_max), dtype=bool)
        for k, sm in enumerate(sampled):             # once per build
            n, _, rk = sm.G.shape
            self.G[k, :n, :, :rk] = sm.G
            self.wV[k, :n] = sm.weights * sm.volume
            self.valid[k, :n] = True
        self.material = material
        self.energy = np.empty((D, s_max))
        self.g = np.empty((D, s_max, r))
        self.CG = np.empty((D, s_max, 9, r))
        self.det = np.ones((D, s_max))

    def evaluate(self, q, want_hessian=True):
        """(energy (D,), g (D, r), K (D, r, r) or None) at q (D, r) (contiguous)."""
        D, s, _, r = self.G.shape
        m = self.material
        CG = self.CG if want_hessian else np.empty((D, 1, 9, r))
        pick(stacked_kernel, stacked_kernel_serial, D * s, weight=4)(
            self.G, self.wV, q, m.kind_id, m.params, bool(want_hessian), False,
            self.energy, self.g, CG, self.det)
        energy, g = self.energy.sum(1), np.empty((D, r))
        sum_samples(self.g, g)
        if not want_hessian:
            return energy, g, None
        K = np.empty((D, r, r))
        # A sample's share of the GEMM is 18 r^2 flops: threads pay for octopus (17 x 147
        # samples, r = 20), not for the cantilever's four domains of 60 samples at r = 12.
        pick(stacked_stiffness, stacked_stiffness_serial, D * s, weight=max(1, r * r // 64))(
            self.G.reshape(D, s * 9, r), self.CG.reshape(D, s * 9, r), K)
        return energy, g, K


#: Domains whose mode counts are within this ratio of a larger one share its stack (and
#: its padded width); fewer stacks mean fewer kernel calls a step.
BUCKET_RATIO = 0.75


def mode_buckets(r):
    """Groups of domains [(ids (k,), width)] for domains with mode counts r (D,): from the
    largest count down, each group takes every domain left with at least BUCKET_RATIO of
    its width. At most log(r_max / r_min) / log(1 / BUCKET_RATIO) + 1 groups."""
    r = np.asarray(r, dtype=np.int64)
    left = np.ones(len(r), dtype=bool)
    out = []
    while left.any():                      # a few groups: one per ratio band of mode counts
        width = int(r[left].max())
        ids = np.flatnonzero(left & (r >= BUCKET_RATIO * width))
        out.append((ids, width))
        left[ids] = False
    return out


class StackedSamples:
    """Every domain's cubature samples, for a few kernel calls per evaluation: domains are
    stacked by mode count (mode_buckets), each stack padded only to its own width. One
    stack padded to the largest count made a hub of 30 modes cost five arms of 12 modes
    the hub's work: on star_limbs the padded kernel did 2.5x and the GEMM 3.3x the needed
    arithmetic (docs/performance.md, session 17).

    r_max: the padded width of the model's (D, r_max) modal state.
    """

    def __init__(self, sampled, r_max, material):
        self.D, self.r_max = len(sampled), int(r_max)
        r = [sm.G.shape[2] for sm in sampled]
        self.stacks = [(ids, SampleStack([sampled[k] for k in ids], width, material))
                       for ids, width in mode_buckets(r)]
        # One stack over every domain at the model's width: its outputs are the model's.
        self._whole = (len(self.stacks) == 1 and self.stacks[0][1].G.shape[3] == self.r_max)
        self.det_at = None              # the q (D, r_max) the stacks' det F were computed at
        # Every real sample has a weight: the kernel forms F for all of them (a zero weight
        # would be skipped, and inverted_count could not see it).
        self._weighted = not any(np.any(st.valid & (st.wV == 0.0)) for _, st in self.stacks)

    def evaluate(self, q, want_hessian=True):
        """(energy (D,), g (D, r_max), K (D, r_max, r_max) or None) at q (D, r_max)."""
        q = np.ascontiguousarray(q)
        # The state the det F below belongs to, by identity: a model's q is replaced, never
        # changed in place, and comparing values (np.array_equal) cost a microsecond a step.
        self.det_at = q
        if self._whole:
            return self.stacks[0][1].evaluate(q, want_hessian)
        D, r_max = self.D, self.r_max
        energy, g = np.zeros(D), np.zeros((D, r_max))
        K = np.zeros((D, r_max, r_max)) if want_hessian else None
        for ids, st in self.stacks:        # one per band of mode counts (mode_buckets)
            w = st.G.shape[3]
            e_b, g_b, K_b = st.evaluate(np.ascontiguousarray(q[ids, :w]), want_hessian)
            energy[ids], g[ids, :w] = e_b, g_b
            if want_hessian:
                K[ids, :w, :w] = K_b
        return energy, g, K

    def inverted_count(self, q):
        """Samples with det F <= 0 (NaN counts) at q (D, r_max), read from the last
        evaluation when it was at q, else formed again (measure.inverted_samples)."""
        if self._weighted and self.det_at is q:
            return sum(count_not_positive(st.det, st.valid) for _, st in self.stacks)
        return sum(inverted_samples(st.G, np.ascontiguousarray(q[ids, :st.G.shape[3]]), st.valid)
                   for ids, st in self.stacks)
