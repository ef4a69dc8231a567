"""The server's watches in a shared registry's store: written through, saved again after an
outage, taken over from silent replicas (drvs.server.watch_sharing; no database: a fake store)."""

import dataclasses
import threading
from types import SimpleNamespace

from drvs.server.params import ServerSettings
from drvs.server.registry import Registry
from drvs.server.shared_registry import StoredWatch, StoreUnavailable
from drvs.server.watch_sharing import TAKEOVER_PERIOD, WatchSharing, open_registry
from drvs.server.watch_table import Watch, WatchTable
from drvs.testing import ManualClock


class FakeStore:
    def __init__(self):
        self.saved, self.dropped, self.orphans, self.down = {}, [], [], False

    def _check(self):
        if self.down:
            raise StoreUnavailable('down')

    def save_watch(self, stored):
        self._check()
        self.saved[(stored.caller, stored.request_id)] = stored

    def drop_watch(self, caller, request_id):
        self._check()
        self.dropped.append((caller, request_id))

    def orphaned_watches(self, after):
        self._check()
        return list(self.orphans)


def watch(request_id, expires_at=20.0, forward_as=None):
    return Watch(
        '/robot',
        request_id,
        'colour',
        'colour',
        (0, 0, 1, 1),
        '/robot/cb',
        0.5,
        20.0,
        True,
        expires_at,
        forward_as,
    )


def sharing(clock):
    registry = SimpleNamespace(store=FakeStore(), down_since=None, recoveries=0, restarted=[])
    table = WatchTable(Registry(), clock)
    return WatchSharing(registry, table, threading.Lock(), 5.0, clock), registry, table


def test_a_plain_watch_is_saved_with_its_time_left_a_fused_one_is_not():
    clock = ManualClock(5.0)
    shared, registry, _ = sharing(clock)
    shared.save(watch('a'))
    shared.save(watch('f', forward_as=('/drvs/fusion_callback', 'w1')))
    assert list(registry.store.saved) == [('/robot', 'a')]
    assert registry.store.saved[('/robot', 'a')].left == 15.0


def test_an_outage_saves_nothing_then_every_standing_watch_once_the_database_is_back():
    clock = ManualClock(0.0)
    shared, registry, table = sharing(clock)
    table.adopt(watch('a'))
    registry.down_since = 1.0
    shared.save(watch('a'))
    shared.drop('/robot', 'b')
    assert (registry.store.saved, registry.store.dropped) == ({}, [])
    registry.down_since, registry.recoveries = None, 1  # back
    shared.follow()
    assert list(registry.store.saved) == [('/robot', 'a')]


def test_the_watches_of_a_silent_replica_are_taken_over_once_a_takeover_period():
    clock = ManualClock(0.0)
    shared, registry, table = sharing(clock)
    orphan = StoredWatch('/other', 'x', 'colour', 'colour', (0, 0, 1, 1), '/other/cb', 0.5, 20.0, True, 10.0)
    registry.store.orphans = [orphan]
    assert shared.follow() is True
    assert table.get(('/other', 'x')).expires_at == 10.0
    registry.store.orphans = [dataclasses.replace(orphan, caller='/third', callback_service='/third/cb')]
    assert shared.follow() is False  # not again before TAKEOVER_PERIOD
    clock.now += TAKEOVER_PERIOD
    assert shared.follow() is True and table.get(('/third', 'x')) is not None


def test_a_store_that_does_not_answer_is_no_error():
    clock = ManualClock(0.0)
    shared, registry, _ = sharing(clock)
    registry.store.down = True
    shared.save(watch('a'))
    shared.drop('/robot', 'a')
    assert shared.follow() is False


def test_memory_is_the_default_registry():
    assert type(open_registry(ServerSettings(), 'r')) is Registry
