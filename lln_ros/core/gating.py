"""Which frames become keyframes, and when a keyframe may answer: gating by odometry motion (or by
appearance novelty without odometry) and recent exclusion in seconds, not frames.

    gate = KeyframeGate({'min_distance_m': 0.05, 'min_angle_deg': 10})
    if gate.decide(stamp_s, T_odom_cam)[0]:        # T (4, 4) from geometry.odometry_pose, or None
        held.add(stamp_s, keyframe)
    for keyframe in held.ready(now_s):             # older than min_age_s: now it may be an answer
        store(keyframe)

A camera standing still makes no new keyframes (no motion, or nothing new in view), and a keyframe
is not an answer until min_age_s have passed, however many frames arrive meanwhile: a robot that
stands still does not "close loops" with itself.
"""

from __future__ import annotations

import numpy as np

from .geometry import invert, rotation_deg

default_conf = {
    'min_distance_m': 0.05,  # odometry: a new keyframe once the camera moved this far from the last one
    'min_angle_deg': 10.0,  # ... or turned this much
    'max_interval_s': 0.0,  # and at least every this many seconds (0 = off)
    # without odometry: a new keyframe when the best answer's S is below this (nothing alike in the
    # map); 0 = every frame without odometry is a keyframe. 25: a still camera stores one keyframe
    # and rtabmap_loop keeps every revisit (docs/geometry.md 'Novelty gating'); 15 lost revisits
    'novelty_max_score': 25.0,
    'min_age_s': 2.0,  # a keyframe may answer once it is this much older than the query
}


class KeyframeGate:
    """Keyframe decisions for a stream of frames (module doc); one caller at a time."""

    def __init__(self, conf: dict | None = None):
        self.conf = c = {**default_conf, **(conf or {})}
        for key in ('min_distance_m', 'min_angle_deg', 'max_interval_s', 'novelty_max_score', 'min_age_s'):
            if not float(c[key]) >= 0:
                raise ValueError(f'{key} must be at least 0, got {c[key]}')
        self.last_T, self.last_stamp = None, None

    @property
    def judges_novelty(self) -> bool:
        """Without odometry, is a frame judged by its best S (False: every frame is novel)?"""
        return self.conf['novelty_max_score'] > 0

    def decide(self, stamp_s: float, T_odom: np.ndarray | None = None, best_score: float | None = None):
        """(keyframe?, why) for a frame at stamp_s with its odometry pose (4, 4) or None and, without
        odometry, the best S its query got (None: no answer, the map has nothing alike)."""
        c = self.conf
        if self.last_stamp is None:
            return self._take(stamp_s, T_odom, 'first frame')
        if c['max_interval_s'] > 0 and stamp_s - self.last_stamp >= c['max_interval_s']:
            return self._take(stamp_s, T_odom, 'interval')
        if T_odom is not None and self.last_T is not None:
            D = invert(self.last_T) @ T_odom
            if np.linalg.norm(D[:3, 3]) >= c['min_distance_m']:
                return self._take(stamp_s, T_odom, 'distance')
            if rotation_deg(D[:3, :3]) >= c['min_angle_deg']:
                return self._take(stamp_s, T_odom, 'angle')
            return False, 'not moved enough'
        if not self.judges_novelty or best_score is None or best_score < c['novelty_max_score']:
            return self._take(stamp_s, T_odom, 'novel')
        return False, 'seen before'

    def _take(self, stamp_s, T_odom, why):
        self.last_stamp, self.last_T = float(stamp_s), T_odom if T_odom is not None else self.last_T
        return True, why


class HeldKeyframes:
    """Keyframes held back until they are min_age_s old (recent exclusion in seconds)."""

    def __init__(self, min_age_s: float = default_conf['min_age_s']):
        self.min_age_s, self.items = float(min_age_s), []

    def add(self, stamp_s: float, item) -> None:
        self.items.append((float(stamp_s), item))

    def ready(self, now_s: float) -> list:
        """The held items at least min_age_s older than now_s, oldest first (removed from the hold)."""
        n = 0
        while n < len(self.items) and now_s - self.items[n][0] >= self.min_age_s:
            n += 1
        out, self.items = [item for _, item in self.items[:n]], self.items[n:]
        return out
