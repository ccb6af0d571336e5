"""Query latency of a map on a real Milvus server beside the SQLite map, same keyframes, same queries.

    .venv/bin/python test/milvus_loopback.py --server -- nice -n 10 .venv/bin/python \\
        bench/bench_milvus_server.py [--sizes 1000,10000] [--queries 200] [--profile]

(the server only runs in a loopback-only network namespace: test/milvus_loopback.py says why; this
script refuses to run outside one, and talks to 127.0.0.1 only.) Grows an SQLite map (in --dir) and a
map on the server ($LLN_MILVUS_URI, database lln_bench, dropped at the end) with the same synthetic
keyframes (bench/bench_map.py's: n=50, D=192, a 12x9 grid), then at each size times the same noisy
revisit queries on, interleaved so that load from other processes hits them alike:

  sqlite           SQLiteMapStore, the shipped defaults (prefilter landmarks, prefilter_k 100, k 5)
  milvus           MilvusMapStore reopened as a node would open it (a fresh open reads every row:
                   landmark index, integrity check, read cache), the shipped defaults
  milvus no cache  the same open store with an empty read cache of 0 bytes (as conf cache_mb 0):
                   every query fetches its candidates' rows from the server (one query by primary
                   key), the path of a map larger than the cache

and prints p50 / p95 ms, the ratio to SQLite's p50, top-1 agreement, the open time (and how much of
it the integrity check took), and the load average before and after. --profile prints where the
no-cache path's time goes (cProfile, the top functions by cumulative time).
"""

from __future__ import annotations

import argparse
import copy
import cProfile
import io
import os
import pstats
import shutil
import sys
import time
from pathlib import Path

# one BLAS / OpenMP thread per query, as bench_map.py measures (read before numpy loads)
for _var in ('OPENBLAS_NUM_THREADS', 'OMP_NUM_THREADS', 'MKL_NUM_THREADS'):
    os.environ.setdefault(_var, '1')
_HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(_HERE))
sys.path.insert(0, str(_HERE.parent))
sys.path.insert(0, str(_HERE.parent / 'test'))
import numpy as np  # noqa: E402
from bench_map import MODEL, synthetic_set  # noqa: E402
from milvus_loopback import only_loopback  # noqa: E402

from lln_ros.mapstore import MapStore  # noqa: E402
from lln_ros.mapstore.milvus import RowCache, row_problem  # noqa: E402


def load() -> str:
    return ' '.join(f'{v:.1f}' for v in os.getloadavg())


def integrity_s(store) -> float:
    """The integrity check's own time over every cached row (what the open adds to its read)."""
    rows = list(store._cache._rows.values())
    dim = int(store.model['descriptor_dim'])
    t = time.perf_counter()
    bad = [row_problem(r, dim) for r in rows]
    took = time.perf_counter() - t
    assert not any(bad) and len(rows) == len(store), (len(rows), len(store))
    return took


def measure(stores: dict, truth: dict, rng, count: int) -> dict:
    ids = sorted(truth)
    picks = rng.choice(ids, count)
    times = {name: [] for name in stores}
    top1 = {name: 0 for name in stores}
    for kid in picks:
        q = synthetic_set(rng, truth[int(kid)])
        for name, store in stores.items():
            t = time.perf_counter()
            found = store.query(q, k=5)
            times[name].append(time.perf_counter() - t)
            top1[name] += bool(found) and found[0].keyframe_id == int(kid)
    return {
        name: {
            'p50': float(np.percentile(np.array(ts) * 1000, 50)),
            'p95': float(np.percentile(np.array(ts) * 1000, 95)),
            'top1': top1[name] / count,
        }
        for name, ts in times.items()
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    ap.add_argument('--sizes', default='1000,10000')
    ap.add_argument('--queries', type=int, default=200)
    ap.add_argument('--dir', default='/tmp/lln_bench_milvus_server')
    ap.add_argument('--uri', default=os.environ.get('LLN_MILVUS_URI', ''))
    ap.add_argument('--profile', action='store_true')
    args = ap.parse_args(argv)
    if not only_loopback() or not args.uri.startswith('milvus://127.0.0.1:'):
        ap.error('run under test/milvus_loopback.py --server (a loopback-only namespace, LLN_MILVUS_URI on 127.0.0.1)')
    work = Path(args.dir)
    shutil.rmtree(work, ignore_errors=True)
    work.mkdir(parents=True)
    name = f'bms_{os.getpid()}'
    uris = {'sqlite': str(work / 'map.db'), 'milvus': f'{args.uri}/lln_bench?map={name}'}
    rng = np.random.default_rng(0)
    # the Milvus writer keeps no read cache: the stores measured are opened afresh at each size
    writers = {
        k: MapStore.open(u, model=MODEL, conf={'cache_mb': 0} if k == 'milvus' else None) for k, u in uris.items()
    }
    truth, rows = {}, []
    print(f'load average at start: {load()} ({os.cpu_count()} cores)', file=sys.stderr)
    try:
        for size in sorted(int(s) for s in args.sizes.split(',')):
            t = {'sqlite': 0.0, 'milvus': 0.0}
            while len(writers['sqlite']) < size:
                sets = [synthetic_set(rng) for _ in range(min(1000, size - len(writers['sqlite'])))]
                stamps = [(len(truth) + i, 0) for i in range(len(sets))]
                for k, store in writers.items():
                    start = time.perf_counter()
                    got = store.add_many(sets, stamps)
                    t[k] += time.perf_counter() - start
                truth.update(zip(got, sets))
            for store in writers.values():
                store.save()
            print(f'{size} keyframes stored (add_many s: {t})', file=sys.stderr)
            start = time.perf_counter()
            milvus = MapStore.open(uris['milvus'], create=False)
            open_s = time.perf_counter() - start
            check_s = integrity_s(milvus)
            # the same store (one open: it trains the landmark index), its read cache swapped for none
            bare = copy.copy(milvus)
            bare._cache = RowCache(0)
            stores = {'sqlite': writers['sqlite'], 'milvus': milvus, 'milvus no cache': bare}
            before = load()
            measure(stores, truth, rng, 10)  # warm-up
            stats = measure(stores, truth, rng, args.queries)
            rows.append((size, stats, open_s, check_s, before, load()))
            print(f'{size} keyframes measured: {stats}', file=sys.stderr)
            if args.profile:
                for what, store in (('milvus', milvus), ('milvus no cache', bare)):
                    prof = cProfile.Profile()
                    prof.enable()
                    measure({what: store}, truth, rng, 30)
                    prof.disable()
                    out = io.StringIO()
                    pstats.Stats(prof, stream=out).sort_stats('cumulative').print_stats(22)
                    print(f'--- {what}, {size} keyframes, 30 queries\n{out.getvalue()[-5000:]}', file=sys.stderr)
            milvus.close()
    finally:
        for store in writers.values():
            store.close()
        from pymilvus import MilvusClient

        from lln_ros.mapstore.milvus import parse_uri

        where = parse_uri(uris['milvus'])
        client = MilvusClient(uri=where['uri'], db_name=where['db_name'])
        for c in client.list_collections():
            if c.startswith(name + '_'):
                client.drop_collection(c)
        client.close()
        shutil.rmtree(work, ignore_errors=True)
        from lln_ros.mapstore.milvus import MilvusMapStore
        from lln_ros.mapstore.milvus_mixins import landmark_file

        kept = landmark_file(where['label'], MilvusMapStore.default_conf['landmark_dir'])
        if kept and os.path.exists(kept):  # this machine's landmark index file of the dropped map
            os.remove(kept)
    print(f'n=50, D=192, {args.queries} queries per size, prefilter landmarks (default), k=5, {os.cpu_count()} cores')
    print('| keyframes | backend | p50 ms | p95 ms | p50 / SQLite p50 | top-1 | load before -> after |')
    print('|---|---|---|---|---|---|---|')
    for size, stats, open_s, check_s, before, after in rows:
        base = stats['sqlite']['p50']
        for backend, s in stats.items():
            print(
                f'| {size:,} | {backend} | {s["p50"]:.1f} | {s["p95"]:.1f} | {s["p50"] / base:.2f}x '
                f'| {s["top1"]:.2f} | {before} -> {after} |'
            )
    for size, _, open_s, check_s, *_ in rows:
        print(f'{size:,} keyframes: Milvus open {open_s:.1f} s, of which the integrity check {check_s * 1000:.1f} ms')
    return 0


if __name__ == '__main__':
    sys.exit(main())
