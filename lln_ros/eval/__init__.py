"""Offline evaluation (lln-eval), the online-vs-offline comparison (lln-demo) and their one report stack.

    runner    evaluate / evaluate_dataset: every method on every dataset, the paper's protocol
    methods   the rows: methods, LLN heads, extractor variants
    peers     the sad / seqslam rows and X+seq
    reloc     the relocalization rows (--reloc)
    timing    round-robin timing of every row
    online    lln-demo: rankings from the nodes' answers, transport accounting, online vs offline
    report    number formats, JSON, markdown, CSV (lln-eval, lln-demo, scripts/results_md.py)
    figures   PR curves, recall@K, heatmaps, match pictures

Names are imported on first use, so the report stack (scripts/results_md.py, lln-demo's bad-input
checks) does not pay for torch.
"""

from importlib import import_module

_LAZY = {
    'ALL_METHODS': 'methods',
    'METHODS': 'methods',
    'METRIC_KEYS': 'methods',
    'REPORT_KEYS': 'methods',
    'Head': 'methods',
    'load_heads': 'methods',
    'parse_head': 'methods',
    'parse_methods': 'methods',
    'DatasetRun': 'runner',
    'EvalRun': 'runner',
    'default_conf': 'runner',
    'evaluate': 'runner',
    'evaluate_dataset': 'runner',
}
__all__ = list(_LAZY)


def __getattr__(name):
    if name in _LAZY:
        return getattr(import_module(f'.{_LAZY[name]}', __name__), name)
    raise AttributeError(f'module {__name__!r} has no attribute {name!r}')
