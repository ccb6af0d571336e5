"""Which min_score gives which loop-closure precision and recall: the matcher's mapping mode replayed
offline on a loop sequence (default ../shared/data/rtabmap_loop), the best candidate's score of every
query against the ground-truth matrix. Prints the table docs/slam_integration.md quotes.

    .venv/bin/python scripts/loop_closure_thresholds.py [--data DIR] [--exclude-recent 10] [--prefilter-k 100]

Same code path as the matcher node (MapStore.query, then add, with its defaults); every query is
answered, so precision counts wrong answers of frames that revisit nothing (rtabmap_loop frames 1-40).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument('--data', default=str(REPO.parent / 'shared' / 'data' / 'rtabmap_loop'))
    p.add_argument('--gt', default='samples_GT.bmp', help='ground truth file inside --data')
    p.add_argument('--exclude-recent', type=int, default=10)
    from lln_ros.core.localizer import default_conf as matcher_defaults

    p.add_argument('--prefilter-k', type=int, default=matcher_defaults['prefilter_k'], help="default: the matcher's")
    args = p.parse_args()
    from lln_ros.core.extractor import Extractor
    from lln_ros.core.loop_closure import threshold_table
    from lln_ros.io.datasets import loop
    from lln_ros.io.image import load_image
    from lln_ros.mapstore import MapStore

    ds = loop(args.data, Path(args.data) / args.gt, min_gap=args.exclude_recent)
    extractor = Extractor({'num_threads': 2})
    scores, correct = [], []
    with tempfile.TemporaryDirectory() as tmp:
        store = MapStore.open(Path(tmp) / 'map.db')
        for i, path in enumerate(ds.query_paths):
            lset = extractor(load_image(path))
            found = store.query(lset, prefilter_k=args.prefilter_k, k=1, exclude_recent=args.exclude_recent)
            store.add(lset, (i, 0))
            if found:
                scores.append(found[0].score)
                correct.append(bool(ds.gt[i, found[0].keyframe_id - 1]))  # ids 1.. in storage order
        store.close()
    positives = int(ds.gt.any(1).sum())
    print(
        f'{ds.name}: {len(ds.query_paths)} frames, {len(scores)} answered, {positives} revisit an earlier '
        f'place; exclude_recent {args.exclude_recent}, prefilter_k {args.prefilter_k}'
    )
    print(
        f'top-1 correct on the revisits: {sum(correct)}; score of right answers median '
        f'{np.median([s for s, c in zip(scores, correct) if c]):.2f}, wrong answers median '
        f'{np.median([s for s, c in zip(scores, correct) if not c]):.2f}'
    )
    print('| target precision | min_score (S) | precision | recall |')
    print('|---|---|---|---|')
    for row in threshold_table(np.array(scores), np.array(correct), positives):
        print(
            f'| {row["precision_target"]:.2f} | {row["threshold"]:.2f} | {row["precision"]:.3f} | {row["recall"]:.3f} |'
        )
    return 0


if __name__ == '__main__':
    sys.exit(main())
