"""What one hostile message costs the matcher's decoding and decisions, next to a good query.

    python bench/bench_hostile.py [--keyframes 300] [--repeat 5]

A real SQLite map (in a temporary folder) of synthetic keyframes with the default model's shapes
(n=50, D=192, 12x9 grid at 384x288). Each message goes through what the node does with it:
msgs.cloud_to_landmarks with the node's limits, then Localizer.query. Per message: the median
time of --repeat runs, then the peak of traced allocations of one more run (tracemalloc; numpy
reports its arrays to it), printed as a table with the outcome (answered / the counter it was refused under).
"""

from __future__ import annotations

import argparse
import array
import os
import statistics
import sys
import tempfile
import time
import tracemalloc
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_integrity import SPACE, synthetic  # noqa: E402

from lln_ros.core.localizer import Localizer  # noqa: E402
from lln_ros.errors import MessageError  # noqa: E402
from lln_ros.mapstore import open_for_matcher as open_map  # noqa: E402
from lln_ros.ros import msgs  # noqa: E402


def hostile(good) -> dict:
    base = msgs.cloud_to_array(msgs.landmarks_to_cloud(good))
    col, row = np.floor(base['u'][1:] / base['w'][1:]), np.floor(base['v'][1:] / base['h'][1:])
    tiny = base.copy()
    tiny['w'][1:], tiny['h'][1:] = 1e-3, 1e-3
    tiny['u'][1:], tiny['v'][1:] = (col + 0.5) * 1e-3, (row + 0.5) * 1e-3
    huge = base.copy()
    huge['w'][0], huge['h'][0] = 1e9, 1e9
    wide = base.copy()
    wide['w'][0] = 32768
    many = np.zeros(100_001, base.dtype)
    many[0], many[1:] = base[0], base[1]
    truncated = msgs.array_to_cloud(base)
    truncated.data = array.array('B', bytes(truncated.data)[:-7])
    return {
        'good query': msgs.array_to_cloud(base),
        'cell 1e-3 px': msgs.array_to_cloud(tiny),
        'image 1e9 x 1e9': msgs.array_to_cloud(huge),
        'image 32768 px wide': msgs.array_to_cloud(wide),
        '100k landmark rows': msgs.array_to_cloud(many),
        'truncated data': truncated,
    }


def handle(loc: Localizer, cloud) -> str:
    before = loc.counters.snapshot()
    try:
        lset = msgs.cloud_to_landmarks(cloud, **loc.landmark_decoding('bad_query'))
    except MessageError as e:
        loc.refuse('bad_query', e)
        return 'bad_query'
    answer = loc.query(lset, 1)
    if answer is not None:
        return f'answered ({len(answer.rows)} rows)'
    after = loc.counters.snapshot()
    return next(k for k in after if after[k] != before.get(k, 0))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--keyframes', type=int, default=300)
    ap.add_argument('--repeat', type=int, default=5)
    args = ap.parse_args(argv)
    rng = np.random.default_rng(0)
    sets = synthetic(rng, args.keyframes)
    with tempfile.TemporaryDirectory() as tmp:
        store, _ = open_map(os.path.join(tmp, 'map.db'), descriptor_space=SPACE)
        with store:
            store.add_many(sets, [(i, 0) for i in range(len(sets))])
            loc = Localizer(store, log=_Quiet())
            rows = []
            for name, cloud in hostile(sets[7]).items():
                times, peaks, outcome = [], [], ''
                for _ in range(args.repeat):  # timed without tracemalloc, which slows allocation
                    start = time.perf_counter()
                    outcome = handle(loc, cloud)
                    times.append(time.perf_counter() - start)
                tracemalloc.start()
                handle(loc, cloud)
                peaks.append(tracemalloc.get_traced_memory()[1])
                tracemalloc.stop()
                wire = len(cloud.data) / 2**20
                rows.append((name, wire, statistics.median(times) * 1e3, max(peaks) / 2**20, outcome))
    load = ' '.join(f'{x:.1f}' for x in os.getloadavg())
    print(f'map: {args.keyframes} keyframes (n=50, D=192); load average {load} on {os.cpu_count()} cores')
    print(f'{"message":<22}{"on the wire MB":>15}{"ms":>9}{"peak alloc MB":>15}  outcome')
    for name, wire, ms, peak, outcome in rows:
        print(f'{name:<22}{wire:>15.2f}{ms:>9.2f}{peak:>15.2f}  {outcome}')
    return 0


class _Quiet:
    def warning(self, text):
        pass

    error = info = warning


if __name__ == '__main__':
    sys.exit(main())
