"""The multi-domain subspace model (`model.kind: reduced`, docs/method.md §5-§13): its
build, state and outputs. Domains joined by coupling elements, each a rigid frame plus a
modal subspace, all stepped by one unified implicit solve.

The method's parts live in modules named after them, mixed into ReducedModel:

    step.py                the step: A Q' = b, Newton iterations, the state update
                           (linear_step.py: a one-iteration step in compiled calls)
    generalised_forces.py  G and K of domains (cubature) and coupling elements; loads
    unified_system.py      Mgen, A = Mgen + dt Dgen + dt^2 K, its solve; the two-step foil
    fictitious.py          fictitious forces; the free body's mean rigid motion
    contact_rows.py        contact rows C = dt n^T J and the contact correction
                           (with residual_compliance.py: the dent the modes cannot make)
    guard_terms.py         the stability guard's measure, energy projection, untangle

and the kernels they call in layout, frames, sampled_forces, coupling, block_cholesky,
reconstruct and measure. This module builds the model (partition, bases, cubature, coupling
tables, DOF layout) and holds its state q, qd, frames and the full-space rows.
"""
import time

import numpy as np
from scipy.spatial.transform import Rotation

from ..errors import SceneError
from ..fem.assembly import stiffness_pattern
from ..fem.elements import tet_geometry
from ..fem.mass import lumped_mass
from ..linear_solver import SparseSolver
from ..precompute import (PrecomputeCache, bases_cache_key, compliance_cache_key, contact_modes_cache_key,
                          cubature_cache_key)
from ..rotations import cross
from . import reconstruct
from .block_cholesky import BlockCholesky
from .contact_modes import add_contact_modes
from .contact_rows import ContactRows
from .coupling import TwoPhaseProjection
from .domains import FullDomain, build_subspace_domain
from .fictitious import FictitiousTerms
from .generalised_forces import GeneralisedForces
from .guard_terms import GuardTerms
from .frames import FrameState
from .layout import DomainLayout
from .residual_compliance import ResidualCompliance, build_residual_compliance
from .sampled_forces import StackedSamples
from .step import Step
from .unified_system import UnifiedSystem


def _jsonable(x):
    """Numbers and arrays of an info dict as plain JSON types."""
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple, np.ndarray)):
        return [_jsonable(v) for v in x]
    if isinstance(x, (np.floating, np.integer, np.bool_)):
        return x.item()
    return x


#: Without cubature, domains with at most this many modes evaluate every element as a
#: weight-1 sample (sampled_forces kernels) instead of assembling a sparse K and forming
#: U^T K U. Measured (session 22, `_evaluate` medians, one domain of a box): 240 tets at
#: r = 12, 0.39-0.57 -> 0.19-0.21 ms; 1,920 tets at r = 12, 1.5-1.7 -> 1.0 ms; 15,360 tets
#: at r = 20, 15-20 -> 13-16 ms; but 1,920 tets at r = 30, 1.9-2.4 -> 2.3-2.9 ms (the
#: per-sample 9 x 9 x r product outgrows the element path).
EXACT_SAMPLES_MAX_MODES = 20
#: ... and while the samples' G (s, 9, r) of all domains stays within this many bytes.
EXACT_SAMPLES_MAX_BYTES = 64 * 2**20


def exact_samples(subspace):
    """Every domain element of every domain as a cubature sample of weight 1
    (sampled_forces.SampledDomainForces: with all elements at weight 1 the sampled force
    and stiffness are the domain's exact ones), or None when a domain has more than
    EXACT_SAMPLES_MAX_MODES modes or no elements, or G would exceed EXACT_SAMPLES_MAX_BYTES."""
    from .sampled_forces import SampledDomainForces
    fms = [dom.forces for dom in subspace]
    if any(getattr(fm, "tets", None) is None or len(fm.tets) == 0 for fm in fms):
        return None
    if max(dom.r for dom in subspace) > EXACT_SAMPLES_MAX_MODES:
        return None
    if sum(72 * len(fm.tets) * dom.r for dom, fm in zip(subspace, fms)) > EXACT_SAMPLES_MAX_BYTES:
        return None
    return [SampledDomainForces.build(dom.U3, fm.tets, fm.geom.grads, fm.geom.volume, fm.material)
            for dom, fm in zip(subspace, fms)]


class ReducedModel(Step, GeneralisedForces, UnifiedSystem, ContactRows, FictitiousTerms, GuardTerms):
    """Multi-domain subspace model of a Body; see the module docstring.

    cfg: the scene's `model` section; damping {"alpha", "beta"}; dt > 0.
    """

    kind = "reduced"
    can_untangle = True

    def __init__(self, body, cfg, dt, damping, solver="auto", progress=None, cache=None, contact_vertices=None,
                 contact_mode_vertices=None, training_loads=None):
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
        self.bases_key = bases_cache_key(body, cfg, training_loads)
        hit = self.cache.load("bases", self.bases_key)
        if hit is not None:
            labels, names = hit[0]["labels"], list(hit[1]["names"])
            self.partition_notes = list(hit[1].get("partition_notes", []))
            say(f"cache: bases loaded from {self.cache.path('bases', self.bases_key)}")
        else:
            self.partition_notes = []         # why the domains are where they are (auto placement)
            labels, names = domain_labels(cfg.get("domains"), body.vertices, body.tets, self.partition_notes,
                                          poses=_training_poses(body, self.vertex_mass, training_loads, say))
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
        # model.basis.interface_modes: static answers to loads on the coupling elements'
        # vertices added to each domain (contact_modes.py; Craig-Bampton-like attachment
        # modes, docs/method.md §6.3).
        interface_modes = basis_opts.pop("interface_modes", 0)
        if isinstance(interface_modes, bool) or not isinstance(interface_modes, int) or interface_modes < 0:
            raise SceneError(f"model.basis.interface_modes must be an integer >= 0, got {interface_modes!r}")
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
        # Interface and contact modes (contact_modes.py). Not cached: a few sparse solves;
        # the key of every later stage includes them.
        self.interface_modes_note = None
        if interface_modes and len(part.coupling_elements):
            ids = np.setdiff1d(np.unique(tets[np.asarray(part.coupling_elements, dtype=np.int64)]), body.pinned)
            self.subspace, self.interface_modes_note = add_contact_modes(
                self.subspace, body, self.vertex_mass, ids, {"kind": "static", "count": interface_modes},
                progress=say, what="interface modes")
            self.bases_key = contact_modes_cache_key(self.bases_key, {"interface_modes": interface_modes}, ids)
        # Contact modes: the anchors the residual compliance is measured against.
        self.contact_modes_note = None
        self.contact_mode_vertices = contact_mode_vertices
        if contact_mode_vertices is not None:
            self.subspace, self.contact_modes_note = add_contact_modes(
                self.subspace, body, self.vertex_mass, np.asarray(contact_mode_vertices, dtype=np.int64),
                cfg["contact_modes"], progress=say)
            self.bases_key = contact_modes_cache_key(self.bases_key, cfg["contact_modes"], contact_mode_vertices)
        self.sub_index_of_domain = np.array([k if kind == "sub" else -1 for kind, k in self.domain_kind], dtype=np.int64)

        # Generalised DOF layout -------------------------------------------------
        sizes = np.array([dom.n_dofs for dom in self.subspace], dtype=np.int64)
        self.sub_offsets = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
        self.S = int(self.sub_offsets[-1])
        self.layout = DomainLayout.build(self.subspace, self.sub_offsets, n)
        self._surface_set = reconstruct.VertexSet(self.layout, self.body.surface.vertex_ids)
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
        # The step's matrix: no iterative refinement of its solves (linear_solver.py).
        self.sparse_solver = SparseSolver(solver, refine=False) if self.F > 0 else None
        self.compliance = self._build_compliance(contact_vertices, say)
        self.reset()
        self.samples = None             # StackedSamples once cubature exists (_stack_samples)
        self.cubature_info = self._build_cubature(cfg.get("cubature") or {}, say)
        self._stack_samples()
        self.build_seconds = time.perf_counter() - t_start

    def _build_compliance(self, candidates, say):
        """The residual contact compliance on the candidate vertices (residual_compliance.py),
        from the cache when its inputs are unchanged; None without candidates, or when
        full-space domains make n_gen large (contact on their vertices is exact already)."""
        self.compliance_note = None
        if candidates is None or len(candidates) == 0:
            return None
        if self.F:
            self.compliance_note = "not built: the model has full-space domains, where contact is exact"
            return None
        candidates = np.asarray(candidates, dtype=np.int64)
        key = compliance_cache_key(self.bases_key, candidates)
        hit = self.cache.load("compliance", key)
        if hit is not None:
            arrays, meta = hit
            say(f"cache: residual compliance loaded from {self.cache.path('compliance', key)}")
            comp = ResidualCompliance.on(candidates, arrays["domain"], arrays["C"], len(self.body.vertices),
                                         dict(meta["info"]))
        else:
            t0 = time.perf_counter()
            comp = build_residual_compliance(self.body, self.layout, self.n_gen, self.vertex_mass, candidates,
                                             progress=say)
            comp.info["seconds"] = time.perf_counter() - t0
            self.cache.save("compliance", key, {"domain": comp.domain, "C": comp.C}, {"info": comp.info})
        X = self.body.vertices[candidates]
        self.compliance_note = (f"{comp.n} surface vertices nearest the colliders' scene paths "
                                f"(box {np.ptp(X, axis=0).round(4).tolist()} m), {comp.info['megabytes']:.1f} MB; "
                                f"median residual/full compliance {comp.info['diagonal_ratio']:.2f}")
        say(f"residual compliance: {self.compliance_note}")
        return comp

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
        training = generate_training(self, progress=say, seed=int(ccfg.get("seed", 0)),
                                     reduced_simulation=self.training_simulation, **tcfg)
        self.reset()                       # a reduced training run stepped this model
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

    def training_simulation(self, alpha):
        """(step(f), positions()) of this model from rest, with the forces it has now (exact,
        before cubature), mass damping alpha and one Newton iteration: the reduced source of
        cubature training (training.generate_training). The model's settings are unchanged."""
        self.reset()
        terms = self.step_terms(alpha=alpha, newton_iterations=1)
        return (lambda f: self._step(f, None, None, terms)), self.vertex_positions

    def _stack_samples(self):
        """All domains' cubature samples in one array (one kernel call a step). Without
        cubature, every domain element as a sample of weight 1 (the exact forces, through
        the same kernels) when that is small and cheap (exact_samples), else None: each
        domain's exact sparse path (SubspaceDomain.reduced_tangent)."""
        sampled = [dom.sampled for dom in self.subspace]
        if sampled and any(sm is None for sm in sampled):
            sampled = exact_samples(self.subspace)
        self.samples = StackedSamples(sampled, self.layout.r_max, self.body.material) if sampled else None

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
        domain (contact rows: sparse_rows.ContactRowEntries)."""
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
        self._contact_compliance = None
        # Each candidate's dent (n_c, 3) in its domain's rest axes under the last step's
        # contact forces (residual_compliance.py): an output of the contact, kept as state
        # because the next step's slip is measured from it.
        self._dent = np.zeros((self.compliance.n if self.compliance is not None else 0, 3))
        self._start_eval = None         # the evaluation at the current state (_start_evaluation)
        self.timing = {}                # phase times of the step in progress (Step._step)
        self._positions_kept = []       # positions_of at the current state, two ids arrays
        self._dented_kept = None        # _dented's last kept answer

    def _full_rows(self, a):
        """A copy of x_full or v_full (n_verts, 3) for a snapshot. Without full-space
        domains they hold no state (rest positions, zeros) and are only ever replaced,
        never written in place: the same array serves, and a step of a 300K-tet body
        does not copy 1.4 MB three times for nothing."""
        return a.copy() if self.F else a

    def _alive_weights(self):
        """1.0 / 0.0 per full-space domain element (cut elements 0), all domains concatenated."""
        return np.concatenate([fd.alive for fd in self.full]).astype(float) if self.full else np.zeros(0)

    def get_state(self, share=False):
        """A snapshot of the dynamic state (copies): q, qd (per subspace domain), frames,
        full-space x and v, and what the outputs read (last energy, contact, stats).
        set_state(snapshot) restores it exactly (the stability guard rolls back with it).

        share=True: what the model only ever replaces, never writes into (q, qd, the frame
        arrays, the dicts and the contact history a step rebuilds), is shared instead of
        copied; set_state copies it back. For a rollback around steps only (the stability
        guard's, Simulator._save): set_rigid_velocity writes the frame arrays in place.
        The guard snapshots every step, and these copies were a fifth of its own time on
        a 12-DOF model."""
        if share:
            fr = self.frames           # a new FrameState: a projection replaces its arrays
            # _full_rows inlined (two calls a step): rows without full-space domains are shared.
            x_full, v_full = (self.x_full.copy(), self.v_full.copy()) if self.F else (self.x_full, self.v_full)
            return {"q": self.q, "qd": self.qd, "frames": FrameState(fr.c, fr.R, fr.v, fr.w, fr.w_prev),
                    "x_full": x_full, "v_full": v_full,
                    "last": self.last, "contact": self.contact, "stats": self.stats,
                    "contact_history": self._contact_history, "dent": self._dent}
        return {"q": self.q.copy(), "qd": self.qd.copy(),
                "frames": self.frames.copy(), "x_full": self._full_rows(self.x_full),
                "v_full": self._full_rows(self.v_full),
                "last": dict(self.last), "contact": self.contact, "stats": dict(self.stats),
                "contact_history": list(self._contact_history), "dent": self._dent}

    def set_state(self, state):
        """Restore a get_state() snapshot."""
        self.q = np.array(state["q"], dtype=np.float64)
        self.qd = np.array(state["qd"], dtype=np.float64)
        self.frames = state["frames"].copy()
        self.x_full, self.v_full = self._full_rows(state["x_full"]), self._full_rows(state["v_full"])
        self.last, self.contact, self.stats = dict(state["last"]), state["contact"], dict(state["stats"])
        self._contact_history, self._contact_rows_seen = list(state.get("contact_history", [])), None
        self._dent = state["dent"]

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

    # ------------------------------------------------------------------ positions
    def positions_of(self, ids, q=None, frames=None, x_full=None, dent=True):
        """World positions (len(ids), 3) of the given global vertex ids (reconstruct.py),
        with the residual compliance's dent at the current state (dent=False: without it,
        as the contact search measures gaps).

        At the current state the result is kept, read-only, for the same ids array: the
        surface a step's contact search reads at its start is the one the last step's
        output read at its end (hammock: one of its two surface passes a step). The state
        is compared by value (q and the frames are small, and tests write them in place);
        a model with full-space domains, whose state holds every vertex, is not kept."""
        x = self._reduced_positions(ids, q, frames, x_full)
        if dent and q is None and frames is None and self._dent.any():
            x = self._dented(ids, x)
        return x

    def _dented(self, ids, x):
        """x (len(ids), 3), positions of ids at the current state, plus each candidate's
        dent turned by its domain's frame.

        A kept x (read-only, see positions_of) is dented once for the dent it gets: in
        contact the surface at a state is read three times (the step's contact points,
        the output, the next step's contact search), and its copy and dent cost several
        times the kept pass itself (hammock: about 0.1 ms against 15 us). The kept x and
        the dent array are compared by identity: neither is ever written in place."""
        kept = self._dented_kept
        if kept is not None and kept[0] is x and kept[1] is self._dent and kept[2] is ids:
            return kept[3]
        k = self.compliance.index[ids]
        sel = np.flatnonzero(k >= 0)
        if sel.size == 0:
            return x
        out = x.copy()
        R = self.frames.R[self.compliance.domain[k[sel]]]
        out[sel] += np.einsum("kij,kj->ki", R, self._dent[k[sel]])
        if not x.flags.writeable:
            out.flags.writeable = False
            self._dented_kept = (x, self._dent, ids, out)
        return out

    def _reduced_positions(self, ids, q, frames, x_full):
        q_, frames_ = self.q if q is None else q, self.frames if frames is None else frames
        x_full_ = self.x_full if x_full is None else x_full
        if ids is self.body.surface.vertex_ids:
            def compute():
                return self._surface_set.positions(q_, frames_, x_full_)
        else:
            def compute():
                return reconstruct.positions(self.layout, ids, q_, frames_, x_full_)
        if q is not None or frames is not None or x_full is not None or self.F or len(ids) < 256:
            # A few loaded vertices cost nothing to rebuild, and kept they would push the
            # surface out of the two entries.
            return compute()
        for k_ids, k_q, k_c, k_R, x in self._positions_kept:
            if (k_ids is ids and np.array_equal(k_q, self.q) and np.array_equal(k_c, self.frames.c)
                    and np.array_equal(k_R, self.frames.R)):
                return x
        x = compute()
        x.flags.writeable = False
        key = (ids, self.q.copy(), self.frames.c.copy(), self.frames.R.copy())
        self._positions_kept = [key + (x,)] + self._positions_kept[:1]
        return x

    def watch(self, ids):
        """Kept for the Simulator's interface: positions_of is one compiled pass for any ids."""

    def vertex_positions(self):
        return self.positions_of(np.arange(len(self.body.vertices)))

    def vertex_velocities(self):
        """World velocities (n_verts, 3): v + w x (x - c) + R U qd, or the full-space ones."""
        return reconstruct.velocities(self.layout, self.vertex_positions(), self.qd, self.frames, self.v_full)

    # ------------------------------------------------------------------ outputs
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
        lines.append(self._basis_region_line())
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
            lines.append("cubature: off (model.cubature.samples: 0): every domain element every step"
                         + (", as weight-1 samples" if self.samples is not None else ""))
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
        if self.compliance_note is not None:
            lines.append(f"contact: residual compliance (the local dent the modes cannot make, "
                         f"model.contact_compliance): {self.compliance_note}")
        elif self.cfg.get("contact_compliance", 0) == 0:
            lines.append("contact: no residual compliance (model.contact_compliance: 0): the modes alone answer "
                         "a collider, too stiff for a local dent")
        else:
            lines.append("contact: no residual compliance: the scene has no collider, or planes only (a floor "
                         "carries a body with its modes alone; docs/method.md §14.2)")
        if self.contact_modes_note is not None:
            lines.append(f"contact: {self.contact_modes_note} (model.contact_modes; docs/method.md §14.3)")
        if self.interface_modes_note is not None:
            lines.append(f"bases: {self.interface_modes_note} (model.basis.interface_modes; docs/method.md §6.3)")
        return lines

    def _basis_region_line(self):
        """explain(): the region each domain's modes were computed on, and where its
        size came from (the scene, the default, or the default of automatic domains)."""
        from .domains import EXTENSION
        basis = self.cfg.get("basis") or {}
        why = (self.cfg.get("implied") or {}).get("basis.extension")
        if "layers" in basis:
            grown = f"{basis['layers']} element rings (model.basis.layers)"
        else:
            ext = basis.get("extension", EXTENSION)
            grown = (f"about {ext:g} x its diameter (model.basis.extension {ext:g}: "
                     + (why or ("the scene's" if "extension" in basis else "the default")) + ")")
        rings = ", ".join(f"{d.name} +{d.basis_info.get('layers', '?')}"
                          + (f" ({d.basis_info['region_vertices']} vertices)" if "region_vertices" in d.basis_info
                             else "") for d in self.subspace)
        return (f"bases: each domain's modes computed on its region grown by {grown}, the region capped "
                f"by model.basis.max_growth, then restricted to the domain; rings: {rings}")

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


def _training_poses(body, vertex_mass, cases, say):
    """The callable auto placement asks for the scene's training poses (bend_cuts.py):
    (case labels, displacements (c, n, 3)); None without load cases."""
    if not cases:
        return None

    def poses():
        from .bend_cuts import static_poses
        return [c.label for c in cases], static_poses(body, vertex_mass, cases, progress=say)
    return poses
