"""The registry shared through a database by several servers: the store it writes through, and
what each server decides with it.

:class:`SharedRegistry` is a :class:`~drvs.server.registry.Registry` whose entries, ejections and
watches also live in a :class:`RegistryStore` (PostgreSQL: :mod:`drvs.server.pg_store`). Its own
in-memory index stays the cache every match is answered from; :meth:`SharedRegistry.sync`, called a
few times a second, writes the renewals in one batch, sweeps expired leases (one replica at a time)
and follows the store's change log. While the store is out of reach, matches and renewals go
on from the cache and new registrations are refused ``UNAVAILABLE``. No database here: the store
is injected, and tests give a fake. Schema, outage and how to run it: docs/registry.md.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Protocol

from drvs.common.status import UNAVAILABLE, Refusal
from drvs.common.validation import field_of_view_polygon
from drvs.server.registry import RENEWED, Client, Registration, Registry, algorithm_names
from drvs.server.sites import direct_uri
from drvs.server.spatial_index import FieldOfViewIndex
from drvs.server.watch_table import Watch

logger = logging.getLogger('rosout.' + __name__)

__all__ = [
    'Change',
    'RegistryStore',
    'SharedRegistry',
    'StoreError',
    'StoreUnavailable',
    'StoredEjection',
    'StoredEntry',
    'StoredWatch',
    'adopted_watch',
    'stored_watch',
]


class StoreUnavailable(Exception):
    """The store did not answer (connection lost, refused, timed out); the message says why."""


class StoreError(ValueError):
    """A store that cannot work as configured (a bad DSN, a wrong password, a schema this server does
    not know): one line for the user; the server exits 2."""


@dataclass(frozen=True, slots=True)
class StoredEntry:
    """A vision system's row: what every replica needs to match it and forward to it."""

    service_name: str
    field_of_view: tuple[tuple[float, float], ...]
    algorithms: tuple[str, ...]  # sorted
    provider: str = ''
    instance: str = ''
    watch_service: bool = False
    lease_left: float = 0.0  # seconds left when read
    replica: str = ''  # the replica that wrote it last: the one its vision system renews through
    site: str = ''  # the site of the servers it registers through (:mod:`drvs.server.sites`)


@dataclass(frozen=True, slots=True)
class Change:
    """One line of the change log: ``service_name`` as it is now (``entry`` None: removed)."""

    seq: int
    service_name: str
    entry: StoredEntry | None


@dataclass(frozen=True, slots=True)
class StoredEjection:
    """A shared ejection: ``times`` ejected, refused ``left`` seconds more, for the process ``instance``."""

    times: int
    left: float
    instance: str


@dataclass(frozen=True, slots=True)
class StoredWatch:
    """A standing watch as the store keeps it (its time left instead of a clock reading)."""

    caller: str
    request_id: str
    algorithm: str
    algorithm_name: str
    region: tuple[float, float, float, float]
    callback_service: str
    period: float
    duration: float
    changes_only: bool
    left: float
    forward_as: tuple[str, str] | None = None


class RegistryStore(Protocol):
    """What a shared registry writes through. Every method may raise :class:`StoreUnavailable`."""

    replica: str  # this server's name among the replicas
    where: str  # the store for messages (no password)

    def snapshot(self) -> tuple[int, list[StoredEntry]]:
        """Every live entry, and the change-log position they are current at."""
        ...

    def changes(self, after: int) -> list[Change] | None:
        """The changes after position ``after`` in order; None when the log no longer reaches back."""
        ...

    def write(self, entry: StoredEntry, lease: float) -> None:
        """Insert or replace ``entry`` with a lease of ``lease`` seconds from now; logged as a change."""
        ...

    def delete(self, service_name: str) -> None: ...

    def renew(self, renewals: Sequence[tuple[str, float]], lease: float) -> list[str]:
        """Renew each (name, seconds ago) of ``renewals``: its lease ends ``lease`` after that moment
        (not logged as a change); the names it does not hold."""
        ...

    def ejection(self, service_name: str) -> StoredEjection | None:
        """``service_name``'s current ejection, if it is refused now."""
        ...

    def eject(
        self, service_name: str, instance: str, ejection_time: float, max_ejection_time: float
    ) -> StoredEjection:
        """Count one more ejection of ``service_name``: refused ``ejection_time`` × its count (at most
        ``max_ejection_time``) from now."""
        ...

    def forgive(self, service_name: str) -> None:
        """Forget ``service_name``'s past ejections (a forward to it succeeded)."""
        ...

    def sweep(self, max_ejection_time: float) -> bool:
        """Remove expired leases and watches and old ejections, if this replica is the sweeper;
        False when another replica is."""
        ...

    def heartbeat(self) -> None:
        """This replica is alive (its watches are its own)."""
        ...

    def save_watch(self, watch: StoredWatch) -> None: ...

    def drop_watch(self, caller: str, request_id: str) -> None: ...

    def orphaned_watches(self, stale_after: float) -> list[StoredWatch]:
        """Take over the live watches of replicas not heard from for ``stale_after`` seconds."""
        ...

    def close(self) -> None: ...


class SharedRegistry(Registry):
    """A registry written through ``store`` and kept current from its change log.

    :param store: the shared store (connected; :meth:`load` reads it).
    :param make_client: ``make_client(service_name, uri)``: the client of an entry another replica
        registered (no I/O); ``uri``: the address to call it at, for an entry of another site
        (:func:`~drvs.server.sites.direct_uri`), else None.
    :param flush_period: seconds between two batches of renewals written to the store.
    :param sweep_period: seconds between two sweeps of expired leases (default: half a lease; a sweep
        scans every lease, 0.8 s of the database's time at a million: docs/registry.md).
    :param heartbeat_period: seconds between two heartbeats (the other replicas take this one's
        watches over when they stop).
    :param retry_after: seconds a registration refused while the store is out of reach is told to wait,
        and between two attempts to reach it again.
    The other parameters: :class:`~drvs.server.registry.Registry`.
    """

    def __init__(
        self,
        store: RegistryStore,
        lease: float = 10.0,
        max_failures: int = 3,
        clock: Callable[[], float] = time.monotonic,
        index: FieldOfViewIndex | None = None,
        ejection_time: float = 10.0,
        max_ejection_time: float = 300.0,
        make_client: Callable[[str, str | None], Client] | None = None,
        flush_period: float = 0.5,
        sweep_period: float | None = None,
        heartbeat_period: float = 1.0,
        retry_after: float = 1.0,
        site: str = '',
    ):
        super().__init__(lease, max_failures, clock, index, ejection_time, max_ejection_time, site)
        self.store = store
        self.make_client = make_client
        self.flush_period = float(flush_period)
        self.sweep_period = float(sweep_period if sweep_period is not None else self.lease / 2)
        self.heartbeat_period = float(heartbeat_period)
        self.retry_after = float(retry_after)
        self._position = 0  # the change log's position the cache is current at
        self._claimed: set[str] = set()  # entries whose vision system renews through this replica
        self._renewals: dict[str, float] = {}  # renewed here since the last batch -> when (clock)
        self._pending: list[tuple] = []  # writes that found the store out of reach, in order
        self._applying = False  # a removal comes from the change log: not written back
        # Read-your-writes: a change log read that a write of ours overtook holds rows older than
        # the cache; the names written since the read began are left to our own later log line.
        self._writes = 0  # the cache's own writes to the store so far
        self._written: dict[str, int] = {}  # name -> the number of the cache's newest write of it
        self._next_flush = self._next_sweep = self._next_heartbeat = self._next_try = -math.inf
        self.down_since: float | None = None  # on the clock, while the store is out of reach
        self.down_reason = ''
        self.recoveries = 0  # times the store came back (the server saves its watches again)
        self.restarted: list[str] = []  # entries another replica registered anew (a new process): the
        # server forwards their watches again (:meth:`~drvs.server.watch_table.WatchTable.forget`)
        self.retired: list[Client] = []  # clients replaced by one to a new address: the server closes
        # them outside the lock (:meth:`take_retired`)

    # -- the store's state ------------------------------------------------------------------------
    def load(self) -> None:
        """Fill the cache from the store (at start).

        :raises StoreUnavailable: the store did not answer.
        """
        position, entries = self.store.snapshot()
        with self._lock:
            self._apply_snapshot(position, entries)

    def problem(self) -> str | None:
        """Why the store is out of reach and since how long (for ``/diagnostics``); None when it is not."""
        if self.down_since is None:
            return None
        return (
            f'registry database unreachable for {self.clock() - self.down_since:.0f} s '
            f'({self.down_reason}): serving from the cache, refusing new registrations UNAVAILABLE'
        )

    def _went_down(self, error: StoreUnavailable) -> None:
        if self.down_since is None:
            self.down_since = self.clock()
            logger.warning('registry database unreachable (%s): serving matches from the cache', error)
        self.down_reason = str(error)
        self._next_try = self.clock() + self.retry_after

    def _unavailable(self) -> Refusal:
        return Refusal(
            UNAVAILABLE,
            f'registry: the registry database is unreachable ({self.down_reason}); '
            'registrations are refused until it is back, renewals still count',
            self.retry_after,
        )

    # -- Registry's hooks (called with the lock held) ------------------------------------------
    def _persist(self, entry: Registration, change: str) -> None:
        name = entry.service_name
        if change == RENEWED and (name in self._claimed or self.down_since is not None):
            self._claimed.add(name)  # kept in the cache; written with the next batch
            self._renewals[name] = entry.expires_at - self.lease
            return
        if self.down_since is not None:
            raise self._unavailable()
        try:
            self.store.write(_stored(entry, self.store.replica), self.lease)
        except StoreUnavailable as error:
            self._went_down(error)
            raise self._unavailable() from None
        self._wrote(name)
        self._claimed.add(name)
        self._renewals.pop(name, None)

    def _removed(self, entry: Registration) -> None:
        self._claimed.discard(entry.service_name)
        self._renewals.pop(entry.service_name, None)
        if not self._applying:
            self._wrote(entry.service_name)
            self._write(('delete', entry.service_name))

    def _wrote(self, name: str) -> None:
        """Called with the lock held: the cache wrote ``name``'s row (or its removal) to the store."""
        self._writes += 1
        self._written[name] = self._writes

    def _live(self, entry: Registration, now: float) -> bool:
        # A lease renewed through another replica is that replica's to keep: the entry stays until
        # the change log removes it (the sweeper's removal of an expired lease).
        return entry.expires_at > now or entry.service_name not in self._claimed

    def _refuse_if_ejected(self, service_name: str, instance: str, now: float) -> None:
        if service_name not in self._entries and self.down_since is None:
            try:
                shared = self.store.ejection(service_name)
            except StoreUnavailable as error:
                self._went_down(error)
                raise self._unavailable() from None
            if shared is not None:
                self._ejections[service_name] = (shared.times, now + shared.left, shared.instance)
        super()._refuse_if_ejected(service_name, instance, now)

    def _eject(self, service_name: str, instance: str) -> tuple[int, float, str]:
        if self.down_since is None:
            try:
                shared = self.store.eject(service_name, instance, self.ejection_time, self.max_ejection_time)
                return (shared.times, self.clock() + shared.left, shared.instance)
            except StoreUnavailable as error:
                self._went_down(error)
        self._pending.append(('eject', service_name, instance))
        return super()._eject(service_name, instance)

    def _forgiven(self, service_name: str) -> None:
        self._write(('forgive', service_name))

    def _write(self, operation: tuple) -> None:
        """A removal, an ejection or a pardon: written now, or once the store is back."""
        if self.down_since is None:
            try:
                self._run(operation)
                return
            except StoreUnavailable as error:
                self._went_down(error)
        self._pending.append(operation)

    def _run(self, operation: tuple) -> None:
        kind, name = operation[0], operation[1]
        if kind == 'delete':
            self.store.delete(name)
        elif kind == 'forgive':
            self.store.forgive(name)
        else:
            self.store.eject(name, operation[2], self.ejection_time, self.max_ejection_time)

    # -- the periodic work -----------------------------------------------------------------------
    def expire(self) -> list[Registration]:
        """Write the renewals, sweep (if this replica is the sweeper) and follow the change log now:
        the entries removed from the cache (close their clients)."""
        return self._tick(flush=True, sweep=True)

    def sync(self) -> list[Registration]:
        """:meth:`expire`, with the renewals written every ``flush_period`` and the sweep every
        ``sweep_period`` (the server calls it a few times a second). While the store is out of
        reach, nothing expires: the cache keeps serving, and the store is tried every ``retry_after``."""
        now = self.clock()
        flush, sweep = now >= self._next_flush, now >= self._next_sweep
        return self._tick(flush, sweep)

    def _tick(self, flush: bool, sweep: bool) -> list[Registration]:
        now = self.clock()
        if self.down_since is not None and now < self._next_try:
            return []
        try:
            if self.down_since is not None:
                self._catch_up()
            if flush:
                self._next_flush = now + self.flush_period
                self.flush()
            if now >= self._next_heartbeat:
                self._next_heartbeat = now + self.heartbeat_period
                self.store.heartbeat()
            if sweep:
                self._next_sweep = now + self.sweep_period
                self.store.sweep(self.max_ejection_time)
                with self._lock:  # bounded: forget the ejections seen here long ago
                    for name, (_, until, _) in list(self._ejections.items()):
                        if until + self.max_ejection_time < now:
                            del self._ejections[name]
            return self.follow()
        except StoreUnavailable as error:
            self._went_down(error)
            return []

    def _catch_up(self) -> None:
        """The store answers again: the writes it missed, then every lease renewed here."""
        while self._pending:
            self._run(self._pending[0])
            self._pending.pop(0)
        with self._lock:
            for name in self._claimed:
                if name in self._entries:
                    self._renewals.setdefault(name, self._entries[name].expires_at - self.lease)
        self.flush()
        logger.info(
            'registry database reachable again after %.1f s: caught up',
            self.clock() - (self.down_since or 0.0),
        )
        self.down_since, self.down_reason = None, ''
        self.recoveries += 1

    def flush(self) -> None:
        """Write the renewals made since the last batch; an entry the store lost meanwhile (swept
        while this replica could not renew it) is written again whole."""
        with self._lock:
            renewals, self._renewals = self._renewals, {}
        if not renewals:
            return
        now = self.clock()
        try:
            missing = self.store.renew(sorted((name, now - at) for name, at in renewals.items()), self.lease)
            with self._lock:
                lost = [self._entries[n] for n in missing if n in self._entries and n in self._claimed]
            for entry in lost:
                self.store.write(_stored(entry, self.store.replica), self.lease)
        except StoreUnavailable:
            with self._lock:
                for name, at in renewals.items():
                    self._renewals.setdefault(name, at)
            raise

    def take_retired(self) -> list[Client]:
        """The clients replaced since the last call (:attr:`retired`), for the caller to close."""
        with self._lock:
            retired, self.retired = self.retired, []
        return retired

    def follow(self) -> list[Registration]:
        """Apply the change log since the cache's position; the entries removed.

        The rows are read outside the lock, so a registration, move or removal through this
        replica may overtake the read: then the changes from the first of the names it wrote on
        are left for the next call, which reads them again, newer than the cache's write.
        """
        with self._lock:
            mark = self._writes
        changes = self.store.changes(self._position)
        if changes is None:  # the log was pruned past our position: start over from a snapshot
            position, entries = self.store.snapshot()
            with self._lock:
                return self._apply_snapshot(position, entries, mark)
        removed = []
        with self._lock:
            for change in changes:
                if self._written.get(change.service_name, 0) > mark:
                    break  # a write of ours overtook the read: the rest is read again next time
                gone = self._apply(change.service_name, change.entry)
                if gone is not None:
                    removed.append(gone)
                self._position = change.seq
            else:
                self._forget_writes(mark)
        return removed

    def _forget_writes(self, mark: int) -> None:
        """Called with the lock held: the writes a read begun after them has seen are no longer news."""
        self._written = {name: number for name, number in self._written.items() if number > mark}

    def _apply_snapshot(
        self, position: int, entries: list[StoredEntry], mark: int | None = None
    ) -> list[Registration]:
        """Called with the lock held: the cache made equal to ``entries`` (but for the names written
        since the write ``mark``, when the snapshot was read after it)."""
        mark = self._writes if mark is None else mark
        removed = []
        names = {entry.service_name for entry in entries}
        for name in [name for name in self._entries if name not in names]:
            if self._written.get(name, 0) <= mark:
                gone = self._apply(name, None)
                if gone is not None:
                    removed.append(gone)
        for entry in entries:
            if self._written.get(entry.service_name, 0) <= mark:
                self._apply(entry.service_name, entry)
        self._position = position
        self._forget_writes(mark)
        return removed

    def _apply(self, name: str, stored: StoredEntry | None) -> Registration | None:
        """Called with the lock held: one entry as the store has it now; the removed entry, if any."""
        old = self._entries.get(name)
        if stored is None:
            if old is None:
                return None
            self._applying = True
            try:
                return self._remove(name)
            finally:
                self._applying = False
        mine = stored.replica == self.store.replica
        if not mine:
            self._claimed.discard(name)  # its vision system renews through another replica now
            self._renewals.pop(name, None)
        names = frozenset(stored.algorithms) if stored.algorithms else algorithm_names(())
        expires_at = self.clock() + stored.lease_left
        if (
            old is not None
            and old.field_of_view == stored.field_of_view
            and old.algorithms == names
            and old.instance == stored.instance
            and old.watch_service == stored.watch_service
            and old.site == stored.site
        ):
            if not mine:  # the same entry: only its provider or lease may differ
                self._set(old, old.polygon, expires_at, stored, old.client)
            return None
        polygon = old.polygon if old is not None and old.field_of_view == stored.field_of_view else None
        if polygon is None:
            polygon = field_of_view_polygon(stored.field_of_view)
        if old is not None and old.instance != stored.instance:
            self.restarted.append(name)
        client = old.client if old is not None else None
        route = direct_uri(self.site, stored.site, stored.instance)
        if client is not None and old is not None and route != direct_uri(self.site, old.site, old.instance):
            self.retired.append(client)  # an entry of another site at a new address: a new connection
            client = None
        if client is None and self.make_client is not None:
            client = self.make_client(name, route)
        entry = self._set(old, polygon, expires_at, stored, client)
        if old is None or old.field_of_view != entry.field_of_view:
            self._index.insert(name, polygon, entry.field_of_view, value=entry)
        self.version += 1
        self._failures[name] = 0
        return None

    def _set(self, old, polygon, expires_at: float, stored: StoredEntry, client) -> Registration:
        entry = Registration(
            stored.service_name,
            stored.field_of_view,
            polygon,
            expires_at,
            provider=stored.provider,
            instance=stored.instance,
            algorithms=frozenset(stored.algorithms) if stored.algorithms else algorithm_names(()),
            client=client,
            watch_service=stored.watch_service,
            site=stored.site,
        )
        self._entries[entry.service_name] = entry
        if old is not None:
            self._index.set_value(entry.service_name, entry)
        return entry


def _stored(entry: Registration, replica: str) -> StoredEntry:
    return StoredEntry(
        entry.service_name,
        entry.field_of_view,
        tuple(sorted(entry.algorithms)),
        entry.provider,
        entry.instance,
        entry.watch_service,
        0.0,
        replica,
        entry.site,
    )


def stored_watch(watch: Watch, now: float) -> StoredWatch:
    """``watch`` as the store keeps it, its time left counted at ``now`` (the watch table's clock)."""
    return StoredWatch(
        watch.caller,
        watch.request_id,
        watch.algorithm,
        watch.algorithm_name,
        watch.region,
        watch.callback_service,
        watch.period,
        watch.duration,
        watch.changes_only,
        watch.expires_at - now,
        watch.forward_as,
    )


def adopted_watch(stored: StoredWatch, now: float) -> Watch:
    """A watch taken over from the store, expiring ``stored.left`` after ``now`` (the table's clock)."""
    return Watch(
        stored.caller,
        stored.request_id,
        stored.algorithm,
        stored.algorithm_name,
        stored.region,
        stored.callback_service,
        stored.period,
        stored.duration,
        stored.changes_only,
        now + stored.left,
        stored.forward_as,
    )
