#!/usr/bin/env bash
# S on raw against S on centred landmark sets (lln-eval --similarity-center; docs/method.md, "Centring
# the similarity S"), shipped defaults otherwise: the Nordland validation part 0.6:0.7 (never the test
# split), the other shared sets, and issue 28's transformed folds (scripts/shift_folds.py). Needs
# ../shared/data (or LLN_DATA).
#
#   bash scripts/similarity_center.sh        # out/similarity-center/{raw,centred}{,-folds}/, then the table
set -euo pipefail
cd "${LLN_REPO:-$(dirname "$0")/..}"
DATA=${LLN_DATA:-../shared/data}
CACHE=${LLN_CACHE:-cache/features}
OUT=${OUT:-out/similarity-center}
PY=${PY:-.venv/bin/python}
BIN=${BIN:-.venv/bin}
$PY scripts/shift_folds.py --data "$DATA" --out out/shift
shared=(--dataset "aligned:$DATA/nordland_trimmed/summer,$DATA/nordland_trimmed/winter,1" --range 0.6:0.7
  --dataset "loop:$DATA/rtabmap_loop,$DATA/rtabmap_loop/samples_GT.bmp" --dataset "vprbench:$DATA/essex3in1"
  --dataset "poses:$DATA/tum_fr1rpy,15,0.3,2,3")
folds=()
for f in lateral side photo thumb webcam; do folds+=(--dataset "vprbench:out/shift/$f"); done
run() {  # run DIR ARGS...
  local dir=$1; shift
  [ -f "$OUT/$dir/results.json" ] && return 0
  $BIN/lln-eval "$@" --methods lln,act,rand,all --heads shipped=shipped --cache "$CACHE" --no-plots --quiet \
    --timing-images 1 --timing-queries 1 --timing-repeats 1 --out "$OUT/$dir"
}
for s in raw centred; do
  flag=--no-similarity-center; [ $s = centred ] && flag=--similarity-center
  run $s "${shared[@]}" $flag
  run $s-folds "${folds[@]}" $flag
done
$PY - "$OUT" <<'PY'
import json, sys
from pathlib import Path
out = Path(sys.argv[1])
print('| dataset | row | P@100%R raw | P@100%R centred | R@100%P raw | R@100%P centred |')
print('|---|---|---:|---:|---:|---:|')
for part in ('', '-folds'):
    raw, cen = (json.loads((out / f'{s}{part}' / 'results.json').read_text())['datasets'] for s in ('raw', 'centred'))
    for name, ds in raw.items():
        for row, m in ds['methods'].items():
            c = cen[name]['methods'][row]
            print(f"| {name} | {row} | {100 * m['p_at_100r']:.1f} | {100 * c['p_at_100r']:.1f} | "
                  f"{100 * m['r_at_100p']:.1f} | {100 * c['r_at_100p']:.1f} |")
PY
