"""The stability guard (mdss_ros/guard.py) and the model state accessors it rolls back with."""
import numpy as np
import pytest

from mdss_ros import Simulator, load_scene
from mdss_ros.guard import inverted_tets
from mdss_ros.precompute import PrecomputeCache

SMALL = {"body.mesh.cell": 0.05, "model.cubature": {"samples": 0, "interface": "exact"}, "model.modes": 6}


def _sim(kind, **over):
    scene = load_scene("cantilever", overrides=dict(SMALL, **{"model.kind": kind}, **over))
    return Simulator(scene, cache=PrecomputeCache(enabled=False))


@pytest.fixture(scope="module", params=["full", "reduced"])
def sim(request):
    return _sim(request.param)


def _state_arrays(sim):
    return sim.vertex_positions().copy(), sim.model.vertex_velocities().copy()


def test_state_round_trip_restores_and_replays_exactly(sim):
    sim.reset()
    sim.set_wrench("tip", force=(0, 0, -20.0))
    sim.step(3)
    snap = sim.model.get_state()
    x0, v0 = _state_arrays(sim)
    sim.step(2)
    x2, v2 = _state_arrays(sim)
    assert np.abs(x2 - x0).max() > 1e-6               # the state really moved
    sim.model.set_state(snap)
    np.testing.assert_array_equal(sim.vertex_positions(), x0)
    np.testing.assert_array_equal(sim.model.vertex_velocities(), v0)
    sim.guard.invalidate()
    sim.step(2)                                       # same inputs: same trajectory
    np.testing.assert_allclose(sim.vertex_positions(), x2, rtol=0, atol=1e-12)
    # the snapshot is a copy: stepping did not change it
    sim.model.set_state(snap)
    np.testing.assert_array_equal(sim.vertex_positions(), x0)


def test_reduced_state_round_trip_of_a_spinning_free_body():
    sim = Simulator(load_scene("cantilever", overrides=dict(SMALL, **{"model.kind": "reduced", "pins": [],
                                                                      "initial_velocity.angular": [0.5, 0.0, 3.0]})),
                    cache=PrecomputeCache(enabled=False))
    sim.step(3)
    snap = sim.model.get_state()
    x0, v0 = _state_arrays(sim)
    poses = sim.domain_poses().copy()
    sim.step(3)
    assert np.abs(sim.domain_poses() - poses).max() > 1e-3
    sim.model.set_state(snap)
    np.testing.assert_array_equal(sim.vertex_positions(), x0)
    np.testing.assert_array_equal(sim.model.vertex_velocities(), v0)
    np.testing.assert_array_equal(sim.domain_poses(), poses)


def test_stable_run_reports_stable_with_no_recoveries(sim):
    sim.reset()
    sim.set_wrench("tip", force=(0, 0, -5.0))
    for _ in range(10):
        sim.step()
        assert sim.stats()["stability"] == "stable"
    st = sim.stats()
    assert st["guard_recoveries"] == st["guard_failures"] == st["guard_degraded"] == 0
    assert st["guard_substeps"] == 1 and st["guard_attempts"] == 1


def _inject(monkeypatch, sim, spoil, times):
    """Make the model's next `times` steps end in a spoiled state (spoil(model))."""
    model = sim.model
    real = model.step
    calls = {"n": 0}

    def step(*a, **k):
        out = real(*a, **k)
        calls["n"] += 1
        if calls["n"] <= times:
            spoil(model)
        return out
    monkeypatch.setattr(model, "step", step)
    return calls


def _nan(model):
    if model.kind == "full":
        model.x = model.x.copy()
        model.x[5] = np.nan
    else:
        model.q = model.q.copy()
        model.q[0] = np.nan


def _blow_up(model):
    if model.kind == "full":
        model.v = 100.0 * model.v + 1.0
    else:
        model.qd = np.where(model.layout.mask, 100.0 * model.qd + 1.0, 0.0)


@pytest.mark.parametrize("spoil, reason", [(_nan, "non-finite"), (_blow_up, "energy")])
def test_guard_rolls_back_an_injected_divergence_and_recovers(sim, monkeypatch, spoil, reason):
    sim.reset()
    sim.set_wrench("tip", force=(0, 0, -5.0))
    sim.step(3)
    reference = _sim(sim.model.kind)                  # the same run without the injection
    reference.set_wrench("tip", force=(0, 0, -5.0))
    reference.step(3)
    calls = _inject(monkeypatch, sim, spoil, times=1)
    sim.step()
    st = sim.stats()
    assert calls["n"] >= 2                            # rolled back and stepped again
    assert st["stability"] == "recovered" and reason in st["guard_reason"]
    assert st["guard_recoveries"] == 1 and "rollback" in st["guard_action"]
    assert np.all(np.isfinite(sim.vertex_positions()))
    assert abs(sim.time - 4 * sim.dt) < 1e-12
    # The retry (more Newton iterations) starts from the rolled-back state: it lands near
    # the clean one-iteration step, not near the spoiled state.
    # Measured (full / reduced): positions within 2.3e-5 / 2.0e-5 m of the reference (tip
    # deflection 18 mm), kinetic energy +0.042 % / -0.046 % of it (0.56 J): one step of
    # backward Euler solved with 4 Newton iterations instead of 1, a linearisation
    # difference, not round-off. Bounds ~5-10x that; the spoiled state is off by orders of
    # magnitude (x100 velocities: 1e4 x the kinetic energy).
    reference.step()
    assert np.abs(sim.vertex_positions() - reference.vertex_positions()).max() < 1e-4
    assert sim.energy()["kinetic"] == pytest.approx(reference.energy()["kinetic"], rel=5e-3)


def test_guard_never_lets_a_nan_out_and_keeps_the_last_good_state(sim, monkeypatch):
    sim.reset()
    sim.step(2)
    x_good = sim.vertex_positions().copy()
    _inject(monkeypatch, sim, _nan, times=10 ** 6)
    sim.step()
    st = sim.stats()
    assert st["stability"] == "failed" and st["guard_failures"] == 1
    assert st["guard_attempts"] > 3                  # the whole ladder was tried
    np.testing.assert_array_equal(sim.vertex_positions(), x_good)
    assert np.all(np.isfinite(sim.surface_positions())) and np.isfinite(sim.energy()["total"])
    assert sim.step_count == 3                       # time goes on
    monkeypatch.undo()
    sim.step()
    assert sim.stats()["stability"] == "stable" and sim.stats()["guard_failures"] == 1


def test_guard_catches_a_solver_error(sim, monkeypatch):
    sim.reset()
    model = sim.model
    real = model.step
    calls = {"n": 0}

    def step(*a, **k):
        calls["n"] += 1
        if calls["n"] == 1:
            raise np.linalg.LinAlgError("singular matrix")
        return real(*a, **k)
    monkeypatch.setattr(model, "step", step)
    sim.step()
    assert sim.stats()["stability"] == "recovered" and sim.stats()["guard_reason"] == "non-finite"


def test_guard_off_by_scene_key_and_defaults():
    scene = load_scene("cantilever")
    g = scene["model"]["guard"]
    assert g["enabled"] is True and g["max_substeps"] >= 2 and g["energy_growth"] > 0
    sim = _sim("full", **{"model.guard.enabled": False})
    sim.step()
    assert sim.stats()["stability"] == "unchecked"
    with pytest.raises(Exception, match="model.guard.max_substeps"):
        load_scene("cantilever", overrides={"model.guard.max_substeps": 0})


def test_inverted_tets_counts_flipped_elements():
    x = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [0, 0, -1.0]])
    tets = np.array([[0, 1, 2, 3], [0, 2, 1, 4]])
    assert inverted_tets(x, tets) == 0
    x[3, 2] = -0.5                                   # push the apex through the base
    assert inverted_tets(x, tets) == 1


# ---------------------------------------------------------------- implicit fictitious forces
def _spinning_reduced(fictitious, dt, young=1e7):
    from mdss_ros.verify.stability_study import cell_scene
    sc = cell_scene("reduced", "corotated", young, 0.3, dt, 50.0)
    sc["gravity"] = [0.0, 0.0, 0.0]
    sc["model"]["guard"] = {"enabled": False}
    sc["model"]["integrator"]["fictitious"] = fictitious
    return Simulator(load_scene(sc), cache=PrecomputeCache(enabled=False))


def test_fictitious_matrices_split_the_explicit_force():
    """C qd + K_cf q + (q, qd-free part) reproduces frames.fictitious_forces; C is skew,
    K_cf symmetric PSD, and the modal Coriolis flow keeps |qd|."""
    from mdss_ros.reduced.frames import fictitious_forces
    sim = _spinning_reduced("implicit", 1 / 90)
    sim.step(3)
    m = sim.model
    C, K = m._fictitious_matrices(m.frames)                 # (D, r_max, r_max) per domain
    L = m.layout
    rng = np.random.default_rng(0)
    omega = np.einsum("dji,dj->di", m.frames.R, m.frames.w)
    q, qd = rng.normal(size=L.mask.shape) * L.mask, rng.normal(size=L.mask.shape) * L.mask
    zero = np.zeros_like(q)
    f0 = fictitious_forces(L, zero, zero, omega, np.zeros_like(omega))
    f = fictitious_forces(L, q, qd, omega, np.zeros_like(omega))
    np.testing.assert_allclose(f, f0 + np.einsum("dab,db->da", C, qd) + np.einsum("dab,db->da", K, q),
                               rtol=1e-10, atol=1e-10 * np.abs(f).max())
    # one domain checked against the unstacked formula of frames.py's docstring
    t, r = m.subspace[0].tensors, m.subspace[0].r
    w0, q0, qd0 = omega[0], q[0, :r], qd[0, :r]
    direct = (2.0 * np.einsum("b,abk,k->a", qd0, t.W, w0) - np.einsum("i,aij,j->a", w0, t.B1, w0)
              - np.einsum("b,i,abij,j->a", q0, w0, t.B2, w0) + (w0 @ w0) * (t.s + q0))
    np.testing.assert_allclose(f[0, :r], direct, rtol=1e-12, atol=1e-12 * np.abs(direct).max())
    # With an angular acceleration too (the Euler term W(q) alpha), every domain.
    alpha = rng.normal(size=omega.shape)
    fa = fictitious_forces(L, q, qd, omega, alpha)
    for k, dom in enumerate(m.subspace):
        t, r = dom.tensors, dom.r
        w0, a0, q0, qd0 = omega[k], alpha[k], q[k, :r], qd[k, :r]
        direct = (2.0 * np.einsum("b,abk,k->a", qd0, t.W, w0) + np.einsum("b,abk,k->a", q0, t.W, a0)
                  - np.einsum("i,aij,j->a", w0, t.B1, w0)
                  - np.einsum("b,i,abij,j->a", q0, w0, t.B2, w0) + (w0 @ w0) * (t.s + q0))
        np.testing.assert_allclose(fa[k, :r], direct, rtol=1e-12, atol=1e-12 * np.abs(direct).max())
    C, K = C[L.movable], K[L.movable]
    np.testing.assert_allclose(C, -C.transpose(0, 2, 1), atol=1e-12 * np.abs(C).max())
    np.testing.assert_allclose(K, K.transpose(0, 2, 1), atol=1e-12 * np.abs(K).max())
    assert np.linalg.eigvalsh(K).min() > -1e-9 * np.abs(K).max()
    Q = rng.normal(size=m.n_gen)
    Qr = m._modal_coriolis_rotate(m._fictitious_matrices(m.frames)[0], Q, m.dt)
    assert not np.allclose(Qr, Q)
    np.testing.assert_allclose(np.linalg.norm(Qr), np.linalg.norm(Q), rtol=1e-12)


def test_implicit_fictitious_forces_agree_at_small_dt_and_tame_a_fast_spin():
    a, b = _spinning_reduced("explicit", 1e-3), _spinning_reduced("implicit", 1e-3)
    a.step(20)
    b.step(20)
    scale = np.abs(a.vertex_positions() - a.rest_positions()).max()
    assert np.abs(a.vertex_positions() - b.vertex_positions()).max() < 1e-3 * scale
    # 50 rad/s at dt = 1/30 (1.7 rad per step), stiff body: explicit fictitious forces pump
    # energy in by orders of magnitude; the implicit treatment much less. E = 1e8: with the
    # domain-derived modal derivatives (basis.derivatives_on: domain) the 1e7 body's explicit
    # run peaks at 76x its energy and settles; at 1e8 it pumps to 6.2e3x, the implicit 3.1e2x.
    peaks = {}
    for fic in ("explicit", "implicit"):
        sim = _spinning_reduced(fic, 1 / 30, young=1e8)
        e0, peak = sim.energy()["total"], 0.0
        with np.errstate(all="ignore"):
            for _ in range(30):
                sim.step()
                peak = max(peak, sim.energy()["total"] / e0)
        peaks[fic] = peak
    assert peaks["explicit"] > 100 and peaks["implicit"] < 0.1 * peaks["explicit"], peaks


def test_slow_energy_pumping_is_caught_as_drift():
    """A pump that adds 8 % of kinetic energy per step stays under the per-step bound; the
    run's energy ledger catches it, and the retries (which the pump spares) keep the energy
    below that of the same pumped run without the guard."""
    finals = {}
    for guard in (False, True):
        sim = _sim("full", **{"gravity": [0.0, 0.0, 0.0], "body.damping.beta": 0.0, "model.guard.enabled": guard})
        model, real = sim.model, sim.model.step

        def pumped(*a, model=model, real=real, **k):
            out = real(*a, **k)
            if model.integrator.settings.max_iterations == 1:      # first attempts only
                model.v = 1.04 * model.v
            return out
        model.step = pumped
        sim.set_wrench("tip", force=(0, 0, -20.0))
        sim.step(5)
        sim.set_wrench("tip", force=(0, 0, 0))
        reasons = []
        for _ in range(60):
            sim.step()
            reasons.append(sim.stats().get("guard_reason"))
        finals[guard] = sim.energy()["total"]
        if guard:
            assert "energy drift" in reasons and sim.stats()["guard_failures"] == 0
            assert sim.stats()["guard_recoveries"] >= 1
    assert finals[True] < 0.8 * finals[False], finals


def test_guard_sub_steps_sweep_colliders_to_their_target(monkeypatch):
    """A retried step with a moving collider: sub-steps interpolate the collider from its
    pose at the step start to the pose set for the step's end; the contact holds."""
    scene = {"name": "block",
             "body": {"mesh": {"generator": "box", "size": [0.2, 0.2, 0.1], "cell": 0.05, "origin": [-0.1, -0.1, 0.0]},
                      "material": {"model": "neohookean", "young": 1e5, "poisson": 0.3, "density": 1000},
                      "damping": {"alpha": 5.0, "beta": 0.0}},
             "colliders": {"floor": {"shape": "plane"},
                           "ball": {"shape": "sphere", "radius": 0.04, "position": [0, 0, 0.15]}},
             "model": {"kind": "full", "integrator": {"dt": 0.01, "newton_iterations": 2},
                       "guard": {"newton_iterations": 2}}}        # retries = sub-steps only
    sim = Simulator(load_scene(scene))
    sim.step(10)
    poses = []
    real = sim.model.step

    def spy(*a, **k):
        poses.append(sim.colliders["ball"].position.copy())
        out = real(*a, **k)
        if len(poses) == 1:
            _nan(sim.model)
        return out
    monkeypatch.setattr(sim.model, "step", spy)
    sim.set_collider_pose("ball", (0.0, 0.0, 0.135))                 # 5 mm into the top
    sim.step()
    st = sim.stats()
    assert st["stability"] == "recovered" and st["guard_substeps"] == 2
    np.testing.assert_allclose([p[2] for p in poses], [0.135, 0.1425, 0.135])
    np.testing.assert_allclose(sim.colliders["ball"].position, [0, 0, 0.135])
    assert sim.colliders["ball"].signed_distance(sim.vertex_positions())[0].min() > -1e-6


@pytest.mark.parametrize("clamped", [False, True])
def test_reduced_guard_measure_matches_vertex_sums_on_a_spinning_deformed_body(clamped):
    """The guard measures reduced models in reduced coordinates (reduced/measure.py):
    kinetic energy and gravity potential equal the sums over vertices, and the speed bound
    bounds every vertex; free (all frames move) and clamped (one domain without a frame)."""
    from mdss_ros.verify.reduced_reports import beam_scene
    sc = beam_scene("reduced", size=(0.4, 0.1, 0.1), cell=0.05, clamped=clamped, domains={"count": 3}, modes=8)
    if not clamped:
        sc["initial_velocity"] = {"linear": [0.1, 0.2, 0.0], "angular": [1.0, 3.0, 0.5]}
    sc["gravity"] = [0.0, 0.0, -9.81]
    sim = Simulator(sc)
    sim.set_wrench("tip", force=(0.0, 3.0, -5.0))
    sim.step(15)
    m = sim.model
    got = m.guard_measure(sim.gravity)
    x, v = m.vertex_positions(), m.vertex_velocities()
    assert got.kinetic == pytest.approx(0.5 * (m.vertex_mass * (v * v).sum(1)).sum(), rel=1e-10)
    assert got.gravity == pytest.approx(-(m.vertex_mass * (x @ sim.gravity)).sum(), rel=1e-10)
    assert got.speed >= np.sqrt((v * v).sum(1).max())
    assert got.finite and got.inverted == 0


def test_reduced_guard_counts_inverted_samples_and_coupling_elements_like_the_vertices_do():
    """_guard_inverted reads cubature samples from q and coupling elements from the start
    evaluation; it must count what the vertex positions say, here on a crushed state."""
    from mdss_ros import Simulator
    from mdss_ros.guard import inverted_tets
    sim = Simulator("cantilever", {"model.kind": "reduced", "model.domains": {"count": 2}, "model.modes": 6,
                                   "model.cubature": {"samples": 40, "interface": "uniform", "interface_samples": 20,
                                                      "training": {"n_poses": 12}},
                                   "body.mesh.cell": 0.05, "model.guard.enabled": False})
    m = sim.model
    rng = np.random.default_rng(0)
    counts = []
    for scale in (0.0, 0.3, 3.0):
        m.q = m.layout.pad([scale * rng.standard_normal(dom.r) * np.sqrt(dom.total_mass) for dom in m.subspace])
        m._start_evaluation()                         # what the guard's energy check leaves behind
        x = m.vertex_positions()
        tets = [dom.vertices[dom.forces.tets[dom.sampled.elements]] for dom in m.subspace] + [m.body.tets[m.c_tets]]
        expected = sum(inverted_tets(x, t) for t in tets)
        assert m._guard_inverted() == expected        # samples' det F from that evaluation
        m.samples.det_at = None
        assert m._guard_inverted() == expected        # formed again from q
        counts.append(expected)
    assert counts[0] == 0 and counts[-1] > 0


def _tangled_free_body(untangle_after):
    """A free 3-domain reduced beam (no gravity) whose modal coordinates and frames are set
    to a tangle (about 40 of 480 tets inverted): random q and the middle frame turned
    2.5 rad."""
    from mdss_ros.rotations import exp_so3
    sim = Simulator(load_scene("cantilever", overrides=dict(SMALL, **{
        "model.kind": "reduced", "pins": [], "gravity": [0.0, 0.0, 0.0], "model.domains": {"count": 3},
        "model.guard.untangle_after": untangle_after})), cache=PrecomputeCache(enabled=False))
    m = sim.model
    rng = np.random.default_rng(3)
    m.q = m.layout.pad([0.03 * rng.standard_normal(dom.r) * np.sqrt(dom.total_mass) for dom in m.subspace])
    m.frames.R[1] = exp_so3(np.array([0.0, 0.0, 2.5])) @ m.frames.R[1]
    sim.guard.invalidate()
    return sim


def test_untangle_shrinks_a_tangle_until_no_element_is_inverted():
    sim = _tangled_free_body(0)
    m, tets = sim.model, sim.tetrahedra()
    assert inverted_tets(sim.vertex_positions(), tets) > 0
    mass = m.vertex_mass[:, None]
    com = (mass * sim.vertex_positions()).sum(0) / mass.sum()
    q = m.q.copy()
    s = m.untangle(tets)
    assert 0.0 < s < 1.0
    assert inverted_tets(sim.vertex_positions(), tets) == 0
    np.testing.assert_allclose(m.q, s * q)
    # the mass centre stays (the modes carry no mass moment; frames move about their centre)
    np.testing.assert_allclose((mass * sim.vertex_positions()).sum(0) / mass.sum(), com, atol=1e-9)
    assert m.untangle(tets) == 1.0                     # nothing left to untangle


def test_guard_untangles_an_inversion_left_for_untangle_after_steps_and_not_before():
    sim = _tangled_free_body(3)
    tets = sim.tetrahedra()
    reports = []
    for _ in range(3):
        sim.step()
        reports.append(sim.stats())
    assert all("untangled" not in r["guard_action"] for r in reports[:2])
    assert "untangled" in reports[2]["guard_action"] and reports[2]["stability"] != "failed"
    assert "inversion left" in reports[2]["guard_reason"] and 0.0 < reports[2]["guard_untangled"] < 1.0
    assert reports[2]["guard_untangles"] == 1
    assert inverted_tets(sim.vertex_positions(), tets) == 0
    off = _tangled_free_body(0)                         # untangle_after: 0 turns it off
    off.step(4)
    assert off.stats()["guard_untangles"] == 0 and inverted_tets(off.vertex_positions(), tets) > 0


def test_a_step_no_rung_can_take_from_a_tangled_start_untangles_the_start_first(monkeypatch):
    """Found on the stability matrix's corner cell (reduced neo-Hookean, 1 kPa, nu 0, dt
    1/30, 50 rad/s, 1 kN): with the domain-derived modal derivatives it held 9 inverted tets
    at steps 6-7 and no rung of the ladder (up to 64 sub-steps with an energy projection)
    passed from there, so both steps failed. That trajectory is chaotic: on another CPU
    (AMD EPYC, session 12) the same cell never reached such a state, so the rule is tested
    here on a constructed tangle, with every rung made to fail while the start is tangled.
    The guard then untangles the start and walks the ladder again; without the rule the
    step fails."""
    from mdss_ros.guard import StabilityGuard
    walk = StabilityGuard._walk

    def no_rung_from_a_tangle(self, ladder, advance, save, restore, snap, before, *rest):
        if before.inverted:
            return None, None, None, None, before, "inversion"
        return walk(self, ladder, advance, save, restore, snap, before, *rest)

    monkeypatch.setattr(StabilityGuard, "_walk", no_rung_from_a_tangle)
    sim = _tangled_free_body(0)                       # untangle_after 0: only the start rule acts
    tets = sim.tetrahedra()
    assert inverted_tets(sim.vertex_positions(), tets) > 0
    sim.step()
    st = sim.stats()
    assert st["stability"] != "failed", st["guard_action"]
    assert "untangled the start" in st["guard_action"] and "no rung from a tangled start" in st["guard_reason"]
    assert st["guard_untangles"] == 1 and 0.0 < st["guard_untangled"] < 1.0
    assert inverted_tets(sim.vertex_positions(), tets) == 0
    monkeypatch.setattr(StabilityGuard, "_untangle_start", lambda self, before, gravity: None)
    off = _tangled_free_body(0)
    off.step()
    assert off.stats()["stability"] == "failed", "the rule made no difference here"


@pytest.mark.parametrize("plan, kept, tried", [
    ([None, 0.08, 0.03], 3, 3),       # near the bound (0.1): the next rung creates less, kept
    ([None, 0.08, 0.09], 2, 3),       # ... creates more: the first pass is kept
    ([None, 0.04], 2, 2),             # under MARGIN x the bound: no extra rung
])
def test_a_retry_passing_near_the_energy_bound_tries_the_next_rung(monkeypatch, plan, kept, tried):
    """Margin (guard.MARGIN): the verdicts are scripted per attempt (None: rejected for
    energy; a number: passes with that growth) over the real steps of a reduced beam."""
    from mdss_ros import guard as G
    real, real_own = G.StabilityGuard._attempt, G.StabilityGuard._own_step
    calls = []

    def scripted(self, advance, before, f_app, gravity, dt, n_sub, newton, implicit=False, project=False):
        stats, v, after = real(self, advance, before, f_app, gravity, dt, n_sub, newton, implicit, project)
        growth = plan[len(calls)]
        calls.append(n_sub)
        return stats, G.Verdict(hard=[] if growth is not None else ["energy"],
                                growth=1.0 if growth is None else growth, inverted=v.inverted), after

    def scripted_own(self, advance, before, f_app, gravity):
        # The first rung (the model's own step) is run by _step itself, as signs.
        stats, after, _ = real_own(self, advance, before, f_app, gravity)
        growth = plan[len(calls)]
        calls.append(1)
        return stats, after, (((), (), growth) if growth is not None else (("energy",), (), 1.0))

    sim = _sim("reduced")
    assert sim.guard.settings.energy_growth == 0.1
    monkeypatch.setattr(G.StabilityGuard, "_attempt", scripted)
    monkeypatch.setattr(G.StabilityGuard, "_own_step", scripted_own)
    sim.step()
    st = sim.stats()
    assert len(calls) == tried
    assert st["stability"] == "recovered" and st["guard_attempts"] == kept
    assert st["energy_growth"] == plan[kept - 1]


def test_a_guarded_step_ignores_floating_point_errors_and_restores_the_context():
    """StabilityGuard.step sets numpy's floating-point context itself, as np.errstate(all=
    "ignore") would: every error ignored inside the step, the rest (buffer size) taken from
    the caller's context, and the caller's context back afterwards."""
    sim = _sim("reduced")
    real, seen = sim._advance, []

    def advance(*args, **kwargs):
        seen.append((np.geterr(), np.getbufsize()))
        return real(*args, **kwargs)

    sim._advance = advance
    ignore = {"divide": "ignore", "over": "ignore", "under": "ignore", "invalid": "ignore"}
    with np.errstate(all="raise"):
        size = np.getbufsize()
        try:
            np.setbufsize(16384)
            sim.step(2)
            inside_after = (np.geterr(), np.getbufsize())
            np.setbufsize(size)
            sim.step()
        finally:
            np.setbufsize(size)
        assert np.geterr()["invalid"] == "raise"
    assert seen[:2] == [(ignore, 16384)] * 2 and seen[2] == (ignore, size)
    assert inside_after == ({k: "raise" for k in ignore}, 16384)
