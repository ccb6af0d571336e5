"""Relocalization rows of lln-eval (`--reloc`): both keypoint pipelines of lln_ros.core.reloc on a
dataset's top pLLN candidates, region-constrained (mLLN) against all keypoints."""

from __future__ import annotations

import time

import numpy as np

from ..core.reloc import Keypoints, Relocalizer, pair_boxes

eval_conf = {
    'reloc_top': 5,  # pLLN candidates per query (the paper's top 5)
    'reloc_min_inliers': 30,  # a query succeeds when its best true candidate reaches this
    'reloc_queries': 0,  # evenly spaced queries evaluated (0 = every query)
    'reloc_detector': 'orb',
    'reloc_margin': 1.0,
    'reloc_fast_threshold': 20,
}


def evaluate_reloc(
    ds, queries: list, refs: list, ranked: np.ndarray, conf: dict | None = None, progress: str | None = None
) -> dict:
    """Relocalization on a dataset: for each query its top candidates by the place ranking
    (`ranked` (Q, K) ref indices from retrieval.rank_all with the LLN sets `queries` / `refs`), both
    keypoint pipelines against each. A pipeline succeeds on a query when the best candidate that is a
    true match (ds.gt) reaches reloc_min_inliers RANSAC inliers (F; no intrinsics here).

    Returns the JSON entry: per pipeline ('regions', 'all') success rate over the queries that
    have a true match, mean inliers of the best true candidate and of false candidates, mean
    matching + verification ms per query (all its candidates; detection excluded, it is shared
    and reported as detect_ms per image)."""
    from ..core.landmarks import stack_landmarks
    from ..core.similarity import match_batch
    from ..io.image import load_image

    conf = {**eval_conf, **(conf or {})}
    reloc = Relocalizer(
        {
            'detector': conf['reloc_detector'],
            'margin': conf['reloc_margin'],
            'fast_threshold': conf['reloc_fast_threshold'],
        }
    )
    top, need = int(conf['reloc_top']), int(conf['reloc_min_inliers'])
    with_match = np.flatnonzero(ds.gt.any(axis=1))
    n = int(conf['reloc_queries'])
    if 0 < n < len(with_match):
        with_match = with_match[np.unique(np.linspace(0, len(with_match) - 1, n).astype(int))]
    kps: dict[str, Keypoints] = {}
    detect_ms = []

    def keypoints(path) -> Keypoints:
        if str(path) not in kps:
            image = load_image(str(path))
            t0 = time.perf_counter()
            kps[str(path)] = reloc.detect(image)
            detect_ms.append((time.perf_counter() - t0) * 1e3)
        return kps[str(path)]

    stats = {p: {'success': 0, 'best_true': [], 'false': [], 'ms': [], 'matches': []} for p in ('regions', 'all')}
    in_top = 0
    items = with_match
    if progress:
        from tqdm import tqdm

        items = tqdm(with_match, desc=progress, leave=False)
    for q in items:
        cands = ranked[q, :top]
        cands = cands[cands >= 0]
        if not len(cands):
            continue
        kq = keypoints(ds.query_paths[q])
        place = match_batch(queries[q], stack_landmarks([refs[c] for c in cands]))
        best = {'regions': -1, 'all': -1}
        ms = {'regions': 0.0, 'all': 0.0}
        for j, c in enumerate(cands):
            km = keypoints(ds.ref_paths[c])
            qb, mb = pair_boxes(queries[q], refs[c], place.pairs(j), reloc.conf['margin'])
            for name, boxes in (('regions', (qb, mb)), ('all', (None, None))):
                r = reloc.relocalize(kq, km, *boxes)
                ms[name] += r.matches.ms + r.ms
                stats[name]['matches'].append(len(r.matches))
                if ds.gt[q, c]:
                    best[name] = max(best[name], r.inliers)
                else:
                    stats[name]['false'].append(r.inliers)
        in_top += bool(ds.gt[q, cands].any())
        for name, s in stats.items():
            s['ms'].append(ms[name])
            if best[name] >= 0:
                s['best_true'].append(best[name])
                s['success'] += best[name] >= need
    total = len(with_match)
    out = {
        'queries': int(total),
        'top': top,
        'min_inliers': need,
        'detector': reloc.name,
        'fast_threshold': int(reloc.conf['fast_threshold']) if reloc.name == 'orb' else None,
        'margin': float(reloc.conf['margin']),
        'true_match_in_top': in_top / total if total else None,
        'detect_ms': float(np.median(detect_ms)) if detect_ms else None,
        'keypoints_median': float(np.median([len(k) for k in kps.values()])) if kps else None,
        'keypoints_zero': int(sum(len(k) == 0 for k in kps.values())),
    }
    for name, s in stats.items():
        out[name] = {
            'success_rate': s['success'] / total if total else None,
            'mean_inliers_true': float(np.mean(s['best_true'])) if s['best_true'] else None,
            'mean_inliers_false': float(np.mean(s['false'])) if s['false'] else None,
            'ms_per_query': float(np.mean(s['ms'])) if s['ms'] else None,
            'matches_per_pair': float(np.mean(s['matches'])) if s['matches'] else None,
        }
    return out
