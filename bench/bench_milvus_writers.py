"""Many writers on one map (issue 29): insert and query rates with 1, 2 and 4 writer processes on a
real Milvus server beside one SQLite map, in one run, and a soak run that counts every keyframe.

    .venv/bin/python test/milvus_loopback.py -- .venv/bin/python bench/bench_milvus_writers.py \\
        [--writers 1,2,4] [--keyframes 150] [--base 1000] [--soak-s 600] [--soak-writers 4]

(a loopback-only network namespace: test/milvus_loopback.py says why; this script starts and restarts
its own server in it, and talks to 127.0.0.1 only.)

**Rates.** For each backend and each writer count N: a fresh map of --base keyframes (bench_map.py's
synthetic sets: n=50, D=192), then N writer processes (spawn) each store --keyframes keyframes one
at a time as a matcher in mapping mode does (add, then set_origin in its own session), while this
process queries the map with noisy revisits of the base keyframes (shipped query defaults, k 5).
Printed: keyframes/s over all writers, insert p50 ms, query p50 / p95 ms during the writes, the
query p50 over the same backend's 1-writer p50 (issue 29's target: <= 3x at 4 writers), top-1, and
whether every acknowledged keyframe is stored once.

**Soak.** --soak-writers writers store keyframes for --soak-s seconds into one server map; at a third
of the time one of them is killed with SIGKILL, at two thirds the server is restarted (SIGTERM, then
start; the writers get MapErrors meanwhile and go on). Afterwards every acknowledged keyframe is
looked up by its checksum (robot, session, seq): lost = acknowledged but absent, duplicated = a
(robot, session, seq) or an id stored twice (ids counted straight from the server, Strong).
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import os
import queue
import shutil
import signal
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path

for _var in ('OPENBLAS_NUM_THREADS', 'OMP_NUM_THREADS', 'MKL_NUM_THREADS'):
    os.environ.setdefault(_var, '1')  # one BLAS thread per process, as bench_map.py measures
_HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(_HERE))
sys.path.insert(0, str(_HERE.parent))
sys.path.insert(0, str(_HERE.parent / 'test'))
import numpy as np  # noqa: E402
from bench_map import MODEL, synthetic_set  # noqa: E402
from milvus_loopback import LoopbackMilvus, only_loopback  # noqa: E402

from lln_ros.errors import MapError  # noqa: E402
from lln_ros.mapstore import MapStore  # noqa: E402

WAIT_S = 300  # bounds a wait for a process, never a measured time


def load() -> str:
    return ' '.join(f'{v:.1f}' for v in os.getloadavg())


def writer(uri: str, index: int, count: int, seconds: float, start, out) -> None:
    """One writer process: a session of robot w{index}, then keyframes one at a time (count of them,
    or until `seconds` have passed); each acknowledged one is reported as ('acked', index, id,
    session id, seq, insert ms). MapErrors (the server down) are counted and the writer goes on."""
    sys.path.insert(0, str(_HERE))
    rng = np.random.default_rng(1000 + index)
    errors = 0
    with MapStore.open(uri, model=MODEL, conf={'refresh_s': 1.0}) as store:
        while True:
            try:
                session = store.start_session(f'w{index}')
                break
            except MapError:
                errors += 1
                time.sleep(0.5)
        start.wait(WAIT_S)
        t_end, seq = time.monotonic() + seconds, 0
        while (seq < count) if count else (time.monotonic() < t_end):
            lset = synthetic_set(rng)
            t = time.perf_counter()
            try:
                kid = store.add(lset, (index, seq))
                store.set_origin(kid, session.id, seq + 1)  # a session numbers its keyframes from 1
            except MapError:  # not acknowledged: a later row may hold it unacknowledged, never twice acked
                errors += 1
                time.sleep(0.5)
                seq += 1
                continue
            out.put(('acked', index, kid, session.id, seq + 1, (time.perf_counter() - t) * 1e3))
            seq += 1
    out.put(('done', index, errors))


def start_writers(uri: str, n: int, count: int, seconds: float):
    """n writer processes, each with a queue of its own (one killed while it sends may leave its
    queue unusable, never the others')."""
    ctx = mp.get_context('spawn')
    start, outs = ctx.Barrier(n + 1), [ctx.Queue() for _ in range(n)]
    procs = [ctx.Process(target=writer, args=(uri, i, count, seconds, start, outs[i])) for i in range(n)]
    for p in procs:
        p.start()
    start.wait(WAIT_S)  # every writer has opened the map and started its session
    return procs, outs


def drain(outs: list, acked: list, done: dict, wait_s: float = 0.0, skip=()) -> None:
    """Every message waiting in the writers' queues (but those in skip), after wait_s."""
    time.sleep(wait_s)
    for i, out in enumerate(outs):
        while i not in skip:
            try:
                msg = out.get_nowait()
            except queue.Empty:
                break
            if msg[0] == 'acked':
                acked.append(msg[1:])
            else:
                done[msg[1]] = msg[2]


def rates(uri: str, n: int, count: int, base: int, rng) -> dict:
    """One backend, n writers (module doc, Rates)."""
    with MapStore.open(uri, model=MODEL) as seed:
        truth = [synthetic_set(rng) for _ in range(base)]
        ids = seed.add_many(truth, [(99, i) for i in range(base)])
    reader = MapStore.open(uri, create=False)
    for kid, lset in list(zip(ids, truth))[:10]:
        reader.query(synthetic_set(rng, lset), k=5)  # warm-up: the landmark index, the read cache
    procs, outs = start_writers(uri, n, count, 0.0)
    acked, done, times, top1 = [], {}, [], 0
    t0 = time.monotonic()
    while len(done) < n and time.monotonic() - t0 < WAIT_S * 4:
        pick = int(rng.integers(base))
        t = time.perf_counter()
        found = reader.query(synthetic_set(rng, truth[pick]), k=5)
        times.append((time.perf_counter() - t) * 1e3)
        top1 += bool(found) and found[0].keyframe_id == ids[pick]
        drain(outs, acked, done)
    wall = time.monotonic() - t0
    drain(outs, acked, done, wait_s=1.0)
    for p in procs:
        p.join(WAIT_S)
    reader.close()
    with MapStore.open(uri, create=False) as store:
        stored = Counter(store.ids())
    mine = [a[1] for a in acked]
    return {
        'kf_per_s': len(acked) / wall,
        'insert_p50': float(np.percentile([a[4] for a in acked], 50)),
        'query_p50': float(np.percentile(times, 50)),
        'query_p95': float(np.percentile(times, 95)),
        'queries': len(times),
        'top1': top1 / max(len(times), 1),
        'once': len(mine) == len(set(mine)) == n * count and all(stored[k] == 1 for k in mine),
        'exit': [p.exitcode for p in procs],
    }


def server_rows(uri: str) -> tuple[int, list[int]]:
    """(count(*), every row id) of the map's frames collection straight from the server (Strong)."""
    from pymilvus import MilvusClient

    from lln_ros.mapstore.milvus import parse_uri

    where = parse_uri(uri)
    c = MilvusClient(uri=where['uri'], timeout=60, db_name=where['db_name'])
    try:
        name = f'{where["map"]}_frames'
        count = int(c.query(name, filter='', output_fields=['count(*)'], consistency_level='Strong')[0]['count(*)'])
        rows, last = [], -1
        while True:  # paged by id: a query returns at most 16,384 rows
            got = c.query(name, filter=f'id > {last}', output_fields=['id'], limit=16384, consistency_level='Strong')
            if not got:
                return count, rows
            rows += [int(r['id']) for r in got]
            last = max(rows)
    finally:
        c.close()


def soak(server: LoopbackMilvus, uri: str, n: int, seconds: float) -> dict:
    """Module doc, Soak."""
    with MapStore.open(uri, model=MODEL):
        pass
    procs, outs = start_writers(uri, n, 0, seconds)
    acked, done, events = [], {}, []
    t0 = time.monotonic()
    killed = restarted = False
    while len(done) < n - 1 and time.monotonic() - t0 < seconds + WAIT_S:
        drain(outs, acked, done, wait_s=0.5, skip={0} if killed else ())
        now = time.monotonic() - t0
        if not killed and now > seconds / 3:
            os.kill(procs[0].pid, signal.SIGKILL)
            procs[0].join(WAIT_S)
            killed = True
            events.append(f'{now:.0f} s: writer 0 killed (SIGKILL, exit {procs[0].exitcode})')
        if killed and not restarted and now > 2 * seconds / 3:
            t = time.monotonic()
            server.restart()
            restarted = True
            events.append(f'{now:.0f} s: server restarted, down {time.monotonic() - t:.0f} s')
    drain(outs, acked, done, wait_s=1.0, skip={0})
    for p in procs[1:]:
        p.join(WAIT_S)
    with MapStore.open(uri, create=False) as store:
        origins = store.origins()
        sessions = {s.id: s.robot for s in store.sessions()}
        problems = store.check()
    count, rows = server_rows(uri)
    stored = Counter((sessions.get(o.session_id), o.session_id, o.seq) for o in origins.values())
    want = [(f'w{a[0]}', a[2], a[3]) for a in acked]
    by_id = {o_id: (sessions.get(o.session_id), o.session_id, o.seq) for o_id, o in origins.items()}
    return {
        'writers': n,
        'seconds': time.monotonic() - t0,
        'acked': len(acked),
        'acked_per_writer': dict(sorted(Counter(a[0] for a in acked).items())),
        'lost': sum(stored[w] == 0 for w in want),
        'duplicated_checksums': sum(v > 1 for v in stored.values()),
        'wrong_id': sum(by_id.get(a[1]) != w for a, w in zip(acked, want)),
        'rows': count,
        'origins': len(origins),
        'sessions': len(sessions),
        'distinct_ids': len(set(rows)),
        'unacknowledged_rows': count - len(acked),
        'errors': dict(sorted(done.items())),
        'check': problems,
        'events': events,
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    ap.add_argument('--writers', default='1,2,4')
    ap.add_argument('--keyframes', type=int, default=150, help='per writer, in the rate runs')
    ap.add_argument('--base', type=int, default=1000, help='keyframes in the map before the writers start')
    ap.add_argument('--soak-s', type=float, default=600.0, help='0: no soak run')
    ap.add_argument('--soak-writers', type=int, default=4)
    args = ap.parse_args(argv)
    if not only_loopback():
        ap.error('run under test/milvus_loopback.py (a loopback-only network namespace)')
    counts = [int(v) for v in args.writers.split(',')]
    work = Path(tempfile.mkdtemp(prefix='lln_bench_writers_'))
    server = LoopbackMilvus().start()
    rng = np.random.default_rng(0)
    print(f'load average at start: {load()} ({os.cpu_count()} cores)', file=sys.stderr)
    table, soaked, t_all = [], None, time.monotonic()
    try:
        for n in counts:  # backends interleaved per writer count, so other load hits them alike
            for backend in ('sqlite', 'milvus'):
                uri = str(work / f'map_{n}.db') if backend == 'sqlite' else f'{server.uri}/lln_bench?map=bw{n}'
                before = load()
                r = rates(uri, n, args.keyframes, args.base, rng)
                table.append((n, backend, r, before, load()))
                print(f'{backend}, {n} writers: {r}', file=sys.stderr)
        if args.soak_s > 0:
            soaked = soak(server, f'{server.uri}/lln_bench?map=soak', args.soak_writers, args.soak_s)
            print(f'soak: {soaked}', file=sys.stderr)
    finally:
        server.close()
        shutil.rmtree(work, ignore_errors=True)
    print(
        f'{args.base} keyframes in the map, then {args.keyframes} per writer (add + set_origin, one at a time); '
        f'queries k 5, shipped defaults; {os.cpu_count()} cores; {time.monotonic() - t_all:.0f} s wall'
    )
    print(
        '| writers | backend | keyframes/s (all writers) | insert p50 ms | query p50 ms | query p95 ms '
        '| query p50 / 1 writer | top-1 | every acked once | load before -> after |'
    )
    print('|---:|---|---:|---:|---:|---:|---:|---:|---|---|')
    one = {b: r['query_p50'] for n, b, r, *_ in table if n == min(counts)}
    for n, backend, r, before, after in table:
        print(
            f'| {n} | {backend} | {r["kf_per_s"]:.1f} | {r["insert_p50"]:.1f} | {r["query_p50"]:.1f} '
            f'| {r["query_p95"]:.1f} | {r["query_p50"] / one[backend]:.2f}x | {r["top1"]:.2f} '
            f'| {"yes" if r["once"] else "NO"} | {before} -> {after} |'
        )
    if soaked:
        s = soaked
        print(f'\nsoak: {s["writers"]} writers, {s["seconds"]:.0f} s; ' + '; '.join(s['events']))
        print(
            f'acknowledged {s["acked"]} {s["acked_per_writer"]}; lost {s["lost"]}; duplicated (robot, session, '
            f'seq) {s["duplicated_checksums"]}; acked id holding another checksum {s["wrong_id"]}; rows {s["rows"]}, '
            f'distinct ids {s["distinct_ids"]}, unacknowledged rows {s["unacknowledged_rows"]}; '
            f'MapErrors per surviving writer {s["errors"]}; check() {s["check"] or "clean"}'
        )
    return 0


if __name__ == '__main__':
    sys.exit(main())
