"""Accuracy at scale: the Nordland test split inside maps padded with real distractor keyframes.

    python bench/bench_accuracy_at_scale.py [--sizes 0,10000,100000] [--data /work/shared/data]
                                            [--cache cache/features] [--sequence 10] [--dir /tmp/lln_scale]
                                            [--landmark-knn K] [--landmark-alpha A] [--landmark-query-top N]
                                            [--landmark-index-top N] [--landmark-compressed KIND]
                                            [--landmark-refine SQ8] [--landmark-nprobe N] [--landmark-k-factor K]
                                            [--similarity raw|whiten|fuse]
                                            [--sequence-carry 0,10] [--sequence-prefilter-k K] [--prefilter-k K]
                                            [--sequence-acquire-k K]
                                            [--range 0.7:1] [--distractor-seasons summer,winter] [--rescore]

The map: the summer references of the Nordland test split (lln-eval's docs/results.md split:
aligned summer/winter, range 0.7:1, tolerance 1 frame; --range 0.6:0.7 is the validation part,
for choosing settings), keyframe ids in route order, then distractor keyframes appended until each
--sizes (0 = the plain map). Distractors are landmarks of other real images through the shipped
Extractor (backbone features from the on-disk FeatureCache, --cache, shared with lln-eval), in this
order: Nordland summer and winter from 0 to 0.1 of the route before --range starts (0:0.6, the
training part, for the test split; it ends 358 frames before the test range starts and Nordland
never revisits a place, so with a 1-frame tolerance no distractor can be a true match), then every image of
rtabmap_loop, essex3in1 and tum_fr1rpy (--distractor-seasons summer: Nordland's summer only, the
references' season, as in a map built in one season). When more are needed, horizontal flips of those images
(through the same extractor, not cached), then seeded random crops (70-90% of the image, resized
back by the extractor). A distractor is never counted correct: ground truth covers references only.

Queries: the winter test frames (lln-eval's drop rule), in route order, through the matcher's own
decision code (core.localizer.Localizer.query on MapStore.open: shipped defaults, landmark first stage,
rerank by S), single frame (lln) and with sequence_length --sequence (lln+seq). P@100%R is the fraction
of queries whose best answer is a reference within tolerance (every test query has one); with
--sequence-carry N,M one lln+seq column per value of the Localizer's sequence_carry (the best N sequence
ends' next places scored beside the first stage's candidates; 0 = off), and --sequence-prefilter-k the
first-stage candidates it reranks (the matcher's sequence_prefilter_k; the Localizer reranks
max(prefilter_k, sequence_prefilter_k) with a sequence, so fewer than prefilter_k takes --prefilter-k
too); --sequence-acquire-k the candidates while the window fills (the Localizer's sequence_acquire_k:
its first L - 1 queries). --prefilter-k: the first-stage candidates a single frame reranks (the
matcher's prefilter_k). 'first stage' is the recall of a correct reference in the landmark index's
shortlist of prefilter_k keyframes (the map's index, as MapStore.query calls it). Under the table, the
single frame's wrong answers by what they are: another reference (place of the route) or a distractor by
kind (real, flip, crop) and origin (Nordland summer / winter, the other sets).

--landmark-knn / --landmark-alpha / --landmark-query-top / --landmark-index-top /
--landmark-compressed / --landmark-refine / --landmark-nprobe / --landmark-k-factor: the map's first
stage (landmark_index.default_conf, as the map store's conf). --similarity: the reranker S on raw
sets (the default), on centred and whitened sets ('whiten'), or raw + fusion_weight x whitened
('fuse'): the matcher's `similarity` (docs/method.md).

--rescore: no map is built; the map a previous run of the same --range and --distractor-seasons
left in --dir (at its largest size) is scored with this run's settings, the distractors' kinds
replayed from the same pool order. The first stage's query-time settings (--landmark-knn, -alpha,
-query-top) and the Localizer's apply as given; an index setting other than the map's rebuilds its
index first. Minutes at 100k keyframes instead of most of an hour: how settings are compared on one map.

Skips (exit 0, message) when --data is absent.
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from lln_ros.core.extractor import Extractor  # noqa: E402
from lln_ros.core.localizer import CHOICES, Localizer  # noqa: E402
from lln_ros.core.localizer import default_conf as LOC  # noqa: E402
from lln_ros.core.retrieval import default_conf as retrieval_conf  # noqa: E402
from lln_ros.io.datasets import _select, aligned, list_images, parse_range  # noqa: E402
from lln_ros.io.features import FeatureCache  # noqa: E402
from lln_ros.io.image import load_image  # noqa: E402
from lln_ros.mapstore import MapStore  # noqa: E402

T0 = 1_700_000_000 * 10**9
OTHER_SETS = ('rtabmap_loop', 'essex3in1', 'tum_fr1rpy')


def distractor_paths(data: Path, route_end: float = 0.6, seasons=('summer', 'winter')) -> list[Path]:
    """Real images that are never a queried place: Nordland 0:route_end of `seasons` (none when
    route_end <= 0), the other sets."""
    out = []
    for season in seasons if route_end > 0 else ():
        imgs = list_images(data / 'nordland_trimmed' / season)
        out += imgs[_select(len(imgs), (0.0, route_end))]
    for name in OTHER_SETS:
        if (data / name).is_dir():
            out += sorted(p for p in (data / name).rglob('*') if p.suffix.lower() in ('.png', '.jpg', '.jpeg', '.bmp'))
    return out


def augmented(path: Path, k: int, rng) -> np.ndarray:
    """The k-th augmentation round of a real image: 1 = horizontal flip, >= 2 = seeded crop."""
    img = load_image(str(path))
    if k == 1:
        return np.ascontiguousarray(img[:, ::-1])
    h, w = img.shape[:2]
    f = rng.uniform(0.7, 0.9)
    ch, cw = int(h * f), int(w * f)
    y, x = rng.integers(0, h - ch + 1), rng.integers(0, w - cw + 1)
    return np.ascontiguousarray(img[y : y + ch, x : x + cw])


def kind_of(round_: int) -> str:
    """What the pool's round_-th pass adds (augmented's rounds): 'real', 'flip', then 'crop'."""
    return ('real', 'flip', 'crop')[min(round_, 2)]


def result_row(store, target: int, stopped: bool, scores: dict) -> dict:
    """One size's table row: the map's keyframes, the size asked for, score()'s figures, the load."""
    return {'keyframes': len(store), 'target': target, 'stopped': stopped, 'load': os.getloadavg()[0], **scores}


def origin(path: Path) -> str:
    """What a distractor image shows: 'nordland summer' / 'nordland winter' or 'other sets'."""
    return f'nordland {path.parent.name}' if 'nordland_trimmed' in path.parts else 'other sets'


def score(store, sets, gt, ref_ids, seq_len, carries, loc_conf: dict, source: dict) -> dict:
    """P@100%R of lln and lln+seq (per sequence_carry) and the first stage's recall, over the queries in order.
    loc_conf: the Localizer settings every row shares (similarity, prefilter_k, sequence_prefilter_k).
    source: {distractor keyframe id: what it is}; out['lln_wrong']: the single frame's wrong answers
    counted by what they are ('reference': another place of the route)."""
    id_to_ref = {int(k): i for i, k in enumerate(ref_ids)}
    out = {'lln_wrong': {}}
    k = int(loc_conf['prefilter_k'])
    hits = 0
    for qi, lset in enumerate(sets):
        ids, _ = store._landmarks.shortlist(lset, k, below=None, scale=1.0)
        hits += any(int(i) in id_to_ref and gt[qi, id_to_ref[int(i)]] for i in ids)
    out['first_stage'] = hits / len(sets)
    for name, length, carry in [('lln', 0, 0)] + [(seq_name(c, carries), seq_len, c) for c in carries]:
        loc = Localizer(store, {**loc_conf, 'sequence_length': length, 'sequence_carry': carry})
        good, t = 0, time.perf_counter()
        for qi, lset in enumerate(sets):
            answer = loc.query(lset, T0 + 10**13 + qi * 10**9)
            best = int(answer.rows[0]['keyframe_id']) if answer and answer.rows else -1
            right = best in id_to_ref and bool(gt[qi, id_to_ref[best]])
            good += right
            if not length and not right:
                what = 'reference' if best in id_to_ref else source.get(best, 'no answer')
                out['lln_wrong'][what] = out['lln_wrong'].get(what, 0) + 1
        out[name] = good / len(sets)
        out[name + '_ms'] = (time.perf_counter() - t) * 1e3 / len(sets)
    return out


def seq_name(carry: int, carries) -> str:
    return 'lln+seq' if len(carries) == 1 else f'seq c{carry}'


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('--sizes', default='0,10000,100000', help='map sizes, keyframes (0 = the test references only)')
    ap.add_argument('--data', default='/work/shared/data')
    ap.add_argument('--cache', default=os.environ.get('LLN_FEATURES', 'cache/features'))
    ap.add_argument('--sequence', type=int, default=10, help="lln+seq's sequence_length")
    ap.add_argument('--dir', default='/tmp/lln_scale')
    ap.add_argument('--range', default='0.7:1', help='the Nordland part queried (0.6:0.7: the validation part)')
    ap.add_argument(
        '--distractor-seasons',
        default='summer,winter',
        help="Nordland seasons among the distractors: 'summer' pads the map only with the references' season "
        '(a map built in one season, queried in another)',
    )
    ap.add_argument('--rescore', action='store_true', help='score the map already in --dir (module doc)')
    ap.add_argument('--max-seconds', type=float, default=0, help='stop growing the map after this long (0 = never)')
    ap.add_argument(
        '--landmark-knn', type=int, default=retrieval_conf['landmark_knn'], help='first stage: hits per query landmark'
    )
    ap.add_argument(
        '--landmark-query-top',
        type=int,
        default=retrieval_conf['landmark_query_top'],
        help='first stage: query landmarks (best first) that search the index (0 = all)',
    )
    ap.add_argument(
        '--landmark-index-top',
        type=int,
        default=retrieval_conf['landmark_index_top'],
        help="first stage: each keyframe's landmarks (best first) the index holds (0 = all)",
    )
    ap.add_argument(
        '--landmark-compressed',
        default=retrieval_conf['landmark_compressed'],
        help='first stage: the landmark index kind above its threshold (landmark_index.COMPRESSED)',
    )
    ap.add_argument('--landmark-refine', default=retrieval_conf['landmark_refine'], help="ivfpq-fs-refine's codes")
    ap.add_argument(
        '--landmark-nprobe', type=int, default=retrieval_conf['landmark_nprobe'], help="IVF cells probed (0: kind's)"
    )
    ap.add_argument(
        '--landmark-k-factor',
        type=int,
        default=retrieval_conf['landmark_k_factor'],
        help="ivfpq-fs-refine's shortlist factor",
    )
    ap.add_argument(
        '--landmark-alpha',
        type=float,
        default=retrieval_conf['landmark_alpha'],
        help="first stage: a hit's vote exponent",
    )
    ap.add_argument(
        '--sequence-carry',
        default=str(LOC['sequence_carry']),
        help="lln+seq: the Localizer's sequence_carry, or several (comma-separated), a column each",
    )
    ap.add_argument(
        '--sequence-prefilter-k',
        type=int,
        default=LOC['sequence_prefilter_k'],
        help="lln+seq: the Localizer's sequence_prefilter_k (first-stage candidates reranked)",
    )
    ap.add_argument(
        '--sequence-acquire-k',
        type=int,
        default=LOC['sequence_acquire_k'],
        help="lln+seq: the Localizer's sequence_acquire_k (candidates while the window fills; 0 = off)",
    )
    ap.add_argument(
        '--prefilter-k',
        type=int,
        default=LOC['prefilter_k'],
        help="the Localizer's prefilter_k (first-stage candidates a single frame reranks)",
    )
    ap.add_argument(
        '--similarity',
        choices=CHOICES['similarity'],
        default=LOC['similarity'],
        help="the reranker S's sets (similarity center)",
    )
    args = ap.parse_args(argv)
    args.carries = [int(c) for c in args.sequence_carry.split(',')]
    loc_conf = {
        'similarity': args.similarity,
        'prefilter_k': args.prefilter_k,
        'sequence_prefilter_k': args.sequence_prefilter_k,
        'sequence_acquire_k': args.sequence_acquire_k,
    }
    map_conf = {
        'landmark_knn': args.landmark_knn,
        'landmark_alpha': args.landmark_alpha,
        'landmark_query_top': args.landmark_query_top,
        'landmark_index_top': args.landmark_index_top,
        'landmark_compressed': args.landmark_compressed,
        'landmark_refine': args.landmark_refine,
        'landmark_nprobe': args.landmark_nprobe,
        'landmark_k_factor': args.landmark_k_factor,
    }
    data = Path(args.data)
    if not (data / 'nordland_trimmed' / 'summer').is_dir():
        print(f'skipped: no Nordland data under {data} (nordland_trimmed/summer, winter)')
        return 0
    t_start = time.perf_counter()
    sizes = sorted(int(s) for s in args.sizes.split(','))
    folder = Path(args.dir)
    if not args.rescore:
        shutil.rmtree(folder, ignore_errors=True)
        folder.mkdir(parents=True)
    elif not (folder / 'map.db').is_file():
        sys.exit(f'--rescore: no map in {folder} (run once without --rescore)')
    part = parse_range(args.range)
    ds = aligned(data / 'nordland_trimmed' / 'summer', data / 'nordland_trimmed' / 'winter', 1, part)
    extractor = Extractor()
    height = int(extractor.conf['input_height'])
    cache = FeatureCache(args.cache, extractor)
    refs = cache.landmark_sets(ds.ref_paths, height)
    queries = cache.landmark_sets(ds.query_paths, height)
    seasons = tuple(args.distractor_seasons.split(','))
    if not set(seasons) <= {'summer', 'winter'}:
        sys.exit(f'--distractor-seasons: summer and/or winter, got {args.distractor_seasons!r}')
    pool = distractor_paths(data, round(part[0] - 0.1, 6), seasons)  # a tenth of the route apart: no true match
    print(f'{len(refs)} references, {len(queries)} queries, {len(pool)} real distractor images', flush=True)
    rows, used, rng, source = [], {'real': 0, 'flip': 0, 'crop': 0}, np.random.default_rng(0), {}
    rate = []
    if args.rescore:
        with MapStore.open(folder / 'map.db', model=extractor.model_info, conf=map_conf, create=False) as store:
            ids = store.ids()
            ref_ids, distractors = ids[: len(refs)], ids[len(refs) :]
            for i, kid in enumerate(distractors):  # the build's order: pool, then its flips, then crops
                round_, idx = divmod(i, len(pool))
                used[kind_of(round_)] += 1
                source[int(kid)] = f'{kind_of(round_)} {origin(pool[idx])}'
            r = score(store, queries, ds.gt, ref_ids, args.sequence, args.carries, loc_conf, source)
            rows.append(result_row(store, len(store), False, r))
        print(table(rows, args, used, rate))
        return 0
    with MapStore.open(folder / 'map.db', model=extractor.model_info, conf=map_conf) as store:
        ref_ids = store.add_many(refs, [divmod(T0 + i * 10**8, 10**9) for i in range(len(refs))])
        cursor = 0
        for size in sizes:
            stopped = False
            while len(store) < size:
                if args.max_seconds and time.perf_counter() - t_start > args.max_seconds:
                    stopped = True
                    break
                n = min(500, size - len(store))
                round_, idx = divmod(cursor, len(pool))
                chunk = pool[idx : idx + n]
                t = time.perf_counter()
                if round_ == 0:
                    sets = cache.landmark_sets(chunk, height)
                else:
                    sets = [extractor(augmented(p, round_, rng)) for p in chunk]
                used[kind_of(round_)] += len(sets)
                rate.append(((time.perf_counter() - t) * 1e3 / len(chunk), round_))
                start = len(store)
                ids = store.add_many(sets, [divmod(T0 + (10**6 + start + i) * 10**8, 10**9) for i in range(len(sets))])
                source.update((int(i), f'{kind_of(round_)} {origin(p)}') for i, p in zip(ids, chunk))
                cursor += len(chunk)
                print(f'  map {len(store)} keyframes ({used}), {rate[-1][0]:.1f} ms/image', flush=True)
            r = score(store, queries, ds.gt, ref_ids, args.sequence, args.carries, loc_conf, source)
            rows.append(result_row(store, size, stopped, r))
            print(row_line(rows[-1], args.carries), flush=True)
            if stopped:
                break
    print(table(rows, args, used, rate))
    return 0


def row_line(r: dict, carries) -> str:
    seq = ''.join(f' {r[seq_name(c, carries)]:>8.3f}' for c in carries)
    return (
        f'{r["keyframes"]:>9} {r["lln"]:>7.3f}{seq} {r["first_stage"]:>11.3f} '
        f'{r["lln_ms"]:>7.1f} {r["load"]:>5.1f}' + ('  (stopped at --max-seconds)' if r['stopped'] else '')
    )


def table(rows, args, used, rate) -> str:
    k = args.prefilter_k
    lines = [
        f'Nordland summer refs {args.range}, winter queries, tol 1: lln / lln+seq (L={args.sequence}) P@100%R',
        f'first stage: landmark_knn {args.landmark_knn}, landmark_alpha {args.landmark_alpha:g}, query top '
        f'{args.landmark_query_top}, index top {args.landmark_index_top}, {args.landmark_compressed}'
        + (
            f' {args.landmark_refine} k_factor {args.landmark_k_factor}'
            if args.landmark_compressed == 'ivfpq-fs-refine'
            else ''
        )
        + f', nprobe {args.landmark_nprobe or "default"}; S: {args.similarity}; '
        f'sequence_carry {args.sequence_carry}, prefilter_k {args.prefilter_k}, '
        f'sequence_prefilter_k {args.sequence_prefilter_k}, sequence_acquire_k {args.sequence_acquire_k}',
        f'distractors used: {used}, Nordland seasons among them: {args.distractor_seasons}',
        f'{"keyframes":>9} {"lln":>7}'
        + ''.join(f' {seq_name(c, args.carries):>8}' for c in args.carries)
        + f' {"1st@" + str(k):>11} {"ms/q":>7} {"load":>5}',
    ]
    lines += [row_line(r, args.carries) for r in rows]
    for r in rows:  # where the single frame goes wrong: another place of the route, or which distractors
        wrong = ', '.join(f'{k} {v}' for k, v in sorted(r['lln_wrong'].items(), key=lambda kv: -kv[1]))
        lines.append(f'lln wrong at {r["keyframes"]} keyframes: {wrong}')
    for kind, name in ((0, 'cached real'), (1, 'flip'), (2, 'crop')):
        ms = [m for m, rnd in rate if min(rnd, 2) == kind]
        if ms:
            lines.append(f'distractor extraction ({name}): {np.median(ms):.1f} ms/image median over chunks of 500')
    return '\n'.join(lines)


if __name__ == '__main__':
    sys.exit(main())
