"""Which runtime settings run the extractor's network fastest: ONNX Runtime options and OpenVINO.

    python bench/bench_runtime_options.py [--repeats 30] [--budget 6] [--json]

The same exported graph (lln_ros.core.runtime) on one 384x288 view of a real photograph, quiet and with
one competing CPU-bound process (started and stopped here), all in one run so ratios compare.
Tried: ONNX Runtime intra-op threads 1/2, spinning on/off, sequential vs parallel execution, graph
optimisation basic vs all; OpenVINO (when the `openvino` package is installed) with 1/2 inference
threads and the latency hint; torch at 1/2 threads as the reference. lln_ros.core.runtime keeps the
winner (ORT_SESSION_CONFIG, the extractor's default threads); docs/benchmarks.md quotes this table.
"""

from __future__ import annotations

import argparse
import json
import os
import sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from bench_core import competing_load, photo_views, round_robin  # noqa: E402

from lln_ros.core import runtime  # noqa: E402
from lln_ros.core.extractor import Extractor  # noqa: E402


def ort_variant(path, threads: int, spinning: bool, parallel: bool = False, basic: bool = False):
    import onnxruntime as ort

    so = ort.SessionOptions()
    so.intra_op_num_threads = threads
    so.inter_op_num_threads = 1
    so.execution_mode = ort.ExecutionMode.ORT_PARALLEL if parallel else ort.ExecutionMode.ORT_SEQUENTIAL
    so.graph_optimization_level = (
        ort.GraphOptimizationLevel.ORT_ENABLE_BASIC if basic else ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    )
    so.log_severity_level = 3
    so.add_session_config_entry('session.intra_op.allow_spinning', '1' if spinning else '0')
    so.add_session_config_entry('session.inter_op.allow_spinning', '1' if spinning else '0')
    s = ort.InferenceSession(str(path), so, providers=['CPUExecutionProvider'])
    return lambda x: s.run(None, {'rgb': x})


def openvino_variant(path, threads: int, precision: str = 'f32'):
    import openvino as ov

    # f32: the same numbers as torch; OpenVINO's default on a CPU with bf16 units (this one) is bf16
    compiled = ov.Core().compile_model(
        str(path),
        'CPU',
        {'INFERENCE_NUM_THREADS': threads, 'PERFORMANCE_HINT': 'LATENCY', 'INFERENCE_PRECISION_HINT': precision},
    )
    request = compiled.create_infer_request()
    return lambda x: request.infer({0: x})


def variants(ex: Extractor, path) -> dict:
    out = {}
    for t in (1, 2):
        out[f'torch, {t} thread(s)'] = ('torch', t, ex.network)
        out[f'ORT {t}t, spinning on (ORT default)'] = ('ort', t, ort_variant(path, t, True))
        out[f'ORT {t}t, spinning off'] = ('ort', t, ort_variant(path, t, False))
    for t in (1, 2):
        out[f'ORT {t}t, spinning off, parallel execution'] = ('ort', t, ort_variant(path, t, False, parallel=True))
    out['ORT 1t, spinning off, basic graph optimisation'] = ('ort', 1, ort_variant(path, 1, False, basic=True))
    try:
        import openvino  # noqa: F401
    except ImportError:
        print('openvino is not installed: its rows are left out', file=sys.stderr)
    else:
        for t in (1, 2):
            out[f'OpenVINO {t}t, latency hint, f32'] = ('ov', t, openvino_variant(path, t))
        out['OpenVINO 1t, bf16 (its default here; other numbers)'] = ('ov', 1, openvino_variant(path, 1, 'bf16'))
    return out


def call(kind: str, threads: int, fn, x):
    import torch

    def run_once():
        if kind == 'torch':
            torch.set_num_threads(threads)
        return fn(x)

    return run_once


def run(repeats: int, budget: float) -> dict:
    ex = Extractor({'runtime': 'torch'})
    path = runtime.ensure_onnx(ex.model_info['backbone'], ex.model_info['layer'], ex.backbone, ex.head)
    x = photo_views(1, 384)[0][None]
    table = variants(ex, path)
    rows = {name: {} for name in table}
    load = {}
    calls = {name: call(kind, t, fn, x) for name, (kind, t, fn) in table.items()}
    for loaded in (False, True):
        with competing_load(loaded):
            load['loaded' if loaded else 'quiet'] = os.getloadavg()[0]
            for name, stat in round_robin(calls, repeats, budget).items():
                rows[name]['loaded' if loaded else 'quiet'] = stat
    return {'load_average_at_start': os.getloadavg(), 'load_1min': load, 'rows': rows}


def format_table(r: dict) -> str:
    lines = [
        f'load average at start (1/5/15 min): {", ".join(f"{v:.1f}" for v in r["load_average_at_start"])}',
        '',
        '| 384x288, one frame | p50 ms | CPU ms | with 1 competing process: p50 ms | CPU ms | ratio |',
        '|---|---|---|---|---|---|',
    ]
    for name, v in r['rows'].items():
        quiet_ms, loaded_ms = v['quiet']['p50_ms'], v['loaded']['p50_ms']
        lines.append(
            f'| {name} | {quiet_ms:.1f} | {v["quiet"]["cpu_ms"]:.1f} | {loaded_ms:.1f} | {v["loaded"]["cpu_ms"]:.1f} '
            f'| {loaded_ms / quiet_ms:.2f}x |'
        )
    return '\n'.join(lines)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument('--repeats', type=int, default=30, help='timed runs per row (fewer when --budget runs out)')
    p.add_argument('--budget', type=float, default=6.0, help='seconds per row at most (default 6)')
    p.add_argument('--json', action='store_true')
    args = p.parse_args(argv)
    r = run(args.repeats, args.budget)
    print(json.dumps(r) if args.json else format_table(r))
    return 0


if __name__ == '__main__':
    sys.exit(main())
