"""Stability guard: detect a diverging step, roll it back and retry it more carefully.

docs/method.md §15 lists the known limits of the method: explicit fictitious forces, a
single Newton iteration, stiff or nearly incompressible materials, fast rotation. Rather
than make every step expensive, the Simulator steps as configured and this guard checks
the result. After every step it measures the state and looks for

hard signs (the step is rejected):
  * non-finite  -- a NaN or Inf in positions, velocities or energy, or a numerical error
                   raised by the solver (singular or indefinite system, failed SVD);
  * energy      -- the total energy E = kinetic + elastic + gravity potential grew by more
                   than `energy_growth` x (E_kin + E_el before, + |work of the inputs|
                   + |change of gravity potential| + a floor) beyond the work W done by
                   the applied loads and contact forces over the step:
                   E1 - E0 - W > energy_growth * scale. Backward Euler dissipates, so a
                   step that creates energy is diverging;
  * energy drift-- a step that creates energy (each under that bound) while the energy
                   created since the last reset, E - E(0) - W(0..t), exceeds
                   `energy_growth` x the run's energy scale (max over the run of
                   E_kin + E_el + |W| + |gravity potential change|): slow pumping;
  * speed       -- a vertex faster than `max_speed` m/s;
soft signs (a retry is attempted; if none clears them the best finite attempt is kept):
  * inversion   -- more inverted tets (det F <= 0) after the step than before;
  * newton      -- Newton iterations (newton_iterations > 1) whose last residual is more
                   than NEWTON_DIVERGED x the first, or a reduced line search that found no
                   descent from the first iterate (stats newton_stalled "first").

A rejected step is rolled back to the snapshot taken before it (model state, collider
sweep bookkeeping) and retried along a ladder of attempts, cheapest first: the same dt
with `newton_iterations` Newton iterations (backward Euler solved properly instead of
linearly implicit), for a reduced model whose fictitious forces are explicit (the papers')
then also with implicit fictitious forces (StepOptions.fictitious = "implicit"), then dt
split into 2, 4, ... `max_substeps` sub-steps (each checked on its own) with all of that.
On that last rung a sub-step whose only hard signs are "energy" / "energy drift" gets an
energy projection (`project_energy`, in the spirit of Dinev, Liu and Kavan 2018,
"Stabilizing integrators for real-time physics", ACM TOG 37(1)): the velocities relative to
the mass centre are scaled so that the total energy does not exceed its budget, the energy
before the sub-step plus the work of the loads over it; linear momentum is kept. It cannot
remove energy the positions hold (elastic or potential energy above the budget): such a
sub-step stays rejected. (It does not pay back drift accepted earlier; it stops its growth.)
The first attempt that passes is kept ("recovered"), with one exception for margin: a
retry that passes while creating more than MARGIN x `energy_growth` of the step's scale
is tried once more on the next rung, and the one that creates less energy is kept (the
run's drift budget is shared by its steps; a step kept at the bound leaves the next
nothing: a reduced block tumbled by a 5 m/s sphere passed at 8 sub-steps with 0.088 of
the scale, and the next step then failed every rung on the drift). Soft signs alone stop
the ladder at SOFT_MAX_SUBSTEPS sub-steps.
Inverted elements left at the end of `untangle_after` accepted steps in a row (a tangle the
model holds in place rather than a transient) are untangled on a reduced model
(ReducedModel.untangle: modal coordinates and frames shrunk towards a rigid placement of the
rest shape, by the least factor found that leaves none; kept only if that creates no energy
beyond half the drift budget;
reported "recovered", action "untangled (deformation x s)"). A reduced model needs it because
its subspace may hold no path out of an inverted state (a full-space model gets out through
its materials' compression barrier, fem/materials.py).
If no rung passes from a start state with inverted elements (a tangle the last steps
kept), that start is untangled as above (if that creates no energy beyond the same budget)
and the ladder is walked once more from there (action "untangled the start (deformation x
s), ..."). If none passes the hard checks, the state before the step is restored and the
step is marked "failed": the guard never lets a NaN out. Simulated time still advances (the
simulation goes on, holding its last good state).

Per step the guard reports (merged into Simulator.stats()):
  stability "stable" | "recovered" | "degraded" (soft signs left) | "failed",
  guard_reason (what was detected first), guard_action (what fixed it), guard_attempts,
  guard_substeps, guard_projected (kinetic energy removed by energy projections in the step,
  J), guard_indefinite_steps (accepted steps whose reduced system matrix was
  indefinite and solved by LU, see ReducedModel._solve), guard_work (work of the loads and contacts over the step, as the model
  accounts it), guard_untangled (the untangle factor, on a step that untangled), and running
  totals guard_recoveries, guard_failures, guard_degraded, guard_projections (steps kept
  with an energy projection), guard_untangles.
"""
from dataclasses import dataclass, field

import numpy as np

from .errors import MdssError
from .loads import sparse_loads
from .step_options import StepOptions
from .state_measure import Measure, inverted_tets  # noqa: F401  (guard.Measure, guard.inverted_tets)

try:
    # What np.errstate sets and resets (numpy >= 2): the floating-point context is a
    # contextvar holding an "extobj" made by _make_extobj. StabilityGuard.step sets it
    # itself with an extobj made once per context it starts from; np.errstate builds a new
    # one on every entry (about 0.7 us of the guard's ~10 us, every step).
    from numpy._core._ufunc_config import _extobj_contextvar, _make_extobj
except ImportError:                        # another numpy: np.errstate as it is
    _extobj_contextvar = _make_extobj = None

#: Exceptions a diverging step raises (singular or indefinite systems, SVD of NaN,
#: "array must not contain infs or NaNs"). Configuration errors (MdssError) pass through.
NUMERICAL_ERRORS = (ArithmeticError, ValueError, RuntimeError)
#: Soft signs alone stop the ladder at this many sub-steps (see StabilityGuard.step).
SOFT_MAX_SUBSTEPS = 4
#: Newton "diverged": its last residual is this many times its first (a line search keeps
#: the incremental potential decreasing, but the residual norm need not fall monotonically).
NEWTON_DIVERGED = 10.0
#: A retry passing with more than this share of the energy bound tries the next rung too.
MARGIN = 0.5
#: Hard signs an energy projection may clear (see project_energy).
ENERGY_SIGNS = frozenset(("energy", "energy drift"))
#: The ladder's rung for the model's own step: one sub-step, its own Newton iterations and
#: fictitious forces, no energy projection (StabilityGuard._ladder, _own_step).
OWN_RUNG = (1, None, False, False)
_NEG_INF = float("-inf")
#: The report of a step whose own step passed (StabilityGuard._stable), in _step's key
#: order; energy_growth and guard_work are placeholders, the totals and guard_last_event
#: follow.
_STABLE_REPORT = {"guard_attempts": 1, "guard_reason": "", "guard_substeps": 1, "guard_action": "",
                  "stability": "stable", "guard_projected": 0.0, "energy_growth": 0.0, "guard_work": 0.0}


@dataclass
class GuardSettings:
    """The scene's model.guard section (mdss_ros.scene.SCHEMA holds the defaults)."""

    enabled: bool = True
    energy_growth: float = 0.1
    max_speed: float = 1.0e3
    max_substeps: int = 64
    newton_iterations: int = 4
    inversion: bool = True
    energy_projection: bool = True
    untangle_after: int = 10

    @classmethod
    def from_scene(cls, section):
        return cls(**{k: section[k] for k in cls.__dataclass_fields__ if k in section})


def measure(model, tets, gravity, check_inversion=True):
    """Measure a model's current state (see Measure); each model measures itself in its own
    coordinates (model_api.Model.guard_measure; tets are the body's). Never raises on NaN."""
    return model.guard_measure(gravity, check_inversion)


@dataclass
class Verdict:
    hard: list = field(default_factory=list)      # reasons the state must be rejected
    soft: list = field(default_factory=list)      # reasons to try again if possible
    growth: float = 0.0                           # (E1 - E0 - W) / scale
    inverted: int = 0

    @property
    def ok(self):
        return not self.hard and not self.soft


class StabilityGuard:
    """Checks and retries the steps of one model; see the module docstring.

    model: a FullSpaceModel or ReducedModel (get_state, set_state, set_dt, dt,
    vertex_positions, vertex_velocities, elastic_energy, vertex_mass); tets (n_tets, 4).
    """

    def __init__(self, model, tets, settings=None):
        self.model = model
        self.tets = np.asarray(tets)
        self.settings = settings or GuardSettings()
        self._ladder_for = None
        self._floor = None
        self._fp_from = self._fp_ignore = None       # step's floating-point context
        self.reset()

    def reset(self):
        """Forget the cached measurement and the running totals (Simulator.reset)."""
        self.totals = {"guard_recoveries": 0, "guard_failures": 0, "guard_degraded": 0,
                       "guard_substeps_total": 0, "guard_indefinite_steps": 0, "guard_projections": 0,
                       "guard_untangles": 0}
        self._inverted_run = 0
        self.last_event = ""
        self.invalidate()

    def invalidate(self):
        """The state changed outside a step: measure it afresh before the next step, and
        start a new energy ledger (E0, work of the loads so far, run energy scale) there."""
        self._cached = None
        self._ledger = None

    def _scale_floor(self, gravity):
        if self._floor is None:
            x0 = self.model.vertex_positions()
            size = float(np.linalg.norm(x0.max(0) - x0.min(0))) or 1.0
            mass = float(self.model.vertex_mass.sum())
            self._floor = 1e-9 * mass * (float(np.linalg.norm(gravity)) + 1.0) * size
        return self._floor

    def judge(self, before, after, work, model_stats, gravity):
        """Verdict on a (sub-)step from Measure before to Measure after, with work W of the
        applied loads and contacts over it and the model's step stats."""
        hard, soft, growth = self._signs(before, after, work, model_stats, gravity)
        return Verdict(hard=list(hard), soft=list(soft), growth=growth, inverted=after.inverted)

    def _signs(self, before, after, work, model_stats, gravity):
        """judge's checks as (hard signs, soft signs, growth): tuples, () when there are
        none, so the common case (a step that passes) builds no Verdict and no list."""
        s = self.settings
        if not after.finite:
            return ("non-finite",), (), 0.0
        hard, soft = (), ()
        floor = self._floor if self._floor is not None else self._scale_floor(gravity)
        # Measure.total and _run_scale spelled out, the same operations in the same order:
        # this runs after every step, and their calls were a third of it.
        b_kinetic, b_elastic, b_gravity = before.kinetic, before.elastic, before.gravity
        a_elastic, a_gravity = after.elastic, after.gravity
        a_total = after.kinetic + a_elastic + a_gravity
        # max(x, 0.0) written as max evaluates it (it keeps x unless 0.0 > x: the same float
        # for NaN and -0.0), without the builtin call.
        scale = b_kinetic + (0.0 if 0.0 > b_elastic else b_elastic) + abs(work) + abs(a_gravity - b_gravity) + floor
        growth = (a_total - (b_kinetic + b_elastic + b_gravity) - work) / scale
        if growth > s.energy_growth:
            hard = ("energy",)
        elif growth > 0.0 and self._ledger is not None:
            # Slow creation: each step under the bound, the run's total over it.
            E0, W, run_scale = self._ledger
            run_work = W + self._work + work
            run_scale = max(run_scale, after.kinetic + (0.0 if 0.0 > a_elastic else a_elastic) + abs(run_work)
                            + abs(a_gravity - self._G0) + floor)          # _run_scale(after, run_work)
            if (a_total - E0 - W - self._work - work) / run_scale > s.energy_growth:
                hard = ("energy drift",)
        if after.speed is not None:
            speed = after.speed
        else:
            speed = float(np.sqrt((after.v * after.v).sum(1).max())) if len(after.v) else 0.0
        if speed > s.max_speed:
            hard += ("speed",)
        if s.inversion and after.inverted > before.inverted:
            soft = ("inversion",)
        res = model_stats.get("residual") if isinstance(model_stats, dict) else None
        if model_stats.get("newton_iterations", 1) > 1 and res is not None and not res <= NEWTON_DIVERGED:
            soft += ("newton",)
        elif model_stats.get("newton_stalled") == "first":
            # The reduced line search found no descent from the first iterate, and the step
            # ended with no relative motion (reduced/step.py, Step._line_search).
            soft += ("newton",)
        return hard, soft, growth

    def _current(self, gravity, step_count):
        if self._cached is None or self._cached[0] != step_count:
            self._cached = (step_count, measure(self.model, self.tets, gravity, self.settings.inversion))
        if self._ledger is None and self._cached[1].finite:
            m = self._cached[1]
            self._G0 = m.gravity
            self._ledger = (m.total, 0.0, self._run_scale(m, 0.0))
        return self._cached[1]

    def _run_scale(self, m, work):
        """Energy scale of the run at a state: E_kin + E_el + |work so far| + |gravity potential
        change| (+ a floor); the run's scale is its maximum so far."""
        return (m.kinetic + max(m.elastic, 0.0) + abs(work) + abs(m.gravity - self._G0)
                + self._scale_floor(self._gravity))

    def step(self, advance, save, restore, f_app, gravity, step_count):
        """Advance one step of the model's dt through the guard.

        advance(k, n, options): run sub-step k (1..n) of n with these StepOptions (dt / n,
        and the Newton iterations and fictitious forces of the attempt), returning the
        model's stats; save() -> snapshot and restore(snapshot) cover everything
        a step changes. f_app (n_verts, 3) are the applied loads (their work is allowed),
        gravity (3,). Returns (model stats, guard report dict).
        """
        if not self.settings.enabled:
            return advance(1, 1, None), {"stability": "unchecked"}
        # One floating-point context for the whole step, retries and measures included: the
        # guard's business is non-finite states, and entering np.errstate costs a few us,
        # which was a tenth of the guard's own time on a 12-DOF model.
        cv = _extobj_contextvar
        if cv is None:
            with np.errstate(all="ignore"):
                return self._step(advance, save, restore, f_app, gravity, step_count)
        # np.errstate(all="ignore") exactly: _make_extobj takes what it is not given (buffer
        # size, error callback) from the current context, so the extobj is made again
        # whenever the current context is another object than the one it was made from.
        current = cv.get()
        if current is not self._fp_from:
            self._fp_from, self._fp_ignore = current, _make_extobj(all="ignore")
        token = cv.set(self._fp_ignore)
        try:
            return self._step(advance, save, restore, f_app, gravity, step_count)
        finally:
            cv.reset(token)

    def _step(self, advance, save, restore, f_app, gravity, step_count):
        dt = self.model.dt
        self._gravity = gravity
        self._work = 0.0
        c = self._cached
        # _current's common case: the state the last step ended in, measured by it.
        before = c[1] if c is not None and c[0] == step_count and self._ledger is not None else \
            self._current(gravity, step_count)
        snap = save()
        # _ladder's cache read inline (its key is what a step may not change; checked every step).
        model = self.model
        lf = self._ladder_for
        ladder = lf[1] if lf is not None and lf[0] == (model.newton_iterations, model.fictitious) else self._ladder()
        first = None
        if ladder[0] == OWN_RUNG:
            # The model's own step, run every step: judged without a Verdict, and when it
            # passes leaving nothing inverted, reported by _stable without _walk.
            stats, after, signs = self._own_step(advance, before, f_app, gravity)
            if signs is not None and not signs[0] and not signs[1] and not after.inverted:
                # max(-inf, growth): the Verdict's growth, as _own_verdict makes it (NaN -> -inf),
                # written as the comparison max makes.
                growth = signs[2]
                return stats, self._stable(stats, growth if growth > _NEG_INF else _NEG_INF, after, step_count)
            first = (stats, _own_verdict(signs, after), after)
        attempt, best, stats, verdict, after, first_reason = self._walk(ladder, advance, save, restore, snap,
                                                                        before, f_app, gravity, dt, first)
        if attempt == 0 and not after.inverted and not self._projected[0]:
            # The common case, the model's own step passed and left no inverted element:
            # its report without the branches below (they run after every step).
            return stats, self._stable(stats, verdict.growth, after, step_count)
        start_untangled = None
        if attempt is None and best is None and before.inverted:
            # No rung passes from a tangled start (inverted elements the last steps kept):
            # untangle the start state as the untangle_after rule would, and walk once more.
            restore(snap)
            start_untangled = self._untangle_start(before, gravity)
            if start_untangled is not None:
                factor, before_u = start_untangled
                snap_u = save()
                attempt, best, stats, verdict, after, _ = self._walk(ladder, advance, save, restore, snap_u,
                                                                     before_u, f_app, gravity, dt)
                if attempt is None and best is None:
                    start_untangled = None
        report = {"guard_attempts": (attempt if attempt is not None else len(ladder) - 1) + 1,
                  "guard_reason": first_reason or "", "guard_substeps": 1, "guard_action": ""}
        if attempt == 0 and start_untangled is None:
            report["stability"] = "stable"
        elif attempt is not None:
            n_sub, newton, implicit, _ = ladder[attempt]
            report.update(stability="recovered", guard_substeps=n_sub,
                          guard_action=_action(n_sub, newton, implicit, self._projected[0] > 0))
            self.totals["guard_recoveries"] += 1
        elif best is not None:
            # Soft signs everywhere: keep the finite attempt with the fewest inverted tets.
            attempt, verdict, state, stats, after, self._work, self._projected = best
            restore(state)
            n_sub, newton, implicit, _ = ladder[attempt]
            report.update(stability="degraded", guard_substeps=n_sub,
                          guard_action=_action(n_sub, newton, implicit, self._projected[0] > 0),
                          guard_left=",".join(verdict.soft))
            self.totals["guard_degraded"] += 1
        else:
            restore(snap)
            after = before
            self._work = 0.0
            self._projected = (0, 0.0)
            stats = dict(stats or {})
            report.update(stability="failed", guard_action="rolled back to the last good state")
            self.totals["guard_failures"] += 1
        self.totals["guard_substeps_total"] += report["guard_substeps"]
        report["guard_projected"] = float(self._projected[1])
        if self._projected[0]:
            self.totals["guard_projections"] += 1
        if report["stability"] != "failed" and isinstance(stats, dict) and stats.get("indefinite_system"):
            # The reduced solver met an indefinite A and took an LU Newton step; the checks
            # above accepted its result. Counted so a run shows how often that happened.
            self.totals["guard_indefinite_steps"] += 1
        if start_untangled is not None:
            report["guard_reason"] = ",".join(r for r in (report["guard_reason"], "no rung from a tangled start") if r)
            report["guard_action"] = ", ".join(a for a in (f"untangled the start (deformation x {start_untangled[0]:.3f})",
                                                           report["guard_action"]) if a)
            report["guard_untangled"] = float(start_untangled[0])
            self.totals["guard_untangles"] += 1
        if report["stability"] != "failed" and after.finite:
            after = self._untangle(after, report, gravity)
        if report["stability"] != "stable":
            self.last_event = (f"step {step_count + 1}: {report['stability']} ({report['guard_reason']}"
                               f"{'; ' + report['guard_action'] if report['guard_action'] else ''})")
        self._cached = (step_count + 1, after)
        if self._ledger is not None and after.finite:
            E0, W, run_scale = self._ledger
            W += self._work
            self._ledger = (E0, W, max(run_scale, self._run_scale(after, W)))
        report["energy_growth"] = float(verdict.growth) if attempt is not None else float("nan")
        report["guard_work"] = float(self._work)         # work of loads and contacts over the step
        report.update(self.totals, guard_last_event=self.last_event)
        return stats, report

    def _stable(self, stats, growth, after, step_count):
        """The report and bookkeeping of _step for a step whose first rung passed with no
        energy projection and left no inverted element (the same keys in the same order,
        values and totals as _step's general path gives it: "stable", one attempt, one
        sub-step). growth: the step's (E1 - E0 - W) / scale."""
        totals = self.totals
        totals["guard_substeps_total"] += 1
        if isinstance(stats, dict) and stats.get("indefinite_system"):
            totals["guard_indefinite_steps"] += 1       # see _step
        self._inverted_run = 0                          # _untangle with nothing inverted
        self._cached = (step_count + 1, after)
        work = self._work
        ledger = self._ledger
        if ledger is not None:                          # after is finite: the rung passed
            E0, W, run_scale = ledger
            W += work
            # _run_scale(after, W), spelled out (_signs has set the floor)
            floor = self._floor if self._floor is not None else self._scale_floor(self._gravity)
            elastic = after.elastic                     # max(a, b) as in _signs: b if b > a else a
            scale = after.kinetic + (0.0 if 0.0 > elastic else elastic) + abs(W) + abs(after.gravity - self._G0) + floor
            self._ledger = (E0, W, scale if scale > run_scale else run_scale)
        # A copy of the constant part, then the step's values into its placeholders (a
        # dict display of eight keys and update(..., key=) cost more, every step).
        report = _STABLE_REPORT.copy()
        report["energy_growth"] = float(growth)
        report["guard_work"] = float(work)
        report.update(totals)
        report["guard_last_event"] = self.last_event
        return report

    def _walk(self, ladder, advance, save, restore, snap, before, f_app, gravity, dt, first=None):
        """Try the ladder's rungs from the snapshot until one passes. first: the first
        rung's (stats, Verdict, after) when _step has run it already. Returns (attempt index
        or None, best soft-only attempt or None, stats, verdict, after, first reason)."""
        first_reason, best, stats, verdict, after = None, None, None, None, before
        for attempt, (n_sub, newton, implicit, project) in enumerate(ladder):
            if attempt:
                restore(snap)
            if first is not None and not attempt:
                stats, verdict, after = first
            else:
                stats, verdict, after = self._attempt(advance, before, f_app, gravity, dt, n_sub, newton,
                                                      implicit, project)
            if verdict.ok:
                if attempt and attempt + 1 < len(ladder) and verdict.growth > MARGIN * self.settings.energy_growth:
                    return self._with_margin(ladder, attempt, advance, save, restore, snap, before, f_app, gravity,
                                             dt, (stats, verdict, after), best, first_reason)
                return attempt, best, stats, verdict, after, first_reason
            if first_reason is None:
                first_reason = ",".join(verdict.hard + verdict.soft)
            if not verdict.hard and (best is None or verdict.inverted < best[1].inverted):
                best = (attempt, verdict, save(), stats, after, self._work, self._projected)
            if not verdict.hard and n_sub >= SOFT_MAX_SUBSTEPS:
                # Soft signs that survive sub-steps are usually physical (a crushed element):
                # do not spend the whole ladder on them every step.
                break
        return None, best, stats, verdict, after, first_reason

    def _with_margin(self, ladder, attempt, advance, save, restore, snap, before, f_app, gravity, dt, passed,
                     best, first_reason):
        """_walk's return for a retry that passed near the energy bound (MARGIN): the next
        rung is tried from the snapshot, and whichever passes creating less energy is kept."""
        stats, verdict, after = passed
        kept = (save(), self._work, self._projected)
        restore(snap)
        n_sub, newton, implicit, project = ladder[attempt + 1]
        stats2, verdict2, after2 = self._attempt(advance, before, f_app, gravity, dt, n_sub, newton, implicit,
                                                 project)
        if verdict2.ok and verdict2.growth < verdict.growth:
            return attempt + 1, best, stats2, verdict2, after2, first_reason
        restore(kept[0])
        self._work, self._projected = kept[1], kept[2]
        return attempt, best, stats, verdict, after, first_reason

    def _untangle_start(self, before, gravity):
        """The start-state rule of step(): the step's start untangled (see _untangled_state)."""
        return self._untangled_state(before, gravity)

    def _untangled_state(self, reference, gravity):
        """Untangle the model's current state (ReducedModel.untangle). Returns (factor,
        Measure of the untangled state), or None with the state as it was: the model cannot
        untangle, nothing is inverted, s = 0 is inverted too, or the untangle would create
        energy beyond reference's budget (_untangle_affordable)."""
        s = self.settings
        if not (s.inversion and self.model.can_untangle):
            return None
        snap = self.model.get_state()
        factor = self.model.untangle(self.tets)
        if factor is None or factor == 1.0:       # the model left its state alone
            return None
        untangled = measure(self.model, self.tets, gravity, s.inversion)
        if not untangled.finite or not self._untangle_affordable(reference, untangled):
            self.model.set_state(snap)
            return None
        return factor, untangled

    def _untangle(self, after, report, gravity):
        """Inverted elements left after `untangle_after` accepted steps in a row: a reduced
        model whose subspace cannot undo them (a tangle its modes and frames hold in place)
        gets ReducedModel.untangle, its deformation shrunk towards a rigid placement of the
        rest shape just enough that none is left. Kept only if it creates no energy beyond
        half the drift budget (_untangle_affordable).
        Returns the Measure of the state the step ends in."""
        s = self.settings
        if not (s.inversion and s.untangle_after > 0 and self.model.can_untangle) or not after.inverted:
            self._inverted_run = 0
            return after
        self._inverted_run += 1
        if self._inverted_run < s.untangle_after:
            return after
        self._inverted_run = 0
        done = self._untangled_state(after, gravity)
        if done is None:
            return after
        factor, untangled = done
        if report["stability"] == "stable":
            report["stability"] = "recovered"
            self.totals["guard_recoveries"] += 1
        report["guard_reason"] = ",".join(r for r in (report["guard_reason"], "inversion left") if r)
        report["guard_action"] = ", ".join(a for a in (report["guard_action"],
                                                       f"untangled (deformation x {factor:.3f})") if a)
        report["guard_untangled"] = float(factor)
        self.totals["guard_untangles"] += 1
        return untangled

    def _untangle_affordable(self, after, untangled):
        """An untangle may not create energy, except within half the drift budget: moving a
        pinned body that sags under gravity towards its rest shape raises its potential
        energy. Allowed while the energy created since the ledger began, E - E0 - W, stays
        under energy_growth / 2 x the run's energy scale (the drift check's own bound,
        halved to leave the integrator room)."""
        if untangled.total <= after.total + 1e-12 * abs(after.total):
            return True
        if self._ledger is None:
            return False
        E0, W, run_scale = self._ledger
        W += self._work
        run_scale = max(run_scale, self._run_scale(untangled, W))
        return untangled.total - E0 - W <= 0.5 * self.settings.energy_growth * run_scale

    def _ladder(self):
        """The retries, most careful last: (sub-steps, Newton iterations or None, implicit
        fictitious forces, energy projection) per rung. It depends on the settings and on the
        model's own iterations and fictitious treatment, so it is built once."""
        key = (self.model.newton_iterations, self.model.fictitious)
        if self._ladder_for is None or self._ladder_for[0] != key:
            s = self.settings
            newton = s.newton_iterations if s.newton_iterations > key[0] else None
            # Reduced models that integrate fictitious forces explicitly get them implicit on retries.
            implicit = key[1] == "explicit"
            ladder = [(1, None, False)] + ([(1, newton, False)] if newton else []) + \
                ([(1, newton, True)] if implicit else []) + \
                [(n, newton, implicit) for n in _powers_of_two(2, s.max_substeps)]
            # The last rung may project energy (module docstring): the most careful integration
            # first, the projection only for what is left of the energy it created.
            ladder = [rung + (s.energy_projection and i == len(ladder) - 1,) for i, rung in enumerate(ladder)]
            self._ladder_for = (key, ladder)
        return self._ladder_for[1]

    def _attempt(self, advance, before, f_app, gravity, dt, n_sub, newton, implicit=False, project=False):
        """Run n_sub sub-steps (optionally with more Newton iterations and implicit fictitious
        forces), judging each; project=True: a sub-step with only energy signs gets an energy
        projection and is judged again (self._projected counts them: (sub-steps, J removed)).
        Returns (model stats, Verdict, Measure after) and stops at the first bad sub-step."""
        model = self.model
        # The first rung is the model's own step: no options to apply.
        if n_sub == 1 and not newton and not implicit and not project:
            stats, after, signs = self._own_step(advance, before, f_app, gravity)
            return stats, _own_verdict(signs, after), after
        options = (None if n_sub == 1 and not newton and not implicit else
                   StepOptions(dt=dt / n_sub, newton_iterations=newton, fictitious="implicit" if implicit else None))
        stats, verdict, prev = {}, Verdict(growth=-np.inf), before
        self._work = 0.0
        self._projected = (0, 0.0)
        for k in range(1, n_sub + 1):
            try:
                stats = advance(k, n_sub, options)
            except MdssError:
                raise
            except NUMERICAL_ERRORS as err:
                v = Verdict(hard=["non-finite"])
                self.last_error = f"{type(err).__name__}: {err}"
                return {"error": self.last_error}, v, prev
            after = measure(model, self.tets, gravity, self.settings.inversion)
            work = _work(f_app, prev, after, model.contact,
                         stats.get("external_work") if isinstance(stats, dict) else None,
                         stats.get("contact_work") if isinstance(stats, dict) else None)
            v = self.judge(prev, after, work, stats, gravity)
            if project and v.hard and set(v.hard) <= ENERGY_SIGNS:
                # Budget: no energy created by this sub-step (E <= E_before + work); the
                # drift check only judges sub-steps that create energy, so this clears it too.
                # (a hair below it: landing exactly on it leaves round-off growth, which
                # the drift check would judge.)
                excess = after.total - (prev.total + work)
                removed = project_energy(model, after, excess + 1e-9 * abs(excess) + 1e-12 * after.kinetic)
                if removed is not None:
                    after = measure(model, self.tets, gravity, self.settings.inversion)
                    v = self.judge(prev, after, work, stats, gravity)
                    self._projected = (self._projected[0] + 1, self._projected[1] + removed)
            if v.hard:
                return stats, v, after
            # Soft signs do not cut an attempt short (a kept attempt must cover all of dt).
            verdict = Verdict(soft=sorted(set(verdict.soft) | set(v.soft)) if v.soft or verdict.soft else [],
                              growth=max(verdict.growth, v.growth), inverted=v.inverted)
            self._work += work
            prev = after
        return stats, verdict, prev

    def _own_step(self, advance, before, f_app, gravity):
        """_attempt for the model's own step (one sub-step, no StepOptions, no projection: the
        first rung, run every step): what _attempt's loop does for it, judged by _signs.
        Returns (model stats, Measure after, signs): signs (hard, soft, growth) as _signs
        gives them, or None when the step raised a numerical error (after is then before);
        _own_verdict makes the Verdict _attempt would have made of them."""
        self._work = 0.0
        self._projected = (0, 0.0)
        try:
            stats = advance(1, 1, None)
        except MdssError:
            raise
        except NUMERICAL_ERRORS as err:
            self.last_error = f"{type(err).__name__}: {err}"
            return {"error": self.last_error}, before, None
        model = self.model
        after = model.guard_measure(gravity, self.settings.inversion)
        if isinstance(stats, dict):
            mw, cw = stats.get("external_work"), stats.get("contact_work")
            if mw is not None and (cw is not None or not model.contact):
                work = float(mw) + (float(cw) if cw is not None else 0.0)     # _work's first case
            else:
                work = _work(f_app, before, after, model.contact, mw, cw)
        else:
            work = _work(f_app, before, after, model.contact)
        signs = self._signs(before, after, work, stats, gravity)
        if not signs[0]:
            self._work += work
        return stats, after, signs


def _own_verdict(signs, after):
    """The Verdict of StabilityGuard._own_step's result, as _attempt's loop makes it: a
    numerical error (signs None) is "non-finite"; hard signs are kept as judged; otherwise
    the soft signs merge into a Verdict(growth=-inf) (max(-inf, growth): the same float)."""
    if signs is None:
        return Verdict(hard=["non-finite"])
    hard, soft, growth = signs
    if hard:
        return Verdict(hard=list(hard), soft=list(soft), growth=growth, inverted=after.inverted)
    return Verdict(soft=sorted(set(soft)) if soft else [], growth=max(-np.inf, growth), inverted=after.inverted)


def mean_motion(model):
    """(total mass M, mass-centre velocity V (3,)) of a model; V = 0 when pins hold the body
    (then nothing conserves momentum and all motion is scaled)."""
    return model.mean_motion()


def project_energy(model, after, excess):
    """Energy projection: remove `excess` J (> 0) of kinetic energy from the model's current
    state, measured as `after` (Measure), by scaling the motion relative to the mass centre,
    v <- V + s (v - V) (ReducedModel.scale_relative_motion for the reduced model). With
    E_kin = 1/2 M |V|^2 + E_rel (no cross term: V is the mass-weighted mean velocity),
    s = sqrt((E_rel - excess) / E_rel) takes exactly `excess` out and keeps linear momentum;
    angular momentum about the mass centre scales by s. Returns the energy removed, or None
    when it cannot be done (excess not positive or not below E_rel: positions hold the
    created energy)."""
    if not (excess > 0.0) or not after.finite:
        return None
    M, V = mean_motion(model)
    rel = after.kinetic - 0.5 * M * float(V @ V)
    if not (rel > excess):
        return None
    s = float(np.sqrt((rel - excess) / rel))
    model.scale_relative_motion(s, V)
    return float(excess)


def _work(f_app, before, after, contact, model_work=None, contact_work=None):
    """Work of the applied loads (constant over the step) and of the contact forces on the
    body over a (sub-)step. For the loads: the model's own account when it reports one
    (ReducedModel: dt F_app . Q', its backward-Euler work, which stays right when a frame
    turns a large angle in one step), else sum f . (x_after - x_before) (= dt f . v' for
    backward Euler in full space). Contacts: sum f . (x_after - x_before)."""
    if model_work is not None and (contact_work is not None or not contact):
        # The models' own accounts (a reduced step reports both): no arrays to read.
        return float(model_work) + (float(contact_work) if contact_work is not None else 0.0)
    if model_work is not None:
        w = float(model_work)
    else:
        ids, f = sparse_loads(f_app)
        w = float((f * (after.x[ids] - before.x[ids])).sum()) if len(ids) else 0.0
    if contact_work is not None:
        w += float(contact_work)
    elif contact and len(contact.get("vertices", ())):
        ids = np.asarray(contact["vertices"])
        w += float((contact["forces"] * (after.x[ids] - before.x[ids])).sum())
    return w


def _action(n_sub, newton, implicit=False, projected=False):
    parts = []
    if newton:
        parts.append(f"{newton} Newton iterations")
    if implicit:
        parts.append("implicit fictitious forces")
    if n_sub > 1:
        parts.append(f"{n_sub} sub-steps")
    if projected:
        parts.append("energy projection")
    return "rollback, " + " x ".join(parts) if parts else "rollback"


def _powers_of_two(lo, hi):
    out, n = [], lo
    while n <= hi:
        out.append(n)
        n *= 2
    return out
