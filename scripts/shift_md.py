#!/usr/bin/env python3
"""Tables of lln-eval runs (results.json) with issue 28's targets per LLN row.

    python scripts/shift_md.py DIR [DIR ...]     # e.g. out/shift-eval/topn50 out/shift-eval/topn25

One table per DIR: a row per dataset, P@100%R in % per method. Each lln row gets `ok` when it is
>= ACT, >= RAND and >= ALL - 2 points on that dataset, else `MISS` (ALL is every cell, so a run
without it takes ALL from a sibling DIR's run of the same dataset, when given). When the DIRs hold
RAND at more than one --rand-seed (RAND is one fixed draw of cell locations per grid), a last table
gives RAND's spread over the draws per dataset.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np


def load(d: Path) -> dict:
    return json.loads((d / 'results.json').read_text())


def table(d: Path, all_from: dict) -> list[str]:
    r = load(d)
    params = r['parameters']
    sets = r['datasets']
    cols = []
    for ds in sets.values():
        for m in ds['methods']:
            if m not in cols:
                cols.append(m)
    lines = [
        f'{d} (top-n {params["top_n"]}, first stage {params["prefilter"]} {params["prefilter_k"]})',
        '',
        '| set | queries | ' + ' | '.join(cols) + ' |',
        '|---|---:|' + '---:|' * len(cols),
    ]
    for name, ds in sets.items():
        m = {k: 100 * v['p_at_100r'] for k, v in ds['methods'].items()}
        ref_all = m.get('all', all_from.get(name))
        cells = []
        for c in cols:
            if c not in m:
                cells.append('-')
                continue
            text = f'{m[c]:.1f}'
            if c.startswith('lln') and 'act' in m and 'rand' in m and ref_all is not None:
                ok = m[c] >= m['act'] - 1e-9 and m[c] >= m['rand'] - 1e-9 and m[c] >= ref_all - 2 - 1e-9
                text += ' ok' if ok else ' MISS'
            cells.append(text)
        lines.append(f'| {name} | {ds["queries_with_match"]} | ' + ' | '.join(cells) + ' |')
    return lines


def rand_spread(dirs: list) -> list[str]:
    """RAND's P@100%R over every --rand-seed found in dirs: mean, sd, min, max per dataset."""
    by_set: dict = {}
    for d in dirs:
        r = load(d)
        seed = r['parameters'].get('rand_seed', 0)
        for name, ds in r['datasets'].items():
            if 'rand' in ds['methods']:
                by_set.setdefault(name, {})[seed] = 100 * ds['methods']['rand']['p_at_100r']
    if not by_set or max(len(v) for v in by_set.values()) < 2:
        return []
    lines = ['RAND over its seeds', '', '| set | seeds | mean | sd | min | max |', '|---|---:|---:|---:|---:|---:|']
    for name, per_seed in by_set.items():
        v = np.array(list(per_seed.values()))
        sd = v.std(ddof=1) if len(v) > 1 else 0.0
        lines.append(f'| {name} | {len(v)} | {v.mean():.1f} | {sd:.1f} | {v.min():.1f} | {v.max():.1f} |')
    return lines


def main(argv: list[str]) -> int:
    if not argv:
        print(__doc__, file=sys.stderr)
        return 2
    dirs = [Path(a) for a in argv]
    all_from = {}
    for d in dirs:
        for name, ds in load(d)['datasets'].items():
            if 'all' in ds['methods']:
                all_from[name] = 100 * ds['methods']['all']['p_at_100r']
    for d in dirs:
        print('\n'.join(table(d, all_from)) + '\n')
    spread = rand_spread(dirs)
    if spread:
        print('\n'.join(spread) + '\n')
    return 0


if __name__ == '__main__':
    sys.exit(main(sys.argv[1:]))
