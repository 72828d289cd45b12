#!/usr/bin/env bash
# Creates (or refreshes) the project's venv with pinned versions, then prints its python.
# Sourced by demo.sh and run_tests.sh; safe to run by hand.  Re-installs only when the
# requirement files change, so a second run costs a second.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
venv="${MDSS_VENV:-$root/.venv}"

die() { echo "mdss bootstrap: $*" >&2; exit 1; }

python_ok() {  # python >= 3.11 with venv and pip available
  "$1" -c 'import sys, venv, ensurepip; sys.exit(0 if sys.version_info >= (3, 11) else 1)' >/dev/null 2>&1
}

find_python() {
  local c
  if [ -n "${MDSS_PYTHON:-}" ]; then
    python_ok "$MDSS_PYTHON" || die "MDSS_PYTHON=$MDSS_PYTHON is not a Python >= 3.11 with venv/ensurepip"
    echo "$MDSS_PYTHON"; return
  fi
  for c in python3.11 python3.12 python3.13 python3; do
    if command -v "$c" >/dev/null 2>&1 && python_ok "$(command -v "$c")"; then command -v "$c"; return; fi
  done
  if command -v pyenv >/dev/null 2>&1; then
    for v in $(pyenv versions --bare 2>/dev/null | grep -E '^3\.(11|12|13)(\.|$)' | sort -V); do
      c="$(pyenv root)/versions/$v/bin/python3"
      if [ -x "$c" ] && python_ok "$c"; then echo "$c"; return; fi
    done
  fi
  die "no Python >= 3.11 with the venv and ensurepip modules found on PATH or in pyenv.
  Install one (Debian/Ubuntu: apt-get install python3.11 python3.11-venv) or set MDSS_PYTHON=/path/to/python3.11"
}

stamp_of() { cat "$root/requirements.txt" "$root/requirements.lock.txt" "$root/requirements-peers.txt" "$root/requirements-tf.txt" "$root/setup.py" "$root/launch_scripts/bootstrap.sh" | sha256sum | cut -c1-16; }

want="$(stamp_of)"
if [ ! -x "$venv/bin/python" ] || [ "$(cat "$venv/.mdss_stamp" 2>/dev/null)" != "$want" ]; then
  py="$(find_python)"
  if [ ! -x "$venv/bin/python" ]; then
    echo "mdss bootstrap: creating $venv with $py ($("$py" --version 2>&1))" >&2
    "$py" -m venv "$venv" || die "could not create a venv with $py"
  fi
  # pip's own output goes to a log, shown only when a step fails: a successful install
  # prints four progress lines and nothing else (setuptools' editable-install banner and
  # build warnings are noise to a user).
  log="$venv/bootstrap.log"
  : > "$log"
  quiet() { "$@" >>"$log" 2>&1 || { cat "$log" >&2; return 1; }; }
  t0=$SECONDS
  echo "mdss bootstrap: [1/4] installing pinned requirements (first time: a few minutes; log in $log)" >&2
  quiet "$venv/bin/python" -m pip install -q --upgrade pip || die "pip upgrade failed (no access to the Python package index?)"
  quiet "$venv/bin/python" -m pip install -q -r "$root/requirements.txt" -c "$root/requirements.lock.txt" \
    || die "installing requirements.txt failed; see pip's message above"
  quiet "$venv/bin/python" -m pip install -q -r "$root/requirements-peers.txt" -c "$root/requirements.lock.txt" \
    || die "installing requirements-peers.txt (MuJoCo, the peer the reports compare against) failed; see pip's message above"
  echo "mdss bootstrap: [2/4] installing mdss_ros itself (editable)" >&2
  quiet "$venv/bin/python" -m pip install -q --no-deps -e "$root" || die "installing mdss_ros itself failed"
  # numba compiles each kernel on first use; doing it here (cached in the venv) keeps that
  # cost out of the user's first scene, where it looked like a hang (mdss_ros/warmup.py).
  echo "mdss bootstrap: [3/4] compiling the numba kernels once into $venv/numba_cache (2-4 minutes on 2 cores; a line per model)" >&2
  # Its progress lines go to the terminal (stderr: stdout carries the python path back),
  # unbuffered so a log shows them as they come: silent, this step looked like a hang.
  env PYTHONUNBUFFERED=1 NUMBA_CACHE_DIR="${NUMBA_CACHE_DIR:-$venv/numba_cache}" "$venv/bin/python" -m mdss_ros.warmup >&2 \
    || die "compiling the numba kernels failed; see the message above"
  # /tf needs tf2_msgs, which no pip wheel has: build it from the rosidl generator wheels
  # when the machine has a compiler toolchain (launch_scripts/build_tf2_msgs.sh, ~20 s).
  if command -v cmake >/dev/null 2>&1 && command -v make >/dev/null 2>&1 \
      && { command -v c++ >/dev/null 2>&1 || command -v g++ >/dev/null 2>&1; }; then
    echo "mdss bootstrap: [4/4] building tf2_msgs for /tf (about 20 s)" >&2
    quiet env MDSS_VENV="$venv" bash "$root/launch_scripts/build_tf2_msgs.sh" \
      || die "building tf2_msgs failed; see the message above"
  else
    echo "mdss bootstrap: [4/4] skipped: no cmake, make and g++ here, so the node publishes domain frames on" \
         "~/domain_transforms only (apt-get install cmake g++ make, then run again, for /tf)" >&2
  fi
  echo "mdss bootstrap: ready in $((SECONDS - t0)) s" >&2
  echo "$want" > "$venv/.mdss_stamp"
fi
"$venv/bin/python" -c 'import rclpy, numpy, scipy, numba' >/dev/null 2>&1 \
  || die "the venv at $venv is broken (import rclpy/numpy/scipy/numba failed); delete it and run again"
echo "$venv/bin/python"
