#!/usr/bin/env bash
# The README's test command: set up .venv, then run the whole test suite.
# Extra arguments go to pytest, which then runs them as given, in one process (for example:
# scripts/test.sh -k bcrls). --fast first: the inner loop, without the tests that start a
# ROS graph, the Monte Carlo checks, the papers' studies and the slow tests (the folders of
# test/ are the markers).
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/setup_venv.sh
# Keep every ROS graph of this run on this machine and on a domain of its own. The ROS
# graph tests take their domains from slices of 101..232 that this id selects, one per
# worker (test/conftest.py): runs at once on one machine need ids that differ modulo 33 by
# at least the workers' count.
export ROS_AUTOMATIC_DISCOVERY_RANGE=${ROS_AUTOMATIC_DISCOVERY_RANGE:-LOCALHOST}
export ROS_DOMAIN_ID=${ROS_DOMAIN_ID:-$(( ($$ % 100) + 1 ))}
# --fast and the whole suite spread the tests over the cores (pytest-xdist, -n auto; add
# -n 0 for one process, as --pdb needs), the ROS graph tests too: each worker takes its own
# slice of test domains (test/conftest.py), so two graphs started at once never meet.
if [ "${1:-}" = "--fast" ]; then
  shift
  exec .venv/bin/python -m pytest -n auto \
    -m "not ros and not statistical and not papers and not slow" "$@"
fi
if [ $# -eq 0 ]; then
  exec .venv/bin/python -m pytest -n auto
fi
exec .venv/bin/python -m pytest "$@"
