"""Markdown tables from scripts/loo.sh's evaluations: P@100%R of every method on every held-out set.

    .venv/bin/python scripts/loo_md.py out/loo     # prints markdown (pasted into docs/generalisation.md)

One table per first stage (holistic top-K). A head column is marked `ok` where the issue's targets
hold on that set (LLN >= ACT, LLN >= RAND, LLN >= ALL - 2 points), `MISS` where one fails.
"""

import json
import sys
from pathlib import Path

SETS = ('nordland', 'rtabmap', 'essex', 'tum')


def row_p(methods: dict, row: str):
    m = methods.get(row)
    return None if m is None or m.get('p_at_100r') is None else 100 * m['p_at_100r']


def verdict(lln, act, rand, all_):
    ok = lln >= act - 1e-9 and lln >= rand - 1e-9 and lln >= all_ - 2 - 1e-9
    return 'ok' if ok else 'MISS'


def main(root: Path) -> None:
    ks = sorted(
        {p.name.rsplit('-k', 1)[1].split('-')[0] for p in root.glob('eval-*-k*')}, key=lambda k: int(k) or 10**9
    )
    for k in ks:
        runs = {}
        for s in SETS:  # eval-S-kK/ and any eval-S-kK-EXTRA/ (heads evaluated later, --methods lln)
            for p in sorted(root.glob(f'eval-{s}-k{k}*/results.json')):
                if p.parent.name != f'eval-{s}-k{k}' and not p.parent.name.startswith(f'eval-{s}-k{k}-'):
                    continue
                res = json.loads(p.read_text())
                if s not in runs:
                    runs[s] = res
                else:
                    ((_, into),) = runs[s]['datasets'].items()
                    ((_, more),) = res['datasets'].items()
                    into['methods'].update(more['methods'])
                    runs[s]['parameters']['heads'].update(res['parameters']['heads'])
        if not runs:
            continue
        heads = list(dict.fromkeys(h for r in runs.values() for h in r['parameters']['heads']))
        first = (
            'holistic top-30' if k == '30' else ('exhaustive (every reference)' if k == '0' else f'holistic top-{k}')
        )
        print(f'\n### First stage: {first} (`--prefilter-k {k}`)\n')
        print(
            '| held-out set | queries | holistic | ACT | RAND | ALL | ' + ' | '.join(f'LLN[{h}]' for h in heads) + ' |'
        )
        print('|---|---:|---:|---:|---:|---:|' + '---:|' * len(heads))
        for s, res in runs.items():
            ((name, d),) = res['datasets'].items()
            m = d['methods']
            act, rand, all_ = row_p(m, 'act'), row_p(m, 'rand'), row_p(m, 'all')
            cells = []
            for h in heads:
                v = row_p(m, f'lln[{h}]')
                cells.append('n/a' if v is None else f'{v:.1f} {verdict(v, act, rand, all_)}')
            print(
                f'| {name} | {d["queries_with_match"]} | {row_p(m, "holistic"):.1f} | {act:.1f} | {rand:.1f} | '
                f'{all_:.1f} | ' + ' | '.join(cells) + ' |'
            )
    # candidates for the shipped head (scripts/loo.sh): one table per held-out set and first stage;
    # head-independent rows from the candidates' own run, else from the fold's run of the same set
    for cand in sorted(root.glob('candidates-*-k*/results.json')):
        s, k = cand.parent.name[len('candidates-') :].rsplit('-k', 1)
        if not k.isdigit():
            continue
        ((name, d),) = json.loads(cand.read_text())['datasets'].items()
        base = d['methods']
        if row_p(base, 'act') is None and (root / f'eval-{s}-k{k}' / 'results.json').is_file():
            ((_, b),) = json.loads((root / f'eval-{s}-k{k}' / 'results.json').read_text())['datasets'].items()
            base = b['methods']
        act, rand, all_ = (row_p(base, r) for r in ('act', 'rand', 'all'))
        if act is None:
            continue
        first = 'exhaustive' if k == '0' else f'holistic top-{k}'
        print(f'\n### Candidates for the shipped head, held out: {name}, {first}\n')
        print(f'ACT {act:.1f}, RAND {rand:.1f}, ALL {all_:.1f}.\n')
        print('| head | P@100%R | targets |')
        print('|---|---:|---|')
        for row, m in d['methods'].items():
            if row.startswith('lln['):
                v = 100 * m['p_at_100r']
                print(f'| {row} | {v:.1f} | {verdict(v, act, rand, all_)} |')


if __name__ == '__main__':
    main(Path(sys.argv[1] if len(sys.argv) > 1 else 'out/loo'))
