"""A bounded cache of open connections that closes what it evicts.

:class:`ClosingCache` keeps at most ``maxsize`` values, drops those idle for longer than
``ttl`` seconds and the least recently used beyond ``maxsize``, and closes every value it
drops, so file descriptors and threads stay flat however many callers come and go.
Why it is hand-written and how it locks: docs/design.md ("Vision systems").
"""

from __future__ import annotations

import logging
import threading
import time
from collections import OrderedDict
from collections.abc import Callable, Hashable
from typing import Any, Generic, TypeVar

logger = logging.getLogger('rosout.' + __name__)

__all__ = ['ClosingCache']

K = TypeVar('K', bound=Hashable)
V = TypeVar('V')


def _close(value: Any) -> None:
    value.close()


class ClosingCache(Generic[K, V]):
    """At most ``maxsize`` values by key, each closed when dropped.

    :param factory: makes the value for a key not cached.
    :param maxsize: the most values kept; the least recently used goes first.
    :param ttl: seconds a value may stay unused before it is dropped.
    :param clock: monotonic seconds (injectable for tests).
    :param close: closes a dropped value (default: ``value.close()``).
    """

    def __init__(
        self,
        factory: Callable[[K], V],
        maxsize: int,
        ttl: float,
        clock: Callable[[], float] = time.monotonic,
        close: Callable[[V], None] = _close,
    ):
        if maxsize < 1:
            raise ValueError(f'maxsize: must be at least 1, got {maxsize}')
        if not ttl > 0:
            raise ValueError(f'ttl: must be positive, got {ttl}')
        self.factory = factory
        self.maxsize = int(maxsize)
        self.ttl = float(ttl)
        self.clock = clock
        self.close = close
        self._lock = threading.Lock()
        self._entries: OrderedDict[K, tuple[V, float]] = OrderedDict()  # key -> (value, last use)
        self.evictions = 0  # values dropped for idleness or size (not by pop or clear)

    def __len__(self) -> int:
        return len(self._entries)

    def __contains__(self, key: object) -> bool:
        return key in self._entries

    def get(self, key: K) -> V:
        """The value for ``key``, cached or new from ``factory``; then drop idle and excess values."""
        dropped: list[tuple[K, V]] = []
        try:
            with self._lock:
                now = self.clock()
                self._drop_idle(now, dropped)  # first, so an idle value is replaced, not reused
                entry = self._entries.get(key)
                if entry is not None:
                    value = entry[0]
                    self._entries.move_to_end(key)
                else:
                    value = self.factory(key)
                self._entries[key] = (value, now)
                while len(self._entries) > self.maxsize:
                    old_key, (old_value, _) = self._entries.popitem(last=False)
                    dropped.append((old_key, old_value))
                    self.evictions += 1
        finally:
            self._close_all(dropped)
        return value

    def pop(self, key: K) -> bool:
        """Close and remove ``key``'s value; False if it was not cached."""
        with self._lock:
            entry = self._entries.pop(key, None)
        if entry is None:
            return False
        self._close_all([(key, entry[0])])
        return True

    def expire(self) -> int:
        """Close and remove the values idle for longer than ``ttl``; return how many."""
        dropped: list[tuple[K, V]] = []
        with self._lock:
            self._drop_idle(self.clock(), dropped)
        self._close_all(dropped)
        return len(dropped)

    def clear(self) -> None:
        """Close and remove every value."""
        with self._lock:
            dropped = [(key, value) for key, (value, _) in self._entries.items()]
            self._entries.clear()
        self._close_all(dropped)

    def _drop_idle(self, now: float, dropped: list[tuple[K, V]]) -> None:
        while self._entries:
            key, (value, last_use) = next(iter(self._entries.items()))
            if now - last_use <= self.ttl:
                break
            del self._entries[key]
            dropped.append((key, value))
            self.evictions += 1

    def _close_all(self, dropped: list[tuple[K, V]]) -> None:
        for key, value in dropped:
            try:
                self.close(value)
            except Exception:
                logger.exception('closing the cached value for %r failed', key)
