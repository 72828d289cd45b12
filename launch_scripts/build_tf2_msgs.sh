#!/usr/bin/env bash
# Builds tf2_msgs (just tf2_msgs/msg/TFMessage, the type of /tf and /tf_static) from the
# rosidl generator wheels on PyPI, into $venv/tf2_msgs_ws/install, because the pip ROS
# wheels ship no tf2_msgs.  Idempotent: a second run with nothing changed costs a second.
#
#   bash launch_scripts/build_tf2_msgs.sh          # build (if needed), then say what to set
#   eval "$(bash launch_scripts/build_tf2_msgs.sh --env)"   # build (if needed), export it
#
# Needs: the project's venv (launch_scripts/bootstrap.sh; MDSS_VENV picks another one),
# cmake >= 3.19, a C/C++ compiler and make (Debian: apt-get install cmake g++ make;
# installed here when missing and we are root with apt-get), and requirements-tf.txt,
# which this script pip-installs into the venv.  Uses at most 2 cores.
#
# The build is registered into the venv, so every python of the venv finds it with no
# variable to set: its typesupport libraries are linked into $venv/lib (the rclpy wheels'
# bootstrapper puts that folder on LD_LIBRARY_PATH when python starts) and a .pth file
# puts its python package on sys.path. (--env prints the equivalent variables, for a
# process that runs another python.)
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
venv="${MDSS_VENV:-$root/.venv}"
ws="$venv/tf2_msgs_ws"
prefix="$ws/install/tf2_msgs"
mode=build
case "${1:-}" in
  --env) mode=env ;;
  ""|--build) ;;
  -h|--help) sed -n '2,18p' "$0"; exit 0 ;;
  *) echo "usage: $0 [--env]" >&2; exit 2 ;;
esac

die() { echo "build_tf2_msgs: FAILED: $*" >&2; exit 1; }
say() { echo "build_tf2_msgs: $*" >&2; }

py="$venv/bin/python"
[ -x "$py" ] || die "no venv at $venv: run launch_scripts/bootstrap.sh first (or set MDSS_VENV)"
pyver="$("$py" -c 'import sys; print(f"{sys.version_info[0]}.{sys.version_info[1]}")')"
site="$prefix/lib/python$pyver/site-packages"

# -------------------------------------------------------------------- the package source
# Written here (not kept as files) so the stamp below covers it; it is the upstream
# tf2_msgs message, without tf2_msgs' services and actions, which the project does not use.
write_source() {
  local src="$ws/src/tf2_msgs"
  rm -rf "$ws/src"
  mkdir -p "$src/msg"
  echo 'geometry_msgs/TransformStamped[] transforms' > "$src/msg/TFMessage.msg"
  cat > "$src/package.xml" <<'EOF'
<?xml version="1.0"?>
<package format="3">
  <name>tf2_msgs</name>
  <version>0.36.0</version>
  <description>tf2_msgs/msg/TFMessage only, built by mdss_ros from the pip rosidl generators</description>
  <maintainer email="mdss_ros@example.com">mdss_ros</maintainer>
  <license>BSD-3-Clause</license>
  <buildtool_depend>ament_cmake</buildtool_depend>
  <buildtool_depend>rosidl_default_generators</buildtool_depend>
  <depend>geometry_msgs</depend>
  <depend>std_msgs</depend>
  <exec_depend>rosidl_default_runtime</exec_depend>
  <member_of_group>rosidl_interface_packages</member_of_group>
  <export>
    <build_type>ament_cmake</build_type>
  </export>
</package>
EOF
  cat > "$src/CMakeLists.txt" <<'EOF'
cmake_minimum_required(VERSION 3.19)
project(tf2_msgs)

find_package(ament_cmake REQUIRED)
find_package(rosidl_default_generators REQUIRED)
find_package(geometry_msgs REQUIRED)
find_package(std_msgs REQUIRED)

rosidl_generate_interfaces(${PROJECT_NAME}
  "msg/TFMessage.msg"
  DEPENDENCIES geometry_msgs std_msgs
)

# The pip wheels of the message packages (geometry_msgs, std_msgs, builtin_interfaces, ...)
# export their *__rosidl_generator_py targets with include directories of the machine that
# built them (/opt/python/cp311-cp311/...: Python.h and numpy's headers).  They do not
# exist here and CMake refuses to generate; drop the missing ones (this package's own
# generator_py target gets this machine's Python and numpy includes from rosidl_generator_py).
get_property(_imported DIRECTORY PROPERTY IMPORTED_TARGETS)
foreach(_t IN LISTS _imported)
  get_target_property(_dirs ${_t} INTERFACE_INCLUDE_DIRECTORIES)
  if(_dirs)
    set(_kept "")
    foreach(_d IN LISTS _dirs)
      if(_d MATCHES "^/" AND NOT EXISTS "${_d}")
        message(STATUS "tf2_msgs: ignoring missing include dir ${_d} of ${_t}")
      else()
        list(APPEND _kept "${_d}")
      endif()
    endforeach()
    set_target_properties(${_t} PROPERTIES INTERFACE_INCLUDE_DIRECTORIES "${_kept}")
  endif()
endforeach()

ament_export_dependencies(rosidl_default_runtime)
ament_package()
EOF
}

print_env() {
  echo "export PYTHONPATH=\"$site\${PYTHONPATH:+:\$PYTHONPATH}\""
  echo "export LD_LIBRARY_PATH=\"$prefix/lib\${LD_LIBRARY_PATH:+:\$LD_LIBRARY_PATH}\""
  echo "export AMENT_PREFIX_PATH=\"$prefix\${AMENT_PREFIX_PATH:+:\$AMENT_PREFIX_PATH}\""
}

# A check in a fresh process: the type imports, is registered with the fastrtps
# typesupport (a publisher can be created) and carries the right name.
check_built() {
  env PYTHONPATH="$site${PYTHONPATH:+:$PYTHONPATH}" LD_LIBRARY_PATH="$prefix/lib${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}" \
      ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST RMW_IMPLEMENTATION=rmw_fastrtps_cpp \
      "$py" - <<'EOF'
import rclpy
from rclpy.node import Node
from tf2_msgs.msg import TFMessage
from geometry_msgs.msg import TransformStamped
rclpy.init()
try:
    node = Node("build_tf2_msgs_check", enable_rosout=False)
    pub = node.create_publisher(TFMessage, "/build_tf2_msgs_check", 1)
    pub.publish(TFMessage(transforms=[TransformStamped(child_frame_id="check")]))
    node.destroy_node()
finally:
    rclpy.shutdown()
EOF
}

# Link the libraries where the venv's rclpy looks, and the python package onto sys.path.
register() {
  local so
  for so in "$prefix"/lib/*.so; do
    ln -sf "$so" "$venv/lib/$(basename "$so")"
  done
  echo "$site" > "$venv/lib/python$pyver/site-packages/mdss_tf2_msgs.pth"
}

stamp_of() {
  # the ROS wheels the build compiles against are pinned in requirements.lock.txt
  { cat "$root/requirements-tf.txt" "$root/requirements.lock.txt" "$root/launch_scripts/build_tf2_msgs.sh"; echo "$pyver"; } | sha256sum | cut -c1-16
}
want="$(stamp_of)"

if [ -f "$prefix/.mdss_stamp" ] && [ "$(cat "$prefix/.mdss_stamp")" = "$want" ] && [ -d "$site/tf2_msgs" ]; then
  say "up to date: $prefix"
else
  t0=$SECONDS
  # ---- tools: cmake, a C and C++ compiler, make
  missing=()
  command -v cmake >/dev/null 2>&1 || missing+=(cmake)
  command -v cc >/dev/null 2>&1 || command -v gcc >/dev/null 2>&1 || missing+=(gcc)
  command -v c++ >/dev/null 2>&1 || command -v g++ >/dev/null 2>&1 || missing+=(g++)
  command -v make >/dev/null 2>&1 || missing+=(make)
  if [ ${#missing[@]} -gt 0 ]; then
    if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then
      say "installing ${missing[*]} with apt-get"
      { apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "${missing[@]}"; } >&2 \
        || die "apt-get install ${missing[*]} failed"
    else
      die "missing ${missing[*]}: install them (Debian: apt-get install cmake g++ make)"
    fi
  fi
  cmake_ver="$(cmake --version | sed -n 's/^cmake version \([0-9.]*\).*/\1/p')"
  printf '%s\n3.19\n' "$cmake_ver" | sort -V -C -r 2>/dev/null || die "cmake $cmake_ver is too old (need >= 3.19)"

  # ---- the generators (ament_cmake, rosidl_default_generators and what they load)
  mkdir -p "$ws"
  log="$ws/build.log"
  : > "$log"
  say "[1/3] installing requirements-tf.txt into $venv (log: $log)"
  "$py" -m pip install -q -r "$root/requirements-tf.txt" -c "$root/requirements.lock.txt" >>"$log" 2>&1 \
    || { tail -30 "$log" >&2; die "pip install -r requirements-tf.txt failed (see above)"; }

  # ---- colcon build, with the venv as the underlay (the wheels install ROS into it)
  say "[2/3] colcon build tf2_msgs (about 15-30 s on 2 cores)"
  write_source
  rm -rf "$ws/build" "$ws/install"
  ( cd "$ws" && env PATH="$venv/bin:$PATH" AMENT_PREFIX_PATH="$venv" CMAKE_PREFIX_PATH="$venv" \
        LD_LIBRARY_PATH="$venv/lib${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}" MAKEFLAGS=-j2 COLCON_HOME="$ws/.colcon" \
        "$py" -m colcon --log-base "$ws/log" build --base-paths "$ws/src" --build-base "$ws/build" \
          --install-base "$ws/install" --parallel-workers 1 --event-handlers console_direct+ \
          --cmake-args -DPython3_EXECUTABLE="$py" -DBUILD_TESTING=OFF -DCMAKE_BUILD_TYPE=Release ) >>"$log" 2>&1 \
    || { grep -n -B2 -A12 "CMake Error\|error:" "$log" | head -60 >&2; die "colcon build of tf2_msgs failed; full log: $log"; }

  say "[3/3] registering it in the venv and checking: import, fastrtps typesupport, publish"
  register
  check_built >>"$log" 2>&1 || { tail -30 "$log" >&2; die "tf2_msgs built but does not load; full log: $log"; }
  echo "$want" > "$prefix/.mdss_stamp"
  say "built $prefix in $((SECONDS - t0)) s"
fi

register
if [ "$mode" = env ]; then
  print_env
else
  say "tf2_msgs/msg/TFMessage is registered in $venv: the node publishes /tf"
fi
