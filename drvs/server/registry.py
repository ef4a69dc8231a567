"""The registry of vision systems: who sees which part of the floor, runs what, through which connection.

Registrations are leases; failed forwards remove and eject a vision system;
:meth:`Registry.match` is the paper's Algorithm 1 through the spatial index. No ROS here:
:mod:`drvs.server.registration` decides who may register what; the server node forwards. How and
why: docs/design.md ("The server"); what a vision system sees of it: docs/nodes/drvs_server.md.

>>> registry = Registry()
>>> registry.register('/vs1', [(0, 0), (2, 0), (2, 2)], algorithms=['colour', 'sift'])
'registered'
>>> registry.match((0.5, 0.2, 1.0, 0.4), 'sift'), registry.match((0.5, 0.2, 1.0, 0.4), 'motion')
(['/vs1'], [])
>>> registry.available_algorithms()
['colour', 'sift']
"""

from __future__ import annotations

import heapq
import logging
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Protocol

from shapely.geometry import Polygon

from drvs.algorithms import BUILTIN_NAMES
from drvs.algorithms.base import NAME_PATTERN
from drvs.common.status import UNAVAILABLE, Refusal
from drvs.common.validation import ValidationError, field_of_view_polygon, region_of_interest
from drvs.server.sites import other_site, remote, site_name
from drvs.server.spatial_index import FieldOfViewIndex

logger = logging.getLogger('rosout.' + __name__)

__all__ = ['Client', 'Refusal', 'Registration', 'Registry', 'ValidationError', 'algorithm_names']


class Client(Protocol):
    """What the server forwards through, made for each vision system by the caller's ``make_client``."""

    def close(self) -> None: ...


REGISTERED, MOVED, CHANGED, RENEWED, UNREGISTERED, NOT_REGISTERED = (
    'registered',
    'moved',
    'changed',
    'renewed',
    'unregistered',
    'not registered',
)

MAX_ALGORITHMS = 64
"""Most algorithm names one registration may declare."""
MAX_ALGORITHM_NAME = 64
"""Longest algorithm name, in characters."""
_BUILTINS = frozenset(BUILTIN_NAMES)  # one set shared by every registration that runs the built-ins


def algorithm_names(names: Sequence[str]) -> frozenset[str]:
    """The algorithm names a registration declares, checked; an empty list means the built-ins.

    Repeated names count once.

    >>> sorted(algorithm_names([]))
    ['apriltag', 'colour', 'motion']
    >>> sorted(algorithm_names(['sift', 'colour', 'sift']))
    ['colour', 'sift']

    :raises ValidationError: more than :data:`MAX_ALGORITHMS` names; a name that is
        not a string, longer than :data:`MAX_ALGORITHM_NAME` or not an algorithm NAME
        (:data:`drvs.algorithms.base.NAME_PATTERN`), naming it as ``algorithms[i]``.
    """
    if len(names) > MAX_ALGORITHMS:
        raise ValidationError(f'algorithms: {len(names)} names, more than the limit of {MAX_ALGORITHMS}')
    if len(names) == 0:
        return _BUILTINS
    for index, name in enumerate(names):
        if not isinstance(name, str):
            raise ValidationError(f'algorithms[{index}]: expected a string, got {type(name).__name__}')
        if len(name) > MAX_ALGORITHM_NAME:
            raise ValidationError(
                f'algorithms[{index}]: {len(name)} characters, longer than the limit of {MAX_ALGORITHM_NAME}'
            )
        if not NAME_PATTERN.fullmatch(name):
            raise ValidationError(
                f'algorithms[{index}]: {name!r} is not an algorithm NAME '
                '(a letter, then letters, digits or _, without :PARAMS)'
            )
    return frozenset(names)


@dataclass(frozen=True, slots=True)
class Registration:
    """One vision system's entry."""

    service_name: str
    field_of_view: tuple[tuple[float, float], ...]
    polygon: Polygon = field(repr=False, compare=False)
    expires_at: float  # on the registry's clock
    provider: str = ''  # caller id of the node that registered it
    instance: str = ''  # which process serves it (the server uses its rosrpc URI)
    algorithms: frozenset[str] = _BUILTINS  # the algorithm names it runs
    client: Client | None = field(default=None, repr=False, compare=False)  # what the server forwards through
    watch_service: bool = False  # it serves drvs/WatchObjectBoundary too (:mod:`drvs.server.watch_table`)
    site: str = ''  # the site (``~site``) of the server it registered through (:mod:`drvs.server.sites`)


class Registry:
    """Vision systems by service name, with leases, failure counts, ejection and a spatial index.

    :param lease: seconds a registration lasts unless renewed.
    :param max_failures: consecutive failed forwards after which an entry is removed and ejected.
    :param ejection_time: seconds an ejected vision system is refused, times its ejection count.
    :param max_ejection_time: cap on one ejection, seconds.
    :param clock: monotonic seconds (injectable for tests).
    :param index: the spatial index (default: a new :class:`~drvs.server.spatial_index.FieldOfViewIndex`).
    :param site: this server's site: every registration through it is recorded there
        (:mod:`drvs.server.sites`; '' = the only site).
    """

    def __init__(
        self,
        lease: float = 10.0,
        max_failures: int = 3,
        clock: Callable[[], float] = time.monotonic,
        index: FieldOfViewIndex | None = None,
        ejection_time: float = 10.0,
        max_ejection_time: float = 300.0,
        site: str = '',
    ):
        site_name(site)
        if not lease > 0:
            raise ValueError(f'lease: must be positive, got {lease}')
        if max_failures < 1:
            raise ValueError(f'max_failures: must be at least 1, got {max_failures}')
        if not 0 <= ejection_time <= max_ejection_time:
            raise ValueError(
                f'ejection_time: must be between 0 and max_ejection_time ({max_ejection_time}), '
                f'got {ejection_time}'
            )
        self.lease = float(lease)
        self.max_failures = int(max_failures)
        self.ejection_time = float(ejection_time)
        self.max_ejection_time = float(max_ejection_time)
        self.clock = clock
        self.site = site
        self._lock = threading.Lock()
        self._entries: dict[str, Registration] = {}
        self._failures: dict[str, int] = {}
        self._ejections: dict[str, tuple[int, float, str]] = {}  # name -> (times, refused until, instance)
        self._expiries: list[tuple[float, str]] = []  # heap; stale items are skipped
        self._index = index if index is not None else FieldOfViewIndex()
        self.version = 0  # bumped on every change of the listed entries (not on renewals)
        self.ejected_total = 0

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

    def register(
        self,
        service_name: str,
        field_of_view: Sequence[Sequence[float]],
        provider: str = '',
        make_client: Callable[[str, str | None], Client] | None = None,
        instance: str = '',
        algorithms: Sequence[str] = (),
        watch_service: bool = False,
    ) -> str:
        """Add, move, renew or (with no vertices) remove ``service_name``.

        Returns what happened: ``'registered'``, ``'moved'`` (a new field of view),
        ``'changed'`` (the same field of view, new ``algorithms``), ``'renewed'``
        (both the same), ``'unregistered'`` or ``'not registered'`` (empty field
        of view for an unknown name; ``algorithms`` is then ignored). A new
        registration, a move and a change reset the failure count; a renewal does
        not. A new entry gets its client from ``make_client(service_name, None)``
        (the second argument: the address to call it at directly, None for an entry of this
        site; called under the lock: it must do no I/O); a moved, changed or renewed
        one keeps its client. An unregistered entry's client is closed by
        :meth:`unregister`'s caller: use that to remove.

        :param algorithms: the names of the algorithms it runs (:func:`algorithm_names`;
            empty: the built-ins).
        :param watch_service: whether it also serves watches (the server checks it on a new
            registration and passes it on with every renewal).
        :raises ValidationError: the field of view is not a valid polygon, or a name in
            ``algorithms`` is not valid.
        :raises Refusal: ``UNAVAILABLE``, this instance of the vision system is ejected, or the
            name is registered at another site; ``retry_after`` says until when.
        """
        if len(field_of_view) == 0:
            removed = self.unregister(service_name)
            if removed is not None and removed.client is not None:
                removed.client.close()
            return UNREGISTERED if removed is not None else NOT_REGISTERED
        polygon = field_of_view_polygon(field_of_view)
        names = algorithm_names(algorithms)
        points = tuple([(float(p[0]), float(p[1])) for p in field_of_view])
        with self._lock:
            now = self.clock()
            old = self._entries.get(service_name)
            if old is not None and old.site != self.site:
                raise other_site(service_name, old.site, old.expires_at - now)
            self._refuse_if_ejected(service_name, instance, now)
            expires_at = now + self.lease
            if old is None:
                client = make_client(service_name, None) if make_client is not None else None
            else:
                client = old.client
            moved = old is None or old.field_of_view != points
            if old is not None and not moved:
                polygon = old.polygon
                change = RENEWED if old.algorithms == names else CHANGED
            else:
                change = REGISTERED if old is None else MOVED
            entry = Registration(
                service_name,
                points,
                polygon,
                expires_at,
                provider=provider,
                instance=instance,
                algorithms=names,
                client=client,
                watch_service=watch_service,
                site=self.site,
            )
            try:
                self._persist(entry, change)  # a store's write; may refuse before anything changed here
            except Refusal:
                if old is None and client is not None:
                    client.close()
                raise
            self._entries[service_name] = entry
            if moved:
                self._index.insert(service_name, polygon, points, value=entry)
            else:
                self._index.set_value(service_name, entry)  # a match answers the entries it finds
            if change != RENEWED:
                self.version += 1
                self._failures[service_name] = 0
            heapq.heappush(self._expiries, (expires_at, service_name))
        return change

    def _persist(self, entry: Registration, change: str) -> None:
        """Called with the lock held before ``entry`` takes effect: nothing to do in memory
        (a shared registry writes it to its store here, :mod:`drvs.server.shared_registry`)."""

    def _removed(self, entry: Registration) -> None:
        """Called with the lock held when ``entry`` is removed: nothing more to do in memory."""

    def _live(self, entry: Registration, now: float) -> bool:
        """Whether ``entry`` may be matched at ``now``: its lease has not run out."""
        return entry.expires_at > now

    def _refuse_if_ejected(self, service_name: str, instance: str, now: float) -> None:
        times, until, ejected = self._ejections.get(service_name, (0, 0.0, ''))
        if now >= until:
            return
        if instance != ejected:  # a new process: let it in, but remember the count
            self._ejections[service_name] = (times, now, ejected)
            return
        raise Refusal(
            UNAVAILABLE,
            f'service_name: {service_name} was removed after {self.max_failures} failed forwards '
            f'in a row and is ejected for {until - now:.1f} s more (ejection {times}); '
            'make its DetectObjectBoundary answer, or restart it, then register again',
            until - now,
        )

    def ejected_until(self, service_name: str) -> float | None:
        """When ``service_name``'s current ejection ends (registry clock), or None if it is not ejected."""
        with self._lock:
            until = self._ejections.get(service_name, (0, 0.0, ''))[1]
            return until if until > self.clock() else None

    def ejected(self) -> int:
        """How many vision systems are ejected now (their registrations refused ``UNAVAILABLE``)."""
        with self._lock:
            now = self.clock()
            return sum(1 for _, until, _ in self._ejections.values() if until > now)

    def unregister(self, service_name: str) -> Registration | None:
        """Remove ``service_name``; return its entry (close its client), None if it was not registered."""
        with self._lock:
            return self._remove(service_name)

    def _remove(self, service_name: str) -> Registration | None:
        entry = self._entries.pop(service_name, None)
        if entry is None:
            return None
        self._removed(entry)
        self._failures.pop(service_name, None)
        self._index.remove(service_name)
        self.version += 1
        return entry

    def match(self, region: Sequence[float], algorithm: str | None = None) -> list[str]:
        """Service names of the live vision systems whose field of view meets ``region``.

        ``region`` is (min_x, min_y, max_x, max_y), checked by
        :func:`drvs.common.validation.region_of_interest`. With ``algorithm`` (a NAME), only
        those that run it. Sorted by name. Expired entries never match, even before
        :meth:`expire` removes them.
        """
        found = self._index.query_box(region_of_interest(region))  # the entries, current when found
        now = self.clock()
        return sorted(
            entry.service_name
            for entry in found
            if self._live(entry, now) and (algorithm is None or algorithm in entry.algorithms)
        )

    def available_algorithms(self) -> list[str]:
        """The algorithm names that at least one live vision system runs, sorted."""
        now = self.clock()
        with self._lock:
            live = [entry.algorithms for entry in self._entries.values() if self._live(entry, now)]
        return sorted(frozenset().union(*live))

    def expire(self) -> list[Registration]:
        """Remove every entry whose lease has run out; return them (close their clients)."""
        removed = []
        with self._lock:
            now = self.clock()
            while self._expiries and self._expiries[0][0] <= now:
                expires_at, name = heapq.heappop(self._expiries)
                entry = self._entries.get(name)
                if entry is not None and entry.expires_at <= now:
                    self._remove(name)
                    removed.append(entry)
            if len(self._expiries) > 4 * len(self._entries) + 64:  # renewals leave stale heap items
                self._expiries = [(e.expires_at, e.service_name) for e in self._entries.values()]
                heapq.heapify(self._expiries)
            for name, (_, until, _) in list(self._ejections.items()):  # bounded: forget old ones
                if until + self.max_ejection_time < now:
                    del self._ejections[name]
        return removed

    def sync(self) -> list[Registration]:
        """The server's periodic call: :meth:`expire` (a shared registry also follows its store)."""
        return self.expire()

    def record_success(self, service_name: str) -> None:
        """A forward succeeded: the run of failures and past ejections are forgotten."""
        with self._lock:
            if service_name in self._failures:
                self._failures[service_name] = 0
            if self._ejections.pop(service_name, None) is not None:
                self._forgiven(service_name)

    def record_failure(self, service_name: str) -> Registration | None:
        """Count a failed forward; at ``max_failures`` in a row remove and eject the entry and return it.

        An entry of another site is counted but never removed from here: its own site's servers
        judge it (forwards that fail across sites may be the network between them, and an ejection
        would hold at its own site too); its lease ends if it is gone.
        """
        with self._lock:
            if service_name not in self._failures:
                return None
            self._failures[service_name] += 1
            if self._failures[service_name] < self.max_failures:
                return None
            if remote(self.site, self._entries[service_name].site):
                return None
            instance = self._entries[service_name].instance
            self._ejections[service_name] = self._eject(service_name, instance)
            self.ejected_total += 1
            return self._remove(service_name)

    def _eject(self, service_name: str, instance: str) -> tuple[int, float, str]:
        """Called with the lock held: ``service_name``'s ejection (times, refused until, instance)."""
        times = self._ejections.get(service_name, (0, 0.0, ''))[0] + 1
        duration = min(self.ejection_time * times, self.max_ejection_time)
        return (times, self.clock() + duration, instance)

    def _forgiven(self, service_name: str) -> None:
        """Called with the lock held when a successful forward forgets ``service_name``'s ejections."""

    def failures(self, service_name: str) -> int:
        return self._failures.get(service_name, 0)
