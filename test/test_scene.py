import pytest

from mdss_ros import load_scene
from mdss_ros.errors import SceneError

BASE = {
    "name": "t",
    "body": {"mesh": {"generator": "box", "size": [0.2, 0.05, 0.05], "cell": 0.025},
             "material": {"model": "stvk", "young": 1e5, "poisson": 0.3, "density": 1000}},
    "pins": [{"box": [[-0.001, -1, -1], [0.001, 1, 1]]}],
}


def test_defaults_filled_and_overrides_applied():
    s = load_scene(BASE, overrides={"model.integrator.dt": 0.01, "model.modes": 7})
    assert s.dt == 0.01 and s["model"]["modes"] == 7
    assert s["model"]["kind"] == "reduced" and s["gravity"] == [0.0, 0.0, -9.81]
    assert s["model"]["budget"] == {}                     # modes given: the ladder does not choose them


@pytest.mark.parametrize("model", [None, "auto", {"kind": "auto"}])
def test_a_scene_without_a_model_section_gets_the_automatic_model(model):
    """Issue 15: no model section -> reduced, domains placed from the shape, cubature on
    (10 samples per mode), modes by the budget ladder to 5 % RMS error, probed with exact forces."""
    raw = dict(BASE) if model is None else dict(BASE, model=model)
    s = load_scene(raw)
    m = s["model"]
    assert s.automatic_model and m["kind"] == "reduced" and m["domains"] == {"auto": True}
    assert m["cubature"]["samples"] == 10 * m["modes"] and m["cubature"]["interface"] == "exact"
    assert m["budget"]["max_error"] == 0.05 and m["budget"]["probe"] == "exact"
    assert load_scene(s).automatic_model                  # a Scene re-loaded keeps the flag


def test_the_automatic_model_keeps_what_the_scene_gives_and_full_stays_full():
    s = load_scene(dict(BASE, model={"kind": "auto", "domains": {"count": 3}, "integrator": {"dt": 0.02}}))
    assert s["model"]["domains"] == {"count": 3} and s.dt == 0.02 and s["model"]["budget"]["max_error"] == 0.05
    assert load_scene(BASE, {"model.kind": "full"})["model"]["kind"] == "full"
    assert not load_scene(BASE, {"model.kind": "full"}).automatic_model
    plain = load_scene(dict(BASE, model={"kind": "reduced"}))
    assert not plain.automatic_model and plain["model"]["budget"] == {} and plain["model"]["domains"] == {"auto": True}
    assert load_scene(dict(BASE, model={"integrator": {"dt": 0.02}}))["model"]["kind"] == "full"


def test_cantilever_scene_file_loads_by_name():
    s = load_scene("cantilever")
    assert s.name == "cantilever" and s.source.endswith("cantilever.yaml")


@pytest.mark.parametrize("override, words", [
    ({"model.kind": "magic"}, ["model.kind", "magic"]),
    ({"model.integrator.dt": -1.0}, ["model.integrator.dt", "positive"]),
    ({"model.modes": 0}, ["model.modes"]),
    ({"body.colour": "red"}, ["unknown key", "body.colour"]),
    ({"gravity": [0, 0]}, ["gravity", "3 numbers"]),
])
def test_bad_values_name_the_key(override, words):
    with pytest.raises(SceneError) as err:
        load_scene(BASE, overrides=override)
    for w in words:
        assert w in str(err.value)


def test_missing_required_key_and_missing_file():
    raw = dict(BASE)
    raw.pop("body")
    with pytest.raises(SceneError, match="body.mesh"):
        load_scene(raw)
    with pytest.raises(SceneError, match="not found"):
        load_scene("no_such_scene_anywhere")


def test_body_errors_name_the_problem():
    from mdss_ros import Simulator
    with pytest.raises(SceneError, match=r"pins\[0\].*selects no vertex"):
        Simulator(BASE, overrides={"pins": [{"box": [[5, 5, 5], [6, 6, 6]]}]})
    with pytest.raises(SceneError, match="handles.tip"):
        Simulator(BASE, overrides={"handles": {"tip": {"box": [[5, 5, 5], [6, 6, 6]]}}})
    with pytest.raises(SceneError, match="poisson|0.5"):
        Simulator(BASE, overrides={"body.material.poisson": 0.5})
    with pytest.raises(SceneError, match="young"):
        Simulator(BASE, overrides={"body.material.young": -3.0})
    with pytest.raises(SceneError, match="generator"):
        Simulator(BASE, overrides={"body.mesh": {"generator": "donut"}})


def test_yaml_exponent_floats_are_numbers():
    from mdss_ros.scene import read_yaml
    assert read_yaml("a: 1.0e7\nb: 1e5\nc: -2.5E-3") == {"a": 1e7, "b": 1e5, "c": -2.5e-3}


def test_the_automatic_budget_takes_the_scenes_settings_and_yields_to_its_goal():
    part = load_scene(BASE, {"model.budget.horizon": 0.5})["model"]["budget"]
    assert part["max_error"] == 0.05 and part["horizon"] == 0.5 and part["probe"] == "exact"
    own = load_scene(BASE, {"model.budget": {"ms_per_step": 3.0}})["model"]["budget"]
    assert own["ms_per_step"] == 3.0 and "max_error" not in own
