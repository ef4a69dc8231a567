"""Per-caller rate limiting: a token bucket per key (the server's caller ids, the gateway's tokens).

A request takes a token or is refused with the seconds until one will be there (the
server's ``retry_after``); idle buckets and those beyond ``max_keys`` are forgotten, so
memory stays bounded. No ROS here; one lock, ``RateLimiter._lock``. Why it is built this
way: docs/design.md ("Rate limit").
"""

from __future__ import annotations

import threading
import time
from collections import OrderedDict
from collections.abc import Callable

__all__ = ['RateLimiter']

# Tokens short of one that still count as one: a caller that waits exactly the
# retry_after it was given must not be refused again by a rounding error.
_ROUNDING = 1e-9


class RateLimiter:
    """A token bucket per key: ``burst`` requests at once, then ``rate`` per second.

    :param rate: tokens added per second, per key.
    :param burst: the most tokens a bucket holds; a new key starts full.
    :param clock: monotonic seconds (injectable for tests).
    :param max_keys: the most keys tracked at once (least recently used forgotten first).
    """

    def __init__(
        self,
        rate: float,
        burst: float,
        clock: Callable[[], float] = time.monotonic,
        max_keys: int = 100_000,
    ):
        if not rate > 0:
            raise ValueError(f'rate: must be positive, got {rate}')
        if not burst >= 1:
            raise ValueError(f'burst: must be at least 1, got {burst}')
        if max_keys < 1:
            raise ValueError(f'max_keys: must be at least 1, got {max_keys}')
        self.rate = float(rate)
        self.burst = float(burst)
        self.clock = clock
        self.max_keys = int(max_keys)
        self.ttl = self.burst / self.rate
        self._lock = threading.Lock()
        # key -> (tokens, time they were counted), least recently used first. A bucket counted
        # ttl seconds ago or more is full again: it is as good as absent (forgotten when met).
        self._buckets: OrderedDict[str, tuple[float, float]] = OrderedDict()
        self.refused = 0  # requests refused since construction

    def __len__(self) -> int:
        """Keys tracked now (those full again by now not counted)."""
        with self._lock:
            now = self.clock()
            return sum(1 for _, at in self._buckets.values() if now - at < self.ttl)

    def limited(self) -> int:
        """How many keys would be refused now: those with less than one token left."""
        with self._lock:
            now = self.clock()
            return sum(
                1
                for counted, at in self._buckets.values()
                if now - at < self.ttl and counted + max(0.0, now - at) * self.rate < 1 - _ROUNDING
            )

    def take(self, key: str) -> float:
        """Take one token from ``key``'s bucket.

        Returns 0.0 if a token was taken, else the seconds until one will be
        available (> 0); a refusal takes nothing.
        """
        with self._lock:
            now = self.clock()
            buckets = self._buckets
            bucket = buckets.get(key)
            if bucket is None or now - bucket[1] >= self.ttl:
                tokens = self.burst
            else:
                counted, at = bucket
                tokens = min(self.burst, counted + max(0.0, now - at) * self.rate)
            if tokens >= 1 - _ROUNDING:
                # From here the bucket is full again after at most burst / rate seconds.
                buckets[key] = (max(0.0, tokens - 1), now)
                buckets.move_to_end(key)
                self._forget(now)
                return 0.0
            buckets.move_to_end(key)
            self.refused += 1
            return (1 - tokens) / self.rate

    def _forget(self, now: float) -> None:
        """Called with the lock held: drop the least recently used buckets that are full again
        by now, and any beyond ``max_keys``."""
        buckets = self._buckets
        while buckets:
            key, (_, at) = next(iter(buckets.items()))
            if now - at < self.ttl and len(buckets) <= self.max_keys:
                return
            del buckets[key]
