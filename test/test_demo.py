"""The README's first command, launch_scripts/demo.sh, run as a newcomer runs it.

The demo bootstraps the repository's own .venv (here it exists: the suite runs in it),
runs the node on the default scene with a separate timeline publisher, records an MCAP
bag and a rerun file, and prints how to open them. This runs it on a leased ROS domain
with no display, then checks what it said against what it wrote, and replays the bag
with `mdss replay --check` (every recorded output reproduced bit for bit).
"""
import hashlib
import os
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "launch_scripts"))


#: What bootstrap.sh hashes into .venv/.mdss_stamp (its stamp_of), in its order.
STAMPED = ("requirements.txt", "requirements.lock.txt", "requirements-peers.txt", "requirements-tf.txt",
           "setup.py", "launch_scripts/bootstrap.sh")


def _in_repo_venv():
    """demo.sh runs the repository's .venv, bootstrapping it when missing or stale: only a
    suite that runs in that venv, up to date (run_tests.sh and .ci/run bootstrap it first),
    can run it without rebuilding the venv under the running tests."""
    venv = REPO / ".venv"
    if not (venv.is_dir() and Path(sys.prefix).resolve() == venv.resolve()):
        return False
    stamp = hashlib.sha256(b"".join((REPO / f).read_bytes() for f in STAMPED)).hexdigest()[:16]
    try:
        return (venv / ".mdss_stamp").read_text().strip() == stamp
    except OSError:
        return False


@pytest.mark.ros
@pytest.mark.skipif(not _in_repo_venv(), reason="demo.sh uses the repository's own .venv: run the suite "
                                               "through launch_scripts/run_tests.sh")
def test_demo_records_replays_and_says_how_to_open_what_it_wrote(tmp_path):
    from launch_testing import DomainLease, ros_env
    lease = DomainLease()
    try:
        env = ros_env(lease.domain_id, log_dir=tmp_path / "ros_log", base=os.environ)
        for name in ("DISPLAY", "WAYLAND_DISPLAY"):               # a headless machine, as CI is
            env.pop(name, None)
        env["MDSS_OUT"] = str(tmp_path / "demo")
        # Its own process group: on a timeout every process it started (run_scene, the node,
        # the publisher) is stopped before the domain is released.
        demo = subprocess.Popen(["bash", str(REPO / "launch_scripts" / "demo.sh")], env=env, cwd=tmp_path,
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)
        try:
            out, err = demo.communicate(timeout=900)
        except subprocess.TimeoutExpired:
            os.killpg(demo.pid, signal.SIGKILL)
            out, err = demo.communicate()
            pytest.fail(f"demo.sh did not end in 900 s:\n{out[-3000:]}\n{err[-3000:]}")
    finally:
        lease.release()
    assert demo.returncode == 0, (out[-3000:], err[-3000:])
    assert "demo: done in" in out
    bags = sorted((tmp_path / "demo").glob("bag_*"))
    rrds = sorted((tmp_path / "demo").glob("run_*.rrd"))
    assert len(bags) == 1 and len(rrds) == 1, (bags, rrds)
    mcaps = list(bags[0].glob("*.mcap"))
    assert len(mcaps) == 1 and mcaps[0].stat().st_size > 10_000 and rrds[0].stat().st_size > 10_000
    # It names what it wrote, and how to open each on this machine: no display, so rerun's
    # web viewer; ros2 bag only with the note that it needs a ROS 2 install when ros2 is absent.
    assert str(bags[0]) in out and str(rrds[0]) in out and str(mcaps[0]) in out
    assert f"rerun --serve-web {rrds[0]}" in out
    assert f"ros2 bag info {bags[0]}" in out
    assert ("needs a ROS 2 Jazzy install" in out) == (shutil.which("ros2", path=env.get("PATH")) is None)
    replay_line = f"{REPO / '.venv' / 'bin' / 'mdss'} replay {bags[0]} --check"
    assert replay_line in out
    # The replay it suggests passes.
    rep = subprocess.run([str(REPO / ".venv" / "bin" / "mdss"), "replay", str(bags[0]), "--check"],
                         env=env, capture_output=True, text=True, timeout=600)
    assert rep.returncode == 0, (rep.stdout[-2000:], rep.stderr[-2000:])
    assert "check passed" in rep.stdout + rep.stderr
