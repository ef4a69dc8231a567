"""The server's side of a registry shared through a database: opening it, and its watches kept there.

:func:`open_registry` makes the in-memory registry or a :class:`~drvs.server.shared_registry.SharedRegistry`
from ``~registry``. :class:`WatchSharing` decides when a watch is written to the store, dropped from
it, saved again after an outage, and which watches of silent replicas this one takes over; the
server's node only calls it under its watch lock. No ROS here; the rules: docs/registry.md.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from typing import Any

from drvs.server.params import ServerSettings
from drvs.server.registry import Registry
from drvs.server.shared_registry import (
    SharedRegistry,
    StoreError,
    StoreUnavailable,
    adopted_watch,
    stored_watch,
)
from drvs.server.watch_table import Watch, WatchTable

logger = logging.getLogger('rosout.' + __name__)

__all__ = ['TAKEOVER_PERIOD', 'WatchSharing', 'open_registry']

TAKEOVER_PERIOD = 1.0
"""Seconds between two looks for the watches of replicas gone silent."""


def open_registry(settings: ServerSettings, replica: str) -> Registry:
    """The in-memory registry, or one shared through the database ``settings.registry`` names
    (``replica``: this server's name in it).

    :raises StoreError: the database cannot be used (one line; the node exits 2).
    """
    limits: dict[str, Any] = dict(
        lease=settings.lease,
        max_failures=settings.max_failures,
        ejection_time=settings.ejection_time,
        max_ejection_time=settings.max_ejection_time,
    )
    if settings.registry == 'memory':
        return Registry(site=settings.site, **limits)
    try:
        from drvs.server.pg_store import PgStore  # psycopg only when a database is asked for
    except ImportError as error:
        raise StoreError(
            f'~registry: a PostgreSQL registry needs psycopg 3 ({error}): run scripts/setup.sh --postgres'
        ) from None
    store = PgStore(settings.registry, replica=replica, site=settings.site)
    store.open()
    registry = SharedRegistry(
        store, retry_after=settings.unavailable_retry_after, site=settings.site, **limits
    )
    try:
        registry.load()
    except StoreUnavailable as error:
        store.close()
        raise StoreError(f'~registry: the registry database {store.where} did not answer: {error}') from None
    logger.info(
        'registry: %d vision systems from %s (replica %s, site %s)',
        len(registry),
        store.where,
        replica,
        settings.site or '(unnamed)',
    )
    return registry


class WatchSharing:
    """A shared registry's watches: written through to its store, taken over from silent replicas.

    :param registry: the shared registry (its store keeps the watches).
    :param watches: the server's watch table, guarded by ``lock``.
    :param takeover_after: seconds a replica may stay silent before its watches are taken over.
    :param clock: the watch table's clock (ROS time in the node).
    """

    def __init__(
        self,
        registry: SharedRegistry,
        watches: WatchTable,
        lock: threading.Lock,
        takeover_after: float,
        clock: Callable[[], float],
    ):
        self.registry, self.watches, self.lock = registry, watches, lock
        self.takeover_after, self.clock = takeover_after, clock
        self._saved_after = 0  # the registry's recoveries when the watches were last saved
        self._next_takeover = 0.0

    def save(self, watch: Watch) -> None:
        """Keep ``watch`` in the store (a replica that takes over finds it). Fused watches are not
        kept: their callbacks go through this replica's fusion stage."""
        if watch.forward_as is not None or self.registry.down_since is not None:
            return  # a plain watch is saved again once the database is back (:meth:`follow`)
        try:
            self.registry.store.save_watch(stored_watch(watch, self.clock()))
        except StoreUnavailable:
            pass  # saved again at its next renewal, or once the database is back

    def drop(self, caller: str, request_id: str) -> None:
        if self.registry.down_since is not None:
            return
        try:
            self.registry.store.drop_watch(caller, request_id)
        except StoreUnavailable:
            pass  # it expires in the database by itself

    def follow(self) -> bool:
        """One look (from the registry's sync loop): forget the watches of vision systems restarted
        through another replica, save every watch again after an outage, take over those of
        replicas gone silent. True when it took some over (the watch loop has work)."""
        registry = self.registry
        restarted, registry.restarted = registry.restarted, []
        with self.lock:
            for service in restarted:
                self.watches.forget(service)
        if registry.down_since is not None:
            return False
        if registry.recoveries != self._saved_after:
            self._saved_after = registry.recoveries
            with self.lock:
                standing = self.watches.standing()
            for watch in standing:
                self.save(watch)
        now = self.clock()
        if now < self._next_takeover:
            return False
        self._next_takeover = now + TAKEOVER_PERIOD
        try:
            orphans = registry.store.orphaned_watches(self.takeover_after)
        except StoreUnavailable:
            return False
        with self.lock:
            adopted = sum(self.watches.adopt(adopted_watch(stored, self.clock())) for stored in orphans)
        if orphans:
            logger.info(
                'took over %d watches of replicas not heard from in %g s', adopted, self.takeover_after
            )
        return bool(orphans)
