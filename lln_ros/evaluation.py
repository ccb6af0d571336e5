"""Offline evaluation of place recognition: every method on every dataset, the paper's protocol.

    from lln_ros.evaluation import Head, evaluate
    run = evaluate([dataset], Extractor(), {'methods': ('holistic', 'lln', 'act', 'rand', 'all'), 'top_n': 50},
                   heads=[Head('trained', 'best.pt'), Head('untrained', None)], out_dir='results')
    run.results['datasets'][dataset.name]['methods']['lln[trained]']['p_at_100r']

One backbone pass per image: the feature maps come from a FeatureCache at the extractor's input
height, and every method is `Extractor.from_features` with its own conf copy (the methods differ
only in which cells become landmarks). Rows:

    holistic       the global descriptor (max pool) ranking alone, no rerank; n = 1 (one vector per image)
    lln / lln[X]   top-n cells by the LLN activation of head X (one row per head)
    act            top-n cells by feature norm (Chen et al.); no head involved
    rand           the same n random cells in every image; no head involved
    all            every cell of the grid; no head involved
    sad, seqslam   classic peers (lln_ros.peers): patch-normalised thumbnails, single frame / sequence
    X+seq          with conf['sequence'] = L > 0: row X's ranking made sequence-consistent
                   (lln_ros.sequence, the search the matcher node runs online)

Every local method reranks the SAME holistic top-K (prefilter_k, the paper's 30) by the landmark
similarity S (retrieval.rank_all); loop datasets restrict answers with `allowed=ds.candidates`.
prefilter_k 0 scores every reference (exhaustive): no holistic ceiling, K = R.
Per method the metrics.summary numbers are reported, plus

    extract_ms         median per image of the full extraction (resize, backbone, head, selection;
                       holistic: resize, backbone, max pool), timed on a few images of the dataset
    match_ms_per_pair  median over timed queries of (rerank time of one query / its K candidates);
                       holistic: the global-descriptor dot products of one query / R
    n                  landmarks per image (median; `all` depends on the image size); holistic 1

Timing runs every method round-robin on the same images / queries and keeps the best of
`timing_repeats` rounds each, so load from other processes does not favour one method.

Outputs in out_dir: results.json, results.md, and PNGs per dataset: PR curves of every method
(paper Fig. 5), holistic recall@K (Fig. 4), LLN activation heatmaps with the selected cells
(Fig. 3), and match pictures of successes and failures (Fig. 7).
"""
from __future__ import annotations

import copy
import functools
import json
import math
import os
import re
import statistics
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from . import metrics
from .errors import DatasetError, ModelError
from .features import FeatureCache
from .landmarks import METHODS as LOCAL_METHODS, LandmarkSet, l2_normalize, stack_landmarks
from .lln import LLNHead, head_fingerprint, load_checkpoint
from .reloc import eval_conf as reloc_eval_conf, evaluate_reloc, reloc_markdown
from .peers import PEER_METHODS, SadFrontEnd, peer_row, sequence_row
from .sequence import check_conf as sequence_conf, default_conf as sequence_defaults, sad_conf
from .landmark_index import check_prefilter
from .retrieval import batch_index, default_conf as retrieval_conf, first_stage, rank_all
from .similarity import match_batch, match_pair

METHODS = ('holistic',) + tuple(LOCAL_METHODS)   # the paper's rows, the default
ALL_METHODS = METHODS + PEER_METHODS             # plus the classic peers (opt-in: --methods ...,sad,seqslam)
METRIC_KEYS = ('p_at_100r', 'r_at_1', 'r_at_5', 'r_at_10', 'auc_pr', 'r_at_100p')
REPORT_KEYS = METRIC_KEYS + ('extract_ms', 'match_ms_per_pair', 'n')

default_conf = {
    'methods': METHODS,
    'top_n': 50,
    'prefilter': retrieval_conf['prefilter'],  # first stage: landmarks | holistic | exhaustive
    'prefilter_k': retrieval_conf['prefilter_k'],  # first-stage candidates reranked by S (0 = all)
    'scale': 1.0,           # offset-weight width in grid cells (similarity)
    'sequence': 0,          # L > 0: an `X+seq` row per holistic/local row (sequence length L)
    'seqslam_length': 10,   # seqslam's L when 'sequence' is 0
    'timing_images': 5,     # images per dataset the extraction is timed on
    'timing_queries': 10,   # queries per dataset the rerank is timed on
    'timing_repeats': 3,    # best of this many runs per image / query (a shared CPU is noisy)
    'examples': 2,          # success and failure match pictures per dataset (0 = none)
    'heatmap_images': 4,    # images in the activation heatmap figure (0 = no figure)
    'cache_dir': 'cache/features',
    'plots': True,
    'progress': True,       # tqdm bar while backbone features are computed
    'reloc': False,         # also keypoint relocalization on the first lln row's ranking (reloc.py)
    **reloc_eval_conf,
}

UNTRAINED_WORDS = ('', 'xavier', 'untrained', 'none')
SHIPPED_WORDS = ('shipped', 'default')


@dataclass
class Head:
    """An LLN head to evaluate as its own `lln[label]` row.

    weights: a checkpoint path; None (or '', 'xavier', 'untrained') = a seeded Xavier-init head (the
    untrained baseline); 'shipped' = the head shipped for this backbone/layer; 'extractor' = the
    extractor's own head as configured."""
    label: str
    weights: str | None
    module: LLNHead | None = None
    meta: dict = field(default_factory=dict)

    @property
    def trained(self) -> bool:
        return bool(self.meta.get('trained', True))


def parse_head(text: str, label: str | None = None) -> Head:
    """'LABEL=PATH' or 'PATH' -> Head (not loaded). PATH '' / 'xavier' / 'untrained' = untrained."""
    if label is None and '=' in text:
        label, _, text = text.partition('=')
    weights = None if text.strip().lower() in UNTRAINED_WORDS else text
    if label is None:
        label = 'untrained' if weights is None else (
            'shipped' if weights.lower() in SHIPPED_WORDS else Path(weights).stem)
    return Head(label.strip(), weights)


def load_heads(extractor, heads: list[Head] | None) -> list[Head]:
    """Build every head (checkpoint metadata must fit the extractor's backbone/layer/D). No heads =
    the extractor's own head as one unlabelled head (row 'lln').

    An untrained head is Xavier-initialised with the architecture and init seed of the first
    checkpoint among `heads` (so "trained vs untrained" differs only in training), or with the
    default LLNHead conf when no checkpoint is given."""
    if not heads:
        return [Head('', extractor.model_info.get('weights') or None, extractor.head, dict(extractor.head_meta))]
    name, layer, dim = extractor.conf['backbone']['name'], extractor.backbone.layer, extractor.backbone.dim
    labels = [h.label for h in heads]
    if len(set(labels)) != len(labels):
        raise ModelError(f'head labels must be distinct, got {labels}')
    out: list = [None] * len(heads)
    untrained = []
    for i, h in enumerate(heads):
        w = h.weights
        if h.module is not None:
            out[i] = h
        elif w is None or w.strip().lower() in UNTRAINED_WORDS:
            untrained.append(i)
        elif w == 'extractor':
            out[i] = Head(h.label, extractor.model_info.get('weights') or None, extractor.head,
                          dict(extractor.head_meta))
        else:
            if w.lower() in SHIPPED_WORDS:
                from .extractor import shipped_weights
                path = shipped_weights(name, layer)
                if not path:
                    raise ModelError(f'no LLN head ships for backbone {name!r} layer {layer!r}; '
                                     'pass a checkpoint path')
            else:
                path = os.path.expanduser(w)
            module, meta = load_checkpoint(path, name, layer, dim)
            out[i] = Head(h.label, path, module, meta)
    arch = next((h.module.conf for h in out if h is not None and h.weights), None)
    for i in untrained:
        out[i] = Head(heads[i].label, None, LLNHead(dim, arch).eval(), {'trained': False, 'head_conf': arch})
    for h in out:
        for p in h.module.parameters():
            p.requires_grad_(False)
    return out


def variant(extractor, method: str, top_n: int, head: Head | None = None):
    """A shallow copy of the extractor with its own conf (method, top_n) and, optionally, another
    head. The backbone is shared: no second network is built."""
    v = copy.copy(extractor)
    v.conf = {**extractor.conf, 'method': method, 'top_n': int(top_n)}
    if head is not None:
        v.head, v.head_meta = head.module, head.meta
        v.model_info = {**extractor.model_info, 'head': head_fingerprint(head.module),
                        'head_trained': head.trained, 'weights': head.weights or ''}
    return v


def row_names(methods, heads: list[Head]) -> list[tuple[str, str, Head | None]]:
    """(row name, method, head) for every requested method; lln gets one row per head."""
    rows = []
    for m in methods:
        if m == 'lln':
            for h in heads:
                rows.append(('lln' if len(heads) == 1 and not h.label else f'lln[{h.label}]', 'lln', h))
        else:
            rows.append((m, m, None))
    return rows


def parse_methods(text) -> list[str]:
    methods = [m.strip() for m in (text.split(',') if isinstance(text, str) else text) if m.strip()]
    bad = [m for m in methods if m not in ALL_METHODS]
    if bad or not methods:
        raise ValueError(f'unknown method(s) {bad}; choose from {",".join(ALL_METHODS)}')
    return list(dict.fromkeys(methods))


def slug(name: str) -> str:
    return re.sub(r'[^A-Za-z0-9_.-]+', '_', name).strip('_') or 'dataset'


# ---------------------------------------------------------------------------------------------- core


@dataclass
class DatasetRun:
    """Everything computed for one dataset: the JSON entry and the arrays the pictures need."""
    name: str
    entry: dict
    rankings: dict            # row -> (ranked (Q, K), scores (Q, K))
    holistic_full: np.ndarray  # (Q, R) full holistic ranking
    recall_curve: list


@dataclass
class EvalRun:
    results: dict
    datasets: dict            # name -> DatasetRun
    figures: list


def _median_ms(times) -> float:
    return float(statistics.median(times) * 1e3) if times else float('nan')


def _sizes(ds, which: str, paths: list) -> list[tuple]:
    sizes = ds.info.get(f'{which}_sizes')
    if sizes is not None and len(sizes) == len(paths):
        return [tuple(int(v) for v in s) for s in sizes]
    import cv2
    out = []
    for p in paths:
        im = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
        out.append((im.shape[1], im.shape[0]))
    return out


def _holistic_sets(feats: list[np.ndarray], sizes: list[tuple], space: str) -> list[LandmarkSet]:
    """Global descriptors only (no landmarks): what the holistic baseline compares."""
    out = []
    for f, s in zip(feats, sizes):
        d, rows, cols = f.shape
        g = l2_normalize(np.asarray(f, np.float32).reshape(d, -1).max(axis=1)).astype(np.float32)
        out.append(LandmarkSet(g, np.zeros((0, d), np.float32), np.zeros((0, 2), np.int32),
                               np.zeros((0, 2), np.float32), np.zeros(0, np.float32),
                               np.array([s[0] / cols, s[1] / rows], np.float32), np.array(s, np.float32),
                               (rows, cols), None, space))
    return out


def interleaved_times(jobs: dict, repeats: int = 3) -> dict:
    """Wall times of many jobs measured round-robin, so a burst of load from another process hits
    every method alike (a shared CPU is noisy). jobs: name -> list of (callable, divisor). Each
    callable runs once to warm up, then `repeats` rounds; returns name -> median over its callables
    of (best round time / divisor), in ms."""
    for calls in jobs.values():
        for fn, _ in calls:
            fn()
    best = {name: [math.inf] * len(calls) for name, calls in jobs.items()}
    width = max((len(c) for c in jobs.values()), default=0)
    for _ in range(max(1, int(repeats))):
        for i in range(width):
            for name, calls in jobs.items():
                if i < len(calls):
                    t = time.perf_counter()
                    calls[i][0]()
                    best[name][i] = min(best[name][i], time.perf_counter() - t)
    return {name: _median_ms([b / d for b, (_, d) in zip(best[name], jobs[name])]) for name in jobs}


def extraction_job(extractor, image: np.ndarray, holistic: bool = False):
    """One full extraction of an original-size RGB image: resize, backbone, head, selection
    (holistic: resize, backbone, global max pool, no head)."""
    from .image import resize_for_network
    if not holistic:
        return lambda: extractor(image)

    def run():
        net = resize_for_network(image, int(extractor.conf['input_height']))
        f = extractor.backbone_features(net[None])[0]
        l2_normalize(f.flatten(1).amax(dim=1).numpy())
    return run


def _finite(x):
    if isinstance(x, float) and not math.isfinite(x):
        return None
    return x


def evaluate_dataset(ds, extractor, conf: dict | None = None, heads: list[Head] | None = None,
                     spec: str = '', log=None, out_dir: str | os.PathLike | None = None) -> DatasetRun:
    """Every requested method on one dataset (see the module doc). `heads` must be loaded. With
    out_dir (and conf['plots']) the dataset's PNGs are written there and named in entry['figures']."""
    from .image import load_image
    conf = {**default_conf, **(conf or {})}
    heads = heads or load_heads(extractor, None)
    log = log or (lambda msg: None)
    methods = parse_methods(conf['methods'])
    top_n, scale = int(conf['top_n']), float(conf['scale'])
    k = int(conf['prefilter_k']) or len(ds.ref_paths)  # 0: every reference
    prefilter, _ = check_prefilter(conf['prefilter'], conf['prefilter_k'])
    height = int(extractor.conf['input_height'])
    space = extractor.descriptor_space
    seq_len = int(conf['sequence'])
    seq_conf = sequence_conf({**sequence_defaults, 'length': seq_len or int(conf['seqslam_length'])})
    if (seq_len or 'seqslam' in methods) and seq_conf['length'] > len(ds.ref_paths):
        raise DatasetError(f'{ds.name}: sequence length {seq_conf["length"]} is longer than its map '
                           f'({len(ds.ref_paths)} references)')

    # one backbone pass per distinct image (a loop sequence is its own map)
    paths = list(dict.fromkeys([str(p) for p in ds.ref_paths] + [str(p) for p in ds.query_paths]))
    cache = FeatureCache(conf['cache_dir'], extractor)
    feats = dict(zip(paths, cache.load(paths, size=height,
                                         progress=f'features {ds.name}' if conf['progress'] else None)))
    ref_sizes = _sizes(ds, 'ref', ds.ref_paths)
    query_sizes = _sizes(ds, 'query', ds.query_paths)
    ref_feats = [feats[str(p)] for p in ds.ref_paths]
    query_feats = [feats[str(p)] for p in ds.query_paths]
    same_images = [str(p) for p in ds.ref_paths] == [str(p) for p in ds.query_paths]

    # holistic: the full ranking (recall@K curve) and the shared top-K every local method reranks
    hq = _holistic_sets(query_feats, query_sizes, space)
    hr = hq if same_images else _holistic_sets(ref_feats, ref_sizes, space)
    hr_batch = stack_landmarks(hr)
    full, full_scores = rank_all(hq, hr_batch, len(hr), allowed=ds.candidates, rerank_local=False,
                                 prefilter='holistic')
    prefilter_rows = full[:, :min(k, len(hr))]
    kmax = min(len(hr), max(2 * k, 50) if int(conf['prefilter_k']) else 100)
    curve = [metrics.recall_at_k(full, ds.gt, kk) for kk in range(1, kmax + 1)]

    timing_idx = np.unique(np.linspace(0, len(ds.query_paths) - 1,
                                       min(int(conf['timing_images']), len(ds.query_paths))).astype(int))
    timing_images = [load_image(str(ds.query_paths[i])) for i in timing_idx]
    # timed reranks: queries with the full K candidates (early loop frames have only a few)
    counts = (prefilter_rows >= 0).sum(axis=1)
    answerable = [int(i) for i in np.flatnonzero(counts == counts.max())] if counts.max(initial=0) else []
    pick = np.unique(np.linspace(0, len(answerable) - 1, min(int(conf['timing_queries']), len(answerable)))
                     .astype(int)) if answerable else np.zeros(0, int)
    timed = [(answerable[i], prefilter_rows[answerable[i]]) for i in pick]
    reps = int(conf['timing_repeats'])
    front = SadFrontEnd(ds) if any(m in PEER_METHODS for m in methods) else None

    rankings, rows_out, reloc, stages = {}, {}, None, None
    extract_jobs, match_jobs = {}, {}
    for row, method, head in row_names(methods, heads):
        t0 = time.perf_counter()
        if method == 'holistic':
            ranked, scores = full, full_scores
            extract_jobs[row] = [(extraction_job(extractor, im, True), 1) for im in timing_images]
            match_jobs[row] = [(functools.partial(np.matmul, hr_batch.globals, hq[q].global_descriptor),
                                len(hr_batch)) for q, _ in timed]
            n = 1
        elif method in PEER_METHODS:
            ranked, scores = peer_row(method, front, ds.candidates, k, seq_conf)
            extract_jobs[row] = [(front.extraction_job(ds.query_paths[i]), 1) for i in timing_idx]
            match_jobs[row] = [(front.match_job(q), len(ds.ref_paths)) for q, _ in timed]
            n = 1
        else:
            v = variant(extractor, method, top_n, head if method == 'lln' else None)
            qs = [v.from_features(f, s) for f, s in zip(query_feats, query_sizes)]
            rs = qs if same_images else [v.from_features(f, s) for f, s in zip(ref_feats, ref_sizes)]
            batch = stack_landmarks(rs)
            ranked, scores = rank_all(qs, batch, k, allowed=ds.candidates, scale=scale, prefilter=prefilter)
            # the paper's protocol: the same holistic top-K for every local method, only reordered
            same = prefilter != 'holistic' or \
                all(set(a[a >= 0]) == set(b[b >= 0]) for a, b in zip(ranked, prefilter_rows))
            if not same:
                raise AssertionError(f'{row}: reranked candidates differ from the holistic top-{k}')
            if method == 'lln' and stages is None:
                stages = first_stage_report(qs, batch, ds, full, ranked if prefilter == 'exhaustive' else None,
                                            scale, reps)
            extract_jobs[row] = [(extraction_job(v, im), 1) for im in timing_images]
            # keep only what the timed reranks need (the candidates of a few queries), not the map
            match_jobs[row] = [(functools.partial(match_batch, qs[q], batch.take(c[c >= 0]), scale),
                                int((c >= 0).sum())) for q, c in timed]
            n = int(np.median([len(s) for s in qs]))
            if conf['reloc'] and method == 'lln' and reloc is None:
                t1 = time.perf_counter()
                reloc = evaluate_reloc(ds, qs, rs, ranked, conf, f'reloc {ds.name}' if conf['progress'] else None)
                reloc['row'] = row
                log(f'{ds.name}: reloc success {reloc["regions"]["success_rate"]} (regions) vs '
                    f'{reloc["all"]["success_rate"]} (all) ({time.perf_counter() - t1:.1f} s)')
            del qs, rs, batch
        summary = metrics.summary(ranked, scores[:, 0], ds.gt)
        rows_out[row] = {**{key: _finite(float(summary[key])) for key in METRIC_KEYS}, 'n': n}
        if method == 'lln':
            rows_out[row].update({'head': head.label, 'head_trained': head.trained,
                                  'weights': head.weights or '', 'head_fingerprint': head_fingerprint(head.module)})
        rankings[row] = (ranked, scores)
        log(f'{ds.name}: {row:<16} P@100%R {summary["p_at_100r"]:.3f}  R@100%P {summary["r_at_100p"]:.3f}  '
            f'AUC {summary["auc_pr"]:.3f}  ({time.perf_counter() - t0:.1f} s)')

    # X+seq: the same single-frame rankings fed in stream order through the online sequence search
    for row, method, _ in (row_names(methods, heads) if seq_len else []):
        if method in PEER_METHODS:
            continue
        base = (full, full_scores) if method == 'holistic' else rankings[row]
        ranked, scores, seq_ms = sequence_row(*base, len(ds.ref_paths), seq_conf, ds.candidates, k)
        summary = metrics.summary(ranked, scores[:, 0], ds.gt)
        rows_out[f'{row}+seq'] = {**{key: _finite(float(summary[key])) for key in METRIC_KEYS},
                                  'n': rows_out[row]['n'], 'sequence_of': row,
                                  'sequence_ms_per_query': _finite(seq_ms)}
        rankings[f'{row}+seq'] = (ranked, scores)
        log(f'{ds.name}: {row + "+seq":<16} P@100%R {summary["p_at_100r"]:.3f}  R@100%P '
            f'{summary["r_at_100p"]:.3f}  AUC {summary["auc_pr"]:.3f}  ({seq_ms:.2f} ms/query)')

    # timing: every method round-robin on the same images / queries, best of `timing_repeats` each
    t0 = time.perf_counter()
    extract_ms = interleaved_times(extract_jobs, reps)
    match_ms = interleaved_times(match_jobs, reps)
    del extract_jobs, match_jobs
    for row, m in rows_out.items():
        src = m.get('sequence_of', row)  # X+seq: X's extraction and matching, plus sequence_ms_per_query
        m['extract_ms'] = _finite(extract_ms[src])
        m['match_ms_per_pair'] = _finite(match_ms[src])
        rows_out[row] = {**{key: m[key] for key in REPORT_KEYS}, **m}  # report keys first
    log(f'{ds.name}: timing ({time.perf_counter() - t0:.1f} s)')

    info = {key: v for key, v in ds.info.items() if not key.endswith('_sizes')}
    entry = {
        'queries': len(ds.query_paths),
        'queries_with_match': ds.queries_with_match,
        'refs': len(ds.ref_paths),
        'spec': spec,
        'protocol': 'loop (each query only against allowed older frames)' if ds.candidates is not None
                    else 'two traverses',
        'info': info,
        'grid': list(hq[0].grid) if hq else None,
        'timing': {'images': len(timing_images), 'queries': len(timed),
                   'torch_threads': torch.get_num_threads()},
        'recall_at_k_holistic': [_finite(float(r)) for r in curve],
        'first_stage': stages,
        'methods': rows_out,
    }
    if reloc is not None:
        entry['reloc'] = reloc
    run = DatasetRun(ds.name, entry, rankings, full, curve)
    if out_dir is not None and conf['plots']:
        entry['figures'] = write_figures(run, ds, extractor, heads, conf, feats, ref_sizes, query_sizes,
                                         Path(out_dir))
    return run


FIRST_STAGE_KS = (1, 5, 10, 30, 100)


def first_stage_report(qs: list, batch, ds, holistic_full: np.ndarray, exhaustive: np.ndarray | None,
                       scale: float, repeats: int) -> dict:
    """Recall@K (FIRST_STAGE_KS) of each first stage's own ranking, i.e. the ceiling of a rerank of
    its top K, and its cost per query (ms, best of `repeats` over the timed queries): holistic
    (global cosine over every ref), landmarks (landmark_index search + score_hits) and, when the
    run is exhaustive, S over every ref (its ranking `exhaustive`)."""
    kmax = min(max(FIRST_STAGE_KS), len(batch))
    lm, _ = first_stage(qs, batch, kmax, 'landmarks', ds.candidates, scale=scale)
    out = {'holistic': holistic_full, 'landmarks': lm}
    if exhaustive is not None:
        out['exhaustive'] = exhaustive
    report = {name: {'recall_at': {str(kk): _finite(metrics.recall_at_k(r, ds.gt, kk))
                                   for kk in FIRST_STAGE_KS if kk <= r.shape[1]}}
              for name, r in out.items()}
    pick = np.unique(np.linspace(0, len(qs) - 1, min(10, len(qs))).astype(int))
    index = batch_index(batch)

    def holistic_top(q):
        return np.argsort(-(batch.globals @ q.global_descriptor))[:kmax]
    jobs = {'holistic': [(functools.partial(holistic_top, qs[i]), 1) for i in pick],
            'landmarks': [(functools.partial(index.shortlist, qs[i], kmax, None, scale), 1) for i in pick]}
    for name, ms in interleaved_times(jobs, repeats).items():
        report[name]['ms_per_query'] = _finite(ms)
    return report


def evaluate(datasets: list, extractor, conf: dict | None = None, heads: list[Head] | None = None,
             out_dir: str | os.PathLike | None = None, specs: list[str] | None = None,
             command: str = '', log=None) -> EvalRun:
    """Evaluate every dataset; with out_dir, write results.json, results.md and the PNGs there."""
    conf = {**default_conf, **(conf or {})}
    heads = load_heads(extractor, heads)
    conf['methods'] = parse_methods(conf['methods'])
    names = _unique_names([ds.name for ds in datasets])
    if out_dir is not None:
        Path(out_dir).mkdir(parents=True, exist_ok=True)
    runs = {}
    for ds, name, spec in zip(datasets, names, specs or [''] * len(datasets)):
        ds.name = name
        runs[name] = evaluate_dataset(ds, extractor, conf, heads, spec, log, out_dir)
    results = {
        'datasets': {name: r.entry for name, r in runs.items()},
        'parameters': {
            'methods': [r for r, _, _ in row_names(conf['methods'], heads)],
            'sequence': int(conf['sequence']),
            'sequence_search': {key: sequence_defaults[key] for key in ('v_min', 'v_max', 'v_steps')},
            'seqslam': {'length': int(conf['sequence']) or int(conf['seqslam_length']), **sad_conf},
            'top_n': int(conf['top_n']), 'prefilter_k': int(conf['prefilter_k']), 'scale': float(conf['scale']),
            'prefilter': check_prefilter(conf['prefilter'], conf['prefilter_k'])[0],
            'input_height': int(extractor.conf['input_height']),
            'backbone': extractor.conf['backbone']['name'], 'layer': extractor.backbone.layer,
            'descriptor_space': extractor.descriptor_space, 'rand_seed': int(extractor.conf['rand_seed']),
            'heads': {h.label or 'lln': {'weights': h.weights or '', 'trained': h.trained,
                                         'fingerprint': head_fingerprint(h.module)} for h in heads},
            'timing_images': int(conf['timing_images']), 'timing_queries': int(conf['timing_queries']),
            'timing_repeats': int(conf['timing_repeats']),
            'torch_threads': torch.get_num_threads(),
            'blas_threads': os.environ.get('OPENBLAS_NUM_THREADS') or os.environ.get('OMP_NUM_THREADS') or 'default',
            'feature_cache': str(conf['cache_dir']),
            'command': command,
        },
    }
    if out_dir is not None:
        out = Path(out_dir)
        write_json(results, out / 'results.json')
        write_markdown(results, out / 'results.md')
    return EvalRun(results, runs, [f for r in runs.values() for f in _figure_files(r.entry.get('figures'))])


def _figure_files(figs: dict | None) -> list[str]:
    if not figs:
        return []
    out = [f for key, f in figs.items() if key != 'examples' and f]
    for ex in figs.get('examples', []):
        out += [ex['file']] + ([ex['truth_file']] if ex.get('truth_file') else [])
    return out


def _unique_names(names: list[str]) -> list[str]:
    out, seen = [], {}
    for n in names:
        seen[n] = seen.get(n, 0) + 1
        out.append(n if seen[n] == 1 else f'{n}#{seen[n]}')
    return out


# --------------------------------------------------------------------------------------------- output


def _jsonable(x):
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, (np.integer,)):
        return int(x)
    if isinstance(x, (np.floating, float)):
        return _finite(float(x))
    if isinstance(x, np.ndarray):
        return _jsonable(x.tolist())
    if isinstance(x, Path):
        return str(x)
    return x


def write_json(results: dict, path) -> None:
    tmp = Path(f'{path}.tmp')
    tmp.write_text(json.dumps(_jsonable(results), indent=1, allow_nan=False) + '\n')
    os.replace(tmp, path)


def _pct(x) -> str:
    return '–' if x is None else f'{100 * x:.1f}'


def _ms(x) -> str:
    if x is None:
        return '–'
    return f'{x:.1f}' if x >= 10 else f'{x:.3g}'


def markdown(results: dict) -> str:
    """The results as markdown: one table per dataset, every method, the parameters, the figures."""
    p = results.get('parameters', {})
    lines = ['# lln-eval results', '']
    if p.get('command'):
        lines += ['Regenerate with:', '', '```bash', p['command'], '```', '']
    lines += ['Percentages of the queries that have a true match; P@100%R = precision when every query is '
              'answered (= top-1 accuracy, the paper\'s headline), R@100%P = largest recall at precision 1, '
              'AUC-PR = area under the precision-recall curve of a threshold on the top-1 score. ' +
              ({'holistic': 'Every local method reranks the same holistic top-K.',
                'landmarks': 'Every local method reranks the top-K of the landmark first stage, run on its own '
                             'landmarks (prefilter landmarks).',
                'exhaustive': 'Every local method scores every reference (exhaustive, no first stage).'}
               [p.get('prefilter', 'holistic' if p.get('prefilter_k', 30) else 'exhaustive')]), '']
    for name, d in results['datasets'].items():
        lines += [f'## {name}', '']
        facts = [f'{d["queries"]} queries ({d.get("queries_with_match", "?")} with a true match), '
                 f'{d.get("refs", "?")} references; {d.get("protocol", "")}']
        if d.get('spec'):
            facts.append(f'spec `{d["spec"]}`')
        info = {k: v for k, v in d.get('info', {}).items() if v not in (None, [], {})}
        if info:
            facts.append('; '.join(f'{k} {v}' for k, v in info.items()))
        if d.get('grid'):
            facts.append(f'feature grid {d["grid"][1]}x{d["grid"][0]} (cols x rows) of the first query')
        lines += ['; '.join(facts) + '.', '']
        lines += ['| method | n | P@100%R | R@100%P | AUC-PR | R@1 | R@5 | R@10 | extract ms/img | match ms/pair |',
                  '|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|']
        best = max((m['p_at_100r'] for m in d['methods'].values() if m['p_at_100r'] is not None), default=None)
        for row, m in d['methods'].items():
            p100 = _pct(m['p_at_100r'])
            if best is not None and m['p_at_100r'] == best:
                p100 = f'**{p100}**'
            label = row
            if row.startswith('lln') and not m.get('head_trained', True) and 'untrained' not in row:
                label += ' (untrained head)'
            lines.append(f'| {label} | {m["n"]} | {p100} | {_pct(m["r_at_100p"])} | {_pct(m["auc_pr"])} | '
                         f'{_pct(m["r_at_1"])} | {_pct(m["r_at_5"])} | {_pct(m["r_at_10"])} | '
                         f'{_ms(m["extract_ms"])} | {_ms(m["match_ms_per_pair"])} |')
        curve = d.get('recall_at_k_holistic') or []
        k = p.get('prefilter_k')
        if curve and k == 0:
            lines += ['', 'Exhaustive (prefilter_k 0): every reference is scored, so the holistic ranking '
                          f'caps nothing (holistic recall@30 = {_pct(curve[min(30, len(curve)) - 1])}% for comparison).']
        elif curve and k and p.get('prefilter', 'holistic') == 'holistic':
            at = curve[min(k, len(curve)) - 1]
            lines += ['', f'Holistic recall@{min(k, len(curve))} = {_pct(at)}%: the ceiling of every reranking '
                          'method (a true match outside the holistic top-K cannot be recovered).']
        stages = d.get('first_stage') or {}
        if stages:
            ks = [kk for kk in FIRST_STAGE_KS if any(str(kk) in st['recall_at'] for st in stages.values())]
            lines += ['', 'First stage (lln landmarks): recall@K of its own ranking = the ceiling of a rerank of '
                          'its top K, and its cost per query.', '',
                      '| first stage | ' + ' | '.join(f'R@{kk}' for kk in ks) + ' | ms/query |',
                      '|---|' + '---:|' * (len(ks) + 1)]
            for name, st in stages.items():
                lines.append(f'| {name} | ' + ' | '.join(_pct(st['recall_at'].get(str(kk))) for kk in ks) +
                             f' | {_ms(st.get("ms_per_query"))} |')
        t = d.get('timing', {})
        if t:
            lines += ['', f'Timing: extraction median over {t.get("images")} images, matching median over '
                          f'{t.get("queries")} queries (each the best of {p.get("timing_repeats", 1)} runs), '
                          f'CPU, {t.get("torch_threads")} torch threads.']
        if d.get('reloc'):
            lines += [''] + reloc_markdown(d['reloc'])
        figs = d.get('figures') or {}
        if figs:
            lines += ['']
            for key in ('pr', 'recall_at_k', 'heatmaps'):
                if figs.get(key):
                    lines.append(f'![{name} {key}]({figs[key]})')
            for ex in figs.get('examples', []):
                lines.append(f'- {ex["kind"]}: [{ex["file"]}]({ex["file"]}) {ex["caption"]}'
                             + (f' — against its true match: [{ex["truth_file"]}]({ex["truth_file"]})'
                                if ex.get('truth_file') else ''))
        lines.append('')
    if p:
        lines += ['## Parameters', '']
        for key in ('backbone', 'layer', 'descriptor_space', 'input_height', 'top_n', 'prefilter', 'prefilter_k', 'scale',
                    'rand_seed', 'timing_images', 'timing_queries', 'timing_repeats', 'torch_threads',
                    'blas_threads', 'feature_cache', 'sequence', 'sequence_search', 'seqslam'):
            if key in p:
                lines.append(f'- {key}: `{p[key]}`')
        for label, h in p.get('heads', {}).items():
            lines.append(f'- head `{label}`: weights `{h["weights"] or "(Xavier init, seed 0)"}`, '
                         f'trained {h["trained"]}, fingerprint `{h["fingerprint"]}`')
        lines += ['', 'Rows: `holistic` = global max-pool descriptor ranking, no rerank, n = 1 (one vector per '
                      'image); `lln`/`lln[X]` = top-n cells by the activation of LLN head X; `act` = top-n by '
                      'feature norm; `rand` = the same n random cells in every image; `all` = every cell '
                      '(n = median cells per image); `sad` = mean absolute difference of patch-normalised thumbnails, '
                      '`seqslam` = the same, contrast-enhanced, with the sequence search; `X+seq` = row X\'s '
                      'single-frame scores through the causal sequence search (the last L queries, '
                      'constant velocity in the given range). Only the lln rows use a head. `extract ms/img` = full '
                      'extraction from the original image (resize, backbone, head, selection; holistic: no '
                      'head); `match ms/pair` = one query\'s rerank divided by its candidates (holistic: '
                      'dot products with every reference). Features are cached as float16.', '']
    return '\n'.join(lines) + '\n'


def write_markdown(results: dict, path) -> None:
    Path(path).write_text(markdown(_jsonable(results)))


# -------------------------------------------------------------------------------------------- figures


def _pyplot():
    from . import plotting  # noqa: F401  (selects the Agg backend first: files only, no display)
    import matplotlib.pyplot as plt
    return plt


def _colours(rows: list[str]) -> dict:
    plt = _pyplot()
    fixed = {'holistic': 'tab:gray', 'act': 'tab:green', 'rand': 'tab:orange', 'all': 'tab:purple',
             'sad': 'black', 'seqslam': 'tab:olive'}
    lln_cols = iter(['tab:blue', 'tab:red', 'tab:cyan', 'tab:brown', 'tab:pink'])
    out = {}
    for r in rows:
        out[r] = fixed.get(r) or next(lln_cols, None) or plt.get_cmap('tab20')(len(out) % 20)
    return out


def plot_pr(run: DatasetRun, gt: np.ndarray, path) -> None:
    """PR curves of every method on one plot (the paper's Fig. 5)."""
    plt = _pyplot()
    colours = _colours(list(run.rankings))
    fig, ax = plt.subplots(figsize=(6.4, 5), dpi=110)
    for row, (ranked, scores) in run.rankings.items():
        prec, rec, _ = metrics.pr_curve(ranked, scores[:, 0], gt)
        m = run.entry['methods'][row]
        style = '--' if row == 'holistic' else '-'
        ax.plot(np.r_[0.0, rec], np.r_[prec[:1] if len(prec) else [1.0], prec], style, color=colours[row],
                lw=1.6, label=f'{row}: P@100%R {_pct(m["p_at_100r"])}%, AUC {m["auc_pr"] or 0:.2f}')
    ax.set_xlim(0, 1.01)
    ax.set_ylim(0, 1.02)
    ax.set_xlabel('recall')
    ax.set_ylabel('precision')
    ax.grid(alpha=0.3)
    ax.set_title(f'{run.name}: precision-recall (threshold on top-1 score)', fontsize=9)
    ax.legend(fontsize=7, loc='lower left')
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def plot_recall_at_k(run: DatasetRun, gt: np.ndarray, prefilter_k: int, path) -> None:
    """Holistic recall@K against K (the paper's Fig. 4), reranked methods within the top-K dashed."""
    plt = _pyplot()
    colours = _colours(list(run.rankings))
    fig, ax = plt.subplots(figsize=(6.4, 4.4), dpi=110)
    ks = np.arange(1, len(run.recall_curve) + 1)
    ax.plot(ks, run.recall_curve, '-o', ms=2.5, color=colours.get('holistic', 'tab:gray'), label='holistic')
    for row, (ranked, _) in run.rankings.items():
        if row == 'holistic':
            continue
        kk = np.arange(1, min(ranked.shape[1], len(run.recall_curve)) + 1)
        ax.plot(kk, [metrics.recall_at_k(ranked, gt, int(k)) for k in kk], '--', lw=1, color=colours[row],
                label=f'{row} (reranked top-{ranked.shape[1]})')
    if prefilter_k:  # 0: exhaustive, no cut-off to mark
        ax.axvline(prefilter_k, color='k', lw=0.8, ls=':')
        ax.text(prefilter_k, 0.02, f' K = {prefilter_k}', fontsize=8)
    ax.set_ylim(0, 1.02)
    ax.set_xlabel('K (candidates)')
    ax.set_ylabel('recall@K')
    ax.grid(alpha=0.3)
    ax.set_title(f'{run.name}: a true match among the top K', fontsize=9)
    ax.legend(fontsize=7, loc='lower right')
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def plot_heatmaps(images: list[np.ndarray], rows: list[tuple[str, list, list]], path, title: str = '') -> None:
    """Grid of images (columns) x selectors (rows): score-map heatmap and the selected cells outlined
    (the paper's Fig. 3). rows: (label, score maps (rows, cols) per image, LandmarkSets per image)."""
    from matplotlib.patches import Rectangle
    from .plotting import heatmap
    plt = _pyplot()
    nr, nc = len(rows), len(images)
    fig, axes = plt.subplots(nr, nc, figsize=(3.2 * nc, 2.6 * nr + 0.4), dpi=100, squeeze=False)
    for r, (label, maps, sets) in enumerate(rows):
        for c, img in enumerate(images):
            ax = axes[r][c]
            ax.imshow(img)
            heat = heatmap(maps[c], (img.shape[1], img.shape[0]))
            ax.imshow(heat, cmap='jet', alpha=0.55 * heat)
            s = sets[c]
            for (u, v) in s.centers:
                w, h = s.cell_size
                ax.add_patch(Rectangle((u - w / 2, v - h / 2), w, h, fill=False, lw=0.8, ec='white'))
            ax.set_xticks([])
            ax.set_yticks([])
            if c == 0:
                ax.set_ylabel(label, fontsize=8)
    if title:
        fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def write_figures(run: DatasetRun, ds, extractor, heads: list[Head], conf: dict, feats: dict,
                  ref_sizes: list, query_sizes: list, out: Path) -> dict:
    """PNGs of one dataset; returns {'pr', 'recall_at_k', 'heatmaps': file, 'examples': [...]}."""
    from .image import load_image
    from .plotting import plot_matches
    stem = slug(run.name)
    figs: dict = {}
    figs['pr'] = f'{stem}_pr.png'
    plot_pr(run, ds.gt, out / figs['pr'])
    figs['recall_at_k'] = f'{stem}_recall_at_k.png'
    plot_recall_at_k(run, ds.gt, int(conf['prefilter_k']), out / figs['recall_at_k'])
    top_n, scale = int(conf['top_n']), float(conf['scale'])
    methods = parse_methods(conf['methods'])
    qfeat = lambda i: feats[str(ds.query_paths[i])]  # noqa: E731
    rfeat = lambda i: feats[str(ds.ref_paths[i])]  # noqa: E731

    count = min(int(conf['heatmap_images']), len(ds.query_paths))
    if count:
        idx = np.unique(np.linspace(0, len(ds.query_paths) - 1, count).astype(int))
        images = [load_image(str(ds.query_paths[i])) for i in idx]
        rows = []
        show = heads if 'lln' in methods or len(heads) > 1 else heads[:1]
        for h in show:
            v = variant(extractor, 'lln', top_n, h)
            sets = [v.from_features(qfeat(i), query_sizes[i]) for i in idx]
            label = f'LLN {h.label}'.strip() + ('' if h.trained else ' (untrained)')
            rows.append((label, [s.activation for s in sets], sets))
        if 'act' in methods:
            v = variant(extractor, 'act', top_n)
            sets = [v.from_features(qfeat(i), query_sizes[i]) for i in idx]
            norms = [np.linalg.norm(np.asarray(qfeat(i), np.float32), axis=0) for i in idx]
            rows.append(('ACT (feature norm)', norms, sets))
        figs['heatmaps'] = f'{stem}_heatmaps.png'
        plot_heatmaps(images, rows, out / figs['heatmaps'],
                      f'{run.name}: score maps and the top-{top_n} cells (queries {", ".join(map(str, idx))})')

    # match pictures: the first lln row (else the first local row), confident successes and failures
    local = [(r, m, h) for r, m, h in row_names(methods, heads) if m in LOCAL_METHODS]
    figs['examples'] = []
    if not local or int(conf['examples']) <= 0:
        return figs
    row, method, head = local[0]
    v = variant(extractor, method, top_n, head if method == 'lln' else None)
    ranked, scores = run.rankings[row]
    correct = metrics.top1_correct(ranked, ds.gt)
    answered = ranked[:, 0] >= 0
    has = ds.gt.any(1)
    order = np.argsort(-scores[:, 0], kind='stable')
    wins = [int(q) for q in order if correct[q]]
    fails = [int(q) for q in order if answered[q] and has[q] and not correct[q]]
    n_ex = int(conf['examples'])
    pick_wins = [wins[int(i)] for i in np.unique(np.linspace(0, len(wins) - 1, min(n_ex, len(wins))).astype(int))] \
        if wins else []
    k = ranked.shape[1]
    for kind, queries in (('success', pick_wins), ('failure', fails[:n_ex])):
        for j, q in enumerate(queries, 1):
            r = int(ranked[q, 0])
            qs = v.from_features(qfeat(q), query_sizes[q])
            rs = v.from_features(rfeat(r), ref_sizes[r])
            res = match_pair(qs, rs, scale)
            qimg, rimg = load_image(str(ds.query_paths[q])), load_image(str(ds.ref_paths[r]))
            name = f'{stem}_{slug(row)}_{kind}{j}_q{q}.png'
            truth = np.flatnonzero(ds.gt[q])
            hol_rank = int(np.flatnonzero(np.isin(run.holistic_full[q], truth))[0]) + 1 \
                if np.isin(run.holistic_full[q], truth).any() else None
            verdict = 'correct' if kind == 'success' else f'WRONG (true: {", ".join(map(str, truth[:5]))})'
            line1 = (f'query {q} ({Path(ds.query_paths[q]).name}) -> ref {r} ({Path(ds.ref_paths[r]).name}), '
                     f'{verdict}')
            line2 = (f'S = {scores[q, 0]:.2f}, {len(res.pairs(0)["weight"])} mutual pairs; first true match at '
                     f'holistic rank {hol_rank}'
                     + (f' (outside the top-{k}: no rerank can recover it)' if hol_rank and hol_rank > k else ''))
            caption = f'{line1}, {line2}'
            plot_matches(qimg, rimg, qs, rs, res.pairs(0), str(out / name),
                         title=f'{run.name} {row}: {line1}\n{line2}')
            ex = {'kind': kind, 'file': name, 'query': q, 'answer': r, 'score': float(scores[q, 0]),
                  'caption': caption}
            if kind == 'failure' and len(truth):
                true_sets = [v.from_features(rfeat(int(t)), ref_sizes[int(t)]) for t in truth]
                tres = match_batch(qs, stack_landmarks(true_sets), scale)
                b = int(np.argmax(tres.scores))
                t = int(truth[b])
                tname = f'{stem}_{slug(row)}_{kind}{j}_q{q}_truth.png'
                plot_matches(qimg, load_image(str(ds.ref_paths[t])), qs, true_sets[b], tres.pairs(b),
                             str(out / tname), title=f'{run.name} {row}: query {q} vs its true match ref {t}\n'
                                                     f'S = {tres.scores[b]:.2f} (the wrong answer ref {r} scored '
                                                     f'{scores[q, 0]:.2f})')
                ex['truth_file'] = tname
                ex['truth'] = t
            figs['examples'].append(ex)
    return figs


# ------------------------------------------------------------------------------------------ download

GARDENS_POINT_URL = 'https://www.tu-chemnitz.de/etit/proaut/datasets/GardensPoint_Walking.zip'
GARDENS_POINT_FOLDERS = ('day_left', 'day_right', 'night_right')


def _zip_layout(names: list[str], folders) -> str | None:
    """The prefix ('' or 'top/') under which every folder holds at least one image, or None."""
    from .datasets import IMAGE_SUFFIXES
    files = [n for n in names if not n.endswith('/')]
    prefixes = [''] + sorted({n.split('/')[0] + '/' for n in files if '/' in n})
    for pre in prefixes:
        if all(any(n.startswith(f'{pre}{f}/') and n.lower().endswith(IMAGE_SUFFIXES)
                   and '/' not in n[len(pre) + len(f) + 1:] for n in files) for f in folders):
            return pre
    return None


def fetch_gardenspoint(root, url: str = GARDENS_POINT_URL, folders=GARDENS_POINT_FOLDERS,
                       timeout: float = 60.0, progress: bool = True) -> list[str]:
    """Download GardensPoint_Walking.zip into root, check it is a zip holding the expected traverse
    folders (at its top or under one top folder), and extract those folders into root. Folders that
    already exist in root are left alone. Returns the folders extracted. DatasetError on any problem
    (unreachable URL, truncated download, not a zip, corrupt member, missing folders, unsafe paths)."""
    import shutil
    import urllib.error
    import urllib.request
    import zipfile
    from tqdm import tqdm
    from .errors import DatasetError
    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    part = root / '.GardensPoint_Walking.zip.part'
    try:
        try:
            with urllib.request.urlopen(url, timeout=timeout) as resp, open(part, 'wb') as fh:
                total = int(resp.headers.get('Content-Length') or 0)
                with tqdm(total=total or None, unit='B', unit_scale=True, desc=Path(url).name or 'download',
                          disable=not progress) as bar:
                    got = 0
                    for block in iter(lambda: resp.read(1 << 20), b''):
                        fh.write(block)
                        got += len(block)
                        bar.update(len(block))
        except (urllib.error.URLError, OSError, ValueError) as e:
            raise DatasetError(f'cannot download {url}: {getattr(e, "reason", None) or e}') from e
        if total and got != total:
            raise DatasetError(f'download of {url} is truncated: {got} of {total} bytes')
        if not zipfile.is_zipfile(part):
            head = part.read_bytes()[:16]
            raise DatasetError(f'{url} is not a zip archive ({got} bytes starting {head!r})')
        with zipfile.ZipFile(part) as z:
            names = z.namelist()
            unsafe = [n for n in names if n.startswith(('/', '\\')) or '..' in Path(n).parts or ':' in n]
            if unsafe:
                raise DatasetError(f'{url}: the archive holds unsafe paths, e.g. {unsafe[0]!r}')
            pre = _zip_layout(names, folders)
            if pre is None:
                tops = sorted({n.split('/')[0] for n in names})[:8]
                raise DatasetError(f'{url}: the archive lacks the Gardens Point folders {"/, ".join(folders)}/ '
                                   f'with images (its top level: {", ".join(tops) or "nothing"})')
            bad = z.testzip()
            if bad is not None:
                raise DatasetError(f'{url}: archive member {bad!r} is corrupt')
            tmp = root / '.GardensPoint_Walking.extract'
            shutil.rmtree(tmp, ignore_errors=True)
            wanted = [f for f in folders if not (root / f).exists()]
            for n in names:
                for f in wanted:
                    if n.startswith(f'{pre}{f}/'):
                        z.extract(n, tmp)
            for f in wanted:  # move whole folders into place: no half-extracted traverse is ever visible
                os.replace(tmp / pre / f if pre else tmp / f, root / f)
            shutil.rmtree(tmp, ignore_errors=True)
        return wanted
    finally:
        part.unlink(missing_ok=True)
