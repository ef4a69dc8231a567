"""Counts by name since start and over the last period, for a node's health report.

:meth:`PeriodCounts.take_period` returns what was counted since it was last called and
starts a new period (only the node's health report calls it). No ROS here; one lock,
``PeriodCounts._lock``; beyond ``max_keys`` names, new ones count under ``other``.
The node scaffold's use of it: docs/architecture.md.

>>> counts = PeriodCounts()
>>> counts.add('BUSY', 3); counts.add('INVALID')
>>> counts.take_period(), counts.take_period()
({'BUSY': 3, 'INVALID': 1}, {})
>>> counts.totals()
{'BUSY': 3, 'INVALID': 1}
"""

from __future__ import annotations

import threading
from collections.abc import Iterable

__all__ = ['OTHER', 'Counters', 'PeriodCounts']

OTHER = 'other'
"""The name every name beyond ``max_keys`` is counted under."""


class PeriodCounts:
    """Counts per name: in all, and since the last :meth:`take_period`.

    :param max_keys: distinct names kept; further names count under :data:`OTHER`.
    """

    def __init__(self, max_keys: int = 64):
        if max_keys < 1:
            raise ValueError(f'max_keys: must be at least 1, got {max_keys}')
        self.max_keys = int(max_keys)
        self._lock = threading.Lock()
        self._totals: dict[str, int] = {}
        self._period: dict[str, int] = {}

    def add(self, key: str, number: int = 1) -> None:
        """Count ``number`` more of ``key``."""
        with self._lock:
            if key not in self._totals and len(self._totals) >= self.max_keys:
                key = OTHER
            self._totals[key] = self._totals.get(key, 0) + number
            self._period[key] = self._period.get(key, 0) + number

    def totals(self) -> dict[str, int]:
        """Every count since construction."""
        with self._lock:
            return dict(self._totals)

    def take_period(self) -> dict[str, int]:
        """The counts since the previous call (since construction for the first), and a new period."""
        with self._lock:
            period, self._period = self._period, {}
            return period


class Counters:
    """A node's named counters (its ``~stats``) under one lock, and whether they changed.

    :param names: the counters, each starting at 0; others cannot be added or set.

    >>> stats = Counters(('requests', 'refused'))
    >>> stats.add(requests=2); stats.take_changed()
    {'requests': 2, 'refused': 0}
    >>> stats.take_changed() is None
    True
    >>> stats.add(missing=1)
    Traceback (most recent call last):
    ...
    KeyError: "no counter 'missing' (counters: requests, refused)"
    """

    def __init__(self, names: tuple[str, ...] | list[str]):
        self.lock = threading.Lock()  # guards _values and _changed
        self._values: dict[str, int] = dict.fromkeys(names, 0)
        self._changed = True

    def _check(self, keys: Iterable[str]) -> None:
        for key in keys:
            if key not in self._values:
                raise KeyError(f'no counter {key!r} (counters: {", ".join(self._values)})')

    def add(self, **increments: int) -> None:
        """Count ``increments`` more of each named counter."""
        with self.lock:
            self._check(increments)
            for key, number in increments.items():
                self._values[key] += number
            self._changed = True

    def set(self, **values: int) -> bool:
        """Set gauges (``watches`` standing); True if any changed."""
        with self.lock:
            self._check(values)
            changed = any(self._values[key] != value for key, value in values.items())
            self._values.update(values)
            self._changed |= changed
            return changed

    def snapshot(self) -> dict[str, int]:
        """Every counter now."""
        with self.lock:
            return dict(self._values)

    def take_changed(self) -> dict[str, int] | None:
        """The counters if they changed since the last call (the first call: always), else None."""
        with self.lock:
            if not self._changed:
                return None
            self._changed = False
            return dict(self._values)

    def __getitem__(self, key: str) -> int:
        with self.lock:
            return self._values[key]
