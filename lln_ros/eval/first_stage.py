"""lln-eval's first-stage report: the recall@K ceiling and cost per query of each first stage
(holistic, landmarks, the paper's LLN-weighted sum, exhaustive S) on one dataset (runner.py)."""

from __future__ import annotations

import functools

import numpy as np
import torch

from ..core import metrics
from ..core.lln import embed
from ..core.retrieval import batch_index, cosine_top, first_stage
from .report import finite
from .timing import interleaved_times

FIRST_STAGE_KS = (1, 5, 10, 30, 100)


def weighted_sums(head, feats: list[np.ndarray]) -> np.ndarray:
    """(N, D) LLN-weighted sums (lln.embed) of N cached feature maps (D, h, w), one image at a time
    (a dataset's images need not share a grid)."""
    with torch.inference_mode():
        return np.concatenate([embed(head, torch.from_numpy(np.asarray(f, np.float32)[None])).numpy() for f in feats])


def first_stage_report(
    qs: list,
    batch,
    ds,
    holistic_full: np.ndarray,
    exhaustive: np.ndarray | None,
    scale: float,
    repeats: int,
    index=None,
    learned: tuple | None = None,
) -> dict:
    """Recall@K (FIRST_STAGE_KS) of each first stage's own ranking, i.e. the ceiling of a rerank of
    its top K, and its cost per query (ms, best of `repeats` over the timed queries): holistic
    (global cosine over every ref), landmarks (landmark_index search + score_hits), the paper's
    learned holistic descriptor when `learned` = (query F (Q, D), ref F (R, D)) is given (cosine of
    LLN-weighted sums, lln.embed) and, when the run is exhaustive, S over every ref (its ranking
    `exhaustive`)."""
    kmax = min(max(FIRST_STAGE_KS), len(batch))
    index = index if index is not None else batch_index(batch)
    lm, _ = first_stage(qs, batch, kmax, 'landmarks', ds.candidates, scale=scale, index=index)
    out = {'holistic': holistic_full, 'landmarks': lm}
    if learned is not None:  # the paper's own holistic descriptor F = sum w_ij f_ij (lln.embed)
        out['lln-weighted sum'], _ = cosine_top(*learned, kmax, ds.candidates)
    if exhaustive is not None:
        out['exhaustive'] = exhaustive
    report = {
        name: {
            'recall_at': {
                str(kk): finite(metrics.recall_at_k(r, ds.gt, kk)) for kk in FIRST_STAGE_KS if kk <= r.shape[1]
            }
        }
        for name, r in out.items()
    }
    pick = np.unique(np.linspace(0, len(qs) - 1, min(10, len(qs))).astype(int))
    queries = np.stack([q.global_descriptor for q in qs])
    jobs = {
        'holistic': [(functools.partial(cosine_top, queries[i : i + 1], batch.globals, kmax), 1) for i in pick],
        'landmarks': [(functools.partial(index.shortlist, qs[i], kmax, None, scale), 1) for i in pick],
    }
    if learned is not None:
        jobs['lln-weighted sum'] = [
            (functools.partial(cosine_top, learned[0][i : i + 1], learned[1], kmax), 1) for i in pick
        ]
    for name, ms in interleaved_times(jobs, repeats).items():
        report[name]['ms_per_query'] = finite(ms)
    return report
