"""The multi-domain subspace model (`model.kind: reduced`), stepped by one unified
implicit solve over all domains (docs/method.md §9):

    A Q' = b
    A = Mgen + dt Dgen + dt^2 Kgen,    Dgen = alpha Mgen + beta Kgen(step start)
    b = Mgen Q + dt (J^T f_ext - G_int + F_fict + F_gyro)

Q stacks, per subspace domain, [qd_i; v_i; w_i] (a domain holding pins: qd_i only), then
the velocities of the free vertices of full-space domains. Mgen = blockdiag(I_r, m_i I3,
I_i(world)) and lumped masses for full-space vertices. Kgen holds U_i^T K_i U_i of each
domain's elements (evaluated in the domain frame), J_e^T K_e J_e of every coupling
element, and the full-space stiffness. Fictitious forces (docs/method.md §7) and the gyroscopic
term -w x I w are explicit, as in the paper. After the solve:
q' = q + dt qd', c' = c + dt v', R' = exp([dt w']x) R, x' = x + dt xd' (full space).

newton_iterations > 1 re-evaluates forces and tangents at the predicted state and
iterates on the residual r(Q) = Mgen (Q - Q_n) + dt (Dgen Q + G_int(s(Q)) - F_n), with the
explicit terms F_n frozen at the step start, and an Armijo line search on the matching
incremental potential. Its first iterate is exactly the one-step method above.
"""
import time

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from scipy.spatial.transform import Rotation

from ..errors import SceneError
from ..fem.assembly import assemble_matrix, assemble_vector, stiffness_pattern
from ..fem.backward_euler import contact_forces, contact_stats
from ..fem.elements import element_forces, tet_geometry
from ..fem.mass import lumped_mass
from ..linear_solver import NotPositiveDefinite, SparseSolver
from ..loads import sparse_loads
from ..threads import pick
from ..precompute import PrecomputeCache, bases_cache_key, cubature_cache_key
from ..rotations import cross, exp_so3, exp_so3_batch, orthonormalise_batch
from . import reconstruct
from .block_cholesky import BlockCholesky
from .coupling import (TwoPhaseProjection, interface_jacobian, interface_jacobian_serial, project_coupling_full,
                       project_coupling_left, project_forces, skew_batch, spring_forces)
from .domains import FullDomain, build_subspace_domain
from .frames import FrameState, fictitious_forces, omega_B2_omega
from .layout import DomainLayout
from .measure import frame_measure, inverted_samples
from .sampled_forces import StackedSamples


def _jsonable(x):
    """Numbers and arrays of an info dict as plain JSON types."""
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple, np.ndarray)):
        return [_jsonable(v) for v in x]
    if isinstance(x, (np.floating, np.integer, np.bool_)):
        return x.item()
    return x


class ReducedModel:
    """Multi-domain subspace model of a Body; see the module docstring.

    cfg: the scene's `model` section; damping {"alpha", "beta"}; dt > 0.
    """

    kind = "reduced"
    can_untangle = True

    def __init__(self, body, cfg, dt, damping, solver="auto", progress=None, cache=None):
        from .partition import build_partition, domain_elimination_order, domain_labels
        t_start = time.perf_counter()
        say = progress or (lambda msg: None)
        self.body = body
        self.cfg = cfg
        self.dt = float(dt)
        self.alpha, self.beta = float(damping["alpha"]), float(damping["beta"])
        integ = cfg["integrator"]
        self.scheme = integ["scheme"] if integ["scheme"] != "backward_euler" else "one_step"
        self.newton_iterations = integ["newton_iterations"]
        self.tolerance = integ["tolerance"]
        self.line_search = integ["line_search"]
        # "explicit" (the papers'), or "implicit": the Coriolis force on the modes as its exact
        # (norm-preserving) flow and the centrifugal stiffness in the implicit system.
        self.fictitious = integ.get("fictitious", "explicit")
        X, tets = body.vertices, body.tets
        n = len(X)
        self.geom = tet_geometry(X, tets)
        self.vertex_mass = lumped_mass(tets, self.geom.volume, body.material.density, n)

        # Partition and bases, from the cache when their inputs are unchanged ----------
        self.cache = cache if cache is not None else PrecomputeCache()
        self.bases_key = bases_cache_key(body, cfg)
        hit = self.cache.load("bases", self.bases_key)
        if hit is not None:
            labels, names = hit[0]["labels"], list(hit[1]["names"])
            self.partition_notes = list(hit[1].get("partition_notes", []))
            say(f"cache: bases loaded from {self.cache.path('bases', self.bases_key)}")
        else:
            self.partition_notes = []         # why the domains are where they are (auto placement)
            labels, names = domain_labels(cfg.get("domains"), body.vertices, body.tets, self.partition_notes)
            for note in self.partition_notes:
                say(f"domains: {note}")
        self.partition = build_partition(tets, labels, names=names)
        part = self.partition
        d = part.n_domains
        full_set = self._full_space_set(cfg, names)
        pinned_mask = np.zeros(n, dtype=bool)
        pinned_mask[body.pinned] = True
        say(f"partition: {d} domains, {len(part.coupling_elements)} coupling elements, "
            f"graph edges {np.asarray(part.graph_edges).tolist()}")

        # Domains ----------------------------------------------------------------
        r = cfg["modes"]
        basis_opts = dict(cfg.get("basis") or {})
        # model.basis.modes: {domain name: r} overrides model.modes for those domains (a hub
        # that carries the moments of several limbs needs more modes than each limb).
        modes_by_name = basis_opts.pop("modes", None) or {}
        if not isinstance(modes_by_name, dict) or set(modes_by_name) - set(names) or not all(
                isinstance(v, int) and not isinstance(v, bool) and v > 0 for v in modes_by_name.values()):
            raise SceneError(f"model.basis.modes must map domain names ({', '.join(map(str, names))}) to positive "
                             f"integers, got {modes_by_name!r}")
        self.subspace, self.full = [], []
        self.vertex_domain = np.asarray(labels, dtype=np.int64)
        self.vertex_local = np.empty(n, dtype=np.int64)
        self.domain_kind = []                    # per domain: ("sub", k) or ("full", k)
        for i in range(d):
            verts = part.domain_vertices[i]
            self.vertex_local[verts] = np.arange(len(verts))
            if i in full_set:
                self.domain_kind.append(("full", len(self.full)))
                self.full.append(FullDomain(i, names[i], verts, ~pinned_mask[verts], part.domain_elements[i]))
                continue
            r_i = min(modes_by_name.get(names[i], r),
                      3 * len(verts) - (6 if not pinned_mask[verts].any() else 3 * int(pinned_mask[verts].sum())))
            if r_i < 1:
                raise SceneError(f"domain {names[i]} has too few free DOFs for a subspace ({len(verts)} vertices)")
            cached_U = hit[0].get(f"U_{i}") if hit is not None else None
            dom = build_subspace_domain(i, names[i], body, self.vertex_mass, verts, part.domain_elements[i],
                                        r_i, basis_opts, pinned_mask, U=cached_U,
                                        basis_info=hit[1]["basis"].get(str(i)) if hit is not None else None)
            self.domain_kind.append(("sub", len(self.subspace)))
            self.subspace.append(dom)
            say(f"domain {names[i]}: {len(verts)} vertices, {len(part.domain_elements[i])} elements, "
                f"r = {dom.r}, basis region +{dom.basis_info['layers']} layers, {'free (frame + modes)' if dom.movable else 'pinned (modes only)'}, "
                f"basis {dom.basis_info['seconds']:.2f} s")
        self.movable = np.array([dom.movable for dom in self.subspace], dtype=bool)
        if hit is None:
            self.cache.save("bases", self.bases_key,
                            dict({"labels": np.asarray(labels)}, **{f"U_{dom.index}": dom.U for dom in self.subspace}),
                            {"names": list(names), "partition_notes": list(self.partition_notes),
                             "basis": {str(dom.index): {k: v for k, v in dom.basis_info.items() if k != "seconds"}
                                       for dom in self.subspace}})
        self.sub_index_of_domain = np.array([k if kind == "sub" else -1 for kind, k in self.domain_kind], dtype=np.int64)

        # Generalised DOF layout -------------------------------------------------
        sizes = np.array([dom.n_dofs for dom in self.subspace], dtype=np.int64)
        self.sub_offsets = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
        self.S = int(self.sub_offsets[-1])
        self.layout = DomainLayout.build(self.subspace, self.sub_offsets, n)
        full_free = np.zeros(n, dtype=bool)
        for fd in self.full:
            full_free[fd.vertices[fd.free]] = True
        self.is_full_vertex = np.zeros(n, dtype=bool)
        for fd in self.full:
            self.is_full_vertex[fd.vertices] = True
        # Full-space pattern: every element touching a free full-space vertex (their
        # domain elements and coupling elements); other vertices' DOFs are dropped.
        coupling = np.asarray(part.coupling_elements, dtype=np.int64)
        full_elems = np.concatenate([fd.elements for fd in self.full]).astype(np.int64) if self.full else np.zeros(0, np.int64)
        self.ff_elements = np.concatenate([full_elems, coupling]) if self.full else np.zeros(0, np.int64)
        if self.full:
            self.ff_pattern = stiffness_pattern(tets[self.ff_elements], n, np.flatnonzero(~full_free))
            self.F = self.ff_pattern.n_free
            self.full_dof_of_vertex = np.where(full_free, self.ff_pattern.free_dof[3 * np.arange(n)] // 3, -1)
            Mf = np.zeros(self.ff_pattern.nnz)
            Mf[self.ff_pattern.diagonal] = np.repeat(self.vertex_mass[full_free], 3)
            self.M_ff = Mf
            # Mass and axis of each free full-space DOF: gravity on them without an (n, 3) pass.
            free_dofs = np.flatnonzero(self.ff_pattern.free_dof >= 0)
            self._ff_mass, self._ff_axis = self.vertex_mass[free_dofs // 3], free_dofs % 3
            self.ff_geom = self.geom.subset(self.ff_elements)
            self.n_full_elems = len(full_elems)
        else:
            self.F = 0
            self.full_dof_of_vertex = np.full(n, -1, dtype=np.int64)
        self.n_gen = self.S + self.F

        # Coupling ---------------------------------------------------------------
        ccfg = dict(cfg.get("coupling") or {})
        self.coupling_kind = ccfg.get("kind", "element")
        if self.coupling_kind == "element":
            pass                                                # set by _set_coupling_elements
        elif self.coupling_kind == "spring":
            self.c_verts = self._coupling_springs(tets[coupling])
            self.spring_k = float(ccfg.get("stiffness", 1e4))
            self.spring_rest = np.linalg.norm(X[self.c_verts[:, 1]] - X[self.c_verts[:, 0]], axis=1)
        else:
            raise SceneError(f"model.coupling.kind: {self.coupling_kind!r} (element, spring)")
        self.c_weights = None           # (n_c, 4) cubature weights per INTERFACE_GROUPS, None = exact
        self.c_pairs = None             # (n_c, 2) subspace domains of a sampled element, -1 = exact
        self.unsymmetric = False
        self._set_coupling_elements(coupling)

        # Solver -------------------------------------------------------------------
        self.order = domain_elimination_order(len(self.subspace), self._subspace_edges())
        self.block_solver = BlockCholesky(sizes, self._subspace_edges(), self.order) if self.F == 0 else None
        self.sparse_solver = SparseSolver(solver) if self.F > 0 else None
        self.reset()
        self.samples = None             # StackedSamples once cubature exists (_stack_samples)
        self.cubature_info = self._build_cubature(cfg.get("cubature") or {}, say)
        self._stack_samples()
        self.build_seconds = time.perf_counter() - t_start

    def _build_cubature(self, ccfg, say):
        """Training poses and per-domain cubature when model.cubature.samples > 0."""
        from .cubature import build_domain_cubature
        from .training import generate_training
        allowed = {"samples", "tolerance", "interface", "interface_samples", "training", "seed"}
        unknown = set(ccfg) - allowed
        if unknown:
            raise SceneError(f"model.cubature: unknown key(s) {sorted(unknown)} (allowed: {sorted(allowed)})")
        samples = ccfg.get("samples", 0) or 0
        interface = ccfg.get("interface", "exact")
        if interface not in ("exact", "uniform", "nonuniform"):
            raise SceneError(f"model.cubature.interface: {interface!r} (exact, uniform, nonuniform)")
        if interface != "exact" and (self.F or self.coupling_kind != "element"):
            raise SceneError("model.cubature.interface: interface cubature needs element coupling and no "
                             "full-space domains (use interface: exact)")
        if samples <= 0 or not self.subspace:
            if interface != "exact":
                raise SceneError("model.cubature.interface: set model.cubature.samples > 0 as well")
            return {"samples": 0}
        key = cubature_cache_key(self.bases_key, ccfg, self.dt, self.alpha, self.beta, self.cfg)
        hit = self.cache.load("cubature", key)
        if hit is not None:
            say(f"cache: cubature loaded from {self.cache.path('cubature', key)}")
            return self._restore_cubature(*hit)
        tcfg = dict(ccfg.get("training") or {})
        t0 = time.perf_counter()
        training = generate_training(self, progress=say, seed=int(ccfg.get("seed", 0)), **tcfg)
        say(f"training: {training.n_poses} poses from the {training.source} model in {training.seconds:.1f} s")
        info = {"samples": samples, "training_source": training.source, "training_poses": training.n_poses,
                "training_seconds": training.seconds, "domains": []}
        for k, dom in enumerate(self.subspace):
            dom.sampled, d_info = build_domain_cubature(dom, training.q[k], samples, ccfg.get("tolerance", 0.0),
                                                        seed=int(ccfg.get("seed", 0)))
            info["domains"].append(d_info)
            say(f"cubature {dom.name}: {d_info['samples']} of {d_info['elements']} elements, "
                f"training error {d_info['train_error']:.2e}, held-out {d_info.get('held_out_error', float('nan')):.2e}")
        if interface != "exact":
            info["interface"] = self._build_interface_cubature(training, interface,
                                                               int(ccfg.get("interface_samples", samples)),
                                                               int(ccfg.get("seed", 0)), say)
        info["seconds"] = time.perf_counter() - t0
        self.training = training
        arrays = {}
        for k, dom in enumerate(self.subspace):
            arrays[f"elements_{k}"] = dom.sampled.elements
            arrays[f"weights_{k}"] = dom.sampled.weights
            arrays[f"training_q_{k}"] = training.q[k]
        arrays["training_c"], arrays["training_R"] = training.c, training.R
        if self.c_weights is not None:
            arrays["c_tets"], arrays["c_weights"], arrays["c_pairs"] = self.c_tets, self.c_weights, self.c_pairs
        self.cache.save("cubature", key, arrays, _jsonable(dict(info, unsymmetric=self.unsymmetric)))
        return info

    def _stack_samples(self):
        """All domains' cubature samples in one array (one kernel call a step), or None when
        a domain evaluates every element (no cubature: its exact sparse path)."""
        sampled = [dom.sampled for dom in self.subspace]
        ok = bool(sampled) and all(sm is not None for sm in sampled)
        self.samples = StackedSamples(sampled, self.layout.r_max, self.body.material) if ok else None

    def _restore_cubature(self, arrays, meta):
        from .sampled_forces import SampledDomainForces
        for k, dom in enumerate(self.subspace):
            fm = dom.forces
            dom.sampled = SampledDomainForces.build(dom.U3, fm.tets, fm.geom.grads, fm.geom.volume, fm.material,
                                                    arrays[f"elements_{k}"], arrays[f"weights_{k}"])
        if "c_tets" in arrays:
            self._set_coupling_elements(arrays["c_tets"])
            self.c_weights = arrays["c_weights"]
            self.c_pairs = arrays["c_pairs"].astype(np.int64)
            self.unsymmetric = bool(meta.get("unsymmetric", False))
        return dict(meta, cached=True)

    def _build_interface_cubature(self, training, scheme, samples, seed, say):
        """Replace each two-domain interface's coupling elements by weighted samples;
        elements touching three or more domains stay exact."""
        from .cubature import build_interface_cubature
        tets_dom = self.vertex_domain[self.body.tets[self.c_tets]]
        lo, hi = tets_dom.min(1), tets_dom.max(1)
        two = (np.diff(np.sort(tets_dom, axis=1), axis=1) != 0).sum(1) == 1
        keep_exact = self.c_tets[~two]
        new_tets, new_w, new_pairs, infos = [keep_exact], [np.ones((len(keep_exact), 4))], \
            [np.full((len(keep_exact), 2), -1)], []
        for i, j in np.unique(np.stack([lo[two], hi[two]], 1), axis=0):
            elems = self.c_tets[two & (lo == i) & (hi == j)]
            pair = (int(self.sub_index_of_domain[i]), int(self.sub_index_of_domain[j]))
            ids, W, inf = build_interface_cubature(self, elems, pair, training, samples, scheme, seed)
            new_tets.append(ids)
            new_w.append(W)
            new_pairs.append(np.tile(pair, (len(ids), 1)))
            infos.append(inf)
            say(f"interface {self.partition.names[i]}-{self.partition.names[j]}: {len(ids)} of {len(elems)} "
                f"elements ({scheme}), held-out errors "
                f"{ {g: round(v, 4) for g, v in inf.get('held_out_error', {}).items()} }")
        self._set_coupling_elements(np.concatenate(new_tets))
        self.c_weights = np.concatenate(new_w)
        self.c_pairs = np.concatenate(new_pairs).astype(np.int64)
        self.unsymmetric = scheme == "nonuniform"
        return {"scheme": scheme, "interfaces": infos, "exact_elements": int(len(keep_exact))}

    # ------------------------------------------------------------------ setup
    @staticmethod
    def _full_space_set(cfg, names):
        out = set()
        for item in cfg.get("full_space_domains") or []:
            if isinstance(item, int) and 0 <= item < len(names):
                out.add(item)
            elif item in names:
                out.add(names.index(item))
            else:
                raise SceneError(f"model.full_space_domains: unknown domain {item!r} (domains: {names})")
        return out

    def _coupling_springs(self, ctets):
        """Edges of coupling elements whose two vertices lie in different domains."""
        pairs = ctets[:, [[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]]].reshape(-1, 2)
        pairs = np.sort(pairs, axis=1)
        pairs = pairs[self.vertex_domain[pairs[:, 0]] != self.vertex_domain[pairs[:, 1]]]
        return np.unique(pairs, axis=0)

    def _subspace_edges(self):
        edges = []
        for i, j in np.asarray(self.partition.graph_edges, dtype=np.int64).reshape(-1, 2):
            ki, kj = self.domain_kind[i], self.domain_kind[j]
            if ki[0] == "sub" and kj[0] == "sub":
                edges.append((ki[1], kj[1]))
        return np.array(edges, dtype=np.int64).reshape(-1, 2)

    def _set_coupling_elements(self, tet_ids):
        """Use these coupling tets (global ids) and rebuild the interface-vertex maps."""
        if self.coupling_kind == "element":
            self.c_tets = np.asarray(tet_ids, dtype=np.int64)
            self.c_verts = self.body.tets[self.c_tets]
            self.c_geom = self.geom.subset(self.c_tets)
        iface, inv = np.unique(self.c_verts, return_inverse=True)
        # Ordered by domain (full-space vertices last), so that a domain's interface rows
        # are one slice: J, its basis rows and the coupling GEMMs then work on views.
        dom = np.where(self.is_full_vertex[iface], len(self.subspace),
                       self.sub_index_of_domain[self.vertex_domain[iface]])
        order = np.lexsort((iface, dom))
        rank = np.empty_like(order)
        rank[order] = np.arange(len(order))
        self.iface = iface[order]
        self.c_elem = rank[inv].reshape(self.c_verts.shape).astype(np.int64)
        self._guard_tet_list = {}              # the guard's element lists follow the coupling set
        self._build_interface_maps()

    def _build_interface_maps(self):
        """Static part of J for the interface vertices: generalised columns, full flags;
        and each domain's frame columns (D, 6), linear then angular, -1 for a fixed
        domain (contact rows: reconstruct.contact_rows_kernel)."""
        L = self.layout
        self._frame_cols = np.full((L.D, 6), -1, dtype=np.int64)
        self._frame_cols[L.movers] = np.hstack([L.lin_index, L.ang_index])
        iv = self.iface
        n_I = len(iv)
        self.s_max = max([dom.n_dofs for dom in self.subspace] + [3])
        self.J_cols = np.full((n_I, self.s_max), -1, dtype=np.int64)
        self.J_full = self.is_full_vertex[iv]
        self.J_icol = np.full((n_I, 3), -1, dtype=np.int64)
        for k, dom in enumerate(self.subspace):          # per coupling set, not per step
            rows = np.flatnonzero(self.vertex_domain[iv] == dom.index)
            self.J_cols[rows, :dom.n_dofs] = self.sub_offsets[k] + np.arange(dom.n_dofs)
        full_rows = np.flatnonzero(self.J_full)
        fdof = self.full_dof_of_vertex[iv[full_rows]]
        free_rows = full_rows[fdof >= 0]
        self.J_cols[free_rows, :3] = self.S + 3 * fdof[fdof >= 0, None] + np.arange(3)
        self.F_I = len(free_rows)
        self.J_icol[free_rows] = 3 * np.arange(self.F_I)[:, None] + np.arange(3)
        self.iface_full_cols = self.J_cols[free_rows, :3].reshape(-1) - self.S      # (3 F_I,)
        self.J_static = np.zeros((n_I, 3, self.s_max))
        self.J_static[free_rows, :, :3] = np.eye(3)
        # Basis rows and rest offsets of the subspace interface vertices (interface_jacobian)
        L = self.layout
        rows = L.vertex_row[iv]
        sub = np.flatnonzero(rows >= 0)
        U = np.zeros((n_I, 3, L.r_max))
        r_loc = np.zeros((n_I, 3))
        row_dom = np.full(n_I, -1, dtype=np.int64)
        U[sub], r_loc[sub], row_dom[sub] = L.U[rows[sub]], L.r_local[rows[sub]], L.row_domain[rows[sub]]
        self._iface_basis = (U, r_loc, row_dom)
        # The coupling projection's static data (coupling.TwoPhaseProjection)
        sizes = np.array([dom.n_dofs for dom in self.subspace], dtype=np.int64)
        self._tp = TwoPhaseProjection(self.c_elem, self.sub_index_of_domain[self.vertex_domain[iv]], sizes,
                                      self.sub_offsets)

    # ------------------------------------------------------------------ state
    def reset(self):
        # q, qd (D, r_max) zero-padded (layout.py). They are replaced, never written in
        # place, by a step or set_state: the cached start evaluation checks them by identity.
        self.q = self.layout.zeros()
        self.qd = self.layout.zeros()
        self.frames = FrameState.at_rest([dom.cbar for dom in self.subspace])
        self.x_full = self.body.vertices.copy()          # only full-space rows are used
        self._full_alive = self._alive_weights()          # cutting is not undone by a reset
        self.v_full = np.zeros_like(self.x_full)
        self.last = {"elastic": 0.0}
        self.stats = {}
        self.contact = None
        # The contact LCP's warm start (_contact_solve): part of the state, so a rolled
        # back or replayed step repeats bit for bit.
        self._contact_history, self._contact_rows_seen, self._contact_lam = [], None, None
        self._start_eval = None         # the evaluation at the current state (_start_evaluation)

    def _full_rows(self, a):
        """A copy of x_full or v_full (n_verts, 3) for a snapshot. Without full-space
        domains they hold no state (rest positions, zeros) and are only ever replaced,
        never written in place: the same array serves, and a step of a 300K-tet body
        does not copy 1.4 MB three times for nothing."""
        return a.copy() if self.F else a

    def _alive_weights(self):
        """1.0 / 0.0 per full-space domain element (cut elements 0), all domains concatenated."""
        return np.concatenate([fd.alive for fd in self.full]).astype(float) if self.full else np.zeros(0)

    def get_state(self):
        """A snapshot of the dynamic state (copies): q, qd (per subspace domain), frames,
        full-space x and v, and what the outputs read (last energy, contact, stats).
        set_state(snapshot) restores it exactly (the stability guard rolls back with it)."""
        return {"q": self.q.copy(), "qd": self.qd.copy(),
                "frames": self.frames.copy(), "x_full": self._full_rows(self.x_full),
                "v_full": self._full_rows(self.v_full),
                "last": dict(self.last), "contact": self.contact, "stats": dict(self.stats),
                "contact_history": list(self._contact_history)}

    def set_state(self, state):
        """Restore a get_state() snapshot."""
        self.q = np.array(state["q"], dtype=np.float64)
        self.qd = np.array(state["qd"], dtype=np.float64)
        self.frames = state["frames"].copy()
        self.x_full, self.v_full = self._full_rows(state["x_full"]), self._full_rows(state["v_full"])
        self.last, self.contact, self.stats = dict(state["last"]), state["contact"], dict(state["stats"])
        self._contact_history, self._contact_rows_seen = list(state.get("contact_history", [])), None

    @property
    def n_dofs(self):
        return self.n_gen

    def set_dt(self, dt):
        """Change the step (collider sub-steps); every term of a step reads self.dt."""
        self.dt = float(dt)

    def set_rigid_velocity(self, linear, angular, center=None):
        """Give the whole body a rigid velocity v + w x (x - center) (default: its centre of mass)."""
        linear, angular = np.asarray(linear, float), np.asarray(angular, float)
        if center is None:
            center = (self.vertex_mass[:, None] * self.vertex_positions()).sum(0) / self.vertex_mass.sum()
        mv = self.movable
        self.frames.v[mv] = linear + cross(angular, self.frames.c[mv] - center)
        self.frames.w[mv] = angular
        self.frames.w_prev[mv] = angular
        xf = self.x_full
        self.v_full = np.where(self.is_full_vertex[:, None], linear + cross(angular, xf - center), 0.0)
        self.v_full[self.body.pinned] = 0.0

    def get_Q(self):
        Q = self.layout.scatter(np.zeros(self.n_gen), self.qd, self.frames.v, self.frames.w)
        if self.F:
            Q[self.S:] = self._full_free(self.v_full)
        return Q

    def _full_free(self, a):
        return a.reshape(-1)[self.ff_pattern.free_dof >= 0]

    def _full_expand(self, a_free):
        out = np.zeros(3 * len(self.body.vertices))
        out[self.ff_pattern.free_dof >= 0] = a_free
        return out.reshape(-1, 3)

    def _predict(self, Q, base):
        """State reached from the step-start state `base` with velocities Q over dt.

        Without a global motion Q holds inertial velocities and frame centres move on
        straight lines. With one (free bodies, see _global_motion) Q holds velocities
        relative to the body's mean rigid motion (C, V, W): every frame centre and
        full-space vertex is carried rigidly by exp(dt W) about C, plus its relative
        motion, so a rigid spin is integrated exactly instead of spiralling in under
        backward Euler.
        """
        q0, frames0, x0, gm = base
        dt = self.dt
        L = self.layout
        qd = L.gather(Q)
        q = q0 + dt * qd
        v = frames0.v.copy()
        w = frames0.w.copy()
        v[L.movers] = Q[L.lin_index]
        w[L.movers] = Q[L.ang_index]
        frames = frames0.copy()
        if self.F:
            v_full = self._full_expand(Q[self.S:])
        else:
            v_full = self.v_full
        if gm is None:
            frames.advance(v, w, dt, self.movable)
            x_full = x0 + dt * v_full if self.F else x0
        else:
            C, V, W = gm[:3]
            Rg = exp_so3(dt * W)
            C1 = C + dt * V
            mv = self.movable
            rho = Rg @ (frames0.c[mv] - C + dt * v[mv]).T
            frames.c[mv] = C1 + rho.T
            frames.v[mv] = V + cross(W, rho.T) + v[mv] @ Rg.T
            frames.w[mv] = W + w[mv] @ Rg.T
            frames.R[mv] = orthonormalise_batch(Rg @ exp_so3_batch(dt * w[mv]) @ frames0.R[mv])
            if self.F:
                rho_f = (x0 - C + dt * v_full) @ Rg.T
                x_full = np.where(self.is_full_vertex[:, None], C1 + rho_f, x0)
                v_full = np.where(self.is_full_vertex[:, None], V + cross(W, rho_f) + v_full @ Rg.T, 0.0)
            else:
                x_full = x0
        # The angular rows solved I_pred w' = h (momentum form, see _mass_blocks) with the
        # inertia at the predicted rotation; re-express that momentum with the inertia the
        # domain really has after the step, so torque-free domains keep h exactly.
        mv = L.movers
        if len(mv):
            Rp = L.predicted_rotations(frames0.R[mv], frames0.w[mv], dt)
            h = np.einsum("dij,dj->di", Rp @ L.inertia(q0)[mv] @ Rp.transpose(0, 2, 1),
                          frames.w[mv] if gm is None else gm[2] + w[mv])
            R1 = frames.R[mv]
            frames.w[mv] = np.linalg.solve(R1 @ L.inertia(q)[mv] @ R1.transpose(0, 2, 1), h[:, :, None])[:, :, 0]
        if gm is not None:
            # Carrying the state by exp(dt W) also turns its angular momentum by that
            # rotation; where L is not parallel to W (products of inertia) this is a
            # spurious precession, first order in dt. Restore the balance of angular
            # momentum, L' = (L + dt tau_ext) / (1 + dt alpha), with a rigid rotation dW
            # about the mass centre (linear momentum unchanged).
            C1, _, L1, I1 = self._momentum(frames, q, x_full, v_full)
            dW = np.linalg.solve(I1, gm[3] - L1)
            self._dW = float(np.linalg.norm(dW))
            frames.v[mv] += cross(dW, frames.c[mv] - C1)
            frames.w[mv] += dW
            if self.F:
                v_full = np.where(self.is_full_vertex[:, None], v_full + cross(dW, x_full - C1), v_full)
        frames.w_prev = frames0.w.copy()
        return q, qd, frames, x_full, v_full

    def _global_motion(self):
        """(C, V, W, L): mass centre, velocity, angular velocity and angular momentum of
        the whole body, W fitted to L (frames and full-space vertices), or None for a body
        held by pins."""
        if self.body.pinned.size or not self.movable.all():
            return None
        C, V, L, I = self._momentum(self.frames, self.q, self.x_full, self.v_full)
        return C, V, np.linalg.solve(I, L), L

    def _momentum(self, fr, q, x_full, v_full):
        """Mass centre C, its velocity V, angular momentum L about C and inertia I (3, 3)
        of a state, from the domain frames (the deformation's own angular momentum is
        second order because U is mass-orthogonal to rotations) and full-space vertices."""
        m_d = self.layout.total_mass
        full = self.is_full_vertex
        m_f = self.vertex_mass[full]
        x_f, v_f = x_full[full], v_full[full]
        m = m_d.sum() + m_f.sum()
        C = ((m_d[:, None] * fr.c).sum(0) + (m_f[:, None] * x_f).sum(0)) / m
        V = ((m_d[:, None] * fr.v).sum(0) + (m_f[:, None] * v_f).sum(0)) / m
        rho, rho_f = fr.c - C, x_f - C
        I_d = fr.R @ self.layout.inertia(q) @ fr.R.transpose(0, 2, 1)
        I = (I_d.sum(0) + ((m_d * (rho * rho).sum(1)).sum() + (m_f * (rho_f * rho_f).sum(1)).sum()) * np.eye(3)
             - np.einsum("i,ij,ik->jk", m_d, rho, rho) - np.einsum("i,ij,ik->jk", m_f, rho_f, rho_f))
        L = (cross(rho, m_d[:, None] * (fr.v - V)).sum(0) + np.einsum("ijk,ik->j", I_d, fr.w)
             + cross(rho_f, m_f[:, None] * (v_f - V)).sum(0))
        return C, V, L, I

    def _rigid_Q(self, gm, angular_only=False):
        """Generalised velocities of the rigid motion (V, W) about C (n_gen,);
        angular_only: W on the domains' angular rows, zero elsewhere."""
        C, V, W = gm[:3]
        L = self.layout
        Q = np.zeros(self.n_gen)
        Q[L.ang_index] = W
        if not angular_only:
            Q[L.lin_index] = V + cross(W, self.frames.c[L.movers] - C)
        if self.F and not angular_only:
            Q[self.S:] = self._full_free(V + cross(W, self.x_full - C))
        return Q

    def _global_fictitious(self, gm):
        """Centrifugal force of the frame rotating with W on frame centres and full-space
        vertices (n_gen,). The angular rows take W through the momentum form, and the
        Coriolis force through _coriolis_rotate."""
        C, V, W = gm[:3]
        L = self.layout
        F = np.zeros(self.n_gen)
        F[L.lin_index] = -L.total_mass[L.movers, None] * cross(W, cross(W, self.frames.c[L.movers] - C))
        if self.F:
            f = -self.vertex_mass[:, None] * cross(W, cross(W, self.x_full - C))
            F[self.S:] = self._full_free(f)
        return F

    def _coriolis_rotate(self, gm, Q_rel):
        """Exact flow of the Coriolis force -2 m W x v over dt: rotate the relative linear
        velocities by exp(-2 dt W). Explicit Euler would inflate |v_rel| every step (the
        force is gyroscopic) and pump energy and angular momentum into a spinning body;
        the rotation keeps |v_rel| and sum m v_rel = 0 exactly."""
        Rc = exp_so3(-2.0 * self.dt * gm[2])
        Q = Q_rel.copy()
        lin = self.layout.lin_index
        Q[lin] = Q_rel[lin] @ Rc.T
        if self.F:
            Q[self.S:] = self._full_free(self._full_expand(Q_rel[self.S:]) @ Rc.T)
        return Q

    # ------------------------------------------------------------------ positions
    def positions_of(self, ids, q=None, frames=None, x_full=None):
        """World positions (len(ids), 3) of the given global vertex ids (reconstruct.py)."""
        return reconstruct.positions(self.layout, ids, self.q if q is None else q,
                                     self.frames if frames is None else frames,
                                     self.x_full if x_full is None else x_full)

    def watch(self, ids):
        """Kept for the Simulator's interface: positions_of is one compiled pass for any ids."""

    def vertex_positions(self):
        return self.positions_of(np.arange(len(self.body.vertices)))

    def vertex_velocities(self):
        """World velocities (n_verts, 3): v + w x (x - c) + R U qd, or the full-space ones."""
        return reconstruct.velocities(self.layout, self.vertex_positions(), self.qd, self.frames, self.v_full)

    # ------------------------------------------------------------------ forces
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
        t2 = time.perf_counter()
        self.timing = {"domain_ms": 1e3 * (t1 - t0), "coupling_ms": 1e3 * (t2 - t1)}
        return G, K_ss, K_sI, K_ff, energy, J, x_I

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

    def _external(self, f_ext, gravity, frames, q):
        """J^T f_ext + gravity at the step start (n_gen,).

        Only vertices that carry a load are reconstructed. Gravity is in closed form: on a
        subspace domain it is m g on the frame, (sum_l m_l U_l)^T R^T g on the modes (zero
        for a free domain, whose basis is mass-orthogonal to translations) and no torque
        about the mass centre.
        """
        L = self.layout
        Fext = np.zeros(self.n_gen)
        loaded, f_loaded = sparse_loads(f_ext)
        g = np.zeros(3) if gravity is None else np.asarray(gravity, dtype=np.float64)
        modal = np.einsum("dia,di->da", L.mass_moment, np.einsum("dji,j->di", frames.R, g))
        force = np.zeros((L.D, 3))
        torque = np.zeros((L.D, 3))
        rows = L.vertex_row[loaded]
        sub = rows >= 0
        if sub.any():
            rows, fk = rows[sub], f_loaded[sub]
            k = L.row_domain[rows]
            local = np.einsum("li,lij->lj", fk, frames.R[k])             # R^T f per vertex
            np.add.at(modal, k, np.einsum("lia,li->la", L.U[rows], local))
            x = self.positions_of(loaded[sub], q, frames)
            np.add.at(force, k, fk)
            np.add.at(torque, k, cross(x - frames.c[k], fk))
        Fext[L.q_index[L.mask]] = modal[L.mask]
        mv = L.movers
        Fext[L.lin_index] = L.total_mass[mv, None] * g + force[mv]
        Fext[L.ang_index] = torque[mv]
        if self.F:
            Fext[self.S:] = self._ff_mass * g[self._ff_axis]
            dof = self.ff_pattern.free_dof[3 * loaded[:, None] + np.arange(3)]     # (k, 3), -1: not full-space
            Fext[self.S + dof[dof >= 0]] += f_loaded[dof >= 0]
        return Fext

    def _mass_blocks(self, frames, predicted=False):
        """Mgen's subspace part (S, S) dense. predicted=True puts each domain's inertia at
        the rotation exp(dt w) R it will have after the step: the angular rows are in
        momentum form I(t + dt) w' = I(t) w + dt tau, which conserves angular momentum
        where an explicit gyroscopic term -w x I w gains it."""
        L = self.layout
        mv = L.movers
        M = np.zeros((self.S, self.S))
        modal = L.q_index[L.mask]
        M[modal, modal] = 1.0
        if not len(mv):
            return M
        M[L.lin_index, L.lin_index] = L.total_mass[mv, None]
        R = L.predicted_rotations(frames.R[mv], frames.w[mv], self.dt) if predicted else frames.R[mv]
        M[L.ang_index[:, :, None], L.ang_index[:, None, :]] = R @ L.inertia(self.q)[mv] @ R.transpose(0, 2, 1)
        return M

    def _fictitious_matrices(self, frames):
        """Coriolis C and centrifugal stiffness K_cf (D, r_max, r_max) on each domain's q
        rows at the step start (omega = R^T w; zero for a fixed domain): U^T f_fc = C qd +
        K_cf q + (terms free of q and qd), C[a, b] = 2 W[a, b] . omega (skew, W is
        antisymmetric in a, b) and K_cf = |omega|^2 I - omega^T B2 omega (symmetric positive
        semi-definite). Padded rows and columns are zero."""
        L = self.layout
        omega = np.einsum("dji,dj->di", frames.R, frames.w) * L.movable[:, None]
        C = 2.0 * np.einsum("dabk,dk->dab", L.W, omega)
        eye = L.mask[:, :, None] & np.eye(L.r_max, dtype=bool)
        Kc = ((omega * omega).sum(1)[:, None, None] * eye * L.movable[:, None, None]
              - omega_B2_omega(L.B2, omega))
        return C, Kc

    def _modal_coriolis_rotate(self, C, Q):
        """Exact flow of qd' = C qd over dt on the q rows (Mgen is I there): qd <- exp(dt C) qd,
        a rotation because C is skew, so the Coriolis force does no work, as in the continuum
        (explicit Euler multiplies |qd| by sqrt(1 + dt^2 |C|^2) per step). C (D, r_max, r_max)
        from _fictitious_matrices; a fixed domain's block is zero, its exp the identity."""
        L = self.layout
        Q = Q.copy()
        qd = np.einsum("dab,db->da", sla.expm(self.dt * C), L.gather(Q))
        Q[L.q_index[L.mask]] = qd[L.mask]
        return Q

    def _explicit_terms(self, frames, q, qd, coriolis=True):
        """Fictitious forces (q rows) at the step start; the gyroscopic term lives in the
        momentum form of the angular rows (see _mass_blocks). coriolis=False leaves out the
        Coriolis term (the implicit treatment rotates qd instead)."""
        L = self.layout
        F = np.zeros(self.n_gen)
        if not len(L.movers):
            return F                     # fixed frames: no fictitious forces
        omega = np.einsum("dji,dj->di", frames.R, frames.w)
        alpha = np.einsum("dji,dj->di", frames.R, frames.w - frames.w_prev) / self.dt
        f = fictitious_forces(L, q, qd if coriolis else np.zeros_like(qd), omega, alpha)
        rows = L.mask & L.movable[:, None]
        F[L.q_index[rows]] = f[rows]
        return F

    # ------------------------------------------------------------------ linear algebra
    def _system(self, M_ss, K_ss, K_sI, K_ff, D):
        """A = Mgen + dt Dgen + dt^2 K as (dense A_ss, dense A_sI, sparse-data A_ff)."""
        dt = self.dt
        A_ss = M_ss + dt * D[0] + dt * dt * K_ss
        A_sI = dt * D[1] + dt * dt * K_sI if self.F else None
        A_ff = self.M_ff + dt * D[2] + dt * dt * K_ff if self.F else None
        return A_ss, A_sI, A_ff

    def _solve(self, A_ss, A_sI, A_ff, rhs):
        t0 = time.perf_counter()
        if self.F == 0 and self.unsymmetric:
            lu = sla.lu_factor(A_ss, check_finite=False)
            self._resolve = lambda b: sla.lu_solve(lu, b, check_finite=False)
            t1 = time.perf_counter()
            x = sla.lu_solve(lu, rhs, check_finite=False)
        elif self.F == 0:
            try:
                self.block_solver.factor(A_ss)
                self._resolve = self.block_solver.solve
            except NotPositiveDefinite:
                # Large compression (or a centrifugal stiffness) can make A indefinite; LU
                # still gives the Newton step of the linearised system. Its result is checked
                # by the Simulator's stability guard (mdss_ros/guard.py), which rolls the step
                # back and retries with more Newton iterations and smaller dt (A = M + dt^2 K
                # is positive definite for small enough dt) if it diverges, and counts the
                # accepted indefinite steps (stats "guard_indefinite_steps").
                lu = sla.lu_factor(A_ss, check_finite=False)
                self._resolve = lambda b: sla.lu_solve(lu, b, check_finite=False)
                self._indefinite = True
            t1 = time.perf_counter()
            x = self._resolve(rhs)
        else:
            cols = self.iface_full_cols
            B = sp.csr_matrix((np.ravel(A_sI), (np.repeat(np.arange(self.S), len(cols)), np.tile(cols, self.S))),
                              shape=(self.S, self.F))
            A = sp.bmat([[sp.csr_matrix(A_ss), B], [B.T, self.ff_pattern.matrix(A_ff)]], format="csr")
            try:
                self.sparse_solver.factor(A)
                self._resolve = self.sparse_solver.solve
            except NotPositiveDefinite:
                lu = spla.splu(A.tocsc())
                self._resolve = lu.solve
                self._indefinite = True
            t1 = time.perf_counter()
            x = self._resolve(rhs)
        t2 = time.perf_counter()
        self.timing["factor_ms"] = self.timing.get("factor_ms", 0.0) + 1e3 * (t1 - t0)
        self.timing["solve_ms"] = self.timing.get("solve_ms", 0.0) + 1e3 * (t2 - t1)
        return x

    def _matvec(self, A_ss, A_sI, A_ff, Q):
        out = np.zeros_like(Q)
        out[:self.S] = A_ss @ Q[:self.S]
        if self.F:
            cols = self.iface_full_cols
            out[:self.S] += A_sI @ Q[self.S:][cols]
            out[self.S:] = self.ff_pattern.matrix(A_ff) @ Q[self.S:]
            np.add.at(out[self.S:], cols, A_sI.T @ Q[:self.S]) if len(cols) else None
        return out

    # ------------------------------------------------------------------ step
    def _contact_rows(self, contact, gm):
        """Candidate contacts of the surface: (vertices, C (m, n_gen), phi_eff (m,), normals, which,
        friction), or None. C = dt n^T J_l; under a co-rotating step the rigid part of the
        vertex velocity, V + W x (x - C), is a constant folded into phi_eff. friction is
        None (every collider frictionless) or (C3 (3m, n_gen) rows n, t1, t2 per contact,
        g3 (3m,) their constant part (phi_eff, minus the collider's tangential displacement,
        the rigid velocity's share), mu (m,) static or kinetic by the last step's slip,
        tangents (m, 2, 3), rigid3 (3m,) the rigid share alone, the last step's forces as
        a first guess (m, 3) or None), as in BackwardEuler._contact_rows (friction.py)."""
        from ..contact.friction import coefficients, collider_slip, effective_mu, tangent_basis, warm_start
        from ..contact.unilateral import find_contacts, find_triangle_contacts
        ids = contact["vertices"]
        x = self.positions_of(ids)
        rows, which, phi, normals = find_contacts(contact["colliders"], x, x, contact["margin"])
        # Sphere-face contacts enter as weighted copies of their three corners' rows.
        weights = np.ones(len(rows))
        group = np.arange(len(rows))
        n_all = len(self.vertex_domain)
        key = ids[rows] + n_all * which                 # a row's identity from step to step
        if contact.get("triangles") is not None:
            t_idx, bary, t_which, t_phi, t_n = find_triangle_contacts(contact["colliders"], x,
                                                                      contact["triangles"], contact["margin"])
            if len(t_idx):
                base = len(rows)
                rows = np.concatenate([rows, contact["triangles"][t_idx].ravel()])
                weights = np.concatenate([weights, bary.ravel()])
                group = np.concatenate([group, base + np.repeat(np.arange(len(t_idx)), 3)])
                which = np.concatenate([which, np.repeat(t_which, 3)])
                phi = np.concatenate([phi, t_phi])
                normals = np.concatenate([normals, np.repeat(t_n, 3, axis=0)])
                # Face keys follow every vertex key: n_all n_col + t n_col + c for triangle t, collider c.
                n_col = len(contact["colliders"])
                key = np.concatenate([key, n_all * n_col + t_idx * n_col + t_which])
        if len(rows) == 0:
            return None
        rough = coefficients(contact, which) is not None    # else frictionless: one row per contact
        verts = ids[rows]
        xv = x[rows]
        # group is non-decreasing (vertex rows, then three corners per face): one contact per run.
        starts = np.flatnonzero(np.r_[True, group[1:] != group[:-1]])
        tangents = None
        if not rough:
            C = self._rows_along(normals[:, None, :] * weights[:, None, None], verts, xv, starts)
        else:
            # Rows along n, t1, t2 at once; the normal rows are every third of them.
            tangents = tangent_basis(normals)                                   # (corner rows, 2, 3)
            dirs = np.concatenate([normals[:, None, :], tangents], axis=1) * weights[:, None, None]
            C3 = self._rows_along(dirs, verts, xv, starts)
            C = C3[0::3] if sp.issparse(C3) else np.ascontiguousarray(C3[0::3])
        norms = (np.sqrt(np.asarray(C.multiply(C).sum(axis=1)).ravel()) if sp.issparse(C)
                 else np.linalg.norm(C, axis=1))
        verts, which, normals, xv = verts[starts], which[starts], normals[starts], xv[starts]  # a corner per contact
        tangents = None if tangents is None else tangents[starts]
        # Vertices that cannot move (pins: zero rows of U in a fixed domain) cannot be
        # pushed out; their constraints would be infeasible, so they are not contacts.
        movable = norms > 1e-12 * max(float(norms.max()), 1e-300)
        if not movable.all():
            verts, C, phi, normals, which, xv = (verts[movable], C[movable], phi[movable], normals[movable],
                                                 which[movable], xv[movable])
            key = key[movable]
            if tangents is not None:
                tangents = tangents[movable]
                C3 = C3[(3 * np.flatnonzero(movable)[:, None] + np.arange(3)).ravel()]
            if len(verts) == 0:
                return None
        phi_eff = phi.copy()
        self._contact_rigid = np.zeros(len(phi))          # dt n . (rigid velocity) per row
        if gm is not None:
            Cg, Vg, Wg = gm[:3]
            rigid_v = Vg + cross(Wg, xv - Cg)
            self._contact_rigid = self.dt * np.einsum("li,li->l", normals, rigid_v)
            phi_eff += self._contact_rigid
        self._contact_row_keys = key
        fric = None
        if rough:
            n_col = len(contact["colliders"])
            keys = verts * n_col + which
            mu = effective_mu(*coefficients(contact, which), keys, self.contact, n_col)
            g3 = np.zeros((len(verts), 3))
            g3[:, 0] = phi_eff
            g3[:, 1:] = collider_slip(contact, which, xv, tangents)
            rigid3 = np.zeros((len(verts), 3))                 # dt (n, t1, t2) . (rigid velocity)
            rigid3[:, 0] = self._contact_rigid
            if gm is not None:
                rigid3[:, 1:] = self.dt * np.einsum("lij,lj->li", tangents, rigid_v)
                g3[:, 1:] += rigid3[:, 1:]
            fric = (C3, g3.ravel(), mu, tangents, rigid3.ravel(), warm_start(self.contact, keys, tangents, n_col))
        return verts, C, phi_eff, normals, which, fric

    def _rows_along(self, dirs, verts, xv, starts):
        """Constraint rows (m r, n_gen), row l r + j = dt d^T J at contact l along its j-th
        direction: dirs (k, r, 3) per corner row (weighted: a face point's corners carry
        their barycentric weights), verts (k,) vertex ids, xv (k, 3) their positions, starts
        (m,) the first corner row of each contact (corner rows of a contact are adjacent).
        Dense, or CSR when the model has full-space domains (n_gen large, rows sparse)."""
        L = self.layout
        k, r = dirs.shape[:2]
        vrow = L.vertex_row[verts]
        m = len(starts)
        if not self.F:
            # Every vertex is in a subspace domain: one compiled pass (reconstruct.py).
            row_of = np.searchsorted(starts, np.arange(k), side="right") - 1
            out = np.zeros((m * r, self.n_gen))
            reconstruct.contact_rows_kernel(np.ascontiguousarray(dirs), vrow, L.U, L.row_domain, self.frames.R,
                                            self.frames.c, np.ascontiguousarray(xv), L.q_index, L.mask,
                                            self._frame_cols, row_of, self.dt, out)
            return out
        blocks = []                                          # (corner rows, direction, columns, values)
        sel = np.flatnonzero(vrow >= 0)
        if sel.size:
            # d^T R U_l = (R^T d)^T U_l per corner, into its domain's modal columns (padding
            # columns dropped); a movable domain adds [d, (x - c) x d] on its frame's columns.
            dom = L.row_domain[vrow[sel]]
            d = dirs[sel]                                                              # (s, r, 3)
            vals = np.einsum("lri,lib->lrb", np.einsum("lrj,lji->lri", d, self.frames.R[dom]), L.U[vrow[sel]])
            ok = np.broadcast_to(L.mask[dom][:, None, :], vals.shape)
            shape = vals.shape
            blocks.append((np.broadcast_to(sel[:, None, None], shape)[ok],
                           np.broadcast_to(np.arange(r)[None, :, None], shape)[ok],
                           np.broadcast_to(L.q_index[dom][:, None, :], shape)[ok], vals[ok]))
            mover = np.full(L.D, -1, dtype=np.int64)
            mover[L.movers] = np.arange(len(L.movers))
            mv = mover[dom] >= 0
            if mv.any():
                cols = np.hstack([L.lin_index, L.ang_index])[mover[dom[mv]]]          # (s, 6)
                arm = (xv[sel[mv]] - self.frames.c[dom[mv]])[:, None, :]
                frame_vals = np.concatenate([d[mv], cross(np.broadcast_to(arm, d[mv].shape), d[mv])], axis=2)
                shape = frame_vals.shape                                               # (s, r, 6)
                blocks.append((np.broadcast_to(sel[mv][:, None, None], shape).ravel(),
                               np.broadcast_to(np.arange(r)[None, :, None], shape).ravel(),
                               np.broadcast_to(cols[:, None, :], shape).ravel(), frame_vals.ravel()))
        full = np.flatnonzero(vrow < 0)
        if full.size:
            dofs = self.full_dof_of_vertex[verts[full]]
            okf = dofs >= 0
            f_rows = full[okf]
            shape = (len(f_rows), r, 3)
            blocks.append((np.broadcast_to(f_rows[:, None, None], shape).ravel(),
                           np.broadcast_to(np.arange(r)[None, :, None], shape).ravel(),
                           np.broadcast_to((self.S + 3 * dofs[okf, None] + np.arange(3))[:, None, :], shape).ravel(),
                           dirs[f_rows].ravel()))
        # A full-space domain makes n_gen large and its rows 3-sparse: C as CSR
        # (duplicates, a face's corners, are summed on construction).
        row_of = np.searchsorted(starts, np.arange(k), side="right") - 1
        r_idx = row_of[np.concatenate([b[0] for b in blocks])] * r + np.concatenate([b[1] for b in blocks])
        c_idx = np.concatenate([b[2] for b in blocks])
        values = np.concatenate([b[3] for b in blocks])
        return sp.csr_matrix((self.dt * values, (r_idx, c_idx)), shape=(m * r, self.n_gen))

    def _contact_solve(self, rows, Q, dQ):
        """Correct a Newton step for contact: C (Q + dQ') + phi >= 0 via the LCP (unilateral.py),
        or with friction the Coulomb problem on three rows per contact (friction.py).
        Returns (dQ + correction, lam (m,) or (m, 3))."""
        from ..contact.friction import frictional_correction
        from ..contact.unilateral import contact_correction
        verts, C, phi, _, which, friction = rows
        # The LCP's first guess: the rows active in the last Newton iteration, or in the last
        # two steps (a resting or pressed body keeps most of its contacts, and a coarse patch
        # under a held collider can swap its load between vertex and face rows every other
        # step). It saves solves and pivots only; the answer does not depend on it.
        keys = self._contact_row_keys
        history = self._contact_history                          # active keys per step, newest last
        same_step = self._contact_rows_seen is rows
        lam_n = None if not same_step else (self._contact_lam if friction is None else self._contact_lam[:, 0])
        if same_step:
            hint = lam_n > 0
        else:
            hint = np.isin(keys, np.concatenate(history)) if history else None
        # Rows through a few modes per domain are often dependent: regularise (unilateral.py).
        if friction is None:
            lam, corr, info = contact_correction(self._resolve, C, C @ (Q + dQ) + phi, regularize=1e-9, hint=hint)
            active = lam > 0
        else:
            C3, g3, mu = friction[:3]
            guess = self._contact_lam if same_step else friction[5]
            lam, corr, info = frictional_correction(self._resolve, C3, C3 @ (Q + dQ) + g3, mu, regularize=1e-9,
                                                    hint=hint if guess is None else None, lam_guess=guess)
            active = lam[:, 0] > 0
        self._contact_info = info
        self._contact_history = (history[:-1] if same_step else history[-1:]) + [keys[active]]
        self._contact_lam, self._contact_rows_seen = lam, rows
        return dQ + corr, lam

    @staticmethod
    def _contact_force(rows, lam):
        """C^T lam (n_gen,): the contact forces as generalised forces, frictional or not."""
        return rows[1].T @ lam if rows[5] is None else rows[5][0].T @ lam.ravel()

    def step(self, f_ext, gravity=None, contact=None, options=None):
        """Advance by dt under per-vertex loads f_ext (n_verts, 3) and gravity (3,); contact
        as in BackwardEuler.step; options: a StepOptions for this step only (dt, Newton
        iterations, implicit fictitious forces). The step's terms read dt, the iteration
        count and the fictitious treatment from the model, so they are set for the duration
        of the call and always put back."""
        if options is None:
            return self._step(f_ext, gravity, contact)
        saved = (self.dt, self.newton_iterations, self.fictitious)
        if options.dt:
            self.dt = float(options.dt)
        if options.newton_iterations:
            self.newton_iterations = max(self.newton_iterations, int(options.newton_iterations))
        if options.fictitious:
            self.fictitious = options.fictitious
        try:
            return self._step(f_ext, gravity, contact)
        finally:
            self.dt, self.newton_iterations, self.fictitious = saved

    def _step(self, f_ext, gravity, contact):
        t0 = time.perf_counter()
        dt = self.dt
        gm = self._global_motion()
        if gm is not None:
            C, V, W, L = gm
            # Torque of the loads about the mass centre; uniform gravity has none.
            loaded, f_loaded = sparse_loads(f_ext)
            tau = cross(self.positions_of(loaded) - C, f_loaded).sum(0)
            gm = (C, V, W, (L + dt * tau) / (1.0 + dt * self.alpha))
        self._dW = 0.0
        self._indefinite = False
        # The applied loads as generalised forces at the step start (no gravity: it is a
        # potential); their work over the step is dt F_app . Q' (reported for the guard).
        F_app = self._external(f_ext, None, self.frames, self.q)
        base = (self.q.copy(), self.frames.copy(), self._full_rows(self.x_full), gm)
        Qn = self.get_Q()
        if gm is not None:
            Qn = self._coriolis_rotate(gm, Qn - self._rigid_Q(gm))
        implicit = self.fictitious == "implicit"
        if implicit:
            coriolis, centrifugal = self._fictitious_matrices(self.frames)
            Qn = self._modal_coriolis_rotate(coriolis, Qn)
        (G, K_ss, K_sI, K_ff, energy, J, x_I), timing = self._start_evaluation(take=True)
        M_ss = self._mass_blocks(self.frames, predicted=True)
        D = (self.alpha * M_ss + self.beta * K_ss,
             self.beta * K_sI if self.F else None,
             self.alpha * self.M_ff + self.beta * K_ff if self.F else None)
        if implicit:
            # Centrifugal force K_cf q at the end of the step: K_cf q_n (explicit part, in Fn)
            # + dt K_cf qd', a velocity term, hence in D (it enters A as -dt^2 K_cf).
            L = self.layout
            D0 = D[0].copy()
            D0[L.block_rows, L.block_cols] -= dt * centrifugal[L.block_valid]
            D = (D0,) + D[1:]
        Fn = self._external(f_ext, gravity, self.frames, self.q) + \
            self._explicit_terms(self.frames, self.q, self.qd, coriolis=not implicit)
        if gm is not None:
            Fn = Fn + self._global_fictitious(gm)
        Mgen = (M_ss, np.zeros_like(K_sI) if self.F else None, self.M_ff if self.F else None)
        # Momentum at the step start: Mgen(t) (Qn + Q_W) - Mgen(t + dt) Q_W, where Q_W carries
        # the global W on the angular rows (the angular rows hold w - W when gm is used).
        Q_W = self._rigid_Q((np.zeros(3), np.zeros(3), gm[2]), angular_only=True) if gm is not None else 0.0
        Mgen0 = (self._mass_blocks(self.frames),) + Mgen[1:]
        p0 = self._matvec(*Mgen0, Qn + Q_W) - self._matvec(*Mgen, Q_W + np.zeros_like(Qn))

        def residual(Q, G_k):
            return self._matvec(*Mgen, Q) - p0 + dt * (self._matvec(*D, Q) + G_k - Fn)

        t_c = time.perf_counter()
        contact_rows = self._contact_rows(contact, gm) if contact else None
        contact_s = time.perf_counter() - t_c
        lam = None
        if contact_rows is not None and self.scheme == "two_step":
            raise SceneError("contact is available with the one-step scheme only")
        r0 = r_last = 0.0
        if self.scheme == "two_step":
            Q = self._two_step(M_ss, K_ss, D, p0, G, Fn)
            iterations = 1
        else:
            Q = np.zeros_like(Qn)
            iterations, cuts = 0, 0
            r = residual(Q, G)
            r0 = r_last = float(np.linalg.norm(r))
            for it in range(self.newton_iterations):
                A = self._system(M_ss, K_ss, K_sI, K_ff, D)
                dQ = self._solve(*A, -r)
                if contact_rows is not None:
                    t_c = time.perf_counter()
                    dQ, lam = self._contact_solve(contact_rows, Q, dQ)
                    contact_s += time.perf_counter() - t_c
                    if it == 0:
                        # A body at rest pushed only by a collider has r0 = 0: measure the
                        # tolerance against the contact forces' size instead.
                        r0 = max(r0, float(np.linalg.norm(self._contact_force(contact_rows, lam))))
                iterations += 1
                step_len = 1.0
                if self.newton_iterations > 1 and self.line_search and not self.unsymmetric and contact_rows is None:
                    phi0 = self._potential(Q, p0, Mgen, D, Fn, energy)
                    slope = float(r @ dQ)
                    while step_len > 1e-4:
                        trial = Q + step_len * dQ
                        e_t = self._energy_at(trial, base)
                        if self._potential(trial, p0, Mgen, D, Fn, e_t) <= phi0 + 1e-4 * step_len * slope:
                            break
                        step_len *= 0.5
                        cuts += 1
                Q = Q + step_len * dQ
                if it + 1 == self.newton_iterations:
                    break
                q, _, frames, x_full, _ = self._predict(Q, base)
                G, K_ss, K_sI, K_ff, energy, _, _ = self._evaluate(q, frames, x_full)
                r = residual(Q, G)
                # With contact the converged residual is the contact force C^T lam, not zero.
                r_c = r - self._contact_force(contact_rows, lam) if contact_rows is not None else r
                r_last = float(np.linalg.norm(r_c))
                if r_last <= self.tolerance * max(r0, 1e-300):
                    break
        q, qd, frames, x_full, v_full = self._predict(Q, base)
        self.q, self.qd, self.frames = q, qd, frames
        if self.F:             # before the contact outputs, which read full-space positions
            self.x_full, self.v_full = x_full, v_full
        self.contact = None
        contact_work = 0.0
        if contact_rows is not None:
            verts, _, _, normals, which, friction = contact_rows
            lam = self._contact_lam if self._contact_rows_seen is contact_rows else np.zeros(len(verts))
            lam_n = lam if lam.ndim == 1 else lam[:, 0]
            pts = self.positions_of(verts)
            depth = np.zeros(len(verts))
            active = lam_n > 0
            for c_idx, col in enumerate(contact["colliders"]):
                sel = np.flatnonzero(active & (which == c_idx))
                if sel.size:
                    depth[sel] = np.maximum(-col.signed_distance(pts[sel])[0], 0.0)
            w = self._contact_info.get("w") if self._contact_rows_seen is contact_rows else None
            self.contact = contact_forces(verts, normals, which, lam, None if friction is None else friction[3],
                                          pts, depth, w, self.dt)
            # Work of the contact forces over the step in the step's own terms (the guard's
            # energy ledger): the generalised force J^T n lam times dt Q', that is lam . C Q'
            # (C holds dt), plus the rigid velocity a co-rotating step folds into phi.
            if friction is None:
                contact_work = float(lam @ (contact_rows[1] @ Q + self._contact_rigid))
            else:
                contact_work = float(lam.ravel() @ (friction[0] @ Q + friction[4]))
        self.last = {"elastic": energy}
        total = 1e3 * (time.perf_counter() - t0)
        residual_ratio = r_last / r0 if r0 > 0 else 0.0
        external_work = dt * float(F_app @ self.get_Q())
        self.stats = {"newton_iterations": iterations, "residual": residual_ratio, "external_work": external_work,
                      "contact_work": contact_work,
                      "contact_ms": 1e3 * contact_s,      # candidate search, rows, LCP (inside model_ms)
                      "domain_ms": timing["domain_ms"],
                      "coupling_ms": timing["coupling_ms"], "factor_ms": self.timing.get("factor_ms", 0.0),
                      "solve_ms": self.timing.get("solve_ms", 0.0), "model_ms": total,
                      "angular_momentum_correction": self._dW,
                      "indefinite_system": self._indefinite,
                      "domains": len(self.subspace) + len(self.full)}
        if contact_rows is not None:          # candidates and rows the LCP solved for (unilateral.py)
            self.stats.update(contact_stats(self._contact_info))
        self.timing = {}
        return self.stats

    def _potential(self, Q, p0, Mgen, D, Fn, elastic):
        """Incremental potential whose gradient is the residual: 1/2 Q.Mgen Q - p0.Q
        + dt/2 Q.D Q + E(s(Q)) - dt Fn.Q."""
        return (0.5 * Q @ self._matvec(*Mgen, Q) - p0 @ Q + 0.5 * self.dt * Q @ self._matvec(*D, Q)
                + elastic - self.dt * Fn @ Q)

    def _energy_at(self, Q, base):
        q, _, frames, x_full, _ = self._predict(Q, base)
        return self._evaluate(q, frames, x_full, want_hessian=False)[4]

    def _two_step(self, M_ss, K_ss, D, p0, G, Fn):
        """The paper's foil: rigid DOFs with deformation frozen, then deformation with
        frames frozen: block Gauss-Seidel on the one-step system."""
        if self.F:
            raise SceneError("the two-step scheme is available for subspace domains only")
        dt = self.dt
        A = M_ss + dt * D[0] + dt * dt * K_ss
        b = p0 + dt * (Fn - G)
        Qn = np.linalg.solve(M_ss, p0)         # the step-start velocities the paper freezes
        rigid = np.zeros(self.S, dtype=bool)
        rigid[self.layout.lin_index] = True
        rigid[self.layout.ang_index] = True
        Q = Qn.copy()
        rr, dd = np.flatnonzero(rigid), np.flatnonzero(~rigid)
        if rr.size:
            Q[rr] = sla.solve(A[np.ix_(rr, rr)], b[rr] - A[np.ix_(rr, dd)] @ Qn[dd], assume_a="pos")
        Q[dd] = sla.solve(A[np.ix_(dd, dd)], b[dd] - A[np.ix_(dd, rr)] @ Q[rr], assume_a="pos")
        return Q

    def system_matrix(self):
        """The unified matrix A (n_gen, n_gen) at the current state, dense (diagnostics, tests)."""
        G, K_ss, K_sI, K_ff, _, _, _ = self._evaluate(self.q, self.frames, self.x_full)
        M_ss = self._mass_blocks(self.frames, predicted=True)
        D = (self.alpha * M_ss + self.beta * K_ss, self.beta * K_sI if self.F else None,
             self.alpha * self.M_ff + self.beta * K_ff if self.F else None)
        A_ss, A_sI, A_ff = self._system(M_ss, K_ss, K_sI, K_ff, D)
        if not self.F:
            return A_ss
        A = np.zeros((self.n_gen, self.n_gen))
        A[:self.S, :self.S] = A_ss
        A[:self.S, self.S + self.iface_full_cols] = A_sI
        A[self.S + self.iface_full_cols, :self.S] = A_sI.T
        A[self.S:, self.S:] = self.ff_pattern.matrix(A_ff).toarray()
        return A

    # ------------------------------------------------------------------ outputs
    def elastic_energy(self):
        # The evaluation at the current state is the one the next step starts from: the
        # stability guard's energy check after a step costs the next step nothing.
        return self._start_evaluation()[0][4]

    def _start_evaluation(self, take=False):
        """((G, K_ss, K_sI, K_ff, energy, J, x_I), timing) of _evaluate at the current state,
        computed once per state: the cache holds the state objects it was computed from
        (every step and set_state replace them) and is dropped when a step takes it."""
        # Cutting replaces _full_alive: the forces changed, so it is part of the key.
        state = (self.q, self.frames, self.x_full, self._full_alive)
        c = self._start_eval
        if c is None or not all(a is b for a, b in zip(c[0], state)):
            result = self._evaluate(self.q, self.frames, self.x_full)
            c = (state, result, dict(self.timing))
        self._start_eval = None if take else c
        return c[1], c[2]

    def kinetic_energy(self):
        v = self.vertex_velocities()
        return 0.5 * float((self.vertex_mass * (v * v).sum(1)).sum())

    def guard_measure(self, gravity, check_inversion=True):
        """What the stability guard reads from the state (guard.Measure), in the reduced
        coordinates so it costs nothing that grows with the mesh: kinetic energy exactly,
        per free domain 1/2 M |v|^2 + 1/2 w'^T I(q) w' + w' . (q^T W qd) + 1/2 |qd|^2 (the
        basis is mass-orthonormal and mass-orthogonal to rigid motion, W the fictitious
        tensor sum m u_a x u_b); elastic energy from the model's forces (cubature); gravity
        potential from the mass moments; an upper bound of vertex speeds,
        |v| + |w| (rho + sigma |q|) + sigma |qd| (rho the largest rest radius, sigma the
        largest per-vertex basis norm); inverted elements among those the forces sample
        (cubature samples, coupling and full-space elements)."""
        from ..state_measure import Measure
        g = np.asarray(gravity, dtype=np.float64)
        fr = self.frames
        with np.errstate(all="ignore"):
            L = self.layout
            out = np.empty(4)
            frame_measure(self.q, self.qd, fr.c, fr.R, fr.v, fr.w, L.movable, L.total_mass, L.inertia0, L.B1,
                          L.B2, L.W, L.rho, L.sigma, L.mass_r, L.mass_moment, g, out)
            # x_full / v_full hold every vertex but only full-space rows are state: checking
            # them on a model without full-space domains was a third of this measure.
            finite = bool(out[0]) and (not self.F or (np.isfinite(self.x_full).all()
                                                      and np.isfinite(self.v_full).all()))
            if not finite:
                return Measure(None, None, np.nan, np.nan, np.nan, 0, False, speed=np.inf)
            kinetic, grav, speed = float(out[1]), float(out[2]), float(out[3])
            if self.F:
                m = np.where(self.is_full_vertex, self.vertex_mass, 0.0)
                kinetic += 0.5 * float((m * (self.v_full * self.v_full).sum(1)).sum())
                grav -= float((m * (self.x_full @ g)).sum())
                speed = max(speed, float(np.sqrt((self.v_full * self.v_full).sum(1).max())))
            try:
                elastic = float(self.elastic_energy())
            except (ArithmeticError, ValueError, RuntimeError):
                elastic = np.nan
            inverted = self._guard_inverted() if check_inversion else 0
        finite = bool(np.isfinite([kinetic, elastic, grav, speed]).all())
        return Measure(None, None, kinetic, elastic, grav, inverted, finite, speed=speed)

    def mean_motion(self):
        """(total mass M, mass-centre velocity V (3,)) for the guard's energy projection;
        V = 0 for a body held by pins (its momentum is not conserved, scale all motion)."""
        gm = self._global_motion()
        m = float(self.layout.total_mass.sum()) + float(self.vertex_mass[self.is_full_vertex].sum())
        return m, (gm[1].copy() if gm is not None else np.zeros(3))

    def scale_relative_motion(self, s, V):
        """Energy projection (guard.project_energy): v <- V + s (v - V) on frames and
        full-space vertices, w <- s w, qd <- s qd. The kinetic energy is 1/2 M |V|^2 +
        E_rel with E_rel quadratic in (v - V, w, qd) and no cross term (V is the mass-weighted
        mean, the basis carries no linear momentum), so it becomes 1/2 M |V|^2 + s^2 E_rel;
        linear momentum is kept, angular momentum about the mass centre scales by s.
        Positions are untouched (the cached start evaluation stays valid)."""
        fr = self.frames
        mv = self.movable
        fr.v = np.where(mv[:, None], V + s * (fr.v - V), fr.v)
        fr.w = np.where(mv[:, None], s * fr.w, fr.w)
        # The Euler force reads (w - w_prev) / dt: scale both so the projection is no jolt.
        fr.w_prev = np.where(mv[:, None], s * fr.w_prev, fr.w_prev)
        self.qd = s * self.qd
        if self.F:
            self.v_full = np.where(self.is_full_vertex[:, None], V + s * (self.v_full - V), 0.0)
            self.v_full[self.body.pinned] = 0.0

    def untangle(self, tets, bisections=8):
        """Last resort of the stability guard for inverted elements a subspace cannot undo
        (guard.py, `untangle_after`): shrink the deformation towards a rigid placement of
        the rest shape until no element of tets (m, 4) is inverted. With s in [0, 1]:
        q <- s q, qd <- s qd, each frame's rotation slerped and its centre (and the
        full-space vertices) moved from the rigid target (s = 0) to where they are (s = 1);
        s is the largest found by bisection. The target is the rest shape for a pinned
        body; for a free one, the rest shape turned by the frames' mass-weighted mean
        rotation about their mass centre, which it keeps: without full-space domains the
        gravity potential and (frame velocities kept, modes carry none) the linear
        momentum do not change.
        Returns s (1.0: nothing inverted), or None if even s = 0 leaves an inverted element."""
        from ..state_measure import inverted_tets
        from ..rotations import exp_so3, quat_from_matrix
        q0, qd0, fr0, xf0 = self.q, self.qd, self.frames, self.x_full
        m = self.layout.total_mass
        cbar = np.array([dom.cbar for dom in self.subspace]).reshape(-1, 3)
        if len(self.body.pinned) or not self.movable.all():
            R_t, c_mean, cbar_mean = np.eye(3), np.zeros(3), np.zeros(3)
        else:
            u, _, vt = np.linalg.svd(np.einsum("k,kij->ij", m, fr0.R))
            R_t = u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt
            c_mean, cbar_mean = m @ fr0.c / m.sum(), m @ cbar / m.sum()
        c_t = c_mean + (cbar - cbar_mean) @ R_t.T
        x_t = c_mean + (self.body.vertices - cbar_mean) @ R_t.T
        rotvec = []
        for R in fr0.R:                   # loop over domains (d ~ 10)
            x, y, z, w = quat_from_matrix(R_t.T @ R)
            half = np.arctan2(np.sqrt(x * x + y * y + z * z), w)
            n = np.array([x, y, z])
            rotvec.append(2.0 * half * n / max(np.linalg.norm(n), 1e-300))

        def at(s):
            fr = fr0.copy()
            fr.c = np.where(self.movable[:, None], c_t + s * (fr0.c - c_t), fr0.c)
            for k in np.flatnonzero(self.movable):
                fr.R[k] = R_t @ exp_so3(s * rotvec[k])
            xf = np.where(self.is_full_vertex[:, None], x_t + s * (xf0 - x_t), xf0)
            xf[self.body.pinned] = xf0[self.body.pinned]
            return s * q0, fr, xf

        def inverted(s):
            q, fr, xf = at(s)
            return inverted_tets(self.positions_of(np.arange(len(self.body.vertices)), q, fr, xf), tets)

        if not inverted(1.0):
            return 1.0
        if inverted(0.0):
            return None
        lo, hi = 0.0, 1.0
        for _ in range(bisections):
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if not inverted(mid) else (lo, mid)
        self.q, self.frames, self.x_full = at(lo)
        self.qd = lo * qd0
        self._start_eval = None
        return lo

    def _guard_inverted(self):
        """Inverted elements among those the forces evaluate, without rebuilding vertices
        where it can: a cubature sample's F = I + unvec(G_s q) is at hand in reduced
        coordinates, and the coupling elements' vertices are in the start evaluation of the
        next step (which the guard's energy check has just made)."""
        from ..state_measure import inverted_tets
        n = inverted_samples(self.samples.G, self.q, self.samples.valid) if self.samples is not None else 0
        x_I = None
        if self.coupling_kind == "element":
            c = self._start_eval
            if c is not None and all(a is b for a, b in zip(c[0], (self.q, self.frames, self.x_full, self._full_alive))):
                x_I = c[1][6]
        ids, local = self._guard_tets(coupling=x_I is None)
        if len(ids):
            n += inverted_tets(self.positions_of(ids), local)
        if x_I is not None and len(self.c_elem):
            n += inverted_tets(x_I, self.c_elem)
        return n

    def _guard_tets(self, coupling=True):
        """(vertex ids (k,), tets (m, 4) into them) the guard checks for
        inversion from vertex positions: the elements the forces evaluate that are neither
        cubature samples (_guard_inverted reads those from q) nor, unless `coupling`,
        coupling elements."""
        if self._guard_tet_list.get(coupling) is None:
            parts = []
            for dom in self.subspace:
                fm = dom.forces
                if getattr(fm, "tets", None) is None or len(fm.tets) == 0:
                    continue
                if self.samples is None:
                    parts.append(dom.vertices[fm.tets])
            if self.coupling_kind == "element" and coupling:
                parts.append(self.body.tets[self.c_tets])
            if self.F:
                parts.append(self.body.tets[self.ff_elements])
            tets = np.concatenate(parts).astype(np.int64) if parts else np.zeros((0, 4), np.int64)
            ids, local = np.unique(tets, return_inverse=True)
            self._guard_tet_list[coupling] = (ids, local.reshape(tets.shape))
        return self._guard_tet_list[coupling]

    def domain_poses(self):
        """(d, 7) x y z qx qy qz qw per domain: the frames of subspace domains (all at once,
        scipy's Rotation, w >= 0), a best-fit pose for each full-space domain."""
        out = np.zeros((len(self.domain_kind), 7))
        sub = self.sub_index_of_domain >= 0
        if sub.any():
            k = self.sub_index_of_domain[sub]
            out[sub, :3] = self.frames.c[k]
            out[sub, 3:] = Rotation.from_matrix(self.frames.R[k]).as_quat(canonical=True)
        for fd in self.full:                     # full-space domains: a pose fit each (few)
            from ..fem.full_model import best_fit_pose
            ids = fd.vertices
            out[fd.index] = best_fit_pose(self.body.vertices[ids], self.x_full[ids], self.vertex_mass[ids])
        return out

    def domain_names(self):
        return list(self.partition.names)

    def explain(self):
        """What the model took and why, one line per choice (list of str; `mdss run --explain`).

        Domains (where they came from, which hold pins and so carry no rigid DOFs and no
        fictitious-force terms), the free-body treatment, cubature per domain and interface,
        full-space domains and the linear solver."""
        names = self.partition.names
        dcfg = self.cfg.get("domains") or {"count": 1}
        how = (f"user regions ({', '.join(map(str, dcfg['regions']))})" if "regions" in dcfg
               else "the body's shape: a core and its limbs (model.domains: auto)" if "auto" in dcfg
               else f"METIS split into {dcfg.get('count', 1)} balanced contiguous parts (model.domains.count)")
        lines = [f"reduced model: {len(self.domain_kind)} domains from {how}; {self.n_gen} DOFs "
                 f"({self.S} subspace + {self.F} full-space)"]
        lines += [f"  domains: {note}" for note in self.partition_notes]
        pinned = np.zeros(len(self.body.vertices), dtype=bool)
        pinned[self.body.pinned] = True
        cub = {k: d for k, d in enumerate(self.cubature_info.get("domains", []))}
        for i, (kind, k) in enumerate(self.domain_kind):
            verts = self.partition.domain_vertices[i]
            n_pin = int(pinned[verts].sum())
            head = f"  domain {names[i]}: {len(verts)} vertices, {len(self.partition.domain_elements[i])} elements"
            if kind == "full":
                fd = self.full[k]
                lines.append(f"{head}; FULL SPACE (model.full_space_domains): {fd.n_dofs} DOFs, world frame, "
                             f"no modes or frame" + (f", {n_pin} pinned vertices dropped" if n_pin else ""))
                continue
            dom = self.subspace[k]
            if dom.movable:
                rigid = ("frame + 6 rigid DOFs (no pins); fictitious forces (Coriolis, Euler, "
                         "centrifugal) built from its precomputed tensors")
            else:
                rigid = (f"holds {n_pin} pinned vertices: modes only, no rigid DOFs, no fictitious-force "
                         f"terms (its frame cannot move or rotate)")
            c = cub.get(k)
            elems = (f"cubature {c['samples']} of {c['elements']} elements" if c
                     else f"exact forces over all {len(self.partition.domain_elements[i])} elements")
            lines.append(f"{head}; r = {dom.r} modes; {rigid}; {elems}")
        if not self.full:
            lines.append("full-space domains: none (model.full_space_domains is empty)")
        n_c = len(self.partition.coupling_elements)
        iface = self.cubature_info.get("interface")
        if self.coupling_kind != "element":
            lines.append(f"coupling: springs on the edges of {n_c} coupling elements (model.coupling.kind)")
        elif iface:
            n_s = len(self.c_tets) - int(iface.get("exact_elements", 0))
            lines.append(f"coupling: {n_c} coupling elements; {iface['scheme']} interface cubature: {n_s} weighted "
                         f"samples on {len(iface['interfaces'])} two-domain interfaces, "
                         f"{iface.get('exact_elements', 0)} elements touching 3+ domains exact")
        else:
            lines.append(f"coupling: {n_c} coupling elements evaluated exactly every step "
                         f"(model.cubature.interface: exact)")
        if self.cubature_info.get("samples"):
            src = self.cubature_info.get("training_source", "?")
            lines.append(f"cubature: {self.cubature_info['samples']} samples per domain requested, trained on "
                         f"{self.cubature_info.get('training_poses', '?')} poses from the {src} model"
                         + (" (loaded from the cache)" if self.cubature_info.get("cached") else ""))
        else:
            lines.append("cubature: off (model.cubature.samples: 0): every domain element every step")
        if self.body.pinned.size == 0 and self.movable.all():
            lines.append("free body (no pins): the mean rigid motion is integrated exactly about the mass "
                         "centre and angular momentum is rebalanced each step")
        else:
            lines.append(f"held by {self.body.pinned.size} pinned vertices: no whole-body rigid motion step")
        if self.F == 0:
            order = [self.subspace[j].name for j in self.order]
            lines.append(f"solver: dense block Cholesky over {len(self.subspace)} domain blocks, elimination "
                         f"order {order}" + (" (LU: non-uniform interface cubature is unsymmetric)"
                                             if self.unsymmetric else ""))
        else:
            lines.append(f"solver: sparse {self.sparse_solver.backend} on the joint subspace + full-space system")
        return lines

    def cut_elements(self, tet_ids):
        """Remove elements of full-space domains (cutting); returns how many were removed."""
        tet_ids = np.asarray(tet_ids, dtype=np.int64)
        removed = 0
        for fd in self.full:
            hit = np.isin(fd.elements, tet_ids) & fd.alive
            fd.alive[hit] = False
            removed += int(hit.sum())
        self._full_alive = self._alive_weights()
        return removed
