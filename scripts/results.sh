#!/usr/bin/env bash
# Regenerate docs/results.md and its figures (docs/results/): every method, the shipped (trained)
# head against an untrained one, sequence rows and relocalization, on the Nordland test split (the
# last 30% of the route, never trained on) and on rtabmap_loop. Needs ../shared/data (or LLN_DATA).
set -euo pipefail
cd "$(dirname "$0")/.."
DATA=${LLN_DATA:-../shared/data}
CACHE=${LLN_CACHE:-cache/features}
if [ ! -d "$DATA/nordland_trimmed" ] || [ ! -d "$DATA/rtabmap_loop" ]; then
  echo "results: $DATA/nordland_trimmed and $DATA/rtabmap_loop are needed (set LLN_DATA)" >&2
  exit 1
fi
bash scripts/setup.sh
rm -rf docs/results
.venv/bin/lln-eval \
  --dataset "aligned:$DATA/nordland_trimmed/summer,$DATA/nordland_trimmed/winter,1" --range 0.7:1 \
  --dataset "loop:$DATA/rtabmap_loop,$DATA/rtabmap_loop/samples_GT.bmp" \
  --methods holistic,lln,act,rand,all,sad,seqslam --sequence 10 \
  --heads trained=shipped,untrained= --reloc \
  --cache "$CACHE" --out docs/results "$@"
.venv/bin/python scripts/results_md.py docs/results docs/results.md
echo "results: wrote docs/results.md"
