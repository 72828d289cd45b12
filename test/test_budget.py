"""Budget mode (mdss_ros/budget.py): model.budget picks modes from a trade-off probe."""
import pytest

from mdss_ros import Simulator, load_scene
from mdss_ros.budget import build_simulator, candidate_overrides, check_budget
from mdss_ros.errors import SceneError
from mdss_ros.precompute import PrecomputeCache
from mdss_ros.verify.reduced_reports import beam_scene
from small_bodies import star3


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


def test_a_simulator_resolves_its_budget_itself_and_a_second_one_reads_the_cache(tmp_path):
    """Simulator(scene) with a model.budget probes once (budget-free Simulators inside, so
    no recursion) and the next Simulator of the same scene takes the choice from the cache."""
    budget = {"ms_per_step": 1e6, "modes": [2, 4], "horizon": 0.1}
    sim = Simulator(_scene(budget), cache=PrecomputeCache(tmp_path))
    assert sim.scene["model"]["modes"] == 4 and not sim.budget["cached"]
    again = Simulator(_scene(budget), cache=PrecomputeCache(tmp_path))
    assert again.budget["cached"] and again.scene["model"]["modes"] == 4
    with pytest.raises(SceneError, match="not resolved"):
        Simulator(_scene(budget), budget=sim.budget)
    from mdss_ros.simulator import Simulator as Base      # the probe's own class refuses it
    with pytest.raises(SceneError, match="use mdss_ros.Simulator"):
        Base(_scene(budget))


def test_an_exact_probe_walks_the_ladder_without_cubature_then_measures_the_chosen_with_it(tmp_path):
    """budget.probe: exact (the automatic model's): candidates run with exact forces, and the
    chosen one is then built with its cubature (samples scaled with its modes) and measured."""
    budget = {"max_error": 0.05, "modes": [2, 4, 8], "horizon": 0.2, "probe": "exact"}
    sim = build_simulator(_scene(budget, samples=30), cache=PrecomputeCache(tmp_path))
    rep = sim.budget
    assert [c["samples"] for c in rep["candidates"]] == [0] * len(rep["candidates"])     # exact forces
    chosen = rep["chosen"]
    assert chosen["measured"]["with_cubature"] and chosen["measured"]["modes"] == chosen["modes"]
    assert sim.scene["model"]["cubature"]["samples"] == -(-30 * chosen["modes"] // 6) > 0
    assert 0.0 < chosen["measured"]["rms_rel"] < 0.2          # the sampled forces are close to the exact ones
    assert "probe used exact forces" in "\n".join(sim.explain())
    with pytest.raises(SceneError, match="probe"):
        load_scene(_scene({"max_error": 0.05, "probe": "fast"}))


def _star3(budget):
    """The small voxel star (auto domains: 4) with a tip load on one arm."""
    return star3({"kind": "auto", "budget": budget}, handles={"tip": {"box": [[0.33, -1, -1], [1, 1, 1]]}},
                 duration=0.3, timeline=[{"t": 0.0, "topic": "wrench", "frame_id": "tip", "force": [0.0, 0.0, 30.0]}])


def test_the_budget_weighs_domain_options_and_takes_the_fastest_within_the_error(tmp_path):
    """budget.domains: [auto, 1]: at each mode count of the ladder both splits run; the walk
    stops at the first mode count where one is within the error and takes the faster."""
    budget = {"max_error": 0.2, "modes": [2, 4, 8], "horizon": 0.2, "domains": ["auto", 1, 1]}
    sim = Simulator(_star3(budget), cache=PrecomputeCache(tmp_path))
    rep = sim.budget
    labels = {c["domains"] for c in rep["candidates"]}
    assert labels == {"auto (4 domains)", "1 domain"}          # the repeated count is tried once
    last = [c for c in rep["candidates"] if c["modes"] == rep["chosen"]["modes"]]
    within = [c for c in last if c["rms_rel"] <= 0.2]
    assert rep["met"] and within and len(last) == 2
    assert rep["chosen"]["domains"] == min(within, key=lambda c: c["step_ms"])["domains"]
    assert all(min(c["rms_rel"] for c in rep["candidates"] if c["modes"] == m) > 0.2
               for m in {c["modes"] for c in rep["candidates"]} if m < rep["chosen"]["modes"])
    assert sim.stats()["domains"] == (4 if rep["chosen"]["domains"].startswith("auto") else 1)
    assert rep["chosen"]["domains"] in "\n".join(sim.explain())
    with pytest.raises(SceneError, match="needs an error goal"):
        load_scene(_star3({"ms_per_step": 5, "domains": ["auto", 1]}))
    with pytest.raises(SceneError, match="domains: expected a list"):
        load_scene(_star3({"max_error": 0.1, "domains": "auto"}))


def test_the_node_start_notice_says_a_budget_probe_comes_first_then_reads_its_choice(tmp_path):
    from mdss_ros.node import precompute_notice
    budget = {"ms_per_step": 1e6, "modes": [2, 4], "horizon": 0.1}
    scene = load_scene(_scene(budget))
    assert "not probed yet" in precompute_notice(scene, PrecomputeCache(tmp_path))
    build_simulator(scene, cache=PrecomputeCache(tmp_path))
    assert "cache hit" in precompute_notice(scene, PrecomputeCache(tmp_path))
