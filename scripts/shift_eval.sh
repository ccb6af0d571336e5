#!/usr/bin/env bash
# Issue 28: the shipped head against untrained selection on transformed copies of the shared sets
# (scripts/shift_folds.py), and the inference-time candidates (act_fusion), at the shipped defaults
# (landmark first stage, top-100 reranked, top-n 50) and at other top-n. docs/generalisation.md,
# "Unseen kinds of place". Needs ../shared/data (or LLN_DATA).
#
#   bash scripts/shift_eval.sh                 # folds + every run below, into out/shift-eval/
#   FUSIONS="0.25 0.5" TOPNS="25 100" bash scripts/shift_eval.sh
#   HEADS=shipped=shipped,new=out/train/best.pt FUSIONS=" " TOPNS=" " bash scripts/shift_eval.sh
#   RAND_SEEDS="1 2 3 4 5 6 7 8" FOLDS="lateral side" ...   # RAND at other seeds: out/shift-eval/rand-sN
#   then: python scripts/shift_md.py out/shift-eval   (the tables)
set -euo pipefail
cd "${LLN_REPO:-$(dirname "$0")/..}"
DATA=${LLN_DATA:-../shared/data}
CACHE=${LLN_CACHE:-cache/features}
OUT=${OUT:-out/shift-eval}
PY=${PY:-.venv/bin/python}
BIN=${BIN:-.venv/bin}
FOLDS=${FOLDS:-lateral side photo thumb webcam}
FUSIONS=${FUSIONS:-0.25 0.5 0.75}
TOPNS=${TOPNS:-25 100}
$PY scripts/shift_folds.py --data "$DATA" --out out/shift
specs=()
for f in $FOLDS; do specs+=(--dataset "vprbench:out/shift/$f"); done
heads=${HEADS:-shipped=shipped}  # LABEL=CKPT[,LABEL=CKPT...]: candidate heads beside the shipped one
for a in $FUSIONS; do heads+=",f${a/./}=shipped@act_fusion=$a"; done  # f025, f05, f075
run() {  # run DIR ARGS...: lln-eval on every fold, the shipped defaults but ARGS
  local dir=$1; shift
  [ -f "$OUT/$dir/results.json" ] && return 0
  $BIN/lln-eval "${specs[@]}" --cache "$CACHE" --no-plots --quiet \
    --timing-images 1 --timing-queries 1 --timing-repeats 1 --out "$OUT/$dir" "$@"
}
run topn50 --methods holistic,lln,act,rand,all --heads "$heads"
for n in $TOPNS; do run "topn$n" --methods lln,act,rand --heads "$heads" --top-n "$n"; done
# RAND is one fixed draw of cell locations per grid (the paper's): its spread over other draws
for s in ${RAND_SEEDS:-}; do run "rand-s$s" --methods rand --rand-seed "$s"; done
