#!/usr/bin/env bash
# The README's demo command. Bootstraps the venv, then runs the default scene.
# Until the ROS node lands (issue 5) this runs the scene headless through `mdss run`,
# playing its timeline of inputs, and prints what it did.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
py="$(bash "$root/launch_scripts/bootstrap.sh")"
export ROS_AUTOMATIC_DISCOVERY_RANGE="${ROS_AUTOMATIC_DISCOVERY_RANGE:-LOCALHOST}"
export NUMBA_CACHE_DIR="${NUMBA_CACHE_DIR:-$root/.venv/numba_cache}"
scene="${1:-cantilever}"
out="${MDSS_OUT:-$root/out/demo}"
mkdir -p "$out"
cd "$root"
"$py" -m mdss_ros.cli run "$scene" --json "$out/run_summary.json"
echo "demo: summary in $out/run_summary.json"
