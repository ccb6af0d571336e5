"""Map server at scale: insert rate, query latency, memory, disk and cold start vs map size.

    python bench/bench_map.py [--sizes 1000,10000,100000] [--dir /tmp/lln_bench_map] [--threads 1]
                              [--backend sqlite,milvus-lite,milvus] [--uri milvus://HOST:PORT[/db]]
                              [--index-threshold 50000] [--plot out/bench_map.png] [--json]

--backend: one or more of sqlite (the embedded map), milvus-lite (Milvus Lite in --dir) and milvus (a
Milvus server at --uri, default $LLN_MILVUS_URI; the map is database lln_bench, map bench_<pid>,
dropped at the end), each measured in turn in this process, then compared (query p50 / SQLite's).
A real server here, confined to loopback (test/milvus_loopback.py says why):

    .venv/bin/python test/milvus_loopback.py --server -- .venv/bin/python bench/bench_map.py \
        --backend sqlite,milvus-lite,milvus --sizes 1000,10000

One map grows through every size in --sizes (plus the in-between steps of the plot). Synthetic
landmark sets with the default model's shapes: n=50 unit descriptors of D=192 (efficientnet_lite0/
stage6), a 12x9 grid at 384x288. Queries are noisy views of stored keyframes (
a perturbation of norm 0.3 added to each unit vector, renormalised), answered as the matcher answers them: first stage
top prefilter_k (the shipped default), reranked by the landmark similarity S, k=5 -- with every first stage of
--prefilters on the same queries of the same run (landmarks = the shipped default, holistic = the paper's).

At each table size:
  insert/s (bulk)   add_many of 1000 keyframes per transaction, while growing the map
  insert/s (online) add() one keyframe per transaction (fsync each), 200 of them, as the node does,
                    right after the bulk load and the queries; "slowest 50" is the slowest window of 50
  p50 / p95 / p99   query latency per first stage, 200 queries, warm (in the growing process)
  exhaustive p50    prefilter_k 0 (every keyframe fetched and reranked, what Nordland-like routes
                    need, see docs/results.md), 20 queries, maps up to --exhaustive-max keyframes
  top-1             the query's source keyframe ranked first (sanity: the map answers)
  recall@30         IVF holistic top 30 vs exact brute force (1 by construction while exact)
  cold start s      MapStore.open in a fresh process: verify=True (quick_check reads the file) and
                    verify=False; the page cache is warm (the file was just written)
  RSS MB            resident memory of that fresh process after open + 50 queries, and the part
                    of it that is the global index (N x D x 4 bytes)
  lm index MB       the landmark index file (<map>.landmarks; 0 while exact, rebuilt at open)
  KB/keyframe       .db + WAL + .landmarks bytes after a checkpoint, per keyframe
The recall of the compressed landmark index against exact search is measured on descriptors of
real images by bench/bench_landmark_index.py (these synthetic descriptors have no neighbour
structure worth measuring).
"""

from __future__ import annotations

import argparse
import builtins
import functools
import json
import os
import platform
import resource
import shutil
import subprocess
import sys
import time
from pathlib import Path

# BLAS and OpenMP (FAISS) size their thread pools at import: take --threads before numpy loads. On
# this shared 2-core machine one thread per query was ~5x faster than the default (46 -> 9 ms/query
# at 1k keyframes, load ~8): spinning workers wait for cores other processes hold
_threads = sys.argv[sys.argv.index('--threads') + 1] if '--threads' in sys.argv[:-1] else '1'
for _var in ('OPENBLAS_NUM_THREADS', 'OMP_NUM_THREADS', 'MKL_NUM_THREADS'):
    os.environ[_var] = _threads

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from lln_ros.core.landmarks import LandmarkSet  # noqa: E402
from lln_ros.mapstore import MapStore  # noqa: E402

N_LANDMARKS, DIM, ROWS, COLS = 50, 192, 9, 12
SPACE = f'efficientnet_lite0/stage6/{DIM}'
MODEL = {'descriptor_space': SPACE, 'descriptor_dim': DIM}
PLOT_STEPS = (1_000, 2_000, 5_000, 10_000, 20_000, 50_000, 100_000)


def unit(x: np.ndarray) -> np.ndarray:
    return (x / np.linalg.norm(x, axis=-1, keepdims=True)).astype(np.float32)


def synthetic_set(rng, base: LandmarkSet | None = None, noise: float = 0.3) -> LandmarkSet:
    if base is None:
        glob, desc = unit(rng.standard_normal(DIM)), unit(rng.standard_normal((N_LANDMARKS, DIM)))
        flat = rng.choice(ROWS * COLS, N_LANDMARKS, replace=False)
        cells = np.stack([flat % COLS, flat // COLS], axis=1).astype(np.int32)
    else:
        glob = unit(base.global_descriptor + noise * unit(rng.standard_normal(DIM)))
        desc = unit(base.descriptors + noise * unit(rng.standard_normal(base.descriptors.shape)))
        cells = base.cells.copy()
    cell = np.array([384 / COLS, 288 / ROWS], np.float32)
    return LandmarkSet(
        global_descriptor=glob,
        descriptors=desc,
        cells=cells,
        centers=((cells + 0.5) * cell).astype(np.float32),
        scores=np.sort(rng.random(N_LANDMARKS).astype(np.float32))[::-1].copy(),
        cell_size=cell,
        image_size=np.array([384, 288], np.float32),
        grid=(ROWS, COLS),
        activation=None,
        descriptor_space=SPACE,
    )


def rss_mb() -> float:
    with open('/proc/self/status') as f:
        for line in f:
            if line.startswith('VmRSS:'):
                return int(line.split()[1]) / 1024
    return float('nan')


def cold_start(uri: str, verify: bool, conf: dict | None, queries: int = 50) -> dict:
    """Open the map in a fresh process; time the open, then RSS after `queries` queries."""
    code = f"""
import json, time, numpy as np, sys
sys.path.insert(0, {str(Path(__file__).resolve().parent)!r})
from bench_map import rss_mb, synthetic_set
from lln_ros.mapstore import MapStore
rng = np.random.default_rng(7)
before = rss_mb()
t = time.perf_counter()
store = MapStore.open({uri!r}, create=False, verify={verify}, conf={conf!r})
opened = time.perf_counter() - t
ids = store.ids()
for i in rng.choice(len(ids), {queries}):
    store.query(synthetic_set(rng, store.get(int(ids[i]))), k=5)
print(json.dumps({{'open_s': opened, 'rss_before_mb': before, 'rss_mb': rss_mb()}}))
store.close()
"""
    env = {
        **os.environ,
        'PYTHONPATH': os.pathsep.join(
            p for p in (str(Path(__file__).resolve().parents[1]), os.environ.get('PYTHONPATH')) if p
        ),
    }
    out = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True, env=env)
    if out.returncode:  # Milvus Lite: the builder's embedded server still holds the directory lock
        print(f'cold start of {uri} failed:\n{out.stderr[-1500:]}', file=sys.stderr)
        return {'open_s': float('nan'), 'rss_before_mb': float('nan'), 'rss_mb': float('nan')}
    return json.loads(out.stdout.strip().splitlines()[-1])


def query_stats(store, rng, count: int, exhaustive: int = 0, prefilters=('landmarks', 'holistic')) -> dict:
    """Latency, top-1 and holistic recall@30 vs brute force over `count` noisy revisits; with
    exhaustive > 0, the median latency of that many prefilter_k 0 queries too."""
    ids = np.asarray(store.ids())
    picks = rng.choice(len(ids), count, replace=len(ids) < count)
    truth = {int(i): store.get(int(ids[i])) for i in picks}
    globals_ = None
    if hasattr(store, '_index') and store._index is not None and store._index.kind != 'exact':
        globals_ = store._index.index  # recall: compare against exact search on the same vectors
    times = {pf: [] for pf in prefilters}
    top1 = {pf: 0 for pf in prefilters}
    recall = []
    for i in picks:
        q = synthetic_set(rng, truth[int(i)])
        for pf in prefilters:  # interleaved, so load from other processes hits every first stage alike
            t = time.perf_counter()
            found = store.query(q, k=5, prefilter=pf)  # the shipped prefilter_k
            times[pf].append(time.perf_counter() - t)
            top1[pf] += bool(found) and found[0].keyframe_id == int(ids[i])
        if globals_ is not None and len(recall) < 100:
            approx = set(store._index.search(q.global_descriptor, 30)[1].tolist())
            exact = _exact_top(store, q.global_descriptor, 30)
            recall.append(len(approx & exact) / len(exact))
    every = []
    for i in picks[:exhaustive]:
        q = synthetic_set(rng, truth[int(i)])
        t = time.perf_counter()
        store.query(q, prefilter_k=0, k=5)
        every.append(time.perf_counter() - t)
    out = {
        'recall30': float(np.mean(recall)) if recall else None,
        'exhaustive_p50_ms': float(np.median(every)) * 1000 if every else None,
    }
    for n, pf in enumerate(prefilters):
        ms = np.array(times[pf]) * 1000
        pre = '' if n == 0 else f'{pf}_'  # the first (the default) keeps the plain keys
        out.update(
            {
                f'{pre}p50_ms': float(np.percentile(ms, 50)),
                f'{pre}p95_ms': float(np.percentile(ms, 95)),
                f'{pre}p99_ms': float(np.percentile(ms, 99)),
                f'{pre}top1': top1[pf] / count,
            }
        )
    return out


def _exact_top(store, q: np.ndarray, k: int) -> set:
    import faiss

    index = store._index.index
    if not hasattr(store, '_exact_cache') or store._exact_cache[0] != index.ntotal:
        lists, x, ids = index.invlists, [], []
        for c in range(lists.nlist):
            size = lists.list_size(c)
            if size:
                ids.append(faiss.rev_swig_ptr(lists.get_ids(c), size).copy())
                x.append(
                    faiss.rev_swig_ptr(lists.get_codes(c), size * DIM * 4).view(np.float32).reshape(size, DIM).copy()
                )
        store._exact_cache = (index.ntotal, np.concatenate(x), np.concatenate(ids))
    _, x, ids = store._exact_cache
    return set(ids[np.argsort(-(x @ q))[:k]].tolist())


def dir_bytes(path: Path) -> int:
    return sum(f.stat().st_size for f in path.rglob('*') if f.is_file() and not f.is_symlink())


def bytes_on_disk(uri: str) -> int:
    """Bytes of the map on disk; a Milvus server's whole data dir ($LLN_MILVUS_DATA_DIR, without its
    binaries) when it is known (NaN otherwise): main() subtracts what it held before the map."""
    if uri.startswith('milvus://'):
        data = os.environ.get('LLN_MILVUS_DATA_DIR')
        return dir_bytes(Path(data) / 'data') if data else float('nan')
    path = Path(uri.split('://', 1)[-1].split('?')[0]) if '://' in uri else Path(uri)
    if path.is_dir():
        return sum(f.stat().st_size for f in path.rglob('*') if f.is_file())
    return sum(Path(str(path) + s).stat().st_size for s in ('', '-wal', '.landmarks') if Path(str(path) + s).exists())


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    ap.add_argument('--sizes', default='1000,10000,100000')
    ap.add_argument('--dir', default='/tmp/lln_bench_map', help='where the map is built (deleted first)')
    ap.add_argument('--backend', default='sqlite', help='comma-separated: sqlite, milvus-lite, milvus (a server)')
    ap.add_argument(
        '--uri',
        default=os.environ.get('LLN_MILVUS_URI', ''),
        help='--backend milvus: the server, milvus://host:port[/database] (default $LLN_MILVUS_URI)',
    )
    ap.add_argument('--plot', default='out/bench_map.png', help="latency-vs-size plot ('' = none)")
    ap.add_argument('--queries', type=int, default=200)
    ap.add_argument('--threads', default='1', help='BLAS / OpenMP threads (read before numpy loads)')
    ap.add_argument(
        '--index-threshold',
        type=int,
        default=None,
        help="SQLite backend: keyframes above which the global index is IVF (default: the store's)",
    )
    ap.add_argument(
        '--exhaustive-max',
        type=int,
        default=10_000,
        help='largest map also timed with prefilter_k 0 (every keyframe reranked)',
    )
    ap.add_argument(
        '--prefilters',
        default='landmarks,holistic',
        help='first stages timed on the same queries; the first is the p50/p99/top-1 columns',
    )
    ap.add_argument('--json', action='store_true')
    args = ap.parse_args(argv)
    args.prefilter_list = [p for p in args.prefilters.split(',') if p]
    backends = args.backend.split(',')
    bad = [b for b in backends if b not in ('sqlite', 'milvus-lite', 'milvus')]
    if bad or ('milvus' in backends and not args.uri.startswith('milvus://')):
        ap.error(
            f'--backend: unknown {bad}'
            if bad
            else '--backend milvus needs --uri milvus://host:port (or $LLN_MILVUS_URI)'
        )
    results = {}
    for backend in backends:
        results[backend] = run(args, backend)
        print_table(args, backend, results[backend])
    if len(backends) > 1:
        print_comparison(results)
    if args.json:
        print(json.dumps(results))
    if args.plot:
        plot(args, results)
    return 0


def run(args, backend: str) -> dict:
    """Grow one map of this backend through --sizes; measure at each (see the module docstring)."""
    sizes = sorted(int(s) for s in args.sizes.split(','))
    steps = sorted(set(sizes) | {s for s in PLOT_STEPS if s <= sizes[-1]})
    work = Path(args.dir)
    shutil.rmtree(work, ignore_errors=True)
    work.mkdir(parents=True)
    server_map = f'bench_{os.getpid()}'
    uri = {
        'sqlite': str(work / 'map.db'),
        'milvus-lite': f'milvus-lite://{work}/map.db',
        'milvus': f'{args.uri.split("?")[0].rstrip("/")}{"" if urlpath(args.uri) else "/lln_bench"}?map={server_map}',
    }[backend]
    disk_before = bytes_on_disk(uri) if backend == 'milvus' else 0
    rng = np.random.default_rng(0)
    rows, curve = [], []
    conf = {'index_threshold': args.index_threshold} if args.index_threshold else None
    store = MapStore.open(uri, model=MODEL, conf=conf)
    bulk_time, bulk_count = 0.0, 0
    for step in steps:
        while len(store) < step:
            batch = min(1000, step - len(store))
            sets = [synthetic_set(rng) for _ in range(batch)]
            t = time.perf_counter()
            store.add_many(sets, [(len(store) + i, 0) for i in range(batch)])
            bulk_time += time.perf_counter() - t
            bulk_count += batch
        stats = query_stats(
            store,
            rng,
            args.queries if step in sizes else 50,
            20 if step in sizes and step <= args.exhaustive_max else 0,
            args.prefilter_list,
        )
        curve.append({'keyframes': step, **stats})
        print(f'{step:>7} keyframes: p50 {stats["p50_ms"]:.1f} ms, p99 {stats["p99_ms"]:.1f} ms', file=sys.stderr)
        if step not in sizes:
            continue
        online = [synthetic_set(rng) for _ in range(200)]
        stamps = [time.perf_counter()]
        new = []
        for s in online:
            new.append(store.add(s, (0, 0)))
            stamps.append(time.perf_counter())
        online_rate = len(online) / (stamps[-1] - stamps[0])
        slowest = min(50 / (stamps[i + 50] - stamps[i]) for i in range(0, len(online) - 49, 10))
        store.delete(new)  # keep the map at exactly `step` keyframes
        store.save()
        disk = bytes_on_disk(uri) - disk_before
        store.close()
        cold = cold_start(uri, verify=True, conf=conf)
        cold_fast = cold_start(uri, verify=False, conf=conf)
        store = MapStore.open(uri, create=False, verify=False, conf=conf)
        rows.append(
            {
                'keyframes': step,
                'insert_bulk_per_s': bulk_count / bulk_time,
                'insert_online_per_s': online_rate,
                'insert_online_slowest50_per_s': slowest,
                **stats,
                'cold_start_s': cold['open_s'],
                'cold_start_noverify_s': cold_fast['open_s'],
                'rss_mb': cold['rss_mb'],
                'rss_growth_mb': cold['rss_mb'] - cold['rss_before_mb'],
                'index_mb': step * DIM * 4 / 2**20,
                'kb_per_keyframe': disk / step / 1000,
                'index': store.info().get('index'),
                'landmark_index': store.info().get('landmark_index'),
                'landmark_index_mb': store.info().get('landmark_index_bytes', 0) / 2**20,
            }
        )
        # the table so far, on stderr: a run stopped before the largest size still reports the rest
        partial = {'uri': uri, 'cpus': os.cpu_count(), 'load': os.getloadavg()}
        print_table(args, backend, {'info': partial, 'rows': rows}, file=sys.stderr)
    store.close()
    if backend == 'milvus':  # an idle server's CPU climbs with every collection left loaded
        from pymilvus import MilvusClient

        where = __import__('lln_ros.mapstore.milvus', fromlist=['parse_uri']).parse_uri(uri)
        client = MilvusClient(uri=where['uri'], db_name=where['db_name'])
        for name in client.list_collections():
            if name.startswith(server_map + '_'):
                client.drop_collection(name)
        client.close()
    shutil.rmtree(work, ignore_errors=True)
    info = {
        'backend': backend,
        'uri': uri,
        'threads': args.threads,
        'n': N_LANDMARKS,
        'D': DIM,
        'machine': platform.processor() or platform.machine(),
        'cpus': os.cpu_count(),
        'load': os.getloadavg(),
        'max_rss_mb_builder': resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
    }
    return {'info': info, 'rows': rows, 'curve': curve}


def urlpath(uri: str) -> str:
    return uri.split('://', 1)[-1].split('?')[0].partition('/')[2].strip('/')


def print_table(args, backend: str, result: dict, file=None) -> None:
    info, rows = result['info'], result['rows']
    print = functools.partial(builtins.print, file=file or sys.stdout, flush=True)
    print(
        f'backend {backend} ({info["uri"]}), n={N_LANDMARKS}, D={DIM}, {info["cpus"]} CPUs, '
        f'load after it {", ".join(f"{v:.2f}" for v in info["load"])}'
    )
    first, others = args.prefilter_list[0], args.prefilter_list[1:]
    head = (
        'keyframes',
        'index',
        'lm index',
        'ins/s bulk',
        'ins/s online',
        'slowest 50 /s',
        f'{first} p50 ms',
        f'{first} p95 ms',
        f'{first} p99 ms',
        *[f'{pf} {what}' for pf in others for what in ('p50 ms', 'p95 ms', 'p99 ms')],
        'exhaustive p50 ms',
        f'{first} top-1',
        *[f'{pf} top-1' for pf in others],
        'recall@30',
        'cold s',
        'cold s (no verify)',
        'RSS MB',
        'RSS growth MB',
        'index MB',
        'lm index MB',
        'KB/kf',
    )
    print('| ' + ' | '.join(head) + ' |')
    print('|' + '---|' * len(head))
    for r in rows:
        every = f'{r["exhaustive_p50_ms"]:.0f}' if r['exhaustive_p50_ms'] is not None else '-'
        recall = (
            f'{r["recall30"]:.2f}'
            if r['recall30'] is not None
            else ('1 (exact)' if r['index'] in ('exact', 'FLAT') else 'n/a')
        )
        extra = ''.join(
            f'| {r[f"{pf}_p50_ms"]:.1f} | {r[f"{pf}_p95_ms"]:.1f} | {r[f"{pf}_p99_ms"]:.1f} ' for pf in others
        )
        extra_top = ''.join(f'| {r[f"{pf}_top1"]:.2f} ' for pf in others)
        print(
            f'| {r["keyframes"]:,} | {r["index"]} | {r.get("landmark_index")} | {r["insert_bulk_per_s"]:.0f} '
            f'| {r["insert_online_per_s"]:.0f} | {r["insert_online_slowest50_per_s"]:.0f} | {r["p50_ms"]:.1f} '
            f'| {r["p95_ms"]:.1f} | {r["p99_ms"]:.1f} {extra}| {every} | {r["top1"]:.2f} {extra_top}| {recall} '
            f'| {r["cold_start_s"]:.2f} | {r["cold_start_noverify_s"]:.2f} '
            f'| {r["rss_mb"]:.0f} | {r["rss_growth_mb"]:.0f} | {r["index_mb"]:.0f} '
            f'| {r["landmark_index_mb"]:.0f} | {r["kb_per_keyframe"]:.1f} |'
        )
    print()


def print_comparison(results: dict) -> None:
    """Query p50 of every backend over SQLite's, and online inserts, at each size."""
    base = {r['keyframes']: r for r in results.get('sqlite', {'rows': []})['rows']}
    print('| backend | keyframes | p50 ms | p50 / SQLite p50 | ins/s online | slowest 50 /s | load after |')
    print('|---|---|---|---|---|---|---|')
    for backend, result in results.items():
        for r in result['rows']:
            ratio = r['p50_ms'] / base[r['keyframes']]['p50_ms'] if r['keyframes'] in base else float('nan')
            print(
                f'| {backend} | {r["keyframes"]:,} | {r["p50_ms"]:.1f} | {ratio:.1f}x | {r["insert_online_per_s"]:.0f} '
                f'| {r["insert_online_slowest50_per_s"]:.0f} | {result["info"]["load"][0]:.1f} |'
            )


def plot(args, results: dict) -> None:
    import matplotlib

    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    for backend, result in results.items():
        n = [c['keyframes'] for c in result['curve']]
        (line,) = ax.plot(n, [c['p50_ms'] for c in result['curve']], 'o-', label=f'{backend} p50')
        ax.plot(n, [c['p99_ms'] for c in result['curve']], 's--', color=line.get_color(), label=f'{backend} p99')
    ax.set_xscale('log')
    ax.set_yscale('log')
    ax.set_xlabel('keyframes in the map')
    from lln_ros.core.retrieval import default_conf as first_stage

    ax.set_ylabel(f'query latency, ms ({args.prefilter_list[0]} top {first_stage["prefilter_k"]} + rerank)')
    ax.set_title(f'map backends, n={N_LANDMARKS}, D={DIM}')
    ax.grid(True, which='both', alpha=0.3)
    ax.legend(fontsize=8)
    Path(args.plot).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.plot, dpi=120, bbox_inches='tight')
    print(f'plot: {args.plot}', file=sys.stderr)


if __name__ == '__main__':
    sys.exit(main())
