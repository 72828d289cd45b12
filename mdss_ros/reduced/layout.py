"""The subspace domains stacked into arrays: what the reduced step computes on.

A body has D subspace domains; domain k has r_k modes, r_max = max r_k. Every per-domain
quantity is stacked along a first axis of length D and padded with zeros to r_max, so a
step treats all domains at once (numpy batches, one compiled kernel) instead of looping
over them in Python. Zero padding is exact: a padded modal coordinate is never written,
and every padded entry of a tensor is zero, so padded terms add nothing.

The state's modal coordinates are q, qd (D, r_max). The generalised vector Q (n_gen,)
holds, per domain k from offset o_k, its r_k modal velocities and, for a movable (free)
domain, its frame's linear and angular velocities v_k, w_k (docs/method.md §9):

    q_index (D, r_max)      generalised row of each modal coordinate, -1 for padding
    mask (D, r_max)         q_index >= 0
    modal_rows (n_modal,)   q_index[mask]: every modal row
    movers (M,)             the movable domains; lin_index, ang_index (M, 3) rows of v, w

Per domain (docs/method.md §7, reduced/frames.py for the tensors):

    total_mass (D,), inertia0 (D, 3, 3) rest inertia about the centre of mass,
    W (D, r_max, r_max, 3), B1 (D, r_max, 3, 3), B2 (D, r_max, r_max, 3, 3), s (D, r_max)
      fictitious-force tensors (zero for a fixed domain),
    mass_moment (D, 3, r_max) = sum_l m_l U_l,  mass_r (D, 3) = sum_l m_l r_l,
    rho (D,) largest rest radius, sigma (D,) largest per-vertex basis norm (the guard).

Per vertex of a subspace domain, stacked domain after domain (reconstruct.py):

    U (n_sub, 3, r_max) basis rows, r_local (n_sub, 3) rest offsets about the frame origin,
    row_domain (n_sub,); vertex_row (n_verts,) a vertex's row here, -1 for full-space ones.

block_rows, block_cols, block_valid: where the entries of a stack of modal blocks
(D, r_max, r_max)[block_valid] go in an (S, S) matrix.
"""
from dataclasses import dataclass

import numpy as np

from .frames import inertia_kernel


@dataclass(frozen=True)
class DomainLayout:
    r: np.ndarray
    r_max: int
    movable: np.ndarray
    q_index: np.ndarray
    mask: np.ndarray
    modal_rows: np.ndarray
    movers: np.ndarray
    lin_index: np.ndarray
    ang_index: np.ndarray
    total_mass: np.ndarray
    inertia0: np.ndarray
    W: np.ndarray
    B1: np.ndarray
    B2: np.ndarray
    s: np.ndarray
    mass_moment: np.ndarray
    mass_r: np.ndarray
    rho: np.ndarray
    sigma: np.ndarray
    U: np.ndarray
    r_local: np.ndarray
    row_domain: np.ndarray
    vertex_row: np.ndarray
    block_rows: np.ndarray
    block_cols: np.ndarray
    block_valid: np.ndarray

    @classmethod
    def build(cls, domains, offsets, n_verts):
        """domains: the SubspaceDomain list; offsets (D + 1,) generalised offsets."""
        D = len(domains)
        r = np.array([dom.r for dom in domains], dtype=np.int64)
        r_max = int(r.max()) if D else 1
        movable = np.array([dom.movable for dom in domains], dtype=bool)
        q_index = np.full((D, r_max), -1, dtype=np.int64)
        W = np.zeros((D, r_max, r_max, 3))
        B1 = np.zeros((D, r_max, 3, 3))
        B2 = np.zeros((D, r_max, r_max, 3, 3))
        s = np.zeros((D, r_max))
        mass_moment = np.zeros((D, 3, r_max))
        n_sub = sum(len(dom.vertices) for dom in domains)
        U = np.zeros((n_sub, 3, r_max))
        r_local = np.zeros((n_sub, 3))
        row_domain = np.zeros(n_sub, dtype=np.int64)
        vertex_row = np.full(n_verts, -1, dtype=np.int64)
        start = 0
        # Built once per model: a loop over domains here costs nothing per step.
        for k, dom in enumerate(domains):
            rk, n = dom.r, len(dom.vertices)
            q_index[k, :rk] = offsets[k] + np.arange(rk)
            if dom.tensors is not None:
                t = dom.tensors
                W[k, :rk, :rk], B1[k, :rk], B2[k, :rk, :rk], s[k, :rk] = t.W, t.B1, t.B2, t.s
            mass_moment[k, :, :rk] = dom.mass_moment
            U[start:start + n, :, :rk] = dom.U3
            r_local[start:start + n] = dom.r_local
            row_domain[start:start + n] = k
            vertex_row[dom.vertices] = start + np.arange(n)
            start += n
        movers = np.flatnonzero(movable)
        frame0 = offsets[:-1][movers] + r[movers]
        # Where each domain's (r_max, r_max) modal block goes in an (S, S) matrix.
        block_valid = (q_index[:, :, None] >= 0) & (q_index[:, None, :] >= 0)
        block_rows = np.broadcast_to(q_index[:, :, None], block_valid.shape)[block_valid]
        block_cols = np.broadcast_to(q_index[:, None, :], block_valid.shape)[block_valid]
        return cls(r=r, r_max=r_max, movable=movable, q_index=q_index, mask=q_index >= 0,
                   modal_rows=q_index[q_index >= 0], movers=movers,
                   lin_index=frame0[:, None] + np.arange(3), ang_index=frame0[:, None] + np.arange(3, 6),
                   total_mass=np.array([dom.total_mass for dom in domains]),
                   inertia0=np.array([dom.inertia0 for dom in domains]).reshape(D, 3, 3),
                   W=W, B1=B1, B2=B2, s=s, mass_moment=mass_moment,
                   mass_r=np.array([dom.mass @ dom.r_local for dom in domains]).reshape(D, 3),
                   rho=np.array([np.linalg.norm(dom.r_local, axis=1).max() for dom in domains]),
                   sigma=np.array([np.sqrt((dom.U3 ** 2).sum(axis=(1, 2)).max()) for dom in domains]),
                   U=U, r_local=r_local, row_domain=row_domain, vertex_row=vertex_row,
                   block_rows=block_rows, block_cols=block_cols, block_valid=block_valid)

    @property
    def D(self):
        return len(self.r)

    def zeros(self):
        """Modal coordinates of every domain at zero: (D, r_max)."""
        return np.zeros((self.D, self.r_max))

    def pad(self, per_domain):
        """A list of D arrays (r_k,) (or anything stackable row by row) as (D, r_max)."""
        out = self.zeros()
        for k, a in enumerate(per_domain):          # conversion for callers, not in a step
            out[k, :len(a)] = a
        return out

    # ------------------------------------------------------------------ generalised vectors
    def gather(self, Q):
        """Modal rows of a generalised vector Q (n_gen,) as (D, r_max), zero padded."""
        return np.where(self.mask, Q[np.maximum(self.q_index, 0)], 0.0)

    def scatter(self, Q, modal, v=None, w=None):
        """Write modal (D, r_max) and the movers' v, w (D, 3) into Q (n_gen,) in place."""
        Q[self.q_index[self.mask]] = modal[self.mask]
        if v is not None:
            Q[self.lin_index] = v[self.movers]
        if w is not None:
            Q[self.ang_index] = w[self.movers]
        return Q

    # ------------------------------------------------------------------ inertia and rotations
    def inertia(self, q):
        """Inertia about the centre of mass in each domain frame at deformation q (D, r_max):
        (D, 3, 3). I(q) = I0 + (tr L + tr B2(q, q)) I - L - B2(q, q), L = B1(q) + B1(q)^T
        (domains.SubspaceDomain.inertia, all domains at once in frames.inertia_kernel, each
        over its own modes; fixed domains keep I0)."""
        out = np.empty((self.D, 3, 3))
        inertia_kernel(np.ascontiguousarray(q), self.r, self.inertia0, self.B1, self.B2, out)
        return out
