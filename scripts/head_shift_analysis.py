#!/usr/bin/env python3
"""Which cells a head prefers, against ACT's feature-norm choice (issue 28, docs/generalisation.md).

    python scripts/head_shift_analysis.py --dataset vprbench:out/shift/lateral [--dataset ...]
        [--weights CKPT] [--top-n 50] [--cache cache/features] [--out out/shift-analysis]

For every image of every dataset (queries and references), from the cached backbone features
(D, rows, cols) and the head's logits L (rows, cols) = norm_prior * log|f| + c, where c is the
head's learned correction (the 1x1 fuse output):

    spearman      rank correlation of L with the feature norm |f| over the image's cells
    c_spread      std of c over the cells / std of log|f| (0 = the head is ACT's ranking; median)
    overlap       |LLN top-n  ∩  ACT top-n| / n
    border        share of LLN's (ACT's) top-n on the outer ring of the grid, against the ring's
                  share of the grid
    top, bottom   share of the top-n in the upper (lower) third of the image (sky / ground)
    pad_prior     c on a map holding the image's mean feature in every cell: interior minus ring,
                  in units of c's std on the real image (> 0: the zero padding of the 3x3 / 5x5
                  branches alone makes the head prefer the centre, whatever the image shows)

and, per dataset, the mean selection frequency of every cell position (normalised to a 9x9 grid
of relative positions) for LLN and ACT, and the mean c there: a fixed position prior shows as the
same pattern on every dataset. Writes OUT/analysis.json, OUT/analysis.md, OUT/selection.png and
OUT/examples.png (one query and its reference per dataset, both selections drawn on them).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

BINS = 9  # relative-position grid of the selection maps


def rank(x: np.ndarray) -> np.ndarray:
    r = np.empty(x.size)
    r[np.argsort(x, kind='stable')] = np.arange(x.size)
    return r


def spearman(a: np.ndarray, b: np.ndarray) -> float:
    ra, rb = rank(a.ravel()), rank(b.ravel())
    if ra.std() == 0 or rb.std() == 0:
        return float('nan')
    return float(np.corrcoef(ra, rb)[0, 1])


def binned(mask: np.ndarray) -> np.ndarray:
    """(rows, cols) values -> (BINS, BINS) means over relative positions."""
    rows, cols = mask.shape
    ri = np.minimum((np.arange(rows) + 0.5) / rows * BINS, BINS - 1).astype(int)
    ci = np.minimum((np.arange(cols) + 0.5) / cols * BINS, BINS - 1).astype(int)
    s, n = np.zeros((BINS, BINS)), np.zeros((BINS, BINS))
    np.add.at(s, (ri[:, None], ci[None, :]), mask)
    np.add.at(n, (ri[:, None], ci[None, :]), 1)
    return s, n


def analyse(feats: list, head, top_n: int) -> dict:
    import torch

    from lln_ros.core.landmarks import select_landmarks

    prior = float(head.conf.get('norm_prior') or 0)
    stats = {
        k: []
        for k in (
            'spearman',
            'c_spread',
            'overlap',
            'border_lln',
            'border_act',
            'border_grid',
            'top_lln',
            'top_act',
            'bottom_lln',
            'bottom_act',
            'cells',
            'pad_prior',
        )
    }
    maps = {k: [np.zeros((BINS, BINS)), np.zeros((BINS, BINS))] for k in ('lln', 'act', 'c')}
    for f in feats:
        f = np.asarray(f, np.float32)
        d, rows, cols = f.shape
        with torch.inference_mode():
            logits = head.logits(torch.from_numpy(f)[None])[0].numpy()
        lognorm = np.log(np.linalg.norm(f, axis=0) + 1e-6)
        c = logits - prior * lognorm
        n = min(top_n, rows * cols)
        sel = {}
        for name, score in (('lln', logits), ('act', lognorm)):
            m = np.zeros(rows * cols, bool)
            m[select_landmarks(score, n, 'lln')] = True
            sel[name] = m.reshape(rows, cols)
        ring = np.zeros((rows, cols), bool)
        ring[[0, -1], :] = ring[:, [0, -1]] = True
        # the same mean feature in every cell: any spatial pattern of c is then the convs' zero padding
        flat = np.broadcast_to(f.mean(axis=(1, 2), keepdims=True), f.shape).copy()
        with torch.inference_mode():
            c_flat = head.logits(torch.from_numpy(flat)[None])[0].numpy() - prior * np.log(
                np.linalg.norm(flat, axis=0) + 1e-6
            )
        # interior minus ring of c on that input, in units of c's spread over the real image's cells
        stats['pad_prior'].append(float((c_flat[~ring].mean() - c_flat[ring].mean()) / max(c.std(), 1e-9)))
        third = max(1, rows // 3)
        stats['spearman'].append(spearman(logits, lognorm))
        stats['c_spread'].append(float(c.std() / max(lognorm.std(), 1e-9)))
        stats['overlap'].append(float((sel['lln'] & sel['act']).sum() / n))
        stats['border_grid'].append(float(ring.mean()))
        stats['cells'].append(rows * cols)
        for name in ('lln', 'act'):
            stats[f'border_{name}'].append(float((sel[name] & ring).sum() / n))
            stats[f'top_{name}'].append(float(sel[name][:third].sum() / n))
            stats[f'bottom_{name}'].append(float(sel[name][-third:].sum() / n))
        for name, m in (('lln', sel['lln']), ('act', sel['act']), ('c', c - c.mean())):
            s, k = binned(m.astype(float))
            maps[name][0] += s
            maps[name][1] += k
    # c_spread: the median, as a nearly flat image (tiny std of log|f|) makes the ratio explode
    out = {k: float(np.nanmedian(v) if k == 'c_spread' else np.nanmean(v)) for k, v in stats.items()}
    out['images'] = len(feats)
    out['maps'] = {k: (s / np.maximum(k_, 1)).tolist() for k, (s, k_) in maps.items()}
    return out


def figure(results: dict, path: Path, head: str = 'the shipped head') -> None:
    import matplotlib

    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    names = list(results)
    fig, axes = plt.subplots(len(names), 3, figsize=(8.4, 2.5 * len(names) + 0.6), squeeze=False)
    for i, name in enumerate(names):
        r = results[name]
        for j, (key, title, cmap, lim) in enumerate(
            (
                ('lln', 'how often LLN selects a cell', 'viridis', (0, 1)),
                ('act', 'how often ACT selects a cell', 'viridis', (0, 1)),
                ('c', "head's correction c (mean, centred)", 'coolwarm', None),
            )
        ):
            ax = axes[i, j]
            m = np.array(r['maps'][key])
            if lim is None:
                v = float(np.abs(m).max()) or 1.0
                lim = (-v, v)
            im = ax.imshow(m, cmap=cmap, vmin=lim[0], vmax=lim[1], extent=(0, 1, 1, 0))
            ax.set_xticks([0, 0.5, 1])
            ax.set_yticks([0, 0.5, 1])
            ax.tick_params(labelsize=7)
            if i == 0:
                ax.set_title(title, fontsize=9)
            if j == 0:
                ax.set_ylabel(f'{name}\n({r["cells"]:.0f} cells, top-{r["top_n"]})\nrelative row', fontsize=8)
            if i == len(names) - 1:
                ax.set_xlabel('relative column', fontsize=8)
            fig.colorbar(im, ax=ax, fraction=0.046, pad=0.04).ax.tick_params(labelsize=7)
    fig.suptitle(f'Where {head} puts its landmarks,\nper image position (mean over all images)', fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def examples(shown: dict, ex, top_n: int, path: Path, head: str = 'the shipped head') -> None:
    """One row per dataset: a query and its reference, with LLN's top-n cells (filled red squares)
    and ACT's (cyan outlines)."""
    import matplotlib

    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    import torch

    from lln_ros.core.landmarks import select_landmarks
    from lln_ros.io.image import load_image

    fig, axes = plt.subplots(len(shown), 2, figsize=(7.2, 2.3 * len(shown) + 0.5), squeeze=False)
    for i, (name, items) in enumerate(shown.items()):
        for j, (what, img_path, f) in enumerate(items):
            ax = axes[i, j]
            img = load_image(str(img_path))
            h, w = img.shape[:2]
            f = np.asarray(f, np.float32)
            _, rows, cols = f.shape
            with torch.inference_mode():
                logits = ex.head.logits(torch.from_numpy(f)[None])[0].numpy()
            n = min(top_n, rows * cols)
            ax.imshow(img, extent=(0, cols, rows, 0), interpolation='bilinear')
            for k, (score, style) in enumerate(((logits, 'lln'), (np.linalg.norm(f, axis=0), 'act'))):
                for cell in select_landmarks(score, n, 'lln'):
                    r, c = divmod(int(cell), cols)
                    if style == 'lln':
                        ax.add_patch(plt.Rectangle((c + 0.3, r + 0.3), 0.4, 0.4, color='red', lw=0))
                    else:
                        ax.add_patch(plt.Rectangle((c + 0.08, r + 0.08), 0.84, 0.84, fill=False, ec='cyan', lw=0.8))
            ax.set_xlim(0, cols)
            ax.set_ylim(rows, 0)
            ax.set_xticks([])
            ax.set_yticks([])
            ax.set_title(f'{name}: {what} ({w}x{h} px, {cols}x{rows} cells)', fontsize=8)
    fig.suptitle(f'top-{top_n} cells: red squares = {head} (LLN), cyan outlines = ACT (feature norm)', fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    p.add_argument('--dataset', action='append', required=True)
    p.add_argument('--range', default=None, help='START:END of aligned datasets')
    p.add_argument('--weights', default='', help="head checkpoint ('' = the shipped head)")
    p.add_argument('--label', default='', help="the head's name in the pictures' titles (default: the file name)")
    p.add_argument('--top-n', type=int, default=50)
    p.add_argument('--cache', default='cache/features')
    p.add_argument('--out', default='out/shift-analysis')
    p.add_argument('--example', type=int, default=3, help='query index shown in examples.png per dataset')
    a = p.parse_args()

    from lln_ros.core.extractor import Extractor
    from lln_ros.io.datasets import parse_range, parse_spec
    from lln_ros.io.features import FeatureCache

    ex = Extractor({'weights': a.weights})
    cache = FeatureCache(a.cache, ex)
    results, shown = {}, {}
    for spec in a.dataset:
        ds = parse_spec(spec, parse_range(a.range) if spec.startswith('aligned:') else None)
        paths = list(dict.fromkeys([str(q) for q in ds.query_paths] + [str(r) for r in ds.ref_paths]))
        r = analyse(cache.load(paths, size=int(ex.conf['input_height'])), ex.head, a.top_n)
        r['top_n'] = a.top_n
        results[ds.name] = r
        q = min(a.example, len(ds.query_paths) - 1)
        ref = int(np.flatnonzero(ds.gt[q])[0]) if ds.gt[q].any() else q
        pair = [('query', ds.query_paths[q]), ('its reference', ds.ref_paths[ref])]
        shown[ds.name] = [(w, p_, f) for (w, p_), f in zip(pair, cache.load([str(x) for _, x in pair]))]
        print(f'{ds.name}: ' + ', '.join(f'{k} {v:.3f}' for k, v in r.items() if not isinstance(v, (dict, list))))
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / 'analysis.json').write_text(json.dumps(results, indent=1))
    keys = (
        'cells',
        'spearman',
        'c_spread',
        'overlap',
        'border_grid',
        'border_lln',
        'border_act',
        'top_lln',
        'top_act',
        'bottom_lln',
        'bottom_act',
        'pad_prior',
    )
    lines = ['| set | ' + ' | '.join(keys) + ' |', '|---|' + '---:|' * len(keys)]
    for name, r in results.items():
        lines.append(f'| {name} | ' + ' | '.join(f'{r[k]:.2f}' if k != 'cells' else f'{r[k]:.0f}' for k in keys) + ' |')
    (out / 'analysis.md').write_text('\n'.join(lines) + '\n')
    print('\n'.join(lines))
    head = a.label or (f'the head {Path(a.weights).name}' if a.weights else 'the shipped head')
    figure(results, out / 'selection.png', head)
    examples(shown, ex, a.top_n, out / 'examples.png', head)
    print(f'wrote {out}/analysis.json, analysis.md, selection.png, examples.png')
    return 0


if __name__ == '__main__':
    sys.exit(main())
