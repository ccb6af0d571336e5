"""Offline evaluation (lln-eval), the online-vs-offline comparison (lln-demo) and their one report stack.

    runner    evaluate / evaluate_dataset: every method on every dataset, the paper's protocol
    methods   the rows: methods, LLN heads, extractor variants
    peers     the sad / seqslam rows and X+seq
    reloc     the relocalization rows (--reloc)
    timing    round-robin timing of every row
    online    lln-demo: rankings from the nodes' answers, transport accounting, online vs offline
    report    number formats, JSON, markdown, CSV (lln-eval, lln-demo, scripts/results_md.py)
    figures   PR curves, recall@K, heatmaps, match pictures
"""
from .methods import ALL_METHODS, METHODS, METRIC_KEYS, REPORT_KEYS, Head, load_heads, parse_head, parse_methods
from .runner import DatasetRun, EvalRun, default_conf, evaluate, evaluate_dataset

__all__ = ['ALL_METHODS', 'METHODS', 'METRIC_KEYS', 'REPORT_KEYS', 'DatasetRun', 'EvalRun', 'Head', 'default_conf',
           'evaluate', 'evaluate_dataset', 'load_heads', 'parse_head', 'parse_methods']
