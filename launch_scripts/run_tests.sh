#!/usr/bin/env bash
# The README's test command: bootstraps the venv, then runs the default (fast) suite.
# Extra arguments go to pytest, e.g. `--slow` for the long studies or `-k cantilever`.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
py="$(bash "$root/launch_scripts/bootstrap.sh")"
# Keep DDS on this machine unless the user chose otherwise; tests add a unique domain id each.
export ROS_AUTOMATIC_DISCOVERY_RANGE="${ROS_AUTOMATIC_DISCOVERY_RANGE:-LOCALHOST}"
export NUMBA_CACHE_DIR="${NUMBA_CACHE_DIR:-$root/.venv/numba_cache}"
cd "$root"
exec "$py" -m pytest "$@"
