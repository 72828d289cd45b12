"""The compiled frictional contact of a reduced body (reduced/frictional_kernel.py): its
rows against the general corner rows, its Coulomb solve against
friction.frictional_correction, and whole steps against the Python path."""
import numpy as np
import pytest

from mdss_ros import Simulator
from mdss_ros.contact.friction import PHYSICAL_TOL, FrictionRows, frictional_correction
from mdss_ros.reduced import contact_rows as cr
from mdss_ros.reduced.block_cholesky import BlockCholesky
from mdss_ros.reduced.frictional_kernel import compiled_correction
from mdss_ros.reduced.reduced_model import ReducedModel
from mdss_ros.reduced.sparse_rows import ContactRowEntries
from mdss_ros.verify import friction_study as fs


def _sim(case):
    """A reduced block on a rough floor: tilted 20 degrees (sticks), 35 (slides; "kinetic":
    static 0.6, kinetic 0.4), or flat with the floor moving along x under it (a conveyor:
    the collider's own slip)."""
    theta = {"stick": 20.0, "slide": 35.0, "kinetic": 35.0, "conveyor": 0.0}[case]
    friction = {"static": 0.6, "kinetic": 0.4} if case == "kinetic" else 0.5
    return Simulator(fs.incline(theta, fs.REDUCED, friction))


def _advance(sim, case, steps):
    """steps steps; the conveyor's floor moves 0.2 m/s along x."""
    for _ in range(steps):
        if case == "conveyor":
            sim.conveyor_steps = getattr(sim, "conveyor_steps", 0) + 1
            sim.set_collider_pose("floor", (0.2 * fs.DT * sim.conveyor_steps, 0.0, 0.0))
        sim.step()


def _spy_rows(sim, case):
    """The arguments of the next step's _vertex_friction_rows call."""
    captured = {}
    orig = ReducedModel._vertex_friction_rows

    def spy(self, *args):
        captured["args"] = args
        return orig(self, *args)
    ReducedModel._vertex_friction_rows = spy
    try:
        _advance(sim, case, 1)
    finally:
        ReducedModel._vertex_friction_rows = orig
    return captured["args"]


def _capture(monkeypatch, sim, case):
    """(rows, v, guess, factor) of the first of the next 20 steps whose Coulomb solve the
    kernel takes. (The conveyor's floor drags a block at rest on it: in some steps Newton
    does not settle within NEWTON_FIRST iterations and both solves hand the problem to
    Gauss-Seidel, solve_coulomb's fallback.)"""
    seen = []

    def spy(rows, v, guess, factor, **kw):
        done = compiled_correction(rows, v, guess, factor, **kw)
        if done is not None:
            seen.append((rows, np.array(v), np.array(guess), factor))
        return done
    monkeypatch.setattr(cr, "compiled_correction", spy)
    for _ in range(20):
        _advance(sim, case, 1)
        if seen:
            break
    monkeypatch.undo()
    assert len(seen) == 1
    return seen[0]


def _python(rows, v, guess, factor):
    return frictional_correction(cr.CholeskySolves(factor), rows.at(v), None, rows.mu, regularize=1e-9,
                                 lam_guess=guess)


def _assert_same_answer(got, ref):
    lam, corr, info = got
    lam_r, corr_r, info_r = ref
    np.testing.assert_allclose(lam, lam_r, rtol=0, atol=1e-9 * np.abs(lam_r).max())
    np.testing.assert_allclose(corr, corr_r, rtol=0, atol=1e-12 * np.abs(corr_r).max())
    np.testing.assert_allclose(info["w"], info_r["w"], rtol=0, atol=1e-12 * np.abs(info_r["w"]).max())
    for key in ("rows", "working_set", "rounds", "active", "stick", "slip", "newton", "unconverged"):
        assert info[key] == info_r[key], key


@pytest.mark.parametrize("case", ["stick", "slide", "conveyor"])
def test_compiled_coulomb_solve_matches_frictional_correction(monkeypatch, case):
    sim = _sim(case)
    _advance(sim, case, 30)
    rows, v, guess, factor = _capture(monkeypatch, sim, case)
    got = compiled_correction(rows, v, guess, factor)
    assert got is not None
    ref = _python(rows, v, guess, factor)
    assert got[2]["active"] >= 4                                  # a face of the block on the floor
    _assert_same_answer(got, ref)


class _Rows:
    """The attributes of contact_rows.FrictionalRows that compiled_correction reads, for
    dense rows C (3m, S) held as entries, and friction.FrictionRows of the same rows for
    frictional_correction."""

    def __init__(self, C, g3, mu):
        m, S = C.shape[0] // 3, C.shape[1]
        self.rows3 = ContactRowEntries(np.tile(np.arange(S), (3 * m, 1)), C.copy(), np.full(3 * m, S), S)
        self.C, self.g3, self.mu = C, g3, mu
        self.g_n = g3[:, 0].copy()
        self.slot, self.n_built = np.arange(m), m

    def at(self, v):
        return FrictionRows(self.C, self.C @ v + self.g3.ravel())


def test_compiled_coulomb_solve_grows_its_working_set_as_the_python_one():
    """Five contacts of independent rows through a 30-DOF system, all pressed by the free
    step, and a warm start that names one: both solves find the others violated after the
    first round and add them, to the same answer."""
    rng = np.random.default_rng(3)
    S, m = 30, 5
    B = rng.standard_normal((S, S))
    A = B @ B.T + S * np.eye(S)
    factor = BlockCholesky([S], np.zeros((0, 2), dtype=np.int64), [0]).factor(A)
    C = rng.standard_normal((3 * m, S))
    g3 = np.zeros((m, 3))
    g3[:, 0] = -0.1 - rng.random(m)                   # every gap closed by the free step
    g3[:, 1:] = 0.05 * rng.standard_normal((m, 2))
    v = np.zeros(S)
    rows = _Rows(C, g3, np.full(m, 0.5))
    guess = np.zeros((m, 3))
    guess[0, 0] = 1.0
    got, ref = compiled_correction(rows, v, guess, factor), _python(rows, v, guess, factor)
    assert got is not None and got[2]["rounds"] > 1 and got[2]["working_set"] > 1
    assert got[2]["active"] >= 2
    _assert_same_answer(got, ref)


def test_compiled_coulomb_solve_declines_what_it_does_not_handle(monkeypatch):
    sim = _sim("stick")
    _advance(sim, "stick", 30)
    rows, v, guess, factor = _capture(monkeypatch, sim, "stick")
    assert compiled_correction(rows, v, guess, factor) is not None
    assert compiled_correction(rows, v, None, factor) is None            # no warm start: Python's LCP first
    rows.n_built -= 1                                                    # a contact's rows not built
    assert compiled_correction(rows, v, guess, factor) is None


@pytest.mark.parametrize("case", ["stick", "slide", "kinetic", "conveyor"])
def test_vertex_rows_are_the_corner_rows(case):
    """_vertex_friction_rows (compiled) builds the rows, gaps, tangents, coefficients and
    warm start _corner_rows builds for the same candidates: the rows to the bit (the same
    kernel per row), the rigid shares of a co-rotating step to round-off."""
    sim = _sim(case)
    _advance(sim, case, 30)
    m = sim.model
    args = _spy_rows(sim, case)
    fast = m._vertex_friction_rows(*args)
    fast_keys, fast_at = m._contact_row_keys, m._contact_at
    general = m._corner_rows(*args)
    verts, C, phi, normals, which, fr = fast
    verts_g, C_g, phi_g, normals_g, which_g, fr_g = general
    n = len(verts)
    assert n >= 4
    np.testing.assert_array_equal(verts, verts_g)
    np.testing.assert_array_equal(which, which_g)
    np.testing.assert_array_equal(normals, normals_g)
    np.testing.assert_array_equal(fast_keys, m._contact_row_keys)
    np.testing.assert_array_equal(fast_at, m._contact_at)
    np.testing.assert_array_equal(C[np.arange(n)], C_g[np.arange(n)])
    scale = np.abs(phi_g).max()
    np.testing.assert_allclose(phi, phi_g, rtol=0, atol=1e-14 * scale)
    np.testing.assert_array_equal(fr.mu, fr_g.mu)
    fr_g.ensure(np.arange(n))
    v = np.linspace(-1.0, 1.0, m.n_gen)
    np.testing.assert_array_equal(fr._rows(np.arange(n), v)[0], fr_g._rows(np.arange(n), v)[0])
    np.testing.assert_array_equal(fr.tangents, fr_g.tangents)
    np.testing.assert_allclose(fr.g3, fr_g.g3, rtol=0, atol=1e-14 * max(scale, np.abs(fr_g.g3).max()))
    np.testing.assert_allclose(fr.rigid3, fr_g.rigid3, rtol=0, atol=1e-14 * max(np.abs(fr_g.rigid3).max(), 1e-300))
    np.testing.assert_array_equal(fr.guess, fr_g.guess)
    if case == "kinetic":         # the contacts that slid in the last step: the kinetic coefficient
        slid = fr.guess[:, 0] > 0
        assert slid.sum() >= 4 and np.all(fr.mu[slid] == 0.4) and np.all(fr.mu[~slid] == 0.6)
    if case == "conveyor":
        # The floor's own slip is in the rows (0.2 m/s dt; the block, carried at the floor's
        # speed, has the opposite rigid share).
        np.testing.assert_allclose(np.abs(fr.g3[:, 1:] - fr.rigid3[:, 1:]).max(), 0.2 * fs.DT, rtol=1e-9)


def test_a_pinned_vertex_is_no_candidate():
    """A vertex that cannot move (pinned, resting on the floor) has a zero row: the compiled
    rows drop it, as the corner rows do, instead of posing an infeasible contact."""
    scene = fs.incline(0.0, fs.REDUCED)
    scene["pins"] = [{"box": [[-1, -1, -1], [-0.05 + 1e-4, 1, 1]]}]          # the x = -0.05 face
    sim = Simulator(scene)
    _advance(sim, "stick", 5)
    args = _spy_rows(sim, "stick")
    m = sim.model
    fast, general = m._vertex_friction_rows(*args), m._corner_rows(*args)
    np.testing.assert_array_equal(fast[0], general[0])
    ids, near = args[1], args[3]
    pinned = np.flatnonzero(np.abs(m.body.vertices[:, 0] + 0.05) < 1e-9)
    assert np.isin(ids[near], pinned).any()                             # pinned candidates on the floor ...
    assert not np.isin(fast[0], pinned).any()                           # ... are no contacts
    assert len(fast[0]) > 0


def _run_python(sim, case, steps, rows=True, solve=True):
    """steps steps with the Python corner rows (rows) and/or frictional_correction (solve)."""
    orig_rows, orig_solve = ReducedModel._vertex_friction_rows, cr.compiled_correction
    if rows:
        ReducedModel._vertex_friction_rows = ReducedModel._corner_rows
    if solve:
        cr.compiled_correction = lambda *args, **kw: None
    try:
        _advance(sim, case, steps)
    finally:
        ReducedModel._vertex_friction_rows, cr.compiled_correction = orig_rows, orig_solve


@pytest.mark.parametrize("case", ["stick", "slide", "conveyor"])
def test_steps_match_the_python_contact_path(case):
    """100 steps with the compiled rows and Coulomb solve against the same with the corner
    rows and frictional_correction: vertex positions within 1e-10 of the displacement
    (issue 17's bar for a re-implemented step). The conveyor's floor drags the block, and
    in most of its steps Newton hands the Coulomb problem to Gauss-Seidel, which stops where
    the law holds to PHYSICAL_TOL of the rows' scale (the floor's 0.2 m/s x dt): the two
    paths' round-off (the solve's W = Z^T Z summed in another order) moves its answer
    within that (measured: 4e-10 m against 2.2e-9 m). Its rows alone are bit for bit the
    Python ones."""
    a, b = _sim(case), _sim(case)
    _advance(a, case, 100)
    _run_python(b, case, 100)
    x0 = a.model.body.vertices
    xa, xb = a.vertex_positions(), b.vertex_positions()
    assert np.abs(xb - x0).max() > 0
    tol = PHYSICAL_TOL * 0.2 * fs.DT if case == "conveyor" else 1e-10 * np.abs(xb - x0).max()
    np.testing.assert_allclose(xa, xb, rtol=0, atol=tol)
    if case == "conveyor":
        c = _sim(case)
        _run_python(c, case, 100, rows=False)
        np.testing.assert_array_equal(c.vertex_positions(), xb)


@pytest.mark.parametrize("case", ["stick", "slide", "conveyor"])
def test_compiled_contact_record_is_contact_forces(case):
    """_frictional_record (compiled) gives the record fem/backward_euler.contact_forces
    gives for the same answer, and the work FrictionalRows.work does (to round-off)."""
    from mdss_ros.fem.backward_euler import contact_forces
    sim = _sim(case)
    _advance(sim, case, 30)
    m = sim.model
    rows, lam, w = m._contact_rows_seen, m._contact_lam, m._contact_info["w"]
    verts, _, _, normals, which, fr = rows
    pts = m._contact_points(sim._contact_spec(), verts)
    Q = np.linspace(-1e-2, 1e-2, m.n_gen)
    work = m._frictional_record(sim._contact_spec(), rows, lam, w, pts, Q, m.dt)
    got = m.contact
    depth = np.zeros(len(verts))
    on = lam[:, 0] > 0
    depth[on] = np.maximum(-sim.colliders["floor"].signed_distance(pts[on])[0], 0.0)
    ref = contact_forces(verts, normals, which, lam, fr.tangents, pts, depth, w, m.dt)
    assert list(got) == list(ref) and len(got["vertices"]) >= 4
    for key in ref:
        if key in ("forces", "friction", "slip_speed", "depth"):
            np.testing.assert_allclose(got[key], ref[key], rtol=1e-14, atol=1e-14 * np.abs(ref[key]).max())
        else:
            np.testing.assert_array_equal(got[key], ref[key])
    ref_work = fr.work(lam, Q)
    assert ref_work != 0.0
    np.testing.assert_allclose(work, ref_work, rtol=1e-12)
