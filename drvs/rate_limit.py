"""Per-caller rate limiting of ROS requests: a token bucket per caller id.

Each key (the caller id of a ROS request) has a bucket of at most ``burst``
tokens that refills at ``rate`` tokens per second; a request takes one token
or is refused with the seconds until one will be there, which the server
returns as its ``retry_after`` hint (see :func:`drvs.retry.retry_delay`).

Memory stays bounded however many callers come and go: the buckets live in a
``cachetools.TTLCache`` with ``ttl = burst / rate`` and ``maxsize = max_keys``.
A bucket untouched for ``burst / rate`` seconds would be full again anyway,
so forgetting it loses nothing; beyond ``max_keys`` the least recently used
key is forgotten, which at worst hands that caller a fresh full bucket.

No ROS here. Thread-safe: one lock, ``RateLimiter._lock``, guards the buckets
(``TTLCache`` itself is not thread-safe).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

from cachetools import TTLCache

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
        self._lock = threading.Lock()
        # key -> (tokens, time they were counted); the TTL runs from the last write.
        self._buckets: TTLCache = TTLCache(maxsize=self.max_keys, ttl=self.burst / self.rate, timer=clock)
        self.refused = 0  # requests refused since construction

    def __len__(self) -> int:
        """Keys tracked now (expired ones not counted)."""
        with self._lock:
            return len(self._buckets)

    def limited(self) -> int:
        """How many keys would be refused now: those with less than one token left."""
        with self._lock:
            now = self.clock()
            return sum(
                1
                for counted, at in self._buckets.values()
                if counted + max(0.0, now - at) * self.rate < 1 - _ROUNDING
            )

    def take(self, key: str) -> float:
        """Take one token from ``key``'s bucket.

        Returns 0.0 if a token was taken, else the seconds until one will be
        available (> 0); a refusal takes nothing.
        """
        with self._lock:
            now = self.clock()
            bucket = self._buckets.get(key)
            if bucket is None:
                tokens = self.burst
            else:
                counted, at = bucket
                tokens = min(self.burst, counted + max(0.0, now - at) * self.rate)
            if tokens >= 1 - _ROUNDING:
                # A write restarts the TTL: from here the bucket is full again
                # after at most burst / rate seconds, exactly when it expires.
                self._buckets[key] = (max(0.0, tokens - 1), now)
                return 0.0
            self.refused += 1
            return (1 - tokens) / self.rate
