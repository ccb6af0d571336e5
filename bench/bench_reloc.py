"""Relocalization speed and storage: region-constrained (mLLN) vs all-keypoint matching.

    python bench/bench_reloc.py [--json] [--repeats 5] [--margin 1.0] [--pairs 20]

On rtabmap_loop revisit pairs (query frame r against its earliest true match in samples_GT.bmp):
median ms per pair of matching (ratio test) and of RANSAC verification (F) for both pipelines,
mean inliers, and the bytes per keyframe a map spends on stored ORB keypoints (the matcher's
verify mode). Needs ../shared/data/rtabmap_loop.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

from lln_ros.core.extractor import Extractor
from lln_ros.core.reloc import Relocalizer, pair_boxes
from lln_ros.core.similarity import match_pair
from lln_ros.io.image import load_image
from lln_ros.mapstore import MapStore

DATA = Path(__file__).resolve().parents[1].parent / 'shared' / 'data' / 'rtabmap_loop'


def best_of(fn, repeats: int) -> float:
    """Best wall time of fn() over `repeats` runs, in ms (a shared CPU is noisy)."""
    fn()
    best = float('inf')
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t)
    return best * 1e3


def run(repeats: int, margin: float, n_pairs: int) -> dict:
    gt = cv2.imread(str(DATA / 'samples_GT.bmp'), cv2.IMREAD_GRAYSCALE) > 127
    pairs = [(r, int(np.flatnonzero(gt[r])[0])) for r in range(len(gt)) if gt[r].any()]
    pairs = pairs[:: max(1, len(pairs) // n_pairs)][:n_pairs]
    extractor = Extractor({'num_threads': 1})
    reloc = Relocalizer({'margin': margin})
    rows = {'regions': {'match': [], 'verify': [], 'inliers': []}, 'all': {'match': [], 'verify': [], 'inliers': []}}
    for q, m in pairs:
        iq, im = load_image(str(DATA / f'{q + 1}.jpg')), load_image(str(DATA / f'{m + 1}.jpg'))
        a, b = extractor.extract_batch([iq, im])
        qb, mb = pair_boxes(a, b, match_pair(a, b).pairs(0), margin)
        kq, km = reloc.detect(iq), reloc.detect(im)
        for name, boxes in (('regions', (qb, mb)), ('all', (None, None))):
            matches = reloc.match(kq, km, *boxes)
            rows[name]['match'].append(best_of(lambda: reloc.match(kq, km, *boxes), repeats))
            rows[name]['verify'].append(best_of(lambda: reloc.verify(kq, km, matches), repeats))
            rows[name]['inliers'].append(reloc.verify(kq, km, matches).inliers)
    # storage: a map of 100 keyframes with and without 500 ORB keypoints each
    sizes = {}
    image = load_image(str(DATA / '1.jpg'))
    lset = extractor(image)
    kps = Relocalizer({'max_keypoints': 500}).detect(image)
    for with_kps in (False, True):
        with tempfile.TemporaryDirectory() as d:
            with MapStore(os.path.join(d, 'map.db'), model=extractor.model_info) as store:
                for i in range(100):
                    kid = store.add(lset, (i, 0))
                    if with_kps:
                        store.add_keypoints(kid, kps.uv, kps.descriptors)
                store.save()
                sizes[with_kps] = os.path.getsize(os.path.join(d, 'map.db')) / 100
    return {
        'pairs': len(pairs),
        'margin': margin,
        'keypoints_stored': len(kps),
        'load': os.getloadavg()[0],
        **{
            f'{name}_{k}': statistics.median(v) if k != 'inliers' else float(np.mean(v))
            for name, r in rows.items()
            for k, v in r.items()
        },
        'bytes_per_keyframe': sizes[False],
        'bytes_per_keyframe_with_keypoints': sizes[True],
    }


def table(r: dict) -> str:
    lines = [
        f'rtabmap_loop revisit pairs: {r["pairs"]}, regions grown by {r["margin"]:g} cells, '
        f'load average {r["load"]:.1f}',
        '| pipeline | match ms/pair | verify ms/pair | mean inliers |',
        '|---|---:|---:|---:|',
    ]
    for name, label in (('regions', 'mLLN (matched regions)'), ('all', 'all keypoints')):
        lines.append(f'| {label} | {r[name + "_match"]:.2f} | {r[name + "_verify"]:.2f} | {r[name + "_inliers"]:.1f} |')
    extra = r['bytes_per_keyframe_with_keypoints'] - r['bytes_per_keyframe']
    lines += [
        '',
        f'map file per keyframe: {r["bytes_per_keyframe"]:.0f} B landmarks only, '
        f'{r["bytes_per_keyframe_with_keypoints"]:.0f} B with {r["keypoints_stored"]} ORB keypoints '
        f'(+{extra:.0f} B, {extra / r["keypoints_stored"]:.1f} B per keypoint)',
    ]
    return '\n'.join(lines)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    p.add_argument('--json', action='store_true')
    p.add_argument('--repeats', type=int, default=5)
    p.add_argument('--margin', type=float, default=1.0)
    p.add_argument('--pairs', type=int, default=20)
    args = p.parse_args(argv)
    if not DATA.is_dir():
        print(f'bench_reloc: {DATA} is absent', file=sys.stderr)
        return 2
    r = run(args.repeats, args.margin, args.pairs)
    print(json.dumps(r) if args.json else table(r))
    return 0


if __name__ == '__main__':
    sys.exit(main())
