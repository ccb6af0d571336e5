#!/usr/bin/env bash
# Create .venv (Python 3.11) with everything lln_ros needs, then install the package into it.
# Idempotent: a stamp keyed on requirements.txt and setup.py skips the pip work when nothing changed.
set -euo pipefail
cd "$(dirname "$0")/.."
VENV=${LLN_VENV:-.venv}
PY=${PYTHON:-python3.11}

if ! command -v "$PY" >/dev/null 2>&1; then
  echo "setup: $PY not found; lln_ros needs Python 3.11 (the ROS 2 Jazzy wheels are built for it)" >&2
  exit 1
fi
if [ ! -x "$VENV/bin/python" ]; then
  echo "setup: creating $VENV with $PY"
  "$PY" -m venv "$VENV"
fi
touch "$VENV/COLCON_IGNORE"  # colcon must not crawl the venv (the ROS wheels ship package.xml files)
stamp="$VENV/.lln_ros_setup"
want=$(cat requirements.txt setup.py | sha256sum | cut -d' ' -f1)
if [ -f "$stamp" ] && [ "$(cat "$stamp")" = "$want" ]; then
  echo "setup: $VENV is up to date"
  exit 0
fi
# torch==2.13.0 is taken from the local CPU wheel; setuptools<80 because colcon-core rejects newer.
"$VENV/bin/python" -m pip install -q --upgrade pip 'setuptools<80' wheel
"$VENV/bin/python" -m pip install -q -r requirements.txt
"$VENV/bin/python" -m pip install -q --no-deps --no-build-isolation -e .
echo "$want" > "$stamp"
echo "setup: done"
