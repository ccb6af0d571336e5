"""Why the landmark first stage loses references in a large map: index type, centring, distractor kind.

    python bench/bench_first_stage_scale.py [--map /tmp/lln_scale/map.db] [--range 0.7:1]
                                            [--kinds ivfpq-fs,exact] [--cache cache/features]
                                            [--settings 'NAME;...'] [--votes KNN:ALPHA,...] [--nprobe N,...]

Reads the map bench_accuracy_at_scale.py leaves in its --dir (the Nordland test references first,
then its real distractors, all as the shipped Extractor made them) and asks of the first stage
alone (landmark_index.LandmarkIndex.shortlist, k = prefilter_k, no holistic top-up, no rerank):

- does the compressed index lose the references, or do the distractors outscore them? (--kinds:
  'exact' is brute-force inner product over the same vectors, ~6 min per row at 10k keyframes);
- what centring each image's landmarks on their mean does (landmark_center, with its tau: raw
  descriptors at tau 0.35, the setting before, against centred at tau 0.0), and the learned
  whitening after it (landmark_whitening, core.whitening; the default);
- whose keyframes win: the kinds of the top-1 keyframe (a reference, or a distractor by source);
- how many hits a query landmark takes and how they vote (--votes: landmark_knn, landmark_alpha,
  on the default descriptors), and what the search and the scoring of its hits cost (median ms per
  query, one thread; only ratios within one run mean anything on a shared machine);
- how many IVF cells a query landmark probes (--nprobe: landmark_nprobe, on the default descriptors):
  what the compressed index's speed costs in references found.

--range 0.6:0.7 swaps the test references for the validation part of the route (summer 0.6:0.7,
winter queries), with the same distractors: the split the shipped landmark_center and tau were
chosen on. R@K: a reference within 1 frame in the top K.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from collections import Counter
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_accuracy_at_scale import distractor_paths  # noqa: E402

from lln_ros.core.extractor import Extractor  # noqa: E402
from lln_ros.core.landmark_index import LandmarkIndex, encode_ids, score_hits  # noqa: E402
from lln_ros.core.retrieval import default_conf as retrieval_conf  # noqa: E402
from lln_ros.io.datasets import aligned  # noqa: E402
from lln_ros.io.features import FeatureCache  # noqa: E402
from lln_ros.mapstore import MapStore  # noqa: E402

TEST_REFS = 1073  # the Nordland test split's references, the first keyframes of the bench's map
SETTINGS = {
    'raw, tau 0.35': {'landmark_center': False, 'landmark_tau': 0.35, 'landmark_whitening': False},
    'centred, tau 0': {'landmark_whitening': False},
    'whitened, tau 0': {},
}


def source_kinds(data: Path, n_refs: int, n_map: int) -> list[str]:
    """What each map position is: 'reference', or the distractor's source (bench_accuracy_at_scale's
    order: its real pool, then the pool flipped, then seeded crops of it round after round)."""
    pool = distractor_paths(data)
    out = ['reference'] * n_refs
    for d in range(n_map - n_refs):
        round_, i = divmod(d, len(pool))
        p = pool[i]
        kind = f'nordland {p.parent.name}' if 'nordland' in str(p) else p.relative_to(data).parts[0]
        out.append(kind + ('', ' (flipped)', ' (cropped)')[min(round_, 2)])
    return out


def first_stage(sets, queries, gt, n_refs, kind, conf, k) -> tuple[dict, Counter]:
    """R@1 and R@k of the shortlist over `sets` (references first), the median ms per query of the
    FAISS search and of the scoring of its hits (score_hits), and the top-1 positions."""
    conf = {**conf, 'landmark_index_threshold': 1 << 40 if kind == 'exact' else 0}
    if kind != 'exact':
        conf['landmark_compressed'] = kind
    index = LandmarkIndex(sets[0].dim, conf, sets[0].descriptor_space)
    # build: trained on a sample of every landmark, as a map store's rebuild trains it
    index.build(
        np.concatenate([s.descriptors for s in sets]),
        encode_ids(
            np.concatenate([np.full(len(s), i, np.int64) for i, s in enumerate(sets)]),
            np.concatenate([np.asarray(s.cells).reshape(-1, 2) for s in sets]),
        ),
    )
    hit1 = hitk = 0
    top1 = Counter()
    t_search, t_score = [], []
    for qi, q in enumerate(queries):
        t0 = time.perf_counter()
        sims, kf, cells = index.search(q.descriptors, min(int(index.conf['landmark_knn']), index.ntotal))
        t1 = time.perf_counter()
        ids, _ = score_hits(q.cells, sims, kf, cells, index.conf)
        t_search.append(t1 - t0)
        t_score.append(time.perf_counter() - t1)
        ids = ids[:k]
        good = [int(i) < n_refs and bool(gt[qi, int(i)]) for i in ids]
        hit1 += bool(good[:1] and good[0])
        hitk += any(good)
        if len(ids):
            top1[int(ids[0])] += 1
    ms = {'search ms': 1e3 * float(np.median(t_search)), 'score ms': 1e3 * float(np.median(t_score))}
    return {'R@1': hit1 / len(queries), f'R@{k}': hitk / len(queries), **ms}, top1


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('--map', default='/tmp/lln_scale/map.db', help="bench_accuracy_at_scale.py's map (its --dir)")
    ap.add_argument('--data', default='/work/shared/data')
    ap.add_argument('--cache', default=os.environ.get('LLN_FEATURES', 'cache/features'))
    ap.add_argument('--range', default='0.7:1', help='Nordland part the references and queries come from')
    ap.add_argument('--kinds', default='ivfpq-fs', help='index types: exact, ivfpq-fs, ivfpq')
    ap.add_argument(
        '--settings',
        default=';'.join(SETTINGS),
        help=f'descriptor settings, separated by ";" (their names hold commas), of: {"; ".join(SETTINGS)}',
    )
    ap.add_argument(
        '--votes',
        default='',
        help='extra rows on the default descriptors, KNN:ALPHA,... (landmark_knn: hits per query landmark; '
        'landmark_alpha: vote exponent), e.g. 20:3,200:1',
    )
    ap.add_argument(
        '--nprobe',
        default='',
        help='extra rows on the default descriptors, IVF cells probed (landmark_nprobe), e.g. 8,32',
    )
    args = ap.parse_args(argv)
    data = Path(args.data)
    if not Path(args.map).exists():
        print(f'skipped: no map at {args.map} (run bench/bench_accuracy_at_scale.py --dir {Path(args.map).parent})')
        return 0
    span = tuple(float(v) for v in args.range.split(':'))
    ds = aligned(data / 'nordland_trimmed' / 'summer', data / 'nordland_trimmed' / 'winter', 1, span)
    extractor = Extractor()
    height = int(extractor.conf['input_height'])
    cache = FeatureCache(args.cache, extractor)
    queries = cache.landmark_sets(ds.query_paths, height)
    with MapStore.open(args.map, model=extractor.model_info) as store:
        stored = [s for _, _, s in store.keyframes()]
    distractors = stored[TEST_REFS:]
    refs = stored[:TEST_REFS] if args.range == '0.7:1' else cache.landmark_sets(ds.ref_paths, height)
    kinds = source_kinds(data, len(refs), len(refs) + len(distractors))
    k = int(retrieval_conf['prefilter_k'])
    print(
        f'Nordland {args.range}: {len(refs)} references, {len(queries)} winter queries, '
        f'{len(distractors)} distractors; first stage alone, top {k}'
    )
    settings = {name.strip(): SETTINGS[name.strip()] for name in args.settings.split(';') if name.strip()}
    for vote in filter(None, args.votes.split(',')):
        knn, alpha = vote.split(':')
        settings[f'knn {knn}, alpha {alpha}'] = {'landmark_knn': int(knn), 'landmark_alpha': float(alpha)}
    for nprobe in filter(None, args.nprobe.split(',')):
        settings[f'nprobe {int(nprobe)}'] = {'landmark_nprobe': int(nprobe)}
    print(
        f'{"index":>9} {"descriptors":>20} {"map":>14} {"R@1":>6} {"R@" + str(k):>6} {"search":>7} {"score":>6}'
        '  top-1 keyframes by kind'
    )
    for kind in args.kinds.split(','):
        for name, conf in settings.items():
            for label, sets in (('references', refs), (f'+{len(distractors)}', refs + distractors)):
                r, top1 = first_stage(sets, queries, ds.gt, len(refs), kind, conf, k)
                by_kind = Counter()
                for pos, count in top1.items():
                    by_kind[kinds[pos]] += count
                who = ', '.join(f'{n} {c}' for n, c in by_kind.most_common(4)) if label != 'references' else ''
                print(
                    f'{kind:>9} {name:>20} {label:>14} {r["R@1"]:>6.3f} {r[f"R@{k}"]:>6.3f} '
                    f'{r["search ms"]:>7.1f} {r["score ms"]:>6.1f}  {who}',
                    flush=True,
                )
    return 0


if __name__ == '__main__':
    sys.exit(main())
