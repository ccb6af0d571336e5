"""Odometry by stamp, without rclpy: the matcher's buffer of odometry poses, and the pose of a frame.

    buf = OdometryBuffer(capacity=2000)
    buf.add(OdomPose(stamp_ns, T, 'odom', 'base_link'))       # from the sensor thread
    odom = buf.at(stamp_ns, max_dt_s=0.05, wait_s=0.2)       # OdomPose or None

A frame's pose is interpolated between the two samples around its stamp (translation linearly,
rotation along the geodesic) when both are within max_dt of it, else it is the nearest sample
within max_dt. When odometry is flowing but has not yet reached a frame's stamp, `at` waits up to
wait_s for it: the answers and the odometry run on two threads of one process, and under load
(CI, a busy robot computer) the odometry callbacks fall behind the frames they must pose (seen: 7
of 37 keyframes stored without a pose). A stream that has stopped is not waited for.
"""

from __future__ import annotations

import bisect
import threading
import time
from dataclasses import dataclass

import numpy as np

from .geometry import interpolate

FLOWING_S = 1.0  # odometry whose last sample arrived (wall clock) this recently is flowing: worth waiting for


@dataclass
class OdomPose:
    """One odometry sample: stamp (ns), T (4, 4) float64 T(frame_id <- child_frame_id)."""

    stamp_ns: int
    T: np.ndarray
    frame_id: str
    child_frame_id: str = ''


class OdometryBuffer:
    """The newest `capacity` odometry poses, sorted by stamp; a new frame_id starts it afresh (poses
    of two frames cannot be compared). Thread-safe: a node adds from a sensor thread while another
    thread looks poses up (and may wait for them)."""

    def __init__(self, capacity: int):
        self.capacity = int(capacity)
        self.stamps: list[int] = []
        self.poses: list[OdomPose] = []
        self._cond = threading.Condition()
        self._last_add = -float('inf')  # time.monotonic() of the latest sample

    def add(self, odom: OdomPose) -> None:
        with self._cond:
            self._add(odom)
            self._last_add = time.monotonic()
            self._cond.notify_all()

    def _add(self, odom: OdomPose) -> None:
        if self.poses and odom.frame_id != self.poses[-1].frame_id:
            self.stamps, self.poses = [], []
        i = bisect.bisect_left(self.stamps, odom.stamp_ns)
        if i < len(self.stamps) and self.stamps[i] == odom.stamp_ns:
            self.poses[i] = odom
            return
        self.stamps.insert(i, odom.stamp_ns)
        self.poses.insert(i, odom)
        if len(self.stamps) > self.capacity:
            del self.stamps[0], self.poses[0]

    def at(self, stamp_ns: int, max_dt_s: float, wait_s: float = 0.0) -> OdomPose | None:
        """The pose at stamp_ns (module doc), or None when no sample is within max_dt_s of it."""
        stamp_ns = int(stamp_ns)
        with self._cond:
            if wait_s > 0 and self.stamps and self.stamps[-1] < stamp_ns:
                if time.monotonic() - self._last_add < FLOWING_S:
                    self._cond.wait_for(lambda: self.stamps and self.stamps[-1] >= stamp_ns, timeout=wait_s)
            return self._at(stamp_ns, int(float(max_dt_s) * 1e9))

    def _at(self, stamp_ns: int, max_dt_ns: int) -> OdomPose | None:
        i = bisect.bisect_left(self.stamps, stamp_ns)
        if i < len(self.stamps) and self.stamps[i] == stamp_ns:
            return self.poses[i]
        near = [j for j in (i - 1, i) if 0 <= j < len(self.stamps) and abs(self.stamps[j] - stamp_ns) <= max_dt_ns]
        if len(near) == 2:  # one sample either side, both close: interpolate
            a, b = self.poses[i - 1], self.poses[i]
            w = (stamp_ns - a.stamp_ns) / (b.stamp_ns - a.stamp_ns)
            return OdomPose(stamp_ns, interpolate(a.T, b.T, w), a.frame_id, b.child_frame_id)
        return self.poses[near[0]] if near else None
