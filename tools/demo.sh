#!/usr/bin/env bash
# Stand-in demo until the simulated-lab demo exists: runs the demo module when it is there,
# otherwise validates and summarises the shipped ring configuration.
set -euo pipefail
REPO="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$REPO"
if [ -z "${ARUCO_RING_REPO:-}" ]; then
  # shellcheck disable=SC1091
  source .ws/env.sh
fi
if python -c 'import importlib.util, sys; sys.exit(importlib.util.find_spec("aruco_ring_localization.demo") is None)' 2>/dev/null; then
  exec python -m aruco_ring_localization.demo "$@"
fi
exec aruco_ring check-config --ring config/ring.yaml
