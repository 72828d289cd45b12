"""What the stability guard reads from and does to a reduced state (mdss_ros/guard.py,
docs/method.md §15).

- guard_measure: kinetic energy, elastic energy, gravity potential, a vertex-speed bound
  and inverted elements, in reduced coordinates (measure.frame_measure); per free domain
  E_kin = 1/2 M |v|^2 + 1/2 w'^T I(q) w' + w' . (q^T W qd) + 1/2 |qd|^2.
- scale_relative_motion: the energy projection v <- V + s (v - V), w <- s w, qd <- s qd.
- untangle: shrink the deformation towards a rigid placement of the rest shape, by the
  largest s in [0, 1] (bisection) that leaves no inverted element.
"""

from math import isfinite

import numpy as np

from ..rotations import cross
from ..state_measure import Measure, inverted_tets
from . import reconstruct
from .measure import count_not_positive, frame_measure, measure_pack


class GuardTerms:
    """The stability guard's measure, energy projection and untangle on a reduced state. Mixed into
    reduced_model.ReducedModel, whose build provides the attributes it reads."""

    #: (layout, samples, measure.measure_pack(layout), sample det buffers or None), built on
    #: the first measure: the constants frame_measure reads, and the (det, valid) arrays of
    #: every sample stack when inverted elements are counted from those alone
    #: (_inversion_buffers). Keyed on the layout and samples objects, which a build makes once.
    _guard_pack = None

    def kinetic_energy(self):
        v = self.vertex_velocities()
        return 0.5 * float((self.vertex_mass * (v * v).sum(1)).sum())

    def energies(self, gravity):
        """(kinetic, elastic, gravity potential) of the current state (J) for gravity (3,):
        the vertex sums over every vertex, 1/2 m |v|^2 and -m g . x with positions and
        velocities as vertex_positions and vertex_velocities give them, computed without
        a pass over the vertices. The reduced-coordinate formulas of guard_measure
        (frame_measure) are those sums exactly for the basis (mass-orthonormal, and
        mass-orthogonal to rigid motion): within 2.3e-14 of them on six scenes over 120
        steps (session 26). The residual compliance's dent moves a few contact candidates;
        their share is added on those vertices alone (_dent_energies). Simulator.energy
        reads this for /diagnostics and every rerun frame: on armadillo_class (60,266
        vertices) the vertex sums took 24.5 ms a call."""
        g = np.asarray(gravity, dtype=np.float64)
        ok, kinetic, grav, _ = self._frame_energies(g)
        if not ok:
            return np.nan, np.nan, np.nan
        if self._dent.any():
            dk, dg = self._dent_energies(g)
            kinetic, grav = kinetic + dk, grav + dg
        return kinetic, float(self.elastic_energy()), grav

    def _frame_energies(self, g):
        """(all finite, kinetic, gravity potential, vertex-speed bound) of the state without
        the dent: frame_measure, plus the full-space vertices' own sums."""
        fr = self.frames
        pack = self._guard_pack
        if pack is None or pack[0] is not self.layout or pack[1] is not self.samples:
            pack = self._guard_pack = (self.layout, self.samples, measure_pack(self.layout),
                                       self._inversion_buffers())
        # The layout's constants in one array and the result as a tuple of Python floats:
        # the call with 18 arguments, an out array and tolist() was the measure's largest
        # piece beside the elastic evaluation.
        ok, kinetic, grav, speed = frame_measure(self.q, self.qd, fr.c, fr.R, fr.v, fr.w, pack[2], g)
        # x_full / v_full hold every vertex but only full-space rows are state: checking
        # them on a model without full-space domains was a third of this measure.
        if not ok or (self.F and not (np.isfinite(self.x_full).all() and np.isfinite(self.v_full).all())):
            return False, np.nan, np.nan, np.inf
        if self.F:
            m = np.where(self.is_full_vertex, self.vertex_mass, 0.0)
            kinetic += 0.5 * float((m * (self.v_full * self.v_full).sum(1)).sum())
            grav -= float((m * (self.x_full @ g)).sum())
            speed = max(speed, float(np.sqrt((self.v_full * self.v_full).sum(1).max())))
        return True, kinetic, grav, speed

    def _dent_energies(self, g):
        """(kinetic, gravity) the dent adds to the vertex sums: a dented candidate l sits at
        x_l + R d_l, and vertex_velocities takes its arm about the frame centre there, so
        its velocity gains w x (R d_l)."""
        comp = self.compliance                  # the dent's rows are its candidates, in order
        cand = comp.vertices
        shift = np.einsum("kij,kj->ki", self.frames.R[comp.domain], self._dent)     # (c, 3) world dent
        x = self.positions_of(cand, dent=False)
        u = reconstruct.velocities_of(self.layout, cand, x, self.qd, self.frames, self.v_full)
        u_dent = u + cross(self.frames.w[comp.domain], shift)
        m = self.vertex_mass[cand]
        kinetic = 0.5 * float((m * ((u_dent * u_dent).sum(1) - (u * u).sum(1))).sum())
        return kinetic, -float((m * (shift @ g)).sum())

    def guard_measure(self, gravity, check_inversion=True):
        """What the stability guard reads from the state (guard.Measure), in the reduced
        coordinates so it costs nothing that grows with the mesh: kinetic energy exactly,
        per free domain 1/2 M |v|^2 + 1/2 w'^T I(q) w' + w' . (q^T W qd) + 1/2 |qd|^2 (the
        basis is mass-orthonormal and mass-orthogonal to rigid motion, W the fictitious
        tensor sum m u_a x u_b); elastic energy from the model's forces (cubature); gravity
        potential from the mass moments; an upper bound of vertex speeds,
        |v| + |w| (rho + sigma |q|) + sigma |qd| (rho the largest rest radius, sigma the
        largest per-vertex basis norm); inverted elements among those the forces sample
        (cubature samples, coupling and full-space elements). Non-finite states give
        finite=False; the guard calls it under np.errstate(all="ignore"), so they warn
        nowhere."""
        ok, kinetic, grav, speed = self._frame_energies(np.asarray(gravity, dtype=np.float64))
        if not ok:
            return Measure(None, None, np.nan, np.nan, np.nan, 0, False, speed=np.inf)
        pack = self._guard_pack
        try:
            elastic = float(self.elastic_energy())
        except (ArithmeticError, ValueError, RuntimeError):
            elastic = np.nan
        if not check_inversion:
            inverted = 0
        elif pack[3] is not None and self.samples.det_at is self.q:
            # _guard_inverted's answer read straight from the det F buffers of the evaluation
            # just made at q (by elastic_energy above): the calls around the count were most
            # of its cost, after every step.
            inverted = 0
            for det, valid in pack[3]:
                inverted += count_not_positive(det, valid)
        else:
            inverted = self._guard_inverted()
        # Spelled out, not all() over a generator: this runs after every step.
        finite = isfinite(kinetic) and isfinite(elastic) and isfinite(grav) and isfinite(speed)
        return Measure(None, None, kinetic, elastic, grav, inverted, finite, speed)

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
        n = self.samples.inverted_count(self.q) if self.samples is not None else 0
        if not self.F and not len(self.c_elem) and self.samples is not None:
            return n              # _guard_tets has nothing: the forces sample cubature points only
        x_I = None
        # Without coupling elements (one domain) there is nothing to read from x_I, and
        # _guard_tets gives the same elements either way: skip the identity check.
        if self.coupling_kind == "element" and len(self.c_elem):
            c = self._start_eval
            if c is not None and (c[0][0] is self.q and c[0][1] is self.frames and c[0][2] is self.x_full
                                  and c[0][3] is self._full_alive):
                x_I = c[1][6]
        ids, local = self._guard_tets(coupling=x_I is None)
        if len(ids):
            n += inverted_tets(self.positions_of(ids), local)
        if x_I is not None and len(self.c_elem):
            n += inverted_tets(x_I, self.c_elem)
        return n

    def _inversion_buffers(self):
        """((det, valid), ...) per sample stack when _guard_inverted counts cubature samples
        only and reads them from the last evaluation's det F (StackedSamples.inverted_count's
        first case), else None. That is: a model whose forces sample cubature points only
        (no full-space domain, no coupling element), every real sample with a weight (a
        zero-weight sample is skipped by the kernel, its det F not formed: StackedSamples
        then forms F again). The buffers are the stacks' own, written in place by every
        evaluation."""
        samples = self.samples
        if samples is None or self.F or len(self.c_elem):
            return None
        stacks = [st for _, st in samples.stacks]
        if any(np.any(st.valid & (st.wV == 0.0)) for st in stacks):
            return None
        return tuple((st.det, st.valid) for st in stacks)

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
