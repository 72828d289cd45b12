"""clock_mode follow and lockstep (mdss_ros/node.py docstring; docs/architecture.md, "Contracts:
ROS interface"): the rules on their own (no ROS), the node in-process against a Simulator fed
the same stamped inputs, and real processes with a separate clock master (the probe's
play_clock) publishing /clock at 50 Hz of wall time in steps of 0.02 s, which the node's
dt of 1/90 s does not divide. clock_mode source is the default and is what test_node.py,
test_node_record.py and test_node_unit.py run.
"""
import math
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from mdss_ros import Simulator, load_scene
from mdss_ros.node import CLOCK_EPS_S, ExternalClock, MdssNode, steps_before
from mdss_ros.timeline import TimelinePlayer

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "launch_scripts"))
from launch_testing import Launch  # noqa: E402

OVERRIDES = ["body.mesh.cell=0.05", "model.domains.count=2", "model.modes=6"]
OVERRIDES_DICT = {"body.mesh.cell": 0.05, "model.domains.count": 2, "model.modes": 6}
DT = 1.0 / 90.0                    # the cantilever's dt
POSES, POSE_T = "/mdss/domain_poses", "geometry_msgs/msg/PoseArray"
SENT = "@sent/clock"               # the ticks the probe published (play_clock)
TRIGGER = "std_srvs/srv/Trigger"


def _t(stamp):
    return stamp["sec"] + 1e-9 * stamp["nanosec"]


def _k(t):
    """Step index of a sim time (stamps are k dt rounded to the nanosecond)."""
    k = round(t / DT)
    assert abs(t - k * DT) < 2e-9, t
    return k


# ---------------------------------------------------------------------- the rules, no ROS
def test_steps_before_counts_the_steps_that_fit_and_tolerates_nanosecond_truncation():
    assert steps_before(0, DT, 0.0) == 0
    assert steps_before(0, DT, 0.02) == 1                 # 1/90 fits, 2/90 = 0.0222 does not
    assert steps_before(1, DT, 0.04) == 2                 # to 3/90 = 0.0333
    assert steps_before(0, DT, 0.1) == 9                  # 9/90 = 0.1 exactly: fits
    assert steps_before(50, DT, 0.3) == 0                 # sim time already past: nothing
    assert steps_before(0, DT, -1.0) == 0
    for k in range(1, 20000, 7):
        exact = k * DT
        truncated = int(exact * 1e9) * 1e-9               # rclpy Time(seconds=...) truncates
        rounded = round(exact * 1e9) * 1e-9
        assert steps_before(0, DT, truncated) == k, k
        assert steps_before(0, DT, rounded) == k, k
        assert steps_before(0, DT, exact - 1e-6) == k - 1, k   # 1 us short: not yet
        assert steps_before(k - 1, DT, exact) == 1
    assert CLOCK_EPS_S < 1e-6 * DT * 100                  # "tiny": far below any dt in use


def test_follow_rule_tracks_a_50hz_master_within_one_dt_and_never_ahead():
    clock, k = ExternalClock("follow"), 0
    per_tick = []
    for i in range(1, 1001):                              # 20 s of master time
        T = round(0.02 * i * 1e9) * 1e-9
        assert clock.tick(T, k * DT) is False
        n = 0
        while clock.steps_due(k, DT) > 0:
            clock.stepped()
            k += 1
            n += 1
        per_tick.append(n)
        lag = clock.lag(k * DT)
        assert -CLOCK_EPS_S <= lag < DT, (i, lag)         # never ahead, behind by less than dt
    assert k == 1800 and set(per_tick) == {1, 2}          # 1.8 steps per tick on average
    assert clock.ticks == 1000 and clock.jumps_back == 0


def test_follow_rule_jump_back_resets_only_when_the_master_lands_before_the_sim_time():
    clock = ExternalClock("follow")
    assert not clock.tick(1.01, 0.0) and clock.steps_due(0, DT) == 90        # to 1.0
    assert not clock.tick(1.005, 90 * DT)                 # back, not before the sim time: hold
    assert clock.steps_due(90, DT) == 0 and clock.jumps_back == 0
    assert not clock.tick(1.02, 90 * DT) and clock.steps_due(90, DT) == 1    # passes again: 91
    assert clock.tick(0.3, 91 * DT) is True and clock.jumps_back == 1        # before it: reset
    assert clock.steps_due(0, DT) == 27                   # then follow from 0 to 0.3
    assert not clock.tick(0.0, 0.0)                       # a master at 0 with the sim at 0: nothing


def test_lockstep_rule_one_step_per_forward_tick():
    clock = ExternalClock("lockstep")
    assert not clock.tick(0.0, 0.0) and clock.steps_due(0, DT) == 0          # not forward of 0
    for t in (0.02, 0.02, 0.04, 0.04, 0.06):             # repeats step nothing
        clock.tick(t, 0.0)
    assert clock.steps_due(0, DT) == 3
    clock.stepped()
    assert clock.steps_due(1, DT) == 2
    clock.tick(0.08, 0.0, paused=True)                    # paused: not owed later
    assert clock.steps_due(1, DT) == 2
    assert clock.tick(0.05, 0.0) is True                  # back: reset, owed steps dropped
    assert clock.pending == 0 and clock.jumps_back == 1
    clock.tick(0.07, 0.0)
    assert clock.pending == 1 and clock.ticks == 9
    with pytest.raises(ValueError):
        ExternalClock("source")


def test_clock_mode_parameter_check():
    assert MdssNode._check("clock_mode", "source") is None
    assert MdssNode._check("clock_mode", "follow") is None
    assert MdssNode._check("clock_mode", "lockstep") is None
    assert "clock_mode must be one of source, follow, lockstep, got 'Follow'" in MdssNode._check("clock_mode", "Follow")
    assert "clock_mode must be a str" in MdssNode._check("clock_mode", 1)


# ---------------------------------------------------------------------- the node in-process
@pytest.mark.ros
def test_follow_node_in_process_applies_stamped_inputs_like_the_timeline_player(ros_env, monkeypatch):
    """Ticks every 0.02 s to 0.6 s with a wrench stamped 0.1 s on and 0.3 s off: the node's
    state equals a Simulator stepped 54 times by TimelinePlayer (bit for bit); then a
    jump back to 0.2 s resets and the node follows from 0 to 0.2 s (18 steps)."""
    import rclpy
    from rclpy.context import Context
    from rclpy.parameter import Parameter
    from rclpy.signals import SignalHandlerOptions
    from mdss_ros.ros import convert

    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", ros_env["ROS_AUTOMATIC_DISCOVERY_RANGE"])
    assert ros_env["ROS_AUTOMATIC_DISCOVERY_RANGE"] == "LOCALHOST"
    ctx = Context()
    rclpy.init(context=ctx, domain_id=int(ros_env["ROS_DOMAIN_ID"]), signal_handler_options=SignalHandlerOptions.NO)
    node = None
    try:
        node = MdssNode(context=ctx, parameter_overrides=[
            Parameter("scene", value="cantilever"), Parameter("scene_overrides", value=OVERRIDES),
            Parameter("clock_mode", value="follow"), Parameter("points_publish_rate", value=30.0)])
        poses = []
        tp = node._topics
        node._output_pubs[tp.domain_poses].publish = lambda data: poses.append(
            convert.decode(data, tp.type_of(tp.domain_poses)))
        assert tp.clock not in node._output_pubs and node._step_timer is None
        assert node.get_clock().now().nanoseconds > 0     # rclpy's own Node._clock is left alone

        def tick(t):
            node._on_clock(convert.clock(t))
            while node._master.steps_due(node.sim.step_count, node.sim.dt) > 0:   # what the executor does
                node._on_step_guard()

        node.submit("~/wrench", convert.wrench_stamped(0.1, "tip", [0, 0, -20, 0, 0, 0]))
        node.submit("~/wrench", convert.wrench_stamped(0.3, "tip", [0, 0, 0, 0, 0, 0]))
        for i in range(1, 31):
            tick(0.02 * i)
            assert node.sim.time <= 0.02 * i + CLOCK_EPS_S and 0.02 * i - node.sim.time < node.sim.dt
        assert node.sim.step_count == 54 and node.driver.counts["applied"] == 2
        sim = Simulator(load_scene("cantilever", OVERRIDES_DICT))
        player = TimelinePlayer([{"t": 0.1, "topic": "wrench", "frame_id": "tip", "force": [0, 0, -20]},
                                 {"t": 0.3, "topic": "wrench", "frame_id": "tip", "force": [0, 0, 0]}])
        for _ in range(54):
            player.apply_due(sim)
            sim.step()
        np.testing.assert_array_equal(node.sim.surface_positions(), sim.surface_positions())
        assert [round(convert.seconds(p.header.stamp) / DT) for p in poses] == list(range(1, 55))
        values = {kv.key: kv.value for kv in node.diagnostics().status[0].values}
        assert values["clock_mode"] == "follow" and float(values["clock_master_time"]) == pytest.approx(0.6)
        assert -CLOCK_EPS_S <= float(values["clock_lag"]) < DT and values["clock_ticks"] == "30"

        tick(0.2)                                         # the master jumped back
        assert node._master.jumps_back == 1 and node.sim.step_count == 18
        assert math.isclose(node.sim.time, 0.2, abs_tol=1e-12)
        # the reset published the state at t = 0, then the 18 steps
        assert [round(convert.seconds(p.header.stamp) / DT) for p in poses[54:]] == list(range(0, 19))
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown(context=ctx)


# ---------------------------------------------------------------------- real processes
def _start(launch, **params):
    p = dict(scene="cantilever", scene_overrides=OVERRIDES, diagnostics_rate=5.0, points_publish_rate=0.0,
             mesh_publish_rate=0.0, marker_publish_rate=0.0, pose_publish_rate=90.0)   # a pose every step
    p.update(params)
    node = launch.node(**p)
    node.wait_for(r"\] \[mdss\]: ready:", timeout=120)
    return node


def _launch(tmp_path, ros_env):
    launch = Launch(tmp_path, env=ros_env)
    assert launch.env["ROS_AUTOMATIC_DISCOVERY_RANGE"] == "LOCALHOST"
    return launch


def _graph(probe, topic, subscribers=1, timeout=10.0):
    """The probe's graph view of topic once it sees `subscribers` subscriptions on it."""
    deadline = time.monotonic() + timeout
    while True:
        g = probe.graph(topic)
        if g["subscribers"] >= subscribers or time.monotonic() > deadline:
            return g
        time.sleep(0.1)


def _never_ahead(poses, sent):
    """Worst (stamp - newest master time published before the pose was received): <= 0 means
    the node was never ahead. A tick's wall time is taken before it is published, so the
    tick a step waited for always counts."""
    worst = -math.inf
    for p in poses:
        avail = [_t(s["clock"]) for s in sent if s["_recv"] < p["_recv"]]
        worst = max(worst, _t(p["header"]["stamp"]) - (max(avail) if avail else 0.0))
    return worst


def _lags(poses, sent):
    """For each tick but the last: its time minus the newest stamp received before the next
    tick was published (how far behind the node was when the master moved on)."""
    out = []
    for a, b in zip(sent, sent[1:]):
        reached = [_t(p["header"]["stamp"]) for p in poses if p["_recv"] < b["_recv"]]
        out.append(_t(a["clock"]) - (max(reached) if reached else 0.0))
    return np.array(out)


@pytest.mark.ros
def test_follow_tracks_a_50hz_master_within_one_dt_and_never_ahead(tmp_path, ros_env):
    times = [0.02 * i for i in range(1, 101)]             # 2 s of master time at 50 Hz
    with _launch(tmp_path, ros_env) as launch:
        _start(launch, clock_mode="follow", real_time_factor=0.25)   # ignored in follow
        probe = launch.probe()
        probe.sub(POSES, POSE_T)
        probe.diagnostics(where={"clock_mode": "follow"})
        time.sleep(1.0)
        idle = probe.diagnostics()                        # no master yet: nothing steps
        graph = _graph(probe, "/clock")                   # the node subscribes, publishes nothing
        refused = probe.call("/mdss/step", TRIGGER)
        probe.play_clock(times, period=0.02)
        probe.wait(SENT, count=len(times), timeout=30)
        probe.wait(POSES, where={"stamp_ge": 2.0 - 1e-6}, timeout=30)
        time.sleep(0.5)                                   # the master stopped: so does the node
        final = probe.diagnostics()
        poses, sent = probe.get(POSES), probe.get(SENT)
        launch.stop_all(expect=0)
    assert idle["steps"] == "0" and idle["sim_time"] == "0" and idle["clock_ticks"] == "0"
    assert graph == {"publishers": 0, "subscribers": 1}, graph
    assert not refused["success"] and "follow" in refused["message"]
    assert [_k(_t(p["header"]["stamp"])) for p in poses] == list(range(1, 181))   # every step, once
    ahead = _never_ahead(poses, sent)
    lags = _lags(poses, sent)
    print(f"\nfollow: {len(poses)} steps for {len(sent)} ticks; lag when the master moved on: median "
          f"{np.median(lags) * 1e3:.2f} ms, p90 {np.percentile(lags, 90) * 1e3:.2f} ms, max "
          f"{lags.max() * 1e3:.2f} ms, {np.mean(lags < DT) * 100:.0f} % < dt = {DT * 1e3:.2f} ms; "
          f"most ahead {ahead * 1e3:+.3f} ms")
    assert ahead <= CLOCK_EPS_S, ahead
    assert lags.min() >= -CLOCK_EPS_S
    assert np.median(lags) < DT and np.mean(lags < DT) >= 0.8, lags       # timing: a loaded machine may lag
    assert final["steps"] == "180" and float(final["sim_time"]) == pytest.approx(2.0, abs=1e-9)
    assert -CLOCK_EPS_S <= float(final["clock_lag"]) < DT
    # follow subscribes BEST_EFFORT (node.py: a lost tick costs nothing, the next carries the
    # time), so DDS may drop a tick on a loaded machine (CI once counted 99 of 100 with every
    # step taken): the node must count no more ticks than were sent, and the last one.
    assert 1 <= int(final["clock_ticks"]) <= len(times)
    assert float(final["clock_master_time"]) == pytest.approx(times[-1], abs=1e-9)
    assert final["clock_jumps_back"] == "0" and final["stability"] == "ok"


@pytest.mark.ros
def test_follow_jump_back_holds_above_the_sim_time_and_resets_below_it(tmp_path, ros_env):
    """The run is recorded (mcap_path) with a wrench stamped 0.5 s: `mdss replay --check`
    reproduces it bit for bit, the reset included (the recording has /clock records of the
    sim time although the node published none)."""
    from mdss_ros.record.replay import replay
    head = [0.02 * i for i in range(1, 51)]               # to 1.0 s: 90 steps
    hold = [1.01, 1.005, 1.02]                            # back to 1.005 >= sim 1.0: hold; 1.02: step 91
    tail = [0.3 + 0.02 * i for i in range(11)]            # 0.3 < sim time: reset, follow to 0.5
    mcap = tmp_path / "follow.mcap"
    wrench = {"header": {"frame_id": "tip", "stamp": {"sec": 0, "nanosec": 500_000_000}},
              "wrench": {"force": {"x": 0.0, "y": 0.0, "z": -20.0}}}
    with _launch(tmp_path, ros_env) as launch:
        node = _start(launch, clock_mode="follow", mcap_path=str(mcap))
        probe = launch.probe()
        probe.sub(POSES, POSE_T)
        probe.pub("/mdss/wrench", "geometry_msgs/msg/WrenchStamped", wrench)
        probe.diagnostics(where={"inputs_pending": "1"})
        probe.play_clock(head + hold + tail, period=0.02)
        probe.wait(SENT, count=len(head + hold + tail), timeout=30)
        final = probe.diagnostics(where={"clock_jumps_back": "1", "steps": "45"}, timeout=30)
        poses, sent = probe.get(POSES), probe.get(SENT)
        launch.stop_all(expect=0)
    res = replay(mcap, check=True)
    assert res.ok, (res.first_mismatch, res.missing, res.extra)
    assert res.steps == 91 + 45 and res.compared >= 2 * len(poses)
    ks = [_k(_t(p["header"]["stamp"])) for p in poses]
    assert ks == list(range(1, 92)) + list(range(0, 46)), ks     # t = 0 published by the reset
    cut, split = ks.index(0, 1), len(head + hold)
    ahead = max(_never_ahead(poses[:cut], sent[:split]), _never_ahead(poses[cut:], sent[split:]))
    assert ahead <= CLOCK_EPS_S, ahead
    assert float(final["sim_time"]) == pytest.approx(0.5, abs=1e-9) and -CLOCK_EPS_S <= float(final["clock_lag"]) < DT
    warnings = [line for line in node.text.splitlines() if "jumped back" in line]
    assert len(warnings) == 1 and "from 1.02 s to 0.3 s" in warnings[0] and "resetting" in warnings[0], warnings
    print(f"\nfollow jump back: steps {ks[cut - 1]} then reset, 0..{ks[-1]}; most ahead {ahead * 1e3:+.3f} ms")


@pytest.mark.ros
def test_lockstep_steps_once_per_step_call_and_per_forward_tick(tmp_path, ros_env):
    n_calls = 12
    ticks = []
    for i in range(1, 21):                                # 20 forward ticks, 4 repeated
        ticks += [0.02 * i] * (2 if i % 5 == 0 else 1)
    with _launch(tmp_path, ros_env) as launch:
        node = _start(launch, clock_mode="lockstep", real_time_factor=0.0)
        probe = launch.probe()
        probe.sub(POSES, POSE_T)
        probe.diagnostics(where={"clock_mode": "lockstep"})
        time.sleep(1.0)
        idle = probe.diagnostics()
        graph = _graph(probe, "/clock")
        replies = [probe.call("/mdss/step", TRIGGER) for _ in range(n_calls)]
        probe.diagnostics(where={"steps": str(n_calls)})
        time.sleep(1.0)
        after_calls = probe.diagnostics()                 # nothing steps without a request
        probe.play_clock(ticks, period=0.02)
        probe.wait(SENT, count=len(ticks), timeout=30)
        probe.diagnostics(where={"clock_ticks": str(len(ticks))})
        time.sleep(1.0)
        after_ticks = probe.diagnostics()
        probe.play_clock([0.1], period=0.02)              # back from 0.4: reset, no step
        probe.wait(SENT, count=1, timeout=30)
        after_jump = probe.diagnostics(where={"clock_jumps_back": "1"})
        probe.play_clock([0.12], period=0.02)             # forward again: one step
        probe.wait(SENT, count=1, timeout=30)
        probe.diagnostics(where={"clock_ticks": str(len(ticks) + 2)})
        time.sleep(0.5)
        last = probe.diagnostics()
        poses = probe.get(POSES)
        launch.stop_all(expect=0)
    assert idle["steps"] == "0" and graph == {"publishers": 0, "subscribers": 1}, (idle, graph)
    assert all(r["success"] for r in replies)
    assert [r["message"] for r in replies] == [f"t = {k * DT:.9f} s, step {k}" for k in range(1, n_calls + 1)]
    assert after_calls["steps"] == str(n_calls)
    assert after_ticks["steps"] == str(n_calls + 20) and after_ticks["clock_steps_pending"] == "0"
    assert float(after_ticks["sim_time"]) == pytest.approx((n_calls + 20) * DT, abs=1e-6)   # .6g
    assert after_jump["steps"] == "0" and float(after_jump["sim_time"]) == 0.0
    assert last["steps"] == "1" and last["clock_jumps_back"] == "1"
    ks = [_k(_t(p["header"]["stamp"])) for p in poses]
    assert ks == list(range(1, n_calls + 21)) + [0, 1], ks
    assert sum("jumped back" in line for line in node.text.splitlines()) == 1
    print(f"\nlockstep: {n_calls} ~/step calls -> steps 1..{n_calls}; {len(ticks)} ticks "
          f"({len(set(ticks))} forward) -> {int(after_ticks['steps']) - n_calls} steps; jump back -> reset, "
          f"then 1 tick -> {last['steps']} step")


@pytest.mark.ros
def test_bad_clock_mode_is_a_startup_error(tmp_path, ros_env):
    with _launch(tmp_path, ros_env) as launch:
        word = launch.node(name="word", scene="cantilever", clock_mode="realtime")
        number = launch.node(name="number", scene="cantilever", clock_mode=2)
        assert word.wait(60) == 2 and number.wait(60) == 2
    assert "clock_mode must be one of source, follow, lockstep, got 'realtime'" in word.text
    assert "clock_mode" in number.text and "cannot start" in number.text


def test_wall_pace_keeps_sim_time_on_wall_time_through_jitter_and_gives_up_a_long_stall():
    from mdss_ros.node import WallPace
    dt, pace, k = 0.01, WallPace(), 0
    pace.start(100.0, 0)
    rng = np.random.default_rng(0)
    for n in range(1, 200):                       # firings with jitter under half a period
        now = 100.0 + n * dt + rng.uniform(0, 0.45 * dt)
        due = pace.steps_due(now, k, dt, 1.0)
        assert due == 1, (n, due)                  # never skips, never doubles
        k += due
    now = 100.0 + 205 * dt                         # a 6-period hiccup: caught up, not lost
    assert pace.steps_due(now, k, dt, 1.0) == 6
    k += 6
    assert pace.steps_due(now + 0.5, k, dt, 1.0) == 1 and pace.slips == 1      # 0.5 s behind: given up
    assert pace.steps_due(now + 0.5 + dt, k + 1, dt, 1.0) == 1                  # on a new anchor
    assert pace.steps_due(now, k, dt, 0.0) == 1    # as fast as possible: one per firing
    pace.start(100.0, 0)
    assert pace.steps_due(100.0 + 10 * dt, 0, dt, 2.0) == 20                     # real_time_factor 2
