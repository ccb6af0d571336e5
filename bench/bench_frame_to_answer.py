"""Frame to answer: a camera image in, the matcher's candidates out, through the code the nodes run.

    python bench/bench_frame_to_answer.py [--sizes 1000,10000,100000] [--frames 60] [--threads 2]
                                          [--runtimes onnxruntime,onnxruntime-int8]
                                          [--prefilter-k K] [--landmark-query-top N[,M..]] [--similarity fuse,raw]
                                          [--landmark-index KIND[:TOP[:REFINE[:NPROBE[:K]]]][,...]]
                                          [--sequence 0 [--sequence-prefilter-k K] [--sequence-carry N[,M..]]
                                           [--sequence-acquire-k K[,K..]]]
                                          [--dir /tmp/lln_bench_f2a] [--json]

Per frame, in this process and in the nodes' order: Extractor.__call__ (the extractor node's
runtime and threads: ONNX Runtime by default) on a 384x288 RGB frame, then Localizer.query (the
matcher node's decision code: first stage, rerank by S, sequence search with --sequence L > 0) on an
SQLite map of each --sizes keyframes. DDS transport is not in it (bench/bench_node_rate.py measures
the nodes over DDS; a 20 KB landmark cloud costs well under a millisecond on loopback).

The map: 200 real keyframes (views of the photograph matplotlib ships, extracted by the same
Extractor), then synthetic keyframes with the default model's shapes (bench_map.synthetic_set: n=50
unit descriptors, D=192) up to each size; one map grows through --sizes. The queries are the real
keyframes' images again, brightened by 20% and with Gaussian pixel noise (sigma 6), so `top-1`
says the map still answers.

Each size is measured twice in one run, quiet (no process of ours besides this one) and beside one
competing CPU-bound process this script starts and stops, for each --runtimes entry (the
extractor's runtime; the map is built with the first) and each --landmark-query-top value (q-top,
on the same map) and each --sequence-carry value (carry: the matcher's sequence_carry, the places
the best sequences go next scored beside the first stage's candidates; with --sequence) and each
--similarity value (S: the matcher's similarity, e.g. fuse,raw) and each
--sequence-acquire-k value (acq-k: the matcher's sequence_acquire_k, the candidates reranked while
the window fills) and each --landmark-index entry (the map's landmark index kind, landmark_index_top
and refine codes: the map is reopened and its index rebuilt for each): p50 / p90 / p99 wall ms per
frame, the CPU ms per frame (process time, all threads), and the p50 of each stage. With --sequence
L, each row's frames come after a gap, so its first L - 1 are the window filling: `filling` is the
p50 query ms of those, `query` that of all. The load average at the start of
each row is printed: on a shared machine "quiet" means "nothing else of ours".
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import shutil
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_core import competing_load, photo_views  # noqa: E402
from bench_map import synthetic_set  # noqa: E402

from lln_ros.core.extractor import Extractor  # noqa: E402
from lln_ros.core.localizer import Localizer  # noqa: E402
from lln_ros.core.localizer import default_conf as LOC  # noqa: E402
from lln_ros.core.retrieval import default_conf as MAP  # noqa: E402
from lln_ros.mapstore import MapStore  # noqa: E402

REAL_KEYFRAMES = 200
T0 = 1_700_000_000 * 10**9


def query_images(images: list[np.ndarray], count: int, seed: int = 0) -> list[np.ndarray]:
    """`count` photometrically changed copies of `images` (cycled): 1.2x brighter, noise sigma 6."""
    rng = np.random.default_rng(seed)
    out = []
    for i in range(count):
        img = images[i % len(images)].astype(np.float32) * 1.2 + rng.normal(0, 6, images[0].shape)
        out.append(np.clip(img, 0, 255).astype(np.uint8))
    return out


def grow(store, size: int, rng) -> None:
    """Synthetic keyframes until the map holds `size` (bulk, 1000 per transaction)."""
    while len(store) < size:
        batch = [synthetic_set(rng) for _ in range(min(1000, size - len(store)))]
        start = len(store)
        store.add_many(batch, [divmod(T0 + (start + i) * 10**8, 10**9) for i in range(len(batch))])


def percentiles(values: list[float]) -> dict:
    a = np.asarray(values)
    return {f'p{q}': float(np.percentile(a, q)) for q in (50, 90, 99)}


def measure(extractor, loc, images: list, truth: list[int], filling: int = 0) -> dict:
    """Per-frame wall and CPU ms, stage p50s and top-1 of the real keyframe each query shows;
    filling: how many first frames the sequence window fills in (their query p50 apart)."""
    wall, cpu, extract, query, hits = [], [], [], [], 0
    for i, img in enumerate(images):
        w0, c0 = time.perf_counter(), time.process_time()
        lset = extractor(img)
        w1 = time.perf_counter()
        answer = loc.query(lset, T0 + 10**12 + i * 33_000_000)
        w2, c2 = time.perf_counter(), time.process_time()
        wall.append((w2 - w0) * 1e3)
        cpu.append((c2 - c0) * 1e3)
        extract.append((w1 - w0) * 1e3)
        query.append((w2 - w1) * 1e3)
        hits += bool(answer and answer.rows and int(answer.rows[0]['keyframe_id']) == truth[i])
    return {
        **percentiles(wall),
        'cpu_ms_p50': float(np.median(cpu)),
        'extract_ms_p50': float(np.median(extract)),
        'query_ms_p50': float(np.median(query)),
        'filling_ms_p50': float(np.median(query[:filling])) if filling else float('nan'),
        'top1': hits / len(images),
        'frames': len(images),
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('--sizes', default='1000,10000', help='map sizes, keyframes (100000: ~2 GB in --dir)')
    ap.add_argument('--frames', type=int, default=60, help='frames timed per row')
    ap.add_argument('--threads', type=int, default=2, help="the extractor's runtime threads")
    ap.add_argument(
        '--runtimes', default='onnxruntime,onnxruntime-int8', help="the extractor's runtimes, one row set each"
    )
    ap.add_argument(
        '--prefilter-k', type=int, default=LOC['prefilter_k'], help="the matcher's prefilter_k (candidates reranked)"
    )
    ap.add_argument(
        '--landmark-query-top',
        default=str(MAP['landmark_query_top']),
        help="the map's landmark_query_top (query landmarks that search the landmark index; 0 = all); "
        'several, comma-separated: rows for each on the same map',
    )
    ap.add_argument(
        '--landmark-index',
        default=MAP['landmark_compressed'],
        help="the map's landmark index, KIND[:INDEX_TOP[:REFINE[:NPROBE[:K_FACTOR]]]], or several (one --sizes): "
        'one map, its index rebuilt for each (e.g. ivfpq-fs,ivfpq-fs-refine:25:SQ8:32:4)',
    )
    ap.add_argument(
        '--similarity',
        default=LOC['similarity'],
        help="the matcher's similarity (S's sets); several, comma-separated: rows for each on the same map",
    )
    ap.add_argument('--sequence', type=int, default=0, help="the matcher's sequence_length (0 = single frame)")
    ap.add_argument(
        '--sequence-prefilter-k',
        type=int,
        default=LOC['sequence_prefilter_k'],
        help="the matcher's sequence_prefilter_k (first-stage candidates reranked with --sequence)",
    )
    ap.add_argument(
        '--sequence-carry',
        default=str(LOC['sequence_carry']),
        help="the matcher's sequence_carry with --sequence; several, comma-separated: rows for each on the same map",
    )
    ap.add_argument(
        '--sequence-acquire-k',
        default=str(LOC['sequence_acquire_k']),
        help="the matcher's sequence_acquire_k with --sequence; several, comma-separated: rows for each, one map",
    )
    ap.add_argument('--dir', default='/tmp/lln_bench_f2a')
    ap.add_argument('--json', action='store_true')
    args = ap.parse_args(argv)
    sizes = sorted(int(s) for s in args.sizes.split(','))
    folder = Path(args.dir)
    shutil.rmtree(folder, ignore_errors=True)
    folder.mkdir(parents=True)

    extractors = {r: Extractor({'num_threads': args.threads, 'runtime': r}) for r in args.runtimes.split(',')}
    extractor = next(iter(extractors.values()))
    rng = np.random.default_rng(0)
    views = photo_views(REAL_KEYFRAMES, 384)
    rows = []
    tops = [int(t) for t in args.landmark_query_top.split(',')]
    indexes = [landmark_index_conf(spec) for spec in args.landmark_index.split(',')]
    if len(indexes) > 1 and len(sizes) > 1:
        sys.exit('bench_frame_to_answer: several --landmark-index entries need one --sizes')
    queries, real_ids = query_images(views, args.frames), None
    for label, index_conf in indexes:
        # one map: the first entry grows it, each later one reopens it and the store rebuilds the
        # landmark index its conf asks for (a file of another kind is rebuilt from the stored rows)
        with MapStore.open(
            folder / 'map.db', model=extractor.model_info, conf={**index_conf, 'landmark_query_top': tops[0]}
        ) as store:
            if real_ids is None:
                real_ids = store.add_many(
                    [extractor(v) for v in views], [divmod(T0 + i * 10**8, 10**9) for i in range(len(views))]
                )
            truth = [real_ids[i % len(views)] for i in range(args.frames)]
            rows += measure_sizes(store, sizes, tops, extractors, queries, truth, args, rng, label)
    if args.json:
        print(json.dumps(rows, indent=1))
    print(table(rows, args))
    return 0


def landmark_index_conf(spec: str) -> tuple[str, dict]:
    """(label, the map conf it names) of a --landmark-index entry KIND[:TOP[:REFINE[:NPROBE[:K]]]]
    (empty or 0 fields: the defaults, but an empty TOP is 0, every landmark, as before TOP was a field;
    K: ivfpq-fs-refine's landmark_k_factor)."""
    kind, top, refine, nprobe, k_factor = (spec.split(':') + [''] * 4)[:5]
    conf = {'landmark_compressed': kind or MAP['landmark_compressed'], 'landmark_index_top': int(top or 0)}
    conf['landmark_refine'] = refine or MAP['landmark_refine']
    conf['landmark_nprobe'] = int(nprobe or MAP['landmark_nprobe'])
    conf['landmark_k_factor'] = int(k_factor or MAP['landmark_k_factor'])
    refined = conf['landmark_compressed'] == 'ivfpq-fs-refine'
    label = conf['landmark_compressed'] + (f' {conf["landmark_refine"]}' if refined else '')
    label += f' top {conf["landmark_index_top"]}' if conf['landmark_index_top'] else ''
    label += f' np{conf["landmark_nprobe"]}' if int(nprobe or 0) else ''
    return label + (f' k{conf["landmark_k_factor"]}' if refined and int(k_factor or 0) else ''), conf


def measure_sizes(store, sizes, tops, extractors, queries, truth, args, rng, label: str) -> list[dict]:
    """The rows of one map (module doc): each size it grows to x query top x runtime, quiet and busy."""
    rows = []
    for size in sizes:
        grow(store, size, rng)
        carries = [int(c) for c in args.sequence_carry.split(',')] if args.sequence else [0]
        acquires = [int(c) for c in args.sequence_acquire_k.split(',')] if args.sequence else [0]
        sims = args.similarity.split(',')
        for top, sim, carry, acquire, (runtime, ex) in itertools.product(
            tops, sims, carries, acquires, extractors.items()
        ):
            loc = Localizer(
                store,
                {
                    'prefilter_k': args.prefilter_k,
                    'sequence_length': args.sequence,
                    'sequence_prefilter_k': args.sequence_prefilter_k,
                    'sequence_carry': carry,
                    'sequence_acquire_k': acquire,
                    'similarity': sim,
                },
            )
            store._landmarks.conf['landmark_query_top'] = top  # the one map, searched with each value
            loc.query(ex(queries[0]), T0)  # warm with this row's settings (builds what the open left lazy)
            for load in (False, True):
                start_load = os.getloadavg()[0]
                with competing_load(load):
                    # the stamps restart (out of order, or a gap after the warm-up): the window fills again
                    r = measure(ex, loc, queries, truth, max(args.sequence - 1, 0))
                row = {'keyframes': len(store), 'runtime': ex.model_info['runtime'], 'competing': load}
                row |= {'index': label, 'query_top': top, 'similarity': sim, 'carry': carry, 'acquire_k': acquire}
                rows.append({**row, 'load_avg': start_load, **r})
    return rows


def table(rows: list[dict], args) -> str:
    lines = [
        f'frame to answer, 384x288, {args.threads} runtime threads, prefilter_k {args.prefilter_k}, '
        f'sequence_length {args.sequence}'
        + (f' (sequence_prefilter_k {args.sequence_prefilter_k})' if args.sequence else '')
        + ', '
        f'{args.frames} frames per row ({os.cpu_count()} cores)',
        f'{"keyframes":>9} {"landmark index":>28} {"runtime":>16} {"q-top":>5} {"S":>6} {"carry":>5} {"acq-k":>5} '
        f'{"beside":>10} {"load":>5} {"p50 ms":>7} {"p90 ms":>7} {"p99 ms":>7} {"cpu ms":>7} {"extract":>8} '
        f'{"query":>7} {"filling":>7} {"top-1":>6} {"p50/quiet":>9}',
    ]
    key = ('index', 'keyframes', 'runtime', 'query_top', 'similarity', 'carry', 'acquire_k')
    quiet = {tuple(r[k] for k in key): r['p50'] for r in rows if not r['competing']}
    for r in rows:
        lines.append(
            f'{r["keyframes"]:>9} {r["index"]:>28} {r["runtime"]:>16} {r["query_top"]:>5} {r["similarity"]:>6} '
            f'{r["carry"]:>5} '
            f'{r["acquire_k"]:>5} {"1 busy" if r["competing"] else "nothing":>10} '
            f'{r["load_avg"]:>5.1f} '
            f'{r["p50"]:>7.1f} {r["p90"]:>7.1f} {r["p99"]:>7.1f} {r["cpu_ms_p50"]:>7.1f} '
            f'{r["extract_ms_p50"]:>8.1f} {r["query_ms_p50"]:>7.1f} {r["filling_ms_p50"]:>7.1f} {r["top1"]:>6.2f} '
            f'{r["p50"] / quiet[tuple(r[k] for k in key)]:>9.2f}'
        )
    return '\n'.join(lines)


if __name__ == '__main__':
    sys.exit(main())
