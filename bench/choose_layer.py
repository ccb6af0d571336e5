"""Which backbone feature layer should be the default? Measured on development data only.

    python bench/choose_layer.py [--json] [--cache cache/features]

For every (backbone, layer) it reports the descriptor size D, the bytes a keyframe costs in the map
(n = 50 landmarks in float16 plus the float32 global descriptor), the median extraction time of a
384x288 image, and retrieval figures of the head-independent methods (the LLN head is trained per
layer, so it cannot decide the layer): holistic ACT (top 50 by feature norm) and ALL (every cell,
spatially weighted mutual matching, reranking the holistic top 30) on
  - rtabmap_loop (loop protocol: rows 40-83 against frames at least 10 older): top-1 correct and
    recall at precision >= 0.95 over all answered rows;
  - a Nordland development slice from the TRAINING part of the route (0.60-0.70; the test split,
    the last 30%, is never looked at here): winter queries against summer, tolerance +-1.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

from lln_ros.core import metrics
from lln_ros.core.extractor import Extractor
from lln_ros.core.landmarks import stack_landmarks
from lln_ros.core.retrieval import rank_all
from lln_ros.io import datasets
from lln_ros.io.features import FeatureCache
from lln_ros.io.image import load_image

DATA = Path(__file__).resolve().parents[2] / 'shared' / 'data'
CONFIGS = [
    ('efficientnet_lite0', 'stage6'),
    ('efficientnet_lite0', 'stage7'),
    ('efficientnet_lite0', 'head'),
    ('efficientnet_lite2', 'stage7'),
]


def recall_at_precision(ranked, scores, gt, min_precision=0.95) -> float:
    precision, recall, _ = metrics.pr_curve(ranked, scores, gt)
    ok = precision >= min_precision
    return float(recall[ok].max()) if ok.any() else 0.0


def evaluate(ex: Extractor, cache: FeatureCache, ds, methods=('holistic', 'act', 'all')) -> dict:
    fq = cache.load(ds.query_paths, 288)
    fr = fq if ds.ref_paths == ds.query_paths else cache.load(ds.ref_paths, 288)
    out = {}
    for method in methods:
        ex.conf = {**ex.conf, 'method': 'all' if method == 'holistic' else method}
        qs = [ex.from_features(f, s) for f, s in zip(fq, ds.info['query_sizes'])]
        rs = stack_landmarks([ex.from_features(f, s) for f, s in zip(fr, ds.info['ref_sizes'])])
        ranked, scores = rank_all(qs, rs, 30, allowed=ds.candidates, rerank_local=method != 'holistic')
        out[method] = {
            'r_at_1': metrics.recall_at_k(ranked, ds.gt, 1),
            'r_at_p95': recall_at_precision(ranked, scores[:, 0], ds.gt),
        }
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument('--json', action='store_true')
    p.add_argument('--cache', default='cache/features')
    args = p.parse_args(argv)
    if not DATA.is_dir():
        print(f'choose_layer: needs the development data in {DATA}', file=sys.stderr)
        return 2
    rt = DATA / 'rtabmap_loop'
    nl = DATA / 'nordland_trimmed'
    loop = datasets.loop(rt, rt / 'samples_GT.bmp')
    nordland = datasets.aligned(nl / 'summer', nl / 'winter', 1, (0.6, 0.7))
    image = load_image(str(rt / '1.jpg'))  # 512x384 -> 384x288
    rows = []
    for backbone, layer in CONFIGS:
        ex = Extractor({'backbone': {'name': backbone, 'layer': layer}, 'num_threads': 2})
        times = []
        for _ in range(12):
            t = time.perf_counter()
            ex(image)
            times.append(time.perf_counter() - t)
        cache = FeatureCache(args.cache, ex)
        d = ex.backbone.dim
        rows.append(
            {
                'backbone': backbone,
                'layer': layer,
                'D': d,
                'bytes_per_keyframe': 50 * d * 2 + d * 4,
                'extract_ms': statistics.median(times[2:]) * 1e3,
                'rtabmap': evaluate(ex, cache, loop),
                'nordland_dev': evaluate(ex, cache, nordland),
            }
        )
    if args.json:
        print(json.dumps(rows))
        return 0
    print(
        '| backbone / layer | D | bytes/keyframe (n=50) | extract ms | rtabmap top-1: holistic / ACT / ALL | '
        'rtabmap recall@P>=0.95: holistic / ACT / ALL | Nordland dev R@1: holistic / ACT / ALL |'
    )
    print('|---|---|---|---|---|---|---|')
    for r in rows:
        rt_, nd = r['rtabmap'], r['nordland_dev']
        print(
            f'| {r["backbone"]} / {r["layer"]} | {r["D"]} | {r["bytes_per_keyframe"]:,} | {r["extract_ms"]:.1f} | '
            + ' | '.join(
                ' / '.join(f'{d[m][key]:.3f}' for m in ('holistic', 'act', 'all'))
                for d, key in ((rt_, 'r_at_1'), (rt_, 'r_at_p95'), (nd, 'r_at_1'))
            )
            + ' |'
        )
    return 0


if __name__ == '__main__':
    sys.exit(main())
