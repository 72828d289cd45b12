#!/usr/bin/env bash
# The README's demo command. Bootstraps the venv, then runs the ROS 2 node on a scene
# (default: cantilever) with a separate publisher process playing the scene's timeline
# of forces; the node records MCAP (a rosbag2 folder) and a rerun .rrd.
# The first run builds the scene's precompute (bases, cubature) and caches it.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
py="$(bash "$root/launch_scripts/bootstrap.sh")"
export ROS_AUTOMATIC_DISCOVERY_RANGE="${ROS_AUTOMATIC_DISCOVERY_RANGE:-LOCALHOST}"
export NUMBA_CACHE_DIR="${NUMBA_CACHE_DIR:-$root/.venv/numba_cache}"
scene="${1:-cantilever}"
out="${MDSS_OUT:-$root/out/demo}"
stamp="$(date +%Y%m%d_%H%M%S)"
bag="$out/bag_$stamp"
rrd="$out/run_$stamp.rrd"
mkdir -p "$out"
cd "$root"
# The node records every input it applied and every output it published (mcap_path, a
# rosbag2 folder) and a rerun log (rerun_mode file); the timeline comes from another process.
# The script always ends by saying what was recorded, or why there is nothing to open.
t0=$SECONDS
rc=0
"$py" launch_scripts/run_scene.py "$scene" -p "mcap_path:=$bag" -p rerun_mode:=file -p "rerun_path:=$rrd" || rc=$?
echo
mcap="$(ls "$bag"/*.mcap 2>/dev/null | head -n 1 || true)"
if [ -z "$mcap" ] && [ ! -s "$rrd" ]; then
  echo "demo: FAILED after $((SECONDS - t0)) s (exit code $rc): nothing was recorded." >&2
  echo "  The node's messages above say why (look for ERROR or Traceback)." >&2
  echo "  A scene name must be one of: $(cd msg_scenes && ls *.yaml | sed 's/\.yaml$//' | tr '\n' ' ')" >&2
  exit "$(( rc == 0 ? 1 : rc ))"
fi
if [ "$rc" -ne 0 ]; then
  echo "demo: a process exited with code $rc (see above); what was recorded up to then:"
else
  echo "demo: done in $((SECONDS - t0)) s; the node recorded"
fi
[ -n "$mcap" ] && echo "  $bag   rosbag2 folder (MCAP): every input applied and every output published"
[ -s "$rrd" ] && echo "  $rrd   rerun log: surface mesh coloured by domain, frames, colliders, contacts, plots"
echo "open them with"
if [ -s "$rrd" ]; then
  if [ -n "${DISPLAY:-}${WAYLAND_DISPLAY:-}" ]; then
    echo "  rerun viewer:  $root/.venv/bin/rerun $rrd"
  else
    # The native viewer needs a display; its web viewer runs headless.
    echo "  rerun viewer:  $root/.venv/bin/rerun --serve-web $rrd   (no display here: open the address it"
    echo "                 prints, http://127.0.0.1:9090 by default, in a browser; with a display: rerun $rrd)"
  fi
fi
if [ -n "$mcap" ]; then
  echo "  Foxglove:      File > Open local file > $mcap"
  if command -v ros2 >/dev/null 2>&1; then
    echo "  ROS 2 Jazzy:   ros2 bag info $bag   (or ros2 bag play)"
  else
    echo "  ROS 2 Jazzy:   ros2 bag info $bag   (or ros2 bag play; needs a ROS 2 Jazzy install, ros-base or"
    echo "                 desktop: ros2cli and rosbag2 have no pip wheels, so the venv has no ros2 command)"
  fi
  echo "  replay:        $root/.venv/bin/mdss replay $bag --check   (headless, compares every output bit for bit)"
fi
exit "$rc"
