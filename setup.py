"""ament_python package; also installs with plain pip (the path CI and the README use)."""
import os
from glob import glob

from setuptools import find_packages, setup

package_name = "mdss_ros"


def _files(pattern):
    return sorted(f for f in glob(pattern, recursive=True) if os.path.isfile(f))


setup(
    name=package_name,
    version="0.1.0",
    packages=find_packages(exclude=["test", "test.*"]),
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + package_name]),
        ("share/" + package_name, ["package.xml"]),
        ("share/" + package_name + "/config", _files("config/*")),
        ("share/" + package_name + "/msg_scenes", _files("msg_scenes/*")),
        # surface meshes the scenes name relative to themselves (grasp_lift's pads, the bunny)
        ("share/" + package_name + "/msg_scenes/meshes", _files("msg_scenes/meshes/*")),
    ],
    install_requires=["setuptools"],
    zip_safe=True,
    maintainer="mdss_ros developers",
    maintainer_email="mdss@example.com",
    description="Multi-domain subspace simulation of deformable bodies for ROS 2",
    license="Apache-2.0",
    python_requires=">=3.11",
    entry_points={
        "console_scripts": [
            "mdss = mdss_ros.cli:main",
            "mdss_node = mdss_ros.node:main",
        ],
    },
)
