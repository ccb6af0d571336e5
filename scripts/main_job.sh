#!/usr/bin/env bash
# The main job: build a map from one traverse and query it with another through the ROS 2 nodes
# (two extractors + the matcher, real processes over DDS), print the result table next to the offline
# evaluator's, and write the plots. Idempotent: setup is skipped when nothing changed, and lln-demo
# replaces its own previous outputs in out/main_job/.
#
#   bash scripts/main_job.sh                     # ../shared/data (or $LLN_DATA) present: the Nordland test split
#   bash scripts/main_job.sh --download          # otherwise: Gardens Point Walking, fetched once
#   bash scripts/main_job.sh --dataset aligned:MAP_DIR,QUERY_DIR,2
#
# Extra arguments go to lln-demo (see `python -m lln_ros.cli.demo --help`); OUT overrides the folder.
set -euo pipefail
cd "$(dirname "$0")/.."
VENV=${LLN_VENV:-.venv}
OUT=${OUT:-out/main_job}
# lln-demo's default dataset lives here (the repo-relative default is the scripts', never the package's)
LLN_DATA=${LLN_DATA:-../shared/data}
[ -d "$LLN_DATA" ] && LLN_DATA=$(cd "$LLN_DATA" && pwd)
export LLN_DATA

bash scripts/setup.sh
mkdir -p "$(dirname "$OUT")"
exec "$VENV/bin/python" -m lln_ros.cli.demo --out "$OUT" "$@"
