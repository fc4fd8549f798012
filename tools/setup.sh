#!/usr/bin/env bash
# Installs everything aruco_ring_localization needs on Debian 12, and builds the workspace.
#
#   1. Debian's ROS 1 packages (apt), only those not yet installed;
#   2. a venv at .venv/ from /usr/bin/python3 --system-site-packages (Debian's ROS Python
#      modules belong to that interpreter), with the exact pins of requirements.txt,
#      re-installed only when requirements.txt changes;
#   3. a catkin workspace at .ws/ that links this repository's files (and our fiducial_msgs when
#      the real one is not installed), built with the venv's Python, rebuilt only when a file that
#      catkin reads changed;
#   4. .ws/env.sh, which puts all of it into a shell: `source .ws/env.sh` (it leaves ROS_HOME
#      alone: maps and logs go where ROS puts them, ~/.ros unless ROS_HOME is set).
#
# Idempotent, needs no stdin; runs as root, or through sudo for apt.
# ARUCO_RING_FORCE_BUILD=1 forces the catkin build.
set -euo pipefail

REPO="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
VENV="$REPO/.venv"
WS="$REPO/.ws"
SYSTEM_PYTHON=/usr/bin/python3

# Keep in sync with docs/install.md. The ROS 1 packages of Debian 12 (ROS_DISTRO=Debian).
APT_PACKAGES=(
  ros-core catkin librostest-dev python3-rostest python3-rospy python3-tf2-ros
  ros-message-generation ros-message-runtime ros-std-msgs ros-geometry-msgs ros-sensor-msgs
  ros-visualization-msgs ros-nav-msgs ros-std-srvs python3-std-srvs python3-std-msgs
  python3-geometry-msgs python3-sensor-msgs python3-visualization-msgs python3-nav-msgs
  python3-venv cmake g++ make python3-rosbag python3-diagnostic-msgs ros-diagnostic-msgs
  python3-tf2-msgs python3-roslaunch python3-rosnode python3-rostopic python3-rosservice
  python3-rosparam python3-rosgraph python3-rosmsg python3-message-filters tf2-tools
  # a ROS user's habits: rosrun/roscd (rosbash); rosrun tf tf_echo / view_frames (tf-tools,
  # python3-tf; libtf-dev holds the tf package.xml without which rospack cannot find tf);
  # the nodes' diagnostic_updater
  rosbash tf-tools python3-tf libtf-dev python3-diagnostic-updater
  # diagnostic_aggregator with config/diagnostics_aggregator.yaml (-dev holds its package.xml and
  # analyzer plugins, without which rosrun and pluginlib cannot find it; test/integration/diagnostics_aggregator.test)
  libdiagnostic-aggregator-tools libdiagnostic-aggregator-dev
  # rviz, headless rendering and screenshots (make demo GUI=1, test/integration/test_rviz_configs.py)
  rviz python3-rviz xvfb xauth libgl1-mesa-dri imagemagick
)

log() { echo "[setup] $*"; }
die() { echo "[setup] ERROR: $*" >&2; exit 1; }

now() { date +%s.%N; }
STEP_T0=0
step_begin() { STEP_T0="$(now)"; }
step_end() { # step_end NAME WHAT
  local t1
  t1="$(now)"
  awk -v a="$STEP_T0" -v b="$t1" -v n="$1" -v w="$2" 'BEGIN { printf "[setup] %-7s %6.1f s  %s\n", n, b - a, w }'
}
TOTAL_T0="$(now)"

# Prints a file's sha256 (or "none").
hash_of() { if [ -e "$1" ]; then sha256sum "$1" | cut -d' ' -f1; else echo none; fi; }

# --- 1. apt -----------------------------------------------------------------------------
install_apt() {
  step_begin
  local missing=() pkg installed
  # One dpkg-query for all packages; unknown ones are simply absent from its output.
  installed=" $(dpkg-query -W -f='${db:Status-Status}:${Package} ' "${APT_PACKAGES[@]}" 2>/dev/null || true) "
  for pkg in "${APT_PACKAGES[@]}"; do
    case "$installed" in *" installed:$pkg "*) ;; *) missing+=("$pkg") ;; esac
  done
  if [ "${#missing[@]}" -eq 0 ]; then
    step_end apt "all ${#APT_PACKAGES[@]} Debian packages present"
    return
  fi
  local sudo=()
  if [ "$(id -u)" -ne 0 ]; then
    command -v sudo >/dev/null || die "not root and no sudo: install as root: apt-get install ${missing[*]}"
    sudo=(sudo)
  fi
  log "apt: installing ${#missing[@]} package(s): ${missing[*]}"
  export DEBIAN_FRONTEND=noninteractive
  "${sudo[@]}" apt-get -o DPkg::Lock::Timeout=600 update -qq </dev/null
  "${sudo[@]}" apt-get -o DPkg::Lock::Timeout=600 install -y -qq --no-install-recommends \
    "${missing[@]}" </dev/null >"${TMPDIR:-/tmp}/aruco_ring_apt.log" 2>&1 \
    || { tail -n 30 "${TMPDIR:-/tmp}/aruco_ring_apt.log" >&2; die "apt-get install failed"; }
  step_end apt "installed ${#missing[@]} package(s)"
}

# --- 2. venv ----------------------------------------------------------------------------
install_venv() {
  step_begin
  local stamp="$VENV/.requirements.sha256" want
  want="$(hash_of "$REPO/requirements.txt")"
  if [ -x "$VENV/bin/python3" ] && ! "$VENV/bin/python3" -c 'import sys' 2>/dev/null; then
    log "venv: $VENV is broken, recreating it"
    rm -rf "$VENV"
  fi
  if [ ! -x "$VENV/bin/python3" ]; then
    "$SYSTEM_PYTHON" -m venv --system-site-packages "$VENV"
    rm -f "$stamp"
  fi
  if [ "$(cat "$stamp" 2>/dev/null || true)" = "$want" ]; then
    step_end venv "requirements.txt unchanged"
    return
  fi
  log "venv: pip install -r requirements.txt"
  if ! "$VENV/bin/python3" -m pip install --disable-pip-version-check \
    -r "$REPO/requirements.txt" </dev/null >"$VENV/pip.log" 2>&1; then
    tail -n 30 "$VENV/pip.log" >&2
    die "pip install -r requirements.txt failed (full log: $VENV/pip.log)"
  fi
  echo "$want" >"$stamp"
  step_end venv "installed requirements.txt"
}

# --- 3. catkin workspace ----------------------------------------------------------------
# True when a real fiducial_msgs (not ours) is installed in a ROS prefix.
real_fiducial_msgs_installed() {
  local prefix prefixes
  prefixes="${CMAKE_PREFIX_PATH:-}"
  for prefix in /usr /opt/ros/* ${prefixes//:/ }; do
    case "$prefix" in "$WS"*) continue ;; esac
    [ -f "$prefix/share/fiducial_msgs/package.xml" ] && return 0
  done
  return 1
}

# Everything catkin reads to configure: when this digest is unchanged, the build is up to date
# (Python modules are used in place from src/, scripts from scripts/). The build re-runs cmake
# (--force-cmake) because CMakeLists.txt GLOBs scripts/ and test/integration/*.test.
workspace_digest() {
  {
    echo "python=$VENV/bin/python3"
    cd "$REPO"
    ls -1 scripts test/integration/*.test 2>/dev/null || true
    sha256sum package.xml CMakeLists.txt setup.py
    find fiducial_msgs -type f | LC_ALL=C sort | xargs sha256sum
    echo "fiducial_msgs -> $(readlink "$WS/src/fiducial_msgs" || true)"
    ls -1 "$WS/src/aruco_ring_localization" 2>/dev/null || true
  } | sha256sum | cut -d' ' -f1
}

# .ws/src/aruco_ring_localization: a directory of links to the repository's entries, not one link
# to the repository. Through a link to the repository, `rosrun aruco_ring_localization X` (which
# searches the package's directory with find -L) reached .ws/ itself and found every executable
# several times ("non-unique executable"). An entry added to the repository is linked by the next
# `make setup`.
link_package() {
  local pkg="$WS/src/aruco_ring_localization" entry name
  if [ -L "$pkg" ]; then rm -f "$pkg"; fi
  mkdir -p "$pkg"
  for entry in "$pkg"/*; do
    if [ -L "$entry" ] && [ ! -e "$entry" ]; then rm -f "$entry"; fi
  done
  for entry in "$REPO"/*; do
    name="$(basename "$entry")"
    case "$name" in results|fiducial_msgs) continue ;; esac
    ln -sfn "$entry" "$pkg/$name"
  done
}

build_workspace() {
  step_begin
  mkdir -p "$WS/src"
  link_package
  if real_fiducial_msgs_installed; then
    rm -f "$WS/src/fiducial_msgs"
    log "catkin: using the installed fiducial_msgs"
  else
    ln -sfn "$REPO/fiducial_msgs" "$WS/src/fiducial_msgs"
  fi
  local stamp="$WS/.build.sha256" want
  want="$(workspace_digest)"
  if [ "${ARUCO_RING_FORCE_BUILD:-0}" != 1 ] && [ -f "$WS/devel/setup.bash" ] \
    && [ "$(cat "$stamp" 2>/dev/null || true)" = "$want" ]; then
    step_end catkin "workspace up to date"
    return
  fi
  log "catkin: catkin_make in $WS (log: $WS/catkin_make.log)"
  rm -f "$stamp"
  if ! (cd "$WS" && env -u PYTHONPATH catkin_make --force-cmake -DPYTHON_EXECUTABLE="$VENV/bin/python3" \
    -DCATKIN_ENABLE_TESTING=ON -DCMAKE_BUILD_TYPE=Release) >"$WS/catkin_make.log" 2>&1 </dev/null; then
    tail -n 40 "$WS/catkin_make.log" >&2
    die "catkin_make failed (full log: $WS/catkin_make.log)"
  fi
  echo "$want" >"$stamp"
  step_end catkin "built"
}

# --- 4. env.sh --------------------------------------------------------------------------
write_env() {
  local tmp="$WS/env.sh.tmp"
  cat >"$tmp" <<EOF
# Generated by tools/setup.sh. Usage: source $WS/env.sh
# Puts the venv, the built catkin workspace and the aruco_ring tool into this shell.
ARUCO_RING_REPO="$REPO"
export ARUCO_RING_REPO
# catkin's and venv's scripts read unset variables: allow that while sourcing them, even in
# a shell running with 'set -u', and restore the caller's setting afterwards.
case \$- in *u*) _aruco_ring_nounset=1; set +u ;; *) _aruco_ring_nounset=0 ;; esac
# shellcheck disable=SC1091
source "$WS/devel/setup.bash"
# shellcheck disable=SC1091
VIRTUAL_ENV_DISABLE_PROMPT=\${VIRTUAL_ENV_DISABLE_PROMPT:-1} source "$VENV/bin/activate"
if [ "\$_aruco_ring_nounset" = 1 ]; then set -u; fi
unset _aruco_ring_nounset
if [ -z "\${ROS_HOSTNAME:-}" ] && [ -z "\${ROS_IP:-}" ]; then export ROS_HOSTNAME=localhost; fi
export ROS_MASTER_URI="\${ROS_MASTER_URI:-http://localhost:11311}"
case ":\$PATH:" in *":$REPO/scripts:"*) ;; *) export PATH="$REPO/scripts:\$PATH" ;; esac
EOF
  mv "$tmp" "$WS/env.sh"
}

main() {
  [ -x "$SYSTEM_PYTHON" ] || [ "$(id -u)" -eq 0 ] || command -v sudo >/dev/null \
    || die "$SYSTEM_PYTHON not found and cannot install packages"
  install_apt
  install_venv
  build_workspace
  write_env
  local t1
  t1="$(now)"
  awk -v a="$TOTAL_T0" -v b="$t1" -v e="$WS/env.sh" \
    'BEGIN { printf "[setup] %-7s %6.1f s  ready: source %s\n", "total", b - a, e }'
}

main "$@"
