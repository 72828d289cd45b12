"""Precompute cache: reuse, staged invalidation, corrupt and foreign files."""
import numpy as np

from mdss_ros import Simulator, load_scene
from mdss_ros.precompute import PrecomputeCache

OV = {"body.mesh.cell": 0.05, "model.domains.count": 2, "model.modes": 6,
      "model.cubature": {"samples": 30, "training": {"n_poses": 20, "stride": 2, "hold": 6}}}


def _run(cache, ov=OV):
    sim = Simulator(load_scene("cantilever", overrides=ov), cache=cache)
    sim.set_wrench("tip", force=(0.0, 0.0, -10.0))
    sim.step(10)
    return sim


def _kinds(cache):
    return [(stage, kind) for stage, kind, _ in cache.events]


def test_second_build_loads_everything_and_steps_identically(tmp_path):
    first = PrecomputeCache(tmp_path)
    a = _run(first)
    assert ("bases", "saved") in _kinds(first) and ("cubature", "saved") in _kinds(first)
    second = PrecomputeCache(tmp_path)
    b = _run(second)
    assert _kinds(second) == [("bases", "hit"), ("cubature", "hit")]
    for da, db in zip(a.model.subspace, b.model.subspace):
        np.testing.assert_array_equal(da.U, db.U)
        np.testing.assert_array_equal(da.sampled.elements, db.sampled.elements)
    np.testing.assert_array_equal(a.vertex_positions(), b.vertex_positions())
    assert b.build_seconds < a.build_seconds


def test_changing_cubature_settings_reuses_the_bases(tmp_path):
    _run(PrecomputeCache(tmp_path))
    cache = PrecomputeCache(tmp_path)
    _run(cache, dict(OV, **{"model.cubature": {"samples": 12, "training": {"n_poses": 20, "stride": 2, "hold": 6}}}))
    assert ("bases", "hit") in _kinds(cache) and ("cubature", "miss") in _kinds(cache)
    cache = PrecomputeCache(tmp_path)
    _run(cache, dict(OV, **{"model.modes": 5}))
    assert ("bases", "miss") in _kinds(cache)


def test_corrupt_and_foreign_files_are_reported_and_rebuilt(tmp_path):
    ref = _run(PrecomputeCache(tmp_path))
    files = sorted(tmp_path.glob("bases-*.npz"))
    assert len(files) == 1
    files[0].write_bytes(files[0].read_bytes()[:200])          # truncated
    cache = PrecomputeCache(tmp_path)
    again = _run(cache)
    assert ("bases", "corrupt") in _kinds(cache) and ("bases", "saved") in _kinds(cache)
    np.testing.assert_array_equal(again.vertex_positions(), ref.vertex_positions())
    # A valid file of other inputs under this name is caught by its key.
    other = PrecomputeCache(tmp_path / "other")
    _run(other, dict(OV, **{"model.modes": 5}))
    foreign = sorted((tmp_path / "other").glob("bases-*.npz"))[0]
    files[0].write_bytes(foreign.read_bytes())
    cache = PrecomputeCache(tmp_path)
    _run(cache)
    events = [e for e in cache.events if e[0] == "bases"]
    assert events[0][1] == "corrupt" and "other inputs" in events[0][2]


def test_cache_status_reports_missing_then_hit(tmp_path):
    from mdss_ros.model_build import cache_status
    scene = load_scene("cantilever", overrides=OV)
    cache = PrecomputeCache(tmp_path)
    before = cache_status(scene, cache)
    assert not before["hit"] and before["estimate_s"] > 0
    Simulator(scene, cache=PrecomputeCache(tmp_path))
    after = cache_status(scene, PrecomputeCache(tmp_path))
    assert after["hit"] and after["estimate_s"] is None and after["path"].endswith(".npz")


def test_region_order_is_part_of_the_bases_key():
    """The first region to select a vertex wins, so two scenes listing the same regions in
    another order are different partitions and must not share cached bases."""
    from mdss_ros.body import build_body
    from mdss_ros.precompute import bases_cache_key
    from mdss_ros.scene import load_scene, model_config
    a = {"left": {"box": [[-1, -1, -1], [0.25, 1, 1]]}, "right": {"box": [[0.15, -1, -1], [1, 1, 1]]}}
    b = dict(reversed(list(a.items())))
    keys = []
    for regions in (a, b):
        scene = load_scene({"name": "t", "body": {"mesh": {"generator": "box", "size": [0.4, 0.1, 0.1], "cell": 0.05},
                                                  "material": {"model": "stvk", "young": 1e5, "poisson": 0.3,
                                                               "density": 1000}},
                            "model": {"kind": "reduced", "domains": {"regions": regions}, "modes": 4}})
        keys.append(bases_cache_key(build_body(scene), model_config(scene)))
    assert keys[0] != keys[1]


def test_code_fingerprint_ignores_comments_and_docstrings_not_code():
    from mdss_ros.precompute import code_fingerprint
    a = 'def f(x):\n    """Doc."""\n    return x + 1  # why\n'
    b = '# header\ndef f(x):\n    """Other doc,\n    longer."""\n    # a note\n    return x + 1\n'
    c = 'def f(x):\n    """Doc."""\n    return x + 2\n'
    d = 'def f(x):\n    return "x + 1"\n'                   # a string that is code, not a docstring
    assert code_fingerprint(a) == code_fingerprint(b)
    assert code_fingerprint(a) != code_fingerprint(c)
    assert code_fingerprint(a) != code_fingerprint(d)


def test_code_fingerprint_of_one_method():
    from mdss_ros.precompute import STAGE_CODE, code_fingerprint, code_hash
    src = "class A:\n    def f(self):\n        return 1\n\n    def g(self):\n        return 2\n"
    changed_g = src.replace("return 2", "return 3")
    assert code_fingerprint(src, "A.f") == code_fingerprint(changed_g, "A.f")
    assert code_fingerprint(src, "A.g") != code_fingerprint(changed_g, "A.g")
    assert code_fingerprint(src, "A.h") == b"missing"
    # Every method the stages name exists (a rename must not silently drop it from the hash).
    from pathlib import Path
    import mdss_ros
    root = Path(mdss_ros.__file__).parent
    for items in STAGE_CODE.values():
        for item in items:
            rel, _, name = item.partition("::")
            assert code_fingerprint((root / rel).read_text(), name or None) != b"missing", item
    assert code_hash("bases") != code_hash("cubature")


def test_file_fingerprints_are_remembered_until_the_file_changes(tmp_path, monkeypatch):
    """The per-process memo of code fingerprints: a second read of an unchanged file parses
    nothing, and an edit (a new mtime or size) is fingerprinted again."""
    import os
    import mdss_ros.precompute as precompute
    parses = []
    real = precompute.code_fingerprint
    monkeypatch.setattr(precompute, "code_fingerprint", lambda src, name=None: parses.append(name) or real(src, name))
    f = tmp_path / "m.py"
    f.write_text("def f():\n    return 1\n")
    first = precompute._file_fingerprint(f, None)
    assert precompute._file_fingerprint(f, None) == first and len(parses) == 1
    assert precompute._file_fingerprint(f, "f") != first and len(parses) == 2      # a definition: its own entry
    st = f.stat()
    f.write_text("def f():\n    return 2\n")                                    # same size: the mtime tells
    os.utime(f, ns=(st.st_atime_ns, st.st_mtime_ns + 1_000_000))
    changed = precompute._file_fingerprint(f, None)
    assert changed != first and len(parses) == 3


def test_two_writers_of_one_entry_both_finish(tmp_path, monkeypatch):
    """Two runs that build the same precompute at once (two nodes started on one scene, a
    cold shared cache) both save it. They wrote it through the same temporary name
    (KEY.tmp): the first rename moved the other's file away and the second writer's
    os.replace raised FileNotFoundError, failing its build. Here the second writer saves
    while the first is between writing and renaming."""
    import mdss_ros.precompute as precompute
    a, b = PrecomputeCache(tmp_path), PrecomputeCache(tmp_path)
    arrays = {"x": np.arange(5.0)}
    replace = precompute.os.replace
    calls = []

    def interleaved(src, dst):
        calls.append(src)
        if len(calls) == 1:
            b.save("bases", "k", arrays)          # the other run, in the window
        replace(src, dst)
    monkeypatch.setattr(precompute.os, "replace", interleaved)
    a.save("bases", "k", arrays)
    assert len(calls) == 2 and calls[0] != calls[1]
    assert np.array_equal(PrecomputeCache(tmp_path).load("bases", "k")[0]["x"], arrays["x"])
    assert not list(tmp_path.glob("*.tmp"))
