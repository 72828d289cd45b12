"""One step of the reduced model: the unified implicit solve (docs/method.md §9).

    A Q' = b,    b = Mgen Q + dt (J^T f_ext - G_int + F_fict)         (one Newton iteration)
    q' = q + dt qd',   c' = c + dt v',   R' = exp([dt w']x) R,   x' = x + dt xd'

Q (n_gen,) stacks per subspace domain [qd_i; v_i; w_i] (a pinned domain: qd_i only), then
the free full-space DOFs. More Newton iterations solve r(Q) = Mgen (Q - Q_n) + dt (Dgen Q +
G(s(Q)) - F_n) = 0 with an Armijo line search on the incremental potential; contact
corrects each Newton step (contact_rows.py). A step's dt, iteration count and fictitious
treatment come from StepOptions for that step only.
"""
import time
from dataclasses import dataclass

import numpy as np

from ..errors import SceneError
from ..fem.backward_euler import contact_forces, contact_stats
from ..loads import sparse_loads
from ..rotations import cross, exp_so3
from ..step_options import StepOptions
from .frames import FrameState
from .frictional_kernel import record_kernel
from .linear_step import linear_predict_kernel, linear_solve_kernel, linear_step_kernel
from .sparse_rows import ContactRowEntries
from .unified_system import StepSystem


#: Armijo backtracking halves the step from 1 down to this length (step.py, _line_search).
MIN_STEP = 1e-4
#: Levenberg-Marquardt shifts mu (multiples of Mgen added to A) tried in turn when the
#: Newton direction lowers the potential at no length.
DAMPING = (1.0, 10.0, 100.0, 1e3, 1e4)


@dataclass(frozen=True)
class StepTerms:
    """What one step integrates with, resolved once from the model's settings and the
    step's StepOptions and passed down, so no step ever changes the model's settings:
    dt (s), newton_iterations, implicit (fictitious forces), alpha (mass damping 1/s)."""

    dt: float
    newton_iterations: int
    implicit: bool
    alpha: float


class Step:
    """The reduced step, its prediction of the state from Q, and the start-state evaluation. Mixed into
    reduced_model.ReducedModel, whose build provides the attributes it reads."""

    def step(self, f_ext, gravity=None, contact=None, options=None):
        """Advance by dt under per-vertex loads f_ext (n_verts, 3) and gravity (3,); contact
        as in BackwardEuler.step; options: a StepOptions for this step only (dt, Newton
        iterations, implicit fictitious forces). The model's own settings are not touched:
        the step reads them through StepTerms."""
        return self._step(f_ext, gravity, contact, self.step_terms(options))

    def step_terms(self, options=None, alpha=None, newton_iterations=None):
        """The StepTerms of a step: the model's settings, changed by options (StepOptions:
        dt, at least options.newton_iterations, fictitious). alpha, newton_iterations:
        exact values for a training run (training.py), which steps without damping ladders."""
        o = options or StepOptions()
        iterations = max(self.newton_iterations, int(o.newton_iterations or 0))
        return StepTerms(dt=float(o.dt or self.dt),
                         newton_iterations=int(newton_iterations or iterations),
                         implicit=(o.fictitious or self.fictitious) == "implicit",
                         alpha=self.alpha if alpha is None else float(alpha))

    def _step(self, f_ext, gravity, contact, terms):
        if (terms.newton_iterations == 1 and not terms.implicit and not self.F and self.scheme != "two_step"
                and not self.unsymmetric):
            # A subspace-only body's linearly implicit step in compiled calls (one without
            # contact); None where its system is not positive definite (solved below by LU).
            stats = self._linear_step(f_ext, gravity, contact, terms)
            if stats is not None:
                return stats
        t0 = time.perf_counter()
        dt = terms.dt
        inertia, gm = self._step_motion(f_ext, terms)
        self._dW = 0.0
        self._indefinite = False
        # The applied loads as generalised forces at the step start (no gravity: it is a
        # potential); their work over the step is dt F_app . Q' (reported for the guard).
        F_app = self._applied(f_ext, self.frames, self.q)
        base = (self.q.copy(), self.frames.copy(), self._full_rows(self.x_full), gm, inertia)
        Qn = self.get_Q()
        if gm is not None:
            Qn = self._coriolis_rotate(gm, Qn - self._rigid_Q(gm), dt)
        implicit = terms.implicit
        if implicit:
            coriolis, centrifugal = self._fictitious_matrices(self.frames)
            Qn = self._modal_coriolis_rotate(coriolis, Qn, dt)
        (G, K_ss, K_sI, K_ff, energy, J, x_I), timing = self._start_evaluation(take=True)
        # The step's phase times, reset here once: the start evaluation's (made above or,
        # under the stability guard, by its measure after the last step), then every
        # evaluation and solve below adds its own (Newton iterations, line search).
        self.timing = dict(timing)
        # Dgen = alpha Mgen + beta K (step start); with implicit fictitious forces the
        # centrifugal force K_cf q at the end of the step, K_cf q_n (explicit, in Fn) + dt
        # K_cf qd', is a velocity term, hence in Dgen (it enters A as -dt^2 K_cf).
        mass = self._subspace_mass(self.frames, predicted_dt=dt, inertia=inertia)
        system = StepSystem(self, mass, dt, terms.alpha, self.beta, (K_ss, K_sI, K_ff),
                            centrifugal if implicit else None)
        Fn = F_app + self._gravity(gravity, self.frames) + \
            self._explicit_terms(self.frames, self.q, self.qd, dt, coriolis=not implicit)
        if gm is not None:
            Fn = Fn + self._global_fictitious(gm)
        # Momentum at the step start: Mgen(t) (Qn + Q_W) - Mgen(t + dt) Q_W, where Q_W carries
        # the global W on the angular rows (the angular rows hold w - W when gm is used).
        mass0 = self._subspace_mass(self.frames, inertia=inertia)
        S = self.S
        p0 = system.mass_matvec(Qn)                   # the full-space rows: M_ff Qn
        if gm is not None:
            Q_W = self._rigid_Q((np.zeros(3), np.zeros(3), gm[2]), angular_only=True)[:S]
            p0[:S] = mass0.matvec(Qn[:S] + Q_W) - mass.matvec(Q_W)
        else:
            p0[:S] = mass0.matvec(Qn[:S])

        def residual(Q, G_k):
            return system.mass_matvec(Q) - p0 + dt * (system.damping_matvec(Q) + G_k - Fn)

        t_c = time.perf_counter()
        contact_rows = self._contact_rows(contact, gm, dt) if contact else None
        contact_s = time.perf_counter() - t_c
        lam = None
        if contact_rows is not None and self.scheme == "two_step":
            raise SceneError("contact is available with the one-step scheme only")
        r0 = r_last = 0.0
        cuts, damped, stalled = 0, 0, ""
        if self.scheme == "two_step":
            Q = self._two_step(mass.dense(), K_ss, (system.damping_dense(),), p0, G, Fn, dt)
            iterations = 1
        else:
            Q = np.zeros_like(Qn)
            iterations = 0
            r = dt * (G - Fn) - p0                    # the residual at Q = 0
            r0 = r_last = float(np.linalg.norm(r))
            for it in range(terms.newton_iterations):
                A = system.matrix(K_ss, K_sI, K_ff)
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
                if terms.newton_iterations > 1 and self.line_search and not self.unsymmetric and contact_rows is None:
                    step_len, dQ, n_cuts, mu = self._line_search(system, A, r, Q, dQ, (p0, Fn, energy), base, dt)
                    cuts += n_cuts
                    if step_len == 0.0:
                        # No length of any direction lowers the potential: keep this iterate.
                        # At the first iteration that is Q = 0 (no relative motion at the
                        # step's end), which the guard treats as a sign to retry.
                        stalled = "first" if it == 0 else "later"
                        break
                    damped += mu > 0.0
                Q = Q + step_len * dQ
                if it + 1 == terms.newton_iterations:
                    break
                q, _, frames, x_full, _ = self._predict(Q, base, dt)
                G, K_ss, K_sI, K_ff, energy, _, _ = self._evaluate(q, frames, x_full)
                r = residual(Q, G)
                # With contact the converged residual is the contact force C^T lam, not zero.
                r_c = r - self._contact_force(contact_rows, lam) if contact_rows is not None else r
                r_last = float(np.linalg.norm(r_c))
                if r_last <= self.tolerance * max(r0, 1e-300):
                    break
        if gm is not None and self._contact_holds(contact_rows):
            gm = gm[:3] + (None,)
            base = base[:3] + (gm,) + base[4:]
        q, qd, frames, x_full, v_full = self._predict(Q, base, dt)
        self.q, self.qd, self.frames = q, qd, frames
        if self.F:             # before the contact outputs, which read full-space positions
            self.x_full, self.v_full = x_full, v_full
        contact_work = self._contact_outputs(contact, contact_rows, Q, dt)
        self.last = {"elastic": energy}
        self._report(t0, iterations, r_last / r0 if r0 > 0 else 0.0, dt * float(F_app @ self.get_Q()), contact_work,
                     contact_s, cuts, damped, stalled)
        if contact_rows is not None:          # candidates and rows the LCP solved for (unilateral.py)
            self.stats.update(contact_stats(self._contact_info))
        self.timing = {}
        return self.stats

    def _report(self, t0, iterations, residual_ratio, external_work, contact_work=0.0, contact_s=0.0, cuts=0,
                damped=0, stalled=""):
        """self.stats of the step that started at t0 (perf_counter s), from its phase times
        (self.timing: domain, coupling, factor and solve ms; the compiled linear step puts
        its kernels' whole time in factor_ms, docs/performance.md "Measuring") and the
        values given."""
        self.stats = {"newton_iterations": iterations, "residual": residual_ratio, "external_work": external_work,
                      "contact_work": contact_work,
                      "contact_ms": 1e3 * contact_s,      # candidate search, rows, LCP (inside model_ms)
                      "domain_ms": self.timing["domain_ms"],
                      "coupling_ms": self.timing["coupling_ms"], "factor_ms": self.timing.get("factor_ms", 0.0),
                      "solve_ms": self.timing.get("solve_ms", 0.0), "model_ms": 1e3 * (time.perf_counter() - t0),
                      "angular_momentum_correction": self._dW,
                      "line_search_cuts": cuts, "newton_damped": int(damped), "newton_stalled": stalled,
                      "indefinite_system": self._indefinite,
                      "domains": len(self.subspace) + len(self.full)}

    def _contact_holds(self, contact_rows):
        """Whether this step's contact solve left a force on the body. A free body in
        contact keeps the solve's own angular momentum: the rebalance (_rebalance) would
        have to know the contact forces' torque over the step, and one taken at the step
        start either undid the floor's torque (a caterpillar lifting its head was turned by
        up to 0.3 rad/s a step and created energy) or, at a static dt, turned a resting
        block into the floor."""
        return (contact_rows is not None and self._contact_rows_seen is contact_rows
                and bool(np.any(self._contact_lam > 0.0)))

    def _contact_outputs(self, contact, contact_rows, Q, dt):
        """The step's contact record (self.contact) and the residual compliance's dent
        (self._dent) at the new state, from the contact solve's forces; returns the work of
        the contact forces over the step (0.0 without contact rows)."""
        self.contact = None
        self._dent = np.zeros_like(self._dent)
        if contact_rows is None:
            return 0.0
        verts, _, _, normals, which, friction = contact_rows
        lam = self._contact_lam if self._contact_rows_seen is contact_rows else np.zeros(len(verts))
        if self._contact_compliance is not None:
            self._dent = self._contact_compliance.dent(lam.ravel())
        lam_n = lam if lam.ndim == 1 else lam[:, 0]
        pts = self._contact_points(contact, verts)
        w = self._contact_info.get("w") if self._contact_rows_seen is contact_rows else None
        if (friction is not None and lam.ndim == 2 and w is not None and friction.n_built == len(verts)
                and isinstance(friction.rows3, ContactRowEntries)):
            return self._frictional_record(contact, contact_rows, lam, w, pts, Q, dt)
        depth = np.zeros(len(verts))
        active = lam_n > 0
        for c_idx, col in enumerate(contact["colliders"]):       # a few colliders, vectorised each
            sel = np.flatnonzero(active & (which == c_idx))
            if sel.size:
                depth[sel] = np.maximum(-col.signed_distance(pts[sel])[0], 0.0)
        self.contact = contact_forces(verts, normals, which, lam, None if friction is None else friction.tangents,
                                      pts, depth, w, dt)
        # Work of the contact forces over the step in the step's own terms (the guard's
        # energy ledger): the generalised force J^T n lam times dt Q', that is lam . C Q'
        # (C holds dt), plus the rigid velocity a co-rotating step folds into phi.
        if friction is None:
            return float(lam @ (contact_rows[1] @ Q + self._contact_rigid))
        return friction.work(lam, Q)

    def _frictional_record(self, contact, contact_rows, lam, w, pts, Q, dt):
        """_contact_outputs for frictional rows that are all built as entries: the record
        and the forces' work in one compiled pass (frictional_kernel.record_kernel) instead
        of contact_forces' and FrictionalRows.work's numpy, 31 -> 4 us on the reduced
        incline's 48 candidates (docs/performance.md "Session 30"). The same values; the
        work summed in another order (round-off). pts (m, 3) the contact points at the new
        state; returns the work."""
        verts, _, _, normals, which, friction = contact_rows
        m = len(verts)
        rows3 = friction.rows3
        active, forces, fric, slip = np.empty(m, dtype=np.int64), np.empty((m, 3)), np.empty((m, 3)), np.empty(m)
        n, work = record_kernel(lam, normals, friction.tangents, w, float(dt), rows3.cols, rows3.vals, rows3.count,
                                friction.slot, friction.rigid3, np.ascontiguousarray(Q, dtype=np.float64), active,
                                forces, fric, slip)
        a = active[:n]
        which_a, pts_a = which[a], pts[a]
        depth = np.zeros(n)
        for c_idx, col in enumerate(contact["colliders"]):       # a few colliders, vectorised each
            sel = np.flatnonzero(which_a == c_idx)
            if sel.size:
                depth[sel] = np.maximum(-col.distance(pts_a[sel]), 0.0)
        self.contact = {"vertices": verts[a], "normals": normals[a], "which": which_a, "forces": forces[:n],
                        "normal_force": lam[a, 0], "friction": fric[:n], "points": pts_a, "depth": depth,
                        "candidates": int(m), "slip_speed": slip[:n]}
        return float(work)

    def _step_motion(self, f_ext, terms):
        """(inertia, gm) of a step from the current state: the body-frame inertia (D, 3, 3)
        at q for the mass blocks and the prediction (None without movable frames), and a
        free body's mean rigid motion (C, V, W, L') with the angular momentum it must have
        after the step, L' = (L + dt tau) / (1 + dt alpha), tau the loads' torque about the
        mass centre (None for a body held by pins)."""
        inertia = self._inertia_of(self.q) if len(self.layout.movers) else None
        gm = self._global_motion(inertia)
        if gm is None:
            return inertia, None
        C, V, W, L = gm
        # Torque of the loads about the mass centre; uniform gravity has none.
        loaded, f_loaded = sparse_loads(f_ext)
        # Without loads (gravity alone: the incline, a body on a floor) there is no
        # torque to take, and positions_of's surface pass is skipped.
        tau = cross(self.positions_of(loaded) - C, f_loaded).sum(0) if loaded.size else np.zeros(3)
        return inertia, (C, V, W, (L + terms.dt * tau) / (1.0 + terms.dt * terms.alpha))

    def _linear_step(self, f_ext, gravity, contact, terms):
        """_step for a subspace-only body with one Newton iteration and explicit fictitious
        forces, the same operations in compiled calls (linear_step.py): the system and its
        solve (linear_solve_kernel), the contact rows and their correction of the solve as
        in _step, then the new state (linear_predict_kernel); without contact both kernels
        in one call (linear_step_kernel). A free body's mean motion is taken before them and
        its angular momentum balance after them, as _step does. Returns the stats, or None
        (nothing of the state changed, the start evaluation kept) when the unified matrix
        is not positive definite. The stats' factor_ms is the kernels' time (the system,
        its factor and solve, the state update) and solve_ms 0."""
        t0 = time.perf_counter()
        dt = terms.dt
        L, fr, bs = self.layout, self.frames, self.block_solver
        _, gm = self._step_motion(f_ext, terms)
        if gm is None:
            C = V = W = np.zeros(3)
            Rc = np.eye(3)
        else:
            C, V, W = (np.asarray(a, dtype=np.float64) for a in gm[:3])
            Rc = exp_so3(-2.0 * dt * W)            # as _coriolis_rotate
        F_app = self._applied(f_ext, fr, self.q)
        (G, K_ss, _, _, energy, _, _), timing = self._start_evaluation()
        if bs.L is None:
            bs.L = np.zeros((self.S, self.S))      # BlockCholesky.factor's buffer, made on first use
        system = (self.q, self.qd, fr.c, fr.R, fr.v, fr.w, fr.w_prev, G, K_ss, F_app,
                  np.zeros(3) if gravity is None else np.asarray(gravity, dtype=np.float64), gravity is not None,
                  gm is not None, C, V, W, Rc, dt, terms.alpha, self.beta, L.r, L.movable, L.q_index, L.modal_rows,
                  L.movers, L.lin_index, L.ang_index, L.total_mass, L.mass_moment, L.inertia0, L.B1, L.B2, L.W,
                  L.s, self._pattern_buffer(), self._A_blocks, self.sub_offsets, bs.perm, bs.po, bs.later_ptr,
                  bs.later_idx, bs.L)
        q, qd, inertia, Q, r = (np.empty_like(self.q), np.empty_like(self.q), np.empty((L.D, 3, 3)),
                                np.empty(self.S), np.empty(self.S))
        new = FrameState(np.empty_like(fr.c), np.empty_like(fr.R), np.empty_like(fr.v), np.empty_like(fr.w),
                         fr.w.copy())
        state_out = (q, qd, new.c, new.R, new.v, new.w, inertia)
        contact_rows, contact_s = None, 0.0
        t1 = time.perf_counter()
        if not contact:
            failed = linear_step_kernel(*system, *state_out, Q, r)
            kernel_s = time.perf_counter() - t1
        else:
            dQ, I_start = np.empty(self.S), np.empty((L.D, 3, 3))
            failed = linear_solve_kernel(*system, dQ, r, I_start)
            kernel_s = time.perf_counter() - t1
        if failed >= 0:
            return None
        self._start_eval = None                   # taken, as _step's _start_evaluation(take=True)
        self._dW = 0.0
        self._indefinite = False
        self._factor, self._resolve = bs, bs.solve
        r0 = r_last = float(np.linalg.norm(r))
        if contact:
            t_c = time.perf_counter()
            contact_rows = self._contact_rows(contact, gm, dt)
            Q0 = np.zeros(self.S)
            if contact_rows is not None:
                dQ, lam = self._contact_solve(contact_rows, Q0, dQ)
                # A body at rest pushed only by a collider has r0 = 0: measure the
                # tolerance against the contact forces' size instead (as _step).
                r0 = max(r0, float(np.linalg.norm(self._contact_force(contact_rows, lam))))
            Q = Q0 + 1.0 * dQ
            if gm is not None and self._contact_holds(contact_rows):
                gm = gm[:3] + (None,)
            t2 = time.perf_counter()
            contact_s = t2 - t_c
            linear_predict_kernel(self.q, fr.c, fr.R, fr.v, fr.w, Q, dt, gm is not None, C, V, W, L.r, L.movable,
                                  L.q_index, L.movers, L.lin_index, L.ang_index, L.inertia0, L.B1, L.B2, I_start,
                                  *state_out)
            kernel_s += time.perf_counter() - t2
        if len(L.movers):
            # _predict's _inertia_of(q): the next step starts from this q.
            inertia.flags.writeable = False
            self._inertia_kept = (q.copy(), inertia)
        if gm is not None and gm[3] is not None:
            self._rebalance(new, q, self.x_full, self.v_full, inertia, gm[3])
        self.q, self.qd, self.frames = q, qd, new
        contact_work = self._contact_outputs(contact, contact_rows, Q, dt)
        self.last = {"elastic": energy}
        self.timing = dict(timing, factor_ms=1e3 * kernel_s, solve_ms=0.0)
        self._report(t0, 1, r_last / r0 if r0 > 0 else 0.0, dt * float(F_app @ self.get_Q()), contact_work,
                     contact_s)
        if contact_rows is not None:
            self.stats.update(contact_stats(self._contact_info))
        self.timing = {}
        return self.stats

    def _contact_points(self, contact, verts):
        """Positions (m, 3) of the step's contact vertices verts (m,) at the new state.

        They are rows of the contact search's vertex set (the surface), whose positions at
        this state the next step's search reads first and the output reads too: taken from
        that pass, which positions_of keeps, the state costs one surface pass instead of
        that and another over the contact vertices (800 of them on the caterpillar's
        floor). Where positions_of keeps nothing (full-space domains) they are computed
        alone; a set too small to be kept costs next to nothing either way."""
        if self.F:
            return self.positions_of(verts)
        return self.positions_of(contact["vertices"])[self._contact_at]

    def _line_search(self, system, A, r, Q, dQ, terms, base, dt):
        """(step length, direction, halvings, mu) of a Newton iteration from Q along dQ: Armijo
        backtracking on the incremental potential, halving from 1 down to MIN_STEP.

        Where no length lowers the potential, the direction is replaced by the damped
        Newton direction (A + mu Mgen) dQ = -r, for mu in DAMPING (Levenberg-Marquardt):
        it turns towards the mass-weighted steepest descent and shortens, and it is a
        descent direction once A + mu Mgen is positive definite. Why it is needed: the
        tangent omits the derivative of J (§8), which is small next to the inertia until
        coupling elements carry large forces; in a stiff body spun fast (stability_study's
        reduced corotated corner, E 1e11 Pa, spun up to about 1000 rad/s by its load) it
        was ten times the angular inertia / dt^2, the plain direction raised the potential
        at every length down to 1e-4, and the old loop took that last length anyway: 23 J
        of elastic energy became 35,000 J in one sub-step. Returns length 0 (no step) when
        every damped direction fails too; the step then keeps the iterate it has."""
        p0, Fn, energy = terms
        phi0 = system.potential(Q, p0, Fn, energy)
        cuts = 0
        for mu in (0.0,) + DAMPING:
            if mu:
                dQ = self._solve(*system.shifted(A, mu), -r)
            slope = float(r @ dQ)
            if not slope < 0.0:              # an indefinite A's LU direction may climb
                continue
            step_len = 1.0
            while step_len >= MIN_STEP:
                trial = Q + step_len * dQ
                e_t = self._energy_at(trial, base, dt)
                if system.potential(trial, p0, Fn, e_t) <= phi0 + 1e-4 * step_len * slope:
                    return step_len, dQ, cuts, mu
                step_len *= 0.5
                cuts += 1
        return 0.0, dQ, cuts, mu

    def _predict(self, Q, base, dt):
        """State reached from the step-start state `base` with velocities Q over dt.

        Without a global motion Q holds inertial velocities and frame centres move on
        straight lines. With one (free bodies, see _global_motion) Q holds velocities
        relative to the body's mean rigid motion (C, V, W): every frame centre and
        full-space vertex is carried rigidly by exp(dt W) about C, plus its relative
        motion, so a rigid spin is integrated exactly instead of spiralling in under
        backward Euler.
        """
        q0, frames0, x0, gm, inertia0 = base
        L = self.layout
        qd = L.gather(Q)
        q = q0 + dt * qd
        v = frames0.v.copy()
        w = frames0.w.copy()
        v[L.movers] = Q[L.lin_index]
        w[L.movers] = Q[L.ang_index]
        v_full = self._full_expand(Q[self.S:]) if self.F else self.v_full
        # The angular rows solved I_pred w' = h (momentum form, see _mass_blocks) with the
        # inertia at the predicted rotation; predict re-expresses that momentum with the
        # inertia the domain really has after the step, so torque-free domains keep h exactly.
        # A pinned body's frames do not turn: no inertia is needed.
        mv = L.movers
        inertia = self._inertia_of(q) if len(mv) else None
        I_start, I_end = (inertia0, inertia) if len(mv) else (L.inertia0, L.inertia0)   # unread when pinned
        frames = frames0.predict(v, w, dt, self.movable, I_start, I_end, None if gm is None else gm[:3])
        if gm is None:
            x_full = x0 + dt * v_full if self.F else x0
        elif self.F:
            C, V, W = gm[:3]
            Rg, C1 = exp_so3(dt * W), C + dt * V
            rho_f = (x0 - C + dt * v_full) @ Rg.T
            x_full = np.where(self.is_full_vertex[:, None], C1 + rho_f, x0)
            v_full = np.where(self.is_full_vertex[:, None], V + cross(W, rho_f) + v_full @ Rg.T, 0.0)
        else:
            x_full = x0
        if gm is not None and gm[3] is not None:
            v_full = self._rebalance(frames, q, x_full, v_full, inertia, gm[3])
        return q, qd, frames, x_full, v_full

    def _rebalance(self, frames, q, x_full, v_full, inertia, L_target):
        """Carrying the state by exp(dt W) also turns its angular momentum by that
        rotation; where L is not parallel to W (products of inertia) this is a spurious
        precession, first order in dt. Restore the balance of angular momentum, L' =
        L_target = (L + dt tau_ext) / (1 + dt alpha), with a rigid rotation dW about the
        mass centre (linear momentum unchanged): frames (changed in place) at q with the
        body-frame inertia (D, 3, 3), full-space x_full, v_full. Returns v_full."""
        mv = self.layout.movers
        C1, _, L1, I1 = self._momentum(frames, q, x_full, v_full, inertia)
        dW = np.linalg.solve(I1, L_target - L1)
        self._dW = float(np.linalg.norm(dW))
        frames.v[mv] += cross(dW, frames.c[mv] - C1)
        frames.w[mv] += dW
        if self.F:
            v_full = np.where(self.is_full_vertex[:, None], v_full + cross(dW, x_full - C1), v_full)
        return v_full

    #: (q copy, layout.inertia(q)) of the last _inertia_of call.
    _inertia_kept = None

    def _inertia_of(self, q):
        """layout.inertia(q), kept for the last q (compared by value): a step's prediction
        computes the inertia at the state the next step starts from, which read it again."""
        kept = self._inertia_kept
        if kept is not None and np.array_equal(kept[0], q):
            return kept[1]
        inertia = self.layout.inertia(q)
        inertia.flags.writeable = False
        self._inertia_kept = (q.copy(), inertia)
        return inertia

    def _energy_at(self, Q, base, dt):
        q, _, frames, x_full, _ = self._predict(Q, base, dt)
        return self._evaluate(q, frames, x_full, want_hessian=False)[4]

    def elastic_energy(self):
        # The evaluation at the current state is the one the next step starts from: the
        # stability guard's energy check after a step costs the next step nothing.
        return self._start_evaluation()[0][4]

    def _start_evaluation(self, take=False):
        """((G, K_ss, K_sI, K_ff, energy, J, x_I), timing) of _evaluate at the current state,
        computed once per state: the cache holds the state objects it was computed from
        (every step and set_state replace them) and is dropped when a step takes it."""
        # Cutting replaces _full_alive: the forces changed, so it is part of the key.
        c = self._start_eval
        # Compared one by one, not all() over a generator: this runs twice a guarded step.
        if c is None or not (c[0][0] is self.q and c[0][1] is self.frames and c[0][2] is self.x_full
                             and c[0][3] is self._full_alive):
            result = self._evaluate(self.q, self.frames, self.x_full)
            c = ((self.q, self.frames, self.x_full, self._full_alive), result, self.evaluation_timing)
        self._start_eval = None if take else c
        return c[1], c[2]
