"""The newest frame of a camera feed: which frame a request may use, and whether the feed is alive.

Only the newest frame is kept; a request uses it if younger than ``max_age``, else waits
up to ``timeout`` for the next; the feed is stale after ``stale_after`` seconds without
one. Arrival is measured on an injected clock. What a vision system does with it:
docs/nodes/vision_system.md.

>>> from types import SimpleNamespace
>>> from drvs.testing.clock import ManualClock
>>> clock = ManualClock(100.0)
>>> feed = FrameFeed(max_age=0.1, timeout=0.5, stale_after=2.0, clock=clock)
>>> feed.put(SimpleNamespace(stamp=99.95))
>>> feed.get().stamp  # 0.05 s old: fresh enough
99.95
>>> clock.now += 3.0
>>> feed.stale()
True
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from drvs.vision.frame import Frame


class FrameTimeout(RuntimeError):
    """No usable frame arrived in time; the message says how long was waited and for what."""


class FrameFeed:
    """The newest frame of one feed, shared by the subscriber thread and the workers."""

    def __init__(
        self,
        max_age: float,
        timeout: float,
        stale_after: float,
        clock: Callable[[], float] = time.time,
    ):
        self.max_age = max_age
        self.timeout = timeout
        self.stale_after = stale_after
        self.clock = clock
        self.received = 0
        self._frame: Frame | None = None
        self._received_at = -math.inf
        self._changed = threading.Condition()

    def put(self, frame: Frame) -> None:
        """A new frame arrived: it replaces the previous one and wakes the waiting requests."""
        with self._changed:
            self._frame = frame
            self._received_at = self.clock()
            self.received += 1
            self._changed.notify_all()

    def newest(self) -> Frame | None:
        """The newest frame, whatever its age (None before the first)."""
        with self._changed:
            return self._frame

    def get(self) -> Frame:
        """A frame for a request made now: the newest if it is younger than ``max_age``, else the
        next one to arrive. Raises :class:`FrameTimeout` after ``timeout`` seconds without one."""
        with self._changed:
            if self._frame is not None and self.clock() - self._frame.stamp <= self.max_age:
                return self._frame
            seen = self.received
            if not self._changed.wait_for(lambda: self.received > seen, self.timeout):
                if self._frame is None:
                    raise FrameTimeout(f'no frame has arrived yet (waited {self.timeout:g} s)')
                age = self.clock() - self._received_at
                raise FrameTimeout(
                    f'no new frame within {self.timeout:g} s (the last one arrived {age:.1f} s ago)'
                )
            assert self._frame is not None  # a frame was put
            return self._frame

    def stale(self) -> bool:
        """Whether no frame has arrived for ``stale_after`` seconds (True before the first)."""
        with self._changed:
            return self.clock() - self._received_at > self.stale_after

    def age(self) -> float:
        """Seconds since the newest frame arrived (inf before the first)."""
        with self._changed:
            return self.clock() - self._received_at
