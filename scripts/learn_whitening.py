"""Learn a landmark whitening (lln_ros.core.whitening) from ground-truth image pairs.

    python scripts/learn_whitening.py --data SPEC [--data SPEC ...] [--range 0:0.6] [--balance]
                                      [--purpose index|similarity] [--cache cache/features]
                                      [--beta 0.5] [--out FILE.npz]

Each query image with a ground-truth reference is paired with its middle reference; their landmarks
(the shipped Extractor on the cached backbone features) give mutual nearest pairs at most one cell
apart (whitening.landmark_pairs), and W = C_S^-beta of their differences (whitening.learn). --range
applies to aligned datasets (the training part; never the test split). --balance: each --data
set's pairs weigh the same in C_S (whitening.learn's groups), however many it has. `make whitening`
writes the two shipped files (whitening.PURPOSES): the first stage's,
lln_ros/weights/whiten_<backbone>_<layer>.npz, from Nordland's training part 0:0.6, and S's,
whiten_similarity_<backbone>_<layer>.npz, from the four training sets, balanced.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from lln_ros.core import whitening  # noqa: E402
from lln_ros.core.extractor import Extractor  # noqa: E402
from lln_ros.io.datasets import parse_range, parse_spec  # noqa: E402
from lln_ros.io.features import FeatureCache  # noqa: E402


def dataset_pairs(cache, ds, height) -> tuple[np.ndarray, np.ndarray, int]:
    """Matching landmark rows (A (M, D), B (M, D)) of every query with a reference, and the images used."""
    use = [
        (qi, refs[len(refs) // 2])
        for qi, refs in ((q, np.flatnonzero(ds.gt[q])) for q in range(len(ds.gt)))
        if len(refs)
    ]
    qs = cache.landmark_sets([ds.query_paths[q] for q, _ in use], height)
    rs = cache.landmark_sets([ds.ref_paths[r] for _, r in use], height)
    pairs = [whitening.landmark_pairs(r, q, whitening.default_conf['max_cell_distance']) for q, r in zip(qs, rs)]
    return np.concatenate([a for a, _ in pairs]), np.concatenate([b for _, b in pairs]), len(use)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('--data', action='append', required=True, help='dataset SPEC (lln-eval --dataset)')
    ap.add_argument('--range', default=None, help='part of aligned datasets, e.g. 0:0.6')
    ap.add_argument('--cache', default='cache/features')
    ap.add_argument('--beta', type=float, default=whitening.default_conf['beta'])
    ap.add_argument('--balance', action='store_true', help="each --data set's pairs weigh the same")
    ap.add_argument('--purpose', default='index', choices=list(whitening.PURPOSES), help='which shipped file')
    ap.add_argument('--out', default=None, help="default: the default model's shipped file for --purpose")
    args = ap.parse_args(argv)
    extractor = Extractor()
    height = int(extractor.conf['input_height'])
    cache = FeatureCache(args.cache, extractor)
    a, b, images = [], [], []
    for spec in args.data:
        ds = parse_spec(spec, parse_range(args.range) if spec.startswith('aligned:') else None)
        pa, pb, n = dataset_pairs(cache, ds, height)
        print(f'{ds.name}: {n} image pairs, {len(pa)} landmark pairs', flush=True)
        a.append(pa)
        b.append(pb)
        images += list(ds.ref_paths) + list(ds.query_paths)
    groups = np.concatenate([np.full(len(x), i) for i, x in enumerate(a)]) if args.balance else None
    w = whitening.learn(np.concatenate(a), np.concatenate(b), args.beta, whitening.default_conf['floor'], groups)
    out = args.out or str(whitening.default_path(extractor.descriptor_space, args.purpose))
    meta = {
        'descriptor_space': extractor.descriptor_space,
        'head': extractor.model_info['head'],
        'beta': args.beta,
        'purpose': args.purpose,
        'balance': args.balance,
        'data': ' '.join(args.data),
        'range': args.range or '',
        'landmark_pairs': sum(len(x) for x in a),
        'images': len(images),
    }
    whitening.save(out, w, meta)
    print(f'wrote {out}: W {w.shape}, fingerprint {whitening.fingerprint(w)}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
