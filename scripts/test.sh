#!/usr/bin/env bash
# The test command: set up (venv + colcon build), then `colcon test` with ROS isolated to this run
# (own ROS_DOMAIN_ID, localhost discovery only), then print the results. Exit code is the verdict.
set -euo pipefail
repo="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
"$repo/scripts/setup.sh"
# shellcheck disable=SC1091
source "$repo/scripts/env.sh"
cd "$repo"
export ROS_DOMAIN_ID="${ROS_DOMAIN_ID:-$(( (RANDOM % 100) + 100 ))}"
export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
export PYTHONUNBUFFERED=1
echo "[test] colcon test (ROS_DOMAIN_ID=$ROS_DOMAIN_ID)"
extra=()
[ "$#" -gt 0 ] && extra=(--pytest-args "$@")
rc=0
colcon --log-base .colcon/log test --base-paths "$repo" \
  --build-base .colcon/build --install-base .colcon/install \
  --test-result-base .colcon/test_results \
  --event-handlers console_direct+ \
  "${extra[@]}" || rc=$?
colcon test-result --test-result-base .colcon/test_results --verbose || rc=$?
exit "$rc"
