"""At most one log line per kind of event and period, with a count of the lines left out.

A saturated server refuses thousands of calls a second; one line a second per kind of
refusal says as much. Used by every node through :class:`drvs.ros.node.NodeScaffold`.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable, Hashable

__all__ = ['LogThrottle', 'not_logged']


class LogThrottle:
    """At most one log line per kind of event and ``period`` seconds, and how many were not logged.

    >>> clock = iter([0.0, 0.5, 0.7, 1.2]).__next__
    >>> throttle = LogThrottle(1.0, clock)
    >>> [throttle.allow('BUSY') for _ in range(4)]
    [0, None, None, 2]
    """

    def __init__(self, period: float, clock: Callable[[], float] = time.monotonic):
        self.period = period
        self.clock = clock
        self._lock = threading.Lock()  # guards _next and _unlogged
        self._next: dict[Hashable, float] = {}  # kind -> when the next line may be logged
        self._unlogged: dict[Hashable, int] = {}  # kind -> events not logged since the last line

    def allow(self, kind: Hashable) -> int | None:
        """None: do not log this event (it is counted); else log it, with this many not logged before."""
        with self._lock:
            now = self.clock()
            if now < self._next.get(kind, -math.inf):
                self._unlogged[kind] = self._unlogged.get(kind, 0) + 1
                return None
            self._next[kind] = now + self.period
            return self._unlogged.pop(kind, 0)


def not_logged(count: int, period: float) -> str:
    """The suffix of a throttled line: how many like it were left out.

    >>> not_logged(3, 1.0), not_logged(0, 1.0)
    (' (3 more like it not logged in the last 1 s)', '')
    """
    return f' ({count} more like it not logged in the last {period:g} s)' if count else ''
