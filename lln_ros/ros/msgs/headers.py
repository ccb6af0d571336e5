"""std_msgs/Header and builtin_interfaces/Time <-> integer nanoseconds, and the stamp check of every
received message (header_stamp_ns)."""

from __future__ import annotations

from std_msgs.msg import Header

from ...core.limits import stamp_problem
from ...errors import MessageError

# frame_id of every PointCloud2 this package publishes: the clouds are typed tables (landmarks,
# candidates, keypoints, matches), not points in space, and a frame that no TF tree has makes rviz and
# PCL tools say so ("no transform from lln_table") instead of drawing the rows as points at the
# camera. The stamp stays the camera image's, which is how an answer is paired with its frame.
TABLE_FRAME = 'lln_table'

__all__ = [
    'TABLE_FRAME',
    'header_stamp_ns',
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


def header_stamp_ns(header, what: str = 'message') -> int:
    """A received message's stamp (a Header or builtin_interfaces/Time) as integer nanoseconds,
    after checking it against every type it will be written to (limits.stamp_problem: int32 sec,
    nanosec < 1e9). MessageError names the problem: such a stamp is refused at the door, never
    renormalised, so every stamp a node answers with is exactly the sender's."""
    stamp = getattr(header, 'stamp', header)
    problem = stamp_problem(stamp.sec, stamp.nanosec)
    if problem:
        raise MessageError(f'{what}: header {problem}')
    return stamp_to_ns(stamp)
