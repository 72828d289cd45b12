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
    assert s["model"]["kind"] == "full" and s["gravity"] == [0.0, 0.0, -9.81]


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
