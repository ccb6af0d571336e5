"""What the start-up integrity scan costs: the blob-size check the map runs at every open.

    python bench/bench_integrity.py [--keyframes 100000] [--dir /tmp/lln_bench_integrity] [--repeat 3]

Builds (once; reused while --keyframes matches) an SQLite map of synthetic keyframes with the
default model's shapes (n=50, D=192, 21 KB a keyframe), damages one landmark blob to 1 byte, then
times, in this process with the page cache warm (the file was just written or read):

  integrity scan   SQLiteMapStore._damaged: one SELECT with length() on every blob (the scan the
                   open runs and lln-map check reports; finds the damaged keyframe)
  quick_check      PRAGMA quick_check, which the open runs by default (verify=True): reads every page
  open             MapStore.open(verify=False) in full: the scan + reading the global descriptors +
                   building the FAISS index
and prints a table (median of --repeat runs) with the machine's load average.
"""

from __future__ import annotations

import argparse
import os
import sqlite3
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from lln_ros.core.landmarks import LandmarkSet  # noqa: E402
from lln_ros.mapstore import MapStore  # noqa: E402

D, N_LANDMARKS, ROWS, COLS = 192, 50, 9, 12
SPACE = f'efficientnet_lite0/stage6/{D}'


def synthetic(rng, count: int) -> list[LandmarkSet]:
    cell = np.array([384 / COLS, 288 / ROWS], np.float32)
    out = []
    for _ in range(count):
        desc = rng.standard_normal((N_LANDMARKS + 1, D)).astype(np.float32)
        desc /= np.linalg.norm(desc, axis=1, keepdims=True)
        flat = rng.choice(ROWS * COLS, N_LANDMARKS, replace=False)
        cells = np.stack([flat % COLS, flat // COLS], axis=1).astype(np.int32)
        out.append(
            LandmarkSet(
                global_descriptor=desc[0],
                descriptors=desc[1:],
                cells=cells,
                centers=((cells + 0.5) * cell).astype(np.float32),
                scores=np.linspace(1, 0, N_LANDMARKS, dtype=np.float32),
                cell_size=cell,
                image_size=np.array([384, 288], np.float32),
                grid=(ROWS, COLS),
                descriptor_space=SPACE,
            )
        )
    return out


def build(path: Path, keyframes: int) -> None:
    rng = np.random.default_rng(0)
    with MapStore(path, model={'descriptor_space': SPACE, 'descriptor_dim': D}) as store:
        done = len(store)
        while done < keyframes:
            batch = min(1000, keyframes - done)
            store.add_many(synthetic(rng, batch), [(i, 0) for i in range(done, done + batch)])
            done += batch
        store.save()


def timed(fn, repeat: int) -> tuple[float, object]:
    times, result = [], None
    for _ in range(repeat):
        start = time.perf_counter()
        result = fn()
        times.append(time.perf_counter() - start)
    return statistics.median(times), result


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--keyframes', type=int, default=100_000)
    ap.add_argument('--dir', default='/tmp/lln_bench_integrity')
    ap.add_argument('--repeat', type=int, default=3)
    args = ap.parse_args(argv)
    path = Path(args.dir) / f'map_{args.keyframes}.db'
    path.parent.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    build(path, args.keyframes)
    built_s = time.perf_counter() - start
    con = sqlite3.connect(path)
    victim = args.keyframes // 2
    con.execute("UPDATE landmarks SET descriptors = x'00' WHERE keyframe_id = ?", (victim,))
    con.commit()
    con.close()
    with MapStore(path, create=False, verify=False) as store:
        scan_s, damaged = timed(lambda: store._damaged(D), args.repeat)
        quick_s, _ = timed(lambda: store._conn.execute('PRAGMA quick_check(20)').fetchall(), args.repeat)
    assert list(damaged) == [victim], damaged
    open_s, _ = timed(lambda: MapStore(path, create=False, verify=False).close(), args.repeat)
    size_mb = os.path.getsize(path) / 2**20
    load = ' '.join(f'{x:.1f}' for x in os.getloadavg())
    print(
        f'map: {args.keyframes} keyframes (n={N_LANDMARKS}, D={D}), {size_mb:.0f} MB; built/checked in '
        f'{built_s:.0f} s; load average {load} on {os.cpu_count()} cores; warm page cache'
    )
    print(f'{"step":<18}{"median s":>10}{"per 100k keyframes s":>24}')
    for name, seconds in (('integrity scan', scan_s), ('quick_check', quick_s), ('open (verify=False)', open_s)):
        print(f'{name:<18}{seconds:>10.3f}{seconds * 100_000 / args.keyframes:>24.3f}')
    print(f'found: {damaged[victim]}')
    # the damaged blob goes back, so the next run reuses a healthy map
    with MapStore(path, create=False, verify=False) as store:
        good = synthetic(np.random.default_rng(1), 1)[0]
        store._write(
            lambda c: c.execute(
                'UPDATE landmarks SET descriptors = ? WHERE keyframe_id = ?',
                (np.ascontiguousarray(good.descriptors, '<f2').tobytes(), victim),
            )
        )
    return 0


if __name__ == '__main__':
    sys.exit(main())
