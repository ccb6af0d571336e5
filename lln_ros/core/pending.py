"""A buffer of messages waiting for a partner, bounded in count and in bytes (the matcher's verify
mode: keypoints clouds wait for the landmark set of the same stamp). No rclpy.

    pending = Pending(max_items=100, max_bytes=16 * 2**20)
    evicted = pending.put(stamp_ns, payload, nbytes)   # the oldest go first when either bound is hit
    payload = pending.take(stamp_ns)                   # None when nothing waits under that stamp
"""

from __future__ import annotations


class Pending:
    """Insertion-ordered {key: (payload, nbytes)}: at most max_items entries and max_bytes in all.
    A payload larger than max_bytes alone is not kept (put returns 1: itself evicted)."""

    def __init__(self, max_items: int, max_bytes: int):
        self.max_items, self.max_bytes = int(max_items), int(max_bytes)
        self._items: dict = {}
        self.nbytes = 0

    def put(self, key, payload, nbytes: int) -> int:
        """Keep payload under key (replacing one of the same key); returns how many were evicted."""
        self.take(key)
        self._items[key] = (payload, int(nbytes))
        self.nbytes += int(nbytes)
        evicted = 0
        while self._items and (len(self._items) > self.max_items or self.nbytes > self.max_bytes):
            self.nbytes -= self._items.pop(next(iter(self._items)))[1]
            evicted += 1
        return evicted

    def take(self, key):
        held = self._items.pop(key, None)
        if held is None:
            return None
        self.nbytes -= held[1]
        return held[0]

    def __len__(self) -> int:
        return len(self._items)


def keep_newest(entries: dict, size: int) -> None:
    """Keep the newest `size` entries of an insertion-ordered dict."""
    while len(entries) > size:
        entries.pop(next(iter(entries)))
