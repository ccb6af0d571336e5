"""Losses a subscriber can see without the middleware's help (no rclpy).

    gaps = StampGaps()
    missing = gaps.add(stamp_ns)        # frames missing just before this one (0 usually)
    Window(counters).delta()            # counter increases since the last call (one diagnostics period)

A camera or bag publishes at a steady rate, so header stamps advance by about one period. When a
stamp jumps by several periods (and the stream is not just slower), the frames in between were lost
upstream: by DDS (best effort), by the driver, or never recorded. The period is the median of the
last `window` intervals, so a rate change is learnt within a few frames; out-of-order or repeated
stamps start over from the new stamp (counted as `out_of_order`), and so does a jump of more than
`max_gap` periods (a paused bag or a new stream, not losses). A rate that halves for good counts about
window / 2 frames as missing before the median learns it.
"""

from __future__ import annotations

from collections import deque

import numpy as np


class StampGaps:
    """Missing frames from header stamp gaps. A gap of g periods (g >= min_gap) counts round(g) - 1
    missing frames; the period is learnt (median of the last `window` intervals, at least `warmup`)."""

    def __init__(self, window: int = 30, warmup: int = 5, min_gap: float = 1.8, max_gap: float = 50.0):
        self.intervals: deque = deque(maxlen=int(window))
        self.warmup, self.min_gap, self.max_gap = int(warmup), float(min_gap), float(max_gap)
        self.last = None
        self.missing = 0
        self.out_of_order = 0

    def period_ns(self) -> float | None:
        return float(np.median(self.intervals)) if len(self.intervals) >= self.warmup else None

    def add(self, stamp_ns: int) -> int:
        if self.last is not None and stamp_ns <= self.last:
            self.out_of_order += 1  # a bag replayed again, a restarted driver: follow the new stamps
            self.last = stamp_ns
            return 0
        missing = 0
        if self.last is not None:
            interval = stamp_ns - self.last
            period = self.period_ns()
            if period and interval > self.max_gap * period:  # a pause or a new stream, not losses
                self.last = stamp_ns
                return 0
            if period and interval >= self.min_gap * period:
                missing = int(round(interval / period)) - 1
                self.missing += missing
            # gaps are samples too: sporadic losses barely move the median, while a stream that really
            # slowed down (indistinguishable from losing every other frame) stops counting within
            # half a window
            self.intervals.append(interval)
        self.last = stamp_ns
        return missing


class Window:
    """Counter increases between calls: what happened during the last diagnostics period."""

    def __init__(self, snapshot):
        self.snapshot = snapshot  # () -> {name: count}
        self.previous = dict(snapshot())

    def delta(self) -> dict:
        now = dict(self.snapshot())
        out = {k: v - self.previous.get(k, 0) for k, v in now.items() if v != self.previous.get(k, 0)}
        self.previous = now
        return out
