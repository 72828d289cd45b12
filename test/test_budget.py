"""Budget mode (mdss_ros/budget.py): model.budget picks modes from a trade-off probe."""
import pytest

from mdss_ros import Simulator, load_scene
from mdss_ros.budget import build_simulator, candidate_overrides, check_budget
from mdss_ros.errors import SceneError
from mdss_ros.precompute import PrecomputeCache
from mdss_ros.verify.reduced_reports import beam_scene


def _scene(budget, samples=0):
    s = beam_scene("reduced", size=(0.4, 0.1, 0.1), cell=0.05, domains={"count": 2}, modes=6,
                   cubature={"samples": samples}, budget=budget)
    s["duration"] = 0.2
    s["timeline"] = [{"t": 0.0, "topic": "wrench", "frame_id": "tip", "force": [0.0, 0.0, -5.0]}]
    return s


@pytest.mark.parametrize("budget, words", [
    ({"ms_per_step": 1, "max_error": 0.1}, "exactly one of"),
    ({"horizon": 1.0}, "exactly one of"),
    ({"ms_per_step": -1}, "ms_per_step: expected a positive number"),
    ({"max_error": 0.1, "speed": 3}, "unknown key"),
    ({"max_error": 0.1, "modes": [4, 0]}, "modes: expected a list of integers"),
    ("fast", "expected a mapping"),
])
def test_bad_budgets_name_the_problem(budget, words):
    with pytest.raises(SceneError, match=words):
        load_scene(_scene(budget))


def test_candidates_scale_cubature_samples_with_modes():
    model = {"modes": 10, "cubature": {"samples": 60, "interface": "uniform", "interface_samples": 30}}
    ov = candidate_overrides(model, 20)
    assert ov["model.modes"] == 20 and ov["model.cubature"]["samples"] == 120
    assert ov["model.cubature"]["interface_samples"] == 60 and ov["model.budget"] == {}
    assert candidate_overrides({"modes": 6, "cubature": {"samples": 0}}, 12)["model.cubature"]["samples"] == 0
    assert check_budget({"max_error": 0.1, "modes": [8, 4, 8]})["modes"] == [4, 8]


def test_error_budget_takes_the_cheapest_candidate_within_it_and_caches_the_choice(tmp_path):
    cache = PrecomputeCache(tmp_path)
    budget = {"max_error": 0.02, "modes": [2, 4, 8, 16], "horizon": 0.2}
    sim = build_simulator(_scene(budget), cache=cache)
    rep = sim.budget
    errors = {c["modes"]: c["rms_rel"] for c in rep["candidates"]}
    chosen = rep["chosen"]["modes"]
    assert rep["met"] and errors[chosen] <= 0.02
    assert all(e > 0.02 for m, e in errors.items() if m < chosen)          # nothing cheaper was within it
    assert sim.scene["model"]["modes"] == chosen and sim.stats()["budget"]["modes"] == chosen
    again = build_simulator(_scene(budget), cache=PrecomputeCache(tmp_path))
    assert again.budget["cached"] and again.scene["model"]["modes"] == chosen


@pytest.mark.parametrize("ms, expect", [(1e6, "largest"), (1e-6, "smallest")])
def test_time_budget_extremes(tmp_path, ms, expect):
    sim = build_simulator(_scene({"ms_per_step": ms, "modes": [2, 4], "horizon": 0.1}), cache=PrecomputeCache(tmp_path))
    assert sim.scene["model"]["modes"] == (4 if expect == "largest" else 2)
    assert sim.budget["met"] == (expect == "largest")


def test_budget_needs_a_reduced_model():
    s = _scene({"ms_per_step": 5})
    s["model"]["kind"] = "full"
    with pytest.raises(SceneError, match="reduced model"):
        build_simulator(s)


def test_a_simulator_refuses_an_unresolved_budget_and_names_the_way():
    """The probe builds Simulators itself, so budgets are resolved before one is built."""
    with pytest.raises(SceneError, match="build_simulator"):
        Simulator(_scene({"ms_per_step": 5}))
