"""Place-recognition metrics from ranked retrieval results (all fractions in 0..1).

Inputs: ranked (Q, K) ref indices per query, best first (-1 = no answer), top-1 scores (Q,), and the
ground truth gt (Q, R) bool. A query is *answered* when it has a top-1 ref; its answer is correct
when gt[q, top1]. Following the paper, precision-recall comes from sweeping a threshold on the top-1
score: at threshold t the queries with score >= t are accepted;
    precision = correct accepted / accepted,   recall = correct accepted / queries with a true match.
Queries without any true match (loop data: a first visit) can only be false positives.

    p_at_100r   precision when every query that has a match is answered (= top-1 accuracy over them)
    r_at_100p   the largest recall at which precision is exactly 1
    auc_pr      area under the PR curve (average precision, step-wise)
    recall_at_k a correct ref among the first k answers, over queries that have a match
"""

from __future__ import annotations

import numpy as np


def top1_correct(ranked: np.ndarray, gt: np.ndarray) -> np.ndarray:
    top = ranked[:, 0]
    return (top >= 0) & gt[np.arange(len(top)), np.maximum(top, 0)]


def recall_at_k(ranked: np.ndarray, gt: np.ndarray, k: int) -> float:
    has = gt.any(1)
    if not has.any():
        return float('nan')
    top = ranked[:, :k]
    hit = ((top >= 0) & np.take_along_axis(gt, np.maximum(top, 0), axis=1)).any(1)
    return float(hit[has].mean())


def p_at_100r(ranked: np.ndarray, gt: np.ndarray) -> float:
    has = gt.any(1)
    return float(top1_correct(ranked, gt)[has].mean()) if has.any() else float('nan')


def pr_curve(ranked: np.ndarray, scores: np.ndarray, gt: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(precision, recall, thresholds), one point per distinct top-1 score, highest threshold first."""
    answered = ranked[:, 0] >= 0
    correct = top1_correct(ranked, gt)[answered]
    s = np.asarray(scores, np.float64)[answered]
    positives = max(int(gt.any(1).sum()), 1)
    order = np.argsort(-s, kind='stable')
    s, correct = s[order], correct[order]
    tp = np.cumsum(correct)
    n = np.arange(1, len(s) + 1)
    last_of_tie = np.r_[s[1:] != s[:-1], True] if len(s) else np.zeros(0, bool)
    return tp[last_of_tie] / n[last_of_tie], tp[last_of_tie] / positives, s[last_of_tie]


def r_at_100p(ranked: np.ndarray, scores: np.ndarray, gt: np.ndarray) -> float:
    precision, recall, _ = pr_curve(ranked, scores, gt)
    perfect = precision >= 1.0
    return float(recall[perfect].max()) if perfect.any() else 0.0


def auc_pr(ranked: np.ndarray, scores: np.ndarray, gt: np.ndarray) -> float:
    precision, recall, _ = pr_curve(ranked, scores, gt)
    if not len(recall):
        return 0.0
    gained = np.diff(np.r_[0.0, recall])
    return float((gained * precision).sum())


def summary(ranked: np.ndarray, scores: np.ndarray, gt: np.ndarray) -> dict:
    """Every metric of one method on one dataset."""
    return {
        'p_at_100r': p_at_100r(ranked, gt),
        'r_at_100p': r_at_100p(ranked, scores, gt),
        'auc_pr': auc_pr(ranked, scores, gt),
        'r_at_1': recall_at_k(ranked, gt, 1),
        'r_at_5': recall_at_k(ranked, gt, 5),
        'r_at_10': recall_at_k(ranked, gt, 10),
    }
