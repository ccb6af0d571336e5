"""Scoring of metric loop closures (lln-eval --geometry): the figures of issue 27 for one acceptance
rule over a set of replayed queries, and the choice of the rule's thresholds on other queries.

A record (one per replayed query, from eval.geometry.replay) is a dict:
    frame, keyframe_frame (or None: no candidate), score S, revisit (bool: some keyframe the query
    may be answered with is within revisit_deg / revisit_m of it), T_gt (4, 4) T(keyframe <- query)
    from the ground truth, T_map_keyframe (4, 4) (the keyframe's stored pose), T_odom (4, 4) (the
    query's odometry), and est_depth / est_mono: core.geometry.PoseEstimate (None without candidate).
"""

from __future__ import annotations

import itertools
import math

import numpy as np

from ..core import geometry

score_conf = {
    'false_m': 0.5,  # an accepted transform farther than this from the truth is a false fix
    'false_deg': 10.0,  # ... or with a rotation error above this
    'max_false_fix_rate': 0.01,  # the rule chosen maximises correct recall under this on the choosing part
    # the grid searched (every combination); agree_frames uses the ground-truth odometry of the replay
    'grid': {
        'min_inliers': [10, 15, 20, 30, 40, 60, 80],
        'max_reproj_px': [0.75, 1.0, 1.5, 2.0, 3.0],
        'min_inlier_ratio': [0.0, 0.3, 0.5],
        'min_score': [0.0, 5.0, 10.0, 15.0],
        'agree_frames': [0, 1, 2],
    },
}

TARGETS = {
    'with_depth': {
        'rot_err_deg_p50': 2.0,
        'rot_err_deg_p95': 5.0,
        'trans_err_m_p50': 0.05,
        'trans_err_m_p95': 0.15,
        'transform_recall': 0.8,
        'false_fix_rate': 0.01,
    },
    'without_depth': {'rot_err_deg_p50': 3.0, 'trans_dir_err_deg_p50': 10.0},
}


def errors(est, T_gt: np.ndarray) -> tuple[float, float]:
    """(rotation error deg, translation error: metres for PnP, direction degrees for the essential)."""
    rot = geometry.rotation_deg(est.T[:3, :3].T @ T_gt[:3, :3])
    if est.metric:
        return rot, float(np.linalg.norm(est.T[:3, 3] - T_gt[:3, 3]))
    return rot, _direction(est.T, T_gt)


def _direction(T: np.ndarray, T_gt: np.ndarray) -> float:
    """Angle (degrees) between the translations of T and T_gt (NaN when either is zero)."""
    a, b = T[:3, 3], T_gt[:3, 3]
    n = np.linalg.norm(a) * np.linalg.norm(b)
    return math.degrees(math.acos(float(np.clip(a @ b / n, -1, 1)))) if n > 1e-12 else math.nan


def decide(records: list, key: str, rule: dict) -> list[bool]:
    """Accepted or not, per record in replay order (Agreement needs the order), for estimates `key`."""
    conf = {**geometry.default_conf, **rule}
    agree = geometry.Agreement(conf)
    out = []
    for r in records:
        est = r[key]
        ok = est is not None and geometry.accept(est, r['score'], conf)[0]
        T_map = r['T_map_keyframe'] @ est.T if ok else None
        agrees = agree.update(T_map, r['T_odom'], metric=bool(ok and est.metric))
        out.append(ok and agrees)
    return out


def _pct(values, q):
    v = [x for x in values if math.isfinite(x)]
    return float(np.percentile(v, q)) if v else None


def figures(records: list, key: str, accepted: list, conf: dict | None = None) -> dict:
    """The geometry figures over records (a subset, e.g. the report part) with their decisions."""
    c = {**score_conf, **(conf or {})}
    rot, trans, false, correct_revisit = [], [], 0, 0
    revisits = sum(r['revisit'] for r in records)
    accepted_revisits = unscaled = 0
    baselines = []
    for r, ok in zip(records, accepted):
        if not ok:
            continue
        est = r[key]
        e_rot, e_t = errors(est, r['T_gt'])
        rot.append(e_rot)
        # with depth, a query whose keyframe had too few depth points fell back to the essential
        # matrix: its rotation counts, its (unit) translation is not a metric error
        trans.append(e_t if est.metric or key != 'est_depth' else math.nan)
        unscaled += key == 'est_depth' and not est.metric
        baselines.append(float(np.linalg.norm(r['T_gt'][:3, 3])))
        bad = e_rot > c['false_deg'] or (est.metric and e_t > c['false_m'])
        false += bad
        if r['revisit']:
            accepted_revisits += 1
            correct_revisit += not bad
    n = len(rot)
    metric = key == 'est_depth'
    out = {
        'queries': len(records),
        'revisits': int(revisits),
        'accepted': n,
        'rot_err_deg_p50': _pct(rot, 50),
        'rot_err_deg_p95': _pct(rot, 95),
        'transform_recall': accepted_revisits / revisits if revisits else None,
        'correct_transform_recall': correct_revisit / revisits if revisits else None,
        'false_fix_rate': false / n if n else None,
        'false_fixes': int(false),
        'gt_baseline_m_p50': _pct(baselines, 50),
    }
    if metric:
        dirs = [_direction(r[key].T, r['T_gt']) for r, ok in zip(records, accepted) if ok and r[key].metric]
        out.update(
            {
                'accepted_without_scale': int(unscaled),
                'trans_err_m_p50': _pct(trans, 50),
                'trans_err_m_p95': _pct(trans, 95),
                # the same direction figure as without depth: what the baselines allow even metrically
                'trans_dir_err_deg_p50': _pct(dirs, 50),
            }
        )
    else:
        wide = [t for t, b in zip(trans, baselines) if b >= 0.05]
        out.update(
            {
                'trans_dir_err_deg_p50': _pct(trans, 50),
                'trans_dir_err_deg_p95': _pct(trans, 95),
                # the direction of a baseline of a few mm is noise in the ground truth itself
                'trans_dir_err_deg_p50_baseline_5cm': _pct(wide, 50),
                'accepted_baseline_5cm': len(wide),
            }
        )
    return out


def choose(records: list, key: str, conf: dict | None = None) -> tuple[dict, dict]:
    """(rule, its figures on records): the grid point with the highest correct_transform_recall whose
    false_fix_rate is at most max_false_fix_rate (ties: fewer false fixes, then the stricter rule,
    i.e. more inliers and a smaller residual). No admissible point: the strictest rule."""
    c = {**score_conf, **(conf or {})}
    grid = c['grid']
    names = list(grid)
    best = None
    for values in itertools.product(*(grid[n] for n in names)):
        rule = dict(zip(names, values))
        fig = figures(records, key, decide(records, key, rule), c)
        rate = fig['false_fix_rate'] or 0.0
        admissible = fig['accepted'] > 0 and rate <= c['max_false_fix_rate']
        rank = (
            admissible,
            fig['correct_transform_recall'] or 0.0,
            -fig['false_fixes'],
            rule.get('min_inliers', 0),
            -rule.get('max_reproj_px', 0),
            rule.get('min_score', 0),
            rule.get('agree_frames', 0),
        )
        if best is None or rank > best[0]:
            best = (rank, rule, fig)
    if not best[0][0]:
        rule = {n: (max(grid[n]) if n != 'max_reproj_px' else min(grid[n])) for n in names}
        return rule, figures(records, key, decide(records, key, rule), c)
    return best[1], best[2]


def met(fig: dict, targets: dict) -> dict:
    """{figure: True/False/None} against the targets (recall: at least; the rest: at most)."""
    out = {}
    for k, bound in targets.items():
        v = fig.get(k)
        out[k] = None if v is None else bool(v >= bound if k == 'transform_recall' else v <= bound)
    return out
