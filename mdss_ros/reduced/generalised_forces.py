"""Generalised internal and external forces of the unified system (docs/method.md §6.4, §8, §13).

    G = sum_k G_k(q_k) + sum_e J_e^T f_e(x_I),    K = sum_k K_k(q_k) + sum_e J_e^T K_e J_e
    F_ext = J^T f_ext + gravity in closed form

G_k, K_k (r_k,), (r_k, r_k): domain k's sampled forces (sampled_forces.StackedSamples, all
domains in one pass) or its exact sparse tangent. x_I (n_I, 3) the interface vertices'
world positions and J (n_I, 3, s_max) their Jacobians into the owning domains' generalised
columns (coupling.interface_jacobian); f_e, K_e the coupling elements' forces (12,) and
stiffness (12, 12), weighted by the interface cubature and projected by coupling.py's
kernels. Full-space domains add their element forces on their own rows (the S: block).
"""
import time

import numpy as np
from numba import njit

from ..errors import SceneError
from ..fem.assembly import assemble_matrix, assemble_vector
from ..fem.elements import element_forces
from ..loads import sparse_loads
from ..threads import pick
from .reconstruct import loads_kernel, loads_kernel_serial
from .coupling import (interface_jacobian, interface_jacobian_serial, project_coupling_full, project_coupling_left,
                       project_forces, skew_batch, spring_forces)


@njit(cache=True)
def gravity_rows_kernel(mass_moment, r, q_index, R, g, total_mass, movers, lin_index, F):
    """Gravity g (3,) on every subspace domain's rows of F (n_gen,), written: on the modes
    F[q_index[d, a]] = sum_i mass_moment[d, i, a] (R_d^T g)_i (a < r[d]), on a movable
    frame's linear rows m_d g. mass_moment (D, 3, r_max), R (D, 3, 3), total_mass (D,),
    movers (M,), lin_index (M, 3). One pass for two einsums and two masked scatters."""
    for d in range(r.shape[0]):
        g0 = R[d, 0, 0] * g[0] + R[d, 1, 0] * g[1] + R[d, 2, 0] * g[2]
        g1 = R[d, 0, 1] * g[0] + R[d, 1, 1] * g[1] + R[d, 2, 1] * g[2]
        g2 = R[d, 0, 2] * g[0] + R[d, 1, 2] * g[1] + R[d, 2, 2] * g[2]
        for a in range(r[d]):
            F[q_index[d, a]] = mass_moment[d, 0, a] * g0 + mass_moment[d, 1, a] * g1 + mass_moment[d, 2, a] * g2
    for m in range(movers.shape[0]):
        for i in range(3):
            F[lin_index[m, i]] = total_mass[movers[m]] * g[i]


class GeneralisedForces:
    """Internal forces with their tangent, and applied loads, as generalised forces. Mixed into
    reduced_model.ReducedModel, whose build provides the attributes it reads."""

    def _interface_J(self, q, frames):
        """J values (n_I, 3, s_max) and world positions (n_I, 3) of the interface vertices."""
        L = self.layout
        U, r_loc, row_dom = self._iface_basis
        J = np.empty((len(self.iface), 3, self.s_max))
        x = np.empty((len(self.iface), 3))
        pick(interface_jacobian, interface_jacobian_serial, len(U))(
            U, r_loc, row_dom, L.r, L.movable, np.ascontiguousarray(q), np.ascontiguousarray(frames.R),
            np.ascontiguousarray(frames.c), J, x)
        full_rows = np.flatnonzero(self.J_full)
        J[full_rows] = self.J_static[full_rows]
        x[full_rows] = self.x_full_state[self.iface[full_rows]]
        return J, x

    def _evaluate(self, q, frames, x_full, want_hessian=True, project=False):
        """Generalised internal force G (n_gen,), tangent blocks and energy at a state."""
        t0 = time.perf_counter()
        self.x_full_state = x_full
        G = np.zeros(self.n_gen)
        K_ss = np.zeros((self.S, self.S)) if want_hessian else None
        L = self.layout
        if self.samples is not None:
            e, g, Kr = self.samples.evaluate(q, want_hessian)
            energy = float(e.sum())
            G[L.q_index[L.mask]] = g[L.mask]
            if want_hessian:
                K_ss[L.block_rows, L.block_cols] = Kr[L.block_valid]
        else:
            # Exact forces over every domain element (no cubature): each domain's sparse
            # stiffness projected on its basis, the accurate and slow option.
            energy = 0.0
            for k, dom in enumerate(self.subspace):
                e, g, Kr = dom.reduced_tangent(q[k, :dom.r], want_hessian)
                o = self.sub_offsets[k]
                G[o:o + dom.r] += g
                if want_hessian:
                    K_ss[o:o + dom.r, o:o + dom.r] += Kr
                energy += e
        t1 = time.perf_counter()
        K_sI = np.zeros((self.S, 3 * self.F_I)) if want_hessian else None
        K_ff = None
        if self.F:
            e_f, f_f, K_f = element_forces(x_full, self.body.tets[self.ff_elements], self.ff_geom,
                                           self.body.material, want_hessian, project)
            # Only the full-space domain elements act here; coupling elements go through J.
            nf = self.n_full_elems
            alive = self._full_alive
            f_f[:nf] *= alive[:, None, None]
            f_f[nf:] = 0.0
            energy += float((e_f[:nf] * alive).sum())
            G[self.S:] += self._full_free(assemble_vector(self.body.tets[self.ff_elements], f_f, len(self.body.vertices)))
            if want_hessian:
                K_f[:nf] *= alive[:, None, None]
                self._ff_full_K = K_f           # coupling rows are overwritten below
        if not self.F and not len(self.c_elem):
            # One domain: no coupling elements. Their empty kernel calls cost 40 us a step,
            # 15 % of a 12-DOF model's step.
            self._timed(t0, t1, time.perf_counter())
            return G, K_ss, K_sI, K_ff, energy, np.zeros((0, 3, self.s_max)), np.zeros((0, 3))
        # Coupling elements (world frame).
        J, x_I = self._interface_J(q, frames)
        if self.coupling_kind == "element":
            e_c, f_c, K_c = element_forces(x_I, self.c_elem, self.c_geom, self.body.material,
                                           want_hessian, project)
        else:
            e_c, f_c, K_c = spring_forces(x_I, self.c_elem, self.spring_rest, self.spring_k, want_hessian)
        JL = None
        two_phase = want_hessian and self.F == 0 and not self.unsymmetric
        w_c = None
        if self.c_weights is not None:
            w = self.c_weights
            e_c = e_c * w[:, 2]
            if self.unsymmetric:
                JL = self._weighted_left_J(J, x_I, frames)
            elif two_phase:
                w_c = w[:, 0]                   # applied inside the projection
            else:
                f_c = f_c * w[:, 0, None, None]
                if want_hessian:
                    K_c = K_c * w[:, 0, None, None]
        energy += float(e_c.sum())
        if JL is not None:
            project_coupling_left(self.c_elem, f_c, K_c if want_hessian else np.zeros((len(f_c), 12, 12)),
                                  JL, J, self.J_cols, G, K_ss if want_hessian else np.zeros((self.S, self.S)))
        elif two_phase:
            self._tp.add(f_c, K_c, J, G, K_ss, w_c)
        elif want_hessian:
            # Beside full-space domains: subspace pairs two-phase, subspace-full pairs into A_sI.
            project_forces(self.c_elem, f_c, J, self.J_cols, G)
            self._tp.add(f_c, K_c, J, None, K_ss)
            project_coupling_full(self.c_elem, K_c, J, self.J_cols, self.J_full, self.J_icol, K_sI)
            if self.F:
                K_f[self.n_full_elems:] = self._coupling_full_block(K_c)
                K_ff = assemble_matrix(self.ff_pattern, K_f)
        else:
            project_forces(self.c_elem, f_c, J, self.J_cols, G)
        self._timed(t0, t1, time.perf_counter())
        return G, K_ss, K_sI, K_ff, energy, J, x_I

    def _timed(self, t0, t1, t2):
        """Record an evaluation's phases, domains t0..t1 and coupling t1..t2 (perf_counter
        s): as its own (evaluation_timing, which Step._start_evaluation caches with the
        result) and added to self.timing, the running phase times of the step in progress,
        which Step._step resets once at its start. Replacing self.timing here instead lost
        the factor and solve times of every Newton iteration but the last."""
        domain_ms, coupling_ms = 1e3 * (t1 - t0), 1e3 * (t2 - t1)
        self.evaluation_timing = {"domain_ms": domain_ms, "coupling_ms": coupling_ms}
        timing = self.timing
        timing["domain_ms"] = timing.get("domain_ms", 0.0) + domain_ms
        timing["coupling_ms"] = timing.get("coupling_ms", 0.0) + coupling_ms

    def _weighted_left_J(self, J, x_I, frames):
        """Left factor of the non-uniform interface cubature (see cubature.py): per sample
        and vertex, J with the reduced columns weighted by w_Fi or w_Fj, the force columns
        by w_f, and the torque columns rebuilt about O = (c_i + c_j) / 2 as
        -[w_t (x_l - O) - w_f (c_k - O)]x, which conserves linear and angular momentum."""
        JL = J[self.c_elem].copy()                                   # (n_c, 4, 3, s_max)
        w, pairs = self.c_weights, self.c_pairs
        sampled = pairs[:, 0] >= 0
        O = np.zeros((len(pairs), 3))
        O[sampled] = 0.5 * (frames.c[pairs[sampled, 0]] + frames.c[pairs[sampled, 1]])
        slot_sub = self.sub_index_of_domain[self.vertex_domain[self.iface[self.c_elem]]]    # (n_c, 4)
        e_idx, a_idx = np.nonzero((slot_sub >= 0) & sampled[:, None])
        k = slot_sub[e_idx, a_idx]
        r = self.layout.r[k]
        wq = np.where(pairs[e_idx, 0] == k, w[e_idx, 0], w[e_idx, 1])
        col = np.arange(JL.shape[3])
        movable = self.layout.movable[k]
        lin = movable[:, None] & (col >= r[:, None]) & (col < r[:, None] + 3)
        scale = np.where(col < r[:, None], wq[:, None], np.where(lin, w[e_idx, 2, None], 1.0))
        JL[e_idx, a_idx] *= scale[:, None, :]
        m = np.flatnonzero(movable)
        e_m, a_m, k_m = e_idx[m], a_idx[m], k[m]
        x = x_I[self.c_elem[e_m, a_m]]
        lever = w[e_m, 3, None] * (x - O[e_m]) - w[e_m, 2, None] * (frames.c[k_m] - O[e_m])
        ang = r[m, None] + 3 + np.arange(3)                      # (m, 3) torque columns
        # JL[e, a, i, r + 3 + j] = -skew(lever)[i, j]; advanced indices first: (m, j, i).
        JL[e_m[:, None], a_m[:, None], :, ang] = -skew_batch(lever).transpose(0, 2, 1)
        return JL

    def _coupling_full_block(self, K_c):
        """Coupling element matrices with only full-full vertex pairs kept (others via J)."""
        if self.coupling_kind != "element":
            raise SceneError("spring coupling with full-space domains is not supported")
        full = self.J_full[self.c_elem]                          # (n_c, 4)
        mask = np.repeat(full, 3, axis=1)
        return K_c * (mask[:, :, None] & mask[:, None, :])

    def _applied(self, f_ext, frames, q):
        """J^T f_ext at the step start (n_gen,): the applied point loads as generalised
        forces. Only the loaded vertices are visited (reconstruct.loads_kernel, one compiled
        pass): on a subspace domain U_l^T R^T f on the modes, f on the frame's linear rows
        and (x_l - c) x f on its angular rows; on full-space rows f itself."""
        L = self.layout
        F = np.zeros(self.n_gen)
        loaded, f_loaded = sparse_loads(f_ext)
        if not len(loaded):
            return F
        modal, force, torque = L.zeros(), np.zeros((L.D, 3)), np.zeros((L.D, 3))
        pick(loads_kernel, loads_kernel_serial, len(loaded), weight=4)(
            L.vertex_row[loaded], np.ascontiguousarray(f_loaded, dtype=np.float64), L.U, L.r_local, L.row_domain,
            np.ascontiguousarray(q), np.ascontiguousarray(frames.R), np.ascontiguousarray(frames.c),
            modal, force, torque)
        F[L.modal_rows] = modal[L.mask]
        mv = L.movers
        F[L.lin_index] = force[mv]
        F[L.ang_index] = torque[mv]
        if self.F:
            dof = self.ff_pattern.free_dof[3 * loaded[:, None] + np.arange(3)]     # (k, 3), -1: not full-space
            F[self.S + dof[dof >= 0]] += f_loaded[dof >= 0]
        return F

    def _gravity(self, gravity, frames):
        """Gravity as generalised forces (n_gen,), in closed form: on a subspace domain m g
        on the frame, (sum_l m_l U_l)^T R^T g on the modes (zero for a free domain, whose
        basis is mass-orthogonal to translations) and no torque about the mass centre."""
        L = self.layout
        F = np.zeros(self.n_gen)
        if gravity is None:
            return F
        g = np.asarray(gravity, dtype=np.float64)
        gravity_rows_kernel(L.mass_moment, L.r, L.q_index, np.ascontiguousarray(frames.R), g, L.total_mass,
                            L.movers, L.lin_index, F)
        if self.F:
            F[self.S:] = self._ff_mass * g[self._ff_axis]
        return F
