#!/usr/bin/env bash
# Leave-one-dataset-out (LOO) validation of LLN training recipes: docs/generalisation.md.
#
# For every real set H (nordland test split, rtabmap_loop, essex3in1, tum_fr1rpy) and every recipe R,
# train a head on the OTHER sets (validation: the mean over the other sets, see lln-train --val), then
# evaluate it on H beside the head-independent methods (holistic, act, rand, all) and the shipped
# head. H is never trained or tuned on. Then the recipes on every set (Nordland: NRANGE): the
# candidates for the shipped head, held out on the Nordland test split.
#
#   bash scripts/loo.sh                 # everything (train + eval), ~1 h on 2 idle cores with a warm cache
#   TUPLES=200 EPOCHS=2 RECIPES="mix prior" bash scripts/loo.sh   # the first LOO run (docs/generalisation.md)
#   STEP=eval bash scripts/loo.sh       # only re-evaluate existing heads (STEP=train: only train)
#   HELD="essex tum" bash scripts/loo.sh   # only these folds
#   then: .venv/bin/python scripts/loo_md.py out/loo > docs/generalisation-table.md (see the doc)
set -euo pipefail
cd "${LLN_REPO:-$(dirname "$0")/..}"  # LLN_REPO: when running a copy of this script
DATA=${DATA:-../shared/data}
CACHE=${LLN_CACHE:-cache/features}
OUT=${OUT:-out/loo}
EPOCHS=${EPOCHS:-4}
TUPLES=${TUPLES:-0}              # training tuples per epoch; 0 = every query of the training sets
NRANGE=${NRANGE:-0.6:0.66}       # Nordland part trained on (when Nordland is not held out)
NVAL=${NVAL:-0.6:0.66}           # Nordland part validated on (in-sample, as for the other training sets); the test split 0.7:1 is never touched
KS=${KS:-30 0}                   # first stages: holistic top-30 and exhaustive (0)
EXHAUSTIVE=${EXHAUSTIVE:-rtabmap essex}  # sets small enough to score every reference on a loaded 2-core machine
RECIPES=${RECIPES:-prior}
STEP=${STEP:-all}
BIN=.venv/bin
THREADS=${THREADS:-1}

declare -A SPEC=(
  [nordland]="aligned:$DATA/nordland_trimmed/summer,$DATA/nordland_trimmed/winter,1"
  [rtabmap]="loop:$DATA/rtabmap_loop,$DATA/rtabmap_loop/samples_GT.bmp"
  [essex]="vprbench:$DATA/essex3in1"
  [tum]="poses:$DATA/tum_fr1rpy,15,0.3,2,3"   # every 3rd frame (10 Hz): 30 Hz repeats itself
)
SETS="nordland rtabmap essex tum"
HELD=${HELD:-$SETS}             # which folds to run (default: every set held out once)
declare -A FLAGS=(
  [mix]=""                 # the plain LLN head on the mixed sets
  [prior]="--norm-prior 1" # the head as a learned correction of ACT's feature-norm ranking
  [balanced]="--norm-prior 1 --balance-sets"  # the same, every training set an equal share of each epoch
)

train() {  # train NAME RECIPE SET... : a head on the given sets, validated on their mean
  local name=$1 recipe=$2; shift 2
  local args=()
  for s in "$@"; do args+=(--data "${SPEC[$s]}" --val "${SPEC[$s]}"); done
  mkdir -p "$OUT/$name"
  [ -f "$OUT/$name/done" ] && return 0
  $BIN/lln-train "${args[@]}" --range "$NRANGE" --val-range "$NVAL" --out "$OUT/$name" \
    --epochs "$EPOCHS" --tuples-per-epoch "$TUPLES" --cache "$CACHE" --threads "$THREADS" ${FLAGS[$recipe]} \
    2>&1 | tr "\r" "\n" | grep --line-buffered -v '^[^:]*: *[0-9]*%|' > "$OUT/$name/train.log"
  touch "$OUT/$name/done"
}

evaluate() {  # evaluate H K DIR HEADS... : every method on held-out H with first stage K, into OUT/DIR
  local held=$1 k=$2 dir=$3; shift 3
  local range=()
  [ "$held" = nordland ] && range=(--range 0.7:1)
  local heads
  heads=$(IFS=,; echo "$*")
  $BIN/lln-eval --dataset "${SPEC[$held]}" "${range[@]}" --methods "${METHODS:-holistic,lln,act,rand,all}" \
    --heads "$heads" --prefilter holistic --prefilter-k "$k" --cache "$CACHE" --threads "$THREADS" --no-plots --quiet \
    --timing-images 1 --timing-queries 1 --timing-repeats 1 --out "$OUT/$dir"
}

for held in $HELD; do
  others=()
  for s in $SETS; do [ "$s" != "$held" ] && others+=("$s"); done
  heads=(shipped=shipped)
  for r in $RECIPES; do
    [ "$STEP" != eval ] && train "loo-$held-$r" "$r" "${others[@]}"
    heads+=("$r=$OUT/loo-$held-$r/best.pt")
  done
  if [ "$STEP" != train ]; then
    for k in $KS; do
      [ "$k" = 0 ] && [[ " $EXHAUSTIVE " != *" $held "* ]] && continue
      evaluate "$held" "$k" "eval-$held-k$k" "${heads[@]}"
    done
  fi
done

# candidates for the shipped head: each recipe on every set (Nordland: NRANGE only), held out only on
# the Nordland test split: with NRANGE=0:0.6 NVAL=0.6:0.7 and the prior recipe, what `make train` ships
# (docs/generalisation.md, "Decision"). CANDIDATE_SETS="nordland essex tum" keeps rtabmap_loop held out
# too (the second run's candidates)
CANDIDATE_SETS=${CANDIDATE_SETS:-nordland rtabmap essex tum}
if [ "${CANDIDATES:-1}" = 1 ]; then
  heads=()
  for r in $RECIPES; do
    [ "$STEP" != eval ] && train "cand-$r" "$r" $CANDIDATE_SETS
    heads+=("cand-$r=$OUT/cand-$r/best.pt")
  done
  if [ "$STEP" != train ]; then
    for held in $SETS; do
      [[ " $CANDIDATE_SETS " == *" $held "* ]] && continue
      for k in $KS; do
        [ "$k" = 0 ] && [[ " $EXHAUSTIVE " != *" $held "* ]] && continue
        evaluate "$held" "$k" "candidates-$held-k$k" "${heads[@]}"
      done
    done
    METHODS=lln evaluate nordland 30 candidates-nordland-k30 "${heads[@]}"
  fi
fi
