"""Meshless elastic energy, forces and stiffness with nodal integration (docs/method.md §19.3).

Per node i (n nodes), with F_i from the MLS operator (mls.py) and V_i its volume (model.py):

    Eg_i  = (F_i^T F_i - I) / 2                           Green strain ([HZ] eq. 4)
    S_i   = lam tr(Eg_i) I + 2 mu Eg_i                     linear-elastic (StVK) stress ([HZ] eq. 5)
    psi_i = mu Eg_i:Eg_i + lam/2 tr(Eg_i)^2 + U(J_i),   J_i = det F_i   ([HZ] eqs. 10, 12)
    U(J)  = k_v/2 (J - 1)^2 + k_b/(3 j_b) (j_b - J)^3 [J < j_b]
            ([HZ]'s volume term plus the FEM materials' compression barrier, method.md §3.4)
    E     = sum_i V_i psi_i                                nodal integration

The discrete energy E(x) is the model; forces and stiffness are its exact derivatives
(sign convention of §1: f_int = dE/dx, K = d f_int/dx):

    P_i   = dpsi/dF = F_i S_i + U'(J_i) cof(F_i)                                (3, 3)
    f_{s_ia}  += V_i P_i c_ia                                                    (3,)
    H_i[(p,J),(q,L)] = d2psi / dF_pJ dF_qL                                       (9, 9)
          = delta_pq S_LJ + lam F_pJ F_qL + mu F_pL F_qJ + mu (F F^T)_pq delta_JL
            + U''(J) cof_pJ cof_qL + U'(J) eps_pqm eps_JLN F_mN
    K_i[(a,p),(b,q)] = V_i sum_{J,L} c_ia[J] H_i[(p,J),(q,L)] c_ib[L]         (3w, 3w), w = k + 1

([HZ] eq. 11 writes the force on i and on j as the directional derivatives of U_i; summing
V_i P_i c_ia over every stencil that holds a node is the same thing.) The Hessian is
symmetric; with project=True each H_i is replaced by its PSD part (eigen-decomposition of
the (9, 9) matrix, negative eigenvalues set to 0), so K is positive semi-definite.

Arrays: x (n_nodes, 3); F, P (n, 3, 3); H (n, 9, 9) row-major vec(F)[3 p + J] = F[p, J]
(§1); stencil matrices (n, 3w, 3w); data of K on the free DOFs (nnz,).
"""
import time

import numpy as np

from ..fem.assembly import StiffnessPattern, assemble_matrix, assemble_vector, scatter_add, stiffness_pattern
from ..fem.force_model import FreeDofs
from ..mesh.tetmesh import signed_volumes
from .kernels import node_pass

_EPS = np.zeros((3, 3, 3))
_EPS[0, 1, 2] = _EPS[1, 2, 0] = _EPS[2, 0, 1] = 1.0
_EPS[0, 2, 1] = _EPS[2, 1, 0] = _EPS[1, 0, 2] = -1.0


def cofactor(F):
    """cof(F) = det(F) F^-T, written without the inverse: (n, 3, 3)."""
    return 0.5 * np.einsum("ijk,JKL,njK,nkL->niJ", _EPS, _EPS, F, F, optimize=True)


def barrier_volume(J, kv, kb=0.0, jb=0.2):
    """(U, U', U'') (n,) each of the volume terms U(J) = k_v/2 (J - 1)^2 + the compression
    barrier kb/(3 jb) (jb - J)^3 for J < jb (kb = 0: none), at J (n,)."""
    d = np.maximum(jb - J, 0.0) if kb > 0.0 else np.zeros_like(J)
    return (0.5 * kv * (J - 1.0) ** 2 + kb * d ** 3 / (3.0 * jb), kv * (J - 1.0) - kb * d ** 2 / jb,
            kv + 2.0 * kb * d / jb)


def stvk_volume(F, mu, lam, kv, want_hessian=False, project=False, kb=0.0, jb=0.2):
    """psi (n,), P (n, 3, 3), H (n, 9, 9) or None of the meshless law at F (n, 3, 3);
    kb, jb: the compression barrier (barrier_volume)."""
    n = len(F)
    eye = np.eye(3)
    C = np.einsum("nkA,nkB->nAB", F, F)
    Eg = 0.5 * (C - eye)
    tr = np.trace(Eg, axis1=1, axis2=2)
    S = lam * tr[:, None, None] * eye + 2.0 * mu * Eg
    J = np.linalg.det(F)
    cof = cofactor(F)
    U, dU, d2U = barrier_volume(J, kv, kb, jb)
    psi = mu * np.einsum("nab,nab->n", Eg, Eg) + 0.5 * lam * tr * tr + U
    P = F @ S + dU[:, None, None] * cof
    if not want_hessian:
        return psi, P, None
    FFt = F @ F.transpose(0, 2, 1)
    H = (np.einsum("pq,nLJ->npJqL", eye, S)
         + lam * np.einsum("npJ,nqL->npJqL", F, F)
         + mu * np.einsum("npL,nqJ->npJqL", F, F)
         + mu * np.einsum("npq,JL->npJqL", FFt, eye)
         + d2U[:, None, None, None, None] * np.einsum("npJ,nqL->npJqL", cof, cof)
         + dU[:, None, None, None, None] * np.einsum("pqm,JLN,nmN->npJqL", _EPS, _EPS, F,
                                                                  optimize=True))
    H = H.reshape(n, 9, 9)
    if project:
        H = psd_project(H)
    return psi, P, H


def psd_project(H):
    """(n, 9, 9) symmetric matrices with negative eigenvalues set to zero (unchanged where
    none is below -1e-13 of the largest magnitude)."""
    H = 0.5 * (H + H.transpose(0, 2, 1))
    lam, Q = np.linalg.eigh(H)
    neg = (lam < -1e-13 * np.abs(lam).max(axis=1, keepdims=True)).any(axis=1)
    if neg.any():
        lp = np.maximum(lam[neg], 0.0)
        H[neg] = np.einsum("nab,nb,ncb->nac", Q[neg], lp, Q[neg], optimize=True)
    return H


def stencil_stiffness(c, H, V):
    """K_i (n, 3w, 3w) = V_i B_i^T H_i B_i with vec(F_i) = B_i x_stencil (row 3a + p)."""
    n, w, _ = c.shape
    H5 = H.reshape(n, 3, 3, 3, 3)                                     # p J q L
    T = np.matmul(H5.reshape(n, 27, 3), c.transpose(0, 2, 1))       # (n, pJq, b)
    T = T.reshape(n, 3, 3, 3, w).transpose(0, 2, 1, 3, 4).reshape(n, 3, 9 * w)   # (n, J, p q b)
    K = np.matmul(c, T).reshape(n, w, 3, 3, w)                        # a p q b
    return (V[:, None, None, None, None] * K).transpose(0, 1, 2, 4, 3).reshape(n, 3 * w, 3 * w)


class MeshlessForces(FreeDofs):
    """The force-model interface BackwardEuler steps (as fem.force_model.FEMForceModel):
    energy(x), forces(x), tangent(x, project) -> (E, f_int (n_verts, 3), K data (nnz,)),
    free/expand, M on the pattern, vertex_mass, n_free, pattern.

    op: mls.GradientOperator; V (n,) nodal volumes; mass (n,) nodal masses;
    mu, lam, kv: Lame parameters and volume stiffness (Pa); kb (Pa), jb: the compression
    barrier (kb = 0: none); pinned: fixed node ids;
    stabilisation: None or S (n, w, w), the constant scalar stencil stiffness of the
    fit-residual energy 1/2 sum_i x_{s_i}^T (S_i x I_3) x_{s_i} (integration.py);
    tets: None or (t, 4) the tet mesh on the nodes, whose tets get the same compression
    barrier on their own J (tet_barrier; zero while every tet keeps J >= jb);
    material: None (the meshless law above, stvk_volume) or an FEM material
    (fem/materials.py) whose `evaluate` gives psi, P and dP/dF at the stencils' F, its
    compression barrier included (kb must then be 0): the quadratic tets' other laws."""

    mass_kind = "lumped"

    def __init__(self, X, op, V, mass, mu, lam, kv, pinned=(), stabilisation=None, kb=0.0, jb=0.2, tets=None,
                 material=None):
        self.X = np.ascontiguousarray(X, dtype=np.float64)
        self.n_verts = len(self.X)
        self.op = op
        self.V = np.asarray(V, dtype=np.float64)
        self.mu, self.lam, self.kv = float(mu), float(lam), float(kv)
        self.kb, self.jb = float(kb), float(jb)
        self.material = material
        if material is not None and (self.kb or self.kv or stabilisation is not None):
            raise ValueError("MeshlessForces: a material brings its own law and barrier (kv = kb = 0, "
                             "no stabilisation)")
        self.pinned = np.unique(np.asarray(pinned, dtype=np.int64))
        self.tets = None
        if tets is not None and self.kb > 0.0:
            self._init_tets(np.asarray(tets, dtype=np.int64))
        else:
            self.pattern = stiffness_pattern(op.stencil, self.n_verts, self.pinned)
        self.vertex_mass = np.asarray(mass, dtype=np.float64)
        self.M_data = np.zeros(self.pattern.nnz)
        free = self.pattern.free_dof >= 0
        self.M_data[self.pattern.diagonal] = np.repeat(self.vertex_mass, 3)[free]
        self.M = self.pattern.matrix(self.M_data)
        self.S = None
        if stabilisation is not None:
            self.S = np.ascontiguousarray(stabilisation, dtype=np.float64)
        self.backend = "numba"              # or "numpy": the reference the tests compare with
        self._stiff_buffer = None
        self.timings = {}

    def _init_tets(self, tets):
        """The tets' gradient coefficients (F_t = sum_a x_a c_ta^T), rest volumes, and a
        pattern holding both the stencils and the tets (a tet's nodes need not share a
        stencil), with the tets' own scatter rows."""
        n, w = self.op.stencil.shape
        Xt = self.X[tets]
        Dm = (Xt[:, 1:] - Xt[:, :1]).transpose(0, 2, 1)                   # (t, 3, 3) columns = edges
        Dinv = np.linalg.inv(Dm)
        c = np.empty((len(tets), 4, 3))
        c[:, 1:] = Dinv                                                   # rows of Dm^-1
        c[:, 0] = -Dinv.sum(axis=1)
        self.tets, self.tet_c = tets, c
        self.tet_det = np.linalg.det(Dm)                                 # 6 x the signed rest volume
        self.tet_V = np.abs(self.tet_det) / 6.0
        padded = np.concatenate([tets, np.repeat(tets[:, :1], w - 4, axis=1)], axis=1) if w > 4 else tets
        both = stiffness_pattern(np.concatenate([self.op.stencil, padded]), self.n_verts, self.pinned)
        m = 3 * max(w, 4)
        self.tet_scatter = np.ascontiguousarray(both.scatter[n:].reshape(-1, m, m)[:, :12, :12].reshape(-1, 144))
        self.pattern = StiffnessPattern(both.n_free, both.free_dof, both.indptr, both.indices,
                                        np.ascontiguousarray(both.scatter[:n]), both.diagonal)

    def tet_barrier(self, x, want_hessian=False, project=False):
        """(E, forces (n_verts, 3), (ids, tet stiffness (a, 12, 12)) or None) of the
        compression barrier on the tets' J (docs/method.md §19.7): the nodes are a tet
        mesh's vertices, and a node pushed through the face of a tet is what a nodal fit
        over 16 neighbours hardly sees. Only tets with J < jb contribute."""
        if self.tets is None:
            return 0.0, None, None
        t = self.tets
        act = np.flatnonzero(6.0 * signed_volumes(x, t) / self.tet_det < self.jb)    # J = det Ds / det Dm
        if act.size == 0:
            return 0.0, None, None
        F = np.einsum("tap,taJ->tpJ", x[t[act]], self.tet_c[act])
        psi, P, H = stvk_volume(F, 0.0, 0.0, 0.0, want_hessian, project, self.kb, self.jb)
        V, c = self.tet_V[act], self.tet_c[act]
        fe = V[:, None, None] * np.einsum("niJ,naJ->nai", P, c)
        f = assemble_vector(self.tets[act], fe, self.n_verts)
        K = (act, stencil_stiffness(c, H, V)) if want_hessian else None
        return float(V @ psi), f, K

    def _stabilisation(self, x):
        """(E_hg, per-stencil forces (n, w, 3)) of the fit-residual energy, or (0, None)."""
        if self.S is None:
            return 0.0, None
        xs = x[self.op.stencil]                                         # (n, w, 3)
        fs = np.matmul(self.S, xs)
        return 0.5 * float(np.einsum("nad,nad->", xs, fs)), fs

    def node_terms(self, x, want_hessian=False, project=False):
        """(E, stencil forces (n, w, 3), stencil stiffness (n, 3w, 3w) or None) at x: the
        compiled pass (kernels.py), or this module's numpy reference when backend is 'numpy'."""
        if self.backend == "numba" and self.material is None:
            e, fe, Ke = node_pass(x, self.op.stencil, self.op.c, self.V, self.mu, self.lam, self.kv, self.S,
                                  want_hessian, project, self._stiff_buffer if want_hessian else None,
                                  self.kb, self.jb)
            if want_hessian:
                self._stiff_buffer = Ke
            return float(e.sum()), fe, Ke
        F = self.op.deformation_gradients(x)
        if self.material is not None:
            psi, P, H = self.material.evaluate(F, want_hessian, project)
        else:
            psi, P, H = stvk_volume(F, self.mu, self.lam, self.kv, want_hessian, project, self.kb, self.jb)
        fe = self.V[:, None, None] * np.einsum("niJ,naJ->nai", P, self.op.c, optimize=True)
        e_hg, f_hg = self._stabilisation(x)
        Ke = stencil_stiffness(self.op.c, H, self.V) if want_hessian else None
        if f_hg is not None:
            fe = fe + f_hg
            if want_hessian:
                n, w = self.S.shape[:2]
                Ke = Ke.reshape(n, w, 3, w, 3)         # rows 3a + p, columns 3b + q: S_i[a, b] delta_pq
                for p in range(3):
                    Ke[:, :, p, :, p] += self.S
                Ke = Ke.reshape(n, 3 * w, 3 * w)
        return float(self.V @ psi) + e_hg, fe, Ke

    def energy(self, x):
        return self.node_terms(x)[0] + self.tet_barrier(x)[0]

    def forces(self, x):
        E, fe, _ = self.node_terms(x)
        f = assemble_vector(self.op.stencil, fe, self.n_verts)
        Eb, fb, _ = self.tet_barrier(x)
        return E + Eb, (f if fb is None else f + fb)

    def tangent(self, x, project=False, out=None):
        t0 = time.perf_counter()
        E, fe, Ke = self.node_terms(x, want_hessian=True, project=project)
        t1 = time.perf_counter()
        f = assemble_vector(self.op.stencil, fe, self.n_verts)
        K = assemble_matrix(self.pattern, Ke, out)
        Eb, fb, Kb = self.tet_barrier(x, want_hessian=True, project=project)
        if fb is not None:
            E, f = E + Eb, f + fb
            scatter_add(np.ascontiguousarray(Kb[1]).reshape(len(Kb[0]), -1), self.tet_scatter[Kb[0]], K)
        t2 = time.perf_counter()
        self.timings = {"element_ms": 1e3 * (t1 - t0), "scatter_ms": 1e3 * (t2 - t1)}
        return E, f, K
