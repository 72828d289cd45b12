"""mdss_ros: real-time multi-domain subspace simulation of deformable bodies for ROS 2.

The solver is a plain library (no rclpy import here); ``mdss_ros.node`` is the ROS shell.
"""

__version__ = "0.1.0"

from .scene import load_scene  # noqa: E402
from .simulator import Simulator  # noqa: E402

__all__ = ["load_scene", "Simulator", "__version__"]
