"""The registry of vision systems: who sees which part of the floor, for how long.

Each vision system registers its DetectObjectBoundary service name and its
field of view (a polygon on the floor, frame ``map``). A registration is a
lease: it lasts ``lease`` seconds unless renewed by registering again. A moved
camera registers its new field of view and routing follows at once; an empty
field of view unregisters. A vision system whose forwards fail ``max_failures``
times in a row is removed; registering again brings it back.

:meth:`Registry.match` is the paper's Algorithm 1: the vision systems whose
field of view meets the region of interest, through a spatial index
(:mod:`drvs.spatial_index`; touching edges do not count). No ROS here: the
server (:mod:`drvs.ros.server`) checks who may register what and does the
forwarding. Thread-safe: one lock, ``Registry._lock``, guards the entries.
"""

from __future__ import annotations

import heapq
import logging
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

from shapely.geometry import Polygon

from drvs.spatial_index import FieldOfViewIndex
from drvs.validation import ValidationError, field_of_view_polygon, region_geometry, region_of_interest

logger = logging.getLogger('rosout.' + __name__)

__all__ = ['Registration', 'Registry', 'ValidationError']

REGISTERED, MOVED, RENEWED, UNREGISTERED, NOT_REGISTERED = (
    'registered',
    'moved',
    'renewed',
    'unregistered',
    'not registered',
)


@dataclass(frozen=True)
class Registration:
    """One vision system's entry."""

    service_name: str
    field_of_view: tuple[tuple[float, float], ...]
    polygon: Polygon = field(repr=False, compare=False)
    expires_at: float  # on the registry's clock


class Registry:
    """Vision systems by service name, with leases, failure counts and a spatial index.

    :param lease: seconds a registration lasts unless renewed.
    :param max_failures: consecutive failed forwards after which an entry is removed.
    :param clock: monotonic seconds (injectable for tests).
    :param index: the spatial index (default: a background-rebuilding one).
    """

    def __init__(
        self,
        lease: float = 10.0,
        max_failures: int = 3,
        clock: Callable[[], float] = time.monotonic,
        index: FieldOfViewIndex | None = None,
    ):
        if not lease > 0:
            raise ValueError(f'lease: must be positive, got {lease}')
        if max_failures < 1:
            raise ValueError(f'max_failures: must be at least 1, got {max_failures}')
        self.lease = float(lease)
        self.max_failures = int(max_failures)
        self.clock = clock
        self._lock = threading.Lock()
        self._entries: dict[str, Registration] = {}
        self._failures: dict[str, int] = {}
        self._expiries: list[tuple[float, str]] = []  # heap; stale items are skipped
        self._index = index if index is not None else FieldOfViewIndex()
        self.version = 0  # bumped on every change of the listed entries (not on renewals)

    def __len__(self) -> int:
        return len(self._entries)

    def __contains__(self, service_name: str) -> bool:
        return service_name in self._entries

    def get(self, service_name: str) -> Registration | None:
        return self._entries.get(service_name)

    def entries(self) -> list[Registration]:
        """A snapshot of every entry, sorted by service name."""
        with self._lock:
            return sorted(self._entries.values(), key=lambda entry: entry.service_name)

    def register(self, service_name: str, field_of_view: Sequence[Sequence[float]]) -> str:
        """Add, move, renew or (with no vertices) remove ``service_name``.

        Returns what happened: ``'registered'``, ``'moved'``, ``'renewed'`` (same
        field of view), ``'unregistered'`` or ``'not registered'`` (empty field
        of view for an unknown name). Any of them resets the failure count.

        :raises ValidationError: the field of view is not a valid polygon.
        """
        if len(field_of_view) == 0:
            return UNREGISTERED if self.unregister(service_name) else NOT_REGISTERED
        polygon = field_of_view_polygon(field_of_view)
        points = tuple((float(p[0]), float(p[1])) for p in field_of_view)
        with self._lock:
            expires_at = self.clock() + self.lease
            old = self._entries.get(service_name)
            if old is not None and old.field_of_view == points:
                self._entries[service_name] = Registration(service_name, points, old.polygon, expires_at)
                change = RENEWED
            else:
                self._entries[service_name] = Registration(service_name, points, polygon, expires_at)
                self._index.insert(service_name, polygon)
                self.version += 1
                change = REGISTERED if old is None else MOVED
            self._failures[service_name] = 0
            heapq.heappush(self._expiries, (expires_at, service_name))
        return change

    def unregister(self, service_name: str) -> bool:
        """Remove ``service_name``; False if it was not registered."""
        with self._lock:
            return self._remove(service_name)

    def _remove(self, service_name: str) -> bool:
        if self._entries.pop(service_name, None) is None:
            return False
        self._failures.pop(service_name, None)
        self._index.remove(service_name)
        self.version += 1
        return True

    def match(self, region: Sequence[float]) -> list[str]:
        """Service names of the live vision systems whose field of view meets ``region``.

        ``region`` is (min_x, min_y, max_x, max_y), checked by
        :func:`drvs.validation.region_of_interest`. Sorted by name. Expired
        entries never match, even before :meth:`expire` removes them.
        """
        geometry = region_geometry(region_of_interest(region))
        keys = self._index.query(geometry)
        now = self.clock()
        with self._lock:
            live = [key for key in keys if (entry := self._entries.get(key)) and entry.expires_at > now]
        return sorted(live)

    def expire(self) -> list[str]:
        """Remove every entry whose lease has run out; return their names."""
        removed = []
        with self._lock:
            now = self.clock()
            while self._expiries and self._expiries[0][0] <= now:
                expires_at, name = heapq.heappop(self._expiries)
                entry = self._entries.get(name)
                if entry is not None and entry.expires_at <= now and self._remove(name):
                    removed.append(name)
            if len(self._expiries) > 4 * len(self._entries) + 64:  # renewals leave stale heap items
                self._expiries = [(e.expires_at, e.service_name) for e in self._entries.values()]
                heapq.heapify(self._expiries)
        return removed

    def record_success(self, service_name: str) -> None:
        with self._lock:
            if service_name in self._failures:
                self._failures[service_name] = 0

    def record_failure(self, service_name: str) -> bool:
        """Count a failed forward; remove the entry at ``max_failures`` in a row. True if removed."""
        with self._lock:
            if service_name not in self._failures:
                return False
            self._failures[service_name] += 1
            if self._failures[service_name] >= self.max_failures:
                return self._remove(service_name)
            return False

    def failures(self, service_name: str) -> int:
        return self._failures.get(service_name, 0)
