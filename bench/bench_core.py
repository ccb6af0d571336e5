"""Core speed benchmark: backbone, full extraction per runtime, and batched matching per pair.

    python bench/bench_core.py [--json] [--repeats 100] [--threads 2] [--budget 8] [--no-runtimes]

All numbers are medians over `--repeats` runs on real pixels (views of a photograph shipped in
matplotlib), 384x288 input (the paper's 12x9 grid), measured in one run so ratios are comparable.
Paper figures (Table 4, on a GPU) are printed beside ours.

The runtime table: per-frame extraction latency (Extractor.__call__, p50 and p90) for every runtime
(torch, onnxruntime) at 384x288, 512x288 and Nordland's 576x288, with 1 and 2 threads, first as the
machine is, then with one competing CPU-bound process that this script starts and stops itself.
Each row runs `--repeats` frames or `--budget` seconds, whichever ends first (at least 5 frames).
The load average at the start is printed: on a shared machine "quiet" means "no process of ours".
"""

from __future__ import annotations

import argparse
import contextlib
import itertools
import json
import os
import platform
import statistics
import subprocess
import sys
import time

# numpy's BLAS sizes its thread pool at import: take --threads before numpy loads. With more BLAS
# threads than free cores, spinning workers cost ~266 us per pair whatever the work (seen here)
if '--threads' in sys.argv[:-1]:
    os.environ['OPENBLAS_NUM_THREADS'] = sys.argv[sys.argv.index('--threads') + 1]

import numpy as np  # noqa: E402
import torch  # noqa: E402

from lln_ros.core.extractor import Extractor, default_conf  # noqa: E402
from lln_ros.core.landmarks import stack_landmarks  # noqa: E402
from lln_ros.core.similarity import match_batch  # noqa: E402
from lln_ros.io.image import load_image, photo_views, resize_for_network  # noqa: E402

PAPER_MS = {'extract_ms': 16.0, 'lln_50': 6.0, 'lln_75': 13.0, 'all': 27.0, 'holistic': 0.009}


def median_time(fn, repeats: int, warmup: int = 3) -> float:
    """Median wall time of fn() in seconds."""
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return statistics.median(times)


def round_robin(fns: dict, repeats: int, budget: float, warmup: int = 2, block: int = 4) -> dict:
    """{name: fn()} -> {name: p50/p90 wall ms, median CPU ms, frames}. Each round gives every fn a
    turn of one untimed call then `block` timed calls, so all of them see the same minutes of a
    shared machine's load; rounds stop after `repeats` timed calls per fn, or when `budget` seconds
    per fn are used up (at least 5 timed calls).

    Why the untimed call: a runtime's idle workers keep spinning for a few ms after its call (torch's
    OpenMP pool does by default). Timed straight after a torch call, ONNX Runtime at 2 threads shared
    its second core with torch's spinning worker: 13.6 ms per frame instead of 11.5 alone, and 25 CPU
    ms instead of 17 at 1 thread. One untimed call absorbs that, so each fn is timed as it runs
    when it is the only runtime in the process, as in the extractor node."""
    for fn in fns.values():
        for _ in range(warmup):
            fn()
    wall = {name: [] for name in fns}
    cpu = {name: [] for name in fns}
    end = time.perf_counter() + budget * len(fns)
    timed = 0
    while timed < repeats and (timed < 5 or time.perf_counter() < end):
        for name, fn in fns.items():
            fn()
            for _ in range(block):
                t, c = time.perf_counter(), time.process_time()
                fn()
                wall[name].append(time.perf_counter() - t)
                cpu[name].append(time.process_time() - c)
        timed += block
    # CPU time (all threads of this process) per call: the work, whatever the other processes do;
    # for one thread it is close to what the wall time would be on an idle machine
    return {
        name: {
            'p50_ms': float(np.median(wall[name]) * 1e3),
            'p90_ms': float(np.percentile(wall[name], 90) * 1e3),
            'cpu_ms': float(np.median(cpu[name]) * 1e3),
            'frames': len(wall[name]),
        }
        for name in fns
    }


@contextlib.contextmanager
def competing_load(on: bool = True):
    """One CPU-bound process (a Python busy loop) for the duration of the block, when `on`."""
    if not on:
        yield None
        return
    proc = subprocess.Popen([sys.executable, '-c', 'while True: pass'])
    try:
        time.sleep(0.5)  # let the scheduler see it before anything is timed
        yield proc
    finally:
        proc.kill()
        proc.wait()


RUNTIME_SIZES = ((384, 288), (512, 288), (576, 288))


def frame_fn(extractor, threads: int, images: list):
    """A call that extracts the next of `images` with `threads` torch threads."""
    it = itertools.count()

    def fn():
        torch.set_num_threads(threads)  # torch's pool is per process: set it for every call
        return extractor(images[next(it) % len(images)])

    return fn


def runtime_rows(repeats: int, budget: float) -> dict:
    """Per-frame extraction latency for every runtime x size x threads, quiet and loaded."""
    from lln_ros.core.runtime import onnxruntime_available

    runtimes = ['torch'] + (['onnxruntime'] if onnxruntime_available() else [])
    extractors = {(rt, t): Extractor({'runtime': rt, 'num_threads': t, 'top_n': 50}) for rt in runtimes for t in (1, 2)}
    frames = {size: photo_views(4, *size) for size in RUNTIME_SIZES}
    start_load = list(os.getloadavg())
    rows = []
    load = {}
    for loaded in (False, True):
        with competing_load(loaded):
            load['loaded' if loaded else 'quiet'] = os.getloadavg()[0]
            for size in RUNTIME_SIZES:
                for t in (1, 2):
                    stats = round_robin(
                        {rt: frame_fn(extractors[(rt, t)], t, frames[size]) for rt in runtimes}, repeats, budget
                    )
                    rows += [
                        {
                            'runtime': rt,
                            'ran': extractors[(rt, t)].model_info['runtime'],
                            'size': list(size),
                            'threads': t,
                            'loaded': loaded,
                            **stats[rt],
                        }
                        for rt in runtimes
                    ]
    return {
        'load_average_at_start': start_load,
        'load_1min': load,
        'rows': rows,
        'default_runtime': default_conf['runtime'] if onnxruntime_available() else 'torch',
    }


def runtime_summary(r: dict) -> dict:
    """Ratios the issue's targets are stated in, from one run's rows."""

    def p50(rt, size, t, loaded):
        return next(
            (
                x['p50_ms']
                for x in r['rows']
                if x['runtime'] == rt and tuple(x['size']) == size and x['threads'] == t and x['loaded'] == loaded
            ),
            None,
        )

    out = {}
    for t in (1, 2):
        a, b = p50('torch', (384, 288), t, False), p50('onnxruntime', (384, 288), t, False)
        if a and b:
            out[f'speedup_384_{t}t_quiet'] = a / b
        a, b = p50('torch', (384, 288), t, True), p50('onnxruntime', (384, 288), t, True)
        if a and b:
            out[f'speedup_384_{t}t_loaded'] = a / b
    d = r['default_runtime']
    for t in (1, 2):
        quiet_ms, loaded_ms = p50(d, (384, 288), t, False), p50(d, (384, 288), t, True)
        if quiet_ms and loaded_ms:
            out[f'default_loaded_over_quiet_384_{t}t'] = loaded_ms / quiet_ms
    return out


def runtime_table(r: dict) -> str:
    la = ', '.join(f'{v:.1f}' for v in r['load_average_at_start'])
    lines = [
        f'load average at start (1/5/15 min): {la}; default runtime: {r["default_runtime"]}',
        '',
        '| input | threads | runtime | p50 ms | p90 ms | CPU ms | with 1 competing process: p50 ms | p90 ms '
        '| loaded/quiet |',
        '|---|---|---|---|---|---|---|---|---|',
    ]
    quiet = [x for x in r['rows'] if not x['loaded']]
    for q in quiet:
        loaded = next(
            x
            for x in r['rows']
            if x['loaded'] and x['runtime'] == q['runtime'] and x['size'] == q['size'] and x['threads'] == q['threads']
        )
        name = q['runtime'] if q['ran'] == q['runtime'] else f'{q["runtime"]} (ran {q["ran"]})'
        lines.append(
            f'| {q["size"][0]}x{q["size"][1]} | {q["threads"]} | {name} | {q["p50_ms"]:.1f} | '
            f'{q["p90_ms"]:.1f} | {q["cpu_ms"]:.1f} | {loaded["p50_ms"]:.1f} | {loaded["p90_ms"]:.1f} | '
            f'{loaded["p50_ms"] / q["p50_ms"]:.2f}x |'
        )
    s = runtime_summary(r)
    lines.append('')
    for t in (1, 2):
        if f'speedup_384_{t}t_quiet' in s:
            lines.append(
                f'- onnxruntime vs torch at 384x288, {t} thread(s): {s[f"speedup_384_{t}t_quiet"]:.2f}x '
                f'faster (with the competing process: {s[f"speedup_384_{t}t_loaded"]:.2f}x)'
            )
    for t in (1, 2):
        if f'default_loaded_over_quiet_384_{t}t' in s:
            lines.append(
                f'- default runtime, 384x288, {t} thread(s): p50 with the competing process = '
                f'{s[f"default_loaded_over_quiet_384_{t}t"]:.2f}x its p50 without'
            )
    return '\n'.join(lines)


def views(photo: np.ndarray, count: int) -> list[np.ndarray]:
    """`count` different 384x288 views of the photo (shifted windows, some mirrored)."""
    out = []
    for i in range(count):
        y, x = (i * 37) % (photo.shape[0] - 288), (i * 53) % (photo.shape[1] - 384)
        v = photo[y : y + 288, x : x + 384]
        out.append(np.ascontiguousarray(v[:, ::-1] if i % 2 else v))
    return out


def run(repeats: int, threads: int) -> dict:
    import matplotlib.cbook as cbook

    torch.set_num_threads(threads)
    with cbook.get_sample_data('grace_hopper.jpg') as f:
        photo = load_image(f.name)
    images = views(photo, 31)
    query_img = images[0]
    result = {
        'threads': threads,
        'repeats': repeats,
        'machine': platform.processor() or platform.machine(),
        'torch': torch.__version__,
    }

    ex = Extractor({'num_threads': threads, 'top_n': 50, 'runtime': 'torch'})
    net_in = torch.from_numpy(resize_for_network(query_img, 288)[None]).permute(0, 3, 1, 2).float() / 255

    def backbone():
        with torch.inference_mode():
            ex.backbone(net_in)

    result['backbone_ms'] = median_time(backbone, repeats) * 1e3
    result['extract_ms'] = median_time(lambda: ex(query_img), repeats) * 1e3  # torch
    result['extract_over_backbone'] = result['extract_ms'] / result['backbone_ms']

    prepared = {}
    for key, conf in (('lln_50', {'top_n': 50}), ('lln_75', {'top_n': 75}), ('all', {'method': 'all'})):
        sets = Extractor({'num_threads': threads, **conf}).extract_batch(images)
        prepared[key] = (sets[0], stack_landmarks(sets[1:]))
    # torch's worker threads keep spinning for a while after the last extraction and starve numpy's
    # BLAS threads (seen here: a constant 266 us per pair); matching is timed once they are idle
    time.sleep(1.0)
    for key, (q, batch) in prepared.items():
        per_call = median_time(lambda: match_batch(q, batch), repeats * 3)
        result[f'match_us_per_pair_{key}'] = per_call / len(batch) * 1e6
        result[f'n_{key}'] = len(q)
    q, batch = prepared['lln_50']
    for center in ('whiten', 'fuse'):  # the matcher's `similarity` options that cost more than raw S
        per_call = median_time(lambda: match_batch(q, batch, center=center), repeats * 3)
        result[f'match_us_per_pair_lln_50_{center}'] = per_call / len(batch) * 1e6
    sets = [q]
    globals_ = batch.globals
    gq = q.global_descriptor
    result['holistic_us_per_pair'] = median_time(lambda: globals_ @ gq, repeats * 30) / len(globals_) * 1e6
    return result


def table(r: dict) -> str:
    rows = [
        ('backbone forward, 384x288', f'{r["backbone_ms"]:.1f} ms', '-'),
        (
            'full extraction (torch), 384x288',
            f'{r["extract_ms"]:.1f} ms ({r["extract_over_backbone"]:.2f}x backbone)',
            f'{PAPER_MS["extract_ms"]} ms',
        ),
        (
            f'match LLN n={r["n_lln_50"]}, per pair (30 batched)',
            f'{r["match_us_per_pair_lln_50"]:.0f} us',
            f'{PAPER_MS["lln_50"]} ms',
        ),
        (
            f'match LLN n={r["n_lln_75"]}, per pair (30 batched)',
            f'{r["match_us_per_pair_lln_75"]:.0f} us',
            f'{PAPER_MS["lln_75"]} ms',
        ),
        *(
            (
                f'match LLN n={r["n_lln_50"]}, S {center}, per pair (30 batched)',
                f'{r[f"match_us_per_pair_lln_50_{center}"]:.0f} us',
                '-',
            )
            for center in ('whiten', 'fuse')
        ),
        (
            f'match ALL n={r["n_all"]}, per pair (30 batched)',
            f'{r["match_us_per_pair_all"]:.0f} us',
            f'{PAPER_MS["all"]} ms',
        ),
        ('holistic cosine, per pair', f'{r["holistic_us_per_pair"]:.3f} us', f'{PAPER_MS["holistic"]} ms'),
    ]
    w = max(len(a) for a, _, _ in rows)
    lines = [
        f'| {"what":<{w}} | lln_ros ({r["threads"]}-thread CPU, median) | paper (GPU) |',
        f'|{"-" * (w + 2)}|---|---|',
    ]
    lines += [f'| {a:<{w}} | {b} | {c} |' for a, b, c in rows]
    return '\n'.join(lines)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument('--json', action='store_true', help='print one JSON object')
    p.add_argument('--repeats', type=int, default=100)
    p.add_argument('--threads', type=int, default=2)
    p.add_argument(
        '--budget',
        type=float,
        default=8.0,
        help='seconds per runtime-table row at most (default 8; slow rows stop early)',
    )
    p.add_argument('--no-runtimes', action='store_true', help='leave out the runtime table')
    args = p.parse_args(argv)
    r = run(args.repeats, args.threads)
    if not args.no_runtimes:
        r['runtimes'] = runtime_rows(args.repeats, args.budget)
        r['runtimes']['summary'] = runtime_summary(r['runtimes'])
    if args.json:
        print(json.dumps(r))
    else:
        print(table(r))
        if not args.no_runtimes:
            print()
            print(runtime_table(r['runtimes']))
    return 0


if __name__ == '__main__':
    sys.exit(main())
