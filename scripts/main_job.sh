#!/usr/bin/env bash
# The main job: set up, then run balance_node against the simulated robot (sim_node) as separate
# processes over ROS 2 and CAN (udp_multicast), driven by a scripted joystick through
# teleop_node, through the paper's experiments. Writes plots and a report into an output folder
# named at the end. Extra arguments go to `main_job` (e.g. --only startup,standing).
set -euo pipefail
repo="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
"$repo/scripts/setup.sh"
# shellcheck disable=SC1091
source "$repo/scripts/env.sh"
export ROS_DOMAIN_ID="${ROS_DOMAIN_ID:-$(( (RANDOM % 100) + 100 ))}"
export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
export PYTHONUNBUFFERED=1
cd "$repo"
exec main_job --output "${OUTPUT:-$repo/output/main_job_$(date +%Y%m%d_%H%M%S)}" "$@"
