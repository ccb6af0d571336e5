"""Offline evaluation of place recognition: every method on every dataset, the paper's protocol.

    from lln_ros.eval import Head, evaluate
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
    sad, seqslam   classic peers (eval/peers.py): patch-normalised thumbnails, single frame / sequence
    X+seq          with conf['sequence'] = L > 0: row X's ranking made sequence-consistent
                   (lln_ros.core.sequence, the search the matcher node runs online)

Every local method reranks the SAME first-stage top-K (prefilter, prefilter_k; the paper's: holistic,
30) by the landmark similarity S (retrieval.rank_all); loop datasets restrict answers with
`allowed=ds.candidates`. prefilter_k 0 scores every reference (exhaustive): no ceiling, K = R.
X+seq rows of local methods search the rerank of max(prefilter_k, sequence_prefilter_k) candidates
(retrieval.candidates_k), as the matcher does with sequence_length > 0. A dataset that is not a
sequence (Dataset.sequence False: a VPR-Bench folder of unrelated places) gets no X+seq and no
seqslam rows, and a note in its entry saying so.
Per method the metrics.summary numbers are reported, plus

    extract_ms         median per image of the full extraction (resize, backbone, head, selection;
                       holistic: resize, backbone, max pool), timed on a few images of the dataset
    match_ms_per_pair  median over timed queries of (rerank time of one query / its K candidates);
                       holistic: the global-descriptor dot products of one query / R
    n                  landmarks per image (median; `all` depends on the image size); holistic 1

and per dataset `per_query`: every row's top-1 reference per query and the queries (with a true
match) it gets wrong, to compare two rows query by query.

Timing runs every method round-robin on the same images / queries and keeps the best of
`timing_repeats` rounds each, so load from other processes does not favour one method.

Outputs in out_dir: results.json, results.md, and PNGs per dataset: PR curves of every method
(paper Fig. 5), holistic recall@K (Fig. 4), LLN activation heatmaps with the selected cells
(Fig. 3), and match pictures of successes and failures (Fig. 7).
"""

from __future__ import annotations

import functools
import os
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from ..core import metrics
from ..core.extractor import default_conf as extractor_defaults
from ..core.landmark_index import check_prefilter
from ..core.landmark_index import default_conf as landmark_index_defaults
from ..core.landmarks import LandmarkSet, l2_normalize, stack_landmarks
from ..core.lln import head_fingerprint
from ..core.retrieval import batch_index, candidates_k, rank_all, rank_all_at
from ..core.retrieval import default_conf as retrieval_defaults
from ..core.sequence import acquiring, sad_conf
from ..core.sequence import check_conf as sequence_conf
from ..core.sequence import default_conf as sequence_defaults
from ..core.similarity import default_conf as similarity_defaults
from ..core.similarity import match_batch
from ..errors import DatasetError
from ..io.features import FeatureCache
from .figures import figure_files, write_figures
from .first_stage import first_stage_report, weighted_sums
from .methods import (
    METHODS,
    METRIC_KEYS,
    PEER_METHODS,
    REPORT_KEYS,
    Head,
    load_heads,
    parse_methods,
    row_names,
    variant,
)
from .peers import SadFrontEnd, peer_row, sequence_row
from .reloc import eval_conf as reloc_eval_conf
from .reloc import evaluate_reloc
from .report import finite, write_json, write_markdown
from .timing import extraction_job, interleaved_times

# the first stage's settings lln-eval sets (landmark_index conf keys), typed
LANDMARK_CONF = {'landmark_whitening': bool, 'landmark_knn': int, 'landmark_alpha': float}
default_conf = {
    'methods': METHODS,
    'top_n': extractor_defaults['top_n'],
    # holistic candidates every local method reranks (the paper's 30; 0 = all)
    'prefilter': retrieval_defaults['prefilter'],  # first stage: landmarks | holistic | exhaustive
    'prefilter_k': retrieval_defaults['prefilter_k'],
    # X+seq rows of local methods rerank this many first-stage candidates (retrieval.candidates_k)
    'sequence_prefilter_k': retrieval_defaults['sequence_prefilter_k'],
    'scale': retrieval_defaults['scale'],  # offset-weight width in grid cells (similarity)
    # S's sets, one flag each, similarity's default on: minus each set's mean (center True), then
    # whitened (center='whiten'), raw S + fusion_weight x whitened S (center='fuse')
    'similarity_center': similarity_defaults['center'] is True,
    'similarity_whitening': similarity_defaults['center'] == 'whiten',
    'similarity_fusion': similarity_defaults['center'] == 'fuse',
    **{key: landmark_index_defaults[key] for key in LANDMARK_CONF},  # the first stage's, as its index's
    'sequence': 0,  # L > 0: an `X+seq` row per holistic/local row (sequence length L)
    'sequence_carry': retrieval_defaults['sequence_carry'],  # X+seq of local rows: the matcher's sequence_carry
    'sequence_acquire_k': retrieval_defaults['sequence_acquire_k'],  # ... and its candidates while the window fills
    'sequence_score_norm': sequence_defaults['score_norm'],  # X+seq rows (seqslam keeps its own, sequence.py)
    'seqslam_length': sequence_defaults['length'],  # seqslam's L when 'sequence' is 0
    'timing_images': 5,  # images per dataset the extraction is timed on
    'timing_queries': 10,  # queries per dataset the rerank is timed on
    'timing_repeats': 3,  # best of this many runs per image / query (a shared CPU is noisy)
    'examples': 2,  # success and failure match pictures per dataset (0 = none)
    'heatmap_images': 4,  # images in the activation heatmap figure (0 = no figure)
    'cache_dir': 'cache/features',
    'plots': True,
    'progress': True,  # tqdm bar while backbone features are computed
    'reloc': False,  # also keypoint relocalization on the first lln row's ranking (reloc.py)
    **reloc_eval_conf,
}
ECHOED = {'top_n': int, 'prefilter_k': int, 'scale': float, 'sequence_carry': int, 'sequence_score_norm': str}
ECHOED['sequence_acquire_k'] = int
ECHOED |= LANDMARK_CONF | dict.fromkeys(('similarity_center', 'similarity_whitening', 'similarity_fusion'), bool)


@dataclass
class DatasetRun:
    """Everything computed for one dataset: the JSON entry and the arrays the pictures need."""

    name: str
    entry: dict
    rankings: dict  # row -> (ranked (Q, K), scores (Q, K))
    holistic_full: np.ndarray  # (Q, R) full holistic ranking
    recall_curve: list


@dataclass
class EvalRun:
    results: dict
    datasets: dict  # name -> DatasetRun
    figures: list


def _sizes(ds, which: str, paths: list) -> list[tuple]:
    sizes = ds.info.get(f'{which}_sizes')
    if sizes is not None and len(sizes) == len(paths):
        return [tuple(int(v) for v in s) for s in sizes]
    import cv2

    shapes = [cv2.imread(str(p), cv2.IMREAD_UNCHANGED).shape for p in paths]
    return [(shape[1], shape[0]) for shape in shapes]


def _holistic_sets(feats: list[np.ndarray], sizes: list[tuple], space: str) -> list[LandmarkSet]:
    """Global descriptors only (no landmarks): what the holistic baseline compares."""
    out = []
    for f, s in zip(feats, sizes):
        d, rows, cols = f.shape
        g = l2_normalize(np.asarray(f, np.float32).reshape(d, -1).max(axis=1)).astype(np.float32)
        out.append(
            LandmarkSet(
                g,
                np.zeros((0, d), np.float32),
                np.zeros((0, 2), np.int32),
                np.zeros((0, 2), np.float32),
                np.zeros(0, np.float32),
                np.array([s[0] / cols, s[1] / rows], np.float32),
                np.array(s, np.float32),
                (rows, cols),
                None,
                space,
            )
        )
    return out


def evaluate_dataset(
    ds,
    extractor,
    conf: dict | None = None,
    heads: list[Head] | None = None,
    spec: str = '',
    log=None,
    out_dir: str | os.PathLike | None = None,
) -> DatasetRun:
    """Every requested method on one dataset (see the module doc). `heads` must be loaded. With
    out_dir (and conf['plots']) the dataset's PNGs are written there and named in entry['figures']."""
    from ..io.image import load_image

    conf = {**default_conf, **(conf or {})}
    heads = heads or load_heads(extractor, None)
    log = log or (lambda msg: None)
    methods = parse_methods(conf['methods'])
    notes = []
    if not getattr(ds, 'sequence', True) and (int(conf['sequence']) or 'seqslam' in methods):
        # a sequence search over files that are not one route rewards file order, not places
        skipped = ([f'--sequence {int(conf["sequence"])} rows'] if int(conf['sequence']) else []) + (
            ['seqslam'] if 'seqslam' in methods else []
        )
        notes.append(
            f'{" and ".join(skipped)} skipped: the dataset is not a sequence (its files are not ordered '
            'along one route; add sequence=1 to the spec if they are)'
        )
        log(f'{ds.name}: {notes[-1]}')
        methods = [m for m in methods if m != 'seqslam']
        conf = {**conf, 'sequence': 0}
    top_n, scale = int(conf['top_n']), float(conf['scale'])
    fuse, whiten = conf['similarity_fusion'], conf['similarity_whitening']  # precedence: fusion, whitening, centring
    center = 'fuse' if fuse else 'whiten' if whiten else bool(conf['similarity_center'])
    k = int(conf['prefilter_k']) or len(ds.ref_paths)  # 0: every reference
    prefilter, _ = check_prefilter(conf['prefilter'], conf['prefilter_k'])
    height = int(extractor.conf['input_height'])
    space = extractor.descriptor_space
    seq_len, norm = int(conf['sequence']), conf['sequence_score_norm']
    seq_conf = sequence_conf({'length': seq_len or int(conf['seqslam_length']), 'score_norm': norm})
    k_seq = candidates_k(conf['prefilter_k'], conf['sequence_prefilter_k'], bool(seq_len))
    k_acq = max(k_seq, int(conf['sequence_acquire_k'])) if k_seq and conf['sequence_acquire_k'] else k_seq
    if (seq_len or 'seqslam' in methods) and seq_conf['length'] > len(ds.ref_paths):
        raise DatasetError(
            f'{ds.name}: sequence length {seq_conf["length"]} is longer than its map ({len(ds.ref_paths)} references)'
        )

    # one backbone pass per distinct image (a loop sequence is its own map)
    paths = list(dict.fromkeys([str(p) for p in ds.ref_paths] + [str(p) for p in ds.query_paths]))
    cache = FeatureCache(conf['cache_dir'], extractor)
    feats = dict(
        zip(paths, cache.load(paths, size=height, progress=f'features {ds.name}' if conf['progress'] else None))
    )
    ref_sizes = _sizes(ds, 'ref', ds.ref_paths)
    query_sizes = _sizes(ds, 'query', ds.query_paths)
    ref_feats = [feats[str(p)] for p in ds.ref_paths]
    query_feats = [feats[str(p)] for p in ds.query_paths]
    same_images = [str(p) for p in ds.ref_paths] == [str(p) for p in ds.query_paths]

    # holistic: the full ranking (recall@K curve) and the shared top-K every local method reranks
    hq = _holistic_sets(query_feats, query_sizes, space)
    hr = hq if same_images else _holistic_sets(ref_feats, ref_sizes, space)
    hr_batch = stack_landmarks(hr)
    full, full_scores = rank_all(hq, hr_batch, len(hr), allowed=ds.candidates, rerank_local=False, prefilter='holistic')
    prefilter_rows = full[:, : min(k, len(hr))]
    kmax = min(len(hr), max(2 * k, 50) if int(conf['prefilter_k']) else 100)
    curve = [metrics.recall_at_k(full, ds.gt, kk) for kk in range(1, kmax + 1)]

    timing_idx = np.unique(
        np.linspace(0, len(ds.query_paths) - 1, min(int(conf['timing_images']), len(ds.query_paths))).astype(int)
    )
    timing_images = [load_image(str(ds.query_paths[i])) for i in timing_idx]
    # timed reranks: queries with the full K candidates (early loop frames have only a few)
    counts = (prefilter_rows >= 0).sum(axis=1)
    answerable = [int(i) for i in np.flatnonzero(counts == counts.max())] if counts.max(initial=0) else []
    pick = (
        np.unique(np.linspace(0, len(answerable) - 1, min(int(conf['timing_queries']), len(answerable))).astype(int))
        if answerable
        else np.zeros(0, int)
    )
    timed = [(answerable[i], prefilter_rows[answerable[i]]) for i in pick]
    reps = int(conf['timing_repeats'])
    front = SadFrontEnd(ds) if any(m in PEER_METHODS for m in methods) else None

    rankings, rows_out, reloc, stages, score_of = {}, {}, None, None, {}
    seq_bases = {}  # row -> the single-frame ranking of its k_seq candidates, what X+seq searches
    extract_jobs, match_jobs = {}, {}
    for row, method, head in row_names(methods, heads):
        t0 = time.perf_counter()
        if method == 'holistic':
            ranked, scores = full, full_scores
            extract_jobs[row] = [(extraction_job(extractor, im, True), 1) for im in timing_images]
            match_jobs[row] = [
                (functools.partial(np.matmul, hr_batch.globals, hq[q].global_descriptor), len(hr_batch))
                for q, _ in timed
            ]
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
            report_stages = method == 'lln' and stages is None  # the first lln row reports the first stages
            # one landmark index per row, shared by its rerank and its first-stage report; built only
            # where one of them searches it (training it is the expensive part on a large map)
            lm_conf = {key: cast(conf[key]) for key, cast in LANDMARK_CONF.items()}
            index = batch_index(batch, lm_conf) if prefilter == 'landmarks' or report_stages else None
            if seq_len and (k_seq != int(conf['prefilter_k']) or k_acq != k_seq):
                # one first stage of k_acq candidates, one rerank: the single-frame row is its first K, the
                # sequence's its first k_seq but k_acq while the window fills (the Localizer's sequence_acquire_k)
                ks = (int(conf['prefilter_k']), k_seq, k_acq)
                (ranked, scores), base, wide = rank_all_at(
                    qs, batch, ks, ds.candidates, scale, prefilter, index=index, center=center
                )
                seq_bases[row] = acquiring(base, wide, seq_len - 1)
            else:
                ranked, scores = rank_all(
                    qs, batch, k, allowed=ds.candidates, scale=scale, prefilter=prefilter, index=index, center=center
                )
            # the paper's protocol: the same holistic top-K for every local method, only reordered
            same = prefilter != 'holistic' or all(
                set(a[a >= 0]) == set(b[b >= 0]) for a, b in zip(ranked, prefilter_rows)
            )
            if not same:
                raise AssertionError(f'{row}: reranked candidates differ from the holistic top-{k}')
            if report_stages:
                learned = (weighted_sums(v.head, query_feats), weighted_sums(v.head, ref_feats))
                stages = first_stage_report(
                    qs, batch, ds, full, ranked if prefilter == 'exhaustive' else None, scale, reps, index, learned
                )
            extract_jobs[row] = [(extraction_job(v, im), 1) for im in timing_images]
            # keep only what the timed reranks need (the candidates of a few queries), not the map
            match_jobs[row] = [
                (functools.partial(match_batch, qs[q], batch.take(c[c >= 0]), scale, center), int((c >= 0).sum()))
                for q, c in timed
            ]
            n = int(np.median([len(s) for s in qs]))
            score_of[row] = lambda q, refs, qs=qs, b=batch: match_batch(qs[q], b.take(refs), scale, center).scores
            if conf['reloc'] and method == 'lln' and reloc is None:
                t1 = time.perf_counter()
                reloc = evaluate_reloc(ds, qs, rs, ranked, conf, f'reloc {ds.name}' if conf['progress'] else None)
                reloc['row'] = row
                log(
                    f'{ds.name}: reloc success {reloc["regions"]["success_rate"]} (regions) vs '
                    f'{reloc["all"]["success_rate"]} (all) ({time.perf_counter() - t1:.1f} s)'
                )
            del qs, rs, batch, index
        summary = metrics.summary(ranked, scores[:, 0], ds.gt)
        rows_out[row] = {**{key: finite(float(summary[key])) for key in METRIC_KEYS}, 'n': n}
        if method == 'lln':
            rows_out[row].update(
                {
                    'head': head.label,
                    'head_trained': head.trained,
                    'weights': head.weights or '',
                    'head_fingerprint': head_fingerprint(head.module),
                    'held_out': head.held_out(ds),
                }
            )
        rankings[row] = (ranked, scores)
        log(
            f'{ds.name}: {row:<16} P@100%R {summary["p_at_100r"]:.3f}  R@100%P {summary["r_at_100p"]:.3f}  '
            f'AUC {summary["auc_pr"]:.3f}  ({time.perf_counter() - t0:.1f} s)'
            + (f'  [head: {rows_out[row]["held_out"]["status"]}]' if method == 'lln' else '')
        )

    # X+seq: the same single-frame rankings fed in stream order through the online sequence search
    for row, method, _ in row_names(methods, heads) if seq_len else []:
        if method in PEER_METHODS:
            continue
        base = (full, full_scores) if method == 'holistic' else seq_bases.pop(row, rankings[row])
        cands = len(ds.ref_paths) if method == 'holistic' else min(k_seq or len(ds.ref_paths), len(ds.ref_paths))
        carry = (int(conf['sequence_carry']), score_of.get(row))  # holistic rows rank every reference
        ranked, scores, seq_ms = sequence_row(*base, len(ds.ref_paths), seq_conf, ds.candidates, k, *carry)
        summary = metrics.summary(ranked, scores[:, 0], ds.gt)
        rows_out[f'{row}+seq'] = {
            **{key: finite(float(summary[key])) for key in METRIC_KEYS},
            'n': rows_out[row]['n'],
            'sequence_of': row,
            'sequence_candidates': cands,
            'sequence_ms_per_query': finite(seq_ms),
        }
        rankings[f'{row}+seq'] = (ranked, scores)
        log(
            f'{ds.name}: {row + "+seq":<16} P@100%R {summary["p_at_100r"]:.3f}  R@100%P '
            f'{summary["r_at_100p"]:.3f}  AUC {summary["auc_pr"]:.3f}  ({seq_ms:.2f} ms/query)'
        )

    # timing: every method round-robin on the same images / queries, best of `timing_repeats` each
    t0 = time.perf_counter()
    extract_ms = interleaved_times(extract_jobs, reps)
    match_ms = interleaved_times(match_jobs, reps)
    del extract_jobs, match_jobs
    for row, m in rows_out.items():
        src = m.get('sequence_of', row)  # X+seq: X's extraction and matching, plus sequence_ms_per_query
        m['extract_ms'] = finite(extract_ms[src])
        m['match_ms_per_pair'] = finite(match_ms[src])
        rows_out[row] = {**{key: m[key] for key in REPORT_KEYS}, **m}  # report keys first
    log(f'{ds.name}: timing ({time.perf_counter() - t0:.1f} s)')

    info = {key: v for key, v in ds.info.items() if not key.endswith('_sizes')}
    entry = {
        'queries': len(ds.query_paths),
        'queries_with_match': ds.queries_with_match,
        'refs': len(ds.ref_paths),
        'spec': spec,
        'protocol': 'loop (each query only against allowed older frames)'
        if ds.candidates is not None
        else 'two traverses',
        'info': info,
        'sequence': bool(getattr(ds, 'sequence', True)),
        'notes': notes,
        'grid': list(hq[0].grid) if hq else None,
        'timing': {
            'images': len(timing_images),
            'queries': len(timed),
            'torch_threads': torch.get_num_threads(),
            'runtime': extractor.model_info.get('runtime', 'torch'),
        },
        'recall_at_k_holistic': [finite(float(r)) for r in curve],
        'first_stage': stages,
        'methods': rows_out,
        'per_query': per_query_answers(rankings, ds.gt),
    }
    if reloc is not None:
        entry['reloc'] = reloc
    run = DatasetRun(ds.name, entry, rankings, full, curve)
    if out_dir is not None and conf['plots']:
        entry['figures'] = write_figures(run, ds, extractor, heads, conf, feats, ref_sizes, query_sizes, Path(out_dir))
    return run


def per_query_answers(rankings: dict, gt) -> dict:
    """Which queries each row gets wrong, so two rows can be compared query by query (P@100%R only
    says how many). rankings: row -> (ranked (Q, K), scores); gt (Q, R) bool. Query and ref indices
    are positions in the dataset's query / ref lists; top1 is -1 where a row gave no answer."""
    gt = np.asarray(gt, bool)
    has = gt.any(1)
    return {
        'with_match': np.flatnonzero(has).tolist(),
        'top1': {row: ranked[:, 0].astype(int).tolist() for row, (ranked, _) in rankings.items()},
        'wrong': {
            row: np.flatnonzero(has & ~metrics.top1_correct(ranked, gt)).tolist()
            for row, (ranked, _) in rankings.items()
        },
    }


def evaluate(
    datasets: list,
    extractor,
    conf: dict | None = None,
    heads: list[Head] | None = None,
    out_dir: str | os.PathLike | None = None,
    specs: list[str] | None = None,
    command: str = '',
    log=None,
) -> EvalRun:
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
            **{key: cast(conf[key]) for key, cast in ECHOED.items()},
            'sequence_prefilter_k': candidates_k(conf['prefilter_k'], conf['sequence_prefilter_k'], True),
            'prefilter': check_prefilter(conf['prefilter'], conf['prefilter_k'])[0],
            'input_height': int(extractor.conf['input_height']),
            'backbone': extractor.conf['backbone']['name'],
            'layer': extractor.backbone.layer,
            'descriptor_space': extractor.descriptor_space,
            'rand_seed': int(extractor.conf['rand_seed']),
            'act_fusion': float(extractor.conf['act_fusion']),
            'heads': {
                h.label or 'lln': {
                    'weights': h.weights or '',
                    'act_fusion': float({**extractor.conf, **h.select}['act_fusion']),
                    'trained': h.trained,
                    'fingerprint': head_fingerprint(h.module),
                    # what the checkpoint says it was trained and validated on (None: not recorded)
                    **{key: h.meta.get(key) for key in ('train_data', 'val_data', 'epoch')},
                }
                for h in heads
            },
            **{key: int(conf[key]) for key in ('timing_images', 'timing_queries', 'timing_repeats')},
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
    return EvalRun(results, runs, [f for r in runs.values() for f in figure_files(r.entry.get('figures'))])


def _unique_names(names: list[str]) -> list[str]:
    out, seen = [], {}
    for n in names:
        seen[n] = seen.get(n, 0) + 1
        out.append(n if seen[n] == 1 else f'{n}#{seen[n]}')
    return out
