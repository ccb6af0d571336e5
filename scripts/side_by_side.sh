#!/usr/bin/env bash
# Two lln-eval settings side by side, shipped defaults otherwise: the Nordland validation part 0.6:0.7
# (never the test split), the other shared sets, and issue 28's transformed folds
# (scripts/shift_folds.py); methods lln, act, rand, all. Needs ../shared/data (or LLN_DATA).
#
#   bash scripts/side_by_side.sh OUT "A FLAGS" "B FLAGS"      # OUT/{a,b}{,-folds}/, then the table
#   bash scripts/side_by_side.sh out/similarity-center --no-similarity-center --similarity-center
#   bash scripts/side_by_side.sh out/int8 "--runtime onnxruntime" "--runtime onnxruntime-int8"
set -euo pipefail
cd "${LLN_REPO:-$(dirname "$0")/..}"
OUT=$1 A=$2 B=$3
DATA=${LLN_DATA:-../shared/data}
CACHE=${LLN_CACHE:-cache/features}
PY=${PY:-.venv/bin/python}
BIN=${BIN:-.venv/bin}
$PY scripts/shift_folds.py --data "$DATA" --out out/shift >&2
shared=(--dataset "aligned:$DATA/nordland_trimmed/summer,$DATA/nordland_trimmed/winter,1" --range 0.6:0.7
  --dataset "loop:$DATA/rtabmap_loop,$DATA/rtabmap_loop/samples_GT.bmp" --dataset "vprbench:$DATA/essex3in1"
  --dataset "poses:$DATA/tum_fr1rpy,15,0.3,2,3")
folds=()
for f in lateral side photo thumb webcam; do folds+=(--dataset "vprbench:out/shift/$f"); done
run() {  # run DIR ARGS...
  local dir=$1; shift
  [ -f "$OUT/$dir/results.json" ] && return 0
  $BIN/lln-eval "$@" --methods lln,act,rand,all --heads shipped=shipped --cache "$CACHE" --no-plots --quiet \
    --timing-images 1 --timing-queries 1 --timing-repeats 1 --out "$OUT/$dir" >&2
}
# shellcheck disable=SC2086  # the flags are words
for s in a b; do
  flags=$A; [ $s = b ] && flags=$B
  run $s "${shared[@]}" $flags
  run $s-folds "${folds[@]}" $flags
done
$PY - "$OUT" "$A" "$B" <<'PY'
import json, sys
from pathlib import Path
out, a, b = Path(sys.argv[1]), sys.argv[2], sys.argv[3]
print(f'A: `{a}`, B: `{b}`\n')
print('| dataset | row | P@100%R A | P@100%R B | R@100%P A | R@100%P B |')
print('|---|---|---:|---:|---:|---:|')
for part in ('', '-folds'):
    ra, rb = (json.loads((out / f'{s}{part}' / 'results.json').read_text())['datasets'] for s in ('a', 'b'))
    for name, ds in ra.items():
        for row, m in ds['methods'].items():
            c = rb[name]['methods'][row]
            print(f"| {name} | {row} | {100 * m['p_at_100r']:.1f} | {100 * c['p_at_100r']:.1f} | "
                  f"{100 * m['r_at_100p']:.1f} | {100 * c['r_at_100p']:.1f} |")
PY
