#!/usr/bin/env bash
# The README's demo command. Bootstraps the venv, then runs the ROS 2 node on a scene
# (default: cantilever) with a separate publisher process playing the scene's timeline
# of forces, and a recorder process writing the node's outputs to a rosbag2 (MCAP).
# The first run builds the scene's precompute (bases, cubature) and caches it.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
py="$(bash "$root/launch_scripts/bootstrap.sh")"
export ROS_AUTOMATIC_DISCOVERY_RANGE="${ROS_AUTOMATIC_DISCOVERY_RANGE:-LOCALHOST}"
export NUMBA_CACHE_DIR="${NUMBA_CACHE_DIR:-$root/.venv/numba_cache}"
scene="${1:-cantilever}"
out="${MDSS_OUT:-$root/out/demo}"
bag="$out/bag_$(date +%Y%m%d_%H%M%S)"
mkdir -p "$out"
cd "$root"
"$py" launch_scripts/run_scene.py "$scene" --record "$bag"
echo
echo "demo: recorded the node's outputs to $bag (rosbag2, MCAP storage)."
echo "      Open it with Foxglove Studio, 'ros2 bag info $bag' in a ROS 2 install, or Python:"
echo "      $py -c \"from rosbags.rosbag2 import Reader; r = Reader('$bag'); r.open(); print({c.topic: c.msgcount for c in r.connections})\""
