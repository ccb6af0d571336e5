"""std_msgs/Header and builtin_interfaces/Time <-> integer nanoseconds."""

from __future__ import annotations

from std_msgs.msg import Header

__all__ = [
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
