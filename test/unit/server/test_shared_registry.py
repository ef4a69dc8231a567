"""The registry shared through PostgreSQL: replicas, shared ejections, the change log, the sweeper,
an outage, the schema check, watches (one private cluster for the module; docs/registry.md)."""

import random

import psycopg
import pytest

from drvs.common.status import UNAVAILABLE, Refusal
from drvs.server.pg_store import SCHEMA_VERSION, PgStore
from drvs.server.shared_registry import SharedRegistry, StoredWatch, StoreError, StoreUnavailable
from drvs.testing import ManualClock, wait_for
from drvs.testing.postgres import shared_registry


def square(x, y, size=1.0):
    return [(x, y), (x + size, y), (x + size, y + size), (x, y + size)]


@pytest.fixture
def clock():
    return ManualClock(1000.0)


@pytest.fixture
def stores(dsn):
    """Two stores (two replicas' connections) on the module's database; closed after the test."""
    opened = []
    for _ in range(2):
        store = PgStore(dsn)
        store.open()
        opened.append(store)
    yield opened
    for store in opened:
        store.close()


@pytest.fixture
def replicas(stores, clock):
    """Two replicas on one (emptied) database, sharing ``clock``."""
    first = shared_registry(stores[0], clock, lease=10.0, max_failures=1)
    stores[1].clock = clock
    second = SharedRegistry(stores[1], lease=10.0, max_failures=1, clock=clock)
    second.load()
    return first, second


class Client:
    def __init__(self, name, uri=None):
        self.name, self.uri, self.closed = name, uri, False

    def close(self):
        self.closed = True


class Flaky:
    """A store that is out of reach while ``down``; otherwise ``inner``."""

    def __init__(self, inner):
        self.inner, self.down = inner, False
        self.replica = inner.replica

    def __getattr__(self, name):
        method = getattr(self.inner, name)

        def call(*args, **kwargs):
            if self.down:
                raise StoreUnavailable('connection refused')
            return method(*args, **kwargs)

        return call


def test_a_vision_system_registered_through_one_replica_is_matched_by_the_other(replicas):
    first, second = replicas
    second.make_client = Client
    assert first.register('/a', square(0, 0), provider='/vs', algorithms=['sift']) == 'registered'
    assert second.match((0.2, 0.2, 0.4, 0.4)) == []  # not followed yet
    version = second.version
    assert second.sync() == []
    assert second.match((0.2, 0.2, 0.4, 0.4), 'sift') == ['/a'] and second.version > version
    entry = second.get('/a')
    assert (entry.provider, entry.algorithms, entry.client.name) == ('/vs', frozenset({'sift'}), '/a')
    first.register('/a', square(5, 5), provider='/vs', algorithms=['sift'])
    second.sync()
    assert second.match((0.2, 0.2, 0.4, 0.4)) == [] and second.match((5.2, 5.2, 5.4, 5.4)) == ['/a']
    first.unregister('/a')
    removed = second.sync()
    assert [e.service_name for e in removed] == ['/a'] and '/a' not in second
    assert second.match((5.2, 5.2, 5.4, 5.4)) == []


def test_an_ejection_through_one_replica_holds_at_the_other(replicas):
    first, second = replicas
    first.register('/a', square(0, 0), instance='rosrpc://h:1')
    second.sync()
    assert first.record_failure('/a').service_name == '/a'  # max_failures 1
    second.sync()
    assert '/a' not in second
    with pytest.raises(Refusal) as caught:
        second.register('/a', square(0, 0), instance='rosrpc://h:1')
    assert (caught.value.status, caught.value.retry_after) == (UNAVAILABLE, 10.0)
    assert 'ejected for 10.0 s more (ejection 1)' in str(caught.value)
    assert second.register('/a', square(0, 0), instance='rosrpc://h:2') == 'registered'  # a new process


def test_the_cache_and_postgis_agree_on_every_match(replicas, stores):
    """The cache answers every match; PostGIS under its GiST index gives the same answers, touching
    edges and corners included (they do not count)."""
    first, _ = replicas
    rng = random.Random(7)
    for n in range(60):
        x, y = rng.randrange(0, 20), rng.randrange(0, 20)
        if n % 3 == 0:
            first.register(f'/c{n}', [(x, y), (x + 2, y), (x + 1, y + 1.5)])
        else:
            first.register(f'/c{n}', square(x, y, rng.choice([1.0, 2.0])))
    sizes = [(0, 0), (0, 1), (1, 0), (1, 1), (2, 3), (0.5, 0.5)]  # points, segments, boxes
    regions = [
        (x, y, x + w, y + h)
        for x, y, (w, h) in (
            (rng.randrange(0, 21), rng.randrange(0, 21), rng.choice(sizes)) for _ in range(150)
        )
    ]
    for region in regions:
        assert first.match(region) == stores[0].match(region), region


def test_renewals_are_batched_and_a_renewal_through_another_replica_claims_the_lease(replicas, clock):
    first, second = replicas
    first.register('/a', square(0, 0))
    second.sync()
    clock.now += 6
    assert second.register('/a', square(0, 0)) == 'renewed'  # its vision system moved to the second
    first.sync()  # the claim: the first no longer expires it by its own clock
    clock.now += 6  # the first's own lease has run out; the second's has not
    assert first.match((0.2, 0.2, 0.4, 0.4)) == ['/a']
    for _ in range(3):
        clock.now += 4
        assert second.register('/a', square(0, 0)) == 'renewed'
        assert first.sync() == [] and second.sync() == []
    clock.now += 10
    second.expire()  # the sweeper (whichever holds the lock) removes it
    first.expire()
    assert '/a' not in first and '/a' not in second


def test_one_sweeper_at_a_time(stores, clock):
    first, second = stores
    first.clock = second.clock = clock
    # A closed session's backend lets its lock go a moment after the close: wait for it.
    wait_for(lambda: first.sweep(300.0), 5.0, "the first store's sweep (the last test's sessions ending)")
    assert second.sweep(300.0) is False
    first.close()  # its session ends: the lock is free
    wait_for(lambda: second.sweep(300.0), 5.0, "the second store's sweep once the first's session ended")


def test_an_outage_serves_from_the_cache_refuses_registrations_and_catches_up(stores, clock):
    flaky = Flaky(stores[0])
    stores[0].clock = clock
    stores[0].clear()
    registry = SharedRegistry(flaky, lease=10.0, max_failures=1, clock=clock, retry_after=2.0)
    registry.load()
    registry.register('/a', square(0, 0))
    registry.register('/b', square(3, 0))
    flaky.down = True
    clock.now += 4
    assert registry.register('/a', square(0, 0)) == 'renewed'  # kept, written once it is back
    registry.sync()
    assert registry.problem().startswith('registry database unreachable for 0 s (connection refused)')
    with pytest.raises(Refusal) as caught:
        registry.register('/c', square(6, 0))
    assert (caught.value.status, caught.value.retry_after) == (UNAVAILABLE, 2.0)
    assert 'registry database is unreachable' in str(caught.value)
    assert registry.unregister('/b') is not None  # remembered, written when it is back
    for _ in range(6):  # nothing expires while the store is away; renewals keep /a matched
        clock.now += 5
        assert registry.register('/a', square(0, 0)) == 'renewed'
        assert registry.sync() == [] and registry.match((0.2, 0.2, 0.4, 0.4)) == ['/a']
    flaky.down = False
    assert registry.sync() == [] and registry.problem() is not None  # tried again after retry_after
    clock.now += 2.0
    assert registry.sync() == []
    assert registry.problem() is None and registry.recoveries == 1
    assert stores[0].match((0.2, 0.2, 0.4, 0.4)) == ['/a']  # renewed on catching up
    assert stores[0].match((3.2, 0.2, 3.4, 0.4)) == []  # the unregistration was written
    assert registry.register('/c', square(6, 0)) == 'registered'


def test_a_lease_swept_while_its_replica_was_cut_off_is_written_again(replicas, clock):
    first, second = replicas
    first.register('/a', square(0, 0))
    clock.now += 9
    first.register('/a', square(0, 0))  # renewed, not written yet
    clock.now += 1.5
    second.expire()  # swept before the first's batch came
    assert second.store.match((0.2, 0.2, 0.4, 0.4)) == []
    first.flush()
    first.follow()
    assert second.store.match((0.2, 0.2, 0.4, 0.4)) == ['/a'] and first.match((0, 0, 1, 1)) == ['/a']


def test_watches_of_a_replica_gone_silent_are_taken_over(stores, clock):
    first, second = stores
    first.clock = second.clock = clock
    first.clear()
    watch = StoredWatch(
        '/robot',
        'w\x00 ☃',
        'colour:1,2,3,4,5,6',
        'colour',
        (0.0, 0.0, 1.0, 1.0),
        '/robot/cb',
        0.5,
        30.0,
        False,
        30.0,
        ('/drvs/fused', 'f7'),
    )
    first.heartbeat()
    first.save_watch(watch)
    second.heartbeat()
    assert second.orphaned_watches(stale_after=5.0) == []  # its owner is alive
    clock.now += 10
    second.heartbeat()
    [taken] = second.orphaned_watches(stale_after=5.0)
    assert (taken.caller, taken.request_id, taken.region, taken.left, taken.forward_as) == (
        '/robot',
        'w\x00 ☃',
        (0.0, 0.0, 1.0, 1.0),
        20.0,
        ('/drvs/fused', 'f7'),
    )
    assert second.orphaned_watches(stale_after=5.0) == []  # taken once
    second.drop_watch('/robot', 'w\x00 ☃')
    clock.now += 10
    assert first.orphaned_watches(stale_after=5.0) == []


def test_an_unknown_schema_version_is_refused(dsn, stores):
    with psycopg.connect(dsn, autocommit=True) as connection:
        connection.execute('UPDATE drvs_schema SET version = 99')
        try:
            with pytest.raises(StoreError) as caught:
                PgStore(dsn).open()
        finally:
            connection.execute('UPDATE drvs_schema SET version = %s', (SCHEMA_VERSION,))
    message = str(caught.value)
    assert f'holds DRVS schema version 99; this drvs_server knows versions up to {SCHEMA_VERSION}' in message
    assert '\n' not in message


@pytest.mark.parametrize(
    'change, expected',
    [
        (lambda dsn: dsn.replace('drvs:', 'drvs:x', 1), 'password authentication failed for user "drvs"'),
        (lambda dsn: 'postgresql://drvs@127.0.0.1:1/drvs', 'cannot use the registry database'),
        (lambda dsn: 'postgresql://h/d?foo=bar', 'not a valid PostgreSQL DSN'),
    ],
)
def test_a_bad_dsn_or_password_is_one_clear_line(dsn, change, expected):
    with pytest.raises(StoreError) as caught:
        PgStore(change(dsn)).open()
    message = str(caught.value)
    assert expected in message and '\n' not in message
    assert dsn.split(':')[2].split('@')[0] not in message  # never the password


def test_a_replica_behind_a_pruned_change_log_reads_a_snapshot(replicas, dsn):
    first, second = replicas
    first.register('/a', square(0, 0))
    first.register('/b', square(2, 0))
    second.sync()
    first.register('/c', square(4, 0))
    first.unregister('/a')
    with psycopg.connect(dsn, autocommit=True) as connection:  # the sweeper pruned what second has not read
        connection.execute('DELETE FROM drvs_changes WHERE seq < (SELECT max(seq) FROM drvs_changes)')
    removed = second.sync()
    assert [entry.service_name for entry in removed] == ['/a']
    assert sorted(entry.service_name for entry in second.entries()) == ['/b', '/c']
    assert second.match((4.2, 0.2, 4.4, 0.4)) == ['/c']


def test_a_server_started_on_the_database_has_every_registration(replicas, dsn, clock):
    first, _ = replicas
    first.register('/a', square(0, 0), provider='/vs', instance='rosrpc://h:1', algorithms=['sift'])
    store = PgStore(dsn, clock=clock)
    store.open()
    try:
        restarted = SharedRegistry(store, clock=clock, make_client=Client)
        restarted.load()
        entry = restarted.get('/a')
        assert (entry.provider, entry.instance, entry.algorithms, entry.client.name) == (
            '/vs',
            'rosrpc://h:1',
            frozenset({'sift'}),
            '/a',
        )
        assert restarted.match((0.2, 0.2, 0.4, 0.4), 'sift') == ['/a']
    finally:
        store.close()


class Overtaken:
    """A store whose change log read is overtaken by ``write()``, run after the rows were read."""

    def __init__(self, inner, write):
        self.inner, self.write_between = inner, write
        self.replica = inner.replica

    def __getattr__(self, name):
        return getattr(self.inner, name)

    def changes(self, after):
        changes = self.inner.changes(after)
        self.write_between()
        return changes


def test_a_move_that_overtakes_a_change_log_read_is_not_undone_by_it(replicas):
    first, _ = replicas
    first.register('/a', square(0, 0), provider='/vs')
    first.register('/a', square(5, 5), provider='/vs')  # both moves in the log, not followed yet
    first.store = Overtaken(first.store, lambda: first.register('/a', square(9, 9), provider='/vs'))
    first.follow()  # read: the row at (5, 5); the move to (9, 9) came in meanwhile
    assert first.match((9.2, 9.2, 9.4, 9.4)) == ['/a'] and first.match((5.2, 5.2, 5.4, 5.4)) == []
    first.store = first.store.inner
    first.follow()  # the log read again, from where the overtaken read stopped
    assert first.match((9.2, 9.2, 9.4, 9.4)) == ['/a'] and first.match((0.2, 0.2, 0.4, 0.4)) == []
