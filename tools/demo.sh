#!/usr/bin/env bash
# make demo: the paper's experiment on the simulated lab with the real ROS nodes
# (src/aruco_ring_localization/ros/demo.py). Outputs under results/demo/.
#   make demo                 # tables, summary.json, TUM trajectories, figures
#   make demo GUI=1           # the same, with rviz when a display exists
#   tools/demo.sh --fusion paper --method paper   # options of python -m aruco_ring_localization.ros.demo
set -euo pipefail
REPO="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$REPO"
if [ -z "${ARUCO_RING_REPO:-}" ]; then
  # shellcheck disable=SC1091
  source .ws/env.sh
fi
args=()
if [ -n "${GUI:-}" ] && [ "${GUI}" != 0 ]; then
  if [ -n "${DISPLAY:-}" ]; then args+=(--gui); else echo "demo: GUI=1 but DISPLAY is not set: running without rviz"; fi
fi
exec python -m aruco_ring_localization.ros.demo "${args[@]}" "$@"
