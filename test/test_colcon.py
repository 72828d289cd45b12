"""The ROS 2 workspace path: colcon builds the package from the venv, and the node it
installs (install/mdss_ros/lib/mdss_ros/mdss_node) starts and is seen from another process.

colcon (colcon-common-extensions) and ament_package are pinned in requirements.txt, so
the build runs with the venv's python, as `colcon build` in a sourced ROS 2 workspace
runs with the system's. The workspace is a scratch folder whose src/ links this repo.
"""
import os
import subprocess
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "launch_scripts"))
from launch_testing import Launch  # noqa: E402

pytestmark = pytest.mark.ros

REPO = Path(__file__).resolve().parents[1]
OVERRIDES = ["body.mesh.cell=0.05", "model.domains.count=2", "model.modes=6"]


def _build(ws):
    (ws / "src").mkdir(parents=True)
    (ws / "src" / "mdss_ros").symlink_to(REPO, target_is_directory=True)
    env = dict(os.environ, COLCON_HOME=str(ws / ".colcon"))
    out = subprocess.run([sys.executable, "-m", "colcon", "--log-base", str(ws / "log"), "build",
                          "--base-paths", str(ws / "src"), "--build-base", str(ws / "build"),
                          "--install-base", str(ws / "install"), "--packages-select", "mdss_ros",
                          "--event-handlers", "console_direct-"],
                         cwd=ws, env=env, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-3000:]
    assert "1 package finished" in out.stdout, out.stdout[-2000:]
    return ws / "install" / "mdss_ros"


def test_colcon_builds_the_package_and_its_installed_node_runs(tmp_path):
    prefix = _build(tmp_path / "ws")
    # What ament_python promises: the executables under lib/<pkg>, the package index
    # marker, package.xml, config and scenes under share/<pkg>, the library on the path.
    node_exe = prefix / "lib" / "mdss_ros" / "mdss_node"
    assert node_exe.is_file() and os.access(node_exe, os.X_OK)
    assert (prefix / "lib" / "mdss_ros" / "mdss").is_file()
    assert node_exe.read_text().splitlines()[0] == f"#!{sys.executable}"
    assert (prefix / "share" / "ament_index" / "resource_index" / "packages" / "mdss_ros").is_file()
    for rel in ("package.xml", "config/params.yaml", "msg_scenes/cantilever.yaml",
                "msg_scenes/meshes/finger_pad.obj", "msg_scenes/meshes/bunny.obj"):
        assert (prefix / "share" / "mdss_ros" / rel).is_file(), rel
    site = next(prefix.glob("lib/python3*/site-packages"))
    assert (site / "mdss_ros" / "node.py").is_file()

    # Start the installed executable as `ros2 run` would (its own process, the install's
    # library first on the path), and see its topics from a probe process.
    with Launch(tmp_path / "launch") as launch:
        launch.env["PYTHONPATH"] = os.pathsep.join([str(site), launch.env.get("PYTHONPATH", "")])
        launch.env["AMENT_PREFIX_PATH"] = str(prefix)
        node = launch.start("node", [node_exe, "--ros-args", "--params-file",
                                     prefix / "share" / "mdss_ros" / "config" / "params.yaml",
                                     "-p", "scene:=cantilever",
                                     "-p", "scene_overrides:=[" + ", ".join(f'"{o}"' for o in OVERRIDES) + "]"],
                            cwd=tmp_path)
        node.wait_for(r"\] \[mdss\]: ready:", timeout=120)
        probe = launch.probe()
        probe.sub("/mdss/surface/topology", "shape_msgs/msg/Mesh", qos="latched")
        topo = probe.wait("/mdss/surface/topology", timeout=30)[0]
        probe.sub("/clock", "rosgraph_msgs/msg/Clock")
        probe.wait("/clock", count=5, timeout=30)
        launch.stop_all(expect=0)
    assert len(topo["triangles"]) > 0 and len(topo["vertices"]) > 0
    # The scene name was found where the workspace installed it, as `ros2 run` needs.
    installed_scene = prefix / "share" / "mdss_ros" / "msg_scenes" / "cantilever.yaml"
    assert any(f"({installed_scene})" in line for line in node.lines), node.tail()
