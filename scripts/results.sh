#!/usr/bin/env bash
# Regenerate docs/results.md and its figures (docs/results/): every method, the shipped (trained)
# head against an untrained one, sequence rows and relocalization, on the Nordland test split (the
# last 30% of the route, never trained on) and on rtabmap_loop, with the paper's holistic top-30
# prefilter; then Nordland again with exhaustive matching; then both with the shipped default first stage
# (landmarks); then essex3in1 and tum_fr1rpy. The paper's protocol runs (holistic top-30, exhaustive)
# score with the paper's S (--no-similarity-fusion); the shipped-default runs with the default fused S
# (docs/method.md). Needs ../shared/data (or LLN_DATA).
set -euo pipefail
cd "$(dirname "$0")/.."
DATA=${LLN_DATA:-../shared/data}
DATA=$(realpath --relative-to=. "$DATA")  # results.md shows its commands: no /home/someone/ in them
CACHE=${LLN_CACHE:-cache/features}
if [ ! -d "$DATA/nordland_trimmed" ] || [ ! -d "$DATA/rtabmap_loop" ] || [ ! -d "$DATA/essex3in1" ] || [ ! -d "$DATA/tum_fr1rpy" ]; then
  echo "results: $DATA/nordland_trimmed, rtabmap_loop, essex3in1 and tum_fr1rpy are needed (set LLN_DATA)" >&2
  exit 1
fi
bash scripts/setup.sh
rm -rf docs/results
.venv/bin/lln-eval \
  --dataset "aligned:$DATA/nordland_trimmed/summer,$DATA/nordland_trimmed/winter,1" --range 0.7:1 \
  --dataset "loop:$DATA/rtabmap_loop,$DATA/rtabmap_loop/samples_GT.bmp" \
  --methods holistic,lln,act,rand,all,sad,seqslam --sequence 10 \
  --heads trained=shipped,untrained= --reloc --prefilter holistic --prefilter-k 30 --sequence-prefilter-k 30 \
  --no-similarity-fusion \
  --cache "$CACHE" --out docs/results "$@"
# the same Nordland queries with every reference scored (no holistic prefilter): what the holistic
# top-30 costs each reranker, and lln+seq against seqslam, which also compares every map frame
.venv/bin/lln-eval \
  --dataset "aligned:$DATA/nordland_trimmed/summer,$DATA/nordland_trimmed/winter,1" --range 0.7:1 \
  --methods holistic,lln,act,rand,all,sad,seqslam --sequence 10 --prefilter-k 0 --no-similarity-fusion \
  --heads trained=shipped,untrained= \
  --cache "$CACHE" --out docs/results/exhaustive "$@"
# the shipped defaults (the landmark first stage, issue #14): what a user of the matcher gets
.venv/bin/lln-eval \
  --dataset "aligned:$DATA/nordland_trimmed/summer,$DATA/nordland_trimmed/winter,1" --range 0.7:1 \
  --dataset "loop:$DATA/rtabmap_loop,$DATA/rtabmap_loop/samples_GT.bmp" \
  --methods holistic,lln,act,rand,all --sequence 10 --heads trained=shipped \
  --cache "$CACHE" --out docs/results/landmarks "$@"
# the shipped defaults on the Nordland test split without the 10 blank (tunnel) queries and the 14
# repeats of the frozen last winter frame (the aligned reader's drop=blank+frozen option)
.venv/bin/lln-eval \
  --dataset "aligned:$DATA/nordland_trimmed/summer,$DATA/nordland_trimmed/winter,1,drop=blank+frozen" --range 0.7:1 \
  --methods holistic,lln --sequence 10 --heads trained=shipped \
  --cache "$CACHE" --out docs/results/filtered "$@"
# every other real set, the paper's protocol: issue 15's LLN / ACT / RAND / ALL side by side
.venv/bin/lln-eval \
  --dataset "vprbench:$DATA/essex3in1" --dataset "poses:$DATA/tum_fr1rpy,15,0.3,2,3" \
  --methods holistic,lln,act,rand,all --heads trained=shipped --prefilter holistic --prefilter-k 30 --no-similarity-fusion \
  --cache "$CACHE" --out docs/results/other "$@"
.venv/bin/python scripts/results_md.py docs/results.md docs/results docs/results/exhaustive docs/results/landmarks \
  docs/results/filtered docs/results/other
echo "results: wrote docs/results.md"
