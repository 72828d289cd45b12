"""The reduced step's phase times (stats domain_ms, coupling_ms, factor_ms, solve_ms) cover the
whole step: every evaluation and every solve of its Newton iterations and line search, not
only those after the last evaluation (reduced/generalised_forces.py, GeneralisedForces._timed).

Checked structurally: the clock the phases read is replaced by one that advances by exactly
one second per reading, so each evaluation adds 1000 ms to domain_ms and to coupling_ms and
each solve 1000 ms to factor_ms and to solve_ms; the calls are counted."""
from types import SimpleNamespace

import numpy as np
import pytest

from mdss_ros import Simulator
from mdss_ros.precompute import PrecomputeCache
from mdss_ros.reduced import generalised_forces, step, unified_system


def _reduced(iterations):
    scene = {"name": "t",
             "body": {"mesh": {"generator": "box", "size": [0.4, 0.1, 0.1], "cell": 0.05},
                      "material": {"model": "neohookean", "young": 2e4, "poisson": 0.3, "density": 1000},
                      "damping": {"alpha": 0.0, "beta": 0.0}},
             "pins": [{"box": [[-0.001, -1, -1], [0.001, 1, 1]]}],
             "gravity": [0.0, 0.0, -9.81],
             "model": {"kind": "reduced", "domains": {"count": 2}, "modes": 6,
                       "cubature": {"samples": 0, "interface": "exact"},
                       "integrator": {"dt": 0.01, "newton_iterations": iterations, "line_search": True}}}
    return Simulator(scene, cache=PrecomputeCache(enabled=False)).model


def _counted(monkeypatch, model, name, calls):
    real = getattr(model, name)

    def counting(*args, **kwargs):
        calls.append(name)
        return real(*args, **kwargs)

    monkeypatch.setattr(model, name, counting)


def test_phase_times_sum_over_every_newton_iteration(monkeypatch):
    model = _reduced(iterations=3)
    ticks = iter(range(10 ** 6))
    clock = SimpleNamespace(perf_counter=lambda: float(next(ticks)))     # 1 s a reading
    monkeypatch.setattr(generalised_forces, "time", clock)
    monkeypatch.setattr(unified_system, "time", clock)
    calls = []
    _counted(monkeypatch, model, "_evaluate", calls)
    _counted(monkeypatch, model, "_solve", calls)
    f = np.zeros((len(model.body.vertices), 3))
    f[model.body.vertices[:, 0] > 0.39, 2] = -50.0           # a hard pull: Newton iterates
    model.set_state(model.get_state())                        # no cached start evaluation
    stats = model.step(f, np.array([0.0, 0.0, -9.81]))
    evaluations, solves = calls.count("_evaluate"), calls.count("_solve")
    assert stats["newton_iterations"] >= 2 and evaluations >= 2 and solves >= 2
    assert stats["domain_ms"] == stats["coupling_ms"] == 1000.0 * evaluations
    assert stats["factor_ms"] == stats["solve_ms"] == 1000.0 * solves


@pytest.mark.parametrize("compiled", [True, False])
def test_a_start_evaluation_made_before_the_step_counts_once(monkeypatch, compiled):
    """Under the guard the start evaluation is made by its measure after the last step
    (cached): the step reports it, with the evaluations of its own iterations, and a second
    step starts from zero again. compiled: the step runs linear_step.py's kernels (one
    Newton iteration, no contact), whose whole time is factor_ms (the system, its factor
    and sweeps, the new frames: one call) with solve_ms 0; else Step._step's path, one
    _solve."""
    model = _reduced(iterations=1)
    if not compiled:
        model._linear_step = lambda *args: None
    ticks = iter(range(10 ** 6))
    clock = SimpleNamespace(perf_counter=lambda: float(next(ticks)))
    monkeypatch.setattr(generalised_forces, "time", clock)
    monkeypatch.setattr(unified_system, "time", clock)
    monkeypatch.setattr(step, "time", clock)
    f = np.zeros((len(model.body.vertices), 3))
    g = np.array([0.0, 0.0, -9.81])
    calls = []
    _counted(monkeypatch, model, "_evaluate", calls)
    _counted(monkeypatch, model, "_solve", calls)
    model.set_state(model.get_state())            # no cached start evaluation
    for _ in range(2):
        model.elastic_energy()                    # the guard's measure: the start evaluation
        assert calls.count("_evaluate") == 1
        calls.clear()
        stats = model.step(f, g)
        assert calls == ([] if compiled else ["_solve"])      # one iteration, its evaluation cached
        assert stats["domain_ms"] == stats["coupling_ms"] == 1000.0
        if compiled:
            assert stats["factor_ms"] == 1000.0 and stats["solve_ms"] == 0.0
        else:
            assert stats["factor_ms"] == stats["solve_ms"] == 1000.0
        calls.clear()
