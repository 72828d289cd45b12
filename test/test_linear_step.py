"""The compiled linearly implicit step (reduced/linear_step.py) against the general step
(step.Step._step) it replaces for subspace-only bodies with one Newton iteration: two
simulators of one scene, one forced onto the general path, step side by side and must
agree bit for bit (issue 17: "the new step reproduces the current one"), pinned and free,
with and without contact; where the unified matrix is not positive definite the compiled
step hands over to the general one; and the kernels' cache stamp follows the files whose
kernels they link in."""
import hashlib
from pathlib import Path

import numpy as np
import pytest

from mdss_ros.reduced import linear_step
from mdss_ros.simulator import Simulator


def beam(domains, modes=6, **model):
    """A pinned 0.6 m beam of 2e5 Pa under gravity with a tip handle."""
    return {
        "name": "linear_step",
        "body": {"mesh": {"generator": "box", "size": [0.6, 0.1, 0.1], "cell": 0.05},
                 "material": {"model": "neohookean", "young": 2e5, "poisson": 0.3, "density": 1000},
                 "damping": {"alpha": 0.2, "beta": 0.002}},
        "pins": [{"box": [[-0.001, -1, -1], [0.001, 1, 1]]}],
        "handles": {"tip": {"box": [[0.599, -1, -1], [0.601, 1, 1]]}},
        "gravity": [0.0, 0.0, -9.81],
        "model": dict({"kind": "reduced", "domains": {"count": domains}, "modes": modes,
                       "cubature": {"samples": 30, "interface": "uniform", "interface_samples": 15}}, **model),
    }


def _pair(scene):
    compiled, general = Simulator(scene), Simulator(scene)
    general.model._linear_step = lambda *args: None          # every step by Step._step
    return compiled, general


def _step_both(compiled, general, steps, wrench):
    for k in range(steps):
        for sim in (compiled, general):
            sim.set_wrench("tip", force=wrench(k), torque=(0.02 * np.sin(0.1 * k), 0.0, 0.0))
            sim.step()
        assert np.array_equal(compiled.vertex_positions(), general.vertex_positions()), f"step {k + 1}"


@pytest.mark.parametrize("domains", [1, 3])
def test_compiled_step_reproduces_the_general_step_bit_for_bit(domains):
    compiled, general = _pair(beam(domains))
    _step_both(compiled, general, 100, lambda k: (0.0, 2.0 * np.sin(0.05 * k), -4.0))
    a, b = compiled.model, general.model
    assert a.stats["solve_ms"] == 0.0 and b.stats["solve_ms"] > 0.0     # each took its own path
    assert np.array_equal(a.qd, b.qd)
    for name in ("c", "R", "v", "w", "w_prev"):
        assert np.array_equal(getattr(a.frames, name), getattr(b.frames, name)), name
    same = ("newton_iterations", "residual", "external_work", "contact_work", "angular_momentum_correction",
            "indefinite_system", "domains")
    assert {k: a.stats[k] for k in same} == {k: b.stats[k] for k in same}
    assert list(a.stats) == list(b.stats)
    x0 = a.body.vertices
    assert np.abs(compiled.vertex_positions() - x0).max() > 1e-3           # the beam moved


@pytest.mark.parametrize("gravity", [0.0, -9.81])
def test_compiled_step_of_a_free_spinning_body(gravity):
    """No pins: the step relative to the mean rigid motion, the Coriolis flow, the carried
    frames and the angular momentum balance after the kernel (docs/method.md §9.4), in
    free space and falling."""
    scene = beam(3, modes=8)
    scene["pins"] = []
    scene["gravity"] = [0.0, 0.0, gravity]
    compiled, general = _pair(scene)
    for sim in (compiled, general):
        sim.model.set_rigid_velocity([0.1, 0.0, 0.0], [0.0, 2.0, 1.0])
    _step_both(compiled, general, 100, lambda k: (0.0, 1.0, -2.0 * np.cos(0.1 * k)))
    a, b = compiled.model, general.model
    assert a.stats["solve_ms"] == 0.0 and b.stats["solve_ms"] > 0.0
    assert a.stats["angular_momentum_correction"] == b.stats["angular_momentum_correction"] > 0.0
    for name in ("c", "R", "v", "w"):
        assert np.array_equal(getattr(a.frames, name), getattr(b.frames, name)), name


def test_a_compiled_step_leaves_the_start_state_as_it_was():
    """The stability guard's snapshot shares the state's arrays (get_state(share=True)):
    a step must replace them, never write into them, or a rollback restores the new state."""
    scene = beam(3)
    scene["pins"] = []
    compiled = Simulator(scene)
    compiled.model.set_rigid_velocity([0.1, 0.0, 0.0], [0.0, 2.0, 1.0])
    compiled.step(3)
    model = compiled.model
    start = model.get_state(share=True)
    copies = {"q": start["q"].copy(), "qd": start["qd"].copy(),
              **{name: getattr(start["frames"], name).copy() for name in ("c", "R", "v", "w", "w_prev")}}
    compiled.step()
    assert model.stats["solve_ms"] == 0.0
    assert not np.array_equal(model.q, copies["q"])                    # the state moved on
    assert np.array_equal(start["q"], copies["q"]) and np.array_equal(start["qd"], copies["qd"])
    for name in ("c", "R", "v", "w", "w_prev"):
        assert np.array_equal(getattr(start["frames"], name), copies[name]), name


def _contact_pair(scene, steps):
    compiled, general = _pair(scene)
    for k in range(steps):
        for sim in (compiled, general):
            sim.step()
        assert np.array_equal(compiled.vertex_positions(), general.vertex_positions()), f"step {k + 1}"
    a, b = compiled.model, general.model
    assert a.stats["solve_ms"] == 0.0 and b.stats["solve_ms"] > 0.0
    assert a.contact is not None and b.contact is not None
    for key in b.contact:
        assert np.array_equal(np.asarray(a.contact[key]), np.asarray(b.contact[key])), key
    assert a.stats["contact_work"] == b.stats["contact_work"] and a.stats["residual"] == b.stats["residual"]
    return compiled


def test_compiled_step_with_frictional_contact_on_a_free_body():
    """A free block on a tilted frictional floor (issue 18's incline at 35 degrees: it
    slides): the contact rows and the Coulomb solve between the two kernels, the
    angular momentum balance skipped while the floor holds the block."""
    from mdss_ros.verify import friction_study as fs
    compiled = _contact_pair(fs.incline(35.0, fs.REDUCED), 60)
    assert compiled.model.stats["contact_rows"] > 0


def test_compiled_step_with_a_sphere_pressing_a_pinned_beam():
    """Frictionless contact (the LCP) and the residual contact compliance's dent on a
    pinned multi-domain beam."""
    scene = beam(3)
    # 1 mm under the beam, which sags onto it under gravity.
    scene["colliders"] = {"ball": {"shape": "sphere", "radius": 0.05, "position": [0.45, 0.05, -0.051]}}
    compiled = _contact_pair(scene, 40)
    assert compiled.model._dent.any()


def test_compiled_step_with_the_guard_and_its_energy_ledger():
    """Through the Simulator's stability guard (on by default) the runs' guard reports match too."""
    compiled, general = _pair(beam(3, modes=8))
    _step_both(compiled, general, 40, lambda k: (0.0, 0.0, -20.0 if k < 20 else 0.0))
    assert compiled.model.stats["solve_ms"] == 0.0 and general.model.stats["solve_ms"] > 0.0
    for key in ("stability", "energy_growth", "guard_work"):
        assert compiled.stats()[key] == general.stats()[key], key


def test_a_system_that_is_not_positive_definite_goes_the_general_way(monkeypatch):
    """A start tangent that makes A indefinite: the kernel's factor fails, nothing of the
    state is touched, and Step._step solves by LU (stats indefinite_system) as it would
    have alone."""
    compiled, general = _pair(beam(3))
    for sim in (compiled, general):
        model = sim.model
        real = model._start_evaluation

        def negative(take=False, real=real, model=model):
            (G, K, K_sI, K_ff, energy, J, x_I), timing = real(take)
            return (G, -1e9 * np.eye(model.S), K_sI, K_ff, energy, J, x_I), timing

        monkeypatch.setattr(model, "_start_evaluation", negative)
    calls = []
    real_linear = compiled.model._linear_step
    monkeypatch.setattr(compiled.model, "_linear_step", lambda *a: calls.append(real_linear(*a)) or calls[-1])
    compiled.model.step(np.zeros((len(compiled.model.body.vertices), 3)), compiled.gravity)
    general.model.step(np.zeros((len(general.model.body.vertices), 3)), general.gravity)
    assert calls == [None]
    a, b = compiled.model, general.model
    assert a.stats["indefinite_system"] and b.stats["indefinite_system"]
    assert np.array_equal(a.q, b.q) and np.array_equal(a.qd, b.qd)
    for name in ("c", "R", "v", "w", "w_prev"):
        assert np.array_equal(getattr(a.frames, name), getattr(b.frames, name)), name
    assert {k: v for k, v in a.stats.items() if not k.endswith("_ms")} == \
        {k: v for k, v in b.stats.items() if not k.endswith("_ms")}


def test_the_dependency_stamp_follows_the_linked_kernels():
    """numba caches linear_step_kernel with the machine code of the kernels it calls, keyed
    on linear_step.py alone: a change to one of those files must come with a new stamp
    there, which makes numba compile the kernel again."""
    folder = Path(linear_step.__file__).parent
    stamp = "-".join(hashlib.sha256((folder / name).read_bytes()).hexdigest()[:16]
                     for name in linear_step.DEPENDENCIES)
    assert linear_step.DEPENDENCY_STAMP == stamp, (
        f"a kernel linear_step.py links in has changed: set DEPENDENCY_STAMP = {stamp!r}")
