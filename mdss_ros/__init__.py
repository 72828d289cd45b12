"""mdss_ros: real-time multi-domain subspace simulation of deformable bodies for ROS 2.

The solver is a plain library (no rclpy import here); ``mdss_ros.node`` is the ROS shell.
"""

import os
import sys

# A step makes many BLAS calls on tiny matrices (domain blocks of ~20-30 rows); threaded
# OpenBLAS spins on those and, on a loaded 2-core machine, turned an 18x18 triangular
# solve from 8 us into 1.4 ms. Parallelism comes from numba kernels and PARDISO instead.
# Only effective when mdss_ros is imported before numpy; the user's setting wins.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

# numba's compiled kernels live with the venv (the bootstrap fills $VENV/numba_cache once,
# mdss_ros/warmup.py), so `mdss` and `mdss_node` started by hand reuse them instead of
# compiling for ~30 s on their first scene. Inside a venv only; the user's setting wins.
if sys.prefix != sys.base_prefix:
    os.environ.setdefault("NUMBA_CACHE_DIR", os.path.join(sys.prefix, "numba_cache"))

from .version import __version__  # noqa: E402

from .scene import load_scene  # noqa: E402
from .budget import Simulator  # noqa: E402  (resolves model.budget; the automatic model has one)

__all__ = ["load_scene", "Simulator", "__version__"]
