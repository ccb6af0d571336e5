"""Core speed benchmark: backbone, full extraction, and batched matching per pair.

    python bench/bench_core.py [--json] [--repeats 30] [--threads 2]

All numbers are medians over `--repeats` runs on real pixels (views of a photograph shipped in
matplotlib), 384x288 input (the paper's 12x9 grid), measured in one run so ratios are comparable.
Paper figures (Table 4, on a GPU) are printed beside ours.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import time

# numpy's BLAS sizes its thread pool at import: take --threads before numpy loads. With more BLAS
# threads than free cores, spinning workers cost ~266 us per pair whatever the work (seen here)
if '--threads' in sys.argv[:-1]:
    os.environ['OPENBLAS_NUM_THREADS'] = sys.argv[sys.argv.index('--threads') + 1]

import numpy as np  # noqa: E402
import torch  # noqa: E402

from lln_ros.extractor import Extractor  # noqa: E402
from lln_ros.image import load_image, resize_for_network  # noqa: E402
from lln_ros.landmarks import stack_landmarks  # noqa: E402
from lln_ros.similarity import match_batch  # noqa: E402

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


def views(photo: np.ndarray, count: int) -> list[np.ndarray]:
    """`count` different 384x288 views of the photo (shifted windows, some mirrored)."""
    out = []
    for i in range(count):
        y, x = (i * 37) % (photo.shape[0] - 288), (i * 53) % (photo.shape[1] - 384)
        v = photo[y:y + 288, x:x + 384]
        out.append(np.ascontiguousarray(v[:, ::-1] if i % 2 else v))
    return out


def run(repeats: int, threads: int) -> dict:
    import matplotlib.cbook as cbook
    torch.set_num_threads(threads)
    with cbook.get_sample_data('grace_hopper.jpg') as f:
        photo = load_image(f.name)
    images = views(photo, 31)
    query_img = images[0]
    result = {'threads': threads, 'repeats': repeats, 'machine': platform.processor() or platform.machine(),
              'torch': torch.__version__}

    ex = Extractor({'num_threads': threads, 'top_n': 50})
    net_in = torch.from_numpy(resize_for_network(query_img, 288)[None]).permute(0, 3, 1, 2).float() / 255

    def backbone():
        with torch.inference_mode():
            ex.backbone(net_in)
    result['backbone_ms'] = median_time(backbone, repeats) * 1e3
    result['extract_ms'] = median_time(lambda: ex(query_img), repeats) * 1e3
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
    sets = [q]
    globals_ = batch.globals
    gq = q.global_descriptor
    result['holistic_us_per_pair'] = median_time(lambda: globals_ @ gq, repeats * 30) / len(globals_) * 1e6
    return result


def table(r: dict) -> str:
    rows = [
        ('backbone forward, 384x288', f'{r["backbone_ms"]:.1f} ms', '-'),
        ('full extraction, 384x288', f'{r["extract_ms"]:.1f} ms ({r["extract_over_backbone"]:.2f}x backbone)',
         f'{PAPER_MS["extract_ms"]} ms'),
        (f'match LLN n={r["n_lln_50"]}, per pair (30 batched)', f'{r["match_us_per_pair_lln_50"]:.0f} us',
         f'{PAPER_MS["lln_50"]} ms'),
        (f'match LLN n={r["n_lln_75"]}, per pair (30 batched)', f'{r["match_us_per_pair_lln_75"]:.0f} us',
         f'{PAPER_MS["lln_75"]} ms'),
        (f'match ALL n={r["n_all"]}, per pair (30 batched)', f'{r["match_us_per_pair_all"]:.0f} us',
         f'{PAPER_MS["all"]} ms'),
        ('holistic cosine, per pair', f'{r["holistic_us_per_pair"]:.3f} us', f'{PAPER_MS["holistic"]} ms'),
    ]
    w = max(len(a) for a, _, _ in rows)
    lines = [f'| {"what":<{w}} | lln_ros ({r["threads"]}-thread CPU, median) | paper (GPU) |',
             f'|{"-" * (w + 2)}|---|---|']
    lines += [f'| {a:<{w}} | {b} | {c} |' for a, b, c in rows]
    return '\n'.join(lines)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument('--json', action='store_true', help='print one JSON object')
    p.add_argument('--repeats', type=int, default=30)
    p.add_argument('--threads', type=int, default=2)
    args = p.parse_args(argv)
    r = run(args.repeats, args.threads)
    print(json.dumps(r) if args.json else table(r))
    return 0


if __name__ == '__main__':
    sys.exit(main())
