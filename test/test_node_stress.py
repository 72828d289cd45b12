"""launch_scripts/stress_node.py, shortened: the fuzz (malformed and valid messages on every
input topic, predicted verdicts) and the soak (several publisher processes at a steady
rate), each against a real node process on a small model. The tests assert the tool's
criteria that do not depend on timing: no crash, every message counted, rejections as
predicted, finite outputs; the soak's RSS and real-time-factor targets are for the full
run on a quiet machine (`stress_node.py soak`), not asserted here.
"""
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "launch_scripts"))
import stress_node  # noqa: E402

pytestmark = pytest.mark.ros

FINGER_SMALL = ["body.mesh.cell=0.005", "model.modes=6"]
CANTILEVER_SMALL = ["body.mesh.cell=0.05", "model.domains.count=2", "model.modes=6"]


def _criteria(report):
    return {c["name"]: c for c in report["criteria"]}


def _explain(report):
    return "\n".join(f"{'PASS' if c['pass'] else 'FAIL'} {c['name']}: {c['detail']}" for c in report["criteria"])


def test_fuzz_plan_is_deterministic_and_covers_every_category():
    a = stress_node.make_plan(3000, seed=7, has_colliders=True, has_ghosts=True)
    assert a == stress_node.make_plan(3000, seed=7, has_colliders=True, has_ghosts=True)
    assert a != stress_node.make_plan(3000, seed=8, has_colliders=True, has_ghosts=True)
    seen = set(a)
    for group, cats in (("wrench", stress_node.WRENCH_CATS), ("point_forces", stress_node.CLOUD_CATS),
                        ("collider_pose", stress_node.POSE_CATS)):
        missing = [c for c, w in cats.items() if w >= 1 and (group, c) not in seen]
        assert not missing, (group, missing)


@pytest.mark.filterwarnings("ignore::RuntimeWarning")      # norms of the huge values overflow to inf
def test_fuzz_generator_predictions():
    """Each single-defect category is predicted as its rejection kind (the fuzz's table
    relies on it); the messages are real rclpy messages."""
    import numpy as np
    cfg = {"handles": ["top"], "colliders": ["probe"], "ghosts": ["ghost"], "world_frame": "world",
           "limits": stress_node.default_limits()}
    gen = stress_node.Generator(cfg, ([-0.02, -0.02, 0.0], [0.02, 0.02, 0.015]))
    want = {("wrench", "valid"): {"applied"}, ("wrench", "unknown_handle"): {"unknown_handle"},
            ("wrench", "non_finite"): {"non_finite"}, ("wrench", "magnitude"): {"magnitude"},
            ("wrench", "stamp_past"): {"stamp_past"}, ("wrench", "stamp_future"): {"stamp_future"},
            ("point_forces", "valid"): {"applied"}, ("point_forces", "valid_bigendian"): {"applied"},
            ("point_forces", "valid_organized"): {"applied"}, ("point_forces", "oversized"): {"magnitude"},
            ("point_forces", "truncated"): {"bad_cloud"}, ("point_forces", "offset_past_step"): {"bad_cloud"},
            ("point_forces", "step_too_small"): {"bad_cloud"}, ("point_forces", "missing_field"): {"bad_cloud"},
            ("point_forces", "wrong_datatype"): {"bad_cloud"}, ("point_forces", "bad_frame"): {"bad_frame"},
            ("collider_pose", "valid"): {"applied"}, ("collider_pose", "bad_quaternion"): {"bad_quaternion"},
            ("collider_pose", "magnitude"): {"magnitude"}, ("unknown_collider", "garbage"): {"unknown_collider"}}
    for (group, cat), kinds in want.items():
        for i in range(5):
            _, msg, verdict = gen.build(group, cat, np.random.default_rng([1, i]), 10.0)
            assert verdict in kinds, (group, cat, i, verdict)


def test_fuzz_small(tmp_path):
    report = stress_node.run_fuzz("soft_finger", messages=300, seed=1, sets=FINGER_SMALL,
                                  workdir=tmp_path / "fuzz", mcap=tmp_path / "mcap", rate=500.0)
    crit = _criteria(report)
    s = report["sent"]
    assert s["sent"] == 300 and s["acked"], s
    assert s["ghosts"], "no unknown-collider topic was subscribed by the node"
    assert set(s["sent_by_topic"]) >= {"wrench", "point_forces", "collider:probe"}
    # every criterion of the tool (crash, counting, kinds, finite outputs and recording)
    assert report["passed"], _explain(report)
    assert crit["every message counted"]["pass"] and crit["no non-finite value in the recording"]["pass"]
    assert report["mcap_check"]["checked"] > 100 and not report["mcap_check"]["skipped"]


def test_soak_short(tmp_path):
    report = stress_node.run_soak("cantilever", publishers=2, rate=200.0, seconds=8.0, sets=CANTILEVER_SMALL,
                                  workdir=tmp_path / "soak")
    crit = _criteria(report)
    assert report["sent"] >= 2 * 200 * 8 * 0.5, report["publisher_results"]        # both publishers ran
    assert crit["no crash"]["pass"], crit["no crash"]["detail"]
    assert crit["received == sent"]["pass"], crit["received == sent"]["detail"]
    assert crit["no non-finite output (subscriber)"]["pass"], crit["no non-finite output (subscriber)"]["detail"]
    assert report["output_ticks"]["distinct"] > 0 and report["latency_ms"]["n"] > 0
