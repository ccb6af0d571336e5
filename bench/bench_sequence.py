"""Per-query overhead of the matcher's sequence search (KeyframeSequence.update: push into the ring,
map ids to positions, search, map back), against sequence length L and map size.

    python bench/bench_sequence.py [--repeats 2000] [--k 30] [--json]      # --k 0: every keyframe scored

The stream is a vehicle driving the mapped route (true keyframe plus prefilter_k - 1 random others per
query, as the matcher's reranked list); the cost does not depend on the score values, only on L,
K = prefilter_k and the velocity steps (and, through filling the dense window, on the map size).
K = 0 is the matcher's prefilter_k 0 (every keyframe scored, K = map size). The target (issue 7) is
under 1 ms per query at L = 10.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import time

import numpy as np

from lln_ros.core.sequence import KeyframeSequence


def stream(n_queries: int, map_size: int, k: int, seed: int = 0) -> list[dict]:
    rng = np.random.default_rng(seed)
    out = []
    for q in range(n_queries):
        true = q % map_size
        others = rng.choice(np.delete(np.arange(map_size), true), k - 1, replace=False)
        ids = np.r_[true, others] * 2 + 1  # non-contiguous ids, as a map with deletions has
        out.append(dict(zip(ids.tolist(), rng.uniform(0, 1, k).tolist())))
    return out


def time_update(length: int, map_size: int, k: int, repeats: int) -> float:
    """Median seconds of one update (the ring is full: the steady state)."""
    seq = KeyframeSequence({'length': length})
    seq.set_map(np.arange(map_size) * 2 + 1)
    queries = stream(repeats + length, map_size, k or map_size)
    times = []
    for i, scores in enumerate(queries):
        t = time.perf_counter()
        seq.update(i * 50_000_000, scores, k=5)
        if i >= length:
            times.append(time.perf_counter() - t)
    return statistics.median(times)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    p.add_argument('--repeats', type=int, default=2000)
    p.add_argument('--k', type=int, default=30, help='scored keyframes per query (prefilter_k; 0 = all)')
    p.add_argument('--json', action='store_true')
    args = p.parse_args(argv)
    rows = []
    for length in (1, 5, 10, 20):
        for map_size in (100, 1000, 10000):
            ms = time_update(length, map_size, args.k, args.repeats) * 1e3
            rows.append({'L': length, 'map_keyframes': map_size, 'K': args.k, 'ms_per_query': ms})
    load = os.getloadavg()
    if args.json:
        print(json.dumps({'rows': rows, 'loadavg': load, 'cpu': platform.processor() or platform.machine()}))
        return 0
    print(
        f'sequence search overhead per query (median of {args.repeats}), K = {args.k or "map size"}, '
        f'{platform.machine()}, {os.cpu_count()} CPUs, load average {load[0]:.2f} {load[1]:.2f} {load[2]:.2f}'
    )
    print('| L | map keyframes | ms / query | target < 1 ms at L = 10 |')
    print('|---:|---:|---:|---|')
    for r in rows:
        mark = ('ok' if r['ms_per_query'] < 1 else 'MISSED') if r['L'] == 10 else ''
        print(f'| {r["L"]} | {r["map_keyframes"]} | {r["ms_per_query"]:.3f} | {mark} |')
    return 0


if __name__ == '__main__':
    sys.exit(main())
