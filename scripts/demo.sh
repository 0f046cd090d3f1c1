#!/usr/bin/env bash
# The README's main-job command: set up .venv, then run the live demo
# (simulator node + identifier node). Extra arguments go to `bcid demo`.
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/setup_venv.sh
export ROS_AUTOMATIC_DISCOVERY_RANGE=${ROS_AUTOMATIC_DISCOVERY_RANGE:-LOCALHOST}
export ROS_DOMAIN_ID=${ROS_DOMAIN_ID:-$(( ($$ % 100) + 1 ))}
exec .venv/bin/bcid demo "$@"
