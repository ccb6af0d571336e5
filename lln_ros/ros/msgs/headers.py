"""std_msgs/Header and builtin_interfaces/Time <-> integer nanoseconds."""

from __future__ import annotations

from std_msgs.msg import Header

# frame_id of every PointCloud2 this package publishes: the clouds are typed tables (landmarks,
# candidates, keypoints, matches), not points in space, and a frame that no TF tree has makes rviz and
# PCL tools say so ("no transform from lln_table") instead of drawing the rows as points at the
# camera. The stamp stays the camera image's, which is how an answer is paired with its frame.
TABLE_FRAME = 'lln_table'

__all__ = [
    'TABLE_FRAME',
    'make_header',
    'stamp_to_ns',
]


def make_header(stamp_ns: int = 0, frame_id: str = '') -> Header:
    """std_msgs/Header from integer nanoseconds since the epoch."""
    header = Header(frame_id=frame_id)
    header.stamp.sec, header.stamp.nanosec = divmod(int(stamp_ns), 1_000_000_000)
    return header


def stamp_to_ns(stamp) -> int:
    """builtin_interfaces/Time (or a Header) -> integer nanoseconds."""
    stamp = getattr(stamp, 'stamp', stamp)
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)
