"""Keyframe novelty gating without odometry, measured: a camera standing still, and a loop sequence.

    .venv/bin/python scripts/keyframe_novelty.py [--data ../shared/data] [--novelty 0,25,30]
                                                 [--still-seconds 120] [--hz 30] [--accept 17.11]
                                                 [--still-frame IMAGE]

Both parts run the matcher's decision code (core.localizer.Localizer in mapping mode on a real
SQLite map: shipped defaults, exclude_recent 10 keyframes, no odometry) with each
keyframe_novelty_max_score of --novelty (0 = every frame is a keyframe; 25 is the shipped default), on
landmarks of the shipped Extractor:

1. **still**: the first rtabmap_loop frame (or --still-frame) with fresh sensor noise per frame (Gaussian, sigma 2
   grey levels) for --still-seconds at --hz. Every answer is a loop closure with itself: printed
   are the keyframes stored, the frames answered at all (min_score 0) and those answered with
   S >= --accept (docs/slam_integration.md's threshold for precision 0.95).
2. **loop**: rtabmap_loop (84 frames, two laps, ground truth samples_GT.bmp): keyframes stored,
   top-1 correct on the 44 revisits, and the best recall at precision >= 0.95 over thresholds on
   the top-1 S (core.loop_closure.threshold_table; precision counts every answered frame).
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]


def localizers(folder: Path, novelties, model: dict):
    from lln_ros.core.localizer import Localizer
    from lln_ros.mapstore import open_for_matcher

    out = {}
    for t in novelties:
        store, _ = open_for_matcher(str(folder / f'novelty_{t:g}.db'), 'mapping', '')
        loc = Localizer(store, {'mode': 'mapping', 'registration': {'keyframe_novelty_max_score': t}})
        loc.model_info(json.dumps(model))
        out[t] = loc
    return out


def still(extractor, frame: np.ndarray, novelties, seconds: float, hz: float, accept: float, folder: Path):
    rng = np.random.default_rng(0)
    locs = localizers(folder / 'still', novelties, extractor.model_info)
    answered = {t: 0 for t in novelties}
    accepted = {t: 0 for t in novelties}
    n = int(round(seconds * hz))
    for i in range(n):
        noisy = np.clip(frame + rng.normal(0, 2.0, frame.shape), 0, 255).astype(np.uint8)
        lset = extractor(noisy)
        for t, loc in locs.items():
            rows = loc.query(lset, int(i * 1e9 / hz)).rows
            answered[t] += bool(rows)
            accepted[t] += bool(rows) and rows[0]['score'] >= accept
    out = {t: (len(loc.store), answered[t], accepted[t]) for t, loc in locs.items()}
    for loc in locs.values():
        loc.store.close()
    return n, out


def loop(extractor, data: Path, novelties, folder: Path):
    from lln_ros.core.loop_closure import threshold_table
    from lln_ros.io.datasets import loop as loop_dataset
    from lln_ros.io.image import load_image

    ds = loop_dataset(data, data / 'samples_GT.bmp', min_gap=10)
    locs = localizers(folder / 'loop', novelties, extractor.model_info)
    top1 = {t: ([], []) for t in novelties}  # scores, correct of the answered frames
    for i, path in enumerate(ds.query_paths):
        lset = extractor(load_image(path))
        for t, loc in locs.items():
            rows = loc.query(lset, i * 10**9).rows  # stamp = frame index in seconds
            if rows:
                top1[t][0].append(rows[0]['score'])
                top1[t][1].append(bool(ds.gt[i, int(rows[0]['stamp_sec'])]))
    positives = int(ds.gt.any(1).sum())
    out = {}
    for t, loc in locs.items():
        scores, correct = np.array(top1[t][0]), np.array(top1[t][1], bool)
        row = next(r for r in threshold_table(scores, correct, positives) if r['precision_target'] == 0.95)
        out[t] = (len(loc.store), int(correct.sum()), row)
        loc.store.close()
    return len(ds.query_paths), positives, out


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument('--data', default=str(REPO.parent / 'shared' / 'data'))
    p.add_argument('--novelty', default='0,25,30', help='keyframe_novelty_max_score values, comma-separated')
    p.add_argument('--still-seconds', type=float, default=120.0)
    p.add_argument('--hz', type=float, default=30.0)
    p.add_argument('--accept', type=float, default=17.11, help='S an answer needs to count as an accepted closure')
    p.add_argument('--still-frame', help='the image the still camera sees (default: the first rtabmap_loop frame)')
    args = p.parse_args()
    data = Path(args.data) / 'rtabmap_loop'
    if not data.is_dir():
        print(f'skipped: {data} is not there (the shared data set)')
        return 0
    from lln_ros.core.extractor import Extractor
    from lln_ros.io.datasets import list_images
    from lln_ros.io.image import load_image

    novelties = [float(v) for v in args.novelty.split(',')]
    extractor = Extractor({'num_threads': 2})
    t0 = time.monotonic()
    with tempfile.TemporaryDirectory() as tmp:
        still_frame = Path(args.still_frame) if args.still_frame else list_images(data)[0]
        frame = load_image(still_frame).astype(np.float32)
        n, still_out = still(extractor, frame, novelties, args.still_seconds, args.hz, args.accept, Path(tmp))
        frames, positives, loop_out = loop(extractor, data, novelties, Path(tmp))
    print(f'still camera: {n} frames ({args.still_seconds:g} s at {args.hz:g} Hz, {still_frame.name} + noise)')
    print(f'loop: rtabmap_loop, {frames} frames, {positives} revisits; exclude_recent 10, no odometry\n')
    print(
        '| keyframe_novelty_max_score | still: keyframes | still: answered | still: S >= accept '
        '| loop: keyframes | loop: top-1 right | loop: recall @ P>=0.95 (S) |'
    )
    print('|---:|---:|---:|---:|---:|---:|---|')
    for t in novelties:
        kf, ans, acc = still_out[t]
        lkf, right, row = loop_out[t]
        print(
            f'| {t:g} | {kf} | {ans} | {acc} | {lkf} | {right} of {positives} '
            f'| {row["recall"]:.3f} (P {row["precision"]:.3f}, S {row["threshold"]:.2f}) |'
        )
    print(f'\n--accept {args.accept:g}; {time.monotonic() - t0:.0f} s wall')
    return 0


if __name__ == '__main__':
    sys.exit(main())
