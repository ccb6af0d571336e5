"""From the matcher's answers to loop-closure constraints a pose-graph back end takes (no rclpy).

    select = LoopClosureFilter({'min_score': 8.0, 'min_inliers': 15, 'min_gap_s': 5.0})
    closure = select(query_stamp_ns, candidates, matches)   # cloud_to_candidates / cloud_to_matches tables
    if closure is not None:
        graph.add(closure.as_dict())                          # JSON-able: stamps, scores, region pairs

A back end keys its poses by stamp, so a constraint here is (query stamp, keyframe stamp) plus the
evidence (score S, holistic cosine, RANSAC inliers in verify mode), the matched region pairs and,
when the matcher estimated and accepted it (verify + geometry, lln_ros.core.registration), the
relative pose T(keyframe <- query) (4, 4) with its 6x6 covariance of [x y z roll pitch yaw]: a
between-factor as it is (metric: PnP with depth; otherwise the translation is a unit direction
with a huge variance along it). docs/slam_integration.md says what to threshold on.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

DEFAULT_CONF = {
    'min_score': 0.0,  # landmark similarity S of the best candidate (method lln); 0 = any
    'min_inliers': 0,  # verify mode: RANSAC inliers of the best candidate; 0 = do not require
    'min_gap_s': 0.0,  # candidates closer in time than this to the query are odometry, not loops
    'require_pose': False,  # only answers whose best candidate has an accepted pose (pose_accepted = 1)
}


@dataclass
class LoopClosure:
    """One accepted loop closure: the query frame revisits the keyframe."""

    query_stamp_ns: int
    keyframe_stamp_ns: int
    keyframe_id: int
    score: float
    holistic_score: float
    inliers: float | None = None  # verify mode only
    regions: np.ndarray = field(default_factory=lambda: np.zeros((0, 6), np.float32))
    """(M, 6) float32 query_u, query_v, map_u, map_v, cell_w, cell_h of the matched region pairs."""
    transform: np.ndarray | None = None  # (4, 4) T(keyframe <- query), camera optical frames, when accepted
    covariance: np.ndarray | None = None  # (6, 6) of [x y z roll pitch yaw] (ROS order)
    metric: bool = False  # PnP with depth; False: essential matrix, |t| = 1
    keyframe_session_id: int = 0  # the map's session that stored the keyframe (~/info: robot, label); 0 = unknown

    def as_dict(self) -> dict:
        return {
            'query_stamp_ns': self.query_stamp_ns,
            'keyframe_stamp_ns': self.keyframe_stamp_ns,
            'keyframe_id': self.keyframe_id,
            'score': round(self.score, 4),
            'holistic_score': round(self.holistic_score, 4),
            'inliers': None if self.inliers is None else int(self.inliers),
            'regions': np.round(self.regions, 1).tolist(),
            'transform': None if self.transform is None else np.round(self.transform, 6).tolist(),
            'covariance': None if self.covariance is None else self.covariance.ravel().tolist(),
            'metric': self.metric,
            'keyframe_session_id': self.keyframe_session_id,
        }


class LoopClosureFilter:
    """Keeps the best candidate of an answer when it passes every threshold of `conf` (DEFAULT_CONF)."""

    def __init__(self, conf: dict | None = None):
        unknown = set(conf or {}) - set(DEFAULT_CONF)
        if unknown:
            raise ValueError(f'unknown loop-closure settings {sorted(unknown)}; known: {sorted(DEFAULT_CONF)}')
        self.conf = {**DEFAULT_CONF, **(conf or {})}
        self.rejected: dict[str, int] = {}

    def _reject(self, why: str) -> None:
        self.rejected[why] = self.rejected.get(why, 0) + 1

    def __call__(self, query_stamp_ns: int, candidates: np.ndarray, matches: np.ndarray | None = None):
        """candidates: the candidates table (best first), matches: the matches table of the same
        answer (about candidates[0]) or None. Returns a LoopClosure or None (counted in .rejected)."""
        c = self.conf
        stamps = [int(r['stamp_sec']) * 10**9 + int(r['stamp_nanosec']) for r in candidates]
        # best first: the first candidate far enough in time from the query (closer ones are odometry)
        far = [i for i, st in enumerate(stamps) if abs(query_stamp_ns - st) >= c['min_gap_s'] * 1e9]
        if not far:
            self._reject('too_recent' if len(candidates) else 'no_candidate')
            return None
        row, stamp = candidates[far[0]], stamps[far[0]]
        if float(row['score']) < c['min_score']:
            self._reject('low_score')
            return None
        inliers = float(row['inliers']) if 'inliers' in candidates.dtype.names else None
        if c['min_inliers'] > 0 and (inliers is None or math.isnan(inliers) or inliers < c['min_inliers']):
            self._reject('few_inliers')
            return None
        names = candidates.dtype.names
        accepted = 'pose_accepted' in names and float(row['pose_accepted']) == 1.0
        if c['require_pose'] and not accepted:
            self._reject('no_pose')
            return None
        transform = covariance = None
        if accepted:
            from .registration import POSE_XYZQ, pose_from_parts

            x = [float(row[k]) for k in POSE_XYZQ]
            transform = pose_from_parts(x[:3], x[3:], 1e-4)
            covariance = np.array([float(row[f'cov_{i}']) for i in range(36)], np.float64).reshape(6, 6)
        regions = np.zeros((0, 6), np.float32)
        if matches is not None and len(matches) and int(matches['keyframe_id'][0]) == int(row['keyframe_id']):
            regions = np.stack(
                [matches[k] for k in ('query_u', 'query_v', 'map_u', 'map_v', 'cell_w', 'cell_h')], axis=1
            ).astype(np.float32)
        return LoopClosure(
            query_stamp_ns,
            stamp,
            int(row['keyframe_id']),
            float(row['score']),
            float(row['holistic_score']),
            None if inliers is None or math.isnan(inliers) else inliers,
            regions,
            transform,
            covariance,
            accepted and float(row['pose_metric']) == 1.0,
            int(row['session_id']) if 'session_id' in row.dtype.names else 0,
        )


def threshold_table(
    scores: np.ndarray, correct: np.ndarray, positives: int, precisions=(1.0, 0.99, 0.95, 0.9, 0.8)
) -> list[dict]:
    """For each target precision, the lowest threshold on the top-1 score that reaches it and the
    recall there. scores, correct: (Q,) of the answered queries; positives: queries with a true loop."""
    order = np.argsort(-np.asarray(scores, np.float64), kind='stable')
    s, ok = np.asarray(scores, np.float64)[order], np.asarray(correct, bool)[order]
    tp = np.cumsum(ok)
    n = np.arange(1, len(s) + 1)
    last = np.r_[s[1:] != s[:-1], True] if len(s) else np.zeros(0, bool)
    prec, rec, thr = (tp / n)[last], (tp / max(positives, 1))[last], s[last]
    out = []
    for target in precisions:
        good = np.flatnonzero(prec >= target)
        if len(good):
            i = good[np.argmax(rec[good])]
            out.append(
                {
                    'precision_target': target,
                    'threshold': float(thr[i]),
                    'precision': float(prec[i]),
                    'recall': float(rec[i]),
                }
            )
        else:
            out.append(
                {'precision_target': target, 'threshold': float('nan'), 'precision': float('nan'), 'recall': 0.0}
            )
    return out
