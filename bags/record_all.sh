#!/usr/bin/env bash
# Re-record the committed scenario bags: run simulator_node through ROS and record its
# topics with `bcid record` (see bags/README.md). Usage, from the repository root:
#   bags/record_all.sh                 # all five bags
#   bags/record_all.sh ding_miso ...   # only these
# Existing bag directories are replaced. Needs .venv (scripts/setup_venv.sh).
set -euo pipefail
cd "$(dirname "$0")/.."
BIN=${BIN:-.venv/bin}
SEED=1
# A graph of our own, on this machine only, so that nothing else ends up in the bags.
export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
export ROS_DOMAIN_ID=${ROS_DOMAIN_ID:-$(( ($$ % 100) + 101 ))}

samples_of() {
  case "$1" in
    ikeda_closed_loop) echo 4096 ;;
    *) echo 10000 ;;
  esac
}

record_one() {
  local scenario=$1 samples
  samples=$(samples_of "$scenario")
  rm -rf "bags/$scenario"
  echo "== $scenario: $samples samples, seed $SEED (rate and frame size: config/$scenario.yaml)" >&2
  "$BIN/bcid" record "bags/$scenario" \
    --topics /samples /bcid_simulator/true_parameters /bcid_simulator/true_noise_variance &
  local recorder=$!
  # Let the recorder start up; then start_delay gives it time to discover the simulator's
  # topics and subscribe before the first sample is published.
  sleep 5
  "$BIN/simulator_node" --ros-args --params-file "config/$scenario.yaml" \
    -p "num_samples:=$samples" -p "seed:=$SEED" -p start_delay:=3.0
  kill -INT "$recorder"
  wait "$recorder"
  "$BIN/bcid" info "bags/$scenario"
  # A complete bag holds every sample: check it against the offline simulation of the seed.
  "$BIN/python" - "$scenario" "$samples" "$SEED" <<'PY'
import sys
import numpy as np
from bcid_ros.bag.reader import BagReader
from bcid_ros.identifier.layouts import decode_samples
from bcid_ros.simulation import make_scenario
name, count, seed = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
rows = [decode_samples(m) for _, _, m in BagReader(f'bags/{name}').decoded(['/samples'])]
y, u = make_scenario(name).simulate(count, seed)
if sum(r.shape[0] for r in rows) != count or not np.array_equal(np.vstack(rows),
                                                                 np.column_stack([y, u])):
    sys.exit(f'bags/{name}: the samples are not the {count} of seed {seed}; re-record it')
print(f'bags/{name}: all {count} samples of seed {seed}, bit for bit')
PY
}

scenarios=("$@")
if [ ${#scenarios[@]} -eq 0 ]; then
  scenarios=(ding_miso ding_miso_nonstationary ikenoue_colored ikenoue_white_input
             ikeda_closed_loop)
fi
for scenario in "${scenarios[@]}"; do
  record_one "$scenario"
done
