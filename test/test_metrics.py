"""Metrics on hand-computed cases."""

import numpy as np
import pytest

from lln_ros.core import metrics


def case():
    # 5 queries, 6 refs. q0..q3 have a true match, q4 has none (a first visit).
    gt = np.zeros((5, 6), bool)
    gt[0, 0] = gt[1, 1] = gt[2, 2] = gt[3, 3] = True
    ranked = np.array([[0, 5], [4, 1], [2, 0], [3, 1], [5, 0]])  # top-1 correct: q0, q2, q3
    scores = np.array([0.9, 0.8, 0.7, 0.4, 0.6])
    return ranked, scores, gt


def test_recall_and_precision_at_full_recall():
    ranked, scores, gt = case()
    assert metrics.p_at_100r(ranked, gt) == pytest.approx(3 / 4)
    assert metrics.recall_at_k(ranked, gt, 1) == pytest.approx(3 / 4)
    assert metrics.recall_at_k(ranked, gt, 2) == pytest.approx(1.0)


def test_pr_curve_by_hand():
    ranked, scores, gt = case()
    precision, recall, thresholds = metrics.pr_curve(ranked, scores, gt)
    # accepted by descending score: q0 (ok), q1 (wrong), q2 (ok), q4 (wrong, no match), q3 (ok)
    np.testing.assert_allclose(thresholds, [0.9, 0.8, 0.7, 0.6, 0.4])
    np.testing.assert_allclose(precision, [1, 1 / 2, 2 / 3, 2 / 4, 3 / 5])
    np.testing.assert_allclose(recall, [1 / 4, 1 / 4, 2 / 4, 2 / 4, 3 / 4])
    assert metrics.r_at_100p(ranked, scores, gt) == pytest.approx(1 / 4)
    assert metrics.auc_pr(ranked, scores, gt) == pytest.approx(1 / 4 * 1 + 1 / 4 * 2 / 3 + 1 / 4 * 3 / 5)


def test_ties_are_one_threshold_and_unanswered_queries():
    gt = np.eye(3, dtype=bool)
    ranked = np.array([[0], [2], [-1]])
    scores = np.array([0.5, 0.5, -np.inf])
    precision, recall, _ = metrics.pr_curve(ranked, scores, gt)
    np.testing.assert_allclose(precision, [0.5])  # q0 and q1 tie: accepted together
    assert metrics.r_at_100p(ranked, scores, gt) == 0.0
    assert metrics.p_at_100r(ranked, gt) == pytest.approx(1 / 3)
    s = metrics.summary(ranked, scores, gt)
    assert set(s) == {'p_at_100r', 'r_at_100p', 'auc_pr', 'r_at_1', 'r_at_5', 'r_at_10'}
