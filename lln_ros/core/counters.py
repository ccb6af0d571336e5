"""Counters of a node and rate-limited problem logging, without rclpy.

    counters = Counters(log=logger.warning)
    counters.count('queries_received')
    counters.problem('bad_query', 'landmarks cloud: data is truncated: 12 bytes, expected 40')

A problem is counted every time. It is logged the first time its *kind* is seen, and after that at
most once per `period_s` seconds per kind, with the number of repeats since the last line. The
kind is the message with its numbers and quoted strings masked ('data is truncated: # bytes,
expected #'), so messages that differ only in a byte count or a field name are one kind: 300 bad
queries of one sort give one WARN line, not 300. At most `max_kinds` kinds are remembered per
counter (a sender can make endless distinct texts); later ones share the kind '<other>'.
"""

from __future__ import annotations

import re
import threading
import time
from collections import Counter

_MASKS = (re.compile(r"'[^']*'|\"[^\"]*\""), re.compile(r'[-+]?\d+(\.\d+)?([eE][-+]?\d+)?'))


def problem_kind(message: str) -> str:
    """The message with quoted strings -> '…' and numbers -> # (what rate limiting groups by)."""
    text = _MASKS[0].sub("'…'", str(message))
    return _MASKS[1].sub('#', text)[:200]


class Counters:
    """Thread-safe counters plus `problem()`: count a refused input, log its kind rate-limited.

    log: called with one line (a logger's warning method); clock: seconds (time.monotonic)."""

    def __init__(self, log=print, period_s: float = 60.0, max_kinds: int = 64, clock=time.monotonic):
        self.log, self.period_s, self.max_kinds, self.clock = log, float(period_s), int(max_kinds), clock
        self.counts: Counter = Counter()
        self._kinds: dict = {}  # (counter, kind) -> [time last logged, repeats since]
        self._lock = threading.Lock()

    def count(self, key: str, n: int = 1) -> None:
        with self._lock:
            self.counts[key] += n

    def problem(self, counter: str, message: str, kind: str | None = None) -> bool:
        """Count one refused input under `counter`; log it when its kind is new or its period has
        passed. Returns whether a line was logged."""
        kind = kind or problem_kind(message)
        now = self.clock()
        with self._lock:
            self.counts[counter] += 1
            total = self.counts[counter]
            key = (counter, kind)
            if key not in self._kinds and sum(1 for c, _ in self._kinds if c == counter) >= self.max_kinds:
                key = (counter, '<other>')
            state = self._kinds.get(key)
            if state is None:
                self._kinds[key] = [now, 0]
                line = (
                    f'{counter}: {message} (skipped; further problems of this kind are counted and '
                    f'logged at most every {self.period_s:g} s; {total} so far)'
                )
            elif now - state[0] >= self.period_s:
                repeats, state[0], state[1] = state[1], now, 0
                line = (
                    f'{counter}: {message} (skipped; {repeats} more of this kind in the last '
                    f'{self.period_s:g} s; {total} so far)'
                )
            else:
                state[1] += 1
                return False
        self.log(line)
        return True

    def snapshot(self) -> dict:
        with self._lock:
            return dict(self.counts)
