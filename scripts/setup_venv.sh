#!/usr/bin/env bash
# Create or refresh .venv with everything bcid_ros needs (ROS 2 Jazzy from PyPI wheels).
# Re-installs only when a requirements or packaging file changed since the last run.
set -euo pipefail
cd "$(dirname "$0")/.."
VENV=${VENV:-.venv}
PYTHON=${PYTHON:-$(command -v python3.11 || command -v python3)}
if [ ! -x "$VENV/bin/python" ]; then
  if ! "$PYTHON" -m venv "$VENV"; then
    echo "error: '$PYTHON -m venv' failed; on Debian run: apt-get install python3-venv" >&2
    exit 1
  fi
fi
stamp="$VENV/.bcid_installed"
inputs=(requirements.txt requirements-dev.txt setup.py setup.cfg package.xml)
if [ ! -f "$stamp" ] || [ -n "$(find "${inputs[@]}" -newer "$stamp" 2>/dev/null)" ]; then
  "$VENV/bin/python" -m pip install --quiet --upgrade pip setuptools wheel
  "$VENV/bin/python" -m pip install --quiet -r requirements-dev.txt
  "$VENV/bin/python" -m pip install --quiet --no-deps --no-build-isolation -e .
  touch "$stamp"
fi
